//! Path-traced ground truth for relighting: rooms lit only by an
//! environment map, a diffuse object pasted where it belongs, and the
//! scores of a relit composite against the truth.
//!
//! A [`RelightCase`] holds what [`crate::sim::pathtrace`] renders for one
//! scene, all from one camera:
//!
//! - the **photo**: the room without the object (the target of the paste),
//!   with its exact depth and normals;
//! - the **object alone** under the same map, where it is captured: the
//!   object and nothing else (no floor: below the horizon it sees the
//!   map's dim ground), its colour and depth (the `Paste` output of an
//!   identity placement);
//! - the **alpha** of the exact depth test (the object where it is nearer
//!   than the room);
//! - the **truth**: the room with the object, path-traced with the same
//!   seed as the photo (correlated samples: far from the object the two
//!   differ only by noise that meets the object).
//!
//! [`score`] measures a composite in two regions, as display PSNR (sRGB,
//! [`crate::kit::color::display_mse`]): the **influence** region (outside the object, where
//! truth and photo differ by more than [`INFLUENCE_THRESHOLD`] in some
//! display channel: the shadow and the bounce) and the **object** (alpha
//! 1), beside the naive paste (the object's pixels over the photo).

use depthgraph_graph::prelude::*;
use depthgraph_graph::value::Rgb;
use glam::DVec3;

use crate::kit::color::{display_mse_masked, linear_to_srgb, psnr_of_mse};
use crate::relight::envmap::{EnvMapParams, environment_map, pixel_direction};
use crate::sim::pathtrace::{EnvLight, PathTraceParams, path_trace};
use crate::sim::synthetic::{
    Object, Primitive, RenderOptions, Scene, Texture, kinect_like_intrinsics, plane, render, solid,
};

/// A pixel belongs to the influence region when truth and photo differ by
/// more than this in some sRGB display channel (2/255).
pub const INFLUENCE_THRESHOLD: f64 = 2.0 / 255.0;

/// The rooms of the relighting truth.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Room {
    /// A sphere on a grey floor in the open; the sun in front of the
    /// camera (its shadow falls towards the camera: the object's unseen
    /// back casts part of it).
    Open,
    /// A cylinder partly behind a box (the alpha of the depth test cuts it).
    Occluded,
    /// A box beside a sunlit side wall (strong bounce onto the object).
    NearWall,
    /// A sphere on a red floor (the floor's bounce colours the object).
    ColouredFloor,
    /// A sphere pasted before [`furnished_objects`] (a sphere, a box and a
    /// cylinder on a grey floor): a photo whose shading and cast shadows
    /// show its light (the lighting estimate's case; not in [`Room::ALL`],
    /// the rooms of the relighting table).
    Furnished,
}

impl Room {
    /// Every room.
    pub const ALL: [Room; 4] = [
        Room::Open,
        Room::Occluded,
        Room::NearWall,
        Room::ColouredFloor,
    ];

    /// Its name in tables.
    pub fn name(self) -> &'static str {
        match self {
            Room::Open => "open",
            Room::Occluded => "occluded",
            Room::NearWall => "near wall",
            Room::ColouredFloor => "coloured floor",
            Room::Furnished => "furnished",
        }
    }
}

/// The light of a case.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Sky {
    /// The generated sky of `EnvironmentMap` with its sun at
    /// `(elevation, azimuth)` degrees.
    Sun {
        /// Elevation above the horizon, degrees.
        elevation_deg: f64,
        /// Azimuth (0 = behind the camera, positive = to its right), degrees.
        azimuth_deg: f64,
    },
    /// A CIE overcast sky, `L(θ) = L_z (1 + 2 cos θ) / 3` above the
    /// horizon, a dim ground below.
    Overcast,
}

impl Sky {
    /// The equirectangular map (`width x width/2`).
    pub fn map(self, width: usize) -> Result<ColorImage, NodeError> {
        let (w, h) = (width.max(4), (width / 2).max(2));
        match self {
            Sky::Sun {
                elevation_deg,
                azimuth_deg,
            } => environment_map(&EnvMapParams {
                width: w,
                height: h,
                sun_elevation_deg: elevation_deg,
                sun_azimuth_deg: azimuth_deg,
                ..Default::default()
            }),
            Sky::Overcast => Ok(ColorImage::from_fn(w, h, |x, y| {
                let d = pixel_direction(x as f64 + 0.5, y as f64 + 0.5, w, h);
                let up = -d.y;
                if up > 0.0 {
                    let l = 0.9 * (1.0 + 2.0 * up) / 3.0;
                    [l as f32, (l * 1.02) as f32, (l * 1.08) as f32]
                } else {
                    [0.04, 0.035, 0.03]
                }
            })),
        }
    }
}

/// One case of the relighting truth (module docs).
#[derive(Debug, Clone)]
pub struct RelightCase {
    /// Room and sky, for tables.
    pub name: String,
    /// The camera.
    pub k: Intrinsics,
    /// The environment map lighting every render.
    pub env: ColorImage,
    /// The room without the object, path-traced.
    pub photo: ColorImage,
    /// Its exact depth (metres).
    pub depth: DepthMap,
    /// Its exact normals.
    pub normals: NormalMap,
    /// The object alone under the map, path-traced (0 off the object).
    pub object_color: ColorImage,
    /// The object's depth (0 off the object).
    pub object_depth: DepthMap,
    /// 1 where the object is nearer than the room.
    pub alpha: Mask,
    /// The room with the object, path-traced with the photo's seed.
    pub truth: ColorImage,
    /// The analytic object (its id is [`OBJECT_ID`]).
    pub object: Object,
}

impl RelightCase {
    /// `count` directional VPLs of the case's map (seed 1).
    pub fn vpls(&self, count: usize) -> Vec<crate::relight::vpl::Vpl> {
        let p = crate::relight::vpl::VplParams {
            count,
            seed: 1,
            ..Default::default()
        };
        crate::relight::vpl::sample_vpls(&self.env, &p)
    }

    /// The case as `Relight` inputs: the photo and its depth alone
    /// (normals and albedo estimated), the object alone as the paste, the
    /// target's map on both sides.
    pub fn inputs(&self) -> crate::relight::shading::RelightInputs<'_> {
        crate::relight::shading::RelightInputs {
            photo: &self.photo,
            depth: &self.depth,
            normals: None,
            albedo: None,
            pasted_color: &self.object_color,
            pasted_depth: &self.object_depth,
            alpha: &self.alpha,
            k: &self.k,
            capture_vpls: None,
        }
    }
}

/// Id of the pasted object in the case's scenes.
pub const OBJECT_ID: u32 = 100;

/// Floor height below the camera (metres, `+y` is down).
pub const FLOOR_Y: f64 = 0.5;

/// The objects of the furnished room (ids 1-5): a grey floor, the back
/// wall, a grey sphere, a box and a cylinder.
pub fn furnished_objects() -> Vec<Object> {
    let grey = |v: f32| Texture::Solid([v, v, v]);
    vec![
        solid(1, plane([0.0, FLOOR_Y, 0.0], [0.0, -1.0, 0.0]), grey(0.5)),
        back_wall(),
        solid(
            3,
            Primitive::Sphere {
                center: DVec3::new(0.3, FLOOR_Y - 0.18, 1.7),
                radius: 0.18,
            },
            grey(0.6),
        ),
        solid(
            4,
            Primitive::Box {
                center: DVec3::new(-0.35, FLOOR_Y - 0.15, 1.9),
                half_extents: DVec3::new(0.15, 0.15, 0.15),
                yaw_rad: 0.6,
            },
            Texture::Solid([0.55, 0.5, 0.45]),
        ),
        solid(
            5,
            Primitive::Cylinder {
                center_base: DVec3::new(-0.05, FLOOR_Y, 2.5),
                radius: 0.1,
                height: 0.6,
            },
            Texture::Solid([0.45, 0.5, 0.55]),
        ),
    ]
}

/// The back wall: it fills the frame at 3.6 m and ends there (infinite
/// planes beside and above it would light the object from where no photo
/// shows them).
fn back_wall() -> Object {
    solid(
        2,
        Primitive::Box {
            center: DVec3::new(0.0, 0.5 * (FLOOR_Y - 1.7), 3.65),
            half_extents: DVec3::new(2.25, 0.5 * (FLOOR_Y + 1.7), 0.05),
            yaw_rad: 0.0,
        },
        Texture::Solid([0.6, 0.58, 0.55]),
    )
}

/// The room's objects, the pasted object and the sky of `room`.
fn layout(room: Room) -> (Vec<Object>, Object, Sky) {
    let grey: Rgb = [0.5, 0.5, 0.5];
    let floor = |albedo: Texture| solid(1, plane([0.0, FLOOR_Y, 0.0], [0.0, -1.0, 0.0]), albedo);
    let back = back_wall();
    let object_texture = Texture::Waves {
        a: [0.75, 0.72, 0.68],
        b: [0.45, 0.55, 0.7],
        period_m: 0.12,
    };
    match room {
        Room::Open => {
            let r = 0.16;
            (
                vec![floor(Texture::Solid(grey))],
                solid(
                    OBJECT_ID,
                    Primitive::Sphere {
                        center: DVec3::new(0.0, FLOOR_Y - r, 1.5),
                        radius: r,
                    },
                    object_texture,
                ),
                Sky::Sun {
                    elevation_deg: 35.0,
                    azimuth_deg: 150.0,
                },
            )
        }
        Room::Occluded => (
            vec![
                floor(Texture::Checker {
                    a: [0.55, 0.5, 0.45],
                    b: [0.35, 0.32, 0.3],
                    period_m: 0.25,
                }),
                back,
                solid(
                    3,
                    Primitive::Box {
                        center: DVec3::new(-0.2, FLOOR_Y - 0.1, 1.15),
                        half_extents: DVec3::new(0.12, 0.1, 0.1),
                        yaw_rad: 0.3,
                    },
                    Texture::Solid([0.3, 0.35, 0.6]),
                ),
            ],
            solid(
                OBJECT_ID,
                Primitive::Cylinder {
                    center_base: DVec3::new(-0.05, FLOOR_Y, 1.6),
                    radius: 0.12,
                    height: 0.4,
                },
                object_texture,
            ),
            Sky::Sun {
                elevation_deg: 50.0,
                azimuth_deg: -40.0,
            },
        ),
        Room::NearWall => (
            vec![
                floor(Texture::Solid(grey)),
                back,
                // a wall 1.5 m high from 1 m to the back wall, all of its
                // lit face in the frame (an infinite plane would light the
                // object mostly from behind the camera, where no photo
                // shows it)
                solid(
                    4,
                    Primitive::Box {
                        center: DVec3::new(-0.55, FLOOR_Y - 0.75, 2.3),
                        half_extents: DVec3::new(0.05, 0.75, 1.3),
                        yaw_rad: 0.0,
                    },
                    Texture::Solid([0.8, 0.75, 0.55]),
                ),
            ],
            solid(
                OBJECT_ID,
                Primitive::Box {
                    center: DVec3::new(-0.28, FLOOR_Y - 0.14, 1.6),
                    half_extents: DVec3::new(0.14, 0.14, 0.14),
                    yaw_rad: 0.5,
                },
                object_texture,
            ),
            Sky::Sun {
                elevation_deg: 40.0,
                azimuth_deg: 70.0,
            },
        ),
        Room::Furnished => {
            let r = 0.14;
            (
                furnished_objects(),
                solid(
                    OBJECT_ID,
                    Primitive::Sphere {
                        center: DVec3::new(-0.05, FLOOR_Y - r, 1.3),
                        radius: r,
                    },
                    object_texture,
                ),
                Sky::Sun {
                    elevation_deg: 45.0,
                    azimuth_deg: -30.0,
                },
            )
        }
        Room::ColouredFloor => {
            let r = 0.16;
            (
                vec![floor(Texture::Solid([0.7, 0.15, 0.1])), back],
                solid(
                    OBJECT_ID,
                    Primitive::Sphere {
                        center: DVec3::new(0.1, FLOOR_Y - r, 1.5),
                        radius: r,
                    },
                    object_texture,
                ),
                Sky::Sun {
                    elevation_deg: 55.0,
                    azimuth_deg: -20.0,
                },
            )
        }
    }
}

/// Renders the case of `room` under its own sky, or under `sky` when given
/// (module docs): the images `w x h`, the map `map_width x map_width/2`.
pub fn relight_case(
    room: Room,
    sky: Option<Sky>,
    w: usize,
    h: usize,
    map_width: usize,
    pt: &PathTraceParams,
) -> Result<RelightCase, NodeError> {
    let (room_objects, object, own_sky) = layout(room);
    let sky = sky.unwrap_or(own_sky);
    let env = sky.map(map_width)?;
    let light = EnvLight::new(&env)?;
    let k = kinect_like_intrinsics(w, h);
    let base = Scene::of(crate::sim::synthetic::ScenePreset::Tabletop, w, h);
    let scene = |objects: Vec<Object>| Scene {
        objects,
        light: base.light,
        camera: k,
    };
    let room_scene = scene(room_objects.clone());
    let alone = scene(vec![object]);
    let mut all = room_objects;
    all.push(object);
    let with = scene(all);

    let room_geo = render(&room_scene, &RenderOptions::default());
    let obj_geo = render(&alone, &RenderOptions::default());
    let photo = path_trace(&room_scene, &light, pt);
    let truth = path_trace(&with, &light, pt);
    let object_color = path_trace(&alone, &light, pt);
    let object_color = Image::from_fn(w, h, |x, y| {
        if DepthMap::is_valid(*obj_geo.depth.get(x, y)) {
            *object_color.get(x, y)
        } else {
            [0.0; 3]
        }
    });
    let alpha = Image::from_fn(w, h, |x, y| {
        let (zo, zr) = (*obj_geo.depth.get(x, y), *room_geo.depth.get(x, y));
        if DepthMap::is_valid(zo) && (!DepthMap::is_valid(zr) || zo < zr) {
            1.0f32
        } else {
            0.0
        }
    });
    let sky_name = match sky {
        Sky::Sun { .. } => "sun + sky",
        Sky::Overcast => "overcast",
    };
    Ok(RelightCase {
        name: format!("{}, {sky_name}", room.name()),
        k,
        env,
        photo,
        depth: room_geo.depth,
        normals: room_geo.normals,
        object_color,
        object_depth: obj_geo.depth,
        alpha,
        truth,
        object,
    })
}

/// Scores of a composite against a case's truth (module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Scores {
    /// Pixels of the influence region.
    pub influence_px: usize,
    /// Pixels of the object (alpha 1).
    pub object_px: usize,
    /// PSNR (dB) of the composite in the influence region.
    pub influence_db: f64,
    /// PSNR of the naive paste there.
    pub naive_influence_db: f64,
    /// PSNR of the composite on the object.
    pub object_db: f64,
    /// PSNR of the naive paste on the object.
    pub naive_object_db: f64,
}

/// The influence region of a case (module docs): alpha 0 and truth and
/// photo apart by more than [`INFLUENCE_THRESHOLD`] in a display channel.
pub fn influence_region(case: &RelightCase) -> Vec<bool> {
    let enc = |v: f32| f64::from(linear_to_srgb(if v.is_finite() { v } else { 0.0 }));
    case.truth
        .as_slice()
        .iter()
        .zip(case.photo.as_slice())
        .zip(case.alpha.as_slice())
        .map(|((t, p), a)| {
            *a <= 0.0 && (0..3).any(|c| (enc(t[c]) - enc(p[c])).abs() > INFLUENCE_THRESHOLD)
        })
        .collect()
}

/// The naive paste: the object's pixels over the photo.
pub fn naive_paste(case: &RelightCase) -> ColorImage {
    let (w, h) = case.photo.dims();
    Image::from_fn(w, h, |x, y| {
        if *case.alpha.get(x, y) > 0.0 {
            *case.object_color.get(x, y)
        } else {
            *case.photo.get(x, y)
        }
    })
}

/// [`Scores`] of `composite` (the case's size).
pub fn score(case: &RelightCase, composite: &ColorImage) -> Scores {
    let infl = influence_region(case);
    let obj: Vec<bool> = case.alpha.as_slice().iter().map(|a| *a >= 1.0).collect();
    let naive = naive_paste(case);
    let db = |img: &ColorImage, m: &[bool]| {
        psnr_of_mse(display_mse_masked(img.as_slice(), case.truth.as_slice(), m))
    };
    Scores {
        influence_px: infl.iter().filter(|b| **b).count(),
        object_px: obj.iter().filter(|b| **b).count(),
        influence_db: db(composite, &infl),
        naive_influence_db: db(&naive, &infl),
        object_db: db(composite, &obj),
        naive_object_db: db(&naive, &obj),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::relight::scene_cached::{RelightScene, relight_moved};
    use crate::relight::shading::RelightParams;

    /// Two seeds agree to >= 40 dB (display PSNR over the whole truth):
    /// the renders have converged; and the truth differs from the photo
    /// around the object (a region to score).
    #[test]
    fn the_truth_converges_and_the_object_changes_the_room() {
        let pt = |seed| PathTraceParams {
            samples: 160,
            bounces: 3,
            seed,
        };
        let a = relight_case(Room::Open, None, 64, 48, 128, &pt(1)).unwrap();
        let b = relight_case(Room::Open, None, 64, 48, 128, &pt(2)).unwrap();
        let db = psnr_of_mse(crate::kit::color::display_mse(
            a.truth.as_slice(),
            b.truth.as_slice(),
        ));
        assert!(db >= 40.0, "two seeds agree to {db:.1} dB");
        let s = score(&a, &naive_paste(&a));
        assert!(s.influence_px > 20 && s.object_px > 20, "{s:?}");
        // the naive paste is exact on the object only up to the room's light
        assert!(s.naive_object_db < 60.0, "{s:?}");
    }

    /// Relights a case with the default parameters (256 VPLs), given
    /// depth only (normals and albedo estimated).
    fn relit(case: &RelightCase, p: &RelightParams) -> ColorImage {
        let vpls = case.vpls(256);
        let inp = case.inputs();
        let scene = RelightScene::new(&inp.scene(), &vpls, p).unwrap();
        relight_moved(&scene, &inp, p).unwrap().unwrap().color
    }

    fn mean_lum(img: &ColorImage, m: &[bool]) -> f64 {
        let v: Vec<f64> = img
            .as_slice()
            .iter()
            .zip(m)
            .filter(|(_, k)| **k)
            .map(|(c, _)| crate::kit::color::luminance(*c))
            .collect();
        v.iter().sum::<f64>() / v.len().max(1) as f64
    }

    /// Beside a sunlit wall the object receives the wall's bounce: the
    /// truth is brighter than the object captured alone, and the relit
    /// object is brighter than the naive paste, less than 20 % brighter
    /// than the truth (the scene's bounce is unshadowed by the object's
    /// own faces), and closer to it (PSNR, by more than 1 dB).
    #[test]
    fn beside_a_sunlit_wall_the_relit_object_is_not_darker_than_the_truth_allows() {
        let pt = PathTraceParams {
            samples: 48,
            bounces: 3,
            seed: 1,
        };
        let case = relight_case(Room::NearWall, None, 96, 72, 128, &pt).unwrap();
        let obj: Vec<bool> = case.alpha.as_slice().iter().map(|a| *a >= 1.0).collect();
        let r = relit(&case, &RelightParams::default());
        let naive = naive_paste(&case);
        let (t, rl, nv) = (
            mean_lum(&case.truth, &obj),
            mean_lum(&r, &obj),
            mean_lum(&naive, &obj),
        );
        assert!(t > 1.2 * nv, "the wall brightens the object: {t} vs {nv}");
        assert!(
            rl > 1.05 * nv && rl <= 1.2 * t,
            "relit {rl}, naive {nv}, truth {t}"
        );
        let s = score(&case, &r);
        assert!(s.object_db > s.naive_object_db + 1.0, "{s:?}");
    }

    /// The near-wall room under an overcast sky, 96x72, 48 paths, 3 bounces.
    fn wall_overcast() -> RelightCase {
        let pt = PathTraceParams {
            samples: 48,
            bounces: 3,
            seed: 1,
        };
        relight_case(Room::NearWall, Some(Sky::Overcast), 96, 72, 128, &pt).unwrap()
    }

    /// The scene's own bounce into the shadow stays: with the fill light
    /// the relit influence region scores better against the path-traced
    /// truth than when the differential takes the photo's light away in
    /// proportion to the direct light it loses, and the shadow's mean is
    /// nearer the truth's.
    #[test]
    fn shadows_keep_the_scenes_bounce() {
        let case = wall_overcast();
        let with = relit(&case, &RelightParams::default());
        let without = relit(
            &case,
            &RelightParams {
                fill_light: false,
                ..Default::default()
            },
        );
        let (a, b) = (score(&case, &with), score(&case, &without));
        assert!(a.influence_db > b.influence_db, "{a:?} vs {b:?}");
        // the shadow: where the object darkens the room
        let lum = crate::kit::color::luminance;
        let shadow: Vec<bool> = influence_region(&case)
            .iter()
            .zip(case.truth.as_slice().iter().zip(case.photo.as_slice()))
            .map(|(i, (t, p))| *i && lum(*t) < lum(*p))
            .collect();
        let (t, w) = (mean_lum(&case.truth, &shadow), mean_lum(&with, &shadow));
        let wo = mean_lum(&without, &shadow);
        assert!(
            (w - t).abs() < (wo - t).abs(),
            "fill {w}, none {wo}, truth {t}"
        );
    }

    /// Beside the wall the scene's shadow maps cannot tell the wall from
    /// the object's own surface (it lies within their bias) and the sky
    /// leaks onto the object; the march of the photo's depth (`contact`)
    /// blocks it: under an overcast sky the relit object is darker with it
    /// than without (the truth is darker still than either) and closer to
    /// the truth.
    #[test]
    fn the_contact_march_blocks_the_sky_behind_a_wall() {
        let case = wall_overcast();
        let obj: Vec<bool> = case.alpha.as_slice().iter().map(|a| *a >= 1.0).collect();
        let with = relit(&case, &RelightParams::default());
        let without = relit(
            &case,
            &RelightParams {
                contact: false,
                ..Default::default()
            },
        );
        let (lw, lo) = (mean_lum(&with, &obj), mean_lum(&without, &obj));
        assert!(lw < 0.99 * lo, "with the march {lw}, without {lo}");
        let (a, b) = (score(&case, &with), score(&case, &without));
        assert!(a.object_db > b.object_db + 0.3, "{a:?} vs {b:?}");
    }
}

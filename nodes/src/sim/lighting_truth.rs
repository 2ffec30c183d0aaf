//! Path-traced photos with known light, for measuring the lighting
//! estimate (`EstimateLighting`): rooms of diffuse objects lit only by an
//! environment map ([`Sky`]), rendered by [`crate::sim::pathtrace`], with
//! their exact depth and normals and the map itself.

use depthgraph_graph::prelude::*;

use crate::sim::pathtrace::{EnvLight, PathTraceParams, path_trace};
use crate::sim::relight_truth::{Sky, furnished_objects};
use crate::sim::synthetic::{
    Object, RenderOptions, Scene, ScenePreset, Texture, kinect_like_intrinsics, plane, render,
    solid,
};

/// The rooms of the lighting truth.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LightRoom {
    /// A sphere, a box and a cylinder on a grey floor before a wall: curved
    /// and creased surfaces and cast shadows (the cues of a light).
    Objects,
    /// A flat wall facing the camera and nothing else: no cue at all.
    FlatWall,
}

/// A path-traced photo of known light.
#[derive(Debug, Clone)]
pub struct LightCase {
    /// The camera.
    pub k: Intrinsics,
    /// The environment map that lit it.
    pub env: ColorImage,
    /// The photo (linear radiance).
    pub photo: ColorImage,
    /// Its exact depth.
    pub depth: DepthMap,
    /// Its exact normals.
    pub normals: NormalMap,
}

fn objects(room: LightRoom) -> Vec<Object> {
    match room {
        LightRoom::Objects => furnished_objects(),
        LightRoom::FlatWall => vec![solid(
            1,
            plane([0.0, 0.0, 1.5], [0.0, 0.0, -1.0]),
            Texture::Solid([0.6; 3]),
        )],
    }
}

/// Renders `room` under `sky` (images `w x h`, the map `map_width x
/// map_width/2`).
pub fn light_case(
    room: LightRoom,
    sky: Sky,
    w: usize,
    h: usize,
    map_width: usize,
    pt: &PathTraceParams,
) -> Result<LightCase, NodeError> {
    let env = sky.map(map_width)?;
    let light = EnvLight::new(&env)?;
    let k = kinect_like_intrinsics(w, h);
    let base = Scene::of(ScenePreset::Tabletop, w, h);
    let scene = Scene {
        objects: objects(room),
        light: base.light,
        camera: k,
    };
    let geo = render(&scene, &RenderOptions::default());
    let photo = path_trace(&scene, &light, pt);
    Ok(LightCase {
        k,
        env,
        photo,
        depth: geo.depth,
        normals: geo.normals,
    })
}

//! Hard cases for every node kind that takes inputs: images of 1x1, 1xN
//! and Nx1 pixels, all holes or a single valid pixel, depths and colours
//! that are zero, negative, subnormal, huge, NaN or infinite, extreme
//! intrinsics. For each generated case a node either refuses it with an
//! error or returns outputs that hold their type's bounds:
//!
//! - depth: finite and `>= 0` (0 is a hole);
//! - mask and confidence: finite, in `[0, 1]`;
//! - colour, normals, point clouds, meshes, VPLs, scalars: finite.
//!
//! It never panics. Kinds are run with their default parameters.
//! `DEPTHGRAPH_PROPTEST_CASES=N` runs N cases per kind (default 12;
//! `DEPTHGRAPH_PROPTEST_CASES=2000 cargo test --release --test hard_cases`
//! is the long run).
//!
//! Two more properties where they hold for every input: filling a map
//! without holes changes nothing (`PullPush`, `DualPullPush`), and the
//! depth filters are equivariant to a depth scale (`JointBilateral`,
//! `PullPush`: depth x k gives output x k).

use std::panic::{AssertUnwindSafe, catch_unwind};
use std::sync::Arc;

use depthgraph::graph::prelude::*;
use depthgraph::graph::value::{ExposureStack, Mesh, PointCloud, Vpl};
use proptest::prelude::*;
use proptest::test_runner::{Config, TestCaseError, TestRunner};

fn cases() -> u32 {
    std::env::var("DEPTHGRAPH_PROPTEST_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(12)
}

/// Kinds that refuse every generated case by design, and why.
const REFUSE_ALL: &[(&str, &str)] = &[
    (
        "LoadMask",
        "reads a file named by a parameter: the loaders are fuzzed (fuzz/)",
    ),
    ("SaveResponse", "writes a 256x1 response curve only"),
];

/// Kinds whose default parameters make one case slow; they get fewer cases.
const SLOW: &[&str] = &["Relight", "Refocus", "ReverseMappedDof", "NLMeansUpsample"];

/// One hostile `f32`: mostly ordinary, often not.
fn hostile() -> impl Strategy<Value = f32> {
    prop_oneof![
        6 => 0.05f32..20.0,
        1 => Just(0.0f32),
        1 => Just(-0.0f32),
        1 => -5.0f32..-1e-3,
        1 => Just(1e-40f32),
        1 => Just(f32::MIN_POSITIVE),
        1 => Just(3e38f32),
        1 => Just(1e20f32),
        1 => Just(f32::NAN),
        1 => Just(f32::INFINITY),
        1 => Just(f32::NEG_INFINITY),
    ]
}

/// How a generated image is filled.
#[derive(Debug, Clone)]
enum Fill {
    /// Each pixel its own hostile value.
    Mixed(Vec<f32>),
    /// Every pixel a hole (0).
    AllHoles,
    /// One valid pixel (at the index modulo the size) among holes.
    One(usize, f32),
    /// Ordinary smooth values.
    Smooth(f32),
}

#[derive(Clone)]
struct Case {
    w: usize,
    h: usize,
    depth: Fill,
    color: Vec<[f32; 3]>,
    mask: Vec<f32>,
    /// Focal length scale: 1 is a normal lens; 1e-6 and 1e7 are extreme.
    focal: f64,
    scalar: f64,
    /// Whether optional inputs are connected.
    optional: bool,
}

fn case() -> impl Strategy<Value = Case> {
    let dims = prop_oneof![
        Just((1usize, 1usize)),
        (2usize..9).prop_map(|n| (1, n)),
        (2usize..9).prop_map(|n| (n, 1)),
        (2usize..10, 2usize..8),
    ];
    dims.prop_flat_map(|(w, h)| {
        let n = w * h;
        let depth = prop_oneof![
            3 => proptest::collection::vec(hostile(), n).prop_map(Fill::Mixed),
            1 => Just(Fill::AllHoles),
            1 => (0..n, 0.1f32..10.0).prop_map(|(i, z)| Fill::One(i, z)),
            2 => (0.2f32..5.0).prop_map(Fill::Smooth),
        ];
        let color = proptest::collection::vec(
            prop_oneof![
                4 => (0.0f32..1.0, 0.0f32..1.0, 0.0f32..1.0).prop_map(|(r, g, b)| [r, g, b]),
                1 => (hostile(), hostile(), hostile()).prop_map(|(r, g, b)| [r, g, b]),
            ],
            n,
        );
        let mask = proptest::collection::vec(prop_oneof![4 => 0.0f32..=1.0, 1 => hostile()], n);
        let focal = prop_oneof![4 => Just(1.0f64), 1 => Just(1e-6f64), 1 => Just(1e7f64)];
        let scalar = prop_oneof![
            3 => 0.1f64..4.0,
            1 => Just(0.0f64),
            1 => Just(f64::NAN),
            1 => Just(-1.0f64),
            1 => Just(1e300f64),
        ];
        (
            Just((w, h)),
            depth,
            color,
            mask,
            focal,
            scalar,
            any::<bool>(),
        )
    })
    .prop_map(
        |((w, h), depth, color, mask, focal, scalar, optional)| Case {
            w,
            h,
            depth,
            color,
            mask,
            focal,
            scalar,
            optional,
        },
    )
}

impl std::fmt::Debug for Case {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let odd = |v: &[f32]| v.iter().filter(|x| !x.is_finite()).count();
        let d = self.depth();
        write!(
            f,
            "{}x{} depth {:?} (non-finite {}, holes {}, min {:e}, max {:e}), colour non-finite {}, \
             mask non-finite {}, focal x{}, scalar {}",
            self.w,
            self.h,
            match &self.depth {
                Fill::Mixed(_) => "mixed",
                Fill::AllHoles => "all holes",
                Fill::One(..) => "one valid",
                Fill::Smooth(_) => "smooth",
            },
            odd(d.as_slice()),
            d.as_slice().iter().filter(|z| **z == 0.0).count(),
            d.as_slice().iter().copied().fold(f32::INFINITY, f32::min),
            d.as_slice()
                .iter()
                .copied()
                .fold(f32::NEG_INFINITY, f32::max),
            odd(self.color.as_flattened()),
            odd(&self.mask),
            self.focal,
            self.scalar
        )
    }
}

impl Case {
    /// Whether every input sample is finite: then every output must be.
    fn finite(&self) -> bool {
        self.depth().as_slice().iter().all(|z| z.is_finite())
            && self.color.as_flattened().iter().all(|x| x.is_finite())
            && self.mask.iter().all(|x| x.is_finite())
            && self.scalar.is_finite()
    }

    fn depth(&self) -> DepthMap {
        let n = self.w * self.h;
        let v: Vec<f32> = match &self.depth {
            Fill::Mixed(v) => v.clone(),
            Fill::AllHoles => vec![0.0; n],
            Fill::One(i, z) => (0..n).map(|j| if j == i % n { *z } else { 0.0 }).collect(),
            Fill::Smooth(z) => (0..n).map(|j| z + 0.01 * (j % 7) as f32).collect(),
        };
        DepthMap::from_vec(self.w, self.h, v).unwrap()
    }
    fn intrinsics(&self) -> Intrinsics {
        let f = self.w.max(self.h) as f64 * self.focal;
        Intrinsics {
            fx: f,
            fy: f,
            cx: self.w as f64 / 2.0,
            cy: self.h as f64 / 2.0,
            width: self.w,
            height: self.h,
        }
    }
    fn color(&self) -> ColorImage {
        ColorImage::from_vec(self.w, self.h, self.color.clone()).unwrap()
    }
    fn mask(&self) -> Mask {
        Mask::from_vec(self.w, self.h, self.mask.clone()).unwrap()
    }
    fn points(&self) -> PointCloud {
        let d = self.depth();
        let positions: Vec<[f32; 3]> = d
            .as_slice()
            .iter()
            .enumerate()
            .map(|(i, z)| [(i % self.w) as f32 * 0.01, (i / self.w) as f32 * 0.01, *z])
            .collect();
        PointCloud {
            colors: self.color.clone(),
            normals: vec![[0.0, 0.0, -1.0]; positions.len()],
            positions,
        }
    }

    /// A value of type `ty` for this case; `None` for types it cannot make.
    fn value(&self, ty: ValueType, dir: &std::path::Path) -> Option<Value> {
        Some(match ty {
            ValueType::Color => Value::Color(Arc::new(self.color())),
            ValueType::Depth => Value::Depth(Arc::new(self.depth())),
            ValueType::Mask => Value::Mask(Arc::new(self.mask())),
            ValueType::Confidence => Value::Confidence(Arc::new(self.mask().retag())),
            ValueType::Normals => {
                Value::Normals(Arc::new(Image::from_fn(self.w, self.h, |x, y| {
                    let a = (x + 3 * y) as f32 * 0.7;
                    [a.sin() * 0.3, a.cos() * 0.3, -0.9]
                })))
            }
            ValueType::Labels => Value::Labels(Arc::new(Image::from_fn(self.w, self.h, |x, y| {
                ((x + y) % 3) as u32
            }))),
            ValueType::Intrinsics => Value::Intrinsics(self.intrinsics()),
            ValueType::PointCloud => Value::PointCloud(Arc::new(self.points())),
            ValueType::Mesh => {
                let p = self.points();
                let n = p.positions.len() as u32;
                let triangles = if n >= 3 {
                    vec![[0, 1, 2], [0, n - 1, 1]]
                } else {
                    vec![]
                };
                Value::Mesh(Arc::new(Mesh {
                    positions: p.positions,
                    colors: p.colors,
                    normals: p.normals,
                    triangles,
                }))
            }
            ValueType::ExposureStack => {
                let c = self.color();
                let darker = Image::from_fn(self.w, self.h, |x, y| c.get(x, y).map(|v| v * 0.25));
                Value::ExposureStack(Arc::new(ExposureStack {
                    images: vec![darker, c],
                    times_s: vec![0.25, 1.0],
                }))
            }
            ValueType::Vpls => {
                let s = self.scalar as f32;
                Value::Vpls(Arc::new(vec![
                    Vpl {
                        direction: [0.0, -1.0, 0.0],
                        power: [s, s, s],
                    },
                    Vpl {
                        direction: [0.6, -0.8, 0.0],
                        power: [1.0, 0.5, self.mask[0]],
                    },
                ]))
            }
            ValueType::Scalar => Value::Scalar(self.scalar),
            ValueType::File => Value::File(dir.join("in.bin")),
            ValueType::Extension(_) => return None,
        })
    }
}

/// Checks an output against the bounds of its type; the first violation.
/// With non-finite inputs (`finite_in` false) a NaN or infinity may pass
/// through where the node does not read the sample, but a depth is still
/// never negative and a mask never outside `[0, 1]` where it is a number.
fn violation(port: &str, v: &Value, finite_in: bool) -> Option<String> {
    let bad_f32 = |name: &str, vals: &[f32], ok: &dyn Fn(f32) -> bool| {
        vals.iter()
            .position(|x| {
                {
                    // a non-finite input may pass through, but never as a negative depth
                    let negative_depth = name == "depth" && *x < 0.0;
                    let passed_through = !(finite_in || x.is_finite() || negative_depth);
                    !(ok(*x) || passed_through)
                }
            })
            .map(|i| format!("{port} ({name}): sample {i} is {}", vals[i]))
    };
    let finite = |x: f32| x.is_finite();
    match v {
        Value::Depth(d) => bad_f32("depth", d.as_slice(), &|z| z.is_finite() && z >= 0.0),
        Value::Mask(m) => bad_f32("mask", m.as_slice(), &|a| (0.0..=1.0).contains(&a)),
        Value::Confidence(m) => bad_f32("confidence", m.as_slice(), &|a| (0.0..=1.0).contains(&a)),
        Value::Color(c) => bad_f32("color", c.as_slice().as_flattened(), &finite),
        Value::Normals(c) => bad_f32("normals", c.as_slice().as_flattened(), &finite),
        Value::PointCloud(p) => bad_f32("positions", p.positions.as_flattened(), &finite)
            .or_else(|| bad_f32("colors", p.colors.as_flattened(), &finite))
            .or_else(|| bad_f32("normals", p.normals.as_flattened(), &finite)),
        Value::Mesh(m) => bad_f32("positions", m.positions.as_flattened(), &finite).or_else(|| {
            let n = m.positions.len() as u32;
            m.triangles
                .iter()
                .find(|t| t.iter().any(|i| *i >= n))
                .map(|t| format!("{port}: triangle {t:?} beyond {n} vertices"))
        }),
        Value::Vpls(v) => v.iter().enumerate().find_map(|(i, l)| {
            (!l.direction.iter().chain(&l.power).all(|x| x.is_finite()))
                .then(|| format!("{port}: VPL {i} is {l:?}"))
        }),
        Value::Scalar(x) => (!x.is_finite()).then(|| format!("{port}: scalar {x}")),
        Value::ExposureStack(s) => s.images.iter().find_map(|i| {
            bad_f32("exposure", i.as_slice().as_flattened(), &|x| {
                !x.is_infinite()
            })
        }),
        _ => None,
    }
}

fn eval(
    node: &Arc<dyn Node>,
    inputs: &Inputs,
    out_dir: &std::path::Path,
) -> std::thread::Result<Result<Outputs, NodeError>> {
    let params = node.schema().default_params();
    let cancel = CancelToken::new();
    let ctx = EvalCtx {
        node: "under_test",
        cancel: &cancel,
        progress: None,
        out_dir,
        input_files: &[],
        derivations: None,
        max_pixels: depthgraph::graph::node::DEFAULT_MAX_PIXELS,
    };
    catch_unwind(AssertUnwindSafe(|| node.eval(&ctx, inputs, &params)))
}

#[test]
fn every_node_refuses_or_bounds_its_hard_cases() {
    let reg = depthgraph::nodes::registry().unwrap();
    let dir = tempfile::tempdir().unwrap();
    // panics are caught and reported as failures, without their noise
    std::panic::set_hook(Box::new(|_| {}));
    let mut failures = Vec::new();
    let mut tested = 0;
    for kind in reg.kinds() {
        let node = reg.get(kind).unwrap();
        let schema = node.schema();
        if schema.inputs.is_empty()
            || schema
                .inputs
                .iter()
                .any(|p| matches!(p.ty, ValueType::Extension(_)))
        {
            continue; // a source, or an input no case can make
        }
        tested += 1;
        let n = if SLOW.contains(&kind) {
            cases().div_ceil(3)
        } else {
            cases()
        };
        let config = Config {
            cases: n,
            failure_persistence: None,
            max_shrink_iters: 200,
            ..Config::default()
        };
        // the same cases on every run unless asked otherwise, so CI is
        // reproducible; DEPTHGRAPH_PROPTEST_RANDOM=1 draws new ones
        let mut runner = if std::env::var_os("DEPTHGRAPH_PROPTEST_RANDOM").is_some() {
            TestRunner::new(config)
        } else {
            let rng = proptest::test_runner::TestRng::deterministic_rng(config.rng_algorithm);
            TestRunner::new_with_rng(config, rng)
        };
        let produced = std::cell::Cell::new(0usize);
        let first_error = std::cell::RefCell::new(None::<String>);
        let result = runner.run(&case(), |c| {
            let mut inputs = Inputs::new();
            for p in &schema.inputs {
                if p.optional && !c.optional {
                    continue;
                }
                if let Some(v) = c.value(p.ty, dir.path()) {
                    inputs.insert(p.name, v);
                }
            }
            match eval(&node, &inputs, dir.path()) {
                Err(payload) => {
                    let msg = payload
                        .downcast_ref::<String>()
                        .cloned()
                        .or_else(|| payload.downcast_ref::<&str>().map(|s| s.to_string()))
                        .unwrap_or_default();
                    Err(TestCaseError::fail(format!("panicked: {msg}")))
                }
                Ok(Err(e)) => {
                    // refused with an error: fine
                    first_error
                        .borrow_mut()
                        .get_or_insert_with(|| e.to_string());
                    Ok(())
                }
                Ok(Ok(out)) => {
                    produced.set(produced.get() + 1);
                    for (port, v) in &out.values {
                        if let Some(msg) = violation(port, v, c.finite()) {
                            return Err(TestCaseError::fail(msg));
                        }
                    }
                    Ok(())
                }
            }
        });
        if let Err(e) = result {
            failures.push(format!("{kind}: {e}"));
        } else if produced.get() == 0 && !REFUSE_ALL.iter().any(|(k, _)| *k == kind) {
            // a kind that refuses every case tests nothing
            failures.push(format!(
                "{kind}: refused all {n} cases, e.g. {}",
                first_error.borrow().clone().unwrap_or_default()
            ));
        }
    }
    let _ = std::panic::take_hook();
    assert!(tested >= 25, "only {tested} kinds take inputs");
    assert!(failures.is_empty(), "{}", failures.join("\n\n"));
}

/// A depth map of ordinary values with holes at `holes` (indices).
fn smooth_depth(w: usize, h: usize, holes: &[usize]) -> DepthMap {
    DepthMap::from_fn(w, h, |x, y| {
        if holes.contains(&(y * w + x)) {
            0.0
        } else {
            1.0 + 0.05 * x as f32 + 0.02 * (y % 5) as f32
        }
    })
}

fn run_depth(reg: &Registry, kind: &str, inputs: Inputs) -> DepthMap {
    let dir = tempfile::tempdir().unwrap();
    let out = eval(&reg.get(kind).unwrap(), &inputs, dir.path())
        .unwrap()
        .unwrap();
    match &out.values["depth"] {
        Value::Depth(d) => (**d).clone(),
        other => panic!("{kind}: depth is {other:?}"),
    }
}

proptest! {
    #![proptest_config(Config { cases: cases(), failure_persistence: None, ..Config::default() })]

    #[test]
    fn filling_a_complete_map_changes_nothing(w in 1usize..24, h in 1usize..24) {
        let reg = depthgraph::nodes::registry().unwrap();
        let d = smooth_depth(w, h, &[]);
        let k = Intrinsics { fx: 30.0, fy: 30.0, cx: w as f64 / 2.0, cy: h as f64 / 2.0, width: w, height: h };
        let color = ColorImage::from_fn(w, h, |x, _| [x as f32 / w as f32; 3]);
        let mut plain = Inputs::new();
        plain.insert("depth", Value::Depth(Arc::new(d.clone())));
        prop_assert_eq!(&run_depth(&reg, "PullPush", plain), &d);
        let mut dual = Inputs::new();
        dual.insert("depth", Value::Depth(Arc::new(d.clone())));
        dual.insert("color", Value::Color(Arc::new(color)));
        dual.insert("intrinsics", Value::Intrinsics(k));
        prop_assert_eq!(&run_depth(&reg, "DualPullPush", dual), &d);
    }

    #[test]
    fn depth_filters_scale_with_the_depth(
        w in 3usize..20,
        h in 3usize..20,
        k in prop_oneof![Just(0.001f32), 0.25f32..4.0, Just(1000.0f32)],
        hole_seed in 0usize..1000,
    ) {
        let reg = depthgraph::nodes::registry().unwrap();
        let holes: Vec<usize> = (0..(w * h) / 5).map(|i| (hole_seed + i * 7919) % (w * h)).collect();
        let d = smooth_depth(w, h, &holes);
        let scaled = DepthMap::from_vec(w, h, d.as_slice().iter().map(|z| z * k).collect()).unwrap();
        let color = Arc::new(ColorImage::from_fn(w, h, |x, y| [((x + y) % 4) as f32 / 4.0; 3]));
        for kind in ["PullPush", "JointBilateral"] {
            let inputs = |depth: &DepthMap| {
                let mut i = Inputs::new();
                i.insert("depth", Value::Depth(Arc::new(depth.clone())));
                i.insert("color", Value::Color(color.clone()));
                i
            };
            let a = run_depth(&reg, kind, inputs(&d));
            let b = run_depth(&reg, kind, inputs(&scaled));
            for (i, (za, zb)) in a.as_slice().iter().zip(b.as_slice()).enumerate() {
                // same holes; values within 1e-5 relative (f32 rounding of the scale)
                prop_assert_eq!(*za == 0.0, *zb == 0.0, "{} pixel {} hole differs", kind, i);
                let want = za * k;
                prop_assert!((zb - want).abs() <= 1e-5 * want.abs().max(f32::MIN_POSITIVE), "{} pixel {}: {} vs {} x {}", kind, i, zb, za, k);
            }
        }
    }
}

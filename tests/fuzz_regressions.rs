//! Replays every fuzz target's seed corpus (`fuzz/corpus/<target>/`) and
//! every minimized crash input (`fuzz/regressions/<target>/`) through the
//! target's body (`depthgraph::fuzzing`) on stable, so a fixed crash stays
//! fixed without a nightly toolchain. Seeds are made by the project's own
//! writers: `DEPTHGRAPH_WRITE_FUZZ_SEEDS=1 cargo test --test fuzz_regressions`
//! writes them anew.

use std::path::{Path, PathBuf};

use depthgraph::fuzzing::TARGETS;
use depthgraph::graph::prelude::*;
use depthgraph::nodes::io;

fn fuzz_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("fuzz")
}

/// Small files written by the project's own writers, per target.
fn seeds() -> Vec<(&'static str, String, Vec<u8>)> {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let mut out = Vec::new();
    let color = ColorImage::from_fn(5, 3, |x, y| [x as f32 / 4.0, y as f32 / 2.0, 0.25]);
    let depth = DepthMap::from_fn(
        5,
        3,
        |x, y| if x == y { 0.0 } else { 0.5 + 0.25 * x as f32 },
    );
    let read = |p: &Path| std::fs::read(p).unwrap();
    for (name, bits16) in [("rgb8.png", false), ("rgb16.png", true)] {
        let p = d.join(name);
        io::save_color(&color, &p, bits16, 0.0).unwrap();
        out.push(("load_png", name.to_string(), read(&p)));
    }
    for (name, format) in [
        ("depth16.png", io::DepthFormat::Png16),
        ("preview.png", io::DepthFormat::Preview),
    ] {
        let p = d.join(name);
        let params = io::SaveDepthParams {
            format,
            ..Default::default()
        };
        io::save_depth(&depth, &p, &params).unwrap();
        out.push(("load_png", name.to_string(), read(&p)));
    }
    let p = d.join("color.exr");
    io::save_color(&color, &p, false, 0.0).unwrap();
    out.push(("load_exr", "color.exr".into(), read(&p)));
    let p = d.join("depth.exr");
    let params = io::SaveDepthParams {
        format: io::DepthFormat::Exr,
        ..Default::default()
    };
    io::save_depth(&depth, &p, &params).unwrap();
    out.push(("load_exr", "depth.exr".into(), read(&p)));
    // EXR as other writers make them: f16, f32 and u32 channels, ZIP,
    // PIZ and uncompressed, scan lines and tiles
    {
        use exr::prelude::*;
        let (w, h) = (5usize, 3usize);
        let cases: [(&str, FlatSamples, Encoding); 3] = [
            (
                "f16_zip.exr",
                FlatSamples::F16((0..w * h).map(|i| f16::from_f32(0.1 * i as f32)).collect()),
                Encoding {
                    compression: Compression::ZIP16,
                    blocks: Blocks::ScanLines,
                    line_order: LineOrder::Increasing,
                },
            ),
            (
                "u32_piz_tiles.exr",
                FlatSamples::U32((0..w * h).map(|i| i as u32 * 100).collect()),
                Encoding {
                    compression: Compression::PIZ,
                    blocks: Blocks::Tiles(Vec2(4, 4)),
                    line_order: LineOrder::Increasing,
                },
            ),
            (
                "f32_raw.exr",
                FlatSamples::F32(depth.as_slice().to_vec()),
                Encoding::UNCOMPRESSED,
            ),
        ];
        for (name, samples, encoding) in cases {
            let layer = Layer::new(
                (w, h),
                LayerAttributes::named("seed"),
                encoding,
                AnyChannels::sort(SmallVec::from_vec(vec![AnyChannel::new("Z", samples)])),
            );
            let p = d.join(name);
            exr::prelude::Image::from_layer(layer)
                .write()
                .to_file(&p)
                .unwrap();
            out.push(("load_exr", name.to_string(), std::fs::read(&p).unwrap()));
        }
    }
    // Radiance: new RLE, flat (narrow), old RLE, XYZ, bottom-up
    let wide = ColorImage::from_fn(9, 3, |x, y| [0.1 * x as f32, 2.0 * y as f32, 300.0]);
    out.push((
        "load_hdr",
        "rle.hdr".into(),
        io::radiance::encode_rgbe(&wide),
    ));
    out.push((
        "load_hdr",
        "flat.hdr".into(),
        io::radiance::encode_rgbe(&color),
    ));
    let mut old = b"VIEW= -vtv\n#?RADIANCE\nEXPOSURE=0.5\n\n+Y 1 -X 12\n\x80\x40\x20\x81".to_vec();
    old.extend_from_slice(&[1, 1, 1, 11]);
    out.push(("load_hdr", "old_rle.hdr".into(), old));
    let mut xyz = b"#?RADIANCE\nFORMAT=32-bit_rle_xyze\n\n-X 2 +Y 1\n".to_vec();
    xyz.extend_from_slice(&[200, 210, 220, 128, 10, 20, 30, 130]);
    out.push(("load_hdr", "xyz.hdr".into(), xyz));
    // PFM in both byte orders
    for (name, scale, le) in [("le.pfm", "-1.0", true), ("be.pfm", "1.0", false)] {
        let mut b = format!("Pf\n5 3\n{scale}\n").into_bytes();
        for z in depth.as_slice() {
            b.extend_from_slice(&if le { z.to_le_bytes() } else { z.to_be_bytes() });
        }
        out.push(("load_pfm", name.to_string(), b));
    }
    // PGM/PPM: 8 and 16 bit, maxval 65535 and an odd one
    for (name, magic, maxval, ch) in [
        ("g8.pgm", "P5", 255u32, 1usize),
        ("g16.pgm", "P5", 65535, 1),
        ("c12.ppm", "P6", 4095, 3),
    ] {
        let mut b = format!("{magic}\n# a comment\n5 3\n{maxval}\n").into_bytes();
        for i in 0..15 * ch {
            let v = (i as u32 * 977) % (maxval + 1);
            if maxval > 255 {
                b.extend_from_slice(&(v as u16).to_be_bytes());
            } else {
                b.push(v as u8);
            }
        }
        out.push(("load_pnm", name.to_string(), b));
    }
    // an NYU raw dump: little-endian 16-bit disparity, 2047 = none
    let mut b = b"P5\n4 2\n65535\n".to_vec();
    for v in [600u16, 700, 800, 2047, 0, 1000, 1092, 1093] {
        b.extend_from_slice(&v.to_le_bytes());
    }
    out.push(("load_nyu_raw", "nyu.pgm".into(), b));
    // the pipelines of graphs/, and small documents
    for e in std::fs::read_dir(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("graphs"))
        .unwrap()
        .flatten()
    {
        let name = e.file_name().to_string_lossy().into_owned();
        if name == "demo.ron" || name == "refocus.ron" || name == "hdr_merge.ron" {
            out.push(("ron_document", name, read(&e.path())));
        }
    }
    out.push((
        "ron_document",
        "tiny.ron".into(),
        b"(version: 1, nodes: {}, outputs: [])".to_vec(),
    ));
    for (i, s) in [
        "smooth.radius=3",
        "smooth.sigma_color=0.25",
        "smooth.sigma_color=-0.0",
        "blur.f_number=NaN",
        "scene.preset=corridor",
        "scene.width=1e3",
        "blur.aperture=\"hexagon\"",
    ]
    .iter()
    .enumerate()
    {
        out.push(("set_override", format!("set{i}.txt"), s.as_bytes().to_vec()));
    }
    // cache entries as the engine writes them
    let outputs = Outputs::new()
        .with("depth", Value::Depth(std::sync::Arc::new(depth.clone())))
        .with("color", Value::Color(std::sync::Arc::new(color.clone())))
        .with("n", Value::Scalar(-0.0));
    out.push((
        "cache_codec",
        "entry.bin".into(),
        depthgraph::graph::codec::encode(&outputs),
    ));
    out.push((
        "exposure_list",
        "list.txt".into(),
        b"# file time\na.png 0.25\nb.png 1\nc.png 4.0 # bright\n".to_vec(),
    ));
    out
}

fn files_in(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.is_file())
        .collect();
    v.sort();
    v
}

#[test]
fn seeds_corpora_and_regressions_pass_every_target() {
    let seeds = seeds();
    if std::env::var_os("DEPTHGRAPH_WRITE_FUZZ_SEEDS").is_some() {
        for (t, name, bytes) in &seeds {
            let dir = fuzz_dir().join("corpus").join(t);
            std::fs::create_dir_all(&dir).unwrap();
            std::fs::write(dir.join(format!("seed-{name}")), bytes).unwrap();
        }
    }
    let mut replayed = 0;
    for (name, target) in TARGETS {
        let mut inputs: Vec<(String, Vec<u8>)> = seeds
            .iter()
            .filter(|(t, _, _)| t == name)
            .map(|(_, n, b)| (format!("seed {n}"), b.clone()))
            .collect();
        assert!(!inputs.is_empty(), "target {name} has no seed");
        for sub in ["corpus", "regressions"] {
            for p in files_in(&fuzz_dir().join(sub).join(name)) {
                inputs.push((p.display().to_string(), std::fs::read(&p).unwrap()));
            }
        }
        for (what, bytes) in &inputs {
            let r = std::panic::catch_unwind(|| target(bytes));
            assert!(r.is_ok(), "target {name} fails on {what}");
            // and every truncation of a seed (the commonest damage)
            if what.starts_with("seed") {
                for cut in [
                    0,
                    1,
                    bytes.len() / 3,
                    bytes.len() / 2,
                    bytes.len().saturating_sub(1),
                ] {
                    let r = std::panic::catch_unwind(|| target(&bytes[..cut]));
                    assert!(
                        r.is_ok(),
                        "target {name} fails on {what} cut to {cut} bytes"
                    );
                }
            }
            replayed += 1;
        }
    }
    assert!(replayed >= TARGETS.len());
}

#[test]
fn the_properties_can_fail() {
    // an entry that decodes but does not re-encode to itself would be
    // caught: the codec property compares whole byte strings
    let outputs = Outputs::new().with("n", Value::Scalar(1.5));
    let good = depthgraph::graph::codec::encode(&outputs);
    depthgraph::fuzzing::cache_codec(&good);
    let mut trailing = good.clone();
    trailing.push(0);
    // trailing bytes are refused by the decoder (a miss), not re-encoded
    assert!(depthgraph::graph::codec::decode(&trailing, &Default::default()).is_none());
    // a PFM whose scale is NaN is an error, not an image
    let e = io::decode_pfm(
        b"Pf\n1 1\nnan\n\0\0\0\0",
        Path::new("x.pfm"),
        &Default::default(),
    );
    assert!(e.is_err());
}

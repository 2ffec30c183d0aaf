//! PLY writing (binary little-endian or ASCII) of points and meshes.

use std::fs;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use depthgraph_graph::prelude::*;

use super::write::write_atomic;
use crate::kit::color::srgb8;

/// Writes points (with optional colors, sRGB 8-bit, and normals) and optional
/// triangles as PLY.
pub fn write_ply(
    path: &Path,
    positions: &[[f32; 3]],
    colors: &[[f32; 3]],
    normals: &[[f32; 3]],
    triangles: &[[u32; 3]],
    ascii: bool,
) -> Result<PathBuf, NodeError> {
    let has_c = !colors.is_empty() && colors.len() == positions.len();
    let has_n = !normals.is_empty() && normals.len() == positions.len();
    if let Some(t) = triangles
        .iter()
        .find(|t| t.iter().any(|i| *i as usize >= positions.len()))
    {
        return Err(NodeError::Invalid(format!(
            "triangle {t:?} refers to a vertex beyond the {} given",
            positions.len()
        )));
    }
    write_atomic(path, |tmp| {
        let f = fs::File::create(tmp)?;
        let mut w = BufWriter::new(f);
        let mut header = format!(
            "ply\nformat {} 1.0\ncomment written by depthgraph (camera frame: x right, y down, z forward; metres)\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\n",
            if ascii {
                "ascii"
            } else {
                "binary_little_endian"
            },
            positions.len()
        );
        if has_n {
            header.push_str("property float nx\nproperty float ny\nproperty float nz\n");
        }
        if has_c {
            header.push_str("property uchar red\nproperty uchar green\nproperty uchar blue\n");
        }
        if !triangles.is_empty() {
            header.push_str(&format!(
                "element face {}\nproperty list uchar uint vertex_indices\n",
                triangles.len()
            ));
        }
        header.push_str("end_header\n");
        w.write_all(header.as_bytes())?;
        let c8 = |c: &[f32; 3]| c.map(srgb8);
        for i in 0..positions.len() {
            let p = positions[i];
            if ascii {
                let mut line = format!("{} {} {}", p[0], p[1], p[2]);
                if has_n {
                    let n = normals[i];
                    line.push_str(&format!(" {} {} {}", n[0], n[1], n[2]));
                }
                if has_c {
                    let c = c8(&colors[i]);
                    line.push_str(&format!(" {} {} {}", c[0], c[1], c[2]));
                }
                line.push('\n');
                w.write_all(line.as_bytes())?;
            } else {
                for v in p {
                    w.write_all(&v.to_le_bytes())?;
                }
                if has_n {
                    for v in normals[i] {
                        w.write_all(&v.to_le_bytes())?;
                    }
                }
                if has_c {
                    w.write_all(&c8(&colors[i]))?;
                }
            }
        }
        for t in triangles {
            if ascii {
                w.write_all(format!("3 {} {} {}\n", t[0], t[1], t[2]).as_bytes())?;
            } else {
                w.write_all(&[3u8])?;
                for i in t {
                    w.write_all(&i.to_le_bytes())?;
                }
            }
        }
        w.flush()
    })
}

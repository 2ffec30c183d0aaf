//! The agreement checks between the CPU and device results, with the
//! tolerances each device module states. Each returns what it measured, or
//! an error that says where and by how much the results part.

use depthgraph_graph::prelude::*;
use depthgraph_nodes::kit::color::{display_mse, psnr_of_mse};

/// What a depth comparison measured.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthAgreement {
    /// Largest `|Δz| / z` over pixels valid on both.
    pub max_rel: f64,
    /// Pixels compared.
    pub pixels: usize,
}

/// Same size, the same holes, and `|z_gpu - z_cpu| <= rel * z_cpu` at every
/// valid pixel.
pub fn depth_within(cpu: &DepthMap, gpu: &DepthMap, rel: f64) -> Result<DepthAgreement, String> {
    if cpu.dims() != gpu.dims() {
        return Err(format!(
            "sizes differ: {:?} vs {:?}",
            cpu.dims(),
            gpu.dims()
        ));
    }
    let w = cpu.width().max(1);
    let mut max_rel = 0.0f64;
    for (i, (&a, &b)) in cpu.as_slice().iter().zip(gpu.as_slice()).enumerate() {
        let (va, vb) = (DepthMap::is_valid(a), DepthMap::is_valid(b));
        if va != vb {
            return Err(format!(
                "hole masks differ at ({}, {}): cpu {a}, gpu {b}",
                i % w,
                i / w
            ));
        }
        if va {
            // Guard: a > 0 (valid).
            let r = (a as f64 - b as f64).abs() / a as f64;
            if r > rel {
                return Err(format!(
                    "at ({}, {}): cpu {a}, gpu {b}: relative difference {r:.3e} > {rel:e}",
                    i % w,
                    i / w
                ));
            }
            max_rel = max_rel.max(r);
        }
    }
    Ok(DepthAgreement {
        max_rel,
        pixels: cpu.len(),
    })
}

/// PSNR in dB of the display images of `gpu` against `cpu`
/// ([`display_mse`]); infinite when they are equal.
pub fn display_psnr(cpu: &ColorImage, gpu: &ColorImage) -> Result<f64, String> {
    if cpu.dims() != gpu.dims() {
        return Err(format!(
            "sizes differ: {:?} vs {:?}",
            cpu.dims(),
            gpu.dims()
        ));
    }
    // the display encoding maps NaN to 0: compare NaN-ness first
    for (t, (a, b)) in cpu.as_slice().iter().zip(gpu.as_slice()).enumerate() {
        if (0..3).any(|k| a[k].is_nan() != b[k].is_nan()) {
            return Err(format!("pixel {t}: cpu {a:?}, gpu {b:?} (NaN on one side)"));
        }
    }
    Ok(psnr_of_mse(display_mse(cpu.as_slice(), gpu.as_slice())))
}

/// The Refocus check: pixels where `fixed` is true (outside the active
/// tiles) are bit-identical, and the display PSNR is at least `min_db`.
/// Returns the PSNR.
pub fn color_within(
    cpu: &ColorImage,
    gpu: &ColorImage,
    fixed: &[bool],
    min_db: f64,
) -> Result<f64, String> {
    if cpu.dims() != gpu.dims() || fixed.len() != cpu.len() {
        return Err(format!(
            "sizes differ: {:?} vs {:?}",
            cpu.dims(),
            gpu.dims()
        ));
    }
    let w = cpu.width().max(1);
    for (t, ((a, b), &f)) in cpu
        .as_slice()
        .iter()
        .zip(gpu.as_slice())
        .zip(fixed)
        .enumerate()
    {
        if f && a.map(f32::to_bits) != b.map(f32::to_bits) {
            return Err(format!(
                "inactive pixel ({}, {}) differs: cpu {a:?}, gpu {b:?}",
                t % w,
                t / w
            ));
        }
    }
    let psnr = display_psnr(cpu, gpu)?;
    if psnr < min_db {
        return Err(format!("display PSNR {psnr:.2} dB < {min_db} dB"));
    }
    Ok(psnr)
}

/// The EdgeDetect check: strengths within `tol`, and binary edges equal
/// except at pixels the strength leaves ambiguous: within `tol` of the
/// threshold, or an edge candidate whose thinning compares values (itself
/// and its 8 neighbours) two of which are within `2 tol`.
/// Returns the largest strength difference and the number of ambiguous
/// pixels whose edge bit differs.
pub fn edges_within(
    cpu: (&Confidence, &Mask),
    gpu: (&Confidence, &Mask),
    threshold: f64,
    tol: f64,
) -> Result<(f64, usize), String> {
    let ((sa, ea), (sb, eb)) = (cpu, gpu);
    if sa.dims() != sb.dims() || ea.dims() != eb.dims() || sa.dims() != ea.dims() {
        return Err("sizes differ".into());
    }
    let (w, h) = sa.dims();
    let s = sa.as_slice();
    let mut worst = 0.0f64;
    for (t, (a, b)) in s.iter().zip(sb.as_slice()).enumerate() {
        let d = (*a as f64 - *b as f64).abs();
        if d.is_nan() || d > tol {
            return Err(format!(
                "strength at ({}, {}): cpu {a}, gpu {b}",
                t % w,
                t / w
            ));
        }
        worst = worst.max(d);
    }
    let mut ambiguous = 0;
    for (t, (a, b)) in ea.as_slice().iter().zip(eb.as_slice()).enumerate() {
        if a == b {
            continue;
        }
        let (x, y) = ((t % w) as isize, (t / w) as isize);
        let v = s[t] as f64;
        // Below the threshold by more than tol: an edge on neither backend.
        // Otherwise the thinning compares v with its neighbours and the
        // neighbours' maxima per axis: ambiguous when two of these nine
        // values are within 2 tol (a comparison rounding can flip).
        let mut vals = vec![v];
        for dy in -1..=1isize {
            for dx in -1..=1isize {
                if (dx, dy) != (0, 0) {
                    let xx = (x + dx).clamp(0, w as isize - 1) as usize;
                    let yy = (y + dy).clamp(0, h as isize - 1) as usize;
                    vals.push(s[yy * w + xx] as f64);
                }
            }
        }
        let close_pair = vals
            .iter()
            .enumerate()
            .any(|(i, a)| vals[i + 1..].iter().any(|b| (a - b).abs() <= 2.0 * tol));
        let ambiguous_here = (v - threshold).abs() <= tol || (v >= threshold - tol && close_pair);
        if !ambiguous_here {
            return Err(format!(
                "edge bit at ({x}, {y}) differs where the strength {v} is not ambiguous"
            ));
        }
        ambiguous += 1;
    }
    Ok((worst, ambiguous))
}

/// The OcclusionComposite check: the alphas bit-identical; where alpha is
/// 0 or 1, color and depth bit-identical; elsewhere within
/// `rel * max(|v|, 1)`.
pub fn composite_within(
    cpu: (&ColorImage, &DepthMap, &Mask),
    gpu: (&ColorImage, &DepthMap, &Mask),
    rel: f64,
) -> Result<(), String> {
    let ((ca, za, aa), (cb, zb, ab)) = (cpu, gpu);
    if ca.dims() != cb.dims() || za.dims() != zb.dims() || aa.dims() != ab.dims() {
        return Err("sizes differ".into());
    }
    let close = |x: f32, y: f32| {
        let d = (x as f64 - y as f64).abs();
        !d.is_nan() && d <= rel * (x.abs() as f64).max(1.0)
    };
    for t in 0..aa.len() {
        let (a, b) = (aa.as_slice()[t], ab.as_slice()[t]);
        if a.to_bits() != b.to_bits() {
            return Err(format!("alpha at {t}: cpu {a}, gpu {b}"));
        }
        let (c1, c2) = (ca.as_slice()[t], cb.as_slice()[t]);
        let (z1, z2) = (za.as_slice()[t], zb.as_slice()[t]);
        let exact = a == 0.0 || a == 1.0;
        let same = if exact {
            c1.map(f32::to_bits) == c2.map(f32::to_bits) && z1.to_bits() == z2.to_bits()
        } else {
            (0..3).all(|k| close(c1[k], c2[k])) && close(z1, z2)
        };
        if !same {
            return Err(format!(
                "pixel {t} (alpha {a}): cpu {c1:?} {z1}, gpu {c2:?} {z2}"
            ));
        }
    }
    Ok(())
}

/// What a comparison of two direct terms measured.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DirectAgreement {
    /// Pixels the object shades (`hit`), the same on both.
    pub hits: usize,
    /// Largest `|Δ ΔE| / (Σ_k Φ_k + ΔE)` over pixels and channels.
    pub max_rel: f64,
}

/// The same pixel count, the same `hit` at every pixel, and per channel
/// `|de_gpu - de_cpu| <= rel * (total_power + de_cpu)` (the bound of
/// [`crate::relight`]; `total_power`: the sum of every VPL's power).
pub fn direct_within(
    cpu: &[depthgraph_nodes::relight::direct::DirectSum],
    gpu: &[depthgraph_nodes::relight::direct::DirectSum],
    total_power: [f64; 3],
    rel: f64,
) -> Result<DirectAgreement, String> {
    if cpu.len() != gpu.len() {
        return Err(format!("{} pixels vs {}", cpu.len(), gpu.len()));
    }
    let (mut hits, mut max_rel) = (0usize, 0.0f64);
    for (k, (a, b)) in cpu.iter().zip(gpu).enumerate() {
        if a.hit != b.hit {
            return Err(format!(
                "pixel {k} of the plan: hit cpu {} gpu {}",
                a.hit, b.hit
            ));
        }
        hits += usize::from(a.hit);
        for (ch, power) in total_power.iter().enumerate() {
            // guard: the scale is > 0 unless every power and the sum are 0,
            // and then any difference is beyond the bound
            let scale = power + a.de[ch].abs();
            let d = (a.de[ch] - b.de[ch]).abs();
            if d.is_nan() || d > rel * scale {
                return Err(format!(
                    "pixel {k} of the plan, channel {ch}: cpu {} gpu {}: {d:.3e} > {rel:e} x {scale:.3e}",
                    a.de[ch], b.de[ch]
                ));
            }
            if scale > 0.0 {
                max_rel = max_rel.max(d / scale);
            }
        }
    }
    Ok(DirectAgreement { hits, max_rel })
}

/// The object's received light of two backends bit for bit (the device's
/// decisions with the host's f64 sums are the CPU's, [`crate::relight`]):
/// the surfaces compared, or the first that differs.
pub fn object_light_equal(
    cpu: &[depthgraph_nodes::relight::object_light::ObjectLightSum],
    gpu: &[depthgraph_nodes::relight::object_light::ObjectLightSum],
) -> Result<usize, String> {
    if cpu.len() != gpu.len() {
        return Err(format!("{} surfaces vs {}", cpu.len(), gpu.len()));
    }
    let bits = |v: &[f64; 3]| v.map(f64::to_bits);
    for (k, (a, b)) in cpu.iter().zip(gpu).enumerate() {
        if bits(&a.est) != bits(&b.est) || bits(&a.ecap) != bits(&b.ecap) {
            return Err(format!(
                "surface {k}: cpu E^(s+t) {:?} E^o {:?}, gpu {:?} {:?}",
                a.est, a.ecap, b.est, b.ecap
            ));
        }
    }
    Ok(cpu.len())
}

/// The fill light of two backends bit for bit (the device's decisions with
/// the host's f64 sums are the CPU's): the surfaces compared, or the first
/// that differs.
pub fn fill_equal(
    cpu: &[depthgraph_nodes::relight::fill::FillSum],
    gpu: &[depthgraph_nodes::relight::fill::FillSum],
) -> Result<usize, String> {
    if cpu.len() != gpu.len() {
        return Err(format!("{} surfaces vs {}", cpu.len(), gpu.len()));
    }
    for (k, (a, b)) in cpu.iter().zip(gpu).enumerate() {
        if a.map(f64::to_bits) != b.map(f64::to_bits) {
            return Err(format!("surface {k}: cpu {a:?}, gpu {b:?}"));
        }
    }
    Ok(cpu.len())
}

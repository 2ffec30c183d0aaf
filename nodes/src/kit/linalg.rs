//! Small dense linear algebra for the least-squares fits (HDR response
//! curves, lighting estimation).

/// Solves `A x = b` in place for a symmetric positive definite `A` (n x n,
/// row-major; only the lower triangle is read) by Cholesky factorisation.
/// `Err(j)` when pivot `j` is not positive.
pub fn cholesky_solve(a: &mut [f64], n: usize, b: &mut [f64]) -> Result<(), usize> {
    let dot = |x: &[f64], y: &[f64]| x.iter().zip(y).map(|(p, q)| p * q).sum::<f64>();
    for j in 0..n {
        let row_j = j * n;
        let d = a[row_j + j] - dot(&a[row_j..row_j + j], &a[row_j..row_j + j]);
        if !(d > 0.0 && d.is_finite()) {
            return Err(j);
        }
        let d = d.sqrt();
        a[row_j + j] = d;
        for i in (j + 1)..n {
            let row_i = i * n;
            let s = a[row_i + j] - dot(&a[row_i..row_i + j], &a[row_j..row_j + j]);
            a[row_i + j] = s / d; // guard: d > 0 checked above
        }
    }
    // L y = b
    for i in 0..n {
        let s = b[i] - dot(&a[i * n..i * n + i], &b[..i]);
        b[i] = s / a[i * n + i]; // guard: diagonal > 0 after the factorisation
    }
    // L^T x = y
    for i in (0..n).rev() {
        let mut s = b[i];
        for k in (i + 1)..n {
            s -= a[k * n + i] * b[k];
        }
        b[i] = s / a[i * n + i]; // guard: diagonal > 0
    }
    Ok(())
}

//! Linear least squares with one tall design matrix and many right-hand sides:
//! `min_X ||B - A X||_F`, as both the LSFD (one design for all scan points) and the
//! variable-projection pole refinement (one design per trial pole set) need it.
//!
//! The normal equations `A^T A X = A^T B` are formed with faer's matrix products (sequential,
//! so the result does not depend on the thread count) and solved with the small Cholesky of
//! [`super::lscf::cholesky`]; callers scale the columns of `A` to unit norm, which keeps the
//! `ncol x ncol` system well conditioned for distinct poles.

use super::lscf::{cholesky, cholesky_solve};
use super::ModalError;
use faer::linalg::matmul::matmul;
use faer::{Accum, Mat, MatMut, MatRef, Par};

/// Columns in the real/imaginary stacked form in which complex spectra enter [`solve`]:
/// for each `(row, scale)`, `scale * Re(row)` then `scale * Im(row)`, one after another
/// (column-major).
pub(crate) fn stacked<'a>(cols: impl Iterator<Item = (&'a [faer::c64], f64)>) -> Vec<f64> {
    cols.flat_map(|(row, s)| {
        row.iter()
            .map(move |v| s * v.re)
            .chain(row.iter().map(move |v| s * v.im))
    })
    .collect()
}

/// Solution of [`solve`].
pub(crate) struct MultiLs {
    /// `X`, column-major `ncol x nrhs`.
    pub x: Vec<f64>,
    /// `B - A X`, column-major `m x nrhs` (only if asked for).
    pub residual: Option<Vec<f64>>,
}

/// Solve `min ||B - A X||` for `A` (`m x ncol`) and `B` (`m x nrhs`), both column-major.
/// Errors (as `ModalError::Numerical` of `stage`) if `A^T A` is not positive definite.
pub(crate) fn solve(
    a: &[f64],
    m: usize,
    ncol: usize,
    b: &[f64],
    nrhs: usize,
    want_residual: bool,
    stage: &'static str,
) -> Result<MultiLs, ModalError> {
    assert_eq!(a.len(), m * ncol, "design size");
    assert_eq!(b.len(), m * nrhs, "right-hand side size");
    let a_m = MatRef::from_column_major_slice(a, m, ncol);
    let b_m = MatRef::from_column_major_slice(b, m, nrhs);
    let mut gram = Mat::<f64>::zeros(ncol, ncol);
    matmul(
        gram.as_mut(),
        Accum::Replace,
        a_m.transpose(),
        a_m,
        1.0,
        Par::Seq,
    );
    let mut x = vec![0.0; ncol * nrhs];
    matmul(
        MatMut::from_column_major_slice_mut(&mut x, ncol, nrhs),
        Accum::Replace,
        a_m.transpose(),
        b_m,
        1.0,
        Par::Seq,
    );
    crate::simd::clear_upper_vector_state();
    let g: Vec<f64> = (0..ncol * ncol)
        .map(|ij| gram[(ij / ncol, ij % ncol)])
        .collect();
    let l = cholesky(&g, ncol).map_err(|_| ModalError::Numerical {
        stage,
        detail: format!("{ncol}x{ncol} normal equations singular (coincident poles?)"),
    })?;
    // L L^T x = rhs for every column, in place.
    for col in x.chunks_mut(ncol) {
        cholesky_solve(&l, ncol, col);
    }
    let residual = want_residual.then(|| {
        let mut r = b.to_vec();
        matmul(
            MatMut::from_column_major_slice_mut(&mut r, m, nrhs),
            Accum::Add,
            a_m,
            MatRef::from_column_major_slice(&x, ncol, nrhs),
            -1.0,
            Par::Seq,
        );
        crate::simd::clear_upper_vector_state();
        r
    });
    Ok(MultiLs { x, residual })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recovers_exact_coefficients_and_orthogonal_residual() {
        // A: 50 x 3 polynomial basis; B: two columns, one exactly in the span, one not.
        let m = 50;
        let t: Vec<f64> = (0..m).map(|k| k as f64 / (m - 1) as f64).collect();
        let a: Vec<f64> = (0..3)
            .flat_map(|p| t.iter().map(move |x| x.powi(p)))
            .collect();
        let b: Vec<f64> = t
            .iter()
            .map(|x| 1.0 - 2.0 * x + 0.5 * x * x)
            .chain(t.iter().map(|x| (7.0 * x).sin()))
            .collect();
        let s = solve(&a, m, 3, &b, 2, true, "test").unwrap();
        assert!((s.x[0] - 1.0).abs() < 1e-12);
        assert!((s.x[1] + 2.0).abs() < 1e-12);
        assert!((s.x[2] - 0.5).abs() < 1e-12);
        let r = s.residual.unwrap();
        assert!(r[..m].iter().all(|v| v.abs() < 1e-12));
        // The second residual is orthogonal to every column of A.
        for p in 0..3 {
            let d: f64 = (0..m).map(|k| a[p * m + k] * r[m + k]).sum();
            assert!(d.abs() < 1e-10, "column {p}: {d}");
        }
    }
}

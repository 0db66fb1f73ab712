//! Least-squares complex-frequency (LSCF) pole estimation over all scan points at once.
//!
//! Common-denominator rational model in the z-domain basis `Omega_k = exp(-i omega_k dt)`,
//! `dt = 1/(2 f_hi)`:
//!
//! `H_o(omega_k) ~ B_o(Omega_k) / A(Omega_k)`, `A(Omega) = sum_{j=0}^{n} alpha_j Omega^j`,
//! `B_o(Omega) = sum_{j=0}^{n} beta_oj Omega^j`, real coefficients.
//!
//! Linearised equation error `w_o (B_o - H_o A)` per line, with per-point weight `w_o`
//! (default: inverse of the point's noise level, see [`Weighting`]). With
//! `X_o[k,j] = w_o Omega_k^j`, `Y_o[k,j] = -w_o H_ok Omega_k^j`, the real normal-equation blocks
//! `R_o = Re(X^H X)`, `S_o = Re(X^H Y)`, `T_o = Re(Y^H Y)` are Toeplitz, so they are built from
//! `2n+1` lag sums per point. Eliminating the numerators gives the reduced normal equations
//! (Guillaume et al. 2003; Peeters et al. 2004):
//!
//! `M alpha = 0`, `M = sum_o (T_o - S_o^T R_o^{-1} S_o)`, solved with `alpha_n = 1`.
//!
//! All model orders come from one factorisation: with `R = L L^T` at the highest order and
//! `G_o = L^{-1} S_o`, the order-`n` term `S_o^T R^{-1} S_o` is `sum_{k<=n} g_ok g_ok^T`
//! restricted to the leading `(n+1)` block (rows of a lower-triangular solve only depend on
//! leading rows), so the orders are accumulated row by row. The poles are the roots `z_r` of
//! `A`, `lambda_r = -ln(z_r)/dt`. For the stabilization diagram each pole also gets a shape
//! estimate `B_o(z_r)/w_o` (proportional to the residue, up to a factor common to all points),
//! with `beta_o = -R^{-1} S_o alpha`.
//!
//! Cost: the lag sums of all points, the whitened blocks `G_o`, the accumulation over orders
//! and the numerators of all orders are dense matrix products (faer), the roots of
//! consecutive orders are tracked by [`super::roots::poly_roots_from`]. About 5 ms per pass
//! for 77 points x 2000 lines up to order 60 on one core (`cargo bench --bench modal`).

use super::ModalError;
use faer::linalg::matmul::matmul;
use faer::linalg::matmul::triangular::BlockStructure;
use faer::{c64, Accum, Mat, MatMut, MatRef, Par};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// How each scan point is weighted in the LSCF equation error.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Weighting {
    /// `w_o = 1/sigma_o`, `sigma_o` the point's noise level estimated from first differences
    /// of its spectrum (robust median estimate, see [`noise_sigma`]). Noisy points weigh
    /// less; this approximates the maximum-likelihood weighting without repeated blocks.
    NoiseEstimate,
    /// `w_o = 1/rms(H_o)`: every point counts equally whatever its level.
    Rms,
    /// No weighting (`w_o = 1`).
    Unit,
}

/// Parameters of [`lscf_poles`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LscfParams {
    /// Lowest denominator degree (number of poles, both of each conjugate pair) evaluated.
    pub min_order: usize,
    /// Highest denominator degree. 60 resolves ~20–25 modes in the band with room for
    /// computational poles; raise it for wider bands with more modes.
    pub max_order: usize,
    /// Step between evaluated degrees. 2 (default) keeps conjugate pairs complete.
    pub order_step: usize,
    pub weighting: Weighting,
}

impl Default for LscfParams {
    fn default() -> Self {
        Self {
            min_order: 4,
            max_order: 60,
            order_step: 2,
            weighting: Weighting::NoiseEstimate,
        }
    }
}

/// One pole of one model order (only the member with `Im(lambda) > 0` of each pair).
#[derive(Debug, Clone, PartialEq)]
pub struct RawPole {
    /// Pole in rad/s.
    pub lambda: c64,
    /// `|lambda|/(2 pi)`, Hz.
    pub freq_hz: f64,
    /// `-Re(lambda)/|lambda|` (negative for unstable poles).
    pub damping_ratio: f64,
    /// Shape estimate at the used points, proportional to the residues.
    pub shape: Vec<c64>,
}

/// Poles of one model order.
#[derive(Debug, Clone, PartialEq)]
pub struct OrderPoles {
    pub order: usize,
    pub poles: Vec<RawPole>,
}

/// Noise level `sigma` (`E|n|^2 = sigma^2`) of one spectrum from its first differences:
/// for white complex noise `|n_{k+1} - n_k|^2` is exponential with mean `2 sigma^2`, whose
/// median is `2 ln2 sigma^2`. The median ignores the few lines where resonances make the
/// difference large, so the estimate is robust for smooth, well-resolved spectra.
pub fn noise_sigma(row: &[c64]) -> f64 {
    if row.len() < 3 {
        return 0.0;
    }
    let mut d: Vec<f64> = row.windows(2).map(|w| (w[1] - w[0]).norm_sqr()).collect();
    let mid = d.len() / 2;
    let (_, m, _) = d.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
    (*m / (2.0 * std::f64::consts::LN_2)).sqrt()
}

/// Dot product with eight independent partial sums, combined in a fixed order: breaks the
/// floating-point dependency chain (the compiler may not reassociate a plain sum) so the
/// loop vectorises, and stays bit-reproducible.
#[inline]
pub(crate) fn dot(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    let mut acc = [0.0f64; 8];
    let chunks = n / 8;
    for c in 0..chunks {
        let (x, y) = (&a[c * 8..c * 8 + 8], &b[c * 8..c * 8 + 8]);
        for l in 0..8 {
            acc[l] += x[l] * y[l];
        }
    }
    let mut tail = 0.0;
    for k in chunks * 8..n {
        tail += a[k] * b[k];
    }
    ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7])) + tail
}

/// In-place Cholesky `A = L L^T` of a small dense SPD matrix (row-major `n x n`), returning
/// `L` (lower, row-major). Hand-written because the LSCF needs the leading blocks of one
/// factor for every model order and the matrices are at most ~100x100; a relative diagonal
/// jitter is added if rounding makes the Toeplitz Gram matrix indefinite.
pub(crate) fn cholesky(a: &[f64], n: usize) -> Result<Vec<f64>, ModalError> {
    let trace = (0..n).map(|i| a[i * n + i]).sum::<f64>() / n.max(1) as f64;
    for jitter in [0.0, 1e-12, 1e-9, 1e-6] {
        let mut l = vec![0.0; n * n];
        let mut ok = true;
        'outer: for i in 0..n {
            for j in 0..=i {
                let mut s = a[i * n + j];
                if i == j {
                    s += jitter * trace;
                }
                for k in 0..j {
                    s -= l[i * n + k] * l[j * n + k];
                }
                if i == j {
                    if s.is_nan() || s <= 0.0 {
                        ok = false;
                        break 'outer;
                    }
                    l[i * n + i] = s.sqrt();
                } else {
                    l[i * n + j] = s / l[j * n + j];
                }
            }
        }
        if ok {
            return Ok(l);
        }
    }
    Err(ModalError::Numerical {
        stage: "lscf",
        detail: format!("basis Gram matrix of size {n} is not positive definite (band too narrow for the order?)"),
    })
}

/// The z-domain basis `Omega_k^m = exp(-i omega_k m dt)`, `m = 0..=max_order`, on one
/// frequency axis: depends only on the axis and the highest order, so [`super::extract`]
/// builds it once and reuses it for every LSCF pass of a measurement.
#[derive(Debug, Clone)]
pub struct LscfBasis {
    freq_hz: Vec<f64>,
    max_order: usize,
    dt: f64,
    /// `cos(-omega_k m dt)`, column-major `n_lines x (max_order + 1)`.
    e_re: Vec<f64>,
    /// `sin(-omega_k m dt)`, same layout.
    e_im: Vec<f64>,
}

impl LscfBasis {
    /// Basis for `freq_hz` (the band) up to `max_order`. The powers are built by complex
    /// multiplication from `Omega_k` (relative error below `max_order * 2^-52`), which is
    /// much cheaper than one `sin`/`cos` pair per entry.
    pub fn new(freq_hz: &[f64], max_order: usize) -> Self {
        let nf = freq_hz.len();
        let f_hi = freq_hz.last().copied().unwrap_or(1.0);
        let dt = 1.0 / (2.0 * f_hi);
        let n1 = max_order + 1;
        let mut e_re = vec![0.0; n1 * nf];
        let mut e_im = vec![0.0; n1 * nf];
        for (k, &f) in freq_hz.iter().enumerate() {
            let z1 = c64::from_polar(1.0, -2.0 * PI * f * dt);
            let mut z = c64::new(1.0, 0.0);
            for m in 0..n1 {
                e_re[m * nf + k] = z.re;
                e_im[m * nf + k] = z.im;
                z *= z1;
            }
        }
        Self {
            freq_hz: freq_hz.to_vec(),
            max_order,
            dt,
            e_re,
            e_im,
        }
    }

    fn e_re(&self) -> MatRef<'_, f64> {
        MatRef::from_column_major_slice(&self.e_re, self.freq_hz.len(), self.max_order + 1)
    }

    fn e_im(&self) -> MatRef<'_, f64> {
        MatRef::from_column_major_slice(&self.e_im, self.freq_hz.len(), self.max_order + 1)
    }
}

/// Solve `L L^T x = b` in place with the factor of [`cholesky`] (row-major `n x n`).
pub(crate) fn cholesky_solve(l: &[f64], n: usize, b: &mut [f64]) {
    for i in 0..n {
        b[i] = (b[i] - dot(&l[i * n..i * n + i], &b[..i])) / l[i * n + i];
    }
    for i in (0..n).rev() {
        let s: f64 = (i + 1..n).map(|k| l[k * n + i] * b[k]).sum();
        b[i] = (b[i] - s) / l[i * n + i];
    }
}

/// Estimate poles for every model order `min_order, min_order+step, ..., <= max_order`.
///
/// `h[o]` is the spectrum of used point `o` on `freq_hz` (the band). Returns one
/// [`OrderPoles`] per order with the poles whose frequency lies inside the band.
///
/// `line_weight`, if given, multiplies the equation error at each line (common to all
/// points, so the normal-equation blocks stay Toeplitz). [`sk_line_weights`] gives the
/// Sanathanan–Koerner weights that turn the linearised equation error into an approximate
/// output error.
pub fn lscf_poles(
    freq_hz: &[f64],
    h: &[&[c64]],
    line_weight: Option<&[f64]>,
    params: &LscfParams,
) -> Result<Vec<OrderPoles>, ModalError> {
    let weights = point_weights(h, params.weighting);
    lscf_poles_with(
        &LscfBasis::new(freq_hz, params.max_order),
        h,
        &weights,
        line_weight,
        params,
    )
}

fn check_orders(params: &LscfParams) -> Result<(), ModalError> {
    if params.min_order < 2 || params.min_order > params.max_order || params.order_step == 0 {
        return Err(ModalError::Orders {
            min: params.min_order,
            max: params.max_order,
            step: params.order_step,
        });
    }
    Ok(())
}

/// Weight of each point in the LSCF equation error (see [`Weighting`]).
pub fn point_weights(h: &[&[c64]], weighting: Weighting) -> Vec<f64> {
    h.iter()
        .map(|row| {
            let rms = super::frf::rms(row);
            match weighting {
                Weighting::Unit => 1.0,
                Weighting::Rms => 1.0 / rms.max(f64::MIN_POSITIVE),
                Weighting::NoiseEstimate => {
                    1.0 / noise_sigma(row).max(1e-6 * rms).max(f64::MIN_POSITIVE)
                }
            }
        })
        .collect()
}

/// [`lscf_poles`] with a prebuilt basis (`basis.max_order` must be at least
/// `params.max_order`; the axis is the basis's) and point weights from [`point_weights`]
/// (`params.weighting` is not consulted: the caller computes the weights once per set of
/// points and reuses them across passes).
///
/// Dense linear algebra is done with faer's sequential kernels (`Par::Seq`): the extract
/// stage already runs one measurement per core, and sequential kernels keep the result
/// independent of the thread count. Work per call, with `n1 = max_order + 1` and `P` points:
/// the lag sums are two `P x lines x n1` products, the whitened blocks `G_o = L^{-1} S_o`
/// one triangular solve with `P n1` right-hand sides, the reduced normal matrices of all
/// orders `n1` rank-`P` updates, and the numerators of all orders two more products.
pub fn lscf_poles_with(
    basis: &LscfBasis,
    h: &[&[c64]],
    weights: &[f64],
    line_weight: Option<&[f64]>,
    params: &LscfParams,
) -> Result<Vec<OrderPoles>, ModalError> {
    check_orders(params)?;
    let nmax = params.max_order;
    if nmax > basis.max_order {
        return Err(ModalError::Param {
            name: "max_order",
            expected: "at most the basis's highest order",
            found: format!("{nmax} > {}", basis.max_order),
        });
    }
    let nf = basis.freq_hz.len();
    let n1 = nmax + 1;
    let np = h.len();
    if let Some(row) = h.iter().find(|r| r.len() != nf) {
        return Err(ModalError::ShapeLength {
            context: "lscf spectra",
            expected: nf,
            found: row.len(),
        });
    }
    if let Some(lw) = line_weight {
        if lw.len() != nf || lw.iter().any(|w| !w.is_finite() || *w < 0.0) {
            return Err(ModalError::Param {
                name: "line_weight",
                expected: "one finite non-negative weight per line",
                found: format!("{} weights", lw.len()),
            });
        }
    }
    // Squared line weights: every lag sum carries them exactly once.
    let v2: Vec<f64> = match line_weight {
        Some(lw) => lw.iter().map(|w| w * w).collect(),
        None => vec![1.0; nf],
    };
    if weights.len() != np || weights.iter().any(|w| !w.is_finite() || *w <= 0.0) {
        return Err(ModalError::Param {
            name: "weights",
            expected: "one finite positive weight per point",
            found: format!("{} weights for {np} points", weights.len()),
        });
    }
    let (l_mat, l_inv) = whitening(basis, &v2, n1)?;
    let t_lag = t_lags(basis, h, weights, &v2, n1);
    let gp_buf = whitened_blocks(basis, h, weights, &v2, l_mat.as_ref(), n1);
    let rows = np * n1;
    let alphas = denominators(&gp_buf, &t_lag, params, np, n1)?;

    // Numerators: y_o = G_o alpha for all points and orders in one product. Viewed as an
    // n1 x (P n1) matrix, G' has entry (j, o + P i) = G_o[i, j], so
    // Y = G'_view^T A ((P n1) x orders) with Y[o + P i, c] = (G_o alpha_c)[i].
    let n_ord = alphas.len();
    let a_all = Mat::<f64>::from_fn(n1, n_ord, |j, c| alphas[c].1.get(j).copied().unwrap_or(0.0));
    let g_view = MatRef::from_column_major_slice(&gp_buf, n1, rows);
    let mut y_all = Mat::<f64>::zeros(rows, n_ord);
    matmul(
        y_all.as_mut(),
        Accum::Replace,
        g_view.transpose(),
        a_all.as_ref(),
        1.0,
        Par::Seq,
    );
    drop(gp_buf);
    crate::simd::clear_upper_vector_state();

    // Roots of every order, each started from the roots of the previous order (sequential:
    // the polynomials of consecutive orders share most of their roots).
    let mut all_roots: Vec<Vec<c64>> = Vec::with_capacity(alphas.len());
    let mut prev: Vec<c64> = Vec::new();
    for (n, alpha) in &alphas {
        let roots =
            super::roots::poly_roots_from(alpha, &prev).ok_or_else(|| ModalError::Numerical {
                stage: "lscf polynomial roots",
                detail: format!("no root-finder converged at order {n}"),
            })?;
        prev.clone_from(&roots);
        all_roots.push(roots);
    }

    // Shape estimates per order (in parallel, collected in order).
    alphas
        .par_iter()
        .zip(all_roots)
        .enumerate()
        .map(|(c, ((n, _), roots))| {
            let col = y_all.col(c).try_as_col_major().expect("contiguous");
            order_poles(
                *n,
                roots,
                col.as_slice(),
                l_inv.as_ref(),
                weights,
                basis,
                n1,
            )
        })
        .collect()
}

/// The Cholesky factor L of the lag matrix R (r_m = Re sum_k v_k^2 E^m, `v2` the squared
/// line weights) of orders up to `n1 - 1`, and its inverse.
fn whitening(basis: &LscfBasis, v2: &[f64], n1: usize) -> Result<(Mat<f64>, Mat<f64>), ModalError> {
    let nf = basis.freq_hz.len();
    // R (common to all points up to w_o^2, which is folded into H): r_m = Re sum_k v_k^2 E^m.
    let r_lag: Vec<f64> = (0..n1)
        .map(|m| dot(&basis.e_re[m * nf..(m + 1) * nf], v2))
        .collect();
    let mut r = vec![0.0; n1 * n1];
    for i in 0..n1 {
        for j in 0..n1 {
            r[i * n1 + j] = r_lag[i.abs_diff(j)];
        }
    }
    let l = cholesky(&r, n1)?;
    // L as a faer matrix and the inverse of L (lower), whose leading blocks are the inverses
    // of the leading blocks of L.
    let l_mat = Mat::<f64>::from_fn(n1, n1, |i, j| l[i * n1 + j]);
    let mut l_inv = Mat::<f64>::identity(n1, n1);
    faer::linalg::triangular_solve::solve_lower_triangular_in_place(
        l_mat.as_ref(),
        l_inv.as_mut(),
        Par::Seq,
    );
    crate::simd::clear_upper_vector_state();
    Ok((l_mat, l_inv))
}

/// The lags of T summed over points.
fn t_lags(basis: &LscfBasis, h: &[&[c64]], weights: &[f64], v2: &[f64], n1: usize) -> Vec<f64> {
    let nf = basis.freq_hz.len();
    // T summed over points: t_m = Re sum_k v_k^2 (sum_o w_o^2 |H_ok|^2) E^m.
    let mut pow_sum = vec![0.0; nf];
    for (row, w) in h.iter().zip(weights) {
        for (p, v) in pow_sum.iter_mut().zip(row.iter()) {
            *p += w * w * v.norm_sqr();
        }
    }
    for (p, v) in pow_sum.iter_mut().zip(v2) {
        *p *= v;
    }
    (0..n1)
        .map(|m| dot(&basis.e_re[m * nf..(m + 1) * nf], &pow_sum))
        .collect()
}

/// G' = S' L^{-T}, column-major (P n1) x n1: block o holds G_o^T with G_o = L^{-1} S_o, S_o
/// the lag sums of point o.
fn whitened_blocks(
    basis: &LscfBasis,
    h: &[&[c64]],
    weights: &[f64],
    v2: &[f64],
    l_mat: MatRef<'_, f64>,
    n1: usize,
) -> Vec<f64> {
    let nf = basis.freq_hz.len();
    let np = h.len();
    let e_re = basis.e_re().subcols(0, n1);
    let e_im = basis.e_im().subcols(0, n1);
    // Lag sums s_m = sum_k w_o v_k^2 H_ok E^m of every point: with the weighted data as
    // columns (lines x points), Re s_{+m} = p - q and Re s_{-m} = p + q with p = X_re^T E_re,
    // q = X_im^T E_im (points x n1).
    let mut pm = vec![0.0; np * n1];
    let mut qm = vec![0.0; np * n1];
    for (out, im_part, e) in [(&mut pm, false, e_re), (&mut qm, true, e_im)] {
        let x = Mat::<f64>::from_fn(nf, np, |k, o| {
            let v = h[o][k];
            weights[o] * v2[k] * if im_part { v.im } else { v.re }
        });
        matmul(
            MatMut::from_column_major_slice_mut(out, np, n1),
            Accum::Replace,
            x.transpose(),
            e,
            1.0,
            Par::Seq,
        );
    }
    crate::simd::clear_upper_vector_state();
    // Re s_{+m} and Re s_{-m} per point, row-major points x n1.
    let mut s_pos = vec![0.0; np * n1];
    let mut s_neg = vec![0.0; np * n1];
    for o in 0..np {
        for m in 0..n1 {
            let (p, q) = (pm[o + np * m], qm[o + np * m]);
            s_pos[o * n1 + m] = p - q;
            s_neg[o * n1 + m] = p + q;
        }
    }
    drop((pm, qm));

    // S'_o = S_o^T stacked over points ((P n1) x n1, column-major), with
    // S_o[i,j] = -Re s_{j-i}; then G' = S' L^{-T}, i.e. block o of G' is G_o^T with
    // G_o = L^{-1} S_o. Column k of G' holds row k of every G_o, contiguous.
    let rows = np * n1;
    let mut gp_buf = vec![0.0; rows * n1];
    for (i, col) in gp_buf.chunks_mut(rows).enumerate() {
        for (o, blk) in col.chunks_mut(n1).enumerate() {
            let (sp, sn) = (&s_pos[o * n1..(o + 1) * n1], &s_neg[o * n1..(o + 1) * n1]);
            let (below, above) = blk.split_at_mut(i);
            // j < i: -Re s_{-(i-j)}; j >= i: -Re s_{j-i}.
            for (j, v) in below.iter_mut().enumerate() {
                *v = -sn[i - j];
            }
            for (v, s) in above.iter_mut().zip(sp) {
                *v = -s;
            }
        }
    }
    let gp = MatMut::from_column_major_slice_mut(&mut gp_buf, rows, n1);
    faer::linalg::triangular_solve::solve_lower_triangular_in_place(
        l_mat,
        gp.transpose_mut(),
        Par::Seq,
    );
    crate::simd::clear_upper_vector_state();
    gp_buf
}

/// The denominators (alpha, highest coefficient 1) of the orders `params` asks for, from the
/// whitened blocks `gp_slice` and the lags of T.
fn denominators(
    gp_slice: &[f64],
    t_lag: &[f64],
    params: &LscfParams,
    np: usize,
    n1: usize,
) -> Result<Vec<(usize, Vec<f64>)>, ModalError> {
    let nmax = params.max_order;
    let rows = np * n1;
    // Denominators of all orders (sequential: P accumulates row by row). Rows k of all
    // G_o, viewed as an n1 x P matrix W_k (column k of G'), add W_k W_k^T.
    let mut pacc = Mat::<f64>::zeros(n1, n1);
    let mut rows_done = 0usize;
    let mut alphas: Vec<(usize, Vec<f64>)> = Vec::new();
    let mut n = params.min_order;
    while n <= nmax {
        let wb = MatRef::from_column_major_slice(
            &gp_slice[rows_done * rows..(n + 1) * rows],
            n1,
            np * (n + 1 - rows_done),
        );
        // Symmetric: only the lower triangle is accumulated (and read below).
        faer::linalg::matmul::triangular::matmul(
            pacc.as_mut(),
            BlockStructure::TriangularLower,
            Accum::Add,
            wb,
            BlockStructure::Rectangular,
            wb.transpose(),
            BlockStructure::Rectangular,
            1.0,
            Par::Seq,
        );
        rows_done = n + 1;
        // M = T - P on the leading (n+1) block; solve M[:n,:n] a = -M[:n,n].
        let mm = |i: usize, j: usize| t_lag[i.abs_diff(j)] - pacc[(i.max(j), i.min(j))];
        let a_mat = Mat::<f64>::from_fn(n, n, &mm);
        let rhs = Mat::<f64>::from_fn(n, 1, |i, _| -mm(i, n));
        let sol = solve_small(&a_mat, &rhs)?;
        crate::simd::clear_upper_vector_state();
        let mut alpha: Vec<f64> = (0..n).map(|i| sol[(i, 0)]).collect();
        alpha.push(1.0);
        if alpha.iter().all(|v| v.is_finite()) {
            alphas.push((n, alpha));
        }
        n += params.order_step;
    }
    Ok(alphas)
}

/// The poles of order `n` from its denominator's `roots`, with shapes from the numerators
/// `y_col` (Y's column of this order) of every point.
fn order_poles(
    n: usize,
    roots: Vec<c64>,
    y_col: &[f64],
    l_inv: MatRef<'_, f64>,
    weights: &[f64],
    basis: &LscfBasis,
    n1: usize,
) -> Result<OrderPoles, ModalError> {
    let np = weights.len();
    let dt = basis.dt;
    let f_lo = basis.freq_hz[0];
    let f_hi = basis.freq_hz[basis.freq_hz.len() - 1];
    let mut lambdas = Vec::new();
    for z in roots {
        if z.norm_sqr() == 0.0 || !z.re.is_finite() || !z.im.is_finite() {
            continue;
        }
        let lam = -z.ln() / dt;
        if lam.im <= 0.0 {
            continue;
        }
        let f = lam.norm() / (2.0 * PI);
        if f < f_lo || f > f_hi {
            continue;
        }
        lambdas.push((lam, z));
    }
    let nz = lambdas.len();
    let mut shapes = vec![Vec::with_capacity(np); nz];
    if nz > 0 {
        // beta_o = -L_n^{-T} y_o on the leading block, for all points at once:
        // B (P x (n+1)) = -Y_c L_n^{-1}, Y_c[o, i] = Y[o + P i, c].
        let y_c = MatRef::from_column_major_slice(y_col, np, n1).subcols(0, n + 1);
        let mut b = Mat::<f64>::zeros(np, n + 1);
        matmul(
            b.as_mut(),
            Accum::Replace,
            y_c,
            l_inv.submatrix(0, 0, n + 1, n + 1),
            -1.0,
            Par::Seq,
        );
        // B_o(z_r) = sum_j beta_oj z_r^j: products with the Vandermonde matrix.
        let mut v_re = Mat::<f64>::zeros(n + 1, nz);
        let mut v_im = Mat::<f64>::zeros(n + 1, nz);
        for (r, (_, z)) in lambdas.iter().enumerate() {
            let mut zp = c64::new(1.0, 0.0);
            for j in 0..=n {
                v_re[(j, r)] = zp.re;
                v_im[(j, r)] = zp.im;
                zp *= z;
            }
        }
        let mut s_re = Mat::<f64>::zeros(np, nz);
        let mut s_im = Mat::<f64>::zeros(np, nz);
        matmul(
            s_re.as_mut(),
            Accum::Replace,
            b.as_ref(),
            v_re.as_ref(),
            1.0,
            Par::Seq,
        );
        matmul(
            s_im.as_mut(),
            Accum::Replace,
            b.as_ref(),
            v_im.as_ref(),
            1.0,
            Par::Seq,
        );
        crate::simd::clear_upper_vector_state();
        for (r, sh) in shapes.iter_mut().enumerate() {
            for (o, &w) in weights.iter().enumerate() {
                sh.push(c64::new(s_re[(o, r)], s_im[(o, r)]) / w);
            }
        }
    }
    let mut poles: Vec<RawPole> = lambdas
        .into_iter()
        .zip(shapes)
        .map(|((lam, _), shape)| RawPole {
            lambda: lam,
            freq_hz: lam.norm() / (2.0 * PI),
            damping_ratio: -lam.re / lam.norm(),
            shape,
        })
        .collect();
    poles.sort_by(|a, b| a.freq_hz.total_cmp(&b.freq_hz));
    Ok(OrderPoles { order: n, poles })
}

/// Sanathanan–Koerner line weights `v_k = 1/|A(Omega_k)|` from a set of poles (rad/s,
/// `Im > 0`), with `A(Omega) = prod_r (Omega - z_r)(Omega - conj z_r)`, `z_r = exp(-lambda_r dt)`
/// and `dt = 1/(2 f_hi)` as in [`lscf_poles`]; normalised to a maximum of 1. Weighting the
/// equation error `B - H A` by `1/|A_prev|` approximates the output error `B/A - H`, which
/// removes most of the bias of the linearised estimator near resonances (it is what lets
/// two modes closer than their half-power bandwidth come out as two poles).
pub fn sk_line_weights(freq_hz: &[f64], poles: &[c64]) -> Vec<f64> {
    let f_hi = freq_hz.last().copied().unwrap_or(1.0);
    let dt = 1.0 / (2.0 * f_hi);
    let zs: Vec<c64> = poles.iter().map(|l| (-*l * dt).exp()).collect();
    let logs: Vec<f64> = freq_hz
        .iter()
        .map(|&f| {
            let om = c64::from_polar(1.0, -2.0 * PI * f * dt);
            -zs.iter()
                .map(|z| 0.5 * ((om - z).norm_sqr().ln() + (om - z.conj()).norm_sqr().ln()))
                .sum::<f64>()
        })
        .collect();
    let mx = logs.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    logs.iter().map(|l| (l - mx).exp()).collect()
}

/// Solve a small dense square system with faer's partial-pivoting LU.
fn solve_small(a: &Mat<f64>, b: &Mat<f64>) -> Result<Mat<f64>, ModalError> {
    use faer::linalg::solvers::Solve;
    let x = a.partial_piv_lu().solve(b);
    Ok(x)
}

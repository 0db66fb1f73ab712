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

use super::ModalError;
use faer::{c64, Mat};
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
    let nmax = params.max_order;
    if params.min_order < 2 || params.min_order > nmax || params.order_step == 0 {
        return Err(ModalError::Orders {
            min: params.min_order,
            max: nmax,
            step: params.order_step,
        });
    }
    let nf = freq_hz.len();
    let f_lo = freq_hz[0];
    let f_hi = freq_hz[nf - 1];
    let dt = 1.0 / (2.0 * f_hi);
    let n1 = nmax + 1;

    if let Some(lw) = line_weight {
        if lw.len() != nf || lw.iter().any(|w| !w.is_finite() || *w < 0.0) {
            return Err(ModalError::Param {
                name: "line_weight",
                expected: "one finite non-negative weight per line",
                found: format!("{} weights", lw.len()),
            });
        }
    }
    // Weighted basis powers E[m][k] = v_k^2 exp(-i omega_k m dt), m = 0..=nmax, with the
    // squared line weight folded in (every lag sum carries it exactly once).
    // Stored as separate real and imaginary tables for vectorised dot products.
    let mut e_re = vec![0.0; n1 * nf];
    let mut e_im = vec![0.0; n1 * nf];
    for m in 0..n1 {
        for k in 0..nf {
            let ph = -2.0 * PI * freq_hz[k] * m as f64 * dt;
            let v2 = line_weight.map_or(1.0, |lw| lw[k] * lw[k]);
            e_re[m * nf + k] = v2 * ph.cos();
            e_im[m * nf + k] = v2 * ph.sin();
        }
    }
    // Weights.
    let weights: Vec<f64> = h
        .iter()
        .map(|row| {
            let rms = super::frf::rms(row);
            match params.weighting {
                Weighting::Unit => 1.0,
                Weighting::Rms => 1.0 / rms.max(f64::MIN_POSITIVE),
                Weighting::NoiseEstimate => {
                    1.0 / noise_sigma(row).max(1e-6 * rms).max(f64::MIN_POSITIVE)
                }
            }
        })
        .collect();

    // R (common to all points up to w_o^2, which is folded into H): Re c_m.
    let mut r_lag = vec![0.0; n1];
    for (m, rl) in r_lag.iter_mut().enumerate() {
        *rl = e_re[m * nf..(m + 1) * nf].iter().sum();
    }
    let mut r = vec![0.0; n1 * n1];
    for i in 0..n1 {
        for j in 0..n1 {
            r[i * n1 + j] = r_lag[i.abs_diff(j)];
        }
    }
    let l = cholesky(&r, n1)?;
    let mut lt = vec![0.0; n1 * n1]; // L^T, row-major, for contiguous back substitution
    for i in 0..n1 {
        for j in 0..=i {
            lt[j * n1 + i] = l[i * n1 + j];
        }
    }

    // T summed over points: Re t_m, t_m = sum_k (sum_o w_o^2 |H_ok|^2) E[m][k].
    let mut pow_sum = vec![0.0; nf];
    for (row, w) in h.iter().zip(&weights) {
        for (p, v) in pow_sum.iter_mut().zip(row.iter()) {
            *p += w * w * v.norm_sqr();
        }
    }
    let t_lag: Vec<f64> = (0..n1)
        .map(|m| dot(&e_re[m * nf..(m + 1) * nf], &pow_sum))
        .collect();

    // G_o = L^{-1} S_o for every point, S_o[i,j] = -Re s_{j-i}, s_m = sum_k w H_k E^m.
    // Per point (in parallel: independent, each computed sequentially, collected in order,
    // so the result does not depend on the thread count).
    let g_all: Vec<Vec<f64>> = h
        .par_iter()
        .zip(weights.par_iter())
        .map(|(row, &w)| {
            let h_re: Vec<f64> = row.iter().map(|v| v.re).collect();
            let h_im: Vec<f64> = row.iter().map(|v| v.im).collect();
            let mut s_pos = vec![0.0; n1]; // Re s_m, m >= 0
            let mut s_neg = vec![0.0; n1]; // Re s_{-m}
            for m in 0..n1 {
                // Re(H E^m) = p - q and Re(H conj(E^m)) = p + q.
                let p = dot(&h_re, &e_re[m * nf..(m + 1) * nf]);
                let q = dot(&h_im, &e_im[m * nf..(m + 1) * nf]);
                s_pos[m] = w * (p - q);
                s_neg[m] = w * (p + q);
            }
            let mut g = vec![0.0; n1 * n1];
            for i in 0..n1 {
                for j in 0..n1 {
                    let s = if j >= i { s_pos[j - i] } else { s_neg[i - j] };
                    g[i * n1 + j] = -s;
                }
            }
            // Forward substitution L G = S (row-major, row by row).
            for i in 0..n1 {
                let (done, rest) = g.split_at_mut(i * n1);
                let gi = &mut rest[..n1];
                for k in 0..i {
                    let lik = l[i * n1 + k];
                    if lik != 0.0 {
                        for (a, b) in gi.iter_mut().zip(&done[k * n1..(k + 1) * n1]) {
                            *a -= lik * b;
                        }
                    }
                }
                let d = l[i * n1 + i];
                for a in gi.iter_mut() {
                    *a /= d;
                }
            }
            g
        })
        .collect();

    // Denominators of all orders (sequential: P accumulates row by row).
    let mut p = vec![0.0; n1 * n1]; // upper triangle of sum_o sum_{k<=n} g_ok g_ok^T
    let mut rows_done = 0usize;
    let mut alphas: Vec<(usize, Vec<f64>)> = Vec::new();
    let mut n = params.min_order;
    while n <= nmax {
        for k in rows_done..=n {
            for g in &g_all {
                let gk = &g[k * n1..(k + 1) * n1];
                for i in 0..=nmax {
                    let gi = gk[i];
                    if gi == 0.0 {
                        continue;
                    }
                    for (pj, gj) in p[i * n1 + i..(i + 1) * n1].iter_mut().zip(&gk[i..]) {
                        *pj += gi * gj;
                    }
                }
            }
        }
        rows_done = n + 1;
        // M = T - P on the leading (n+1) block; solve M[:n,:n] a = -M[:n,n].
        let mm = |i: usize, j: usize| t_lag[i.abs_diff(j)] - p[i.min(j) * n1 + i.max(j)];
        let a_mat = Mat::<f64>::from_fn(n, n, &mm);
        let rhs = Mat::<f64>::from_fn(n, 1, |i, _| -mm(i, n));
        let sol = solve_small(&a_mat, &rhs)?;
        let mut alpha: Vec<f64> = (0..n).map(|i| sol[(i, 0)]).collect();
        alpha.push(1.0);
        if alpha.iter().all(|v| v.is_finite()) {
            alphas.push((n, alpha));
        }
        n += params.order_step;
    }

    // Roots and shape estimates per order (in parallel, collected in order).
    alphas
        .par_iter()
        .map(|(n, alpha)| {
            let n = *n;
            // Companion matrix of the monic polynomial.
            let comp = Mat::<f64>::from_fn(n, n, |i, j| {
                if i == 0 {
                    -alpha[n - 1 - j]
                } else if i == j + 1 {
                    1.0
                } else {
                    0.0
                }
            });
            let roots = comp.eigenvalues().map_err(|e| ModalError::Numerical {
                stage: "lscf companion eigenvalues",
                detail: format!("{e:?} at order {n}"),
            })?;
            let mut lambdas = Vec::new();
            for z in roots {
                if z.norm() == 0.0 || !z.re.is_finite() || !z.im.is_finite() {
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
            // Numerator coefficients beta_o = -L^{-T} (G_o alpha) on the leading block.
            let mut shapes = vec![Vec::with_capacity(h.len()); lambdas.len()];
            if !lambdas.is_empty() {
                let mut y = vec![0.0; n + 1];
                let mut beta = vec![0.0; n + 1];
                for (g, &w) in g_all.iter().zip(&weights) {
                    for (i, yi) in y.iter_mut().enumerate() {
                        *yi = dot(&g[i * n1..i * n1 + n + 1], alpha);
                    }
                    // Back substitution L_n^T beta = -y.
                    for i in (0..=n).rev() {
                        let s = -y[i] - dot(&lt[i * n1 + i + 1..i * n1 + n + 1], &beta[i + 1..=n]);
                        beta[i] = s / lt[i * n1 + i];
                    }
                    for (sh, (_, z)) in shapes.iter_mut().zip(&lambdas) {
                        // Horner in z.
                        let mut acc = c64::new(0.0, 0.0);
                        for j in (0..=n).rev() {
                            acc = acc * z + beta[j];
                        }
                        sh.push(acc / w);
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
        })
        .collect()
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
                .map(|z| (om - z).norm().ln() + (om - z.conj()).norm().ln())
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

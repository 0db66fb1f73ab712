//! Local output-error refinement of the selected poles (the last step before LSFD).
//!
//! The LSCF is a linearised (equation-error) estimator: at low signal-to-noise its damping
//! estimates are biased. Here each pole (or group of poles whose bands overlap) is refined by
//! minimising the weighted output error over the lines around it, with the residues
//! eliminated (variable projection):
//!
//! `min_theta  sum_o w_o^2 || h_o - A(theta) x_o(theta) ||^2`,  `x_o = argmin ||h_o - A x||`,
//!
//! where `theta = (f_i, zeta_i)` of the group's poles, `A` holds for each pole the columns
//! `g1 + g2`, `i (g1 - g2)` (`g1 = 1/(i omega - lambda)`, `g2` its conjugate pole) and four local
//! residual columns `1, i, u, i u` with `u = (omega - omega_c)/omega_c` (everything outside the
//! group is smooth across the small band), real and imaginary parts stacked. `w_o = 1/sigma_o`
//! (noise level of the point), which makes this the maximum-likelihood estimate for white
//! noise. Levenberg–Marquardt with a forward-difference Jacobian; a refinement is kept only if
//! it lowers the cost and stays within `max_rel_freq_change` and a factor `max_damping_factor`
//! of the starting pole (otherwise the LSCF pole stands).

use super::frf::pole;
use super::linls;
use super::lscf::{cholesky, dot};
use faer::c64;
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// Parameters of [`refine_poles`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RefineParams {
    /// Half-width of the local band in half-power bandwidths `zeta f` (default 8: the
    /// resonance and its skirts, where the pole is observable).
    pub half_bandwidths: f64,
    /// Minimum number of lines on each side of a pole (default 6), for poles narrower than
    /// the line spacing.
    pub min_lines_each_side: usize,
    /// Levenberg–Marquardt iterations (default 10; it usually stops after 2–4).
    pub max_iter: usize,
    /// Largest accepted relative frequency change (default 0.01).
    pub max_rel_freq_change: f64,
    /// Largest accepted damping change factor (default 2).
    pub max_damping_factor: f64,
}

impl Default for RefineParams {
    fn default() -> Self {
        Self {
            half_bandwidths: 8.0,
            min_lines_each_side: 6,
            max_iter: 10,
            max_rel_freq_change: 0.01,
            max_damping_factor: 2.0,
        }
    }
}

/// Problem data of one group: band lines, stacked weighted data per point.
struct Group {
    omega: Vec<f64>,
    omega_c: f64,
    /// Weighted data, column-major `2 lines x points`: column `o` holds the real parts of
    /// point `o` over the band, then the imaginary parts.
    b: Vec<f64>,
    n_points: usize,
}

impl Group {
    /// Design (real/imag stacked, column-major `2 lines x ncol`, unit-norm columns) for
    /// poles `(f_hz, zeta)`.
    fn design(&self, theta: &[f64]) -> (Vec<f64>, usize) {
        let nl = self.omega.len();
        let m = 2 * nl;
        let ncol = theta.len() + 4;
        let mut a = vec![0.0; m * ncol];
        for (p, pc) in theta.chunks(2).enumerate() {
            let lam = pole(pc[0], pc[1]);
            let (ca, cb) = a[2 * p * m..(2 * p + 2) * m].split_at_mut(m);
            for (k, &w) in self.omega.iter().enumerate() {
                let s = c64::new(0.0, w);
                let g1 = (s - lam).inv();
                let g2 = (s - lam.conj()).inv();
                let x = g1 + g2;
                let y = (g1 - g2) * c64::new(0.0, 1.0);
                ca[k] = x.re;
                ca[nl + k] = x.im;
                cb[k] = y.re;
                cb[nl + k] = y.im;
            }
        }
        // Local residual columns 1, i, u, i u.
        let base = theta.len() * m;
        for (k, &w) in self.omega.iter().enumerate() {
            let u = (w - self.omega_c) / self.omega_c;
            a[base + k] = 1.0;
            a[base + m + nl + k] = 1.0;
            a[base + 2 * m + k] = u;
            a[base + 3 * m + nl + k] = u;
        }
        // Unit-norm columns for conditioning.
        for c in a.chunks_mut(m) {
            let n = dot(c, c).sqrt();
            if n > 0.0 {
                c.iter_mut().for_each(|v| *v /= n);
            }
        }
        (a, ncol)
    }

    /// Stacked projected residuals of all points (None if the design is singular).
    fn residuals(&self, theta: &[f64]) -> Option<Vec<f64>> {
        let (a, ncol) = self.design(theta);
        let m = 2 * self.omega.len();
        linls::solve(&a, m, ncol, &self.b, self.n_points, true, "refine")
            .ok()?
            .residual
    }
}

/// Refine poles (rad/s, `Im > 0`, sorted or not) against the spectra `h[point]` on `freq_hz`
/// with per-point weights `weights[point]` (`1/sigma_o`). Returns the refined poles in the
/// input order; poles whose refinement fails or is rejected are returned unchanged.
pub fn refine_poles(
    freq_hz: &[f64],
    h: &[&[c64]],
    weights: &[f64],
    lambdas: &[c64],
    params: &RefineParams,
) -> Vec<c64> {
    let nf = freq_hz.len();
    if nf < 3 || h.is_empty() || lambdas.is_empty() {
        return lambdas.to_vec();
    }
    let df = (freq_hz[nf - 1] - freq_hz[0]) / (nf - 1) as f64;
    // Band of each pole in Hz.
    let fz: Vec<(f64, f64)> = lambdas
        .iter()
        .map(|l| (l.norm() / (2.0 * PI), -l.re / l.norm()))
        .collect();
    let bands: Vec<(f64, f64)> = fz
        .iter()
        .map(|&(f, z)| {
            let half = (params.half_bandwidths * z * f).max(params.min_lines_each_side as f64 * df);
            (f - half, f + half)
        })
        .collect();
    // Group poles with overlapping bands (in frequency order).
    let mut order: Vec<usize> = (0..lambdas.len()).collect();
    order.sort_by(|&a, &b| fz[a].0.total_cmp(&fz[b].0));
    let mut groups: Vec<Vec<usize>> = Vec::new();
    let mut hi = f64::NEG_INFINITY;
    for &i in &order {
        if bands[i].0 <= hi {
            groups.last_mut().expect("a group exists").push(i);
        } else {
            groups.push(vec![i]);
        }
        hi = hi.max(bands[i].1);
    }
    let mut out = lambdas.to_vec();
    for g in groups {
        let lo = g.iter().map(|&i| bands[i].0).fold(f64::INFINITY, f64::min);
        let hi = g
            .iter()
            .map(|&i| bands[i].1)
            .fold(f64::NEG_INFINITY, f64::max);
        let idx: Vec<usize> = (0..nf)
            .filter(|&k| freq_hz[k] >= lo && freq_hz[k] <= hi)
            .collect();
        let ncol = 2 * g.len() + 4;
        if idx.len() < ncol + 2 {
            continue;
        }
        let omega: Vec<f64> = idx.iter().map(|&k| 2.0 * PI * freq_hz[k]).collect();
        let omega_c = 0.5 * (omega[0] + omega[omega.len() - 1]);
        let b: Vec<f64> = h
            .iter()
            .zip(weights)
            .flat_map(|(row, &w)| {
                idx.iter()
                    .map(move |&k| w * row[k].re)
                    .chain(idx.iter().map(move |&k| w * row[k].im))
            })
            .collect();
        let grp = Group {
            omega,
            omega_c,
            b,
            n_points: h.len(),
        };
        let theta0: Vec<f64> = g.iter().flat_map(|&i| [fz[i].0, fz[i].1]).collect();
        if let Some(theta) = levenberg_marquardt(&grp, &theta0, params) {
            let ok = theta.chunks(2).zip(theta0.chunks(2)).all(|(t, t0)| {
                (t[0] / t0[0] - 1.0).abs() <= params.max_rel_freq_change
                    && t[1] > 0.0
                    && t[1] / t0[1] <= params.max_damping_factor
                    && t0[1] / t[1] <= params.max_damping_factor
            });
            if ok {
                for (j, &i) in g.iter().enumerate() {
                    out[i] = pole(theta[2 * j], theta[2 * j + 1]);
                }
            }
        }
    }
    out
}

/// Levenberg–Marquardt on `theta = (f_1, zeta_1, ...)` with a forward-difference Jacobian.
/// Returns `None` if the starting point cannot be evaluated or nothing improved.
fn levenberg_marquardt(grp: &Group, theta0: &[f64], params: &RefineParams) -> Option<Vec<f64>> {
    let np = theta0.len();
    let mut theta = theta0.to_vec();
    let mut r = grp.residuals(&theta)?;
    let mut cost = dot(&r, &r);
    let cost0 = cost;
    let mut mu = 1e-3;
    for _ in 0..params.max_iter {
        // Jacobian columns.
        let mut jac: Vec<Vec<f64>> = Vec::with_capacity(np);
        for p in 0..np {
            let step = if p % 2 == 0 {
                1e-7 * theta[p]
            } else {
                1e-5 * theta[p]
            };
            let mut t = theta.clone();
            t[p] += step;
            let rp = grp.residuals(&t)?;
            jac.push(rp.iter().zip(&r).map(|(a, b)| (a - b) / step).collect());
        }
        let jtj: Vec<f64> = (0..np * np)
            .map(|ij| dot(&jac[ij / np], &jac[ij % np]))
            .collect();
        let jtr: Vec<f64> = jac.iter().map(|c| dot(c, &r)).collect();
        let mut improved = false;
        for _ in 0..8 {
            let mut a = jtj.clone();
            for i in 0..np {
                a[i * np + i] *= 1.0 + mu;
            }
            let Ok(l) = cholesky(&a, np) else {
                mu *= 10.0;
                continue;
            };
            let mut y = vec![0.0; np];
            for i in 0..np {
                y[i] = (-jtr[i] - dot(&l[i * np..i * np + i], &y[..i])) / l[i * np + i];
            }
            let mut d = vec![0.0; np];
            for i in (0..np).rev() {
                let s: f64 = (i + 1..np).map(|k| l[k * np + i] * d[k]).sum();
                d[i] = (y[i] - s) / l[i * np + i];
            }
            let t: Vec<f64> = theta.iter().zip(&d).map(|(a, b)| a + b).collect();
            if t.chunks(2)
                .any(|p| !(p[0] > 0.0 && p[1] > 0.0 && p[1] < 1.0))
            {
                mu *= 10.0;
                continue;
            }
            if let Some(rt) = grp.residuals(&t) {
                let ct = dot(&rt, &rt);
                if ct < cost {
                    let rel = (cost - ct) / cost;
                    theta = t;
                    r = rt;
                    cost = ct;
                    mu = (mu / 3.0).max(1e-9);
                    improved = true;
                    // A relative cost decrease of 1e-6 is a parameter change far below its
                    // statistical uncertainty (which moves the cost by ~1/n_residuals).
                    if rel < 1e-6 {
                        return Some(theta);
                    }
                    break;
                }
            }
            mu *= 10.0;
        }
        if !improved {
            break;
        }
    }
    (cost < cost0).then_some(theta)
}

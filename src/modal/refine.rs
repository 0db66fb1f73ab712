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
//! noise. Levenberg–Marquardt with the variable-projection Jacobian in Kaufman's form
//! (Kaufman 1975; Golub & Pereyra 2003): `J_p = -P_perp (dA/dtheta_p) X`, analytic in the pole
//! parameters and rank two per parameter, so its normal matrix costs a few inner products
//! instead of one residual evaluation per parameter. A refinement is kept only if it lowers
//! the cost and stays within `max_rel_freq_change` and a factor `max_damping_factor` of the
//! starting pole (otherwise the LSCF pole stands).

use super::frf::pole;
use super::linls;
use super::lscf::{cholesky, cholesky_solve, dot};
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

/// The variable-projection problem evaluated at one `theta`.
struct Eval {
    /// Design with unit-norm columns, column-major `m x ncol`.
    a: Vec<f64>,
    ncol: usize,
    /// Norms of the design columns before scaling.
    norms: Vec<f64>,
    /// Coefficients of the scaled columns, column-major `ncol x points`.
    x: Vec<f64>,
    /// Residual `B - A X`, column-major `m x points`.
    r: Vec<f64>,
    cost: f64,
}

impl Group {
    fn m(&self) -> usize {
        2 * self.omega.len()
    }

    /// Design (real/imag stacked, column-major `2 lines x ncol`, unit-norm columns) for
    /// poles `(f_hz, zeta)`, and the column norms before scaling.
    fn design(&self, theta: &[f64]) -> (Vec<f64>, usize, Vec<f64>) {
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
        let mut norms = Vec::with_capacity(ncol);
        for c in a.chunks_mut(m) {
            let n = dot(c, c).sqrt();
            if n > 0.0 {
                c.iter_mut().for_each(|v| *v /= n);
            }
            norms.push(n);
        }
        (a, ncol, norms)
    }

    /// Residuals and coefficients at `theta` (None if the design is singular).
    fn eval(&self, theta: &[f64]) -> Option<Eval> {
        let (a, ncol, norms) = self.design(theta);
        let sol = linls::solve(&a, self.m(), ncol, &self.b, self.n_points, true, "refine").ok()?;
        let r = sol.residual?;
        let cost = dot(&r, &r);
        cost.is_finite().then_some(Eval {
            a,
            ncol,
            norms,
            x: sol.x,
            r,
            cost,
        })
    }

    /// Gauss–Newton normal matrix `J^T J` (row-major) and gradient `J^T r` of the residual
    /// with Kaufman's variable-projection Jacobian at `theta` (see the module
    /// documentation). Parameter `2q` is the frequency of pole `q`, `2q + 1` its damping
    /// ratio; both only move the pole's two columns `a_2q`, `a_2q+1`.
    fn normal_equations(&self, theta: &[f64], ev: &Eval) -> Option<(Vec<f64>, Vec<f64>)> {
        let nl = self.omega.len();
        let m = self.m();
        let np = theta.len();
        let npts = self.n_points;
        // D: for each parameter the derivatives of its pole's two columns, divided by the
        // column norms (the derivative of the norm lies along the column and is removed by
        // the projection), column-major m x 2 np.
        let mut d = vec![0.0; m * 2 * np];
        for (q, pc) in theta.chunks(2).enumerate() {
            let (f, z) = (pc[0], pc[1]);
            let lam = pole(f, z);
            let w_n = 2.0 * PI * f;
            let dlam = [lam / f, c64::new(-w_n, -w_n * z / (1.0 - z * z).sqrt())];
            for (t, dl) in dlam.iter().enumerate() {
                let p = 2 * q + t;
                let (n1, n2) = (ev.norms[2 * q], ev.norms[2 * q + 1]);
                let (d1, d2) = d[2 * p * m..(2 * p + 2) * m].split_at_mut(m);
                for (k, &w) in self.omega.iter().enumerate() {
                    let s = c64::new(0.0, w);
                    let g1 = (s - lam).inv();
                    let g2 = (s - lam.conj()).inv();
                    let t1 = g1 * g1 * dl;
                    let t2 = g2 * g2 * dl.conj();
                    let da = (t1 + t2) / n1;
                    let db = (t1 - t2) * c64::new(0.0, 1.0) / n2;
                    d1[k] = da.re;
                    d1[nl + k] = da.im;
                    d2[k] = db.re;
                    d2[nl + k] = db.im;
                }
            }
        }
        // E = P_perp D.
        let e = linls::solve(&ev.a, m, ev.ncol, &d, 2 * np, true, "refine jacobian")
            .ok()?
            .residual?;
        // Rows of X for the pole columns, and R X^T for them (m x np, column j = R x_j).
        let xrow = |j: usize| -> Vec<f64> { (0..npts).map(|o| ev.x[j + ev.ncol * o]).collect() };
        let xr: Vec<Vec<f64>> = (0..np).map(xrow).collect();
        let xt: Vec<f64> = xr.iter().flatten().copied().collect();
        let mut u = vec![0.0; m * np];
        faer::linalg::matmul::matmul(
            faer::MatMut::from_column_major_slice_mut(&mut u, m, np),
            faer::Accum::Replace,
            faer::MatRef::from_column_major_slice(&ev.r, m, npts),
            faer::MatRef::from_column_major_slice(&xt, npts, np),
            1.0,
            faer::Par::Seq,
        );
        crate::simd::clear_upper_vector_state();
        // Parameter p uses derivative columns (p, 0), (p, 1) of D/E and coefficient rows
        // 2q, 2q + 1 with q = p / 2.
        let ecol = |p: usize, s: usize| &e[(2 * p + s) * m..(2 * p + s + 1) * m];
        let xj = |p: usize, s: usize| 2 * (p / 2) + s;
        let mut jtj = vec![0.0; np * np];
        let mut jtr = vec![0.0; np];
        for p in 0..np {
            for pp in 0..=p {
                let mut v = 0.0;
                for s1 in 0..2 {
                    for s2 in 0..2 {
                        v += dot(ecol(p, s1), ecol(pp, s2)) * dot(&xr[xj(p, s1)], &xr[xj(pp, s2)]);
                    }
                }
                jtj[p * np + pp] = v;
                jtj[pp * np + p] = v;
            }
            jtr[p] = -(0..2)
                .map(|s1| dot(ecol(p, s1), &u[xj(p, s1) * m..(xj(p, s1) + 1) * m]))
                .sum::<f64>();
        }
        Some((jtj, jtr))
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
    let mut out = lambdas.to_vec();
    for (g, grp, theta0) in groups(freq_hz, h, weights, lambdas, params) {
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

/// The refinement problems: poles whose local bands overlap are refined together. For each
/// group, the indices of its poles, its band data and the starting `(f_hz, zeta)` of its
/// poles. Groups whose band has too few lines for their unknowns are left out (their poles
/// stand).
fn groups(
    freq_hz: &[f64],
    h: &[&[c64]],
    weights: &[f64],
    lambdas: &[c64],
    params: &RefineParams,
) -> Vec<(Vec<usize>, Group, Vec<f64>)> {
    let nf = freq_hz.len();
    if nf < 3 || h.is_empty() || lambdas.is_empty() {
        return Vec::new();
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
    let mut members: Vec<Vec<usize>> = Vec::new();
    let mut hi = f64::NEG_INFINITY;
    for &i in &order {
        if bands[i].0 <= hi {
            members.last_mut().expect("a group exists").push(i);
        } else {
            members.push(vec![i]);
        }
        hi = hi.max(bands[i].1);
    }
    let mut out = Vec::with_capacity(members.len());
    for g in members {
        let lo = g.iter().map(|&i| bands[i].0).fold(f64::INFINITY, f64::min);
        let hi = g
            .iter()
            .map(|&i| bands[i].1)
            .fold(f64::NEG_INFINITY, f64::max);
        // The band is a contiguous run of lines (the axis is sorted).
        let first = freq_hz.partition_point(|&f| f < lo);
        let end = freq_hz.partition_point(|&f| f <= hi);
        let ncol = 2 * g.len() + 4;
        if end < first + ncol + 2 {
            continue;
        }
        let lines = first..end;
        let omega: Vec<f64> = freq_hz[lines.clone()]
            .iter()
            .map(|f| 2.0 * PI * f)
            .collect();
        let omega_c = 0.5 * (omega[0] + omega[omega.len() - 1]);
        let b = linls::stacked(
            h.iter()
                .zip(weights)
                .map(|(row, &w)| (&row[lines.clone()], w)),
        );
        let grp = Group {
            omega,
            omega_c,
            b,
            n_points: h.len(),
        };
        let theta0: Vec<f64> = g.iter().flat_map(|&i| [fz[i].0, fz[i].1]).collect();
        out.push((g, grp, theta0));
    }
    out
}

/// Levenberg–Marquardt on `theta = (f_1, zeta_1, ...)` with the variable-projection
/// Jacobian. Returns `None` if the starting point cannot be evaluated or nothing improved.
fn levenberg_marquardt(grp: &Group, theta0: &[f64], params: &RefineParams) -> Option<Vec<f64>> {
    let np = theta0.len();
    let mut theta = theta0.to_vec();
    let mut cur = grp.eval(&theta)?;
    let cost0 = cur.cost;
    let mut mu = 1e-3;
    for _ in 0..params.max_iter {
        let (jtj, jtr) = grp.normal_equations(&theta, &cur)?;
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
            let mut d: Vec<f64> = jtr.iter().map(|g| -g).collect();
            cholesky_solve(&l, np, &mut d);
            let t: Vec<f64> = theta.iter().zip(&d).map(|(a, b)| a + b).collect();
            if t.chunks(2)
                .any(|p| !(p[0] > 0.0 && p[1] > 0.0 && p[1] < 1.0))
            {
                mu *= 10.0;
                continue;
            }
            if let Some(et) = grp.eval(&t) {
                if et.cost < cur.cost {
                    let rel = (cur.cost - et.cost) / cur.cost;
                    theta = t;
                    cur = et;
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
    (cur.cost < cost0).then_some(theta)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::modal::frf;
    use rand::SeedableRng;

    /// Frequency axis, spectra per point, true `(freq_hz, damping_ratio)` of the two modes.
    type Case = (Vec<f64>, Vec<Vec<c64>>, [(f64, f64); 2]);

    /// Two close modes (0.8 % apart) at 12 points, with a smooth background (a rigid-body
    /// `1/(i omega)` term, which the local background model only approximates) if asked, and
    /// noise.
    fn case(noise: f64, background: bool) -> Case {
        let truth = [(500.0, 0.01), (504.0, 0.015)];
        let freq_hz: Vec<f64> = (0..400).map(|k| 470.0 + 0.15 * k as f64).collect();
        let modes: Vec<frf::SynthMode> = truth
            .iter()
            .enumerate()
            .map(|(r, &(f, z))| {
                let lam = frf::pole(f, z);
                let phi: Vec<f64> = (0..12)
                    .map(|o| ((o as f64 + 1.0) * (0.7 + 0.9 * r as f64)).sin())
                    .collect();
                frf::SynthMode {
                    lambda: lam,
                    residues: frf::mobility_residues(lam, &phi, phi[0]),
                }
            })
            .collect();
        let residuals: Vec<frf::ResidualTerm> = background
            .then(|| frf::ResidualTerm {
                power: -1,
                coeffs: (0..12).map(|o| 30.0 + o as f64).collect(),
            })
            .into_iter()
            .collect();
        let mut h = frf::synthesize(&freq_hz, &modes, &residuals);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        frf::add_noise(&mut h, noise, noise, &mut rng);
        (freq_hz, h, truth)
    }

    #[test]
    fn variable_projection_gradient_matches_finite_differences_of_the_cost() {
        // Kaufman's Jacobian drops a term orthogonal to the residual, so J^T r is the exact
        // half-gradient of the cost: a check of the pole-parameter derivatives.
        let (f, h, truth) = case(0.01, true);
        let rows: Vec<&[c64]> = h.iter().map(|r| r.as_slice()).collect();
        let start: Vec<c64> = truth.iter().map(|&(f, z)| frf::pole(f, z)).collect();
        let weights = vec![1.0; rows.len()];
        let mut gs = groups(&f, &rows, &weights, &start, &RefineParams::default());
        assert_eq!(gs.len(), 1, "the two bands overlap: one group");
        let (_, g, _) = gs.pop().unwrap();
        let theta = vec![
            truth[0].0 * 1.001,
            truth[0].1 * 1.2,
            truth[1].0 * 0.999,
            truth[1].1 * 0.8,
        ];
        let ev = g.eval(&theta).unwrap();
        let (jtj, jtr) = g.normal_equations(&theta, &ev).unwrap();
        for p in 0..theta.len() {
            let step = if p % 2 == 0 {
                1e-6 * theta[p]
            } else {
                1e-5 * theta[p]
            };
            let (mut tp, mut tm) = (theta.clone(), theta.clone());
            tp[p] += step;
            tm[p] -= step;
            let fd = (g.eval(&tp).unwrap().cost - g.eval(&tm).unwrap().cost) / (2.0 * step);
            let rel = (2.0 * jtr[p] - fd).abs() / fd.abs();
            assert!(
                rel < 1e-4,
                "parameter {p}: 2 J^T r = {} vs {fd} ({rel:e})",
                2.0 * jtr[p]
            );
            assert!(jtj[p * theta.len() + p] > 0.0);
        }
    }

    #[test]
    fn finds_the_least_squares_poles_of_two_overlapping_modes_from_a_poor_start() {
        let start_of = |truth: &[(f64, f64); 2]| {
            [
                frf::pole(truth[0].0 * 1.002, truth[0].1 * 1.5),
                frf::pole(truth[1].0 * 0.998, truth[1].1 * 0.6),
            ]
        };
        let to_theta = |l: &[c64]| -> Vec<f64> {
            l.iter()
                .flat_map(|l| [l.norm() / (2.0 * PI), -l.re / l.norm()])
                .collect()
        };
        // Without noise or background the model is exact and the truth is the minimum:
        // recovered to rounding.
        let (f, h, truth) = case(0.0, false);
        let rows: Vec<&[c64]> = h.iter().map(|r| r.as_slice()).collect();
        let weights = vec![1.0; rows.len()];
        let params = RefineParams {
            max_iter: 50,
            ..RefineParams::default()
        };
        let out = refine_poles(&f, &rows, &weights, &start_of(&truth), &params);
        let th = to_theta(&out);
        for (r, &(f0, z0)) in truth.iter().enumerate() {
            assert!((th[2 * r] / f0 - 1.0).abs() < 1e-9, "{th:?}");
            assert!((th[2 * r + 1] / z0 - 1.0).abs() < 1e-7, "{th:?}");
        }
        // With noise (modes overlapping by more than their separation, so their estimates
        // scatter), the result is a minimum: not costlier than the truth, zero gradient.
        let (f, h, truth) = case(0.02, true);
        let rows: Vec<&[c64]> = h.iter().map(|r| r.as_slice()).collect();
        let out = refine_poles(&f, &rows, &weights, &start_of(&truth), &params);
        // The problem the refinement solved: its one group (the two bands overlap).
        let mut gs = groups(&f, &rows, &weights, &start_of(&truth), &params);
        assert_eq!(gs.len(), 1);
        let (members, g, _) = gs.pop().unwrap();
        assert_eq!(members.len(), 2);
        let th = to_theta(&out);
        let t0: Vec<f64> = truth.iter().flat_map(|&(f, z)| [f, z]).collect();
        let ev = g.eval(&th).unwrap();
        assert!(ev.cost <= g.eval(&t0).unwrap().cost);
        let (jtj, jtr) = g.normal_equations(&th, &ev).unwrap();
        // Gauss-Newton step at the result: negligible against the parameters.
        let n = th.len();
        let l = cholesky(&jtj, n).unwrap();
        let mut d: Vec<f64> = jtr.iter().map(|g| -g).collect();
        cholesky_solve(&l, n, &mut d);
        for (p, (dp, tp)) in d.iter().zip(&th).enumerate() {
            assert!((dp / tp).abs() < 1e-5, "parameter {p}: step {dp} at {tp}");
        }
    }
}

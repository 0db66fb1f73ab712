//! Least-squares frequency-domain (LSFD) residue fit with residual terms, real-normalised
//! shapes, modal phase collinearity (MPC) and mean phase deviation (MPD).
//!
//! For known poles `lambda_r`, each point's spectrum is linear in the unknowns:
//!
//! `H_o(omega) = sum_r [A_or/(i omega - lambda_r) + conj(A_or)/(i omega - conj(lambda_r))]
//!              + sum_p c_op (i omega)^p`,
//!
//! with complex residues `A_or = a + i b` and real residual coefficients `c_op`. Writing
//! `g1 = 1/(i omega - lambda)`, `g2 = 1/(i omega - conj(lambda))`, the columns for `a` and `b`
//! are `g1 + g2` and `i (g1 - g2)`. Real and imaginary parts of all lines are stacked into one
//! real least-squares problem whose design matrix is shared by all points, so one
//! factorisation solves every point. Columns are scaled to unit norm and the (small,
//! `2 modes + residuals` square) normal equations are solved by Cholesky: with unit-norm
//! columns their conditioning is ample for distinct poles, and unlike faer's QR (which may
//! split work over threads) the result is bit-identical whatever the thread count.
//!
//! Residual terms model what lies outside the band: for a mobility, modes below (rigid body,
//! `1/(i omega m)`) give power -1 and modes above (`i omega / k`) power +1; for a
//! base-excitation transmissibility the rigid-body 1 is power 0, modes below give power -2
//! (`omega_r^2/(i omega)^2`) and modes above power +2.

use super::linls;
use super::lscf::dot;
use super::{FunctionKind, ModalError};
use faer::c64;
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// Residual terms of the LSFD.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LsfdParams {
    /// Powers `p` of the residual terms `c (i omega)^p`.
    pub residual_powers: Vec<i32>,
}

impl LsfdParams {
    /// Default residual terms for a kind of spectrum (see the module documentation).
    pub fn for_kind(kind: FunctionKind) -> Self {
        let residual_powers = match kind {
            FunctionKind::Mobility => vec![-1, 0, 1],
            FunctionKind::Transmissibility => vec![-2, 0, 2],
            FunctionKind::Other => vec![-2, -1, 0, 1, 2],
        };
        Self { residual_powers }
    }
}

/// Result of [`lsfd`].
#[derive(Debug, Clone, PartialEq)]
pub struct LsfdFit {
    /// `residues[point][mode]`.
    pub residues: Vec<Vec<c64>>,
    /// `residual_coeffs[point][term]`, aligned with `residual_powers`.
    pub residual_coeffs: Vec<Vec<f64>>,
    /// Relative fit error per point, `||H - H_fit|| / ||H||`.
    pub fit_error: Vec<f64>,
    /// `||H - H_fit||^2` and `||H||^2` per point.
    pub residual_sq: Vec<f64>,
    pub norm_sq: Vec<f64>,
}

impl LsfdFit {
    /// Relative fit error over the points with `mask[o] == true`.
    pub fn overall_error(&self, mask: &[bool]) -> f64 {
        let (mut r, mut n) = (0.0, 0.0);
        for (o, &m) in mask.iter().enumerate() {
            if m {
                r += self.residual_sq[o];
                n += self.norm_sq[o];
            }
        }
        if n > 0.0 {
            (r / n).sqrt()
        } else {
            f64::NAN
        }
    }
}

/// Fit residues and residual terms for the poles `lambdas` (rad/s, `Im > 0`) to every
/// spectrum `h[point]` on `freq_hz`.
pub fn lsfd(
    freq_hz: &[f64],
    h: &[&[c64]],
    lambdas: &[c64],
    params: &LsfdParams,
) -> Result<LsfdFit, ModalError> {
    let nf = freq_hz.len();
    let nm = lambdas.len();
    let np = params.residual_powers.len();
    let ncol = 2 * nm + np;
    if 2 * nf < ncol {
        return Err(ModalError::Numerical {
            stage: "lsfd",
            detail: format!("{ncol} unknowns per point but only {nf} lines"),
        });
    }
    let mut cols: Vec<Vec<c64>> = Vec::with_capacity(ncol);
    for lam in lambdas {
        let (mut ca, mut cb) = (Vec::with_capacity(nf), Vec::with_capacity(nf));
        for &f in freq_hz {
            let s = c64::new(0.0, 2.0 * PI * f);
            let g1 = (s - lam).inv();
            let g2 = (s - lam.conj()).inv();
            ca.push(g1 + g2);
            cb.push((g1 - g2) * c64::new(0.0, 1.0));
        }
        cols.push(ca);
        cols.push(cb);
    }
    for &p in &params.residual_powers {
        cols.push(
            freq_hz
                .iter()
                .map(|&f| c64::new(0.0, 2.0 * PI * f).powi(p))
                .collect(),
        );
    }
    let scale: Vec<f64> = cols
        .iter()
        .map(|c| {
            let n = c.iter().map(|v| v.norm_sqr()).sum::<f64>().sqrt();
            if n > 0.0 {
                1.0 / n
            } else {
                1.0
            }
        })
        .collect();
    // Real design (real parts of all lines, then imaginary parts; unit-norm columns),
    // column-major 2 nf x ncol, and the data of every point as the columns of B.
    let m = 2 * nf;
    let a = linls::stacked(cols.iter().zip(&scale).map(|(c, &sc)| (c.as_slice(), sc)));
    let b = linls::stacked(h.iter().map(|row| (*row, 1.0)));
    let sol = linls::solve(&a, m, ncol, &b, h.len(), true, "lsfd")?;
    let resid = sol.residual.expect("asked for");
    let mut residues = Vec::with_capacity(h.len());
    let mut residual_coeffs = Vec::with_capacity(h.len());
    let mut fit_error = Vec::with_capacity(h.len());
    let mut residual_sq = Vec::with_capacity(h.len());
    let mut norm_sq = Vec::with_capacity(h.len());
    for (o, x) in sol.x.chunks(ncol).enumerate() {
        let coef: Vec<f64> = (0..ncol).map(|j| x[j] * scale[j]).collect();
        if coef.iter().any(|v| !v.is_finite()) {
            return Err(ModalError::Numerical {
                stage: "lsfd",
                detail: format!("non-finite residue for point {o} (poles too close?)"),
            });
        }
        residues.push(
            (0..nm)
                .map(|r| c64::new(coef[2 * r], coef[2 * r + 1]))
                .collect::<Vec<_>>(),
        );
        residual_coeffs.push(coef[2 * nm..].to_vec());
        let r = &resid[o * m..(o + 1) * m];
        let bo = &b[o * m..(o + 1) * m];
        let rs = dot(r, r);
        let ns = dot(bo, bo);
        residual_sq.push(rs);
        norm_sq.push(ns);
        fit_error.push(if ns > 0.0 { (rs / ns).sqrt() } else { f64::NAN });
    }
    Ok(LsfdFit {
        residues,
        residual_coeffs,
        fit_error,
        residual_sq,
        norm_sq,
    })
}

/// Second moments `(Sxx, Syy, Sxy)` of the complex components (as points in the plane)
/// over the masked-in entries, and the principal angle `theta` maximising
/// `sum (x cos theta + y sin theta)^2`.
fn moments(v: &[c64], mask: &[bool]) -> (f64, f64, f64, f64) {
    let (mut sxx, mut syy, mut sxy) = (0.0, 0.0, 0.0);
    for (z, &m) in v.iter().zip(mask) {
        if m {
            sxx += z.re * z.re;
            syy += z.im * z.im;
            sxy += z.re * z.im;
        }
    }
    let theta = 0.5 * (2.0 * sxy).atan2(sxx - syy);
    (sxx, syy, sxy, theta)
}

/// Real-normalised shape: components projected on the principal direction of the complex
/// residues in the plane (the best real approximation up to a complex factor), scaled so
/// that the largest |component| is +1. Masked-out points are `NaN`.
pub fn real_normalise(v: &[c64], mask: &[bool]) -> Vec<f64> {
    let (_, _, _, theta) = moments(v, mask);
    let (c, s) = (theta.cos(), theta.sin());
    let proj: Vec<f64> = v.iter().map(|z| z.re * c + z.im * s).collect();
    let mut big = 0.0f64;
    for (p, &m) in proj.iter().zip(mask) {
        if m && p.abs() > big.abs() {
            big = *p;
        }
    }
    proj.iter()
        .zip(mask)
        .map(|(p, &m)| if m && big != 0.0 { p / big } else { f64::NAN })
        .collect()
}

/// Each mode's share of the fitted response at its own natural frequency `|lambda_r|`, the
/// largest over the points with `mask[o] == true`: the magnitude of its term over the sum of
/// every mode term's and the residual terms' magnitudes there, in [0, 1]. A mode a point
/// shows dominates there (share near 1); two close modes share it; a pole whose term is a
/// small share is no resonance of these spectra. `NaN` when no point is masked in.
pub fn peak_shares(lambdas: &[c64], fit: &LsfdFit, powers: &[i32], mask: &[bool]) -> Vec<f64> {
    let term = |a: c64, lam: c64, s: c64| a * (s - lam).inv() + a.conj() * (s - lam.conj()).inv();
    (0..lambdas.len())
        .map(|r| {
            let s = c64::new(0.0, lambdas[r].norm());
            let mut best: Option<f64> = None;
            for (o, _) in mask.iter().enumerate().filter(|(_, &m)| m) {
                let own = term(fit.residues[o][r], lambdas[r], s).norm();
                let modes: f64 = (0..lambdas.len())
                    .map(|q| term(fit.residues[o][q], lambdas[q], s).norm())
                    .sum();
                let residual: c64 = powers
                    .iter()
                    .zip(&fit.residual_coeffs[o])
                    .map(|(&p, &c)| s.powi(p) * c)
                    .sum();
                let total = modes + residual.norm();
                let share = if total > 0.0 { own / total } else { 0.0 };
                best = Some(best.map_or(share, |b: f64| b.max(share)));
            }
            best.unwrap_or(f64::NAN)
        })
        .collect()
}

/// Modal phase collinearity and mean phase deviation (degrees) of a complex shape over the
/// masked-in points.
///
/// `MPC = ((Sxx - Syy)^2 + 4 Sxy^2) / (Sxx + Syy)^2` = `((s1 - s2)/(s1 + s2))^2` with `s1, s2` the
/// eigenvalues of the 2x2 moment matrix (Pappa et al. 1993); 1 for a real (collinear) shape.
/// `MPD = sum |v_o| delta_o / sum |v_o|` with `delta_o` the angle between component `o` and
/// the principal line, in [0°, 90°].
pub fn mpc_mpd(v: &[c64], mask: &[bool]) -> (f64, f64) {
    let (sxx, syy, sxy, theta) = moments(v, mask);
    let tr = sxx + syy;
    let mpc = if tr > 0.0 {
        ((sxx - syy).powi(2) + 4.0 * sxy * sxy) / (tr * tr)
    } else {
        f64::NAN
    };
    let (c, s) = (theta.cos(), theta.sin());
    let (mut num, mut den) = (0.0, 0.0);
    for (z, &m) in v.iter().zip(mask) {
        let a = z.norm();
        if m && a > 0.0 {
            let perp = (-z.re * s + z.im * c).abs();
            num += a * (perp / a).clamp(0.0, 1.0).asin();
            den += a;
        }
    }
    let mpd = if den > 0.0 {
        (num / den).to_degrees()
    } else {
        f64::NAN
    };
    (mpc, mpd)
}

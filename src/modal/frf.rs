//! Synthesis of spectra from poles, residues and residual terms, plus measurement noise.
//!
//! The forward model shared by the tests, the benchmark and the virtual lab:
//!
//! `H_o(omega) = sum_r [A_or/(i omega - lambda_r) + conj(A_or)/(i omega - conj(lambda_r))]
//!              + sum_p c_op (i omega)^p`
//!
//! with `lambda_r = -zeta_r omega_r + i omega_r sqrt(1 - zeta_r^2)` (rad/s), complex residues
//! `A_or` and real residual coefficients `c_op`. Helpers turn real mode shapes into the
//! residues of a mobility (hammer, free-free) or a base-excitation transmissibility.
//! Noise enters only through an explicit RNG.

use faer::c64;
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use std::f64::consts::PI;

/// Pole `lambda = -zeta omega_n + i omega_n sqrt(1 - zeta^2)` in rad/s from the undamped
/// natural frequency in Hz and the damping ratio (`0 <= zeta < 1`).
pub fn pole(freq_hz: f64, damping_ratio: f64) -> c64 {
    let w = 2.0 * PI * freq_hz;
    c64::new(
        -damping_ratio * w,
        w * (1.0 - damping_ratio * damping_ratio).sqrt(),
    )
}

/// One mode of a synthetic spectrum set: its pole and one complex residue per point.
#[derive(Debug, Clone, PartialEq)]
pub struct SynthMode {
    pub lambda: c64,
    pub residues: Vec<c64>,
}

/// A residual term `c_o (i omega)^power` with one real coefficient per point.
#[derive(Debug, Clone, PartialEq)]
pub struct ResidualTerm {
    pub power: i32,
    pub coeffs: Vec<f64>,
}

/// Evaluate the pole–residue model at every frequency: returns `h[point][line]`.
/// The number of points is taken from the first mode or residual term (0 if none).
pub fn synthesize(
    freq_hz: &[f64],
    modes: &[SynthMode],
    residuals: &[ResidualTerm],
) -> Vec<Vec<c64>> {
    let n_points = modes
        .first()
        .map(|m| m.residues.len())
        .or_else(|| residuals.first().map(|r| r.coeffs.len()))
        .unwrap_or(0);
    let mut h = vec![vec![c64::new(0.0, 0.0); freq_hz.len()]; n_points];
    for (k, &f) in freq_hz.iter().enumerate() {
        let s = c64::new(0.0, 2.0 * PI * f);
        for m in modes {
            let g1 = (s - m.lambda).inv();
            let g2 = (s - m.lambda.conj()).inv();
            for (o, a) in m.residues.iter().enumerate().take(n_points) {
                h[o][k] += a * g1 + a.conj() * g2;
            }
        }
        for r in residuals {
            let sp = s.powi(r.power);
            for (o, c) in r.coeffs.iter().enumerate().take(n_points) {
                h[o][k] += sp * *c;
            }
        }
    }
    h
}

/// Residues of a mobility (velocity over force) for a mode with real mass-normalised
/// shape `phi` (1/sqrt(kg)) at the points and `phi_ref` at the driving point.
///
/// From `s phi_o phi_ref / (s^2 + 2 zeta omega s + omega^2)` = `A/(s-lambda) + conj/(s-conj lambda)`
/// with `A = lambda phi_o phi_ref / (lambda - conj(lambda))` in (m/s)/N · rad/s.
pub fn mobility_residues(lambda: c64, phi: &[f64], phi_ref: f64) -> Vec<c64> {
    let k = lambda / (lambda - lambda.conj());
    phi.iter().map(|p| k * (p * phi_ref)).collect()
}

/// Residues and constant term of the absolute-velocity transmissibility under base
/// excitation for a mode with real shape `phi` and participation factor `gamma`:
///
/// `T_o(s) = 1 - sum_r gamma_r phi_or s^2 / (s^2 + 2 zeta_r omega_r s + omega_r^2)`
///
/// Since `-s^2/(s^2 + 2 zeta w s + w^2) = -1 + (2 zeta w s + w^2)/(s^2 + 2 zeta w s + w^2)`,
/// each modal term equals the constant `-gamma phi` plus a pole pair with residue
/// `A = gamma phi (2 zeta w lambda + w^2)/(lambda - conj(lambda))`.
/// Returns `(residues, constant per point)`; the caller adds the rigid-body 1.
pub fn transmissibility_terms(lambda: c64, phi: &[f64], gamma: f64) -> (Vec<c64>, Vec<f64>) {
    let w = lambda.norm();
    let zeta = -lambda.re / w;
    // -s^2/(s^2 + 2 zeta w s + w^2) = -1 + (2 zeta w s + w^2)/(s^2 + 2 zeta w s + w^2)
    let k = (lambda * (2.0 * zeta * w) + w * w) / (lambda - lambda.conj());
    let residues = phi.iter().map(|p| k * (gamma * p)).collect();
    let constant = phi.iter().map(|p| -gamma * p).collect();
    (residues, constant)
}

/// Add circular complex Gaussian noise to every line:
/// `sigma_o = floor_rel * max_o rms(H_o) + prop_rel * rms(H_o)` (standard deviation of the
/// complex noise, i.e. `E|n|^2 = sigma^2`). The floor models the vibrometer's noise common
/// to all points, the proportional part the excitation/leakage errors.
pub fn add_noise<R: Rng + ?Sized>(h: &mut [Vec<c64>], floor_rel: f64, prop_rel: f64, rng: &mut R) {
    let rms: Vec<f64> = h.iter().map(|row| rms(row)).collect();
    let max_rms = rms.iter().cloned().fold(0.0, f64::max);
    for (row, r) in h.iter_mut().zip(rms) {
        let sigma = floor_rel * max_rms + prop_rel * r;
        add_white_noise(row, sigma, rng);
    }
}

/// Add circular complex Gaussian noise with `E|n|^2 = sigma^2` to one spectrum.
pub fn add_white_noise<R: Rng + ?Sized>(row: &mut [c64], sigma: f64, rng: &mut R) {
    let s = sigma / std::f64::consts::SQRT_2;
    for v in row.iter_mut() {
        let a: f64 = StandardNormal.sample(rng);
        let b: f64 = StandardNormal.sample(rng);
        *v += c64::new(s * a, s * b);
    }
}

/// Root mean square magnitude of a spectrum.
pub fn rms(row: &[c64]) -> f64 {
    if row.is_empty() {
        return 0.0;
    }
    (row.iter().map(|v| v.norm_sqr()).sum::<f64>() / row.len() as f64).sqrt()
}

/// Scan points on a regular `nx x ny` grid covering a `length_m x width_m` plate (corners
/// included), row by row (x fastest). Returned as `(x_m, y_m)`.
pub fn grid_points(nx: usize, ny: usize, length_m: f64, width_m: f64) -> Vec<(f64, f64)> {
    let mut out = Vec::with_capacity(nx * ny);
    for j in 0..ny {
        for i in 0..nx {
            let x = length_m * i as f64 / (nx.max(2) - 1) as f64;
            let y = width_m * j as f64 / (ny.max(2) - 1) as f64;
            out.push((x, y));
        }
    }
    out
}

/// Analytic plate-like shape with `kx` sign changes along x and `ky` along y, at the
/// normalised coordinates `u = x/L`, `v = y/W` in [0, 1]:
/// `g_kx(u) g_ky(v)` with `g_0 = 1`, `g_1(u) = 2u - 1`, `g_k(u) = cos(k pi u)` for `k >= 2`.
/// Mimics free-free plate modes (torsion = (1,1), first bending along x = (2,0)); used by the
/// tests, the benchmark and as a stand-in before the FE model exists.
pub fn plate_like_shape(kx: usize, ky: usize, u: f64, v: f64) -> f64 {
    fn g(k: usize, t: f64) -> f64 {
        match k {
            0 => 1.0,
            1 => 2.0 * t - 1.0,
            _ => (k as f64 * PI * t).cos(),
        }
    }
    g(kx, u) * g(ky, v)
}

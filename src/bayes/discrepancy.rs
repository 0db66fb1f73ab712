//! The model-form discrepancy shared by every unit of a step: per updated mode, a relative
//! eigenvalue bias d_m that no parameter of the model can absorb (pure; no I/O).
//!
//! The model eigenvalue of mode m becomes λ_m(θ) (1 + d_m) for every unit. Why this form:
//! - A plate model misses physics a real board has (transverse shear and rotary inertia, the
//!   copper as layers, the contact patch of a joint). What it misses is the same on every
//!   board of a campaign, so it is common to the units, not independent between them (so is
//!   one mesh's discretization error: `update::problem::ModelErrorPrior`). It is
//!   a bias per mode and setup, and nothing in the per-unit terms covers it: the units'
//!   parameters take up what they can and the rest shows up as a systematic residual that the
//!   intervals, narrowed by hundreds of measurements, miss.
//! - Kennedy & O'Hagan's (2001) discrepancy, left free per mode, is confounded with the
//!   parameters: a common shift of the moduli and a discrepancy along their sensitivities
//!   predict the same data, so neither is identified (Brynjarsdóttir & O'Hagan 2014), and a
//!   sampler that moves one block at a time crawls along that ridge. Plumlee (2017, JASA
//!   112:1274) removes the confounding by keeping the discrepancy orthogonal to the model's
//!   parameter gradient. Here d = N w, with N an orthonormal basis of the orthogonal
//!   complement of the span of W S. S holds the relative eigenvalue sensitivities ∂λ_m/λ_m per
//!   unit coordinate where the units are, modes × coordinates; W a diagonal metric over the
//!   modes (the stage uses the plain one, every mode alike). Then Sᵀ W d = 0: to first order
//!   no shift of the parameters mimics a discrepancy. The parameters are then those of the
//!   best-fitting model. d is what no parameter can fit: the part the users need in their
//!   intervals, and the baseline the diagnosis must beat. Measured: on the solid-truth
//!   paper campaign d still correlates with the boards' mean moduli at up to ±0.9 a
//!   posteriori, which the block moves mix slowly at 2000 particles (see the stage).
//! - Prior: w_j ~ N(0, τ²), so d ~ N(0, τ² N Nᵀ): an exchangeable per-mode discrepancy of
//!   scale τ, less the part the parameters absorb. The scale is hierarchical,
//!   ln τ ~ N(ln τ₀, s²): the modes' discrepancies share it and the campaign sets it. τ₀ is
//!   the model's stated fidelity ([`FREE_FIDELITY_FREQ`], [`BOLTED_FIDELITY_FREQ`]), not a
//!   value fitted to any lab.
//!
//! - What varies from unit to unit: the model's form errs a little differently on each board
//!   (the shear correction follows E/G_xz, and the boards' moduli differ by a few per cent;
//!   each board's unmodelled geometry differs). With only the common d, each board's
//!   parameters fit as many modes as they have coordinates exactly, and the rest of its
//!   misfit went into the per-mode ε of some modes, which grew to 1–2 % while the fitted
//!   modes' ε fell to the measurement scatter (2e-5): a funnel whose choice of modes
//!   differed between runs. A per-unit model error b_m ~ N(0, σ_u²) (integrated per unit,
//!   `modal::log_lik_with`) with σ_u inferred takes that part instead; its prior median is
//!   [`UNIT_SHARE`] of τ₀.
//!
//! Global coordinates: ln τ, ln σ_u, then w₁..w_k.
//!
//! - The part the parameters absorb. Under the same exchangeable prior d ~ N(0, τ² I), the
//!   part of d inside the span of S is a = (SᵀWS)⁻¹SᵀW d in unit coordinates: the data see
//!   λ(x)(1 + S a) ≈ λ(x + a), so they identify the fitted coordinates x + a, never a. The
//!   physical coordinates are x − a, with a at its prior given τ, N(0, τ² M Mᵀ), M =
//!   (SᵀWS)⁻¹SᵀW ([`Discrepancy::confounded_shift`]): what Kennedy & O'Hagan's
//!   unconstrained discrepancy gives the parameters (Brynjarsdóttir & O'Hagan 2014), to
//!   first order. The predictions do not need it (x + a and d's orthogonal part reproduce
//!   the data); a parameter's interval that claims to hold the board's physical value does.

use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::Serialize;

use super::stats::normal_lpdf;

/// The stated fidelity of the free-free plate model: the median of the prior of a mode's
/// frequency discrepancy, relative. Two sources, both independent of any lab:
/// - The paper this tool grows from: its updated free-free model missed validation modes by
///   up to 0.56 %.
/// - Thin-plate theory: the transverse-shear correction of a Kirchhoff plate,
///   Δf/f ≈ (π²/12)(E/κG_xz)(h/λ)². A 1.6 mm FR-4 board (E/G_xz ≈ 6, κ = 5/6) has
///   half-wavelengths λ = 25–80 mm in its first eight modes, which gives 0.1–2 %.
///
/// The median 0.5 % with [`FIDELITY_LOG_SD`] spans that range.
pub const FREE_FIDELITY_FREQ: f64 = 0.005;
/// The stated fidelity of the bolted model (spring joints on a plate): the paper's updated
/// bolted model missed validation modes by up to 1.5 %.
pub const BOLTED_FIDELITY_FREQ: f64 = 0.015;
/// Log-sd of the scale's prior: a factor e either way (90 % of the prior within ×5.2).
pub const FIDELITY_LOG_SD: f64 = 1.0;
/// The per-unit model error's prior median as a share of τ₀: the unit-to-unit variation of
/// a model-form error is the error times the relative variation of what it depends on. The
/// shear correction of a plate scales with E/G_xz; the boards' in-plane moduli scatter by
/// 1.5–2 % (the paper's posterior) and G_xz, never measured, plausibly by 5–10 %: a tenth.
pub const UNIT_SHARE: f64 = 0.1;
/// Log-sd of the per-unit scale's prior: wider than τ's (a factor e^1.5 either way), the
/// share above being the rougher estimate.
pub const UNIT_LOG_SD: f64 = 1.5;

/// The relative eigenvalue discrepancy of a relative frequency discrepancy f
/// (λ ∝ f²: (1 + f)² − 1).
pub fn eigenvalue_of_freq(f: f64) -> f64 {
    (1.0 + f) * (1.0 + f) - 1.0
}

/// The relative frequency discrepancy of a relative eigenvalue discrepancy d (√(1 + d) − 1).
pub fn freq_of_eigenvalue(d: f64) -> f64 {
    (1.0 + d).max(0.0).sqrt() - 1.0
}

/// A discrepancy over `n_modes` modes (see the module doc).
#[derive(Clone, Debug, Serialize)]
pub struct Discrepancy {
    pub n_modes: usize,
    /// N, n_modes × k row-major, orthonormal columns orthogonal to the sensitivities.
    pub basis: Vec<f64>,
    pub k: usize,
    /// Median τ₀ of the scale's prior (relative eigenvalue).
    pub scale_median: f64,
    pub scale_log_sd: f64,
    /// Median and log-sd of the per-unit scale σ_u's prior (relative eigenvalue).
    pub unit_scale_median: f64,
    pub unit_scale_log_sd: f64,
    /// Unit coordinates (the columns of S).
    pub unit_dim: usize,
    /// L (unit_dim × unit_dim, lower, row-major) with L Lᵀ = M Mᵀ, M = (SᵀWS)⁻¹SᵀW over the
    /// columns the modes see (the others' rows zero): a = τ L z, z ~ N(0, I), is the part of
    /// an exchangeable discrepancy of scale τ that the parameters absorb (module doc).
    pub confounded: Vec<f64>,
}

impl Discrepancy {
    /// The discrepancy of `n_modes` modes orthogonal, in the metric of the per-mode weights
    /// `weights` (W, the data's precision; empty: equal), to the columns of `sens` (n_modes ×
    /// n_cols row-major, relative eigenvalue sensitivities), with the frequency fidelity
    /// `fidelity_freq` as its scale's median; the columns `pinned` (coordinates held by data
    /// of their own: the balance's mass, a measured thickness) absorb none of it
    /// ([`confounded_factor`]). `None` where the sensitivities span every mode (nothing is
    /// left that the parameters cannot absorb).
    pub fn new(
        sens: &[f64],
        n_modes: usize,
        n_cols: usize,
        weights: &[f64],
        fidelity_freq: f64,
        pinned: &[usize],
    ) -> Option<Discrepancy> {
        let ws: Vec<f64> = (0..n_modes * n_cols)
            .map(|i| sens[i] * weights.get(i / n_cols.max(1)).copied().unwrap_or(1.0))
            .collect();
        let (basis, k) = complement_basis(&ws, n_modes, n_cols);
        let confounded = confounded_factor(sens, n_modes, n_cols, weights, pinned);
        (k > 0 && fidelity_freq > 0.0).then(|| Discrepancy {
            n_modes,
            basis,
            k,
            scale_median: eigenvalue_of_freq(fidelity_freq),
            scale_log_sd: FIDELITY_LOG_SD,
            unit_scale_median: UNIT_SHARE * eigenvalue_of_freq(fidelity_freq),
            unit_scale_log_sd: UNIT_LOG_SD,
            unit_dim: n_cols,
            confounded,
        })
    }

    /// The part a of a discrepancy of scale `tau` that the unit coordinates absorb, for the
    /// standard normal draw `z` (unit_dim long): a = τ L z (module doc). The physical unit
    /// coordinates are the fitted ones less a.
    pub fn confounded_shift(&self, tau: f64, z: &[f64]) -> Vec<f64> {
        crate::bayes::stats::lower_mul(&self.confounded, self.unit_dim, z)
            .into_iter()
            .map(|v| tau * v)
            .collect()
    }

    /// The unit coordinates that absorb part of the discrepancy (seen by the modes and not
    /// held by data of their own): the nonzero rows of L.
    pub fn absorbing(&self) -> Vec<usize> {
        let d = self.unit_dim;
        (0..d)
            .filter(|k| {
                self.confounded[k * d..(k + 1) * d]
                    .iter()
                    .any(|v| *v != 0.0)
            })
            .collect()
    }

    /// Coordinates in the global vector: ln τ, ln σ_u and w.
    pub fn dim(&self) -> usize {
        2 + self.k
    }

    pub fn names(&self) -> Vec<String> {
        ["log_discrepancy_scale", "log_unit_discrepancy_scale"]
            .into_iter()
            .map(str::to_string)
            .chain((0..self.k).map(|j| format!("discrepancy_w{j}")))
            .collect()
    }

    /// d per mode from the block h = (ln τ, ln σ_u, w).
    pub fn bias(&self, h: &[f64]) -> Vec<f64> {
        let w = &h[2..2 + self.k];
        (0..self.n_modes)
            .map(|m| {
                let row = &self.basis[m * self.k..(m + 1) * self.k];
                row.iter().zip(w).map(|(a, b)| a * b).sum()
            })
            .collect()
    }

    /// τ of the block h.
    pub fn scale(&self, h: &[f64]) -> f64 {
        h[0].exp()
    }

    /// σ_u of the block h.
    pub fn unit_scale(&self, h: &[f64]) -> f64 {
        h[1].exp()
    }

    /// log p(ln τ, ln σ_u, w).
    pub fn log_prior(&self, h: &[f64]) -> f64 {
        let ln_tau = h[0];
        let tau = ln_tau.exp();
        normal_lpdf(ln_tau, self.scale_median.ln(), self.scale_log_sd)
            + normal_lpdf(h[1], self.unit_scale_median.ln(), self.unit_scale_log_sd)
            + h[2..2 + self.k]
                .iter()
                .map(|&w| normal_lpdf(w, 0.0, tau))
                .sum::<f64>()
    }

    /// A prior draw of the block.
    pub fn sample(&self, rng: &mut ChaCha8Rng) -> Vec<f64> {
        let z: f64 = StandardNormal.sample(rng);
        let ln_tau = self.scale_median.ln() + self.scale_log_sd * z;
        let z: f64 = StandardNormal.sample(rng);
        let ln_unit = self.unit_scale_median.ln() + self.unit_scale_log_sd * z;
        let mut out = vec![ln_tau, ln_unit];
        for _ in 0..self.k {
            let z: f64 = StandardNormal.sample(rng);
            out.push(ln_tau.exp() * z);
        }
        out
    }
}

/// The scale τ of a model-form discrepancy that a step's likelihood does not carry, inferred
/// after the fit from its updated modes' mean residuals: a cut module (Plummer 2015; Jacob
/// et al. 2017). It widens the predictions of the modes the step did not update (a
/// validation mode's d ~ N(0, τ²), as with a discrepancy in the likelihood) and feeds
/// nothing back into the fit or its evidence.
///
/// Why: step 2 carries no discrepancy (a per-mode bias common to every assembly spans every
/// shift a common joint effect makes, so no refit could be told from it). Its updated
/// modes' systematic misfit then goes into their ε, which holds their own intervals, but a
/// mode it did not update borrowed only ε: on the realistic lab's null the bolted
/// bending-x-2 (a validation mode) sat 1.4–1.5 % below every prediction, and its own-board
/// 90 % intervals held 67–75 % of its measurements.
///
/// The model is the discrepancy's own (module doc): d ~ N(0, τ² I) over the updated modes,
/// the units' coordinates absorb its part in the span of S, so the mean residuals m see
/// r = Nᵀ m ~ N(0, τ² I_k + Nᵀ diag(se²) N) (se the residuals' standard errors), with the
/// prior ln τ ~ N(ln τ₀, s²) of the step's stated fidelity. With few modes (step 2 has 4)
/// the posterior is wide, and the draws carry that width into the predictions.
#[derive(Clone, Debug, PartialEq)]
pub struct CutScale {
    /// ln τ on a uniform grid.
    ln_tau: Vec<f64>,
    /// The posterior's cumulative distribution at the grid points (0 at the first, 1 at the
    /// last; trapezoids between).
    cdf: Vec<f64>,
}

/// Grid of the cut scale's posterior: ln τ₀ ± this many prior sds, in this many points.
const CUT_GRID_SDS: f64 = 6.0;
const CUT_GRID_POINTS: usize = 2401;

impl CutScale {
    /// The posterior of τ given the mean relative eigenvalue residuals `mean_resid` of the
    /// `disc.n_modes` updated modes and their standard errors `se`. `None` where the
    /// residuals are not finite or the discrepancy leaves nothing (k = 0).
    pub fn new(disc: &Discrepancy, mean_resid: &[f64], se: &[f64]) -> Option<CutScale> {
        use super::stats::{cholesky_jittered, lower_solve_sq_norm};
        let (n, k) = (disc.n_modes, disc.k);
        if k == 0
            || mean_resid.len() != n
            || se.len() != n
            || mean_resid.iter().chain(se).any(|v| !v.is_finite())
        {
            return None;
        }
        let col = |j: usize| (0..n).map(move |m| disc.basis[m * k + j]);
        let r: Vec<f64> = (0..k)
            .map(|j| col(j).zip(mean_resid).map(|(a, b)| a * b).sum())
            .collect();
        // Nᵀ diag(se²) N.
        let mut noise = vec![0.0; k * k];
        for i in 0..k {
            for j in 0..k {
                noise[i * k + j] = (0..n)
                    .map(|m| disc.basis[m * k + i] * se[m] * se[m] * disc.basis[m * k + j])
                    .sum();
            }
        }
        let (mu, sd) = (disc.scale_median.ln(), disc.scale_log_sd);
        let step = 2.0 * CUT_GRID_SDS * sd / (CUT_GRID_POINTS - 1) as f64;
        let ln_tau: Vec<f64> = (0..CUT_GRID_POINTS)
            .map(|i| mu - CUT_GRID_SDS * sd + step * i as f64)
            .collect();
        let zero = vec![0.0; k];
        let log_post: Vec<f64> = ln_tau
            .iter()
            .map(|&lt| {
                let t2 = (2.0 * lt).exp();
                let mut c = noise.clone();
                (0..k).for_each(|i| c[i * k + i] += t2);
                let (l, jitter) = cholesky_jittered(&c, k);
                if !jitter.is_finite() {
                    return f64::NEG_INFINITY;
                }
                let log_det: f64 = (0..k).map(|i| 2.0 * l[i * k + i].ln()).sum();
                normal_lpdf(lt, mu, sd) - 0.5 * (log_det + lower_solve_sq_norm(&l, k, &r, &zero))
            })
            .collect();
        let top = log_post.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        if !top.is_finite() {
            return None;
        }
        let dens: Vec<f64> = log_post.iter().map(|v| (v - top).exp()).collect();
        let mut cdf = vec![0.0; dens.len()];
        for i in 1..dens.len() {
            cdf[i] = cdf[i - 1] + 0.5 * (dens[i - 1] + dens[i]);
        }
        let total = cdf[cdf.len() - 1];
        cdf.iter_mut().for_each(|v| *v /= total);
        Some(CutScale { ln_tau, cdf })
    }

    /// τ at the posterior's quantile `p` ∈ [0, 1] (linear in ln τ between grid points).
    pub fn quantile(&self, p: f64) -> f64 {
        let p = p.clamp(0.0, 1.0);
        let i = self
            .cdf
            .partition_point(|&c| c < p)
            .clamp(1, self.cdf.len() - 1);
        let (c0, c1) = (self.cdf[i - 1], self.cdf[i]);
        let t = if c1 > c0 { (p - c0) / (c1 - c0) } else { 0.0 };
        (self.ln_tau[i - 1] + t * (self.ln_tau[i] - self.ln_tau[i - 1])).exp()
    }

    /// A posterior draw of τ.
    pub fn draw(&self, rng: &mut ChaCha8Rng) -> f64 {
        use rand::RngExt;
        self.quantile(rng.random::<f64>())
    }
}

/// Relative sensitivities ∂λ_m/λ_m per coordinate at x0 by central differences of step
/// `h` (n_modes × x0.len() row-major); `lambda(x)` is the model's eigenvalue per mode, None
/// where undefined. `None` where the model is undefined at a stencil point.
pub fn sensitivities(
    lambda: impl Fn(&[f64]) -> Option<Vec<f64>>,
    x0: &[f64],
    n_modes: usize,
    h: f64,
) -> Option<Vec<f64>> {
    let c = lambda(x0)?;
    let d = x0.len();
    let mut s = vec![0.0; n_modes * d];
    for k in 0..d {
        let mut xp = x0.to_vec();
        let mut xm = x0.to_vec();
        xp[k] += h;
        xm[k] -= h;
        let (p, m) = (lambda(&xp)?, lambda(&xm)?);
        for mode in 0..n_modes {
            s[mode * d + k] = (p[mode] - m[mode]) / (2.0 * h * c[mode]);
        }
    }
    Some(s)
}

/// Columns of S whose length is below this share of the longest are not seen by the modes
/// (the mass scale where the moduli are per unit mass: zero up to the finite differences'
/// round-off); their coordinates absorb nothing.
const UNSEEN_COLUMN: f64 = 1e-6;

/// L with L Lᵀ = M Mᵀ, M = (SᵀWS)⁻¹SᵀW over the seen columns of `sens` (n × c row-major;
/// W = diag `weights`, empty: I) that are not `pinned` (held by data of their own, to
/// first order exactly: a balance's 1e-4 against a discrepancy's 1e-3); zero rows and
/// columns for the others (see [`Discrepancy::confounded`]).
pub fn confounded_factor(
    sens: &[f64],
    n: usize,
    c: usize,
    weights: &[f64],
    pinned: &[usize],
) -> Vec<f64> {
    use crate::bayes::stats::{cholesky_jittered, lower_solve, lower_transpose_solve};
    let w = |m: usize| weights.get(m).copied().unwrap_or(1.0);
    let norm = |j: usize| (0..n).map(|m| sens[m * c + j].powi(2)).sum::<f64>().sqrt();
    let longest = (0..c).map(norm).fold(0.0, f64::max);
    let seen: Vec<usize> = (0..c)
        .filter(|&j| norm(j) > UNSEEN_COLUMN * longest && !pinned.contains(&j))
        .collect();
    let q = seen.len();
    let mut out = vec![0.0; c * c];
    if q == 0 {
        return out;
    }
    // A = SᵀWS over the seen columns, M = A⁻¹ SᵀW (q × n), then C = M Mᵀ.
    let mut a = vec![0.0; q * q];
    for (i, &ci) in seen.iter().enumerate() {
        for (j, &cj) in seen.iter().enumerate() {
            a[i * q + j] = (0..n)
                .map(|m| w(m) * sens[m * c + ci] * sens[m * c + cj])
                .sum();
        }
    }
    let (la, jitter) = cholesky_jittered(&a, q);
    if !jitter.is_finite() {
        return out;
    }
    let mut mt = vec![0.0; n * q];
    for m in 0..n {
        let b: Vec<f64> = seen.iter().map(|&cj| w(m) * sens[m * c + cj]).collect();
        let y = lower_transpose_solve(&la, q, &lower_solve(&la, q, &b));
        mt[m * q..(m + 1) * q].copy_from_slice(&y);
    }
    let mut cov = vec![0.0; q * q];
    for i in 0..q {
        for j in 0..q {
            cov[i * q + j] = (0..n).map(|m| mt[m * q + i] * mt[m * q + j]).sum();
        }
    }
    let (l, jitter) = cholesky_jittered(&cov, q);
    if !jitter.is_finite() {
        return out;
    }
    for (i, &ci) in seen.iter().enumerate() {
        for (j, &cj) in seen.iter().enumerate() {
            out[ci * c + cj] = l[i * q + j];
        }
    }
    out
}

/// An orthonormal basis (n × k row-major) of the orthogonal complement of the span of the
/// columns of `a` (n × c row-major), by modified Gram–Schmidt: first the columns of `a`,
/// dropping those that add less than a 1e-8 share of their length, then the unit vectors
/// e_1..e_n against them. Deterministic; k = n − rank(a).
pub fn complement_basis(a: &[f64], n: usize, c: usize) -> (Vec<f64>, usize) {
    let mut q: Vec<Vec<f64>> = vec![];
    let add = |v: Vec<f64>, q: &mut Vec<Vec<f64>>| -> bool {
        let norm0 = v.iter().map(|x| x * x).sum::<f64>().sqrt();
        if norm0 == 0.0 || !norm0.is_finite() {
            return false;
        }
        let mut v = v;
        // Twice: re-orthogonalisation keeps the basis orthonormal to round-off.
        for _ in 0..2 {
            for u in q.iter() {
                let p: f64 = u.iter().zip(&v).map(|(a, b)| a * b).sum();
                v.iter_mut().zip(u).for_each(|(x, y)| *x -= p * y);
            }
        }
        let norm = v.iter().map(|x| x * x).sum::<f64>().sqrt();
        if norm <= 1e-8 * norm0 {
            return false;
        }
        q.push(v.into_iter().map(|x| x / norm).collect());
        true
    };
    for j in 0..c {
        add((0..n).map(|i| a[i * c + j]).collect(), &mut q);
    }
    let rank = q.len();
    for i in 0..n {
        if q.len() == n {
            break;
        }
        add(
            (0..n).map(|r| f64::from(u8::from(r == i))).collect(),
            &mut q,
        );
    }
    let k = q.len() - rank;
    let mut basis = vec![0.0; n * k];
    for (j, v) in q[rank..].iter().enumerate() {
        for i in 0..n {
            basis[i * k + j] = v[i];
        }
    }
    (basis, k)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    /// Simulation-based calibration of [`CutScale`] on its own generative model: τ from
    /// the prior, d ~ N(0, τ² I) over 4 modes of which one direction is absorbed by a unit
    /// coordinate (k = 3, step 2's case), mean residuals with standard errors of a tenth of
    /// τ₀. The posterior's 90 % interval must hold τ, and the posterior predictive's 90 %
    /// interval a new (validation) mode's d, at the nominal rate: 400 replicates, the count
    /// within 3 binomial sds of 360.
    #[test]
    fn the_cut_scale_and_its_predictive_are_calibrated() {
        let sens = [1.0, 0.8, 1.3, 0.6];
        let disc = Discrepancy::new(&sens, 4, 1, &[], BOLTED_FIDELITY_FREQ, &[]).unwrap();
        assert_eq!(disc.k, 3);
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let se = vec![0.1 * disc.scale_median; 4];
        let (reps, mut tau_in, mut d_in) = (400, 0, 0);
        for _ in 0..reps {
            let z: f64 = StandardNormal.sample(&mut rng);
            let tau = (disc.scale_median.ln() + disc.scale_log_sd * z).exp();
            let m: Vec<f64> = (0..4)
                .map(|i| {
                    let (a, b): (f64, f64) = (
                        StandardNormal.sample(&mut rng),
                        StandardNormal.sample(&mut rng),
                    );
                    tau * a + se[i] * b
                })
                .collect();
            let cut = CutScale::new(&disc, &m, &se).unwrap();
            if (cut.quantile(0.05)..=cut.quantile(0.95)).contains(&tau) {
                tau_in += 1;
            }
            let z: f64 = StandardNormal.sample(&mut rng);
            let d_new = tau * z;
            let mut pred: Vec<f64> = (0..400)
                .map(|_| {
                    let z: f64 = StandardNormal.sample(&mut rng);
                    cut.draw(&mut rng) * z
                })
                .collect();
            pred.sort_by(f64::total_cmp);
            if (pred[20]..=pred[379]).contains(&d_new) {
                d_in += 1;
            }
        }
        for (what, n) in [("tau", tau_in), ("a new mode's d", d_in)] {
            assert!((342..=378).contains(&n), "{what}: {n} of {reps} inside");
        }
    }

    /// Residuals far above the stated fidelity move τ up; residuals at the noise level move
    /// it below the prior's median; nothing to infer (k = 0) or non-finite residuals: none.
    #[test]
    fn the_cut_scale_follows_the_residuals() {
        let sens = [1.0, 0.8, 1.3, 0.6];
        let disc = Discrepancy::new(&sens, 4, 1, &[], BOLTED_FIDELITY_FREQ, &[]).unwrap();
        let t0 = disc.scale_median;
        let se = [1e-4; 4];
        let big = CutScale::new(&disc, &[5.0 * t0, -4.0 * t0, 6.0 * t0, -5.0 * t0], &se).unwrap();
        assert!(big.quantile(0.05) > t0, "{}", big.quantile(0.05));
        let small = CutScale::new(&disc, &[1e-4, -1e-4, 2e-4, 0.0], &se).unwrap();
        assert!(small.quantile(0.5) < 0.5 * t0, "{}", small.quantile(0.5));
        assert!(small.quantile(0.05) < small.quantile(0.5));
        assert!(CutScale::new(&disc, &[f64::NAN, 0.0, 0.0, 0.0], &se).is_none());
        let full = Discrepancy::new(&[1.0, 0.0, 0.0, 1.0], 2, 2, &[], 0.015, &[]);
        assert!(full.is_none());
    }

    #[test]
    fn the_complement_is_orthonormal_and_orthogonal_to_the_columns() {
        // 5 modes, 3 columns of which the third is the sum of the first two: rank 2.
        let (n, c) = (5, 3);
        let cols = [
            [1.0, 0.9, 1.1, 0.5, 2.0],
            [0.2, -0.3, 1.0, 1.5, 0.1],
            [1.2, 0.6, 2.1, 2.0, 2.1],
        ];
        let a: Vec<f64> = (0..n)
            .flat_map(|i| cols.iter().map(move |col| col[i]))
            .collect();
        let (b, k) = complement_basis(&a, n, c);
        assert_eq!(k, 3);
        for j in 0..k {
            for l in 0..k {
                let p: f64 = (0..n).map(|i| b[i * k + j] * b[i * k + l]).sum();
                let want = if j == l { 1.0 } else { 0.0 };
                assert!((p - want).abs() < 1e-12, "({j}, {l}): {p}");
            }
            for col in &cols {
                let p: f64 = (0..n).map(|i| b[i * k + j] * col[i]).sum();
                assert!(p.abs() < 1e-12, "column {col:?}: {p}");
            }
        }
    }

    /// With W = I, M Mᵀ = (SᵀS)⁻¹ (M = (SᵀS)⁻¹Sᵀ); a column the modes do not see (zero, as
    /// the mass scale's is with moduli per unit mass) gets a zero row and column.
    #[test]
    fn the_confounded_part_is_the_least_squares_map_of_an_exchangeable_discrepancy() {
        let (n, c) = (6, 3);
        let cols = [
            [0.9, 0.1, 0.5, 0.8, 0.2, 0.6],
            [0.0; 6],
            [0.1, 0.95, 0.4, 0.3, 0.7, 0.2],
        ];
        let s: Vec<f64> = (0..n)
            .flat_map(|i| cols.iter().map(move |col| col[i]))
            .collect();
        let l = confounded_factor(&s, n, c, &[], &[]);
        let llt = |i: usize, j: usize| (0..c).map(|k| l[i * c + k] * l[j * c + k]).sum::<f64>();
        // (SᵀS)⁻¹ over columns 0 and 2 by the 2 × 2 closed form.
        let dot = |a: &[f64; 6], b: &[f64; 6]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
        let (a, b, d) = (
            dot(&cols[0], &cols[0]),
            dot(&cols[0], &cols[2]),
            dot(&cols[2], &cols[2]),
        );
        let det = a * d - b * b;
        for (i, j, want) in [(0, 0, d / det), (0, 2, -b / det), (2, 2, a / det)] {
            assert!((llt(i, j) - want).abs() < 1e-12 * want.abs(), "({i}, {j})");
        }
        for k in 0..c {
            assert_eq!(llt(1, k), 0.0);
        }
        // The shift scales with τ.
        let disc = Discrepancy::new(&s, n, c, &[], 0.005, &[]).expect("k = 4");
        let z = [0.3, -1.2, 0.7];
        let a1 = disc.confounded_shift(1e-3, &z);
        let a2 = disc.confounded_shift(2e-3, &z);
        for k in 0..c {
            assert!((a2[k] - 2.0 * a1[k]).abs() < 1e-18);
        }
        assert_eq!(a1[1], 0.0);
        // Column 2 pinned: column 0 alone absorbs, (s₀ᵀs₀)⁻¹.
        let l = confounded_factor(&s, n, c, &[], &[2]);
        assert!((l[0] * l[0] - 1.0 / a).abs() < 1e-12 / a);
        assert!(l[2 * c..].iter().all(|v| *v == 0.0));
    }

    #[test]
    fn as_many_independent_columns_as_modes_leave_no_discrepancy() {
        let a = vec![1.0, 0.0, 0.3, 1.0];
        assert!(Discrepancy::new(&a, 2, 2, &[], 0.005, &[]).is_none());
        assert!(Discrepancy::new(&a[..2], 2, 1, &[], 0.005, &[]).is_some());
    }

    /// The prior's draws have the stated scale: the median of τ is τ₀, and d's covariance is
    /// τ² N Nᵀ (its trace is k τ²).
    #[test]
    fn prior_draws_follow_the_stated_fidelity() {
        let a = vec![1.0, 1.0, 1.0, 1.0];
        let disc = Discrepancy::new(&a, 4, 1, &[], 0.005, &[]).expect("k = 3");
        assert!((disc.scale_median - 0.010025).abs() < 1e-12);
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let n = 20_000;
        let mut taus = vec![];
        let mut ratio = 0.0;
        for _ in 0..n {
            let h = disc.sample(&mut rng);
            assert!(disc.log_prior(&h).is_finite());
            let d = disc.bias(&h);
            // Orthogonal to the column: the discrepancy has no mean shift.
            assert!(d.iter().sum::<f64>().abs() < 1e-12);
            let tau = disc.scale(&h);
            ratio += d.iter().map(|v| v * v).sum::<f64>() / (tau * tau);
            taus.push(tau);
        }
        taus.sort_by(f64::total_cmp);
        let median = taus[n / 2];
        assert!((median / disc.scale_median - 1.0).abs() < 0.05, "{median}");
        let mut units: Vec<f64> = (0..2001)
            .map(|_| disc.unit_scale(&disc.sample(&mut rng)))
            .collect();
        units.sort_by(f64::total_cmp);
        let m = units[1000] / disc.unit_scale_median;
        // The sample median's relative sd: 1.5 × 1.2533 / √2001 = 0.042.
        assert!((m - 1.0).abs() < 0.17, "{m}");
        // E[|d|²/τ²] = k = 3 (χ² with 3 degrees of freedom; sd of the mean 0.017).
        assert!(
            (ratio / n as f64 - 3.0).abs() < 0.07,
            "{}",
            ratio / n as f64
        );
    }

    /// With unequal weights the discrepancy is orthogonal to the columns in their metric
    /// (Sᵀ W d = 0), so a weighted least-squares fit of the parameters does not move with it.
    #[test]
    fn the_discrepancy_is_orthogonal_in_the_datas_metric() {
        let (n, c) = (5, 2);
        let cols = [[1.0, 0.9, 1.1, 0.5, 2.0], [0.2, -0.3, 1.0, 1.5, 0.1]];
        let a: Vec<f64> = (0..n)
            .flat_map(|i| cols.iter().map(move |col| col[i]))
            .collect();
        let w = [1.0, 25.0, 4.0, 0.5, 9.0];
        let disc = Discrepancy::new(&a, n, c, &w, 0.005, &[]).expect("k = 3");
        assert_eq!(disc.k, 3);
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for _ in 0..20 {
            let d = disc.bias(&disc.sample(&mut rng));
            for col in &cols {
                let p: f64 = (0..n).map(|i| col[i] * w[i] * d[i]).sum();
                assert!(p.abs() < 1e-14, "{p}");
            }
        }
    }

    #[test]
    fn central_differences_match_a_closed_form() {
        // λ_m = (1 + x0)^(m+1) (1 + x1)^(-1): ∂λ/λ = ((m+1)/(1+x0), −1/(1+x1)).
        let f = |x: &[f64]| -> Option<Vec<f64>> {
            Some(
                (0..3)
                    .map(|m| (1.0 + x[0]).powi(m + 1) / (1.0 + x[1]))
                    .collect(),
            )
        };
        let s = sensitivities(f, &[0.0, 0.0], 3, 1e-4).expect("defined");
        for m in 0..3 {
            assert!((s[m * 2] - (m + 1) as f64).abs() < 1e-6, "{s:?}");
            assert!((s[m * 2 + 1] + 1.0).abs() < 1e-6, "{s:?}");
        }
    }

    #[test]
    fn frequency_and_eigenvalue_discrepancies_invert() {
        for f in [-0.02, 0.0, 0.003, 0.05] {
            assert!((freq_of_eigenvalue(eigenvalue_of_freq(f)) - f).abs() < 1e-15);
        }
    }
}

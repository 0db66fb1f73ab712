//! A normalised Gaussian reference distribution q(g) Π_b q_b(x_b) for tempering to start from
//! (instead of the prior), and its construction from the target alone (a Laplace-type
//! approximation that uses the unit structure). Pure: no I/O.
//!
//! Why: tempered SMC from the prior needs about as many stages as the data carry information
//! (≈ 45 stages for seven boards measured to 0.1 %), and every stage costs mutation sweeps. A
//! reference close to the posterior needs a handful. The SMC stays exact whatever q is (q
//! only has to be normalised and cover the posterior; its error costs stages, not bias), and
//! the log evidence keeps its meaning: tempering q^{1−β} (p L)^β from β = 0 to 1 estimates
//! Z = ∫ p L because q is normalised.
//!
//! Construction ([`laplace_reference`]), for a target whose units are informed by their own
//! data:
//! 1. g⁰ = the coordinate-wise median of prior draws; x_b⁰ likewise, or a start point the
//!    caller knows (`ReferenceOptions::start`), with g⁰'s population location moved to it.
//! 2. Per unit b (in parallel): Newton's method on f_b(x) = log p(x | g) + log L_b(x, g) with
//!    a finite-difference gradient and Hessian (the model is a black box), Levenberg-damped,
//!    with backtracking. The Hessian at the optimum gives the unit's precision.
//! 3. g given the units' optima: adaptive random-walk Metropolis on
//!    log p(g) + Σ_b log ∫ p(x_b | g) L_b(x_b, g) dx_b, each unit's likelihood a quadratic
//!    around x̂_b re-formed at every g from a finite-difference stencil whose model outputs
//!    are cached (no model evaluation; [`GivenUnits`]). Its mode is the next g; steps 2–3
//!    repeat until that mode settles (the error scales in g change the units' weights), and
//!    the chain runs in the last round.
//! 4. q(g) = N(mean, inflation² · cov) of the g chain; q_b = N(mean, inflation² · cov) of
//!    unit b's conditional normals given g ([`GivenUnits::unit_moments`]) over draws of the
//!    chain (N(x̂_b, inflation² · H_b⁻¹) where its prior is not a normal).
//!    Units are independent of g in q; their coupling is restored by the tempering.
//!
//! A modular step's groups each carry their own first-step draw, which moves their units:
//! [`reference_for_aux`] moves the reference to one group's draw (`smc::Start::GroupReferences`).

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use rayon::prelude::*;

use super::smc::{stream_key, Target};
use super::stats::{
    cholesky_jittered, lower_mul, lower_solve, lower_solve_sq_norm, mean_and_covariance, LN_2PI,
};

/// A multivariate normal with a lower Cholesky factor (row-major).
#[derive(Clone, Debug, serde::Serialize)]
pub struct Mvn {
    pub mean: Vec<f64>,
    pub chol: Vec<f64>,
    /// log det L (= ½ log det Σ).
    log_det_l: f64,
}

impl Mvn {
    /// From a mean and a covariance (jittered where not positive-definite).
    pub fn new(mean: Vec<f64>, cov: &[f64]) -> Mvn {
        let d = mean.len();
        let (chol, _) = cholesky_jittered(cov, d);
        let log_det_l = (0..d).map(|i| chol[i * d + i].ln()).sum();
        Mvn {
            mean,
            chol,
            log_det_l,
        }
    }
    pub fn dim(&self) -> usize {
        self.mean.len()
    }
    pub fn lpdf(&self, x: &[f64]) -> f64 {
        let d = self.dim();
        if d == 0 {
            return 0.0;
        }
        let ss = lower_solve_sq_norm(&self.chol, d, x, &self.mean);
        -0.5 * (d as f64 * LN_2PI + ss) - self.log_det_l
    }
    pub fn sample(&self, rng: &mut ChaCha8Rng) -> Vec<f64> {
        let d = self.dim();
        let e: Vec<f64> = (0..d).map(|_| StandardNormal.sample(rng)).collect();
        lower_mul(&self.chol, d, &e)
            .iter()
            .zip(&self.mean)
            .map(|(a, m)| a + m)
            .collect()
    }
    /// The covariance L Lᵀ, row-major.
    pub fn covariance(&self) -> Vec<f64> {
        lower_times_upper(&self.chol, self.dim())
    }
    /// Standard deviations (the covariance's diagonal, square-rooted).
    pub fn sd(&self) -> Vec<f64> {
        let d = self.dim();
        (0..d)
            .map(|i| {
                (0..=i)
                    .map(|k| self.chol[i * d + k].powi(2))
                    .sum::<f64>()
                    .sqrt()
            })
            .collect()
    }
}

/// q(g) Π_b q_b(x_b).
#[derive(Clone, Debug, serde::Serialize)]
pub struct GaussianReference {
    pub global: Mvn,
    pub units: Vec<Mvn>,
}

impl GaussianReference {
    /// Why this reference cannot start a tempering, if it cannot: a coordinate whose mean is
    /// not finite, or whose sd is not finite, below 1e-8 (1 + |mean|) or above 1e3 (1 + |mean|),
    /// spreads no posterior of measured data has in the sampler's coordinates (relative
    /// parameters and logarithms of scales; a unit's spread is bounded by its population's).
    /// From such a q the log-weights span hundreds of orders of magnitude and the tempering
    /// stalls (`smc::SmcError::Stalled`), or no draw can be evaluated. The wide kind: a
    /// re-formed quadratic (`ReferenceOptions::reform_curvature`) extrapolated to a curvature
    /// of the wrong sign, measured on the blind rotation campaign's step 2 with its shape terms
    /// down-weighted (unit sd 1.3e154).
    pub fn degeneracy(&self) -> Option<String> {
        let check = |what: &str, m: &Mvn| -> Option<String> {
            m.mean
                .iter()
                .zip(m.sd())
                .enumerate()
                .find_map(|(k, (mu, sd))| {
                    degenerate_coordinate(*mu, sd)
                        .then(|| format!("{what} coordinate {k}: mean {mu:.4e}, sd {sd:.3e}"))
                })
        };
        check("global", &self.global).or_else(|| {
            self.units
                .iter()
                .enumerate()
                .find_map(|(b, u)| check(&format!("unit {b}"), u))
        })
    }
    pub fn sample(&self, rng: &mut ChaCha8Rng) -> (Vec<f64>, Vec<Vec<f64>>) {
        let g = self.global.sample(rng);
        let x = self.units.iter().map(|u| u.sample(rng)).collect();
        (g, x)
    }
}

/// A reference coordinate of mean `mu` and sd `sd` that no sampler can start from: not
/// finite, a spread under 1e-8 of its scale (the data cannot pin a coordinate that tightly
/// through measurement noise) or over 1e3 of it.
fn degenerate_coordinate(mu: f64, sd: f64) -> bool {
    let scale = 1.0 + mu.abs();
    !mu.is_finite() || !sd.is_finite() || sd <= 1e-8 * scale || sd > 1e3 * scale
}

/// Tuning of [`laplace_reference`].
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct ReferenceOptions {
    /// Standard deviations of q are the Laplace ones times this (> 1: q must cover the
    /// posterior; the tempering pays for the excess in stages).
    pub inflation: f64,
    /// Newton iterations per unit and outer round.
    pub newton_iterations: usize,
    /// Most outer rounds (units, then g); fewer where g's mode settles first (see
    /// [`laplace_reference`]).
    pub rounds: usize,
    /// Random-walk Metropolis steps of g per round (after as many for adaptation).
    pub g_steps: usize,
    /// Where every unit's search starts (and g's population location with it), instead of
    /// the prior's centre: a point the caller already knows fits the data, e.g. from a fit of
    /// the mean data. A posterior with several modes (one mechanism trading against another)
    /// is then approached from the best one, not from whichever the prior centre falls near.
    #[serde(default)]
    pub start: Option<Vec<f64>>,
    /// Re-form each unit's likelihood quadratic at every g in the step for g (see
    /// `GivenUnits`): for units of one parameter that can fit some data exactly (a
    /// modular step's joints); off by default. With two (ln K and ln k_rot per measurement)
    /// it ran the demo's ε and δ to e^-75 … e^-244 ([`GaussianReference::degeneracy`] flags
    /// such a result).
    #[serde(default)]
    pub reform_curvature: bool,
    /// Integrate units of one coordinate out of g's density by quadrature
    /// ([`super::unit_quadrature`]) instead of the Laplace form: for a modular step's joints,
    /// whose one stiffness per measurement can fit a mode it barely moves, where the Laplace
    /// form puts a false peak at ε → 0. Needs the units' prior as a normal
    /// ([`Target::unit_prior_normal`]); takes precedence over `reform_curvature`.
    #[serde(default)]
    pub quadrature_units: bool,
    /// Where the rounds reach a degenerate reference (units whose coordinates can fit their
    /// modes let the alternation run the noise scales towards zero, a unit of zero spread,
    /// before g settles), the reference these first rounds gave instead: the construction
    /// before g's mode had to settle, which covers such a posterior and lets the tempering
    /// correct it. The rounds stop as soon as a unit's spread collapses, and the fallback
    /// resumes from the state these rounds left, so it costs no round twice. None: no
    /// fallback.
    #[serde(default = "default_fallback_rounds")]
    pub fallback_rounds: Option<usize>,
}

fn default_fallback_rounds() -> Option<usize> {
    Some(FALLBACK_ROUNDS)
}

impl Default for ReferenceOptions {
    fn default() -> Self {
        ReferenceOptions {
            inflation: 1.3,
            newton_iterations: 30,
            rounds: MAX_ROUNDS,
            g_steps: 20000,
            start: None,
            reform_curvature: false,
            quadrature_units: false,
            fallback_rounds: default_fallback_rounds(),
        }
    }
}

/// What the construction found, for the report.
#[derive(Clone, Debug, serde::Serialize)]
pub struct ReferenceInfo {
    /// Model evaluations spent.
    pub model_evals: u64,
    /// Acceptance rate of the last round's g chain.
    pub g_acceptance: f64,
    /// Per unit: Newton converged (relative step below tolerance) in the last round.
    pub converged: Vec<bool>,
    /// Rounds run (see [`laplace_reference`]); after a fallback, the fallback's.
    pub rounds: usize,
    /// Why the rounds fell back to their first `ReferenceOptions::fallback_rounds`, and after
    /// how many.
    pub fell_back: Option<(usize, String)>,
    /// Why the construction was run again from the start the target's data gave
    /// ([`Target::data_start_global`]); the counts above are the second run's, but
    /// `model_evals`, which holds both.
    pub restarted: Option<String>,
}

/// Errors of the construction.
#[derive(Debug, thiserror::Error)]
pub enum ReferenceError {
    #[error(
        "unit {0}: the model is undefined at the unit's reference point (the prior's centre, or the optimum a search reached), so no reference can be built there"
    )]
    Undefined(usize),
}

/// f_b(x) = log p(x | g) + log L_b(x, g), −∞ where undefined, plus model evaluations made.
fn unit_objective<T: Target>(
    t: &T,
    aux: &[f64],
    ctx: &T::Ctx,
    b: usize,
    x: &[f64],
) -> (f64, Option<T::Cache>) {
    let lp = t.log_prior_unit(ctx, b, x);
    if !lp.is_finite() {
        return (f64::NEG_INFINITY, None);
    }
    match t.model(aux, b, x) {
        Some(c) => {
            let l = t.log_lik(ctx, b, x, &c);
            (
                if l.is_nan() {
                    f64::NEG_INFINITY
                } else {
                    lp + l
                },
                Some(c),
            )
        }
        None => (f64::NEG_INFINITY, None),
    }
}

/// The points of the central-difference stencil at x with steps h: x, then x ± h_i e_i for
/// each i, then x + (s_i h_i, s_j h_j) for each i > j and signs (+,+), (−,−), (+,−), (−,+):
/// 2d² + 1 points, in the order [`stencil_derivatives`] reads their values.
fn stencil_points(x: &[f64], h: &[f64]) -> Vec<Vec<f64>> {
    let d = x.len();
    let mut pts = Vec::with_capacity(2 * d * d + 1);
    pts.push(x.to_vec());
    for i in 0..d {
        for s in [1.0, -1.0] {
            let mut p = x.to_vec();
            p[i] += s * h[i];
            pts.push(p);
        }
    }
    for i in 0..d {
        for j in 0..i {
            for (si, sj) in [(1.0, 1.0), (-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0)] {
                let mut p = x.to_vec();
                p[i] += si * h[i];
                p[j] += sj * h[j];
                pts.push(p);
            }
        }
    }
    pts
}

/// (f(x), gradient, Hessian row-major) from f's values at [`stencil_points`]; None where a
/// value is not finite.
fn stencil_derivatives(v: &[f64], h: &[f64]) -> Option<(f64, Vec<f64>, Vec<f64>)> {
    let d = h.len();
    if v.iter().any(|f| !f.is_finite()) {
        return None;
    }
    let f0 = v[0];
    let mut g = vec![0.0; d];
    let mut hess = vec![0.0; d * d];
    for i in 0..d {
        let (fp, fm) = (v[1 + 2 * i], v[2 + 2 * i]);
        g[i] = (fp - fm) / (2.0 * h[i]);
        hess[i * d + i] = (fp - 2.0 * f0 + fm) / (h[i] * h[i]);
    }
    let mut k = 1 + 2 * d;
    for i in 0..d {
        for j in 0..i {
            let hij = (v[k] + v[k + 1] - v[k + 2] - v[k + 3]) / (4.0 * h[i] * h[j]);
            hess[i * d + j] = hij;
            hess[j * d + i] = hij;
            k += 4;
        }
    }
    Some((f0, g, hess))
}

/// Finite-difference gradient and Hessian of `f` at x with steps h (central differences:
/// 2d² + 1 evaluations). Returns (f(x), grad, hessian row-major), None where f is not finite
/// at a stencil point.
fn fd_newton_terms(
    f: &mut dyn FnMut(&[f64]) -> f64,
    x: &[f64],
    h: &[f64],
) -> Option<(f64, Vec<f64>, Vec<f64>)> {
    let mut v = Vec::with_capacity(2 * x.len() * x.len() + 1);
    for p in stencil_points(x, h) {
        let f = f(&p);
        if !f.is_finite() {
            return None;
        }
        v.push(f);
    }
    stencil_derivatives(&v, h)
}

/// Solve (A) x = b for a symmetric positive-definite A via its (jittered) Cholesky factor.
fn spd_solve(a: &[f64], d: usize, b: &[f64]) -> Vec<f64> {
    let (l, _) = cholesky_jittered(a, d);
    upper_solve_transposed(&l, d, &lower_solve(&l, d, b))
}

/// Inverse of a symmetric positive-definite matrix.
pub(crate) fn spd_inverse(a: &[f64], d: usize) -> Vec<f64> {
    let mut inv = vec![0.0; d * d];
    for j in 0..d {
        let mut e = vec![0.0; d];
        e[j] = 1.0;
        let c = spd_solve(a, d, &e);
        for i in 0..d {
            inv[i * d + j] = c[i];
        }
    }
    inv
}

/// Eigenvalues (clamped to ≥ `floor`) and eigenvectors (column k of the row-major d × d
/// matrix) of the symmetric part of `a` (faer's self-adjoint eigen-decomposition; the
/// matrices are unit-sized, d ≤ ~10).
fn clamped_eigen(a: &[f64], d: usize, floor: f64) -> (Vec<f64>, Vec<f64>) {
    // NaN stays NaN (`f64::max` would return the floor), so a non-finite matrix gives a
    // NaN density, which the callers turn into −∞, not a finite one.
    let clamp = |v: f64| if v.is_nan() { v } else { v.max(floor) };
    if d == 1 {
        // One coordinate per unit (a joint's stiffness in step 2): the reference's random
        // walk on g calls this per unit and step, and faer's decomposition of a 1 × 1 matrix
        // (its allocations) was most of the reference's time there.
        return (vec![clamp(a[0])], vec![1.0]);
    }
    let m = faer::Mat::<f64>::from_fn(d, d, |i, j| 0.5 * (a[i * d + j] + a[j * d + i]));
    let Ok(evd) = m.as_ref().self_adjoint_eigen(faer::Side::Lower) else {
        // Not expected for finite input; fall back to the clamped diagonal.
        let mut u = vec![0.0; d * d];
        (0..d).for_each(|i| u[i * d + i] = 1.0);
        return ((0..d).map(|i| clamp(a[i * d + i])).collect(), u);
    };
    let (u, lam) = (evd.U(), evd.S());
    (
        (0..d).map(|k| clamp(lam[k])).collect(),
        (0..d * d).map(|idx| u[(idx / d, idx % d)]).collect(),
    )
}

/// The positive-definite part of a symmetric matrix: U max(Λ, floor) Uᵀ.
fn make_positive(a: &[f64], d: usize, floor: f64) -> Vec<f64> {
    if d == 1 {
        return vec![a[0].max(floor)];
    }
    let (lam, u) = clamped_eigen(a, d, floor);
    (0..d * d)
        .map(|idx| {
            let (i, j) = (idx / d, idx % d);
            (0..d).map(|k| u[i * d + k] * lam[k] * u[j * d + k]).sum()
        })
        .collect()
}

/// The smallest curvature [`newton_mode`] keeps, relative to each coordinate's own (the
/// Hessian's eigenvalues after scaling to unit diagonal, [`make_positive_scaled`]).
const NEWTON_CURVATURE_FLOOR: f64 = 1e-8;

/// [`make_positive`] in the coordinates' own scales: with S = diag(√|a_ii|), the eigenvalues
/// of S⁻¹ A S⁻¹ are clamped to ≥ `rel_floor`, then scaled back. A floor relative to the
/// largest diagonal entry depends on the coordinates' units: a board's mass pinned by the
/// balance to 3e-6 against a shear modulus the modes leave at 3e-2 is a precision ratio of
/// 1e8, and a floor of 1e-8 of the largest then overwrote the shear modulus's curvature (the
/// lumped-mass campaign with the mass term at the balance's precision, whose Laplace reference
/// then diverged). A coordinate with zero curvature is scaled by the largest, as before.
fn make_positive_scaled(a: &[f64], d: usize, rel_floor: f64) -> Vec<f64> {
    let diag_max = (0..d)
        .map(|i| a[i * d + i].abs())
        .filter(|v| v.is_finite())
        .fold(0.0, f64::max)
        .max(1e-300);
    let s: Vec<f64> = (0..d)
        .map(|i| {
            let v = a[i * d + i].abs();
            if v.is_finite() && v > 0.0 {
                v.sqrt()
            } else {
                diag_max.sqrt()
            }
        })
        .collect();
    let scaled: Vec<f64> = (0..d * d).map(|k| a[k] / (s[k / d] * s[k % d])).collect();
    make_positive(&scaled, d, rel_floor)
        .iter()
        .enumerate()
        .map(|(k, v)| v * s[k / d] * s[k % d])
        .collect()
}

/// Newton's method on one unit's f_b; returns (x̂, precision −∇²f at x̂, converged, evals).
fn unit_mode<T: Target>(
    t: &T,
    aux: &[f64],
    ctx: &T::Ctx,
    b: usize,
    x0: &[f64],
    h0: &[f64],
    iterations: usize,
) -> (Vec<f64>, Vec<f64>, bool, u64) {
    let mut evals = 0u64;
    let mut f = |x: &[f64]| -> f64 {
        evals += 1;
        unit_objective(t, aux, ctx, b, x).0
    };
    let (x, p, c) = newton_mode(&mut f, x0, h0, iterations);
    (x, p, c, evals)
}

/// Damped Newton ascent of a black-box f from x0 with finite-difference derivatives (initial
/// steps h0, then a fifth of the local sd); returns (x̂, precision −∇²f at x̂ made
/// positive-definite, converged).
pub(crate) fn newton_mode(
    f: &mut dyn FnMut(&[f64]) -> f64,
    x0: &[f64],
    h0: &[f64],
    iterations: usize,
) -> (Vec<f64>, Vec<f64>, bool) {
    let d = x0.len();
    let mut x = x0.to_vec();
    let mut h = h0.to_vec();
    let mut lambda = 1e-3;
    let mut converged = false;
    let mut prec = vec![0.0; d * d];
    for i in 0..d {
        prec[i * d + i] = 1.0 / (h0[i] * h0[i] * 1e4);
    }
    for _ in 0..iterations {
        let Some((f0, g, hess)) = fd_newton_terms(f, &x, &h) else {
            // A stencil point left the model's domain: shrink the steps and retry.
            h.iter_mut().for_each(|v| *v *= 0.25);
            continue;
        };
        // Precision = −Hessian, made positive-definite (the objective need not be concave
        // far from the mode).
        let neg: Vec<f64> = hess.iter().map(|v| -v).collect();
        let p = make_positive_scaled(&neg, d, NEWTON_CURVATURE_FLOOR);
        prec = p.clone();
        let mut accepted = false;
        for _ in 0..20 {
            let mut a = p.clone();
            for i in 0..d {
                a[i * d + i] *= 1.0 + lambda;
            }
            let step = spd_solve(&a, d, &g);
            let xn: Vec<f64> = x.iter().zip(&step).map(|(a, s)| a + s).collect();
            let fnew = f(&xn);
            if fnew.is_finite() && fnew >= f0 - 1e-12 * f0.abs() {
                // Converged when the step is small against the posterior sd.
                let sd: Vec<f64> = {
                    let inv = spd_inverse(&p, d);
                    (0..d).map(|i| inv[i * d + i].max(0.0).sqrt()).collect()
                };
                let small = step.iter().zip(&sd).all(|(s, v)| s.abs() <= 1e-3 * v);
                x = xn;
                lambda = (lambda * 0.3).max(1e-9);
                accepted = true;
                // The next stencil: a fraction of the local sd (inside the quadratic
                // region, far above round-off).
                // (Clamped to [1e-4, 1] × the initial step: far from the mode the local
                // curvature can be nearly flat, and a stencil as wide as that flat sd would
                // leave the quadratic region altogether.)
                for i in 0..d {
                    if sd[i].is_finite() && sd[i] > 0.0 {
                        h[i] = (0.2 * sd[i]).clamp(1e-4 * h0[i], h0[i]);
                    }
                }
                if small {
                    converged = true;
                }
                break;
            }
            lambda *= 10.0;
        }
        if converged || !accepted {
            break;
        }
    }
    // Precision at the final point.
    if let Some((_, _, hess)) = fd_newton_terms(f, &x, &h) {
        let neg: Vec<f64> = hess.iter().map(|v| -v).collect();
        prec = make_positive_scaled(&neg, d, NEWTON_CURVATURE_FLOOR);
    }
    (x, prec, converged)
}

/// L Lᵀ of a lower-triangular row-major d × d factor.
fn lower_times_upper(l: &[f64], d: usize) -> Vec<f64> {
    let mut out = vec![0.0; d * d];
    for i in 0..d {
        for j in 0..d {
            out[i * d + j] = (0..d).map(|k| l[i * d + k] * l[j * d + k]).sum();
        }
    }
    out
}

/// log ∫ N(x; m, L Lᵀ) exp(−½ (x − x̂)ᵀ H (x − x̂) + gᵀ (x − x̂)) dx, H positive
/// semi-definite; H = 0 and g = 0 give 0. In the prior's whitened coordinates x = m + L z
/// (stable as L → 0), with u = m − x̂, B = I + Lᵀ H L and c = Lᵀ (g − H u), it is
/// −½ uᵀ H u + gᵀ u − ½ log |B| + ½ cᵀ B⁻¹ c. Evaluated as written, −½ uᵀ H u and the
/// quadratic part of ½ cᵀ B⁻¹ c cancel, and where the prior is wide against a sharply
/// pinned unit (L Lᵀ H large) their round-off is several units of log density and of
/// either sign (test below: +3.0 on a true −34.1), so the density can rise where it falls.
/// The g random walk of the reference, on null-3 with the model-error term (and an
/// adaptive proposal, since dropped), reached population sds of e^3.9 and log densities of
/// 6e10 before this form. Here, with H = Rᵀ R (R = Λ^½ Qᵀ from H's
/// eigen-decomposition, zero rows where H is flat), w = R u and M = R L, the quadratic part
/// is −½ wᵀ (I + M Mᵀ)⁻¹ w (push-through identity), a sum of squares; log |B| = log |I + M Mᵀ|
/// (Sylvester), and the rest, gᵀ u + ½ (Lᵀg)ᵀ B⁻¹ (Lᵀg) − (Lᵀg)ᵀ B⁻¹ Mᵀ w, is of the order of
/// |g| |u| only.
fn log_marginal_quadratic(m: &[f64], l: &[f64], x_hat: &[f64], h: &[f64], g: &[f64]) -> f64 {
    log_marginal_quadratic_root(m, l, x_hat, &psd_root(h, m.len()), g)
}

/// [`log_marginal_quadratic`] given R with Rᵀ R = H ([`psd_root`]; formed once where H is
/// fixed).
fn log_marginal_quadratic_root(m: &[f64], l: &[f64], x_hat: &[f64], r: &[f64], g: &[f64]) -> f64 {
    let d = m.len();
    // Where H is flat (a zero row of R: a direction of zero or, before clamping, negative
    // curvature, or one 1e12 times below the largest), a gradient along it makes the
    // quadratic an unbounded ramp, and its marginal grows linearly in m without end: the
    // reference's random walk on g followed it (the paper demo's joint_rotation refit, a unit
    // optimum at its box edge: μ of ln k_con at −1.1e3, sd 5e-10). The form is read as flat
    // there: the gradient keeps only its part in H's range (R's rows are orthogonal, scaled
    // eigenvectors). With H positive definite, g as given.
    let Whitened { g, u, w, mm } = whitened(m, l, x_hat, r, g);
    let g = &g;
    let gram = |left: bool| -> Vec<f64> {
        // I + M Mᵀ (left) or I + Mᵀ M.
        (0..d * d)
            .map(|idx| {
                let (i, j) = (idx / d, idx % d);
                let s: f64 = if left {
                    (0..d).map(|k| mm[i * d + k] * mm[j * d + k]).sum()
                } else {
                    (0..d).map(|k| mm[k * d + i] * mm[k * d + j]).sum()
                };
                s + if i == j { 1.0 } else { 0.0 }
            })
            .collect()
    };
    let (lc, _) = cholesky_jittered(&gram(true), d);
    let (lb, _) = cholesky_jittered(&gram(false), d);
    let log_det_c: f64 = (0..d).map(|i| 2.0 * lc[i * d + i].ln()).sum();
    let quad = lower_solve(&lc, d, &w).iter().map(|v| v * v).sum::<f64>();
    // Lᵀ g, B⁻¹ Lᵀ g and Mᵀ w.
    let lg: Vec<f64> = (0..d)
        .map(|j| (j..d).map(|q| l[q * d + j] * g[q]).sum())
        .collect();
    let y = lower_solve(&lb, d, &lg);
    let b_inv_lg = upper_solve_transposed(&lb, d, &y);
    let mtw: Vec<f64> = (0..d)
        .map(|j| (0..d).map(|k| mm[k * d + j] * w[k]).sum())
        .collect();
    let gu: f64 = g.iter().zip(&u).map(|(a, b)| a * b).sum();
    let lg_b_lg: f64 = y.iter().map(|v| v * v).sum();
    let cross: f64 = b_inv_lg.iter().zip(&mtw).map(|(a, b)| a * b).sum();
    -0.5 * quad - 0.5 * log_det_c + gu + 0.5 * lg_b_lg - cross
}

/// The gradient `g` with only its part in the range of H = Rᵀ R (see
/// [`log_marginal_quadratic_root`]): along a flat row of R (zero, or below 1e-12 of the
/// largest curvature: the ramp's crest as far off as the gradient over that curvature) a
/// gradient would make the quadratic an unbounded ramp. With H positive definite, g as given.
fn gradient_in_range(r: &[f64], g: &[f64]) -> Vec<f64> {
    let d = g.len();
    let row_sq: Vec<f64> = (0..d)
        .map(|k| (0..d).map(|q| r[k * d + q] * r[k * d + q]).sum())
        .collect();
    let flat = 1e-12 * row_sq.iter().fold(0.0f64, |a, &b| a.max(b));
    if row_sq.iter().all(|&n| n > flat) {
        return g.to_vec();
    }
    let mut gp = vec![0.0; d];
    for k in (0..d).filter(|&k| row_sq[k] > flat) {
        let c = (0..d).map(|q| r[k * d + q] * g[q]).sum::<f64>() / row_sq[k];
        for q in 0..d {
            gp[q] += c * r[k * d + q];
        }
    }
    gp
}

/// The terms a unit's prior N(m, L Lᵀ) and quadratic likelihood (H = Rᵀ R, gradient g at
/// x̂) share in the prior's whitened coordinates: the gradient in H's range
/// ([`gradient_in_range`]), u = m − x̂, w = R u and M = R L (row-major).
struct Whitened {
    g: Vec<f64>,
    u: Vec<f64>,
    w: Vec<f64>,
    mm: Vec<f64>,
}

fn whitened(m: &[f64], l: &[f64], x_hat: &[f64], r: &[f64], g: &[f64]) -> Whitened {
    let d = m.len();
    let u: Vec<f64> = m.iter().zip(x_hat).map(|(a, b)| a - b).collect();
    let w: Vec<f64> = (0..d)
        .map(|k| (0..d).map(|q| r[k * d + q] * u[q]).sum())
        .collect();
    // M = R L (lower-triangular L, row-major).
    let mm: Vec<f64> = (0..d * d)
        .map(|idx| {
            let (k, j) = (idx / d, idx % d);
            (j..d).map(|q| r[k * d + q] * l[q * d + j]).sum()
        })
        .collect();
    Whitened {
        g: gradient_in_range(r, g),
        u,
        w,
        mm,
    }
}

/// The normal N(x; m, L Lᵀ) · exp(−½ (x − x̂)ᵀ Rᵀ R (x − x̂) + gᵀ (x − x̂)) normalised: its
/// mean and covariance (row-major). In the prior's whitened coordinates x = m + L z (stable
/// as L → 0, a population pinned tight), z's precision is B = I + Mᵀ M (M = R L) and its
/// mean B⁻¹ Lᵀ (g − Rᵀ R u), u = m − x̂; so x's mean is m + L z̄ and its covariance
/// L B⁻¹ Lᵀ. The gradient keeps its part in H's range ([`gradient_in_range`]).
fn conditional_normal(
    m: &[f64],
    l: &[f64],
    x_hat: &[f64],
    r: &[f64],
    g: &[f64],
) -> (Vec<f64>, Vec<f64>) {
    let d = m.len();
    let Whitened { g, w, mm, .. } = whitened(m, l, x_hat, r, g);
    // g − Rᵀ w, then c = Lᵀ (g − Rᵀ w).
    let v: Vec<f64> = (0..d)
        .map(|q| g[q] - (0..d).map(|k| r[k * d + q] * w[k]).sum::<f64>())
        .collect();
    let c: Vec<f64> = (0..d)
        .map(|j| (j..d).map(|q| l[q * d + j] * v[q]).sum())
        .collect();
    let b: Vec<f64> = (0..d * d)
        .map(|idx| {
            let (i, j) = (idx / d, idx % d);
            (0..d).map(|k| mm[k * d + i] * mm[k * d + j]).sum::<f64>()
                + if i == j { 1.0 } else { 0.0 }
        })
        .collect();
    let b_inv = spd_inverse(&b, d);
    let z: Vec<f64> = (0..d)
        .map(|i| (0..d).map(|j| b_inv[i * d + j] * c[j]).sum())
        .collect();
    let mean: Vec<f64> = (0..d)
        .map(|i| m[i] + (0..=i).map(|q| l[i * d + q] * z[q]).sum::<f64>())
        .collect();
    // L B⁻¹ Lᵀ.
    let lb: Vec<f64> = (0..d * d)
        .map(|idx| {
            let (i, j) = (idx / d, idx % d);
            (0..=i).map(|q| l[i * d + q] * b_inv[q * d + j]).sum()
        })
        .collect();
    let cov: Vec<f64> = (0..d * d)
        .map(|idx| {
            let (i, j) = (idx / d, idx % d);
            (0..=j).map(|q| lb[i * d + q] * l[j * d + q]).sum()
        })
        .collect();
    (mean, cov)
}

/// R with Rᵀ R = H⁺, H⁺ the positive semi-definite part of a symmetric H (negative
/// eigenvalues taken as 0): R = Λ^½ Uᵀ, row-major d × d.
fn psd_root(h: &[f64], d: usize) -> Vec<f64> {
    let (lam, u) = clamped_eigen(h, d, 0.0);
    eigen_root(&lam, &u, d)
}

/// R with Rᵀ R = U Λ Uᵀ: row k is √λ_k times eigenvector k (`u` row-major, eigenvectors in
/// its columns; Λ ≥ 0).
fn eigen_root(lam: &[f64], u: &[f64], d: usize) -> Vec<f64> {
    (0..d * d)
        .map(|idx| {
            let (k, j) = (idx / d, idx % d);
            lam[k].sqrt() * u[j * d + k]
        })
        .collect()
}

/// How far from a unit's optimum, in the round's posterior sds along a direction, the
/// crest of its quadratic likelihood may sit ([`trusted_root`]).
const TRUST_SDS: f64 = 3.0;

/// R with Rᵀ R = H', H' the positive part of a unit's likelihood curvature `h` at its optimum
/// x̂, raised where needed so that the quadratic's crest, along each of H's eigenvectors
/// v, lies within [`TRUST_SDS`] sds of x̂, sd = 1/√(vᵀ P v) the round's posterior sd along v
/// (P = `prec`, the other directions held): curvature λ ≥ |vᵀ g| / (TRUST_SDS · sd). Why: a direction of slight curvature with a
/// gradient along it (the data's pull balanced by the prior's) makes a crest far beyond
/// any point the curvature was measured at, whose height ½ (vᵀg)²/λ is unbounded as λ → 0.
/// g's density then buys that height by widening the population: on a campaign with an
/// unmodelled mass on every board, the boards' transverse shear moduli (data slope 15 per
/// unit, curvature near zero) ran σ of that coordinate to e²⁵ in one round, then the units
/// to e⁶⁹ and the reference to a degenerate μ. Past the round's posterior bulk the
/// quadratic is extrapolation; the reference is only a proposal, the tempering corrects it.
/// Directions flat to 1e-12 of the largest curvature stay flat ([`gradient_in_range`]).
fn trusted_root(h: &[f64], g: &[f64], prec: &[f64], d: usize) -> Vec<f64> {
    let (mut lam, u) = clamped_eigen(h, d, 0.0);
    let flat = 1e-12 * lam.iter().fold(0.0f64, |a, &b| a.max(b));
    for (k, l) in lam.iter_mut().enumerate() {
        if l.is_nan() || *l <= flat {
            continue;
        }
        let v = |j: usize| u[j * d + k];
        let gk: f64 = (0..d).map(|j| v(j) * g[j]).sum();
        let pk: f64 = (0..d)
            .map(|i| v(i) * (0..d).map(|j| prec[i * d + j] * v(j)).sum::<f64>())
            .sum();
        if pk > 0.0 && pk.is_finite() && gk.is_finite() {
            *l = l.max(gk.abs() * pk.sqrt() / TRUST_SDS);
        }
    }
    eigen_root(&lam, &u, d)
}

/// x with Lᵀ x = y, L lower-triangular row-major.
fn upper_solve_transposed(l: &[f64], d: usize, y: &[f64]) -> Vec<f64> {
    let mut x = y.to_vec();
    for i in (0..d).rev() {
        let s: f64 = (i + 1..d).map(|k| l[k * d + i] * x[k]).sum();
        x[i] = (x[i] - s) / l[i * d + i];
    }
    x
}

/// Coordinate-wise median of vectors.
fn median_of(vs: &[Vec<f64>]) -> Vec<f64> {
    let d = vs[0].len();
    (0..d)
        .map(|k| {
            let mut c: Vec<f64> = vs.iter().map(|v| v[k]).collect();
            c.sort_by(f64::total_cmp);
            c[c.len() / 2]
        })
        .collect()
}

/// The density of g given the units' optima x̂_b (step 3 of the construction):
/// log p(g) + Σ_b log ∫ p(x_b | g) L̃_b(x_b, g) dx_b, where L̃_b is unit b's likelihood as a
/// quadratic in x_b around x̂_b. At the round's g its curvature is the unit's precision less
/// the prior's and its gradient minus the prior's (x̂_b is the optimum). So g sees
/// ∫ p(x_b | g) L_b(x_b) dx_b, not p(x̂_b | g) L_b(x̂_b): with point estimates, units the data
/// leave unidentified would pull σ to zero, a funnel the reference would then sit in. Where
/// p(x_b | g) is not a normal, the point form. No model evaluation: the units' model outputs
/// are cached.
///
/// With `reform` (ReferenceOptions::reform_curvature) the quadratic follows g: the change of
/// the likelihood's gradient and Hessian since the round's g, from a finite-difference
/// stencil around x̂_b whose model outputs are cached, is added. The error scales (ε, δ) are
/// part of g and set how sharply the data pin each unit; a quadratic frozen at one g pays ε's
/// normalising constants without the matching narrowing of the units, so the ascent of g
/// runs towards ε → 0 for a mode the units can fit exactly (one joint stiffness per bolted
/// measurement fitting one bolted mode), a ridge of the profile likelihood the marginal does
/// not have. Far from the round's g the added change is an extrapolation, and with units of
/// several strongly correlated parameters (the boards' moduli and mass scale) it ran ε to
/// e^-100 on the demo's step 1, so it is the modular step's option, not the default.
pub(super) struct GivenUnits<'a, T: Target> {
    t: &'a T,
    xs: &'a [Vec<f64>],
    /// Per unit: the stencil's steps (empty without `reform`), its points (x̂_b first) and the
    /// model outputs there.
    steps: Vec<Vec<f64>>,
    points: Vec<Vec<Vec<f64>>>,
    stencils: Vec<Vec<T::Cache>>,
    /// Per unit, the quadratic at the round's g (None: the point form).
    at_round: Vec<Option<RoundQuadratic>>,
}

/// Times a unit's stencil is shrunk (by 4) before its quadratic stays frozen instead.
const STENCIL_SHRINKS: usize = 4;

/// A unit's stencil steps (empty: no stencil), points (x̂_b first) and model outputs there
/// (None where undefined).
type UnitStencil<C> = (Vec<f64>, Vec<Vec<f64>>, Vec<Option<C>>);

/// See [`GivenUnits`]: the curvature (re-formed) or the root of its positive part (frozen),
/// the gradient, and the stencil's likelihood gradient and Hessian at the round's g (with
/// `reform`).
struct RoundQuadratic {
    /// The re-formed form's curvature at the round's g (empty when frozen).
    curvature: Vec<f64>,
    /// The frozen form's R with Rᵀ R = the positive part of the curvature, formed once
    /// (empty when re-formed: the curvature then changes with g).
    root: Vec<f64>,
    gradient: Vec<f64>,
    stencil: Option<(Vec<f64>, Vec<f64>)>,
}

impl<'a, T: Target> GivenUnits<'a, T> {
    /// The quadratics at `g_round`, with stencils of a fifth of each unit's sd under its
    /// precision `precs[b]` when `reform`.
    pub(super) fn new(
        t: &'a T,
        aux: &[f64],
        g_round: &[f64],
        xs: &'a [Vec<f64>],
        precs: &[Vec<f64>],
        reform: bool,
    ) -> Result<(Self, u64), ReferenceError> {
        let d = t.unit_dim();
        let per_unit: Vec<UnitStencil<T::Cache>> = (0..xs.len())
            .into_par_iter()
            .map(|b| {
                let x = &xs[b];
                if reform {
                    let inv = spd_inverse(&precs[b], d);
                    let mut h: Vec<f64> = (0..d)
                        .map(|i| {
                            let sd = inv[i * d + i].max(0.0).sqrt();
                            (0.2 * sd).max(1e-9 * (1.0 + x[i].abs()))
                        })
                        .collect();
                    // A stencil point outside the model's domain (a unit near the edge where
                    // the model stops being defined): shrink the stencil; if it still leaves
                    // the domain, this unit keeps the quadratic frozen at the round's g.
                    for _ in 0..STENCIL_SHRINKS {
                        let pts = stencil_points(x, &h);
                        let caches: Vec<Option<T::Cache>> =
                            pts.iter().map(|pt| t.model(aux, b, pt)).collect();
                        if caches.iter().all(Option::is_some) {
                            return (h, pts, caches);
                        }
                        h.iter_mut().for_each(|v| *v *= 0.25);
                    }
                }
                (vec![], vec![x.clone()], vec![t.model(aux, b, x)])
            })
            .collect();
        let mut evals = 0u64;
        let mut steps = Vec::with_capacity(xs.len());
        let mut points = Vec::with_capacity(xs.len());
        let mut stencils = Vec::with_capacity(xs.len());
        for (b, (h, pts, caches)) in per_unit.into_iter().enumerate() {
            evals += caches.len() as u64;
            let caches = caches
                .into_iter()
                .collect::<Option<Vec<_>>>()
                .ok_or(ReferenceError::Undefined(b))?;
            steps.push(h);
            points.push(pts);
            stencils.push(caches);
        }
        let round_ctx = t.ctx(g_round);
        let at_round = (0..xs.len())
            .map(|b| {
                let (m, l) = t.unit_prior_normal(&round_ctx, b)?;
                let p = spd_inverse(&lower_times_upper(&l, d), d);
                let h: Vec<f64> = precs[b].iter().zip(&p).map(|(a, q)| a - q).collect();
                let r: Vec<f64> = xs[b].iter().zip(&m).map(|(x, m)| x - m).collect();
                let gradient: Vec<f64> = (0..d)
                    .map(|i| (0..d).map(|j| p[i * d + j] * r[j]).sum())
                    .collect();
                let reform = !steps[b].is_empty();
                let stencil = if reform {
                    let ll: Vec<f64> = points[b]
                        .iter()
                        .zip(&stencils[b])
                        .map(|(pt, c)| t.log_lik(&round_ctx, b, pt, c))
                        .collect();
                    let (_, sg, sh) = stencil_derivatives(&ll, &steps[b])?;
                    Some((sg, sh))
                } else {
                    None
                };
                // Re-formed: the curvature at the round's g, changed per g by the stencil;
                // frozen: only its positive part's root is needed.
                let (curvature, root) = if reform {
                    (h, vec![])
                } else {
                    (vec![], trusted_root(&h, &gradient, &precs[b], d))
                };
                Some(RoundQuadratic {
                    root,
                    curvature,
                    gradient,
                    stencil,
                })
            })
            .collect();
        Ok((
            GivenUnits {
                t,
                xs,
                steps,
                points,
                stencils,
                at_round,
            },
            evals,
        ))
    }

    /// Per unit, its mean and covariance over the draws `gs` of g (the law of total
    /// variance over the conditional normals p(x_b | g) · L̃_b(x_b), L̃_b the round's
    /// quadratic, [`conditional_normal`]); None for a unit in the point form. A unit the data
    /// leave loose follows its population, so its spread is the population's over g's
    /// spread, not its spread at one g: at the mean of a population scale whose posterior
    /// spans a factor of e in sd, the units' spread was 2–6 times too narrow (the underfill
    /// campaign's transverse shear moduli, step 1).
    pub(super) fn unit_moments(&self, gs: &[Vec<f64>]) -> Vec<Option<(Vec<f64>, Vec<f64>)>> {
        let t = self.t;
        let d = t.unit_dim();
        let ctxs: Vec<T::Ctx> = gs.iter().map(|g| t.ctx(g)).collect();
        (0..self.xs.len())
            .map(|b| {
                let q0 = self.at_round[b].as_ref()?;
                let root = if q0.root.is_empty() {
                    psd_root(&make_positive(&q0.curvature, d, 0.0), d)
                } else {
                    q0.root.clone()
                };
                let per: Vec<(Vec<f64>, Vec<f64>)> = ctxs
                    .iter()
                    .filter_map(|ctx| {
                        let (m, l) = t.unit_prior_normal(ctx, b)?;
                        let (mean, cov) =
                            conditional_normal(&m, &l, &self.xs[b], &root, &q0.gradient);
                        (mean.iter().chain(&cov).all(|v| v.is_finite())).then_some((mean, cov))
                    })
                    .collect();
                if per.is_empty() {
                    return None;
                }
                // Law of total variance: the means' spread plus the mean covariance.
                let (mean, mut cov) = mean_and_covariance(per.iter().map(|p| p.0.as_slice()));
                let n = per.len() as f64;
                for (_, c) in &per {
                    cov.iter_mut().zip(c).for_each(|(v, c)| *v += c / n);
                }
                Some((mean, cov))
            })
            .collect()
    }

    fn log_density(&self, g: &[f64]) -> f64 {
        let t = self.t;
        let lp = t.log_prior_global(g);
        if !lp.is_finite() {
            return f64::NEG_INFINITY;
        }
        let ctx = t.ctx(g);
        let mut s = lp;
        for (b, x) in self.xs.iter().enumerate() {
            let ll: Vec<f64> = self.points[b]
                .iter()
                .zip(&self.stencils[b])
                .map(|(p, c)| t.log_lik(&ctx, b, p, c))
                .collect();
            let (Some(q0), Some((m, l))) = (&self.at_round[b], t.unit_prior_normal(&ctx, b)) else {
                s += t.log_prior_unit(&ctx, b, x) + ll[0];
                continue;
            };
            match &q0.stencil {
                None => s += ll[0] + log_marginal_quadratic_root(&m, &l, x, &q0.root, &q0.gradient),
                Some((sg, sh)) => {
                    let Some((l0, grad, hess)) = stencil_derivatives(&ll, &self.steps[b]) else {
                        return f64::NEG_INFINITY;
                    };
                    let d = x.len();
                    let curv: Vec<f64> = (0..d * d)
                        .map(|k| q0.curvature[k] - (hess[k] - sh[k]))
                        .collect();
                    let curv = make_positive(&curv, d, 0.0);
                    let grad: Vec<f64> = (0..d).map(|k| q0.gradient[k] + grad[k] - sg[k]).collect();
                    s += l0 + log_marginal_quadratic(&m, &l, x, &curv, &grad);
                }
            }
        }
        if s.is_nan() {
            f64::NEG_INFINITY
        } else {
            s
        }
    }
}

/// g's density given the units: by quadrature over units of one coordinate
/// (`ReferenceOptions::quadrature_units`), else the Laplace form ([`GivenUnits`]).
enum GDensity<'a, T: Target> {
    Laplace(GivenUnits<'a, T>),
    Quadrature(super::unit_quadrature::QuadratureUnits<'a, T>),
}

impl<'a, T: Target> GDensity<'a, T> {
    fn new(
        t: &'a T,
        aux: &[f64],
        g_round: &[f64],
        xs: &'a [Vec<f64>],
        precs: &[Vec<f64>],
        opts: &ReferenceOptions,
    ) -> Result<(Self, u64), ReferenceError> {
        if opts.quadrature_units && t.unit_dim() == 1 {
            if let Some((q, e)) = super::unit_quadrature::QuadratureUnits::new(t, aux, g_round, xs)
            {
                return Ok((GDensity::Quadrature(q), e));
            }
        }
        let (given, e) = GivenUnits::new(t, aux, g_round, xs, precs, opts.reform_curvature)?;
        Ok((GDensity::Laplace(given), e))
    }

    fn log_density(&self, g: &[f64]) -> f64 {
        match self {
            GDensity::Laplace(u) => u.log_density(g),
            GDensity::Quadrature(u) => u.log_density(g),
        }
    }
}

/// A later round's finite-difference steps on g: a fifth of the sd of the previous round's
/// precision `g_prec` (ng × ng), but never above round 0's steps `hg0` (≥ 1e-8, so the
/// range below is never empty) nor below 1e-10; `hg0` where that sd is not finite. See the
/// round loop of [`laplace_reference`] for why the cap.
fn later_round_steps(g_prec: &[f64], hg0: &[f64]) -> Vec<f64> {
    let ng = hg0.len();
    let inv = spd_inverse(g_prec, ng);
    (0..ng)
        .map(|i| {
            let h = 0.2 * inv[i * ng + i].max(0.0).sqrt();
            if h.is_finite() {
                h.clamp(1e-10, hg0[i])
            } else {
                hg0[i]
            }
        })
        .collect()
}

/// The Gaussian reference of `t` (see the module doc); `aux` = the auxiliary values the
/// units are evaluated with (a representative draw for a modular step, empty otherwise).
///
/// The alternation between the units and g is a coordinate ascent, and it can settle in a
/// basin the data rule out: from the prior's centre, a mode's noise scale that starts large
/// lets the units' fits ignore that mode, whose misfit then keeps the scale large. A
/// reference there misplaces the units (and the surrogate boxes built on it): the tempering
/// still converges, but slowly and on the ROM. Where the target's own data say so
/// ([`Target::data_start_global`]), the construction runs once more from the start they
/// give.
pub fn laplace_reference<T: Target>(
    t: &T,
    aux: &[f64],
    opts: &ReferenceOptions,
    seed: u64,
) -> Result<(GaussianReference, ReferenceInfo), ReferenceError> {
    let (q, info) = construct_reference(t, aux, opts, seed, None)?;
    match t.data_start_global(&q.global.mean) {
        None => Ok((q, info)),
        Some((g0, why)) => {
            let (q2, mut info2) = construct_reference(t, aux, opts, seed, Some(&g0))?;
            info2.model_evals += info.model_evals;
            info2.restarted = Some(why);
            Ok((q2, info2))
        }
    }
}

/// One construction of [`laplace_reference`], g's search starting at `g_start` where given
/// (else at the prior's centre, its population location at `ReferenceOptions::start`).
fn construct_reference<T: Target>(
    t: &T,
    aux: &[f64],
    opts: &ReferenceOptions,
    seed: u64,
    g_start: Option<&[f64]>,
) -> Result<(GaussianReference, ReferenceInfo), ReferenceError> {
    let nu = t.n_units();
    let ng = t.n_global();
    let d = t.unit_dim();
    // 1. Prior centre and spread.
    let draws: Vec<(Vec<f64>, Vec<Vec<f64>>)> = (0..401)
        .map(|i| {
            let mut rng = ChaCha8Rng::seed_from_u64(stream_key(&[seed, 0xFEFE, i]));
            t.sample_prior(&mut rng)
        })
        .collect();
    let gs: Vec<Vec<f64>> = draws.iter().map(|(g, _)| g.clone()).collect();
    let mut g = median_of(&gs);
    let mut xs: Vec<Vec<f64>> = match &opts.start {
        Some(x0) if x0.len() == d => {
            t.centre_global_at(&mut g, x0);
            vec![x0.clone(); nu]
        }
        _ => (0..nu)
            .map(|b| median_of(&draws.iter().map(|(_, x)| x[b].clone()).collect::<Vec<_>>()))
            .collect(),
    };
    if let Some(g0) = g_start {
        debug_assert_eq!(g0.len(), ng, "a start for g of the target's length");
        g = g0.to_vec();
    }
    // Initial finite-difference steps: a hundredth of the prior spread of each coordinate.
    let h0: Vec<Vec<f64>> = (0..nu)
        .map(|b| {
            (0..d)
                .map(|k| {
                    let mut c: Vec<f64> = draws.iter().map(|(_, x)| x[b][k]).collect();
                    c.sort_by(f64::total_cmp);
                    let iqr = c[c.len() * 3 / 4] - c[c.len() / 4];
                    (iqr / 1.35 * 1e-2).max(1e-12)
                })
                .collect()
        })
        .collect();
    let mut precs = vec![vec![0.0; d * d]; nu];
    let mut converged = vec![false; nu];
    let mut evals = 0u64;
    let mut g_prec = vec![0.0; ng * ng];
    let hg0: Vec<f64> = (0..ng)
        .map(|k| {
            let mut c: Vec<f64> = gs.iter().map(|v| v[k]).collect();
            c.sort_by(f64::total_cmp);
            let iqr = c[c.len() * 3 / 4] - c[c.len() / 4];
            (iqr / 1.35 * 1e-2).max(1e-8)
        })
        .collect();
    let rounds = opts.rounds.max(1);
    let mut g_hat_prev: Option<Vec<f64>> = None;
    // The state after the units of round `fallback_rounds` − 1 (g, the units, g's last
    // precision, that round), and whether the construction resumed from it: then that round
    // is the last.
    let fallback = opts.fallback_rounds.filter(|&k| k >= 1 && k < rounds);
    struct Snapshot {
        g: Vec<f64>,
        xs: Vec<Vec<f64>>,
        precs: Vec<Vec<f64>>,
        converged: Vec<bool>,
        g_prec: Vec<f64>,
        round: usize,
    }
    let mut snapshot: Option<Snapshot> = None;
    let mut fell_back: Option<(usize, String)> = None;
    let mut round = 0;
    'construction: loop {
        if fell_back.is_none() {
            let ctx = t.ctx(&g);
            // 2. Units.
            let res: Vec<_> = (0..nu)
                .into_par_iter()
                .map(|b| {
                    let h: Vec<f64> = if round == 0 {
                        h0[b].clone()
                    } else {
                        let inv = spd_inverse(&precs[b], d);
                        (0..d)
                            .map(|i| (0.2 * inv[i * d + i].max(0.0).sqrt()).max(1e-14))
                            .collect()
                    };
                    unit_mode(t, aux, &ctx, b, &xs[b], &h, opts.newton_iterations)
                })
                .collect();
            for (b, (x, p, c, e)) in res.into_iter().enumerate() {
                xs[b] = x;
                precs[b] = p;
                converged[b] = c;
                evals += e;
            }
            if fallback == Some(round + 1) {
                snapshot = Some(Snapshot {
                    g: g.clone(),
                    xs: xs.clone(),
                    precs: precs.clone(),
                    converged: converged.clone(),
                    g_prec: g_prec.clone(),
                    round,
                });
            } else if let Some(why) = snapshot
                .as_ref()
                .and_then(|_| degenerate_unit(&xs, &precs, d).or_else(|| t.collapsed_global(&g)))
            {
                // A unit's spread collapsed: no later round brings it back.
                fell_back = Some((round + 1, why));
                let s = snapshot.take().expect("a snapshot");
                (g, xs, precs, converged, g_prec, round) =
                    (s.g, s.xs, s.precs, s.converged, s.g_prec, s.round);
            }
        }
        let last = fell_back.is_some() || round + 1 >= rounds;
        // 3. g given the units.
        let (given, e) = GDensity::new(t, aux, &g, &xs, &precs, opts)?;
        evals += e;
        let log_g = |g: &[f64]| given.log_density(g);
        // Laplace on g first (its Hessian is the chain's proposal), then a random walk
        // with that proposal: the chain's moments carry what the Gaussian misses (skew in
        // ln σ, the weakly identified correlations).
        // Finite-difference steps: a hundredth of the prior spread in round 0; then a fifth
        // of the previous round's sd, never above the first (a round whose Newton search
        // stopped short of the mode leaves a precision that can be near-singular; steps
        // from it, hundreds of times the prior's hundredth, made every later Hessian
        // garbage, and the reference collapsed to a hundredth of the posterior's spread: the
        // paper campaign in moduli per unit mass, whose pilot run then took 68 stages).
        let hg: Vec<f64> = if round == 0 {
            hg0.clone()
        } else {
            later_round_steps(&g_prec, &hg0)
        };
        let mut fg = |v: &[f64]| log_g(v);
        let (g_hat, prec, _) = newton_mode(&mut fg, &g, &hg, 4 * opts.newton_iterations);
        g_prec = prec;
        let cov = spd_inverse(&g_prec, ng);
        // The rounds alternate between the units given g and g given the units, a
        // coordinate ascent that converges linearly and, along a ridge (an error scale
        // against the units it weighs), slowly; a fixed count can stop it short, with every
        // unit's likelihood too flat in q and the tempering paying in stages. So the rounds
        // go on until g's mode moves by under ROUND_TOLERANCE_SD of its sd (or
        // `opts.rounds` is reached). An earlier round needs only g's mode to place the next
        // units, not the chain's mean: the chain, most of a round's cost, runs in the last
        // round alone.
        let settled = g_hat_prev.as_ref().is_some_and(|p: &Vec<f64>| {
            (0..ng).all(|k| {
                (g_hat[k] - p[k]).abs() <= ROUND_TOLERANCE_SD * cov[k * ng + k].max(0.0).sqrt()
            })
        });
        if !last && !settled {
            g_hat_prev = Some(g_hat.clone());
            g = g_hat;
            round += 1;
            continue;
        }
        let given = match given {
            GDensity::Quadrature(mut q) => {
                // The chain evaluates g's density 2 × g_steps times: only nodes that weigh
                // anywhere near g's mode count (see `QuadratureUnits::prune`).
                q.prune(&sigma_points(&g_hat, &cov, PRUNE_SDS), PRUNE_NATS);
                GDensity::Quadrature(q)
            }
            other => other,
        };
        let log_g = |g: &[f64]| given.log_density(g);
        let (chain, acc) = rwm(
            &log_g,
            &g_hat,
            &cov,
            opts.g_steps,
            seed ^ (round as u64 + 1),
        );
        let n = chain.len() as f64;
        g = (0..ng)
            .map(|k| chain.iter().map(|v| v[k]).sum::<f64>() / n)
            .collect();
        // The units' moments over g's spread, from draws evenly spaced along the chain.
        let every = |n: usize| -> Vec<Vec<f64>> {
            let k = (chain.len() / n).max(1);
            chain.iter().step_by(k).cloned().collect()
        };
        // With quadrature: the units' moments on the last round's grid; without: their
        // moments over g's spread under the Laplace form.
        let (quad_moments, laplace_moments) = match &given {
            GDensity::Quadrature(q) => (Some(q.unit_moments(&every(UNIT_MOMENT_DRAWS))), vec![]),
            GDensity::Laplace(u) => (None, u.unit_moments(&every(LAPLACE_MOMENT_DRAWS))),
        };
        let g_chain = chain;
        // 4. q.
        let q = assemble(
            &g,
            &g_chain,
            &xs,
            &precs,
            &quad_moments,
            &laplace_moments,
            opts,
        );
        if fell_back.is_none() {
            if let (Some(why), Some(s)) =
                (q.degeneracy(), snapshot.take().filter(|s| s.round != round))
            {
                fell_back = Some((round + 1, why));
                (g, xs, precs, converged, g_prec, round) =
                    (s.g, s.xs, s.precs, s.converged, s.g_prec, s.round);
                continue 'construction;
            }
        }
        break 'construction Ok((
            q,
            ReferenceInfo {
                model_evals: evals,
                g_acceptance: acc,
                converged,
                rounds: round + 1,
                fell_back,
                restarted: None,
            },
        ));
    }
}

/// The reference from the last round: g's chain (its mean `g`), the units' optima and
/// precisions, and their moments over g's spread where the round took them.
fn assemble(
    g: &[f64],
    g_chain: &[Vec<f64>],
    xs: &[Vec<f64>],
    precs: &[Vec<f64>],
    quad_moments: &Option<Vec<Option<(f64, f64)>>>,
    laplace_moments: &[Option<(Vec<f64>, Vec<f64>)>],
    opts: &ReferenceOptions,
) -> GaussianReference {
    let ng = g.len();
    let c2 = opts.inflation * opts.inflation;
    let n = g_chain.len() as f64;
    let mut cov = vec![0.0; ng * ng];
    for v in g_chain {
        for i in 0..ng {
            for j in 0..ng {
                cov[i * ng + j] += (v[i] - g[i]) * (v[j] - g[j]) / n;
            }
        }
    }
    cov.iter_mut().for_each(|v| *v *= c2);
    let global = Mvn::new(g.to_vec(), &cov);
    let mut units = unit_references(xs, precs, c2);
    if let Some(m) = quad_moments {
        moment_units(&mut units, m, c2);
    }
    for (u, m) in units.iter_mut().zip(laplace_moments) {
        if let Some((mean, cov)) = m {
            let q = Mvn::new(
                mean.clone(),
                &cov.iter().map(|v| v * c2).collect::<Vec<_>>(),
            );
            if q.mean.iter().chain(&q.chol).all(|v| v.is_finite()) {
                *u = q;
            }
        }
    }
    GaussianReference { global, units }
}

/// The first unit whose spread (from its precision) is degenerate
/// ([`degenerate_coordinate`]), as the reference would name it.
fn degenerate_unit(xs: &[Vec<f64>], precs: &[Vec<f64>], d: usize) -> Option<String> {
    xs.iter().zip(precs).enumerate().find_map(|(b, (x, p))| {
        let inv = spd_inverse(p, d);
        (0..d).find_map(|k| {
            let sd = inv[k * d + k].max(0.0).sqrt();
            degenerate_coordinate(x[k], sd)
                .then(|| format!("unit {b} coordinate {k}: mean {:.4e}, sd {sd:.3e}", x[k]))
        })
    })
}

/// The reference of one group of a modular (cut) posterior: `base`, built with
/// representative auxiliary values (e.g. the first step's posterior mean), moved to the group's
/// own `aux` (one first-step draw). Each group targets the second step given its draw, and
/// the draws spread the units' optima far beyond one unit's posterior width (ten times, on
/// the demo's bolted step), so one q for every group covers none of them well; the tempering
/// then pays for the mismatch in stages and the evidence in variance.
///
/// Warm-started from `base`: per unit a few Newton iterations from its base optimum at g's
/// base mean, then g's mode given the units by an ascent with g's base covariance as the
/// metric (no new Hessian of g), `rounds` times. q_g keeps the base's spreads of g (the
/// spread of g given one draw hardly depends on which) and takes the units' new curvatures.
/// With `opts.quadrature_units` (units of one coordinate) g's
/// density integrates the units on small grids around the base's units and the group's
/// optima ([`group_span`]), one round, and the units take their moments on those grids over
/// q_g's spread. Returns the reference and the model evaluations spent.
pub fn reference_for_aux<T: Target>(
    t: &T,
    base: &GaussianReference,
    aux: &[f64],
    opts: &ReferenceOptions,
    rounds: usize,
) -> Result<(GaussianReference, u64), ReferenceError> {
    let nu = t.n_units();
    let d = t.unit_dim();
    let c2 = opts.inflation * opts.inflation;
    let g_cov: Vec<f64> = base.global.covariance().iter().map(|v| v / c2).collect();
    let mut g = base.global.mean.clone();
    let mut xs: Vec<Vec<f64>> = base.units.iter().map(|u| u.mean.clone()).collect();
    let mut precs = vec![vec![0.0; d * d]; nu];
    let mut evals = 0u64;
    // The group's grids are placed by the base's units, so the quadrature needs no unit
    // prior as a normal (the surrogate target offers none).
    let quadrature = opts.quadrature_units && d == 1;
    // Under quadrature g's density does not depend on the units' curvatures, so one round.
    for _ in 0..if quadrature { 1 } else { rounds.max(1) } {
        let ctx = t.ctx(&g);
        for b in 0..nu {
            let h: Vec<f64> = base.units[b]
                .sd()
                .iter()
                .map(|s| (0.2 * s / opts.inflation).max(1e-14))
                .collect();
            let (x, p, _, e) = unit_mode(t, aux, &ctx, b, &xs[b], &h, opts.newton_iterations);
            xs[b] = x;
            precs[b] = p;
            evals += e;
        }
        if quadrature {
            break;
        }
        let (given, e) = GDensity::new(t, aux, &g, &xs, &precs, opts)?;
        evals += e;
        g = ascend_in_metric(&|v: &[f64]| given.log_density(v), &g, &g_cov, 20);
    }
    let mut units = unit_references(&xs, &precs, c2);
    if quadrature {
        // The group's grids around where the base put each unit and where the group's draw
        // moves its optimum (the base's units carry their spread over g, see
        // `laplace_reference`), then g's mode by a short ascent from the base's (a group's
        // g moves little from it), and the units' moments over q_g's spread.
        let spans: Vec<super::unit_quadrature::Span> = (0..nu)
            .map(|b| group_span(base.units[b].mean[0], base.units[b].sd()[0], xs[b][0]))
            .collect();
        let (q, e) = super::unit_quadrature::QuadratureUnits::with_spans(t, aux, &spans);
        evals += e;
        g = ascend_in_metric(
            &|v: &[f64]| q.log_density(v),
            &g,
            &g_cov,
            GROUP_ASCENT_STEPS,
        );
        let qg = Mvn::new(g.clone(), &g_cov);
        // Fixed draws: the same inputs give the same reference.
        let mut rng = ChaCha8Rng::seed_from_u64(stream_key(&[0x0A55_D4A5]));
        let gs: Vec<Vec<f64>> = (0..UNIT_MOMENT_DRAWS)
            .map(|_| qg.sample(&mut rng))
            .collect();
        moment_units(&mut units, &q.unit_moments(&gs), c2);
    }
    let global = Mvn::new(g, &base.global.covariance());
    Ok((GaussianReference { global, units }, evals))
}

/// g's mode and the points `sds` of g's sds away along each axis of its covariance `cov`
/// (the columns of its Cholesky factor), both ways.
fn sigma_points(g: &[f64], cov: &[f64], sds: f64) -> Vec<Vec<f64>> {
    let ng = g.len();
    let l = Mvn::new(g.to_vec(), cov).chol;
    let mut pts = vec![g.to_vec()];
    for k in 0..ng {
        for sign in [-1.0, 1.0] {
            pts.push((0..ng).map(|i| g[i] + sign * sds * l[i * ng + k]).collect());
        }
    }
    pts
}

/// Where a quadrature's nodes are pruned before g's chain: nodes below their unit's peak by
/// more than `PRUNE_NATS` at g's mode and at `PRUNE_SDS` sds along every axis of its Laplace
/// covariance. Such a node changes its unit's log integral by under 1e-13 there; only in g's
/// far tail, which a reference need not fit, can it weigh more.
const PRUNE_SDS: f64 = 3.0;
const PRUNE_NATS: f64 = 30.0;

/// Draws of g over which units take their quadrature moments
/// ([`super::unit_quadrature::QuadratureUnits::unit_moments`]).
const UNIT_MOMENT_DRAWS: usize = 16;

/// The default cap on the reference's rounds: a round without the chain costs one Newton
/// search per unit and one for g, so the cap only bounds a crawl (see [`laplace_reference`]).
pub const MAX_ROUNDS: usize = 12;

/// The rounds whose reference replaces a degenerate one (`ReferenceOptions::fallback_rounds`):
/// the fixed count the construction had before its rounds went on until g settled. Enrichment
/// refits of step 2 with two or three coordinates a measurement (the realistic fixture's
/// ln K, m_fix and f_fix; a joint's rotational stiffness) reach a unit sd of ~1e-9 by the
/// twelfth round; their 3-round reference covers the posterior (posterior sd / reference sd
/// 0.1–3.5 over g's coordinates) and the tempering takes 13–15 stages. 3 is not fitted to
/// those campaigns: it is the count the construction ran on every step before the rounds
/// went on until g settled (2250d65).
const FALLBACK_ROUNDS: usize = 3;

/// A round whose mode of g moved by less than this many of its sds (every coordinate) from
/// the previous round's is the last: a shift of δ sds costs a normal reference δ²/2 nats of
/// KL divergence per coordinate, 0.045 at 0.3, under the 0.058 its inflation by 1.3 already
/// spends (½ (1/1.69 + ln 1.69 − 1)): an argument from the construction, not a fit to a lab.
const ROUND_TOLERANCE_SD: f64 = 0.3;

/// Draws of g over which units take their moments under the Laplace form
/// ([`GivenUnits::unit_moments`]): closed forms, unit-sized matrices, so many more than
/// under quadrature; 64 reach a population scale's tails where a loose unit's spread comes
/// from.
const LAPLACE_MOMENT_DRAWS: usize = 64;

/// Ascent steps of a group's g under quadrature (from the base's mean, in its metric).
const GROUP_ASCENT_STEPS: usize = 6;

/// A group's grid for one unit: the base's mean `m` and the group's optimum `x` widened by
/// `GROUP_SDS` of the base's (inflated) sd `s` each way, at `NODES_PER_SD` nodes per sd (the
/// midpoint rule's error on a Gaussian of sd s at spacing s/2 is ~1e-34), at most
/// `unit_quadrature::NODES` (coarser on a wider span).
fn group_span(m: f64, s: f64, x: f64) -> super::unit_quadrature::Span {
    const GROUP_SDS: f64 = 6.0;
    const NODES_PER_SD: f64 = 2.0;
    let lo = m.min(x) - GROUP_SDS * s;
    let hi = m.max(x) + GROUP_SDS * s;
    let nodes = (((hi - lo) / s) * NODES_PER_SD).ceil();
    let nodes = if nodes.is_finite() {
        (nodes as usize).clamp(8, super::unit_quadrature::NODES)
    } else {
        super::unit_quadrature::NODES
    };
    super::unit_quadrature::Span { lo, hi, nodes }
}

/// Units of one coordinate replaced by their quadrature moments (variance × `c2`) where
/// those are finite and positive.
fn moment_units(units: &mut [Mvn], moments: &[Option<(f64, f64)>], c2: f64) {
    for (u, m) in units.iter_mut().zip(moments) {
        if let Some((mean, var)) = m {
            if mean.is_finite() && var.is_finite() && *var > 0.0 {
                *u = Mvn::new(vec![*mean], &[var * c2]);
            }
        }
    }
}

/// A reference refitted to a pilot run's posterior: one small SMC from the Laplace reference
/// `q`, then q's global and unit parts replaced by the pilot particles' means and covariances,
/// inflated by `inflation`. The Laplace form is a normal at a mode, and the hierarchy's
/// scale and correlation coordinates have skewed posteriors with few boards: on the demo's
/// step 1 its offsets reached 2.6 sd, which cost 9–10 tempering stages a run. Any normalised
/// q leaves the evidence and posterior exact, so this only changes the cost; it is dropped
/// (and `q` kept) when the pilot's moments are degenerate.
pub fn pilot_reference<T: Target + Sync>(
    t: &T,
    q: &GaussianReference,
    smc_opts: &super::smc::SmcOptions,
    particles: usize,
    inflation: f64,
    seed: u64,
) -> Result<(GaussianReference, usize), super::smc::SmcError>
where
    T::Cache: Send + Sync,
{
    use super::smc;
    let o = smc::SmcOptions {
        n_particles: particles,
        groups: 1,
        ..smc_opts.clone()
    };
    let start = smc::Start::Reference(std::sync::Arc::new(q.clone()));
    let res = smc::run_with(
        t,
        &o,
        smc::stream_key(&[seed, 0x9170]),
        0,
        &start,
        &[],
        &|_| {},
    )?;
    let c2 = inflation * inflation;
    let moments = |(mean, cov): (Vec<f64>, Vec<f64>)| -> Mvn {
        Mvn::new(mean, &cov.iter().map(|v| v * c2).collect::<Vec<_>>())
    };
    let ps = &res.particles;
    let refit = GaussianReference {
        global: moments(mean_and_covariance(ps.iter().map(|p| p.g.as_slice()))),
        units: (0..q.units.len())
            .map(|b| moments(mean_and_covariance(ps.iter().map(|p| p.x[b].as_slice()))))
            .collect(),
    };
    let stages = res.stages.len();
    Ok(match refit.degeneracy() {
        None => (refit, stages),
        Some(_) => (q.clone(), stages),
    })
}

/// Ascent of f from `x0` along `cov` · ∇f (a Newton step when cov is the inverse of −∇²f;
/// the gradient by central differences at a twentieth of each sd), halving the step until f
/// rises; stops when a step is below 1e-3 sd or f stops rising.
fn ascend_in_metric(
    f: &dyn Fn(&[f64]) -> f64,
    x0: &[f64],
    cov: &[f64],
    iterations: usize,
) -> Vec<f64> {
    let d = x0.len();
    let sd: Vec<f64> = (0..d).map(|i| cov[i * d + i].max(0.0).sqrt()).collect();
    let mut x = x0.to_vec();
    let mut fx = f(&x);
    if !fx.is_finite() {
        return x;
    }
    for _ in 0..iterations {
        let mut grad = vec![0.0; d];
        let mut xp = x.clone();
        for i in 0..d {
            let h = (0.05 * sd[i]).max(1e-12);
            xp[i] = x[i] + h;
            let fp = f(&xp);
            xp[i] = x[i] - h;
            let fm = f(&xp);
            xp[i] = x[i];
            grad[i] = (fp - fm) / (2.0 * h);
        }
        if grad.iter().any(|v| !v.is_finite()) {
            break;
        }
        let step: Vec<f64> = (0..d)
            .map(|i| (0..d).map(|j| cov[i * d + j] * grad[j]).sum())
            .collect();
        let mut a = 1.0;
        let mut moved = false;
        for _ in 0..12 {
            let xn: Vec<f64> = x.iter().zip(&step).map(|(v, s)| v + a * s).collect();
            let fnew = f(&xn);
            if fnew.is_finite() && fnew > fx {
                x = xn;
                fx = fnew;
                moved = true;
                break;
            }
            a *= 0.5;
        }
        let small = (0..d).all(|i| (a * step[i]).abs() <= 1e-3 * sd[i]);
        if !moved || small {
            break;
        }
    }
    x
}

/// q_b = N(x̂_b, c2 · precision_b⁻¹) per unit.
fn unit_references(xs: &[Vec<f64>], precs: &[Vec<f64>], c2: f64) -> Vec<Mvn> {
    xs.iter()
        .zip(precs)
        .map(|(x, p)| {
            let mut c = spd_inverse(p, x.len());
            c.iter_mut().for_each(|v| *v *= c2);
            Mvn::new(x.clone(), &c)
        })
        .collect()
}

/// Random-walk Metropolis from `x0` with proposal covariance (2.38²/d) · `cov` (the
/// Laplace covariance), the scale tuned toward 0.25 acceptance during `steps` warm-up steps;
/// `steps` more are kept.
fn rwm(
    f: &dyn Fn(&[f64]) -> f64,
    x0: &[f64],
    cov: &[f64],
    steps: usize,
    seed: u64,
) -> (Vec<Vec<f64>>, f64) {
    let d = x0.len();
    let mut rng = ChaCha8Rng::seed_from_u64(stream_key(&[seed, 0xA11C]));
    let chol = cholesky_jittered(cov, d).0;
    let mut x = x0.to_vec();
    let mut fx = f(&x);
    let mut scale = 2.38 / (d.max(1) as f64).sqrt();
    let mut kept = Vec::with_capacity(steps);
    let mut acc = 0.0;
    for it in 0..2 * steps {
        let e: Vec<f64> = (0..d).map(|_| StandardNormal.sample(&mut rng)).collect();
        let s = lower_mul(&chol, d, &e);
        let xn: Vec<f64> = x.iter().zip(&s).map(|(a, b)| a + scale * b).collect();
        let fnew = f(&xn);
        let u: f64 = rng.random();
        let ok = fnew.is_finite() && u.ln() < fnew - fx;
        if ok {
            x = xn;
            fx = fnew;
        }
        if it < steps {
            let a = if ok { 1.0 } else { 0.0 };
            scale *= ((a - 0.25) / (1.0 + it as f64).sqrt()).exp();
        } else {
            acc += if ok { 1.0 } else { 0.0 };
            kept.push(x.clone());
        }
    }
    (kept, acc / steps.max(1) as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Where the rounds collapse a unit, the construction stops there and returns the
    /// reference of its first `fallback_rounds`, the very one a construction of that many
    /// rounds builds; without the fallback the reference is degenerate. The target is the
    /// error-scale funnel (`funnel_tests`): two coordinates a unit fit two of its three
    /// modes exactly, as a step-2 enrichment refit's do, so the alternation runs an error
    /// scale towards zero.
    #[test]
    fn a_collapsing_construction_falls_back_to_its_first_rounds() {
        let t = crate::bayes::funnel_tests::Funnel::new(30, [0.01, 0.01, 0.01], 7, false);
        let opts = ReferenceOptions {
            g_steps: 2000,
            ..ReferenceOptions::default()
        };
        let none = ReferenceOptions {
            fallback_rounds: None,
            ..opts.clone()
        };
        let (q_none, info_none) = laplace_reference(&t, &[], &none, 3).unwrap();
        assert!(q_none.degeneracy().is_some(), "the toy collapses");
        let (q, info) = laplace_reference(&t, &[], &opts, 3).unwrap();
        let (after, _) = info.fell_back.clone().expect("a fallback");
        assert!(q.degeneracy().is_none());
        assert_eq!(info.rounds, FALLBACK_ROUNDS);
        assert!(after > FALLBACK_ROUNDS && after <= info_none.rounds);
        let three = ReferenceOptions {
            rounds: FALLBACK_ROUNDS,
            ..none
        };
        let (q3, info3) = laplace_reference(&t, &[], &three, 3).unwrap();
        assert!(info3.fell_back.is_none());
        assert_eq!(q.global.mean, q3.global.mean);
        assert_eq!(q.global.chol, q3.global.chol);
        for (a, b) in q.units.iter().zip(&q3.units) {
            assert_eq!((&a.mean, &a.chol), (&b.mean, &b.chol));
        }
        // Fewer model evaluations than the rounds and the rebuild it replaces.
        assert!(info.model_evals < info_none.model_evals + info3.model_evals);
    }

    /// A collapse of g itself ([`Target::collapsed_global`]: an error scale run far below
    /// its prior, the units' spreads intact) falls back as a unit's does: the first check
    /// after the snapshot stops the rounds, and the reference is the first rounds' own, with
    /// the target's reason, for fewer evaluations than rounds until a unit collapses.
    #[test]
    fn a_collapse_of_g_falls_back_to_the_first_rounds() {
        let mut t = crate::bayes::funnel_tests::Funnel::new(30, [0.05, 0.05, 0.05], 7, false);
        let opts = ReferenceOptions {
            g_steps: 2000,
            ..ReferenceOptions::default()
        };
        // The toy's units collapse by themselves, a few rounds after the snapshot.
        let (q0, info0) = laplace_reference(&t, &[], &opts, 3).unwrap();
        let (after0, why0) = info0.fell_back.clone().expect("the units collapse");
        assert!(
            after0 > FALLBACK_ROUNDS + 1 && why0.starts_with("unit"),
            "{why0}"
        );
        // Every g counts as collapsed: the first check after the snapshot falls back, to
        // the same first rounds.
        t.collapse_below = Some(f64::INFINITY);
        let (q, info) = laplace_reference(&t, &[], &opts, 3).unwrap();
        let (after, why) = info.fell_back.clone().expect("a fallback");
        assert_eq!((after, info.rounds), (FALLBACK_ROUNDS + 1, FALLBACK_ROUNDS));
        assert!(why.contains("ln ε_0 below"), "{why}");
        assert_eq!(q.global.mean, q0.global.mean);
        assert_eq!(q.global.chol, q0.global.chol);
        assert!(info.model_evals < info0.model_evals);
    }

    /// Where the target's data reject g's mode ([`Target::data_start_global`]), the reference
    /// is the construction from the start they give, whole (not a blend of the two), its
    /// model evaluations those of both constructions, and why is kept; without a start it is
    /// the first construction's.
    #[test]
    fn a_reference_the_data_reject_is_searched_again_from_their_start() {
        let mut t = crate::bayes::funnel_tests::Funnel::new(30, [0.05, 0.05, 0.05], 7, true);
        let opts = ReferenceOptions {
            g_steps: 2000,
            ..ReferenceOptions::default()
        };
        let (q0, info0) = laplace_reference(&t, &[], &opts, 3).unwrap();
        assert!(info0.restarted.is_none());
        let g0 = vec![0.2f64.ln(); 3];
        t.restart = Some(g0.clone());
        let (q, info) = laplace_reference(&t, &[], &opts, 3).unwrap();
        let (q1, info1) = construct_reference(&t, &[], &opts, 3, Some(&g0)).unwrap();
        assert_eq!(info.restarted.as_deref(), Some("a start the data give"));
        assert_eq!(
            (&q.global.mean, &q.global.chol),
            (&q1.global.mean, &q1.global.chol)
        );
        for (a, b) in q.units.iter().zip(&q1.units) {
            assert_eq!((&a.mean, &a.chol), (&b.mean, &b.chol));
        }
        assert_eq!(info.model_evals, info0.model_evals + info1.model_evals);
        assert_eq!(info.rounds, info1.rounds);
        assert_ne!(
            q.global.mean, q0.global.mean,
            "the second search started elsewhere"
        );
    }

    /// A unit's mass pinned by the balance (sd 2.8e-6) beside a shear modulus the modes
    /// leave at sd 0.03, correlated at 0.5: precisions 1e8 apart. The precision returned is
    /// the Hessian's own; a floor relative to the largest diagonal entry (1e-8 of it, 1.7e3)
    /// raised the weak direction's (~1.1e3) and broke the reference built on it.
    #[test]
    fn newton_keeps_a_weak_coordinates_curvature_beside_a_pinned_one() {
        let (s1, s2, rho) = (2.8e-6f64, 0.03f64, 0.5f64);
        let cov = [s1 * s1, rho * s1 * s2, rho * s1 * s2, s2 * s2];
        let a = spd_inverse(&cov, 2);
        let centre = [0.3, -0.2];
        let mut f = |x: &[f64]| -> f64 {
            let u = [x[0] - centre[0], x[1] - centre[1]];
            -0.5 * (a[0] * u[0] * u[0] + 2.0 * a[1] * u[0] * u[1] + a[3] * u[1] * u[1])
        };
        let (x, prec, converged) = newton_mode(&mut f, &[0.3 + 1e-5, 0.0], &[1e-7, 1e-3], 30);
        assert!(converged);
        assert!((x[0] - centre[0]).abs() < 1e-3 * s1, "{x:?}");
        assert!((x[1] - centre[1]).abs() < 1e-3 * s2, "{x:?}");
        let got = spd_inverse(&prec, 2);
        for k in 0..4 {
            assert!(
                (got[k] - cov[k]).abs() < 1e-4 * cov[k].abs(),
                "{got:?} vs {cov:?}"
            );
        }
    }

    /// The cap of 6ad6da6: a near-singular precision from a round whose Newton search
    /// stopped short (one direction with curvature 1e-6 where round 0's steps were 1e-2)
    /// gives a step of 0.2 / √1e-6 = 200 without it; with it, round 0's step. A
    /// well-conditioned precision keeps its own fifth of an sd, and a singular one (an
    /// infinite or NaN sd) falls back to round 0's.
    #[test]
    fn later_round_steps_never_exceed_round_zeros() {
        let hg0 = [1e-2, 1e-2];
        let near_singular = [1e-6, 0.0, 0.0, 1e4];
        let h = later_round_steps(&near_singular, &hg0);
        assert_eq!(h[0], 1e-2, "capped at round 0's step");
        assert!((h[1] - 0.2 * 1e-2).abs() < 1e-15, "{h:?}");
        let fine = [1e6, 0.0, 0.0, 4e6];
        let h = later_round_steps(&fine, &hg0);
        assert!(
            (h[0] - 0.2e-3).abs() < 1e-15 && (h[1] - 0.1e-3).abs() < 1e-15,
            "{h:?}"
        );
        let singular = [0.0, 0.0, 0.0, 0.0];
        let h = later_round_steps(&singular, &hg0);
        assert!(
            h.iter().all(|v| v.is_finite() && *v > 0.0 && *v <= 1e-2),
            "{h:?}"
        );
    }

    /// A wide prior against a sharply pinned unit: H = Q diag(1e13, 1e7) Qᵀ, L = 50 I,
    /// u = (100, −80), g = 0. With L isotropic the integral factors along H's eigenvectors:
    /// Σ_k −½ w_k² / (1/h_k + ρ²) − ½ ln(1 + ρ² h_k), w = Qᵀ u, each term exact in f64.
    /// The value is within 1e-9 of it; the whitened form as written (−½ uᵀ H u + ½ cᵀ B⁻¹ c,
    /// two ~1e16 terms) gave −31.16 here (run against the previous implementation).
    #[test]
    fn marginal_of_a_wide_prior_against_a_sharp_quadratic_is_exact() {
        let (c, s) = (0.6f64, 0.8f64);
        let hk = [1e13, 1e7];
        // H = Q diag(hk) Qᵀ, Q = [[c, −s], [s, c]].
        let h = [
            hk[0] * c * c + hk[1] * s * s,
            (hk[0] - hk[1]) * c * s,
            (hk[0] - hk[1]) * c * s,
            hk[0] * s * s + hk[1] * c * c,
        ];
        let rho = 50.0;
        let l = [rho, 0.0, 0.0, rho];
        let u = [100.0, -80.0];
        let got = log_marginal_quadratic(&u, &l, &[0.0, 0.0], &h, &[0.0, 0.0]);
        let w = [c * u[0] + s * u[1], -s * u[0] + c * u[1]];
        let want: f64 = (0..2)
            .map(|k| {
                -0.5 * w[k] * w[k] / (1.0 / hk[k] + rho * rho) - 0.5 * (rho * rho * hk[k]).ln_1p()
            })
            .sum();
        assert!((got - want).abs() <= 1e-9, "{got} vs {want}");
    }

    /// A unit quadratic flat along one direction (zero or negative curvature, clamped) with
    /// a gradient along it is an unbounded ramp, whose marginal grows linearly as the prior's
    /// mean m moves along the gradient: it is read as flat there, so the marginal equals the
    /// one without that part of the gradient and stays bounded in m (it ran the demo's
    /// joint_rotation reference to μ = −1.1e3). The part of g in H's range still counts.
    #[test]
    fn a_gradient_along_a_flat_direction_is_no_ramp() {
        let l = [0.5, 0.0, 0.2, 0.4];
        let h = [4.0, 0.0, 0.0, 0.0];
        for h11 in [0.0, -3.0] {
            let h = [h[0], h[1], h[2], h11];
            let hp = make_positive(&h, 2, 0.0);
            for m1 in [0.0, 10.0, -1e3] {
                let m = [0.3, m1];
                let with = log_marginal_quadratic(&m, &l, &[0.1, 0.0], &hp, &[1.5, 40.0]);
                let without = log_marginal_quadratic(&m, &l, &[0.1, 0.0], &hp, &[1.5, 0.0]);
                assert!(
                    (with - without).abs() <= 1e-12 * (1.0 + without.abs()),
                    "{with} vs {without}"
                );
                assert!(with.is_finite() && with < 10.0, "m1 = {m1}: {with}");
            }
        }
        // The range's part: a gradient along the curved direction shifts the marginal.
        let m = [0.3, 0.0];
        let a = log_marginal_quadratic(&m, &l, &[0.1, 0.0], &h, &[1.5, 0.0]);
        let b = log_marginal_quadratic(&m, &l, &[0.1, 0.0], &h, &[0.0, 0.0]);
        assert!((a - b).abs() > 1e-3);
    }

    /// A direction of slight curvature with a gradient along it (the data's pull on a unit
    /// coordinate they barely see, balanced by its prior) has its crest within
    /// [`TRUST_SDS`] round sds of the optimum, so the marginal stays bounded however wide
    /// the population's prior grows; with the plain root it grows to the crest's height
    /// ½ g²/λ (here 1.1e6 nats), which ran a campaign's σ of a shear modulus to e²⁵. A
    /// well-curved direction keeps its curvature.
    #[test]
    fn a_slightly_curved_ramp_has_its_crest_within_reach() {
        let h = [4.0, 0.0, 0.0, 1e-4];
        let sd1 = 0.03;
        let prec = [8.0, 0.0, 0.0, 1.0 / (sd1 * sd1)];
        let g = [0.7, 15.0];
        let r = trusted_root(&h, &g, &prec, 2);
        let rtr = |r: &[f64]| -> Vec<f64> {
            (0..4)
                .map(|idx| {
                    (0..2)
                        .map(|k| r[k * 2 + idx / 2] * r[k * 2 + idx % 2])
                        .sum()
                })
                .collect()
        };
        let hr = rtr(&r);
        assert!((hr[0] - 4.0).abs() < 1e-9 && hr[1].abs() < 1e-9, "{hr:?}");
        let crest = g[1] / hr[3];
        assert!(
            crest <= TRUST_SDS * sd1 * (1.0 + 1e-9) && crest > 0.5 * TRUST_SDS * sd1,
            "crest at {crest}"
        );
        let plain = psd_root(&h, 2);
        let x_hat = [0.1, 0.0];
        let mut worst: f64 = f64::NEG_INFINITY;
        let mut plain_best: f64 = f64::NEG_INFINITY;
        for s in [0.03, 1.0, 1e2, 1e4, 1e6] {
            let l = [0.5, 0.0, 0.0, s];
            let m = [0.3, 0.0];
            worst = worst.max(log_marginal_quadratic_root(&m, &l, &x_hat, &r, &g));
            plain_best = plain_best.max(log_marginal_quadratic_root(&m, &l, &x_hat, &plain, &g));
        }
        assert!(worst < 2.0, "trusted marginal up to {worst}");
        assert!(plain_best > 1e5, "plain marginal up to {plain_best}");
        // Without a gradient along it, the slight curvature is kept.
        let hr = rtr(&trusted_root(&h, &[0.7, 0.0], &prec, 2));
        assert!((hr[3] - 1e-4).abs() < 1e-12, "{hr:?}");
    }

    /// The closed form against a brute-force 2-D quadrature of the same integral.
    #[test]
    fn marginal_of_a_quadratic_likelihood_matches_quadrature() {
        let m = [0.3, -0.2];
        // Σ = L Lᵀ with a correlation; H singular along one direction (an unidentified
        // parameter), g non-zero and not in H's range.
        let l = [0.5, 0.0, 0.2, 0.3];
        let h = [4.0, 2.0, 2.0, 1.0];
        let g = [0.7, -0.4];
        let x_hat = [0.1, 0.25];
        let closed = log_marginal_quadratic(&m, &l, &x_hat, &h, &g);
        // Along H's null direction the form is read as flat (no ramp, see
        // `a_gradient_along_a_flat_direction_is_no_ramp`): the quadrature integrates the
        // gradient's part in H's range, v = (2, 1)/√5.
        let gv = (2.0 * g[0] + g[1]) / 5.0;
        let g = [2.0 * gv, gv];
        let s = lower_times_upper(&l, 2);
        let p = spd_inverse(&s, 2);
        let det_s = s[0] * s[3] - s[1] * s[2];
        let (n, lo, hi) = (1200, -6.0, 6.0);
        let dx = (hi - lo) / n as f64;
        let mut sum = 0.0;
        for i in 0..n {
            for j in 0..n {
                let x = [lo + (i as f64 + 0.5) * dx, lo + (j as f64 + 0.5) * dx];
                let r = [x[0] - m[0], x[1] - m[1]];
                let y = [x[0] - x_hat[0], x[1] - x_hat[1]];
                let q_prior =
                    r[0] * (p[0] * r[0] + p[1] * r[1]) + r[1] * (p[2] * r[0] + p[3] * r[1]);
                let q_lik = y[0] * (h[0] * y[0] + h[1] * y[1]) + y[1] * (h[2] * y[0] + h[3] * y[1]);
                let lpdf = -0.5 * q_prior - (2.0 * std::f64::consts::PI).ln() - 0.5 * det_s.ln();
                sum += (lpdf - 0.5 * q_lik + g[0] * y[0] + g[1] * y[1]).exp() * dx * dx;
            }
        }
        assert!(
            (closed - sum.ln()).abs() < 1e-6,
            "closed form {closed}, quadrature {}",
            sum.ln()
        );
        // A flat likelihood carries no information: the integral of the prior is 1.
        let zero = log_marginal_quadratic(&m, &l, &x_hat, &[0.0; 4], &[0.0; 2]);
        assert!(zero.abs() < 1e-14);
    }

    /// The conditional normal in the whitened form against the precision form written out:
    /// precision P + H, mean (P + H)⁻¹ (P m + H x̂ + g), P = (L Lᵀ)⁻¹, on a correlated 2-D
    /// case; and a population pinned tight (L = 1e-7 I) leaves the unit at the population's
    /// mean with its spread, however sharp the likelihood.
    #[test]
    fn a_units_conditional_normal_matches_the_precision_form() {
        let m = [0.3, -0.2];
        let l = [0.5, 0.0, 0.2, 0.4];
        let x_hat = [0.1, 0.05];
        let h = [40.0, 12.0, 12.0, 9.0];
        let g = [0.7, -1.1];
        let (mean, cov) = conditional_normal(&m, &l, &x_hat, &psd_root(&h, 2), &g);
        let s = lower_times_upper(&l, 2);
        let p = spd_inverse(&s, 2);
        let a: Vec<f64> = p.iter().zip(&h).map(|(p, h)| p + h).collect();
        let a_inv = spd_inverse(&a, 2);
        let rhs: Vec<f64> = (0..2)
            .map(|i| {
                (0..2)
                    .map(|j| p[i * 2 + j] * m[j] + h[i * 2 + j] * x_hat[j])
                    .sum::<f64>()
                    + g[i]
            })
            .collect();
        for i in 0..2 {
            let want: f64 = (0..2).map(|j| a_inv[i * 2 + j] * rhs[j]).sum();
            assert!(
                (mean[i] - want).abs() < 1e-12,
                "mean {mean:?}, coordinate {i}: {want}"
            );
            for j in 0..2 {
                let c = a_inv[i * 2 + j];
                assert!(
                    (cov[i * 2 + j] - c).abs() < 1e-12 * (1.0 + c.abs()),
                    "{cov:?} vs {a_inv:?}"
                );
            }
        }
        let tight = [1e-7, 0.0, 0.0, 1e-7];
        let (mean, cov) = conditional_normal(&m, &tight, &x_hat, &psd_root(&h, 2), &g);
        assert!(
            (mean[0] - m[0]).abs() < 1e-11 && (mean[1] - m[1]).abs() < 1e-11,
            "{mean:?}"
        );
        assert!(
            (cov[0] / 1e-14 - 1.0).abs() < 1e-9 && (cov[3] / 1e-14 - 1.0).abs() < 1e-9,
            "{cov:?}"
        );
    }
}

//! Tempered sequential Monte Carlo for hierarchical models (the sampler kernel; pure, no I/O).
//!
//! Target at inverse temperature β: π_β(g, x) ∝ p(g) Π_b p(x_b | g) · [Π_b L_b(x_b, g)]^β, where
//! g is the global (population and error) vector and x_b the parameters of unit b (a board, a
//! joint). Units are conditionally independent given g, and every unit's likelihood depends
//! on x_b through an expensive model evaluation (the ROM) and on g only through cheap terms
//! (prediction-error scales). [`Target`] exposes exactly that split.
//!
//! One run (Del Moral, Doucet & Jasra 2006, with adaptive tempering as in Jasra et al. 2011):
//! 1. N particles from the prior (β = 0).
//! 2. The next β is chosen by bisection so that the effective sample size of the incremental
//!    weights exp(Δβ · log L) equals `target_ess` · N; the log evidence gains
//!    log mean exp(Δβ · log L) (all weights in log space).
//! 3. Systematic resampling (the resampling is at every stage, so the incremental ESS is
//!    the conditional ESS of Zhou, Johansen & Aston 2016).
//! 4. Mutation by Metropolis-within-Gibbs sweeps, each leaving π_β invariant:
//!    - one random-walk move per unit on x_b with g fixed (one model evaluation per unit:
//!      the cost grows linearly with the units), proposal covariance = the particle cloud's
//!      covariance of x_b, scaled;
//!    - `global_moves` random-walk moves on g with every x_b fixed (the centred
//!      parametrisation): the model outputs are cached per unit, so these cost no model
//!      evaluation at all;
//!    - optionally one move on g with the standardised units z_b = (diag σ L)⁻¹ (x_b − μ)
//!      fixed (the non-centred parametrisation, one model evaluation per unit). Alternating
//!      the two parametrisations is the interweaving strategy of Yu & Meng (2011): the centred
//!      move mixes well when the data pin the units, the non-centred one when they do not.
//!
//!    Proposal scales adapt between sweeps toward `target_acceptance`; sweeps continue until
//!    the mean squared jump, in units of the cloud's covariance, accumulated per coordinate
//!    over the sweeps reaches `jump_target` (an expected-squared-jump-distance rule), between
//!    `min_sweeps` and `max_sweeps`.
//!
//! Randomness: every draw comes from a ChaCha8 stream keyed by (seed, run, stage, sweep,
//! particle), and all reductions over particles run in particle order after the parallel
//! map, so the output does not depend on the thread count.

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use rayon::prelude::*;

use super::resample;
use super::stats::{cholesky_jittered, ess, log_mean_exp, lower_mul, lower_solve};

/// A hierarchical target (see the module doc).
pub trait Target: Sync {
    /// The expensive part of a unit's likelihood (e.g. the ROM's eigenvalues and shapes).
    type Cache: Clone + Send + Sync;
    /// Whatever `g` unpacks into (population parameters, error scales), computed once per g.
    type Ctx: Send + Sync;
    /// Length of the global vector.
    fn n_global(&self) -> usize;
    /// Number of units.
    fn n_units(&self) -> usize;
    /// Parameters per unit.
    fn unit_dim(&self) -> usize;
    /// A draw (g, x_1..x_B) from the prior.
    fn sample_prior(&self, rng: &mut ChaCha8Rng) -> (Vec<f64>, Vec<Vec<f64>>);
    /// log p(g), −∞ outside the support.
    fn log_prior_global(&self, g: &[f64]) -> f64;
    /// Unpack g.
    fn ctx(&self, g: &[f64]) -> Self::Ctx;
    /// log p(x_b | g).
    fn log_prior_unit(&self, ctx: &Self::Ctx, b: usize, x: &[f64]) -> f64;
    /// The model evaluation of unit b at x; `None` where the model is undefined.
    fn model(&self, b: usize, x: &[f64]) -> Option<Self::Cache>;
    /// log L_b from the cached model output (cheap).
    fn log_lik(&self, ctx: &Self::Ctx, b: usize, x: &[f64], cache: &Self::Cache) -> f64;
    /// z = standardised x_b under p(x_b | g).
    fn to_standard(&self, ctx: &Self::Ctx, b: usize, x: &[f64]) -> Vec<f64>;
    /// Inverse of [`Target::to_standard`].
    fn from_standard(&self, ctx: &Self::Ctx, b: usize, z: &[f64]) -> Vec<f64>;
}

/// Tuning of the sampler.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct SmcOptions {
    /// Particles per run.
    pub n_particles: usize,
    /// Target ESS fraction of the incremental weights when choosing the next β.
    pub target_ess: f64,
    /// Target acceptance rate of the random-walk moves.
    pub target_acceptance: f64,
    /// Accumulated mean squared jump per coordinate (in posterior-sd units) that ends the
    /// mutation of a stage.
    pub jump_target: f64,
    pub min_sweeps: usize,
    pub max_sweeps: usize,
    /// Centred moves of g per sweep (they need no model evaluation).
    pub global_moves: usize,
    /// Add one non-centred move of g per sweep.
    pub noncentred: bool,
    /// Give up (with an error) after this many tempering stages.
    pub max_stages: usize,
}

impl Default for SmcOptions {
    fn default() -> Self {
        SmcOptions {
            n_particles: 2000,
            target_ess: 0.5,
            target_acceptance: 0.3,
            jump_target: 1.0,
            min_sweeps: 2,
            max_sweeps: 40,
            global_moves: 5,
            noncentred: true,
            max_stages: 400,
        }
    }
}

/// One particle: the global vector, the units, their cached model outputs and log L_b.
#[derive(Clone, Debug)]
pub struct Particle<C> {
    pub g: Vec<f64>,
    pub x: Vec<Vec<f64>>,
    pub cache: Vec<Option<C>>,
    pub ll: Vec<f64>,
}

impl<C> Particle<C> {
    /// Total log-likelihood.
    pub fn log_lik(&self) -> f64 {
        self.ll.iter().sum()
    }
}

/// What one tempering stage did.
#[derive(Clone, Debug, serde::Serialize)]
pub struct StageInfo {
    pub run: usize,
    pub stage: usize,
    /// β after this stage.
    pub beta: f64,
    /// ESS of the incremental weights, in particles (before resampling).
    pub ess: f64,
    /// log mean of the incremental weights.
    pub log_evidence_increment: f64,
    /// Acceptance rates of the unit moves, centred global moves and non-centred moves.
    pub acceptance_unit: f64,
    pub acceptance_global: f64,
    pub acceptance_noncentred: f64,
    /// Mutation sweeps run.
    pub sweeps: usize,
    /// Distinct particles after resampling (before mutation).
    pub unique_after_resampling: usize,
    /// Model evaluations of this stage (all particles).
    pub model_evals: u64,
}

/// The result of one run.
#[derive(Clone, Debug)]
pub struct RunResult<C> {
    pub particles: Vec<Particle<C>>,
    pub log_evidence: f64,
    pub stages: Vec<StageInfo>,
}

/// Errors of the sampler.
#[derive(Debug, thiserror::Error)]
pub enum SmcError {
    #[error("no prior draw has a finite likelihood ({0} particles): the model cannot be evaluated anywhere the prior puts mass")]
    NoFiniteLikelihood(usize),
    #[error("tempering did not reach β = 1 within {stages} stages (β = {beta:.3e})")]
    TooManyStages { stages: usize, beta: f64 },
}

/// A key mixed from several integers (splitmix64 steps): independent streams per
/// (seed, run, stage, sweep, particle).
pub fn stream_key(parts: &[u64]) -> u64 {
    let mut h: u64 = 0x9E37_79B9_7F4A_7C15;
    for &p in parts {
        h ^= p.wrapping_add(0x9E37_79B9_7F4A_7C15);
        h = h.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = h;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        h = z ^ (z >> 31);
    }
    h
}

fn rng_for(parts: &[u64]) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(stream_key(parts))
}

fn normal_vec(rng: &mut ChaCha8Rng, n: usize) -> Vec<f64> {
    (0..n).map(|_| StandardNormal.sample(rng)).collect()
}

/// Evaluate unit b at x: model output and log L_b (−∞ where the model is undefined).
fn eval_unit<T: Target>(t: &T, ctx: &T::Ctx, b: usize, x: &[f64]) -> (Option<T::Cache>, f64) {
    match t.model(b, x) {
        Some(c) => {
            let l = t.log_lik(ctx, b, x, &c);
            (Some(c), if l.is_nan() { f64::NEG_INFINITY } else { l })
        }
        None => (None, f64::NEG_INFINITY),
    }
}

/// Weighted mean and lower Cholesky factor of the covariance of vectors (equal weights).
fn cloud_cholesky(vs: &[&[f64]]) -> Vec<f64> {
    let d = vs[0].len();
    let n = vs.len() as f64;
    let mut mean = vec![0.0; d];
    for v in vs {
        for k in 0..d {
            mean[k] += v[k] / n;
        }
    }
    let mut cov = vec![0.0; d * d];
    for v in vs {
        for i in 0..d {
            let a = v[i] - mean[i];
            for j in 0..=i {
                cov[i * d + j] += a * (v[j] - mean[j]) / n;
            }
        }
    }
    for i in 0..d {
        for j in 0..i {
            cov[j * d + i] = cov[i * d + j];
        }
        // A collapsed direction (all particles equal) still gets a small step.
        let floor = 1e-12 * (1.0 + mean[i] * mean[i]);
        if cov[i * d + i] < floor {
            cov[i * d + i] = floor;
        }
    }
    cholesky_jittered(&cov, d).0
}

/// Proposal factors for one stage: one per unit, one for g.
struct Proposals {
    unit: Vec<Vec<f64>>,
    global: Vec<f64>,
}

fn proposals<C>(ps: &[Particle<C>], n_units: usize) -> Proposals {
    let unit = (0..n_units)
        .map(|b| cloud_cholesky(&ps.iter().map(|p| p.x[b].as_slice()).collect::<Vec<_>>()))
        .collect();
    let global = cloud_cholesky(&ps.iter().map(|p| p.g.as_slice()).collect::<Vec<_>>());
    Proposals { unit, global }
}

#[derive(Default, Clone, Copy)]
struct SweepStats {
    acc_unit: f64,
    n_unit: f64,
    acc_global: f64,
    n_global: f64,
    acc_nc: f64,
    n_nc: f64,
    /// Σ over units of the whitened squared jump / d.
    jump_unit: f64,
    /// Whitened squared jump of g / dim g.
    jump_global: f64,
    evals: u64,
}

struct Scales {
    unit: f64,
    global: f64,
    nc: f64,
}

/// One Metropolis-within-Gibbs sweep of one particle at β.
#[allow(clippy::too_many_arguments)]
fn sweep<T: Target>(
    t: &T,
    p: &mut Particle<T::Cache>,
    beta: f64,
    prop: &Proposals,
    sc: &Scales,
    opts: &SmcOptions,
    rng: &mut ChaCha8Rng,
) -> SweepStats {
    let mut st = SweepStats::default();
    let d = t.unit_dim();
    let ng = t.n_global();
    let mut ctx = t.ctx(&p.g);
    let tempered = |ll: f64| if beta == 0.0 { 0.0 } else { beta * ll };
    // Unit moves, g fixed.
    for b in 0..t.n_units() {
        let eps = normal_vec(rng, d);
        let step = lower_mul(&prop.unit[b], d, &eps);
        let xn: Vec<f64> = p.x[b]
            .iter()
            .zip(&step)
            .map(|(a, s)| a + sc.unit * s)
            .collect();
        let lp_new = t.log_prior_unit(&ctx, b, &xn);
        let u: f64 = rng.random();
        st.n_unit += 1.0;
        if !lp_new.is_finite() {
            continue;
        }
        let (c, ll) = eval_unit(t, &ctx, b, &xn);
        st.evals += 1;
        let lp_old = t.log_prior_unit(&ctx, b, &p.x[b]);
        let log_r = lp_new + tempered(ll) - lp_old - tempered(p.ll[b]);
        if ll > f64::NEG_INFINITY && u.ln() < log_r {
            let w = lower_solve(&prop.unit[b], d, &step);
            st.jump_unit += sc.unit * sc.unit * w.iter().map(|v| v * v).sum::<f64>() / d as f64;
            p.x[b] = xn;
            p.cache[b] = c;
            p.ll[b] = ll;
            st.acc_unit += 1.0;
        }
    }
    if t.n_units() > 0 {
        st.jump_unit /= t.n_units() as f64;
    }
    // Centred moves of g: no model evaluation.
    let mut lpg = t.log_prior_global(&p.g);
    for _ in 0..opts.global_moves {
        let eps = normal_vec(rng, ng);
        let step = lower_mul(&prop.global, ng, &eps);
        let gn: Vec<f64> =
            p.g.iter()
                .zip(&step)
                .map(|(a, s)| a + sc.global * s)
                .collect();
        let u: f64 = rng.random();
        st.n_global += 1.0;
        let lpg_new = t.log_prior_global(&gn);
        if !lpg_new.is_finite() {
            continue;
        }
        let ctx_new = t.ctx(&gn);
        let mut log_r = lpg_new - lpg;
        let mut ll_new = Vec::with_capacity(t.n_units());
        for b in 0..t.n_units() {
            log_r += t.log_prior_unit(&ctx_new, b, &p.x[b]) - t.log_prior_unit(&ctx, b, &p.x[b]);
            let l = match &p.cache[b] {
                Some(c) => t.log_lik(&ctx_new, b, &p.x[b], c),
                None => f64::NEG_INFINITY,
            };
            log_r += tempered(l) - tempered(p.ll[b]);
            ll_new.push(l);
        }
        if log_r.is_finite() && u.ln() < log_r {
            let w = lower_solve(&prop.global, ng, &step);
            st.jump_global += sc.global * sc.global * w.iter().map(|v| v * v).sum::<f64>();
            p.g = gn;
            ctx = ctx_new;
            p.ll = ll_new;
            lpg = lpg_new;
            st.acc_global += 1.0;
        }
    }
    // One non-centred move of g: units follow through their standardised values.
    if opts.noncentred && t.n_units() > 0 {
        let eps = normal_vec(rng, ng);
        let step = lower_mul(&prop.global, ng, &eps);
        let gn: Vec<f64> = p.g.iter().zip(&step).map(|(a, s)| a + sc.nc * s).collect();
        let u: f64 = rng.random();
        st.n_nc += 1.0;
        let lpg_new = t.log_prior_global(&gn);
        if lpg_new.is_finite() {
            let ctx_new = t.ctx(&gn);
            let mut log_r = lpg_new - lpg;
            let mut moved = Vec::with_capacity(t.n_units());
            for b in 0..t.n_units() {
                let z = t.to_standard(&ctx, b, &p.x[b]);
                let xn = t.from_standard(&ctx_new, b, &z);
                let (c, l) = eval_unit(t, &ctx_new, b, &xn);
                st.evals += 1;
                log_r += tempered(l) - tempered(p.ll[b]);
                moved.push((xn, c, l));
            }
            if log_r.is_finite() && u.ln() < log_r {
                let w = lower_solve(&prop.global, ng, &step);
                st.jump_global += sc.nc * sc.nc * w.iter().map(|v| v * v).sum::<f64>();
                p.g = gn;
                for (b, (xn, c, l)) in moved.into_iter().enumerate() {
                    p.x[b] = xn;
                    p.cache[b] = c;
                    p.ll[b] = l;
                }
                st.acc_nc += 1.0;
            }
        }
    }
    st.jump_global /= ng.max(1) as f64;
    st
}

/// Bisection for the next temperature increment: the largest Δ ≤ 1 − β whose incremental
/// weights keep ESS ≥ target · N.
fn next_increment(ll: &[f64], beta: f64, target: f64) -> f64 {
    let n = ll.len() as f64;
    let ess_at = |delta: f64| -> f64 {
        let lw: Vec<f64> = ll.iter().map(|l| delta * l).collect();
        ess(&lw)
    };
    let max = 1.0 - beta;
    if ess_at(max) >= target * n {
        return max;
    }
    let (mut lo, mut hi) = (0.0, max);
    for _ in 0..100 {
        let mid = 0.5 * (lo + hi);
        if ess_at(mid) >= target * n {
            lo = mid;
        } else {
            hi = mid;
        }
        if hi - lo <= 1e-12 * max.max(1e-300) {
            break;
        }
    }
    lo.max(1e-12 * max)
}

/// Run one tempered SMC from the prior; `observe` sees every stage as it ends.
pub fn run<T: Target>(
    t: &T,
    opts: &SmcOptions,
    seed: u64,
    run_index: usize,
    observe: &(dyn Fn(&StageInfo) + Sync),
) -> Result<RunResult<T::Cache>, SmcError> {
    let n = opts.n_particles;
    let r = run_index as u64;
    let particles: Vec<Particle<T::Cache>> = (0..n)
        .into_par_iter()
        .map(|i| {
            let mut rng = rng_for(&[seed, r, 0, u64::MAX, i as u64]);
            let (g, x) = t.sample_prior(&mut rng);
            let ctx = t.ctx(&g);
            let (cache, ll): (Vec<_>, Vec<_>) = x
                .iter()
                .enumerate()
                .map(|(b, xb)| eval_unit(t, &ctx, b, xb))
                .unzip();
            Particle { g, x, cache, ll }
        })
        .collect();
    run_from(t, opts, seed, run_index, particles, 0.0, observe)
}

/// Continue tempering from `particles` (equally weighted, distributed as π_β at `beta0`).
pub fn run_from<T: Target>(
    t: &T,
    opts: &SmcOptions,
    seed: u64,
    run_index: usize,
    mut particles: Vec<Particle<T::Cache>>,
    beta0: f64,
    observe: &(dyn Fn(&StageInfo) + Sync),
) -> Result<RunResult<T::Cache>, SmcError> {
    let n = particles.len();
    let r = run_index as u64;
    if particles.iter().all(|p| p.log_lik() == f64::NEG_INFINITY) {
        return Err(SmcError::NoFiniteLikelihood(n));
    }
    let d = t.unit_dim().max(1) as f64;
    let mut beta = beta0;
    let mut log_z = 0.0;
    let mut stages = Vec::new();
    let mut scales = Scales {
        unit: 2.38 / d.sqrt(),
        global: 2.38 / (t.n_global().max(1) as f64).sqrt(),
        nc: 2.38 / (t.n_global().max(1) as f64).sqrt(),
    };
    let mut stage = 0usize;
    while beta < 1.0 {
        stage += 1;
        if stage > opts.max_stages {
            return Err(SmcError::TooManyStages {
                stages: opts.max_stages,
                beta,
            });
        }
        let ll: Vec<f64> = particles.iter().map(|p| p.log_lik()).collect();
        let delta = next_increment(&ll, beta, opts.target_ess);
        let lw: Vec<f64> = ll.iter().map(|l| delta * l).collect();
        let inc = log_mean_exp(&lw);
        let ess_inc = ess(&lw);
        log_z += inc;
        beta = if 1.0 - (beta + delta) < 1e-12 {
            1.0
        } else {
            beta + delta
        };
        // Resample.
        let w = super::stats::normalize(&lw);
        let u: f64 = rng_for(&[seed, r, stage as u64, u64::MAX - 1]).random();
        let idx = resample::systematic(&w, n, u);
        let unique = {
            let mut v = idx.clone();
            v.dedup();
            v.len()
        };
        particles = idx.iter().map(|&i| particles[i].clone()).collect();
        // Mutate.
        let prop = proposals(&particles, t.n_units());
        let (mut acc_u, mut acc_g, mut acc_n) = (0.0, 0.0, 0.0);
        let (mut jump_u, mut jump_g) = (0.0, 0.0);
        let mut sweeps = 0;
        let mut evals = 0u64;
        while sweeps < opts.max_sweeps {
            let stats: Vec<SweepStats> = particles
                .par_iter_mut()
                .enumerate()
                .map(|(i, p)| {
                    let mut rng = rng_for(&[seed, r, stage as u64, sweeps as u64, i as u64]);
                    sweep(t, p, beta, &prop, &scales, opts, &mut rng)
                })
                .collect();
            sweeps += 1;
            let mut tot = SweepStats::default();
            for s in &stats {
                tot.acc_unit += s.acc_unit;
                tot.n_unit += s.n_unit;
                tot.acc_global += s.acc_global;
                tot.n_global += s.n_global;
                tot.acc_nc += s.acc_nc;
                tot.n_nc += s.n_nc;
                tot.jump_unit += s.jump_unit;
                tot.jump_global += s.jump_global;
                tot.evals += s.evals;
            }
            evals += tot.evals;
            let rate = |a: f64, m: f64| if m > 0.0 { a / m } else { f64::NAN };
            let (au, ag, an) = (
                rate(tot.acc_unit, tot.n_unit),
                rate(tot.acc_global, tot.n_global),
                rate(tot.acc_nc, tot.n_nc),
            );
            acc_u += au;
            acc_g += ag;
            acc_n += an;
            jump_u += tot.jump_unit / n as f64;
            jump_g += tot.jump_global / n as f64;
            // Adapt the scales toward the target acceptance (population-wide rates).
            let adapt = |s: &mut f64, a: f64| {
                if a.is_finite() {
                    *s = (*s * (a - opts.target_acceptance).exp()).clamp(1e-3, 10.0);
                }
            };
            adapt(&mut scales.unit, au);
            adapt(&mut scales.global, ag);
            adapt(&mut scales.nc, an);
            let units_ok = t.n_units() == 0 || jump_u >= opts.jump_target;
            let global_ok = t.n_global() == 0 || jump_g >= opts.jump_target;
            if sweeps >= opts.min_sweeps && units_ok && global_ok {
                break;
            }
        }
        let k = sweeps as f64;
        let info = StageInfo {
            run: run_index,
            stage,
            beta,
            ess: ess_inc,
            log_evidence_increment: inc,
            acceptance_unit: acc_u / k,
            acceptance_global: acc_g / k,
            acceptance_noncentred: acc_n / k,
            sweeps,
            unique_after_resampling: unique,
            model_evals: evals,
        };
        observe(&info);
        stages.push(info);
    }
    Ok(RunResult {
        particles,
        log_evidence: log_z,
        stages,
    })
}

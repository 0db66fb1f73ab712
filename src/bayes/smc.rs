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
//!    the particles have forgotten where resampling put them: the mean over coordinates of
//!    the correlation, across particles, between each coordinate after resampling and now
//!    falls to `decorrelation_target` (a jump-distance rule: ρ = 1 − E[(x_t − x_0)²]/(2 Var x)
//!    for a stationary cloud), between `min_sweeps` and `max_sweeps`.
//!
//! Randomness: every draw comes from a ChaCha8 stream keyed by (seed, run, stage, sweep,
//! particle), and all reductions over particles run in particle order after the parallel
//! map, so the output does not depend on the thread count.

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use rayon::prelude::*;

use super::resample;
use super::stats::{cholesky_jittered, ess, log_mean_exp, lower_mul};

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
    /// The model evaluation of unit b at x, given the particle's fixed auxiliary values
    /// (e.g. the step-1 board parameters a modular posterior carries; empty when unused);
    /// `None` where the model is undefined.
    fn model(&self, aux: &[f64], b: usize, x: &[f64]) -> Option<Self::Cache>;
    /// log L_b from the cached model output (cheap).
    fn log_lik(&self, ctx: &Self::Ctx, b: usize, x: &[f64], cache: &Self::Cache) -> f64;
    /// z = standardised x_b under p(x_b | g).
    fn to_standard(&self, ctx: &Self::Ctx, b: usize, x: &[f64]) -> Vec<f64>;
    /// Inverse of [`Target::to_standard`].
    #[allow(clippy::wrong_self_convention)] // x from z, the model's own map: not a constructor.
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
    /// The mutation of a stage ends when the mean, over all coordinates (g and every
    /// unit), of the correlation across particles between a coordinate's value after
    /// resampling and its current value has fallen to this level.
    pub decorrelation_target: f64,
    pub min_sweeps: usize,
    pub max_sweeps: usize,
    /// Centred moves of g per sweep (they need no model evaluation).
    pub global_moves: usize,
    /// Non-centred moves of g per sweep (each costs one model evaluation per unit).
    pub noncentred: usize,
    /// Give up (with an error) after this many tempering stages.
    pub max_stages: usize,
}

impl Default for SmcOptions {
    fn default() -> Self {
        SmcOptions {
            n_particles: 2000,
            target_ess: 0.5,
            target_acceptance: 0.3,
            decorrelation_target: 0.5,
            min_sweeps: 2,
            max_sweeps: 25,
            global_moves: 20,
            noncentred: 2,
            max_stages: 400,
        }
    }
}

/// One particle: the global vector, the units, their cached model outputs and log L_b, and
/// fixed auxiliary values that no move changes (shared, as resampling copies them).
#[derive(Clone, Debug)]
pub struct Particle<C> {
    pub aux: std::sync::Arc<Vec<f64>>,
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
    /// Mean correlation between the coordinates after resampling and after mutation.
    pub decorrelation: f64,
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
fn eval_unit<T: Target>(
    t: &T,
    aux: &[f64],
    ctx: &T::Ctx,
    b: usize,
    x: &[f64],
) -> (Option<T::Cache>, f64) {
    match t.model(aux, b, x) {
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
    acc_unit_z: f64,
    n_unit_z: f64,
    acc_global: f64,
    n_global: f64,
    acc_nc: f64,
    n_nc: f64,
    evals: u64,
}

struct Scales {
    unit: f64,
    unit_z: f64,
    global: f64,
    nc: f64,
}

/// Metropolis step of unit b to `xn` (symmetric proposal) with uniform `u`: returns
/// (1 if accepted else 0, model evaluations made).
fn unit_move<T: Target>(
    t: &T,
    p: &mut Particle<T::Cache>,
    ctx: &T::Ctx,
    b: usize,
    xn: Vec<f64>,
    u: f64,
    beta: f64,
) -> (f64, u64) {
    let tempered = |ll: f64| if beta == 0.0 { 0.0 } else { beta * ll };
    let lp_new = t.log_prior_unit(ctx, b, &xn);
    if !lp_new.is_finite() {
        return (0.0, 0);
    }
    let (c, ll) = eval_unit(t, &p.aux, ctx, b, &xn);
    let lp_old = t.log_prior_unit(ctx, b, &p.x[b]);
    let log_r = lp_new + tempered(ll) - lp_old - tempered(p.ll[b]);
    if ll > f64::NEG_INFINITY && u.ln() < log_r {
        p.x[b] = xn;
        p.cache[b] = c;
        p.ll[b] = ll;
        (1.0, 1)
    } else {
        (0.0, 1)
    }
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
        let u: f64 = rng.random();
        st.n_unit += 1.0;
        let (acc, evals) = unit_move(t, p, &ctx, b, xn, u, beta);
        st.acc_unit += acc;
        st.evals += evals;
        // The same unit in its standardised coordinates z = (diag σ L)⁻¹ (x − μ): the
        // proposal follows the particle's own population scale, which is the right one
        // while the data are weak (low β); the move above, scaled by the cloud, is the right
        // one once the data pin the unit. The map is linear given g, so the random walk in z
        // is symmetric in x.
        let z = t.to_standard(&ctx, b, &p.x[b]);
        let zn: Vec<f64> = z
            .iter()
            .map(|v| {
                let e: f64 = StandardNormal.sample(rng);
                v + sc.unit_z * e
            })
            .collect();
        let xn = t.from_standard(&ctx, b, &zn);
        let u: f64 = rng.random();
        st.n_unit_z += 1.0;
        let (acc, evals) = unit_move(t, p, &ctx, b, xn, u, beta);
        st.acc_unit_z += acc;
        st.evals += evals;
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
            p.g = gn;
            ctx = ctx_new;
            p.ll = ll_new;
            lpg = lpg_new;
            st.acc_global += 1.0;
        }
    }
    // Non-centred moves of g: units follow through their standardised values.
    for _ in 0..if t.n_units() > 0 { opts.noncentred } else { 0 } {
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
                let (c, l) = eval_unit(t, &p.aux, &ctx_new, b, &xn);
                st.evals += 1;
                log_r += tempered(l) - tempered(p.ll[b]);
                moved.push((xn, c, l));
            }
            if log_r.is_finite() && u.ln() < log_r {
                p.g = gn;
                ctx = ctx_new;
                lpg = lpg_new;
                for (b, (xn, c, l)) in moved.into_iter().enumerate() {
                    p.x[b] = xn;
                    p.cache[b] = c;
                    p.ll[b] = l;
                }
                st.acc_nc += 1.0;
            }
        }
    }
    st
}

fn flat<C>(p: &Particle<C>) -> Vec<f64> {
    let mut v = p.g.clone();
    for x in &p.x {
        v.extend(x);
    }
    v
}

/// Mean over coordinates of the correlation across particles between `start` and the
/// particles' current values (coordinates constant in either are left out).
fn mean_correlation<C: Sync + Send>(start: &[Vec<f64>], ps: &[Particle<C>]) -> f64 {
    let now: Vec<Vec<f64>> = ps.iter().map(flat).collect();
    let n = start.len() as f64;
    let dim = start[0].len();
    let mut sum = 0.0;
    let mut cnt = 0.0;
    for k in 0..dim {
        let (ma, mb) = (
            start.iter().map(|v| v[k]).sum::<f64>() / n,
            now.iter().map(|v| v[k]).sum::<f64>() / n,
        );
        let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
        for (a, b) in start.iter().zip(&now) {
            let (da, db) = (a[k] - ma, b[k] - mb);
            sab += da * db;
            saa += da * da;
            sbb += db * db;
        }
        if saa > 0.0 && sbb > 0.0 {
            sum += sab / (saa * sbb).sqrt();
            cnt += 1.0;
        }
    }
    if cnt > 0.0 {
        sum / cnt
    } else {
        0.0
    }
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
    run_with_aux(t, opts, seed, run_index, &[], observe)
}

/// [`run`] where particle i carries `aux[i % aux.len()]` (fixed values the model reads and
/// no move changes: e.g. step-1 posterior draws); `aux` empty = no auxiliary values. The
/// initial distribution is then aux × prior, and the log evidence is that of the data given
/// the aux distribution.
pub fn run_with_aux<T: Target>(
    t: &T,
    opts: &SmcOptions,
    seed: u64,
    run_index: usize,
    aux: &[std::sync::Arc<Vec<f64>>],
    observe: &(dyn Fn(&StageInfo) + Sync),
) -> Result<RunResult<T::Cache>, SmcError> {
    let n = opts.n_particles;
    let r = run_index as u64;
    let empty = std::sync::Arc::new(Vec::new());
    let particles: Vec<Particle<T::Cache>> = (0..n)
        .into_par_iter()
        .map(|i| {
            let mut rng = rng_for(&[seed, r, 0, u64::MAX, i as u64]);
            let (g, x) = t.sample_prior(&mut rng);
            let ctx = t.ctx(&g);
            let aux = if aux.is_empty() {
                empty.clone()
            } else {
                aux[i % aux.len()].clone()
            };
            let (cache, ll): (Vec<_>, Vec<_>) = x
                .iter()
                .enumerate()
                .map(|(b, xb)| eval_unit(t, &aux, &ctx, b, xb))
                .unzip();
            Particle {
                aux,
                g,
                x,
                cache,
                ll,
            }
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
        unit_z: 2.38 / d.sqrt(),
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
        let start: Vec<Vec<f64>> = particles.iter().map(flat).collect();
        let mut rho = 1.0;
        let (mut acc_u, mut acc_g, mut acc_n) = (0.0, 0.0, 0.0);
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
                tot.acc_unit_z += s.acc_unit_z;
                tot.n_unit_z += s.n_unit_z;
                tot.acc_global += s.acc_global;
                tot.n_global += s.n_global;
                tot.acc_nc += s.acc_nc;
                tot.n_nc += s.n_nc;
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
            // Adapt the scales toward the target acceptance (population-wide rates).
            let adapt = |s: &mut f64, a: f64| {
                if a.is_finite() {
                    *s = (*s * (a - opts.target_acceptance).exp()).clamp(1e-3, 10.0);
                }
            };
            adapt(&mut scales.unit, au);
            adapt(&mut scales.unit_z, rate(tot.acc_unit_z, tot.n_unit_z));
            adapt(&mut scales.global, ag);
            adapt(&mut scales.nc, an);
            rho = mean_correlation(&start, &particles);
            if sweeps >= opts.min_sweeps && rho <= opts.decorrelation_target {
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
            decorrelation: rho,
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

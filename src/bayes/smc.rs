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
//!    - one componentwise pass over g (one coordinate at a time, no model evaluation).
//!    - per prediction-error scale ε_m the target declares ([`Target::log_error_scales`]),
//!      one move of ln ε_m by s that takes every unit along its residual line, multiplying
//!      its residual of mode m by about e^s (one model evaluation per unit). Where the units
//!      can fit a mode nearly exactly (as many unit parameters as the modes less one) the
//!      likelihood grows without bound as ε_m → 0, and (ε_m, units) form a funnel: the moves
//!      above, which hold the units or their standardised values while ε_m moves, cross it
//!      only by many small steps, and the runs disagree on ε_m (`funnel_tests`).
//!
//!    A move whose proposal lands where the model is expensive (the target offers a cheap
//!    stand-in there, [`Target::screen`]) is a delayed-acceptance move (Christen & Fox 2005):
//!    a first accept/reject with the stand-in, and the model is evaluated only for proposals
//!    that pass it, accepted with the ratio of the model's to the stand-in's acceptance
//!    ratio. The kernel keeps π_β invariant whatever the stand-in's error.
//!
//!    Proposal scales adapt between sweeps toward `target_acceptance`; sweeps continue until
//!    the particles have forgotten where resampling put them: the largest, over coordinates,
//!    correlation across particles between a coordinate after resampling and now falls to
//!    `decorrelation_target` (a jump-distance rule: ρ = 1 − E[(x_t − x_0)²]/(2 Var x) for a
//!    stationary cloud), between `min_sweeps` and `max_sweeps`; below the noise floor of
//!    that largest correlation, by each coordinate's decay extrapolated from its last clear
//!    reading.
//! 5. Tempering may start from a normalised reference q instead of the prior ([`Start`]):
//!    π_β ∝ q^{1−β} (p L)^β; particles may form groups normalised on their own (modular
//!    posteriors, `SmcOptions::groups`); [`correct`] adds a weighting stage at β = 1 (from a
//!    surrogate model to the exact one).
//!
//! Randomness: every draw comes from a ChaCha8 stream keyed by (seed, run, stage, sweep,
//! particle), and all reductions over particles run in particle order after the parallel
//! map, so the output does not depend on the thread count.

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use rayon::prelude::*;

use super::reference::GaussianReference;
use super::resample;
use super::stats::{
    cholesky_jittered, ess, log_mean_exp, lower_mul, lower_solve, lower_transpose_solve,
};

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
    /// [`Target::ctx`] and [`Target::log_prior_global`] of g together (a target whose two
    /// share work overrides it).
    fn ctx_with_prior(&self, g: &[f64]) -> (Self::Ctx, f64) {
        (self.ctx(g), self.log_prior_global(g))
    }
    /// [`Target::ctx_with_prior`] at `gn`, which differs only in coordinate k from the g
    /// whose context `ctx` is (a target can then redo only what k enters; the default redoes
    /// everything).
    fn ctx_after(&self, _ctx: &Self::Ctx, gn: &[f64], _k: usize) -> (Self::Ctx, f64) {
        self.ctx_with_prior(gn)
    }
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
    /// Move g's location of the units' population to the unit point x (a search that knows
    /// where the units are starts its g there); by default g is left as it is.
    fn centre_global_at(&self, _g: &mut [f64], _x: &[f64]) {}
    /// Where a search for g's mode that ended at `g` sits in a basin the target's own data
    /// rule out (e.g. a noise scale far above the scatter of a unit's repeated
    /// measurements): g with those coordinates moved to where the data put them, and why.
    /// None (the default) where the data say nothing against `g`.
    fn data_start_global(&self, _g: &[f64]) -> Option<(Vec<f64>, String)> {
        None
    }
    /// Where a search for g's mode has run a coordinate to where the prior puts no mass, in
    /// the direction a false peak of the search pulls it (e.g. a noise scale towards zero,
    /// where units that can fit a mode exactly make the Laplace form grow without bound):
    /// why. None (the default) where nothing has collapsed. The reference then falls back to
    /// its first rounds (`reference::ReferenceOptions::fallback_rounds`).
    fn collapsed_global(&self, _g: &[f64]) -> Option<String> {
        None
    }
    /// p(x_b | g) as a normal (mean, lower Cholesky factor of its covariance, row-major),
    /// where it is one; None (the default) otherwise.
    fn unit_prior_normal(&self, _ctx: &Self::Ctx, _b: usize) -> Option<(Vec<f64>, Vec<f64>)> {
        None
    }
    /// Expensive model evaluations so far (e.g. the ROM's, where a surrogate could not
    /// answer), for [`SmcOptions::max_expensive_evals_per_particle_unit`]; 0 (the default) where every
    /// evaluation costs alike. The count must not depend on the thread count (count every
    /// call, not the calls of one thread).
    fn expensive_evals(&self) -> u64 {
        0
    }
    /// A cheap stand-in for [`Target::model`] where `model` is expensive at x (e.g. a
    /// surrogate extrapolated beyond its box, where `model` falls back to the ROM), for the
    /// first stage of a delayed-acceptance move; None (the default) where `model` is cheap
    /// or there is no stand-in. It must be a fixed function of (aux, b, x): the moves stay
    /// exact whatever its error (Christen & Fox 2005), its error only costs acceptance.
    fn screen(&self, _aux: &[f64], _b: usize, _x: &[f64]) -> Option<Self::Cache> {
        None
    }
    /// The global coordinates of the per-mode prediction-error scales on the log scale
    /// (ln ε_m, mode m = position in the list), for the moves that scale an error scale
    /// together with the residuals it governs; empty (the default) where g has none.
    fn log_error_scales(&self) -> Vec<usize> {
        vec![]
    }
    /// Which terms of the density g's coordinate k enters (beyond log p(g)): a move of that
    /// coordinate alone re-prices only those. [`GlobalRole::Both`] (the default) is always
    /// correct; the others only save work.
    fn global_role(&self, _k: usize) -> GlobalRole {
        GlobalRole::Both
    }
    /// Unit b's residual of error mode m (the m-th of [`Target::log_error_scales`]) from its
    /// model output, on the scale ε_m measures (e.g. the mean relative eigenvalue error);
    /// None where the unit has no observation of the mode.
    fn residual(&self, _b: usize, _m: usize, _cache: &Self::Cache) -> Option<f64> {
        None
    }
}

/// The terms of the density a coordinate of g enters besides log p(g) ([`Target::global_role`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GlobalRole {
    /// The units' prior log p(x_b | g) only (a population parameter).
    UnitPrior,
    /// The units' likelihood only (a prediction-error scale).
    Likelihood,
    /// Both.
    Both,
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
    /// The mutation of a stage ends when the largest, over all coordinates (g and every
    /// unit), correlation across particles between a coordinate's value after resampling
    /// and its current value has fallen to this level (read, or extrapolated below the
    /// statistic's noise floor, `Decorrelation`).
    pub decorrelation_target: f64,
    pub min_sweeps: usize,
    pub max_sweeps: usize,
    /// The cap of the last stage (β = 1), whose particles are the posterior sample: its
    /// mutation goes on until the same decorrelation rule holds, up to this many sweeps.
    /// Slowly mixing coordinates (an error scale pinned by the units it trades off with, a
    /// funnel) carry the tempering path's imprint into the output when the last stage stops
    /// at `max_sweeps`; the intermediate stages only need to keep the cloud healthy.
    #[serde(default = "default_final_max_sweeps")]
    pub final_max_sweeps: usize,
    /// The decorrelation target of the last stage (β = 1), at most `decorrelation_target`:
    /// a cloud whose slowest coordinate (an error scale's long tail into a funnel) is still
    /// correlated 0.5 with where resampling left it reports that tail as the tempering path
    /// drew it (in the funnel test of `funnel_tests`, the worst quantile of ln ε 0.34 off at
    /// 0.5, 0.075 at 0.1). Below the noise floor of the largest correlation over its
    /// coordinates (`correlation_noise_floor`, about √(2 ln D / N) for D coordinates and N
    /// distinct starts: 0.14 at 400 particles and 60 coordinates) the rule cannot read the
    /// correlations and reaches the target by extrapolating each coordinate's geometric decay
    /// from its last clear reading (`Decorrelation`).
    #[serde(default = "default_final_decorrelation_target")]
    pub final_decorrelation_target: f64,
    /// Centred moves of g per sweep (they need no model evaluation), besides one
    /// componentwise move per coordinate. 8: step 1 of the demo at 4 × 2000 ran the same
    /// sweeps with 8 as with 20 (last stage 17–20 against 18–21), min ESS 7061 against 6934,
    /// R-hat ≤ 1.001, in 35.9 s against 40.9 s; with 4 it was 37.7 s (one run took a stage
    /// more).
    pub global_moves: usize,
    /// Non-centred moves of g per sweep (each costs one model evaluation per unit). 1: on
    /// the demo campaign at 4 × 2000, step 2 (30 units) took 6 sweeps in its last stage
    /// against 7 with 2, 6.2 M model evaluations against 9.3 M, tempering 6.3 s against
    /// 7.8 s, min ESS 5377 against 4984, R-hat ≤ 1.001 and the same log evidence; step 1
    /// 18.2 s against 18.9 s, min ESS 7174 against 6886.
    pub noncentred: usize,
    /// Give up (with an error) after this many tempering stages.
    pub max_stages: usize,
    /// Independent groups of consecutive particles (1 = one population). With G > 1 the
    /// weights are normalised and resampled within each group of N/G particles, so each
    /// group is its own sampler of the same target given its particles' fixed auxiliary
    /// values: the modular ("cut") posterior of a second step, where every group carries one
    /// first-step draw that the second step's data must not reweight (Plummer 2015). The
    /// temperature follows the mean within-group ESS; the log evidence is the log of the
    /// mean over groups of each group's evidence.
    #[serde(default = "one")]
    pub groups: usize,
    /// Give up (with an error) when a run has spent more than this many expensive model
    /// evaluations ([`Target::expensive_evals`]) per particle and unit, checked between
    /// stages. `None`: no limit.
    /// A sampler whose cheap stand-ins fail everywhere (a surrogate refused for every unit)
    /// tempers on the expensive model at every step; a caller that prefers an answer in
    /// bounded time to an exact one at any cost (the diagnosis's refits) sets it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_expensive_evals_per_particle_unit: Option<f64>,
}

fn one() -> usize {
    1
}

fn default_final_decorrelation_target() -> f64 {
    0.1
}

fn default_final_max_sweeps() -> usize {
    100
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
            final_max_sweeps: default_final_max_sweeps(),
            final_decorrelation_target: default_final_decorrelation_target(),
            global_moves: 8,
            noncentred: 1,
            max_stages: 400,
            groups: 1,
            max_expensive_evals_per_particle_unit: None,
        }
    }
}

/// One particle: the global vector, the units, their cached model outputs and log L_b, and
/// fixed auxiliary values that no move changes (shared, as resampling copies them).
#[derive(Clone, Debug)]
pub struct Particle<C> {
    /// The particle's group (0 without groups): resampling copies within a group, so it never
    /// changes; it picks the group's reference q with [`Start::GroupReferences`].
    pub group: usize,
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
    /// With groups: each group's log mean incremental weight (empty without groups).
    #[serde(skip)]
    pub group_log_evidence_increments: Vec<f64>,
    /// Acceptance rates of the unit moves, centred global moves and non-centred moves.
    pub acceptance_unit: f64,
    pub acceptance_global: f64,
    pub acceptance_noncentred: f64,
    /// Acceptance rate of the moves that scale an error scale with its residuals (NaN where
    /// the target has none).
    pub acceptance_rescale: f64,
    /// Mutation sweeps run.
    pub sweeps: usize,
    /// Mean correlation between the coordinates after resampling and after mutation.
    pub decorrelation: f64,
    /// Distinct particles after resampling (before mutation).
    pub unique_after_resampling: usize,
    /// Model evaluations of this stage (all particles).
    pub model_evals: u64,
    /// Proposals rejected by a delayed-acceptance screen, without a model evaluation.
    pub screened_out: u64,
    /// `temper` (a tempering stage) or `correct` (a correction stage at β = 1, [`correct`]).
    pub kind: &'static str,
}

/// The result of one run.
#[derive(Clone, Debug)]
pub struct RunResult<C> {
    pub particles: Vec<Particle<C>>,
    pub log_evidence: f64,
    /// With groups: each group's log evidence (empty without groups).
    pub group_log_evidence: Vec<f64>,
    pub stages: Vec<StageInfo>,
}

/// Errors of the sampler.
#[derive(Debug, thiserror::Error)]
pub enum SmcError {
    #[error("no prior draw has a finite likelihood ({0} particles): the model cannot be evaluated anywhere the prior puts mass")]
    NoFiniteLikelihood(usize),
    #[error("{n} particles cannot form {groups} equal groups")]
    Groups { n: usize, groups: usize },
    #[error("{references} group references for {groups} particle groups")]
    GroupReferences { references: usize, groups: usize },
    #[error("tempering did not reach β = 1 within {stages} stages (β = {beta:.3e})")]
    TooManyStages { stages: usize, beta: f64 },
    #[error("tempering spent {used} expensive model evaluations, over the limit of {max}, by stage {stage} (β = {beta:.3e})")]
    OverBudget {
        used: u64,
        max: u64,
        stage: usize,
        beta: f64,
    },
    /// The tempering has stalled: at [`STALLED_STAGES`] stages in a row even the smallest
    /// step the bisection resolves left the weights degenerate. It would creep on by
    /// Δβ ≈ 1e-12 a stage with one live particle, and never finish.
    #[error(
        "tempering stalled at stage {stage} (β = {beta:.3e}): {stalled} stages in a row, even \
         Δβ = {delta:.1e} left an ESS of {ess:.2} of {n} particles ({infinite} with a log-likelihood \
         ratio of −∞; the finite ones span {spread:.3e}). The start is far narrower than the \
         posterior (a reference of near-zero spread) or the likelihood is degenerate \
         (a noise level near zero)"
    )]
    Stalled {
        stage: usize,
        beta: f64,
        stalled: usize,
        delta: f64,
        ess: f64,
        n: usize,
        infinite: usize,
        spread: f64,
    },
}

/// Stages in a row whose temperature step cannot keep the ESS at its target before
/// [`run_from`] gives up with [`SmcError::Stalled`]. One such stage is normal (e.g. the first,
/// when most prior draws have a zero likelihood: the step kills them and the resampling
/// recovers); three mean the weights stay degenerate however small the step.
pub const STALLED_STAGES: usize = 3;

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

/// Where tempering starts (β = 0).
#[derive(Clone, Debug, Default)]
pub enum Start {
    /// The prior: π_β ∝ p(g) Π_b p(x_b | g) · L^β.
    #[default]
    Prior,
    /// A normalised reference q (see [`super::reference`]): π_β ∝ q^{1−β} · (p L)^β. The log
    /// evidence is still that of p L, because q is normalised.
    Reference(std::sync::Arc<GaussianReference>),
    /// One normalised reference per particle group (`SmcOptions::groups`): group k tempers
    /// from q_k, e.g. a modular posterior's second step, where each group's target depends on
    /// its carried first-step draw and one q for all would fit none. Each group's log evidence
    /// stays that of p L given its draw, because every q_k is normalised.
    GroupReferences(std::sync::Arc<Vec<GaussianReference>>),
}

impl Start {
    /// The reference q of particle group `group` (None: the prior).
    pub fn q(&self, group: usize) -> Option<&GaussianReference> {
        match self {
            Start::Prior => None,
            Start::Reference(q) => Some(q),
            Start::GroupReferences(qs) => Some(&qs[group % qs.len()]),
        }
    }
}

/// The tempered density π_β, split as the moves need it: a global part and one part per unit.
struct Tempered<'a, T: Target> {
    t: &'a T,
    start: &'a Start,
    beta: f64,
}

/// (1 − β) a + β b, exact at the ends (where the other side may be −∞).
fn mix(a: f64, b: f64, beta: f64) -> f64 {
    if beta == 0.0 {
        a
    } else if beta == 1.0 {
        b
    } else {
        (1.0 - beta) * a + beta * b
    }
}

impl<T: Target> Tempered<'_, T> {
    /// The global part for a particle of group `group`.
    fn global(&self, group: usize, g: &[f64]) -> f64 {
        self.global_with_prior(group, g, self.t.log_prior_global(g))
    }
    /// [`Tempered::global`] given log p(g) = `lp`.
    fn global_with_prior(&self, group: usize, g: &[f64], lp: f64) -> f64 {
        match self.start.q(group) {
            None => lp,
            Some(q) => mix(q.global.lpdf(g), lp, self.beta),
        }
    }
    /// The unit's part given its log prior under g and its log-likelihood (particle group
    /// `group`).
    fn unit(&self, group: usize, b: usize, x: &[f64], lp: f64, ll: f64) -> f64 {
        match self.start.q(group) {
            None => {
                lp + if self.beta == 0.0 {
                    0.0
                } else {
                    self.beta * ll
                }
            }
            Some(q) => mix(q.units[b].lpdf(x), lp + ll, self.beta),
        }
    }
    /// `unit(new) − unit(old)` for one unit whose x is unchanged (a centred move of g):
    /// (log prior, log-likelihood) new and old. A reference's q_b(x_b) then cancels, so it is
    /// not evaluated.
    fn unit_change(&self, group: usize, new: (f64, f64), old: (f64, f64)) -> f64 {
        let tempered = |(lp, ll): (f64, f64)| {
            lp + if self.beta == 0.0 {
                0.0
            } else {
                self.beta * ll
            }
        };
        match self.start.q(group) {
            None => tempered(new) - tempered(old),
            Some(_) if self.beta == 0.0 => 0.0,
            Some(_) => self.beta * (new.0 + new.1) - self.beta * (old.0 + old.1),
        }
    }
    /// log (p L / q) of a particle: what the next temperature increment weights by.
    fn log_ratio(&self, p: &Particle<T::Cache>) -> f64 {
        match self.start.q(p.group) {
            None => p.log_lik(),
            Some(q) => {
                let ctx = self.t.ctx(&p.g);
                let mut s = self.t.log_prior_global(&p.g) - q.global.lpdf(&p.g);
                for b in 0..p.x.len() {
                    s += self.t.log_prior_unit(&ctx, b, &p.x[b]) + p.ll[b]
                        - q.units[b].lpdf(&p.x[b]);
                }
                if s.is_nan() {
                    f64::NEG_INFINITY
                } else {
                    s
                }
            }
        }
    }
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

/// Lower Cholesky factor of the covariance of vectors (equal weights). With `groups` > 1 the
/// vectors form that many equal groups of consecutive vectors and the covariance is the
/// pooled within-group one: in a modular posterior each group targets the second step given
/// its own carried first-step draw, so the spread between groups (set by the carried draws,
/// which no move changes) is not a scale any move should take.
fn cloud_cholesky(vs: &[&[f64]], groups: usize) -> Vec<f64> {
    let d = vs[0].len();
    let (mean, _, mut cov) = pooled_covariance(vs, groups);
    for i in 0..d {
        // A collapsed direction (all particles equal) still gets a small step.
        let floor = 1e-12 * (1.0 + mean[i] * mean[i]);
        if cov[i * d + i] < floor {
            cov[i * d + i] = floor;
        }
    }
    cholesky_jittered(&cov, d).0
}

/// The overall mean, the group means ([`group_means`]) and the pooled within-group
/// covariance (divided by the count, row-major) of equal-length vectors.
fn pooled_covariance(vs: &[&[f64]], groups: usize) -> (Vec<f64>, Vec<Vec<f64>>, Vec<f64>) {
    let d = vs[0].len();
    let n = vs.len() as f64;
    let mut mean = vec![0.0; d];
    for v in vs {
        for k in 0..d {
            mean[k] += v[k] / n;
        }
    }
    let centres = group_means(vs, groups, &mean);
    let k_per = vs.len() / centres.len();
    let mut cov = vec![0.0; d * d];
    for (idx, v) in vs.iter().enumerate() {
        let c = &centres[idx / k_per];
        for i in 0..d {
            let a = v[i] - c[i];
            for j in 0..=i {
                cov[i * d + j] += a * (v[j] - c[j]) / n;
            }
        }
    }
    for i in 0..d {
        for j in 0..i {
            cov[j * d + i] = cov[i * d + j];
        }
    }
    (mean, centres, cov)
}

/// The mean of each of `groups` equal groups of consecutive vectors; with one group (or a
/// count that does not divide them) the overall `mean`.
fn group_means(vs: &[&[f64]], groups: usize, mean: &[f64]) -> Vec<Vec<f64>> {
    if groups <= 1 || !vs.len().is_multiple_of(groups) {
        return vec![mean.to_vec()];
    }
    let k = vs.len() / groups;
    vs.chunks(k)
        .map(|c| {
            let mut m = vec![0.0; mean.len()];
            for v in c {
                for (a, b) in m.iter_mut().zip(v.iter()) {
                    *a += b / k as f64;
                }
            }
            m
        })
        .collect()
}

struct Proposals {
    unit: Vec<Vec<f64>>,
    global: Vec<f64>,
    /// The cloud's standard deviation of every global coordinate (componentwise moves).
    global_sd: Vec<f64>,
    /// Per error scale of [`Target::log_error_scales`]: its global coordinate and every
    /// unit's residual line (None: the unit stays put in that scale's moves).
    rescale: Vec<(usize, Vec<Option<ResidualLine>>)>,
}

/// One unit's residual of one error mode, linearised across the particle cloud, for the
/// move that scales the error scale and the residuals together ([`rescale_step`]):
/// r(x) ≈ r0[group] + a·x (the cloud's least-squares line, pooled within groups), and the
/// direction `dir` (a·dir = 1) along which the unit moves to change r: the cloud's
/// regression of x on r, so the unit follows the trade-offs the posterior has between r
/// and its other terms (another mode's residual, the population).
struct ResidualLine {
    a: Vec<f64>,
    dir: Vec<f64>,
    r0: Vec<f64>,
}

impl ResidualLine {
    /// The map x → x + (e^s − 1) r(x) dir, which multiplies r by e^s (exactly for the line,
    /// about for the model), and the log of its Jacobian |1 + (e^s − 1) a·dir| (= s).
    /// The same map with −s undoes it: a bijection, as Metropolis–Hastings needs.
    fn apply(&self, group: usize, x: &[f64], s: f64) -> (Vec<f64>, f64) {
        let r = self.r0[group.min(self.r0.len() - 1)] + dot(&self.a, x);
        let f = s.exp_m1();
        let xn = x
            .iter()
            .zip(&self.dir)
            .map(|(v, d)| v + f * r * d)
            .collect();
        let log_jac = (1.0 + f * dot(&self.a, &self.dir)).abs().ln();
        (xn, log_jac)
    }
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(u, v)| u * v).sum()
}

/// The smallest share of a residual's spread across the cloud that its line must explain
/// for the unit to follow the line (R² of the within-group regression): below it the
/// residual is not near-linear in x over the cloud (or does not vary), and a unit that
/// followed would only spoil the move's acceptance.
const MIN_LINE_R2: f64 = 0.5;

/// The residual line of unit b for error mode m across the particles (see [`ResidualLine`]).
fn residual_line<T: Target>(
    t: &T,
    ps: &[Particle<T::Cache>],
    groups: usize,
    b: usize,
    m: usize,
) -> Option<ResidualLine> {
    let d = t.unit_dim();
    // (x, r) of every particle; a particle without a residual voids the line.
    let xr = ps
        .iter()
        .map(|p| {
            let r = t.residual(b, m, p.cache[b].as_ref()?)?;
            Some(p.x[b].iter().copied().chain([r]).collect::<Vec<f64>>())
        })
        .collect::<Option<Vec<Vec<f64>>>>()?;
    let (_, centres, cov) =
        pooled_covariance(&xr.iter().map(Vec::as_slice).collect::<Vec<_>>(), groups);
    // Blocks of the (d + 1)² covariance: Σ_xx, c = Σ_xr, Var r.
    let e = d + 1;
    let sxx: Vec<f64> = (0..d * d).map(|i| cov[(i / d) * e + i % d]).collect();
    let sxr: Vec<f64> = (0..d).map(|j| cov[j * e + d]).collect();
    let srr = cov[d * e + d];
    let (lf, jitter) = cholesky_jittered(&sxx, d);
    if !jitter.is_finite() {
        return None;
    }
    let a = lower_transpose_solve(&lf, d, &lower_solve(&lf, d, &sxr));
    // The variance the line explains, aᵀ Σ a = aᵀ c.
    let explained = dot(&a, &sxr);
    if !(explained.is_finite() && explained > 0.0 && explained >= MIN_LINE_R2 * srr) {
        return None;
    }
    let dir = sxr.iter().map(|c| c / explained).collect();
    let r0 = centres.iter().map(|c| c[d] - dot(&a, &c[..d])).collect();
    Some(ResidualLine { a, dir, r0 })
}

/// The smallest share of ln ε_m's spread across the cloud that the units' residuals of mode m
/// must pin (R² of ln ε_m on ln of their mean square, within groups) for the rescale move of
/// ε_m to run: the conditional spread of ln ε_m given the units is then at most √(1 − R²) ≈
/// 0.71 of its marginal one, and below that the componentwise move of ε_m (no model
/// evaluation) loses little. In a funnel R² is near 1; where ε_m is set by the spread of many
/// measurements and not by a few units' fits, near 0, and the move's model evaluations (one
/// per unit) would be spent for nothing.
const MIN_FUNNEL_R2: f64 = 0.5;

/// R² across the cloud (pooled within groups) of g[k] = ln ε_m against ln of the mean over
/// units of their squared residual of mode m; 0 where a residual is missing or does not vary.
fn funnel_r2<T: Target>(
    t: &T,
    ps: &[Particle<T::Cache>],
    groups: usize,
    k: usize,
    m: usize,
) -> f64 {
    let rows = ps
        .iter()
        .map(|p| {
            let mut s = 0.0;
            for (b, c) in p.cache.iter().enumerate() {
                let r = t.residual(b, m, c.as_ref()?)?;
                s += r * r;
            }
            let v = (s / t.n_units().max(1) as f64).ln();
            v.is_finite().then_some([p.g[k], v])
        })
        .collect::<Option<Vec<[f64; 2]>>>();
    let Some(rows) = rows else { return 0.0 };
    let (_, _, cov) = pooled_covariance(&rows.iter().map(|r| &r[..]).collect::<Vec<_>>(), groups);
    let r2 = cov[1] * cov[1] / (cov[0] * cov[3]);
    if r2.is_finite() {
        r2
    } else {
        0.0
    }
}

fn proposals<T: Target>(t: &T, ps: &[Particle<T::Cache>], groups: usize) -> Proposals {
    let n_units = t.n_units();
    let rescale = t
        .log_error_scales()
        .into_iter()
        .enumerate()
        .filter(|&(m, k)| funnel_r2(t, ps, groups, k, m) >= MIN_FUNNEL_R2)
        .map(|(m, k)| {
            let lines = (0..n_units)
                .into_par_iter()
                .map(|b| residual_line(t, ps, groups, b, m))
                .collect();
            (k, lines)
        })
        .collect();
    let unit = (0..n_units)
        .map(|b| {
            cloud_cholesky(
                &ps.iter().map(|p| p.x[b].as_slice()).collect::<Vec<_>>(),
                groups,
            )
        })
        .collect();
    let global = cloud_cholesky(
        &ps.iter().map(|p| p.g.as_slice()).collect::<Vec<_>>(),
        groups,
    );
    let ng = ps[0].g.len();
    let global_sd = (0..ng)
        .map(|i| {
            (0..=i)
                .map(|k| global[i * ng + k].powi(2))
                .sum::<f64>()
                .sqrt()
        })
        .collect();
    Proposals {
        unit,
        global,
        global_sd,
        rescale,
    }
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
    acc_comp: f64,
    n_comp: f64,
    acc_rescale: f64,
    n_rescale: f64,
    evals: u64,
    /// Proposals rejected by a delayed-acceptance screen (no model evaluation).
    screened_out: u64,
}

/// log L_b of the screen's stand-in at x, or None where the target has none (the model is
/// cheap there).
fn screen_ll<T: Target>(t: &T, aux: &[f64], ctx: &T::Ctx, b: usize, x: &[f64]) -> Option<f64> {
    t.screen(aux, b, x).map(|c| {
        let l = t.log_lik(ctx, b, x, &c);
        if l.is_nan() {
            f64::NEG_INFINITY
        } else {
            l
        }
    })
}

/// The outcome of one move: accepted (0 or 1), model evaluations made, proposals screened
/// out.
#[derive(Default, Clone, Copy)]
struct MoveOutcome {
    accepted: f64,
    evals: u64,
    screened_out: u64,
}

/// Metropolis step of unit b to `xn` (symmetric proposal). Where the target has a stand-in
/// (its screen) at `xn` or at the current value, a delayed-acceptance step: the stand-in
/// density π̃ is the screen where there is one and the model elsewhere (one fixed function
/// of the state, as the method needs); its ratio r̃ first, then the model at `xn` only if that
/// passed, accepted with probability min(1, r / r̃). Elsewhere plain Metropolis (r̃ = r).
fn unit_move<T: Target>(
    tp: &Tempered<'_, T>,
    p: &mut Particle<T::Cache>,
    ctx: &T::Ctx,
    b: usize,
    xn: Vec<f64>,
    rng: &mut ChaCha8Rng,
) -> MoveOutcome {
    let t = tp.t;
    let u: f64 = rng.random();
    let lp_new = t.log_prior_unit(ctx, b, &xn);
    if !lp_new.is_finite() && matches!(tp.start, Start::Prior) {
        return MoveOutcome::default();
    }
    let lp_old = t.log_prior_unit(ctx, b, &p.x[b]);
    let old = tp.unit(p.group, b, &p.x[b], lp_old, p.ll[b]);
    let (s_new, s_old) = (
        screen_ll(t, &p.aux, ctx, b, &xn),
        screen_ll(t, &p.aux, ctx, b, &p.x[b]),
    );
    let mut out = MoveOutcome::default();
    let mut evaluated = None;
    let mut log_r1 = None;
    if s_new.is_some() || s_old.is_some() {
        let f_new = match s_new {
            Some(l) => l,
            None => {
                let e = eval_unit(t, &p.aux, ctx, b, &xn);
                out.evals += 1;
                let l = e.1;
                evaluated = Some(e);
                l
            }
        };
        let r1 = tp.unit(p.group, b, &xn, lp_new, f_new)
            - tp.unit(p.group, b, &p.x[b], lp_old, s_old.unwrap_or(p.ll[b]));
        if !(f_new > f64::NEG_INFINITY && u.ln() < r1) {
            out.screened_out = u64::from(s_new.is_some());
            return out;
        }
        log_r1 = Some(r1);
    }
    let (c, ll) = match evaluated {
        Some(e) => e,
        None => {
            out.evals += 1;
            eval_unit(t, &p.aux, ctx, b, &xn)
        }
    };
    let log_r = tp.unit(p.group, b, &xn, lp_new, ll) - old;
    // Plain: the one uniform, min(1, r). Delayed: a second uniform, min(1, r / r̃).
    let (u2, log_r2) = match log_r1 {
        None => (u, log_r),
        Some(r1) => (rng.random::<f64>(), log_r - r1),
    };
    if ll > f64::NEG_INFINITY && u2.ln() < log_r2 {
        p.x[b] = xn;
        p.cache[b] = c;
        p.ll[b] = ll;
        out.accepted = 1.0;
    }
    out
}

/// A centred move of g to `gn` with every unit fixed (their cached model outputs reused: no
/// model evaluation): accepted with uniform `u`, updating the particle, its context, its
/// global density term and `lp_units` (each unit's log p(x_b | g), kept by the caller so each
/// move prices the units under the new g only); `role`: the terms a move along one
/// coordinate must re-price ([`Target::global_role`]). Returns whether it was accepted.
#[allow(clippy::too_many_arguments)]
fn centred_g_move<T: Target>(
    tp: &Tempered<'_, T>,
    p: &mut Particle<T::Cache>,
    ctx: &mut T::Ctx,
    lg: &mut f64,
    lp_units: &mut [f64],
    (gn, ctx_new, lp_g): (Vec<f64>, T::Ctx, f64),
    role: GlobalRole,
    u: f64,
) -> bool {
    let t = tp.t;
    if !lp_g.is_finite() {
        return false;
    }
    let lg_new = tp.global_with_prior(p.group, &gn, lp_g);
    let mut log_r = lg_new - *lg;
    let mut ll_new = Vec::with_capacity(t.n_units());
    let mut lp_new = Vec::with_capacity(t.n_units());
    for (b, lp_old) in lp_units.iter().enumerate() {
        let l = match (&p.cache[b], role) {
            (_, GlobalRole::UnitPrior) => p.ll[b],
            (Some(c), _) => t.log_lik(&ctx_new, b, &p.x[b], c),
            (None, _) => f64::NEG_INFINITY,
        };
        let l = if l.is_nan() { f64::NEG_INFINITY } else { l };
        let lp = if role == GlobalRole::Likelihood {
            *lp_old
        } else {
            t.log_prior_unit(&ctx_new, b, &p.x[b])
        };
        log_r += tp.unit_change(p.group, (lp, l), (*lp_old, p.ll[b]));
        ll_new.push(l);
        lp_new.push(lp);
    }
    if log_r.is_finite() && u.ln() < log_r {
        p.g = gn;
        *ctx = ctx_new;
        p.ll = ll_new;
        lp_units.copy_from_slice(&lp_new);
        *lg = lg_new;
        true
    } else {
        false
    }
}

/// A move of g to `gn` (with its context) that takes unit b to `moves[b]` =
/// (x_b', log |∂x_b'/∂x_b|), or leaves it where it is (None: its cached model output is
/// re-priced under gn, no model evaluation). Metropolis–Hastings with the Jacobian: the map
/// must be a bijection that the same move with the opposite step undoes. Where the target
/// has a stand-in (its screen) at a moving unit's new or current value, delayed acceptance
/// (see `unit_move`): the first stage takes the stand-in density π̃ for those units, and the
/// model is evaluated at their new values only if it passes; units without one enter both
/// stages with the model. Returns whether it was accepted.
#[allow(clippy::too_many_arguments, clippy::type_complexity)]
fn joint_move<T: Target>(
    tp: &Tempered<'_, T>,
    p: &mut Particle<T::Cache>,
    ctx: &mut T::Ctx,
    lg: &mut f64,
    (gn, ctx_new): (Vec<f64>, T::Ctx),
    moves: Vec<Option<(Vec<f64>, f64)>>,
    rng: &mut ChaCha8Rng,
    st: &mut SweepStats,
) -> bool {
    let t = tp.t;
    let u: f64 = rng.random();
    let lg_new = tp.global(p.group, &gn);
    let mut log_r = lg_new - *lg;
    let mut log_r1 = log_r;
    // Per unit: (new x or None, model output, log L, its new log prior, its old density,
    // whether a stand-in priced it, log-Jacobian).
    let mut moved: Vec<(Option<Vec<f64>>, Option<T::Cache>, f64, f64, f64, bool, f64)> =
        Vec::with_capacity(moves.len());
    let mut deferred = vec![];
    for (b, mv) in moves.into_iter().enumerate() {
        let lp_old = t.log_prior_unit(ctx, b, &p.x[b]);
        let Some((xn, jac)) = mv else {
            let l = match &p.cache[b] {
                Some(c) => t.log_lik(&ctx_new, b, &p.x[b], c),
                None => f64::NEG_INFINITY,
            };
            let l = if l.is_nan() { f64::NEG_INFINITY } else { l };
            let lp = t.log_prior_unit(&ctx_new, b, &p.x[b]);
            let d = tp.unit_change(p.group, (lp, l), (lp_old, p.ll[b]));
            log_r += d;
            log_r1 += d;
            moved.push((None, None, l, lp, 0.0, false, 0.0));
            continue;
        };
        let lp_new = t.log_prior_unit(&ctx_new, b, &xn);
        let old = tp.unit(p.group, b, &p.x[b], lp_old, p.ll[b]);
        let (s_new, s_old) = (
            screen_ll(t, &p.aux, &ctx_new, b, &xn),
            screen_ll(t, &p.aux, ctx, b, &p.x[b]),
        );
        let (c, l) = if s_new.is_none() {
            st.evals += 1;
            eval_unit(t, &p.aux, &ctx_new, b, &xn)
        } else {
            (None, f64::NEG_INFINITY)
        };
        if s_new.is_some() || s_old.is_some() {
            log_r1 += tp.unit(p.group, b, &xn, lp_new, s_new.unwrap_or(l))
                - tp.unit(p.group, b, &p.x[b], lp_old, s_old.unwrap_or(p.ll[b]))
                + jac;
            deferred.push(b);
        } else {
            let d = tp.unit(p.group, b, &xn, lp_new, l) - old + jac;
            log_r += d;
            log_r1 += d;
        }
        moved.push((Some(xn), c, l, lp_new, old, s_new.is_some(), jac));
    }
    let mut u = u;
    if !deferred.is_empty() {
        if !(log_r1.is_finite() && u.ln() < log_r1) {
            st.screened_out += 1;
            return false;
        }
        for &b in &deferred {
            let m = &mut moved[b];
            let xn = m.0.as_ref().expect("a deferred unit moves");
            if m.5 {
                let (c, l) = eval_unit(t, &p.aux, &ctx_new, b, xn);
                st.evals += 1;
                m.1 = c;
                m.2 = l;
            }
            log_r += tp.unit(p.group, b, xn, m.3, m.2) - m.4 + m.6;
        }
        log_r -= log_r1;
        u = rng.random();
    }
    if !(log_r.is_finite() && u.ln() < log_r) {
        return false;
    }
    p.g = gn;
    *ctx = ctx_new;
    *lg = lg_new;
    for (b, (xn, c, l, ..)) in moved.into_iter().enumerate() {
        if let Some(xn) = xn {
            p.x[b] = xn;
            p.cache[b] = c;
        }
        p.ll[b] = l;
    }
    true
}

/// A move of one error scale ln ε_m by `step` = s that takes every unit with a residual
/// line for the mode along it, multiplying its (linearised) residual by e^s: the
/// standardised residuals r/ε stay about where they were, so the move crosses the funnel
/// between an error scale and the units that pin it in one step (a data-space analogue of
/// the non-centred parametrisation). Each moved unit costs one model evaluation.
#[allow(clippy::too_many_arguments)]
fn rescale_step<T: Target>(
    tp: &Tempered<'_, T>,
    p: &mut Particle<T::Cache>,
    ctx: &mut T::Ctx,
    lg: &mut f64,
    (k, lines): (usize, &[Option<ResidualLine>]),
    step: f64,
    rng: &mut ChaCha8Rng,
    st: &mut SweepStats,
) -> bool {
    let t = tp.t;
    let mut gn = p.g.clone();
    gn[k] += step;
    if !t.log_prior_global(&gn).is_finite() {
        return false;
    }
    let ctx_new = t.ctx(&gn);
    let moves = lines
        .iter()
        .enumerate()
        .map(|(b, line)| line.as_ref().map(|l| l.apply(p.group, &p.x[b], step)))
        .collect();
    joint_move(tp, p, ctx, lg, (gn, ctx_new), moves, rng, st)
}

/// One Metropolis-within-Gibbs sweep of one particle at β.
fn sweep<T: Target>(
    tp: &Tempered<'_, T>,
    p: &mut Particle<T::Cache>,
    prop: &Proposals,
    sc: &Scales,
    opts: &SmcOptions,
    rng: &mut ChaCha8Rng,
) -> SweepStats {
    let t = tp.t;
    let mut st = SweepStats::default();
    let d = t.unit_dim();
    let ng = t.n_global();
    let mut ctx = t.ctx(&p.g);
    // Unit moves, g fixed.
    for b in 0..t.n_units() {
        let eps = normal_vec(rng, d);
        let step = lower_mul(&prop.unit[b], d, &eps);
        let xn: Vec<f64> = p.x[b]
            .iter()
            .zip(&step)
            .map(|(a, s)| a + sc.unit * s)
            .collect();
        st.n_unit += 1.0;
        let m = unit_move(tp, p, &ctx, b, xn, rng);
        st.acc_unit += m.accepted;
        st.evals += m.evals;
        st.screened_out += m.screened_out;
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
        st.n_unit_z += 1.0;
        let m = unit_move(tp, p, &ctx, b, xn, rng);
        st.acc_unit_z += m.accepted;
        st.evals += m.evals;
        st.screened_out += m.screened_out;
    }
    // Centred moves of g: no model evaluation.
    let mut lg = tp.global(p.group, &p.g);
    let mut lp_units: Vec<f64> = (0..t.n_units())
        .map(|b| t.log_prior_unit(&ctx, b, &p.x[b]))
        .collect();
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
        let (ctx_new, lp_g) = t.ctx_with_prior(&gn);
        if centred_g_move(
            tp,
            p,
            &mut ctx,
            &mut lg,
            &mut lp_units,
            (gn, ctx_new, lp_g),
            GlobalRole::Both,
            u,
        ) {
            st.acc_global += 1.0;
        }
    }
    // Componentwise centred moves of g, one coordinate at a time (no model evaluation):
    // a joint random walk in g is throttled by its worst-scaled coordinate, and the error
    // scales of rarely informative modes have skewed, heavy-tailed posteriors that it
    // barely moves.
    for k in 0..ng {
        let e: f64 = StandardNormal.sample(rng);
        let mut gn = p.g.clone();
        gn[k] += sc.comp * prop.global_sd[k] * e;
        let u: f64 = rng.random();
        st.n_comp += 1.0;
        let role = t.global_role(k);
        let (ctx_new, lp_g) = t.ctx_after(&ctx, &gn, k);
        let moved = (gn, ctx_new, lp_g);
        if centred_g_move(tp, p, &mut ctx, &mut lg, &mut lp_units, moved, role, u) {
            st.acc_comp += 1.0;
        }
    }
    // Moves of one error scale with the residuals it governs (see `rescale_step`): an
    // error scale that the units can pin (a mode they fit nearly exactly, its ε near zero,
    // the units in a narrow band of width ∝ ε) is a funnel that the moves above cross only
    // by many small steps.
    for (k, lines) in &prop.rescale {
        let e: f64 = StandardNormal.sample(rng);
        let step = sc.rescale * prop.global_sd[*k] * e;
        st.n_rescale += 1.0;
        if rescale_step(tp, p, &mut ctx, &mut lg, (*k, lines), step, rng, &mut st) {
            st.acc_rescale += 1.0;
        }
    }
    // Non-centred moves of g: units follow through their standardised values. In (g, z)
    // coordinates the density gains the Jacobian |∂x/∂z| = det(diag σ L), and
    // log p(x | g) + log |∂x/∂z| = log N(z; 0, I) is unchanged when z is, so a unit's
    // log-Jacobian is log p(x_b | g) − log p(x_b' | g').
    for _ in 0..if t.n_units() > 0 { opts.noncentred } else { 0 } {
        let eps = normal_vec(rng, ng);
        let step = lower_mul(&prop.global, ng, &eps);
        let gn: Vec<f64> = p.g.iter().zip(&step).map(|(a, s)| a + sc.nc * s).collect();
        st.n_nc += 1.0;
        if !t.log_prior_global(&gn).is_finite() {
            continue;
        }
        let ctx_new = t.ctx(&gn);
        let moves = (0..t.n_units())
            .map(|b| {
                let z = t.to_standard(&ctx, b, &p.x[b]);
                let xn = t.from_standard(&ctx_new, b, &z);
                let jac = t.log_prior_unit(&ctx, b, &p.x[b]) - t.log_prior_unit(&ctx_new, b, &xn);
                Some((xn, jac))
            })
            .collect();
        if joint_move(tp, p, &mut ctx, &mut lg, (gn, ctx_new), moves, rng, &mut st) {
            st.acc_nc += 1.0;
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

/// Per coordinate, the correlation across particles between `start` and the particles'
/// current values (None for a coordinate constant in either). With `groups` > 1 the
/// correlation is the pooled within-group one: resampling copies particles inside their
/// group, and what the moves must forget is where in its group a particle was put; the
/// differences between groups come from their carried draws, which stay (measured across
/// groups, the rule could never be met and every stage would run `max_sweeps`).
fn correlations<C: Sync + Send>(
    start: &[Vec<f64>],
    ps: &[Particle<C>],
    groups: usize,
) -> Vec<Option<f64>> {
    let now: Vec<Vec<f64>> = ps.iter().map(flat).collect();
    let n = start.len();
    let dim = start[0].len();
    let groups = if groups > 1 && n.is_multiple_of(groups) {
        groups
    } else {
        1
    };
    let k_per = n / groups;
    (0..dim)
        .map(|k| {
            let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
            for g in 0..groups {
                let (a_g, b_g) = (
                    &start[g * k_per..(g + 1) * k_per],
                    &now[g * k_per..(g + 1) * k_per],
                );
                let (ma, mb) = (
                    a_g.iter().map(|v| v[k]).sum::<f64>() / k_per as f64,
                    b_g.iter().map(|v| v[k]).sum::<f64>() / k_per as f64,
                );
                for (a, b) in a_g.iter().zip(b_g) {
                    let (da, db) = (a[k] - ma, b[k] - mb);
                    sab += da * db;
                    saa += da * da;
                    sbb += db * db;
                }
            }
            (saa > 0.0 && sbb > 0.0).then(|| sab / (saa * sbb).sqrt())
        })
        .collect()
}

/// The stopping rule of a stage's mutation. The largest, not the mean, over coordinates: a
/// few slowly mixing coordinates (heavy-tailed error scales, say) would hide in a mean over
/// dozens of well-mixed ones. A correlation can be read only down to the noise floor of the
/// largest of D sample correlations (`correlation_noise_floor`); a target below it is
/// reached by extrapolation: each coordinate's correlation, last read where it stood clearly
/// above that floor (at twice it), is taken to decay geometrically over the sweeps
/// (ρ_t = ρ^t, the autocorrelation of a chain with one slow direction), and the stage runs
/// until every coordinate's extrapolated correlation is at the target.
pub(crate) struct Decorrelation {
    target: f64,
    floor: f64,
    /// Per coordinate, the sweeps its last clear reading says it needs.
    need: Vec<usize>,
    /// The largest correlation of the last sweep.
    pub(crate) max: f64,
}

impl Decorrelation {
    pub(crate) fn new(target: f64, dim: usize, n_eff: f64) -> Decorrelation {
        Decorrelation {
            target,
            floor: correlation_noise_floor(dim, n_eff),
            need: vec![0; dim],
            max: 1.0,
        }
    }
    /// Reads the correlations after `sweeps` sweeps; true when the stage may stop.
    pub(crate) fn update(&mut self, sweeps: usize, rho: &[Option<f64>]) -> bool {
        self.max = rho
            .iter()
            .flatten()
            .copied()
            .fold(f64::NEG_INFINITY, f64::max);
        if !self.max.is_finite() {
            self.max = 0.0;
        }
        for (need, r) in self.need.iter_mut().zip(rho) {
            if let Some(r) = *r {
                if r > 2.0 * self.floor && r < 1.0 && self.target > 0.0 {
                    let t = sweeps as f64 * self.target.ln() / r.ln();
                    *need = t.ceil().min(1e6) as usize;
                }
            }
        }
        self.max <= self.target.max(self.floor)
            && sweeps >= self.need.iter().copied().max().unwrap_or(0)
    }
}

/// The level the largest of `dim` sample correlations between independent clouds of
/// `n_eff` distinct points stays near even when every coordinate has forgotten its start:
/// each is about N(0, 1/n_eff), and the largest of `dim` such is about √(2 ln dim / n_eff)
/// (the Gumbel location of a Gaussian maximum). A decorrelation target below it cannot be
/// told from noise: the mutation would run to its cap whatever the chain's mixing (at 400
/// particles and 60 coordinates it is 0.14, more with duplicated starts).
fn correlation_noise_floor(dim: usize, n_eff: f64) -> f64 {
    (2.0 * (dim.max(2) as f64).ln() / n_eff.max(1.0)).sqrt()
}

/// Mean over groups of the within-group ESS fraction of log weights.
fn group_ess_fraction(lw: &[f64], groups: usize) -> f64 {
    let k = lw.len() / groups;
    (0..groups)
        .map(|g| ess(&lw[g * k..(g + 1) * k]) / k as f64)
        .sum::<f64>()
        / groups as f64
}

/// Bisection for the next temperature increment: the largest Δ ≤ 1 − β whose incremental
/// weights keep the (mean within-group) ESS ≥ target · N. When not even the smallest step it
/// resolves (1e-12 (1 − β)) keeps the target, that smallest step is returned, flagged `true`
/// (stalled).
fn next_increment(ll: &[f64], beta: f64, target: f64, groups: usize) -> (f64, bool) {
    let frac_at = |delta: f64| -> f64 {
        let lw: Vec<f64> = ll.iter().map(|l| delta * l).collect();
        group_ess_fraction(&lw, groups)
    };
    let max = 1.0 - beta;
    if frac_at(max) >= target {
        return (max, false);
    }
    let (mut lo, mut hi) = (0.0, max);
    for _ in 0..100 {
        let mid = 0.5 * (lo + hi);
        if frac_at(mid) >= target {
            lo = mid;
        } else {
            hi = mid;
        }
        if hi - lo <= 1e-12 * max.max(1e-300) {
            break;
        }
    }
    if lo > 0.0 {
        (lo, false)
    } else {
        (1e-12 * max, true)
    }
}

/// Run one tempered SMC from the prior; `observe` sees every stage as it ends.
pub fn run<T: Target>(
    t: &T,
    opts: &SmcOptions,
    seed: u64,
    run_index: usize,
    observe: &(dyn Fn(&StageInfo) + Sync),
) -> Result<RunResult<T::Cache>, SmcError> {
    run_with(t, opts, seed, run_index, &Start::Prior, &[], observe)
}

/// [`run`] where particle i carries `aux[i % aux.len()]` (with groups: group g carries
/// `aux[g % aux.len()]`) (fixed values the model reads and
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
    run_with(t, opts, seed, run_index, &Start::Prior, aux, observe)
}

/// One run from `start` (the prior or a reference q), with auxiliary values as in
/// [`run_with_aux`].
pub fn run_with<T: Target>(
    t: &T,
    opts: &SmcOptions,
    seed: u64,
    run_index: usize,
    start: &Start,
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
            let group = if opts.groups > 1 {
                i / (n / opts.groups).max(1)
            } else {
                0
            };
            let (g, x) = match start.q(group) {
                None => t.sample_prior(&mut rng),
                Some(q) => q.sample(&mut rng),
            };
            let ctx = t.ctx(&g);
            let aux = if aux.is_empty() {
                empty.clone()
            } else if opts.groups > 1 {
                // One auxiliary value per group.
                aux[group % aux.len()].clone()
            } else {
                aux[i % aux.len()].clone()
            };
            let (cache, ll): (Vec<_>, Vec<_>) = x
                .iter()
                .enumerate()
                .map(|(b, xb)| eval_unit(t, &aux, &ctx, b, xb))
                .unzip();
            Particle {
                group,
                aux,
                g,
                x,
                cache,
                ll,
            }
        })
        .collect();
    run_from(t, opts, seed, run_index, start, particles, 0.0, observe)
}

/// Per-run adaptive state carried from stage to stage.
struct Scales {
    unit: f64,
    unit_z: f64,
    global: f64,
    nc: f64,
    comp: f64,
    rescale: f64,
}

impl Scales {
    fn new<T: Target>(t: &T) -> Scales {
        let d = t.unit_dim().max(1) as f64;
        let g = (t.n_global().max(1) as f64).sqrt();
        Scales {
            unit: 2.38 / d.sqrt(),
            unit_z: 2.38 / d.sqrt(),
            global: 2.38 / g,
            nc: 2.38 / g,
            comp: 2.4,
            rescale: 2.4,
        }
    }
}

/// Weight by `lw`, resample, mutate at `beta`: one stage. `mutate_if_unique_below`: the
/// mutation is skipped when at least this fraction of the particles stayed distinct through
/// resampling (1.0 or more: always mutate).
#[allow(clippy::too_many_arguments)]
fn stage_step<T: Target>(
    tp: &Tempered<'_, T>,
    opts: &SmcOptions,
    seed: u64,
    run_index: usize,
    stage: usize,
    particles: &mut Vec<Particle<T::Cache>>,
    lw: &[f64],
    scales: &mut Scales,
    mutate_if_unique_below: f64,
) -> StageInfo {
    let t = tp.t;
    let n = particles.len();
    let r = run_index as u64;
    let groups = opts.groups.max(1);
    let k = n / groups;
    // Per group: log mean weight (the group's evidence increment), then resampling inside
    // the group.
    let group_inc: Vec<f64> = (0..groups)
        .map(|g| log_mean_exp(&lw[g * k..(g + 1) * k]))
        .collect();
    let inc = log_mean_exp(lw);
    let ess_inc = group_ess_fraction(lw, groups) * n as f64;
    let mut idx = Vec::with_capacity(n);
    for g in 0..groups {
        let w = super::stats::normalize(&lw[g * k..(g + 1) * k]);
        let u: f64 = rng_for(&[seed, r, stage as u64, u64::MAX - 1, g as u64]).random();
        idx.extend(
            resample::systematic(&w, k, u)
                .into_iter()
                .map(|i| g * k + i),
        );
    }
    let unique = {
        let mut v = idx.clone();
        v.dedup();
        v.len()
    };
    // Effective number of distinct starting points, N² / Σ c_i² over the copy counts c_i
    // (systematic resampling returns each parent's copies next to each other).
    let copies_eff = {
        let mut sq = 0.0;
        let mut run = 0usize;
        for (j, &i) in idx.iter().enumerate() {
            run += 1;
            if j + 1 == idx.len() || idx[j + 1] != i {
                sq += (run * run) as f64;
                run = 0;
            }
        }
        (n * n) as f64 / sq
    };
    *particles = idx.iter().map(|&i| particles[i].clone()).collect();
    let mut rho = 0.0;
    let (mut acc_u, mut acc_g, mut acc_n, mut acc_r) = (0.0, 0.0, 0.0, 0.0);
    let mut sweeps = 0;
    let mut evals = 0u64;
    let mut screened_out = 0u64;
    if (unique as f64) < mutate_if_unique_below * n as f64 {
        let prop = proposals(t, particles, groups);
        let start: Vec<Vec<f64>> = particles.iter().map(flat).collect();
        rho = 1.0;
        let (cap, target) = if tp.beta >= 1.0 {
            (
                opts.final_max_sweeps.max(opts.max_sweeps),
                opts.final_decorrelation_target
                    .min(opts.decorrelation_target),
            )
        } else {
            (opts.max_sweeps, opts.decorrelation_target)
        };
        let mut rule = Decorrelation::new(target, start[0].len(), copies_eff);
        while sweeps < cap {
            let stats: Vec<SweepStats> = particles
                .par_iter_mut()
                .enumerate()
                .map(|(i, p)| {
                    let mut rng = rng_for(&[seed, r, stage as u64, sweeps as u64, i as u64]);
                    sweep(tp, p, &prop, scales, opts, &mut rng)
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
                tot.acc_comp += s.acc_comp;
                tot.n_comp += s.n_comp;
                tot.acc_rescale += s.acc_rescale;
                tot.n_rescale += s.n_rescale;
                tot.evals += s.evals;
                tot.screened_out += s.screened_out;
            }
            evals += tot.evals;
            screened_out += tot.screened_out;
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
            // One-dimensional moves (a coordinate of g; an error scale with its residuals):
            // the optimal acceptance is 0.44 (Gelman et al.).
            let adapt_1d = |s: &mut f64, a: f64| {
                if a.is_finite() {
                    *s = (*s * (a - 0.44).exp()).clamp(1e-3, 20.0);
                }
            };
            adapt_1d(&mut scales.comp, rate(tot.acc_comp, tot.n_comp));
            let ar = rate(tot.acc_rescale, tot.n_rescale);
            acc_r += ar;
            adapt_1d(&mut scales.rescale, ar);
            let stop = rule.update(sweeps, &correlations(&start, particles, groups));
            rho = rule.max;
            if sweeps >= opts.min_sweeps && stop {
                break;
            }
        }
    }
    let k = (sweeps as f64).max(1.0);
    StageInfo {
        run: run_index,
        stage,
        beta: tp.beta,
        ess: ess_inc,
        log_evidence_increment: inc,
        group_log_evidence_increments: if groups > 1 { group_inc } else { vec![] },
        acceptance_unit: if sweeps > 0 { acc_u / k } else { f64::NAN },
        acceptance_global: if sweeps > 0 { acc_g / k } else { f64::NAN },
        acceptance_noncentred: if sweeps > 0 { acc_n / k } else { f64::NAN },
        acceptance_rescale: if sweeps > 0 { acc_r / k } else { f64::NAN },
        sweeps,
        decorrelation: rho,
        unique_after_resampling: unique,
        model_evals: evals,
        screened_out,
        kind: "temper",
    }
}

/// Continue tempering from `particles` (equally weighted, distributed as π_β at `beta0`,
/// with π_β as `start` defines it).
#[allow(clippy::too_many_arguments)]
pub fn run_from<T: Target>(
    t: &T,
    opts: &SmcOptions,
    seed: u64,
    run_index: usize,
    start: &Start,
    mut particles: Vec<Particle<T::Cache>>,
    beta0: f64,
    observe: &(dyn Fn(&StageInfo) + Sync),
) -> Result<RunResult<T::Cache>, SmcError> {
    let n = particles.len();
    if particles.iter().all(|p| p.log_lik() == f64::NEG_INFINITY) {
        return Err(SmcError::NoFiniteLikelihood(n));
    }
    let groups = opts.groups.max(1);
    if n % groups != 0 {
        return Err(SmcError::Groups { n, groups });
    }
    if let Start::GroupReferences(qs) = start {
        if qs.len() != groups {
            return Err(SmcError::GroupReferences {
                references: qs.len(),
                groups,
            });
        }
    }
    let mut beta = beta0;
    let mut log_z = 0.0;
    let mut group_log_z = vec![0.0; groups];
    let mut stages = Vec::new();
    let mut scales = Scales::new(t);
    let mut stage = 0usize;
    let mut stalled = 0usize;
    let expensive_at_start = t.expensive_evals();
    while beta < 1.0 {
        stage += 1;
        if stage > opts.max_stages {
            return Err(SmcError::TooManyStages {
                stages: opts.max_stages,
                beta,
            });
        }
        if let Some(per) = opts.max_expensive_evals_per_particle_unit {
            let max = (per * (n * t.n_units()) as f64) as u64;
            let used = t.expensive_evals() - expensive_at_start;
            if used > max {
                return Err(SmcError::OverBudget {
                    used,
                    max,
                    stage: stage - 1,
                    beta,
                });
            }
        }
        let ratio: Vec<f64> = {
            let tp = Tempered { t, start, beta };
            particles.par_iter().map(|p| tp.log_ratio(p)).collect()
        };
        let (delta, stall) = next_increment(&ratio, beta, opts.target_ess, groups);
        let lw: Vec<f64> = ratio.iter().map(|l| delta * l).collect();
        stalled = if stall { stalled + 1 } else { 0 };
        if stalled >= STALLED_STAGES {
            let finite = ratio.iter().copied().filter(|l| l.is_finite());
            let (lo, hi) = finite.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), l| {
                (a.min(l), b.max(l))
            });
            return Err(SmcError::Stalled {
                stage,
                beta,
                stalled,
                delta,
                ess: group_ess_fraction(&lw, groups) * n as f64,
                n,
                infinite: ratio.iter().filter(|l| !l.is_finite()).count(),
                spread: (hi - lo).max(0.0),
            });
        }
        beta = if 1.0 - (beta + delta) < 1e-12 {
            1.0
        } else {
            beta + delta
        };
        let tp = Tempered { t, start, beta };
        let info = stage_step(
            &tp,
            opts,
            seed,
            run_index,
            stage,
            &mut particles,
            &lw,
            &mut scales,
            f64::INFINITY,
        );
        if groups > 1 {
            for (z, i) in group_log_z
                .iter_mut()
                .zip(&info.group_log_evidence_increments)
            {
                *z += i;
            }
            log_z = log_mean_exp(&group_log_z);
        } else {
            log_z += info.log_evidence_increment;
        }
        observe(&info);
        stages.push(info);
    }
    Ok(RunResult {
        group_log_evidence: if groups > 1 { group_log_z } else { vec![] },
        particles,
        log_evidence: log_z,
        stages,
    })
}

/// A correction stage at β = 1: weight the particles of `res` by `lw` (e.g. log L_new −
/// log L_old when the particles' model outputs were replaced by a more exact model's),
/// resample (within groups), and mutate under `t` only when fewer than
/// `mutate_if_unique_below` · N particles stayed distinct. The particles' caches and
/// log-likelihoods must already be `t`'s. The run's log evidence is corrected and the stage
/// appended to its stages; the stage is returned too.
pub fn correct<T: Target>(
    t: &T,
    opts: &SmcOptions,
    seed: u64,
    run_index: usize,
    res: &mut RunResult<T::Cache>,
    lw: &[f64],
    mutate_if_unique_below: f64,
) -> StageInfo {
    let tp = Tempered {
        t,
        start: &Start::Prior,
        beta: 1.0,
    };
    let mut scales = Scales::new(t);
    let stage = res.stages.len() + 1;
    // The mutation here only diversifies the copies the reweighting made (the tempering's
    // last stage has mixed already, under the stricter rule): the intermediate stages' rule.
    let opts = &SmcOptions {
        final_decorrelation_target: opts.decorrelation_target,
        ..opts.clone()
    };
    let mut info = stage_step(
        &tp,
        opts,
        seed,
        run_index,
        stage,
        &mut res.particles,
        lw,
        &mut scales,
        mutate_if_unique_below,
    );
    info.kind = "correct";
    if res.group_log_evidence.is_empty() {
        res.log_evidence += info.log_evidence_increment;
    } else {
        for (z, i) in res
            .group_log_evidence
            .iter_mut()
            .zip(&info.group_log_evidence_increments)
        {
            *z += i;
        }
        res.log_evidence = log_mean_exp(&res.group_log_evidence);
    }
    res.stages.push(info.clone());
    info
}

//! The SMC pipeline of a step: the Laplace-type reference, the pilot groups and pilot run,
//! the per-unit surrogates and subspaces, the tempering and the correction to the ROM.

use crate::bayes::smc::{self, Particle, SmcOptions, StageInfo};
use crate::bayes::target::ModalTarget;
use crate::findings::{Finding, Findings, Severity};
use anyhow::anyhow;
use std::sync::Arc;

/// How a step's posterior is sampled: nothing here changes the model or the data, only the
/// draws (and the seed they come from).
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct SamplerParams {
    pub seed: u64,
    pub runs: usize,
    pub smc: SmcOptions,
    /// Draws used for the posterior-predictive residuals, in all (spread evenly over the
    /// runs).
    pub residual_draws: usize,
    /// Start tempering from the prior (else from the Laplace-type reference).
    pub from_prior: bool,
    /// Local surrogates of the units' modal terms, corrected to the ROM at the end.
    pub surrogate: bool,
    /// The correction solves each unit's modes in a verified subspace of the ROM inside the
    /// unit's surrogate box (else in the whole ROM).
    pub subspace: bool,
}

/// What the acceleration did (reference, surrogates, correction), for the report.
#[derive(Debug, Default, serde::Serialize)]
pub struct Acceleration {
    pub start: &'static str,
    pub reference_model_evals: u64,
    pub reference_g_acceptance: f64,
    pub reference_units_converged: Vec<bool>,
    /// Rounds the reference's construction ran (units, then g) before g's mode settled.
    pub reference_rounds: usize,
    /// Why the reference was searched again from the scatter of the units' repeated
    /// measurements (`bayes::reference::laplace_reference`); None where it was not.
    pub reference_restarted: Option<String>,
    /// Why the reference is that of the construction's first rounds (a unit's spread or an
    /// error scale collapsed later: `ReferenceOptions::fallback_rounds`), and after how many
    /// rounds; None where it is the last round's.
    pub reference_fell_back: Option<String>,
    pub surrogate_units: usize,
    pub surrogate_refused: Vec<String>,
    pub surrogate_degree: Vec<Option<usize>>,
    /// Per unit: the surrogate box's half-width in reference sd (10, halved where the ROM or
    /// the polynomial does not hold that far).
    pub surrogate_half_width_sd: Vec<Option<f64>>,
    pub surrogate_max_abs_dlog_lik: Vec<Option<f64>>,
    pub surrogate_rom_evals: u64,
    /// Proposals outside a surrogate's box (`surrogate_half_width_sd`), evaluated by the ROM.
    pub surrogate_proposals_outside_box: u64,
    /// Fraction of the final particles' units beyond their surrogate's box (ROM-evaluated).
    pub surrogate_edge_fraction: f64,
    /// Per run: ESS of the correction weights L_ROM / L_surrogate, in particles.
    pub correction_ess: Vec<f64>,
    /// Per run: largest |log L_ROM − log L_surrogate| over the particles.
    pub correction_max_abs_dlog_lik: Vec<f64>,
    /// Per run: mutation sweeps of the correction stage (0 when resampling kept ≥ 98 %).
    pub correction_sweeps: Vec<usize>,
    /// Per unit: the dimensions, summed over its updated modes, of the verified per-mode
    /// subspaces of the ROM the correction solves in inside the unit's surrogate box
    /// (`bayes::surrogate::fit_subspace`; None: the ROM).
    pub subspace_dim: Vec<Option<usize>>,
    /// Per unit: its largest |log L_subspace − log L_ROM| on the verification points.
    pub subspace_max_abs_dlog_lik: Vec<Option<f64>>,
    pub subspace_refused: Vec<String>,
    pub subspace_rom_evals: u64,
    /// Wall seconds stay out of the file (the same inputs and seed give the same bytes);
    /// `-v` prints them.
    #[serde(skip)]
    pub subspace_seconds: f64,
    /// Posterior sd / reference sd per global coordinate (first run): how well the
    /// reference fitted (1 = exactly; the reference is inflated, so ~0.8 is expected).
    pub reference_sd_ratio_global: Vec<f64>,
    /// The same per unit coordinate, unit by unit.
    pub reference_sd_ratio_units: Vec<Vec<f64>>,
    /// Run 1: (posterior mean − reference mean) / reference sd of every global coordinate
    /// (same order as `reference_sd_ratio_global`).
    pub reference_offset_global: Vec<f64>,
    /// Particles of the pilot run whose posterior moments replaced the Laplace reference
    /// (0: no pilot), its tempering stages, and its wall seconds (printed with `-v`, kept out
    /// of the file: a pilot made update_report.json differ between two runs).
    pub pilot_particles: usize,
    pub pilot_stages: usize,
    #[serde(skip)]
    pub pilot_seconds: f64,
    /// Step 2: pilot groups left out of the surrogates' spread, and groups (over all runs)
    /// that tempered from the base reference, because their moved reference was degenerate.
    pub degenerate_pilot_groups: usize,
    pub degenerate_group_references: usize,
}

/// Particles of the pilot run whose posterior moments replace the Laplace reference of a run
/// without groups (`bayes::reference::pilot_reference`, inflated by `PILOT_INFLATION`); a
/// pilot runs only when the main runs have at least `PILOT_MIN_RATIO` times as many particles,
/// so it costs a few per cent and saves tempering stages.
pub const PILOT_PARTICLES: usize = 400;

pub const PILOT_MIN_RATIO: usize = 4;

pub const PILOT_INFLATION: f64 = 1.1;

pub type Results = Vec<smc::RunResult<crate::bayes::modal::Terms>>;

/// A check of a step's reference before sampling ([`run_smc`]), given the inflation of its
/// sds over the Laplace ones (`ReferenceOptions::inflation`).
pub type ReferenceCheck<'a> =
    dyn Fn(&crate::bayes::reference::GaussianReference, f64) -> anyhow::Result<()> + 'a;

/// `aux`: per run, the auxiliary values its particles carry (step 2: step-1 draws; with
/// `opts.smc.groups` > 1 group g carries aux[g]); empty for step 1.
///
/// `start`: a unit point known to fit the data (step 2: the joint centre fitted to the mean
/// bolted modes), where the reference's search begins; None = the prior's centre.
///
/// `check_reference`: run on the reference before any sampling (step 1: the ROM-box rule
/// on the reference's draws); its error stops the run.
#[allow(clippy::too_many_arguments)]
pub fn run_smc(
    target: &ModalTarget,
    opts: &SamplerParams,
    what: &str,
    aux: &[Vec<Arc<Vec<f64>>>],
    start: Option<&[f64]>,
    check_reference: &ReferenceCheck<'_>,
    progress: &(dyn Fn(u64, String) + Sync),
    verbose: bool,
) -> anyhow::Result<(Results, Acceleration)> {
    use crate::bayes::surrogate::SurrogateTarget;
    let mut acc = Acceleration {
        start: if opts.from_prior {
            "prior"
        } else {
            "reference"
        },
        ..Default::default()
    };
    let t_start = std::time::Instant::now();
    let all_aux: Vec<&Arc<Vec<f64>>> = aux.iter().flatten().collect();
    // A modular step: groups carrying their own auxiliary values (step-1 draws).
    let modular = opts.smc.groups > 1 && !aux.is_empty();
    let base_ref = base_reference(
        target, opts, what, &all_aux, start, modular, verbose, &mut acc,
    )?;
    if let Some((q, ropts)) = &base_ref {
        check_reference(q, ropts.inflation)?;
    }
    let t_base = t_start.elapsed().as_secs_f64();
    let grouped = base_ref.is_some() && modular;
    let _nu = smc::Target::n_units(target);
    // Where the units go across the groups' draws: with groups, each group's units sit
    // elsewhere (its draw moves them), so a few pilot groups, spread over the draws, are
    // moved to their own draws with the ROM; the surrogates' samples then cover the base
    // reference widened by twice the pilots' spread of the units, and the groups' own
    // references are found on the surrogates (their boxes cover where they go).
    let unit_spread = pilot_unit_spread(target, &base_ref, grouped, &all_aux, what, &mut acc)?;
    let surrogates = fit_surrogates(target, opts, &base_ref, &unit_spread, &all_aux, &mut acc);
    let t_surrogates = t_start.elapsed().as_secs_f64() - t_base;
    // The correction's model: per unit with a surrogate, a verified subspace of the ROM over
    // the surrogate's box (the ROM beyond it).
    let t_sub = std::time::Instant::now();
    let exact_target = fit_subspaces(target, opts, &base_ref, &surrogates, &mut acc);
    acc.subspace_seconds = t_sub.elapsed().as_secs_f64();
    let exact: &ModalTarget = exact_target.as_ref().unwrap_or(target);
    let sur = SurrogateTarget::new(target, surrogates, &all_aux);
    let starts = run_starts(&sur, opts, &base_ref, grouped, aux, what, &mut acc)?;
    let t_groups = t_start.elapsed().as_secs_f64() - t_base - t_surrogates;
    if verbose {
        eprintln!(
            "{what}: reference {t_base:.1} s (pilots and) surrogates {t_surrogates:.1} s, subspaces {:.1} s, pilot run ({:.1} s) or group references {:.1} s",
            acc.subspace_seconds,
            acc.pilot_seconds,
            t_groups - acc.subspace_seconds
        );
        if !acc.surrogate_refused.is_empty() {
            eprintln!(
                "{what}: {} of {} units without a surrogate (the ROM evaluates them), e.g. {}",
                acc.surrogate_refused.len(),
                acc.surrogate_refused.len() + acc.surrogate_units,
                acc.surrogate_refused[0]
            );
        }
    }
    let mut out = vec![];
    let (mut t_tempering, mut t_correction) = (0.0, 0.0);
    for r in 0..opts.runs {
        let base = (r * 1000) as u64;
        let observe = |s: &StageInfo| {
            if verbose {
                eprintln!(
                    "{what} run {} stage {:3} {} beta {:.3e} ess {:6.0} acc unit/global/nc/rescale {:.2}/{:.2}/{:.2}/{:.2} sweeps {:2} rho {:.2} unique {:5} evals {}",
                    r + 1, s.stage, s.kind, s.beta, s.ess, s.acceptance_unit, s.acceptance_global,
                    s.acceptance_noncentred, s.acceptance_rescale, s.sweeps, s.decorrelation, s.unique_after_resampling, s.model_evals
                );
            }
            progress(
                base + (s.beta * 1000.0) as u64,
                format!("{what} run {}/{} stage {}", r + 1, opts.runs, s.stage),
            );
        };
        let a: &[Arc<Vec<f64>>] = if aux.is_empty() {
            &[]
        } else {
            &aux[r % aux.len()]
        };
        let t_run = std::time::Instant::now();
        let mut res = smc::run_with(&sur, &opts.smc, opts.seed, r, &starts[r], a, &observe)
            .map_err(|e| anyhow!("{what}, run {}: {e}", r + 1))?;
        t_tempering += t_run.elapsed().as_secs_f64();
        let t_corr = std::time::Instant::now();
        if sur.surrogates.iter().any(|s| s.is_some()) {
            correct_to_rom((exact, &sur), opts, r, &mut res, &observe, &mut acc);
        }
        t_correction += t_corr.elapsed().as_secs_f64();
        if let (0, Some(_)) = (r, &base_ref) {
            reference_offsets(target, &starts[0], &res, opts, (what, verbose), &mut acc);
        }
        out.push(res);
    }
    if verbose {
        eprintln!("{what}: tempering {t_tempering:.1} s, correction to the ROM {t_correction:.1} s (all runs)");
    }
    acc.surrogate_proposals_outside_box =
        sur.outside_box.load(std::sync::atomic::Ordering::Relaxed);
    // Final particles beyond the boxes cost ROM evaluations at every later sweep: the
    // reference was narrower than the posterior there.
    acc.surrogate_edge_fraction = edge_fraction(&out, &sur, target);
    Ok((out, acc))
}

/// The base reference of a step: the Laplace-type Gaussian around the units located with the
/// mean auxiliary values (`None`: tempering starts from the prior).
#[allow(clippy::too_many_arguments)]
fn base_reference(
    target: &ModalTarget,
    opts: &SamplerParams,
    what: &str,
    all_aux: &[&Arc<Vec<f64>>],
    start: Option<&[f64]>,
    modular: bool,
    verbose: bool,
    acc: &mut Acceleration,
) -> anyhow::Result<BaseReference> {
    use crate::bayes::reference::{laplace_reference, ReferenceOptions};
    Ok(if opts.from_prior {
        None
    } else {
        // Units are located with the mean auxiliary values (step 2: the step-1 posterior
        // mean); with groups, each group's reference is then moved to its own draw.
        let aux_mean: Vec<f64> = match all_aux.first() {
            None => vec![],
            Some(a0) => (0..a0.len())
                .map(|k| all_aux.iter().map(|a| a[k]).sum::<f64>() / all_aux.len() as f64)
                .collect(),
        };
        let mut ropts = ReferenceOptions {
            start: start.map(<[f64]>::to_vec),
            // A modular step whose units are one parameter (a joint's stiffness per bolted
            // measurement) that can fit a mode exactly (see `ReferenceOptions`): quadrature
            // over the units, for the base and each group's reference; a degenerate q falls
            // back to the frozen quadratic, and the groups with it. With two
            // (an enrichment's refit: ln K and ln k_rot per measurement) the re-formed
            // quadratic ran the demo's ε and δ to e^-75 … e^-244, a reference of zero spread.
            reform_curvature: modular && smc::Target::unit_dim(target) == 1,
            quadrature_units: modular && smc::Target::unit_dim(target) == 1,
            ..ReferenceOptions::default()
        };
        let (mut q, mut info) = laplace_reference(target, &aux_mean, &ropts, opts.seed)
            .map_err(|e| anyhow!("{what}: building the reference: {e}"))?;
        if let (Some(why), true) = (
            q.degeneracy(),
            ropts.reform_curvature || ropts.quadrature_units,
        ) {
            // The quadrature or re-formed quadratic gave a degenerate q: the frozen one.
            if verbose {
                eprintln!("{what}: the quadrature or re-formed reference is degenerate ({why}); frozen curvature instead");
            }
            ropts.reform_curvature = false;
            ropts.quadrature_units = false;
            (q, info) = laplace_reference(target, &aux_mean, &ropts, opts.seed)
                .map_err(|e| anyhow!("{what}: building the reference: {e}"))?;
        }
        if let (Some((after, why)), true) = (&info.fell_back, verbose) {
            eprintln!(
                "{what}: the reference after {after} rounds is degenerate ({why}); the reference of the first {} instead",
                info.rounds
            );
        }
        if let Some(why) = q.degeneracy() {
            anyhow::bail!(
                "{what}: the reference built from the Laplace approximation is degenerate ({why}): \
                 the data pin a coordinate far more tightly than measurement noise can; check \
                 the noise priors (--eps-median, --delta-median, --eps-fixed, --delta-fixed) and the modes used, or start from the prior (--from-prior)"
            );
        }
        acc.reference_model_evals = info.model_evals;
        acc.reference_g_acceptance = info.g_acceptance;
        acc.reference_units_converged = info.converged;
        acc.reference_rounds = info.rounds;
        acc.reference_restarted = info.restarted;
        acc.reference_fell_back = info
            .fell_back
            .as_ref()
            .map(|(after, why)| format!("after {after} rounds: {why}"));
        if verbose {
            eprintln!(
                "{what}: reference ({} rounds) g mean {:.4?}, sd {:.4?}; unit sd {:.3?}",
                info.rounds,
                q.global.mean,
                q.global.sd(),
                q.units.iter().map(|u| u.sd()).collect::<Vec<_>>()
            );
        }
        Some((Arc::new(q), ropts))
    })
}

/// A step's base reference and the options it was built with.
type BaseReference = Option<(
    Arc<crate::bayes::reference::GaussianReference>,
    crate::bayes::reference::ReferenceOptions,
)>;

/// Where the units go across the groups' draws: with groups, each group's units sit
/// elsewhere (its draw moves them), so a few pilot groups, spread over the draws, are moved
/// to their own draws with the ROM; the surrogates' samples then cover the base reference
/// widened by twice the pilots' spread of the units, and the groups' own references are found
/// on the surrogates (their boxes cover where they go).
fn pilot_unit_spread(
    target: &ModalTarget,
    base_ref: &BaseReference,
    grouped: bool,
    all_aux: &[&Arc<Vec<f64>>],
    what: &str,
    acc: &mut Acceleration,
) -> anyhow::Result<Vec<Option<crate::bayes::reference::Mvn>>> {
    use crate::bayes::reference::{reference_for_aux, GaussianReference};
    use rayon::prelude::*;
    let nu = smc::Target::n_units(target);
    Ok(match &base_ref {
        Some((q, ropts)) if grouped => {
            let n_pilot = all_aux.len().min(8);
            let pilots: Vec<(GaussianReference, u64)> = (0..n_pilot)
                .into_par_iter()
                .map(|k| {
                    let a = all_aux[(2 * k + 1) * all_aux.len() / (2 * n_pilot)];
                    reference_for_aux(target, q, a, ropts, 1)
                })
                .collect::<Result<_, _>>()
                .map_err(|e| anyhow!("{what}: a pilot group's reference: {e}"))?;
            acc.reference_model_evals += pilots.iter().map(|(_, e)| e).sum::<u64>();
            // A pilot whose reference came out degenerate says nothing about the spread.
            let n_all = pilots.len();
            let pilots: Vec<(GaussianReference, u64)> = pilots
                .into_iter()
                .filter(|(p, _)| p.degeneracy().is_none())
                .collect();
            acc.degenerate_pilot_groups = n_all - pilots.len();
            (0..nu)
                .map(|b| {
                    if pilots.is_empty() {
                        return None;
                    }
                    let d = q.units[b].dim();
                    let np = pilots.len() as f64;
                    let mean: Vec<f64> = (0..d)
                        .map(|k| pilots.iter().map(|(p, _)| p.units[b].mean[k]).sum::<f64>() / np)
                        .collect();
                    let mut cov = q.units[b].covariance();
                    for (p, _) in &pilots {
                        for i in 0..d {
                            for j in 0..d {
                                cov[i * d + j] += 4.0
                                    * (p.units[b].mean[i] - mean[i])
                                    * (p.units[b].mean[j] - mean[j])
                                    / np;
                            }
                        }
                    }
                    Some(crate::bayes::reference::Mvn::new(mean, &cov))
                })
                .collect()
        }
        _ => vec![None; nu],
    })
}

/// Per unit, a local surrogate of its modal terms over the reference (widened by the pilots'
/// spread), verified against the ROM; `None` where it was refused.
fn fit_surrogates(
    target: &ModalTarget,
    opts: &SamplerParams,
    base_ref: &BaseReference,
    unit_spread: &[Option<crate::bayes::reference::Mvn>],
    all_aux: &[&Arc<Vec<f64>>],
    acc: &mut Acceleration,
) -> Vec<Option<Arc<crate::bayes::surrogate::UnitSurrogate>>> {
    use crate::bayes::surrogate::{fit_unit, SurrogateOptions};
    use rand::SeedableRng;
    use rayon::prelude::*;
    let nu = smc::Target::n_units(target);
    match (&base_ref, opts.surrogate) {
        (Some((q, _)), true) => {
            let ctx = smc::Target::ctx(target, &q.global.mean);
            let so = SurrogateOptions::default();
            let fits: Vec<_> = (0..nu)
                .into_par_iter()
                .map(|b| {
                    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(smc::stream_key(&[
                        opts.seed, 0x5A, b as u64,
                    ]));
                    let unit_q = unit_spread[b].as_ref().unwrap_or(&q.units[b]);
                    let samples: Vec<Vec<f64>> = (0..400)
                        .map(|i| {
                            let a: &[f64] = if all_aux.is_empty() {
                                &[]
                            } else {
                                all_aux[(i * 7919) % all_aux.len()]
                            };
                            target.surrogate_inputs(a, b, &unit_q.sample(&mut rng))
                        })
                        .collect();
                    fit_unit(target, b, &samples, &ctx.eps, &ctx.delta, &so, opts.seed)
                })
                .collect();
            fits.into_iter()
                .enumerate()
                .map(|(b, f)| match f {
                    Ok(s) => {
                        acc.surrogate_units += 1;
                        acc.surrogate_degree.push(Some(s.degree));
                        acc.surrogate_half_width_sd.push(Some(s.half_width));
                        acc.surrogate_max_abs_dlog_lik.push(Some(s.max_abs_dll));
                        acc.surrogate_rom_evals += s.rom_evals;
                        Some(Arc::new(s))
                    }
                    Err(e) => {
                        acc.surrogate_refused.push(format!("unit {b}: {e}"));
                        acc.surrogate_degree.push(None);
                        acc.surrogate_half_width_sd.push(None);
                        acc.surrogate_max_abs_dlog_lik.push(None);
                        None
                    }
                })
                .collect()
        }
        _ => vec![None; nu],
    }
}

/// The correction's model: per unit with a surrogate, a verified subspace of the ROM over the
/// surrogate's box (the ROM beyond it).
fn fit_subspaces(
    target: &ModalTarget,
    opts: &SamplerParams,
    base_ref: &BaseReference,
    surrogates: &[Option<Arc<crate::bayes::surrogate::UnitSurrogate>>],
    acc: &mut Acceleration,
) -> Option<ModalTarget> {
    use crate::bayes::surrogate::{fit_subspace, SubspaceOptions};
    use rayon::prelude::*;
    match (&base_ref, opts.subspace) {
        // With a covariate the ROM is solved per condition and the subspaces (one box of
        // ROM parameters) do not apply (`ModalTarget::model`).
        (Some((q, _)), true)
            if surrogates.iter().any(Option::is_some) && !target.has_covariate() =>
        {
            let ctx = smc::Target::ctx(target, &q.global.mean);
            let so = SubspaceOptions::default();
            let fits: Vec<Option<Result<_, String>>> = surrogates
                .par_iter()
                .enumerate()
                .map(|(b, s)| {
                    let s = s.as_ref()?;
                    Some(fit_subspace(
                        target, b, s, &ctx.eps, &ctx.delta, &so, opts.seed,
                    ))
                })
                .collect();
            let subspaces = fits
                .into_iter()
                .enumerate()
                .map(|(b, f)| match f {
                    Some(Ok(s)) => {
                        acc.subspace_dim.push(Some(s.dim()));
                        acc.subspace_max_abs_dlog_lik.push(Some(s.max_abs_dll));
                        acc.subspace_rom_evals += s.rom_evals;
                        Some(Arc::new(s))
                    }
                    other => {
                        if let Some(Err(e)) = other {
                            acc.subspace_refused.push(format!("unit {b}: {e}"));
                        }
                        acc.subspace_dim.push(None);
                        acc.subspace_max_abs_dlog_lik.push(None);
                        None
                    }
                })
                .collect();
            Some(ModalTarget {
                subspaces,
                ..target.clone()
            })
        }
        _ => None,
    }
}

/// One start per run: the prior, the reference, or (groups carrying their own auxiliary
/// values: a modular step) one reference per group, found on the surrogates.
#[allow(clippy::too_many_arguments)]
fn run_starts(
    sur: &crate::bayes::surrogate::SurrogateTarget<'_>,
    opts: &SamplerParams,
    base_ref: &BaseReference,
    grouped: bool,
    aux: &[Vec<Arc<Vec<f64>>>],
    what: &str,
    acc: &mut Acceleration,
) -> anyhow::Result<Vec<smc::Start>> {
    use crate::bayes::reference::{reference_for_aux, GaussianReference};
    use rayon::prelude::*;
    Ok(match &base_ref {
        None => vec![smc::Start::Prior; opts.runs],
        Some((q, ropts)) if !grouped => {
            let q = if opts.smc.n_particles >= PILOT_MIN_RATIO * PILOT_PARTICLES {
                let t0 = std::time::Instant::now();
                let (q, stages) = crate::bayes::reference::pilot_reference(
                    sur,
                    q,
                    &opts.smc,
                    PILOT_PARTICLES,
                    PILOT_INFLATION,
                    opts.seed,
                )
                .map_err(|e| anyhow!("{what}: the pilot run: {e}"))?;
                acc.pilot_particles = PILOT_PARTICLES;
                acc.pilot_stages = stages;
                acc.pilot_seconds = t0.elapsed().as_secs_f64();
                Arc::new(q)
            } else {
                q.clone()
            };
            vec![smc::Start::Reference(q); opts.runs]
        }
        Some((q, ropts)) => {
            let mut starts = Vec::with_capacity(opts.runs);
            for r in 0..opts.runs {
                let run_aux = &aux[r % aux.len()];
                let refs: Vec<(GaussianReference, u64)> = run_aux
                    .par_iter()
                    .map(|a| reference_for_aux(sur, q, a, ropts, 2))
                    .collect::<Result<_, _>>()
                    .map_err(|e| anyhow!("{what}: a group's reference (run {}): {e}", r + 1))?;
                // A group whose moved reference is degenerate tempers from the base reference
                // instead: still normalised, so still exact, only slower for that group.
                starts.push(smc::Start::GroupReferences(Arc::new(
                    refs.into_iter()
                        .map(|(g, _)| match g.degeneracy() {
                            None => g,
                            Some(_) => {
                                acc.degenerate_group_references += 1;
                                (**q).clone()
                            }
                        })
                        .collect(),
                )));
            }
            starts
        }
    })
}

/// Particles evaluated together in the correction to the ROM: a group's (ten in step 2),
/// at most this many, so that a run without groups still spreads over the threads.
const SHARED_CHUNK: usize = 16;

/// Correction to the ROM: every particle's units re-evaluated by the ROM and weighted by
/// L_ROM / L_surrogate, then the correction stage.
fn correct_to_rom(
    (exact, sur): (&ModalTarget, &crate::bayes::surrogate::SurrogateTarget<'_>),
    opts: &SamplerParams,
    r: usize,
    res: &mut smc::RunResult<crate::bayes::modal::Terms>,
    observe: &(dyn Fn(&StageInfo) + Sync),
    acc: &mut Acceleration,
) {
    use rayon::prelude::*;
    let nu = sur.surrogates.len();
    // Correction to the ROM: every particle's units re-evaluated by the ROM and
    // weighted by L_ROM / L_surrogate. Unit by unit, every particle at a time: a
    // unit's ROM (its subspace's packed terms, 0.45 MB at the bolted ROM's 50 terms)
    // then stays in the core's cache across particles; particle by particle, every
    // evaluation streamed it back (the same sums in the same order either way).
    let ctxs: Vec<_> = res
        .particles
        .par_iter()
        .map(|p| smc::Target::ctx(exact, &p.g))
        .collect();
    let mut lw = vec![0.0; res.particles.len()];
    // The particles of a group (one step-1 draw each) share all stiffness terms but their
    // joint's: evaluated together, the shared part is summed once (`model_shared`).
    let mut by_group: std::collections::BTreeMap<usize, Vec<usize>> = Default::default();
    for (i, p) in res.particles.iter().enumerate() {
        by_group.entry(p.group).or_default().push(i);
    }
    let chunks: Vec<&[usize]> = by_group
        .values()
        .flat_map(|v| v.chunks(SHARED_CHUNK))
        .collect();
    for b in 0..nu {
        if sur.surrogates[b].is_none() {
            continue;
        }
        let mut evaluated: Vec<Option<crate::bayes::modal::Terms>> =
            vec![None; res.particles.len()];
        let per_chunk: Vec<Vec<Option<crate::bayes::modal::Terms>>> = chunks
            .par_iter()
            .map(|idx| {
                let p0 = &res.particles[idx[0]];
                if idx
                    .iter()
                    .all(|&i| Arc::ptr_eq(&res.particles[i].aux, &p0.aux))
                {
                    let xs: Vec<&[f64]> = idx
                        .iter()
                        .map(|&i| res.particles[i].x[b].as_slice())
                        .collect();
                    exact.model_shared(&p0.aux, b, &xs)
                } else {
                    idx.iter()
                        .map(|&i| {
                            let p = &res.particles[i];
                            smc::Target::model(exact, &p.aux, b, &p.x[b])
                        })
                        .collect()
                }
            })
            .collect();
        for (idx, cs) in chunks.iter().zip(per_chunk) {
            for (&i, c) in idx.iter().zip(cs) {
                evaluated[i] = c;
            }
        }
        res.particles
            .par_iter_mut()
            .zip(ctxs.par_iter())
            .zip(lw.par_iter_mut())
            .zip(evaluated.into_par_iter())
            .for_each(|(((p, ctx), lw), c)| {
                let l = match &c {
                    Some(c) => smc::Target::log_lik(exact, ctx, b, &p.x[b], c),
                    None => f64::NEG_INFINITY,
                };
                let l = if l.is_nan() { f64::NEG_INFINITY } else { l };
                *lw += l - p.ll[b];
                p.cache[b] = c;
                p.ll[b] = l;
            });
    }
    let max_dll = lw.iter().map(|v| v.abs()).fold(0.0, f64::max);
    // Mutation after the correction runs on the ROM (every proposal a ROM evaluation):
    // on the demo's step 2 at 2000 × 4 two such sweeps cost ~100 s a run to
    // diversify the 4 % of particles the resampling duplicated (correction ESS 0.99),
    // so they run only when more than a tenth are copies (a surrogate that missed).
    let info = smc::correct(exact, &opts.smc, opts.seed, r, res, &lw, 0.9);
    let rom_evals = (res.particles.len() * acc.surrogate_units) as u64;
    if let Some(last) = res.stages.last_mut() {
        last.model_evals += rom_evals;
    }
    observe(&info);
    acc.correction_ess.push(info.ess);
    acc.correction_max_abs_dlog_lik.push(max_dll);
    acc.correction_sweeps.push(info.sweeps);
}

/// The first run's particles against the reference they started from: per coordinate the
/// mean offset and the sd ratio, in reference sds.
fn reference_offsets(
    target: &ModalTarget,
    start: &smc::Start,
    res: &smc::RunResult<crate::bayes::modal::Terms>,
    opts: &SamplerParams,
    (what, verbose): (&str, bool),
    acc: &mut Acceleration,
) {
    let nu = smc::Target::n_units(target);
    // Each particle measured against its own group's q: (value − q mean) / q sd;
    // the mean of that is the offset, its sd the posterior sd / reference sd.
    let moments = |z: Vec<f64>| -> (f64, f64) {
        let n = z.len().max(1) as f64;
        let m = z.iter().sum::<f64>() / n;
        (
            m,
            (z.iter().map(|v| (v - m).powi(2)).sum::<f64>() / n).sqrt(),
        )
    };
    let q_of = |p: &smc::Particle<crate::bayes::modal::Terms>| {
        start.q(p.group).expect("a reference start")
    };
    // Each group's q sds, once (Mvn::sd sums its Cholesky rows).
    let sds: Vec<(Vec<f64>, Vec<Vec<f64>>)> = (0..opts.smc.groups.max(1))
        .map(|g| {
            let q = start.q(g).expect("a reference start");
            (q.global.sd(), q.units.iter().map(|u| u.sd()).collect())
        })
        .collect();
    let ng = smc::Target::n_global(target);
    let global: Vec<(f64, f64)> = (0..ng)
        .map(|k| {
            moments(
                res.particles
                    .iter()
                    .map(|p| (p.g[k] - q_of(p).global.mean[k]) / sds[p.group].0[k])
                    .collect(),
            )
        })
        .collect();
    acc.reference_offset_global = global.iter().map(|m| m.0).collect();
    acc.reference_sd_ratio_global = global.iter().map(|m| m.1).collect();
    acc.reference_sd_ratio_units = (0..nu)
        .map(|b| {
            (0..smc::Target::unit_dim(target))
                .map(|k| {
                    moments(
                        res.particles
                            .iter()
                            .map(|p| (p.x[b][k] - q_of(p).units[b].mean[k]) / sds[p.group].1[b][k])
                            .collect(),
                    )
                    .1
                })
                .collect()
        })
        .collect();
    if verbose {
        eprintln!(
            "{what}: (posterior mean - reference mean) / reference sd, global {:.2?}",
            acc.reference_offset_global
        );
        eprintln!(
            "{what}: posterior sd / reference sd, global {:.2?}",
            acc.reference_sd_ratio_global
        );
        eprintln!(
            "{what}: posterior sd / reference sd, units {:.2?}",
            acc.reference_sd_ratio_units
        );
    }
}

/// The fraction of the final particles' units beyond their surrogate's box.
fn edge_fraction(
    out: &Results,
    sur: &crate::bayes::surrogate::SurrogateTarget<'_>,
    target: &ModalTarget,
) -> f64 {
    let mut n_edge = 0usize;
    let mut n_all = 0usize;
    for res in out {
        for p in &res.particles {
            for (b, s) in sur.surrogates.iter().enumerate() {
                if let Some(s) = s {
                    n_all += 1;
                    if s.box_position(&target.surrogate_inputs(&p.aux, b, &p.x[b])) > 1.0 {
                        n_edge += 1;
                    }
                }
            }
        }
    }
    n_edge as f64 / n_all.max(1) as f64
}

/// The ROM-box rule: the fraction of `draws` (per draw, every unit's coordinates: the
/// posterior's particles, or draws of the reference, named by `what`), per unit parameter,
/// outside the box the ROM was built and verified for, over the units `evaluated` marks (those
/// whose likelihood evaluates the ROM: a unit informed by a mass term alone never does, and
/// its coordinates may range as widely as the population's). Returns a description of every
/// violation.
#[allow(clippy::too_many_arguments)]
pub fn box_violations(
    draws: &[&[Vec<f64>]],
    what: &str,
    unit_names: &[String],
    param_names: &[String],
    relative: impl Fn(&[f64]) -> Vec<f64>,
    inside: impl Fn(usize, f64) -> bool,
    evaluated: impl Fn(usize) -> bool,
    tolerance: f64,
) -> Vec<String> {
    let mut out = vec![];
    for (b, unit) in unit_names.iter().enumerate() {
        if !evaluated(b) {
            continue;
        }
        // Each draw's coordinates, once per unit.
        let rel: Vec<Vec<f64>> = draws.iter().map(|x| relative(&x[b])).collect();
        for (k, pn) in param_names.iter().enumerate() {
            let n = rel.len();
            let mut bad = 0usize;
            let mut xs = Vec::with_capacity(n);
            for x in rel.iter().map(|x| x[k]) {
                xs.push(x);
                if !inside(k, x) {
                    bad += 1;
                }
            }
            let frac = bad as f64 / n.max(1) as f64;
            if frac > tolerance {
                xs.sort_by(f64::total_cmp);
                out.push(format!(
                    "{unit}: {pn}: {:.1} % of the {what} lies outside the ROM's box ({what} median {:.3})",
                    100.0 * frac,
                    xs[xs.len() / 2]
                ));
            }
        }
    }
    out
}

pub fn particles_of(
    results: &[smc::RunResult<crate::bayes::modal::Terms>],
) -> Vec<(usize, usize, &Particle<crate::bayes::modal::Terms>)> {
    results
        .iter()
        .enumerate()
        .flat_map(|(r, res)| {
            res.particles
                .iter()
                .enumerate()
                .map(move |(i, p)| (r, i, p))
        })
        .collect()
}

/// The surrogate boxes' half-widths in reference sd, e.g. `10` or `2.5–10`.
pub fn half_widths(acc: &Acceleration) -> String {
    let hw: Vec<f64> = acc
        .surrogate_half_width_sd
        .iter()
        .flatten()
        .copied()
        .collect();
    let lo = hw.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = hw.iter().copied().fold(0.0, f64::max);
    if hw.is_empty() || lo == hi {
        format!("{hi}")
    } else {
        format!("{lo}–{hi}")
    }
}

/// The findings when the reference was searched twice, and when final particles lie beyond
/// their surrogate's box (a cost, not a bias: the ROM evaluates them).
pub fn acceleration_findings(acc: &Acceleration, findings: &mut Findings) {
    if let Some(why) = &acc.reference_restarted {
        findings.push(Finding::new(
            Severity::Info,
            "update.reference_restarted",
            format!("the tempering's reference: {why}"),
        ));
    }
    if acc.surrogate_edge_fraction > 1e-3 {
        findings.push(Finding::new(
            Severity::Info,
            "update.surrogate_box_edge",
            format!("{:.2} % of the final particles lie beyond their unit's surrogate box ({} reference sd): the posterior is wider than the reference there, and the ROM evaluated them ({} proposals outside the boxes)", 100.0 * acc.surrogate_edge_fraction, half_widths(acc), acc.surrogate_proposals_outside_box),
        ));
    }
}

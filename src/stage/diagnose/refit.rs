//! The diagnosis's refits: the update steps rerun with a screened mechanism (`update boards
//! --enrich` for a board mechanism, `update joints --enrich` for a joint one), with exactly
//! the options of the work directory's steps (read from their manifests), gated on their
//! convergence; the added mass's point refined by the refits' evidence; and each refit read
//! back as a [`Refit`]. Every call into `crate::stage::update` of the diagnosis is here.

use super::DiagnoseOptions;
use crate::diagnose::library::{is_board_mechanism, Mechanism};
use crate::diagnose::locate::{self, Located};
use crate::diagnose::misfit::{self, Part, RefitShares};
use crate::diagnose::point_search;
use crate::diagnose::regions;
use crate::diagnose::screen::Candidate;
use crate::diagnose::select::{self, setup_errors_of, NewModeNote, Refit};
use crate::diagnose::verdict::{self, quantile, MAX_R_HAT_EVIDENCE};
use crate::io::diagnose_inputs::{
    evidence_runs, joint_ratios, read_refit, refit_gates, refit_residuals, sorted_column,
    RefitSource,
};
use crate::io::diagnose_inputs::{measurement_errors, setup_errors};
use crate::io::read_json;
use crate::io::tables::update::{
    provenance as update_provenance, read_residual_rows, write_residuals,
};
use crate::io::work_dir::{self, WorkDir};
pub(super) use crate::stage::update::load_board;
use crate::stage::update::{ScreenRun, ShapeWeighting, UpdateOptions, MAX_R_HAT};
use crate::stage::StageOutcome;
use crate::update::centre::CentreFit;
use crate::update::joint_screen::JointScreen;
use crate::update::posterior::Residual;
use crate::update::prepare::CentreGate;
use anyhow::{anyhow, Context};
use std::path::Path;

/// A refit directory (or a baseline step) as a [`Refit`] ([`read_refit`]), its convergence
/// gated at the updating's own level ([`MAX_R_HAT`]).
pub(super) fn summarize_refit(
    src: RefitSource<'_>,
    step1_baseline: Option<&[f64]>,
    outliers: &[String],
) -> anyhow::Result<Refit> {
    read_refit(src, step1_baseline, outliers, MAX_R_HAT)
}

/// A candidate's refit directory `out` (`rel` as the diagnosis names it).
fn candidate_source<'a>(cand: &Candidate, out: &'a Path, rel: &'a str) -> RefitSource<'a> {
    RefitSource {
        dir: out,
        rel_dir: rel,
        mechanism: Some(cand.mechanism),
        joint: cand.joint,
    }
}

/// A baseline step's directory `dir` (`rel` as the diagnosis names it).
fn baseline_source<'a>(dir: &'a Path, rel: &'a str) -> RefitSource<'a> {
    RefitSource {
        dir,
        rel_dir: rel,
        mechanism: None,
        joint: None,
    }
}

/// The options the work directory's step 2 ran with (its manifest's config).
pub(super) fn step2_options(work: &Path) -> anyhow::Result<UpdateOptions> {
    step_options(
        work,
        work_dir::UPDATE_JOINTS,
        crate::stage::update::MANIFEST_JOINTS,
    )
}

/// The options the work directory's step 1 ran with.
pub(super) fn step1_options(work: &Path) -> anyhow::Result<UpdateOptions> {
    step_options(
        work,
        work_dir::UPDATE_BOARDS,
        crate::stage::update::MANIFEST_BOARDS,
    )
}

fn step_options(work: &Path, dir: &str, manifest: &str) -> anyhow::Result<UpdateOptions> {
    let p = work.join(dir).join(manifest);
    let m = read_json(&p)?;
    let cfg = m
        .get("config")
        .cloned()
        .ok_or_else(|| anyhow!("{}: no `config`: not a stage manifest", p.display()))?;
    let mut o: UpdateOptions = serde_json::from_value(cfg).with_context(|| {
        format!(
            "{}: config is not the options of `update {}` (written by another version?)",
            p.display(),
            dir.trim_start_matches("update_")
        )
    })?;
    // The manifest's options carry no output directory: the baseline's is where they ran.
    o.out = work.join(dir);
    // A refit's likelihood must be the baseline's: its shape terms take the weights the
    // baseline estimated, not weights of its own (their evidences would not compare).
    if o.model.shape_weights == ShapeWeighting::Auto {
        o.model.shape_weights = ShapeWeighting::from_evidence(&o.out.join("evidence.json"))?;
    }
    Ok(o)
}

/// The options of one candidate's refit: the step-2 options with the enrichment.
fn refit_options(opts: &DiagnoseOptions, base: &UpdateOptions, cand: &Candidate) -> UpdateOptions {
    let mut o = base.clone();
    let wd = WorkDir::new(&opts.work_dir);
    o.ingest_dir = wd.ingest();
    o.pair_dir = wd.pair();
    o.extract_dir = Some(wd.extract());
    o.board = opts.board.clone();
    o.out = opts.out.join(format!("refits/{}", cand.id()));
    o.force = opts.force;
    o.model.enrich = Some(cand.mechanism);
    o.model.enrich_joint = cand.joint;
    o.model.enrich_units = cand.measurements.clone();
    o
}

/// The options of a refit's step 2 (the bolted joints): [`refit_options`] with the budget of
/// ROM evaluations ([`REFIT_ROM_EVALS_PER_PARTICLE_UNIT`]).
fn joint_refit_options(
    opts: &DiagnoseOptions,
    base: &UpdateOptions,
    cand: &Candidate,
) -> UpdateOptions {
    let mut o = refit_options(opts, base, cand);
    o.sampler.smc.max_expensive_evals_per_particle_unit = Some(REFIT_ROM_EVALS_PER_PARTICLE_UNIT);
    o
}

/// A joint refit's budget of bolted-ROM evaluations in its tempering, per particle and unit
/// and run (the sampler gives up beyond it, and the refit is reported failed: never
/// favoured). Inside their verified boxes the surrogates answer and the ROM is rarely called;
/// a unit without a surrogate costs 6–75 a stage. 100 lets a few units temper on the ROM
/// through a run, while an enrichment whose modes the surrogates cannot follow anywhere stops
/// after a stage or two with its reason instead of spending minutes on each of hundreds.
/// Step 1 has none: its free-free ROM is cheap, and a covariate's refit runs it without
/// surrogates by design.
const REFIT_ROM_EVALS_PER_PARTICLE_UNIT: f64 = 100.0;

/// The step-1 options of a board mechanism's refit, its point at `xy_m` (`added_mass`).
fn board_refit_options(
    opts: &DiagnoseOptions,
    base1: &UpdateOptions,
    cand: &Candidate,
    xy_m: Option<[f64; 2]>,
) -> UpdateOptions {
    let mut o = refit_options(opts, base1, cand);
    o.model.enrich_joint = None;
    o.model.enrich_covariate = cand.covariate.clone();
    o.model.enrich_location = xy_m;
    o
}

/// Run one candidate's refit: step 1 (`update boards --enrich`) for a board mechanism, on
/// the step-1 options `base1`; step 2 (`update joints --enrich`) for a joint mechanism, on
/// the step-2 options `base2`.
///
/// `decided` is asked before the last step is rerun for its convergence ([`run_gated`]).
/// A step-2 preparation kept between the sampler's runs of one candidate
/// ([`crate::update::prepare::JointPrep`]).
pub(super) type PrepMemo = std::cell::RefCell<Option<crate::update::prepare::JointPrep>>;

pub(super) fn run_refit(
    opts: &DiagnoseOptions,
    (base1, base2): (&UpdateOptions, Option<&UpdateOptions>),
    cand: &Candidate,
    (decided, gate): (&dyn Fn() -> Option<String>, Option<&CentreGate>),
    prep: &PrepMemo,
    verbose: bool,
) -> anyhow::Result<StageOutcome> {
    if is_board_mechanism(cand.mechanism) {
        // Step 1 with the mechanism (refits/<id>/boards), then, where the campaign has a
        // step 2, step 2 on top of it carrying the boards' coefficients (refits/<id>).
        let mut o = board_refit_options(opts, base1, cand, cand.point_xy_m);
        let boards = o.out.join("boards");
        o.out = boards.clone();
        let Some(base) = base2 else {
            return run_gated(
                o,
                &base1.out,
                |o| crate::stage::update::run_boards(o, verbose),
                decided,
            );
        };
        run_gated(
            o,
            &base1.out,
            |o| crate::stage::update::run_boards(o, verbose),
            &|| None,
        )?;
        let mut o2 = joint_refit_options(opts, base, cand);
        o2.model.enrich_joint = None;
        // The gate's retry reuses the first attempt's preparation (same model spec).
        run_gated(
            o2,
            &base.out,
            |o| {
                crate::stage::update::run_joints_with(
                    o,
                    &boards,
                    &mut prep.borrow_mut(),
                    None,
                    verbose,
                )
            },
            decided,
        )
    } else {
        let base = base2.ok_or_else(|| {
            anyhow!(
                "{}: no step 2 (update_joints): a joint mechanism cannot be refitted",
                opts.work_dir.display()
            )
        })?;
        let o = joint_refit_options(opts, base, cand);
        run_gated(
            o,
            &base.out,
            |o| {
                let boards = WorkDir::new(&opts.work_dir).update_boards();
                crate::stage::update::run_joints_with(
                    o,
                    &boards,
                    &mut prep.borrow_mut(),
                    gate,
                    verbose,
                )
            },
            decided,
        )
    }
}

/// The gate of a joint mechanism's refit that is judged on the located bolted mean shifts
/// (one acting on every assembly alike): after its centre fit, before its ROM and sampler
/// (`update::prepare::CentreGate`), the share of those shifts it would leave
/// ([`misfit::centre_fit_share`], against the baseline step 2's centre fit in its
/// evidence.json); above the decision rule's `max_remaining_share` the refit cannot be
/// favoured ([`select::cannot_be_favoured`]) and is stopped there, with the reason. On the
/// default board the sampler's part of such a refit (its ROM, surrogates and tempering) took
/// 2–3 minutes; a refit of the misfit of the joint model's own form was stopped after none of
/// it. None for other candidates, or where the baseline recorded no centre fit.
pub(super) fn centre_gate(
    opts: &DiagnoseOptions,
    base2: Option<&UpdateOptions>,
    cand: &Candidate,
    located: &Located,
) -> Option<Box<CentreGate<'static>>> {
    if is_board_mechanism(cand.mechanism) || Part::of(cand) != Part::Modes {
        return None;
    }
    let labels: Vec<String> = misfit::bolted_shift_labels(located)
        .into_iter()
        .map(str::to_string)
        .collect();
    if labels.is_empty() {
        return None;
    }
    let ev = read_json(&base2?.out.join("evidence.json")).ok()?;
    let Some(base) = ev["rom_centre_rel_residuals"].as_object() else {
        // A step 2 written before the centre fit's residuals were kept: say why the refit
        // runs in full rather than skip the gate silently.
        eprintln!(
            "diagnose: {}: no centre-fit gate: the baseline step 2's evidence.json has no rom_centre_rel_residuals (written by an older hbmu; rerun update joints to have it)",
            cand.id()
        );
        return None;
    };
    let base: Vec<(String, f64)> = base
        .iter()
        .filter_map(|(l, r)| Some((l.clone(), r.as_f64()?)))
        .collect();
    if base.is_empty() {
        return None;
    }
    let (id, max_share) = (cand.id(), opts.select.max_remaining_share);
    Some(Box::new(move |fit: &CentreFit| {
        let refs: Vec<&str> = labels.iter().map(String::as_str).collect();
        let share = misfit::centre_fit_share(&refs, &base, &fit.rel_residuals)?;
        eprintln!(
            "diagnose: {id}: its centre fit leaves {:.0} % of the located bolted mean shifts ({})",
            100.0 * share,
            refs.join(", ")
        );
        (share > max_share).then(|| {
            format!(
                "not refitted: its centre fit (the enriched model's population-level least-squares fit to the median bolted frequencies) leaves {:.0} % of the located bolted mean shifts against the baseline's centre fit, more than the {:.0} % a favoured refit may leave",
                100.0 * share,
                100.0 * max_share
            )
        })
    }))
}

/// The bulk ESS per run below which a refit's population-level parameter is resampled
/// ([`run_gated`]): Vehtari et al. (2021) ask for 100 per chain before R-hat and the
/// posterior quantiles are to be trusted.
const MIN_ESS_PER_RUN: f64 = 100.0;

/// The particles' factor that brings a bulk ESS of `ess` to `min_ess`: the ESS of an SMC
/// population grows in proportion to its particles, so the ratio rounded up, at least 2 (a
/// retry that only just reaches the bar would miss it half the time) and at most 4.
fn ess_particle_factor(ess: f64, min_ess: f64) -> usize {
    let r = (min_ess / ess.max(1.0)).ceil();
    if r.is_finite() {
        (r as usize).clamp(2, 4)
    } else {
        4
    }
}

/// Why a refit step's first attempt is run again, with whether the retry takes more runs
/// and its particles' factor; None to keep it. `all_r_hat` is the worst population-level
/// R-hat across runs, `own_r_hat` and `own_ess` the worst of the parameters the baseline
/// lacks (R-hat over the mechanism's locations and scales, ESS over its locations: the
/// finding's estimates), `min_ess` the ESS bar of the step's runs (None where the step's
/// estimates are not the ones reported: no ESS rule).
///
/// - Above [`MAX_R_HAT_EVIDENCE`] on any parameter the evidence gives no Bayes factor
///   (`verdict::r_hat_gate`): more runs and particles.
/// - Above the updating's own level ([`MAX_R_HAT`]) on the mechanism's own parameters its
///   estimates are approximate: the same.
/// - Between the two levels on a parameter the baseline has too (a nuisance the finding does
///   not report, e.g. μ of the transverse shear modulus) the runs' spread of the log
///   evidence is still its standard error, so the Bayes factor stands and the gate marks the
///   refit approximate; a retry there (four times the first attempt's work) decided nothing:
///   on the realistic two-effect campaign the added-mass refit reran at 4 × 400 for an R-hat
///   of 1.059 on μ of G_z, 409 s, and its ln B (409.5 ± 0.1) was decisive either way.
/// - Too few effective draws of a location of the mechanism's: more particles (the ESS of
///   each run grows with them, and the bar with the runs).
///
/// For disagreeing runs more runs, not only more particles: two runs that settle on
/// different trade-offs between the modes' error scales stay apart however many particles
/// each has, and R-hat from two runs is itself too noisy to tell.
fn retry_rule(
    all_r_hat: Option<(String, f64)>,
    own_r_hat: Option<(String, f64)>,
    own_ess: Option<(String, f64)>,
    min_ess: Option<f64>,
) -> Option<(String, bool, usize)> {
    let disagree = |(name, rh): (String, f64), bar: f64| {
        (rh > bar).then(|| {
            (
                format!("R-hat across runs of {name} {rh:.3} > {bar}"),
                true,
                2,
            )
        })
    };
    all_r_hat
        .and_then(|w| disagree(w, MAX_R_HAT_EVIDENCE))
        .or_else(|| own_r_hat.and_then(|w| disagree(w, MAX_R_HAT)))
        .or_else(|| {
            let min_ess = min_ess?;
            own_ess.filter(|(_, e)| *e < min_ess).map(|(name, ess)| {
                (
                    format!("bulk ESS of {name} {ess:.0} < {min_ess:.0} ({MIN_ESS_PER_RUN} a run)"),
                    false,
                    ess_particle_factor(ess, min_ess),
                )
            })
        })
}

/// Run one update step of a refit; when [`retry_rule`] asks, run it once more: with twice
/// the particles and twice the runs (at least 4) where the runs disagree, with the particles
/// that bring the ESS to its bar ([`ess_particle_factor`]) and the same runs where a location
/// of the mechanism's has fewer than [`MIN_ESS_PER_RUN`] effective draws a run. Without this
/// a decisive candidate whose runs disagreed gave no Bayes factor at all, and an estimate's
/// quantiles rested on too few draws. The ESS rule is Vehtari et al.'s for the quantiles one
/// reports, so it reads the finding's estimates only; the baseline's own parameters are
/// reported by the baseline, which no such rule reruns.
/// The retry replaces the first attempt's outputs; if it still disagrees, the gate reports
/// it.
///
/// The retry is for the Bayes factor and the estimates. Before it, `decided` says whether the
/// first attempt already misses a bar of the decision rule that the evidence does not set
/// ([`select::cannot_be_favoured`]); then the refit cannot be favoured whatever its Bayes
/// factor, and the retry is not run.
fn run_gated(
    mut o: UpdateOptions,
    baseline: &Path,
    step: impl Fn(&UpdateOptions) -> anyhow::Result<StageOutcome>,
    decided: &dyn Fn() -> Option<String>,
) -> anyhow::Result<StageOutcome> {
    let r = step(&o)?;
    let summary = o.out.join("summary.parquet");
    let gates = refit_gates(&summary, &baseline.join("summary.parquet"))?;
    // The ESS rule is for the estimates a finding reports; a retry for estimates another
    // refit reports would sharpen quantiles nobody reads (on the realistic fixture campaign,
    // 2 runs of 400 particles).
    let estimates_here =
        !judged_by_new_modes_refit(o.model.enrich, o.model.enrich_new_modes, &o.out);
    let rule = |min_ess| {
        retry_rule(
            gates.r_hat.clone(),
            gates.own_r_hat.clone(),
            gates.own_ess.clone(),
            min_ess,
        )
    };
    let bar = MIN_ESS_PER_RUN * o.sampler.runs as f64;
    let Some((why, more_runs, factor)) = rule(estimates_here.then_some(bar)) else {
        if let Some((why, ..)) = rule(Some(bar)).filter(|_| !estimates_here) {
            eprintln!(
                "diagnose: {}: {why}; not rerun: its estimates come from the refit with the mechanism's own modes",
                o.out.display()
            );
        }
        return Ok(r);
    };
    if let Some(not) = decided() {
        eprintln!(
            "diagnose: {}: {why}; not rerun: it cannot be favoured whatever its Bayes factor ({not})",
            o.out.display()
        );
        return Ok(r);
    }
    o.sampler.smc.n_particles *= factor;
    if more_runs {
        o.sampler.runs = (2 * o.sampler.runs).max(4);
    }
    eprintln!(
        "diagnose: {}: {why}: rerun with {} runs of {} particles",
        o.out.display(),
        o.sampler.runs,
        o.sampler.smc.n_particles
    );
    step(&o)
}

/// A joint refit's enriched model may carry modes the baseline lacks (a fixture's own) that
/// the campaign identified and pair left unpaired (`new_modes` of its evidence.json). The
/// refit itself leaves them out, so that its evidence is over the baseline's data; a second
/// refit (`<refit>/new_modes`, `update joints --enrich-new-modes`) fits them too, and its
/// population medians replace the estimates: the mode is the mechanism's most direct
/// evidence (a fixture's own resonance pins its frequency). Its held-out errors replace the
/// first refit's too: the held-out modes are in neither refit's data, and the first refit,
/// blind to the mechanism's own mode, can put it where it spoils its neighbours (on the
/// realistic fixture campaign at 2683 Hz against the measured 2761 Hz, the bolted held-out
/// error going from 0.361 % to 0.621 %). It is not run for a refit that cannot be favoured
/// whatever its Bayes factor and held-out error (`not_favourable` is then why): better
/// estimates of a mechanism the diagnosis will not claim are not worth a second sampler's
/// run; the modes are still named.
#[allow(clippy::too_many_arguments)]
fn new_modes_refit(
    opts: &DiagnoseOptions,
    base2: Option<&UpdateOptions>,
    cand: &Candidate,
    out: &Path,
    rel: &str,
    r: &mut Refit,
    not_favourable: Option<String>,
    prep: &PrepMemo,
    verbose: bool,
) -> anyhow::Result<()> {
    let found = listed_new_modes(out)?;
    let Some(base) = base2.filter(|_| !found.is_empty() && r.failed.is_none()) else {
        return Ok(());
    };
    let step = match not_favourable {
        Some(why) => Err(anyhow!(
            "not refitted: the refit cannot be favoured whatever its Bayes factor ({why})"
        )),
        None => Ok(()),
    };
    let nm_rel = format!("{rel}/new_modes");
    let step = step.and_then(|_| {
        let mut o = joint_refit_options(opts, base, cand);
        o.out = out.join("new_modes");
        o.model.enrich_new_modes = true;
        run_gated(
            o.clone(),
            &base.out,
            |o| {
                let boards = WorkDir::new(&opts.work_dir).update_boards();
                crate::stage::update::run_joints_with(
                    o,
                    &boards,
                    &mut prep.borrow_mut(),
                    None,
                    verbose,
                )
            },
            &|| None,
        )
        .and_then(|_| summarize_refit(candidate_source(cand, &o.out, &nm_rel), None, &[]))
    });
    let (dir, why) = match step {
        Ok(nm) if nm.failed.is_none() && !nm.estimates.is_empty() => {
            if !nm.held_out.is_empty() {
                r.held_out = nm.held_out.clone();
            }
            r.estimates = nm
                .estimates
                .into_iter()
                .map(|mut e| {
                    e.scope = format!("{}, fitted with the mechanism's own mode(s)", e.scope);
                    e
                })
                .collect();
            (Some(nm_rel), None)
        }
        Ok(nm) => (
            None,
            Some(nm.failed.unwrap_or_else(|| "no estimates".into())),
        ),
        Err(e) => (None, Some(format!("{e:#}").replace('\n', " "))),
    };
    r.new_modes = found
        .iter()
        .map(|m| NewModeNote {
            label: m["label"].as_str().unwrap_or_default().to_string(),
            model_freq_hz: m["model_freq_hz"].as_f64().unwrap_or(f64::NAN),
            median_freq_hz: m["median_freq_hz"].as_f64().unwrap_or(f64::NAN),
            n_paired: m["n_paired"].as_u64().unwrap_or(0) as usize,
            n_measurements: m["n_measurements"].as_u64().unwrap_or(0) as usize,
            estimates_dir: dir.clone(),
            estimates_failed: why.clone(),
        })
        .collect();
    Ok(())
}

/// The located point of an `added_mass` candidate, refined by the refits' own evidence
/// ([`crate::diagnose::point_search`]): step-1 refits with the point fixed at the probes of
/// a compass search (`refits/<id>/location/x<mm>_y<mm>`, each a hashed stage of its own)
/// from the localisation's grid point, steps halving from half a grid step to an eighth while
/// a step can still move a frequency by the practical threshold
/// ([`point_search::SearchPlan::for_point`]). Returns the candidate at the
/// refined point, with the location's Laplace posterior in place of the map's Occam factor
/// and ln(mass) spread, and every probe. Any other candidate, or a search that could not
/// run (a probe off the board, a failed refit), is returned as it was; that, and a last
/// stencil without a maximum, is the returned note (in the refit's `location_note` and a
/// `diagnose.location_search` warning among the stage's findings).
pub(super) fn refine_point(
    opts: &DiagnoseOptions,
    board: &crate::fem::Board,
    base1: &UpdateOptions,
    cand: &Candidate,
    verbose: bool,
) -> (Candidate, Vec<point_search::Probe>, Option<String>) {
    let (Mechanism::AddedMass, Some(start), Some(_)) =
        (cand.mechanism, cand.point_xy_m, cand.point_located)
    else {
        return (cand.clone(), vec![], None);
    };
    // Each probe with half the refit's particles (the log evidence between probes differs by
    // tens to hundreds, its error across runs is a few).
    let grid = regions::grid_step_m(board);
    let shift = cand.point_located.map_or(0.0, |p| p.step_shift_rel);
    let threshold = opts.select.practical_threshold_rel;
    let Some(plan) = point_search::SearchPlan::for_point(grid, shift, threshold) else {
        let why = format!(
            "the point not refined: moving the fitted mass by {:.2} mm changes no fitted frequency by more than {:.3} %, under the {:.2} % practical threshold",
            0.5 * grid * 1e3,
            100.0 * 0.5 * shift,
            100.0 * threshold
        );
        eprintln!("diagnose: {}: {why}", cand.id());
        let mut c = cand.clone();
        c.reason = format!("{}; {why}", c.reason);
        return (c, vec![], None);
    };
    let probe = |p: [f64; 2]| -> anyhow::Result<point_search::Probe> {
        let mut o = board_refit_options(opts, base1, cand, Some(p));
        o.sampler.smc.n_particles = (o.sampler.smc.n_particles / 2).max(100);
        o.out = opts.out.join(format!(
            "refits/{}/location/x{:.3}_y{:.3}",
            cand.id(),
            p[0] * 1e3,
            p[1] * 1e3
        ));
        crate::stage::update::run_boards(&o, verbose)?;
        let z = evidence_runs(&o.out)?;
        let m = sorted_column(
            &o.out.join("population.parquet"),
            &format!("mu_{}", crate::diagnose::library::ADDED_MASS),
        )?;
        if z.is_empty() || m.is_empty() {
            anyhow::bail!("{}: no log evidence or no mass", o.out.display());
        }
        let (log_evidence, se) = select::runs_mean_se(&z).unwrap_or((f64::NAN, f64::NAN));
        let q = point_search::Probe {
            x_m: p[0],
            y_m: p[1],
            log_evidence,
            // One run has no spread to go by: every difference then counts.
            log_evidence_se: if se.is_finite() { se } else { 0.0 },
            ln_mass_kg: quantile(&m, 0.5).ln(),
            misfit_rel: point_search::worst_mean_residual(&refit_residuals(&o.out)?),
        };
        eprintln!(
            "diagnose: {}: point ({:.3}, {:.3}) mm: log evidence {:.2}, mass {:.4} g, worst free-free mode {:.3} %",
            cand.id(),
            p[0] * 1e3,
            p[1] * 1e3,
            q.log_evidence,
            q.ln_mass_kg.exp() * 1e3,
            100.0 * q.misfit_rel
        );
        Ok(q)
    };
    let point_search::SearchResult {
        probes,
        last,
        end_xy_m: end,
    } = match point_search::search(start, &plan, probe) {
        Ok(r) => r,
        Err(e) => {
            let note = format!(
                "the point's refinement stopped ({}); the refit keeps the located point ({:.2}, {:.2}) mm and the localisation map's spread",
                format!("{e:#}").replace('\n', " "),
                start[0] * 1e3,
                start[1] * 1e3
            );
            eprintln!("diagnose: {}: {note}", cand.id());
            return (cand.clone(), vec![], Some(note));
        }
    };
    let (c, note) =
        point_search::refined(cand, end, last.as_ref(), board.length_x_m * board.width_y_m);
    if let Some(n) = &note {
        eprintln!("diagnose: {}: {n}", cand.id());
    }
    (c, probes, note)
}

/// What the decision rule compares a refit with: the located misfit, the locate step's
/// input, the baseline's summary and step-1 log evidence per run.
pub(super) struct Against<'a> {
    pub located: &'a Located,
    pub input: &'a locate::LocateInput,
    pub baseline: &'a Refit,
    pub z1: &'a [f64],
}

/// Why the refit of `cand` as it stands in its directory cannot be favoured whatever its
/// Bayes factor ([`select::cannot_be_favoured`]); None where it could be, or where its
/// outputs cannot be read (then the evidence is left to decide). A joint refit whose
/// enriched model has modes of its own that the campaign shows is judged without its
/// held-out error, as [`refit`] judges it: the refit that fits those modes too decides it
/// ([`new_modes_refit`]). Judged with it, the fixture refit's retry for its ESS was skipped
/// on the realistic fixture campaign for a held-out error (0.372 % → 0.618 %) that a refit
/// blind to the fixture's own resonance makes, and the second refit never ran.
pub(super) fn cannot_be_favoured(
    opts: &DiagnoseOptions,
    cand: &Candidate,
    a: &Against,
) -> Option<String> {
    let rel = format!("refits/{}", cand.id());
    let out = opts.out.join(&rel);
    let outliers = &a.located.measurements_after_covariates;
    let r = summarize_refit(candidate_source(cand, &out, &rel), Some(a.z1), outliers).ok()?;
    let after = refit_residuals(&out).ok()?;
    judged(opts, cand, a, r, &after, &out)
}

/// Why the refit `r` of `cand` (its residuals `after`, its directory `out`) cannot be
/// favoured whatever its Bayes factor: [`select::cannot_be_favoured`] with its shares of the
/// located misfit, and without its held-out error where it is a joint refit whose enriched
/// model has modes of its own that the campaign shows ([`new_modes_refit`] judges those).
fn judged(
    opts: &DiagnoseOptions,
    cand: &Candidate,
    a: &Against,
    mut r: Refit,
    after: &[locate::ResidualObs],
    out: &Path,
) -> Option<String> {
    with_shares(opts, cand, a, &mut r, after);
    if judged_by_new_modes_refit(Some(cand.mechanism), false, out) {
        r.held_out.clear();
    }
    select::cannot_be_favoured(a.baseline, &r, &opts.select)
}

/// Whether the refit of `mechanism` in `out` leaves its estimates and held-out error to the
/// refit that fits its enriched model's own modes ([`new_modes_refit`]): a joint mechanism
/// whose evidence.json lists modes of its own that the campaign shows, and not itself that
/// refit (`fits_new_modes`). False where the evidence cannot be read.
fn judged_by_new_modes_refit(
    mechanism: Option<Mechanism>,
    fits_new_modes: bool,
    out: &Path,
) -> bool {
    mechanism.is_some_and(|m| !is_board_mechanism(m))
        && !fits_new_modes
        && listed_new_modes(out).is_ok_and(|m| !m.is_empty())
}

/// The modes a joint refit's enriched model adds that the campaign shows (`new_modes` of
/// its evidence.json; empty where it lists none).
fn listed_new_modes(out: &Path) -> anyhow::Result<Vec<serde_json::Value>> {
    let ev = read_json(&out.join("evidence.json"))?;
    Ok(ev["new_modes"].as_array().cloned().unwrap_or_default())
}

/// Set a refit's share of the located misfit it leaves and the misfit it removes, from its
/// residuals `after`.
fn with_shares(
    opts: &DiagnoseOptions,
    cand: &Candidate,
    a: &Against,
    r: &mut Refit,
    after: &[locate::ResidualObs],
) {
    let shares = RefitShares::new(a.located, a.input, after, &opts.locate, &cand.measurements);
    r.remaining_share = shares.own(cand);
    r.explained_rel = shares.explained(cand);
}

/// The every-joint candidate's screen ([`screen_first`]): the screen, the screened
/// assemblies' residuals under its model, and why the candidate is not refitted, if it is
/// not.
pub(super) struct Screened {
    pub screen: Option<JointScreen>,
    pub residuals: Vec<Residual>,
    pub skip: Option<String>,
}

/// The every-joint candidate on its outlier assemblies is screened first, and refitted only
/// where the screen could clear the evidence bar and the practical threshold: its screen
/// (None for other candidates, or without a step 2) and why it is not refitted, if it is not
/// (select::screen_says_skip). Shared by the diagnosis and `--only`, so a cluster's fan-out
/// skips what the local run skips.
pub(super) fn screen_first(
    opts: &DiagnoseOptions,
    base2: Option<&UpdateOptions>,
    cand: &Candidate,
    verbose: bool,
) -> Screened {
    let (screen, residuals) = match base2 {
        Some(base2)
            if crate::diagnose::library::is_every_joint(Some(cand.mechanism), cand.joint)
                && !cand.measurements.is_empty() =>
        {
            let t0 = std::time::Instant::now();
            let s = joint_screen(opts, base2, cand, verbose);
            eprintln!(
                "diagnose: per-assembly joint screen of {} assemblies in {:.1} s: {}",
                cand.measurements.len(),
                t0.elapsed().as_secs_f64(),
                match &s {
                    Ok(ScreenRun {
                        screen:
                            JointScreen {
                                log_bayes_factor: Some(b),
                                log_bayes_factor_se: Some(se),
                                ..
                            },
                        ..
                    }) => format!("ln B {b:.1} ± {se:.1}"),
                    Ok(s) => format!("failed: {}", s.screen.failed.clone().unwrap_or_default()),
                    Err(e) => format!("failed: {e:#}"),
                }
            );
            match s {
                Ok(s) => {
                    if verbose {
                        print_screen(&s.screen);
                    }
                    (Some(s.screen), s.residuals)
                }
                // Recorded in diagnosis.json; the refit decides.
                Err(e) => (
                    Some(JointScreen::failed(format!("{e:#}").replace('\n', " "))),
                    vec![],
                ),
            }
        }
        _ => (None, vec![]),
    };
    let skip = screen
        .as_ref()
        .and_then(|s| select::screen_says_skip(s, &opts.select));
    Screened {
        screen,
        residuals,
        skip,
    }
}

/// The every-joint candidate judged on its screen (no sampler's refit): the screen's model
/// (each screened assembly's joints their own stiffnesses, the rest the baseline's) is the
/// baseline's posterior reweighted by importance sampling, so it has the evidence, the
/// estimates and the predictions a refit has. Its Bayes factor is the screen's; its
/// residuals (`refits/<id>/screen/residuals.parquet`) are the baseline step 2's with the
/// screened assemblies' rows from the screen's posterior. The other assemblies keep the
/// baseline's predictions: the screen's model leaves their likelihood as it was, and the
/// one thing it changes for them, the weights of the baseline's draws of the population,
/// is neglected (the screen keeps too few draws, 16, to resample their predictions from).
/// The step-2 seed and inputs fix every byte.
fn screen_refit(
    opts: &DiagnoseOptions,
    board: &crate::fem::Board,
    cand: &Candidate,
    screen: JointScreen,
    rows: Vec<Residual>,
) -> anyhow::Result<Refit> {
    let rel = format!("refits/{}/screen", cand.id());
    let out = opts.out.join(&rel);
    let joints = WorkDir::new(&opts.work_dir).update_joints();
    let screened: std::collections::BTreeSet<&str> = screen
        .units
        .iter()
        .map(|u| u.measurement_id.as_str())
        .collect();
    let base = read_residual_rows(&joints.join("residuals.parquet"))?;
    let mut merged: Vec<Residual> = base
        .into_iter()
        .filter(|r| !screened.contains(r.measurement_id.as_str()))
        .collect();
    merged.extend(rows);
    merged.sort_by(|a, b| (&a.measurement_id, &a.label).cmp(&(&b.measurement_id, &b.label)));
    let fingerprint = read_json(&joints.join(crate::stage::update::MANIFEST_JOINTS))?
        ["fingerprint"]
        .as_str()
        .unwrap_or_default()
        .to_string();
    std::fs::create_dir_all(&out)?;
    let p = out.join("residuals.parquet");
    write_residuals(
        &p,
        &merged,
        &update_provenance(
            "diagnose joint screen",
            &format!("{fingerprint}; {}", cand.id()),
        ),
    )?;
    let (estimates, deviating_joints) = verdict::screen_estimates(&screen, board);
    let held_out_by_measurement = measurement_errors(&p, false)?;
    Ok(Refit {
        mechanism: Some(cand.mechanism),
        joint: cand.joint,
        dir: rel,
        held_out: setup_errors_of(&held_out_by_measurement, |_| true),
        held_out_by_measurement,
        outliers: screened.iter().map(|m| m.to_string()).collect(),
        updated: setup_errors(&p, true)?,
        estimates,
        deviating_joints,
        joint_screen: Some(screen),
        from_screen: true,
        ..Default::default()
    })
}

/// Run (or find up to date) one candidate's refit.
pub(super) fn refit(
    opts: &DiagnoseOptions,
    board: &crate::fem::Board,
    bases: (&UpdateOptions, Option<&UpdateOptions>),
    cand: &Candidate,
    against: &Against,
    verbose: bool,
) -> Refit {
    let (outliers, z1) = (&against.located.measurements_after_covariates, against.z1);
    let (refined, probes, location_note) = refine_point(opts, board, bases.0, cand, verbose);
    let cand = &refined;
    let rel = format!("refits/{}", cand.id());
    let out = opts.out.join(&rel);
    let decided = || cannot_be_favoured(opts, cand, against);
    let Screened {
        screen,
        residuals,
        skip,
    } = screen_first(opts, bases.1, cand, verbose);
    if let Some(why) = skip {
        return Refit {
            joint_screen: screen,
            ..Refit::failed(Some(cand.mechanism), cand.joint, rel, why)
        };
    }
    // A screen with a result is the refit; a failed one leaves it to the sampler.
    if let Some(s) = screen.as_ref().filter(|s| s.log_bayes_factor.is_some()) {
        return screen_refit(opts, board, cand, s.clone(), residuals).unwrap_or_else(|e| Refit {
            joint_screen: screen.clone(),
            ..Refit::failed(
                Some(cand.mechanism),
                cand.joint,
                format!("{rel}/screen"),
                format!("{e:#}").replace('\n', " "),
            )
        });
    }
    let gate = centre_gate(opts, bases.1, cand, against.located);
    // One preparation (centre fit and ROM) for the refit, its gate's retry and its new-mode
    // refit: the same model, the new mode's label aside (`joint_prep_key`).
    let prep = PrepMemo::default();
    let r = run_refit(
        opts,
        bases,
        cand,
        (&decided, gate.as_deref()),
        &prep,
        verbose,
    )
    .and_then(|_| {
        let mut r = summarize_refit(candidate_source(cand, &out, &rel), Some(z1), outliers)?;
        if crate::diagnose::library::is_every_joint(Some(cand.mechanism), cand.joint) {
            let by = joint_ratios(&out, board.holes.len())?;
            let (est, dev) = verdict::every_joint_estimates(by, board, outliers);
            r.estimates.extend(est);
            r.deviating_joints = dev;
        }
        if !is_board_mechanism(cand.mechanism) {
            // The refit as summarized here, not read again from its directory; its held-out
            // error aside: the refit that fits the mechanism's own modes is the one whose
            // predictions the held-out modes judge (`new_modes_refit`).
            let not_favourable = refit_residuals(&out)
                .ok()
                .and_then(|after| judged(opts, cand, against, r.clone(), &after, &out));
            new_modes_refit(
                opts,
                bases.1,
                cand,
                &out,
                &rel,
                &mut r,
                not_favourable,
                &prep,
                verbose,
            )?;
        }
        // The location was chosen from the data: its Occam factor joins the evidence, and
        // its uncertainty the mass's interval (the refit's is conditional on the point).
        if let Some(pl) = cand.point_located {
            verdict::with_located_point(&mut r, pl, cand.point_xy_m);
            r.location_probes = probes.clone();
            r.location_note = location_note.clone();
        }
        Ok(r)
    });
    let mut r = match r {
        Ok(r) => r,
        Err(e) => Refit {
            location_note,
            ..Refit::failed(
                Some(cand.mechanism),
                cand.joint,
                rel,
                format!("{e:#}").replace('\n', " "),
            )
        },
    };
    r.joint_screen = screen;
    r
}

/// The screen per assembly, for `-v`.
fn print_screen(s: &JointScreen) {
    for u in &s.units {
        eprintln!(
            "  {}: ln B {:.1} ± {:.1}, frequency effect {}, min ESS {:.0}, ratios {}",
            u.measurement_id,
            u.log_bayes_factor,
            u.log_bayes_factor_se,
            u.freq_effect_rel
                .map_or("not evaluated".to_string(), |e| format!(
                    "{:.3} %",
                    100.0 * e
                )),
            u.min_ess,
            u.joints
                .iter()
                .map(|j| format!(
                    "j{} {:.2} ({:.2}–{:.2})",
                    j.joint, j.ratio_median, j.ratio_q05, j.ratio_q95
                ))
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
}

/// Importance draws per assembly and baseline draw, and baseline draws averaged over, of the
/// per-assembly joint screen: the IS standard error of one assembly's ln Z is then ~0.05
/// where its ESS is ~half the draws, and 16 of the baseline's draws span its posterior of
/// the error scales.
const SCREEN_IS_DRAWS: usize = 300;
const SCREEN_BASELINE_DRAWS: usize = 16;

/// The every-joint candidate's per-assembly screen on its outlier assemblies
/// ([`crate::update::joint_screen`]), with the step-2 options of its refit.
fn joint_screen(
    opts: &DiagnoseOptions,
    base2: &UpdateOptions,
    cand: &Candidate,
    verbose: bool,
) -> anyhow::Result<ScreenRun> {
    let o = refit_options(opts, base2, cand);
    let wd = WorkDir::new(&opts.work_dir);
    crate::stage::update::screen_joint_units(
        &o,
        &wd.update_boards(),
        &wd.update_joints(),
        (SCREEN_BASELINE_DRAWS, SCREEN_IS_DRAWS),
        opts.select.practical_threshold_rel,
        verbose,
    )
}

/// The baselines' summaries: step 1's, and where the campaign has a step 2, step 2's with
/// step 1's free-free errors (a board mechanism changes both).
pub(super) fn baselines(w: &Path, step2: bool) -> anyhow::Result<(Refit, Option<Refit>)> {
    let wd = WorkDir::new(w);
    let boards = wd.update_boards();
    let baseline1 = summarize_refit(baseline_source(&boards, "../update_boards"), None, &[])?;
    let baseline = if step2 {
        let joints = wd.update_joints();
        let mut b = summarize_refit(baseline_source(&joints, "../update_joints"), None, &[])?;
        b.held_out.extend(baseline1.held_out.iter().cloned());
        b.held_out_by_measurement
            .extend(baseline1.held_out_by_measurement.iter().cloned());
        b.updated.extend(baseline1.updated.iter().cloned());
        Some(b)
    } else {
        None
    };
    Ok((baseline1, baseline))
}

#[cfg(test)]
mod tests {
    /// An ESS short of the bar asks for the particles that reach it (ESS grows with them), at
    /// least twice and at most four times the first attempt's.
    #[test]
    fn the_ess_retry_scales_the_particles_to_the_shortfall() {
        use super::ess_particle_factor;
        assert_eq!(ess_particle_factor(165.0, 200.0), 2);
        assert_eq!(ess_particle_factor(199.0, 200.0), 2);
        assert_eq!(ess_particle_factor(65.0, 200.0), 4);
        assert_eq!(ess_particle_factor(90.0, 200.0), 3);
        assert_eq!(ess_particle_factor(0.0, 200.0), 4);
        assert_eq!(ess_particle_factor(f64::NAN, 200.0), 4);
    }

    /// A joint refit whose evidence lists modes of its own leaves its estimates and held-out
    /// error to the refit that fits them; that refit, a board mechanism's, one without such
    /// modes and one without a readable evidence.json keep their own.
    #[test]
    fn only_a_joint_refit_listing_new_modes_is_judged_by_the_new_modes_refit() {
        use super::judged_by_new_modes_refit as by;
        use crate::diagnose::library::Mechanism;
        let t = tempfile::tempdir().unwrap();
        let (with, without, none) = (t.path().join("a"), t.path().join("b"), t.path().join("c"));
        for (d, ev) in [
            (&with, r#"{"new_modes": [{"label": "fixture-1"}]}"#),
            (&without, r#"{"new_modes": []}"#),
        ] {
            std::fs::create_dir_all(d).unwrap();
            std::fs::write(d.join("evidence.json"), ev).unwrap();
        }
        let fixture = Some(Mechanism::FixtureCompliance);
        assert!(by(fixture, false, &with));
        assert!(!by(fixture, true, &with));
        assert!(!by(fixture, false, &without));
        assert!(!by(fixture, false, &none));
        assert!(!by(Some(Mechanism::AddedMass), false, &with));
        assert!(!by(None, false, &with));
    }

    /// A refit step is retried where its evidence gives no Bayes factor (any parameter above
    /// 1.1), where the mechanism's own parameters disagree above 1.05, or where its
    /// estimates have too few draws; a nuisance the baseline has too, between 1.05 and 1.1,
    /// is no reason: the Bayes factor stands.
    #[test]
    fn a_refit_is_retried_for_its_bayes_factor_and_its_own_estimates_only() {
        use super::retry_rule;
        let w = |n: &str, v: f64| Some((n.to_string(), v));
        let own_ok = w("mu_added_mass_g", 1.01);
        let ess_ok = w("mu_added_mass_g", 400.0);
        // The two-effect campaign's added-mass refit: a baseline nuisance at 1.059.
        assert_eq!(
            retry_rule(
                w("mu_g_z_pa", 1.059),
                own_ok.clone(),
                ess_ok.clone(),
                Some(200.0)
            ),
            None
        );
        let (why, more_runs, factor) = retry_rule(
            w("mu_g_z_pa", 1.12),
            own_ok.clone(),
            ess_ok.clone(),
            Some(200.0),
        )
        .unwrap();
        assert!(why.contains("mu_g_z_pa 1.120 > 1.1"), "{why}");
        assert_eq!((more_runs, factor), (true, 2));
        let (why, more_runs, _) = retry_rule(
            w("sigma_added_mass_g", 1.06),
            w("sigma_added_mass_g", 1.06),
            ess_ok,
            Some(200.0),
        )
        .unwrap();
        assert!(why.contains("sigma_added_mass_g 1.060 > 1.05"), "{why}");
        assert!(more_runs);
        let (why, more_runs, factor) = retry_rule(
            w("mu_g_z_pa", 1.02),
            own_ok,
            w("mu_added_mass_g", 90.0),
            Some(200.0),
        )
        .unwrap();
        assert!(
            why.contains("bulk ESS of mu_added_mass_g 90 < 200"),
            "{why}"
        );
        assert_eq!((more_runs, factor), (false, 3));
        assert_eq!(retry_rule(None, None, None, Some(200.0)), None);
        // A step whose estimates another refit reports (the fixture's, before the refit with
        // its own mode): no ESS retry, but its runs' disagreement is still retried.
        let short = w("mu_ln_m_fix", 196.0);
        assert_eq!(
            retry_rule(
                w("mu_g_z_pa", 1.02),
                w("mu_ln_m_fix", 1.01),
                short.clone(),
                None
            ),
            None
        );
        let (_, more_runs, _) =
            retry_rule(w("mu_g_z_pa", 1.12), w("mu_ln_m_fix", 1.01), short, None).unwrap();
        assert!(more_runs);
    }
}

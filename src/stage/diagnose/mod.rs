//! `hbmu diagnose WORK_DIR --out DIR`: reads a work directory's posterior tables, locates
//! the misfit ([`crate::diagnose::locate`]), screens the mechanism library against the
//! located signature ([`crate::diagnose::screen`]), refits the screened joint mechanisms with
//! `update joints --enrich` (each refit its own hashed stage under `DIR/refits/<id>`, so a
//! cluster can run them side by side: `--only <id>` runs one and stops), compares them with
//! the work directory's step 2 by log evidence and held-out error
//! ([`crate::diagnose::select`]), and writes `diagnosis.json`, `diagnosis.parquet` and
//! `diagnosis_modes.parquet` (each mode's misfit before and after every refit).
//!
//! The refits run with exactly the options the work directory's step 2 ran with (read from
//! its manifest), so the Bayes factors compare like with like.

pub mod inputs;
pub mod regions;

use crate::diagnose::library::{is_board_mechanism, Mechanism};
use crate::diagnose::locate::{self, LocateOptions, Located, ModeCheck};
use crate::diagnose::misfit::{MisfitParts, RefitShares};
use crate::diagnose::point_search;
use crate::diagnose::screen::{self, Candidate};
use crate::diagnose::select::{
    self, Compared, DeviatingJoint, Estimate, NewModeNote, Refit, SelectOptions, SetupError,
    Verdict,
};
use crate::findings::{Finding, Findings, Severity};
use crate::io::manifest::StageSpec;
use crate::io::tables::{self, c, Col, Cols, TableSpec};
use crate::stage::update::{ShapeWeighting, UpdateOptions};
use crate::stage::{exit, StageOutcome, StageResult};
use anyhow::{anyhow, Context};

/// Largest R-hat across a refit's runs for its evidence to count (the updating's own
/// convergence level).
use crate::stage::update::MAX_R_HAT;
use arrow::array::{ArrayRef, BooleanArray, Float64Array, Int32Array, StringArray};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::Arc;

pub const MANIFEST: &str = "diagnose.manifest.json";
pub const JSON: &str = "diagnosis.json";

pub const DIAGNOSIS: TableSpec = TableSpec {
    name: "diagnosis",
    doc: "The diagnosis's candidates, one row per screened mechanism (and joint), strongest first: the screening score, the refit's log Bayes factor over the work directory's step 2 with its standard error, whether it is favoured, the held-out bolted mean absolute frequency error before and after, the parameter estimate (population median and 90 % interval) and the sentence. diagnosis.json holds the verdict, the located evidence and the same findings.",
    open: false,
    columns: &[
        c("rank", Col::Int32, false, "", "Order in the diagnosis (1 = strongest)."),
        c("mechanism", Col::Utf8, false, "", "Mechanism id (joint_rotation, joint_stiffness_per_joint, joint_mass, fixture_compliance, temperature_stiffness, added_mass, local_stiffness_loss, prestress)."),
        c("joint", Col::Int32, true, "", "Joint (1-based, hole order of the board file) of a per-joint candidate."),
        c("covariate", Col::Utf8, true, "", "Sheet column the candidate follows, if any."),
        c("screen_reason", Col::Utf8, false, "", "Why the screening kept the candidate."),
        c("refitted", Col::Bool, false, "", "A refit with the mechanism was run."),
        c("log_bayes_factor", Col::Float64, true, "", "ln p(data | candidate) − ln p(data | baseline), from the SMC runs; null without a refit or when it failed."),
        c("log_bayes_factor_se", Col::Float64, true, "", "Standard error of the log Bayes factor (independent runs)."),
        c("favoured", Col::Bool, false, "", "Passes the decision rule (see diagnosis.json: options)."),
        c("held_out_bolted_error_before_percent", Col::Float64, true, "%", "Mean |f̂ − f|/f̂ of the bolted modes not used for updating, baseline."),
        c("held_out_bolted_error_after_percent", Col::Float64, true, "%", "The same with the candidate."),
        c("parameter", Col::Utf8, true, "", "The candidate's parameter (unit in its name)."),
        c("estimate_median", Col::Float64, true, "", "Population median of the parameter (its unit)."),
        c("estimate_q05", Col::Float64, true, "", "5 % quantile."),
        c("estimate_q95", Col::Float64, true, "", "95 % quantile."),
        c("failed", Col::Utf8, true, "", "Why the refit gave no posterior."),
        c("sentence", Col::Utf8, false, "", "The finding in words."),
    ],
};

pub const MODES: TableSpec = TableSpec {
    name: "diagnosis_modes",
    doc: "Each mode's misfit before and after the candidates: per model (`baseline` = the work directory's update steps, or a refitted candidate's id) and (setup, label), the mean relative residual r = (f_measured − f̄_model)/f̄_model over the measurements (the mean of the board means with at least `min_boards_for_board_test` boards, as locate's mode check) with its standard error. The baseline rows are locate's mode checks; a refit's rows the same computation over refits/<id>/residuals.parquet (its setups only). Failed refits have no rows.",
    open: false,
    columns: &[
        c("model", Col::Utf8, false, "", "`baseline` or the refitted candidate's id (its directory under refits/)."),
        c("setup", Col::Utf8, false, "", "Setup."),
        c("label", Col::Utf8, false, "", "Mode label."),
        c("used_for_updating", Col::Bool, false, "", "The label was used for updating (false: a validation mode)."),
        c("n", Col::Int32, false, "", "Residual rows (measurements) of the mode."),
        c("n_boards", Col::Int32, false, "", "Boards among them."),
        c("mean_rel_residual", Col::Float64, true, "", "Mean relative residual (dimensionless; null when undefined)."),
        c("se_rel_residual", Col::Float64, true, "", "Its standard error (null with one unit)."),
        c("located", Col::Bool, false, "", "The baseline's mode check located this (setup, label) as misfitting."),
    ],
};

/// One favoured finding of `diagnosis.json`.
#[derive(Debug, Clone, serde::Serialize, schemars::JsonSchema)]
pub struct FindingDoc {
    /// Mechanism id.
    pub mechanism: Mechanism,
    /// Where the finding is: the joint and its centre (per-joint mechanisms) or the located
    /// point (`added_mass`); null for mechanisms without a place.
    pub location: Option<Location>,
    /// The sheet column the finding follows, if any.
    pub covariate: Option<String>,
    /// Parameter estimates: population median with its 90 % interval.
    pub estimates: Vec<Estimate>,
    pub log_bayes_factor: Option<f64>,
    pub log_bayes_factor_se: Option<f64>,
    /// Held-out mean absolute frequency error before and after, per setup, percent.
    pub held_out_error: Vec<HeldOut>,
    /// The refit's directory, relative to the diagnosis directory.
    pub refit_dir: String,
    pub sentence: String,
}

#[derive(Debug, Clone, serde::Serialize, schemars::JsonSchema)]
pub struct Location {
    /// 1-based, hole order of the board file; absent for a point on the board.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub joint: Option<usize>,
    pub x_m: f64,
    pub y_m: f64,
}

#[derive(Debug, Clone, serde::Serialize, schemars::JsonSchema)]
pub struct HeldOut {
    pub setup: String,
    pub before_percent: f64,
    pub after_percent: f64,
}

/// One screened candidate of `diagnosis.json`, with its refit when it had one.
#[derive(Debug, Clone, serde::Serialize, schemars::JsonSchema)]
pub struct CandidateDoc {
    pub id: String,
    pub candidate: Candidate,
    pub refit: Option<Compared>,
    pub sentence: String,
}

/// `diagnosis.json`.
#[derive(Debug, Clone, serde::Serialize, schemars::JsonSchema)]
pub struct DiagnosisDoc {
    pub verdict: Verdict,
    /// What locate found (the summary; `checks` has the tests behind it).
    pub located: LocatedSummary,
    /// Favoured mechanisms, strongest first.
    pub findings: Vec<FindingDoc>,
    /// Every screened candidate, refitted ones first in order of their Bayes factor.
    pub candidates: Vec<CandidateDoc>,
    pub remaining_discrepancy: String,
    pub options: DiagnoseOptions,
    pub checks: Located,
    /// Problems met on the way (missing tables, quarantined measurements, the verdict).
    pub stage_findings: Vec<Finding>,
}

/// The located evidence in short.
#[derive(Debug, Clone, serde::Serialize, schemars::JsonSchema)]
pub struct LocatedSummary {
    /// Anything located by the statistical tests (at the tolerance of `options.locate`).
    pub any: bool,
    /// A structured misfit at or above the practical threshold (`options.select`): a located
    /// mode's mean shift or covariate trend that large, an outlier measurement or a recurring
    /// unpaired mode. Only then are candidates refitted and a misfit reported.
    pub above_practical_threshold: bool,
    /// The largest |mean relative residual| of any checked mode (`setup label`) and its
    /// value: how far the model is from these boards at worst.
    pub largest_mode_misfit: Option<(String, f64)>,
    pub setups: Vec<String>,
    pub modes: Vec<crate::diagnose::locate::LocatedMode>,
    pub measurements: Vec<String>,
    /// Outlier measurements whose deviation is one mode's alone (likely identification
    /// slips; not counted as misfit).
    pub identification_outliers: Vec<crate::diagnose::locate::IdentificationOutlier>,
    pub covariates: Vec<crate::diagnose::locate::LocatedCovariate>,
    pub unpaired_clusters: Vec<crate::diagnose::locate::UnpairedCluster>,
    pub never_seen: Vec<crate::diagnose::locate::ModelModePresence>,
    /// Board regions: the point-mass localisation of the free-free misfit
    /// ([`regions::point_mass_region`]); empty when it did not run, `board_regions_note`
    /// says why, and what is not localised yet.
    pub board_regions: Vec<regions::BoardRegion>,
    pub board_regions_note: String,
}

/// Options of `hbmu diagnose`.
#[derive(Debug, Clone, serde::Serialize, schemars::JsonSchema)]
pub struct DiagnoseOptions {
    #[serde(skip)]
    pub work_dir: PathBuf,
    #[serde(skip)]
    pub out: PathBuf,
    #[serde(skip)]
    pub board: Option<PathBuf>,
    #[serde(skip)]
    pub force: bool,
    /// Run only this candidate's refit (its id, e.g. `joint_rotation` or
    /// `joint_stiffness_per_joint_2`) and stop: the cluster fan-out.
    #[serde(skip)]
    pub only: Option<String>,
    pub locate: LocateOptions,
    pub select: SelectOptions,
    /// Refit at most this many screened candidates (0: locate and screen only).
    pub max_refits: usize,
}

use crate::io::read_json;

/// The options the work directory's step 2 ran with (its manifest's config).
fn step2_options(work: &Path) -> anyhow::Result<UpdateOptions> {
    step_options(work, "update_joints", crate::stage::update::MANIFEST_JOINTS)
}

/// The options the work directory's step 1 ran with.
fn step1_options(work: &Path) -> anyhow::Result<UpdateOptions> {
    step_options(work, "update_boards", crate::stage::update::MANIFEST_BOARDS)
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
    // A refit's likelihood must be the baseline's: its shape terms take the weights the
    // baseline estimated, not weights of its own (their evidences would not compare).
    if o.model.shape_weights == ShapeWeighting::Auto {
        o.model.shape_weights =
            ShapeWeighting::from_evidence(&work.join(dir).join("evidence.json"))?;
    }
    Ok(o)
}

/// Mean absolute relative error per setup of the held-out (`used == false`) or updated modes
/// in a residuals table.
fn setup_errors(path: &Path, used: bool) -> anyhow::Result<Vec<SetupError>> {
    let mut acc: BTreeMap<String, (f64, usize)> = BTreeMap::new();
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let (setup, rel, u) = (
            c.str("setup")?,
            c.f64("rel_residual")?,
            c.bool("used_for_updating")?,
        );
        for i in 0..b.num_rows() {
            if u.value(i) == used && rel.value(i).is_finite() {
                let e = acc.entry(setup.value(i).to_string()).or_default();
                e.0 += rel.value(i).abs();
                e.1 += 1;
            }
        }
    }
    Ok(acc
        .into_iter()
        .map(|(setup, (s, n))| SetupError {
            setup,
            mean_abs_error_percent: 100.0 * s / n.max(1) as f64,
            n,
        })
        .collect())
}

fn quantile(sorted: &[f64], q: f64) -> f64 {
    // numpy's default (linear) quantile.
    let h = (sorted.len() - 1) as f64 * q;
    let (lo, hi) = (h.floor() as usize, h.ceil() as usize);
    sorted[lo] + (h - lo as f64) * (sorted[hi] - sorted[lo])
}

/// The log evidence of every run of an update directory (its evidence.json).
fn evidence_runs(dir: &Path) -> anyhow::Result<Vec<f64>> {
    let ev = read_json(&dir.join("evidence.json"))?;
    Ok(ev["log_evidence_runs"]
        .as_array()
        .ok_or_else(|| {
            anyhow!(
                "{}: no log_evidence_runs",
                dir.join("evidence.json").display()
            )
        })?
        .iter()
        .filter_map(|v| v.as_f64())
        .collect())
}

/// The R-hat across runs above which a refit's evidence gives no Bayes factor: 1.1, the
/// classical threshold of Gelman & Rubin's diagnostic (Gelman et al., Bayesian Data Analysis,
/// 3rd ed., §11.5). Up to it the runs' spread of the log evidence is its standard error; above
/// it, runs that sampled different parts of the posterior may each miss mass the others saw.
/// [`MAX_R_HAT`] (1.05) still marks the refit's estimates approximate, and makes
/// [`run_gated`] retry it with more particles and runs.
const MAX_R_HAT_EVIDENCE: f64 = 1.1;

/// The gate on a refit step's worst population-level R-hat (parameter, value) in `dir`: why
/// its evidence gives no Bayes factor (above [`MAX_R_HAT_EVIDENCE`]), or why its estimates
/// are approximate (above [`MAX_R_HAT`]).
fn r_hat_gate(worst: Option<(String, f64)>, dir: &Path) -> (Option<String>, Option<String>) {
    match worst {
        Some((name, r)) if r > MAX_R_HAT_EVIDENCE => (
            Some(format!(
                "sampler not converged: R-hat across runs of {name} {r:.3} > {MAX_R_HAT_EVIDENCE} in {}, so its evidence gives no Bayes factor",
                dir.display()
            )),
            None,
        ),
        Some((name, r)) if r > MAX_R_HAT => (
            None,
            Some(format!(
                "approximate: the runs disagree a little (R-hat of {name} {r:.3} > {MAX_R_HAT})"
            )),
        ),
        _ => (None, None),
    }
}

/// The population-level parameter (no board, no measurement) with the largest R-hat in a
/// summary table, with that R-hat; None without such rows or R-hats (one run).
fn population_r_hat(path: &Path) -> anyhow::Result<Option<(String, f64)>> {
    population_worst(path, "r_hat", |a, b| a > b)
}

/// The population-level parameter with the smallest bulk ESS, with that ESS.
fn population_ess(path: &Path) -> anyhow::Result<Option<(String, f64)>> {
    population_worst(path, "ess_bulk", |a, b| a < b)
}

/// The population-level row of a summary table whose finite `col` is worst by `worse`.
fn population_worst(
    path: &Path,
    col: &str,
    worse: impl Fn(f64, f64) -> bool,
) -> anyhow::Result<Option<(String, f64)>> {
    let mut worst: Option<(String, f64)> = None;
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let (name, board, meas, r) = (
            c.str("parameter")?,
            c.str("board_id")?,
            c.str("measurement_id")?,
            c.f64(col)?,
        );
        for i in 0..b.num_rows() {
            use arrow::array::Array;
            if board.is_valid(i) || meas.is_valid(i) || !r.value(i).is_finite() {
                continue;
            }
            if worst.as_ref().is_none_or(|(_, w)| worse(r.value(i), *w)) {
                worst = Some((name.value(i).to_string(), r.value(i)));
            }
        }
    }
    Ok(worst)
}

/// Every value of a Float64 column of a Parquet table, sorted.
fn sorted_column(path: &Path, col: &str) -> anyhow::Result<Vec<f64>> {
    let mut v = vec![];
    for b in &tables::read_parquet(path)? {
        let a = Cols { batch: b, path }.f64(col)?;
        v.extend((0..b.num_rows()).map(|i| a.value(i)));
    }
    v.sort_by(f64::total_cmp);
    Ok(v)
}

/// A refit directory (or a baseline step) as a [`Refit`]. A board mechanism's refit has
/// its step 1 in `dir/boards` and, where the campaign has a step 2, its step 2 in `dir`:
/// its log evidence per run is then Z₂′ + (Z₁′ − Z₁), `step1_baseline` = the baseline's Z₁
/// per run, so that it compares with the baseline's step 2 (Z₂) as a joint refit does (whose
/// step 1 is the baseline's): every Bayes factor is over the same data, both steps.
fn summarize_refit(
    dir: &Path,
    rel_dir: &str,
    mechanism: Option<Mechanism>,
    joint: Option<usize>,
    step1_baseline: Option<&[f64]>,
    outliers: &[String],
) -> anyhow::Result<Refit> {
    let board_mech = mechanism.is_some_and(is_board_mechanism);
    let dir1 = dir.join("boards");
    let has2 = dir.join("evidence.json").is_file();
    let main = if board_mech && !has2 { &dir1 } else { dir };
    let mut log_evidence_runs = evidence_runs(main)?;
    if board_mech && has2 {
        let z1 = evidence_runs(&dir1)?;
        let base = step1_baseline.unwrap_or(&[]);
        if z1.is_empty() || base.is_empty() {
            anyhow::bail!(
                "{}: no step-1 evidence to combine with step 2",
                dir1.display()
            );
        }
        for (r, z) in log_evidence_runs.iter_mut().enumerate() {
            *z += z1[r % z1.len()] - base[r % base.len()];
        }
    }
    let res = main.join("residuals.parquet");
    // A refit whose independent runs disagree on its population-level parameters (the
    // mechanism's, the hyperparameters, the error scales: rank-normalised split R-hat across
    // runs above 1.05) has not sampled its posterior: its evidence gives no Bayes factor.
    // Per-unit parameters are not gated: in step 2 each run carries its own subset of the
    // step-1 draws (the cut posterior), and a measurement's contact stiffness, tied to its
    // board's draw, differs between runs by that subset's Monte Carlo error alone (R-hat up
    // to 1.1 with 20 draws per run on a board the bolted data constrain strongly); that
    // error is in the runs' evidences, and so in the Bayes factor's standard error.
    //
    // Between MAX_R_HAT and MAX_R_HAT_EVIDENCE the runs disagree a little: the Bayes factor
    // stands (each run is an independent estimate of the log evidence, and their spread is
    // its standard error, which the decision rule weighs), while the estimates' intervals are
    // said to be approximate.
    let mut failed = None;
    let mut convergence_note = None;
    if mechanism.is_some() {
        let mut reps = vec![main.to_path_buf()];
        if board_mech && has2 {
            reps.push(dir1.clone());
        }
        for d in reps {
            let (f, n) = r_hat_gate(population_r_hat(&d.join("summary.parquet"))?, &d);
            failed = failed.or(f);
            convergence_note = convergence_note.or(n);
        }
    }
    let mut estimates = vec![];
    let ev1 = if mechanism.is_some_and(is_board_mechanism) {
        read_json(&dir.join("boards/evidence.json"))?
    } else {
        serde_json::Value::Null
    };
    let point_mass = &ev1["enrichment"]["effect"];
    if point_mass["kind"].as_str() == Some("point_mass") {
        // Its step-1 refit (`boards/`): the population median of the added mass (the
        // column holds reference · e^μ, kg), and the mass's spread over the boards.
        let param = point_mass["parameter"].as_str().unwrap_or_default();
        let v = sorted_column(
            &dir.join("boards/population.parquet"),
            &format!("mu_{param}"),
        )?;
        if !v.is_empty() {
            estimates.push(Estimate {
                parameter: param.to_string(),
                scope: format!(
                    "population median, at ({:.1}, {:.1}) mm",
                    1e3 * point_mass["x_m"].as_f64().unwrap_or(f64::NAN),
                    1e3 * point_mass["y_m"].as_f64().unwrap_or(f64::NAN)
                ),
                median: quantile(&v, 0.5),
                q05: quantile(&v, 0.05),
                q95: quantile(&v, 0.95),
            });
        }
    } else if mechanism.is_some_and(is_board_mechanism) {
        // Its step-1 refit (`boards/`): the coefficient's population mean, as drawn.
        let coef = ev1["enrichment"]["coefficient"]
            .as_str()
            .unwrap_or_default();
        let v = sorted_column(
            &dir.join("boards/population.parquet"),
            &format!("mu_{coef}"),
        )?;
        if !v.is_empty() {
            estimates.push(Estimate {
                parameter: coef.to_string(),
                scope: format!(
                    "population mean, per unit of {} around {:.2}",
                    ev1["enrichment"]["covariate"]
                        .as_str()
                        .unwrap_or("the covariate"),
                    ev1["enrichment"]["covariate_reference"]
                        .as_f64()
                        .unwrap_or(f64::NAN)
                ),
                median: quantile(&v, 0.5),
                q05: quantile(&v, 0.05),
                q95: quantile(&v, 0.95),
            });
        }
    } else if mechanism.is_some() {
        // Extra coordinates (beyond ln k_con): population medians report_ref · e^μ.
        let ev = read_json(&dir.join("evidence.json"))?;
        let coords = ev["enrichment"]["coordinates"]
            .as_array()
            .cloned()
            .unwrap_or_default();
        let pop = dir.join("population.parquet");
        let batches = tables::read_parquet(&pop)?;
        // Every joint's contrast (no joint named): no population median to report (their
        // common part is the prior's); the per-measurement ratios are `every_joint_estimates`.
        let every_joint = crate::diagnose::library::is_every_joint(mechanism, joint);
        let skip = if every_joint { coords.len() } else { 1 };
        for cdef in coords.iter().skip(skip) {
            let name = cdef["name"].as_str().unwrap_or_default();
            let param = cdef["report_param"].as_str().unwrap_or_default();
            let col = format!("mu_{name}");
            let mut v = vec![];
            for b in &batches {
                let c = Cols {
                    batch: b,
                    path: &pop,
                };
                let a = c.f64(&col)?;
                // The column holds ln(report_ref) + μ.
                v.extend((0..b.num_rows()).map(|i| a.value(i).exp()));
            }
            v.sort_by(f64::total_cmp);
            if !v.is_empty() {
                estimates.push(Estimate {
                    parameter: param.to_string(),
                    scope: "population median".into(),
                    median: quantile(&v, 0.5),
                    q05: quantile(&v, 0.05),
                    q95: quantile(&v, 0.95),
                });
            }
        }
        // A mechanism that acts on some measurements only (one joint loose in some
        // assemblies): its estimate in each outlier measurement the locate step found
        // (joints.parquet holds report_ref · e^x per measurement). Not every measurement
        // whose interval excludes the reference: the joints of one assembly differ by a few
        // per cent anyway, and the bolted data resolve that.
        if mechanism == Some(Mechanism::JointStiffnessPerJoint) && !every_joint {
            let jp = dir.join("joints.parquet");
            for cdef in coords.iter().skip(1) {
                let param = cdef["report_param"].as_str().unwrap_or_default();
                let mut by: BTreeMap<String, Vec<f64>> = BTreeMap::new();
                for b in &tables::read_parquet(&jp)? {
                    let c = Cols {
                        batch: b,
                        path: &jp,
                    };
                    let (m, a) = (c.str("measurement_id")?, c.f64(param)?);
                    for i in 0..b.num_rows() {
                        by.entry(m.value(i).to_string())
                            .or_default()
                            .push(a.value(i));
                    }
                }
                for (m, mut v) in by {
                    if !outliers.contains(&m) {
                        continue;
                    }
                    v.sort_by(f64::total_cmp);
                    let (q05, q95) = (quantile(&v, 0.05), quantile(&v, 0.95));
                    {
                        estimates.push(Estimate {
                            parameter: param.to_string(),
                            scope: format!("measurement {m}"),
                            median: quantile(&v, 0.5),
                            q05,
                            q95,
                        });
                    }
                }
            }
        }
    }
    if let Some(note) = &convergence_note {
        for e in estimates.iter_mut() {
            e.scope = format!("{}; {note}", e.scope);
        }
    }
    let mut held_out = setup_errors(&res, false)?;
    let mut updated = setup_errors(&res, true)?;
    if board_mech && has2 {
        // The free-free predictions of its step 1 too.
        let res1 = dir1.join("residuals.parquet");
        held_out.extend(setup_errors(&res1, false)?);
        updated.extend(setup_errors(&res1, true)?);
    }
    Ok(Refit {
        mechanism,
        joint,
        dir: rel_dir.to_string(),
        log_evidence_runs,
        held_out,
        updated,
        estimates,
        failed,
        log_location_occam: None,
        point_xy_m: None,
        location_probes: vec![],
        location_note: None,
        remaining_share: None,
        explained_rel: None,
        deviating_joints: vec![],
        new_modes: vec![],
    })
}

/// A joint deviates in a measurement when the 90 % interval of its stiffness over the mean
/// of the others' lies entirely below `DEVIATING_RATIO` or entirely above its inverse. The joints of one correctly torqued
/// assembly differ by a few per cent to ~10 % (contact-stiffness scatter); a loose bolt or a
/// missing washer changes one by a factor of 1.5 or more. 0.8 sits between: a mere scatter
/// never reaches it, and a bolt at two thirds of the others' still does.
const DEVIATING_RATIO: f64 = 0.8;

/// The every-joint refit of `joint_stiffness_per_joint` (refits/<id>/joints.parquet: per
/// measurement each joint's k_ratio_<j>): per measurement, the joint with the largest
/// |ln median ratio|, when it deviates (`DEVIATING_RATIO`) or the measurement is one of
/// locate's outliers; as estimates (parameter k_ratio_<j>, scope "measurement <id>") and
/// as deviating joints (only those that deviate).
fn every_joint_estimates(
    dir: &Path,
    board: &crate::fem::Board,
    outliers: &[String],
) -> anyhow::Result<(Vec<Estimate>, Vec<DeviatingJoint>)> {
    let jp = dir.join("joints.parquet");
    let n = board.holes.len();
    // measurement → per joint, the ratio draws.
    let mut by: BTreeMap<String, Vec<Vec<f64>>> = BTreeMap::new();
    for b in &tables::read_parquet(&jp)? {
        let c = Cols {
            batch: b,
            path: &jp,
        };
        let m = c.str("measurement_id")?;
        let cols = (1..=n)
            .map(|j| c.f64(&format!("k_ratio_{j}")))
            .collect::<std::io::Result<Vec<_>>>()?;
        for i in 0..b.num_rows() {
            let e = by
                .entry(m.value(i).to_string())
                .or_insert_with(|| vec![vec![]; n]);
            for (j, a) in cols.iter().enumerate() {
                e[j].push(a.value(i));
            }
        }
    }
    let (mut est, mut dev) = (vec![], vec![]);
    for (m, mut per) in by {
        let q: Vec<(f64, f64, f64)> = per
            .iter_mut()
            .map(|v| {
                v.sort_by(f64::total_cmp);
                (quantile(v, 0.5), quantile(v, 0.05), quantile(v, 0.95))
            })
            .collect();
        let Some(j) = (0..n).max_by(|&a, &b| q[a].0.ln().abs().total_cmp(&q[b].0.ln().abs()))
        else {
            continue;
        };
        let (med, lo, hi) = q[j];
        let deviates = hi < DEVIATING_RATIO || lo > 1.0 / DEVIATING_RATIO;
        if !(deviates || outliers.contains(&m)) {
            continue;
        }
        est.push(Estimate {
            parameter: format!("k_ratio_{}", j + 1),
            scope: format!("measurement {m}"),
            median: med,
            q05: lo,
            q95: hi,
        });
        if deviates {
            dev.push(DeviatingJoint {
                measurement_id: m,
                joint: j + 1,
                x_m: board.holes[j].x_m,
                y_m: board.holes[j].y_m,
                ratio_median: med,
                ratio_q05: lo,
                ratio_q95: hi,
            });
        }
    }
    Ok((est, dev))
}

/// The options of one candidate's refit: the step-2 options with the enrichment.
fn refit_options(opts: &DiagnoseOptions, base: &UpdateOptions, cand: &Candidate) -> UpdateOptions {
    let mut o = base.clone();
    o.ingest_dir = opts.work_dir.join("ingest");
    o.pair_dir = opts.work_dir.join("pair");
    o.extract_dir = Some(opts.work_dir.join("extract"));
    o.board = opts.board.clone();
    o.out = opts.out.join(format!("refits/{}", cand.id()));
    o.force = opts.force;
    o.model.enrich = Some(cand.mechanism);
    o.model.enrich_joint = cand.joint;
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
/// favoured). Inside their verified boxes the surrogates answer and the ROM is rarely called
/// (the blind underfill campaign's joint_mass refit: 0.7 per particle and unit over a whole
/// run); a unit without a surrogate costs 6–75 a stage (2–25 sweeps of three moves). 100
/// lets a few units temper on the ROM through a run; an enrichment whose modes the
/// surrogates cannot follow anywhere (the fixture's own mode swept across the band by its
/// prior on the underfill campaign: every unit refused) spent 450 000 ROM evaluations
/// (75 per particle and unit), ~2.5 min on 2 cores, on each of what would have been hundreds
/// of stages; with a budget of 50 it stopped after the first with its reason (100 allows a
/// second: 150 > 100 after it). Step 1 has none: its
/// free-free ROM is cheap (1.3 M evaluations in 19 s), and a covariate's refit runs it
/// without surrogates by design (a board refit with the temperature coefficient spent 57
/// per particle and unit in its first two stages, 45 s in all).
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
fn run_refit(
    opts: &DiagnoseOptions,
    (base1, base2): (&UpdateOptions, Option<&UpdateOptions>),
    cand: &Candidate,
    decided: &dyn Fn() -> Option<String>,
    verbose: bool,
) -> anyhow::Result<StageOutcome> {
    if is_board_mechanism(cand.mechanism) {
        // Step 1 with the mechanism (refits/<id>/boards), then, where the campaign has a
        // step 2, step 2 on top of it carrying the boards' coefficients (refits/<id>).
        let mut o = board_refit_options(opts, base1, cand, cand.point_xy_m);
        let boards = o.out.join("boards");
        o.out = boards.clone();
        let Some(base) = base2 else {
            return run_gated(o, |o| crate::stage::update::run_boards(o, verbose), decided);
        };
        run_gated(o, |o| crate::stage::update::run_boards(o, verbose), &|| {
            None
        })?;
        let mut o2 = joint_refit_options(opts, base, cand);
        o2.model.enrich_joint = None;
        run_gated(
            o2,
            |o| crate::stage::update::run_joints(o, &boards, verbose),
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
            |o| crate::stage::update::run_joints(o, &opts.work_dir.join("update_boards"), verbose),
            decided,
        )
    }
}

/// The bulk ESS per run below which a refit's population-level parameter is resampled
/// ([`run_gated`]): Vehtari et al. (2021) ask for 100 per chain before R-hat and the
/// posterior quantiles are to be trusted. Measured on the paper campaign's rotation refit
/// at 2 runs × 200 (R-hat 1.03 passed): the population median of k_rot had a bulk ESS of 97
/// and a 90 % interval about half as wide as at 4 × 400 (1.514–1.551 against 1.497–1.564,
/// truth 1.5).
const MIN_ESS_PER_RUN: f64 = 100.0;

/// Run one update step of a refit; when its independent runs disagree on a population-level
/// parameter (R-hat above [`MAX_R_HAT`], the gate [`summarize_refit`] applies) or one has
/// fewer than [`MIN_ESS_PER_RUN`] effective draws a run, run it once more with twice the
/// particles and twice the runs (at least 4). A refit is a few samplers'
/// worth of work, and without this a decisive candidate whose nuisance scale mixed slowly (a
/// mode's shape error with a bulk ESS of 25) gave no Bayes factor at all. More runs, not only
/// more particles: two runs that settle on different trade-offs between the modes' error
/// scales (the blind rotation campaign's refit: ε of one mode 3e-5 in one run, 8e-5 in the
/// other) stay apart however many particles each has, and R-hat from two runs is itself
/// too noisy to tell; four runs of 400 agreed there (R-hat 1.02). The retry replaces the
/// first attempt's outputs; if it still disagrees, the gate reports it.
///
/// The retry is for the Bayes factor. Before it, `decided` says whether the first attempt
/// already misses a bar of the decision rule that the evidence does not set
/// ([`select::cannot_be_favoured`]); then the refit cannot be favoured whatever its Bayes
/// factor, and the retry (four times the first attempt's work) is not run.
fn run_gated(
    mut o: UpdateOptions,
    step: impl Fn(&UpdateOptions) -> anyhow::Result<StageOutcome>,
    decided: &dyn Fn() -> Option<String>,
) -> anyhow::Result<StageOutcome> {
    let r = step(&o)?;
    let summary = o.out.join("summary.parquet");
    let min_ess = MIN_ESS_PER_RUN * o.sampler.runs as f64;
    let why = if let Some((name, rh)) = population_r_hat(&summary)?.filter(|(_, r)| *r > MAX_R_HAT)
    {
        format!("R-hat across runs of {name} {rh:.3} > {MAX_R_HAT}")
    } else if let Some((name, ess)) = population_ess(&summary)?.filter(|(_, e)| *e < min_ess) {
        format!("bulk ESS of {name} {ess:.0} < {min_ess:.0} ({MIN_ESS_PER_RUN} a run)")
    } else {
        return Ok(r);
    };
    if let Some(not) = decided() {
        eprintln!(
            "diagnose: {}: {why}; not rerun: it cannot be favoured whatever its Bayes factor ({not})",
            o.out.display()
        );
        return Ok(r);
    }
    o.sampler.smc.n_particles *= 2;
    o.sampler.runs = (2 * o.sampler.runs).max(4);
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
/// evidence (a fixture's own resonance pins its frequency). It is not run for a refit that
/// cannot be favoured whatever its Bayes factor (`not_favourable` is then why): better estimates
/// of a mechanism the diagnosis will not claim are not worth a second sampler's run; the
/// modes are still named.
#[allow(clippy::too_many_arguments)]
fn new_modes_refit(
    opts: &DiagnoseOptions,
    base2: Option<&UpdateOptions>,
    cand: &Candidate,
    out: &Path,
    rel: &str,
    r: &mut Refit,
    not_favourable: Option<String>,
    verbose: bool,
) -> anyhow::Result<()> {
    let ev = read_json(&out.join("evidence.json"))?;
    let found: Vec<&serde_json::Value> = ev["new_modes"]
        .as_array()
        .map(|a| a.iter().collect())
        .unwrap_or_default();
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
            |o| crate::stage::update::run_joints(o, &opts.work_dir.join("update_boards"), verbose),
            &|| None,
        )
        .and_then(|_| summarize_refit(&o.out, &nm_rel, Some(cand.mechanism), cand.joint, None, &[]))
    });
    let (dir, why) = match step {
        Ok(nm) if nm.failed.is_none() && !nm.estimates.is_empty() => {
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
/// from the localisation's grid point, steps halving from 1 mm to 0.25 mm. Returns the candidate at the
/// refined point, with the location's Laplace posterior in place of the map's Occam factor
/// and ln(mass) spread, and every probe. Any other candidate, or a search that could not
/// run (a probe off the board, a failed refit), is returned as it was; that, and a last
/// stencil without a maximum, is the returned note (in the refit's `location_note` and a
/// `diagnose.location_search` warning among the stage's findings).
fn refine_point(
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
    // From half the map's grid step (its point is within one of the map's optimum) to an
    // eighth; each probe with half the refit's particles (the log evidence between probes
    // differs by tens to hundreds, its error across runs is a few).
    let plan = point_search::SearchPlan {
        first_step_m: 0.5 * regions::grid_step_m(board),
        last_step_m: 0.125 * regions::grid_step_m(board),
        max_probes: 24,
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
        let q = point_search::Probe {
            x_m: p[0],
            y_m: p[1],
            log_evidence: z.iter().sum::<f64>() / z.len() as f64,
            ln_mass_kg: quantile(&m, 0.5).ln(),
        };
        eprintln!(
            "diagnose: {}: point ({:.3}, {:.3}) mm: log evidence {:.2}, mass {:.4} g",
            cand.id(),
            p[0] * 1e3,
            p[1] * 1e3,
            q.log_evidence,
            q.ln_mass_kg.exp() * 1e3
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
    let mut c = cand.clone();
    c.point_xy_m = Some(end);
    let mut note = None;
    if let Some(post) = last.laplace(board.length_x_m * board.width_y_m) {
        c.point_located = Some(screen::PointLocated {
            log_occam: post.log_occam,
            location_ln_mass_sd: post.ln_mass_sd,
        });
        c.reason = format!(
            "{}; the point refined by the refits' evidence to ({:.2}, {:.2}) mm (sd {:.2}, {:.2} mm)",
            c.reason,
            end[0] * 1e3,
            end[1] * 1e3,
            post.sd_m[0] * 1e3,
            post.sd_m[1] * 1e3
        );
    } else {
        note = Some(format!(
            "the refinement's last stencil (step {:.3} mm) has no interior maximum of the log evidence: the point moved to the best probe ({:.2}, {:.2}) mm, the location's Occam factor and the mass's spread are the localisation map's",
            last.h_m * 1e3,
            end[0] * 1e3,
            end[1] * 1e3
        ));
        eprintln!("diagnose: {}: {}", cand.id(), note.as_deref().unwrap_or(""));
    }
    (c, probes, note)
}

/// What the decision rule compares a refit with: the located misfit, the locate step's
/// input, the baseline's summary and step-1 log evidence per run.
struct Against<'a> {
    located: &'a Located,
    input: &'a locate::LocateInput,
    baseline: &'a Refit,
    z1: &'a [f64],
}

/// Why the refit of `cand` as it stands in its directory cannot be favoured whatever its
/// Bayes factor ([`select::cannot_be_favoured`]); None where it could be, or where its
/// outputs cannot be read (then the evidence is left to decide).
fn cannot_be_favoured(opts: &DiagnoseOptions, cand: &Candidate, a: &Against) -> Option<String> {
    let rel = format!("refits/{}", cand.id());
    let out = opts.out.join(&rel);
    let outliers = &a.located.measurements_after_covariates;
    let mut r = summarize_refit(
        &out,
        &rel,
        Some(cand.mechanism),
        cand.joint,
        Some(a.z1),
        outliers,
    )
    .ok()?;
    let after = refit_residuals(&out).ok()?;
    with_shares(opts, cand, a, &mut r, &after);
    select::cannot_be_favoured(a.baseline, &r, &opts.select)
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
    let shares = RefitShares::new(a.located, a.input, after, &opts.locate);
    r.remaining_share = shares.own(cand);
    r.explained_rel = shares.explained(cand);
}

/// Run (or find up to date) one candidate's refit.
fn refit(
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
    let r = run_refit(opts, bases, cand, &decided, verbose).and_then(|_| {
        let mut r = summarize_refit(
            &out,
            &rel,
            Some(cand.mechanism),
            cand.joint,
            Some(z1),
            outliers,
        )?;
        if crate::diagnose::library::is_every_joint(Some(cand.mechanism), cand.joint) {
            let (est, dev) = every_joint_estimates(&out, board, outliers)?;
            r.estimates.extend(est);
            r.deviating_joints = dev;
        }
        if !is_board_mechanism(cand.mechanism) {
            // The refit as summarized here, not read again from its directory.
            let not_favourable = refit_residuals(&out).ok().and_then(|after| {
                let mut judged = r.clone();
                with_shares(opts, cand, against, &mut judged, &after);
                select::cannot_be_favoured(against.baseline, &judged, &opts.select)
            });
            new_modes_refit(
                opts,
                bases.1,
                cand,
                &out,
                &rel,
                &mut r,
                not_favourable,
                verbose,
            )?;
        }
        // The location was chosen from the data: its Occam factor joins the evidence, and
        // its uncertainty the mass's interval (the refit's is conditional on the point).
        if let Some(pl) = cand.point_located {
            r.log_evidence_runs
                .iter_mut()
                .for_each(|z| *z += pl.log_occam);
            r.log_location_occam = Some(pl.log_occam);
            r.point_xy_m = cand.point_xy_m;
            r.location_probes = probes.clone();
            r.location_note = location_note.clone();
            for e in r.estimates.iter_mut() {
                let z = 1.645 * pl.location_ln_mass_sd;
                let lo = (e.median / e.q05).ln().hypot(z);
                let hi = (e.q95 / e.median).ln().hypot(z);
                e.q05 = e.median * (-lo).exp();
                e.q95 = e.median * hi.exp();
                e.scope = format!(
                    "{}; 90 % interval widened by the location's uncertainty (sd of ln mass {:.3})",
                    e.scope, pl.location_ln_mass_sd
                );
            }
        }
        Ok(r)
    });
    match r {
        Ok(r) => r,
        Err(e) => Refit {
            mechanism: Some(cand.mechanism),
            joint: cand.joint,
            dir: rel,
            log_evidence_runs: vec![],
            held_out: vec![],
            updated: vec![],
            estimates: vec![],
            failed: Some(format!("{e:#}").replace('\n', " ")),
            log_location_occam: None,
            point_xy_m: None,
            location_probes: vec![],
            location_note,
            remaining_share: None,
            explained_rel: None,
            deviating_joints: vec![],
            new_modes: vec![],
        },
    }
}

/// The diagnosis stage.
pub fn run(opts: &DiagnoseOptions, verbose: bool) -> anyhow::Result<StageOutcome> {
    let w = &opts.work_dir;
    let mut inputs = vec![
        w.join("ingest/measurements.parquet"),
        w.join("extract/modes.parquet"),
        w.join("pair/pairs.parquet"),
        w.join("update_boards/residuals.parquet"),
        w.join("update_boards/population.parquet"),
        w.join("update_boards/boards.parquet"),
    ];
    let step2 = w.join("update_joints/evidence.json").is_file();
    if step2 {
        for f in ["residuals.parquet", "population.parquet", "evidence.json"] {
            inputs.push(w.join("update_joints").join(f));
        }
    }
    if let Some(b) = &opts.board {
        inputs.push(b.clone());
    }
    let base = if step2 { Some(step2_options(w)?) } else { None };
    let mut config = serde_json::to_value(opts)?;
    config["step2_options"] = serde_json::to_value(&base)?;
    let base1 = step1_options(w)?;
    config["step1_options"] = serde_json::to_value(&base1)?;
    let spec = StageSpec {
        stage: "diagnose".into(),
        inputs,
        input_base: w.clone(),
        config,
        seed: base.as_ref().map(|b| b.sampler.seed),
        manifest_path: opts.out.join(MANIFEST),
    };
    // The cluster fan-out: one refit, no diagnosis.
    if let Some(only) = &opts.only {
        let (input, _) = inputs::read_inputs(w)?;
        let located = locate::locate(&input, &opts.locate);
        let (board, _) = crate::stage::update::load_board(opts.board.as_deref())?;
        let (_, cands) = screen_candidates(w, &board, &base1, &input, &located, &opts.locate);
        let cand = cands.iter().find(|c| c.id() == *only).ok_or_else(|| {
            anyhow!(
                "--only {only}: not a screened candidate of this work directory (screened: {})",
                cands.iter().map(|c| c.id()).collect::<Vec<_>>().join(", ")
            )
        })?;
        let (cand, _, _) = refine_point(opts, &board, &base1, cand, verbose);
        let (baseline1, baseline) = baselines(w, step2)?;
        let against = Against {
            located: &located,
            input: &input,
            baseline: baseline.as_ref().unwrap_or(&baseline1),
            z1: &baseline1.log_evidence_runs,
        };
        let decided = || cannot_be_favoured(opts, &cand, &against);
        return run_refit(opts, (&base1, base.as_ref()), &cand, &decided, verbose);
    }
    crate::stage::run(spec, opts.force, |_prep| {
        let mut findings = Findings::default();
        let (input, in_findings) = inputs::read_inputs(w)?;
        findings.0.extend(in_findings.0);
        let located = locate::locate(&input, &opts.locate);
        let (board, _) = crate::stage::update::load_board(opts.board.as_deref())?;
        let (regions, candidates) =
            screen_candidates(w, &board, &base1, &input, &located, &opts.locate);
        let mut refits: Vec<Refit> = vec![];
        let (baseline1, baseline) = baselines(w, step2)?;
        let mut parts = MisfitParts::new(&located);
        let above = above_practical_threshold(&located, opts.select.practical_threshold_rel);
        // Below the practical threshold nothing is refitted: no finding could be claimed.
        if above {
            // Joint mechanisms need step 2; board mechanisms only step 1. The refits stop
            // once every part of the located misfit (the mean shifts, each covariate trend)
            // has a favoured refit that leaves at most STOP_REMAINING_SHARE of it: the rest
            // of the candidates were screened for a misfit that is then explained, and each
            // would cost a sampler's run (the per-joint refits of a campaign whose joints
            // fit are the slowest); they are reported as not refitted.
            let base_ref = baseline.as_ref().unwrap_or(&baseline1);
            let against = Against {
                located: &located,
                input: &input,
                baseline: base_ref,
                z1: &baseline1.log_evidence_runs,
            };
            for cand in candidates
                .iter()
                .filter(|c| c.refittable() && (step2 || is_board_mechanism(c.mechanism)))
                .take(opts.max_refits)
            {
                let t0 = std::time::Instant::now();
                let mut r = refit(
                    opts,
                    &board,
                    (&base1, base.as_ref()),
                    cand,
                    &against,
                    verbose,
                );
                let shares = if r.failed.is_none() {
                    let after = refit_residuals(&opts.out.join(&r.dir))?;
                    let shares = RefitShares::new(&located, &input, &after, &opts.locate);
                    r.remaining_share = shares.own(cand);
                    r.explained_rel = shares.explained(cand);
                    Some(shares)
                } else {
                    None
                };
                eprintln!(
                    "diagnose: refit {} in {:.1} s{}",
                    cand.id(),
                    t0.elapsed().as_secs_f64(),
                    r.failed
                        .as_ref()
                        .map(|e| format!(": failed: {e}"))
                        .unwrap_or_default()
                );
                if let Some(shares) = shares.filter(|_| {
                    select::compare(base_ref, std::slice::from_ref(&r), &opts.select)
                        .first()
                        .is_some_and(|c| c.favoured)
                }) {
                    parts.record_favoured(&shares);
                }
                refits.push(r);
                if parts.all_explained(STOP_REMAINING_SHARE) {
                    break;
                }
            }
        }
        // Against the baseline over the same data: both steps where the campaign has a
        // step 2 (summarize_refit), else step 1 (only board mechanisms are refitted then).
        let compared = select::compare(
            baseline.as_ref().unwrap_or(&baseline1),
            &refits,
            &opts.select,
        );
        let mut verdict = select::verdict(above, &compared);
        let region_limit_m = board.length_x_m.min(board.width_y_m) / 4.0;
        let boards_off = whole_board_outliers(&located, &input.measurements);
        if verdict == Verdict::UnexplainedMisfit
            && model_form_pattern(&located, &regions.0, region_limit_m, boards_off.is_some())
        {
            verdict = Verdict::ModelForm;
        }
        write_outputs(
            opts,
            (&located, above, &boards_off.unwrap_or_default()),
            regions,
            &candidates,
            &compared,
            verdict,
            parts.unexplained(STOP_REMAINING_SHARE),
            findings,
            verbose,
        )
    })
}

/// The baselines' summaries: step 1's, and where the campaign has a step 2, step 2's with
/// step 1's free-free errors (a board mechanism changes both).
fn baselines(w: &Path, step2: bool) -> anyhow::Result<(Refit, Option<Refit>)> {
    let baseline1 = summarize_refit(
        &w.join("update_boards"),
        "../update_boards",
        None,
        None,
        None,
        &[],
    )?;
    let baseline = if step2 {
        let mut b = summarize_refit(
            &w.join("update_joints"),
            "../update_joints",
            None,
            None,
            None,
            &[],
        )?;
        b.held_out.extend(baseline1.held_out.iter().cloned());
        b.updated.extend(baseline1.updated.iter().cloned());
        Some(b)
    } else {
        None
    };
    Ok((baseline1, baseline))
}

/// Whether the located misfit holds a structured part at or above the practical threshold
/// (relative frequency): a located mode's mean shift or a located covariate trend that large
/// ([`crate::diagnose::misfit::largest_structured`]), an outlier measurement (several modes
/// off together) or a recurring unpaired mode.
fn above_practical_threshold(located: &Located, threshold: f64) -> bool {
    located.any
        && (crate::diagnose::misfit::largest_structured(located)
            .is_some_and(|(_, v)| v >= threshold)
            || !located.measurements.is_empty()
            || !located.unpaired_clusters.is_empty())
}

/// Whether an unexplained misfit has the pattern of the model's form rather than of a
/// concealed effect: it is in the free-free modes (the board itself, whatever its mounting),
/// the localisation places it nowhere on the board (no located region whose 90 % radius is
/// within `region_limit_m`: a region spanning the board is no place), and nothing singles out
/// a measurement, a covariate or an unpaired mode. Boards that differ from one another (the
/// `board_id` covariate) do not count against it: the discrepancy's per-unit part is the
/// model's form erring differently on each board. A concealed effect leaves one of those
/// marks: a joint's only in bolted modes, a mass or a local stiffening a region, a drift a
/// covariate trend, a loose bolt its measurements, a fixture its own mode. Outlier
/// measurements that are every measurement of their boards in a setup
/// (`boards_only_outliers`, [`whole_board_outliers`]) are those boards differing from the
/// others, the same per-unit part. The stage's limit is a quarter of the board's shorter
/// side (12.5 mm on the 80 × 50 mm board).
fn model_form_pattern(
    located: &Located,
    regions: &[regions::BoardRegion],
    region_limit_m: f64,
    boards_only_outliers: bool,
) -> bool {
    located.modes.iter().any(|m| m.setup == "free")
        && !regions
            .iter()
            .any(|r| r.located && r.fit.region_radius_m <= region_limit_m)
        && located
            .covariates
            .iter()
            .all(|c| c.covariate == crate::diagnose::locate::BOARD_COVARIATE)
        && (located.measurements.is_empty() || boards_only_outliers)
        && located.unpaired_clusters.is_empty()
}

/// `Some(boards)` when every outlier measurement is one of all the measurements (at least two)
/// of its board in its setup, and those boards differ from the others (`board_id` located in
/// that setup): the repeat measurements of a board agree with each other, the board itself is
/// off the population, as `(setup, board)` pairs. `Some(empty)` without outliers; `None` when
/// some outlier stands apart from its board's other measurements (a measurement's own
/// problem: a loose bolt, a drift, a slip).
fn whole_board_outliers(
    located: &Located,
    measurements: &[locate::MeasurementInfo],
) -> Option<Vec<(String, String)>> {
    let off: BTreeSet<&str> = located.measurements.iter().map(|m| m.as_str()).collect();
    let mut per_board: BTreeMap<(&str, &str), (usize, usize)> = BTreeMap::new();
    for m in measurements {
        let e = per_board
            .entry((m.setup.as_str(), m.board_id.as_str()))
            .or_default();
        e.0 += 1;
        e.1 += usize::from(off.contains(m.measurement_id.as_str()));
    }
    let board_located = |setup: &str| {
        located
            .covariates
            .iter()
            .any(|c| c.setup == setup && c.covariate == crate::diagnose::locate::BOARD_COVARIATE)
    };
    let mut boards = vec![];
    for ((setup, board), (n, n_off)) in per_board {
        if n_off == 0 {
            continue;
        }
        if n_off < n || n < 2 || !board_located(setup) {
            return None;
        }
        boards.push((setup.to_string(), board.to_string()));
    }
    Some(boards)
}

/// A favoured refit that leaves at most this share of the located misfit explains it, and the
/// remaining candidates are not refitted.
const STOP_REMAINING_SHARE: f64 = 0.2;

/// A refit's residuals: its step 2's and, for a board mechanism, its step 1's (`boards/`).
fn refit_residuals(dir: &Path) -> anyhow::Result<Vec<locate::ResidualObs>> {
    let mut obs = vec![];
    for p in [
        dir.join("residuals.parquet"),
        dir.join("boards/residuals.parquet"),
    ] {
        if p.is_file() {
            obs.extend(inputs::read_residuals(&p)?);
        }
    }
    Ok(obs)
}

/// The board regions and the screened candidates, a located point mass attached (the same
/// for the diagnosis and for one candidate's refit, `--only`).
fn screen_candidates(
    work: &Path,
    board: &crate::fem::Board,
    base1: &UpdateOptions,
    input: &locate::LocateInput,
    located: &Located,
    lopts: &LocateOptions,
) -> ((Vec<regions::BoardRegion>, String), Vec<Candidate>) {
    let regions = board_regions(work, board, (base1, input, located), lopts);
    let mut candidates = screen::screen(located, board);
    for r in &regions.0 {
        match r.mechanism {
            Mechanism::AddedMass => screen::attach_point_mass(
                &mut candidates,
                [r.fit.x_m, r.fit.y_m],
                r.located.then_some(screen::PointLocated {
                    log_occam: r.fit.log_location_occam,
                    location_ln_mass_sd: r.fit.location_ln_amplitude_sd,
                }),
                &r.sentence,
            ),
            // A located loss is the library's `local_stiffness_loss` there; a stiffening has
            // no mechanism in the library and stays a located, unexplained signature.
            Mechanism::LocalStiffnessLoss if r.located && r.fit.amplitude < 0.0 => {
                screen::attach_stiffness_loss(&mut candidates, [r.fit.x_m, r.fit.y_m], &r.sentence)
            }
            _ => {}
        }
    }
    (regions, candidates)
}

/// The board regions of the located free-free misfit and the note on what was (not) done.
fn board_regions(
    work: &Path,
    board: &crate::fem::Board,
    (base1, input, located): (&UpdateOptions, &locate::LocateInput, &Located),
    lopts: &LocateOptions,
) -> (Vec<regions::BoardRegion>, String) {
    if !located.setups.iter().any(|s| s == "free") {
        return (
            vec![],
            "not run: no free-free misfit located (the point-mass and stiffness localisations use the free-free modes)".to_string(),
        );
    }
    let mut freq: BTreeMap<String, (f64, usize)> = BTreeMap::new();
    for r in input.residuals.iter().filter(|r| r.setup == "free") {
        let e = freq.entry(r.label.clone()).or_insert((0.0, 0));
        e.0 += r.model_freq_hz_mean;
        e.1 += 1;
    }
    let model_freq: Vec<(String, f64)> = freq
        .into_iter()
        .map(|(l, (s, n))| (l, s / n as f64))
        .collect();
    let inp = regions::RegionInput {
        work,
        board,
        params: &base1.model.params,
        checks: &located.mode_checks,
        residual_model_freq: &model_freq,
        locate: lopts,
        pairs: &input.pairs,
    };
    let fb = match regions::FreeBasis::new(&inp) {
        Ok(fb) => fb,
        Err(e) => return (vec![], format!("localisation failed: {e:#}")),
    };
    let mut note = vec![];
    let mut out = vec![];
    match regions::point_mass_region(&inp, &fb) {
        Ok(r) => {
            note.push("point-mass localisation of the free-free misfit (exact frequency shifts in a modal basis, the stiffness parameters projected off, the measured shapes choosing over the points the frequencies leave open)".to_string());
            out.push(r);
        }
        Err(e) => note.push(format!("point-mass localisation failed: {e:#}")),
    }
    match regions::stiffness_region(&inp, &fb) {
        Ok(r) => {
            note.push(format!("stiffness localisation (first-order signature of a change of the core's bending stiffness over a {:.0} mm disc, either sign, the board parameters projected off, the measured shapes choosing as for the point mass)", 2e3 * regions::STIFFNESS_RADIUS_M));
            out.push(r);
        }
        Err(e) => note.push(format!("stiffness localisation failed: {e:#}")),
    }
    demote_weaker_regions(&mut out);
    (out, note.join("; "))
}

/// Where several signatures located the same misfit, the weaker one is not located: the
/// same residuals, the same number of fitted quantities (an amplitude and two coordinates),
/// so the larger Δχ² is the likelier mechanism. Where the updating had shape terms, the Δχ²
/// is the frequencies' plus the shapes' at each located point (the sum each point was chosen
/// by, and the refit's likelihood has both): on a board whose few free-free modes leave
/// both signatures explaining 99 % of the frequency misfit, the shapes are what tells a
/// point mass from a soft spot. Without shape terms, the frequencies' explained share.
/// The weaker one's sentence says which one explains more, and by what.
fn demote_weaker_regions(regions: &mut [regions::BoardRegion]) {
    let with_shapes = regions
        .iter()
        .filter(|r| r.located)
        .all(|r| r.combined_delta_chi2.is_some());
    let key = |r: &regions::BoardRegion| {
        if with_shapes {
            r.combined_delta_chi2.unwrap_or(f64::NEG_INFINITY)
        } else {
            r.fit.explained_share
        }
    };
    let best = regions
        .iter()
        .enumerate()
        .filter(|(_, r)| r.located)
        .max_by(|a, b| key(a.1).total_cmp(&key(b.1)))
        .map(|(i, r)| (i, r.mechanism, key(r), r.fit.explained_share));
    let Some((bi, bm, bk, bs)) = best else {
        return;
    };
    for (i, r) in regions.iter_mut().enumerate() {
        if i != bi && r.located {
            r.located = false;
            let by = if with_shapes {
                format!(
                    "frequencies and mode shapes together, Δχ² {:.0} against {:.0}; of the frequencies alone {:.0} % against {:.0} %",
                    bk,
                    key(r),
                    100.0 * bs,
                    100.0 * r.fit.explained_share
                )
            } else {
                format!(
                    "{:.0} % against {:.0} %",
                    100.0 * bs,
                    100.0 * r.fit.explained_share
                )
            };
            r.sentence = format!(
                "{} Not located: the {} signature explains more of the misfit ({by}).",
                r.sentence,
                bm.id(),
            );
        }
    }
}

#[allow(clippy::too_many_arguments)]
fn write_outputs(
    opts: &DiagnoseOptions,
    (located, above, boards_off): (&Located, bool, &[(String, String)]),
    (board_regions, board_regions_note): (Vec<regions::BoardRegion>, String),
    candidates: &[Candidate],
    compared: &[Compared],
    verdict: Verdict,
    unexplained: Option<String>,
    mut findings: Findings,
    verbose: bool,
) -> anyhow::Result<StageResult> {
    // Rows: refitted candidates in the order of `compare`, then the screened ones not refitted.
    struct Row {
        cand: Candidate,
        cmp: Option<Compared>,
    }
    let mut rows: Vec<Row> = vec![];
    for c in compared {
        if let Some(cand) = candidates
            .iter()
            .find(|k| Some(k.mechanism) == c.refit.mechanism && k.joint == c.refit.joint)
        {
            rows.push(Row {
                cand: cand.clone(),
                cmp: Some(c.clone()),
            });
        }
    }
    for k in candidates {
        if !rows.iter().any(|r| r.cand.id() == k.id()) {
            rows.push(Row {
                cand: k.clone(),
                cmp: None,
            });
        }
    }
    let sentence = |r: &Row| match &r.cmp {
        Some(c) => select::sentence(c),
        None => format!(
            "Candidate: {} (screened: {}; not refitted{})",
            r.cand.mechanism.description(),
            r.cand.reason,
            if r.cand.refittable() {
                ""
            } else {
                ": this mechanism has no refit yet"
            }
        ),
    };
    let findings_doc: Vec<FindingDoc> = rows
        .iter()
        .filter_map(|r| {
            let c = r.cmp.as_ref().filter(|c| c.favoured)?;
            Some(FindingDoc {
                mechanism: r.cand.mechanism,
                location: match (
                    r.cand.joint,
                    r.cand.joint_xy_m,
                    c.refit.point_xy_m.or(r.cand.point_xy_m),
                ) {
                    // The every-joint refit: the joint that deviates in the most measurements
                    // (all of them in the estimates and the sentence).
                    (None, None, None) if !c.refit.deviating_joints.is_empty() => {
                        select::main_deviating_joint(&c.refit.deviating_joints).map(|d| Location {
                            joint: Some(d.joint),
                            x_m: d.x_m,
                            y_m: d.y_m,
                        })
                    }
                    (Some(joint), Some([x_m, y_m]), _) => Some(Location {
                        joint: Some(joint),
                        x_m,
                        y_m,
                    }),
                    (None, _, Some([x_m, y_m])) => Some(Location {
                        joint: None,
                        x_m,
                        y_m,
                    }),
                    _ => None,
                },
                covariate: r.cand.covariate.clone(),
                estimates: c.refit.estimates.clone(),
                log_bayes_factor: c.log_bayes_factor,
                log_bayes_factor_se: c.log_bayes_factor_se,
                held_out_error: c
                    .held_out_before_after
                    .iter()
                    .map(|(setup, b, a)| HeldOut {
                        setup: setup.clone(),
                        before_percent: *b,
                        after_percent: *a,
                    })
                    .collect(),
                refit_dir: c.refit.dir.clone(),
                sentence: select::sentence(c),
            })
        })
        .collect();
    let threshold = opts.select.practical_threshold_rel;
    let largest = crate::diagnose::misfit::largest_mode_misfit(located);
    let remaining = match verdict {
        Verdict::NoMissingPhysics => match &largest {
            Some((at, v)) => format!(
                "none: the model differs from these boards by at most {:.3} % ({at}){}; below the {:.2} % practical threshold, and included in the predicted intervals as the model-form discrepancy",
                100.0 * v,
                if located.any {
                    " (statistically located, practically small)"
                } else {
                    ""
                },
                100.0 * threshold
            ),
            None => "none: no setup, mode, measurement or covariate misfits beyond the tolerance".to_string(),
        },
        Verdict::MechanismFound => match &unexplained {
            Some(p) => format!("{p}: no favoured mechanism explains this part of the located misfit (none leaves at most {:.0} % of it); the favoured refits' residuals are in refits/<id>/residuals.parquet, the located evidence below is the baseline's", 100.0 * STOP_REMAINING_SHARE),
            None => "see the best candidate's refit residuals (refits/<id>/residuals.parquet); the located evidence below is the baseline's".to_string(),
        },
        Verdict::ModelForm => {
            let (at, v) = crate::diagnose::misfit::largest_structured(located)
                .unwrap_or_else(|| ("?".into(), f64::NAN));
            let boards = if boards_off.is_empty() {
                "with no covariate trend, outlier measurement or unpaired mode".to_string()
            } else {
                format!(
                    "with no covariate trend or unpaired mode; the outlier measurements are every measurement of {} (their repeat measurements agree, the boards themselves differ from the others beyond the model's parameters: the per-board part of the same form)",
                    boards_off
                        .iter()
                        .map(|(s, b)| format!("{b} ({s})"))
                        .collect::<Vec<_>>()
                        .join(", ")
                )
            };
            format!(
                "model form: the model differs from every board alike by up to {:.3} % ({at}), above the {:.2} % practical threshold, in the free-free modes (the board itself, whatever its mounting), placed nowhere on the board, and {boards}: the form of the model (a thin plate without transverse shear and rotary inertia, copper homogenised into the laminate), not a concealed effect. It is in the predicted intervals as the model-form discrepancy; a richer model would narrow them. Located modes: {:?}",
                100.0 * v,
                100.0 * threshold,
                located.modes.iter().map(|m| format!("{}/{}", m.setup, m.label)).collect::<Vec<_>>(),
            )
        }
        Verdict::UnexplainedMisfit => format!(
            "located but not explained by any refitted mechanism: setups {:?}, modes {:?}, measurements {:?}, covariates {:?}{}",
            located.setups,
            located.modes.iter().map(|m| format!("{}/{}", m.setup, m.label)).collect::<Vec<_>>(),
            located.measurements,
            located.covariates.iter().map(|c| format!("{}/{}", c.setup, c.covariate)).collect::<Vec<_>>(),
            board_regions
                .iter()
                .filter(|r| r.located)
                .map(|r| format!("; where on the board: {}", r.sentence))
                .collect::<String>()
        ),
    };
    if verdict != Verdict::NoMissingPhysics {
        findings.push(Finding::new(
            Severity::Warning,
            match verdict {
                Verdict::MechanismFound => "diagnose.mechanism_found",
                Verdict::ModelForm => "diagnose.model_form",
                _ => "diagnose.unexplained_misfit",
            },
            if verdict == Verdict::ModelForm {
                remaining.clone()
            } else {
                rows.first()
                    .map(sentence)
                    .unwrap_or_else(|| remaining.clone())
            },
        ));
    }
    if let (Verdict::MechanismFound, Some(p)) = (verdict, &unexplained) {
        findings.push(Finding::new(
            Severity::Warning,
            "diagnose.remaining_discrepancy",
            format!("besides the mechanism(s) found, {p} remain(s) unexplained: {remaining}"),
        ));
    }
    for c in compared {
        if let Some(note) = &c.refit.location_note {
            findings.push(Finding::new(
                Severity::Warning,
                "diagnose.location_search",
                format!("{}: {note}", c.refit.dir),
            ));
        }
    }
    for o in &located.identification_outliers {
        findings.push(Finding::new(
            Severity::Warning,
            "diagnose.identification_outlier",
            format!(
                "{} ({}, {}): mode {} is {:+.3} % off the other measurements (t {:.1} beyond the {:.2} % tolerance) while its other modes agree with them (p {:.2}); a slip of the modal fit is likelier than missing physics, which moves several modes together. Check its stabilization diagram; not counted as misfit",
                o.measurement_id,
                o.board_id,
                o.setup,
                o.label,
                100.0 * o.centred_rel_residual,
                o.z,
                100.0 * located.options.tolerance_rel,
                o.p_value_other_modes
            ),
        ));
    }
    let doc = DiagnosisDoc {
        verdict,
        located: LocatedSummary {
            any: located.any,
            above_practical_threshold: above,
            largest_mode_misfit: largest.clone(),
            setups: located.setups.clone(),
            modes: located.modes.clone(),
            measurements: located.measurements.clone(),
            identification_outliers: located.identification_outliers.clone(),
            covariates: located.covariates.clone(),
            unpaired_clusters: located.unpaired_clusters.clone(),
            never_seen: located.never_seen.clone(),
            board_regions,
            board_regions_note,
        },
        findings: findings_doc,
        candidates: rows
            .iter()
            .map(|r| CandidateDoc {
                id: r.cand.id(),
                candidate: r.cand.clone(),
                refit: r.cmp.clone(),
                sentence: sentence(r),
            })
            .collect(),
        remaining_discrepancy: remaining,
        options: opts.clone(),
        checks: located.clone(),
        stage_findings: findings.0.clone(),
    };
    std::fs::create_dir_all(&opts.out)?;
    let mut outputs = vec![];
    let p = opts.out.join(JSON);
    crate::io::atomic::write_bytes(&p, serde_json::to_string_pretty(&doc)?.as_bytes())?;
    outputs.push(p);
    // diagnosis.parquet
    let f = |g: &dyn Fn(&Row) -> Option<f64>| -> ArrayRef {
        Arc::new(Float64Array::from(rows.iter().map(g).collect::<Vec<_>>()))
    };
    let held = |r: &Row, after: bool| {
        r.cmp.as_ref().and_then(|c| {
            c.held_out_before_after
                .iter()
                .find(|(s, _, _)| s == "bolted")
                .map(|(_, b, a)| if after { *a } else { *b })
        })
    };
    let est = |r: &Row| {
        r.cmp
            .as_ref()
            .and_then(|c| c.refit.estimates.first().cloned())
    };
    let cols: Vec<ArrayRef> = vec![
        Arc::new(Int32Array::from_iter_values(
            (1..=rows.len() as i32).collect::<Vec<_>>(),
        )),
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|r| r.cand.mechanism.id()),
        )),
        Arc::new(Int32Array::from(
            rows.iter()
                .map(|r| r.cand.joint.map(|j| j as i32))
                .collect::<Vec<_>>(),
        )),
        Arc::new(StringArray::from(
            rows.iter()
                .map(|r| r.cand.covariate.clone())
                .collect::<Vec<_>>(),
        )),
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|r| r.cand.reason.clone()),
        )),
        Arc::new(BooleanArray::from(
            rows.iter().map(|r| r.cmp.is_some()).collect::<Vec<_>>(),
        )),
        f(&|r| r.cmp.as_ref().and_then(|c| c.log_bayes_factor)),
        f(&|r| r.cmp.as_ref().and_then(|c| c.log_bayes_factor_se)),
        Arc::new(BooleanArray::from(
            rows.iter()
                .map(|r| r.cmp.as_ref().is_some_and(|c| c.favoured))
                .collect::<Vec<_>>(),
        )),
        f(&|r| held(r, false)),
        f(&|r| held(r, true)),
        Arc::new(StringArray::from(
            rows.iter()
                .map(|r| est(r).map(|e| e.parameter))
                .collect::<Vec<_>>(),
        )),
        f(&|r| est(r).map(|e| e.median)),
        f(&|r| est(r).map(|e| e.q05)),
        f(&|r| est(r).map(|e| e.q95)),
        Arc::new(StringArray::from(
            rows.iter()
                .map(|r| r.cmp.as_ref().and_then(|c| c.refit.failed.clone()))
                .collect::<Vec<_>>(),
        )),
        Arc::new(StringArray::from_iter_values(rows.iter().map(sentence))),
    ];
    let mut md = BTreeMap::new();
    md.insert("hbmu.verdict".to_string(), serde_json::to_string(&verdict)?);
    let schema = DIAGNOSIS.schema(&[], &tables::table_metadata(&DIAGNOSIS, &md));
    let p = opts.out.join("diagnosis.parquet");
    tables::write_parquet(&p, &tables::batch(schema, cols)?)?;
    outputs.push(p);
    // diagnosis_modes.parquet: each mode's misfit, baseline and every refit that gave one.
    let mut mode_rows: Vec<(String, ModeCheck)> = located
        .mode_checks
        .iter()
        .map(|m| ("baseline".to_string(), m.clone()))
        .collect();
    for r in &rows {
        let Some(c) = r.cmp.as_ref().filter(|c| c.refit.failed.is_none()) else {
            continue;
        };
        mode_rows.extend(
            locate::mode_means(
                &refit_residuals(&opts.out.join(&c.refit.dir))?,
                &opts.locate,
            )
            .into_iter()
            .map(|m| (r.cand.id(), m)),
        );
    }
    let is_located = |m: &ModeCheck| {
        located
            .modes
            .iter()
            .any(|l| l.setup == m.setup && l.label == m.label)
    };
    let fin = |v: f64| v.is_finite().then_some(v);
    let cols: Vec<ArrayRef> = vec![
        Arc::new(StringArray::from_iter_values(
            mode_rows.iter().map(|(k, _)| k.as_str()),
        )),
        Arc::new(StringArray::from_iter_values(
            mode_rows.iter().map(|(_, m)| m.setup.as_str()),
        )),
        Arc::new(StringArray::from_iter_values(
            mode_rows.iter().map(|(_, m)| m.label.as_str()),
        )),
        Arc::new(BooleanArray::from(
            mode_rows
                .iter()
                .map(|(_, m)| m.used_for_updating)
                .collect::<Vec<_>>(),
        )),
        Arc::new(Int32Array::from_iter_values(
            mode_rows.iter().map(|(_, m)| m.n as i32),
        )),
        Arc::new(Int32Array::from_iter_values(
            mode_rows.iter().map(|(_, m)| m.n_boards as i32),
        )),
        Arc::new(Float64Array::from(
            mode_rows
                .iter()
                .map(|(_, m)| fin(m.mean_rel_residual))
                .collect::<Vec<_>>(),
        )),
        Arc::new(Float64Array::from(
            mode_rows
                .iter()
                .map(|(_, m)| fin(m.se_rel_residual))
                .collect::<Vec<_>>(),
        )),
        Arc::new(BooleanArray::from(
            mode_rows
                .iter()
                .map(|(_, m)| is_located(m))
                .collect::<Vec<_>>(),
        )),
    ];
    let schema = MODES.schema(&[], &tables::table_metadata(&MODES, &BTreeMap::new()));
    let p = opts.out.join("diagnosis_modes.parquet");
    tables::write_parquet(&p, &tables::batch(schema, cols)?)?;
    outputs.push(p);
    for fd in findings.iter() {
        if verbose || fd.severity >= Severity::Warning {
            eprintln!("{fd}");
        }
    }
    eprintln!(
        "diagnose: verdict {}; {} candidates screened, {} refitted; {}",
        serde_json::to_string(&verdict)?.trim_matches('"'),
        candidates.len(),
        compared.len(),
        findings.summary()
    );
    let mut s = BTreeMap::new();
    s.insert("verdict".into(), serde_json::to_value(verdict)?);
    Ok(StageResult {
        outputs,
        exit_code: exit::OK,
        summary: s,
    })
}

#[cfg(test)]
mod tests {
    use super::{
        above_practical_threshold, demote_weaker_regions, model_form_pattern, whole_board_outliers,
    };
    use crate::diagnose::library::Mechanism;
    use crate::diagnose::localize::LocalFit;
    use crate::diagnose::locate::{self, LocateInput, LocateOptions, LocatedMode};
    use crate::stage::diagnose::regions::BoardRegion;

    fn region(mechanism: Mechanism, share: f64, combined: Option<f64>) -> BoardRegion {
        let fit = LocalFit {
            x_m: 0.05,
            y_m: 0.03,
            amplitude: 1.0,
            amplitude_se: 0.1,
            chi2_before: 100.0,
            chi2_after: 100.0 * (1.0 - share),
            dof_after: 2,
            explained_share: share,
            p_value: 1e-9,
            region_radius_m: 0.01,
            region_points: 10,
            log_location_occam: -1.0,
            inflation: 1.0,
            ..LocalFit::default()
        };
        BoardRegion {
            combined_delta_chi2: combined,
            ..BoardRegion::located_fit(mechanism, fit, "Fit.")
        }
    }

    /// A located mean shift counts as a finding only at or above the practical threshold;
    /// an unexplained free-free misfit placed nowhere on the board is the model's form, and a
    /// located region, an outlier measurement or a bolted-only misfit is not.
    #[test]
    fn the_practical_threshold_and_the_model_form_pattern() {
        let mut loc = locate::locate(&LocateInput::default(), &LocateOptions::default());
        let shift = |setup: &str, r: f64| LocatedMode {
            setup: setup.into(),
            label: "plate-2-2".into(),
            mean_rel_residual: r,
            reasons: vec!["mean_shift".into()],
        };
        assert!(!above_practical_threshold(&loc, 3e-3), "nothing located");
        loc.any = true;
        loc.modes = vec![shift("free", -0.0011)];
        assert!(!above_practical_threshold(&loc, 3e-3), "0.11 % < 0.3 %");
        assert!(above_practical_threshold(&loc, 1e-3));
        loc.modes.push(shift("bolted", 0.007));
        assert!(above_practical_threshold(&loc, 3e-3));
        assert!(model_form_pattern(&loc, &[], 0.0125, false));
        // A region of 10 mm places the misfit; one spanning the board does not.
        let placed = region(Mechanism::AddedMass, 0.9, None);
        assert!(!model_form_pattern(
            &loc,
            std::slice::from_ref(&placed),
            0.0125,
            false
        ));
        let mut wide = placed;
        wide.fit.region_radius_m = 0.055;
        assert!(model_form_pattern(&loc, &[wide], 0.0125, false));
        let mut one = loc.clone();
        one.measurements = vec!["M040".into()];
        assert!(!model_form_pattern(&one, &[], 0.0125, false));
        // Boards that differ are the per-unit discrepancy's; a temperature trend is not.
        let cov = |name: &str| locate::LocatedCovariate {
            setup: "free".into(),
            covariate: name.into(),
            q_value: 1e-6,
            slope_rel_per_unit: None,
            unit: String::new(),
        };
        let mut boards = loc.clone();
        boards.covariates = vec![cov("board_id")];
        assert!(model_form_pattern(&boards, &[], 0.0125, false));
        boards.covariates.push(cov("temperature_c"));
        assert!(!model_form_pattern(&boards, &[], 0.0125, false));
        let mut bolted = loc.clone();
        bolted.modes.remove(0);
        assert!(!model_form_pattern(&bolted, &[], 0.0125, false));

        // Outliers that are all of a board's measurements (with boards located as differing)
        // are the board; one that stands apart from its board's other measurements is not.
        let info = |m: &str, b: &str| locate::MeasurementInfo {
            measurement_id: m.into(),
            board_id: b.into(),
            setup: "free".into(),
        };
        let ms = [
            info("M1", "B1"),
            info("M2", "B1"),
            info("M3", "B2"),
            info("M4", "B2"),
        ];
        let mut whole = loc.clone();
        whole.covariates = vec![cov("board_id")];
        whole.measurements = vec!["M1".into(), "M2".into()];
        assert_eq!(
            whole_board_outliers(&whole, &ms),
            Some(vec![("free".to_string(), "B1".to_string())])
        );
        assert!(model_form_pattern(&whole, &[], 0.0125, true));
        whole.measurements = vec!["M1".into()];
        assert_eq!(whole_board_outliers(&whole, &ms), None);
        whole.measurements = vec!["M1".into(), "M2".into()];
        whole.covariates.clear();
        assert_eq!(
            whole_board_outliers(&whole, &ms),
            None,
            "boards not located as differing"
        );
        whole.measurements.clear();
        assert_eq!(whole_board_outliers(&whole, &ms), Some(vec![]));
    }

    /// A refit whose runs disagree a little keeps its Bayes factor (its estimates are said
    /// to be approximate); one whose runs disagree beyond the classical 1.1 gives none.
    #[test]
    fn the_r_hat_gate_keeps_the_evidence_of_runs_that_disagree_a_little() {
        let d = std::path::Path::new("refits/joint_rotation");
        let w = |r: f64| Some(("mu_ln_k_rot".to_string(), r));
        assert_eq!(super::r_hat_gate(None, d), (None, None));
        assert_eq!(super::r_hat_gate(w(1.03), d), (None, None));
        let (failed, note) = super::r_hat_gate(w(1.053), d);
        assert!(failed.is_none());
        assert!(note.unwrap().contains("R-hat of mu_ln_k_rot 1.053 > 1.05"));
        let (failed, note) = super::r_hat_gate(w(1.2), d);
        assert!(failed
            .unwrap()
            .contains("1.200 > 1.1 in refits/joint_rotation"));
        assert!(note.is_none());
    }

    /// Two signatures that explain the frequencies alike: with shape terms the combined Δχ²
    /// decides (here against the frequencies' slightly larger share), without them the share.
    #[test]
    fn the_shapes_decide_between_signatures_the_frequencies_cannot_tell_apart() {
        let mut r = [
            region(Mechanism::AddedMass, 0.9913, Some(187_842.0)),
            region(Mechanism::LocalStiffnessLoss, 0.9926, Some(184_405.0)),
        ];
        demote_weaker_regions(&mut r);
        assert!(r[0].located && !r[1].located);
        assert!(r[1].sentence.contains("added_mass signature explains more"));
        assert!(r[1].sentence.contains("Δχ² 187842 against 184405"));

        let mut r = [
            region(Mechanism::AddedMass, 0.9913, None),
            region(Mechanism::LocalStiffnessLoss, 0.9926, None),
        ];
        demote_weaker_regions(&mut r);
        assert!(!r[0].located && r[1].located);
        assert!(r[0].sentence.contains("(99 % against 99 %)"));

        // A region that was not located is neither compared nor changed.
        let mut r = [
            region(Mechanism::AddedMass, 0.9, Some(10.0)),
            region(Mechanism::LocalStiffnessLoss, 0.4, Some(50.0)),
        ];
        r[1].located = false;
        demote_weaker_regions(&mut r);
        assert!(r[0].located && r[1].sentence == "Fit.");
    }
}

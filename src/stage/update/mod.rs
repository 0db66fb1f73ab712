//! Stage `update`: the two-step hierarchical Bayesian updating (the kernels are in
//! [`crate::update`]).
//!
//! - `update boards` (step 1, [`boards`]): free-free modes of every board and the balance
//!   masses update the boards' parameters and their population.
//! - `update joints` (step 2, [`joints`]): the bolted modes update every measurement's joint
//!   parameters, carrying step 1's draws (the cut posterior).
//!
//! Inputs: `masses`/`specimens`/`measurements` of ingest, `modes` of extract,
//! `pairs`/`presence` of pair, a board file (default: the built-in board); the ROM is built
//! here from the board. Outputs (flat Parquet, schemas in `schemas/tables/`): `population`,
//! `boards` or `joints`, `summary`, `stages`, `residuals`, `rom.npz`, `evidence.json`,
//! `update_report.json`.

use crate::bayes::shape_weight::ShapeWeight;
use crate::bayes::smc::{self, StageInfo};
use crate::fem::params::names;
use crate::fem::Board;
use crate::fem::Setup;
use crate::findings::{Finding, Findings, Severity};
use crate::io::manifest::StageSpec;
use crate::io::model_cache;
use crate::io::modes_table::read_modes_table;
use crate::io::tables::update::{
    provenance, read_masses, read_pairs, read_presence, read_specimen_thickness, read_step1,
    read_step1_enrichment, write_draws, write_residuals, write_stages, write_summary, BOARDS,
    BOARDS_PHYSICAL, POPULATION,
};
use crate::io::tables::update::{read_covariate, write_joint_tables};
use crate::io::tables::{self, Cols};
use crate::modal::rows::ModeRow;
use crate::modal::rows::PairRow;
use crate::stage::{exit, PhaseClock, StageOutcome, StageResult};
use crate::update::enrichment::{is_board_mechanism, Mechanism};
use crate::update::posterior::{convergence_finding, lost_finding, residuals, SummaryRow};
use crate::update::prepare::{CentreGate, JointPrep};
use crate::update::problem::{
    discrepancy_for, model_error_from, model_error_study, report_shape_weights, select_labels,
    weigh_shapes, ModelSpec,
};
use crate::update::rom_box::{
    rom_box_check, rom_centre_check, rom_options_for, widened, RomBoxViolation,
};
use crate::update::sampler::{acceleration_findings, run_smc, Acceleration, SamplerParams};
use crate::update::step1::Step1;
use anyhow::{anyhow, bail, Context};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

pub use crate::update::posterior::MAX_R_HAT;
pub use crate::update::problem::ShapeWeighting;

mod boards;
mod joints;

pub use boards::run_boards;
pub use joints::{run_joints, run_joints_with, screen_joint_units, ScreenRun};

pub use crate::io::tables::update::{MANIFEST_BOARDS, MANIFEST_JOINTS};

/// A step's options: where it reads and writes, what it updates with which model
/// ([`ModelSpec`]), and how the posterior is sampled ([`SamplerParams`]). The configuration the
/// stage fingerprints is the last two (flattened: the same keys as one flat struct).
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct UpdateOptions {
    #[serde(skip)]
    pub ingest_dir: PathBuf,
    #[serde(skip)]
    pub pair_dir: PathBuf,
    /// Extract output (modes.parquet); default: `extract` next to the pair directory.
    #[serde(skip)]
    pub extract_dir: Option<PathBuf>,
    #[serde(skip)]
    pub board: Option<PathBuf>,
    #[serde(skip)]
    pub out: PathBuf,
    #[serde(skip)]
    pub force: bool,
    /// Where model artifacts (ROMs, the mesh study) are looked up and published: the CLI's
    /// is `HBMU_CACHE`'s; none builds every one. Not an option of the result (a hit is the
    /// build, bit for bit), so outside the fingerprint.
    #[serde(skip)]
    pub cache: Option<crate::io::cache::Cache>,
    #[serde(flatten)]
    pub sampler: SamplerParams,
    #[serde(flatten)]
    pub model: ModelSpec,
}

impl UpdateOptions {
    fn extract_dir(&self) -> PathBuf {
        self.extract_dir.clone().unwrap_or_else(|| {
            self.pair_dir
                .parent()
                .map(|p| p.join("extract"))
                .unwrap_or_else(|| PathBuf::from("extract"))
        })
    }
}

// ---------------------------------------------------------------------------------------------
// Reading the campaign's tables.

pub(crate) fn load_board(path: Option<&Path>) -> anyhow::Result<(Board, String)> {
    let text = match path {
        Some(p) => std::fs::read_to_string(p)
            .with_context(|| format!("cannot read board file {}", p.display()))?,
        None => crate::fem::board::DEFAULT_BOARD_TOML.to_string(),
    };
    let board = Board::from_toml_str(&text).map_err(|e| match path {
        Some(p) => anyhow!("{}: {e}", p.display()),
        None => anyhow!("built-in board: {e}"),
    })?;
    Ok((board, text))
}

// ---------------------------------------------------------------------------------------------
// From tables to the likelihood's data.

impl ShapeWeighting {
    /// `auto`, `off`, or the path of an `update` stage's evidence.json whose `shape_weights`
    /// are taken (`--shape-weights`).
    pub fn parse(arg: &str) -> Result<ShapeWeighting, String> {
        match arg {
            "auto" => Ok(ShapeWeighting::Auto),
            "off" => Ok(ShapeWeighting::Off),
            path => Self::from_evidence(Path::new(path)).map_err(|e| format!("{e:#}")),
        }
    }

    /// The weights an `update` run used, from its evidence.json (`shape_weights`: one
    /// {label, weight, …} per mode; absent or empty: a run without shape terms, `Off`).
    pub fn from_evidence(path: &Path) -> anyhow::Result<ShapeWeighting> {
        let ev = crate::io::read_json(path)?;
        let Some(list) = ev.get("shape_weights").and_then(|v| v.as_array()) else {
            return Ok(ShapeWeighting::Off);
        };
        let mut map = BTreeMap::new();
        for (i, w) in list.iter().enumerate() {
            let w: ShapeWeight = serde_json::from_value(w.clone()).with_context(|| {
                format!(
                    "{}: shape_weights[{i}]: expected {{label, weight, …}}",
                    path.display()
                )
            })?;
            if !(w.weight > 0.0 && w.weight <= 1.0) {
                bail!(
                    "{}: shape_weights[{i}] ({}): weight {} is not in (0, 1]",
                    path.display(),
                    w.label,
                    w.weight
                );
            }
            map.insert(w.label, w.weight);
        }
        Ok(ShapeWeighting::Given(map))
    }
}

// ---------------------------------------------------------------------------------------------
// Draw tables and their summary.

/// Step 2 of a campaign without a paired bolted mode (free-free only, or every bolted
/// measurement quarantined or without an identified mode): nothing to update. The stage
/// succeeds with `update_report.json` alone, which says why, and no posterior: `propagate`
/// and `report` then go on without bolted predictions, so a free-free campaign goes through
/// the whole pipeline.
fn no_bolted_data(
    opts: &UpdateOptions,
    measurements: &Path,
    mut findings: Findings,
) -> anyhow::Result<StageResult> {
    let mut n_bolted = 0usize;
    for b in tables::read_parquet(measurements)? {
        let c = Cols {
            batch: &b,
            path: measurements,
        };
        let st = c.str("setup")?;
        n_bolted += (0..b.num_rows())
            .filter(|&i| arrow::array::Array::is_valid(st, i) && st.value(i) == "bolted")
            .count();
    }
    let (severity, message) = if n_bolted == 0 {
        (
            Severity::Info,
            "the campaign has no bolted measurement: step 2 has nothing to update (no joint posterior)".to_string(),
        )
    } else {
        (
            Severity::Warning,
            format!("none of the campaign's {n_bolted} bolted measurements has a paired mode in pairs.parquet (see the ingest and pair reports): step 2 has nothing to update (no joint posterior)"),
        )
    };
    eprintln!("update joints: {message}");
    findings.push(Finding::new(severity, "update.no_bolted_data", message));
    let report = serde_json::json!({
        "labels": Vec::<String>::new(),
        "runs": 0,
        "bolted_measurements": n_bolted,
        "findings": findings.0,
    });
    let p = opts.out.join("update_report.json");
    crate::io::atomic::write_bytes(&p, serde_json::to_string_pretty(&report)?.as_bytes())?;
    Ok(StageResult {
        outputs: vec![p],
        exit_code: crate::stage::exit::OK,
        summary: BTreeMap::from([(
            "bolted_measurements".to_string(),
            serde_json::json!(n_bolted),
        )]),
    })
}

// ---------------------------------------------------------------------------------------------
// Running the sampler.

/// The board and the stage spec shared by both steps: inputs named by content (they come from
/// several stage directories, so no path may reach the fingerprint), the options, the board
/// file's hash and the step's own config entries.
fn step_spec(
    opts: &UpdateOptions,
    stage: &str,
    mut inputs: Vec<PathBuf>,
    extra_config: &[(&str, &str)],
    manifest: &str,
) -> anyhow::Result<(Board, StageSpec)> {
    if let Some(b) = &opts.board {
        inputs.push(b.clone());
    }
    let (board, board_text) = load_board(opts.board.as_deref())?;
    let mut config = serde_json::to_value(opts)?;
    config["board_blake3"] = blake3::hash(board_text.as_bytes())
        .to_hex()
        .to_string()
        .into();
    for (k, v) in extra_config {
        config[*k] = (*v).into();
    }
    let spec = StageSpec {
        stage: stage.into(),
        inputs,
        input_base: PathBuf::new(),
        config,
        seed: Some(opts.sampler.seed),
        manifest_path: opts.out.join(manifest),
    };
    Ok((board, spec))
}

/// A step's SMC ([`run_smc`]) with its progress on a progress bar.
fn sample(
    target: &crate::bayes::target::ModalTarget,
    sampler: &crate::update::sampler::SamplerParams,
    what: &str,
    aux: &[Vec<std::sync::Arc<Vec<f64>>>],
    start: Option<&[f64]>,
    check_reference: &crate::update::sampler::ReferenceCheck<'_>,
    verbose: bool,
) -> anyhow::Result<(
    crate::update::sampler::Results,
    crate::update::sampler::Acceleration,
)> {
    let pb = crate::stage::progress_bar((sampler.runs * 1000) as u64, what);
    let out = run_smc(
        target,
        sampler,
        what,
        aux,
        start,
        check_reference,
        &progress_to(&pb),
        verbose,
    )?;
    pb.finish_and_clear();
    Ok(out)
}

/// The sampler's progress on a progress bar.
fn progress_to(pb: &indicatif::ProgressBar) -> impl Fn(u64, String) + Sync + '_ {
    move |position, message| {
        pb.set_position(position);
        pb.set_message(message);
    }
}

#[allow(clippy::too_many_arguments)]
fn finish(
    opts: &UpdateOptions,
    findings: Findings,
    mut outputs: Vec<PathBuf>,
    results: &[smc::RunResult<crate::bayes::modal::Terms>],
    summary: &[SummaryRow],
    ev: serde_json::Value,
    sampler_seconds: f64,
    labels: &[String],
    verbose: bool,
    what: &str,
    acceleration: &Acceleration,
    phases: &PhaseClock,
) -> anyhow::Result<StageResult> {
    let mut findings = findings;
    if let Some(f) = convergence_finding(summary, results.len()) {
        findings.push(f);
    }
    for f in findings.iter() {
        if verbose || f.severity >= Severity::Warning {
            eprintln!("{f}");
        }
    }
    let max_rhat = summary.iter().map(|r| r.s.r_hat).fold(f64::NAN, f64::max);
    let min_ess = summary
        .iter()
        .map(|r| r.s.ess_bulk.min(r.s.ess_tail))
        .fold(f64::NAN, f64::min);
    let evals: u64 = results
        .iter()
        .flat_map(|r| &r.stages)
        .map(|s| s.model_evals)
        .sum();
    let report = serde_json::json!({
        "labels": labels,
        "runs": results.len(),
        "particles": opts.sampler.smc.n_particles,
        "stages_per_run": results.iter().map(|r| r.stages.len()).collect::<Vec<_>>(),
        "max_r_hat": max_rhat,
        "min_ess": min_ess,
        "evidence": ev,
        "acceleration": acceleration,
        "held_out_boards": opts.model.hold_out_boards,
        "held_out_measurements": opts.model.hold_out_measurements,
        "findings": findings.0,
    });
    let p = opts.out.join("update_report.json");
    crate::io::atomic::write_bytes(&p, serde_json::to_string_pretty(&report)?.as_bytes())?;
    outputs.push(p);
    eprintln!(
        "{what}: {} runs × {} particles, {} stages per run, log evidence {:.2} ± {:.2}, max R-hat {:.4}, min ESS {:.0}; {} ROM evaluations in {:.1} s; {}",
        results.len(),
        opts.sampler.smc.n_particles,
        results.iter().map(|r| r.stages.len().to_string()).collect::<Vec<_>>().join("/"),
        ev["log_evidence_mean"].as_f64().unwrap_or(f64::NAN),
        ev["log_evidence_standard_error"].as_f64().unwrap_or(f64::NAN),
        max_rhat,
        min_ess,
        evals,
        sampler_seconds,
        findings.summary()
    );
    let mut s = BTreeMap::new();
    s.insert("max_r_hat".into(), serde_json::json!(max_rhat));
    s.insert("rom_evaluations".into(), serde_json::json!(evals));
    s.insert("sampler_seconds".into(), serde_json::json!(sampler_seconds));
    s.insert("phase_seconds".into(), phases.summary());
    Ok(StageResult {
        outputs,
        exit_code: exit::OK,
        summary: s,
    })
}

//! Stage `update`: two-step hierarchical Bayesian updating (see `bayes`).
//!
//! - `update boards` (step 1): free-free modes of every board + the balance masses update the
//!   boards' parameters and their population (MVN + LKJ), with per-mode prediction errors.
//! - `update joints` (step 2, bolted, boards carried from step 1) is not built yet.
//!
//! Inputs: `masses` of ingest, `modes` of extract, `pairs`/`presence` of pair, a board
//! description (default: the built-in board); the ROM is built here from the board.
//! Outputs (flat Parquet, schemas in `schemas/tables/`): `population`, `boards`,
//! `summary`, `stages`, `residuals`, and `evidence.json`, `update_report.json`.

use crate::bayes::shape_weight::ShapeWeight;
use crate::bayes::smc::{self, StageInfo};
use crate::fem::params::names;
use crate::fem::Board;
use crate::findings::{Finding, Findings, Severity};
use crate::io::manifest::StageSpec;
use crate::io::modes_table::read_modes_table;
use crate::io::tables::update::{
    provenance, read_masses, read_pairs, read_presence, read_specimen_thickness, read_step1,
    read_step1_enrichment, write_draws, write_residuals, write_stages, write_summary, BOARDS,
    POPULATION,
};
use crate::io::tables::update::{read_covariate, write_joint_tables};
use crate::io::tables::{self, Cols};
use crate::modal::rows::ModeRow;
use crate::modal::rows::PairRow;
use crate::stage::{exit, StageOutcome, StageResult};
use crate::update::enrichment::{is_board_mechanism, Mechanism};
use crate::update::posterior::{convergence_finding, lost_finding, residuals, SummaryRow};
use crate::update::prepare::JointPrep;
use crate::update::problem::{
    discrepancy_for, report_shape_weights, select_labels, weigh_shapes, ModelSpec,
};
use crate::update::rom_box::{
    rom_box_check, rom_centre_check, rom_for, RomBoxViolation, MAX_ROM_BOX,
};
use crate::update::sampler::{check_surrogate_edges, run_smc, Acceleration, SamplerParams};
use crate::update::step1::Step1;
use anyhow::{anyhow, bail, Context};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

pub use crate::update::posterior::MAX_R_HAT;
pub use crate::update::problem::ShapeWeighting;

pub const MANIFEST_BOARDS: &str = "update_boards.manifest.json";
pub const MANIFEST_JOINTS: &str = "update_joints.manifest.json";

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

/// Step 1: boards, free-free.
pub fn run_boards(opts: &UpdateOptions, verbose: bool) -> anyhow::Result<StageOutcome> {
    let extract_dir = opts.extract_dir();
    let pairs_path = opts.pair_dir.join("pairs.parquet");
    let presence_path = opts.pair_dir.join("presence.parquet");
    let modes_path = extract_dir.join("modes.parquet");
    let masses_path = opts.ingest_dir.join("masses.parquet");
    let measurements_path = opts.ingest_dir.join("measurements.parquet");
    let specimens_path = opts.ingest_dir.join("specimens.parquet");
    if let Some(m) = opts.model.enrich.filter(|m| !is_board_mechanism(*m)) {
        bail!(
            "--enrich {}: not a board mechanism (update boards refits temperature_stiffness, added_mass)",
            m.id()
        );
    }
    if !(opts.model.mass_floor_rel.is_finite() && opts.model.mass_floor_rel >= 0.0) {
        bail!(
            "--mass-floor: expected a finite relative value >= 0, found {}",
            opts.model.mass_floor_rel
        );
    }
    let mut inputs = vec![
        pairs_path.clone(),
        presence_path.clone(),
        modes_path.clone(),
        masses_path.clone(),
    ];
    if opts.model.enrich_covariate.is_some() {
        inputs.push(measurements_path.clone());
    }
    // Older ingest outputs have no specimens table: every board at the board file's thickness.
    if specimens_path.is_file() {
        inputs.push(specimens_path.clone());
    }
    let (board, spec) = step_spec(
        opts,
        "update_boards",
        inputs,
        &[("step", "boards")],
        MANIFEST_BOARDS,
    )?;
    let paths = BoardPaths {
        pairs: pairs_path,
        presence: presence_path,
        modes: modes_path,
        masses: masses_path,
        measurements: measurements_path,
        specimens: specimens_path,
    };
    crate::stage::run(spec, opts.force, |prep| {
        // One attempt at the ROM box `opts.model.rom_box`; `carried` are findings of an
        // earlier one.
        widen_rom_box_once(opts, |o, carried| {
            boards_attempt(o, carried, &board, &paths, prep, verbose)
        })
    })
}

struct BoardPaths {
    pairs: PathBuf,
    presence: PathBuf,
    modes: PathBuf,
    masses: PathBuf,
    measurements: PathBuf,
    specimens: PathBuf,
}

fn boards_attempt(
    opts: &UpdateOptions,
    carried: &[Finding],
    board: &Board,
    paths: &BoardPaths,
    prep: &crate::io::manifest::Prepared,
    verbose: bool,
) -> anyhow::Result<StageResult> {
    use crate::update::boards;
    let mut clock = PhaseClock::new("update boards", verbose);
    let mut findings = Findings::default();
    findings.0.extend(carried.iter().cloned());
    let pairs = read_pairs(&paths.pairs)?;
    let presence = read_presence(&paths.presence, "free")?;
    let labels = select_labels(&pairs, "free", &opts.model.modes, &presence, &mut findings)?;
    // Boards measured in thickness: the core thickness is a board parameter (exact in the
    // model), each board's reading an observation of it. The sheet gives the overall thickness
    // a micrometer reads over the copper (a finished board's, as a fabrication drawing gives
    // it): the board file's copper layers are taken off.
    let copper_m = board.copper_thickness_m();
    let thickness_m: BTreeMap<String, f64> = read_specimen_thickness(&paths.specimens)?
        .into_iter()
        .map(|(b, h)| (b, h - copper_m))
        .collect();
    let with_thickness;
    let opts =
        if thickness_m.is_empty() || opts.model.params.iter().any(|p| p == names::CORE_THICKNESS) {
            opts
        } else {
            let mut o = opts.clone();
            o.model.params.push(names::CORE_THICKNESS.into());
            with_thickness = o;
            &with_thickness
        };
    let bm = boards::board_model(
        board,
        &opts.model,
        &labels,
        &pairs,
        !thickness_m.is_empty(),
        &mut findings,
    )?;
    let need = bm.need;
    clock.lap("models");
    let rom = rom_for(&bm.model, need, &bm.log_axes, &opts.model)?;
    rom_centre_check(&bm.model, &rom, need, &mut findings)?;
    clock.lap("rom_build");
    if opts.model.rom_box > ModelSpec::DEFAULT_ROM_BOX {
        let worst = rom_box_check(&bm.model, &rom, opts.model.rom_box, need)?;
        findings.push(Finding::new(
            if worst > 1e-4 { Severity::Warning } else { Severity::Info },
            "update.rom_box_check",
            format!(
                "the ROM over ±{:.0} %: worst relative frequency error {worst:.1e} against the full model over its first {need} modes at 8 Latin-hypercube points{}",
                100.0 * opts.model.rom_box,
                if worst > 1e-4 { " (above 1e-4, the accuracy the ±20 % ROM is held to: raise --rom-basis)" } else { "" }
            ),
        ));
    }
    let masses = read_masses(&paths.masses)?;
    let covariate = match (&opts.model.enrich, &opts.model.enrich_covariate) {
        (Some(Mechanism::TemperatureStiffness), Some(column)) => {
            Some(read_covariate(&paths.measurements, column)?)
        }
        _ => None,
    };
    let mode_rows = read_modes_table(&paths.modes)?;
    let measurements_source = paths.measurements.display().to_string();
    let mut bt = boards::board_target(
        board,
        &bm,
        &rom,
        &opts.model,
        (&labels, &pairs, &mode_rows),
        &masses,
        covariate
            .as_deref()
            .map(|v| (v, measurements_source.as_str())),
        &thickness_m,
        &mut findings,
    )?;
    // The surrogates model a unit's terms as a function of its ROM parameters alone; with a
    // covariate the terms also follow the unit's coefficient, so the ROM runs directly.
    let mut sopts = opts.clone();
    sopts.sampler.surrogate &= bt.target.covariate.is_none();
    clock.lap("unit_data");
    let shape_weights = weigh_shapes(
        &mut bt.target,
        &opts.model.shape_weights,
        (&[], None),
        &labels.labels,
        opts.sampler.seed,
        "boards",
    )?;
    report_shape_weights(&shape_weights, "boards", verbose, &mut findings);
    clock.lap("shape_weights");
    let pb = crate::stage::progress_bar((sopts.sampler.runs * 1000) as u64, "boards");
    let (results, acceleration) = run_smc(
        &bt.target,
        &sopts.sampler,
        "boards",
        &[],
        None,
        &progress_to(&pb),
        verbose,
    )?;
    pb.finish_and_clear();
    let sampler_seconds = clock.lap("sampler");
    check_surrogate_edges(&acceleration, &mut findings);
    boards::check_board_box(&bm, &bt, &results, &opts.model)?;
    let prov = provenance("update_boards", &prep.fingerprint);
    let mut outputs = vec![];
    let (pop, boards_t, summary) =
        boards::board_tables(&bm, &bt, &results, &labels, opts.sampler.runs);
    let p = opts.out.join("population.parquet");
    write_draws(&p, &POPULATION, &pop, false, &prov)?;
    outputs.push(p);
    let p = opts.out.join("boards.parquet");
    write_draws(&p, &BOARDS, &boards_t, true, &prov)?;
    outputs.push(p);
    let p = opts.out.join("summary.parquet");
    write_summary(&p, &summary, &prov)?;
    outputs.push(p);
    let stages: Vec<StageInfo> = results.iter().flat_map(|r| r.stages.clone()).collect();
    let p = opts.out.join("stages.parquet");
    write_stages(&p, &stages, &prov)?;
    outputs.push(p);
    clock.lap("tables");
    let (res, lost) = residuals(
        &bt.target,
        &bt.all_pred,
        &bm.all.labels,
        &labels.labels,
        &bt.units_all,
        &results,
        "free",
        opts.sampler.residual_draws,
        bt.model_error.as_ref().map(|m| m.sd.as_slice()),
    );
    lost_finding(&lost, &mut findings);
    let p = opts.out.join("residuals.parquet");
    write_residuals(&p, &res, &prov)?;
    outputs.push(p);
    let p = opts.out.join("rom.npz");
    crate::io::atomic::write_bytes(&p, &bt.target.predictor.rom.to_npz_bytes())?;
    outputs.push(p);
    let ev = boards::board_evidence(&bm, &bt, &results, &labels, &shape_weights)?;
    let p = opts.out.join("evidence.json");
    crate::io::atomic::write_bytes(&p, serde_json::to_string_pretty(&ev)?.as_bytes())?;
    outputs.push(p);
    clock.lap("residuals");
    finish(
        opts,
        findings,
        outputs,
        &results,
        &summary,
        ev,
        sampler_seconds,
        &labels.labels,
        verbose,
        "update boards",
        &acceleration,
        &clock,
    )
}

/// Runs a step-1 attempt; when its posterior presses against the ROM's box and a box up to
/// [`MAX_ROM_BOX`] would hold it, rebuilds the ROM over that box and runs once more (the
/// finding `update.rom_box_widened` says so, and the new ROM is checked against the full
/// model). A posterior that still presses, or needs more, stops the stage with the message.
fn widen_rom_box_once(
    opts: &UpdateOptions,
    attempt: impl Fn(&UpdateOptions, &[Finding]) -> anyhow::Result<StageResult>,
) -> anyhow::Result<StageResult> {
    let e = match attempt(opts, &[]) {
        Err(e) => e,
        ok => return ok,
    };
    let Some(v) = e.downcast_ref::<RomBoxViolation>() else {
        return Err(e);
    };
    if v.needed_half_width > MAX_ROM_BOX || v.needed_half_width <= opts.model.rom_box {
        return Err(e);
    }
    let mut wider = opts.clone();
    wider.model.rom_box = v.needed_half_width;
    let what = v
        .message
        .lines()
        .filter_map(|l| l.strip_prefix("  "))
        .collect::<Vec<_>>()
        .join("; ");
    let note = Finding::new(
        Severity::Warning,
        "update.rom_box_widened",
        format!(
            "the posterior pressed against the ROM's ±{:.0} % box ({}): the ROM was rebuilt over ±{:.0} % around the board file's values, checked against the full model (update.rom_box_check), and the sampling run again",
            100.0 * opts.model.rom_box,
            what.trim(),
            100.0 * wider.model.rom_box
        ),
    );
    eprintln!("update boards: {}", note.message);
    attempt(&wider, &[note])
}

/// The key of a [`JointPrep`]: the step's input files by content and its model spec (not the
/// sampler's parameters, which do not change the preparation).
fn joint_prep_key(prep: &crate::io::manifest::Prepared, spec: &ModelSpec) -> String {
    let mut h = blake3::Hasher::new();
    for f in &prep.inputs {
        h.update(f.path.as_bytes());
        h.update(&[0]);
        h.update(f.blake3.as_bytes());
        h.update(&[0]);
    }
    h.update(serde_json::to_string(spec).unwrap_or_default().as_bytes());
    h.finalize().to_hex().to_string()
}

/// The sampler's progress on a progress bar.
fn progress_to(pb: &indicatif::ProgressBar) -> impl Fn(u64, String) + Sync + '_ {
    move |position, message| {
        pb.set_position(position);
        pb.set_message(message);
    }
}

/// Step 2: the joints, bolted, carrying step 1's posterior (the cut posterior).
pub fn run_joints(
    opts: &UpdateOptions,
    boards_dir: &Path,
    verbose: bool,
) -> anyhow::Result<StageOutcome> {
    run_joints_with(opts, boards_dir, &mut None, verbose)
}

/// [`run_joints`] with the caller's preparation: a `memo` prepared for the same model spec and
/// inputs (its key says) spares the centre fit and the ROM; a new preparation is left in it.
pub fn run_joints_with(
    opts: &UpdateOptions,
    boards_dir: &Path,
    memo: &mut Option<JointPrep>,
    verbose: bool,
) -> anyhow::Result<StageOutcome> {
    let extract_dir = opts.extract_dir();
    let paths = JointPaths {
        pairs: opts.pair_dir.join("pairs.parquet"),
        presence: opts.pair_dir.join("presence.parquet"),
        modes: extract_dir.join("modes.parquet"),
        step1: boards_dir.join("boards.parquet"),
        step1_evidence: boards_dir.join("evidence.json"),
        measurements: opts.ingest_dir.join("measurements.parquet"),
    };
    let mut inputs = vec![
        paths.pairs.clone(),
        paths.presence.clone(),
        paths.modes.clone(),
        paths.step1.clone(),
        paths.measurements.clone(),
    ];
    if opts.model.enrich.is_some_and(is_board_mechanism) {
        inputs.push(paths.step1_evidence.clone());
        inputs.push(paths.measurements.clone());
    }
    let (board, spec) = step_spec(
        opts,
        "update_joints",
        inputs,
        &[("step", "joints"), ("posterior", "cut")],
        MANIFEST_JOINTS,
    )?;
    crate::stage::run(spec, opts.force, |prep| {
        joints_body(opts, &board, &paths, prep, memo, verbose)
    })
}

struct JointPaths {
    pairs: PathBuf,
    presence: PathBuf,
    modes: PathBuf,
    step1: PathBuf,
    step1_evidence: PathBuf,
    measurements: PathBuf,
}

/// Step 2's inputs as read: the bolted pairs, the step-1 posterior, a board mechanism's step-1
/// enrichment and covariate column.
struct JointInputs {
    pairs: Vec<PairRow>,
    presence: Vec<String>,
    step1: Step1,
    step1_enrichment: serde_json::Value,
    mode_rows: Vec<ModeRow>,
    covariate: Option<Vec<(String, Option<f64>)>>,
}

fn read_joint_inputs(
    opts: &UpdateOptions,
    paths: &JointPaths,
    pairs: Vec<PairRow>,
) -> anyhow::Result<JointInputs> {
    let step1 = read_step1(&paths.step1)?;
    let presence = read_presence(&paths.presence, "bolted")?;
    let board_mech = opts.model.enrich.filter(|m| is_board_mechanism(*m));
    let step1_enrichment = match board_mech {
        Some(_) => read_step1_enrichment(&paths.step1_evidence)?,
        None => serde_json::Value::Null,
    };
    let mode_rows = read_modes_table(&paths.modes)?;
    let covariate = match board_mech {
        Some(Mechanism::TemperatureStiffness) => match step1_enrichment["covariate"].as_str() {
            Some(column) => Some(read_covariate(&paths.measurements, column)?),
            None => None,
        },
        _ => None,
    };
    Ok(JointInputs {
        pairs,
        presence,
        step1,
        step1_enrichment,
        mode_rows,
        covariate,
    })
}

fn joints_body(
    opts: &UpdateOptions,
    board: &Board,
    paths: &JointPaths,
    prep: &crate::io::manifest::Prepared,
    memo: &mut Option<JointPrep>,
    verbose: bool,
) -> anyhow::Result<StageResult> {
    use crate::update::joints;
    let mut clock = PhaseClock::new("update joints", verbose);
    let mut findings = Findings::default();
    let pairs = read_pairs(&paths.pairs)?;
    if !pairs.iter().any(|p| p.setup == "bolted") {
        return no_bolted_data(opts, &paths.measurements, findings);
    }
    let inp = read_joint_inputs(opts, paths, pairs)?;
    let (step1_source, ev_source) = (
        paths.step1.display().to_string(),
        paths.step1_evidence.display().to_string(),
    );
    let labels = select_labels(
        &inp.pairs,
        "bolted",
        &opts.model.modes,
        &inp.presence,
        &mut findings,
    )?;
    let bolted_rows: Vec<&PairRow> = inp.pairs.iter().filter(|p| p.setup == "bolted").collect();
    let mut jm = joints::joint_models(
        board,
        &opts.model,
        &labels,
        &inp.pairs,
        &inp.step1,
        &step1_source,
        &inp.step1_enrichment,
        &mut findings,
    )?;
    clock.lap("models");
    let t_centre = std::time::Instant::now();
    let key = joint_prep_key(prep, &opts.model);
    let remembered = memo.take().filter(|m| m.key == key);
    let centre = match &remembered {
        Some(m) => m.centre.clone(),
        None => joints::fit_joint_centre_of(&jm, &labels, &bolted_rows)?,
    };
    if verbose {
        eprintln!(
            "joints: ROM centre {:?} = {centre:.4?} (ln, relative to the priors' centres), {} in {:.1} s",
            jm.enr.coordinates.iter().map(|c| c.name.as_str()).collect::<Vec<_>>(),
            if remembered.is_some() { "as prepared by the caller's previous run of the same step" } else { "fitted" },
            t_centre.elapsed().as_secs_f64()
        );
    }
    let c = joints::centred(
        &mut jm,
        &centre,
        &labels,
        &opts.model,
        &inp.mode_rows,
        &bolted_rows,
        &mut findings,
    )?;
    let bolted_rows: Vec<&PairRow> = bolted_rows.into_iter().chain(&c.new_rows).collect();
    clock.lap("centre_fit");
    let rom = match remembered {
        Some(m) => m.rom,
        None => rom_for(&jm.model, c.need, &c.log_axes, &opts.model)?,
    };
    *memo = Some(JointPrep {
        key,
        centre: centre.clone(),
        rom: rom.clone(),
    });
    rom_centre_check(&jm.model, &rom, c.need, &mut findings)?;
    clock.lap("rom_build");
    let measurements_source = paths.measurements.display().to_string();
    let mut jt = joints::joint_target(
        &jm,
        &c,
        &rom,
        &bolted_rows,
        &inp.mode_rows,
        (&inp.step1, &step1_source),
        (&inp.step1_enrichment, &ev_source),
        inp.covariate
            .as_deref()
            .map(|v| (v, measurements_source.as_str())),
        &opts.model,
        &opts.sampler,
        &mut findings,
    )?;
    let mut sopts = opts.clone();
    sopts.sampler = jt.sampler.clone();
    clock.lap("unit_data");
    // The units located for the weights with the step-1 posterior mean of the boards.
    let step1 = &inp.step1;
    let draws_mean: Vec<f64> = match step1.draws.first() {
        None => vec![],
        Some((_, d0)) => (0..d0.len())
            .map(|k| step1.draws.iter().map(|(_, d)| d[k]).sum::<f64>() / step1.draws.len() as f64)
            .collect(),
    };
    jt.target.errors.discrepancy = discrepancy_for(
        &jt.target,
        &draws_mean,
        // Off unless asked for (`--discrepancy-pct`): bolted, each measurement's joint
        // stiffness is already free, and a per-mode bias common to every assembly spans every
        // shift a common joint effect makes, so no refit could be told from it.
        opts.model.discrepancy_freq.unwrap_or(0.0),
        "joints",
        &mut findings,
    )?;
    let shape_weights = weigh_shapes(
        &mut jt.target,
        &opts.model.shape_weights,
        (&draws_mean, Some(&centre)),
        &c.labels.labels,
        opts.sampler.seed,
        "joints",
    )?;
    report_shape_weights(&shape_weights, "joints", verbose, &mut findings);
    clock.lap("shape_weights");
    let pb = crate::stage::progress_bar((sopts.sampler.runs * 1000) as u64, "joints");
    let (results, acceleration) = run_smc(
        &jt.target,
        &sopts.sampler,
        "joints",
        &jt.aux,
        Some(&centre),
        &progress_to(&pb),
        verbose,
    )?;
    pb.finish_and_clear();
    let sampler_seconds = clock.lap("sampler");
    check_surrogate_edges(&acceleration, &mut findings);
    joints::check_joint_box(
        (&jm, &c),
        &centre,
        &results,
        &jt.unit_names,
        &opts.model,
        verbose,
    )?;
    findings.push(joints::rom_posterior_finding(
        &jm.model, &jt.target, &results, c.need,
    ));
    let prov = provenance("update_joints", &prep.fingerprint);
    let tables = joints::joint_tables(&jm, &jt, &results, &c.labels, &inp.step1, opts.sampler.runs);
    let mut outputs = write_joint_tables(&opts.out, &tables, &results, &prov)?;
    clock.lap("tables");
    let (res, lost) = residuals(
        &jt.target,
        &jt.all_pred,
        &c.all.labels,
        &c.labels.labels,
        &jt.units_all,
        &results,
        "bolted",
        opts.sampler.residual_draws,
        None,
    );
    lost_finding(&lost, &mut findings);
    let p = opts.out.join("residuals.parquet");
    write_residuals(&p, &res, &prov)?;
    outputs.push(p);
    let p = opts.out.join("rom.npz");
    crate::io::atomic::write_bytes(&p, &jt.target.predictor.rom.to_npz_bytes())?;
    outputs.push(p);
    let ev = joints::joint_evidence(
        (&jm, &c),
        &jt.target,
        &results,
        &centre,
        &inp.step1_enrichment,
        &shape_weights,
        &opts.model,
    )?;
    let p = opts.out.join("evidence.json");
    crate::io::atomic::write_bytes(&p, serde_json::to_string_pretty(&ev)?.as_bytes())?;
    outputs.push(p);
    clock.lap("residuals");
    finish(
        &sopts,
        findings,
        outputs,
        &results,
        &tables.summary,
        ev,
        sampler_seconds,
        &c.labels.labels,
        verbose,
        "update joints",
        &acceleration,
        &clock,
    )
}

/// Wall time per phase of an update step: printed with `--verbose` as each phase ends, and
/// kept in the manifest's summary (`phase_seconds`), never in an output table (outputs stay
/// byte-identical between runs). Where the time goes is an acceptance point of the updating.
struct PhaseClock {
    last: std::time::Instant,
    laps: Vec<(&'static str, f64)>,
    verbose: bool,
    what: &'static str,
}

impl PhaseClock {
    fn new(what: &'static str, verbose: bool) -> PhaseClock {
        PhaseClock {
            last: std::time::Instant::now(),
            laps: vec![],
            verbose,
            what,
        }
    }

    /// End the phase `name` now; returns its seconds.
    fn lap(&mut self, name: &'static str) -> f64 {
        let now = std::time::Instant::now();
        let s = now.duration_since(self.last).as_secs_f64();
        self.last = now;
        if self.verbose {
            eprintln!("{}: {name} {s:.1} s", self.what);
        }
        self.laps.push((name, s));
        s
    }

    fn summary(&self) -> serde_json::Value {
        serde_json::Value::Object(
            self.laps
                .iter()
                .map(|(n, s)| (n.to_string(), serde_json::json!(s)))
                .collect(),
        )
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

#[cfg(test)]
mod joint_prep_tests {
    use super::*;
    use crate::bayes::target::ErrorPrior;
    use crate::io::manifest::{FileHash, Prepared};

    fn prepared(input_blake3: &str) -> Prepared {
        Prepared {
            spec: StageSpec {
                stage: "update_joints".into(),
                inputs: vec![],
                input_base: PathBuf::new(),
                config: serde_json::Value::Null,
                seed: Some(1),
                manifest_path: PathBuf::new(),
            },
            inputs: vec![FileHash {
                path: "pairs.parquet".into(),
                blake3: input_blake3.into(),
                bytes: 1,
            }],
            config_blake3: String::new(),
            fingerprint: String::new(),
        }
    }

    fn spec(rom_box: f64, enrich: Mechanism) -> ModelSpec {
        ModelSpec {
            modes: vec![],
            params: vec![],
            prior_width: 1.0,
            sigma_scale: 0.5,
            sigma_prior: Default::default(),
            lkj_eta: 2.0,
            eps: ErrorPrior::Fixed { value: 1e-3 },
            delta: None,
            rom_box,
            box_tolerance: 0.01,
            rom_max_basis: None,
            enrich: Some(enrich),
            enrich_joint: None,
            enrich_covariate: None,
            enrich_location: None,
            enrich_new_modes: false,
            model_error: false,
            discrepancy_freq: None,
            hold_out_boards: vec![],
            board_coordinates: Default::default(),
            mass_floor_rel: ModelSpec::DEFAULT_MASS_FLOOR_REL,
            shape_weights: Default::default(),
        }
    }

    /// A preparation is keyed by the inputs' content and the model spec (the sampler's
    /// parameters are not part of it): another model option or input content changes it.
    #[test]
    fn the_preparation_key_is_the_inputs_and_the_model_spec() {
        let key = joint_prep_key(&prepared("aa"), &spec(0.2, Mechanism::JointRotation));
        assert_eq!(
            joint_prep_key(&prepared("aa"), &spec(0.2, Mechanism::JointRotation)),
            key
        );
        assert_ne!(
            joint_prep_key(&prepared("aa"), &spec(0.3, Mechanism::JointRotation)),
            key
        );
        assert_ne!(
            joint_prep_key(&prepared("aa"), &spec(0.2, Mechanism::JointMass)),
            key
        );
        assert_ne!(
            joint_prep_key(&prepared("ab"), &spec(0.2, Mechanism::JointRotation)),
            key
        );
    }
}

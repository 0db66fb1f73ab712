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

use crate::bayes::modal::{CovariateEffect, ModalPredictor};
use crate::bayes::population::PopulationPrior;
use crate::bayes::shape_weight::ShapeWeight;
use crate::bayes::smc::{self, StageInfo};
use crate::bayes::target::{
    Compose, ErrorModel, ErrorPrior, JointsCovariate, ModalTarget, PerMass,
};
use crate::fem::params::names;
use crate::fem::{Board, FeModel, Setup};
use crate::findings::{Finding, Findings, Severity};
use crate::io::manifest::StageSpec;
use crate::io::modes_table::read_modes_table;
use crate::io::tables::update::{
    provenance, read_masses, read_pairs, read_presence, read_specimen_thickness, read_step1,
    read_step1_enrichment, step1_point_mass, write_draws, write_residuals, write_stages,
    write_summary, write_table, BOARDS, JOINTS, POPULATION, POPULATION_JOINTS,
};
use crate::io::tables::{self, Cols};
use crate::modal::rows::PairRow;
use crate::stage::{exit, StageOutcome, StageResult};
use crate::update::centre::fit_centre;
use crate::update::enrichment::{
    board_enrichment, is_board_mechanism, joint_enrichment, BoardContext, BoardEffect,
    JointContext, Mechanism,
};
use crate::update::new_modes::{match_modes, pair_new_modes};
use crate::update::posterior::{
    convergence_finding, discrepancy_columns, discrepancy_json, discrepancy_values, evidence_json,
    lost_finding, population_columns, residuals, DrawTable, SummaryRow,
};
use crate::update::prepare::JointPrep;
use crate::update::problem::{
    all_labels, core_thickness_mass, discrepancy_for, identified_modes, mass_obs, match_points,
    model_error_prior, modes_needed, report_shape_weights, select_labels, shape_map, thickness_obs,
    unit_and_residual_data, weigh_shapes, BoardCoordinates, Labels, ModelSpec,
};
use crate::update::rom_box::{
    rom_box_check, rom_centre_check, rom_for, rom_posterior_check, RomBoxViolation, MAX_ROM_BOX,
};
use crate::update::sampler::{
    box_violations, check_surrogate_edges, particles_of, run_smc, Acceleration, SamplerParams,
};
use anyhow::{anyhow, bail, Context};
use arrow::array::{ArrayRef, Float64Array, Int32Array, StringArray};
use arrow::datatypes::DataType;
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::Arc;

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
/// The numeric column `column` of measurements.parquet for the measurements `used`, as
/// offsets from their mean (returned too). A used measurement without a value is a warning
/// and sits at the mean (offset 0), so the refit keeps the baseline's data.
fn covariate_offsets(
    path: &Path,
    column: &str,
    used: &BTreeSet<&str>,
    findings: &mut Findings,
) -> anyhow::Result<(BTreeMap<String, f64>, f64)> {
    let mut values: BTreeMap<String, f64> = BTreeMap::new();
    let mut missing = vec![];
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let mid = c.str("measurement_id")?;
        let col = b.column_by_name(column).ok_or_else(|| {
            anyhow!(
                "{}: no column {column:?} (the covariate of the enrichment); columns: {}",
                path.display(),
                b.schema()
                    .fields()
                    .iter()
                    .map(|f| f.name().as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        })?;
        let col = arrow::compute::cast(col, &DataType::Float64).with_context(|| {
            format!(
                "{}: column {column:?} is not numeric (expected a number per measurement)",
                path.display()
            )
        })?;
        let a = col
            .as_any()
            .downcast_ref::<Float64Array>()
            .ok_or_else(|| anyhow!("{}: column {column:?}: expected float64", path.display()))?;
        for i in 0..b.num_rows() {
            let m = mid.value(i);
            if !used.contains(m) {
                continue;
            }
            if arrow::array::Array::is_valid(a, i) && a.value(i).is_finite() {
                values.insert(m.to_string(), a.value(i));
            } else {
                missing.push(m.to_string());
            }
        }
    }
    for m in used {
        if !values.contains_key(*m) && !missing.iter().any(|x| x == m) {
            missing.push(m.to_string());
        }
    }
    if values.is_empty() {
        bail!(
            "{}: column {column:?} has no value for any measurement used; nothing to refit against",
            path.display()
        );
    }
    if !missing.is_empty() {
        findings.push(Finding::new(
            Severity::Warning,
            "update.covariate_missing",
            format!(
                "{} measurement(s) have no {column}: {}; taken at the mean of the others",
                missing.len(),
                missing.join(", ")
            ),
        ));
    }
    let mean = values.values().sum::<f64>() / values.len() as f64;
    Ok((
        values.into_iter().map(|(k, v)| (k, v - mean)).collect(),
        mean,
    ))
}

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
    crate::stage::run(spec, opts.force, |prep| {
        // One attempt at the ROM box `opts.model.rom_box`; `carried` are findings of an earlier one.
        let attempt = |opts: &UpdateOptions, carried: &[Finding]| -> anyhow::Result<StageResult> {
            let mut clock = PhaseClock::new("update boards", verbose);
            let mut findings = Findings::default();
            findings.0.extend(carried.iter().cloned());
            let pairs = read_pairs(&pairs_path)?;
            let presence = read_presence(&presence_path, "free")?;
            let labels =
                select_labels(&pairs, "free", &opts.model.modes, &presence, &mut findings)?;
            // Boards measured in thickness: the core thickness is a board parameter (exact in
            // the model), each board's reading an observation of it. The sheet gives the
            // overall thickness a micrometer reads over the copper (a finished board's, as a
            // fabrication drawing gives it): the board file's copper layers are taken off.
            let copper_m = board.copper_thickness_m();
            let thickness_m: BTreeMap<String, f64> = read_specimen_thickness(&specimens_path)?
                .into_iter()
                .map(|(b, h)| (b, h - copper_m))
                .collect();
            let with_thickness;
            let opts = if thickness_m.is_empty()
                || opts.model.params.iter().any(|p| p == names::CORE_THICKNESS)
            {
                opts
            } else {
                let mut o = opts.clone();
                o.model.params.push(names::CORE_THICKNESS.into());
                with_thickness = o;
                &with_thickness
            };
            let model_opts = crate::fem::ModelOptions {
                core_thickness: !thickness_m.is_empty(),
            };
            let mut model = FeModel::build_with(&board, Setup::Free, &board.mesh, model_opts)?;
            let board_nominal = model.nominal_params();
            // The board's own mass (the balance weighs an added mass with it).
            let nominal_mass_g = model.total_mass_kg(&board_nominal)? * 1e3;
            let enrichment = opts
                .model
                .enrich
                .map(|m| {
                    board_enrichment(
                        m,
                        BoardContext {
                            board_mass_kg: 1e-3 * nominal_mass_g,
                            location_m: opts.model.enrich_location,
                        },
                    )
                    .map_err(|e| anyhow!("--enrich: {e}"))
                })
                .transpose()?;
            // A point mechanism's parameter joins the updated ones on a logarithmic coordinate.
            let mut param_names = opts.model.params.clone();
            let mut log_axes: Vec<(String, f64)> = vec![];
            if let Some(BoardEffect::PointMass {
                parameter,
                x_m,
                y_m,
                reference_kg,
                log_box,
            }) = enrichment.as_ref().map(|e| &e.effect)
            {
                model
                    .add_point_mass_param(parameter, *x_m, *y_m, *reference_kg)
                    .map_err(|e| anyhow!("--enrich added_mass at ({x_m}, {y_m}) m: {e}"))?;
                param_names.push(parameter.clone());
                log_axes.push((parameter.clone(), *log_box));
            }
            let nominal = model.nominal_params();
            let mut updated = vec![];
            for p in &param_names {
                updated.push(nominal.position(p).map_err(|_| {
                    anyhow!(
                        "--params: {p:?} is not a parameter of the model; expected some of {:?}",
                        nominal.names
                    )
                })?);
            }
            let reference: Vec<f64> = updated.iter().map(|&i| nominal.values[i]).collect();
            if let Some((i, _)) = reference.iter().enumerate().find(|(_, v)| **v == 0.0) {
                bail!(
                    "--params: {} has nominal value 0; relative updating needs a non-zero nominal",
                    param_names[i]
                );
            }
            let all = all_labels(&pairs, "free", 40, &mut findings);
            let need = modes_needed(&labels, &all);
            clock.lap("models");
            let rom = rom_for(&model, need, &log_axes, &opts.model)?;
            rom_centre_check(&model, &rom, need, &mut findings)?;
            clock.lap("rom_build");
            if opts.model.rom_box > ModelSpec::DEFAULT_ROM_BOX {
                let worst = rom_box_check(&model, &rom, opts.model.rom_box, need)?;
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
            let model_error = opts
                .model
                .model_error
                .then(|| model_error_prior(&board, &board_nominal, &labels, &all))
                .transpose()?;
            let point_masses: Vec<usize> = log_axes
                .iter()
                .map(|(n, _)| rom.map.names.iter().position(|m| m == n).unwrap_or(0))
                .collect();
            let thickness = core_thickness_mass(&model)?;
            let predictor = ModalPredictor::new(rom.clone(), &labels.model_mode, nominal_mass_g)?
                .with_point_masses(point_masses.clone())
                .with_core_thickness(thickness);
            let all_pred = ModalPredictor::new(rom.clone(), &all.model_mode, nominal_mass_g)?
                .with_point_masses(point_masses)
                .with_core_thickness(thickness);
            // Units: every board with free-free pairs or a mass.
            let masses = read_masses(&masses_path)?;
            // The enrichment's covariate per free-free measurement, as offsets from their mean.
            let (cov_offsets, covariate) = match enrichment.as_ref().and_then(|e| match &e.effect {
                BoardEffect::Covariate {
                    coefficient,
                    scaled,
                } => Some((e, coefficient, scaled)),
                BoardEffect::PointMass { .. } => None,
            }) {
                Some((e, coefficient, scaled)) => {
                    let column = opts.model.enrich_covariate.clone().ok_or_else(|| {
                        anyhow!("--enrich {}: needs the covariate column", e.mechanism.id())
                    })?;
                    let free: BTreeSet<&str> = pairs
                        .iter()
                        .filter(|p| p.setup == "free")
                        .map(|p| p.measurement_id.as_str())
                        .collect();
                    let (offsets, reference) =
                        covariate_offsets(&measurements_path, &column, &free, &mut findings)?;
                    let scaled: Vec<usize> = scaled
                        .iter()
                        .map(|n| {
                            rom.map.names.iter().position(|m| m == n).ok_or_else(|| {
                                anyhow!(
                                    "--enrich {}: the model has no parameter {n:?}",
                                    e.mechanism.id()
                                )
                            })
                        })
                        .collect::<anyhow::Result<_>>()?;
                    let cov = CovariateEffect {
                        name: coefficient.clone(),
                        covariate: column,
                        reference,
                        scaled,
                    };
                    (Some(offsets), Some(cov))
                }
                None => (None, None),
            };
            let wanted: BTreeSet<(String, i32)> = pairs
                .iter()
                .filter(|p| p.setup == "free")
                .map(|p| (p.measurement_id.clone(), p.mode))
                .collect();
            let mode_rows = read_modes_table(&modes_path)?;
            let shapes = shape_map(&mode_rows, &wanted);
            let mut board_ids: BTreeSet<String> = pairs
                .iter()
                .filter(|p| p.setup == "free")
                .map(|p| p.board_id.clone())
                .collect();
            board_ids.extend(masses.keys().cloned());
            for b in &opts.model.hold_out_boards {
                if !board_ids.contains(b) {
                    bail!(
                    "--hold-out: board {b} has no paired free-free mode and no balance reading in this campaign (boards: {})",
                    board_ids.iter().cloned().collect::<Vec<_>>().join(", ")
                );
                }
                findings.push(Finding::new(
                Severity::Info,
                "update.board_held_out",
                format!("board {b} is held out (--hold-out): its modes and mass are not used; the report compares its measurements with the new-board prediction"),
            ));
            }
            board_ids.retain(|b| !opts.model.hold_out_boards.contains(b));
            if board_ids.is_empty() {
                bail!("--hold-out leaves no board to update");
            }
            // The balance informs the mass parameters: mass_scale, and an added mass.
            let mass_updated =
                opts.model.params.iter().any(|p| p == names::MASS_SCALE) || !log_axes.is_empty();
            let use_shapes = opts.model.delta.is_some();
            let mut units = vec![];
            let mut units_all = vec![];
            let mut unit_names = vec![];
            for b in &board_ids {
                let rows: Vec<&PairRow> = pairs
                    .iter()
                    .filter(|p| p.setup == "free" && &p.board_id == b)
                    .collect();
                let (mut data, (data_all, meta_all)) = unit_and_residual_data(
                    &rows,
                    &labels,
                    &all,
                    use_shapes,
                    (&model, &rom, &shapes),
                    cov_offsets.as_ref(),
                    &mut findings,
                )?;
                data.mass = match masses.get(b) {
                    Some(m) if mass_updated => {
                        mass_obs(m, b, opts.model.mass_floor_rel, &mut findings)
                    }
                    Some(_) => None,
                    None => {
                        findings.push(Finding::new(
                        Severity::Warning,
                        "update.not_weighed",
                        format!("board {b} was never weighed (no stable balance reading): its mass is informed by the population only"),
                    ));
                        None
                    }
                };
                if data.freq.is_empty() && data.mass.is_none() {
                    findings.push(Finding::new(
                    Severity::Warning,
                    "update.board_no_data",
                    format!("board {b} has no paired free-free mode to update and no usable mass; left out of step 1"),
                ));
                    continue;
                }
                if data.freq.is_empty() {
                    findings.push(Finding::new(
                    Severity::Warning,
                    "update.board_no_modes",
                    format!("board {b} has no paired free-free mode to update; only its mass informs it"),
                ));
                }
                // Modes missing in some measurements: reported, the rest are used.
                let meas: BTreeSet<&str> = rows.iter().map(|p| p.measurement_id.as_str()).collect();
                for (m, l) in labels.labels.iter().enumerate() {
                    let n = data.freq.iter().filter(|f| f.mode == m).count();
                    if n > 0 && n < meas.len() {
                        findings.push(Finding::new(
                        Severity::Info,
                        "update.mode_missing",
                        format!("board {b}: mode {l:?} is paired in {n} of {} measurements; the others contribute no term for it", meas.len()),
                    ));
                    }
                }
                units.push(data);
                units_all.push((data_all, meta_all));
                unit_names.push(b.clone());
            }
            if units.is_empty() {
                bail!("no board has data for step 1 (no paired free-free mode and no mass)");
            }
            let d = updated.len();
            let d0 = opts.model.params.len();
            let mut prior = PopulationPrior {
                mu_mean: vec![0.0; d0],
                mu_sd: vec![opts.model.prior_width; d0],
                sigma_scale: vec![opts.model.sigma_scale; d0],
                // The board parameters' family; an enrichment's coordinate stays half-normal
                // (a coefficient probably common to all boards).
                sigma_prior: vec![opts.model.sigma_prior; d0],
                lkj_eta: opts.model.lkj_eta,
            };
            if let Some(e) = &enrichment {
                // The board's coordinate (a coefficient, or ln of an added mass): population
                // mean ~ the mechanism's prior, and a board-to-board sd of a fifth of that
                // prior's.
                prior.mu_mean.push(e.prior_mean);
                prior.mu_sd.push(e.prior_sd);
                prior.sigma_scale.push(0.2 * e.prior_sd);
            }
            let log: Vec<bool> = (0..d).map(|k| k >= d0).collect();
            // Moduli per unit mass scale, where the mass scale is updated too.
            let mass = param_names[..d0]
                .iter()
                .position(|p| p == crate::fem::params::names::MASS_SCALE);
            let per_mass = match (opts.model.board_coordinates, mass) {
                (BoardCoordinates::PerMass, Some(mass)) => Some(PerMass {
                    mass,
                    specific: (0..d)
                        .map(|k| k < d0 && k != mass && param_names[k].ends_with("_pa"))
                        .collect(),
                }),
                _ => None,
            };
            if opts.model.board_coordinates == BoardCoordinates::PerMass && per_mass.is_none() {
                findings.push(Finding::new(
                    Severity::Info,
                    "update.board_coordinates",
                    format!("moduli per unit mass scale need {} among the updated parameters ({}): the population is formed in the parameters themselves", crate::fem::params::names::MASS_SCALE, param_names[..d0].join(", ")),
                ));
            }
            // The population's coordinates: names and the values x = 0 stands for.
            let (pop_names, pop_reference): (Vec<String>, Vec<f64>) = (0..d)
                .map(|k| match &per_mass {
                    Some(pm) if pm.is_specific(k) => (
                        crate::fem::params::names::per_mass_scale(&param_names[k]),
                        reference[k] / reference[pm.mass],
                    ),
                    _ => (param_names[k].clone(), reference[k]),
                })
                .unzip();
            let mut target = ModalTarget {
                predictor,
                compose: Compose::Boards {
                    updated: updated.clone(),
                    reference: reference.clone(),
                    log: log.clone(),
                    per_mass,
                },
                prior,
                errors: ErrorModel {
                    n_modes: labels.labels.len(),
                    eps: opts.model.eps,
                    delta: opts.model.delta,
                    model_error_sd: model_error.as_ref().map(|m| m.sd_updated.clone()),
                    discrepancy: None,
                },
                units,
                covariate: covariate.clone(),
                subspaces: vec![],
                coord_obs: thickness_obs(
                    &param_names,
                    board.core.thickness_m,
                    &unit_names,
                    &thickness_m,
                    opts.model.rom_box,
                    &mut findings,
                ),
            };
            target.errors.discrepancy = discrepancy_for(
                &target,
                &[],
                opts.model
                    .discrepancy_freq
                    .unwrap_or(crate::bayes::discrepancy::FREE_FIDELITY_FREQ),
                "boards",
                &mut findings,
            )?;
            // The surrogates model a unit's terms as a function of its ROM parameters alone; with
            // a covariate the terms also follow the unit's coefficient, so the ROM runs directly.
            let mut sopts = opts.clone();
            sopts.sampler.surrogate &= target.covariate.is_none();
            clock.lap("unit_data");
            let shape_weights = weigh_shapes(
                &mut target,
                &opts.model.shape_weights,
                (&[], None),
                &labels.labels,
                opts.sampler.seed,
                "boards",
            )?;
            report_shape_weights(&shape_weights, "boards", verbose, &mut findings);
            clock.lap("shape_weights");
            let (results, acceleration) =
                run_smc(&target, &sopts.sampler, "boards", &[], None, verbose)?;
            let sampler_seconds = clock.lap("sampler");
            check_surrogate_edges(&acceleration, &mut findings);
            let violations = box_violations(
                &results,
                &unit_names,
                &param_names,
                |x| target.compose.relative_params(x),
                |k, x| match log_axes.get(k.wrapping_sub(d0)) {
                    Some((_, w)) if k >= d0 => x.abs() <= *w,
                    _ => x.abs() <= opts.model.rom_box,
                },
                opts.model.box_tolerance,
            );
            if !violations.is_empty() {
                // The half-width that holds every sampled value of the relative coordinates, with
                // a margin, to the next 5 %.
                let mut reach = 0.0f64;
                for r in &results {
                    for p in &r.particles {
                        for x in &p.x {
                            let x = target.compose.relative_params(x);
                            for (k, v) in x.iter().enumerate() {
                                if k < d0 || log_axes.get(k.wrapping_sub(d0)).is_none() {
                                    reach = reach.max(v.abs());
                                }
                            }
                        }
                    }
                }
                return Err(RomBoxViolation {
                message: format!(
                    "the posterior presses against the ROM's ±{:.0} % box (relative to the board file's nominal values):\n  {}\nThe ROM is not verified there. Re-centre the model: put the posterior means in the board file (--model) and run again, or leave an uninformed parameter out (--params).",
                    100.0 * opts.model.rom_box,
                    violations.join("\n  ")
                ),
                needed_half_width: (reach * 1.15 / 0.05).ceil() * 0.05,
            }
            .into());
            }
            // Outputs.
            let prov = provenance("update_boards", &prep.fingerprint);
            let mut outputs = vec![];
            let (pcols, pop_of) =
                population_columns(&target, &pop_names, &pop_reference, &labels.labels);
            let mut pop = DrawTable::new(&pcols);
            let mut bcols: Vec<(String, String)> = param_names
                .iter()
                .map(|p| (p.clone(), String::new()))
                .collect();
            bcols.push(("mass_g".into(), "g".into()));
            // A board enrichment's coefficient per board (step 2 carries it with the draw).
            if let Some(c) = &covariate {
                bcols.push((c.name.clone(), format!("1/(unit of {})", c.covariate)));
            }
            let mut boards = DrawTable::new(&bcols);
            for (r, i, p) in particles_of(&results) {
                pop.push(r, i, None, &pop_of(&p.g));
                for (b, name) in unit_names.iter().enumerate() {
                    let v = target.values(&p.aux, b, &p.x[b]);
                    let mut row: Vec<f64> = updated.iter().map(|&k| v[k]).collect();
                    row.push(target.predictor.mass_g(&v));
                    if covariate.is_some() {
                        row.push(p.x[b][d]);
                    }
                    boards.push(r, i, Some(name), &row);
                }
            }
            let mut summary = pop.summarize(opts.sampler.runs, true);
            summary.extend(boards.summarize(opts.sampler.runs, true));
            let p = opts.out.join("population.parquet");
            write_draws(&p, &POPULATION, &pop, false, &prov)?;
            outputs.push(p);
            let p = opts.out.join("boards.parquet");
            write_draws(&p, &BOARDS, &boards, true, &prov)?;
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
                &target,
                &all_pred,
                &all.labels,
                &labels.labels,
                &units_all,
                &results,
                "free",
                opts.sampler.residual_draws,
                model_error.as_ref().map(|m| m.sd.as_slice()),
            );
            lost_finding(&lost, &mut findings);
            let p = opts.out.join("residuals.parquet");
            write_residuals(&p, &res, &prov)?;
            outputs.push(p);
            let p = opts.out.join("rom.npz");
            crate::io::atomic::write_bytes(&p, &target.predictor.rom.to_npz_bytes())?;
            outputs.push(p);
            let log_z: Vec<f64> = results.iter().map(|r| r.log_evidence).collect();
            let mut ev = evidence_json(&log_z, "boards (step 1)");
            match (&enrichment, &covariate) {
                (Some(e), Some(c)) => {
                    if let BoardEffect::Covariate {
                        coefficient,
                        scaled,
                    } = &e.effect
                    {
                        ev["enrichment"] = serde_json::json!({
                            "mechanism": e.mechanism,
                            "coefficient": coefficient,
                            "scaled": scaled,
                            "covariate": c.covariate,
                            "covariate_reference": c.reference,
                            "prior_mean": e.prior_mean,
                            "prior_sd": e.prior_sd,
                        });
                    }
                }
                (Some(e), None) => {
                    ev["enrichment"] = serde_json::to_value(e)?;
                }
                _ => {}
            }
            ev["model_error"] = serde_json::to_value(&model_error)?;
            ev["shape_weights"] = serde_json::to_value(&shape_weights)?;
            ev["discrepancy"] = discrepancy_json(&target, &labels.labels);
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
        };
        widen_rom_box_once(opts, |o, carried| attempt(o, carried))
    })
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

static JOINT_PREP: std::sync::Mutex<Option<JointPrep>> = std::sync::Mutex::new(None);

/// The key of [`JointPrep`]: the step's input files by content and its configuration without
/// the sampler's options (`smc`, `runs`, `seed`).
fn joint_prep_key(prep: &crate::io::manifest::Prepared) -> String {
    let mut config = prep.spec.config.clone();
    if let Some(o) = config.as_object_mut() {
        for k in ["smc", "runs", "seed"] {
            o.remove(k);
        }
    }
    let mut h = blake3::Hasher::new();
    for f in &prep.inputs {
        h.update(f.path.as_bytes());
        h.update(&[0]);
        h.update(f.blake3.as_bytes());
        h.update(&[0]);
    }
    h.update(config.to_string().as_bytes());
    h.finalize().to_hex().to_string()
}

/// Step 2: joints, bolted, the modular posterior over the step-1 draws.
pub fn run_joints(
    opts: &UpdateOptions,
    boards_dir: &Path,
    verbose: bool,
) -> anyhow::Result<StageOutcome> {
    let extract_dir = opts.extract_dir();
    let pairs_path = opts.pair_dir.join("pairs.parquet");
    let presence_path = opts.pair_dir.join("presence.parquet");
    let modes_path = extract_dir.join("modes.parquet");
    let step1_path = boards_dir.join("boards.parquet");
    let measurements_path = opts.ingest_dir.join("measurements.parquet");
    let mut inputs = vec![
        pairs_path.clone(),
        presence_path.clone(),
        modes_path.clone(),
        step1_path.clone(),
        measurements_path.clone(),
    ];
    if opts
        .model
        .enrich
        .is_some_and(crate::diagnose::library::is_board_mechanism)
    {
        inputs.push(boards_dir.join("evidence.json"));
        inputs.push(opts.ingest_dir.join("measurements.parquet"));
    }
    let (board, spec) = step_spec(
        opts,
        "update_joints",
        inputs,
        &[("step", "joints"), ("posterior", "cut")],
        MANIFEST_JOINTS,
    )?;
    crate::stage::run(spec, opts.force, |prep| {
        let mut clock = PhaseClock::new("update joints", verbose);
        let mut findings = Findings::default();
        let pairs = read_pairs(&pairs_path)?;
        if !pairs.iter().any(|p| p.setup == "bolted") {
            return no_bolted_data(opts, &measurements_path, findings);
        }
        let step1 = read_step1(&step1_path)?;
        let presence = read_presence(&presence_path, "bolted")?;
        let labels = select_labels(
            &pairs,
            "bolted",
            &opts.model.modes,
            &presence,
            &mut findings,
        )?;
        let bolted_rows: Vec<&PairRow> = pairs.iter().filter(|p| p.setup == "bolted").collect();
        let band_top_hz = bolted_rows.iter().map(|p| p.freq_hz).fold(0.0, f64::max);
        // A board mechanism (its step-1 refit is `boards_dir`) keeps the baseline joints.
        let board_mech = opts
            .model
            .enrich
            .filter(|m| crate::diagnose::library::is_board_mechanism(*m));
        let enr = joint_enrichment(
            &board,
            opts.model.enrich.filter(|_| board_mech.is_none()),
            opts.model.enrich_joint,
            JointContext {
                band_top_hz,
                k_con_prior_sd: opts.model.prior_width,
            },
        )
        .map_err(|e| anyhow!("update joints --enrich: {e}"))?;
        // Where step 1 updated the core thickness, each board's draw carries it.
        let model_opts = crate::fem::ModelOptions {
            core_thickness: step1.params.iter().any(|p| p == names::CORE_THICKNESS),
        };
        let mut model = FeModel::build_with(
            &board,
            Setup::Bolted(enr.joint_model.clone()),
            board.mesh_for(&Setup::bolted()),
            model_opts,
        )?;
        // The board mechanism's step-1 enrichment (its evidence.json), and a point mass it
        // added to the boards: the same point mass in the bolted model, its value from each
        // board's step-1 draw like every board parameter.
        let step1_enrichment = match board_mech {
            Some(_) => read_step1_enrichment(&boards_dir.join("evidence.json"))?,
            None => serde_json::Value::Null,
        };
        let point_mass = step1_point_mass(&step1_enrichment, &step1, &step1_path)?;
        let mut baseline = FeModel::build_with(
            &board,
            Setup::bolted(),
            board.mesh_for(&Setup::bolted()),
            model_opts,
        )?;
        if let Some(pm) = &point_mass {
            for m in [&mut model, &mut baseline] {
                m.add_point_mass_param(&pm.parameter, pm.x_m, pm.y_m, pm.mean_kg)
                    .map_err(|e| anyhow!("{}: the step-1 added mass: {e}", step1_path.display()))?;
            }
        }
        let nominal = model.nominal_params();
        let mut board_params = vec![];
        for p in &step1.params {
            board_params.push(nominal.position(p).map_err(|_| {
                anyhow!(
                    "{}: step-1 parameter {p:?} is not a parameter of the bolted model ({:?})",
                    step1_path.display(),
                    nominal.names
                )
            })?);
        }
        let reference: Vec<(usize, f64)> = enr
            .reference
            .iter()
            .map(|(n, v)| Ok((nominal.position(n)?, *v)))
            .collect::<Result<_, crate::fem::FemError>>()?;
        let coords: Vec<Vec<(usize, f64)>> = enr
            .coordinates
            .iter()
            .map(|c| {
                c.acts_on
                    .iter()
                    .map(|(n, a)| Ok((nominal.position(n)?, *a)))
                    .collect::<Result<Vec<_>, crate::fem::FemError>>()
            })
            .collect::<Result<_, _>>()?;
        // The boards' posterior means (for the joint's centre).
        let d1 = step1.block();
        let nd = step1.draws.len() as f64;
        let mut board_mean: BTreeMap<String, f64> = BTreeMap::new();
        for (k, p) in step1.params.iter().enumerate() {
            let m = step1
                .draws
                .iter()
                .map(|(_, v)| {
                    (0..step1.board_ids.len())
                        .map(|b| v[b * d1 + k])
                        .sum::<f64>()
                })
                .sum::<f64>()
                / (nd * step1.board_ids.len() as f64);
            board_mean.insert(p.clone(), m);
        }
        let with_board_mean = |mut p: crate::fem::Params| {
            for (name, v) in &board_mean {
                if let Ok(i) = p.position(name) {
                    p.values[i] = *v;
                }
            }
            p
        };
        // Reference shapes: the paired model modes of the baseline at the boards' mean.
        let points = match_points(&board);
        let all = all_labels(&pairs, "bolted", 40, &mut findings);
        let n_ref = modes_needed(&labels, &all);
        let extra_modes = if enr.joint_model.has_fixture() { 3 } else { 2 };
        let n_track = n_ref + extra_modes;
        let base_modes = baseline.modes(&with_board_mean(baseline.nominal_params()), n_ref)?;
        let w_all = baseline.w_at(&base_modes, &points)?;
        let pick =
            |idx: &[usize]| faer::Mat::from_fn(points.len(), idx.len(), |i, j| w_all[(i, idx[j])]);
        let w_labels = pick(&labels.model_mode);
        let mut p_base = with_board_mean(nominal.clone());
        for &(i, v) in &reference {
            p_base.values[i] = v;
        }
        let spans: Vec<f64> = enr
            .coordinates
            .iter()
            .enumerate()
            .map(|(k, c)| {
                if k == 0 {
                    opts.model.prior_width.max(1.0) * 3.0
                } else {
                    3.0 * c.prior_sd
                }
            })
            .collect();
        clock.lap("models");
        let t_centre = std::time::Instant::now();
        // All coordinates are fitted to the median frequencies (k_con trades off against
        // k_rot, one joint's ratio against the common k_con); then an enrichment's own
        // coordinates are kept within half their ROM half-width of their prior's centre, and
        // k_con is refitted with them held there. Left free, they ran to the box edge in the
        // lab's scenarios (a fixture resonance crossing the modes, one joint's ratio, a flat
        // direction of k_rot), which left the prior's centre outside the ROM's box and the
        // sampler with no particle the ROM could evaluate.
        //
        // Every joint's contrast (`joint_stiffness_per_joint` with no joint named) stays at 0,
        // equal joints: fitted to the median frequencies they have no common direction the
        // data fix (their mean is the prior's alone), and a typical assembly has no loose
        // bolt.
        let prep_key = joint_prep_key(prep);
        let remembered = JOINT_PREP
            .lock()
            .ok()
            .and_then(|m| m.as_ref().filter(|m| m.key == prep_key).cloned());
        let n_fit = if enr.every_joint() { 1 } else { coords.len() };
        let centre = match &remembered {
            Some(m) => m.centre.clone(),
            None => fit_centre(
                &model,
                &p_base,
                &coords,
                &spans,
                &enr,
                n_fit,
                (&labels, &bolted_rows),
                (&w_labels, &points),
                n_track,
            )?,
        };
        if verbose {
            eprintln!(
                "joints: ROM centre {:?} = {centre:.4?} (ln, relative to the priors' centres), {} in {:.1} s",
                enr.coordinates.iter().map(|c| c.name.as_str()).collect::<Vec<_>>(),
                if remembered.is_some() { "remembered from this process's previous run of the same step" } else { "fitted" },
                t_centre.elapsed().as_secs_f64()
            );
        }
        // The ROM's centre: the reference joint values moved to the fitted coordinates (the
        // board parameters stay at the board file's nominal values).
        let mut rom_centre = nominal.clone();
        for &(i, v) in &reference {
            rom_centre.values[i] = v;
        }
        for (k, acts) in coords.iter().enumerate() {
            for &(i, a) in acts {
                rom_centre.values[i] *= (a * centre[k]).exp();
            }
        }
        model.map.nominal = rom_centre.values.clone();
        let k_centre = rom_centre
            .get(names::K_CON)
            .or_else(|_| rom_centre.get(&names::k_con_joint(1)))?;
        // Labels carried over to the (enriched) model's modes at the centre by shape.
        let centre_p = with_board_mean(model.nominal_params());
        let (label_modes, _) = match_modes(&model, &centre_p, n_track, &w_labels, &points)?;
        let (all_modes, _) =
            match_modes(&model, &centre_p, n_track, &pick(&all.model_mode), &points)?;
        let mut labels = Labels {
            labels: labels.labels.clone(),
            model_mode: label_modes,
        };
        let mut all = Labels {
            labels: all.labels.clone(),
            model_mode: all_modes,
        };
        // modes.parquet, read once for the new modes' pairing and the shape terms.
        let mode_rows = read_modes_table(&modes_path)?;
        // Modes the enrichment adds (a fixture's own) that the campaign identified and pair
        // left unpaired: recorded in evidence.json (`new_modes`), and with
        // --enrich-new-modes updated as labels of their own.
        let new_modes = match opts.model.enrich.filter(|m| !is_board_mechanism(*m)) {
            Some(mech) => {
                let taken: Vec<usize> = labels
                    .model_mode
                    .iter()
                    .chain(&all.model_mode)
                    .copied()
                    .collect();
                let paired: BTreeSet<(String, i32)> = bolted_rows
                    .iter()
                    .map(|p| (p.measurement_id.clone(), p.mode))
                    .collect();
                pair_new_modes(
                    &model,
                    &centre_p,
                    n_track,
                    &taken,
                    &identified_modes(&mode_rows, "bolted"),
                    &paired,
                    mech.id(),
                )?
            }
            None => vec![],
        };
        let mut new_rows = vec![];
        for nm in &new_modes {
            let used = opts.model.enrich_new_modes;
            findings.push(Finding::new(
                Severity::Info,
                "update.new_mode_paired",
                format!(
                    "the enriched model's mode {} at {:.1} Hz (no baseline label) pairs with {} of {} bolted measurements' modes that pair left unpaired (median {:.1} Hz); {}",
                    nm.model_mode + 1,
                    nm.model_freq_hz,
                    nm.rows.len(),
                    nm.n_measurements,
                    nm.median_freq_hz(),
                    if used {
                        format!("updated as {:?}", nm.label)
                    } else {
                        "not updated (--enrich-new-modes updates it)".to_string()
                    }
                ),
            ));
            if used {
                labels.labels.push(nm.label.clone());
                labels.model_mode.push(nm.model_mode);
                all.labels.push(nm.label.clone());
                all.model_mode.push(nm.model_mode);
                new_rows.extend(nm.rows.iter().cloned());
            }
        }
        let bolted_rows: Vec<&PairRow> = bolted_rows.into_iter().chain(&new_rows).collect();
        let need = modes_needed(&labels, &all);
        // ROM box: ±rom_box, and along every parameter an extra coordinate moves, the sum of
        // the ln half-widths of the coordinates acting on it.
        let mut log_axes: Vec<(String, f64)> = vec![];
        for (k, c) in enr.coordinates.iter().enumerate() {
            if c.log_box.is_none() {
                continue;
            }
            for &(i, _) in &coords[k] {
                let w: f64 = enr
                    .coordinates
                    .iter()
                    .zip(&coords)
                    .filter(|(_, acts)| acts.iter().any(|(j, _)| *j == i))
                    .map(|(cc, acts)| {
                        let a = acts
                            .iter()
                            .find(|(j, _)| *j == i)
                            .map_or(1.0, |(_, a)| a.abs());
                        a * cc.log_box.unwrap_or((1.0 + opts.model.rom_box).ln())
                    })
                    .sum();
                if !log_axes.iter().any(|(n, _)| *n == nominal.names[i]) {
                    log_axes.push((nominal.names[i].clone(), w));
                }
            }
        }
        // The added mass varies between boards and draws by more than a ±20 % box around its
        // step-1 mean need cover: a logarithmic axis of e^±0.7 (half to twice the mean).
        let mut point_masses = vec![];
        if let Some(pm) = &point_mass {
            log_axes.push((pm.parameter.clone(), 0.7));
            point_masses.push(nominal.position(&pm.parameter)?);
        }
        clock.lap("centre_fit");
        let rom = match remembered {
            Some(m) => m.rom,
            None => {
                let rom = rom_for(&model, need, &log_axes, &opts.model)?;
                if let Ok(mut m) = JOINT_PREP.lock() {
                    *m = Some(JointPrep {
                        key: prep_key,
                        centre: centre.clone(),
                        rom: rom.clone(),
                    });
                }
                rom
            }
        };
        rom_centre_check(&model, &rom, need, &mut findings)?;
        clock.lap("rom_build");
        let mut p_board = model.nominal_params();
        for &i in &point_masses {
            p_board.values[i] = 0.0;
        }
        let nominal_mass_g = model.total_mass_kg(&p_board)? * 1e3;
        let thickness = core_thickness_mass(&model)?;
        let predictor = ModalPredictor::new(rom.clone(), &labels.model_mode, nominal_mass_g)?
            .with_point_masses(point_masses.clone())
            .with_core_thickness(thickness);
        let all_pred = ModalPredictor::new(rom.clone(), &all.model_mode, nominal_mass_g)?
            .with_point_masses(point_masses)
            .with_core_thickness(thickness);
        let wanted: BTreeSet<(String, i32)> = bolted_rows
            .iter()
            .map(|p| (p.measurement_id.clone(), p.mode))
            .collect();
        let shapes = shape_map(&mode_rows, &wanted);
        let use_shapes = opts.model.delta.is_some();
        let measurement_ids: BTreeSet<String> = bolted_rows
            .iter()
            .map(|p| p.measurement_id.clone())
            .collect();
        let mut units = vec![];
        let mut units_all = vec![];
        let mut unit_names = vec![];
        let mut unit_boards = vec![];
        let mut unit_board_idx = vec![];
        for m in &measurement_ids {
            let rows: Vec<&PairRow> = bolted_rows
                .iter()
                .copied()
                .filter(|p| &p.measurement_id == m)
                .collect();
            let bid = rows[0].board_id.clone();
            let Some(bi) = step1.board_ids.iter().position(|b| *b == bid) else {
                findings.push(
                    Finding::new(
                        Severity::Warning,
                        "update.no_step1_posterior",
                        format!("bolted measurement of board {bid}, which has no step-1 posterior in {}; left out of step 2", step1_path.display()),
                    )
                    .measurement(m.clone()),
                );
                continue;
            };
            let (data, (data_all, meta_all)) = unit_and_residual_data(
                &rows,
                &labels,
                &all,
                use_shapes,
                (&model, &rom, &shapes),
                None,
                &mut findings,
            )?;
            if data.freq.is_empty() {
                findings.push(
                    Finding::new(
                        Severity::Warning,
                        "update.measurement_no_modes",
                        format!("bolted measurement of board {bid} has no paired mode to update; left out of step 2"),
                    )
                    .measurement(m.clone()),
                );
                continue;
            }
            units.push(data);
            units_all.push((data_all, meta_all));
            unit_names.push(m.clone());
            unit_boards.push(bid);
            unit_board_idx.push(bi);
        }
        // The board mechanism's covariate per bolted measurement, relative to step 1's
        // reference (its evidence.json), and where each board's coefficient sits in aux.
        let joints_cov = match board_mech.filter(|m| *m == Mechanism::TemperatureStiffness) {
            None => None,
            Some(m) => {
                let ev_path = boards_dir.join("evidence.json");
                let reference = step1_enrichment["covariate_reference"].as_f64().ok_or_else(|| {
                    anyhow!("{}: no enrichment.covariate_reference: --boards must be the step-1 refit of {}", ev_path.display(), m.id())
                })?;
                let column = step1_enrichment["covariate"]
                    .as_str()
                    .unwrap_or_default()
                    .to_string();
                let coefficient = step1_enrichment["coefficient"].as_str().unwrap_or_default();
                let k = step1
                    .coefs
                    .iter()
                    .position(|c| *c == coefficient)
                    .ok_or_else(|| {
                        anyhow!(
                            "{}: no column {:?}: --boards must be the step-1 refit of {}",
                            step1_path.display(),
                            coefficient,
                            m.id()
                        )
                    })?;
                let used: BTreeSet<&str> = unit_names.iter().map(|s| s.as_str()).collect();
                let (offsets, mean) = covariate_offsets(
                    &opts.ingest_dir.join("measurements.parquet"),
                    &column,
                    &used,
                    &mut findings,
                )?;
                let scaled = step1_enrichment["scaled"]
                    .as_array()
                    .into_iter()
                    .flatten()
                    .map(|n| nominal.position(n.as_str().unwrap_or_default()))
                    .collect::<Result<Vec<_>, _>>()?;
                Some(JointsCovariate {
                    block: step1.block(),
                    coef: step1.params.len() + k,
                    scaled,
                    // Offsets from step 1's reference, not from the bolted measurements' mean.
                    offsets: unit_names
                        .iter()
                        .map(|u| offsets.get(u).copied().unwrap_or(0.0) + mean - reference)
                        .collect(),
                })
            }
        };
        if units.is_empty() {
            bail!("no bolted measurement has data for step 2 (no paired bolted mode of a board with a step-1 posterior)");
        }
        let mut target = ModalTarget {
            predictor,
            compose: Compose::Joints {
                board_params: board_params.clone(),
                unit_board: unit_board_idx.clone(),
                coords: coords.clone(),
                reference: reference.clone(),
                covariate: joints_cov,
            },
            prior: PopulationPrior {
                mu_mean: vec![0.0; coords.len()],
                mu_sd: enr.coordinates.iter().map(|c| c.prior_sd).collect(),
                sigma_scale: vec![opts.model.sigma_scale; coords.len()],
                sigma_prior: vec![],
                lkj_eta: opts.model.lkj_eta,
            },
            errors: ErrorModel {
                n_modes: labels.labels.len(),
                eps: opts.model.eps,
                delta: opts.model.delta,
                model_error_sd: None,
                discrepancy: None,
            },
            units,
            covariate: None,
            subspaces: vec![],
            coord_obs: vec![],
        };
        // The cut posterior: groups of `group` particles, each carrying one step-1 draw; every
        // run takes its own evenly spaced subset of the step-1 draws.
        let group = 10usize;
        let groups = (opts.sampler.smc.n_particles / group).max(1);
        let mut sopts = opts.clone();
        sopts.sampler.smc.n_particles = groups * group;
        sopts.sampler.smc.groups = groups;
        let mut aux_index: Vec<Vec<usize>> = vec![];
        let aux: Vec<Vec<Arc<Vec<f64>>>> = (0..opts.sampler.runs)
            .map(|r| {
                let idx: Vec<usize> = (0..groups)
                    .map(|g| {
                        ((g * opts.sampler.runs + r) * step1.draws.len()
                            / (groups * opts.sampler.runs))
                            % step1.draws.len()
                    })
                    .collect();
                let a = idx
                    .iter()
                    .map(|&i| Arc::new(step1.draws[i].1.clone()))
                    .collect();
                aux_index.push(idx);
                a
            })
            .collect();
        clock.lap("unit_data");
        // The units located for the weights with the step-1 posterior mean of the boards.
        let draws_mean: Vec<f64> = match step1.draws.first() {
            None => vec![],
            Some((_, d0)) => (0..d0.len())
                .map(|k| {
                    step1.draws.iter().map(|(_, d)| d[k]).sum::<f64>() / step1.draws.len() as f64
                })
                .collect(),
        };
        target.errors.discrepancy = discrepancy_for(
            &target,
            &draws_mean,
            // Off unless asked for (`--discrepancy-pct`): bolted, the joint stiffness of each
            // measurement is already free, and a per-mode bias common to every assembly at the
            // bolted model's fidelity (1.5 %) spans every shift a common joint effect makes
            // (a rotational restraint, a joint mass, a compliant fixture move the same few
            // bolted modes in every assembly): with it, such an effect is by construction
            // indistinguishable from the model's form, and no refit could be told from it.
            opts.model.discrepancy_freq.unwrap_or(0.0),
            "joints",
            &mut findings,
        )?;
        let shape_weights = weigh_shapes(
            &mut target,
            &opts.model.shape_weights,
            (&draws_mean, Some(&centre)),
            &labels.labels,
            opts.sampler.seed,
            "joints",
        )?;
        report_shape_weights(&shape_weights, "joints", verbose, &mut findings);
        clock.lap("shape_weights");
        let (results, acceleration) = run_smc(
            &target,
            &sopts.sampler,
            "joints",
            &aux,
            Some(&centre),
            verbose,
        )?;
        let sampler_seconds = clock.lap("sampler");
        check_surrogate_edges(&acceleration, &mut findings);
        // The ROM's box per coordinate, around the fitted centre.
        let coord_names: Vec<String> = enr.coordinates.iter().map(|c| c.name.clone()).collect();
        let bounds: Vec<(f64, f64)> = enr
            .coordinates
            .iter()
            .zip(&centre)
            .map(|(c, &x0)| match c.log_box {
                Some(w) => (x0 - w, x0 + w),
                None => (
                    x0 + (1.0 - opts.model.rom_box).ln(),
                    x0 + (1.0 + opts.model.rom_box).ln(),
                ),
            })
            .collect();
        if verbose {
            eprintln!("joints: ROM box per coordinate (ln) {bounds:.3?}");
        }
        let violations = box_violations(
            &results,
            &unit_names,
            &coord_names,
            |x| x.to_vec(),
            |k, x| x >= bounds[k].0 && x <= bounds[k].1,
            opts.model.box_tolerance,
        );
        if !violations.is_empty() {
            bail!(
                "the joint posterior presses against the ROM's box (±{:.0} % around k_con_n_per_m = {k_centre:.4e} N/m, fitted to the bolted modes at the boards' posterior mean{}):\n  {}\nThe joints differ more between measurements than one ROM covers; a per-measurement ROM is not built yet.",
                100.0 * opts.model.rom_box,
                if coords.len() > 1 { ", and the enrichment's logarithmic axes" } else { "" },
                violations.join("\n  ")
            );
        }
        // A check: where the full model fails at a draw, a warning, and the posterior stands.
        findings.push(match rom_posterior_check(&model, &target, &results, 4, need) {
            Ok((rom_err, noise)) => Finding::new(
                if rom_err > 0.25 * noise {
                    Severity::Warning
                } else {
                    Severity::Info
                },
                "update.rom_posterior_check",
                format!(
                    "the ROM's {need} lowest frequencies at 4 posterior draws differ from the full model's by at most {rom_err:.2e} (relative), against a measurement noise of {noise:.2e} (half the smallest posterior median of ε){}",
                    if rom_err > 0.25 * noise { ": above a quarter of the noise, the posterior is the ROM's more than the model's (raise --rom-basis)" } else { "" }
                ),
            ),
            Err(e) => Finding::new(
                Severity::Warning,
                "update.rom_posterior_check",
                format!("the ROM could not be checked against the full model at posterior draws: {e}"),
            ),
        });
        let prov = provenance("update_joints", &prep.fingerprint);
        let mut outputs = vec![];
        // population.parquet (step 2).
        let mut pcols: Vec<(String, String)> = vec![];
        for c in &enr.coordinates {
            let u = if c.report_unit.is_empty() {
                String::new()
            } else {
                format!("ln({})", c.report_unit)
            };
            pcols.push((format!("mu_{}", c.name), u.clone()));
            pcols.push((format!("sigma_{}", c.name), u));
        }
        let infer_eps = matches!(target.errors.eps, ErrorPrior::Inferred { .. });
        let infer_delta = matches!(target.errors.delta, Some(ErrorPrior::Inferred { .. }));
        if infer_eps {
            pcols.extend(
                labels
                    .labels
                    .iter()
                    .map(|l| (format!("eps_{l}"), String::new())),
            );
        }
        if infer_delta {
            pcols.extend(
                labels
                    .labels
                    .iter()
                    .map(|l| (format!("delta_{l}"), String::new())),
            );
        }
        let with_discrepancy = target.errors.discrepancy.is_some();
        if with_discrepancy {
            pcols.extend(discrepancy_columns(&labels.labels));
        }
        let mut pop = DrawTable::new(&pcols);
        let jcols: Vec<(String, String)> = enr
            .coordinates
            .iter()
            .map(|c| (c.report_param.clone(), c.report_unit.clone()))
            .collect();
        let mut jt = DrawTable::new(&jcols);
        let (mut b_run, mut b_draw) = (vec![], vec![]);
        let mut joint_boards = vec![];
        for (r, i, p) in particles_of(&results) {
            let ctx = smc::Target::ctx(&target, &p.g);
            let mut row = vec![];
            for (k, c) in enr.coordinates.iter().enumerate() {
                row.push(c.report_ref.ln() + ctx.pop.mu[k]);
                row.push(ctx.pop.sigma[k]);
            }
            if infer_eps {
                row.extend(&ctx.eps);
            }
            if infer_delta {
                row.extend(&ctx.delta);
            }
            if with_discrepancy {
                row.extend(discrepancy_values(&target, &p.g, &ctx));
            }
            pop.push(r, i, None, &row);
            let g = i / group;
            let (kr, kd) = step1.draws
                [aux_index[r % aux_index.len()][g % aux_index[r % aux_index.len()].len()]]
            .0;
            b_run.push(kr);
            b_draw.push(kd);
            for (b, name) in unit_names.iter().enumerate() {
                jt.push(r, i, Some(name), &enr.report_values(&p.x[b]));
                joint_boards.push(unit_boards[b].clone());
            }
        }
        let mut summary = pop.summarize(opts.sampler.runs, true);
        let mut js = jt.summarize(opts.sampler.runs, false);
        for row in &mut js {
            row.board_id = row
                .measurement_id
                .as_ref()
                .and_then(|m| unit_names.iter().position(|u| u == m))
                .map(|b| unit_boards[b].clone());
        }
        summary.extend(js);
        let p = opts.out.join("population.parquet");
        let cols: Vec<ArrayRef> = vec![
            Arc::new(Int32Array::from(pop.run.clone())),
            Arc::new(Int32Array::from(pop.draw.clone())),
            Arc::new(Int32Array::from(b_run)),
            Arc::new(Int32Array::from(b_draw)),
            Arc::new(Float64Array::from(pop.cols[0].2.clone())),
            Arc::new(Float64Array::from(pop.cols[1].2.clone())),
        ];
        write_table(&p, &POPULATION_JOINTS, cols, &pop.cols[2..], &prov)?;
        outputs.push(p);
        let p = opts.out.join("joints.parquet");
        let cols: Vec<ArrayRef> = vec![
            Arc::new(Int32Array::from(jt.run.clone())),
            Arc::new(Int32Array::from(jt.draw.clone())),
            Arc::new(StringArray::from_iter_values(
                jt.key.iter().map(|k| k.as_deref().unwrap_or("")),
            )),
            Arc::new(StringArray::from_iter_values(joint_boards.iter())),
            Arc::new(Float64Array::from(jt.cols[0].2.clone())),
        ];
        write_table(&p, &JOINTS, cols, &jt.cols[1..], &prov)?;
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
            &target,
            &all_pred,
            &all.labels,
            &labels.labels,
            &units_all,
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
        crate::io::atomic::write_bytes(&p, &target.predictor.rom.to_npz_bytes())?;
        outputs.push(p);
        let log_z: Vec<f64> = results.iter().map(|r| r.log_evidence).collect();
        let mut ev = evidence_json(&log_z, "joints (step 2), modular (cut) posterior");
        ev["note_cut"] = "log p(bolted data | step-1 posterior): the mean over the carried step-1 draws of each draw's evidence".into();
        ev["k_con_rom_centre_n_per_m"] = k_centre.into();
        ev["enrichment"] = serde_json::to_value(&enr)?;
        ev["new_modes"] = serde_json::Value::Array(
            new_modes
                .iter()
                .map(|nm| {
                    serde_json::json!({
                        "label": nm.label,
                        "model_mode": nm.model_mode + 1,
                        "model_freq_hz": nm.model_freq_hz,
                        "median_freq_hz": nm.median_freq_hz(),
                        "n_paired": nm.rows.len(),
                        "n_measurements": nm.n_measurements,
                        "updated": opts.model.enrich_new_modes,
                    })
                })
                .collect(),
        );
        if let Some(m) = board_mech {
            // The joints are the baseline's; the boards carry the mechanism (step 1's refit).
            ev["board_mechanism"] = serde_json::to_value(m)?;
            ev["boards_dir_evidence"] = step1_enrichment;
        }
        ev["rom_centre_coordinates"] = serde_json::to_value(&centre)?;
        ev["shape_weights"] = serde_json::to_value(&shape_weights)?;
        ev["discrepancy"] = discrepancy_json(&target, &labels.labels);
        let p = opts.out.join("evidence.json");
        crate::io::atomic::write_bytes(&p, serde_json::to_string_pretty(&ev)?.as_bytes())?;
        outputs.push(p);
        clock.lap("residuals");
        finish(
            &sopts,
            findings,
            outputs,
            &results,
            &summary,
            ev,
            sampler_seconds,
            &labels.labels,
            verbose,
            "update joints",
            &acceleration,
            &clock,
        )
    })
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
    use crate::bayes::smc::SmcOptions;
    use crate::io::manifest::{FileHash, Prepared};

    fn prepared(config: serde_json::Value, input_blake3: &str) -> Prepared {
        Prepared {
            spec: StageSpec {
                stage: "update_joints".into(),
                inputs: vec![],
                input_base: PathBuf::new(),
                config,
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

    fn config(particles: usize, runs: usize, seed: u64, rom_box: f64) -> serde_json::Value {
        let smc = SmcOptions {
            n_particles: particles,
            ..SmcOptions::default()
        };
        serde_json::json!({
            "smc": smc, "runs": runs, "seed": seed, "rom_box": rom_box, "enrich": "joint_rotation",
        })
    }

    /// The remembered centre and ROM are reused across the sampler's options only: another
    /// particle count, run count or seed keeps the key; another model option or input
    /// content changes it.
    #[test]
    fn the_preparation_key_ignores_the_sampler_only() {
        let key = joint_prep_key(&prepared(config(200, 2, 1, 0.2), "aa"));
        assert_eq!(joint_prep_key(&prepared(config(400, 4, 2, 0.2), "aa")), key);
        assert_ne!(joint_prep_key(&prepared(config(200, 2, 1, 0.3), "aa")), key);
        let mut other = config(200, 2, 1, 0.2);
        other["enrich"] = "joint_mass".into();
        assert_ne!(joint_prep_key(&prepared(other, "aa")), key);
        assert_ne!(joint_prep_key(&prepared(config(200, 2, 1, 0.2), "ab")), key);
    }
}

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

use crate::bayes::modal::{CovariateEffect, FreqObs, MassObs, ModalPredictor, ShapeObs, UnitData};
use crate::bayes::population::PopulationPrior;
use crate::bayes::shape_weight::{point_key, PointShape, ShapeWeight};
use crate::bayes::smc::{self, Particle, SmcOptions, StageInfo};
use crate::bayes::stats::median;
use crate::bayes::target::{
    Compose, ErrorModel, ErrorPrior, JointsCovariate, ModalTarget, PerMass,
};
use crate::diagnose::library::{
    board_enrichment, is_board_mechanism, joint_enrichment, BoardContext, BoardEffect,
    JointContext, JointEnrichment, Mechanism,
};
use crate::fem::params::names;
use crate::fem::{Board, FeModel, Rom, RomOptions, Setup};
use crate::findings::{Finding, Findings, Severity};
use crate::io::manifest::StageSpec;
use crate::io::modes_table::{read_modes_table, ModeRow};
use crate::io::tables::{self, c, Col, Cols, TableSpec};
use crate::modal::mac::mac_real;
use crate::stage::{exit, StageOutcome, StageResult};
use anyhow::{anyhow, bail, Context};
use arrow::array::{ArrayRef, BooleanArray, Float64Array, Int32Array, StringArray};
use arrow::datatypes::{DataType, Field};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::Arc;

pub const MANIFEST_BOARDS: &str = "update_boards.manifest.json";
pub const MANIFEST_JOINTS: &str = "update_joints.manifest.json";

pub const JOINTS: TableSpec = TableSpec {
    name: "joints",
    doc: "Step-2 posterior draws of every bolted measurement's joint stiffness, one row per particle and measurement. The modular (cut) posterior: every particle carries one step-1 draw of the boards (population.parquet's boards_run/boards_draw), and the bolted data updated only the joint parameters. A refit with an enrichment (`--enrich`, the diagnosis's candidates) adds one column per extra coordinate, named with its unit (e.g. k_rot_nm_per_rad, joint_mass_kg, m_fix_kg, f_fix_hz, k_ratio_<j>); with `joint_stiffness_per_joint` at one joint k_con_n_per_m is the stiffness of the other joints and k_ratio_<j> that joint's over theirs; with every joint (no joint named) k_con_n_per_m is the joints' geometric mean and k_ratio_<j> each joint's stiffness over the mean of the others' in that measurement.",
    open: true,
    columns: &[
        c("run", Col::Int32, false, "", "Independent SMC run (ArviZ chain)."),
        c("draw", Col::Int32, false, "", "Particle index within the run."),
        c("measurement_id", Col::Utf8, false, "", "Bolted measurement."),
        c("board_id", Col::Utf8, false, "", "Board of the measurement."),
        c("k_con_n_per_m", Col::Float64, false, "N/m", "Total joint contact stiffness of the measurement's fixing."),
    ],
};

pub const POPULATION_JOINTS: TableSpec = TableSpec {
    name: "population_joints",
    doc: "Step-2 (joints) population draws, one row per particle, written as population.parquet in the step-2 directory: the step-1 draw the particle carries, the population of ln k_con (natural log of N/m), with an enrichment (`--enrich`) `mu_<coord>`/`sigma_<coord>` of every extra coordinate (natural logs of the parameter in its unit, e.g. mu_ln_k_rot), and the bolted modes' prediction errors `eps_<label>`, `delta_<label>` (when inferred); with the model-form discrepancy (the default, `--discrepancy-pct`), `discrepancy_scale` (its scale τ, relative eigenvalue), `discrepancy_unit_scale` (σ_u, the sd of the part that differs between measurements, integrated out per measurement) and `discrepancy_<label>` (the bolted mode's discrepancy d: the model eigenvalue is λ (1 + d) for every measurement).",
    open: true,
    columns: &[
        c("run", Col::Int32, false, "", "Independent SMC run (ArviZ chain)."),
        c("draw", Col::Int32, false, "", "Particle index within the run (ArviZ draw)."),
        c("boards_run", Col::Int32, false, "", "run of the step-1 draw (boards.parquet) this particle carries."),
        c("boards_draw", Col::Int32, false, "", "draw of the step-1 draw this particle carries."),
        c("mu_ln_k_con", Col::Float64, false, "ln(N/m)", "Population mean of ln k_con_n_per_m."),
        c("sigma_ln_k_con", Col::Float64, false, "ln(N/m)", "Population standard deviation of ln k_con_n_per_m."),
    ],
};

pub const POPULATION: TableSpec = TableSpec {
    name: "population",
    doc: "Posterior draws of the population (hyper-)parameters, one row per particle; run = independent SMC run (ArviZ: chain = run, draw = draw). Step 1 (boards): for every updated parameter <p> (unit in its name) `mu_<p>` (population mean, unit of <p>), `sigma_<p>` (population standard deviation, unit of <p>), `corr_<p>_<q>` (population correlation). By default (`--board-coordinates per-mass`), where mass_scale is updated, the population of every modulus <m>_pa is formed per unit mass scale: its coordinate is `<m>_per_mass_scale_pa` = <m>_pa / mass_scale (Pa; free-free frequencies follow it), so the columns are e.g. `mu_e_x_per_mass_scale_pa`, `sigma_e_x_per_mass_scale_pa`, `corr_e_x_per_mass_scale_pa_mass_scale`; boards.parquet keeps the moduli themselves. A parameter on a logarithmic coordinate (added_mass_kg of `--enrich added_mass`) has `mu_<p>` = the population median (reference · e^μ, unit of <p>) and `sigma_<p>` in natural-log units. Prediction errors per mode label <l>: `eps_<l>` (relative standard deviation of the eigenvalue λ = ω², dimensionless) and `delta_<l>` (standard deviation of the unit-norm shape residual), when inferred. With the model-form discrepancy (the default, `--discrepancy-pct`): `discrepancy_scale` (its scale τ, relative eigenvalue), `discrepancy_unit_scale` (σ_u, the sd of the part that differs between boards, integrated out per board) and `discrepancy_<l>` (the updated mode's discrepancy d, common to every board: the model eigenvalue is λ (1 + d); orthogonal to what the board parameters can absorb).",
    open: true,
    columns: &[
        c("run", Col::Int32, false, "", "Independent SMC run (ArviZ chain)."),
        c("draw", Col::Int32, false, "", "Particle index within the run (ArviZ draw)."),
    ],
};

pub const BOARDS: TableSpec = TableSpec {
    name: "boards",
    doc: "Step-1 posterior draws of every board's parameters, one row per particle and board; one column per updated parameter, named with its unit (e.g. e_x_pa, e_y_pa, g_xy_pa, mass_scale); a refit with `--enrich added_mass` adds added_mass_kg (the lumped mass at the enrichment's point; mass_g then includes it, as the balance weighs it), one with `--enrich temperature_stiffness` temperature_coefficient_per_k. Where the sheet gave boards' thickness_mm (ingest's specimens.parquet), core_thickness_m (m): the board's core thickness, updated from its measurement and its frequencies.",
    open: true,
    columns: &[
        c("run", Col::Int32, false, "", "Independent SMC run (ArviZ chain)."),
        c("draw", Col::Int32, false, "", "Particle index within the run."),
        c("board_id", Col::Utf8, false, "", "Board."),
        c("mass_g", Col::Float64, false, "g", "Model mass of the board at this draw."),
    ],
};

pub const SUMMARY: TableSpec = TableSpec {
    name: "summary",
    doc: "Posterior summary, one row per parameter (and board or measurement where it has one): moments and quantiles over all runs' draws; rank-normalised split R-hat and bulk/tail ESS across runs (Vehtari et al. 2021, the definitions ArviZ uses).",
    open: false,
    columns: &[
        c("parameter", Col::Utf8, false, "", "Column name in population/boards (unit in the name)."),
        c("board_id", Col::Utf8, true, "", "Board, for per-board parameters."),
        c("measurement_id", Col::Utf8, true, "", "Measurement, for per-measurement parameters (none yet: step 2 is to come)."),
        c("mean", Col::Float64, false, "", "Posterior mean (unit of the parameter)."),
        c("sd", Col::Float64, false, "", "Posterior standard deviation."),
        c("q05", Col::Float64, false, "", "5 % quantile."),
        c("q50", Col::Float64, false, "", "Median."),
        c("q95", Col::Float64, false, "", "95 % quantile."),
        c("r_hat", Col::Float64, false, "", "Rank-normalised split R-hat across runs."),
        c("ess_bulk", Col::Float64, false, "", "Bulk effective sample size."),
        c("ess_tail", Col::Float64, false, "", "Tail effective sample size."),
    ],
};

pub const STAGES: TableSpec = TableSpec {
    name: "stages",
    doc: "The tempering path: one row per SMC run and tempering stage.",
    open: false,
    columns: &[
        c("run", Col::Int32, false, "", "Independent SMC run."),
        c("stage", Col::Int32, false, "", "Tempering stage, 1-based."),
        c(
            "beta",
            Col::Float64,
            false,
            "",
            "Inverse temperature after the stage.",
        ),
        c(
            "ess",
            Col::Float64,
            false,
            "",
            "Effective sample size of the incremental weights, particles.",
        ),
        c(
            "log_evidence_increment",
            Col::Float64,
            false,
            "",
            "log mean of the incremental weights.",
        ),
        c(
            "acceptance_unit",
            Col::Float64,
            true,
            "",
            "Acceptance rate of the per-unit moves.",
        ),
        c(
            "acceptance_global",
            Col::Float64,
            true,
            "",
            "Acceptance rate of the centred population moves.",
        ),
        c(
            "acceptance_noncentred",
            Col::Float64,
            true,
            "",
            "Acceptance rate of the non-centred population moves.",
        ),
        c(
            "acceptance_rescale",
            Col::Float64,
            true,
            "",
            "Acceptance rate of the moves that scale one mode's prediction-error scale together with the units' residuals of that mode (null where no error scale is inferred).",
        ),
        c("mutation_steps", Col::Int32, false, "", "Mutation sweeps."),
        c(
            "unique_after_resampling",
            Col::Int32,
            false,
            "",
            "Distinct particles after resampling.",
        ),
        c(
            "model_evals",
            Col::Float64,
            false,
            "",
            "Model evaluations of the stage (ROM or verified surrogate).",
        ),
        c(
            "screened_out",
            Col::Float64,
            false,
            "",
            "Proposals the delayed-acceptance screen rejected without a model evaluation (where a surrogate's extrapolation stood in for the ROM beyond the surrogate's box).",
        ),
        c(
            "kind",
            Col::Utf8,
            false,
            "",
            "`temper`: a tempering stage; `correct`: the final correction from the surrogates to the ROM at β = 1 (weights L_ROM / L_surrogate, the ROM solved in each unit's verified subspace inside its box, resampling, and mutation under the ROM only when resampling left fewer than 98 % of the particles distinct).",
        ),
    ],
};

pub const RESIDUALS: TableSpec = TableSpec {
    name: "residuals",
    doc: "Measured vs posterior-predictive model modes, one row per measurement and accepted paired mode of the step's setup (updating and validation modes).",
    open: false,
    columns: &[
        c("measurement_id", Col::Utf8, false, "", "Measurement."),
        c("board_id", Col::Utf8, false, "", "Board."),
        c("setup", Col::Utf8, false, "", "`free` or `bolted`."),
        c("label", Col::Utf8, false, "", "Mode label (from pair)."),
        c("freq_hz", Col::Float64, false, "Hz", "Identified frequency."),
        c("model_freq_hz_mean", Col::Float64, false, "Hz", "Posterior mean of the model frequency of this board/measurement."),
        c("model_freq_hz_sd", Col::Float64, false, "Hz", "Posterior standard deviation of the model frequency (parameter uncertainty)."),
        c("predictive_sd_hz", Col::Float64, false, "Hz", "Posterior-predictive standard deviation of a measurement: parameter uncertainty, for updated modes the inferred prediction error, and (step 1 with its model-error term) the model error's prior spread of the label (evidence.json's model_error)."),
        c("rel_residual", Col::Float64, false, "", "(freq_hz - model_freq_hz_mean) / model_freq_hz_mean."),
        c("std_residual", Col::Float64, false, "", "(freq_hz - model_freq_hz_mean) / predictive_sd_hz."),
        c("mac", Col::Float64, true, "", "MAC of the measured shape and the model shape (posterior mean); null without a usable shape."),
        c("used_for_updating", Col::Bool, false, "", "The mode's label was used for updating."),
    ],
};

/// Options shared by both steps.
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
    pub seed: u64,
    pub runs: usize,
    pub smc: SmcOptions,
    /// Mode labels to update; empty = those `pair` marks `used_for_updating`.
    pub modes: Vec<String>,
    /// Step 1: the updated board parameters (ROM parameter names).
    pub params: Vec<String>,
    /// Prior sd of the population means, relative to nominal (step 1) or in ln K (step 2).
    pub prior_width: f64,
    /// Scale of the population sds' prior (relative, or in ln K): the half-normal's scale;
    /// the log-normal's median is 0.6745 × it.
    pub sigma_scale: f64,
    /// Step 1: the prior family of the board parameters' population sds (step 2: always
    /// half-normal).
    #[serde(default)]
    pub sigma_prior: crate::bayes::population::SigmaPrior,
    pub lkj_eta: f64,
    pub eps: ErrorPrior,
    /// `None`: shape terms off.
    pub delta: Option<ErrorPrior>,
    /// ROM half-width (relative) and the largest posterior mass allowed outside it.
    pub rom_box: f64,
    pub box_tolerance: f64,
    /// Draws per run used for the posterior-predictive residuals.
    pub residual_draws: usize,
    /// Cap on the ROM's basis (None: the physics core's default). A smaller basis is faster
    /// and less accurate; the ROM accuracy test states the error of the default.
    pub rom_max_basis: Option<usize>,
    /// Start tempering from the prior (else from the Laplace-type reference).
    pub from_prior: bool,
    /// Local surrogates of the units' modal terms, corrected to the ROM at the end.
    pub surrogate: bool,
    /// The correction solves each unit's modes in a verified subspace of the ROM inside the
    /// unit's surrogate box (else in the whole ROM).
    pub subspace: bool,
    /// Step 2: refit with a joint enrichment of the diagnosis's library (`None`: the baseline).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub enrich: Option<Mechanism>,
    /// Step 2 with `joint_stiffness_per_joint`: the joint (1-based; `None`: every joint).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub enrich_joint: Option<usize>,
    /// Step 1 with `temperature_stiffness`: the numeric sheet column the FR-4 moduli follow.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub enrich_covariate: Option<String>,
    /// Step 1 with `added_mass`: the point (x_m, y_m) of the lumped mass.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub enrich_location: Option<[f64; 2]>,
    /// Step 2 with an enrichment: the enriched model's modes that no baseline label
    /// carries (a fixture's own mode) are paired with the identified modes pair left
    /// unpaired, and join the updating as labels of their own ([`pair_new_modes`]).
    #[serde(skip_serializing_if = "std::ops::Not::not", default)]
    pub enrich_new_modes: bool,
    /// Step 1: a relative model-form error per updated mode, common to a board's
    /// measurements and independent between boards, integrated out; its prior sd from the
    /// model's discretization spread (`fem::convergence::mesh_spread`).
    #[serde(default)]
    pub model_error: bool,
    /// The model's stated fidelity: the prior median of the model-form discrepancy's scale,
    /// a relative frequency ([`crate::bayes::discrepancy`]); `None`: the setup's default
    /// (free-free [`crate::bayes::discrepancy::FREE_FIDELITY_FREQ`]; bolted none, see
    /// `run_joints`, [`crate::bayes::discrepancy::BOLTED_FIDELITY_FREQ`] being the bolted
    /// model's stated fidelity to give it); 0: no discrepancy term.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub discrepancy_freq: Option<f64>,
    /// Step 1: boards whose measurements and masses are left out of the updating, so that
    /// the new-board prediction can be validated on them (the report compares them with it).
    #[serde(skip_serializing_if = "Vec::is_empty", default)]
    pub hold_out_boards: Vec<String>,
    /// Step 1: the coordinates the board population is formed in.
    #[serde(default)]
    pub board_coordinates: BoardCoordinates,
    /// Step 1: the floor of the mass term's sd, relative to the weighed mass
    /// ([`UpdateOptions::DEFAULT_MASS_FLOOR_REL`]; `mass_obs` says why).
    #[serde(default = "default_mass_floor_rel")]
    pub mass_floor_rel: f64,
    /// The power of each mode's shape term ([`crate::bayes::shape_weight`]).
    #[serde(default)]
    pub shape_weights: ShapeWeighting,
}

/// How each mode's shape term is weighted against its measurements' shared error
/// (`--shape-weights`).
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ShapeWeighting {
    /// 1 / design effect of the residuals at the Laplace reference's centre
    /// ([`crate::bayes::shape_weight`]).
    #[default]
    Auto,
    /// Every shape term at full weight: the measurements' shape errors independent.
    Off,
    /// Given per mode label (a diagnosis's refit takes its baseline's, so that their
    /// evidences are of the same likelihood); a label not given: 1.
    Given(BTreeMap<String, f64>),
}

fn default_mass_floor_rel() -> f64 {
    UpdateOptions::DEFAULT_MASS_FLOOR_REL
}

/// The coordinates of step 1's board population (`bayes::target::PerMass` says why).
#[derive(
    Clone,
    Copy,
    Debug,
    Default,
    PartialEq,
    Eq,
    serde::Serialize,
    serde::Deserialize,
    clap::ValueEnum,
)]
#[serde(rename_all = "snake_case")]
pub enum BoardCoordinates {
    /// With the mass scale updated, every modulus (a parameter in Pa) per unit mass scale:
    /// the population's coordinate `<modulus>_per_mass_scale_pa` is modulus / mass_scale.
    #[default]
    PerMass,
    /// Every parameter as it is.
    Natural,
}

impl UpdateOptions {
    /// Default floor of the mass term's sd, relative to the weighed mass (`mass_obs`).
    pub const DEFAULT_MASS_FLOOR_REL: f64 = 2e-4;
    /// The ROM box the tests verify the ROM over (relative half-width); step 1 widens it
    /// when the posterior presses against it ([`MAX_ROM_BOX`]).
    pub const DEFAULT_ROM_BOX: f64 = 0.2;

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

#[derive(Debug, Clone)]
pub(crate) struct PairRow {
    pub(crate) measurement_id: String,
    pub(crate) board_id: String,
    pub(crate) setup: String,
    pub(crate) mode: i32,
    pub(crate) freq_hz: f64,
    pub(crate) model_mode: i32,
    pub(crate) label: String,
}

/// The accepted pairs of pairs.parquet (with an identified mode, a frequency and a model mode).
pub(crate) fn read_pairs(path: &Path) -> anyhow::Result<Vec<PairRow>> {
    let mut out = vec![];
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let (mid, bid, setup, mode, f, mm, label, acc) = (
            c.str("measurement_id")?,
            c.str("board_id")?,
            c.str("setup")?,
            c.i32("mode")?,
            c.f64("freq_hz")?,
            c.i32("model_mode")?,
            c.str("label")?,
            c.bool("accepted")?,
        );
        for i in 0..b.num_rows() {
            use arrow::array::Array;
            if !acc.value(i) || mode.is_null(i) || f.is_null(i) || mm.is_null(i) {
                continue;
            }
            out.push(PairRow {
                measurement_id: mid.value(i).into(),
                board_id: bid.value(i).into(),
                setup: setup.value(i).into(),
                mode: mode.value(i),
                freq_hz: f.value(i),
                model_mode: mm.value(i),
                label: label.value(i).into(),
            });
        }
    }
    Ok(out)
}

fn read_presence(path: &Path, setup: &str) -> anyhow::Result<Vec<String>> {
    let mut out = vec![];
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let (s, l, u) = (
            c.str("setup")?,
            c.str("label")?,
            c.bool("used_for_updating")?,
        );
        for i in 0..b.num_rows() {
            if s.value(i) == setup && u.value(i) {
                out.push(l.value(i).to_string());
            }
        }
    }
    Ok(out)
}

/// Identified modes with their shapes: (measurement, mode) → its row of modes.parquet.
type ShapeMap<'a> = BTreeMap<(String, i32), &'a ModeRow>;

/// The rows of the `wanted` (measurement, mode) keys among the rows of modes.parquet.
fn shape_map<'a>(rows: &'a [ModeRow], wanted: &BTreeSet<(String, i32)>) -> ShapeMap<'a> {
    rows.iter()
        .map(|r| ((r.measurement_id.clone(), r.mode), r))
        .filter(|(key, _)| wanted.contains(key))
        .collect()
}

#[derive(Debug, Clone)]
struct MassRow {
    mass_g: f64,
    n_stable: i32,
    std_g: f64,
    resolution_g: f64,
    inconsistent: bool,
}

fn read_masses(path: &Path) -> anyhow::Result<BTreeMap<String, MassRow>> {
    let mut out = BTreeMap::new();
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let (bid, m, n, s, r, inc) = (
            c.str("board_id")?,
            c.f64("mass_g")?,
            c.i32("n_stable")?,
            c.f64("std_g")?,
            c.f64("resolution_g")?,
            c.bool("inconsistent")?,
        );
        for i in 0..b.num_rows() {
            out.insert(
                bid.value(i).to_string(),
                MassRow {
                    mass_g: m.value(i),
                    n_stable: n.value(i),
                    std_g: s.value(i),
                    resolution_g: r.value(i),
                    inconsistent: inc.value(i),
                },
            );
        }
    }
    Ok(out)
}

/// Each board's measured overall thickness from ingest's specimens.parquet, m (boards the
/// sheet gives none for are absent; no table: empty).
fn read_specimen_thickness(path: &Path) -> anyhow::Result<BTreeMap<String, f64>> {
    let mut out = BTreeMap::new();
    if !path.is_file() {
        return Ok(out);
    }
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let (bid, h) = (c.str("board_id")?, c.f64("thickness_mm")?);
        for i in 0..b.num_rows() {
            if arrow::array::Array::is_valid(h, i) {
                out.insert(bid.value(i).to_string(), 1e-3 * h.value(i));
            }
        }
    }
    Ok(out)
}

/// Where `model` has the core thickness as a parameter: its index, nominal value (m) and the
/// core's share of the board's nominal mass (the part that follows the thickness).
fn core_thickness_mass(model: &FeModel) -> anyhow::Result<Option<(usize, f64, f64)>> {
    let p = model.nominal_params();
    let Ok(i) = p.position(names::CORE_THICKNESS) else {
        return Ok(None);
    };
    let h0 = p.values[i];
    let mut twice = p.clone();
    twice.values[i] = 2.0 * h0;
    let (m0, m2) = (model.total_mass_kg(&p)?, model.total_mass_kg(&twice)?);
    Ok(Some((i, h0, (m2 - m0) / m0)))
}

/// Standard deviation of a board's measured core thickness, m: 5 µm, 0.3 % of a 1.5 mm
/// core. A micrometer's own error is ±2 µm (ISO 3611's maximum permissible error below
/// 25 mm); a laminate's thickness varies over the board by more than that, and the sheet
/// gives one number for the whole board. Free-free frequencies fix E h² (D ∝ E h³, mass ∝ h),
/// so this is what keeps a modulus's interval honest: ±0.6 % in E for ±0.3 % in h.
pub const THICKNESS_SD_M: f64 = 5e-6;

/// Per unit (board), its measured core thickness as an observation of its thickness
/// coordinate (k, relative value, relative sd; the coordinate is h / h₀ − 1). A board the
/// sheet gives no thickness for, or one outside the ROM's box (not verified there), has none,
/// each said in a warning: the population informs it, as it does an unweighed board's mass.
fn thickness_obs(
    param_names: &[String],
    h0_m: f64,
    unit_names: &[String],
    thickness_m: &BTreeMap<String, f64>,
    rom_box: f64,
    findings: &mut Findings,
) -> Vec<Vec<(usize, f64, f64)>> {
    let Some(k) = param_names.iter().position(|p| p == names::CORE_THICKNESS) else {
        return vec![];
    };
    let mut listed = vec![];
    let out = unit_names
        .iter()
        .map(|b| match thickness_m.get(b) {
            None => {
                findings.push(Finding::new(
                    Severity::Warning,
                    "update.thickness_unknown",
                    format!("board {b}: the sheet gives no thickness_mm while other boards have one; its core thickness is informed by the population and its frequencies only"),
                ));
                vec![]
            }
            Some(&h) if (h / h0_m - 1.0).abs() > rom_box => {
                findings.push(Finding::new(
                    Severity::Warning,
                    "update.thickness_outside_box",
                    format!("board {b}: its core thickness {:.3} mm (thickness_mm less the board file's copper) is {:+.1} % off the board file's {:.3} mm, outside the ROM's ±{:.0} % box (expected a laminate within its tolerance, thickness_mm the overall thickness over the copper: check the sheet, or the board file's core.thickness_m); not used", 1e3 * h, 100.0 * (h / h0_m - 1.0), 1e3 * h0_m, 100.0 * rom_box),
                ));
                vec![]
            }
            Some(&h) => {
                listed.push(format!("{b} {:.3}", 1e3 * h));
                vec![(k, h / h0_m - 1.0, THICKNESS_SD_M / h0_m)]
            }
        })
        .collect();
    findings.push(Finding::new(
        Severity::Info,
        "update.specimen_thickness",
        format!(
            "core thickness per board from the sheet (thickness_mm, the overall thickness, less the board file's copper layers), mm (board file: {:.3}), each a measurement of the board's core_thickness_m with sd {:.3} mm: {}",
            1e3 * h0_m,
            1e3 * THICKNESS_SD_M,
            listed.join(", ")
        ),
    ));
    out
}

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

/// The updated labels and, per label, the model mode (0-based) it pairs with at the centre.
struct Labels {
    labels: Vec<String>,
    model_mode: Vec<usize>,
}

fn select_labels(
    pairs: &[PairRow],
    setup: &str,
    requested: &[String],
    presence: &[String],
    findings: &mut Findings,
) -> anyhow::Result<Labels> {
    let chosen: Vec<String> = if requested.is_empty() {
        presence.to_vec()
    } else {
        requested.to_vec()
    };
    if chosen.is_empty() {
        bail!(
            "no {setup} mode is marked for updating (presence.parquet) and none was requested with --modes: nothing to update"
        );
    }
    let mut labels = vec![];
    let mut model_mode = vec![];
    for l in chosen {
        let mut counts: BTreeMap<i32, usize> = BTreeMap::new();
        for p in pairs.iter().filter(|p| p.setup == setup && p.label == l) {
            *counts.entry(p.model_mode).or_default() += 1;
        }
        match counts.iter().max_by_key(|(_, n)| **n) {
            Some((mm, _)) if *mm >= 1 => {
                labels.push(l);
                model_mode.push((*mm - 1) as usize);
            }
            _ => findings.push(Finding::new(
                Severity::Warning,
                "update.label_unpaired",
                format!("mode {l:?} has no accepted {setup} pair; left out of the updating"),
            )),
        }
    }
    if labels.is_empty() {
        bail!("none of the {setup} modes to update has an accepted pair in pairs.parquet");
    }
    Ok(Labels { labels, model_mode })
}

/// The scan points of an identified mode's shape where the shape is finite and the model can
/// be evaluated, and the shape's values there.
fn usable_points(model: &FeModel, row: &ModeRow) -> (Vec<[f64; 2]>, Vec<f64>) {
    let mut pts = vec![];
    let mut u = vec![];
    for ((v, x), y) in row.shape.iter().zip(&row.x_m).zip(&row.y_m) {
        if v.is_finite() && model.shape_operator(&[[*x, *y]]).is_ok() {
            pts.push([*x, *y]);
            u.push(*v);
        }
    }
    (pts, u)
}

/// A shape observation of one identified mode at its valid scan points, or `None` (with a
/// finding) when fewer than 3 points remain.
fn shape_obs(
    model: &FeModel,
    rom: &Rom,
    mode: usize,
    shape: &ModeRow,
    measurement_id: &str,
    grams: &mut Vec<Vec<f64>>,
    findings: &mut Findings,
) -> anyhow::Result<Option<ShapeObs>> {
    let (pts, u) = usable_points(model, shape);
    let nrm = u.iter().map(|v| v * v).sum::<f64>().sqrt();
    if pts.len() < 3 || nrm == 0.0 {
        findings.push(
            Finding::new(
                Severity::Warning,
                "update.shape_points",
                format!(
                    "only {} usable scan points for a mode shape (expected at least 3); its shape term is left out",
                    pts.len()
                ),
            )
            .measurement(measurement_id.to_string()),
        );
        return Ok(None);
    }
    let op = rom.shape_operator(model, &pts)?;
    let r = rom.dim();
    let n = pts.len();
    let points = PointShape {
        mode,
        keys: pts.iter().map(|q| point_key(q[0], q[1])).collect(),
        u: u.iter().map(|v| v / nrm).collect(),
        p: (0..n)
            .flat_map(|i| (0..r).map(move |a| (i, a)))
            .map(|(i, a)| op.p[(i, a)])
            .collect(),
    };
    let mut pt_u = vec![0.0; r];
    let mut gram = vec![0.0; r * r];
    for (i, ui) in u.iter().enumerate() {
        for a in 0..r {
            let pa = op.p[(i, a)];
            pt_u[a] += pa * ui / nrm;
            for b in 0..r {
                gram[a * r + b] += pa * op.p[(i, b)];
            }
        }
    }
    let gram = match grams.iter().position(|g| *g == gram) {
        Some(i) => i,
        None => {
            grams.push(gram);
            grams.len() - 1
        }
    };
    Ok(Some(ShapeObs {
        mode,
        pt_u,
        gram,
        n_points: n,
        ln_n: (n as f64).ln(),
        cond: 0,
        weight: 1.0,
        points: Some(Arc::new(points)),
    }))
}

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

/// Set the power of every shape term of `target` as `how` says, and return each mode's
/// weight with what it came from (empty without shape terms). `Auto` locates the units with
/// the Laplace reference at full weight (from `start`, with the mean auxiliary values),
/// takes each shape's residual against the model there, and weighs each mode by
/// [`crate::bayes::shape_weight::design_weights`].
fn weigh_shapes(
    target: &mut ModalTarget,
    how: &ShapeWeighting,
    (aux_mean, start): (&[f64], Option<&[f64]>),
    labels: &[String],
    seed: u64,
    what: &str,
) -> anyhow::Result<Vec<ShapeWeight>> {
    use crate::bayes::shape_weight::{design_weights, residual, ModeResidual};
    use rayon::prelude::*;
    if target.units.iter().all(|u| u.shapes.is_empty()) {
        return Ok(vec![]);
    }
    let count = |m: usize| -> usize {
        target
            .units
            .iter()
            .flat_map(|u| &u.shapes)
            .filter(|o| o.mode == m)
            .count()
    };
    let given = |w: &dyn Fn(&str) -> f64| -> Vec<ShapeWeight> {
        labels
            .iter()
            .enumerate()
            .map(|(m, l)| ShapeWeight {
                label: l.clone(),
                n_observations: count(m),
                n_pairs: 0,
                correlation: None,
                design_effect: 1.0 / w(l),
                weight: w(l),
            })
            .collect()
    };
    let weights = match how {
        ShapeWeighting::Off => given(&|_| 1.0),
        ShapeWeighting::Given(map) => given(&|l| map.get(l).copied().unwrap_or(1.0)),
        ShapeWeighting::Auto => {
            let ropts = crate::bayes::reference::ReferenceOptions {
                start: start.map(<[f64]>::to_vec),
                ..Default::default()
            };
            let (q, _) =
                crate::bayes::reference::laplace_reference(&*target, aux_mean, &ropts, seed)
                    .map_err(|e| {
                        anyhow!("{what}: locating the units to weigh the shape terms: {e}")
                    })?;
            let t = &*target;
            let res: Vec<ModeResidual> = (0..t.units.len())
                .into_par_iter()
                .flat_map_iter(|b| {
                    let pred = t
                        .predictor
                        .predict(&t.values(aux_mean, b, &q.units[b].mean));
                    t.units[b]
                        .shapes
                        .iter()
                        .filter_map(|o| {
                            let (pred, ps) = (pred.as_ref()?, o.points.as_ref()?);
                            Some(ModeResidual {
                                mode: o.mode,
                                keys: ps.keys.clone(),
                                r: residual(ps, &pred.vectors[o.mode], &t.predictor.refs[o.mode])?,
                            })
                        })
                        .collect::<Vec<_>>()
                })
                .collect();
            design_weights(&res, labels)
        }
    };
    for u in &mut target.units {
        for o in &mut u.shapes {
            o.weight = weights[o.mode].weight;
        }
    }
    Ok(weights)
}

/// The shape terms' weights in the log (verbose) and, where a mode's measurements share
/// most of their shape error, a finding: its shapes then count as few measurements.
fn report_shape_weights(w: &[ShapeWeight], what: &str, verbose: bool, findings: &mut Findings) {
    if verbose && !w.is_empty() {
        let s: Vec<String> = w
            .iter()
            .map(|w| {
                format!(
                    "{} {:.3} (ρ {:.3}, J {})",
                    w.label,
                    w.weight,
                    w.correlation.unwrap_or(f64::NAN),
                    w.n_observations
                )
            })
            .collect();
        eprintln!("{what}: shape-term weights {}", s.join(", "));
    }
    let low: Vec<String> = w
        .iter()
        .filter(|w| w.weight < 0.5)
        .map(|w| {
            format!(
                "{} (ρ = {:.2} over {} measurements: worth {:.1})",
                w.label,
                w.correlation.unwrap_or(f64::NAN),
                w.n_observations,
                w.n_observations as f64 * w.weight
            )
        })
        .collect();
    if !low.is_empty() {
        findings.push(Finding::new(
            Severity::Info,
            "update.shape_weights",
            format!("{what}: the shape residuals of {} agree between measurements (an error they share: extraction or model), so their shape terms count as fewer independent measurements (evidence.json shape_weights)", low.join(", ")),
        ));
    }
}

/// Where a frequency observation came from, and the index of its shape observation.
#[derive(Clone, Debug)]
struct ObsMeta {
    measurement_id: String,
    board_id: String,
    label: usize,
    freq_hz: f64,
    shape: Option<usize>,
}

/// The data of one group of measurements (a board's free-free measurements, or one bolted
/// measurement) for the given labels.
fn unit_data(
    rows: &[&PairRow],
    labels: &[String],
    shapes: Option<(&FeModel, &Rom, &ShapeMap<'_>)>,
    findings: &mut Findings,
) -> anyhow::Result<(UnitData, Vec<ObsMeta>)> {
    let mut d = UnitData::default();
    let mut meta = vec![];
    for p in rows {
        let Some(m) = labels.iter().position(|l| *l == p.label) else {
            continue;
        };
        let w = 2.0 * std::f64::consts::PI * p.freq_hz;
        d.freq.push(FreqObs::new(m, w * w));
        meta.push(ObsMeta {
            measurement_id: p.measurement_id.clone(),
            board_id: p.board_id.clone(),
            label: m,
            freq_hz: p.freq_hz,
            shape: None,
        });
        if let Some((model, rom, map)) = shapes {
            match map.get(&(p.measurement_id.clone(), p.mode)) {
                Some(s) => {
                    if let Some(o) = shape_obs(model, rom, m, s, &p.measurement_id, &mut d.grams, findings)? {
                        meta.last_mut().expect("pushed above").shape = Some(d.shapes.len());
                        d.shapes.push(o);
                    }
                }
                None => findings.push(
                    Finding::new(
                        Severity::Warning,
                        "update.shape_missing",
                        format!("identified mode {} has no shape in modes.parquet; its shape term is left out", p.mode),
                    )
                    .measurement(p.measurement_id.clone()),
                ),
            }
        }
    }
    Ok((d, meta))
}

fn mass_obs(
    m: &MassRow,
    board_id: &str,
    floor_rel: f64,
    findings: &mut Findings,
) -> Option<MassObs> {
    if m.n_stable < 1 || !m.mass_g.is_finite() {
        return None;
    }
    let res2 = m.resolution_g * m.resolution_g / 12.0;
    let sd2 = if m.inconsistent {
        findings.push(Finding::new(
            Severity::Warning,
            "update.mass_inconsistent",
            format!("board {board_id}: the balance readings disagree (ingest flagged them); the mass term uses their full spread, not the spread of the mean"),
        ));
        m.std_g * m.std_g + res2
    } else {
        m.std_g * m.std_g / m.n_stable as f64 + res2
    };
    // A floor of `floor_rel` (default 2e-4) of the mass: the balance's readability is not its
    // accuracy. Weighing a board (ρ ≈ 1.9 g/cm³) against steel calibration weights (8 g/cm³)
    // without the air-buoyancy correction alone shifts the reading by ≈ 0.05 %
    // (ρ_air V (1 − ρ/ρ_ref)); calibration adds to it. Without the floor a 0.1 mg
    // readability pins mass_scale to 2e-6, a precision no other part of the model has.
    // Readings corrected for buoyancy against a calibrated balance (or a virtual lab's,
    // which has neither error) need no floor: `--mass-floor 0`.
    let sd = sd2.sqrt().max(floor_rel * m.mass_g.abs()).max(1e-9);
    Some(MassObs {
        mass_g: m.mass_g,
        sd_g: sd,
    })
}

// ---------------------------------------------------------------------------------------------
// Draw tables and their summary.

/// Draws of named scalar columns, one row per (run, draw[, key]).
struct DrawTable {
    run: Vec<i32>,
    draw: Vec<i32>,
    /// board_id or measurement_id (None for population draws).
    key: Vec<Option<String>>,
    /// Column names (unit in the name) and values, one value per row.
    cols: Vec<(String, String, Vec<f64>)>,
}

impl DrawTable {
    fn new(names_units: &[(String, String)]) -> DrawTable {
        DrawTable {
            run: vec![],
            draw: vec![],
            key: vec![],
            cols: names_units
                .iter()
                .map(|(n, u)| (n.clone(), u.clone(), vec![]))
                .collect(),
        }
    }
    fn push(&mut self, run: usize, draw: usize, key: Option<&str>, values: &[f64]) {
        self.run.push(run as i32);
        self.draw.push(draw as i32);
        self.key.push(key.map(str::to_string));
        for (c, v) in self.cols.iter_mut().zip(values) {
            c.2.push(*v);
        }
    }

    /// Summary rows: per column and key, chains = runs.
    fn summarize(&self, runs: usize, key_is_board: bool) -> Vec<SummaryRow> {
        let keys: BTreeSet<Option<String>> = self.key.iter().cloned().collect();
        let mut out = vec![];
        for k in &keys {
            for (name, _, vals) in &self.cols {
                let mut chains: Vec<Vec<f64>> = vec![vec![]; runs];
                for i in 0..vals.len() {
                    if &self.key[i] == k {
                        chains[self.run[i] as usize].push(vals[i]);
                    }
                }
                let s = crate::bayes::diagnostics::summarize(&chains);
                out.push(SummaryRow {
                    parameter: name.clone(),
                    board_id: if key_is_board { k.clone() } else { None },
                    measurement_id: if key_is_board { None } else { k.clone() },
                    s,
                });
            }
        }
        out
    }
}

/// Largest split R-hat across runs that counts as agreement (Vehtari et al. 2021 advise 1.01
/// for a final analysis; at the pipeline's few runs of a few hundred particles, 1.05 is the
/// level below which the runs' differences are within their Monte Carlo error).
pub const MAX_R_HAT: f64 = 1.05;
/// Smallest bulk or tail ESS (over all runs) below which quantiles are unreliable.
pub const MIN_ESS: f64 = 100.0;

/// A warning when the independent runs disagree (R-hat above [`MAX_R_HAT`]) or the effective
/// sample size is small (below [`MIN_ESS`]), naming the worst parameters: the posterior
/// and the evidence's error bar are then not to be trusted as they stand (more particles or
/// runs; a multimodal posterior, e.g. of a model that misses physics, needs more of both).
fn convergence_finding(summary: &[SummaryRow], runs: usize) -> Option<Finding> {
    let name = |r: &SummaryRow| {
        let mut n = r.parameter.clone();
        if let Some(m) = r.measurement_id.as_ref().or(r.board_id.as_ref()) {
            n.push_str(&format!(" [{m}]"));
        }
        n
    };
    let mut bad_r: Vec<&SummaryRow> = summary
        .iter()
        .filter(|r| runs >= 2 && r.s.r_hat > MAX_R_HAT)
        .collect();
    bad_r.sort_by(|a, b| b.s.r_hat.total_cmp(&a.s.r_hat));
    let ess = |r: &SummaryRow| r.s.ess_bulk.min(r.s.ess_tail);
    let mut bad_e: Vec<&SummaryRow> = summary.iter().filter(|r| ess(r) < MIN_ESS).collect();
    bad_e.sort_by(|a, b| ess(a).total_cmp(&ess(b)));
    if bad_r.is_empty() && bad_e.is_empty() {
        return None;
    }
    let list = |v: &[&SummaryRow], f: &dyn Fn(&SummaryRow) -> String| {
        let mut s: Vec<String> = v.iter().take(4).map(|r| f(r)).collect();
        if v.len() > 4 {
            s.push(format!("{} more", v.len() - 4));
        }
        s.join(", ")
    };
    let mut parts = vec![];
    if !bad_r.is_empty() {
        parts.push(format!(
            "{} parameter(s) with R-hat above {MAX_R_HAT} ({}): the independent runs disagree",
            bad_r.len(),
            list(&bad_r, &|r| format!("{} {:.3}", name(r), r.s.r_hat))
        ));
    }
    if !bad_e.is_empty() {
        parts.push(format!(
            "{} parameter(s) with bulk or tail ESS below {MIN_ESS:.0} ({})",
            bad_e.len(),
            list(&bad_e, &|r| format!("{} {:.0}", name(r), ess(r)))
        ));
    }
    Some(Finding::new(
        Severity::Warning,
        "update.not_converged",
        format!(
            "{}; the posterior and the evidence's error bar are not reliable as they stand: rerun with more particles or runs (a posterior with several modes, as a model missing physics can have, needs both)",
            parts.join("; ")
        ),
    ))
}

struct SummaryRow {
    parameter: String,
    board_id: Option<String>,
    measurement_id: Option<String>,
    s: crate::bayes::diagnostics::Summary,
}

fn provenance(stage: &str, fingerprint: &str) -> BTreeMap<String, String> {
    BTreeMap::from([
        ("hbmu.stage".to_string(), stage.to_string()),
        ("hbmu.fingerprint".to_string(), fingerprint.to_string()),
        (
            "hbmu.version".to_string(),
            crate::io::manifest::TOOL_VERSION.to_string(),
        ),
        ("hbmu.campaign".to_string(), String::new()),
    ])
}

/// Write a table of `spec` with extra float columns (name, unit) after the spec's columns.
fn write_table(
    path: &Path,
    spec: &TableSpec,
    mut cols: Vec<ArrayRef>,
    extra: &[(String, String, Vec<f64>)],
    prov: &BTreeMap<String, String>,
) -> anyhow::Result<()> {
    let fields: Vec<Field> = extra
        .iter()
        .map(|(n, u, _)| {
            let mut md = std::collections::HashMap::new();
            if !u.is_empty() {
                md.insert("unit".to_string(), u.clone());
            }
            Field::new(n, DataType::Float64, false).with_metadata(md)
        })
        .collect();
    let mut md = tables::table_metadata(spec, prov);
    let mut units = spec.units();
    for (n, u, _) in extra {
        if !u.is_empty() {
            units.insert(n.clone(), u.clone());
        }
    }
    md.insert("hbmu.units".into(), serde_json::to_string(&units)?);
    let schema = spec.schema(&fields, &md);
    for (_, _, v) in extra {
        cols.push(Arc::new(Float64Array::from(v.clone())));
    }
    tables::write_parquet(path, &tables::batch(schema, cols)?)?;
    Ok(())
}

fn write_draws(
    path: &Path,
    spec: &TableSpec,
    t: &DrawTable,
    with_key: bool,
    prov: &BTreeMap<String, String>,
) -> anyhow::Result<()> {
    let mut cols: Vec<ArrayRef> = vec![
        Arc::new(Int32Array::from(t.run.clone())),
        Arc::new(Int32Array::from(t.draw.clone())),
    ];
    if with_key {
        cols.push(Arc::new(StringArray::from_iter_values(
            t.key.iter().map(|k| k.as_deref().unwrap_or("")),
        )));
    }
    // Spec float columns are taken from the table by name, the rest are extra.
    let spec_names: Vec<&str> = spec.columns.iter().map(|c| c.name).collect();
    let mut extra = vec![];
    for col in &t.cols {
        if spec_names.contains(&col.0.as_str()) {
            cols.push(Arc::new(Float64Array::from(col.2.clone())));
        } else {
            extra.push(col.clone());
        }
    }
    write_table(path, spec, cols, &extra, prov)
}

fn write_summary(
    path: &Path,
    rows: &[SummaryRow],
    prov: &BTreeMap<String, String>,
) -> anyhow::Result<()> {
    let f = |g: fn(&crate::bayes::diagnostics::Summary) -> f64| -> ArrayRef {
        Arc::new(Float64Array::from_iter_values(rows.iter().map(|r| g(&r.s))))
    };
    let cols: Vec<ArrayRef> = vec![
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|r| r.parameter.as_str()),
        )),
        Arc::new(StringArray::from_iter(
            rows.iter().map(|r| r.board_id.as_deref()),
        )),
        Arc::new(StringArray::from_iter(
            rows.iter().map(|r| r.measurement_id.as_deref()),
        )),
        f(|s| s.mean),
        f(|s| s.sd),
        f(|s| s.q05),
        f(|s| s.q50),
        f(|s| s.q95),
        f(|s| s.r_hat),
        f(|s| s.ess_bulk),
        f(|s| s.ess_tail),
    ];
    write_table(path, &SUMMARY, cols, &[], prov)
}

fn write_stages(
    path: &Path,
    st: &[StageInfo],
    prov: &BTreeMap<String, String>,
) -> anyhow::Result<()> {
    let nan_null = |v: f64| if v.is_finite() { Some(v) } else { None };
    let cols: Vec<ArrayRef> = vec![
        Arc::new(Int32Array::from_iter_values(
            st.iter().map(|s| s.run as i32),
        )),
        Arc::new(Int32Array::from_iter_values(
            st.iter().map(|s| s.stage as i32),
        )),
        Arc::new(Float64Array::from_iter_values(st.iter().map(|s| s.beta))),
        Arc::new(Float64Array::from_iter_values(st.iter().map(|s| s.ess))),
        Arc::new(Float64Array::from_iter_values(
            st.iter().map(|s| s.log_evidence_increment),
        )),
        Arc::new(Float64Array::from_iter(
            st.iter().map(|s| nan_null(s.acceptance_unit)),
        )),
        Arc::new(Float64Array::from_iter(
            st.iter().map(|s| nan_null(s.acceptance_global)),
        )),
        Arc::new(Float64Array::from_iter(
            st.iter().map(|s| nan_null(s.acceptance_noncentred)),
        )),
        Arc::new(Float64Array::from_iter(
            st.iter().map(|s| nan_null(s.acceptance_rescale)),
        )),
        Arc::new(Int32Array::from_iter_values(
            st.iter().map(|s| s.sweeps as i32),
        )),
        Arc::new(Int32Array::from_iter_values(
            st.iter().map(|s| s.unique_after_resampling as i32),
        )),
        Arc::new(Float64Array::from_iter_values(
            st.iter().map(|s| s.model_evals as f64),
        )),
        Arc::new(Float64Array::from_iter_values(
            st.iter().map(|s| s.screened_out as f64),
        )),
        Arc::new(StringArray::from_iter_values(st.iter().map(|s| s.kind))),
    ];
    write_table(path, &STAGES, cols, &[], prov)
}

/// One residual row.
struct Residual {
    measurement_id: String,
    board_id: String,
    setup: String,
    label: String,
    freq_hz: f64,
    mean: f64,
    sd: f64,
    pred_sd: f64,
    mac: Option<f64>,
    used: bool,
}

fn write_residuals(
    path: &Path,
    rows: &[Residual],
    prov: &BTreeMap<String, String>,
) -> anyhow::Result<()> {
    let cols: Vec<ArrayRef> = vec![
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|r| r.measurement_id.as_str()),
        )),
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|r| r.board_id.as_str()),
        )),
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|r| r.setup.as_str()),
        )),
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|r| r.label.as_str()),
        )),
        Arc::new(Float64Array::from_iter_values(
            rows.iter().map(|r| r.freq_hz),
        )),
        Arc::new(Float64Array::from_iter_values(rows.iter().map(|r| r.mean))),
        Arc::new(Float64Array::from_iter_values(rows.iter().map(|r| r.sd))),
        Arc::new(Float64Array::from_iter_values(
            rows.iter().map(|r| r.pred_sd),
        )),
        Arc::new(Float64Array::from_iter_values(
            rows.iter().map(|r| (r.freq_hz - r.mean) / r.mean),
        )),
        Arc::new(Float64Array::from_iter_values(
            rows.iter().map(|r| (r.freq_hz - r.mean) / r.pred_sd),
        )),
        Arc::new(Float64Array::from_iter(rows.iter().map(|r| r.mac))),
        Arc::new(BooleanArray::from_iter(rows.iter().map(|r| Some(r.used)))),
    ];
    write_table(path, &RESIDUALS, cols, &[], prov)
}

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

/// The population columns of a step's discrepancy: its scale, its per-unit scale and d per
/// label (relative eigenvalue), in the order of [`discrepancy_values`].
fn discrepancy_columns(labels: &[String]) -> Vec<(String, String)> {
    [
        "discrepancy_scale".to_string(),
        "discrepancy_unit_scale".to_string(),
    ]
    .into_iter()
    .chain(labels.iter().map(|l| format!("discrepancy_{l}")))
    .map(|n| (n, String::new()))
    .collect()
}

/// The values of [`discrepancy_columns`] at the global vector g (its context `ctx`).
fn discrepancy_values(
    target: &ModalTarget,
    g: &[f64],
    ctx: &crate::bayes::target::Ctx,
) -> Vec<f64> {
    let h = &g[target.prior.dim()..];
    let e = &target.errors;
    [
        e.discrepancy_scale(h).unwrap_or(f64::NAN),
        e.discrepancy_unit_scale(h).unwrap_or(f64::NAN),
    ]
    .into_iter()
    .chain(ctx.bias.iter().copied())
    .collect()
}

/// evidence.json's `discrepancy`: the prior of the model-form discrepancy (null without one).
fn discrepancy_json(target: &ModalTarget, labels: &[String]) -> serde_json::Value {
    match &target.errors.discrepancy {
        None => serde_json::Value::Null,
        Some(d) => serde_json::json!({
            "labels": labels,
            "fidelity_freq": crate::bayes::discrepancy::freq_of_eigenvalue(d.scale_median),
            "scale_median": d.scale_median,
            "scale_log_sd": d.scale_log_sd,
            "unit_scale_median": d.unit_scale_median,
            "unit_scale_log_sd": d.unit_scale_log_sd,
            "k": d.k,
            "basis": d.basis,
        }),
    }
}

/// Evidence of the runs: each run's log evidence, their mean and standard error.
fn evidence_json(log_z: &[f64], posterior: &str) -> serde_json::Value {
    let n = log_z.len() as f64;
    let mean = log_z.iter().sum::<f64>() / n;
    let sd = if log_z.len() > 1 {
        (log_z.iter().map(|z| (z - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt()
    } else {
        f64::NAN
    };
    serde_json::json!({
        "posterior": posterior,
        "log_evidence_runs": log_z,
        "log_evidence_mean": mean,
        "log_evidence_sd_across_runs": if sd.is_finite() { serde_json::json!(sd) } else { serde_json::Value::Null },
        "log_evidence_standard_error": if sd.is_finite() { serde_json::json!(sd / n.sqrt()) } else { serde_json::Value::Null },
        "note": "log p(data | model) from independent SMC runs (product of the mean incremental weights); standard error = sd across runs / sqrt(runs)",
    })
}

// ---------------------------------------------------------------------------------------------
// Running the sampler.

/// Independent runs of one target, with a progress bar over the tempering path.
/// What the acceleration did (reference, surrogates, correction), for the report.
#[derive(Default, serde::Serialize)]
struct Acceleration {
    start: &'static str,
    reference_model_evals: u64,
    reference_g_acceptance: f64,
    reference_units_converged: Vec<bool>,
    surrogate_units: usize,
    surrogate_refused: Vec<String>,
    surrogate_degree: Vec<Option<usize>>,
    /// Per unit: the surrogate box's half-width in reference sd (10, halved where the ROM or
    /// the polynomial does not hold that far).
    surrogate_half_width_sd: Vec<Option<f64>>,
    surrogate_max_abs_dlog_lik: Vec<Option<f64>>,
    surrogate_rom_evals: u64,
    /// Proposals outside a surrogate's box (`surrogate_half_width_sd`), evaluated by the ROM.
    surrogate_proposals_outside_box: u64,
    /// Fraction of the final particles' units beyond their surrogate's box (ROM-evaluated).
    surrogate_edge_fraction: f64,
    /// Per run: ESS of the correction weights L_ROM / L_surrogate, in particles.
    correction_ess: Vec<f64>,
    /// Per run: largest |log L_ROM − log L_surrogate| over the particles.
    correction_max_abs_dlog_lik: Vec<f64>,
    /// Per run: mutation sweeps of the correction stage (0 when resampling kept ≥ 98 %).
    correction_sweeps: Vec<usize>,
    /// Per unit: the dimensions, summed over its updated modes, of the verified per-mode
    /// subspaces of the ROM the correction solves in inside the unit's surrogate box
    /// (`bayes::surrogate::fit_subspace`; None: the ROM).
    subspace_dim: Vec<Option<usize>>,
    /// Per unit: its largest |log L_subspace − log L_ROM| on the verification points.
    subspace_max_abs_dlog_lik: Vec<Option<f64>>,
    subspace_refused: Vec<String>,
    subspace_rom_evals: u64,
    /// Wall seconds stay out of the file (the same inputs and seed give the same bytes);
    /// `-v` prints them.
    #[serde(skip)]
    subspace_seconds: f64,
    /// Posterior sd / reference sd per global coordinate (first run): how well the
    /// reference fitted (1 = exactly; the reference is inflated, so ~0.8 is expected).
    reference_sd_ratio_global: Vec<f64>,
    /// The same per unit coordinate, unit by unit.
    reference_sd_ratio_units: Vec<Vec<f64>>,
    /// Run 1: (posterior mean − reference mean) / reference sd of every global coordinate
    /// (same order as `reference_sd_ratio_global`).
    reference_offset_global: Vec<f64>,
    /// Particles of the pilot run whose posterior moments replaced the Laplace reference
    /// (0: no pilot), its tempering stages, and its wall seconds (printed with `-v`, kept out
    /// of the file: a pilot made update_report.json differ between two runs).
    pilot_particles: usize,
    pilot_stages: usize,
    #[serde(skip)]
    pilot_seconds: f64,
    /// Step 2: pilot groups left out of the surrogates' spread, and groups (over all runs)
    /// that tempered from the base reference, because their moved reference was degenerate.
    degenerate_pilot_groups: usize,
    degenerate_group_references: usize,
}

/// Particles of the pilot run whose posterior moments replace the Laplace reference of a run
/// without groups (`bayes::reference::pilot_reference`, inflated by `PILOT_INFLATION`); a
/// pilot runs only when the main runs have at least `PILOT_MIN_RATIO` times as many particles,
/// so it costs a few per cent. On the demo's step 1 at 2000 × 4 it cut the tempering stages
/// from 10 to 5 a run.
const PILOT_PARTICLES: usize = 400;
const PILOT_MIN_RATIO: usize = 4;
const PILOT_INFLATION: f64 = 1.1;

type Results = Vec<smc::RunResult<crate::bayes::modal::Terms>>;

/// `aux`: per run, the auxiliary values its particles carry (step 2: step-1 draws; with
/// `opts.smc.groups` > 1 group g carries aux[g]); empty for step 1.
///
/// `start`: a unit point known to fit the data (step 2: the joint centre fitted to the mean
/// bolted modes), where the reference's search begins; None = the prior's centre.
fn run_smc(
    target: &ModalTarget,
    opts: &UpdateOptions,
    what: &str,
    aux: &[Vec<Arc<Vec<f64>>>],
    start: Option<&[f64]>,
    verbose: bool,
) -> anyhow::Result<(Results, Acceleration)> {
    use crate::bayes::reference::{
        laplace_reference, reference_for_aux, GaussianReference, ReferenceOptions,
    };
    use crate::bayes::surrogate::{
        fit_subspace, fit_unit, SubspaceOptions, SurrogateOptions, SurrogateTarget,
    };
    use rand::SeedableRng;
    use rayon::prelude::*;
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
    let base_ref = if opts.from_prior {
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
            // measurement) that can fit a mode exactly (see `ReferenceOptions`). With two
            // (an enrichment's refit: ln K and ln k_rot per measurement) the re-formed
            // quadratic ran the demo's ε and δ to e^-75 … e^-244, a reference of zero spread.
            reform_curvature: modular && smc::Target::unit_dim(target) == 1,
            ..ReferenceOptions::default()
        };
        let (mut q, mut info) = laplace_reference(target, &aux_mean, &ropts, opts.seed)
            .map_err(|e| anyhow!("{what}: building the reference: {e}"))?;
        if let (Some(why), true) = (q.degeneracy(), ropts.reform_curvature) {
            // The re-formed quadratic extrapolated past where it holds: the frozen one.
            if verbose {
                eprintln!("{what}: the re-formed reference is degenerate ({why}); frozen curvature instead");
            }
            ropts.reform_curvature = false;
            (q, info) = laplace_reference(target, &aux_mean, &ropts, opts.seed)
                .map_err(|e| anyhow!("{what}: building the reference: {e}"))?;
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
        if verbose {
            eprintln!(
                "{what}: reference g mean {:.4?}, sd {:.4?}; unit sd {:.3?}",
                q.global.mean,
                q.global.sd(),
                q.units.iter().map(|u| u.sd()).collect::<Vec<_>>()
            );
        }
        Some((Arc::new(q), ropts))
    };
    let t_base = t_start.elapsed().as_secs_f64();
    let grouped = base_ref.is_some() && modular;
    let nu = smc::Target::n_units(target);
    // Where the units go across the groups' draws: with groups, each group's units sit
    // elsewhere (its draw moves them), so a few pilot groups, spread over the draws, are
    // moved to their own draws with the ROM; the surrogates' samples then cover the base
    // reference widened by twice the pilots' spread of the units, and the groups' own
    // references are found on the surrogates (their boxes cover where they go).
    let unit_spread: Vec<Option<crate::bayes::reference::Mvn>> = match &base_ref {
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
    };
    let surrogates: Vec<Option<Arc<crate::bayes::surrogate::UnitSurrogate>>> =
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
                                target.values(a, b, &unit_q.sample(&mut rng))
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
        };
    let t_surrogates = t_start.elapsed().as_secs_f64() - t_base;
    // The correction's model: per unit with a surrogate, a verified subspace of the ROM over
    // the surrogate's box (the ROM beyond it).
    let t_sub = std::time::Instant::now();
    let exact_target: Option<ModalTarget> = match (&base_ref, opts.subspace) {
        (Some((q, _)), true) if surrogates.iter().any(Option::is_some) => {
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
    };
    acc.subspace_seconds = t_sub.elapsed().as_secs_f64();
    let exact: &ModalTarget = exact_target.as_ref().unwrap_or(target);
    let sur = SurrogateTarget {
        inner: target,
        surrogates,
        outside_box: Default::default(),
        rom_evals: Default::default(),
    };
    // One start per run: the prior, the reference, or (groups carrying their own auxiliary
    // values: a modular step) one reference per group, found on the surrogates.
    let starts: Vec<smc::Start> = match &base_ref {
        None => vec![smc::Start::Prior; opts.runs],
        Some((q, ropts)) if !grouped => {
            let q = if opts.smc.n_particles >= PILOT_MIN_RATIO * PILOT_PARTICLES {
                let t0 = std::time::Instant::now();
                let (q, stages) = crate::bayes::reference::pilot_reference(
                    &sur,
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
                    .map(|a| reference_for_aux(&sur, q, a, ropts, 2))
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
    };
    let t_groups = t_start.elapsed().as_secs_f64() - t_base - t_surrogates;
    if verbose {
        eprintln!(
            "{what}: reference {t_base:.1} s (pilots and) surrogates {t_surrogates:.1} s, subspaces {:.1} s, pilot run ({:.1} s) or group references {:.1} s",
            acc.subspace_seconds,
            acc.pilot_seconds,
            t_groups - acc.subspace_seconds
        );
    }
    let pb = crate::stage::progress_bar((opts.runs * 1000) as u64, what);
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
            pb.set_position(base + (s.beta * 1000.0) as u64);
            pb.set_message(format!(
                "{what} run {}/{} stage {}",
                r + 1,
                opts.runs,
                s.stage
            ));
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
            for b in 0..nu {
                if sur.surrogates[b].is_none() {
                    continue;
                }
                res.particles
                    .par_iter_mut()
                    .zip(ctxs.par_iter())
                    .zip(lw.par_iter_mut())
                    .for_each(|((p, ctx), lw)| {
                        let c = smc::Target::model(exact, &p.aux, b, &p.x[b]);
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
            let info = smc::correct(exact, &opts.smc, opts.seed, r, &mut res, &lw, 0.9);
            let rom_evals = (res.particles.len() * acc.surrogate_units) as u64;
            if let Some(last) = res.stages.last_mut() {
                last.model_evals += rom_evals;
            }
            observe(&info);
            acc.correction_ess.push(info.ess);
            acc.correction_max_abs_dlog_lik.push(max_dll);
            acc.correction_sweeps.push(info.sweeps);
        }
        t_correction += t_corr.elapsed().as_secs_f64();
        if let (0, Some(_)) = (r, &base_ref) {
            // Each particle measured against its own group's q: (value − q mean) / q sd;
            // the mean of that is the offset, its sd the posterior sd / reference sd.
            let start = &starts[0];
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
                                    .map(|p| {
                                        (p.x[b][k] - q_of(p).units[b].mean[k])
                                            / sds[p.group].1[b][k]
                                    })
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
        out.push(res);
    }
    pb.finish_and_clear();
    if verbose {
        eprintln!("{what}: tempering {t_tempering:.1} s, correction to the ROM {t_correction:.1} s (all runs)");
    }
    acc.surrogate_proposals_outside_box =
        sur.outside_box.load(std::sync::atomic::Ordering::Relaxed);
    // Final particles beyond the boxes cost ROM evaluations at every later sweep: the
    // reference was narrower than the posterior there.
    let mut n_edge = 0usize;
    let mut n_all = 0usize;
    for res in &out {
        for p in &res.particles {
            for (b, s) in sur.surrogates.iter().enumerate() {
                if let Some(s) = s {
                    n_all += 1;
                    if s.box_position(&target.values(&p.aux, b, &p.x[b])) > 1.0 {
                        n_edge += 1;
                    }
                }
            }
        }
    }
    acc.surrogate_edge_fraction = n_edge as f64 / n_all.max(1) as f64;
    Ok((out, acc))
}

/// The ROM-box rule: the fraction of posterior draws, per unit parameter, outside the box
/// the ROM was built and verified for. Returns a description of every violation.
fn box_violations(
    results: &[smc::RunResult<crate::bayes::modal::Terms>],
    unit_names: &[String],
    param_names: &[String],
    relative: impl Fn(&[f64]) -> Vec<f64>,
    inside: impl Fn(usize, f64) -> bool,
    tolerance: f64,
) -> Vec<String> {
    let mut out = vec![];
    for (b, unit) in unit_names.iter().enumerate() {
        // Each particle's coordinates, once per unit.
        let rel: Vec<Vec<f64>> = results
            .iter()
            .flat_map(|r| r.particles.iter().map(|p| relative(&p.x[b])))
            .collect();
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
                    "{unit}: {pn}: {:.1} % of the posterior lies outside the ROM's box (posterior median {:.3})",
                    100.0 * frac,
                    xs[xs.len() / 2]
                ));
            }
        }
    }
    out
}

fn particles_of(
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

/// A function from a global vector to the population table's values.
type PopulationRow<'a> = Box<dyn Fn(&[f64]) -> Vec<f64> + 'a>;

/// Population columns of a draw, in physical units of the parameters.
fn population_columns<'a>(
    target: &'a ModalTarget,
    param_names: &[String],
    reference: &[f64],
    labels: &[String],
) -> (Vec<(String, String)>, PopulationRow<'a>) {
    let d = param_names.len();
    // Parameters on a logarithmic coordinate (p = ref e^x): μ is reported as the population
    // median ref e^μ, σ in ln units.
    let log: Vec<bool> = match &target.compose {
        Compose::Boards { log, .. } => (0..d)
            .map(|k| log.get(k).copied().unwrap_or(false))
            .collect(),
        Compose::Joints { .. } => vec![false; d],
    };
    let unit = |n: &str| -> String {
        if n.ends_with("_pa") {
            "Pa".into()
        } else if n.ends_with("_n_per_m") {
            "N/m".into()
        } else if n.ends_with("_kg") {
            "kg".into()
        } else {
            String::new()
        }
    };
    let mut cols: Vec<(String, String)> = vec![];
    cols.extend(param_names.iter().map(|n| (format!("mu_{n}"), unit(n))));
    cols.extend(param_names.iter().zip(&log).map(|(n, &l)| {
        (
            format!("sigma_{n}"),
            if l { "ln".to_string() } else { unit(n) },
        )
    }));
    for i in 0..d {
        for j in i + 1..d {
            cols.push((
                format!("corr_{}_{}", param_names[i], param_names[j]),
                String::new(),
            ));
        }
    }
    let infer_eps = matches!(target.errors.eps, ErrorPrior::Inferred { .. });
    let infer_delta = matches!(target.errors.delta, Some(ErrorPrior::Inferred { .. }));
    if infer_eps {
        cols.extend(labels.iter().map(|l| (format!("eps_{l}"), String::new())));
    }
    if infer_delta {
        cols.extend(labels.iter().map(|l| (format!("delta_{l}"), String::new())));
    }
    let with_discrepancy = target.errors.discrepancy.is_some();
    if with_discrepancy {
        cols.extend(discrepancy_columns(labels));
    }
    // The covariate coefficient (absolute, the unit coordinate after the parameters).
    if let Some(c) = &target.covariate {
        let unit = format!("1/(unit of {})", c.covariate);
        cols.push((format!("mu_{}", c.name), unit.clone()));
        cols.push((format!("sigma_{}", c.name), unit));
    }
    let with_beta = target.covariate.is_some();
    let reference = reference.to_vec();
    let f = Box::new(move |g: &[f64]| -> Vec<f64> {
        let ctx = smc::Target::ctx(target, g);
        let mut v: Vec<f64> = reference
            .iter()
            .zip(&ctx.pop.mu)
            .zip(&log)
            .map(|((r, m), &l)| if l { r * m.exp() } else { r * (1.0 + m) })
            .collect();
        v.extend(
            reference
                .iter()
                .zip(&ctx.pop.sigma)
                .zip(&log)
                .map(|((r, s), &l)| if l { *s } else { r * s }),
        );
        let o = ctx.pop.correlation();
        let dd = ctx.pop.mu.len();
        for i in 0..d {
            for j in i + 1..d {
                v.push(o[i * dd + j]);
            }
        }
        if infer_eps {
            v.extend(&ctx.eps);
        }
        if infer_delta {
            v.extend(&ctx.delta);
        }
        if with_discrepancy {
            v.extend(discrepancy_values(target, g, &ctx));
        }
        if with_beta {
            v.push(ctx.pop.mu[d]);
            v.push(ctx.pop.sigma[d]);
        }
        v
    });
    (cols, f)
}

/// Posterior-predictive residuals of every accepted paired mode (updating and validation
/// labels) of the units, from up to `opts.residual_draws` draws per run.
#[allow(clippy::too_many_arguments)]
fn residuals(
    target: &ModalTarget,
    all_pred: &ModalPredictor,
    all_labels: &[String],
    updated: &[String],
    units_all: &[(UnitData, Vec<ObsMeta>)],
    results: &[smc::RunResult<crate::bayes::modal::Terms>],
    setup: &str,
    draws_per_run: usize,
    model_error_sd: Option<&[f64]>,
) -> (Vec<Residual>, Vec<Lost>) {
    use rayon::prelude::*;
    let upd_idx: Vec<Option<usize>> = all_labels
        .iter()
        .map(|l| updated.iter().position(|u| u == l))
        .collect();
    type Row = Result<(Residual, Option<Lost>), Lost>;
    let out: Vec<Row> = units_all
        .par_iter()
        .enumerate()
        .flat_map_iter(|(b, (data, meta))| {
            let nf = data.freq.len();
            let mut s1 = vec![0.0; nf];
            let mut s2 = vec![0.0; nf];
            let mut se = vec![0.0; nf];
            let mut mac = vec![0.0; data.shapes.len()];
            let mut nmac = vec![0.0; data.shapes.len()];
            let mut nk = vec![0.0; nf];
            let mut n_all = 0.0;
            for r in results {
                let step = (r.particles.len() / draws_per_run.max(1)).max(1);
                for p in r.particles.iter().step_by(step) {
                    let v = target.values(&p.aux, b, &p.x[b]);
                    n_all += 1.0;
                    // A label lost at this draw (its mode not trackable) leaves the others.
                    // With a covariate effect: one prediction per condition.
                    let vs = target
                        .condition_values(b, &v, &p.x[b])
                        .unwrap_or_else(|| vec![Some(v.clone())]);
                    let Some(tracked_preds) = vs
                        .iter()
                        .map(|vk| all_pred.predict_tracked(vk.as_ref()?))
                        .collect::<Option<Vec<_>>>()
                    else {
                        continue;
                    };
                    let nm = all_labels.len();
                    let tracked: Vec<bool> = tracked_preds
                        .iter()
                        .flat_map(|(_, t)| t.iter().copied())
                        .collect();
                    let preds: Vec<_> = tracked_preds.into_iter().map(|(p, _)| p).collect();
                    let t = all_pred.terms_conditions(&preds, data, &v);
                    let ctx = smc::Target::ctx(target, &p.g);
                    for (k, f) in data.freq.iter().enumerate() {
                        let slot = f.cond * nm + f.mode;
                        if !tracked[slot] {
                            continue;
                        }
                        let fm = t.lambda[slot].max(0.0).sqrt() / (2.0 * std::f64::consts::PI);
                        s1[k] += fm;
                        s2[k] += fm * fm;
                        nk[k] += 1.0;
                        if let Some(u) = upd_idx[f.mode] {
                            let e = ctx.eps[u] * fm / 2.0;
                            se[k] += e * e;
                        }
                        // The model-error term's spread (relative on λ: half on f).
                        if let Some(sd) = model_error_sd {
                            let e = sd[f.mode] * fm / 2.0;
                            se[k] += e * e;
                        }
                    }
                    for (k, omm) in t.one_minus_mac.iter().enumerate() {
                        let sh = &data.shapes[k];
                        if tracked[sh.cond * nm + sh.mode] {
                            mac[k] += 1.0 - omm;
                            nmac[k] += 1.0;
                        }
                    }
                }
            }
            meta.iter()
                .enumerate()
                .map(|(k, m)| {
                    let label = all_labels[m.label].clone();
                    let n = nk[k];
                    if n == 0.0 {
                        return Err(Lost {
                            measurement_id: m.measurement_id.clone(),
                            label,
                            share_tracked: 0.0,
                        });
                    }
                    let mean = s1[k] / n;
                    let var = (s2[k] / n - mean * mean).max(0.0);
                    Ok((
                        Residual {
                            measurement_id: m.measurement_id.clone(),
                            board_id: m.board_id.clone(),
                            setup: setup.to_string(),
                            label: label.clone(),
                            freq_hz: m.freq_hz,
                            mean,
                            sd: var.sqrt(),
                            pred_sd: (var + se[k] / n).sqrt().max(1e-12),
                            mac: m
                                .shape
                                .and_then(|i| (nmac[i] > 0.0).then(|| mac[i] / nmac[i])),
                            used: upd_idx[m.label].is_some(),
                        },
                        (n < 0.9 * n_all).then(|| Lost {
                            measurement_id: m.measurement_id.clone(),
                            label,
                            share_tracked: n / n_all,
                        }),
                    ))
                })
                .collect::<Vec<_>>()
        })
        .collect();
    let mut rows = vec![];
    let mut lost = vec![];
    for r in out {
        match r {
            Ok((row, partial)) => {
                rows.push(row);
                lost.extend(partial);
            }
            Err(l) => lost.push(l),
        }
    }
    (rows, lost)
}

/// A residual row whose label could not be tracked at every posterior draw (the row is left
/// out when it never was).
struct Lost {
    measurement_id: String,
    label: String,
    share_tracked: f64,
}

/// The finding for rows of the residual table left out or averaged over fewer draws because
/// their label's mode could not be tracked (its overlap with the reference mode fell below
/// 1/√2): nothing is dropped silently.
fn lost_finding(lost: &[Lost], findings: &mut Findings) {
    if lost.is_empty() {
        return;
    }
    let dropped: Vec<String> = lost
        .iter()
        .filter(|l| l.share_tracked == 0.0)
        .map(|l| format!("{} {}", l.measurement_id, l.label))
        .collect();
    let partial: Vec<String> = lost
        .iter()
        .filter(|l| l.share_tracked > 0.0)
        .map(|l| {
            format!(
                "{} {} ({:.0} %)",
                l.measurement_id,
                l.label,
                100.0 * l.share_tracked
            )
        })
        .collect();
    let show = |v: &[String]| {
        let mut s = v.iter().take(8).cloned().collect::<Vec<_>>().join(", ");
        if v.len() > 8 {
            s.push_str(&format!(", … ({} in all)", v.len()));
        }
        s
    };
    let mut msg = String::from("posterior-predictive residuals: some modes could not be tracked at every posterior draw (overlap with the label's reference mode below 1/√2)");
    if !dropped.is_empty() {
        msg.push_str(&format!(
            "; left out of residuals.parquet, never tracked: {}",
            show(&dropped)
        ));
    }
    if !partial.is_empty() {
        msg.push_str(&format!(
            "; averaged over the draws where tracked: {}",
            show(&partial)
        ));
    }
    findings.push(Finding::new(
        Severity::Warning,
        "update.residual_label_lost",
        msg,
    ));
}

/// The prior of step 1's model-error term ([`ErrorModel::model_error_sd`]).
#[derive(Clone, Debug, serde::Serialize)]
struct ModelErrorPrior {
    /// How the model's frequencies move on finer meshes.
    spread: crate::fem::convergence::MeshSpread,
    /// Every paired free-free label (updating and validation) and its prior sd of the
    /// relative eigenvalue error b.
    labels: Vec<String>,
    sd: Vec<f64>,
    /// The sds of the updated labels, in their order.
    #[serde(skip)]
    sd_updated: Vec<f64>,
}

/// Floor of a label's model-error sd, relative to the largest of the labels: a mode whose
/// frequency happens to agree between the meshes compared is not thereby exact.
const MODEL_ERROR_FLOOR_SHARE: f64 = 0.1;

/// The model-error prior of the labels: b_m ~ N(0, s_m²), s_m = 2 × the mode's relative
/// frequency spread over the √2 and 2 × finer meshes (λ = ω², so twice the frequency's
/// relative error), floored at a tenth of the largest s of the labels (and 1e-7).
fn model_error_prior(
    board: &Board,
    nominal: &crate::fem::Params,
    updated: &Labels,
    all: &Labels,
) -> anyhow::Result<ModelErrorPrior> {
    let n = modes_needed(updated, all);
    // The mesh study's models are the standard ones: a known thickness is at its nominal in
    // `nominal`, so it is simply left out.
    let (names_std, values_std) = nominal
        .names
        .iter()
        .zip(&nominal.values)
        .filter(|(n, _)| *n != names::CORE_THICKNESS)
        .map(|(n, v)| (n.clone(), *v))
        .unzip();
    let nominal = &crate::fem::Params {
        names: names_std,
        values: values_std,
    };
    let spread = crate::fem::convergence::mesh_spread(board, &Setup::Free, &board.mesh, nominal, n)
        .map_err(|e| anyhow!("the model-error term's mesh study: {e}"))?;
    let raw = |mm: usize| 2.0 * spread.rel_spread.get(mm).copied().unwrap_or(0.0);
    let top = all
        .model_mode
        .iter()
        .chain(&updated.model_mode)
        .map(|&mm| raw(mm))
        .fold(0.0, f64::max);
    let floor = (MODEL_ERROR_FLOOR_SHARE * top).max(1e-7);
    let sd_of = |mm: usize| raw(mm).max(floor);
    Ok(ModelErrorPrior {
        labels: all.labels.clone(),
        sd: all.model_mode.iter().map(|&mm| sd_of(mm)).collect(),
        sd_updated: updated.model_mode.iter().map(|&mm| sd_of(mm)).collect(),
        spread,
    })
}

/// The model-form discrepancy of `target`'s updated modes ([`crate::bayes::discrepancy`]),
/// orthogonal to the relative eigenvalue sensitivities of unit 0's coordinates at x = 0 (the
/// reference point; step 2 with the auxiliary values `aux`, the step-1 posterior mean), its
/// scale's prior median `fidelity_freq` (relative frequency). `None` (with an info finding)
/// where the fidelity is 0, or where the units' coordinates span every mode.
fn discrepancy_for(
    target: &ModalTarget,
    aux: &[f64],
    fidelity_freq: f64,
    what: &str,
    findings: &mut Findings,
) -> anyhow::Result<Option<crate::bayes::discrepancy::Discrepancy>> {
    use crate::bayes::discrepancy::{sensitivities, Discrepancy};
    if fidelity_freq == 0.0 {
        return Ok(None);
    }
    if !(fidelity_freq.is_finite() && fidelity_freq > 0.0) {
        bail!("{what}: the model's fidelity (--discrepancy-pct) must be a finite share ≥ 0, found {fidelity_freq}");
    }
    let nm = target.errors.n_modes;
    let d = smc::Target::unit_dim(target);
    let lambda = |x: &[f64]| -> Option<Vec<f64>> {
        let t = smc::Target::model(target, aux, 0, x)?;
        let l = t.lambda[..nm].to_vec();
        l.iter().all(|v| v.is_finite() && *v > 0.0).then_some(l)
    };
    let sens_at = |x0: &[f64]| {
        sensitivities(lambda, x0, nm, 1e-3)
            .filter(|s| s.iter().all(|v| v.is_finite()))
            .ok_or_else(|| anyhow!("{what}: the model-form discrepancy: the model is undefined (or a label lost) within 0.1 % of {x0:?}"))
    };
    // The plain metric: every mode's discrepancy weighs alike. The data's precision per
    // mode (n_m over the within-board scatter ε̂_m², plus the model-error term) as the metric
    // gave a discrepancy space whose evidence was lower by 13 nats on the realistic paper
    // campaign (400 × 2), and no less correlation with the boards' moduli.
    let w = vec![1.0; nm];
    // The sensitivities where the units are, not at the reference point: the units sit a few
    // per cent from it (a plate's moduli fitted to a real board), and the sensitivities move
    // by as much, which leaves a discrepancy orthogonal at the reference point correlated
    // with the units' common shift at the 1e-4 level its posterior resolves (±0.9 on the
    // solid-truth campaign; the sampler then crawled). The units' common offset is the
    // weighted least-squares fit of the mean log-eigenvalue residuals at the reference point.
    let x0 = vec![0.0; d];
    let mut sens = sens_at(&x0)?;
    if let Some(l0) = lambda(&x0) {
        let mut r = vec![0.0; nm];
        let mut n = vec![0usize; nm];
        for u in &target.units {
            for f in u.freq.iter().filter(|f| f.cond == 0) {
                r[f.mode] += f.ln_lambda_hat - l0[f.mode].ln();
                n[f.mode] += 1;
            }
        }
        let r: Vec<f64> = r
            .iter()
            .zip(&n)
            .map(|(a, k)| a / (*k).max(1) as f64)
            .collect();
        if let Some(v) = weighted_offset(&sens, &r, &w, d) {
            // Within the ROM's verified box.
            let v: Vec<f64> = v.iter().map(|a| a.clamp(-0.15, 0.15)).collect();
            if let Ok(s) = sens_at(&v) {
                sens = s;
            }
        }
    }
    let disc = Discrepancy::new(&sens, nm, d, &w, fidelity_freq);
    if disc.is_none() {
        findings.push(Finding::new(
            Severity::Info,
            "update.discrepancy_none",
            format!("{what}: the units' {d} coordinate(s) span all {nm} updated modes: no discrepancy is left that the parameters cannot absorb, so none is inferred"),
        ));
    }
    Ok(disc)
}

/// argmin over v of Σ_m w_m (r_m − (S v)_m)² (S: n_m × d row-major), with a ridge of 1e-12
/// of the normal matrix's trace so that a coordinate the modes do not see (the mass scale,
/// whose moduli are per unit mass) stays at 0. `None` where the solve fails.
fn weighted_offset(s: &[f64], r: &[f64], w: &[f64], d: usize) -> Option<Vec<f64>> {
    let nm = r.len();
    let mut a = vec![0.0; d * d];
    let mut b = vec![0.0; d];
    for m in 0..nm {
        for i in 0..d {
            b[i] += w[m] * s[m * d + i] * r[m];
            for j in 0..d {
                a[i * d + j] += w[m] * s[m * d + i] * s[m * d + j];
            }
        }
    }
    let tr: f64 = (0..d).map(|i| a[i * d + i]).sum();
    for i in 0..d {
        a[i * d + i] += 1e-12 * tr.max(1e-300);
    }
    let (l, jitter) = crate::bayes::stats::cholesky_jittered(&a, d);
    if !jitter.is_finite() {
        return None;
    }
    let y = crate::bayes::stats::lower_solve(&l, d, &b);
    let v = crate::bayes::stats::lower_transpose_solve(&l, d, &y);
    v.iter().all(|x| x.is_finite()).then_some(v)
}

/// Model modes a ROM must carry for the updated labels and every paired label.
fn modes_needed(labels: &Labels, all: &Labels) -> usize {
    labels
        .model_mode
        .iter()
        .chain(&all.model_mode)
        .copied()
        .max()
        .unwrap_or(0)
        + 1
}

/// Labels of every accepted pair of a setup, with their model mode (0-based), in model order.
/// Every paired label of `setup` with its model mode (the one most of its pairs name). A
/// model mode carries one label: where two labels name the same mode (the pair stage
/// labels measured modes one measurement at a time, and near-degenerate modes can trade
/// labels), the label with more pairs keeps it and the other is reported in `findings` and
/// left out of the residuals. Two labels on one mode gave that mode's reference shape to
/// both, and the second was tracked onto an unrelated mode (a residual of −40 %).
fn all_labels(pairs: &[PairRow], setup: &str, n_modes: usize, findings: &mut Findings) -> Labels {
    let mut by: BTreeMap<String, BTreeMap<i32, usize>> = BTreeMap::new();
    for p in pairs.iter().filter(|p| p.setup == setup) {
        *by.entry(p.label.clone())
            .or_default()
            .entry(p.model_mode)
            .or_default() += 1;
    }
    // (model mode, pairs, label), the mode's most-paired label first.
    let mut v: Vec<(usize, usize, String)> = by
        .into_iter()
        .filter_map(|(l, c)| {
            let (mm, n) = c.into_iter().max_by_key(|(_, n)| *n)?;
            (mm >= 1 && (mm as usize) <= n_modes).then(|| ((mm - 1) as usize, n, l))
        })
        .collect();
    v.sort_by(|a, b| a.0.cmp(&b.0).then(b.1.cmp(&a.1)).then(a.2.cmp(&b.2)));
    let mut kept: Vec<(usize, String)> = vec![];
    for (m, n, l) in v {
        match kept.iter().find(|(k, _)| *k == m) {
            Some((_, winner)) => findings.push(Finding::new(
                Severity::Warning,
                "update.label_shares_mode",
                format!(
                    "{setup}: label {l:?} ({n} pair(s)) names model mode {} like {winner:?}, which has more pairs; its pairs have no residual rows",
                    m + 1
                ),
            )),
            None => kept.push((m, l)),
        }
    }
    Labels {
        labels: kept.iter().map(|(_, l)| l.clone()).collect(),
        model_mode: kept.iter().map(|(m, _)| *m).collect(),
    }
}

fn rom_for(
    model: &FeModel,
    n_modes_needed: usize,
    log_axes: &[(String, f64)],
    opts: &UpdateOptions,
) -> anyhow::Result<Rom> {
    let d = RomOptions::default();
    // A logarithmic axis needs more basis vectors: over e^{±3} of a joint's rotational
    // stiffness the bolted ROM's worst frequency error is 1.3e-4 with 64 vectors and 3.0e-5
    // with 80 (`rom_with_a_logarithmic_axis_matches_the_full_model_along_it`), so a cap
    // chosen for the ±20 % box is raised to 64 + 8 per such axis.
    let cap = opts.rom_max_basis.unwrap_or(d.max_basis);
    let max_basis = if log_axes.is_empty() {
        cap
    } else {
        cap.max(d.max_basis) + 8 * log_axes.len()
    };
    // The core thickness splits the mass into two terms: the three rigid-body vectors then
    // lead the basis (`fem::rom`) and take three of its vectors, which a cap chosen for the
    // elastic modes must not lose (at a cap of 12 the labels could no longer be tracked).
    let max_basis = if model.map.names.iter().any(|n| n == names::CORE_THICKNESS) {
        max_basis + 3
    } else {
        max_basis
    };
    let ro = RomOptions {
        n_modes: n_modes_needed.max(d.n_modes),
        box_rel: opts.rom_box,
        max_basis,
        log_axes: log_axes.to_vec(),
        ..d
    };
    Ok(Rom::build(model, &ro)?)
}

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
        seed: Some(opts.seed),
        manifest_path: opts.out.join(manifest),
    };
    Ok((board, spec))
}

/// A unit's data for the updated labels and, for the residuals, for every paired label with
/// shapes; the residual data's findings are reported too, once each.
#[allow(clippy::type_complexity)]
fn unit_and_residual_data(
    rows: &[&PairRow],
    labels: &Labels,
    all: &Labels,
    use_shapes: bool,
    (model, rom, shapes): (&FeModel, &Rom, &ShapeMap<'_>),
    covariate: Option<&BTreeMap<String, f64>>,
    findings: &mut Findings,
) -> anyhow::Result<(UnitData, (UnitData, Vec<ObsMeta>))> {
    let sh = use_shapes.then_some((model, rom, shapes));
    let (mut data, meta) = unit_data(rows, &labels.labels, sh, findings)?;
    let mut residual_findings = Findings::default();
    let mut all_data = unit_data(
        rows,
        &all.labels,
        Some((model, rom, shapes)),
        &mut residual_findings,
    )?;
    if let Some(c) = covariate {
        set_conditions(&mut data, &meta, c);
        set_conditions(&mut all_data.0, &all_data.1, c);
    }
    for f in residual_findings.0 {
        if !findings.0.contains(&f) {
            findings.push(f);
        }
    }
    Ok((data, all_data))
}

/// A unit's conditions: the distinct covariate offsets of its measurements (in order of
/// first appearance), and each observation's condition.
fn set_conditions(data: &mut UnitData, meta: &[ObsMeta], offsets: &BTreeMap<String, f64>) {
    data.conditions.clear();
    for (k, m) in meta.iter().enumerate() {
        let c = offsets.get(&m.measurement_id).copied().unwrap_or(0.0);
        let i = match data.conditions.iter().position(|x| *x == c) {
            Some(i) => i,
            None => {
                data.conditions.push(c);
                data.conditions.len() - 1
            }
        };
        data.freq[k].cond = i;
        if let Some(sh) = m.shape {
            data.shapes[sh].cond = i;
        }
    }
}

/// The surrogate boxes' half-widths in reference sd, e.g. `10` or `2.5–10`.
fn half_widths(acc: &Acceleration) -> String {
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

/// The finding when final particles lie beyond their surrogate's box (a cost, not a bias:
/// the ROM evaluates them).
fn check_surrogate_edges(acc: &Acceleration, findings: &mut Findings) {
    if acc.surrogate_edge_fraction > 1e-3 {
        findings.push(Finding::new(
            Severity::Info,
            "update.surrogate_box_edge",
            format!("{:.2} % of the final particles lie beyond their unit's surrogate box ({} reference sd): the posterior is wider than the reference there, and the ROM evaluated them ({} proposals outside the boxes)", 100.0 * acc.surrogate_edge_fraction, half_widths(acc), acc.surrogate_proposals_outside_box),
        ));
    }
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
    if let Some(m) = opts.enrich.filter(|m| !is_board_mechanism(*m)) {
        bail!(
            "--enrich {}: not a board mechanism (update boards refits temperature_stiffness, added_mass)",
            m.id()
        );
    }
    if !(opts.mass_floor_rel.is_finite() && opts.mass_floor_rel >= 0.0) {
        bail!(
            "--mass-floor: expected a finite relative value >= 0, found {}",
            opts.mass_floor_rel
        );
    }
    let mut inputs = vec![
        pairs_path.clone(),
        presence_path.clone(),
        modes_path.clone(),
        masses_path.clone(),
    ];
    if opts.enrich_covariate.is_some() {
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
        // One attempt at the ROM box `opts.rom_box`; `carried` are findings of an earlier one.
        let attempt = |opts: &UpdateOptions, carried: &[Finding]| -> anyhow::Result<StageResult> {
            let mut clock = PhaseClock::new("update boards", verbose);
            let mut findings = Findings::default();
            findings.0.extend(carried.iter().cloned());
            let pairs = read_pairs(&pairs_path)?;
            let presence = read_presence(&presence_path, "free")?;
            let labels = select_labels(&pairs, "free", &opts.modes, &presence, &mut findings)?;
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
                || opts.params.iter().any(|p| p == names::CORE_THICKNESS)
            {
                opts
            } else {
                let mut o = opts.clone();
                o.params.push(names::CORE_THICKNESS.into());
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
                .enrich
                .map(|m| {
                    board_enrichment(
                        m,
                        BoardContext {
                            board_mass_kg: 1e-3 * nominal_mass_g,
                            location_m: opts.enrich_location,
                        },
                    )
                    .map_err(|e| anyhow!("--enrich: {e}"))
                })
                .transpose()?;
            // A point mechanism's parameter joins the updated ones on a logarithmic coordinate.
            let mut param_names = opts.params.clone();
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
            let rom = rom_for(&model, need, &log_axes, opts)?;
            rom_centre_check(&model, &rom, need, &mut findings)?;
            clock.lap("rom_build");
            if opts.rom_box > UpdateOptions::DEFAULT_ROM_BOX {
                let worst = rom_box_check(&model, &rom, opts.rom_box, need)?;
                findings.push(Finding::new(
                if worst > 1e-4 { Severity::Warning } else { Severity::Info },
                "update.rom_box_check",
                format!(
                    "the ROM over ±{:.0} %: worst relative frequency error {worst:.1e} against the full model over its first {need} modes at 8 Latin-hypercube points{}",
                    100.0 * opts.rom_box,
                    if worst > 1e-4 { " (above 1e-4, the accuracy the ±20 % ROM is held to: raise --rom-basis)" } else { "" }
                ),
            ));
            }
            let model_error = opts
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
                    let column = opts.enrich_covariate.clone().ok_or_else(|| {
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
            for b in &opts.hold_out_boards {
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
            board_ids.retain(|b| !opts.hold_out_boards.contains(b));
            if board_ids.is_empty() {
                bail!("--hold-out leaves no board to update");
            }
            // The balance informs the mass parameters: mass_scale, and an added mass.
            let mass_updated =
                opts.params.iter().any(|p| p == names::MASS_SCALE) || !log_axes.is_empty();
            let use_shapes = opts.delta.is_some();
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
                    Some(m) if mass_updated => mass_obs(m, b, opts.mass_floor_rel, &mut findings),
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
            let d0 = opts.params.len();
            let mut prior = PopulationPrior {
                mu_mean: vec![0.0; d0],
                mu_sd: vec![opts.prior_width; d0],
                sigma_scale: vec![opts.sigma_scale; d0],
                // The board parameters' family; an enrichment's coordinate stays half-normal
                // (a coefficient probably common to all boards).
                sigma_prior: vec![opts.sigma_prior; d0],
                lkj_eta: opts.lkj_eta,
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
            let per_mass = match (opts.board_coordinates, mass) {
                (BoardCoordinates::PerMass, Some(mass)) => Some(PerMass {
                    mass,
                    specific: (0..d)
                        .map(|k| k < d0 && k != mass && param_names[k].ends_with("_pa"))
                        .collect(),
                }),
                _ => None,
            };
            if opts.board_coordinates == BoardCoordinates::PerMass && per_mass.is_none() {
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
                    eps: opts.eps,
                    delta: opts.delta,
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
                    opts.rom_box,
                    &mut findings,
                ),
            };
            target.errors.discrepancy = discrepancy_for(
                &target,
                &[],
                opts.discrepancy_freq
                    .unwrap_or(crate::bayes::discrepancy::FREE_FIDELITY_FREQ),
                "boards",
                &mut findings,
            )?;
            // The surrogates model a unit's terms as a function of its ROM parameters alone; with
            // a covariate the terms also follow the unit's coefficient, so the ROM runs directly.
            let mut sopts = opts.clone();
            sopts.surrogate &= target.covariate.is_none();
            clock.lap("unit_data");
            let shape_weights = weigh_shapes(
                &mut target,
                &opts.shape_weights,
                (&[], None),
                &labels.labels,
                opts.seed,
                "boards",
            )?;
            report_shape_weights(&shape_weights, "boards", verbose, &mut findings);
            clock.lap("shape_weights");
            let (results, acceleration) = run_smc(&target, &sopts, "boards", &[], None, verbose)?;
            let sampler_seconds = clock.lap("sampler");
            check_surrogate_edges(&acceleration, &mut findings);
            let violations = box_violations(
                &results,
                &unit_names,
                &param_names,
                |x| target.compose.relative_params(x),
                |k, x| match log_axes.get(k.wrapping_sub(d0)) {
                    Some((_, w)) if k >= d0 => x.abs() <= *w,
                    _ => x.abs() <= opts.rom_box,
                },
                opts.box_tolerance,
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
                    100.0 * opts.rom_box,
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
            let mut summary = pop.summarize(opts.runs, true);
            summary.extend(boards.summarize(opts.runs, true));
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
                opts.residual_draws,
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

/// Widest ROM box step 1 rebuilds to, relative half-width: beyond it a parameter is so far from
/// the board file's value, or so little informed, that the board file (or `--params`) needs
/// changing, not the ROM.
const MAX_ROM_BOX: f64 = 0.5;

/// The step-1 posterior pressing against the ROM's box: the stage's message, and the relative
/// half-width that would hold what was sampled.
#[derive(Debug)]
struct RomBoxViolation {
    message: String,
    needed_half_width: f64,
}

impl std::fmt::Display for RomBoxViolation {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.message)
    }
}

impl std::error::Error for RomBoxViolation {}

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
    if v.needed_half_width > MAX_ROM_BOX || v.needed_half_width <= opts.rom_box {
        return Err(e);
    }
    let mut wider = opts.clone();
    wider.rom_box = v.needed_half_width;
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
            100.0 * opts.rom_box,
            what.trim(),
            100.0 * wider.rom_box
        ),
    );
    eprintln!("update boards: {}", note.message);
    attempt(&wider, &[note])
}

/// The ROM against the full model at the ROM's centre (one full solve): the worst relative
/// frequency error of the `n_modes` lowest modes, as an info finding, a warning above 1e-5
/// (the order of the measurements' frequency noise). A ROM is exact at its centre up to
/// round-off; anything more is a construction error (as a mass coefficient other than 1
/// at the centre once was: every frequency 0.39 % high).
fn rom_centre_check(
    model: &FeModel,
    rom: &Rom,
    n_modes: usize,
    findings: &mut Findings,
) -> anyhow::Result<()> {
    let worst = worst_frequency_error(model, rom, &[model.nominal_params()], n_modes)?;
    findings.push(Finding::new(
        if worst > 1e-5 {
            Severity::Warning
        } else {
            Severity::Info
        },
        "update.rom_centre_check",
        format!(
            "the ROM's {n_modes} lowest frequencies at its centre differ from the full model's by at most {:.2e} (relative)",
            worst
        ),
    ));
    Ok(())
}

/// The worst relative difference between the ROM's and the full model's `n_modes` lowest
/// frequencies over `points` (one full solve each).
fn worst_frequency_error(
    model: &FeModel,
    rom: &Rom,
    points: &[crate::fem::Params],
    n_modes: usize,
) -> anyhow::Result<f64> {
    let sop = rom.shape_operator(model, &[[0.0, 0.0]])?;
    let mut worst = 0.0f64;
    for p in points {
        let full = model.modes(p, n_modes)?;
        let red = rom.eval(p, &sop)?;
        for (a, b) in red.freq_hz.iter().zip(&full.freq_hz).take(n_modes) {
            worst = worst.max((a - b).abs() / b);
        }
    }
    Ok(worst)
}

/// The ROM's worst relative frequency error against the full model over the first `n_modes`
/// modes, at `n_points` Latin-hypercube points of its box (a design apart from the build's).
fn rom_box_check(model: &FeModel, rom: &Rom, box_rel: f64, n_modes: usize) -> anyhow::Result<f64> {
    let points = crate::fem::rom::latin_hypercube_params(&model.map, 8, box_rel, 0x00B0_C5EC);
    worst_frequency_error(model, rom, &points, n_modes)
}

/// The ROM against the full model where the posterior lies: at `n_points` particles spread
/// evenly over every run's output (each at one unit, cycling through the units), the worst
/// relative difference of the `n_modes` lowest frequencies, and the smallest relative
/// frequency noise of the updated modes (half the posterior median of ε, which is relative on
/// λ = ω²) it is to be compared with. The box checks ask whether the ROM holds over its box;
/// this asks whether it holds where the answer is, at the accuracy the answer claims.
fn rom_posterior_check(
    model: &FeModel,
    target: &ModalTarget,
    results: &Results,
    n_points: usize,
    n_modes: usize,
) -> anyhow::Result<(f64, f64)> {
    let all = particles_of(results);
    let n = n_points.min(all.len());
    let points: Vec<crate::fem::Params> = (0..n)
        .map(|k| {
            let (_, _, p) = all[k * all.len() / n];
            let b = k % target.units.len();
            let mut params = model.nominal_params();
            params.values = target.values(&p.aux, b, &p.x[b]);
            params
        })
        .collect();
    let worst = worst_frequency_error(model, &target.predictor.rom, &points, n_modes)?;
    let mut eps: Vec<Vec<f64>> = vec![vec![]; target.errors.n_modes];
    for (_, _, p) in &all {
        let ctx = smc::Target::ctx(target, &p.g);
        for (m, e) in ctx.eps.iter().enumerate() {
            eps[m].push(*e);
        }
    }
    let noise = eps
        .iter_mut()
        .map(|v| {
            v.sort_by(f64::total_cmp);
            0.5 * v[v.len() / 2]
        })
        .fold(f64::INFINITY, f64::min);
    Ok((worst, noise))
}

/// Step-1 posterior draws read back from boards.parquet.
struct Step1 {
    /// Boards in the order of `values` blocks.
    board_ids: Vec<String>,
    /// The updated parameters (ROM names), in column order.
    params: Vec<String>,
    /// Coefficients of a board enrichment (e.g. `temperature_coefficient_per_k`), after the
    /// parameters in every board's block.
    coefs: Vec<String>,
    /// Per (run, draw): every board's parameter and coefficient values, board-major.
    draws: Vec<((i32, i32), Vec<f64>)>,
}

impl Step1 {
    /// Values per board in a draw: parameters, then coefficients.
    fn block(&self) -> usize {
        self.params.len() + self.coefs.len()
    }
}

/// The `enrichment` of a step-1 refit's evidence.json (null for the baseline).
fn read_step1_enrichment(path: &Path) -> anyhow::Result<serde_json::Value> {
    Ok(crate::io::read_json(path)?["enrichment"].clone())
}

/// A point mass a step-1 refit added to the boards: its parameter, point and posterior mean.
struct Step1PointMass {
    parameter: String,
    x_m: f64,
    y_m: f64,
    /// Mean over every board and draw, kg (the bolted ROM's centre along it).
    mean_kg: f64,
}

/// The point mass of a step-1 enrichment (its `effect` of kind `point_mass`), if any.
fn step1_point_mass(
    enrichment: &serde_json::Value,
    step1: &Step1,
    step1_path: &Path,
) -> anyhow::Result<Option<Step1PointMass>> {
    let e = &enrichment["effect"];
    if e["kind"].as_str() != Some("point_mass") {
        return Ok(None);
    }
    let parameter = e["parameter"].as_str().unwrap_or_default().to_string();
    let (Some(x_m), Some(y_m)) = (e["x_m"].as_f64(), e["y_m"].as_f64()) else {
        bail!(
            "{}: the step-1 enrichment's point mass has no x_m/y_m",
            step1_path.display()
        );
    };
    let Some(k) = step1.params.iter().position(|p| *p == parameter) else {
        bail!(
            "{}: no column {parameter:?}, the step-1 enrichment's added mass",
            step1_path.display()
        );
    };
    let d1 = step1.block();
    let nb = step1.board_ids.len();
    let (mut sum, mut n) = (0.0, 0usize);
    for (_, v) in &step1.draws {
        for b in 0..nb {
            sum += v[b * d1 + k];
            n += 1;
        }
    }
    Ok(Some(Step1PointMass {
        parameter,
        x_m,
        y_m,
        mean_kg: sum / n.max(1) as f64,
    }))
}

fn read_step1(path: &Path) -> anyhow::Result<Step1> {
    let batches = tables::read_parquet(path)?;
    let Some(first) = batches.first() else {
        bail!("{}: no rows: the step-1 posterior is empty", path.display());
    };
    let (coefs, params): (Vec<String>, Vec<String>) = first
        .schema()
        .fields()
        .iter()
        .filter(|f| f.data_type() == &DataType::Float64 && f.name() != "mass_g")
        .map(|f| f.name().clone())
        .partition(|n| crate::diagnose::library::is_board_coefficient(n));
    if params.is_empty() {
        bail!(
            "{}: no parameter columns (expected e.g. e_x_pa, mass_scale)",
            path.display()
        );
    }
    let mut by: BTreeMap<(i32, i32), BTreeMap<String, Vec<f64>>> = BTreeMap::new();
    let mut board_ids: BTreeSet<String> = BTreeSet::new();
    for b in &batches {
        let c = Cols { batch: b, path };
        let (run, draw, bid) = (c.i32("run")?, c.i32("draw")?, c.str("board_id")?);
        let cols: Vec<&Float64Array> = params
            .iter()
            .chain(&coefs)
            .map(|p| c.f64(p))
            .collect::<Result<_, _>>()?;
        for i in 0..b.num_rows() {
            board_ids.insert(bid.value(i).to_string());
            by.entry((run.value(i), draw.value(i))).or_default().insert(
                bid.value(i).to_string(),
                cols.iter().map(|a| a.value(i)).collect(),
            );
        }
    }
    let board_ids: Vec<String> = board_ids.into_iter().collect();
    let mut draws = vec![];
    for (k, m) in by {
        let mut v = Vec::with_capacity(board_ids.len() * params.len());
        for bid in &board_ids {
            let Some(x) = m.get(bid) else {
                bail!(
                    "{}: draw (run {}, draw {}) has no row for board {bid}",
                    path.display(),
                    k.0,
                    k.1
                );
            };
            v.extend(x);
        }
        draws.push((k, v));
    }
    Ok(Step1 {
        board_ids,
        params,
        coefs,
        draws,
    })
}

/// Points at which mode shapes of different joint models are compared: a 13 × 9 grid inset
/// by 4 % of the outline, without the points inside a hole's clamped disc.
fn match_points(board: &Board) -> Vec<[f64; 2]> {
    let (lx, ly) = (board.length_x_m, board.width_y_m);
    let r_clamp = 0.5 * board.joint().clamp_diameter_m;
    let mut out = vec![];
    for j in 0..9 {
        for i in 0..13 {
            let x = lx * (0.04 + 0.92 * i as f64 / 12.0);
            let y = ly * (0.04 + 0.92 * j as f64 / 8.0);
            if board
                .holes
                .iter()
                .all(|h| (x - h.x_m).hypot(y - h.y_m) > r_clamp.max(0.5 * h.diameter_m) * 1.05)
            {
                out.push([x, y]);
            }
        }
    }
    out
}

/// The identified modes of `setup` among the rows of modes.parquet (finite frequency only).
fn identified_modes<'a>(rows: &'a [ModeRow], setup: &str) -> Vec<&'a ModeRow> {
    rows.iter()
        .filter(|r| r.setup == setup && r.freq_hz.is_finite())
        .collect()
}

/// Least MAC of an identified mode with an enriched model's new mode, and the largest
/// relative frequency difference, for the two to pair (pair's own rule is MAC-based too).
const NEW_MODE_MIN_MAC: f64 = 0.9;
const NEW_MODE_MAX_REL_FREQ: f64 = 0.05;

/// The modes of `model` at `p` that no label carries (`taken`), paired with the identified
/// modes pair left unpaired (`identified` minus `paired`): per measurement the unpaired
/// mode of largest MAC ≥ [`NEW_MODE_MIN_MAC`] within [`NEW_MODE_MAX_REL_FREQ`] of the
/// model's frequency. A model mode becomes a label (`<mechanism>-mode-<k>`) where it pairs
/// in at least half of the measurements: an enrichment that predicts a mode the baseline
/// cannot have (a fixture's own resonance) is then held to that mode too.
#[allow(clippy::too_many_arguments)]
fn pair_new_modes(
    model: &FeModel,
    p: &crate::fem::Params,
    n_track: usize,
    taken: &[usize],
    identified: &[&ModeRow],
    paired: &BTreeSet<(String, i32)>,
    mechanism: &str,
) -> anyhow::Result<Vec<NewMode>> {
    let m = model.modes(p, n_track)?;
    let key = |r: &ModeRow| (r.measurement_id.clone(), r.mode);
    let unpaired: Vec<&ModeRow> = identified
        .iter()
        .copied()
        .filter(|r| !paired.contains(&key(r)))
        .collect();
    let measurements: BTreeSet<&str> = identified
        .iter()
        .map(|r| r.measurement_id.as_str())
        .collect();
    let (lo, hi) = identified
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(lo, hi), r| {
            (lo.min(r.freq_hz), hi.max(r.freq_hz))
        });
    // The model modes no label carries, within the identified band.
    let candidates: Vec<usize> = (0..m.freq_hz.len())
        .filter(|&c| {
            let fc = m.freq_hz[c];
            !(taken.contains(&c)
                || fc < lo * (1.0 - NEW_MODE_MAX_REL_FREQ)
                || fc > hi * (1.0 + NEW_MODE_MAX_REL_FREQ))
        })
        .collect();
    let far = |f: f64, fc: f64| (f / fc - 1.0).abs() > NEW_MODE_MAX_REL_FREQ;
    // Each unpaired mode near a candidate's frequency with a shape at ≥ 3 usable points: the
    // shape there and the model's modes there, evaluated once.
    let mut obs: Vec<(&ModeRow, Vec<f64>, faer::Mat<f64>)> = vec![];
    for &r in &unpaired {
        if candidates.iter().all(|&c| far(r.freq_hz, m.freq_hz[c])) {
            continue;
        }
        let (pts, u) = usable_points(model, r);
        if pts.len() < 3 {
            continue;
        }
        let w = model.w_at(&m, &pts)?;
        obs.push((r, u, w));
    }
    let mut used: BTreeSet<(String, i32)> = BTreeSet::new();
    let mut out = vec![];
    for &c in &candidates {
        let fc = m.freq_hz[c];
        let mut best: BTreeMap<&str, (f64, &ModeRow)> = BTreeMap::new();
        for (r, u, w) in &obs {
            if far(r.freq_hz, fc) || used.contains(&key(r)) {
                continue;
            }
            let wc: Vec<f64> = (0..u.len()).map(|i| w[(i, c)]).collect();
            let mac = mac_real(u, &wc);
            let m = r.measurement_id.as_str();
            if mac >= NEW_MODE_MIN_MAC && best.get(m).is_none_or(|b| mac > b.0) {
                best.insert(m, (mac, *r));
            }
        }
        if best.is_empty() || 2 * best.len() < measurements.len() {
            continue;
        }
        let label = format!("{mechanism}-mode-{}", out.len() + 1);
        let rows: Vec<PairRow> = best
            .values()
            .map(|(_, r)| {
                used.insert(key(r));
                PairRow {
                    measurement_id: r.measurement_id.clone(),
                    board_id: r.board_id.clone(),
                    setup: "bolted".into(),
                    mode: r.mode,
                    freq_hz: r.freq_hz,
                    model_mode: c as i32 + 1,
                    label: label.clone(),
                }
            })
            .collect();
        out.push(NewMode {
            model_mode: c,
            model_freq_hz: fc,
            label,
            rows,
            n_measurements: measurements.len(),
        });
    }
    Ok(out)
}

/// A mode of an enriched model that no baseline label carries, with the identified modes it
/// pairs with ([`pair_new_modes`]).
#[derive(Clone, Debug)]
struct NewMode {
    /// 0-based mode of the enriched model at the ROM's centre.
    model_mode: usize,
    model_freq_hz: f64,
    /// `<mechanism>-mode-<k>`.
    label: String,
    /// One pair per measurement where it paired.
    rows: Vec<PairRow>,
    /// Bolted measurements with an identified mode.
    n_measurements: usize,
}

impl NewMode {
    fn median_freq_hz(&self) -> f64 {
        let f: Vec<f64> = self.rows.iter().map(|r| r.freq_hz).collect();
        median(&f)
    }
}

/// The modes of `model` at `p` matched to the reference shapes (columns of `w_ref`, w at
/// `points`) by MAC, greedily from the best pair: per reference, the 0-based mode and its
/// frequency. A joint enrichment can add modes (the fixture's) and reorder them, so labels
/// are carried over by shape, never by position.
fn match_modes(
    model: &FeModel,
    p: &crate::fem::Params,
    n_modes: usize,
    w_ref: &faer::Mat<f64>,
    points: &[[f64; 2]],
) -> anyhow::Result<(Vec<usize>, Vec<f64>)> {
    let m = model.modes(p, n_modes)?;
    let w = model.w_at(&m, points)?;
    let nr = w_ref.ncols();
    let mut pairs = vec![];
    for a in 0..nr {
        for b in 0..w.ncols() {
            let (mut ab, mut aa, mut bb) = (0.0, 0.0, 0.0);
            for i in 0..points.len() {
                ab += w_ref[(i, a)] * w[(i, b)];
                aa += w_ref[(i, a)] * w_ref[(i, a)];
                bb += w[(i, b)] * w[(i, b)];
            }
            pairs.push((ab * ab / (aa * bb).max(f64::MIN_POSITIVE), a, b));
        }
    }
    pairs.sort_by(|x, y| y.0.total_cmp(&x.0));
    let mut idx = vec![usize::MAX; nr];
    let mut taken = vec![false; w.ncols()];
    for (_, a, b) in pairs {
        if idx[a] == usize::MAX && !taken[b] {
            idx[a] = b;
            taken[b] = true;
        }
    }
    let f = idx.iter().map(|&b| m.freq_hz[b]).collect();
    Ok((idx, f))
}

/// The joint step's preparation that depends on nothing but its inputs and the options other
/// than the sampler's (the fitted ROM centre and the ROM), remembered within the process for
/// one key ([`joint_prep_key`]). The diagnosis's gate (`stage::diagnose`, `run_gated`) runs a
/// refit's step 2 a second time with more particles and runs; on the paper campaign's rotation
/// refit the centre fit and the ROM took 34 s of each attempt (0.8 s remembered; the whole
/// diagnosis 267 s before, 239 s after, same tables). Not a file cache: the stage's
/// manifest already decides when a whole step is reused, and this only spares a re-run in the
/// same process the identical work.
#[derive(Clone)]
struct JointPrep {
    key: String,
    centre: Vec<f64>,
    rom: Rom,
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

/// The ROM's centre in the enrichment's coordinates (ln, relative to the priors' centres).
#[allow(clippy::too_many_arguments)]
fn fit_centre(
    model: &FeModel,
    p_base: &crate::fem::Params,
    coords: &[Vec<(usize, f64)>],
    spans: &[f64],
    enr: &JointEnrichment,
    n_fit: usize,
    (labels, bolted_rows): (&Labels, &[&PairRow]),
    (w_labels, points): (&faer::Mat<f64>, &[[f64; 2]]),
    n_track: usize,
) -> anyhow::Result<Vec<f64>> {
    let mut fit = fit_joint_centre(
        model,
        p_base,
        &coords[..n_fit],
        &spans[..n_fit],
        labels,
        bolted_rows,
        (w_labels, points),
        n_track,
    )?;
    fit.resize(coords.len(), 0.0);
    let mut centre: Vec<f64> = fit
        .iter()
        .zip(&enr.coordinates)
        .enumerate()
        .map(|(k, (x, c))| match c.log_box {
            Some(w) if k > 0 => x.clamp(-0.5 * w, 0.5 * w),
            _ => *x,
        })
        .collect();
    if centre != fit {
        let mut p_held = p_base.clone();
        for (k, acts) in coords.iter().enumerate().skip(1) {
            for &(i, a) in acts {
                p_held.values[i] *= (a * centre[k]).exp();
            }
        }
        centre[0] = fit_joint_centre(
            model,
            &p_held,
            &coords[..1],
            &spans[..1],
            labels,
            bolted_rows,
            (w_labels, points),
            n_track,
        )?[0];
    }
    Ok(centre)
}

/// The centre of a step-2 model's ROM: the unit coordinates that best fit the median
/// bolted frequency of every label at the boards' posterior mean (`p_base`, reference
/// values of the joint parameters), by Levenberg–Marquardt within ±`spans[k]`, with the
/// full FE model. The ROM
/// is built around it: its box is ±20 % and the nominal joint can be off by far more.
/// Only the ROM's centre depends on the data; the priors do not. The reference of the SMC
/// starts its search there too.
///
/// An enrichment can make the fit multimodal: a fixture resonance fits one way above the
/// band (where it hardly acts) and another way between two measured modes, and a local
/// search from the prior's centre never crosses a mode to reach the other. So the
/// enrichment's own coordinates (all but the first, k_con; the first two of them) are first
/// scanned on a grid over ±⅔ of their spans (7 points each, at most 7² points), and the
/// search runs from the prior's centre and from the two best grid points; the lowest misfit
/// wins.
#[allow(clippy::too_many_arguments)]
fn fit_joint_centre(
    model: &FeModel,
    p_base: &crate::fem::Params,
    coords: &[Vec<(usize, f64)>],
    spans: &[f64],
    labels: &Labels,
    rows: &[&PairRow],
    (w_ref, points): (&faer::Mat<f64>, &[[f64; 2]]),
    n_modes: usize,
) -> anyhow::Result<Vec<f64>> {
    // Median measured frequency per label.
    let med: Vec<Option<f64>> = labels
        .labels
        .iter()
        .map(|l| {
            let mut f: Vec<f64> = rows
                .iter()
                .filter(|p| &p.label == l)
                .map(|p| p.freq_hz)
                .collect();
            f.sort_by(f64::total_cmp);
            (!f.is_empty()).then(|| f[f.len() / 2])
        })
        .collect();
    // Relative residuals of the labels with a measured median.
    let resid = |x: &[f64]| -> anyhow::Result<Vec<f64>> {
        let mut p = p_base.clone();
        for (k, acts) in coords.iter().enumerate() {
            for &(i, a) in acts {
                p.values[i] *= (a * x[k]).exp();
            }
        }
        let (_, f) = match_modes(model, &p, n_modes, w_ref, points)?;
        Ok(med
            .iter()
            .zip(&f)
            .filter_map(|(m, fm)| m.map(|m| (fm - m) / m))
            .collect())
    };
    // Levenberg–Marquardt on ln-coordinates with forward-difference Jacobians (d ≤ 3, a few
    // dozen FE solves), kept inside ±spans: a joint's stiffnesses trade off against each
    // other (k_con against k_rot), a ridge a one-coordinate-at-a-time search crawls along.
    let d = coords.len();
    // The grid of starts over the enrichment's coordinates: 7 points over ±⅔ of each span
    // (±2 prior sd, the spans being 3 prior sd).
    const GRID: [f64; 7] = [-1.0, -2.0 / 3.0, -1.0 / 3.0, 0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0];
    let mut grid: Vec<Vec<f64>> = vec![vec![0.0; d]];
    for k in 1..d.min(3) {
        grid = grid
            .iter()
            .flat_map(|g| {
                GRID.iter().map(move |&t| {
                    let mut g = g.clone();
                    g[k] = t * 2.0 / 3.0 * spans[k];
                    g
                })
            })
            .collect();
    }
    // The grid's FE solves side by side (rayon's collect keeps the grid's order).
    use rayon::prelude::*;
    let mut scored: Vec<(f64, Vec<f64>)> = grid
        .into_par_iter()
        // The prior's centre is the search's first start anyway.
        .filter(|g| g.iter().any(|v| *v != 0.0))
        .filter_map(|g| resid(&g).ok().map(|r| (sum_sq(&r), g)))
        .collect();
    scored.sort_by(|a, b| a.0.total_cmp(&b.0));
    // From the prior's centre as before (its failure is the step's); a grid start whose
    // search meets a point the model cannot solve is dropped.
    let mut best = levenberg_marquardt(&resid, vec![0.0; d], spans)?;
    for (_, x0) in scored.into_iter().take(2) {
        if let Ok((c, x)) = levenberg_marquardt(&resid, x0, spans) {
            if c < best.0 {
                best = (c, x);
            }
        }
    }
    Ok(best.1)
}

fn sum_sq(r: &[f64]) -> f64 {
    r.iter().map(|v| v * v).sum()
}

/// Levenberg–Marquardt on the residuals `resid` from `x0`, kept inside ±`spans`: the final
/// sum of squares and point.
///
/// Each residual is a full FE eigen-solve (sequential inside), so the search runs two at a
/// time: a trial point's forward-difference neighbours are evaluated beside the trial itself
/// (used when the trial is accepted, as most are; wasted otherwise). The values are the same
/// as one at a time. It stops when an accepted step moves no coordinate by more than
/// `STEP_TOL` (1e-4 in ln units, a 0.01 % change of a stiffness: the fit only centres the
/// ROM, whose box is ±20 % or wider); before, it ran on until eight damped trials in a row
/// failed to lower a misfit that was already flat, half its FE solves.
fn levenberg_marquardt(
    resid: &(dyn Fn(&[f64]) -> anyhow::Result<Vec<f64>> + Sync),
    x0: Vec<f64>,
    spans: &[f64],
) -> anyhow::Result<(f64, Vec<f64>)> {
    use rayon::prelude::*;
    const STEP_TOL: f64 = 1e-4;
    let d = x0.len();
    let h = 1e-3;
    // resid at x and at x + h e_k for every k, side by side.
    let with_neighbours = |x: &[f64]| -> Vec<anyhow::Result<Vec<f64>>> {
        (0..=d)
            .into_par_iter()
            .map(|k| {
                let mut y = x.to_vec();
                if k > 0 {
                    y[k - 1] += h;
                }
                resid(&y)
            })
            .collect()
    };
    let jacobian =
        |r0: &[f64], nb: Vec<anyhow::Result<Vec<f64>>>| -> anyhow::Result<Vec<Vec<f64>>> {
            nb.into_iter()
                .map(|r| Ok(r?.iter().zip(r0).map(|(v, v0)| (v - v0) / h).collect()))
                .collect()
        };
    let mut x = x0;
    let mut evals = with_neighbours(&x).into_iter();
    let mut r0 = evals.next().expect("the point itself")?;
    let mut c0 = sum_sq(&r0);
    let mut jac = jacobian(&r0, evals.collect())?;
    let mut mu = 1e-3;
    for _ in 0..12 {
        let mut accepted = None;
        for _ in 0..8 {
            // (JᵀJ + μ diag(JᵀJ)) δ = −Jᵀ r, d × d by Gaussian elimination.
            let mut a = vec![vec![0.0; d + 1]; d];
            for k in 0..d {
                for l in 0..d {
                    a[k][l] = jac[k].iter().zip(&jac[l]).map(|(u, v)| u * v).sum();
                }
                a[k][k] *= 1.0 + mu;
                a[k][k] += 1e-12;
                a[k][d] = -jac[k].iter().zip(&r0).map(|(u, v)| u * v).sum::<f64>();
            }
            for c in 0..d {
                let piv = (c..d)
                    .max_by(|&i, &j| a[i][c].abs().total_cmp(&a[j][c].abs()))
                    .unwrap_or(c);
                a.swap(c, piv);
                for i in c + 1..d {
                    let f = a[i][c] / a[c][c];
                    let (top, rest) = a.split_at_mut(i);
                    for (x, y) in rest[0][c..].iter_mut().zip(&top[c][c..]) {
                        *x -= f * y;
                    }
                }
            }
            let mut delta = vec![0.0; d];
            for c in (0..d).rev() {
                let s: f64 = (c + 1..d).map(|j| a[c][j] * delta[j]).sum();
                delta[c] = (a[c][d] - s) / a[c][c];
            }
            let y: Vec<f64> = (0..d)
                .map(|k| (x[k] + delta[k]).clamp(-spans[k], spans[k]))
                .collect();
            let mut evals = with_neighbours(&y).into_iter();
            let r = evals.next().expect("the trial itself")?;
            let c = sum_sq(&r);
            if c < c0 {
                mu = (mu * 0.3).max(1e-6);
                accepted = Some((y, r, c, evals.collect::<Vec<_>>()));
                break;
            }
            mu *= 10.0;
        }
        let Some((y, r, c, neighbours)) = accepted else {
            break;
        };
        let step = y
            .iter()
            .zip(&x)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        x = y;
        r0 = r;
        c0 = c;
        if c0 < 1e-14 || step < STEP_TOL {
            break;
        }
        // A neighbour the model cannot solve ends the search at the accepted point, the best
        // one found (before, that Jacobian failed the whole step; the search now stops where
        // the model stops being defined).
        match jacobian(&r0, neighbours) {
            Ok(j) => jac = j,
            Err(_) => break,
        }
    }
    Ok((c0, x))
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
        let labels = select_labels(&pairs, "bolted", &opts.modes, &presence, &mut findings)?;
        let bolted_rows: Vec<&PairRow> = pairs.iter().filter(|p| p.setup == "bolted").collect();
        let band_top_hz = bolted_rows.iter().map(|p| p.freq_hz).fold(0.0, f64::max);
        // A board mechanism (its step-1 refit is `boards_dir`) keeps the baseline joints.
        let board_mech = opts
            .enrich
            .filter(|m| crate::diagnose::library::is_board_mechanism(*m));
        let enr = joint_enrichment(
            &board,
            opts.enrich.filter(|_| board_mech.is_none()),
            opts.enrich_joint,
            JointContext {
                band_top_hz,
                k_con_prior_sd: opts.prior_width,
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
                    opts.prior_width.max(1.0) * 3.0
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
        let new_modes = match opts.enrich.filter(|m| !is_board_mechanism(*m)) {
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
            let used = opts.enrich_new_modes;
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
                        a * cc.log_box.unwrap_or((1.0 + opts.rom_box).ln())
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
                let rom = rom_for(&model, need, &log_axes, opts)?;
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
        let use_shapes = opts.delta.is_some();
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
                sigma_scale: vec![opts.sigma_scale; coords.len()],
                sigma_prior: vec![],
                lkj_eta: opts.lkj_eta,
            },
            errors: ErrorModel {
                n_modes: labels.labels.len(),
                eps: opts.eps,
                delta: opts.delta,
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
        let groups = (opts.smc.n_particles / group).max(1);
        let mut sopts = opts.clone();
        sopts.smc.n_particles = groups * group;
        sopts.smc.groups = groups;
        let mut aux_index: Vec<Vec<usize>> = vec![];
        let aux: Vec<Vec<Arc<Vec<f64>>>> = (0..opts.runs)
            .map(|r| {
                let idx: Vec<usize> = (0..groups)
                    .map(|g| {
                        ((g * opts.runs + r) * step1.draws.len() / (groups * opts.runs))
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
            opts.discrepancy_freq.unwrap_or(0.0),
            "joints",
            &mut findings,
        )?;
        let shape_weights = weigh_shapes(
            &mut target,
            &opts.shape_weights,
            (&draws_mean, Some(&centre)),
            &labels.labels,
            opts.seed,
            "joints",
        )?;
        report_shape_weights(&shape_weights, "joints", verbose, &mut findings);
        clock.lap("shape_weights");
        let (results, acceleration) =
            run_smc(&target, &sopts, "joints", &aux, Some(&centre), verbose)?;
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
                    x0 + (1.0 - opts.rom_box).ln(),
                    x0 + (1.0 + opts.rom_box).ln(),
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
            opts.box_tolerance,
        );
        if !violations.is_empty() {
            bail!(
                "the joint posterior presses against the ROM's box (±{:.0} % around k_con_n_per_m = {k_centre:.4e} N/m, fitted to the bolted modes at the boards' posterior mean{}):\n  {}\nThe joints differ more between measurements than one ROM covers; a per-measurement ROM is not built yet.",
                100.0 * opts.rom_box,
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
        let mut summary = pop.summarize(opts.runs, true);
        let mut js = jt.summarize(opts.runs, false);
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
            opts.residual_draws,
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
                        "updated": opts.enrich_new_modes,
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
        "particles": opts.smc.n_particles,
        "stages_per_run": results.iter().map(|r| r.stages.len()).collect::<Vec<_>>(),
        "max_r_hat": max_rhat,
        "min_ess": min_ess,
        "evidence": ev,
        "acceleration": acceleration,
        "held_out_boards": opts.hold_out_boards,
        "findings": findings.0,
    });
    let p = opts.out.join("update_report.json");
    crate::io::atomic::write_bytes(&p, serde_json::to_string_pretty(&report)?.as_bytes())?;
    outputs.push(p);
    eprintln!(
        "{what}: {} runs × {} particles, {} stages per run, log evidence {:.2} ± {:.2}, max R-hat {:.4}, min ESS {:.0}; {} ROM evaluations in {:.1} s; {}",
        results.len(),
        opts.smc.n_particles,
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
mod convergence_tests {
    use super::*;
    use crate::bayes::diagnostics::summarize;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use rand_distr::{Distribution, Normal};

    fn row(name: &str, chains: &[Vec<f64>]) -> SummaryRow {
        SummaryRow {
            parameter: name.into(),
            board_id: None,
            measurement_id: Some("M001".into()),
            s: summarize(chains),
        }
    }

    fn chains(seed: u64, shifts: &[f64], n: usize) -> Vec<Vec<f64>> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let d = Normal::new(0.0, 1.0).unwrap();
        shifts
            .iter()
            .map(|s| (0..n).map(|_| s + d.sample(&mut rng)).collect())
            .collect()
    }

    #[test]
    fn agreeing_runs_raise_nothing_and_disagreeing_runs_are_named() {
        let good = row("k_con_n_per_m", &chains(1, &[0.0, 0.0], 400));
        assert!(good.s.r_hat < MAX_R_HAT && good.s.ess_bulk > MIN_ESS);
        assert!(convergence_finding(&[good], 2).is_none());
        // Two runs in different modes (two sd apart): R-hat far above 1.05.
        let good = row("mu_ln_k_con", &chains(2, &[0.0, 0.0], 400));
        let bad = row("eps_plate-0-0", &chains(3, &[0.0, 2.0], 400));
        assert!(bad.s.r_hat > 1.3, "{}", bad.s.r_hat);
        let f = convergence_finding(&[good, bad], 2).expect("a warning");
        assert_eq!(f.code, "update.not_converged");
        assert!(f.message.contains("eps_plate-0-0 [M001]"), "{}", f.message);
        assert!(!f.message.contains("mu_ln_k_con"), "{}", f.message);
        // Too few effective draws: 2 runs of 30.
        let short = row("sigma_ln_k_con", &chains(4, &[0.0, 0.0], 30));
        let f = convergence_finding(&[short], 2).expect("a warning");
        assert!(f.message.contains("ESS below 100"), "{}", f.message);
    }
}

#[cfg(test)]
mod mass_term_tests {
    use super::*;

    /// The balance term's sd: the spread of the mean and the readability's uniform rounding
    /// error, never below the floor (relative to the mass); with the floor at 0, the readings'
    /// own sd; readings ingest flagged as inconsistent keep their full spread.
    #[test]
    fn the_mass_term_sd_is_the_readings_sd_floored() {
        let row = MassRow {
            mass_g: 12.5,
            n_stable: 6,
            std_g: 6e-5,
            resolution_g: 1e-4,
            inconsistent: false,
        };
        let own = (6e-5f64 * 6e-5 / 6.0 + 1e-4 * 1e-4 / 12.0).sqrt();
        let mut f = Findings::default();
        let floored = mass_obs(
            &row,
            "PCB-01",
            UpdateOptions::DEFAULT_MASS_FLOOR_REL,
            &mut f,
        )
        .expect("a mass term");
        assert_eq!(floored.sd_g, 2e-4 * 12.5);
        assert_eq!(floored.mass_g, 12.5);
        let bare = mass_obs(&row, "PCB-01", 0.0, &mut f).expect("a mass term");
        assert!((bare.sd_g - own).abs() < 1e-15, "{} vs {own}", bare.sd_g);
        let spread = MassRow {
            inconsistent: true,
            ..row
        };
        let s = mass_obs(&spread, "PCB-01", 0.0, &mut f).expect("a mass term");
        assert!((s.sd_g - (6e-5f64 * 6e-5 + 1e-4 * 1e-4 / 12.0).sqrt()).abs() < 1e-15);
        assert_eq!(f.0.len(), 1, "the inconsistent readings are reported");
        let none = MassRow { n_stable: 0, ..row };
        assert!(mass_obs(&none, "PCB-01", 0.0, &mut f).is_none());
    }
}

#[cfg(test)]
mod joint_prep_tests {
    use super::*;
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

#[cfg(test)]
mod thickness_tests {
    use super::*;

    /// A board's measured core thickness becomes an observation of its thickness coordinate
    /// (relative to the board file's, sd THICKNESS_SD_M relative); a board the sheet gives
    /// none for, or one outside the ROM's box, gets none and a warning naming it. The core's
    /// mass share: the same board without its copper weighs its core.
    #[test]
    fn measured_thickness_is_an_observation_of_the_boards_coordinate() {
        let board = Board::default_board();
        let h0 = board.core.thickness_m;
        let params: Vec<String> = ["e_x_pa", "mass_scale", names::CORE_THICKNESS]
            .map(String::from)
            .to_vec();
        let units: Vec<String> = ["A", "B", "C"].map(String::from).to_vec();
        let given = BTreeMap::from([("A".to_string(), 1.06 * h0), ("C".to_string(), 1.5 * h0)]);
        let mut findings = Findings::default();
        let obs = thickness_obs(&params, h0, &units, &given, 0.2, &mut findings);
        assert_eq!(obs.len(), 3);
        assert_eq!(obs[0].len(), 1);
        let (k, x, sd) = obs[0][0];
        assert_eq!(k, 2);
        assert!((x - 0.06).abs() < 1e-12 && (sd - THICKNESS_SD_M / h0).abs() < 1e-15);
        assert!(obs[1].is_empty() && obs[2].is_empty());
        let codes: Vec<(&str, bool)> = findings
            .iter()
            .map(|f| (f.code.as_str(), f.message.starts_with("board ")))
            .collect();
        assert!(
            codes.contains(&("update.thickness_unknown", true)),
            "{codes:?}"
        );
        assert!(
            codes.contains(&("update.thickness_outside_box", true)),
            "{codes:?}"
        );
        // Without the parameter: nothing observed, nothing said.
        let mut none = Findings::default();
        assert!(thickness_obs(&params[..2], h0, &units, &given, 0.2, &mut none).is_empty());
        assert!(none.is_empty());
        let mesh = crate::fem::MeshOptions { nx: 8, ny: 6 };
        let plain = FeModel::build(&board, Setup::Free, &mesh).unwrap();
        assert!(core_thickness_mass(&plain).unwrap().is_none());
        let model = FeModel::build_with(
            &board,
            Setup::Free,
            &mesh,
            crate::fem::ModelOptions {
                core_thickness: true,
            },
        )
        .unwrap();
        let (_, h, share) = core_thickness_mass(&model).unwrap().unwrap();
        assert_eq!(h, h0);
        let mut bare = board.clone();
        bare.copper.clear();
        let core = FeModel::build(&bare, Setup::Free, &mesh).unwrap();
        let want = core.total_mass_kg(&core.nominal_params()).unwrap()
            / model.total_mass_kg(&model.nominal_params()).unwrap();
        assert!(
            (share - want).abs() < 1e-12 && want < 1.0,
            "share {share} vs {want}"
        );
    }
}

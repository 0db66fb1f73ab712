//! Scenario files of the virtual lab (`data/lab/*.toml`, schema
//! `schemas/lab_scenario.schema.json`): what campaign to simulate (boards, measurements per
//! board and setup), how the truth is built (mesh, joint details, parameter population),
//! how the instruments behave (spectral lines, damping, noise, drop-outs, balance), and
//! which concealed physical effects are switched on.
//!
//! Every section has defaults equal to the paper-like campaign, so an effect scenario is
//! a few lines. Parsing rejects unknown fields; [`Scenario::validate`] checks every value
//! for physical sense and names the field, what was expected and what was found.
//! Units are SI and carried in the field names.

use serde::{Deserialize, Serialize};

use super::LabError;

/// A complete scenario.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scenario {
    /// Short name, written into the truth file.
    pub name: String,
    /// Free text: what the scenario is for.
    #[serde(default)]
    pub description: String,
    /// Seed used when the caller gives none.
    #[serde(default = "d_seed")]
    pub seed: u64,
    #[serde(default)]
    pub campaign: CampaignPlan,
    #[serde(default)]
    pub truth: TruthModel,
    #[serde(default)]
    pub population: Population,
    #[serde(default)]
    pub measurement: Instrument,
    #[serde(default)]
    pub lab: LabConditions,
    #[serde(default)]
    pub balance: Balance,
    #[serde(default)]
    pub effects: Effects,
    /// `exact` (default): the lab writes tidy files. `realistic`: every habit of a real lab
    /// is on unless `[habits]` switches it off.
    #[serde(default, skip_serializing_if = "Preset::is_exact")]
    pub preset: Preset,
    /// The habits of a real lab, each switchable; unset ones follow `preset`.
    #[serde(default, skip_serializing_if = "Habits::is_unset")]
    pub habits: Habits,
}

/// The scenario's preset for the lab habits.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Preset {
    /// Tidy files: every habit off unless switched on.
    #[default]
    Exact,
    /// A real lab's files: every habit on unless switched off.
    Realistic,
}

impl Preset {
    fn is_exact(&self) -> bool {
        *self == Preset::Exact
    }
}

/// The habits of a real lab in the campaign files (`[habits]`). Each is `true`/`false`, or
/// unset to follow the scenario's `preset`. What each does: `super::habits`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Habits {
    /// Balance logs: a check weight `REF-10G` read at the start of each weighing day, the
    /// board tray zeroed (`Z A`) and tared (`T S`) under the ID `TRAY` before every board.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reference_weights: Option<bool>,
    /// One board weighed once more on a later day, in a log file of its own.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reweighed_board: Option<bool>,
    /// One board ID spelled differently on one sheet row and one balance line (`PCB-3` for
    /// `PCB-03`), and a trailing space on another sheet row's board_id.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub id_variants: Option<bool>,
    /// One free-free measurement repeated after a bad one (mostly noise): both rows on the
    /// sheet, the bad one's note starting `INVALID`, the repeat's note `repeat of <id>`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub repeated_measurement: Option<bool>,
    /// Bolted measurements on a coarser grid than the free ones, shifted by 1 mm in x on
    /// every bolted day after the first.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub scan_grids: Option<bool>,
    /// Two scan points off the board in bolted measurements: a bolt head and the fixture.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub off_board_points: Option<bool>,
    /// Empty temperature and date cells on a few sheet rows.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sheet_gaps: Option<bool>,
}

impl Habits {
    fn is_unset(&self) -> bool {
        *self == Habits::default()
    }
}

/// The habits after the preset: plain switches.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct HabitSwitches {
    pub reference_weights: bool,
    pub reweighed_board: bool,
    pub id_variants: bool,
    pub repeated_measurement: bool,
    pub scan_grids: bool,
    pub off_board_points: bool,
    pub sheet_gaps: bool,
}

impl HabitSwitches {
    /// Whether any habit is on.
    pub fn any(&self) -> bool {
        *self != HabitSwitches::default()
    }
}

fn d_seed() -> u64 {
    20_240_601
}

/// Which boards are measured how often.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CampaignPlan {
    /// Number of nominally identical boards, named `PCB-01`, `PCB-02`, ….
    pub n_boards: usize,
    /// Free-free (hammer) measurements per board.
    pub free_per_board: usize,
    /// Bolted (shaker) measurements: groups of boards (1-based) with a count each.
    pub bolted: Vec<BoltedGroup>,
    /// Date of the first measurement day, `YYYY-MM-DD`.
    pub start_date: String,
    /// Operators, assigned in turn.
    pub operators: Vec<String>,
    /// Nominal bolt tightening torque, N·m.
    pub torque_nm: f64,
    /// Write each row's board dimensions on the sheet, after the other columns:
    /// `length_mm` and `width_mm` (caliper, to 0.01 mm: the board file's `length_x_m` and
    /// `width_y_m`, which the truth does not vary) and `thickness_mm` (micrometer, to
    /// 0.001 mm: the overall thickness a micrometer reads over the copper, the board's FR-4
    /// core as drawn, see `population.thickness_rel_std`, plus the board file's copper
    /// layers). Default false: no such columns.
    #[serde(skip_serializing_if = "is_false")]
    pub sheet_dimensions: bool,
}

fn is_false(v: &bool) -> bool {
    !*v
}

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

impl Default for CampaignPlan {
    fn default() -> Self {
        CampaignPlan {
            n_boards: 7,
            free_per_board: 5,
            bolted: vec![
                BoltedGroup {
                    boards: vec![1, 2],
                    per_board: 9,
                    purpose: "updating".into(),
                },
                BoltedGroup {
                    boards: vec![3, 4, 5, 6],
                    per_board: 3,
                    purpose: "validation".into(),
                },
            ],
            start_date: "2025-03-03".into(),
            operators: vec!["A. Weber".into(), "J. Kim".into()],
            torque_nm: 0.5,
            sheet_dimensions: false,
        }
    }
}

/// Bolted measurements of a group of boards.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoltedGroup {
    /// 1-based board numbers.
    pub boards: Vec<usize>,
    /// Measurements per board, each with its own bolt set.
    pub per_board: usize,
    /// Free text written into the sheet's notes (e.g. `updating`, `validation`).
    #[serde(default)]
    pub purpose: String,
}

/// How the truth model is built: richer than the updating model.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TruthModel {
    /// Truth mesh (finer than the board's default mesh), elements along x. Default
    /// 80 × 50: on the built-in board within 3 ppm of 160 × 100 on the first 8 free
    /// frequencies (its node lines on the copper's edges, as every mesh's), so the truth is
    /// the converged plate, not one discretization of it.
    pub mesh_nx: usize,
    /// Elements along y.
    pub mesh_ny: usize,
    /// Modes computed for a free measurement (in band and above it).
    pub n_free_modes: usize,
    /// Modes computed for a bolted measurement (in band and above it).
    pub n_bolted_modes: usize,
    /// Share of each bolt's head, washer and nut that rides with the board's clamped
    /// patch, kg per joint. Default 0: the updating model's baseline joint has no mass, and
    /// 0.2 g per joint already moves the bolted modes by up to 0.18 % (the default board),
    /// ten times the frequency noise, so a non-zero value is missing physics for the
    /// diagnosis to find (mechanism `joint_mass`), not a refinement below the noise.
    pub joint_mass_kg: f64,
    /// Relative scatter of the four joints' contact stiffness around the measurement's
    /// K_con (the bolts are never tightened exactly alike).
    pub per_joint_k_rel_std: f64,
    /// The truth's physics: `plate`, hbmu's own plate model on a finer mesh (the exact-model
    /// check: does the updating recover its own model?), or `solid`, the layered 3D solid of
    /// [`crate::lab::solid`] solved by CalculiX (independent of the updating model).
    pub physics: Physics,
    /// Options of the solid truth.
    pub solid: crate::lab::solid::SolidOptions,
}

/// Which physics computes the truth.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Physics {
    #[default]
    Plate,
    Solid,
}

impl Default for TruthModel {
    fn default() -> Self {
        TruthModel {
            mesh_nx: 80,
            mesh_ny: 50,
            n_free_modes: 12,
            n_bolted_modes: 11,
            joint_mass_kg: 0.0,
            per_joint_k_rel_std: 0.02,
            physics: Physics::Plate,
            solid: crate::lab::solid::SolidOptions::default(),
        }
    }
}

/// The hierarchical truth: population of board parameters and of the contact stiffness.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Population {
    /// Relative standard deviations of (E_x, E_y, G_xy, mass scale) around the board
    /// file's nominal values.
    pub rel_std: [f64; 4],
    /// Correlation matrix of the same four, symmetric positive definite.
    pub correlation: [[f64; 4]; 4],
    /// Mean contact stiffness per joint, N/m.
    pub k_con_mean_n_per_m: f64,
    /// Relative standard deviation of K_con between bolted measurements.
    pub k_con_rel_std: f64,
    /// Relative standard deviation of each board's FR-4 core thickness around the board
    /// file's `core.thickness_m` (a laminate's ±10 % tolerance is about 0.05), drawn
    /// independently of the four above. Default 0: every board at the nominal thickness.
    /// Plate truth only.
    #[serde(skip_serializing_if = "is_zero")]
    pub thickness_rel_std: f64,
}

impl Default for Population {
    fn default() -> Self {
        Population {
            rel_std: [0.018, 0.016, 0.02, 0.012],
            correlation: [
                [1.0, 0.5, 0.3, 0.4],
                [0.5, 1.0, 0.3, 0.4],
                [0.3, 0.3, 1.0, 0.2],
                [0.4, 0.4, 0.2, 1.0],
            ],
            k_con_mean_n_per_m: 5.0e6,
            k_con_rel_std: 0.085,
            thickness_rel_std: 0.0,
        }
    }
}

/// Vibrometer, hammer and shaker behaviour.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Instrument {
    /// Free-free: spectral lines and top of band, Hz (lines at k·Δf, k = 1..n).
    pub free_lines: usize,
    pub free_max_hz: f64,
    /// Bolted: spectral lines and top of band, Hz.
    pub bolted_lines: usize,
    pub bolted_max_hz: f64,
    /// Modal damping ratios are drawn log-uniformly in [min, max].
    pub damping_min: f64,
    pub damping_max: f64,
    /// Noise floor: standard deviation of the complex noise, relative to the largest
    /// |H| of the measurement (common to all lines and points).
    pub noise_floor_rel: f64,
    /// Noise proportional to |H| (excitation, leakage), relative.
    pub noise_prop_rel: f64,
    /// Probability that a scan point has no record (vibrometer marked it invalid).
    pub missing_point_prob: f64,
    /// Probability that a record is mostly noise (speckle drop-out).
    pub dropout_point_prob: f64,
    /// Write coherence records (function type 6) in every other measurement.
    pub coherence: bool,
    /// Free-free: rigid-body modes on the foam, range of their frequencies, Hz.
    pub suspension_hz: [f64; 2],
    /// Shaker cross-axis motion: standard deviation of the base rocking, expressed as the
    /// rigid base motion across the scan grid relative to the reference motion.
    pub base_rocking_rel: f64,
}

impl Default for Instrument {
    fn default() -> Self {
        Instrument {
            free_lines: 2000,
            free_max_hz: 5000.0,
            bolted_lines: 1600,
            bolted_max_hz: 4000.0,
            damping_min: 0.005,
            damping_max: 0.02,
            noise_floor_rel: 3.0e-4,
            noise_prop_rel: 0.01,
            missing_point_prob: 0.02,
            dropout_point_prob: 0.02,
            coherence: true,
            suspension_hz: [8.0, 25.0],
            base_rocking_rel: 0.03,
        }
    }
}

/// Lab temperature during the campaign: T = mean + swing · sin(2π k / period) + noise
/// over the measurement index k.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LabConditions {
    pub temperature_mean_c: f64,
    pub temperature_swing_c: f64,
    /// Period of the slow swing, in measurements.
    pub temperature_period: f64,
    pub temperature_noise_c: f64,
}

impl Default for LabConditions {
    fn default() -> Self {
        LabConditions {
            temperature_mean_c: 22.5,
            temperature_swing_c: 1.0,
            temperature_period: 23.0,
            temperature_noise_c: 0.2,
        }
    }
}

/// The balance.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Balance {
    /// Weighing sessions per board (each in a possibly different unit).
    pub sessions_per_board: usize,
    /// Stable readings per session.
    pub stable_per_session: usize,
    /// Readability d, g (0.1 mg for an analytical balance).
    pub resolution_g: f64,
    /// Repeatability of a stable reading, in units of d.
    pub repeatability_d: f64,
    /// Probability of a busy or error line before a reading.
    pub glitch_prob: f64,
    /// Probability that a stable reading arrives garbled (a transmission glitch the
    /// ingest must report and drop).
    pub garbled_prob: f64,
}

impl Default for Balance {
    fn default() -> Self {
        Balance {
            sessions_per_board: 2,
            stable_per_session: 3,
            resolution_g: 1e-4,
            repeatability_d: 0.4,
            glitch_prob: 0.3,
            garbled_prob: 0.05,
        }
    }
}

/// The concealed effects (a)–(e); all off is the null scenario.
#[derive(Clone, Debug, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Effects {
    pub rotational_restraint: Option<RotationalRestraint>,
    pub loose_bolt: Option<LooseBolt>,
    pub temperature: Option<TemperatureSoftening>,
    pub lumped_mass: Option<LumpedMass>,
    pub compliant_fixture: Option<CompliantFixture>,
    /// (f) Kept out of the diagnosis's mechanism library on purpose: the test of a misfit
    /// the library cannot explain.
    pub underfill: Option<Underfill>,
}

impl Effects {
    /// Whether any effect is on.
    pub fn any(&self) -> bool {
        self.rotational_restraint.is_some()
            || self.loose_bolt.is_some()
            || self.temperature.is_some()
            || self.lumped_mass.is_some()
            || self.compliant_fixture.is_some()
            || self.underfill.is_some()
    }
}

/// (a) The clamped patch restrains the board's rotation: bending moment through the joint.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RotationalRestraint {
    /// Rotational stiffness per joint and axis, N·m/rad.
    pub k_rot_nm_per_rad: f64,
}

/// (b) One loose bolt in a share of the bolted measurements.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LooseBolt {
    /// Share of bolted measurements with one loose bolt, in [0, 1].
    pub share: f64,
    /// Contact stiffness of the loose joint relative to the others, in (0, 1).
    pub stiffness_factor: f64,
}

/// (c) FR-4 moduli soften with temperature: E(T) = E_ref (1 + α (T − T_ref)) for
/// E_x, E_y and G_xy.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TemperatureSoftening {
    /// α, 1/K (negative: softening).
    pub coefficient_per_k: f64,
    /// T_ref, °C: the temperature the board parameters are given at.
    pub reference_c: f64,
}

/// (d) An unmodelled lumped mass (component, glue, connector) on every board.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LumpedMass {
    pub mass_kg: f64,
    pub x_m: f64,
    pub y_m: f64,
}

/// (f) Epoxy underfill under a BGA in every board: the laminate's core is `stiffness_factor`
/// times as stiff in bending over a disc (copper and mass unchanged). A local stiffening: not
/// in the diagnosis's library (which has a local stiffness loss and an added mass).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Underfill {
    pub x_m: f64,
    pub y_m: f64,
    pub radius_m: f64,
    /// Factor on the core's bending stiffness in the disc, > 1.
    pub stiffness_factor: f64,
}

/// (e) The shaker fixture is compliant: a mass on a spring between armature and bolts.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CompliantFixture {
    pub k_fix_n_per_m: f64,
    pub m_fix_kg: f64,
}

impl Scenario {
    /// The habits in force: each as set in `[habits]`, else on under the `realistic` preset.
    pub fn habits(&self) -> HabitSwitches {
        let on = self.preset == Preset::Realistic;
        let h = &self.habits;
        let r = |v: Option<bool>| v.unwrap_or(on);
        HabitSwitches {
            reference_weights: r(h.reference_weights),
            reweighed_board: r(h.reweighed_board),
            id_variants: r(h.id_variants),
            repeated_measurement: r(h.repeated_measurement),
            scan_grids: r(h.scan_grids),
            off_board_points: r(h.off_board_points),
            sheet_gaps: r(h.sheet_gaps),
        }
    }

    /// Parse and validate a scenario from TOML text.
    pub fn from_toml_str(text: &str) -> Result<Scenario, LabError> {
        let s: Scenario =
            toml::from_str(text).map_err(|e| LabError::ScenarioParse(e.to_string()))?;
        s.validate()?;
        Ok(s)
    }

    /// Check every value; the error names the field, what was expected and what was found.
    pub fn validate(&self) -> Result<(), LabError> {
        validate_campaign(&self.campaign)?;
        validate_truth(&self.truth)?;
        validate_population(&self.population, &self.truth)?;
        validate_measurement(&self.measurement)?;
        validate_lab_and_balance(&self.lab, &self.balance)?;
        validate_effects(&self.effects)
    }
}

/// A scenario error: `field` expected `expected`, found `found`.
fn bad(field: &str, expected: &str, found: impl std::fmt::Display) -> LabError {
    LabError::ScenarioInvalid {
        field: field.to_string(),
        expected: expected.to_string(),
        found: found.to_string(),
    }
}

/// `v` must be finite and positive.
fn pos(field: &str, v: f64) -> Result<(), LabError> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(bad(field, "a finite positive number", v))
    }
}

/// `v` must be finite and non-negative.
fn nonneg(field: &str, v: f64) -> Result<(), LabError> {
    if v.is_finite() && v >= 0.0 {
        Ok(())
    } else {
        Err(bad(field, "a finite number >= 0", v))
    }
}

/// `v` must be a probability.
fn prob(field: &str, v: f64) -> Result<(), LabError> {
    if (0.0..=1.0).contains(&v) {
        Ok(())
    } else {
        Err(bad(field, "a probability in [0, 1]", v))
    }
}

/// Checks the campaign plan.
fn validate_campaign(c: &CampaignPlan) -> Result<(), LabError> {
    if c.n_boards == 0 || c.n_boards > 99 {
        return Err(bad("campaign.n_boards", "1 to 99 boards", c.n_boards));
    }
    if c.free_per_board > 999 {
        return Err(bad(
            "campaign.free_per_board",
            "at most 999",
            c.free_per_board,
        ));
    }
    let mut seen = vec![false; c.n_boards + 1];
    for (g, grp) in c.bolted.iter().enumerate() {
        for &b in &grp.boards {
            if b == 0 || b > c.n_boards {
                return Err(bad(
                    &format!("campaign.bolted[{g}].boards"),
                    &format!("board numbers in 1..={}", c.n_boards),
                    b,
                ));
            }
            if seen[b] {
                return Err(bad(
                    &format!("campaign.bolted[{g}].boards"),
                    "each board in at most one group",
                    b,
                ));
            }
            seen[b] = true;
        }
        if grp.per_board > 99 {
            return Err(bad(
                &format!("campaign.bolted[{g}].per_board"),
                "at most 99",
                grp.per_board,
            ));
        }
    }
    if chrono::NaiveDate::parse_from_str(&c.start_date, "%Y-%m-%d").is_err() {
        return Err(bad(
            "campaign.start_date",
            "a date YYYY-MM-DD",
            &c.start_date,
        ));
    }
    if c.operators.is_empty() {
        return Err(bad("campaign.operators", "at least one name", "[]"));
    }
    pos("campaign.torque_nm", c.torque_nm)?;
    Ok(())
}

/// Checks the truth model.
fn validate_truth(t: &TruthModel) -> Result<(), LabError> {
    if t.mesh_nx < 4 || t.mesh_ny < 4 {
        return Err(bad(
            "truth.mesh_nx/mesh_ny",
            "at least 4 × 4 elements",
            format!("{} × {}", t.mesh_nx, t.mesh_ny),
        ));
    }
    if t.n_free_modes == 0 || t.n_bolted_modes == 0 {
        return Err(bad(
            "truth.n_free_modes/n_bolted_modes",
            ">= 1",
            format!("{} / {}", t.n_free_modes, t.n_bolted_modes),
        ));
    }
    nonneg("truth.joint_mass_kg", t.joint_mass_kg)?;
    nonneg("truth.per_joint_k_rel_std", t.per_joint_k_rel_std)?;
    if t.per_joint_k_rel_std > 0.2 {
        return Err(bad(
            "truth.per_joint_k_rel_std",
            "at most 0.2",
            t.per_joint_k_rel_std,
        ));
    }
    t.solid
        .check()
        .map_err(|(field, expected, found)| bad(&field, &expected, found))?;
    if t.physics == Physics::Solid && t.joint_mass_kg > 0.0 {
        return Err(bad(
            "truth.joint_mass_kg",
            "0 with truth.physics = \"solid\" (its riding mass is truth.solid.riding_mass_kg)",
            t.joint_mass_kg,
        ));
    }
    Ok(())
}

/// Checks the population (some limits depend on the truth's physics `t`).
fn validate_population(p: &Population, t: &TruthModel) -> Result<(), LabError> {
    for (i, s) in p.rel_std.iter().enumerate() {
        nonneg(&format!("population.rel_std[{i}]"), *s)?;
        if *s > 0.2 {
            return Err(bad(&format!("population.rel_std[{i}]"), "at most 0.2", s));
        }
    }
    for i in 0..4 {
        if (p.correlation[i][i] - 1.0).abs() > 1e-12 {
            return Err(bad(
                &format!("population.correlation[{i}][{i}]"),
                "1 on the diagonal",
                p.correlation[i][i],
            ));
        }
        for j in 0..4 {
            let (a, b) = (p.correlation[i][j], p.correlation[j][i]);
            if !(a.is_finite() && (a - b).abs() <= 1e-12 && a.abs() <= 1.0) {
                return Err(bad(
                    &format!("population.correlation[{i}][{j}]"),
                    "a symmetric matrix with entries in [-1, 1]",
                    a,
                ));
            }
        }
    }
    if super::truth::cholesky4(&p.correlation).is_none() {
        return Err(bad(
            "population.correlation",
            "a positive definite matrix",
            format!("{:?}", p.correlation),
        ));
    }
    pos("population.k_con_mean_n_per_m", p.k_con_mean_n_per_m)?;
    nonneg("population.k_con_rel_std", p.k_con_rel_std)?;
    if p.k_con_rel_std > 0.3 {
        return Err(bad(
            "population.k_con_rel_std",
            "at most 0.3",
            p.k_con_rel_std,
        ));
    }
    if !(p.thickness_rel_std.is_finite() && (0.0..0.2).contains(&p.thickness_rel_std)) {
        return Err(bad(
            "population.thickness_rel_std",
            "a finite number in [0, 0.2)",
            p.thickness_rel_std,
        ));
    }
    if t.physics == Physics::Solid && p.thickness_rel_std > 0.0 {
        return Err(bad(
            "population.thickness_rel_std",
            "0 with truth.physics = \"solid\" (a per-board core thickness needs the plate truth)",
            p.thickness_rel_std,
        ));
    }
    Ok(())
}

/// Checks the instrument.
fn validate_measurement(m: &Instrument) -> Result<(), LabError> {
    for (f, n, hz) in [
        ("measurement.free", m.free_lines, m.free_max_hz),
        ("measurement.bolted", m.bolted_lines, m.bolted_max_hz),
    ] {
        if !(16..=100_000).contains(&n) {
            return Err(bad(&format!("{f}_lines"), "16 to 100000 lines", n));
        }
        pos(&format!("{f}_max_hz"), hz)?;
    }
    if !(m.damping_min > 0.0 && m.damping_min <= m.damping_max && m.damping_max < 0.2) {
        return Err(bad(
            "measurement.damping_min/damping_max",
            "0 < min <= max < 0.2",
            format!("{} / {}", m.damping_min, m.damping_max),
        ));
    }
    nonneg("measurement.noise_floor_rel", m.noise_floor_rel)?;
    nonneg("measurement.noise_prop_rel", m.noise_prop_rel)?;
    prob("measurement.missing_point_prob", m.missing_point_prob)?;
    prob("measurement.dropout_point_prob", m.dropout_point_prob)?;
    if !(0.0..=0.3).contains(&m.base_rocking_rel) {
        return Err(bad(
            "measurement.base_rocking_rel",
            "a fraction in [0, 0.3]",
            m.base_rocking_rel,
        ));
    }
    if !(m.suspension_hz[0] > 0.0 && m.suspension_hz[0] <= m.suspension_hz[1]) {
        return Err(bad(
            "measurement.suspension_hz",
            "[lo, hi] with 0 < lo <= hi",
            format!("{:?}", m.suspension_hz),
        ));
    }
    Ok(())
}

/// Checks the lab conditions and the balance.
fn validate_lab_and_balance(l: &LabConditions, b: &Balance) -> Result<(), LabError> {
    if !(l.temperature_mean_c > -50.0 && l.temperature_mean_c < 100.0) {
        return Err(bad(
            "lab.temperature_mean_c",
            "-50 to 100 °C",
            l.temperature_mean_c,
        ));
    }
    nonneg("lab.temperature_swing_c", l.temperature_swing_c)?;
    pos("lab.temperature_period", l.temperature_period)?;
    nonneg("lab.temperature_noise_c", l.temperature_noise_c)?;
    if b.sessions_per_board == 0 || b.stable_per_session == 0 {
        return Err(bad(
            "balance.sessions_per_board/stable_per_session",
            ">= 1",
            format!("{} / {}", b.sessions_per_board, b.stable_per_session),
        ));
    }
    if ![1e-3, 1e-4, 1e-5]
        .iter()
        .any(|d| (b.resolution_g - d).abs() < 1e-12)
    {
        return Err(bad(
            "balance.resolution_g",
            "1e-3, 1e-4 or 1e-5 g",
            b.resolution_g,
        ));
    }
    nonneg("balance.repeatability_d", b.repeatability_d)?;
    prob("balance.glitch_prob", b.glitch_prob)?;
    prob("balance.garbled_prob", b.garbled_prob)?;
    Ok(())
}

/// Checks the systematic effects.
fn validate_effects(e: &Effects) -> Result<(), LabError> {
    if let Some(r) = &e.rotational_restraint {
        pos(
            "effects.rotational_restraint.k_rot_nm_per_rad",
            r.k_rot_nm_per_rad,
        )?;
    }
    if let Some(lb) = &e.loose_bolt {
        prob("effects.loose_bolt.share", lb.share)?;
        if !(lb.stiffness_factor > 0.0 && lb.stiffness_factor < 1.0) {
            return Err(bad(
                "effects.loose_bolt.stiffness_factor",
                "a factor in (0, 1)",
                lb.stiffness_factor,
            ));
        }
    }
    if let Some(tc) = &e.temperature {
        if !(tc.coefficient_per_k.is_finite() && tc.coefficient_per_k.abs() < 0.05) {
            return Err(bad(
                "effects.temperature.coefficient_per_k",
                "|α| < 0.05 1/K",
                tc.coefficient_per_k,
            ));
        }
        if !tc.reference_c.is_finite() {
            return Err(bad(
                "effects.temperature.reference_c",
                "a finite °C",
                tc.reference_c,
            ));
        }
    }
    if let Some(lm) = &e.lumped_mass {
        pos("effects.lumped_mass.mass_kg", lm.mass_kg)?;
        nonneg("effects.lumped_mass.x_m", lm.x_m)?;
        nonneg("effects.lumped_mass.y_m", lm.y_m)?;
    }
    if let Some(f) = &e.compliant_fixture {
        pos("effects.compliant_fixture.k_fix_n_per_m", f.k_fix_n_per_m)?;
        pos("effects.compliant_fixture.m_fix_kg", f.m_fix_kg)?;
    }
    if let Some(d) = &e.underfill {
        nonneg("effects.underfill.x_m", d.x_m)?;
        nonneg("effects.underfill.y_m", d.y_m)?;
        pos("effects.underfill.radius_m", d.radius_m)?;
        if !(d.stiffness_factor.is_finite() && d.stiffness_factor > 1.0) {
            return Err(bad(
                "effects.underfill.stiffness_factor",
                "a finite factor above 1",
                d.stiffness_factor,
            ));
        }
    }
    Ok(())
}

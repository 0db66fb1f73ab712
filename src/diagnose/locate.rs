//! Locate: posterior-predictive checks of the updated model against the recordings.
//!
//! Pure: plain data in ([`LocateInput`], read from a work directory by
//! `io::diagnose_inputs`), plain data out ([`Located`], serialisable). Five checks:
//!
//! 1. **Modes** ([`ModeCheck`]), per (setup, label): the mean relative residual
//!    r = (f_measured − f̄_model)/f̄_model over the measurements, tested against its scatter.
//!    The prediction-error scale ε of an updated mode is *inferred*, so a systematic misfit is
//!    partly absorbed into a large ε and the standardized residuals look like N(0, 1); the
//!    misfit still shows as (i) a mean of r that is consistently away from zero across
//!    measurements and boards (this test ignores the predictive sd on purpose), (ii) an inferred
//!    ε far above the measurement-scatter level (the ε of the best-fitting setup, the free-free
//!    one in a paper-like campaign), (iii) validation modes (not used for updating) with a
//!    mean residual: the same test (i) applies to them.
//! 2. **Measurements** ([`MeasurementCheck`]): a joint outlier statistic over a measurement's
//!    modes, robust to a contaminated minority (a loose bolt in 30 % of the bolted measurements).
//! 3. **Covariates** ([`CovariateTest`]): every sheet column that varies within a setup,
//!    numeric (regression slope) or categorical (one-way ANOVA), blocked by board and
//!    adjusted for the measurements' own fitted parameters (a bolted measurement's contact
//!    stiffness), so that a residual pattern the model's form ties to them is not read as a
//!    sheet column's effect.
//! 4. **Unpaired modes** ([`UnpairedCluster`], [`ModelModePresence`]): identified modes with no
//!    accepted pair clustered by frequency; model modes never seen.
//! 5. A summary ([`Located`]) and the [`Signature`] that screening regresses on sensitivities.
//!
//! Multiplicity: Benjamini–Hochberg within each family (modes, measurements, covariates) at
//! [`LocateOptions::fdr`]; see there for the default and why.

use super::shapes::{shape_checks, ShapeCheck};
use crate::bayes::stats::median;
use serde::Serialize;
use statrs::distribution::{ChiSquared, ContinuousCDF, FisherSnedecor, Normal, StudentsT};
use std::collections::{BTreeMap, BTreeSet};

// ---------------------------------------------------------------------------------------------
// Input.

/// One paired mode of one measurement against the updated model (a row of an update step's
/// `residuals.parquet`; see `update::posterior::residuals`).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ResidualObs {
    pub measurement_id: String,
    pub board_id: String,
    pub setup: String,
    pub label: String,
    /// Identified natural frequency, Hz.
    pub freq_hz: f64,
    /// Posterior mean of the model frequency for this measurement's unit, Hz.
    pub model_freq_hz_mean: f64,
    /// Posterior-predictive sd, Hz: posterior sd of the model frequency plus, for updated modes
    /// only, the inferred prediction error (ε/2 · f). Validation modes carry no error term.
    pub predictive_sd_hz: f64,
    /// (freq_hz − model_freq_hz_mean) / model_freq_hz_mean.
    pub rel_residual: f64,
    /// (freq_hz − model_freq_hz_mean) / predictive_sd_hz.
    pub std_residual: f64,
    /// Whether the label's frequencies were used for updating (false: validation mode).
    pub used_for_updating: bool,
    /// MAC of the measured and the model shape (None: no usable shape).
    pub mac: Option<f64>,
}

/// Posterior draws of the inferred prediction-error scale of one mode: `eps_<label>` of an
/// update step's `population.parquet` (relative sd of the eigenvalue λ = ω², dimensionless;
/// the relative frequency sd is ε/2).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct EpsDraws {
    pub setup: String,
    pub label: String,
    pub draws: Vec<f64>,
}

/// A measurement (status ok) of the sheet.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct MeasurementInfo {
    pub measurement_id: String,
    pub board_id: String,
    pub setup: String,
}

/// Values of one sheet column, aligned with [`LocateInput::measurements`] (`None`: empty cell).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub enum CovariateValues {
    Numeric(Vec<Option<f64>>),
    Categorical(Vec<Option<String>>),
}

/// One sheet column to test residuals against.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Covariate {
    /// Column name (as in the sheet, or derived, e.g. `date_day`).
    pub name: String,
    /// Unit of a numeric covariate (`K`... as the table says; empty when none).
    pub unit: String,
    pub values: CovariateValues,
}

/// An identified mode (a row of `extract/modes.parquet`).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct IdentifiedMode {
    pub measurement_id: String,
    pub setup: String,
    /// Mode number within the measurement (1-based).
    pub mode: i32,
    pub freq_hz: f64,
}

/// A row of `pair/pairs.parquet`: a model mode and what it was paired with.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct PairObs {
    pub measurement_id: String,
    pub setup: String,
    pub label: String,
    /// Identified mode number, when paired.
    pub mode: Option<i32>,
    pub model_freq_hz: Option<f64>,
    pub accepted: bool,
    /// The model mode had no identified counterpart in this measurement.
    pub missing: bool,
}

/// Everything [`locate`] looks at.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct LocateInput {
    pub measurements: Vec<MeasurementInfo>,
    pub covariates: Vec<Covariate>,
    pub residuals: Vec<ResidualObs>,
    pub eps: Vec<EpsDraws>,
    pub identified: Vec<IdentifiedMode>,
    pub pairs: Vec<PairObs>,
    /// The updating's own per-measurement parameters (step 2: each bolted measurement's
    /// contact stiffness), ln of the posterior median: measurement id → values in
    /// [`Self::unit_param_names`] order. They are nuisance regressors of the covariate tests
    /// ([`CovariateTest::adjusted_for`]).
    pub unit_params: BTreeMap<String, Vec<f64>>,
    /// Names of [`Self::unit_params`]' values, e.g. `ln k_con_n_per_m`.
    pub unit_param_names: Vec<String>,
}

/// The sheet column naming the board, tested as a covariate (boards that differ).
pub const BOARD_COVARIATE: &str = "board_id";

/// Tuning knobs of [`locate`].
#[derive(Clone, Debug, PartialEq, Serialize, schemars::JsonSchema)]
pub struct LocateOptions {
    /// False discovery rate of the Benjamini–Hochberg procedure, in every family of tests.
    /// Default 0.01: a diagnosis that claims missing physics triggers refits and a verdict an
    /// engineer acts on, so a false alarm costs more than a late detection; the misfits worth
    /// a diagnosis (the paper's 1.5 % in bolted modes, a loose bolt, a 1 % thermal drift) are
    /// tens of standard errors away from zero on a paper-size campaign (30+ measurements per
    /// setup), where 0.01 instead of 0.05 costs almost no power.
    pub fdr: f64,
    /// Smallest relative frequency misfit worth explaining, |mean r| (and ε/2 for the ε
    /// check). The mode test is a minimum-effect test, H0: |μ| ≤ tolerance. Default 5e-4
    /// (0.05 %, 0.5 Hz at 1 kHz): above the model's own numerical error (a 30-vector ROM
    /// basis ~1e-4, discretization below the measurement scatter by the physics-core
    /// requirement), yet 30x below the paper's 1.5 % misfit. Without it, a campaign with
    /// free-free scatter ~1e-5 makes every 1e-4 numerical bias "significant".
    pub tolerance_rel: f64,
    /// An updated mode's median ε above this multiple of the reference setup's ε level
    /// (and ε/2 above `tolerance_rel`) is flagged `eps_excess`. Default 10: a 100-fold
    /// variance, beyond what the difference in identification scatter between setups (a few
    /// times the damping) explains.
    pub eps_ratio_threshold: f64,
    /// Setup whose ε level stands for the measurement scatter; `None`: the setup with the
    /// smallest median ε (the best-fitting one).
    pub reference_setup: Option<String>,
    /// Fewer boards than this with a (setup, label): the mean test runs over measurements
    /// instead of over board means.
    pub min_boards_for_board_test: usize,
    /// Fewest measurements of a label for its robust centre and scale (outlier statistic).
    pub min_measurements_per_label: usize,
    /// Relative width of a cluster of unpaired modes: a window [f, f (1 + width)].
    pub cluster_rel_width: f64,
    /// A cluster seen in at least this share of a setup's measurements is recurring.
    pub recurring_share: f64,
    /// ... and in at least this many measurements.
    pub recurring_min_measurements: usize,
}

impl Default for LocateOptions {
    fn default() -> Self {
        Self {
            fdr: 0.01,
            tolerance_rel: 5e-4,
            eps_ratio_threshold: 10.0,
            reference_setup: None,
            min_boards_for_board_test: 3,
            min_measurements_per_label: 5,
            cluster_rel_width: 0.03,
            recurring_share: 0.5,
            recurring_min_measurements: 3,
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Output.

/// Mean residual of one board (for consistency across boards).
#[derive(Clone, Debug, PartialEq, Serialize, schemars::JsonSchema)]
pub struct BoardMean {
    pub board_id: String,
    pub n: usize,
    pub mean_rel_residual: f64,
}

/// Check of one (setup, label) over its measurements.
#[derive(Clone, Debug, Default, PartialEq, Serialize, schemars::JsonSchema)]
pub struct ModeCheck {
    pub setup: String,
    pub label: String,
    /// Whether the label was used for updating (false: a validation mode).
    pub used_for_updating: bool,
    /// Measurements (residual rows).
    pub n: usize,
    pub n_boards: usize,
    pub mean_rel_residual: f64,
    /// Sample sd of r over the measurements.
    pub sd_rel_residual: f64,
    /// Standard error of the mean used by the test: sd of the board means / √boards
    /// (`test = "boards"`) or sd / √n (`test = "measurements"`).
    pub se_rel_residual: f64,
    /// `boards` (board means as the units: robust to measurements of one board being
    /// correlated) or `measurements` (too few boards).
    pub test: String,
    /// Degrees of freedom of the t test.
    pub df: f64,
    /// Two-sided p of the t test of mean r = 0 (reported, not used for the decision).
    pub p_zero: Option<f64>,
    /// p of the minimum-effect test H0: |μ| ≤ tolerance_rel:
    /// P(T ≥ (|m| − δ)/se) + P(T ≥ (|m| + δ)/se), T ~ t_df (the size of the region
    /// {|m̂| ≥ |m|} at μ = ±δ, the least favourable null; equals `p_zero` at δ = 0).
    pub p_value: Option<f64>,
    /// Benjamini–Hochberg adjusted `p_value` over all (setup, label).
    pub q_value: Option<f64>,
    /// Share of measurements whose residual has the sign of the mean.
    pub share_same_sign: f64,
    /// Share of boards whose mean residual has the sign of the overall mean.
    pub share_boards_same_sign: f64,
    pub board_means: Vec<BoardMean>,
    /// Root mean square of the standardized residuals (~1 for updated modes even under a
    /// misfit absorbed by ε; large for validation modes, which have no error term).
    pub rms_std_residual: f64,
    /// Median of the inferred ε draws (relative eigenvalue sd), updated modes only.
    pub eps_median: Option<f64>,
    /// `eps_median` / the reference setup's ε level.
    pub eps_ratio: Option<f64>,
    /// The mean misfit is significant (q ≤ fdr).
    pub mean_misfit: bool,
    /// ε far above the reference level (see [`LocateOptions::eps_ratio_threshold`]).
    pub eps_excess: bool,
}

/// One mode's contribution to a measurement's outlier statistic.
#[derive(Clone, Debug, PartialEq, Serialize, schemars::JsonSchema)]
pub struct MeasurementResidual {
    pub label: String,
    pub rel_residual: f64,
    /// r minus the mean of the other clean measurements of its (setup, label).
    pub centred_rel_residual: f64,
    /// Predictive t beyond the tolerance δ: sign(c) max(|c| − δ, 0) / (sd of the others
    /// · √(1 + 1/n)), c = `centred_rel_residual`; |z| is stochastically below |t(n − 1)|
    /// whenever the measurement is within δ of the others.
    pub z: f64,
    /// Degrees of freedom of `z`'s t distribution (the other clean measurements − 1).
    pub df: f64,
}

/// An outlier measurement whose deviation sits in one mode alone: that mode is far from
/// the other measurements while the rest of the measurement agrees with them (their χ² has
/// p > `fdr`). Every mechanism of the library acts on the structure and moves each mode
/// whose energy lies where it acts, so it shifts several modes of a measurement together;
/// a lone pole that slipped (a biased fit, a neighbouring spurious pole) moves one. Reported
/// as a data-quality finding, not as a located misfit, unless the board's other measurements
/// share the deviation (a slip does not recur from fit to fit; see
/// `recurring_slips_are_the_boards`).
#[derive(Clone, Debug, PartialEq, Serialize, schemars::JsonSchema)]
pub struct IdentificationOutlier {
    pub measurement_id: String,
    pub board_id: String,
    pub setup: String,
    pub label: String,
    /// The mode's relative residual minus the mean of the other clean measurements.
    pub centred_rel_residual: f64,
    /// Its predictive t beyond the tolerance (see [`MeasurementResidual::z`]).
    pub z: f64,
    /// χ² p of the measurement's other modes.
    pub p_value_other_modes: f64,
}

/// Joint outlier check of one measurement over its modes.
#[derive(Clone, Debug, PartialEq, Serialize, schemars::JsonSchema)]
pub struct MeasurementCheck {
    pub measurement_id: String,
    pub board_id: String,
    pub setup: String,
    /// Modes in the statistic.
    pub n_modes: usize,
    /// Σ z'², z' = the normal score of each mode's predictive t (two-sided tail kept);
    /// ~χ²(n_modes) when the measurement is like the others. Two passes (one-step
    /// reweighting): a robust pass (median, MAD) picks the measurements to leave out of the
    /// centre and scale (first-pass p < 0.025), so that a contaminated minority (a loose bolt
    /// in 30 % of the measurements) neither inflates the scale nor hides itself; the second
    /// pass tests every measurement against the mean and sd of the other clean ones. The
    /// reported z shrink each deviation by `tolerance_rel` first (a minimum-effect test, as for
    /// the modes): on free-free scatter of 1e-5 a 2e-4 identification slip is "significant"
    /// but not a misfit worth explaining.
    pub chi2: f64,
    pub p_value: Option<f64>,
    /// BH over all measurements.
    pub q_value: Option<f64>,
    pub outlier: bool,
    /// An outlier whose deviation is one mode's alone and not its board's (see
    /// [`IdentificationOutlier`]): the label; such a measurement is not among
    /// [`Located::measurements`].
    pub single_mode: Option<String>,
    /// Left out of the clean centre and scale by the robust first pass.
    pub left_out_of_scale: bool,
    pub residuals: Vec<MeasurementResidual>,
}

/// Mean of the per-measurement residual summary on one level of a categorical covariate.
#[derive(Clone, Debug, PartialEq, Serialize, schemars::JsonSchema)]
pub struct LevelMean {
    pub level: String,
    pub n: usize,
    pub mean_rel_residual: f64,
}

/// Slope of one label's centred residual against a numeric covariate (descriptive).
#[derive(Clone, Debug, PartialEq, Serialize, schemars::JsonSchema)]
pub struct LabelSlope {
    pub label: String,
    pub n: usize,
    pub slope_rel_per_unit: f64,
    pub se: f64,
}

/// Test of one covariate in one setup. The response is one value per measurement: the
/// precision-weighted mean over its modes of r − median_label(r) (weights 1/scale²), so
/// that measurements are the independent units.
#[derive(Clone, Debug, PartialEq, Serialize, schemars::JsonSchema)]
pub struct CovariateTest {
    pub setup: String,
    pub covariate: String,
    /// `numeric` or `categorical`.
    pub kind: String,
    pub unit: String,
    /// Measurements with a value.
    pub n: usize,
    /// Board as a blocking factor (fixed effects): the per-board parameters of the updating
    /// absorb each board's mean, so only within-board variation is informative. False when
    /// the covariate is constant within boards (or is the board).
    pub blocked_by_board: bool,
    /// The measurements' own fitted parameters held fixed as well ([`LocateInput::unit_params`],
    /// e.g. `ln k_con_n_per_m` of the bolted measurements). A model whose form is off by an
    /// amount that depends on a unit's parameter (the joint model's error grows as the
    /// contact softens) leaves residuals that follow that parameter; a sheet column that
    /// happens to trend with it (the contact stiffness of a board's successive assemblies
    /// drifting by chance over the day) would otherwise take that model-form pattern for its
    /// own effect. Only what the covariate explains beyond them counts. Empty when the setup
    /// has no per-measurement parameters (free-free: the board's parameters are constant
    /// within a board, and the board blocking already holds them).
    pub adjusted_for: Vec<String>,
    /// Numeric: relative frequency change per unit of the covariate (e.g. per K).
    pub slope_rel_per_unit: Option<f64>,
    pub slope_se: Option<f64>,
    /// F statistic (numeric: t²) and its degrees of freedom.
    pub f: f64,
    pub df1: f64,
    pub df2: f64,
    pub p_value: f64,
    /// BH over all (setup, covariate).
    pub q_value: f64,
    /// Size of the effect in relative frequency: numeric, |slope| × the covariate's observed
    /// range; categorical, the spread (max − min) of the level means.
    pub effect_rel: f64,
    /// q ≤ fdr and `effect_rel` > tolerance_rel: statistically and practically significant
    /// (on free-free scatter of 1e-5 a slope of 6e-6 per K is "significant" at q = 0.003 but
    /// moves frequencies by 6e-5 over a 9 K swing: nothing worth explaining).
    pub significant: bool,
    /// Categorical: raw mean per level.
    pub levels: Vec<LevelMean>,
    /// Numeric: per-label slopes (same blocking), descriptive.
    pub per_label: Vec<LabelSlope>,
}

/// A covariate not tested in a setup, and why.
#[derive(Clone, Debug, PartialEq, Serialize, schemars::JsonSchema)]
pub struct SkippedCovariate {
    pub setup: String,
    pub covariate: String,
    pub reason: String,
}

/// Unpaired identified modes of one setup within a window of relative width `cluster_rel_width`.
#[derive(Clone, Debug, PartialEq, Serialize, schemars::JsonSchema)]
pub struct UnpairedCluster {
    pub setup: String,
    pub median_freq_hz: f64,
    pub min_freq_hz: f64,
    pub max_freq_hz: f64,
    /// Modes in the cluster.
    pub n_modes: usize,
    /// Distinct measurements with a mode in the cluster.
    pub n_measurements: usize,
    /// Of the setup's measurements.
    pub share_of_setup: f64,
    pub recurring: bool,
    pub measurement_ids: Vec<String>,
}

/// How often one model mode of a setup was seen.
#[derive(Clone, Debug, PartialEq, Serialize, schemars::JsonSchema)]
pub struct ModelModePresence {
    pub setup: String,
    pub label: String,
    pub median_model_freq_hz: Option<f64>,
    pub n_measurements: usize,
    pub n_missing: usize,
    pub never_seen: bool,
}

/// Per (setup, label) in the signature.
#[derive(Clone, Debug, PartialEq, Serialize, schemars::JsonSchema)]
pub struct SignatureMode {
    pub setup: String,
    pub label: String,
    pub used_for_updating: bool,
    pub n: usize,
    pub mean_rel_residual: f64,
    pub se_rel_residual: f64,
}

/// Per measurement in the signature: its residual vector.
#[derive(Clone, Debug, PartialEq, Serialize, schemars::JsonSchema)]
pub struct SignatureMeasurement {
    pub measurement_id: String,
    pub board_id: String,
    pub setup: String,
    pub labels: Vec<String>,
    pub rel_residual: Vec<f64>,
}

/// What screening regresses on mechanism sensitivities.
#[derive(Clone, Debug, Default, PartialEq, Serialize, schemars::JsonSchema)]
pub struct Signature {
    pub modes: Vec<SignatureMode>,
    pub measurements: Vec<SignatureMeasurement>,
}

/// A (setup, label) located as misfitting, with the reasons (`mean_shift`, `eps_excess`,
/// `validation`).
#[derive(Clone, Debug, PartialEq, Serialize, schemars::JsonSchema)]
pub struct LocatedMode {
    pub setup: String,
    pub label: String,
    pub mean_rel_residual: f64,
    pub reasons: Vec<String>,
}

/// A significant covariate, in short.
#[derive(Clone, Debug, PartialEq, Serialize, schemars::JsonSchema)]
pub struct LocatedCovariate {
    pub setup: String,
    pub covariate: String,
    pub q_value: f64,
    pub slope_rel_per_unit: Option<f64>,
    pub unit: String,
}

/// The result of [`locate`]: the summary first, the checks behind it after.
#[derive(Clone, Debug, PartialEq, Serialize, schemars::JsonSchema)]
pub struct Located {
    pub options: LocateOptions,
    /// Anything located at all: modes, measurements, covariates or recurring unpaired modes.
    /// Model modes never seen do not count: a mode with a nodal line at the excitation point
    /// or at the band edge is never seen in a campaign the model fits (both the paper-like
    /// null and the demo campaigns have two such bolted modes).
    pub any: bool,
    /// Setups with a located mode or outlier measurement.
    pub setups: Vec<String>,
    pub modes: Vec<LocatedMode>,
    /// Outlier measurement ids: several modes' frequencies off (or one mode with too few
    /// others to tell; single-mode outliers are in `identification_outliers`), or the
    /// measurement's mode shapes off in every mode ([`Self::shape_outliers`]).
    pub measurements: Vec<String>,
    /// Outliers by their mode shapes ([`crate::diagnose::shapes`]): a loose bolt's
    /// frequency drop is absorbed into the measurement's own contact stiffness, its
    /// asymmetric shape change is not.
    pub shape_outliers: Vec<String>,
    /// Outlier measurements whose deviation is one mode's alone: likely an identification
    /// slip, listed for the engineer to check, not counted as misfit.
    pub identification_outliers: Vec<IdentificationOutlier>,
    /// Outlier measurement ids once the located numeric covariates are taken out (each
    /// label's board-blocked slope times the covariate's deviation from its board or setup
    /// mean, whichever fits better; see `adjust_for_covariates`): a
    /// temperature drift makes the measurements at the extremes outliers, a loose bolt stays.
    pub measurements_after_covariates: Vec<String>,
    /// Outliers of [`Self::measurements`] whose deviation their board's other measurements in
    /// the setup share ([`board_shared_outliers`]): the board differs from the population
    /// (its assemblies alike), not this measurement from its board. A loose bolt, a slip or a
    /// drift sets one measurement apart from the same board's others; these cannot be it.
    pub board_shared: Vec<String>,
    pub covariates: Vec<LocatedCovariate>,
    /// Recurring clusters of unpaired identified modes.
    pub unpaired_clusters: Vec<UnpairedCluster>,
    /// (setup, label) of model modes never identified.
    pub never_seen: Vec<ModelModePresence>,
    pub reference_setup: Option<String>,
    /// Median over the reference setup's labels of their median ε.
    pub reference_eps: Option<f64>,
    pub mode_checks: Vec<ModeCheck>,
    pub measurement_checks: Vec<MeasurementCheck>,
    pub shape_checks: Vec<ShapeCheck>,
    pub covariate_tests: Vec<CovariateTest>,
    pub skipped_covariates: Vec<SkippedCovariate>,
    pub all_unpaired_clusters: Vec<UnpairedCluster>,
    pub model_modes: Vec<ModelModePresence>,
    pub signature: Signature,
    /// Residual rows ignored because a number was not finite.
    pub rows_ignored: usize,
}

// ---------------------------------------------------------------------------------------------
// Statistics.

/// P(T ≥ t), T ~ Student t with `df` degrees of freedom.
pub fn t_sf(t: f64, df: f64) -> f64 {
    match StudentsT::new(0.0, 1.0, df) {
        Ok(d) => d.sf(t),
        Err(_) => f64::NAN,
    }
}

/// Two-sided p of a t statistic.
pub fn t_two_sided(t: f64, df: f64) -> f64 {
    (2.0 * t_sf(t.abs(), df)).min(1.0)
}

/// P(F ≥ f), F ~ F(d1, d2).
pub fn f_sf(f: f64, d1: f64, d2: f64) -> f64 {
    if f <= 0.0 {
        return 1.0;
    }
    match FisherSnedecor::new(d1, d2) {
        Ok(d) => d.sf(f),
        Err(_) => f64::NAN,
    }
}

/// P(X ≥ x), X ~ χ²(k).
pub fn chi2_sf(x: f64, k: f64) -> f64 {
    match ChiSquared::new(k) {
        Ok(d) => d.sf(x),
        Err(_) => f64::NAN,
    }
}

/// |z| of the standard normal with two-sided tail probability p (capped at 38 where p
/// underflows).
fn normal_abs_z(p: f64) -> f64 {
    if p.is_nan() || p <= 0.0 {
        return 38.0;
    }
    let n = Normal::new(0.0, 1.0).expect("standard normal");
    (-n.inverse_cdf((p / 2.0).min(0.5))).clamp(0.0, 38.0)
}

/// Benjamini–Hochberg adjusted p-values (q-values), in input order:
/// q_(i) = min_{j ≥ i} p_(j) m / j over the ascending order, capped at 1. Reject where q ≤ α.
pub fn benjamini_hochberg(p: &[f64]) -> Vec<f64> {
    let m = p.len();
    let mut order: Vec<usize> = (0..m).collect();
    order.sort_by(|&a, &b| p[a].total_cmp(&p[b]));
    let mut q = vec![1.0; m];
    let mut running = 1.0f64;
    for (rank, &i) in order.iter().enumerate().rev() {
        running = running.min(p[i] * m as f64 / (rank + 1) as f64);
        q[i] = running.min(1.0);
    }
    q
}

/// BH over optional p-values (None stays None).
pub(crate) fn bh_opt(p: &[Option<f64>]) -> Vec<Option<f64>> {
    let idx: Vec<usize> = (0..p.len()).filter(|&i| p[i].is_some()).collect();
    let vals: Vec<f64> = idx.iter().map(|&i| p[i].unwrap_or(1.0)).collect();
    let q = benjamini_hochberg(&vals);
    let mut out = vec![None; p.len()];
    for (k, &i) in idx.iter().enumerate() {
        out[i] = Some(q[k]);
    }
    out
}

fn mean(x: &[f64]) -> f64 {
    x.iter().sum::<f64>() / x.len() as f64
}

/// Sample sd (n − 1); 0 for fewer than two values.
fn sd(x: &[f64]) -> f64 {
    if x.len() < 2 {
        return 0.0;
    }
    let m = mean(x);
    (x.iter().map(|v| (v - m).powi(2)).sum::<f64>() / (x.len() - 1) as f64).sqrt()
}

/// 1.4826 × median absolute deviation: a consistent estimate of the normal sd.
pub(crate) fn mad_sd(x: &[f64]) -> f64 {
    let m = median(x);
    let dev: Vec<f64> = x.iter().map(|v| (v - m).abs()).collect();
    1.4826 * median(&dev)
}

/// The minimum-effect test of [`ModeCheck::p_value`].
pub fn min_effect_p(mean: f64, se: f64, df: f64, tolerance: f64) -> f64 {
    if se.is_nan() || se <= 0.0 {
        return if mean.abs() > tolerance { 0.0 } else { 1.0 };
    }
    let a = mean.abs();
    (t_sf((a - tolerance) / se, df) + t_sf((a + tolerance) / se, df)).min(1.0)
}

/// Residual of `v` after least-squares projection on the span of `cols` (Householder QR with
/// column pivoting from faer; columns scaled to unit norm first so that the rank tolerance is
/// relative), and the numerical rank of `cols`.
fn project_out(cols: &[Vec<f64>], v: &[f64]) -> (Vec<f64>, usize) {
    let n = v.len();
    let cols: Vec<Vec<f64>> = cols
        .iter()
        .filter_map(|c| {
            let norm = c.iter().map(|x| x * x).sum::<f64>().sqrt();
            (norm > 0.0).then(|| c.iter().map(|x| x / norm).collect())
        })
        .collect();
    if cols.is_empty() || n == 0 {
        return (v.to_vec(), 0);
    }
    let p = cols.len();
    let a = faer::Mat::<f64>::from_fn(n, p, |i, j| cols[j][i]);
    let qr = a.col_piv_qr();
    let r = qr.thin_R();
    let q = qr.compute_thin_Q();
    let k = n.min(p);
    let r0 = r[(0, 0)].abs();
    let rank = (0..k)
        .take_while(|&i| r[(i, i)].abs() > 1e-9 * r0.max(f64::MIN_POSITIVE))
        .count();
    let mut res = v.to_vec();
    for j in 0..rank {
        let c: f64 = (0..n).map(|i| q[(i, j)] * v[i]).sum();
        for (i, x) in res.iter_mut().enumerate() {
            *x -= c * q[(i, j)];
        }
    }
    (res, rank)
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// Result of a nested linear-model test.
struct LmTest {
    f: f64,
    df1: f64,
    df2: f64,
    p: f64,
    slope: Option<(f64, f64)>,
}

/// F test of adding `extra` columns to `base` (which should hold the intercept) for `y`;
/// with one extra column also its slope and standard error (Frisch–Waugh–Lovell). `None`
/// when the extra columns add no rank or no residual degrees of freedom are left.
fn nested_f(base: &[Vec<f64>], extra: &[Vec<f64>], y: &[f64]) -> Option<LmTest> {
    let n = y.len();
    let (ry, r0) = project_out(base, y);
    // Extra columns residualized on the base; a column (numerically) inside the base span
    // (e.g. a covariate constant within boards, blocked by board) adds nothing.
    let ex: Vec<Vec<f64>> = extra
        .iter()
        .map(|c| (project_out(base, c).0, dot(c, c).sqrt()))
        .filter(|(r, raw)| dot(r, r).sqrt() > 1e-8 * raw)
        .map(|(r, _)| r)
        .collect();
    let (ry1, k) = project_out(&ex, &ry);
    if k == 0 {
        return None;
    }
    let df2 = n as f64 - (r0 + k) as f64;
    if df2 < 1.0 {
        return None;
    }
    let rss0 = dot(&ry, &ry);
    let rss1 = dot(&ry1, &ry1);
    let f = ((rss0 - rss1).max(0.0) / k as f64) / (rss1 / df2);
    let slope = (extra.len() == 1).then(|| {
        let x = &ex[0];
        let sxx = dot(x, x);
        let b = dot(x, &ry) / sxx;
        (b, (rss1 / df2 / sxx).sqrt())
    });
    let f = if f.is_finite() { f } else { f64::INFINITY };
    Some(LmTest {
        f,
        df1: k as f64,
        df2,
        p: if f.is_infinite() {
            0.0
        } else {
            f_sf(f, k as f64, df2)
        },
        slope,
    })
}

// ---------------------------------------------------------------------------------------------
// The kernel.

/// Locate the misfit of the updated model: see the module doc.
pub fn locate(input: &LocateInput, opts: &LocateOptions) -> Located {
    let rows: Vec<&ResidualObs> = input
        .residuals
        .iter()
        .filter(|r| r.rel_residual.is_finite() && r.std_residual.is_finite())
        .collect();
    let rows_ignored = input.residuals.len() - rows.len();

    // Reference ε level.
    let mut eps_med: BTreeMap<(String, String), f64> = BTreeMap::new();
    for e in &input.eps {
        let d: Vec<f64> = e.draws.iter().copied().filter(|v| v.is_finite()).collect();
        if !d.is_empty() {
            eps_med.insert((e.setup.clone(), e.label.clone()), median(&d));
        }
    }
    let mut setup_eps: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    for ((s, _), v) in &eps_med {
        setup_eps.entry(s.clone()).or_default().push(*v);
    }
    let setup_level: BTreeMap<String, f64> = setup_eps
        .iter()
        .map(|(s, v)| (s.clone(), median(v)))
        .collect();
    let reference_setup = match &opts.reference_setup {
        Some(s) => setup_level.contains_key(s).then(|| s.clone()),
        None => setup_level
            .iter()
            .min_by(|a, b| a.1.total_cmp(b.1))
            .map(|(s, _)| s.clone()),
    };
    let reference_eps = reference_setup.as_ref().map(|s| setup_level[s]);

    let mode_checks = mode_checks(&rows, &eps_med, reference_eps, opts);
    let (mut measurement_checks, signature_measurements) = measurement_checks(&rows, opts);
    recurring_slips_are_the_boards(&mut measurement_checks, &rows, opts);
    let (covariate_tests, skipped_covariates) = covariate_tests(input, &rows, opts);
    let adjusted = adjust_for_covariates(input, &rows, &covariate_tests);
    let adjusted_refs: Vec<&ResidualObs> = adjusted.iter().collect();
    let mut adjusted_checks = self::measurement_checks(&adjusted_refs, opts).0;
    recurring_slips_are_the_boards(&mut adjusted_checks, &adjusted_refs, opts);
    let measurements_after_covariates: Vec<String> = adjusted_checks
        .into_iter()
        .filter(|m| m.outlier && m.single_mode.is_none())
        .map(|m| m.measurement_id)
        .collect();
    let all_unpaired_clusters = unpaired_clusters(input, opts);
    let model_modes = model_mode_presence(input);

    let modes: Vec<LocatedMode> = mode_checks
        .iter()
        .filter(|m| m.mean_misfit || m.eps_excess)
        .map(|m| {
            let mut reasons = vec![];
            if m.mean_misfit {
                reasons.push("mean_shift".to_string());
            }
            if m.eps_excess {
                reasons.push("eps_excess".to_string());
            }
            if !m.used_for_updating {
                reasons.push("validation".to_string());
            }
            LocatedMode {
                setup: m.setup.clone(),
                label: m.label.clone(),
                mean_rel_residual: m.mean_rel_residual,
                reasons,
            }
        })
        .collect();
    let freq_outliers: Vec<String> = measurement_checks
        .iter()
        .filter(|m| m.outlier && m.single_mode.is_none())
        .map(|m| m.measurement_id.clone())
        .collect();
    let freq_shared = board_shared_outliers(&rows, &freq_outliers, opts);
    // Shape outliers join the frequency ones (covariates move frequencies, not shapes, so
    // they stay outliers after the covariates too). An outlier is board-shared only when
    // each of its reasons is: a loose bolt's frequencies may look like its board-mates'
    // while its shapes do not.
    let shape_checks = shape_checks(&rows, opts);
    let shape_outliers: Vec<String> = shape_checks
        .iter()
        .filter(|c| c.outlier)
        .map(|c| c.measurement_id.clone())
        .collect();
    let mut measurements = freq_outliers.clone();
    let mut measurements_after_covariates = measurements_after_covariates;
    for m in &shape_outliers {
        if !measurements.contains(m) {
            measurements.push(m.clone());
        }
        if !measurements_after_covariates.contains(m) {
            measurements_after_covariates.push(m.clone());
        }
    }
    let board_shared: Vec<String> = measurements
        .iter()
        .filter(|m| {
            (!freq_outliers.contains(m) || freq_shared.contains(m))
                && shape_checks
                    .iter()
                    .filter(|c| &c.measurement_id == *m && c.outlier)
                    .all(|c| c.board_shared)
        })
        .cloned()
        .collect();
    let identification_outliers: Vec<IdentificationOutlier> = measurement_checks
        .iter()
        .filter(|m| m.outlier && m.single_mode.is_some())
        .filter_map(|m| {
            let (i, p) = single_mode(&m.residuals, opts.fdr)?;
            let r = &m.residuals[i];
            Some(IdentificationOutlier {
                measurement_id: m.measurement_id.clone(),
                board_id: m.board_id.clone(),
                setup: m.setup.clone(),
                label: r.label.clone(),
                centred_rel_residual: r.centred_rel_residual,
                z: r.z,
                p_value_other_modes: p,
            })
        })
        .collect();
    let setups: Vec<String> = modes
        .iter()
        .map(|m| m.setup.clone())
        .chain(
            measurement_checks
                .iter()
                .filter(|m| m.outlier && m.single_mode.is_none())
                .map(|m| m.setup.clone()),
        )
        .chain(
            shape_checks
                .iter()
                .filter(|c| c.outlier)
                .map(|c| c.setup.clone()),
        )
        .collect::<BTreeSet<_>>()
        .into_iter()
        .collect();
    let covariates: Vec<LocatedCovariate> = covariate_tests
        .iter()
        .filter(|c| c.significant)
        .map(|c| LocatedCovariate {
            setup: c.setup.clone(),
            covariate: c.covariate.clone(),
            q_value: c.q_value,
            slope_rel_per_unit: c.slope_rel_per_unit,
            unit: c.unit.clone(),
        })
        .collect();
    let unpaired: Vec<UnpairedCluster> = all_unpaired_clusters
        .iter()
        .filter(|c| c.recurring)
        .cloned()
        .collect();
    let never_seen: Vec<ModelModePresence> = model_modes
        .iter()
        .filter(|m| m.never_seen)
        .cloned()
        .collect();
    let signature = Signature {
        modes: mode_checks
            .iter()
            .map(|m| SignatureMode {
                setup: m.setup.clone(),
                label: m.label.clone(),
                used_for_updating: m.used_for_updating,
                n: m.n,
                mean_rel_residual: m.mean_rel_residual,
                se_rel_residual: m.se_rel_residual,
            })
            .collect(),
        measurements: signature_measurements,
    };
    Located {
        options: opts.clone(),
        any: !(modes.is_empty()
            && measurements.is_empty()
            && covariates.is_empty()
            && unpaired.is_empty()),
        setups,
        modes,
        measurements,
        shape_outliers,
        identification_outliers,
        measurements_after_covariates,
        board_shared,
        covariates,
        unpaired_clusters: unpaired,
        never_seen,
        reference_setup,
        reference_eps,
        mode_checks,
        measurement_checks,
        shape_checks,
        covariate_tests,
        skipped_covariates,
        all_unpaired_clusters,
        model_modes,
        signature,
        rows_ignored,
    }
}

fn sign_share(x: &[f64], m: f64) -> f64 {
    if x.is_empty() {
        return 0.0;
    }
    let s = m.signum();
    x.iter().filter(|v| v.signum() == s && **v != 0.0).count() as f64 / x.len() as f64
}

/// The mode checks ([`ModeCheck`]) of a residual table alone: the same per-(setup, label)
/// mean relative residual (mean of the board means with enough boards), scatter and
/// minimum-effect test as [`locate`] computes, without the ε comparison (no ε draws). The
/// diagnosis uses it for a refit's residuals, so that a mode's misfit before and after a
/// candidate come from one computation.
pub fn mode_means(residuals: &[ResidualObs], opts: &LocateOptions) -> Vec<ModeCheck> {
    let rows: Vec<&ResidualObs> = residuals
        .iter()
        .filter(|r| r.rel_residual.is_finite() && r.std_residual.is_finite())
        .collect();
    mode_checks(&rows, &BTreeMap::new(), None, opts)
}

fn mode_checks(
    rows: &[&ResidualObs],
    eps_med: &BTreeMap<(String, String), f64>,
    reference_eps: Option<f64>,
    opts: &LocateOptions,
) -> Vec<ModeCheck> {
    let mut groups: BTreeMap<(String, String), Vec<&ResidualObs>> = BTreeMap::new();
    for r in rows {
        groups
            .entry((r.setup.clone(), r.label.clone()))
            .or_default()
            .push(r);
    }
    let mut out: Vec<ModeCheck> = groups
        .into_iter()
        .map(|((setup, label), g)| {
            let x: Vec<f64> = g.iter().map(|r| r.rel_residual).collect();
            let n = x.len();
            let m = mean(&x);
            let s = sd(&x);
            let mut by_board: BTreeMap<&str, Vec<f64>> = BTreeMap::new();
            for r in &g {
                by_board
                    .entry(r.board_id.as_str())
                    .or_default()
                    .push(r.rel_residual);
            }
            let board_means: Vec<BoardMean> = by_board
                .iter()
                .map(|(b, v)| BoardMean {
                    board_id: b.to_string(),
                    n: v.len(),
                    mean_rel_residual: mean(v),
                })
                .collect();
            let bm: Vec<f64> = board_means.iter().map(|b| b.mean_rel_residual).collect();
            let nb = bm.len();
            // Board means as units when there are enough boards: the mean of the board means
            // (each board weighs alike) and their sd.
            let (test, centre, se, df) = if nb >= opts.min_boards_for_board_test {
                (
                    "boards",
                    mean(&bm),
                    sd(&bm) / (nb as f64).sqrt(),
                    (nb - 1) as f64,
                )
            } else {
                ("measurements", m, s / (n as f64).sqrt(), n as f64 - 1.0)
            };
            let testable = df >= 1.0;
            let p_zero = testable.then(|| {
                if se > 0.0 {
                    t_two_sided(centre / se, df)
                } else if centre == 0.0 {
                    1.0
                } else {
                    0.0
                }
            });
            let p_value = testable.then(|| min_effect_p(centre, se, df, opts.tolerance_rel));
            let used = g.iter().any(|r| r.used_for_updating);
            let eps_median = used
                .then(|| eps_med.get(&(setup.clone(), label.clone())).copied())
                .flatten();
            let eps_ratio = match (eps_median, reference_eps) {
                (Some(e), Some(r)) if r > 0.0 => Some(e / r),
                _ => None,
            };
            let eps_excess = match (eps_ratio, eps_median) {
                (Some(ratio), Some(e)) => {
                    ratio > opts.eps_ratio_threshold && e / 2.0 > opts.tolerance_rel
                }
                _ => false,
            };
            let rms = (g.iter().map(|r| r.std_residual.powi(2)).sum::<f64>() / n as f64).sqrt();
            ModeCheck {
                setup,
                label,
                used_for_updating: used,
                n,
                n_boards: nb,
                mean_rel_residual: centre,
                sd_rel_residual: s,
                se_rel_residual: se,
                test: test.to_string(),
                df,
                p_zero,
                p_value,
                q_value: None,
                share_same_sign: sign_share(&x, centre),
                share_boards_same_sign: sign_share(&bm, centre),
                board_means,
                rms_std_residual: rms,
                eps_median,
                eps_ratio,
                mean_misfit: false,
                eps_excess,
            }
        })
        .collect();
    let q = bh_opt(&out.iter().map(|m| m.p_value).collect::<Vec<_>>());
    for (m, q) in out.iter_mut().zip(q) {
        m.q_value = q;
        m.mean_misfit = q.is_some_and(|q| q <= opts.fdr);
    }
    out
}

/// Robust centre and scale per (setup, label).
type Scales = BTreeMap<(String, String), (f64, f64, usize)>;

fn robust_scales(rows: &[&ResidualObs], min_n: usize) -> Scales {
    let mut groups: BTreeMap<(String, String), Vec<f64>> = BTreeMap::new();
    for r in rows {
        groups
            .entry((r.setup.clone(), r.label.clone()))
            .or_default()
            .push(r.rel_residual);
    }
    groups
        .into_iter()
        .filter(|(_, v)| v.len() >= min_n)
        .filter_map(|(k, v)| {
            let s = mad_sd(&v);
            (s > 0.0).then(|| (k, (median(&v), s, v.len())))
        })
        .collect()
}

/// Measurements whose first-pass (robust) p is below this are left out of the clean centre
/// and scale of the second pass: the 0.975 cut-off of one-step reweighted robust estimators
/// (Rousseeuw & Leroy 1987).
const REWEIGHT_P: f64 = 0.025;

/// Σ z'² over a measurement's modes, z' = the normal score of a t-distributed residual.
fn chi2_of(z_df: &[(f64, f64)]) -> f64 {
    z_df.iter()
        .map(|&(z, df)| normal_abs_z(t_two_sided(z, df)).powi(2))
        .sum()
}

fn measurement_checks(
    rows: &[&ResidualObs],
    opts: &LocateOptions,
) -> (Vec<MeasurementCheck>, Vec<SignatureMeasurement>) {
    let min_n = opts.min_measurements_per_label.max(4);
    let scales = robust_scales(rows, min_n);
    let mut by_m: ByMeasurement = BTreeMap::new();
    for r in rows {
        by_m.entry((
            r.setup.clone(),
            r.measurement_id.clone(),
            r.board_id.clone(),
        ))
        .or_default()
        .push(r);
    }
    // Pass 1: robust z against the median and 1.4826 MAD, mapped through t with the MAD's
    // effective degrees of freedom (asymptotic efficiency 0.37). Robust to a contaminated
    // minority, but its inflated scale costs power: it only picks who to leave out.
    let mut excluded: BTreeSet<(String, String)> = BTreeSet::new();
    for ((setup, mid, _), g) in &by_m {
        let z: Vec<(f64, f64)> = g
            .iter()
            .filter_map(|r| {
                let &(c, s, n) = scales.get(&(setup.clone(), r.label.clone()))?;
                Some(((r.rel_residual - c) / s, (0.37 * (n as f64 - 1.0)).max(1.0)))
            })
            .collect();
        if !z.is_empty() && chi2_sf(chi2_of(&z), z.len() as f64) < REWEIGHT_P {
            excluded.insert((setup.clone(), mid.clone()));
        }
    }
    // Pass 2, iterated to a fixed point (at most 10 times): every measurement against the
    // mean and sd of the other kept ones; those with p < REWEIGHT_P are left out next time.
    for _ in 0..10 {
        let checks = studentized_checks(&by_m, &excluded, rows, min_n, 0.0);
        let next: BTreeSet<(String, String)> = checks
            .iter()
            .filter(|c| c.p_value.is_some_and(|p| p < REWEIGHT_P))
            .map(|c| (c.setup.clone(), c.measurement_id.clone()))
            .collect();
        if next == excluded {
            break;
        }
        excluded = next;
    }
    // The reported statistic: the same, minimum-effect (see MeasurementCheck::chi2).
    let mut checks = studentized_checks(&by_m, &excluded, rows, min_n, opts.tolerance_rel);
    let sig = by_m
        .iter()
        .map(|((setup, mid, board), g)| {
            let mut g = g.clone();
            g.sort_by(|a, b| a.label.cmp(&b.label));
            SignatureMeasurement {
                measurement_id: mid.clone(),
                board_id: board.clone(),
                setup: setup.clone(),
                labels: g.iter().map(|r| r.label.clone()).collect(),
                rel_residual: g.iter().map(|r| r.rel_residual).collect(),
            }
        })
        .collect();
    let q = bh_opt(&checks.iter().map(|m| m.p_value).collect::<Vec<_>>());
    for (m, q) in checks.iter_mut().zip(q) {
        m.q_value = q;
        m.outlier = q.is_some_and(|q| q <= opts.fdr);
        if m.outlier {
            m.single_mode =
                single_mode(&m.residuals, opts.fdr).map(|(i, _)| m.residuals[i].label.clone());
        }
    }
    (checks, sig)
}

/// The one mode that makes a measurement an outlier, with the χ² p of its other modes: the
/// mode with the largest |z| when at least two others are tested and they pass (p > `alpha`).
fn single_mode(res: &[MeasurementResidual], alpha: f64) -> Option<(usize, f64)> {
    if res.len() < 3 {
        return None;
    }
    let (imax, _) = res
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.z.abs().total_cmp(&b.1.z.abs()))?;
    let rest: Vec<(f64, f64)> = res
        .iter()
        .enumerate()
        .filter(|(i, _)| *i != imax)
        .map(|(_, r)| (r.z, r.df))
        .collect();
    let p = chi2_sf(chi2_of(&rest), rest.len() as f64);
    (p > alpha).then_some((imax, p))
}

/// A single-mode outlier whose board's other measurements share its deviation is the
/// board's, not a slip of its modal fit: each measurement's poles are fitted to its own FRFs,
/// so a slip does not recur in the board's separate measurements, while a per-board
/// deviation (the model's form erring differently on a board whose moduli stand apart, a
/// board's own defect) recurs in every one. Such an outlier loses its `single_mode` mark: it
/// is a located outlier, and [`board_shared_outliers`] names it the board's. One whose board
/// has no other measurement stays a slip: nothing tells.
fn recurring_slips_are_the_boards(
    checks: &mut [MeasurementCheck],
    rows: &[&ResidualObs],
    opts: &LocateOptions,
) {
    let slips: Vec<String> = checks
        .iter()
        .filter(|c| c.outlier && c.single_mode.is_some())
        .map(|c| c.measurement_id.clone())
        .collect();
    let shared = board_shared_outliers(rows, &slips, opts);
    for c in checks.iter_mut() {
        if shared.contains(&c.measurement_id) {
            c.single_mode = None;
        }
    }
}

/// The outliers (`outliers`, measurement ids) whose deviation their board shares: each is
/// tested against the median of its board's other measurements in its setup, mode by mode,
/// z = (|x − median(mates)| − tolerance) / (s_w √(1 + π/(2m))) with m mates and s_w the
/// label's pooled within-board sd over the measurements that are not outliers (the median's
/// variance is π/(2m) σ² for normal scatter), Σ z² against χ²(k). An outlier with p ≥ fdr
/// (nothing sets it apart from its board) is board-shared. One with no mates, or no mode to
/// compare, is not: nothing tells. The mates include the board's other outliers: when a
/// board's assemblies all deviate alike, each is flagged or not by chance, and each agrees
/// with the others.
pub fn board_shared_outliers(
    rows: &[&ResidualObs],
    outliers: &[String],
    opts: &LocateOptions,
) -> Vec<String> {
    let out: BTreeSet<&str> = outliers.iter().map(|m| m.as_str()).collect();
    // (setup, label) → board → [(measurement, residual)].
    type ByBoard<'a> = BTreeMap<&'a str, Vec<(&'a str, f64)>>;
    let mut by: BTreeMap<(&str, &str), ByBoard> = BTreeMap::new();
    for r in rows {
        by.entry((r.setup.as_str(), r.label.as_str()))
            .or_default()
            .entry(r.board_id.as_str())
            .or_default()
            .push((r.measurement_id.as_str(), r.rel_residual));
    }
    // Pooled within-board sd of the measurements that are not outliers, per (setup, label).
    let s_w: BTreeMap<(&str, &str), f64> = by
        .iter()
        .filter_map(|(k, boards)| {
            let (mut ss, mut dof) = (0.0, 0usize);
            for v in boards.values() {
                let clean: Vec<f64> = v
                    .iter()
                    .filter(|(m, _)| !out.contains(m))
                    .map(|&(_, x)| x)
                    .collect();
                if clean.len() >= 2 {
                    let m = mean(&clean);
                    ss += clean.iter().map(|x| (x - m).powi(2)).sum::<f64>();
                    dof += clean.len() - 1;
                }
            }
            (dof >= 2 && ss > 0.0).then(|| (*k, (ss / dof as f64).sqrt()))
        })
        .collect();
    let mut shared = vec![];
    for id in outliers {
        let mut zs = vec![];
        for (k, boards) in &by {
            let Some(&s) = s_w.get(k) else { continue };
            for v in boards.values() {
                let Some(&(_, x)) = v.iter().find(|(m, _)| m == id) else {
                    continue;
                };
                let mates: Vec<f64> = v.iter().filter(|(m, _)| m != id).map(|&(_, x)| x).collect();
                if mates.is_empty() {
                    continue;
                }
                let m = mates.len() as f64;
                let d = x - median(&mates);
                let z = (d.abs() - opts.tolerance_rel).max(0.0)
                    / (s * (1.0 + std::f64::consts::FRAC_PI_2 / m).sqrt());
                zs.push(z);
            }
        }
        if !zs.is_empty() {
            let chi2: f64 = zs.iter().map(|z| z * z).sum();
            if chi2_sf(chi2, zs.len() as f64) >= opts.fdr {
                shared.push(id.clone());
            }
        }
    }
    shared
}

type ByMeasurement<'a> = BTreeMap<(String, String, String), Vec<&'a ResidualObs>>;

/// One pass of the measurement checks against the clean (not `excluded`) measurements.
fn studentized_checks(
    by_m: &ByMeasurement,
    excluded: &BTreeSet<(String, String)>,
    rows: &[&ResidualObs],
    min_n: usize,
    tolerance: f64,
) -> Vec<MeasurementCheck> {
    let mut clean: BTreeMap<(String, String), (f64, f64, f64)> = BTreeMap::new();
    for r in rows {
        if !excluded.contains(&(r.setup.clone(), r.measurement_id.clone())) {
            let e = clean
                .entry((r.setup.clone(), r.label.clone()))
                .or_insert((0.0, 0.0, 0.0));
            e.0 += 1.0;
            e.1 += r.rel_residual;
            e.2 += r.rel_residual * r.rel_residual;
        }
    }
    let mut checks = vec![];
    for ((setup, mid, board), g) in by_m {
        let mut g = g.clone();
        g.sort_by(|a, b| a.label.cmp(&b.label));
        let out = excluded.contains(&(setup.clone(), mid.clone()));
        let mut res = vec![];
        let mut z_df = vec![];
        for r in &g {
            let Some(&(n, s1, s2)) = clean.get(&(setup.clone(), r.label.clone())) else {
                continue;
            };
            // Predictive t of a new value against the other clean measurements: a kept
            // measurement is left out of its own mean and sd (leave-one-out).
            let x = r.rel_residual;
            let (n, s1, s2) = if out {
                (n, s1, s2)
            } else {
                (n - 1.0, s1 - x, s2 - x * x)
            };
            if n < (min_n - 1) as f64 || n < 3.0 {
                continue;
            }
            let m = s1 / n;
            let var = ((s2 - n * m * m) / (n - 1.0)).max(0.0);
            if var.is_nan() || var <= 0.0 {
                continue;
            }
            let d = x - m;
            let z = d.signum() * (d.abs() - tolerance).max(0.0) / (var * (1.0 + 1.0 / n)).sqrt();
            z_df.push((z, n - 1.0));
            res.push(MeasurementResidual {
                label: r.label.clone(),
                rel_residual: x,
                centred_rel_residual: x - m,
                z,
                df: n - 1.0,
            });
        }
        let k = res.len();
        let chi2 = chi2_of(&z_df);
        checks.push(MeasurementCheck {
            measurement_id: mid.clone(),
            board_id: board.clone(),
            setup: setup.clone(),
            n_modes: k,
            chi2,
            p_value: (k > 0).then(|| chi2_sf(chi2, k as f64)),
            q_value: None,
            outlier: false,
            single_mode: None,
            left_out_of_scale: out,
            residuals: res,
        });
    }
    checks
}

/// The per-measurement response of the covariate tests: precision-weighted mean of the
/// centred residuals, by setup: measurement id → value.
fn measurement_response(
    rows: &[&ResidualObs],
    opts: &LocateOptions,
) -> BTreeMap<(String, String), f64> {
    let scales = robust_scales(rows, opts.min_measurements_per_label.max(2));
    let mut acc: BTreeMap<(String, String), (f64, f64)> = BTreeMap::new();
    for r in rows {
        if let Some(&(c, s, _)) = scales.get(&(r.setup.clone(), r.label.clone())) {
            let w = 1.0 / (s * s);
            let e = acc
                .entry((r.setup.clone(), r.measurement_id.clone()))
                .or_insert((0.0, 0.0));
            e.0 += w * (r.rel_residual - c);
            e.1 += w;
        }
    }
    acc.into_iter().map(|(k, (s, w))| (k, s / w)).collect()
}

/// The covariate tests ([`CovariateTest`]) of a residual table against the sheet's columns,
/// the same computation as [`locate`]'s. The diagnosis uses it for a refit's residuals, so a
/// covariate trend before and after a candidate come from one computation.
pub fn covariate_effects(input: &LocateInput, opts: &LocateOptions) -> Vec<CovariateTest> {
    let rows: Vec<&ResidualObs> = input
        .residuals
        .iter()
        .filter(|r| r.rel_residual.is_finite() && r.std_residual.is_finite())
        .collect();
    covariate_tests(input, &rows, opts).0
}

fn covariate_tests(
    input: &LocateInput,
    rows: &[&ResidualObs],
    opts: &LocateOptions,
) -> (Vec<CovariateTest>, Vec<SkippedCovariate>) {
    let resp = measurement_response(rows, opts);
    let scales = robust_scales(rows, opts.min_measurements_per_label.max(2));
    let setups: BTreeSet<String> = resp.keys().map(|(s, _)| s.clone()).collect();
    let mut tests = vec![];
    let mut skipped = vec![];
    for setup in &setups {
        // Measurements of this setup with a response, in input order.
        let idx: Vec<usize> = (0..input.measurements.len())
            .filter(|&i| {
                let m = &input.measurements[i];
                &m.setup == setup && resp.contains_key(&(setup.clone(), m.measurement_id.clone()))
            })
            .collect();
        for cov in &input.covariates {
            let skip = |reason: String| SkippedCovariate {
                setup: setup.clone(),
                covariate: cov.name.clone(),
                reason,
            };
            // Measurements with a value.
            let (sel, xnum, xcat): (Vec<usize>, Vec<f64>, Vec<String>) = match &cov.values {
                CovariateValues::Numeric(v) => {
                    let sel: Vec<usize> = idx
                        .iter()
                        .copied()
                        .filter(|&i| v.get(i).copied().flatten().is_some_and(f64::is_finite))
                        .collect();
                    let x = sel.iter().map(|&i| v[i].unwrap_or(f64::NAN)).collect();
                    (sel, x, vec![])
                }
                CovariateValues::Categorical(v) => {
                    let sel: Vec<usize> = idx
                        .iter()
                        .copied()
                        .filter(|&i| {
                            v.get(i)
                                .is_some_and(|s| s.as_ref().is_some_and(|s| !s.trim().is_empty()))
                        })
                        .collect();
                    let x = sel
                        .iter()
                        .map(|&i| v[i].clone().unwrap_or_default().trim().to_string())
                        .collect();
                    (sel, vec![], x)
                }
            };
            let n = sel.len();
            let numeric = matches!(cov.values, CovariateValues::Numeric(_));
            let distinct = if numeric {
                let mut d = xnum.clone();
                d.sort_by(f64::total_cmp);
                d.dedup();
                d.len()
            } else {
                xcat.iter().collect::<BTreeSet<_>>().len()
            };
            if distinct < 2 {
                skipped.push(skip(format!(
                    "no variation ({distinct} distinct value(s) in {n} measurements)"
                )));
                continue;
            }
            if !numeric && distinct * 2 > n {
                skipped.push(skip(format!(
                    "free text or identifier: {distinct} distinct values in {n} measurements"
                )));
                continue;
            }
            let y: Vec<f64> = sel
                .iter()
                .map(|&i| resp[&(setup.clone(), input.measurements[i].measurement_id.clone())])
                .collect();
            let boards: Vec<&str> = sel
                .iter()
                .map(|&i| input.measurements[i].board_id.as_str())
                .collect();
            let extra: Vec<Vec<f64>> = if numeric {
                vec![xnum.clone()]
            } else {
                let levels: Vec<&String> =
                    xcat.iter().collect::<BTreeSet<_>>().into_iter().collect();
                levels[1..]
                    .iter()
                    .map(|l| xcat.iter().map(|x| f64::from(u8::from(&x == l))).collect())
                    .collect()
            };
            let is_board = cov.name == BOARD_COVARIATE;
            let (nuisance, adjusted_for) = unit_nuisance(input, &sel);
            let mut intercept = vec![vec![1.0; n]];
            intercept.extend(nuisance);
            let blocked = (!is_board)
                .then(|| {
                    let mut base = intercept.clone();
                    base.extend(dummies(&boards));
                    nested_f(&base, &extra, &y)
                })
                .flatten();
            let (lm, blocked_by_board) = match blocked {
                Some(t) => (Some(t), true),
                None => (nested_f(&intercept, &extra, &y), false),
            };
            let Some(lm) = lm else {
                skipped.push(skip(format!(
                    "too few measurements for the test ({n} with {distinct} distinct values)"
                )));
                continue;
            };
            let levels = if numeric {
                vec![]
            } else {
                let mut by: BTreeMap<&str, Vec<f64>> = BTreeMap::new();
                for (x, v) in xcat.iter().zip(&y) {
                    by.entry(x.as_str()).or_default().push(*v);
                }
                by.into_iter()
                    .map(|(l, v)| LevelMean {
                        level: l.to_string(),
                        n: v.len(),
                        mean_rel_residual: mean(&v),
                    })
                    .collect()
            };
            let effect_rel = match lm.slope.filter(|_| numeric) {
                Some((b, _)) => {
                    let lo = xnum.iter().copied().fold(f64::INFINITY, f64::min);
                    let hi = xnum.iter().copied().fold(f64::NEG_INFINITY, f64::max);
                    b.abs() * (hi - lo)
                }
                None => {
                    let m: Vec<f64> = levels.iter().map(|l| l.mean_rel_residual).collect();
                    m.iter().copied().fold(f64::NEG_INFINITY, f64::max)
                        - m.iter().copied().fold(f64::INFINITY, f64::min)
                }
            };
            let per_label = if numeric {
                label_slopes(rows, setup, &scales, input, &sel, &xnum, blocked_by_board)
            } else {
                vec![]
            };
            tests.push(CovariateTest {
                setup: setup.clone(),
                covariate: cov.name.clone(),
                kind: if numeric { "numeric" } else { "categorical" }.to_string(),
                unit: cov.unit.clone(),
                n,
                blocked_by_board,
                adjusted_for,
                slope_rel_per_unit: lm.slope.filter(|_| numeric).map(|s| s.0),
                slope_se: lm.slope.filter(|_| numeric).map(|s| s.1),
                f: lm.f,
                df1: lm.df1,
                df2: lm.df2,
                p_value: lm.p,
                q_value: f64::NAN,
                effect_rel,
                significant: false,
                levels,
                per_label,
            });
        }
    }
    let q = benjamini_hochberg(&tests.iter().map(|t| t.p_value).collect::<Vec<_>>());
    for (t, q) in tests.iter_mut().zip(q) {
        t.q_value = q;
        t.significant = q <= opts.fdr && t.effect_rel > opts.tolerance_rel;
    }
    (tests, skipped)
}

/// The nuisance columns of the covariate tests over the measurements `sel` (indices into
/// [`LocateInput::measurements`]): each per-measurement parameter of the updating, centred,
/// and its name; none unless every selected measurement has one (a setup without
/// per-measurement parameters, or a table that does not cover it).
fn unit_nuisance(input: &LocateInput, sel: &[usize]) -> (Vec<Vec<f64>>, Vec<String>) {
    let rows: Option<Vec<&Vec<f64>>> = sel
        .iter()
        .map(|&i| {
            input
                .unit_params
                .get(&input.measurements[i].measurement_id)
                .filter(|v| {
                    v.len() == input.unit_param_names.len() && v.iter().all(|x| x.is_finite())
                })
        })
        .collect();
    match rows {
        Some(rows) if !rows.is_empty() && !input.unit_param_names.is_empty() => {
            let cols = (0..input.unit_param_names.len())
                .map(|k| {
                    let c: Vec<f64> = rows.iter().map(|r| r[k]).collect();
                    let m = mean(&c);
                    c.iter().map(|x| x - m).collect()
                })
                .collect();
            (cols, input.unit_param_names.clone())
        }
        _ => (vec![], vec![]),
    }
}

/// The residual rows with the located numeric covariates' per-label slopes taken out.
fn adjust_for_covariates(
    input: &LocateInput,
    rows: &[&ResidualObs],
    tests: &[CovariateTest],
) -> Vec<ResidualObs> {
    let mut out: Vec<ResidualObs> = rows.iter().map(|r| (*r).clone()).collect();
    let index: BTreeMap<&str, usize> = input
        .measurements
        .iter()
        .enumerate()
        .map(|(i, m)| (m.measurement_id.as_str(), i))
        .collect();
    for t in tests
        .iter()
        .filter(|t| t.significant && t.kind == "numeric")
    {
        let Some(CovariateValues::Numeric(v)) = input
            .covariates
            .iter()
            .find(|c| c.name == t.covariate)
            .map(|c| &c.values)
        else {
            continue;
        };
        let slopes: BTreeMap<&str, f64> = t
            .per_label
            .iter()
            .map(|l| (l.label.as_str(), l.slope_rel_per_unit))
            .collect();
        // Centre the covariate on the board's mean (the board's parameters absorbed its mean
        // effect, as in a step that updates the boards) or on the setup's (they did not, as
        // for boards carried into a later step): whichever leaves the smaller sum of squares
        // of the label-centred residuals.
        let adjusted = |by_board: bool| -> Vec<ResidualObs> {
            let key = |m_board: &'_ str| {
                if by_board {
                    m_board.to_string()
                } else {
                    String::new()
                }
            };
            let mut centres: BTreeMap<String, (f64, f64)> = BTreeMap::new();
            for (m, x) in input.measurements.iter().zip(v) {
                if let Some(x) = x.filter(|x| m.setup == t.setup && x.is_finite()) {
                    let e = centres.entry(key(&m.board_id)).or_insert((0.0, 0.0));
                    e.0 += x;
                    e.1 += 1.0;
                }
            }
            let mut o = out.clone();
            for r in o.iter_mut().filter(|r| r.setup == t.setup) {
                let x = index
                    .get(r.measurement_id.as_str())
                    .and_then(|&i| v.get(i).copied().flatten());
                if let (Some(x), Some(b), Some(c)) = (
                    x,
                    slopes.get(r.label.as_str()),
                    centres.get(&key(&r.board_id)),
                ) {
                    r.rel_residual -= b * (x - c.0 / c.1);
                }
            }
            o
        };
        let ss = |rows: &[ResidualObs]| -> f64 {
            let mut by: BTreeMap<&str, Vec<f64>> = BTreeMap::new();
            for r in rows.iter().filter(|r| r.setup == t.setup) {
                by.entry(r.label.as_str()).or_default().push(r.rel_residual);
            }
            by.values()
                .map(|v| {
                    let m = mean(v);
                    v.iter().map(|x| (x - m).powi(2)).sum::<f64>()
                })
                .sum()
        };
        let a = adjusted(true);
        let b = adjusted(false);
        out = if ss(&a) <= ss(&b) { a } else { b };
    }
    out
}

/// Indicator columns of all levels but the first.
fn dummies(levels: &[&str]) -> Vec<Vec<f64>> {
    let set: Vec<&str> = levels
        .iter()
        .copied()
        .collect::<BTreeSet<_>>()
        .into_iter()
        .collect();
    set[1..]
        .iter()
        .map(|l| levels.iter().map(|x| f64::from(u8::from(x == l))).collect())
        .collect()
}

fn label_slopes(
    rows: &[&ResidualObs],
    setup: &str,
    scales: &Scales,
    input: &LocateInput,
    sel: &[usize],
    x: &[f64],
    blocked: bool,
) -> Vec<LabelSlope> {
    let pos: BTreeMap<&str, usize> = sel
        .iter()
        .enumerate()
        .map(|(k, &i)| (input.measurements[i].measurement_id.as_str(), k))
        .collect();
    let mut by_label: BTreeMap<&str, Vec<(usize, f64)>> = BTreeMap::new();
    for r in rows.iter().filter(|r| r.setup == setup) {
        if let (Some(&k), Some(&(c, _, _))) = (
            pos.get(r.measurement_id.as_str()),
            scales.get(&(r.setup.clone(), r.label.clone())),
        ) {
            by_label
                .entry(r.label.as_str())
                .or_default()
                .push((k, r.rel_residual - c));
        }
    }
    by_label
        .into_iter()
        .filter_map(|(label, v)| {
            let y: Vec<f64> = v.iter().map(|p| p.1).collect();
            let xs: Vec<f64> = v.iter().map(|p| x[p.0]).collect();
            let mut base = vec![vec![1.0; y.len()]];
            if blocked {
                let b: Vec<&str> = v
                    .iter()
                    .map(|p| input.measurements[sel[p.0]].board_id.as_str())
                    .collect();
                base.extend(dummies(&b));
            }
            let t = nested_f(&base, &[xs], &y)?;
            let (s, se) = t.slope?;
            Some(LabelSlope {
                label: label.to_string(),
                n: y.len(),
                slope_rel_per_unit: s,
                se,
            })
        })
        .collect()
}

fn unpaired_clusters(input: &LocateInput, opts: &LocateOptions) -> Vec<UnpairedCluster> {
    let paired: BTreeSet<(&str, i32)> = input
        .pairs
        .iter()
        .filter(|p| p.accepted)
        .filter_map(|p| p.mode.map(|m| (p.measurement_id.as_str(), m)))
        .collect();
    let mut by_setup: BTreeMap<&str, Vec<(f64, &str)>> = BTreeMap::new();
    for m in &input.identified {
        if m.freq_hz.is_finite() && !paired.contains(&(m.measurement_id.as_str(), m.mode)) {
            by_setup
                .entry(m.setup.as_str())
                .or_default()
                .push((m.freq_hz, m.measurement_id.as_str()));
        }
    }
    let mut n_setup: BTreeMap<&str, BTreeSet<&str>> = BTreeMap::new();
    for m in &input.measurements {
        n_setup
            .entry(m.setup.as_str())
            .or_default()
            .insert(m.measurement_id.as_str());
    }
    for m in &input.identified {
        n_setup
            .entry(m.setup.as_str())
            .or_default()
            .insert(m.measurement_id.as_str());
    }
    let mut out = vec![];
    for (setup, mut v) in by_setup {
        v.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(b.1)));
        let total = n_setup.get(setup).map_or(0, |s| s.len()).max(1);
        // Greedy densest window: the window [f, f (1 + w)] holding the most distinct
        // measurements becomes a cluster, its modes leave, repeat. Unlike single linkage it
        // cannot chain scattered modes into one wide "cluster".
        while !v.is_empty() {
            let mut best = (0, 0, 0usize);
            for i in 0..v.len() {
                let hi = v[i].0 * (1.0 + opts.cluster_rel_width);
                let j = i + v[i..].iter().take_while(|p| p.0 <= hi).count();
                let n = v[i..j].iter().map(|p| p.1).collect::<BTreeSet<_>>().len();
                if n > best.2 {
                    best = (i, j, n);
                }
            }
            let (i, j, _) = best;
            let c: Vec<(f64, &str)> = v.drain(i..j).collect();
            let f: Vec<f64> = c.iter().map(|p| p.0).collect();
            let ms: BTreeSet<&str> = c.iter().map(|p| p.1).collect();
            let share = ms.len() as f64 / total as f64;
            out.push(UnpairedCluster {
                setup: setup.to_string(),
                median_freq_hz: median(&f),
                min_freq_hz: f[0],
                max_freq_hz: f[f.len() - 1],
                n_modes: c.len(),
                n_measurements: ms.len(),
                share_of_setup: share,
                recurring: share >= opts.recurring_share
                    && ms.len() >= opts.recurring_min_measurements,
                measurement_ids: ms.into_iter().map(str::to_string).collect(),
            });
        }
    }
    out.sort_by(|a, b| {
        a.setup
            .cmp(&b.setup)
            .then(a.median_freq_hz.total_cmp(&b.median_freq_hz))
    });
    out
}

fn model_mode_presence(input: &LocateInput) -> Vec<ModelModePresence> {
    type Acc<'a> = (BTreeSet<&'a str>, BTreeSet<&'a str>, Vec<f64>);
    let mut acc: BTreeMap<(&str, &str), Acc> = BTreeMap::new();
    for p in &input.pairs {
        let e = acc
            .entry((p.setup.as_str(), p.label.as_str()))
            .or_insert_with(|| (BTreeSet::new(), BTreeSet::new(), vec![]));
        e.0.insert(p.measurement_id.as_str());
        if p.missing {
            e.1.insert(p.measurement_id.as_str());
        }
        if let Some(f) = p.model_freq_hz.filter(|f| f.is_finite()) {
            e.2.push(f);
        }
    }
    acc.into_iter()
        .map(|((s, l), (all, miss, f))| ModelModePresence {
            setup: s.to_string(),
            label: l.to_string(),
            median_model_freq_hz: (!f.is_empty()).then(|| median(&f)),
            n_measurements: all.len(),
            n_missing: miss.len(),
            never_seen: !all.is_empty() && miss.len() == all.len(),
        })
        .collect()
}

#[cfg(test)]
#[path = "locate_tests.rs"]
mod tests;

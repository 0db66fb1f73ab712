//! The diagnosis section of the validation report (pure): `diagnosis.json` as the report
//! reads it ([`DiagnosisView`], lenient: every number may be null, fields the report does not
//! show are ignored), the per-mode misfits of `diagnosis_modes.parquet` ([`ModeMisfit`]), and
//! the tables the section shows, built once ([`tables`]) so that the page and the Parquet/CSV
//! files next to it hold the same values.

use crate::table_spec::{c, Col, TableSpec};
use serde::Deserialize;

/// `diagnosis.json`, the parts the report shows.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(default)]
pub struct DiagnosisView {
    /// `no_missing_physics`, `mechanism_found` or `unexplained_misfit`.
    pub verdict: String,
    pub located: LocatedView,
    pub findings: Vec<FindingView>,
    pub candidates: Vec<CandidateView>,
    pub remaining_discrepancy: String,
    pub checks: ChecksView,
}

#[derive(Clone, Debug, Default, Deserialize)]
#[serde(default)]
pub struct LocatedView {
    pub any: bool,
    pub setups: Vec<String>,
    pub modes: Vec<LocatedModeView>,
    pub measurements: Vec<String>,
    pub shape_outliers: Vec<ShapeOutlierView>,
    pub identification_outliers: Vec<IdentificationOutlierView>,
    pub covariates: Vec<CovariateView>,
    pub unpaired_clusters: Vec<ClusterView>,
    pub never_seen: Vec<NeverSeenView>,
    pub board_regions: Vec<RegionView>,
    pub board_regions_note: String,
}

#[derive(Clone, Debug, Default, Deserialize)]
#[serde(default)]
pub struct ShapeOutlierView {
    pub measurement_id: String,
    pub board_id: String,
    pub setup: String,
    pub n_modes: usize,
    pub q_value: Option<f64>,
}

#[derive(Clone, Debug, Default, Deserialize)]
#[serde(default)]
pub struct RegionView {
    pub mechanism: String,
    pub amplitude_unit: String,
    pub located: bool,
    pub fit: RegionFitView,
    pub sentence: String,
}

#[derive(Clone, Debug, Default, Deserialize)]
#[serde(default)]
pub struct RegionFitView {
    pub x_m: Option<f64>,
    pub y_m: Option<f64>,
    pub amplitude: Option<f64>,
    pub amplitude_se: Option<f64>,
    pub region_radius_m: Option<f64>,
    pub explained_share: Option<f64>,
    pub p_value: Option<f64>,
    pub alternatives: Vec<[f64; 3]>,
}

#[derive(Clone, Debug, Default, Deserialize)]
#[serde(default)]
pub struct IdentificationOutlierView {
    pub measurement_id: String,
    pub board_id: String,
    pub setup: String,
    pub label: String,
    pub centred_rel_residual: Option<f64>,
    pub z: Option<f64>,
    pub p_value_other_modes: Option<f64>,
}

#[derive(Clone, Debug, Default, Deserialize)]
#[serde(default)]
pub struct LocatedModeView {
    pub setup: String,
    pub label: String,
    pub mean_rel_residual: Option<f64>,
    pub reasons: Vec<String>,
}

#[derive(Clone, Debug, Default, Deserialize)]
#[serde(default)]
pub struct CovariateView {
    pub setup: String,
    pub covariate: String,
    pub q_value: Option<f64>,
    pub slope_rel_per_unit: Option<f64>,
    pub unit: String,
}

#[derive(Clone, Debug, Default, Deserialize)]
#[serde(default)]
pub struct ClusterView {
    pub setup: String,
    pub median_freq_hz: Option<f64>,
    pub min_freq_hz: Option<f64>,
    pub max_freq_hz: Option<f64>,
    pub n_modes: usize,
    pub n_measurements: usize,
    pub share_of_setup: Option<f64>,
}

#[derive(Clone, Debug, Default, Deserialize)]
#[serde(default)]
pub struct NeverSeenView {
    pub setup: String,
    pub label: String,
    pub median_model_freq_hz: Option<f64>,
    pub n_measurements: usize,
    pub n_missing: usize,
}

#[derive(Clone, Debug, Default, Deserialize)]
#[serde(default)]
pub struct FindingView {
    pub sentence: String,
}

#[derive(Clone, Debug, Default, Deserialize)]
#[serde(default)]
pub struct CandidateView {
    pub id: String,
    pub candidate: ScreenedView,
    pub refit: Option<ComparedView>,
    pub sentence: String,
}

#[derive(Clone, Debug, Default, Deserialize)]
#[serde(default)]
pub struct ScreenedView {
    pub mechanism: String,
    pub joint: Option<i64>,
    pub covariate: Option<String>,
    pub reason: String,
}

#[derive(Clone, Debug, Default, Deserialize)]
#[serde(default)]
pub struct ComparedView {
    pub refit: RefitView,
    pub log_bayes_factor: Option<f64>,
    pub log_bayes_factor_se: Option<f64>,
    pub favoured: bool,
    /// (setup, before %, after %).
    pub held_out_before_after: Vec<(String, Option<f64>, Option<f64>)>,
}

#[derive(Clone, Debug, Default, Deserialize)]
#[serde(default)]
pub struct RefitView {
    pub estimates: Vec<EstimateView>,
    pub failed: Option<String>,
}

#[derive(Clone, Debug, Default, Deserialize)]
#[serde(default)]
pub struct EstimateView {
    pub parameter: String,
    pub scope: String,
    pub median: Option<f64>,
    pub q05: Option<f64>,
    pub q95: Option<f64>,
}

#[derive(Clone, Debug, Default, Deserialize)]
#[serde(default)]
pub struct ChecksView {
    pub measurements_after_covariates: Vec<String>,
    pub measurement_checks: Vec<MeasurementCheckView>,
}

#[derive(Clone, Debug, Default, Deserialize)]
#[serde(default)]
pub struct MeasurementCheckView {
    pub measurement_id: String,
    pub board_id: String,
    pub setup: String,
    pub n_modes: usize,
    pub chi2: Option<f64>,
    pub q_value: Option<f64>,
}

/// A row of `diagnosis_modes.parquet`.
#[derive(Clone, Debug, PartialEq)]
pub struct ModeMisfit {
    /// `baseline` or a refitted candidate's id.
    pub model: String,
    pub setup: String,
    pub label: String,
    pub used_for_updating: bool,
    pub n: usize,
    pub mean_rel_residual: Option<f64>,
    pub located: bool,
}

/// What the report knows of the diagnosis.
#[derive(Clone, Debug, Default)]
pub struct DiagnosisData {
    pub doc: DiagnosisView,
    /// `diagnosis_modes.parquet`; `None` when the diagnose stage did not write it (an older
    /// version): the before/after table and figure then say so.
    pub modes: Option<Vec<ModeMisfit>>,
}

/// One cell of a section table.
#[derive(Clone, Debug, PartialEq)]
pub enum Cell {
    Str(Option<String>),
    F64(Option<f64>),
    Int(Option<i64>),
    Bool(bool),
}

/// A table of the section: its spec (the Parquet/CSV file the report stage writes, its
/// columns in the order of the rows' cells), the page's column headers and the rows.
#[derive(Clone, Debug)]
pub struct Table {
    pub spec: &'static TableSpec,
    pub headers: &'static [&'static str],
    /// Decimals shown per column (numbers only; the page keeps the full value in `data-value`).
    pub digits: &'static [usize],
    pub rows: Vec<Vec<Cell>>,
}

pub const LOCATED_MODES: TableSpec = TableSpec {
    name: "diagnosis_located_modes",
    doc: "The modes the diagnosis located as misfitting (diagnosis.json: located.modes): setup, label, the baseline's mean relative residual (f_measured − f̄_model)/f̄_model in percent, and why (mean_shift, eps_excess, validation).",
    open: false,
    columns: &[
        c("setup", Col::Utf8, false, "", "Setup."),
        c("label", Col::Utf8, false, "", "Mode label."),
        c("mean_rel_residual_pct", Col::Float64, true, "%", "Mean relative residual of the baseline, percent."),
        c("reasons", Col::Utf8, false, "", "Why it was located, comma-separated."),
    ],
};

pub const OUTLIERS: TableSpec = TableSpec {
    name: "diagnosis_outliers",
    doc: "Outlier measurements of the diagnosis (diagnosis.json: located.measurements, with their check from checks.measurement_checks): the joint statistic over the measurement's modes and its BH q-value, the shape check's q-value where the mode shapes make it one (located.shape_outliers), and whether it stays an outlier once the located covariates are taken out.",
    open: false,
    columns: &[
        c("measurement_id", Col::Utf8, false, "", "Measurement."),
        c("board_id", Col::Utf8, true, "", "Board."),
        c("setup", Col::Utf8, true, "", "Setup."),
        c("n_modes", Col::Int32, true, "", "Modes in the statistic."),
        c("chi2", Col::Float64, true, "", "Sum of squared normal scores over the modes (~chi2(n_modes) when like the others)."),
        c("q_value", Col::Float64, true, "", "Benjamini–Hochberg q-value over all measurements."),
        c("shape_q_value", Col::Float64, true, "", "The shape check's BH q-value (every mode's MAC against the setup's; located.shape_outliers); null when not a shape outlier."),
        c("outlier_after_covariates", Col::Bool, false, "", "Still an outlier with the located covariates taken out."),
    ],
};

pub const IDENTIFICATION_OUTLIERS: TableSpec = TableSpec {
    name: "diagnosis_identification_outliers",
    doc: "Outlier measurements whose deviation is one mode's alone (diagnosis.json: located.identification_outliers): the mode is far from the other measurements while the measurement's other modes agree with them. Likely a slip of the modal fit; listed for checking, not counted as misfit.",
    open: false,
    columns: &[
        c("measurement_id", Col::Utf8, false, "", "Measurement."),
        c("board_id", Col::Utf8, false, "", "Board."),
        c("setup", Col::Utf8, false, "", "Setup."),
        c("label", Col::Utf8, false, "", "The mode that deviates."),
        c("centred_rel_residual_pct", Col::Float64, true, "%", "Its relative residual minus the mean of the other clean measurements, percent."),
        c("z", Col::Float64, true, "", "Its predictive t beyond the tolerance."),
        c("p_value_other_modes", Col::Float64, true, "", "Chi-square p of the measurement's other modes."),
    ],
};

pub const COVARIATES: TableSpec = TableSpec {
    name: "diagnosis_covariates",
    doc: "Sheet columns the residuals follow significantly (diagnosis.json: located.covariates): the BH q-value of the covariate's test and, for a numeric covariate, the slope of the relative residual per unit of the covariate.",
    open: false,
    columns: &[
        c("setup", Col::Utf8, false, "", "Setup."),
        c("covariate", Col::Utf8, false, "", "Sheet column."),
        c("q_value", Col::Float64, true, "", "Benjamini–Hochberg q-value over the covariate tests."),
        c("slope_rel_per_unit", Col::Float64, true, "", "Relative residual per unit of the covariate (numeric covariates)."),
        c("unit", Col::Utf8, false, "", "Unit of the covariate (empty when none)."),
    ],
};

pub const CLUSTERS: TableSpec = TableSpec {
    name: "diagnosis_unpaired_clusters",
    doc: "Recurring clusters of identified modes that no model mode pairs with (diagnosis.json: located.unpaired_clusters): a mode the model lacks.",
    open: false,
    columns: &[
        c("setup", Col::Utf8, false, "", "Setup."),
        c("median_freq_hz", Col::Float64, true, "Hz", "Median frequency of the cluster."),
        c("min_freq_hz", Col::Float64, true, "Hz", "Lowest frequency."),
        c("max_freq_hz", Col::Float64, true, "Hz", "Highest frequency."),
        c("n_modes", Col::Int32, false, "", "Identified modes in the cluster."),
        c("n_measurements", Col::Int32, false, "", "Measurements with a mode in it."),
        c("share_of_setup", Col::Float64, true, "", "Share of the setup's measurements."),
    ],
};

pub const NEVER_SEEN: TableSpec = TableSpec {
    name: "diagnosis_never_seen",
    doc: "Model modes never identified in any measurement of their setup (diagnosis.json: located.never_seen); not counted as a misfit (a nodal line at the excitation point or a band edge does this).",
    open: false,
    columns: &[
        c("setup", Col::Utf8, false, "", "Setup."),
        c("label", Col::Utf8, false, "", "Model mode label."),
        c("median_model_freq_hz", Col::Float64, true, "Hz", "Median model frequency over the measurements."),
        c("n_measurements", Col::Int32, false, "", "Measurements of the setup."),
        c("n_missing", Col::Int32, false, "", "Measurements where it was not identified."),
    ],
};

pub const REGIONS: TableSpec = TableSpec {
    name: "diagnosis_board_regions",
    doc: "Where on the board (diagnosis.json: located.board_regions): the localisations of the free-free misfit, one row per signature (a point mass, `added_mass`; a change of the core's bending stiffness over a small disc, `local_stiffness_loss`, either sign): the best point of a grid over the board, the amplitude there (a mass in g, or the stiffness factor − 1), the 90 % region's radius, the share of the misfit (off the board parameters' span) it explains, and the places the frequencies cannot tell apart from it. Where both signatures pass the rule, only the one explaining more is located.",
    open: false,
    columns: &[
        c("mechanism", Col::Utf8, false, "", "Mechanism whose signature was fitted."),
        c("located", Col::Bool, false, "", "Significant and explains at least half the misfit."),
        c("x_mm", Col::Float64, true, "mm", "Best point, x."),
        c("y_mm", Col::Float64, true, "mm", "Best point, y."),
        c("amplitude", Col::Float64, true, "", "Least-squares amplitude at the best point, in amplitude_unit."),
        c("amplitude_se", Col::Float64, true, "", "Its standard error."),
        c("amplitude_unit", Col::Utf8, false, "", "`g` (a point mass) or `factor - 1` (the core's bending stiffness over the disc)."),
        c("region_radius_mm", Col::Float64, true, "mm", "Radius of the 90 % region."),
        c("explained_share", Col::Float64, true, "", "Share of the misfit explained."),
        c("p_value", Col::Float64, true, "", "Tail probability of the χ² reduction under no change."),
        c("alternatives", Col::Utf8, false, "", "Other points (mm) the frequencies fit about as well."),
    ],
};

pub const CANDIDATES: TableSpec = TableSpec {
    name: "diagnosis_candidates",
    doc: "The mechanisms the diagnosis screened (diagnosis.json: candidates), strongest first: why each was screened in, whether it was refitted, its log Bayes factor over the baseline with the standard error, whether it is favoured, the held-out mean absolute frequency error before and after per setup, the parameter estimates (median and 90 % interval) and why a refit failed. A candidate with several held-out setups or parameters takes several rows (the k-th setup and the k-th parameter side by side, the candidate's columns repeated).",
    open: false,
    columns: &[
        c("rank", Col::Int32, false, "", "Order in diagnosis.json (1 = strongest)."),
        c("id", Col::Utf8, false, "", "Candidate id (its refit directory under diagnose/refits/)."),
        c("mechanism", Col::Utf8, false, "", "Mechanism id."),
        c("joint", Col::Int32, true, "", "Joint of a per-joint candidate (1-based)."),
        c("covariate", Col::Utf8, true, "", "Sheet column the candidate follows."),
        c("screen_reason", Col::Utf8, false, "", "Why the screening kept it."),
        c("refitted", Col::Bool, false, "", "A refit was run."),
        c("log_bayes_factor", Col::Float64, true, "", "ln p(data | candidate) − ln p(data | baseline)."),
        c("log_bayes_factor_se", Col::Float64, true, "", "Its standard error over the independent runs."),
        c("favoured", Col::Bool, false, "", "Passes the decision rule."),
        c("held_out_setup", Col::Utf8, true, "", "Setup of the held-out error."),
        c("held_out_before_pct", Col::Float64, true, "%", "Held-out mean absolute frequency error of the baseline, percent."),
        c("held_out_after_pct", Col::Float64, true, "%", "The same with the candidate, percent."),
        c("parameter", Col::Utf8, true, "", "Parameter of the estimate (unit in its name)."),
        c("estimate_median", Col::Float64, true, "", "Median (the parameter's unit)."),
        c("estimate_q05", Col::Float64, true, "", "5 % quantile."),
        c("estimate_q95", Col::Float64, true, "", "95 % quantile."),
        c("failed", Col::Utf8, true, "", "Why the refit gave no posterior."),
    ],
};

pub const BEFORE_AFTER: TableSpec = TableSpec {
    name: "diagnosis_before_after",
    doc: "Each mode's mean relative residual (f_measured − f̄_model)/f̄_model in percent, baseline against the best refit (the first favoured candidate, else the first refitted one that gave a posterior), from diagnose/diagnosis_modes.parquet: every mode of the setups the refit covers; without a refit, the located modes with the baseline only.",
    open: false,
    columns: &[
        c("setup", Col::Utf8, false, "", "Setup."),
        c("label", Col::Utf8, false, "", "Mode label."),
        c("used_for_updating", Col::Bool, false, "", "Used for updating (false: a validation mode)."),
        c("located", Col::Bool, false, "", "Located as misfitting in the baseline."),
        c("n_before", Col::Int32, true, "", "Measurements behind the baseline's mean."),
        c("before_pct", Col::Float64, true, "%", "Baseline mean relative residual, percent."),
        c("model", Col::Utf8, true, "", "The refit (candidate id); null without one."),
        c("n_after", Col::Int32, true, "", "Measurements behind the refit's mean."),
        c("after_pct", Col::Float64, true, "%", "The refit's mean relative residual, percent."),
    ],
};

/// Every table of the section, in the order [`tables`] returns them.
pub const SECTIONS: [&TableSpec; 9] = [
    &LOCATED_MODES,
    &OUTLIERS,
    &IDENTIFICATION_OUTLIERS,
    &COVARIATES,
    &CLUSTERS,
    &NEVER_SEEN,
    &REGIONS,
    &CANDIDATES,
    &BEFORE_AFTER,
];

fn s(v: &str) -> Cell {
    Cell::Str(Some(v.to_string()))
}
fn so(v: Option<&str>) -> Cell {
    Cell::Str(v.map(str::to_string))
}
fn f(v: Option<f64>) -> Cell {
    Cell::F64(v.filter(|x| x.is_finite()))
}
fn pct(v: Option<f64>) -> Cell {
    f(v.map(|x| 100.0 * x))
}
fn i(v: usize) -> Cell {
    Cell::Int(Some(v as i64))
}

/// The refit the before/after comparison shows: the first favoured candidate that has mode
/// rows, else the first refitted one that has them (candidates are strongest first).
pub fn best_refit(d: &DiagnosisData) -> Option<String> {
    let modes = d.modes.as_ref()?;
    let has = |id: &str| modes.iter().any(|m| m.model == id);
    let refitted = || {
        d.doc
            .candidates
            .iter()
            .filter(|c| c.refit.as_ref().is_some_and(|r| r.refit.failed.is_none()))
    };
    refitted()
        .find(|c| c.refit.as_ref().is_some_and(|r| r.favoured) && has(&c.id))
        .or_else(|| refitted().find(|c| has(&c.id)))
        .map(|c| c.id.clone())
}

/// The section's tables, in the order the page shows them.
pub fn tables(d: &DiagnosisData) -> Vec<Table> {
    let loc = &d.doc.located;
    vec![
        located_modes_table(loc),
        outliers_table(&d.doc),
        slips_table(loc),
        covariates_table(loc),
        clusters_table(loc),
        never_seen_table(loc),
        regions_table(loc),
        candidates_table(&d.doc),
        before_after_table(d),
    ]
}

/// The located modes.
fn located_modes_table(loc: &LocatedView) -> Table {
    let located_modes = loc
        .modes
        .iter()
        .map(|m| {
            vec![
                s(&m.setup),
                s(&m.label),
                pct(m.mean_rel_residual),
                s(&m.reasons.join(", ")),
            ]
        })
        .collect();
    Table {
        spec: &LOCATED_MODES,
        headers: &["setup", "mode", "mean relative residual [%]", "reasons"],
        digits: &[0, 0, 3, 0],
        rows: located_modes,
    }
}

/// The outlier measurements with their checks.
fn outliers_table(doc: &DiagnosisView) -> Table {
    let loc = &doc.located;
    let outliers = loc
        .measurements
        .iter()
        .map(|id| {
            let chk = doc
                .checks
                .measurement_checks
                .iter()
                .find(|m| &m.measurement_id == id);
            let shape = loc.shape_outliers.iter().find(|m| &m.measurement_id == id);
            vec![
                s(id),
                so(chk
                    .map(|m| m.board_id.as_str())
                    .or(shape.map(|m| m.board_id.as_str()))),
                so(chk
                    .map(|m| m.setup.as_str())
                    .or(shape.map(|m| m.setup.as_str()))),
                Cell::Int(chk.map(|m| m.n_modes as i64)),
                f(chk.and_then(|m| m.chi2)),
                f(chk.and_then(|m| m.q_value)),
                f(shape.and_then(|m| m.q_value)),
                Cell::Bool(doc.checks.measurements_after_covariates.contains(id)),
            ]
        })
        .collect();
    Table {
        spec: &OUTLIERS,
        headers: &[
            "measurement",
            "board",
            "setup",
            "modes",
            "χ²",
            "q-value",
            "shape q-value",
            "still an outlier without the covariates",
        ],
        digits: &[0, 0, 0, 0, 1, 4, 4, 0],
        rows: outliers,
    }
}

/// The identification outliers (one mode of one measurement).
fn slips_table(loc: &LocatedView) -> Table {
    let slips = loc
        .identification_outliers
        .iter()
        .map(|o| {
            vec![
                s(&o.measurement_id),
                s(&o.board_id),
                s(&o.setup),
                s(&o.label),
                pct(o.centred_rel_residual),
                f(o.z),
                f(o.p_value_other_modes),
            ]
        })
        .collect();
    Table {
        spec: &IDENTIFICATION_OUTLIERS,
        headers: &[
            "measurement",
            "board",
            "setup",
            "mode",
            "off the others [%]",
            "t",
            "p of its other modes",
        ],
        digits: &[0, 0, 0, 0, 3, 1, 3],
        rows: slips,
    }
}

/// The significant covariates.
fn covariates_table(loc: &LocatedView) -> Table {
    let covariates = loc
        .covariates
        .iter()
        .map(|c| {
            vec![
                s(&c.setup),
                s(&c.covariate),
                f(c.q_value),
                f(c.slope_rel_per_unit),
                s(&c.unit),
            ]
        })
        .collect();
    Table {
        spec: &COVARIATES,
        headers: &[
            "setup",
            "covariate",
            "q-value",
            "slope [relative residual per unit]",
            "unit",
        ],
        digits: &[0, 0, 4, 6, 0],
        rows: covariates,
    }
}

/// The recurring unpaired-mode clusters.
fn clusters_table(loc: &LocatedView) -> Table {
    let clusters = loc
        .unpaired_clusters
        .iter()
        .map(|c| {
            vec![
                s(&c.setup),
                f(c.median_freq_hz),
                f(c.min_freq_hz),
                f(c.max_freq_hz),
                i(c.n_modes),
                i(c.n_measurements),
                f(c.share_of_setup),
            ]
        })
        .collect();
    Table {
        spec: &CLUSTERS,
        headers: &[
            "setup",
            "median [Hz]",
            "min [Hz]",
            "max [Hz]",
            "modes",
            "measurements",
            "share of the setup",
        ],
        digits: &[0, 2, 2, 2, 0, 0, 3],
        rows: clusters,
    }
}

/// The model modes never seen.
fn never_seen_table(loc: &LocatedView) -> Table {
    let never = loc
        .never_seen
        .iter()
        .map(|m| {
            vec![
                s(&m.setup),
                s(&m.label),
                f(m.median_model_freq_hz),
                i(m.n_measurements),
                i(m.n_missing),
            ]
        })
        .collect();
    Table {
        spec: &NEVER_SEEN,
        headers: &[
            "setup",
            "model mode",
            "median model frequency [Hz]",
            "measurements",
            "not identified in",
        ],
        digits: &[0, 0, 2, 0, 0],
        rows: never,
    }
}

/// The board regions (a mass in g).
fn regions_table(loc: &LocatedView) -> Table {
    let mm = |v: Option<f64>| v.map(|x| x * 1e3);
    // A mass in g; another amplitude as it is.
    let amp = |r: &RegionView, v: Option<f64>| {
        if r.amplitude_unit == "kg" {
            mm(v)
        } else {
            v
        }
    };
    let regions = loc
        .board_regions
        .iter()
        .map(|r| {
            vec![
                s(&r.mechanism),
                Cell::Bool(r.located),
                f(mm(r.fit.x_m)),
                f(mm(r.fit.y_m)),
                f(amp(r, r.fit.amplitude)),
                f(amp(r, r.fit.amplitude_se)),
                s(if r.amplitude_unit == "kg" {
                    "g"
                } else {
                    &r.amplitude_unit
                }),
                f(mm(r.fit.region_radius_m)),
                f(r.fit.explained_share),
                f(r.fit.p_value),
                s(&r.fit
                    .alternatives
                    .iter()
                    .map(|a| format!("({:.0}, {:.0})", a[0] * 1e3, a[1] * 1e3))
                    .collect::<Vec<_>>()
                    .join(" ")),
            ]
        })
        .collect();
    Table {
        spec: &REGIONS,
        headers: &[
            "mechanism",
            "located",
            "x [mm]",
            "y [mm]",
            "amplitude",
            "± se",
            "unit",
            "90 % radius [mm]",
            "share explained",
            "p",
            "also fits at [mm]",
        ],
        digits: &[0, 0, 1, 1, 3, 3, 0, 1, 3, 3, 0],
        rows: regions,
    }
}

/// The candidates: a row per held-out setup and estimate (at least one).
fn candidates_table(doc: &DiagnosisView) -> Table {
    let mut cands = vec![];
    for (k, cd) in doc.candidates.iter().enumerate() {
        let r = cd.refit.as_ref();
        let held: &[(String, Option<f64>, Option<f64>)] =
            r.map(|r| r.held_out_before_after.as_slice()).unwrap_or(&[]);
        let est: &[EstimateView] = r.map(|r| r.refit.estimates.as_slice()).unwrap_or(&[]);
        for j in 0..held.len().max(est.len()).max(1) {
            let h = held.get(j);
            let e = est.get(j);
            cands.push(vec![
                i(k + 1),
                s(&cd.id),
                s(&cd.candidate.mechanism),
                Cell::Int(cd.candidate.joint),
                so(cd.candidate.covariate.as_deref()),
                s(&cd.candidate.reason),
                Cell::Bool(r.is_some()),
                f(r.and_then(|r| r.log_bayes_factor)),
                f(r.and_then(|r| r.log_bayes_factor_se)),
                Cell::Bool(r.is_some_and(|r| r.favoured)),
                so(h.map(|h| h.0.as_str())),
                f(h.and_then(|h| h.1)),
                f(h.and_then(|h| h.2)),
                so(e.map(|e| e.parameter.as_str())),
                f(e.and_then(|e| e.median)),
                f(e.and_then(|e| e.q05)),
                f(e.and_then(|e| e.q95)),
                so(r.and_then(|r| r.refit.failed.as_deref())),
            ]);
        }
    }
    Table {
        spec: &CANDIDATES,
        headers: &[
            "rank",
            "id",
            "mechanism",
            "joint",
            "covariate",
            "screened in because",
            "refitted",
            "log Bayes factor",
            "± se",
            "favoured",
            "held-out setup",
            "held-out error before [%]",
            "after [%]",
            "parameter",
            "median",
            "5 %",
            "95 %",
            "refit failed",
        ],
        digits: &[0, 0, 0, 0, 0, 0, 0, 2, 2, 0, 0, 4, 4, 0, 4, 4, 4, 0],
        rows: cands,
    }
}

/// The before/after per mode of the best refit ([`best_refit`]); without one, the located modes with the baseline only.
fn before_after_table(d: &DiagnosisData) -> Table {
    let mut before_after = vec![];
    let best = best_refit(d);
    if let Some(modes) = &d.modes {
        let base = modes.iter().filter(|m| m.model == "baseline");
        match &best {
            Some(id) => {
                for a in modes.iter().filter(|m| &m.model == id) {
                    let b = base
                        .clone()
                        .find(|b| b.setup == a.setup && b.label == a.label);
                    before_after.push(vec![
                        s(&a.setup),
                        s(&a.label),
                        Cell::Bool(a.used_for_updating),
                        Cell::Bool(b.is_some_and(|b| b.located)),
                        Cell::Int(b.map(|b| b.n as i64)),
                        pct(b.and_then(|b| b.mean_rel_residual)),
                        s(id),
                        i(a.n),
                        pct(a.mean_rel_residual),
                    ]);
                }
            }
            None => {
                for b in base.filter(|b| b.located) {
                    before_after.push(vec![
                        s(&b.setup),
                        s(&b.label),
                        Cell::Bool(b.used_for_updating),
                        Cell::Bool(true),
                        i(b.n),
                        pct(b.mean_rel_residual),
                        Cell::Str(None),
                        Cell::Int(None),
                        Cell::F64(None),
                    ]);
                }
            }
        }
    }
    Table {
        spec: &BEFORE_AFTER,
        headers: &[
            "setup",
            "mode",
            "updating",
            "located",
            "n before",
            "before [%]",
            "refit",
            "n after",
            "after [%]",
        ],
        digits: &[0, 0, 0, 0, 0, 4, 0, 0, 4],
        rows: before_after,
    }
}

/// The verdict in plain language, for a test engineer.
pub fn verdict_statement(doc: &DiagnosisView) -> String {
    match doc.verdict.as_str() {
        "no_missing_physics" => match doc.remaining_discrepancy.strip_prefix("none: ") {
            Some(q) if q.starts_with("the model differs") => format!("No missing physics: {q}. Nothing to change in the model or the test."),
            _ => "No missing physics: the updated model fits every setup, mode and measurement within the tolerance; nothing to change in the model or the test.".to_string(),
        },
        "mechanism_found" => {
            let s: Vec<&str> = doc.findings.iter().map(|f| f.sentence.as_str()).collect();
            format!(
                "Missing physics found, and a mechanism explains it: {}",
                if s.is_empty() { "(no finding sentence in diagnosis.json)".to_string() } else { s.join(" ") }
            )
        }
        "unexplained_misfit" => "The model misfits the measurements where located below, and no refitted mechanism of the library explains it: check the test set-up (fixture, bolts, sensors) at the located setups and modes before trusting predictions there.".to_string(),
        "model_form" => format!("The model's form limits its fit, not a concealed effect: {}", doc.remaining_discrepancy.strip_prefix("model form: ").unwrap_or(&doc.remaining_discrepancy)),
        v => format!("Unknown verdict `{v}` in diagnosis.json."),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::diagnose::doc::{
        CandidateDoc, DiagnoseOptions, DiagnosisDoc, FindingDoc, HeldOut, LocatedSummary,
    };
    use crate::diagnose::library::Mechanism;
    use crate::diagnose::locate::{
        self, LocateInput, LocateOptions, LocatedCovariate, LocatedMode, MeasurementCheck,
        ModelModePresence, UnpairedCluster,
    };
    use crate::diagnose::screen::Candidate;
    use crate::diagnose::select::{Compared, Estimate, Refit, SelectOptions, Verdict};
    use crate::report::html::{render, ReportData};
    use std::collections::BTreeMap;

    /// A diagnosis document from the diagnose stage's own types, with a known content.
    fn doc(verdict: Verdict) -> DiagnosisDoc {
        let lo = LocateOptions::default();
        let mut checks = locate::locate(&LocateInput::default(), &lo);
        let modes = vec![
            LocatedMode {
                setup: "bolted".into(),
                label: "plate-0-0".into(),
                mean_rel_residual: 0.00367165366012717,
                reasons: vec!["mean_shift".into(), "eps_excess".into()],
            },
            LocatedMode {
                setup: "bolted".into(),
                label: "plate-2-2".into(),
                mean_rel_residual: -0.0007180620223115361,
                reasons: vec!["mean_shift".into()],
            },
        ];
        let covariates = vec![LocatedCovariate {
            setup: "bolted".into(),
            covariate: "temperature_c".into(),
            q_value: 1.25e-4,
            slope_rel_per_unit: Some(-2.5e-4),
            unit: "°C".into(),
        }];
        let clusters = vec![UnpairedCluster {
            setup: "bolted".into(),
            median_freq_hz: 1234.5,
            min_freq_hz: 1230.25,
            max_freq_hz: 1240.0,
            n_modes: 7,
            n_measurements: 6,
            share_of_setup: 0.6,
            recurring: true,
            measurement_ids: vec![],
        }];
        let never = vec![ModelModePresence {
            setup: "bolted".into(),
            label: "plate-3-1".into(),
            median_model_freq_hz: Some(3110.8496570560533),
            n_measurements: 27,
            n_missing: 27,
            never_seen: true,
        }];
        checks.measurement_checks = vec![MeasurementCheck {
            measurement_id: "B03-bolted-2".into(),
            board_id: "B03".into(),
            setup: "bolted".into(),
            n_modes: 9,
            chi2: 87.125,
            p_value: Some(1e-9),
            q_value: Some(3.5e-8),
            outlier: true,
            single_mode: None,
            left_out_of_scale: true,
            residuals: vec![],
        }];
        checks.measurements_after_covariates = vec!["B03-bolted-2".into()];
        let est = Estimate {
            parameter: "k_rot_nm_per_rad".into(),
            scope: "population median".into(),
            median: 1.7063406448261371,
            q05: 1.6489953247826106,
            q95: 1.7510891006135292,
        };
        let refit = |m: Mechanism, failed: Option<&str>| Refit {
            mechanism: Some(m),
            joint: None,
            dir: format!("refits/{}", m.id()),
            log_evidence_runs: vec![1.0, 2.0],
            held_out: vec![],
            updated: vec![],
            estimates: if failed.is_none() {
                vec![est.clone()]
            } else {
                vec![]
            },
            failed: failed.map(str::to_string),
            ..Default::default()
        };
        let cand = |m: Mechanism| Candidate {
            mechanism: m,
            joint: None,
            joint_xy_m: None,
            covariate: None,
            point_xy_m: None,
            point_located: None,
            measurements: vec![],
            reason: "6 bolted mode(s) misfit while free-free fits".into(),
        };
        let favoured = verdict == Verdict::MechanismFound;
        let rot = Compared {
            refit: refit(Mechanism::JointRotation, None),
            log_bayes_factor: Some(868.6582312557075),
            log_bayes_factor_se: Some(1.8878265146718618),
            favoured,
            explains: true,
            practical: true,
            held_out_before_after: vec![(
                "bolted".into(),
                0.12947891045305393,
                0.07104580650339282,
            )],
            held_out_outliers_before_after: vec![],
        };
        let mass = Compared {
            refit: refit(
                Mechanism::JointMass,
                Some("sampler not converged: R-hat 1.2"),
            ),
            log_bayes_factor: None,
            log_bayes_factor_se: None,
            favoured: false,
            explains: true,
            practical: true,
            held_out_before_after: vec![],
            held_out_outliers_before_after: vec![],
        };
        DiagnosisDoc {
            verdict,
            located: LocatedSummary {
                any: true,
                above_practical_threshold: true,
                largest_mode_misfit: Some(("bolted plate-0-0".into(), 0.00367165366012717)),
                setups: vec!["bolted".into()],
                modes,
                measurements: vec!["B03-bolted-2".into()],
                shape_outliers: vec![],
                identification_outliers: vec![crate::diagnose::locate::IdentificationOutlier {
                    measurement_id: "M040".into(),
                    board_id: "PCB-01".into(),
                    setup: "bolted".into(),
                    label: "plate-2-2".into(),
                    centred_rel_residual: -7.978542433250206e-4,
                    z: -43.50835007946529,
                    p_value_other_modes: 0.9990234375,
                }],
                covariates,
                unpaired_clusters: clusters,
                never_seen: never,
                board_regions: vec![crate::diagnose::regions::BoardRegion {
                    amplitude_unit: "kg".into(),
                    ..crate::diagnose::regions::BoardRegion::located_fit(
                        Mechanism::AddedMass,
                        crate::diagnose::localize::LocalFit {
                            x_m: 0.056,
                            y_m: 0.030,
                            amplitude: 0.207e-3,
                            amplitude_se: 0.006e-3,
                            chi2_before: 1303.9,
                            chi2_after: 0.22,
                            dof_after: 1,
                            explained_share: 0.9998,
                            p_value: 2.3e-282,
                            region_radius_m: 0.054,
                            region_points: 40,
                            alternatives: vec![[0.024, 0.030, 1303.4]],
                            log_location_occam: -4.1,
                            location_ln_amplitude_sd: 0.02,
                            inflation: 1.0,
                            ..Default::default()
                        },
                        "A point mass.",
                    )
                }],
                board_regions_note: "point-mass localisation".into(),
            },
            findings: if favoured {
                vec![FindingDoc {
                    mechanism: Mechanism::JointRotation,
                    location: None,
                    covariate: None,
                    estimates: vec![est.clone()],
                    log_bayes_factor: rot.log_bayes_factor,
                    log_bayes_factor_se: rot.log_bayes_factor_se,
                    held_out_error: vec![HeldOut {
                        setup: "bolted".into(),
                        before_percent: 0.12947891045305393,
                        after_percent: 0.07104580650339282,
                    }],
                    held_out_error_outliers: vec![],
                    refit_dir: "refits/joint_rotation".into(),
                    sentence: "The bolted joints restrain the board's rotation.".into(),
                }]
            } else {
                vec![]
            },
            candidates: vec![
                CandidateDoc {
                    id: "joint_rotation".into(),
                    candidate: cand(Mechanism::JointRotation),
                    refit: Some(rot),
                    sentence: "rotation".into(),
                },
                CandidateDoc {
                    id: "joint_mass".into(),
                    candidate: cand(Mechanism::JointMass),
                    refit: Some(mass),
                    sentence: "mass".into(),
                },
                CandidateDoc {
                    id: "fixture_compliance".into(),
                    candidate: cand(Mechanism::FixtureCompliance),
                    refit: None,
                    sentence: "fixture".into(),
                },
            ],
            remaining_discrepancy:
                "located but not explained by any refitted mechanism: setups [\"bolted\"]".into(),
            options: DiagnoseOptions {
                work_dir: Default::default(),
                out: Default::default(),
                board: None,
                force: false,
                only: None,
                locate: lo,
                select: SelectOptions::default(),
                max_refits: 1,
            },
            checks,
            stage_findings: vec![],
        }
    }

    fn modes() -> Vec<ModeMisfit> {
        let m = |model: &str, label: &str, n: usize, r: f64, located: bool| ModeMisfit {
            model: model.into(),
            setup: "bolted".into(),
            label: label.into(),
            used_for_updating: label != "bending-x-2",
            n,
            mean_rel_residual: Some(r),
            located,
        };
        vec![
            ModeMisfit {
                setup: "free".into(),
                ..m("baseline", "torsion-1", 30, 1.5e-5, false)
            },
            m("baseline", "plate-0-0", 27, 0.00367165366012717, true),
            m("baseline", "plate-2-2", 27, -0.0007180620223115361, true),
            m("baseline", "bending-x-2", 27, 0.0001, false),
            m("joint_rotation", "plate-0-0", 27, 0.00021, false),
            m("joint_rotation", "plate-2-2", 27, -0.00012, false),
            m("joint_rotation", "bending-x-2", 26, 0.00005, false),
        ]
    }

    fn data(verdict: Verdict) -> DiagnosisData {
        let json = serde_json::to_string(&doc(verdict)).unwrap();
        DiagnosisData {
            doc: serde_json::from_str(&json).unwrap(),
            modes: Some(modes()),
        }
    }

    /// The `(data-col, data-value)` cells of every row of a table of the page.
    fn cells(html: &str, table: &str) -> Vec<BTreeMap<String, String>> {
        let start = html
            .find(&format!("data-table=\"{table}\""))
            .unwrap_or_else(|| panic!("table {table} in the page"));
        let body = &html[start..start + html[start..].find("</table>").unwrap()];
        body.split("<tr>")
            .skip(1)
            .filter_map(|row| {
                let mut m = BTreeMap::new();
                for part in row.split("data-col=\"").skip(1) {
                    let col = &part[..part.find('"').unwrap()];
                    let v = part.split("data-value=\"").nth(1).unwrap();
                    m.insert(col.to_string(), v[..v.find('"').unwrap()].to_string());
                }
                (!m.is_empty()).then_some(m)
            })
            .collect()
    }

    fn num(s: &str) -> f64 {
        s.parse()
            .unwrap_or_else(|_| panic!("{s:?} is not a number"))
    }

    fn page(d: Option<DiagnosisData>) -> crate::report::html::Rendered {
        render(&ReportData {
            diagnosis: d,
            ..Default::default()
        })
    }

    #[test]
    fn the_diagnosis_section_shows_the_verdict_and_the_source_numbers() {
        let src = doc(Verdict::MechanismFound);
        let r = page(Some(data(Verdict::MechanismFound)));
        let h = &r.html;
        assert!(h.contains("data-verdict=\"mechanism_found\""));
        assert!(
            h.contains("The bolted joints restrain the board&#39;s rotation")
                || h.contains("The bolted joints restrain the board's rotation")
        );
        assert!(r
            .markdown
            .contains("**Diagnosis — verdict `mechanism_found`:** Missing physics found"));
        assert!(!h.contains("Remaining discrepancy"));
        // Located modes: percent of the document's relative residuals.
        let lm = cells(h, "diagnosis_located_modes");
        assert_eq!(lm.len(), 2);
        for (row, m) in lm.iter().zip(&src.located.modes) {
            assert_eq!(row["label"], m.label);
            assert_eq!(
                num(&row["mean_rel_residual_pct"]),
                100.0 * m.mean_rel_residual
            );
            assert_eq!(row["reasons"], m.reasons.join(", "));
        }
        // Outliers with their check.
        let o = cells(h, "diagnosis_outliers");
        assert_eq!(o.len(), 1);
        assert_eq!(o[0]["measurement_id"], "B03-bolted-2");
        assert_eq!(num(&o[0]["chi2"]), 87.125);
        assert_eq!(num(&o[0]["q_value"]), 3.5e-8);
        assert_eq!(o[0]["n_modes"], "9");
        assert_eq!(o[0]["outlier_after_covariates"], "yes");
        let slip = cells(h, "diagnosis_identification_outliers");
        let want = &src.located.identification_outliers[0];
        assert_eq!(slip.len(), 1);
        assert_eq!(slip[0]["measurement_id"], "M040");
        assert_eq!(slip[0]["label"], "plate-2-2");
        assert_eq!(
            num(&slip[0]["centred_rel_residual_pct"]),
            100.0 * want.centred_rel_residual
        );
        assert_eq!(num(&slip[0]["z"]), want.z);
        assert_eq!(
            num(&slip[0]["p_value_other_modes"]),
            want.p_value_other_modes
        );
        let c = cells(h, "diagnosis_covariates");
        assert_eq!(num(&c[0]["q_value"]), 1.25e-4);
        assert_eq!(num(&c[0]["slope_rel_per_unit"]), -2.5e-4);
        let u = cells(h, "diagnosis_unpaired_clusters");
        assert_eq!(num(&u[0]["median_freq_hz"]), 1234.5);
        assert_eq!(num(&u[0]["min_freq_hz"]), 1230.25);
        assert_eq!(u[0]["n_measurements"], "6");
        let n = cells(h, "diagnosis_never_seen");
        assert_eq!(num(&n[0]["median_model_freq_hz"]), 3110.8496570560533);
        let g = cells(h, "diagnosis_board_regions");
        assert_eq!(g.len(), 1);
        assert!((num(&g[0]["x_mm"]) - 56.0).abs() < 1e-9, "{g:?}");
        assert!((num(&g[0]["amplitude"]) - 0.207).abs() < 1e-12, "{g:?}");
        assert_eq!(g[0]["amplitude_unit"], "g");
        assert_eq!(g[0]["alternatives"], "(24, 30)");
        assert_eq!(n[0]["n_missing"], "27");
        // Candidates: Bayes factor, held-out error, estimate, failure.
        let k = cells(h, "diagnosis_candidates");
        assert_eq!(k.len(), 3);
        assert_eq!(k[0]["id"], "joint_rotation");
        assert_eq!(num(&k[0]["log_bayes_factor"]), 868.6582312557075);
        assert_eq!(num(&k[0]["log_bayes_factor_se"]), 1.8878265146718618);
        assert_eq!(k[0]["favoured"], "yes");
        assert_eq!(num(&k[0]["held_out_before_pct"]), 0.12947891045305393);
        assert_eq!(num(&k[0]["held_out_after_pct"]), 0.07104580650339282);
        assert_eq!(k[0]["parameter"], "k_rot_nm_per_rad");
        assert_eq!(num(&k[0]["estimate_median"]), 1.7063406448261371);
        assert_eq!(num(&k[0]["estimate_q05"]), 1.6489953247826106);
        assert_eq!(num(&k[0]["estimate_q95"]), 1.7510891006135292);
        assert_eq!(k[1]["failed"], "sampler not converged: R-hat 1.2");
        assert_eq!(k[1]["log_bayes_factor"], "");
        assert_eq!(k[2]["refitted"], "no");
        assert_eq!(k[2]["screen_reason"], src.candidates[2].candidate.reason);
        // Before/after: the refit's modes with the baseline's, in percent.
        let ba = cells(h, "diagnosis_before_after");
        let ms = modes();
        assert_eq!(ba.len(), 3);
        for row in &ba {
            let find = |model: &str| {
                ms.iter()
                    .find(|m| m.model == model && m.label == row["label"])
                    .unwrap()
            };
            assert_eq!(row["model"], "joint_rotation");
            assert_eq!(
                num(&row["before_pct"]),
                100.0 * find("baseline").mean_rel_residual.unwrap()
            );
            assert_eq!(
                num(&row["after_pct"]),
                100.0 * find("joint_rotation").mean_rel_residual.unwrap()
            );
            assert_eq!(row["n_after"], find("joint_rotation").n.to_string());
            assert_eq!(row["located"] == "yes", find("baseline").located, "{row:?}");
        }
        // The figure: one bar pair per mode, axis with its unit.
        let sec = &h[h.find("<h2 id=\"diagnosis\"").unwrap()..];
        let sec = &sec[..sec[4..].find("<h2").unwrap()];
        assert_eq!(sec.matches("<figure class=\"plot\"").count(), 1);
        let fig = &sec[sec.find("<figure").unwrap()..];
        assert!(
            fig.contains("[%]") && fig.contains("plate-0-0 *") && fig.contains("joint_rotation")
        );
    }

    /// The report stage writes each row's cells under its spec's columns by position: every
    /// table has one header, one digit count and one cell per row for each column.
    #[test]
    fn every_table_has_a_cell_for_each_column_of_its_spec() {
        for verdict in [Verdict::MechanismFound, Verdict::UnexplainedMisfit] {
            let ts = tables(&data(verdict));
            let names: Vec<&str> = ts.iter().map(|t| t.spec.name).collect();
            let want: Vec<&str> = SECTIONS.iter().map(|s| s.name).collect();
            assert_eq!(names, want);
            for t in &ts {
                let n = t.spec.columns.len();
                assert_eq!((t.headers.len(), t.digits.len()), (n, n), "{}", t.spec.name);
                assert!(t.rows.iter().all(|r| r.len() == n), "{}", t.spec.name);
            }
        }
    }

    #[test]
    fn without_a_refit_or_a_diagnosis_the_section_says_so() {
        // Unexplained misfit: the remaining discrepancy is shown; no favoured candidate, the
        // before/after still compares with the first refit that gave a posterior.
        let r = page(Some(data(Verdict::UnexplainedMisfit)));
        assert!(r.html.contains("data-verdict=\"unexplained_misfit\""));
        assert!(r
            .html
            .contains("Remaining discrepancy:</strong> located but not explained"));
        assert!(r
            .markdown
            .contains("Remaining discrepancy: located but not explained"));
        // No per-mode table written by diagnose: said, not invented.
        let mut d = data(Verdict::MechanismFound);
        d.modes = None;
        let r = page(Some(d));
        assert!(r.html.contains("diagnosis_modes.parquet</code> is missing"));
        assert!(!r.html.contains("data-table=\"diagnosis_before_after\""));
        // No refit rows: the located modes, baseline only.
        let mut d = data(Verdict::UnexplainedMisfit);
        d.modes = Some(
            modes()
                .into_iter()
                .filter(|m| m.model == "baseline")
                .collect(),
        );
        let r = page(Some(d));
        let ba = cells(&r.html, "diagnosis_before_after");
        assert_eq!(ba.len(), 2);
        assert!(ba
            .iter()
            .all(|b| b["after_pct"].is_empty() && b["located"] == "yes"));
        // Empty evidence tables: one line each.
        let mut d = data(Verdict::NoMissingPhysics);
        d.doc.located = LocatedView::default();
        let r = page(Some(d));
        assert!(r
            .html
            .contains("<strong>Outlier measurements:</strong> none."));
        assert!(!r.html.contains("data-table=\"diagnosis_outliers\""));
        // Absent: one line.
        let r = page(None);
        assert!(r.html.contains("The diagnose stage has not run"));
        assert!(r.markdown.contains("the diagnose stage has not run"));
    }
}

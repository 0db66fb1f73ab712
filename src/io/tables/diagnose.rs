//! The spec, row types, reader and writer of diagnose's diagnosis and diagnosis_modes tables,
//! and the specs of the diagnosis section's tables the report stage writes
//! ([`crate::report::diagnosis::tables`] builds their rows).

use crate::diagnose::locate::ModeCheck;
use crate::diagnose::select::Verdict;
use crate::diagnose::verdict::{sentence, Row};
use crate::io::tables::{self, c, Col, TableSpec};
use arrow::array::{ArrayRef, BooleanArray, Float64Array, Int32Array, StringArray};
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;

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
    doc: "Outlier measurements of the diagnosis (diagnosis.json: located.measurements, with their check from checks.measurement_checks): the joint statistic over the measurement's modes and its BH q-value, and whether it stays an outlier once the located covariates are taken out.",
    open: false,
    columns: &[
        c("measurement_id", Col::Utf8, false, "", "Measurement."),
        c("board_id", Col::Utf8, true, "", "Board."),
        c("setup", Col::Utf8, true, "", "Setup."),
        c("n_modes", Col::Int32, true, "", "Modes in the statistic."),
        c("chi2", Col::Float64, true, "", "Sum of squared normal scores over the modes (~chi2(n_modes) when like the others)."),
        c("q_value", Col::Float64, true, "", "Benjamini–Hochberg q-value over all measurements."),
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

/// Every table spec of the report's diagnosis section (for `hbmu schemas`).
pub const SPECS: [&TableSpec; 9] = [
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

/// The spec of the section table `name` (a [`crate::report::diagnosis::Section`]'s name).
pub fn section_spec(name: &str) -> Option<&'static TableSpec> {
    SPECS.into_iter().find(|s| s.name == name)
}

/// One row of `diagnosis.parquet` (see [`DIAGNOSIS`]); the rank is the row's position.
#[derive(Clone, Debug, Default)]
pub struct DiagnosisRow {
    pub mechanism: String,
    pub joint: Option<i32>,
    pub covariate: Option<String>,
    pub screen_reason: String,
    pub refitted: bool,
    pub log_bayes_factor: Option<f64>,
    pub log_bayes_factor_se: Option<f64>,
    pub favoured: bool,
    pub held_out_bolted_error_before_percent: Option<f64>,
    pub held_out_bolted_error_after_percent: Option<f64>,
    pub parameter: Option<String>,
    pub estimate_median: Option<f64>,
    pub estimate_q05: Option<f64>,
    pub estimate_q95: Option<f64>,
    pub failed: Option<String>,
    pub sentence: String,
}

impl DiagnosisRow {
    /// The table's row of a diagnosis row (its first estimate, its held-out bolted error).
    pub fn of(r: &Row) -> Self {
        let est = r.first_estimate();
        DiagnosisRow {
            mechanism: r.cand.mechanism.id().to_string(),
            joint: r.cand.joint.map(|j| j as i32),
            covariate: r.cand.covariate.clone(),
            screen_reason: r.cand.reason.clone(),
            refitted: r.cmp.is_some(),
            log_bayes_factor: r.cmp.as_ref().and_then(|c| c.log_bayes_factor),
            log_bayes_factor_se: r.cmp.as_ref().and_then(|c| c.log_bayes_factor_se),
            favoured: r.cmp.as_ref().is_some_and(|c| c.favoured),
            held_out_bolted_error_before_percent: r.held_out_bolted(false),
            held_out_bolted_error_after_percent: r.held_out_bolted(true),
            parameter: est.as_ref().map(|e| e.parameter.clone()),
            estimate_median: est.as_ref().map(|e| e.median),
            estimate_q05: est.as_ref().map(|e| e.q05),
            estimate_q95: est.as_ref().map(|e| e.q95),
            failed: r.cmp.as_ref().and_then(|c| c.refit.failed.clone()),
            sentence: sentence(r),
        }
    }
}

/// Write `diagnosis.parquet` at `path`, the verdict in its metadata (`hbmu.verdict`).
pub fn write_diagnosis(
    path: &Path,
    rows: &[DiagnosisRow],
    verdict: &Verdict,
) -> anyhow::Result<()> {
    let f = |g: &dyn Fn(&DiagnosisRow) -> Option<f64>| -> ArrayRef {
        Arc::new(Float64Array::from(rows.iter().map(g).collect::<Vec<_>>()))
    };
    let cols: Vec<ArrayRef> = vec![
        Arc::new(Int32Array::from_iter_values(
            (1..=rows.len() as i32).collect::<Vec<_>>(),
        )),
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|r| r.mechanism.as_str()),
        )),
        Arc::new(Int32Array::from(
            rows.iter().map(|r| r.joint).collect::<Vec<_>>(),
        )),
        Arc::new(StringArray::from(
            rows.iter().map(|r| r.covariate.clone()).collect::<Vec<_>>(),
        )),
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|r| r.screen_reason.clone()),
        )),
        Arc::new(BooleanArray::from(
            rows.iter().map(|r| r.refitted).collect::<Vec<_>>(),
        )),
        f(&|r| r.log_bayes_factor),
        f(&|r| r.log_bayes_factor_se),
        Arc::new(BooleanArray::from(
            rows.iter().map(|r| r.favoured).collect::<Vec<_>>(),
        )),
        f(&|r| r.held_out_bolted_error_before_percent),
        f(&|r| r.held_out_bolted_error_after_percent),
        Arc::new(StringArray::from(
            rows.iter().map(|r| r.parameter.clone()).collect::<Vec<_>>(),
        )),
        f(&|r| r.estimate_median),
        f(&|r| r.estimate_q05),
        f(&|r| r.estimate_q95),
        Arc::new(StringArray::from(
            rows.iter().map(|r| r.failed.clone()).collect::<Vec<_>>(),
        )),
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|r| r.sentence.as_str()),
        )),
    ];
    let mut md = BTreeMap::new();
    md.insert("hbmu.verdict".to_string(), serde_json::to_string(verdict)?);
    let schema = DIAGNOSIS.schema(&[], &tables::table_metadata(&DIAGNOSIS, &md));
    tables::write_parquet(path, &tables::batch(schema, cols)?)?;
    Ok(())
}

/// One row of `diagnosis_modes.parquet` (see [`MODES`]): the model (`baseline` or a refit's
/// id), the mode's check, and whether the baseline located it.
pub type ModeRow = (String, ModeCheck, bool);

/// Write `diagnosis_modes.parquet` at `path` (undefined means and standard errors as null).
pub fn write_modes(path: &Path, mode_rows: &[ModeRow]) -> anyhow::Result<()> {
    let fin = |v: f64| v.is_finite().then_some(v);
    let cols: Vec<ArrayRef> = vec![
        Arc::new(StringArray::from_iter_values(
            mode_rows.iter().map(|(k, _, _)| k.as_str()),
        )),
        Arc::new(StringArray::from_iter_values(
            mode_rows.iter().map(|(_, m, _)| m.setup.as_str()),
        )),
        Arc::new(StringArray::from_iter_values(
            mode_rows.iter().map(|(_, m, _)| m.label.as_str()),
        )),
        Arc::new(BooleanArray::from(
            mode_rows
                .iter()
                .map(|(_, m, _)| m.used_for_updating)
                .collect::<Vec<_>>(),
        )),
        Arc::new(Int32Array::from_iter_values(
            mode_rows.iter().map(|(_, m, _)| m.n as i32),
        )),
        Arc::new(Int32Array::from_iter_values(
            mode_rows.iter().map(|(_, m, _)| m.n_boards as i32),
        )),
        Arc::new(Float64Array::from(
            mode_rows
                .iter()
                .map(|(_, m, _)| fin(m.mean_rel_residual))
                .collect::<Vec<_>>(),
        )),
        Arc::new(Float64Array::from(
            mode_rows
                .iter()
                .map(|(_, m, _)| fin(m.se_rel_residual))
                .collect::<Vec<_>>(),
        )),
        Arc::new(BooleanArray::from(
            mode_rows.iter().map(|(_, _, l)| *l).collect::<Vec<_>>(),
        )),
    ];
    let schema = MODES.schema(&[], &tables::table_metadata(&MODES, &BTreeMap::new()));
    tables::write_parquet(path, &tables::batch(schema, cols)?)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The report's section tables (the page's columns) are the tables written here, column
    /// for column.
    #[test]
    fn the_report_sections_are_these_specs() {
        let sections = crate::report::diagnosis::SECTIONS;
        assert_eq!(sections.len(), SPECS.len());
        for (sec, spec) in sections.iter().zip(SPECS) {
            assert_eq!(sec.name, spec.name);
            let names: Vec<&str> = spec.columns.iter().map(|c| c.name).collect();
            let want: Vec<&str> = sec.columns.iter().map(|c| c.name).collect();
            assert_eq!(names, want, "{}", spec.name);
            assert!(section_spec(sec.name).is_some());
        }
    }
}

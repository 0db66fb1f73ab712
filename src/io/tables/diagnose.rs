//! The spec, row types, reader and writer of diagnose's diagnosis and diagnosis_modes tables,
//! and, re-exported, the specs of the diagnosis section's tables the report stage writes
//! (owned by [`crate::report::diagnosis`], which builds their rows).

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
    doc: "Each mode's misfit before and after the candidates: per model (`baseline` = the work directory's update steps, or a refitted candidate's id) and (setup, label), the mean relative residual r = (f_measured − f̄_model)/f̄_model over the measurements (the mean of the board means with at least `min_boards_for_board_test` boards, as locate's mode check) with its standard error. The baseline rows are locate's mode checks; a refit's rows the same computation over the residuals.parquet of its directory (refits/<id>, or refits/<id>/screen for the every-joint candidate judged on its screen; its setups only). Failed refits have no rows.",
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

pub use crate::report::diagnosis::{
    BEFORE_AFTER, CANDIDATES, CLUSTERS, COVARIATES, IDENTIFICATION_OUTLIERS, LOCATED_MODES,
    NEVER_SEEN, OUTLIERS, REGIONS, SECTIONS as SPECS,
};

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

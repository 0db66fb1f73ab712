//! The diagnosis stage's inputs: the work directory's tables (and a refit's) read into the
//! plain data of [`crate::diagnose::locate`], [`crate::diagnose::regions`] and
//! [`crate::diagnose::select`].
//!
//! Required: `ingest/measurements.parquet`, `extract/modes.parquet`, `pair/pairs.parquet`
//! and the residuals of at least one update step. Optional (a [`Finding`] when absent):
//! either step's `residuals.parquet` and `population.parquet` (the ε draws). A table that
//! is there but lacks a column or has the wrong type is an error naming the file and column.
//!
//! Covariates are discovered from the measurement table's columns, not listed: every column
//! except the identifiers and the ingest's own bookkeeping ([`NOT_COVARIATES`]) is one;
//! float/integer columns are numeric (unit from the column's metadata), string columns are
//! categorical unless every non-empty value parses as a number (extra sheet columns are
//! written as strings). The date becomes two covariates: `date_days` (numeric, days since the
//! campaign's first measurement) and `date_day` (categorical, the calendar day).

use crate::diagnose::library::{is_board_mechanism, Mechanism};
use crate::diagnose::locate::{
    Covariate, CovariateValues, EpsDraws, IdentifiedMode, LocateInput, MeasurementInfo, PairObs,
    ResidualObs,
};
use crate::diagnose::regions::{MeasuredShape, RegionFiles};
use crate::diagnose::select::{setup_errors_of, Estimate, MeasurementError, Refit, SetupError};
use crate::diagnose::verdict::{quantile, r_hat_gate};
use crate::findings::{Finding, Findings, Severity};
use crate::io::modes_table::read_modes_table;
use crate::io::read_json;
use crate::io::tables::update::read_residuals;
use crate::io::tables::{self, read_parquet, Cols};
use crate::io::work_dir::{self, WorkDir};
use anyhow::{anyhow, bail, Context};
use arrow::array::{Array, AsArray};
use arrow::datatypes::{DataType, Float64Type, Int32Type, Int64Type};
use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

/// Columns of `measurements.parquet` that are not covariates: identifiers, free text, the
/// ingest's status and file summary, and the raw date columns (replaced by `date_days` and
/// `date_day`). `setup` is not a covariate because every test runs within a setup.
pub const NOT_COVARIATES: &[&str] = &[
    "measurement_id",
    "setup",
    "file",
    "notes",
    "sheet_line",
    "status",
    "status_reason",
    "function_type",
    "reference_node",
    "n_scan_points",
    "n_records",
    "n_coherence",
    "n_records_dropped",
    "freq_start_hz",
    "freq_step_hz",
    "n_lines",
    "uff_blake3",
    "date",
    "date_unix_ns",
];

/// The update steps, in order: directory under the work directory.
const STEPS: [&str; 2] = [work_dir::UPDATE_BOARDS, work_dir::UPDATE_JOINTS];

const NS_PER_DAY: f64 = 86_400e9;

/// Read a work directory into the input of [`crate::diagnose::locate::locate`].
pub fn read_inputs(work_dir: &Path) -> anyhow::Result<(LocateInput, Findings)> {
    let mut findings = Findings::default();
    let mut input = LocateInput::default();
    let wd = WorkDir::new(work_dir);
    read_measurements(&wd.measurements(), &mut input, &mut findings)?;
    input.identified = read_modes(&wd.modes())?;
    input.pairs = read_pairs(&wd.pairs())?;
    let known: BTreeSet<String> = input
        .measurements
        .iter()
        .map(|m| m.measurement_id.clone())
        .collect();
    for step in STEPS {
        let res = work_dir.join(step).join("residuals.parquet");
        if !res.is_file() {
            findings.push(Finding::new(
                Severity::Info,
                "diagnose.no_step",
                format!("no {step}/residuals.parquet: the step did not run (or failed); its setup is not checked"),
            ).file(format!("{step}/residuals.parquet")));
            continue;
        }
        let rows = read_residuals(&res)?;
        if rows.is_empty() {
            findings.push(
                Finding::new(
                    Severity::Warning,
                    "diagnose.empty_residuals",
                    "residuals.parquet has no rows: the step's setup is not checked",
                )
                .file(format!("{step}/residuals.parquet")),
            );
            continue;
        }
        let setups: BTreeSet<String> = rows.iter().map(|r| r.setup.clone()).collect();
        let unknown: BTreeSet<&str> = rows
            .iter()
            .filter(|r| !known.contains(&r.measurement_id))
            .map(|r| r.measurement_id.as_str())
            .collect();
        if !unknown.is_empty() {
            findings.push(
                Finding::new(
                    Severity::Warning,
                    "diagnose.unknown_measurement",
                    format!(
                        "residuals of measurements not ok in ingest/measurements.parquet: {}; kept in the mode checks, without covariates",
                        unknown.into_iter().collect::<Vec<_>>().join(", ")
                    ),
                )
                .file(format!("{step}/residuals.parquet")),
            );
        }
        let pop = work_dir.join(step).join("population.parquet");
        match (setups.len(), pop.is_file()) {
            (_, false) => findings.push(
                Finding::new(
                    Severity::Info,
                    "diagnose.no_population",
                    "no population.parquet: the prediction-error scales ε are not checked",
                )
                .file(format!("{step}/population.parquet")),
            ),
            (1, true) => {
                let setup = setups.iter().next().cloned().unwrap_or_default();
                input.eps.extend(read_eps(&pop, &setup)?);
            }
            (n, true) => findings.push(
                Finding::new(
                    Severity::Warning,
                    "diagnose.eps_setup_ambiguous",
                    format!("the step's residuals hold {n} setups: its ε draws cannot be assigned to one; not checked"),
                )
                .file(format!("{step}/population.parquet")),
            ),
        }
        input.residuals.extend(rows);
    }
    let joints = wd.update_joints().join("joints.parquet");
    if joints.is_file() {
        let (names, by_measurement, skipped) = read_unit_params(&joints)?;
        input.unit_param_names = names;
        input.unit_params = by_measurement;
        if !skipped.is_empty() {
            findings.push(
                Finding::new(
                    Severity::Info,
                    "diagnose.unit_param_skipped",
                    format!(
                        "column(s) {} hold a non-positive or non-finite value: no logarithm, so the covariate tests are not adjusted for them",
                        skipped.join(", ")
                    ),
                )
                .file(format!("{}/joints.parquet", work_dir::UPDATE_JOINTS)),
            );
        }
    }
    if input.residuals.is_empty() {
        bail!(
            "{}: no residuals of any update step (expected {} or {}): run `hbmu update boards` first",
            work_dir.display(),
            work_dir.join(STEPS[0]).join("residuals.parquet").display(),
            work_dir.join(STEPS[1]).join("residuals.parquet").display()
        );
    }
    Ok((input, findings))
}

fn unit_of(field: &arrow::datatypes::Field) -> String {
    field.metadata().get("unit").cloned().unwrap_or_default()
}

/// The measurement table: measurements with status `ok`, and the covariates.
fn read_measurements(
    path: &Path,
    input: &mut LocateInput,
    findings: &mut Findings,
) -> anyhow::Result<()> {
    let batches = tables::read_parquet(path)?;
    // Column name → (unit, kind) and the values in row order.
    let mut numeric: BTreeMap<String, (String, Vec<Option<f64>>)> = BTreeMap::new();
    let mut strings: BTreeMap<String, Vec<Option<String>>> = BTreeMap::new();
    let mut date_ns: Vec<Option<i64>> = vec![];
    let mut date_str: Vec<Option<String>> = vec![];
    let mut n_quarantined = 0;
    for b in &batches {
        let c = Cols { batch: b, path };
        let (mid, bid, setup, status) = (
            c.str("measurement_id")?,
            c.str("board_id")?,
            c.str("setup")?,
            c.str("status")?,
        );
        let ok: Vec<usize> = (0..b.num_rows())
            .filter(|&i| status.is_valid(i) && status.value(i) == "ok")
            .collect();
        n_quarantined += b.num_rows() - ok.len();
        for &i in &ok {
            input.measurements.push(MeasurementInfo {
                measurement_id: mid.value(i).to_string(),
                board_id: bid.value(i).to_string(),
                setup: setup.value(i).to_string(),
            });
        }
        let schema = b.schema();
        for (k, field) in schema.fields().iter().enumerate() {
            let name = field.name().as_str();
            let col = b.column(k);
            if name == "date_unix_ns" {
                let a = col.as_primitive_opt::<Int64Type>().with_context(|| {
                    format!(
                        "{}: column \"date_unix_ns\": expected int64",
                        path.display()
                    )
                })?;
                date_ns.extend(ok.iter().map(|&i| a.is_valid(i).then(|| a.value(i))));
                continue;
            }
            if name == "date" {
                let a = col.as_string_opt::<i32>().with_context(|| {
                    format!("{}: column \"date\": expected string", path.display())
                })?;
                date_str.extend(
                    ok.iter()
                        .map(|&i| a.is_valid(i).then(|| a.value(i).to_string())),
                );
                continue;
            }
            if NOT_COVARIATES.contains(&name) {
                continue;
            }
            let nums: Option<Vec<Option<f64>>> = match col.data_type() {
                DataType::Float64 => {
                    let a = col.as_primitive::<Float64Type>();
                    Some(
                        ok.iter()
                            .map(|&i| a.is_valid(i).then(|| a.value(i)))
                            .collect(),
                    )
                }
                DataType::Int64 => {
                    let a = col.as_primitive::<Int64Type>();
                    Some(
                        ok.iter()
                            .map(|&i| a.is_valid(i).then(|| a.value(i) as f64))
                            .collect(),
                    )
                }
                DataType::Int32 => {
                    let a = col.as_primitive::<Int32Type>();
                    Some(
                        ok.iter()
                            .map(|&i| a.is_valid(i).then(|| f64::from(a.value(i))))
                            .collect(),
                    )
                }
                DataType::Utf8 => {
                    let a = col.as_string::<i32>();
                    strings
                        .entry(name.to_string())
                        .or_default()
                        .extend(ok.iter().map(|&i| {
                            (a.is_valid(i) && !a.value(i).trim().is_empty())
                                .then(|| a.value(i).trim().to_string())
                        }));
                    None
                }
                DataType::Boolean => {
                    let a = col.as_boolean();
                    strings.entry(name.to_string()).or_default().extend(
                        ok.iter()
                            .map(|&i| a.is_valid(i).then(|| a.value(i).to_string())),
                    );
                    None
                }
                other => {
                    findings.push(
                        Finding::new(
                            Severity::Info,
                            "diagnose.covariate_type",
                            format!("column {name:?} of type {other} is not a covariate (expected a number or a string)"),
                        )
                        .file("ingest/measurements.parquet"),
                    );
                    None
                }
            };
            if let Some(v) = nums {
                numeric
                    .entry(name.to_string())
                    .or_insert_with(|| (unit_of(field), vec![]))
                    .1
                    .extend(v);
            }
        }
    }
    if n_quarantined > 0 {
        findings.push(
            Finding::new(
                Severity::Info,
                "diagnose.quarantined",
                format!("{n_quarantined} quarantined measurement(s) left out (no residuals)"),
            )
            .file("ingest/measurements.parquet"),
        );
    }
    let n = input.measurements.len();
    let mut covs = vec![];
    for (name, (unit, v)) in numeric {
        if v.len() == n {
            covs.push(Covariate {
                name,
                unit,
                values: CovariateValues::Numeric(v),
            });
        }
    }
    for (name, v) in strings {
        if v.len() != n {
            continue;
        }
        // Extra sheet columns arrive as strings: numeric when every value parses.
        let parsed: Vec<Option<f64>> = v
            .iter()
            .map(|s| s.as_deref().and_then(|s| s.parse::<f64>().ok()))
            .collect();
        let all_numeric = v.iter().any(Option::is_some)
            && v.iter()
                .zip(&parsed)
                .all(|(s, p)| s.is_none() || p.is_some());
        covs.push(Covariate {
            name,
            unit: String::new(),
            values: if all_numeric {
                CovariateValues::Numeric(parsed)
            } else {
                CovariateValues::Categorical(v)
            },
        });
    }
    if date_ns.len() == n && date_ns.iter().any(Option::is_some) {
        let t0 = date_ns.iter().flatten().min().copied().unwrap_or(0);
        covs.push(Covariate {
            name: "date_days".into(),
            unit: "d".into(),
            values: CovariateValues::Numeric(
                date_ns
                    .iter()
                    .map(|t| t.map(|t| (t - t0) as f64 / NS_PER_DAY))
                    .collect(),
            ),
        });
    }
    if date_str.len() == n && date_str.iter().any(Option::is_some) {
        covs.push(Covariate {
            name: "date_day".into(),
            unit: String::new(),
            values: CovariateValues::Categorical(
                date_str
                    .iter()
                    .map(|d| d.as_deref().map(|d| d.get(..10).unwrap_or(d).to_string()))
                    .collect(),
            ),
        });
    }
    input.covariates = covs;
    Ok(())
}

fn read_modes(path: &Path) -> anyhow::Result<Vec<IdentifiedMode>> {
    Ok(read_modes_table(path)?
        .into_iter()
        .map(|r| IdentifiedMode {
            measurement_id: r.measurement_id,
            setup: r.setup,
            mode: r.mode,
            freq_hz: r.freq_hz,
        })
        .collect())
}

fn read_pairs(path: &Path) -> anyhow::Result<Vec<PairObs>> {
    let mut out = vec![];
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let (mid, setup, label, mode, mf, acc, miss) = (
            c.str("measurement_id")?,
            c.str("setup")?,
            c.str("label")?,
            c.i32("mode")?,
            c.f64("model_freq_hz")?,
            c.bool("accepted")?,
            c.bool("missing")?,
        );
        for i in 0..b.num_rows() {
            out.push(PairObs {
                measurement_id: mid.value(i).to_string(),
                setup: setup.value(i).to_string(),
                label: label.value(i).to_string(),
                mode: mode.is_valid(i).then(|| mode.value(i)),
                model_freq_hz: mf.is_valid(i).then(|| mf.value(i)),
                accepted: acc.value(i),
                missing: miss.value(i),
            });
        }
    }
    Ok(out)
}

/// The `eps_<label>` columns of a population table.
fn read_eps(path: &Path, setup: &str) -> anyhow::Result<Vec<EpsDraws>> {
    let mut by: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let schema = b.schema();
        for field in schema.fields() {
            if let Some(label) = field.name().strip_prefix("eps_") {
                let a = c.f64(field.name())?;
                by.entry(label.to_string())
                    .or_default()
                    .extend(a.iter().flatten());
            }
        }
    }
    Ok(by
        .into_iter()
        .map(|(label, draws)| EpsDraws {
            setup: setup.to_string(),
            label,
            draws,
        })
        .collect())
}

/// Mean absolute relative error per setup of the held-out (`used == false`) or updated modes
/// in a residuals table.
pub fn setup_errors(path: &Path, used: bool) -> anyhow::Result<Vec<SetupError>> {
    Ok(setup_errors_of(&measurement_errors(path, used)?, |_| true))
}

/// [`setup_errors`]' terms per (setup, measurement).
pub fn measurement_errors(path: &Path, used: bool) -> anyhow::Result<Vec<MeasurementError>> {
    let mut acc: BTreeMap<(String, String), (f64, usize)> = BTreeMap::new();
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let (setup, mid, rel, u) = (
            c.str("setup")?,
            c.str("measurement_id")?,
            c.f64("rel_residual")?,
            c.bool("used_for_updating")?,
        );
        for i in 0..b.num_rows() {
            if u.value(i) == used && rel.value(i).is_finite() {
                let e = acc
                    .entry((setup.value(i).to_string(), mid.value(i).to_string()))
                    .or_default();
                e.0 += rel.value(i).abs();
                e.1 += 1;
            }
        }
    }
    Ok(acc
        .into_iter()
        .map(
            |((setup, measurement_id), (sum_abs_rel, n))| MeasurementError {
                setup,
                measurement_id,
                sum_abs_rel,
                n,
            },
        )
        .collect())
}

/// The log evidence of every run of an update directory (its evidence.json).
pub fn evidence_runs(dir: &Path) -> anyhow::Result<Vec<f64>> {
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

/// The population-level parameter (no board, no measurement) with the largest R-hat in a
/// summary table, with that R-hat; None without such rows or R-hats (one run).
pub fn population_r_hat(path: &Path) -> anyhow::Result<Option<(String, f64)>> {
    Ok(worst(
        &population_rows(path)?,
        |r| r.r_hat,
        |a, b| a > b,
        |_| true,
    ))
}

/// The physical 5/50/95 % quantiles of every population-level parameter of the summary table
/// at `path` that has finite ones (a step with a model-form discrepancy or a cut scale), by
/// name; empty without them.
pub fn physical_quantiles(path: &Path) -> anyhow::Result<BTreeMap<String, (f64, f64, f64)>> {
    let mut out = BTreeMap::new();
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let name = c.str("parameter")?;
        let (board, unit) = (c.str("board_id")?, c.str("measurement_id")?);
        let (Ok(a), Ok(m), Ok(z)) = (
            c.f64("physical_q05"),
            c.f64("physical_q50"),
            c.f64("physical_q95"),
        ) else {
            return Ok(out);
        };
        for i in 0..b.num_rows() {
            let v = |a: &arrow::array::Float64Array| (!a.is_null(i)).then(|| a.value(i));
            if let (true, Some(a), Some(m), Some(z)) =
                (board.is_null(i) && unit.is_null(i), v(a), v(m), v(z))
            {
                if a.is_finite() && z.is_finite() {
                    out.insert(name.value(i).to_string(), (a, m, z));
                }
            }
        }
    }
    Ok(out)
}

/// The parameters of the summary table at `baseline`, by name.
fn summary_parameters(baseline: &Path) -> anyhow::Result<std::collections::BTreeSet<String>> {
    let mut known = std::collections::BTreeSet::new();
    for b in tables::read_parquet(baseline)? {
        let c = Cols {
            batch: &b,
            path: baseline,
        };
        let name = c.str("parameter")?;
        known.extend((0..b.num_rows()).map(|i| name.value(i).to_string()));
    }
    Ok(known)
}

/// What a refit step's retry is decided on (`stage::diagnose::refit::retry_rule`), from its
/// summary table and its baseline's, each read once.
#[derive(Clone, Debug, PartialEq)]
pub struct RefitGates {
    /// The population-level parameter with the largest R-hat across runs.
    pub r_hat: Option<(String, f64)>,
    /// Of the population-level parameters the baseline lacks (a refit's own: the mechanism's
    /// location and scale), the one with the largest R-hat.
    pub own_r_hat: Option<(String, f64)>,
    /// Of the population locations (`mu_…`) the baseline lacks (the finding's estimates,
    /// `refit_estimates`), the one with the smallest bulk ESS. A refit's population scales
    /// (`sigma_…`) are nuisance parameters no finding reports; the runs' agreement on them is
    /// R-hat's to judge.
    pub own_ess: Option<(String, f64)>,
}

/// The [`RefitGates`] of the summary table at `path` against the one at `baseline`.
pub fn refit_gates(path: &Path, baseline: &Path) -> anyhow::Result<RefitGates> {
    let known = summary_parameters(baseline)?;
    let rows = population_rows(path)?;
    let gt = |a: f64, b: f64| a > b;
    Ok(RefitGates {
        r_hat: worst(&rows, |r| r.r_hat, gt, |_| true),
        own_r_hat: worst(&rows, |r| r.r_hat, gt, |n| !known.contains(n)),
        own_ess: worst(
            &rows,
            |r| r.ess_bulk,
            |a, b| a < b,
            |n| n.starts_with("mu_") && !known.contains(n),
        ),
    })
}

/// A population-level row (no board, no measurement) of a summary table.
struct PopulationRow {
    parameter: String,
    r_hat: f64,
    ess_bulk: f64,
}

/// The population-level rows of the summary table at `path`.
fn population_rows(path: &Path) -> anyhow::Result<Vec<PopulationRow>> {
    let mut out = vec![];
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let (name, board, meas, r_hat, ess) = (
            c.str("parameter")?,
            c.str("board_id")?,
            c.str("measurement_id")?,
            c.f64("r_hat")?,
            c.f64("ess_bulk")?,
        );
        use arrow::array::Array;
        out.extend(
            (0..b.num_rows())
                .filter(|&i| !board.is_valid(i) && !meas.is_valid(i))
                .map(|i| PopulationRow {
                    parameter: name.value(i).to_string(),
                    r_hat: r_hat.value(i),
                    ess_bulk: ess.value(i),
                }),
        );
    }
    Ok(out)
}

/// Of `rows` whose parameter `keep` accepts, the one whose finite `col` is worst by `worse`
/// (the first on a tie), with that value.
fn worst(
    rows: &[PopulationRow],
    col: impl Fn(&PopulationRow) -> f64,
    worse: impl Fn(f64, f64) -> bool,
    keep: impl Fn(&str) -> bool,
) -> Option<(String, f64)> {
    let mut out: Option<(String, f64)> = None;
    for r in rows {
        let v = col(r);
        if v.is_finite() && keep(&r.parameter) && out.as_ref().is_none_or(|(_, w)| worse(v, *w)) {
            out = Some((r.parameter.clone(), v));
        }
    }
    out
}

/// Measurement id → ln of its per-measurement parameters' posterior medians.
type UnitParams = BTreeMap<String, Vec<f64>>;

/// The per-measurement parameters of step 2's `joints.parquet` (every float64 column: the
/// contact stiffness, a refit's extra coordinates), as ln of each measurement's posterior
/// median, with their names (`ln <column>`). A column with a non-positive value is skipped
/// (it has no logarithm; the baseline's are stiffnesses) and returned by name.
fn read_unit_params(path: &Path) -> anyhow::Result<(Vec<String>, UnitParams, Vec<String>)> {
    let batches = tables::read_parquet(path)?;
    let Some(first) = batches.first() else {
        return Ok((vec![], BTreeMap::new(), vec![]));
    };
    let cols: Vec<String> = first
        .schema()
        .fields()
        .iter()
        .filter(|f| f.data_type() == &DataType::Float64)
        .map(|f| f.name().clone())
        .collect();
    // column → measurement → draws.
    let mut by: Vec<BTreeMap<String, Vec<f64>>> = vec![BTreeMap::new(); cols.len()];
    for b in &batches {
        let c = Cols { batch: b, path };
        let m = c.str("measurement_id")?;
        for (k, name) in cols.iter().enumerate() {
            let a = c.f64(name)?;
            for i in 0..b.num_rows() {
                by[k]
                    .entry(m.value(i).to_string())
                    .or_default()
                    .push(a.value(i));
            }
        }
    }
    let keep: Vec<usize> = (0..cols.len())
        .filter(|&k| by[k].values().flatten().all(|x| x.is_finite() && *x > 0.0))
        .collect();
    let mut out = UnitParams::new();
    for &k in &keep {
        for (m, v) in &mut by[k] {
            v.sort_by(f64::total_cmp);
            out.entry(m.clone())
                .or_default()
                .push(quantile(v, 0.5).ln());
        }
    }
    let names = keep.iter().map(|&k| format!("ln {}", cols[k])).collect();
    let skipped = (0..cols.len())
        .filter(|k| !keep.contains(k))
        .map(|k| cols[k].clone())
        .collect();
    Ok((names, out, skipped))
}

/// Every value of a Float64 column of a Parquet table, sorted.
pub fn sorted_column(path: &Path, col: &str) -> anyhow::Result<Vec<f64>> {
    let mut v = vec![];
    for b in &tables::read_parquet(path)? {
        let a = Cols { batch: b, path }.f64(col)?;
        v.extend((0..b.num_rows()).map(|i| a.value(i)));
    }
    v.sort_by(f64::total_cmp);
    Ok(v)
}

/// A refit's residuals: its step 2's and, for a board mechanism, its step 1's (`boards/`).
pub fn refit_residuals(dir: &Path) -> anyhow::Result<Vec<ResidualObs>> {
    let mut obs = vec![];
    for p in [
        dir.join("residuals.parquet"),
        dir.join("boards/residuals.parquet"),
    ] {
        if p.is_file() {
            obs.extend(read_residuals(&p)?);
        }
    }
    Ok(obs)
}

/// The updating's shape error δ per label of `label_index` (the median of population.parquet's
/// `delta_<label>`); a label the updating held out (no δ) takes the largest δ of the others,
/// the least weight. `None` when the updating had no shape terms.
pub fn shape_errors(
    path: &Path,
    label_index: &[(String, usize)],
) -> anyhow::Result<Option<Vec<f64>>> {
    let batches = read_parquet(path).with_context(|| format!("reading {}", path.display()))?;
    let mut out: Vec<Option<f64>> = vec![];
    for (label, _) in label_index {
        let col = format!("delta_{label}");
        let mut v = vec![];
        for b in &batches {
            let c = Cols { batch: b, path };
            if let Ok(a) = c.f64(&col) {
                v.extend(a.iter().flatten().filter(|x| x.is_finite() && *x > 0.0));
            }
        }
        v.sort_by(f64::total_cmp);
        out.push((!v.is_empty()).then(|| v[v.len() / 2]));
    }
    let Some(worst) = out.iter().flatten().copied().reduce(f64::max) else {
        return Ok(None);
    };
    Ok(Some(out.into_iter().map(|d| d.unwrap_or(worst)).collect()))
}

/// Whether the campaign's balance weighed at least one board (ingest/masses.parquet has a
/// row with a stable mass).
pub fn weighed(work: &Path) -> anyhow::Result<bool> {
    let path = WorkDir::new(work).masses();
    if !path.is_file() {
        return Ok(false);
    }
    Ok(read_parquet(&path)
        .with_context(|| format!("reading {}", path.display()))?
        .iter()
        .any(|b| b.num_rows() > 0))
}

/// Median over every row of `boards.parquet` of each parameter column.
pub fn posterior_centre(path: &Path, params: &[String]) -> anyhow::Result<Vec<f64>> {
    let mut cols: Vec<Vec<f64>> = vec![vec![]; params.len()];
    for b in read_parquet(path).with_context(|| format!("reading {}", path.display()))? {
        let c = Cols { batch: &b, path };
        for (k, name) in params.iter().enumerate() {
            cols[k].extend(c.f64(name)?.iter().flatten());
        }
    }
    cols.into_iter()
        .zip(params)
        .map(|(mut v, name)| {
            v.retain(|x| x.is_finite());
            if v.is_empty() {
                return Err(anyhow!("{}: no finite {name}", path.display()));
            }
            v.sort_by(f64::total_cmp);
            let n = v.len();
            Ok(if n % 2 == 1 {
                v[n / 2]
            } else {
                0.5 * (v[n / 2 - 1] + v[n / 2])
            })
        })
        .collect()
}

/// The work directory's tables the board-region localisations read
/// ([`crate::diagnose::regions::RegionFiles`]).
pub struct WorkDirRegions<'a> {
    pub work: &'a Path,
}

impl RegionFiles for WorkDirRegions<'_> {
    fn posterior_centre(&self, params: &[String]) -> anyhow::Result<Vec<f64>> {
        let boards = WorkDir::new(self.work)
            .update_boards()
            .join("boards.parquet");
        posterior_centre(&boards, params)
    }

    fn weighed(&self) -> anyhow::Result<bool> {
        weighed(self.work)
    }

    fn shape_errors(&self, label_index: &[(String, usize)]) -> anyhow::Result<Option<Vec<f64>>> {
        let population = WorkDir::new(self.work)
            .update_boards()
            .join("population.parquet");
        shape_errors(&population, label_index)
    }

    fn measured_shapes(
        &self,
        wanted: &dyn Fn(&str, i32) -> bool,
    ) -> anyhow::Result<Vec<MeasuredShape>> {
        measured_shapes(&WorkDir::new(self.work).modes(), wanted)
    }
}

/// The shapes and scan points of the rows of a modes table that `wanted` accepts (by
/// measurement and mode), in file order.
pub fn measured_shapes(
    modes_path: &Path,
    wanted: &dyn Fn(&str, i32) -> bool,
) -> anyhow::Result<Vec<MeasuredShape>> {
    let mut out = vec![];
    for b in
        read_parquet(modes_path).with_context(|| format!("reading {}", modes_path.display()))?
    {
        let c = Cols {
            batch: &b,
            path: modes_path,
        };
        let (mid, mode) = (c.str("measurement_id")?, c.i32("mode")?);
        for i in 0..b.num_rows() {
            if !wanted(mid.value(i), mode.value(i)) {
                continue;
            }
            out.push(MeasuredShape {
                measurement_id: mid.value(i).to_string(),
                mode: mode.value(i),
                shape: c.list_f64("shape", i)?.unwrap_or_default(),
                x_m: c.list_f64("x_m", i)?.unwrap_or_default(),
                y_m: c.list_f64("y_m", i)?.unwrap_or_default(),
            });
        }
    }
    Ok(out)
}

/// The every-joint refit's `joints.parquet` in `dir`: per measurement, each of the `n`
/// joints' k_ratio_<j> draws.
pub fn joint_ratios(dir: &Path, n: usize) -> anyhow::Result<BTreeMap<String, Vec<Vec<f64>>>> {
    let jp = dir.join("joints.parquet");
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
    Ok(by)
}

/// The parameter estimates of a refit directory: a point mass's added mass and a
/// covariate's coefficient from its step 1 (`boards/`), a joint mechanism's extra
/// coordinates from step 2 (population medians), and a per-joint stiffness's estimate in
/// each outlier measurement.
fn refit_estimates(
    dir: &Path,
    mechanism: Option<Mechanism>,
    joint: Option<usize>,
    outliers: &[String],
) -> anyhow::Result<Vec<Estimate>> {
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
        let physical = physical_quantiles(&dir.join("summary.parquet"))?;
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
            // With a model-form discrepancy in the refit, the physical value: the draws less
            // the discrepancy's part the coordinate absorbs (summary's physical quantiles).
            if let Some(&(q05, q50, q95)) = physical.get(&col) {
                estimates.push(Estimate {
                    parameter: param.to_string(),
                    scope: "population median, physical (less the model-form discrepancy's part the fit absorbs)".into(),
                    median: q50.exp(),
                    q05: q05.exp(),
                    q95: q95.exp(),
                });
            } else if !v.is_empty() {
                estimates.push(Estimate {
                    parameter: param.to_string(),
                    scope: "population median".into(),
                    median: quantile(&v, 0.5),
                    q05: quantile(&v, 0.05),
                    q95: quantile(&v, 0.95),
                });
            }
        }
        if mechanism == Some(Mechanism::JointStiffnessPerJoint) && !every_joint {
            estimates.extend(per_measurement_estimates(dir, &coords, outliers)?);
        }
    }
    Ok(estimates)
}

/// A mechanism that acts on some measurements only (one joint loose in some
/// assemblies): its estimate in each outlier measurement the locate step found
/// (joints.parquet holds report_ref · e^x per measurement). Not every measurement
/// whose interval excludes the reference: the joints of one assembly differ by a few
/// per cent anyway, and the bolted data resolve that.
fn per_measurement_estimates(
    dir: &Path,
    coords: &[serde_json::Value],
    outliers: &[String],
) -> anyhow::Result<Vec<Estimate>> {
    let mut estimates = vec![];
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
    Ok(estimates)
}

/// Where a refit's (or a baseline step's) tables lie and what it refitted.
#[derive(Clone, Copy, Debug)]
pub struct RefitSource<'a> {
    pub dir: &'a Path,
    /// `dir` as the diagnosis names it (relative to the diagnosis directory).
    pub rel_dir: &'a str,
    pub mechanism: Option<Mechanism>,
    /// The joint (1-based) of a per-joint candidate.
    pub joint: Option<usize>,
}

/// A refit directory (or a baseline step) as a [`Refit`]. A board mechanism's refit has
/// its step 1 in `dir/boards` and, where the campaign has a step 2, its step 2 in `dir`:
/// its log evidence per run is then Z₂′ + (Z₁′ − Z₁), `step1_baseline` = the baseline's Z₁
/// per run, so that it compares with the baseline's step 2 (Z₂) as a joint refit does (whose
/// step 1 is the baseline's): every Bayes factor is over the same data, both steps.
/// `max_r_hat` is the updating's convergence level ([`r_hat_gate`]).
pub fn read_refit(
    src: RefitSource<'_>,
    step1_baseline: Option<&[f64]>,
    outliers: &[String],
    max_r_hat: f64,
) -> anyhow::Result<Refit> {
    let RefitSource {
        dir,
        rel_dir,
        mechanism,
        joint,
    } = src;
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
            let (f, n) = r_hat_gate(population_r_hat(&d.join("summary.parquet"))?, &d, max_r_hat);
            failed = failed.or(f);
            convergence_note = convergence_note.or(n);
        }
    }
    let mut estimates = refit_estimates(dir, mechanism, joint, outliers)?;
    if let Some(note) = &convergence_note {
        for e in estimates.iter_mut() {
            e.scope = format!("{}; {note}", e.scope);
        }
    }
    let mut held_out_by_measurement = measurement_errors(&res, false)?;
    let mut updated = setup_errors(&res, true)?;
    if board_mech && has2 {
        // The free-free predictions of its step 1 too.
        let res1 = dir1.join("residuals.parquet");
        held_out_by_measurement.extend(measurement_errors(&res1, false)?);
        updated.extend(setup_errors(&res1, true)?);
    }
    let held_out = setup_errors_of(&held_out_by_measurement, |_| true);
    Ok(Refit {
        mechanism,
        joint,
        dir: rel_dir.to_string(),
        log_evidence_runs,
        held_out,
        held_out_by_measurement,
        outliers: outliers.to_vec(),
        updated,
        estimates,
        failed,
        ..Default::default()
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The refit's gates read its own population-level parameters: the ESS gate its
    /// locations only (the finding's estimates), the own R-hat its locations and scales. A
    /// parameter the baseline has too (however low its ESS or high its R-hat) and per-board
    /// rows are not them; the whole R-hat reads every population-level row.
    #[test]
    fn the_refit_gates_read_the_parameters_the_baseline_lacks() {
        use crate::update::posterior::SummaryRow;
        let row = |p: &str, board: Option<&str>, ess: f64, r_hat: f64| SummaryRow {
            parameter: p.into(),
            board_id: board.map(String::from),
            measurement_id: None,
            s: crate::bayes::diagnostics::Summary {
                mean: 0.0,
                sd: 1.0,
                q05: -1.6,
                q50: 0.0,
                q95: 1.6,
                r_hat,
                ess_bulk: ess,
                ess_tail: ess,
            },
            physical: None,
        };
        let d = tempfile::tempdir().unwrap();
        let (base, refit) = (
            d.path().join("base.parquet"),
            d.path().join("refit.parquet"),
        );
        let prov = Default::default();
        tables::update::write_summary(&base, &[row("mu_g_z_pa", None, 300.0, 1.0)], &prov).unwrap();
        let rows = [
            row("mu_g_z_pa", None, 81.0, 1.08),
            row("temperature_coefficient_per_k", Some("PCB-01"), 20.0, 1.3),
            row("mu_temperature_coefficient_per_k", None, 150.0, 1.02),
            row("sigma_temperature_coefficient_per_k", None, 65.0, 1.04),
        ];
        tables::update::write_summary(&refit, &rows, &prov).unwrap();
        let gates = refit_gates(&refit, &base).unwrap();
        assert_eq!(
            gates.own_ess,
            Some(("mu_temperature_coefficient_per_k".to_string(), 150.0))
        );
        assert_eq!(gates.r_hat, Some(("mu_g_z_pa".to_string(), 1.08)));
        assert_eq!(gates.r_hat, population_r_hat(&refit).unwrap());
        assert_eq!(
            gates.own_r_hat,
            Some(("sigma_temperature_coefficient_per_k".to_string(), 1.04))
        );
        let missing = d.path().join("none.parquet");
        assert!(refit_gates(&refit, &missing).is_err());
    }

    /// The demo work directory (when `make -C pipelines demo` has run) reads without error,
    /// with both steps, ε of every updated label and the sheet's covariates.
    #[test]
    fn reads_the_demo_work_directory_when_present() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("target/work/paper");
        if !dir.join("update_joints/residuals.parquet").is_file() {
            eprintln!("skipped: no demo work directory at {}", dir.display());
            return;
        }
        let (inp, findings) = read_inputs(&dir).unwrap();
        assert!(findings.count(Severity::Warning) == 0, "{findings:?}");
        let setups: BTreeSet<&str> = inp.residuals.iter().map(|r| r.setup.as_str()).collect();
        assert_eq!(setups, BTreeSet::from(["bolted", "free"]));
        let names: BTreeSet<&str> = inp.covariates.iter().map(|c| c.name.as_str()).collect();
        for want in [
            "temperature_c",
            "torque_nm",
            "operator",
            "bolt_set",
            "board_id",
            "date_days",
            "date_day",
        ] {
            assert!(names.contains(want), "{want} not in {names:?}");
        }
        assert!(!names.contains("notes") && !names.contains("measurement_id"));
        // Every updated label of both steps has its ε draws.
        for r in inp.residuals.iter().filter(|r| r.used_for_updating) {
            assert!(inp
                .eps
                .iter()
                .any(|e| e.setup == r.setup && e.label == r.label && !e.draws.is_empty()));
        }
    }

    /// A copy of the demo's tables without step 2 (None when the demo has not run).
    fn demo_copy_without_step_2() -> Option<tempfile::TempDir> {
        let demo = Path::new(env!("CARGO_MANIFEST_DIR")).join("target/work/paper");
        let files = [
            "ingest/measurements.parquet",
            "extract/modes.parquet",
            "pair/pairs.parquet",
            "update_boards/residuals.parquet",
            "update_boards/population.parquet",
        ];
        if !files.iter().all(|f| demo.join(f).is_file()) {
            eprintln!("skipped: no demo work directory at {}", demo.display());
            return None;
        }
        let tmp = tempfile::tempdir().unwrap();
        for f in files {
            let to = tmp.path().join(f);
            std::fs::create_dir_all(to.parent().unwrap()).unwrap();
            std::fs::copy(demo.join(f), to).unwrap();
        }
        Some(tmp)
    }

    #[test]
    fn a_missing_step_is_a_finding_and_a_bad_table_an_error_naming_file_and_column() {
        let Some(tmp) = demo_copy_without_step_2() else {
            return;
        };
        let (inp, findings) = read_inputs(tmp.path()).unwrap();
        assert!(
            findings.iter().any(|f| f.code == "diagnose.no_step"
                && f.file.as_deref() == Some("update_joints/residuals.parquet")),
            "{findings:?}"
        );
        assert!(inp.residuals.iter().all(|r| r.setup == "free"));
        assert!(inp.eps.iter().all(|e| e.setup == "free") && !inp.eps.is_empty());
        // No population table: a finding, ε not checked.
        std::fs::remove_file(tmp.path().join("update_boards/population.parquet")).unwrap();
        let (inp, findings) = read_inputs(tmp.path()).unwrap();
        assert!(inp.eps.is_empty());
        assert!(findings.iter().any(|f| f.code == "diagnose.no_population"));
        // A table without the expected columns: the error names the file and the column.
        std::fs::copy(
            tmp.path().join("pair/pairs.parquet"),
            tmp.path().join("update_boards/residuals.parquet"),
        )
        .unwrap();
        let e = format!("{:#}", read_inputs(tmp.path()).unwrap_err());
        assert!(
            e.contains("update_boards/residuals.parquet") && e.contains("model_freq_hz_mean"),
            "{e}"
        );
        // No residuals of any step: an error saying what to run.
        std::fs::remove_file(tmp.path().join("update_boards/residuals.parquet")).unwrap();
        let e = format!("{:#}", read_inputs(tmp.path()).unwrap_err());
        assert!(
            e.contains("no residuals") && e.contains("hbmu update boards"),
            "{e}"
        );
    }

    #[test]
    fn unit_parameters_are_the_ln_median_and_a_column_without_a_logarithm_is_named() {
        use arrow::array::{Float64Array, StringArray};
        use arrow::datatypes::{Field, Schema};
        use arrow::record_batch::RecordBatch;
        use std::sync::Arc;
        let tmp = tempfile::tempdir().unwrap();
        let p = tmp.path().join("joints.parquet");
        let schema = Arc::new(Schema::new(vec![
            Field::new("measurement_id", DataType::Utf8, false),
            Field::new("k_con_n_per_m", DataType::Float64, false),
            Field::new("shift", DataType::Float64, false),
        ]));
        let b = RecordBatch::try_new(
            schema,
            vec![
                Arc::new(StringArray::from(vec!["M1", "M1", "M1", "M2"])),
                Arc::new(Float64Array::from(vec![1e6, 4e6, 2e6, 3e6])),
                Arc::new(Float64Array::from(vec![0.1, -0.2, 0.3, 0.0])),
            ],
        )
        .unwrap();
        tables::write_parquet(&p, &b).unwrap();
        let (names, by, skipped) = read_unit_params(&p).unwrap();
        assert_eq!(names, ["ln k_con_n_per_m"]);
        assert_eq!(skipped, ["shift"]);
        assert!((by["M1"][0] - 2e6f64.ln()).abs() < 1e-12);
        assert!((by["M2"][0] - 3e6f64.ln()).abs() < 1e-12);
    }

    #[test]
    fn a_missing_work_directory_names_the_file() {
        let e = read_inputs(Path::new("/nonexistent/work")).unwrap_err();
        assert!(format!("{e:#}").contains("measurements.parquet"), "{e:#}");
    }
}

//! The diagnosis stage's inputs: the work directory's tables read into the plain data of
//! [`crate::diagnose::locate`].
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

use crate::diagnose::locate::{
    Covariate, CovariateValues, EpsDraws, IdentifiedMode, LocateInput, MeasurementInfo, PairObs,
    ResidualObs,
};
use crate::findings::{Finding, Findings, Severity};
use crate::io::modes_table::read_modes_table;
use crate::io::tables::{self, Cols};
use anyhow::{bail, Context};
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
const STEPS: [&str; 2] = ["update_boards", "update_joints"];

const NS_PER_DAY: f64 = 86_400e9;

/// Read a work directory into the input of [`crate::diagnose::locate::locate`].
pub fn read_inputs(work_dir: &Path) -> anyhow::Result<(LocateInput, Findings)> {
    let mut findings = Findings::default();
    let mut input = LocateInput::default();
    let meas_path = work_dir.join("ingest/measurements.parquet");
    read_measurements(&meas_path, &mut input, &mut findings)?;
    input.identified = read_modes(&work_dir.join("extract/modes.parquet"))?;
    input.pairs = read_pairs(&work_dir.join("pair/pairs.parquet"))?;
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

pub(crate) fn read_residuals(path: &Path) -> anyhow::Result<Vec<ResidualObs>> {
    let mut out = vec![];
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let (mid, bid, setup, label, f, fm, psd, rel, z, used) = (
            c.str("measurement_id")?,
            c.str("board_id")?,
            c.str("setup")?,
            c.str("label")?,
            c.f64("freq_hz")?,
            c.f64("model_freq_hz_mean")?,
            c.f64("predictive_sd_hz")?,
            c.f64("rel_residual")?,
            c.f64("std_residual")?,
            c.bool("used_for_updating")?,
        );
        for i in 0..b.num_rows() {
            out.push(ResidualObs {
                measurement_id: mid.value(i).to_string(),
                board_id: bid.value(i).to_string(),
                setup: setup.value(i).to_string(),
                label: label.value(i).to_string(),
                freq_hz: f.value(i),
                model_freq_hz_mean: fm.value(i),
                predictive_sd_hz: psd.value(i),
                rel_residual: rel.value(i),
                std_residual: z.value(i),
                used_for_updating: used.value(i),
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

#[cfg(test)]
mod tests {
    use super::*;

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
    fn a_missing_work_directory_names_the_file() {
        let e = read_inputs(Path::new("/nonexistent/work")).unwrap_err();
        assert!(format!("{e:#}").contains("measurements.parquet"), "{e:#}");
    }
}

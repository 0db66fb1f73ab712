//! The spec, row types, reader and writer of report's table2 and intervals tables (Parquet
//! and CSV), and the report's readers of the other stages' outputs: the measured frequencies
//! (residuals, held-out boards' pairs), specimens, an update step's draws, summaries and
//! tempering paths, the diagnosis, and the plots to copy.

use crate::io::read_json;
use crate::io::tables::{self, c, Col, Cols, TableSpec};
use crate::io::work_dir::{self, WorkDir};
use crate::report::diagnosis::{self, Cell, DiagnosisData, DiagnosisView, ModeMisfit};
use crate::report::html::{Provenance, StepData, SummaryRow};
use crate::report::sources;
use crate::report::validation::{Interval, Measured, Table2Row};
use anyhow::{anyhow, bail, Context};
use arrow::array::{Array, ArrayRef, BooleanArray, Float64Array, Int32Array, StringArray};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

pub const TABLE2: TableSpec = TableSpec {
    name: "table2",
    doc: "The Table-2 analog of the validation report: per setup and mode, the measured mean and standard deviation over every measurement of every board (each board weighted equally) against the prediction for a new board (model mean and sd, predictive sd with the prediction error), their relative errors, and the coverage of the predicted 90 % intervals. Null where undefined (fewer than two measurements).",
    open: false,
    columns: &[
        c("setup", Col::Utf8, false, "", "`free` or `bolted`."),
        c("label", Col::Utf8, false, "", "Mode label."),
        c("role", Col::Utf8, false, "", "`updating` or `validation` (not used for updating)."),
        c("n_measured", Col::Int32, false, "", "Measurements of the mode (all boards)."),
        c("n_boards", Col::Int32, false, "", "Boards behind n_measured."),
        c("measured_mean_hz", Col::Float64, true, "Hz", "Mean of the measured frequencies, every board weighted equally (a measurement of a board measured n_b times weighs 1 / (n_b n_boards)): the mean of a measurement of a board picked at random, which the new-board prediction stands for."),
        c("measured_sd_hz", Col::Float64, true, "Hz", "Standard deviation of the measured frequencies with the same weights w (reliability-weighted: sum w (f - mean)^2 / (1 - sum w^2)); the sample sd when every board has as many measurements."),
        c("simulated_mean_hz", Col::Float64, true, "Hz", "Mean model frequency of a new board."),
        c("simulated_sd_hz", Col::Float64, true, "Hz", "Standard deviation of the model frequency of a new board."),
        c("predictive_sd_hz", Col::Float64, true, "Hz", "Standard deviation of a predicted measurement of a new board."),
        c("discrepancy_mean_pct", Col::Float64, true, "%", "Model-form discrepancy of a new board's predicted measurement (predictions.parquet discrepancy_rel, in % of the frequency): its mean over the draws, 0 where the updating ran without one. Beside simulated_sd_hz (the parameters' spread), the model's own error."),
        c("discrepancy_sd_pct", Col::Float64, true, "%", "Standard deviation of that discrepancy over the draws (its posterior spread; for a validation mode, its prior at the inferred scale)."),
        c("mean_error_with_discrepancy_pct", Col::Float64, true, "%", "(simulated mean with the discrepancy - measured mean) / measured mean."),
        c("mean_error_pct", Col::Float64, true, "%", "(simulated mean - measured mean) / measured mean."),
        c("sd_error_pct", Col::Float64, true, "%", "(predictive sd - measured sd) / measured sd."),
        c("board_coverage_90", Col::Float64, true, "", "Fraction of the measurements inside their own board's predicted 90 % interval."),
        c("new_board_coverage_90", Col::Float64, true, "", "Fraction of the measurements inside the new board's predicted 90 % interval."),
        c("n_held_out", Col::Int32, false, "", "Measurements of the mode on boards held out of the updating (`update boards --hold-out`); not in n_measured or the measured mean and sd."),
        c("held_out_coverage_90", Col::Float64, true, "", "Fraction of the held-out boards' measurements inside the new board's predicted 90 % interval (the out-of-sample test); null without held-out boards."),
    ],
};

pub const INTERVALS: TableSpec = TableSpec {
    name: "intervals",
    doc: "Predicted distributions of the validation report (the Figure-6 analog's boxes): per scope (`board`, `new_board`), board, setup and mode, the model frequency's mean and sd and the quantiles of a predicted measurement (numpy's default linear interpolation), with the measurements compared (the board's own; every updated board's for a new board, and apart the held-out boards') and how many lie in [q05, q95].",
    open: false,
    columns: &[
        c("scope", Col::Utf8, false, "", "`board` or `new_board`."),
        c("board_id", Col::Utf8, true, "", "Board; null for a new board."),
        c("setup", Col::Utf8, false, "", "`free` or `bolted`."),
        c("label", Col::Utf8, false, "", "Mode label."),
        c("role", Col::Utf8, false, "", "`updating` or `validation`."),
        c("n_draws", Col::Int32, false, "", "Predictions behind the interval."),
        c("model_mean_hz", Col::Float64, true, "Hz", "Mean model frequency."),
        c("model_sd_hz", Col::Float64, true, "Hz", "Standard deviation of the model frequency."),
        c("q05_hz", Col::Float64, true, "Hz", "5 % quantile of a predicted measurement."),
        c("q25_hz", Col::Float64, true, "Hz", "25 % quantile."),
        c("q50_hz", Col::Float64, true, "Hz", "Median."),
        c("q75_hz", Col::Float64, true, "Hz", "75 % quantile."),
        c("q95_hz", Col::Float64, true, "Hz", "95 % quantile."),
        c("n_measured", Col::Int32, false, "", "Measurements compared."),
        c("n_inside_90", Col::Int32, false, "", "Measurements inside [q05, q95]."),
        c("n_held_out", Col::Int32, false, "", "Measurements held out of the updating: for a new board, those of the held-out boards (`update boards --hold-out`); for a measured board, its own held-out measurements (`--hold-out-measurements`)."),
        c("n_held_out_inside_90", Col::Int32, false, "", "Held-out measurements inside [q05, q95]."),
    ],
};

/// The measured frequencies of an update step's residuals.parquet.
pub fn read_measured(path: &Path) -> anyhow::Result<Vec<Measured>> {
    let mut out = vec![];
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let (m, bid, st, l, f, u) = (
            c.str("measurement_id")?,
            c.str("board_id")?,
            c.str("setup")?,
            c.str("label")?,
            c.f64("freq_hz")?,
            c.bool("used_for_updating")?,
        );
        for i in 0..b.num_rows() {
            out.push(Measured {
                measurement_id: m.value(i).into(),
                board_id: bid.value(i).into(),
                setup: st.value(i).into(),
                label: l.value(i).into(),
                freq_hz: f.value(i),
                used_for_updating: u.value(i),
                held_out: false,
                board_updated: true,
            });
        }
    }
    Ok(out)
}

/// The boards' measured dimensions from ingest's specimens.parquet, when any board has one.
pub fn read_specimens(path: &Path) -> anyhow::Result<Vec<(String, [Option<f64>; 3])>> {
    let mut out = vec![];
    if !path.is_file() {
        return Ok(out);
    }
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let bid = c.str("board_id")?;
        let cols = [
            c.f64("length_mm")?,
            c.f64("width_mm")?,
            c.f64("thickness_mm")?,
        ];
        for r in 0..b.num_rows() {
            let dims = cols.map(|a| a.is_valid(r).then(|| a.value(r)));
            out.push((bid.value(r).to_string(), dims));
        }
    }
    if out.iter().all(|(_, d)| d.iter().all(Option::is_none)) {
        out.clear();
    }
    Ok(out)
}

/// The measured frequencies step 1 held out: the accepted pairs (read as the updating reads
/// them) of the held-out boards (both setups) and of the held-out measurements of updated
/// boards, each mode's role taken from the updated boards' residuals.
pub fn read_held_out(
    pairs: &Path,
    (boards, measurements): (&[String], &[String]),
    roles: &BTreeMap<(String, String), bool>,
) -> anyhow::Result<Vec<Measured>> {
    let mut out = vec![];
    for p in crate::io::tables::pairs::read_pairs(pairs)? {
        let board_held = boards.contains(&p.board_id);
        let measurement_held = p.setup == "free" && measurements.contains(&p.measurement_id);
        if !(board_held || measurement_held) {
            continue;
        }
        let key = (p.setup, p.label);
        let Some(used) = roles.get(&key) else {
            continue; // a mode the updated boards' residuals do not have: nothing predicts it
        };
        out.push(Measured {
            measurement_id: p.measurement_id,
            board_id: p.board_id,
            setup: key.0,
            label: key.1,
            freq_hz: p.freq_hz,
            used_for_updating: *used,
            held_out: true,
            board_updated: !board_held,
        });
    }
    Ok(out)
}

/// Float columns of a draws table except the given keys, in file order.
fn float_columns(path: &Path, skip: &[&str]) -> anyhow::Result<Vec<(String, Vec<f64>)>> {
    let mut cols: Vec<(String, Vec<f64>)> = vec![];
    for b in tables::read_parquet(path)? {
        for (k, f) in b.schema().fields().iter().enumerate() {
            if skip.contains(&f.name().as_str())
                || f.data_type() != &arrow::datatypes::DataType::Float64
            {
                continue;
            }
            let a = b
                .column(k)
                .as_any()
                .downcast_ref::<Float64Array>()
                .expect("float64 checked");
            match cols.iter_mut().find(|(n, _)| n == f.name()) {
                Some((_, v)) => v.extend(a.iter().map(|x| x.unwrap_or(f64::NAN))),
                None => cols.push((
                    f.name().clone(),
                    a.iter().map(|x| x.unwrap_or(f64::NAN)).collect(),
                )),
            }
        }
    }
    Ok(cols)
}

/// Per-unit draws of a boards/joints table: (parameter, unit, draws), units sorted.
fn unit_draws(
    path: &Path,
    key: &str,
    skip: &[&str],
) -> anyhow::Result<Vec<(String, String, Vec<f64>)>> {
    let mut by: BTreeMap<(String, String), Vec<f64>> = BTreeMap::new();
    let mut order: Vec<String> = vec![];
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let k = c.str(key)?;
        for (j, f) in b.schema().fields().iter().enumerate() {
            if skip.contains(&f.name().as_str())
                || f.data_type() != &arrow::datatypes::DataType::Float64
            {
                continue;
            }
            if !order.contains(f.name()) {
                order.push(f.name().clone());
            }
            let a = b
                .column(j)
                .as_any()
                .downcast_ref::<Float64Array>()
                .expect("float64 checked");
            for i in 0..b.num_rows() {
                by.entry((f.name().clone(), k.value(i).to_string()))
                    .or_default()
                    .push(a.value(i));
            }
        }
    }
    let mut out = vec![];
    for p in &order {
        for ((q, u), v) in &by {
            if q == p {
                out.push((p.clone(), u.clone(), v.clone()));
            }
        }
    }
    Ok(out)
}

/// An update step's summary.parquet.
fn read_summary(path: &Path) -> anyhow::Result<Vec<SummaryRow>> {
    let mut out = vec![];
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let (p, bid, mid) = (
            c.str("parameter")?,
            c.str("board_id")?,
            c.str("measurement_id")?,
        );
        let f: Vec<&Float64Array> = [
            "mean", "sd", "q05", "q50", "q95", "r_hat", "ess_bulk", "ess_tail",
        ]
        .iter()
        .map(|n| c.f64(n))
        .collect::<Result<_, _>>()?;
        // A summary written before its step had physical bounds has no such columns.
        let phys: Option<(&Float64Array, &Float64Array)> =
            match (c.f64("physical_q05"), c.f64("physical_q95")) {
                (Ok(a), Ok(b)) => Some((a, b)),
                _ => None,
            };
        for i in 0..b.num_rows() {
            let unit = if !bid.is_null(i) {
                Some(bid.value(i).to_string())
            } else if !mid.is_null(i) {
                Some(mid.value(i).to_string())
            } else {
                None
            };
            let g = |k: usize| value_or_nan(f[k], i);
            out.push(SummaryRow {
                parameter: p.value(i).into(),
                unit,
                mean: g(0),
                sd: g(1),
                q05: g(2),
                q50: g(3),
                q95: g(4),
                r_hat: g(5),
                ess_bulk: g(6),
                ess_tail: g(7),
                physical_q05: phys.map_or(f64::NAN, |(a, _)| value_or_nan(a, i)),
                physical_q95: phys.map_or(f64::NAN, |(_, b)| value_or_nan(b, i)),
            });
        }
    }
    Ok(out)
}

/// An update step's tempering path per run (stage, beta, ESS) from stages.parquet.
fn read_stages(path: &Path) -> anyhow::Result<Vec<Vec<(f64, f64, f64)>>> {
    let mut runs: BTreeMap<i32, Vec<(f64, f64, f64)>> = BTreeMap::new();
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let (r, s, beta, ess) = (
            c.i32("run")?,
            c.i32("stage")?,
            c.f64("beta")?,
            c.f64("ess")?,
        );
        for i in 0..b.num_rows() {
            runs.entry(r.value(i)).or_default().push((
                s.value(i) as f64,
                beta.value(i),
                ess.value(i),
            ));
        }
    }
    Ok(runs.into_values().collect())
}

/// What the report shows of one update step (`dir`): population draws, per-unit draws of
/// `units` keyed by `key`, summary, tempering paths and evidence.
pub fn step_data(dir: &Path, name: &str, units: &str, key: &str) -> anyhow::Result<StepData> {
    Ok(StepData {
        name: name.into(),
        population: float_columns(&dir.join("population.parquet"), &[])?,
        units: unit_draws(&dir.join(units), key, &["mass_g"])?,
        summary: read_summary(&dir.join("summary.parquet"))?,
        stages: read_stages(&dir.join("stages.parquet"))?,
        evidence: read_json(&dir.join("evidence.json"))?,
    })
}

/// The SVG files of `dir`, sorted; none when it does not exist.
pub fn svgs(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .map(|r| {
            r.filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.extension().is_some_and(|x| x == "svg"))
                .collect()
        })
        .unwrap_or_default();
    v.sort();
    v
}

/// Row i of a float column, null as NaN.
fn value_or_nan(a: &Float64Array, i: usize) -> f64 {
    if a.is_null(i) {
        f64::NAN
    } else {
        a.value(i)
    }
}

/// NaN and infinities as null.
fn opt_f64(v: f64) -> Option<f64> {
    v.is_finite().then_some(v)
}

/// The setup, label and role (`updating` or `validation`) columns of both report tables.
fn mode_cols<R>(rows: &[R], key: impl Fn(&R) -> (&str, &str, bool)) -> [ArrayRef; 3] {
    let role = |u: bool| if u { "updating" } else { "validation" };
    [
        Arc::new(StringArray::from_iter_values(rows.iter().map(|r| key(r).0))),
        Arc::new(StringArray::from_iter_values(rows.iter().map(|r| key(r).1))),
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|r| role(key(r).2)),
        )),
    ]
}

/// table2.parquet and table2.csv under `out`.
pub fn write_table2(
    out: &Path,
    rows: &[Table2Row],
    prov: &BTreeMap<String, String>,
) -> anyhow::Result<Vec<PathBuf>> {
    let f = |g: fn(&Table2Row) -> f64| -> ArrayRef {
        Arc::new(Float64Array::from_iter(rows.iter().map(|r| opt_f64(g(r)))))
    };
    let mut cols: Vec<ArrayRef> = mode_cols(rows, |r| {
        (r.setup.as_str(), r.label.as_str(), r.used_for_updating)
    })
    .into();
    cols.extend([
        Arc::new(Int32Array::from_iter_values(
            rows.iter().map(|r| r.n_measured as i32),
        )),
        Arc::new(Int32Array::from_iter_values(
            rows.iter().map(|r| r.n_boards as i32),
        )),
        f(|r| r.measured_mean_hz),
        f(|r| r.measured_sd_hz),
        f(|r| r.simulated_mean_hz),
        f(|r| r.simulated_sd_hz),
        f(|r| r.predictive_sd_hz),
        f(|r| r.discrepancy_mean_pct),
        f(|r| r.discrepancy_sd_pct),
        f(|r| r.mean_error_with_discrepancy_pct),
        f(|r| r.mean_error_pct),
        f(|r| r.sd_error_pct),
        f(|r| r.board_coverage_90),
        f(|r| r.new_board_coverage_90),
        Arc::new(Int32Array::from_iter_values(
            rows.iter().map(|r| r.n_held_out as i32),
        )),
        f(|r| r.held_out_coverage_90),
    ]);
    write_both(out, &TABLE2, cols, prov)
}

/// intervals.parquet and intervals.csv under `out`.
pub fn write_intervals(
    out: &Path,
    rows: &[Interval],
    prov: &BTreeMap<String, String>,
) -> anyhow::Result<Vec<PathBuf>> {
    let f = |g: fn(&Interval) -> f64| -> ArrayRef {
        Arc::new(Float64Array::from_iter(rows.iter().map(|r| opt_f64(g(r)))))
    };
    let mut cols: Vec<ArrayRef> = vec![
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|r| r.scope.as_str()),
        )),
        Arc::new(StringArray::from_iter(
            rows.iter().map(|r| r.board_id.as_deref()),
        )),
    ];
    cols.extend(mode_cols(rows, |r| {
        (r.setup.as_str(), r.label.as_str(), r.used_for_updating)
    }));
    cols.extend([
        Arc::new(Int32Array::from_iter_values(
            rows.iter().map(|r| r.n_draws as i32),
        )),
        f(|r| r.model_mean_hz),
        f(|r| r.model_sd_hz),
        f(|r| r.q05_hz),
        f(|r| r.q25_hz),
        f(|r| r.q50_hz),
        f(|r| r.q75_hz),
        f(|r| r.q95_hz),
        Arc::new(Int32Array::from_iter_values(
            rows.iter().map(|r| r.n_measured as i32),
        )),
        Arc::new(Int32Array::from_iter_values(
            rows.iter().map(|r| r.n_inside_90 as i32),
        )),
        Arc::new(Int32Array::from_iter_values(
            rows.iter().map(|r| r.n_held_out as i32),
        )),
        Arc::new(Int32Array::from_iter_values(
            rows.iter().map(|r| r.n_held_out_inside_90 as i32),
        )),
    ]);
    write_both(out, &INTERVALS, cols, prov)
}

/// `diagnosis.json` and, when there, `diagnosis_modes.parquet` of the diagnose stage.
pub fn read_diagnosis(json: &Path, modes: &Path) -> anyhow::Result<DiagnosisData> {
    let b = std::fs::read(json).with_context(|| format!("cannot read {}", json.display()))?;
    let doc: DiagnosisView = serde_json::from_slice(&b).with_context(|| {
        format!(
            "{}: not a diagnosis document (expected the fields of schemas/diagnosis.schema.json)",
            json.display()
        )
    })?;
    let modes = if modes.is_file() {
        let mut out = vec![];
        for b in tables::read_parquet(modes)? {
            let c = Cols {
                batch: &b,
                path: modes,
            };
            let (m, st, l, u, n, r, loc) = (
                c.str("model")?,
                c.str("setup")?,
                c.str("label")?,
                c.bool("used_for_updating")?,
                c.i32("n")?,
                c.f64("mean_rel_residual")?,
                c.bool("located")?,
            );
            for i in 0..b.num_rows() {
                out.push(ModeMisfit {
                    model: m.value(i).into(),
                    setup: st.value(i).into(),
                    label: l.value(i).into(),
                    used_for_updating: u.value(i),
                    n: n.value(i).max(0) as usize,
                    mean_rel_residual: (!r.is_null(i)).then(|| r.value(i)),
                    located: loc.value(i),
                });
            }
        }
        Some(out)
    } else {
        None
    };
    Ok(DiagnosisData { doc, modes })
}

/// One table of the diagnosis section as Parquet and CSV.
pub fn write_section_table(
    out: &Path,
    t: &diagnosis::Table,
    prov: &BTreeMap<String, String>,
) -> anyhow::Result<Vec<PathBuf>> {
    let spec = t.spec;
    let mut cols: Vec<ArrayRef> = vec![];
    for (k, col) in spec.columns.iter().enumerate() {
        let cells = t.rows.iter().map(|r| &r[k]);
        let a: ArrayRef = match col.ty {
            Col::Utf8 => Arc::new(StringArray::from_iter(cells.map(|c| match c {
                Cell::Str(v) => v.clone(),
                _ => None,
            }))),
            Col::Float64 => Arc::new(Float64Array::from_iter(cells.map(|c| match c {
                Cell::F64(v) => *v,
                _ => None,
            }))),
            Col::Int32 => Arc::new(Int32Array::from_iter(cells.map(|c| match c {
                Cell::Int(v) => v.map(|x| x as i32),
                _ => None,
            }))),
            Col::Bool => Arc::new(BooleanArray::from_iter(cells.map(|c| match c {
                Cell::Bool(b) => Some(*b),
                _ => None,
            }))),
            other => bail!(
                "{}: column {} of type {other:?} not supported",
                t.spec.name,
                col.name
            ),
        };
        cols.push(a);
    }
    write_both(out, spec, cols, prov)
}

/// The table as Parquet and as CSV (numbers in Rust's shortest round-trip form, empty = null).
fn write_both(
    out: &Path,
    spec: &TableSpec,
    cols: Vec<ArrayRef>,
    prov: &BTreeMap<String, String>,
) -> anyhow::Result<Vec<PathBuf>> {
    let schema = spec.schema(&[], &tables::table_metadata(spec, prov));
    let batch = tables::batch(schema, cols)?;
    let pq = out.join(format!("{}.parquet", spec.name));
    tables::write_parquet(&pq, &batch)?;
    let mut w = csv::Writer::from_writer(vec![]);
    w.write_record(spec.columns.iter().map(|c| c.name))?;
    for i in 0..batch.num_rows() {
        let rec: Vec<String> = batch
            .columns()
            .iter()
            .map(|a| {
                if a.is_null(i) {
                    return String::new();
                }
                if let Some(s) = a.as_any().downcast_ref::<StringArray>() {
                    s.value(i).to_string()
                } else if let Some(x) = a.as_any().downcast_ref::<Float64Array>() {
                    x.value(i).to_string()
                } else if let Some(x) = a.as_any().downcast_ref::<Int32Array>() {
                    x.value(i).to_string()
                } else if let Some(x) = a.as_any().downcast_ref::<BooleanArray>() {
                    x.value(i).to_string()
                } else {
                    String::new()
                }
            })
            .collect();
        w.write_record(&rec)?;
    }
    let bytes = w.into_inner().map_err(|e| anyhow!("csv: {e}"))?;
    let csvp = out.join(format!("{}.csv", spec.name));
    crate::io::atomic::write_bytes(&csvp, &bytes)?;
    Ok(vec![pq, csvp])
}

// ---------------------------------------------------------------------------------------------
// The report's inputs in a work directory.

/// The diagnose stage's document (see `stage::diagnose::JSON`).
const DIAGNOSIS_FILE: &str = "diagnosis.json";
/// The diagnose stage's per-mode misfits (see `stage::diagnose::MODES`).
const DIAGNOSIS_MODES_FILE: &str = "diagnosis_modes.parquet";

/// The report's inputs in a work directory: where they are, which are there, and the list the
/// manifest hashes (in the order it hashes them).
pub struct Sources {
    pub step1: PathBuf,
    pub step2: PathBuf,
    pub prop: PathBuf,
    pub has2: bool,
    pub step1_report: serde_json::Value,
    pub held_out: Vec<String>,
    /// Free-free measurements step 1 held out while updating their boards.
    pub held_out_measurements: Vec<String>,
    pub pairs: PathBuf,
    /// Step 2's update_report.json when step 2 ran without a posterior.
    pub step2_note: Option<PathBuf>,
    pub ingest_report: PathBuf,
    pub specimens: PathBuf,
    pub diag_json: PathBuf,
    pub diag_modes: PathBuf,
    pub has_diag: bool,
    /// The plots to copy, with the stage that drew them.
    pub plots: Vec<(&'static str, PathBuf)>,
    /// Manifests of every stage (provenance).
    pub manifests: Vec<PathBuf>,
    pub inputs: Vec<PathBuf>,
}

/// Locate the inputs of the report of work directory `w`; an error when a required one is
/// missing.
pub fn locate(w: &Path) -> anyhow::Result<Sources> {
    let wd = WorkDir::new(w);
    let (step1, step2, prop) = (wd.update_boards(), wd.update_joints(), wd.propagate());
    if !prop.join("predictions.parquet").is_file() {
        bail!(
            "{}: no predictions.parquet; run `hbmu propagate {} --out {}` first",
            prop.display(),
            step1.display(),
            prop.display()
        );
    }
    if !step1.join("boards.parquet").is_file() {
        bail!(
            "{}: no step-1 posterior (boards.parquet); run `hbmu update boards` first",
            step1.display()
        );
    }
    let has2 = step2.join("joints.parquet").is_file();
    let step1_report = read_json(&step1.join("update_report.json"))?;
    let held_out = sources::held_out_boards(&step1_report);
    let held_out_measurements = sources::held_out_measurements(&step1_report);
    let pairs = w.join("pair").join("pairs.parquet");
    let mut inputs = vec![
        prop.join("predictions.parquet"),
        prop.join("propagate_report.json"),
    ];
    let step_files = [
        "population.parquet",
        "summary.parquet",
        "stages.parquet",
        "residuals.parquet",
        "evidence.json",
        "update_report.json",
    ];
    inputs.extend(step_files.iter().map(|f| step1.join(f)));
    inputs.push(step1.join("boards.parquet"));
    if has2 {
        // update_report.json is optional in step 2 (not part of its output contract).
        inputs.extend(
            step_files
                .iter()
                .map(|f| step2.join(f))
                .filter(|p| !p.ends_with("update_report.json") || p.is_file()),
        );
        inputs.push(step2.join("joints.parquet"));
    }
    // Step 2 that ran without a posterior (a campaign without paired bolted modes) says why.
    let step2_note = step2.join("update_report.json");
    let step2_note = (!has2 && step2_note.is_file()).then_some(step2_note);
    if let Some(p) = &step2_note {
        inputs.push(p.clone());
    }
    if !held_out.is_empty() {
        if !pairs.is_file() {
            bail!(
                "{}: step 1 held out boards {} but the work directory has no pair/pairs.parquet to compare their measurements with",
                step1.display(),
                held_out.join(", ")
            );
        }
        inputs.push(pairs.clone());
    }
    let ingest_report = w.join("ingest").join("ingest_report.json");
    let specimens = w.join("ingest").join("specimens.parquet");
    if specimens.is_file() {
        inputs.push(specimens.clone());
    }
    if ingest_report.is_file() {
        inputs.push(ingest_report.clone());
    }
    // The diagnosis, when the diagnose stage ran: its document and per-mode misfits.
    let diag_json = w.join("diagnose").join(DIAGNOSIS_FILE);
    let diag_modes = w.join("diagnose").join(DIAGNOSIS_MODES_FILE);
    let has_diag = diag_json.is_file();
    if has_diag {
        inputs.push(diag_json.clone());
        if diag_modes.is_file() {
            inputs.push(diag_modes.clone());
        }
    }
    let plots: Vec<(&str, PathBuf)> = svgs(&w.join("extract").join("plots"))
        .into_iter()
        .map(|p| ("extract", p))
        .chain(
            svgs(&w.join("pair").join("plots"))
                .into_iter()
                .map(|p| ("pair", p)),
        )
        .collect();
    inputs.extend(plots.iter().map(|(_, p)| p.clone()));
    Ok(Sources {
        step1,
        step2,
        prop,
        has2,
        step1_report,
        held_out,
        held_out_measurements,
        pairs,
        step2_note,
        ingest_report,
        specimens,
        diag_json,
        diag_modes,
        has_diag,
        plots,
        manifests: manifests(w),
        inputs,
    })
}

/// Manifests of every stage (provenance): their outputs' hashes only, no times.
fn manifests(w: &Path) -> Vec<PathBuf> {
    let mut manifests = vec![];
    for d in work_dir::STAGES
        .into_iter()
        .filter(|&d| d != work_dir::REPORT)
    {
        let mut v: Vec<PathBuf> = std::fs::read_dir(w.join(d))
            .map(|r| {
                r.filter_map(|e| e.ok().map(|e| e.path()))
                    .filter(|p| p.to_string_lossy().ends_with(".manifest.json"))
                    .collect()
            })
            .unwrap_or_default();
        v.sort();
        manifests.extend(v);
    }
    manifests
}

/// The measured frequencies (both steps' residuals, and the held-out boards' pairs), step 2's
/// data, or why there is none.
pub fn read_measurements(
    src: &Sources,
) -> anyhow::Result<(Vec<Measured>, Option<StepData>, Option<String>)> {
    let mut measured = read_measured(&src.step1.join("residuals.parquet"))?;
    let mut step2_data = None;
    let mut step2_absent = None;
    if src.has2 {
        measured.extend(read_measured(&src.step2.join("residuals.parquet"))?);
        step2_data = Some(step_data(
            &src.step2,
            "joints (step 2)",
            "joints.parquet",
            "measurement_id",
        )?);
    } else {
        let note = src.step2_note.as_deref().map(read_json).transpose()?;
        step2_absent = Some(sources::step2_absent(note.as_ref()));
    }
    if !src.held_out.is_empty() || !src.held_out_measurements.is_empty() {
        let roles: BTreeMap<(String, String), bool> = measured
            .iter()
            .map(|m| ((m.setup.clone(), m.label.clone()), m.used_for_updating))
            .collect();
        measured.extend(read_held_out(
            &src.pairs,
            (&src.held_out, &src.held_out_measurements),
            &roles,
        )?);
    }
    Ok((measured, step2_data, step2_absent))
}

/// The provenance of every stage manifest that reads.
pub fn provenance(manifests: &[PathBuf], w: &Path) -> Vec<Provenance> {
    let mut provenance = vec![];
    for m in manifests {
        let Some(man) = crate::io::manifest::read_manifest(m) else {
            continue;
        };
        provenance.push(Provenance {
            stage: man.stage.clone(),
            manifest: crate::io::manifest::rel_path(m, w),
            tool_version: man.tool_version.clone(),
            fingerprint: man.fingerprint.clone(),
            outputs: man
                .outputs
                .iter()
                .map(|o| (o.path.clone(), o.blake3.clone()))
                .collect(),
        });
    }
    provenance
}

/// Copy the plots under `out/plots/<stage>/`: the copies and the page's links to them.
#[allow(clippy::type_complexity)]
pub fn copy_plots(
    plots: &[(&str, PathBuf)],
    out: &Path,
) -> anyhow::Result<(Vec<PathBuf>, Vec<(String, String, String)>)> {
    let mut outputs = vec![];
    let mut links = vec![];
    for (kind, p) in plots {
        let name = p
            .file_name()
            .map(|n| n.to_string_lossy().to_string())
            .unwrap_or_default();
        let (mid, what, rel) = sources::plot_link(kind, &name);
        let dst = out.join(&rel);
        crate::io::atomic::write_bytes(
            &dst,
            &std::fs::read(p).with_context(|| format!("cannot read {}", p.display()))?,
        )?;
        outputs.push(dst);
        links.push((mid, what, rel));
    }
    Ok((outputs, links))
}

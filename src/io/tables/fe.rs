//! The `fe` stage's tables: fe_modes.parquet and sensitivity.parquet (specs in
//! [`crate::io::tables`]), their writers, and the scan points `fe modes` reports shapes at.

use crate::fem::{Board, Params};
use crate::io::tables::{self, TableSpec};
use anyhow::{bail, Context};
use arrow::array::{ArrayRef, Float64Array, Int32Array, StringArray};
use faer::Mat;
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;

/// The table metadata of an `fe` table: stage, fingerprint, version, board.
pub fn provenance(stage: &str, fingerprint: &str, board: &Board) -> BTreeMap<String, String> {
    BTreeMap::from([
        ("hbmu.stage".to_string(), stage.to_string()),
        ("hbmu.fingerprint".to_string(), fingerprint.to_string()),
        (
            "hbmu.version".to_string(),
            crate::io::manifest::TOOL_VERSION.to_string(),
        ),
        ("hbmu.board".to_string(), board.name.clone()),
        ("hbmu.campaign".to_string(), String::new()),
    ])
}

/// Write an `fe` table.
fn write(
    path: &Path,
    spec: &TableSpec,
    prov: &BTreeMap<String, String>,
    cols: Vec<ArrayRef>,
) -> anyhow::Result<()> {
    let schema = spec.schema(&[], &tables::table_metadata(spec, prov));
    let b = tables::batch(schema, cols)?;
    tables::write_parquet(path, &b).with_context(|| format!("writing {}", path.display()))
}

/// fe_modes.parquet at `out`: per mode its frequency and its shape `w` (points × modes) at
/// the points `nodes`, `pts`.
pub fn write_modes(
    out: &Path,
    prov: &BTreeMap<String, String>,
    setup: &str,
    freq_hz: &[f64],
    nodes: &[i64],
    pts: &[[f64; 2]],
    w: &Mat<f64>,
) -> anyhow::Result<()> {
    let n = freq_hz.len();
    write(
        out,
        &tables::FE_MODES,
        prov,
        vec![
            Arc::new(StringArray::from(vec![setup; n])),
            Arc::new(Int32Array::from_iter_values((1..=n).map(|m| m as i32))),
            Arc::new(Float64Array::from(freq_hz.to_vec())),
            tables::list_i64_col((0..n).map(|_| nodes.to_vec())),
            tables::list_f64_col((0..n).map(|_| pts.iter().map(|p| p[0]).collect())),
            tables::list_f64_col((0..n).map(|_| pts.iter().map(|p| p[1]).collect())),
            tables::list_f64_col((0..n).map(|j| (0..pts.len()).map(|i| w[(i, j)]).collect())),
        ],
    )
}

/// sensitivity.parquet at `out`: per mode and parameter of `p`, the derivative `d_freq_hz`
/// (modes × parameters) and its `%/%` form.
pub fn write_sensitivity(
    out: &Path,
    prov: &BTreeMap<String, String>,
    setup: &str,
    p: &Params,
    freq_hz: &[f64],
    d_freq_hz: &Mat<f64>,
) -> anyhow::Result<()> {
    let mut rows: Vec<(i32, f64, String, f64, f64, f64)> = vec![];
    for j in 0..freq_hz.len() {
        for (k, name) in p.names.iter().enumerate() {
            let df = d_freq_hz[(j, k)];
            rows.push((
                j as i32 + 1,
                freq_hz[j],
                name.clone(),
                p.values[k],
                df,
                p.values[k] / freq_hz[j] * df,
            ));
        }
    }
    write(
        out,
        &tables::SENSITIVITY,
        prov,
        vec![
            Arc::new(StringArray::from(vec![setup; rows.len()])),
            Arc::new(Int32Array::from_iter_values(rows.iter().map(|r| r.0))),
            Arc::new(Float64Array::from_iter_values(rows.iter().map(|r| r.1))),
            Arc::new(StringArray::from_iter_values(
                rows.iter().map(|r| r.2.as_str()),
            )),
            Arc::new(Float64Array::from_iter_values(rows.iter().map(|r| r.3))),
            Arc::new(Float64Array::from_iter_values(rows.iter().map(|r| r.4))),
            Arc::new(Float64Array::from_iter_values(rows.iter().map(|r| r.5))),
        ],
    )
}

/// Node ids and (x, y) of the points at which shapes are reported.
/// `from`: an ingest output directory and a measurement id, whose points (not the
/// reference) are read from its scan_points.parquet; `None`: the board's scan grid.
pub fn report_points(
    board: &Board,
    from: Option<(&Path, &str)>,
) -> anyhow::Result<(Vec<i64>, Vec<[f64; 2]>)> {
    match from {
        None => {
            let pts = board.scan_points_m();
            Ok(((1..=pts.len() as i64).collect(), pts))
        }
        Some((ingest_dir, measurement_id)) => {
            let path = ingest_dir.join("scan_points.parquet");
            let rows = tables::read_scan_points(&path)?;
            let pts: Vec<_> = rows
                .into_iter()
                .filter(|r| r.measurement_id == measurement_id && !r.is_reference)
                .collect();
            if pts.is_empty() {
                bail!(
                    "{}: no scan points for measurement {:?} (is it quarantined, or misspelt?)",
                    path.display(),
                    measurement_id
                );
            }
            Ok((
                pts.iter().map(|r| r.node).collect(),
                pts.iter().map(|r| [r.xyz_m[0], r.xyz_m[1]]).collect(),
            ))
        }
    }
}

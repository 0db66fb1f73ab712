//! The spec, row types, reader and writer of extract's modes.parquet and point_flags.parquet,
//! and extract's input: the ingest tables read back as one [`MeasurementInput`] per measurement.
//! The stages that use identified modes (`pair`, `update`, `diagnose`) read modes.parquet as
//! [`ModeRow`]s; a missing column or one of the wrong type is an error naming the file and
//! column.

use crate::io::tables::{self, c, Col, Cols, TableSpec};
use crate::modal::{self, FunctionKind, MeasurementSpectra, PointSpectrum};
use anyhow::Context;
use arrow::array::{ArrayRef, Float64Array, Int32Array, Int64Array, StringArray};
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;

pub const MODES: TableSpec = TableSpec {
    name: "modes",
    doc: "Identified modes, one row per (measurement, mode), modes ascending in frequency. Shapes are real-normalised (largest |component| = +1) and aligned with the `node`, `x_m`, `y_m` lists; NaN at scan points excluded from the fit (see point_flags.parquet).",
    open: false,
    columns: &[
        c("measurement_id", Col::Utf8, false, "", "Measurement id."),
        c("board_id", Col::Utf8, false, "", "Board."),
        c("setup", Col::Utf8, false, "", "`free` or `bolted`."),
        c("mode", Col::Int32, false, "", "Identified mode number in this measurement, 1-based, ascending frequency."),
        c("freq_hz", Col::Float64, false, "Hz", "Undamped natural frequency |lambda|/(2 pi)."),
        c("damping_ratio", Col::Float64, false, "", "Viscous damping ratio -Re(lambda)/|lambda|."),
        c("mpc", Col::Float64, false, "", "Modal phase collinearity, 0..1 (1 = real mode)."),
        c("mpd_deg", Col::Float64, false, "deg", "Mean phase deviation."),
        c("cluster_size", Col::Int32, false, "", "Model orders in which the pole was stable (support in the stabilization diagram)."),
        c("fit_error", Col::Float64, false, "", "Relative residual of the LSFD fit over the used scan points of the measurement."),
        c("n_points_used", Col::Int32, false, "", "Scan points used in the fit (for `uff55`: with a value in the shape)."),
        c("band_lo_hz", Col::Float64, false, "Hz", "Identification band, lower edge."),
        c("band_hi_hz", Col::Float64, false, "Hz", "Identification band, upper edge."),
        c("node", Col::ListI64, false, "", "Scan-point node labels."),
        c("x_m", Col::ListF64, false, "m", "Scan-point x coordinates."),
        c("y_m", Col::ListF64, false, "m", "Scan-point y coordinates."),
        c("shape", Col::ListF64, false, "", "Real-normalised mode shape at the scan points."),
        c("source", Col::Utf8, false, "", "Who identified the mode: `lscf` (hbmu's extraction from the FRFs) or `uff55` (the lab's modal software, its UFF dataset 55 passed through: no stabilization support, `cluster_size` 0, `fit_error` NaN, band = the span of its modes)."),
    ],
};

pub const POINT_FLAGS: TableSpec = TableSpec {
    name: "point_flags",
    doc: "Scan points excluded from a measurement's modal fit, with the reason (low coherence, noise-like spectrum, no signal, fit outlier).",
    open: false,
    columns: &[
        c("measurement_id", Col::Utf8, false, "", "Measurement id."),
        c("node", Col::Int64, false, "", "Scan-point node label."),
        c("reason", Col::Utf8, false, "", "Why the point was excluded."),
    ],
};

/// One measurement's spectra and metadata, read from the ingest tables.
#[derive(Debug, Clone)]
pub struct MeasurementInput {
    pub measurement_id: String,
    pub board_id: String,
    pub setup: String,
    pub points: Vec<tables::ScanPointRow>,
    pub spectra: MeasurementSpectra,
    /// The lab's modes at `points` (dataset 55) for a measurement without response records:
    /// passed through instead of identified.
    pub given: Option<Vec<modal::GivenMode>>,
}

/// Read the ok measurements of an ingest directory, in sheet order.
pub fn read_ingest(dir: &Path) -> anyhow::Result<Vec<MeasurementInput>> {
    let mpath = dir.join("measurements.parquet");
    let mut meta: Vec<(String, String, String)> = vec![];
    for b in tables::read_parquet(&mpath)? {
        let c = Cols {
            batch: &b,
            path: &mpath,
        };
        let (id, board, setup, status) = (
            c.str("measurement_id")?,
            c.str("board_id")?,
            c.str("setup")?,
            c.str("status")?,
        );
        for i in 0..b.num_rows() {
            if status.value(i) == "ok" {
                meta.push((
                    id.value(i).into(),
                    board.value(i).into(),
                    setup.value(i).into(),
                ));
            }
        }
    }
    let mut points: BTreeMap<String, Vec<tables::ScanPointRow>> = BTreeMap::new();
    for p in tables::read_scan_points(&dir.join("scan_points.parquet"))? {
        points.entry(p.measurement_id.clone()).or_default().push(p);
    }
    // Response and coherence records per measurement and node.
    let mut resp: BTreeMap<String, BTreeMap<i64, (i32, Rec)>> = BTreeMap::new();
    let mut coh: BTreeMap<String, BTreeMap<i64, Vec<f64>>> = BTreeMap::new();
    let fpath = dir.join("frf.parquet");
    for b in tables::read_parquet(&fpath)? {
        tables::check_frf_layout(&b, &fpath)?;
        let c = Cols {
            batch: &b,
            path: &fpath,
        };
        let (id, node, ft) = (
            c.str("measurement_id")?,
            c.i64("node")?,
            c.i32("function_type")?,
        );
        for i in 0..b.num_rows() {
            let re = c.list_f64("re", i)?.unwrap_or_default();
            let (f0, df) = (
                c.f64("freq_start_hz")?.value(i),
                c.f64("freq_step_hz")?.value(i),
            );
            let freq: Vec<f64> = (0..re.len()).map(|k| f0 + k as f64 * df).collect();
            let im = c.list_f64("im", i)?;
            if ft.value(i) == 6 {
                coh.entry(id.value(i).into())
                    .or_default()
                    .insert(node.value(i), re);
            } else {
                resp.entry(id.value(i).into())
                    .or_default()
                    .insert(node.value(i), (ft.value(i), (re, im, freq)));
            }
        }
    }
    let mut vendor = read_vendor_modes(&dir.join("vendor_modes.parquet"))?;
    let mut out = vec![];
    for (id, board, setup) in meta {
        let pts_all = points.remove(&id).unwrap_or_default();
        let (pts, spectra, given) = match resp.remove(&id) {
            Some(recs) => {
                let cohs = coh.remove(&id).unwrap_or_default();
                let (pts, spectra) = response_spectra(pts_all, &recs, &cohs);
                (pts, spectra, None)
            }
            None => {
                // No response record: the lab's modes, at the scan points any of them covers.
                let Some(vm) = vendor.remove(&id) else {
                    continue;
                };
                let pts: Vec<tables::ScanPointRow> =
                    pts_all.into_iter().filter(|p| p.has_record).collect();
                let given = vm
                    .into_iter()
                    .map(|v| modal::GivenMode {
                        freq_hz: v.freq_hz,
                        damping_ratio: v.damping_ratio,
                        mpc: v.mpc,
                        mpd_deg: v.mpd_deg,
                        shape: pts
                            .iter()
                            .map(|p| v.shape_at.get(&p.node).copied().unwrap_or(f64::NAN))
                            .collect(),
                    })
                    .collect();
                let none = MeasurementSpectra {
                    freq_hz: vec![],
                    points: vec![],
                    kind: FunctionKind::Other,
                };
                (pts, none, Some(given))
            }
        };
        out.push(MeasurementInput {
            measurement_id: id,
            board_id: board,
            setup,
            points: pts,
            spectra,
            given,
        });
    }
    Ok(out)
}

/// A response record's re, im (none for a real function) and frequencies.
type Rec = (Vec<f64>, Option<Vec<f64>>, Vec<f64>);

/// The spectra of one measurement's scan points with a response record (`recs` by node:
/// function type, re, im, frequencies), with their coherence; the points in scan order.
fn response_spectra(
    pts_all: Vec<tables::ScanPointRow>,
    recs: &BTreeMap<i64, (i32, Rec)>,
    cohs: &BTreeMap<i64, Vec<f64>>,
) -> (Vec<tables::ScanPointRow>, MeasurementSpectra) {
    let mut pts = vec![];
    let mut spectra = vec![];
    let mut freq_hz = vec![];
    let mut kind = FunctionKind::Other;
    for p in pts_all.into_iter().filter(|p| p.has_record) {
        let Some((ft, (re, im, f))) = recs.get(&p.node) else {
            continue;
        };
        kind = match ft {
            4 => FunctionKind::Mobility,
            5 => FunctionKind::Transmissibility,
            _ => FunctionKind::Other,
        };
        if freq_hz.is_empty() {
            freq_hz = f.clone();
        }
        spectra.push(PointSpectrum {
            node_id: p.node,
            re: re.clone(),
            im: im.clone().unwrap_or_else(|| vec![0.0; re.len()]),
            coherence: cohs.get(&p.node).cloned(),
        });
        pts.push(p);
    }
    let spectra = MeasurementSpectra {
        freq_hz,
        points: spectra,
        kind,
    };
    (pts, spectra)
}

/// A row of `vendor_modes.parquet`, its shape by node.
struct VendorRow {
    freq_hz: f64,
    damping_ratio: f64,
    mpc: f64,
    mpd_deg: f64,
    shape_at: BTreeMap<i64, f64>,
}

/// `vendor_modes.parquet` by measurement (rows in file order); none when an ingest directory
/// written before the table existed lacks it.
fn read_vendor_modes(path: &Path) -> anyhow::Result<BTreeMap<String, Vec<VendorRow>>> {
    let mut out: BTreeMap<String, Vec<VendorRow>> = BTreeMap::new();
    if !path.exists() {
        return Ok(out);
    }
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let (id, f, z, mpc, mpd) = (
            c.str("measurement_id")?,
            c.f64("freq_hz")?,
            c.f64("damping_ratio")?,
            c.f64("mpc")?,
            c.f64("mpd_deg")?,
        );
        for i in 0..b.num_rows() {
            let nodes = c.list_i64("node", i)?;
            let shape = c.list_f64("shape", i)?.unwrap_or_default();
            anyhow::ensure!(
                nodes.len() == shape.len(),
                "{}: row {i}: {} nodes but {} shape values; expected one value per node",
                path.display(),
                nodes.len(),
                shape.len()
            );
            out.entry(id.value(i).to_string())
                .or_default()
                .push(VendorRow {
                    freq_hz: f.value(i),
                    damping_ratio: z.value(i),
                    mpc: mpc.value(i),
                    mpd_deg: mpd.value(i),
                    shape_at: nodes.into_iter().zip(shape).collect(),
                });
        }
    }
    Ok(out)
}

/// One row of modes.parquet: an identified mode of a measurement's extraction.
pub struct ModeOut<'a> {
    pub input: &'a MeasurementInput,
    pub extraction: &'a modal::Extraction,
    /// 0-based position of the mode in the extraction.
    pub index: usize,
    pub mode: &'a modal::IdentifiedMode,
}

/// Write modes.parquet at `path`.
pub fn write_modes(
    path: &Path,
    prov: &BTreeMap<String, String>,
    rows: &[ModeOut],
) -> anyhow::Result<()> {
    let cols: Vec<ArrayRef> = vec![
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|r| r.input.measurement_id.as_str()),
        )),
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|r| r.input.board_id.as_str()),
        )),
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|r| r.input.setup.as_str()),
        )),
        Arc::new(Int32Array::from_iter_values(
            rows.iter().map(|r| r.index as i32 + 1),
        )),
        Arc::new(Float64Array::from_iter_values(
            rows.iter().map(|r| r.mode.freq_hz),
        )),
        Arc::new(Float64Array::from_iter_values(
            rows.iter().map(|r| r.mode.damping_ratio),
        )),
        Arc::new(Float64Array::from_iter_values(
            rows.iter().map(|r| r.mode.mpc),
        )),
        Arc::new(Float64Array::from_iter_values(
            rows.iter().map(|r| r.mode.mpd_deg),
        )),
        Arc::new(Int32Array::from_iter_values(
            rows.iter().map(|r| r.mode.cluster_size as i32),
        )),
        Arc::new(Float64Array::from_iter_values(
            rows.iter().map(|r| r.extraction.overall_fit_error),
        )),
        Arc::new(Int32Array::from_iter_values(rows.iter().map(|r| {
            r.mode.shape.iter().filter(|v| v.is_finite()).count() as i32
        }))),
        Arc::new(Float64Array::from_iter_values(
            rows.iter().map(|r| r.extraction.band_hz.0),
        )),
        Arc::new(Float64Array::from_iter_values(
            rows.iter().map(|r| r.extraction.band_hz.1),
        )),
        tables::list_i64_col(
            rows.iter()
                .map(|r| r.input.points.iter().map(|p| p.node).collect()),
        ),
        tables::list_f64_col(
            rows.iter()
                .map(|r| r.input.points.iter().map(|p| p.xyz_m[0]).collect()),
        ),
        tables::list_f64_col(
            rows.iter()
                .map(|r| r.input.points.iter().map(|p| p.xyz_m[1]).collect()),
        ),
        tables::list_f64_col(rows.iter().map(|r| r.mode.shape.clone())),
        Arc::new(StringArray::from_iter_values(rows.iter().map(|r| {
            if r.input.given.is_some() {
                "uff55"
            } else {
                "lscf"
            }
        }))),
    ];
    let schema = MODES.schema(&[], &tables::table_metadata(&MODES, prov));
    tables::write_parquet(path, &tables::batch(schema, cols)?)
        .with_context(|| format!("writing {}", path.display()))
}

/// Write point_flags.parquet at `path`: (measurement, node, reason) per excluded point.
pub fn write_point_flags(
    path: &Path,
    prov: &BTreeMap<String, String>,
    flags: &[(&str, i64, String)],
) -> anyhow::Result<()> {
    let schema = POINT_FLAGS.schema(&[], &tables::table_metadata(&POINT_FLAGS, prov));
    let cols: Vec<ArrayRef> = vec![
        Arc::new(StringArray::from_iter_values(flags.iter().map(|f| f.0))),
        Arc::new(Int64Array::from_iter_values(flags.iter().map(|f| f.1))),
        Arc::new(StringArray::from_iter_values(
            flags.iter().map(|f| f.2.as_str()),
        )),
    ];
    tables::write_parquet(path, &tables::batch(schema, cols)?)
        .with_context(|| format!("writing {}", path.display()))
}

pub use crate::modal::rows::ModeRow;

/// Every row of `modes.parquet` at `path`, in file order.
pub fn read_modes_table(path: &Path) -> anyhow::Result<Vec<ModeRow>> {
    let mut out = vec![];
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let (id, board, setup, mode, f, zeta, lo, hi) = (
            c.str("measurement_id")?,
            c.str("board_id")?,
            c.str("setup")?,
            c.i32("mode")?,
            c.f64("freq_hz")?,
            c.f64("damping_ratio")?,
            c.f64("band_lo_hz")?,
            c.f64("band_hi_hz")?,
        );
        for i in 0..b.num_rows() {
            out.push(ModeRow {
                measurement_id: id.value(i).to_string(),
                board_id: board.value(i).to_string(),
                setup: setup.value(i).to_string(),
                mode: mode.value(i),
                freq_hz: f.value(i),
                damping_ratio: zeta.value(i),
                band_lo_hz: lo.value(i),
                band_hi_hz: hi.value(i),
                node: c.list_i64("node", i)?,
                x_m: c.list_f64("x_m", i)?.unwrap_or_default(),
                y_m: c.list_f64("y_m", i)?.unwrap_or_default(),
                shape: c.list_f64("shape", i)?.unwrap_or_default(),
            });
        }
    }
    Ok(out)
}

//! Stage `extract`: ingest tables → identified modes per measurement (`modes.parquet`), the
//! scan points excluded from each fit with their reason (`point_flags.parquet`), and a
//! stabilization diagram per measurement (`plots/<measurement>_stabilization.svg`).
//!
//! Reads `measurements.parquet`, `scan_points.parquet`, `frf.parquet` and
//! `vendor_modes.parquet` of an ingest directory; runs the modal kernel
//! ([`crate::modal::extract`]) on every measurement whose ingest status is `ok` and that has
//! response records, in parallel, collecting results in sheet order so the outputs are
//! byte-identical whatever the thread count. A measurement without response records whose
//! lab exported its modes (dataset 55) has them passed through
//! ([`crate::modal::pass_through`], `source = uff55`). A measurement the kernel cannot
//! identify is reported (finding + exit code 3) and the others proceed.

use crate::findings::{Finding, Findings, Severity};
use crate::io::manifest::StageSpec;
use crate::io::tables::{self, c, Col, Cols, TableSpec};
use crate::modal::{self, ExtractParams, FunctionKind, MeasurementSpectra, PointSpectrum};
use crate::stage::{exit, StageOutcome, StageResult};
use anyhow::Context;
use arrow::array::{ArrayRef, Float64Array, Int32Array, Int64Array, StringArray};
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
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

pub const MANIFEST: &str = "extract.manifest.json";

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
    type Rec = (Vec<f64>, Option<Vec<f64>>, Vec<f64>);
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
        let Some(recs) = resp.remove(&id) else {
            // No response record: the lab's modes, at the scan points any of them covers.
            if let Some(vm) = vendor.remove(&id) {
                let pts: Vec<tables::ScanPointRow> = points
                    .remove(&id)
                    .unwrap_or_default()
                    .into_iter()
                    .filter(|p| p.has_record)
                    .collect();
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
                out.push(MeasurementInput {
                    measurement_id: id,
                    board_id: board,
                    setup,
                    points: pts,
                    spectra: MeasurementSpectra {
                        freq_hz: vec![],
                        points: vec![],
                        kind: FunctionKind::Other,
                    },
                    given: Some(given),
                });
            }
            continue;
        };
        let pts_all = points.remove(&id).unwrap_or_default();
        let cohs = coh.remove(&id).unwrap_or_default();
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
        out.push(MeasurementInput {
            measurement_id: id,
            board_id: board,
            setup,
            points: pts,
            spectra: MeasurementSpectra {
                freq_hz,
                points: spectra,
                kind,
            },
            given: None,
        });
    }
    Ok(out)
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

struct Done {
    input: MeasurementInput,
    result: Result<modal::Extraction, modal::ModalError>,
    svg: Option<String>,
}

/// Options of `hbmu extract`.
#[derive(Debug, Clone)]
pub struct ExtractOptions {
    pub ingest_dir: PathBuf,
    pub out: PathBuf,
    pub force: bool,
    pub params: ExtractParams,
    pub plots: bool,
}

/// Run the stage.
pub fn run(opts: &ExtractOptions, verbose: bool) -> anyhow::Result<StageOutcome> {
    let mut inputs: Vec<PathBuf> = ["measurements.parquet", "scan_points.parquet", "frf.parquet"]
        .iter()
        .map(|n| opts.ingest_dir.join(n))
        .collect();
    // Written by ingest since mode sets are passed through; an older ingest directory has none.
    let vendor = opts.ingest_dir.join("vendor_modes.parquet");
    if vendor.exists() {
        inputs.push(vendor);
    }
    let spec = StageSpec {
        stage: "extract".into(),
        inputs,
        input_base: opts.ingest_dir.clone(),
        config: serde_json::json!({"params": opts.params, "plots": opts.plots}),
        seed: None,
        manifest_path: opts.out.join(MANIFEST),
    };
    crate::stage::run(spec, opts.force, |prep| {
        let ms = read_ingest(&opts.ingest_dir)?;
        let pb = crate::stage::progress_bar(ms.len() as u64, "extract");
        let done: Vec<Done> = ms
            .into_par_iter()
            .map(|input| {
                let result = match &input.given {
                    Some(given) => Ok(modal::pass_through(given)),
                    None => modal::extract(&input.spectra, &opts.params),
                };
                let svg = match (&result, opts.plots) {
                    (Ok(x), true) if input.given.is_none() => {
                        let sel: Vec<f64> = x.modes.iter().map(|m| m.freq_hz).collect();
                        crate::report::plots::stabilization_svg(
                            &x.stabilization,
                            &sel,
                            None,
                            &format!(
                                "{} ({}, {})",
                                input.measurement_id, input.board_id, input.setup
                            ),
                        )
                        .ok()
                    }
                    _ => None,
                };
                pb.inc(1);
                Done { input, result, svg }
            })
            .collect();
        pb.finish_and_clear();
        write_outputs(opts, &prep.fingerprint, &done, verbose)
    })
}

fn write_outputs(
    opts: &ExtractOptions,
    fingerprint: &str,
    done: &[Done],
    verbose: bool,
) -> anyhow::Result<StageResult> {
    let out = &opts.out;
    std::fs::create_dir_all(out)?;
    let mut findings = Findings::default();
    let mut outputs = vec![];
    // modes
    let mut rows: Vec<(&Done, usize, &modal::IdentifiedMode)> = vec![];
    let mut flags: Vec<(&str, i64, String)> = vec![];
    for d in done {
        match &d.result {
            Ok(x) => {
                for (k, m) in x.modes.iter().enumerate() {
                    rows.push((d, k, m));
                }
                for (i, fl) in x.point_flags.iter().enumerate() {
                    for f in fl {
                        flags.push((&d.input.measurement_id, d.input.points[i].node, f.reason()));
                    }
                }
                let used = x.point_flags.iter().filter(|f| f.is_empty()).count();
                if d.input.given.is_none() && used < modal::FEW_POINTS {
                    let each: Vec<String> = x
                        .modes
                        .iter()
                        .map(|m| {
                            format!(
                                "{:.1} Hz ({} orders, share {:.2}{})",
                                m.freq_hz,
                                m.cluster_size,
                                m.peak_share,
                                if m.peak_share < 0.5 { ", weak" } else { "" }
                            )
                        })
                        .collect();
                    findings.push(
                        Finding::new(
                            Severity::Info,
                            "extract.few_points",
                            format!(
                                "identified from {used} response point(s): with fewer than {} the residues' phase collinearity (MPC) cannot tell a mode from noise, so each mode was kept on its stabilization support (orders) and its share of the response at its own frequency (at least {}): {}. A weak mode (share under 0.5) shares its peak with another mode or lies near a node of its shape at these points: its frequency and damping are less certain",
                                modal::FEW_POINTS,
                                opts.params.selection.min_peak_share,
                                if each.is_empty() { "none".to_string() } else { each.join(", ") }
                            ),
                        )
                        .measurement(d.input.measurement_id.clone()),
                    );
                }
                if d.input.given.is_some() {
                    findings.push(
                        Finding::new(
                            Severity::Info,
                            "extract.vendor_modes",
                            format!(
                                "{} mode(s) passed through from the lab's mode sets (UFF dataset 55, see ingest's vendor_modes.parquet): identified by the lab's software, not by hbmu; no stabilization support, `source = uff55`",
                                x.modes.len()
                            ),
                        )
                        .measurement(d.input.measurement_id.clone()),
                    );
                }
                if x.modes.is_empty() {
                    findings.push(
                        Finding::new(
                            Severity::Warning,
                            "extract.no_modes",
                            "no physical pole was selected in the band",
                        )
                        .measurement(d.input.measurement_id.clone()),
                    );
                }
            }
            Err(e) => findings.push(
                Finding::new(
                    Severity::Quarantined,
                    "extract.failed",
                    format!("modal identification failed: {e}"),
                )
                .measurement(d.input.measurement_id.clone()),
            ),
        }
    }
    let prov = BTreeMap::from([
        ("hbmu.stage".to_string(), "extract".to_string()),
        ("hbmu.fingerprint".to_string(), fingerprint.to_string()),
        (
            "hbmu.version".to_string(),
            crate::io::manifest::TOOL_VERSION.to_string(),
        ),
        ("hbmu.campaign".to_string(), String::new()),
    ]);
    let cols: Vec<ArrayRef> = vec![
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|r| r.0.input.measurement_id.as_str()),
        )),
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|r| r.0.input.board_id.as_str()),
        )),
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|r| r.0.input.setup.as_str()),
        )),
        Arc::new(Int32Array::from_iter_values(
            rows.iter().map(|r| r.1 as i32 + 1),
        )),
        Arc::new(Float64Array::from_iter_values(
            rows.iter().map(|r| r.2.freq_hz),
        )),
        Arc::new(Float64Array::from_iter_values(
            rows.iter().map(|r| r.2.damping_ratio),
        )),
        Arc::new(Float64Array::from_iter_values(rows.iter().map(|r| r.2.mpc))),
        Arc::new(Float64Array::from_iter_values(
            rows.iter().map(|r| r.2.mpd_deg),
        )),
        Arc::new(Int32Array::from_iter_values(
            rows.iter().map(|r| r.2.cluster_size as i32),
        )),
        Arc::new(Float64Array::from_iter_values(rows.iter().map(|r| {
            r.0.result
                .as_ref()
                .map(|x| x.overall_fit_error)
                .unwrap_or(f64::NAN)
        }))),
        Arc::new(Int32Array::from_iter_values(rows.iter().map(|r| {
            r.2.shape.iter().filter(|v| v.is_finite()).count() as i32
        }))),
        Arc::new(Float64Array::from_iter_values(rows.iter().map(|r| {
            r.0.result.as_ref().map(|x| x.band_hz.0).unwrap_or(f64::NAN)
        }))),
        Arc::new(Float64Array::from_iter_values(rows.iter().map(|r| {
            r.0.result.as_ref().map(|x| x.band_hz.1).unwrap_or(f64::NAN)
        }))),
        tables::list_i64_col(
            rows.iter()
                .map(|r| r.0.input.points.iter().map(|p| p.node).collect()),
        ),
        tables::list_f64_col(
            rows.iter()
                .map(|r| r.0.input.points.iter().map(|p| p.xyz_m[0]).collect()),
        ),
        tables::list_f64_col(
            rows.iter()
                .map(|r| r.0.input.points.iter().map(|p| p.xyz_m[1]).collect()),
        ),
        tables::list_f64_col(rows.iter().map(|r| r.2.shape.clone())),
        Arc::new(StringArray::from_iter_values(rows.iter().map(|r| {
            if r.0.input.given.is_some() {
                "uff55"
            } else {
                "lscf"
            }
        }))),
    ];
    let p = out.join("modes.parquet");
    let schema = MODES.schema(&[], &tables::table_metadata(&MODES, &prov));
    tables::write_parquet(&p, &tables::batch(schema, cols)?)
        .with_context(|| format!("writing {}", p.display()))?;
    outputs.push(p);

    let p = out.join("point_flags.parquet");
    let schema = POINT_FLAGS.schema(&[], &tables::table_metadata(&POINT_FLAGS, &prov));
    let cols: Vec<ArrayRef> = vec![
        Arc::new(StringArray::from_iter_values(flags.iter().map(|f| f.0))),
        Arc::new(Int64Array::from_iter_values(flags.iter().map(|f| f.1))),
        Arc::new(StringArray::from_iter_values(
            flags.iter().map(|f| f.2.as_str()),
        )),
    ];
    tables::write_parquet(&p, &tables::batch(schema, cols)?)
        .with_context(|| format!("writing {}", p.display()))?;
    outputs.push(p);

    if opts.plots {
        for d in done {
            if let Some(svg) = &d.svg {
                let p = out.join("plots").join(format!(
                    "{}_stabilization.svg",
                    sanitize(&d.input.measurement_id)
                ));
                crate::io::atomic::write_bytes(&p, svg.as_bytes())?;
                outputs.push(p);
            }
        }
    }
    let report = serde_json::json!({
        "measurements": done.len(),
        "modes": rows.len(),
        "flagged_points": flags.len(),
        "findings": findings.0,
    });
    let p = out.join("extract_report.json");
    let mut bytes = serde_json::to_vec_pretty(&report)?;
    bytes.push(b'\n');
    crate::io::atomic::write_bytes(&p, &bytes)?;
    outputs.push(p);

    for f in findings.iter() {
        if verbose || f.severity >= Severity::Quarantined {
            eprintln!("{f}");
        }
    }
    let failed = findings.count(Severity::Quarantined);
    eprintln!(
        "extract: {} measurements, {} modes, {} scan points flagged, {} failed",
        done.len(),
        rows.len(),
        flags.len(),
        failed
    );
    let mut summary = BTreeMap::new();
    summary.insert("measurements".into(), done.len().into());
    summary.insert("modes".into(), rows.len().into());
    summary.insert("failed".into(), failed.into());
    Ok(StageResult {
        outputs,
        exit_code: if failed > 0 {
            exit::QUARANTINED
        } else {
            exit::OK
        },
        summary,
    })
}

/// A file-name-safe version of an id.
pub fn sanitize(id: &str) -> String {
    id.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' || c == '.' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

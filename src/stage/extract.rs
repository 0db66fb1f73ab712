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
use crate::io::tables::extract::{read_ingest, MeasurementInput, ModeOut};
use crate::io::tables::{self};
use crate::modal::{self, ExtractParams};
use crate::stage::{exit, StageOutcome, StageResult};
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::path::PathBuf;

pub const MANIFEST: &str = "extract.manifest.json";

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
    let mut rows: Vec<ModeOut> = vec![];
    let mut flags: Vec<(&str, i64, String)> = vec![];
    for d in done {
        match &d.result {
            Ok(x) => {
                for (index, mode) in x.modes.iter().enumerate() {
                    rows.push(ModeOut {
                        input: &d.input,
                        extraction: x,
                        index,
                        mode,
                    });
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
    let p = out.join("modes.parquet");
    tables::extract::write_modes(&p, &prov, &rows)?;
    outputs.push(p);
    let p = out.join("point_flags.parquet");
    tables::extract::write_point_flags(&p, &prov, &flags)?;
    outputs.push(p);

    if opts.plots {
        for d in done {
            if let Some(svg) = &d.svg {
                let p = out.join("plots").join(format!(
                    "{}_stabilization.svg",
                    crate::io::sanitize(&d.input.measurement_id)
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

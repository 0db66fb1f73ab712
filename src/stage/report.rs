//! Stage `report`: the validation report of one work directory.
//!
//! Reads `propagate/` (predictions), `update_boards/` and, when present, `update_joints/`
//! (posteriors, summaries, tempering paths, evidence, residuals = the measurements compared),
//! `ingest/ingest_report.json` (findings), the stabilization and MAC plots of `extract/plots`
//! and `pair/plots`, `diagnose/diagnosis.json` and `diagnose/diagnosis_modes.parquet` when the
//! diagnose stage ran (the Diagnosis section, whose tables also go out as Parquet and CSV), and
//! every stage manifest (provenance). Writes `report.html` (self-contained,
//! inline SVG), `summary.md`, the tables `table2` and `intervals` as Parquet and CSV, and copies
//! of the plots under `plots/` so the directory can be sent as it is. The rendering is pure
//! (`report::html`); this file only reads and writes.

use crate::io::manifest::StageSpec;
use crate::io::read_json;
use crate::io::tables::report::{
    copy_plots, locate, provenance, read_diagnosis, read_measurements, read_specimens, step_data,
    write_intervals, write_section_table, write_table2,
};
use crate::report::diagnosis;
use crate::report::html::{self, ReportData};
use crate::report::sources;
use crate::report::validation::{self, Interval};
use crate::stage::{exit, StageOutcome, StageResult};
use std::collections::BTreeMap;
use std::path::PathBuf;

pub const MANIFEST: &str = "report.manifest.json";
pub const HTML: &str = "report.html";

/// Options of `hbmu report`.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ReportOptions {
    #[serde(skip)]
    pub work_dir: PathBuf,
    #[serde(skip)]
    pub out: PathBuf,
    #[serde(skip)]
    pub force: bool,
}

/// Run `hbmu report`.
pub fn run(opts: &ReportOptions, verbose: bool) -> anyhow::Result<StageOutcome> {
    let w = &opts.work_dir;
    let mut src = locate(w)?;
    let spec = StageSpec {
        stage: "report".into(),
        inputs: std::mem::take(&mut src.inputs),
        input_base: w.clone(),
        config: serde_json::json!({ "step2": src.has2, "diagnosis": src.has_diag }),
        seed: None,
        manifest_path: opts.out.join(MANIFEST),
    };
    crate::stage::run(spec, opts.force, |prep| {
        let preds =
            crate::io::tables::propagate::read_preds(&src.prop.join("predictions.parquet"))?;
        let (measured, step2_data, step2_absent) = read_measurements(&src)?;
        let iv = validation::intervals(&preds, &measured);
        let t2 = validation::table2(&preds, &measured, &iv);
        let mut meas_map: BTreeMap<(String, String, String), Vec<f64>> = BTreeMap::new();
        for m in &measured {
            meas_map
                .entry((m.board_id.clone(), m.setup.clone(), m.label.clone()))
                .or_default()
                .push(m.freq_hz);
        }
        let mut findings = vec![];
        let mut ingest = sources::IngestSummary::default();
        if src.ingest_report.is_file() {
            let v = read_json(&src.ingest_report)?;
            ingest = sources::ingest_summary(&v);
            sources::findings_of("ingest", &v, &mut findings);
        }
        sources::findings_of("update boards", &src.step1_report, &mut findings);
        if src.has2 && src.step2.join("update_report.json").is_file() {
            sources::findings_of(
                "update joints",
                &read_json(&src.step2.join("update_report.json"))?,
                &mut findings,
            );
        }
        let prop_report = read_json(&src.prop.join("propagate_report.json"))?;
        sources::findings_of("propagate", &prop_report, &mut findings);
        let provenance = provenance(&src.manifests, w);
        // Copies of the plots, linked from the page.
        let (mut outputs, links) = copy_plots(&src.plots, &opts.out)?;
        let diagnosis = if src.has_diag {
            Some(read_diagnosis(&src.diag_json, &src.diag_modes)?)
        } else {
            None
        };
        let title = format!(
            "Validation report: {}",
            w.canonicalize()
                .ok()
                .and_then(|c| c.file_name().map(|n| n.to_string_lossy().to_string()))
                .unwrap_or_else(|| "campaign".into())
        );
        let data = ReportData {
            title,
            tool_version: crate::io::manifest::TOOL_VERSION.into(),
            step1: step_data(&src.step1, "boards (step 1)", "boards.parquet", "board_id")?,
            step2: step2_data,
            step2_absent,
            table2: t2.clone(),
            intervals: iv.clone(),
            measured: meas_map,
            propagate: prop_report,
            plot_links: links,
            ingest_measurements: ingest.measurements,
            quarantined: ingest.quarantined,
            specimens: read_specimens(&src.specimens)?,
            ingest_counts: ingest.counts,
            findings,
            provenance,
            inputs: prep
                .inputs
                .iter()
                .filter(|f| !f.path.ends_with(".svg"))
                .map(|f| (f.path.clone(), f.blake3.clone()))
                .collect(),
            diagnosis,
        };
        let r = html::render(&data);
        let prov = BTreeMap::from([
            ("hbmu.stage".to_string(), "report".to_string()),
            ("hbmu.fingerprint".to_string(), prep.fingerprint.clone()),
            (
                "hbmu.version".to_string(),
                crate::io::manifest::TOOL_VERSION.to_string(),
            ),
            ("hbmu.campaign".to_string(), String::new()),
        ]);
        outputs.extend(write_table2(&opts.out, &t2, &prov)?);
        outputs.extend(write_intervals(&opts.out, &iv, &prov)?);
        if let Some(d) = &data.diagnosis {
            for t in diagnosis::tables(d) {
                outputs.extend(write_section_table(&opts.out, &t, &prov)?);
            }
        }
        let p = opts.out.join(HTML);
        crate::io::atomic::write_bytes(&p, r.html.as_bytes())?;
        outputs.push(p);
        let p = opts.out.join("summary.md");
        crate::io::atomic::write_bytes(&p, r.markdown.as_bytes())?;
        outputs.push(p);
        let summary = summarise(&iv, r.figures, src.has2);
        if verbose {
            for f in &data.findings {
                eprintln!("{} {} {}: {}", f.stage, f.severity, f.code, f.message);
            }
        }
        Ok(StageResult {
            outputs,
            exit_code: exit::OK,
            summary,
        })
    })
}

/// Say the free-free coverage of the 90 % intervals on stderr; the manifest's summary.
fn summarise(iv: &[Interval], figures: usize, has2: bool) -> BTreeMap<String, serde_json::Value> {
    let c = validation::free_coverage(iv);
    let ((vk, vn), (nk, nn), (hk, hn)) = (c.validation, c.new_board, c.held_out);
    let (mk, mn) = c.held_out_measurements;
    eprintln!(
        "report: {} figures; free-free coverage of the 90 % intervals: validation modes {vk}/{vn}, new board {nk}/{nn}{}{}{}",
        figures,
        if hn > 0 {
            format!(", held-out boards by the new board {hk}/{hn}")
        } else {
            String::new()
        },
        if mn > 0 {
            format!(", held-out measurements by their own board {mk}/{mn}")
        } else {
            String::new()
        },
        if has2 { "" } else { "; no step-2 posterior: no bolted predictions" }
    );
    let mut s = BTreeMap::new();
    s.insert("figures".into(), serde_json::json!(figures));
    s.insert(
        "validation_coverage_free".into(),
        serde_json::json!([vk, vn]),
    );
    s.insert(
        "new_board_coverage_free".into(),
        serde_json::json!([nk, nn]),
    );
    if hn > 0 {
        s.insert("held_out_coverage_free".into(), serde_json::json!([hk, hn]));
    }
    if mn > 0 {
        s.insert(
            "held_out_measurements_coverage_free".into(),
            serde_json::json!([mk, mn]),
        );
    }
    s
}

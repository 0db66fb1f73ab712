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
    read_diagnosis, read_held_out, read_measured, read_specimens, step_data, svgs, write_intervals,
    write_section_table, write_table2,
};
use crate::report::diagnosis;
use crate::report::html::{self, Provenance, ReportData, StepData};
use crate::report::sources;
use crate::report::validation::{self, Interval, Measured};
use crate::stage::{exit, StageOutcome, StageResult};
use anyhow::{bail, Context};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

pub const MANIFEST: &str = "report.manifest.json";
pub const HTML: &str = "report.html";
/// The diagnose stage's document (see `stage::diagnose::JSON`).
const DIAGNOSIS_FILE: &str = "diagnosis.json";
/// The diagnose stage's per-mode misfits (see `stage::diagnose::MODES`).
const DIAGNOSIS_MODES_FILE: &str = "diagnosis_modes.parquet";

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

/// The report's inputs in a work directory: where they are, which are there, and the list the
/// manifest hashes (in the order it hashes them).
struct Sources {
    step1: PathBuf,
    step2: PathBuf,
    prop: PathBuf,
    has2: bool,
    step1_report: serde_json::Value,
    held_out: Vec<String>,
    pairs: PathBuf,
    /// Step 2's update_report.json when step 2 ran without a posterior.
    step2_note: Option<PathBuf>,
    ingest_report: PathBuf,
    specimens: PathBuf,
    diag_json: PathBuf,
    diag_modes: PathBuf,
    has_diag: bool,
    /// The plots to copy, with the stage that drew them.
    plots: Vec<(&'static str, PathBuf)>,
    /// Manifests of every stage (provenance).
    manifests: Vec<PathBuf>,
    inputs: Vec<PathBuf>,
}

/// Locate the inputs of the report of work directory `w`; an error when a required one is
/// missing.
fn locate(w: &Path) -> anyhow::Result<Sources> {
    let step1 = w.join("update_boards");
    let step2 = w.join("update_joints");
    let prop = w.join("propagate");
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
    for d in [
        "ingest",
        "extract",
        "pair",
        "fe",
        "update_boards",
        "update_joints",
        "propagate",
        "diagnose",
    ] {
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

/// The measured frequencies (both steps' residuals, and the held-out boards' pairs), step 2's
/// data, or why there is none.
fn read_measurements(
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
    if !src.held_out.is_empty() {
        let roles: BTreeMap<(String, String), bool> = measured
            .iter()
            .map(|m| ((m.setup.clone(), m.label.clone()), m.used_for_updating))
            .collect();
        measured.extend(read_held_out(&src.pairs, &src.held_out, &roles)?);
    }
    Ok((measured, step2_data, step2_absent))
}

/// The provenance of every stage manifest that reads.
fn provenance(manifests: &[PathBuf], w: &Path) -> Vec<Provenance> {
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
fn copy_plots(
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

/// Say the free-free coverage of the 90 % intervals on stderr; the manifest's summary.
fn summarise(iv: &[Interval], figures: usize, has2: bool) -> BTreeMap<String, serde_json::Value> {
    let cov = |scope: &str, upd: Option<bool>| {
        validation::coverage(iv.iter().filter(|i| {
            i.scope == scope && i.setup == "free" && upd.is_none_or(|u| i.used_for_updating == u)
        }))
    };
    let (vk, vn) = cov("board", Some(false));
    let (nk, nn) = cov("new_board", None);
    let (hk, hn) = validation::held_out_coverage(
        iv.iter()
            .filter(|i| i.scope == "new_board" && i.setup == "free"),
    );
    eprintln!(
        "report: {} figures; free-free coverage of the 90 % intervals: validation modes {vk}/{vn}, new board {nk}/{nn}{}{}",
        figures,
        if hn > 0 {
            format!(", held-out boards by the new board {hk}/{hn}")
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
    s
}

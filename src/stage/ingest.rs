//! Stage `ingest`: a measurement campaign directory → `campaign.mcap` + Parquet tables + report.
//!
//! Reads the contract of `campaign-format.md`: the sheet, one UFF per measurement, and the
//! balance logs. Cross-checks them (every sheet row has its file, every UFF is in the sheet,
//! every board weighed, scan points consistent within a setup, unique ids), converts to SI,
//! and writes flat tables. One bad measurement never sinks the campaign: it is quarantined
//! (listed in `measurements.parquet` with its reason, no FRF rows) and the run exits with
//! [`exit::QUARANTINED`]. Nothing is silently dropped: every dropped record and every ignored
//! file is a finding in `ingest_report.json` and summarised on stderr.

use crate::findings::{Finding, Findings, Severity};
use crate::io::balance_log::{self, BoardMass, MassParams, Reading};
use crate::io::manifest::{self, StageSpec};
use crate::io::mcap_writer::{
    BalanceMsg, CampaignMcap, FunctionMsg, PointMsg, ScanPointsMsg, SheetMsg,
};
use crate::io::sheet::{self, Setup, SheetRow};
use crate::io::tables::{self, TableSpec};
use crate::io::uff::{self, Abscissa, Dataset, FunctionType, Ordinate};
use crate::stage::{exit, StageOutcome, StageResult};
use anyhow::{bail, Context};
use arrow::array::{
    ArrayRef, BooleanArray, Float64Array, Float64Builder, Int32Array, Int64Array, ListBuilder,
    StringArray,
};
use arrow::datatypes::{DataType, Field};
use rayon::prelude::*;
use serde::Serialize;
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Tunable checks of the ingest stage (part of the fingerprint).
#[derive(Debug, Clone, Serialize)]
pub struct IngestConfig {
    /// Balance-spread flag: std of stable readings above this many resolution steps.
    pub mass_max_std_in_d: f64,
    /// Two scan points with the same node id in two measurements of one setup are "the same
    /// point" when within this distance; beyond it the grids are reported inconsistent.
    pub scan_point_tolerance_m: f64,
}

impl Default for IngestConfig {
    fn default() -> Self {
        IngestConfig {
            mass_max_std_in_d: MassParams::default().max_std_in_d,
            scan_point_tolerance_m: 0.5e-3,
        }
    }
}

/// Names of the files the stage writes into its output directory.
pub const OUTPUTS: [&str; 7] = [
    "measurements.parquet",
    "scan_points.parquet",
    "frf.parquet",
    "scale_readings.parquet",
    "masses.parquet",
    "campaign.mcap",
    "ingest_report.json",
];
pub const MANIFEST: &str = "ingest.manifest.json";
/// Version of the output layout (2: frf.parquet's axis as start + step, not a list per row).
pub const OUTPUT_LAYOUT: u32 = 2;

/// One function record, SI units, evenly spaced axis.
#[derive(Debug, Clone)]
pub struct Record {
    pub node: i64,
    pub function_type: i32,
    pub response_direction: i32,
    pub reference_node: i64,
    pub reference_direction: i32,
    pub ordinate_unit: &'static str,
    pub freq_start_hz: f64,
    pub freq_step_hz: f64,
    pub re: Vec<f64>,
    pub im: Option<Vec<f64>>,
}

/// One scan point, metres.
#[derive(Debug, Clone, PartialEq)]
pub struct Point {
    pub node: i64,
    pub xyz_m: [f64; 3],
    pub is_reference: bool,
    pub has_record: bool,
}

/// One measurement after ingest.
#[derive(Debug, Clone)]
pub struct Measurement {
    pub row: SheetRow,
    /// `Some(reason)` when quarantined.
    pub quarantine: Option<String>,
    pub uff_blake3: Option<String>,
    pub points: Vec<Point>,
    pub records: Vec<Record>,
    pub coherence: Vec<Record>,
    pub dropped: usize,
}

impl Measurement {
    fn new(row: SheetRow) -> Self {
        Measurement {
            row,
            quarantine: None,
            uff_blake3: None,
            points: vec![],
            records: vec![],
            coherence: vec![],
            dropped: 0,
        }
    }
    fn reference_node(&self) -> Option<i64> {
        self.records.first().map(|r| r.reference_node)
    }
    fn n_scan_points(&self) -> usize {
        self.points
            .iter()
            .filter(|p| !p.is_reference || p.has_record)
            .count()
    }
}

/// Everything read from a campaign, before writing.
#[derive(Debug, Default)]
pub struct Campaign {
    pub name: String,
    pub measurements: Vec<Measurement>,
    pub readings: Vec<Reading>,
    pub masses: Vec<BoardMass>,
    pub findings: Findings,
    /// Extra sheet columns, in header order.
    pub extra_columns: Vec<String>,
}

fn rel(p: &Path, base: &Path) -> String {
    manifest::rel_path(p, base)
}

/// Recursively list regular files under `dir`, sorted.
fn list_files(dir: &Path) -> std::io::Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d)? {
            let e = e?;
            let ft = e.file_type()?;
            let name = e.file_name();
            if name.to_string_lossy().starts_with('.') {
                continue;
            }
            if ft.is_dir() {
                stack.push(e.path());
            } else if ft.is_file() {
                out.push(e.path());
            }
        }
    }
    out.sort();
    Ok(out)
}

/// The campaign directory and its sheet exist; else a clear error naming what is missing.
fn check_campaign_dir(dir: &Path) -> anyhow::Result<()> {
    if !dir.is_dir() {
        bail!(
            "campaign directory {} does not exist or is not a directory",
            dir.display()
        );
    }
    let sheet_path = dir.join("campaign.csv");
    if !sheet_path.is_file() {
        bail!(
            "{}: no measurement sheet (expected campaign.csv in the campaign directory; see campaign-format.md)",
            dir.display()
        );
    }
    Ok(())
}

/// The files that determine the stage's outputs: the sheet, every file it names that exists,
/// and every balance log. Fails with a clear message when the campaign cannot be read at all.
pub fn discover_inputs(dir: &Path) -> anyhow::Result<Vec<PathBuf>> {
    check_campaign_dir(dir)?;
    let sheet_path = dir.join("campaign.csv");
    let mut inputs: BTreeSet<PathBuf> = BTreeSet::new();
    inputs.insert(sheet_path.clone());
    let bytes = std::fs::read(&sheet_path)
        .with_context(|| format!("cannot read {}", sheet_path.display()))?;
    if let Ok(s) = sheet::parse(&bytes, "campaign.csv") {
        for r in &s.rows {
            let p = dir.join(&r.file);
            if !r.file.is_empty() && p.is_file() {
                inputs.insert(p);
            }
        }
    }
    for sub in ["vibrometer", "scale"] {
        let d = dir.join(sub);
        if d.is_dir() {
            inputs.extend(list_files(&d)?);
        }
    }
    Ok(inputs.into_iter().collect())
}

/// Read, parse and cross-check a campaign. Fatal only when nothing can be read (no sheet, a
/// sheet without required columns, no measurement at all).
pub fn read_campaign(dir: &Path, cfg: &IngestConfig) -> anyhow::Result<Campaign> {
    check_campaign_dir(dir)?;
    let name = dir
        .canonicalize()
        .ok()
        .and_then(|p| p.file_name().map(|n| n.to_string_lossy().into_owned()))
        .unwrap_or_else(|| "campaign".into());
    let mut findings = Findings::default();
    let sheet_bytes = std::fs::read(dir.join("campaign.csv"))?;
    let sheet = sheet::parse(&sheet_bytes, "campaign.csv")?;
    findings.extend(sheet.findings.clone());
    if sheet.rows.is_empty() {
        bail!(
            "{}: empty campaign: campaign.csv has a header but no measurement rows",
            dir.display()
        );
    }

    // Row-level checks: ids, setup, file.
    let mut measurements: Vec<Measurement> =
        sheet.rows.iter().cloned().map(Measurement::new).collect();
    let mut first_line: HashMap<String, u64> = HashMap::new();
    for m in &mut measurements {
        let row = &m.row;
        let f = |code: &str, msg: String| {
            Finding::new(Severity::Quarantined, code, msg)
                .file("campaign.csv")
                .line(row.line)
                .measurement(row.measurement_id.clone())
        };
        let reason = if row.measurement_id.is_empty() {
            Some(f(
                "sheet.empty_id",
                "measurement_id is empty (expected a unique id)".into(),
            ))
        } else if let Some(l) = first_line.get(&row.measurement_id) {
            Some(f(
                "sheet.duplicate_id",
                format!(
                    "duplicate measurement_id {:?} (first used on line {l}); this row is quarantined",
                    row.measurement_id
                ),
            ))
        } else if row.board_id.is_empty() {
            Some(f(
                "sheet.empty_board",
                "board_id is empty (expected the specimen id)".into(),
            ))
        } else if row.setup.is_none() {
            Some(f(
                "sheet.unknown_setup",
                format!(
                    "setup: expected `free` or `bolted`, found {:?}",
                    row.setup_raw
                ),
            ))
        } else if row.file.is_empty() {
            Some(f(
                "sheet.empty_file",
                "file is empty (expected the UFF path)".into(),
            ))
        } else if !dir.join(&row.file).is_file() {
            Some(f(
                "sheet.missing_file",
                format!(
                    "file {:?} does not exist in the campaign directory",
                    row.file
                ),
            ))
        } else {
            None
        };
        if !row.measurement_id.is_empty() {
            first_line
                .entry(row.measurement_id.clone())
                .or_insert(row.line);
        }
        if let Some(fd) = reason {
            m.quarantine = Some(fd.message.clone());
            findings.push(fd);
        }
    }

    // UFF files, in parallel; results collected in sheet order (deterministic).
    let pb = crate::stage::progress_bar(measurements.len() as u64, "UFF files");
    let per_meas: Vec<Findings> = measurements
        .par_iter_mut()
        .map(|m| {
            let out = if m.quarantine.is_none() {
                read_measurement(dir, m)
            } else {
                Findings::default()
            };
            pb.inc(1);
            out
        })
        .collect();
    pb.finish_and_clear();
    for f in per_meas {
        findings.extend(f);
    }

    // Files nobody asked for.
    let named: BTreeSet<PathBuf> = measurements
        .iter()
        .map(|m| normalize(&dir.join(&m.row.file)))
        .collect();
    for p in list_files(dir)? {
        let r = rel(&p, dir);
        if r == "campaign.csv" || named.contains(&normalize(&p)) {
            continue;
        }
        if r.starts_with("scale/") && r.ends_with(".log") {
            continue;
        }
        if r.starts_with("vibrometer/") && r.to_ascii_lowercase().ends_with(".uff") {
            findings.push(
                Finding::new(
                    Severity::Warning,
                    "campaign.uff_not_in_sheet",
                    "UFF file is not named by any row of campaign.csv (expected every vibrometer file in the sheet); not ingested",
                )
                .file(r),
            );
        } else {
            findings.push(
                Finding::new(
                    Severity::Info,
                    "campaign.ignored_file",
                    "not part of the campaign contract; ignored",
                )
                .file(r),
            );
        }
    }

    check_scan_point_consistency(&measurements, cfg, &mut findings);

    // Balance logs.
    let mut readings = Vec::new();
    let scale_dir = dir.join("scale");
    if scale_dir.is_dir() {
        for p in list_files(&scale_dir)? {
            let r = rel(&p, dir);
            if !r.ends_with(".log") {
                continue;
            }
            let bytes = std::fs::read(&p).with_context(|| format!("cannot read {r}"))?;
            let (rs, f) = balance_log::parse(&bytes, &r);
            readings.extend(rs);
            findings.extend(f);
        }
    }
    let masses = balance_log::board_masses(
        &readings,
        MassParams {
            max_std_in_d: cfg.mass_max_std_in_d,
        },
    );
    let weighed: BTreeSet<&str> = masses.iter().map(|m| m.board_id.as_str()).collect();
    let boards: BTreeSet<&str> = measurements
        .iter()
        .map(|m| m.row.board_id.as_str())
        .filter(|b| !b.is_empty())
        .collect();
    for b in &boards {
        if !weighed.contains(b) {
            findings.push(Finding::new(
                Severity::Warning,
                "balance.board_not_weighed",
                format!("board {b} has no stable balance reading in scale/*.log (expected every board weighed)"),
            ));
        }
    }
    for m in &masses {
        if !boards.contains(m.board_id.as_str()) {
            findings.push(Finding::new(
                Severity::Info,
                "balance.unknown_board",
                format!(
                    "board {} was weighed but has no measurement in the sheet",
                    m.board_id
                ),
            ));
        }
        if m.inconsistent {
            findings.push(Finding::new(
                Severity::Warning,
                "balance.inconsistent_readings",
                format!(
                    "board {}: {} stable readings spread {:.4} g (std), more than {} x the balance resolution {:.4} g",
                    m.board_id, m.n_stable, m.std_g, cfg.mass_max_std_in_d, m.resolution_g
                ),
            ));
        }
    }
    Ok(Campaign {
        name,
        measurements,
        readings,
        masses,
        findings,
        extra_columns: sheet.extra_columns,
    })
}

fn normalize(p: &Path) -> PathBuf {
    p.canonicalize().unwrap_or_else(|_| p.to_path_buf())
}

/// Unit conversion of one function record's ordinate, file units → SI.
fn ordinate_factor(f: &uff::Function58, units: Option<&uff::Units164>) -> f64 {
    let Some(u) = units else { return 1.0 };
    let num = &f.ordinate_axis;
    let den = &f.denominator_axis;
    let le = (num.length_exp - den.length_exp) as i32;
    let fe = (num.force_exp - den.force_exp) as i32;
    // SI = value / (L^le · F^fe), UFF factors divide.
    1.0 / (u.length_factor.powi(le) * u.force_factor.powi(fe))
}

/// Parse one measurement's UFF and fill `m`; returns its findings. Quarantines on fatal issues.
fn read_measurement(dir: &Path, m: &mut Measurement) -> Findings {
    let mut fd = Findings::default();
    let file = m.row.file.clone();
    let mid = m.row.measurement_id.clone();
    let setup = m.row.setup.expect("checked before");
    let path = dir.join(&file);
    let quarantine = |m: &mut Measurement, fd: &mut Findings, code: &str, msg: String| {
        fd.push(
            Finding::new(Severity::Quarantined, code, msg.clone())
                .file(file.clone())
                .measurement(mid.clone()),
        );
        m.quarantine = Some(msg);
    };
    let bytes = match std::fs::read(&path) {
        Ok(b) => b,
        Err(e) => {
            quarantine(
                m,
                &mut fd,
                "uff.unreadable",
                format!("cannot read file: {e}"),
            );
            return fd;
        }
    };
    m.uff_blake3 = Some(blake3::hash(&bytes).to_hex().to_string());
    let parsed = match uff::parse(&bytes) {
        Ok(p) => p,
        Err(e) => {
            quarantine(m, &mut fd, "uff.not_uff", e.to_string());
            return fd;
        }
    };
    for iss in &parsed.issues {
        fd.push(
            Finding::new(
                Severity::RecordDropped,
                "uff.bad_dataset",
                format!("{}; dataset dropped", iss.kind),
            )
            .file(file.clone())
            .line(iss.line as u64)
            .record(format!(
                "dataset {} #{}",
                iss.number.map_or("?".into(), |n| n.to_string()),
                iss.index
            ))
            .measurement(mid.clone()),
        );
        m.dropped += 1;
    }
    for s in &parsed.skipped {
        fd.push(
            Finding::new(
                Severity::Info,
                "uff.skipped_dataset",
                format!("dataset {} is not used by hbmu; skipped", s.number),
            )
            .file(file.clone())
            .line(s.line as u64)
            .record(format!("dataset {} #{}", s.number, s.index))
            .measurement(mid.clone()),
        );
    }
    let units = parsed.datasets.iter().find_map(|d| match d {
        Dataset::Units(u) => Some(u.clone()),
        _ => None,
    });
    let to_m = |v: f64| match &units {
        Some(u) => u.length_to_metres(v),
        None => v * 1e-3, // contract: millimetres without dataset 164
    };
    // Nodes: merged over all node datasets; a repeated id with other coordinates is reported.
    let mut nodes: BTreeMap<i64, [f64; 3]> = BTreeMap::new();
    for d in &parsed.datasets {
        if let Dataset::Nodes(ns) = d {
            for n in &ns.nodes {
                let xyz = n.xyz_file_units.map(to_m);
                if let Some(old) = nodes.insert(n.id, xyz) {
                    if old != xyz {
                        fd.push(
                            Finding::new(
                                Severity::Warning,
                                "uff.node_redefined",
                                format!("node {} defined twice with different coordinates; the later definition is used", n.id),
                            )
                            .file(file.clone())
                            .line(ns.line as u64)
                            .measurement(mid.clone()),
                        );
                    }
                }
            }
        }
    }
    if nodes.is_empty() {
        quarantine(
            m,
            &mut fd,
            "uff.no_geometry",
            "no scan-point geometry (expected dataset 2411 or 15 with the scan points)".into(),
        );
        return fd;
    }

    let expected_type = setup.expected_function_type();
    let mut axis: Option<(f64, f64, usize)> = None;
    let mut seen: BTreeSet<(i64, i32)> = BTreeSet::new();
    let mut ref_count: BTreeMap<i64, usize> = BTreeMap::new();
    for d in &parsed.datasets {
        let Dataset::Function(f) = d else { continue };
        let ft = f.function_type.code() as i32;
        let loc = format!("dataset 58 at line {} (node {})", f.line, f.response_node);
        let mut drop = |fd: &mut Findings, code: &str, msg: String| {
            fd.push(
                Finding::new(
                    Severity::RecordDropped,
                    code,
                    format!("{msg}; record dropped"),
                )
                .file(file.clone())
                .line(f.line as u64)
                .record(loc.clone())
                .measurement(mid.clone()),
            );
            m.dropped += 1;
        };
        let is_coh = f.function_type == FunctionType::Coherence;
        if !is_coh && ft != expected_type {
            let what = match f.function_type {
                FunctionType::Frf | FunctionType::Transmissibility => "does not match the setup",
                _ => "is not one the contract knows",
            };
            drop(
                &mut fd,
                "uff.function_type",
                format!(
                    "function type {ft} {what} (expected {expected_type} for setup `{}`, or 6 coherence)",
                    setup.as_str()
                ),
            );
            continue;
        }
        let mut sign = 1.0;
        match f.response_direction {
            3 => {}
            -3 => {
                sign = -1.0;
                fd.push(
                    Finding::new(
                        Severity::Info,
                        "uff.direction_flipped",
                        "response direction -Z; ordinate negated to +Z",
                    )
                    .file(file.clone())
                    .line(f.line as u64)
                    .record(loc.clone())
                    .measurement(mid.clone()),
                );
            }
            d => {
                drop(
                    &mut fd,
                    "uff.direction",
                    format!("response direction {d} (expected 3 = +Z)"),
                );
                continue;
            }
        }
        if !nodes.contains_key(&f.response_node) {
            drop(
                &mut fd,
                "uff.unknown_node",
                format!(
                    "response node {} has no coordinates in dataset 2411/15",
                    f.response_node
                ),
            );
            continue;
        }
        let (min, inc) = match &f.abscissa {
            Abscissa::Even { min, increment } => (*min, *increment),
            Abscissa::Uneven(_) => {
                drop(
                    &mut fd,
                    "uff.uneven_abscissa",
                    "abscissa is unevenly spaced (expected evenly spaced frequency lines)".into(),
                );
                continue;
            }
        };
        let n = f.ordinate.len();
        if !(inc.is_finite() && inc > 0.0 && min.is_finite() && min >= 0.0) || n < 2 {
            drop(
                &mut fd,
                "uff.bad_abscissa",
                format!("abscissa start {min} Hz, step {inc} Hz, {n} lines (expected start >= 0, step > 0, >= 2 lines)"),
            );
            continue;
        }
        if !is_coh {
            match axis {
                None => axis = Some((min, inc, n)),
                Some((a0, da, na)) => {
                    let same = na == n
                        && (a0 - min).abs() <= 1e-9 * da.max(1.0)
                        && (da - inc).abs() <= 1e-9 * da;
                    if !same {
                        drop(
                            &mut fd,
                            "uff.axis_mismatch",
                            format!("frequency axis {min} Hz + k*{inc} Hz, {n} lines differs from the measurement's first record ({a0} Hz + k*{da} Hz, {na} lines)"),
                        );
                        continue;
                    }
                }
            }
        }
        if !seen.insert((f.response_node, ft)) {
            drop(
                &mut fd,
                "uff.duplicate_record",
                format!(
                    "second record of function type {ft} for node {} (the first is kept)",
                    f.response_node
                ),
            );
            continue;
        }
        let factor = sign
            * if is_coh {
                1.0
            } else {
                ordinate_factor(f, units.as_ref())
            };
        let (re, im) = match (&f.ordinate, is_coh) {
            (Ordinate::Complex { re, im }, false) => (
                re.iter().map(|v| v * factor).collect(),
                Some(im.iter().map(|v| v * factor).collect()),
            ),
            (Ordinate::Real(v), true) => (v.clone(), None),
            (Ordinate::Real(_), false) => {
                drop(
                    &mut fd,
                    "uff.real_ordinate",
                    format!("function type {ft} has a real ordinate (expected complex)"),
                );
                continue;
            }
            (Ordinate::Complex { re, im }, true) => {
                // Coherence is real by definition; some writers store it as complex with a
                // zero imaginary part. Keep the real part, and say so.
                let max_im = im.iter().fold(0.0f64, |a, v| a.max(v.abs()));
                fd.push(
                    Finding::new(
                        Severity::Info,
                        "uff.complex_coherence",
                        format!("coherence stored as complex (max |imag| = {max_im:.3e}); real part used"),
                    )
                    .file(file.clone())
                    .line(f.line as u64)
                    .record(loc.clone())
                    .measurement(mid.clone()),
                );
                (re.clone(), None)
            }
        };
        if !is_coh {
            *ref_count.entry(f.reference_node).or_default() += 1;
        }
        let rec = Record {
            node: f.response_node,
            function_type: ft,
            response_direction: 3,
            reference_node: f.reference_node,
            reference_direction: f.reference_direction as i32,
            ordinate_unit: match ft {
                4 => "m/s/N",
                _ => "1",
            },
            freq_start_hz: min,
            freq_step_hz: inc,
            re,
            im,
        };
        if is_coh {
            m.coherence.push(rec);
        } else {
            m.records.push(rec);
        }
    }
    if m.records.is_empty() {
        quarantine(
            m,
            &mut fd,
            "uff.no_records",
            format!(
                "no usable response record (expected dataset 58 records of function type {expected_type})"
            ),
        );
        return fd;
    }
    // Coherence on another axis than the response records is of no use.
    if let Some((a0, da, na)) = axis {
        let before = m.coherence.len();
        m.coherence.retain(|c| {
            c.re.len() == na
                && (c.freq_start_hz - a0).abs() <= 1e-9 * da.max(1.0)
                && (c.freq_step_hz - da).abs() <= 1e-9 * da
        });
        let lost = before - m.coherence.len();
        if lost > 0 {
            m.dropped += lost;
            fd.push(
                Finding::new(
                    Severity::RecordDropped,
                    "uff.coherence_axis",
                    format!("{lost} coherence record(s) on another frequency axis than the response records; dropped"),
                )
                .file(file.clone())
                .measurement(mid.clone()),
            );
        }
    }
    let main_ref = ref_count
        .iter()
        .max_by_key(|(node, n)| (**n, -**node))
        .map(|(node, _)| *node)
        .expect("records non-empty");
    if ref_count.len() > 1 {
        fd.push(
            Finding::new(
                Severity::Warning,
                "uff.mixed_reference",
                format!("records use {} different reference nodes ({:?}); expected one reference per measurement", ref_count.len(), ref_count.keys().collect::<Vec<_>>()),
            )
            .file(file.clone())
            .measurement(mid.clone()),
        );
    }
    // Put the main reference first so `reference_node()` reports it.
    m.records
        .sort_by_key(|r| (r.reference_node != main_ref, r.node));
    m.coherence.sort_by_key(|r| r.node);
    let with_record: BTreeSet<i64> = m.records.iter().map(|r| r.node).collect();
    if !nodes.contains_key(&main_ref) {
        fd.push(
            Finding::new(
                Severity::Warning,
                "uff.reference_without_geometry",
                format!("reference node {main_ref} has no coordinates in dataset 2411/15"),
            )
            .file(file.clone())
            .measurement(mid.clone()),
        );
    }
    m.points = nodes
        .iter()
        .map(|(&node, &xyz_m)| Point {
            node,
            xyz_m,
            is_reference: node == main_ref,
            has_record: with_record.contains(&node),
        })
        .collect();
    let no_record = m
        .points
        .iter()
        .filter(|p| !p.is_reference && !p.has_record)
        .count();
    if no_record > 0 {
        fd.push(
            Finding::new(
                Severity::Info,
                "uff.points_without_record",
                format!("{no_record} scan point(s) have no response record (marked invalid by the vibrometer, or dropped)"),
            )
            .file(file)
            .measurement(mid),
        );
    }
    fd
}

/// Within one setup, the same node id must sit at the same place in every measurement, and the
/// grids should match. Compared with the first good measurement of the setup (sheet order).
fn check_scan_point_consistency(ms: &[Measurement], cfg: &IngestConfig, fd: &mut Findings) {
    for setup in [Setup::Free, Setup::Bolted] {
        let good: Vec<&Measurement> = ms
            .iter()
            .filter(|m| m.quarantine.is_none() && m.row.setup == Some(setup))
            .collect();
        let Some(first) = good.first() else { continue };
        let grid = |m: &Measurement| -> BTreeMap<i64, [f64; 3]> {
            m.points
                .iter()
                .filter(|p| !p.is_reference)
                .map(|p| (p.node, p.xyz_m))
                .collect()
        };
        let g0 = grid(first);
        for m in good.iter().skip(1) {
            let g = grid(m);
            let moved: Vec<i64> = g
                .iter()
                .filter_map(|(n, p)| {
                    let q = g0.get(n)?;
                    let d = ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2))
                        .sqrt();
                    (d > cfg.scan_point_tolerance_m).then_some(*n)
                })
                .collect();
            let only_here = g.keys().filter(|n| !g0.contains_key(n)).count();
            let missing = g0.keys().filter(|n| !g.contains_key(n)).count();
            if !moved.is_empty() || only_here > 0 || missing > 0 {
                fd.push(
                    Finding::new(
                        Severity::Warning,
                        "campaign.scan_grid_inconsistent",
                        format!(
                            "scan points differ from measurement {} of the same setup `{}`: {} node(s) moved by more than {:.1} mm (e.g. {:?}), {} extra, {} missing",
                            first.row.measurement_id,
                            setup.as_str(),
                            moved.len(),
                            cfg.scan_point_tolerance_m * 1e3,
                            moved.iter().take(5).collect::<Vec<_>>(),
                            only_here,
                            missing
                        ),
                    )
                    .file(m.row.file.clone())
                    .measurement(m.row.measurement_id.clone()),
                );
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Writing.

fn provenance(campaign: &Campaign, fingerprint: &str) -> BTreeMap<String, String> {
    BTreeMap::from([
        ("hbmu.campaign".to_string(), campaign.name.clone()),
        ("hbmu.stage".to_string(), "ingest".to_string()),
        ("hbmu.fingerprint".to_string(), fingerprint.to_string()),
        (
            "hbmu.version".to_string(),
            manifest::TOOL_VERSION.to_string(),
        ),
    ])
}

fn strs<I: IntoIterator<Item = Option<S>>, S: AsRef<str>>(it: I) -> ArrayRef {
    Arc::new(StringArray::from_iter(it))
}
fn f64s<I: IntoIterator<Item = Option<f64>>>(it: I) -> ArrayRef {
    Arc::new(Float64Array::from_iter(it))
}
fn i64s<I: IntoIterator<Item = Option<i64>>>(it: I) -> ArrayRef {
    Arc::new(Int64Array::from_iter(it))
}
fn i32s<I: IntoIterator<Item = Option<i32>>>(it: I) -> ArrayRef {
    Arc::new(Int32Array::from_iter(it))
}
fn bools<I: IntoIterator<Item = Option<bool>>>(it: I) -> ArrayRef {
    Arc::new(BooleanArray::from_iter(it))
}

fn write_table(
    path: &Path,
    spec: &TableSpec,
    prov: &BTreeMap<String, String>,
    extra: &[Field],
    cols: Vec<ArrayRef>,
) -> anyhow::Result<()> {
    let schema = spec.schema(extra, &tables::table_metadata(spec, prov));
    let b = tables::batch(schema, cols)?;
    tables::write_parquet(path, &b).with_context(|| format!("writing {}", path.display()))
}

fn write_measurements(
    c: &Campaign,
    extra_cols: &[String],
    path: &Path,
    prov: &BTreeMap<String, String>,
) -> anyhow::Result<()> {
    let ms = &c.measurements;
    let axis = |m: &Measurement| {
        m.records
            .first()
            .map(|r| (r.freq_start_hz, r.freq_step_hz, r.re.len()))
    };
    let mut cols: Vec<ArrayRef> = vec![
        strs(ms.iter().map(|m| Some(m.row.measurement_id.as_str()))),
        strs(ms.iter().map(|m| Some(m.row.board_id.as_str()))),
        strs(ms.iter().map(|m| {
            Some(
                m.row
                    .setup
                    .map(|s| s.as_str().to_string())
                    .unwrap_or_else(|| m.row.setup_raw.clone()),
            )
        })),
        strs(ms.iter().map(|m| Some(m.row.file.as_str()))),
        strs(ms.iter().map(|m| m.row.bolt_set.as_deref())),
        f64s(ms.iter().map(|m| m.row.torque_nm)),
        f64s(ms.iter().map(|m| m.row.temperature_c)),
        strs(ms.iter().map(|m| m.row.date.as_deref())),
        i64s(ms.iter().map(|m| m.row.date_unix_ns)),
        strs(ms.iter().map(|m| m.row.operator.as_deref())),
        strs(ms.iter().map(|m| m.row.notes.as_deref())),
        i64s(ms.iter().map(|m| Some(m.row.line as i64))),
        strs(ms.iter().map(|m| {
            Some(if m.quarantine.is_some() {
                "quarantined"
            } else {
                "ok"
            })
        })),
        strs(ms.iter().map(|m| m.quarantine.as_deref())),
        i32s(
            ms.iter()
                .map(|m| m.records.first().map(|r| r.function_type)),
        ),
        i64s(ms.iter().map(|m| m.reference_node())),
        i32s(ms.iter().map(|m| Some(m.n_scan_points() as i32))),
        i32s(ms.iter().map(|m| Some(m.records.len() as i32))),
        i32s(ms.iter().map(|m| Some(m.coherence.len() as i32))),
        i32s(ms.iter().map(|m| Some(m.dropped as i32))),
        f64s(ms.iter().map(|m| axis(m).map(|a| a.0))),
        f64s(ms.iter().map(|m| axis(m).map(|a| a.1))),
        i32s(ms.iter().map(|m| axis(m).map(|a| a.2 as i32))),
        strs(ms.iter().map(|m| m.uff_blake3.as_deref())),
    ];
    let own: BTreeSet<&str> = tables::MEASUREMENTS
        .columns
        .iter()
        .map(|c| c.name)
        .collect();
    let mut extra_fields = Vec::new();
    for name in extra_cols {
        let col_name = if own.contains(name.as_str()) {
            format!("sheet_{name}")
        } else {
            name.clone()
        };
        extra_fields.push(Field::new(col_name, DataType::Utf8, true));
        cols.push(strs(
            ms.iter().map(|m| m.row.extra.get(name).map(|s| s.as_str())),
        ));
    }
    write_table(path, &tables::MEASUREMENTS, prov, &extra_fields, cols)
}

fn list_f64<'a, I: IntoIterator<Item = Option<&'a [f64]>>>(it: I) -> ArrayRef {
    let mut b = ListBuilder::new(Float64Builder::new());
    for v in it {
        match v {
            Some(v) => {
                b.values().append_slice(v);
                b.append(true);
            }
            None => b.append(false),
        }
    }
    Arc::new(b.finish())
}

fn write_outputs(c: &Campaign, out: &Path, fingerprint: &str) -> anyhow::Result<Vec<PathBuf>> {
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let prov = provenance(c, fingerprint);
    let p = |n: &str| out.join(n);
    write_measurements(c, &c.extra_columns, &p("measurements.parquet"), &prov)?;

    // scan_points
    let pts: Vec<(&str, &Point)> = c
        .measurements
        .iter()
        .filter(|m| m.quarantine.is_none())
        .flat_map(|m| {
            m.points
                .iter()
                .map(move |p| (m.row.measurement_id.as_str(), p))
        })
        .collect();
    write_table(
        &p("scan_points.parquet"),
        &tables::SCAN_POINTS,
        &prov,
        &[],
        vec![
            strs(pts.iter().map(|(m, _)| Some(*m))),
            i64s(pts.iter().map(|(_, p)| Some(p.node))),
            f64s(pts.iter().map(|(_, p)| Some(p.xyz_m[0]))),
            f64s(pts.iter().map(|(_, p)| Some(p.xyz_m[1]))),
            f64s(pts.iter().map(|(_, p)| Some(p.xyz_m[2]))),
            bools(pts.iter().map(|(_, p)| Some(p.is_reference))),
            bools(pts.iter().map(|(_, p)| Some(p.has_record))),
        ],
    )?;

    // frf
    let recs: Vec<(&str, &Record)> = c
        .measurements
        .iter()
        .filter(|m| m.quarantine.is_none())
        .flat_map(|m| {
            m.records
                .iter()
                .chain(m.coherence.iter())
                .map(move |r| (m.row.measurement_id.as_str(), r))
        })
        .collect();
    // scale readings
    let rs = &c.readings;
    write_table(
        &p("scale_readings.parquet"),
        &tables::SCALE_READINGS,
        &prov,
        &[],
        vec![
            strs(rs.iter().map(|r| Some(r.file.as_str()))),
            i64s(rs.iter().map(|r| Some(r.line as i64))),
            strs(rs.iter().map(|r| r.timestamp.as_deref())),
            i64s(rs.iter().map(|r| r.time_unix_ns)),
            strs(rs.iter().map(|r| r.board_id.as_deref())),
            strs(rs.iter().map(|r| Some(r.response.as_str()))),
            strs(rs.iter().map(|r| Some(r.status.as_str()))),
            f64s(rs.iter().map(|r| r.value)),
            strs(rs.iter().map(|r| r.unit.as_deref())),
            f64s(rs.iter().map(|r| r.mass_g)),
            f64s(rs.iter().map(|r| r.resolution_g)),
        ],
    )?;

    // masses
    let ms = &c.masses;
    write_table(
        &p("masses.parquet"),
        &tables::MASSES,
        &prov,
        &[],
        vec![
            strs(ms.iter().map(|m| Some(m.board_id.as_str()))),
            f64s(ms.iter().map(|m| Some(m.mass_g))),
            i32s(ms.iter().map(|m| Some(m.n_stable as i32))),
            f64s(ms.iter().map(|m| Some(m.std_g))),
            f64s(ms.iter().map(|m| Some(m.resolution_g))),
            bools(ms.iter().map(|m| Some(m.inconsistent))),
        ],
    )?;

    // The two big outputs, the spectra table and the MCAP, are encoded side by side (each
    // file's bytes do not depend on the other, nor on the thread count).
    let t_big = std::time::Instant::now();
    let (frf, mcap) = rayon::join(
        || -> anyhow::Result<()> {
            write_table(
                &p("frf.parquet"),
                &tables::FRF,
                &prov,
                &[],
                vec![
                    strs(recs.iter().map(|(m, _)| Some(*m))),
                    i64s(recs.iter().map(|(_, r)| Some(r.node))),
                    i32s(recs.iter().map(|(_, r)| Some(r.function_type))),
                    i32s(recs.iter().map(|(_, r)| Some(r.response_direction))),
                    i64s(recs.iter().map(|(_, r)| Some(r.reference_node))),
                    i32s(recs.iter().map(|(_, r)| Some(r.reference_direction))),
                    strs(recs.iter().map(|(_, r)| Some(r.ordinate_unit))),
                    f64s(recs.iter().map(|(_, r)| Some(r.freq_start_hz))),
                    f64s(recs.iter().map(|(_, r)| Some(r.freq_step_hz))),
                    i32s(recs.iter().map(|(_, r)| Some(r.re.len() as i32))),
                    list_f64(recs.iter().map(|(_, r)| Some(r.re.as_slice()))),
                    list_f64(recs.iter().map(|(_, r)| r.im.as_deref())),
                ],
            )?;
            Ok(())
        },
        || write_mcap(c, &p("campaign.mcap"), &prov),
    );
    frf?;
    mcap?;
    log::debug(format_args!(
        "frf.parquet and campaign.mcap written in {:.2} s",
        t_big.elapsed().as_secs_f64()
    ));
    write_report(c, &p("ingest_report.json"), fingerprint)?;
    Ok(OUTPUTS.iter().map(|n| p(n)).collect())
}

/// Timing lines on stderr when `HBMU_TIMING` is set (benchmarks, profiling).
mod log {
    pub fn debug(args: std::fmt::Arguments) {
        if std::env::var_os("HBMU_TIMING").is_some() {
            eprintln!("timing: {args}");
        }
    }
}

/// JSON encoding behind a trait object, so one closure encodes any message type.
mod erased {
    pub trait Msg: Sync {
        fn json(&self) -> std::io::Result<Vec<u8>>;
    }
    impl<T: serde::Serialize + Sync> Msg for T {
        fn json(&self) -> std::io::Result<Vec<u8>> {
            serde_json::to_vec(self).map_err(std::io::Error::other)
        }
    }
}

fn write_mcap(c: &Campaign, path: &Path, prov: &BTreeMap<String, String>) -> anyhow::Result<()> {
    crate::io::atomic::write_file_with(path, |file| {
        let mut w = CampaignMcap::create(std::io::BufWriter::new(file), prov)?;
        for m in &c.measurements {
            let t = m.row.date_unix_ns.unwrap_or(0).max(0) as u64;
            w.write(
                "/sheet",
                t,
                &SheetMsg {
                    measurement_id: m.row.measurement_id.clone(),
                    board_id: m.row.board_id.clone(),
                    setup: m
                        .row
                        .setup
                        .map(|s| s.as_str().to_string())
                        .unwrap_or_else(|| m.row.setup_raw.clone()),
                    file: m.row.file.clone(),
                    bolt_set: m.row.bolt_set.clone(),
                    torque_nm: m.row.torque_nm,
                    temperature_c: m.row.temperature_c,
                    date: m.row.date.clone(),
                    operator: m.row.operator.clone(),
                    notes: m.row.notes.clone(),
                    extra: m.row.extra.clone(),
                    sheet_line: m.row.line,
                    status: if m.quarantine.is_some() {
                        "quarantined"
                    } else {
                        "ok"
                    }
                    .into(),
                    status_reason: m.quarantine.clone(),
                },
            )?;
        }
        // The spectra dominate the file: encode each measurement's messages in parallel,
        // then write them in sheet order (same bytes whatever the thread count).
        type Encoded<'a> = (u64, Vec<(&'a str, Vec<u8>)>);
        let encoded: Vec<std::io::Result<Encoded>> = c
            .measurements
            .par_iter()
            .filter(|m| m.quarantine.is_none())
            .map(|m| {
                let t = m.row.date_unix_ns.unwrap_or(0).max(0) as u64;
                let id = &m.row.measurement_id;
                let enc = |v: &dyn erased::Msg| v.json();
                let mut msgs = vec![(
                    "/scan_points",
                    enc(&ScanPointsMsg {
                        measurement_id: id.clone(),
                        points: m
                            .points
                            .iter()
                            .map(|p| PointMsg {
                                node: p.node,
                                x_m: p.xyz_m[0],
                                y_m: p.xyz_m[1],
                                z_m: p.xyz_m[2],
                                is_reference: p.is_reference,
                            })
                            .collect(),
                    })?,
                )];
                for (topic, recs) in [("/frf", &m.records), ("/coherence", &m.coherence)] {
                    for r in recs {
                        msgs.push((
                            topic,
                            enc(&FunctionMsg {
                                measurement_id: id.clone(),
                                node: r.node,
                                function_type: r.function_type,
                                response_direction: r.response_direction,
                                reference_node: r.reference_node,
                                reference_direction: r.reference_direction,
                                ordinate_unit: r.ordinate_unit.into(),
                                freq_start_hz: r.freq_start_hz,
                                freq_step_hz: r.freq_step_hz,
                                re: r.re.clone(),
                                im: r.im.clone().unwrap_or_default(),
                            })?,
                        ));
                    }
                }
                Ok((t, msgs))
            })
            .collect();
        for e in encoded {
            let (t, msgs) = e?;
            for (topic, data) in msgs {
                w.write_encoded(topic, t, &data)?;
            }
        }
        for r in &c.readings {
            w.write(
                "/balance",
                r.time_unix_ns.unwrap_or(0).max(0) as u64,
                &BalanceMsg {
                    file: r.file.clone(),
                    line: r.line,
                    timestamp: r.timestamp.clone(),
                    board_id: r.board_id.clone(),
                    response: r.response.clone(),
                    status: r.status.as_str().into(),
                    value: r.value,
                    unit: r.unit.clone(),
                    mass_g: r.mass_g,
                },
            )?;
        }
        for f in c.findings.iter() {
            w.write("/ingest/findings", 0, f)?;
        }
        w.finish()
    })
    .with_context(|| format!("writing {}", path.display()))
}

#[derive(Serialize)]
struct Report<'a> {
    campaign: &'a str,
    fingerprint: &'a str,
    measurements: usize,
    quarantined: Vec<QuarantineEntry<'a>>,
    counts: BTreeMap<String, usize>,
    findings: &'a [Finding],
}

#[derive(Serialize)]
struct QuarantineEntry<'a> {
    measurement_id: &'a str,
    file: &'a str,
    reason: &'a str,
}

fn severity_counts(f: &Findings) -> BTreeMap<String, usize> {
    let mut counts = BTreeMap::new();
    for x in f.iter() {
        *counts.entry(x.severity.to_string()).or_insert(0) += 1;
    }
    counts
}

fn write_report(c: &Campaign, path: &Path, fingerprint: &str) -> anyhow::Result<()> {
    let r = Report {
        campaign: &c.name,
        fingerprint,
        measurements: c.measurements.len(),
        quarantined: c
            .measurements
            .iter()
            .filter_map(|m| {
                m.quarantine.as_deref().map(|reason| QuarantineEntry {
                    measurement_id: &m.row.measurement_id,
                    file: &m.row.file,
                    reason,
                })
            })
            .collect(),
        counts: severity_counts(&c.findings),
        findings: &c.findings.0,
    };
    let mut bytes = serde_json::to_vec_pretty(&r)?;
    bytes.push(b'\n');
    crate::io::atomic::write_bytes(path, &bytes)
        .with_context(|| format!("writing {}", path.display()))
}

/// Options of `hbmu ingest`.
#[derive(Debug, Clone)]
pub struct IngestOptions {
    pub campaign: PathBuf,
    pub out: PathBuf,
    pub force: bool,
    pub config: IngestConfig,
}

/// Run the stage: skip when up to date, else read, check and write. Findings go to stderr
/// (summary always; each finding when `verbose`).
pub fn run(opts: &IngestOptions, verbose: bool) -> anyhow::Result<StageOutcome> {
    let inputs = discover_inputs(&opts.campaign)?;
    let spec = StageSpec {
        stage: "ingest".into(),
        inputs,
        input_base: opts.campaign.clone(),
        // The layout of the outputs is part of the configuration: a new layout reruns ingest.
        config: serde_json::json!({"checks": opts.config, "layout": OUTPUT_LAYOUT}),
        seed: None,
        manifest_path: opts.out.join(MANIFEST),
    };
    crate::stage::run(spec, opts.force, |prep| {
        let t0 = std::time::Instant::now();
        let campaign = read_campaign(&opts.campaign, &opts.config)?;
        let t_read = t0.elapsed().as_secs_f64();
        let outputs = write_outputs(&campaign, &opts.out, &prep.fingerprint)?;
        if verbose {
            eprintln!(
                "ingest: read and checked in {t_read:.2} s, outputs written in {:.2} s",
                t0.elapsed().as_secs_f64() - t_read
            );
        }
        let n_q = campaign
            .measurements
            .iter()
            .filter(|m| m.quarantine.is_some())
            .count();
        for f in campaign.findings.iter() {
            if verbose || f.severity >= Severity::Quarantined {
                eprintln!("{f}");
            }
        }
        eprintln!(
            "ingest {}: {} measurements, {} quarantined; {} (details in {})",
            campaign.name,
            campaign.measurements.len(),
            n_q,
            campaign.findings.summary(),
            opts.out.join("ingest_report.json").display()
        );
        let mut summary = BTreeMap::new();
        summary.insert("measurements".into(), campaign.measurements.len().into());
        summary.insert("quarantined".into(), n_q.into());
        summary.insert(
            "findings".into(),
            serde_json::to_value(severity_counts(&campaign.findings))?,
        );
        Ok(StageResult {
            outputs,
            exit_code: if n_q > 0 { exit::QUARANTINED } else { exit::OK },
            summary,
        })
    })
}

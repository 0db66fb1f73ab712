//! The campaign model and its cross-checks, pure: the sheet, one UFF per measurement and the
//! balance logs of `campaign-format.md`, read through a [`Source`] (names and bytes; the
//! directory behind it is `io::campaign_dir`), parsed, checked against each other (every sheet
//! row has its file, every UFF is in the sheet, every board weighed, scan points consistent
//! within a setup, unique ids) and converted to SI. One bad measurement never sinks the
//! campaign: it is quarantined with its reason. Nothing is silently dropped: every dropped
//! record and every ignored file is a [`Finding`]. The writers of the ingest outputs are in
//! `io::ingest_outputs`; the stage that wires both is `stage::ingest`.
//!
//! The board population is exactly the sheet's boards. IDs are compared by [`board_key`]
//! (case, spaces and separators, zero padding of numbers ignored):
//! - sheet rows spelling one board differently (`PCB-3` among `PCB-03`): resolved to the
//!   spelling most rows use, warning `sheet.board_id_variant`; if no spelling is the most
//!   used, each stays a board of its own, warning `sheet.board_id_ambiguous`;
//! - a balance-log ID equal to a sheet board: that board; one that matches exactly one sheet
//!   board by key: resolved to it, warning `balance.board_id_variant`; by key more than one:
//!   not joined to any, `balance.board_id_ambiguous` (record dropped from the masses);
//!   no sheet board at all: not a board (a check weight, a tray), info `balance.not_a_board`
//!   (warning `balance.unknown_board` when it looks like a board ID: same letters as a sheet
//!   board's). Its lines stay in `scale_readings.parquet` with no `sheet_board_id`; it has no
//!   row in `masses.parquet`. A check weight named by its mass (`REF-10G`) whose mean stable
//!   reading is off its nominal by more than the readings' allowed spread: warning
//!   `balance.check_weight_off`.
//!
//! Beyond the contract's mobility scans, a response record measured as accelerance or
//! receptance (or a transmissibility of other motions) is converted by (iω)^q and keeps what
//! it was in `measured_as`; a roving hammer (one response node, the reference moving) is read
//! by reciprocity. Mode sets (dataset 55: the modes a lab's modal software identified) are
//! read as [`VendorMode`]s: a measurement with no response record takes them as its modes
//! (extract passes them through); beside FRFs they are kept for comparison, with a warning.
//!
//! A row the lab marked invalid is quarantined (`sheet.marked_invalid`): its notes start with
//! `invalid` (any case, e.g. `INVALID - double hit, repeated as M013`), or an extra column
//! `valid` says `no`/`false`/`0`/`n`/`invalid`. A note `repeat of <id>` is checked against
//! the sheet (`sheet.repeat_of_unknown`, `sheet.repeat_of_valid`: both rows then kept).

use crate::findings::{Finding, Findings, Severity};
use crate::formats::balance_log::{self, BoardMass, MassParams, Reading};
use crate::formats::sheet::{self, Setup, SheetRow};
use crate::formats::uff::{self, Abscissa, Dataset, FunctionType, Ordinate};
use anyhow::{bail, Context};
use rayon::prelude::*;
use serde::Serialize;
use std::collections::{BTreeMap, BTreeSet, HashMap};

/// Where a campaign's files come from. The checks ask for names (relative to the campaign
/// root, `/` separators) and bytes; they never open paths.
pub trait Source: Sync {
    /// The campaign's name (its directory's name).
    fn name(&self) -> String;
    /// How to name the campaign in an error message (its directory).
    fn describe(&self) -> String;
    /// Every regular file except hidden ones, relative, sorted.
    fn list(&self) -> std::io::Result<Vec<String>>;
    /// `rel` names an existing regular file.
    fn is_file(&self, rel: &str) -> bool;
    /// The identity of the file `rel` names: equal for two names of one file (a symbolic link
    /// and its target); `rel` itself when unknown.
    fn identity(&self, rel: &str) -> String;
    /// The file's bytes.
    fn read(&self, rel: &str) -> std::io::Result<Vec<u8>>;
}

/// A scan point further than this from the board's plane z = 0 is not on the board, m (the
/// board is 1.6 mm thick and its top face may be the plane; a bolt head stands 2 mm or more).
const OFF_PLANE_M: f64 = 1.0e-3;

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

/// One function record, SI units, evenly spaced axis.
#[derive(Debug, Clone)]
pub struct Record {
    pub node: i64,
    pub function_type: i32,
    pub response_direction: i32,
    pub reference_node: i64,
    pub reference_direction: i32,
    /// What the record measured, numerator/denominator (`acceleration/force`, `velocity/velocity`,
    /// `coherence`, or `unspecified` when the file names no motion): the ordinate is converted
    /// to the contract's quantity (`ordinate_unit`).
    pub measured_as: String,
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

/// One mode of a mode set (dataset 55) as the lab's modal software identified it: its shape
/// along the response direction (+Z, or the set's scalar) at the nodes that have coordinates,
/// real-normalised like extract's (largest |component| = +1; a complex shape projected on
/// its principal direction first).
#[derive(Debug, Clone, PartialEq)]
pub struct VendorMode {
    /// 1-based line of the dataset's opening `-1` in its file.
    pub line: usize,
    /// The file's mode number (record 7), when given.
    pub mode_number: Option<i64>,
    /// 2 normal mode, 3 or 7 complex mode.
    pub analysis_type: i64,
    pub freq_hz: f64,
    pub damping_ratio: f64,
    /// Modal phase collinearity and mean phase deviation of the shape (1 and 0 for a real one).
    pub mpc: f64,
    pub mpd_deg: f64,
    /// Nodes ascending, aligned with `shape`.
    pub nodes: Vec<i64>,
    pub shape: Vec<f64>,
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
    /// Modes the lab's software identified (dataset 55), ascending in frequency. Extract
    /// passes them through for a measurement without response records; beside FRFs they are
    /// kept for comparison and extract identifies from the FRFs.
    pub vendor_modes: Vec<VendorMode>,
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
            vendor_modes: vec![],
            dropped: 0,
        }
    }
    /// The excitation reference node (of the first response record).
    pub fn reference_node(&self) -> Option<i64> {
        self.records.first().map(|r| r.reference_node)
    }
    /// Scan points with a response (the reference only when it has a record).
    pub fn n_scan_points(&self) -> usize {
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
    /// The sheet's boards with their measured dimensions (where the sheet gives them).
    pub specimens: Vec<Specimen>,
    pub findings: Findings,
    /// Extra sheet columns, in header order.
    pub extra_columns: Vec<String>,
}

/// Read, parse and cross-check a campaign. Fatal only when nothing can be read (no sheet, a
/// sheet without required columns, no measurement at all).
///
/// `on_file` is called once per UFF file read (a progress bar, or nothing).
pub fn read_campaign(
    src: &dyn Source,
    cfg: &IngestConfig,
    on_file: &(dyn Fn() + Sync),
) -> anyhow::Result<Campaign> {
    let name = src.name();
    let mut findings = Findings::default();
    let sheet_bytes = src
        .read("campaign.csv")
        .with_context(|| format!("{}: cannot read campaign.csv", src.describe()))?;
    let sheet = sheet::parse(&sheet_bytes, "campaign.csv")?;
    findings.extend(sheet.findings.clone());
    if sheet.rows.is_empty() {
        bail!(
            "{}: empty campaign: campaign.csv has a header but no measurement rows",
            src.describe()
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
        } else if !src.is_file(&row.file) {
            Some(f(
                "sheet.missing_file",
                format!(
                    "file {:?} does not exist in the campaign directory",
                    row.file
                ),
            ))
        } else {
            invalid_mark(row).map(|why| {
                f(
                    "sheet.marked_invalid",
                    format!("the lab marked this measurement invalid ({why}); not ingested, its UFF {:?} is left unread", row.file),
                )
            })
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

    check_repeats(&measurements, &mut findings);
    let boards = resolve_sheet_boards(&mut measurements, &mut findings);

    // UFF files, in parallel; results collected in sheet order (deterministic).
    let per_meas: Vec<Findings> = measurements
        .par_iter_mut()
        .map(|m| {
            let out = if m.quarantine.is_none() {
                read_measurement(src, m)
            } else {
                Findings::default()
            };
            on_file();
            out
        })
        .collect();
    for f in per_meas {
        findings.extend(f);
    }

    // Files nobody asked for.
    let named: BTreeSet<String> = measurements
        .iter()
        .map(|m| src.identity(&m.row.file))
        .collect();
    let files = src
        .list()
        .with_context(|| format!("cannot list {}", src.describe()))?;
    for r in files.iter().cloned() {
        if r == "campaign.csv" || named.contains(&src.identity(&r)) {
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
    for r in files
        .iter()
        .filter(|r| r.starts_with("scale/") && r.ends_with(".log"))
    {
        let bytes = src.read(r).with_context(|| format!("cannot read {r}"))?;
        let (rs, f) = balance_log::parse(&bytes, r);
        readings.extend(rs);
        findings.extend(f);
    }
    resolve_balance_ids(&mut readings, &boards, cfg.mass_max_std_in_d, &mut findings);
    // Masses of the sheet's boards only, from the lines resolved to them.
    let joined: Vec<Reading> = readings
        .iter()
        .filter_map(|r| {
            r.sheet_board_id.as_ref().map(|b| Reading {
                board_id: Some(b.clone()),
                ..r.clone()
            })
        })
        .collect();
    let masses = balance_log::board_masses(
        &joined,
        MassParams {
            max_std_in_d: cfg.mass_max_std_in_d,
        },
    );
    let weighed: BTreeSet<&str> = masses.iter().map(|m| m.board_id.as_str()).collect();
    for b in &boards {
        if !weighed.contains(b.as_str()) {
            findings.push(Finding::new(
                Severity::Warning,
                "balance.board_not_weighed",
                format!("board {b} has no stable balance reading in scale/*.log (expected every board weighed)"),
            ));
        }
    }
    for m in &masses {
        if m.n_days > 1 && m.day_spread_g > cfg.mass_max_std_in_d * m.resolution_g {
            findings.push(Finding::new(
                Severity::Warning,
                "balance.mass_changed_between_days",
                format!(
                    "board {}: weighed on {} days whose means differ by {:.4} g, more than {} x the balance resolution {:.4} g (expected the same board to weigh the same); all {} stable readings averaged",
                    m.board_id, m.n_days, m.day_spread_g, cfg.mass_max_std_in_d, m.resolution_g, m.n_stable
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
    let specimens = specimen_dimensions(&measurements, &boards, &mut findings);
    Ok(Campaign {
        name,
        measurements,
        readings,
        masses,
        specimens,
        findings,
        extra_columns: sheet.extra_columns,
    })
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

/// Order of the time derivative a dataset-58 axis measures (UFF specific data type, record 9
/// or 10 field 1): 8 displacement 0, 11 velocity 1, 12 acceleration 2. `None` for anything
/// else (0 unknown, 1 general, 13 force, ...).
fn motion_order(spec_data_type: i64) -> Option<i32> {
    match spec_data_type {
        8 => Some(0),
        11 => Some(1),
        12 => Some(2),
        _ => None,
    }
}

fn motion_name(order: i32) -> &'static str {
    match order {
        0 => "displacement",
        1 => "velocity",
        _ => "acceleration",
    }
}

/// What a response record measured, and the power q of iω that turns it into the contract's
/// quantity (mobility for an FRF, a velocity ratio for a transmissibility): the stored value is
/// the measured one times (iω)^q. An accelerance (acceleration/force) has q = -1, a receptance
/// q = +1. A numerator that names no quantity (specific data type 0 unknown, 1 general) is
/// taken as the contract's quantity and called `unspecified`; one that names another quantity
/// than a motion (2 stress, 13 force, ...) is `None`.
fn measured_as(f: &uff::Function58) -> Option<(String, i32)> {
    let spec = f.ordinate_axis.spec_data_type;
    let num = motion_order(spec);
    if num.is_none() && !matches!(spec, 0 | 1) {
        return None;
    }
    Some(match f.function_type {
        FunctionType::Transmissibility => {
            let den = motion_order(f.denominator_axis.spec_data_type);
            match (num, den) {
                (Some(n), Some(d)) => (format!("{}/{}", motion_name(n), motion_name(d)), d - n),
                // One side named: the other is taken as the same quantity (a plain ratio).
                (Some(n), None) | (None, Some(n)) => {
                    (format!("{}/{}", motion_name(n), motion_name(n)), 0)
                }
                (None, None) => ("unspecified".to_owned(), 0),
            }
        }
        _ => match num {
            Some(n) => (format!("{}/force", motion_name(n)), 1 - n),
            None => ("unspecified".to_owned(), 0),
        },
    })
}

/// Multiplies a spectrum by (iω)^q, ω = 2π f_k, in place. The lines at 0 Hz, where a division
/// by iω has no value, are set to 0; returns how many.
fn times_i_omega_pow(q: i32, f0_hz: f64, df_hz: f64, re: &mut [f64], im: &mut [f64]) -> usize {
    if q == 0 {
        return 0;
    }
    let mut zeroed = 0;
    for (k, (r, i)) in re.iter_mut().zip(im.iter_mut()).enumerate() {
        let w = std::f64::consts::TAU * (f0_hz + k as f64 * df_hz);
        if w == 0.0 && q < 0 {
            (*r, *i) = (0.0, 0.0);
            zeroed += 1;
            continue;
        }
        // (iω)^q = ω^q · i^q, and i^q cycles through 1, i, -1, -i.
        let m = w.powi(q);
        let (a, b) = (*r * m, *i * m);
        (*r, *i) = match q.rem_euclid(4) {
            0 => (a, b),
            1 => (-b, a),
            2 => (-a, -b),
            _ => (b, -a),
        };
    }
    zeroed
}

/// A roving hammer: every response record of the setup's function type shares one response
/// node (the fixed accelerometer) and they move the reference over several nodes. By Maxwell's
/// reciprocity H(a, b) = H(b, a), so each record is read as the response at its reference node
/// to an excitation at the fixed node. Returns the fixed node.
fn roving_response_node(datasets: &[Dataset], expected_type: i32) -> Option<i64> {
    let recs: Vec<&uff::Function58> = datasets
        .iter()
        .filter_map(|d| match d {
            Dataset::Function(f) if f.function_type.code() as i32 == expected_type => Some(f),
            _ => None,
        })
        .collect();
    let responses: BTreeSet<i64> = recs.iter().map(|f| f.response_node).collect();
    let references: BTreeSet<i64> = recs.iter().map(|f| f.reference_node).collect();
    // Only an FRF can rove: a base-excited transmissibility has one physical reference.
    (expected_type == 4 && responses.len() == 1 && references.len() >= 2)
        .then(|| *responses.first().expect("one response node"))
}

/// Quarantines `m` with the finding `code`, `msg`.
fn quarantine(
    m: &mut Measurement,
    fd: &mut Findings,
    file: &str,
    mid: &str,
    code: &str,
    msg: String,
) {
    fd.push(
        Finding::new(Severity::Quarantined, code, msg.clone())
            .file(file.to_owned())
            .measurement(mid.to_owned()),
    );
    m.quarantine = Some(msg);
}

/// Parse one measurement's UFF and fill `m`; returns its findings. Quarantines on fatal issues.
fn read_measurement(src: &dyn Source, m: &mut Measurement) -> Findings {
    let mut fd = Findings::default();
    let file = m.row.file.clone();
    let mid = m.row.measurement_id.clone();
    let setup = m.row.setup.expect("checked before");
    let bytes = match src.read(&file) {
        Ok(b) => b,
        Err(e) => {
            let msg = format!("cannot read file: {e}");
            quarantine(m, &mut fd, &file, &mid, "uff.unreadable", msg);
            return fd;
        }
    };
    m.uff_blake3 = Some(blake3::hash(&bytes).to_hex().to_string());
    let parsed = match uff::parse(&bytes) {
        Ok(p) => p,
        Err(e) => {
            quarantine(m, &mut fd, &file, &mid, "uff.not_uff", e.to_string());
            return fd;
        }
    };
    note_parse_issues(&parsed, m, &mut fd, &file, &mid);
    let units = parsed.datasets.iter().find_map(|d| match d {
        Dataset::Units(u) => Some(u.clone()),
        _ => None,
    });
    let nodes = merged_nodes(&parsed.datasets, units.as_ref(), &mut fd, &file, &mid);
    if nodes.is_empty() {
        quarantine(
            m,
            &mut fd,
            &file,
            &mid,
            "uff.no_geometry",
            "no scan-point geometry (expected dataset 2411 or 15 with the scan points)".into(),
        );
        return fd;
    }

    let expected_type = setup.expected_function_type();
    let roving = roving_response_node(&parsed.datasets, expected_type);
    if let Some(fixed) = roving {
        fd.push(
            Finding::new(
                Severity::Info,
                "uff.roving_reference",
                format!("every response record has response node {fixed} and the reference moves over several nodes (a roving hammer): by reciprocity each record is read as the response at its reference node to an excitation at node {fixed}"),
            )
            .file(file.clone())
            .measurement(mid.clone()),
        );
    }
    let reader = RecordReader {
        file: &file,
        mid: &mid,
        setup,
        expected_type,
        roving,
        nodes: &nodes,
        units: units.as_ref(),
    };
    let mut state = RecordState::default();
    for d in &parsed.datasets {
        let Dataset::Function(f) = d else { continue };
        let Some((rec, is_coh)) = reader.read(f, &mut state, &mut fd, &mut m.dropped) else {
            continue;
        };
        if is_coh {
            m.coherence.push(rec);
        } else {
            m.records.push(rec);
        }
    }
    note_conversions(&state.converted, expected_type, &mut fd, &file, &mid);
    // Mode sets (dataset 55, one per mode) as modal-analysis software exports them.
    let (vendor_modes, dropped) = read_vendor_modes(&parsed.datasets, &nodes, &mut fd, &file, &mid);
    m.vendor_modes = vendor_modes;
    m.dropped += dropped;
    let vendor: Vec<String> = m
        .vendor_modes
        .iter()
        .map(|v| format!("{:.1} Hz at line {}", v.freq_hz, v.line))
        .collect();
    if m.records.is_empty() {
        if vendor.is_empty() {
            quarantine(
                m,
                &mut fd,
                &file,
                &mid,
                "uff.no_records",
                format!(
                    "no usable response record (expected dataset 58 records of function type {expected_type}) and no mode set (dataset 55)"
                ),
            );
            return fd;
        }
        modes_only(m, &nodes, &vendor, &mut fd, &file, &mid);
        return fd;
    }
    if !vendor.is_empty() {
        fd.push(
            Finding::new(
                Severity::Warning,
                "uff.mode_sets_not_used",
                format!(
                    "the measurement holds FRFs and {} dataset-55 mode(s) ({}): extract identifies the modes from the FRFs; the lab's modes are kept in vendor_modes.parquet for comparison",
                    vendor.len(),
                    vendor.join(", ")
                ),
            )
            .file(file.clone())
            .measurement(mid.clone()),
        );
    }
    drop_off_axis_coherence(m, state.axis, &mut fd, &file, &mid);
    place_points(m, &nodes, &state.ref_count, &mut fd, &file, &mid);
    fd
}

/// The findings on the datasets the parser dropped (each counted in `m.dropped`) or
/// skipped.
fn note_parse_issues(
    parsed: &uff::UffFile,
    m: &mut Measurement,
    fd: &mut Findings,
    file: &str,
    mid: &str,
) {
    for iss in &parsed.issues {
        fd.push(
            Finding::new(
                Severity::RecordDropped,
                "uff.bad_dataset",
                format!("{}; dataset dropped", iss.kind),
            )
            .file(file.to_owned())
            .line(iss.line as u64)
            .record(format!(
                "dataset {} #{}",
                iss.number.map_or("?".into(), |n| n.to_string()),
                iss.index
            ))
            .measurement(mid.to_owned()),
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
            .file(file.to_owned())
            .line(s.line as u64)
            .record(format!("dataset {} #{}", s.number, s.index))
            .measurement(mid.to_owned()),
        );
    }
}

/// The nodes of all node datasets, metres, merged; a repeated id with other coordinates is
/// reported (the later definition is used).
fn merged_nodes(
    datasets: &[Dataset],
    units: Option<&uff::Units164>,
    fd: &mut Findings,
    file: &str,
    mid: &str,
) -> BTreeMap<i64, [f64; 3]> {
    let to_m = |v: f64| match units {
        Some(u) => u.length_to_metres(v),
        None => v * 1e-3, // contract: millimetres without dataset 164
    };
    // Nodes: merged over all node datasets; a repeated id with other coordinates is reported.
    let mut nodes: BTreeMap<i64, [f64; 3]> = BTreeMap::new();
    for d in datasets {
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
                            .file(file.to_owned())
                            .line(ns.line as u64)
                            .measurement(mid.to_owned()),
                        );
                    }
                }
            }
        }
    }
    nodes
}

/// What reading one measurement's records needs to know.
struct RecordReader<'a> {
    file: &'a str,
    mid: &'a str,
    setup: Setup,
    expected_type: i32,
    /// The fixed response node of a roving hammer ([`roving_response_node`]).
    roving: Option<i64>,
    nodes: &'a BTreeMap<i64, [f64; 3]>,
    units: Option<&'a uff::Units164>,
}

/// What reading a measurement's records accumulates over them.
#[derive(Default)]
struct RecordState {
    /// The response records' frequency axis (start, step, lines): the first record's.
    axis: Option<(f64, f64, usize)>,
    /// (node, function type) of the records kept.
    seen: BTreeSet<(i64, i32)>,
    /// Response records per reference node.
    ref_count: BTreeMap<i64, usize>,
    /// Per quantity converted: (q, records, lines zeroed at 0 Hz).
    converted: BTreeMap<String, (i32, usize, usize)>,
}

impl RecordReader<'_> {
    /// Record `f` converted to the contract (and whether it is a coherence), or `None` when
    /// it is dropped (with a finding, counted in `dropped`).
    fn read(
        &self,
        f: &uff::Function58,
        st: &mut RecordState,
        fd: &mut Findings,
        dropped: &mut usize,
    ) -> Option<(Record, bool)> {
        let (file, mid, setup, expected_type) =
            (self.file, self.mid, self.setup, self.expected_type);
        let ft = f.function_type.code() as i32;
        // The scan point a record belongs to, and its excitation (swapped for a roving hammer).
        let (node, node_dir, reference, reference_dir) = match self.roving {
            Some(fixed) if f.response_node == fixed => (
                f.reference_node,
                f.reference_direction,
                f.response_node,
                f.response_direction,
            ),
            _ => (
                f.response_node,
                f.response_direction,
                f.reference_node,
                f.reference_direction,
            ),
        };
        let loc = format!("dataset 58 at line {} (node {node})", f.line);
        let mut drop = |fd: &mut Findings, code: &str, msg: String| {
            fd.push(
                Finding::new(
                    Severity::RecordDropped,
                    code,
                    format!("{msg}; record dropped"),
                )
                .file(file.to_owned())
                .line(f.line as u64)
                .record(loc.clone())
                .measurement(mid.to_owned()),
            );
            *dropped += 1;
        };
        let is_coh = f.function_type == FunctionType::Coherence;
        if !is_coh && ft != expected_type {
            let what = match f.function_type {
                FunctionType::Frf | FunctionType::Transmissibility => "does not match the setup",
                _ => "is not one the contract knows",
            };
            drop(
                fd,
                "uff.function_type",
                format!(
                    "function type {ft} {what} (expected {expected_type} for setup `{}`, or 6 coherence)",
                    setup.as_str()
                ),
            );
            return None;
        }
        let mut sign = 1.0;
        match node_dir {
            3 => {}
            -3 => {
                sign = -1.0;
                fd.push(
                    Finding::new(
                        Severity::Info,
                        "uff.direction_flipped",
                        "response direction -Z; ordinate negated to +Z",
                    )
                    .file(file.to_owned())
                    .line(f.line as u64)
                    .record(loc.clone())
                    .measurement(mid.to_owned()),
                );
            }
            d => {
                drop(
                    fd,
                    "uff.direction",
                    format!("response direction {d} (expected 3 = +Z)"),
                );
                return None;
            }
        }
        if !self.nodes.contains_key(&node) {
            drop(
                fd,
                "uff.unknown_node",
                format!("response node {node} has no coordinates in dataset 2411/15"),
            );
            return None;
        }
        let (min, inc) = match &f.abscissa {
            Abscissa::Even { min, increment } => (*min, *increment),
            Abscissa::Uneven(_) => {
                drop(
                    fd,
                    "uff.uneven_abscissa",
                    "abscissa is unevenly spaced (expected evenly spaced frequency lines)".into(),
                );
                return None;
            }
        };
        let n = f.ordinate.len();
        if !(inc.is_finite() && inc > 0.0 && min.is_finite() && min >= 0.0) || n < 2 {
            drop(
                fd,
                "uff.bad_abscissa",
                format!("abscissa start {min} Hz, step {inc} Hz, {n} lines (expected start >= 0, step > 0, >= 2 lines)"),
            );
            return None;
        }
        if !is_coh {
            match st.axis {
                None => st.axis = Some((min, inc, n)),
                Some((a0, da, na)) => {
                    let same = na == n
                        && (a0 - min).abs() <= 1e-9 * da.max(1.0)
                        && (da - inc).abs() <= 1e-9 * da;
                    if !same {
                        drop(
                            fd,
                            "uff.axis_mismatch",
                            format!("frequency axis {min} Hz + k*{inc} Hz, {n} lines differs from the measurement's first record ({a0} Hz + k*{da} Hz, {na} lines)"),
                        );
                        return None;
                    }
                }
            }
        }
        if !st.seen.insert((node, ft)) {
            drop(
                fd,
                "uff.duplicate_record",
                format!("second record of function type {ft} for node {node} (the first is kept)"),
            );
            return None;
        }
        let factor = sign
            * if is_coh {
                1.0
            } else {
                ordinate_factor(f, self.units)
            };
        let (measured, q) = if is_coh {
            ("coherence".to_owned(), 0)
        } else if let Some(m) = measured_as(f) {
            m
        } else {
            drop(
                fd,
                "uff.ordinate_quantity",
                format!("ordinate specific data type {} names no motion (expected 8 displacement, 11 velocity or 12 acceleration, or 0/1 unknown/general for the contract's quantity)", f.ordinate_axis.spec_data_type),
            );
            return None;
        };
        let (re, im) = match (&f.ordinate, is_coh) {
            (Ordinate::Complex { re, im }, false) => {
                let mut re: Vec<f64> = re.iter().map(|v| v * factor).collect();
                let mut im: Vec<f64> = im.iter().map(|v| v * factor).collect();
                let zeroed = times_i_omega_pow(q, min, inc, &mut re, &mut im);
                if q != 0 {
                    let e = st.converted.entry(measured.clone()).or_insert((q, 0, 0));
                    e.1 += 1;
                    e.2 += zeroed;
                }
                (re, Some(im))
            }
            (Ordinate::Real(v), true) => (v.clone(), None),
            (Ordinate::Real(_), false) => {
                drop(
                    fd,
                    "uff.real_ordinate",
                    format!("function type {ft} has a real ordinate (expected complex)"),
                );
                return None;
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
                    .file(file.to_owned())
                    .line(f.line as u64)
                    .record(loc.clone())
                    .measurement(mid.to_owned()),
                );
                (re.clone(), None)
            }
        };
        if !is_coh {
            *st.ref_count.entry(reference).or_default() += 1;
        }
        let rec = Record {
            node,
            function_type: ft,
            response_direction: 3,
            reference_node: reference,
            reference_direction: reference_dir as i32,
            measured_as: measured,
            ordinate_unit: match ft {
                4 => "m/s/N",
                _ => "1",
            },
            freq_start_hz: min,
            freq_step_hz: inc,
            re,
            im,
        };
        Some((rec, is_coh))
    }
}

/// One finding per quantity whose records were converted to the contract's quantity.
fn note_conversions(
    converted: &BTreeMap<String, (i32, usize, usize)>,
    expected_type: i32,
    fd: &mut Findings,
    file: &str,
    mid: &str,
) {
    for (measured, (q, n, zeroed)) in converted {
        let how = match q {
            -1 => "divided by iω",
            1 => "multiplied by iω",
            -2 => "divided by -ω²",
            2 => "multiplied by -ω²",
            _ => "multiplied by (iω)^q",
        };
        let target = if expected_type == 4 {
            "mobility (m/s)/N"
        } else {
            "a velocity ratio"
        };
        let zero_note = if *zeroed > 0 {
            format!("; {zeroed} line(s) at 0 Hz have no value and are set to 0")
        } else {
            String::new()
        };
        fd.push(
            Finding::new(
                Severity::Info,
                "uff.converted_ordinate",
                format!("{n} record(s) measured as {measured}: {how} to {target} (q = {q}){zero_note}; frf.parquet keeps what was measured in `measured_as`"),
            )
            .file(file.to_owned())
            .measurement(mid.to_owned()),
        );
    }
}

/// A measurement of modes only (`vendor` describes them): the lab identified them; its
/// scan points are the nodes with coordinates, with a record where a mode has a value.
fn modes_only(
    m: &mut Measurement,
    nodes: &BTreeMap<i64, [f64; 3]>,
    vendor: &[String],
    fd: &mut Findings,
    file: &str,
    mid: &str,
) {
    let with_value: BTreeSet<i64> = m
        .vendor_modes
        .iter()
        .flat_map(|v| v.nodes.iter().copied())
        .collect();
    m.points = nodes
        .iter()
        .map(|(&node, &xyz_m)| Point {
            node,
            xyz_m,
            is_reference: false,
            has_record: with_value.contains(&node),
        })
        .collect();
    fd.push(
        Finding::new(
            Severity::Info,
            "uff.vendor_modes",
            format!(
                "no response record; {} mode(s) identified by the lab's modal software (dataset 55: {}) are the measurement's modes: extract passes them through, `source = uff55` in modes.parquet",
                vendor.len(),
                vendor.join(", ")
            ),
        )
        .file(file.to_owned())
        .measurement(mid.to_owned()),
    );
    note_points(m, fd, file, mid, "no value in any mode set");
}

/// Drops the coherence records on another frequency axis than the response records'
/// (`axis`): they are of no use.
fn drop_off_axis_coherence(
    m: &mut Measurement,
    axis: Option<(f64, f64, usize)>,
    fd: &mut Findings,
    file: &str,
    mid: &str,
) {
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
                .file(file.to_owned())
                .measurement(mid.to_owned()),
            );
        }
    }
}

/// The main reference (the one most records use), the records sorted with it first, and
/// the scan points of a measurement with response records.
fn place_points(
    m: &mut Measurement,
    nodes: &BTreeMap<i64, [f64; 3]>,
    ref_count: &BTreeMap<i64, usize>,
    fd: &mut Findings,
    file: &str,
    mid: &str,
) {
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
            .file(file.to_owned())
            .measurement(mid.to_owned()),
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
            .file(file.to_owned())
            .measurement(mid.to_owned()),
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
    note_points(
        m,
        fd,
        file,
        mid,
        "no response record (marked invalid by the vibrometer, or dropped)",
    );
}

/// The findings on a measurement's scan points: points off the board's plane, and points
/// without data (`missing` says why there is none).
fn note_points(m: &Measurement, fd: &mut Findings, file: &str, mid: &str, missing: &str) {
    // The contract's frame has the board in z = 0: a scan point well off that plane is not
    // on the board (a bolt head, the fixture). Kept in scan_points.parquet; pair, which knows
    // the board's outline, names points off it and leaves them out of the MAC.
    for p in m.points.iter().filter(|p| !p.is_reference) {
        if p.xyz_m[2].abs() > OFF_PLANE_M {
            fd.push(
                Finding::new(
                    Severity::Warning,
                    "uff.point_off_plane",
                    format!(
                        "scan point node {} at z = {:.2} mm lies off the board's plane (expected |z| <= {:.1} mm for a point on the board): not a board point (a bolt head, the fixture?); kept; if it lies off the board's outline, pair leaves it out of the MAC and update out of its shape terms",
                        p.node,
                        p.xyz_m[2] * 1e3,
                        OFF_PLANE_M * 1e3
                    ),
                )
                .file(file.to_string())
                .record(format!("node {}", p.node))
                .measurement(mid.to_string()),
            );
        }
    }
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
                format!("{no_record} scan point(s) have {missing}"),
            )
            .file(file.to_string())
            .measurement(mid.to_string()),
        );
    }
}

/// The modes of a file's mode sets (dataset 55), ascending in frequency, and how many sets were
/// dropped. A set that is no
/// mode (another analysis type), whose frequency or damping is unusable, whose data are no
/// scalar or translation, or that has no finite value at a node with coordinates is dropped
/// with a finding naming its line; nodes without coordinates are named and left out.
fn read_vendor_modes(
    datasets: &[Dataset],
    nodes: &BTreeMap<i64, [f64; 3]>,
    fd: &mut Findings,
    file: &str,
    mid: &str,
) -> (Vec<VendorMode>, usize) {
    use faer::c64;
    let finding = |severity, code: &str, line: usize, msg: String| {
        Finding::new(severity, code, msg)
            .file(file.to_string())
            .line(line as u64)
            .record("dataset 55".to_string())
            .measurement(mid.to_string())
    };
    let (mut out, mut dropped) = (vec![], 0);
    for d in datasets {
        let Dataset::NodalData(n) = d else { continue };
        let mut drop = |fd: &mut Findings, code: &str, what: String| {
            dropped += 1;
            fd.push(finding(
                Severity::RecordDropped,
                code,
                n.line,
                format!("{what}; mode set dropped"),
            ))
        };
        let Some(p) = n.mode() else {
            drop(fd, "uff.mode_set_type", format!("analysis type {}: expected a mode (2, a normal mode with frequency, modal mass and damping in record 8; 3 or 7, a complex mode with its eigenvalue)", n.analysis_type));
            continue;
        };
        if !(p.freq_hz.is_finite() && p.freq_hz > 0.0 && p.damping_ratio.is_finite()) {
            drop(fd, "uff.mode_set_values", format!("frequency {} Hz, damping ratio {}: expected a positive frequency and a finite damping ratio", p.freq_hz, p.damping_ratio));
            continue;
        }
        // The component along the response direction: the scalar, or Z of the translations.
        let comp = match n.data_characteristic {
            1 => 0,
            2 | 3 => 2,
            dc => {
                drop(fd, "uff.mode_set_component", format!("data characteristic {dc}: expected 1 (a scalar, taken as the response direction) or 2/3 (translations, of which Z is used)"));
                continue;
            }
        };
        let mut vals: BTreeMap<i64, c64> = BTreeMap::new();
        let (mut no_geometry, mut repeated, mut not_finite) = (0usize, 0usize, 0usize);
        for v in &n.nodes {
            let re = v.re.get(comp).copied().unwrap_or(f64::NAN);
            let im = v.im.as_ref().map_or(Some(0.0), |i| i.get(comp).copied());
            let z = c64::new(re, im.unwrap_or(f64::NAN));
            if !nodes.contains_key(&v.node) {
                no_geometry += 1;
            } else if !(z.re.is_finite() && z.im.is_finite()) {
                not_finite += 1;
            } else if vals.insert(v.node, z).is_some() {
                repeated += 1;
            }
        }
        let zs: Vec<c64> = vals.values().copied().collect();
        let mask = vec![true; zs.len()];
        let shape = crate::modal::lsfd::real_normalise(&zs, &mask);
        if shape.is_empty() || shape.iter().any(|v| !v.is_finite()) {
            drop(fd, "uff.mode_set_no_points", format!("{:.1} Hz: no nonzero finite value at a node with coordinates (dataset 2411/15); {} node(s) without coordinates, {} not finite", p.freq_hz, no_geometry, not_finite));
            continue;
        }
        if no_geometry + repeated + not_finite > 0 {
            fd.push(finding(
                Severity::Warning,
                "uff.mode_set_nodes",
                n.line,
                format!("{:.1} Hz: {no_geometry} node(s) without coordinates in dataset 2411/15, {not_finite} with a value that is not finite, {repeated} given twice (the later value kept); the mode is used at its other {} node(s)", p.freq_hz, vals.len()),
            ));
        }
        let (mpc, mpd_deg) = crate::modal::lsfd::mpc_mpd(&zs, &mask);
        out.push(VendorMode {
            line: n.line,
            mode_number: p.mode_number,
            analysis_type: n.analysis_type,
            freq_hz: p.freq_hz,
            damping_ratio: p.damping_ratio,
            mpc,
            mpd_deg,
            nodes: vals.keys().copied().collect(),
            shape,
        });
    }
    out.sort_by(|a, b| a.freq_hz.total_cmp(&b.freq_hz));
    (out, dropped)
}

/// The key two spellings of one board ID share: letters upper-cased, numbers without their
/// leading zeros, anything else (spaces, `-`, `_`, `.`) only a separator. `PCB-03`, `pcb-3`,
/// ` PCB 03` and `PCB03` share the key `PCB|3`; `PCB-1-2` (`PCB|1|2`) and `PCB-12` do not.
pub fn board_key(id: &str) -> String {
    let mut parts: Vec<String> = vec![];
    let mut cur = String::new();
    let mut digits = false;
    let flush = |cur: &mut String, digits: bool, parts: &mut Vec<String>| {
        if !cur.is_empty() {
            let t = if digits {
                let t = cur.trim_start_matches('0');
                if t.is_empty() { "0" } else { t }.to_string()
            } else {
                cur.clone()
            };
            parts.push(t);
            cur.clear();
        }
    };
    for c in id.chars() {
        if c.is_ascii_digit() {
            if !digits {
                flush(&mut cur, digits, &mut parts);
                digits = true;
            }
            cur.push(c);
        } else if c.is_alphanumeric() {
            if digits {
                flush(&mut cur, digits, &mut parts);
                digits = false;
            }
            cur.extend(c.to_uppercase());
        } else {
            flush(&mut cur, digits, &mut parts);
        }
    }
    flush(&mut cur, digits, &mut parts);
    parts.join("|")
}

/// The key's letters only (`PCB|3` → `PCB|#`): an ID with the letters of a sheet board but
/// another number looks like a board ID.
fn key_shape(key: &str) -> String {
    key.split('|')
        .map(|p| {
            if p.chars().all(|c| c.is_ascii_digit()) {
                "#"
            } else {
                p
            }
        })
        .collect::<Vec<_>>()
        .join("|")
}

/// The nominal mass of a check weight named `REF-<number><unit>` (`REF-10G`, `ref_200mg`), g.
fn check_weight_nominal_g(id: &str) -> Option<f64> {
    let u = id.to_ascii_uppercase();
    let rest = u.strip_prefix("REF")?.trim_start_matches(['-', '_', ' ']);
    let split = rest.find(|c: char| !(c.is_ascii_digit() || c == '.'))?;
    let (num, unit) = rest.split_at(split);
    let factor = match unit {
        "G" => 1.0,
        "MG" => 1e-3,
        "KG" => 1e3,
        _ => return None,
    };
    num.parse::<f64>()
        .ok()
        .filter(|v| *v > 0.0)
        .map(|v| v * factor)
}

/// Why a sheet row is marked invalid by the lab, if it is: notes starting with `invalid`
/// (any case), or an extra column `valid` saying no.
fn invalid_mark(row: &SheetRow) -> Option<String> {
    for (col, v) in &row.extra {
        if col.trim().eq_ignore_ascii_case("valid")
            && ["no", "n", "false", "0", "invalid"]
                .contains(&v.trim().to_ascii_lowercase().as_str())
        {
            return Some(format!("column {col} = {v:?}"));
        }
    }
    let note = row.notes.as_deref()?.trim_start();
    note.to_ascii_lowercase()
        .starts_with("invalid")
        .then(|| format!("notes {:?}", note.lines().next().unwrap_or(note)))
}

/// The measurement id a note says the row repeats (`repeat of M012 ...`), if any.
fn repeat_of(notes: &str) -> Option<String> {
    let lower = notes.to_ascii_lowercase();
    let at = lower.find("repeat of ")? + "repeat of ".len();
    let id: String = notes[at..]
        .chars()
        .take_while(|c| c.is_alphanumeric() || *c == '-' || *c == '_')
        .collect();
    (!id.is_empty()).then_some(id)
}

/// Cross-check the notes about invalid and repeated measurements: a repeat of a row that is
/// not on the sheet or not marked invalid, and a note mentioning `invalid` that marks nothing.
fn check_repeats(ms: &[Measurement], findings: &mut Findings) {
    let by_id: HashMap<&str, &Measurement> = ms
        .iter()
        .map(|m| (m.row.measurement_id.as_str(), m))
        .collect();
    for m in ms {
        let row = &m.row;
        let Some(notes) = row.notes.as_deref() else {
            continue;
        };
        let f = |code: &str, msg: String| {
            Finding::new(Severity::Warning, code, msg)
                .file("campaign.csv")
                .line(row.line)
                .measurement(row.measurement_id.clone())
        };
        match repeat_of(notes) {
            Some(id) => match by_id.get(id.as_str()) {
                None => findings.push(f(
                    "sheet.repeat_of_unknown",
                    format!("notes say this repeats {id:?}, which no row of the sheet is; kept"),
                )),
                Some(o) if invalid_mark(&o.row).is_none() => findings.push(f(
                    "sheet.repeat_of_valid",
                    format!(
                        "notes say this repeats {id:?} (line {}), which is not marked invalid (expected its notes to start with `invalid`, or valid = no); both kept",
                        o.row.line
                    ),
                )),
                Some(_) => {}
            },
            None => {
                if invalid_mark(row).is_none() && notes.to_ascii_lowercase().contains("invalid") {
                    findings.push(f(
                        "sheet.note_mentions_invalid",
                        format!("notes mention `invalid` ({:?}) but do not mark the row (notes starting with `invalid`, or valid = no); kept", notes.lines().next().unwrap_or(notes)),
                    ));
                }
            }
        }
    }
}

/// One board of the sheet and its measured dimensions.
#[derive(Debug, Clone, PartialEq)]
pub struct Specimen {
    pub board_id: String,
    /// Length, width and overall thickness, mm ([`sheet::DIMENSIONS`]): the mean over the rows
    /// that give it, `None` where no row does.
    pub dimensions_mm: [Option<f64>; 3],
    /// Rows giving each dimension.
    pub n_rows: [usize; 3],
}

/// Relative spread of one specimen's readings of a dimension above which they disagree: 1 %,
/// ten times a micrometer's repeatability on a 1.5 mm laminate (±2 µm) and forty times a
/// caliper's on an 80 mm board (±0.02 mm), so only a slip (a digit, another specimen's
/// value) is flagged, never the gauge's own scatter.
const DIMENSION_REL_TOL: f64 = 0.01;

/// Every sheet board's dimensions from the rows that give them (quarantined rows included:
/// the specimen was measured whatever became of its vibration test), readings that disagree
/// named in a warning.
fn specimen_dimensions(
    ms: &[Measurement],
    boards: &BTreeSet<String>,
    findings: &mut Findings,
) -> Vec<Specimen> {
    boards
        .iter()
        .map(|b| {
            let rows: Vec<&sheet::SheetRow> =
                ms.iter().map(|m| &m.row).filter(|r| r.board_id == *b).collect();
            let mut n_rows = [0; 3];
            let dimensions_mm = std::array::from_fn(|k| {
                let vals: Vec<(f64, u64)> = rows
                    .iter()
                    .filter_map(|r| r.dimensions_mm[k].map(|v| (v, r.line)))
                    .collect();
                n_rows[k] = vals.len();
                if vals.is_empty() {
                    return None;
                }
                let mean = vals.iter().map(|v| v.0).sum::<f64>() / vals.len() as f64;
                let (lo, hi) = vals
                    .iter()
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, c), v| (a.min(v.0), c.max(v.0)));
                if hi - lo > DIMENSION_REL_TOL * mean {
                    let list = vals
                        .iter()
                        .map(|(v, l)| format!("{v} on line {l}"))
                        .collect::<Vec<_>>()
                        .join(", ");
                    findings.push(
                        Finding::new(
                            Severity::Warning,
                            "sheet.dimension_disagrees",
                            format!(
                                "board {b}: column {} reads {list}, spread more than {:.0} % of their mean (expected one specimen to measure the same); the mean {mean:.4} mm taken",
                                sheet::DIMENSIONS[k],
                                100.0 * DIMENSION_REL_TOL
                            ),
                        )
                        .file("campaign.csv"),
                    );
                }
                Some(mean)
            });
            Specimen {
                board_id: b.clone(),
                dimensions_mm,
                n_rows,
            }
        })
        .collect()
}

/// The sheet's boards: rows spelling one board differently are resolved to the spelling most
/// rows use (`sheet.board_id_variant`); spellings used equally often stay apart
/// (`sheet.board_id_ambiguous`). Rewrites the rows' board_id; returns the boards.
fn resolve_sheet_boards(ms: &mut [Measurement], findings: &mut Findings) -> BTreeSet<String> {
    // key → spelling → (rows, first line)
    let mut spellings: BTreeMap<String, BTreeMap<String, (usize, u64)>> = BTreeMap::new();
    for m in ms.iter() {
        let b = &m.row.board_id;
        if b.is_empty() {
            continue;
        }
        let e = spellings
            .entry(board_key(b))
            .or_default()
            .entry(b.clone())
            .or_insert((0, m.row.line));
        e.0 += 1;
    }
    let mut canonical: HashMap<String, String> = HashMap::new();
    for sp in spellings.values() {
        if sp.len() < 2 {
            continue;
        }
        let mut by_count: Vec<(&String, &(usize, u64))> = sp.iter().collect();
        by_count.sort_by_key(|(s, (n, line))| (std::cmp::Reverse(*n), *line, (*s).clone()));
        if by_count[0].1 .0 > by_count[1].1 .0 {
            for (s, _) in &by_count[1..] {
                canonical.insert((*s).clone(), by_count[0].0.clone());
            }
        } else {
            let list = by_count
                .iter()
                .map(|(s, (n, line))| format!("{s:?} ({n} row(s), first on line {line})"))
                .collect::<Vec<_>>()
                .join(", ");
            for (s, (_, line)) in &by_count {
                findings.push(
                    Finding::new(
                        Severity::Warning,
                        "sheet.board_id_ambiguous",
                        format!("board_id {s:?} differs from another board_id only in case, separators or zero padding, and neither is used more often: {list}; kept as separate boards (expected one spelling per board)"),
                    )
                    .file("campaign.csv")
                    .line(*line),
                );
            }
        }
    }
    for m in ms.iter_mut() {
        if let Some(c) = canonical.get(&m.row.board_id) {
            findings.push(
                Finding::new(
                    Severity::Warning,
                    "sheet.board_id_variant",
                    format!(
                        "board_id {:?} is spelled otherwise than on the other rows of that board; resolved to {c:?}",
                        m.row.board_id
                    ),
                )
                .file("campaign.csv")
                .line(m.row.line)
                .measurement(m.row.measurement_id.clone()),
            );
            m.row.board_id = c.clone();
        }
    }
    ms.iter()
        .map(|m| m.row.board_id.clone())
        .filter(|b| !b.is_empty())
        .collect()
}

/// Resolve every balance line's ID against the sheet's boards (see the module doc) and fill
/// [`Reading::sheet_board_id`].
fn resolve_balance_ids(
    readings: &mut [Reading],
    boards: &BTreeSet<String>,
    max_std_in_d: f64,
    findings: &mut Findings,
) {
    let mut by_key: BTreeMap<String, Vec<&str>> = BTreeMap::new();
    for b in boards {
        by_key.entry(board_key(b)).or_default().push(b);
    }
    let shapes: BTreeSet<String> = by_key.keys().map(|k| key_shape(k)).collect();
    // The lines of an ID that is not a board, per (file, id).
    #[derive(Default)]
    struct NotABoard {
        first_line: u64,
        lines: usize,
        /// Stable readings, g.
        stable: Vec<f64>,
        /// Their coarsest resolution, g.
        d: f64,
    }
    let mut others: BTreeMap<(String, String), NotABoard> = BTreeMap::new();
    for r in readings.iter_mut() {
        let Some(id) = r.board_id.clone() else {
            continue;
        };
        if boards.contains(&id) {
            r.sheet_board_id = Some(id);
            continue;
        }
        let key = board_key(&id);
        match by_key.get(&key).map(Vec::as_slice) {
            Some([b]) => {
                findings.push(
                    Finding::new(
                        Severity::Warning,
                        "balance.board_id_variant",
                        format!("ID {id:?} is not spelled as on the sheet; resolved to board {b:?}"),
                    )
                    .file(r.file.clone())
                    .line(r.line),
                );
                r.sheet_board_id = Some(b.to_string());
            }
            Some(bs) => findings.push(
                Finding::new(
                    Severity::RecordDropped,
                    "balance.board_id_ambiguous",
                    format!("ID {id:?} could be any of the sheet's boards {bs:?}; joined to none (the line stays in scale_readings.parquet)"),
                )
                .file(r.file.clone())
                .line(r.line),
            ),
            None => {
                let e = others
                    .entry((r.file.clone(), id))
                    .or_insert_with(|| NotABoard {
                        first_line: r.line,
                        ..Default::default()
                    });
                e.lines += 1;
                if let (balance_log::Status::Stable, Some(g)) = (r.status, r.mass_g) {
                    e.stable.push(g);
                    e.d = e.d.max(r.resolution_g.unwrap_or(0.0));
                }
            }
        }
    }
    for ((file, id), nb) in others {
        let NotABoard {
            first_line: line,
            lines: n,
            stable,
            d,
        } = nb;
        let looks_like_board = shapes.contains(&key_shape(&board_key(&id)));
        // A check weight named by its nominal mass checks the balance: its mean reading
        // should lie within the spread allowed for a board's readings.
        if let (Some(nominal), false) = (check_weight_nominal_g(&id), stable.is_empty()) {
            let mean = stable.iter().sum::<f64>() / stable.len() as f64;
            if (mean - nominal).abs() > max_std_in_d * d.max(f64::MIN_POSITIVE) {
                findings.push(
                    Finding::new(
                        Severity::Warning,
                        "balance.check_weight_off",
                        format!(
                            "check weight {id:?} reads {mean:.5} g on average over {} stable reading(s), {:+.2} mg from its nominal {nominal} g (expected within {max_std_in_d} x the resolution {d} g): the balance may be off; board masses kept as read",
                            stable.len(),
                            (mean - nominal) * 1e3
                        ),
                    )
                    .file(file.clone())
                    .line(line),
                );
            }
        }
        let stable = if stable.is_empty() {
            "no stable reading".to_string()
        } else {
            format!(
                "{} stable reading(s), mean {:.4} g",
                stable.len(),
                stable.iter().sum::<f64>() / stable.len() as f64
            )
        };
        let (sev, code, what) = if looks_like_board {
            (
                Severity::Warning,
                "balance.unknown_board",
                "looks like a board ID, but no row of the sheet names that board",
            )
        } else {
            (
                Severity::Info,
                "balance.not_a_board",
                "is not a board of the sheet (a check weight, a tray)",
            )
        };
        findings.push(
            Finding::new(
                sev,
                code,
                format!("ID {id:?} {what}: its {n} line(s) ({stable}) stay in scale_readings.parquet and give no board mass"),
            )
            .file(file)
            .line(line),
        );
    }
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

/// A campaign held in memory, for tests: the checks need nothing but names and bytes.
#[cfg(test)]
pub(crate) struct InMemory<'a>(pub &'a std::collections::BTreeMap<String, Vec<u8>>);

#[cfg(test)]
impl Source for InMemory<'_> {
    fn name(&self) -> String {
        "in-memory".into()
    }
    fn describe(&self) -> String {
        "in-memory campaign".into()
    }
    fn list(&self) -> std::io::Result<Vec<String>> {
        Ok(self.0.keys().cloned().collect())
    }
    fn is_file(&self, rel: &str) -> bool {
        self.0.contains_key(rel)
    }
    fn identity(&self, rel: &str) -> String {
        rel.into()
    }
    fn read(&self, rel: &str) -> std::io::Result<Vec<u8>> {
        self.0
            .get(rel)
            .cloned()
            .ok_or_else(|| std::io::Error::new(std::io::ErrorKind::NotFound, rel.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeMap;

    /// The example campaign (written by pyuff) from memory, and with one UFF missing: the
    /// same checks as from disk, the missing file quarantines its measurement only.
    #[test]
    fn campaign_checks_run_on_names_and_bytes_alone() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data/example/campaign");
        let mut files = BTreeMap::new();
        let mut stack = vec![root.clone()];
        while let Some(d) = stack.pop() {
            for e in std::fs::read_dir(&d).unwrap() {
                let p = e.unwrap().path();
                if p.is_dir() {
                    stack.push(p);
                } else {
                    let rel = p
                        .strip_prefix(&root)
                        .unwrap()
                        .to_string_lossy()
                        .replace('\\', "/");
                    files.insert(rel, std::fs::read(&p).unwrap());
                }
            }
        }
        let cfg = IngestConfig::default();
        let c = read_campaign(&InMemory(&files), &cfg, &|| {}).unwrap();
        assert!(!c.measurements.is_empty());
        assert!(c.measurements.iter().all(|m| m.quarantine.is_none()));
        assert!(c.measurements.iter().all(|m| !m.records.is_empty()));
        let gone = c.measurements[0].row.file.clone();
        files.remove(&gone);
        let c2 = read_campaign(&InMemory(&files), &cfg, &|| {}).unwrap();
        assert!(c2.measurements[0].quarantine.is_some());
        assert!(c2.measurements[1..].iter().all(|m| m.quarantine.is_none()));
        assert!(c2
            .findings
            .iter()
            .any(|f| f.code == "sheet.missing_file" && f.message.contains(&gone)));
    }

    /// The sheet's dimensions become each board's: the mean of its rows, a slip (one row
    /// reading 1.06 for 1.60 mm) named with its lines, a board without them left unknown,
    /// and a bad cell a finding without losing the row's other values.
    #[test]
    fn specimen_dimensions_are_each_boards_rows_with_disagreements_named() {
        let sheet = "measurement_id,board_id,setup,file,length_mm,width_mm,thickness_mm\n\
                     M1,B-1,free,v/m1.uff,80.01,50.00,1.600\n\
                     M2,B-1,free,v/m2.uff,79.99,,1.602\n\
                     M3,B-2,free,v/m3.uff,80.00,50.02,1.520\n\
                     M4,B-2,free,v/m4.uff,80.00,50.02,1.06\n\
                     M5,B-3,free,v/m5.uff,,,\n\
                     M6,B-3,free,v/m6.uff,-80,x,\n";
        let files = BTreeMap::from([("campaign.csv".to_owned(), sheet.as_bytes().to_vec())]);
        let c = read_campaign(&InMemory(&files), &IngestConfig::default(), &|| {}).unwrap();
        let by: BTreeMap<&str, &Specimen> = c
            .specimens
            .iter()
            .map(|s| (s.board_id.as_str(), s))
            .collect();
        let b1 = by["B-1"];
        assert!((b1.dimensions_mm[0].unwrap() - 80.0).abs() < 1e-12);
        assert_eq!(b1.dimensions_mm[1], Some(50.0));
        assert!((b1.dimensions_mm[2].unwrap() - 1.601).abs() < 1e-12);
        assert_eq!(b1.n_rows, [2, 1, 2]);
        let b2 = by["B-2"];
        assert!((b2.dimensions_mm[2].unwrap() - 1.29).abs() < 1e-12);
        let slip: Vec<_> = c
            .findings
            .iter()
            .filter(|f| f.code == "sheet.dimension_disagrees")
            .collect();
        assert_eq!(slip.len(), 1, "{slip:?}");
        assert!(
            slip[0].message.contains("B-2")
                && slip[0].message.contains("1.06 on line 5")
                && slip[0].message.contains("thickness_mm"),
            "{}",
            slip[0].message
        );
        assert_eq!(by["B-3"].dimensions_mm, [None, None, None]);
        assert_eq!(by["B-3"].n_rows, [0, 0, 0]);
        // A negative length and a word: each a finding on its line; the rows stay.
        assert!(c
            .findings
            .iter()
            .any(|f| f.code == "sheet.not_a_dimension" && f.line == Some(7)));
        assert!(c
            .findings
            .iter()
            .any(|f| f.code == "sheet.not_a_number" && f.line == Some(7)));
        assert_eq!(c.measurements.len(), 6);
    }

    /// One free-free measurement in memory: nodes 1..=4 on the board, records from `recs`.
    fn one_measurement(recs: &[uff::Function58]) -> Campaign {
        one_measurement_with(recs, b"")
    }

    /// [`one_measurement`] with `extra` datasets appended to its UFF.
    fn one_measurement_with(recs: &[uff::Function58], extra: &[u8]) -> Campaign {
        use crate::formats::uff::{write_2411, write_58, Format, Node};
        let mut bytes = Vec::new();
        let nodes: Vec<Node> = (1..=4)
            .map(|k| Node {
                id: k,
                def_cs: 1,
                disp_cs: 1,
                color: 11,
                xyz_file_units: [10.0 * k as f64, 20.0, 0.0],
            })
            .collect();
        write_2411(&nodes, &mut bytes).unwrap();
        for r in recs {
            write_58(r, Format::Ascii, &mut bytes).unwrap();
        }
        bytes.extend_from_slice(extra);
        let files = BTreeMap::from([
            (
                "campaign.csv".to_owned(),
                b"measurement_id,board_id,setup,file\nM1,B-1,free,v/m1.uff\n".to_vec(),
            ),
            ("v/m1.uff".to_owned(), bytes),
            (
                "scale/b.log".to_owned(),
                b"2026-11-01T08:00:00 B-1 S S 13.0312 g\n".to_vec(),
            ),
        ]);
        read_campaign(&InMemory(&files), &IngestConfig::default(), &|| {}).unwrap()
    }

    /// A double-precision FRF record: response `node`, reference `reference`, numerator
    /// specific data type `spec` (8, 11, 12), ordinate `h` on 0, 10, 20, ... Hz.
    fn frf(node: i64, reference: i64, spec: i64, h: &[(f64, f64)]) -> uff::Function58 {
        use crate::formats::uff::{AxisSpec, Function58, OrdinateDataType};
        Function58 {
            id_lines: [
                "t".into(),
                "NONE".into(),
                "NONE".into(),
                "NONE".into(),
                "NONE".into(),
            ],
            function_type: FunctionType::Frf,
            function_id: 0,
            version: 0,
            load_case: 0,
            response_entity: "B".into(),
            response_node: node,
            response_direction: 3,
            reference_entity: "H".into(),
            reference_node: reference,
            reference_direction: 3,
            ordinate_data_type: OrdinateDataType::ComplexDouble,
            num_points: h.len(),
            z_axis_value: 0.0,
            abscissa_axis: AxisSpec {
                spec_data_type: 18,
                ..Default::default()
            },
            ordinate_axis: AxisSpec {
                spec_data_type: spec,
                length_exp: 1,
                ..Default::default()
            },
            denominator_axis: AxisSpec {
                spec_data_type: 13,
                force_exp: 1,
                ..Default::default()
            },
            z_axis: AxisSpec::default(),
            abscissa: Abscissa::Even {
                min: 0.0,
                increment: 10.0,
            },
            ordinate: Ordinate::Complex {
                re: h.iter().map(|v| v.0).collect(),
                im: h.iter().map(|v| v.1).collect(),
            },
            binary: false,
            line: 0,
        }
    }

    /// An accelerance A = iω·Y and a receptance X = Y/(iω) of one mobility Y come out of ingest
    /// as Y (the closed forms), labelled with what was measured, with the 0 Hz line of the
    /// accelerance named in a finding; a mobility passes unchanged.
    #[test]
    fn accelerance_and_receptance_are_converted_to_mobility() {
        let mob: Vec<(f64, f64)> = (0..6).map(|k| (1.0 + k as f64, 0.5 - k as f64)).collect();
        let w = |k: usize| std::f64::consts::TAU * 10.0 * k as f64;
        // iω(a + ib) = -ωb + iωa; (a + ib)/(iω) = b/ω - ia/ω.
        let acc: Vec<(f64, f64)> = mob
            .iter()
            .enumerate()
            .map(|(k, &(a, b))| (-w(k) * b, w(k) * a))
            .collect();
        let rec: Vec<(f64, f64)> = mob
            .iter()
            .enumerate()
            .map(|(k, &(a, b))| {
                if k == 0 {
                    (0.0, 0.0)
                } else {
                    (b / w(k), -a / w(k))
                }
            })
            .collect();
        let c = one_measurement(&[frf(1, 4, 11, &mob), frf(2, 4, 12, &acc), frf(3, 4, 8, &rec)]);
        let m = &c.measurements[0];
        assert!(m.quarantine.is_none(), "{:?}", m.quarantine);
        let by_node: BTreeMap<i64, &Record> = m.records.iter().map(|r| (r.node, r)).collect();
        assert_eq!(by_node[&1].measured_as, "velocity/force");
        assert_eq!(by_node[&2].measured_as, "acceleration/force");
        assert_eq!(by_node[&3].measured_as, "displacement/force");
        for node in [1, 2, 3] {
            let r = by_node[&node];
            let im = r.im.as_ref().unwrap();
            // At 0 Hz an accelerance has no mobility (set to 0) and a receptance's is 0.
            for k in usize::from(node != 1)..mob.len() {
                let tol = 1e-9 * (1.0 + mob[k].0.abs() + mob[k].1.abs());
                assert!(
                    (r.re[k] - mob[k].0).abs() < tol,
                    "node {node} line {k}: {}",
                    r.re[k]
                );
                assert!(
                    (im[k] - mob[k].1).abs() < tol,
                    "node {node} line {k}: {}",
                    im[k]
                );
            }
        }
        assert_eq!(
            (by_node[&2].re[0], by_node[&2].im.as_ref().unwrap()[0]),
            (0.0, 0.0)
        );
        let conv: Vec<&Finding> = c
            .findings
            .iter()
            .filter(|f| f.code == "uff.converted_ordinate")
            .collect();
        assert_eq!(conv.len(), 2, "{conv:?}");
        assert!(conv.iter().any(|f| f.message.contains("acceleration/force")
            && f.message.contains("divided by iω")
            && f.message.contains("1 line(s) at 0 Hz")));
        assert!(conv
            .iter()
            .any(|f| f.message.contains("displacement/force")
                && f.message.contains("multiplied by iω")));
    }

    /// A roving hammer (one response node, the reference moving) is read by reciprocity: one
    /// record per excited node, all referenced to the fixed response node, said in a finding;
    /// a fixed-reference measurement is not mistaken for one.
    #[test]
    fn a_roving_hammer_is_read_by_reciprocity() {
        let h: Vec<(f64, f64)> = (0..4).map(|k| (k as f64, 1.0)).collect();
        let c = one_measurement(&[frf(4, 1, 11, &h), frf(4, 2, 11, &h), frf(4, 3, 11, &h)]);
        let m = &c.measurements[0];
        assert!(m.quarantine.is_none(), "{:?}", m.quarantine);
        let nodes: Vec<(i64, i64)> = m
            .records
            .iter()
            .map(|r| (r.node, r.reference_node))
            .collect();
        assert_eq!(nodes, vec![(1, 4), (2, 4), (3, 4)]);
        assert_eq!(m.reference_node(), Some(4));
        assert!(m.points.iter().any(|p| p.node == 4 && p.is_reference));
        assert!(c.findings.iter().any(|f| f.code == "uff.roving_reference"));
        assert!(!c.findings.iter().any(|f| f.code == "uff.mixed_reference"));
        // Bad input: a reference without coordinates loses its record only (named), and a
        // record whose ordinate is no motion (a stress) is dropped with what was expected.
        let mut bad = frf(4, 9, 11, &h);
        bad.line = 0;
        let mut stress = frf(4, 3, 11, &h);
        stress.ordinate_axis.spec_data_type = 2;
        let c = one_measurement(&[frf(4, 1, 11, &h), frf(4, 2, 11, &h), bad, stress]);
        let nodes: Vec<i64> = c.measurements[0].records.iter().map(|r| r.node).collect();
        assert_eq!(nodes, vec![1, 2]);
        assert!(c.findings.iter().any(|f| f.code == "uff.unknown_node"
            && f.message.contains("response node 9")
            && f.severity == Severity::RecordDropped));
        assert!(c.findings.iter().any(|f| f.code == "uff.ordinate_quantity"
            && f.message.contains("specific data type 2 names no motion")));
        // A fixed reference over several response nodes: the ordinary scan.
        let c = one_measurement(&[frf(1, 4, 11, &h), frf(2, 4, 11, &h)]);
        assert!(!c.findings.iter().any(|f| f.code == "uff.roving_reference"));
        let nodes: Vec<i64> = c.measurements[0].records.iter().map(|r| r.node).collect();
        assert_eq!(nodes, vec![1, 2]);
    }

    /// Mode sets (dataset 55) are read and named, never silently skipped: beside FRFs a
    /// warning says the FRFs are identified and the sets kept for comparison; alone they are
    /// the measurement's modes; a set that is no mode is dropped naming its line.
    #[test]
    fn mode_sets_are_kept_beside_frfs_and_are_the_modes_of_a_measurement_without_records() {
        let ds55 = b"    -1\n    55\nNONE\nNONE\nNONE\nNONE\nNONE\n         1         2         2         8         2         3\n         2         4         1         1\n  4.12500e+02  0.00000e+00  1.10000e-02  0.00000e+00\n         1\n  0.00000e+00  0.00000e+00  1.00000e+00\n    -1\n";
        let h: Vec<(f64, f64)> = (0..4).map(|k| (k as f64, 1.0)).collect();
        let c = one_measurement_with(&[frf(1, 4, 11, &h), frf(2, 4, 11, &h)], ds55);
        let m = &c.measurements[0];
        assert!(m.quarantine.is_none());
        assert_eq!((m.records.len(), m.vendor_modes.len()), (2, 1));
        let w = c
            .findings
            .iter()
            .find(|f| f.code == "uff.mode_sets_not_used")
            .unwrap();
        assert_eq!(w.severity, Severity::Warning);
        assert!(
            w.message
                .contains("1 dataset-55 mode(s) (412.5 Hz at line ")
                && w.message.contains("vendor_modes.parquet"),
            "{}",
            w.message
        );

        // Modes only: a normal mode, a complex one (analysis type 3, eigenvalue of 800 Hz at
        // 2 % damping; one of its nodes has no coordinates), and a frequency response (type
        // 5), which is no mode. The measurement is not quarantined; its modes ascend.
        let wn = std::f64::consts::TAU * 800.0;
        let (sigma, wd) = (-0.02 * wn, wn * (1.0f64 - 0.0004).sqrt());
        let complex = format!("    -1\n    55\nNONE\nNONE\nNONE\nNONE\nNONE\n         1         3         2         8         5         3\n         2         6         1         2\n {sigma:.10e} {wd:.10e} 0.0 0.0 0.0 0.0\n         2\n 0.0 0.0 0.0 0.0 1.0 0.1\n         3\n 0.0 0.0 0.0 0.0 -0.5 -0.05\n         9\n 0.0 0.0 0.0 0.0 1.0 0.0\n    -1\n");
        let response = b"    -1\n    55\nNONE\nNONE\nNONE\nNONE\nNONE\n         1         5         2         8         2         3\n         2         1         1         1\n  1.00000e+02\n         1\n  0.00000e+00  0.00000e+00  1.00000e+00\n    -1\n";
        let bytes = [complex.as_bytes(), ds55, response].concat();
        let c = one_measurement_with(&[], &bytes);
        let m = &c.measurements[0];
        assert!(m.quarantine.is_none(), "{:?}", m.quarantine);
        assert_eq!(m.vendor_modes.len(), 2, "{:?}", c.findings);
        let (a, b) = (&m.vendor_modes[0], &m.vendor_modes[1]);
        assert_eq!(
            (a.freq_hz, a.damping_ratio, a.analysis_type),
            (412.5, 0.011, 2)
        );
        assert_eq!(
            (a.nodes.clone(), a.shape.clone(), a.mpc),
            (vec![1], vec![1.0], 1.0)
        );
        assert!((b.freq_hz - 800.0).abs() < 1e-6 && (b.damping_ratio - 0.02).abs() < 1e-9);
        assert_eq!((b.analysis_type, b.mode_number), (3, Some(2)));
        assert_eq!(b.nodes, vec![2, 3]);
        assert!((b.shape[0] - 1.0).abs() < 1e-12 && (b.shape[1] + 0.5).abs() < 1e-12);
        assert!((b.mpc - 1.0).abs() < 1e-12, "{}", b.mpc);
        let has: Vec<(i64, bool)> = m.points.iter().map(|p| (p.node, p.has_record)).collect();
        assert_eq!(has, vec![(1, true), (2, true), (3, true), (4, false)]);
        let code = |code: &str| c.findings.iter().find(|f| f.code == code).unwrap();
        assert!(code("uff.vendor_modes").message.contains("2 mode(s)"));
        let nodes = code("uff.mode_set_nodes");
        assert!(
            nodes.message.contains("1 node(s) without coordinates"),
            "{}",
            nodes.message
        );
        assert!(nodes.line.is_some());
        let dropped = code("uff.mode_set_type");
        assert_eq!(dropped.severity, Severity::RecordDropped);
        assert!(
            dropped.message.contains("analysis type 5"),
            "{}",
            dropped.message
        );
        assert!(dropped.line > nodes.line, "{:?}", dropped.line);
        assert_eq!(m.dropped, 1);

        // Neither records nor modes: quarantined, saying what was expected.
        let c = one_measurement_with(&[], response);
        let q = c.measurements[0].quarantine.as_deref().unwrap();
        assert!(
            q.contains("no usable response record") && q.contains("no mode set"),
            "{q}"
        );
    }
}

//! Writers of the ingest stage's outputs: the six Parquet tables, `campaign.mcap` and
//! `ingest_report.json`, from a checked [`Campaign`]. Same campaign → same bytes, whatever the
//! thread count.

use crate::campaign::{Campaign, Measurement, Point, Record, VendorMode};
use crate::findings::{Finding, Findings};
use crate::io::manifest;
use crate::io::mcap_writer::{
    encoding_of, BalanceMsg, CampaignMcap, F64Le, FunctionMsg, PointMsg, ScanPointsMsg, SheetMsg,
    VendorModeMsg,
};
use crate::io::tables::{self, TableSpec};
use anyhow::Context;
use arrow::array::{
    ArrayRef, BooleanArray, Float64Array, Float64Builder, Int32Array, Int64Array, ListBuilder,
    StringArray,
};
use arrow::datatypes::{DataType, Field};
use serde::Serialize;
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Names of the files the stage writes into its output directory.
pub const OUTPUTS: [&str; 9] = [
    "measurements.parquet",
    "scan_points.parquet",
    "frf.parquet",
    "vendor_modes.parquet",
    "scale_readings.parquet",
    "masses.parquet",
    "specimens.parquet",
    "campaign.mcap",
    "ingest_report.json",
];

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
        f64s(ms.iter().map(|m| m.row.dimensions_mm[0])),
        f64s(ms.iter().map(|m| m.row.dimensions_mm[1])),
        f64s(ms.iter().map(|m| m.row.dimensions_mm[2])),
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

pub fn write_outputs(c: &Campaign, out: &Path, fingerprint: &str) -> anyhow::Result<Vec<PathBuf>> {
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
    // vendor modes
    let vm: Vec<(&str, usize, &VendorMode)> = c
        .measurements
        .iter()
        .filter(|m| m.quarantine.is_none())
        .flat_map(|m| {
            m.vendor_modes
                .iter()
                .enumerate()
                .map(move |(k, v)| (m.row.measurement_id.as_str(), k, v))
        })
        .collect();
    write_table(
        &p("vendor_modes.parquet"),
        &tables::VENDOR_MODES,
        &prov,
        &[],
        vec![
            strs(vm.iter().map(|(m, _, _)| Some(*m))),
            i32s(vm.iter().map(|(_, k, _)| Some(*k as i32 + 1))),
            i64s(vm.iter().map(|(_, _, v)| v.mode_number)),
            i32s(vm.iter().map(|(_, _, v)| Some(v.analysis_type as i32))),
            i64s(vm.iter().map(|(_, _, v)| Some(v.line as i64))),
            f64s(vm.iter().map(|(_, _, v)| Some(v.freq_hz))),
            f64s(vm.iter().map(|(_, _, v)| Some(v.damping_ratio))),
            f64s(vm.iter().map(|(_, _, v)| Some(v.mpc))),
            f64s(vm.iter().map(|(_, _, v)| Some(v.mpd_deg))),
            tables::list_i64_col(vm.iter().map(|(_, _, v)| v.nodes.clone())),
            tables::list_f64_col(vm.iter().map(|(_, _, v)| v.shape.clone())),
        ],
    )?;

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
            strs(rs.iter().map(|r| r.sheet_board_id.as_deref())),
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
            i32s(ms.iter().map(|m| Some(m.n_days as i32))),
            f64s(ms.iter().map(|m| Some(m.day_means_ss_g2))),
            f64s(ms.iter().map(|m| Some(m.day_share_sq_sum))),
        ],
    )?;

    // specimens
    let sp = &c.specimens;
    write_table(
        &p("specimens.parquet"),
        &tables::SPECIMENS,
        &prov,
        &[],
        vec![
            strs(sp.iter().map(|s| Some(s.board_id.as_str()))),
            f64s(sp.iter().map(|s| s.dimensions_mm[0])),
            f64s(sp.iter().map(|s| s.dimensions_mm[1])),
            f64s(sp.iter().map(|s| s.dimensions_mm[2])),
            i32s(sp.iter().map(|s| Some(s.n_rows[0] as i32))),
            i32s(sp.iter().map(|s| Some(s.n_rows[1] as i32))),
            i32s(sp.iter().map(|s| Some(s.n_rows[2] as i32))),
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
                    strs(recs.iter().map(|(_, r)| Some(r.measured_as.as_str()))),
                    f64s(recs.iter().map(|(_, r)| Some(r.freq_start_hz))),
                    f64s(recs.iter().map(|(_, r)| Some(r.freq_step_hz))),
                    i32s(recs.iter().map(|(_, r)| Some(r.re.len() as i32))),
                    list_f64(recs.iter().map(|(_, r)| Some(r.re.as_slice()))),
                    list_f64(recs.iter().map(|(_, r)| r.im.as_deref())),
                ],
            )?;
            log::debug(format_args!(
                "frf.parquet written in {:.2} s",
                t_big.elapsed().as_secs_f64()
            ));
            Ok(())
        },
        || -> anyhow::Result<()> {
            write_mcap(c, &p("campaign.mcap"), &prov)?;
            log::debug(format_args!(
                "campaign.mcap written in {:.2} s",
                t_big.elapsed().as_secs_f64()
            ));
            Ok(())
        },
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
        // The spectra dominate the file. They are CBOR byte strings, so encoding is a copy:
        // each message goes into one reused buffer and straight to the writer (holding all
        // encoded messages at once cost 160 MB of page faults on the paper campaign, and
        // encoding in parallel gained nothing once the spectra stopped being JSON text).
        let mut buf = Vec::new();
        for m in c.measurements.iter().filter(|m| m.quarantine.is_none()) {
            let t = m.row.date_unix_ns.unwrap_or(0).max(0) as u64;
            let id = &m.row.measurement_id;
            w.write(
                "/scan_points",
                t,
                &ScanPointsMsg {
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
                },
            )?;
            for (topic, recs) in [("/frf", &m.records), ("/coherence", &m.coherence)] {
                for r in recs {
                    buf.clear();
                    encoding_of(topic).encode_into(
                        &FunctionMsg {
                            measurement_id: id,
                            node: r.node,
                            function_type: r.function_type,
                            response_direction: r.response_direction,
                            reference_node: r.reference_node,
                            reference_direction: r.reference_direction,
                            ordinate_unit: r.ordinate_unit,
                            measured_as: &r.measured_as,
                            freq_start_hz: r.freq_start_hz,
                            freq_step_hz: r.freq_step_hz,
                            re: F64Le(&r.re),
                            im: F64Le(r.im.as_deref().unwrap_or_default()),
                        },
                        &mut buf,
                    )?;
                    w.write_encoded(topic, t, &buf)?;
                }
            }
            for (k, v) in m.vendor_modes.iter().enumerate() {
                w.write(
                    "/vendor_modes",
                    t,
                    &VendorModeMsg {
                        measurement_id: id,
                        mode: k as i32 + 1,
                        mode_number: v.mode_number,
                        analysis_type: v.analysis_type,
                        uff_line: v.line as u64,
                        freq_hz: v.freq_hz,
                        damping_ratio: v.damping_ratio,
                        mpc: v.mpc,
                        mpd_deg: v.mpd_deg,
                        node: &v.nodes,
                        shape: &v.shape,
                    },
                )?;
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
                    sheet_board_id: r.sheet_board_id.clone(),
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

pub fn severity_counts(f: &Findings) -> BTreeMap<String, usize> {
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

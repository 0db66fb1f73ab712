//! The bad-input suite: each broken input gets a clear error or a quarantine naming the file,
//! line or record; nothing panics, and the good measurements still come through.

use crate::common::*;
use std::path::{Path, PathBuf};

struct Run {
    code: Option<i32>,
    stderr: String,
    report: Option<serde_json::Value>,
}

fn ingest(c: &Path) -> Run {
    let out = c.parent().unwrap().join("out");
    let o = hbmu(&[
        "ingest",
        c.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "-v",
    ]);
    let err = stderr(&o);
    assert!(!err.contains("panicked"), "panic: {err}");
    let report = std::fs::read(out.join("ingest_report.json"))
        .ok()
        .map(|b| serde_json::from_slice(&b).unwrap());
    Run {
        code: o.status.code(),
        stderr: err,
        report,
    }
}

impl Run {
    fn findings(&self) -> Vec<serde_json::Value> {
        self.report.as_ref().unwrap()["findings"]
            .as_array()
            .unwrap()
            .clone()
    }
    fn with_code(&self, code: &str) -> Vec<serde_json::Value> {
        self.findings()
            .into_iter()
            .filter(|f| f["code"] == code)
            .collect()
    }
    fn quarantined(&self) -> Vec<String> {
        self.report.as_ref().unwrap()["quarantined"]
            .as_array()
            .unwrap()
            .iter()
            .map(|q| q["measurement_id"].as_str().unwrap().to_string())
            .collect()
    }
    /// Measurements with status ok in measurements.parquet, read back through arrow.
    fn ok_count(&self, c: &Path) -> usize {
        let out = c.parent().unwrap().join("out");
        let file = std::fs::File::open(out.join("measurements.parquet")).unwrap();
        let r = parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder::try_new(file)
            .unwrap()
            .build()
            .unwrap();
        let mut n = 0;
        for b in r {
            let b = b.unwrap();
            let s = b
                .column_by_name("status")
                .unwrap()
                .as_any()
                .downcast_ref::<arrow::array::StringArray>()
                .unwrap()
                .clone();
            n += s.iter().filter(|v| *v == Some("ok")).count();
        }
        n
    }
}

fn uff(c: &Path, m: &str) -> PathBuf {
    c.join("vibrometer").join(format!("{m}.uff"))
}

/// Line index (0-based) of the `58` number line of the k-th dataset 58 in the file.
fn dataset58(lines: &[String], k: usize) -> usize {
    lines
        .iter()
        .enumerate()
        .filter(|(_, l)| l.trim() == "58")
        .nth(k)
        .map(|(i, _)| i)
        .expect("dataset present")
}

fn edit_lines(p: &Path, f: impl FnOnce(&mut Vec<String>)) {
    let text = std::fs::read_to_string(p).unwrap();
    let mut lines: Vec<String> = text.split('\n').map(|s| s.to_string()).collect();
    f(&mut lines);
    std::fs::write(p, lines.join("\n")).unwrap();
}

#[test]
fn truncated_uff_drops_the_last_dataset_only() {
    let (_t, c) = campaign_copy();
    let p = uff(&c, "M001");
    let bytes = std::fs::read(&p).unwrap();
    std::fs::write(&p, &bytes[..bytes.len() - 3000]).unwrap();
    let r = ingest(&c);
    assert_eq!(r.code, Some(0), "{}", r.stderr);
    let bad = r.with_code("uff.bad_dataset");
    assert_eq!(bad.len(), 1, "{:#?}", r.findings());
    assert_eq!(bad[0]["file"], "vibrometer/M001.uff");
    assert!(bad[0]["line"].as_u64().unwrap() > 1);
    assert_eq!(r.ok_count(&c), 9);
}

#[test]
fn file_that_is_not_uff_is_quarantined_and_others_proceed() {
    let (_t, c) = campaign_copy();
    std::fs::write(uff(&c, "M002"), "this is not a universal file\n").unwrap();
    let r = ingest(&c);
    assert_eq!(r.code, Some(3), "exit code says something was quarantined");
    assert_eq!(r.quarantined(), vec!["M002"]);
    assert_eq!(r.ok_count(&c), 8);
    assert!(r.stderr.contains("M002"), "{}", r.stderr);
}

#[test]
fn wrong_record_length_and_non_numeric_and_nan_are_located() {
    let (_t, c) = campaign_copy();
    edit_lines(&uff(&c, "M001"), |l| {
        let i = dataset58(l, 2);
        l.remove(i + 20); // one data line fewer than declared
        let j = dataset58(l, 5);
        l[j + 15] = l[j + 15].replacen("e", "x", 1); // non-numeric field
        let k = dataset58(l, 8);
        let first = l[k + 13].split_whitespace().next().unwrap().to_string();
        l[k + 13] = l[k + 13].replacen(&first, "NaN", 1); // NaN ordinate
    });
    let r = ingest(&c);
    assert_eq!(r.code, Some(0), "{}", r.stderr);
    let bad = r.with_code("uff.bad_dataset");
    assert_eq!(bad.len(), 3, "{:#?}", r.findings());
    let msgs: Vec<&str> = bad.iter().map(|f| f["message"].as_str().unwrap()).collect();
    assert!(msgs.iter().any(|m| m.contains("expected")), "{msgs:?}");
    assert!(bad.iter().all(|f| f["line"].as_u64().is_some()));
    assert_eq!(r.ok_count(&c), 9);
}

#[test]
fn unknown_function_type_is_dropped_with_a_finding() {
    let (_t, c) = campaign_copy();
    edit_lines(&uff(&c, "M004"), |l| {
        let i = dataset58(l, 0);
        l[i + 6] = format!("{:>10}", 9) + &l[i + 6][10..];
    });
    let r = ingest(&c);
    let f = r.with_code("uff.function_type");
    assert_eq!(f.len(), 1, "{:#?}", r.findings());
    assert!(f[0]["message"]
        .as_str()
        .unwrap()
        .contains("function type 9"));
    assert_eq!(f[0]["measurement_id"], "M004");
    assert_eq!(r.ok_count(&c), 9);
}

#[test]
fn missing_file_and_duplicate_id_are_quarantined() {
    let (_t, c) = campaign_copy();
    let sheet = c.join("campaign.csv");
    let mut s = std::fs::read_to_string(&sheet).unwrap();
    s.push_str("M099,PCB-01,free,vibrometer/nope.uff,,,,,,,\r\n");
    s.push_str("M001,PCB-02,free,vibrometer/M004.uff,,,,,,,\r\n");
    std::fs::write(&sheet, s).unwrap();
    let r = ingest(&c);
    assert_eq!(r.code, Some(3));
    let mut q = r.quarantined();
    q.sort();
    assert_eq!(q, vec!["M001", "M099"]);
    let dup = r.with_code("sheet.duplicate_id");
    assert_eq!(dup.len(), 1);
    assert!(dup[0]["line"].as_u64().unwrap() > 1);
    assert!(!r.with_code("sheet.missing_file").is_empty());
    assert_eq!(r.ok_count(&c), 9, "the nine good rows still come through");
}

#[test]
fn missing_header_column_is_a_clear_error() {
    let (_t, c) = campaign_copy();
    let sheet = c.join("campaign.csv");
    let s = std::fs::read_to_string(&sheet)
        .unwrap()
        .replacen("board_id,", "board,", 1);
    std::fs::write(&sheet, s).unwrap();
    let r = ingest(&c);
    assert_eq!(r.code, Some(1));
    assert!(r.stderr.contains("board_id"), "{}", r.stderr);
    assert!(r.stderr.contains("campaign.csv:1"), "{}", r.stderr);
}

#[test]
fn garbage_and_unstable_balance_lines() {
    let (_t, c) = campaign_copy();
    let log = c.join("scale/balance.log");
    let mut s = std::fs::read_to_string(&log).unwrap();
    s.push_str("complete garbage\n");
    s.push_str("2026-11-01T09:00:00 PCB-02 S D     99.0000 g\n");
    s.push_str("2026-11-01T09:00:01 PCB-02 S Q what\n");
    s.push_str("2026-11-01T09:00:02 PCB-02 EL\n");
    std::fs::write(&log, s).unwrap();
    let before = {
        let (_t2, c2) = campaign_copy();
        let r = ingest(&c2);
        assert_eq!(r.code, Some(0));
        mass_of(&c2, "PCB-02")
    };
    let r = ingest(&c);
    assert_eq!(r.code, Some(0));
    let bad: Vec<_> = r
        .findings()
        .into_iter()
        .filter(|f| f["code"].as_str().unwrap().starts_with("balance."))
        .collect();
    assert_eq!(bad.len(), 2, "{bad:#?}");
    assert!(bad.iter().all(|f| f["file"] == "scale/balance.log"));
    // The dynamic 99 g reading does not enter the mass.
    assert_eq!(mass_of(&c, "PCB-02"), before);
}

fn mass_of(c: &Path, board: &str) -> f64 {
    let out = c.parent().unwrap().join("out");
    let file = std::fs::File::open(out.join("masses.parquet")).unwrap();
    let r = parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder::try_new(file)
        .unwrap()
        .build()
        .unwrap();
    for b in r {
        let b = b.unwrap();
        let ids = b
            .column_by_name("board_id")
            .unwrap()
            .as_any()
            .downcast_ref::<arrow::array::StringArray>()
            .unwrap()
            .clone();
        let m = b
            .column_by_name("mass_g")
            .unwrap()
            .as_any()
            .downcast_ref::<arrow::array::Float64Array>()
            .unwrap()
            .clone();
        for i in 0..b.num_rows() {
            if ids.value(i) == board {
                return m.value(i);
            }
        }
    }
    panic!("no mass for {board}")
}

#[test]
fn empty_campaign_is_a_clear_error() {
    let t = tempfile::tempdir().unwrap();
    let c = t.path().join("campaign");
    std::fs::create_dir_all(&c).unwrap();
    let r = ingest(&c);
    assert_eq!(r.code, Some(1));
    assert!(r.stderr.contains("campaign.csv"), "{}", r.stderr);
    std::fs::write(
        c.join("campaign.csv"),
        "measurement_id,board_id,setup,file\n",
    )
    .unwrap();
    let r = ingest(&c);
    assert_eq!(r.code, Some(1));
    assert!(r.stderr.contains("empty campaign"), "{}", r.stderr);
}

#[test]
fn uff_not_in_sheet_and_unknown_files_are_reported() {
    let (_t, c) = campaign_copy();
    std::fs::copy(uff(&c, "M001"), uff(&c, "stray")).unwrap();
    std::fs::write(c.join("README.txt"), "notes").unwrap();
    let r = ingest(&c);
    assert_eq!(r.code, Some(0));
    assert_eq!(r.with_code("campaign.uff_not_in_sheet").len(), 1);
    assert_eq!(r.with_code("campaign.ignored_file").len(), 1);
}

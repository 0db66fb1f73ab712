//! Ingest stage end to end: the example campaign, reproducibility, and the bad-input suite.

use crate::common::*;
use std::path::Path;

mod bad_input;

fn read_json(p: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(p).unwrap()).unwrap()
}

#[test]
fn example_campaign_ingests_cleanly() {
    let (_t, c) = campaign_copy();
    let out = c.parent().unwrap().join("out");
    let o = hbmu(&[
        "ingest",
        c.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    for f in hbmu::stage::ingest::OUTPUTS {
        assert!(out.join(f).is_file(), "missing output {f}");
    }
    let report = read_json(&out.join("ingest_report.json"));
    assert_eq!(report["measurements"], 9);
    assert_eq!(report["quarantined"].as_array().unwrap().len(), 0);
    // The only findings are the deliberate ones: one invalid scan point per bolted measurement.
    let findings = report["findings"].as_array().unwrap();
    assert_eq!(findings.len(), 3, "{findings:#?}");
    assert!(findings
        .iter()
        .all(|f| f["code"] == "uff.points_without_record"));
}

fn files_bytes(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut v: Vec<(String, Vec<u8>)> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| {
            !p.file_name()
                .unwrap()
                .to_string_lossy()
                .ends_with(".manifest.json")
        })
        .map(|p| {
            (
                p.file_name().unwrap().to_string_lossy().into_owned(),
                std::fs::read(&p).unwrap(),
            )
        })
        .collect();
    v.sort();
    v
}

#[test]
fn reproducible_bytes_noop_rerun_and_change_detection() {
    let (t, c) = campaign_copy();
    let out1 = t.path().join("out1");
    let out2 = t.path().join("out2");
    for (out, threads) in [(&out1, "1"), (&out2, "2")] {
        let o = hbmu(&[
            "--threads",
            threads,
            "ingest",
            c.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ]);
        assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    }
    // Same inputs → same bytes, whatever the thread count.
    assert_eq!(files_bytes(&out1), files_bytes(&out2));
    let m1 = read_json(&out1.join("ingest.manifest.json"));
    let m2 = read_json(&out2.join("ingest.manifest.json"));
    for k in ["fingerprint", "inputs", "outputs", "config_blake3"] {
        assert_eq!(m1[k], m2[k], "manifest field {k}");
    }
    assert_eq!(m1["stage"], "ingest");
    assert!(m1["inputs"].as_array().unwrap().len() >= 11);

    // Touch nothing → no-op (manifest untouched, message says so).
    let before = std::fs::read(out1.join("ingest.manifest.json")).unwrap();
    let o = hbmu(&[
        "ingest",
        c.to_str().unwrap(),
        "--out",
        out1.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(0));
    assert!(stderr(&o).contains("up to date"), "{}", stderr(&o));
    assert_eq!(
        before,
        std::fs::read(out1.join("ingest.manifest.json")).unwrap()
    );

    // A damaged output is detected and the stage reruns.
    std::fs::write(out1.join("masses.parquet"), b"damaged").unwrap();
    let o = hbmu(&[
        "ingest",
        c.to_str().unwrap(),
        "--out",
        out1.to_str().unwrap(),
    ]);
    assert!(!stderr(&o).contains("up to date"));
    assert_eq!(files_bytes(&out1), files_bytes(&out2));

    // Change one input → the stage reruns and the new fingerprint differs.
    let log = c.join("scale/balance.log");
    let mut s = std::fs::read_to_string(&log).unwrap();
    s.push_str("2026-11-02T10:00:00 PCB-01 S S    13.0001 g\n");
    std::fs::write(&log, s).unwrap();
    let o = hbmu(&[
        "ingest",
        c.to_str().unwrap(),
        "--out",
        out1.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(0));
    assert!(!stderr(&o).contains("up to date"));
    let m3 = read_json(&out1.join("ingest.manifest.json"));
    assert_ne!(m3["fingerprint"], m1["fingerprint"]);
    let changed: Vec<_> = m3["inputs"]
        .as_array()
        .unwrap()
        .iter()
        .zip(m1["inputs"].as_array().unwrap())
        .filter(|(a, b)| a != b)
        .map(|(a, _)| a["path"].as_str().unwrap().to_string())
        .collect();
    assert_eq!(changed, vec!["scale/balance.log".to_string()]);
}

#[test]
fn no_temp_files_left_behind() {
    let (t, c) = campaign_copy();
    let out = t.path().join("out");
    hbmu(&[
        "ingest",
        c.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    let stray: Vec<_> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with('.'))
        .collect();
    assert!(stray.is_empty(), "{stray:?}");
}

//! The virtual lab end to end: `lab simulate` → `ingest` → `extract` → `pair` on the default
//! (paper-like) campaign, checked against the truth file the lab keeps apart.

use crate::common::*;
use std::collections::BTreeSet;
use std::path::Path;

fn json(p: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(p).unwrap()).unwrap()
}

#[test]
fn default_campaign_through_the_pipeline_matches_its_truth() {
    let t = tempfile::tempdir().unwrap();
    let p = |n: &str| t.path().join(n).to_str().unwrap().to_string();

    // The truth must stay outside the campaign directory.
    let o = hbmu(&[
        "lab",
        "simulate",
        "paper",
        "--out",
        &p("campaign"),
        "--truth",
        &p("campaign/truth.json"),
    ]);
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr(&o).contains("kept apart"), "{}", stderr(&o));

    let o = hbmu(&[
        "lab",
        "simulate",
        "paper",
        "--out",
        &p("campaign"),
        "--truth",
        &p("truth.json"),
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let truth = json(&t.path().join("truth.json"));
    let ms = truth["measurements"].as_array().unwrap();
    assert_eq!(
        ms.len(),
        7 * 5 + 2 * 9 + 4 * 3,
        "the paper's campaign shape"
    );

    // Ingest: no findings but the deliberate imperfections, which it reports.
    let o = hbmu(&["ingest", &p("campaign"), "--out", &p("ingest")]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let report = json(&t.path().join("ingest/ingest_report.json"));
    assert_eq!(report["quarantined"].as_array().unwrap().len(), 0);
    let mut expected_missing = BTreeSet::new();
    for m in ms {
        if !m["missing_nodes"].as_array().unwrap().is_empty() {
            expected_missing.insert(m["measurement_id"].as_str().unwrap().to_string());
        }
    }
    let garbled = truth["garbled_balance_lines"].as_array().unwrap().len();
    let mut reported_missing = BTreeSet::new();
    let mut balance_findings = 0;
    for f in report["findings"].as_array().unwrap() {
        match f["code"].as_str().unwrap() {
            "uff.points_without_record" => {
                reported_missing.insert(f["measurement_id"].as_str().unwrap().to_string());
            }
            "balance.unknown_response" | "balance.unparsed_line" => balance_findings += 1,
            other => panic!("unexpected finding {other}: {f}"),
        }
    }
    assert_eq!(reported_missing, expected_missing);
    assert_eq!(balance_findings, garbled);

    // Extraction: identified frequencies sit on the truth's, no spurious mode.
    let o = hbmu(&["extract", &p("ingest"), "--out", &p("extract")]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let batches = hbmu::io::tables::read_parquet(&t.path().join("extract/modes.parquet")).unwrap();
    let mut rel_errors = vec![];
    let mut damping_errors = vec![];
    for b in &batches {
        let c = hbmu::io::tables::Cols {
            batch: b,
            path: Path::new("modes.parquet"),
        };
        let (id, f, z) = (
            c.str("measurement_id").unwrap(),
            c.f64("freq_hz").unwrap(),
            c.f64("damping_ratio").unwrap(),
        );
        for i in 0..b.num_rows() {
            let m = ms
                .iter()
                .find(|m| m["measurement_id"] == id.value(i))
                .unwrap();
            let (err, dz) = m["modes"]
                .as_array()
                .unwrap()
                .iter()
                .filter(|tm| tm["in_band"].as_bool().unwrap())
                .map(|tm| {
                    let tf = tm["freq_hz"].as_f64().unwrap();
                    let tz = tm["damping_ratio"].as_f64().unwrap();
                    ((f.value(i) / tf - 1.0).abs(), (z.value(i) / tz - 1.0).abs())
                })
                .min_by(|a, b| a.0.total_cmp(&b.0))
                .unwrap();
            assert!(
                err < 0.005,
                "{}: {} Hz is no truth mode (spurious)",
                id.value(i),
                f.value(i)
            );
            rel_errors.push(err);
            damping_errors.push(dz);
        }
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    assert!(rel_errors.len() > 300, "{} modes", rel_errors.len());
    assert!(median(&mut rel_errors) < 5e-4, "median frequency error");
    assert!(median(&mut damping_errors) < 0.1, "median damping error");

    // Pairing: the four updating modes of the paper are present in every free measurement.
    let o = hbmu(&["pair", &p("extract"), "--out", &p("pair")]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let pres = hbmu::io::tables::read_parquet(&t.path().join("pair/presence.parquet")).unwrap();
    let mut used = BTreeSet::new();
    for b in &pres {
        let c = hbmu::io::tables::Cols {
            batch: b,
            path: Path::new("presence.parquet"),
        };
        let (s, l, u) = (
            c.str("setup").unwrap(),
            c.str("label").unwrap(),
            c.bool("used_for_updating").unwrap(),
        );
        for i in 0..b.num_rows() {
            if s.value(i) == "free" && u.value(i) {
                used.insert(l.value(i).to_string());
            }
        }
    }
    for l in ["torsion-1", "bending-x-1", "bending-y-1"] {
        assert!(
            used.contains(l),
            "{l} not present in every free measurement: {used:?}"
        );
    }
}

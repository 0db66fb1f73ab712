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

/// A small campaign of the realistic preset (every lab habit on) through `ingest`, `extract`
/// and `pair`: the invalid measurement is quarantined and the others come through, the board
/// population is the sheet's boards, and the scan points off the board (a bolt head, the
/// fixture) are named by ingest (file, node) and left out of the shapes by pair.
#[test]
fn realistic_campaign_keeps_the_sheet_boards_and_names_points_off_the_board() {
    let t = tempfile::tempdir().unwrap();
    let p = |n: &str| t.path().join(n).to_str().unwrap().to_string();
    std::fs::write(
        t.path().join("realistic.toml"),
        "name = \"realistic-small\"\nseed = 7\npreset = \"realistic\"\n\
         [campaign]\nn_boards = 2\nfree_per_board = 3\n\
         bolted = [{ boards = [1], per_board = 1, purpose = \"updating\" }]\n",
    )
    .unwrap();
    let o = hbmu(&[
        "lab",
        "simulate",
        &p("realistic.toml"),
        "--out",
        &p("campaign"),
        "--truth",
        &p("truth.json"),
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let truth = json(&t.path().join("truth.json"));
    let habits = &truth["habits"];

    // Ingest: exit 3, the one quarantined measurement being the one the lab marked invalid.
    let o = hbmu(&["ingest", &p("campaign"), "--out", &p("ingest")]);
    assert_eq!(o.status.code(), Some(3), "{}", stderr(&o));
    let report = json(&t.path().join("ingest/ingest_report.json"));
    let bad = habits["invalid_measurements"][0][0].as_str().unwrap();
    let quarantined: Vec<&str> = report["quarantined"]
        .as_array()
        .unwrap()
        .iter()
        .map(|q| q["measurement_id"].as_str().unwrap())
        .collect();
    assert_eq!(quarantined, vec![bad]);
    let findings = report["findings"].as_array().unwrap();
    let off: Vec<(String, i64)> = habits["off_board_nodes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| (v[0].as_str().unwrap().to_string(), v[1].as_i64().unwrap()))
        .collect();
    assert!(!off.is_empty());
    for (mid, node) in &off {
        assert!(
            findings.iter().any(|f| f["code"] == "uff.point_off_plane"
                && f["measurement_id"] == mid.as_str()
                && f["file"] == format!("vibrometer/{mid}.uff")
                && f["record"] == format!("node {node}")),
            "{mid} node {node}"
        );
    }
    // masses.parquet: the sheet's boards, nothing else.
    let mut ids = BTreeSet::new();
    for b in hbmu::io::tables::read_parquet(&t.path().join("ingest/masses.parquet")).unwrap() {
        let c = hbmu::io::tables::Cols {
            batch: &b,
            path: Path::new("masses.parquet"),
        };
        let s = c.str("board_id").unwrap();
        ids.extend((0..b.num_rows()).map(|i| s.value(i).to_string()));
    }
    assert_eq!(
        ids,
        BTreeSet::from(["PCB-01".to_string(), "PCB-02".to_string()])
    );

    // Extract skips the quarantined measurement; pair names the points off the board.
    let o = hbmu(&["extract", &p("ingest"), "--out", &p("extract")]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let o = hbmu(&["--verbose", "pair", &p("extract"), "--out", &p("pair")]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let err = stderr(&o);
    for (mid, node) in &off {
        assert!(
            err.lines().any(|l| l.contains("pair.point_outside_model")
                && l.contains(&format!("[{mid}]"))
                && l.contains(&format!("node {node} "))),
            "{mid} node {node}: {err}"
        );
    }
}

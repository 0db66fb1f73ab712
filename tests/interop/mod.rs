//! Interop with third-party clients: pandas/pyarrow read every table as documented, the
//! official `mcap` Python reader reads every channel and schema. (UFF interop with `pyuff` is
//! tested next to the UFF reader, in `src/io/uff/tests.rs`.)

use crate::common::*;

#[test]
fn pandas_and_mcap_read_ingest_outputs() {
    if !python_has(&["pandas", "pyarrow", "mcap", "cbor2"]) {
        return;
    }
    let (t, c) = campaign_copy();
    let out = t.path().join("out");
    let o = hbmu(&[
        "ingest",
        c.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let s = python(
        "read_outputs.py",
        &[
            out.to_str().unwrap(),
            repo().join("schemas").to_str().unwrap(),
        ],
    );
    let v: serde_json::Value = serde_json::from_str(s.trim()).unwrap();
    for t in [
        "measurements",
        "scan_points",
        "frf",
        "scale_readings",
        "masses",
    ] {
        assert!(v["tables"][t]["rows"].as_u64().unwrap() > 0, "{t}: {v}");
    }
    for topic in ["/sheet", "/scan_points", "/frf", "/coherence", "/balance"] {
        assert!(
            v["mcap"][topic]["messages"].as_u64().unwrap() > 0,
            "{topic}: {v}"
        );
    }
    assert_eq!(v["mcap"]["/sheet"]["messages"], 9);
    assert_eq!(v["mcap_metadata"][0], "campaign");
}

/// Few-point hammer tests as pyuff writes them (accelerance at three points, a roving hammer,
/// receptance): ingest gives each record as the mobility at its (response, reference) pair,
/// against the script's closed form, and keeps what was measured in `measured_as`. A
/// measurement of modes only (dataset 55, a normal and a complex mode) comes out of extract
/// as the written modes, `source = uff55`.
#[test]
fn pyuff_few_point_accelerance_and_roving_hammer_campaign_is_read_as_mobility() {
    if !python_has(&["pyuff", "pandas", "pyarrow", "numpy"]) {
        return;
    }
    let t = tempfile::tempdir().unwrap();
    let c = t.path().join("campaign");
    let out = t.path().join("ingest");
    let script = "pyuff_few_point_campaign.py";
    python(script, &["write", c.to_str().unwrap()]);
    let o = hbmu(&[
        "ingest",
        c.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let s = python(
        script,
        &["check", c.to_str().unwrap(), out.to_str().unwrap()],
    );
    let v: serde_json::Value = serde_json::from_str(s.trim()).unwrap();
    assert_eq!(v["records"], 10, "{v}");
    // M4 holds only the lab's modes (dataset 55): extract passes them through.
    let ex = t.path().join("extract");
    let o = hbmu(&[
        "extract",
        out.to_str().unwrap(),
        "--out",
        ex.to_str().unwrap(),
    ]);
    assert!(matches!(o.status.code(), Some(0 | 3)), "{}", stderr(&o));
    let s = python(script, &["check-modes", ex.to_str().unwrap()]);
    let v: serde_json::Value = serde_json::from_str(s.trim()).unwrap();
    assert_eq!(v["modes"], 2, "{v}");
}

mod gerber;

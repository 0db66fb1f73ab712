//! The stages after ingest, end to end through the CLI: `fe`, `extract`, `pair`.
//!
//! The example campaign is written by `data/example/make_example.py` (pyuff) from known modes:
//! free-free boards with natural frequencies 780, 955, 1870, 2560 Hz times a per-board scale
//! (PCB-01 1.000, PCB-02 1.012, PCB-03 0.991) and damping ratios 1.0, 0.8, 1.2, 0.9 %. Those
//! are the references here.

use crate::common::*;
use std::path::Path;

fn read_table(p: &Path) -> Vec<arrow::array::RecordBatch> {
    hbmu::io::tables::read_parquet(p).unwrap()
}

#[test]
fn extract_recovers_the_example_modes_and_pair_labels_them() {
    let (t, c) = campaign_copy();
    let w = t.path();
    let s = |p: &str| w.join(p).to_str().unwrap().to_string();
    let o = hbmu(&["ingest", c.to_str().unwrap(), "--out", &s("ingest")]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let o = hbmu(&["extract", &s("ingest"), "--out", &s("extract")]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let truth_f = [780.0, 955.0, 1870.0, 2560.0];
    let truth_z = [0.010, 0.008, 0.012, 0.009];
    let scale = |board: &str| match board {
        "PCB-01" => 1.0,
        "PCB-02" => 1.012,
        "PCB-03" => 0.991,
        b => panic!("unexpected board {b}"),
    };
    let mut checked = 0;
    for b in read_table(&w.join("extract/modes.parquet")) {
        let cols = hbmu::io::tables::Cols {
            batch: &b,
            path: Path::new("modes.parquet"),
        };
        let (setup, board, f, z) = (
            cols.str("setup").unwrap(),
            cols.str("board_id").unwrap(),
            cols.f64("freq_hz").unwrap(),
            cols.f64("damping_ratio").unwrap(),
        );
        for i in 0..b.num_rows() {
            if setup.value(i) != "free" {
                continue;
            }
            let k = truth_f
                .iter()
                .map(|t| (f.value(i) / (t * scale(board.value(i))) - 1.0).abs())
                .enumerate()
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .unwrap();
            assert!(k.1 < 5e-4, "mode at {} Hz is no truth mode", f.value(i));
            let dz = (z.value(i) / truth_z[k.0] - 1.0).abs();
            assert!(dz < 0.1, "damping {} vs {}", z.value(i), truth_z[k.0]);
            checked += 1;
        }
    }
    assert_eq!(checked, 6 * 4, "every free mode of every free measurement");

    let o = hbmu(&["pair", &s("extract"), "--out", &s("pair")]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let pairs = read_table(&w.join("pair/pairs.parquet"));
    let mut torsion_ok = 0;
    for b in &pairs {
        let cols = hbmu::io::tables::Cols {
            batch: b,
            path: Path::new("pairs.parquet"),
        };
        let (label, acc, f) = (
            cols.str("label").unwrap(),
            cols.bool("accepted").unwrap(),
            cols.f64("freq_hz").unwrap(),
        );
        for i in 0..b.num_rows() {
            if acc.value(i) && label.value(i) == "torsion-1" {
                assert!((f.value(i) - 780.0).abs() < 15.0);
                torsion_ok += 1;
            }
        }
    }
    assert_eq!(
        torsion_ok, 6,
        "the example's torsion mode is paired in every free measurement"
    );
    // A model mode carries one label in every measurement of its setup, whatever each
    // measurement scanned (labels come from the setup's model on a grid over the board).
    let mut labels: std::collections::BTreeMap<(String, i32), std::collections::BTreeSet<String>> =
        Default::default();
    for b in &pairs {
        let cols = hbmu::io::tables::Cols {
            batch: b,
            path: Path::new("pairs.parquet"),
        };
        let (setup, model_mode, label) = (
            cols.str("setup").unwrap(),
            b.column_by_name("model_mode")
                .unwrap()
                .as_any()
                .downcast_ref::<arrow::array::Int32Array>()
                .unwrap(),
            cols.str("label").unwrap(),
        );
        for i in 0..b.num_rows() {
            if arrow::array::Array::is_valid(model_mode, i) {
                labels
                    .entry((setup.value(i).to_string(), model_mode.value(i)))
                    .or_default()
                    .insert(label.value(i).to_string());
            }
        }
    }
    assert!(!labels.is_empty());
    for (k, v) in &labels {
        assert_eq!(v.len(), 1, "model mode {k:?} has labels {v:?}");
    }
}

#[test]
fn fe_modes_sensitivity_and_rom_through_the_cli() {
    let t = tempfile::tempdir().unwrap();
    let p = |n: &str| t.path().join(n).to_str().unwrap().to_string();
    let o = hbmu(&["fe", "modes", "--out", &p("free.parquet")]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let b = &read_table(&t.path().join("free.parquet"))[0];
    let cols = hbmu::io::tables::Cols {
        batch: b,
        path: Path::new("free.parquet"),
    };
    let f = cols.f64("freq_hz").unwrap();
    // The default board resembles the paper's: first free-free modes near 778 and 954 Hz.
    assert!((f.value(0) / 778.5 - 1.0).abs() < 0.03, "{}", f.value(0));
    assert!((f.value(1) / 954.4 - 1.0).abs() < 0.03, "{}", f.value(1));
    assert_eq!(cols.list_f64("shape_w", 0).unwrap().unwrap().len(), 77);

    // A stiffer E_x raises the x-bending mode: --set reaches the model.
    let o = hbmu(&[
        "fe",
        "modes",
        "--set",
        "e_x_pa=30e9",
        "--out",
        &p("stiff.parquet"),
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let b2 = &read_table(&t.path().join("stiff.parquet"))[0];
    let f2 = hbmu::io::tables::Cols {
        batch: b2,
        path: Path::new("stiff.parquet"),
    }
    .f64("freq_hz")
    .unwrap()
    .value(1);
    assert!(f2 > f.value(1) * 1.02);

    let o = hbmu(&[
        "fe",
        "modes",
        "--set",
        "nonsense=1",
        "--out",
        &p("x.parquet"),
    ]);
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr(&o).contains("known parameters"), "{}", stderr(&o));

    let o = hbmu(&["fe", "sensitivity", "--out", &p("sens.parquet")]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let o = hbmu(&["fe", "rom", "--out", &p("rom.npz")]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let bytes = std::fs::read(t.path().join("rom.npz")).unwrap();
    let rom = hbmu::fem::Rom::from_npz_bytes(&bytes).unwrap();
    assert_eq!(rom.n_modes, 8);
    // Up to date on a second run.
    let o = hbmu(&["fe", "rom", "--out", &p("rom.npz")]);
    assert!(stderr(&o).contains("up to date"), "{}", stderr(&o));
}

/// `fe modes` chooses the mesh (recorded in the metadata), keeps a given one, and reads
/// a board whose copper is a raster density map; a missing map file is named.
#[test]
fn fe_modes_chooses_the_mesh_and_reads_density_maps() {
    let t = tempfile::tempdir().unwrap();
    let p = |n: &str| t.path().join(n).to_str().unwrap().to_string();
    let meta = |f: &str| -> serde_json::Value {
        let file = std::fs::File::open(t.path().join(f)).unwrap();
        let r = parquet::file::reader::SerializedFileReader::new(file).unwrap();
        use parquet::file::reader::FileReader;
        let kv = r
            .metadata()
            .file_metadata()
            .key_value_metadata()
            .unwrap()
            .clone();
        let v = kv.iter().find(|k| k.key == "hbmu.fe.mesh").unwrap();
        serde_json::from_str(v.value.as_ref().unwrap()).unwrap()
    };
    // A board: the default with its top copper as a 16 × 10 raster of 0.5.
    let mut toml = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("data/boards/default.toml"),
    )
    .unwrap();
    toml = toml.replacen(
        "coverage = [\n  { kind = \"rect\", x0_m = 0.003",
        "density_maps = [{ file = \"top.csv\", x0_m = 0.0, y0_m = 0.0, x1_m = 0.08, y1_m = 0.05 }]\ncoverage = [\n  { kind = \"rect\", x0_m = 0.003",
        1,
    );
    assert!(toml.contains("top.csv"));
    std::fs::write(t.path().join("board.toml"), &toml).unwrap();
    let o = hbmu(&[
        "fe",
        "modes",
        "--board",
        &p("board.toml"),
        "--out",
        &p("x.parquet"),
    ]);
    assert_ne!(o.status.code(), Some(0));
    assert!(stderr(&o).contains("top.csv"), "{}", stderr(&o));
    let row = vec!["0.5"; 16].join(",");
    let csv = format!("# top copper\n{}\n", vec![row; 10].join("\n"));
    std::fs::write(t.path().join("top.csv"), csv).unwrap();
    let o = hbmu(&[
        "fe",
        "modes",
        "--board",
        &p("board.toml"),
        "--mesh-tol",
        "5e-4",
        "--out",
        &p("m.parquet"),
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let m = meta("m.parquet");
    assert_eq!(m["how"], "chosen");
    let chosen = &m["choice"]["chosen"];
    assert!(chosen["max_rel_error"].as_f64().unwrap() < 5e-4, "{m}");
    assert_eq!(m["nx"], chosen["mesh"][0]);
    let o = hbmu(&[
        "fe",
        "modes",
        "--board",
        &p("board.toml"),
        "--mesh",
        "20",
        "13",
        "--out",
        &p("g.parquet"),
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let m = meta("g.parquet");
    assert_eq!(
        (m["how"].as_str(), m["nx"].as_u64()),
        (Some("given"), Some(20))
    );
}

//! The default board: parses, weighs about 13 g, frequencies near the paper's.

use crate::fem::board::Board;
use crate::fem::model::{FeModel, Setup};

#[test]
fn default_board_mass_and_frequencies_resemble_the_paper() {
    // The in-plane moduli are the least-squares fit of this shear-deformable board to all
    // eight of the paper's means (data/boards/default.toml): -1.8 ... +2.9 % measured.
    let b = Board::default_board();
    let m = FeModel::build(&b, Setup::Free, &b.mesh).unwrap();
    let p = m.nominal_params();
    let mass = m.total_mass_kg(&p).unwrap();
    let modes = m.modes(&p, 8).unwrap();
    eprintln!(
        "mass {mass} kg, ndof {}, dropped {}, f {:?}",
        m.n_dof, modes.n_rigid_dropped, modes.freq_hz
    );
    let mb = FeModel::build(&b, Setup::bolted(), &b.mesh).unwrap();
    let mo = mb.modes(&mb.nominal_params(), 8).unwrap();
    eprintln!("bolted f {:?}", mo.freq_hz);
    assert!(
        (mass - 0.013).abs() < 0.0005,
        "mass {mass} kg, expected about 13 g"
    );
    assert_eq!(modes.n_rigid_dropped, 3);
    // Seed paper, Table 2, measured means (sorted by frequency).
    let paper_hz = [778.5, 954.4, 1872.0, 2402.0, 2562.0, 2966.0, 3537.0, 4116.0];
    for (f, p) in modes.freq_hz.iter().zip(paper_hz) {
        assert!((f - p).abs() < 0.035 * p, "{f} Hz vs paper {p} Hz");
    }
}

#[test]
fn bad_boards_are_rejected_with_the_field_named() {
    let good = crate::fem::board::DEFAULT_BOARD_TOML;
    let neg = good.replace("thickness_m = 1.5e-3", "thickness_m = -1.5e-3");
    let err = Board::from_toml_str(&neg).unwrap_err().to_string();
    assert!(
        err.contains("core.thickness_m") && err.contains("-0.0015"),
        "{err}"
    );
    let unknown = good.replace(
        "name = \"paper-pcb\"",
        "name = \"paper-pcb\"\ncolour = \"green\"",
    );
    assert!(matches!(
        Board::from_toml_str(&unknown),
        Err(crate::fem::FemError::BoardParse(_))
    ));
    let nu = good.replace("nu_xy = 0.14", "nu_xy = 1.5");
    assert!(Board::from_toml_str(&nu)
        .unwrap_err()
        .to_string()
        .contains("nu_xy"));
    let hole = good.replace("x_m = 0.075\ny_m = 0.045", "x_m = 0.095\ny_m = 0.045");
    assert!(Board::from_toml_str(&hole)
        .unwrap_err()
        .to_string()
        .contains("holes[3]"));
    // Holes need the joints' data; a board without holes does not.
    let start = good.find("[joint]").unwrap();
    let end = start + good[start..].find("\n\n").unwrap();
    let no_joint = format!("{}{}", &good[..start], &good[end..]);
    let err = Board::from_toml_str(&no_joint).unwrap_err().to_string();
    assert!(err.contains("4 holes but no [joint] section"), "{err}");
    let plate = std::fs::read_to_string(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data/boards/plate_300x200x3.toml"),
    )
    .unwrap();
    let b = Board::from_toml_str(&plate).unwrap();
    assert!(b.joint.is_none() && b.holes.is_empty());
}

#[test]
fn coverage_fraction_of_known_regions() {
    let mut b = Board::default_board();
    // Layer 0 covers y in [3, 22] mm: a cell inside is fully covered, one straddling
    // y = 22 mm by half, one in the gap not at all.
    let near = |f: f64, e: f64| assert!((f - e).abs() < 1e-12, "{f} vs {e}");
    near(b.coverage_fraction(0, 0.010, 0.010, 0.012, 0.012), 1.0);
    near(b.coverage_fraction(0, 0.010, 0.021, 0.012, 0.023), 0.5);
    near(b.coverage_fraction(0, 0.010, 0.023, 0.012, 0.025), 0.0);
    // Polygon (triangle) covers exactly half of its bounding square.
    b.copper[0].coverage = vec![crate::fem::board::Region::Polygon {
        vertices_m: vec![[0.0, 0.0], [0.01, 0.0], [0.0, 0.01]],
        fraction: 1.0,
    }];
    let f = b.coverage_fraction(0, 0.0, 0.0, 0.01, 0.01);
    assert!((f - 0.5).abs() <= 1e-12, "{f}");
    // A 40 % hatched pour over the cell, a solid pad overlapping its left quarter
    // (overlap takes the max: 1 there), and a cut-out removing the top half.
    use crate::fem::board::Region;
    let rect = |x0, y0, x1, y1, fraction| Region::Rect {
        x0_m: x0,
        y0_m: y0,
        x1_m: x1,
        y1_m: y1,
        fraction,
    };
    b.copper[0].coverage = vec![
        rect(0.0, 0.0, 0.01, 0.01, 0.4),
        rect(0.0, 0.0, 0.0025, 0.01, 1.0),
    ];
    let f = b.coverage_fraction(0, 0.0, 0.0, 0.01, 0.01);
    assert!((f - (0.25 + 0.75 * 0.4)).abs() < 1e-12, "{f}");
    b.copper[0].cutouts = vec![rect(-1.0, 0.005, 1.0, 1.0, 1.0)];
    let f = b.coverage_fraction(0, 0.0, 0.0, 0.01, 0.01);
    assert!((f - 0.5 * (0.25 + 0.75 * 0.4)).abs() < 1e-12, "{f}");
    // Bad fractions are refused with the field named.
    b.copper[0].coverage[0] = rect(0.0, 0.0, 0.01, 0.01, 1.4);
    let e = b.validate().unwrap_err().to_string();
    assert!(e.contains("copper[0].coverage[0].fraction"), "{e}");
}

#[test]
fn schema_lists_exactly_the_board_fields() {
    // The JSON schema in schemas/ and the serde struct must name the same keys.
    let schema: serde_json::Value =
        serde_json::from_str(include_str!("../../../schemas/board.schema.json")).unwrap();
    // With every optional key set, so that each is compared.
    let mut full = Board::default_board();
    full.core.g_xz_pa.get_or_insert(3e9);
    full.core.g_yz_pa.get_or_insert(3e9);
    let board = serde_json::to_value(full).unwrap();
    let keys = |v: &serde_json::Value| -> Vec<String> {
        let mut k: Vec<String> = v.as_object().unwrap().keys().cloned().collect();
        k.sort();
        k
    };
    assert_eq!(keys(&schema["properties"]), keys(&board));
    for sub in ["core", "joint", "mesh", "mesh_bolted", "scan_grid"] {
        assert_eq!(
            keys(&schema["properties"][sub]["properties"]),
            keys(&board[sub]),
            "{sub}"
        );
    }
    assert_eq!(
        keys(&schema["properties"]["copper"]["items"]["properties"]),
        keys(&board["copper"][0])
    );
    assert_eq!(
        keys(&schema["properties"]["holes"]["items"]["properties"]),
        keys(&board["holes"][0])
    );
}

#[test]
fn same_inputs_give_the_same_bytes() {
    let b = Board::default_board();
    let m = FeModel::build(&b, Setup::bolted(), &b.mesh).unwrap();
    let p = m.nominal_params();
    let a = m.modes(&p, 5).unwrap();
    let c = m.modes(&p, 5).unwrap();
    assert_eq!(a.eigenvalues, c.eigenvalues);
    assert_eq!(a.shapes, c.shapes);
}

#[test]
fn scan_grid_points_lie_on_the_board_and_avoid_holes() {
    let b = Board::default_board();
    let m = FeModel::build(&b, Setup::Free, &b.mesh).unwrap();
    let pts = b.scan_points_m();
    assert_eq!(pts.len(), b.scan_grid.nx * b.scan_grid.ny);
    assert!(m.shape_operator(&pts).is_ok());
}

#[test]
fn results_do_not_depend_on_faer_parallelism() {
    // The kernels call faer with explicit `Par::Seq`, so its global setting (which the
    // CLI may raise) cannot change a single bit of the modes or of the ROM artifact.
    let b = crate::fem::tests::helpers::thin_board();
    let m = FeModel::build(&b, Setup::bolted(), &b.mesh).unwrap();
    let p = m.nominal_params();
    let opts = crate::fem::rom::RomOptions {
        n_modes: 4,
        n_random: 2,
        ..Default::default()
    };
    let run = |par: faer::Par| {
        faer::set_global_parallelism(par);
        let modes = m.modes(&p, 6).unwrap();
        let rom = crate::fem::rom::Rom::build(&m, &opts).unwrap();
        (modes.eigenvalues, modes.shapes, rom.to_npz_bytes())
    };
    let seq = run(faer::Par::Seq);
    let par = run(faer::Par::rayon(2));
    faer::set_global_parallelism(faer::Par::Seq);
    assert_eq!(seq.0, par.0);
    assert_eq!(seq.1, par.1);
    assert!(seq.2 == par.2, "ROM bytes differ with the thread count");
}

/// A raster density map integrates exactly like the same pattern drawn as regions:
/// cells of 5 mm across 2 mm elements (edges mid-element), a 0.45 block and a solid
/// block overlapping it (max), with a cut-out crossing both.
#[test]
fn density_map_equals_the_same_pattern_as_regions() {
    use crate::fem::board::{DensityMap, Grid, Region};
    let mut regions = crate::fem::tests::helpers::thin_board();
    let (nx, ny) = (16usize, 10usize);
    let mut values = vec![0.0; nx * ny];
    for j in 1..7 {
        for i in 2..10 {
            values[j * nx + i] = 0.45;
        }
    }
    for j in 3..5 {
        for i in 8..13 {
            values[j * nx + i] = 1.0;
        }
    }
    let rect = |x0, y0, x1, y1, fraction| Region::Rect {
        x0_m: x0,
        y0_m: y0,
        x1_m: x1,
        y1_m: y1,
        fraction,
    };
    let cut = vec![rect(0.021, 0.011, 0.047, 0.019, 1.0)];
    regions.copper[0].coverage = vec![
        rect(0.010, 0.005, 0.050, 0.035, 0.45),
        rect(0.040, 0.015, 0.065, 0.025, 1.0),
    ];
    regions.copper[0].cutouts = cut.clone();
    let mut raster = regions.clone();
    raster.copper[0].coverage = vec![];
    raster.copper[0].density_maps = vec![DensityMap {
        file: "top.csv".into(),
        x0_m: 0.0,
        y0_m: 0.0,
        x1_m: 0.080,
        y1_m: 0.050,
        grid: Some(Grid { nx, ny, values }),
    }];
    raster.validate().unwrap();
    let f = |b: &Board| {
        let m = FeModel::build(b, Setup::Free, &b.mesh).unwrap();
        m.modes(&m.nominal_params(), 6).unwrap().freq_hz
    };
    let (a, r) = (f(&regions), f(&raster));
    for j in 0..6 {
        assert!(
            (a[j] / r[j] - 1.0).abs() < 1e-10,
            "mode {j}: {} vs {}",
            a[j],
            r[j]
        );
    }
    // Without its grid (TOML read alone) the board is refused, naming the map.
    raster.copper[0].density_maps[0].grid = None;
    let e = raster.validate().unwrap_err().to_string();
    assert!(e.contains("density_maps[0] (top.csv)"), "{e}");
}

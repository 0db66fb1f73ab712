//! Tests of the boards' drawn core thickness (`population.thickness_rel_std`) and of the
//! sheet's dimension columns (`campaign.sheet_dimensions`), on small truth meshes.

use super::truth::{self, joint_model, truth_bolted_mesh, SetupKind};
use super::*;
use crate::fem::params::names;
use crate::fem::{FeModel, MeshOptions, Setup};

/// A small plate-truth campaign: 2 boards, one free measurement each, one bolted, a coarse
/// truth mesh (the tests compare the truth with models built on the same mesh).
fn small_thick(rel_std: f64, sheet_dimensions: bool) -> Scenario {
    let mut s = builtin_scenario("null").unwrap();
    s.campaign.n_boards = 2;
    s.campaign.free_per_board = 1;
    s.campaign.bolted = vec![scenario::BoltedGroup {
        boards: vec![2],
        per_board: 1,
        purpose: "updating".into(),
    }];
    s.campaign.sheet_dimensions = sheet_dimensions;
    s.truth.mesh_nx = 16;
    s.truth.mesh_ny = 10;
    s.population.thickness_rel_std = rel_std;
    s
}

#[test]
fn thickness_draw_is_nominal_at_zero_and_leaves_the_other_draws_alone() {
    let board = crate::fem::tests::helpers::thin_board();
    let h0 = board.core.thickness_m;
    let mut s = builtin_scenario("null").unwrap();
    s.campaign.n_boards = 7;
    let seed = 20_240_601;
    let p0 = truth::plan(&s, &board, seed).unwrap();
    for bd in &p0.boards {
        assert_eq!(bd.core_thickness_m, h0, "{}", bd.board_id);
    }
    // The moduli and mass draws are still those of the board stream alone, as before.
    let l = truth::cholesky4(&s.population.correlation).unwrap();
    for (b, bd) in p0.boards.iter().enumerate() {
        use rand::SeedableRng;
        use rand_distr::Distribution;
        let mut rng =
            rand_chacha::ChaCha8Rng::seed_from_u64(child_seed(seed, Stream::Board, b as u64));
        let n: [f64; 4] = std::array::from_fn(|_| rand_distr::StandardNormal.sample(&mut rng));
        let d: [f64; 4] = std::array::from_fn(|i| {
            s.population.rel_std[i] * (0..=i).map(|k| l[i][k] * n[k]).sum::<f64>()
        });
        assert_eq!(bd.deviation_rel, d, "{}", bd.board_id);
    }
    // A thickness scatter changes the thicknesses only: its stream is its own.
    s.population.thickness_rel_std = 0.05;
    let p1 = truth::plan(&s, &board, seed).unwrap();
    for (a, b) in p0.boards.iter().zip(&p1.boards) {
        assert_eq!(a.deviation_rel, b.deviation_rel);
        assert_eq!(
            [a.e_x_pa, a.e_y_pa, a.g_xy_pa, a.mass_scale],
            [b.e_x_pa, b.e_y_pa, b.g_xy_pa, b.mass_scale]
        );
        assert_ne!(b.core_thickness_m, h0);
        assert!((b.core_thickness_m / h0 - 1.0).abs() < 0.25, "{b:?}");
    }
    for (a, b) in p0.measurements.iter().zip(&p1.measurements) {
        assert_eq!(a.temperature_c, b.temperature_c);
        assert_eq!(a.bolted, b.bolted);
    }
    // Old scenarios serialise as before (no new keys in truth.json's scenario).
    let v = serde_json::to_value(builtin_scenario("null").unwrap()).unwrap();
    assert!(v["population"].get("thickness_rel_std").is_none());
    assert!(v["campaign"].get("sheet_dimensions").is_none());
}

#[test]
fn truth_of_a_thick_board_is_the_board_built_at_its_thickness() {
    let board = crate::fem::tests::helpers::thin_board();
    let mut s = small_thick(0.05, false);
    s.population.rel_std = [0.0; 4]; // the thickness alone makes the boards differ
    let seed = 5;
    let plan = truth::plan(&s, &board, seed).unwrap();
    let models = truth::Models::build(&s, &board, None).unwrap();
    let cache = truth::free_board_modes(&s, &plan, &models).unwrap();
    let mesh = MeshOptions {
        nx: s.truth.mesh_nx,
        ny: s.truth.mesh_ny,
    };
    let nominal = FeModel::build(&board, Setup::Free, &mesh).unwrap();
    let f_nom = nominal
        .modes(&nominal.nominal_params(), s.truth.n_free_modes)
        .unwrap()
        .freq_hz;
    let at = |h: f64| {
        let mut b = board.clone();
        b.core.thickness_m = h;
        b
    };
    for (b, bd) in plan.boards.iter().enumerate() {
        let bh = at(bd.core_thickness_m);
        let m = FeModel::build(&bh, Setup::Free, &mesh).unwrap();
        let p = m.nominal_params();
        let f = m.modes(&p, s.truth.n_free_modes).unwrap().freq_hz;
        let truth = &cache.with[b];
        for (r, (ft, fb)) in truth.freq_hz.iter().zip(&f).enumerate() {
            // The ratio to the nominal board's, as the truth gives it and as the board built
            // at that thickness does.
            let (rt, rb) = (ft / f_nom[r], fb / f_nom[r]);
            assert!(
                (rt / rb - 1.0).abs() < 1e-9,
                "{} mode {}: truth ratio {rt}, built {rb}",
                bd.board_id,
                r + 1
            );
        }
        // Bending frequencies grow about in proportion to the thickness.
        let hr = bd.core_thickness_m / board.core.thickness_m;
        assert!(
            ((truth.freq_hz[0] / f_nom[0]) / hr - 1.0).abs() < 0.03,
            "{}: f1 ratio {} for h ratio {hr}",
            bd.board_id,
            truth.freq_hz[0] / f_nom[0]
        );
        // What the balance weighs follows the thickness too.
        let mass = m.total_mass_kg(&p).unwrap();
        assert!(
            (truth.total_mass_kg / mass - 1.0).abs() < 1e-12,
            "{}",
            bd.board_id
        );
    }
    // Bolted: the one bolted measurement (board 2) against the board built at its thickness.
    let mt = plan
        .measurements
        .iter()
        .find(|m| m.setup == SetupKind::Bolted)
        .unwrap();
    let ms = truth::measurement_modes(&s, &plan, &models, &cache, mt).unwrap();
    let bh = at(plan.boards[mt.board].core_thickness_m);
    let m = FeModel::build(
        &bh,
        Setup::Bolted(joint_model(&s, false)),
        &truth_bolted_mesh(&s, &board),
    )
    .unwrap();
    let mut p = m.nominal_params();
    for (j, k) in mt
        .bolted
        .as_ref()
        .unwrap()
        .k_joint_n_per_m
        .iter()
        .enumerate()
    {
        p.set(&names::k_con_joint(j + 1), *k).unwrap();
    }
    let f = m.modes(&p, s.truth.n_bolted_modes).unwrap().freq_hz;
    for (r, (ft, fb)) in ms.set.freq_hz.iter().zip(&f).enumerate() {
        assert!(
            (ft / fb - 1.0).abs() < 1e-9,
            "bolted mode {}: truth {ft} Hz, built {fb} Hz",
            r + 1
        );
    }
}

/// The sheet's rows: header and records.
fn sheet_rows(bytes: &[u8]) -> (Vec<String>, Vec<Vec<String>>) {
    let mut r = csv::Reader::from_reader(bytes);
    let header = r.headers().unwrap().iter().map(String::from).collect();
    let rows = r
        .records()
        .map(|rec| rec.unwrap().iter().map(String::from).collect())
        .collect();
    (header, rows)
}

#[test]
fn sheet_gives_each_boards_dimensions_when_asked_and_only_then() {
    let board = crate::fem::tests::helpers::thin_board();
    let seed = 9;
    let mut on = small_thick(0.045, true);
    // Gaps and spellings on the sheet leave the dimension columns alone.
    on.habits.sheet_gaps = Some(true);
    on.habits.id_variants = Some(true);
    let mut off = on.clone();
    off.campaign.sheet_dimensions = false;
    let a = simulate(&on, &board, seed).unwrap();
    let b = simulate(&off, &board, seed).unwrap();
    let (ha, ra) = sheet_rows(&a.files["campaign.csv"]);
    let (hb, rb) = sheet_rows(&b.files["campaign.csv"]);
    assert_eq!(
        &ha[ha.len() - 3..],
        ["length_mm", "width_mm", "thickness_mm"]
    );
    assert_eq!(ha[..ha.len() - 3], hb[..]);
    assert!(!hb.iter().any(|c| c.ends_with("_mm")), "{hb:?}");
    // Everything else is the same campaign.
    for (name, bytes) in &a.files {
        if name != "campaign.csv" {
            assert_eq!(Some(bytes), b.files.get(name), "{name}");
        }
    }
    assert_eq!(ra.len(), a.truth.measurements.len());
    let n = hb.len();
    for ((row, other), mt) in ra.iter().zip(&rb).zip(&a.truth.measurements) {
        assert_eq!(row[..n], other[..]);
        let bt = a
            .truth
            .boards
            .iter()
            .find(|bt| bt.draw.board_id == mt.board_id)
            .unwrap();
        assert_eq!(row[n], format!("{:.2}", 1e3 * board.length_x_m));
        assert_eq!(row[n + 1], format!("{:.2}", 1e3 * board.width_y_m));
        // The overall thickness: the core plus the copper layers.
        let overall = bt.draw.core_thickness_m + board.copper_thickness_m();
        assert_eq!(row[n + 2], format!("{:.3}", 1e3 * overall));
        let t_mm: f64 = row[n + 2].parse().unwrap();
        assert!((t_mm - 1e3 * overall).abs() <= 5e-4 + 1e-12);
    }
    // The truth file states each board's thickness; the boards differ.
    let th: Vec<f64> = a
        .truth
        .boards
        .iter()
        .map(|b| b.draw.core_thickness_m)
        .collect();
    assert_ne!(th[0], th[1]);
    assert!(a.truth.truth_model.contains("core thickness per board"));
}

#[test]
fn bad_thickness_scatter_names_the_field() {
    for v in ["-0.01", "0.2", "0.5", "nan", "inf"] {
        let e = Scenario::from_toml_str(&format!(
            "name = \"x\"\n[population]\nthickness_rel_std = {v}\n"
        ))
        .unwrap_err();
        assert!(
            e.to_string().contains("population.thickness_rel_std"),
            "{v}: {e}"
        );
    }
    // The solid truth has one thickness for every board.
    let e = Scenario::from_toml_str(
        "name = \"x\"\n[truth]\nphysics = \"solid\"\n[population]\nthickness_rel_std = 0.05\n",
    )
    .unwrap_err();
    let msg = e.to_string();
    assert!(
        msg.contains("population.thickness_rel_std") && msg.contains("solid"),
        "{msg}"
    );
    // Good values parse; the switch is a bool.
    let s = Scenario::from_toml_str(
        "name = \"x\"\n[population]\nthickness_rel_std = 0.045\n[campaign]\nsheet_dimensions = true\n",
    )
    .unwrap();
    assert_eq!(s.population.thickness_rel_std, 0.045);
    assert!(s.campaign.sheet_dimensions);
    assert!(
        Scenario::from_toml_str("name = \"x\"\n[campaign]\nsheet_dimensions = \"yes\"\n").is_err()
    );
}

//! ROM accuracy against the full model over a Latin hypercube of the ±20 % box, and
//! the NPZ round trip.

use faer::Mat;

use crate::fem::board::Board;
use crate::fem::model::{FeModel, Setup};
use crate::fem::rom::{latin_hypercube_params, Rom, RomOptions};

/// Modal assurance criterion of two real shape vectors.
pub fn mac(a: &[f64], b: &[f64]) -> f64 {
    let ab: f64 = a.iter().zip(b).map(|(x, y)| x * y).sum();
    let aa: f64 = a.iter().map(|x| x * x).sum();
    let bb: f64 = b.iter().map(|x| x * x).sum();
    ab * ab / (aa * bb)
}

fn col(m: &Mat<f64>, j: usize) -> Vec<f64> {
    (0..m.nrows()).map(|i| m[(i, j)]).collect()
}

fn check_rom(setup: Setup, n_modes: usize, n_points: usize) -> (f64, f64, usize) {
    let board = Board::default_board();
    let model = FeModel::build(&board, setup, &board.mesh).unwrap();
    let opts = RomOptions {
        n_modes,
        ..RomOptions::default()
    };
    let t0 = std::time::Instant::now();
    let rom = Rom::build(&model, &opts).unwrap();
    eprintln!("ROM build {:?}, dim {}", t0.elapsed(), rom.dim());
    let pts = board.scan_points_m();
    let sop = model.shape_operator(&pts).unwrap();
    let rsop = rom.shape_operator(&model, &pts).unwrap();
    // A different seed from the build's snapshot design.
    let sample = latin_hypercube_params(&model.map, n_points, 0.2, 0x00AC_CE55);
    let (mut worst_f, mut worst_mac) = (0.0f64, 1.0f64);
    for p in &sample {
        let full = model.modes(p, n_modes).unwrap();
        let wf = sop.apply(full.shapes.as_ref());
        let red = rom.eval(p, &rsop).unwrap();
        for j in 0..n_modes {
            let e = (red.freq_hz[j] - full.freq_hz[j]).abs() / full.freq_hz[j];
            worst_f = worst_f.max(e);
            worst_mac = worst_mac.min(mac(&col(&wf, j), &col(&red.shapes_at_points, j)));
        }
    }
    (worst_f, worst_mac, rom.dim())
}

#[test]
fn rom_matches_full_model_free_over_latin_hypercube() {
    let (f, m, r) = check_rom(Setup::Free, 8, 200);
    eprintln!("free: worst freq error {f:e}, worst MAC {m}, dim {r}");
    assert!(f < 1e-3, "worst relative frequency error {f}");
    assert!(m >= 0.999, "worst MAC {m}");
}

#[test]
fn rom_matches_full_model_bolted_over_latin_hypercube() {
    let (f, m, r) = check_rom(Setup::bolted(), 7, 200);
    eprintln!("bolted: worst freq error {f:e}, worst MAC {m}, dim {r}");
    assert!(f < 1e-3, "worst relative frequency error {f}");
    assert!(m >= 0.999, "worst MAC {m}");
}

#[test]
fn rom_npz_round_trip_preserves_every_number() {
    let board = Board::default_board();
    let model = FeModel::build(&board, Setup::bolted(), &board.mesh).unwrap();
    let opts = RomOptions {
        n_modes: 4,
        n_random: 2,
        ..RomOptions::default()
    };
    let rom = Rom::build(&model, &opts).unwrap();
    let bytes = rom.to_npz_bytes();
    let back = Rom::from_npz_bytes(&bytes).unwrap();
    assert_eq!(back.map, rom.map);
    assert_eq!(
        (back.n_rigid, back.n_modes, back.setup.as_str()),
        (rom.n_rigid, rom.n_modes, rom.setup.as_str())
    );
    assert_eq!(back.basis, rom.basis);
    assert_eq!(back.k_r, rom.k_r);
    assert_eq!(back.m_r, rom.m_r);
    // Deterministic bytes.
    assert_eq!(back.to_npz_bytes(), bytes);
    // Corruption is detected.
    let mut bad = bytes.clone();
    let k = bad.len() / 2;
    bad[k] ^= 0xFF;
    assert!(Rom::from_npz_bytes(&bad).is_err());
}

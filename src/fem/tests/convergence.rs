//! Mesh convergence on a realistic board (`data/boards/realistic.toml`: holes near the
//! corners, hatched pours of partial coverage, a ground plane with a cut-out and
//! anti-pads, traces): free-free and bolted at fixed K_con, on four meshes.

use crate::fem::board::{Board, MeshOptions};
use crate::fem::model::{FeModel, Setup};

const MESHES: [(usize, usize); 4] = [(40, 25), (80, 50), (120, 75), (160, 100)];

fn realistic() -> Board {
    Board::from_toml_str(include_str!("../../../data/boards/realistic.toml")).unwrap()
}

fn freqs(b: &Board, setup: Setup, nx: usize, ny: usize, n: usize) -> Vec<f64> {
    let m = FeModel::build(b, setup, &MeshOptions { nx, ny }).unwrap();
    m.modes(&m.nominal_params(), n).unwrap().freq_hz
}

/// Free-free, first 8 modes: the board's default mesh (120 × 75) is within 0.05 % of
/// the Richardson value. The order is taken as 2 (from 80 × 50 and 160 × 100): the
/// per-element copper homogenisation converges more slowly and less regularly than
/// the element's O(h⁴) (see `fem::convergence`). Not asserted, because it does not
/// hold: convergence monotone over all four meshes (mode 4 moves by 3e-6 relative in
/// the wrong direction between 80 × 50 and 120 × 75), and 40 × 25 within 0.05 % (it is
/// 0.10 % off on mode 8).
#[test]
fn realistic_board_free_free_converges_at_its_default_mesh() {
    let b = realistic();
    assert_eq!((b.mesh.nx, b.mesh.ny), (120, 75));
    let f: Vec<Vec<f64>> = MESHES
        .iter()
        .map(|&(nx, ny)| freqs(&b, Setup::Free, nx, ny, 8))
        .collect();
    let rich: Vec<f64> = (0..8)
        .map(|j| f[3][j] + (f[3][j] - f[1][j]) / 3.0)
        .collect();
    for (k, &(nx, ny)) in MESHES.iter().enumerate() {
        let e: Vec<String> = (0..8)
            .map(|j| format!("{:+.4}", 100.0 * (f[k][j] / rich[j] - 1.0)))
            .collect();
        eprintln!("free {nx} × {ny}: % vs Richardson {}", e.join(" "));
    }
    for j in 0..8 {
        let e = (f[2][j] / rich[j] - 1.0).abs();
        assert!(
            e < 5e-4,
            "mode {j}: default mesh {:.4} % from Richardson",
            100.0 * e
        );
    }
}

/// Bolted at fixed K_con: the first 7 modes on 80 × 50 and 120 × 75 agree with
/// 160 × 100 within 0.1 %. Not asserted, because it does not hold: 40 × 25 is 0.26 %
/// off on this board (0.07 % on the default board, see the joints tests).
#[test]
fn realistic_board_bolted_is_mesh_independent_at_fixed_k_con() {
    let b = realistic();
    let f: Vec<Vec<f64>> = MESHES
        .iter()
        .map(|&(nx, ny)| freqs(&b, Setup::bolted(), nx, ny, 7))
        .collect();
    for (k, &(nx, ny)) in MESHES.iter().enumerate() {
        let e: Vec<String> = (0..7)
            .map(|j| format!("{:+.4}", 100.0 * (f[k][j] / f[3][j] - 1.0)))
            .collect();
        eprintln!("bolted {nx} × {ny}: % vs 160 × 100 {}", e.join(" "));
    }
    for (k, &(nx, ny)) in MESHES.iter().enumerate().skip(1) {
        for j in 0..7 {
            assert!(
                (f[k][j] / f[3][j] - 1.0).abs() < 1e-3,
                "{nx} × {ny} mode {j}"
            );
        }
    }
}

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

/// Free-free, first 8 modes, copper integrated exactly per piece (`fem::copper`):
/// every mesh from 40 × 25 up is within 0.05 % of the Richardson value (order 2, from
/// 80 × 50 and 160 × 100), and every frequency decreases monotonically over the four
/// meshes (Rayleigh–Ritz from above; 40 × 25 ⊂ 80 × 50 ⊂ 160 × 100 are nested, 120 × 75
/// is not, so its place in the order is a real check). Measured: 40 × 25 at most
/// 0.018 %, 120 × 75 at most 0.004 %.
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
        let hz: Vec<String> = f[k].iter().map(|v| format!("{v:.3}")).collect();
        eprintln!("free {nx} × {ny}: Hz {}", hz.join(" "));
    }
    for (k, &(nx, ny)) in MESHES.iter().enumerate() {
        for j in 0..8 {
            let e = (f[k][j] / rich[j] - 1.0).abs();
            assert!(
                e < 5e-4,
                "{nx} × {ny} mode {j}: {:.4} % from Richardson",
                100.0 * e
            );
            if k > 0 {
                assert!(f[k][j] < f[k - 1][j], "{nx} × {ny} mode {j}: not monotone");
            }
        }
    }
}

/// Bolted at fixed K_con: the first 7 modes on 80 × 50 and 120 × 75 agree with
/// 160 × 100 within 0.1 % (measured: 0.010 % and 0.004 %), and decrease monotonically
/// over the four meshes. Not asserted, because it does not hold: 40 × 25 within 0.1 %
/// (it is 0.145 % off on mode 1; the stress field around the 5.5 mm clamp is resolved
/// by 2 mm elements only to that; 0.26 % before copper was integrated per piece).
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
        let hz: Vec<String> = f[k].iter().map(|v| format!("{v:.3}")).collect();
        eprintln!("bolted {nx} × {ny}: Hz {}", hz.join(" "));
    }
    for (k, &(nx, ny)) in MESHES.iter().enumerate().skip(1) {
        for j in 0..7 {
            assert!(
                (f[k][j] / f[3][j] - 1.0).abs() < 1e-3,
                "{nx} × {ny} mode {j}"
            );
            assert!(f[k][j] < f[k - 1][j], "{nx} × {ny} mode {j}: not monotone");
        }
    }
}

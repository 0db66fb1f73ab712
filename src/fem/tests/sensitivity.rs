//! Analytic eigen-derivatives against central finite differences of the full model, and
//! the qualitative pattern of the paper's Table 1.

use crate::fem::model::{FeModel, Setup};
use crate::fem::params::names;
use crate::fem::sensitivity::{eigen_derivatives, freq_derivatives_for, table_percent_per_percent};

fn check_derivatives(setup: Setup, n_modes: usize) {
    let board = crate::fem::tests::helpers::thin_board();
    let model = FeModel::build(&board, setup, &board.mesh).unwrap();
    let p = model.nominal_params();
    let modes = model.modes(&p, n_modes).unwrap();
    let d = eigen_derivatives(&model, &p, &modes, true).unwrap();
    let ds = d.d_shapes.as_ref().unwrap();
    let n = model.n_dof;
    // The targeted derivatives, for every other parameter in reverse order.
    let subset: Vec<usize> = (0..p.values.len()).rev().step_by(2).collect();
    let targeted = freq_derivatives_for(&model, &p, &modes, &subset).unwrap();
    for (k, name) in p.names.iter().enumerate() {
        let h = 1e-4 * p.values[k].abs();
        let (mut pp, mut pm) = (p.clone(), p.clone());
        pp.values[k] += h;
        pm.values[k] -= h;
        let mut mp = model.modes(&pp, n_modes).unwrap();
        let mut mm = model.modes(&pm, n_modes).unwrap();
        // Align the arbitrary eigenvector signs with the base modes.
        for other in [&mut mp, &mut mm] {
            for j in 0..n_modes {
                let dot: f64 = (0..n)
                    .map(|i| other.shapes[(i, j)] * modes.shapes[(i, j)])
                    .sum();
                if dot < 0.0 {
                    for i in 0..n {
                        other.shapes[(i, j)] = -other.shapes[(i, j)];
                    }
                }
            }
        }
        for j in 0..n_modes {
            // Eigenvalue, compared in %/% units: (p/λ) ∂λ/∂p.
            let fd = (mp.eigenvalues[j] - mm.eigenvalues[j]) / (2.0 * h);
            let s_fd = p.values[k] / modes.eigenvalues[j] * fd;
            let s_an = p.values[k] / modes.eigenvalues[j] * d.d_eigenvalue[(j, k)];
            assert!(
                (s_an - s_fd).abs() <= 1e-4 * s_fd.abs().max(1e-2),
                "mode {} / {name}: analytic {s_an}, finite difference {s_fd}",
                j + 1
            );
            // The targeted frequency derivative, in %/%.
            if let Some(col) = subset.iter().position(|&i| i == k) {
                let fd = (mp.freq_hz[j] - mm.freq_hz[j]) / (2.0 * h);
                let s_fd = p.values[k] / modes.freq_hz[j] * fd;
                let s_t = p.values[k] / modes.freq_hz[j] * targeted[(j, col)];
                assert!(
                    (s_t - s_fd).abs() <= 1e-4 * s_fd.abs().max(1e-2),
                    "mode {} / {name}: targeted {s_t}, finite difference {s_fd}",
                    j + 1
                );
            }
            // Shape: ‖p (∂φ_an − ∂φ_fd)‖ ≤ 1e-4 ‖φ‖.
            let (mut err, mut nrm) = (0.0f64, 0.0f64);
            for i in 0..n {
                let fdv = (mp.shapes[(i, j)] - mm.shapes[(i, j)]) / (2.0 * h);
                err += (p.values[k] * (ds[k][(i, j)] - fdv)).powi(2);
                nrm += modes.shapes[(i, j)].powi(2);
            }
            let rel = (err / nrm).sqrt();
            assert!(
                rel <= 1e-4,
                "mode {} / {name}: shape derivative relative error {rel:e}",
                j + 1
            );
        }
    }
}

#[test]
fn free_derivatives_match_central_differences() {
    check_derivatives(Setup::Free, 8);
}

#[test]
fn bolted_derivatives_match_central_differences() {
    check_derivatives(Setup::bolted(), 7);
}

/// Paper, Table 1: torsion driven by G_xy, x-bending by E_x, y-bending by E_y, and
/// every frequency falls with mass as f ∝ m^(-1/2), i.e. exactly −0.5 %/%.
#[test]
fn table_shows_the_papers_pattern() {
    let board = crate::fem::tests::helpers::thin_board();
    let model = FeModel::build(&board, Setup::Free, &board.mesh).unwrap();
    let p = model.nominal_params();
    let rows = table_percent_per_percent(&model, &p, 8).unwrap();
    let get = |mode: usize, name: &str| {
        rows.iter()
            .find(|r| r.mode == mode && r.param == name)
            .map(|r| r.pct_per_pct)
            .unwrap()
    };
    for m in 1..=8 {
        eprintln!(
            "mode {m}: Ex {:.3} Ey {:.3} Gxy {:.3} nu {:.4} Ecu {:.3} mass {:.3}",
            get(m, names::E_X),
            get(m, names::E_Y),
            get(m, names::G_XY),
            get(m, names::NU_XY),
            get(m, names::E_CU),
            get(m, names::MASS_SCALE)
        );
        assert!((get(m, names::MASS_SCALE) + 0.5).abs() < 1e-9);
    }
    let dominant = |m: usize| {
        [names::E_X, names::E_Y, names::G_XY]
            .into_iter()
            .max_by(|a, b| get(m, a).total_cmp(&get(m, b)))
            .unwrap()
    };
    // Frequencies are homogeneous of degree 1/2 in the stiffness, so a mode's %/% over
    // all stiffness parameters sum to 0.5 (less the small frozen coupling correction);
    // "driven by" = the parameter carries more than half of that. (The paper's Table 1
    // columns sum to ≈ 1, i.e. they are eigenvalue sensitivities, twice ours.)
    let driven = |m: usize, name: &str| dominant(m) == name && get(m, name) > 0.25;
    // Mode 1 torsion, mode 2 first x-bending (paper: EF1, EF2).
    assert!(
        driven(1, names::G_XY),
        "torsion: G_xy {}",
        get(1, names::G_XY)
    );
    assert!(
        driven(2, names::E_X),
        "x-bending: E_x {}",
        get(2, names::E_X)
    );
    // Some mode among the first five is y-bending (paper: EF4).
    assert!((1..=5).any(|m| driven(m, names::E_Y)));
    // ν_xy matters little (paper: |·| < 0.03).
    assert!((1..=8).all(|m| get(m, names::NU_XY).abs() < 0.05));
}

/// The coupling correction follows the moduli: K(p) of the nominal model through its
/// affine expansion equals K of a model assembled directly at p (core moduli and copper
/// modulus changed in the board itself, so every −B A⁻¹ B is recomputed per element)
/// to rounding, at corners and inside the ±20 % box.
#[test]
fn affine_stiffness_equals_direct_assembly_anywhere_in_the_box() {
    use crate::fem::params::names;
    let b = crate::fem::tests::helpers::thin_board();
    let mesh = crate::fem::MeshOptions { nx: 20, ny: 13 };
    let m0 = crate::fem::FeModel::build(&b, crate::fem::Setup::Free, &mesh).unwrap();
    assert!(m0.k_term_names.iter().any(|n| n.starts_with("coupling_s")));
    let x: Vec<f64> = (0..m0.n_dof)
        .map(|i| ((i * 7919) % 101) as f64 / 101.0 - 0.5)
        .collect();
    for f in [
        [1.2, 0.8, 1.2, 0.8, 0.8],
        [0.8, 1.2, 0.8, 1.2, 1.2],
        [1.07, 0.93, 1.13, 1.01, 1.17],
    ] {
        let mut p = m0.nominal_params();
        let mut bp = b.clone();
        for (k, name) in [
            names::E_X,
            names::E_Y,
            names::G_XY,
            names::NU_XY,
            names::E_CU,
        ]
        .iter()
        .enumerate()
        {
            p.set(name, p.get(name).unwrap() * f[k]).unwrap();
        }
        bp.core.e_x_pa *= f[0];
        bp.core.e_y_pa *= f[1];
        bp.core.g_xy_pa *= f[2];
        bp.core.nu_xy *= f[3];
        for l in &mut bp.copper {
            l.e_pa *= f[4];
        }
        let m1 = crate::fem::FeModel::build(&bp, crate::fem::Setup::Free, &mesh).unwrap();
        let y0 = m0.stiffness_apply(&p, &x).unwrap();
        let y1 = m1.stiffness_apply(&m1.nominal_params(), &x).unwrap();
        let num: f64 = y0.iter().zip(&y1).map(|(a, b)| (a - b).powi(2)).sum();
        let den: f64 = y1.iter().map(|a| a * a).sum();
        assert!(
            (num / den).sqrt() < 1e-11,
            "{f:?}: relative difference {}",
            (num / den).sqrt()
        );
    }
}

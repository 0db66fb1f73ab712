//! The core thickness as a parameter ([`ModelOptions::core_thickness`]) is exact: the model
//! at thickness h equals the model of the board whose file says h, copper coupling included.

use crate::fem::board::Board;
use crate::fem::model::{FeModel, ModelOptions, Setup};
use crate::fem::params::names;

fn with_thickness(board: &Board, h_m: f64) -> Board {
    let mut b = board.clone();
    b.core.thickness_m = h_m;
    b
}

/// Eigenvalues and mass of `model` at `p` against those of the board built at thickness `h`.
fn compare(board: &Board, setup: Setup, h_m: f64, scale_e_x: f64, tol: f64) {
    let mesh = board.mesh_for(&setup).clone();
    let opts = ModelOptions {
        core_thickness: true,
    };
    let para = FeModel::build_with(board, setup.clone(), &mesh, opts).unwrap();
    let mut p = para.nominal_params();
    p.set(names::CORE_THICKNESS, h_m).unwrap();
    let ex = p.get(names::E_X).unwrap();
    p.set(names::E_X, ex * scale_e_x).unwrap();
    p.set(names::MASS_SCALE, 1.03).unwrap();
    let direct_board = with_thickness(board, h_m);
    // On the same node lines (a shear-deformable board's grading follows its thickness).
    let (x_m, y_m) = (para.mesh.x_m.clone(), para.mesh.y_m.clone());
    let direct = FeModel::build_on_lines(&direct_board, setup, x_m, y_m).unwrap();
    let mut q = direct.nominal_params();
    q.set(names::E_X, ex * scale_e_x).unwrap();
    q.set(names::MASS_SCALE, 1.03).unwrap();
    let (a, b) = (para.modes(&p, 8).unwrap(), direct.modes(&q, 8).unwrap());
    for (k, (fa, fb)) in a.freq_hz.iter().zip(&b.freq_hz).enumerate() {
        assert!(
            ((fa - fb) / fb).abs() < tol,
            "h {h_m} m, mode {k}: {fa} Hz with the thickness a parameter, {fb} Hz built at it ({:e})",
            fa / fb - 1.0
        );
    }
    let (ma, mb) = (
        para.total_mass_kg(&p).unwrap(),
        direct.total_mass_kg(&q).unwrap(),
    );
    assert!(((ma - mb) / mb).abs() < 1e-12, "mass {ma} vs {mb} kg");
}

/// The default board (asymmetric copper, so the −B A⁻¹ B coupling is in play) free and
/// bolted, 8 % thicker and 10 % thinner, with a modulus off nominal.
#[test]
fn the_thickness_parameter_reproduces_the_board_built_at_that_thickness() {
    let b = crate::fem::tests::helpers::thin_board();
    let h0 = b.core.thickness_m;
    for h in [1.08 * h0, 0.9 * h0] {
        compare(&b, Setup::Free, h, 1.05, 1e-9);
        compare(&b, Setup::bolted(), h, 0.97, 1e-9);
    }
    // At the nominal thickness it is the standard model.
    compare(&b, Setup::Free, h0, 1.0, 1e-9);
}

/// The same board shear-deformable: exact but for the transverse shear stiffness, taken
/// ∝ h (the copper's share of Whitney's S moves a little with h); within 1e-4 at ±10 %.
#[test]
fn the_thickness_parameter_follows_a_shear_deformable_board() {
    let mut b = crate::fem::tests::helpers::thin_board();
    b.core.g_xz_pa = Some(3e9);
    b.core.g_yz_pa = Some(3e9);
    let h0 = b.core.thickness_m;
    for h in [1.1 * h0, 0.9 * h0] {
        compare(&b, Setup::Free, h, 1.05, 1e-4);
    }
    compare(&b, Setup::Free, h0, 1.0, 1e-9);
}

/// A plain plate (no copper): eigenvalues scale as h² at fixed moduli and density scale
/// (D ∝ h³, mass ∝ h), the closed form of Kirchhoff plate theory.
#[test]
fn a_plate_without_copper_scales_its_eigenvalues_with_h_squared() {
    let b = super::helpers::plain_board(0.1, 0.06, 2e-3, 20e9, 18e9, 8e9, 0.14, 1850.0);
    let opts = ModelOptions {
        core_thickness: true,
    };
    let m = FeModel::build_with(&b, Setup::Free, &b.mesh, opts).unwrap();
    let p0 = m.nominal_params();
    let mut p1 = p0.clone();
    p1.set(names::CORE_THICKNESS, 2.3e-3).unwrap();
    let (a, c) = (m.modes(&p0, 5).unwrap(), m.modes(&p1, 5).unwrap());
    for (f0, f1) in a.freq_hz.iter().zip(&c.freq_hz) {
        assert!((f1 / f0 - 1.15).abs() < 1e-10, "{f1} / {f0}");
    }
    let ratio = m.total_mass_kg(&p1).unwrap() / m.total_mass_kg(&p0).unwrap();
    assert!((ratio - 1.15).abs() < 1e-12);
}

/// The coefficients' derivatives in h (the sensitivities' chain rule) match central
/// differences, the coupling terms' included.
#[test]
fn thickness_coefficient_gradients_match_finite_differences() {
    let b = crate::fem::tests::helpers::thin_board();
    let opts = ModelOptions {
        core_thickness: true,
    };
    let m = FeModel::build_with(&b, Setup::Free, &b.mesh, opts).unwrap();
    let mut p = m.nominal_params();
    let i = p.position(names::CORE_THICKNESS).unwrap();
    p.values[i] *= 1.04;
    p.values[0] *= 0.97;
    let c = m.map.coefficients(&p).unwrap();
    let dh = 1e-6 * p.values[i];
    let (mut lo, mut hi) = (p.clone(), p.clone());
    lo.values[i] -= dh;
    hi.values[i] += dh;
    let (cl, ch) = (
        m.map.coefficients(&lo).unwrap(),
        m.map.coefficients(&hi).unwrap(),
    );
    let mut n_h = 0;
    for (t, g) in c.k_grad.iter().enumerate() {
        let fd = (ch.k[t] - cl.k[t]) / (2.0 * dh);
        assert!(
            (g[i] - fd).abs() <= 1e-6 * fd.abs().max(c.k[t].abs() / p.values[i]),
            "{}: ∂c/∂h {} vs {fd}",
            m.k_term_names[t],
            g[i]
        );
        n_h += usize::from(g[i] != 0.0);
    }
    for (t, g) in c.m_grad.iter().enumerate() {
        let fd = (ch.m[t] - cl.m[t]) / (2.0 * dh);
        assert!(
            (g[i] - fd).abs() <= 1e-6 * fd.abs().max(1e-12),
            "mass term {t}"
        );
    }
    assert!(n_h > 10, "terms depending on h: {n_h}");
    // The values alone (the sampler's path) are the same numbers.
    let (k, mm) = m.map.coefficient_values(&p.values);
    assert_eq!(k, c.k);
    assert_eq!(mm, c.m);
}

/// The thin board's free model with its core thickness as a parameter (two mass terms: core
/// and copper) on a 20 × 12 mesh, and its ROM of 6 modes.
fn two_mass_rom() -> (FeModel, crate::fem::rom::Rom) {
    use crate::fem::rom::{Rom, RomOptions};
    let b = crate::fem::tests::helpers::thin_board();
    let mesh = crate::fem::MeshOptions { nx: 20, ny: 12 };
    let opts = ModelOptions {
        core_thickness: true,
    };
    let model = FeModel::build_with(&b, Setup::Free, &mesh, opts).unwrap();
    assert_eq!(model.map.m_coefs.len(), 2, "core and copper mass terms");
    let rom = Rom::build(
        &model,
        &RomOptions {
            n_modes: 6,
            n_random: 8,
            ..RomOptions::default()
        },
    )
    .unwrap();
    (model, rom)
}

/// The ROM of a model with several mass terms (the core thickness splits the mass): its hot
/// path (`eval_lowest`, the wanted eigenpairs of L⁻¹ Kʳ L⁻ᵀ) gives the full path's
/// (`eval_coefs`, a complete eigen-decomposition) eigenvalues and vectors, and the full
/// model's frequencies, at points across the box.
#[test]
fn the_rom_hot_path_with_two_mass_terms_matches_its_full_path_and_the_model() {
    use crate::fem::rom::latin_hypercube_params;
    let (model, rom) = two_mass_rom();
    let none = rom.shape_operator(&model, &[]).unwrap();
    for p in latin_hypercube_params(&model.map, 6, 0.15, 11) {
        let c = rom.map.coefficients(&p).unwrap();
        let fast = rom.eval_lowest(&c.k, &c.m, 6).unwrap();
        let full = rom.eval_coefs(&c.k, &c.m, &none).unwrap();
        let fe = model.modes(&p, 6).unwrap();
        for j in 0..6 {
            let (a, b) = (fast.eigenvalues[j], full.eigenvalues[j]);
            assert!(((a - b) / b).abs() < 1e-10, "mode {j}: {a} vs {b}");
            let f = a.sqrt() / (2.0 * std::f64::consts::PI);
            assert!(
                ((f - fe.freq_hz[j]) / fe.freq_hz[j]).abs() < 1e-4,
                "mode {j}: ROM {f} Hz, model {} Hz",
                fe.freq_hz[j]
            );
            let d = (0..rom.dim())
                .map(|i| (fast.vectors[j][i] - full.reduced[(i, j)]).abs())
                .fold(0.0, f64::max);
            let n = (0..rom.dim())
                .map(|i| full.reduced[(i, j)].abs())
                .fold(0.0, f64::max);
            assert!(d < 1e-7 * n, "mode {j}: vectors differ by {d} (of {n})");
        }
    }
}

/// A mode's subspace of a ROM with several mass terms (`Rom::subspace`, the pencil
/// (Wᵀ Kʳ W, Wᵀ Mʳ W)): at the points whose vectors span it, the mode exactly (its vector
/// lies in the span); elsewhere a Ritz pair of the ROM, checked on the ROM's own matrices:
/// yᵀ Mʳ y = 1, the Galerkin residual Wᵀ (Kʳ − λ Mʳ) y = 0, and λ within 1e-3 of the ROM's
/// eigenvalue.
#[test]
fn a_mode_subspace_with_two_mass_terms_gives_ritz_pairs_of_the_rom() {
    use crate::fem::rom::latin_hypercube_params;
    let (model, rom) = two_mass_rom();
    let r = rom.dim();
    let j = 2usize;
    let coefs = |p: &crate::fem::Params| rom.map.coefficient_values(&p.values);
    let snaps = latin_hypercube_params(&model.map, 8, 0.1, 5);
    let vectors: Vec<Vec<f64>> = snaps
        .iter()
        .map(|p| {
            let (k, m) = coefs(p);
            rom.eval_lowest(&k, &m, 6).unwrap().vectors[j].clone()
        })
        .collect();
    let sub = rom.subspace(&vectors, 1e-9).expect("a subspace");
    assert!(sub.dim() < r, "q = {} of r = {r}", sub.dim());
    let unit = |v: &[f64]| {
        let n = v.iter().map(|a| a * a).sum::<f64>().sqrt();
        v.iter().map(|a| a / n).collect::<Vec<f64>>()
    };
    let target = sub.project(&unit(&vectors[0]));
    let times = |a: &faer::Mat<f64>, y: &[f64]| -> Vec<f64> {
        (0..r)
            .map(|i| (0..r).map(|k| a[(i, k)] * y[k]).sum())
            .collect()
    };
    let sum = |c: &[f64], terms: &[faer::Mat<f64>]| {
        let mut s = faer::Mat::<f64>::zeros(r, r);
        for (ci, t) in c.iter().zip(terms) {
            s += faer::Scale(*ci) * t;
        }
        s
    };
    for (which, points) in [
        ("spanning", snaps.clone()),
        ("new", latin_hypercube_params(&model.map, 6, 0.1, 77)),
    ] {
        for p in &points {
            let (k, m) = coefs(p);
            let rom_mode = rom.eval_lowest(&k, &m, 6).unwrap();
            let (lam, y, overlap) = rom.eval_nearest_in(&sub, &k, &m, &target).unwrap();
            let lam_rom = rom_mode.eigenvalues[j];
            assert!(overlap > 0.9, "{which}: overlap {overlap}");
            let (kr, mr) = (sum(&k, &rom.k_r), sum(&m, &rom.m_r));
            let (ky, my) = (times(&kr, &y), times(&mr, &y));
            let ymy: f64 = y.iter().zip(&my).map(|(a, b)| a * b).sum();
            assert!((ymy - 1.0).abs() < 1e-10, "{which}: yᵀMy = {ymy}");
            let res: Vec<f64> = ky.iter().zip(&my).map(|(a, b)| a - lam * b).collect();
            let g = sub.project(&res);
            let gn = g.iter().map(|a| a * a).sum::<f64>().sqrt();
            let kn = ky.iter().map(|a| a * a).sum::<f64>().sqrt();
            assert!(gn < 1e-9 * kn, "{which}: Galerkin residual {gn} of {kn}");
            let rel = (lam - lam_rom) / lam_rom;
            if which == "spanning" {
                assert!(rel.abs() < 1e-10, "{which}: λ {lam} vs the ROM's {lam_rom}");
                let d = y
                    .iter()
                    .zip(&rom_mode.vectors[j])
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0, f64::max);
                assert!(d < 1e-6, "{which}: vectors differ by {d}");
            } else {
                // Rayleigh–Ritz: the error is of the order of the square of the vector's
                // distance from the span.
                assert!(rel.abs() < 1e-3, "{which}: λ off by {rel:e}");
            }
        }
    }
}

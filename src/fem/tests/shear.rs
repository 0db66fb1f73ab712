//! The shear-deformable board (a core with transverse shear moduli) built through the same
//! public path as the PCB, against Navier's simply supported Mindlin plate and, free-free,
//! against an independent Ritz solution (Legendre polynomials in w, θx, θy).

use super::helpers::*;
use crate::fem::board::Board;
use crate::fem::dense::lowest_eigenpairs;
use crate::fem::model::Setup;

const CORE: (f64, f64, f64, f64) = (22e9, 19e9, 3.5e9, 0.13);
const RHO: f64 = 1900.0;

/// A plain board (no copper, no holes) with transverse shear moduli `g_z`, and its
/// reference plate: S = 5/6 G h is exactly Whitney's for one homogeneous layer.
fn shear_board(a: f64, b: f64, h: f64, g_z: f64) -> (Board, MindlinPlate) {
    let (ex, ey, gxy, nu) = CORE;
    let mut board = plain_board(a, b, h, ex, ey, gxy, nu, RHO);
    board.core.g_xz_pa = Some(g_z);
    board.core.g_yz_pa = Some(g_z);
    (
        board,
        MindlinPlate::homogeneous(a, b, h, CORE, (g_z, g_z), RHO),
    )
}

fn hz(lam: f64) -> f64 {
    lam.sqrt() / (2.0 * std::f64::consts::PI)
}

/// Simply supported 80 × 50 × 2 mm plate, G_z = 1 GPa (shear lowers the six lowest modes by
/// 1.5–6 % below Rayleigh's plate): the board model within 5e-4 of Navier's Mindlin
/// frequencies on a 32 × 20 mesh.
#[test]
fn shear_deformable_board_matches_navier() {
    let (board, plate) = shear_board(0.08, 0.05, 2e-3, 1e9);
    let model = build(&board, Setup::Free, 32, 20);
    assert_eq!(model.mesh.dofs_per_node, 6);
    let lam = constrained_eigenvalues(&model, &simply_supported_dofs(&model), 6, -1.0);
    let mut pairs: Vec<(usize, usize)> = (1..6).flat_map(|m| (1..5).map(move |n| (m, n))).collect();
    pairs.sort_by(|p, q| {
        plate
            .navier_hz(p.0, p.1)
            .total_cmp(&plate.navier_hz(q.0, q.1))
    });
    for (k, &(m, n)) in pairs.iter().take(6).enumerate() {
        let (exact, thin) = (plate.navier_hz(m, n), plate.rayleigh_hz(m, n));
        assert!(
            thin / exact - 1.0 > 0.01,
            "({m}, {n}): too little shear to test"
        );
        let f = hz(lam[k]);
        assert!(
            (f / exact - 1.0).abs() < 5e-4,
            "mode ({m}, {n}): board {f} Hz, Navier {exact} Hz (Rayleigh {thin} Hz)"
        );
    }
}

/// Legendre polynomials P_0 … P_p at ξ and their derivatives.
fn legendre(p: usize, xi: f64) -> (Vec<f64>, Vec<f64>) {
    let mut v = vec![1.0, xi];
    let mut d = vec![0.0, 1.0];
    for n in 1..p {
        let nf = n as f64;
        v.push(((2.0 * nf + 1.0) * xi * v[n] - nf * v[n - 1]) / (nf + 1.0));
        d.push(d[n - 1] + (2.0 * nf + 1.0) * v[n]);
    }
    v.truncate(p + 1);
    d.truncate(p + 1);
    (v, d)
}

/// Gauss–Legendre nodes and weights on [−1, 1] (Newton on P_n from Chebyshev guesses).
fn gauss_legendre(n: usize) -> (Vec<f64>, Vec<f64>) {
    let (mut x, mut w) = (vec![0.0; n], vec![0.0; n]);
    for i in 0..n {
        let mut z = (std::f64::consts::PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
        for _ in 0..100 {
            let (v, d) = legendre(n, z);
            let dz = v[n] / d[n];
            z -= dz;
            if dz.abs() < 1e-15 {
                break;
            }
        }
        let (_, d) = legendre(n, z);
        x[i] = z;
        w[i] = 2.0 / ((1.0 - z * z) * d[n] * d[n]);
    }
    (x, w)
}

/// One-dimensional integrals over [0, len] of the Legendre basis mapped there:
/// (∫ φ_i φ_k, ∫ φ_i' φ_k', ∫ φ_i' φ_k).
type Integrals1d = (Vec<Vec<f64>>, Vec<Vec<f64>>, Vec<Vec<f64>>);

fn integrals_1d(p: usize, len: f64) -> Integrals1d {
    let (xs, ws) = gauss_legendre(p + 2);
    let z = vec![vec![0.0; p + 1]; p + 1];
    let (mut a0, mut a1, mut a10) = (z.clone(), z.clone(), z);
    let jac = 0.5 * len;
    for (x, w) in xs.iter().zip(&ws) {
        let (v, d) = legendre(p, *x);
        for i in 0..=p {
            for k in 0..=p {
                a0[i][k] += w * jac * v[i] * v[k];
                a1[i][k] += w * d[i] * d[k] / jac;
                a10[i][k] += w * d[i] * v[k];
            }
        }
    }
    (a0, a1, a10)
}

/// The free plate's lowest `count` elastic frequencies (Hz) by the Ritz method: w, θx, θy
/// each a sum of products of Legendre polynomials of degree ≤ p in x and y (free edges need
/// no constraint), U = ½ ∫ κᵀDκ + S_x (w_x − θx)² + S_y (w_y − θy)², T = ½ ω² ∫ ρh w² +
/// I |θ|². Independent of the finite elements in all but the energy it minimises.
fn ritz_free_hz(pl: &MindlinPlate, p: usize, count: usize) -> Vec<f64> {
    let q = p + 1;
    let nf = q * q;
    let n = 3 * nf;
    let (ax0, ax1, ax10) = integrals_1d(p, pl.a);
    let (by0, by1, by10) = integrals_1d(p, pl.b);
    let [d11, d22, d12, d66] = pl.d;
    let [sx, sy] = pl.s;
    let mut k = vec![0.0; n * n];
    let mut m = vec![0.0; n * n];
    // Blocks: 0 = w, 1 = θx, 2 = θy; index (i, j) ↦ i q + j (i along x, j along y).
    for i in 0..q {
        for j in 0..q {
            let r = i * q + j;
            for kx in 0..q {
                for l in 0..q {
                    let c = kx * q + l;
                    let (x0, x1, y0, y1) = (ax0[i][kx], ax1[i][kx], by0[j][l], by1[j][l]);
                    let mut add = |br: usize, bc: usize, v: f64| {
                        k[(br * nf + r) * n + bc * nf + c] += v;
                    };
                    add(0, 0, sx * x1 * y0 + sy * x0 * y1);
                    add(1, 1, d11 * x1 * y0 + d66 * x0 * y1 + sx * x0 * y0);
                    add(2, 2, d22 * x0 * y1 + d66 * x1 * y0 + sy * x0 * y0);
                    // ∫ θx,x θy,y and ∫ θx,y θy,x (row θx_(i,j), column θy_(k,l)).
                    let xy = d12 * ax10[i][kx] * by10[l][j] + d66 * ax10[kx][i] * by10[j][l];
                    add(1, 2, xy);
                    // −S_x ∫ w_x θx and −S_y ∫ w_y θy (row w_(i,j)).
                    add(0, 1, -sx * ax10[i][kx] * y0);
                    add(0, 2, -sy * x0 * by10[j][l]);
                    let mm = x0 * y0;
                    m[r * n + c] += pl.rho_h * mm;
                    m[(nf + r) * n + nf + c] += pl.inertia * mm;
                    m[(2 * nf + r) * n + 2 * nf + c] += pl.inertia * mm;
                }
            }
        }
    }
    // The lower blocks by symmetry.
    for r in 0..n {
        for c in 0..r {
            k[r * n + c] = k[c * n + r];
        }
    }
    let km = faer::Mat::from_fn(n, n, |r, c| k[r * n + c]);
    let mm = faer::Mat::from_fn(n, n, |r, c| m[r * n + c]);
    let (_, ct) = crate::fem::rom::whiten(km, &mm).expect("positive mass");
    let mut a: Vec<f64> = (0..n * n).map(|q| ct[(q / n, q % n)]).collect();
    // Three rigid modes first.
    let e = lowest_eigenpairs(&mut a, n, 0, count + 3);
    assert!(e.values[2].abs() < 1e-6 * e.values[3], "three rigid modes");
    e.values[3..3 + count].iter().map(|v| hz(*v)).collect()
}

/// Free 80 × 50 × 2 mm plate, G_z = 1 GPa: the board's eight lowest elastic modes against the
/// Ritz reference (degree 22, within 2e-6 of degree 18; measured 1.2e-6). The shear lowers them
/// by 0.5–5 % (against the reference with a thousandfold shear stiffness). The free edges'
/// shear boundary layer (δ = 1.2 mm) converges at the bilinear shear strains' O(h²); with the
/// mesh graded towards the edges ([`crate::fem::model::EDGE_GRADING`]) the board on 80 × 50
/// is within 5e-5 of the reference (measured 0–26 ppm; 40 × 25: 1–106 ppm), and halving the
/// elements divides the error by more than 2.5 where it exceeds 1e-5 (measured 3.4–4.9).
#[test]
fn free_shear_deformable_board_matches_ritz() {
    let (board, plate) = shear_board(0.08, 0.05, 2e-3, 1e9);
    let n_modes = 8;
    let reference = ritz_free_hz(&plate, 22, n_modes);
    let coarser = ritz_free_hz(&plate, 18, n_modes);
    let thin = ritz_free_hz(
        &MindlinPlate {
            s: plate.s.map(|s| 1e3 * s),
            ..plate
        },
        18,
        n_modes,
    );
    for ((r, c), t) in reference.iter().zip(&coarser).zip(&thin) {
        assert!(
            (c / r - 1.0).abs() < 2e-6,
            "Ritz not converged: {c} against {r} Hz"
        );
        assert!(
            t / r - 1.0 > 0.005,
            "too little shear to test: {t} against {r} Hz"
        );
    }
    let error = |nx: usize, ny: usize| -> Vec<f64> {
        let model = build(&board, Setup::Free, nx, ny);
        let modes = model.modes(&model.nominal_params(), n_modes).unwrap();
        modes
            .freq_hz
            .iter()
            .zip(&reference)
            .map(|(f, r)| f / r - 1.0)
            .collect()
    };
    let (coarse, fine) = (error(40, 25), error(80, 50));
    for (k, (ec, ef)) in coarse.iter().zip(&fine).enumerate() {
        assert!(
            ef.abs() < 5e-5,
            "mode {k}: the board is {ef:e} off the Ritz reference"
        );
        if ef.abs() > 1e-5 {
            assert!(
                ec / ef > 2.5,
                "mode {k}: error {ec:e} at 40 × 25, {ef:e} at 80 × 50"
            );
        }
    }
}

/// The transverse shear modulus as a parameter: on a plain board (S exactly ∝ G) the model
/// at G equals the board built with G, to rounding.
#[test]
fn the_shear_modulus_parameter_reproduces_the_board_built_with_it() {
    let (board, _) = shear_board(0.08, 0.05, 2e-3, 1e9);
    let model = build(&board, Setup::Free, 24, 15);
    let mut p = model.nominal_params();
    p.set(crate::fem::params::names::G_Z, 2.5e9).unwrap();
    let (direct_board, _) = shear_board(0.08, 0.05, 2e-3, 2.5e9);
    // On the same node lines (the edge grading follows the nominal G).
    let (x_m, y_m) = (model.mesh.x_m.clone(), model.mesh.y_m.clone());
    let direct =
        crate::fem::model::FeModel::build_on_lines(&direct_board, Setup::Free, x_m, y_m).unwrap();
    let a = model.modes(&p, 6).unwrap();
    let b = direct.modes(&direct.nominal_params(), 6).unwrap();
    for (fa, fb) in a.freq_hz.iter().zip(&b.freq_hz) {
        assert!(
            (fa / fb - 1.0).abs() < 1e-10,
            "{fa} Hz with the parameter, {fb} Hz built"
        );
    }
}

//! The virtual lab's solid truth (CalculiX on a gmsh mesh): its mesh convergence, its cost
//! per solve, and its distance from hbmu's updating model (the plate) on the shipped boards
//! at nominal parameters, free-free and bolted (K̄ on every joint), modes paired by MAC on the
//! board's scan grid.
//!
//! `cargo bench --bench solid_truth [-- SIZE_MM ...]` (default sizes 3, 2, 1.5, 1 mm for the
//! convergence; the distance table at the finest). Needs gmsh and ccx on the PATH.
//!
//! To take the distance apart: `SOLID_G_Z_PA` sets the solid's transverse shear moduli
//! G_xz = G_yz (default 3.5 GPa; a hundredfold makes the solid nearly rigid in transverse
//! shear, the plate's Kirchhoff assumption); `SOLID_ONLY` = `free` or `bolted` runs one setup,
//! `SOLID_BOARD` = `default` or `realistic` one board, `SOLID_RIDING_KG` the mass riding on
//! each clamped patch, `SOLID_K_ROT` the lab's added rotational restraint per joint (N·m/rad,
//! the `rotational_restraint` effect). `PLATE_G_Z_PA` makes the plate
//! shear-deformable with those transverse shear moduli, `PLATE_MESH` = `nx,ny` sets its mesh,
//! `PLATE_TANGENTIAL` its joint's `tangential_over_normal` (0: the contact slides freely).

use std::sync::Arc;
use std::time::Instant;

use hbmu::fem::params::names;
use hbmu::fem::{Board, FeModel, Setup};
use hbmu::io::external::Calculix;
use hbmu::lab::solid::{SolidModel, SolidOptions, State};

fn mac(a: &[f64], b: &[f64]) -> f64 {
    let d = |x: &[f64], y: &[f64]| x.iter().zip(y).map(|(p, q)| p * q).sum::<f64>();
    d(a, b).powi(2) / (d(a, a) * d(b, b))
}

fn main() {
    let args: Vec<f64> = std::env::args()
        .skip(1)
        .filter_map(|a| a.parse().ok())
        .collect();
    let sizes_mm = if args.is_empty() {
        vec![3.0, 2.0, 1.5, 1.0]
    } else {
        args
    };
    let solver = Arc::new(Calculix::locate().expect("gmsh and ccx"));
    let boards = [
        ("default", include_str!("../data/boards/default.toml")),
        ("realistic", include_str!("../data/boards/realistic.toml")),
    ];
    let env = |k: &str| std::env::var(k).ok();
    let g_z_pa: Option<f64> = env("SOLID_G_Z_PA").map(|v| v.parse().expect("SOLID_G_Z_PA in Pa"));
    for (name, text) in boards {
        if env("SOLID_BOARD").is_some_and(|b| b != name) {
            continue;
        }
        let board = Board::from_toml_str(text).unwrap();
        let points = board.scan_points_m();
        let k_bar = board.joint().k_con_n_per_m;
        for bolted in [false, true] {
            if env("SOLID_ONLY").is_some_and(|o| o != if bolted { "bolted" } else { "free" }) {
                continue;
            }
            let n_modes = if bolted { 11 } else { 12 };
            let max_hz = if bolted { 4000.0 } else { 5000.0 };
            let st = State {
                e_x_pa: board.core.e_x_pa,
                e_y_pa: board.core.e_y_pa,
                g_xy_pa: board.core.g_xy_pa,
                mass_scale: 1.0,
                k_joint_n_per_m: if bolted {
                    vec![k_bar; board.holes.len()]
                } else {
                    vec![]
                },
                k_rot_nm_per_rad: if bolted {
                    env("SOLID_K_ROT").map(|v| v.parse().expect("SOLID_K_ROT in N·m/rad"))
                } else {
                    None
                },
                point_mass: None,
                underfill_factor: None,
                fixture: None,
                n_modes,
            };
            let setup = if bolted { "bolted" } else { "free" };
            let mut last = None;
            for &h in &sizes_mm {
                let d = SolidOptions::default();
                let opts = SolidOptions {
                    element_size_m: 1e-3 * h,
                    g_xz_pa: g_z_pa.unwrap_or(d.g_xz_pa),
                    g_yz_pa: g_z_pa.unwrap_or(d.g_yz_pa),
                    riding_mass_kg: env("SOLID_RIDING_KG").map_or(d.riding_mass_kg, |v| {
                        v.parse().expect("SOLID_RIDING_KG in kg")
                    }),
                    ..d
                };
                let t0 = Instant::now();
                let m = SolidModel::build(&board, &opts, bolted, None, solver.clone()).unwrap();
                let t1 = Instant::now();
                let modes = m.modes(&st, &points, [-0.012, 0.025, -0.008]).unwrap();
                let t2 = Instant::now();
                let (n3, nb) = m.size();
                println!(
                    "{name} {setup} h={h} mm: {n3} nodes, {nb} bricks, mesh {:.1} s, solve {:.1} s; f = {:?}",
                    (t1 - t0).as_secs_f64(),
                    (t2 - t1).as_secs_f64(),
                    modes.freq_hz.iter().map(|f| (f * 10.0).round() / 10.0).collect::<Vec<_>>()
                );
                last = Some(modes);
            }
            let truth = last.unwrap();
            // The updating model at its own mesh, nominal parameters.
            let setup_fe = if bolted { Setup::bolted() } else { Setup::Free };
            let mut board = board.clone();
            if let Some(g) =
                env("PLATE_G_Z_PA").map(|v| v.parse::<f64>().expect("PLATE_G_Z_PA in Pa"))
            {
                board.core.g_xz_pa = Some(g);
                board.core.g_yz_pa = Some(g);
            }
            if let (Some(t), Some(j)) = (env("PLATE_TANGENTIAL"), board.joint.as_mut()) {
                j.tangential_over_normal = t.parse().expect("PLATE_TANGENTIAL: a ratio");
            }
            let mut mesh = board.mesh_for(&setup_fe).clone();
            if let Some(m) = env("PLATE_MESH") {
                let n: Vec<usize> = m
                    .split(',')
                    .map(|v| v.parse().expect("PLATE_MESH nx,ny"))
                    .collect();
                (mesh.nx, mesh.ny) = (n[0], n[1]);
            }
            let fe = FeModel::build(&board, setup_fe.clone(), &mesh).unwrap();
            let mut p = fe.nominal_params();
            if bolted {
                p.set(names::K_CON, k_bar).unwrap();
            }
            let um = fe.modes(&p, n_modes + 2).unwrap();
            let shapes = fe.w_at(&um, &points).unwrap();
            let ushape =
                |j: usize| -> Vec<f64> { (0..points.len()).map(|o| shapes[(o, j)]).collect() };
            // Bolted: also the plate at the K_con that fits the truth best (least squares in
            // relative frequency over the in-band modes, a log grid ×1/4 … ×16 of K̄), the
            // residual a step-2 update could not remove.
            let best_k = if bolted {
                let misfit = |k: f64| -> f64 {
                    let mut p = fe.nominal_params();
                    p.set(names::K_CON, k).unwrap();
                    let um = fe.modes(&p, n_modes + 2).unwrap();
                    let sh = fe.w_at(&um, &points).unwrap();
                    let s =
                        |j: usize| -> Vec<f64> { (0..points.len()).map(|o| sh[(o, j)]).collect() };
                    let mut ss = 0.0;
                    for (r, f) in truth
                        .freq_hz
                        .iter()
                        .enumerate()
                        .filter(|(_, f)| **f < max_hz)
                    {
                        let j = (0..um.freq_hz.len())
                            .max_by(|a, b| {
                                mac(&truth.shapes[r], &s(*a))
                                    .total_cmp(&mac(&truth.shapes[r], &s(*b)))
                            })
                            .unwrap();
                        ss += (um.freq_hz[j] / f - 1.0).powi(2);
                    }
                    ss
                };
                // A log grid, then golden-section search on ln K between the best point's
                // neighbours (to 0.1 % in K).
                let lnk = |i: f64| k_bar.ln() + std::f64::consts::LN_2 * (-2.0 + 6.0 * i / 24.0);
                let i_best = (0..=24)
                    .map(|i| (i, misfit(lnk(i as f64).exp())))
                    .min_by(|a, b| a.1.total_cmp(&b.1))
                    .unwrap()
                    .0 as f64;
                let (mut lo, mut hi) = (lnk(i_best - 1.0), lnk(i_best + 1.0));
                let g = (5f64.sqrt() - 1.0) / 2.0;
                while hi - lo > 1e-3 {
                    let (a, b) = (hi - g * (hi - lo), lo + g * (hi - lo));
                    if misfit(a.exp()) < misfit(b.exp()) {
                        hi = b;
                    } else {
                        lo = a;
                    }
                }
                Some((0.5 * (lo + hi)).exp())
            } else {
                None
            };
            if let Some(k) = best_k {
                p.set(names::K_CON, k).unwrap();
            }
            let um_fit = fe.modes(&p, n_modes + 2).unwrap();
            println!(
                "{name} {setup}: mode, truth Hz, plate Hz, plate/truth - 1 %, MAC{}",
                best_k.map_or(String::new(), |k| format!(
                    "; then at the best K_con {k:.3e} N/m (K̄ {k_bar:.1e}): plate Hz, %"
                ))
            );
            for (r, f) in truth
                .freq_hz
                .iter()
                .enumerate()
                .filter(|(_, f)| **f < max_hz)
            {
                let (j, best) = (0..um.freq_hz.len())
                    .map(|j| (j, mac(&truth.shapes[r], &ushape(j))))
                    .max_by(|a, b| a.1.total_cmp(&b.1))
                    .unwrap();
                let fit = if best_k.is_some() {
                    format!(
                        "  {:8.1} {:+7.3}",
                        um_fit.freq_hz[j],
                        100.0 * (um_fit.freq_hz[j] / f - 1.0)
                    )
                } else {
                    String::new()
                };
                println!(
                    "  {:2} {:8.1} {:8.1} {:+7.3} {:.3}{fit}",
                    r + 1,
                    f,
                    um.freq_hz[j],
                    100.0 * (um.freq_hz[j] / f - 1.0),
                    best
                );
            }
        }
    }
}

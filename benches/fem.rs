//! Benchmarks of the physics core (plain `Instant` timing, numbers printed):
//! full-model assembly + lowest 20 modes on the default mesh, and ROM evaluations per
//! second on one core (first 8 frequencies + shapes at the default scan points).

use std::hint::black_box;
use std::time::Instant;

use hbmu::fem::board::{Board, MeshOptions};
use hbmu::fem::model::{FeModel, Setup};
use hbmu::fem::rom::{latin_hypercube_params, Rom, RomOptions};

/// CPU time of this thread, s (from /proc/thread-self/schedstat, ns resolution), so
/// that numbers are not inflated by other processes on a shared machine.
fn cpu_s() -> f64 {
    std::fs::read_to_string("/proc/thread-self/schedstat")
        .ok()
        .and_then(|s| {
            s.split_whitespace()
                .next()
                .and_then(|v| v.parse::<f64>().ok())
        })
        .map(|ns| ns * 1e-9)
        .unwrap_or(f64::NAN)
}

/// Reset the process's peak resident set size (Linux: `5` to /proc/self/clear_refs), so
/// that [`peak_rss_mb`] reports the peak of what runs after.
fn reset_peak_rss() {
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}

/// Peak resident set size of the process since the last reset, MB (VmHWM), NaN if
/// unavailable.
fn peak_rss_mb() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|v| v.parse::<f64>().ok())
        })
        .map(|kb| kb / 1024.0)
        .unwrap_or(f64::NAN)
}

fn main() {
    faer::set_global_parallelism(faer::Par::Seq);
    let board = Board::default_board();
    for (label, setup) in [("free", Setup::Free), ("bolted", Setup::bolted())] {
        let mut best_build = f64::INFINITY;
        let mut best_modes = f64::INFINITY;
        let mut n_dof = 0;
        reset_peak_rss();
        for _ in 0..3 {
            let t0 = Instant::now();
            let model =
                FeModel::build(&board, setup.clone(), board.mesh_for(&setup)).expect("build");
            let t1 = Instant::now();
            let modes = model.modes(&model.nominal_params(), 20).expect("modes");
            let t2 = Instant::now();
            black_box(&modes);
            n_dof = model.n_dof;
            best_build = best_build.min((t1 - t0).as_secs_f64());
            best_modes = best_modes.min((t2 - t1).as_secs_f64());
        }
        println!(
            "full {label}: {n_dof} DOFs, assembly {:.1} ms, lowest 20 modes {:.1} ms (best of 3), peak RSS {:.0} MB",
            best_build * 1e3,
            best_modes * 1e3,
            peak_rss_mb()
        );
    }
    // Copper integrated per piece: assembly and 8 modes of the realistic board
    // (partial pours, traces, cut-outs: many cut elements), and the mesh choice of
    // `fe modes` (0.02 %) on the default board.
    let realistic = Board::from_toml_str(include_str!("../data/boards/realistic.toml"))
        .expect("realistic board");
    // 42 × 27 bolted: the mesh `fe modes` chooses for the bolted realistic board (graded
    // towards the joints; 85 × 53 on the uniform mesh it replaced).
    for (label, setup, nx, ny) in [
        ("free", Setup::Free, 40, 25),
        ("free", Setup::Free, 120, 75),
        ("bolted", Setup::bolted(), 42, 27),
        ("bolted", Setup::bolted(), 85, 53),
    ] {
        reset_peak_rss();
        let t0 = Instant::now();
        let model = FeModel::build(&realistic, setup, &MeshOptions { nx, ny }).expect("build");
        let t1 = Instant::now();
        black_box(model.modes(&model.nominal_params(), 8).expect("modes"));
        println!(
            "realistic {label} {nx}x{ny}: {} DOFs, assembly {:.0} ms, 8 modes {:.0} ms, peak RSS {:.0} MB",
            model.n_dof,
            (t1 - t0).as_secs_f64() * 1e3,
            t1.elapsed().as_secs_f64() * 1e3,
            peak_rss_mb()
        );
    }
    // A raster density map of 0.2 mm cells (400 × 250, values varying cell to cell) as
    // the top copper: assembly cost of per-cell exact integration.
    {
        let mut b = board.clone();
        let (nx, ny) = (400usize, 250usize);
        let values = (0..nx * ny)
            .map(|k| 0.2 + 0.6 * (((k * 7919) % 101) as f64 / 100.0))
            .collect();
        b.copper[0].coverage.clear();
        b.copper[0].density_maps = vec![hbmu::fem::board::DensityMap {
            file: "bench.csv".into(),
            x0_m: 0.0,
            y0_m: 0.0,
            x1_m: b.length_x_m,
            y1_m: b.width_y_m,
            grid: Some(hbmu::fem::board::Grid { nx, ny, values }),
        }];
        let t0 = Instant::now();
        let model = FeModel::build(&b, Setup::Free, &b.mesh).expect("build");
        println!(
            "raster 400x250 cells on {}x{}: assembly {:.0} ms",
            b.mesh.nx,
            b.mesh.ny,
            t0.elapsed().as_secs_f64() * 1e3
        );
        black_box(model);
    }
    for (label, setup) in [("free", Setup::Free), ("bolted", Setup::bolted())] {
        let t0 = Instant::now();
        let p = FeModel::build(&board, setup.clone(), &board.mesh)
            .expect("build")
            .nominal_params();
        let c = hbmu::fem::convergence::choose_mesh(
            &board,
            &setup,
            &p,
            8,
            hbmu::fem::convergence::DEFAULT_MESH_TOL,
            hbmu::fem::convergence::MAX_CHOICE_ELEMENTS,
        )
        .expect("choice");
        println!(
            "mesh choice {label} (default board, tol 0.02 %): {}x{} (estimate {:.4} %), {:.1} s",
            c.chosen.mesh[0],
            c.chosen.mesh[1],
            100.0 * c.chosen.max_rel_error,
            t0.elapsed().as_secs_f64()
        );
    }
    // Mesh study of the default board: first 8 free-free and 7 bolted frequencies on
    // four meshes, Richardson-extrapolated from the two finest (BFS: O(h⁴)), with the
    // cost of each full solve.
    for (label, setup, n_modes) in [("free", Setup::Free, 8), ("bolted", Setup::bolted(), 7)] {
        let meshes = [(40, 25), (80, 50), (120, 75), (160, 100)];
        let mut freqs = Vec::new();
        for &(nx, ny) in &meshes {
            let t0 = Instant::now();
            let model =
                FeModel::build(&board, setup.clone(), &MeshOptions { nx, ny }).expect("build");
            let t1 = Instant::now();
            let f = model
                .modes(&model.nominal_params(), n_modes)
                .expect("modes")
                .freq_hz;
            println!(
                "mesh {label} {nx}x{ny}: {} DOFs, assembly {:.0} ms, {n_modes} modes {:.0} ms",
                model.n_dof,
                (t1 - t0).as_secs_f64() * 1e3,
                t1.elapsed().as_secs_f64() * 1e3
            );
            freqs.push(f);
        }
        let ratio: f64 = 160.0 / 120.0;
        let rich: Vec<f64> = (0..n_modes)
            .map(|j| freqs[3][j] + (freqs[3][j] - freqs[2][j]) / (ratio.powi(4) - 1.0))
            .collect();
        for (k, &(nx, ny)) in meshes.iter().enumerate() {
            let errs: Vec<String> = (0..n_modes)
                .map(|j| format!("{:+.3}", 100.0 * (freqs[k][j] / rich[j] - 1.0)))
                .collect();
            println!(
                "mesh {label} {nx}x{ny}: error vs Richardson, %: {}",
                errs.join(" ")
            );
        }
    }
    for (label, setup, n_modes) in [("free", Setup::Free, 8), ("bolted", Setup::bolted(), 7)] {
        let model = FeModel::build(&board, setup.clone(), board.mesh_for(&setup)).expect("build");
        reset_peak_rss();
        let t0 = Instant::now();
        let rom = Rom::build(
            &model,
            &RomOptions {
                n_modes,
                ..RomOptions::default()
            },
        )
        .expect("rom");
        let t_build = t0.elapsed().as_secs_f64();
        let rom_peak_mb = peak_rss_mb();
        let pts = board.scan_points_m();
        let sop = rom.shape_operator(&model, &pts).expect("shape operator");
        let sample = latin_hypercube_params(&model.map, 1000, 0.2, 7);
        let coefs: Vec<_> = sample
            .iter()
            .map(|p| rom.map.coefficients(p).expect("coefs"))
            .collect();
        let (mut best, mut best_cpu) = (f64::INFINITY, f64::INFINITY);
        for _ in 0..5 {
            let (t, c0) = (Instant::now(), cpu_s());
            for c in &coefs {
                black_box(rom.eval_coefs(&c.k, &c.m, &sop).expect("eval"));
            }
            best = best.min(t.elapsed().as_secs_f64());
            best_cpu = best_cpu.min(cpu_s() - c0);
        }
        // Breakdown: the dense eigen-solve alone.
        let r_us = rom.dim();
        let mut a0 = vec![0.0; r_us * r_us];
        for kf in &rom.k_r {
            for i in 0..r_us {
                for j in 0..r_us {
                    a0[i * r_us + j] += kf[(i, j)];
                }
            }
        }
        let c0 = cpu_s();
        for _ in 0..coefs.len() {
            let mut a = a0.clone();
            black_box(hbmu::fem::dense::lowest_eigenpairs(
                &mut a,
                r_us,
                rom.n_rigid,
                n_modes,
            ));
        }
        let eig_us = (cpu_s() - c0) / coefs.len() as f64 * 1e6;
        let c0 = cpu_s();
        for _ in 0..coefs.len() {
            let a = faer::Mat::from_fn(r_us, r_us, |i, j| a0[i * r_us + j]);
            black_box(a.self_adjoint_eigen(faer::Side::Lower).expect("evd"));
        }
        let faer_us = (cpu_s() - c0) / coefs.len() as f64 * 1e6;
        println!("ROM {label}: dense eigen-solve alone {eig_us:.1} µs CPU (faer self_adjoint_eigen, all vectors: {faer_us:.1} µs CPU)");
        let per_s = coefs.len() as f64 / best_cpu;
        println!(
            "ROM {label}: wall {:.0} evaluations/s, CPU {:.0} evaluations/s",
            coefs.len() as f64 / best,
            per_s
        );
        let r = rom.dim() as f64;
        // Flops of one dense evaluation: affine sum (n_k r²), Householder
        // tridiagonalisation (4/3 r³), eigenvalues by QL (~30 r), back-transformed
        // eigenvectors (2 r² per vector), shapes at points (2 n_pts r per mode).
        let nk = rom.k_r.len() as f64;
        let k = (n_modes + rom.n_rigid) as f64;
        let flops = nk * r * r
            + 4.0 / 3.0 * r.powi(3)
            + 4.0 * r * r * k
            + 2.0 * pts.len() as f64 * r * n_modes as f64;
        println!(
            "ROM {label}: build {:.1} s (peak RSS {:.0} MB), r = {}, {} scan points, {:.0} evaluations/s on one core ({:.1} µs each, ≈ {:.0} kflop each → {:.2} Gflop/s)",
            t_build,
            rom_peak_mb,
            rom.dim(),
            pts.len(),
            per_s,
            1e6 / per_s,
            flops / 1e3,
            flops * per_s / 1e9
        );
    }
}

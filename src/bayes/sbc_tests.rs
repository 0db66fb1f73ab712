//! Simulation-based calibration of the step-1 modal target on a ROM (Talts et al. 2018), in CI.
//!
//! The problem (small so that the test stays well under two minutes on two shared cores):
//! the built-in board on a coarse 16 × 10 mesh, a ROM with at most 14 basis vectors
//! (n_modes = 5, 8 random snapshots), 2 boards × 2 free-free measurements, 3 updated modes
//! (the first three elastic modes), 2 updated parameters (e_x_pa, g_xy_pa as relative
//! deviations), μ ~ N(0, 0.05²), σ ~ HalfNormal(0.03), LKJ(2); ε inferred per mode,
//! ln ε ~ N(ln 0.02, 0.3²) (about 1 % in frequency: moderately informative data, few
//! tempering stages). The data are simulated from the prior through the same ROM (see
//! `sbc_driver` for the exact draw of the eigenvalues and for how ranks and ties are formed).
//!
//! Test: 100 replications, SMC with 100 particles, L = 21 draws (22 ranks) per replication,
//! for each of μ_e_x, μ_g_xy, ln σ_e_x, board 0's e_x and ln ε of mode 1: Pearson's
//! chi-square on 11 bins of 2 ranks (10 degrees of freedom, exact tail), family-wise level
//! 0.01 with Bonferroni over the 5 quantities (each p > 0.002). Fixed seeds: deterministic.
//! The larger run is the benchmark `benches/sbc.rs`.

use super::modal::{FreqObs, ModalPredictor, UnitData};
use super::population::{PopulationPrior, SigmaPrior};
use super::smc::{self, SmcOptions, Target};
use super::target::{Compose, ErrorModel, ErrorPrior, ModalTarget};
use crate::fem::{Board, FeModel, MeshOptions, Rom, RomOptions, Setup};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use rayon::prelude::*;

#[path = "sbc_driver.rs"]
pub(crate) mod driver;

use driver::*;

pub(crate) fn ci_problem() -> Problem {
    Problem {
        boards: 2,
        measurements: 2,
        modes: vec![0, 1, 2],
        params: vec!["e_x_pa", "g_xy_pa"],
        mesh: (16, 10),
        max_basis: 14,
        rom_random: 8,
        mu_sd: 0.05,
        sigma_scale: 0.03,
        sigma_prior: SigmaPrior::HalfNormal,
        lkj_eta: 2.0,
        eps: ErrorPrior::Inferred {
            median: 0.02,
            log_sd: 0.3,
        },
    }
}

/// The chi-square tail against published table values (upper quantiles of χ²_k).
#[test]
fn chi2_tail_matches_tables() {
    // k = 2: exactly e^{−x/2}.
    assert!((chi2_sf_even(3.0, 2) - (-1.5f64).exp()).abs() < 1e-15);
    // k = 10: χ²_0.95 = 18.307, χ²_0.99 = 23.209, χ²_0.5 = 9.342.
    for (x, p) in [(18.307, 0.05), (23.209, 0.01), (9.342, 0.5)] {
        assert!(
            (chi2_sf_even(x, 10) - p).abs() < 2e-4,
            "{x}: {}",
            chi2_sf_even(x, 10)
        );
    }
    // k = 20: χ²_0.95 = 31.410.
    assert!((chi2_sf_even(31.410, 20) - 0.05).abs() < 2e-4);
}

/// Ranks of the true values among posterior draws are uniform (see the module doc).
#[test]
fn sbc_ranks_of_the_step1_target_are_uniform() {
    let p = ci_problem();
    let sim = build_target(&p);
    let names = quantity_names(&sim, &p.params);
    let opts = SmcOptions {
        n_particles: 100,
        ..SmcOptions::default()
    };
    let (reps, draws, bins) = (100, 21, 11);
    let t0 = std::time::Instant::now();
    let s = run_sbc(&sim, &|t| t, names, &opts, reps, draws, 20_261_123);
    let alpha = 0.01 / s.names.len() as f64;
    let mut report = vec![];
    let mut failed = vec![];
    for (name, ranks) in s.names.iter().zip(&s.ranks) {
        let (stat, pv, counts) = chi2_uniform(ranks, s.draws + 1, bins);
        report.push(format!(
            "{name:>16}: X² = {stat:6.2}, p = {pv:.4}, bins {counts:?}"
        ));
        if pv <= alpha {
            failed.push(name.clone());
        }
    }
    let mean_stages = s.stages.iter().sum::<usize>() as f64 / reps as f64;
    eprintln!(
        "SBC: {reps} replications × {} particles, {draws} draws, {mean_stages:.1} stages on average, {} prior draws redrawn, {:.1} s\n{}",
        opts.n_particles,
        s.redrawn,
        t0.elapsed().as_secs_f64(),
        report.join("\n")
    );
    assert!(
        failed.is_empty(),
        "ranks not uniform (p ≤ {alpha:.4}) for {failed:?}:\n{}",
        report.join("\n")
    );
}

//! Simulation-based calibration of the step-1 modal target at benchmark size (the CI test
//! `bayes::sbc_tests` runs the same problem with 100 replications × 100 particles): prints
//! the chi-square p-value of every quantity's rank histogram, the Bonferroni verdict and the
//! time. Same problem as the CI test (see `src/bayes/sbc_tests.rs`), larger sampler and more
//! replications: `HBMU_SBC_REPS` (default 400) × `HBMU_SBC_PARTICLES` (default 200)
//! particles, L = 104 draws per replication (105 ranks) in 21 bins of 5 (20 degrees of
//! freedom).
//!
//! `cargo bench --bench sbc`

use hbmu::bayes::modal::{FreqObs, ModalPredictor, UnitData};
use hbmu::bayes::population::{PopulationPrior, SigmaPrior};
use hbmu::bayes::smc::{self, SmcOptions, Target};
use hbmu::bayes::target::{Compose, ErrorModel, ErrorPrior, ModalTarget};
use hbmu::fem::{Board, FeModel, MeshOptions, Rom, RomOptions, Setup};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use rayon::prelude::*;

#[path = "../src/bayes/sbc_driver.rs"]
#[allow(dead_code)]
mod driver;

use driver::*;

fn env_usize(name: &str, default: usize) -> usize {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn main() {
    let reps = env_usize("HBMU_SBC_REPS", 400);
    let particles = env_usize("HBMU_SBC_PARTICLES", 200);
    let (draws, bins) = (104, 21);
    let p = Problem {
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
    };
    let t0 = std::time::Instant::now();
    let sim = build_target(&p);
    let build_s = t0.elapsed().as_secs_f64();
    let names = quantity_names(&sim, &p.params);
    let opts = SmcOptions {
        n_particles: particles,
        ..SmcOptions::default()
    };
    let t1 = std::time::Instant::now();
    let s = run_sbc(&sim, &|t| t, names, &opts, reps, draws, 20_261_124);
    let run_s = t1.elapsed().as_secs_f64();
    let alpha = 0.01 / s.names.len() as f64;
    println!(
        "SBC benchmark: {reps} replications × {particles} particles, {} draws ({} ranks, {bins} bins), ROM built in {build_s:.1} s, SBC {run_s:.1} s ({:.2} s per replication), {:.1} stages on average, {} prior draws redrawn",
        s.draws,
        s.draws + 1,
        run_s / reps as f64,
        s.stages.iter().sum::<usize>() as f64 / reps as f64,
        s.redrawn
    );
    let mut all_ok = true;
    for (name, ranks) in s.names.iter().zip(&s.ranks) {
        let (stat, pv, counts) = chi2_uniform(ranks, s.draws + 1, bins);
        let ok = pv > alpha;
        all_ok &= ok;
        println!(
            "{name:>16}: X² = {stat:7.2} (20 dof), p = {pv:.4} {} bins {counts:?}",
            if ok { "ok " } else { "NOT UNIFORM" }
        );
    }
    println!(
        "Bonferroni at family-wise 0.01 (each p > {alpha:.4}): {}",
        if all_ok { "uniform" } else { "NOT uniform" }
    );
}

//! The acceleration pipeline of [`super::sampler::run_smc`] (the Laplace-type reference start,
//! the per-unit surrogates and subspaces, the correction to the ROM) against plain tempering
//! from the prior, which the simulation-based calibration (`bayes::sbc_tests`) shows samples
//! the exact posterior. The accelerations change how the posterior is reached, never which:
//! on the SBC's small step-1 problem, with data from one prior draw, both give the same
//! posterior moments within their Monte Carlo error.

use super::sampler::{run_smc, SamplerParams};
use crate::bayes::sbc_tests::ci_problem;
use crate::bayes::sbc_tests::driver::{build_target, quantities, quantity_names, simulate_data};
use crate::bayes::smc::{SmcOptions, Target};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// Mean and sd of each quantity over every run's final particles.
fn moments(t: &crate::bayes::target::ModalTarget, r: &super::sampler::Results) -> Vec<[f64; 2]> {
    let q: Vec<Vec<f64>> = r
        .iter()
        .flat_map(|run| run.particles.iter().map(|p| quantities(t, &p.g, &p.x)))
        .collect();
    let n = q.len() as f64;
    (0..q[0].len())
        .map(|k| {
            let m = q.iter().map(|v| v[k]).sum::<f64>() / n;
            let v = q.iter().map(|v| (v[k] - m).powi(2)).sum::<f64>() / (n - 1.0);
            [m, v.sqrt()]
        })
        .collect()
}

#[test]
fn the_accelerated_pipeline_samples_the_posterior_of_plain_tempering() {
    let p = ci_problem();
    let mut t = build_target(&p);
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let (g, x) = t.sample_prior(&mut rng);
    t.units = simulate_data(&t, &g, &x, &mut rng).expect("the ROM tracks the prior draw");
    let fast = SamplerParams {
        seed: 5,
        runs: 2,
        smc: SmcOptions {
            n_particles: 1500,
            ..SmcOptions::default()
        },
        residual_draws: 0,
        from_prior: false,
        surrogate: true,
        subspace: true,
    };
    let plain = SamplerParams {
        seed: 6,
        from_prior: true,
        surrogate: false,
        subspace: false,
        ..fast.clone()
    };
    let quiet = |_: u64, _: String| {};
    let run = |o: &SamplerParams| {
        run_smc(&t, o, "boards", &[], None, &|_, _| Ok(()), &quiet, false).unwrap()
    };
    let (rf, acc) = run(&fast);
    let (rp, _) = run(&plain);
    // The accelerations ran: a reference start, a surrogate for every unit, a correction.
    assert_eq!(acc.start, "reference");
    assert_eq!(acc.surrogate_units, t.units.len(), "{acc:?}");
    assert_eq!(acc.correction_ess.len(), fast.runs);
    // Tolerances from the Monte Carlo error: 3000 particles per method and an effective
    // sample of at least 500 after resampling and mutation put a mean's error under 0.045 sd
    // per method (0.065 sd for the difference) and an sd's relative error under 3.2 % (4.5 %
    // for the ratio): 0.2 sd and 15 % are over 3 standard errors.
    let names = quantity_names(&t, &p.params);
    for ((n, f), s) in names.iter().zip(moments(&t, &rf)).zip(moments(&t, &rp)) {
        let z = (f[0] - s[0]) / s[1];
        assert!(
            z.abs() < 0.2,
            "{n}: mean {} vs {} (sd {}): {z:.2} sd",
            f[0],
            s[0],
            s[1]
        );
        let ratio = f[1] / s[1];
        assert!(
            (0.85..1.18).contains(&ratio),
            "{n}: sd {} vs {}",
            f[1],
            s[1]
        );
    }
}

//! Benchmark of the convergence diagnostics: `summarize` (R-hat, bulk and tail ESS, moments
//! and quantiles) of 50 parameters × 4 chains × N draws, for N = 2000 and 5000, AR(1) draws
//! with φ = 0.9. Target: well under a second for all 50 parameters.
//!
//! Run: `cargo bench --bench diagnostics`.

use std::hint::black_box;
use std::time::Instant;

use hbmu::bayes::diagnostics::summarize;

/// Deterministic draws from the crate's seeded generator.
struct Rng(rand_chacha::ChaCha8Rng);

impl Rng {
    fn new(seed: u64) -> Rng {
        Rng(rand::SeedableRng::seed_from_u64(seed))
    }

    fn normal(&mut self) -> f64 {
        rand_distr::Distribution::sample(&rand_distr::StandardNormal, &mut self.0)
    }
}

fn main() {
    let mut rng = Rng::new(7);
    for n_draw in [2000usize, 5000] {
        let params: Vec<Vec<Vec<f64>>> = (0..50)
            .map(|_| {
                (0..4)
                    .map(|_| {
                        let mut x = 0.0;
                        (0..n_draw)
                            .map(|_| {
                                x = 0.9 * x + rng.normal();
                                x
                            })
                            .collect()
                    })
                    .collect()
            })
            .collect();
        let mut best = f64::INFINITY;
        for _ in 0..5 {
            let t = Instant::now();
            for chains in &params {
                black_box(summarize(black_box(chains)));
            }
            best = best.min(t.elapsed().as_secs_f64());
        }
        println!(
            "summarize: 50 parameters x 4 chains x {n_draw} draws: {:.1} ms (best of 5, one thread)",
            best * 1e3
        );
    }
}

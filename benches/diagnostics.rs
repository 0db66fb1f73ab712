//! Benchmark of the convergence diagnostics: `summarize` (R-hat, bulk and tail ESS, moments
//! and quantiles) of 50 parameters × 4 chains × N draws, for N = 2000 and 5000, AR(1) draws
//! with φ = 0.9. Target: well under a second for all 50 parameters.
//!
//! Run: `cargo bench --bench diagnostics`.

use std::hint::black_box;
use std::time::Instant;

use hbmu::bayes::diagnostics::summarize;

/// SplitMix64 + Box-Muller: deterministic draws without a `rand` dependency.
struct Rng(u64);

impl Rng {
    fn uniform(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        ((z >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }

    fn normal(&mut self) -> f64 {
        let (u, v) = (self.uniform(), self.uniform());
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }
}

fn main() {
    let mut rng = Rng(7);
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

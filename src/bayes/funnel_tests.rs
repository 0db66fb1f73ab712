//! The error-scale funnel, against quadrature: B units x_b ∈ ℝ² ~ N(0, I), three "modes"
//! y_bm = a_m·x_b + e, e ~ N(0, ε_m²), ln ε_m ~ N(ln 0.05, 1.5²). Two parameters per unit
//! fit two of the three modes exactly, so the likelihood is unbounded as any ε_m → 0 and the
//! posterior of ln ε_m has a long left tail (the structure of step 2 with two joint
//! parameters per measurement and three modes). Given ε the units integrate out in closed
//! form (y_b ~ N(0, AAᵀ + diag ε²)), so the marginal posterior of (ln ε_1, ln ε_2, ln ε_3) is a
//! three-dimensional quadrature: the reference the sampler is held to.

use super::diagnostics::{ess_bulk, rhat};
use super::smc::{self, SmcOptions, Target};
use super::stats::normal_lpdf;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

const A: [[f64; 2]; 3] = [[1.0, 0.0], [0.0, 1.0], [0.6, 0.8]];
const PRIOR_MEDIAN: f64 = 0.05;
const PRIOR_LOG_SD: f64 = 1.5;

pub(super) struct Funnel {
    y: Vec<[f64; 3]>,
    /// Offer the residual-scaling moves (`Target::log_error_scales`).
    rescale: bool,
    /// The start `Target::data_start_global` offers for any other g (None: none).
    pub(super) restart: Option<Vec<f64>>,
    /// `Target::collapsed_global` reports a collapse where some ln ε_m is below this.
    pub(super) collapse_below: Option<f64>,
}

impl Funnel {
    pub(super) fn new(n_units: usize, eps: [f64; 3], seed: u64, rescale: bool) -> Funnel {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut n = || -> f64 { StandardNormal.sample(&mut rng) };
        let y = (0..n_units)
            .map(|_| {
                let x = [n(), n()];
                let mut y = [0.0; 3];
                for m in 0..3 {
                    y[m] = A[m][0] * x[0] + A[m][1] * x[1] + eps[m] * n();
                }
                y
            })
            .collect();
        Funnel {
            y,
            rescale,
            restart: None,
            collapse_below: None,
        }
    }

    /// log p(y | ln ε) with the units integrated out.
    fn log_marginal(&self, le: &[f64; 3]) -> f64 {
        let mut s = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                s[i][j] = A[i][0] * A[j][0] + A[i][1] * A[j][1];
            }
            s[i][i] += (2.0 * le[i]).exp();
        }
        let flat: Vec<f64> = s.iter().flatten().copied().collect();
        let (l, _) = super::stats::cholesky_jittered(&flat, 3);
        let log_det: f64 = (0..3).map(|i| 2.0 * l[i * 3 + i].ln()).sum();
        self.y
            .iter()
            .map(|y| {
                let q = super::stats::lower_solve_sq_norm(&l, 3, y, &[0.0; 3]);
                -0.5 * (q + log_det + 3.0 * super::stats::LN_2PI)
            })
            .sum()
    }

    /// Quantiles of the marginal posterior of every ln ε_m by quadrature on a grid
    /// (h = 0.08 in ln ε, from 7 prior medians' e-folds below to 3 above).
    fn reference_quantiles(&self, probs: &[f64]) -> Vec<Vec<f64>> {
        let (lo, hi, n) = (PRIOR_MEDIAN.ln() - 7.0, PRIOR_MEDIAN.ln() + 3.0, 126);
        let h = (hi - lo) / (n - 1) as f64;
        let grid: Vec<f64> = (0..n).map(|i| lo + h * i as f64).collect();
        let prior: Vec<f64> = grid
            .iter()
            .map(|v| normal_lpdf(*v, PRIOR_MEDIAN.ln(), PRIOR_LOG_SD))
            .collect();
        let mut lp = Vec::with_capacity(n * n * n);
        for i in 0..n {
            for j in 0..n {
                for k in 0..n {
                    let le = [grid[i], grid[j], grid[k]];
                    lp.push(self.log_marginal(&le) + prior[i] + prior[j] + prior[k]);
                }
            }
        }
        let top = lp.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let mut marg = vec![vec![0.0; n]; 3];
        for (idx, v) in lp.iter().enumerate() {
            let w = (v - top).exp();
            for (m, i) in [idx / (n * n), (idx / n) % n, idx % n]
                .into_iter()
                .enumerate()
            {
                marg[m][i] += w;
            }
        }
        // Piecewise-constant density on cells centred on the grid points.
        marg.iter()
            .map(|mg| {
                let total: f64 = mg.iter().sum();
                probs
                    .iter()
                    .map(|&p| {
                        let mut acc = 0.0;
                        for (i, w) in mg.iter().enumerate() {
                            let w = w / total;
                            if acc + w >= p {
                                return grid[i] - 0.5 * h + h * (p - acc) / w;
                            }
                            acc += w;
                        }
                        hi
                    })
                    .collect()
            })
            .collect()
    }
}

impl Target for Funnel {
    type Cache = [f64; 3];
    type Ctx = [f64; 3];
    fn n_global(&self) -> usize {
        3
    }
    fn n_units(&self) -> usize {
        self.y.len()
    }
    fn unit_dim(&self) -> usize {
        2
    }
    fn sample_prior(&self, rng: &mut ChaCha8Rng) -> (Vec<f64>, Vec<Vec<f64>>) {
        let mut n = || -> f64 { StandardNormal.sample(rng) };
        let g = (0..3)
            .map(|_| PRIOR_MEDIAN.ln() + PRIOR_LOG_SD * n())
            .collect();
        let x = self.y.iter().map(|_| vec![n(), n()]).collect();
        (g, x)
    }
    fn log_prior_global(&self, g: &[f64]) -> f64 {
        g.iter()
            .map(|v| normal_lpdf(*v, PRIOR_MEDIAN.ln(), PRIOR_LOG_SD))
            .sum()
    }
    fn ctx(&self, g: &[f64]) -> [f64; 3] {
        [g[0].exp(), g[1].exp(), g[2].exp()]
    }
    fn log_prior_unit(&self, _ctx: &[f64; 3], _b: usize, x: &[f64]) -> f64 {
        x.iter().map(|v| normal_lpdf(*v, 0.0, 1.0)).sum()
    }
    fn model(&self, _aux: &[f64], _b: usize, x: &[f64]) -> Option<[f64; 3]> {
        Some(A.map(|a| a[0] * x[0] + a[1] * x[1]))
    }
    fn log_lik(&self, eps: &[f64; 3], b: usize, _x: &[f64], c: &[f64; 3]) -> f64 {
        (0..3)
            .map(|m| normal_lpdf(self.y[b][m], c[m], eps[m]))
            .sum()
    }
    fn to_standard(&self, _ctx: &[f64; 3], _b: usize, x: &[f64]) -> Vec<f64> {
        x.to_vec()
    }
    fn from_standard(&self, _ctx: &[f64; 3], _b: usize, z: &[f64]) -> Vec<f64> {
        z.to_vec()
    }
    fn log_error_scales(&self) -> Vec<usize> {
        if self.rescale {
            vec![0, 1, 2]
        } else {
            vec![]
        }
    }
    fn residual(&self, b: usize, m: usize, c: &[f64; 3]) -> Option<f64> {
        Some(c[m] - self.y[b][m])
    }
    fn data_start_global(&self, g: &[f64]) -> Option<(Vec<f64>, String)> {
        let r = self.restart.as_ref().filter(|r| r.as_slice() != g)?;
        Some((r.clone(), "a start the data give".into()))
    }
    fn collapsed_global(&self, g: &[f64]) -> Option<String> {
        let below = self.collapse_below?;
        g.iter()
            .position(|&v| v < below)
            .map(|m| format!("ln ε_{m} below {below}"))
    }
}

/// Pooled quantiles, R-hat and bulk ESS of ln ε_m over runs.
fn posterior(
    results: &[smc::RunResult<[f64; 3]>],
    m: usize,
    probs: &[f64],
) -> (Vec<f64>, f64, f64) {
    let chains: Vec<Vec<f64>> = results
        .iter()
        .map(|r| r.particles.iter().map(|p| p.g[m]).collect())
        .collect();
    let mut all: Vec<f64> = chains.iter().flatten().copied().collect();
    all.sort_by(f64::total_cmp);
    let q = probs
        .iter()
        .map(|&p| crate::report::validation::quantile_sorted(&all, p))
        .collect();
    (q, rhat(&chains), ess_bulk(&chains))
}

/// The sampler with the residual-scaling moves reproduces the quadrature's posterior of every
/// ln ε_m, long left tail included, and its runs agree. Measured (4 runs × 400 particles):
/// worst quantile error 0.075, R-hat ≤ 1.003, bulk ESS ≥ 1440 of 1600; without the moves
/// (`HBMU_FUNNEL_COMPARE=1` runs that too) the runs stay where tempering left them: R-hat
/// 1.38, ESS 9, the 5 % quantile 1.6 too high.
#[test]
fn error_scales_of_a_funnel_match_the_quadrature() {
    let probs = [0.05, 0.25, 0.5, 0.75, 0.95];
    let opts = SmcOptions {
        n_particles: 400,
        ..SmcOptions::default()
    };
    let compare = std::env::var_os("HBMU_FUNNEL_COMPARE").is_some();
    let reference = Funnel::new(30, [0.01, 0.01, 0.01], 7, true).reference_quantiles(&probs);
    let mut worst = (0.0f64, 0.0f64);
    for rescale in [true, false] {
        if !rescale && !compare {
            break;
        }
        let t = Funnel::new(30, [0.01, 0.01, 0.01], 7, rescale);
        let results: Vec<_> = (0..4)
            .map(|r| smc::run(&t, &opts, 11, r, &|_| {}).expect("run"))
            .collect();
        let evals: u64 = results
            .iter()
            .flat_map(|r| &r.stages)
            .map(|s| s.model_evals)
            .sum();
        for (m, reference) in reference.iter().enumerate() {
            let (q, rh, ess) = posterior(&results, m, &probs);
            let err = q
                .iter()
                .zip(reference)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            eprintln!(
                "rescale {rescale}: ln eps_{m}: sampler {q:.3?} quadrature {reference:.3?}: worst {err:.3}, R-hat {rh:.3}, ESS {ess:.0}, model evals {evals}"
            );
            if rescale {
                worst = (worst.0.max(err), worst.1.max(rh));
            }
        }
    }
    assert!(worst.0 < 0.2, "worst quantile error of ln ε {:.3}", worst.0);
    assert!(worst.1 < 1.03, "worst R-hat of ln ε {:.3}", worst.1);
}

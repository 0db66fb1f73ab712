//! The population (hyper-)prior of a hierarchical model: parameters of the units (boards,
//! joints) are θ_t ~ MVN(μ, diag(σ) Ω diag(σ)), in units chosen by the caller (the board
//! model uses relative deviations from nominal, θ = p/p_nom − 1).
//!
//! Unconstrained global vector, in this order:
//! - μ (d values), prior μ_k ~ N(m_k, w_k²);
//! - log σ (d values), prior σ_k ~ HalfNormal(s_k), with the Jacobian σ of the log map, or
//!   ln σ_k ~ N(ln(m s_k), 1.5²), m = 0.6745 the half-normal's median ([`SigmaPrior`]);
//! - y (d(d−1)/2 values), Ω = L Lᵀ with L from y by the canonical-partial-correlation
//!   transform z = tanh(y) (Lewandowski, Kurowicka & Joe 2009; Stan's `cholesky_corr`):
//!   L₀₀ = 1, L_i0 = z_i0, L_ij = z_ij √(1 − Σ_{k<j} L_ik²), L_ii = √(1 − Σ_{k<i} L_ik²);
//!   prior Ω ~ LKJ(η), whose density on the free elements of L is
//!   Π_{i≥1} L_ii^{d − i + 2η − 3} (0-based i), times the Jacobian
//!   Π_{i>j} (1 − z_ij²) √(1 − Σ_{k<j} L_ik²) of y → L.
//!
//! Under LKJ(η) the z_ij are independent with (z_ij + 1)/2 ~ Beta(b_j, b_j),
//! b_j = η + (d − 2 − j)/2, which is how [`PopulationPrior::sample`] draws Ω exactly.
//!
//! Non-centred form: θ_t = μ + diag(σ) L z_t with z_t ~ N(0, I) ([`Population::from_standard`]).

use rand::Rng;
use rand_distr::{Beta, Distribution, StandardNormal};

use super::stats::{half_normal_lpdf, normal_lpdf, LN_2PI};

/// The prior family of a population sd σ_k, of scale s_k (`PopulationPrior::sigma_scale`).
///
/// Why two: a half-normal whose scale sits well above the spread is flat in σ near the data,
/// and with few units a flat prior on σ widens the posterior of σ (σ² gets n − 2 degrees of
/// freedom instead of n − 1: with 6 boards the median of σ is 1.22 × the sample sd instead
/// of 1.07 ×), and so the prediction for a new unit. The log-normal over orders of magnitude
/// is locally the scale-invariant (Jeffreys) prior p(σ) ∝ 1/σ, whose new-unit predictive is
/// the classical prediction interval; it keeps the half-normal's median, so a scale means
/// the same typical size under both. The half-normal puts more mass near σ = 0 (units alike),
/// which suits a coefficient that is probably common to all units.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SigmaPrior {
    /// σ_k ~ HalfNormal(s_k).
    #[default]
    HalfNormal,
    /// ln σ_k ~ N(ln(0.6745 s_k), 1.5²).
    LogNormal,
}

/// The half-normal's median over its scale, Φ⁻¹(0.75): the log-normal's median.
const HALF_NORMAL_MEDIAN: f64 = 0.674_489_750_196_081_7;
/// Log-sd of the log-normal σ prior: 1.5 puts ±2 sd at e^±3, a factor of 20 either way.
pub const SIGMA_LOG_SD: f64 = 1.5;

/// Hyperprior settings for d unit parameters.
#[derive(Clone, Debug, serde::Serialize)]
pub struct PopulationPrior {
    /// Prior means of μ.
    pub mu_mean: Vec<f64>,
    /// Prior standard deviations of μ.
    pub mu_sd: Vec<f64>,
    /// Scales of σ's prior (the half-normal's scale; the log-normal's median is 0.6745 ×).
    pub sigma_scale: Vec<f64>,
    /// σ's prior family per coordinate; coordinates beyond its length are half-normal.
    pub sigma_prior: Vec<SigmaPrior>,
    /// LKJ shape η (1 = uniform over correlation matrices; larger = closer to I).
    pub lkj_eta: f64,
    /// The LKJ normalising constant, computed at its first use.
    #[serde(skip)]
    pub lkj_log_norm: LkjNorm,
}

/// A prior's LKJ normalising constant, computed once for the (d, η) it is first asked for
/// (the sampler asks at every move of the global vector) and recomputed for any other.
#[derive(Clone, Debug, Default)]
pub struct LkjNorm(std::sync::OnceLock<(usize, u64, f64)>);

impl LkjNorm {
    fn get(&self, d: usize, eta: f64) -> f64 {
        let &(cd, ce, c) = self
            .0
            .get_or_init(|| (d, eta.to_bits(), lkj_log_normaliser(d, eta)));
        if cd == d && ce == eta.to_bits() {
            c
        } else {
            lkj_log_normaliser(d, eta)
        }
    }
}

/// μ, σ and the Cholesky factors of one global vector.
#[derive(Clone, Debug)]
pub struct Population {
    pub mu: Vec<f64>,
    pub sigma: Vec<f64>,
    /// Cholesky factor of the correlation matrix, row-major d × d.
    pub l_corr: Vec<f64>,
    /// Cholesky factor of the covariance, diag(σ) L, row-major d × d.
    pub l_cov: Vec<f64>,
    /// Σ log diag(l_cov), for the normal's normalising constant.
    pub log_det_half: f64,
}

impl PopulationPrior {
    /// Number of unit parameters d.
    pub fn d(&self) -> usize {
        self.mu_mean.len()
    }

    /// Length of the unconstrained global vector.
    pub fn dim(&self) -> usize {
        let d = self.d();
        2 * d + d * (d - 1) / 2
    }

    /// σ's prior family of coordinate k.
    pub fn sigma_family(&self, k: usize) -> SigmaPrior {
        self.sigma_prior.get(k).copied().unwrap_or_default()
    }

    /// Names of the global coordinates, given the unit parameters' names.
    pub fn coordinate_names(&self, names: &[String]) -> Vec<String> {
        let d = self.d();
        let mut out: Vec<String> = names.iter().map(|n| format!("mu_{n}")).collect();
        out.extend(names.iter().map(|n| format!("log_sigma_{n}")));
        for i in 1..d {
            for j in 0..i {
                out.push(format!("lkj_y_{}_{}", names[i], names[j]));
            }
        }
        out
    }

    /// Log density of the unconstrained global vector (all Jacobians included).
    pub fn log_prior(&self, g: &[f64]) -> f64 {
        let (l, log_jac) = lkj_cholesky(&g[2 * self.d()..], self.d());
        self.log_prior_with(g, &l, log_jac)
    }

    /// [`PopulationPrior::log_prior`] given the correlation's Cholesky factor of g and its
    /// log-Jacobian ([`lkj_cholesky`]).
    fn log_prior_with(&self, g: &[f64], l: &[f64], log_jac: f64) -> f64 {
        let d = self.d();
        let mut lp = 0.0;
        for k in 0..d {
            lp += normal_lpdf(g[k], self.mu_mean[k], self.mu_sd[k]);
            let ls = g[d + k];
            let s = ls.exp();
            if !(s.is_finite() && s > 0.0) {
                return f64::NEG_INFINITY;
            }
            lp += match self.sigma_family(k) {
                SigmaPrior::HalfNormal => half_normal_lpdf(s, self.sigma_scale[k]) + ls,
                // A density on ln σ itself: no Jacobian.
                SigmaPrior::LogNormal => normal_lpdf(
                    ls,
                    (HALF_NORMAL_MEDIAN * self.sigma_scale[k]).ln(),
                    SIGMA_LOG_SD,
                ),
            };
        }
        if !log_jac.is_finite() {
            return f64::NEG_INFINITY;
        }
        lp + lkj_cholesky_lpdf_with(l, d, self.lkj_eta, self.lkj_log_norm.get(d, self.lkj_eta))
            + log_jac
    }

    /// A draw of the global vector from the prior.
    pub fn sample<R: Rng + ?Sized>(&self, rng: &mut R) -> Vec<f64> {
        let d = self.d();
        let mut g = Vec::with_capacity(self.dim());
        for k in 0..d {
            let z: f64 = StandardNormal.sample(rng);
            g.push(self.mu_mean[k] + self.mu_sd[k] * z);
        }
        for k in 0..d {
            let z: f64 = StandardNormal.sample(rng);
            g.push(match self.sigma_family(k) {
                SigmaPrior::HalfNormal => (self.sigma_scale[k] * z.abs()).max(1e-300).ln(),
                SigmaPrior::LogNormal => {
                    (HALF_NORMAL_MEDIAN * self.sigma_scale[k]).ln() + SIGMA_LOG_SD * z
                }
            });
        }
        for i in 1..d {
            for j in 0..i {
                let b = self.lkj_eta + (d as f64 - 2.0 - j as f64) / 2.0;
                let beta = Beta::new(b, b).expect("LKJ shape is positive");
                let u: f64 = beta.sample(rng);
                let z = (2.0 * u - 1.0).clamp(-1.0 + 1e-15, 1.0 - 1e-15);
                g.push(z.atanh());
            }
        }
        g
    }

    /// μ, σ, Cholesky factors of a global vector.
    pub fn unpack(&self, g: &[f64]) -> Population {
        self.unpack_with_prior(g).0
    }

    /// [`PopulationPrior::unpack`] and [`PopulationPrior::log_prior`] of g together: they
    /// share the correlation's Cholesky factor, which the sampler's moves of g would
    /// otherwise form twice.
    pub fn unpack_with_prior(&self, g: &[f64]) -> (Population, f64) {
        let d = self.d();
        let mu = g[..d].to_vec();
        let sigma: Vec<f64> = g[d..2 * d].iter().map(|v| v.exp()).collect();
        let (l_corr, log_jac) = lkj_cholesky(&g[2 * d..], d);
        let lp = self.log_prior_with(g, &l_corr, log_jac);
        let mut l_cov = l_corr.clone();
        for i in 0..d {
            for j in 0..=i {
                l_cov[i * d + j] *= sigma[i];
            }
        }
        let log_det_half = (0..d).map(|i| l_cov[i * d + i].ln()).sum();
        (
            Population {
                mu,
                sigma,
                l_corr,
                l_cov,
                log_det_half,
            },
            lp,
        )
    }
}

impl Population {
    /// log MVN(x | μ, Σ).
    pub fn log_density(&self, x: &[f64]) -> f64 {
        let d = self.mu.len();
        let ss = super::stats::lower_solve_sq_norm(&self.l_cov, d, x, &self.mu);
        -0.5 * (d as f64 * LN_2PI + ss) - self.log_det_half
    }

    /// z = (diag(σ) L)⁻¹ (x − μ).
    pub fn to_standard(&self, x: &[f64]) -> Vec<f64> {
        let d = self.mu.len();
        let r: Vec<f64> = x.iter().zip(&self.mu).map(|(a, b)| a - b).collect();
        super::stats::lower_solve(&self.l_cov, d, &r)
    }

    /// x = μ + diag(σ) L z.
    pub fn from_standard(&self, z: &[f64]) -> Vec<f64> {
        let d = self.mu.len();
        super::stats::lower_mul(&self.l_cov, d, z)
            .iter()
            .zip(&self.mu)
            .map(|(a, b)| a + b)
            .collect()
    }

    /// The correlation matrix Ω = L Lᵀ, row-major.
    pub fn correlation(&self) -> Vec<f64> {
        let d = self.mu.len();
        let mut o = vec![0.0; d * d];
        for i in 0..d {
            for j in 0..d {
                o[i * d + j] = (0..d)
                    .map(|k| self.l_corr[i * d + k] * self.l_corr[j * d + k])
                    .sum();
            }
        }
        o
    }
}

/// L (row-major d × d) from the unconstrained y, and log |∂L/∂y| over the free elements.
pub fn lkj_cholesky(y: &[f64], d: usize) -> (Vec<f64>, f64) {
    let mut l = vec![0.0; d * d];
    let mut log_jac = 0.0;
    let mut k = 0;
    if d > 0 {
        l[0] = 1.0;
    }
    for i in 1..d {
        let mut rem: f64 = 1.0; // 1 − Σ_{k<j} L_ik²
        for j in 0..i {
            let z = y[k].tanh();
            k += 1;
            log_jac += (1.0 - z * z).ln() + 0.5 * rem.ln();
            l[i * d + j] = z * rem.sqrt();
            rem -= l[i * d + j] * l[i * d + j];
        }
        l[i * d + i] = rem.max(0.0).sqrt();
    }
    (l, log_jac)
}

/// log LKJ-Cholesky density of L (over its free elements), shape η.
pub fn lkj_cholesky_lpdf(l: &[f64], d: usize, eta: f64) -> f64 {
    lkj_cholesky_lpdf_with(l, d, eta, lkj_log_normaliser(d, eta))
}

/// [`lkj_cholesky_lpdf`] with its normalising constant `log_norm` given.
fn lkj_cholesky_lpdf_with(l: &[f64], d: usize, eta: f64, log_norm: f64) -> f64 {
    // The normalising constant is the same for every L and cancels in every ratio the
    // sampler forms, but the evidence needs it: c_d(η) from Lewandowski et al. (2009),
    // eq. 16, written in terms of the Beta function.
    let mut lp = log_norm;
    for i in 1..d {
        let e = d as f64 - i as f64 + 2.0 * eta - 3.0;
        lp += e * l[i * d + i].ln();
    }
    lp
}

/// log of the LKJ normalising constant, so that the density integrates to one: the z_ij are
/// independent scaled Beta(b_j, b_j) variables on (−1, 1), each with normaliser
/// 2^{2b−1} B(b, b).
fn lkj_log_normaliser(d: usize, eta: f64) -> f64 {
    let mut c = 0.0;
    for i in 1..d {
        for j in 0..i {
            let b = eta + (d as f64 - 2.0 - j as f64) / 2.0;
            c -= (2.0 * b - 1.0) * std::f64::consts::LN_2 + ln_beta(b, b);
        }
    }
    c
}

/// ln B(a, b) = ln Γ(a) + ln Γ(b) − ln Γ(a + b).
pub fn ln_beta(a: f64, b: f64) -> f64 {
    ln_gamma(a) + ln_gamma(b) - ln_gamma(a + b)
}

/// ln Γ(x) for x > 0 (Lanczos, g = 7, n = 9; relative error ≈ 1e-15).
pub fn ln_gamma(x: f64) -> f64 {
    const G: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        let pi = std::f64::consts::PI;
        return (pi / (pi * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let mut a = G[0];
    let t = x + 7.5;
    for (i, g) in G.iter().enumerate().skip(1) {
        a += g / (x + i as f64);
    }
    0.5 * (2.0 * std::f64::consts::PI).ln() + (x + 0.5) * t.ln() - t + a.ln()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn prior(d: usize, eta: f64) -> PopulationPrior {
        PopulationPrior {
            mu_mean: vec![0.0; d],
            mu_sd: vec![1.0; d],
            sigma_scale: vec![1.0; d],
            sigma_prior: vec![],
            lkj_eta: eta,
            lkj_log_norm: Default::default(),
        }
    }

    #[test]
    fn ln_gamma_matches_known_values() {
        assert!((ln_gamma(1.0)).abs() < 1e-14);
        assert!((ln_gamma(0.5) - std::f64::consts::PI.sqrt().ln()).abs() < 1e-13);
        assert!((ln_gamma(10.0) - 362_880f64.ln()).abs() < 1e-12);
    }

    #[test]
    fn lkj_factor_has_unit_rows() {
        let y = [0.3, -1.2, 0.7, 2.0, -0.1, 0.4];
        let (l, _) = lkj_cholesky(&y, 4);
        for i in 0..4 {
            let n: f64 = (0..4).map(|k| l[i * 4 + k] * l[i * 4 + k]).sum();
            assert!((n - 1.0).abs() < 1e-12);
        }
    }

    /// The log-density of y is a proper density: for d = 2 it is the density of
    /// r = tanh(y) under LKJ(η), i.e. (r+1)/2 ~ Beta(η, η), times the Jacobian 1 − r².
    /// Integrated numerically it gives one.
    #[test]
    fn lkj_density_integrates_to_one_for_d2() {
        for eta in [1.0, 2.0, 4.5] {
            let n = 200_000;
            let (a, b) = (-12.0, 12.0);
            let h = (b - a) / n as f64;
            let mut s = 0.0;
            for k in 0..n {
                let y = a + (k as f64 + 0.5) * h;
                let (l, lj) = lkj_cholesky(&[y], 2);
                s += (lkj_cholesky_lpdf(&l, 2, eta) + lj).exp() * h;
            }
            assert!((s - 1.0).abs() < 1e-6, "eta {eta}: {s}");
        }
    }

    /// Exact draws and the analytic density agree: under LKJ(η) in d dimensions each
    /// correlation has Var(r) = 1/(2η + d − 1); and a random-walk Metropolis chain on the
    /// unconstrained density gives the same variance (checks density + Jacobian for d = 4).
    #[test]
    fn lkj_draws_and_density_agree_with_the_marginal_variance() {
        let d = 4;
        let eta = 2.0;
        let want = 1.0 / (2.0 * eta + d as f64 - 1.0);
        let p = prior(d, eta);
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let n = 40_000;
        let mut acc = vec![0.0; 6];
        for _ in 0..n {
            let g = p.sample(&mut rng);
            let o = p.unpack(&g).correlation();
            let mut k = 0;
            for i in 1..d {
                for j in 0..i {
                    acc[k] += o[i * d + j] * o[i * d + j];
                    k += 1;
                }
            }
        }
        for a in &acc {
            let v = a / n as f64;
            assert!((v - want).abs() < 0.01, "exact draws: {v} vs {want}");
        }
        // Metropolis on the y-density alone.
        let m = 6;
        let dens = |y: &[f64]| {
            let (l, lj) = lkj_cholesky(y, d);
            lkj_cholesky_lpdf(&l, d, eta) + lj
        };
        let mut y = vec![0.0; m];
        let mut ly = dens(&y);
        let mut sum = vec![0.0; m];
        let steps = 400_000;
        let mut cnt = 0;
        for s in 0..steps {
            let prop: Vec<f64> = y
                .iter()
                .map(|v| {
                    let z: f64 = StandardNormal.sample(&mut rng);
                    v + 0.5 * z
                })
                .collect();
            let lp = dens(&prop);
            let u: f64 = rand::RngExt::random(&mut rng);
            if u.ln() < lp - ly {
                y = prop;
                ly = lp;
            }
            if s > 10_000 && s % 5 == 0 {
                let (l, _) = lkj_cholesky(&y, d);
                let mut k = 0;
                for i in 1..d {
                    for j in 0..i {
                        let r: f64 = (0..d).map(|q| l[i * d + q] * l[j * d + q]).sum();
                        sum[k] += r * r;
                        k += 1;
                    }
                }
                cnt += 1;
            }
        }
        for s in &sum {
            let v = s / cnt as f64;
            assert!((v - want).abs() < 0.02, "metropolis: {v} vs {want}");
        }
    }

    #[test]
    fn standard_map_round_trips_and_density_matches_mvn() {
        let p = prior(3, 2.0);
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let g = p.sample(&mut rng);
        let pop = p.unpack(&g);
        let x = [0.1, -0.4, 0.25];
        let z = pop.to_standard(&x);
        let back = pop.from_standard(&z);
        for (a, b) in back.iter().zip(&x) {
            assert!((a - b).abs() < 1e-12);
        }
        // Against an explicit covariance: Σ = diag(σ) Ω diag(σ).
        let o = pop.correlation();
        let s: Vec<f64> = (0..9)
            .map(|k| o[k] * pop.sigma[k / 3] * pop.sigma[k % 3])
            .collect();
        let (l, _) = crate::bayes::stats::cholesky_jittered(&s, 3);
        let r: Vec<f64> = x.iter().zip(&pop.mu).map(|(a, b)| a - b).collect();
        let w = crate::bayes::stats::lower_solve(&l, 3, &r);
        let want = -0.5 * (3.0 * LN_2PI + w.iter().map(|v| v * v).sum::<f64>())
            - (0..3).map(|i| l[i * 3 + i].ln()).sum::<f64>();
        assert!((pop.log_density(&x) - want).abs() < 1e-10);
        assert!(p.log_prior(&g).is_finite());
    }

    /// Both σ families: the draws' median is the half-normal's median, 0.6745 s, under
    /// either; the log-normal's ln σ has sd 1.5; and log_prior is, along ln σ, the density the
    /// draws follow (a histogram of ln σ against exp(log_prior) with the rest fixed).
    #[test]
    fn sigma_families_share_the_median_and_their_density_matches_their_draws() {
        for fam in [SigmaPrior::HalfNormal, SigmaPrior::LogNormal] {
            let mut p = prior(2, 2.0);
            p.sigma_scale = vec![0.05, 0.05];
            p.sigma_prior = vec![fam];
            assert_eq!(p.sigma_family(1), SigmaPrior::HalfNormal);
            let mut rng = ChaCha8Rng::seed_from_u64(11);
            let mut ls: Vec<f64> = (0..40_000).map(|_| p.sample(&mut rng)[2]).collect();
            ls.sort_by(f64::total_cmp);
            let med = ls[ls.len() / 2].exp();
            assert!(
                (med / (HALF_NORMAL_MEDIAN * 0.05) - 1.0).abs() < 0.03,
                "{fam:?}: {med}"
            );
            if fam == SigmaPrior::LogNormal {
                let m = ls.iter().sum::<f64>() / ls.len() as f64;
                let sd = (ls.iter().map(|v| (v - m).powi(2)).sum::<f64>() / ls.len() as f64).sqrt();
                assert!((sd - SIGMA_LOG_SD).abs() < 0.03, "{sd}");
            }
            // Density along ln σ_0 (other coordinates at a fixed point) against the draws.
            let g0 = p.sample(&mut rng);
            let dens = |v: f64| {
                let mut g = g0.clone();
                g[2] = v;
                p.log_prior(&g).exp()
            };
            let (lo, hi) = (ls[200], ls[ls.len() - 200]);
            let bins = 20;
            let w = (hi - lo) / bins as f64;
            let grid: Vec<f64> = (0..2000)
                .map(|i| lo + (i as f64 + 0.5) * (hi - lo) / 2000.0)
                .collect();
            let norm: f64 = grid.iter().map(|&v| dens(v)).sum::<f64>() * (hi - lo) / 2000.0;
            let inside = ls.iter().filter(|v| **v >= lo && **v < hi).count() as f64;
            for b in 0..bins {
                let (a, c) = (lo + b as f64 * w, lo + (b + 1) as f64 * w);
                let got = ls.iter().filter(|v| **v >= a && **v < c).count() as f64 / inside;
                let want: f64 = grid
                    .iter()
                    .filter(|v| **v >= a && **v < c)
                    .map(|&v| dens(v))
                    .sum::<f64>()
                    * (hi - lo)
                    / 2000.0
                    / norm;
                assert!(
                    (got - want).abs() < 0.006,
                    "{fam:?} bin {b}: {got} vs {want}"
                );
            }
        }
    }
}

//! Convergence diagnostics of posterior draws: rank-normalized split R-hat, bulk and tail
//! effective sample size (ESS), and the per-quantity summary written next to the draws.
//!
//! This module owns the numbers that say whether the updater's chains (SMC runs) can be
//! trusted. Every function takes the draws of one scalar quantity as `chains[c][d]` (draw `d`
//! of chain `c`, all chains the same length) and returns plain numbers; nothing here does I/O
//! or draws random numbers.
//!
//! The definitions are those of Vehtari, Gelman, Simpson, Carpenter & Bürkner (2021),
//! "Rank-normalization, folding, and localization: an improved R-hat for assessing
//! convergence of MCMC", Bayesian Analysis 16(2), exactly as ArviZ 0.23 implements them
//! (`arviz.rhat(method="rank")`, `arviz.ess(method="bulk")`, `arviz.ess(method="tail")`),
//! step for step, so that our values agree with ArviZ's to rounding:
//!
//! * split: each chain of `n` draws becomes two chains, its first `⌊n/2⌋` and its last
//!   `⌊n/2⌋` draws (the middle draw of an odd `n` is dropped); the first halves come first.
//! * rank-normalize: `z = Φ⁻¹((r − 3/8) / (N − 3/4 + 1))` with `r` the average rank (ties
//!   share the mean of their ranks) among all `N` split draws (Blom 1958).
//! * R-hat of `m` chains of `n` draws: `√((B/W + n − 1)/n)` with `B = n·var(chain means)`
//!   and `W = mean(chain variances)` (both `ddof = 1`). Rank R-hat is
//!   `max(R-hat(z(split)), R-hat(z(|split − median(split)|)))`.
//! * ESS of `m` chains of `n` draws: `m·n / τ` with `τ = −1 + 2 Σ_{t ≤ T} ρ̂_t + ρ̂_{T+1}`,
//!   `ρ̂_t = 1 − (W − mean_c acov_c(t)) / var⁺` (biased autocovariances `acov_c`, `W` the
//!   mean within-chain variance, `var⁺ = W (n−1)/n + var(chain means)`), truncated by
//!   Geyer's initial positive sequence and made monotone (Geyer 1992); `τ ≥ 1/log10(m·n)`.
//!   Bulk ESS is the ESS of the rank-normalized split draws; tail ESS is the smaller ESS of
//!   the split indicators `draw ≤ q` at the 5 % and 95 % quantiles `q` of all draws (R's type
//!   7 quantile, i.e. linear interpolation).
//!
//! Edge cases follow ArviZ 0.23: any NaN draw gives NaN for R-hat and both ESS; fewer than
//! 4 draws per chain gives NaN; R-hat needs at least 2 chains (1 chain gives NaN, although
//! split R-hat would be defined: ArviZ refuses it and so do we); draws that are all equal
//! give R-hat NaN (0/0) and ESS equal to the number of split draws. Infinite draws are not
//! special-cased: the arithmetic runs as in ArviZ. Ragged chains are a caller bug and panic.
//!
//! One deliberate difference: chains each constant but different from one another (e.g.
//! SMC runs each collapsed onto one particle) give R-hat `+∞`, where ArviZ divides by a
//! within-chain variance made of rounding error and returns a number above about 1e6 whose
//! digits are noise.
//!
//! Differences at rounding level: Φ⁻¹ is Wichura's AS241 (relative error about 1e-16) where
//! SciPy uses Cephes `ndtri` (they differ by a few ulps); sums of draws follow NumPy's
//! pairwise order, but the autocovariances come from one FFT of two chains packed as real
//! and imaginary parts and one inverse FFT of the summed power spectra, where ArviZ
//! transforms each chain. Where a ρ̂ sum lands within rounding of zero, the truncation lag
//! (and so the ESS) could differ; the ArviZ interop test at the bottom measures the
//! agreement on random draws of many kinds.

use rustfft::num_complex::Complex;
use rustfft::FftPlanner;

/// Posterior summary of one scalar quantity over all chains pooled.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Summary {
    /// Mean of all draws.
    pub mean: f64,
    /// Standard deviation of all draws (`ddof = 1`).
    pub sd: f64,
    /// 5 % quantile of all draws (linear interpolation, NumPy's default).
    pub q05: f64,
    /// Median of all draws (linear interpolation).
    pub q50: f64,
    /// 95 % quantile of all draws (linear interpolation).
    pub q95: f64,
    /// Rank-normalized split R-hat ([`rhat`]).
    pub r_hat: f64,
    /// Bulk effective sample size ([`ess_bulk`]).
    pub ess_bulk: f64,
    /// Tail effective sample size ([`ess_tail`]).
    pub ess_tail: f64,
}

/// Rank-normalized split R-hat: the larger of the bulk and the folded (tail) R-hat.
/// Identical definition to `arviz.rhat(method="rank")` (ArviZ 0.23). NaN with fewer than 2
/// chains, fewer than 4 draws per chain, any NaN draw, or all draws equal.
pub fn rhat(chains: &[Vec<f64>]) -> f64 {
    let Some(x) = Chains::checked(chains, 2) else {
        return f64::NAN;
    };
    let split = x.split();
    let z = z_scale(&split.data);
    rank_rhat(&split, z)
}

/// Bulk effective sample size: ESS of the rank-normalized split draws. Identical definition
/// to `arviz.ess(method="bulk")` (ArviZ 0.23). NaN with fewer than 4 draws per chain or any
/// NaN draw; the number of split draws when all draws are equal.
pub fn ess_bulk(chains: &[Vec<f64>]) -> f64 {
    let Some(x) = Chains::checked(chains, 1) else {
        return f64::NAN;
    };
    let split = x.split();
    ess_plain(&split.with_data(z_scale(&split.data)))
}

/// Tail effective sample size: the smaller ESS of the split indicators `draw ≤ q` at the
/// 5 % and 95 % quantiles of all draws. Identical definition to `arviz.ess(method="tail")`
/// (ArviZ 0.23). NaN with fewer than 4 draws per chain or any NaN draw.
pub fn ess_tail(chains: &[Vec<f64>]) -> f64 {
    let Some(x) = Chains::checked(chains, 1) else {
        return f64::NAN;
    };
    let mut sorted = x.data.clone();
    sorted.sort_unstable_by(f64::total_cmp);
    tail_ess(&x, &sorted)
}

/// Mean, standard deviation, 5/50/95 % quantiles of all draws pooled, with [`rhat`],
/// [`ess_bulk`] and [`ess_tail`] (same values as those functions; the sorting and ranking
/// are shared). With no draws every field is NaN; a NaN draw makes every field NaN
/// (NumPy's behaviour for mean, sd and quantiles).
pub fn summarize(chains: &[Vec<f64>]) -> Summary {
    let pooled: Vec<f64> = chains.iter().flatten().copied().collect();
    let n = pooled.len();
    if n == 0 || pooled.iter().any(|v| v.is_nan()) {
        // Every statistic is NaN (`Chains::checked` would still panic on ragged chains).
        let _ = Chains::checked(chains, 1);
        return Summary {
            mean: f64::NAN,
            sd: f64::NAN,
            q05: f64::NAN,
            q50: f64::NAN,
            q95: f64::NAN,
            r_hat: f64::NAN,
            ess_bulk: f64::NAN,
            ess_tail: f64::NAN,
        };
    }
    let mean = mean(&pooled);
    let sd = var_ddof1(&pooled).sqrt();
    let mut sorted = pooled;
    sorted.sort_unstable_by(f64::total_cmp);
    let q = |p| quantile_linear(&sorted, p);
    let (r_hat, ess_bulk, ess_tail) = match Chains::checked(chains, 1) {
        None => (f64::NAN, f64::NAN, f64::NAN),
        Some(x) => {
            let split = x.split();
            let z = z_scale(&split.data);
            let ess_bulk = ess_plain(&split.with_data(z.clone()));
            let r_hat = if x.n_chain >= 2 {
                rank_rhat(&split, z)
            } else {
                f64::NAN
            };
            (r_hat, ess_bulk, tail_ess(&x, &sorted))
        }
    };
    Summary {
        mean,
        sd,
        q05: q(0.05),
        q50: q(0.5),
        q95: q(0.95),
        r_hat,
        ess_bulk,
        ess_tail,
    }
}

/// ArviZ's `_rhat_rank` on split chains `split` with rank-normalized values `z`.
fn rank_rhat(split: &Chains, z: Vec<f64>) -> f64 {
    let bulk = rhat_plain(&split.with_data(z));
    let med = median(&split.data);
    let folded: Vec<f64> = split.data.iter().map(|v| (v - med).abs()).collect();
    let tail = rhat_plain(&split.with_data(z_scale(&folded)));
    // Python's `max(bulk, tail)`: `tail` only if it compares greater (so a NaN bulk stays).
    if tail > bulk {
        tail
    } else {
        bulk
    }
}

/// ArviZ's `_ess_tail` given the (unsplit) chains and all their draws sorted.
fn tail_ess(x: &Chains, sorted: &[f64]) -> f64 {
    let ess_at = |prob: f64| {
        let q = quantile_type7_mquantiles(sorted, prob);
        let indicator: Vec<f64> = x
            .data
            .iter()
            .map(|&v| f64::from(u8::from(v <= q)))
            .collect();
        ess_plain(&x.with_data(indicator).split())
    };
    let (low, high) = (ess_at(0.05), ess_at(0.95));
    // Python's `min(low, high)`.
    if high < low {
        high
    } else {
        low
    }
}

// ---------------------------------------------------------------------------------------------
// Draws as one row-major block

/// `n_chain` chains of `n_draw` draws, chain `c` at `data[c * n_draw..(c + 1) * n_draw]`.
struct Chains {
    n_chain: usize,
    n_draw: usize,
    data: Vec<f64>,
}

impl Chains {
    /// The draws as one block, or `None` where ArviZ's validity check fails (fewer than
    /// `min_chains` chains, fewer than 4 draws, or a NaN). Panics on ragged chains.
    fn checked(chains: &[Vec<f64>], min_chains: usize) -> Option<Chains> {
        let n_draw = chains.first().map_or(0, Vec::len);
        for (c, chain) in chains.iter().enumerate() {
            assert_eq!(
                chain.len(),
                n_draw,
                "diagnostics: chain {c} has {} draws, chain 0 has {n_draw}; all chains must be \
                 the same length",
                chain.len()
            );
        }
        if chains.len() < min_chains.max(1) || n_draw < 4 {
            return None;
        }
        if chains.iter().flatten().any(|v| v.is_nan()) {
            return None;
        }
        Some(Chains {
            n_chain: chains.len(),
            n_draw,
            data: chains.concat(),
        })
    }

    fn chain(&self, c: usize) -> &[f64] {
        &self.data[c * self.n_draw..(c + 1) * self.n_draw]
    }

    fn with_data(&self, data: Vec<f64>) -> Chains {
        debug_assert_eq!(data.len(), self.data.len());
        Chains {
            n_chain: self.n_chain,
            n_draw: self.n_draw,
            data,
        }
    }

    /// ArviZ's `_split_chains`: first halves of all chains, then last halves.
    fn split(&self) -> Chains {
        let half = self.n_draw / 2;
        let mut data = Vec::with_capacity(2 * self.n_chain * half);
        for c in 0..self.n_chain {
            data.extend_from_slice(&self.chain(c)[..half]);
        }
        for c in 0..self.n_chain {
            data.extend_from_slice(&self.chain(c)[self.n_draw - half..]);
        }
        Chains {
            n_chain: 2 * self.n_chain,
            n_draw: half,
            data,
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Building blocks (ArviZ 0.23 `arviz/stats/diagnostics.py`)

/// ArviZ's `_rhat`: classic R-hat of the chains as given (no split, no ranks).
///
/// One deliberate difference: when every chain is constant (within-chain variance exactly
/// zero) but the chains differ, this returns `+∞` where ArviZ divides by a variance made of
/// rounding error and returns some number above about 1e6 whose digits are noise.
fn rhat_plain(x: &Chains) -> f64 {
    let n = x.n_draw as f64;
    let all_chains_constant =
        (0..x.n_chain).all(|c| x.chain(c).iter().all(|&v| v == x.chain(c)[0]));
    if all_chains_constant {
        let first = x.data[0];
        return if (0..x.n_chain).all(|c| x.chain(c)[0] == first) {
            f64::NAN
        } else {
            f64::INFINITY
        };
    }
    let means: Vec<f64> = (0..x.n_chain).map(|c| mean(x.chain(c))).collect();
    let within = mean(
        &(0..x.n_chain)
            .map(|c| var_ddof1(x.chain(c)))
            .collect::<Vec<_>>(),
    );
    let between = n * var_ddof1(&means);
    ((between / within + n - 1.0) / n).sqrt()
}

/// ArviZ's `_ess`: ESS of the chains as given, Geyer's initial monotone sequence.
fn ess_plain(x: &Chains) -> f64 {
    if x.data.iter().any(|v| v.is_nan()) {
        return f64::NAN;
    }
    let (lo, hi) = x
        .data
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| {
            (lo.min(v), hi.max(v))
        });
    // `np.finfo(float).resolution`
    if hi - lo < 1e-15 {
        return x.data.len() as f64;
    }
    let (m, n) = (x.n_chain, x.n_draw);
    let nf = n as f64;
    let acov = mean_autocovariance(x);
    let means: Vec<f64> = (0..m).map(|c| mean(x.chain(c))).collect();
    let mean_var = acov[0] * nf / (nf - 1.0);
    let mut var_plus = mean_var * (nf - 1.0) / nf;
    if m > 1 {
        var_plus += var_ddof1(&means);
    }
    let rho = |t: usize| 1.0 - (mean_var - acov[t]) / var_plus;

    let mut rho_hat = vec![0.0; n];
    let mut rho_even = 1.0;
    rho_hat[0] = rho_even;
    let mut rho_odd = rho(1);
    rho_hat[1] = rho_odd;

    // Geyer's initial positive sequence.
    let mut t = 1usize;
    while t + 3 < n && rho_even + rho_odd > 0.0 {
        rho_even = rho(t + 1);
        rho_odd = rho(t + 2);
        if rho_even + rho_odd >= 0.0 {
            rho_hat[t + 1] = rho_even;
            rho_hat[t + 2] = rho_odd;
        }
        t += 2;
    }
    // `max_t = t - 2` may be -1; index with `max_t + 1 = t - 1 >= 0`.
    let max_t_plus_1 = t - 1;
    if rho_even > 0.0 {
        rho_hat[max_t_plus_1] = rho_even;
    }
    // Geyer's initial monotone sequence.
    let mut t = 1usize;
    while t + 3 <= max_t_plus_1 {
        if rho_hat[t + 1] + rho_hat[t + 2] > rho_hat[t - 1] + rho_hat[t] {
            rho_hat[t + 1] = (rho_hat[t - 1] + rho_hat[t]) / 2.0;
            rho_hat[t + 2] = rho_hat[t + 1];
        }
        t += 2;
    }
    let size = (m * n) as f64;
    let tau = -1.0 + 2.0 * rho_hat[..max_t_plus_1].iter().sum::<f64>() + rho_hat[max_t_plus_1];
    let floor = 1.0 / size.log10();
    // Python's `max(tau, floor)`.
    let tau = if floor > tau { floor } else { tau };
    if rho_hat.iter().any(|v| v.is_nan()) {
        return f64::NAN;
    }
    size / tau
}

/// Mean over chains of each chain's biased autocovariance (`acov_c(t) = Σ_d (x_d − x̄)(x_{d+t}
/// − x̄) / n`) for lags `0..n`, via FFT with zero padding to a 5-smooth length `≥ 2n`.
///
/// Written here rather than taken from a crate: no maintained crate computes multi-chain
/// autocovariances, and packing two real chains into one complex FFT halves the work.
/// `|X_k|² + |Y_k|² = (|Z_k|² + |Z_{L−k}|²) / 2` for `z = x + i·y`.
fn mean_autocovariance(x: &Chains) -> Vec<f64> {
    let n = x.n_draw;
    let len = next_5_smooth(2 * n);
    let mut planner = FftPlanner::<f64>::new();
    let forward = planner.plan_fft_forward(len);
    let inverse = planner.plan_fft_inverse(len);
    let mut power = vec![0.0f64; len];
    let mut buf = vec![Complex::new(0.0, 0.0); len];
    let mut c = 0;
    while c < x.n_chain {
        let re = x.chain(c);
        let mre = mean(re);
        buf.iter_mut().for_each(|z| *z = Complex::new(0.0, 0.0));
        for (z, v) in buf.iter_mut().zip(re) {
            z.re = v - mre;
        }
        if c + 1 < x.n_chain {
            let im = x.chain(c + 1);
            let mim = mean(im);
            for (z, v) in buf.iter_mut().zip(im) {
                z.im = v - mim;
            }
        }
        forward.process(&mut buf);
        for (k, p) in power.iter_mut().enumerate() {
            let a = buf[k].norm_sqr();
            let b = buf[(len - k) % len].norm_sqr();
            *p += 0.5 * (a + b);
        }
        c += 2;
    }
    for (z, p) in buf.iter_mut().zip(&power) {
        *z = Complex::new(*p, 0.0);
    }
    inverse.process(&mut buf);
    let scale = 1.0 / (len as f64 * n as f64 * x.n_chain as f64);
    buf[..n].iter().map(|z| z.re * scale).collect()
}

/// Smallest `2^a 3^b 5^c ≥ target` (SciPy's `next_fast_len`; the length does not change the
/// result, only the speed).
fn next_5_smooth(target: usize) -> usize {
    let mut best = usize::MAX;
    let mut p5 = 1usize;
    while p5 < 2 * target.max(1) {
        let mut p35 = p5;
        while p35 < 2 * target.max(1) {
            let mut p = p35;
            while p < target {
                p *= 2;
            }
            best = best.min(p);
            p35 *= 3;
        }
        p5 *= 5;
    }
    best
}

/// ArviZ's `_z_scale`: average ranks (ties share their mean rank), Blom's back-transform
/// `(r − 3/8) / (N − 3/4 + 1)` and the standard normal quantile. No NaN in `values`.
fn z_scale(values: &[f64]) -> Vec<f64> {
    let n = values.len();
    let mut order: Vec<(f64, usize)> = values.iter().copied().zip(0..).collect();
    order.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
    let denom = (n as f64 - 2.0 * 0.375) + 1.0;
    let mut z = vec![0.0; n];
    let mut start = 0;
    while start < n {
        let mut end = start + 1;
        while end < n && order[end].0 == order[start].0 {
            end += 1;
        }
        // 1-based ranks start+1..=end share their mean.
        let rank = (start + 1 + end) as f64 / 2.0;
        let zi = normal_quantile((rank - 0.375) / denom);
        for &(_, i) in &order[start..end] {
            z[i] = zi;
        }
        start = end;
    }
    z
}

/// `np.median` of values without NaN.
fn median(values: &[f64]) -> f64 {
    let mut s = values.to_vec();
    let n = s.len();
    let (left, mid, _) = s.select_nth_unstable_by(n / 2, f64::total_cmp);
    let mid = *mid;
    if n % 2 == 1 {
        mid
    } else {
        let below = left.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        (below + mid) / 2.0
    }
}

/// SciPy's `mquantiles(alphap=1, betap=1)` (ArviZ's quantile for the tail ESS) on sorted
/// values: `(1 − γ) x[k−1] + γ x[k]`, `k = ⌊clip(n p + 1 − p, 1, n − 1)⌋`. The exact
/// arithmetic matters: tied draws must fall on the same side of `q` as in ArviZ.
fn quantile_type7_mquantiles(sorted: &[f64], p: f64) -> f64 {
    let n = sorted.len();
    if n == 1 {
        return sorted[0];
    }
    // `alphap + p (1 − alphap − betap)` with alphap = betap = 1 (exactly `1 + (−p)`).
    let m = 1.0 - p;
    let aleph = n as f64 * p + m;
    let k = aleph.clamp(1.0, (n - 1) as f64).floor();
    let gamma = (aleph - k).clamp(0.0, 1.0);
    let k = k as usize;
    (1.0 - gamma) * sorted[k - 1] + gamma * sorted[k]
}

/// NumPy's default `np.quantile` (method "linear") on sorted values, including NumPy's
/// `_lerp` (interpolate from the upper point when the weight is at least 1/2).
fn quantile_linear(sorted: &[f64], p: f64) -> f64 {
    let n = sorted.len();
    let virtual_index = (n - 1) as f64 * p;
    let lo = virtual_index.floor();
    let gamma = virtual_index - lo;
    let lo = (lo as usize).min(n - 1);
    let hi = (lo + 1).min(n - 1);
    let (a, b) = (sorted[lo], sorted[hi]);
    let diff = b - a;
    if gamma >= 0.5 {
        b - diff * (1.0 - gamma)
    } else {
        a + diff * gamma
    }
}

/// `Σ_{i<n} term(i)` in NumPy's summation order (`pairwise_sum` in NumPy's
/// `loops_utils.h`: blocks of at most 128 terms summed with 8 accumulators, halves added
/// recursively), so that means and variances round as in NumPy/ArviZ; this matters where a
/// spread is at rounding level (e.g. the standard deviation of constant draws).
fn numpy_sum(n: usize, term: &impl Fn(usize) -> f64) -> f64 {
    fn block(lo: usize, n: usize, term: &impl Fn(usize) -> f64) -> f64 {
        if n < 8 {
            (lo..lo + n).fold(0.0, |acc, i| acc + term(i))
        } else if n <= 128 {
            let mut r = [0.0; 8];
            for (j, rj) in r.iter_mut().enumerate() {
                *rj = term(lo + j);
            }
            let mut i = 8;
            while i < n - n % 8 {
                for (j, rj) in r.iter_mut().enumerate() {
                    *rj += term(lo + i + j);
                }
                i += 8;
            }
            let mut res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));
            while i < n {
                res += term(lo + i);
                i += 1;
            }
            res
        } else {
            let n2 = n / 2;
            let n2 = n2 - n2 % 8;
            block(lo, n2, term) + block(lo + n2, n - n2, term)
        }
    }
    block(0, n, term)
}

/// `np.mean`.
fn mean(v: &[f64]) -> f64 {
    numpy_sum(v.len(), &|i| v[i]) / v.len() as f64
}

/// `np.var(ddof=1)`.
fn var_ddof1(v: &[f64]) -> f64 {
    let m = mean(v);
    numpy_sum(v.len(), &|i| (v[i] - m) * (v[i] - m)) / (v.len() as f64 - 1.0)
}

/// Standard normal quantile Φ⁻¹(p), Wichura's algorithm AS241 (PPND16, Applied Statistics
/// 37(3), 1988), relative error about 1e-16. Hand-written: std has no inverse normal CDF and
/// a statistics crate for this one function is not worth the dependency; the coefficients
/// and evaluation order are those of CPython's `statistics.NormalDist.inv_cdf`. ±∞ at 0 and
/// 1, NaN outside [0, 1].
#[allow(clippy::excessive_precision)]
fn normal_quantile(p: f64) -> f64 {
    // Numerator and denominator coefficients, highest power first.
    const A: [f64; 8] = [
        2.5090809287301226727e+3,
        3.3430575583588128105e+4,
        6.7265770927008700853e+4,
        4.5921953931549871457e+4,
        1.3731693765509461125e+4,
        1.9715909503065514427e+3,
        1.3314166789178437745e+2,
        3.3871328727963666080e+0,
    ];
    const B: [f64; 8] = [
        5.2264952788528545610e+3,
        2.8729085735721942674e+4,
        3.9307895800092710610e+4,
        2.1213794301586595867e+4,
        5.3941960214247511077e+3,
        6.8718700749205790830e+2,
        4.2313330701600911252e+1,
        1.0,
    ];
    const C: [f64; 8] = [
        7.74545014278341407640e-4,
        2.27238449892691845833e-2,
        2.41780725177450611770e-1,
        1.27045825245236838258e+0,
        3.64784832476320460504e+0,
        5.76949722146069140550e+0,
        4.63033784615654529590e+0,
        1.42343711074968357734e+0,
    ];
    const D: [f64; 8] = [
        1.05075007164441684324e-9,
        5.47593808499534494600e-4,
        1.51986665636164571966e-2,
        1.48103976427480074590e-1,
        6.89767334985100004550e-1,
        1.67638483018380384940e+0,
        2.05319162663775882187e+0,
        1.0,
    ];
    const E: [f64; 8] = [
        2.01033439929228813265e-7,
        2.71155556874348757815e-5,
        1.24266094738807843860e-3,
        2.65321895265761230930e-2,
        2.96560571828504891230e-1,
        1.78482653991729133580e+0,
        5.46378491116411436990e+0,
        6.65790464350110377720e+0,
    ];
    const F: [f64; 8] = [
        2.04426310338993978564e-15,
        1.42151175831644588870e-7,
        1.84631831751005468180e-5,
        7.86869131145613259100e-4,
        1.48753612908506148525e-2,
        1.36929880922735805310e-1,
        5.99832206555887937690e-1,
        1.0,
    ];
    fn horner(c: &[f64; 8], r: f64) -> f64 {
        c[1..].iter().fold(c[0], |acc, &ci| acc * r + ci)
    }
    if p.is_nan() || !(0.0..=1.0).contains(&p) {
        return f64::NAN;
    }
    if p == 0.0 {
        return f64::NEG_INFINITY;
    }
    if p == 1.0 {
        return f64::INFINITY;
    }
    let q = p - 0.5;
    if q.abs() <= 0.425 {
        let r = 0.180625 - q * q;
        return horner(&A, r) * q / horner(&B, r);
    }
    let r = if q <= 0.0 { p } else { 1.0 - p };
    let r = (-r.ln()).sqrt();
    let x = if r <= 5.0 {
        let r = r - 1.6;
        horner(&C, r) / horner(&D, r)
    } else {
        let r = r - 5.0;
        horner(&E, r) / horner(&F, r)
    };
    if q < 0.0 {
        -x
    } else {
        x
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic draws from the crate's seeded generator.
    struct Rng(rand_chacha::ChaCha8Rng);

    impl Rng {
        fn new(seed: u64) -> Rng {
            Rng(rand::SeedableRng::seed_from_u64(seed))
        }

        fn normal(&mut self) -> f64 {
            rand_distr::Distribution::sample(&rand_distr::StandardNormal, &mut self.0)
        }

        /// `n_chain` stationary AR(1) chains `x_d = φ x_{d−1} + ε_d`.
        fn ar1(&mut self, n_chain: usize, n_draw: usize, phi: f64) -> Vec<Vec<f64>> {
            (0..n_chain)
                .map(|_| {
                    let mut x = self.normal() / (1.0 - phi * phi).sqrt();
                    (0..n_draw)
                        .map(|_| {
                            let out = x;
                            x = phi * x + self.normal();
                            out
                        })
                        .collect()
                })
                .collect()
        }
    }

    fn rel_err(got: f64, want: f64) -> f64 {
        if got == want || (got.is_nan() && want.is_nan()) {
            0.0
        } else {
            (got - want).abs() / want.abs()
        }
    }

    #[test]
    fn normal_quantile_matches_published_values() {
        // Φ⁻¹ at 0.975, 0.95, 0.5, 1e-10 (Abramowitz & Stegun table 26.5 / closed values).
        assert!(rel_err(normal_quantile(0.975), 1.959_963_984_540_054) < 1e-15);
        assert!(rel_err(normal_quantile(0.95), 1.644_853_626_951_472_2) < 1e-15);
        assert_eq!(normal_quantile(0.5), 0.0);
        assert!(rel_err(normal_quantile(1e-10), -6.361_340_902_404_056) < 1e-14);
        assert!(rel_err(-normal_quantile(0.025), normal_quantile(0.975)) < 1e-15);
        assert_eq!(normal_quantile(0.0), f64::NEG_INFINITY);
        assert!(normal_quantile(1.5).is_nan());
    }

    #[test]
    fn iid_chains_have_rhat_near_one_and_ess_near_draw_count() {
        let mut rng = Rng::new(1);
        let chains: Vec<Vec<f64>> = (0..4)
            .map(|_| (0..2000).map(|_| rng.normal()).collect())
            .collect();
        let r = rhat(&chains);
        assert!((0.995..1.01).contains(&r), "R-hat {r}");
        for ess in [ess_bulk(&chains), ess_tail(&chains)] {
            assert!((0.8 * 8000.0..1.2 * 8000.0).contains(&ess), "ESS {ess}");
        }
    }

    #[test]
    fn ar1_bulk_ess_matches_the_integrated_autocorrelation_time() {
        // For AR(1), τ = (1 + φ)/(1 − φ); the ESS of 4 × 5000 draws is 20000/τ up to sampling
        // error of order 10 % at this length.
        let mut rng = Rng::new(2);
        for phi in [0.5, 0.9] {
            let chains = rng.ar1(4, 5000, phi);
            let want = 20000.0 * (1.0 - phi) / (1.0 + phi);
            let got = ess_bulk(&chains);
            assert!(
                rel_err(got, want) < 0.2,
                "φ {phi}: ESS {got}, theory {want}"
            );
            assert!(rhat(&chains) < 1.02);
        }
    }

    #[test]
    fn shifted_chains_have_large_rhat() {
        let mut rng = Rng::new(3);
        let mut chains = rng.ar1(4, 1000, 0.3);
        chains[3].iter_mut().for_each(|v| *v += 2.0);
        assert!(rhat(&chains) > 1.2, "R-hat {}", rhat(&chains));
    }

    #[test]
    fn rank_diagnostics_are_invariant_to_monotone_transforms() {
        let mut rng = Rng::new(4);
        let chains = rng.ar1(3, 777, 0.8);
        let exp: Vec<Vec<f64>> = chains
            .iter()
            .map(|c| c.iter().map(|v| v.exp()).collect())
            .collect();
        assert_eq!(ess_bulk(&chains), ess_bulk(&exp));
        assert_eq!(ess_tail(&chains), ess_tail(&exp));
        let affine: Vec<Vec<f64>> = chains
            .iter()
            .map(|c| c.iter().map(|v| 3.0 * v - 7.0).collect())
            .collect();
        assert!((rhat(&chains) - rhat(&affine)).abs() < 1e-12);
    }

    #[test]
    fn edge_cases_follow_arviz() {
        let constant = vec![vec![2.5; 50]; 4];
        assert!(rhat(&constant).is_nan());
        assert_eq!(ess_bulk(&constant), 200.0);
        assert_eq!(ess_tail(&constant), 200.0);
        let short = vec![vec![1.0, 2.0, 3.0]; 4];
        assert!(rhat(&short).is_nan() && ess_bulk(&short).is_nan() && ess_tail(&short).is_nan());
        let mut rng = Rng::new(5);
        let one = rng.ar1(1, 301, 0.5);
        assert!(rhat(&one).is_nan());
        assert!(ess_bulk(&one).is_finite() && ess_tail(&one).is_finite());
        let mut with_nan = rng.ar1(2, 100, 0.5);
        with_nan[1][57] = f64::NAN;
        let s = summarize(&with_nan);
        assert!(s.mean.is_nan() && s.q50.is_nan() && s.r_hat.is_nan() && s.ess_bulk.is_nan());
        assert!(summarize(&[]).ess_tail.is_nan());
    }

    #[test]
    #[should_panic(expected = "all chains must be the same length")]
    fn ragged_chains_panic() {
        rhat(&[vec![0.0; 10], vec![0.0; 9]]);
    }

    #[test]
    fn summary_moments_and_quantiles() {
        let s = summarize(&[vec![4.0, 1.0], vec![3.0, 2.0]]);
        assert_eq!(s.mean, 2.5);
        assert!(rel_err(s.sd, (5.0f64 / 3.0).sqrt()) < 1e-15);
        // NumPy linear: index (n − 1) p = 0.15, 1.5, 2.85.
        assert!(rel_err(s.q05, 1.15) < 1e-15);
        assert_eq!(s.q50, 2.5);
        assert!(rel_err(s.q95, 3.85) < 1e-15);
    }

    #[test]
    fn next_5_smooth_lengths() {
        assert_eq!(next_5_smooth(1), 1);
        assert_eq!(next_5_smooth(7), 8);
        assert_eq!(next_5_smooth(4001), 4050);
        assert_eq!(next_5_smooth(4096), 4096);
    }

    // -----------------------------------------------------------------------------------------
    // Interop with ArviZ: tests/interop/arviz_write_fixtures.py draws random chains of many
    // kinds and prints ArviZ's R-hat / ESS and NumPy's moments and quantiles for them.

    fn fixture() -> Option<serde_json::Value> {
        let script = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/interop/arviz_write_fixtures.py");
        let mut args = vec![script.to_string_lossy().into_owned()];
        if let Ok(extra) = std::env::var("HBMU_ARVIZ_FIXTURE_ARGS") {
            args.extend(extra.split_whitespace().map(String::from));
        }
        let out = std::process::Command::new("python3").args(&args).output();
        match out {
            Ok(o) if o.status.success() => Some(serde_json::from_slice(&o.stdout).unwrap()),
            other => {
                if std::env::var("HBMU_REQUIRE_INTEROP").as_deref() == Ok("1") {
                    panic!(
                        "arviz_write_fixtures.py failed (python3 with arviz, numpy, scipy is required): {other:?}"
                    );
                }
                eprintln!("NOTICE: ArviZ interop test skipped: python3 with arviz not available");
                None
            }
        }
    }

    /// A number of the fixture: the bit pattern of an IEEE 754 double.
    fn num(v: &serde_json::Value) -> f64 {
        f64::from_bits(v.as_u64().expect("fixture numbers are u64 bit patterns"))
    }

    #[test]
    fn agrees_with_arviz_on_random_draws() {
        let Some(fix) = fixture() else { return };
        for pair in fix["normal_quantile"].as_array().unwrap() {
            let (p, want) = (num(&pair[0]), num(&pair[1]));
            let got = normal_quantile(p);
            assert!(rel_err(got, want) < 1e-14, "Φ⁻¹({p}) = {got}, SciPy {want}");
        }
        let cases = fix["cases"].as_array().unwrap();
        let (mut worst_rhat, mut worst_ess, mut worst_moment) = (0.0f64, 0.0f64, 0.0f64);
        for case in cases {
            let name = case["name"].as_str().unwrap();
            let chains: Vec<Vec<f64>> = case["chains"]
                .as_array()
                .unwrap()
                .iter()
                .map(|c| c.as_array().unwrap().iter().map(num).collect())
                .collect();
            let s = summarize(&chains);
            let want_rhat = num(&case["r_hat"]);
            let d_rhat = if s.r_hat.is_nan() && want_rhat.is_nan() {
                0.0
            } else if (want_rhat > 1e6 || want_rhat.is_nan()) && s.r_hat > 1e6 {
                // Chains constant within, different between: the within-chain variance is 0
                // and R-hat is +∞, which we return (see `rhat_plain`). ArviZ 0.23 gives a huge
                // number (a rounding-noise variance) without numba and NaN with numba
                // installed (checked on this fixture): neither says "converged".
                0.0
            } else {
                (s.r_hat - want_rhat).abs()
            };
            assert!(
                d_rhat <= 1e-9,
                "{name}: R-hat {} vs ArviZ {want_rhat}",
                s.r_hat
            );
            worst_rhat = worst_rhat.max(d_rhat);
            for (what, got, key) in [
                ("ess_bulk", s.ess_bulk, "ess_bulk"),
                ("ess_tail", s.ess_tail, "ess_tail"),
            ] {
                let want = num(&case[key]);
                let e = rel_err(got, want);
                assert!(e <= 1e-6, "{name}: {what} {got} vs ArviZ {want}");
                worst_ess = worst_ess.max(e);
            }
            let scale = num(&case["sd"]).abs();
            for (what, got) in [
                ("mean", s.mean),
                ("sd", s.sd),
                ("q05", s.q05),
                ("q50", s.q50),
                ("q95", s.q95),
            ] {
                let want = num(&case[what]);
                // Relative to the spread: a mean near zero differs by summation order only.
                let e = if got == want || (got.is_nan() && want.is_nan()) {
                    0.0
                } else {
                    (got - want).abs() / want.abs().max(scale)
                };
                assert!(e <= 1e-12, "{name}: {what} {got} vs NumPy {want}");
                worst_moment = worst_moment.max(e);
            }
        }
        eprintln!(
            "ArviZ {}: {} cases, worst |ΔR-hat| {worst_rhat:.3e}, worst relative ΔESS {worst_ess:.3e}, \
             worst relative Δ(mean, sd, quantiles) {worst_moment:.3e}",
            fix["arviz_version"],
            cases.len()
        );
    }
}

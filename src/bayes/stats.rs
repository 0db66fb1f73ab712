//! Small numerical helpers of the sampler: log-sum-exp, normal log-densities, the effective
//! sample size of log weights, the median. All weights stay in log space.

/// ln(2π).
pub const LN_2PI: f64 = 1.837_877_066_409_345_5;

/// log Σ exp(aᵢ), stable; −∞ for an empty slice or all −∞.
pub fn log_sum_exp(a: &[f64]) -> f64 {
    let m = a.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    if !m.is_finite() {
        return m;
    }
    m + a.iter().map(|v| (v - m).exp()).sum::<f64>().ln()
}

/// log of the mean of exp(aᵢ).
pub fn log_mean_exp(a: &[f64]) -> f64 {
    log_sum_exp(a) - (a.len() as f64).ln()
}

/// The median of `x`: the middle value, the mean of the two middle ones for an even count,
/// NaN when empty.
pub fn median(x: &[f64]) -> f64 {
    let mut v = x.to_vec();
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n == 0 {
        return f64::NAN;
    }
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Normalised weights from log weights.
pub fn normalize(logw: &[f64]) -> Vec<f64> {
    let l = log_sum_exp(logw);
    logw.iter().map(|v| (v - l).exp()).collect()
}

/// Effective sample size (Σw)²/Σw² of log weights, in particles.
pub fn ess(logw: &[f64]) -> f64 {
    let w = normalize(logw);
    1.0 / w.iter().map(|v| v * v).sum::<f64>()
}

/// log N(x | mean, sd²).
pub fn normal_lpdf(x: f64, mean: f64, sd: f64) -> f64 {
    let z = (x - mean) / sd;
    -0.5 * (LN_2PI + z * z) - sd.ln()
}

/// log of the half-normal density with scale `s` at `x ≥ 0` (−∞ below 0).
pub fn half_normal_lpdf(x: f64, s: f64) -> f64 {
    if x < 0.0 {
        return f64::NEG_INFINITY;
    }
    std::f64::consts::LN_2 + normal_lpdf(x, 0.0, s)
}

/// Lower Cholesky factor of a symmetric positive (semi-)definite d × d matrix (row-major),
/// with a diagonal jitter added where a pivot is not positive. Returns the factor and the
/// jitter used (0 for a positive-definite input). A matrix with a non-finite entry, or one
/// that no jitter up to 1e3 × its largest diagonal makes positive, has no factor: the result is
/// then a factor of NaNs with an infinite jitter, so every density built on it is NaN (which
/// the sampler treats as −∞, and `GaussianReference::degeneracy` reports) instead of this
/// looping for ever, as it did on a NaN covariance.
pub fn cholesky_jittered(a: &[f64], d: usize) -> (Vec<f64>, f64) {
    let no_factor = || (vec![f64::NAN; d * d], f64::INFINITY);
    if a[..d * d].iter().any(|v| !v.is_finite()) {
        return no_factor();
    }
    let scale = (0..d)
        .map(|i| a[i * d + i].abs())
        .fold(0.0, f64::max)
        .max(1e-300);
    let mut jitter = 0.0;
    while jitter <= 1e3 * scale {
        if let Some(l) = cholesky(a, d, jitter) {
            return (l, jitter);
        }
        jitter = if jitter == 0.0 {
            1e-12 * scale
        } else {
            jitter * 10.0
        };
    }
    no_factor()
}

fn cholesky(a: &[f64], d: usize, jitter: f64) -> Option<Vec<f64>> {
    let mut l = vec![0.0; d * d];
    for i in 0..d {
        for j in 0..=i {
            let mut s = a[i * d + j] + if i == j { jitter } else { 0.0 };
            for k in 0..j {
                s -= l[i * d + k] * l[j * d + k];
            }
            if i == j {
                if s.is_nan() || s <= 0.0 || !s.is_finite() {
                    return None;
                }
                l[i * d + i] = s.sqrt();
            } else {
                l[i * d + j] = s / l[j * d + j];
            }
        }
    }
    Some(l)
}

/// Mean and covariance (divided by n, the maximum-likelihood form) of equal-length vectors
/// (at least one).
pub fn mean_and_covariance<'a>(
    vs: impl Iterator<Item = &'a [f64]> + Clone,
) -> (Vec<f64>, Vec<f64>) {
    let n = vs.clone().count().max(1) as f64;
    let d = vs.clone().next().map_or(0, <[f64]>::len);
    let mut mean = vec![0.0; d];
    for v in vs.clone() {
        mean.iter_mut().zip(v).for_each(|(m, x)| *m += x / n);
    }
    let mut cov = vec![0.0; d * d];
    for v in vs {
        for i in 0..d {
            for j in 0..d {
                cov[i * d + j] += (v[i] - mean[i]) * (v[j] - mean[j]) / n;
            }
        }
    }
    (mean, cov)
}

/// y = L x for a lower-triangular row-major L.
pub fn lower_mul(l: &[f64], d: usize, x: &[f64]) -> Vec<f64> {
    (0..d)
        .map(|i| (0..=i).map(|k| l[i * d + k] * x[k]).sum())
        .collect()
}

/// ‖L⁻¹ (x − m)‖² for lower-triangular L (row-major d × d), without allocating for
/// d ≤ 32: the squared Mahalanobis distance of the sampler's hot path (population and
/// reference densities, evaluated for every unit at every move of the global vector).
pub fn lower_solve_sq_norm(l: &[f64], d: usize, x: &[f64], m: &[f64]) -> f64 {
    let mut stack = [0.0; 32];
    let mut heap = Vec::new();
    let z: &mut [f64] = if d <= stack.len() {
        &mut stack[..d]
    } else {
        heap.resize(d, 0.0);
        &mut heap
    };
    for ((zi, a), b) in z.iter_mut().zip(x).zip(m) {
        *zi = a - b;
    }
    lower_solve_in_place(l, d, z);
    z.iter().map(|v| v * v).sum()
}

/// L⁻¹ b for lower-triangular L (row-major d × d).
pub fn lower_solve(l: &[f64], d: usize, b: &[f64]) -> Vec<f64> {
    let mut x = b[..d].to_vec();
    lower_solve_in_place(l, d, &mut x);
    x
}

/// L⁻ᵀ b for lower-triangular L (row-major d × d): back substitution with Lᵀ. With
/// [`lower_solve`] it solves (L Lᵀ) x = b.
pub fn lower_transpose_solve(l: &[f64], d: usize, b: &[f64]) -> Vec<f64> {
    let mut x = b[..d].to_vec();
    for i in (0..d).rev() {
        let s: f64 = (i + 1..d).map(|k| l[k * d + i] * x[k]).sum();
        x[i] = (x[i] - s) / l[i * d + i];
    }
    x
}

/// Forward substitution in place: b (length d) becomes L⁻¹ b.
pub(crate) fn lower_solve_in_place(l: &[f64], d: usize, x: &mut [f64]) {
    for i in 0..d {
        let s: f64 = (0..i).map(|k| l[i * d + k] * x[k]).sum();
        x[i] = (x[i] - s) / l[i * d + i];
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn log_sum_exp_is_stable() {
        let a = [1000.0, 1000.0];
        assert!((log_sum_exp(&a) - (1000.0 + 2f64.ln())).abs() < 1e-12);
        assert_eq!(log_sum_exp(&[f64::NEG_INFINITY; 3]), f64::NEG_INFINITY);
        assert!((ess(&[0.0; 10]) - 10.0).abs() < 1e-12);
    }

    #[test]
    fn median_of_odd_even_and_empty() {
        assert_eq!(median(&[3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&[4.0, 1.0, 3.0, 2.0]), 2.5);
        assert!(median(&[]).is_nan());
    }

    #[test]
    fn cholesky_reproduces_the_matrix() {
        let a = [4.0, 2.0, 0.4, 2.0, 3.0, 0.5, 0.4, 0.5, 2.0];
        let (l, j) = cholesky_jittered(&a, 3);
        assert_eq!(j, 0.0);
        for i in 0..3 {
            for k in 0..3 {
                let v: f64 = (0..3).map(|m| l[i * 3 + m] * l[k * 3 + m]).sum();
                assert!((v - a[i * 3 + k]).abs() < 1e-12);
            }
        }
        let b = [1.0, -2.0, 0.5];
        let x = lower_solve(&l, 3, &b);
        let back = lower_mul(&l, 3, &x);
        for (u, v) in back.iter().zip(&b) {
            assert!((u - v).abs() < 1e-12);
        }
        // (L Lᵀ)⁻¹ b: A x = b.
        let x = lower_transpose_solve(&l, 3, &lower_solve(&l, 3, &b));
        for i in 0..3 {
            let ax: f64 = (0..3).map(|k| a[i * 3 + k] * x[k]).sum();
            assert!((ax - b[i]).abs() < 1e-12, "row {i}");
        }
        // Singular input gets a jitter, never a failure.
        let (_, j) = cholesky_jittered(&[1.0, 1.0, 1.0, 1.0], 2);
        assert!(j > 0.0);
        // A NaN input, or one no jitter up to 1e3 × its largest diagonal makes positive, has
        // no factor: NaNs, returned (it looped for ever on a NaN before).
        for bad in [[f64::NAN, 0.0, 0.0, 1.0], [0.0, 1e6, 1e6, 0.0]] {
            let (l, j) = cholesky_jittered(&bad, 2);
            assert!(j.is_infinite() && l.iter().all(|v| v.is_nan()), "{bad:?}");
        }
    }
}

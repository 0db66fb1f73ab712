//! Levenberg–Marquardt for small nonlinear least-squares problems whose residual function
//! gives its Jacobian too.

/// Σ r², the least-squares objective.
pub fn sum_sq(r: &[f64]) -> f64 {
    r.iter().map(|v| v * v).sum()
}

/// Residuals and their Jacobian at a point: `jac[k][i]` = ∂r_i/∂x_k.
pub type WithJacobian = (Vec<f64>, Vec<Vec<f64>>);

/// A search's end: the sum of squares, the point and the residuals there.
pub type Fitted = (f64, Vec<f64>, Vec<f64>);

/// Levenberg–Marquardt on the residuals and Jacobian `eval` from `x0`, kept inside ±`spans`:
/// the final sum of squares, point and residuals. It stops when a step, accepted or only
/// proposed, moves no coordinate by more than `STEP_TOL` (1e-4: in the ln units of the
/// centre fits a 0.01 % change, far below the ROM box it centres) or changes no residual by
/// more than `resid_tol`, measured for an accepted step and predicted by the Jacobian for a
/// proposed one (a search along a ridge of the misfit, two parameters trading off, otherwise
/// spends dozens of solves on steps the residuals do not see).
pub fn levenberg_marquardt(
    eval: &(dyn Fn(&[f64]) -> anyhow::Result<WithJacobian> + Sync),
    x0: Vec<f64>,
    spans: &[f64],
    resid_tol: f64,
) -> anyhow::Result<Fitted> {
    const STEP_TOL: f64 = 1e-4;
    let d = x0.len();
    let mut x = x0;
    let (mut r0, mut jac) = eval(&x)?;
    let mut c0 = sum_sq(&r0);
    let mut mu = 1e-3;
    for _ in 0..12 {
        let mut accepted = None;
        for _ in 0..8 {
            // (JᵀJ + μ diag(JᵀJ)) δ = −Jᵀ r, d × d by Gaussian elimination.
            let mut a = vec![vec![0.0; d + 1]; d];
            for k in 0..d {
                for l in 0..d {
                    a[k][l] = jac[k].iter().zip(&jac[l]).map(|(u, v)| u * v).sum();
                }
                a[k][k] *= 1.0 + mu;
                a[k][k] += 1e-12;
                a[k][d] = -jac[k].iter().zip(&r0).map(|(u, v)| u * v).sum::<f64>();
            }
            for c in 0..d {
                let piv = (c..d)
                    .max_by(|&i, &j| a[i][c].abs().total_cmp(&a[j][c].abs()))
                    .unwrap_or(c);
                a.swap(c, piv);
                for i in c + 1..d {
                    let f = a[i][c] / a[c][c];
                    let (top, rest) = a.split_at_mut(i);
                    for (x, y) in rest[0][c..].iter_mut().zip(&top[c][c..]) {
                        *x -= f * y;
                    }
                }
            }
            let mut delta = vec![0.0; d];
            for c in (0..d).rev() {
                let s: f64 = (c + 1..d).map(|j| a[c][j] * delta[j]).sum();
                delta[c] = (a[c][d] - s) / a[c][c];
            }
            let y: Vec<f64> = (0..d)
                .map(|k| (x[k] + delta[k]).clamp(-spans[k], spans[k]))
                .collect();
            // A trial the linearisation says is below both tolerances is not solved: at
            // the minimum, rounding rejects it and μ's growth would spend up to 8
            // evaluations (FE solves in the centre fits) on steps of 1e-10.
            let step = y
                .iter()
                .zip(&x)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            let predicted = (0..r0.len())
                .map(|i| (0..d).map(|k| jac[k][i] * (y[k] - x[k])).sum::<f64>().abs())
                .fold(0.0, f64::max);
            if step < STEP_TOL || predicted < resid_tol {
                break;
            }
            let (r, jac_y) = eval(&y)?;
            let c = sum_sq(&r);
            if c < c0 {
                mu = (mu * 0.3).max(1e-6);
                accepted = Some((y, r, c, jac_y));
                break;
            }
            mu *= 10.0;
        }
        let Some((y, r, c, jac_y)) = accepted else {
            break;
        };
        let step = y
            .iter()
            .zip(&x)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        let moved = r
            .iter()
            .zip(&r0)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        x = y;
        r0 = r;
        c0 = c;
        jac = jac_y;
        if c0 < 1e-14 || step < STEP_TOL || moved < resid_tol {
            break;
        }
    }
    Ok((c0, x, r0))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The least-squares line y ≈ a + b t by the normal equations' closed form: (a, b).
    fn line_fit(t: &[f64], y: &[f64]) -> (f64, f64) {
        let n = t.len() as f64;
        let (st, sy) = (t.iter().sum::<f64>(), y.iter().sum::<f64>());
        let stt: f64 = t.iter().map(|v| v * v).sum();
        let sty: f64 = t.iter().zip(y).map(|(a, b)| a * b).sum();
        let b = (n * sty - st * sy) / (n * stt - st * st);
        ((sy - b * st) / n, b)
    }

    /// A linear least-squares problem: the minimiser and its residual are the normal
    /// equations' closed form (y = 1.5 + 0.25 t + noise, fitted by a line).
    #[test]
    fn a_line_fit_reaches_the_normal_equations_solution() {
        let t: Vec<f64> = (0..8).map(|i| i as f64).collect();
        let noise = [0.03, -0.02, 0.01, 0.04, -0.05, 0.02, -0.01, -0.02];
        let y: Vec<f64> = t
            .iter()
            .zip(noise)
            .map(|(t, e)| 1.5 + 0.25 * t + e)
            .collect();
        let (a, b) = line_fit(&t, &y);
        let best: f64 = t.iter().zip(&y).map(|(t, y)| (a + b * t - y).powi(2)).sum();
        let eval = |x: &[f64]| -> anyhow::Result<WithJacobian> {
            let r = t.iter().zip(&y).map(|(t, y)| x[0] + x[1] * t - y).collect();
            Ok((r, vec![vec![1.0; t.len()], t.clone()]))
        };
        let (c, x, _) = levenberg_marquardt(&eval, vec![0.0, 0.0], &[10.0, 10.0], 0.0).unwrap();
        assert!(
            (x[0] - a).abs() < 1e-5 && (x[1] - b).abs() < 1e-5,
            "{x:?} vs {a} {b}"
        );
        assert!((c - best).abs() < 1e-9, "{c} vs {best}");
    }

    /// A search started at the minimiser solves once: the step it proposes there is below
    /// the tolerances, so no rejected trial is evaluated (before, rounding rejected it and μ
    /// grew through 8 more evaluations).
    #[test]
    fn a_search_at_the_minimum_evaluates_once() {
        let t: Vec<f64> = (0..8).map(|i| i as f64).collect();
        let y: Vec<f64> = t
            .iter()
            .map(|t| 0.5 - 0.1 * t + 0.01 * (t * 1.7).sin())
            .collect();
        let (a, b) = line_fit(&t, &y);
        let calls = std::sync::atomic::AtomicUsize::new(0);
        let eval = |x: &[f64]| -> anyhow::Result<WithJacobian> {
            calls.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            let r = t.iter().zip(&y).map(|(t, y)| x[0] + x[1] * t - y).collect();
            Ok((r, vec![vec![1.0; t.len()], t.clone()]))
        };
        let (_, x, _) = levenberg_marquardt(&eval, vec![a, b], &[10.0, 10.0], 1e-6).unwrap();
        assert_eq!(x, vec![a, b]);
        assert_eq!(calls.load(std::sync::atomic::Ordering::Relaxed), 1);
    }

    /// y = 2 e^{-0.7 t} (+ noise), its residuals and their Jacobian in (ln a, b).
    fn decay(noise: &[f64]) -> impl Fn(&[f64]) -> anyhow::Result<WithJacobian> + Sync {
        let t: Vec<f64> = (0..10).map(|i| 0.3 * i as f64).collect();
        let y: Vec<f64> = t
            .iter()
            .zip(noise)
            .map(|(t, e)| 2.0 * (-0.7 * t).exp() + e)
            .collect();
        move |x: &[f64]| {
            let m: Vec<f64> = t.iter().map(|t| x[0].exp() * (x[1] * t).exp()).collect();
            let r = m.iter().zip(&y).map(|(m, y)| m - y).collect();
            let jac = vec![m.clone(), m.iter().zip(&t).map(|(m, t)| m * t).collect()];
            Ok((r, jac))
        }
    }

    /// A nonlinear problem with an exact fit: y = 2 e^{-0.7 t} from a start far off, and the
    /// bounds are honoured where the minimiser lies outside them.
    #[test]
    fn an_exponential_decay_is_found_and_the_bounds_hold() {
        let eval = decay(&[0.0; 10]);
        let (c, x, _) = levenberg_marquardt(&eval, vec![0.0, 0.0], &[5.0, 5.0], 0.0).unwrap();
        assert!(
            (x[0] - 2f64.ln()).abs() < 1e-3 && (x[1] + 0.7).abs() < 1e-3,
            "{x:?}"
        );
        assert!(c < 1e-6, "{c}");
        let (_, x, _) = levenberg_marquardt(&eval, vec![0.0, 0.0], &[5.0, 0.5], 0.0).unwrap();
        assert!(x[1] >= -0.5 - 1e-12, "{x:?}");
    }

    /// The residual tolerance stops a search whose steps no longer change the residuals by
    /// that much, in fewer evaluations than the coordinate tolerance alone: on Rosenbrock's
    /// valley (r = (10 (x₁ − x₀²), 1 − x₀), minimum 0 at (1, 1)), whose curved ridge a
    /// Gauss–Newton search follows in many short steps, from (0.9, 0.7).
    #[test]
    fn the_residual_tolerance_stops_where_the_residuals_settle() {
        let calls = std::sync::atomic::AtomicUsize::new(0);
        let eval = |x: &[f64]| -> anyhow::Result<WithJacobian> {
            calls.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            let r = vec![10.0 * (x[1] - x[0] * x[0]), 1.0 - x[0]];
            Ok((r, vec![vec![-20.0 * x[0], -1.0], vec![10.0, 0.0]]))
        };
        let (c_full, x_full, _) =
            levenberg_marquardt(&eval, vec![0.9, 0.7], &[5.0, 5.0], 0.0).unwrap();
        let n_full = calls.swap(0, std::sync::atomic::Ordering::Relaxed);
        let (c_tol, _, _) = levenberg_marquardt(&eval, vec![0.9, 0.7], &[5.0, 5.0], 1e-3).unwrap();
        let n_tol = calls.load(std::sync::atomic::Ordering::Relaxed);
        assert!(
            (x_full[0] - 1.0).abs() < 1e-3 && c_full < 1e-8,
            "{x_full:?} {c_full}"
        );
        assert!(c_tol < 1e-4, "{c_tol}");
        assert!(n_tol < n_full, "{n_tol} vs {n_full}");
    }
}

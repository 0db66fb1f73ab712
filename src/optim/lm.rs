//! Levenberg–Marquardt for small nonlinear least-squares problems with a residual function
//! and finite-difference Jacobians.

/// Σ r², the least-squares objective.
pub fn sum_sq(r: &[f64]) -> f64 {
    r.iter().map(|v| v * v).sum()
}

/// Levenberg–Marquardt on the residuals `resid` from `x0`, kept inside ±`spans`: the final
/// sum of squares and point.
///
/// A residual may be expensive (a full FE eigen-solve), so a trial point's forward-difference
/// neighbours are evaluated in parallel beside the trial itself (used when the trial is
/// accepted, as most are); the values are those of a sequential search. It stops when an
/// accepted step moves no coordinate by more than `STEP_TOL` (1e-4: in the ln units of the
/// centre fits a 0.01 % change, far below the ROM box it centres).
pub fn levenberg_marquardt(
    resid: &(dyn Fn(&[f64]) -> anyhow::Result<Vec<f64>> + Sync),
    x0: Vec<f64>,
    spans: &[f64],
) -> anyhow::Result<(f64, Vec<f64>)> {
    use rayon::prelude::*;
    const STEP_TOL: f64 = 1e-4;
    let d = x0.len();
    let h = 1e-3;
    // resid at x and at x + h e_k for every k, side by side.
    let with_neighbours = |x: &[f64]| -> Vec<anyhow::Result<Vec<f64>>> {
        (0..=d)
            .into_par_iter()
            .map(|k| {
                let mut y = x.to_vec();
                if k > 0 {
                    y[k - 1] += h;
                }
                resid(&y)
            })
            .collect()
    };
    let jacobian =
        |r0: &[f64], nb: Vec<anyhow::Result<Vec<f64>>>| -> anyhow::Result<Vec<Vec<f64>>> {
            nb.into_iter()
                .map(|r| Ok(r?.iter().zip(r0).map(|(v, v0)| (v - v0) / h).collect()))
                .collect()
        };
    let mut x = x0;
    let mut evals = with_neighbours(&x).into_iter();
    let mut r0 = evals.next().expect("the point itself")?;
    let mut c0 = sum_sq(&r0);
    let mut jac = jacobian(&r0, evals.collect())?;
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
            let mut evals = with_neighbours(&y).into_iter();
            let r = evals.next().expect("the trial itself")?;
            let c = sum_sq(&r);
            if c < c0 {
                mu = (mu * 0.3).max(1e-6);
                accepted = Some((y, r, c, evals.collect::<Vec<_>>()));
                break;
            }
            mu *= 10.0;
        }
        let Some((y, r, c, neighbours)) = accepted else {
            break;
        };
        let step = y
            .iter()
            .zip(&x)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        x = y;
        r0 = r;
        c0 = c;
        if c0 < 1e-14 || step < STEP_TOL {
            break;
        }
        // A neighbour the model cannot solve ends the search at the accepted point, the best
        // one found: the search stops where the model stops being defined.
        match jacobian(&r0, neighbours) {
            Ok(j) => jac = j,
            Err(_) => break,
        }
    }
    Ok((c0, x))
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let n = t.len() as f64;
        let (st, sy) = (t.iter().sum::<f64>(), y.iter().sum::<f64>());
        let stt: f64 = t.iter().map(|v| v * v).sum();
        let sty: f64 = t.iter().zip(&y).map(|(a, b)| a * b).sum();
        let b = (n * sty - st * sy) / (n * stt - st * st);
        let a = (sy - b * st) / n;
        let best: f64 = t.iter().zip(&y).map(|(t, y)| (a + b * t - y).powi(2)).sum();
        let resid = |x: &[f64]| -> anyhow::Result<Vec<f64>> {
            Ok(t.iter().zip(&y).map(|(t, y)| x[0] + x[1] * t - y).collect())
        };
        let (c, x) = levenberg_marquardt(&resid, vec![0.0, 0.0], &[10.0, 10.0]).unwrap();
        assert!(
            (x[0] - a).abs() < 1e-5 && (x[1] - b).abs() < 1e-5,
            "{x:?} vs {a} {b}"
        );
        assert!((c - best).abs() < 1e-9, "{c} vs {best}");
    }

    /// A nonlinear problem with an exact fit: y = 2 e^{-0.7 t} from a start far off, and the
    /// bounds are honoured where the minimiser lies outside them.
    #[test]
    fn an_exponential_decay_is_found_and_the_bounds_hold() {
        let t: Vec<f64> = (0..10).map(|i| 0.3 * i as f64).collect();
        let y: Vec<f64> = t.iter().map(|t| 2.0 * (-0.7 * t).exp()).collect();
        let resid = |x: &[f64]| -> anyhow::Result<Vec<f64>> {
            Ok(t.iter()
                .zip(&y)
                .map(|(t, y)| x[0].exp() * (x[1] * t).exp() - y)
                .collect())
        };
        let (c, x) = levenberg_marquardt(&resid, vec![0.0, 0.0], &[5.0, 5.0]).unwrap();
        assert!(
            (x[0] - 2f64.ln()).abs() < 1e-3 && (x[1] + 0.7).abs() < 1e-3,
            "{x:?}"
        );
        assert!(c < 1e-6, "{c}");
        let (_, x) = levenberg_marquardt(&resid, vec![0.0, 0.0], &[5.0, 0.5]).unwrap();
        assert!(x[1] >= -0.5 - 1e-12, "{x:?}");
    }
}

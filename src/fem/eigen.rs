//! Sparse generalized symmetric eigen-solver for the lowest modes of K φ = λ M φ:
//! shift-invert Lanczos with full M-reorthogonalisation.
//!
//! With a shift σ below the lowest eigenvalue (default σ = −(2π · 100 Hz)², so that
//! K − σM is positive definite even for the free board whose K is singular), the
//! operator OP = (K − σM)⁻¹ M is self-adjoint in the M-inner product and has the
//! eigenvalues θ = 1/(λ − σ): the lowest λ become the largest, well-separated θ.
//! Lanczos builds an M-orthonormal basis Q of the Krylov space of OP and the
//! tridiagonal T = Qᵀ M OP Q; Ritz pairs (θ, Q s) of T converge when the residual
//! estimate β_k |s_k| ≤ tol · θ. Full reorthogonalisation (two Gram–Schmidt passes)
//! keeps Q orthonormal, which at the sizes here (n ≲ 10⁴, a few tens of steps) costs
//! less than the sparse solves. We write this by hand because no crate offers a sparse
//! generalized symmetric eigen-solver on top of faer's sparse Cholesky.

use faer::Mat;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::FemError;

/// Tuning knobs of the Lanczos solver.
#[derive(Clone, Debug)]
pub struct EigenOptions {
    /// Shift σ, rad²/s²; must lie below the lowest eigenvalue.
    pub shift: f64,
    /// Relative residual tolerance on θ.
    pub tol: f64,
    /// Seed of the start vector.
    pub seed: u64,
    /// Largest Krylov dimension before giving up.
    pub max_steps: usize,
}

impl Default for EigenOptions {
    fn default() -> Self {
        let w = 2.0 * std::f64::consts::PI * 100.0;
        EigenOptions {
            shift: -w * w,
            tol: 1e-10,
            seed: 0x5eed_1a2c,
            max_steps: 600,
        }
    }
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// The `nev` eigenpairs with smallest λ of the pencil (K, M), given `solve` (in place
/// x ← (K − σM)⁻¹ x for an n × 1 matrix) and `mmul` (y ← M x). Returns eigenvalues
/// ascending and M-orthonormal eigenvectors (columns), each signed so that its dot
/// product with the fixed weights [`sign_weight`] is positive.
pub fn shift_invert_lanczos(
    n: usize,
    nev: usize,
    opts: &EigenOptions,
    solve: impl Fn(&mut Mat<f64>),
    mmul: impl Fn(&[f64], &mut [f64]),
) -> Result<(Vec<f64>, Mat<f64>), FemError> {
    if nev == 0 || nev > n {
        return Err(FemError::Request(format!(
            "eigenpairs: expected 1..={n}, found {nev}"
        )));
    }
    let max_steps = opts.max_steps.min(n);
    let mut rng = ChaCha8Rng::seed_from_u64(opts.seed);
    let mut q: Vec<Vec<f64>> = Vec::new();
    let mut mq: Vec<Vec<f64>> = Vec::new();
    let mut alpha: Vec<f64> = Vec::new();
    let mut beta: Vec<f64> = Vec::new();
    let mut buf = Mat::<f64>::zeros(n, 1);
    let mut mw = vec![0.0; n];

    // Start vector: random, M-normalised.
    let new_start = |rng: &mut ChaCha8Rng, q: &[Vec<f64>], mq: &[Vec<f64>]| -> Option<Vec<f64>> {
        let mut v: Vec<f64> = (0..n).map(|_| rng.random::<f64>() - 0.5).collect();
        for _ in 0..2 {
            for (qi, mqi) in q.iter().zip(mq) {
                let c = dot(mqi, &v);
                v.iter_mut().zip(qi).for_each(|(x, y)| *x -= c * y);
            }
        }
        Some(v)
    };
    let mut v = new_start(&mut rng, &q, &mq).unwrap_or_default();
    let mut mv = vec![0.0; n];
    mmul(&v, &mut mv);
    let nrm = dot(&v, &mv).sqrt();
    if !(nrm > 0.0) {
        return Err(FemError::Eigen(
            "start vector has zero M-norm: M is singular".into(),
        ));
    }
    v.iter_mut().for_each(|x| *x /= nrm);
    mv.iter_mut().for_each(|x| *x /= nrm);

    let check_every = 5;
    let min_steps = (2 * nev + 10).min(max_steps);
    for j in 0..max_steps {
        q.push(v.clone());
        mq.push(mv.clone());
        // w = OP q_j = (K − σM)⁻¹ M q_j.
        for i in 0..n {
            buf[(i, 0)] = mv[i];
        }
        solve(&mut buf);
        let mut w: Vec<f64> = (0..n).map(|i| buf[(i, 0)]).collect();
        let a = dot(&mv, &w);
        alpha.push(a);
        // Full reorthogonalisation, two passes (includes the three-term recurrence).
        for _ in 0..2 {
            for (qi, mqi) in q.iter().zip(&mq) {
                let c = dot(mqi, &w);
                w.iter_mut().zip(qi).for_each(|(x, y)| *x -= c * y);
            }
        }
        mmul(&w, &mut mw);
        let b = dot(&w, &mw).max(0.0).sqrt();
        let steps = j + 1;
        let done = steps == max_steps;
        if steps >= min_steps && (steps % check_every == 0 || done) {
            if let Some(res) = ritz(&q, &alpha, &beta, b, nev, opts, n)? {
                return Ok(res);
            }
        }
        if done {
            break;
        }
        let scale = alpha.iter().fold(0.0f64, |m, x| m.max(x.abs()));
        if b <= 1e-13 * scale {
            // Invariant subspace found: continue with a fresh orthogonal vector.
            beta.push(0.0);
            let Some(mut nv) = new_start(&mut rng, &q, &mq) else {
                break;
            };
            mmul(&nv, &mut mw);
            let nn = dot(&nv, &mw).sqrt();
            if !(nn > 0.0) {
                break;
            }
            nv.iter_mut().for_each(|x| *x /= nn);
            v = nv;
            mv = mw.iter().map(|x| x / nn).collect();
        } else {
            beta.push(b);
            v = w.iter().map(|x| x / b).collect();
            mv = mw.iter().map(|x| x / b).collect();
        }
    }
    // Final attempt with whatever subspace we have.
    let b_last = 0.0;
    match ritz(&q, &alpha, &beta, b_last, nev, opts, n)? {
        Some(r) if q.len() == n => Ok(r),
        _ => Err(FemError::Eigen(format!(
            "expected {nev} converged eigenpairs within {} Lanczos steps, found fewer (tol {:e})",
            q.len(),
            opts.tol
        ))),
    }
}

#[allow(clippy::type_complexity)]
fn ritz(
    q: &[Vec<f64>],
    alpha: &[f64],
    beta: &[f64],
    b_next: f64,
    nev: usize,
    opts: &EigenOptions,
    n: usize,
) -> Result<Option<(Vec<f64>, Mat<f64>)>, FemError> {
    let k = alpha.len();
    if k < nev {
        return Ok(None);
    }
    // Largest θ of T = lowest eigenvalues of −T, by the sequential dense solver (so the
    // result does not depend on faer's global parallelism).
    let mut neg_t = vec![0.0; k * k];
    for i in 0..k {
        neg_t[i * k + i] = -alpha[i];
        if i + 1 < k {
            neg_t[i * k + i + 1] = -beta[i];
            neg_t[(i + 1) * k + i] = -beta[i];
        }
    }
    let se = super::dense::lowest_eigenpairs(&mut neg_t, k, 0, nev);
    for i in 0..nev {
        let theta = -se.values[i];
        if !(theta > 0.0) || (b_next * se.vectors[i][k - 1]).abs() > opts.tol * theta {
            return Ok(None);
        }
    }
    let lambda: Vec<f64> = (0..nev).map(|i| opts.shift - 1.0 / se.values[i]).collect();
    let mut vecs = Mat::<f64>::zeros(n, nev);
    for (c, s) in se.vectors.iter().enumerate() {
        for (j, qj) in q.iter().enumerate() {
            let w = s[j];
            if w != 0.0 {
                for r in 0..n {
                    vecs[(r, c)] += w * qj[r];
                }
            }
        }
        if (0..n).map(|r| sign_weight(r) * vecs[(r, c)]).sum::<f64>() < 0.0 {
            for r in 0..n {
                vecs[(r, c)] = -vecs[(r, c)];
            }
        }
    }
    Ok(Some((lambda, vecs)))
}

/// Fixed weights that fix eigenvector signs: w_i = frac(0.618… · (i + 1)) − ½ (the
/// golden-ratio sequence). Unlike "largest entry positive" this does not flip between
/// symmetric entries of equal magnitude, so signs vary smoothly with the parameters
/// except where the weighted sum crosses zero.
pub fn sign_weight(i: usize) -> f64 {
    ((i as f64 + 1.0) * 0.618_033_988_749_894_8).fract() - 0.5
}

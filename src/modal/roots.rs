//! Roots of a real polynomial: eigenvalues of its companion matrix by a Francis double-shift
//! QR iteration that works directly on the (already upper Hessenberg) companion matrix.
//!
//! Hand-written because the LSCF needs the roots of one polynomial per model order (29 of
//! them per pass, degree up to 60 or more) and the general eigen-solvers at hand first
//! reduce the matrix to Hessenberg form and accumulate work we do not need; faer keeps its
//! Hessenberg QR (`lahqr`) private. This is the classical eigenvalues-only algorithm
//! (EISPACK `hqr`, as in Press et al., *Numerical Recipes*, 3rd ed., §11.6.3) preceded by an
//! exact power-of-two balancing (EISPACK `balanc`, §11.6.1), which keeps the companion
//! structure and much improves the accuracy of roots of polynomials whose coefficients span
//! many orders of magnitude. Cost `O(n^3)` with a small constant and no allocation beyond
//! the `n x n` work matrix. Verified in the tests against faer's general eigen-solver and
//! against polynomials with known roots.

use faer::c64;

/// Roots of `sum_j coef[j] z^j` (ascending coefficients, `coef[n] != 0`), in no particular
/// order; complex roots come in exact conjugate pairs. If the QR iteration does not converge
/// (30 iterations per root, as in EISPACK) faer's general eigen-solver is tried on the same
/// matrix. `None` if that fails too or a coefficient is not finite.
pub fn poly_roots(coef: &[f64]) -> Option<Vec<c64>> {
    roots_with(coef, 30)
}

/// [`poly_roots`] with at most `max_its` QR sweeps per root before the fallback.
fn roots_with(coef: &[f64], max_its: usize) -> Option<Vec<c64>> {
    let n = coef.len().checked_sub(1)?;
    if n == 0 {
        return Some(Vec::new());
    }
    let lead = coef[n];
    if lead == 0.0 || coef.iter().any(|c| !c.is_finite()) {
        return None;
    }
    // Companion matrix (row-major), first row -coef[n-1-j]/coef[n], ones on the subdiagonal:
    // upper Hessenberg.
    let mut a = vec![0.0; n * n];
    for j in 0..n {
        a[j] = -coef[n - 1 - j] / lead;
    }
    for i in 1..n {
        a[i * n + i - 1] = 1.0;
    }
    balance(&mut a, n);
    let balanced = a.clone();
    hessenberg_eigenvalues(&mut a, n, max_its).or_else(|| {
        // The double-shift iteration gave up (rare: 30 sweeps on one root); faer's general
        // solver (Hessenberg reduction, multishift QR with aggressive deflation) decides.
        let m = faer::Mat::<f64>::from_fn(n, n, |i, j| balanced[i * n + j]);
        let ev = m.eigenvalues().ok()?;
        crate::simd::clear_upper_vector_state();
        ev.iter()
            .all(|z| z.re.is_finite() && z.im.is_finite())
            .then_some(ev)
    })
}

/// Diagonal similarity `D^{-1} A D` with powers of two (exact in floating point) that makes
/// the row and column norms of each index comparable. Keeps any sparsity pattern, so a
/// Hessenberg matrix stays Hessenberg.
fn balance(a: &mut [f64], n: usize) {
    const RADIX: f64 = 2.0;
    const SQRDX: f64 = RADIX * RADIX;
    let mut done = false;
    let mut sweeps = 0;
    while !done && sweeps < 100 {
        done = true;
        sweeps += 1;
        for i in 0..n {
            let (mut r, mut c) = (0.0f64, 0.0f64);
            for j in 0..n {
                if j != i {
                    c += a[j * n + i].abs();
                    r += a[i * n + j].abs();
                }
            }
            if c != 0.0 && r != 0.0 {
                let mut g = r / RADIX;
                let mut f = 1.0;
                let s = c + r;
                while c < g {
                    f *= RADIX;
                    c *= SQRDX;
                }
                g = r * RADIX;
                while c > g {
                    f /= RADIX;
                    c /= SQRDX;
                }
                if (c + r) / f < 0.95 * s {
                    done = false;
                    let g = 1.0 / f;
                    for j in 0..n {
                        a[i * n + j] *= g;
                    }
                    for j in 0..n {
                        a[j * n + i] *= f;
                    }
                }
            }
        }
    }
}

/// `|a|` with the sign of `b` (Fortran `SIGN`).
fn sign(a: f64, b: f64) -> f64 {
    if b >= 0.0 {
        a.abs()
    } else {
        -a.abs()
    }
}

/// All eigenvalues of the upper Hessenberg matrix `a` (row-major `n x n`, destroyed).
/// `None` if one root needs more than `max_its` sweeps.
pub(crate) fn hessenberg_eigenvalues(a: &mut [f64], n: usize, max_its: usize) -> Option<Vec<c64>> {
    let idx = |i: usize, j: usize| i * n + j;
    let mut wr = vec![0.0; n];
    let mut wi = vec![0.0; n];
    let mut anorm = 0.0;
    for i in 0..n {
        for j in i.saturating_sub(1)..n {
            anorm += a[idx(i, j)].abs();
        }
    }
    if !anorm.is_finite() {
        return None;
    }
    // `nn` is the last row of the active (not yet deflated) block, `t` the accumulated
    // exceptional shift.
    let mut nn = n as isize - 1;
    let mut t = 0.0;
    while nn >= 0 {
        let mut its = 0;
        loop {
            // Look for a single small subdiagonal element.
            let mut l = nn;
            while l >= 1 {
                let lu = l as usize;
                let mut s = a[idx(lu - 1, lu - 1)].abs() + a[idx(lu, lu)].abs();
                if s == 0.0 {
                    s = anorm;
                }
                if a[idx(lu, lu - 1)].abs() + s == s {
                    a[idx(lu, lu - 1)] = 0.0;
                    break;
                }
                l -= 1;
            }
            let nu = nn as usize;
            let mut x = a[idx(nu, nu)];
            if l == nn {
                // One root found.
                wr[nu] = x + t;
                wi[nu] = 0.0;
                nn -= 1;
                break;
            }
            let mut y = a[idx(nu - 1, nu - 1)];
            let mut w = a[idx(nu, nu - 1)] * a[idx(nu - 1, nu)];
            if l == nn - 1 {
                // Two roots found.
                let p = 0.5 * (y - x);
                let q = p * p + w;
                let mut z = q.abs().sqrt();
                x += t;
                if q >= 0.0 {
                    z = p + sign(z, p);
                    wr[nu - 1] = x + z;
                    wr[nu] = x + z;
                    if z != 0.0 {
                        wr[nu] = x - w / z;
                    }
                    wi[nu - 1] = 0.0;
                    wi[nu] = 0.0;
                } else {
                    wr[nu - 1] = x + p;
                    wr[nu] = x + p;
                    wi[nu - 1] = -z;
                    wi[nu] = z;
                }
                nn -= 2;
                break;
            }
            // No roots found yet: iterate.
            if its == max_its {
                return None;
            }
            if its == 10 || its == 20 {
                // Exceptional shift.
                t += x;
                for i in 0..=nu {
                    a[idx(i, i)] -= x;
                }
                let s = a[idx(nu, nu - 1)].abs() + a[idx(nu - 1, nu - 2)].abs();
                x = 0.75 * s;
                y = x;
                w = -0.4375 * s * s;
            }
            its += 1;
            let lu = l as usize;
            // Form the shift and look for two consecutive small subdiagonal elements.
            let mut m = nu - 2;
            let (mut p, mut q, mut r);
            let mut z;
            loop {
                z = a[idx(m, m)];
                let rr = x - z;
                let ss = y - z;
                p = (rr * ss - w) / a[idx(m + 1, m)] + a[idx(m, m + 1)];
                q = a[idx(m + 1, m + 1)] - z - rr - ss;
                r = a[idx(m + 2, m + 1)];
                let s = p.abs() + q.abs() + r.abs();
                p /= s;
                q /= s;
                r /= s;
                if m == lu {
                    break;
                }
                let u = a[idx(m, m - 1)].abs() * (q.abs() + r.abs());
                let v =
                    p.abs() * (a[idx(m - 1, m - 1)].abs() + z.abs() + a[idx(m + 1, m + 1)].abs());
                if u + v == v {
                    break;
                }
                m -= 1;
            }
            for i in m + 2..=nu {
                a[idx(i, i - 2)] = 0.0;
                if i != m + 2 {
                    a[idx(i, i - 3)] = 0.0;
                }
            }
            // Double QR step on rows l..=nn and columns m..=nn.
            let mut xk = 0.0;
            for k in m..nu {
                if k != m {
                    p = a[idx(k, k - 1)];
                    q = a[idx(k + 1, k - 1)];
                    r = 0.0;
                    if k + 1 != nu {
                        r = a[idx(k + 2, k - 1)];
                    }
                    xk = p.abs() + q.abs() + r.abs();
                    if xk != 0.0 {
                        p /= xk;
                        q /= xk;
                        r /= xk;
                    }
                }
                let s = sign((p * p + q * q + r * r).sqrt(), p);
                if s != 0.0 {
                    if k == m {
                        if lu != m {
                            a[idx(k, k - 1)] = -a[idx(k, k - 1)];
                        }
                    } else {
                        a[idx(k, k - 1)] = -s * xk;
                    }
                    p += s;
                    let xs = p / s;
                    let ys = q / s;
                    let zs = r / s;
                    q /= p;
                    r /= p;
                    // Row modification (rows k, k+1[, k+2], columns k..=nn), on row slices
                    // so the inner loop runs without bounds checks.
                    let (head, tail) = a.split_at_mut((k + 1) * n);
                    let r0 = &mut head[k * n + k..=k * n + nu];
                    let (r1, r2) = tail.split_at_mut(n);
                    let r1 = &mut r1[k..=nu];
                    if k + 1 != nu {
                        let r2 = &mut r2[k..=nu];
                        for ((x0, x1), x2) in r0.iter_mut().zip(r1.iter_mut()).zip(r2.iter_mut()) {
                            let pp = *x0 + q * *x1 + r * *x2;
                            *x2 -= pp * zs;
                            *x1 -= pp * ys;
                            *x0 -= pp * xs;
                        }
                    } else {
                        for (x0, x1) in r0.iter_mut().zip(r1.iter_mut()) {
                            let pp = *x0 + q * *x1;
                            *x1 -= pp * ys;
                            *x0 -= pp * xs;
                        }
                    }
                    // Column modification (rows l..=min(nn, k+3), columns k, k+1[, k+2]).
                    let mmin = if nu < k + 3 { nu } else { k + 3 };
                    if k + 1 != nu {
                        for i in lu..=mmin {
                            let c = &mut a[i * n + k..i * n + k + 3];
                            let pp = xs * c[0] + ys * c[1] + zs * c[2];
                            c[2] -= pp * r;
                            c[1] -= pp * q;
                            c[0] -= pp;
                        }
                    } else {
                        for i in lu..=mmin {
                            let c = &mut a[i * n + k..i * n + k + 2];
                            let pp = xs * c[0] + ys * c[1];
                            c[1] -= pp * q;
                            c[0] -= pp;
                        }
                    }
                }
            }
        }
    }
    let out: Vec<c64> = wr.iter().zip(&wi).map(|(&r, &i)| c64::new(r, i)).collect();
    out.iter()
        .all(|z| z.re.is_finite() && z.im.is_finite())
        .then_some(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Expand `prod (z - r)` with the given real and conjugate-pair roots.
    fn poly_from_roots(roots: &[c64]) -> Vec<f64> {
        let mut c = vec![c64::new(1.0, 0.0)];
        for r in roots {
            let mut next = vec![c64::new(0.0, 0.0); c.len() + 1];
            for (j, cj) in c.iter().enumerate() {
                next[j + 1] += *cj;
                next[j] -= *cj * r;
            }
            c = next;
        }
        c.iter().map(|v| v.re).collect()
    }

    /// Match each expected root with its nearest found root (greedy, exclusive) and return
    /// the largest distance relative to `max(1, |r|)`.
    fn worst_match(expected: &[c64], found: &[c64]) -> f64 {
        assert_eq!(expected.len(), found.len());
        let mut used = vec![false; found.len()];
        let mut worst = 0.0f64;
        for e in expected {
            let (k, d) = found
                .iter()
                .enumerate()
                .filter(|(k, _)| !used[*k])
                .map(|(k, f)| (k, (f - e).norm()))
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .unwrap();
            used[k] = true;
            worst = worst.max(d / e.norm().max(1.0));
        }
        worst
    }

    #[test]
    fn known_roots_of_lscf_like_polynomials() {
        // Roots near the unit circle at well separated angles, as the z-domain LSCF
        // denominators have (lightly damped poles plus computational poles), degree 4..60,
        // against the known roots and against faer's eigenvalues of the same companion.
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for deg_half in [2usize, 5, 10, 20, 30] {
            let mut roots = Vec::new();
            for j in 0..deg_half {
                let ang = std::f64::consts::PI * (j as f64 + 0.5 + 0.3 * rng.random::<f64>())
                    / deg_half as f64;
                let rad = 1.0 + 0.05 * rng.random::<f64>();
                let z = c64::from_polar(rad, ang);
                roots.push(z);
                roots.push(z.conj());
            }
            let coef = poly_from_roots(&roots);
            let found = poly_roots(&coef).expect("converges");
            let w = worst_match(&roots, &found);
            let n = coef.len() - 1;
            let comp = faer::Mat::<f64>::from_fn(n, n, |i, j| {
                if i == 0 {
                    -coef[n - 1 - j]
                } else if i == j + 1 {
                    1.0
                } else {
                    0.0
                }
            });
            let wf = worst_match(&roots, &comp.eigenvalues().unwrap());
            // The roots of an expanded polynomial are only as accurate as its conditioning
            // allows (at degree 60 with all roots near the unit circle, 3e-4 for any
            // method working from the coefficients): as accurate as faer's general
            // eigen-solver, and to 1e-12 where the problem is well conditioned.
            assert!(
                w <= 10.0 * wf + 1e-13 && (n > 20 || w < 1e-12),
                "degree {n}: worst root error {w:e} (faer {wf:e})"
            );
            // Conjugate pairs are exact.
            for z in found.iter().filter(|z| z.im != 0.0) {
                assert!(found.iter().any(|y| *y == z.conj()));
            }
        }
    }

    #[test]
    fn agrees_with_faer_on_random_polynomials_and_hessenberg_matrices() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        for n in [1usize, 2, 3, 4, 7, 16, 33, 60, 80] {
            let coef: Vec<f64> = (0..=n).map(|_| rng.random::<f64>() - 0.5).collect();
            let found = poly_roots(&coef).expect("converges");
            let comp = faer::Mat::<f64>::from_fn(n, n, |i, j| {
                if i == 0 {
                    -coef[n - 1 - j] / coef[n]
                } else if i == j + 1 {
                    1.0
                } else {
                    0.0
                }
            });
            let reference = comp.eigenvalues().unwrap();
            let w = worst_match(&reference, &found);
            assert!(w < 1e-7, "polynomial degree {n}: {w:e}");
            // A general upper Hessenberg matrix (not a companion matrix).
            let h = faer::Mat::<f64>::from_fn(n, n, |i, j| {
                if i <= j + 1 {
                    rng.random::<f64>() - 0.5
                } else {
                    0.0
                }
            });
            let mut a: Vec<f64> = (0..n * n).map(|ij| h[(ij / n, ij % n)]).collect();
            let found = hessenberg_eigenvalues(&mut a, n, 30).expect("converges");
            let reference = h.eigenvalues().unwrap();
            let w = worst_match(&reference, &found);
            assert!(w < 1e-9, "hessenberg {n}: {w:e}");
        }
    }

    #[test]
    fn falls_back_to_faer_when_the_iteration_gives_up() {
        let roots: Vec<c64> = (1..=6)
            .flat_map(|j| {
                let z = c64::from_polar(1.0 - 0.01 * j as f64, 0.5 * j as f64);
                [z, z.conj()]
            })
            .collect();
        let coef = poly_from_roots(&roots);
        // No sweep allowed: every root comes from the fallback.
        let found = roots_with(&coef, 0).expect("fallback succeeds");
        assert!(worst_match(&roots, &found) < 1e-10);
        let direct = poly_roots(&coef).unwrap();
        assert!(worst_match(&direct, &found) < 1e-10);
    }

    #[test]
    fn degenerate_inputs() {
        assert_eq!(poly_roots(&[]), None);
        assert_eq!(poly_roots(&[3.0]), Some(vec![]));
        assert_eq!(poly_roots(&[1.0, 0.0]), None);
        assert_eq!(poly_roots(&[1.0, f64::NAN, 1.0]), None);
        let r = poly_roots(&[-2.0, 1.0]).unwrap();
        assert_eq!(r, vec![c64::new(2.0, 0.0)]);
        // Multiple root: z^2 - 2z + 1.
        let r = poly_roots(&[1.0, -2.0, 1.0]).unwrap();
        assert!(r.iter().all(|z| (z - c64::new(1.0, 0.0)).norm() < 1e-7));
        // Zero roots: z^3.
        let r = poly_roots(&[0.0, 0.0, 0.0, 1.0]).unwrap();
        assert!(r.iter().all(|z| z.norm() < 1e-12));
    }
}

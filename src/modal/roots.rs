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
//!
//! Along a stabilization diagram the polynomial of order `n` has nearly the roots of order
//! `n - 2` plus two more, so [`poly_roots_from`] starts the simultaneous Aberth–Ehrlich
//! iteration (Bini 1996, the method of MPSolve) from those: `O(n^2)` per sweep, cubic
//! convergence, a root stops moving once its residual is at the rounding level of the
//! evaluation. If it has not converged after a few dozen sweeps the QR path decides.

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

/// Roots of `sum_j coef[j] z^j` as [`poly_roots`], by an Aberth–Ehrlich iteration started
/// from `guesses` (typically the roots of the previous, lower order); missing starting
/// points (`guesses.len() < degree`) are placed on the unit circle in the widest angular
/// gaps, surplus ones are ignored. Falls back to [`poly_roots`] if the iteration does not
/// converge. Deterministic: a fixed sweep order, no randomness.
pub fn poly_roots_from(coef: &[f64], guesses: &[c64]) -> Option<Vec<c64>> {
    let n = coef.len().checked_sub(1)?;
    if n <= 2 || coef[n] == 0.0 || coef.iter().any(|c| !c.is_finite()) {
        return poly_roots(coef);
    }
    let mut z: Vec<c64> = guesses
        .iter()
        .filter(|g| g.re.is_finite() && g.im.is_finite())
        .take(n)
        .copied()
        .collect();
    while z.len() < n {
        let (phi, r) = widest_gap(&z);
        let g = c64::from_polar(r, phi);
        z.push(g);
        if z.len() < n {
            z.push(g.conj());
        }
    }
    // Separate coincident starting points (the iteration divides by their differences).
    for i in 1..n {
        for j in 0..i {
            if (z[i] - z[j]).norm_sqr() <= 1e-20 * z[i].norm_sqr().max(f64::MIN_POSITIVE) {
                z[i] *= c64::from_polar(1.0 + 1e-6, 1e-6 * (i as f64 + 1.0));
            }
        }
    }
    if aberth(coef, &mut z, 60) {
        Some(z)
    } else {
        poly_roots(coef)
    }
}

/// Widest angular gap among the roots in the closed upper half-plane (bounded by the
/// angles 0 and pi): its mid-angle and the median modulus of the roots (1 if none).
fn widest_gap(z: &[c64]) -> (f64, f64) {
    let mut ang: Vec<f64> = z
        .iter()
        .filter(|v| v.im >= 0.0)
        .map(|v| v.im.atan2(v.re))
        .collect();
    ang.push(0.0);
    ang.push(std::f64::consts::PI);
    ang.sort_by(|a, b| a.total_cmp(b));
    let (mut best, mut mid) = (-1.0, std::f64::consts::FRAC_PI_2);
    for w in ang.windows(2) {
        if w[1] - w[0] > best {
            best = w[1] - w[0];
            mid = 0.5 * (w[0] + w[1]);
        }
    }
    let mut mods: Vec<f64> = z.iter().map(|v| v.norm()).filter(|m| *m > 0.0).collect();
    mods.sort_by(|a, b| a.total_cmp(b));
    let r = mods.get(mods.len() / 2).copied().unwrap_or(1.0);
    (mid, r)
}

/// Newton ratio `p(z)/p'(z)` and whether `|p(z)|` is at the rounding level of its Horner
/// evaluation (`8 n eps sum |a_j| |z|^j`). For `|z| > 1` the reversed polynomial in `1/z` is
/// evaluated instead, which keeps the evaluation backward stable.
fn newton_ratio(coef: &[f64], z: c64) -> (c64, bool) {
    let n = coef.len() - 1;
    let eps = f64::EPSILON;
    // (Moduli through `norm_sqr`: `norm` is a `hypot` call, which dominated this loop.)
    if z.norm_sqr() <= 1.0 {
        let (mut p, mut dp) = (c64::new(coef[n], 0.0), c64::new(0.0, 0.0));
        let mut bound = coef[n].abs();
        let az = z.norm_sqr().sqrt();
        for j in (0..n).rev() {
            dp = dp * z + p;
            p = p * z + coef[j];
            bound = bound * az + coef[j].abs();
        }
        let tol = 8.0 * n as f64 * eps * bound;
        (p / dp, p.norm_sqr() <= tol * tol)
    } else {
        // p(z) = z^n q(y), y = 1/z, q(y) = sum_j coef[n-j] y^j; p/p' = z q / (n q - y q').
        let y = z.inv();
        let (mut q, mut dq) = (c64::new(coef[0], 0.0), c64::new(0.0, 0.0));
        let mut bound = coef[0].abs();
        let ay = y.norm_sqr().sqrt();
        for &c in &coef[1..] {
            dq = dq * y + q;
            q = q * y + c;
            bound = bound * ay + c.abs();
        }
        let den = q * n as f64 - y * dq;
        let tol = 8.0 * n as f64 * eps * bound;
        (z * q / den, q.norm_sqr() <= tol * tol)
    }
}

/// Aberth–Ehrlich sweeps (Gauss–Seidel order) until every root is at its rounding level or
/// its correction is below `4 eps |z|`; `false` after `max_sweeps` or on a non-finite value.
fn aberth(coef: &[f64], z: &mut [c64], max_sweeps: usize) -> bool {
    let n = z.len();
    let mut done = vec![false; n];
    for _ in 0..max_sweeps {
        let mut all = true;
        for i in 0..n {
            if done[i] {
                continue;
            }
            let zi = z[i];
            let (ratio, converged) = newton_ratio(coef, zi);
            // At the rounding level one more correction is still taken (it is what brings
            // the root to full accuracy), then the root is frozen.
            if converged {
                done[i] = true;
            } else {
                all = false;
            }
            let mut s = c64::new(0.0, 0.0);
            for (j, zj) in z.iter().enumerate() {
                if j != i {
                    s += (zi - zj).inv();
                }
            }
            let w = ratio / (c64::new(1.0, 0.0) - ratio * s);
            if !(w.re.is_finite() && w.im.is_finite()) {
                if converged {
                    continue;
                }
                return false;
            }
            z[i] = zi - w;
            if w.norm_sqr() <= 16.0 * f64::EPSILON * f64::EPSILON * zi.norm_sqr() {
                done[i] = true;
            }
        }
        if all {
            return true;
        }
    }
    false
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
fn hessenberg_eigenvalues(a: &mut [f64], n: usize, max_its: usize) -> Option<Vec<c64>> {
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
    fn warm_started_roots_agree_with_qr_along_an_order_sequence() {
        // A sequence of polynomials like an LSCF stabilization diagram: fixed "physical"
        // roots near the unit circle plus computational ones that change with the order.
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let physical: Vec<c64> = [0.4, 0.9, 1.3, 2.2, 2.25, 2.9]
            .iter()
            .map(|&a| c64::from_polar(1.0 + 0.01 * a, -a))
            .collect();
        let mut prev: Vec<c64> = Vec::new();
        for half in physical.len()..=30 {
            let mut roots: Vec<c64> = physical.clone();
            while roots.len() < half {
                let a = -std::f64::consts::PI * rng.random::<f64>();
                roots.push(c64::from_polar(0.6 + 0.8 * rng.random::<f64>(), a));
            }
            let roots: Vec<c64> = roots.iter().flat_map(|z| [*z, z.conj()]).collect();
            let coef = poly_from_roots(&roots);
            let qr = poly_roots(&coef).unwrap();
            let warm = poly_roots_from(&coef, &prev).unwrap();
            assert_eq!(warm.len(), coef.len() - 1);
            // Against the known roots: as accurate as the QR path (both are limited by the
            // conditioning of the expanded polynomial).
            let (w, wq) = (worst_match(&roots, &warm), worst_match(&roots, &qr));
            assert!(
                w <= 10.0 * wq + 1e-12,
                "degree {}: warm {w:e}, qr {wq:e}",
                coef.len() - 1
            );
            // The physical roots themselves to the conditioning of the problem.
            for p in &physical {
                let d = warm
                    .iter()
                    .map(|z| (z - p).norm())
                    .fold(f64::INFINITY, f64::min);
                assert!(
                    d < 1e-6,
                    "degree {}: physical root off by {d:e}",
                    coef.len() - 1
                );
            }
            prev = warm;
        }
        // Cold start (no guesses) and surplus guesses work too.
        let coef = poly_from_roots(
            &physical
                .iter()
                .flat_map(|z| [*z, z.conj()])
                .collect::<Vec<_>>(),
        );
        let cold = poly_roots_from(&coef, &[]).unwrap();
        assert!(worst_match(&poly_roots(&coef).unwrap(), &cold) < 1e-9);
        let many: Vec<c64> = (0..40)
            .map(|k| c64::from_polar(1.0, 0.1 * k as f64))
            .collect();
        let surplus = poly_roots_from(&coef, &many).unwrap();
        assert!(worst_match(&poly_roots(&coef).unwrap(), &surplus) < 1e-9);
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(64))]
        /// Whatever the coefficients and the starting points, every returned root is a root
        /// up to rounding: `|p(z)|` within a small multiple of the evaluation's error bound
        /// `eps sum |a_j| |z|^j` (a backward-error check that needs no reference solver).
        #[test]
        fn every_root_has_a_rounding_level_residual(
            coef in proptest::collection::vec(-1.0f64..1.0, 3..40),
            guesses in proptest::collection::vec((-2.0f64..2.0, -2.0f64..2.0), 0..45),
        ) {
            let mut coef = coef;
            let n = coef.len() - 1;
            if coef[n].abs() < 1e-3 {
                coef[n] = 1.0;
            }
            let g: Vec<c64> = guesses.iter().map(|&(re, im)| c64::new(re, im)).collect();
            let roots = poly_roots_from(&coef, &g).expect("a root-finder converges");
            proptest::prop_assert_eq!(roots.len(), n);
            for z in &roots {
                // Evaluate in the stable direction (reversed polynomial outside the circle).
                let (val, bound) = if z.norm() <= 1.0 {
                    let mut p = c64::new(0.0, 0.0);
                    let mut b = 0.0;
                    for c in coef.iter().rev() {
                        p = p * z + c;
                        b = b * z.norm() + c.abs();
                    }
                    (p.norm(), b)
                } else {
                    let y = z.inv();
                    let mut q = c64::new(0.0, 0.0);
                    let mut b = 0.0;
                    for c in coef.iter() {
                        q = q * y + c;
                        b = b * y.norm() + c.abs();
                    }
                    (q.norm(), b)
                };
                proptest::prop_assert!(
                    val <= 1e3 * n as f64 * f64::EPSILON * bound,
                    "root {} of degree {}: |p| = {:e}, bound {:e}", z, n, val, bound
                );
            }
        }
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

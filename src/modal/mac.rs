//! Modal assurance criterion (MAC) between shapes, real and complex, and MAC matrices.
//!
//! `MAC(a, b) = |a^H b|^2 / ((a^H a)(b^H b))`, in [0, 1]; 1 means the shapes are parallel.
//! Components that are not finite in either vector (excluded scan points are `NaN`) are
//! skipped, so shapes with missing points compare over the points both have.

use faer::c64;

/// Real MAC over the components finite in both vectors. Returns 0 when either vector has
/// no energy on the common components.
pub fn mac_real(a: &[f64], b: &[f64]) -> f64 {
    let (mut ab, mut aa, mut bb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        if x.is_finite() && y.is_finite() {
            ab += x * y;
            aa += x * x;
            bb += y * y;
        }
    }
    if aa <= 0.0 || bb <= 0.0 {
        return 0.0;
    }
    (ab * ab / (aa * bb)).clamp(0.0, 1.0)
}

/// Complex MAC `|a^H b|^2 / ((a^H a)(b^H b))` over the components finite in both vectors.
pub fn mac_complex(a: &[c64], b: &[c64]) -> f64 {
    let mut ab = c64::new(0.0, 0.0);
    let (mut aa, mut bb) = (0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        if x.re.is_finite() && x.im.is_finite() && y.re.is_finite() && y.im.is_finite() {
            ab += x.conj() * y;
            aa += x.norm_sqr();
            bb += y.norm_sqr();
        }
    }
    if aa <= 0.0 || bb <= 0.0 {
        return 0.0;
    }
    (ab.norm_sqr() / (aa * bb)).clamp(0.0, 1.0)
}

/// MAC matrix `m[i][j] = MAC(a[i], b[j])` between two sets of real shapes.
pub fn mac_matrix(a: &[Vec<f64>], b: &[Vec<f64>]) -> Vec<Vec<f64>> {
    a.iter()
        .map(|x| b.iter().map(|y| mac_real(x, y)).collect())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn orthogonal_and_parallel() {
        assert!((mac_real(&[1.0, 0.0], &[0.0, 2.0])).abs() < 1e-15);
        assert!((mac_real(&[1.0, -2.0, 3.0], &[-2.0, 4.0, -6.0]) - 1.0).abs() < 1e-15);
        // NaN components are skipped.
        assert!((mac_real(&[1.0, f64::NAN, 3.0], &[2.0, 5.0, 6.0]) - 1.0).abs() < 1e-15);
    }

    proptest! {
        /// MAC is invariant to complex scaling of either vector and equals cos^2 of the
        /// angle; the complex MAC of real vectors equals the real MAC.
        #[test]
        fn scale_invariance(v in proptest::collection::vec(-1.0f64..1.0, 3..12),
                            w in proptest::collection::vec(-1.0f64..1.0, 3..12),
                            s in 0.1f64..10.0, ph in -3.0f64..3.0) {
            let n = v.len().min(w.len());
            let (v, w) = (&v[..n], &w[..n]);
            let m = mac_real(v, w);
            prop_assert!((0.0..=1.0).contains(&m));
            let rot = c64::from_polar(s, ph);
            let vc: Vec<c64> = v.iter().map(|x| rot * *x).collect();
            let wc: Vec<c64> = w.iter().map(|x| c64::new(*x, 0.0)).collect();
            prop_assert!((mac_complex(&vc, &wc) - m).abs() < 1e-9);
            let dot: f64 = v.iter().zip(w).map(|(a, b)| a * b).sum();
            let na: f64 = v.iter().map(|a| a * a).sum();
            let nb: f64 = w.iter().map(|a| a * a).sum();
            if na > 1e-9 && nb > 1e-9 {
                prop_assert!((m - dot * dot / (na * nb)).abs() < 1e-9);
            }
        }
    }
}

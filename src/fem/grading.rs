//! Node lines of a graded tensor-product mesh: denser where the field varies quickly.
//!
//! A bolted board's field varies on the scale of the clamp around each joint (a small
//! stiff support), and much more slowly elsewhere; a uniform mesh fine enough at the
//! joints is needlessly fine in the interior. Along each axis the node lines are
//! x_i = C⁻¹(i / n) for a node density
//!
//! ρ(x) = 1 + A Σ_k sech²((x − c_k) / w),   C(x) = ∫₀ˣ ρ / ∫₀ᴸ ρ,
//!
//! with c_k the joints' coordinates along that axis, w the width of the refined zone and
//! A the refinement (elements near a joint are about 1 + A times smaller than far from
//! it). C has the closed form x + A w Σ_k [tanh((x − c_k)/w) + tanh(c_k/w)], and C⁻¹ is
//! found by bisection to the last bit. The map does not depend on n, so the meshes
//! n ⊂ 2n ⊂ 4n are nested (x_{2i} at 2n is x_i at n, bit for bit: (2i)/(2n) and i/n round
//! to the same number), which keeps Rayleigh–Ritz monotonicity across mesh doublings.
//! A = 0 (or no centres) gives the uniform mesh x_i = i L / n exactly.

/// Node coordinates x_0 = 0 < x_1 < … < x_n = `len` along one axis (m), graded towards
/// `centres` (m; centres closer than `width / 2` are merged into their mean, so two
/// joints in one line refine it once) with refinement `amplitude` over `width` (m).
pub fn node_lines(len: f64, n: usize, centres: &[f64], width: f64, amplitude: f64) -> Vec<f64> {
    let mut cs: Vec<f64> = centres.to_vec();
    cs.sort_by(f64::total_cmp);
    let mut merged: Vec<(f64, usize)> = vec![];
    for c in cs {
        match merged.last_mut() {
            Some((m, k)) if c - *m / *k as f64 <= 0.5 * width => {
                *m += c;
                *k += 1;
            }
            _ => merged.push((c, 1)),
        }
    }
    let cs: Vec<f64> = merged.into_iter().map(|(m, k)| m / k as f64).collect();
    if amplitude == 0.0 || cs.is_empty() || !(width > 0.0) {
        return uniform_lines(len, n);
    }
    // Unnormalised cumulative density.
    let cum = |x: f64| -> f64 {
        x + amplitude
            * width
            * cs.iter()
                .map(|c| ((x - c) / width).tanh() + (c / width).tanh())
                .sum::<f64>()
    };
    let total = cum(len);
    (0..=n)
        .map(|i| {
            if i == 0 {
                return 0.0;
            }
            if i == n {
                return len;
            }
            let target = (i as f64 / n as f64) * total;
            let (mut lo, mut hi) = (0.0_f64, len);
            // C is strictly increasing; bisect until the interval cannot shrink.
            loop {
                let mid = 0.5 * (lo + hi);
                if mid <= lo || mid >= hi {
                    break hi;
                }
                if cum(mid) < target {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
        })
        .collect()
}

/// Uniform node lines x_i = i (L / n), as the uniform mesh has always placed them.
pub fn uniform_lines(len: f64, n: usize) -> Vec<f64> {
    let h = len / n as f64;
    (0..=n).map(|i| i as f64 * h).collect()
}

/// The element of `lines` (increasing node coordinates) that contains `x`: the last
/// element whose start is ≤ x, clamped to the mesh.
pub fn element_of(lines: &[f64], x: f64) -> usize {
    let n = lines.len() - 1;
    lines[1..n].partition_point(|&l| l <= x).min(n - 1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uniform_without_centres_or_amplitude() {
        let l = node_lines(0.08, 40, &[], 3e-3, 2.0);
        assert_eq!(l.len(), 41);
        for (i, x) in l.iter().enumerate() {
            assert_eq!(*x, i as f64 * (0.08 / 40.0), "node {i}");
        }
        assert_eq!(node_lines(0.08, 40, &[0.004], 3e-3, 0.0), l);
    }

    #[test]
    fn graded_lines_are_nested_increasing_and_finer_at_the_centres() {
        let cs = [0.004, 0.076, 0.004];
        let (w, a) = (2.75e-3, 2.0);
        let l1 = node_lines(0.08, 40, &cs, w, a);
        let l2 = node_lines(0.08, 80, &cs, w, a);
        let l4 = node_lines(0.08, 160, &cs, w, a);
        assert_eq!((l1[0], l1[40]), (0.0, 0.08));
        for i in 0..=40 {
            assert_eq!(l1[i], l2[2 * i], "node {i} of 40 vs 80");
            assert_eq!(l1[i], l4[4 * i], "node {i} of 40 vs 160");
        }
        let h: Vec<f64> = l1.windows(2).map(|p| p[1] - p[0]).collect();
        assert!(h.iter().all(|&d| d > 0.0));
        // The density at a centre is 1 + A (the other centre is 18 widths away) and ~1
        // midway, so the sizes there differ by ~(1 + A).
        let at = h[element_of(&l1, 0.004)];
        let mid = h[element_of(&l1, 0.04)];
        assert!(
            (mid / at - (1.0 + a)).abs() < 0.05 * (1.0 + a),
            "{mid} / {at}"
        );
        // Symmetric centres give a symmetric mesh.
        for i in 0..=40 {
            assert!((l1[i] + l1[40 - i] - 0.08).abs() < 1e-15, "node {i}");
        }
    }

    #[test]
    fn element_of_finds_the_containing_element() {
        let l = node_lines(0.05, 25, &[0.004, 0.046], 2.75e-3, 2.0);
        for e in 0..25 {
            let x = 0.5 * (l[e] + l[e + 1]);
            assert_eq!(element_of(&l, x), e);
            assert_eq!(element_of(&l, l[e]), e);
        }
        assert_eq!(element_of(&l, 0.05), 24);
        assert_eq!(element_of(&l, -1e-12), 0);
        assert_eq!(element_of(&l, 0.06), 24);
    }
}

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

/// One refined zone along an axis: the term A sech²((x − c)/w) of the node density.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bump {
    /// Centre c, m.
    pub centre_m: f64,
    /// Width w, m.
    pub width_m: f64,
    /// Refinement A (elements there about 1 + A times smaller).
    pub amplitude: f64,
}

/// Node coordinates x_0 = 0 < x_1 < … < x_n = `len` along one axis (m), graded towards
/// `centres` (m; centres closer than `width / 2` are merged into their mean, so two
/// joints in one line refine it once) with refinement `amplitude` over `width` (m).
pub fn node_lines(len: f64, n: usize, centres: &[f64], width: f64, amplitude: f64) -> Vec<f64> {
    graded_lines(len, n, &merged_bumps(centres, width, amplitude))
}

/// The bumps of `centres` (m) of one width and refinement, centres closer than `width / 2`
/// merged into their mean; none where the refinement or width is zero.
pub fn merged_bumps(centres: &[f64], width: f64, amplitude: f64) -> Vec<Bump> {
    if amplitude == 0.0 || !(width > 0.0) {
        return vec![];
    }
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
    merged
        .into_iter()
        .map(|(m, k)| Bump {
            centre_m: m / k as f64,
            width_m: width,
            amplitude,
        })
        .collect()
}

/// Node coordinates x_0 = 0 < x_1 < … < x_n = `len` along one axis (m) for the node
/// density 1 + Σ_k A_k sech²((x − c_k)/w_k) of `bumps` (none: the uniform lines).
pub fn graded_lines(len: f64, n: usize, bumps: &[Bump]) -> Vec<f64> {
    if bumps.is_empty() {
        return uniform_lines(len, n);
    }
    // Unnormalised cumulative density, summed over runs of bumps of one width and refinement
    // (A w Σ_k …, the order of operations the single-width grading has always used).
    let cum = |x: f64| -> f64 {
        let mut out = x;
        for run in bumps.chunk_by(|a, b| a.width_m == b.width_m && a.amplitude == b.amplitude) {
            let (a, w) = (run[0].amplitude, run[0].width_m);
            out += a
                * w
                * run
                    .iter()
                    .map(|b| ((x - b.centre_m) / w).tanh() + (b.centre_m / w).tanh())
                    .sum::<f64>();
        }
        out
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

/// An interface along one axis: a coordinate across which the material changes (a copper
/// edge), with a weight saying how much it matters (how much stiffness changes across it,
/// over how long an edge); see [`snap_to_interfaces`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Interface {
    /// Coordinate along the axis, m.
    pub at_m: f64,
    /// Importance, any positive unit (only the order matters).
    pub weight: f64,
}

/// `lines` (increasing node coordinates) with interior lines moved onto `interfaces`.
///
/// Why: the BFS element's curvature is continuous inside it, but across an interface
/// where the bending stiffness jumps (a copper edge) the exact curvature jumps. With the
/// jump inside an element the frequencies converge only like O(h), not O(h⁴): on the
/// built-in board the free modes at 56 × 35 were 124 ppm off converged, while 40 × 25,
/// whose lines fall on the copper edges by chance, was 15 ppm off; with the lines moved
/// onto the edges 56 × 35 is 10 ppm off and the bolted 80 × 50 4 ppm (59 before).
///
/// Interfaces already on a line (within 1e-9 of an element) claim it first, then the
/// others by weight (heaviest first; ties by coordinate): each takes the nearer free line
/// of the element it lies in (else the farther one; a tie within 1e-9 of the element
/// takes the lower line), provided the two elements beside
/// that line keep at least a third of their size; an interface no line may take is left
/// inside its element. The end lines never move. Interfaces at the same coordinate
/// (within 1e-12 m) are one, their weights summed. The result depends on the lines only
/// through their positions, so a mesh and its doubling (whose lines include the coarse
/// ones) stay nested where each interface is taken at both.
pub fn snap_to_interfaces(lines: &[f64], interfaces: &[Interface]) -> Vec<f64> {
    let n = lines.len() - 1;
    let mut out = lines.to_vec();
    if n < 2 {
        return out;
    }
    let (lo, hi) = (lines[0], lines[n]);
    let mut cs: Vec<Interface> = interfaces
        .iter()
        .copied()
        .filter(|c| c.at_m > lo && c.at_m < hi && c.weight > 0.0)
        .collect();
    cs.sort_by(|a, b| a.at_m.total_cmp(&b.at_m));
    let mut merged: Vec<Interface> = Vec::with_capacity(cs.len());
    for c in cs {
        match merged.last_mut() {
            Some(m) if c.at_m - m.at_m <= 1e-12 => m.weight += c.weight,
            _ => merged.push(c),
        }
    }
    let on_line = |c: &Interface| -> bool {
        let e = element_of(lines, c.at_m);
        let tol = 1e-9 * (lines[e + 1] - lines[e]);
        (c.at_m - lines[e]).abs() <= tol || (lines[e + 1] - c.at_m).abs() <= tol
    };
    merged.sort_by(|a, b| {
        on_line(b)
            .cmp(&on_line(a))
            .then(b.weight.total_cmp(&a.weight))
            .then(a.at_m.total_cmp(&b.at_m))
    });
    let mut taken = vec![false; n + 1];
    for c in merged {
        let e = element_of(lines, c.at_m);
        // A tie (to rounding: 3 × 0.005 is 0.015000000000000003) takes the lower line.
        let tie = 1e-9 * (lines[e + 1] - lines[e]);
        let (near, far) = if (c.at_m - lines[e]) - (lines[e + 1] - c.at_m) <= tie {
            (e, e + 1)
        } else {
            (e + 1, e)
        };
        for i in [near, far] {
            if i == 0 || i == n || taken[i] {
                continue;
            }
            let (h0, h1) = (lines[i] - lines[i - 1], lines[i + 1] - lines[i]);
            if c.at_m - out[i - 1] >= h0 / 3.0 && out[i + 1] - c.at_m >= h1 / 3.0 {
                out[i] = c.at_m;
                taken[i] = true;
                break;
            }
        }
    }
    out
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

    /// Bumps of two widths (joints and edges): nested, and each zone's elements about 1 + A
    /// times smaller than the interior's, whatever the other bump.
    #[test]
    fn bumps_of_several_widths_are_nested_and_refine_each_zone() {
        let mut bumps = merged_bumps(&[0.005, 0.075], 3e-3, 2.0);
        bumps.extend(merged_bumps(&[0.0, 0.08], 1e-3, 15.0));
        let l1 = graded_lines(0.08, 56, &bumps);
        let l2 = graded_lines(0.08, 112, &bumps);
        for i in 0..=56 {
            assert_eq!(l1[i], l2[2 * i], "node {i} of 56 vs 112");
        }
        let h: Vec<f64> = l2.windows(2).map(|p| p[1] - p[0]).collect();
        assert!(h.iter().all(|&d| d > 0.0));
        let mid = h[element_of(&l2, 0.04)];
        let (edge, joint) = (h[0], h[element_of(&l2, 0.005)]);
        assert!(
            (mid / edge - 16.0).abs() < 0.15 * 16.0,
            "edge: {mid} / {edge}"
        );
        // At the joint 1 + A = 3 (the edge's bump, 5 of its widths away, adds 0.3 %).
        assert!((mid / joint - 3.0).abs() < 0.1, "joint: {mid} / {joint}");
    }

    fn iface(at_m: f64, weight: f64) -> Interface {
        Interface { at_m, weight }
    }

    #[test]
    fn snapping_puts_lines_on_interfaces_and_keeps_elements_sound() {
        let l = uniform_lines(0.05, 25);
        // 2 mm elements; 22 and 28 mm are on lines already: nothing moves.
        let s = snap_to_interfaces(&l, &[iface(0.022, 1.0), iface(0.028, 1.0)]);
        assert_eq!(s, l);
        // 22.7 mm: the nearer line (22) moves onto it; 23 mm (a tie) takes the lower line.
        let s = snap_to_interfaces(&l, &[iface(0.0227, 1.0)]);
        assert_eq!(s[11], 0.0227);
        assert_eq!(s.iter().filter(|&&x| !l.contains(&x)).count(), 1);
        let s = snap_to_interfaces(&l, &[iface(0.023, 1.0)]);
        assert_eq!((s[11], s[12]), (0.023, l[12]));
        // Two interfaces in one element: the heavier takes the nearer line, the other
        // the farther one; a third has no line left and stays inside its element.
        let s = snap_to_interfaces(
            &l,
            &[iface(0.0225, 1.0), iface(0.0235, 5.0), iface(0.023, 0.1)],
        );
        assert_eq!((s[11], s[12]), (0.0225, 0.0235));
        assert!(!s.contains(&0.023));
        // An interface on a line claims it before a heavier one that wanted it.
        // (20.8 mm: its nearer line, 20 mm, is taken, so it takes the farther one.)
        let s = snap_to_interfaces(&l, &[iface(0.0208, 9.0), iface(0.020, 0.1)]);
        assert_eq!((s[10], s[11]), (l[10], 0.0208));
        // Too close to the board's edge for any element to keep a third of its size.
        let s = snap_to_interfaces(&l, &[iface(0.0004, 1.0)]);
        assert_eq!(s, l);
        // Whatever the interfaces, lines stay increasing, the ends never move and no
        // element shrinks below a third of its size.
        let ifs: Vec<Interface> = (0..200)
            .map(|k| iface(0.05 * ((k as f64 * 0.618_034) % 1.0), 1.0 + k as f64))
            .collect();
        let g = node_lines(0.05, 25, &[0.005, 0.045], 1.5e-3, 2.0);
        for base in [l.clone(), g] {
            let s = snap_to_interfaces(&base, &ifs);
            assert_eq!((s[0], s[25]), (base[0], base[25]));
            for i in 0..25 {
                let (h, h0) = (s[i + 1] - s[i], base[i + 1] - base[i]);
                assert!(h >= h0 / 3.0 - 1e-15, "element {i}: {h} of {h0}");
            }
        }
    }

    #[test]
    fn snapped_doubling_contains_the_coarse_lines() {
        let ifs = [
            iface(0.003, 2.0),
            iface(0.0227, 1.0),
            iface(0.0351, 1.0),
            iface(0.047, 2.0),
        ];
        let c = snap_to_interfaces(&uniform_lines(0.05, 25), &ifs);
        let f = snap_to_interfaces(&uniform_lines(0.05, 50), &ifs);
        for x in &c {
            assert!(f.contains(x), "{x} of the coarse mesh not in the fine one");
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

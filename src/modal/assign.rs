//! Optimal one-to-one assignment (Hungarian algorithm, Kuhn–Munkres with potentials).
//!
//! Hand-written (O(n^2 m), ~60 lines) because the `pathfinding` crate's `kuhn_munkres`
//! needs integer-like (`Ord`) weights, and scaling MAC values to integers would round away
//! exactly the small differences that decide between close modes.

/// Minimum-cost assignment for a rectangular cost matrix `cost[i][j]` (`n` rows, `m`
/// columns, all rows the same length, finite entries). Returns, for each row, the column it
/// is assigned to (`None` for the `n - m` surplus rows when `n > m`). Every column is used at
/// most once and the total cost is minimal.
pub fn hungarian_min(cost: &[Vec<f64>]) -> Vec<Option<usize>> {
    let n = cost.len();
    if n == 0 {
        return Vec::new();
    }
    let m = cost[0].len();
    if m == 0 {
        return vec![None; n];
    }
    if n > m {
        // Solve the transpose and invert the mapping.
        let t: Vec<Vec<f64>> = (0..m)
            .map(|j| (0..n).map(|i| cost[i][j]).collect())
            .collect();
        let tj = hungarian_min(&t);
        let mut out = vec![None; n];
        for (j, i) in tj.iter().enumerate() {
            if let Some(i) = i {
                out[*i] = Some(j);
            }
        }
        return out;
    }
    // e-maxx formulation, 1-based with a virtual column 0.
    let inf = f64::INFINITY;
    let mut u = vec![0.0; n + 1];
    let mut v = vec![0.0; m + 1];
    let mut p = vec![0usize; m + 1];
    let mut way = vec![0usize; m + 1];
    for i in 1..=n {
        p[0] = i;
        let mut j0 = 0usize;
        let mut minv = vec![inf; m + 1];
        let mut used = vec![false; m + 1];
        loop {
            used[j0] = true;
            let i0 = p[j0];
            let mut delta = inf;
            let mut j1 = 0usize;
            for j in 1..=m {
                if !used[j] {
                    let cur = cost[i0 - 1][j - 1] - u[i0] - v[j];
                    if cur < minv[j] {
                        minv[j] = cur;
                        way[j] = j0;
                    }
                    if minv[j] < delta {
                        delta = minv[j];
                        j1 = j;
                    }
                }
            }
            for j in 0..=m {
                if used[j] {
                    u[p[j]] += delta;
                    v[j] -= delta;
                } else {
                    minv[j] -= delta;
                }
            }
            j0 = j1;
            if p[j0] == 0 {
                break;
            }
        }
        loop {
            let j1 = way[j0];
            p[j0] = p[j1];
            j0 = j1;
            if j0 == 0 {
                break;
            }
        }
    }
    let mut out = vec![None; n];
    for j in 1..=m {
        if p[j] != 0 {
            out[p[j] - 1] = Some(j - 1);
        }
    }
    out
}

/// Maximum-weight assignment (e.g. on a MAC matrix): `hungarian_min` on `-weight`.
pub fn hungarian_max(weight: &[Vec<f64>]) -> Vec<Option<usize>> {
    let neg: Vec<Vec<f64>> = weight
        .iter()
        .map(|r| r.iter().map(|w| -w).collect())
        .collect();
    hungarian_min(&neg)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Brute force over all injective maps rows -> columns (reference).
    fn brute(cost: &[Vec<f64>]) -> f64 {
        fn rec(i: usize, cost: &[Vec<f64>], used: &mut Vec<bool>) -> f64 {
            if i == cost.len() {
                return 0.0;
            }
            let mut best = f64::INFINITY;
            for j in 0..cost[0].len() {
                if !used[j] {
                    used[j] = true;
                    best = best.min(cost[i][j] + rec(i + 1, cost, used));
                    used[j] = false;
                }
            }
            best
        }
        rec(0, cost, &mut vec![false; cost[0].len()])
    }

    proptest! {
        #[test]
        fn matches_brute_force(n in 1usize..5, extra in 0usize..3,
                               vals in proptest::collection::vec(-5.0f64..5.0, 64)) {
            let m = n + extra;
            let cost: Vec<Vec<f64>> = (0..n).map(|i| (0..m).map(|j| vals[i * 8 + j]).collect()).collect();
            let a = hungarian_min(&cost);
            let mut seen = vec![false; m];
            let mut total = 0.0;
            for (i, j) in a.iter().enumerate() {
                let j = j.expect("n <= m: every row assigned");
                prop_assert!(!seen[j]);
                seen[j] = true;
                total += cost[i][j];
            }
            prop_assert!((total - brute(&cost)).abs() < 1e-9);
            // Transposed (more rows than columns) gives the same optimum.
            let t: Vec<Vec<f64>> = (0..m).map(|j| (0..n).map(|i| cost[i][j]).collect()).collect();
            let at = hungarian_min(&t);
            let tot_t: f64 = at.iter().enumerate().filter_map(|(j, i)| i.map(|i| t[j][i])).sum();
            prop_assert!((tot_t - total).abs() < 1e-9);
            prop_assert_eq!(at.iter().filter(|x| x.is_some()).count(), n);
        }
    }
}

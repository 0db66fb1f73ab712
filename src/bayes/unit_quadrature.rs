//! The density of the global parameters g with units of one coordinate integrated out by
//! quadrature: log p(g) + Σ_b log ∫ p(x_b | g) L_b(x_b, g) dx_b, the integral by the midpoint
//! rule on a fixed grid per unit whose model outputs are evaluated once.
//!
//! Why not the Laplace form of `reference::GivenUnits`: where a unit's one coordinate (a
//! joint's stiffness per bolted measurement) barely moves one mode, the unit can still fit
//! that mode exactly, and the integrand is far from a Gaussian in x_b. On the fixture campaign
//! of the independent truth, the re-formed Laplace marginal of ln ε (plate-1-0) peaked at
//! ε = e^-12 by 100 nats over ε ≈ 1e-3, while this quadrature on 19,200 nodes per unit had no
//! peak there (−1027.7 against −1017.0 on the plateau the SMC posterior sits on). The base
//! reference then sat 88 of its sds from the posterior and step 2 took 39 tempering stages.
//!
//! The grid spans the unit's prior given the round's g (±`PRIOR_SDS` sd) and its optimum;
//! where the integrand is narrower than the node spacing (ε far below the data's scatter),
//! the rule underestimates it, which keeps the reference away from such ε rather than drawing
//! it there. The rule is exact to O(h²) elsewhere; its test is a linear-Gaussian unit whose
//! marginal is closed-form.

use super::smc::Target;
use super::stats::log_sum_exp;

/// Nodes per unit: the spacing is then a twelfth of the prior's sd (more where the unit's
/// optimum lies beyond the prior's ±`PRIOR_SDS` sd). For a Gaussian integrand of sd w the
/// midpoint rule's relative error is about 2 exp(−2π² w²/h²): 5e-9 at h = w, so the rule is
/// exact for any unit the data pin no tighter than a twelfth of the population's spread.
pub const NODES: usize = 120;

/// The grid's half-width in the unit prior's sds (the prior density at its edge is e^-12.5
/// of the peak's).
pub const PRIOR_SDS: f64 = 5.0;

/// One unit's grid: `nodes` midpoints spanning `lo`..`hi`.
#[derive(Clone, Copy, Debug)]
pub struct Span {
    pub lo: f64,
    pub hi: f64,
    pub nodes: usize,
}

impl Span {
    fn spacing(&self) -> f64 {
        (self.hi - self.lo) / self.nodes as f64
    }
}

/// Per unit, the grid's nodes with their model outputs, and the node spacing.
pub struct QuadratureUnits<'a, T: Target> {
    t: &'a T,
    nodes: Vec<Vec<(f64, T::Cache)>>,
    spacing: Vec<f64>,
}

impl<'a, T: Target> QuadratureUnits<'a, T> {
    /// The grids of every unit (`unit_dim` must be 1) for the prior at `g_round` and the
    /// optima `xs`: `NODES` nodes over the prior's ±`PRIOR_SDS` sd and the optimum; `None`
    /// where a unit's prior is not a normal. Returns the model evaluations made too.
    pub fn new(t: &'a T, aux: &[f64], g_round: &[f64], xs: &[Vec<f64>]) -> Option<(Self, u64)> {
        let ctx = t.ctx(g_round);
        let spans: Vec<Span> = (0..xs.len())
            .map(|b| {
                let (m, l) = t.unit_prior_normal(&ctx, b)?;
                let (m, s) = (m[0], l[0].abs());
                let lo = (m - PRIOR_SDS * s).min(xs[b][0] - 0.5 * s);
                let hi = (m + PRIOR_SDS * s).max(xs[b][0] + 0.5 * s);
                (s > 0.0 && lo.is_finite() && hi.is_finite()).then_some(Span {
                    lo,
                    hi,
                    nodes: NODES,
                })
            })
            .collect::<Option<_>>()?;
        Some(Self::with_spans(t, aux, &spans))
    }

    /// The grids on given spans (`unit_dim` must be 1), e.g. a group's units around where a
    /// base reference put them. Nodes where the model is undefined are left out (the
    /// integrand is 0 there). Returns the model evaluations made too.
    pub fn with_spans(t: &'a T, aux: &[f64], spans: &[Span]) -> (Self, u64) {
        use rayon::prelude::*;
        assert_eq!(t.unit_dim(), 1, "quadrature over units of one coordinate");
        let nodes: Vec<Vec<(f64, T::Cache)>> = spans
            .par_iter()
            .enumerate()
            .map(|(b, sp)| {
                let h = sp.spacing();
                (0..sp.nodes)
                    .filter_map(|j| {
                        let x = sp.lo + (j as f64 + 0.5) * h;
                        t.model(aux, b, &[x]).map(|c| (x, c))
                    })
                    .collect()
            })
            .collect();
        let spacing = spans.iter().map(Span::spacing).collect();
        let evals = spans.iter().map(|s| s.nodes as u64).sum();
        (QuadratureUnits { t, nodes, spacing }, evals)
    }

    /// Per unit, the mean and variance of x_b under the integrand's weights, pooled over the
    /// draws `gs` of g (law of total variance: the mean of each draw's variance plus the
    /// variance of its means). A unit's spread then carries that of the error scales, which
    /// set how tightly the data pin it (the funnel); the Laplace curvature at one g gave the
    /// bolted units of the paper-like campaign a q 5.5-6 times narrower than their posterior.
    /// No draw resolves a spread below the grid's rounding variance h²/12. `None` for a unit
    /// no draw weighs.
    pub fn unit_moments(&self, gs: &[Vec<f64>]) -> Vec<Option<(f64, f64)>> {
        let t = self.t;
        let ctxs: Vec<T::Ctx> = gs.iter().map(|g| t.ctx(g)).collect();
        self.nodes
            .iter()
            .enumerate()
            .map(|(b, ns)| {
                let per: Vec<(f64, f64)> = ctxs
                    .iter()
                    .filter_map(|ctx| {
                        let f: Vec<f64> = ns
                            .iter()
                            .map(|(x, c)| {
                                let v =
                                    t.log_prior_unit(ctx, b, &[*x]) + t.log_lik(ctx, b, &[*x], c);
                                if v.is_nan() {
                                    f64::NEG_INFINITY
                                } else {
                                    v
                                }
                            })
                            .collect();
                        let m = f.iter().copied().fold(f64::NEG_INFINITY, f64::max);
                        if !m.is_finite() {
                            return None;
                        }
                        let w: Vec<f64> = f.iter().map(|v| (v - m).exp()).collect();
                        let sw: f64 = w.iter().sum();
                        let mean = ns.iter().zip(&w).map(|((x, _), w)| x * w).sum::<f64>() / sw;
                        let var = ns
                            .iter()
                            .zip(&w)
                            .map(|((x, _), w)| (x - mean).powi(2) * w)
                            .sum::<f64>()
                            / sw;
                        Some((mean, var.max(self.spacing[b].powi(2) / 12.0)))
                    })
                    .collect();
                if per.is_empty() {
                    return None;
                }
                let n = per.len() as f64;
                let mean = per.iter().map(|p| p.0).sum::<f64>() / n;
                let var = per.iter().map(|p| p.1 + (p.0 - mean).powi(2)).sum::<f64>() / n;
                Some((mean, var))
            })
            .collect()
    }

    /// Drops every node whose log integrand is below its unit's peak by more than `nats` at
    /// each of the points `gs` of g (a unit keeps at least its best node): g's density then
    /// costs a fraction (on the paper-like campaign's bolted units, whose data pin each
    /// joint to a few nodes of the prior's grid) and changes by under e^-nats per node there.
    pub fn prune(&mut self, gs: &[Vec<f64>], nats: f64) {
        let t = self.t;
        let ctxs: Vec<T::Ctx> = gs.iter().map(|g| t.ctx(g)).collect();
        for (b, ns) in self.nodes.iter_mut().enumerate() {
            let mut keep = vec![false; ns.len()];
            for ctx in &ctxs {
                let f: Vec<f64> = ns
                    .iter()
                    .map(|(x, c)| t.log_prior_unit(ctx, b, &[*x]) + t.log_lik(ctx, b, &[*x], c))
                    .collect();
                let m = f
                    .iter()
                    .copied()
                    .filter(|v| !v.is_nan())
                    .fold(f64::NEG_INFINITY, f64::max);
                if !m.is_finite() {
                    continue;
                }
                for (k, v) in keep.iter_mut().zip(&f) {
                    *k |= *v >= m - nats;
                }
            }
            if keep.iter().any(|k| *k) {
                let mut it = keep.iter();
                ns.retain(|_| *it.next().expect("one flag per node"));
            }
        }
    }

    /// log p(g) + Σ_b log Σ_j h_b p(x_j | g) L_b(x_j, g); −∞ outside the prior's support.
    pub fn log_density(&self, g: &[f64]) -> f64 {
        let t = self.t;
        let lp = t.log_prior_global(g);
        if !lp.is_finite() {
            return f64::NEG_INFINITY;
        }
        let ctx = t.ctx(g);
        let mut s = lp;
        let mut v = Vec::with_capacity(NODES);
        for (b, ns) in self.nodes.iter().enumerate() {
            v.clear();
            v.extend(ns.iter().map(|(x, c)| {
                let f = t.log_prior_unit(&ctx, b, &[*x]) + t.log_lik(&ctx, b, &[*x], c);
                if f.is_nan() {
                    f64::NEG_INFINITY
                } else {
                    f
                }
            }));
            let l = log_sum_exp(&v);
            if l == f64::NEG_INFINITY {
                return f64::NEG_INFINITY;
            }
            s += l + self.spacing[b].ln();
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::super::smc::Target;
    use super::super::stats::{normal_lpdf, LN_2PI};
    use super::QuadratureUnits;
    use rand_chacha::ChaCha8Rng;

    /// Units x_b ~ N(μ, σ²), g = (μ, ln σ, ln ε); two "modes" y_bm = a_m x_b + e, e ~ N(0, ε²),
    /// the second barely moved by x (a = 0.01, as a joint stiffness moves plate-1-0). Given g
    /// the units integrate out in closed form: y_b ~ N(a μ, σ² a aᵀ + ε² I).
    struct Linear {
        y: Vec<[f64; 2]>,
    }
    const A: [f64; 2] = [1.0, 0.01];

    impl Linear {
        fn exact(&self, g: &[f64]) -> f64 {
            let (mu, s2, e2) = (g[0], (2.0 * g[1]).exp(), (2.0 * g[2]).exp());
            // Σ = s2 a aᵀ + e2 I (2 × 2), inverse and determinant in closed form.
            let (c00, c01, c11) = (
                s2 * A[0] * A[0] + e2,
                s2 * A[0] * A[1],
                s2 * A[1] * A[1] + e2,
            );
            let det = c00 * c11 - c01 * c01;
            self.log_prior_global(g)
                + self
                    .y
                    .iter()
                    .map(|y| {
                        let r = [y[0] - A[0] * mu, y[1] - A[1] * mu];
                        let q =
                            (c11 * r[0] * r[0] - 2.0 * c01 * r[0] * r[1] + c00 * r[1] * r[1]) / det;
                        -0.5 * (q + det.ln() + 2.0 * LN_2PI)
                    })
                    .sum::<f64>()
        }
    }

    impl Target for Linear {
        type Cache = ();
        type Ctx = [f64; 3];
        fn n_global(&self) -> usize {
            3
        }
        fn n_units(&self) -> usize {
            self.y.len()
        }
        fn unit_dim(&self) -> usize {
            1
        }
        fn sample_prior(&self, _rng: &mut ChaCha8Rng) -> (Vec<f64>, Vec<Vec<f64>>) {
            unreachable!("not sampled")
        }
        fn log_prior_global(&self, g: &[f64]) -> f64 {
            normal_lpdf(g[0], 0.0, 1.0)
                + normal_lpdf(g[1], -1.0, 1.0)
                + normal_lpdf(g[2], -3.0, 1.5)
        }
        fn ctx(&self, g: &[f64]) -> [f64; 3] {
            [g[0], g[1].exp(), g[2].exp()]
        }
        fn log_prior_unit(&self, c: &[f64; 3], _b: usize, x: &[f64]) -> f64 {
            normal_lpdf(x[0], c[0], c[1])
        }
        fn model(&self, _aux: &[f64], _b: usize, _x: &[f64]) -> Option<()> {
            Some(())
        }
        fn log_lik(&self, c: &[f64; 3], b: usize, x: &[f64], _: &()) -> f64 {
            (0..2)
                .map(|m| normal_lpdf(self.y[b][m], A[m] * x[0], c[2]))
                .sum()
        }
        fn to_standard(&self, c: &[f64; 3], _b: usize, x: &[f64]) -> Vec<f64> {
            vec![(x[0] - c[0]) / c[1]]
        }
        fn from_standard(&self, c: &[f64; 3], _b: usize, z: &[f64]) -> Vec<f64> {
            vec![c[0] + c[1] * z[0]]
        }
        fn unit_prior_normal(&self, c: &[f64; 3], _b: usize) -> Option<(Vec<f64>, Vec<f64>)> {
            Some((vec![c[0]], vec![c[1]]))
        }
    }

    /// Where the data do not pin a unit beyond its prior's spread the rule matches the closed
    /// form (to 5e-6 nats over five units); where ε is far below that (the likelihood
    /// narrower than the node spacing) it underestimates it here, so g's density there does
    /// not peak falsely (a node within a few likelihood widths of a unit's peak could
    /// overestimate that unit's term; the grid's placement does not favour it).
    /// Five units, x_b = 0.3 + 0.4 z, data with ε = 0.05; the units' optima.
    fn five_units() -> (Linear, Vec<Vec<f64>>) {
        let z = [-1.2, -0.4, 0.1, 0.7, 1.5];
        let noise = [
            [0.3, -0.8],
            [1.1, 0.2],
            [-0.5, 0.9],
            [0.0, -1.3],
            [0.6, 0.4],
        ];
        let y: Vec<[f64; 2]> = z
            .iter()
            .zip(&noise)
            .map(|(z, n)| {
                let x = 0.3 + 0.4 * z;
                [A[0] * x + 0.05 * n[0], A[1] * x + 0.05 * n[1]]
            })
            .collect();
        let xs: Vec<Vec<f64>> = z.iter().map(|z| vec![0.3 + 0.4 * z]).collect();
        (Linear { y }, xs)
    }

    /// x_b's posterior given g in closed form: prior N(μ, σ²) times y_bm ~ N(a_m x, ε²).
    fn conditional(t: &Linear, b: usize, g: &[f64]) -> (f64, f64) {
        let (mu, s2, e2) = (g[0], (2.0 * g[1]).exp(), (2.0 * g[2]).exp());
        let prec = 1.0 / s2 + A.iter().map(|a| a * a).sum::<f64>() / e2;
        let lin = mu / s2 + (0..2).map(|m| A[m] * t.y[b][m]).sum::<f64>() / e2;
        (lin / prec, 1.0 / prec)
    }

    #[test]
    fn quadrature_matches_the_closed_form_and_raises_no_needle() {
        let (t, xs) = five_units();
        let g_round = [0.3, 0.4f64.ln(), 0.05f64.ln()];
        let (q, evals) = QuadratureUnits::new(&t, &[], &g_round, &xs).expect("normal unit priors");
        assert_eq!(evals, 5 * super::NODES as u64);
        for g in [
            g_round,
            [0.2, 0.5f64.ln(), 0.08f64.ln()],
            [0.35, 0.3f64.ln(), 0.2f64.ln()],
        ] {
            let (a, b) = (q.log_density(&g), t.exact(&g));
            assert!(
                (a - b).abs() < 5e-6,
                "g {g:?}: quadrature {a} against closed form {b}"
            );
        }
        for le in [-6.0, -9.0, -12.0] {
            let g = [0.3, 0.4f64.ln(), le];
            let (a, b) = (q.log_density(&g), t.exact(&g));
            assert!(
                a <= b + 1e-9,
                "ln ε {le}: quadrature {a} above the closed form {b}"
            );
        }
    }

    /// The Laplace form's unit moments (`reference::GivenUnits::unit_moments`, the frozen
    /// quadratic, exact here for g with the round's ε): over one draw of g the closed-form
    /// conditional posterior; over two draws that differ in the population's μ and σ, the law
    /// of total variance's pooling of those.
    #[test]
    fn laplace_unit_moments_match_the_closed_form() {
        let (t, _) = five_units();
        let g_round = [0.3, 0.4f64.ln(), 0.05f64.ln()];
        let g2 = [0.1, 1.5f64.ln(), 0.05f64.ln()];
        let xs: Vec<Vec<f64>> = (0..5)
            .map(|b| vec![conditional(&t, b, &g_round).0])
            .collect();
        let precs: Vec<Vec<f64>> = (0..5)
            .map(|b| vec![1.0 / conditional(&t, b, &g_round).1])
            .collect();
        let (u, _) =
            super::super::reference::GivenUnits::new(&t, &[], &g_round, &xs, &precs, false)
                .expect("defined");
        let one = u.unit_moments(&[g_round.to_vec()]);
        let two = u.unit_moments(&[g_round.to_vec(), g2.to_vec()]);
        for b in 0..5 {
            let (m1, v1) = conditional(&t, b, &g_round);
            let (m2, v2) = conditional(&t, b, &g2);
            let (qm, qv) = one[b].clone().expect("normal prior");
            assert!(
                (qm[0] - m1).abs() < 1e-9 && (qv[0] / v1 - 1.0).abs() < 1e-9,
                "unit {b}: ({qm:?}, {qv:?}) against ({m1}, {v1})"
            );
            let mean = 0.5 * (m1 + m2);
            let var = 0.5 * (v1 + v2) + 0.25 * (m1 - m2).powi(2);
            let (qm, qv) = two[b].clone().expect("normal prior");
            assert!(
                (qm[0] - mean).abs() < 1e-9 && (qv[0] / var - 1.0).abs() < 1e-9,
                "unit {b}, two draws: ({qm:?}, {qv:?}) against ({mean}, {var})"
            );
        }
    }

    /// A unit's moments over one draw of g are its closed-form conditional posterior's; over
    /// two draws, the law of total variance's pooling of those. Pruned at g's mode and
    /// ±3 sd, the density there is unchanged, with fewer nodes.
    #[test]
    fn moments_and_pruning_against_the_closed_form() {
        let (t, xs) = five_units();
        let g_round = [0.3, 0.4f64.ln(), 0.05f64.ln()];
        let (mut q, _) = QuadratureUnits::new(&t, &[], &g_round, &xs).expect("normal unit priors");
        let g2 = [0.25, 0.3f64.ln(), 0.08f64.ln()];
        let one = q.unit_moments(&[g_round.to_vec()]);
        let two = q.unit_moments(&[g_round.to_vec(), g2.to_vec()]);
        for b in 0..5 {
            let (m1, v1) = conditional(&t, b, &g_round);
            let (m2, v2) = conditional(&t, b, &g2);
            let (qm, qv) = one[b].expect("weighed");
            assert!(
                (qm - m1).abs() < 1e-9 && (qv / v1 - 1.0).abs() < 1e-9,
                "unit {b}: ({qm}, {qv}) against ({m1}, {v1})"
            );
            let mean = 0.5 * (m1 + m2);
            let var = 0.5 * (v1 + v2) + 0.25 * (m1 - m2).powi(2);
            let (qm, qv) = two[b].expect("weighed");
            assert!(
                (qm - mean).abs() < 1e-9 && (qv / var - 1.0).abs() < 1e-9,
                "unit {b}, two draws: ({qm}, {qv}) against ({mean}, {var})"
            );
        }
        let sds = [0.05, 0.1, 0.1];
        let mut pts = vec![g_round.to_vec()];
        for k in 0..3 {
            for sign in [-3.0, 3.0] {
                let mut g = g_round.to_vec();
                g[k] += sign * sds[k];
                pts.push(g);
            }
        }
        let before: Vec<f64> = pts.iter().map(|g| q.log_density(g)).collect();
        let n_before: usize = q.nodes.iter().map(Vec::len).sum();
        q.prune(&pts, 30.0);
        let n_after: usize = q.nodes.iter().map(Vec::len).sum();
        assert!(n_after < n_before / 2, "{n_after} of {n_before} nodes kept");
        for (g, b) in pts.iter().zip(&before) {
            let a = q.log_density(g);
            assert!((a - b).abs() < 1e-9, "g {g:?}: pruned {a} against {b}");
        }
    }
}

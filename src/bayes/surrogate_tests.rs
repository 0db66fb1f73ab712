//! The unit surrogates against the ROM they stand in for, on the small step-1 problem of the
//! simulation-based calibration (coarse mesh, 3 modes, e_x and g_xy): the verified box holds
//! the polynomial to its tolerance on fresh points, the box is in ln of positive inputs, and
//! a tolerance no polynomial meets halves the box down to its floor and then refuses, and a
//! degree over the term limit is never fitted.

use super::modal;
use super::sbc_tests::ci_problem;
use super::sbc_tests::driver::{build_target, simulate_data};
use super::smc::Target;
use super::surrogate::{fit_unit, SurrogateOptions};
use super::target::ModalTarget;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// The CI problem with data simulated from one prior draw, and 300 ROM parameter vectors of
/// unit 0 around its true value (relative spread `spread` on each updated parameter).
fn problem(spread: f64) -> (ModalTarget, Vec<Vec<f64>>, Vec<f64>) {
    let mut t = build_target(&ci_problem());
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let (g, x) = t.sample_prior(&mut rng);
    t.units = simulate_data(&t, &g, &x, &mut rng).expect("the ROM tracks the prior draw");
    let eps = t.ctx(&g).eps;
    let samples = (0..300)
        .map(|_| {
            let xi: Vec<f64> = x[0]
                .iter()
                .map(|v| v + spread * (2.0 * rng.random::<f64>() - 1.0))
                .collect();
            t.values(&[], 0, &xi)
        })
        .collect();
    (t, samples, eps)
}

#[test]
fn the_surrogate_holds_its_verified_tolerance_on_fresh_points_in_its_box() {
    let (t, samples, eps) = problem(0.004);
    // Tighter than the default (0.5): the check below is then a sharp one.
    let opts = SurrogateOptions {
        tolerance_dll: 0.05,
        ..SurrogateOptions::default()
    };
    let s = fit_unit(&t, 0, &samples, &eps, &[], &opts, 11).expect("a surrogate");
    // Stiffnesses are positive: the box is in their logarithm.
    assert_eq!(s.inputs.len(), 2);
    assert!(s.log_input.iter().all(|&l| l));
    assert!(s.max_abs_dll <= opts.tolerance_dll);
    // Fresh points: perturb a sample towards the box's edge; wherever the surrogate claims
    // the point (inside its box) its log-likelihood is the ROM's to within the tolerance
    // (with a margin for points the 60 verification draws did not see).
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    let (mut inside, mut worst) = (0, 0.0f64);
    for k in 0..400 {
        let mut v = samples[k % samples.len()].clone();
        let f = 1.0 + 0.03 * (2.0 * rng.random::<f64>() - 1.0);
        v[s.inputs[k % 2]] *= f;
        let Some(ts) = s.terms(&v) else { continue };
        inside += 1;
        let p = t.predictor.predict(&v).expect("ROM");
        let tr = t.predictor.terms(&p, &t.units[0], &v);
        let dll = modal::log_lik(&t.units[0], &ts, &eps, &[])
            - modal::log_lik(&t.units[0], &tr, &eps, &[]);
        worst = worst.max(dll.abs());
    }
    assert!(inside > 200, "only {inside} of 400 points in the box");
    assert!(
        worst <= 3.0 * opts.tolerance_dll,
        "max |Δ log L| {worst:.3e}"
    );
}

#[test]
fn a_tolerance_no_polynomial_meets_halves_the_box_to_its_floor_then_refuses() {
    let (t, samples, eps) = problem(0.004);
    let opts = SurrogateOptions {
        degrees: vec![2],
        tolerance_dll: 1e-14,
        ..SurrogateOptions::default()
    };
    let e = fit_unit(&t, 0, &samples, &eps, &[], &opts, 11).expect_err("refused");
    for hw in ["10 sd", "5 sd", "2.5 sd"] {
        assert!(e.contains(hw), "{e}");
    }
    assert!(!e.contains("1.25 sd"), "{e}");
}

#[test]
fn a_degree_over_the_term_limit_is_not_fitted_and_higher_ones_are_not_tried() {
    let (t, samples, eps) = problem(0.004);
    // Two inputs: degree 2 has 6 terms, degree 3 has 10. A limit of 8 stops at degree 3.
    let opts = SurrogateOptions {
        degrees: vec![2, 3, 4],
        tolerance_dll: 1e-14,
        max_terms: 8,
        ..SurrogateOptions::default()
    };
    let e = fit_unit(&t, 0, &samples, &eps, &[], &opts, 11).expect_err("refused");
    assert!(
        e.contains("degree 3: 10 terms in 2 inputs, over the limit of 8"),
        "{e}"
    );
    assert!(!e.contains("degree 4"), "{e}");
    // Within the limit the same problem fits (the default tolerance).
    let ok = SurrogateOptions {
        max_terms: 8,
        ..SurrogateOptions::default()
    };
    let s = fit_unit(&t, 0, &samples, &eps, &[], &ok, 11).expect("a degree-2 surrogate");
    assert_eq!(s.degree, 2);
}

/// [`problem`]'s unit 0 with its surrogate and its mode subspaces, fitted with a span
/// tolerance looser than the default (1e-7): this ROM is small (r = 14), and the looser one
/// keeps the subspaces strict ones, so the checks on them are not trivially met.
fn subspace_problem() -> (
    ModalTarget,
    std::sync::Arc<super::surrogate::UnitSurrogate>,
    std::sync::Arc<super::surrogate::UnitSubspace>,
    Vec<f64>,
    super::surrogate::SubspaceOptions,
) {
    use super::surrogate::{fit_subspace, SubspaceOptions};
    use std::sync::Arc;
    let (t, samples, eps) = problem(0.004);
    let s = Arc::new(
        fit_unit(&t, 0, &samples, &eps, &[], &SurrogateOptions::default(), 11)
            .expect("a surrogate"),
    );
    let so = SubspaceOptions {
        rel_tol: 1e-5,
        max_dim_fraction: 1.0,
        ..SubspaceOptions::default()
    };
    let sub = Arc::new(fit_subspace(&t, 0, &s, &eps, &[], &so, 11).expect("a subspace"));
    (t, s, sub, eps, so)
}

/// A step-1 unit's coordinates of the parameter vector v (`Compose::Boards` inverted).
fn unit_coordinates(t: &ModalTarget, v: &[f64]) -> Vec<f64> {
    let super::target::Compose::Boards {
        updated,
        reference,
        log,
        ..
    } = &t.compose
    else {
        panic!("a step-1 target");
    };
    updated
        .iter()
        .enumerate()
        .map(|(k, &i)| {
            if log.get(k).copied().unwrap_or(false) {
                (v[i] / reference[k]).ln()
            } else {
                v[i] / reference[k] - 1.0
            }
        })
        .collect()
}

/// The subspaces of the ROM the correction solves in, one per updated mode: verified on the
/// unit's surrogate box, each smaller than the ROM, exact where its eigenvectors were taken
/// (the box's centre; to the square of its span tolerance), and within its verified
/// tolerance of the ROM's log-likelihood on fresh points in the box, through
/// [`ModalTarget::model`] itself.
#[test]
fn the_mode_subspaces_are_exact_at_their_snapshots_and_within_tolerance_in_their_box() {
    use std::sync::Arc;
    let (t, s, sub, eps, so) = subspace_problem();
    assert!(sub.max_abs_dll <= so.tolerance_dll, "{}", sub.max_abs_dll);
    let r = t.predictor.rom.dim();
    assert_eq!(sub.subs.len(), t.predictor.refs.len());
    for m in &sub.subs {
        assert!(m.sub.dim() < r, "subspace {} of {r}", m.sub.dim());
    }
    let at = |v: &[f64]| {
        let full = t.predictor.predict(v).expect("ROM");
        let local = t
            .predictor
            .predict_in_modes(&sub.subs, v)
            .expect("subspaces");
        (full, local)
    };
    let (full, local) = at(&s.point(&[0.0, 0.0]));
    for (m, (a, b)) in local.lambda.iter().zip(&full.lambda).enumerate() {
        let rel = (a - b) / b;
        // Vectors within rel_tol of the span add none: the error is of order rel_tol².
        assert!(
            rel.abs() < 100.0 * so.rel_tol.powi(2),
            "centre, mode {m}: {rel:e}"
        );
    }
    let mut target = t.clone();
    target.subspaces = vec![Some(Arc::clone(&sub))];
    let mut rng = ChaCha8Rng::seed_from_u64(13);
    let mut worst = 0.0f64;
    for _ in 0..100 {
        let u: Vec<f64> = (0..2).map(|_| 2.0 * rng.random::<f64>() - 1.0).collect();
        let v = s.point(&u);
        let (full, local) = at(&v);
        for (m, (a, b)) in local.lambda.iter().zip(&full.lambda).enumerate() {
            // Not an upper bound (the Ritz vector may lean on lower modes), but within what
            // the verified tolerance allows (|Δ log L| ≤ 1e-3 at ε = 0.004 is a relative
            // eigenvalue error of a few 1e-6).
            let rel = (a - b) / b;
            assert!(rel.abs() < 1e-4, "mode {m}: {rel:e}");
        }
        let x = unit_coordinates(&t, &v);
        let tm = target.model(&[], 0, &x).expect("subspace terms");
        let p = t.predictor.predict(&v).expect("ROM");
        let tr = t.predictor.terms(&p, &t.units[0], &v);
        let dll = modal::log_lik(&t.units[0], &tm, &eps, &[])
            - modal::log_lik(&t.units[0], &tr, &eps, &[]);
        worst = worst.max(dll.abs());
    }
    assert!(worst <= 3.0 * so.tolerance_dll, "max |Δ log L| {worst:.3e}");
    assert!(worst > 0.0, "the target did not solve in the subspace");
}

/// A surrogate with its leading input fixed (a group's step-1 draw in step 2) is the same
/// polynomial: its terms match the whole one's wherever the free input goes, and a fixed
/// value outside the box leaves no restricted polynomial.
#[test]
fn the_surrogate_with_its_leading_input_fixed_is_the_same_polynomial() {
    let (t, samples, eps) = problem(0.004);
    let s = fit_unit(&t, 0, &samples, &eps, &[], &SurrogateOptions::default(), 11)
        .expect("a surrogate");
    assert_eq!(s.inputs.len(), 2);
    assert!(s.fix_leading(0, &samples[0]).is_none());
    assert!(s.fix_leading(2, &samples[0]).is_none());
    let f = s
        .fix_leading(1, &samples[0])
        .expect("the sample is inside the box");
    let mut rng = ChaCha8Rng::seed_from_u64(13);
    let mut compared = 0;
    for _ in 0..200 {
        let mut v = samples[0].clone();
        v[s.inputs[1]] *= 1.0 + 0.03 * (2.0 * rng.random::<f64>() - 1.0);
        let (Some(a), Some(b)) = (s.terms(&v), s.terms_fixed(&f, &v)) else {
            assert!(s.terms_fixed(&f, &v).is_none(), "outside the box for both");
            continue;
        };
        compared += 1;
        for (x, y) in a.lambda.iter().zip(&b.lambda) {
            assert!((x - y).abs() <= 1e-12 * x.abs(), "λ {x} against {y}");
        }
        assert!((a.mass_g - b.mass_g).abs() <= 1e-12 * a.mass_g.abs());
    }
    assert!(compared > 100, "only {compared} points compared");
    // The leading input far outside the box: every point with it is the ROM's.
    let mut far = samples[0].clone();
    far[s.inputs[0]] *= 2.0;
    assert!(s.fix_leading(1, &far).is_none());
}

/// The correction's evaluation of a group of points together (`ModalTarget::model_shared`):
/// points that differ in one coordinate share the stiffness terms the other sets, and the
/// terms and log-likelihoods equal one point at a time to round-off; points that differ in
/// every coordinate share none and give the same too.
#[test]
fn a_group_evaluated_together_gives_each_points_own_terms() {
    use std::sync::Arc;
    let (t, s, sub, eps, _) = subspace_problem();
    let mut target = t.clone();
    target.subspaces = vec![Some(Arc::clone(&sub))];
    let unit_x = |v: &[f64]| unit_coordinates(&t, v);
    let mut rng = ChaCha8Rng::seed_from_u64(17);
    let mut u = || 1.6 * rng.random::<f64>() - 0.8;
    let x0 = unit_x(&s.point(&[u(), u()]));
    // One coordinate shared, then none.
    let one: Vec<Vec<f64>> = (0..6)
        .map(|_| {
            let x1 = unit_x(&s.point(&[0.0, u()]));
            vec![x0[0], x1[1]]
        })
        .collect();
    let both: Vec<Vec<f64>> = (0..6).map(|_| unit_x(&s.point(&[u(), u()]))).collect();
    // The first group shares some stiffness coefficients and not others: both parts of
    // the shared sum are exercised.
    let ck = |x: &[f64]| {
        t.predictor
            .rom
            .map
            .coefficient_values(&t.values(&[], 0, x))
            .0
    };
    let (a, b) = (ck(&one[0]), ck(&one[1]));
    let same = a
        .iter()
        .zip(&b)
        .filter(|(p, q)| p.to_bits() == q.to_bits())
        .count();
    assert!(same > 0 && same < a.len(), "{same} of {} shared", a.len());
    let mut solved_together = 0;
    for xs in [one, both] {
        let refs: Vec<&[f64]> = xs.iter().map(|x| x.as_slice()).collect();
        let together = target.model_shared(&[], 0, &refs);
        for (x, c) in xs.iter().zip(&together) {
            let alone = target.model(&[], 0, x).expect("terms");
            let c = c.as_ref().expect("terms together");
            let (la, lc) = (
                modal::log_lik(&t.units[0], &alone, &eps, &[]),
                modal::log_lik(&t.units[0], c, &eps, &[]),
            );
            assert!((la - lc).abs() <= 1e-9 * la.abs().max(1.0), "{la} vs {lc}");
            solved_together += 1;
        }
    }
    assert_eq!(solved_together, 12);
}

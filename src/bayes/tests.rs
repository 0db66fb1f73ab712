//! Tests of the sampler against closed forms: a linear-Gaussian hierarchical model whose
//! posterior moments and evidence are exact, and thread-count independence.

use super::smc::{self, SmcOptions, Target};
use super::stats::{cholesky_jittered, lower_solve, lower_transpose_solve, LN_2PI};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

/// y_{b,r,k} ~ N(x_{b,k}, s_k²), x_{b,k} ~ N(μ_k, τ_k²), μ_k ~ N(m_k, v_k): coordinates are
/// independent, so each is a Gaussian vector of dimension 1 + B + B·R.
struct LinearGaussian {
    m: Vec<f64>,
    v: Vec<f64>,
    tau: Vec<f64>,
    s: Vec<f64>,
    /// y[b][r][k]
    y: Vec<Vec<Vec<f64>>>,
    /// `model` calls (each one "expensive" for [`Target::expensive_evals`]).
    calls: std::sync::atomic::AtomicU64,
}

impl Target for LinearGaussian {
    type Cache = Vec<f64>;
    type Ctx = Vec<f64>;
    fn expensive_evals(&self) -> u64 {
        self.calls.load(std::sync::atomic::Ordering::Relaxed)
    }
    fn n_global(&self) -> usize {
        self.m.len()
    }
    fn n_units(&self) -> usize {
        self.y.len()
    }
    fn unit_dim(&self) -> usize {
        self.m.len()
    }
    fn sample_prior(&self, rng: &mut ChaCha8Rng) -> (Vec<f64>, Vec<Vec<f64>>) {
        let mut n = || -> f64 { StandardNormal.sample(rng) };
        let g: Vec<f64> = (0..self.m.len())
            .map(|k| self.m[k] + self.v[k].sqrt() * n())
            .collect();
        let x = (0..self.y.len())
            .map(|_| (0..g.len()).map(|k| g[k] + self.tau[k] * n()).collect())
            .collect();
        (g, x)
    }
    fn log_prior_global(&self, g: &[f64]) -> f64 {
        (0..g.len())
            .map(|k| super::stats::normal_lpdf(g[k], self.m[k], self.v[k].sqrt()))
            .sum()
    }
    fn ctx(&self, g: &[f64]) -> Vec<f64> {
        g.to_vec()
    }
    fn log_prior_unit(&self, ctx: &Vec<f64>, _b: usize, x: &[f64]) -> f64 {
        (0..x.len())
            .map(|k| super::stats::normal_lpdf(x[k], ctx[k], self.tau[k]))
            .sum()
    }
    /// The auxiliary value, when there is one, shifts every prediction (a first step's draw
    /// that moves the second step's units: the modular case).
    fn model(&self, aux: &[f64], _b: usize, x: &[f64]) -> Option<Vec<f64>> {
        self.calls
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let shift = aux.first().copied().unwrap_or(0.0);
        Some(x.iter().map(|v| v + shift).collect())
    }
    fn log_lik(&self, _ctx: &Vec<f64>, b: usize, _x: &[f64], c: &Vec<f64>) -> f64 {
        self.y[b]
            .iter()
            .map(|yr| {
                (0..c.len())
                    .map(|k| super::stats::normal_lpdf(yr[k], c[k], self.s[k]))
                    .sum::<f64>()
            })
            .sum()
    }
    fn to_standard(&self, ctx: &Vec<f64>, _b: usize, x: &[f64]) -> Vec<f64> {
        (0..x.len())
            .map(|k| (x[k] - ctx[k]) / self.tau[k])
            .collect()
    }
    fn from_standard(&self, ctx: &Vec<f64>, _b: usize, z: &[f64]) -> Vec<f64> {
        (0..z.len()).map(|k| ctx[k] + self.tau[k] * z[k]).collect()
    }
}

/// Exact posterior means and variances of (μ_k, x_{1,k} … x_{B,k}) and log p(y_k), by
/// Gaussian conditioning of the joint vector (μ, x, y) of coordinate k.
fn exact(t: &LinearGaussian, k: usize) -> (Vec<f64>, Vec<f64>, f64) {
    let nb = t.y.len();
    let nr = t.y[0].len();
    let nl = 1 + nb; // latent
    let no = nb * nr;
    let (v, tau2, s2) = (t.v[k], t.tau[k] * t.tau[k], t.s[k] * t.s[k]);
    // Latent covariance: μ ↔ everything v; x_b ↔ x_b' v + τ² δ.
    let cov_l = |i: usize, j: usize| -> f64 {
        let mut c = v;
        if i > 0 && i == j {
            c += tau2;
        }
        c
    };
    // y_{b,r} = x_b + e: cov(latent i, y_(b,r)) = cov_l(i, 1 + b).
    let unit_of = |o: usize| 1 + o / nr;
    let mut syy = vec![0.0; no * no];
    for a in 0..no {
        for b in 0..no {
            syy[a * no + b] = cov_l(unit_of(a), unit_of(b)) + if a == b { s2 } else { 0.0 };
        }
    }
    let y: Vec<f64> = (0..no).map(|o| t.y[o / nr][o % nr][k] - t.m[k]).collect();
    let (l, _) = cholesky_jittered(&syy, no);
    let w = lower_solve(&l, no, &y);
    let log_z = -0.5 * (no as f64 * LN_2PI + w.iter().map(|a| a * a).sum::<f64>())
        - (0..no).map(|i| l[i * no + i].ln()).sum::<f64>();
    // Solve Syy α = y and Syy B = Syl.
    let solve = |b: &[f64]| lower_transpose_solve(&l, no, &lower_solve(&l, no, b));
    let alpha = solve(&y);
    let mut mean = vec![0.0; nl];
    let mut var = vec![0.0; nl];
    for i in 0..nl {
        let syl: Vec<f64> = (0..no).map(|o| cov_l(i, unit_of(o))).collect();
        mean[i] = t.m[k] + syl.iter().zip(&alpha).map(|(a, b)| a * b).sum::<f64>();
        let beta = solve(&syl);
        var[i] = cov_l(i, i) - syl.iter().zip(&beta).map(|(a, b)| a * b).sum::<f64>();
    }
    (mean, var, log_z)
}

fn problem() -> LinearGaussian {
    // Data drawn once (fixed numbers so the test does not depend on a generator).
    let y = vec![
        vec![vec![0.61, -1.02], vec![0.44, -0.95], vec![0.52, -1.11]],
        vec![vec![1.35, -0.42], vec![1.21, -0.51], vec![1.30, -0.47]],
        vec![vec![0.05, -0.88], vec![0.17, -0.79], vec![0.11, -0.90]],
        vec![vec![0.92, -1.30], vec![0.80, -1.22], vec![0.87, -1.41]],
    ];
    LinearGaussian {
        m: vec![0.0, 0.0],
        v: vec![1.0, 4.0],
        tau: vec![0.5, 0.3],
        s: vec![0.08, 0.1],
        y,
        calls: Default::default(),
    }
}

#[test]
fn smc_matches_the_closed_form_hierarchical_posterior_and_evidence() {
    let t = problem();
    let opts = SmcOptions {
        n_particles: 1000,
        ..SmcOptions::default()
    };
    let results: Vec<_> = (0..8)
        .map(|r| smc::run(&t, &opts, 42, r, &|_| {}).expect("run"))
        .collect();
    assert_matches_exact(&t, &results);
}

/// A budget of expensive evaluations stops the tempering between stages with the count it
/// reached; a budget the run stays within changes nothing (the same particles and evidence).
#[test]
fn a_budget_of_expensive_evaluations_stops_the_run_and_otherwise_changes_nothing() {
    let t = problem();
    let opts = SmcOptions {
        n_particles: 200,
        ..SmcOptions::default()
    };
    let free = smc::run(&t, &opts, 42, 0, &|_| {}).expect("run");
    let used = free.stages.iter().map(|s| s.model_evals).sum::<u64>();
    let per_unit = used as f64 / (200 * t.y.len()) as f64;
    let within = SmcOptions {
        max_expensive_evals_per_particle_unit: Some(2.0 * per_unit),
        ..opts.clone()
    };
    let r = smc::run(&t, &within, 42, 0, &|_| {}).expect("within its budget");
    assert_eq!(r.log_evidence, free.log_evidence);
    assert_eq!(r.particles[0].g, free.particles[0].g);
    let tight = SmcOptions {
        max_expensive_evals_per_particle_unit: Some(0.25 * per_unit),
        ..opts
    };
    match smc::run(&t, &tight, 42, 0, &|_| {}) {
        Err(smc::SmcError::OverBudget {
            used, max, stage, ..
        }) => {
            assert!(used > max, "{used} vs {max}");
            assert!(stage >= 1 && stage < free.stages.len(), "stage {stage}");
        }
        other => panic!(
            "expected the budget's error, got {:?}",
            other.map(|r| r.log_evidence)
        ),
    }
}

/// The same from the Laplace reference of `bayes::reference` instead of the prior: still
/// exact (q is normalised), in fewer stages.
#[test]
fn smc_from_the_laplace_reference_matches_the_closed_form_in_fewer_stages() {
    let t = problem();
    let opts = SmcOptions {
        n_particles: 1000,
        ..SmcOptions::default()
    };
    let (q, info) = super::reference::laplace_reference(
        &t,
        &[],
        &super::reference::ReferenceOptions::default(),
        5,
    )
    .expect("reference");
    assert!(info.converged.iter().all(|c| *c), "{info:?}");
    let start = smc::Start::Reference(std::sync::Arc::new(q));
    let results: Vec<_> = (0..8)
        .map(|r| smc::run_with(&t, &opts, 42, r, &start, &[], &|_| {}).expect("run"))
        .collect();
    let from_prior = smc::run(&t, &opts, 42, 0, &|_| {})
        .expect("run")
        .stages
        .len();
    let from_q = results[0].stages.len();
    eprintln!("stages: from the prior {from_prior}, from the reference {from_q}");
    assert!(from_q < from_prior, "{from_q} vs {from_prior}");
    assert_matches_exact(&t, &results);
}

/// Groups carrying their own auxiliary values (a modular step): each group's target is the
/// problem with its data shifted by its value, so its units sit far from the other groups'
/// (the shifts are 5–40 posterior sd of a unit). With one reference per group, moved there
/// from the reference at the mean value by `reference_for_aux`, every group's log evidence
/// and posterior mean match the closed form of its own shifted problem, and the tempering
/// needs fewer stages than from the single reference.
#[test]
fn group_references_match_each_groups_closed_form() {
    let t = problem();
    let shifts = [-0.3, 0.0, 0.2, 0.5];
    let per_group = 500;
    let opts = SmcOptions {
        n_particles: per_group * shifts.len(),
        groups: shifts.len(),
        ..SmcOptions::default()
    };
    let aux: Vec<std::sync::Arc<Vec<f64>>> = shifts
        .iter()
        .map(|a| std::sync::Arc::new(vec![*a]))
        .collect();
    let mean_aux = [shifts.iter().sum::<f64>() / shifts.len() as f64];
    let ropts = super::reference::ReferenceOptions::default();
    let (base, _) =
        super::reference::laplace_reference(&t, &mean_aux, &ropts, 5).expect("reference");
    let refs: Vec<_> = aux
        .iter()
        .map(|a| {
            super::reference::reference_for_aux(&t, &base, a, &ropts, 2)
                .expect("group reference")
                .0
        })
        .collect();
    let grouped = smc::Start::GroupReferences(std::sync::Arc::new(refs));
    let single = smc::Start::Reference(std::sync::Arc::new(base));
    let runs = 4;
    let results: Vec<_> = (0..runs)
        .map(|r| smc::run_with(&t, &opts, 42, r, &grouped, &aux, &|_| {}).expect("run"))
        .collect();
    let from_single = smc::run_with(&t, &opts, 42, 0, &single, &aux, &|_| {})
        .expect("run")
        .stages
        .len();
    let from_groups = results[0].stages.len();
    eprintln!("stages: one reference {from_single}, group references {from_groups}");
    assert!(from_groups < from_single, "{from_groups} vs {from_single}");
    for (g, a) in shifts.iter().enumerate() {
        let mut shifted = problem();
        for yb in &mut shifted.y {
            for yr in yb.iter_mut() {
                yr.iter_mut().for_each(|v| *v -= a);
            }
        }
        let exact_z: f64 = (0..2).map(|k| exact(&shifted, k).2).sum();
        let zs: Vec<f64> = results.iter().map(|r| r.group_log_evidence[g]).collect();
        let zm = zs.iter().sum::<f64>() / runs as f64;
        let zsd = (zs.iter().map(|z| (z - zm).powi(2)).sum::<f64>() / (runs - 1) as f64).sqrt();
        assert!(
            (zm - exact_z).abs() < 4.0 * zsd / (runs as f64).sqrt() + 0.03,
            "group {g}: log Z {zm:.4} (runs {zs:?}) vs exact {exact_z:.4}"
        );
        for k in 0..2 {
            let (mean, var, _) = exact(&shifted, k);
            let ps: Vec<&smc::Particle<Vec<f64>>> = results
                .iter()
                .flat_map(|r| r.particles.iter().filter(|p| p.group == g))
                .collect();
            let n = ps.len() as f64;
            for i in 0..mean.len() {
                let get = |p: &smc::Particle<Vec<f64>>| if i == 0 { p.g[k] } else { p.x[i - 1][k] };
                let m = ps.iter().map(|p| get(p)).sum::<f64>() / n;
                // Resampled particles are correlated: a generous multiple of the naive se.
                let se = (var[i] / n).sqrt();
                assert!(
                    (m - mean[i]).abs() < 10.0 * se + 0.01 * var[i].sqrt(),
                    "group {g} coord {k} latent {i}: mean {m} vs exact {} (sd {})",
                    mean[i],
                    var[i].sqrt()
                );
            }
        }
    }
}

fn assert_matches_exact(t: &LinearGaussian, results: &[smc::RunResult<Vec<f64>>]) {
    let runs = results.len();
    let exact_log_z: f64 = (0..2).map(|k| exact(t, k).2).sum();
    let zs: Vec<f64> = results.iter().map(|r| r.log_evidence).collect();
    let zm = zs.iter().sum::<f64>() / runs as f64;
    let zsd = (zs.iter().map(|z| (z - zm).powi(2)).sum::<f64>() / (runs - 1) as f64).sqrt();
    let zse = zsd / (runs as f64).sqrt();
    assert!(
        (zm - exact_log_z).abs() < 4.0 * zse + 0.02,
        "log Z {zm:.4} ± {zse:.4} vs exact {exact_log_z:.4} (runs {zs:?})"
    );
    eprintln!("log Z: {zm:.4} ± {zse:.4} (sd across runs {zsd:.4}), exact {exact_log_z:.4}");
    assert!(zsd < 0.3, "log Z spread across runs {zsd}");
    for k in 0..2 {
        let (mean, var, _) = exact(t, k);
        for i in 0..mean.len() {
            let get = |p: &smc::Particle<Vec<f64>>| if i == 0 { p.g[k] } else { p.x[i - 1][k] };
            let per_run: Vec<(f64, f64)> = results
                .iter()
                .map(|r| {
                    let n = r.particles.len() as f64;
                    let m = r.particles.iter().map(get).sum::<f64>() / n;
                    let v = r
                        .particles
                        .iter()
                        .map(|p| (get(p) - m).powi(2))
                        .sum::<f64>()
                        / n;
                    (m, v)
                })
                .collect();
            let m = per_run.iter().map(|a| a.0).sum::<f64>() / runs as f64;
            let v = per_run.iter().map(|a| a.1).sum::<f64>() / runs as f64;
            let se = (per_run.iter().map(|a| (a.0 - m).powi(2)).sum::<f64>()
                / (runs - 1) as f64
                / runs as f64)
                .sqrt();
            assert!(
                (m - mean[i]).abs() < 4.0 * se + 0.01 * var[i].sqrt(),
                "coord {k} latent {i}: mean {m} ± {se} vs exact {}",
                mean[i]
            );
            assert!(
                (v / var[i] - 1.0).abs() < 0.1,
                "coord {k} latent {i}: variance {v} vs exact {}",
                var[i]
            );
        }
    }
}

#[test]
fn same_seed_gives_the_same_particles_on_any_thread_count() {
    let t = problem();
    let opts = SmcOptions {
        n_particles: 200,
        ..SmcOptions::default()
    };
    let go = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("pool");
        pool.install(|| smc::run(&t, &opts, 9, 0, &|_| {}).expect("run"))
    };
    let (a, b) = (go(1), go(3));
    assert_eq!(a.log_evidence.to_bits(), b.log_evidence.to_bits());
    for (p, q) in a.particles.iter().zip(&b.particles) {
        assert_eq!(p.g, q.g);
        assert_eq!(p.x, q.x);
    }
    let c = smc::run(&t, &opts, 10, 0, &|_| {}).expect("run");
    assert_ne!(a.log_evidence, c.log_evidence);
}

/// The linear-Gaussian target whose model counts as expensive on one side of the space
/// (x_{b,0} > 0.5, where most boards' posteriors lie), with a deliberately wrong stand-in
/// there (shifted by 0.05 and stretched by 10 %, far beyond the data's noise): the
/// delayed-acceptance moves must still sample the exact posterior.
struct Screened(LinearGaussian);

impl Target for Screened {
    type Cache = Vec<f64>;
    type Ctx = Vec<f64>;
    fn n_global(&self) -> usize {
        self.0.n_global()
    }
    fn n_units(&self) -> usize {
        self.0.n_units()
    }
    fn unit_dim(&self) -> usize {
        self.0.unit_dim()
    }
    fn sample_prior(&self, rng: &mut ChaCha8Rng) -> (Vec<f64>, Vec<Vec<f64>>) {
        self.0.sample_prior(rng)
    }
    fn log_prior_global(&self, g: &[f64]) -> f64 {
        self.0.log_prior_global(g)
    }
    fn ctx(&self, g: &[f64]) -> Vec<f64> {
        self.0.ctx(g)
    }
    fn log_prior_unit(&self, ctx: &Vec<f64>, b: usize, x: &[f64]) -> f64 {
        self.0.log_prior_unit(ctx, b, x)
    }
    fn model(&self, aux: &[f64], b: usize, x: &[f64]) -> Option<Vec<f64>> {
        self.0.model(aux, b, x)
    }
    fn log_lik(&self, ctx: &Vec<f64>, b: usize, x: &[f64], c: &Vec<f64>) -> f64 {
        self.0.log_lik(ctx, b, x, c)
    }
    fn to_standard(&self, ctx: &Vec<f64>, b: usize, x: &[f64]) -> Vec<f64> {
        self.0.to_standard(ctx, b, x)
    }
    fn from_standard(&self, ctx: &Vec<f64>, b: usize, z: &[f64]) -> Vec<f64> {
        self.0.from_standard(ctx, b, z)
    }
    fn screen(&self, _aux: &[f64], _b: usize, x: &[f64]) -> Option<Vec<f64>> {
        (x[0] > 0.5).then(|| x.iter().map(|v| 1.1 * v + 0.05).collect())
    }
}

#[test]
fn delayed_acceptance_with_a_wrong_screen_still_matches_the_closed_form() {
    let t = Screened(problem());
    let opts = SmcOptions {
        n_particles: 1000,
        ..SmcOptions::default()
    };
    let results: Vec<_> = (0..8)
        .map(|r| smc::run(&t, &opts, 42, r, &|_| {}).expect("run"))
        .collect();
    let screened: u64 = results
        .iter()
        .flat_map(|r| &r.stages)
        .map(|s| s.screened_out)
        .sum();
    let evals: u64 = results
        .iter()
        .flat_map(|r| &r.stages)
        .map(|s| s.model_evals)
        .sum();
    eprintln!("delayed acceptance: {screened} proposals screened out, {evals} model evaluations");
    assert!(screened > 0, "the screen never rejected a proposal");
    assert_matches_exact(&t.0, &results);
}

/// A likelihood of (near) zero noise — the replicates disagree by 0.1 at a noise sd of 1e-9,
/// so log L spans ~1e16 over the prior — leaves the weights degenerate at every step the
/// bisection can resolve. The sampler must stop with `Stalled` after `STALLED_STAGES`
/// stages, not creep on by Δβ ≈ 1e-12 a stage.
#[test]
fn degenerate_weights_stop_the_tempering_with_a_clear_error() {
    let mut t = problem();
    t.s = vec![1e-9, 1e-9];
    let opts = SmcOptions {
        n_particles: 200,
        ..SmcOptions::default()
    };
    match smc::run(&t, &opts, 7, 0, &|_| {}) {
        Err(e @ smc::SmcError::Stalled { stage, stalled, .. }) => {
            eprintln!("{e}");
            assert_eq!(stalled, smc::STALLED_STAGES);
            assert_eq!(stage, smc::STALLED_STAGES);
            assert!(e.to_string().contains("stalled"), "{e}");
        }
        Err(e) => panic!("expected Stalled, got {e}"),
        Ok(r) => panic!(
            "expected Stalled, reached β = 1 in {} stages",
            r.stages.len()
        ),
    }
}

/// A reference of near-zero spread (what a runaway ascent to ε → 0 leaves) or of an absurd
/// one is flagged, with the coordinate named; the Laplace reference of the closed-form problem is not.
#[test]
fn a_reference_of_zero_spread_is_flagged_degenerate() {
    use super::reference::{GaussianReference, Mvn};
    let t = problem();
    let (q, _) = super::reference::laplace_reference(
        &t,
        &[],
        &super::reference::ReferenceOptions::default(),
        5,
    )
    .expect("reference");
    assert_eq!(q.degeneracy(), None);
    let mut bad: GaussianReference = q.clone();
    bad.units[2] = Mvn::new(vec![-75.0, 0.3], &[1e-30, 0.0, 0.0, 1e-2]);
    let why = bad.degeneracy().expect("degenerate");
    assert!(why.contains("unit 2 coordinate 0"), "{why}");
    // The wide kind: a re-formed quadratic of the wrong curvature sign (unit sd 1.3e154 on
    // the blind rotation campaign), far beyond any population's spread.
    let mut wide: GaussianReference = q.clone();
    wide.units[1] = Mvn::new(vec![0.1, 0.3], &[1e-2, 0.0, 0.0, 1.7e308]);
    let why = wide.degeneracy().expect("degenerate");
    assert!(why.contains("unit 1 coordinate 1"), "{why}");
    let mut nan = q;
    nan.global.mean[1] = f64::NAN;
    assert!(nan
        .degeneracy()
        .expect("degenerate")
        .contains("global coordinate 1"));
}

/// A reference refitted to a pilot run's moments (`reference::pilot_reference`) is still a
/// normalised q: tempering from it matches the closed form, in no more stages than from the
/// Laplace reference it was refined from.
#[test]
fn smc_from_a_pilot_refined_reference_matches_the_closed_form() {
    let t = problem();
    let opts = SmcOptions {
        n_particles: 1000,
        ..SmcOptions::default()
    };
    let (q, _) = super::reference::laplace_reference(
        &t,
        &[],
        &super::reference::ReferenceOptions::default(),
        5,
    )
    .expect("reference");
    let (pilot, pilot_stages) =
        super::reference::pilot_reference(&t, &q, &opts, 300, 1.1, 11).expect("pilot");
    assert!(pilot_stages >= 1);
    assert_eq!(pilot.degeneracy(), None);
    let from_laplace = smc::run_with(
        &t,
        &opts,
        42,
        0,
        &smc::Start::Reference(std::sync::Arc::new(q)),
        &[],
        &|_| {},
    )
    .expect("run")
    .stages
    .len();
    let start = smc::Start::Reference(std::sync::Arc::new(pilot));
    let results: Vec<_> = (0..8)
        .map(|r| smc::run_with(&t, &opts, 42, r, &start, &[], &|_| {}).expect("run"))
        .collect();
    let from_pilot = results[0].stages.len();
    eprintln!("stages: from the Laplace reference {from_laplace}, from the pilot's {from_pilot}");
    assert!(from_pilot <= from_laplace, "{from_pilot} vs {from_laplace}");
    assert_matches_exact(&t, &results);
}

/// The stopping rule on a coordinate whose correlation decays geometrically, ρ_t = 0.8^t
/// (0.8^11 = 0.086 is the first at or below the target 0.1): read directly where the noise
/// floor is low, and extrapolated from its last clear reading where the floor hides
/// everything below 0.4; both stop at sweep 11. Raising the target to the floor instead
/// (the rule before) would stop at sweep 8, where ρ = 0.17.
#[test]
fn decorrelation_rule_extrapolates_below_the_noise_floor() {
    let stop_at = |n_eff: f64| {
        let mut rule = smc::Decorrelation::new(0.1, 2, n_eff);
        (1..100)
            .find(|&t| rule.update(t, &[Some(0.8f64.powi(t as i32)), Some(0.0)]))
            .unwrap()
    };
    // Floor √(2 ln 2 / n_eff): 0.012 at 10⁴ distinct starts, 0.2 at 35.
    assert_eq!(stop_at(1e4), 11);
    assert_eq!(stop_at(2.0 * 2f64.ln() / 0.04), 11);
}

//! Simulation-based calibration (SBC; Talts, Betancourt, Simpson, Vehtari & Gelman 2018) of
//! the step-1 modal target on a ROM, shared by the CI test (`bayes::sbc_tests`) and the
//! benchmark (`benches/sbc.rs`), which both include this file with `#[path]`. It names every
//! import through `super::*`, so the same text compiles inside the library (crate paths) and
//! in the benchmark (`hbmu::` paths); it uses the public API only.
//!
//! One replication: draw (g, x) from the prior of the target, simulate the data through the
//! ROM from exactly the likelihood the sampler uses, run one SMC on those data, and record,
//! for each scalar quantity, the rank of the true value among L posterior draws (L + 1
//! possible ranks). If the sampler draws from the exact posterior, every rank is uniform on
//! {0, …, L} (Talts et al., Theorem 1); the ranks over replications are tested with a
//! chi-square test on equal-width bins.
//!
//! - Draws: the SMC's final particles (equally weighted, after resampling and mutation at
//!   β = 1), thinned to L evenly spaced indices. The particles come out of systematic
//!   resampling in ancestor order, so evenly spaced indices spread over the ancestors.
//! - Ties: a draw equal to the truth (a particle whose moves were all refused keeps a
//!   duplicate of its ancestor) counts below the truth with a randomised tie-break: the
//!   rank is (draws < truth) + U{0, …, draws == truth}, from the replication's seeded RNG.
//! - Eigenvalue data: the likelihood's eigenvalue term has the data-scaled standard
//!   deviation ε λ̂ (see `bayes::modal`), i.e. the density of λ̂ given λ is
//!   ∝ N(λ̂; λ, (ε λ̂)²). In w = λ/λ̂ that density is ∝ N(w; 1, ε²)/w, which we draw exactly
//!   by rejection: w ~ N(1, ε²) restricted to w ≥ 1 − 8ε, accepted with probability
//!   (1 − 8ε)/w (the envelope drops 8-sigma tails, mass < 1e-15). Its normaliser is
//!   E[1/w] ≈ 1 + ε², which the sampler's likelihood leaves out: an O(n ε²) tilt of the ε
//!   posterior (n eigenvalue terms), about 1e-2 nats here, far below what 100 or 1000
//!   replications can see.

use super::*;

/// The SBC problem: a small step-1 model.
#[derive(Clone, Debug)]
pub struct Problem {
    /// Boards (units).
    pub boards: usize,
    /// Measurements per board (each gives one eigenvalue per updated mode).
    pub measurements: usize,
    /// Updated elastic modes, 0-based model order.
    pub modes: Vec<usize>,
    /// Updated parameters (relative deviations from the board file's nominal values).
    pub params: Vec<&'static str>,
    /// FE mesh of the default board (elements along x, y).
    pub mesh: (usize, usize),
    /// ROM basis cap.
    pub max_basis: usize,
    /// ROM snapshot points besides centre and axis ends.
    pub rom_random: usize,
    /// Population prior: sd of μ, half-normal scale of σ, LKJ η (relative units).
    pub mu_sd: f64,
    pub sigma_scale: f64,
    /// σ's prior family (the update's default: half-normal).
    pub sigma_prior: SigmaPrior,
    pub lkj_eta: f64,
    /// Prior of the relative eigenvalue errors ε.
    pub eps: ErrorPrior,
}

/// The step-1 target of `p` with empty data slots (λ̂ = NaN until [`simulate`] fills them).
pub fn build_target(p: &Problem) -> ModalTarget {
    // The built-in board as a thin plate: the SBC checks the sampler, and the thin plate's
    // ROM is the smaller one (`data/boards/paper_thin.toml`).
    let mut board = Board::from_toml_str(include_str!("../../data/boards/paper_thin.toml"))
        .expect("data/boards/paper_thin.toml parses");
    board.mesh = MeshOptions {
        nx: p.mesh.0,
        ny: p.mesh.1,
    };
    let model = FeModel::build(&board, Setup::Free, &board.mesh).expect("FE model");
    let n_track = p.modes.iter().copied().max().unwrap_or(0) + 3;
    let rom = Rom::build(
        &model,
        &RomOptions {
            n_modes: n_track,
            n_random: p.rom_random,
            max_basis: p.max_basis,
            ..RomOptions::default()
        },
    )
    .expect("ROM");
    let nominal = model.nominal_params();
    let updated: Vec<usize> = p
        .params
        .iter()
        .map(|n| nominal.position(n).expect("parameter of the model"))
        .collect();
    let reference = updated.iter().map(|&i| nominal.values[i]).collect();
    let mass_g = model.total_mass_kg(&nominal).expect("mass") * 1e3;
    let predictor = ModalPredictor::new(rom, &p.modes, mass_g).expect("predictor");
    let d = p.params.len();
    let unit = UnitData {
        freq: (0..p.measurements)
            .flat_map(|_| (0..p.modes.len()).map(|m| FreqObs::new(m, f64::NAN)))
            .collect(),
        ..UnitData::default()
    };
    ModalTarget {
        predictor,
        compose: Compose::Boards {
            updated,
            reference,
            log: vec![],
            per_mass: None,
            total_mass: None,
        },
        prior: PopulationPrior {
            mu_mean: vec![0.0; d],
            mu_sd: vec![p.mu_sd; d],
            sigma_scale: vec![p.sigma_scale; d],
            sigma_prior: vec![p.sigma_prior; d],
            lkj_eta: p.lkj_eta,
            lkj_log_norm: Default::default(),
        },
        errors: ErrorModel {
            n_modes: p.modes.len(),
            eps: p.eps,
            delta: None,
            model_error_sd: None,
            discrepancy: None,
        },
        units: vec![unit; p.boards],
        covariate: None,
        subspaces: vec![],
        coord_obs: vec![],
    }
}

/// Names of the scalar quantities whose ranks are tested.
pub fn quantity_names(t: &ModalTarget, params: &[&str]) -> Vec<String> {
    let mut out: Vec<String> = params.iter().map(|p| format!("mu_{p}")).collect();
    out.push(format!("log_sigma_{}", params[0]));
    out.push(format!("board0_{}", params[0]));
    if let ErrorPrior::Inferred { .. } = t.errors.eps {
        out.push("log_eps_mode0".into());
    }
    out
}

/// The quantities of [`quantity_names`] at (g, x): population means μ_k, ln σ₀, board 0's
/// first parameter, ln ε of the first mode (when inferred); all on the sampler's scale.
pub fn quantities(t: &ModalTarget, g: &[f64], x: &[Vec<f64>]) -> Vec<f64> {
    let d = t.prior.d();
    let mut out: Vec<f64> = g[..d].to_vec();
    out.push(g[d]);
    out.push(x[0][0]);
    if let ErrorPrior::Inferred { .. } = t.errors.eps {
        out.push(g[t.prior.dim()]);
    }
    out
}

/// A draw of the data from the model at (g, x): λ̂ from the density the likelihood implies
/// (see the module doc). `None` when the ROM cannot be evaluated at x (a draw outside the
/// model's domain).
pub fn simulate_data(
    t: &ModalTarget,
    g: &[f64],
    x: &[Vec<f64>],
    rng: &mut ChaCha8Rng,
) -> Option<Vec<UnitData>> {
    let (eps, _) = t.errors.unpack(&g[t.prior.dim()..]);
    let mut units = t.units.clone();
    for (b, u) in units.iter_mut().enumerate() {
        let v = t.values(&[], b, &x[b]);
        let pred = t.predictor.predict(&v)?;
        for f in &mut u.freq {
            let e = eps[f.mode];
            let lo = 1.0 - 8.0 * e;
            let w = loop {
                let z: f64 = StandardNormal.sample(rng);
                let w = 1.0 + e * z;
                let u: f64 = rng.random();
                if w >= lo && u * w <= lo {
                    break w;
                }
            };
            *f = FreqObs::new(f.mode, pred.lambda[f.mode] / w);
        }
    }
    Some(units)
}

/// Ranks of all replications.
#[derive(Clone, Debug)]
pub struct Sbc {
    pub names: Vec<String>,
    /// ranks[q][rep] in 0..=draws.
    pub ranks: Vec<Vec<usize>>,
    /// Posterior draws per replication (L); ranks take L + 1 values.
    pub draws: usize,
    /// Tempering stages of every replication.
    pub stages: Vec<usize>,
    /// Prior draws that had to be redrawn because the ROM could not be evaluated there.
    pub redrawn: usize,
}

/// Rank of `truth` among `draws`, ties broken uniformly at random.
pub fn rank(truth: f64, draws: &[f64], rng: &mut ChaCha8Rng) -> usize {
    let below = draws.iter().filter(|&&d| d < truth).count();
    let equal = draws.iter().filter(|&&d| d == truth).count();
    below + rng.random_range(0..=equal)
}

/// Run `reps` replications. The data come from `sim` (its prior and likelihood); the
/// sampler runs on `fit(sim with the simulated data)`: the identity for a calibration check,
/// a deliberately different model to show that the check can fail. Replications run in
/// parallel, each from its own seeds, so the result does not depend on the thread count.
pub fn run_sbc(
    sim: &ModalTarget,
    fit: &(dyn Fn(ModalTarget) -> ModalTarget + Sync),
    names: Vec<String>,
    opts: &SmcOptions,
    reps: usize,
    draws: usize,
    seed: u64,
) -> Sbc {
    assert!((1..=opts.n_particles).contains(&draws));
    let per_rep: Vec<(Vec<usize>, usize, usize)> = (0..reps)
        .into_par_iter()
        .map(|rep| {
            let mut rng = ChaCha8Rng::seed_from_u64(
                seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ (rep as u64).wrapping_add(1),
            );
            let mut redrawn = 0;
            let (g, x, units) = loop {
                let (g, x) = sim.sample_prior(&mut rng);
                match simulate_data(sim, &g, &x, &mut rng) {
                    Some(u) => break (g, x, u),
                    None => redrawn += 1,
                }
            };
            let truth = quantities(sim, &g, &x);
            let mut t = sim.clone();
            t.units = units;
            let t = fit(t);
            let res = smc::run(&t, opts, seed ^ 0x5BC0_5BC0, rep, &|_| {})
                .unwrap_or_else(|e| panic!("SBC replication {rep}: {e}"));
            let n = res.particles.len();
            let picked: Vec<Vec<f64>> = (0..draws)
                .map(|k| {
                    let p = &res.particles[k * n / draws];
                    quantities(&t, &p.g, &p.x)
                })
                .collect();
            let ranks = (0..truth.len())
                .map(|q| {
                    let col: Vec<f64> = picked.iter().map(|v| v[q]).collect();
                    rank(truth[q], &col, &mut rng)
                })
                .collect();
            (ranks, res.stages.len(), redrawn)
        })
        .collect();
    let nq = names.len();
    Sbc {
        ranks: (0..nq)
            .map(|q| per_rep.iter().map(|r| r.0[q]).collect())
            .collect(),
        names,
        draws,
        stages: per_rep.iter().map(|r| r.1).collect(),
        redrawn: per_rep.iter().map(|r| r.2).sum(),
    }
}

/// Upper tail P(X² ≥ x) of the chi-square distribution with an even number of degrees of
/// freedom k: the closed form e^{−x/2} Σ_{i<k/2} (x/2)^i / i! (a Poisson tail), exact; the
/// bins are chosen so that k is even, so no incomplete-gamma routine is needed.
pub fn chi2_sf_even(x: f64, k: usize) -> f64 {
    assert!(
        k >= 2 && k.is_multiple_of(2),
        "even degrees of freedom expected, found {k}"
    );
    let h = 0.5 * x.max(0.0);
    let mut term = 1.0;
    let mut sum = 1.0;
    for i in 1..k / 2 {
        term *= h / i as f64;
        sum += term;
    }
    ((-h).exp() * sum).min(1.0)
}

/// Chi-square test of uniformity of ranks in 0..n_ranks over `bins` equal-width bins
/// (n_ranks must be a multiple of bins, bins − 1 even): (statistic, p-value, counts).
pub fn chi2_uniform(ranks: &[usize], n_ranks: usize, bins: usize) -> (f64, f64, Vec<usize>) {
    assert!(
        n_ranks.is_multiple_of(bins),
        "{n_ranks} ranks do not fall into {bins} equal bins"
    );
    let w = n_ranks / bins;
    let mut counts = vec![0usize; bins];
    for &r in ranks {
        counts[r / w] += 1;
    }
    let e = ranks.len() as f64 / bins as f64;
    let stat: f64 = counts
        .iter()
        .map(|&c| (c as f64 - e) * (c as f64 - e) / e)
        .sum();
    (stat, chi2_sf_even(stat, bins - 1), counts)
}

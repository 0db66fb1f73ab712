//! Monte Carlo propagation of the hierarchical posterior to predicted eigenfrequencies.
//!
//! Per propagation draw d (its own ChaCha8 stream `d` of the seed, so the result does not
//! depend on the thread count or on the order in which draws run):
//! 1. a step-1 particle i is picked uniformly (the SMC's final particles carry equal weights);
//! 2. **new board, free-free**: θ = μ + diag(σ) L z, z ~ N(0, I), L Lᵀ = Ω (the population's
//!    correlation), μ, σ, Ω of particle i;
//! 3. **each measured board, free-free**: θ_b of particle i;
//! 4. with a step-2 posterior: a step-2 particle j is picked uniformly; it carries the step-1
//!    draw (cut posterior) whose boards and population are used; a **new joint** ln k ~
//!    N(μ_lnK, σ_lnK) of particle j is drawn, and every measured board and a new board (drawn
//!    as in 2, from the carried step-1 population) are evaluated bolted with it.
//!
//! Every evaluation gives the model frequency f of every label (modes tracked by their overlap
//! with the label's reduced vector at the ROM centre, as the updating does) and a predicted
//! *measurement* f_obs: λ_obs = λ (1 + ε z), z ~ N(0, 1), the likelihood's relative eigenvalue
//! error ε of that label at the same particle (Vanik–Beck–Au). A label that was not updated
//! (a validation mode) has no inferred ε of its own: the modes' errors are treated as
//! exchangeable draws from a log-normal population, whose parameters are the mean and sample
//! standard deviation of ln ε over the updated labels of the same setup at that particle, and a
//! new ε is drawn from it per evaluation ([`pooled_eps`]); its rows say so (`eps_pooled`).
//! Where the label's own repeat measurements give its measurement repeatability (the pooled
//! within-board scatter, [`repeatability_eps`]; set with [`LabelModel::with_repeatability`]),
//! ε is the larger of the two: a mode that the test resolves worse than the updated ones (near
//! a nodal line of the excitation, say) has a larger error than theirs, and its replicates
//! show it without using where the mode lies (the model's prediction is still what the
//! validation checks).
//!
//! The model-error term of step 1 (`bayes::target::ErrorModel::model_error_sd`, a relative
//! eigenvalue error b ~ N(0, s²) common to a board's measurements of a mode and independent
//! between boards): f_obs gets λ (1 + b)(1 + ε z) with b drawn from that prior for a new board
//! (every label) and for a measured board's labels that were not updated. A measured board's
//! updated label keeps b = 0: its own measurements have fixed b together with the board's
//! parameters, and b's prior spread added again would widen what the data already settled.
//!
//! The model-form discrepancy of each step ([`Discrepancy`], `bayes::discrepancy`): every
//! evaluation's eigenvalue of a label is λ (1 + d), d the particle's discrepancy of the label
//! (common to every board, new or measured), or for a label the step did not update a draw
//! from N(0, τ²) at the particle's scale τ. It enters f_obs only; f stays the model's. Its
//! per-unit part σ_u joins the model-error term b where b is drawn: a new board, a validation
//! label, and (with σ_u) every bolted prediction, whose mounting is new. A measured board's
//! updated label takes the board's own offset from the model instead, where the stage gives
//! it ([`Posterior::board_offsets`]): its measurements fixed both parts, and the offset's
//! prior is the common d with the per-unit sd about it.
//!
//! Parameters outside the admissible region (non-positive moduli, ν² E_y/E_x ≥ 1) or where a
//! label cannot be tracked give no row; they are counted in [`Counts`], never dropped
//! silently. Draws outside the ROM's verified box are evaluated and counted.

use crate::fem::rom::Rom;
use crate::fem::FemError;
use faer::{Mat, Side};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use rayon::prelude::*;

/// A ROM with the labels it predicts: each label's reference reduced vector at the centre.
#[derive(Clone, Debug)]
pub struct LabelModel {
    pub rom: Rom,
    /// Labels, in the order of `refs`.
    pub labels: Vec<String>,
    /// Unit reference vectors of the labels at the ROM centre.
    refs: Vec<Vec<f64>>,
    /// Modes computed per evaluation (the highest reference plus a margin for swaps).
    n_track: usize,
    /// Half-width of the ROM's verified box, relative to its centre.
    pub box_rel: f64,
    /// Per parameter, the half-width in ln p of a logarithmic axis of the box, or `None` for a
    /// ±`box_rel` one.
    log_box: Vec<Option<f64>>,
    /// Per label, the relative eigenvalue error its repeat measurements show
    /// ([`repeatability_eps`]); used for labels without an inferred ε.
    pub repeatability_eps: Vec<Option<f64>>,
    /// Per label, the prior sd s of the model-error term (0: none).
    pub model_error_sd: Vec<f64>,
}

impl LabelModel {
    /// `modes[l]`: the 0-based ROM mode at the centre that label `labels[l]` pairs with. The
    /// box is the one the ROM was built over ([`Rom::built_box`]: an update step that widened
    /// its box or its shear modulus's axis built its ROM over the wider one); for a ROM that
    /// does not record it, ±`box_rel` with the model's own logarithmic axes
    /// ([`crate::fem::rom::with_own_log_axes`]).
    pub fn new(
        rom: Rom,
        labels: Vec<String>,
        modes: &[usize],
        box_rel: f64,
    ) -> Result<LabelModel, FemError> {
        if labels.len() != modes.len() {
            return Err(FemError::Request(format!(
                "expected one model mode per label, found {} labels and {} modes",
                labels.len(),
                modes.len()
            )));
        }
        if let Some(m) = modes.iter().find(|m| **m >= rom.n_modes) {
            return Err(FemError::Request(format!(
                "model mode {} is beyond the ROM's {} modes",
                m + 1,
                rom.n_modes
            )));
        }
        let n_track = (modes.iter().copied().max().unwrap_or(0) + 3).min(rom.n_modes);
        let c = rom.map.coefficients_unchecked(&rom.map.nominal);
        let centre = rom.eval_lowest(&c.k, &c.m, n_track)?;
        let refs = modes
            .iter()
            .map(|&j| {
                let v = &centre.vectors[j];
                let n = v.iter().map(|a| a * a).sum::<f64>().sqrt();
                v.iter().map(|a| a / n).collect()
            })
            .collect();
        let n = labels.len();
        let (box_rel, axes) = match &rom.built_box {
            Some(b) => (b.box_rel, b.log_axes.clone()),
            None => (box_rel, crate::fem::rom::with_own_log_axes(&rom.map, &[])),
        };
        let log_box = rom
            .map
            .names
            .iter()
            .map(|p| axes.iter().find(|(a, _)| a == p).map(|(_, w)| *w))
            .collect();
        Ok(LabelModel {
            rom,
            labels,
            refs,
            n_track,
            box_rel,
            log_box,
            repeatability_eps: vec![None; n],
            model_error_sd: vec![0.0; n],
        })
    }

    /// Set the model-error term's prior sd per label (order of `labels`; 0: none).
    pub fn with_model_error(mut self, sd: Vec<f64>) -> Result<LabelModel, FemError> {
        if sd.len() != self.labels.len() || sd.iter().any(|v| !(v.is_finite() && *v >= 0.0)) {
            return Err(FemError::Request(format!(
                "model error: expected one finite sd ≥ 0 per label ({}), found {:?}",
                self.labels.len(),
                sd
            )));
        }
        self.model_error_sd = sd;
        Ok(self)
    }

    /// Set the repeatability ε per label (order of `labels`; extra or missing entries are an
    /// error).
    pub fn with_repeatability(mut self, eps: Vec<Option<f64>>) -> Result<LabelModel, FemError> {
        if eps.len() != self.labels.len() {
            return Err(FemError::Request(format!(
                "repeatability: expected one entry per label ({}), found {}",
                self.labels.len(),
                eps.len()
            )));
        }
        self.repeatability_eps = eps;
        Ok(self)
    }

    /// Eigenvalues λ = ω² (rad²/s²) of every label at the full parameter vector `values`;
    /// `None` where the parameters are inadmissible or a label cannot be tracked
    /// ([`crate::bayes::modal::assign_labels`]).
    pub fn eigenvalues(&self, values: &[f64]) -> Option<Vec<f64>> {
        let map = &self.rom.map;
        if !crate::bayes::modal::admissible(map, values) {
            return None;
        }
        let (ck, cm) = map.coefficient_values(values);
        let modes = self.rom.eval_lowest(&ck, &cm, self.n_track).ok()?;
        crate::bayes::modal::assign_labels(&self.refs, &modes.vectors)
            .into_iter()
            .map(|a| a.map(|j| modes.eigenvalues[j]))
            .collect::<Option<Vec<f64>>>()
    }

    /// The box in words: "±20 % (g_z_pa × or ÷ 2.00)".
    pub fn box_description(&self) -> String {
        let logs: Vec<String> = self
            .rom
            .map
            .names
            .iter()
            .zip(&self.log_box)
            .filter_map(|(n, w)| w.map(|w| format!("{n} × or ÷ {:.2}", w.exp())))
            .collect();
        if logs.is_empty() {
            format!("±{:.0} %", 100.0 * self.box_rel)
        } else {
            format!("±{:.0} % ({})", 100.0 * self.box_rel, logs.join(", "))
        }
    }

    /// True when every parameter lies inside the ROM's box around its centre.
    pub fn inside_box(&self, values: &[f64]) -> bool {
        self.rom
            .map
            .nominal
            .iter()
            .zip(values)
            .zip(&self.log_box)
            .all(|((c, v), w)| match w {
                _ if *c == 0.0 => true,
                Some(w) => (v / c).ln().abs() <= w * (1.0 + 1e-12),
                None => ((v - c) / c).abs() <= self.box_rel * (1.0 + 1e-12),
            })
    }
}

/// Population hyperparameters of one particle, in physical units of the parameters.
#[derive(Clone, Debug)]
pub struct Population {
    pub mu: Vec<f64>,
    pub sigma: Vec<f64>,
    /// Correlation matrix Ω, d × d row-major.
    pub corr: Vec<f64>,
}

/// One step-1 particle.
#[derive(Clone, Debug)]
pub struct Step1Particle {
    pub population: Population,
    /// Per measured board (order of [`Posterior::board_ids`]), the updated parameters.
    pub boards: Vec<Vec<f64>>,
    /// Relative eigenvalue error ε per free label (order of the free [`LabelModel`]'s
    /// labels); `None` where the label was not updated.
    pub eps: Vec<Option<f64>>,
    /// The model-form discrepancy of step 1 ([`Discrepancy`]).
    pub discrepancy: Discrepancy,
}

/// A particle's model-form discrepancy of one setup (`bayes::discrepancy`): d per label
/// (relative eigenvalue, common to every board; `None` where the label was not updated) and
/// its scale τ (`None`: the step ran without one; every d is then 0). A label without its own
/// d (a validation mode) draws d ~ N(0, τ²) per evaluation: the data have not fixed it.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Discrepancy {
    pub d: Vec<Option<f64>>,
    pub scale: Option<f64>,
    /// The sd σ_u of the part that differs between units (boards, or bolted measurements):
    /// added to the model-error term where that is drawn (`None`: none).
    pub unit_scale: Option<f64>,
}

impl Discrepancy {
    /// No discrepancy for `n` labels.
    pub fn none(n: usize) -> Discrepancy {
        Discrepancy {
            d: vec![None; n],
            scale: None,
            unit_scale: None,
        }
    }
}

/// One step-2 particle: the carried step-1 particle and the joint population.
#[derive(Clone, Debug)]
pub struct Step2Particle {
    /// Index into [`Posterior::step1`].
    pub step1: usize,
    pub mu_ln_k: f64,
    pub sigma_ln_k: f64,
    /// ε per bolted label (order of the bolted [`LabelModel`]'s labels).
    pub eps: Vec<Option<f64>>,
    /// The model-form discrepancy of step 2 (bolted labels).
    pub discrepancy: Discrepancy,
}

/// The posterior to propagate.
#[derive(Clone, Debug)]
pub struct Posterior {
    /// Updated parameter names (ROM parameter names), order of the particle vectors.
    pub params: Vec<String>,
    /// Where step 1's population took moduli per unit mass: the mass scale's index in
    /// `params`, and per parameter whether the population's coordinate is it over the mass
    /// scale. `None`: the population is in `params` itself.
    pub per_mass: Option<crate::bayes::target::PerMass>,
    pub board_ids: Vec<String>,
    pub step1: Vec<Step1Particle>,
    /// Step 2 (bolted), when given.
    pub step2: Option<Vec<Step2Particle>>,
    /// Per measured board (order of `board_ids`), per free label: the board's measured mean
    /// eigenvalue λ̄ (rad²/s²) and its number of measurements, for the labels step 1 updated
    /// with a per-unit discrepancy; empty or `None`: none. With them a measured board's
    /// prediction of an updated label is conditioned on what its measurements fixed of the
    /// model error (see [`evaluate`]).
    pub board_offsets: Vec<Vec<Option<BoardMean>>>,
}

/// A measured board's mean eigenvalue of a label (rad²/s²) and its number of measurements.
pub type BoardMean = (f64, usize);

/// Which population the prediction is for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Scope {
    NewBoard,
    Board,
}

impl Scope {
    pub fn as_str(self) -> &'static str {
        match self {
            Scope::NewBoard => "new_board",
            Scope::Board => "board",
        }
    }
}

/// `free` or `bolted`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum SetupKind {
    Free,
    Bolted,
}

impl SetupKind {
    pub fn as_str(self) -> &'static str {
        match self {
            SetupKind::Free => "free",
            SetupKind::Bolted => "bolted",
        }
    }
}

/// One predicted frequency.
#[derive(Clone, Debug, PartialEq)]
pub struct Prediction {
    pub draw: u32,
    pub scope: Scope,
    /// Index into [`Posterior::board_ids`]; `None` for a new board.
    pub board: Option<usize>,
    pub setup: SetupKind,
    /// Index into the setup's labels.
    pub label: usize,
    /// Model frequency, Hz.
    pub freq_hz: f64,
    /// Predicted measurement (model, its discrepancy and prediction error), Hz.
    pub freq_obs_hz: f64,
    /// The model-form discrepancy in freq_obs_hz, relative frequency (0 without one).
    pub discrepancy_rel: f64,
    /// The label's ε was borrowed from an updated label (validation mode).
    pub eps_pooled: bool,
}

/// Evaluations that gave no prediction, and draws outside the ROM box, per setup and scope.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct Counts {
    pub evaluations: u64,
    pub inadmissible_or_untracked: u64,
    pub outside_rom_box: u64,
    /// New-board draws (free) outside the box, of `new_board_free` draws.
    pub new_board_outside_box: u64,
}

impl Counts {
    fn add(&mut self, o: &Counts) {
        self.evaluations += o.evaluations;
        self.inadmissible_or_untracked += o.inadmissible_or_untracked;
        self.outside_rom_box += o.outside_rom_box;
        self.new_board_outside_box += o.new_board_outside_box;
    }
}

/// The forward models of the setups.
pub struct Models<'a> {
    pub free: &'a LabelModel,
    /// Positions of the posterior's parameters in the free ROM's parameter vector.
    pub free_idx: Vec<usize>,
    /// The bolted model, the posterior's parameters' positions in it, and k_con's position.
    pub bolted: Option<(&'a LabelModel, Vec<usize>, usize)>,
}

#[derive(Debug, thiserror::Error)]
pub enum PropagateError {
    #[error("propagation: {0}")]
    Input(String),
}

/// Draws, per draw, the predictions of every scope and setup (see the module doc).
pub fn propagate(
    post: &Posterior,
    models: &Models,
    draws: usize,
    seed: u64,
) -> Result<(Vec<Prediction>, Counts), PropagateError> {
    let d = post.params.len();
    if post.step1.is_empty() {
        return Err(PropagateError::Input(
            "the step-1 posterior has no particle".into(),
        ));
    }
    for (i, p) in post.step1.iter().enumerate() {
        if p.population.mu.len() != d
            || p.population.sigma.len() != d
            || p.population.corr.len() != d * d
            || p.boards.len() != post.board_ids.len()
            || p.boards.iter().any(|b| b.len() != d)
            || p.eps.len() != models.free.labels.len()
            || p.discrepancy.d.len() != models.free.labels.len()
        {
            return Err(PropagateError::Input(format!(
                "step-1 particle {i}: expected {d} parameters, {} boards and {} labels",
                post.board_ids.len(),
                models.free.labels.len()
            )));
        }
    }
    // Cholesky factors of every particle's Ω, once.
    let chol: Vec<Vec<f64>> = post
        .step1
        .iter()
        .enumerate()
        .map(|(i, p)| {
            cholesky(&p.population.corr, d).ok_or_else(|| {
                PropagateError::Input(format!(
                "step-1 particle {i}: the population correlation matrix is not positive definite"
            ))
            })
        })
        .collect::<Result<_, _>>()?;
    let step2 = match (&post.step2, &models.bolted) {
        (Some(s), Some((bm, _, _))) => {
            if s.is_empty() {
                return Err(PropagateError::Input(
                    "the step-2 posterior has no particle".into(),
                ));
            }
            for (j, p) in s.iter().enumerate() {
                if p.step1 >= post.step1.len()
                    || p.eps.len() != bm.labels.len()
                    || p.discrepancy.d.len() != bm.labels.len()
                {
                    return Err(PropagateError::Input(format!(
                        "step-2 particle {j}: carries step-1 particle {} of {} and {} of {} bolted labels' errors",
                        p.step1,
                        post.step1.len(),
                        p.eps.len(),
                        bm.labels.len()
                    )));
                }
            }
            Some(s)
        }
        (Some(_), None) => {
            return Err(PropagateError::Input(
                "a step-2 posterior was given without a bolted model".into(),
            ))
        }
        _ => None,
    };
    let per_draw: Vec<(Vec<Prediction>, Counts)> = (0..draws)
        .into_par_iter()
        .map(|k| {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            rng.set_stream(k as u64);
            one_draw(
                post,
                models,
                &chol,
                step2.map(|v| v.as_slice()),
                k as u32,
                &mut rng,
            )
        })
        .collect();
    let mut out = Vec::new();
    let mut counts = Counts::default();
    for (p, c) in per_draw {
        out.extend(p);
        counts.add(&c);
    }
    Ok((out, counts))
}

/// Lower Cholesky factor of a symmetric d × d matrix (row-major), `None` if not SPD.
fn cholesky(a: &[f64], d: usize) -> Option<Vec<f64>> {
    let m = Mat::from_fn(d, d, |i, j| a[i * d + j]);
    let llt = m.llt(Side::Lower).ok()?;
    let l = llt.L();
    crate::simd::clear_upper_vector_state();
    Some((0..d * d).map(|k| l[(k / d, k % d)]).collect())
}

/// A new board's parameters: a draw of the population's coordinates, moduli per unit mass
/// turned back into moduli.
fn new_board(
    pop: &Population,
    l: &[f64],
    per_mass: Option<&crate::bayes::target::PerMass>,
    rng: &mut ChaCha8Rng,
) -> Vec<f64> {
    let mut theta = population_draw(pop, l, rng);
    if let Some(pm) = per_mass {
        let mass = theta[pm.mass];
        for (k, t) in theta.iter_mut().enumerate() {
            if pm.is_specific(k) {
                *t *= mass;
            }
        }
    }
    theta
}

fn population_draw(pop: &Population, l: &[f64], rng: &mut ChaCha8Rng) -> Vec<f64> {
    let d = pop.mu.len();
    let z: Vec<f64> = (0..d).map(|_| StandardNormal.sample(rng)).collect();
    (0..d)
        .map(|i| {
            let lz: f64 = (0..=i).map(|j| l[i * d + j] * z[j]).sum();
            pop.mu[i] + pop.sigma[i] * lz
        })
        .collect()
}

#[allow(clippy::too_many_arguments)]
fn evaluate(
    model: &LabelModel,
    nominal_values: &[f64],
    idx: &[usize],
    theta: &[f64],
    k_con: Option<(usize, f64)>,
    (eps, disc, offsets): (&[Option<f64>], &Discrepancy, &[Option<BoardMean>]),
    head: (u32, Scope, Option<usize>, SetupKind),
    rng: &mut ChaCha8Rng,
    out: &mut Vec<Prediction>,
    counts: &mut Counts,
) -> bool {
    let mut v = nominal_values.to_vec();
    for (i, t) in idx.iter().zip(theta) {
        v[*i] = *t;
    }
    if let Some((i, k)) = k_con {
        v[i] = k;
    }
    counts.evaluations += 1;
    let inside = model.inside_box(&v);
    if !inside {
        counts.outside_rom_box += 1;
    }
    let updated: Vec<f64> = eps.iter().flatten().copied().collect();
    // The random numbers are drawn whether or not the evaluation succeeds, so one failed
    // evaluation does not shift the streams of the others.
    let noise: Vec<(f64, f64, f64)> = (0..eps.len())
        .map(|_| {
            (
                StandardNormal.sample(rng),
                StandardNormal.sample(rng),
                StandardNormal.sample(rng),
            )
        })
        .collect();
    // Drawn only with a discrepancy, so that a posterior without one keeps its streams.
    let z_disc: Vec<f64> = match disc.scale {
        Some(_) => (0..eps.len()).map(|_| StandardNormal.sample(rng)).collect(),
        None => vec![],
    };
    let Some(lambda) = model.eigenvalues(&v) else {
        counts.inadmissible_or_untracked += 1;
        return inside;
    };
    let (draw, scope, board, setup) = head;
    for (l, lam) in lambda.iter().enumerate() {
        let (z, z_eps, z_b) = noise[l];
        let (e, pooled) = match eps[l] {
            Some(e) => (e, false),
            None => {
                let p = pooled_eps(&updated, z_eps);
                let r = model.repeatability_eps.get(l).copied().flatten();
                (r.map_or(p, |r| r.max(p)), true)
            }
        };
        let to_hz = |x: f64| x.max(0.0).sqrt() / (2.0 * std::f64::consts::PI);
        // The model error: drawn where the data have not fixed it (module doc).
        let s = model.model_error_sd.get(l).copied().unwrap_or(0.0);
        let s = s.hypot(disc.unit_scale.unwrap_or(0.0));
        // A new unit: a new board, or bolted with a new joint when the per-unit part is
        // inferred (a bolted unit is a measurement, a mounting: the next one is new).
        let new_unit =
            scope == Scope::NewBoard || (setup == SetupKind::Bolted && disc.unit_scale.is_some());
        let b = if new_unit || eps[l].is_none() {
            s * z_b
        } else {
            0.0
        };
        let d = match (disc.d.get(l).copied().flatten(), disc.scale) {
            (Some(d), _) => d,
            (None, Some(tau)) => tau * z_disc[l],
            (None, None) => 0.0,
        };
        // A measured board's own offset, where its measurements fixed it (common and per-unit
        // part at once): the model error t of this draw's λ against the board's measured mean
        // λ̄ has the prior N(d, s²) (the common discrepancy, and the per-unit sd s about it);
        // given the n measurements it is normal with mean d + k (λ̄/λ − 1 − d),
        // k = s²/(s² + ε²/n), and sd √(k ε²/n).
        let (d, b) = match (offsets.get(l).copied().flatten(), eps[l]) {
            (Some((mean, n)), Some(e)) if !new_unit && n > 0 => {
                let v = e * e / n as f64;
                let k = s * s / (s * s + v);
                (d + k * (mean / lam - 1.0 - d) + (k * v).sqrt() * z_b, 0.0)
            }
            _ => (d, b),
        };
        out.push(Prediction {
            draw,
            scope,
            board,
            setup,
            label: l,
            freq_hz: to_hz(*lam),
            freq_obs_hz: to_hz(lam * (1.0 + d) * (1.0 + b) * (1.0 + e * z)),
            discrepancy_rel: crate::bayes::discrepancy::freq_of_eigenvalue(d),
            eps_pooled: pooled,
        });
    }
    inside
}

/// The relative eigenvalue error a label's repeat measurements show: 2 s, s the pooled
/// within-group standard deviation of its relative frequency residuals (one group per board:
/// the same board measured again differs by the measurement alone), λ = ω² doubling a relative
/// frequency error. `None` with fewer than 4 degrees of freedom (Σ (n_g − 1)).
pub fn repeatability_eps(groups: &[Vec<f64>]) -> Option<f64> {
    let mut ss = 0.0;
    let mut df = 0usize;
    for g in groups {
        let v: Vec<f64> = g.iter().copied().filter(|x| x.is_finite()).collect();
        if v.len() < 2 {
            continue;
        }
        let m = v.iter().sum::<f64>() / v.len() as f64;
        ss += v.iter().map(|x| (x - m) * (x - m)).sum::<f64>();
        df += v.len() - 1;
    }
    (df >= 4).then(|| 2.0 * (ss / df as f64).sqrt())
}

/// ε of a label that was not updated: exp(m + s z), m and s the mean and sample standard
/// deviation (n − 1; 0 for one label) of ln ε over the updated labels; 0 without any.
pub fn pooled_eps(updated: &[f64], z: f64) -> f64 {
    let logs: Vec<f64> = updated
        .iter()
        .filter(|e| **e > 0.0)
        .map(|e| e.ln())
        .collect();
    if logs.is_empty() {
        return 0.0;
    }
    let n = logs.len() as f64;
    let m = logs.iter().sum::<f64>() / n;
    let s = if logs.len() > 1 {
        (logs.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0)).sqrt()
    } else {
        0.0
    };
    (m + s * z).exp()
}

fn one_draw(
    post: &Posterior,
    models: &Models,
    chol: &[Vec<f64>],
    step2: Option<&[Step2Particle]>,
    draw: u32,
    rng: &mut ChaCha8Rng,
) -> (Vec<Prediction>, Counts) {
    let mut out = Vec::new();
    let mut counts = Counts::default();
    let free = models.free;
    let free_nominal = free.rom.map.nominal.clone();
    let i = rng.random_range(0..post.step1.len());
    let p = &post.step1[i];
    let theta = new_board(&p.population, &chol[i], post.per_mass.as_ref(), rng);
    let inside = evaluate(
        free,
        &free_nominal,
        &models.free_idx,
        &theta,
        None,
        (&p.eps, &p.discrepancy, &[]),
        (draw, Scope::NewBoard, None, SetupKind::Free),
        rng,
        &mut out,
        &mut counts,
    );
    if !inside {
        counts.new_board_outside_box += 1;
    }
    for (b, th) in p.boards.iter().enumerate() {
        evaluate(
            free,
            &free_nominal,
            &models.free_idx,
            th,
            None,
            (
                &p.eps,
                &p.discrepancy,
                post.board_offsets.get(b).map_or(&[][..], |v| v.as_slice()),
            ),
            (draw, Scope::Board, Some(b), SetupKind::Free),
            rng,
            &mut out,
            &mut counts,
        );
    }
    if let (Some(s2), Some((bm, bidx, kidx))) = (step2, &models.bolted) {
        let j = rng.random_range(0..s2.len());
        let q = &s2[j];
        let p1 = &post.step1[q.step1];
        let bolted_nominal = bm.rom.map.nominal.clone();
        let joint = |rng: &mut ChaCha8Rng| -> f64 {
            let z: f64 = StandardNormal.sample(rng);
            (q.mu_ln_k + q.sigma_ln_k * z).exp()
        };
        let k = joint(rng);
        let theta = new_board(&p1.population, &chol[q.step1], post.per_mass.as_ref(), rng);
        evaluate(
            bm,
            &bolted_nominal,
            bidx,
            &theta,
            Some((*kidx, k)),
            (&q.eps, &q.discrepancy, &[]),
            (draw, Scope::NewBoard, None, SetupKind::Bolted),
            rng,
            &mut out,
            &mut counts,
        );
        for (b, th) in p1.boards.iter().enumerate() {
            let k = joint(rng);
            evaluate(
                bm,
                &bolted_nominal,
                bidx,
                th,
                Some((*kidx, k)),
                (&q.eps, &q.discrepancy, &[]),
                (draw, Scope::Board, Some(b), SetupKind::Bolted),
                rng,
                &mut out,
                &mut counts,
            );
        }
    }
    (out, counts)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fem::model::Setup;
    use crate::fem::params::names;
    use crate::fem::rom::RomOptions;
    use crate::fem::tests::helpers::{build, plain_board};

    /// A small free plate ROM (coarse mesh, few snapshots: the test checks the propagation,
    /// not the ROM) and its first two labels.
    fn model() -> LabelModel {
        let board = plain_board(0.2, 0.15, 1.6e-3, 24e9, 20e9, 8e9, 0.15, 1900.0);
        let fe = build(&board, Setup::Free, 8, 6);
        let rom = Rom::build(
            &fe,
            &RomOptions {
                n_modes: 4,
                n_random: 4,
                derivative_snapshots: false,
                ..RomOptions::default()
            },
        )
        .unwrap();
        LabelModel::new(rom, vec!["m1".into(), "m2".into()], &[0, 1], 0.2).unwrap()
    }

    /// A shear-deformable board's G_z is inside the box over × or ÷ 2 (its ROM's logarithmic
    /// axis, as `fe rom` and the updating build it), the moduli over ±20 % only.
    #[test]
    fn the_box_check_follows_the_transverse_shear_modulus_log_axis() {
        let mut board = plain_board(0.2, 0.15, 1.6e-3, 24e9, 20e9, 8e9, 0.15, 1900.0);
        board.core.g_xz_pa = Some(3e9);
        board.core.g_yz_pa = Some(3e9);
        let fe = build(&board, Setup::Free, 6, 4);
        let ro = RomOptions {
            n_modes: 3,
            n_random: 2,
            derivative_snapshots: false,
            log_axes: crate::fem::rom::with_own_log_axes(&fe.map, &[]),
            ..RomOptions::default()
        };
        assert_eq!(ro.log_axes.len(), 1);
        let lm =
            LabelModel::new(Rom::build(&fe, &ro).unwrap(), vec!["m1".into()], &[0], 0.2).unwrap();
        let at = |name: &str, factor: f64| {
            let mut v = lm.rom.map.nominal.clone();
            let k = lm.rom.map.names.iter().position(|n| n == name).unwrap();
            v[k] *= factor;
            lm.inside_box(&v)
        };
        assert!(at(names::G_Z, 1.9) && at(names::G_Z, 0.55));
        assert!(!at(names::G_Z, 2.1) && !at(names::G_Z, 0.45));
        assert!(at(names::E_X, 1.19) && !at(names::E_X, 1.25));
        assert_eq!(lm.box_description(), "±20 % (g_z_pa × or ÷ 2.00)");

        // A ROM built over a wider box (an update step that widened its box and its G_z
        // axis) is checked over that box, whatever the fallback given; one that does not
        // record its box (an older NPZ) over the fallback and the model's own axes.
        let wide = RomOptions {
            box_rel: 0.3,
            log_axes: vec![(names::G_Z.to_string(), 4f64.ln())],
            ..ro
        };
        let rom = Rom::build(&fe, &wide).unwrap();
        let back = Rom::from_npz_bytes(&rom.to_npz_bytes()).unwrap();
        assert_eq!(back.built_box, rom.built_box);
        let lm = LabelModel::new(back, vec!["m1".into()], &[0], 0.2).unwrap();
        let at = |lm: &LabelModel, name: &str, factor: f64| {
            let mut v = lm.rom.map.nominal.clone();
            let k = lm.rom.map.names.iter().position(|n| n == name).unwrap();
            v[k] *= factor;
            lm.inside_box(&v)
        };
        assert!(at(&lm, names::G_Z, 0.3) && !at(&lm, names::G_Z, 0.2));
        assert!(at(&lm, names::E_X, 1.25) && !at(&lm, names::E_X, 1.35));
        let mut old = rom;
        old.built_box = None;
        let lm = LabelModel::new(old, vec!["m1".into()], &[0], 0.2).unwrap();
        assert!(!at(&lm, names::G_Z, 0.3) && !at(&lm, names::E_X, 1.25));
    }

    /// Free-free models of `lm` whose one updated parameter is mass_scale.
    fn mass_scale_models(lm: &LabelModel) -> Models<'_> {
        let idx = vec![lm
            .rom
            .map
            .names
            .iter()
            .position(|n| n == names::MASS_SCALE)
            .unwrap()];
        Models {
            free: lm,
            free_idx: idx,
            bolted: None,
        }
    }

    fn posterior(eps: Vec<Option<f64>>) -> Posterior {
        // One updated parameter: mass_scale ~ N(1, 0.05²) in the population; one board at 1.1.
        Posterior {
            params: vec![names::MASS_SCALE.into()],
            per_mass: None,
            board_ids: vec!["B1".into()],
            step1: vec![Step1Particle {
                population: Population {
                    mu: vec![1.0],
                    sigma: vec![0.05],
                    corr: vec![1.0],
                },
                boards: vec![vec![1.1]],
                discrepancy: Discrepancy::none(eps.len()),
                eps,
            }],
            step2: None,
            board_offsets: vec![],
        }
    }

    /// With moduli per unit mass scale, a new board's modulus is the population coordinate's
    /// draw times its mass scale's draw: their ratio is the coordinate, exactly.
    #[test]
    fn a_per_mass_coordinate_becomes_the_modulus_times_the_mass_scale() {
        let pop = Population {
            mu: vec![2.0e10, 1.0],
            sigma: vec![4.0e8, 0.02],
            corr: vec![1.0, 0.3, 0.3, 1.0],
        };
        let l = cholesky(&[1.0, 0.3, 0.3, 1.0], 2).expect("cholesky");
        let pm = crate::bayes::target::PerMass {
            mass: 1,
            specific: vec![true, false],
        };
        let mut a = ChaCha8Rng::seed_from_u64(5);
        let mut b = ChaCha8Rng::seed_from_u64(5);
        for _ in 0..50 {
            let phi = population_draw(&pop, &l, &mut a);
            let theta = new_board(&pop, &l, Some(&pm), &mut b);
            assert_eq!(theta[1], phi[1]);
            assert!((theta[0] / theta[1] - phi[0]).abs() <= 1e-12 * phi[0]);
        }
    }

    #[test]
    fn new_board_quantiles_follow_the_mass_scaling_law() {
        // With only the mass scaled, λ(m) = λ₀ / m exactly (M(p) = m M₀, K fixed), so
        // f = f₀ / √m with m ~ N(1, 0.05²): P(f ≤ f₀/√(1 + 0.05 z_p)) = 1 − p.
        let lm = model();
        let f0: Vec<f64> = lm
            .eigenvalues(&lm.rom.map.nominal)
            .unwrap()
            .iter()
            .map(|l| l.sqrt() / (2.0 * std::f64::consts::PI))
            .collect();
        let models = mass_scale_models(&lm);
        let n = 4000;
        let (preds, counts) = propagate(&posterior(vec![None, None]), &models, n, 7).unwrap();
        assert_eq!(counts.evaluations, 2 * n as u64);
        assert_eq!(counts.inadmissible_or_untracked, 0);
        let newb: Vec<f64> = preds
            .iter()
            .filter(|p| p.scope == Scope::NewBoard && p.label == 0)
            .map(|p| p.freq_hz)
            .collect();
        assert_eq!(newb.len(), n);
        // Standard normal quantiles z_p (published values).
        for (p, z) in [
            (0.05, -1.644_853_6),
            (0.25, -0.674_489_75),
            (0.5, 0.0),
            (0.95, 1.644_853_6),
        ] {
            let f_p = f0[0] / (1.0f64 + 0.05 * z).sqrt();
            let frac = newb.iter().filter(|f| **f <= f_p).count() as f64 / n as f64;
            let se = (p * (1.0 - p) / n as f64).sqrt();
            assert!((frac - (1.0 - p)).abs() < 4.0 * se, "p {p}: {frac}");
        }
        // The measured board: f = f₀/√1.1 in every draw (no prediction error given).
        for p in preds.iter().filter(|p| p.scope == Scope::Board) {
            let want = f0[p.label] / 1.1f64.sqrt();
            assert!(
                (p.freq_hz - want).abs() < 1e-9 * want,
                "{} vs {want}",
                p.freq_hz
            );
            assert_eq!(p.freq_obs_hz, p.freq_hz);
        }
    }

    /// The discrepancy multiplies every board's eigenvalue of an updated label by exactly
    /// 1 + d (new and measured boards alike), and gives a label without its own d a spread
    /// N(0, τ²) on the eigenvalue; freq_hz stays the model's.
    #[test]
    fn the_discrepancy_shifts_updated_labels_and_spreads_the_others() {
        let lm = model();
        let models = mass_scale_models(&lm);
        let mut post = posterior(vec![None, None]);
        post.step1[0].discrepancy = Discrepancy {
            d: vec![Some(0.01), None],
            scale: Some(0.02),
            unit_scale: None,
        };
        let n = 4000;
        let (preds, _) = propagate(&post, &models, n, 3).unwrap();
        let r = |label: usize, scope: Scope| -> Vec<f64> {
            preds
                .iter()
                .filter(|p| p.scope == scope && p.label == label)
                .map(|p| (p.freq_obs_hz / p.freq_hz).powi(2) - 1.0)
                .collect()
        };
        for scope in [Scope::Board, Scope::NewBoard] {
            for v in r(0, scope) {
                assert!((v - 0.01).abs() < 1e-12, "{scope:?}: {v}");
            }
            let (m, sd) = crate::report::validation::mean_sd(&r(1, scope));
            assert!(
                m.abs() < 4.0 * 0.02 / (n as f64).sqrt(),
                "{scope:?}: mean {m}"
            );
            assert!(
                (sd - 0.02).abs() < 4.0 * 0.02 / (2.0 * n as f64).sqrt(),
                "{scope:?}: sd {sd}"
            );
        }
        for p in preds.iter().filter(|p| p.label == 0) {
            assert!((p.discrepancy_rel - (1.01f64.sqrt() - 1.0)).abs() < 1e-15);
        }
    }

    /// A measured board's updated label with a per-unit discrepancy is conditioned on what
    /// its measurements fixed: its predicted measurement centres on the board's measured mean
    /// (shrunk by s²/(s² + ε²/n)), whatever the draw's parameters; a new board draws the
    /// per-unit part from N(0, s²).
    #[test]
    fn a_measured_board_is_predicted_from_its_own_offset() {
        let lm = model();
        let models = mass_scale_models(&lm);
        let mut post = posterior(vec![Some(1e-4), None]);
        post.step1[0].discrepancy = Discrepancy {
            d: vec![Some(0.0), None],
            scale: Some(1e-9),
            unit_scale: Some(0.01),
        };
        let lam = lm.eigenvalues(&lm.rom.map.nominal).unwrap()[0] / 1.1;
        let mean = lam * 1.004;
        post.board_offsets = vec![vec![Some((mean, 5)), None]];
        let n = 2000;
        let (preds, _) = propagate(&post, &models, n, 5).unwrap();
        let two_pi = 2.0 * std::f64::consts::PI;
        let obs = |scope: Scope| -> Vec<f64> {
            preds
                .iter()
                .filter(|p| p.scope == scope && p.label == 0)
                .map(|p| (two_pi * p.freq_obs_hz).powi(2) / mean - 1.0)
                .collect()
        };
        let k = 1e-4 / (1e-4 + 1e-8 / 5.0);
        let (m, sd) = crate::report::validation::mean_sd(&obs(Scope::Board));
        // Centred on k λ̄ + (1 − k) λ; spread ε (1 + k/n)^½ ≈ 1.1e-4.
        assert!((m - (k - 1.0) * 0.004 / 1.004).abs() < 2e-5, "mean {m}");
        assert!(sd < 2e-4, "sd {sd}");
        let (_, sd_new) = crate::report::validation::mean_sd(&obs(Scope::NewBoard));
        assert!(sd_new > 0.009, "a new board's spread {sd_new}");
    }

    /// The same board beside a common discrepancy d = 1 % and a per-unit sd as small as the
    /// measurements' own precision: the offset's prior is centred on d, so the prediction
    /// lies between the model with its discrepancy and the board's measured mean (d + k
    /// (λ̄/λ − 1 − d)), not between the bare model and the mean. Centred on the bare model,
    /// a board's prediction misses its own measurements in every mode whose common
    /// discrepancy exceeds ε/√n once the per-unit sd is small (with step 1's mesh term off,
    /// 20/49 held-out measurements of the realistic null inside).
    #[test]
    fn a_measured_boards_offset_is_shrunk_towards_the_common_discrepancy() {
        let lm = model();
        let models = mass_scale_models(&lm);
        let mut post = posterior(vec![Some(1e-3), None]);
        post.step1[0].discrepancy = Discrepancy {
            d: vec![Some(0.01), None],
            scale: Some(0.01),
            unit_scale: Some(1e-3 / 5f64.sqrt()),
        };
        let lam = lm.eigenvalues(&lm.rom.map.nominal).unwrap()[0] / 1.1;
        let mean = lam * 1.012;
        post.board_offsets = vec![vec![Some((mean, 5)), None]];
        let (preds, _) = propagate(&post, &models, 2000, 5).unwrap();
        let two_pi = 2.0 * std::f64::consts::PI;
        let t: Vec<f64> = preds
            .iter()
            .filter(|p| p.scope == Scope::Board && p.label == 0)
            .map(|p| (two_pi * p.freq_obs_hz).powi(2) / lam - 1.0)
            .collect();
        // s² = ε²/n: k = ½, the centre halfway between 1.0 % and 1.2 %.
        let (m, _) = crate::report::validation::mean_sd(&t);
        assert!((m - 0.011).abs() < 2e-4, "mean {m}");
    }

    #[test]
    fn prediction_error_is_relative_on_the_eigenvalue_and_pooled_for_validation_modes() {
        let lm = model();
        let models = mass_scale_models(&lm);
        let n = 4000;
        let (preds, _) = propagate(&posterior(vec![Some(0.02), None]), &models, n, 11).unwrap();
        for label in [0, 1] {
            // (f_obs/f)² − 1 = ε z: mean 0, sd ε = 0.02 (label 1 borrows label 0's ε).
            let r: Vec<f64> = preds
                .iter()
                .filter(|p| p.scope == Scope::Board && p.label == label)
                .map(|p| (p.freq_obs_hz / p.freq_hz).powi(2) - 1.0)
                .collect();
            let (m, s) = crate::report::validation::mean_sd(&r);
            assert!(
                m.abs() < 4.0 * 0.02 / (n as f64).sqrt(),
                "label {label}: mean {m}"
            );
            // sd of a sample sd ≈ σ / √(2n).
            assert!(
                (s - 0.02).abs() < 4.0 * 0.02 / (2.0 * n as f64).sqrt(),
                "label {label}: sd {s}"
            );
            let pooled = preds
                .iter()
                .filter(|p| p.label == label)
                .all(|p| p.eps_pooled == (label == 1));
            assert!(pooled);
        }
        // With a repeatability of 0.05 (above the pooled 0.02), label 1 takes it; label 0
        // keeps its own inferred ε.
        let lm = model()
            .with_repeatability(vec![Some(0.1), Some(0.05)])
            .unwrap();
        let models = mass_scale_models(&lm);
        let (preds, _) = propagate(&posterior(vec![Some(0.02), None]), &models, n, 11).unwrap();
        for (label, want) in [(0, 0.02), (1, 0.05)] {
            let r: Vec<f64> = preds
                .iter()
                .filter(|p| p.scope == Scope::Board && p.label == label)
                .map(|p| (p.freq_obs_hz / p.freq_hz).powi(2) - 1.0)
                .collect();
            let (_, s) = crate::report::validation::mean_sd(&r);
            assert!(
                (s - want).abs() < 4.0 * want / (2.0 * n as f64).sqrt(),
                "label {label}: sd {s}, want {want}"
            );
        }
    }

    /// The model-error term: (f_obs/f)² = (1 + b)(1 + ε z), so its variance is
    /// s² + ε² + s²ε²; drawn for a new board's labels and a measured board's validation label,
    /// not for a measured board's updated label (its sd stays ε).
    #[test]
    fn model_error_widens_what_the_data_have_not_fixed() {
        let lm = model().with_model_error(vec![0.03, 0.04]).unwrap();
        let models = mass_scale_models(&lm);
        let n = 4000;
        let (preds, _) = propagate(&posterior(vec![Some(0.02), None]), &models, n, 13).unwrap();
        let sd_of = |scope: Scope, label: usize| {
            let r: Vec<f64> = preds
                .iter()
                .filter(|p| p.scope == scope && p.label == label)
                .map(|p| (p.freq_obs_hz / p.freq_hz).powi(2) - 1.0)
                .collect();
            crate::report::validation::mean_sd(&r).1
        };
        let e = 0.02f64;
        for (scope, label, s) in [
            (Scope::Board, 0, 0.0),
            (Scope::Board, 1, 0.04),
            (Scope::NewBoard, 0, 0.03),
            (Scope::NewBoard, 1, 0.04),
        ] {
            let want = (s * s + e * e + s * s * e * e).sqrt();
            let got = sd_of(scope, label);
            assert!(
                (got - want).abs() < 4.0 * want / (2.0 * n as f64).sqrt(),
                "{scope:?} label {label}: sd {got}, want {want}"
            );
        }
        assert!(model().with_model_error(vec![0.01]).is_err());
        assert!(model().with_model_error(vec![0.01, f64::NAN]).is_err());
    }

    #[test]
    fn repeatability_is_twice_the_pooled_within_board_sd() {
        // Two boards: deviations ±1e-4 around each mean, 3 + 2 values (df 3) → None; a
        // third board adds df 2 → pooled sd from the sums of squares.
        let a = vec![0.01 - 1e-4, 0.01, 0.01 + 1e-4];
        let b = vec![-0.02 - 1e-4, -0.02 + 1e-4];
        assert_eq!(repeatability_eps(&[a.clone(), b.clone()]), None);
        let c = vec![0.0, 2e-4, 4e-4];
        let ss = 2e-8 + 2e-8 + 8e-8;
        let e = repeatability_eps(&[a, b, c, vec![5.0]]).unwrap();
        assert!((e - 2.0 * (ss / 5.0_f64).sqrt()).abs() < 1e-15, "{e}");
    }

    #[test]
    fn pooled_eps_is_the_log_normal_of_the_updated_modes() {
        // ln 0.01 and ln 0.04: mean ln 0.02, sample sd |ln 4| / √2.
        let e = [0.01, 0.04];
        assert!((pooled_eps(&e, 0.0) - 0.02).abs() < 1e-15);
        let s = 4f64.ln() / 2f64.sqrt();
        assert!((pooled_eps(&e, 1.5) - 0.02 * (1.5 * s).exp()).abs() < 1e-15);
        assert!((pooled_eps(&[0.03], 2.0) - 0.03).abs() < 1e-15);
        assert_eq!(pooled_eps(&[], 1.0), 0.0);
    }

    #[test]
    fn same_seed_same_predictions_whatever_the_thread_count() {
        let lm = model();
        let models = mass_scale_models(&lm);
        let post = posterior(vec![Some(0.01), None]);
        let run = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| propagate(&post, &models, 300, 5).unwrap())
        };
        let (a, ca) = run(1);
        let (b, cb) = run(3);
        assert_eq!(a, b);
        assert_eq!(ca, cb);
        let (c, _) = propagate(&post, &models, 300, 6).unwrap();
        assert_ne!(a, c, "another seed gives other draws");
    }

    #[test]
    fn bad_posteriors_are_refused_with_what_was_expected() {
        let lm = model();
        let models = Models {
            free: &lm,
            free_idx: vec![0],
            bolted: None,
        };
        let mut post = posterior(vec![None]);
        let e = propagate(&post, &models, 10, 1).unwrap_err().to_string();
        assert!(
            e.contains("expected 1 parameters, 1 boards and 2 labels"),
            "{e}"
        );
        post.step1[0].eps = vec![None, None];
        post.step1[0].discrepancy = Discrepancy::none(2);
        post.step1[0].population.corr = vec![-1.0];
        let e = propagate(&post, &models, 10, 1).unwrap_err().to_string();
        assert!(e.contains("not positive definite"), "{e}");
    }
}

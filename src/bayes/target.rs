//! The hierarchical modal-updating target, as an [`smc::Target`]:
//! population prior over the units' parameters, prediction-error scales per mode, and the
//! modal likelihood of [`super::modal`].
//!
//! - Step 1 (boards, free-free): a unit is a board, x = relative deviations of the updated
//!   parameters from the board file's nominal values (p = p₀ (1 + x)).
//! - Step 2 (joints, bolted): a unit is a bolted measurement, x = (ln K / K₀) of its joint
//!   stiffness; the board's parameters come from a step-1 posterior draw held in the
//!   particle's auxiliary values (`smc::run_with`; groups make it the modular posterior).
//!
//! Global vector: [population (see [`PopulationPrior`]) | ln ε per mode | ln δ per mode];
//! the error blocks are absent when fixed.
//!
//! The model-error term ([`ErrorModel::model_error_sd`]): each unit's model eigenvalue of
//! mode m is λ_m (1 + b_m), b_m ~ N(0, s_m²) a relative model-form error (e.g. the
//! discretization's, [`crate::fem::convergence::mesh_spread`]), integrated out in closed
//! form per unit ([`modal::log_lik_with`]). Without it a model error common to all
//! measurements of a board is read as information about the board's parameters, whose
//! intervals, as narrow as the measurements allow, then miss the truth.
//!
//! With a [`CovariateEffect`] (step 1 only; the diagnosis's `temperature_stiffness`), a
//! board's x has one more coordinate, its coefficient β_b (absolute, after the relative
//! deviations), and the board's model is evaluated at every condition of its measurements. ln ε and ln δ are normal (log-normal scales): a
//! weakly informative prior over orders of magnitude that, unlike a half-normal, puts no
//! appreciable mass on absurdly small errors (a half-normal's ln-scale density decays only
//! like ε as ε → 0, which made the first tempering stages do nothing but remove those).

use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::Serialize;

use super::modal::{self, CovariateEffect, ModalPredictor, Terms, UnitData};
use super::population::{Population, PopulationPrior};
use super::smc::{GlobalRole, Target};
use super::stats::normal_lpdf;

/// How one family of prediction-error scales is treated.
#[derive(Clone, Copy, Debug, Serialize, serde::Deserialize, PartialEq)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum ErrorPrior {
    /// Inferred per mode with a log-normal prior: ln value ~ N(ln median, log_sd²).
    Inferred { median: f64, log_sd: f64 },
    /// Fixed to this value for every mode.
    Fixed { value: f64 },
}

/// Prediction-error scales: ε (relative, on eigenvalues) and δ (on unit-norm shapes).
#[derive(Clone, Debug, Serialize)]
pub struct ErrorModel {
    pub n_modes: usize,
    pub eps: ErrorPrior,
    /// `None`: shape terms are not used.
    pub delta: Option<ErrorPrior>,
    /// Prior sd s_m of each mode's relative eigenvalue model error b_m ~ N(0, s_m²),
    /// integrated out per unit (`None`: the model is taken as exact).
    pub model_error_sd: Option<Vec<f64>>,
    /// The model-form discrepancy shared by the units (`None`: none), its block after ε's
    /// and δ's.
    pub discrepancy: Option<super::discrepancy::Discrepancy>,
}

impl ErrorModel {
    fn block(p: &ErrorPrior, n: usize) -> usize {
        match p {
            ErrorPrior::Inferred { .. } => n,
            ErrorPrior::Fixed { .. } => 0,
        }
    }
    /// Coordinates in the global vector.
    pub fn dim(&self) -> usize {
        self.scales_dim() + self.discrepancy.as_ref().map_or(0, |d| d.dim())
    }
    /// Coordinates of ε's and δ's blocks (where the discrepancy's block starts).
    fn scales_dim(&self) -> usize {
        Self::block(&self.eps, self.n_modes)
            + self.delta.map_or(0, |d| Self::block(&d, self.n_modes))
    }
    /// The discrepancy d per mode of the error block h (empty without one).
    pub fn bias(&self, h: &[f64]) -> Vec<f64> {
        match &self.discrepancy {
            Some(d) => d.bias(&h[self.scales_dim()..]),
            None => vec![],
        }
    }
    /// The discrepancy's scale τ of the error block h (`None` without one).
    pub fn discrepancy_scale(&self, h: &[f64]) -> Option<f64> {
        let d = self.discrepancy.as_ref()?;
        Some(d.scale(&h[self.scales_dim()..]))
    }
    /// The discrepancy's per-unit scale σ_u of the error block h (`None` without one).
    pub fn discrepancy_unit_scale(&self, h: &[f64]) -> Option<f64> {
        let d = self.discrepancy.as_ref()?;
        Some(d.unit_scale(&h[self.scales_dim()..]))
    }
    /// The sd per mode of the per-unit model error integrated out ([`modal::log_lik_with`]):
    /// the fixed `model_error_sd` and the discrepancy's σ_u together (empty: none).
    pub fn unit_model_error_sd(&self, h: &[f64]) -> Vec<f64> {
        self.unit_model_error_sd_with(self.discrepancy_unit_scale(h))
    }
    /// [`ErrorModel::unit_model_error_sd`] with the discrepancy's σ_u given (`None`: none), as
    /// a posterior table reports it.
    pub fn unit_model_error_sd_with(&self, unit_scale: Option<f64>) -> Vec<f64> {
        let u2 = unit_scale.map(|s| s * s);
        match (&self.model_error_sd, u2) {
            (Some(sd), Some(v)) => sd.iter().map(|s| (s * s + v).sqrt()).collect(),
            (Some(sd), None) => sd.clone(),
            (None, Some(v)) => vec![v.sqrt(); self.n_modes],
            (None, None) => vec![],
        }
    }
    /// Names of the coordinates given the mode labels.
    pub fn names(&self, labels: &[String]) -> Vec<String> {
        let mut out = vec![];
        if let ErrorPrior::Inferred { .. } = self.eps {
            out.extend(labels.iter().map(|l| format!("log_eps_{l}")));
        }
        if let Some(ErrorPrior::Inferred { .. }) = self.delta {
            out.extend(labels.iter().map(|l| format!("log_delta_{l}")));
        }
        if let Some(d) = &self.discrepancy {
            out.extend(d.names());
        }
        out
    }
    fn unpack_one(p: &ErrorPrior, h: &[f64], n: usize) -> (Vec<f64>, usize) {
        match p {
            ErrorPrior::Inferred { .. } => (h[..n].iter().map(|v| v.exp()).collect(), n),
            ErrorPrior::Fixed { value } => (vec![*value; n], 0),
        }
    }
    /// (ε, δ) per mode; δ empty without shape terms.
    pub fn unpack(&self, h: &[f64]) -> (Vec<f64>, Vec<f64>) {
        let (eps, used) = Self::unpack_one(&self.eps, h, self.n_modes);
        let delta = match &self.delta {
            Some(d) => Self::unpack_one(d, &h[used..], self.n_modes).0,
            None => vec![],
        };
        (eps, delta)
    }
    fn lp_one(p: &ErrorPrior, h: &[f64]) -> (f64, usize) {
        match p {
            ErrorPrior::Inferred { median, log_sd } => (
                h.iter()
                    .map(|&v| normal_lpdf(v, median.ln(), *log_sd))
                    .sum(),
                h.len(),
            ),
            ErrorPrior::Fixed { .. } => (0.0, 0),
        }
    }
    /// Log prior of the error block (with the log-scale Jacobians).
    pub fn log_prior(&self, h: &[f64]) -> f64 {
        let n = Self::block(&self.eps, self.n_modes);
        let (a, _) = Self::lp_one(&self.eps, &h[..n]);
        // δ's block only: the discrepancy's block follows it.
        let b = match &self.delta {
            Some(d) => Self::lp_one(d, &h[n..self.scales_dim()]).0,
            None => 0.0,
        };
        let c = match &self.discrepancy {
            Some(d) => d.log_prior(&h[self.scales_dim()..]),
            None => 0.0,
        };
        a + b + c
    }
    /// A prior draw of the error block.
    pub fn sample(&self, rng: &mut ChaCha8Rng) -> Vec<f64> {
        let mut out = vec![];
        for p in std::iter::once(&self.eps).chain(self.delta.as_ref()) {
            if let ErrorPrior::Inferred { median, log_sd } = p {
                for _ in 0..self.n_modes {
                    let z: f64 = StandardNormal.sample(rng);
                    out.push(median.ln() + log_sd * z);
                }
            }
        }
        if let Some(d) = &self.discrepancy {
            out.extend(d.sample(rng));
        }
        out
    }
}

/// How a unit's x (and, for step 2 when it comes, the particle's aux) become the ROM's
/// parameter vector.
#[derive(Clone, Debug)]
pub enum Compose {
    /// Step 1: p[updated[k]] = reference[k] (1 + x_k), or reference[k] e^{x_k} where
    /// `log[k]` (a parameter whose prior spans orders of magnitude: the diagnosis's added
    /// mass); the reference is the board file's nominal value, which need not be the ROM's
    /// centre. `log` may be shorter than `updated` (missing entries: relative).
    Boards {
        updated: Vec<usize>,
        reference: Vec<f64>,
        log: Vec<bool>,
        /// Moduli per unit mass ([`PerMass`]); `None`: every coordinate is its own parameter.
        per_mass: Option<PerMass>,
        /// The mass coordinate as the weighed total beside a point mass ([`TotalMass`]);
        /// `None`: the mass coordinate is the board's own mass scale.
        total_mass: Option<TotalMass>,
    },
    /// Step 2: p[board_params[k]] = aux[unit_board[b] · board_params.len() + k] (the step-1
    /// draw of unit b's board, absolute values) and, log-linearly in the unit's coordinates,
    /// p_i = ref_i · exp(Σ_k a_ik x_k) for every (i, ref_i) of `reference`, with
    /// `coords[k]` = the (i, a_ik) of coordinate k. The baseline has one coordinate,
    /// ln(k_con / k_ref); the diagnosis's enrichments add more
    /// ([`crate::diagnose::library`]).
    Joints {
        board_params: Vec<usize>,
        unit_board: Vec<usize>,
        coords: Vec<Vec<(usize, f64)>>,
        reference: Vec<(usize, f64)>,
        /// A step-1 covariate effect carried into step 2 (`None`: none).
        covariate: Option<JointsCovariate>,
        /// Per unit: whether coordinates 1.. (an enrichment's own) act on it; `None`: on
        /// every unit. Coordinate 0 (the contact stiffness) always acts. A unit they do not
        /// act on keeps them as latent draws of the population, which its likelihood ignores.
        enriched_units: Option<Vec<bool>>,
    },
}

/// Step-1 coordinates of the moduli per unit mass: coordinate k with `specific[k]` is the
/// relative deviation of p_k / m from reference_k / reference_m, m the parameter of
/// coordinate `mass` (the mass scale), so p_k = reference_k (1 + x_k) · m / reference_m.
///
/// Why: a free-free structure's eigenvalues are stiffness over mass, unchanged when every
/// modulus and the mass scale move by the same factor, so the frequencies fix the moduli per
/// unit mass and the balance fixes the mass. Boards whose stiffness and mass vary together
/// (fibre and resin content move both) have strongly correlated moduli and mass, a
/// correlation a handful of boards cannot pin down; the population's correlation prior then
/// shrinks it towards zero and the predicted frequency spread of a new board, which follows
/// modulus over mass, comes out too wide (1.4–1.6× the classical prediction interval on the
/// lab's 7-board null campaign). In these coordinates the frequency-relevant spread is a
/// population sd of its own, learnt from the boards as directly as a single quantity.
#[derive(Clone, Debug)]
pub struct PerMass {
    /// Index (into the unit coordinates) of the mass parameter.
    pub mass: usize,
    /// Per unit coordinate: a modulus expressed per unit mass (relative coordinates only,
    /// never a logarithmic one).
    pub specific: Vec<bool>,
}

/// Step-1 coordinates of a point mass beside the board's mass scale (the diagnosis's
/// `added_mass` refit): coordinate `mass` is the weighed total, board and point mass,
/// relative to its nominal, x_T = M / (M₀ + m_ref) − 1, and the board's own mass scale
/// follows as 1 + x_m = (1 + x_T)(1 + r) − r e^{x_a}, with x_a = ln(m / m_ref) the point
/// mass's coordinate and r = m_ref / M₀.
///
/// Why: the balance weighs the board with the point mass, to 3e-6 of it on a 0.1 mg
/// balance, so in the parameters themselves the posterior lies along the curved ridge
/// M₀ (1 + x_m) + m_ref e^{x_a} = M. A Gaussian reference and random-walk moves follow a
/// curved ridge thinner than their steps badly: the refit took 17–24 tempering stages and
/// ended short of its ESS (stop 87; stop 88 measured 847 s and R-hat 1.33). In these
/// coordinates the balance pins x_T alone and the modes, which tell the point mass from a
/// mass spread over the board, pin x_a; each posterior is close to a normal in them.
#[derive(Clone, Debug)]
pub struct TotalMass {
    /// Index (into the unit coordinates) of the mass coordinate (x_T in place of x_m).
    pub mass: usize,
    /// Index of the point mass's logarithmic coordinate x_a.
    pub point: usize,
    /// m_ref / M₀: the point mass's reference over the board's nominal mass.
    pub ratio: f64,
}

impl TotalMass {
    /// The board's own mass-scale coordinate x_m at unit coordinates x (x_T at `mass`).
    pub fn board_mass_coordinate(&self, x: &[f64]) -> f64 {
        let r = self.ratio;
        (1.0 + x[self.mass]) * (1.0 + r) - r * x[self.point].exp() - 1.0
    }

    /// The inverse: x_T from the board's mass-scale coordinate x_m and x_a.
    pub fn total_coordinate(&self, x_m: f64, x_a: f64) -> f64 {
        let r = self.ratio;
        (1.0 + x_m + r * x_a.exp()) / (1.0 + r) - 1.0
    }
}

impl PerMass {
    /// Whether coordinate k is a modulus per unit mass.
    pub fn is_specific(&self, k: usize) -> bool {
        self.specific.get(k).copied().unwrap_or(false)
    }

    /// The factor a modulus per unit mass is multiplied by, m / reference_m = 1 + x_mass, at
    /// unit coordinates x (relative ones: `specific` marks no logarithmic coordinate).
    pub fn mass_factor(&self, x: &[f64]) -> f64 {
        1.0 + x[self.mass]
    }
}

impl Compose {
    /// Step 1: the unit coordinates with the mass coordinate as the board's own mass scale
    /// (x_m; [`TotalMass`] holds the weighed total there), so that every other rule reads
    /// them as before. Borrowed unchanged without a total-mass coordinate, and in step 2.
    pub fn board_coordinates<'a>(&self, x: &'a [f64]) -> std::borrow::Cow<'a, [f64]> {
        match self {
            Compose::Boards {
                total_mass: Some(t),
                ..
            } => {
                let mut y = x.to_vec();
                y[t.mass] = t.board_mass_coordinate(x);
                std::borrow::Cow::Owned(y)
            }
            _ => std::borrow::Cow::Borrowed(x),
        }
    }

    /// Step 1: a unit's parameters relative to their references, p_k / reference_k − 1 (ln
    /// of it on a logarithmic coordinate), from its coordinates x: x itself unless moduli are
    /// per unit mass or the mass coordinate is the weighed total. Step 2: x.
    pub fn relative_params(&self, x: &[f64]) -> Vec<f64> {
        let x = &*self.board_coordinates(x);
        match self {
            Compose::Boards {
                per_mass: Some(pm), ..
            } => {
                let m = pm.mass_factor(x);
                x.iter()
                    .enumerate()
                    .map(|(k, &v)| {
                        if pm.is_specific(k) {
                            (1.0 + v) * m - 1.0
                        } else {
                            v
                        }
                    })
                    .collect()
            }
            _ => x.to_vec(),
        }
    }
}

/// A step-1 [`CovariateEffect`] in step 2: every board's block of aux holds its parameters
/// and, at `coef`, its coefficient β_b; unit b's ROM parameters `scaled` are multiplied by
/// 1 + β_b c_b, c_b = `offsets[b]` the measurement's covariate relative to step 1's
/// reference.
#[derive(Clone, Debug)]
pub struct JointsCovariate {
    /// Length of one board's block of aux (parameters, then coefficients).
    pub block: usize,
    pub coef: usize,
    pub scaled: Vec<usize>,
    pub offsets: Vec<f64>,
}

/// One hierarchical modal target.
#[derive(Clone, Debug)]
pub struct ModalTarget {
    pub predictor: ModalPredictor,
    pub compose: Compose,
    pub prior: PopulationPrior,
    pub errors: ErrorModel,
    pub units: Vec<UnitData>,
    /// A per-measurement covariate scaling stiffness (`None`: the baseline); step 1 only.
    pub covariate: Option<CovariateEffect>,
    /// Per unit, a verified subspace of the ROM that [`Target::model`] solves in inside its
    /// box (`surrogate::fit_subspace`); empty or None: the ROM.
    pub subspaces: Vec<Option<std::sync::Arc<super::surrogate::UnitSubspace>>>,
    /// Per unit, direct measurements of its coordinates, (coordinate k, value, sd) with
    /// x_k ~ N(value, sd²) in the likelihood: a specimen's measured core thickness, relative to
    /// the reference like its coordinate. Empty: none.
    pub coord_obs: Vec<Vec<(usize, f64, f64)>>,
}

/// Unpacked global vector.
pub struct Ctx {
    pub pop: Population,
    /// log p of the population block of g ([`PopulationPrior::log_prior`]).
    pub lp_pop: f64,
    pub eps: Vec<f64>,
    pub delta: Vec<f64>,
    /// The discrepancy d per mode (empty without one).
    pub bias: Vec<f64>,
    /// ln ε and 2 ln δ per mode, formed once per global vector (not per unit).
    pub logs: modal::ErrorLogs,
}

/// How far above the scatter of a unit's repeated measurements a mode's ε may sit in g's
/// mode before the reference is searched again from that scatter
/// ([`ModalTarget::noise_restart`]). The scatter estimates ε itself: the per-unit model error
/// σ_u carries what differs between units, so the posterior's ε sits at it (on the five
/// realistic nulls, fold 0 of each: 0.90–1.25×). A tenfold excess is beyond its sampling error at three
/// degrees of freedom and more (P(s < σ/10) < 0.002 for χ²₃).
pub const NOISE_RESTART_FACTOR: f64 = 10.0;
/// The degrees of freedom a mode's repeat scatter needs before it can overrule g's mode.
pub const NOISE_RESTART_MIN_DOF: usize = 3;

/// How many of its prior's sds below the prior's median an error scale (ε or δ) of g may
/// fall during the reference's search before the search is taken to have collapsed
/// ([`ModalTarget::collapsed_error_scale`]). The prior is the user's statement of plausible
/// noise (ε: median 0.5 %, a factor 4.5 per sd, the default of both steps), and below five sds it
/// holds under 3e-7 of its mass: a joint enrichment's units of two or three coordinates that
/// each fit a bolted mode exactly reach that only through the Laplace form's false peak at
/// ε → 0 (the realistic fixture refit ran ln ε of bending-y-1 to −17.0, 7.8 sds, with the
/// plate modes' ε left at 2–3e-3). A false alarm costs stages, not the answer: the fallback
/// reference is a valid start, and the tempering corrects it.
pub const COLLAPSE_PRIOR_SDS: f64 = 5.0;

impl ModalTarget {
    /// [`Target::collapsed_global`]: the first inferred ln ε or ln δ of g more than
    /// [`COLLAPSE_PRIOR_SDS`] of its prior's log-sd below the prior's log-median.
    pub fn collapsed_error_scale(&self, g: &[f64]) -> Option<String> {
        let mut k = self.prior.dim();
        for (name, p) in [
            ("ε", Some(&self.errors.eps)),
            ("δ", self.errors.delta.as_ref()),
        ] {
            let Some(ErrorPrior::Inferred { median, log_sd }) = p else {
                continue;
            };
            for m in 0..self.errors.n_modes {
                let z = (g.get(k + m)? - median.ln()) / log_sd;
                if z < -COLLAPSE_PRIOR_SDS {
                    return Some(format!(
                        "mode {m}: {name} {:.2e}, {:.1} prior sds below its median {median:.2e}",
                        g[k + m].exp(),
                        -z
                    ));
                }
            }
            k += self.errors.n_modes;
        }
        None
    }

    /// [`Target::data_start_global`]: where g's ε of some mode exceeds
    /// [`NOISE_RESTART_FACTOR`] times the scatter of the units' repeated measurements of it
    /// ([`modal::repeat_scatter`], at [`NOISE_RESTART_MIN_DOF`] or more), g with every such
    /// mode's ln ε at its scatter; None otherwise, or where ε is fixed.
    pub fn noise_restart(&self, g: &[f64]) -> Option<(Vec<f64>, String)> {
        if !matches!(self.errors.eps, ErrorPrior::Inferred { .. }) {
            return None;
        }
        let k0 = self.prior.dim();
        let scatter = modal::repeat_scatter(&self.units, self.errors.n_modes);
        let mut out = g.to_vec();
        let mut why = vec![];
        for (m, sc) in scatter.iter().enumerate() {
            let Some((s, dof)) = *sc else { continue };
            let eps = g.get(k0 + m)?.exp();
            if dof >= NOISE_RESTART_MIN_DOF && s > 0.0 && eps > NOISE_RESTART_FACTOR * s {
                why.push(format!(
                    "mode {m}: ε {eps:.2e} against a repeat scatter of {s:.2e} ({dof} dof)"
                ));
                out[k0 + m] = s.ln();
            }
        }
        (!why.is_empty()).then(|| {
            (
                out,
                format!(
                    "the first search ended with ε over {NOISE_RESTART_FACTOR} times the scatter of the units' repeated measurements ({}); searched again from that scatter",
                    why.join("; ")
                ),
            )
        })
    }

    /// The ROM parameter vector of unit b given the particle's auxiliary values.
    pub fn values(&self, aux: &[f64], b: usize, x: &[f64]) -> Vec<f64> {
        let map = &self.predictor.rom.map;
        let mut v = map.nominal.clone();
        match &self.compose {
            Compose::Boards {
                updated,
                reference,
                log,
                per_mass,
                ..
            } => {
                let x = &*self.compose.board_coordinates(x);
                for (k, &i) in updated.iter().enumerate() {
                    v[i] = if log.get(k).copied().unwrap_or(false) {
                        reference[k] * x[k].exp()
                    } else {
                        reference[k] * (1.0 + x[k])
                    };
                }
                if let Some(pm) = per_mass {
                    let m = pm.mass_factor(x);
                    for (k, &i) in updated.iter().enumerate() {
                        if pm.is_specific(k) {
                            v[i] *= m;
                        }
                    }
                }
            }
            Compose::Joints {
                board_params,
                unit_board,
                coords,
                reference,
                covariate,
                enriched_units,
            } => {
                let d1 = covariate.as_ref().map_or(board_params.len(), |c| c.block);
                let o = unit_board[b] * d1;
                for (k, &i) in board_params.iter().enumerate() {
                    v[i] = aux[o + k];
                }
                if let Some(c) = covariate {
                    // A non-positive factor makes the stiffness non-positive: the ROM
                    // rejects it (no model there).
                    let f = 1.0 + aux[o + c.coef] * c.offsets[b];
                    for &i in &c.scaled {
                        v[i] *= f;
                    }
                }
                for &(i, r) in reference {
                    v[i] = r;
                }
                let enriched = enriched_units.as_ref().is_none_or(|e| e[b]);
                for (k, acts) in coords.iter().enumerate() {
                    if k > 0 && !enriched {
                        continue;
                    }
                    for &(i, a) in acts {
                        v[i] *= (a * x[k]).exp();
                    }
                }
            }
        }
        v
    }
}

impl ModalTarget {
    /// The context of a population (with its log prior) and the error block `h` of g.
    fn ctx_of(&self, pop: Population, lp_pop: f64, h: &[f64]) -> Ctx {
        let (eps, delta) = self.errors.unpack(h);
        let bias = self.errors.bias(h);
        Ctx {
            pop,
            lp_pop,
            logs: modal::ErrorLogs::new(&eps, &delta)
                .with_model_error(&self.errors.unit_model_error_sd(h))
                .with_bias(&bias),
            eps,
            delta,
            bias,
        }
    }

    /// With a covariate effect, the ROM parameter vector of every condition of unit b
    /// (None where the coefficient makes a stiffness non-positive); `None` without one.
    pub fn condition_values(
        &self,
        b: usize,
        v: &[f64],
        x: &[f64],
    ) -> Option<Vec<Option<Vec<f64>>>> {
        let beta = x[self.covariate_coordinate()?];
        self.conditions_at(b, v, beta)
    }

    /// The unit coordinate holding the covariate's coefficient β_b (`None`: no covariate).
    fn covariate_coordinate(&self) -> Option<usize> {
        self.covariate.as_ref()?;
        match &self.compose {
            Compose::Boards { updated, .. } => Some(updated.len()),
            Compose::Joints { .. } => None,
        }
    }

    fn conditions_at(&self, b: usize, v: &[f64], beta: f64) -> Option<Vec<Option<Vec<f64>>>> {
        let e = self.covariate.as_ref()?;
        let conds = &self.units[b].conditions;
        Some(if conds.is_empty() {
            vec![Some(v.to_vec())]
        } else {
            conds.iter().map(|&c| e.at(v, beta, c)).collect()
        })
    }

    /// What unit b's terms are a function of, the inputs of its surrogate
    /// (`surrogate::fit_unit`): the ROM parameter vector, then, with a covariate, the unit's
    /// coefficient β_b (its terms then follow β_b through every condition's scaled moduli).
    pub fn surrogate_inputs(&self, aux: &[f64], b: usize, x: &[f64]) -> Vec<f64> {
        let mut v = self.values(aux, b, x);
        if let Some(k) = self.covariate_coordinate() {
            v.push(x[k]);
        }
        v
    }

    /// The eigenvalues unit b's terms carry: one per mode and condition.
    pub fn n_lambda(&self, b: usize) -> usize {
        let conds = match self.covariate_coordinate() {
            Some(_) => self.units[b].conditions.len().max(1),
            None => 1,
        };
        conds * self.predictor.refs.len()
    }

    /// Unit b's terms by the full ROM at surrogate inputs w ([`Self::surrogate_inputs`]);
    /// None where the ROM cannot track the updated modes (or a condition's stiffness is not
    /// positive).
    pub fn rom_terms_at(&self, b: usize, w: &[f64]) -> Option<Terms> {
        let data = &self.units[b];
        match self.covariate_coordinate() {
            None => {
                let p = self.predictor.predict(w)?;
                Some(self.predictor.terms(&p, data, w))
            }
            Some(_) => {
                let (v, beta) = w.split_at(w.len() - 1);
                let preds = self
                    .conditions_at(b, v, beta[0])?
                    .iter()
                    .map(|vk| self.predictor.predict(vk.as_ref()?))
                    .collect::<Option<Vec<_>>>()?;
                Some(self.predictor.terms_conditions(&preds, data, v))
            }
        }
    }

    /// Whether unit terms follow a covariate (then [`Target::model`] solves the full ROM at
    /// every condition and ignores [`Self::subspaces`]).
    pub fn has_covariate(&self) -> bool {
        self.covariate_coordinate().is_some()
    }
}

impl ModalTarget {
    /// [`Target::model`] of unit b at several points `xs` with the same auxiliary values:
    /// where the unit solves in its mode subspaces, the stiffness terms the points share
    /// are summed once ([`ModalPredictor::predict_in_modes_shared`]); elsewhere one point
    /// at a time, as [`Target::model`] does. The correction of step 2's particles to the
    /// ROM calls it per group (one step-1 draw, ten particles).
    pub fn model_shared(&self, aux: &[f64], b: usize, xs: &[&[f64]]) -> Vec<Option<Terms>> {
        let Some(Some(s)) = self.subspaces.get(b).filter(|_| !self.has_covariate()) else {
            return xs.iter().map(|x| Target::model(self, aux, b, x)).collect();
        };
        let data = &self.units[b];
        let vs: Vec<Vec<f64>> = xs.iter().map(|x| self.values(aux, b, x)).collect();
        let inside: Vec<usize> = (0..vs.len())
            .filter(|&i| s.region.box_position(&vs[i]) <= 1.0)
            .collect();
        let mut local: Vec<Option<modal::Prediction>> = vec![None; vs.len()];
        let preds = self.predictor.predict_in_modes_shared(
            &s.subs,
            &inside.iter().map(|&i| vs[i].as_slice()).collect::<Vec<_>>(),
        );
        for (&i, p) in inside.iter().zip(preds) {
            local[i] = p;
        }
        vs.iter()
            .zip(local)
            .map(|(v, local)| {
                let pred = match local {
                    Some(p) => p,
                    None => self.predictor.predict(v)?,
                };
                Some(
                    self.predictor
                        .terms(&pred, data, v)
                        .with_sufficient(data, self.errors.n_modes),
                )
            })
            .collect()
    }
}

impl Target for ModalTarget {
    type Cache = Terms;
    type Ctx = Ctx;
    fn n_global(&self) -> usize {
        self.prior.dim() + self.errors.dim()
    }
    fn n_units(&self) -> usize {
        self.units.len()
    }
    fn unit_dim(&self) -> usize {
        self.prior.d()
    }
    fn sample_prior(&self, rng: &mut ChaCha8Rng) -> (Vec<f64>, Vec<Vec<f64>>) {
        let mut g = self.prior.sample(rng);
        g.extend(self.errors.sample(rng));
        let pop = self.prior.unpack(&g);
        let d = self.prior.d();
        let x = (0..self.units.len())
            .map(|_| {
                let z: Vec<f64> = (0..d).map(|_| StandardNormal.sample(rng)).collect();
                pop.from_standard(&z)
            })
            .collect();
        (g, x)
    }
    fn log_prior_global(&self, g: &[f64]) -> f64 {
        let k = self.prior.dim();
        self.prior.log_prior(&g[..k]) + self.errors.log_prior(&g[k..])
    }
    fn ctx(&self, g: &[f64]) -> Ctx {
        let k = self.prior.dim();
        let (pop, lp_pop) = self.prior.unpack_with_prior(&g[..k]);
        self.ctx_of(pop, lp_pop, &g[k..])
    }
    fn ctx_with_prior(&self, g: &[f64]) -> (Ctx, f64) {
        let ctx = self.ctx(g);
        let lp = ctx.lp_pop + self.errors.log_prior(&g[self.prior.dim()..]);
        (ctx, lp)
    }
    fn ctx_after(&self, ctx: &Ctx, gn: &[f64], k: usize) -> (Ctx, f64) {
        // An error scale leaves the population (and its LKJ factor) as it was.
        let pd = self.prior.dim();
        if k < pd {
            return self.ctx_with_prior(gn);
        }
        let new = self.ctx_of(ctx.pop.clone(), ctx.lp_pop, &gn[pd..]);
        let lp = new.lp_pop + self.errors.log_prior(&gn[pd..]);
        (new, lp)
    }
    fn log_prior_unit(&self, ctx: &Ctx, _b: usize, x: &[f64]) -> f64 {
        ctx.pop.log_density(x)
    }
    fn unit_prior_normal(&self, ctx: &Ctx, _b: usize) -> Option<(Vec<f64>, Vec<f64>)> {
        Some((ctx.pop.mu.clone(), ctx.pop.l_cov.clone()))
    }
    fn centre_global_at(&self, g: &mut [f64], x: &[f64]) {
        // g starts with μ, in the units' own coordinates (population.rs).
        g[..x.len()].copy_from_slice(x);
    }
    fn data_start_global(&self, g: &[f64]) -> Option<(Vec<f64>, String)> {
        self.noise_restart(g)
    }
    fn collapsed_global(&self, g: &[f64]) -> Option<String> {
        self.collapsed_error_scale(g)
    }
    fn model(&self, aux: &[f64], b: usize, x: &[f64]) -> Option<Terms> {
        let data = &self.units[b];
        let t = if self.has_covariate() {
            self.rom_terms_at(b, &self.surrogate_inputs(aux, b, x))?
        } else {
            let v = self.values(aux, b, x);
            let local = match self.subspaces.get(b) {
                Some(Some(s)) if s.region.box_position(&v) <= 1.0 => {
                    self.predictor.predict_in_modes(&s.subs, &v)
                }
                _ => None,
            };
            let pred = match local {
                Some(p) => p,
                None => self.predictor.predict(&v)?,
            };
            self.predictor.terms(&pred, data, &v)
        };
        Some(t.with_sufficient(data, self.errors.n_modes))
    }
    fn log_lik(&self, ctx: &Ctx, b: usize, x: &[f64], c: &Terms) -> f64 {
        let direct: f64 = self
            .coord_obs
            .get(b)
            .into_iter()
            .flatten()
            .map(|&(k, value, sd)| normal_lpdf(value, x[k], sd))
            .sum();
        modal::log_lik_with(&self.units[b], c, &ctx.eps, &ctx.delta, &ctx.logs) + direct
    }
    fn to_standard(&self, ctx: &Ctx, _b: usize, x: &[f64]) -> Vec<f64> {
        ctx.pop.to_standard(x)
    }
    fn from_standard(&self, ctx: &Ctx, _b: usize, z: &[f64]) -> Vec<f64> {
        ctx.pop.from_standard(z)
    }
    fn global_role(&self, k: usize) -> GlobalRole {
        // g = (population parameters, error scales): the first enter the units' prior only,
        // the others their likelihood only.
        if k < self.prior.dim() {
            GlobalRole::UnitPrior
        } else {
            GlobalRole::Likelihood
        }
    }
    fn log_error_scales(&self) -> Vec<usize> {
        match self.errors.eps {
            ErrorPrior::Inferred { .. } => (0..self.errors.n_modes)
                .map(|m| self.prior.dim() + m)
                .collect(),
            ErrorPrior::Fixed { .. } => vec![],
        }
    }
    /// The mean relative eigenvalue residual λ_m / λ̂ − 1 over the unit's observations of
    /// mode m (each at its own condition).
    fn residual(&self, b: usize, m: usize, c: &Terms) -> Option<f64> {
        let nm = self.errors.n_modes;
        let (mut sum, mut n) = (0.0, 0usize);
        for f in self.units[b].freq.iter().filter(|f| f.mode == m) {
            sum += c.lambda[f.cond * nm + m] / f.lambda_hat - 1.0;
            n += 1;
        }
        (n > 0).then(|| sum / n as f64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bayes::modal::{FreqObs, ModalPredictor};

    fn covariate_target() -> (ModalTarget, Vec<usize>) {
        let (_, _, rom) = crate::bayes::modal::tests::free_rom();
        let names = rom.map.names.clone();
        let pos = |n: &str| names.iter().position(|m| m == n).expect("parameter");
        let updated = vec![pos("e_x_pa"), pos("e_y_pa"), pos("g_xy_pa")];
        let reference = updated.iter().map(|&i| rom.map.nominal[i]).collect();
        let predictor = ModalPredictor::new(rom, &[0, 1, 2, 3], 12.7).expect("predictor");
        let unit = UnitData {
            conditions: vec![-2.0, 3.0],
            ..UnitData::default()
        };
        let t = ModalTarget {
            predictor,
            compose: Compose::Boards {
                updated: updated.clone(),
                reference,
                log: vec![],
                per_mass: None,
                total_mass: None,
            },
            prior: PopulationPrior {
                mu_mean: vec![0.0; 4],
                mu_sd: vec![0.1, 0.1, 0.1, 0.005],
                sigma_scale: vec![0.05, 0.05, 0.05, 0.001],
                sigma_prior: vec![],
                lkj_eta: 2.0,
                lkj_log_norm: Default::default(),
            },
            errors: ErrorModel {
                n_modes: 4,
                eps: ErrorPrior::Fixed { value: 1e-4 },
                delta: None,
                model_error_sd: None,
                discrepancy: None,
            },
            units: vec![unit],
            covariate: Some(CovariateEffect {
                name: "temperature_coefficient_per_k".into(),
                covariate: "temperature_c".into(),
                reference: 23.0,
                scaled: updated.clone(),
            }),
            subspaces: vec![],
            coord_obs: vec![],
        };
        (t, updated)
    }

    /// The reference's restart from the data: a mode whose ε in g sits more than tenfold above
    /// the scatter of the units' repeated measurements of it is moved to that scatter, the
    /// others are left as they are; a mode measured once per unit, or with fewer than three
    /// degrees of freedom, never overrules g; a fixed ε never restarts.
    #[test]
    fn a_noise_scale_far_above_the_repeat_scatter_restarts_the_search() {
        let (mut t, _) = covariate_target();
        t.covariate = None;
        t.errors.eps = ErrorPrior::Inferred {
            median: 1e-3,
            log_sd: 1.0,
        };
        // Mode 0: two units, λ̂ 0.99, 1.01 and 1.98, 1.98, 2.04 (relative deviations ±0.01 and
        // −0.01, −0.01, +0.02: Σ = 2e-4 + 6e-4 over 1 + 2 dof); mode 1: three
        // repeats of one unit only (2 dof); mode 2: once per unit; mode 3: none.
        let obs = |m: usize, l: f64| FreqObs::new(m, l);
        let a = UnitData {
            freq: vec![
                obs(0, 0.99),
                obs(0, 1.01),
                obs(1, 5.0),
                obs(1, 5.05),
                obs(1, 4.95),
                obs(2, 3.0),
            ],
            ..UnitData::default()
        };
        let b = UnitData {
            freq: vec![obs(0, 1.98), obs(0, 1.98), obs(0, 2.04), obs(2, 3.1)],
            ..UnitData::default()
        };
        t.units = vec![a, b];
        let sc = modal::repeat_scatter(&t.units, 4);
        let s0 = ((2.0 * 0.01f64.powi(2) + 2.0 * 0.01f64.powi(2) + 0.02f64.powi(2)) / 3.0).sqrt();
        let (v0, d0) = sc[0].expect("mode 0 repeated");
        assert!((v0 - s0).abs() < 1e-12 * s0, "{v0} vs {s0}");
        assert_eq!(d0, 3);
        assert_eq!(sc[1].map(|x| x.1), Some(2));
        assert_eq!((sc[2], sc[3]), (None, None));
        let k0 = t.prior.dim();
        let mut g = vec![0.0; t.n_global()];
        // ε of every mode at 9 × mode 0's scatter: no restart.
        g[k0..k0 + 4].iter_mut().for_each(|v| *v = (9.0 * s0).ln());
        assert!(t.noise_restart(&g).is_none());
        // Mode 0 at 11 ×, modes 1-3 far above anything: only mode 0 restarts.
        g[k0] = (11.0 * s0).ln();
        g[k0 + 1..k0 + 4].iter_mut().for_each(|v| *v = 1.0f64.ln());
        let (g2, why) = t.noise_restart(&g).expect("a restart");
        assert!((g2[k0] - s0.ln()).abs() < 1e-12, "{why}");
        assert_eq!(&g2[k0 + 1..], &g[k0 + 1..]);
        assert_eq!(&g2[..k0], &g[..k0]);
        assert!(why.contains("mode 0") && !why.contains("mode 1"), "{why}");
        t.errors.eps = ErrorPrior::Fixed { value: 1e-4 };
        assert!(t.noise_restart(&g[..t.n_global()]).is_none());
    }

    /// An error scale more than five prior sds below its prior's median is a collapse; four
    /// are not; a δ is judged against δ's prior, and fixed scales have no coordinates.
    #[test]
    fn an_error_scale_far_below_its_prior_is_a_collapsed_search() {
        let (mut t, _) = covariate_target();
        t.covariate = None;
        let (med_e, sd_e, med_d, sd_d) = (5e-3f64, 1.5, 0.1f64, 1.0);
        t.errors.eps = ErrorPrior::Inferred {
            median: med_e,
            log_sd: sd_e,
        };
        t.errors.delta = Some(ErrorPrior::Inferred {
            median: med_d,
            log_sd: sd_d,
        });
        let (k0, n) = (t.prior.dim(), t.errors.n_modes);
        let mut g = vec![0.0; t.n_global()];
        g[k0..k0 + n]
            .iter_mut()
            .for_each(|v| *v = med_e.ln() - 4.9 * sd_e);
        g[k0 + n..k0 + 2 * n]
            .iter_mut()
            .for_each(|v| *v = med_d.ln() - 4.9 * sd_d);
        assert!(t.collapsed_error_scale(&g).is_none());
        g[k0 + 1] = med_e.ln() - 5.1 * sd_e;
        let why = t.collapsed_error_scale(&g).expect("ε of mode 1 collapsed");
        assert!(
            why.starts_with("mode 1: ε") && why.contains("5.1 prior sds"),
            "{why}"
        );
        g[k0 + 1] = med_e.ln();
        // δ's coordinate at ε's collapse level is 4.9 of its own sds below: fine.
        g[k0 + n + 2] = med_d.ln() - 4.9 * sd_d;
        assert!(t.collapsed_error_scale(&g).is_none());
        g[k0 + n + 2] = med_d.ln() - 5.5 * sd_d;
        let why = t.collapsed_error_scale(&g).expect("δ of mode 2 collapsed");
        assert!(why.starts_with("mode 2: δ"), "{why}");
        // With ε fixed, δ's block starts at k0.
        t.errors.eps = ErrorPrior::Fixed { value: 1e-4 };
        let g2 = [&g[..k0], &g[k0 + n..]].concat();
        let why = t.collapsed_error_scale(&g2).expect("δ of mode 2 collapsed");
        assert!(why.starts_with("mode 2: δ"), "{why}");
    }

    /// With a covariate effect, a board's terms hold one prediction per condition, each the
    /// ROM's at the moduli scaled by 1 + β c (condition-major); the likelihood reads each
    /// observation's own condition, so data made at β = −0.004 favour β = −0.004 over 0 and
    /// over −0.003 decisively.
    #[test]
    fn covariate_conditions_are_the_rom_at_the_scaled_moduli() {
        let (mut t, scaled) = covariate_target();
        let x = [0.01, -0.02, 0.015, -0.004];
        let terms = t.model(&[], 0, &x).expect("terms");
        let v = t.values(&[], 0, &x);
        let nm = 4;
        assert_eq!(terms.lambda.len(), 2 * nm);
        for (k, c) in [-2.0, 3.0].into_iter().enumerate() {
            let mut vk = v.clone();
            for &i in &scaled {
                vk[i] *= 1.0 + x[3] * c;
            }
            let direct = t.predictor.predict(&vk).expect("direct");
            for m in 0..nm {
                assert_eq!(
                    terms.lambda[k * nm + m],
                    direct.lambda[m],
                    "condition {k} mode {m}"
                );
            }
        }
        // β < 0: the warmer condition (c = 3) is the softer.
        assert!(terms.lambda[nm] < terms.lambda[0]);
        // Observations at both conditions, exact at β = −0.004.
        t.units[0].freq = (0..2 * nm)
            .map(|s| FreqObs {
                cond: s / nm,
                ..FreqObs::new(s % nm, terms.lambda[s])
            })
            .collect();
        let ctx = t.ctx(&{
            let mut rng = <ChaCha8Rng as rand::SeedableRng>::seed_from_u64(1);
            let mut g = t.prior.sample(&mut rng);
            g.extend(t.errors.sample(&mut rng));
            g
        });
        let ll = |beta: f64| {
            let mut xb = x;
            xb[3] = beta;
            let c = t.model(&[], 0, &xb).expect("terms");
            t.log_lik(&ctx, 0, &xb, &c)
        };
        let (at, zero, near) = (ll(-0.004), ll(0.0), ll(-0.003));
        assert!(at - zero > 100.0 && at - near > 10.0, "{at} {zero} {near}");
    }

    /// With a covariate the surrogate's inputs end with the unit's coefficient β_b: the
    /// surrogate fitted over (moduli, β) holds both conditions' eigenvalues, and on fresh
    /// points its log-likelihood is the per-condition ROM's within its verified tolerance,
    /// β moving it as the ROM does (before, a covariate refit ran without surrogates).
    #[test]
    fn a_covariate_surrogate_follows_the_coefficient_through_every_condition() {
        use crate::bayes::surrogate::{fit_unit, SurrogateOptions};
        use rand::RngExt;
        let (mut t, _) = covariate_target();
        let x0 = [0.01, -0.02, 0.015, -0.004];
        let exact = t.model(&[], 0, &x0).expect("terms");
        t.units[0].freq = (0..8)
            .map(|s| FreqObs {
                cond: s / 4,
                ..FreqObs::new(s % 4, exact.lambda[s])
            })
            .collect();
        assert_eq!(t.n_lambda(0), 8);
        let mut rng = <ChaCha8Rng as rand::SeedableRng>::seed_from_u64(3);
        let spread = [2e-4, 2e-4, 2e-4, 2e-4];
        let near = |rng: &mut ChaCha8Rng| -> Vec<f64> {
            x0.iter()
                .zip(&spread)
                .map(|(v, s)| v + s * (2.0 * rng.random::<f64>() - 1.0))
                .collect()
        };
        let samples: Vec<Vec<f64>> = (0..300)
            .map(|_| t.surrogate_inputs(&[], 0, &near(&mut rng)))
            .collect();
        let w = samples[0].len();
        assert_eq!(w, t.values(&[], 0, &x0).len() + 1);
        let eps = vec![1e-4; 4];
        let opts = SurrogateOptions::default();
        let s = fit_unit(&t, 0, &samples, &eps, &[], &opts, 5).expect("a surrogate");
        assert!(s.inputs.contains(&(w - 1)), "β is an input: {:?}", s.inputs);
        let ll = |c: &Terms| modal::log_lik(&t.units[0], c, &eps, &[]);
        let (mut inside, mut worst) = (0, 0.0f64);
        for _ in 0..200 {
            let x = near(&mut rng);
            let Some(ts) = s.terms(&t.surrogate_inputs(&[], 0, &x)) else {
                continue;
            };
            inside += 1;
            assert_eq!(ts.lambda.len(), 8);
            let tr = t.model(&[], 0, &x).expect("ROM");
            worst = worst.max((ll(&ts) - ll(&tr)).abs());
        }
        assert!(inside > 150, "{inside} of 200 in the box");
        assert!(
            worst <= 3.0 * opts.tolerance_dll,
            "max |Δ log L| {worst:.3e}"
        );
        // β alone moves the surrogate's likelihood as it moves the ROM's.
        let mut xb = x0;
        xb[3] += 1e-4;
        let ts = s.terms(&t.surrogate_inputs(&[], 0, &xb)).expect("inside");
        let tr = t.model(&[], 0, &xb).expect("ROM");
        let drop_rom = ll(&exact) - ll(&tr);
        assert!(drop_rom > 1.0, "{drop_rom}");
        assert!(
            (ll(&ts) - ll(&tr)).abs() < 0.1 * drop_rom,
            "{} vs {}",
            ll(&ts),
            ll(&tr)
        );
    }

    /// Moduli per unit mass: p_k = reference_k (1 + x_k)(1 + x_m) for a modulus, the mass
    /// scale itself as it is; so modulus over mass scale follows x_k alone (a move of x_m
    /// leaves it), and `relative_params` is each parameter over its reference, minus 1.
    #[test]
    fn per_mass_coordinates_hold_modulus_over_mass_scale() {
        let (_, _, rom) = crate::bayes::modal::tests::free_rom();
        let names = rom.map.names.clone();
        let pos = |n: &str| names.iter().position(|m| m == n).expect("parameter");
        let updated = vec![pos("e_x_pa"), pos("g_xy_pa"), pos("mass_scale")];
        let reference: Vec<f64> = updated.iter().map(|&i| rom.map.nominal[i]).collect();
        let (mut t, _) = covariate_target();
        t.covariate = None;
        t.compose = Compose::Boards {
            updated: updated.clone(),
            reference: reference.clone(),
            log: vec![],
            per_mass: Some(PerMass {
                mass: 2,
                specific: vec![true, true, false],
            }),
            total_mass: None,
        };
        let ratio = |x: &[f64]| {
            let v = t.values(&[], 0, x);
            [v[updated[0]] / v[updated[2]], v[updated[1]] / v[updated[2]]]
        };
        let x = [0.02, -0.01, 0.03];
        let v = t.values(&[], 0, &x);
        assert_eq!(v[updated[2]], reference[2] * 1.03);
        let e = reference[0] * 1.02 * 1.03;
        assert!(
            (v[updated[0]] - e).abs() <= 1e-12 * e,
            "{} {e}",
            v[updated[0]]
        );
        let (a, b) = (ratio(&x), ratio(&[0.02, -0.01, -0.05]));
        for k in 0..2 {
            assert!((a[k] - b[k]).abs() <= 1e-12 * a[k], "{a:?} {b:?}");
            let want = reference[k] / reference[2] * (1.0 + x[k]);
            assert!((a[k] - want).abs() <= 1e-12 * want, "{} {want}", a[k]);
        }
        let rel = t.compose.relative_params(&x);
        for (k, &i) in updated.iter().enumerate() {
            let r = v[i] / reference[k] - 1.0;
            assert!((rel[k] - r).abs() < 1e-14, "{k}: {} {r}", rel[k]);
        }
    }

    /// Beside a point mass the mass coordinate is the weighed total: whatever the point
    /// mass's coordinate, the board's mass scale and the point mass add up to
    /// (M₀ + m_ref)(1 + x_T), and the moduli per unit mass follow the board's own mass scale.
    #[test]
    fn a_total_mass_coordinate_holds_the_weighed_total_whatever_the_point_mass() {
        let (m0_g, m_ref_g) = (12.7, 0.127);
        let t = TotalMass {
            mass: 1,
            point: 2,
            ratio: m_ref_g / m0_g,
        };
        let c = Compose::Boards {
            updated: vec![0, 1, 2],
            reference: vec![2.0e10, 1.0, 1e-3 * m_ref_g],
            log: vec![false, false, true],
            per_mass: Some(PerMass {
                mass: 1,
                specific: vec![true, false, false],
            }),
            total_mass: Some(t.clone()),
        };
        let x_t = 3e-4;
        for x_a in [-4.0, -1.0, 0.0, 0.7, 2.5] {
            let x = [0.01, x_t, x_a];
            let rel = c.relative_params(&x);
            let total = m0_g * (1.0 + rel[1]) + m_ref_g * rel[2].exp();
            let want = (m0_g + m_ref_g) * (1.0 + x_t);
            assert!(
                (total - want).abs() <= 1e-13 * want,
                "{x_a}: {total} {want}"
            );
            // The modulus per unit mass scale is 1 + x_0 of its reference, as without a
            // point mass.
            assert!(((1.0 + rel[0]) / (1.0 + rel[1]) - 1.01).abs() < 1e-14);
            assert_eq!(rel[2], x_a);
            let x_m = t.board_mass_coordinate(&x);
            assert!((t.total_coordinate(x_m, x_a) - x_t).abs() < 1e-15);
        }
        // At the point mass's reference, x_T = 0 is the nominal board.
        assert!(t.board_mass_coordinate(&[0.0, 0.0, 0.0]).abs() < 1e-15);
    }

    /// Step 2 carries a board's coefficient in aux after its parameters and scales the
    /// moduli of each bolted measurement by 1 + β_b c_b.
    #[test]
    fn joints_compose_scales_the_board_moduli_by_the_measurement_covariate() {
        let (t, scaled) = covariate_target();
        let nominal = t.predictor.rom.map.nominal.clone();
        let board_params = scaled.clone();
        let mut tj = t.clone();
        tj.covariate = None;
        tj.compose = Compose::Joints {
            board_params: board_params.clone(),
            unit_board: vec![1, 0],
            coords: vec![],
            reference: vec![],
            covariate: Some(JointsCovariate {
                block: 4,
                coef: 3,
                scaled: scaled.clone(),
                offsets: vec![2.5, -1.0],
            }),
            enriched_units: None,
        };
        // Two boards: [e_x, e_y, g_xy, β] each.
        let aux: Vec<f64> = [1.0, 1.01]
            .iter()
            .zip([-0.004, -0.003])
            .flat_map(|(f, beta)| {
                board_params
                    .iter()
                    .map(|&i| nominal[i] * f)
                    .chain(std::iter::once(beta))
                    .collect::<Vec<_>>()
            })
            .collect();
        // Unit 0 is on board 1 (β −0.003, c 2.5), unit 1 on board 0 (β −0.004, c −1).
        for (b, (f, beta, c)) in [(1.01, -0.003, 2.5), (1.0, -0.004, -1.0)]
            .into_iter()
            .enumerate()
        {
            let v = tj.values(&aux, b, &[]);
            for &i in &scaled {
                let want = nominal[i] * f * (1.0 + beta * c);
                assert!((v[i] / want - 1.0).abs() < 1e-14, "unit {b} parameter {i}");
            }
        }
    }

    /// With `enriched_units`, an enrichment's own coordinates (1..) act only on the units
    /// named; the contact stiffness (coordinate 0) on every unit.
    #[test]
    fn an_enrichment_acts_only_on_its_units() {
        let (t, scaled) = covariate_target();
        let nominal = t.predictor.rom.map.nominal.clone();
        let (i0, i1) = (scaled[0], scaled[1]);
        let mut tj = t.clone();
        tj.covariate = None;
        tj.compose = Compose::Joints {
            board_params: vec![],
            unit_board: vec![0, 0],
            coords: vec![vec![(i0, 1.0)], vec![(i1, 1.0)]],
            reference: vec![],
            covariate: None,
            enriched_units: Some(vec![false, true]),
        };
        let x = [0.1, -0.4];
        let v0 = tj.values(&[], 0, &x);
        let v1 = tj.values(&[], 1, &x);
        assert!((v0[i0] / (nominal[i0] * 0.1f64.exp()) - 1.0).abs() < 1e-14);
        assert!((v0[i1] / nominal[i1] - 1.0).abs() < 1e-14, "not enriched");
        assert!((v1[i0] / (nominal[i0] * 0.1f64.exp()) - 1.0).abs() < 1e-14);
        assert!((v1[i1] / (nominal[i1] * (-0.4f64).exp()) - 1.0).abs() < 1e-14);
    }

    /// The error block's prior is the sum of its blocks' own priors: ε's and δ's log-normal
    /// per mode, and the discrepancy's (ln τ, ln σ_u, w). A δ prior that read past its block
    /// put its log-normal on ln τ, ln σ_u and w as well (measured: τ's prior median doubled
    /// and its log-sd shrank to 0.83).
    #[test]
    fn the_error_prior_is_the_sum_of_its_blocks() {
        use crate::bayes::discrepancy::Discrepancy;
        let nm = 4;
        let sens = [1.0, 0.9, 1.1, 0.4];
        let disc = Discrepancy::new(&sens, nm, 1, &[], 0.005, &[]).expect("k = 3");
        let eps = (0.004, 1.5);
        let delta = (0.1, 1.5);
        let e = ErrorModel {
            n_modes: nm,
            eps: ErrorPrior::Inferred {
                median: eps.0,
                log_sd: eps.1,
            },
            delta: Some(ErrorPrior::Inferred {
                median: delta.0,
                log_sd: delta.1,
            }),
            model_error_sd: None,
            discrepancy: Some(disc.clone()),
        };
        let mut rng = <ChaCha8Rng as rand::SeedableRng>::seed_from_u64(7);
        for _ in 0..5 {
            let h = e.sample(&mut rng);
            assert_eq!(h.len(), 2 * nm + disc.dim());
            let want = h[..nm]
                .iter()
                .map(|&v| normal_lpdf(v, eps.0.ln(), eps.1))
                .sum::<f64>()
                + h[nm..2 * nm]
                    .iter()
                    .map(|&v| normal_lpdf(v, delta.0.ln(), delta.1))
                    .sum::<f64>()
                + disc.log_prior(&h[2 * nm..]);
            let got = e.log_prior(&h);
            assert!((got - want).abs() < 1e-12, "{got} vs {want}");
        }
    }
}

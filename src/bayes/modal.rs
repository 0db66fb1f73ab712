//! The modal likelihood after Vanik, Beck & Au (2000), over a ROM, as plain data and pure
//! functions: what a unit's measurements are ([`UnitData`]), what the model predicts for
//! them ([`ModalPredictor::predict`], [`Terms`]) and the log-likelihood given the
//! prediction-error scales ([`log_lik`]).
//!
//! Per measurement r and updated mode m:
//! - eigenvalue term: λ̂_rm ~ N(λ_m(θ), (ε_m λ̂_rm)²), λ = (2π f)², ε_m the relative
//!   prediction error of mode m (measurement scatter and model error together);
//! - shape term: the measured shape u (unit norm, at the measurement's valid scan points,
//!   points flagged by `extract` left out) is a ψ(θ) + e with the optimal scale a and
//!   e ~ N(0, δ_m²/n · I), n points; with a profiled out, ‖u − aψ‖² = 1 − MAC(u, ψ), so
//!   log L = −(n/2) ln(2π δ_m²/n) − n (1 − MAC)/(2 δ_m²).
//!   MAC is formed in the ROM's reduced coordinates: ψ = P y with P the reduced shape
//!   operator at the points, so uᵀψ = (Pᵀu)ᵀ y and ψᵀψ = yᵀ (PᵀP) y: the r-vector Pᵀu and the
//!   r × r Gram matrix PᵀP are precomputed once per observation, and no shape is ever
//!   expanded to the points in the sampler's hot path;
//! - mass term: the balance mean m̂ ~ N(m(θ), s²), s from `update::problem::mass_obs`.
//!
//! Mode tracking: the model's modes are matched to the updated labels by the largest
//! overlap |yᵀ y_ref| with the label's reduced vector at the ROM centre (M₀-inner product,
//! since the ROM basis is M₀-orthonormal), not by their order, so a mode swap inside the
//! box does not mix labels. A label whose best overlap falls below 1/√2 is lost and the
//! model is undefined there.

use crate::fem::rom::Rom;

use super::stats::LN_2PI;

/// One eigenvalue observation.
#[derive(Clone, Debug)]
pub struct FreqObs {
    /// Index of the updated mode.
    pub mode: usize,
    /// Measured eigenvalue (2π f̂)², rad²/s².
    pub lambda_hat: f64,
    /// ln λ̂ (precomputed: the likelihood's hot path).
    pub ln_lambda_hat: f64,
    /// The measurement's condition: index into [`UnitData::conditions`] (0 without any).
    pub cond: usize,
}

impl FreqObs {
    pub fn new(mode: usize, lambda_hat: f64) -> FreqObs {
        FreqObs {
            mode,
            lambda_hat,
            ln_lambda_hat: lambda_hat.ln(),
            cond: 0,
        }
    }
}

/// A covariate that scales some of the model's stiffness parameters per measurement:
/// p(c) = p_ref (1 + β_b c) for the parameters it acts on (the FR-4 moduli against the
/// sheet's temperature: the diagnosis's `temperature_stiffness`), c the measurement's
/// covariate relative to `reference`, β_b the unit's coefficient (an extra unit coordinate
/// with its population). The model is evaluated at every distinct condition of a unit
/// ([`UnitData::conditions`]): exact, no sensitivity expansion (a free-free campaign's
/// eigenvalues scatter by 2e-5–1e-4, below what a first-order expansion in β c keeps).
#[derive(Clone, Debug)]
pub struct CovariateEffect {
    /// The coefficient's column name, unit in the name (e.g. `temperature_coefficient_per_k`).
    pub name: String,
    /// The sheet column the covariate comes from.
    pub covariate: String,
    /// The covariate's reference value (the mean over the measurements used).
    pub reference: f64,
    /// Indices of the scaled ROM parameters.
    pub scaled: Vec<usize>,
}

impl CovariateEffect {
    /// The ROM parameter vector of condition c for coefficient β; None where 1 + β c ≤ 0.
    pub fn at(&self, values: &[f64], beta: f64, c: f64) -> Option<Vec<f64>> {
        let f = 1.0 + beta * c;
        if f.is_nan() || f <= 0.0 {
            return None;
        }
        let mut v = values.to_vec();
        for &i in &self.scaled {
            v[i] *= f;
        }
        Some(v)
    }
}

/// One mode-shape observation, reduced to what the likelihood needs.
#[derive(Clone, Debug)]
pub struct ShapeObs {
    pub mode: usize,
    /// Pᵀu, length r (u = measured shape at the valid points, unit norm).
    pub pt_u: Vec<f64>,
    /// Index of PᵀP in [`UnitData::grams`] (measurements with the same valid points share
    /// one, so yᵀ(PᵀP)y is formed once per mode and point set).
    pub gram: usize,
    /// Valid scan points n.
    pub n_points: usize,
    /// ln n (precomputed).
    pub ln_n: f64,
    /// The measurement's condition (index into [`UnitData::conditions`]).
    pub cond: usize,
    /// The power of this observation's term (1: an independent observation; below 1 where the
    /// mode's shapes share an error between measurements, [`super::shape_weight`]).
    pub weight: f64,
    /// The shape at its scan points with the model's interpolation there (to estimate the
    /// weight from the residuals; the likelihood uses `pt_u` and the Gram matrix); `None`
    /// where not kept.
    pub points: Option<std::sync::Arc<super::shape_weight::PointShape>>,
}

/// A balance observation of a board's mass.
#[derive(Clone, Debug)]
pub struct MassObs {
    pub mass_g: f64,
    pub sd_g: f64,
}

/// Everything measured on one unit.
#[derive(Clone, Debug, Default)]
pub struct UnitData {
    pub freq: Vec<FreqObs>,
    pub shapes: Vec<ShapeObs>,
    /// Distinct Gram matrices PᵀP (r × r row-major) of the shape observations.
    pub grams: Vec<Vec<f64>>,
    pub mass: Option<MassObs>,
    /// The covariate of each distinct condition of the unit's measurements, relative to the
    /// effect's reference ([`CovariateEffect`]); empty without one (a single condition).
    pub conditions: Vec<f64>,
}

/// Per updated mode, the scatter of the units' repeated eigenvalue measurements: the pooled
/// sd of λ̂ relative to its mean over each unit's measurements of the mode in one condition,
/// with its degrees of freedom (Σ (n − 1) over those groups). It is the measurement noise ε
/// (relative, on eigenvalues) estimated without the model: a unit's parameters are the same
/// in every repeat, so the model cannot explain any of it. None for a mode no unit measured
/// twice in one condition.
pub fn repeat_scatter(units: &[UnitData], n_modes: usize) -> Vec<Option<(f64, usize)>> {
    let mut ss = vec![0.0; n_modes];
    let mut dof = vec![0usize; n_modes];
    for u in units {
        // (mode, condition) → the unit's λ̂ there.
        let mut groups: std::collections::BTreeMap<(usize, usize), Vec<f64>> =
            std::collections::BTreeMap::new();
        for f in &u.freq {
            if f.mode < n_modes && f.lambda_hat.is_finite() && f.lambda_hat > 0.0 {
                groups
                    .entry((f.mode, f.cond))
                    .or_default()
                    .push(f.lambda_hat);
            }
        }
        for ((m, _), l) in groups {
            if l.len() < 2 {
                continue;
            }
            let mean = l.iter().sum::<f64>() / l.len() as f64;
            ss[m] += l.iter().map(|v| (v / mean - 1.0).powi(2)).sum::<f64>();
            dof[m] += l.len() - 1;
        }
    }
    (0..n_modes)
        .map(|m| (dof[m] > 0).then(|| ((ss[m] / dof[m] as f64).sqrt(), dof[m])))
        .collect()
}

/// Per-mode blocks of [`Terms::suff`] (then one scalar).
const SUFF_BLOCKS: usize = 6;

/// The model's prediction for one unit at one parameter point.
#[derive(Clone, Debug)]
pub struct Terms {
    /// λ_m of every updated mode, per condition (condition-major: λ of mode m in condition
    /// k at k · n_modes + m; one condition without a covariate).
    pub lambda: Vec<f64>,
    /// 1 − MAC of every shape observation (same order as `UnitData::shapes`).
    pub one_minus_mac: Vec<f64>,
    /// Model mass, g.
    pub mass_g: f64,
    /// The unit's log-likelihood reduced to per-mode sums that do not depend on ε or δ
    /// ([`Terms::with_sufficient`]); empty where not formed. With them a change of the
    /// global vector (ε, δ, the population) re-prices a unit in O(modes), not O(data).
    pub suff: Vec<f64>,
}

impl Terms {
    /// These terms with the per-mode sufficient statistics of `data` for `n_modes`
    /// updated modes: Σ u² and the count of eigenvalue terms, Σ w n (1 − MAC) and Σ w n of the
    /// shape terms, Σ u v and Σ v² (u = (λ̂ − λ)/λ̂, v = λ/λ̂: with a model error b the
    /// residual is u − b v, so Σ (u − b v)² = Σu² − 2b Σuv + b² Σv², see [`log_lik_with`]),
    /// then everything else (normalising constants, the mass term).
    pub fn with_sufficient(mut self, data: &UnitData, n_modes: usize) -> Terms {
        let nm = n_modes;
        let mut s = vec![0.0; SUFF_BLOCKS * nm + 1];
        let mut rest = 0.0;
        for f in &data.freq {
            let lambda = self.lambda[f.cond * nm + f.mode];
            let r = (f.lambda_hat - lambda) / f.lambda_hat;
            let v = lambda / f.lambda_hat;
            s[f.mode] += r * r;
            s[nm + f.mode] += 1.0;
            s[4 * nm + f.mode] += r * v;
            s[5 * nm + f.mode] += v * v;
            rest += 0.5 * LN_2PI + f.ln_lambda_hat;
        }
        for (o, omm) in data.shapes.iter().zip(&self.one_minus_mac) {
            // n points of a term raised to the power w: w n in the sums, as in `log_lik_with`.
            let n = o.weight * o.n_points as f64;
            s[2 * nm + o.mode] += n * omm;
            s[3 * nm + o.mode] += n;
            rest += 0.5 * n * (LN_2PI - o.ln_n);
        }
        if let Some(m) = &data.mass {
            let z = (m.mass_g - self.mass_g) / m.sd_g;
            rest += 0.5 * (LN_2PI + z * z) + m.sd_g.ln();
        }
        s[SUFF_BLOCKS * nm] = rest;
        self.suff = s;
        self
    }
}

/// The ROM with the updated modes' references: the forward model of a unit.
#[derive(Clone, Debug)]
pub struct ModalPredictor {
    pub rom: Rom,
    /// Reference reduced vectors (unit norm) of the updated modes at the ROM centre.
    pub refs: Vec<Vec<f64>>,
    /// Modes computed per evaluation (covers the references plus a margin for swaps).
    pub n_track: usize,
    /// Position of `mass_scale` among the ROM's parameters, if any, and the model mass
    /// at the ROM centre in g.
    pub mass_scale_idx: Option<usize>,
    pub nominal_mass_g: f64,
    /// Parameters that are lumped masses in kg ([`crate::fem::FeModel::add_point_mass_param`]),
    /// weighed with the board: they add to the mass, not to `nominal_mass_g`, which is the
    /// board's alone.
    pub point_mass_idx: Vec<usize>,
    /// Where the core thickness is a parameter ([`crate::fem::ModelOptions::core_thickness`]):
    /// its index, its nominal value (m) and the core's share of `nominal_mass_g`, the part
    /// of the mass that follows the thickness.
    pub core_thickness: Option<(usize, f64, f64)>,
}

/// Prediction of the updated modes: eigenvalues and reduced vectors in label order.
#[derive(Clone, Debug)]
pub struct Prediction {
    pub lambda: Vec<f64>,
    pub vectors: Vec<Vec<f64>>,
}

/// One updated mode's subspace of the ROM ([`ModalPredictor::mode_subspaces`]) and the
/// mode's reference vector projected into it.
#[derive(Clone, Debug)]
pub struct ModeSubspace {
    pub sub: crate::fem::rom::SubspaceRom,
    target: Vec<f64>,
}

/// Whether the ROM can be evaluated at `values` (its full parameter vector): every value finite,
/// every one but Poisson's ratio positive, and the core's Poisson ratios admissible
/// (ν_xy² E_y/E_x < 1).
pub fn admissible(map: &crate::fem::params::ParamMap, values: &[f64]) -> bool {
    let finite_positive = map
        .names
        .iter()
        .zip(values)
        .all(|(n, v)| v.is_finite() && (n == crate::fem::params::names::NU_XY || *v > 0.0));
    let [ix, iy, _, inu] = map.core_idx;
    finite_positive && values[inu] * values[inu] * values[iy] / values[ix] < 1.0
}

/// Which model mode carries each label: per reference shape (unit length, in the ROM's
/// coordinates), the index among `vectors`, or `None` where the label is lost. Greedy by
/// overlap |yᵀr|/‖y‖, ties broken by (label, mode) order so that the result is deterministic;
/// a mode carries one label at most. A few modes: a full Hungarian step is not needed.
///
/// A mode carries a label when its overlap is at least 1/√2 (no other mode can overlap as
/// much), or when two modes veer and share the label's shape, as a board mode does with the
/// fixture's resonance or with another mode crossing it: the label then follows the larger
/// share, provided the two together hold at least half of the reference (o² + o₂² ≥ ½) and
/// this one at least a quarter (o ≥ ½). With the 1/√2 rule alone every draw where a mode
/// hybridised had no prediction, and the posterior was pushed away from the physics that
/// hybridises it (a fixture mass at the edge of its box instead of the truth).
pub fn assign_labels(refs: &[Vec<f64>], vectors: &[Vec<f64>]) -> Vec<Option<usize>> {
    let nt = vectors.len();
    let norms: Vec<f64> = vectors
        .iter()
        .map(|y| y.iter().map(|a| a * a).sum::<f64>().sqrt())
        .collect();
    let mut pairs: Vec<(f64, usize, usize)> = Vec::with_capacity(refs.len() * nt);
    for (m, r) in refs.iter().enumerate() {
        for (j, y) in vectors.iter().enumerate() {
            let o = y.iter().zip(r).map(|(a, b)| a * b).sum::<f64>().abs() / norms[j];
            pairs.push((o, m, j));
        }
    }
    // Per label, its two largest overlaps (pairs are still in label-major order here).
    let top2: Vec<(f64, f64)> = (0..refs.len())
        .map(|m| {
            pairs[m * nt..(m + 1) * nt]
                .iter()
                .fold(
                    (0.0, 0.0),
                    |(a, b), &(o, _, _)| {
                        if o > a {
                            (o, a)
                        } else {
                            (a, b.max(o))
                        }
                    },
                )
        })
        .collect();
    let tracks = |o: f64, m: usize| {
        if o >= std::f64::consts::FRAC_1_SQRT_2 {
            return true;
        }
        let (a, b) = top2[m];
        let other = if o >= a { b } else { a };
        o >= 0.5 && o * o + other * other >= 0.5
    };
    pairs.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
    let mut out = vec![None; refs.len()];
    let mut done = vec![false; refs.len()];
    let mut taken = vec![false; nt];
    for (o, m, j) in pairs {
        if done[m] || taken[j] {
            continue;
        }
        // Every later pair of this label overlaps less: if this one does not carry it, the
        // label is lost.
        done[m] = true;
        if tracks(o, m) {
            taken[j] = true;
            out[m] = Some(j);
        }
    }
    out
}

impl ModalPredictor {
    /// `ref_modes`: for every updated mode, its 0-based index among the ROM's modes at the
    /// centre.
    pub fn new(
        rom: Rom,
        ref_modes: &[usize],
        nominal_mass_g: f64,
    ) -> Result<ModalPredictor, crate::fem::FemError> {
        let max = ref_modes.iter().copied().max().unwrap_or(0);
        if max >= rom.n_modes {
            return Err(crate::fem::FemError::Request(format!(
                "updated mode {} of the model is beyond the ROM's {} modes",
                max + 1,
                rom.n_modes
            )));
        }
        let n_track = (max + 3).min(rom.n_modes);
        let c = rom.map.coefficients_unchecked(&rom.map.nominal);
        let centre = rom.eval_lowest(&c.k, &c.m, n_track)?;
        let refs = ref_modes
            .iter()
            .map(|&j| {
                let v = &centre.vectors[j];
                let n = v.iter().map(|a| a * a).sum::<f64>().sqrt();
                v.iter().map(|a| a / n).collect()
            })
            .collect();
        let mass_scale_idx = rom
            .map
            .names
            .iter()
            .position(|n| n == crate::fem::params::names::MASS_SCALE);
        Ok(ModalPredictor {
            rom,
            refs,
            n_track,
            mass_scale_idx,
            nominal_mass_g,
            point_mass_idx: vec![],
            core_thickness: None,
        })
    }

    /// The same predictor whose mass also counts the lumped-mass parameters `idx` (kg);
    /// `nominal_mass_g` must then be the board's mass without them.
    pub fn with_point_masses(mut self, idx: Vec<usize>) -> ModalPredictor {
        self.point_mass_idx = idx;
        self
    }

    /// The same predictor whose mass follows the core thickness: `Some((idx, nominal_m,
    /// core_share))`, the parameter's index, its nominal value and the core's share of
    /// `nominal_mass_g` (`None`: no thickness parameter).
    pub fn with_core_thickness(mut self, thickness: Option<(usize, f64, f64)>) -> Self {
        self.core_thickness = thickness;
        self
    }

    /// Model mass at `values` (the ROM's full parameter vector), g.
    pub fn mass_g(&self, values: &[f64]) -> f64 {
        let mut board = match self.mass_scale_idx {
            Some(i) => self.nominal_mass_g * values[i] / self.rom.map.nominal[i],
            None => self.nominal_mass_g,
        };
        if let Some((i, h0, share)) = self.core_thickness {
            board *= 1.0 - share + share * values[i] / h0;
        }
        board
            + self
                .point_mass_idx
                .iter()
                .map(|&i| 1e3 * values[i])
                .sum::<f64>()
    }

    /// The updated modes at `values`; `None` where the parameters are inadmissible or a
    /// label cannot be tracked.
    pub fn predict(&self, values: &[f64]) -> Option<Prediction> {
        self.assign(values, false).map(|(p, _)| p)
    }

    /// As [`Self::predict`], but a label that cannot be tracked does not void the others:
    /// per label whether it was tracked (a lost label has λ = NaN and its reference vector).
    /// For reporting (posterior-predictive residuals of every paired label), never for the
    /// likelihood.
    pub fn predict_tracked(&self, values: &[f64]) -> Option<(Prediction, Vec<bool>)> {
        self.assign(values, true)
    }

    /// Every tracked mode (not only the updated ones) at `values`, None where the parameters
    /// are inadmissible.
    pub fn tracked_modes(&self, values: &[f64]) -> Option<crate::fem::rom::ReducedModes> {
        self.solve(values, |ck, cm| self.rom.eval_lowest(ck, cm, self.n_track))
    }

    /// `eval` at the affine coefficients of `values`, None where they are inadmissible or it
    /// fails.
    fn solve(
        &self,
        values: &[f64],
        eval: impl FnOnce(&[f64], &[f64]) -> Result<crate::fem::rom::ReducedModes, crate::fem::FemError>,
    ) -> Option<crate::fem::rom::ReducedModes> {
        if !admissible(&self.rom.map, values) {
            return None;
        }
        let (ck, cm) = self.rom.map.coefficient_values(values);
        eval(&ck, &cm).ok()
    }

    /// One subspace of the ROM per updated mode, each spanned by that mode's vectors in
    /// `snaps[m]` (reduced coordinates, e.g. [`Prediction::vectors`] at points of a box) to
    /// within `rel_tol` ([`crate::fem::rom::Rom::subspace`]). None where a mode has no
    /// vector or `snaps` does not hold one list per updated mode.
    pub fn mode_subspaces(
        &self,
        snaps: &[Vec<Vec<f64>>],
        rel_tol: f64,
    ) -> Option<Vec<ModeSubspace>> {
        if snaps.len() != self.refs.len() {
            return None;
        }
        snaps
            .iter()
            .zip(&self.refs)
            .map(|(s, r)| {
                let sub = self.rom.subspace(s, rel_tol)?;
                let target = sub.project(r);
                Some(ModeSubspace { sub, target })
            })
            .collect()
    }

    /// As [`Self::predict`], each updated mode solved in its own subspace
    /// ([`Self::mode_subspaces`]; their error against the ROM is the caller's to verify).
    /// None where the parameters are inadmissible or a mode's nearest Ritz vector overlaps
    /// its reference by less than 1/√2 (the caller then solves in the ROM, whose label
    /// assignment also settles two modes that mix).
    pub fn predict_in_modes(&self, subs: &[ModeSubspace], values: &[f64]) -> Option<Prediction> {
        if subs.len() != self.refs.len() || !admissible(&self.rom.map, values) {
            return None;
        }
        let (ck, cm) = self.rom.map.coefficient_values(values);
        self.solve_in_modes(subs, (&ck, &cm), &[])
    }

    /// [`Self::predict_in_modes`] at several parameter vectors that share most stiffness
    /// coefficients (the particles of one group in step 2: one step-1 draw, each its own
    /// joint stiffness). The terms whose coefficients agree bit for bit at every admissible
    /// vector are summed once per mode subspace, then each vector adds its own: with the
    /// bolted ROM's 47 terms, 46 are shared. The same prediction as one vector at a time up
    /// to the order of the sums (round-off).
    pub fn predict_in_modes_shared(
        &self,
        subs: &[ModeSubspace],
        values: &[&[f64]],
    ) -> Vec<Option<Prediction>> {
        let coefs: Vec<Option<(Vec<f64>, Vec<f64>)>> = values
            .iter()
            .map(|v| {
                (subs.len() == self.refs.len() && admissible(&self.rom.map, v))
                    .then(|| self.rom.map.coefficient_values(v))
            })
            .collect();
        let ok: Vec<&(Vec<f64>, Vec<f64>)> = coefs.iter().flatten().collect();
        let Some(first) = ok.first() else {
            return vec![None; values.len()];
        };
        let (shared, own): (Vec<usize>, Vec<usize>) = (0..first.0.len())
            .partition(|&k| ok.iter().all(|c| c.0[k].to_bits() == first.0[k].to_bits()));
        let parts: Vec<Vec<f64>> = subs
            .iter()
            .map(|s| s.sub.k_part(&first.0, &shared))
            .collect();
        let parts: Vec<(&[f64], &[usize])> = parts
            .iter()
            .map(|p| (p.as_slice(), own.as_slice()))
            .collect();
        coefs
            .iter()
            .map(|c| {
                let (ck, cm) = c.as_ref()?;
                self.solve_in_modes(subs, (ck, cm), &parts)
            })
            .collect()
    }

    /// Each mode in its subspace at coefficients (ck, cm), with the shared parts of
    /// [`Self::predict_in_modes_shared`] (one per subspace) or none.
    fn solve_in_modes(
        &self,
        subs: &[ModeSubspace],
        (ck, cm): (&[f64], &[f64]),
        parts: &[(&[f64], &[usize])],
    ) -> Option<Prediction> {
        let mut lambda = Vec::with_capacity(subs.len());
        let mut vectors = Vec::with_capacity(subs.len());
        for (m, s) in subs.iter().enumerate() {
            let (l, y, o) = self
                .rom
                .eval_nearest_in_parts(&s.sub, ck, cm, &s.target, parts.get(m).copied())
                .ok()?;
            if o < std::f64::consts::FRAC_1_SQRT_2 {
                return None;
            }
            lambda.push(l);
            vectors.push(y);
        }
        Some(Prediction { lambda, vectors })
    }

    fn assign(&self, values: &[f64], allow_lost: bool) -> Option<(Prediction, Vec<bool>)> {
        self.label(self.tracked_modes(values)?, allow_lost)
    }

    /// The updated modes among `modes`, by their overlap with the references.
    fn label(
        &self,
        modes: crate::fem::rom::ReducedModes,
        allow_lost: bool,
    ) -> Option<(Prediction, Vec<bool>)> {
        let nm = self.refs.len();
        let mut out_l = vec![0.0; nm];
        let mut out_v = vec![Vec::new(); nm];
        let assigned = assign_labels(&self.refs, &modes.vectors);
        let mut tracked = vec![false; nm];
        for (m, a) in assigned.iter().enumerate() {
            if let Some(j) = *a {
                tracked[m] = true;
                out_l[m] = modes.eigenvalues[j];
                out_v[m] = modes.vectors[j].clone();
            }
        }
        for m in 0..nm {
            if !tracked[m] {
                if !allow_lost {
                    return None;
                }
                out_l[m] = f64::NAN;
                out_v[m] = self.refs[m].clone();
            }
        }
        Some((
            Prediction {
                lambda: out_l,
                vectors: out_v,
            },
            tracked,
        ))
    }

    /// The likelihood's inputs for `data` from a prediction.
    pub fn terms(&self, pred: &Prediction, data: &UnitData, values: &[f64]) -> Terms {
        self.terms_conditions(std::slice::from_ref(pred), data, values)
    }

    /// The likelihood's inputs for `data` from one prediction per condition
    /// ([`UnitData::conditions`]; one without).
    pub fn terms_conditions(&self, preds: &[Prediction], data: &UnitData, values: &[f64]) -> Terms {
        let r = self.rom.dim();
        // yᵀ G y per (condition, Gram, mode), formed on first use.
        let nm = preds[0].vectors.len();
        let ng = data.grams.len();
        let mut yy = vec![f64::NAN; preds.len() * ng * nm];
        let one_minus_mac = data
            .shapes
            .iter()
            .map(|s| {
                let y = &preds[s.cond].vectors[s.mode];
                let uy: f64 = s.pt_u.iter().zip(y).map(|(a, b)| a * b).sum();
                let slot = &mut yy[(s.cond * ng + s.gram) * nm + s.mode];
                if slot.is_nan() {
                    // G is symmetric: yᵀGy = Σ_i y_i (G_ii y_i + 2 Σ_{j>i} G_ij y_j), half
                    // the multiply-adds of the full form.
                    let g = &data.grams[s.gram];
                    let mut q = 0.0;
                    for i in 0..r {
                        let row = &g[i * r + i + 1..(i + 1) * r];
                        let off: f64 = row.iter().zip(&y[i + 1..]).map(|(a, b)| a * b).sum();
                        q += y[i] * (g[i * r + i] * y[i] + 2.0 * off);
                    }
                    *slot = q;
                }
                (1.0 - uy * uy / *slot).max(0.0)
            })
            .collect();
        Terms {
            lambda: preds
                .iter()
                .flat_map(|p| p.lambda.iter().copied())
                .collect(),
            one_minus_mac,
            mass_g: self.mass_g(values),
            suff: vec![],
        }
    }
}

/// log L of one unit given its terms, the relative eigenvalue errors ε (per mode) and the
/// shape errors δ (per mode; unused when the unit has no shape observations).
pub fn log_lik(data: &UnitData, t: &Terms, eps: &[f64], delta: &[f64]) -> f64 {
    log_lik_with(data, t, eps, delta, &ErrorLogs::new(eps, delta))
}

/// ln ε and 2 ln δ per mode, formed once per global vector and shared by every unit's
/// [`log_lik_with`] (the sampler's hot path), and the variances s² of the model-error term
/// per mode (empty: none).
#[derive(Clone, Debug, Default)]
pub struct ErrorLogs {
    ln_eps: Vec<f64>,
    ln_d2: Vec<f64>,
    model_var: Vec<f64>,
    bias: Vec<f64>,
}

impl ErrorLogs {
    pub fn new(eps: &[f64], delta: &[f64]) -> ErrorLogs {
        ErrorLogs {
            ln_eps: eps.iter().map(|e| e.ln()).collect(),
            ln_d2: delta.iter().map(|d| 2.0 * d.ln()).collect(),
            model_var: vec![],
            bias: vec![],
        }
    }
    /// These logs with a discrepancy d per mode shared by the units
    /// ([`super::discrepancy`]): the model eigenvalue λ (1 + d_m) (empty: none).
    pub fn with_bias(mut self, d: &[f64]) -> ErrorLogs {
        self.bias = d.to_vec();
        self
    }
    /// These logs with the model-error term's prior sd s per mode (empty: none).
    pub fn with_model_error(mut self, sd: &[f64]) -> ErrorLogs {
        self.model_var = sd.iter().map(|s| s * s).collect();
        self
    }
}

/// [`log_lik`] with the logarithms of ε and δ given (`logs` = `ErrorLogs::new(eps, delta)`),
/// and, where `logs` holds a model-error variance s_m², the unit's eigenvalue terms of mode
/// m integrated over a model error b_m ~ N(0, s_m²) common to them (the model eigenvalue
/// λ (1 + b_m)): with q = Σu², a = Σuv, c = Σv² (u = (λ̂ − λ)/λ̂, v = λ/λ̂) and P = 1/s² + c/ε²,
/// ∫ N(b; 0, s²) Π N(λ̂; λ(1 + b), (ε λ̂)²) db = Π (2π)^(-1/2) (ε λ̂)^(-1)
/// · exp(−q/(2ε²) + (a/ε²)²/(2P)) · (1 + s² c/ε²)^(-1/2), exact. The error is common to one
/// unit's measurements and independent between units, which keeps units conditionally
/// independent (the sampler's blocked moves need it).
pub fn log_lik_with(
    data: &UnitData,
    t: &Terms,
    eps: &[f64],
    delta: &[f64],
    logs: &ErrorLogs,
) -> f64 {
    let (ln_eps, ln_d2) = (&logs.ln_eps, &logs.ln_d2);
    let nm = eps.len();
    if t.suff.len() == SUFF_BLOCKS * nm + 1 {
        let s = &t.suff;
        let mut l = -s[SUFF_BLOCKS * nm];
        for m in 0..nm {
            if s[nm + m] > 0.0 {
                let e2 = eps[m] * eps[m];
                // With a discrepancy d the model eigenvalue is λ' = λ (1 + d): the residual
                // u − d v and v' = (1 + d) v, so Σu'² = q − 2da + d²c,
                // Σu'v' = (1 + d)(a − dc), Σv'² = (1 + d)² c.
                let (q, a, c) = {
                    let (q, a, c) = (s[m], s[4 * nm + m], s[5 * nm + m]);
                    match logs.bias.get(m) {
                        Some(&d) if d != 0.0 => (
                            (q - 2.0 * d * a + d * d * c).max(0.0),
                            (1.0 + d) * (a - d * c),
                            (1.0 + d) * (1.0 + d) * c,
                        ),
                        _ => (q, a, c),
                    }
                };
                match logs.model_var.get(m).filter(|v| **v > 0.0) {
                    None => l -= 0.5 * q / e2 + s[nm + m] * ln_eps[m],
                    Some(&v) => {
                        // The closed form rearranged so that nothing cancels: with
                        // W = q c − a² ≥ 0 (Cauchy–Schwarz; the spread of the unit's
                        // measurements about their common offset, clamped against
                        // round-off) and D = ε² + s² c,
                        // −q/(2D) − s² W/(2ε² D) − (n − 1) ln ε − ½ ln D. As written above
                        // (−q/(2ε²) + …), the two large terms cancel as ε → 0 and their
                        // round-off ran the reference's ε to zero on a mode measured once
                        // per unit (W = 0: ε is then free, not rewarded).
                        let w = (q * c - a * a).max(0.0);
                        let dd = e2 + v * c;
                        l -= 0.5 * q / dd
                            + 0.5 * v * w / (e2 * dd)
                            + (s[nm + m] - 1.0) * ln_eps[m]
                            + 0.5 * dd.ln();
                    }
                }
            }
            if s[3 * nm + m] > 0.0 {
                l -= 0.5 * s[3 * nm + m] * ln_d2[m] + s[2 * nm + m] / (2.0 * delta[m] * delta[m]);
            }
        }
        return l;
    }
    if !logs.model_var.is_empty() || !logs.bias.is_empty() {
        // The eigenvalue terms no longer factor by measurement: through the statistics.
        let fast = t.clone().with_sufficient(data, nm);
        return log_lik_with(data, &fast, eps, delta, logs);
    }
    let mut l = 0.0;
    for f in &data.freq {
        let sd = eps[f.mode] * f.lambda_hat;
        let lambda = t.lambda[f.cond * nm + f.mode];
        let z = (f.lambda_hat - lambda) / sd;
        l -= 0.5 * (LN_2PI + z * z) + ln_eps[f.mode] + f.ln_lambda_hat;
    }
    for (s, omm) in data.shapes.iter().zip(&t.one_minus_mac) {
        // The term to the power w (`ShapeObs::weight`): w n in place of n.
        let n = s.weight * s.n_points as f64;
        let d2 = delta[s.mode] * delta[s.mode];
        l -= 0.5 * n * (LN_2PI + ln_d2[s.mode] - s.ln_n) + n * omm / (2.0 * d2);
    }
    if let Some(m) = &data.mass {
        let z = (m.mass_g - t.mass_g) / m.sd_g;
        l -= 0.5 * (LN_2PI + z * z) + m.sd_g.ln();
    }
    l
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::fem::{Board, FeModel, RomOptions, Setup};

    /// A board mode veering with a fixture mode: the two model modes are rotations of the
    /// board shape e₀ and the fixture's e₁ by θ. Through the whole veering (θ from 0 to π/2,
    /// the exact crossing included) the label follows the mode with the larger share of e₁ and
    /// is never lost, and a second label on an untouched mode keeps its mode. A reference
    /// spread evenly over three modes, or held a third by one mode, is lost.
    #[test]
    fn a_label_follows_the_larger_share_through_a_veering_and_is_lost_when_spread() {
        let e = |i: usize| {
            (0..4)
                .map(|k| f64::from(u8::from(k == i)))
                .collect::<Vec<f64>>()
        };
        // The label's reference shape (taken at the ROM's centre) has a part along a third
        // mode e₂ too, as it does away from the centre: at the crossing each veering mode then
        // holds 0.67 of it, below the 1/√2 that identifies a single mode.
        let n0 = 1.0f64.hypot(0.33);
        let refs = vec![vec![1.0 / n0, 0.0, 0.33 / n0, 0.0], e(3)];
        for step in 0..=40 {
            let t = std::f64::consts::FRAC_PI_2 * f64::from(step) / 40.0;
            let (c, s) = (t.cos(), t.sin());
            // Scaled by 3 and -2: the overlap must not depend on a mode's length or sign.
            let y1 = vec![3.0 * c, 3.0 * s, 0.0, 0.0];
            let y2 = vec![2.0 * s, -2.0 * c, 0.0, 0.0];
            let vectors = vec![y1, y2, e(2), e(3)];
            let a = assign_labels(&refs, &vectors);
            let expect = if c > s {
                0
            } else if s > c {
                1
            } else {
                a[0].unwrap_or(9)
            };
            assert!(
                matches!(a[0], Some(j) if j == expect && j < 2),
                "θ = {t}: {a:?}"
            );
            assert_eq!(a[1], Some(3), "θ = {t}");
        }
        let third = 1.0 / 3f64.sqrt();
        let spread = vec![vec![third, third, third, 0.0], vec![0.0, 0.0, 0.0, 1.0]];
        let a = assign_labels(&[e(0)], &spread);
        assert_eq!(a, vec![None], "evenly over three modes");
        let weak = vec![vec![0.55, 0.835, 0.0, 0.0], vec![0.3, 0.0, 0.954, 0.0]];
        let a = assign_labels(&[e(0)], &weak);
        assert_eq!(
            a,
            vec![None],
            "0.55 and 0.3: together less than half of the reference"
        );
    }

    /// The default board free-free, its FE model and a 30-vector ROM (shared with the
    /// target's tests).
    pub(crate) fn free_rom() -> (Board, FeModel, crate::fem::Rom) {
        let board = crate::fem::tests::helpers::thin_board();
        let model = FeModel::build(&board, Setup::Free, &board.mesh).expect("model");
        let rom = crate::fem::Rom::build(
            &model,
            &RomOptions {
                max_basis: 30,
                ..RomOptions::default()
            },
        )
        .expect("rom");
        (board, model, rom)
    }

    /// The shape term's MAC, formed in reduced coordinates from Pᵀu and PᵀP, equals the MAC
    /// of the shapes expanded to the points; the eigenvalue is the ROM's; the modes are
    /// tracked to their labels by overlap even when the labels are given out of order.
    #[test]
    fn reduced_mac_and_tracking_match_the_expanded_rom() {
        let (board, model, rom) = free_rom();
        let pts = board.scan_points_m();
        let op = rom.shape_operator(&model, &pts).expect("operator");
        let mut p = rom.nominal_params();
        p.values[0] *= 1.07; // e_x off-centre, inside the box
        p.values[2] *= 0.93; // g_xy
        let full = rom.eval(&p, &op).expect("eval");
        // Labels out of model order: modes 3, 1, 2 (0-based 2, 0, 1).
        let refs = [2usize, 0, 1];
        let pred = ModalPredictor::new(rom.clone(), &refs, 12.7).expect("predictor");
        let r = rom.dim();
        let n = pts.len();
        let mut gram = vec![0.0; r * r];
        for i in 0..n {
            for a in 0..r {
                for b in 0..r {
                    gram[a * r + b] += op.p[(i, a)] * op.p[(i, b)];
                }
            }
        }
        let mut data = UnitData {
            grams: vec![gram],
            ..UnitData::default()
        };
        // "Measured" shapes: the expanded shape of each label's mode plus a fixed
        // perturbation, unit norm.
        let mut direct = vec![];
        for (m, &j) in refs.iter().enumerate() {
            let w: Vec<f64> = (0..n).map(|i| full.shapes_at_points[(i, j)]).collect();
            let wn = w.iter().map(|v| v * v).sum::<f64>().sqrt();
            let u: Vec<f64> = w
                .iter()
                .enumerate()
                .map(|(i, v)| v / wn + 0.05 * ((i * 7 + m) as f64).sin())
                .collect();
            let un = u.iter().map(|v| v * v).sum::<f64>().sqrt();
            let u: Vec<f64> = u.iter().map(|v| v / un).collect();
            let uw: f64 = u.iter().zip(&w).map(|(a, b)| a * b).sum();
            direct.push(1.0 - uw * uw / (wn * wn));
            let pt_u = (0..r)
                .map(|a| (0..n).map(|i| op.p[(i, a)] * u[i]).sum())
                .collect();
            data.shapes.push(ShapeObs {
                mode: m,
                pt_u,
                gram: 0,
                n_points: n,
                ln_n: (n as f64).ln(),
                cond: 0,
                weight: 1.0,
                points: None,
            });
        }
        let v = p.values.clone();
        let pr = pred.predict(&v).expect("tracked");
        let t = pred.terms(&pr, &data, &v);
        for (m, &j) in refs.iter().enumerate() {
            assert!(
                (pr.lambda[m] / full.eigenvalues[j] - 1.0).abs() < 1e-10,
                "label {m}: λ {} vs ROM mode {j} {}",
                pr.lambda[m],
                full.eigenvalues[j]
            );
            assert!(
                (t.one_minus_mac[m] - direct[m]).abs() < 1e-9,
                "label {m}: 1 − MAC {} vs expanded {}",
                t.one_minus_mac[m],
                direct[m]
            );
            assert!(direct[m] > 1e-4, "the perturbation must matter");
        }
        // Mass follows mass_scale linearly.
        let i = pred.mass_scale_idx.expect("mass_scale is a parameter");
        let mut v2 = v.clone();
        v2[i] *= 1.1;
        assert!((pred.mass_g(&v2) / pred.mass_g(&v) - 1.1).abs() < 1e-12);
    }

    /// A label whose reference no model mode resembles voids the likelihood's prediction,
    /// while the reporting prediction keeps every other label, with the same eigenvalues.
    /// The sufficient-statistics path of `log_lik_with` (O(modes)) equals the term-by-term
    /// sum over every observation, with two conditions, shapes, a mode with no data and the
    /// mass term.
    #[test]
    fn sufficient_statistics_give_the_term_by_term_log_likelihood() {
        let nm = 3;
        let mut data = UnitData::default();
        for (k, (mode, lh)) in [(0, 1.0e7), (0, 1.02e7), (2, 4.1e7), (2, 3.9e7), (0, 0.98e7)]
            .into_iter()
            .enumerate()
        {
            let mut f = FreqObs::new(mode, lh);
            f.cond = k % 2;
            data.freq.push(f);
        }
        // One shape term down-weighted (a power likelihood): the sums must carry it as the
        // direct form does.
        for (mode, n, weight) in [(0, 40usize, 1.0), (2, 35, 0.3), (2, 40, 1.0)] {
            data.shapes.push(ShapeObs {
                mode,
                pt_u: vec![],
                gram: 0,
                n_points: n,
                ln_n: (n as f64).ln(),
                cond: 0,
                weight,
                points: None,
            });
        }
        data.mass = Some(MassObs {
            mass_g: 13.1,
            sd_g: 0.02,
        });
        let t = Terms {
            lambda: vec![1.01e7, 2.0e7, 4.05e7, 0.99e7, 2.1e7, 3.95e7],
            one_minus_mac: vec![0.01, 0.002, 0.03],
            mass_g: 13.12,
            suff: vec![],
        };
        let (eps, delta) = ([0.011, 0.02, 0.007], [0.05, 0.1, 0.08]);
        let direct = log_lik(&data, &t, &eps, &delta);
        let fast = t.clone().with_sufficient(&data, nm);
        assert_eq!(fast.suff.len(), SUFF_BLOCKS * nm + 1);
        let got = log_lik(&data, &fast, &eps, &delta);
        assert!(
            (got - direct).abs() <= 1e-12 * direct.abs(),
            "{got} vs {direct}"
        );
        // The down-weighted term is 0.3 of its Gaussian log density over its 35 points (each
        // point's variance δ²/n, the residual's squared norm 1 − MAC).
        let mut full = data.clone();
        full.shapes[1].weight = 1.0;
        let (n, d2) = (35.0f64, delta[2] * delta[2]);
        let term = -0.5 * n * (LN_2PI + (d2 / n).ln()) - t.one_minus_mac[1] / (2.0 * d2 / n);
        let lost = log_lik(&full, &t, &eps, &delta) - direct;
        assert!(
            (lost - 0.7 * term).abs() <= 1e-9 * term.abs(),
            "{lost} vs 0.7 × {term}"
        );
        // With a model-error term: the closed form equals the likelihood integrated over b
        // numerically (λ (1 + b), b ~ N(0, s²); trapezoid over ±10 s), mode by mode.
        let sd = [0.004, 0.01, 0.003];
        let logs = ErrorLogs::new(&eps, &delta).with_model_error(&sd);
        let closed = log_lik_with(&data, &t, &eps, &delta, &logs);
        let at = |b: &[f64]| {
            let mut shifted = t.clone();
            for (k, l) in shifted.lambda.iter_mut().enumerate() {
                *l *= 1.0 + b[k % nm];
            }
            log_lik(&data, &shifted, &eps, &delta)
        };
        // Modes 0 and 2 have data (mode 1 none: its b integrates to 1); the integrand
        // factors by mode, so integrate each mode with the other's b at 0 and add the
        // logs, minus the b = 0 likelihood counted twice.
        let l0 = at(&[0.0; 3]);
        let mut integrated = l0;
        for m in [0, 2] {
            let n = 4000;
            let h = 20.0 * sd[m] / n as f64;
            let mut acc = 0.0;
            for i in 0..=n {
                let b = -10.0 * sd[m] + i as f64 * h;
                let mut bv = [0.0; 3];
                bv[m] = b;
                let w = if i == 0 || i == n { 0.5 } else { 1.0 };
                let prior = (-0.5 * (b / sd[m]).powi(2)).exp()
                    / (sd[m] * (2.0 * std::f64::consts::PI).sqrt());
                acc += w * h * prior * (at(&bv) - l0).exp();
            }
            integrated += acc.ln();
        }
        assert!(
            (closed - integrated).abs() < 1e-6,
            "closed form {closed} vs quadrature {integrated}"
        );
        assert!((closed - direct).abs() > 0.1);

        // A discrepancy d shared by the units: the statistics' shift equals the direct
        // likelihood at λ (1 + d); with the model-error term too, the closed form at the
        // shifted eigenvalues.
        let d = [0.003, -0.02, 0.011];
        let shifted = {
            let mut s = t.clone();
            for (k, l) in s.lambda.iter_mut().enumerate() {
                *l *= 1.0 + d[k % nm];
            }
            s
        };
        let want = log_lik(&data, &shifted, &eps, &delta);
        let logs = ErrorLogs::new(&eps, &delta).with_bias(&d);
        for terms in [&t, &fast] {
            let got = log_lik_with(&data, terms, &eps, &delta, &logs);
            assert!((got - want).abs() <= 1e-9 * want.abs(), "{got} vs {want}");
        }
        let logs = ErrorLogs::new(&eps, &delta)
            .with_model_error(&sd)
            .with_bias(&d);
        let want = log_lik_with(
            &data,
            &shifted,
            &eps,
            &delta,
            &ErrorLogs::new(&eps, &delta).with_model_error(&sd),
        );
        let got = log_lik_with(&data, &t, &eps, &delta, &logs);
        assert!((got - want).abs() <= 1e-9 * want.abs(), "{got} vs {want}");
    }

    #[test]
    fn a_lost_label_voids_predict_but_not_the_other_labels_of_predict_tracked() {
        let (_, _, rom) = free_rom();
        let good = ModalPredictor::new(rom.clone(), &[0, 1, 2], 12.7).expect("predictor");
        let mut lost = good.clone();
        // A reference orthogonal to every tracked mode at the centre (Gram–Schmidt of a
        // fixed vector against their reduced vectors, orthonormal since M_r = I there).
        let c = rom.map.coefficients_unchecked(&rom.map.nominal);
        let centre = rom.eval_lowest(&c.k, &c.m, good.n_track).expect("centre");
        let r = rom.dim();
        let mut x: Vec<f64> = (0..r).map(|i| ((3 * i + 1) as f64).sin()).collect();
        for _ in 0..2 {
            for y in &centre.vectors {
                let yy: f64 = y.iter().map(|a| a * a).sum();
                let xy: f64 = x.iter().zip(y).map(|(a, b)| a * b).sum();
                x.iter_mut().zip(y).for_each(|(a, b)| *a -= xy / yy * b);
            }
        }
        let xn = x.iter().map(|a| a * a).sum::<f64>().sqrt();
        lost.refs[1] = x.iter().map(|a| a / xn).collect();
        let v = rom.map.nominal.clone();
        assert!(lost.predict(&v).is_none());
        let (p, tracked) = lost.predict_tracked(&v).expect("admissible parameters");
        assert_eq!(tracked, vec![true, false, true]);
        assert!(p.lambda[1].is_nan());
        let q = good.predict(&v).expect("tracked");
        assert_eq!(p.lambda[0], q.lambda[0]);
        assert_eq!(p.lambda[2], q.lambda[2]);
        assert_eq!(good.predict_tracked(&v).expect("all").1, vec![true; 3]);
    }
}

//! From paired data to the likelihood: the updated labels, each unit's frequency, shape, mass
//! and thickness observations, the shape-term weights, the model-error prior and the
//! model-form discrepancy of a step.

use crate::bayes::modal::{FreqObs, MassObs, ModalPredictor, ShapeObs, UnitData};
use crate::bayes::shape_weight::{point_key, PointShape, ShapeWeight};
use crate::bayes::smc::{self};
use crate::bayes::target::{ErrorPrior, ModalTarget};
use crate::fem::params::names;
use crate::fem::{Board, FeModel, Rom};
use crate::findings::{Finding, Findings, Severity};
use crate::modal::rows::{ModeRow, PairRow};
use crate::update::enrichment::Mechanism;
use anyhow::{anyhow, bail};
use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

/// What a step updates and with which model: the modes and parameters, the priors, the error
/// model and discrepancy, the ROM box, the enrichment of a diagnosis's refit, the held-out
/// boards. Step 2's preparation depends on this (and the data) alone.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct ModelSpec {
    /// Mode labels to update; empty = those `pair` marks `used_for_updating`.
    pub modes: Vec<String>,
    /// Step 1: the updated board parameters (ROM parameter names).
    pub params: Vec<String>,
    /// Prior sd of the population means, relative to nominal (step 1) or in ln K (step 2).
    pub prior_width: f64,
    /// Scale of the population sds' prior (relative, or in ln K): the half-normal's scale;
    /// the log-normal's median is 0.6745 × it.
    pub sigma_scale: f64,
    /// Step 1: the prior family of the board parameters' population sds (step 2: always
    /// half-normal).
    #[serde(default)]
    pub sigma_prior: crate::bayes::population::SigmaPrior,
    pub lkj_eta: f64,
    pub eps: ErrorPrior,
    /// `None`: shape terms off.
    pub delta: Option<ErrorPrior>,
    /// ROM half-width (relative) and the largest posterior mass allowed outside it.
    pub rom_box: f64,
    pub box_tolerance: f64,
    /// Cap on the ROM's basis (None: the physics core's default). A smaller basis is faster
    /// and less accurate; the ROM accuracy test states the error of the default.
    pub rom_max_basis: Option<usize>,
    /// Half-width (ln) of the ROM's transverse-shear-modulus axis where step 1 widened it
    /// (`None`: [`crate::fem::rom::G_Z_LOG_BOX`]; at most [`crate::update::rom_box::MAX_G_Z_LOG_BOX`]).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub g_z_log_box: Option<f64>,
    /// Step 2: refit with a joint enrichment of the diagnosis's library (`None`: the baseline).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub enrich: Option<Mechanism>,
    /// Step 2 with `joint_stiffness_per_joint`: the joint (1-based; `None`: every joint).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub enrich_joint: Option<usize>,
    /// Step 2 with an enrichment: the bolted measurements that get its own coordinates (the
    /// diagnosis's outlier assemblies for a per-assembly mechanism); the others keep the
    /// baseline's joint. Empty: every measurement.
    #[serde(skip_serializing_if = "Vec::is_empty", default)]
    pub enrich_units: Vec<String>,
    /// Step 1 with `temperature_stiffness`: the numeric sheet column the FR-4 moduli follow.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub enrich_covariate: Option<String>,
    /// Step 1 with `added_mass`: the point (x_m, y_m) of the lumped mass.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub enrich_location: Option<[f64; 2]>,
    /// Step 2 with an enrichment: the enriched model's modes that no baseline label
    /// carries (a fixture's own mode) are paired with the identified modes pair left
    /// unpaired, and join the updating as labels of their own ([`pair_new_modes`]).
    #[serde(skip_serializing_if = "std::ops::Not::not", default)]
    pub enrich_new_modes: bool,
    /// Step 1: a relative model-form error per updated mode, common to a board's
    /// measurements and independent between boards, integrated out; its prior sd from the
    /// model's discretization spread (`fem::convergence::mesh_spread`).
    #[serde(default)]
    pub model_error: bool,
    /// The model's stated fidelity: the prior median of the model-form discrepancy's scale,
    /// a relative frequency ([`crate::bayes::discrepancy`]); `None`: the setup's default
    /// (free-free [`crate::bayes::discrepancy::FREE_FIDELITY_FREQ`]; bolted none, see
    /// `run_joints`, [`crate::bayes::discrepancy::BOLTED_FIDELITY_FREQ`] being the bolted
    /// model's stated fidelity to give it); 0: no discrepancy term.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub discrepancy_freq: Option<f64>,
    /// Step 1: boards whose measurements and masses are left out of the updating, so that
    /// the new-board prediction can be validated on them (the report compares them with it).
    #[serde(skip_serializing_if = "Vec::is_empty", default)]
    pub hold_out_boards: Vec<String>,
    /// Step 1: free-free measurements left out of the updating while their boards are
    /// updated from the others, so that the own-board prediction can be validated on them.
    #[serde(skip_serializing_if = "Vec::is_empty", default)]
    pub hold_out_measurements: Vec<String>,
    /// Step 1: the coordinates the board population is formed in.
    #[serde(default)]
    pub board_coordinates: BoardCoordinates,
    /// Step 1: the sd of the balance's error common to every board, relative to the weighed
    /// mass ([`ModelSpec::DEFAULT_BALANCE_BIAS_REL`]; [`balance_bias_draw`] says why).
    #[serde(default = "default_balance_bias_rel")]
    pub balance_bias_rel: f64,
    /// The power of each mode's shape term ([`crate::bayes::shape_weight`]).
    #[serde(default)]
    pub shape_weights: ShapeWeighting,
}

fn default_balance_bias_rel() -> f64 {
    ModelSpec::DEFAULT_BALANCE_BIAS_REL
}

#[cfg(test)]
impl ModelSpec {
    /// A spec for tests: no modes, parameters or enrichment chosen, a fixed ε, no shape
    /// terms, the default ROM box; tests set what they exercise.
    pub(crate) fn for_tests() -> ModelSpec {
        ModelSpec {
            modes: vec![],
            params: vec![],
            prior_width: 1.0,
            sigma_scale: 0.5,
            sigma_prior: Default::default(),
            lkj_eta: 2.0,
            eps: ErrorPrior::Fixed { value: 1e-3 },
            delta: None,
            rom_box: ModelSpec::DEFAULT_ROM_BOX,
            box_tolerance: 0.01,
            rom_max_basis: None,
            g_z_log_box: None,
            enrich: None,
            enrich_joint: None,
            enrich_units: vec![],
            enrich_covariate: None,
            enrich_location: None,
            enrich_new_modes: false,
            model_error: false,
            discrepancy_freq: None,
            hold_out_boards: vec![],
            hold_out_measurements: vec![],
            board_coordinates: Default::default(),
            balance_bias_rel: ModelSpec::DEFAULT_BALANCE_BIAS_REL,
            shape_weights: Default::default(),
        }
    }
}

impl ModelSpec {
    /// Default sd of the balance's common error, relative ([`balance_bias_draw`]). A lab
    /// either corrects for buoyancy (β ≈ 0: a calibrated balance with class-E2 weights errs
    /// by ~3e-6 at 10 g) or does not (β ≈ −ρ_air/ρ (1 − ρ/ρ_ref) = −4.8e-4 for FR-4 against
    /// steel), and the campaign does not say which: a zero-mean normal holding both within
    /// its 90 % interval has sd 4.8e-4 / 1.645 ≈ 3e-4.
    pub const DEFAULT_BALANCE_BIAS_REL: f64 = 3e-4;
    /// The ROM box the tests verify the ROM over (relative half-width); step 1 widens it
    /// when the posterior presses against it ([`crate::update::rom_box::MAX_ROM_BOX`]).
    pub const DEFAULT_ROM_BOX: f64 = 0.2;
}

/// How each mode's shape term is weighted against its measurements' shared error
/// (`--shape-weights`).
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ShapeWeighting {
    /// 1 / design effect of the residuals at the Laplace reference's centre
    /// ([`crate::bayes::shape_weight`]).
    #[default]
    Auto,
    /// Every shape term at full weight: the measurements' shape errors independent.
    Off,
    /// Given per mode label (a diagnosis's refit takes its baseline's, so that their
    /// evidences are of the same likelihood); a label not given: 1.
    Given(BTreeMap<String, f64>),
}

/// The coordinates of step 1's board population (`bayes::target::PerMass` says why).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BoardCoordinates {
    /// With the mass scale updated, every modulus (a parameter in Pa) per unit mass scale:
    /// the population's coordinate `<modulus>_per_mass_scale_pa` is modulus / mass_scale.
    #[default]
    PerMass,
    /// Every parameter as it is.
    Natural,
}

/// Identified modes with their shapes: (measurement, mode) → its row of modes.parquet.
pub type ShapeMap<'a> = BTreeMap<(String, i32), &'a ModeRow>;

/// The rows of the `wanted` (measurement, mode) keys among the rows of modes.parquet.
pub fn shape_map<'a>(rows: &'a [ModeRow], wanted: &BTreeSet<(String, i32)>) -> ShapeMap<'a> {
    rows.iter()
        .map(|r| ((r.measurement_id.clone(), r.mode), r))
        .filter(|(key, _)| wanted.contains(key))
        .collect()
}

#[derive(Debug, Clone)]
pub struct MassRow {
    pub mass_g: f64,
    pub n_stable: i32,
    pub std_g: f64,
    pub resolution_g: f64,
    pub inconsistent: bool,
    /// Days with a stable reading, their means' sum of squares (g²) and Σ (day's share of
    /// the readings)² (`formats::balance_log::BoardMass`).
    pub n_days: i32,
    pub day_means_ss_g2: f64,
    pub day_share_sq_sum: f64,
}

/// Where `model` has the core thickness as a parameter: its index, nominal value (m) and the
/// core's share of the board's nominal mass (the part that follows the thickness).
pub fn core_thickness_mass(model: &FeModel) -> anyhow::Result<Option<(usize, f64, f64)>> {
    let p = model.nominal_params();
    let Ok(i) = p.position(names::CORE_THICKNESS) else {
        return Ok(None);
    };
    let h0 = p.values[i];
    let mut twice = p.clone();
    twice.values[i] = 2.0 * h0;
    let (m0, m2) = (model.total_mass_kg(&p)?, model.total_mass_kg(&twice)?);
    Ok(Some((i, h0, (m2 - m0) / m0)))
}

/// The predictors of a step: over the updated labels' model modes and over all labels'
/// (the residuals and the intervals), each at the nominal mass `nominal_mass_g`, with the
/// point-mass coordinates `point_masses` and `model`'s core thickness
/// ([`core_thickness_mass`]).
pub fn predictors(
    (model, rom): (&FeModel, &Rom),
    [updated, all]: [&Labels; 2],
    nominal_mass_g: f64,
    point_masses: &[usize],
) -> anyhow::Result<(ModalPredictor, ModalPredictor)> {
    let thickness = core_thickness_mass(model)?;
    let make = |modes: &[usize]| -> anyhow::Result<ModalPredictor> {
        Ok(ModalPredictor::new(rom.clone(), modes, nominal_mass_g)?
            .with_point_masses(point_masses.to_vec())
            .with_core_thickness(thickness))
    };
    Ok((make(&updated.model_mode)?, make(&all.model_mode)?))
}

/// A step's target and what its residuals need: the predictor over every label (not only
/// the updated ones), each unit's data over every label with its observations' metadata, and
/// the units' names.
pub struct StepTarget {
    pub target: ModalTarget,
    pub all_pred: ModalPredictor,
    pub units_all: Vec<(UnitData, Vec<ObsMeta>)>,
    pub unit_names: Vec<String>,
}

/// Standard deviation of a board's measured core thickness, m: 5 µm, 0.3 % of a 1.5 mm
/// core. A micrometer's own error is ±2 µm (ISO 3611's maximum permissible error below
/// 25 mm); a laminate's thickness varies over the board by more than that, and the sheet
/// gives one number for the whole board. Free-free frequencies fix E h² (D ∝ E h³, mass ∝ h),
/// so this is what keeps a modulus's interval honest: ±0.6 % in E for ±0.3 % in h.
pub const THICKNESS_SD_M: f64 = 5e-6;

/// Per unit (board), its measured core thickness as an observation of its thickness
/// coordinate (k, relative value, relative sd; the coordinate is h / h₀ − 1). A board the
/// sheet gives no thickness for, or one outside the ROM's box (not verified there), has none,
/// each said in a warning: the population informs it, as it does an unweighed board's mass.
pub fn thickness_obs(
    param_names: &[String],
    h0_m: f64,
    unit_names: &[String],
    thickness_m: &BTreeMap<String, f64>,
    rom_box: f64,
    findings: &mut Findings,
) -> Vec<Vec<(usize, f64, f64)>> {
    let Some(k) = param_names.iter().position(|p| p == names::CORE_THICKNESS) else {
        return vec![];
    };
    let mut listed = vec![];
    let out = unit_names
        .iter()
        .map(|b| match thickness_m.get(b) {
            None => {
                findings.push(Finding::new(
                    Severity::Warning,
                    "update.thickness_unknown",
                    format!("board {b}: the sheet gives no thickness_mm while other boards have one; its core thickness is informed by the population and its frequencies only"),
                ));
                vec![]
            }
            Some(&h) if (h / h0_m - 1.0).abs() > rom_box => {
                findings.push(Finding::new(
                    Severity::Warning,
                    "update.thickness_outside_box",
                    format!("board {b}: its core thickness {:.3} mm (thickness_mm less the board file's copper) is {:+.1} % off the board file's {:.3} mm, outside the ROM's ±{:.0} % box (expected a laminate within its tolerance, thickness_mm the overall thickness over the copper: check the sheet, or the board file's core.thickness_m); not used", 1e3 * h, 100.0 * (h / h0_m - 1.0), 1e3 * h0_m, 100.0 * rom_box),
                ));
                vec![]
            }
            Some(&h) => {
                listed.push(format!("{b} {:.3}", 1e3 * h));
                vec![(k, h / h0_m - 1.0, THICKNESS_SD_M / h0_m)]
            }
        })
        .collect();
    findings.push(Finding::new(
        Severity::Info,
        "update.specimen_thickness",
        format!(
            "core thickness per board from the sheet (thickness_mm, the overall thickness, less the board file's copper layers), mm (board file: {:.3}), each a measurement of the board's core_thickness_m with sd {:.3} mm: {}",
            1e3 * h0_m,
            1e3 * THICKNESS_SD_M,
            listed.join(", ")
        ),
    ));
    out
}

/// The updated labels and, per label, the model mode (0-based) it pairs with at the centre.
pub struct Labels {
    pub labels: Vec<String>,
    pub model_mode: Vec<usize>,
}

pub fn select_labels(
    pairs: &[PairRow],
    setup: &str,
    requested: &[String],
    presence: &[String],
    findings: &mut Findings,
) -> anyhow::Result<Labels> {
    let chosen: Vec<String> = if requested.is_empty() {
        presence.to_vec()
    } else {
        requested.to_vec()
    };
    if chosen.is_empty() {
        bail!(
            "no {setup} mode is marked for updating (presence.parquet) and none was requested with --modes: nothing to update"
        );
    }
    let mut labels = vec![];
    let mut model_mode = vec![];
    for l in chosen {
        let mut counts: BTreeMap<i32, usize> = BTreeMap::new();
        for p in pairs.iter().filter(|p| p.setup == setup && p.label == l) {
            *counts.entry(p.model_mode).or_default() += 1;
        }
        match counts.iter().max_by_key(|(_, n)| **n) {
            Some((mm, _)) if *mm >= 1 => {
                labels.push(l);
                model_mode.push((*mm - 1) as usize);
            }
            _ => findings.push(Finding::new(
                Severity::Warning,
                "update.label_unpaired",
                format!("mode {l:?} has no accepted {setup} pair; left out of the updating"),
            )),
        }
    }
    if labels.is_empty() {
        bail!("none of the {setup} modes to update has an accepted pair in pairs.parquet");
    }
    Ok(Labels { labels, model_mode })
}

/// The scan points of an identified mode's shape where the shape is finite and the model can
/// be evaluated, and the shape's values there.
pub fn usable_points(model: &FeModel, row: &ModeRow) -> (Vec<[f64; 2]>, Vec<f64>) {
    let mut pts = vec![];
    let mut u = vec![];
    for ((v, x), y) in row.shape.iter().zip(&row.x_m).zip(&row.y_m) {
        if v.is_finite() && model.shape_operator(&[[*x, *y]]).is_ok() {
            pts.push([*x, *y]);
            u.push(*v);
        }
    }
    (pts, u)
}

/// A shape observation of one identified mode at its valid scan points, or `None` (with a
/// finding) when fewer than 3 points remain.
pub fn shape_obs(
    model: &FeModel,
    rom: &Rom,
    mode: usize,
    shape: &ModeRow,
    measurement_id: &str,
    grams: &mut Vec<Vec<f64>>,
    findings: &mut Findings,
) -> anyhow::Result<Option<ShapeObs>> {
    let (pts, u) = usable_points(model, shape);
    let nrm = u.iter().map(|v| v * v).sum::<f64>().sqrt();
    if pts.len() < 3 || nrm == 0.0 {
        findings.push(
            Finding::new(
                Severity::Warning,
                "update.shape_points",
                format!(
                    "only {} usable scan points for a mode shape (expected at least 3); its shape term is left out",
                    pts.len()
                ),
            )
            .measurement(measurement_id.to_string()),
        );
        return Ok(None);
    }
    let op = rom.shape_operator(model, &pts)?;
    let r = rom.dim();
    let n = pts.len();
    let points = PointShape {
        mode,
        keys: pts.iter().map(|q| point_key(q[0], q[1])).collect(),
        u: u.iter().map(|v| v / nrm).collect(),
        p: (0..n)
            .flat_map(|i| (0..r).map(move |a| (i, a)))
            .map(|(i, a)| op.p[(i, a)])
            .collect(),
    };
    let mut pt_u = vec![0.0; r];
    let mut gram = vec![0.0; r * r];
    for (i, ui) in u.iter().enumerate() {
        for a in 0..r {
            let pa = op.p[(i, a)];
            pt_u[a] += pa * ui / nrm;
            for b in 0..r {
                gram[a * r + b] += pa * op.p[(i, b)];
            }
        }
    }
    let gram = match grams.iter().position(|g| *g == gram) {
        Some(i) => i,
        None => {
            grams.push(gram);
            grams.len() - 1
        }
    };
    Ok(Some(ShapeObs {
        mode,
        pt_u,
        gram,
        n_points: n,
        ln_n: (n as f64).ln(),
        cond: 0,
        weight: 1.0,
        points: Some(Arc::new(points)),
    }))
}

/// Set the power of every shape term of `target` as `how` says, and return each mode's
/// weight with what it came from (empty without shape terms). `Auto` locates the units with
/// the Laplace reference at full weight (from `start`, with the mean auxiliary values),
/// takes each shape's residual against the model there, and weighs each mode by
/// [`crate::bayes::shape_weight::design_weights`].
pub fn weigh_shapes(
    target: &mut ModalTarget,
    how: &ShapeWeighting,
    (aux_mean, start): (&[f64], Option<&[f64]>),
    labels: &[String],
    seed: u64,
    what: &str,
) -> anyhow::Result<Vec<ShapeWeight>> {
    use crate::bayes::shape_weight::{design_weights, residual, ModeResidual};
    use rayon::prelude::*;
    if target.units.iter().all(|u| u.shapes.is_empty()) {
        return Ok(vec![]);
    }
    let count = |m: usize| -> usize {
        target
            .units
            .iter()
            .flat_map(|u| &u.shapes)
            .filter(|o| o.mode == m)
            .count()
    };
    let given = |w: &dyn Fn(&str) -> f64| -> Vec<ShapeWeight> {
        labels
            .iter()
            .enumerate()
            .map(|(m, l)| ShapeWeight {
                label: l.clone(),
                n_observations: count(m),
                n_pairs: 0,
                correlation: None,
                design_effect: 1.0 / w(l),
                weight: w(l),
            })
            .collect()
    };
    let weights = match how {
        ShapeWeighting::Off => given(&|_| 1.0),
        ShapeWeighting::Given(map) => given(&|l| map.get(l).copied().unwrap_or(1.0)),
        ShapeWeighting::Auto => {
            // The weights need the units' locations only, which settle in the first rounds
            // (the later ones move the scales: ln σ_u, the discrepancy's weights). Measured on
            // the realistic null campaign: the same weights to 1e-3 after 3 rounds as after
            // the 7 a settled reference took, 9 s sooner.
            let ropts = crate::bayes::reference::ReferenceOptions {
                start: start.map(<[f64]>::to_vec),
                rounds: 3,
                ..Default::default()
            };
            let (q, _) =
                crate::bayes::reference::laplace_reference(&*target, aux_mean, &ropts, seed)
                    .map_err(|e| {
                        anyhow!("{what}: locating the units to weigh the shape terms: {e}")
                    })?;
            let t = &*target;
            let res: Vec<ModeResidual> = (0..t.units.len())
                .into_par_iter()
                .flat_map_iter(|b| {
                    let pred = t
                        .predictor
                        .predict(&t.values(aux_mean, b, &q.units[b].mean));
                    t.units[b]
                        .shapes
                        .iter()
                        .filter_map(|o| {
                            let (pred, ps) = (pred.as_ref()?, o.points.as_ref()?);
                            Some(ModeResidual {
                                mode: o.mode,
                                keys: ps.keys.clone(),
                                r: residual(ps, &pred.vectors[o.mode], &t.predictor.refs[o.mode])?,
                            })
                        })
                        .collect::<Vec<_>>()
                })
                .collect();
            design_weights(&res, labels)
        }
    };
    for u in &mut target.units {
        for o in &mut u.shapes {
            o.weight = weights[o.mode].weight;
        }
    }
    Ok(weights)
}

/// The shape terms' weights in the log (verbose) and, where a mode's measurements share
/// most of their shape error, a finding: its shapes then count as few measurements.
pub fn report_shape_weights(w: &[ShapeWeight], what: &str, verbose: bool, findings: &mut Findings) {
    if verbose && !w.is_empty() {
        let s: Vec<String> = w
            .iter()
            .map(|w| {
                format!(
                    "{} {:.3} (ρ {:.3}, J {})",
                    w.label,
                    w.weight,
                    w.correlation.unwrap_or(f64::NAN),
                    w.n_observations
                )
            })
            .collect();
        eprintln!("{what}: shape-term weights {}", s.join(", "));
    }
    let low: Vec<String> = w
        .iter()
        .filter(|w| w.weight < 0.5)
        .map(|w| {
            format!(
                "{} (ρ = {:.2} over {} measurements: worth {:.1})",
                w.label,
                w.correlation.unwrap_or(f64::NAN),
                w.n_observations,
                w.n_observations as f64 * w.weight
            )
        })
        .collect();
    if !low.is_empty() {
        findings.push(Finding::new(
            Severity::Info,
            "update.shape_weights",
            format!("{what}: the shape residuals of {} agree between measurements (an error they share: extraction or model), so their shape terms count as fewer independent measurements (evidence.json shape_weights)", low.join(", ")),
        ));
    }
}

/// Where a frequency observation came from, and the index of its shape observation.
#[derive(Clone, Debug)]
pub struct ObsMeta {
    pub measurement_id: String,
    pub board_id: String,
    pub label: usize,
    pub freq_hz: f64,
    pub shape: Option<usize>,
}

/// The data of one group of measurements (a board's free-free measurements, or one bolted
/// measurement) for the given labels.
pub fn unit_data(
    rows: &[&PairRow],
    labels: &[String],
    shapes: Option<(&FeModel, &Rom, &ShapeMap<'_>)>,
    findings: &mut Findings,
) -> anyhow::Result<(UnitData, Vec<ObsMeta>)> {
    let mut d = UnitData::default();
    let mut meta = vec![];
    for p in rows {
        let Some(m) = labels.iter().position(|l| *l == p.label) else {
            continue;
        };
        let w = 2.0 * std::f64::consts::PI * p.freq_hz;
        d.freq.push(FreqObs::new(m, w * w));
        meta.push(ObsMeta {
            measurement_id: p.measurement_id.clone(),
            board_id: p.board_id.clone(),
            label: m,
            freq_hz: p.freq_hz,
            shape: None,
        });
        if let Some((model, rom, map)) = shapes {
            match map.get(&(p.measurement_id.clone(), p.mode)) {
                Some(s) => {
                    if let Some(o) = shape_obs(model, rom, m, s, &p.measurement_id, &mut d.grams, findings)? {
                        meta.last_mut().expect("pushed above").shape = Some(d.shapes.len());
                        d.shapes.push(o);
                    }
                }
                None => findings.push(
                    Finding::new(
                        Severity::Warning,
                        "update.shape_missing",
                        format!("identified mode {} has no shape in modes.parquet; its shape term is left out", p.mode),
                    )
                    .measurement(p.measurement_id.clone()),
                ),
            }
        }
    }
    Ok((d, meta))
}

/// A board's balance observation: the mean of its stable readings, with the sd of that mean.
/// It is the larger of two:
/// - the readings' own: their spread over √n and the rounding error no number of readings
///   averages out ([`systematic_rounding_var`]; one reading has no spread of its own, so
///   it is taken as one readability step, the order of an analytical balance's
///   repeatability; readings ingest flagged as inconsistent keep their full spread);
/// - what the balance may err from one placement of a board to the next (eccentric load,
///   drift between sessions, handling): the campaign's own measure of it, `placement`
///   ([`placement_scatter`]), times the board's share of its days, with the rounding's
///   systematic part, where boards were weighed again on other days; else the OIML
///   allowance ([`MPE_READABILITY_STEPS`]).
///
/// The error every board shares is not in it (buoyancy, calibration:
/// [`balance_bias_draw`]): it moves every board's mass together, and the contrasts between
/// boards are known to this precision.
pub fn mass_obs(
    m: &MassRow,
    board_id: &str,
    placement: Option<PlacementScatter>,
    findings: &mut Findings,
) -> Option<MassObs> {
    if m.n_stable < 1 || !m.mass_g.is_finite() {
        return None;
    }
    // One reading has no spread of its own: none for the rounding, one step for its noise.
    let (spread, one) = if m.n_stable >= 2 {
        (m.std_g, m.std_g)
    } else {
        (0.0, m.resolution_g)
    };
    let rounding2 = systematic_rounding_var(m.resolution_g, spread);
    let sd2 = if m.inconsistent {
        findings.push(Finding::new(
            Severity::Warning,
            "update.mass_inconsistent",
            format!("board {board_id}: the balance readings disagree (ingest flagged them); the mass term uses their full spread, not the spread of the mean"),
        ));
        m.std_g * m.std_g + rounding2
    } else {
        one * one / f64::from(m.n_stable) + rounding2
    };
    let between_sd2 = match placement {
        // The day means' scatter holds the rounding's random part, not its systematic one.
        Some(p) => p.var_g2 * m.day_share_sq_sum.clamp(0.0, 1.0) + rounding2,
        None => (MPE_READABILITY_STEPS * m.resolution_g).powi(2) / 3.0,
    };
    // A microgram per gram: no balance a board fits on reads finer, and a log without a
    // readability and a single reading would otherwise pin the mass exactly.
    let sd = sd2
        .max(between_sd2)
        .sqrt()
        .max(MIN_MASS_SD_REL * m.mass_g.abs())
        .max(1e-9);
    Some(MassObs {
        mass_g: m.mass_g,
        sd_g: sd,
    })
}

/// The variance of the rounding error that the mean of readings rounded to `d` keeps
/// however many there are, given the readings' sample sd `s_obs` (g).
/// - Readings that never vary (s_obs = 0, or a single reading) may all carry one rounding
///   error: uniform within ±d/2 over the unknown true value, d²/12.
/// - Noise dithers the rounding: for a Gaussian input of sd σ, the mean of the rounded
///   readings is biased by a periodic function of the true value, the rounding error's
///   sawtooth series averaged over the noise, whose k-th harmonic has amplitude
///   (d/πk) e^(−2π²k²σ²/d²) (Widrow & Kollár 2008, *Quantization Noise*, Cambridge UP);
///   the rest of the rounding error is noise the readings' spread already shows. The
///   systematic variance left, over an unknown true value, is Σ_k (d²/2π²k²)
///   e^(−4π²k²σ²/d²) ≤ d²/12 · e^(−4π²σ²/d²) (Σ 1/k² = π²/6), the bound taken: exact at
///   σ = 0, about 2e-3 × d²/12 at σ = 0.4 d, a repeatability analytical balances quote.
/// - σ² is the readings' variance less d²/12 (Sheppard's correction: their spread holds the
///   rounding's noise).
pub fn systematic_rounding_var(d: f64, s_obs: f64) -> f64 {
    if d <= 0.0 || !d.is_finite() {
        return 0.0;
    }
    let uniform = d * d / 12.0;
    let sigma2 = (s_obs * s_obs - uniform).max(0.0);
    uniform * (-4.0 * std::f64::consts::PI.powi(2) * sigma2 / (d * d)).exp()
}

/// The balance's scatter from one placement of a board to the next: the variance of one
/// day's mean reading, pooled over the boards weighed on more than one day.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct PlacementScatter {
    /// E[σ²] given the pooled sum of squares S on ν degrees of freedom under the Jeffreys
    /// prior, S / (ν − 2), g²: the plain S / ν would make the intervals too narrow on the
    /// few re-weighings a campaign has (the t quantile with ν = 8 is 1.86 against
    /// 1.645 √(8/6) = 1.90 for this variance).
    pub var_g2: f64,
    /// ν: the day means less one per board, summed.
    pub df: usize,
    /// Boards weighed on more than one day.
    pub n_boards: usize,
}

/// The fewest degrees of freedom that make a placement scatter: E[σ²] is finite from 3.
pub const MIN_PLACEMENT_DF: usize = 3;

/// The placement scatter of the balance that read `resolution_g` (boards read at the same
/// readability pool; another balance's readings stay apart), from every board's day means
/// (a board re-weighed on another day was taken off the pan and put back, so its day means
/// differ by what a placement errs, which the readings of one session cannot show). None
/// below [`MIN_PLACEMENT_DF`]. A board whose mass changed between days (ingest warns) pools
/// too: its scatter widens every board's term, the safe side.
pub fn placement_scatter<'a>(
    rows: impl IntoIterator<Item = &'a MassRow>,
    resolution_g: f64,
) -> Option<PlacementScatter> {
    let (mut ss, mut df, mut n_boards) = (0.0, 0usize, 0usize);
    for m in rows {
        if m.n_days >= 2 && m.resolution_g == resolution_g && m.day_means_ss_g2.is_finite() {
            ss += m.day_means_ss_g2;
            df += m.n_days as usize - 1;
            n_boards += 1;
        }
    }
    (df >= MIN_PLACEMENT_DF).then(|| PlacementScatter {
        var_g2: ss / (df as f64 - 2.0),
        df,
        n_boards,
    })
}

/// The smallest sd of a board's mass term, relative to its mass ([`mass_obs`]).
pub const MIN_MASS_SD_REL: f64 = 1e-6;

/// What a balance may err on one board and not on the next, in readability steps d, taken
/// as uniform within ± this (sd: it / √3 d), when the campaign does not measure it itself
/// ([`placement_scatter`]). OIML R 76-1 allows a class I balance ±0.5 e up to 50 000 e,
/// and an analytical balance's verification interval e is at most 10 d (1 mg on a 0.1 mg
/// balance): ±5 d. Eccentric placement and non-linearity, which differ between boards, are
/// what that allowance covers once the common calibration is drawn apart. It is a bound a
/// verified balance keeps, not its typical error: where boards were re-weighed, their
/// scatter is the measure. Without any allowance the mass term of a 0.1 mg balance's
/// repeated readings pinned a board's mass to 3e-6, and on the realistic lumped-mass
/// campaign step 1's Laplace fit diverged (the mass held against frequencies a point mass
/// lowers; the total-mass coordinate has carried that ridge since).
pub const MPE_READABILITY_STEPS: f64 = 5.0;

/// The seed stream of the balance's common bias ([`balance_bias_draw`]).
const BALANCE_BIAS_STREAM: u64 = 0x6261_6c62_6961;

/// One draw, for particle `i` of run `r`, of the balance's error common to every board, β,
/// relative: every weighed mass is the board's times 1 + β. Why common and why its scale:
/// - Weighing a board (ρ ≈ 1.9 g/cm³) against steel calibration weights (8 g/cm³) without
///   the air-buoyancy correction shifts the reading by ρ_air V (1 − ρ/ρ_ref) ≈ 0.05 %, the
///   same fraction for every board of one laminate; a calibration error scales every
///   reading alike. Both are the same on every board of a campaign, and neither is seen in
///   the readings' spread.
/// - The frequencies fix each board's stiffness per unit mass, so β moves every board's mass
///   and moduli together and leaves the data unchanged: the data cannot inform it, and it is
///   drawn from its prior, N(0, `sd_rel`²) (`--balance-bias`, default
///   [`ModelSpec::DEFAULT_BALANCE_BIAS_REL`]), into the physical columns only, as the
///   discrepancy's confounded part is ([`crate::update::posterior::confounded_draw`]).
///   Treated as independent per board (a floor on each board's term, before), it made every
///   contrast between boards as uncertain as the common level.
pub fn balance_bias_draw(sd_rel: f64, seed: u64, (r, i): (usize, usize)) -> f64 {
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};
    if sd_rel <= 0.0 {
        return 0.0;
    }
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(crate::bayes::smc::stream_key(&[
        seed,
        BALANCE_BIAS_STREAM,
        r as u64,
        i as u64,
    ]));
    let z: f64 = StandardNormal.sample(&mut rng);
    sd_rel * z
}

/// The prior of step 1's model-error term ([`ErrorModel::model_error_sd`]).
#[derive(Clone, Debug, serde::Serialize)]
pub struct ModelErrorPrior {
    /// How the model's frequencies move on finer meshes.
    pub spread: crate::fem::convergence::MeshSpread,
    /// Every paired free-free label (updating and validation) and its prior sd of the
    /// relative eigenvalue error b.
    pub labels: Vec<String>,
    pub sd: Vec<f64>,
    /// The sds of the updated labels, in their order.
    #[serde(skip)]
    pub sd_updated: Vec<f64>,
    /// Whether b is each board's own (independent between boards, integrated out per board).
    /// False where the step infers the model-form discrepancy: one mesh's error on boards
    /// whose parameters differ by a few per cent is the same on every board, so it is part of
    /// the discrepancy common to them, and only the sds' record stays
    /// ([`ModelErrorPrior::common_to_boards`]).
    pub per_board: bool,
}

impl ModelErrorPrior {
    /// The term taken by the discrepancy common to the boards, not drawn per board.
    ///
    /// Why: a discretization error is a function of the mesh and of the mode's wavelength over
    /// the element size. Every board runs on the same mesh, with moduli and thickness a few
    /// per cent from the others', so the error is nearly the same on every board (a tenth of
    /// itself apart in rms over the modes for moduli 4 % apart, most of that in a pair of
    /// modes near veering: the test `one_meshs_error_is_nearly_the_same_on_boards_a_few_per_
    /// cent_apart`). What differs between boards is a model error varying between boards,
    /// which the discrepancy's per-unit part σ_u takes, inferred from the boards themselves.
    /// Drawn in full and independently per board, the term let each board depart from the
    /// others by the whole mesh error in the modes the mesh resolves worst, and widened every
    /// contrast between boards along those modes.
    pub fn common_to_boards(mut self) -> Self {
        self.per_board = false;
        self
    }
    /// The per-board sds (of every label, or of the updated ones) where the term is each
    /// board's own; `None` where the common discrepancy took it.
    pub fn board_sd(&self, updated_only: bool) -> Option<&[f64]> {
        self.per_board.then_some(match updated_only {
            true => self.sd_updated.as_slice(),
            false => self.sd.as_slice(),
        })
    }
}

/// Floor of a label's model-error sd, relative to the largest of the labels: a mode whose
/// frequency happens to agree between the meshes compared is not thereby exact.
pub const MODEL_ERROR_FLOOR_SHARE: f64 = 0.1;

/// The mesh study the model-error term needs ([`model_error_from`]): the free board's
/// `fem::convergence::mesh_spread` on its own mesh, at these parameters, over this many modes.
pub fn model_error_study(
    nominal: &crate::fem::Params,
    updated: &Labels,
    all: &Labels,
) -> (crate::fem::Params, usize) {
    let n = modes_needed(updated, all);
    // The mesh study's models are the standard ones: a known thickness is at its nominal in
    // `nominal`, so it is simply left out.
    let (names, values) = nominal
        .names
        .iter()
        .zip(&nominal.values)
        .filter(|(n, _)| *n != names::CORE_THICKNESS)
        .map(|(n, v)| (n.clone(), *v))
        .unzip();
    (crate::fem::Params { names, values }, n)
}

/// The model-error prior of the labels: b_m ~ N(0, s_m²), s_m = 2 × the mode's relative
/// frequency spread over the √2 and 2 × finer meshes (λ = ω², so twice the frequency's
/// relative error), floored at a tenth of the largest s of the labels (and 1e-7).
/// `spread` is the outcome of the study [`model_error_study`] names.
pub fn model_error_from(
    spread: crate::fem::convergence::MeshSpread,
    updated: &Labels,
    all: &Labels,
) -> ModelErrorPrior {
    let raw = |mm: usize| 2.0 * spread.rel_spread.get(mm).copied().unwrap_or(0.0);
    let top = all
        .model_mode
        .iter()
        .chain(&updated.model_mode)
        .map(|&mm| raw(mm))
        .fold(0.0, f64::max);
    let floor = (MODEL_ERROR_FLOOR_SHARE * top).max(1e-7);
    let sd_of = |mm: usize| raw(mm).max(floor);
    ModelErrorPrior {
        labels: all.labels.clone(),
        sd: all.model_mode.iter().map(|&mm| sd_of(mm)).collect(),
        sd_updated: updated.model_mode.iter().map(|&mm| sd_of(mm)).collect(),
        spread,
        per_board: true,
    }
}

/// Unit 0's eigenvalues of the updated modes at the unit coordinates `x` (with the auxiliary
/// values `aux`), `None` where the model is undefined or an eigenvalue is not positive: what
/// the modes' sensitivities to the unit coordinates are taken of.
pub fn unit0_eigenvalues(target: &ModalTarget, aux: &[f64], x: &[f64]) -> Option<Vec<f64>> {
    let nm = target.errors.n_modes;
    let t = smc::Target::model(target, aux, 0, x)?;
    let l = t.lambda[..nm].to_vec();
    l.iter().all(|v| v.is_finite() && *v > 0.0).then_some(l)
}

/// The central differences' step of the modes' sensitivities to the unit coordinates (relative
/// coordinates: 0.1 %).
pub const SENSITIVITY_STEP: f64 = 1e-3;

/// The model-form discrepancy of `target`'s updated modes ([`crate::bayes::discrepancy`]),
/// orthogonal to the relative eigenvalue sensitivities of unit 0's coordinates near `x_ref`
/// (the reference point x = 0 where None; step 2 passes its centre fit, where every label is
/// tracked, with the auxiliary values `aux`, the step-1 posterior mean), its
/// scale's prior median `fidelity_freq` (relative frequency); the unit coordinates `pinned`
/// (held by data of their own) absorb none of it. `None` (with an info finding) where the
/// fidelity is 0, or where the units' coordinates span every mode.
pub fn discrepancy_for(
    target: &ModalTarget,
    (aux, x_ref): (&[f64], Option<&[f64]>),
    fidelity_freq: f64,
    (pinned, what): (&[usize], &str),
    findings: &mut Findings,
) -> anyhow::Result<Option<crate::bayes::discrepancy::Discrepancy>> {
    use crate::bayes::discrepancy::{sensitivities, Discrepancy};
    if fidelity_freq == 0.0 {
        return Ok(None);
    }
    if !(fidelity_freq.is_finite() && fidelity_freq > 0.0) {
        bail!("{what}: the model's fidelity (--discrepancy-pct) must be a finite share ≥ 0, found {fidelity_freq}");
    }
    let nm = target.errors.n_modes;
    let d = smc::Target::unit_dim(target);
    let lambda = |x: &[f64]| unit0_eigenvalues(target, aux, x);
    let sens_at = |x0: &[f64]| {
        sensitivities(lambda, x0, nm, SENSITIVITY_STEP)
            .filter(|s| s.iter().all(|v| v.is_finite()))
            .ok_or_else(|| anyhow!("{what}: the model-form discrepancy: the model is undefined (or a label lost) within 0.1 % of {x0:?}"))
    };
    // The plain metric: every mode's discrepancy weighs alike. The data's precision per
    // mode (n_m over the within-board scatter ε̂_m², plus the model-error term) as the metric
    // gave a discrepancy space whose evidence was lower by 13 nats on the realistic paper
    // campaign (400 × 2), and no less correlation with the boards' moduli.
    let w = vec![1.0; nm];
    // The sensitivities where the units are, not at the reference point: the units sit a few
    // per cent from it (a plate's moduli fitted to a real board), and the sensitivities move
    // by as much, which leaves a discrepancy orthogonal at the reference point correlated
    // with the units' common shift at the 1e-4 level its posterior resolves (±0.9 on the
    // solid-truth campaign; the sampler then crawled). The units' common offset is the
    // weighted least-squares fit of the mean log-eigenvalue residuals at the reference point.
    let x0 = x_ref.map_or_else(|| vec![0.0; d], <[f64]>::to_vec);
    let mut sens = sens_at(&x0)?;
    if let Some(l0) = lambda(&x0) {
        let mut r = vec![0.0; nm];
        let mut n = vec![0usize; nm];
        for u in &target.units {
            for f in u.freq.iter().filter(|f| f.cond == 0) {
                r[f.mode] += f.ln_lambda_hat - l0[f.mode].ln();
                n[f.mode] += 1;
            }
        }
        let r: Vec<f64> = r
            .iter()
            .zip(&n)
            .map(|(a, k)| a / (*k).max(1) as f64)
            .collect();
        if let Some(v) = weighted_offset(&sens, &r, &w, d) {
            // Within the ROM's verified box.
            let v: Vec<f64> = v
                .iter()
                .zip(&x0)
                .map(|(a, c)| c + a.clamp(-0.15, 0.15))
                .collect();
            if let Ok(s) = sens_at(&v) {
                sens = s;
            }
        }
    }
    let disc = Discrepancy::new(&sens, nm, d, &w, fidelity_freq, pinned);
    if disc.is_none() {
        findings.push(Finding::new(
            Severity::Info,
            "update.discrepancy_none",
            format!("{what}: the units' {d} coordinate(s) span all {nm} updated modes: no discrepancy is left that the parameters cannot absorb, so none is inferred"),
        ));
    }
    Ok(disc)
}

/// argmin over v of Σ_m w_m (r_m − (S v)_m)² (S: n_m × d row-major), with a ridge of 1e-12
/// of the normal matrix's trace so that a coordinate the modes do not see (the mass scale,
/// whose moduli are per unit mass) stays at 0. `None` where the solve fails.
pub fn weighted_offset(s: &[f64], r: &[f64], w: &[f64], d: usize) -> Option<Vec<f64>> {
    let nm = r.len();
    let mut a = vec![0.0; d * d];
    let mut b = vec![0.0; d];
    for m in 0..nm {
        for i in 0..d {
            b[i] += w[m] * s[m * d + i] * r[m];
            for j in 0..d {
                a[i * d + j] += w[m] * s[m * d + i] * s[m * d + j];
            }
        }
    }
    let tr: f64 = (0..d).map(|i| a[i * d + i]).sum();
    for i in 0..d {
        a[i * d + i] += 1e-12 * tr.max(1e-300);
    }
    let (l, jitter) = crate::bayes::stats::cholesky_jittered(&a, d);
    if !jitter.is_finite() {
        return None;
    }
    let y = crate::bayes::stats::lower_solve(&l, d, &b);
    let v = crate::bayes::stats::lower_transpose_solve(&l, d, &y);
    v.iter().all(|x| x.is_finite()).then_some(v)
}

/// Model modes a ROM must carry for the updated labels and every paired label.
pub fn modes_needed(labels: &Labels, all: &Labels) -> usize {
    labels
        .model_mode
        .iter()
        .chain(&all.model_mode)
        .copied()
        .max()
        .unwrap_or(0)
        + 1
}

/// Labels of every accepted pair of a setup, with their model mode (0-based), in model order.
/// Every paired label of `setup` with its model mode (the one most of its pairs name). A
/// model mode carries one label: where two labels name the same mode (the pair stage
/// labels measured modes one measurement at a time, and near-degenerate modes can trade
/// labels), the label with more pairs keeps it and the other is reported in `findings` and
/// left out of the residuals. Two labels on one mode gave that mode's reference shape to
/// both, and the second was tracked onto an unrelated mode (a residual of −40 %).
pub fn all_labels(
    pairs: &[PairRow],
    setup: &str,
    n_modes: usize,
    findings: &mut Findings,
) -> Labels {
    let mut by: BTreeMap<String, BTreeMap<i32, usize>> = BTreeMap::new();
    for p in pairs.iter().filter(|p| p.setup == setup) {
        *by.entry(p.label.clone())
            .or_default()
            .entry(p.model_mode)
            .or_default() += 1;
    }
    // (model mode, pairs, label), the mode's most-paired label first.
    let mut v: Vec<(usize, usize, String)> = by
        .into_iter()
        .filter_map(|(l, c)| {
            let (mm, n) = c.into_iter().max_by_key(|(_, n)| *n)?;
            (mm >= 1 && (mm as usize) <= n_modes).then(|| ((mm - 1) as usize, n, l))
        })
        .collect();
    v.sort_by(|a, b| a.0.cmp(&b.0).then(b.1.cmp(&a.1)).then(a.2.cmp(&b.2)));
    let mut kept: Vec<(usize, String)> = vec![];
    for (m, n, l) in v {
        match kept.iter().find(|(k, _)| *k == m) {
            Some((_, winner)) => findings.push(Finding::new(
                Severity::Warning,
                "update.label_shares_mode",
                format!(
                    "{setup}: label {l:?} ({n} pair(s)) names model mode {} like {winner:?}, which has more pairs; its pairs have no residual rows",
                    m + 1
                ),
            )),
            None => kept.push((m, l)),
        }
    }
    Labels {
        labels: kept.iter().map(|(_, l)| l.clone()).collect(),
        model_mode: kept.iter().map(|(m, _)| *m).collect(),
    }
}

/// A unit's data for the updated labels and, for the residuals, for every paired label with
/// shapes; the residual data's findings are reported too, once each.
#[allow(clippy::type_complexity)]
pub fn unit_and_residual_data(
    rows: &[&PairRow],
    labels: &Labels,
    all: &Labels,
    use_shapes: bool,
    (model, rom, shapes): (&FeModel, &Rom, &ShapeMap<'_>),
    covariate: Option<&BTreeMap<String, f64>>,
    findings: &mut Findings,
) -> anyhow::Result<(UnitData, (UnitData, Vec<ObsMeta>))> {
    let sh = use_shapes.then_some((model, rom, shapes));
    let (mut data, meta) = unit_data(rows, &labels.labels, sh, findings)?;
    let mut residual_findings = Findings::default();
    let mut all_data = unit_data(
        rows,
        &all.labels,
        Some((model, rom, shapes)),
        &mut residual_findings,
    )?;
    if let Some(c) = covariate {
        set_conditions(&mut data, &meta, c);
        set_conditions(&mut all_data.0, &all_data.1, c);
    }
    for f in residual_findings.0 {
        if !findings.0.contains(&f) {
            findings.push(f);
        }
    }
    Ok((data, all_data))
}

/// A unit's conditions: the distinct covariate offsets of its measurements (in order of
/// first appearance), and each observation's condition.
pub fn set_conditions(data: &mut UnitData, meta: &[ObsMeta], offsets: &BTreeMap<String, f64>) {
    data.conditions.clear();
    for (k, m) in meta.iter().enumerate() {
        let c = offsets.get(&m.measurement_id).copied().unwrap_or(0.0);
        let i = match data.conditions.iter().position(|x| *x == c) {
            Some(i) => i,
            None => {
                data.conditions.push(c);
                data.conditions.len() - 1
            }
        };
        data.freq[k].cond = i;
        if let Some(sh) = m.shape {
            data.shapes[sh].cond = i;
        }
    }
}

/// Points at which mode shapes of different joint models are compared: a 13 × 9 grid inset
/// by 4 % of the outline, without the points inside a hole's clamped disc.
pub fn match_points(board: &Board) -> Vec<[f64; 2]> {
    let (lx, ly) = (board.length_x_m, board.width_y_m);
    let r_clamp = 0.5 * board.joint().clamp_diameter_m;
    let mut out = vec![];
    for j in 0..9 {
        for i in 0..13 {
            let x = lx * (0.04 + 0.92 * i as f64 / 12.0);
            let y = ly * (0.04 + 0.92 * j as f64 / 8.0);
            if board
                .holes
                .iter()
                .all(|h| (x - h.x_m).hypot(y - h.y_m) > r_clamp.max(0.5 * h.diameter_m) * 1.05)
            {
                out.push([x, y]);
            }
        }
    }
    out
}

/// The identified modes of `setup` among the rows of modes.parquet (finite frequency only).
pub fn identified_modes<'a>(rows: &'a [ModeRow], setup: &str) -> Vec<&'a ModeRow> {
    rows.iter()
        .filter(|r| r.setup == setup && r.freq_hz.is_finite())
        .collect()
}

/// A numeric sheet column per measurement in its table's order (`None`: no finite value),
/// with the table's name for messages.
pub type CovariateColumn<'a> = (&'a [(String, Option<f64>)], &'a str);

/// The covariate of an enrichment for the measurements `used`, as offsets from their mean
/// (returned too): `values` is the column per measurement in its table's order (`None`: no
/// finite value), `source` names the table in messages. A used measurement without a value is
/// a warning and sits at the mean (offset 0), so the refit keeps the baseline's data.
pub fn covariate_offsets(
    values: &[(String, Option<f64>)],
    source: &str,
    column: &str,
    used: &BTreeSet<&str>,
    findings: &mut Findings,
) -> anyhow::Result<(BTreeMap<String, f64>, f64)> {
    let mut found: BTreeMap<String, f64> = BTreeMap::new();
    let mut missing = vec![];
    for (m, v) in values {
        if !used.contains(m.as_str()) {
            continue;
        }
        match v {
            Some(v) => {
                found.insert(m.clone(), *v);
            }
            None => missing.push(m.clone()),
        }
    }
    for m in used {
        if !found.contains_key(*m) && !missing.iter().any(|x| x == m) {
            missing.push(m.to_string());
        }
    }
    if found.is_empty() {
        bail!("{source}: column {column:?} has no value for any measurement used; nothing to refit against");
    }
    if !missing.is_empty() {
        findings.push(Finding::new(
            Severity::Warning,
            "update.covariate_missing",
            format!(
                "{} measurement(s) have no {column}: {}; taken at the mean of the others",
                missing.len(),
                missing.join(", ")
            ),
        ));
    }
    let mean = found.values().sum::<f64>() / found.len() as f64;
    Ok((
        found.into_iter().map(|(k, v)| (k, v - mean)).collect(),
        mean,
    ))
}

#[cfg(test)]
mod mass_term_tests {
    use super::*;

    /// The balance term's sd: the spread of the mean and the rounding's systematic part,
    /// never below the board-to-board allowance of ±5 readability steps (the common
    /// part is drawn apart); one reading counts as one readability step; readings ingest
    /// flagged as inconsistent keep their full spread; a single reading with no readability
    /// is held to 1e-6 of the mass.
    #[test]
    fn the_mass_term_sd_is_the_readings_sd_of_the_mean() {
        let row = MassRow {
            mass_g: 12.5,
            n_stable: 6,
            std_g: 6e-5,
            resolution_g: 1e-4,
            inconsistent: false,
            n_days: 1,
            day_means_ss_g2: 0.0,
            day_share_sq_sum: 1.0,
        };
        let mut f = Findings::default();
        let mpe = 5e-4 / 3f64.sqrt();
        let m = mass_obs(&row, "PCB-01", None, &mut f).expect("a mass term");
        assert!(
            (m.sd_g - mpe).abs() < 1e-15,
            "readings' sd of the mean below the balance's allowance: {}",
            m.sd_g
        );
        assert_eq!(m.mass_g, 12.5);
        // A coarse balance's readings: their own spread.
        let coarse = MassRow {
            std_g: 0.5,
            resolution_g: 0.01,
            ..row
        };
        // Their spread (50 d) dithers the rounding: none of it stays systematic.
        let own = (0.25f64 / 6.0).sqrt();
        let c = mass_obs(&coarse, "PCB-01", None, &mut f).expect("a mass term");
        assert!((c.sd_g - own).abs() < 1e-15, "{} vs {own}", c.sd_g);
        // One reading: one readability step for its spread.
        let single = MassRow {
            n_stable: 1,
            std_g: 0.0,
            resolution_g: 0.01,
            ..row
        };
        let one = mass_obs(&single, "PCB-01", None, &mut f).expect("a mass term");
        assert!((one.sd_g - 0.05 / 3f64.sqrt()).abs() < 1e-15);
        let bare = MassRow {
            resolution_g: 0.0,
            ..single
        };
        let b = mass_obs(&bare, "PCB-01", None, &mut f).expect("a mass term");
        assert_eq!(b.sd_g, MIN_MASS_SD_REL * 12.5);
        assert!(f.0.is_empty());
        let spread = MassRow {
            inconsistent: true,
            ..row
        };
        let s = mass_obs(&spread, "PCB-01", None, &mut f).expect("a mass term");
        assert!((s.sd_g - mpe).abs() < 1e-15);
        let wide = MassRow {
            std_g: 0.01,
            inconsistent: true,
            ..row
        };
        let w = mass_obs(&wide, "PCB-01", None, &mut f).expect("a mass term");
        assert!((w.sd_g - 0.01).abs() < 1e-15);
        assert_eq!(f.0.len(), 2, "the inconsistent readings are reported");
        let none = MassRow { n_stable: 0, ..row };
        assert!(mass_obs(&none, "PCB-01", None, &mut f).is_none());
    }

    /// Boards re-weighed on other days: their day means' scatter, pooled over the boards of
    /// one readability, on the degrees of freedom they give, replaces the OIML allowance;
    /// each board's term is it times the board's share of its days.
    #[test]
    fn re_weighed_boards_measure_the_balance_between_placements() {
        let two_days = MassRow {
            mass_g: 12.5,
            n_stable: 6,
            std_g: 6e-5,
            resolution_g: 1e-4,
            inconsistent: false,
            n_days: 2,
            day_means_ss_g2: 2e-9,
            day_share_sq_sum: 0.5,
        };
        let three_days = MassRow {
            n_days: 3,
            day_means_ss_g2: 1e-9,
            ..two_days.clone()
        };
        let other_balance = MassRow {
            resolution_g: 1e-3,
            day_means_ss_g2: 1.0,
            ..two_days.clone()
        };
        let rows = [two_days.clone(), three_days, other_balance];
        // Two boards of ν 1 and 2: none below 3 degrees of freedom.
        assert_eq!(placement_scatter(&rows[..1], 1e-4), None);
        let p = placement_scatter(&rows, 1e-4).expect("three degrees of freedom");
        assert_eq!((p.df, p.n_boards), (3, 2));
        assert!((p.var_g2 - 3e-9).abs() < 1e-22, "S / (ν - 2): {}", p.var_g2);
        let mut f = Findings::default();
        let m = mass_obs(&two_days, "PCB-01", Some(p), &mut f).expect("a mass term");
        // One day's variance over the board's two days, 3e-9 × 0.5, above the readings'
        // 3.6e-9 / 6, with the rounding's systematic part (readings 0.6 d apart: 1.8e-5 of
        // d²/12).
        let q = systematic_rounding_var(1e-4, 6e-5);
        assert!(q > 0.0 && q < 2e-5 * 1e-8 / 12.0, "{q}");
        assert!((m.sd_g - (1.5e-9 + q).sqrt()).abs() < 1e-18, "{}", m.sd_g);
        // A scatter below the readings' own: theirs.
        let tight = PlacementScatter { var_g2: 0.0, ..p };
        let t = mass_obs(&two_days, "PCB-01", Some(tight), &mut f).expect("a mass term");
        let own = (3.6e-9f64 / 6.0 + q).sqrt();
        assert!(
            (t.sd_g - own).abs() < 1e-18,
            "the readings' own: {} vs {own}",
            t.sd_g
        );
        assert!(f.0.is_empty());
    }

    /// Rounding to d: all of it systematic when the readings never vary (d²/12), the first
    /// harmonic's e^(−4π²σ²/d²) of it under Gaussian noise of sd σ (the readings' variance
    /// less d²/12), nothing without a readability.
    #[test]
    fn noise_dithers_the_rounding_out_of_the_mean() {
        let d = 1e-4;
        assert_eq!(systematic_rounding_var(d, 0.0), d * d / 12.0);
        assert_eq!(
            systematic_rounding_var(d, 0.2 * d),
            d * d / 12.0,
            "below d/√12"
        );
        let at = |sigma: f64| systematic_rounding_var(d, (sigma * sigma + d * d / 12.0).sqrt());
        let expect = d * d / 12.0 * (-4.0 * std::f64::consts::PI.powi(2) * 0.16).exp();
        assert!(
            (at(0.4 * d) - expect).abs() < 1e-6 * expect,
            "{}",
            at(0.4 * d)
        );
        assert!(at(0.4 * d) < 2e-3 * d * d / 12.0);
        assert!(at(0.1 * d) < d * d / 12.0 && at(0.1 * d) > at(0.2 * d));
        assert_eq!(systematic_rounding_var(0.0, 1.0), 0.0);
    }

    /// The bound against the rounding's bias computed directly (no series): for true
    /// values x₀ across one step, the mean of round(x₀ + σz) by the normal's step
    /// probabilities, less x₀; its mean square over x₀ lies under the bound taken from the
    /// readings' variance (also computed directly), for σ from 0 to 0.5 d.
    #[test]
    fn the_rounding_bound_holds_the_bias_computed_directly() {
        use statrs::distribution::{ContinuousCDF, Normal};
        let d = 1e-4;
        for sigma_d in [0.0, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5] {
            let sigma = sigma_d * d;
            let n = 400;
            let (mut bias_ms, mut var) = (0.0, 0.0);
            for i in 0..n {
                let x0 = (i as f64 + 0.5) / n as f64 * d;
                let (mean, second) = if sigma == 0.0 {
                    let r = (x0 / d).round() * d;
                    (r, r * r)
                } else {
                    let z = Normal::new(0.0, sigma).expect("a normal");
                    (-12..=12).fold((0.0, 0.0), |(m, s), k| {
                        let v = f64::from(k) * d;
                        let p = z.cdf(v + 0.5 * d - x0) - z.cdf(v - 0.5 * d - x0);
                        (m + v * p, s + v * v * p)
                    })
                };
                bias_ms += (mean - x0).powi(2) / n as f64;
                var += (second - mean * mean) / n as f64;
            }
            let bound = systematic_rounding_var(d, var.sqrt());
            assert!(bias_ms <= bound, "σ = {sigma_d} d: {bias_ms:e} > {bound:e}");
            // Within a factor 2 from σ = 0.3 d (1.7 there; the higher harmonics fade).
            if sigma_d >= 0.3 {
                assert!(
                    bound < 2.0 * bias_ms,
                    "σ = {sigma_d} d: {bound:e} vs {bias_ms:e}"
                );
            }
        }
    }

    /// The balance's common bias: zero without a scale, the same for the same particle and
    /// seed, and over many particles a normal of the given sd.
    #[test]
    fn the_balance_bias_is_a_seeded_normal_of_its_scale() {
        assert_eq!(balance_bias_draw(0.0, 7, (0, 3)), 0.0);
        assert_eq!(
            balance_bias_draw(3e-4, 7, (1, 3)),
            balance_bias_draw(3e-4, 7, (1, 3))
        );
        assert_ne!(
            balance_bias_draw(3e-4, 7, (1, 3)),
            balance_bias_draw(3e-4, 7, (1, 4))
        );
        let n = 20_000;
        let d: Vec<f64> = (0..n).map(|i| balance_bias_draw(3e-4, 7, (0, i))).collect();
        let mean = d.iter().sum::<f64>() / n as f64;
        let sd = (d.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n as f64).sqrt();
        // Standard errors: 3e-4 / √n = 2.1e-6 for the mean, 1.5e-6 for the sd.
        assert!(mean.abs() < 1e-5, "{mean}");
        assert!((sd - 3e-4).abs() < 8e-6, "{sd}");
    }
}

#[cfg(test)]
mod thickness_tests {
    use super::*;
    use crate::fem::Setup;

    /// A board's measured core thickness becomes an observation of its thickness coordinate
    /// (relative to the board file's, sd THICKNESS_SD_M relative); a board the sheet gives
    /// none for, or one outside the ROM's box, gets none and a warning naming it. The core's
    /// mass share: the same board without its copper weighs its core.
    #[test]
    fn measured_thickness_is_an_observation_of_the_boards_coordinate() {
        let board = crate::fem::tests::helpers::thin_board();
        let h0 = board.core.thickness_m;
        let params: Vec<String> = ["e_x_pa", "mass_scale", names::CORE_THICKNESS]
            .map(String::from)
            .to_vec();
        let units: Vec<String> = ["A", "B", "C"].map(String::from).to_vec();
        let given = BTreeMap::from([("A".to_string(), 1.06 * h0), ("C".to_string(), 1.5 * h0)]);
        let mut findings = Findings::default();
        let obs = thickness_obs(&params, h0, &units, &given, 0.2, &mut findings);
        assert_eq!(obs.len(), 3);
        assert_eq!(obs[0].len(), 1);
        let (k, x, sd) = obs[0][0];
        assert_eq!(k, 2);
        assert!((x - 0.06).abs() < 1e-12 && (sd - THICKNESS_SD_M / h0).abs() < 1e-15);
        assert!(obs[1].is_empty() && obs[2].is_empty());
        let codes: Vec<(&str, bool)> = findings
            .iter()
            .map(|f| (f.code.as_str(), f.message.starts_with("board ")))
            .collect();
        assert!(
            codes.contains(&("update.thickness_unknown", true)),
            "{codes:?}"
        );
        assert!(
            codes.contains(&("update.thickness_outside_box", true)),
            "{codes:?}"
        );
        // Without the parameter: nothing observed, nothing said.
        let mut none = Findings::default();
        assert!(thickness_obs(&params[..2], h0, &units, &given, 0.2, &mut none).is_empty());
        assert!(none.is_empty());
        let mesh = crate::fem::MeshOptions { nx: 8, ny: 6 };
        let plain = FeModel::build(&board, Setup::Free, &mesh).unwrap();
        assert!(core_thickness_mass(&plain).unwrap().is_none());
        let model = FeModel::build_with(
            &board,
            Setup::Free,
            &mesh,
            crate::fem::ModelOptions {
                core_thickness: true,
            },
        )
        .unwrap();
        let (_, h, share) = core_thickness_mass(&model).unwrap().unwrap();
        assert_eq!(h, h0);
        let mut bare = board.clone();
        bare.copper.clear();
        let core = FeModel::build(&bare, Setup::Free, &mesh).unwrap();
        let want = core.total_mass_kg(&core.nominal_params()).unwrap()
            / model.total_mass_kg(&model.nominal_params()).unwrap();
        assert!(
            (share - want).abs() < 1e-12 && want < 1.0,
            "share {share} vs {want}"
        );
    }
}

#[cfg(test)]
mod assembly_tests {
    use super::*;

    fn pair(m: &str, b: &str, mode: i32, f: f64, mm: i32, label: &str) -> PairRow {
        PairRow {
            measurement_id: m.into(),
            board_id: b.into(),
            setup: "free".into(),
            mode,
            freq_hz: f,
            model_mode: mm,
            label: label.into(),
        }
    }

    /// A small campaign's pairs to the likelihood's data: the labels pair's presence marks,
    /// each at the model mode most of its pairs name; a requested label without a pair is
    /// named and left out; every pair of a board becomes a frequency term λ̂ = (2π f)² of its
    /// label, in pair order, with its measurement and board.
    #[test]
    fn pairs_become_labels_and_frequency_terms() {
        let pairs = vec![
            pair("M1", "B1", 1, 100.0, 7, "torsion-1"),
            pair("M1", "B1", 2, 180.0, 8, "bending-x-1"),
            pair("M2", "B1", 1, 101.0, 7, "torsion-1"),
            pair("M3", "B2", 1, 99.0, 9, "torsion-1"),
            pair("M3", "B2", 2, 181.0, 8, "bending-x-1"),
        ];
        let presence = vec!["torsion-1".to_string(), "bending-x-1".to_string()];
        let mut findings = Findings::default();
        let labels = select_labels(&pairs, "free", &[], &presence, &mut findings).unwrap();
        assert_eq!(labels.labels, presence);
        assert_eq!(
            labels.model_mode,
            vec![6, 7],
            "the majority model mode, 0-based"
        );
        assert!(findings.0.is_empty());

        let asked = vec!["torsion-1".to_string(), "plate-2-2".to_string()];
        let l2 = select_labels(&pairs, "free", &asked, &presence, &mut findings).unwrap();
        assert_eq!(l2.labels, vec!["torsion-1".to_string()]);
        assert_eq!(findings.0.len(), 1);
        assert_eq!(findings.0[0].code, "update.label_unpaired");
        assert!(select_labels(
            &pairs,
            "free",
            &["plate-2-2".into()],
            &presence,
            &mut findings
        )
        .is_err());

        let b1: Vec<&PairRow> = pairs.iter().filter(|p| p.board_id == "B1").collect();
        let (data, meta) = unit_data(&b1, &labels.labels, None, &mut findings).unwrap();
        let w = |f: f64| (2.0 * std::f64::consts::PI * f).powi(2);
        let got: Vec<(usize, f64)> = data.freq.iter().map(|o| (o.mode, o.lambda_hat)).collect();
        assert_eq!(got, vec![(0, w(100.0)), (1, w(180.0)), (0, w(101.0))]);
        assert_eq!(
            meta.iter()
                .map(|m| (m.measurement_id.as_str(), m.label))
                .collect::<Vec<_>>(),
            vec![("M1", 0), ("M1", 1), ("M2", 0)]
        );
        assert!(data.shapes.is_empty() && data.mass.is_none());
    }
}

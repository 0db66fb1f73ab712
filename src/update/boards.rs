//! Step 1 (boards, free-free) as pure functions: the free model with the measured thickness
//! and a board enrichment, the units (every board's frequencies, shapes, mass, thickness and
//! covariate), the population prior and the target, the ROM-box rule on the posterior, the
//! tables' rows and the evidence. `stage::update` reads the inputs, calls these in order and
//! writes the outputs.

use crate::bayes::modal::{CovariateEffect, Terms, UnitData};
use crate::bayes::population::PopulationPrior;
use crate::bayes::smc::Particle;
use crate::bayes::target::{Compose, ErrorModel, ModalTarget, PerMass, TotalMass};
use crate::fem::params::names;
use crate::fem::{Board, FeModel, Params, Rom, Setup};
use crate::findings::{Finding, Findings, Severity};
use crate::modal::rows::{ModeRow, PairRow};
use crate::update::enrichment::{board_enrichment, BoardContext, BoardEffect, BoardEnrichment};
use crate::update::posterior::{
    carried_deviation, confounded_draw, discrepancy_json, evidence_json, less_confounded,
    population_columns, DrawTable, SummaryRow,
};
use crate::update::problem::CovariateColumn;
use crate::update::problem::{
    all_labels, balance_bias_draw, covariate_offsets, discrepancy_for, mass_obs, modes_needed,
    placement_scatter, predictors, shape_map, thickness_obs, unit_and_residual_data,
    BoardCoordinates, Labels, MassRow, ModelErrorPrior, ModelSpec, ObsMeta, PlacementScatter,
    StepTarget,
};
use crate::update::rom_box::RomBoxViolation;
use crate::update::sampler::{box_violations, particles_of, Results};
use anyhow::{anyhow, bail};
use std::collections::{BTreeMap, BTreeSet};

/// Prior sd (relative) of the population mean of a shear-deformable board's transverse shear
/// modulus, at least: no datasheet gives it, and micromechanics (Halpin–Tsai, E-glass fibres
/// of G 30 GPa in epoxy of G 1.3 GPa) puts woven FR-4's at 2.5–3.5 GPa over the fibre volume
/// fractions of common prepregs (0.35–0.5), ±17 % about its middle: taken 30 %.
pub const G_Z_PRIOR_WIDTH: f64 = 0.3;

/// Step 1's parameters when the user names none: the paper's (the in-plane moduli and the
/// mass scale), and on a shear-deformable board its transverse shear modulus too. That one is
/// uncertain by ±17 % or more ([`G_Z_PRIOR_WIDTH`]). Mindlin's lowering of a mode,
/// (π²/12)(E/κG)(h/λ)², is 1–3 % for a 1.5 mm FR-4 core (E/κG ≈ 10) at half-wavelengths of
/// 25–40 mm, and changes in proportion to G's relative error: 0.2–0.5 % over that range. Held
/// at its nominal value, that error would be read as the model's form, above the diagnosis's
/// practical threshold (0.1 %).
pub fn default_params(board: &crate::fem::board::Board) -> Vec<String> {
    let mut p: Vec<String> = [names::E_X, names::E_Y, names::G_XY, names::MASS_SCALE]
        .map(String::from)
        .to_vec();
    if board.core.transverse_shear().is_some() {
        p.push(names::G_Z.into());
    }
    p
}

/// The free model of step 1: a board enrichment's parameter added, the updated parameters and
/// their nominal values, the labels it tracks.
pub struct BoardModel {
    pub model: FeModel,
    pub board_nominal: Params,
    /// The board's own mass (the balance weighs an added mass with it), g.
    pub nominal_mass_g: f64,
    pub enrichment: Option<BoardEnrichment>,
    pub param_names: Vec<String>,
    /// A point mechanism's parameter, on a logarithmic axis of this half-width.
    pub log_axes: Vec<(String, f64)>,
    pub updated: Vec<usize>,
    pub reference: Vec<f64>,
    pub all: Labels,
    pub need: usize,
}

/// The free model (see [`BoardModel`]); `with_thickness`: the core thickness a parameter.
pub fn board_model(
    board: &Board,
    spec: &ModelSpec,
    labels: &Labels,
    pairs: &[PairRow],
    with_thickness: bool,
    findings: &mut Findings,
) -> anyhow::Result<BoardModel> {
    let model_opts = crate::fem::ModelOptions {
        core_thickness: with_thickness,
    };
    let mut model = FeModel::build_with(board, Setup::Free, &board.mesh, model_opts)?;
    let board_nominal = model.nominal_params();
    // The board's own mass (the balance weighs an added mass with it).
    let nominal_mass_g = model.total_mass_kg(&board_nominal)? * 1e3;
    let enrichment = spec
        .enrich
        .map(|m| {
            board_enrichment(
                m,
                BoardContext {
                    board_mass_kg: 1e-3 * nominal_mass_g,
                    location_m: spec.enrich_location,
                },
            )
            .map_err(|e| anyhow!("--enrich: {e}"))
        })
        .transpose()?;
    // A point mechanism's parameter joins the updated ones on a logarithmic coordinate.
    let mut param_names = spec.params.clone();
    let mut log_axes: Vec<(String, f64)> = vec![];
    if let Some(BoardEffect::PointMass {
        parameter,
        x_m,
        y_m,
        reference_kg,
        log_box,
    }) = enrichment.as_ref().map(|e| &e.effect)
    {
        model
            .add_point_mass_param(parameter, *x_m, *y_m, *reference_kg)
            .map_err(|e| anyhow!("--enrich added_mass at ({x_m}, {y_m}) m: {e}"))?;
        param_names.push(parameter.clone());
        log_axes.push((parameter.clone(), *log_box));
    }
    let nominal = model.nominal_params();
    let mut updated = vec![];
    for p in &param_names {
        updated.push(nominal.position(p).map_err(|_| {
            anyhow!(
                "--params: {p:?} is not a parameter of the model; expected some of {:?}",
                nominal.names
            )
        })?);
    }
    let reference: Vec<f64> = updated.iter().map(|&i| nominal.values[i]).collect();
    if let Some((i, _)) = reference.iter().enumerate().find(|(_, v)| **v == 0.0) {
        bail!(
            "--params: {} has nominal value 0; relative updating needs a non-zero nominal",
            param_names[i]
        );
    }
    let all = all_labels(pairs, "free", 40, findings);
    let need = modes_needed(labels, &all);
    Ok(BoardModel {
        model,
        board_nominal,
        nominal_mass_g,
        enrichment,
        param_names,
        log_axes,
        updated,
        reference,
        all,
        need,
    })
}

/// Step 1's target and what its outputs need: the boards (units) and their residual data, the
/// model-error prior, a covariate, the population's coordinates.
pub struct BoardTarget {
    pub step: StepTarget,
    pub model_error: Option<ModelErrorPrior>,
    pub covariate: Option<CovariateEffect>,
    pub pop_names: Vec<String>,
    pub pop_reference: Vec<f64>,
    /// Updated coordinates, and of them the board parameters (an enrichment's follow).
    pub d: usize,
    pub d0: usize,
}

/// The population's coordinate of the mass beside a point mass ([`TotalMass`]): the weighed
/// total over its nominal (the board's nominal mass and the point mass's reference).
pub const TOTAL_MASS_SCALE: &str = "total_mass_scale";

/// Step 1's target: the boards with free-free pairs or a mass are its units. `masses`: the
/// balance's per board; `covariate_values`: a temperature enrichment's column per measurement
/// with its source; `thickness_m`: the boards' measured core thickness; `model_error`: the
/// model-error term's prior where the step has one ([`crate::update::problem::model_error_from`] of the mesh
/// study [`crate::update::problem::model_error_study`] names).
#[allow(clippy::too_many_arguments)]
pub fn board_target(
    board: &Board,
    bm: &BoardModel,
    model_error: Option<ModelErrorPrior>,
    rom: &Rom,
    spec: &ModelSpec,
    (labels, pairs, mode_rows): (&Labels, &[PairRow], &[ModeRow]),
    masses: &BTreeMap<String, MassRow>,
    covariate_values: Option<CovariateColumn<'_>>,
    thickness_m: &BTreeMap<String, f64>,
    findings: &mut Findings,
) -> anyhow::Result<BoardTarget> {
    let (model, all, log_axes, nominal_mass_g) =
        (&bm.model, &bm.all, &bm.log_axes, bm.nominal_mass_g);
    let point_masses: Vec<usize> = log_axes
        .iter()
        .map(|(n, _)| rom.map.names.iter().position(|m| m == n).unwrap_or(0))
        .collect();
    let (predictor, all_pred) =
        predictors((model, rom), [labels, all], nominal_mass_g, &point_masses)?;
    // Units: every board with free-free pairs or a mass.
    // The enrichment's covariate per free-free measurement, as offsets from their mean.
    let (cov_offsets, covariate) = match bm.enrichment.as_ref().and_then(|e| match &e.effect {
        BoardEffect::Covariate {
            coefficient,
            scaled,
        } => Some((e, coefficient, scaled)),
        BoardEffect::PointMass { .. } => None,
    }) {
        Some((e, coefficient, scaled)) => {
            let column = spec.enrich_covariate.clone().ok_or_else(|| {
                anyhow!("--enrich {}: needs the covariate column", e.mechanism.id())
            })?;
            let free: BTreeSet<&str> = pairs
                .iter()
                .filter(|p| p.setup == "free")
                .map(|p| p.measurement_id.as_str())
                .collect();
            let (offsets, reference) = covariate_offsets(
                covariate_values.map_or(&[][..], |(v, _)| v),
                covariate_values.map_or("", |(_, s)| s),
                &column,
                &free,
                findings,
            )?;
            let scaled: Vec<usize> = scaled
                .iter()
                .map(|n| {
                    rom.map.names.iter().position(|m| m == n).ok_or_else(|| {
                        anyhow!(
                            "--enrich {}: the model has no parameter {n:?}",
                            e.mechanism.id()
                        )
                    })
                })
                .collect::<anyhow::Result<_>>()?;
            let cov = CovariateEffect {
                name: coefficient.clone(),
                covariate: column,
                reference,
                scaled,
            };
            (Some(offsets), Some(cov))
        }
        None => (None, None),
    };
    let (units, units_all, unit_names) = board_units(
        bm,
        rom,
        spec,
        (labels, pairs, mode_rows),
        masses,
        cov_offsets.as_ref(),
        findings,
    )?;
    let (updated, reference, param_names) = (&bm.updated, &bm.reference, &bm.param_names);
    let d = updated.len();
    let d0 = spec.params.len();
    let mut prior = PopulationPrior {
        mu_mean: vec![0.0; d0],
        mu_sd: spec
            .params
            .iter()
            .map(|p| match p.as_str() {
                names::G_Z => spec.prior_width.max(G_Z_PRIOR_WIDTH),
                _ => spec.prior_width,
            })
            .collect(),
        sigma_scale: vec![spec.sigma_scale; d0],
        // The board parameters' family; an enrichment's coordinate stays half-normal
        // (a coefficient probably common to all boards).
        sigma_prior: vec![spec.sigma_prior; d0],
        lkj_eta: spec.lkj_eta,
        lkj_log_norm: Default::default(),
    };
    if let Some(e) = &bm.enrichment {
        // The board's coordinate (a coefficient, or ln of an added mass): population
        // mean ~ the mechanism's prior, and a board-to-board sd of a fifth of that
        // prior's.
        prior.mu_mean.push(e.prior_mean);
        prior.mu_sd.push(e.prior_sd);
        prior.sigma_scale.push(0.2 * e.prior_sd);
    }
    let log: Vec<bool> = (0..d).map(|k| k >= d0).collect();
    // Moduli per unit mass scale, where the mass scale is updated too.
    let mass = param_names[..d0]
        .iter()
        .position(|p| p == crate::fem::params::names::MASS_SCALE);
    let per_mass = match (spec.board_coordinates, mass) {
        (BoardCoordinates::PerMass, Some(mass)) => Some(PerMass {
            mass,
            specific: (0..d)
                .map(|k| k < d0 && k != mass && param_names[k].ends_with("_pa"))
                .collect(),
        }),
        _ => None,
    };
    if spec.board_coordinates == BoardCoordinates::PerMass && per_mass.is_none() {
        findings.push(Finding::new(
            Severity::Info,
            "update.board_coordinates",
            format!("moduli per unit mass scale need {} among the updated parameters ({}): the population is formed in the parameters themselves", crate::fem::params::names::MASS_SCALE, param_names[..d0].join(", ")),
        ));
    }
    // A point mass beside the mass scale: the mass coordinate is the weighed total
    // (`TotalMass` says why). Not with the core thickness updated, whose share of the mass
    // the total would have to carry too: there the coordinates stay the parameters.
    let total_mass = match (&bm.enrichment, mass) {
        (Some(e), Some(mass)) if !param_names.iter().any(|p| p == names::CORE_THICKNESS) => {
            match &e.effect {
                BoardEffect::PointMass { reference_kg, .. } => Some(TotalMass {
                    mass,
                    point: d0,
                    ratio: 1e3 * reference_kg / nominal_mass_g,
                }),
                BoardEffect::Covariate { .. } => None,
            }
        }
        _ => None,
    };
    // The population's coordinates: names and the values x = 0 stands for.
    let (pop_names, pop_reference): (Vec<String>, Vec<f64>) = (0..d)
        .map(|k| match (&per_mass, &total_mass) {
            (Some(pm), _) if pm.is_specific(k) => (
                crate::fem::params::names::per_mass_scale(&param_names[k]),
                reference[k] / reference[pm.mass],
            ),
            (_, Some(t)) if t.mass == k => (TOTAL_MASS_SCALE.to_string(), reference[k]),
            _ => (param_names[k].clone(), reference[k]),
        })
        .unzip();
    let mut target = ModalTarget {
        predictor,
        compose: Compose::Boards {
            updated: updated.clone(),
            reference: reference.clone(),
            log: log.clone(),
            per_mass,
            total_mass,
        },
        prior,
        errors: ErrorModel {
            n_modes: labels.labels.len(),
            eps: spec.eps,
            delta: spec.delta,
            model_error_sd: None,
            discrepancy: None,
        },
        units,
        covariate: covariate.clone(),
        subspaces: vec![],
        coord_obs: thickness_obs(
            param_names,
            board.core.thickness_m,
            &unit_names,
            thickness_m,
            spec.rom_box,
            findings,
        ),
    };
    // Coordinates held by data of their own absorb none of the discrepancy: the mass scale
    // where a board was weighed, a thickness where the sheet measured it.
    let mut pinned: Vec<usize> = target
        .coord_obs
        .iter()
        .flatten()
        .map(|&(k, _, _)| k)
        .collect();
    if target.units.iter().any(|u| u.mass.is_some()) {
        pinned.extend(mass);
    }
    pinned.sort_unstable();
    pinned.dedup();
    target.errors.discrepancy = discrepancy_for(
        &target,
        (&[], None),
        spec.discrepancy_freq
            .unwrap_or(crate::bayes::discrepancy::FREE_FIDELITY_FREQ),
        (&pinned, "boards"),
        findings,
    )?;
    // The mesh's error is common to the boards: with the discrepancy inferred it is part of
    // d ([`ModelErrorPrior::common_to_boards`]); without one, each board's term.
    let model_error = match &target.errors.discrepancy {
        Some(_) => model_error.map(ModelErrorPrior::common_to_boards),
        None => model_error,
    };
    target.errors.model_error_sd = model_error
        .as_ref()
        .and_then(|m| m.board_sd(true))
        .map(<[f64]>::to_vec);
    Ok(BoardTarget {
        step: StepTarget {
            target,
            all_pred,
            units_all,
            unit_names,
        },
        model_error,
        covariate,
        pop_names,
        pop_reference,
        d,
        d0,
    })
}

/// Step 1's units: every board with free-free pairs or a mass, less the held-out ones; per
/// board its data for the likelihood, and for the residuals.
#[allow(clippy::type_complexity)]
fn board_units(
    bm: &BoardModel,
    rom: &Rom,
    spec: &ModelSpec,
    (labels, pairs, mode_rows): (&Labels, &[PairRow], &[ModeRow]),
    masses: &BTreeMap<String, MassRow>,
    cov_offsets: Option<&BTreeMap<String, f64>>,
    findings: &mut Findings,
) -> anyhow::Result<(Vec<UnitData>, Vec<(UnitData, Vec<ObsMeta>)>, Vec<String>)> {
    let (model, all) = (&bm.model, &bm.all);
    let wanted: BTreeSet<(String, i32)> = pairs
        .iter()
        .filter(|p| p.setup == "free")
        .map(|p| (p.measurement_id.clone(), p.mode))
        .collect();
    let shapes = shape_map(mode_rows, &wanted);
    let mut board_ids: BTreeSet<String> = pairs
        .iter()
        .filter(|p| p.setup == "free")
        .map(|p| p.board_id.clone())
        .collect();
    board_ids.extend(masses.keys().cloned());
    for b in &spec.hold_out_boards {
        if !board_ids.contains(b) {
            bail!(
            "--hold-out: board {b} has no paired free-free mode and no balance reading in this campaign (boards: {})",
            board_ids.iter().cloned().collect::<Vec<_>>().join(", ")
        );
        }
        findings.push(Finding::new(
        Severity::Info,
        "update.board_held_out",
        format!("board {b} is held out (--hold-out): its modes and mass are not used; the report compares its measurements with the new-board prediction"),
    ));
    }
    board_ids.retain(|b| !spec.hold_out_boards.contains(b));
    if board_ids.is_empty() {
        bail!("--hold-out leaves no board to update");
    }
    // Measurements held out of the updating: each must be a free-free measurement of a board
    // that is updated (a held-out board's are out already).
    for m in &spec.hold_out_measurements {
        let Some(p) = pairs
            .iter()
            .find(|p| p.setup == "free" && &p.measurement_id == m)
        else {
            let mut free: Vec<&str> = pairs
                .iter()
                .filter(|p| p.setup == "free")
                .map(|p| p.measurement_id.as_str())
                .collect();
            free.sort_unstable();
            free.dedup();
            bail!(
                "--hold-out-measurements: {m} is not a free-free measurement with a paired mode in this campaign (free-free measurements: {})",
                free.join(", ")
            );
        };
        if !board_ids.contains(&p.board_id) {
            bail!(
                "--hold-out-measurements: {m} is a measurement of board {}, which is held out as a whole (--hold-out)",
                p.board_id
            );
        }
        findings.push(
            Finding::new(
                Severity::Info,
                "update.measurement_held_out",
                format!("measurement {m} of board {} is held out (--hold-out-measurements): its modes are not used; the report compares them with the board's own prediction", p.board_id),
            )
            .measurement(m.clone()),
        );
    }
    // The balance informs the mass parameters: mass_scale, and an added mass.
    let mass_updated =
        spec.params.iter().any(|p| p == names::MASS_SCALE) || !bm.log_axes.is_empty();
    // One placement scatter per balance (readability), said once and used by every board.
    let placements = if mass_updated {
        balance_placements(masses, findings)
    } else {
        vec![]
    };
    let use_shapes = spec.delta.is_some();
    let mut units = vec![];
    let mut units_all = vec![];
    let mut unit_names = vec![];
    for b in &board_ids {
        let rows: Vec<&PairRow> = pairs
            .iter()
            .filter(|p| {
                p.setup == "free"
                    && &p.board_id == b
                    && !spec.hold_out_measurements.contains(&p.measurement_id)
            })
            .collect();
        let (mut data, (data_all, meta_all)) = unit_and_residual_data(
            &rows,
            labels,
            all,
            use_shapes,
            (model, rom, &shapes),
            cov_offsets,
            findings,
        )?;
        data.mass = match masses.get(b) {
            Some(m) if mass_updated => {
                let placement = placements
                    .iter()
                    .find(|(d, _)| *d == m.resolution_g)
                    .and_then(|(_, p)| *p);
                mass_obs(m, b, placement, findings)
            }
            Some(_) => None,
            None => {
                findings.push(Finding::new(
                Severity::Warning,
                "update.not_weighed",
                format!("board {b} was never weighed (no stable balance reading): its mass is informed by the population only"),
            ));
                None
            }
        };
        if data.freq.is_empty() && data.mass.is_none() {
            findings.push(Finding::new(
            Severity::Warning,
            "update.board_no_data",
            format!("board {b} has no paired free-free mode to update and no usable mass; left out of step 1"),
        ));
            continue;
        }
        if data.freq.is_empty() {
            findings.push(Finding::new(
                Severity::Warning,
                "update.board_no_modes",
                format!(
                    "board {b} has no paired free-free mode to update; only its mass informs it"
                ),
            ));
        }
        // Modes missing in some measurements: reported, the rest are used.
        let meas: BTreeSet<&str> = rows.iter().map(|p| p.measurement_id.as_str()).collect();
        for (m, l) in labels.labels.iter().enumerate() {
            let n = data.freq.iter().filter(|f| f.mode == m).count();
            if n > 0 && n < meas.len() {
                findings.push(Finding::new(
                Severity::Info,
                "update.mode_missing",
                format!("board {b}: mode {l:?} is paired in {n} of {} measurements; the others contribute no term for it", meas.len()),
            ));
            }
        }
        units.push(data);
        units_all.push((data_all, meta_all));
        unit_names.push(b.clone());
    }
    if units.is_empty() {
        bail!("no board has data for step 1 (no paired free-free mode and no mass)");
    }
    Ok((units, units_all, unit_names))
}

/// The ROM-box rule: a posterior that presses against the ROM's box is a [`RomBoxViolation`]
/// with the half-width that would hold it.
pub fn check_board_box(
    bm: &BoardModel,
    bt: &BoardTarget,
    results: &Results,
    spec: &ModelSpec,
) -> anyhow::Result<()> {
    let draws: Vec<&[Vec<f64>]> = particles_of(results)
        .into_iter()
        .map(|(_, _, p)| p.x.as_slice())
        .collect();
    board_box(bm, bt, &draws, "posterior", spec)
}

/// Draws of a reference's units checked before sampling.
const REFERENCE_BOX_DRAWS: usize = 1000;

/// The ROM-box rule applied to the reference before any sampling: when the reference's own
/// draws press against the box, the posterior it approximates will too, and a tempering on
/// this ROM would be spent only to learn that. The same [`RomBoxViolation`], from
/// [`REFERENCE_BOX_DRAWS`] draws of the units (a fixed stream: the same reference gives the
/// same verdict) with the reference's `inflation` of its sds taken out: the inflation is a
/// deliberate over-spread for the tempering, not where the posterior lies.
///
/// It may only widen the box, never stop the stage: a violation no box up to the widest would
/// hold passes (Ok), and the posterior, checked after sampling, decides. The reference of a
/// board without modes is its population's predictive, whose tails over a population scale
/// that few boards inform can reach past any box the posterior's draws stay inside.
pub fn check_board_reference_box(
    bm: &BoardModel,
    bt: &BoardTarget,
    q: &crate::bayes::reference::GaussianReference,
    inflation: f64,
    spec: &ModelSpec,
) -> anyhow::Result<()> {
    use rand::SeedableRng;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(crate::bayes::smc::stream_key(&[0xB0C5]));
    let units: Vec<Vec<Vec<f64>>> = (0..REFERENCE_BOX_DRAWS)
        .map(|_| {
            q.units
                .iter()
                .map(|u| {
                    let x = u.sample(&mut rng);
                    x.iter()
                        .zip(&u.mean)
                        .map(|(x, m)| m + (x - m) / inflation)
                        .collect()
                })
                .collect()
        })
        .collect();
    let draws: Vec<&[Vec<f64>]> = units.iter().map(Vec::as_slice).collect();
    match board_box(bm, bt, &draws, "reference", spec) {
        Err(e) => match e.downcast_ref::<RomBoxViolation>() {
            Some(v) if crate::update::rom_box::widened(spec, v).is_none() => Ok(()),
            _ => Err(e),
        },
        ok => ok,
    }
}

/// [`check_board_box`] over `draws` (per draw, every unit's coordinates) of the `what`.
fn board_box(
    bm: &BoardModel,
    bt: &BoardTarget,
    draws: &[&[Vec<f64>]],
    what: &'static str,
    spec: &ModelSpec,
) -> anyhow::Result<()> {
    // The ROM's logarithmic axes by parameter: an enrichment's coordinate is its logarithm
    // already (k ≥ d0), a board parameter's (the shear modulus) is relative.
    let axes = crate::update::rom_box::rom_log_axes(&bm.model.map, &bm.log_axes, spec);
    let log_box = |k: usize| {
        axes.iter()
            .find(|(n, _)| *n == bm.param_names[k])
            .map(|(_, w)| *w)
    };
    // A board informed by its mass alone (no paired mode) never evaluates the ROM: its
    // moduli range as the population's, and the ROM's box says nothing of its posterior.
    let evaluated = |b: usize| {
        let u = &bt.step.target.units[b];
        !u.freq.is_empty() || !u.shapes.is_empty()
    };
    let violations = box_violations(
        draws,
        what,
        &bt.step.unit_names,
        &bm.param_names,
        |x| bt.step.target.compose.relative_params(x),
        |k, x| match log_box(k) {
            Some(w) if k >= bt.d0 => x.abs() <= w,
            Some(w) => (1.0 + x).ln().abs() <= w,
            None => x.abs() <= spec.rom_box,
        },
        evaluated,
        spec.box_tolerance,
    );
    if !violations.is_empty() {
        // The half-width that holds every sampled value of the relative coordinates, with
        // a margin, to the next 5 %; the same in ln for the shear modulus's axis.
        let g_z = bm
            .param_names
            .iter()
            .position(|n| n == crate::fem::params::names::G_Z)
            .filter(|&k| k < bt.d0);
        let (mut reach, mut reach_g_z) = (0.0f64, 0.0f64);
        for units in draws {
            for (_, x) in units.iter().enumerate().filter(|(b, _)| evaluated(*b)) {
                let x = bt.step.target.compose.relative_params(x);
                for (k, v) in x.iter().enumerate() {
                    // A wider linear box does not hold a logarithmic axis.
                    if log_box(k).is_none() {
                        reach = reach.max(v.abs());
                    } else if Some(k) == g_z {
                        // A modulus at or below 0 is beyond any box.
                        let l = if *v > -1.0 {
                            (1.0 + v).ln().abs()
                        } else {
                            f64::INFINITY
                        };
                        reach_g_z = reach_g_z.max(l);
                    }
                }
            }
        }
        let needed_g_z_log_box = g_z
            .and_then(log_box)
            .filter(|w| reach_g_z > *w)
            .map(|_| crate::update::rom_box::holding(reach_g_z));
        return Err(RomBoxViolation {
        by: what,
        message: format!(
            "the {what} presses against the ROM's ±{:.0} % box (relative to the board file's nominal values):\n  {}\nThe ROM is not verified there. Re-centre the model: put values near the medians above in the board file (--board) and run again, or leave an uninformed parameter out (--params).",
            100.0 * spec.rom_box,
            violations.join("\n  ")
        ),
        needed_half_width: crate::update::rom_box::holding(reach),
        needed_g_z_log_box,
    }
    .into());
    }
    Ok(())
}

/// Step 1's draws as the tables' rows: the population, the boards, and the summary. The
/// summary's physical quantiles are those of the draws less what the data cannot inform and
/// every board shares, one draw of each per particle from streams keyed by `seed`: the
/// model-form discrepancy's part the parameters absorb (`Discrepancy::confounded_shift`),
/// with each board's deviation from the population mean carried to the sensitivities at the
/// centre that leaves ([`carried_deviation`]), and, where boards were weighed, the balance's
/// common bias of sd `balance_bias_rel` ([`crate::update::problem::balance_bias_draw`]),
/// which divides every mass scale (and with it the moduli of a per-mass population) by
/// 1 + β. None where neither applies.
pub fn board_tables(
    bm: &BoardModel,
    bt: &BoardTarget,
    results: &Results,
    labels: &Labels,
    (runs, seed, balance_bias_rel): (usize, u64, f64),
) -> BoardTables {
    let (pcols, pop_of) = population_columns(
        &bt.step.target,
        &bt.pop_names,
        &bt.pop_reference,
        &labels.labels,
    );
    let mut pop = DrawTable::new(&pcols);
    let mut bcols: Vec<(String, String)> = bm
        .param_names
        .iter()
        .map(|p| (p.clone(), String::new()))
        .collect();
    bcols.push(("mass_g".into(), "g".into()));
    // A board enrichment's coefficient per board (step 2 carries it with the draw).
    if let Some(c) = &bt.covariate {
        bcols.push((c.name.clone(), format!("1/(unit of {})", c.covariate)));
    }
    let mut boards = DrawTable::new(&bcols);
    let mut pop_phys = DrawTable::new(&pcols);
    let mut boards_phys = DrawTable::new(&bcols);
    let target = &bt.step.target;
    let disc = target.errors.discrepancy.as_ref();
    // The balance's bias applies to the mass scale's (relative) coordinate where a board was
    // weighed; a point mass weighed with the board is left as fitted (beside one, the
    // coordinate is the weighed total, `TotalMass`, and the board's own mass takes it all).
    let mass_coord = bm
        .param_names
        .iter()
        .position(|p| p == crate::fem::params::names::MASS_SCALE)
        .filter(|_| balance_bias_rel > 0.0 && target.units.iter().any(|u| u.mass.is_some()));
    let physical = disc.is_some() || mass_coord.is_some();
    let unbias = |x: &mut [f64], beta: f64| {
        if let Some(k) = mass_coord {
            x[k] = (1.0 + x[k]) / (1.0 + beta) - 1.0;
        }
    };
    let board_row = |p: &Particle<Terms>, b: usize, x: &[f64]| {
        let v = target.values(&p.aux, b, x);
        let mut row: Vec<f64> = bm.updated.iter().map(|&k| v[k]).collect();
        row.push(target.predictor.mass_g(&v));
        if bt.covariate.is_some() {
            row.push(x[bt.d]);
        }
        row
    };
    for (r, i, p) in particles_of(results) {
        pop.push(r, i, None, &pop_of(&p.g));
        for (b, name) in bt.step.unit_names.iter().enumerate() {
            boards.push(r, i, Some(name), &board_row(p, b, &p.x[b]));
        }
        if !physical {
            continue;
        }
        // The population mean μ leads g, in the units' coordinates; both shifts are common to
        // every unit and to μ, so the spreads do not move (β's scaling of the mass scale's
        // spread, 3e-4 of it, is left out).
        let a = confounded_draw(target, &p.g, seed, (r, i));
        let beta = balance_bias_draw(balance_bias_rel, seed, (r, i));
        let mut g = p.g.clone();
        g.iter_mut().zip(&a).for_each(|(v, s)| *v -= s);
        let carry = disc.and_then(|disc| physical_sensitivities(target, p, &a, disc));
        unbias(&mut g, beta);
        pop_phys.push(r, i, None, &pop_of(&g));
        for (b, name) in bt.step.unit_names.iter().enumerate() {
            // Each board's deviation from the population mean, carried to the physical
            // centre's sensitivities ([`carried_deviation`]); without them, shifted alone.
            let carried = carry.as_ref().and_then(|(sf, sp, absorbing)| {
                let n = a.len();
                let dev: Vec<f64> = (0..n).map(|k| p.x[b][k] - p.g[k]).collect();
                let c = carried_deviation((sf, sp), target.errors.n_modes, absorbing, &dev)?;
                let mut x = p.x[b].clone();
                (0..n).for_each(|k| x[k] = p.g[k] - a[k] + c[k]);
                Some(x)
            });
            let mut x = carried.unwrap_or_else(|| less_confounded(&p.x[b], &a));
            unbias(&mut x, beta);
            boards_phys.push(r, i, Some(name), &board_row(p, b, &x));
        }
    }
    let mut summary = pop.summarize(runs, true);
    summary.extend(boards.summarize(runs, true));
    if physical {
        let mut phys = pop_phys.summarize(runs, true);
        phys.extend(boards_phys.summarize(runs, true));
        for (row, ph) in summary.iter_mut().zip(phys) {
            debug_assert!(row.parameter == ph.parameter && row.board_id == ph.board_id);
            row.physical = Some(ph.s);
        }
    }
    BoardTables {
        population: pop,
        boards,
        summary,
        physical: physical.then_some(boards_phys),
    }
}

/// Step 1's draws as tables ([`board_tables`]).
pub struct BoardTables {
    pub population: DrawTable,
    /// The fitted draws, the ones the predictions use.
    pub boards: DrawTable,
    pub summary: Vec<SummaryRow>,
    /// The boards' physical draws (the summary's physical quantiles are theirs), where
    /// there are any.
    pub physical: Option<DrawTable>,
}

/// The relative eigenvalue sensitivities of unit 0's model at the particle's population mean
/// (the fitted centre) and at that mean less the discrepancy's absorbed part `a` (the
/// physical centre), and the coordinates that absorb (`Discrepancy::absorbing`); `None`
/// without an absorbed part or where the model is undefined at either.
fn physical_sensitivities(
    target: &ModalTarget,
    p: &Particle<Terms>,
    a: &[f64],
    disc: &crate::bayes::discrepancy::Discrepancy,
) -> Option<(Vec<f64>, Vec<f64>, Vec<usize>)> {
    let n = a.len();
    if n == 0 || n > p.g.len() {
        return None;
    }
    let nm = target.errors.n_modes;
    let lambda = |x: &[f64]| crate::update::problem::unit0_eigenvalues(target, &p.aux, x);
    let centre = &p.g[..n];
    let physical: Vec<f64> = centre.iter().zip(a).map(|(c, a)| c - a).collect();
    let h = crate::update::problem::SENSITIVITY_STEP;
    let sf = crate::bayes::discrepancy::sensitivities(lambda, centre, nm, h)?;
    let sp = crate::bayes::discrepancy::sensitivities(lambda, &physical, nm, h)?;
    Some((sf, sp, disc.absorbing()))
}

/// Step 1's evidence.json.
pub fn board_evidence(
    bm: &BoardModel,
    bt: &BoardTarget,
    results: &Results,
    labels: &Labels,
    shape_weights: &[crate::bayes::shape_weight::ShapeWeight],
) -> anyhow::Result<serde_json::Value> {
    let log_z: Vec<f64> = results.iter().map(|r| r.log_evidence).collect();
    let mut ev = evidence_json(&log_z, "boards (step 1)");
    match (&bm.enrichment, &bt.covariate) {
        (Some(e), Some(c)) => {
            if let BoardEffect::Covariate {
                coefficient,
                scaled,
            } = &e.effect
            {
                ev["enrichment"] = serde_json::json!({
                    "mechanism": e.mechanism,
                    "coefficient": coefficient,
                    "scaled": scaled,
                    "covariate": c.covariate,
                    "covariate_reference": c.reference,
                    "prior_mean": e.prior_mean,
                    "prior_sd": e.prior_sd,
                });
            }
        }
        (Some(e), None) => {
            ev["enrichment"] = serde_json::to_value(e)?;
        }
        _ => {}
    }
    ev["model_error"] = serde_json::to_value(&bt.model_error)?;
    ev["shape_weights"] = serde_json::to_value(shape_weights)?;
    ev["discrepancy"] = discrepancy_json(&bt.step.target, &labels.labels);
    Ok(ev)
}

/// The placement scatter of each balance (readability) of `masses`, and a finding per
/// balance saying what each board's mass term allows for the balance's error between
/// placements: the campaign's own re-weighings, or the OIML bound.
fn balance_placements(
    masses: &BTreeMap<String, MassRow>,
    findings: &mut Findings,
) -> Vec<(f64, Option<PlacementScatter>)> {
    use crate::update::problem::{MIN_PLACEMENT_DF, MPE_READABILITY_STEPS};
    let mut out: Vec<(f64, Option<PlacementScatter>)> = vec![];
    for m in masses.values() {
        let d = m.resolution_g;
        if out.iter().any(|(seen, _)| *seen == d) {
            continue;
        }
        let placement = placement_scatter(masses.values(), d);
        out.push((d, placement));
        let message = match placement {
            Some(p) => format!(
                "balance of readability {d} g: {} boards weighed on more than one day give one day's mean an sd of {:.3} mg ({} degrees of freedom); each board's mass term allows that for placing it on the pan, over its number of days, not the OIML allowance of ±{MPE_READABILITY_STEPS} d",
                p.n_boards,
                1e3 * p.var_g2.sqrt(),
                p.df
            ),
            None => format!(
                "balance of readability {d} g: too few boards weighed again on another day to measure what placing a board on the pan errs (fewer than {MIN_PLACEMENT_DF} degrees of freedom); each board's mass term allows the OIML R 76-1 class I bound of ±{MPE_READABILITY_STEPS} d. Weigh each board on two days to have the campaign measure it"
            ),
        };
        findings.push(Finding::new(
            Severity::Info,
            "update.balance_placement",
            message,
        ));
    }
    out
}

#[cfg(test)]
mod tests {
    /// The default parameters follow the board: a thin plate's four, and a shear-deformable
    /// plate's transverse shear modulus beside them.
    #[test]
    fn the_default_parameters_add_the_shear_modulus_of_a_shear_deformable_board() {
        let mut board = crate::fem::tests::helpers::thin_board();
        assert_eq!(
            super::default_params(&board),
            ["e_x_pa", "e_y_pa", "g_xy_pa", "mass_scale"]
        );
        board.core.g_xz_pa = Some(3.0e9);
        board.core.g_yz_pa = Some(3.0e9);
        assert_eq!(
            super::default_params(&board),
            ["e_x_pa", "e_y_pa", "g_xy_pa", "mass_scale", "g_z_pa"]
        );
    }
}

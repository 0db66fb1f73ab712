//! Step 2 (joints) as pure functions: the bolted models with the enrichment and the step-1
//! boards, the centre's labels and new modes, the cut posterior's target and groups, the checks
//! of the posterior against the ROM's box and the full model, the tables' rows and the evidence.
//! `stage::update` reads the inputs, calls these in order and writes the outputs.

use crate::bayes::discrepancy::CutScale;
use crate::bayes::population::PopulationPrior;
use crate::bayes::smc;
use crate::bayes::target::{Compose, ErrorModel, ErrorPrior, JointsCovariate, ModalTarget};
use crate::fem::params::names;
use crate::fem::{Board, FeModel, Params, Rom, Setup};
use crate::findings::{Finding, Findings, Severity};
use crate::modal::rows::{ModeRow, PairRow};
use crate::update::enrichment::{
    is_board_mechanism, joint_enrichment, JointContext, JointEnrichment, Mechanism,
};
use crate::update::new_modes::{match_modes, pair_new_modes, NewMode};
use crate::update::posterior::{
    confounded_draw, confounded_draw_at, discrepancy_columns, discrepancy_json, discrepancy_values,
    evidence_json, less_confounded, DrawTable, SummaryRow,
};
use crate::update::problem::CovariateColumn;
use crate::update::problem::{
    all_labels, covariate_offsets, identified_modes, match_points, modes_needed, predictors,
    shape_map, unit_and_residual_data, Labels, ModelSpec, StepTarget,
};
use crate::update::rom_box::{holding, rom_posterior_check, MAX_G_Z_LOG_BOX};
use crate::update::sampler::{box_violations, particles_of, Results, SamplerParams};
use crate::update::step1::{step1_point_mass, Step1, Step1PointMass};
use anyhow::{anyhow, bail};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

/// The bolted models of step 2 and what they are evaluated against: the enrichment, the
/// enriched model (its nominal moved to the ROM's centre by [`centred`]), the step-1 boards'
/// parameters and mean, the reference shapes of the baseline at the boards' mean.
pub struct JointModels {
    pub board_mech: Option<Mechanism>,
    pub enr: JointEnrichment,
    pub model: FeModel,
    pub point_mass: Option<Step1PointMass>,
    pub nominal: Params,
    pub board_params: Vec<usize>,
    pub reference: Vec<(usize, f64)>,
    pub coords: Vec<Vec<(usize, f64)>>,
    pub board_mean: BTreeMap<String, f64>,
    pub points: Vec<[f64; 2]>,
    pub all: Labels,
    pub n_track: usize,
    pub w_all: faer::Mat<f64>,
    pub w_labels: faer::Mat<f64>,
    pub p_base: Params,
    pub spans: Vec<f64>,
}

impl JointModels {
    /// `p` with the step-1 boards' posterior means.
    pub fn with_board_mean(&self, mut p: Params) -> Params {
        for (name, v) in &self.board_mean {
            if let Ok(i) = p.position(name) {
                p.values[i] = *v;
            }
        }
        p
    }

    /// The reference shapes of the model modes `idx` at the match points.
    pub fn pick(&self, idx: &[usize]) -> faer::Mat<f64> {
        faer::Mat::from_fn(self.points.len(), idx.len(), |i, j| self.w_all[(i, idx[j])])
    }
}

/// The bolted models of step 2 (see [`JointModels`]); `step1_source` names the step-1 table in
/// messages; `step1_enrichment` is a board mechanism's step-1 evidence (its `enrichment`), or
/// null.
#[allow(clippy::too_many_arguments)]
pub fn joint_models(
    board: &Board,
    spec: &ModelSpec,
    labels: &Labels,
    pairs: &[PairRow],
    step1: &Step1,
    step1_source: &str,
    step1_enrichment: &serde_json::Value,
    findings: &mut Findings,
) -> anyhow::Result<JointModels> {
    let bolted_rows: Vec<&PairRow> = pairs.iter().filter(|p| p.setup == "bolted").collect();
    let band_top_hz = bolted_rows.iter().map(|p| p.freq_hz).fold(0.0, f64::max);
    // A board mechanism (its step-1 refit is `boards_dir`) keeps the baseline joints.
    let board_mech = spec
        .enrich
        .filter(|m| crate::update::enrichment::is_board_mechanism(*m));
    let enr = joint_enrichment(
        board,
        spec.enrich.filter(|_| board_mech.is_none()),
        spec.enrich_joint,
        JointContext {
            band_top_hz,
            k_con_prior_sd: spec.prior_width,
        },
    )
    .map_err(|e| anyhow!("update joints --enrich: {e}"))?;
    // Where step 1 updated the core thickness, each board's draw carries it.
    let model_opts = crate::fem::ModelOptions {
        core_thickness: step1.params.iter().any(|p| p == names::CORE_THICKNESS),
    };
    let mut model = FeModel::build_with(
        board,
        Setup::Bolted(enr.joint_model.clone()),
        board.mesh_for(&Setup::bolted()),
        model_opts,
    )?;
    // The board mechanism's step-1 enrichment (its evidence.json), and a point mass it
    // added to the boards: the same point mass in the bolted model, its value from each
    // board's step-1 draw like every board parameter.
    let point_mass = step1_point_mass(step1_enrichment, step1, step1_source)?;
    // Without a joint enrichment the baseline is the model itself: a copy, not a second
    // assembly (about a second of step 2 on the realistic board).
    let mut baseline = if model.setup == Setup::bolted() {
        model.clone()
    } else {
        FeModel::build_with(
            board,
            Setup::bolted(),
            board.mesh_for(&Setup::bolted()),
            model_opts,
        )?
    };
    if let Some(pm) = &point_mass {
        for m in [&mut model, &mut baseline] {
            m.add_point_mass_param(&pm.parameter, pm.x_m, pm.y_m, pm.mean_kg)
                .map_err(|e| anyhow!("{step1_source}: the step-1 added mass: {e}"))?;
        }
    }
    let nominal = model.nominal_params();
    let mut board_params = vec![];
    for p in &step1.params {
        board_params.push(nominal.position(p).map_err(|_| {
            anyhow!(
                "{}: step-1 parameter {p:?} is not a parameter of the bolted model ({:?})",
                step1_source,
                nominal.names
            )
        })?);
    }
    let reference: Vec<(usize, f64)> = enr
        .reference
        .iter()
        .map(|(n, v)| Ok((nominal.position(n)?, *v)))
        .collect::<Result<_, crate::fem::FemError>>()?;
    let coords: Vec<Vec<(usize, f64)>> = enr
        .coordinates
        .iter()
        .map(|c| {
            c.acts_on
                .iter()
                .map(|(n, a)| Ok((nominal.position(n)?, *a)))
                .collect::<Result<Vec<_>, crate::fem::FemError>>()
        })
        .collect::<Result<_, _>>()?;
    // The boards' posterior means (for the joint's centre).
    let d1 = step1.block();
    let nd = step1.draws.len() as f64;
    let mut board_mean: BTreeMap<String, f64> = BTreeMap::new();
    for (k, p) in step1.params.iter().enumerate() {
        let m = step1
            .draws
            .iter()
            .map(|(_, v)| {
                (0..step1.board_ids.len())
                    .map(|b| v[b * d1 + k])
                    .sum::<f64>()
            })
            .sum::<f64>()
            / (nd * step1.board_ids.len() as f64);
        board_mean.insert(p.clone(), m);
    }
    let with_board_mean = |mut p: crate::fem::Params| {
        for (name, v) in &board_mean {
            if let Ok(i) = p.position(name) {
                p.values[i] = *v;
            }
        }
        p
    };
    // Reference shapes: the paired model modes of the baseline at the boards' mean.
    let points = match_points(board);
    let all = all_labels(pairs, "bolted", 40, findings);
    let n_ref = modes_needed(labels, &all);
    let extra_modes = if enr.joint_model.has_fixture() { 3 } else { 2 };
    let n_track = n_ref + extra_modes;
    let base_modes = baseline.modes(&with_board_mean(baseline.nominal_params()), n_ref)?;
    let w_all = baseline.w_at(&base_modes, &points)?;
    let pick =
        |idx: &[usize]| faer::Mat::from_fn(points.len(), idx.len(), |i, j| w_all[(i, idx[j])]);
    let w_labels = pick(&labels.model_mode);
    let mut p_base = with_board_mean(nominal.clone());
    for &(i, v) in &reference {
        p_base.values[i] = v;
    }
    let spans: Vec<f64> = enr
        .coordinates
        .iter()
        .enumerate()
        .map(|(k, c)| {
            if k == 0 {
                spec.prior_width.max(1.0) * 3.0
            } else {
                3.0 * c.prior_sd
            }
        })
        .collect();
    Ok(JointModels {
        board_mech,
        enr,
        model,
        point_mass,
        nominal,
        board_params,
        reference,
        coords,
        board_mean,
        points,
        all,
        n_track,
        w_all,
        w_labels,
        p_base,
        spans,
    })
}

/// The centre fitted to the median bolted frequencies ([`crate::update::centre::fit_centre`]).
/// All coordinates are fitted (k_con trades off against k_rot, one joint's ratio against the
/// common k_con); an enrichment's own coordinates are then kept within half their ROM
/// half-width of their prior's centre and k_con refitted with them held there, so that the
/// prior's centre stays inside the ROM's box. Every joint's contrast
/// (`joint_stiffness_per_joint` with no joint named) stays at 0: the median frequencies fix no
/// common direction of it.
pub fn fit_joint_centre_of(
    jm: &JointModels,
    labels: &Labels,
    bolted_rows: &[&PairRow],
) -> anyhow::Result<crate::update::centre::CentreFit> {
    let n_fit = if jm.enr.every_joint() {
        1
    } else {
        jm.coords.len()
    };
    crate::update::centre::fit_centre(
        &jm.model,
        &jm.p_base,
        &jm.coords,
        &jm.spans,
        &jm.enr,
        n_fit,
        (labels, bolted_rows),
        (&jm.w_labels, &jm.points),
        jm.n_track,
    )
}

/// What the centre decides: the joint stiffness there, the labels carried to the enriched
/// model's modes, the new modes paired, the ROM's logarithmic axes and point masses.
pub struct Centred {
    pub k_centre: f64,
    pub labels: Labels,
    pub all: Labels,
    pub new_modes: Vec<NewMode>,
    /// Pairs of the new modes that join the updating (`--enrich-new-modes`).
    pub new_rows: Vec<PairRow>,
    pub need: usize,
    pub log_axes: Vec<(String, f64)>,
    pub point_masses: Vec<usize>,
}

/// Moves the model's nominal to the ROM's centre `centre` and carries the labels there.
pub fn centred(
    jm: &mut JointModels,
    centre: &[f64],
    labels: &Labels,
    spec: &ModelSpec,
    mode_rows: &[ModeRow],
    bolted_rows: &[&PairRow],
    findings: &mut Findings,
) -> anyhow::Result<Centred> {
    // The ROM's centre: the reference joint values moved to the fitted coordinates (the
    // board parameters stay at the board file's nominal values).
    let (nominal, reference, coords, model) =
        (&jm.nominal, &jm.reference, &jm.coords, &mut jm.model);
    let mut rom_centre = nominal.clone();
    for &(i, v) in reference {
        rom_centre.values[i] = v;
    }
    for (k, acts) in coords.iter().enumerate() {
        for &(i, a) in acts {
            rom_centre.values[i] *= (a * centre[k]).exp();
        }
    }
    model.map.nominal = rom_centre.values.clone();
    let k_centre = rom_centre
        .get(names::K_CON)
        .or_else(|_| rom_centre.get(&names::k_con_joint(1)))?;
    // Labels carried over to the (enriched) model's modes at the centre by shape.
    let model = &jm.model;
    let centre_p = jm.with_board_mean(model.nominal_params());
    let (label_modes, _) = match_modes(model, &centre_p, jm.n_track, &jm.w_labels, &jm.points)?;
    let (all_modes, _) = match_modes(
        model,
        &centre_p,
        jm.n_track,
        &jm.pick(&jm.all.model_mode),
        &jm.points,
    )?;
    let mut labels = Labels {
        labels: labels.labels.clone(),
        model_mode: label_modes,
    };
    let mut all = Labels {
        labels: jm.all.labels.clone(),
        model_mode: all_modes,
    };
    // Modes the enrichment adds (a fixture's own) that the campaign identified and pair
    // left unpaired: recorded in evidence.json (`new_modes`), and with
    // --enrich-new-modes updated as labels of their own.
    let new_modes = match spec.enrich.filter(|m| !is_board_mechanism(*m)) {
        Some(mech) => {
            let taken: Vec<usize> = labels
                .model_mode
                .iter()
                .chain(&all.model_mode)
                .copied()
                .collect();
            let paired: BTreeSet<(String, i32)> = bolted_rows
                .iter()
                .map(|p| (p.measurement_id.clone(), p.mode))
                .collect();
            pair_new_modes(
                model,
                &centre_p,
                jm.n_track,
                &taken,
                &identified_modes(mode_rows, "bolted"),
                &paired,
                mech.id(),
            )?
        }
        None => vec![],
    };
    let mut new_rows = vec![];
    for nm in &new_modes {
        let used = spec.enrich_new_modes;
        findings.push(Finding::new(
            Severity::Info,
            "update.new_mode_paired",
            format!(
                "the enriched model's mode {} at {:.1} Hz (no baseline label) pairs with {} of {} bolted measurements' modes that pair left unpaired (median {:.1} Hz); {}",
                nm.model_mode + 1,
                nm.model_freq_hz,
                nm.rows.len(),
                nm.n_measurements,
                nm.median_freq_hz(),
                if used {
                    format!("updated as {:?}", nm.label)
                } else {
                    "not updated (--enrich-new-modes updates it)".to_string()
                }
            ),
        ));
        if used {
            labels.labels.push(nm.label.clone());
            labels.model_mode.push(nm.model_mode);
            all.labels.push(nm.label.clone());
            all.model_mode.push(nm.model_mode);
            new_rows.extend(nm.rows.iter().cloned());
        }
    }
    let need = modes_needed(&labels, &all);
    let (enr, coords, nominal) = (&jm.enr, &jm.coords, &jm.nominal);
    // ROM box: ±rom_box, and along every parameter an extra coordinate moves, the sum of
    // the ln half-widths of the coordinates acting on it.
    let mut log_axes: Vec<(String, f64)> = vec![];
    for (k, c) in enr.coordinates.iter().enumerate() {
        if c.log_box.is_none() {
            continue;
        }
        for &(i, _) in &coords[k] {
            let w: f64 = enr
                .coordinates
                .iter()
                .zip(coords)
                .filter(|(_, acts)| acts.iter().any(|(j, _)| *j == i))
                .map(|(cc, acts)| {
                    let a = acts
                        .iter()
                        .find(|(j, _)| *j == i)
                        .map_or(1.0, |(_, a)| a.abs());
                    a * cc.log_box.unwrap_or((1.0 + spec.rom_box).ln())
                })
                .sum();
            if !log_axes.iter().any(|(n, _)| *n == nominal.names[i]) {
                log_axes.push((nominal.names[i].clone(), w));
            }
        }
    }
    // The added mass varies between boards and draws by more than a ±20 % box around its
    // step-1 mean need cover: a logarithmic axis of e^±0.7 (half to twice the mean).
    let mut point_masses = vec![];
    if let Some(pm) = &jm.point_mass {
        log_axes.push((pm.parameter.clone(), 0.7));
        point_masses.push(nominal.position(&pm.parameter)?);
    }
    Ok(Centred {
        k_centre,
        labels,
        all,
        new_modes,
        new_rows,
        need,
        log_axes,
        point_masses,
    })
}

/// `spec` with the ROM's transverse-shear-modulus axis wide enough to hold every step-1 draw
/// of it the cut posterior carries (step 1 widens its own axis when its posterior needs it,
/// `update::rom_box::widened`), relative to `nominal`'s value (the board file's, where step 2
/// centres its ROM), with step 1's margin, up to [`MAX_G_Z_LOG_BOX`]; `spec` unchanged where
/// the default axis holds them or the model has no such parameter.
pub fn holding_step1_g_z(spec: &ModelSpec, step1: &Step1, nominal: &Params) -> ModelSpec {
    let g_z = crate::fem::params::names::G_Z;
    let (Some(k), Ok(g0)) = (step1.params.iter().position(|p| p == g_z), nominal.get(g_z)) else {
        return spec.clone();
    };
    let d1 = step1.block();
    let reach = step1
        .draws
        .iter()
        .flat_map(|(_, v)| (0..step1.board_ids.len()).map(move |b| v[b * d1 + k]))
        .map(|g| {
            if g > 0.0 {
                (g / g0).ln().abs()
            } else {
                f64::INFINITY
            }
        })
        .fold(0.0, f64::max);
    let held = spec.g_z_log_box.unwrap_or(crate::fem::rom::G_Z_LOG_BOX);
    if reach <= held {
        return spec.clone();
    }
    ModelSpec {
        g_z_log_box: Some(holding(reach).min(MAX_G_Z_LOG_BOX)),
        ..spec.clone()
    }
}

/// The cut posterior's target and its groups: every unit a bolted measurement, every group of
/// `group` particles carrying one step-1 draw.
pub struct JointTarget {
    pub step: StepTarget,
    pub unit_boards: Vec<String>,
    pub group: usize,
    /// The sampler with the particles rounded to whole groups.
    pub sampler: SamplerParams,
    pub aux: Vec<Vec<Arc<Vec<f64>>>>,
    pub aux_index: Vec<Vec<usize>>,
}

/// Step 2's target; `covariate`: a temperature mechanism's column per measurement (file
/// order) with its source, for messages.
#[allow(clippy::too_many_arguments)]
pub fn joint_target(
    jm: &JointModels,
    c: &Centred,
    rom: &Rom,
    bolted_rows: &[&PairRow],
    mode_rows: &[ModeRow],
    (step1, step1_source): (&Step1, &str),
    (step1_enrichment, step1_enrichment_source): (&serde_json::Value, &str),
    covariate: Option<CovariateColumn<'_>>,
    spec: &ModelSpec,
    sampler: &SamplerParams,
    findings: &mut Findings,
) -> anyhow::Result<JointTarget> {
    let (model, labels, all) = (&jm.model, &c.labels, &c.all);
    let point_masses = c.point_masses.clone();
    let mut p_board = model.nominal_params();
    for &i in &point_masses {
        p_board.values[i] = 0.0;
    }
    let nominal_mass_g = model.total_mass_kg(&p_board)? * 1e3;
    let (predictor, all_pred) =
        predictors((model, rom), [labels, all], nominal_mass_g, &point_masses)?;
    let wanted: BTreeSet<(String, i32)> = bolted_rows
        .iter()
        .map(|p| (p.measurement_id.clone(), p.mode))
        .collect();
    let shapes = shape_map(mode_rows, &wanted);
    let use_shapes = spec.delta.is_some();
    let measurement_ids: BTreeSet<String> = bolted_rows
        .iter()
        .map(|p| p.measurement_id.clone())
        .collect();
    let mut units = vec![];
    let mut units_all = vec![];
    let mut unit_names = vec![];
    let mut unit_boards = vec![];
    let mut unit_board_idx = vec![];
    for m in &measurement_ids {
        let rows: Vec<&PairRow> = bolted_rows
            .iter()
            .copied()
            .filter(|p| &p.measurement_id == m)
            .collect();
        let bid = rows[0].board_id.clone();
        let Some(bi) = step1.board_ids.iter().position(|b| *b == bid) else {
            findings.push(
                Finding::new(
                    Severity::Warning,
                    "update.no_step1_posterior",
                    format!("bolted measurement of board {bid}, which has no step-1 posterior in {step1_source}; left out of step 2"),
                )
                .measurement(m.clone()),
            );
            continue;
        };
        let (data, (data_all, meta_all)) = unit_and_residual_data(
            &rows,
            labels,
            all,
            use_shapes,
            (model, rom, &shapes),
            None,
            findings,
        )?;
        if data.freq.is_empty() {
            findings.push(
                Finding::new(
                    Severity::Warning,
                    "update.measurement_no_modes",
                    format!("bolted measurement of board {bid} has no paired mode to update; left out of step 2"),
                )
                .measurement(m.clone()),
            );
            continue;
        }
        units.push(data);
        units_all.push((data_all, meta_all));
        unit_names.push(m.clone());
        unit_boards.push(bid);
        unit_board_idx.push(bi);
    }
    // The board mechanism's covariate per bolted measurement, relative to step 1's
    // reference (its evidence.json), and where each board's coefficient sits in aux.
    let joints_cov = match jm
        .board_mech
        .filter(|m| *m == Mechanism::TemperatureStiffness)
    {
        None => None,
        Some(m) => {
            let reference = step1_enrichment["covariate_reference"].as_f64().ok_or_else(|| {
                anyhow!("{step1_enrichment_source}: no enrichment.covariate_reference: --boards must be the step-1 refit of {}", m.id())
            })?;
            let column = step1_enrichment["covariate"]
                .as_str()
                .unwrap_or_default()
                .to_string();
            let coefficient = step1_enrichment["coefficient"].as_str().unwrap_or_default();
            let k = step1
                .coefs
                .iter()
                .position(|c| *c == coefficient)
                .ok_or_else(|| {
                    anyhow!(
                        "{}: no column {:?}: --boards must be the step-1 refit of {}",
                        step1_source,
                        coefficient,
                        m.id()
                    )
                })?;
            let used: BTreeSet<&str> = unit_names.iter().map(|s| s.as_str()).collect();
            let (values, values_source) = covariate
                .ok_or_else(|| anyhow!("{m:?}: the covariate column {column:?} was not read"))?;
            let (offsets, mean) =
                covariate_offsets(values, values_source, &column, &used, findings)?;
            let scaled = step1_enrichment["scaled"]
                .as_array()
                .into_iter()
                .flatten()
                .map(|n| jm.nominal.position(n.as_str().unwrap_or_default()))
                .collect::<Result<Vec<_>, _>>()?;
            Some(JointsCovariate {
                block: step1.block(),
                coef: step1.params.len() + k,
                scaled,
                // Offsets from step 1's reference, not from the bolted measurements' mean.
                offsets: unit_names
                    .iter()
                    .map(|u| offsets.get(u).copied().unwrap_or(0.0) + mean - reference)
                    .collect(),
            })
        }
    };
    if units.is_empty() {
        bail!("no bolted measurement has data for step 2 (no paired bolted mode of a board with a step-1 posterior)");
    }
    let enriched_units = if spec.enrich_units.is_empty() {
        None
    } else {
        if spec.enrich.is_none() {
            bail!("--enrich-units names the measurements an enrichment acts on; give --enrich too");
        }
        for m in &spec.enrich_units {
            if !unit_names.contains(m) {
                bail!("--enrich-units: {m} is not a bolted measurement of step 2 (expected one of {})", unit_names.join(", "));
            }
        }
        Some(
            unit_names
                .iter()
                .map(|u| spec.enrich_units.contains(u))
                .collect(),
        )
    };
    let target = ModalTarget {
        predictor,
        compose: Compose::Joints {
            board_params: jm.board_params.clone(),
            unit_board: unit_board_idx.clone(),
            coords: jm.coords.clone(),
            reference: jm.reference.clone(),
            covariate: joints_cov,
            enriched_units,
        },
        prior: PopulationPrior {
            mu_mean: vec![0.0; jm.coords.len()],
            mu_sd: jm.enr.coordinates.iter().map(|c| c.prior_sd).collect(),
            sigma_scale: vec![spec.sigma_scale; jm.coords.len()],
            sigma_prior: vec![],
            lkj_eta: spec.lkj_eta,
            lkj_log_norm: Default::default(),
        },
        errors: ErrorModel {
            n_modes: labels.labels.len(),
            eps: spec.eps,
            delta: spec.delta,
            model_error_sd: None,
            discrepancy: None,
        },
        units,
        covariate: None,
        subspaces: vec![],
        coord_obs: vec![],
    };
    // The cut posterior: groups of `group` particles, each carrying one step-1 draw; every
    // run takes its own evenly spaced subset of the step-1 draws.
    let group = 10usize;
    let groups = (sampler.smc.n_particles / group).max(1);
    let mut sampler = sampler.clone();
    sampler.smc.n_particles = groups * group;
    sampler.smc.groups = groups;
    let mut aux_index: Vec<Vec<usize>> = vec![];
    let aux: Vec<Vec<Arc<Vec<f64>>>> = (0..sampler.runs)
        .map(|r| {
            let idx: Vec<usize> = (0..groups)
                .map(|g| {
                    ((g * sampler.runs + r) * step1.draws.len() / (groups * sampler.runs))
                        % step1.draws.len()
                })
                .collect();
            let a = idx
                .iter()
                .map(|&i| Arc::new(step1.draws[i].1.clone()))
                .collect();
            aux_index.push(idx);
            a
        })
        .collect();
    Ok(JointTarget {
        step: StepTarget {
            target,
            all_pred,
            units_all,
            unit_names,
        },
        unit_boards,
        group,
        sampler,
        aux,
        aux_index,
    })
}

/// The box rule of step 2: the posterior must lie inside the ROM's box around the centre.
pub fn check_joint_box(
    (jm, c): (&JointModels, &Centred),
    centre: &[f64],
    results: &Results,
    unit_names: &[String],
    spec: &ModelSpec,
    verbose: bool,
) -> anyhow::Result<()> {
    let k_centre = c.k_centre;
    // The ROM's box per coordinate, around the fitted centre.
    let enr = &jm.enr;
    let coord_names: Vec<String> = enr.coordinates.iter().map(|c| c.name.clone()).collect();
    let bounds: Vec<(f64, f64)> = enr
        .coordinates
        .iter()
        .zip(centre)
        .map(|(c, &x0)| match c.log_box {
            Some(w) => (x0 - w, x0 + w),
            None => (
                x0 + (1.0 - spec.rom_box).ln(),
                x0 + (1.0 + spec.rom_box).ln(),
            ),
        })
        .collect();
    if verbose {
        eprintln!("joints: ROM box per coordinate (ln) {bounds:.3?}");
    }
    let draws: Vec<&[Vec<f64>]> = particles_of(results)
        .into_iter()
        .map(|(_, _, p)| p.x.as_slice())
        .collect();
    let violations = box_violations(
        &draws,
        "posterior",
        unit_names,
        &coord_names,
        |x| x.to_vec(),
        |k, x| x >= bounds[k].0 && x <= bounds[k].1,
        |_| true,
        spec.box_tolerance,
    );
    if !violations.is_empty() {
        bail!(
            "the joint posterior presses against the ROM's box (±{:.0} % around k_con_n_per_m = {k_centre:.4e} N/m, fitted to the bolted modes at the boards' posterior mean{}):\n  {}\nThe joints differ more between measurements than one ROM covers; a per-measurement ROM is not built yet.",
            100.0 * spec.rom_box,
            if jm.coords.len() > 1 { ", and the enrichment's logarithmic axes" } else { "" },
            violations.join("\n  ")
        );
    }
    Ok(())
}

/// The ROM against the full model at posterior draws, as a finding (a failed check is a
/// warning, and the posterior stands).
pub fn rom_posterior_finding(
    model: &FeModel,
    target: &ModalTarget,
    results: &Results,
    need: usize,
) -> Finding {
    match rom_posterior_check(model, target, results, 4, need) {
        Ok((rom_err, noise)) => Finding::new(
            if rom_err > 0.25 * noise {
                Severity::Warning
            } else {
                Severity::Info
            },
            "update.rom_posterior_check",
            format!(
                "the ROM's {need} lowest frequencies at 4 posterior draws differ from the full model's by at most {rom_err:.2e} (relative), against a measurement noise of {noise:.2e} (half the smallest posterior median of ε){}",
                if rom_err > 0.25 * noise { ": above a quarter of the noise, the posterior is the ROM's more than the model's (raise --rom-basis)" } else { "" }
            ),
        ),
        Err(e) => Finding::new(
            Severity::Warning,
            "update.rom_posterior_check",
            format!("the ROM could not be checked against the full model at posterior draws: {e}"),
        ),
    }
}

/// Step 2's draws as the tables' rows: the population (with each particle's step-1 draw), the
/// joints per measurement, and the summary.
pub struct JointTables {
    pub pop: DrawTable,
    pub jt: DrawTable,
    pub b_run: Vec<i32>,
    pub b_draw: Vec<i32>,
    pub joint_boards: Vec<String>,
    pub summary: Vec<SummaryRow>,
}

/// The cut estimate of the model-form scale of step 2 ([`CutScale`]) from its
/// posterior-predictive residuals `res`: per updated label of `labels` (the target's
/// order), the mean relative eigenvalue residual ((f / f̂)² − 1) over its measurements and
/// its standard error. `None` without a basis, or where a label has fewer than two
/// measurements (no standard error).
pub fn cut_scale(
    basis: Option<&crate::bayes::discrepancy::Discrepancy>,
    res: &[crate::update::posterior::Residual],
    labels: &[String],
) -> Option<CutScale> {
    let basis = basis?;
    let mut mean = vec![];
    let mut se = vec![];
    for l in labels {
        let r: Vec<f64> = res
            .iter()
            .filter(|r| r.used && &r.label == l)
            .map(|r| (r.freq_hz / r.mean).powi(2) - 1.0)
            .collect();
        if r.len() < 2 {
            return None;
        }
        let (m, sd) = crate::report::validation::mean_sd(&r);
        mean.push(m);
        se.push(sd / (r.len() as f64).sqrt());
    }
    CutScale::new(basis, &mean, &se)
}

/// evidence.json's `predictive_discrepancy`: the cut scale's posterior (null without one).
pub fn cut_scale_json(cut: Option<&CutScale>) -> serde_json::Value {
    use crate::bayes::discrepancy::freq_of_eigenvalue;
    match cut {
        None => serde_json::Value::Null,
        Some(c) => serde_json::json!({
            "note": "cut estimate of the model-form scale tau (relative eigenvalue) from the updated bolted modes' mean residuals; it widens the predictions of the bolted modes step 2 did not update, and nothing else (bayes::discrepancy::CutScale)",
            "fidelity_freq": crate::bayes::discrepancy::BOLTED_FIDELITY_FREQ,
            "scale_q05": c.quantile(0.05),
            "scale_q50": c.quantile(0.5),
            "scale_q95": c.quantile(0.95),
            "freq_q50": freq_of_eigenvalue(c.quantile(0.5)),
        }),
    }
}

/// The rows of step 2's tables from the runs' particles; with a cut scale `cut` (its basis
/// and its seed), a `predictive_discrepancy_scale` column of its draws, one per particle.
/// The summary's physical quantiles are those of the draws less the part of the model-form
/// discrepancy the coordinates absorb (keyed by `seed`), as in step 1: what an estimate that
/// claims to hold the physical value needs. With a discrepancy in the likelihood it is
/// drawn at its scale ([`confounded_draw`]); without one, at the cut scale's draw
/// ([`confounded_draw_at`]): the likelihood and the predictions stay the baseline's, and a
/// parameter the data pin only through small shifts of the modes, which the model's form
/// makes as well, gets the width that form gives it (the fixture's mass had 0.0906–0.0908
/// kg against the lab's 0.1).
#[allow(clippy::too_many_arguments)]
pub fn joint_tables(
    jm: &JointModels,
    jt_: &JointTarget,
    results: &Results,
    labels: &Labels,
    step1: &Step1,
    (runs, seed): (usize, u64),
    cut: Option<(&CutScale, &crate::bayes::discrepancy::Discrepancy, u64)>,
) -> JointTables {
    let target = &jt_.step.target;
    // population.parquet (step 2).
    let mut pcols: Vec<(String, String)> = vec![];
    let enr = &jm.enr;
    for c in &enr.coordinates {
        let u = if c.report_unit.is_empty() {
            String::new()
        } else {
            format!("ln({})", c.report_unit)
        };
        pcols.push((format!("mu_{}", c.name), u.clone()));
        pcols.push((format!("sigma_{}", c.name), u));
    }
    let infer_eps = matches!(target.errors.eps, ErrorPrior::Inferred { .. });
    let infer_delta = matches!(target.errors.delta, Some(ErrorPrior::Inferred { .. }));
    if infer_eps {
        pcols.extend(
            labels
                .labels
                .iter()
                .map(|l| (format!("eps_{l}"), String::new())),
        );
    }
    if infer_delta {
        pcols.extend(
            labels
                .labels
                .iter()
                .map(|l| (format!("delta_{l}"), String::new())),
        );
    }
    let with_discrepancy = target.errors.discrepancy.is_some();
    if with_discrepancy {
        pcols.extend(discrepancy_columns(&labels.labels));
    }
    let mut cut_rng = cut.map(|(c, basis, seed)| (c, basis, ChaCha8Rng::seed_from_u64(seed)));
    if cut_rng.is_some() {
        pcols.push(("predictive_discrepancy_scale".into(), String::new()));
    }
    let mut pop = DrawTable::new(&pcols);
    let jcols: Vec<(String, String)> = enr
        .coordinates
        .iter()
        .map(|c| (c.report_param.clone(), c.report_unit.clone()))
        .collect();
    let mut jt = DrawTable::new(&jcols);
    let mut pop_phys = DrawTable::new(&pcols);
    let mut jt_phys = DrawTable::new(&jcols);
    let (mut b_run, mut b_draw) = (vec![], vec![]);
    let mut joint_boards = vec![];
    for (r, i, p) in particles_of(results) {
        let ctx = smc::Target::ctx(target, &p.g);
        let mut row = vec![];
        for (k, c) in enr.coordinates.iter().enumerate() {
            row.push(c.report_ref.ln() + ctx.pop.mu[k]);
            row.push(ctx.pop.sigma[k]);
        }
        if infer_eps {
            row.extend(&ctx.eps);
        }
        if infer_delta {
            row.extend(&ctx.delta);
        }
        if with_discrepancy {
            row.extend(discrepancy_values(target, &p.g, &ctx));
        }
        let mut a = with_discrepancy.then(|| confounded_draw(target, &p.g, seed, (r, i)));
        if let Some((c, basis, rng)) = cut_rng.as_mut() {
            let tau = c.draw(rng);
            row.push(tau);
            a = a.or_else(|| Some(confounded_draw_at(basis, tau, seed, (r, i))));
        }
        pop.push(r, i, None, &row);
        // The shift is common to every unit and to μ (the coordinates' population means lead
        // the row, each beside its σ); the spreads do not move.
        if let Some(a) = a {
            for (k, ak) in a.iter().enumerate().take(enr.coordinates.len()) {
                row[2 * k] -= ak;
            }
            pop_phys.push(r, i, None, &row);
            for (b, name) in jt_.step.unit_names.iter().enumerate() {
                let x = less_confounded(&p.x[b], &a);
                jt_phys.push(r, i, Some(name), &enr.report_values(&x));
            }
        }
        let g = i / jt_.group;
        let (kr, kd) = step1.draws[jt_.aux_index[r % jt_.aux_index.len()]
            [g % jt_.aux_index[r % jt_.aux_index.len()].len()]]
        .0;
        b_run.push(kr);
        b_draw.push(kd);
        for (b, name) in jt_.step.unit_names.iter().enumerate() {
            jt.push(r, i, Some(name), &enr.report_values(&p.x[b]));
            joint_boards.push(jt_.unit_boards[b].clone());
        }
    }
    let mut summary = pop.summarize(runs, true);
    let mut js = jt.summarize(runs, false);
    for row in &mut js {
        row.board_id = row
            .measurement_id
            .as_ref()
            .and_then(|m| jt_.step.unit_names.iter().position(|u| u == m))
            .map(|b| jt_.unit_boards[b].clone());
    }
    summary.extend(js);
    if !pop_phys.run.is_empty() {
        let mut phys = pop_phys.summarize(runs, true);
        phys.extend(jt_phys.summarize(runs, false));
        for (row, ph) in summary.iter_mut().zip(phys) {
            debug_assert!(row.parameter == ph.parameter && row.measurement_id == ph.measurement_id);
            row.physical = Some(ph.s);
        }
    }
    JointTables {
        pop,
        jt,
        b_run,
        b_draw,
        joint_boards,
        summary,
    }
}

/// Step 2's evidence.json.
#[allow(clippy::too_many_arguments)]
pub fn joint_evidence(
    (jm, c): (&JointModels, &Centred),
    target: &ModalTarget,
    results: &Results,
    centre: &crate::update::centre::CentreFit,
    step1_enrichment: &serde_json::Value,
    shape_weights: &[crate::bayes::shape_weight::ShapeWeight],
    spec: &ModelSpec,
) -> anyhow::Result<serde_json::Value> {
    let log_z: Vec<f64> = results.iter().map(|r| r.log_evidence).collect();
    let mut ev = evidence_json(&log_z, "joints (step 2), modular (cut) posterior");
    ev["note_cut"] = "log p(bolted data | step-1 posterior): the mean over the carried step-1 draws of each draw's evidence".into();
    ev["k_con_rom_centre_n_per_m"] = c.k_centre.into();
    ev["enrichment"] = serde_json::to_value(&jm.enr)?;
    ev["new_modes"] = serde_json::Value::Array(
        c.new_modes
            .iter()
            .map(|nm| {
                serde_json::json!({
                    "label": nm.label,
                    "model_mode": nm.model_mode + 1,
                    "model_freq_hz": nm.model_freq_hz,
                    "median_freq_hz": nm.median_freq_hz(),
                    "n_paired": nm.rows.len(),
                    "n_measurements": nm.n_measurements,
                    "updated": spec.enrich_new_modes,
                })
            })
            .collect(),
    );
    if let Some(m) = jm.board_mech {
        // The joints are the baseline's; the boards carry the mechanism (step 1's refit).
        ev["board_mechanism"] = serde_json::to_value(m)?;
        ev["boards_dir_evidence"] = step1_enrichment.clone();
    }
    ev["rom_centre_coordinates"] = serde_json::to_value(&centre.coords)?;
    // Each label's relative misfit at the centre (the population-level least-squares fit):
    // the diagnosis's screen of a joint refit compares its own with the baseline's.
    ev["rom_centre_rel_residuals"] = centre
        .rel_residuals
        .iter()
        .map(|(l, r)| (l.clone(), serde_json::json!(r)))
        .collect::<serde_json::Map<_, _>>()
        .into();
    ev["shape_weights"] = serde_json::to_value(shape_weights)?;
    ev["discrepancy"] = discrepancy_json(target, &c.labels.labels);
    Ok(ev)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Step 2's ROM holds the step-1 draws of the shear modulus it carries: the default axis
    /// where it holds them, step 1's margin beyond it, at most the widest axis.
    #[test]
    fn the_shear_modulus_axis_holds_the_step1_draws() {
        let g_z = names::G_Z.to_string();
        let nominal = Params {
            names: vec!["e_x_pa".into(), g_z.clone()],
            values: vec![24e9, 3e9],
        };
        let step1 = |g: &[f64]| Step1 {
            board_ids: vec!["A".into(), "B".into()],
            params: vec!["e_x_pa".into(), g_z.clone()],
            coefs: vec![],
            draws: g
                .chunks(2)
                .enumerate()
                .map(|(i, p)| ((0, i as i32), vec![24e9, p[0], 24e9, p[1]]))
                .collect(),
        };
        let spec = ModelSpec::for_tests();
        // Within × or ÷ 2: unchanged.
        let s = holding_step1_g_z(&spec, &step1(&[3e9, 2.9e9, 1.6e9, 5.9e9]), &nominal);
        assert_eq!(s.g_z_log_box, None);
        // The underfill campaign's × 0.47: ln 0.47 = −0.755, × 1.15 = 0.869, to 0.90.
        let s = holding_step1_g_z(&spec, &step1(&[3e9, 1.41e9, 2.9e9, 3.1e9]), &nominal);
        assert!((s.g_z_log_box.unwrap() - 0.9).abs() < 1e-12, "{s:?}");
        // Beyond × 4: the widest axis (the ROM's posterior check then warns).
        let s = holding_step1_g_z(&spec, &step1(&[3e9, 0.5e9, 3e9, 3e9]), &nominal);
        assert_eq!(s.g_z_log_box, Some(MAX_G_Z_LOG_BOX));
        // A model without the parameter: unchanged.
        let thin = Params {
            names: vec!["e_x_pa".into()],
            values: vec![24e9],
        };
        let s = holding_step1_g_z(&spec, &step1(&[3e9, 0.5e9, 3e9, 3e9]), &thin);
        assert_eq!(s.g_z_log_box, None);
    }
}

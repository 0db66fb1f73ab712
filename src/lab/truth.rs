//! The hierarchical truth behind a virtual campaign and its modes.
//!
//! Draws (all from child seeds, see [`super::child_seed`]):
//! - per board b: θ_b = θ̄ ∘ (1 + δ_b), δ_b ~ N(0, S R S) with S = diag(rel_std) and R the
//!   correlation matrix, for θ = (E_x [Pa], E_y [Pa], G_xy [Pa], mass scale [-]);
//! - per board b, from a stream of its own: the FR-4 core thickness
//!   h_b = h₀ max(1 + s_h z_b, 1/2) [m], z_b ~ N(0, 1), s_h = `population.thickness_rel_std`;
//! - per bolted measurement: K_con ~ N(K̄, (rel_std K̄)²) [N/m], each joint's stiffness
//!   K_con (1 + ε_j), ε_j ~ N(0, per_joint_rel_std²), and a loose-bolt draw (used only when
//!   the loose-bolt effect is on, so every scenario shares the same draws);
//! - per measurement: the lab temperature T_k = T̄ + A sin(2π k / P) + N(0, σ_T²) [°C].
//!
//! Truth models (richer than the updating model): the board on a finer mesh than its
//! default, bolted through per-joint contact springs on the clamped patches (with the
//! riding share of the bolt mass when the scenario's `[truth] joint_mass_kg` gives one;
//! default none), plus the features of the switched-on effects. For each
//! measurement the modes are computed twice when an effect touches its setup: with the
//! effects and without them (the counterfactual, paired by MAC on the scan grid), so the
//! truth file states by how much each effect moved each mode.

use faer::Mat;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

use super::scenario::{Physics, Scenario};
use super::solid::{SolidModel, Solver, State as SolidState};
use super::{child_seed, LabError, Stream};
use crate::fem::params::names;
use crate::fem::{
    Board, FeModel, JointFeature, JointModel, MeshOptions, ModelOptions, Modes, Params, Setup,
};

/// Test setup of a measurement.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
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

/// Cholesky factor L (lower) of a 4 × 4 symmetric matrix, `None` unless positive definite.
pub fn cholesky4(a: &[[f64; 4]; 4]) -> Option<[[f64; 4]; 4]> {
    let mut l = [[0.0; 4]; 4];
    for i in 0..4 {
        for j in 0..=i {
            let s: f64 = a[i][j] - (0..j).map(|k| l[i][k] * l[j][k]).sum::<f64>();
            if i == j {
                if s.is_nan() || s <= 1e-12 {
                    return None;
                }
                l[i][i] = s.sqrt();
            } else {
                l[i][j] = s / l[j][j];
            }
        }
    }
    Some(l)
}

/// One board's drawn parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BoardDraw {
    pub board_id: String,
    pub e_x_pa: f64,
    pub e_y_pa: f64,
    pub g_xy_pa: f64,
    /// Scale of the board's distributed mass (FR-4 and copper), dimensionless.
    pub mass_scale: f64,
    /// The relative deviations δ drawn, (E_x, E_y, G_xy, mass scale).
    pub deviation_rel: [f64; 4],
    /// The board's FR-4 core thickness, m (the board file's unless
    /// `population.thickness_rel_std` > 0).
    pub core_thickness_m: f64,
}

/// One bolted measurement's drawn joint state.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BoltedDraw {
    /// The measurement's contact stiffness K_con, N/m per joint.
    pub k_con_n_per_m: f64,
    /// Each joint's stiffness before any loose bolt, N/m.
    pub k_joint_n_per_m: Vec<f64>,
    /// 0-based joint that is loose (only when the loose-bolt effect is on and drawn).
    pub loose_joint: Option<usize>,
    /// Bolt set id written to the sheet.
    pub bolt_set: String,
}

/// One planned measurement.
#[derive(Clone, Debug)]
pub struct Planned {
    /// 0-based position in the campaign (sheet order).
    pub index: usize,
    pub measurement_id: String,
    /// 0-based board number.
    pub board: usize,
    pub board_id: String,
    pub setup: SetupKind,
    /// UFF path relative to the campaign directory.
    pub file: String,
    pub temperature_c: f64,
    /// ISO-8601 date-time.
    pub date: String,
    pub operator: String,
    pub notes: String,
    pub torque_nm: Option<f64>,
    pub bolted: Option<BoltedDraw>,
    /// What the lab's habits changed (`super::habits`); default: nothing.
    pub habits: super::habits::MeasurementHabits,
}

/// The drawn campaign.
#[derive(Clone, Debug)]
pub struct Plan {
    pub boards: Vec<BoardDraw>,
    pub measurements: Vec<Planned>,
    /// Date (YYYY-MM-DD) of the first and of the last measurement day (weighing days).
    pub first_day: String,
    pub last_day: String,
    /// The campaign seed.
    pub seed: u64,
}

fn normal(rng: &mut ChaCha8Rng) -> f64 {
    StandardNormal.sample(rng)
}

/// Draw the boards, the schedule, the temperatures and the bolted joint states.
pub fn plan(s: &Scenario, board: &Board, seed: u64) -> Result<Plan, LabError> {
    let pop = &s.population;
    let l = cholesky4(&pop.correlation).ok_or_else(|| LabError::ScenarioInvalid {
        field: "population.correlation".into(),
        expected: "a positive definite matrix".into(),
        found: format!("{:?}", pop.correlation),
    })?;
    let c = &board.core;
    let boards: Vec<BoardDraw> = (0..s.campaign.n_boards)
        .map(|b| {
            let mut rng = ChaCha8Rng::seed_from_u64(child_seed(seed, Stream::Board, b as u64));
            let n: [f64; 4] = std::array::from_fn(|_| normal(&mut rng));
            let d: [f64; 4] = std::array::from_fn(|i| {
                pop.rel_std[i] * (0..=i).map(|k| l[i][k] * n[k]).sum::<f64>()
            });
            // The thickness from a stream of its own: the draws above stay as they were.
            let mut hrng = ChaCha8Rng::seed_from_u64(child_seed(seed, Stream::Thickness, b as u64));
            let z_h = normal(&mut hrng);
            BoardDraw {
                board_id: format!("PCB-{:02}", b + 1),
                e_x_pa: c.e_x_pa * (1.0 + d[0]),
                e_y_pa: c.e_y_pa * (1.0 + d[1]),
                g_xy_pa: c.g_xy_pa * (1.0 + d[2]),
                mass_scale: 1.0 + d[3],
                deviation_rel: d,
                core_thickness_m: c.thickness_m * (1.0 + pop.thickness_rel_std * z_h).max(0.5),
            }
        })
        .collect();

    // Sheet order: all free measurements board by board, then the bolted ones.
    let mut order: Vec<(usize, SetupKind, usize, String)> = Vec::new();
    for b in 0..s.campaign.n_boards {
        for k in 0..s.campaign.free_per_board {
            order.push((b, SetupKind::Free, k, String::new()));
        }
    }
    for g in &s.campaign.bolted {
        for &b in &g.boards {
            for k in 0..g.per_board {
                order.push((b - 1, SetupKind::Bolted, k, g.purpose.clone()));
            }
        }
    }
    let start =
        chrono::NaiveDate::parse_from_str(&s.campaign.start_date, "%Y-%m-%d").map_err(|e| {
            LabError::ScenarioInvalid {
                field: "campaign.start_date".into(),
                expected: "a date YYYY-MM-DD".into(),
                found: format!("{} ({e})", s.campaign.start_date),
            }
        })?;
    // 16 measurements a day from 09:00, 25 minutes each.
    const PER_DAY: usize = 16;
    let n_joints = board.holes.len();
    let lab = &s.lab;
    let mut bolted_count = 0u64;
    let mut measurements = Vec::with_capacity(order.len());
    for (index, (b, setup, k, purpose)) in order.into_iter().enumerate() {
        let day = start + chrono::Days::new((index / PER_DAY) as u64);
        let minutes = 9 * 60 + 25 * (index % PER_DAY);
        let date = format!(
            "{}T{:02}:{:02}:00",
            day.format("%Y-%m-%d"),
            minutes / 60,
            minutes % 60
        );
        let mut trng =
            ChaCha8Rng::seed_from_u64(child_seed(seed, Stream::Temperature, index as u64));
        let temperature_c = lab.temperature_mean_c
            + lab.temperature_swing_c
                * (2.0 * std::f64::consts::PI * index as f64 / lab.temperature_period).sin()
            + lab.temperature_noise_c * normal(&mut trng);
        let board_id = boards[b].board_id.clone();
        let (bolted, notes, torque) = match setup {
            SetupKind::Free => (
                None,
                format!("free-free on foam, hammer, run {}", k + 1),
                None,
            ),
            SetupKind::Bolted => {
                let mut rng =
                    ChaCha8Rng::seed_from_u64(child_seed(seed, Stream::Bolted, bolted_count));
                bolted_count += 1;
                let k_con = s.population.k_con_mean_n_per_m
                    * (1.0 + s.population.k_con_rel_std * normal(&mut rng)).max(0.3);
                let k_joint: Vec<f64> = (0..n_joints)
                    .map(|_| {
                        k_con * (1.0 + s.truth.per_joint_k_rel_std * normal(&mut rng)).max(0.3)
                    })
                    .collect();
                let u: f64 = rng.random();
                let j = ((rng.random::<f64>() * n_joints as f64) as usize).min(n_joints - 1);
                let loose_joint = s
                    .effects
                    .loose_bolt
                    .as_ref()
                    .and_then(|lb| (u < lb.share).then_some(j));
                let bolt_set = format!("BS-{:02}{:02}", b + 1, k + 1);
                let notes = if k % 4 == 1 {
                    format!("{purpose}; bolts {bolt_set}, torque checked, \"hand tight\" first")
                } else if k % 4 == 3 {
                    format!("{purpose}\nlaser re-focused after bolt change")
                } else {
                    purpose.clone()
                };
                (
                    Some(BoltedDraw {
                        k_con_n_per_m: k_con,
                        k_joint_n_per_m: k_joint,
                        loose_joint,
                        bolt_set,
                    }),
                    notes,
                    Some(s.campaign.torque_nm),
                )
            }
        };
        measurements.push(Planned {
            index,
            measurement_id: format!("M{:03}", index + 1),
            board: b,
            board_id,
            setup,
            file: format!("vibrometer/M{:03}.uff", index + 1),
            temperature_c,
            date,
            operator: s.campaign.operators[index % s.campaign.operators.len()].clone(),
            notes,
            torque_nm: torque,
            bolted,
            habits: Default::default(),
        });
    }
    let n_days = measurements.len().div_ceil(PER_DAY).max(1) as u64;
    Ok(Plan {
        boards,
        measurements,
        first_day: start.format("%Y-%m-%d").to_string(),
        last_day: (start + chrono::Days::new(n_days - 1))
            .format("%Y-%m-%d")
            .to_string(),
        seed,
    })
}

/// The truth FE models: with the effects, and without them where that changes the model.
pub struct Models {
    pub free: FeModel,
    pub free_cf: Option<FeModel>,
    /// `None` when the campaign has no bolted measurement (a board without holes is fine).
    pub bolted: Option<FeModel>,
    pub bolted_cf: Option<FeModel>,
    /// Scan points, m (the board's default scan grid).
    pub points: Vec<[f64; 2]>,
    /// The solid truth's meshes, when `[truth] physics = "solid"`: then the modes come from
    /// them, and the plate models above serve only as the updating model's reference.
    pub solid: Option<SolidTruth>,
}

/// The solid truth of both setups.
pub struct SolidTruth {
    pub free: SolidModel,
    /// `None` when the campaign has no bolted measurement.
    pub bolted: Option<SolidModel>,
}

/// Which model state a solve is of: a setup with the concealed effects that change the model,
/// or without them (the counterfactual).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Variant {
    Free,
    FreeCf,
    Bolted,
    BoltedCf,
}

/// The modes of board `bd` in `variant`, FR-4 moduli scaled by `stiff`, joints per `bolted`
/// (the loose joint softened when `loose`), shapes at `points`, from the plate or the solid
/// truth.
#[allow(clippy::too_many_arguments)]
fn modes_of(
    s: &Scenario,
    models: &Models,
    variant: Variant,
    bd: &BoardDraw,
    stiff: f64,
    bolted: Option<&BoltedDraw>,
    loose: bool,
    points: &[[f64; 2]],
) -> Result<ModeSet, LabError> {
    let n = match variant {
        Variant::Free | Variant::FreeCf => s.truth.n_free_modes,
        Variant::Bolted | Variant::BoltedCf => s.truth.n_bolted_modes,
    };
    let Some(solid) = &models.solid else {
        let model = match variant {
            Variant::Free => &models.free,
            Variant::FreeCf => models.free_cf.as_ref().unwrap_or(&models.free),
            Variant::Bolted | Variant::BoltedCf => {
                let plain = models.bolted.as_ref().ok_or_else(|| {
                    LabError::Solid("a bolted measurement, but no bolted model was built".into())
                })?;
                match variant {
                    Variant::BoltedCf => models.bolted_cf.as_ref().unwrap_or(plain),
                    _ => plain,
                }
            }
        };
        let p = params(s, model, bd, stiff, bolted, loose)?;
        return mode_set(model, &p, n, points);
    };
    // The model-changing effects only in the states with effects.
    let none = super::scenario::Effects::default();
    let e = if matches!(variant, Variant::Free | Variant::Bolted) {
        &s.effects
    } else {
        &none
    };
    let st = SolidState {
        e_x_pa: bd.e_x_pa * stiff,
        e_y_pa: bd.e_y_pa * stiff,
        g_xy_pa: bd.g_xy_pa * stiff,
        mass_scale: bd.mass_scale,
        k_joint_n_per_m: bolted.map_or_else(Vec::new, |bo| joint_stiffnesses(s, bo, loose)),
        k_rot_nm_per_rad: e.rotational_restraint.as_ref().map(|r| r.k_rot_nm_per_rad),
        point_mass: e
            .lumped_mass
            .as_ref()
            .map(|lm| ([lm.x_m, lm.y_m], lm.mass_kg)),
        underfill_factor: e.underfill.as_ref().map(|u| u.stiffness_factor),
        fixture: e
            .compliant_fixture
            .as_ref()
            .map(|f| (f.k_fix_n_per_m, f.m_fix_kg)),
        n_modes: n,
    };
    let model = match variant {
        Variant::Free | Variant::FreeCf => &solid.free,
        Variant::Bolted | Variant::BoltedCf => solid.bolted.as_ref().ok_or_else(|| {
            LabError::Solid("a bolted measurement, but no bolted solid model was built".into())
        })?,
    };
    model.modes(&st, points, super::measure::SHAKER_REFERENCE_M)
}

/// The truth joint model with or without the effect features.
pub fn joint_model(s: &Scenario, with_effects: bool) -> JointModel {
    let mut features = vec![
        JointFeature::PerJointTranslational,
        JointFeature::JointMass {
            mass_kg: s.truth.joint_mass_kg,
        },
    ];
    if with_effects {
        if let Some(r) = &s.effects.rotational_restraint {
            features.push(JointFeature::RotationalRestraint {
                k_rot_nm_per_rad: r.k_rot_nm_per_rad,
            });
        }
        if let Some(f) = &s.effects.compliant_fixture {
            features.push(JointFeature::CompliantFixture {
                k_fix_n_per_m: f.k_fix_n_per_m,
                m_fix_kg: f.m_fix_kg,
            });
        }
    }
    JointModel { features }
}

/// The truth's bolted mesh: the scenario's truth mesh, or, where the board's bolted mesh is
/// finer than its default mesh, that bolted mesh refined by the same factor as the truth mesh
/// refines the default one (the truth stays finer than the updating model in every setup).
pub fn truth_bolted_mesh(s: &Scenario, board: &Board) -> MeshOptions {
    match &board.mesh_bolted {
        Some(mb) => {
            let fx = s.truth.mesh_nx as f64 / board.mesh.nx as f64;
            let fy = s.truth.mesh_ny as f64 / board.mesh.ny as f64;
            MeshOptions {
                nx: s.truth.mesh_nx.max((mb.nx as f64 * fx).round() as usize),
                ny: s.truth.mesh_ny.max((mb.ny as f64 * fy).round() as usize),
            }
        }
        None => MeshOptions {
            nx: s.truth.mesh_nx,
            ny: s.truth.mesh_ny,
        },
    }
}

impl Models {
    /// Build the truth models of `s` for `board`.
    pub fn build(
        s: &Scenario,
        board: &Board,
        solver: Option<std::sync::Arc<dyn Solver>>,
    ) -> Result<Models, LabError> {
        let mesh = MeshOptions {
            nx: s.truth.mesh_nx,
            ny: s.truth.mesh_ny,
        };
        let bolted_mesh = truth_bolted_mesh(s, board);
        let e = &s.effects;
        let opts = model_options(s);
        let free_plain = FeModel::build_with(board, Setup::Free, &mesh, opts)?;
        let mut free = free_plain.clone();
        if let Some(lm) = &e.lumped_mass {
            free.add_point_mass(lm.x_m, lm.y_m, lm.mass_kg)?;
        }
        if let Some(d) = &e.underfill {
            free.add_core_stiffness_change(d.x_m, d.y_m, d.radius_m, d.stiffness_factor)?;
        }
        let free_cf = (e.lumped_mass.is_some() || e.underfill.is_some()).then_some(free_plain);
        // The bolted models only where something is measured bolted.
        let (bolted, bolted_cf) = if has_bolted(s) {
            let bolted_plain = FeModel::build_with(
                board,
                Setup::Bolted(joint_model(s, false)),
                &bolted_mesh,
                opts,
            )?;
            let model_changes_bolted = e.rotational_restraint.is_some()
                || e.compliant_fixture.is_some()
                || e.lumped_mass.is_some()
                || e.underfill.is_some();
            let mut bolted = if e.rotational_restraint.is_some() || e.compliant_fixture.is_some() {
                FeModel::build_with(
                    board,
                    Setup::Bolted(joint_model(s, true)),
                    &bolted_mesh,
                    opts,
                )?
            } else {
                bolted_plain.clone()
            };
            if let Some(lm) = &e.lumped_mass {
                bolted.add_point_mass(lm.x_m, lm.y_m, lm.mass_kg)?;
            }
            if let Some(d) = &e.underfill {
                bolted.add_core_stiffness_change(d.x_m, d.y_m, d.radius_m, d.stiffness_factor)?;
            }
            (Some(bolted), model_changes_bolted.then_some(bolted_plain))
        } else {
            (None, None)
        };
        let points = board.scan_points_m();
        // Fail early with a clear error if a scan point is off the board or in a hole.
        free.shape_operator(&points)?;
        let solid = match s.truth.physics {
            Physics::Plate => None,
            Physics::Solid => {
                let solver = solver.ok_or_else(|| {
                    LabError::Solid(
                        "truth.physics = \"solid\" needs gmsh and CalculiX, and none were given"
                            .into(),
                    )
                })?;
                let underfill = e.underfill.as_ref().map(|u| super::solid::geo::Disc {
                    x_m: u.x_m,
                    y_m: u.y_m,
                    r_m: u.radius_m,
                });
                let opts = &s.truth.solid;
                let free = SolidModel::build(board, opts, false, underfill, solver.clone())?;
                let bolted = if has_bolted(s) {
                    Some(SolidModel::build(board, opts, true, underfill, solver)?)
                } else {
                    None
                };
                Some(SolidTruth { free, bolted })
            }
        };
        Ok(Models {
            free,
            free_cf,
            bolted,
            bolted_cf,
            points,
            solid,
        })
    }
}

/// Options of the plate truth models: the core thickness as a parameter when the boards'
/// thicknesses vary (else the models are built exactly as without it).
pub fn model_options(s: &Scenario) -> ModelOptions {
    ModelOptions {
        core_thickness: s.population.thickness_rel_std > 0.0,
    }
}

/// Whether the campaign measures any board bolted.
fn has_bolted(s: &Scenario) -> bool {
    s.campaign
        .bolted
        .iter()
        .any(|g| g.per_board > 0 && !g.boards.is_empty())
}

/// Stiffness factor of the temperature effect at `temperature_c` (1 without the effect).
pub fn stiffness_factor(s: &Scenario, temperature_c: f64) -> f64 {
    s.effects.temperature.as_ref().map_or(1.0, |t| {
        1.0 + t.coefficient_per_k * (temperature_c - t.reference_c)
    })
}

/// Parameters of `model` for board `bd`, FR-4 moduli scaled by `stiff`, joints per `bolted`
/// (with the loose joint softened when `loose` is set).
fn params(
    s: &Scenario,
    model: &FeModel,
    bd: &BoardDraw,
    stiff: f64,
    bolted: Option<&BoltedDraw>,
    loose: bool,
) -> Result<Params, LabError> {
    let mut p = model.nominal_params();
    p.set(names::E_X, bd.e_x_pa * stiff)?;
    p.set(names::E_Y, bd.e_y_pa * stiff)?;
    p.set(names::G_XY, bd.g_xy_pa * stiff)?;
    p.set(names::MASS_SCALE, bd.mass_scale)?;
    if p.names.iter().any(|n| n == names::CORE_THICKNESS) {
        p.set(names::CORE_THICKNESS, bd.core_thickness_m)?;
    }
    if let Some(bo) = bolted {
        for (j, k) in joint_stiffnesses(s, bo, loose).into_iter().enumerate() {
            p.set(&names::k_con_joint(j + 1), k)?;
        }
    }
    Ok(p)
}

/// Each joint's stiffness in a bolted measurement, N/m: the drawn ones, the loose joint's
/// softened by the loose-bolt effect when `loose`.
fn joint_stiffnesses(s: &Scenario, bo: &BoltedDraw, loose: bool) -> Vec<f64> {
    bo.k_joint_n_per_m
        .iter()
        .enumerate()
        .map(
            |(j, k)| match (loose, bo.loose_joint, &s.effects.loose_bolt) {
                (true, Some(lj), Some(lb)) if lj == j => k * lb.stiffness_factor,
                _ => *k,
            },
        )
        .collect()
}

/// Modes of one model state evaluated on the scan grid.
#[derive(Clone, Debug)]
pub struct ModeSet {
    pub freq_hz: Vec<f64>,
    /// `shapes[r][o]`: mass-normalised shape of mode r at scan point o, 1/√kg.
    pub shapes: Vec<Vec<f64>>,
    /// Participation Γ_r = φ_rᵀ M r for base motion in z, √kg (bolted only).
    pub gamma: Vec<f64>,
    /// Bolted only: participation in rigid base rotations about the shaker reference
    /// point, φ_rᵀ M r_θ with r_θ: w = x − x_ref (resp. y − y_ref) and unit slope,
    /// √kg·m per mode.
    pub gamma_rock: Vec<[f64; 2]>,
    /// Free only: the three rigid-body shapes at the scan points (M-orthonormal).
    pub rigid: Vec<Vec<f64>>,
    /// Total mass rᵀ M r, kg.
    pub total_mass_kg: f64,
}

fn to_rows(m: &Mat<f64>) -> Vec<Vec<f64>> {
    (0..m.ncols())
        .map(|j| (0..m.nrows()).map(|i| m[(i, j)]).collect())
        .collect()
}

/// Rigid-body modes of a free model: w = 1, w = x − x̄, w = y − ȳ (with their slopes),
/// M-orthonormalised by Gram–Schmidt, evaluated at `points`.
fn rigid_shapes(
    model: &FeModel,
    p: &Params,
    points: &[[f64; 2]],
) -> Result<Vec<Vec<f64>>, LabError> {
    let mesh = &model.mesh;
    let mut vecs = vec![vec![0.0; model.n_dof]; 3];
    let (cx, cy) = (0.5 * model.board.length_x_m, 0.5 * model.board.width_y_m);
    for j in 0..=mesh.ny {
        for i in 0..=mesh.nx {
            if let Some(d) = mesh.node_dof[j * (mesh.nx + 1) + i] {
                let (x, y) = (mesh.x_m[i], mesh.y_m[j]);
                vecs[0][d] = 1.0;
                vecs[1][d] = x - cx;
                vecs[1][d + 1] = 1.0;
                vecs[2][d] = y - cy;
                vecs[2][d + 2] = 1.0;
            }
        }
    }
    let mut done: Vec<(Vec<f64>, Vec<f64>)> = Vec::new(); // (v, M v)
    for mut v in vecs {
        for (u, mu) in &done {
            let c: f64 = v.iter().zip(mu).map(|(a, b)| a * b).sum();
            v.iter_mut().zip(u).for_each(|(a, b)| *a -= c * b);
        }
        let mv = model.mass_apply(p, &v)?;
        let n = v.iter().zip(&mv).map(|(a, b)| a * b).sum::<f64>().sqrt();
        let v: Vec<f64> = v.iter().map(|a| a / n).collect();
        let mv: Vec<f64> = mv.iter().map(|a| a / n).collect();
        done.push((v, mv));
    }
    let m = Mat::from_fn(model.n_dof, 3, |i, j| done[j].0[i]);
    Ok(to_rows(&model.shape_operator(points)?.apply(m.as_ref())))
}

fn mode_set(
    model: &FeModel,
    p: &Params,
    n: usize,
    points: &[[f64; 2]],
) -> Result<ModeSet, LabError> {
    let modes: Modes = model.modes(p, n)?;
    let shapes = to_rows(&model.w_at(&modes, points)?);
    let free = matches!(model.setup, Setup::Free);
    let gamma = if free {
        vec![]
    } else {
        model.participation_z(p, &modes)?
    };
    let rigid = if free {
        rigid_shapes(model, p, points)?
    } else {
        vec![]
    };
    let gamma_rock = if free {
        vec![]
    } else {
        let [xr, yr, _] = super::measure::SHAKER_REFERENCE_M;
        let mesh = &model.mesh;
        let mut rx = vec![0.0; model.n_dof];
        let mut ry = vec![0.0; model.n_dof];
        for j in 0..=mesh.ny {
            for i in 0..=mesh.nx {
                if let Some(d) = mesh.node_dof[j * (mesh.nx + 1) + i] {
                    rx[d] = mesh.x_m[i] - xr;
                    rx[d + 1] = 1.0;
                    ry[d] = mesh.y_m[j] - yr;
                    ry[d + 2] = 1.0;
                }
            }
        }
        let (mrx, mry) = (model.mass_apply(p, &rx)?, model.mass_apply(p, &ry)?);
        (0..modes.shapes.ncols())
            .map(|c| {
                let g = |mr: &[f64]| {
                    (0..model.n_dof)
                        .map(|i| modes.shapes[(i, c)] * mr[i])
                        .sum::<f64>()
                };
                [g(&mrx), g(&mry)]
            })
            .collect()
    };
    Ok(ModeSet {
        freq_hz: modes.freq_hz,
        shapes,
        gamma,
        gamma_rock,
        rigid,
        total_mass_kg: model.total_mass_kg(p)?,
    })
}

/// Per board: the free modes at the reference state (with and without effects), and masses.
pub struct FreeCache {
    /// With effects (temperature at its reference), per board.
    pub with: Vec<ModeSet>,
    /// Without effects, per board (`None` when no effect touches the free setup).
    pub without: Vec<Option<ModeSet>>,
}

/// Free modes of every board at the reference temperature (in parallel, board order).
pub fn free_board_modes(s: &Scenario, plan: &Plan, m: &Models) -> Result<FreeCache, LabError> {
    use rayon::prelude::*;
    let pairs: Vec<(ModeSet, Option<ModeSet>)> = plan
        .boards
        .par_iter()
        .map(|bd| {
            let with = modes_of(s, m, Variant::Free, bd, 1.0, None, false, &m.points)?;
            let without = match &m.free_cf {
                Some(_) => Some(modes_of(
                    s,
                    m,
                    Variant::FreeCf,
                    bd,
                    1.0,
                    None,
                    false,
                    &m.points,
                )?),
                None => None,
            };
            Ok((with, without))
        })
        .collect::<Result<_, LabError>>()?;
    let (with, without) = pairs.into_iter().unzip();
    Ok(FreeCache { with, without })
}

/// One mode of a measurement's truth.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModeTruth {
    /// 1-based mode number in ascending frequency.
    pub mode: usize,
    /// Undamped natural frequency of the truth model, Hz.
    pub freq_hz: f64,
    /// Modal damping ratio used in the synthesis.
    pub damping_ratio: f64,
    /// Whether the mode lies inside the measured band.
    pub in_band: bool,
    /// Γ = φᵀ M r, √kg (bolted), `None` for free.
    pub participation_z: Option<f64>,
    /// Frequency of the paired mode without the concealed effects, Hz (`None` if no mode
    /// of the counterfactual pairs with it, e.g. the fixture's own mode).
    pub freq_without_effects_hz: Option<f64>,
    /// 100 (f / f_without − 1), %.
    pub shift_percent: Option<f64>,
    /// MAC of the pairing on the scan grid.
    pub mac_with_counterfactual: Option<f64>,
    /// How strongly the mode shows in the data: RMS over the scan points of its own
    /// term's magnitude at its natural frequency, |φ_o φ_d| / (2 ζ ω_r) in (m/s)/N (free,
    /// hammer at d) or |Γ φ_o| / (2 ζ) (bolted, dimensionless).
    pub peak_magnitude_rms: f64,
}

/// The truth of one measurement.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MeasurementTruth {
    pub measurement_id: String,
    pub board_id: String,
    pub setup: SetupKind,
    pub file: String,
    /// Lab temperature during the measurement (the sheet prints it to 0.1 °C), °C.
    pub temperature_c: f64,
    /// FR-4 stiffness factor of the temperature effect (1 without it).
    pub stiffness_factor: f64,
    pub k_con_n_per_m: Option<f64>,
    pub k_joint_n_per_m: Option<Vec<f64>>,
    /// 1-based number of the loose joint (hole order of the board file), if any.
    pub loose_joint: Option<usize>,
    pub bolt_set: Option<String>,
    pub modes: Vec<ModeTruth>,
    /// Free only: rigid-body (foam suspension) frequencies, Hz.
    pub suspension_hz: Vec<f64>,
    /// Node ids with no record (vibrometer marked them invalid).
    pub missing_nodes: Vec<i64>,
    /// Node ids whose record is mostly noise (speckle drop-out).
    pub dropout_nodes: Vec<i64>,
    /// The driving point: hammer impact node (free) or shaker reference node (bolted).
    pub reference_node: i64,
    /// Bolted: base rocking about the reference point, (a_x, a_y) in rad per metre of
    /// reference motion (the shaker's cross-axis motion).
    pub base_rocking_rad_per_m: Option<[f64; 2]>,
}

/// Modes and draws of one measurement, ready for the instruments.
pub struct MeasurementModes {
    pub truth: MeasurementTruth,
    /// The modes; for bolted measurements `gamma` includes the base rocking.
    pub set: ModeSet,
    pub damping: Vec<f64>,
    /// Bolted: rigid base motion at each scan point per unit reference motion,
    /// 1 + a_x (x − x_ref) + a_y (y − y_ref); empty for free measurements.
    pub base_motion: Vec<f64>,
}

/// Node id of the shaker reference point of bolted measurements (off the board).
pub const SHAKER_REFERENCE_NODE: i64 = 900;
/// 0-based scan point of the hammer impact (node 1, near a corner: every mode responds).
pub const HAMMER_POINT: usize = 0;

/// Pair the modes of `a` with those of `b`: first greedily by MAC on the scan grid (each
/// mode of `a` in ascending order takes the unused mode of `b` with the largest MAC ≥ 0.6),
/// then the leftovers by nearest frequency within 5 % (close modes that the effect mixes
/// lose their MAC but not their identity as a pair). Returns (index in `b`, MAC).
fn pair(a: &ModeSet, b: &ModeSet) -> Vec<Option<(usize, f64)>> {
    let dot = |x: &[f64], y: &[f64]| x.iter().zip(y).map(|(p, q)| p * q).sum::<f64>();
    let mac =
        |x: &[f64], y: &[f64]| dot(x, y).powi(2) / (dot(x, x) * dot(y, y)).max(f64::MIN_POSITIVE);
    let mut used = vec![false; b.shapes.len()];
    let mut out: Vec<Option<(usize, f64)>> = a
        .shapes
        .iter()
        .map(|x| {
            let best = b
                .shapes
                .iter()
                .enumerate()
                .filter(|(j, _)| !used[*j])
                .map(|(j, y)| (j, mac(x, y)))
                .filter(|(_, m)| *m >= 0.6)
                .max_by(|p, q| p.1.total_cmp(&q.1));
            if let Some((j, _)) = best {
                used[j] = true;
            }
            best
        })
        .collect();
    for (i, o) in out.iter_mut().enumerate() {
        if o.is_some() {
            continue;
        }
        let fa = a.freq_hz[i];
        let near = (0..b.freq_hz.len())
            .filter(|j| !used[*j] && (b.freq_hz[*j] / fa - 1.0).abs() <= 0.05)
            .min_by(|p, q| {
                (b.freq_hz[*p] - fa)
                    .abs()
                    .total_cmp(&(b.freq_hz[*q] - fa).abs())
            });
        if let Some(j) = near {
            used[j] = true;
            *o = Some((j, mac(&a.shapes[i], &b.shapes[j])));
        }
    }
    out
}

/// Modes of measurement `m` with and without effects, damping and drop-out draws.
pub fn measurement_modes(
    s: &Scenario,
    plan: &Plan,
    models: &Models,
    cache: &FreeCache,
    m: &Planned,
) -> Result<MeasurementModes, LabError> {
    let bd = &plan.boards[m.board];
    let stiff = stiffness_factor(s, m.temperature_c);
    // The measurement's own scan points on the board (habit `scan_grids`, bolted only: the
    // free modes are cached per board on the board's grid); points off it come last.
    let grid = m.habits.grid.as_ref();
    let points: &[[f64; 2]] = grid.map_or(&models.points, |g| &g.board);
    let n_off = grid.map_or(0, |g| g.off_board.len());
    if grid.is_some() && m.setup == SetupKind::Free {
        return Err(LabError::ScenarioInvalid {
            field: "habits".into(),
            expected: "own scan grids for bolted measurements only".into(),
            found: format!("a grid for free measurement {}", m.measurement_id),
        });
    }
    let (mut set, cf): (ModeSet, Option<ModeSet>) = match m.setup {
        SetupKind::Free => {
            let with = if stiff != 1.0 {
                modes_of(
                    s,
                    models,
                    Variant::Free,
                    bd,
                    stiff,
                    None,
                    false,
                    &models.points,
                )?
            } else {
                cache.with[m.board].clone()
            };
            let cf = match (&cache.without[m.board], stiff != 1.0) {
                (Some(w), _) => Some(w.clone()),
                (None, true) => Some(cache.with[m.board].clone()),
                (None, false) => None,
            };
            (with, cf)
        }
        SetupKind::Bolted => {
            let bo = m.bolted.as_ref();
            let with = modes_of(s, models, Variant::Bolted, bd, stiff, bo, true, points)?;
            let loose = bo.is_some_and(|b| b.loose_joint.is_some());
            let cf = match &models.bolted_cf {
                Some(_) => Some(modes_of(
                    s,
                    models,
                    Variant::BoltedCf,
                    bd,
                    1.0,
                    bo,
                    false,
                    points,
                )?),
                None if stiff != 1.0 || loose => Some(modes_of(
                    s,
                    models,
                    Variant::Bolted,
                    bd,
                    1.0,
                    bo,
                    false,
                    points,
                )?),
                None => None,
            };
            (with, cf)
        }
    };
    let inst = &s.measurement;
    let mut rng = ChaCha8Rng::seed_from_u64(child_seed(
        seed_of(plan),
        Stream::Measurement,
        m.index as u64,
    ));
    let (lo, hi) = (inst.damping_min.ln(), inst.damping_max.ln());
    let damping: Vec<f64> = set
        .freq_hz
        .iter()
        .map(|_| (lo + (hi - lo) * rng.random::<f64>()).exp())
        .collect();
    let suspension_hz: Vec<f64> = (0..3)
        .map(|_| {
            inst.suspension_hz[0]
                + (inst.suspension_hz[1] - inst.suspension_hz[0]) * rng.random::<f64>()
        })
        .collect();
    let mut missing_nodes = Vec::new();
    let mut dropout_nodes = Vec::new();
    let reference_node = match m.setup {
        SetupKind::Free => HAMMER_POINT as i64 + 1,
        SetupKind::Bolted => SHAKER_REFERENCE_NODE,
    };
    for o in 0..points.len() + n_off {
        let (u1, u2): (f64, f64) = (rng.random(), rng.random());
        let node = o as i64 + 1;
        if node == reference_node {
            continue; // the hammer point always has its record
        }
        if u1 < inst.missing_point_prob {
            missing_nodes.push(node);
        } else if u2 < inst.dropout_point_prob {
            dropout_nodes.push(node);
        }
    }
    // Shaker cross-axis motion: the base rocks about the reference point by a_x, a_y
    // (rad per metre of reference motion), so antisymmetric modes show in the data too.
    let mut base_motion = Vec::new();
    let mut rocking = None;
    if m.setup == SetupKind::Bolted {
        let lx = models.points.iter().map(|p| p[0]).fold(0.0, f64::max);
        let ly = models.points.iter().map(|p| p[1]).fold(0.0, f64::max);
        let ax = inst.base_rocking_rel / lx * normal(&mut rng);
        let ay = inst.base_rocking_rel / ly * normal(&mut rng);
        let [xr, yr, _] = super::measure::SHAKER_REFERENCE_M;
        for (g, gr) in set.gamma.iter_mut().zip(&set.gamma_rock) {
            *g += ax * gr[0] + ay * gr[1];
        }
        base_motion = points
            .iter()
            .copied()
            .chain(
                grid.iter()
                    .flat_map(|g| g.off_board.iter().map(|p| [p[0], p[1]])),
            )
            .map(|p| 1.0 + ax * (p[0] - xr) + ay * (p[1] - yr))
            .collect();
        rocking = Some([ax, ay]);
    }
    let max_hz = match m.setup {
        SetupKind::Free => inst.free_max_hz,
        SetupKind::Bolted => inst.bolted_max_hz,
    };
    let pairing = cf.as_ref().map(|c| pair(&set, c));
    let modes = set
        .freq_hz
        .iter()
        .enumerate()
        .map(|(r, &f)| {
            let (f0, mac) = match &pairing {
                Some(pr) => match pr[r] {
                    Some((j, mac)) => (cf.as_ref().map(|c| c.freq_hz[j]), Some(mac)),
                    None => (None, None),
                },
                None => (Some(f), Some(1.0)),
            };
            let sh = &set.shapes[r];
            let rms = (sh.iter().map(|v| v * v).sum::<f64>() / sh.len().max(1) as f64).sqrt();
            let w = 2.0 * std::f64::consts::PI * f;
            let peak_magnitude_rms = match m.setup {
                SetupKind::Free => rms * sh[HAMMER_POINT].abs() / (2.0 * damping[r] * w),
                SetupKind::Bolted => rms * set.gamma[r].abs() / (2.0 * damping[r]),
            };
            ModeTruth {
                mode: r + 1,
                peak_magnitude_rms,
                freq_hz: f,
                damping_ratio: damping[r],
                in_band: f < max_hz,
                participation_z: set.gamma.get(r).copied(),
                freq_without_effects_hz: f0,
                shift_percent: f0.map(|f0| 100.0 * (f / f0 - 1.0)),
                mac_with_counterfactual: mac,
            }
        })
        .collect();
    let truth = MeasurementTruth {
        measurement_id: m.measurement_id.clone(),
        board_id: m.board_id.clone(),
        setup: m.setup,
        file: m.file.clone(),
        temperature_c: m.temperature_c,
        stiffness_factor: stiff,
        k_con_n_per_m: m.bolted.as_ref().map(|b| b.k_con_n_per_m),
        k_joint_n_per_m: m.bolted.as_ref().map(|b| b.k_joint_n_per_m.clone()),
        loose_joint: m.bolted.as_ref().and_then(|b| b.loose_joint.map(|j| j + 1)),
        bolt_set: m.bolted.as_ref().map(|b| b.bolt_set.clone()),
        modes,
        suspension_hz: if m.setup == SetupKind::Free {
            suspension_hz
        } else {
            vec![]
        },
        missing_nodes,
        dropout_nodes,
        reference_node,
        base_rocking_rad_per_m: rocking,
    };
    // Points off the board (a bolt head, the fixture) have no board mode in them: they move
    // with the base only.
    for sh in &mut set.shapes {
        sh.extend(std::iter::repeat_n(0.0, n_off));
    }
    Ok(MeasurementModes {
        truth,
        set,
        damping,
        base_motion,
    })
}

fn seed_of(plan: &Plan) -> u64 {
    plan.seed
}

/// One board's truth.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BoardTruth {
    #[serde(flatten)]
    pub draw: BoardDraw,
    /// Mass of the board itself (FR-4 and copper), kg.
    pub board_mass_kg: f64,
    /// What the balance weighs: the board plus any unmodelled lumped mass, kg.
    pub weighed_mass_kg: f64,
    /// Free-free elastic frequencies of the truth model at the reference state, Hz.
    pub free_freq_hz: Vec<f64>,
}

/// The population the boards were drawn from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PopulationTruth {
    pub parameters: [String; 4],
    pub mean: [f64; 4],
    pub rel_std: [f64; 4],
    pub correlation: [[f64; 4]; 4],
    /// Covariance in the parameters' units, Σ_ij = σ_i σ_j ρ_ij.
    pub covariance: [[f64; 4]; 4],
    pub k_con_mean_n_per_m: f64,
    pub k_con_rel_std: f64,
}

/// Everything behind the campaign that the campaign directory does not contain.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Truth {
    pub scenario_name: String,
    pub seed: u64,
    pub board_name: String,
    /// How the truth model differs from the updating model, in words.
    pub truth_model: String,
    pub population: PopulationTruth,
    pub boards: Vec<BoardTruth>,
    pub measurements: Vec<MeasurementTruth>,
    /// The concealed effects (all five, each with `enabled`) and what a correct diagnosis says.
    pub effects: Vec<super::effects::EffectTruth>,
    /// Plain-words summary of the hidden physics of the campaign.
    pub summary: String,
    /// Deliberate imperfection of the balance logs: garbled lines, `file:line` (1-based).
    pub garbled_balance_lines: Vec<String>,
    /// The updating model's misfit to the truth model at the population mean.
    pub model_misfit: ModelMisfit,
    /// The scenario as simulated.
    pub scenario: Scenario,
    /// Where the lab's habits left their marks (absent when none is on).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub habits: Option<super::habits::HabitsTruth>,
}

/// How far the truth model lies from the updating model (the board's default mesh,
/// baseline joint) at the population mean: board nominal parameters, the same K_con
/// K̄ in both (K_con is the joint's physical total stiffness on any mesh, so no mapping
/// between meshes is needed), no concealed effect. The rest is what makes the truth
/// richer: its finer mesh, its per-joint stiffnesses and any bolt mass on the patches.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelMisfit {
    /// Updating model assumed: the board's default mesh, baseline joint (one K_con).
    pub updating_mesh: [usize; 2],
    /// The updating model's bolted mesh (the board's `mesh_bolted`, else its mesh).
    pub updating_mesh_bolted: [usize; 2],
    /// Relative misfit of the bolted in-band frequencies, updating vs truth, % (empty when
    /// nothing is measured bolted).
    pub bolted_misfit_percent: Vec<f64>,
    /// Relative misfit of the free-free in-band frequencies, updating vs truth, %.
    pub free_misfit_percent: Vec<f64>,
}

/// The updating model's misfit to the truth model at the population mean (two
/// eigen-solves of each).
pub fn model_misfit(s: &Scenario, board: &Board, models: &Models) -> Result<ModelMisfit, LabError> {
    if models.solid.is_some() {
        return solid_model_misfit(s, board, models);
    }
    let bolted_misfit_percent = match &models.bolted {
        None => vec![],
        Some(bolted) => {
            let plain = models.bolted_cf.as_ref().unwrap_or(bolted);
            let k_bar = s.population.k_con_mean_n_per_m;
            let mut pt = plain.nominal_params();
            for j in 0..board.holes.len() {
                pt.set(&names::k_con_joint(j + 1), k_bar)?;
            }
            let truth = plain.modes(&pt, s.truth.n_bolted_modes)?;
            let upd = FeModel::build(board, Setup::bolted(), board.mesh_for(&Setup::bolted()))?;
            let mut p = upd.nominal_params();
            p.set(names::K_CON, k_bar)?;
            let fu = upd.modes(&p, s.truth.n_bolted_modes)?.freq_hz;
            fu.iter()
                .zip(&truth.freq_hz)
                .filter(|(_, b)| **b < s.measurement.bolted_max_hz)
                .map(|(a, b)| 100.0 * (a / b - 1.0))
                .collect()
        }
    };
    let uf = FeModel::build(board, Setup::Free, &board.mesh)?;
    let fu = uf.modes(&uf.nominal_params(), 8)?.freq_hz;
    let ftf = models.free_cf.as_ref().unwrap_or(&models.free);
    let ft = ftf.modes(&ftf.nominal_params(), 8)?.freq_hz;
    let free_misfit_percent = fu
        .iter()
        .zip(&ft)
        .filter(|(_, b)| **b < s.measurement.free_max_hz)
        .map(|(a, b)| 100.0 * (a / b - 1.0))
        .collect();
    Ok(ModelMisfit {
        updating_mesh: [board.mesh.nx, board.mesh.ny],
        updating_mesh_bolted: {
            let m = board.mesh_for(&Setup::bolted());
            [m.nx, m.ny]
        },
        bolted_misfit_percent,
        free_misfit_percent,
    })
}

/// [`model_misfit`] for the solid truth: both models' modes at the nominal board and K̄ on
/// every joint, paired by MAC on the scan grid (the solid's mode order can differ from the
/// plate's), one figure per in-band truth mode (`NaN`, `null` in the JSON, where no updating
/// mode pairs).
fn solid_model_misfit(
    s: &Scenario,
    board: &Board,
    models: &Models,
) -> Result<ModelMisfit, LabError> {
    let c = &board.core;
    let nominal = BoardDraw {
        board_id: "nominal".into(),
        e_x_pa: c.e_x_pa,
        e_y_pa: c.e_y_pa,
        g_xy_pa: c.g_xy_pa,
        mass_scale: 1.0,
        deviation_rel: [0.0; 4],
        core_thickness_m: c.thickness_m,
    };
    let k_bar = s.population.k_con_mean_n_per_m;
    let misfit = |truth: &ModeSet, upd: &ModeSet, max_hz: f64| -> Vec<f64> {
        let pairs = pair(truth, upd);
        truth
            .freq_hz
            .iter()
            .zip(pairs)
            .filter(|(f, _)| **f < max_hz)
            .map(|(f, p)| p.map_or(f64::NAN, |(j, _)| 100.0 * (upd.freq_hz[j] / f - 1.0)))
            .collect()
    };
    let uf = FeModel::build(board, Setup::Free, &board.mesh)?;
    let upd_free = mode_set(
        &uf,
        &uf.nominal_params(),
        s.truth.n_free_modes + 2,
        &models.points,
    )?;
    let truth_free = modes_of(
        s,
        models,
        Variant::FreeCf,
        &nominal,
        1.0,
        None,
        false,
        &models.points,
    )?;
    let free_misfit_percent = misfit(&truth_free, &upd_free, s.measurement.free_max_hz);
    let bolted_misfit_percent = match models.solid.as_ref().and_then(|m| m.bolted.as_ref()) {
        Some(_) => {
            let bo = BoltedDraw {
                k_con_n_per_m: k_bar,
                k_joint_n_per_m: vec![k_bar; board.holes.len()],
                loose_joint: None,
                bolt_set: String::new(),
            };
            let truth = modes_of(
                s,
                models,
                Variant::BoltedCf,
                &nominal,
                1.0,
                Some(&bo),
                false,
                &models.points,
            )?;
            let upd = FeModel::build(board, Setup::bolted(), board.mesh_for(&Setup::bolted()))?;
            let mut p = upd.nominal_params();
            p.set(names::K_CON, k_bar)?;
            let um = mode_set(&upd, &p, s.truth.n_bolted_modes + 2, &models.points)?;
            misfit(&truth, &um, s.measurement.bolted_max_hz)
        }
        None => vec![],
    };
    Ok(ModelMisfit {
        updating_mesh: [board.mesh.nx, board.mesh.ny],
        updating_mesh_bolted: {
            let m = board.mesh_for(&Setup::bolted());
            [m.nx, m.ny]
        },
        bolted_misfit_percent,
        free_misfit_percent,
    })
}

/// Put the truth together.
pub fn assemble(
    s: &Scenario,
    board: &Board,
    plan: &Plan,
    cache: &FreeCache,
    measurements: Vec<MeasurementTruth>,
    model_misfit: ModelMisfit,
) -> Truth {
    let c = &board.core;
    let mean = [c.e_x_pa, c.e_y_pa, c.g_xy_pa, 1.0];
    let p = &s.population;
    let sd: [f64; 4] = std::array::from_fn(|i| p.rel_std[i] * mean[i]);
    let covariance =
        std::array::from_fn(|i| std::array::from_fn(|j| sd[i] * sd[j] * p.correlation[i][j]));
    let boards = plan
        .boards
        .iter()
        .enumerate()
        .map(|(b, d)| {
            let with = &cache.with[b];
            let plain = cache.without[b].as_ref().unwrap_or(with);
            BoardTruth {
                draw: d.clone(),
                board_mass_kg: plain.total_mass_kg,
                weighed_mass_kg: with.total_mass_kg,
                free_freq_hz: with.freq_hz.clone(),
            }
        })
        .collect();
    let effects = super::effects::describe(s, &measurements);
    let summary = super::effects::summary(&effects);
    Truth {
        scenario_name: s.name.clone(),
        seed: plan.seed,
        board_name: board.name.clone(),
        truth_model: match s.truth.physics {
            Physics::Plate => format!(
            "board on a {}x{} BFS mesh, bolted {}x{} (updating {}x{}, bolted {}x{}), holes as cut cells; \
             bolted: one contact stiffness per joint (K_con of the measurement scattered by {:.1} % per joint) \
             as a spring layer over each clamped annulus, {:.2} g of each bolt spread over the annulus; copper pattern as in the board file",
            s.truth.mesh_nx,
            s.truth.mesh_ny,
            truth_bolted_mesh(s, board).nx,
            truth_bolted_mesh(s, board).ny,
            board.mesh.nx,
            board.mesh.ny,
            board.mesh_for(&Setup::bolted()).nx,
            board.mesh_for(&Setup::bolted()).ny,
            100.0 * s.truth.per_joint_k_rel_std,
            1e3 * s.truth.joint_mass_kg
        ) + &if s.population.thickness_rel_std > 0.0 {
            format!(
                "; FR-4 core thickness per board (scattered by {:.1} % around the board file's, see boards' core_thickness_m)",
                100.0 * s.population.thickness_rel_std
            )
        } else {
            String::new()
        },
            Physics::Solid => format!(
                "layered 3D solid (CalculiX C3D20, {} brick(s) through the FR-4 core, one per copper layer where copper lies) on a gmsh quadrilateral mesh of {:.2} mm conforming to the outline, holes, copper regions and clamped annuli; FR-4 through-thickness E_z {:.1} GPa, G_xz/G_yz {:.2}/{:.2} GPa; bolted: each clamped annulus's bottom face on z springs (the joint's stiffness spread by area; K_con of the measurement scattered by {:.1} % per joint) and on in-plane springs (Mindlin's tangential share), {:.2} g of screw head and washer on its top face",
                s.truth.solid.core_layers,
                1e3 * s.truth.solid.element_size_m,
                1e-9 * s.truth.solid.e_z_pa,
                1e-9 * s.truth.solid.g_xz_pa,
                1e-9 * s.truth.solid.g_yz_pa,
                100.0 * s.truth.per_joint_k_rel_std,
                1e3 * s.truth.solid.riding_mass_kg
            ),
        },
        population: PopulationTruth {
            parameters: [
                names::E_X.to_string(),
                names::E_Y.to_string(),
                names::G_XY.to_string(),
                names::MASS_SCALE.to_string(),
            ],
            mean,
            rel_std: p.rel_std,
            correlation: p.correlation,
            covariance,
            k_con_mean_n_per_m: p.k_con_mean_n_per_m,
            k_con_rel_std: p.k_con_rel_std,
        },
        boards,
        measurements,
        effects,
        summary,
        garbled_balance_lines: Vec::new(),
        model_misfit,
        scenario: s.clone(),
        habits: None,
    }
}

//! The library of physical mechanisms the diagnosis can propose: each is an enrichment of
//! the model with few parameters, physical priors and a plain-language description.
//!
//! A joint mechanism enriches step 2 (the bolted joints): the joint model gains features
//! ([`JointFeature`]) and every bolted measurement (a step-2 unit) gains coordinates.
//! A unit's coordinates act on the ROM's parameters log-linearly:
//! p_i = ref_i · exp(Σ_k a_ik x_k), so a coordinate can move several parameters (one
//! joint stiffness for all joints) and a parameter can follow several coordinates (the
//! fixture's spring k = m (2π f)² follows ln m and ln f). Coordinate 0 is always
//! ln(k_con / k_con,nominal), the baseline's, so the baseline is the enrichment with no
//! extra coordinate and every refit nests it.
//!
//! Priors are physical, never fitted to the data being diagnosed (the Bayes factors would
//! otherwise be biased towards the enrichment):
//! - `joint_rotation`: the rotational stiffness a uniform contact layer of the joint's own
//!   nominal stiffness would have over the clamped annulus, k_rot = k_con (r_o² + r_i²)/4
//!   (∫ r² cos²θ dA / A over the annulus), with a log-sd of 1.5: the contact pressure is far
//!   from uniform (a clamped patch is stiffer at the rim), so only the order of magnitude is
//!   known;
//! - `joint_mass`: the bolt's mass from the board file (bolt, nut and washers), log-sd 1;
//! - `fixture_compliance`: fixture mass 0.1 kg with a log-sd of 1.5 (5 g to 2 kg at 2 sd),
//!   and its own resonance at 1.5 × the top of the measured band (a fixture is designed to
//!   resonate above the band; at the band top it would sit on the highest measured mode,
//!   where the two hybridise and no draw near the prior's centre could be evaluated) with a
//!   log-sd of 1;
//! - `joint_stiffness_per_joint`: the stiffness ratio of one joint to the others, centred on
//!   1 with a log-sd of 0.7 (a loose bolt halves it, a missing washer doubles it); without a
//!   joint named, every joint's ratio at once, per measurement (the bolt that is loose may
//!   differ between assemblies).
//!
//! A board mechanism enriches step 1 (free-free): `temperature_stiffness` scales the FR-4
//! moduli (E_x, E_y, G_xy) of every measurement by 1 + β (c − c_ref), c the sheet's
//! covariate (temperature) and β one global coefficient ([`BoardEnrichment`]), prior
//! N(0, (0.5 %/K)²): epoxy-glass laminates below their glass transition lose about 0.05–0.5 %
//! of their moduli per kelvin, so the prior covers that range within about one sd either
//! way without fixing the sign. `added_mass` adds a lumped mass at the located point whose
//! value is a per-board model parameter (`added_mass_kg`, [`BoardEffect::PointMass`]).

use serde::Serialize;

use crate::fem::joints::{JointFeature, JointModel};
use crate::fem::params::names;
use crate::fem::Board;

/// The mechanism ids of the diagnosis (the list, in findings as `mechanism`).
#[derive(
    Clone,
    Copy,
    Debug,
    PartialEq,
    Eq,
    PartialOrd,
    Ord,
    Serialize,
    serde::Deserialize,
    schemars::JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum Mechanism {
    JointRotation,
    JointStiffnessPerJoint,
    JointMass,
    FixtureCompliance,
    TemperatureStiffness,
    AddedMass,
    LocalStiffnessLoss,
    Prestress,
}

impl Mechanism {
    pub const ALL: [Mechanism; 8] = [
        Mechanism::JointRotation,
        Mechanism::JointStiffnessPerJoint,
        Mechanism::JointMass,
        Mechanism::FixtureCompliance,
        Mechanism::TemperatureStiffness,
        Mechanism::AddedMass,
        Mechanism::LocalStiffnessLoss,
        Mechanism::Prestress,
    ];

    /// The id as written in `diagnosis.json`.
    pub fn id(self) -> &'static str {
        match self {
            Mechanism::JointRotation => "joint_rotation",
            Mechanism::JointStiffnessPerJoint => "joint_stiffness_per_joint",
            Mechanism::JointMass => "joint_mass",
            Mechanism::FixtureCompliance => "fixture_compliance",
            Mechanism::TemperatureStiffness => "temperature_stiffness",
            Mechanism::AddedMass => "added_mass",
            Mechanism::LocalStiffnessLoss => "local_stiffness_loss",
            Mechanism::Prestress => "prestress",
        }
    }

    /// The mechanism of an id as written in `diagnosis.json` (and on the command line).
    pub fn from_id(id: &str) -> Option<Mechanism> {
        Mechanism::ALL.into_iter().find(|m| m.id() == id)
    }

    /// The physics in plain words.
    pub fn description(self) -> &'static str {
        match self {
            Mechanism::JointRotation => "the bolted joints restrain the board's rotation (they transmit bending moment), not only its out-of-plane motion",
            Mechanism::JointStiffnessPerJoint => "one joint is weaker or stiffer than the others (a loose bolt, a missing washer)",
            Mechanism::JointMass => "the joints add mass (bolt, nut, washers moving with the board)",
            Mechanism::FixtureCompliance => "the shaker fixture is not rigid: a mass on a spring between the armature and the bolts",
            Mechanism::TemperatureStiffness => "the FR-4 stiffness changes with the lab temperature",
            Mechanism::AddedMass => "a localized mass on the board that the model lacks (a component, glue, a connector)",
            Mechanism::LocalStiffnessLoss => "the board is locally less stiff than modelled (damage, a cut-out, delamination)",
            Mechanism::Prestress => "in-plane prestress from the clamping force",
        }
    }
}

/// One coordinate of a step-2 unit: its name, the ROM parameters it moves with their
/// exponents, and its prior N(0, prior_sd²) on the population mean (relative to the
/// reference values).
#[derive(Clone, Debug, Serialize)]
pub struct Coordinate {
    /// e.g. `ln_k_rot` (population columns are `mu_<name>`, `sigma_<name>`).
    pub name: String,
    /// The parameter the coordinate is reported as (unit in its name): report_ref · e^x.
    pub report_param: String,
    pub report_ref: f64,
    /// Unit of `report_param`.
    pub report_unit: String,
    /// (ROM parameter name, exponent a_ik).
    pub acts_on: Vec<(String, f64)>,
    /// Prior sd of the population mean, in ln units.
    pub prior_sd: f64,
    /// Half-width in ln units of the ROM's box along the parameters it moves beyond the
    /// baseline's ±20 % (`None`: the baseline box).
    pub log_box: Option<f64>,
}

/// A step-2 enrichment: the joint model, the reference values of the parameters the
/// coordinates move (the prior centres), and the coordinates. `joint` = the joint
/// (1-based) of `joint_stiffness_per_joint`.
#[derive(Clone, Debug, Serialize)]
pub struct JointEnrichment {
    pub mechanism: Option<Mechanism>,
    pub joint: Option<usize>,
    pub joint_model: JointModel,
    /// (ROM parameter name, reference value) for every parameter a coordinate moves.
    pub reference: Vec<(String, f64)>,
    pub coordinates: Vec<Coordinate>,
}

/// `joint_stiffness_per_joint` with every joint its own contrast: the mechanism with no
/// joint named.
pub fn is_every_joint(mechanism: Option<Mechanism>, joint: Option<usize>) -> bool {
    mechanism == Some(Mechanism::JointStiffnessPerJoint) && joint.is_none()
}

impl JointEnrichment {
    /// [`is_every_joint`] of this enrichment.
    pub fn every_joint(&self) -> bool {
        is_every_joint(self.mechanism, self.joint)
    }

    /// One unit's coordinates as reported (joints.parquet): report_ref · e^x, except the
    /// contrasts of [`Self::every_joint`], reported as each joint's stiffness over the mean
    /// of the others' in that measurement, k_j / mean_{i≠j} k_i (x_0 cancels). With one
    /// joint named, e^x of its coordinate is that ratio already.
    pub fn report_values(&self, x: &[f64]) -> Vec<f64> {
        if !self.every_joint() {
            return self
                .coordinates
                .iter()
                .zip(x)
                .map(|(c, v)| c.report_ref * v.exp())
                .collect();
        }
        let e: Vec<f64> = x[1..].iter().map(|v| v.exp()).collect();
        let (sum, others) = (e.iter().sum::<f64>(), (e.len() - 1) as f64);
        let mut out = vec![self.coordinates[0].report_ref * x[0].exp()];
        out.extend(e.iter().map(|&k| k * others / (sum - k)));
        out
    }
}

/// A step-1 enrichment: the mechanism, what it adds to the board model, and the prior of
/// its per-board coordinate's population mean, N(prior_mean, prior_sd²) (board-to-board sd
/// half-normal with a fifth of prior_sd as its scale).
#[derive(Clone, Debug, Serialize)]
pub struct BoardEnrichment {
    pub mechanism: Mechanism,
    pub effect: BoardEffect,
    pub prior_mean: f64,
    pub prior_sd: f64,
}

/// What a step-1 enrichment adds to the board model.
#[derive(Clone, Debug, Serialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum BoardEffect {
    /// A covariate c of every measurement scales `scaled` (ROM parameter names) by
    /// 1 + β (c − c_ref); β, the board's coordinate, is absolute (`coefficient`, unit in the
    /// name, a boards.parquet column).
    Covariate {
        coefficient: String,
        scaled: Vec<String>,
    },
    /// A lumped mass at (x_m, y_m) that the board file lacks: a model parameter
    /// `parameter` (kg) whose board coordinate is ln(m / reference_kg), on a logarithmic
    /// ROM axis of half-width `log_box`.
    PointMass {
        parameter: String,
        x_m: f64,
        y_m: f64,
        reference_kg: f64,
        log_box: f64,
    },
}

/// What a step-1 enrichment needs to know: the board model's nominal mass (the prior scale
/// of an added mass) and the located point of a point mechanism.
#[derive(Clone, Copy, Debug)]
pub struct BoardContext {
    pub board_mass_kg: f64,
    pub location_m: Option<[f64; 2]>,
}

/// The boards.parquet column of the `temperature_stiffness` coefficient.
pub const TEMPERATURE_COEFFICIENT: &str = "temperature_coefficient_per_k";

/// The model parameter of the `added_mass` refit, kg.
pub const ADDED_MASS: &str = "added_mass_kg";

/// The step-1 model of a board mechanism; errors name the mechanisms that have one and what
/// they need.
///
/// `added_mass`: the prior median is 1 % of the board's nominal mass with a log-sd of 1.5
/// (0.05 % to 20 % of the board at 2 sd: a glue blob to a connector or a shielding can),
/// so the prior is set by the board, never by the mass the localisation fitted. The ROM's
/// axis spans e^±4.5 (3 prior sd); over it the ROM's worst frequency error is 7e-6
/// (`point_mass_parameter_is_the_point_mass_and_a_log_axis_rom_follows_it`).
pub fn board_enrichment(
    mechanism: Mechanism,
    ctx: BoardContext,
) -> Result<BoardEnrichment, String> {
    match mechanism {
        Mechanism::TemperatureStiffness => Ok(BoardEnrichment {
            mechanism,
            effect: BoardEffect::Covariate {
                coefficient: TEMPERATURE_COEFFICIENT.into(),
                scaled: vec![names::E_X.into(), names::E_Y.into(), names::G_XY.into()],
            },
            prior_mean: 0.0,
            prior_sd: 0.005,
        }),
        Mechanism::AddedMass => {
            let [x_m, y_m] = ctx
                .location_m
                .ok_or("added_mass needs its location (--enrich-location X_M,Y_M)")?;
            if !(ctx.board_mass_kg.is_finite() && ctx.board_mass_kg > 0.0) {
                return Err(format!(
                    "added_mass: expected a positive board mass, found {} kg",
                    ctx.board_mass_kg
                ));
            }
            Ok(BoardEnrichment {
                mechanism,
                effect: BoardEffect::PointMass {
                    parameter: ADDED_MASS.into(),
                    x_m,
                    y_m,
                    reference_kg: 0.01 * ctx.board_mass_kg,
                    log_box: 4.5,
                },
                prior_mean: 0.0,
                prior_sd: 1.5,
            })
        }
        m => Err(format!(
            "{} has no step-1 refit (board mechanisms: temperature_stiffness, added_mass)",
            m.id()
        )),
    }
}

/// Whether a column of boards.parquet is a board enrichment's coefficient (not a model
/// parameter).
pub fn is_board_coefficient(column: &str) -> bool {
    column == TEMPERATURE_COEFFICIENT
}

/// Whether the mechanism's refit is a step-1 (board) refit rather than a step-2 one.
pub fn is_board_mechanism(m: Mechanism) -> bool {
    matches!(m, Mechanism::TemperatureStiffness | Mechanism::AddedMass)
}

/// What the enrichment needs to know of the campaign: the highest paired bolted frequency
/// (the fixture's prior resonance sits at the top of the band).
#[derive(Clone, Copy, Debug)]
pub struct JointContext {
    pub band_top_hz: f64,
    /// Prior sd of the baseline's ln k_con population mean.
    pub k_con_prior_sd: f64,
}

fn k_con_coordinate(acts_on: Vec<(String, f64)>, k0: f64, prior_sd: f64) -> Coordinate {
    Coordinate {
        name: "ln_k_con".into(),
        report_param: names::K_CON.into(),
        report_ref: k0,
        report_unit: "N/m".into(),
        acts_on,
        prior_sd,
        log_box: None,
    }
}

/// The step-2 model of `mechanism` (`None`: the baseline). Errors name what the board
/// lacks (e.g. no holes for a per-joint model).
pub fn joint_enrichment(
    board: &Board,
    mechanism: Option<Mechanism>,
    joint: Option<usize>,
    ctx: JointContext,
) -> Result<JointEnrichment, String> {
    let k0 = board.joint().k_con_n_per_m;
    let mut reference = vec![(names::K_CON.to_string(), k0)];
    let mut coords = vec![k_con_coordinate(
        vec![(names::K_CON.into(), 1.0)],
        k0,
        ctx.k_con_prior_sd,
    )];
    let mut features = vec![JointFeature::Translational];
    match mechanism {
        None => {}
        Some(Mechanism::JointRotation) => {
            let r_o = 0.5 * board.joint().clamp_diameter_m;
            let r_i = board
                .holes
                .first()
                .map(|h| 0.5 * h.diameter_m)
                .unwrap_or(0.0)
                .min(r_o);
            let k_rot = k0 * (r_o * r_o + r_i * r_i) / 4.0;
            features.push(JointFeature::RotationalRestraint {
                k_rot_nm_per_rad: k_rot,
            });
            reference.push((names::K_ROT.into(), k_rot));
            coords.push(Coordinate {
                name: "ln_k_rot".into(),
                report_param: names::K_ROT.into(),
                report_ref: k_rot,
                report_unit: "N·m/rad".into(),
                acts_on: vec![(names::K_ROT.into(), 1.0)],
                prior_sd: 1.5,
                log_box: Some(4.5),
            });
        }
        Some(Mechanism::JointMass) => {
            let m = if board.joint().bolt_mass_kg > 0.0 {
                board.joint().bolt_mass_kg
            } else {
                1e-3
            };
            features.push(JointFeature::JointMass { mass_kg: m });
            reference.push((names::JOINT_MASS.into(), m));
            coords.push(Coordinate {
                name: "ln_joint_mass".into(),
                report_param: names::JOINT_MASS.into(),
                report_ref: m,
                report_unit: "kg".into(),
                acts_on: vec![(names::JOINT_MASS.into(), 1.0)],
                prior_sd: 1.0,
                log_box: Some(3.0),
            });
        }
        Some(Mechanism::FixtureCompliance) => {
            let m = 0.1;
            // The prior's resonance: 1.5 × the band top (a fixture is designed to resonate
            // above the band; at the band top itself it would sit on the highest measured
            // mode, where the two hybridise and the mode cannot be tracked).
            let f0 = 1.5 * ctx.band_top_hz;
            let w = 2.0 * std::f64::consts::PI * f0;
            let k = m * w * w;
            features.push(JointFeature::CompliantFixture {
                k_fix_n_per_m: k,
                m_fix_kg: m,
            });
            reference.push((names::M_FIX.into(), m));
            reference.push((names::K_FIX.into(), k));
            coords.push(Coordinate {
                name: "ln_m_fix".into(),
                report_param: names::M_FIX.into(),
                report_ref: m,
                report_unit: "kg".into(),
                acts_on: vec![(names::M_FIX.into(), 1.0), (names::K_FIX.into(), 1.0)],
                prior_sd: 1.5,
                log_box: Some(4.5),
            });
            coords.push(Coordinate {
                name: "ln_f_fix".into(),
                report_param: "f_fix_hz".into(),
                report_ref: f0,
                report_unit: "Hz".into(),
                acts_on: vec![(names::K_FIX.into(), 2.0)],
                prior_sd: 1.0,
                log_box: Some(3.0),
            });
        }
        Some(Mechanism::JointStiffnessPerJoint) => {
            let n = board.holes.len();
            if n < 2 {
                return Err(format!(
                    "joint_stiffness_per_joint: the board has {n} joint(s); one joint against the others needs at least 2"
                ));
            }
            features = vec![JointFeature::PerJointTranslational];
            reference = (1..=n).map(|i| (names::k_con_joint(i), k0)).collect();
            coords = vec![k_con_coordinate(
                (1..=n).map(|i| (names::k_con_joint(i), 1.0)).collect(),
                k0,
                ctx.k_con_prior_sd,
            )];
            match joint {
                Some(j) => {
                    if j == 0 || j > n {
                        return Err(format!(
                            "joint_stiffness_per_joint: expected a joint in 1..={n}, found {j}"
                        ));
                    }
                    coords.push(Coordinate {
                        name: format!("ln_k_ratio_{j}"),
                        report_param: format!("k_ratio_{j}"),
                        report_ref: 1.0,
                        report_unit: String::new(),
                        acts_on: vec![(names::k_con_joint(j), 1.0)],
                        prior_sd: 0.7,
                        log_box: Some(2.1),
                    });
                }
                None => {
                    // Every joint its own stiffness in every measurement (the bolt that is
                    // loose may differ between assemblies): a centred contrast per joint,
                    // ln k_i = x_0 + r_i − r̄, so x_0 stays the joints' mean (geometric)
                    // stiffness and the likelihood sees only the contrasts; their common
                    // part r̄ is left to the prior (nothing in the data moves it). The
                    // contrasts' half-width 1.4 (e^−1.4 = 0.25: a bolt at a quarter of the
                    // others') makes each joint's ROM axis 1 + 2 (n−1)/n · 1.4, 3.1 for four
                    // joints, the single-joint refit's.
                    let inv = 1.0 / n as f64;
                    for j in 1..=n {
                        coords.push(Coordinate {
                            name: format!("ln_k_contrast_{j}"),
                            report_param: format!("k_ratio_{j}"),
                            report_ref: 1.0,
                            report_unit: String::new(),
                            acts_on: (1..=n)
                                .map(|i| {
                                    let a = if i == j { 1.0 - inv } else { -inv };
                                    (names::k_con_joint(i), a)
                                })
                                .collect(),
                            prior_sd: 0.7,
                            log_box: Some(1.4),
                        });
                    }
                }
            }
        }
        Some(m) => {
            return Err(format!(
                "{} is not a joint mechanism: it has no step-2 refit",
                m.id()
            ))
        }
    }
    // The joint stiffness varies between measurements (re-assembly, torque) by far more than
    // a ±20 % box around one centre covers, and trades off against an enrichment (k_con
    // against k_rot, a loose joint against the others) along ridges the posterior follows:
    // its ROM axis is logarithmic, e^±1 around the fitted centre, in the baseline and in
    // every enrichment alike (so their evidences rest on the same treatment of k_con).
    coords[0].log_box = Some(1.0);
    Ok(JointEnrichment {
        mechanism,
        joint,
        joint_model: JointModel { features },
        reference,
        coordinates: coords,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn board() -> Board {
        crate::fem::Board::from_toml_str(include_str!("../../data/boards/default.toml")).unwrap()
    }

    #[test]
    fn baseline_is_one_k_con_coordinate_and_enrichments_nest_it() {
        let b = board();
        let ctx = JointContext {
            band_top_hz: 3000.0,
            k_con_prior_sd: 1.0,
        };
        let base = joint_enrichment(&b, None, None, ctx).unwrap();
        assert_eq!(base.coordinates.len(), 1);
        assert_eq!(base.joint_model, JointModel::baseline());
        for m in [
            Mechanism::JointRotation,
            Mechanism::JointMass,
            Mechanism::FixtureCompliance,
        ] {
            let e = joint_enrichment(&b, Some(m), None, ctx).unwrap();
            assert_eq!(e.coordinates[0].name, "ln_k_con");
            assert!(e.coordinates.len() > 1);
            e.joint_model.validate().unwrap();
        }
        let e =
            joint_enrichment(&b, Some(Mechanism::JointStiffnessPerJoint), Some(2), ctx).unwrap();
        assert_eq!(e.coordinates[0].acts_on.len(), b.holes.len());
        assert!(
            joint_enrichment(&b, Some(Mechanism::JointStiffnessPerJoint), Some(9), ctx).is_err()
        );
        assert!(joint_enrichment(&b, Some(Mechanism::AddedMass), None, ctx).is_err());
    }

    #[test]
    fn every_joint_contrasts_leave_the_mean_stiffness_and_report_ratios_to_the_others() {
        let b = board();
        let ctx = JointContext {
            band_top_hz: 3000.0,
            k_con_prior_sd: 1.0,
        };
        let e = joint_enrichment(&b, Some(Mechanism::JointStiffnessPerJoint), None, ctx).unwrap();
        let n = b.holes.len();
        assert!(e.every_joint());
        assert_eq!(e.coordinates.len(), 1 + n);
        // ln k_i = Σ_k a_ik x_k: the contrasts move no joint's mean, so equal contrasts
        // change nothing and x_0 is the joints' mean ln stiffness.
        let ln_k = |x: &[f64]| -> Vec<f64> {
            (1..=n)
                .map(|i| {
                    let p = names::k_con_joint(i);
                    e.coordinates
                        .iter()
                        .zip(x)
                        .map(|(c, v)| {
                            c.acts_on
                                .iter()
                                .filter(|(q, _)| *q == p)
                                .map(|(_, a)| a * v)
                                .sum::<f64>()
                        })
                        .sum()
                })
                .collect()
        };
        let mut x = vec![0.3; 1 + n];
        let k = ln_k(&x);
        assert!(k.iter().all(|v| (v - 0.3).abs() < 1e-12), "{k:?}");
        // Joint 2 at half the others: its ratio is 0.5, the others' (1 / mean of the rest).
        x[2] += 0.5f64.ln();
        let k = ln_k(&x);
        let mean_ln = k.iter().sum::<f64>() / n as f64;
        assert!((mean_ln - 0.3).abs() < 1e-12);
        let r = e.report_values(&x);
        assert!((r[0] - b.joint().k_con_n_per_m * 0.3f64.exp()).abs() < 1e-6 * r[0]);
        let kk: Vec<f64> = k.iter().map(|v| v.exp()).collect();
        for j in 0..n {
            let others: f64 = kk
                .iter()
                .enumerate()
                .filter(|(i, _)| *i != j)
                .map(|(_, v)| v)
                .sum::<f64>()
                / (n - 1) as f64;
            assert!((r[1 + j] - kk[j] / others).abs() < 1e-12, "{j}: {r:?}");
        }
        assert!((r[2] - 0.5).abs() < 1e-12);
        // A single joint named reports e^x: the ratio of that joint to the others.
        let one =
            joint_enrichment(&b, Some(Mechanism::JointStiffnessPerJoint), Some(3), ctx).unwrap();
        assert!(!one.every_joint());
        assert!((one.report_values(&[0.0, 0.5f64.ln()])[1] - 0.5).abs() < 1e-12);
    }

    #[test]
    fn fixture_reference_resonance_is_above_the_band_top() {
        let b = board();
        let ctx = JointContext {
            band_top_hz: 2500.0,
            k_con_prior_sd: 1.0,
        };
        let e = joint_enrichment(&b, Some(Mechanism::FixtureCompliance), None, ctx).unwrap();
        let get = |n: &str| e.reference.iter().find(|(a, _)| a == n).unwrap().1;
        let f = (get(names::K_FIX) / get(names::M_FIX)).sqrt() / (2.0 * std::f64::consts::PI);
        assert!((f - 3750.0).abs() < 1e-9);
        let fc = e.coordinates.iter().find(|c| c.name == "ln_f_fix").unwrap();
        assert_eq!(fc.report_ref, 3750.0);
    }
}

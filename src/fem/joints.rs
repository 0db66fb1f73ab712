//! The bolted-joint family. A joint ties the board to the shaker fixture over the
//! clamped annulus around its hole (the bolt-head / washer / nut contact, outer
//! diameter `joint.clamp_diameter_m`): every mesh node of the board inside that disc
//! belongs to the joint's patch, and a joint's stiffness or mass is shared equally by
//! its patch nodes. The bolts are rigid and move with the fixture, so their own mass
//! does not enter the fixed-base modes (it enters only through [`JointFeature::JointMass`]).
//!
//! Features combine; each adds affine terms and parameters:
//! - [`JointFeature::Translational`] (the paper's baseline): out-of-plane springs of total
//!   stiffness K_con (`k_con_n_per_m`, head and nut contacts in parallel) per joint;
//! - [`JointFeature::PerJointTranslational`]: the same with one `k_con_{j}_n_per_m` per joint;
//! - [`JointFeature::RotationalRestraint`]: springs on ∂w/∂x and ∂w/∂y of the patch
//!   nodes, total `k_rot_nm_per_rad` per joint and axis;
//! - [`JointFeature::JointMass`]: a lumped z-mass `joint_mass_kg` per joint on its patch;
//! - [`JointFeature::CompliantFixture`]: the fixture becomes one z-DOF with mass
//!   `m_fix_kg` on a spring `k_fix_n_per_m` to the (rigid, moving) base; joint springs
//!   then attach to the fixture DOF instead of the base.
//!
//! Not built yet: prestress (geometric stiffness from the clamping force); its hook is
//! an extra affine stiffness term here once the membrane state is modelled.

use serde::{Deserialize, Serialize};

use super::params::names;
use super::FemError;

/// One ingredient of a joint model.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum JointFeature {
    /// One out-of-plane contact stiffness K_con for all joints (baseline).
    Translational,
    /// One out-of-plane contact stiffness per joint (replaces `Translational`).
    PerJointTranslational,
    /// Rotational restraint per joint and axis, nominal N·m/rad (may be 0).
    RotationalRestraint {
        /// Nominal k_rot, N·m/rad.
        k_rot_nm_per_rad: f64,
    },
    /// Lumped joint mass per joint, nominal kg (may be 0).
    JointMass {
        /// Nominal mass, kg.
        mass_kg: f64,
    },
    /// Compliant fixture: one z-DOF with a mass on a spring to the base.
    CompliantFixture {
        /// Nominal suspension stiffness, N/m.
        k_fix_n_per_m: f64,
        /// Nominal fixture mass, kg.
        m_fix_kg: f64,
    },
}

/// A combination of joint features.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JointModel {
    /// The features; exactly one of `Translational` / `PerJointTranslational`.
    pub features: Vec<JointFeature>,
}

impl JointModel {
    /// The paper's model: one K_con for all joints.
    pub fn baseline() -> JointModel {
        JointModel {
            features: vec![JointFeature::Translational],
        }
    }

    /// Check the combination.
    pub fn validate(&self) -> Result<(), FemError> {
        let n_trans = self
            .features
            .iter()
            .filter(|f| {
                matches!(
                    f,
                    JointFeature::Translational | JointFeature::PerJointTranslational
                )
            })
            .count();
        if n_trans != 1 {
            return Err(FemError::Param(format!(
                "joint model: expected exactly one translational feature, found {n_trans}"
            )));
        }
        for f in &self.features {
            let bad = match f {
                JointFeature::RotationalRestraint { k_rot_nm_per_rad } => {
                    !(*k_rot_nm_per_rad >= 0.0 && k_rot_nm_per_rad.is_finite())
                }
                JointFeature::JointMass { mass_kg } => !(*mass_kg >= 0.0 && mass_kg.is_finite()),
                JointFeature::CompliantFixture {
                    k_fix_n_per_m,
                    m_fix_kg,
                } => !(*k_fix_n_per_m > 0.0 && *m_fix_kg > 0.0 && k_fix_n_per_m.is_finite()),
                _ => false,
            };
            if bad {
                return Err(FemError::Param(format!(
                    "joint feature {f:?}: expected finite non-negative values (k_fix, m_fix > 0)"
                )));
            }
        }
        Ok(())
    }

    /// Whether the model has the compliant-fixture DOF.
    pub fn has_fixture(&self) -> bool {
        self.features
            .iter()
            .any(|f| matches!(f, JointFeature::CompliantFixture { .. }))
    }
}

/// Which matrix a term belongs to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Which {
    /// Stiffness.
    K,
    /// Mass.
    M,
}

/// One affine joint term: `triplets` assembled at `param = scale`.
#[derive(Clone, Debug)]
pub struct JointTerm {
    pub which: Which,
    pub param: String,
    pub nominal: f64,
    pub scale: f64,
    pub triplets: Vec<(usize, usize, f64)>,
}

/// Patch of one joint: the global w-DOF index of each patch node (the slopes follow
/// at +1, +2 in the BFS DOF order).
pub type Patch = Vec<usize>;

fn spring(t: &mut Vec<(usize, usize, f64)>, i: usize, to: Option<usize>, k: f64) {
    t.push((i, i, k));
    if let Some(f) = to {
        t.push((f, f, k));
        t.push((i, f, -k));
        t.push((f, i, -k));
    }
}

/// The affine terms of `model` for the given patches. `fixture_dof` is the index of
/// the fixture z-DOF when the model has one. `k_con_nominal` and `bolt_mass_kg` come
/// from the board.
pub fn joint_terms(
    model: &JointModel,
    patches: &[Patch],
    fixture_dof: Option<usize>,
    k_con_nominal: f64,
) -> Vec<JointTerm> {
    let mut out = Vec::new();
    let ref_or = |v: f64, r: f64| if v > 0.0 { v } else { r };
    for f in &model.features {
        match f {
            JointFeature::Translational => {
                let mut t = Vec::new();
                for p in patches {
                    let k = k_con_nominal / p.len() as f64;
                    for &w in p {
                        spring(&mut t, w, fixture_dof, k);
                    }
                }
                out.push(JointTerm {
                    which: Which::K,
                    param: names::K_CON.to_string(),
                    nominal: k_con_nominal,
                    scale: k_con_nominal,
                    triplets: t,
                });
            }
            JointFeature::PerJointTranslational => {
                for (j, p) in patches.iter().enumerate() {
                    let mut t = Vec::new();
                    let k = k_con_nominal / p.len() as f64;
                    for &w in p {
                        spring(&mut t, w, fixture_dof, k);
                    }
                    out.push(JointTerm {
                        which: Which::K,
                        param: names::k_con_joint(j + 1),
                        nominal: k_con_nominal,
                        scale: k_con_nominal,
                        triplets: t,
                    });
                }
            }
            JointFeature::RotationalRestraint { k_rot_nm_per_rad } => {
                let scale = ref_or(*k_rot_nm_per_rad, 1.0);
                let mut t = Vec::new();
                for p in patches {
                    let k = scale / p.len() as f64;
                    for &w in p {
                        t.push((w + 1, w + 1, k));
                        t.push((w + 2, w + 2, k));
                    }
                }
                out.push(JointTerm {
                    which: Which::K,
                    param: names::K_ROT.to_string(),
                    nominal: *k_rot_nm_per_rad,
                    scale,
                    triplets: t,
                });
            }
            JointFeature::JointMass { mass_kg } => {
                let scale = ref_or(*mass_kg, 1e-3);
                let mut t = Vec::new();
                for p in patches {
                    let m = scale / p.len() as f64;
                    for &w in p {
                        t.push((w, w, m));
                    }
                }
                out.push(JointTerm {
                    which: Which::M,
                    param: names::JOINT_MASS.to_string(),
                    nominal: *mass_kg,
                    scale,
                    triplets: t,
                });
            }
            JointFeature::CompliantFixture {
                k_fix_n_per_m,
                m_fix_kg,
            } => {
                // validate() guarantees the fixture DOF exists for this feature.
                let fdof = fixture_dof.unwrap_or_else(|| unreachable!("fixture DOF missing"));
                out.push(JointTerm {
                    which: Which::K,
                    param: names::K_FIX.to_string(),
                    nominal: *k_fix_n_per_m,
                    scale: *k_fix_n_per_m,
                    triplets: vec![(fdof, fdof, *k_fix_n_per_m)],
                });
                let scale = ref_or(*m_fix_kg, 1e-2);
                out.push(JointTerm {
                    which: Which::M,
                    param: names::M_FIX.to_string(),
                    nominal: *m_fix_kg,
                    scale,
                    triplets: vec![(fdof, fdof, scale)],
                });
            }
        }
    }
    out
}

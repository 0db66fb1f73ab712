//! The bolted-joint family. A joint ties the board to the shaker fixture over the
//! clamped annulus around its hole (the bolt-head / washer / nut contact, outer
//! diameter `joint.clamp_diameter_m`, inner edge the hole): a joint is a distributed
//! layer over that annulus, its stiffness (or mass) per area being the joint's total
//! over the annulus area, integrated consistently with the element shape functions
//! over the exact part of the annulus in each element (cut-cell quadrature,
//! [`super::geometry`]). So `k_con_n_per_m` is the joint's physical total stiffness
//! whatever the mesh, and the model converges with the mesh like the plate itself. The bolts are rigid and move with the fixture, so their own mass
//! does not enter the fixed-base modes (it enters only through [`JointFeature::JointMass`]).
//!
//! Features combine; each adds affine terms and parameters:
//! - [`JointFeature::Translational`] (the paper's baseline): out-of-plane springs of total
//!   stiffness K_con (`k_con_n_per_m`, head and nut contacts in parallel) per joint;
//! - [`JointFeature::PerJointTranslational`]: the same with one `k_con_{j}_n_per_m` per joint;
//! - [`JointFeature::RotationalRestraint`]: a layer on the slopes ∂w/∂x and ∂w/∂y, total
//!   `k_rot_nm_per_rad` per joint and axis (a uniform rotation θ stores ½ k_rot θ²);
//! - [`JointFeature::JointMass`]: a z-mass `joint_mass_kg` per joint spread uniformly
//!   over its annulus;
//! - [`JointFeature::CompliantFixture`]: the fixture becomes one z-DOF with mass
//!   `m_fix_kg` on a spring `k_fix_n_per_m` to the (rigid, moving) base; joint springs
//!   then attach to the fixture DOF instead of the base.
//!
//! Not built yet: prestress (geometric stiffness from the clamping force); its hook is
//! an extra affine stiffness term here once the membrane state is modelled.

use serde::{Deserialize, Serialize};

use super::params::names;
use super::plate::{Mat16, PartIntegrals};
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

/// The clamped annulus of one joint on the mesh: per element it touches, the element's
/// DOFs and the integrals of its shape functions over the part of the annulus inside
/// it ([`PartIntegrals`], cut-cell quadrature), and the annulus area (the sum of the
/// parts, m²). Stiffness and mass per area are the joint's totals over this area, so
/// every total is the physical one whatever the mesh.
#[derive(Clone, Debug)]
pub struct Patch {
    /// Area of the clamped annulus on the board, m².
    pub area_m2: f64,
    /// `(element DOFs, integrals)` of every element the annulus covers in part.
    pub parts: Vec<([usize; 16], PartIntegrals)>,
}

/// Out-of-plane spring layer of total stiffness `k` (N/m) over `p`, to the ground or
/// to the fixture DOF `to`: energy ½ (k/A) ∫ (w − u_f)² dA.
fn spring_layer(t: &mut Vec<(usize, usize, f64)>, p: &Patch, to: Option<usize>, k: f64) {
    let kpa = k / p.area_m2;
    for (dofs, pi) in &p.parts {
        for r in 0..16 {
            for c in 0..16 {
                t.push((dofs[r], dofs[c], kpa * pi.nn[r][c]));
            }
        }
        if let Some(f) = to {
            t.push((f, f, kpa * pi.area_m2));
            for r in 0..16 {
                t.push((dofs[r], f, -kpa * pi.n[r]));
                t.push((f, dofs[r], -kpa * pi.n[r]));
            }
        }
    }
}

/// Layer over `p` with matrix `pick(part)` per element and total `v` per unit of the
/// matrix's rigid response: entries (v/A) × the integral.
fn layer(
    t: &mut Vec<(usize, usize, f64)>,
    p: &Patch,
    v: f64,
    pick: impl Fn(&PartIntegrals) -> &Mat16,
) {
    let per_area = v / p.area_m2;
    for (dofs, pi) in &p.parts {
        let m = pick(pi);
        for r in 0..16 {
            for c in 0..16 {
                t.push((dofs[r], dofs[c], per_area * m[r][c]));
            }
        }
    }
}

/// The affine terms of `model` for the given patches. `fixture_dof` is the index of
/// the fixture z-DOF when the model has one. `k_con_nominal` comes from the board.
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
                    spring_layer(&mut t, p, fixture_dof, k_con_nominal);
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
                    spring_layer(&mut t, p, fixture_dof, k_con_nominal);
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
                // Energy ½ (k_rot/A) ∫ (w_x² + w_y²) dA: a uniform rotation θ about
                // either axis stores ½ k_rot θ².
                let scale = ref_or(*k_rot_nm_per_rad, 1.0);
                let mut t = Vec::new();
                for p in patches {
                    layer(&mut t, p, scale, |pi| &pi.grad);
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
                // Mass per area m/A over the annulus, consistent: ∫ (m/A) N Nᵀ dA.
                let scale = ref_or(*mass_kg, 1e-3);
                let mut t = Vec::new();
                for p in patches {
                    layer(&mut t, p, scale, |pi| &pi.nn);
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

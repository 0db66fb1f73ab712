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
//!   stiffness K_con (`k_con_n_per_m`, head and nut contacts in parallel) per joint, and the
//!   contact's tangential stiffness: a stuck contact holds the board's face in-plane with
//!   `tangential_over_normal` × K_con (Mindlin 1949; the board file's
//!   [`super::board::JointData::tangential_over_normal`]). The face lies h/2 from the
//!   mid-plane, where a slope w,x moves it by (h/2) w,x, so these springs restrain the slopes
//!   by ratio × K_con × (h/2)² per joint and axis, less what the board's in-plane rigid
//!   motion (three DOFs of the model, [`Contact::inplane_dofs`]) gives way: a mode whose
//!   slopes at the joints push all the faces one way slides the board rather than strain the
//!   springs. The membrane is otherwise rigid (its stiffness E h is some ten times the
//!   contact's). The contact is at the bottom face, the standoff's: the screw head's own
//!   friction acts through the shank, which bends in its clearance hole. On the
//!   shear-deformable plate the face moves with the normal's rotation θ = ∇w − γ; the layer
//!   takes ∇w, the shear strain under the clamp being a few per cent of the slope. Scaled
//!   with K_con, it adds no parameter;
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
    /// Power of the core thickness (over its nominal) the term goes with, when the thickness
    /// is a parameter: 0 for all but the contact's face-offset terms.
    pub h_power: i32,
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

/// The normal contact stiffness of a joint and its stuck contact's tangential stiffness.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Contact {
    /// Nominal K_con per joint, N/m (the board's `k_con_n_per_m`).
    pub k_con_nominal: f64,
    /// Tangential over normal stiffness (the board's `tangential_over_normal`).
    pub tangential_over_normal: f64,
    /// Half the core's nominal thickness and half the copper's, m: the contact face (the
    /// board's bottom face) lies their sum below the mid-plane.
    pub half_core_m: f64,
    pub half_copper_m: f64,
    /// Whether the core thickness is a parameter: the face offset then follows it, and the
    /// contact's terms are split by power of the thickness.
    pub thickness_param: bool,
    /// The board's in-plane rigid motion `[u, v, φ]` (m, m, rad about the frame's z axis):
    /// the DOFs the tangential springs pull on. `None` holds the board fixed in-plane.
    pub inplane_dofs: Option<[usize; 3]>,
}

impl Contact {
    /// The board's contact at its bottom face, the board's in-plane rigid motion at
    /// `inplane_dofs`.
    pub fn of_board(
        board: &super::Board,
        thickness_param: bool,
        inplane_dofs: Option<[usize; 3]>,
    ) -> Contact {
        let j = board.joint();
        Contact {
            k_con_nominal: j.k_con_n_per_m,
            tangential_over_normal: j.tangential_over_normal,
            half_core_m: 0.5 * board.core.thickness_m,
            half_copper_m: 0.5 * board.copper_thickness_m(),
            thickness_param,
            inplane_dofs,
        }
    }
}

type Triplets = Vec<(usize, usize, f64)>;

/// A contact's triplets by order in the face offset c: `[c⁰, c¹, c²]`, each at c = 1.
type ByOffset = [Triplets; 3];

/// Normal springs of total `k` over `p` (to the fixture DOF `to` if any) and the stuck
/// contact's tangential springs of total `ratio × k` at the bottom face, to the ground.
/// The face at (x, y) moves in-plane by (u − φ y + c w_x, v + φ x + c w_y), c the face's
/// offset below the mid-plane (Kirchhoff kinematics; [`JointFeature::Translational`]).
fn contact_layer(t: &mut ByOffset, p: &Patch, to: Option<usize>, k: f64, contact: &Contact) {
    spring_layer(&mut t[0], p, to, k);
    let kt = contact.tangential_over_normal * k;
    if kt <= 0.0 {
        return;
    }
    layer(&mut t[2], p, kt, |pi| &pi.grad);
    let Some([u, v, phi]) = contact.inplane_dofs else {
        return;
    };
    let kpa = kt / p.area_m2;
    let sym = |t: &mut Triplets, r: usize, q: usize, x: f64| {
        t.push((r, q, x));
        if r != q {
            t.push((q, r, x));
        }
    };
    for (dofs, pi) in &p.parts {
        sym(&mut t[0], u, u, kpa * pi.area_m2);
        sym(&mut t[0], v, v, kpa * pi.area_m2);
        sym(&mut t[0], phi, phi, kpa * pi.r2_m4);
        sym(&mut t[0], u, phi, -kpa * pi.y_m3);
        sym(&mut t[0], v, phi, kpa * pi.x_m3);
        for r in 0..16 {
            sym(&mut t[1], u, dofs[r], kpa * pi.n_x[r]);
            sym(&mut t[1], v, dofs[r], kpa * pi.n_y[r]);
            sym(&mut t[1], phi, dofs[r], kpa * pi.n_rot[r]);
        }
    }
}

/// The stiffness terms of one contact parameter from its triplets by face offset. The offset
/// is c = (h/h₀) c_core + c_cu: with the thickness a parameter, the terms go by its power
/// (`h_power` 0, 1, 2); else one term at the nominal offset.
fn contact_terms(param: String, k_nominal: f64, t: ByOffset, contact: &Contact) -> Vec<JointTerm> {
    let (hc, cu) = (contact.half_core_m, contact.half_copper_m);
    let [t0, t1, t2] = t;
    let combine = |parts: [(&Triplets, f64); 3]| -> Triplets {
        parts
            .iter()
            .filter(|(_, f)| *f != 0.0)
            .flat_map(|(t, f)| t.iter().map(move |&(r, c, x)| (r, c, f * x)))
            .collect()
    };
    let by_power: Vec<(i32, Triplets)> = if contact.thickness_param {
        vec![
            (0, combine([(&t0, 1.0), (&t1, cu), (&t2, cu * cu)])),
            (1, combine([(&t0, 0.0), (&t1, hc), (&t2, 2.0 * hc * cu)])),
            (2, combine([(&t0, 0.0), (&t1, 0.0), (&t2, hc * hc)])),
        ]
    } else {
        let c = hc + cu;
        vec![(0, combine([(&t0, 1.0), (&t1, c), (&t2, c * c)]))]
    };
    by_power
        .into_iter()
        .filter(|(_, t)| !t.is_empty())
        .map(|(h_power, triplets)| JointTerm {
            which: Which::K,
            param: param.clone(),
            nominal: k_nominal,
            scale: k_nominal,
            h_power,
            triplets,
        })
        .collect()
}

/// The affine terms of `model` for the given patches. `fixture_dof` is the index of
/// the fixture z-DOF when the model has one.
pub fn joint_terms(
    model: &JointModel,
    patches: &[Patch],
    fixture_dof: Option<usize>,
    contact: Contact,
) -> Vec<JointTerm> {
    let k_con_nominal = contact.k_con_nominal;
    let mut out = Vec::new();
    let ref_or = |v: f64, r: f64| if v > 0.0 { v } else { r };
    for f in &model.features {
        match f {
            JointFeature::Translational => {
                let mut t = ByOffset::default();
                for p in patches {
                    contact_layer(&mut t, p, fixture_dof, k_con_nominal, &contact);
                }
                out.extend(contact_terms(
                    names::K_CON.to_string(),
                    k_con_nominal,
                    t,
                    &contact,
                ));
            }
            JointFeature::PerJointTranslational => {
                for (j, p) in patches.iter().enumerate() {
                    let mut t = ByOffset::default();
                    contact_layer(&mut t, p, fixture_dof, k_con_nominal, &contact);
                    out.extend(contact_terms(
                        names::k_con_joint(j + 1),
                        k_con_nominal,
                        t,
                        &contact,
                    ));
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
                    h_power: 0,
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
                    h_power: 0,
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
                    h_power: 0,
                    triplets: vec![(fdof, fdof, *k_fix_n_per_m)],
                });
                let scale = ref_or(*m_fix_kg, 1e-2);
                out.push(JointTerm {
                    which: Which::M,
                    param: names::M_FIX.to_string(),
                    nominal: *m_fix_kg,
                    scale,
                    h_power: 0,
                    triplets: vec![(fdof, fdof, scale)],
                });
            }
        }
    }
    out
}

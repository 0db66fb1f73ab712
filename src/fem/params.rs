//! User-facing model parameters and their map to the affine coefficients.
//!
//! The model is K(p) = Σᵢ cᵢ(p) Kᵢ, M(p) = Σⱼ dⱼ(p) Mⱼ. Each term's coefficient is a
//! [`Coef`]: a ratio of a plane-stress modulus of the FR-4 core to its nominal value
//! (Q₁₁ = E_x/(1 − ν_xy ν_yx), Q₂₂ = E_y/(1 − ν_xy ν_yx), Q₁₂ = ν_xy E_y/(1 − ν_xy ν_yx),
//! Q₆₆ = G_xy, ν_yx = ν_xy E_y/E_x), a parameter over its nominal value (copper
//! modulus, mass scale, joint stiffnesses and masses) over the value its term was
//! assembled at, or the constant 1. The terms are
//! assembled at the nominal values, so every coefficient is 1 at the nominal point.
//! [`ParamMap::coefficients`] also returns ∂c/∂p for the chain rule of the
//! sensitivities.

use serde::{Deserialize, Serialize};

use super::laminate::{core_q_scale, coupling_kernel, coupling_value, orthotropic_q};
use super::FemError;

/// Names of the standard parameters (units in the names).
pub mod names {
    /// FR-4 Young's modulus along x, Pa.
    pub const E_X: &str = "e_x_pa";
    /// FR-4 Young's modulus along y, Pa.
    pub const E_Y: &str = "e_y_pa";
    /// FR-4 shear modulus, Pa.
    pub const G_XY: &str = "g_xy_pa";
    /// FR-4 major Poisson ratio.
    pub const NU_XY: &str = "nu_xy";
    /// Copper Young's modulus, Pa (all layers scaled together).
    pub const E_CU: &str = "e_cu_pa";
    /// Scale of the whole board mass (FR-4 and copper), dimensionless.
    pub const MASS_SCALE: &str = "mass_scale";
    /// Out-of-plane contact stiffness of each joint, N/m.
    pub const K_CON: &str = "k_con_n_per_m";
    /// Rotational restraint of each joint, N·m/rad.
    pub const K_ROT: &str = "k_rot_nm_per_rad";
    /// Lumped joint mass at each joint, kg.
    pub const JOINT_MASS: &str = "joint_mass_kg";
    /// Fixture suspension stiffness, N/m.
    pub const K_FIX: &str = "k_fix_n_per_m";
    /// Fixture mass, kg.
    pub const M_FIX: &str = "m_fix_kg";
    /// Thickness of the FR-4 core, m: a parameter only in a model built with
    /// [`crate::fem::ModelOptions::core_thickness`] (a specimen's measured thickness).
    pub const CORE_THICKNESS: &str = "core_thickness_m";
    /// Transverse shear modulus G_xz of the FR-4 core, Pa (G_yz keeps its ratio to it): a
    /// parameter of shear-deformable boards (a core with `g_xz_pa` and `g_yz_pa`) only.
    pub const G_Z: &str = "g_z_pa";
    /// Step 1's population coordinate of a modulus taken per unit mass scale
    /// (`update boards --board-coordinates per-mass`): `e_x_pa` → `e_x_per_mass_scale_pa`.
    pub fn per_mass_scale(param: &str) -> String {
        let stem = param.strip_suffix("_pa").unwrap_or(param);
        format!("{stem}_per_{MASS_SCALE}_pa")
    }
    /// The modulus of a coordinate named by [`per_mass_scale`], if it is one.
    pub fn modulus_of_per_mass_scale(coordinate: &str) -> Option<String> {
        coordinate
            .strip_suffix(&format!("_per_{MASS_SCALE}_pa"))
            .map(|stem| format!("{stem}_pa"))
    }
    /// Contact stiffness of joint `j` (1-based) in the per-joint variant, N/m.
    pub fn k_con_joint(j: usize) -> String {
        format!("k_con_{j}_n_per_m")
    }
}

/// A named parameter vector.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Params {
    /// Parameter names, in the model's order.
    pub names: Vec<String>,
    /// Values, same order as `names`.
    pub values: Vec<f64>,
}

impl Params {
    /// Value of `name`.
    pub fn get(&self, name: &str) -> Result<f64, FemError> {
        self.position(name).map(|i| self.values[i])
    }

    /// Set `name` to `value`.
    pub fn set(&mut self, name: &str, value: f64) -> Result<(), FemError> {
        let i = self.position(name)?;
        self.values[i] = value;
        Ok(())
    }

    /// Index of `name`.
    pub fn position(&self, name: &str) -> Result<usize, FemError> {
        self.names.iter().position(|n| n == name).ok_or_else(|| {
            FemError::Param(format!("expected one of {:?}, found {name:?}", self.names))
        })
    }
}

/// How one affine term's coefficient depends on the parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Coef {
    /// Q_c(E_x, E_y, G_xy, ν_xy) / Q_c(nominal), c ∈ {0: Q11, 1: Q22, 2: Q12, 3: Q66}
    /// (a component zero at nominal divides by [`super::laminate::core_q_scale`]).
    CoreQ {
        /// Component index.
        comp: usize,
    },
    /// p_k / scale: the term was assembled at p_k = scale (the nominal value when it
    /// is positive, else a reference value).
    Linear {
        /// Parameter index.
        param: usize,
        /// Parameter value the term was assembled at.
        scale: f64,
    },
    /// Always 1.
    Const,
    /// One term of the exact coupling-correction expansion ([`super::laminate`]):
    /// G_comp(s_node; p) / scale, where G is [`super::laminate::coupling_kernel`] with
    /// the core moduli and ε = E_cu / `e_cu_nominal_pa` of `p`; the term was assembled
    /// with −scale = −G_comp(s_node; nominal) (or −1 when that vanishes).
    Coupling {
        /// Interpolation node, m (copper variable s).
        s_node_m: f64,
        /// Component 0..4 of `[c11, c22, c12, c66]`.
        comp: usize,
        /// Value of G the term was assembled at.
        scale: f64,
        /// Core thickness h, m.
        h_core_m: f64,
        /// Plane-stress stiffness of copper at its nominal modulus, Pa.
        q_cu_pa: [f64; 4],
        /// Index of `e_cu_pa`.
        e_cu_param: usize,
        /// Nominal copper modulus, Pa.
        e_cu_nominal_pa: f64,
        /// Index of `core_thickness_m` when the core thickness is a parameter: G is then
        /// evaluated at h = p[h_param] instead of `h_core_m`.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        h_param: Option<usize>,
    },
    /// `base` times (p_k / nominal)^power: one term of a thickness-dependent quantity's
    /// polynomial in the core thickness h = p_k (bending stiffness of the core h³, of a
    /// copper layer at its surface h², h, 1; the coupling correction's t² likewise; the core's
    /// mass h), so that the model stays affine, and exact, in h.
    ThicknessPower {
        base: Box<Coef>,
        /// Index of `core_thickness_m`.
        param: usize,
        /// Thickness the term was assembled at, m.
        nominal_m: f64,
        power: i32,
    },
}

/// The parameter list of a model and the coefficient map of its K and M terms.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ParamMap {
    /// Parameter names.
    pub names: Vec<String>,
    /// Nominal values (the ones the terms were assembled at).
    pub nominal: Vec<f64>,
    /// Coefficient of each stiffness term.
    pub k_coefs: Vec<Coef>,
    /// Coefficient of each mass term.
    pub m_coefs: Vec<Coef>,
    /// Indices of e_x, e_y, g_xy, nu_xy.
    pub core_idx: [usize; 4],
}

/// Coefficients and their gradients at one parameter point.
#[derive(Clone, Debug)]
pub struct Coefficients {
    /// cᵢ of the stiffness terms.
    pub k: Vec<f64>,
    /// dⱼ of the mass terms.
    pub m: Vec<f64>,
    /// ∂cᵢ/∂p_k, `k_grad[i][k]`.
    pub k_grad: Vec<Vec<f64>>,
    /// ∂dⱼ/∂p_k.
    pub m_grad: Vec<Vec<f64>>,
}

impl ParamMap {
    /// The nominal parameters.
    pub fn nominal_params(&self) -> Params {
        Params {
            names: self.names.clone(),
            values: self.nominal.clone(),
        }
    }

    /// Check `p` names the same parameters, in order, with admissible values.
    pub fn check(&self, p: &Params) -> Result<(), FemError> {
        if p.names != self.names {
            return Err(FemError::Param(format!(
                "expected parameters {:?}, found {:?}",
                self.names, p.names
            )));
        }
        for (n, v) in p.names.iter().zip(&p.values) {
            let ok = if n == names::NU_XY {
                v.is_finite()
            } else if n == names::CORE_THICKNESS {
                v.is_finite() && *v > 0.0
            } else {
                v.is_finite() && *v >= 0.0
            };
            if !ok {
                return Err(FemError::Param(format!(
                    "{n}: expected a finite non-negative value, found {v}"
                )));
            }
        }
        let [ix, iy, _, inu] = self.core_idx;
        let (ex, ey, nu) = (p.values[ix], p.values[iy], p.values[inu]);
        if !(ex > 0.0 && ey > 0.0 && nu * nu * ey / ex < 1.0) {
            return Err(FemError::Param(format!(
                "core: expected E_x, E_y > 0 and ν_xy² E_y/E_x < 1, found E_x = {ex}, E_y = {ey}, ν_xy = {nu}"
            )));
        }
        Ok(())
    }

    /// Coefficients at `p`, with gradients.
    pub fn coefficients(&self, p: &Params) -> Result<Coefficients, FemError> {
        self.check(p)?;
        Ok(self.coefficients_unchecked(&p.values))
    }

    /// The coefficient values alone (stiffness, mass) at raw values the caller has checked:
    /// the sampler's hot path, which needs no gradients. The same operations as
    /// [`Self::coefficients_unchecked`]'s values, so the same bits, without its gradient
    /// vector per term (an allocation each, and the coupling kernel's derivatives: 5 % of
    /// a bolted step 2's profile).
    pub fn coefficient_values(&self, v: &[f64]) -> (Vec<f64>, Vec<f64>) {
        let [ix, iy, ig, inu] = self.core_idx;
        let q_nom = core_q_scale(orthotropic_q(
            self.nominal[ix],
            self.nominal[iy],
            self.nominal[ig],
            self.nominal[inu],
        ));
        let (ex, ey, g, nu) = (v[ix], v[iy], v[ig], v[inu]);
        let den = 1.0 - nu * nu * ey / ex;
        let q = [ex / den, ey / den, nu * ey / den, g];
        fn eval(c: &Coef, q: &[f64; 4], q_nom: &[f64; 4], v: &[f64]) -> f64 {
            match c {
                Coef::CoreQ { comp } => q[*comp] * (1.0 / q_nom[*comp]),
                Coef::Linear { param, scale } => v[*param] / scale,
                Coef::Const => 1.0,
                Coef::Coupling {
                    s_node_m,
                    comp,
                    scale,
                    h_core_m,
                    q_cu_pa,
                    e_cu_param,
                    e_cu_nominal_pa,
                    h_param,
                } => {
                    let eps = v[*e_cu_param] / e_cu_nominal_pa;
                    let h = h_param.map_or(*h_core_m, |i| v[i]);
                    coupling_value(*q, h, *q_cu_pa, eps, *s_node_m)[*comp] / scale
                }
                Coef::ThicknessPower {
                    base,
                    param,
                    nominal_m,
                    power,
                } => eval(base, q, q_nom, v) * (v[*param] / nominal_m).powi(*power),
            }
        }
        (
            self.k_coefs
                .iter()
                .map(|c| eval(c, &q, &q_nom, v))
                .collect(),
            self.m_coefs
                .iter()
                .map(|c| eval(c, &q, &q_nom, v))
                .collect(),
        )
    }

    /// Coefficients at raw values (caller has checked them).
    pub fn coefficients_unchecked(&self, v: &[f64]) -> Coefficients {
        let np = self.names.len();
        let [ix, iy, ig, inu] = self.core_idx;
        let q_nom = core_q_scale(orthotropic_q(
            self.nominal[ix],
            self.nominal[iy],
            self.nominal[ig],
            self.nominal[inu],
        ));
        let (ex, ey, g, nu) = (v[ix], v[iy], v[ig], v[inu]);
        let den = 1.0 - nu * nu * ey / ex;
        // ∂den/∂(E_x, E_y, ν).
        let dden = [nu * nu * ey / (ex * ex), -nu * nu / ex, -2.0 * nu * ey / ex];
        // (value, ∂/∂E_x, ∂/∂E_y, ∂/∂G, ∂/∂ν) of the four Q components.
        let quot = |num: f64, dnum: [f64; 3]| -> [f64; 4] {
            let mut d = [0.0; 4];
            for k in 0..3 {
                d[k] = dnum[k] / den - num * dden[k] / (den * den);
            }
            // reorder to (E_x, E_y, G, ν): G does not enter num/den.
            [d[0], d[1], 0.0, d[2]]
        };
        let q = [ex / den, ey / den, nu * ey / den, g];
        let dq = [
            quot(ex, [1.0, 0.0, 0.0]),
            quot(ey, [0.0, 1.0, 0.0]),
            quot(nu * ey, [0.0, nu, ey]),
            [0.0, 0.0, 1.0, 0.0],
        ];
        // (value, ∂/∂p) of one coefficient.
        let eval = |c: &Coef| -> (f64, Vec<f64>) {
            let mut grad = vec![0.0; np];
            // A thickness power's factor r^power (r = h / nominal) and its derivative in h,
            // then its base.
            let (c, power) = match c {
                Coef::ThicknessPower {
                    base,
                    param,
                    nominal_m,
                    power,
                } => {
                    let r = v[*param] / nominal_m;
                    let d = f64::from(*power) * r.powi(*power - 1) / nominal_m;
                    (&**base, Some((*param, r.powi(*power), d)))
                }
                c => (c, None),
            };
            let value = match c {
                Coef::CoreQ { comp } => {
                    let s = 1.0 / q_nom[*comp];
                    for (k, idx) in [ix, iy, ig, inu].iter().enumerate() {
                        grad[*idx] += dq[*comp][k] * s;
                    }
                    q[*comp] * s
                }
                Coef::Linear { param, scale } => {
                    grad[*param] = 1.0 / scale;
                    v[*param] / scale
                }
                Coef::Const => 1.0,
                Coef::Coupling {
                    s_node_m,
                    comp,
                    scale,
                    h_core_m,
                    q_cu_pa,
                    e_cu_param,
                    e_cu_nominal_pa,
                    h_param,
                } => {
                    let eps = v[*e_cu_param] / e_cu_nominal_pa;
                    let h = h_param.map_or(*h_core_m, |i| v[i]);
                    let (g, d_core, d_eps) = coupling_kernel(q, h, *q_cu_pa, eps, *s_node_m);
                    for j in 0..4 {
                        for (k, idx) in [ix, iy, ig, inu].iter().enumerate() {
                            grad[*idx] += d_core[j][*comp] * dq[j][k] / scale;
                        }
                    }
                    grad[*e_cu_param] += d_eps[*comp] / (e_cu_nominal_pa * scale);
                    if let Some(i) = h_param {
                        // N = h Q_core + ε s Q_cu: ∂G/∂h = Σ_j ∂G/∂Q_core[j] · Q_core[j] / h.
                        grad[*i] +=
                            (0..4).map(|j| d_core[j][*comp] * q[j]).sum::<f64>() / (h * scale);
                    }
                    g[*comp] / scale
                }
                Coef::ThicknessPower { .. } => unreachable!("unwrapped above"),
            };
            match power {
                None => (value, grad),
                Some((param, factor, d)) => {
                    for g in grad.iter_mut() {
                        *g *= factor;
                    }
                    grad[param] += value * d;
                    (value * factor, grad)
                }
            }
        };
        let (k, k_grad): (Vec<_>, Vec<_>) = self.k_coefs.iter().map(eval).unzip();
        let (m, m_grad): (Vec<_>, Vec<_>) = self.m_coefs.iter().map(eval).unzip();
        Coefficients {
            k,
            m,
            k_grad,
            m_grad,
        }
    }
}

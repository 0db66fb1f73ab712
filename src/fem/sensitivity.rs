//! Analytic eigen-sensitivities of the full model, and the `%/%` table (the analog of
//! the paper's Table 1).
//!
//! For a simple eigenpair (λ, φ) with φᵀ M φ = 1 and a parameter p entering through the
//! affine coefficients, ∂K/∂p = Σᵢ (∂cᵢ/∂p) Kᵢ and ∂M/∂p = Σⱼ (∂dⱼ/∂p) Mⱼ:
//!
//! - eigenvalue: ∂λ/∂p = φᵀ (∂K/∂p − λ ∂M/∂p) φ; frequency ∂f/∂p = (∂λ/∂p)/(4π √λ);
//! - mode shape (Nelson's method): solve (K − λM) v = −(∂K/∂p − λ ∂M/∂p − (∂λ/∂p) M) φ
//!   with the DOF q of largest |φ_q| held at v_q = 0 (which removes the singularity),
//!   then ∂φ/∂p = v + c φ with c = −φᵀ M v − ½ φᵀ (∂M/∂p) φ, which keeps the mass
//!   normalisation. The solve uses a sparse LU of the indefinite K − λM.
//!
//! The table entry for mode j and parameter p is (p / f_j) ∂f_j/∂p, the per-cent change
//! of the frequency per per-cent change of the parameter.

use faer::linalg::solvers::Solve;
use faer::Mat;
use serde::{Deserialize, Serialize};

use super::model::{FeModel, Modes};
use super::params::Params;
use super::FemError;

/// Derivatives of the modes with respect to every model parameter.
#[derive(Clone, Debug)]
pub struct EigenDerivatives {
    /// Parameter names (columns).
    pub param_names: Vec<String>,
    /// ∂λ_j/∂p_k (rad²/s² per parameter unit), n_modes × n_params.
    pub d_eigenvalue: Mat<f64>,
    /// ∂f_j/∂p_k (Hz per parameter unit), n_modes × n_params.
    pub d_freq_hz: Mat<f64>,
    /// ∂φ_j/∂p_k as one n_dof × n_modes matrix per parameter (if requested).
    pub d_shapes: Option<Vec<Mat<f64>>>,
}

/// One row of the `%/%` table.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SensitivityRow {
    /// Mode number, 1-based, ascending frequency.
    pub mode: usize,
    /// Frequency of the mode, Hz.
    pub freq_hz: f64,
    /// Parameter name.
    pub param: String,
    /// (p / f) ∂f/∂p, %/%.
    pub pct_per_pct: f64,
}

/// Analytic derivatives of `modes` (computed by `model.modes(p, …)`) at `p`.
/// With `with_shapes`, also the full-DOF mode-shape derivatives (one sparse LU per mode).
pub fn eigen_derivatives(
    model: &FeModel,
    p: &Params,
    modes: &Modes,
    with_shapes: bool,
) -> Result<EigenDerivatives, FemError> {
    let c = model.coefficients(p)?;
    let n = model.n_dof;
    let nm = modes.shapes.ncols();
    let np = p.values.len();
    if modes.shapes.nrows() != n {
        return Err(FemError::Request(format!(
            "modes: expected {n} DOFs, found {}",
            modes.shapes.nrows()
        )));
    }
    let pat = &model.pattern;
    let mut d_lam = Mat::<f64>::zeros(nm, np);
    let mut d_f = Mat::<f64>::zeros(nm, np);
    let mut d_shapes = with_shapes.then(|| {
        (0..np)
            .map(|_| Mat::<f64>::zeros(n, nm))
            .collect::<Vec<_>>()
    });
    let kv = model.k_values(&c.k);
    let mv = model.m_values(&c.m);
    for j in 0..nm {
        let phi: Vec<f64> = (0..n).map(|i| modes.shapes[(i, j)]).collect();
        let lam = modes.eigenvalues[j];
        // Per-term products Kᵢ φ and Mⱼ φ.
        let apply = |val: &[f64]| {
            let mut y = vec![0.0; n];
            pat.matvec(val, &phi, &mut y);
            y
        };
        let kphi: Vec<Vec<f64>> = model.k_terms.iter().map(|t| apply(t)).collect();
        let mphi: Vec<Vec<f64>> = model.m_terms.iter().map(|t| apply(t)).collect();
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
        let a: Vec<f64> = kphi.iter().map(|v| dot(&phi, v)).collect();
        let b: Vec<f64> = mphi.iter().map(|v| dot(&phi, v)).collect();
        for k in 0..np {
            let dk: f64 = (0..a.len()).map(|i| c.k_grad[i][k] * a[i]).sum();
            let dm: f64 = (0..b.len()).map(|i| c.m_grad[i][k] * b[i]).sum();
            let dl = dk - lam * dm;
            d_lam[(j, k)] = dl;
            d_f[(j, k)] = dl / (4.0 * std::f64::consts::PI * lam.max(f64::MIN_POSITIVE).sqrt());
        }
        if let Some(ds) = d_shapes.as_mut() {
            // K − λM with row/column q replaced by the identity.
            let q = (0..n)
                .max_by(|&x, &y| phi[x].abs().total_cmp(&phi[y].abs()))
                .unwrap_or(0);
            let mut av: Vec<f64> = kv.iter().zip(&mv).map(|(k, m)| k - lam * m).collect();
            for col in 0..n {
                for t in pat.col_ptr[col]..pat.col_ptr[col + 1] {
                    let row = pat.row_idx[t];
                    if row == q || col == q {
                        av[t] = if row == col { 1.0 } else { 0.0 };
                    }
                }
            }
            // Symmetric diagonal equilibration D A D (D = |diag A|^(-1/2)): the BFS DOFs
            // (w, slopes, twist) differ in scale by powers of the element size, so the
            // unscaled LU loses digits in proportion; on a graded mesh (elements of
            // several sizes) that was 1e-4 of the shape derivative.
            let mut dscale = vec![1.0; n];
            for col in 0..n {
                for t in pat.col_ptr[col]..pat.col_ptr[col + 1] {
                    if pat.row_idx[t] == col && av[t] != 0.0 {
                        dscale[col] = 1.0 / av[t].abs().sqrt();
                    }
                }
            }
            for col in 0..n {
                for t in pat.col_ptr[col]..pat.col_ptr[col + 1] {
                    av[t] *= dscale[pat.row_idx[t]] * dscale[col];
                }
            }
            let lu = pat.view(&av).sp_lu().map_err(|e| {
                FemError::Factorisation(format!("K − λM for mode {}: {e:?}", j + 1))
            })?;
            let mphi_full: Vec<f64> = {
                let mut y = vec![0.0; n];
                pat.matvec(&mv, &phi, &mut y);
                y
            };
            let mut rhs = Mat::<f64>::zeros(n, np);
            let mut dm_phi_all = Vec::with_capacity(np);
            for k in 0..np {
                let mut dkphi = vec![0.0; n];
                let mut dmphi = vec![0.0; n];
                for (i, v) in kphi.iter().enumerate() {
                    let g = c.k_grad[i][k];
                    if g != 0.0 {
                        dkphi.iter_mut().zip(v).for_each(|(x, y)| *x += g * y);
                    }
                }
                for (i, v) in mphi.iter().enumerate() {
                    let g = c.m_grad[i][k];
                    if g != 0.0 {
                        dmphi.iter_mut().zip(v).for_each(|(x, y)| *x += g * y);
                    }
                }
                let dl = d_lam[(j, k)];
                for i in 0..n {
                    rhs[(i, k)] = -(dkphi[i] - lam * dmphi[i] - dl * mphi_full[i]);
                }
                rhs[(q, k)] = 0.0;
                dm_phi_all.push(dot(&phi, &dmphi));
            }
            for k in 0..np {
                for i in 0..n {
                    rhs[(i, k)] *= dscale[i];
                }
            }
            lu.solve_in_place(rhs.as_mut());
            for k in 0..np {
                let v: Vec<f64> = (0..n).map(|i| dscale[i] * rhs[(i, k)]).collect();
                let cc = -dot(&mphi_full, &v) - 0.5 * dm_phi_all[k];
                for i in 0..n {
                    ds[k][(i, j)] = v[i] + cc * phi[i];
                }
            }
        }
    }
    Ok(EigenDerivatives {
        param_names: p.names.clone(),
        d_eigenvalue: d_lam,
        d_freq_hz: d_f,
        d_shapes,
    })
}

/// ∂f_j/∂p_k (Hz per parameter unit) of `modes` with respect to the parameters `params`
/// only, n_modes × `params.len()`: the eigenvalue part of [`eigen_derivatives`]. Only the
/// affine terms whose coefficient moves with one of `params` are visited, each by one
/// quadratic form φᵀ Tᵢ φ. Why: step 2's centre fit needs the joint stiffness's column
/// alone, and all 47 stiffness terms of the bolted board (core, copper coupling, shear,
/// joint) cost it more than the FE solve it follows.
pub fn freq_derivatives_for(
    model: &FeModel,
    p: &Params,
    modes: &Modes,
    params: &[usize],
) -> Result<Mat<f64>, FemError> {
    let c = model.coefficients(p)?;
    let n = model.n_dof;
    if modes.shapes.nrows() != n {
        return Err(FemError::Request(format!(
            "modes: expected {n} DOFs, found {}",
            modes.shapes.nrows()
        )));
    }
    if let Some(&k) = params.iter().find(|&&k| k >= p.values.len()) {
        return Err(FemError::Request(format!(
            "parameter index {k} beyond the model's {}",
            p.values.len()
        )));
    }
    let moves = |grad: &[f64]| params.iter().any(|&k| grad[k] != 0.0);
    let nm = modes.shapes.ncols();
    let mut d_f = Mat::<f64>::zeros(nm, params.len());
    for j in 0..nm {
        let phi = modes.shapes.col_as_slice(j);
        let lam = modes.eigenvalues[j];
        let form = |terms: &[Vec<f64>], grads: &[Vec<f64>]| -> Vec<Option<f64>> {
            terms
                .iter()
                .zip(grads)
                .map(|(t, g)| moves(g).then(|| model.pattern.quadratic_form(t, phi)))
                .collect()
        };
        let a = form(&model.k_terms, &c.k_grad);
        let b = form(&model.m_terms, &c.m_grad);
        for (col, &k) in params.iter().enumerate() {
            let sum = |forms: &[Option<f64>], grads: &[Vec<f64>]| -> f64 {
                forms
                    .iter()
                    .zip(grads)
                    .filter_map(|(f, g)| f.map(|f| g[k] * f))
                    .sum()
            };
            let dl = sum(&a, &c.k_grad) - lam * sum(&b, &c.m_grad);
            d_f[(j, col)] = dl / (4.0 * std::f64::consts::PI * lam.max(f64::MIN_POSITIVE).sqrt());
        }
    }
    Ok(d_f)
}

/// The `%/%` sensitivity table of the lowest `n_modes` modes at `p`: one row per
/// (mode, parameter), modes outer. Parameters with value 0 get 0.
pub fn table_percent_per_percent(
    model: &FeModel,
    p: &Params,
    n_modes: usize,
) -> Result<Vec<SensitivityRow>, FemError> {
    let modes = model.modes(p, n_modes)?;
    let d = eigen_derivatives(model, p, &modes, false)?;
    let mut rows = Vec::with_capacity(n_modes * p.values.len());
    for j in 0..n_modes {
        for (k, name) in p.names.iter().enumerate() {
            rows.push(SensitivityRow {
                mode: j + 1,
                freq_hz: modes.freq_hz[j],
                param: name.clone(),
                pct_per_pct: p.values[k] / modes.freq_hz[j] * d.d_freq_hz[(j, k)],
            });
        }
    }
    Ok(rows)
}

//! Parametric reduced-order model (ROM): one global reduced basis V for the whole
//! ±20 % parameter box, the affine terms projected once (Kᵢʳ = Vᵀ Kᵢ V, Mⱼʳ = Vᵀ Mⱼ V),
//! and a small dense generalized eigen-solve per evaluation.
//!
//! Basis: snapshots of the lowest `n_modes + n_extra` modes of the full model at the
//! box centre, at the ±`box_rel` end of each parameter axis, and at `n_random` Latin
//! hypercube points (explicit seed), plus the centre's mode-shape derivatives
//! p ∂φ/∂p (Nelson, [`super::sensitivity`]). The design is adaptive by default, a greedy
//! reduced-basis construction (Veroy et al. 2003; Hesthaven, Rozza & Stamm 2016, ch. 3): the
//! centre and the axis ends (a logarithmic axis's two ends) are solved first, without the
//! derivatives; the other points are candidates, ranked by a residual estimate of the current
//! ROM's frequency error (`Rom::residual_indicator`: sparse products, no solve), and solved a
//! few at a time, worst first, until the current ROM already reproduces the points it ranked
//! worst ([`ADAPTIVE_TOL`]). The two designs are compared, time and error over the box, by
//! the experiment `adaptive_snapshot_design_against_the_full_one_on_the_default_board`.
//! The snapshots are compressed by an M-weighted POD
//! (eigen-decomposition of the Gram matrix Sᵀ M₀ S, M₀ = M at nominal) and truncated
//! at singular values below `pod_tol` of the largest (or at `max_basis` vectors). For
//! the free setup the snapshots are M₀-orthogonalised against the three rigid-body
//! vectors (w = 1, x, y); with a single mass term the elastic modes are M-orthogonal
//! to them at every p, so the rigid vectors are left out of the basis; with several
//! mass terms (e.g. a point mass) they lead the basis, stay exact rigid modes of every
//! reduced model (Kᵢ r = 0 for every term), and the evaluation drops them. Since the model is affine, the projected model is exact
//! in its parameters: the only ROM error is the basis truncation, measured by the ROM
//! accuracy test over ≥ 200 Latin-hypercube points.
//!
//! Evaluation at p: Kʳ = Σ cᵢ(p) Kᵢʳ, Mʳ = Σ dⱼ(p) Mⱼʳ. When the model has one mass
//! term (all our standard setups: mass only through `mass_scale`), the basis is
//! M₀-orthonormal so Mʳ = d₀ I and the pencil reduces to the symmetric eigenproblem of
//! Kʳ/d₀; otherwise Mʳ = L Lᵀ (Cholesky) and we solve L⁻¹ Kʳ L⁻ᵀ z = λ z, y = L⁻ᵀ z.
//! Shapes at scan points are P y with the precomputed P = S V (S: DOF → w at points).

use faer::{Mat, MatRef, Side};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::model::{FeModel, Setup};
use super::params::{ParamMap, Params};
use super::{npz, FemError};

/// Build options of the ROM.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RomOptions {
    /// Modes of interest (8 for free, 7 for bolted in the acceptance test).
    pub n_modes: usize,
    /// Extra modes per snapshot (they enrich the basis).
    pub n_extra: usize,
    /// Half-width of the parameter box, relative (0.2 = ±20 %).
    pub box_rel: f64,
    /// Latin-hypercube snapshot points in addition to centre and axis ends.
    pub n_random: usize,
    /// POD truncation: keep singular values above `pod_tol` × the largest.
    pub pod_tol: f64,
    /// Upper bound on the basis size.
    pub max_basis: usize,
    /// Seed of the snapshot design.
    pub seed: u64,
    /// Add the centre's mode-shape derivatives p ∂φ/∂p as snapshots (the full design only:
    /// the adaptive one leaves them out).
    pub derivative_snapshots: bool,
    /// Parameters whose box is wide and logarithmic instead of ±`box_rel`: (name, w), the
    /// box being nominal · e^{±w}. Such an axis gets snapshots at `LOG_AXIS_POINTS` evenly
    /// spaced points in ln p besides the centre, and the Latin-hypercube points spread over
    /// it in ln p. Used for parameters known only to orders of magnitude (the diagnosis's
    /// enrichments, e.g. a joint's rotational stiffness).
    #[serde(default)]
    pub log_axes: Vec<(String, f64)>,
    /// Solve the design's interior points (a logarithmic axis's inner points and the
    /// Latin-hypercube points) only while the basis does not yet reproduce them
    /// ([`ADAPTIVE_BATCH`], [`ADAPTIVE_TOL`]); false solves every point of the design. Options
    /// recorded before this field existed read as false, the design they were built with.
    #[serde(default)]
    pub adaptive: bool,
}

/// Snapshots along each logarithmic axis (besides the centre).
pub const LOG_AXIS_POINTS: usize = 8;

/// Points the adaptive design solves per round: the candidates whose residual indicator is
/// largest. Fixed, not the thread count, so that the basis is the same whatever the threads;
/// 4 keeps two cores busy with two solves each.
pub const ADAPTIVE_BATCH: usize = 4;

/// The adaptive design stops once the round's points (the candidates the indicator ranks
/// worst) are reproduced by the current ROM to within this relative frequency error, or to
/// within twice the ROM's own error at the points already solved, whichever is larger: the
/// latter is the basis cap's truncation error, which no further snapshot lowers. 1e-6 is a
/// hundredth of the accuracy the ROM tests ask over the box (1e-4) and a thousandth of the
/// diagnosis's practical threshold (0.1 %): a property of the tool, not of any lab's data. On
/// the capped bases the updating builds, the truncation rule is the one that stops the design.
/// The factor 2 allows a point outside the snapshots a larger error than the snapshots' own
/// (test against training error) while still telling it from a basis that misses a direction.
pub const ADAPTIVE_TOL: f64 = 1e-6;

/// Half-width (ln) of a shear-deformable board's transverse shear modulus's ROM axis: × or ÷ 2
/// about the board file's value, 2.3 of its prior sds (≥ 30 %,
/// [`crate::update::boards::G_Z_PRIOR_WIDTH`]) either way. The ±20 % box, right for moduli a
/// datasheet gives, spans less than one of them.
pub const G_Z_LOG_BOX: f64 = std::f64::consts::LN_2;

/// The basis cap for a ROM with `n_log_axes` logarithmic axes: a cap chosen for the ±20 % box
/// is raised to the default's 64 + 8 per such axis (over e^{±3} of a joint's rotational
/// stiffness the bolted ROM's worst frequency error is 1.3e-4 with 64 vectors and 3.0e-5 with
/// 80, `rom_with_a_logarithmic_axis_matches_the_full_model_along_it`).
pub fn basis_cap(cap: usize, n_log_axes: usize) -> usize {
    if n_log_axes == 0 {
        cap
    } else {
        cap.max(RomOptions::default().max_basis) + 8 * n_log_axes
    }
}

/// The basis of the updating's ROM on `map` (`update::rom_box::rom_for`) when its cap is `cap`
/// and its extra logarithmic axes `log_axes`: [`basis_cap`] over those and the map's own axes,
/// plus the three rigid-body vectors that lead the basis when the core thickness splits the
/// mass into two terms (a cap chosen for the elastic modes must not lose them: at a cap of 12
/// the labels could no longer be tracked). The propagation truncates the `fe rom` stage's ROM
/// to it, so that it predicts with the reduced model the posterior was computed with.
pub fn updating_basis(map: &ParamMap, cap: usize, log_axes: &[(String, f64)]) -> usize {
    let b = basis_cap(cap, with_own_log_axes(map, log_axes).len());
    if map
        .names
        .iter()
        .any(|n| n == super::params::names::CORE_THICKNESS)
    {
        b + 3
    } else {
        b
    }
}

/// `log_axes` and the parameter map's own logarithmic axes (the transverse shear modulus,
/// [`G_Z_LOG_BOX`]): every ROM of a model, the updating's and the `fe rom` stage's that the
/// propagation reads, spans the same box.
pub fn with_own_log_axes(map: &ParamMap, log_axes: &[(String, f64)]) -> Vec<(String, f64)> {
    let mut out = log_axes.to_vec();
    let g_z = super::params::names::G_Z;
    if map.names.iter().any(|m| m == g_z) && !out.iter().any(|(n, _)| n == g_z) {
        out.push((g_z.to_string(), G_Z_LOG_BOX));
    }
    out
}

impl Default for RomOptions {
    fn default() -> Self {
        RomOptions {
            n_modes: 8,
            n_extra: 4,
            box_rel: 0.2,
            n_random: 32,
            pod_tol: 1e-5,
            max_basis: 64,
            seed: 20_240_613,
            derivative_snapshots: true,
            log_axes: Vec::new(),
            adaptive: true,
        }
    }
}

/// A built ROM: plain data, serialisable with [`Rom::to_npz_bytes`].
#[derive(Clone, Debug)]
pub struct Rom {
    /// Parameter names, nominal values and coefficient map (same as the full model's).
    pub map: ParamMap,
    /// Reduced stiffness terms Kᵢʳ (r × r each).
    pub k_r: Vec<Mat<f64>>,
    /// Reduced mass terms Mⱼʳ (r × r each).
    pub m_r: Vec<Mat<f64>>,
    /// Basis V (n_dof × r), M₀-orthonormal.
    pub basis: Mat<f64>,
    /// Number of rigid-body vectors leading the basis (3 free, 0 bolted).
    pub n_rigid: usize,
    /// Modes the ROM was built for.
    pub n_modes: usize,
    /// Setup label, `"free"` or `"bolted"`.
    pub setup: String,
    /// Upper triangles of `k_r`, packed ([`super::dense::packed_upper`]), for the hot path.
    pub(crate) k_flat: Vec<Vec<f64>>,
    /// The box the ROM was built over (its snapshots span it), about `map.nominal`; None for a
    /// ROM read from an NPZ written before it was recorded.
    pub built_box: Option<RomBox>,
}

/// The parameter box a ROM was built over, about its centre: ±`box_rel` relative, except the
/// logarithmic axes (name, w), over e^{±w}. Whoever evaluates the ROM (the propagation)
/// checks its draws against this box, the one the snapshots spanned and the update steps
/// checked the ROM over (a step that widened it records the wider one).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RomBox {
    pub box_rel: f64,
    pub log_axes: Vec<(String, f64)>,
}

/// Reduced operator from reduced coordinates to w at given points: P = S V.
#[derive(Clone, Debug)]
pub struct RomShapeOperator {
    /// Points `[x_m, y_m]`.
    pub points_m: Vec<[f64; 2]>,
    /// P, n_points × r.
    pub p: Mat<f64>,
    /// Row-major copy of P for the hot path.
    p_rows: Vec<f64>,
}

/// Analytic derivatives of the ROM's modes with respect to every parameter.
#[derive(Clone, Debug)]
pub struct RomDerivatives {
    /// ∂λ_j/∂p_k, n_modes × n_params.
    pub d_eigenvalue: Mat<f64>,
    /// ∂f_j/∂p_k (Hz per parameter unit), n_modes × n_params.
    pub d_freq_hz: Mat<f64>,
    /// ∂w/∂p_k at the operator's points, one n_points × n_modes matrix per parameter.
    pub d_shapes_at_points: Vec<Mat<f64>>,
}

/// The ROM's modes at one parameter point.
#[derive(Clone, Debug)]
pub struct RomModes {
    /// Frequencies, Hz.
    pub freq_hz: Vec<f64>,
    /// Eigenvalues ω², rad²/s².
    pub eigenvalues: Vec<f64>,
    /// Mass-normalised reduced eigenvectors y (r × n), full shape = V y.
    pub reduced: Mat<f64>,
    /// w at the operator's points, n_points × n (1/√kg).
    pub shapes_at_points: Mat<f64>,
}

fn lhs_points(n: usize, dim: usize, rng: &mut ChaCha8Rng) -> Vec<Vec<f64>> {
    // Latin hypercube on [-1, 1]^dim: one point per stratum and dimension.
    let mut cols: Vec<Vec<f64>> = Vec::with_capacity(dim);
    for _ in 0..dim {
        let mut perm: Vec<usize> = (0..n).collect();
        for i in (1..n).rev() {
            let j = rng.random_range(0..=i);
            perm.swap(i, j);
        }
        cols.push(
            perm.iter()
                .map(|&k| -1.0 + 2.0 * (k as f64 + rng.random::<f64>()) / n as f64)
                .collect(),
        );
    }
    (0..n)
        .map(|i| (0..dim).map(|d| cols[d][i]).collect())
        .collect()
}

/// `n` Latin-hypercube points in the ±`box_rel` box around the nominal parameters of
/// `map` (parameters with nominal 0 stay 0). Deterministic in `seed`.
pub fn latin_hypercube_params(map: &ParamMap, n: usize, box_rel: f64, seed: u64) -> Vec<Params> {
    latin_hypercube_params_log(map, n, box_rel, &[], seed)
}

/// As [`latin_hypercube_params`], with the parameters of `log_axes` spread over
/// nominal · e^{±w} in ln p (see [`RomOptions::log_axes`]).
pub fn latin_hypercube_params_log(
    map: &ParamMap,
    n: usize,
    box_rel: f64,
    log_axes: &[(String, f64)],
    seed: u64,
) -> Vec<Params> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let log_w: Vec<Option<f64>> = map
        .names
        .iter()
        .map(|nm| log_axes.iter().find(|(a, _)| a == nm).map(|(_, w)| *w))
        .collect();
    lhs_points(n, map.names.len(), &mut rng)
        .into_iter()
        .map(|u| Params {
            names: map.names.clone(),
            values: map
                .nominal
                .iter()
                .zip(&u)
                .zip(&log_w)
                .map(|((v, t), w)| match w {
                    Some(w) => v * (w * t).exp(),
                    None => v * (1.0 + box_rel * t),
                })
                .collect(),
        })
        .collect()
}

impl Rom {
    /// Build the ROM of `model` (see the module doc for the snapshot design).
    pub fn build(model: &FeModel, opts: &RomOptions) -> Result<Rom, FemError> {
        if opts.n_modes == 0 || !(opts.box_rel >= 0.0 && opts.box_rel < 1.0) {
            return Err(FemError::Request(format!(
                "ROM options: expected n_modes >= 1 and 0 <= box_rel < 1, found {} and {}",
                opts.n_modes, opts.box_rel
            )));
        }
        let n = model.n_dof;
        let nominal = model.nominal_params();
        for (name, w) in &opts.log_axes {
            nominal.position(name)?;
            if !(w.is_finite() && *w > 0.0) {
                return Err(FemError::Request(format!(
                    "ROM options: log axis {name:?} needs a positive finite half-width, found {w}"
                )));
            }
        }
        let (first, mut pool) = snapshot_design(model, &nominal, opts);

        let c0 = model.coefficients(&nominal)?;
        let m0 = model.m_values(&c0.m);
        let mdot = m_product(model, &m0);
        let lead = rigid_lead(model, &mdot);
        let m_lead: Vec<Vec<f64>> = lead.iter().map(|l| mdot(l)).collect();
        // Snapshots, M₀-orthogonalised against the lead vectors. The full-model solves are
        // independent: one per point on the rayon pool (the FE kernels themselves are
        // sequential), the derivative snapshots' solve beside them; results in point order,
        // so the basis is the same whatever the thread count.
        let orthogonal = |mut v: Vec<f64>| {
            for _ in 0..2 {
                for (l, ml) in lead.iter().zip(&m_lead) {
                    let c: f64 = ml.iter().zip(&v).map(|(a, b)| a * b).sum();
                    v.iter_mut().zip(l).for_each(|(x, y)| *x -= c * y);
                }
            }
            v
        };
        let n_snap_modes = opts.n_modes + opts.n_extra;
        let solve = |points: &[Params]| {
            points
                .par_iter()
                .map(|p| model.modes(p, n_snap_modes))
                .collect::<Result<Vec<_>, _>>()
        };
        let (point_modes, centre_derivatives) = rayon::join(
            || solve(&first),
            || -> Result<_, FemError> {
                // The adaptive design leaves the derivatives out: each mode's Nelson solve is a
                // sparse LU of K − λM, and the centre's twelve took longer than all the points
                // the design solved, while the axis ends' snapshots span p ∂φ/∂p to second
                // order in the step.
                if !opts.derivative_snapshots || opts.adaptive {
                    return Ok(None);
                }
                let modes = model.modes(&nominal, n_snap_modes)?;
                let d = super::sensitivity::eigen_derivatives(model, &nominal, &modes, true)?;
                Ok(Some(d))
            },
        );
        let point_modes = point_modes?;
        let mut snaps: Vec<Vec<f64>> = Vec::new();
        let push_modes = |snaps: &mut Vec<Vec<f64>>, modes: &super::Modes| {
            for j in 0..modes.shapes.ncols() {
                snaps.push(orthogonal((0..n).map(|i| modes.shapes[(i, j)]).collect()));
            }
        };
        for modes in &point_modes {
            push_modes(&mut snaps, modes);
        }
        // Derivative snapshots at the centre: p_k ∂φ_j/∂p_k (Nelson), which carry the
        // first-order change of every mode over the box.
        if let Some(d) = centre_derivatives? {
            for (k, dk) in d.d_shapes.unwrap_or_default().iter().enumerate() {
                let pk = nominal.values[k];
                for j in 0..dk.ncols() {
                    snaps.push(orthogonal((0..n).map(|i| pk * dk[(i, j)]).collect()));
                }
            }
        }
        let assemble = |snaps: &[Vec<f64>]| assemble_rom(model, opts, (snaps, &lead), (&c0, &m0));
        if !opts.adaptive {
            return assemble(&snaps);
        }
        // The adaptive rounds: rank the candidates by the residual of the current ROM's modes
        // in the full model (no solve), solve the worst few, and stop once the ROM reproduced
        // them; otherwise add them and build again.
        let mut solved: Vec<(Params, Vec<f64>)> = first
            .into_iter()
            .zip(&point_modes)
            .map(|(p, m)| (p, m.freq_hz[..opts.n_modes.min(m.freq_hz.len())].to_vec()))
            .collect();
        let mut rom = assemble(&snaps)?;
        while !pool.is_empty() {
            let score = pool
                .par_iter()
                .map(|p| rom.residual_indicator(model, p))
                .collect::<Result<Vec<f64>, _>>()?;
            let mut order: Vec<usize> = (0..pool.len()).collect();
            order.sort_by(|a, b| score[*b].total_cmp(&score[*a]).then(a.cmp(b)));
            let mut take: Vec<usize> = order.into_iter().take(ADAPTIVE_BATCH).collect();
            take.sort_unstable();
            let batch: Vec<Params> = take.iter().map(|&i| pool[i].clone()).collect();
            for &i in take.iter().rev() {
                pool.remove(i);
            }
            let modes = solve(&batch)?;
            let err_at = |p: &Params, f: &[f64]| rom.freq_error(p, f);
            let err_new = batch
                .iter()
                .zip(&modes)
                .map(|(p, m)| err_at(p, &m.freq_hz))
                .collect::<Result<Vec<_>, _>>()?
                .into_iter()
                .fold(0.0, f64::max);
            let err_own = solved
                .iter()
                .map(|(p, f)| err_at(p, f))
                .collect::<Result<Vec<_>, _>>()?
                .into_iter()
                .fold(0.0, f64::max);
            if err_new <= ADAPTIVE_TOL.max(2.0 * err_own) {
                break;
            }
            for (p, m) in batch.into_iter().zip(&modes) {
                push_modes(&mut snaps, m);
                solved.push((p, m.freq_hz[..opts.n_modes.min(m.freq_hz.len())].to_vec()));
            }
            rom = assemble(&snaps)?;
        }
        Ok(rom)
    }

    /// The largest estimated relative frequency error of this ROM's modes at `p` in `model`,
    /// from the residual r = K(p)φ − λM(p)φ of each Ritz pair (φ = V y, M-normalised): by
    /// Kato–Temple the eigenvalue error is at most ‖r‖²_{M⁻¹} / gap, gap the distance to the
    /// nearest other eigenvalue, so the frequency error is about ‖r‖²_{M⁻¹} / (2 λ gap); M⁻¹
    /// is taken as the inverse of M's diagonal (Jacobi), which makes this an estimate for
    /// ranking candidate snapshot points, not a bound. A few sparse products, no solve.
    fn residual_indicator(&self, model: &FeModel, p: &Params) -> Result<f64, FemError> {
        let c = model.coefficients(p)?;
        // The ROM's own modes (the top one's gap is to the mode below it).
        let red = self.eval_lowest(&c.k, &c.m, self.n_modes)?;
        let (kv, mv) = (model.k_values(&c.k), model.m_values(&c.m));
        let pat = &model.pattern;
        let n = model.n_dof;
        let mut m_diag = vec![0.0; n];
        for col in 0..n {
            for t in pat.col_ptr[col]..pat.col_ptr[col + 1] {
                if pat.row_idx[t] == col {
                    m_diag[col] = mv[t];
                }
            }
        }
        let y = Mat::from_fn(self.dim(), red.vectors.len(), |i, j| red.vectors[j][i]);
        let ritz = product_seq(self.basis.as_ref(), y.as_ref());
        // K Φ and M Φ for all the Ritz vectors in one pass over the pattern each.
        let w = ritz.ncols();
        let phi = rows_of(&ritz, 0, w);
        let (mut kx, mut mx) = (vec![0.0; n * w], vec![0.0; n * w]);
        pat.matmat_rows(&kv, &phi, w, &mut kx);
        pat.matmat_rows(&mv, &phi, w, &mut mx);
        let lam = &red.eigenvalues;
        let mut worst = 0.0f64;
        for j in 0..lam.len() {
            let r2: f64 = (0..n)
                .filter(|&i| m_diag[i] > 0.0)
                .map(|i| (kx[i * w + j] - lam[j] * mx[i * w + j]).powi(2) / m_diag[i])
                .sum();
            let gap = [j.checked_sub(1), Some(j + 1)]
                .into_iter()
                .flatten()
                .filter_map(|k| lam.get(k))
                .map(|l| (l - lam[j]).abs())
                .fold(f64::INFINITY, f64::min)
                .min(lam[j]);
            if lam[j] > 0.0 && gap > 0.0 {
                worst = worst.max(r2 / (2.0 * lam[j] * gap));
            }
        }
        Ok(worst)
    }

    /// The worst relative error of this ROM's lowest frequencies at `p` against the full
    /// model's `freq_hz` (ascending, as solved).
    fn freq_error(&self, p: &Params, freq_hz: &[f64]) -> Result<f64, FemError> {
        let c = self.map.coefficients(p)?;
        let red = self.eval_lowest(&c.k, &c.m, self.n_modes)?;
        Ok(red
            .eigenvalues
            .iter()
            .zip(freq_hz)
            .map(|(l, f)| (l.max(0.0).sqrt() / (2.0 * std::f64::consts::PI) / f - 1.0).abs())
            .fold(0.0, f64::max))
    }
}

/// The snapshot points of `opts`'s design: those solved first, and the candidates the adaptive
/// rounds choose from (empty where the design is not adaptive: every point is solved first, in
/// the order a full design always had). First: the centre, each ±`box_rel` axis end, each
/// logarithmic axis's two ends; candidates: the logarithmic axes' inner points, then the
/// Latin-hypercube points.
pub(crate) fn snapshot_design(
    model: &FeModel,
    nominal: &Params,
    opts: &RomOptions,
) -> (Vec<Params>, Vec<Params>) {
    let mut first = vec![nominal.clone()];
    let mut inner = Vec::new();
    for k in 0..nominal.values.len() {
        let log_w = opts
            .log_axes
            .iter()
            .find(|(a, _)| *a == nominal.names[k])
            .map(|(_, w)| *w);
        let factors: Vec<(f64, bool)> = match log_w {
            Some(w) => (0..LOG_AXIS_POINTS)
                .map(|i| {
                    let t = -1.0 + 2.0 * i as f64 / (LOG_AXIS_POINTS - 1) as f64;
                    ((w * t).exp(), i == 0 || i + 1 == LOG_AXIS_POINTS)
                })
                .collect(),
            None => vec![(1.0 - opts.box_rel, true), (1.0 + opts.box_rel, true)],
        };
        for (f, end) in factors {
            let mut p = nominal.clone();
            p.values[k] *= f;
            if p.values[k] != nominal.values[k] {
                if end || !opts.adaptive {
                    first.push(p);
                } else {
                    inner.push(p);
                }
            }
        }
    }
    let lhs = latin_hypercube_params_log(
        &model.map,
        opts.n_random,
        opts.box_rel,
        &opts.log_axes,
        opts.seed,
    );
    if opts.adaptive {
        inner.extend(lhs);
    } else {
        first.extend(lhs);
    }
    (first, inner)
}

/// x ↦ M₀ x, M₀ the mass matrix with values `m0` on `model`'s pattern.
fn m_product<'a>(model: &'a FeModel, m0: &'a [f64]) -> impl Fn(&[f64]) -> Vec<f64> + 'a {
    move |x: &[f64]| {
        let mut y = vec![0.0; model.n_dof];
        model.pattern.matvec(m0, x, &mut y);
        y
    }
}

/// The free board's rigid-body vectors (w = 1, x, y), M₀-orthonormal; none for other setups.
fn rigid_lead(model: &FeModel, mdot: &impl Fn(&[f64]) -> Vec<f64>) -> Vec<Vec<f64>> {
    let n = model.n_dof;
    let mut lead: Vec<Vec<f64>> = Vec::new();
    if matches!(model.setup, Setup::Free) {
        let mesh = &model.mesh;
        for kind in 0..3 {
            let mut r = vec![0.0; n];
            for j in 0..=mesh.ny {
                for i in 0..=mesh.nx {
                    if let Some(d) = mesh.node_dof[j * (mesh.nx + 1) + i] {
                        let (x, y) = (mesh.x_m[i], mesh.y_m[j]);
                        match kind {
                            0 => r[d] = 1.0,
                            1 => {
                                r[d] = x;
                                r[d + 1] = 1.0;
                            }
                            _ => {
                                r[d] = y;
                                r[d + 2] = 1.0;
                            }
                        }
                    }
                }
            }
            lead.push(r);
        }
        m_gram_schmidt(&mut lead, mdot);
    }
    lead
}

/// The ROM whose basis is the M-weighted POD of `snaps` (led by `lead`, the rigid vectors),
/// truncated by `opts`, with every affine term projected on it.
fn assemble_rom(
    model: &FeModel,
    opts: &RomOptions,
    (snaps, lead): (&[Vec<f64>], &[Vec<f64>]),
    (c0, m0): (&super::params::Coefficients, &[f64]),
) -> Result<Rom, FemError> {
    let n = model.n_dof;
    let free = matches!(model.setup, Setup::Free);
    let mdot = m_product(model, m0);
    // M-weighted POD via the Gram matrix G = Sᵀ M₀ S (dense products, see `at_b`).
    let ns = snaps.len();
    let s_mat = Mat::from_fn(n, ns, |i, j| snaps[j][i]);
    let ms_mat = by_column_chunks(n, ns, |j0, w| {
        sparse_times(&model.pattern, m0, &s_mat, j0, w)
    });
    let gram = by_column_chunks(ns, ns, |j0, w| {
        at_b(s_mat.as_ref(), ms_mat.as_ref().subcols(j0, w))
    });
    // Largest Gram eigenpairs = lowest of −G, by the sequential dense solver.
    let max_pod = opts.max_basis.saturating_sub(if model.m_terms.len() > 1 {
        lead.len()
    } else {
        0
    });
    let mut neg_g = vec![0.0; ns * ns];
    for i in 0..ns {
        for j in 0..ns {
            neg_g[i * ns + j] = -gram[(i, j)];
        }
    }
    let se = super::dense::lowest_eigenpairs(&mut neg_g, ns, 0, max_pod.min(ns));
    let smax = (-se.values[0]).max(0.0);
    let mut pod: Vec<Vec<f64>> = Vec::new();
    let n_pod = se
        .values
        .iter()
        .take(se.vectors.len())
        .take_while(|v| {
            let sk = -**v;
            sk > 0.0 && sk.sqrt() >= opts.pod_tol * smax.sqrt()
        })
        .count();
    if n_pod > 0 {
        // The POD vectors S U, one dense product.
        let u = Mat::from_fn(ns, n_pod, |i, k| se.vectors[k][i]);
        let su = product_seq(s_mat.as_ref(), u.as_ref());
        crate::simd::clear_upper_vector_state();
        pod.extend((0..n_pod).map(|k| (0..n).map(|i| su[(i, k)]).collect::<Vec<f64>>()));
    }
    // With one mass term M(p) ∝ M₀, so the elastic modes stay M₀-orthogonal to the
    // rigid ones for every p: the rigid vectors can be left out of the basis (the
    // snapshots were orthogonalised against them), which shrinks r by 3. With more
    // mass terms they must stay in, and the evaluation drops their eigenvalues.
    let keep_rigid = model.m_terms.len() > 1;
    let mut vecs = if keep_rigid {
        lead.to_vec()
    } else {
        Vec::new()
    };
    let n_rigid = vecs.len();
    vecs.extend(pod);
    m_gram_schmidt(&mut vecs, &mdot);
    if !keep_rigid {
        // One mass term M(p) = c_m(p) M₁: the evaluation's hot path takes Mʳ = c_m I,
        // so the basis must be orthonormal in M₁ itself, not in M(centre) = c_m(centre)
        // M₁. The two differ when the centre's mass coefficient is not 1 (a ROM centred
        // on a posterior mean of `mass_scale`): every eigenvalue was off by that factor.
        let s = c0.m[0].sqrt();
        for v in &mut vecs {
            v.iter_mut().for_each(|x| *x *= s);
        }
    }
    let r = vecs.len();
    let basis = Mat::from_fn(n, r, |i, j| vecs[j][i]);
    // Vᵀ T V per affine term, the terms in parallel (each product sequential: the same
    // bytes whatever the thread count).
    let basis_rows = rows_of(&basis, 0, r);
    let project = |val: &Vec<f64>| -> Mat<f64> {
        let kv = sparse_times_rows(&model.pattern, val, &basis_rows, r);
        let mut m = at_b(basis.as_ref(), kv.as_ref());
        symmetrize(&mut m);
        m
    };
    let k_r = model.k_terms.par_iter().map(project).collect();
    let m_r = model.m_terms.par_iter().map(project).collect();
    let mut rom = Rom::from_parts(
        model.map.clone(),
        k_r,
        m_r,
        basis,
        n_rigid,
        opts.n_modes,
        if free { "free".into() } else { "bolted".into() },
    );
    rom.built_box = Some(RomBox {
        box_rel: opts.box_rel,
        log_axes: opts.log_axes.clone(),
    });
    Ok(rom)
}

impl Rom {
    /// Assemble a ROM from its parts (used by the builder and the NPZ loader).
    pub fn from_parts(
        map: ParamMap,
        k_r: Vec<Mat<f64>>,
        m_r: Vec<Mat<f64>>,
        basis: Mat<f64>,
        n_rigid: usize,
        n_modes: usize,
        setup: String,
    ) -> Rom {
        let k_flat = k_r
            .iter()
            .map(|m| super::dense::packed_upper(m.nrows(), |i, j| m[(i, j)]))
            .collect();
        Rom {
            map,
            k_r,
            m_r,
            basis,
            n_rigid,
            n_modes,
            setup,
            k_flat,
            built_box: None,
        }
    }

    /// Basis dimension r.
    pub fn dim(&self) -> usize {
        self.basis.ncols()
    }

    /// The nominal parameters.
    pub fn nominal_params(&self) -> Params {
        self.map.nominal_params()
    }

    /// Reduced shape operator for `points_m`: P = S V with S from the full model.
    pub fn shape_operator(
        &self,
        model: &FeModel,
        points_m: &[[f64; 2]],
    ) -> Result<RomShapeOperator, FemError> {
        if model.n_dof != self.basis.nrows() {
            return Err(FemError::Request(format!(
                "shape operator: expected a model with {} DOFs, found {}",
                self.basis.nrows(),
                model.n_dof
            )));
        }
        let s = model.shape_operator(points_m)?;
        let p = s.apply(self.basis.as_ref());
        let p_rows = (0..p.nrows())
            .flat_map(|i| (0..p.ncols()).map(move |j| (i, j)))
            .map(|(i, j)| p[(i, j)])
            .collect();
        Ok(RomShapeOperator {
            points_m: points_m.to_vec(),
            p,
            p_rows,
        })
    }

    /// Lowest `self.n_modes` elastic modes at `p`, with shapes at the operator's points.
    pub fn eval(&self, p: &Params, shapes: &RomShapeOperator) -> Result<RomModes, FemError> {
        let c = self.map.coefficients(p)?;
        self.eval_coefs(&c.k, &c.m, shapes)
    }

    /// [`Rom::eval`] from raw affine coefficients (no parameter checks; for samplers
    /// that have validated their parameters already).
    pub fn eval_coefs(
        &self,
        ck: &[f64],
        cm: &[f64],
        shapes: &RomShapeOperator,
    ) -> Result<RomModes, FemError> {
        let r = self.dim();
        if shapes.p.ncols() != r {
            return Err(FemError::Request(format!(
                "shape operator: expected {r} reduced coordinates, found {}",
                shapes.p.ncols()
            )));
        }
        let want = self.n_modes + self.n_rigid;
        if want > r {
            return Err(FemError::Request(format!(
                "ROM: expected at least {want} basis vectors, found {r}"
            )));
        }
        if ck.len() != self.k_r.len() || cm.len() != self.m_r.len() {
            return Err(FemError::Request(format!(
                "coefficients: expected {} stiffness and {} mass, found {} and {}",
                self.k_r.len(),
                self.m_r.len(),
                ck.len(),
                cm.len()
            )));
        }
        if self.m_r.len() == 1 {
            return Ok(self.eval_single_mass(ck, cm[0], shapes));
        }
        let mut k = Mat::<f64>::zeros(r, r);
        for (ci, ki) in ck.iter().zip(&self.k_r) {
            axpy_mat(&mut k, *ci, ki.as_ref());
        }
        let (lam, y) = {
            let (l, ct) = self.whitened(k, cm)?;
            let l = l.as_ref();
            let evd = ct
                .self_adjoint_eigen(Side::Lower)
                .map_err(|e| FemError::Eigen(format!("reduced eigen-solve: {e:?}")))?;
            let s = evd.S().column_vector();
            let u = evd.U();
            let lam: Vec<f64> = (self.n_rigid..want).map(|i| s[i]).collect();
            let mut z = Mat::from_fn(r, self.n_modes, |i, j| u[(i, self.n_rigid + j)]);
            faer::linalg::triangular_solve::solve_upper_triangular_in_place(
                l.transpose(),
                z.as_mut(),
                faer::Par::Seq,
            );
            (lam, z)
        };
        // Deterministic sign (see `eigen::sign_weight`).
        let mut y = y;
        for j in 0..y.ncols() {
            if (0..r)
                .map(|i| super::eigen::sign_weight(i) * y[(i, j)])
                .sum::<f64>()
                < 0.0
            {
                for i in 0..r {
                    y[(i, j)] = -y[(i, j)];
                }
            }
        }
        let w = &shapes.p * &y;
        Ok(RomModes {
            freq_hz: lam
                .iter()
                .map(|l| l.max(0.0).sqrt() / (2.0 * std::f64::consts::PI))
                .collect(),
            eigenvalues: lam,
            reduced: y,
            shapes_at_points: w,
        })
    }

    /// Hot path for one mass term: Mʳ = d₀ I, so the modes are the eigenpairs of
    /// Kʳ/d₀, solved by [`super::dense::lowest_eigenpairs`] for the wanted ones only.
    fn eval_single_mass(&self, ck: &[f64], d0: f64, shapes: &RomShapeOperator) -> RomModes {
        let r = self.dim();
        let nm = self.n_modes;
        let mut a = super::dense::upper_sum(ck, &self.k_flat, r);
        let se = super::dense::wanted_eigenpairs(&mut a, r, self.n_rigid, nm);
        let lam: Vec<f64> = se.values[..nm].iter().map(|v| v / d0).collect();
        let scale = 1.0 / d0.sqrt();
        let mut reduced = Mat::<f64>::zeros(r, nm);
        let npts = shapes.p.nrows();
        let mut w = Mat::<f64>::zeros(npts, nm);
        for (j, z) in se.vectors.iter().enumerate() {
            let sgn = if (0..r)
                .map(|i| super::eigen::sign_weight(i) * z[i])
                .sum::<f64>()
                < 0.0
            {
                -scale
            } else {
                scale
            };
            let y: Vec<f64> = z.iter().map(|v| v * sgn).collect();
            for i in 0..r {
                reduced[(i, j)] = y[i];
            }
            for i in 0..npts {
                let row = &shapes.p_rows[i * r..(i + 1) * r];
                w[(i, j)] = row.iter().zip(&y).map(|(a, b)| a * b).sum();
            }
        }
        RomModes {
            freq_hz: lam
                .iter()
                .map(|l| l.max(0.0).sqrt() / (2.0 * std::f64::consts::PI))
                .collect(),
            eigenvalues: lam,
            reduced,
            shapes_at_points: w,
        }
    }

    /// [`Rom::eval`] plus analytic derivatives with respect to every parameter, by the
    /// same formulas as [`super::sensitivity`] applied to the reduced pencil
    /// (Kʳ(p), Mʳ(p)): ∂λ = yᵀ(∂Kʳ − λ ∂Mʳ)y, and Nelson's method for ∂y with a dense
    /// LU of the r × r matrix Kʳ − λMʳ; shapes ∂w = P ∂y. For gradient-based samplers.
    pub fn eval_with_derivatives(
        &self,
        p: &Params,
        shapes: &RomShapeOperator,
    ) -> Result<(RomModes, RomDerivatives), FemError> {
        use faer::linalg::solvers::Solve;
        let c = self.map.coefficients(p)?;
        let modes = self.eval_coefs(&c.k, &c.m, shapes)?;
        let r = self.dim();
        let np = p.values.len();
        let nm = self.n_modes;
        let mut k = Mat::<f64>::zeros(r, r);
        for (ci, ki) in c.k.iter().zip(&self.k_r) {
            axpy_mat(&mut k, *ci, ki.as_ref());
        }
        let mut m = Mat::<f64>::zeros(r, r);
        for (ci, mi) in c.m.iter().zip(&self.m_r) {
            axpy_mat(&mut m, *ci, mi.as_ref());
        }
        let weighted = |grads: &[Vec<f64>], terms: &[Mat<f64>], kk: usize| {
            let mut out = Mat::<f64>::zeros(r, r);
            for (g, t) in grads.iter().zip(terms) {
                if g[kk] != 0.0 {
                    axpy_mat(&mut out, g[kk], t.as_ref());
                }
            }
            out
        };
        let dks: Vec<Mat<f64>> = (0..np)
            .map(|kk| weighted(&c.k_grad, &self.k_r, kk))
            .collect();
        let dms: Vec<Mat<f64>> = (0..np)
            .map(|kk| weighted(&c.m_grad, &self.m_r, kk))
            .collect();
        let mut d_lam = Mat::<f64>::zeros(nm, np);
        let mut d_f = Mat::<f64>::zeros(nm, np);
        let mut d_y: Vec<Mat<f64>> = (0..np).map(|_| Mat::<f64>::zeros(r, nm)).collect();
        for j in 0..nm {
            let y = modes.reduced.col(j);
            let lam = modes.eigenvalues[j];
            let my = &m * y;
            let q = (0..r)
                .max_by(|&a, &b| y[a].abs().total_cmp(&y[b].abs()))
                .unwrap_or(0);
            let mut a = Mat::from_fn(r, r, |i, jj| k[(i, jj)] - lam * m[(i, jj)]);
            for t in 0..r {
                a[(q, t)] = 0.0;
                a[(t, q)] = 0.0;
            }
            a[(q, q)] = 1.0;
            let lu = a.partial_piv_lu();
            let mut rhs = Mat::<f64>::zeros(r, np);
            let mut ydmy = vec![0.0; np];
            for kk in 0..np {
                let dky = &dks[kk] * y;
                let dmy = &dms[kk] * y;
                let dl: f64 = (0..r).map(|i| y[i] * (dky[i] - lam * dmy[i])).sum();
                d_lam[(j, kk)] = dl;
                d_f[(j, kk)] =
                    dl / (4.0 * std::f64::consts::PI * lam.max(f64::MIN_POSITIVE).sqrt());
                ydmy[kk] = (0..r).map(|i| y[i] * dmy[i]).sum();
                for i in 0..r {
                    rhs[(i, kk)] = -(dky[i] - lam * dmy[i] - dl * my[i]);
                }
                rhs[(q, kk)] = 0.0;
            }
            let v = lu.solve(&rhs);
            for kk in 0..np {
                let cc = -(0..r).map(|i| my[i] * v[(i, kk)]).sum::<f64>() - 0.5 * ydmy[kk];
                for i in 0..r {
                    d_y[kk][(i, j)] = v[(i, kk)] + cc * y[i];
                }
            }
        }
        let d_shapes_at_points = d_y.iter().map(|dy| &shapes.p * dy).collect();
        Ok((
            modes,
            RomDerivatives {
                d_eigenvalue: d_lam,
                d_freq_hz: d_f,
                d_shapes_at_points,
            },
        ))
    }

    /// Full-DOF shapes V y of ROM modes (n_dof × n).
    pub fn expand(&self, modes: &RomModes) -> Mat<f64> {
        &self.basis * &modes.reduced
    }

    /// Serialise as NPZ (see [`super::npz`] for the layout).
    pub fn to_npz_bytes(&self) -> Vec<u8> {
        npz::rom_to_npz(self)
    }

    /// Read a ROM written by [`Rom::to_npz_bytes`].
    pub fn from_npz_bytes(bytes: &[u8]) -> Result<Rom, FemError> {
        npz::rom_from_npz(bytes)
    }
}

fn axpy_mat(dst: &mut Mat<f64>, a: f64, x: MatRef<'_, f64>) {
    for j in 0..dst.ncols() {
        for i in 0..dst.nrows() {
            dst[(i, j)] += a * x[(i, j)];
        }
    }
}

fn symmetrize(m: &mut Mat<f64>) {
    for j in 0..m.ncols() {
        for i in 0..j {
            let v = 0.5 * (m[(i, j)] + m[(j, i)]);
            m[(i, j)] = v;
            m[(j, i)] = v;
        }
    }
}

/// Columns of width [`PRODUCT_CHUNK`] per parallel task in [`by_column_chunks`]: fixed, not
/// derived from the thread count, so every entry is computed by the same sequence of
/// operations whatever the pool size.
const PRODUCT_CHUNK: usize = 32;

/// A `rows` × `q` matrix whose columns `j0 .. j0 + w` are `block(j0, w)`: the chunks of
/// [`PRODUCT_CHUNK`] columns in parallel, each on one thread, stitched in order. Why the
/// blocked products at all: on the bolted ROM's snapshots (n = 16,412, 744 columns) the
/// row-by-row dot products they replace took most of the ROM build.
fn by_column_chunks(
    rows: usize,
    q: usize,
    block: impl Fn(usize, usize) -> Mat<f64> + Sync,
) -> Mat<f64> {
    let starts: Vec<usize> = (0..q).step_by(PRODUCT_CHUNK).collect();
    let blocks: Vec<Mat<f64>> = starts
        .par_iter()
        .map(|&j0| block(j0, PRODUCT_CHUNK.min(q - j0)))
        .collect();
    let mut out = Mat::<f64>::zeros(rows, q);
    for (blk, &j0) in blocks.iter().zip(&starts) {
        out.as_mut().subcols_mut(j0, blk.ncols()).copy_from(blk);
    }
    out
}

/// T X[:, j0 .. j0 + w] for the sparse symmetric T (values `val` on `pattern`), on the
/// calling thread.
fn sparse_times(
    pattern: &super::sparse::Pattern,
    val: &[f64],
    x: &Mat<f64>,
    j0: usize,
    w: usize,
) -> Mat<f64> {
    sparse_times_rows(pattern, val, &rows_of(x, j0, w), w)
}

/// X[:, j0 .. j0 + w] row-major ([`super::sparse::Pattern::matmat_rows`]' layout).
fn rows_of(x: &Mat<f64>, j0: usize, w: usize) -> Vec<f64> {
    let n = x.nrows();
    let mut out = vec![0.0; n * w];
    for j in 0..w {
        for (i, v) in x.col_as_slice(j0 + j).iter().enumerate() {
            out[i * w + j] = *v;
        }
    }
    out
}

/// T X for X given row-major n × w ([`rows_of`]), as a matrix.
fn sparse_times_rows(
    pattern: &super::sparse::Pattern,
    val: &[f64],
    xr: &[f64],
    w: usize,
) -> Mat<f64> {
    let n = pattern.n;
    let mut yr = vec![0.0; n * w];
    pattern.matmat_rows(val, xr, w, &mut yr);
    Mat::from_fn(n, w, |i, j| yr[i * w + j])
}

/// Aᵀ B, one sequential faer product.
fn at_b(a: MatRef<'_, f64>, b: MatRef<'_, f64>) -> Mat<f64> {
    let mut out = Mat::<f64>::zeros(a.ncols(), b.ncols());
    faer::linalg::matmul::matmul(
        out.as_mut(),
        faer::Accum::Replace,
        a.transpose(),
        b,
        1.0,
        faer::Par::Seq,
    );
    crate::simd::clear_upper_vector_state();
    out
}

/// Two-pass modified Gram–Schmidt in the M-inner product; drops vectors that become
/// negligible (relative M-norm below 1e-10).
fn m_gram_schmidt(vecs: &mut Vec<Vec<f64>>, mdot: &impl Fn(&[f64]) -> Vec<f64>) {
    let mut out: Vec<Vec<f64>> = Vec::new();
    let mut mout: Vec<Vec<f64>> = Vec::new();
    for v in vecs.iter() {
        let mut w = v.clone();
        let n0 = {
            let mw = mdot(&w);
            w.iter().zip(&mw).map(|(a, b)| a * b).sum::<f64>().sqrt()
        };
        for _ in 0..2 {
            for (o, mo) in out.iter().zip(&mout) {
                let c: f64 = mo.iter().zip(&w).map(|(a, b)| a * b).sum();
                w.iter_mut().zip(o).for_each(|(x, y)| *x -= c * y);
            }
        }
        let mw = mdot(&w);
        let nrm = w.iter().zip(&mw).map(|(a, b)| a * b).sum::<f64>().sqrt();
        if nrm > 1e-10 * n0 {
            out.push(w.iter().map(|x| x / nrm).collect());
            mout.push(mw.iter().map(|x| x / nrm).collect());
        }
    }
    *vecs = out;
}

/// The lowest elastic modes of a ROM at one point, in reduced coordinates only.
#[derive(Clone, Debug)]
pub struct ReducedModes {
    /// Eigenvalues ω², rad²/s², ascending.
    pub eigenvalues: Vec<f64>,
    /// Mass-normalised reduced eigenvectors, `vectors[j]` of length r, sign as in
    /// [`Rom::eval`].
    pub vectors: Vec<Vec<f64>>,
}

impl Rom {
    /// The lowest `count` (≤ `n_modes`) elastic modes from raw affine coefficients, without
    /// shapes at points: the sampler's hot path, which needs only a few modes and forms its
    /// shape terms from the reduced vectors (see `bayes::boards`).
    pub fn eval_lowest(
        &self,
        ck: &[f64],
        cm: &[f64],
        count: usize,
    ) -> Result<ReducedModes, FemError> {
        let r = self.dim();
        let count = count.min(self.n_modes);
        if self.m_r.len() != 1 && ck.len() == self.k_r.len() && cm.len() == self.m_r.len() {
            return self.eval_lowest_pencil((ck, cm), count);
        }
        if self.m_r.len() != 1 || ck.len() != self.k_r.len() {
            // Coefficients of the wrong length: the full path, whose error says what it expected.
            let empty = RomShapeOperator {
                points_m: vec![],
                p: Mat::zeros(0, r),
                p_rows: vec![],
            };
            let m = self.eval_coefs(ck, cm, &empty)?;
            return Ok(ReducedModes {
                eigenvalues: m.eigenvalues[..count].to_vec(),
                vectors: (0..count)
                    .map(|j| (0..r).map(|i| m.reduced[(i, j)]).collect())
                    .collect(),
            });
        }
        let d0 = cm[0];
        // Only the upper triangle: the tridiagonalisation reads nothing else (half the
        // 49 × r² multiply-adds of the built-in board's stiffness terms).
        let mut a = super::dense::upper_sum(ck, &self.k_flat, r);
        let se = super::dense::wanted_eigenpairs(&mut a, r, self.n_rigid, count);
        let scale = 1.0 / d0.sqrt();
        let vectors = se
            .vectors
            .into_iter()
            .map(|z| mass_normalised(z, scale))
            .collect();
        Ok(ReducedModes {
            eigenvalues: se.values[..count].iter().map(|v| v / d0).collect(),
            vectors,
        })
    }
}

impl Rom {
    /// The pencil (Kʳ, Mʳ = Σ cm_j Mʳ_j) made standard: the Cholesky factor L of Mʳ and the
    /// symmetric C = L⁻¹ Kʳ L⁻ᵀ (symmetrised against rounding), for both several-mass paths.
    fn whitened(&self, k: Mat<f64>, cm: &[f64]) -> Result<(Mat<f64>, Mat<f64>), FemError> {
        let r = self.dim();
        let mut m = Mat::<f64>::zeros(r, r);
        for (ci, mi) in cm.iter().zip(&self.m_r) {
            axpy_mat(&mut m, *ci, mi.as_ref());
        }
        whiten(k, &m).map_err(|e| FemError::Factorisation(format!("reduced mass: {e}")))
    }

    /// [`Rom::eval_lowest`] for several mass terms (a point mass, the core thickness):
    /// Mʳ = L Lᵀ, the wanted eigenpairs of L⁻¹ Kʳ L⁻ᵀ by [`super::dense::wanted_eigenpairs`]
    /// (the hot path's solver, not a full eigen-decomposition: 5× faster per evaluation on the
    /// bolted board), y = L⁻ᵀ z, signed as [`Rom::eval_coefs`] signs them.
    fn eval_lowest_pencil(
        &self,
        (ck, cm): (&[f64], &[f64]),
        count: usize,
    ) -> Result<ReducedModes, FemError> {
        let r = self.dim();
        let up = super::dense::upper_sum(ck, &self.k_flat, r);
        let (l, ct) = self.whitened(symmetric_from_upper(&up, r), cm)?;
        let l = l.as_ref();
        // Only the upper triangle is read by the solver.
        let mut a = upper_row_major(&ct);
        let se = super::dense::wanted_eigenpairs(&mut a, r, self.n_rigid, count);
        let mut y = Mat::from_fn(r, count, |i, j| se.vectors[j][i]);
        faer::linalg::triangular_solve::solve_upper_triangular_in_place(
            l.transpose(),
            y.as_mut(),
            faer::Par::Seq,
        );
        let vectors = (0..count)
            .map(|j| mass_normalised((0..r).map(|i| y[(i, j)]).collect(), 1.0))
            .collect();
        Ok(ReducedModes {
            eigenvalues: se.values[..count].to_vec(),
            vectors,
        })
    }
}

/// The symmetric r × r matrix whose upper triangle is `u`'s (row-major, as
/// [`super::dense::upper_sum`] leaves it).
fn symmetric_from_upper(u: &[f64], r: usize) -> Mat<f64> {
    Mat::from_fn(
        r,
        r,
        |i, j| if j >= i { u[i * r + j] } else { u[j * r + i] },
    )
}

/// `m`'s upper triangle, row-major, its lower triangle 0: what the dense solvers read.
fn upper_row_major(m: &Mat<f64>) -> Vec<f64> {
    let r = m.nrows();
    (0..r * r)
        .map(|p| {
            if p % r >= p / r {
                m[(p / r, p % r)]
            } else {
                0.0
            }
        })
        .collect()
}

/// The pencil (K, M) made standard: the lower Cholesky factor L of M and the symmetric
/// C = L⁻¹ K L⁻ᵀ (symmetrised against rounding); Err with faer's reason where M is not
/// positive-definite.
pub(crate) fn whiten(k: Mat<f64>, m: &Mat<f64>) -> Result<(Mat<f64>, Mat<f64>), String> {
    let llt = m.llt(Side::Lower).map_err(|e| format!("{e:?}"))?;
    let l = llt.L();
    let mut c = k;
    faer::linalg::triangular_solve::solve_lower_triangular_in_place(l, c.as_mut(), faer::Par::Seq);
    let mut ct = c.transpose().to_owned();
    faer::linalg::triangular_solve::solve_lower_triangular_in_place(l, ct.as_mut(), faer::Par::Seq);
    symmetrize(&mut ct);
    Ok((l.to_owned(), ct))
}

/// The ROM restricted to a subspace of its reduced coordinates (a second-level Galerkin
/// reduction): Kˢ = Wᵀ Kʳ W for W (r × q) with orthonormal columns, and Mˢ = Wᵀ Mʳ W where
/// the ROM has several mass terms (with one, Mʳ = d₀ I and Mˢ = d₀ I). Built by
/// [`Rom::subspace`] from one mode's eigenvectors at a few points of a small parameter box,
/// it reproduces that mode there at a fraction of the cost (q³ instead of r³,
/// [`Rom::eval_nearest_in`]), its eigenvalue's error quadratic in the distance of the ROM's
/// eigenvector from the subspace (Rayleigh–Ritz). Its error is not assumed: the sampler
/// verifies it against the ROM (`bayes::surrogate::fit_subspace`).
#[derive(Clone, Debug)]
pub struct SubspaceRom {
    r: usize,
    q: usize,
    /// W, r × q, row-major.
    w: Vec<f64>,
    /// Wᵀ Kᵢʳ W, q × q each, upper triangle packed ([`super::dense::packed_upper`]).
    k_flat: Vec<Vec<f64>>,
    /// Wᵀ Mⱼʳ W, packed as `k_flat`; empty where the ROM has one mass term (Mʳ = d₀ I).
    m_flat: Vec<Vec<f64>>,
}

impl SubspaceRom {
    /// Subspace dimension q.
    pub fn dim(&self) -> usize {
        self.q
    }

    /// Σ cₖ Kₖˢ over the terms k in `which` (ascending), the part of Kˢ that
    /// [`Rom::eval_nearest_in_parts`] completes.
    pub fn k_part(&self, ck: &[f64], which: &[usize]) -> Vec<f64> {
        let mut a = vec![0.0; self.q * self.q];
        super::dense::upper_add(&mut a, ck, &self.k_flat, self.q, which);
        a
    }

    /// Wᵀ v: a vector of the ROM's reduced coordinates (length r) in the subspace's.
    pub fn project(&self, v: &[f64]) -> Vec<f64> {
        let q = self.q;
        let mut out = vec![0.0; q];
        for (row, vi) in self.w.chunks_exact(q).zip(v) {
            out.iter_mut().zip(row).for_each(|(o, w)| *o += w * vi);
        }
        out
    }
}

impl Rom {
    /// An orthonormal basis of the span of `vectors` (reduced coordinates, length r), picked
    /// greedily (largest remaining component first, orthogonalised twice) until every vector
    /// lies within `rel_tol` (relative to its norm) of the span, and the ROM projected on it.
    /// None where no vector is given.
    pub fn subspace(&self, vectors: &[Vec<f64>], rel_tol: f64) -> Option<SubspaceRom> {
        let r = self.dim();
        if vectors.is_empty() || vectors.iter().any(|v| v.len() != r) {
            return None;
        }
        let mut rest: Vec<Vec<f64>> = vectors
            .iter()
            .filter_map(|v| {
                let n = v.iter().map(|a| a * a).sum::<f64>().sqrt();
                (n > 0.0 && n.is_finite()).then(|| v.iter().map(|a| a / n).collect())
            })
            .collect();
        let mut basis: Vec<Vec<f64>> = vec![];
        while basis.len() < r {
            let (k, norm) = rest
                .iter()
                .enumerate()
                .map(|(k, v)| (k, v.iter().map(|a| a * a).sum::<f64>().sqrt()))
                .fold((usize::MAX, 0.0f64), |a, b| if b.1 > a.1 { b } else { a });
            if k == usize::MAX || norm <= rel_tol {
                break;
            }
            let mut u = rest.swap_remove(k);
            // Twice is enough (Kahan–Parlett): the second pass removes what rounding left.
            for _ in 0..2 {
                for b in &basis {
                    let c: f64 = b.iter().zip(&u).map(|(x, y)| x * y).sum();
                    u.iter_mut().zip(b).for_each(|(x, y)| *x -= c * y);
                }
            }
            let n = u.iter().map(|a| a * a).sum::<f64>().sqrt();
            if n <= 0.5 * rel_tol {
                continue;
            }
            u.iter_mut().for_each(|a| *a /= n);
            for v in rest.iter_mut() {
                let c: f64 = u.iter().zip(v.iter()).map(|(x, y)| x * y).sum();
                v.iter_mut().zip(&u).for_each(|(x, y)| *x -= c * y);
            }
            basis.push(u);
        }
        let q = basis.len();
        if q == 0 {
            return None;
        }
        let mut w = vec![0.0; r * q];
        for (j, b) in basis.iter().enumerate() {
            for i in 0..r {
                w[i * q + j] = b[i];
            }
        }
        let wm = Mat::from_fn(r, q, |i, j| w[i * q + j]);
        let project = |k: &Mat<f64>| {
            let kw = product_seq(k.as_ref(), wm.as_ref());
            let ks = product_seq(wm.transpose(), kw.as_ref());
            super::dense::packed_upper(q, |i, j| ks[(i, j)])
        };
        let k_flat = self.k_r.iter().map(project).collect();
        let m_flat = if self.m_r.len() == 1 {
            vec![]
        } else {
            self.m_r.iter().map(project).collect()
        };
        Some(SubspaceRom {
            r,
            q,
            w,
            k_flat,
            m_flat,
        })
    }

    /// One mode in the subspace `sub`, built from that mode's own eigenvectors over a
    /// parameter box: the Ritz pair of the projected pencil whose vector overlaps most with
    /// `target` (the mode's unit reference vector in the ROM's reduced coordinates, projected
    /// by [`SubspaceRom::project`]). Returns its eigenvalue, its vector lifted back to the
    /// ROM's reduced coordinates (mass-normalised, sign as in [`Rom::eval`]) and the
    /// overlap |yᵀ y_ref| / |y| that [`crate::bayes::modal`] tracks labels by.
    ///
    /// Why one mode at a time: a subspace spanned by one mode's vectors holds the few
    /// directions that mode sweeps over the box (q ≈ 10–20), where a subspace for every mode
    /// the labels are told apart from needs all of theirs (q ≈ 45 of the bolted ROM's 88).
    /// The Ritz value of the pair nearest the mode is accurate to the square of the mode's
    /// distance from the span (Rayleigh–Ritz); the other Ritz pairs mix other modes and are
    /// discarded. The accuracy is not assumed: `bayes::surrogate::fit_subspace` verifies it.
    pub fn eval_nearest_in(
        &self,
        sub: &SubspaceRom,
        ck: &[f64],
        cm: &[f64],
        target: &[f64],
    ) -> Result<(f64, Vec<f64>, f64), FemError> {
        self.eval_nearest_in_parts(sub, ck, cm, target, None)
    }

    /// [`Self::eval_nearest_in`] with Kˢ's terms outside `shared.1` already summed in
    /// `shared.0` ([`SubspaceRom::k_part`] at coefficients equal to `ck`'s there): the
    /// evaluations of one group of particles share every term but their own stiffness's.
    pub fn eval_nearest_in_parts(
        &self,
        sub: &SubspaceRom,
        ck: &[f64],
        cm: &[f64],
        target: &[f64],
        shared: Option<(&[f64], &[usize])>,
    ) -> Result<(f64, Vec<f64>, f64), FemError> {
        let (r, q) = (sub.r, sub.q);
        let k_sum = |ck: &[f64]| -> Vec<f64> {
            match shared {
                Some((part, rest)) => {
                    let mut a = part.to_vec();
                    super::dense::upper_add(&mut a, ck, &sub.k_flat, q, rest);
                    a
                }
                None => super::dense::upper_sum(ck, &sub.k_flat, q),
            }
        };
        let n_mass = sub.m_flat.len().max(1);
        if r != self.dim()
            || cm.len() != n_mass
            || ck.len() != sub.k_flat.len()
            || target.len() != q
        {
            return Err(FemError::Request(format!(
                "subspace: expected a ROM of dimension {r} with {n_mass} mass term(s), {} stiffness terms and a target of length {q}",
                sub.k_flat.len()
            )));
        }
        let lift = |z: &[f64]| -> Vec<f64> {
            (0..r)
                .map(|i| {
                    sub.w[i * q..(i + 1) * q]
                        .iter()
                        .zip(z)
                        .map(|(a, b)| a * b)
                        .sum::<f64>()
                })
                .collect()
        };
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
        if sub.m_flat.is_empty() {
            let d0 = cm[0];
            let mut a = k_sum(ck);
            let (value, z, overlap) =
                nearest_ritz(&mut a, q, target, |z: &[f64]| dot(z, target).abs());
            return Ok((
                value / d0,
                mass_normalised(lift(&z), 1.0 / d0.sqrt()),
                overlap,
            ));
        }
        // Several mass terms: the projected pencil (Kˢ, Mˢ) made standard by Mˢ = L Lᵀ,
        // A = L⁻¹ Kˢ L⁻ᵀ; an eigenvector z of A is s = L⁻ᵀ z in the subspace's coordinates
        // (Mˢ-normalised, so y = W s is Mʳ-normalised). The search starts from Lᵀ t, whose
        // s is the reference t itself; overlaps are measured on s, as the ROM's labels are.
        let ks = k_sum(ck);
        let ms = super::dense::upper_sum(cm, &sub.m_flat, q);
        let (l, c) = whiten(symmetric_from_upper(&ks, q), &symmetric_from_upper(&ms, q))
            .map_err(|e| FemError::Factorisation(format!("subspace mass: {e}")))?;
        let mut a = upper_row_major(&c);
        let start: Vec<f64> = (0..q)
            .map(|i| (i..q).map(|j| l[(j, i)] * target[j]).sum())
            .collect();
        // s = L⁻ᵀ z by back substitution (Lᵀ is upper triangular).
        let back = |z: &[f64]| -> Vec<f64> {
            let mut s = z.to_vec();
            for i in (0..q).rev() {
                let t: f64 = (i + 1..q).map(|j| l[(j, i)] * s[j]).sum();
                s[i] = (s[i] - t) / l[(i, i)];
            }
            s
        };
        let overlap_of = |z: &[f64]| {
            let s = back(z);
            dot(&s, target).abs() / dot(&s, &s).sqrt()
        };
        let (value, z, overlap) = nearest_ritz(&mut a, q, &start, overlap_of);
        Ok((value, mass_normalised(lift(&back(&z)), 1.0), overlap))
    }
}

/// The eigenpair of the symmetric `a` (row-major q × q, upper triangle read, overwritten)
/// whose vector overlaps `start` most by `overlap_of`, for [`Rom::eval_nearest_in`].
/// Rayleigh-quotient iteration from `start`: where it lands on a vector that overlaps by
/// more than 1/√2, that is the nearest Ritz pair (no other can overlap as much); otherwise
/// the Ritz values nearest `start`'s Rayleigh quotient, their vectors compared.
fn nearest_ritz(
    a: &mut [f64],
    q: usize,
    start: &[f64],
    overlap_of: impl Fn(&[f64]) -> f64,
) -> (f64, Vec<f64>, f64) {
    if let Some(found) = super::dense::rayleigh_quotient_iteration(a, q, start)
        .map(|(v, z)| {
            let o = overlap_of(&z);
            (v, z, o)
        })
        .filter(|t| t.2 > std::f64::consts::FRAC_1_SQRT_2)
    {
        return found;
    }
    let (mut num, mut den) = (0.0, 0.0);
    for i in 0..q {
        let row = &a[i * q + i + 1..(i + 1) * q];
        let off: f64 = row.iter().zip(&start[i + 1..]).map(|(x, y)| x * y).sum();
        num += start[i] * (a[i * q + i] * start[i] + 2.0 * off);
        den += start[i] * start[i];
    }
    let se = super::dense::nearest_eigenpairs(a, q, num / den, 3);
    let (k, o) = se
        .vectors
        .iter()
        .map(|z| overlap_of(z))
        .enumerate()
        .fold((0, -1.0f64), |a, b| if b.1 > a.1 { b } else { a });
    (se.values[k], se.vectors[k].clone(), o)
}

/// A · B as one sequential faer product: the same bits whatever the thread count.
fn product_seq(a: faer::MatRef<'_, f64>, b: faer::MatRef<'_, f64>) -> Mat<f64> {
    let mut out = Mat::<f64>::zeros(a.nrows(), b.ncols());
    faer::linalg::matmul::matmul(
        out.as_mut(),
        faer::Accum::Replace,
        a,
        b,
        1.0,
        faer::Par::Seq,
    );
    out
}

/// A unit eigenvector z of Kʳ/d₀ (Mʳ = d₀ I) as the mass-normalised vector `scale` · z
/// (`scale` = 1/√d₀), its sign fixed as every ROM mode's (see `eigen::sign_weight`).
fn mass_normalised(mut z: Vec<f64>, scale: f64) -> Vec<f64> {
    let neg = z
        .iter()
        .enumerate()
        .map(|(i, v)| super::eigen::sign_weight(i) * v)
        .sum::<f64>()
        < 0.0;
    let s = if neg { -scale } else { scale };
    z.iter_mut().for_each(|v| *v *= s);
    z
}

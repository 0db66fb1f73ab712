//! Local polynomial surrogates of a unit's modal terms, verified against the ROM, and the
//! target that uses them inside their verified box (the ROM everywhere else). Pure: no I/O.
//!
//! Why: once the reference ([`super::reference`]) has located each unit's posterior, the
//! sampler only visits a small box around it, where the map from parameters to the
//! likelihood's inputs (eigenvalues, 1 − MAC of every shape observation, mass) is smooth and
//! nearly quadratic. A total-degree Legendre polynomial fitted there by least squares costs
//! ~1 µs per evaluation against ~40–90 µs for the ROM's dense eigen-solve, and its error is
//! measured, not assumed: on fresh points in the box, in units of log-likelihood at the
//! reference's error scales. A unit whose surrogate misses the tolerance at every degree
//! keeps the ROM.
//!
//! Exactness does not rest on the surrogate: the sampler's final correction stage weights
//! every particle by L_ROM / L_surrogate (`smc::correct`), so the posterior and the evidence
//! are the ROM's; the surrogate's error only costs effective sample size, which is reported.
//! The correction prices each unit in subspaces of the ROM, one per updated mode
//! ([`fit_subspace`]), built over the same box: a Galerkin reduction, not a fit, verified to
//! |Δ log L| ≤ 1e-3 per unit against the ROM; beyond the box (or where a mode's Ritz vector
//! strays from its reference) the ROM itself answers.

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::sync::Arc;

use super::modal::{self, Terms, UnitData};
use super::smc::{stream_key, GlobalRole, Target};
use super::stats::{cholesky_jittered, lower_mul, lower_solve};
use super::target::ModalTarget;

/// Legendre P_0..P_p at u.
fn legendre(u: f64, p: usize, out: &mut [f64]) {
    out[0] = 1.0;
    if p >= 1 {
        out[1] = u;
    }
    for k in 2..=p {
        let kf = k as f64;
        out[k] = ((2.0 * kf - 1.0) * u * out[k - 1] - (kf - 1.0) * out[k - 2]) / kf;
    }
}

/// Multi-indices of total degree ≤ p in d variables, in a fixed order.
fn multi_indices(d: usize, p: usize) -> Vec<Vec<u8>> {
    let mut out = vec![];
    let mut cur = vec![0u8; d];
    fn rec(i: usize, left: usize, cur: &mut Vec<u8>, out: &mut Vec<Vec<u8>>) {
        if i == cur.len() {
            out.push(cur.clone());
            return;
        }
        for k in 0..=left {
            cur[i] = k as u8;
            rec(i + 1, left - k, cur, out);
        }
        cur[i] = 0;
    }
    rec(0, p, &mut cur, &mut out);
    out
}

/// One unit's surrogate over the ROM parameters `inputs`, in whitened coordinates
/// u = L⁻¹ (w − centre) / half_width with the box |u_k| ≤ 1, where w_k = ln v_k for an
/// input that is positive at every sample (`log_input`) and v_k otherwise.
#[derive(Clone, Debug, serde::Serialize)]
pub struct UnitSurrogate {
    pub inputs: Vec<usize>,
    /// Per input: the box is in ln v (a stiffness the sampler moves on a log axis over
    /// orders of magnitude: a box in v would reach zero or below, where no model exists).
    pub log_input: Vec<bool>,
    pub centre: Vec<f64>,
    chol: Vec<f64>,
    pub half_width: f64,
    /// The ROM parameter vector the inputs are set in (the other parameters keep its values).
    #[serde(skip)]
    base: Vec<f64>,
    pub degree: usize,
    #[serde(skip)]
    exps: Vec<Vec<u8>>,
    /// n_terms × n_out, row-major.
    #[serde(skip)]
    coef: Vec<f64>,
    n_modes: usize,
    n_shapes: usize,
    /// Largest |log L_surrogate − log L_ROM| on the verification points.
    pub max_abs_dll: f64,
    /// ROM evaluations spent fitting and verifying.
    pub rom_evals: u64,
}

impl UnitSurrogate {
    fn n_out(&self) -> usize {
        self.n_modes + self.n_shapes + 1
    }
    /// Whitened box coordinates u of the ROM parameter vector (|u_k| ≤ 1 inside the box).
    fn whiten(&self, v: &[f64]) -> Vec<f64> {
        // In place, one allocation: the tempering's every proposal whitens once or twice.
        let d = self.inputs.len();
        let mut w: Vec<f64> = self
            .inputs
            .iter()
            .zip(&self.log_input)
            .zip(&self.centre)
            .map(|((&i, &lg), c)| to_box_axis(v[i], lg) - c)
            .collect();
        crate::bayes::stats::lower_solve_in_place(&self.chol, d, &mut w);
        w.iter_mut().for_each(|x| *x /= self.half_width);
        w
    }
    /// Whitened box coordinates of the ROM parameter vector, None outside the box.
    fn coords(&self, v: &[f64]) -> Option<Vec<f64>> {
        let u = self.whiten(v);
        u.iter().all(|x| x.abs() <= 1.0).then_some(u)
    }
    fn basis(&self, u: &[f64]) -> Vec<f64> {
        basis(&self.exps, self.degree, u)
    }
    /// The ROM parameter vector at whitened box coordinates u.
    pub fn point(&self, u: &[f64]) -> Vec<f64> {
        let x = lower_mul(&self.chol, self.inputs.len(), u);
        let mut v = self.base.clone();
        for (k, &i) in self.inputs.iter().enumerate() {
            let a = self.centre[k] + self.half_width * x[k];
            v[i] = if self.log_input[k] { a.exp() } else { a };
        }
        v
    }
    /// The largest |u_k| of v in box units (1 = the box's edge).
    pub fn box_position(&self, v: &[f64]) -> f64 {
        self.whiten(v).iter().map(|x| x.abs()).fold(0.0, f64::max)
    }
    /// The terms at v, None outside the box.
    pub fn terms(&self, v: &[f64]) -> Option<Terms> {
        let u = self.coords(v)?;
        Some(self.terms_at(&u))
    }
    /// The polynomial at v wherever v is: inside the box the verified surrogate, beyond it an
    /// extrapolation with no error bound. Only a stand-in for a delayed-acceptance screen
    /// ([`Target::screen`]), never a model value.
    pub fn extrapolate(&self, v: &[f64]) -> Terms {
        self.terms_at(&self.whiten(v))
    }
    fn terms_at(&self, u: &[f64]) -> Terms {
        self.terms_of(&self.basis(u), &self.coef)
    }
    /// The terms of the polynomial with coefficients `coef` (n_terms × n_out) at its basis
    /// values `phi`.
    fn terms_of(&self, phi: &[f64], coef: &[f64]) -> Terms {
        let n_out = self.n_out();
        let mut out = vec![0.0; n_out];
        for (t, ph) in phi.iter().enumerate() {
            let row = &coef[t * n_out..(t + 1) * n_out];
            out.iter_mut().zip(row).for_each(|(o, c)| *o += ph * c);
        }
        let mass_g = out[n_out - 1];
        let one_minus_mac = out[self.n_modes..self.n_modes + self.n_shapes]
            .iter()
            .map(|v| v.max(0.0))
            .collect();
        // The output vector becomes λ (one allocation fewer).
        out.truncate(self.n_modes);
        out.iter_mut().for_each(|v| *v = v.exp());
        Terms {
            lambda: out,
            one_minus_mac,
            mass_g,
            suff: vec![],
        }
    }
    /// The surrogate with its first `n_fixed` inputs set as they are in `v` (a ROM parameter
    /// vector): the same polynomial, its terms summed over the fixed inputs' Legendre values
    /// once, a polynomial in the other inputs alone. None where the fixed inputs lie outside
    /// the box (every point with them is outside, the ROM's).
    ///
    /// Why: in a modular step the first inputs are a group's step-1 draw (the board's moduli),
    /// the same for every evaluation of that group, while the total-degree basis spends most
    /// of its terms on them (degree 5 in 8 inputs: 1287 terms; in the last 3 alone, 56).
    /// Valid because whitening is lower-triangular: u_k depends on the inputs up to k, so the
    /// leading u are the fixed inputs' alone.
    pub fn fix_leading(&self, n_fixed: usize, v: &[f64]) -> Option<FixedLeading> {
        let d = self.inputs.len();
        if n_fixed == 0 || n_fixed >= d {
            return None;
        }
        let u = self.whiten(v);
        if u[..n_fixed].iter().any(|x| x.is_nan() || x.abs() > 1.0) {
            return None;
        }
        let p = self.degree;
        let leg = legendre_table(&u[..n_fixed], p);
        let exps = multi_indices(d - n_fixed, p);
        let index: std::collections::BTreeMap<&[u8], usize> = exps
            .iter()
            .enumerate()
            .map(|(j, e)| (e.as_slice(), j))
            .collect();
        let n_out = self.n_out();
        let mut coef = vec![0.0; exps.len() * n_out];
        for (t, e) in self.exps.iter().enumerate() {
            let w = monomial(&leg, p, &e[..n_fixed]);
            let j = index[&e[n_fixed..]];
            let (src, dst) = (
                &self.coef[t * n_out..(t + 1) * n_out],
                &mut coef[j * n_out..(j + 1) * n_out],
            );
            dst.iter_mut().zip(src).for_each(|(o, c)| *o += w * c);
        }
        Some(FixedLeading {
            n_fixed,
            exps,
            coef,
        })
    }
    /// The terms at v by `f` ([`Self::fix_leading`] at v's fixed inputs), None outside the
    /// box.
    pub fn terms_fixed(&self, f: &FixedLeading, v: &[f64]) -> Option<Terms> {
        let u = self.coords(v)?;
        let phi = basis(&f.exps, self.degree, &u[f.n_fixed..]);
        Some(self.terms_of(&phi, &f.coef))
    }
}

/// A [`UnitSurrogate`] with its leading inputs fixed ([`UnitSurrogate::fix_leading`]).
#[derive(Clone, Debug)]
pub struct FixedLeading {
    n_fixed: usize,
    exps: Vec<Vec<u8>>,
    /// n_terms × n_out, row-major.
    coef: Vec<f64>,
}

/// P_0..P_p of every coordinate of u, coordinate after coordinate.
fn legendre_table(u: &[f64], p: usize) -> Vec<f64> {
    let mut leg = vec![0.0; u.len() * (p + 1)];
    for (k, &x) in u.iter().enumerate() {
        legendre(x, p, &mut leg[k * (p + 1)..(k + 1) * (p + 1)]);
    }
    leg
}

/// The product of Legendre polynomials of multi-index `e` from a [`legendre_table`].
fn monomial(leg: &[f64], p: usize, e: &[u8]) -> f64 {
    e.iter()
        .enumerate()
        .map(|(k, &q)| leg[k * (p + 1) + q as usize])
        .product()
}

/// The total-degree Legendre basis of `exps` (degree ≤ p) at u.
fn basis(exps: &[Vec<u8>], p: usize, u: &[f64]) -> Vec<f64> {
    let leg = legendre_table(u, p);
    exps.iter().map(|e| monomial(&leg, p, e)).collect()
}

/// An input's coordinate on the box's axis: ln v (NaN where v ≤ 0: outside every box) or v.
fn to_box_axis(v: f64, log: bool) -> f64 {
    if !log {
        v
    } else if v > 0.0 {
        v.ln()
    } else {
        f64::NAN
    }
}

/// Aᵀ A (nt × nt) and Aᵀ Y (nt × n_out), row-major, for the design rows A and outputs Y:
/// sequential faer products (the caller runs units in parallel; a fixed order keeps the
/// sums, and so the surrogate, the same whatever the thread count).
fn normal_equations(
    rows: &[Vec<f64>],
    ys: &[Vec<f64>],
    nt: usize,
    n_out: usize,
) -> (Vec<f64>, Vec<f64>) {
    let a = faer::Mat::<f64>::from_fn(rows.len(), nt, |i, j| rows[i][j]);
    let y = faer::Mat::<f64>::from_fn(ys.len(), n_out, |i, j| ys[i][j]);
    let mut ata = faer::Mat::<f64>::zeros(nt, nt);
    let mut aty = faer::Mat::<f64>::zeros(nt, n_out);
    for (out, rhs) in [(&mut ata, a.as_ref()), (&mut aty, y.as_ref())] {
        faer::linalg::matmul::matmul(
            out.as_mut(),
            faer::Accum::Replace,
            a.transpose(),
            rhs,
            1.0,
            faer::Par::Seq,
        );
    }
    crate::simd::clear_upper_vector_state();
    let flat = |m: &faer::Mat<f64>| -> Vec<f64> {
        (0..m.nrows())
            .flat_map(|i| (0..m.ncols()).map(move |j| m[(i, j)]))
            .collect()
    };
    (flat(&ata), flat(&aty))
}

fn outputs(t: &Terms) -> Vec<f64> {
    let mut o: Vec<f64> = t.lambda.iter().map(|v| v.ln()).collect();
    o.extend(&t.one_minus_mac);
    o.push(t.mass_g);
    o
}

/// Tuning of the surrogates.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct SurrogateOptions {
    /// Box half-width in standard deviations of the samples it is fitted around.
    pub half_width_sd: f64,
    /// Where the ROM cannot follow the updated modes everywhere in the box, or no degree
    /// passes the verification, the box is halved, down to this half-width (then the unit
    /// keeps the ROM).
    pub min_half_width_sd: f64,
    /// Degrees tried in order until the verification passes.
    pub degrees: Vec<usize>,
    /// Fitting points per polynomial term.
    pub oversampling: f64,
    /// Verification points.
    pub n_verify: usize,
    /// Largest accepted |Δ log L| on the verification points (the worst over the whole box,
    /// edges included; default 0.5). It only sets cost: the final correction to the ROM makes
    /// the posterior exact, and the error where the posterior lies is far smaller (on the
    /// paper demo's joint_rotation refit, max |Δ log L| over the final particles 4.5e-5
    /// with 0.5 here; 0.05 shrank 24 of 30 boxes to 2.5 sd and tripled the refit's time).
    pub tolerance_dll: f64,
    /// Largest number of polynomial terms tried (a degree with more is skipped and the box
    /// halved): fitting costs 2 × n_terms ROM evaluations and ~2 n_terms³ flops per unit
    /// and box. 2000 admits degree 6 in up to 7 inputs and degree 4 in up to 12.
    pub max_terms: usize,
}

impl Default for SurrogateOptions {
    fn default() -> Self {
        SurrogateOptions {
            half_width_sd: 10.0,
            min_half_width_sd: 2.5,
            degrees: vec![2, 3, 4, 5, 6],
            oversampling: 2.0,
            n_verify: 60,
            tolerance_dll: 0.5,
            max_terms: 2000,
        }
    }
}

/// Why a unit keeps the ROM.
#[derive(Clone, Debug, serde::Serialize)]
pub struct SurrogateRefusal {
    pub unit: usize,
    pub reason: String,
}

/// Fit unit b's surrogate around `samples` (ROM parameter vectors the sampler is expected
/// to visit: e.g. draws from the reference); `eps`, `delta` = error scales at which the
/// log-likelihood error is verified.
pub fn fit_unit(
    target: &ModalTarget,
    b: usize,
    samples: &[Vec<f64>],
    eps: &[f64],
    delta: &[f64],
    opts: &SurrogateOptions,
    seed: u64,
) -> Result<UnitSurrogate, String> {
    let data: &UnitData = &target.units[b];
    let nv = samples[0].len();
    let n = samples.len() as f64;
    let raw_mean: Vec<f64> = (0..nv)
        .map(|k| samples.iter().map(|s| s[k]).sum::<f64>() / n)
        .collect();
    let inputs: Vec<usize> = (0..nv)
        .filter(|&k| {
            let var = samples
                .iter()
                .map(|s| (s[k] - raw_mean[k]).powi(2))
                .sum::<f64>()
                / n;
            var > 1e-24 * (1.0 + raw_mean[k] * raw_mean[k])
        })
        .collect();
    let d = inputs.len();
    if d == 0 {
        return Err("no parameter varies".into());
    }
    let log_input: Vec<bool> = inputs
        .iter()
        .map(|&k| samples.iter().all(|s| s[k] > 0.0))
        .collect();
    // The samples on the box's axes.
    let w: Vec<Vec<f64>> = samples
        .iter()
        .map(|s| {
            inputs
                .iter()
                .zip(&log_input)
                .map(|(&k, &lg)| to_box_axis(s[k], lg))
                .collect()
        })
        .collect();
    let (centre, cov) = super::stats::mean_and_covariance(w.iter().map(Vec::as_slice));
    let chol = cholesky_jittered(&cov, d).0;
    let rom_terms = |w: &[f64]| target.rom_terms_at(b, w);
    let mut rng = ChaCha8Rng::seed_from_u64(stream_key(&[seed, 0x5u64, b as u64]));
    let mut evals = 0u64;
    let mut errors = vec![];
    let mut half_width = opts.half_width_sd;
    while half_width >= opts.min_half_width_sd {
        let mut last_err = String::new();
        // The previous degree's worst error: a polynomial of a smooth map converges with its
        // degree, so a degree that does not lower it means something in the box is not
        // smooth (two modes crossing, a mode the ROM hands over to another), and higher
        // degrees only cost (each one more ROM evaluations and ~2 n_terms³ flops): the box
        // is halved instead.
        let mut prev_worst = f64::INFINITY;
        // The box's evaluated points (u, outputs), shared by its degrees: a degree fits on
        // every point evaluated so far (the lower degrees' fitting and verification points,
        // fresh to it) and only evaluates the ones it lacks; its own verification points are
        // drawn fresh and join the pool. The last degree's fit then costs its own points
        // alone, not the sum over every degree tried (on the realistic fixture's refit, 8
        // inputs up to degree 5: 2339 ROM evaluations a unit on average where it was 3873).
        // The pool's whitened points and their outputs.
        let (mut pool_u, mut ys): (Vec<Vec<f64>>, Vec<Vec<f64>>) = (vec![], vec![]);
        'degrees: for &p in &opts.degrees {
            let exps = multi_indices(d, p);
            let nt = exps.len();
            if nt > opts.max_terms {
                last_err = format!(
                    "degree {p}: {nt} terms in {d} inputs, over the limit of {}",
                    opts.max_terms
                );
                break 'degrees;
            }
            let n_fit = ((nt as f64) * opts.oversampling).ceil() as usize + 4;
            let mut s = UnitSurrogate {
                inputs: inputs.clone(),
                log_input: log_input.clone(),
                centre: centre.clone(),
                chol: chol.clone(),
                half_width,
                base: raw_mean.clone(),
                degree: p,
                exps,
                coef: vec![],
                n_modes: target.n_lambda(b),
                n_shapes: data.shapes.len(),
                max_abs_dll: f64::NAN,
                rom_evals: 0,
            };
            let n_out = s.n_out();
            let untracked = "the ROM cannot track the updated modes everywhere in the box";
            // Fitting design: uniform in the whitened box, plus the centre.
            while pool_u.len() < n_fit {
                let u: Vec<f64> = if pool_u.is_empty() {
                    vec![0.0; d]
                } else {
                    (0..d).map(|_| 2.0 * rng.random::<f64>() - 1.0).collect()
                };
                let v = s.point(&u);
                evals += 1;
                let Some(t) = rom_terms(&v) else {
                    last_err = untracked.into();
                    break 'degrees;
                };
                pool_u.push(u);
                ys.push(outputs(&t));
            }
            let rows: Vec<Vec<f64>> = pool_u.iter().map(|u| s.basis(u)).collect();
            // Least squares by the normal equations (Legendre basis on uniform points: well
            // conditioned at these degrees), the products Aᵀ A and Aᵀ Y by faer: with the
            // hand-written triple loop the blind underfill campaign's fixture refit (30 units,
            // 7 inputs, up to degree 6 = 1716 terms) spent over 12 min fitting surrogates; with
            // faer and the degree rule below, 46 s.
            let (ata, aty) = normal_equations(&rows, &ys, nt, n_out);
            let (l, _) = cholesky_jittered(&ata, nt);
            let mut coef = vec![0.0; nt * n_out];
            for o in 0..n_out {
                let rhs: Vec<f64> = (0..nt).map(|i| aty[i * n_out + o]).collect();
                let y = lower_solve(&l, nt, &rhs);
                let mut x = vec![0.0; nt];
                for i in (0..nt).rev() {
                    let sum: f64 = (i + 1..nt).map(|k| l[k * nt + i] * x[k]).sum();
                    x[i] = (y[i] - sum) / l[i * nt + i];
                }
                for i in 0..nt {
                    coef[i * n_out + o] = x[i];
                }
            }
            s.coef = coef;
            // Verification on fresh points.
            let mut worst = 0.0f64;
            for _ in 0..opts.n_verify {
                let u: Vec<f64> = (0..d).map(|_| 2.0 * rng.random::<f64>() - 1.0).collect();
                let v = s.point(&u);
                evals += 1;
                let Some(tr) = rom_terms(&v) else {
                    last_err = untracked.into();
                    break 'degrees;
                };
                // At the drawn u itself: v's round trip through exp and ln could put a point
                // drawn at the box's edge a rounding error outside it.
                let ts = s.terms_at(&u);
                let dll = (modal::log_lik(data, &ts, eps, delta)
                    - modal::log_lik(data, &tr, eps, delta))
                .abs();
                worst = worst.max(if dll.is_nan() { f64::INFINITY } else { dll });
                pool_u.push(u);
                ys.push(outputs(&tr));
            }
            s.max_abs_dll = worst;
            s.rom_evals = evals;
            if worst <= opts.tolerance_dll {
                return Ok(s);
            }
            last_err = format!("degree {p}: max |Δ log L| {worst:.3e} on the verification points");
            if worst >= prev_worst {
                last_err.push_str(", no better than one degree lower");
                break 'degrees;
            }
            prev_worst = worst;
        }
        errors.push(format!("{half_width} sd: {last_err}"));
        half_width *= 0.5;
    }
    Err(errors.join("; "))
}

/// The modal target with per-unit surrogates: a unit's model is its surrogate inside the
/// surrogate's box and the ROM outside it (and for units without a surrogate).
///
/// The boxes are `half_width_sd` = 10 standard deviations of the (already inflated)
/// reference wide, where a Gaussian-like posterior has no appreciable mass (< 1e-20), or
/// narrower where the ROM or the polynomial does not hold that far (`min_half_width_sd`). A
/// posterior that is not Gaussian-like (a parameter the data bound only on one side, a
/// population scale the reference underestimates) reaches beyond them; there the ROM answers,
/// so the boxes never restrict the posterior: they only decide where evaluations are cheap.
/// `outside_box` counts the ROM evaluations that cost, and the stage reports the fraction of
/// final particles beyond the boxes.
pub struct SurrogateTarget<'a> {
    pub inner: &'a ModalTarget,
    pub surrogates: Vec<Option<Arc<UnitSurrogate>>>,
    /// Proposals that fell outside a unit's box and went to the ROM (a count for the report;
    /// it does not influence any result).
    pub outside_box: std::sync::atomic::AtomicU64,
    /// Every ROM evaluation `model` made (units without a surrogate, proposals beyond a box):
    /// [`Target::expensive_evals`].
    pub rom_evals: std::sync::atomic::AtomicU64,
    /// A modular step's groups, by the address of their auxiliary values (the `Arc`s the
    /// sampler hands every evaluation of the group), and per unit and group its surrogate
    /// with the group's inputs fixed ([`UnitSurrogate::fix_leading`]). Auxiliary values
    /// from anywhere else take the whole polynomial.
    group_of: std::collections::HashMap<usize, usize>,
    fixed: Vec<Vec<Option<FixedLeading>>>,
}

impl<'a> SurrogateTarget<'a> {
    /// The target over `surrogates`; `all_aux`: the groups' auxiliary values (empty for a
    /// step without groups).
    pub fn new(
        inner: &'a ModalTarget,
        surrogates: Vec<Option<Arc<UnitSurrogate>>>,
        all_aux: &[&Arc<Vec<f64>>],
    ) -> Self {
        use rayon::prelude::*;
        let group_of = all_aux
            .iter()
            .enumerate()
            .map(|(g, a)| (a.as_ptr() as usize, g))
            .collect();
        let x0 = vec![0.0; inner.unit_dim()];
        let fixed = surrogates
            .par_iter()
            .enumerate()
            .map(|(b, s)| {
                let (Some(s), Some(a0)) = (s, all_aux.first()) else {
                    return vec![];
                };
                // The leading inputs no unit coordinate moves: the group's alone.
                let v0 = inner.surrogate_inputs(a0, b, &x0);
                let moved: Vec<Vec<f64>> = (0..x0.len())
                    .map(|k| {
                        let mut x = x0.clone();
                        x[k] = 0.5;
                        inner.surrogate_inputs(a0, b, &x)
                    })
                    .collect();
                let n_fixed = s
                    .inputs
                    .iter()
                    .take_while(|&&i| moved.iter().all(|v| v[i] == v0[i]))
                    .count();
                all_aux
                    .iter()
                    .map(|a| s.fix_leading(n_fixed, &inner.surrogate_inputs(a, b, &x0)))
                    .collect()
            })
            .collect();
        SurrogateTarget {
            inner,
            surrogates,
            outside_box: Default::default(),
            rom_evals: Default::default(),
            group_of,
            fixed,
        }
    }
}

impl Target for SurrogateTarget<'_> {
    fn expensive_evals(&self) -> u64 {
        self.rom_evals.load(std::sync::atomic::Ordering::Relaxed)
    }
    type Cache = Terms;
    type Ctx = <ModalTarget as Target>::Ctx;
    fn n_global(&self) -> usize {
        self.inner.n_global()
    }
    fn n_units(&self) -> usize {
        self.inner.n_units()
    }
    fn unit_dim(&self) -> usize {
        self.inner.unit_dim()
    }
    fn sample_prior(&self, rng: &mut ChaCha8Rng) -> (Vec<f64>, Vec<Vec<f64>>) {
        self.inner.sample_prior(rng)
    }
    fn log_prior_global(&self, g: &[f64]) -> f64 {
        self.inner.log_prior_global(g)
    }
    fn ctx(&self, g: &[f64]) -> Self::Ctx {
        self.inner.ctx(g)
    }
    fn ctx_with_prior(&self, g: &[f64]) -> (Self::Ctx, f64) {
        self.inner.ctx_with_prior(g)
    }
    fn ctx_after(&self, ctx: &Self::Ctx, gn: &[f64], k: usize) -> (Self::Ctx, f64) {
        self.inner.ctx_after(ctx, gn, k)
    }
    fn log_prior_unit(&self, ctx: &Self::Ctx, b: usize, x: &[f64]) -> f64 {
        self.inner.log_prior_unit(ctx, b, x)
    }
    fn model(&self, aux: &[f64], b: usize, x: &[f64]) -> Option<Terms> {
        if let Some(Some(s)) = self.surrogates.get(b) {
            let v = self.inner.surrogate_inputs(aux, b, x);
            let fixed = self
                .group_of
                .get(&(aux.as_ptr() as usize))
                .and_then(|&g| self.fixed.get(b)?.get(g)?.as_ref());
            let terms = match fixed {
                Some(f) => s.terms_fixed(f, &v),
                None => s.terms(&v),
            };
            if let Some(t) = terms {
                return Some(t.with_sufficient(&self.inner.units[b], self.inner.errors.n_modes));
            }
            self.outside_box
                .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        }
        self.rom_evals
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        self.inner.model(aux, b, x)
    }
    fn log_lik(&self, ctx: &Self::Ctx, b: usize, x: &[f64], c: &Terms) -> f64 {
        self.inner.log_lik(ctx, b, x, c)
    }
    /// Beyond a unit's box, where `model` is the ROM: the surrogate's polynomial extrapolated
    /// (inside the box it is the model itself, so π̃ is that polynomial everywhere). Proposals
    /// it rejects cost no ROM evaluation; the ROM still decides the rest.
    fn screen(&self, aux: &[f64], b: usize, x: &[f64]) -> Option<Terms> {
        let s = self.surrogates.get(b)?.as_ref()?;
        let v = self.inner.surrogate_inputs(aux, b, x);
        if s.box_position(&v) <= 1.0 {
            return None;
        }
        Some(
            s.extrapolate(&v)
                .with_sufficient(&self.inner.units[b], self.inner.errors.n_modes),
        )
    }
    fn to_standard(&self, ctx: &Self::Ctx, b: usize, x: &[f64]) -> Vec<f64> {
        self.inner.to_standard(ctx, b, x)
    }
    fn from_standard(&self, ctx: &Self::Ctx, b: usize, z: &[f64]) -> Vec<f64> {
        self.inner.from_standard(ctx, b, z)
    }
    fn global_role(&self, k: usize) -> GlobalRole {
        self.inner.global_role(k)
    }
    fn log_error_scales(&self) -> Vec<usize> {
        self.inner.log_error_scales()
    }
    fn residual(&self, b: usize, m: usize, c: &Terms) -> Option<f64> {
        self.inner.residual(b, m, c)
    }
}

/// A unit's subspaces of the ROM, one per updated mode ([`modal::ModeSubspace`]), over its
/// surrogate's box:
/// the exact model of the correction stage, where every final particle's units are priced
/// (N × units evaluations a run, the sampler's largest fixed cost). Its error is measured the
/// way the surrogate's is: |log L_subspace − log L_ROM| at fresh points all over the box, at
/// the reference's error scales, held to [`SubspaceOptions::tolerance_dll`].
#[derive(Clone, Debug)]
pub struct UnitSubspace {
    /// One subspace per updated mode.
    pub subs: Vec<modal::ModeSubspace>,
    /// The box it was built and verified in.
    pub region: Arc<UnitSurrogate>,
    /// Largest |log L_subspace − log L_ROM| on the verification points.
    pub max_abs_dll: f64,
    /// ROM evaluations spent building and verifying it.
    pub rom_evals: u64,
}

impl UnitSubspace {
    /// The dimensions of its modes' subspaces, summed.
    pub fn dim(&self) -> usize {
        self.subs.iter().map(|s| s.sub.dim()).sum()
    }
}

/// Tuning of the unit subspaces.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct SubspaceOptions {
    /// Largest accepted |Δ log L| on the verification points. It bounds how far the
    /// posterior can sit from the ROM's: a particle's log weight moves by at most this much
    /// per unit in the box (default 1e-3; the reference's own Monte Carlo error of log Z is
    /// ~1e-2).
    pub tolerance_dll: f64,
    /// Verification points per round.
    pub n_verify: usize,
    /// Rounds that add the eigenvectors of the points that failed and verify again.
    pub max_rounds: usize,
    /// A subspace wider than this fraction of the ROM is not worth it: the unit keeps the ROM.
    pub max_dim_fraction: f64,
    /// Eigenvectors within this distance (relative) of the span add no direction.
    pub rel_tol: f64,
}

impl Default for SubspaceOptions {
    fn default() -> Self {
        SubspaceOptions {
            tolerance_dll: 1e-3,
            n_verify: 40,
            max_rounds: 6,
            max_dim_fraction: 0.7,
            rel_tol: 1e-7,
        }
    }
}

/// Build and verify unit b's subspaces over `region` (the unit's surrogate), one per
/// updated mode ([`modal::ModalPredictor::mode_subspaces`]): the mode's eigenvectors at the box's
/// centre, at ±½ and ±1 along each of its axes and at (±½, ±½) in each pair of axes, then rounds of verification on fresh
/// points, each adding the vectors of the points that failed. `eps`, `delta` = error scales
/// at which the log-likelihood error is verified.
pub fn fit_subspace(
    target: &ModalTarget,
    b: usize,
    region: &Arc<UnitSurrogate>,
    eps: &[f64],
    delta: &[f64],
    opts: &SubspaceOptions,
    seed: u64,
) -> Result<UnitSubspace, String> {
    let data: &UnitData = &target.units[b];
    let pred = &target.predictor;
    let r = pred.rom.dim();
    let d = region.inputs.len();
    let nm = pred.refs.len();
    let mut rng = ChaCha8Rng::seed_from_u64(stream_key(&[seed, 0x5B5u64, b as u64]));
    let mut evals = 0u64;
    let mut snaps: Vec<Vec<Vec<f64>>> = vec![vec![]; nm];
    let add = |snaps: &mut Vec<Vec<Vec<f64>>>, v: &[f64]| -> Result<(), String> {
        let p = pred
            .predict(v)
            .ok_or("the ROM cannot track the updated modes at a point of the box")?;
        for (s, y) in snaps.iter_mut().zip(p.vectors) {
            s.push(y);
        }
        Ok(())
    };
    // Along each axis (a mode's vector sweeps its pure derivatives there) and at the corners
    // of every axis pair's inner square (the mixed second derivatives, which a mode's own
    // vectors along the axes do not span).
    let mut design = vec![vec![0.0; d]];
    for k in 0..d {
        for a in [-1.0, -0.5, 0.5, 1.0] {
            let mut u = vec![0.0; d];
            u[k] = a;
            design.push(u);
        }
        for l in 0..k {
            for (a, c) in [(-0.5, -0.5), (-0.5, 0.5), (0.5, -0.5), (0.5, 0.5)] {
                let mut u = vec![0.0; d];
                u[k] = a;
                u[l] = c;
                design.push(u);
            }
        }
    }
    // Every tracked mode's vector at the centre: a mode's first-order change is a
    // combination of the others (modal expansion of its derivative), so its own vectors
    // alone leave it short of the ROM's accuracy between the design points.
    let centre = pred
        .tracked_modes(&region.point(&vec![0.0; d]))
        .ok_or("the ROM has no modes at the box's centre")?;
    evals += 1;
    for s in snaps.iter_mut() {
        s.extend(centre.vectors.iter().cloned());
    }
    for u in &design {
        add(&mut snaps, &region.point(u))?;
        evals += 1;
    }
    let mut worst = f64::INFINITY;
    for _ in 0..=opts.max_rounds {
        let subs = pred
            .mode_subspaces(&snaps, opts.rel_tol)
            .ok_or("a mode has no vector to span its subspace")?;
        if let Some(q) = subs
            .iter()
            .map(|s| s.sub.dim())
            .find(|&q| q as f64 > opts.max_dim_fraction * r as f64)
        {
            return Err(format!(
                "a mode's subspace needs {q} of the ROM's {r} dimensions"
            ));
        }
        worst = 0.0f64;
        let mut failed = vec![];
        for _ in 0..opts.n_verify {
            let u: Vec<f64> = (0..d).map(|_| 2.0 * rng.random::<f64>() - 1.0).collect();
            let v = region.point(&u);
            evals += 1;
            let p_rom = pred
                .predict(&v)
                .ok_or("the ROM cannot track the updated modes")?;
            let t_rom = pred.terms(&p_rom, data, &v);
            let dll = match pred.predict_in_modes(&subs, &v) {
                Some(p) => (modal::log_lik(data, &pred.terms(&p, data, &v), eps, delta)
                    - modal::log_lik(data, &t_rom, eps, delta))
                .abs(),
                None => f64::INFINITY,
            };
            let dll = if dll.is_nan() { f64::INFINITY } else { dll };
            if dll > opts.tolerance_dll {
                failed.push(v);
            }
            worst = worst.max(dll);
        }
        if failed.is_empty() {
            return Ok(UnitSubspace {
                subs,
                region: Arc::clone(region),
                max_abs_dll: worst,
                rom_evals: evals,
            });
        }
        for v in failed.iter().take(4 * d.max(1)) {
            add(&mut snaps, v)?;
            evals += 1;
        }
    }
    Err(format!(
        "max |Δ log L| {worst:.3e} on the verification points after {} rounds",
        opts.max_rounds + 1
    ))
}

//! Where on the board: sensitivity-based localisation of a missing point mass, or of a
//! local stiffness change, from the free-free frequency residuals (pure). The kernel fits
//! one amplitude at every point of a grid, given each point's signature; the point mass's
//! signature is derived below, a stiffness change's (either sign, `positive_only = false`)
//! is ½ (f − 1) E_jj / λ_j with E the changed stiffness as a form on the modes.
//!
//! A point mass δm at (x, y) on a board whose weighed mass the model spreads over its area
//! changes each mode's frequency, to first order, by
//!
//! ```text
//! δ ln f_j = −½ δm φ_j(x, y)²  +  (a uniform mass change, absorbed by mass_scale)
//! ```
//!
//! with φ_j the mass-normalised shape (1/√kg). The updating has already fitted each board's
//! parameters θ (moduli, mass scale), so what the residuals can still hold is the part of the
//! signature that no change of θ reproduces. For every candidate point on a grid, the
//! signature s_j(x, y) = −½ φ_j(x, y)² and the residuals r_j (mean over boards of the board
//! means of (f_measured − f_model)/f_model) are both projected off the span of the parameter
//! sensitivities A_jk = ∂ ln f_j/∂ ln θ_k, in the metric of the residuals' standard errors;
//! the weighted least-squares amplitude δm̂ and its χ² reduction
//!
//! ```text
//! Δχ²(x, y) = (s̃ᵀ W r̃)² / (s̃ᵀ W s̃),   δm̂ = s̃ᵀ W r̃ / s̃ᵀ W s̃ (> 0 for a mass)
//! ```
//!
//! map how well a point mass there explains the misfit (the classic sensitivity-based error
//! localisation of model updating, e.g. Friswell & Mottershead 1995, ch. 8, restricted to a
//! one-point, one-parameter error). The best point is the located region; its uncertainty is
//! the set of points whose Δχ² lies within the 90 % quantile of χ²₂ of the best (a profile
//! likelihood region for two location coordinates), the threshold scaled by the reduced χ²
//! left after the fit when that exceeds one (the residual model error, not only the
//! measurement scatter, sets the resolution). Frequencies are invariant under the symmetries
//! of a symmetric plate, so separate maxima inside that threshold are reported as
//! alternatives rather than silently dropped.

use serde::Serialize;

use super::locate::chi2_sf;

/// One mode's residual: the mean relative frequency residual over boards and its standard
/// error.
#[derive(Clone, Debug, PartialEq)]
pub struct ModeResidual {
    pub label: String,
    pub mean_rel: f64,
    pub se_rel: f64,
}

/// The inputs of [`localize_point_mass`]; all per-mode vectors in the order of `modes`.
#[derive(Clone, Debug)]
pub struct LocalizeInput<'a> {
    pub modes: &'a [ModeResidual],
    /// Nuisance sensitivities, one column per updated parameter: ∂ ln f_j/∂ ln θ_k.
    pub nuisance: &'a [Vec<f64>],
    /// Candidate points (m, board frame).
    pub points_m: &'a [[f64; 2]],
    /// Per point, the signature ∂ ln f_j/∂m (1/kg) of a point mass there.
    pub signature: &'a [Vec<f64>],
    /// The exact frequency change of a point mass in a modal basis (`None`: first order).
    pub exact: Option<ModalBasis<'a>>,
    /// Only a positive amplitude is physical (a mass); `false`: either sign (a stiffness
    /// change, stiffer or softer).
    pub positive_only: bool,
}

/// A truncated modal basis of the board: the exact eigenvalues of the board with a point
/// mass m at p, within the span of these modes, are the roots of a secular equation
/// ([`point_mass_eigenvalues`]), so the mass's frequency change is computed to all orders in
/// m, not to first order. At the mass a localisation is after (1–2 % of the board) the first
/// order under-estimates it by a third (the lab's 0.25 g came out 0.177 g), and the
/// linearisation error inflates the χ² that sets the region.
#[derive(Clone, Copy, Debug)]
pub struct ModalBasis<'a> {
    /// Eigenvalues λ_k = ω_k² (rad²/s²), ascending; rigid-body modes 0.
    pub lambda: &'a [f64],
    /// Per candidate point (the order of `points_m`), the mass-normalised shapes φ_k(p).
    pub phi: &'a [Vec<f64>],
    /// Per residual mode (the order of `modes`), its index in `lambda`.
    pub observed: &'a [usize],
    /// The board's mass M (kg) when the balance fixed the total: the board's own mass then
    /// drops by the added mass m (the updating's mass scale followed the balance, which
    /// weighed the added mass with the board), scaling every eigenvalue by 1/(1 − m/M).
    /// `None`: the total is free (a mass scale among the nuisance parameters absorbs it).
    pub weighed_mass_kg: Option<f64>,
}

/// The eigenvalues `wanted` (indices into `lambda`, elastic modes) of (Λ, I + m a aᵀ): a
/// modal basis (Λ, mass-normalised) with a point mass m whose shape values are a = φ(p).
///
/// From Λx = μ(x + m a aᵀx), every eigenvalue not equal to a λ_k solves the secular equation
///
/// ```text
/// g(μ) = 1 + m A_r − m μ Σ_{λ_k > 0} a_k² / (λ_k − μ) = 0,   A_r = Σ_{λ_k = 0} a_k²
/// ```
///
/// (a rigid mode's term μ a_k²/(0 − μ) is the constant −a_k²). g falls from +∞ to −∞
/// between consecutive elastic poles (and from 1 + m A_r > 0 at 0 to −∞ below the first), so
/// the j-th elastic eigenvalue has exactly one root in (λ_{j−1}, λ_j] (mass only lowers
/// eigenvalues, interlacing), found by bisection to machine precision. A mode with a_j = 0
/// (a node at p) keeps λ_j. Written by hand: it is 30 lines, and no crate solves a rank-one
/// secular equation.
pub fn point_mass_eigenvalues(lambda: &[f64], a: &[f64], m: f64, wanted: &[usize]) -> Vec<f64> {
    let rigid = |l: f64| l <= 1e-9 * lambda.last().copied().unwrap_or(1.0).abs();
    let a_r: f64 = lambda
        .iter()
        .zip(a)
        .filter(|(l, _)| rigid(**l))
        .map(|(_, v)| v * v)
        .sum();
    let g = |mu: f64| {
        let h: f64 = lambda
            .iter()
            .zip(a)
            .filter(|(l, _)| !rigid(**l))
            .map(|(l, v)| v * v / (l - mu))
            .sum();
        1.0 + m * a_r - m * mu * h
    };
    wanted
        .iter()
        .map(|&j| {
            let hi0 = lambda[j];
            if m <= 0.0 || a[j] == 0.0 || rigid(hi0) {
                return hi0;
            }
            let lo0 = lambda[..j]
                .iter()
                .copied()
                .filter(|l| *l < hi0)
                .fold(0.0, f64::max);
            let (mut lo, mut hi) = (lo0, hi0);
            for _ in 0..200 {
                let mid = 0.5 * (lo + hi);
                if mid <= lo || mid >= hi {
                    break;
                }
                if g(mid) > 0.0 {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            0.5 * (lo + hi)
        })
        .collect()
}

/// The signature of a point mass m at candidate point `i` in the exact modal basis:
/// δ ln f_j = ½ ln(μ_j / λ_j) per residual mode.
fn exact_signature(b: &ModalBasis, i: usize, m: f64) -> Vec<f64> {
    // With the total weighed: (K, (1 − m/M) M₀ + m N Nᵀ) has the eigenvalues of
    // (K, M₀ + m′ N Nᵀ), m′ = m / (1 − m/M), divided by 1 − m/M.
    let (m_eff, shift) = match b.weighed_mass_kg {
        Some(big) if m < big => {
            let k = 1.0 - m / big;
            (m / k, -0.5 * k.ln())
        }
        Some(_) => return vec![f64::NAN; b.observed.len()],
        None => (m, 0.0),
    };
    let mu = point_mass_eigenvalues(b.lambda, &b.phi[i], m_eff, b.observed);
    mu.iter()
        .zip(b.observed)
        .map(|(u, &j)| 0.5 * (u / b.lambda[j]).ln() + shift)
        .collect()
}

/// The weighted least-squares mass at point `i` in the exact modal basis, from the first-order
/// amplitude `m0`, by Gauss–Newton on the projected, weighted residual: (Δχ², mass, se).
fn exact_fit(
    b: &ModalBasis,
    i: usize,
    m0: f64,
    r: &[f64],
    w_sqrt: &[f64],
    q: &[Vec<f64>],
) -> (f64, f64, f64) {
    let proj = |v: Vec<f64>| {
        let mut v: Vec<f64> = v.iter().zip(w_sqrt).map(|(a, w)| a * w).collect();
        project_off(&mut v, q);
        v
    };
    let chi2 = |s: &[f64]| r.iter().zip(s).map(|(a, b)| (a - b) * (a - b)).sum::<f64>();
    let chi2_0 = dot(r, r);
    let mut m = m0.max(0.0);
    let mut jj = 0.0;
    for _ in 0..8 {
        if m <= 0.0 {
            break;
        }
        let s = proj(exact_signature(b, i, m));
        let h = 1e-3 * m;
        let s2 = proj(exact_signature(b, i, m + h));
        let jac: Vec<f64> = s2.iter().zip(&s).map(|(a, c)| (a - c) / h).collect();
        jj = dot(&jac, &jac);
        if jj.is_nan() || jj <= 0.0 {
            break;
        }
        let step: f64 = jac
            .iter()
            .zip(r.iter().zip(&s))
            .map(|(j, (a, c))| j * (a - c))
            .sum::<f64>()
            / jj;
        let next = (m + step).max(0.0);
        let done = (next - m).abs() <= 1e-9 * m;
        m = next;
        if done {
            break;
        }
    }
    if !(m > 0.0 && jj > 0.0) {
        return (0.0, 0.0, f64::INFINITY);
    }
    let d = chi2_0 - chi2(&proj(exact_signature(b, i, m)));
    (d.max(0.0), m, 1.0 / jj.sqrt())
}

/// A located local change: a point mass, or a change of stiffness over a small disc.
#[derive(Clone, Debug, PartialEq, Serialize, schemars::JsonSchema)]
#[cfg_attr(test, derive(Default))]
pub struct LocalFit {
    /// Best point, m.
    pub x_m: f64,
    pub y_m: f64,
    /// Weighted least-squares amplitude at the best point and its standard error (scaled by
    /// the reduced χ² when above one): a point mass's mass in kg, or a stiffness change's
    /// factor − 1 (see the region's `amplitude_unit`).
    pub amplitude: f64,
    pub amplitude_se: f64,
    /// χ² of the residuals off the parameters' span, before and after the point mass.
    pub chi2_before: f64,
    pub chi2_after: f64,
    /// Degrees of freedom left after the fit (modes − independent parameters − 3).
    pub dof_after: usize,
    /// Share of χ²_before the point mass explains.
    pub explained_share: f64,
    /// Tail probability of Δχ² under no point mass (χ² with 3 degrees of freedom: mass and
    /// two coordinates).
    pub p_value: f64,
    /// Radius of the 90 % region around the best point, m: the largest distance from it of a
    /// region point that is not nearer to an alternative ([`local_radius`]).
    pub region_radius_m: f64,
    /// Grid points in the region.
    pub region_points: usize,
    /// Other local maxima inside the region's threshold, farther than `min_separation_m` from
    /// the best point and from each other (x_m, y_m, Δχ²): places the frequencies cannot tell
    /// apart from the best one.
    pub alternatives: Vec<[f64; 3]>,
    /// The location's Occam factor, ln of the mean over the grid of the likelihood ratio
    /// exp(−(Δχ²_best − Δχ²_i) / 2s) (s the χ² inflation of the region), summed over the
    /// points nearer the best point than any alternative: a refit with the mass fixed at the
    /// best point has an evidence too high by about −this much against one whose location is
    /// uniform over the board (Laplace's approximation over the location; the look-elsewhere
    /// penalty of having chosen the point from the data). ≤ 0.
    pub log_location_occam: f64,
    /// The sd of ln|amplitude| over the location's uncertainty: of the fitted amplitude at
    /// the points of the best point's part of the grid, weighted by the same likelihood
    /// ratios. A fit at a fixed point is conditional on it; this is what the point's
    /// uncertainty adds.
    pub location_ln_amplitude_sd: f64,
    /// What one grid step moves: the largest change, over the fitted modes and the best
    /// point's grid neighbours, of the relative frequency shift the fitted amplitude predicts
    /// (first order). The refit's point search refines the point only by steps that change a
    /// frequency by the practical threshold or more. 0 where not computed.
    pub step_shift_rel: f64,
    /// Δχ² of every candidate point (the order of `points_m`; 0 where no amplitude of the
    /// allowed sign fits) and the χ² inflation s of the region threshold; not written out.
    #[serde(skip)]
    #[schemars(skip)]
    pub delta_chi2: Vec<f64>,
    #[serde(skip)]
    #[schemars(skip)]
    pub inflation: f64,
    /// The fitted amplitude at every candidate point; not written out.
    #[serde(skip)]
    #[schemars(skip)]
    pub amplitude_at: Vec<f64>,
}

/// The weighted standard deviation of the values of (weight, value) pairs; 0 when empty.
pub fn weighted_sd(wv: &[(f64, f64)]) -> f64 {
    let sw: f64 = wv.iter().map(|(w, _)| w).sum();
    if sw.is_nan() || sw <= 0.0 {
        return 0.0;
    }
    let mean = wv.iter().map(|(w, v)| w * v).sum::<f64>() / sw;
    (wv.iter().map(|(w, v)| w * (v - mean).powi(2)).sum::<f64>() / sw).sqrt()
}

/// The sd of ln|amplitude| that the grid's resolution leaves: the grid places the best point
/// only to within a step (the top lies within a step of the best point: uniform over ±h,
/// sd h/√3 each way, as for the refit's point search, `point_search::Stencil::laplace`),
/// times the gradient of ln|amplitude| there by differences over the best point's grid
/// neighbours along x and along y (central where both have an amplitude of its sign). The
/// likelihood-weighted spread over the grid misses this when the frequencies single out one
/// grid point: on the realistic lumped-mass campaign it was 0.029 while the refit's mass
/// moved by 20 % per millimetre (0.193–0.288 g one millimetre either side in x).
pub fn grid_resolution_ln_sd(points_m: &[[f64; 2]], amplitude: &[f64], best: usize) -> f64 {
    let [bx, by] = points_m[best];
    let a0 = amplitude[best];
    let scale = points_m
        .iter()
        .map(|p| p[0].abs().max(p[1].abs()))
        .fold(0.0, f64::max);
    let tol = 1e-9 * scale.max(f64::MIN_POSITIVE);
    let mut var = 0.0;
    for axis in 0..2 {
        let other = 1 - axis;
        let along = |sign: f64| {
            (0..points_m.len())
                .filter(|&i| {
                    let p = points_m[i];
                    (p[other] - [bx, by][other]).abs() <= tol
                        && sign * (p[axis] - [bx, by][axis]) > tol
                        && amplitude[i] * a0 > 0.0
                })
                .min_by(|&i, &j| {
                    (points_m[i][axis] - [bx, by][axis])
                        .abs()
                        .total_cmp(&(points_m[j][axis] - [bx, by][axis]).abs())
                })
        };
        let ends: Vec<usize> = [along(-1.0), along(1.0)].into_iter().flatten().collect();
        let (lo, hi) = match ends.as_slice() {
            [l, h] => (*l, *h),
            [e] if points_m[*e][axis] < [bx, by][axis] => (*e, best),
            [e] => (best, *e),
            _ => continue,
        };
        let h = ends
            .iter()
            .map(|&e| (points_m[e][axis] - [bx, by][axis]).abs())
            .fold(f64::INFINITY, f64::min);
        let g = (amplitude[hi].abs().ln() - amplitude[lo].abs().ln())
            / (points_m[hi][axis] - points_m[lo][axis]);
        var += (g * h / 3f64.sqrt()).powi(2);
    }
    var.sqrt()
}

/// The largest distance from `best` of a region point that is not nearer to one of `others`:
/// the radius of the part of the region around `best` (the region of a near-symmetric board
/// holds the mirror points too).
fn local_radius(region: &[[f64; 2]], best: [f64; 2], others: &[[f64; 2]]) -> f64 {
    let dist = |p: [f64; 2], q: [f64; 2]| (p[0] - q[0]).hypot(p[1] - q[1]);
    region
        .iter()
        .filter(|p| others.iter().all(|o| dist(**p, best) <= dist(**p, *o)))
        .map(|p| dist(*p, best))
        .fold(0.0, f64::max)
}

/// Weighted residual-space projector: the orthonormal basis of the weighted nuisance columns
/// (modified Gram–Schmidt; columns that add less than 1e-9 of their norm are dropped).
fn basis(nuisance: &[Vec<f64>], w_sqrt: &[f64]) -> Vec<Vec<f64>> {
    let mut q: Vec<Vec<f64>> = vec![];
    for col in nuisance {
        let mut v: Vec<f64> = col.iter().zip(w_sqrt).map(|(a, w)| a * w).collect();
        let n0 = norm(&v);
        project_off(&mut v, &q);
        let n = norm(&v);
        if n0 > 0.0 && n > 1e-9 * n0 {
            q.push(v.iter().map(|x| x / n).collect());
        }
    }
    q
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn norm(a: &[f64]) -> f64 {
    dot(a, a).sqrt()
}

fn project_off(v: &mut [f64], q: &[Vec<f64>]) {
    for b in q {
        let d = dot(v, b);
        v.iter_mut().zip(b).for_each(|(x, y)| *x -= d * y);
    }
}

/// 90 % quantile of χ² with 2 degrees of freedom: −2 ln 0.1.
pub const CHI2_2_Q90: f64 = 4.605_170_185_988_091;

/// 99.9 % quantile of χ² with 2 degrees of freedom: −2 ln 0.001.
pub const CHI2_2_Q999: f64 = 13.815_510_557_964_274;

/// Locate a point mass; `None` when there are too few modes (at least the independent
/// nuisance parameters + 3 are needed), no finite standard error, or no point gives a positive
/// mass. `min_separation_m` separates alternatives from the best point.
pub fn localize_point_mass(inp: &LocalizeInput, min_separation_m: f64) -> Option<LocalFit> {
    localize_point_mass_at(inp, min_separation_m, None)
}

/// [`localize_point_mass`] with the best point given (`Some(index into points_m)`), e.g. one
/// of its alternatives that other evidence (the mode shapes) prefers: mass, χ², region and
/// alternatives are then those of that point. `None` also when the given point's mass is not
/// positive.
pub fn localize_point_mass_at(
    inp: &LocalizeInput,
    min_separation_m: f64,
    at: Option<usize>,
) -> Option<LocalFit> {
    let n = inp.modes.len();
    if n == 0
        || inp.points_m.len() != inp.signature.len()
        || inp.nuisance.iter().any(|c| c.len() != n)
        || inp.signature.iter().any(|s| s.len() != n)
    {
        return None;
    }
    if inp
        .modes
        .iter()
        .any(|m| !(m.se_rel.is_finite() && m.se_rel > 0.0 && m.mean_rel.is_finite()))
    {
        return None;
    }
    let w_sqrt: Vec<f64> = inp.modes.iter().map(|m| 1.0 / m.se_rel).collect();
    let q = basis(inp.nuisance, &w_sqrt);
    if n < q.len() + 3 {
        return None;
    }
    let mut r: Vec<f64> = inp
        .modes
        .iter()
        .zip(&w_sqrt)
        .map(|(m, w)| m.mean_rel * w)
        .collect();
    project_off(&mut r, &q);
    let chi2_before = dot(&r, &r);
    // Per point: amplitude and Δχ² (0 where the amplitude is not a positive mass).
    let fits: Vec<(f64, f64, f64)> = inp
        .signature
        .iter()
        .map(|s| {
            let mut v: Vec<f64> = s.iter().zip(&w_sqrt).map(|(a, w)| a * w).collect();
            project_off(&mut v, &q);
            let ss = dot(&v, &v);
            if ss.is_nan() || ss <= 0.0 {
                return (0.0, 0.0, f64::INFINITY);
            }
            let amp = dot(&v, &r) / ss;
            let d = if amp > 0.0 || (!inp.positive_only && amp < 0.0) {
                amp * amp * ss
            } else {
                0.0
            };
            (d, amp, 1.0 / ss.sqrt())
        })
        .collect();
    // To all orders in the mass where a modal basis is given, from the first-order amplitude.
    let fits: Vec<(f64, f64, f64)> = match &inp.exact {
        Some(b) if b.phi.len() == fits.len() && b.observed.len() == n => fits
            .iter()
            .enumerate()
            .map(|(i, &(d, amp, _))| {
                if d > 0.0 {
                    exact_fit(b, i, amp, &r, &w_sqrt, &q)
                } else {
                    (0.0, 0.0, f64::INFINITY)
                }
            })
            .collect(),
        _ => fits,
    };
    let (best, &(d_best, amp, se0)) = match at {
        Some(i) => (i, fits.get(i)?),
        None => fits
            .iter()
            .enumerate()
            .max_by(|a, b| a.1 .0.total_cmp(&b.1 .0))?,
    };
    if d_best.is_nan() || d_best <= 0.0 {
        return None;
    }
    let dof_after = n - q.len() - 3;
    let chi2_after = (chi2_before - d_best).max(0.0);
    let inflation = if dof_after > 0 {
        (chi2_after / dof_after as f64).max(1.0)
    } else {
        1.0
    };
    let threshold = CHI2_2_Q90 * inflation;
    let [bx, by] = inp.points_m[best];
    let dist = |p: [f64; 2], q: [f64; 2]| (p[0] - q[0]).hypot(p[1] - q[1]);
    let in_region: Vec<usize> = (0..fits.len())
        .filter(|&i| d_best - fits[i].0 <= threshold)
        .collect();
    // Local maxima in the region (a point at least as good as every point within the
    // separation distance), strongest first, kept when far from the best and each other.
    let mut maxima: Vec<usize> = in_region
        .iter()
        .copied()
        .filter(|&i| i != best)
        .filter(|&i| {
            (0..fits.len()).all(|j| {
                j == i
                    || dist(inp.points_m[i], inp.points_m[j]) > min_separation_m
                    || fits[j].0 <= fits[i].0
            })
        })
        .collect();
    maxima.sort_by(|a, b| fits[*b].0.total_cmp(&fits[*a].0));
    let mut kept: Vec<[f64; 2]> = vec![[bx, by]];
    let mut alternatives = vec![];
    for i in maxima {
        let p = inp.points_m[i];
        if kept.iter().all(|k| dist(*k, p) > min_separation_m) {
            kept.push(p);
            alternatives.push([p[0], p[1], fits[i].0]);
        }
    }
    let region: Vec<[f64; 2]> = in_region.iter().map(|&i| inp.points_m[i]).collect();
    let others: Vec<[f64; 2]> = alternatives.iter().map(|a| [a[0], a[1]]).collect();
    let region_radius_m = local_radius(&region, [bx, by], &others);
    // Over the best point's own part of the grid (not the mirror points': the refit at the
    // chosen point is compared with a model whose location prior covers the board, and the
    // mirror points' share of that evidence is left out, which errs against the mass).
    let own: f64 = (0..fits.len())
        .filter(|&i| {
            let p = inp.points_m[i];
            others.iter().all(|o| dist(p, [bx, by]) <= dist(p, *o))
        })
        .map(|i| (-(d_best - fits[i].0).max(0.0) / (2.0 * inflation)).exp())
        .sum();
    let log_location_occam = (own / fits.len() as f64).ln().min(0.0);
    let weighted: Vec<(f64, f64)> = (0..fits.len())
        .filter(|&i| {
            let p = inp.points_m[i];
            fits[i].1 * amp > 0.0 && others.iter().all(|o| dist(p, [bx, by]) <= dist(p, *o))
        })
        .map(|i| {
            (
                (-(d_best - fits[i].0).max(0.0) / (2.0 * inflation)).exp(),
                fits[i].1.abs().ln(),
            )
        })
        .collect();
    let amplitudes: Vec<f64> = fits.iter().map(|f| f.1).collect();
    let location_ln_amplitude_sd =
        weighted_sd(&weighted).hypot(grid_resolution_ln_sd(inp.points_m, &amplitudes, best));
    Some(LocalFit {
        x_m: bx,
        y_m: by,
        amplitude: amp,
        amplitude_se: se0 * inflation.sqrt(),
        chi2_before,
        chi2_after,
        dof_after,
        explained_share: if chi2_before > 0.0 {
            d_best / chi2_before
        } else {
            0.0
        },
        p_value: chi2_sf(d_best, 3.0),
        region_radius_m,
        region_points: in_region.len(),
        alternatives,
        log_location_occam,
        location_ln_amplitude_sd,
        step_shift_rel: 0.0,
        delta_chi2: fits.iter().map(|f| f.0).collect(),
        inflation,
        amplitude_at: fits.iter().map(|f| f.1).collect(),
    })
}

/// One measured mode shape for [`shape_score`]: the measured shape at the scan points, the
/// model's (mass-normalised) shape there, and the first-order change of the model's shape
/// per kilogram of a point mass at the candidate point c,
///
/// ```text
/// ∂φ_j/∂m = Σ_{k≠j} −λ_j φ_k(c) φ_j(c) / (λ_j − λ_k) · φ_k   (rigid-body modes included, λ = 0)
/// ```
///
/// (the −½ φ_j(c)² φ_j self term only rescales the shape and drops out with the optimal
/// scale). The points are those of one measurement; non-finite measured values are left out.
#[derive(Clone, Debug)]
pub struct ShapeObs {
    pub measured: Vec<f64>,
    pub model: Vec<f64>,
    pub d_model_per_kg: Vec<f64>,
    /// The shape's weight in the score: 1, or n / δ² (n scan points, δ the updating's shape
    /// error of its mode), which makes the score the first-order Δχ² of the updating's shape
    /// terms n (1 − MAC) / δ² ([`crate::bayes::modal::log_lik`]), comparable with the
    /// frequencies' Δχ².
    pub weight: f64,
}

/// How much a point mass of `mass_kg` with the given shape changes reduces the mode-shape
/// residuals: Σ over shapes of (‖ρ‖² − ‖ρ − m σ′‖²) / ‖φ‖², with ρ = ψ/α − φ the residual of
/// the measured shape ψ after its least-squares scale α (sign included) onto the model's φ,
/// and σ′ the shape change with its component along φ removed (the scale absorbs it). Larger
/// is better; a signature of the wrong sign or place scores below zero. The frequencies of a
/// symmetric board cannot tell mirror points apart, the shape changes can: φ_k(c) φ_j(c)
/// changes sign under a mirror for modes of opposite symmetry.
pub fn shape_score(obs: &[ShapeObs], mass_kg: f64) -> f64 {
    let mut total = 0.0;
    for o in obs {
        let idx: Vec<usize> = (0..o.measured.len())
            .filter(|&i| {
                o.measured[i].is_finite()
                    && o.model[i].is_finite()
                    && o.d_model_per_kg[i].is_finite()
            })
            .collect();
        let pick = |v: &[f64]| idx.iter().map(|&i| v[i]).collect::<Vec<f64>>();
        let (psi, phi, d) = (pick(&o.measured), pick(&o.model), pick(&o.d_model_per_kg));
        let pp = dot(&phi, &phi);
        let alpha = dot(&psi, &phi) / pp;
        if idx.len() < 3 || pp <= 0.0 || alpha == 0.0 || !alpha.is_finite() {
            continue;
        }
        let rho: Vec<f64> = psi.iter().zip(&phi).map(|(a, b)| a / alpha - b).collect();
        let along = dot(&d, &phi) / pp;
        let sig: Vec<f64> = d
            .iter()
            .zip(&phi)
            .map(|(a, b)| mass_kg * (a - along * b))
            .collect();
        let after: f64 = rho.iter().zip(&sig).map(|(r, s)| (r - s) * (r - s)).sum();
        total += o.weight * (dot(&rho, &rho) - after) / pp;
    }
    total
}

#[cfg(test)]
mod tests {
    use super::*;

    /// On a 2 mm grid whose amplitude grows by e^0.1 per millimetre along x and not along y,
    /// the resolution's sd of ln amplitude is 0.1 × 2 mm / √3; at the grid's edge the
    /// difference is one-sided; a neighbour with the other sign is not a neighbour.
    #[test]
    fn the_grid_resolution_carries_the_amplitude_gradient() {
        let mut pts = vec![];
        let mut amp = vec![];
        for i in 0..3 {
            for k in 0..3 {
                pts.push([0.002 * i as f64, 0.002 * k as f64]);
                amp.push((0.1 * 2.0 * i as f64).exp());
            }
        }
        let want = 0.1 * 2.0 / 3f64.sqrt();
        let centre = 4; // (2, 2) mm
        assert!((grid_resolution_ln_sd(&pts, &amp, centre) - want).abs() < 1e-9);
        assert!((grid_resolution_ln_sd(&pts, &amp, 0) - want).abs() < 1e-9);
        amp[7] = -amp[7]; // (4, 2) mm: the other sign
        let got = grid_resolution_ln_sd(&pts, &amp, centre);
        assert!((got - want).abs() < 1e-9, "{got}");
        amp[1] = -amp[1]; // (0, 2) mm too: no neighbour along x
        assert_eq!(grid_resolution_ln_sd(&pts, &amp, centre), 0.0);
    }

    fn fit(
        modes: &[ModeResidual],
        nuisance: &[Vec<f64>],
        points: &[[f64; 2]],
        sig: &[Vec<f64>],
    ) -> Option<LocalFit> {
        let inp = LocalizeInput {
            modes,
            nuisance,
            points_m: points,
            signature: sig,
            exact: None,
            positive_only: true,
        };
        localize_point_mass(&inp, 0.01)
    }

    /// The 0.08 × 0.05 m board's points on a 2.5 mm grid, and at each the signature of
    /// modes 0..n from `sig_at(mode, x_m, y_m)`.
    fn board_grid(
        n: usize,
        sig_at: impl Fn(usize, f64, f64) -> f64,
    ) -> (Vec<[f64; 2]>, Vec<Vec<f64>>) {
        let mut points = vec![];
        let mut sig = vec![];
        for i in 0..=32 {
            for k in 0..=20 {
                let (x, y) = (i as f64 * 0.0025, k as f64 * 0.0025);
                points.push([x, y]);
                sig.push((0..n).map(|j| sig_at(j, x, y)).collect());
            }
        }
        (points, sig)
    }

    /// A synthetic "plate": modes with shapes sin(a x) sin(b y) on a 0.08 × 0.05 m rectangle
    /// (mass-normalised for a 20 g board), a point mass of 0.3 g at (0.055, 0.031) and two
    /// nuisance parameters (a uniform stiffness and a uniform mass scale). The residuals are
    /// the exact first-order effect plus the part the nuisance parameters would have absorbed;
    /// the localisation finds the point within one grid step (2.5 mm; the true point is off
    /// the grid in y) and the mass within 10 %.
    #[test]
    fn finds_a_point_mass_on_an_asymmetric_signature() {
        let (lx, ly, m_board): (f64, f64, f64) = (0.08, 0.05, 0.02);
        let waves: [(f64, f64); 9] = [
            (1.0, 1.0),
            (2.0, 1.0),
            (1.0, 2.0),
            (3.0, 1.0),
            (2.0, 2.0),
            (1.5, 1.0),
            (3.0, 2.0),
            (1.0, 3.0),
            (2.5, 1.5),
        ];
        // Half-integer waves break the mirror symmetry as a board's real copper does.
        let phi = |j: usize, x: f64, y: f64| {
            let (a, b) = waves[j];
            2.0 / m_board.sqrt()
                * (a * std::f64::consts::PI * x / lx).sin()
                * (b * std::f64::consts::PI * y / ly).sin()
        };
        let n = waves.len();
        let (x0, y0, dm) = (0.055, 0.031, 0.3e-3);
        let nuisance = vec![vec![0.5; n], vec![-0.5; n]];
        let stiffness_absorbed = 0.002;
        let modes: Vec<ModeResidual> = (0..n)
            .map(|j| ModeResidual {
                label: format!("m{j}"),
                mean_rel: -0.5 * dm * phi(j, x0, y0).powi(2) + 0.5 * stiffness_absorbed,
                se_rel: 1e-4 * (1.0 + 0.1 * j as f64),
            })
            .collect();
        let (points, sig) = board_grid(n, |j, x, y| -0.5 * phi(j, x, y).powi(2));
        let fit = fit(&modes, &nuisance, &points, &sig).unwrap();
        assert!(
            (fit.x_m - x0).abs() <= 0.0025 && (fit.y_m - y0).abs() <= 0.0025,
            "{fit:?}"
        );
        assert!((fit.amplitude / dm - 1.0).abs() < 0.1, "{fit:?}");
        assert!(fit.explained_share > 0.9, "{fit:?}");
        assert!(fit.p_value < 1e-6, "{fit:?}");
        // The location's Occam factor: between one grid point of the board's and all of
        // them, and for this sharp a peak (σ ≈ 1e-4 on shifts of 1e-2) a few points' worth.
        let n_pts = points.len() as f64;
        assert!(
            fit.log_location_occam >= -n_pts.ln() && fit.log_location_occam < (10.0 / n_pts).ln(),
            "{fit:?}"
        );
    }

    /// A change of either sign (a stiffness loss, amplitude < 0, on a signature of the
    /// stiffness's sign) is found where `positive_only` is off, at its point and size; a fit
    /// restricted to positive amplitudes (a mass) explains clearly less, elsewhere.
    #[test]
    fn either_sign_finds_a_loss_a_positive_fit_misses() {
        let (lx, ly): (f64, f64) = (0.08, 0.05);
        let waves: [(f64, f64); 7] = [
            (1.0, 1.0),
            (2.0, 1.0),
            (1.0, 2.0),
            (3.0, 1.0),
            (2.0, 2.0),
            (1.5, 1.0),
            (2.5, 1.5),
        ];
        // Curvature-like signature: positive everywhere but with its own pattern per mode.
        let sig_at = |j: usize, x: f64, y: f64| {
            let (a, b) = waves[j];
            0.01 * ((a * std::f64::consts::PI * x / lx).cos()
                * (b * std::f64::consts::PI * y / ly).cos())
            .powi(2)
        };
        let n = waves.len();
        let (x0, y0, amp) = (0.0225, 0.0325, -0.6);
        let nuisance = vec![vec![0.5; n]];
        let modes: Vec<ModeResidual> = (0..n)
            .map(|j| ModeResidual {
                label: format!("m{j}"),
                mean_rel: amp * sig_at(j, x0, y0),
                se_rel: 1e-4,
            })
            .collect();
        let (points, sig) = board_grid(n, sig_at);
        let inp = |positive_only| LocalizeInput {
            modes: &modes,
            nuisance: &nuisance,
            points_m: &points,
            signature: &sig,
            exact: None,
            positive_only,
        };
        let either = localize_point_mass(&inp(false), 0.01).unwrap();
        assert!((either.amplitude / amp - 1.0).abs() < 1e-6, "{either:?}");
        assert!(either.explained_share > 0.999, "{either:?}");
        // The cos² signature is mirror-symmetric: the point or one of its mirror images.
        let mirrors = [[x0, y0], [lx - x0, y0], [x0, ly - y0], [lx - x0, ly - y0]];
        assert!(
            mirrors
                .iter()
                .any(|m| (either.x_m - m[0]).abs() < 1e-9 && (either.y_m - m[1]).abs() < 1e-9),
            "{either:?}"
        );
        // Restricted to positive amplitudes, the best fit lies elsewhere and explains
        // clearly less.
        if let Some(p) = localize_point_mass(&inp(true), 0.01) {
            assert!(p.amplitude > 0.0);
            assert!(
                p.explained_share < either.explained_share - 0.1,
                "{} vs {}",
                p.explained_share,
                either.explained_share
            );
            assert!(!mirrors
                .iter()
                .any(|m| (p.x_m - m[0]).abs() < 1e-9 && (p.y_m - m[1]).abs() < 1e-9));
        }
    }

    /// Measured shapes made by the first-order change of a point mass at c score higher at c
    /// than at its mirror image, where the change has the opposite sign in the modes of
    /// opposite symmetry.
    #[test]
    fn shape_changes_tell_a_point_from_its_mirror_image() {
        let lx: f64 = 0.08;
        let pts: Vec<f64> = (0..=20).map(|i| lx * i as f64 / 20.0).collect();
        // A beam-like set: a symmetric and an antisymmetric mode about x = lx/2, plus a rigid
        // translation; eigenvalues 1, 3, 0.
        let shape = |k: usize, x: f64| match k {
            0 => (std::f64::consts::PI * x / lx).sin(),
            1 => (2.0 * std::f64::consts::PI * x / lx).sin(),
            _ => 0.7,
        };
        let lam = [1.0, 3.0, 0.0];
        let d = |j: usize, c: f64| -> Vec<f64> {
            pts.iter()
                .map(|&x| {
                    (0..3)
                        .filter(|&k| k != j)
                        .map(|k| {
                            -lam[j] * shape(k, c) * shape(j, c) / (lam[j] - lam[k]) * shape(k, x)
                        })
                        .sum()
                })
                .collect()
        };
        let (c, mirror, m) = (0.055, lx - 0.055, 0.05);
        let obs = |at: f64| -> Vec<ShapeObs> {
            (0..2)
                .map(|j| {
                    let model: Vec<f64> = pts.iter().map(|&x| shape(j, x)).collect();
                    let truth = d(j, c);
                    ShapeObs {
                        measured: model
                            .iter()
                            .zip(&truth)
                            .map(|(a, b)| -2.0 * (a + m * b))
                            .collect(),
                        model,
                        d_model_per_kg: d(j, at),
                        weight: 1.0,
                    }
                })
                .collect()
        };
        let (at_c, at_mirror) = (shape_score(&obs(c), m), shape_score(&obs(mirror), m));
        assert!(
            at_c > 0.0 && at_c > at_mirror + 0.5 * at_c,
            "{at_c} vs {at_mirror}"
        );
    }

    /// Residuals in the span of the parameters alone (nothing a point mass adds) locate
    /// nothing significant: the best Δχ² is noise-sized.
    #[test]
    fn residuals_the_parameters_explain_locate_nothing() {
        let n = 6;
        let nuisance = vec![(0..n).map(|j| 0.3 + 0.1 * j as f64).collect::<Vec<_>>()];
        // Residual = a multiple of the nuisance column + tiny alternating noise.
        let modes: Vec<ModeResidual> = (0..n)
            .map(|j| ModeResidual {
                label: format!("m{j}"),
                mean_rel: 0.01 * (0.3 + 0.1 * j as f64) + if j % 2 == 0 { 1e-5 } else { -1e-5 },
                se_rel: 1e-4,
            })
            .collect();
        let points: Vec<[f64; 2]> = (0..50).map(|i| [i as f64 * 1e-3, 0.0]).collect();
        let sig: Vec<Vec<f64>> = (0..50)
            .map(|i| {
                (0..n)
                    .map(|j| -((i as f64 * 0.1 + j as f64).sin()).powi(2) * 50.0)
                    .collect()
            })
            .collect();
        if let Some(f) = fit(&modes, &nuisance, &points, &sig) {
            assert!(f.chi2_before < 1.0 && f.p_value > 0.3, "{f:?}");
        }
    }
}

#[cfg(test)]
mod exact_tests {
    use super::*;
    use crate::fem::eigen::EigenOptions;
    use crate::fem::{FeModel, Setup};

    /// The secular equation in a modal basis of the measured modes + 40 against the FE
    /// model with the point mass assembled (M + m N Nᵀ): a 0.25 g and a 1 g mass (2 % and
    /// 8 % of the default board) at an interior point, the 8 lowest elastic modes. The
    /// truncated basis lacks the high modes' local flexibility at the point: the worst error
    /// is 7.4e-5 (0.5 % of the shift) at 0.25 g and 9.1e-4 (1.9 %) at 1 g, against the first
    /// order's 1.7e-3 (12 % of the shift) and 2.4e-2.
    #[test]
    fn exact_localisation_matches_the_fe_model_with_the_point_mass() {
        let board = crate::fem::tests::helpers::thin_board();
        let model = FeModel::build(&board, Setup::Free, &board.mesh).unwrap();
        let p = model.nominal_params();
        let (modes, rigid) = model
            .modes_and_rigid(&p, 48, &EigenOptions::default())
            .unwrap();
        let (x, y) = (0.0553, 0.0311);
        let op = model.shape_operator(&[[x, y]]).unwrap();
        let (el, rg) = (op.apply(modes.shapes.as_ref()), op.apply(rigid.as_ref()));
        let lambda: Vec<f64> = std::iter::repeat_n(0.0, rigid.ncols())
            .chain(modes.eigenvalues.iter().copied())
            .collect();
        let a: Vec<f64> = (0..rigid.ncols())
            .map(|k| rg[(0, k)])
            .chain((0..modes.eigenvalues.len()).map(|k| el[(0, k)]))
            .collect();
        let observed: Vec<usize> = (0..8).map(|j| j + rigid.ncols()).collect();
        for (m, tol, share) in [(2.5e-4, 1e-4, 0.01), (1e-3, 2e-3, 0.03)] {
            let mu = point_mass_eigenvalues(&lambda, &a, m, &observed);
            let mut with = model.clone();
            with.add_point_mass(x, y, m).unwrap();
            let full = with.modes(&p, 8).unwrap();
            let mut worst: f64 = 0.0;
            let mut shift: f64 = 0.0;
            let mut first_order: f64 = 0.0;
            for j in 0..8 {
                let f = mu[j].sqrt() / (2.0 * std::f64::consts::PI);
                worst = worst.max((f / full.freq_hz[j] - 1.0).abs());
                let a_j = a[observed[j]];
                let f1 = modes.freq_hz[j] * (1.0 - 0.5 * m * a_j * a_j);
                first_order = first_order.max((f1 / full.freq_hz[j] - 1.0).abs());
                shift = shift.max((full.freq_hz[j] / modes.freq_hz[j] - 1.0).abs());
            }
            eprintln!("m = {m} kg: largest shift {shift:.2e}, worst error {worst:.2e}, first order's {first_order:.2e}");
            assert!(worst < tol && worst < share * shift, "{worst} vs {shift}");
        }
    }

    /// First order: for a small mass every root is λ_j (1 − m φ_j(p)²), and no mass, no
    /// change; a node (φ_j(p) = 0) keeps λ_j.
    #[test]
    fn secular_roots_reduce_to_first_order_and_keep_nodes() {
        let lambda = [0.0, 0.0, 100.0, 400.0, 900.0];
        let a = [0.3, -0.2, 1.5, 0.0, -2.0];
        let obs = [2, 3, 4];
        assert_eq!(
            point_mass_eigenvalues(&lambda, &a, 0.0, &obs),
            vec![100.0, 400.0, 900.0]
        );
        let m = 1e-6;
        let mu = point_mass_eigenvalues(&lambda, &a, m, &obs);
        for (k, &j) in obs.iter().enumerate() {
            let first = lambda[j] * (1.0 - m * a[j] * a[j]);
            assert!(
                (mu[k] - first).abs() <= 1e-9 * lambda[j],
                "{} vs {first}",
                mu[k]
            );
        }
        assert_eq!(mu[1], 400.0);
    }
}

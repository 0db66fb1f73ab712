//! Step 2's centre: the joint parameters that fit the mean bolted modes, found by
//! Levenberg–Marquardt on the full model.

use crate::fem::FeModel;
use crate::modal::rows::PairRow;
use crate::optim::lm::{levenberg_marquardt, sum_sq, WithJacobian};
use crate::update::enrichment::JointEnrichment;
use crate::update::new_modes::match_modes_of;
use crate::update::problem::Labels;

/// The centre fits' residual tolerance: a search stops once a step changes no label's
/// relative frequency residual by more than 1e-6. That is a thousandth of the diagnosis's
/// practical threshold (`select::DEFAULT_PRACTICAL_THRESHOLD_REL`, 0.1 %) and below the
/// ROM's own frequency error, which the steps check against the full model (1e-6 to 6e-5 on
/// the board models): the centre serves the ROM's box and the misfit shares the diagnosis
/// compares, and neither sees a change of that size. A search along a ridge (a joint's
/// ratio trading off against the common stiffness) spent dozens of FE solves on it.
const RESID_TOL: f64 = 1e-6;

/// A step-2 centre fit: the coordinates, and each label's relative residual there,
/// (model − median measured) / median measured, the labels with a measured median only.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CentreFit {
    pub coords: Vec<f64>,
    pub rel_residuals: Vec<(String, f64)>,
}

/// The ROM's centre in the enrichment's coordinates (ln, relative to the priors' centres).
#[allow(clippy::too_many_arguments)]
pub fn fit_centre(
    model: &FeModel,
    p_base: &crate::fem::Params,
    coords: &[Vec<(usize, f64)>],
    spans: &[f64],
    enr: &JointEnrichment,
    n_fit: usize,
    (labels, bolted_rows): (&Labels, &[&PairRow]),
    (w_labels, points): (&faer::Mat<f64>, &[[f64; 2]]),
    n_track: usize,
) -> anyhow::Result<CentreFit> {
    let CentreFit {
        coords: mut fit,
        mut rel_residuals,
    } = fit_joint_centre(
        model,
        p_base,
        &coords[..n_fit],
        &spans[..n_fit],
        labels,
        bolted_rows,
        (w_labels, points),
        n_track,
    )?;
    fit.resize(coords.len(), 0.0);
    let mut centre: Vec<f64> = fit
        .iter()
        .zip(&enr.coordinates)
        .enumerate()
        .map(|(k, (x, c))| match c.log_box {
            Some(w) if k > 0 => x.clamp(-0.5 * w, 0.5 * w),
            _ => *x,
        })
        .collect();
    if centre != fit {
        let mut p_held = p_base.clone();
        for (k, acts) in coords.iter().enumerate().skip(1) {
            for &(i, a) in acts {
                p_held.values[i] *= (a * centre[k]).exp();
            }
        }
        let k_con = fit_joint_centre(
            model,
            &p_held,
            &coords[..1],
            &spans[..1],
            labels,
            bolted_rows,
            (w_labels, points),
            n_track,
        )?;
        centre[0] = k_con.coords[0];
        rel_residuals = k_con.rel_residuals;
    }
    Ok(CentreFit {
        coords: centre,
        rel_residuals,
    })
}

/// The centre of a step-2 model's ROM, with each label's relative residual there: the unit
/// coordinates that best fit the median bolted frequency of every label at the boards' posterior mean (`p_base`, reference
/// values of the joint parameters), by Levenberg–Marquardt within ±`spans[k]`, with the
/// full FE model. The ROM
/// is built around it: its box is ±20 % and the nominal joint can be off by far more.
/// Only the ROM's centre depends on the data; the priors do not. The reference of the SMC
/// starts its search there too.
///
/// An enrichment can make the fit multimodal: a fixture resonance fits one way above the
/// band (where it hardly acts) and another way between two measured modes, and a local
/// search from the prior's centre never crosses a mode to reach the other. So the
/// enrichment's own coordinates (all but the first, k_con; the first two of them) are first
/// scanned on a grid over ±⅔ of their spans (7 points each, at most 7² points), and the
/// search runs from the prior's centre and from the two best grid points; the lowest misfit
/// wins.
#[allow(clippy::too_many_arguments)]
pub fn fit_joint_centre(
    model: &FeModel,
    p_base: &crate::fem::Params,
    coords: &[Vec<(usize, f64)>],
    spans: &[f64],
    labels: &Labels,
    rows: &[&PairRow],
    (w_ref, points): (&faer::Mat<f64>, &[[f64; 2]]),
    n_modes: usize,
) -> anyhow::Result<CentreFit> {
    // Median measured frequency per label.
    let med: Vec<Option<f64>> = labels
        .labels
        .iter()
        .map(|l| {
            let mut f: Vec<f64> = rows
                .iter()
                .filter(|p| &p.label == l)
                .map(|p| p.freq_hz)
                .collect();
            f.sort_by(f64::total_cmp);
            (!f.is_empty()).then(|| f[f.len() / 2])
        })
        .collect();
    let eval = |x: &[f64], jac: bool| {
        centre_residuals(
            model,
            p_base,
            coords,
            &med,
            (w_ref, points),
            n_modes,
            x,
            jac,
        )
    };
    let resid = |x: &[f64]| eval(x, false).map(|(r, _)| r);
    // Levenberg–Marquardt on ln-coordinates with analytic Jacobians (d ≤ 3, a few dozen FE
    // solves), kept inside ±spans: a joint's stiffnesses trade off against each other (k_con
    // against k_rot, one joint's ratio against the common k_con), a ridge a
    // one-coordinate-at-a-time search crawls along.
    let d = coords.len();
    // The grid of starts over the enrichment's coordinates: 7 points over ±⅔ of each span
    // (±2 prior sd, the spans being 3 prior sd).
    const GRID: [f64; 7] = [-1.0, -2.0 / 3.0, -1.0 / 3.0, 0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0];
    let mut grid: Vec<Vec<f64>> = vec![vec![0.0; d]];
    for k in 1..d.min(3) {
        grid = grid
            .iter()
            .flat_map(|g| {
                GRID.iter().map(move |&t| {
                    let mut g = g.clone();
                    g[k] = t * 2.0 / 3.0 * spans[k];
                    g
                })
            })
            .collect();
    }
    // The grid's FE solves side by side (rayon's collect keeps the grid's order).
    use rayon::prelude::*;
    let mut scored: Vec<(f64, Vec<f64>)> = grid
        .into_par_iter()
        // The prior's centre is the search's first start anyway.
        .filter(|g| g.iter().any(|v| *v != 0.0))
        .filter_map(|g| resid(&g).ok().map(|r| (sum_sq(&r), g)))
        .collect();
    scored.sort_by(|a, b| a.0.total_cmp(&b.0));
    // From the prior's centre (its failure is the step's) and from the two best grid points
    // (a search that meets a point the model cannot solve is dropped), side by side; the
    // lowest misfit wins, the earlier start on a tie, so the result is that of a sequential
    // search.
    let with_jac = |x: &[f64]| eval(x, true);
    let starts: Vec<Vec<f64>> = std::iter::once(vec![0.0; d])
        .chain(scored.into_iter().take(2).map(|(_, x0)| x0))
        .collect();
    let mut runs = starts
        .into_par_iter()
        .map(|x0| levenberg_marquardt(&with_jac, x0, spans, RESID_TOL))
        .collect::<Vec<_>>()
        .into_iter();
    let mut best = runs.next().expect("the prior's centre")?;
    for run in runs.flatten() {
        if run.0 < best.0 {
            best = run;
        }
    }
    let measured = labels.labels.iter().zip(&med).filter(|(_, m)| m.is_some());
    let rel_residuals = measured.map(|(l, _)| l.clone()).zip(best.2).collect();
    Ok(CentreFit {
        coords: best.1,
        rel_residuals,
    })
}

/// The centre fit's residuals at `x` (ln-coordinates, `coords[k]` scaling each parameter i by
/// e^{a x_k}): each label's (model − median) / median over the labels with a median (`med`),
/// the model's mode matched to the label by shape. With `jac`, their Jacobian: ∂f/∂x_k =
/// Σ a p_i ∂f/∂p_i, from the eigenvalue derivatives of the matched modes
/// ([`crate::fem::sensitivity::eigen_derivatives`] without shape derivatives: a few
/// matrix-vector products, where a forward difference costs an FE solve per coordinate).
#[allow(clippy::too_many_arguments)]
fn centre_residuals(
    model: &FeModel,
    p_base: &crate::fem::Params,
    coords: &[Vec<(usize, f64)>],
    med: &[Option<f64>],
    (w_ref, points): (&faer::Mat<f64>, &[[f64; 2]]),
    n_modes: usize,
    x: &[f64],
    jac: bool,
) -> anyhow::Result<WithJacobian> {
    let mut p = p_base.clone();
    for (k, acts) in coords.iter().enumerate() {
        for &(i, a) in acts {
            p.values[i] *= (a * x[k]).exp();
        }
    }
    let (idx, m) = match_modes_of(model, &p, n_modes, w_ref, points)?;
    let measured = || med.iter().zip(&idx).filter_map(|(m, &b)| m.map(|m| (m, b)));
    let r = measured()
        .map(|(med, b)| (m.freq_hz[b] - med) / med)
        .collect();
    if !jac {
        return Ok((r, vec![]));
    }
    // The derivatives with respect to the parameters the coordinates move, only.
    let mut params: Vec<usize> = coords.iter().flatten().map(|&(i, _)| i).collect();
    params.sort_unstable();
    params.dedup();
    let d = crate::fem::sensitivity::freq_derivatives_for(model, &p, &m, &params)?;
    let col = |i: usize| params.binary_search(&i).expect("a coordinate's parameter");
    let j = coords
        .iter()
        .map(|acts| {
            measured()
                .map(|(med, b)| {
                    acts.iter()
                        .map(|&(i, a)| a * p.values[i] * d[(b, col(i))])
                        .sum::<f64>()
                        / med
                })
                .collect()
        })
        .collect();
    Ok((r, j))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fem::params::names;
    use crate::fem::Setup;

    /// The centre fit's analytic Jacobian against central differences of its residuals, on
    /// the thin board bolted: one coordinate on the contact stiffness alone, one scaling
    /// E_x and E_y together with a = ½ (the form an enrichment's coordinate takes). The
    /// labels are matched by shape to the nominal modes 1–6; the medians sit 1 % off them.
    #[test]
    fn the_centre_jacobian_matches_central_differences() {
        let board = crate::fem::tests::helpers::thin_board();
        let model = FeModel::build(&board, Setup::bolted(), &board.mesh).unwrap();
        let p0 = model.nominal_params();
        let at = |n: &str| p0.names.iter().position(|m| m == n).unwrap();
        let coords = vec![
            vec![(at(names::K_CON), 1.0)],
            vec![(at(names::E_X), 0.5), (at(names::E_Y), 0.5)],
        ];
        let points: Vec<[f64; 2]> = (0..5)
            .flat_map(|i| (0..4).map(move |j| [0.008 + 0.016 * i as f64, 0.007 + 0.012 * j as f64]))
            .collect();
        let m0 = model.modes(&p0, 8).unwrap();
        let w_all = model.w_at(&m0, &points).unwrap();
        let w_ref = faer::Mat::from_fn(points.len(), 6, |i, j| w_all[(i, j)]);
        let med: Vec<Option<f64>> = (0..6)
            .map(|j| (j != 3).then(|| 1.01 * m0.freq_hz[j]))
            .collect();
        let x = [0.1, -0.05];
        let f = |x: &[f64], jac| {
            centre_residuals(&model, &p0, &coords, &med, (&w_ref, &points), 8, x, jac).unwrap()
        };
        let (r, j) = f(&x, true);
        assert_eq!((r.len(), j.len(), j[0].len()), (5, 2, 5));
        let h = 1e-4;
        for k in 0..2 {
            let (mut up, mut dn) = (x, x);
            up[k] += h;
            dn[k] -= h;
            let (ru, _) = f(&up, false);
            let (rd, _) = f(&dn, false);
            for i in 0..5 {
                let fd = (ru[i] - rd[i]) / (2.0 * h);
                assert!(
                    (j[k][i] - fd).abs() <= 1e-4 * fd.abs().max(1e-3),
                    "coordinate {k}, label {i}: analytic {} vs central {fd}",
                    j[k][i]
                );
            }
        }
    }
}

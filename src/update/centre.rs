//! Step 2's centre: the joint parameters that fit the mean bolted modes, found by
//! Levenberg–Marquardt on the full model.

use crate::fem::FeModel;
use crate::modal::rows::PairRow;
use crate::optim::lm::{levenberg_marquardt, sum_sq};
use crate::update::enrichment::JointEnrichment;
use crate::update::new_modes::match_modes;
use crate::update::problem::Labels;

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
    // Relative residuals of the labels with a measured median.
    let resid = |x: &[f64]| -> anyhow::Result<Vec<f64>> {
        let mut p = p_base.clone();
        for (k, acts) in coords.iter().enumerate() {
            for &(i, a) in acts {
                p.values[i] *= (a * x[k]).exp();
            }
        }
        let (_, f) = match_modes(model, &p, n_modes, w_ref, points)?;
        Ok(med
            .iter()
            .zip(&f)
            .filter_map(|(m, fm)| m.map(|m| (fm - m) / m))
            .collect())
    };
    // Levenberg–Marquardt on ln-coordinates with forward-difference Jacobians (d ≤ 3, a few
    // dozen FE solves), kept inside ±spans: a joint's stiffnesses trade off against each
    // other (k_con against k_rot), a ridge a one-coordinate-at-a-time search crawls along.
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
    // From the prior's centre as before (its failure is the step's); a grid start whose
    // search meets a point the model cannot solve is dropped.
    let mut best = levenberg_marquardt(&resid, vec![0.0; d], spans)?;
    for (_, x0) in scored.into_iter().take(2) {
        if let Ok((c, x)) = levenberg_marquardt(&resid, x0, spans) {
            if c < best.0 {
                best = (c, x);
            }
        }
    }
    let at = resid(&best.1)?;
    let measured = labels.labels.iter().zip(&med).filter(|(_, m)| m.is_some());
    let rel_residuals = measured.map(|(l, _)| l.clone()).zip(at).collect();
    Ok(CentreFit {
        coords: best.1,
        rel_residuals,
    })
}

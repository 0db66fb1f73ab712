//! Where on the board: the inputs of [`crate::diagnose::localize`] from a work directory.
//!
//! The free-free model is built from the board file at the step-1 posterior centre (the
//! median over all boards' draws of every updated parameter, `update_boards/boards.parquet`);
//! its modes give the point-mass signature −½ φ_j² on a grid over the board (holes left out)
//! and, by finite differences of 1 % in each updated parameter, the sensitivities the
//! localisation projects off. Labels are matched to model modes by the nearest frequency to
//! their mean model frequency in the step-1 residuals. The frequencies cannot tell the mirror
//! images of a point apart on a near-symmetric board; the measured mode shapes
//! (`extract/modes.parquet`, the accepted free-free pairs) choose among the best point and
//! its alternatives by [`shape_score`].

use std::path::Path;

use anyhow::{anyhow, Context};

use crate::diagnose::library::Mechanism;
use crate::diagnose::localize::{
    localize_point_mass, localize_point_mass_at, shape_score, LocalizeInput, ModeResidual,
    PointMassFit, ShapeObs,
};
use crate::diagnose::locate::{LocateOptions, ModeCheck, PairObs};
use crate::fem::eigen::EigenOptions;
use crate::fem::{Board, FeModel, Setup};
use crate::io::tables::{read_parquet, Cols};

/// Grid step of the candidate points, m. 2 mm: a tenth of the shortest bending half-wave of
/// the modes a free-free test identifies on a board of a few centimetres, and 5× finer than
/// the 10 mm a located region must be within.
pub const GRID_STEP_M: f64 = 2e-3;

/// Alternatives closer than this to the best point are the same region.
pub const MIN_SEPARATION_M: f64 = 10e-3;

/// A point-mass fit is reported as located when its Δχ² is significant at the locate step's
/// FDR level and it explains at least this share of the free-free misfit off the parameters'
/// span: a mechanism is named as the location of a misfit only when it accounts for most of
/// it.
pub const MIN_EXPLAINED_SHARE: f64 = 0.5;

/// One located (or examined) board region.
#[derive(Clone, Debug, serde::Serialize, schemars::JsonSchema)]
pub struct BoardRegion {
    /// The mechanism whose signature was fitted (`added_mass`).
    pub mechanism: Mechanism,
    /// Whether the fit passes the rule (significant, and explains at least half the misfit).
    pub located: bool,
    pub fit: PointMassFit,
    /// The mode-shape score of each candidate point (x_m, y_m, score; [`shape_score`],
    /// larger is better): the best point of the frequencies and its alternatives. Empty when
    /// no measured shape could be used.
    pub shape_scores: Vec<[f64; 3]>,
    /// The shapes chose another point than the frequencies' best (which became an
    /// alternative; the fit is the chosen point's).
    pub chosen_by_shapes: bool,
    /// Measured shapes used by the shape choice, and those left out (lists of unequal
    /// length, scan points the model cannot evaluate).
    pub shapes_used: usize,
    pub shapes_skipped: usize,
    pub sentence: String,
}

/// The point-mass localisation over the free-free modes of `checks` (locate's mode checks).
/// `Err` says why it could not run (the stage writes it as the note).
pub fn point_mass_region(
    work: &Path,
    board: &Board,
    params: &[String],
    checks: &[ModeCheck],
    residual_model_freq: &[(String, f64)],
    locate: &LocateOptions,
    pairs: &[PairObs],
) -> anyhow::Result<BoardRegion> {
    let free: Vec<&ModeCheck> = checks.iter().filter(|c| c.setup == "free").collect();
    if free.is_empty() {
        return Err(anyhow!("no free-free mode residuals"));
    }
    let centre = posterior_centre(&work.join("update_boards/boards.parquet"), params)?;
    let model = FeModel::build(board, Setup::Free, &board.mesh)?;
    let mut p0 = model.nominal_params();
    for (name, v) in params.iter().zip(&centre) {
        p0.set(name, *v)?;
    }
    let n_model = free.len() + 4;
    let (modes0, rigid) = model.modes_and_rigid(&p0, n_model, &EigenOptions::default())?;
    // Label → model mode by nearest frequency (each model mode used once).
    let mut taken = vec![false; modes0.freq_hz.len()];
    let mut index = vec![];
    for c in &free {
        let f = residual_model_freq
            .iter()
            .find(|(l, _)| *l == c.label)
            .map(|(_, f)| *f)
            .ok_or_else(|| anyhow!("label {:?}: no model frequency in the residuals", c.label))?;
        let (j, _) = modes0
            .freq_hz
            .iter()
            .enumerate()
            .filter(|(j, _)| !taken[*j])
            .min_by(|a, b| (a.1 - f).abs().total_cmp(&(b.1 - f).abs()))
            .ok_or_else(|| anyhow!("fewer model modes than labels"))?;
        taken[j] = true;
        index.push(j);
    }
    let nuisance: Vec<Vec<f64>> = params
        .iter()
        .map(|name| -> anyhow::Result<Vec<f64>> {
            let mut p = p0.clone();
            let v = p.get(name)?;
            let h: f64 = 0.01;
            p.set(name, v * h.exp())?;
            let m = model.modes(&p, n_model)?;
            Ok(index
                .iter()
                .map(|&j| {
                    // The perturbed mode nearest in frequency to the centre's mode j.
                    let f0 = modes0.freq_hz[j];
                    let f = m
                        .freq_hz
                        .iter()
                        .copied()
                        .min_by(|a, b| (a - f0).abs().total_cmp(&(b - f0).abs()))
                        .unwrap_or(f0);
                    (f / f0).ln() / h
                })
                .collect())
        })
        .collect::<anyhow::Result<_>>()?;
    let points = grid(board);
    let w = model.w_at(&modes0, &points)?;
    let signature: Vec<Vec<f64>> = (0..points.len())
        .map(|i| index.iter().map(|&j| -0.5 * w[(i, j)].powi(2)).collect())
        .collect();
    let modes: Vec<ModeResidual> = free
        .iter()
        .map(|c| ModeResidual {
            label: c.label.clone(),
            mean_rel: c.mean_rel_residual,
            se_rel: c.se_rel_residual,
        })
        .collect();
    let inp = LocalizeInput {
        modes: &modes,
        nuisance: &nuisance,
        points_m: &points,
        signature: &signature,
    };
    let fit = localize_point_mass(&inp, MIN_SEPARATION_M).ok_or_else(|| {
        anyhow!(
            "no point mass fits the free-free residuals ({} modes, {} parameters)",
            modes.len(),
            params.len()
        )
    })?;
    // Mode shapes choose among the best point and its alternatives; the chosen point's own
    // fit (mass, χ², region) is then the one reported.
    let label_index: Vec<(String, usize)> = free
        .iter()
        .zip(&index)
        .map(|(c, &j)| (c.label.clone(), j))
        .collect();
    let shapes = shape_choice(
        &model,
        (&modes0, &rigid),
        &work.join("extract/modes.parquet"),
        pairs,
        &label_index,
        &fit,
    )?;
    let chosen = shapes
        .scores
        .iter()
        .max_by(|a, b| a[2].total_cmp(&b[2]))
        .filter(|b| (b[0], b[1]) != (fit.x_m, fit.y_m))
        .and_then(|b| points.iter().position(|p| (p[0], p[1]) == (b[0], b[1])))
        .and_then(|i| localize_point_mass_at(&inp, MIN_SEPARATION_M, Some(i)));
    let chosen_by_shapes = chosen.is_some();
    let fit = chosen.unwrap_or(fit);
    let shape_scores = shapes.scores;
    let located = fit.p_value < locate.fdr && fit.explained_share >= MIN_EXPLAINED_SHARE;
    let alt = if fit.alternatives.is_empty() {
        String::new()
    } else {
        format!(
            "; the frequencies fit about as well at {}{}",
            fit.alternatives
                .iter()
                .map(|a| format!("({:.0}, {:.0}) mm", a[0] * 1e3, a[1] * 1e3))
                .collect::<Vec<_>>()
                .join(", "),
            if chosen_by_shapes {
                " (the mode shapes chose this point over them)"
            } else if shape_scores.len() > 1 {
                " (the mode shapes agree with this point)"
            } else {
                " (no measured mode shape to choose)"
            },
        )
    };
    let skipped = if shapes.skipped > 0 {
        format!(
            " {} of {} measured shapes were left out of the shape choice (lists of unequal length, or scan points the model cannot evaluate).",
            shapes.skipped,
            shapes.skipped + shapes.used
        )
    } else {
        String::new()
    };
    let sentence = if located {
        format!(
            "A point mass of {:.3} ± {:.3} g at ({:.0}, {:.0}) mm (90 % region radius {:.0} mm) explains {:.0} % of the free-free misfit that the board parameters cannot{alt}.{skipped}",
            fit.mass_kg * 1e3,
            fit.mass_se_kg * 1e3,
            fit.x_m * 1e3,
            fit.y_m * 1e3,
            fit.region_radius_m * 1e3,
            100.0 * fit.explained_share
        )
    } else {
        format!(
            "No point mass explains the free-free misfit: the best, {:.3} g at ({:.0}, {:.0}) mm, explains {:.0} % of it (p = {:.2e}); not located.",
            fit.mass_kg * 1e3,
            fit.x_m * 1e3,
            fit.y_m * 1e3,
            100.0 * fit.explained_share,
            fit.p_value
        )
    };
    Ok(BoardRegion {
        mechanism: Mechanism::AddedMass,
        located,
        fit,
        shape_scores,
        chosen_by_shapes,
        shapes_used: shapes.used,
        shapes_skipped: shapes.skipped,
        sentence,
    })
}

/// What [`shape_choice`] found.
struct ShapeChoice {
    /// (x_m, y_m, score) of the best point and each alternative; empty without shapes.
    scores: Vec<[f64; 3]>,
    used: usize,
    skipped: usize,
}

/// [`shape_score`] of the best point and each alternative over the measured free-free shapes
/// of the accepted pairs of the labels in `label_index` (label → model mode index).
fn shape_choice(
    model: &FeModel,
    (modes, rigid): (&crate::fem::Modes, &faer::Mat<f64>),
    modes_path: &Path,
    pairs: &[PairObs],
    label_index: &[(String, usize)],
    fit: &PointMassFit,
) -> anyhow::Result<ShapeChoice> {
    use std::collections::BTreeMap;
    let mut skipped = 0;
    let mut wanted: BTreeMap<(String, i32), usize> = BTreeMap::new();
    for p in pairs.iter().filter(|p| p.setup == "free" && p.accepted) {
        if let (Some(m), Some((_, j))) = (p.mode, label_index.iter().find(|(l, _)| *l == p.label)) {
            wanted.insert((p.measurement_id.clone(), m), *j);
        }
    }
    // Measured shapes with their points, by measurement.
    // Per measurement: (model mode index, measured shape, its points).
    type Measured = (usize, Vec<f64>, Vec<[f64; 2]>);
    let mut by_meas: BTreeMap<String, Vec<Measured>> = BTreeMap::new();
    for b in
        read_parquet(modes_path).with_context(|| format!("reading {}", modes_path.display()))?
    {
        let c = Cols {
            batch: &b,
            path: modes_path,
        };
        let (mid, mode) = (c.str("measurement_id")?, c.i32("mode")?);
        for i in 0..b.num_rows() {
            let Some(&j) = wanted.get(&(mid.value(i).to_string(), mode.value(i))) else {
                continue;
            };
            let s = c.list_f64("shape", i)?.unwrap_or_default();
            let x = c.list_f64("x_m", i)?.unwrap_or_default();
            let y = c.list_f64("y_m", i)?.unwrap_or_default();
            if s.len() != x.len() || s.len() != y.len() || s.is_empty() {
                skipped += 1;
                continue;
            }
            let pts = x.iter().zip(&y).map(|(a, b)| [*a, *b]).collect();
            by_meas
                .entry(mid.value(i).to_string())
                .or_default()
                .push((j, s, pts));
        }
    }
    let cands: Vec<[f64; 2]> = std::iter::once([fit.x_m, fit.y_m])
        .chain(fit.alternatives.iter().map(|a| [a[0], a[1]]))
        .collect();
    let none = |skipped| ShapeChoice {
        scores: vec![],
        used: 0,
        skipped,
    };
    if cands.len() < 2 || by_meas.is_empty() {
        return Ok(none(skipped));
    }
    let at_c = model.shape_operator(&cands)?;
    let el_c = at_c.apply(modes.shapes.as_ref());
    let rig_c = at_c.apply(rigid.as_ref());
    let lam = &modes.eigenvalues;
    let mut obs: Vec<Vec<ShapeObs>> = vec![vec![]; cands.len()];
    for shapes in by_meas.values() {
        for (j, psi, pts) in shapes {
            // Scan points the model cannot evaluate (in a hole, off the board) leave the
            // measurement's shape out.
            let Ok(op) = model.shape_operator(pts) else {
                skipped += 1;
                continue;
            };
            let el = op.apply(modes.shapes.as_ref());
            let rig = op.apply(rigid.as_ref());
            let n = pts.len();
            for (ci, o) in obs.iter_mut().enumerate() {
                let phi_j_c = el_c[(ci, *j)];
                let mut d = vec![0.0; n];
                for k in (0..lam.len()).filter(|k| k != j) {
                    let coef = -lam[*j] * el_c[(ci, k)] * phi_j_c / (lam[*j] - lam[k]);
                    d.iter_mut()
                        .enumerate()
                        .for_each(|(i, v)| *v += coef * el[(i, k)]);
                }
                for r in 0..rig.ncols() {
                    let coef = -rig_c[(ci, r)] * phi_j_c;
                    d.iter_mut()
                        .enumerate()
                        .for_each(|(i, v)| *v += coef * rig[(i, r)]);
                }
                o.push(ShapeObs {
                    measured: psi.clone(),
                    model: (0..n).map(|i| el[(i, *j)]).collect(),
                    d_model_per_kg: d,
                });
            }
        }
    }
    if obs[0].is_empty() {
        return Ok(none(skipped));
    }
    Ok(ShapeChoice {
        used: obs[0].len(),
        skipped,
        scores: cands
            .iter()
            .zip(&obs)
            .map(|(c, o)| [c[0], c[1], shape_score(o, fit.mass_kg)])
            .collect(),
    })
}

/// Median over every row of `boards.parquet` of each parameter column.
fn posterior_centre(path: &Path, params: &[String]) -> anyhow::Result<Vec<f64>> {
    let mut cols: Vec<Vec<f64>> = vec![vec![]; params.len()];
    for b in read_parquet(path).with_context(|| format!("reading {}", path.display()))? {
        let c = Cols { batch: &b, path };
        for (k, name) in params.iter().enumerate() {
            cols[k].extend(c.f64(name)?.iter().flatten());
        }
    }
    cols.into_iter()
        .zip(params)
        .map(|(mut v, name)| {
            v.retain(|x| x.is_finite());
            if v.is_empty() {
                return Err(anyhow!("{}: no finite {name}", path.display()));
            }
            v.sort_by(f64::total_cmp);
            let n = v.len();
            Ok(if n % 2 == 1 {
                v[n / 2]
            } else {
                0.5 * (v[n / 2 - 1] + v[n / 2])
            })
        })
        .collect()
}

/// Grid points over the board at [`GRID_STEP_M`], none inside a hole (nor within a grid step
/// of its edge, where the clamp or the drill sits).
fn grid(board: &Board) -> Vec<[f64; 2]> {
    let nx = (board.length_x_m / GRID_STEP_M).round() as usize;
    let ny = (board.width_y_m / GRID_STEP_M).round() as usize;
    let mut out = vec![];
    for i in 0..=nx {
        for k in 0..=ny {
            let x = board.length_x_m * i as f64 / nx as f64;
            let y = board.width_y_m * k as f64 / ny as f64;
            if board
                .holes
                .iter()
                .all(|h| (x - h.x_m).hypot(y - h.y_m) > 0.5 * h.diameter_m + GRID_STEP_M)
            {
                out.push([x, y]);
            }
        }
    }
    out
}

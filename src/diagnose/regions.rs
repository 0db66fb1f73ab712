//! Where on the board: the localisations of the free-free misfit ([`crate::diagnose::localize`])
//! over the board, with the work directory's tables read through [`RegionFiles`].
//!
//! The free-free model is built from the board file at the step-1 posterior centre (the
//! median over all boards' draws of every updated parameter, `update_boards/boards.parquet`);
//! its modes give the point-mass signature −½ φ_j² and a core stiffness change's
//! ½ E_jj/λ_j ([`stiffness_region`]) on a grid over the board (holes left out)
//! and, by finite differences of 1 % in each updated parameter, the sensitivities the
//! localisation projects off. Labels are matched to model modes by the nearest frequency to
//! their mean model frequency in the step-1 residuals. The frequencies cannot tell the mirror
//! images of a point apart on a near-symmetric board; the measured mode shapes
//! (`extract/modes.parquet`, the accepted free-free pairs) choose among the best point and
//! its alternatives by [`shape_score`].

use anyhow::anyhow;

use crate::diagnose::library::Mechanism;
use crate::diagnose::localize::{
    localize_point_mass, localize_point_mass_at, shape_score, weighted_sd, LocalFit, LocalizeInput,
    ModalBasis, ModeResidual, ShapeObs, CHI2_2_Q90, CHI2_2_Q999,
};
use crate::diagnose::locate::{LocateOptions, ModeCheck, PairObs, ResidualObs};
use crate::fem::eigen::EigenOptions;
use crate::fem::params::names;
use crate::fem::{Board, FeModel, Setup};
use std::collections::BTreeMap;

/// Grid cells along the board's shorter side for the candidate points: 25 (2 mm on a 50 mm
/// board). The shortest bending half-wave of the first eight or so modes a free-free test
/// identifies spans about a quarter of the shorter side whatever the board's size, so the
/// step is a tenth of it; it follows the board rather than being a length.
pub const GRID_CELLS_SHORT_SIDE: f64 = 25.0;

/// Grid step of the candidate points on `board`, m ([`GRID_CELLS_SHORT_SIDE`]).
pub fn grid_step_m(board: &Board) -> f64 {
    board.length_x_m.min(board.width_y_m) / GRID_CELLS_SHORT_SIDE
}

/// Alternatives closer than this to the best point are the same region, m: five grid steps
/// (10 mm on a 50 mm board, the distance within which a located region counts as found).
pub fn min_separation_m(board: &Board) -> f64 {
    5.0 * grid_step_m(board)
}

/// A point-mass fit is reported as located when its Δχ² is significant at the locate step's
/// FDR level and it explains at least this share of the free-free misfit off the parameters'
/// span: a mechanism is named as the location of a misfit only when it accounts for most of
/// it.
pub const MIN_EXPLAINED_SHARE: f64 = 0.5;

/// The rule of a located region: significant at the locate step's FDR level, and explaining
/// at least [`MIN_EXPLAINED_SHARE`] of the misfit.
fn passes_rule(fit: &LocalFit, locate: &LocateOptions) -> bool {
    fit.p_value < locate.fdr && fit.explained_share >= MIN_EXPLAINED_SHARE
}

/// One located (or examined) board region.
#[derive(Clone, Debug, serde::Serialize, schemars::JsonSchema)]
pub struct BoardRegion {
    /// The mechanism whose signature was fitted: `added_mass` (a point mass) or
    /// `local_stiffness_loss` (a change of the core's bending stiffness over a small disc,
    /// either sign: a negative amplitude is a loss, a positive one a stiffening, which the
    /// library has no mechanism for).
    pub mechanism: Mechanism,
    /// The unit of `fit.amplitude`: `kg` (a point mass) or `factor - 1` (the core bending
    /// stiffness over the disc of [`STIFFNESS_RADIUS_M`]).
    pub amplitude_unit: String,
    /// Whether the fit passes the rule (significant, and explains at least half the misfit).
    pub located: bool,
    pub fit: LocalFit,
    /// The mode-shape score of each candidate point (x_m, y_m, score; [`shape_score`],
    /// larger is better): the best point of the frequencies, its alternatives, and the point
    /// the shapes chose in the frequencies' region when it is none of those. Empty when no
    /// measured shape could be used.
    pub shape_scores: Vec<[f64; 3]>,
    /// The shapes chose another point than the frequencies' best (which became an
    /// alternative; the fit is the chosen point's).
    pub chosen_by_shapes: bool,
    /// Measured shapes used by the shape choice, and those left out (lists of unequal
    /// length, scan points the model cannot evaluate).
    pub shapes_used: usize,
    pub shapes_skipped: usize,
    /// The frequencies' Δχ² plus the shapes' at the located point, the sum the point was
    /// chosen by (`None` where the updating had no shape terms, and the shapes only chose
    /// among alternatives); what ranks two signatures of the same misfit. Not written out.
    #[serde(skip)]
    pub combined_delta_chi2: Option<f64>,
    pub sentence: String,
}

#[cfg(test)]
impl BoardRegion {
    /// A located region of `fit` with no shape scores (tests' fixture).
    pub fn located_fit(mechanism: Mechanism, fit: LocalFit, sentence: &str) -> Self {
        BoardRegion {
            mechanism,
            amplitude_unit: String::new(),
            located: true,
            fit,
            shape_scores: vec![],
            chosen_by_shapes: false,
            shapes_used: 0,
            shapes_skipped: 0,
            combined_delta_chi2: None,
            sentence: sentence.into(),
        }
    }
}

/// What the localisations read: the work directory's tables (step-1 posterior, measured
/// shapes; [`RegionFiles`]), the board, the updated parameters, locate's mode checks (the free-free ones are localised),
/// each label's mean model frequency in the step-1 residuals, locate's options and the pairs.
pub struct RegionInput<'a> {
    pub files: &'a dyn RegionFiles,
    pub board: &'a Board,
    pub params: &'a [String],
    pub checks: &'a [ModeCheck],
    pub residual_model_freq: &'a [(String, f64)],
    pub locate: &'a LocateOptions,
    pub pairs: &'a [PairObs],
}

/// The work directory's tables a localisation reads, each when it needs it (so a missing or
/// bad table fails the localisation that reads it, with its file named).
pub trait RegionFiles {
    /// Median over every row of `update_boards/boards.parquet` of each parameter column.
    fn posterior_centre(&self, params: &[String]) -> anyhow::Result<Vec<f64>>;
    /// Whether the campaign's balance weighed at least one board.
    fn weighed(&self) -> anyhow::Result<bool>;
    /// The updating's shape error δ per label of `label_index` (label → model mode index);
    /// `None` when the updating had no shape terms.
    fn shape_errors(&self, label_index: &[(String, usize)]) -> anyhow::Result<Option<Vec<f64>>>;
    /// The measured shapes (`extract/modes.parquet`) of the (measurement, mode) rows that
    /// `wanted` accepts, in file order.
    fn measured_shapes(
        &self,
        wanted: &dyn Fn(&str, i32) -> bool,
    ) -> anyhow::Result<Vec<MeasuredShape>>;
}

/// One identified mode's measured shape and its scan points (lists as read; unequal lengths
/// are left out by the shape choice).
#[derive(Clone, Debug, Default)]
pub struct MeasuredShape {
    pub measurement_id: String,
    pub mode: i32,
    pub shape: Vec<f64>,
    pub x_m: Vec<f64>,
    pub y_m: Vec<f64>,
}

/// Each free-free label's mean model frequency over the residuals (what [`FreeBasis`] matches
/// model modes by).
pub fn free_model_freq(residuals: &[ResidualObs]) -> Vec<(String, f64)> {
    let mut freq: BTreeMap<String, (f64, usize)> = BTreeMap::new();
    for r in residuals.iter().filter(|r| r.setup == "free") {
        let e = freq.entry(r.label.clone()).or_insert((0.0, 0));
        e.0 += r.model_freq_hz_mean;
        e.1 += 1;
    }
    freq.into_iter()
        .map(|(l, (s, n))| (l, s / n as f64))
        .collect()
}

/// The free-free model at the step-1 posterior centre, its modes matched to the residuals'
/// labels, and the parameter sensitivities a localisation projects off: what the point-mass
/// and the stiffness localisations share.
pub struct FreeBasis {
    model: FeModel,
    modes0: crate::fem::Modes,
    rigid: faer::Mat<f64>,
    /// Per free-free label (the order of `free`), its model mode.
    index: Vec<usize>,
    free: Vec<ModeCheck>,
    /// Free-free labels left out: without a finite standard error (or mean) to weigh their
    /// mean residual by, as a mode paired in one measurement only (near the band's edge).
    pub left_out: Vec<String>,
    nuisance: Vec<Vec<f64>>,
    /// The boards were weighed and the mass scale followed the balance (not a nuisance).
    weighed: bool,
    board_mass_kg: f64,
    /// The candidate points ([`grid`]).
    points: Vec<[f64; 2]>,
}

impl FreeBasis {
    /// `Err` says why no localisation can run (no free-free residuals, a label without a
    /// model mode, a model that cannot be built).
    pub fn new(inp: &RegionInput) -> anyhow::Result<Self> {
        let RegionInput {
            files,
            board,
            params,
            checks,
            residual_model_freq,
            ..
        } = *inp;
        let (free, without_se): (Vec<ModeCheck>, Vec<ModeCheck>) = checks
            .iter()
            .filter(|c| c.setup == "free")
            .cloned()
            .partition(|c| {
                c.se_rel_residual.is_finite()
                    && c.se_rel_residual > 0.0
                    && c.mean_rel_residual.is_finite()
            });
        let left_out: Vec<String> = without_se.into_iter().map(|c| c.label).collect();
        if free.is_empty() {
            return Err(if left_out.is_empty() {
                anyhow!("no free-free mode residuals")
            } else {
                anyhow!(
                    "no free-free mode with a standard error (left out: {})",
                    left_out.join(", ")
                )
            });
        }
        let centre = files.posterior_centre(params)?;
        let model = FeModel::build(board, Setup::Free, &board.mesh)?;
        let mut p0 = model.nominal_params();
        for (name, v) in params.iter().zip(&centre) {
            p0.set(name, *v)?;
        }
        // The modes above the measured ones are the exact modal basis's (a point mass
        // couples every mode; 40 more than measured keep the truncation below the noise, see
        // `exact_localisation_matches_the_fe_model_with_the_point_mass`).
        let n_model = free.len() + 40;
        let (modes0, rigid) = model.modes_and_rigid(&p0, n_model, &EigenOptions::default())?;
        // Label → model mode by nearest frequency (each model mode used once).
        let mut taken = vec![false; modes0.freq_hz.len()];
        let mut index = vec![];
        for c in &free {
            let f = residual_model_freq
                .iter()
                .find(|(l, _)| *l == c.label)
                .map(|(_, f)| *f)
                .ok_or_else(|| {
                    anyhow!("label {:?}: no model frequency in the residuals", c.label)
                })?;
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
        // Where the boards were weighed and the updating fitted their mass scale to the
        // balance, the total mass is known: an added mass takes its share from the board's
        // own mass, so the mass scale is not a free direction of the residuals (which would
        // discard the absolute size of the shifts) but part of the signature (a point mass
        // minus the same mass spread uniformly). A stiffness change leaves the mass alone.
        let weighed = params.iter().any(|p| p == names::MASS_SCALE) && files.weighed()?;
        let board_mass_kg = model.total_mass_kg(&p0)?;
        // d ln f / d ln p of each labelled mode: first order and exact at the centre
        // (`fem::sensitivity`, one pass over the centre's modes), where five finite-difference
        // solves of 48 modes each took ~80 s on the shear-deformable default board.
        let d = crate::fem::sensitivity::eigen_derivatives(&model, &p0, &modes0, false)?;
        let nuisance: Vec<Vec<f64>> = params
            .iter()
            .filter(|name| !(weighed && *name == names::MASS_SCALE))
            .map(|name| -> anyhow::Result<Vec<f64>> {
                let k = p0
                    .names
                    .iter()
                    .position(|n| n == name)
                    .ok_or_else(|| anyhow!("parameter {name:?}: not a model parameter"))?;
                let v = p0.values[k];
                Ok(index
                    .iter()
                    .map(|&j| v * d.d_freq_hz[(j, k)] / modes0.freq_hz[j])
                    .collect())
            })
            .collect::<anyhow::Result<_>>()?;
        Ok(FreeBasis {
            model,
            modes0,
            rigid,
            index,
            free,
            left_out,
            nuisance,
            weighed,
            board_mass_kg,
            points: grid(board),
        })
    }

    fn residuals(&self) -> Vec<ModeResidual> {
        self.free
            .iter()
            .map(|c| ModeResidual {
                label: c.label.clone(),
                mean_rel: c.mean_rel_residual,
                se_rel: c.se_rel_residual,
            })
            .collect()
    }
}

/// The point-mass localisation over the free-free modes of `checks` (locate's mode checks).
/// `Err` says why it could not run (the stage writes it as the note).
pub fn point_mass_region(inp: &RegionInput, fb: &FreeBasis) -> anyhow::Result<BoardRegion> {
    let RegionInput { locate, .. } = *inp;
    let FreeBasis {
        model,
        modes0,
        rigid,
        index,
        nuisance,
        weighed,
        board_mass_kg,
        ..
    } = fb;
    let (weighed, board_mass_kg) = (*weighed, *board_mass_kg);
    let points = &fb.points;
    let w = model.w_at(modes0, points)?;
    let uniform = if weighed { 1.0 / board_mass_kg } else { 0.0 };
    let signature: Vec<Vec<f64>> = (0..points.len())
        .map(|i| {
            index
                .iter()
                .map(|&j| -0.5 * (w[(i, j)].powi(2) - uniform))
                .collect()
        })
        .collect();
    // The modal basis: rigid-body modes (λ = 0) first, then the elastic ones.
    let n_rig = rigid.ncols();
    let w_rig = model.shape_operator(points)?.apply(rigid.as_ref());
    let lambda: Vec<f64> = std::iter::repeat_n(0.0, n_rig)
        .chain(modes0.eigenvalues.iter().copied())
        .collect();
    let phi: Vec<Vec<f64>> = (0..points.len())
        .map(|i| {
            (0..n_rig)
                .map(|k| w_rig[(i, k)])
                .chain((0..modes0.eigenvalues.len()).map(|k| w[(i, k)]))
                .collect()
        })
        .collect();
    let observed: Vec<usize> = index.iter().map(|j| j + n_rig).collect();
    let modes = fb.residuals();
    let loc_in = LocalizeInput {
        modes: &modes,
        nuisance,
        points_m: points,
        signature: &signature,
        exact: Some(ModalBasis {
            lambda: &lambda,
            phi: &phi,
            observed: &observed,
            weighed_mass_kg: weighed.then_some(board_mass_kg),
        }),
        positive_only: true,
    };
    // The measured mode shapes join the frequencies.
    let (mut fit, d) = locate_and_decide(inp, fb, &loc_in, "point mass", &|_| Coupling::PointMass)?;
    let ShapeDecision {
        has_delta,
        ref open,
        ref combined,
        best_open,
        ..
    } = d;
    if let (true, Some(k), false) = (has_delta, best_open, d.shapes.scores.is_empty()) {
        // The region and the location's Occam factor of the combined map (the refit's
        // likelihood has both the frequencies and the shapes).
        let s2 = 2.0 * fit.inflation;
        let top = combined[k];
        let own: f64 = combined
            .iter()
            .map(|d| (-(top - d).max(0.0) / s2).exp())
            .sum();
        fit.log_location_occam = (own / points.len() as f64).ln().min(0.0);
        let wv: Vec<(f64, f64)> = open
            .iter()
            .zip(combined)
            .filter(|(&i, _)| fit.amplitude_at[i] > 0.0)
            .map(|(&i, d)| ((-(top - d).max(0.0) / s2).exp(), fit.amplitude_at[i].ln()))
            .collect();
        // The location's uncertainty within the chosen region is the frequencies' where
        // that is wider: the shape terms weigh every scan point as independent (n / δ²),
        // while a shape residual of model-form error is smooth over the board, so their Δχ²
        // overstates how well they place a point (the mass's interval came out too narrow).
        // The shapes still choose between regions (mirror images), which the frequencies
        // cannot.
        let freq_region = (fit.region_radius_m, fit.region_points);
        fit.location_ln_amplitude_sd = weighted_sd(&wv).max(fit.location_ln_amplitude_sd);
        combined_region(&mut fit, combined, k, open, points);
        // The region reported (radius and its points together) is the wider of the two.
        if freq_region.0 > fit.region_radius_m {
            (fit.region_radius_m, fit.region_points) = freq_region;
        }
    }
    fit.step_shift_rel = step_shift_rel(
        points,
        &signature,
        [fit.x_m, fit.y_m],
        grid_step_m(inp.board),
        fit.amplitude,
    );
    let located = passes_rule(&fit, locate);
    let alt = alternatives_clause(&fit, d.chosen_by_shapes, d.shape_scores.len());
    let skipped = if d.shapes.skipped > 0 {
        format!(
            " {} of {} measured shapes were left out of the shape choice (lists of unequal length, or scan points the model cannot evaluate).",
            d.shapes.skipped,
            d.shapes.skipped + d.shapes.used
        )
    } else {
        String::new()
    };
    let sentence = if located {
        format!(
            "A point mass of {:.3} ± {:.3} g at ({:.0}, {:.0}) mm (90 % region radius {:.0} mm) explains {:.0} % of the free-free misfit that the board parameters cannot{alt}.{skipped}",
            fit.amplitude * 1e3,
            fit.amplitude_se * 1e3,
            fit.x_m * 1e3,
            fit.y_m * 1e3,
            fit.region_radius_m * 1e3,
            100.0 * fit.explained_share
        )
    } else {
        format!(
            "No point mass explains the free-free misfit: the best, {:.3} g at ({:.0}, {:.0}) mm, explains {:.0} % of it (p = {:.2e}); not located.",
            fit.amplitude * 1e3,
            fit.x_m * 1e3,
            fit.y_m * 1e3,
            100.0 * fit.explained_share,
            fit.p_value
        )
    };
    Ok(d.region(Mechanism::AddedMass, "kg", located, fit, sentence))
}

/// [`LocalFit::step_shift_rel`] of a point mass `amplitude` kg at the grid point `at`:
/// `signature[i][j]` = ∂ ln f_j/∂m of a point mass at `points[i]`; the neighbours are the
/// grid points one `step` away along x or y (fewer beside a hole or an edge). 0 when `at` is
/// not a grid point.
fn step_shift_rel(
    points: &[[f64; 2]],
    signature: &[Vec<f64>],
    at: [f64; 2],
    step: f64,
    amplitude: f64,
) -> f64 {
    let dist = |p: &[f64; 2]| (p[0] - at[0]).hypot(p[1] - at[1]);
    let Some(i0) = points.iter().position(|p| dist(p) < 0.25 * step) else {
        return 0.0;
    };
    points
        .iter()
        .enumerate()
        .filter(|(_, p)| (dist(p) - step).abs() < 0.25 * step)
        .flat_map(|(i, _)| {
            signature[i]
                .iter()
                .zip(&signature[i0])
                .map(|(a, b)| (amplitude * (a - b)).abs())
        })
        .fold(0.0, f64::max)
}

/// Radius of the disc of a stiffness change's signature, m: a spot the size of a component's
/// footprint or a delamination (the signature varies over a bending half-wave, ≥ 15 mm on a
/// board of a few centimetres, so a disc up to a few mm wide has one signature).
pub const STIFFNESS_RADIUS_M: f64 = 4e-3;

/// The localisation of a local stiffness change from the free-free frequency residuals: at
/// every grid point, the first-order signature of a change of the core's bending stiffness
/// over a disc of [`STIFFNESS_RADIUS_M`] there, δ ln f_j = ½ (f − 1) E_jj / λ_j with E the
/// core's bending stiffness over the disc as a form on the modes
/// ([`FeModel::core_stiffness_form`]), fitted with either sign, the board parameters'
/// sensitivities projected off as for the point mass ([`localize_point_mass`]). The
/// frequencies alone cannot tell the mirror points of a near-symmetric board apart; the
/// measured shapes choose among them ([`decide_by_shapes`]).
pub fn stiffness_region(inp: &RegionInput, fb: &FreeBasis) -> anyhow::Result<BoardRegion> {
    let RegionInput { locate, .. } = *inp;
    let points = &fb.points;
    let cols = &fb.index;
    let shapes = faer::Mat::<f64>::from_fn(fb.modes0.shapes.nrows(), cols.len(), |r, c| {
        fb.modes0.shapes[(r, cols[c])]
    });
    let signature: Vec<Vec<f64>> = points
        .iter()
        .map(|p| {
            let e = fb
                .model
                .core_stiffness_form(p[0], p[1], STIFFNESS_RADIUS_M, shapes.as_ref());
            cols.iter()
                .enumerate()
                .map(|(k, &j)| 0.5 * e[(k, k)] / fb.modes0.eigenvalues[j])
                .collect()
        })
        .collect();
    let modes = fb.residuals();
    let loc_in = LocalizeInput {
        modes: &modes,
        nuisance: &fb.nuisance,
        points_m: points,
        signature: &signature,
        exact: None,
        positive_only: false,
    };
    // The measured mode shapes join the frequencies, as for the point mass.
    let (mut fit, d) = locate_and_decide(inp, fb, &loc_in, "stiffness change", &|open| {
        Coupling::Stiffness(
            open.iter()
                .map(|&i| {
                    fb.model.core_stiffness_form(
                        points[i][0],
                        points[i][1],
                        STIFFNESS_RADIUS_M,
                        fb.modes0.shapes.as_ref(),
                    )
                })
                .collect(),
        )
    })?;
    if let (true, Some(k)) = (d.has_delta, d.best_open) {
        combined_region(&mut fit, &d.combined, k, &d.open, points);
    }
    let located = passes_rule(&fit, locate);
    let kind = if fit.amplitude > 0.0 {
        "stiffening"
    } else {
        "loss"
    };
    let area_mm2 = std::f64::consts::PI * (STIFFNESS_RADIUS_M * 1e3).powi(2);
    let alt = alternatives_clause(&fit, d.chosen_by_shapes, d.shape_scores.len());
    let sentence = if located {
        format!(
            "A local {kind} of the board's bending stiffness at ({:.0}, {:.0}) mm (90 % region {}): the core's bending stiffness × {:.2} ± {:.2} over a {:.0} mm disc (or as much over another small area: (f − 1) × area = {:+.0} mm²) explains {:.0} % of the free-free misfit that the board parameters cannot{alt}.",
            fit.x_m * 1e3,
            fit.y_m * 1e3,
            if fit.region_radius_m > 0.0 {
                format!("radius {:.0} mm", fit.region_radius_m * 1e3)
            } else {
                format!("within the {:.0} mm grid step", grid_step_m(inp.board) * 1e3)
            },
            1.0 + fit.amplitude,
            fit.amplitude_se,
            2.0 * STIFFNESS_RADIUS_M * 1e3,
            fit.amplitude * area_mm2,
            100.0 * fit.explained_share
        ) + if fit.amplitude > 0.0 {
            " The library has no mechanism that stiffens the board locally (an underfilled or potted component, a stiffener, a thicker laminate there): the location and the size are the signature to act on."
        } else {
            ""
        }
    } else {
        format!(
            "No local stiffness change explains the free-free misfit: the best, a {kind} (core bending stiffness × {:.2} over a {:.0} mm disc) at ({:.0}, {:.0}) mm, explains {:.0} % of it (p = {:.2e}); not located.",
            1.0 + fit.amplitude,
            2.0 * STIFFNESS_RADIUS_M * 1e3,
            fit.x_m * 1e3,
            fit.y_m * 1e3,
            100.0 * fit.explained_share,
            fit.p_value
        )
    };
    Ok(d.region(
        Mechanism::LocalStiffnessLoss,
        "factor - 1",
        located,
        fit,
        sentence,
    ))
}

/// A localisation over `fb`'s grid ([`localize_point_mass`]; `what` names the change in the
/// error when nothing fits), then the measured shapes' decision ([`decide_by_shapes`]): the
/// fit at the point they chose (the frequencies' best when they chose none) and the decision.
fn locate_and_decide(
    inp: &RegionInput,
    fb: &FreeBasis,
    loc_in: &LocalizeInput,
    what: &str,
    coupling: &dyn Fn(&[usize]) -> Coupling,
) -> anyhow::Result<(LocalFit, ShapeDecision)> {
    let fit = localize_point_mass(loc_in, min_separation_m(inp.board)).ok_or_else(|| {
        anyhow!(
            "no {what} fits the free-free residuals ({} modes, {} parameters)",
            loc_in.modes.len(),
            inp.params.len()
        )
    })?;
    let mut d = decide_by_shapes(inp, fb, loc_in, &fit, coupling)?;
    let fit = d.fit.take().unwrap_or(fit);
    Ok((fit, d))
}

/// What the measured shapes decided for a localisation ([`decide_by_shapes`]).
struct ShapeDecision {
    /// The fit at the point the shapes chose, when it is not the frequencies' best.
    fit: Option<LocalFit>,
    chosen_by_shapes: bool,
    /// The shape scores of the frequencies' best point, its alternatives and the chosen
    /// point.
    shape_scores: Vec<[f64; 3]>,
    shapes: ShapeChoice,
    /// The updating had shape terms (the shapes' Δχ² joins the frequencies').
    has_delta: bool,
    open: Vec<usize>,
    combined: Vec<f64>,
    best_open: Option<usize>,
}

impl ShapeDecision {
    /// The board region of a localisation decided so: `fit` at the chosen point, `located` by
    /// the rule, with its sentence.
    fn region(
        self,
        mechanism: Mechanism,
        amplitude_unit: &str,
        located: bool,
        fit: LocalFit,
        sentence: String,
    ) -> BoardRegion {
        // The combined map's Δχ² at the chosen point, where the shapes had terms of their own.
        let combined_delta_chi2 = self
            .best_open
            .filter(|_| self.has_delta && !self.shapes.scores.is_empty())
            .map(|k| self.combined[k]);
        BoardRegion {
            mechanism,
            amplitude_unit: amplitude_unit.into(),
            located,
            fit,
            shape_scores: self.shape_scores,
            chosen_by_shapes: self.chosen_by_shapes,
            shapes_used: self.shapes.used,
            shapes_skipped: self.shapes.skipped,
            combined_delta_chi2,
            sentence,
        }
    }
}

/// The measured mode shapes join a localisation's frequencies: over the points the
/// frequencies leave open (their 99.9 % region), the first-order Δχ² of the updating's shape
/// terms (weights n / δ², δ its posterior shape error per mode) adds to the frequencies'
/// Δχ², and the best of the sum is the located point. Where the updating had no shape terms
/// (no δ), the shapes only choose among the frequencies' best point and its alternatives.
/// `coupling` gives the change's coupling of the modes at the open points.
fn decide_by_shapes(
    inp: &RegionInput,
    fb: &FreeBasis,
    loc_in: &LocalizeInput,
    fit: &LocalFit,
    coupling: &dyn Fn(&[usize]) -> Coupling,
) -> anyhow::Result<ShapeDecision> {
    let label_index: Vec<(String, usize)> = fb
        .free
        .iter()
        .zip(&fb.index)
        .map(|(c, &j)| (c.label.clone(), j))
        .collect();
    let delta = inp.files.shape_errors(&label_index)?;
    let has_delta = delta.is_some();
    let points = loc_in.points_m;
    let open = open_points(fit, has_delta, points);
    let shapes = shape_choice(
        &fb.model,
        (&fb.modes0, &fb.rigid),
        (inp.files, inp.pairs),
        &label_index,
        delta.as_ref(),
        (&open, points, &fit.amplitude_at),
        coupling(&open),
    )?;
    let (combined, best_open) = combined_scores(fit, has_delta, &open, &shapes);
    let chosen = best_open
        .map(|k| open[k])
        .filter(|&i| points[i] != [fit.x_m, fit.y_m])
        .and_then(|i| localize_point_mass_at(loc_in, min_separation_m(inp.board), Some(i)));
    let shape_scores: Vec<[f64; 3]> = std::iter::once([fit.x_m, fit.y_m])
        .chain(fit.alternatives.iter().map(|a| [a[0], a[1]]))
        .chain(best_open.map(|k| points[open[k]]))
        .filter_map(|p| shapes.scores.iter().find(|s| [s[0], s[1]] == p).copied())
        .fold(vec![], |mut v, sc| {
            if !v.contains(&sc) {
                v.push(sc);
            }
            v
        });
    Ok(ShapeDecision {
        chosen_by_shapes: chosen.is_some(),
        fit: chosen,
        shape_scores,
        shapes,
        has_delta,
        open,
        combined,
        best_open,
    })
}

/// "; the frequencies fit about as well at …" with what the shapes said, or nothing without
/// alternatives.
fn alternatives_clause(fit: &LocalFit, chosen_by_shapes: bool, n_scores: usize) -> String {
    if fit.alternatives.is_empty() {
        return String::new();
    }
    format!(
        "; the frequencies fit about as well at {}{}",
        fit.alternatives
            .iter()
            .map(|a| format!("({:.0}, {:.0}) mm", a[0] * 1e3, a[1] * 1e3))
            .collect::<Vec<_>>()
            .join(", "),
        if chosen_by_shapes {
            " (the mode shapes chose this point over them)"
        } else if n_scores > 1 {
            " (the mode shapes agree with this point)"
        } else {
            " (no measured mode shape to choose)"
        }
    )
}

/// The 90 % region of the combined (frequencies and shapes) map around the open point `k`:
/// its radius and number of points.
fn combined_region(
    fit: &mut LocalFit,
    combined: &[f64],
    k: usize,
    open: &[usize],
    points: &[[f64; 2]],
) {
    let c = points[open[k]];
    let top = combined[k];
    let region: Vec<usize> = (0..open.len())
        .filter(|&m| top - combined[m] <= CHI2_2_Q90 * fit.inflation)
        .collect();
    fit.region_radius_m = region
        .iter()
        .map(|&m| (points[open[m]][0] - c[0]).hypot(points[open[m]][1] - c[1]))
        .fold(0.0, f64::max);
    fit.region_points = region.len();
}

/// The points the measured shapes choose among: with the updating's shape errors (`delta`),
/// every point in the frequencies' 99.9 % region; without, the best point and its
/// alternatives.
fn open_points(fit: &LocalFit, has_delta: bool, points: &[[f64; 2]]) -> Vec<usize> {
    let d_best = fit.delta_chi2.iter().copied().fold(0.0, f64::max);
    if has_delta {
        (0..points.len())
            .filter(|&i| {
                fit.delta_chi2[i] > 0.0 && d_best - fit.delta_chi2[i] <= CHI2_2_Q999 * fit.inflation
            })
            .collect()
    } else {
        std::iter::once([fit.x_m, fit.y_m])
            .chain(fit.alternatives.iter().map(|a| [a[0], a[1]]))
            .filter_map(|c| points.iter().position(|p| *p == c))
            .collect()
    }
}

/// Per open point, the frequencies' Δχ² plus the shapes' (with shape errors) or the shape
/// score alone (without), and the open point where it is largest (`None` without shapes).
fn combined_scores(
    fit: &LocalFit,
    has_delta: bool,
    open: &[usize],
    shapes: &ShapeChoice,
) -> (Vec<f64>, Option<usize>) {
    let combined: Vec<f64> = open
        .iter()
        .zip(&shapes.scores)
        .map(|(&i, sc)| {
            if has_delta {
                fit.delta_chi2[i] + sc[2]
            } else {
                sc[2]
            }
        })
        .collect();
    let best = combined
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1))
        .map(|(k, _)| k)
        .filter(|_| !shapes.scores.is_empty());
    (combined, best)
}

/// What [`shape_choice`] found.
struct ShapeChoice {
    /// (x_m, y_m, score) of the best point and each alternative; empty without shapes.
    scores: Vec<[f64; 3]>,
    used: usize,
    skipped: usize,
}

/// [`shape_score`] of the points `open` (indices into `points`, each with its fitted mass
/// from `mass_at`) over the measured free-free shapes of the accepted pairs of the labels in
/// `label_index` (label → model mode index), each shape weighted by n / δ² of its label
/// (`delta`) or by 1 (`None`).
/// How a local change at a candidate point couples the modes, to first order: the change of
/// mode j's shape per unit amplitude is Σ_k c_k φ_k over the elastic modes plus Σ_r c_r ρ_r
/// over the rigid-body modes.
enum Coupling {
    /// A point mass (per kg): c_k = −λ_j φ_k(p) φ_j(p) / (λ_j − λ_k), c_r = −ρ_r(p) φ_j(p).
    PointMass,
    /// A stiffness change with the form E (per open point, over the elastic modes;
    /// [`FeModel::core_stiffness_form`]) per unit amplitude: c_k = E_kj / (λ_j − λ_k); a
    /// stiffness change does not strain the rigid-body modes (c_r = 0).
    Stiffness(Vec<faer::Mat<f64>>),
}

fn shape_choice(
    model: &FeModel,
    (modes, rigid): (&crate::fem::Modes, &faer::Mat<f64>),
    (files, pairs): (&dyn RegionFiles, &[PairObs]),
    label_index: &[(String, usize)],
    delta: Option<&Vec<f64>>,
    (open, points, mass_at): (&[usize], &[[f64; 2]], &[f64]),
    coupling: Coupling,
) -> anyhow::Result<ShapeChoice> {
    use std::collections::BTreeMap;
    let mut skipped = 0;
    // (measurement, mode) → (model mode index, the shape's weight per scan point).
    let mut wanted: BTreeMap<(String, i32), (usize, f64)> = BTreeMap::new();
    for p in pairs.iter().filter(|p| p.setup == "free" && p.accepted) {
        let Some(k) = label_index.iter().position(|(l, _)| *l == p.label) else {
            continue;
        };
        if let Some(m) = p.mode {
            let w = delta.map_or(1.0, |d| 1.0 / (d[k] * d[k]));
            wanted.insert((p.measurement_id.clone(), m), (label_index[k].1, w));
        }
    }
    // Measured shapes with their points, by measurement.
    // Per measurement: (model mode index, measured shape, its points).
    type Measured = (usize, f64, Vec<f64>, Vec<[f64; 2]>);
    let mut by_meas: BTreeMap<String, Vec<Measured>> = BTreeMap::new();
    let measured = files
        .measured_shapes(&|mid: &str, mode: i32| wanted.contains_key(&(mid.to_string(), mode)))?;
    for m in measured {
        let Some(&(j, w)) = wanted.get(&(m.measurement_id.clone(), m.mode)) else {
            continue;
        };
        let (s, x, y) = (m.shape, m.x_m, m.y_m);
        if s.len() != x.len() || s.len() != y.len() || s.is_empty() {
            skipped += 1;
            continue;
        }
        let pts = x.iter().zip(&y).map(|(a, b)| [*a, *b]).collect();
        by_meas
            .entry(m.measurement_id)
            .or_default()
            .push((j, w, s, pts));
    }
    let cands: Vec<[f64; 2]> = open.iter().map(|&i| points[i]).collect();
    let none = |skipped| ShapeChoice {
        scores: vec![],
        used: 0,
        skipped,
    };
    if cands.is_empty() || by_meas.is_empty() {
        return Ok(none(skipped));
    }
    // Per measured shape: its model mode, weight, values, and the model's elastic and rigid
    // shapes at its scan points.
    struct Prepared {
        j: usize,
        weight: f64,
        psi: Vec<f64>,
        el: faer::Mat<f64>,
        rig: faer::Mat<f64>,
    }
    let mut prepared = vec![];
    for shapes in by_meas.values() {
        for (j, w, psi, pts) in shapes {
            // Scan points the model cannot evaluate (in a hole, off the board) leave the
            // measurement's shape out.
            let Ok(op) = model.shape_operator(pts) else {
                skipped += 1;
                continue;
            };
            prepared.push(Prepared {
                j: *j,
                weight: w * pts.len() as f64,
                psi: psi.clone(),
                el: op.apply(modes.shapes.as_ref()),
                rig: op.apply(rigid.as_ref()),
            });
        }
    }
    if prepared.is_empty() {
        return Ok(none(skipped));
    }
    let at_c = model.shape_operator(&cands)?;
    let el_c = at_c.apply(modes.shapes.as_ref());
    let rig_c = at_c.apply(rigid.as_ref());
    let lam = &modes.eigenvalues;
    use rayon::prelude::*;
    let scores: Vec<f64> = (0..cands.len())
        .into_par_iter()
        .map(|ci| {
            let mut total = 0.0;
            for p in &prepared {
                let (j, n) = (p.j, p.psi.len());
                let phi_j_c = el_c[(ci, j)];
                let mut d = vec![0.0; n];
                for k in (0..lam.len()).filter(|k| *k != j) {
                    let coef = match &coupling {
                        Coupling::PointMass => {
                            -lam[j] * el_c[(ci, k)] * phi_j_c / (lam[j] - lam[k])
                        }
                        Coupling::Stiffness(e) => e[ci][(k, j)] / (lam[j] - lam[k]),
                    };
                    d.iter_mut()
                        .enumerate()
                        .for_each(|(i, v)| *v += coef * p.el[(i, k)]);
                }
                if let Coupling::PointMass = coupling {
                    for r in 0..p.rig.ncols() {
                        let coef = -rig_c[(ci, r)] * phi_j_c;
                        d.iter_mut()
                            .enumerate()
                            .for_each(|(i, v)| *v += coef * p.rig[(i, r)]);
                    }
                }
                let o = ShapeObs {
                    measured: p.psi.clone(),
                    model: (0..n).map(|i| p.el[(i, j)]).collect(),
                    d_model_per_kg: d,
                    weight: p.weight,
                };
                total += shape_score(std::slice::from_ref(&o), mass_at[open[ci]]);
            }
            total
        })
        .collect();
    Ok(ShapeChoice {
        used: prepared.len(),
        skipped,
        scores: cands
            .iter()
            .zip(&scores)
            .map(|(c, sc)| [c[0], c[1], *sc])
            .collect(),
    })
}

/// Grid points over the board at [`grid_step_m`], none inside a hole (nor within a grid step
/// of its edge, where the clamp or the drill sits).
fn grid(board: &Board) -> Vec<[f64; 2]> {
    let step = grid_step_m(board);
    let nx = (board.length_x_m / step).round() as usize;
    let ny = (board.width_y_m / step).round() as usize;
    let mut out = vec![];
    for i in 0..=nx {
        for k in 0..=ny {
            let x = board.length_x_m * i as f64 / nx as f64;
            let y = board.width_y_m * k as f64 / ny as f64;
            if board
                .holes
                .iter()
                .all(|h| (x - h.x_m).hypot(y - h.y_m) > 0.5 * h.diameter_m + step)
            {
                out.push([x, y]);
            }
        }
    }
    out
}

/// Where several signatures located the same misfit, the weaker one is not located: the
/// same residuals, the same number of fitted quantities (an amplitude and two coordinates),
/// so the larger Δχ² is the likelier mechanism. Where the updating had shape terms, the Δχ²
/// is the frequencies' plus the shapes' at each located point (the sum each point was chosen
/// by, and the refit's likelihood has both): on a board whose few free-free modes leave
/// both signatures explaining 99 % of the frequency misfit, the shapes are what tells a
/// point mass from a soft spot. Without shape terms, the frequencies' explained share.
/// The weaker one's sentence says which one explains more, and by what.
pub fn demote_weaker_regions(regions: &mut [BoardRegion]) {
    let with_shapes = regions
        .iter()
        .filter(|r| r.located)
        .all(|r| r.combined_delta_chi2.is_some());
    let key = |r: &BoardRegion| {
        if with_shapes {
            r.combined_delta_chi2.unwrap_or(f64::NEG_INFINITY)
        } else {
            r.fit.explained_share
        }
    };
    let best = regions
        .iter()
        .enumerate()
        .filter(|(_, r)| r.located)
        .max_by(|a, b| key(a.1).total_cmp(&key(b.1)))
        .map(|(i, r)| (i, r.mechanism, key(r), r.fit.explained_share));
    let Some((bi, bm, bk, bs)) = best else {
        return;
    };
    for (i, r) in regions.iter_mut().enumerate() {
        if i != bi && r.located {
            r.located = false;
            let by = if with_shapes {
                format!(
                    "frequencies and mode shapes together, Δχ² {:.0} against {:.0}; of the frequencies alone {:.0} % against {:.0} %",
                    bk,
                    key(r),
                    100.0 * bs,
                    100.0 * r.fit.explained_share
                )
            } else {
                format!(
                    "{:.0} % against {:.0} %",
                    100.0 * bs,
                    100.0 * r.fit.explained_share
                )
            };
            r.sentence = format!(
                "{} Not located: the {} signature explains more of the misfit ({by}).",
                r.sentence,
                bm.id(),
            );
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::{demote_weaker_regions, BoardRegion};
    use crate::diagnose::library::Mechanism;
    use crate::diagnose::localize::LocalFit;

    /// A located region of `mechanism` explaining `share` of its modes' misfit, with the
    /// shapes' combined Δχ² `combined` (a fixture of the diagnosis's tests).
    pub(crate) fn region(mechanism: Mechanism, share: f64, combined: Option<f64>) -> BoardRegion {
        let fit = LocalFit {
            x_m: 0.05,
            y_m: 0.03,
            amplitude: 1.0,
            amplitude_se: 0.1,
            chi2_before: 100.0,
            chi2_after: 100.0 * (1.0 - share),
            dof_after: 2,
            explained_share: share,
            p_value: 1e-9,
            region_radius_m: 0.01,
            region_points: 10,
            log_location_occam: -1.0,
            inflation: 1.0,
            ..LocalFit::default()
        };
        BoardRegion {
            combined_delta_chi2: combined,
            ..BoardRegion::located_fit(mechanism, fit, "Fit.")
        }
    }

    /// A free-free mode seen in one measurement has no standard error: the localisations
    /// leave it out and say so, and run on the others (before, the mode failed both with "no
    /// point mass fits the free-free residuals").
    #[test]
    fn a_mode_seen_once_is_left_out_of_the_localisations_not_fatal_to_them() {
        use super::{point_mass_region, FreeBasis, MeasuredShape, RegionFiles, RegionInput};
        use crate::diagnose::locate::{LocateOptions, ModeCheck};
        use crate::fem::{FeModel, Setup};
        struct Nominal(FeModel);
        impl RegionFiles for Nominal {
            fn posterior_centre(&self, params: &[String]) -> anyhow::Result<Vec<f64>> {
                let p = self.0.nominal_params();
                params.iter().map(|n| Ok(p.get(n)?)).collect()
            }
            fn weighed(&self) -> anyhow::Result<bool> {
                Ok(false)
            }
            fn shape_errors(&self, _: &[(String, usize)]) -> anyhow::Result<Option<Vec<f64>>> {
                Ok(None)
            }
            fn measured_shapes(
                &self,
                _: &dyn Fn(&str, i32) -> bool,
            ) -> anyhow::Result<Vec<MeasuredShape>> {
                Ok(vec![])
            }
        }
        let board = crate::fem::tests::helpers::thin_board();
        let model = FeModel::build(&board, Setup::Free, &board.mesh).unwrap();
        let modes = model.modes(&model.nominal_params(), 8).unwrap();
        let labels: Vec<String> = (1..=8).map(|k| format!("mode-{k}")).collect();
        let freq: Vec<(String, f64)> = labels
            .iter()
            .cloned()
            .zip(modes.freq_hz.iter().copied())
            .collect();
        // A misfit in seven modes seen 35 times each, and the eighth seen once (se 0).
        let checks: Vec<ModeCheck> = labels
            .iter()
            .enumerate()
            .map(|(k, l)| ModeCheck {
                setup: "free".into(),
                label: l.clone(),
                n: if k == 7 { 1 } else { 35 },
                mean_rel_residual: 1e-3 * ((k as f64) - 3.5) / 3.5,
                se_rel_residual: if k == 7 { 0.0 } else { 5e-5 },
                ..ModeCheck::default()
            })
            .collect();
        let params: Vec<String> = ["e_x_pa", "e_y_pa", "g_xy_pa", "mass_scale"]
            .map(String::from)
            .to_vec();
        let files = Nominal(model);
        let opts = LocateOptions::default();
        let inp = RegionInput {
            files: &files,
            board: &board,
            params: &params,
            checks: &checks,
            residual_model_freq: &freq,
            locate: &opts,
            pairs: &[],
        };
        let fb = FreeBasis::new(&inp).unwrap();
        let r = point_mass_region(&inp, &fb);
        assert!(r.is_ok(), "{:?}", r.err());
        assert_eq!(fb.left_out, ["mode-8"]);
    }

    /// Two signatures that explain the frequencies alike: with shape terms the combined Δχ²
    /// decides (here against the frequencies' slightly larger share), without them the share.
    #[test]
    fn the_shapes_decide_between_signatures_the_frequencies_cannot_tell_apart() {
        let mut r = [
            region(Mechanism::AddedMass, 0.9913, Some(187_842.0)),
            region(Mechanism::LocalStiffnessLoss, 0.9926, Some(184_405.0)),
        ];
        demote_weaker_regions(&mut r);
        assert!(r[0].located && !r[1].located);
        assert!(r[1].sentence.contains("added_mass signature explains more"));
        assert!(r[1].sentence.contains("Δχ² 187842 against 184405"));

        let mut r = [
            region(Mechanism::AddedMass, 0.9913, None),
            region(Mechanism::LocalStiffnessLoss, 0.9926, None),
        ];
        demote_weaker_regions(&mut r);
        assert!(!r[0].located && r[1].located);
        assert!(r[0].sentence.contains("(99 % against 99 %)"));

        // A region that was not located is neither compared nor changed.
        let mut r = [
            region(Mechanism::AddedMass, 0.9, Some(10.0)),
            region(Mechanism::LocalStiffnessLoss, 0.4, Some(50.0)),
        ];
        r[1].located = false;
        demote_weaker_regions(&mut r);
        assert!(r[0].located && r[1].sentence == "Fit.");
    }
}

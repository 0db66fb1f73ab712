//! Pairing identified modes with model modes: MAC matrix, optimal one-to-one assignment,
//! acceptance thresholds, shape labels, swap and missing-mode reports, and the rule that
//! decides which modes count as present in every measurement of a setup.
//!
//! Labels come from the model shape at a grid of points (the pair stage labels each setup's
//! model once, on a grid over the whole board, [`pair_modes_labelled`]; [`pair_modes`] labels
//! at the measurement's scan points): points are grouped into rows
//! (same y) and columns (same x); along each row the sign changes of the shape are counted
//! (ignoring components below `label_amp_fraction` of the largest), giving `nx` nodal lines
//! crossed along x, and likewise `ny` along y (energy-weighted median over rows/columns).
//! `(1,1)` is `torsion-1`; `(k+1, 0)` is `bending-x-k` (bending along x, k-th); `(0, k+1)` is
//! `bending-y-k`; anything else is `plate-nx-ny`. Without a grid (fewer than two rows or
//! columns of 3 points), the label is `mode-<model index + 1>`.

use super::assign::hungarian_max;
use super::mac::mac_matrix;
use super::ModalError;
use crate::fem::{Board, FeModel, FemError, Modes, Setup};
use crate::findings::{Finding, Findings, Severity};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// A scan point in the board frame (m).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ScanPoint {
    pub node_id: i64,
    pub x_m: f64,
    pub y_m: f64,
    pub z_m: f64,
}

/// A model mode evaluated at the scan points.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModelMode {
    pub freq_hz: f64,
    /// Real shape at the scan points, same order as the identified shapes.
    pub shape: Vec<f64>,
}

/// Thresholds of the pairing.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PairParams {
    /// Minimum MAC for an accepted pair (default 0.8, a common engineering threshold for
    /// "same mode" between test and an un-updated model).
    pub mac_min: f64,
    /// Maximum relative frequency deviation `|f_id/f_model - 1|` of an accepted pair
    /// (default 0.5: generous, the model is not updated yet; the MAC decides).
    pub max_freq_deviation: f64,
    /// Components below this fraction of the largest |component| are ignored when counting
    /// sign changes for labels (default 0.1).
    pub label_amp_fraction: f64,
    /// Coordinates closer than this fraction of the point cloud's extent belong to the same
    /// row/column (default 0.02).
    pub grid_tol_fraction: f64,
    /// Frequency pairing ([`pair_modes_by_frequency`], for points too sparse for the MAC):
    /// the prior predictive sd of ln f of an un-updated model mode (default 0.05: f goes as
    /// √stiffness, and the updating's prior gives each modulus's population mean a 10 % sd,
    /// `update boards --prior-width`).
    pub freq_sd_rel: f64,
    /// A pair further apart than this many `freq_sd_rel` is not accepted (default 3).
    pub freq_gate_sd: f64,
    /// Visibility at which a mode is surely seen at the measured points: its largest amplitude
    /// there over its largest on the board (default 0.1: its peak then lies within 20 dB of
    /// what it shows elsewhere, as extract's `min_peak_share`). A less visible model mode may
    /// still show (a lightly damped peak rises ~1/(2ζ) over the response), so it stays a
    /// candidate at a log-likelihood penalty ln(v / min_visibility), and is not reported
    /// missing when no partner is found.
    pub min_visibility: f64,
}

impl Default for PairParams {
    fn default() -> Self {
        Self {
            mac_min: 0.8,
            max_freq_deviation: 0.5,
            label_amp_fraction: 0.1,
            grid_tol_fraction: 0.02,
            freq_sd_rel: 0.05,
            freq_gate_sd: 3.0,
            min_visibility: 0.1,
        }
    }
}

/// An identified mode to pair: frequency and real shape at the scan points (`NaN` allowed).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct IdentifiedShape {
    pub freq_hz: f64,
    pub shape: Vec<f64>,
}

/// The pairing of one identified mode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModePair {
    /// Index of the identified mode.
    pub mode: usize,
    /// Model mode it was assigned to (`None` if there are more identified than model modes).
    pub model_mode: Option<usize>,
    /// Label of the assigned model mode (empty if none).
    pub label: String,
    pub mac: f64,
    /// MAC and frequency thresholds both met.
    pub accepted: bool,
}

/// Result of [`pair_modes`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Pairing {
    /// `mac[identified][model]`.
    pub mac: Vec<Vec<f64>>,
    /// One entry per identified mode.
    pub pairs: Vec<ModePair>,
    /// Labels of all model modes.
    pub model_labels: Vec<String>,
    /// Model modes inside the identification band without an accepted pair.
    pub missing: Vec<usize>,
    /// Pairs of model modes `(a, b)`, `f_model(a) < f_model(b)`, whose accepted identified
    /// partners come in the opposite frequency order (mode swap).
    pub swaps: Vec<(usize, usize)>,
}

/// Group coordinates into lines: returns for each point the index of its group.
fn group_coords(vals: &[f64], tol: f64) -> Vec<usize> {
    let mut idx: Vec<usize> = (0..vals.len()).collect();
    idx.sort_by(|&a, &b| vals[a].total_cmp(&vals[b]));
    let mut group = vec![0usize; vals.len()];
    let mut g = 0usize;
    let mut start = f64::NAN;
    for (k, &i) in idx.iter().enumerate() {
        if k == 0 {
            start = vals[i];
        } else if vals[i] - start > tol {
            g += 1;
            start = vals[i];
        }
        group[i] = g;
    }
    group
}

/// Energy-weighted median of sign-change counts along lines (`along` is the coordinate
/// along the line, `line_of` the line index per point). `None` if fewer than two lines
/// have 3 points.
fn count_sign_changes(
    shape: &[f64],
    along: &[f64],
    line_of: &[usize],
    amp_min: f64,
) -> Option<usize> {
    let n_lines = line_of.iter().copied().max().map_or(0, |m| m + 1);
    let mut counts: Vec<(usize, f64)> = Vec::new();
    for l in 0..n_lines {
        let mut pts: Vec<usize> = (0..shape.len())
            .filter(|&i| line_of[i] == l && shape[i].is_finite())
            .collect();
        if pts.len() < 3 {
            continue;
        }
        pts.sort_by(|&a, &b| along[a].total_cmp(&along[b]));
        let energy: f64 = pts.iter().map(|&i| shape[i] * shape[i]).sum();
        let mut last_sign = 0.0f64;
        let mut changes = 0usize;
        for &i in &pts {
            if shape[i].abs() < amp_min {
                continue;
            }
            let s = shape[i].signum();
            if last_sign != 0.0 && s != last_sign {
                changes += 1;
            }
            last_sign = s;
        }
        counts.push((changes, energy));
    }
    if counts.len() < 2 {
        return None;
    }
    counts.sort_by_key(|c| c.0);
    let total: f64 = counts.iter().map(|c| c.1).sum();
    let mut acc = 0.0;
    for (c, e) in &counts {
        acc += e;
        if acc >= 0.5 * total {
            return Some(*c);
        }
    }
    counts.last().map(|c| c.0)
}

/// Nodal-line counts `(nx, ny)` of a real shape at the scan points, if they form a grid.
pub fn nodal_counts(
    shape: &[f64],
    points: &[ScanPoint],
    params: &PairParams,
) -> Option<(usize, usize)> {
    if shape.len() != points.len() || points.is_empty() {
        return None;
    }
    let xs: Vec<f64> = points.iter().map(|p| p.x_m).collect();
    let ys: Vec<f64> = points.iter().map(|p| p.y_m).collect();
    let ext = |v: &[f64]| {
        v.iter().cloned().fold(f64::NEG_INFINITY, f64::max)
            - v.iter().cloned().fold(f64::INFINITY, f64::min)
    };
    let tol = params.grid_tol_fraction * ext(&xs).max(ext(&ys));
    let rows = group_coords(&ys, tol);
    let cols = group_coords(&xs, tol);
    let amp = shape
        .iter()
        .filter(|v| v.is_finite())
        .fold(0.0f64, |a, v| a.max(v.abs()));
    if amp == 0.0 {
        return None;
    }
    let amp_min = params.label_amp_fraction * amp;
    let nx = count_sign_changes(shape, &xs, &rows, amp_min)?;
    let ny = count_sign_changes(shape, &ys, &cols, amp_min)?;
    Some((nx, ny))
}

/// Label of a shape from its nodal-line counts (see the module documentation).
pub fn label_shape(
    shape: &[f64],
    points: &[ScanPoint],
    index: usize,
    params: &PairParams,
) -> String {
    match nodal_counts(shape, points, params) {
        Some((1, 1)) => "torsion-1".to_string(),
        Some((nx, 0)) if nx >= 2 => format!("bending-x-{}", nx - 1),
        Some((0, ny)) if ny >= 2 => format!("bending-y-{}", ny - 1),
        Some((nx, ny)) => format!("plate-{nx}-{ny}"),
        None => format!("mode-{}", index + 1),
    }
}

/// Pair identified modes with model modes.
///
/// `band_hz` is the identification band: model modes inside it without an accepted partner
/// are reported missing. Errors if a shape's length differs from the number of points.
pub fn pair_modes(
    identified: &[IdentifiedShape],
    model: &[ModelMode],
    points: &[ScanPoint],
    band_hz: (f64, f64),
    params: &PairParams,
) -> Result<Pairing, ModalError> {
    for s in identified
        .iter()
        .map(|m| &m.shape)
        .chain(model.iter().map(|m| &m.shape))
    {
        if s.len() != points.len() {
            return Err(ModalError::ShapeLength {
                context: "pair_modes (shape vs scan points)",
                expected: points.len(),
                found: s.len(),
            });
        }
    }
    let model_labels = label_modes(model, points, params);
    pair_modes_labelled(identified, model, model_labels, band_hz, params)
}

/// Labels of model modes from their shapes at `points` ([`label_shape`]), made unique (a
/// second occurrence gets "#2", ...).
pub fn label_modes(model: &[ModelMode], points: &[ScanPoint], params: &PairParams) -> Vec<String> {
    let mut model_labels: Vec<String> = model
        .iter()
        .enumerate()
        .map(|(j, m)| label_shape(&m.shape, points, j, params))
        .collect();
    let mut seen: BTreeMap<String, usize> = BTreeMap::new();
    for l in model_labels.iter_mut() {
        let c = seen.entry(l.clone()).or_insert(0);
        *c += 1;
        if *c > 1 {
            *l = format!("{l}#{c}");
        }
    }
    model_labels
}

/// [`pair_modes`] with the model modes' labels given: e.g. labelled once per setup on a
/// grid over the whole board, so that a model mode keeps its label in every measurement,
/// whichever part of the board a measurement scanned (labels from a measurement's own scan
/// points can differ between scan grids for a mode whose nodal pattern is ambiguous).
pub fn pair_modes_labelled(
    identified: &[IdentifiedShape],
    model: &[ModelMode],
    model_labels: Vec<String>,
    band_hz: (f64, f64),
    params: &PairParams,
) -> Result<Pairing, ModalError> {
    if model_labels.len() != model.len() {
        return Err(ModalError::ShapeLength {
            context: "pair_modes_labelled (labels vs model modes)",
            expected: model.len(),
            found: model_labels.len(),
        });
    }
    if let Some(n) = model.first().map(|m| m.shape.len()) {
        for s in identified
            .iter()
            .map(|m| &m.shape)
            .chain(model.iter().map(|m| &m.shape))
        {
            if s.len() != n {
                return Err(ModalError::ShapeLength {
                    context: "pair_modes_labelled (identified vs model shapes)",
                    expected: n,
                    found: s.len(),
                });
            }
        }
    }
    let id_shapes: Vec<Vec<f64>> = identified.iter().map(|m| m.shape.clone()).collect();
    let mo_shapes: Vec<Vec<f64>> = model.iter().map(|m| m.shape.clone()).collect();
    let mac = mac_matrix(&id_shapes, &mo_shapes);
    let assignment = if model.is_empty() {
        vec![None; identified.len()]
    } else {
        hungarian_max(&mac)
    };
    let pairs: Vec<ModePair> = assignment
        .iter()
        .enumerate()
        .map(|(i, a)| match a {
            Some(j) => {
                let m = mac[i][*j];
                let dev = (identified[i].freq_hz / model[*j].freq_hz - 1.0).abs();
                ModePair {
                    mode: i,
                    model_mode: Some(*j),
                    label: model_labels[*j].clone(),
                    mac: m,
                    accepted: m >= params.mac_min && dev <= params.max_freq_deviation,
                }
            }
            None => ModePair {
                mode: i,
                model_mode: None,
                label: String::new(),
                mac: 0.0,
                accepted: false,
            },
        })
        .collect();
    let accepted_model = accepted_partners(&pairs, model.len());
    let missing = (0..model.len())
        .filter(|&j| {
            model[j].freq_hz >= band_hz.0
                && model[j].freq_hz <= band_hz.1
                && accepted_model[j].is_none()
        })
        .collect();
    let swaps = swaps_of(identified, model, &accepted_model);
    Ok(Pairing {
        mac,
        pairs,
        model_labels,
        missing,
        swaps,
    })
}

/// The largest MAC between two different model modes at the measured points, over the model
/// modes whose frequency lies in `band_hz` widened by the relative `margin` (the candidates of
/// a pairing). The points tell the model's modes apart by MAC only when this stays below the
/// pairing's `mac_min`; otherwise two model modes look alike there and the MAC cannot choose
/// (one point: every MAC is 1). 0 with fewer than two candidates.
pub fn model_mac_max(model: &[ModelMode], band_hz: (f64, f64), margin: f64) -> f64 {
    let near: Vec<Vec<f64>> = model
        .iter()
        .filter(|m| {
            m.freq_hz >= band_hz.0 * (1.0 - margin) && m.freq_hz <= band_hz.1 * (1.0 + margin)
        })
        .map(|m| m.shape.clone())
        .collect();
    let mac = mac_matrix(&near, &near);
    let mut worst = 0.0f64;
    for (a, row) in mac.iter().enumerate() {
        for (b, &v) in row.iter().enumerate() {
            if a != b && v.is_finite() {
                worst = worst.max(v);
            }
        }
    }
    worst
}

/// Pair identified modes with model modes by frequency and visibility, for scan points too
/// sparse for the MAC ([`model_mac_max`]). `visibility[j]` is model mode j's largest
/// |amplitude| at the measured points over its largest on the board.
///
/// A model mode is a candidate for an identified one when it moves at the points at all and its
/// frequency lies within `freq_gate_sd` prior predictive sds (`freq_sd_rel` in ln f). Among
/// candidates the assignment maximises, over all pairs at once, the prior predictive log
/// density of the frequency ratio plus the log probability that the mode is seen there,
/// ln min(1, v / `min_visibility`), where each identified mode may instead be none of the
/// model's (a mode the model lacks, or a spurious pole: a density uniform in ln f over the
/// identified modes' span). A common sd on ln f makes the optimal one-to-one assignment keep
/// the modes' order; a mode near a node of its shape at the points loses to one seen well;
/// an identified mode far from every candidate is left unpaired rather than forced, and one
/// forced pair never displaces a close one; a model mode in the band seen surely (v ≥ `min_visibility`) without a partner is
/// missing; a less visible one is not. Labels and the `Pairing` are those of
/// [`pair_modes_labelled`] (the MAC matrix still reported), so that later stages cannot tell
/// the difference.
pub fn pair_modes_by_frequency(
    identified: &[IdentifiedShape],
    model: &[ModelMode],
    model_labels: Vec<String>,
    visibility: &[f64],
    band_hz: (f64, f64),
    params: &PairParams,
) -> Result<Pairing, ModalError> {
    for (context, n) in [
        (
            "pair_modes_by_frequency (labels vs model modes)",
            model_labels.len(),
        ),
        (
            "pair_modes_by_frequency (visibility vs model modes)",
            visibility.len(),
        ),
    ] {
        if n != model.len() {
            return Err(ModalError::ShapeLength {
                context,
                expected: model.len(),
                found: n,
            });
        }
    }
    let id_shapes: Vec<Vec<f64>> = identified.iter().map(|m| m.shape.clone()).collect();
    let mo_shapes: Vec<Vec<f64>> = model.iter().map(|m| m.shape.clone()).collect();
    let mac = mac_matrix(&id_shapes, &mo_shapes);
    // Log-likelihood of "identified mode i is model mode j": the prior predictive density of
    // its ln f, times the probability that j is seen at the points.
    let ln_norm = (params.freq_sd_rel * (2.0 * std::f64::consts::PI).sqrt()).ln();
    let score = |i: usize, j: usize| -> Option<f64> {
        let z = (identified[i].freq_hz / model[j].freq_hz).ln() / params.freq_sd_rel;
        let seen = (visibility[j] / params.min_visibility).min(1.0);
        (z.is_finite() && z.abs() <= params.freq_gate_sd && seen > 0.0)
            .then(|| -0.5 * z * z - ln_norm + seen.ln())
    };
    // ... against "it is none of them" (a mode the model lacks, or a spurious one): a density
    // uniform in ln f over the span the identified modes occupy (at least the gate's width).
    let (lo, hi) = identified
        .iter()
        .map(|m| m.freq_hz)
        .filter(|f| f.is_finite() && *f > 0.0)
        .fold((f64::INFINITY, 0.0f64), |(a, b), f| (a.min(f), b.max(f)));
    let span = if hi > lo { (hi / lo).ln() } else { 0.0 };
    let unpaired = -span
        .max(2.0 * params.freq_gate_sd * params.freq_sd_rel)
        .ln();
    // Costs: every identified mode has its own "unpaired" column; a pair that is no candidate
    // costs more than any assignment of candidates, and is never taken.
    let (n, m) = (identified.len(), model.len());
    let forbidden = 1e6;
    let cost: Vec<Vec<f64>> = (0..n)
        .map(|i| {
            (0..m)
                .map(|j| score(i, j).map_or(forbidden, |s| -s))
                .chain((0..n).map(|k| if k == i { -unpaired } else { forbidden }))
                .collect()
        })
        .collect();
    let assignment: Vec<Option<usize>> = super::assign::hungarian_min(&cost)
        .into_iter()
        .map(|a| a.filter(|&j| j < m))
        .collect();
    let pairs: Vec<ModePair> = assignment
        .iter()
        .enumerate()
        .map(|(i, a)| {
            let accepted = a.is_some_and(|j| score(i, j).is_some());
            ModePair {
                mode: i,
                model_mode: *a,
                label: a.map_or(String::new(), |j| model_labels[j].clone()),
                mac: a.map_or(0.0, |j| mac[i][j]),
                accepted,
            }
        })
        .collect();
    let partner = accepted_partners(&pairs, model.len());
    let missing = (0..model.len())
        .filter(|&j| {
            model[j].freq_hz >= band_hz.0
                && model[j].freq_hz <= band_hz.1
                && visibility[j] >= params.min_visibility
                && partner[j].is_none()
        })
        .collect();
    let swaps = swaps_of(identified, model, &partner);
    Ok(Pairing {
        mac,
        pairs,
        model_labels,
        missing,
        swaps,
    })
}

/// Per model mode, the identified mode accepted as its partner.
fn accepted_partners(pairs: &[ModePair], n_model: usize) -> Vec<Option<usize>> {
    let mut v = vec![None; n_model];
    for p in pairs.iter().filter(|p| p.accepted) {
        if let Some(j) = p.model_mode {
            v[j] = Some(p.mode);
        }
    }
    v
}

/// Pairs of model modes `(a, b)`, `f(a) < f(b)`, whose accepted partners come in the
/// opposite frequency order.
fn swaps_of(
    identified: &[IdentifiedShape],
    model: &[ModelMode],
    partner: &[Option<usize>],
) -> Vec<(usize, usize)> {
    let mut swaps = Vec::new();
    for a in 0..model.len() {
        for b in 0..model.len() {
            if model[a].freq_hz < model[b].freq_hz {
                if let (Some(ia), Some(ib)) = (partner[a], partner[b]) {
                    if identified[ia].freq_hz > identified[ib].freq_hz {
                        swaps.push((a, b));
                    }
                }
            }
        }
    }
    swaps
}

/// Accepted mode labels of one measurement, for the presence rule.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PresenceRecord {
    pub measurement_id: String,
    pub setup: String,
    pub accepted_labels: Vec<String>,
}

/// Presence of one mode label within one setup.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LabelPresence {
    pub setup: String,
    pub label: String,
    /// Measurements of the setup in which the label was accepted.
    pub n_present: usize,
    pub n_measurements: usize,
    /// `n_present >= min_fraction * n_measurements`.
    pub used_for_updating: bool,
}

/// The paper's rule, made explicit: a mode counts for updating in a setup if it is accepted
/// in at least `min_fraction` of that setup's measurements (the paper: `1.0`, every
/// measurement; the remaining modes serve for validation). Sorted by setup, then label.
pub fn modes_present(records: &[PresenceRecord], min_fraction: f64) -> Vec<LabelPresence> {
    let mut n_meas: BTreeMap<&str, usize> = BTreeMap::new();
    let mut counts: BTreeMap<(&str, &str), usize> = BTreeMap::new();
    for r in records {
        *n_meas.entry(r.setup.as_str()).or_insert(0) += 1;
        let mut labels: Vec<&str> = r.accepted_labels.iter().map(|s| s.as_str()).collect();
        labels.sort_unstable();
        labels.dedup();
        for l in labels {
            *counts.entry((r.setup.as_str(), l)).or_insert(0) += 1;
        }
    }
    counts
        .into_iter()
        .map(|((setup, label), n)| {
            let total = n_meas[setup];
            LabelPresence {
                setup: setup.to_string(),
                label: label.to_string(),
                n_present: n,
                n_measurements: total,
                used_for_updating: n as f64 >= min_fraction * total as f64 - 1e-12,
            }
        })
        .collect()
}

// ---------------------------------------------------------------------------------------------
// The pair stage's computation: one model per setup, labelled on a grid over the board, and
// the pairing of one measurement's modes with it.

/// One measurement's identified modes (consecutive rows of modes.parquet), with the band and
/// scan points of its first row.
pub struct MeasurementModes {
    pub measurement_id: String,
    pub board_id: String,
    pub setup: String,
    pub band: (f64, f64),
    pub points: Vec<ScanPoint>,
    /// (identified mode number, frequency, shape at `points`).
    pub modes: Vec<(i32, f64, Vec<f64>)>,
}

/// A setup's full model at its nominal parameters, its modes, their labels on the board grid
/// ([`board_grid_labels`]) and each mode's largest |amplitude| on that grid.
pub struct SetupModel {
    pub model: FeModel,
    pub modes: Modes,
    pub labels: Vec<String>,
    pub board_max: Vec<f64>,
}

impl SetupModel {
    /// Build the model of `setup` and label its first `n_model_modes` modes. Each model mode
    /// is labelled once per setup, on a grid over the whole board, so it keeps its label in
    /// every measurement whatever part of the board was scanned.
    pub fn build(
        board: &Board,
        setup: Setup,
        n_model_modes: usize,
        params: &PairParams,
    ) -> Result<SetupModel, FemError> {
        let model = FeModel::build(board, setup.clone(), board.mesh_for(&setup))?;
        let p = model.nominal_params();
        let modes = model.modes(&p, n_model_modes)?;
        let (labels, board_max) = board_grid_labels(board, &model, &modes, params)?;
        Ok(SetupModel {
            model,
            modes,
            labels,
            board_max,
        })
    }
}

/// One row of pairs.parquet of a measurement: an identified mode (paired or not) or a model
/// mode in the band that found no partner (`missing`).
pub struct PairRecord {
    pub mode: Option<i32>,
    pub freq_hz: Option<f64>,
    pub model_mode: Option<i32>,
    pub model_freq_hz: Option<f64>,
    pub label: String,
    pub mac: Option<f64>,
    pub accepted: bool,
    pub missing: bool,
    pub swapped: bool,
}

/// A measurement's pairing: its rows, its presence record, and what its MAC plot shows.
pub struct MeasurementPairing {
    pub rows: Vec<PairRecord>,
    pub presence: PresenceRecord,
    pub pairing: Pairing,
    pub model_modes: Vec<ModelMode>,
}

/// Pair one measurement's modes with its setup's model: by MAC where its points tell the
/// model's modes apart, else by frequency, visibility and order (finding `pair.by_frequency`).
/// Scan points off the model board are left out (finding `pair.point_outside_model`); `None`
/// when no point is left or the pairing fails (a quarantine finding).
pub fn pair_measurement(
    m: &MeasurementModes,
    sm: &SetupModel,
    p: &PairParams,
    findings: &mut Findings,
) -> Result<Option<MeasurementPairing>, FemError> {
    let (model, fe_modes, labels, board_max) = (&sm.model, &sm.modes, &sm.labels, &sm.board_max);
    // Scan points the model cannot evaluate (outside the outline, inside a hole) are
    // left out of this measurement's MAC, and reported.
    let mut keep = vec![];
    for (i, pt) in m.points.iter().enumerate() {
        if model.w_at(fe_modes, &[[pt.x_m, pt.y_m]]).is_ok() {
            keep.push(i);
        } else {
            findings.push(
                Finding::new(
                    Severity::Warning,
                    "pair.point_outside_model",
                    format!(
                        "scan point node {} at ({:.4}, {:.4}) m is outside the model board or inside a hole; left out of the MAC",
                        pt.node_id, pt.x_m, pt.y_m
                    ),
                )
                .measurement(m.measurement_id.clone()),
            );
        }
    }
    if keep.is_empty() {
        findings.push(
            Finding::new(
                Severity::Quarantined,
                "pair.points",
                "no scan point lies on the model board (expected at least 1)",
            )
            .measurement(m.measurement_id.clone()),
        );
        return Ok(None);
    }
    let points: Vec<ScanPoint> = keep.iter().map(|&i| m.points[i]).collect();
    let model_modes = modes_at(model, fe_modes, &points)?;
    let identified: Vec<IdentifiedShape> = m
        .modes
        .iter()
        .map(|(_, f, s)| IdentifiedShape {
            freq_hz: *f,
            shape: keep.iter().map(|&i| s[i]).collect(),
        })
        .collect();
    // The MAC pairs modes only where these points tell the model's own modes apart.
    let alike = model_mac_max(&model_modes, m.band, p.freq_gate_sd * p.freq_sd_rel);
    let by_mac = points.len() >= 3 && alike < p.mac_min;
    let paired = if by_mac {
        pair_modes_labelled(&identified, &model_modes, labels.clone(), m.band, p)
    } else {
        let visibility = visibility(&model_modes, board_max);
        findings.push(
            Finding::new(
                Severity::Info,
                "pair.by_frequency",
                format!(
                    "{} scan point(s) cannot tell the model's modes apart by MAC (two model modes near the band have MAC {alike:.2} at them, against {} for a pair); paired on frequency (prior predictive sd {} of ln f, at most {} sd apart), on each model mode's amplitude at the points (under {} of its largest on the board: near a node there, less likely seen, not missing when unseen) and on the modes' order",
                    points.len(),
                    p.mac_min,
                    p.freq_sd_rel,
                    p.freq_gate_sd,
                    p.min_visibility
                ),
            )
            .measurement(m.measurement_id.clone()),
        );
        pair_modes_by_frequency(
            &identified,
            &model_modes,
            labels.clone(),
            &visibility,
            m.band,
            p,
        )
    };
    let pairing = match paired {
        Ok(p) => p,
        Err(e) => {
            findings.push(
                Finding::new(Severity::Quarantined, "pair.failed", e.to_string())
                    .measurement(m.measurement_id.clone()),
            );
            return Ok(None);
        }
    };
    let (rows, accepted_labels) = pair_records(m, &pairing, &model_modes);
    Ok(Some(MeasurementPairing {
        rows,
        presence: PresenceRecord {
            measurement_id: m.measurement_id.clone(),
            setup: m.setup.clone(),
            accepted_labels,
        },
        pairing,
        model_modes,
    }))
}

/// Each model mode's visibility at the points: its largest |amplitude| there over its largest
/// on the board grid, at most 1 (0 for a mode flat on the board).
fn visibility(model_modes: &[ModelMode], board_max: &[f64]) -> Vec<f64> {
    model_modes
        .iter()
        .zip(board_max)
        .map(|(mm, &big)| {
            let here = mm.shape.iter().fold(0.0f64, |a, v| a.max(v.abs()));
            if big > 0.0 {
                (here / big).min(1.0)
            } else {
                0.0
            }
        })
        .collect()
}

/// The rows of a measurement's pairing (one per identified mode, then one per missing model
/// mode) and the labels of its accepted pairs.
fn pair_records(
    m: &MeasurementModes,
    pairing: &Pairing,
    model_modes: &[ModelMode],
) -> (Vec<PairRecord>, Vec<String>) {
    let swapped: std::collections::BTreeSet<usize> =
        pairing.swaps.iter().flat_map(|&(a, b)| [a, b]).collect();
    let mut accepted_labels = vec![];
    let mut rows = vec![];
    for pr in &pairing.pairs {
        let (mode_no, f, _) = &m.modes[pr.mode];
        if pr.accepted {
            accepted_labels.push(pr.label.clone());
        }
        rows.push(PairRecord {
            mode: Some(*mode_no),
            freq_hz: Some(*f),
            model_mode: pr.model_mode.map(|j| j as i32 + 1),
            model_freq_hz: pr.model_mode.map(|j| model_modes[j].freq_hz),
            label: pr.label.clone(),
            mac: pr.model_mode.map(|_| pr.mac),
            accepted: pr.accepted,
            missing: false,
            swapped: swapped.contains(&pr.mode),
        });
    }
    for &j in &pairing.missing {
        rows.push(PairRecord {
            mode: None,
            freq_hz: None,
            model_mode: Some(j as i32 + 1),
            model_freq_hz: Some(model_modes[j].freq_hz),
            label: pairing.model_labels[j].clone(),
            mac: None,
            accepted: false,
            missing: true,
            swapped: false,
        });
    }
    (rows, accepted_labels)
}

/// Row and column labels of a measurement's MAC plot: `<mode>: <f> Hz` per identified mode,
/// `<label> <f>` per model mode.
pub fn mac_plot_labels(
    m: &MeasurementModes,
    mp: &MeasurementPairing,
) -> (Vec<String>, Vec<String>) {
    let rl: Vec<String> = m
        .modes
        .iter()
        .map(|(k, f, _)| format!("{k}: {f:.0} Hz"))
        .collect();
    let cl: Vec<String> = mp
        .pairing
        .model_labels
        .iter()
        .zip(&mp.model_modes)
        .map(|(l, mm)| format!("{l} {:.0}", mm.freq_hz))
        .collect();
    (rl, cl)
}

/// Grid points along the board's longer side for labelling model modes (25 on an 80 mm board): a
/// mode's nodal lines are resolved up to order ~8 whatever the scan grid was.
const LABEL_GRID_POINTS: usize = 25;

/// Labels of the model's modes from their shapes on a regular grid over the whole board
/// (cell centres of a `LABEL_GRID_POINTS`-per-longer-side grid; points in holes or off the
/// outline are left out), made unique ([`label_modes`]); and each mode's largest
/// |amplitude| on that grid (the scale of its visibility at a measurement's points).
pub fn board_grid_labels(
    board: &Board,
    model: &FeModel,
    modes: &Modes,
    params: &PairParams,
) -> Result<(Vec<String>, Vec<f64>), FemError> {
    let (lx, ly) = (board.length_x_m, board.width_y_m);
    let step = lx.max(ly) / LABEL_GRID_POINTS as f64;
    let (nx, ny) = (
        ((lx / step).round() as usize).max(3),
        ((ly / step).round() as usize).max(3),
    );
    let mut points = vec![];
    for j in 0..ny {
        for i in 0..nx {
            let (x, y) = (
                (i as f64 + 0.5) * lx / nx as f64,
                (j as f64 + 0.5) * ly / ny as f64,
            );
            if model.w_at(modes, &[[x, y]]).is_ok() {
                points.push(ScanPoint {
                    node_id: (j * nx + i) as i64,
                    x_m: x,
                    y_m: y,
                    z_m: 0.0,
                });
            }
        }
    }
    let shapes = modes_at(model, modes, &points)?;
    let board_max = shapes
        .iter()
        .map(|m| m.shape.iter().fold(0.0f64, |a, v| a.max(v.abs())))
        .collect();
    Ok((label_modes(&shapes, &points, params), board_max))
}

/// The model's modes as shapes at `points`.
pub fn modes_at(
    model: &FeModel,
    modes: &Modes,
    points: &[ScanPoint],
) -> Result<Vec<ModelMode>, FemError> {
    let pts: Vec<[f64; 2]> = points.iter().map(|p| [p.x_m, p.y_m]).collect();
    let w = model.w_at(modes, &pts)?;
    Ok((0..modes.freq_hz.len())
        .map(|j| ModelMode {
            freq_hz: modes.freq_hz[j],
            shape: (0..pts.len()).map(|i| w[(i, j)]).collect(),
        })
        .collect())
}

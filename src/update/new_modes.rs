//! An enriched model's own modes (a fixture's resonance) paired with the identified modes
//! pair left unpaired, so that they join the updating as labels of their own.

use crate::bayes::stats::median;
use crate::fem::FeModel;
use crate::modal::mac::mac_real;
use crate::modal::rows::{ModeRow, PairRow};
use crate::update::problem::usable_points;
use std::collections::{BTreeMap, BTreeSet};

/// Least MAC of an identified mode with an enriched model's new mode, and the largest
/// relative frequency difference, for the two to pair (pair's own rule is MAC-based too).
pub const NEW_MODE_MIN_MAC: f64 = 0.9;

pub const NEW_MODE_MAX_REL_FREQ: f64 = 0.05;

/// The modes of `model` at `p` that no label carries (`taken`), paired with the identified
/// modes pair left unpaired (`identified` minus `paired`): per measurement the unpaired
/// mode of largest MAC ≥ [`NEW_MODE_MIN_MAC`] within [`NEW_MODE_MAX_REL_FREQ`] of the
/// model's frequency. A model mode becomes a label (`<mechanism>-mode-<k>`) where it pairs
/// in at least half of the measurements: an enrichment that predicts a mode the baseline
/// cannot have (a fixture's own resonance) is then held to that mode too.
#[allow(clippy::too_many_arguments)]
pub fn pair_new_modes(
    model: &FeModel,
    p: &crate::fem::Params,
    n_track: usize,
    taken: &[usize],
    identified: &[&ModeRow],
    paired: &BTreeSet<(String, i32)>,
    mechanism: &str,
) -> anyhow::Result<Vec<NewMode>> {
    let m = model.modes(p, n_track)?;
    let key = |r: &ModeRow| (r.measurement_id.clone(), r.mode);
    let unpaired: Vec<&ModeRow> = identified
        .iter()
        .copied()
        .filter(|r| !paired.contains(&key(r)))
        .collect();
    let measurements: BTreeSet<&str> = identified
        .iter()
        .map(|r| r.measurement_id.as_str())
        .collect();
    let (lo, hi) = identified
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(lo, hi), r| {
            (lo.min(r.freq_hz), hi.max(r.freq_hz))
        });
    // The model modes no label carries, within the identified band.
    let candidates: Vec<usize> = (0..m.freq_hz.len())
        .filter(|&c| {
            let fc = m.freq_hz[c];
            !(taken.contains(&c)
                || fc < lo * (1.0 - NEW_MODE_MAX_REL_FREQ)
                || fc > hi * (1.0 + NEW_MODE_MAX_REL_FREQ))
        })
        .collect();
    let far = |f: f64, fc: f64| (f / fc - 1.0).abs() > NEW_MODE_MAX_REL_FREQ;
    // Each unpaired mode near a candidate's frequency with a shape at ≥ 3 usable points: the
    // shape there and the model's modes there, evaluated once.
    let mut obs: Vec<(&ModeRow, Vec<f64>, faer::Mat<f64>)> = vec![];
    for &r in &unpaired {
        if candidates.iter().all(|&c| far(r.freq_hz, m.freq_hz[c])) {
            continue;
        }
        let (pts, u) = usable_points(model, r);
        if pts.len() < 3 {
            continue;
        }
        let w = model.w_at(&m, &pts)?;
        obs.push((r, u, w));
    }
    let mut used: BTreeSet<(String, i32)> = BTreeSet::new();
    let mut out = vec![];
    for &c in &candidates {
        let fc = m.freq_hz[c];
        let mut best: BTreeMap<&str, (f64, &ModeRow)> = BTreeMap::new();
        for (r, u, w) in &obs {
            if far(r.freq_hz, fc) || used.contains(&key(r)) {
                continue;
            }
            let wc: Vec<f64> = (0..u.len()).map(|i| w[(i, c)]).collect();
            let mac = mac_real(u, &wc);
            let m = r.measurement_id.as_str();
            if mac >= NEW_MODE_MIN_MAC && best.get(m).is_none_or(|b| mac > b.0) {
                best.insert(m, (mac, *r));
            }
        }
        if best.is_empty() || 2 * best.len() < measurements.len() {
            continue;
        }
        let label = format!("{mechanism}-mode-{}", out.len() + 1);
        let rows: Vec<PairRow> = best
            .values()
            .map(|(_, r)| {
                used.insert(key(r));
                PairRow {
                    measurement_id: r.measurement_id.clone(),
                    board_id: r.board_id.clone(),
                    setup: "bolted".into(),
                    mode: r.mode,
                    freq_hz: r.freq_hz,
                    model_mode: c as i32 + 1,
                    label: label.clone(),
                }
            })
            .collect();
        out.push(NewMode {
            model_mode: c,
            model_freq_hz: fc,
            label,
            rows,
            n_measurements: measurements.len(),
        });
    }
    Ok(out)
}

/// A mode of an enriched model that no baseline label carries, with the identified modes it
/// pairs with ([`pair_new_modes`]).
#[derive(Clone, Debug)]
pub struct NewMode {
    /// 0-based mode of the enriched model at the ROM's centre.
    pub model_mode: usize,
    pub model_freq_hz: f64,
    /// `<mechanism>-mode-<k>`.
    pub label: String,
    /// One pair per measurement where it paired.
    pub rows: Vec<PairRow>,
    /// Bolted measurements with an identified mode.
    pub n_measurements: usize,
}

impl NewMode {
    pub fn median_freq_hz(&self) -> f64 {
        let f: Vec<f64> = self.rows.iter().map(|r| r.freq_hz).collect();
        median(&f)
    }
}

/// The modes of `model` at `p` matched to the reference shapes (columns of `w_ref`, w at
/// `points`) by MAC, greedily from the best pair: per reference, the 0-based mode and its
/// frequency. A joint enrichment can add modes (the fixture's) and reorder them, so labels
/// are carried over by shape, never by position.
pub fn match_modes(
    model: &FeModel,
    p: &crate::fem::Params,
    n_modes: usize,
    w_ref: &faer::Mat<f64>,
    points: &[[f64; 2]],
) -> anyhow::Result<(Vec<usize>, Vec<f64>)> {
    let (idx, m) = match_modes_of(model, p, n_modes, w_ref, points)?;
    let f = idx.iter().map(|&b| m.freq_hz[b]).collect();
    Ok((idx, f))
}

/// [`match_modes`] with the solved modes themselves (for their derivatives).
pub fn match_modes_of(
    model: &FeModel,
    p: &crate::fem::Params,
    n_modes: usize,
    w_ref: &faer::Mat<f64>,
    points: &[[f64; 2]],
) -> anyhow::Result<(Vec<usize>, crate::fem::Modes)> {
    let m = model.modes(p, n_modes)?;
    let w = model.w_at(&m, points)?;
    let nr = w_ref.ncols();
    let mut pairs = vec![];
    for a in 0..nr {
        for b in 0..w.ncols() {
            let (mut ab, mut aa, mut bb) = (0.0, 0.0, 0.0);
            for i in 0..points.len() {
                ab += w_ref[(i, a)] * w[(i, b)];
                aa += w_ref[(i, a)] * w_ref[(i, a)];
                bb += w[(i, b)] * w[(i, b)];
            }
            pairs.push((ab * ab / (aa * bb).max(f64::MIN_POSITIVE), a, b));
        }
    }
    pairs.sort_by(|x, y| y.0.total_cmp(&x.0));
    let mut idx = vec![usize::MAX; nr];
    let mut taken = vec![false; w.ncols()];
    for (_, a, b) in pairs {
        if idx[a] == usize::MAX && !taken[b] {
            idx[a] = b;
            taken[b] = true;
        }
    }
    Ok((idx, m))
}

//! Shape outliers: measurements whose measured mode shapes differ from the model's more than
//! the other measurements of their setup do, in every mode. Pure, over the residual rows'
//! MAC (`residuals.parquet`'s `mac`).
//!
//! Why a shape check beside the frequency one ([`super::locate::MeasurementCheck`]): the
//! updating fits each bolted measurement its own contact stiffness, and a stiffness change at
//! one joint moves every frequency of the assembly much as a change at all four does. So a
//! loose bolt's frequency drop is absorbed into that measurement's contact stiffness and its
//! frequency residuals look like its board-mates'. What the symmetric joint model cannot
//! absorb is the shape: one soft corner tilts every mode's shape towards it, and every mode's
//! MAC against the symmetric model drops together. Noise lowers the MAC of one measurement's
//! modes too, but then the measurement is still unlike the others, which is what an outlier
//! check reports; the refits decide whether a mechanism explains it.
//!
//! The statistic, per measurement: x = ln(1 − MAC) per paired mode (1 − MAC of a noisy
//! shape is a scaled sum of squares, near log-normal), a robust z against the setup's median
//! and MAD of that mode (robust to a contaminated minority: a loose bolt in 30 % of the
//! assemblies neither inflates the scale nor hides itself), combined by Stouffer's Σ z / √n,
//! and the sum standardized by its own median and MAD over the setup's measurements,
//! one-sided (shapes worse than the others'). Multiplicity: Benjamini–Hochberg over the
//! measurements at [`LocateOptions::fdr`]. An outlier that one mode alone makes (the others'
//! sum not significant on its own: a near-degenerate pair that mixed, one poorly fitted
//! pole; [`SINGLE_MODE_CONFIRM_P`]) is an identification matter and not a shape outlier. A shape outlier every one of whose board's measurements in
//! the setup (at least two) is also one is board-shared: the board's shape differs, not one
//! assembly's.

use serde::Serialize;
use statrs::distribution::{ContinuousCDF, Normal};
use std::collections::BTreeMap;

use super::locate::{LocateOptions, ResidualObs};
use crate::bayes::stats::median;

/// 1 − MAC below this is taken as this: shapes agreeing to 1e-6 differ by round-off in the
/// MAC, not by physics, and the logarithm needs a floor.
pub const MAC_GAP_FLOOR: f64 = 1e-6;

/// Fewest paired modes with a MAC for a measurement's shape statistic: with two, one slipped
/// mode cannot be told from a shape change of the whole measurement.
pub const MIN_SHAPE_MODES: usize = 3;

/// An outlier is one mode's alone when the other modes' sum has p above this: a confirmation
/// of one already flagged measurement, at the usual 5 %, not a family's level. (On the
/// realistic lab's loose bolts, the softened corner's mode stands out most, at z ≈ 11, and
/// the rest at p = 0.01–0.02; a slipped pole leaves the rest at p ≈ 0.5.)
pub const SINGLE_MODE_CONFIRM_P: f64 = 0.05;

/// One mode's part of a measurement's shape statistic.
#[derive(Clone, Debug, PartialEq, Serialize, schemars::JsonSchema)]
pub struct ShapeMode {
    pub label: String,
    pub mac: f64,
    /// Robust z of ln(1 − MAC) against the setup's median and MAD of the mode (positive: the
    /// shape is further from the model's than the others').
    pub z: f64,
}

/// The shape check of one measurement.
#[derive(Clone, Debug, PartialEq, Serialize, schemars::JsonSchema)]
pub struct ShapeCheck {
    pub measurement_id: String,
    pub board_id: String,
    pub setup: String,
    pub n_modes: usize,
    /// Stouffer's Σ z / √n over the modes (None: fewer than [`MIN_SHAPE_MODES`]); its p
    /// standardizes it by the setup's median and MAD of it.
    pub z: Option<f64>,
    /// One-sided p of `z` (None: fewer than [`MIN_SHAPE_MODES`] modes).
    pub p_value: Option<f64>,
    /// BH over all measurements with a p.
    pub q_value: Option<f64>,
    /// q ≤ fdr and not one mode's alone.
    pub outlier: bool,
    /// q ≤ fdr, but the other modes pass: the label of the one mode that made it.
    pub single_mode: Option<String>,
    /// An outlier whose board's every measurement in the setup is one too.
    pub board_shared: bool,
    pub modes: Vec<ShapeMode>,
}

fn std_normal() -> Normal {
    Normal::new(0.0, 1.0).expect("standard normal")
}

/// Median and the locate step's robust sd (1.4826 × MAD).
fn median_mad(x: &[f64]) -> (f64, f64) {
    (median(x), super::locate::mad_sd(x))
}

fn stouffer(z: &[f64]) -> f64 {
    z.iter().sum::<f64>() / (z.len() as f64).sqrt()
}

fn upper_p(z: f64) -> f64 {
    std_normal().sf(z)
}

type Key = (String, String, String); // (setup, measurement, board)

/// The shape check of every measurement with at least [`MIN_SHAPE_MODES`] MACs.
pub fn shape_checks(rows: &[&ResidualObs], opts: &LocateOptions) -> Vec<ShapeCheck> {
    let min_n = opts.min_measurements_per_label.max(4);
    // (setup, label) → measurement → x; and per measurement its (label, mac, x).
    let mut by_label: BTreeMap<(String, String), BTreeMap<String, f64>> = BTreeMap::new();
    let mut by_m: BTreeMap<Key, Vec<(String, f64, f64)>> = BTreeMap::new();
    for r in rows {
        let Some(mac) = r
            .mac
            .filter(|m| m.is_finite() && (0.0..=1.0 + 1e-9).contains(m))
        else {
            continue;
        };
        let x = (1.0 - mac).max(MAC_GAP_FLOOR).ln();
        by_label
            .entry((r.setup.clone(), r.label.clone()))
            .or_default()
            .insert(r.measurement_id.clone(), x);
        by_m.entry((
            r.setup.clone(),
            r.measurement_id.clone(),
            r.board_id.clone(),
        ))
        .or_default()
        .push((r.label.clone(), mac, x));
    }
    // Per mode: robust centre and scale (median, 1.4826 MAD), so that a contaminated
    // minority neither inflates the scale nor hides itself.
    let robust: BTreeMap<(String, String), (f64, f64)> = by_label
        .iter()
        .filter(|(_, v)| v.len() >= min_n)
        .filter_map(|(k, v)| {
            let x: Vec<f64> = v.values().copied().collect();
            let (c, s) = median_mad(&x);
            (s > 0.0).then(|| (k.clone(), (c, s)))
        })
        .collect();
    let mut checks: Vec<ShapeCheck> = by_m
        .iter()
        .map(|((setup, mid, board), modes)| {
            let scored: Vec<ShapeMode> = modes
                .iter()
                .filter_map(|(label, mac, x)| {
                    let (c, s) = robust.get(&(setup.clone(), label.clone()))?;
                    Some(ShapeMode {
                        label: label.clone(),
                        mac: *mac,
                        z: (x - c) / s,
                    })
                })
                .collect();
            let z: Vec<f64> = scored.iter().map(|m| m.z).collect();
            ShapeCheck {
                measurement_id: mid.clone(),
                board_id: board.clone(),
                setup: setup.clone(),
                n_modes: z.len(),
                z: (z.len() >= MIN_SHAPE_MODES).then(|| stouffer(&z)),
                p_value: None,
                q_value: None,
                outlier: false,
                single_mode: None,
                board_shared: false,
                modes: scored,
            }
        })
        .collect();
    // Stouffer's sum standardized by its own robust spread over the setup's measurements:
    // the modes' scales come from a few tens of measurements each, and one measurement's
    // modes share its noise level, so the raw sum's null spread is not 1 (0.9–1.8 on the
    // realistic lab's null campaigns); its median and MAD over the measurements are.
    let mut by_setup: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    for c in &checks {
        if let Some(z) = c.z {
            by_setup.entry(c.setup.clone()).or_default().push(z);
        }
    }
    let spread: BTreeMap<String, (f64, f64)> = by_setup
        .into_iter()
        .filter(|(_, z)| z.len() >= min_n)
        .map(|(s, z)| (s, median_mad(&z)))
        .filter(|(_, (_, sd))| *sd > 0.0)
        .collect();
    let standard = |setup: &str, z: f64| spread.get(setup).map(|(c, s)| (z - c) / s);
    for c in &mut checks {
        c.p_value = c.z.and_then(|z| standard(&c.setup, z)).map(upper_p);
    }
    let q = super::locate::bh_opt(&checks.iter().map(|c| c.p_value).collect::<Vec<_>>());
    for (c, q) in checks.iter_mut().zip(q) {
        c.q_value = q;
        if !q.is_some_and(|q| q <= opts.fdr) {
            continue;
        }
        // One mode alone? The rest, without the largest z, must stand out on their own too.
        let imax = (0..c.modes.len())
            .max_by(|&a, &b| c.modes[a].z.total_cmp(&c.modes[b].z))
            .unwrap_or(0);
        let rest: Vec<f64> = (0..c.modes.len())
            .filter(|&i| i != imax)
            .map(|i| c.modes[i].z)
            .collect();
        let p_rest = standard(&c.setup, stouffer(&rest)).map_or(1.0, upper_p);
        if p_rest > SINGLE_MODE_CONFIRM_P {
            c.single_mode = Some(c.modes[imax].label.clone());
        } else {
            c.outlier = true;
        }
    }
    // Board-shared: every measurement of the board in the setup (at least two) an outlier.
    let mut per_board: BTreeMap<(String, String), (usize, usize)> = BTreeMap::new();
    for c in &checks {
        let e = per_board
            .entry((c.setup.clone(), c.board_id.clone()))
            .or_default();
        e.0 += 1;
        e.1 += usize::from(c.outlier);
    }
    for c in &mut checks {
        let (n, n_out) = per_board[&(c.setup.clone(), c.board_id.clone())];
        c.board_shared = c.outlier && n >= 2 && n_out == n;
    }
    checks
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use rand_distr::{Distribution, Normal as RNormal};

    const LABELS: [&str; 6] = ["m1", "m2", "m3", "m4", "m5", "m6"];

    /// Six boards of five bolted assemblies; ln(1 − MAC) per mode N(c_mode, 0.5²), with
    /// `bad(measurement index, mode index)` added to it.
    fn rows(seed: u64, bad: impl Fn(usize, usize) -> f64) -> Vec<ResidualObs> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let n01 = RNormal::new(0.0, 1.0).unwrap();
        let mut out = vec![];
        for k in 0..30 {
            for (i, label) in LABELS.iter().enumerate() {
                let x = -7.0 + 0.4 * i as f64 + 0.5 * n01.sample(&mut rng) + bad(k, i);
                out.push(ResidualObs {
                    measurement_id: format!("M{k:02}"),
                    board_id: format!("B{}", k / 5),
                    setup: "bolted".into(),
                    label: label.to_string(),
                    freq_hz: 1000.0,
                    model_freq_hz_mean: 1000.0,
                    predictive_sd_hz: 1.0,
                    rel_residual: 0.0,
                    std_residual: 0.0,
                    used_for_updating: true,
                    mac: Some(1.0 - x.exp()),
                });
            }
        }
        out
    }

    fn outliers(rows: &[ResidualObs]) -> (Vec<ShapeCheck>, Vec<String>) {
        let refs: Vec<&ResidualObs> = rows.iter().collect();
        let c = shape_checks(&refs, &LocateOptions::default());
        let o = c
            .iter()
            .filter(|c| c.outlier)
            .map(|c| c.measurement_id.clone())
            .collect();
        (c, o)
    }

    #[test]
    fn a_minority_whose_every_shape_is_off_is_found_and_no_other() {
        // Nine of thirty assemblies with every mode's 1 − MAC eight times the others' (ln 8 =
        // 2.1, about four of their sds; the realistic lab's loose bolt: 6 to 30 times).
        let loose = [0, 3, 6, 11, 14, 17, 21, 24, 28];
        for seed in 0..5 {
            let r = rows(
                seed,
                |k, _| if loose.contains(&k) { 8f64.ln() } else { 0.0 },
            );
            let (c, o) = outliers(&r);
            let want: Vec<String> = loose.iter().map(|k| format!("M{k:02}")).collect();
            assert_eq!(o, want, "seed {seed}: {c:?}");
            assert!(c.iter().all(|c| !c.board_shared));
        }
    }

    #[test]
    fn like_shapes_are_not_outliers() {
        // Under the null the BH family holds its FDR: over 20 campaigns of 30 measurements,
        // no outlier at 0.01 in nearly all.
        let flagged: usize = (0..20)
            .map(|seed| outliers(&rows(100 + seed, |_, _| 0.0)).1.len())
            .sum();
        assert!(
            flagged <= 1,
            "{flagged} false shape outliers in 20 null campaigns"
        );
    }

    #[test]
    fn one_slipped_mode_is_not_a_shape_outlier() {
        // Assembly 7's mode 3 with a MAC near 0.7 (a mixed pair), its other modes as usual:
        // either Stouffer's sum does not reach the FDR, or the rest pass on their own.
        for seed in 0..5 {
            let r = rows(seed, |k, i| {
                if k == 7 && i == 2 {
                    6.2 + 0.3f64.ln()
                } else {
                    0.0
                }
            });
            let (c, o) = outliers(&r);
            assert!(o.is_empty(), "{o:?}");
            let m = c.iter().find(|c| c.measurement_id == "M07").unwrap();
            assert!(m.modes.iter().find(|x| x.label == "m3").unwrap().mac < 0.95);
            assert!(
                m.q_value.unwrap() > 0.01 || m.single_mode.as_deref() == Some("m3"),
                "{m:?}"
            );
        }
        // With three modes, one slip reaches the FDR alone: named, not an outlier.
        let r: Vec<ResidualObs> = rows(7, |k, i| if k == 7 && i == 0 { 5.0 } else { 0.0 })
            .into_iter()
            .filter(|r| ["m1", "m2", "m3"].contains(&r.label.as_str()))
            .collect();
        let (c, o) = outliers(&r);
        assert!(o.is_empty(), "{o:?}");
        let m = c.iter().find(|c| c.measurement_id == "M07").unwrap();
        assert_eq!(m.single_mode.as_deref(), Some("m1"), "{m:?}");
    }

    #[test]
    fn a_board_whose_every_assembly_is_off_shares_it() {
        // Board B2 (assemblies 10..14) off in every assembly; assembly 21 alone on B4.
        let r = rows(3, |k, _| {
            if (10..15).contains(&k) || k == 21 {
                8f64.ln()
            } else {
                0.0
            }
        });
        let (c, o) = outliers(&r);
        assert_eq!(o, ["M10", "M11", "M12", "M13", "M14", "M21"]);
        for m in &c {
            assert_eq!(
                m.board_shared,
                m.board_id == "B2",
                "{}: {m:?}",
                m.measurement_id
            );
        }
    }

    #[test]
    fn too_few_modes_give_no_statistic() {
        let r: Vec<ResidualObs> = rows(1, |_, _| 0.0)
            .into_iter()
            .filter(|r| r.label == "m1" || r.label == "m2")
            .collect();
        let (c, o) = outliers(&r);
        assert!(o.is_empty());
        assert!(c.iter().all(|c| c.p_value.is_none() && c.n_modes == 2));
    }
}

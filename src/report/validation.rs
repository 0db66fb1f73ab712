//! Validation tables from predictions and measurements, pure: predicted intervals per board,
//! setup and mode (the Figure-6 analog's boxes), their coverage of the measurements, and the
//! Table-2 analog (measured vs simulated mean and standard deviation per mode).
//!
//! Quantiles are numpy's default (linear interpolation between order statistics, "type 7"
//! of Hyndman & Fan 1996), so a reader recomputing them with `numpy.quantile` gets the same
//! numbers. Sample standard deviations divide by n − 1.

use std::collections::BTreeMap;

/// One predicted frequency (a row of predictions.parquet).
#[derive(Clone, Debug)]
pub struct Pred {
    /// `new_board` or `board`.
    pub scope: String,
    /// None for a new board.
    pub board_id: Option<String>,
    pub setup: String,
    pub label: String,
    pub freq_hz: f64,
    pub freq_obs_hz: f64,
    /// The model-form discrepancy in freq_obs_hz, relative frequency (0 without one).
    pub discrepancy_rel: f64,
}

/// One measured frequency of a paired mode.
#[derive(Clone, Debug)]
pub struct Measured {
    pub measurement_id: String,
    pub board_id: String,
    pub setup: String,
    pub label: String,
    pub freq_hz: f64,
    pub used_for_updating: bool,
    /// The measurement was not used by the updating: its board was held out (`update boards
    /// --hold-out`), compared with the new-board prediction only; or, with
    /// `board_updated`, the measurement alone (`--hold-out-measurements`), compared with its
    /// board's own prediction only.
    pub held_out: bool,
    /// The measurement's board was updated (from its other measurements).
    pub board_updated: bool,
}

/// Key of an interval: (scope, board, setup, label).
pub type Key = (String, Option<String>, String, String);

/// The predicted distribution of one (scope, board, setup, label) and its measurements.
#[derive(Clone, Debug, PartialEq)]
pub struct Interval {
    pub scope: String,
    pub board_id: Option<String>,
    pub setup: String,
    pub label: String,
    pub used_for_updating: bool,
    /// Predictions behind the interval.
    pub n_draws: usize,
    /// Mean and sd of the model frequency.
    pub model_mean_hz: f64,
    pub model_sd_hz: f64,
    /// Quantiles of the predicted measurement (freq_obs_hz).
    pub q05_hz: f64,
    pub q25_hz: f64,
    pub q50_hz: f64,
    pub q75_hz: f64,
    pub q95_hz: f64,
    /// Measurements compared (the board's own; for a new board, those of every board used
    /// for updating) and how many lie in [q05, q95].
    pub n_measured: usize,
    pub n_inside_90: usize,
    /// Measurements held out of the updating and how many lie in [q05, q95]: for a new
    /// board, those of the held-out boards; for a measured board, its own held-out
    /// measurements (`update boards --hold-out-measurements`).
    pub n_held_out: usize,
    pub n_held_out_inside_90: usize,
}

/// Quantile `p` of sorted data, numpy's default linear interpolation.
pub fn quantile_sorted(x: &[f64], p: f64) -> f64 {
    if x.is_empty() {
        return f64::NAN;
    }
    let h = (x.len() - 1) as f64 * p;
    let lo = h.floor() as usize;
    let hi = (lo + 1).min(x.len() - 1);
    x[lo] + (h - lo as f64) * (x[hi] - x[lo])
}

/// Mean and sample standard deviation (n − 1; NaN below two values).
pub fn mean_sd(x: &[f64]) -> (f64, f64) {
    let n = x.len() as f64;
    if x.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    let m = x.iter().sum::<f64>() / n;
    if x.len() < 2 {
        return (m, f64::NAN);
    }
    let v = x.iter().map(|v| (v - m).powi(2)).sum::<f64>() / (n - 1.0);
    (m, v.sqrt())
}

/// Mean and standard deviation of measurements grouped by board, every board weighted
/// equally: a measurement of a board with n_b of them weighs 1/(n_b B) over B boards. These
/// are the moments of "a measurement of a board picked at random", which is what a new
/// board's predicted measurement stands for; the plain moments over all measurements let a
/// board measured three times as often pull them three times as hard (the paper-like
/// campaign measures two boards bolted 9 times and four boards 3 times). The variance is the
/// reliability-weighted estimate Σ wᵢ (xᵢ − m)² / (1 − Σ wᵢ²) (Σ wᵢ = 1), the sample
/// variance when every board has as many measurements. Returns (mean, sd, boards); sd is NaN
/// below two measurements or when Σ wᵢ² = 1 (a single measurement).
pub fn board_weighted_mean_sd<'a>(
    x: impl IntoIterator<Item = (&'a str, f64)>,
) -> (f64, f64, usize) {
    let x: Vec<(&str, f64)> = x.into_iter().collect();
    let mut count: BTreeMap<&str, usize> = BTreeMap::new();
    for (b, _) in &x {
        *count.entry(b).or_default() += 1;
    }
    let nb = count.len();
    if x.is_empty() {
        return (f64::NAN, f64::NAN, 0);
    }
    let w = |b: &str| 1.0 / (count[b] as f64 * nb as f64);
    let m: f64 = x.iter().map(|(b, v)| w(b) * v).sum();
    let sw2: f64 = x.iter().map(|(b, _)| w(b).powi(2)).sum();
    if x.len() < 2 || sw2 >= 1.0 - 1e-12 {
        return (m, f64::NAN, nb);
    }
    let v = x.iter().map(|(b, v)| w(b) * (v - m).powi(2)).sum::<f64>() / (1.0 - sw2);
    (m, v.sqrt(), nb)
}

/// Intervals of every (scope, board, setup, label) of the predictions, sorted by key, with
/// the coverage of the measurements: a board's own measurements for scope `board`, and apart
/// from them its measurements held out of the updating (the out-of-sample test of the
/// own-board prediction); for a new board, every updated board's measurements of that setup
/// and label, and apart from them the held-out boards' (the out-of-sample test of the
/// new-board prediction). A held-out measurement of an updated board is no test of the
/// new-board prediction (its board is in the population's sample): compared with its own
/// board's interval only.
pub fn intervals(preds: &[Pred], measured: &[Measured]) -> Vec<Interval> {
    let mut groups: BTreeMap<Key, (Vec<f64>, Vec<f64>)> = BTreeMap::new();
    for p in preds {
        let g = groups
            .entry((
                p.scope.clone(),
                p.board_id.clone(),
                p.setup.clone(),
                p.label.clone(),
            ))
            .or_default();
        g.0.push(p.freq_hz);
        g.1.push(p.freq_obs_hz);
    }
    let used: BTreeMap<(String, String), bool> = measured
        .iter()
        .filter(|m| !m.held_out)
        .map(|m| ((m.setup.clone(), m.label.clone()), m.used_for_updating))
        .collect();
    groups
        .into_iter()
        .map(|((scope, board_id, setup, label), (model, mut obs))| {
            obs.sort_by(f64::total_cmp);
            let q = |p| quantile_sorted(&obs, p);
            let (q05, q95) = (q(0.05), q(0.95));
            let compared = |held_out: bool| -> Vec<f64> {
                measured
                    .iter()
                    .filter(|m| {
                        m.setup == setup
                            && m.label == label
                            && m.held_out == held_out
                            && match &board_id {
                                Some(b) => *b == m.board_id,
                                None => !(m.held_out && m.board_updated),
                            }
                    })
                    .map(|m| m.freq_hz)
                    .collect()
            };
            let (meas, held) = (compared(false), compared(true));
            let inside = |f: &[f64]| f.iter().filter(|f| **f >= q05 && **f <= q95).count();
            let (mm, ms) = mean_sd(&model);
            Interval {
                used_for_updating: used
                    .get(&(setup.clone(), label.clone()))
                    .copied()
                    .unwrap_or(false),
                n_draws: obs.len(),
                model_mean_hz: mm,
                model_sd_hz: ms,
                q05_hz: q05,
                q25_hz: q(0.25),
                q50_hz: q(0.5),
                q75_hz: q(0.75),
                q95_hz: q95,
                n_measured: meas.len(),
                n_inside_90: inside(&meas),
                n_held_out: held.len(),
                n_held_out_inside_90: inside(&held),
                scope,
                board_id,
                setup,
                label,
            }
        })
        .collect()
}

/// One row of the Table-2 analog.
#[derive(Clone, Debug, PartialEq)]
pub struct Table2Row {
    pub setup: String,
    pub label: String,
    pub used_for_updating: bool,
    pub n_measured: usize,
    /// Boards behind n_measured.
    pub n_boards: usize,
    /// Mean and sd of the measured frequencies, every board weighted equally
    /// ([`board_weighted_mean_sd`]).
    pub measured_mean_hz: f64,
    pub measured_sd_hz: f64,
    /// New board: model mean and sd, and the sd of a predicted measurement.
    pub simulated_mean_hz: f64,
    pub simulated_sd_hz: f64,
    pub predictive_sd_hz: f64,
    /// The model-form discrepancy of a new board's predicted measurement (relative
    /// frequency, %): its mean and sd over the draws (0 without one).
    pub discrepancy_mean_pct: f64,
    pub discrepancy_sd_pct: f64,
    /// (simulated mean with the discrepancy − measured) / measured, %.
    pub mean_error_with_discrepancy_pct: f64,
    /// (simulated − measured) / measured, %.
    pub mean_error_pct: f64,
    /// (predictive sd − measured sd) / measured sd, %.
    pub sd_error_pct: f64,
    /// Fraction of the measurements inside their own board's 90 % interval.
    pub board_coverage_90: f64,
    /// Fraction of the measurements inside the new board's 90 % interval.
    pub new_board_coverage_90: f64,
    /// Measurements of the held-out boards, and the fraction of them inside the new board's
    /// 90 % interval (NaN without held-out boards).
    pub n_held_out: usize,
    pub held_out_coverage_90: f64,
}

/// The Table-2 analog per setup and label with predictions for a new board: measured mean
/// and sd over every measurement of every updated board, each board weighted equally
/// ([`board_weighted_mean_sd`]), against the new-board prediction,
/// and the held-out boards' coverage by it.
pub fn table2(preds: &[Pred], measured: &[Measured], iv: &[Interval]) -> Vec<Table2Row> {
    type Draws = (Vec<f64>, Vec<f64>, Vec<f64>);
    let mut newb: BTreeMap<(String, String), Draws> = BTreeMap::new();
    for p in preds.iter().filter(|p| p.scope == "new_board") {
        let g = newb.entry((p.setup.clone(), p.label.clone())).or_default();
        g.0.push(p.freq_hz);
        g.1.push(p.freq_obs_hz);
        g.2.push(p.discrepancy_rel);
    }
    let mut out = vec![];
    // Free-free first, then bolted; labels in order within a setup.
    let mut newb: Vec<_> = newb.into_iter().collect();
    newb.sort_by(|a, b| (a.0 .0 != "free", &a.0 .1).cmp(&(b.0 .0 != "free", &b.0 .1)));
    for ((setup, label), (model, obs, disc)) in newb {
        let ms: Vec<&Measured> = measured
            .iter()
            .filter(|m| m.setup == setup && m.label == label && !m.held_out)
            .collect();
        let (mm, msd, n_boards) =
            board_weighted_mean_sd(ms.iter().map(|m| (m.board_id.as_str(), m.freq_hz)));
        let (sm, ssd) = mean_sd(&model);
        let (_, psd) = mean_sd(&obs);
        let (dm, dsd) = mean_sd(&disc);
        let with_disc: Vec<f64> = model
            .iter()
            .zip(&disc)
            .map(|(f, d)| f * (1.0 + d))
            .collect();
        let (swd, _) = mean_sd(&with_disc);
        let board_iv = |b: &str| {
            iv.iter().find(|i| {
                i.scope == "board"
                    && i.board_id.as_deref() == Some(b)
                    && i.setup == setup
                    && i.label == label
            })
        };
        let inside_board = ms
            .iter()
            .filter(|m| {
                board_iv(&m.board_id)
                    .is_some_and(|i| m.freq_hz >= i.q05_hz && m.freq_hz <= i.q95_hz)
            })
            .count();
        let nb = iv
            .iter()
            .find(|i| i.scope == "new_board" && i.setup == setup && i.label == label);
        let n = ms.len().max(1) as f64;
        out.push(Table2Row {
            used_for_updating: ms.first().is_some_and(|m| m.used_for_updating),
            n_measured: ms.len(),
            n_boards,
            measured_mean_hz: mm,
            measured_sd_hz: msd,
            simulated_mean_hz: sm,
            simulated_sd_hz: ssd,
            predictive_sd_hz: psd,
            discrepancy_mean_pct: 100.0 * dm,
            discrepancy_sd_pct: 100.0 * dsd,
            mean_error_with_discrepancy_pct: 100.0 * (swd - mm) / mm,
            mean_error_pct: 100.0 * (sm - mm) / mm,
            sd_error_pct: 100.0 * (psd - msd) / msd,
            board_coverage_90: if ms.is_empty() {
                f64::NAN
            } else {
                inside_board as f64 / n
            },
            new_board_coverage_90: match nb {
                Some(i) if !ms.is_empty() => i.n_inside_90 as f64 / n,
                _ => f64::NAN,
            },
            n_held_out: nb.map_or(0, |i| i.n_held_out),
            held_out_coverage_90: match nb {
                Some(i) if i.n_held_out > 0 => i.n_held_out_inside_90 as f64 / i.n_held_out as f64,
                _ => f64::NAN,
            },
            setup,
            label,
        });
    }
    out
}

/// Coverage over a set of intervals: (measurements inside, measurements).
pub fn coverage<'a>(iv: impl IntoIterator<Item = &'a Interval>) -> (usize, usize) {
    iv.into_iter()
        .fold((0, 0), |(a, b), i| (a + i.n_inside_90, b + i.n_measured))
}

/// Coverage of the held-out measurements by the intervals given, (inside, measurements): of
/// the held-out boards by the new board's, of a board's held-out measurements by its own.
pub fn held_out_coverage<'a>(iv: impl IntoIterator<Item = &'a Interval>) -> (usize, usize) {
    iv.into_iter().fold((0, 0), |(a, b), i| {
        (a + i.n_held_out_inside_90, b + i.n_held_out)
    })
}

/// The free-free coverage of the 90 % intervals, each as (inside, measurements): of the
/// validation modes by their boards' intervals, of every measurement by the new board's, of
/// the held-out boards by the new board's, and of the held-out measurements by their boards'.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FreeCoverage {
    pub validation: (usize, usize),
    pub new_board: (usize, usize),
    pub held_out: (usize, usize),
    /// The updating modes' measurements held out of the updating, by their own boards'
    /// intervals (`update boards --hold-out-measurements`).
    pub held_out_measurements: (usize, usize),
}

/// [`FreeCoverage`] of a set of intervals.
pub fn free_coverage(iv: &[Interval]) -> FreeCoverage {
    let cov = |scope: &str, upd: Option<bool>| {
        coverage(iv.iter().filter(|i| {
            i.scope == scope && i.setup == "free" && upd.is_none_or(|u| i.used_for_updating == u)
        }))
    };
    FreeCoverage {
        validation: cov("board", Some(false)),
        new_board: cov("new_board", None),
        held_out: held_out_coverage(
            iv.iter()
                .filter(|i| i.scope == "new_board" && i.setup == "free"),
        ),
        held_out_measurements: held_out_coverage(
            iv.iter()
                .filter(|i| i.scope == "board" && i.setup == "free" && i.used_for_updating),
        ),
    }
}

/// How often the new-unit 90 % predictive interval covers the units it was learnt from, when
/// `n` units are drawn from a normal population and observed exactly, with a flat prior on
/// the mean and on ln σ: the posterior predictive is x̄ ± t₀.₉₅,ₙ₋₁ s √(1 + 1/n), and for an
/// in-sample unit n (xᵢ − x̄)² / ((n − 1)² s²) ~ Beta(½, (n − 2)/2), so the coverage is
/// I_z(½, (n − 2)/2) at z = t² (n + 1) / (n − 1)² (1 if z ≥ 1). It exceeds 90 % (99.6 % for
/// n = 7: every in-sample unit lies within (n − 1)/√n sample sds of the mean), so a new-board
/// prediction that covers all measured boards is what a calibrated hierarchy with few boards
/// gives; the test at the nominal rate is on held-out boards. NaN below 3 units.
pub fn in_sample_coverage_90(n: usize) -> f64 {
    use statrs::distribution::{ContinuousCDF, StudentsT};
    use statrs::function::beta::beta_reg;
    if n < 3 {
        return f64::NAN;
    }
    let nf = n as f64;
    let t = StudentsT::new(0.0, 1.0, nf - 1.0)
        .expect("n ≥ 3: positive degrees of freedom")
        .inverse_cdf(0.95);
    let z = t * t * (nf + 1.0) / ((nf - 1.0) * (nf - 1.0));
    if z >= 1.0 {
        1.0
    } else {
        beta_reg(0.5, (nf - 2.0) / 2.0, z)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_match_numpy_linear() {
        // numpy.quantile([1, 2, 3, 4], [0.05, 0.25, 0.5, 0.75, 0.95])
        //   = [1.15, 1.75, 2.5, 3.25, 3.85]
        let x = [1.0, 2.0, 3.0, 4.0];
        let want = [1.15, 1.75, 2.5, 3.25, 3.85];
        for (p, w) in [0.05, 0.25, 0.5, 0.75, 0.95].iter().zip(want) {
            assert!((quantile_sorted(&x, *p) - w).abs() < 1e-12, "{p}");
        }
        assert_eq!(quantile_sorted(&[7.0], 0.3), 7.0);
        let (m, s) = mean_sd(&[2.0, 4.0, 4.0, 4.0, 5.0, 5.0, 7.0, 9.0]);
        assert_eq!(m, 5.0);
        assert!((s - (32.0f64 / 7.0).sqrt()).abs() < 1e-12);
    }

    #[test]
    fn coverage_counts_own_board_and_all_boards_for_a_new_board() {
        let mut preds = vec![];
        for k in 0..101 {
            for (scope, b) in [
                ("board", Some("A")),
                ("board", Some("B")),
                ("new_board", None),
            ] {
                let centre = match b {
                    Some("A") => 100.0,
                    Some("B") => 110.0,
                    _ => 105.0,
                };
                let spread = if b.is_none() { 10.0 } else { 1.0 };
                let f = centre + spread * (k as f64 - 50.0) / 50.0;
                preds.push(Pred {
                    scope: scope.into(),
                    board_id: b.map(str::to_string),
                    setup: "free".into(),
                    label: "m1".into(),
                    freq_hz: f,
                    freq_obs_hz: f,
                    discrepancy_rel: 0.0,
                });
            }
        }
        let m = |b: &str, f: f64| Measured {
            measurement_id: format!("{b}{f}"),
            board_id: b.into(),
            setup: "free".into(),
            label: "m1".into(),
            freq_hz: f,
            used_for_updating: false,
            held_out: b == "H",
            board_updated: b != "H",
        };
        // Board A: 90 % interval [99.1, 100.9]; B: [109.1, 110.9]; new: [96, 114]. Board H
        // is held out: compared with the new board only, and apart.
        let meas = vec![
            m("A", 100.0),
            m("A", 101.5),
            m("B", 110.5),
            m("B", 120.0),
            m("H", 97.0),
            m("H", 95.0),
            m("H", 113.0),
        ];
        let iv = intervals(&preds, &meas);
        assert_eq!(iv.len(), 3);
        let a = iv
            .iter()
            .find(|i| i.board_id.as_deref() == Some("A"))
            .unwrap();
        assert!((a.q05_hz - 99.1).abs() < 1e-9 && (a.q95_hz - 100.9).abs() < 1e-9);
        assert_eq!((a.n_inside_90, a.n_measured), (1, 2));
        let nb = iv.iter().find(|i| i.scope == "new_board").unwrap();
        assert_eq!((nb.n_inside_90, nb.n_measured), (3, 4));
        assert_eq!((nb.n_held_out_inside_90, nb.n_held_out), (2, 3));
        assert!(iv
            .iter()
            .all(|i| i.scope == "new_board" || i.n_held_out == 0));
        assert_eq!(held_out_coverage(&iv), (2, 3));
        // Board A's measurements held out of the updating (`--hold-out-measurements`):
        // compared with A's own interval apart from the others, never with the new board's.
        let mut with_a = meas.clone();
        for f in [100.5, 101.0, 103.0] {
            with_a.push(Measured {
                held_out: true,
                ..m("A", f)
            });
        }
        let iv_a = intervals(&preds, &with_a);
        let a = iv_a
            .iter()
            .find(|i| i.board_id.as_deref() == Some("A"))
            .unwrap();
        assert_eq!((a.n_inside_90, a.n_measured), (1, 2));
        assert_eq!((a.n_held_out_inside_90, a.n_held_out), (1, 3));
        let nb = iv_a.iter().find(|i| i.scope == "new_board").unwrap();
        assert_eq!((nb.n_inside_90, nb.n_measured), (3, 4));
        assert_eq!((nb.n_held_out_inside_90, nb.n_held_out), (2, 3));
        let t = table2(&preds, &meas, &iv);
        assert_eq!(t.len(), 1);
        assert!((t[0].board_coverage_90 - 0.5).abs() < 1e-12);
        assert!((t[0].new_board_coverage_90 - 0.75).abs() < 1e-12);
        assert!((t[0].measured_mean_hz - 108.0).abs() < 1e-12);
        assert!((t[0].simulated_mean_hz - 105.0).abs() < 1e-9);
        assert_eq!(t[0].n_measured, 4);
        assert_eq!(t[0].n_held_out, 3);
        assert!((t[0].held_out_coverage_90 - 2.0 / 3.0).abs() < 1e-12);
    }

    /// Board-weighted moments against the plain ones at equal counts, a board measured nine
    /// times against one measured once, and the variance's unbiasedness for iid values.
    #[test]
    fn board_weighted_moments_weigh_boards_equally_and_are_unbiased_for_iid_values() {
        // Equal counts: the plain sample moments.
        let x = [("a", 1.0), ("a", 2.0), ("b", 4.0), ("b", 7.0)];
        let (m, s, nb) = board_weighted_mean_sd(x);
        let (pm, ps) = mean_sd(&[1.0, 2.0, 4.0, 7.0]);
        assert_eq!(nb, 2);
        assert!((m - pm).abs() < 1e-12 && (s - ps).abs() < 1e-12);
        // A board measured nine times does not outweigh one measured once.
        let mut x: Vec<(&str, f64)> = vec![("a", 10.0); 9];
        x.push(("b", 0.0));
        assert!((board_weighted_mean_sd(x).0 - 5.0).abs() < 1e-12);
        // One measurement: no sd.
        assert!(board_weighted_mean_sd([("a", 1.0)]).1.is_nan());
        // Reliability weights: the variance is unbiased for iid values whatever the counts.
        use rand::SeedableRng;
        use rand_distr::{Distribution, StandardNormal};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let boards = ["a", "b", "c", "d", "e", "f"];
        let counts = [9usize, 9, 3, 3, 3, 1];
        let reps = 40_000;
        let mut v = 0.0;
        for _ in 0..reps {
            let mut x: Vec<(&str, f64)> = vec![];
            for (b, n) in boards.iter().zip(counts) {
                for _ in 0..n {
                    x.push((b, StandardNormal.sample(&mut rng)));
                }
            }
            v += board_weighted_mean_sd(x).1.powi(2);
        }
        v /= reps as f64;
        // The sample variance of 28 normals has sd sqrt(2/27) per replication; the weighted
        // one (fewer effective values) somewhat more: 5 of those over the replications.
        assert!(
            (v - 1.0).abs() < 5.0 * (2.0f64 / 6.0 / reps as f64).sqrt(),
            "{v}"
        );
    }

    /// The closed form against a seeded simulation of the classical setting: n exact draws
    /// of a normal population, interval x̄ ± t s √(1 + 1/n), the fraction of the n draws
    /// inside (and, as a check of the simulation, a new draw's coverage, 90 %).
    #[test]
    fn in_sample_coverage_matches_a_simulation() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, StandardNormal};
        use statrs::distribution::{ContinuousCDF, StudentsT};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for n in [3usize, 5, 7, 12] {
            let nf = n as f64;
            let t = StudentsT::new(0.0, 1.0, nf - 1.0)
                .unwrap()
                .inverse_cdf(0.95);
            let reps = 40_000;
            let (mut inside, mut new_inside) = (0usize, 0usize);
            for _ in 0..reps {
                let x: Vec<f64> = (0..n).map(|_| StandardNormal.sample(&mut rng)).collect();
                let (m, s) = mean_sd(&x);
                let h = t * s * (1.0 + 1.0 / nf).sqrt();
                inside += x.iter().filter(|v| (*v - m).abs() <= h).count();
                let y: f64 = StandardNormal.sample(&mut rng);
                new_inside += usize::from((y - m).abs() <= h);
            }
            let sim = inside as f64 / (reps * n) as f64;
            let want = in_sample_coverage_90(n);
            // Draws within a replication are dependent: a generous 5 binomial sds of the
            // replications alone.
            let se = (want * (1.0 - want) / reps as f64).sqrt().max(1e-4);
            assert!(
                (sim - want).abs() < 5.0 * se,
                "n = {n}: simulated {sim}, closed form {want}"
            );
            let new = new_inside as f64 / reps as f64;
            assert!(
                (new - 0.9).abs() < 5.0 * (0.09f64 / reps as f64).sqrt(),
                "n = {n}: new {new}"
            );
        }
        assert!((in_sample_coverage_90(7) - 0.9962).abs() < 5e-4);
        assert!(in_sample_coverage_90(2).is_nan());
    }
}

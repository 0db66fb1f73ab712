//! The parts of a located misfit and the share of each a refit leaves: the mean shifts of
//! the located modes, and each located covariate's trend. A mechanism is judged on the part
//! it was screened for, and the diagnosis stops refitting once every part is explained. Pure
//! over [`Located`], the locate input and a refit's residuals.

use std::collections::{BTreeMap, BTreeSet};

use super::locate::{self, LocateOptions, Located, ModeCheck, ResidualObs};
use super::screen::Candidate;

/// The located modes whose mean shift is the misfit a mechanism must remove: those located
/// for a mean shift. Where none is and no covariate trend was located either (a misfit of
/// scatter alone, e.g. outlier measurements), every located mode.
pub fn mean_shift_modes(located: &Located) -> Vec<&locate::LocatedMode> {
    let shifted: Vec<_> = located
        .modes
        .iter()
        .filter(|m| m.reasons.iter().any(|r| r == "mean_shift"))
        .collect();
    if shifted.is_empty() && located.covariates.is_empty() {
        located.modes.iter().collect()
    } else {
        shifted
    }
}

/// The located bolted modes whose mean shifts a joint mechanism acting on every assembly is
/// judged on ([`RefitShares::own`]).
pub fn bolted_shift_labels(located: &Located) -> Vec<&str> {
    mean_shift_modes(located)
        .into_iter()
        .filter(|m| m.setup == "bolted")
        .map(|m| m.label.as_str())
        .collect()
}

/// The share of the located bolted mean shifts (`labels`) a joint refit would leave, predicted
/// before its sampler from step 2's centre fits, the population-level least-squares fit of a
/// model to the median bolted frequencies (`update::centre`): Σ |r_refit| / Σ |r_base| over
/// the labels both fits have, r each label's relative misfit at its model's centre, the
/// baseline's (`base`) and the enriched model's (`refit`). The sampler's refit moves its
/// population-level coordinates to the same data, so its mean shifts follow its centre fit's;
/// what it adds (each assembly's own contact stiffness, the priors) scatters the units about
/// the population and does not remove a shift common to them. `None` without such a label
/// or with no baseline misfit.
pub fn centre_fit_share(
    labels: &[&str],
    base: &[(String, f64)],
    refit: &[(String, f64)],
) -> Option<f64> {
    let of = |v: &[(String, f64)], l: &str| v.iter().find(|(m, _)| m == l).map(|(_, r)| *r);
    let (b, a) = labels
        .iter()
        .filter_map(|l| Some((of(base, l)?, of(refit, l)?)))
        .fold((0.0, 0.0), |(b, a), (x, y)| (b + x.abs(), a + y.abs()));
    (b > 0.0).then(|| a / b)
}

/// Σ |mean relative residual| over the mean-shift modes ([`mean_shift_modes`]) after a refit
/// (`after`) over the same before; a located mode the refit has no row for (a setup it did
/// not refit) keeps its baseline value. `None` without such a mode.
pub fn remaining_share(located: &Located, after: &[ModeCheck]) -> Option<f64> {
    remaining_share_in(located, after, None)
}

/// Per mean-shift mode ([`mean_shift_modes`]) of `setup` (`None`: every setup), its
/// |mean relative residual| in the baseline and after a refit (`after`; a mode the refit has
/// no row for, a setup it did not refit, keeps its baseline value).
fn before_after(located: &Located, after: &[ModeCheck], setup: Option<&str>) -> Vec<(f64, f64)> {
    mean_shift_modes(located)
        .into_iter()
        .filter(|l| setup.is_none_or(|s| l.setup == s))
        .filter_map(|l| {
            let same = |m: &&ModeCheck| m.setup == l.setup && m.label == l.label;
            let b = located
                .mode_checks
                .iter()
                .find(same)?
                .mean_rel_residual
                .abs();
            let a = after
                .iter()
                .find(same)
                .map_or(b, |m| m.mean_rel_residual.abs());
            Some((b, a))
        })
        .collect()
}

/// [`remaining_share`] over the mean-shift modes of one setup (`None`: every setup).
fn remaining_share_in(located: &Located, after: &[ModeCheck], setup: Option<&str>) -> Option<f64> {
    let (before, left) = before_after(located, after, setup)
        .into_iter()
        .fold((0.0, 0.0), |(b, l), (x, y)| (b + x, l + y));
    (before > 0.0).then(|| left / before)
}

/// The largest reduction of a mean-shift mode's |mean relative residual| by a refit
/// (`after`): how much misfit the refit explains in its best-explained mode, for the
/// practical threshold. `None` without such a mode.
pub fn largest_reduction(located: &Located, after: &[ModeCheck]) -> Option<f64> {
    before_after(located, after, None)
        .into_iter()
        .map(|(b, a)| b - a)
        .reduce(f64::max)
}

/// The part of the misfit that the measurements a mechanism acts on carry alone, before a
/// refit and after it: the share the refit leaves, and how much it changes (for the practical
/// threshold). `after` holds the refit's rows; a row it lacks keeps `before`'s (a setup it did
/// not refit). `None` without such a row.
///
/// A mechanism that acts on some assemblies only (a loose bolt) is judged on this part: it
/// makes them stand apart from the others, which a mechanism acting on every assembly alike
/// cannot do, while the mean shifts common to every assembly (the joint model's form, or a
/// mechanism of all assemblies) are not its to remove. Each measurement is judged on what
/// made it an outlier:
/// - its frequencies (`freq_ms`): Σ over its rows of |r − c|, r the relative residual and c
///   the mean of its label's over the setup's other measurements; the change is the largest
///   reduction of one row's term;
/// - its shapes (`shape_ms`, [`super::shapes`]): Σ over its rows of (x − c)⁺, x = ln(1 − MAC)
///   and c the median of its label's over the other measurements (how much further its
///   shapes are from the model's than the others'); the change is the largest change of one
///   of its modes' predicted frequencies, relative (a loose bolt's frequency drop is largely
///   absorbed by the assembly's own contact stiffness: its shapes are what set it apart).
///
/// With both kinds, the larger share left and the larger change count: each part must be
/// explained.
pub fn assemblies_part(
    before: &[ResidualObs],
    after: &[ResidualObs],
    (freq_ms, shape_ms): (&[String], &[String]),
) -> Option<(f64, f64)> {
    let key = |r: &ResidualObs| (r.measurement_id.clone(), r.label.clone());
    let refitted: BTreeSet<(String, String)> = after.iter().map(key).collect();
    let merged: Vec<&ResidualObs> = after
        .iter()
        .chain(before.iter().filter(|r| !refitted.contains(&key(r))))
        .collect();
    let before: Vec<&ResidualObs> = before.iter().collect();
    let acting = |r: &ResidualObs| {
        freq_ms.contains(&r.measurement_id) || shape_ms.contains(&r.measurement_id)
    };
    // Per row of `ms` (measurement, label), its term against the other measurements' centre
    // of `value` (None: the row has none).
    let terms = |rows: &[&ResidualObs],
                 ms: &[String],
                 value: &dyn Fn(&ResidualObs) -> Option<f64>,
                 centre: &dyn Fn(&mut Vec<f64>) -> f64,
                 term: &dyn Fn(f64, f64) -> f64|
     -> BTreeMap<(String, String), f64> {
        let setups: BTreeSet<&str> = rows
            .iter()
            .filter(|r| ms.contains(&r.measurement_id))
            .map(|r| r.setup.as_str())
            .collect();
        let mut others: BTreeMap<(&str, &str), Vec<f64>> = BTreeMap::new();
        for r in rows
            .iter()
            .filter(|r| setups.contains(r.setup.as_str()) && !acting(r))
        {
            if let Some(v) = value(r) {
                others.entry((&r.setup, &r.label)).or_default().push(v);
            }
        }
        let centres: BTreeMap<(&str, &str), f64> = others
            .into_iter()
            .map(|(k, mut v)| (k, centre(&mut v)))
            .collect();
        rows.iter()
            .filter(|r| ms.contains(&r.measurement_id))
            .filter_map(|r| {
                let c = centres.get(&(r.setup.as_str(), r.label.as_str()))?;
                Some((key(r), term(value(r)?, *c)))
            })
            .collect()
    };
    let mean = |v: &mut Vec<f64>| v.iter().sum::<f64>() / v.len() as f64;
    let median = |v: &mut Vec<f64>| crate::bayes::stats::median(v);
    let rel = |r: &ResidualObs| r.rel_residual.is_finite().then_some(r.rel_residual);
    let gap = |r: &ResidualObs| {
        r.mac
            .filter(|m| m.is_finite())
            .map(|m| (1.0 - m).max(super::shapes::MAC_GAP_FLOOR).ln())
    };
    let mut parts: Vec<(f64, f64)> = vec![];
    // Frequencies.
    let abs_dev = |x: f64, c: f64| (x - c).abs();
    let b = terms(&before, freq_ms, &rel, &mean, &abs_dev);
    let a = terms(&merged, freq_ms, &rel, &mean, &abs_dev);
    let both: Vec<(f64, f64)> = b
        .iter()
        .filter_map(|(k, x)| Some((*x, *a.get(k)?)))
        .collect();
    let total: f64 = both.iter().map(|p| p.0).sum();
    if total > 0.0 {
        parts.push((
            both.iter().map(|p| p.1).sum::<f64>() / total,
            both.iter()
                .map(|p| p.0 - p.1)
                .fold(f64::NEG_INFINITY, f64::max),
        ));
    }
    // Shapes.
    let excess = |x: f64, c: f64| (x - c).max(0.0);
    let b = terms(&before, shape_ms, &gap, &median, &excess);
    let a = terms(&merged, shape_ms, &gap, &median, &excess);
    let total: f64 = b
        .iter()
        .filter(|(k, _)| a.contains_key(*k))
        .map(|(_, x)| x)
        .sum();
    if total > 0.0 {
        let left: f64 = b.keys().filter_map(|k| a.get(k)).sum();
        let moved = |r: &&&ResidualObs| shape_ms.contains(&r.measurement_id);
        let model_before: BTreeMap<(String, String), f64> = before
            .iter()
            .filter(moved)
            .map(|r| (key(r), r.model_freq_hz_mean))
            .collect();
        let change = merged
            .iter()
            .filter(moved)
            .filter_map(|r| Some((r.model_freq_hz_mean / model_before.get(&key(r))? - 1.0).abs()))
            .filter(|v| v.is_finite())
            .fold(0.0, f64::max);
        parts.push((left / total, change));
    }
    parts
        .into_iter()
        .reduce(|x, y| (x.0.max(y.0), x.1.max(y.1)))
}

/// The largest located structured misfit, relative: the largest |mean relative residual| of
/// a located mode and the largest effect of a located covariate trend, with where it is
/// (`setup/label` or `setup/covariate`). `None` when nothing of either kind is located.
pub fn largest_structured(located: &Located) -> Option<(String, f64)> {
    let modes = located_modes(located, None);
    let covs = located
        .covariate_tests
        .iter()
        .filter(|t| t.significant)
        .map(|t| {
            (
                format!("{} trend with {}", t.setup, t.covariate),
                t.effect_rel,
            )
        });
    modes
        .chain(covs)
        .filter(|(_, v)| v.is_finite())
        .max_by(|a, b| a.1.total_cmp(&b.1))
}

/// The located modes (of `setup`, or every setup) as (`setup label`, |mean relative
/// residual|).
fn located_modes<'a>(
    located: &'a Located,
    setup: Option<&'a str>,
) -> impl Iterator<Item = (String, f64)> + 'a {
    located
        .modes
        .iter()
        .filter(move |m| setup.is_none_or(|s| m.setup == s))
        .map(|m| {
            (
                format!("{} {}", m.setup, m.label),
                m.mean_rel_residual.abs(),
            )
        })
}

/// The located mode of `setup` with the largest |mean relative residual| (`setup label`,
/// value).
pub fn largest_located_mode(located: &Located, setup: &str) -> Option<(String, f64)> {
    located_modes(located, Some(setup))
        .filter(|(_, v)| v.is_finite())
        .max_by(|a, b| a.1.total_cmp(&b.1))
}

/// The largest |mean relative residual| over every checked mode, located or not: how far
/// the model is from the boards at worst (`setup label`, value). `None` without a check.
pub fn largest_mode_misfit(located: &Located) -> Option<(String, f64)> {
    located
        .mode_checks
        .iter()
        .filter(|m| m.mean_rel_residual.is_finite())
        .map(|m| {
            (
                format!("{} {}", m.setup, m.label),
                m.mean_rel_residual.abs(),
            )
        })
        .max_by(|a, b| a.1.total_cmp(&b.1))
}

/// The share of a located covariate's trend a refit leaves: Σ over the setups where the trend
/// was located of its effect (|slope| × the covariate's range, [`locate::covariate_effects`])
/// on the refit's residuals, over the same on the baseline's. A setup the refit did not touch
/// keeps the baseline's rows. `None` when the covariate's trend was not located.
pub fn covariate_share(
    located: &Located,
    input: &locate::LocateInput,
    after: &[ResidualObs],
    covariate: &str,
    lopts: &LocateOptions,
) -> Option<f64> {
    let setups: BTreeSet<&str> = located
        .covariates
        .iter()
        .filter(|c| c.covariate == covariate)
        .map(|c| c.setup.as_str())
        .collect();
    let effect = |tests: &[locate::CovariateTest]| -> f64 {
        tests
            .iter()
            .filter(|t| t.covariate == covariate && setups.contains(t.setup.as_str()))
            .map(|t| t.effect_rel)
            .sum()
    };
    let before = effect(&located.covariate_tests);
    if setups.is_empty() || before <= 0.0 {
        return None;
    }
    let refitted: BTreeSet<&str> = after.iter().map(|r| r.setup.as_str()).collect();
    let mut merged = locate::LocateInput {
        residuals: after.to_vec(),
        ..input.clone()
    };
    merged.residuals.extend(
        input
            .residuals
            .iter()
            .filter(|r| !refitted.contains(r.setup.as_str()))
            .cloned(),
    );
    Some(effect(&locate::covariate_effects(&merged, lopts)) / before)
}

/// The parts of a located misfit, each of which some mechanism must explain: the mean shifts
/// ([`remaining_share`]) and each located covariate's trend ([`covariate_share`]). A
/// covariate mechanism is judged on its covariate's trend, every other mechanism on the mean
/// shifts: two effects at once (a temperature drift and a mass) are then two findings, each
/// explaining its part, where one share over both would make each leave the other's.
#[derive(Debug)]
pub struct MisfitParts {
    /// Share of the mean shifts each refit left (`None`: no mean shift located).
    modes: Option<Vec<f64>>,
    /// Per located covariate, the share of its trend each refit left.
    covariates: BTreeMap<String, Vec<f64>>,
}

/// The share of every part of the located misfit one refit leaves, computed once from its
/// residuals.
#[derive(Debug)]
pub struct RefitShares {
    /// Of the mean shifts (`None`: none located).
    modes: Option<f64>,
    /// Of the bolted modes' mean shifts, the part a joint mechanism acts on: a joint cannot
    /// move a free-free mode, so the free-free misfit (the model's form, a board mechanism)
    /// is not its to explain (`None`: no bolted mode located).
    bolted_modes: Option<f64>,
    /// Of the free-free modes' mean shifts, the part a board mechanism is judged on: the
    /// free-free modes are the board's alone, while the bolted ones carry the joints' misfit
    /// too (the joint model's form, a joint mechanism), which a mass or a local stiffness
    /// cannot be asked to explain (`None`: no free-free mode located).
    free_modes: Option<f64>,
    /// The largest reduction of a mean-shift mode's misfit ([`largest_reduction`]).
    modes_reduction: Option<f64>,
    /// Of each located covariate's trend: the share left, and the effect before (relative).
    covariates: BTreeMap<String, (Option<f64>, f64)>,
    /// Of the part the candidate's measurements carry ([`assemblies_part`]), for a joint
    /// mechanism acting on some assemblies only: the share left and the largest reduction.
    assemblies: Option<(f64, f64)>,
}

impl RefitShares {
    pub fn new(
        located: &Located,
        input: &locate::LocateInput,
        after: &[ResidualObs],
        lopts: &LocateOptions,
        acting_on: &[String],
    ) -> Self {
        let means = locate::mode_means(after, lopts);
        RefitShares {
            assemblies: {
                let shape: Vec<String> = acting_on
                    .iter()
                    .filter(|m| located.shape_outliers.contains(m))
                    .cloned()
                    .collect();
                let freq: Vec<String> = acting_on
                    .iter()
                    .filter(|m| !shape.contains(m))
                    .cloned()
                    .collect();
                assemblies_part(&input.residuals, after, (&freq, &shape))
            },
            modes: remaining_share(located, &means),
            bolted_modes: remaining_share_in(located, &means, Some("bolted")),
            free_modes: remaining_share_in(located, &means, Some("free")),
            modes_reduction: largest_reduction(located, &means),
            covariates: located
                .covariates
                .iter()
                .map(|c| {
                    let share = covariate_share(located, input, after, &c.covariate, lopts);
                    let before: f64 = located
                        .covariate_tests
                        .iter()
                        .filter(|t| t.covariate == c.covariate && t.significant)
                        .map(|t| t.effect_rel)
                        .fold(0.0, f64::max);
                    (c.covariate.clone(), (share, before))
                })
                .collect(),
        }
    }

    /// The candidate's own share: of its covariate's trend; for a joint mechanism acting on
    /// some assemblies only, of the part they carry ([`assemblies_part`]); of the bolted
    /// modes' mean shifts for another joint mechanism, of the free-free modes' for a board
    /// mechanism (either, when its setup has no located mode: of all the mean shifts).
    pub fn own(&self, cand: &Candidate) -> Option<f64> {
        let board = super::library::is_board_mechanism(cand.mechanism);
        match Part::of(cand) {
            Part::Covariate(c) => self.covariates.get(&c).and_then(|v| v.0),
            Part::Assemblies => self.assemblies.map(|a| a.0),
            Part::Modes if !board => self.bolted_modes.or(self.modes),
            Part::Modes => self.free_modes.or(self.modes),
        }
    }

    /// How much misfit the candidate explains, relative (for the practical threshold): of its
    /// covariate's trend, the effect it removes; for a joint mechanism acting on some
    /// assemblies only, the largest reduction of their part in one mode; else the largest
    /// reduction of a mean-shift mode's misfit.
    pub fn explained(&self, cand: &Candidate) -> Option<f64> {
        let board = super::library::is_board_mechanism(cand.mechanism);
        match &cand.covariate {
            Some(c) => self
                .covariates
                .get(c)
                .and_then(|(share, before)| share.map(|s| (1.0 - s) * before)),
            None if !board && !cand.measurements.is_empty() => self.assemblies.map(|a| a.1),
            None => self.modes_reduction,
        }
    }
}

/// The part of the located misfit a candidate is refitted for, the unit of the refit budget
/// (`--max-refits` per part): two effects at once (a temperature trend and a concealed mass)
/// are two parts, and one refit spent on the first must not leave the second unexamined.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Part {
    /// The located modes' mean shifts (a board mechanism: the free-free ones; a joint
    /// mechanism on every assembly: the bolted ones).
    Modes,
    /// The trend with this sheet column.
    Covariate(String),
    /// The outlier assemblies a per-assembly joint mechanism acts on.
    Assemblies,
}

impl Part {
    /// The part `cand` is judged on ([`RefitShares::own`]).
    pub fn of(cand: &Candidate) -> Part {
        let board = super::library::is_board_mechanism(cand.mechanism);
        match &cand.covariate {
            Some(c) => Part::Covariate(c.clone()),
            None if !board && !cand.measurements.is_empty() => Part::Assemblies,
            None => Part::Modes,
        }
    }
}

/// The refit budget: at most `per_part` refits for each [`Part`], none for a part a favoured
/// refit has already explained.
#[derive(Debug)]
pub struct RefitBudget {
    per_part: usize,
    spent: BTreeMap<Part, usize>,
}

impl RefitBudget {
    pub fn new(per_part: usize) -> Self {
        RefitBudget {
            per_part,
            spent: BTreeMap::new(),
        }
    }
    /// Whether `cand` is refitted (candidates come in the screen's order); counts it if so.
    pub fn admit(&mut self, cand: &Candidate, parts: &MisfitParts, share: f64) -> bool {
        let part = Part::of(cand);
        if parts.explained(&part, share) {
            return false;
        }
        let n = self.spent.entry(part).or_default();
        if *n >= self.per_part {
            return false;
        }
        *n += 1;
        true
    }
}

/// Whether one of the favoured refits' remaining shares `v` is at most `share`.
fn explains(v: &[f64], share: f64) -> bool {
    v.iter().any(|s| *s <= share)
}

impl MisfitParts {
    /// Whether a favoured refit left at most `share` of `part` (never for the assemblies'
    /// part, which only its own refits address).
    pub fn explained(&self, part: &Part, share: f64) -> bool {
        let done = |v: &Vec<f64>| explains(v, share);
        match part {
            Part::Modes => self.modes.as_ref().is_some_and(done),
            Part::Covariate(c) => self.covariates.get(c).is_some_and(done),
            Part::Assemblies => false,
        }
    }

    pub fn new(located: &Located) -> Self {
        MisfitParts {
            modes: remaining_share(located, &[]).map(|_| vec![]),
            covariates: located
                .covariates
                .iter()
                .map(|c| (c.covariate.clone(), vec![]))
                .collect(),
        }
    }

    /// Count a favoured refit: the share it leaves of every part.
    pub fn record_favoured(&mut self, shares: &RefitShares) {
        if let (Some(v), Some(s)) = (&mut self.modes, shares.modes) {
            v.push(s);
        }
        for (c, v) in self.covariates.iter_mut() {
            if let Some(s) = shares.covariates.get(c).and_then(|x| x.0) {
                v.push(s);
            }
        }
    }
    /// Every part explained: a favoured refit left at most `share` of it.
    pub fn all_explained(&self, share: f64) -> bool {
        let done = |v: &Vec<f64>| explains(v, share);
        self.modes.as_ref().is_none_or(done) && self.covariates.values().all(done)
    }

    /// The parts no favoured refit explained, in words (`None`: all explained).
    pub fn unexplained(&self, share: f64) -> Option<String> {
        let done = |v: &Vec<f64>| explains(v, share);
        let mut parts = vec![];
        if self.modes.as_ref().is_some_and(|v| !done(v)) {
            parts.push("the located modes' mean shifts".to_string());
        }
        for (c, v) in &self.covariates {
            if !done(v) {
                parts.push(format!("the trend with the sheet's {c}"));
            }
        }
        (!parts.is_empty()).then(|| parts.join(" and "))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(m: &str, label: &str, rel: f64) -> ResidualObs {
        ResidualObs {
            measurement_id: m.into(),
            board_id: "B".into(),
            setup: "bolted".into(),
            label: label.into(),
            freq_hz: 100.0 * (1.0 + rel),
            model_freq_hz_mean: 100.0,
            predictive_sd_hz: 0.1,
            rel_residual: rel,
            std_residual: 10.0 * rel,
            used_for_updating: true,
            mac: None,
        }
    }

    /// The predicted share is Σ|refit| / Σ|base| over the labels both centre fits have.
    #[test]
    fn the_centre_fit_share_compares_the_fits_over_the_located_labels() {
        let v = |x: &[(&str, f64)]| -> Vec<(String, f64)> {
            x.iter().map(|(l, r)| (l.to_string(), *r)).collect()
        };
        let base = v(&[("a", 0.012), ("b", -0.006), ("c", 0.5)]);
        let refit = v(&[("a", -0.003), ("b", 0.0015), ("d", 0.0)]);
        // c: not located; d: not in the baseline; the share over a and b.
        let s = centre_fit_share(&["a", "b", "d"], &base, &refit).unwrap();
        assert!((s - 0.0045 / 0.018).abs() < 1e-12, "{s}");
        assert_eq!(centre_fit_share(&["c"], &base, &refit), None);
        assert_eq!(centre_fit_share(&[], &base, &refit), None);
    }

    /// Two effects are two parts: with one refit per part, a temperature trend and the mean
    /// shifts each get theirs (in the screen's order), a second candidate for a part does
    /// not, and a part a favoured refit has explained takes none.
    #[test]
    fn the_refit_budget_is_per_part_of_the_misfit() {
        use crate::update::enrichment::Mechanism;
        let mut temp = Candidate::new(Mechanism::TemperatureStiffness, String::new());
        temp.covariate = Some("temperature_c".into());
        let rot = Candidate::new(Mechanism::JointRotation, String::new());
        let jmass = Candidate::new(Mechanism::JointMass, String::new());
        let mut loose = Candidate::new(Mechanism::JointStiffnessPerJoint, String::new());
        loose.measurements = vec!["M7".into()];
        let parts = MisfitParts {
            modes: Some(vec![]),
            covariates: [("temperature_c".to_string(), vec![])].into(),
        };
        let mut b = RefitBudget::new(1);
        let admitted: Vec<bool> = [&temp, &rot, &jmass, &loose]
            .iter()
            .map(|c| b.admit(c, &parts, 0.2))
            .collect();
        assert_eq!(admitted, [true, true, false, true]);
        let mut b = RefitBudget::new(2);
        assert!(b.admit(&rot, &parts, 0.2) && b.admit(&jmass, &parts, 0.2));
        assert!(!b.admit(&rot, &parts, 0.2));
        // The mean shifts explained (a favoured refit left 10 %): no refit for them.
        let explained = MisfitParts {
            modes: Some(vec![0.1]),
            covariates: [("temperature_c".to_string(), vec![0.5])].into(),
        };
        let mut b = RefitBudget::new(1);
        assert!(!b.admit(&rot, &explained, 0.2));
        assert!(b.admit(&temp, &explained, 0.2));
        assert!(!RefitBudget::new(0).admit(&temp, &parts, 0.2));
    }

    /// The part the outlier carries is its deviation from the other measurements' mean: a
    /// refit that brings it to the others leaves none of it, whatever their common shift; a
    /// row the refit lacks keeps the baseline's.
    #[test]
    fn the_assemblies_part_is_their_deviation_from_the_others() {
        let ms = vec!["M4".to_string()];
        let before: Vec<ResidualObs> = ["M1", "M2", "M3"]
            .iter()
            .flat_map(|m| [row(m, "a", 0.002), row(m, "b", -0.001)])
            .chain([row("M4", "a", 0.012), row("M4", "b", -0.005)])
            .collect();
        // M4 brought to the others (all shifted by the same 0.001): nothing left.
        let after: Vec<ResidualObs> = ["M1", "M2", "M3", "M4"]
            .iter()
            .flat_map(|m| [row(m, "a", 0.003), row(m, "b", 0.0)])
            .collect();
        let (share, red) = assemblies_part(&before, &after, (&ms, &[])).unwrap();
        assert!(share.abs() < 1e-12, "{share}");
        assert!((red - 0.010).abs() < 1e-12, "{red}");
        // Only M4's rows refitted, half way: half left; the others keep the baseline's.
        let half = vec![row("M4", "a", 0.007), row("M4", "b", -0.003)];
        let (share, red) = assemblies_part(&before, &half, (&ms, &[])).unwrap();
        assert!((share - 0.5).abs() < 1e-12, "{share}");
        assert!((red - 0.005).abs() < 1e-12, "{red}");
        assert_eq!(assemblies_part(&before, &after, (&[], &[])), None);
    }

    /// A shape outlier is judged on how much further its shapes are from the model's than
    /// the others' (ln(1 − MAC) above their median), and its change is the largest change of
    /// its predicted frequencies.
    #[test]
    fn a_shape_outlier_is_judged_on_its_shapes() {
        let ms = vec!["M4".to_string()];
        let with_mac = |m: &str, label: &str, mac: f64, model_hz: f64| ResidualObs {
            mac: Some(mac),
            model_freq_hz_mean: model_hz,
            ..row(m, label, 0.0)
        };
        let mut before: Vec<ResidualObs> = ["M1", "M2", "M3"]
            .iter()
            .flat_map(|m| {
                [
                    with_mac(m, "a", 0.9999, 100.0),
                    with_mac(m, "b", 0.9999, 200.0),
                ]
            })
            .collect();
        // M4's gaps 1e-3 against the others' 1e-4: ln 10 above in each mode.
        before.extend([
            with_mac("M4", "a", 0.999, 100.0),
            with_mac("M4", "b", 0.999, 200.0),
        ]);
        // Refitted: mode a back to the others' (its frequency moved 0.3 %), b half way in ln.
        let after = vec![
            with_mac("M4", "a", 0.9999, 99.7),
            with_mac("M4", "b", 1.0 - 10f64.powf(-3.5), 200.0),
        ];
        let (share, change) = assemblies_part(&before, &after, (&[], &ms)).unwrap();
        assert!((share - 0.25).abs() < 1e-9, "{share}");
        assert!((change - 0.003).abs() < 1e-9, "{change}");
        // Frequencies and shapes at once: the larger share left counts. M4's frequencies
        // 1 % off the others' before and after: all of that part is left.
        let off = |rows: &mut Vec<ResidualObs>| {
            for r in rows.iter_mut().filter(|r| r.measurement_id == "M4") {
                r.rel_residual = 0.01;
            }
        };
        let (mut before, mut after) = (before, after);
        off(&mut before);
        off(&mut after);
        let (share, _) = assemblies_part(&before, &after, (&ms, &ms)).unwrap();
        assert!((share - 1.0).abs() < 1e-12, "{share}");
    }
}

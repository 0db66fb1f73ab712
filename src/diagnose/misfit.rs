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

/// The largest located structured misfit, relative: the largest |mean relative residual| of
/// a located mode and the largest effect of a located covariate trend, with where it is
/// (`setup/label` or `setup/covariate`). `None` when nothing of either kind is located.
pub fn largest_structured(located: &Located) -> Option<(String, f64)> {
    let modes = located.modes.iter().map(|m| {
        (
            format!("{} {}", m.setup, m.label),
            m.mean_rel_residual.abs(),
        )
    });
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
}

impl RefitShares {
    pub fn new(
        located: &Located,
        input: &locate::LocateInput,
        after: &[ResidualObs],
        lopts: &LocateOptions,
    ) -> Self {
        let means = locate::mode_means(after, lopts);
        RefitShares {
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

    /// The candidate's own share: of its covariate's trend, of the bolted modes' mean shifts
    /// for a joint mechanism, of the free-free modes' for a board mechanism (either, when
    /// its setup has no located mode: of all the mean shifts).
    pub fn own(&self, cand: &Candidate) -> Option<f64> {
        match &cand.covariate {
            Some(c) => self.covariates.get(c).and_then(|v| v.0),
            None if !super::library::is_board_mechanism(cand.mechanism) => {
                self.bolted_modes.or(self.modes)
            }
            None => self.free_modes.or(self.modes),
        }
    }

    /// How much misfit the candidate explains, relative (for the practical threshold): of its
    /// covariate's trend, the effect it removes; else the largest reduction of a mean-shift
    /// mode's misfit.
    pub fn explained(&self, cand: &Candidate) -> Option<f64> {
        match &cand.covariate {
            Some(c) => self
                .covariates
                .get(c)
                .and_then(|(share, before)| share.map(|s| (1.0 - s) * before)),
            None => self.modes_reduction,
        }
    }
}

impl MisfitParts {
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
        let done = |v: &Vec<f64>| v.iter().any(|s| *s <= share);
        self.modes.as_ref().is_none_or(done) && self.covariates.values().all(done)
    }

    /// The parts no favoured refit explained, in words (`None`: all explained).
    pub fn unexplained(&self, share: f64) -> Option<String> {
        let done = |v: &Vec<f64>| v.iter().any(|s| *s <= share);
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

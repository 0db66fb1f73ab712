//! The diagnosis's decisions and its document, pure: whether the located misfit is large
//! enough to refit, whether an unexplained one is the model's form, the gates on a refit's
//! convergence, the every-joint refit's deviating joints, and `diagnosis.json` with the
//! verdict's sentences and findings ([`document`]).

use crate::diagnose::doc::{
    CandidateDoc, DiagnoseOptions, DiagnosisDoc, FindingDoc, HeldOut, LocatedSummary, Location,
};
use crate::diagnose::locate::{self, Located, ModeCheck};
use crate::diagnose::regions::BoardRegion;
use crate::diagnose::screen::{Candidate, PointLocated};
use crate::diagnose::select::{self, Compared, DeviatingJoint, Estimate, Refit, Verdict};
use crate::findings::{Finding, Findings, Severity};
use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

/// A favoured refit that leaves at most this share of the located misfit explains it, and the
/// remaining candidates are not refitted.
pub const STOP_REMAINING_SHARE: f64 = 0.2;

/// Whether the located misfit holds a structured part at or above the practical threshold
/// (relative frequency): a located mode's mean shift or a located covariate trend that large
/// ([`crate::diagnose::misfit::largest_structured`]), an outlier measurement (several modes
/// off together) or a recurring unpaired mode.
pub fn above_practical_threshold(located: &Located, threshold: f64) -> bool {
    located.any
        && (crate::diagnose::misfit::largest_structured(located)
            .is_some_and(|(_, v)| v >= threshold)
            || !located.measurements.is_empty()
            || !located.unpaired_clusters.is_empty())
}

/// Whether an unexplained misfit has the pattern of the model's form rather than of a
/// concealed effect: it is in the free-free modes (the board itself, whatever its mounting),
/// or, in the bolted modes alone, within the bolted model's stated fidelity
/// ([`crate::bayes::discrepancy::BOLTED_FIDELITY_FREQ`], the paper's validation error of its
/// bolted model) in every located mode ([`bolted_within_fidelity`]),
/// the localisation places it nowhere on the board (no located region whose 90 % radius is
/// within `region_limit_m`: a region spanning the board is no place), and nothing singles out
/// a measurement, a covariate or an unpaired mode. Boards that differ from one another (the
/// `board_id` covariate) do not count against it: the discrepancy's per-unit part is the
/// model's form erring differently on each board. A concealed effect leaves one of those
/// marks: a joint's only in bolted modes, a mass or a local stiffening a region, a drift a
/// covariate trend, a loose bolt its measurements, a fixture its own mode. Outlier
/// measurements that are every measurement of their boards in a setup
/// (`boards_only_outliers`, [`whole_board_outliers`]) are those boards differing from the
/// others, the same per-unit part. The stage's limit is a quarter of the board's shorter
/// side (12.5 mm on the 80 × 50 mm board).
///
/// Outlier bolted measurements in `joint_form` ([`joint_form_outliers`]) are the joint model's
/// per-assembly form, the same argument one level down: with no located mode beside them they
/// are the bolted form by themselves, and `boards_only_outliers` is then judged on the other
/// outliers.
pub fn model_form_pattern(
    located: &Located,
    regions: &[BoardRegion],
    region_limit_m: f64,
    boards_only_outliers: bool,
    joint_form: &[String],
) -> bool {
    let bolted_form =
        bolted_within_fidelity(located) || (located.modes.is_empty() && !joint_form.is_empty());
    (free_modes_located(located) || bolted_form)
        && !regions
            .iter()
            .any(|r| r.located && r.fit.region_radius_m <= region_limit_m)
        && located
            .covariates
            .iter()
            .all(|c| c.covariate == crate::diagnose::locate::BOARD_COVARIATE)
        && (located.measurements.iter().all(|m| joint_form.contains(m)) || boards_only_outliers)
        && located.unpaired_clusters.is_empty()
}

/// The outlier measurements that are the joint model's per-assembly form rather than a
/// concealed effect: bolted, every mode within the bolted model's stated fidelity of the other
/// assemblies ([`crate::bayes::discrepancy::BOLTED_FIDELITY_FREQ`], centred residuals), and
/// screened by the per-assembly joint screen (`screens`), which found the data against its
/// joints having stiffnesses of their own (ln B < 0) and no joint apart.
///
/// The joint model gives an assembly one contact stiffness over each clamped annulus. Real
/// joints of one assembly differ from each other and from the model's contact (preload
/// scatter of torque-tightened bolts, seating, the contact's pressure and slip), so each
/// assembly's modes scatter about the others' by a pattern its one stiffness cannot take up;
/// the same form that shifts every assembly alike ([`bolted_within_fidelity`]), erring
/// differently on each. The concealed effects that single out assemblies (a loose bolt, a
/// missing washer) are joints apart, which the screen tests for; an outlier it clears, within
/// the stated fidelity, is left to the form. Beyond the fidelity, or unscreened, it stays
/// unexplained.
pub fn joint_form_outliers(
    located: &Located,
    screens: &[&crate::update::joint_screen::JointScreen],
) -> Vec<String> {
    let cleared = |m: &str| {
        screens.iter().any(|s| {
            s.failed.is_none()
                && s.log_bayes_factor.is_some()
                && s.units.iter().any(|u| {
                    u.measurement_id == m && u.log_bayes_factor < 0.0 && u.deviating_joint.is_none()
                })
        })
    };
    let within = |m: &str| {
        located
            .measurement_checks
            .iter()
            .find(|c| c.measurement_id == m && c.setup == "bolted")
            .is_some_and(|c| {
                c.residuals.iter().all(|r| {
                    r.centred_rel_residual.abs() <= crate::bayes::discrepancy::BOLTED_FIDELITY_FREQ
                })
            })
    };
    located
        .measurements
        .iter()
        .filter(|m| within(m) && cleared(m))
        .cloned()
        .collect()
}

/// Whether a free-free mode is among the located ones: the misfit is the board's own.
fn free_modes_located(located: &Located) -> bool {
    located.modes.iter().any(|m| m.setup == "free")
}

/// Whether the located modes are bolted ones alone, each mean shift within the bolted model's
/// stated fidelity. A misfit common to every assembly in the bolted modes is what the joint
/// model's form leaves (contact as springs over the clamped annulus, against a real contact's
/// pressure and slip), and what a joint effect common to every assembly leaves too. The
/// library's joint mechanisms are the candidates for the second; when none is favoured, what
/// remains within the fidelity the bolted model is stated to have is that model performing as
/// stated, and beyond it the misfit stays unexplained.
pub fn bolted_within_fidelity(located: &Located) -> bool {
    !located.modes.is_empty()
        && located.modes.iter().all(|m| {
            m.setup != "free"
                && m.mean_rel_residual.abs() <= crate::bayes::discrepancy::BOLTED_FIDELITY_FREQ
        })
}

/// `Some(boards)` when every outlier measurement is its board's rather than its own: one of
/// all the measurements (at least two) of its board in its setup, those boards differing from
/// the others (`board_id` located in that setup), or an outlier whose board's other
/// measurements share its deviation ([`Located::board_shared`]). The repeat measurements of a
/// board agree with each other; the board itself is off the population, as `(setup, board)`
/// pairs. `Some(empty)` without outliers; `None` when some outlier stands apart from its
/// board's other measurements (a measurement's own problem: a loose bolt, a drift, a slip).
pub fn whole_board_outliers(
    located: &Located,
    measurements: &[locate::MeasurementInfo],
) -> Option<Vec<(String, String)>> {
    let off: BTreeSet<&str> = located.measurements.iter().map(|m| m.as_str()).collect();
    let shared: BTreeSet<&str> = located.board_shared.iter().map(|m| m.as_str()).collect();
    // (setup, board) → (measurements, outliers, outliers its board shares).
    let mut per_board: BTreeMap<(&str, &str), (usize, usize, usize)> = BTreeMap::new();
    for m in measurements {
        let e = per_board
            .entry((m.setup.as_str(), m.board_id.as_str()))
            .or_default();
        let id = m.measurement_id.as_str();
        e.0 += 1;
        e.1 += usize::from(off.contains(id));
        e.2 += usize::from(off.contains(id) && shared.contains(id));
    }
    let board_located = |setup: &str| {
        located
            .covariates
            .iter()
            .any(|c| c.setup == setup && c.covariate == crate::diagnose::locate::BOARD_COVARIATE)
    };
    let mut boards = vec![];
    for ((setup, board), (n, n_off, n_shared)) in per_board {
        if n_off == 0 {
            continue;
        }
        let whole = n_off == n && n >= 2 && board_located(setup);
        if !(whole || n_shared == n_off) {
            return None;
        }
        boards.push((setup.to_string(), board.to_string()));
    }
    Some(boards)
}

/// The `q` quantile of sorted values, numpy's default (linear) interpolation.
pub fn quantile(sorted: &[f64], q: f64) -> f64 {
    let h = (sorted.len() - 1) as f64 * q;
    let (lo, hi) = (h.floor() as usize, h.ceil() as usize);
    sorted[lo] + (h - lo as f64) * (sorted[hi] - sorted[lo])
}

/// The R-hat across runs above which a refit's evidence gives no Bayes factor: 1.1, the
/// classical threshold of Gelman & Rubin's diagnostic (Gelman et al., Bayesian Data Analysis,
/// 3rd ed., §11.5). Up to it the runs' spread of the log evidence is its standard error; above
/// it, runs that sampled different parts of the posterior may each miss mass the others saw.
/// The updating's own level (1.05) still marks the refit's estimates approximate; the stage
/// retries a refit with more particles and runs above this level, or above 1.05 on the
/// mechanism's own parameters (`stage::diagnose::refit::retry_rule`).
pub const MAX_R_HAT_EVIDENCE: f64 = 1.1;

/// The gate on a refit step's worst population-level R-hat (parameter, value) in `dir`: why
/// its evidence gives no Bayes factor (above [`MAX_R_HAT_EVIDENCE`]), or why its estimates
/// are approximate (above `max_r_hat`, the updating's own convergence level).
pub fn r_hat_gate(
    worst: Option<(String, f64)>,
    dir: &Path,
    max_r_hat: f64,
) -> (Option<String>, Option<String>) {
    match worst {
        Some((name, r)) if r > MAX_R_HAT_EVIDENCE => (
            Some(format!(
                "sampler not converged: R-hat across runs of {name} {r:.3} > {MAX_R_HAT_EVIDENCE} in {}, so its evidence gives no Bayes factor",
                dir.display()
            )),
            None,
        ),
        Some((name, r)) if r > max_r_hat => (
            None,
            Some(format!(
                "approximate: the runs disagree a little (R-hat of {name} {r:.3} > {max_r_hat})"
            )),
        ),
        _ => (None, None),
    }
}

/// A joint deviates in a measurement when the 90 % interval of its stiffness over the mean
/// of the others' lies entirely below `DEVIATING_RATIO` or entirely above its inverse. The joints of one correctly torqued
/// assembly differ by a few per cent to ~10 % (contact-stiffness scatter); a loose bolt or a
/// missing washer changes one by a factor of 1.5 or more. 0.8 sits between: a mere scatter
/// never reaches it, and a bolt at two thirds of the others' still does.
pub const DEVIATING_RATIO: f64 = 0.8;

/// The every-joint refit of `joint_stiffness_per_joint` (per measurement each joint's
/// k_ratio_<j> draws, `by`): per measurement, the joint with the largest |ln median ratio|,
/// when it deviates (`DEVIATING_RATIO`) or the measurement is one of locate's outliers; as
/// estimates (parameter k_ratio_<j>, scope "measurement <id>") and as deviating joints (only
/// those that deviate).
pub fn every_joint_estimates(
    by: BTreeMap<String, Vec<Vec<f64>>>,
    board: &crate::fem::Board,
    outliers: &[String],
) -> (Vec<Estimate>, Vec<DeviatingJoint>) {
    let n = board.holes.len();
    let (mut est, mut dev) = (vec![], vec![]);
    for (m, mut per) in by {
        let q: Vec<(f64, f64, f64)> = per
            .iter_mut()
            .map(|v| {
                v.sort_by(f64::total_cmp);
                (quantile(v, 0.5), quantile(v, 0.05), quantile(v, 0.95))
            })
            .collect();
        let Some(j) = (0..n).max_by(|&a, &b| q[a].0.ln().abs().total_cmp(&q[b].0.ln().abs()))
        else {
            continue;
        };
        let (med, lo, hi) = q[j];
        let deviates = hi < DEVIATING_RATIO || lo > 1.0 / DEVIATING_RATIO;
        if !(deviates || outliers.contains(&m)) {
            continue;
        }
        est.push(Estimate {
            parameter: format!("k_ratio_{}", j + 1),
            scope: format!("measurement {m}"),
            median: med,
            q05: lo,
            q95: hi,
        });
        if deviates {
            dev.push(DeviatingJoint {
                measurement_id: m,
                joint: j + 1,
                x_m: board.holes[j].x_m,
                y_m: board.holes[j].y_m,
                ratio_median: med,
                ratio_q05: lo,
                ratio_q95: hi,
            });
        }
    }
    (est, dev)
}

/// The every-joint candidate judged on its per-assembly screen: per screened assembly, the
/// joint whose ratio to the others' is furthest from 1 as an estimate (parameter
/// k_ratio_<j>, scope "measurement <id>, per-assembly screen"), and the joint the screen
/// names as deviating (its interval excludes 1 and it moves a mode by the practical
/// threshold), if any.
pub fn screen_estimates(
    js: &crate::update::joint_screen::JointScreen,
    board: &crate::fem::Board,
) -> (Vec<Estimate>, Vec<DeviatingJoint>) {
    let (mut est, mut dev) = (vec![], vec![]);
    for u in &js.units {
        let furthest = u.joints.iter().max_by(|a, b| {
            a.ratio_median
                .ln()
                .abs()
                .total_cmp(&b.ratio_median.ln().abs())
        });
        let Some(j) = u
            .deviating_joint
            .and_then(|d| u.joints.get(d - 1))
            .or(furthest)
        else {
            continue;
        };
        est.push(Estimate {
            parameter: format!("k_ratio_{}", j.joint),
            scope: format!("measurement {}, per-assembly screen", u.measurement_id),
            median: j.ratio_median,
            q05: j.ratio_q05,
            q95: j.ratio_q95,
        });
        if u.deviating_joint == Some(j.joint) {
            let h = &board.holes[j.joint - 1];
            dev.push(DeviatingJoint {
                measurement_id: u.measurement_id.clone(),
                joint: j.joint,
                x_m: h.x_m,
                y_m: h.y_m,
                ratio_median: j.ratio_median,
                ratio_q05: j.ratio_q05,
                ratio_q95: j.ratio_q95,
            });
        }
    }
    (est, dev)
}

/// One row of the diagnosis: a screened candidate, with its refit's comparison when it had
/// one.
#[derive(Clone, Debug)]
pub struct Row {
    pub cand: Candidate,
    pub cmp: Option<Compared>,
}

impl Row {
    /// The held-out bolted error before (or `after`) the refit, percent.
    pub fn held_out_bolted(&self, after: bool) -> Option<f64> {
        self.cmp.as_ref().and_then(|c| {
            c.held_out_before_after
                .iter()
                .find(|(s, _, _)| s == "bolted")
                .map(|(_, b, a)| if after { *a } else { *b })
        })
    }

    /// The refit's first estimate.
    pub fn first_estimate(&self) -> Option<Estimate> {
        self.cmp
            .as_ref()
            .and_then(|c| c.refit.estimates.first().cloned())
    }
}

/// Rows: refitted candidates in the order of `compare`, then the screened ones not refitted.
pub fn rows(candidates: &[Candidate], compared: &[Compared]) -> Vec<Row> {
    let mut rows: Vec<Row> = vec![];
    for c in compared {
        if let Some(cand) = candidates
            .iter()
            .find(|k| Some(k.mechanism) == c.refit.mechanism && k.joint == c.refit.joint)
        {
            rows.push(Row {
                cand: cand.clone(),
                cmp: Some(c.clone()),
            });
        }
    }
    for k in candidates {
        if !rows.iter().any(|r| r.cand.id() == k.id()) {
            rows.push(Row {
                cand: k.clone(),
                cmp: None,
            });
        }
    }
    rows
}

/// A row's sentence: the refit's, or why the candidate was screened and not refitted.
pub fn sentence(r: &Row) -> String {
    match &r.cmp {
        Some(c) => select::sentence(c),
        None => format!(
            "Candidate: {} (screened: {}; not refitted{})",
            r.cand.mechanism.description(),
            r.cand.reason,
            if r.cand.refittable() {
                ""
            } else {
                ": this mechanism has no refit yet"
            }
        ),
    }
}

/// A favoured row's finding.
fn finding_doc(r: &Row) -> Option<FindingDoc> {
    let c = r.cmp.as_ref().filter(|c| c.favoured)?;
    Some(FindingDoc {
        mechanism: r.cand.mechanism,
        location: match (
            r.cand.joint,
            r.cand.joint_xy_m,
            c.refit.point_xy_m.or(r.cand.point_xy_m),
        ) {
            // The every-joint refit: the joint that deviates in the most measurements
            // (all of them in the estimates and the sentence).
            (None, None, None) if !c.refit.deviating_joints.is_empty() => {
                select::main_deviating_joint(&c.refit.deviating_joints).map(|d| Location {
                    joint: Some(d.joint),
                    x_m: d.x_m,
                    y_m: d.y_m,
                })
            }
            (Some(joint), Some([x_m, y_m]), _) => Some(Location {
                joint: Some(joint),
                x_m,
                y_m,
            }),
            (None, _, Some([x_m, y_m])) => Some(Location {
                joint: None,
                x_m,
                y_m,
            }),
            _ => None,
        },
        covariate: r.cand.covariate.clone(),
        estimates: c.refit.estimates.clone(),
        log_bayes_factor: c.log_bayes_factor,
        log_bayes_factor_se: c.log_bayes_factor_se,
        held_out_error: held_out_doc(&c.held_out_before_after),
        held_out_error_outliers: held_out_doc(&c.held_out_outliers_before_after),
        refit_dir: c.refit.dir.clone(),
        sentence: select::sentence(c),
    })
}

/// `remaining_discrepancy` of `diagnosis.json`: what the verdict leaves unexplained, in words.
pub fn remaining_discrepancy(
    (verdict, model_form): (Verdict, &str),
    (located, boards_off, joint_form): (&Located, &[(String, String)], &[String]),
    board_regions: &[BoardRegion],
    threshold: f64,
    largest: &Option<(String, f64)>,
    unexplained: &Option<String>,
) -> String {
    match verdict {
    Verdict::NoMissingPhysics => match &largest {
        Some((at, v)) => format!(
            "none: the model differs from these boards by at most {:.3} % ({at}){}; below the {:.2} % practical threshold, and included in the predicted intervals as the model-form discrepancy",
            100.0 * v,
            if located.any {
                " (statistically located, practically small)"
            } else {
                ""
            },
            100.0 * threshold
        ),
        None => "none: no setup, mode, measurement or covariate misfits beyond the tolerance".to_string(),
    },
    Verdict::MechanismFound => match &unexplained {
        Some(p) => format!("{p}: no favoured mechanism explains this part of the located misfit (none leaves at most {:.0} % of it); the favoured refits' residuals are in their directories (`dir`: refits/<id>, or refits/<id>/screen for a candidate judged on its screen), the located evidence below is the baseline's", 100.0 * STOP_REMAINING_SHARE),
        None => "see the best candidate's refit residuals (residuals.parquet in its `dir`: refits/<id>, or refits/<id>/screen for a candidate judged on its screen); the located evidence below is the baseline's".to_string(),
    },
    Verdict::ModelForm => {
        let (at, v) = crate::diagnose::misfit::largest_structured(located)
            .unwrap_or_else(|| ("?".into(), f64::NAN));
        // The outliers the form accounts for: whole boards, then single assemblies.
        let mut outliers = vec![];
        if !boards_off.is_empty() {
            outliers.push(format!(
                "the outlier measurements are every measurement of {} (their repeat measurements agree, the boards themselves differ from the others beyond the model's parameters: the per-board part of the same form)",
                boards_off
                    .iter()
                    .map(|(s, b)| format!("{b} ({s})"))
                    .collect::<Vec<_>>()
                    .join(", ")
            ));
        }
        if !joint_form.is_empty() {
            outliers.push(joint_form_clause(joint_form));
        }
        let boards = if outliers.is_empty() {
            "with no covariate trend, outlier measurement or unpaired mode".to_string()
        } else {
            format!(
                "with no covariate trend or unpaired mode; {}",
                outliers.join("; and ")
            )
        };
        let modes = located
            .modes
            .iter()
            .map(|m| format!("{}/{}", m.setup, m.label))
            .collect::<Vec<_>>();
        if free_modes_located(located) {
            // The free-free form's size is quoted from the free-free modes: the bolted ones
            // carry the joint model's form too.
            let (at, v) =
                crate::diagnose::misfit::largest_located_mode(located, "free").unwrap_or((at, v));
            format!(
                "model form: the model differs from every board alike by up to {:.3} % ({at}), above the {:.2} % practical threshold, in the free-free modes (the board itself, whatever its mounting), placed nowhere on the board, and {boards}: the form of the model ({model_form}), not a concealed effect. It is in the predicted intervals as the model-form discrepancy; a richer model would narrow them. Located modes: {modes:?}",
                100.0 * v,
                100.0 * threshold,
            )
        } else if located.modes.is_empty() {
            format!(
                "model form: no mode is off for every assembly alike, {boards}; no joint mechanism of the library refitted explains them: the form of the joint model, or a joint effect outside the library, which these data cannot tell apart",
            )
        } else {
            format!(
                "model form: the bolted model differs from every assembly alike by up to {:.3} % ({at}), above the {:.2} % practical threshold but within the {:.1} % its joint model is stated to hold (the paper's validation error of its bolted model), in the bolted modes alone, and {boards}; no joint mechanism of the library refitted explains it: the form of the joint model (the contact as springs over the clamped annulus), or a joint effect outside the library, which these data cannot tell apart. Located modes: {modes:?}",
                100.0 * v,
                100.0 * threshold,
                100.0 * crate::bayes::discrepancy::BOLTED_FIDELITY_FREQ,
            )
        }
    }
    Verdict::UnexplainedMisfit => format!(
        "located but not explained by any refitted mechanism: setups {:?}, modes {:?}, measurements {:?}, covariates {:?}{}{}",
        located.setups,
        located.modes.iter().map(|m| format!("{}/{}", m.setup, m.label)).collect::<Vec<_>>(),
        located.measurements,
        located.covariates.iter().map(|c| format!("{}/{}", c.setup, c.covariate)).collect::<Vec<_>>(),
        shape_outlier_clause(located),
        board_regions
            .iter()
            .filter(|r| r.located)
            .map(|r| format!("; where on the board: {}", r.sentence))
            .collect::<String>()
    ),
}
}

/// The joint model's per-assembly form ([`joint_form_outliers`]), in words.
fn joint_form_clause(joint_form: &[String]) -> String {
    format!(
        "the outlier bolted measurement(s) {} stand apart from the other assemblies within the {:.1} % the joint model is stated to hold, and the per-assembly joint screen finds no joint of theirs apart (the data are against their joints having stiffnesses of their own): the joint model's per-assembly form (one contact stiffness per assembly), erring differently on each assembly",
        joint_form.join(", "),
        100.0 * crate::bayes::discrepancy::BOLTED_FIDELITY_FREQ
    )
}

/// Held-out errors before → after as the document gives them.
fn held_out_doc(v: &[(String, f64, f64)]) -> Vec<HeldOut> {
    v.iter()
        .map(|(setup, b, a)| HeldOut {
            setup: setup.clone(),
            before_percent: *b,
            after_percent: *a,
        })
        .collect()
}

/// The outliers by their mode shapes, in words ("" without any): in a bolted setup the
/// assemblies a loose or mis-seated joint would single out.
fn shape_outlier_clause(located: &Located) -> String {
    let ids: Vec<String> = located
        .shape_checks
        .iter()
        .filter(|c| c.outlier)
        .map(|c| format!("{} ({}, {})", c.measurement_id, c.board_id, c.setup))
        .collect();
    if ids.is_empty() {
        return String::new();
    }
    format!(
        "; {} measurement(s) stand apart by their mode shapes, every mode further from the model's than in the setup's other measurements (a joint seated differently in those assemblies would do it): {}",
        ids.len(),
        ids.join(", ")
    )
}

/// The stage's findings of the verdict: the verdict itself (unless no missing physics), a
/// remaining discrepancy, the location searches' notes and the identification outliers.
pub fn verdict_findings(
    findings: &mut Findings,
    (verdict, remaining, unexplained): (Verdict, &str, &Option<String>),
    rows: &[Row],
    compared: &[Compared],
    located: &Located,
) {
    if verdict != Verdict::NoMissingPhysics {
        findings.push(Finding::new(
            Severity::Warning,
            match verdict {
                Verdict::MechanismFound => "diagnose.mechanism_found",
                Verdict::ModelForm => "diagnose.model_form",
                _ => "diagnose.unexplained_misfit",
            },
            if verdict == Verdict::ModelForm {
                remaining.to_string()
            } else {
                rows.first()
                    .map(sentence)
                    .unwrap_or_else(|| remaining.to_string())
            },
        ));
    }
    if let (Verdict::MechanismFound, Some(p)) = (verdict, &unexplained) {
        findings.push(Finding::new(
            Severity::Warning,
            "diagnose.remaining_discrepancy",
            format!("besides the mechanism(s) found, {p} remain(s) unexplained: {remaining}"),
        ));
    }
    for c in compared {
        if let Some(note) = &c.refit.location_note {
            findings.push(Finding::new(
                Severity::Warning,
                "diagnose.location_search",
                format!("{}: {note}", c.refit.dir),
            ));
        }
    }
    for o in &located.identification_outliers {
        findings.push(Finding::new(
            Severity::Warning,
            "diagnose.identification_outlier",
            format!(
                "{} ({}, {}): mode {} is {:+.3} % off the other measurements (t {:.1} beyond the {:.2} % tolerance) while its other modes agree with them (p {:.2}); a slip of the modal fit is likelier than missing physics, which moves several modes together. Check its stabilization diagram; not counted as misfit",
                o.measurement_id,
                o.board_id,
                o.setup,
                o.label,
                100.0 * o.centred_rel_residual,
                o.z,
                100.0 * located.options.tolerance_rel,
                o.p_value_other_modes
            ),
        ));
    }
}

/// `diagnosis.json`, and the stage's findings with the verdict's (see [`verdict_findings`]).
#[allow(clippy::too_many_arguments)]
pub fn document(
    opts: &DiagnoseOptions,
    (located, above, boards_off, joint_form): (&Located, bool, &[(String, String)], &[String]),
    (board_regions, board_regions_note): (Vec<BoardRegion>, String),
    rows: &[Row],
    compared: &[Compared],
    (verdict, model_form): (Verdict, &str),
    unexplained: Option<String>,
    findings: &mut Findings,
) -> DiagnosisDoc {
    let findings_doc: Vec<FindingDoc> = rows.iter().filter_map(finding_doc).collect();
    let threshold = opts.select.practical_threshold_rel;
    let largest = crate::diagnose::misfit::largest_mode_misfit(located);
    let remaining = remaining_discrepancy(
        (verdict, model_form),
        (located, boards_off, joint_form),
        &board_regions,
        threshold,
        &largest,
        &unexplained,
    );
    verdict_findings(
        findings,
        (verdict, &remaining, &unexplained),
        rows,
        compared,
        located,
    );
    DiagnosisDoc {
        verdict,
        located: LocatedSummary {
            any: located.any,
            above_practical_threshold: above,
            largest_mode_misfit: largest.clone(),
            setups: located.setups.clone(),
            modes: located.modes.clone(),
            measurements: located.measurements.clone(),
            shape_outliers: located
                .shape_checks
                .iter()
                .filter(|c| c.outlier)
                .cloned()
                .collect(),
            identification_outliers: located.identification_outliers.clone(),
            covariates: located.covariates.clone(),
            unpaired_clusters: located.unpaired_clusters.clone(),
            never_seen: located.never_seen.clone(),
            board_regions,
            board_regions_note,
        },
        findings: findings_doc,
        candidates: rows
            .iter()
            .map(|r| CandidateDoc {
                id: r.cand.id(),
                candidate: r.cand.clone(),
                refit: r.cmp.clone(),
                sentence: sentence(r),
            })
            .collect(),
        remaining_discrepancy: remaining,
        options: opts.clone(),
        checks: located.clone(),
        stage_findings: findings.0.clone(),
    }
}

/// The rows of `diagnosis_modes.parquet`: the baseline's mode checks, then each refit's
/// (`refits`: its id and its mode means), each with whether the baseline located the mode.
pub fn mode_rows(
    located: &Located,
    refits: Vec<(String, Vec<ModeCheck>)>,
) -> Vec<(String, ModeCheck, bool)> {
    let mut mode_rows: Vec<(String, ModeCheck)> = located
        .mode_checks
        .iter()
        .map(|m| ("baseline".to_string(), m.clone()))
        .collect();
    for (id, checks) in refits {
        mode_rows.extend(checks.into_iter().map(|m| (id.clone(), m)));
    }
    let is_located = |m: &ModeCheck| {
        located
            .modes
            .iter()
            .any(|l| l.setup == m.setup && l.label == m.label)
    };
    mode_rows
        .into_iter()
        .map(|(k, m)| {
            let l = is_located(&m);
            (k, m, l)
        })
        .collect()
}

/// A refit of a point the localisation chose from the data: its Occam factor joins the
/// evidence, and its uncertainty the mass's interval (the refit's is conditional on the
/// point).
pub fn with_located_point(r: &mut Refit, pl: PointLocated, point_xy_m: Option<[f64; 2]>) {
    r.log_evidence_runs
        .iter_mut()
        .for_each(|z| *z += pl.log_occam);
    r.log_location_occam = Some(pl.log_occam);
    r.point_xy_m = point_xy_m;
    for e in r.estimates.iter_mut() {
        let z = 1.645 * pl.location_ln_mass_sd;
        let lo = (e.median / e.q05).ln().hypot(z);
        let hi = (e.q95 / e.median).ln().hypot(z);
        e.q05 = e.median * (-lo).exp();
        e.q95 = e.median * hi.exp();
        e.scope = format!(
            "{}; 90 % interval widened by the location's uncertainty (sd of ln mass {:.3})",
            e.scope, pl.location_ln_mass_sd
        );
    }
}

#[cfg(test)]
mod tests {
    use super::{
        above_practical_threshold, model_form_pattern, shape_outlier_clause, whole_board_outliers,
    };
    use crate::diagnose::library::Mechanism;
    use crate::diagnose::locate::{self, LocateInput, LocateOptions, LocatedMode};
    use crate::diagnose::regions::tests::region;

    /// The unexplained verdict names the assemblies that stand apart by their shapes.
    #[test]
    fn the_shape_outliers_are_named() {
        let mut loc = locate::locate(&LocateInput::default(), &LocateOptions::default());
        assert_eq!(shape_outlier_clause(&loc), "");
        let check = |id: &str, outlier: bool| crate::diagnose::shapes::ShapeCheck {
            measurement_id: id.into(),
            board_id: "PCB-04".into(),
            setup: "bolted".into(),
            n_modes: 5,
            z: Some(9.0),
            p_value: Some(1e-9),
            q_value: Some(1e-8),
            outlier,
            single_mode: None,
            board_shared: false,
            modes: vec![],
        };
        loc.shape_checks = vec![check("M059", true), check("M058", false)];
        let s = shape_outlier_clause(&loc);
        assert!(
            s.contains("1 measurement(s)") && s.contains("M059 (PCB-04, bolted)"),
            "{s}"
        );
        assert!(!s.contains("M058"), "{s}");
    }

    /// A located mean shift counts as a finding only at or above the practical threshold;
    /// an unexplained free-free misfit placed nowhere on the board is the model's form, and a
    /// located region or an outlier measurement is not; a bolted-only one is within the
    /// bolted model's stated fidelity.
    #[test]
    fn the_practical_threshold_and_the_model_form_pattern() {
        let mut loc = locate::locate(&LocateInput::default(), &LocateOptions::default());
        let shift = |setup: &str, r: f64| LocatedMode {
            setup: setup.into(),
            label: "plate-2-2".into(),
            mean_rel_residual: r,
            reasons: vec!["mean_shift".into()],
        };
        assert!(!above_practical_threshold(&loc, 3e-3), "nothing located");
        loc.any = true;
        loc.modes = vec![shift("free", -0.0011)];
        assert!(!above_practical_threshold(&loc, 3e-3), "0.11 % < 0.3 %");
        assert!(above_practical_threshold(&loc, 1e-3));
        loc.modes.push(shift("bolted", 0.007));
        assert!(above_practical_threshold(&loc, 3e-3));
        assert!(model_form_pattern(&loc, &[], 0.0125, false, &[]));
        // The free-free form is quoted from the free-free modes (0.11 %), not from the bolted
        // ones (0.7 %), which carry the joint model's form too.
        let said = super::remaining_discrepancy(
            (crate::diagnose::select::Verdict::ModelForm, "a thin plate"),
            (&loc, &[], &[]),
            &[],
            1e-3,
            &None,
            &None,
        );
        assert!(said.contains("by up to 0.110 % (free plate-2-2)"), "{said}");
        // A region of 10 mm places the misfit; one spanning the board does not.
        let placed = region(Mechanism::AddedMass, 0.9, None);
        assert!(!model_form_pattern(
            &loc,
            std::slice::from_ref(&placed),
            0.0125,
            false,
            &[]
        ));
        let mut wide = placed;
        wide.fit.region_radius_m = 0.055;
        assert!(model_form_pattern(&loc, &[wide], 0.0125, false, &[]));
        let mut one = loc.clone();
        one.measurements = vec!["M040".into()];
        assert!(!model_form_pattern(&one, &[], 0.0125, false, &[]));
        // Boards that differ are the per-unit discrepancy's; a temperature trend is not.
        let cov = |name: &str| locate::LocatedCovariate {
            setup: "free".into(),
            covariate: name.into(),
            q_value: 1e-6,
            slope_rel_per_unit: None,
            unit: String::new(),
        };
        let mut boards = loc.clone();
        boards.covariates = vec![cov("board_id")];
        assert!(model_form_pattern(&boards, &[], 0.0125, false, &[]));
        boards.covariates.push(cov("temperature_c"));
        assert!(!model_form_pattern(&boards, &[], 0.0125, false, &[]));
        // A bolted-only misfit common to every assembly is the joint model's form within the
        // bolted model's stated fidelity (1.5 %), and unexplained beyond it or with an
        // outlier assembly.
        let mut bolted = loc.clone();
        bolted.modes.remove(0);
        assert!(model_form_pattern(&bolted, &[], 0.0125, false, &[]));
        bolted.modes.push(shift("bolted", -0.016));
        assert!(!super::bolted_within_fidelity(&bolted));
        assert!(!model_form_pattern(&bolted, &[], 0.0125, false, &[]));
        bolted.modes.pop();
        bolted.measurements = vec!["M040".into()];
        assert!(!model_form_pattern(&bolted, &[], 0.0125, false, &[]));

        // Outliers that are all of a board's measurements (with boards located as differing)
        // are the board; one that stands apart from its board's other measurements is not.
        let info = |m: &str, b: &str| locate::MeasurementInfo {
            measurement_id: m.into(),
            board_id: b.into(),
            setup: "free".into(),
        };
        let ms = [
            info("M1", "B1"),
            info("M2", "B1"),
            info("M3", "B2"),
            info("M4", "B2"),
        ];
        let mut whole = loc.clone();
        whole.covariates = vec![cov("board_id")];
        whole.measurements = vec!["M1".into(), "M2".into()];
        assert_eq!(
            whole_board_outliers(&whole, &ms),
            Some(vec![("free".to_string(), "B1".to_string())])
        );
        assert!(model_form_pattern(&whole, &[], 0.0125, true, &[]));
        whole.measurements = vec!["M1".into()];
        assert_eq!(whole_board_outliers(&whole, &ms), None);
        whole.measurements = vec!["M1".into(), "M2".into()];
        whole.covariates.clear();
        assert_eq!(
            whole_board_outliers(&whole, &ms),
            None,
            "boards not located as differing"
        );
        whole.measurements.clear();
        assert_eq!(whole_board_outliers(&whole, &ms), Some(vec![]));
    }

    /// An outlier assembly within the bolted model's stated fidelity that the per-assembly
    /// joint screen clears (ln B < 0, no joint apart) is the joint model's per-assembly form;
    /// one beyond the fidelity, one the screen finds a joint apart in or favours, a free-free
    /// one and an unscreened one are not.
    #[test]
    fn outlier_assemblies_the_joint_screen_clears_are_the_joint_models_form() {
        use crate::diagnose::select::Verdict;
        use crate::update::joint_screen::{JointScreen, ScreenUnit};
        let mut loc = locate::locate(&LocateInput::default(), &LocateOptions::default());
        let res = |label: &str, c: f64| locate::MeasurementResidual {
            label: label.into(),
            rel_residual: c,
            centred_rel_residual: c,
            z: 6.8,
            df: 18.0,
        };
        let check = |id: &str, setup: &str, c: f64| locate::MeasurementCheck {
            measurement_id: id.into(),
            board_id: "PCB-05".into(),
            setup: setup.into(),
            n_modes: 2,
            chi2: 95.7,
            p_value: Some(1e-19),
            q_value: Some(1e-17),
            outlier: true,
            single_mode: None,
            left_out_of_scale: true,
            residuals: vec![res("plate-0-0", c), res("plate-1-0", 0.002)],
        };
        let ids = ["M063", "M043", "M010", "M050", "M051"];
        loc.any = true;
        loc.measurement_checks = vec![
            check("M063", "bolted", 0.0027),
            check("M043", "bolted", -0.02),
            check("M010", "free", 0.0027),
            check("M050", "bolted", 0.0027),
            check("M051", "bolted", 0.0027),
        ];
        loc.measurements = ids.map(String::from).to_vec();
        let unit = |id: &str, lbf: f64, dev: Option<usize>| ScreenUnit {
            measurement_id: id.into(),
            log_bayes_factor: lbf,
            log_bayes_factor_se: 0.1,
            joints: vec![],
            freq_effect_rel: Some(3e-4),
            deviating_joint: dev,
            min_ess: 110.0,
            posterior: vec![],
        };
        let screen = JointScreen {
            units: vec![
                unit("M063", -6.7, None),
                unit("M043", -8.1, None),
                unit("M010", -6.0, None),
                unit("M050", 4.0, None),
                unit("M051", -1.0, Some(2)),
            ],
            log_bayes_factor: Some(-14.7),
            log_bayes_factor_se: Some(0.13),
            baseline_draws: 16,
            dropped_draws: vec![],
            contrast_log_sd: 0.7,
            model_evals: 19520,
            failed: None,
            untracked: vec![],
        };
        let jf = super::joint_form_outliers(&loc, &[&screen]);
        assert_eq!(jf, vec!["M063".to_string()]);
        assert!(
            super::joint_form_outliers(&loc, &[]).is_empty(),
            "unscreened"
        );
        let failed = JointScreen::failed("no draws".into());
        assert!(super::joint_form_outliers(&loc, &[&failed]).is_empty());

        // With a bolted shift common to every assembly, or alone, such outliers are the form;
        // with another outlier beside them the misfit stays unexplained.
        assert!(!model_form_pattern(&loc, &[], 0.0125, false, &jf));
        loc.measurements = vec!["M063".into()];
        loc.modes = vec![LocatedMode {
            setup: "bolted".into(),
            label: "plate-0-0".into(),
            mean_rel_residual: 0.0043,
            reasons: vec!["mean_shift".into()],
        }];
        assert!(!model_form_pattern(&loc, &[], 0.0125, false, &[]));
        assert!(model_form_pattern(&loc, &[], 0.0125, false, &jf));
        let said = |loc: &locate::Located| {
            super::remaining_discrepancy(
                (Verdict::ModelForm, "a thin plate"),
                (loc, &[], &jf),
                &[],
                1e-3,
                &None,
                &None,
            )
        };
        let s = said(&loc);
        assert!(
            s.contains("by up to 0.430 %") && s.contains("M063") && s.contains("per-assembly form"),
            "{s}"
        );
        loc.modes.clear();
        assert!(model_form_pattern(&loc, &[], 0.0125, false, &jf));
        let s = said(&loc);
        assert!(
            s.contains("no mode is off for every assembly alike") && s.contains("M063"),
            "{s}"
        );
    }

    /// A refit whose runs disagree a little keeps its Bayes factor (its estimates are said
    /// to be approximate); one whose runs disagree beyond the classical 1.1 gives none.
    #[test]
    fn the_r_hat_gate_keeps_the_evidence_of_runs_that_disagree_a_little() {
        let d = std::path::Path::new("refits/joint_rotation");
        let w = |r: f64| Some(("mu_ln_k_rot".to_string(), r));
        assert_eq!(super::r_hat_gate(None, d, 1.05), (None, None));
        assert_eq!(super::r_hat_gate(w(1.03), d, 1.05), (None, None));
        let (failed, note) = super::r_hat_gate(w(1.053), d, 1.05);
        assert!(failed.is_none());
        assert!(note.unwrap().contains("R-hat of mu_ln_k_rot 1.053 > 1.05"));
        let (failed, note) = super::r_hat_gate(w(1.2), d, 1.05);
        assert!(failed
            .unwrap()
            .contains("1.200 > 1.1 in refits/joint_rotation"));
        assert!(note.is_none());
    }
}

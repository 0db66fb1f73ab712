//! Refining a located point by the refits' own evidence (pure).
//!
//! The localisation ([`super::localize`]) maps how well a point mass explains the misfit on a
//! grid, with a first-order treatment of the board parameters and the mode shapes; the
//! refit's likelihood (every board, every measurement, the weighted shape terms, the exact
//! model) is much sharper. On the blind `lumped_mass` campaign the refit's step-1 log
//! evidence at the true point (55, 31) mm was 300 above the map's best grid point (54, 32) mm,
//! 1.4 mm away, and the mass fitted there was 0.328 g against 0.2499 g at the true point
//! (truth 0.25 g): the mass trades against the point's distance to the modes' nodal lines.
//! So the point is a parameter of the refit, profiled by its log evidence: a compass search
//! whose every probe is a step-1 refit at a fixed point, moving to the best probe and halving
//! its step once none beats the centre ([`search`]). The best probe is the point; the last
//! stencil's curvature and step give the location's posterior: its Occam factor against a
//! uniform prior over the board, and the spread of ln(mass) it carries.

use crate::diagnose::screen::{Candidate, PointLocated};
use serde::Serialize;

/// One probe: the log evidence of a refit with its point fixed at `xy_m`, and the ln of the
/// mass it fitted (population median, kg).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, schemars::JsonSchema)]
pub struct Probe {
    pub x_m: f64,
    pub y_m: f64,
    pub log_evidence: f64,
    /// The standard error of `log_evidence`: its runs' spread (sd / √runs; 0 with one run).
    pub log_evidence_se: f64,
    pub ln_mass_kg: f64,
    /// The largest |mean relative frequency residual| of a free-free mode the refit left
    /// ([`worst_mean_residual`]): what the point changes in the fit, in the practical
    /// threshold's terms. NaN when not known.
    pub misfit_rel: f64,
}

/// The largest |mean relative residual| over the free-free labels of a refit's residuals
/// (each label's mean over its measurements); NaN without any.
pub fn worst_mean_residual(rows: &[crate::diagnose::locate::ResidualObs]) -> f64 {
    let mut by: std::collections::BTreeMap<&str, (f64, usize)> = Default::default();
    for r in rows
        .iter()
        .filter(|r| r.setup == "free" && r.rel_residual.is_finite())
    {
        let e = by.entry(r.label.as_str()).or_default();
        e.0 += r.rel_residual;
        e.1 += 1;
    }
    by.values()
        .map(|(s, n)| (s / *n as f64).abs())
        .fold(f64::NAN, f64::max)
}

/// A probe is a better point than another only when its log evidence is higher by more than
/// this many standard errors of the difference: within it, the two are the same to the
/// refits' own precision, and moving on chases the runs' scatter (on the realistic lumped-mass
/// campaign the last 0.25 mm stencils differed by 0.05–0.4 with standard errors of 0.1–0.6,
/// and every such move cost four more refits).
pub const BETTER_BY_SE: f64 = 2.0;

impl Probe {
    /// Whether `self` beats `other` beyond their evidences' error ([`BETTER_BY_SE`]).
    pub fn beats(&self, other: &Probe) -> bool {
        self.log_evidence - other.log_evidence
            > BETTER_BY_SE * self.log_evidence_se.hypot(other.log_evidence_se)
    }
}

/// A compass stencil: the centre and its four neighbours at ±`h_m` along x and y.
#[derive(Clone, Copy, Debug)]
pub struct Stencil {
    pub centre: Probe,
    /// −x, +x, −y, +y.
    pub arms: [Probe; 4],
    pub h_m: f64,
}

impl Stencil {
    /// The Laplace approximation of the location's posterior at the centre (separable along
    /// x and y, the curvatures from the arms), widened by the stencil's resolution: `None`
    /// without a maximum along both axes.
    pub fn laplace(&self, board_area_m2: f64) -> Option<LocationPosterior> {
        let c = self.centre.log_evidence;
        let h = self.h_m;
        let curv = |a: &Probe, b: &Probe| (a.log_evidence - 2.0 * c + b.log_evidence) / (h * h);
        let (cx, cy) = (
            curv(&self.arms[0], &self.arms[1]),
            curv(&self.arms[2], &self.arms[3]),
        );
        if !(cx < 0.0 && cy < 0.0 && board_area_m2 > 0.0) {
            return None;
        }
        // The curvature's sd, and the search's resolution: the log evidence is peaked like
        // a logarithm near its top, not a parabola, so three probes h apart say only that
        // the top lies within a step of the best (uniform over ±h: sd h/√3). On the second
        // blind added-mass campaign (0.4 g at (26.3, 17.6) mm) the parabolas' vertex of the
        // last 0.25 mm stencil, (26.18, 17.54) mm, lay further from the mass than the best
        // probe, (26.25, 17.5) mm.
        let res = h / 3f64.sqrt();
        let sd = [(-1.0 / cx).sqrt().hypot(res), (-1.0 / cy).sqrt().hypot(res)];
        // The gradient of ln(mass) over the location, by central differences.
        let g = [
            (self.arms[1].ln_mass_kg - self.arms[0].ln_mass_kg) / (2.0 * h),
            (self.arms[3].ln_mass_kg - self.arms[2].ln_mass_kg) / (2.0 * h),
        ];
        // ∫ exp(L(p) − L(p̂)) dp / A over a uniform prior on the board: 2π sd_x sd_y / A.
        let log_occam = (2.0 * std::f64::consts::PI * sd[0] * sd[1] / board_area_m2)
            .ln()
            .min(0.0);
        Some(LocationPosterior {
            xy_m: [self.centre.x_m, self.centre.y_m],
            sd_m: sd,
            log_occam,
            ln_mass_sd: (g[0] * sd[0]).hypot(g[1] * sd[1]),
        })
    }
}

/// The location's posterior from the last stencil ([`Stencil::laplace`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LocationPosterior {
    /// Its mode: the best probe (the stencil's centre), m.
    pub xy_m: [f64; 2],
    /// Its standard deviation along x and y, m.
    pub sd_m: [f64; 2],
    /// ln(posterior width / prior width) of the location: the Occam factor of having fitted
    /// it, ≤ 0, added to the refit's log evidence.
    pub log_occam: f64,
    /// The sd of ln(mass) that the location's uncertainty carries.
    pub ln_mass_sd: f64,
}

/// The compass search's schedule.
#[derive(Clone, Debug)]
pub struct SearchPlan {
    /// The first step, m.
    pub first_step_m: f64,
    /// The search ends once no arm at this step beats the centre, m.
    pub last_step_m: f64,
    /// Probes at most (the search then ends at its best centre).
    pub max_probes: usize,
    /// The practical threshold (relative frequency): the search ends at a stencil none of
    /// whose arms changes the fit's worst mode ([`Probe::misfit_rel`]) by this much from the
    /// centre's, whatever their evidence: a finer or further point would be one the user
    /// cannot see in any frequency. `None`: the evidence alone decides.
    pub practical_rel: Option<f64>,
}

impl SearchPlan {
    /// The schedule for a point the localisation map placed on its grid of step `grid_m`:
    /// steps halve from half a grid step (the map's point is within one step of its
    /// optimum) to an eighth, but only while a step can still change a fitted frequency by
    /// `threshold_rel` or more: `step_shift_rel` is what a whole grid step changes
    /// ([`crate::diagnose::localize::LocalFit::step_shift_rel`]), first order in the step.
    /// A finer point would be a statistical refinement the user cannot see in any
    /// frequency, at four refits a stencil. `None`: not even the first step reaches the
    /// threshold, and the map's point stands. A `step_shift_rel` ≤ 0 (not known) keeps the
    /// whole schedule.
    pub fn for_point(grid_m: f64, step_shift_rel: f64, threshold_rel: f64) -> Option<SearchPlan> {
        let (first, finest) = (0.5 * grid_m, 0.125 * grid_m);
        let moves = |h: f64| step_shift_rel <= 0.0 || step_shift_rel * h / grid_m >= threshold_rel;
        if !moves(first) {
            return None;
        }
        let mut last = first;
        while last > finest * (1.0 + 1e-9) && moves(0.5 * last) {
            last *= 0.5;
        }
        Some(SearchPlan {
            first_step_m: first,
            last_step_m: last,
            max_probes: 24,
            practical_rel: Some(threshold_rel),
        })
    }
}

/// What [`search`] found.
#[derive(Clone, Debug)]
pub struct SearchResult {
    /// Every probe, in the order run.
    pub probes: Vec<Probe>,
    /// The last stencil: the best centre and its arms at the smallest step reached. `None`:
    /// the search ended at its start, whose refit left no free-free mode as far off as the
    /// practical threshold (no arm could gain that much).
    pub last: Option<Stencil>,
    /// The point the final refit is to use: the best probe.
    pub end_xy_m: [f64; 2],
}

/// Run a compass search from `start`: probe the four arms at ±h along x and y, move to the
/// best probe while it beats the centre beyond their evidences' error ([`Probe::beats`]),
/// else halve h, until no arm at `last_step_m` beats
/// it. A pattern search, not a Newton step: the log evidence of a point is peaked like a
/// logarithm, not a parabola, once the model error the refit infers falls to the noise (on
/// the blind `lumped_mass` campaign 190 below the peak at 0.5 mm, 240 at 1 mm), and a
/// parabola through 1 mm arms sent the centre the wrong way. `probe` runs one refit at a
/// point (an error ends the search).
pub fn search<E>(
    start: [f64; 2],
    plan: &SearchPlan,
    mut probe: impl FnMut([f64; 2]) -> Result<Probe, E>,
) -> Result<SearchResult, E> {
    let mut probes: Vec<Probe> = vec![];
    let mut run = |p: [f64; 2], probes: &mut Vec<Probe>| -> Result<Probe, E> {
        // The same point (to a micrometre) is never refitted twice.
        if let Some(q) = probes
            .iter()
            .find(|q| (q.x_m - p[0]).abs() < 1e-6 && (q.y_m - p[1]).abs() < 1e-6)
        {
            return Ok(*q);
        }
        let q = probe(p)?;
        probes.push(q);
        Ok(q)
    };
    let mut centre = run(start, &mut probes)?;
    if plan
        .practical_rel
        .is_some_and(|t| centre.misfit_rel.is_finite() && centre.misfit_rel < t)
    {
        return Ok(SearchResult {
            probes,
            last: None,
            end_xy_m: start,
        });
    }
    let mut h = plan.first_step_m;
    loop {
        let mut arms = [centre; 4];
        for (k, d) in [[-h, 0.0], [h, 0.0], [0.0, -h], [0.0, h]]
            .iter()
            .enumerate()
        {
            arms[k] = run([centre.x_m + d[0], centre.y_m + d[1]], &mut probes)?;
        }
        let best = arms
            .iter()
            .copied()
            .max_by(|a, b| a.log_evidence.total_cmp(&b.log_evidence))
            .unwrap_or(centre);
        let st = Stencil {
            centre,
            arms,
            h_m: h,
        };
        let out_of_probes = probes.len() + 4 > plan.max_probes;
        // No arm gains the threshold on the worst mode (a worse arm gains nothing).
        let flat = plan.practical_rel.is_some_and(|t| {
            centre.misfit_rel.is_finite()
                && arms
                    .iter()
                    .all(|a| a.misfit_rel.is_finite() && centre.misfit_rel - a.misfit_rel < t)
        });
        if flat {
            let best = if best.beats(&centre) { best } else { centre };
            return Ok(SearchResult {
                probes,
                last: Some(st),
                end_xy_m: [best.x_m, best.y_m],
            });
        }
        if best.beats(&centre) && !out_of_probes {
            centre = best;
            continue;
        }
        if h <= plan.last_step_m * (1.0 + 1e-9) || out_of_probes {
            let best = if best.beats(&centre) { best } else { centre };
            let end = [best.x_m, best.y_m];
            return Ok(SearchResult {
                probes,
                last: Some(st),
                end_xy_m: end,
            });
        }
        h *= 0.5;
    }
}

/// The candidate at the search's end point `end`: with the location's Laplace posterior of
/// the `last` stencil in place of the map's Occam factor and ln(mass) spread, or, when that
/// stencil has no interior maximum, as it was with the note saying so.
pub fn refined(
    cand: &Candidate,
    end: [f64; 2],
    last: Option<&Stencil>,
    board_area_m2: f64,
) -> (Candidate, Option<String>) {
    let mut c = cand.clone();
    c.point_xy_m = Some(end);
    let mut note = None;
    let Some(last) = last else {
        c.reason = format!(
            "{}; the point not refined: the refit there leaves no free-free mode as far off as the practical threshold",
            c.reason
        );
        return (c, None);
    };
    if let Some(post) = last.laplace(board_area_m2) {
        c.point_located = Some(PointLocated {
            log_occam: post.log_occam,
            location_ln_mass_sd: post.ln_mass_sd,
            step_shift_rel: cand.point_located.map_or(0.0, |p| p.step_shift_rel),
        });
        c.reason = format!(
            "{}; the point refined by the refits' evidence to ({:.2}, {:.2}) mm (sd {:.2}, {:.2} mm)",
            c.reason,
            end[0] * 1e3,
            end[1] * 1e3,
            post.sd_m[0] * 1e3,
            post.sd_m[1] * 1e3
        );
    } else {
        note = Some(format!(
            "the refinement's last stencil (step {:.3} mm) has no interior maximum of the log evidence: the point moved to the best probe ({:.2}, {:.2}) mm, the location's Occam factor and the mass's spread are the localisation map's",
            last.h_m * 1e3,
            end[0] * 1e3,
            end[1] * 1e3
        ));
    }
    (c, note)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The schedule stops halving where a step no longer moves a frequency by the threshold
    /// (a 2 mm grid, a 0.1 % threshold).
    #[test]
    fn the_search_refines_only_by_steps_a_frequency_can_show() {
        let g = 2e-3;
        // 0.4 % a grid step: 1 mm moves 0.2 %, 0.5 mm 0.1 %, 0.25 mm 0.05 %.
        let p = SearchPlan::for_point(g, 4e-3, 1e-3).unwrap();
        assert!((p.first_step_m - 1e-3).abs() < 1e-12);
        assert!((p.last_step_m - 0.5e-3).abs() < 1e-12, "{}", p.last_step_m);
        // 2 % a grid step: down to an eighth of it.
        let p = SearchPlan::for_point(g, 2e-2, 1e-3).unwrap();
        assert!((p.last_step_m - 0.25e-3).abs() < 1e-12);
        // 0.15 %: half a grid step moves 0.075 %, under the threshold: no search.
        assert!(SearchPlan::for_point(g, 1.5e-3, 1e-3).is_none());
        // Not known: the whole schedule.
        let p = SearchPlan::for_point(g, 0.0, 1e-3).unwrap();
        assert!((p.last_step_m - 0.25e-3).abs() < 1e-12);
    }

    /// A log evidence peaked at `(x0, y0)` with sd `s` along each axis; ln mass linear.
    fn field(x0: f64, y0: f64, s: [f64; 2]) -> impl Fn([f64; 2]) -> Probe {
        move |p| Probe {
            x_m: p[0],
            y_m: p[1],
            log_evidence: 100.0
                - 0.5 * ((p[0] - x0) / s[0]).powi(2)
                - 0.5 * ((p[1] - y0) / s[1]).powi(2),
            log_evidence_se: 0.0,
            ln_mass_kg: -8.0 + 50.0 * (p[0] - x0) - 20.0 * (p[1] - y0),
            // The worst mode's misfit grows by 0.05 % a millimetre from the peak.
            misfit_rel: 1e-3 + 0.5 * (p[0] - x0).hypot(p[1] - y0),
        }
    }

    /// With a practical threshold the search ends at the first stencil whose arms change
    /// the worst mode's misfit by less than it, at the best probe, where the evidence alone
    /// would go on halving its step.
    #[test]
    fn the_search_ends_where_no_arm_changes_the_fit_by_the_practical_threshold() {
        let (x0, y0) = (0.0553, 0.0312);
        let f = field(x0, y0, [6e-5, 8e-5]);
        let plan = |practical_rel| SearchPlan {
            first_step_m: 1e-3,
            last_step_m: 2.5e-4,
            max_probes: 30,
            practical_rel,
        };
        let by_evidence = search([0.054, 0.032], &plan(None), |p| Ok::<_, ()>(f(p))).unwrap();
        // The best 1 mm arm gains 0.033 % on the worst mode: under 0.1 %, one stencil.
        let practical = search([0.054, 0.032], &plan(Some(1e-3)), |p| Ok::<_, ()>(f(p))).unwrap();
        assert_eq!(practical.probes.len(), 5);
        assert!(by_evidence.probes.len() > 5);
        // The best of those five: the +x arm, nearer the peak.
        assert_eq!(practical.end_xy_m, [0.055, 0.032]);
        // That gain passes a 0.02 % threshold: the search goes on.
        let finer = search([0.054, 0.032], &plan(Some(2e-4)), |p| Ok::<_, ()>(f(p))).unwrap();
        assert!(finer.probes.len() > 5);
        // A start whose refit leaves its worst mode under the threshold is the point.
        let near = search([0.0553, 0.0312], &plan(Some(2e-3)), |p| Ok::<_, ()>(f(p))).unwrap();
        assert_eq!(near.probes.len(), 1);
        assert!(near.last.is_none());
        assert_eq!(near.end_xy_m, [0.0553, 0.0312]);
        // Unknown misfits never end it.
        let nan = |p| Probe {
            misfit_rel: f64::NAN,
            ..f(p)
        };
        let unknown = search([0.054, 0.032], &plan(Some(1e-3)), |p| Ok::<_, ()>(nan(p))).unwrap();
        assert_eq!(unknown.probes.len(), by_evidence.probes.len());
    }

    #[test]
    fn the_worst_mean_residual_is_over_free_free_labels() {
        let row = |setup: &str, label: &str, rel: f64| crate::diagnose::locate::ResidualObs {
            measurement_id: "M1".into(),
            board_id: "B1".into(),
            setup: setup.into(),
            label: label.into(),
            freq_hz: 1.0,
            model_freq_hz_mean: 1.0,
            predictive_sd_hz: 1.0,
            rel_residual: rel,
            std_residual: 0.0,
            used_for_updating: true,
            mac: None,
        };
        let rows = [
            row("free", "a", 1e-3),
            row("free", "a", -3e-3),
            row("free", "b", 5e-4),
            row("bolted", "c", 1e-2),
        ];
        assert!((worst_mean_residual(&rows) - 1e-3).abs() < 1e-15);
        assert!(worst_mean_residual(&rows[3..]).is_nan());
    }

    #[test]
    fn the_search_finds_a_peak_off_the_grid_and_its_laplace_posterior() {
        // The peak 1.4 mm from the start, sd 0.06 mm by 0.08 mm, as on the blind campaign.
        let (x0, y0, s) = (0.055, 0.031, [6e-5, 8e-5]);
        let f = field(x0, y0, s);
        let plan = SearchPlan {
            first_step_m: 1e-3,
            last_step_m: 2.5e-4,
            max_probes: 30,
            practical_rel: None,
        };
        let SearchResult {
            probes,
            last,
            end_xy_m: end,
        } = search([0.054, 0.032], &plan, |p| Ok::<_, ()>(f(p))).unwrap();
        // The best probe: the peak lies on the 1 mm lattice from the start.
        assert!(
            (end[0] - x0).abs() < 1e-9 && (end[1] - y0).abs() < 1e-9,
            "{end:?}"
        );
        assert!(probes.len() <= 24, "{} probes", probes.len());
        let area = 0.1 * 0.08;
        let post = last.unwrap().laplace(area).unwrap();
        assert!((post.xy_m[0] - x0).abs() < 1e-9);
        // The curvature's sd with the last step's resolution (0.25 mm / √3).
        let res = 2.5e-4 / 3f64.sqrt();
        let sd = [s[0].hypot(res), s[1].hypot(res)];
        assert!((post.sd_m[0] - sd[0]).abs() < 1e-12 && (post.sd_m[1] - sd[1]).abs() < 1e-12);
        let occam = (2.0 * std::f64::consts::PI * sd[0] * sd[1] / area).ln();
        assert!((post.log_occam - occam).abs() < 1e-9);
        // sd of ln m = |g| · sd per axis: (50 · sd_x, 20 · sd_y).
        let want = (50.0 * sd[0]).hypot(20.0 * sd[1]);
        assert!((post.ln_mass_sd - want).abs() < 1e-9, "{}", post.ln_mass_sd);
    }

    #[test]
    fn differences_within_the_evidence_error_do_not_move_the_search() {
        // A logarithmic peak (as the refits' evidence near the mass) 0.3 mm from the start,
        // each probe's evidence with a standard error of 0.5 and a deterministic scatter of
        // that size: the exact search chases the scatter through the 0.25 mm stencils, the
        // error-aware one stops once the arms no longer beat the centre beyond 2 se.
        let (x0, y0) = (0.0553, 0.0302);
        let noisy = |se: f64| {
            move |p: [f64; 2]| Probe {
                x_m: p[0],
                y_m: p[1],
                log_evidence: 5000.0 - 8.0 * ((p[0] - x0).hypot(p[1] - y0) / 1e-4 + 1.0).ln()
                    + 0.5 * (p[0] * 7.3e4 + p[1] * 3.1e4).sin(),
                log_evidence_se: se,
                ln_mass_kg: -8.0,
                misfit_rel: f64::NAN,
            }
        };
        let plan = SearchPlan {
            first_step_m: 1e-3,
            last_step_m: 2.5e-4,
            max_probes: 40,
            practical_rel: None,
        };
        let exact = search([0.055, 0.030], &plan, |p| Ok::<_, ()>(noisy(0.0)(p))).unwrap();
        let aware = search([0.055, 0.030], &plan, |p| Ok::<_, ()>(noisy(0.5)(p))).unwrap();
        assert!(
            aware.probes.len() < exact.probes.len(),
            "{} probes with the error against {} without",
            aware.probes.len(),
            exact.probes.len()
        );
        // Still within a last step of the peak along each axis.
        let d = (aware.end_xy_m[0] - x0)
            .abs()
            .max((aware.end_xy_m[1] - y0).abs());
        assert!(d <= 2.5e-4 + 1e-9, "{:?}", aware.end_xy_m);
    }

    #[test]
    fn no_maximum_gives_no_laplace_posterior_and_a_failed_probe_ends_the_search() {
        let c = Probe {
            x_m: 0.0,
            y_m: 0.0,
            log_evidence: 0.0,
            log_evidence_se: 0.0,
            ln_mass_kg: 0.0,
            misfit_rel: f64::NAN,
        };
        let at = |x: f64, y: f64, l: f64| Probe {
            x_m: x,
            y_m: y,
            log_evidence: l,
            log_evidence_se: 0.0,
            ln_mass_kg: 0.0,
            misfit_rel: f64::NAN,
        };
        // Rising along +x: no maximum along x.
        let st = Stencil {
            centre: c,
            arms: [
                at(-1e-3, 0.0, -1.0),
                at(1e-3, 0.0, 1.0),
                at(0.0, -1e-3, -1.0),
                at(0.0, 1e-3, -1.0),
            ],
            h_m: 1e-3,
        };
        assert!(st.laplace(1.0).is_none());
        let plan = SearchPlan {
            first_step_m: 1e-3,
            last_step_m: 1e-3,
            max_probes: 10,
            practical_rel: None,
        };
        let mut n = 0;
        let r = search([0.0, 0.0], &plan, |_| {
            n += 1;
            if n == 3 {
                Err("refit failed")
            } else {
                Ok(c)
            }
        });
        assert_eq!(r.unwrap_err(), "refit failed");
    }
}

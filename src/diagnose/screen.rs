//! Screen: which mechanisms of the library could explain the located signature, in which
//! order, so the expensive refits run on a few. Pure over [`Located`] and the board.
//!
//! The rules follow where each mechanism acts (its sensitivity pattern at the level the
//! locate step resolves):
//! - only the bolted setup misfits (free-free clean) → the joint mechanisms: they change
//!   nothing in free-free. A recurring unpaired bolted mode (an extra resonance in every
//!   bolted measurement) puts `fixture_compliance` first: only it adds a mode. Outlier
//!   bolted measurements that stand apart from their board's other assemblies (not
//!   [`Located::board_shared`]: a board whose assemblies all deviate alike is the board's
//!   own misfit) put `joint_stiffness_per_joint` next, with or without a mode-level
//!   shift (a loose bolt in some assemblies moves the modes' means a little too): every
//!   joint at once per measurement (which joint is loose may differ between assemblies),
//!   then one candidate per joint; it acts on some measurements only. Then
//!   `joint_rotation` (changes the bending pattern of all modes), `joint_mass`, and
//!   `fixture_compliance` when no unpaired mode recurs. A weakness: a few outliers on top
//!   of a mode-level shift put the per-joint refit ahead of `joint_rotation`; ordering by
//!   each mechanism's linearised share of the misfit would tell them apart;
//! - a numeric covariate trend → `temperature_stiffness` when the column is a temperature
//!   (its name or unit says so), with the covariate named;
//! - free-free modes misfit without a covariate → `added_mass` and `local_stiffness_loss`
//!   (they act in both setups), before the joint mechanisms (which cannot touch free-free);
//! - a located point mass or stiffness loss (the localisation, [`attach_point_mass`],
//!   [`attach_stiffness_loss`]) moves its mechanism first, with its location; a located
//!   point mass is a candidate even beside a covariate trend (two effects at once).
//!
//! The joint mechanisms have a step-2 refit (`update joints --enrich`),
//! `temperature_stiffness` a step-1 one (`update boards --enrich`, on the named covariate);
//! the others are listed with their screening reason and no Bayes factor.

use serde::Serialize;

use super::library::Mechanism;
use super::locate::Located;
use super::regions::BoardRegion;
use crate::fem::Board;

/// One screened candidate.
#[derive(Clone, Debug, Serialize, PartialEq, schemars::JsonSchema)]
pub struct Candidate {
    pub mechanism: Mechanism,
    /// 1-based joint of a per-joint candidate.
    pub joint: Option<usize>,
    /// The joint's centre, m (per-joint candidates).
    pub joint_xy_m: Option<[f64; 2]>,
    pub covariate: Option<String>,
    /// The located point of a point mechanism (`added_mass`), m.
    #[serde(default)]
    pub point_xy_m: Option<[f64; 2]>,
    /// When the point passed the localisation's rule: what its refit needs of the location's
    /// uncertainty. `None`: not located, and the point mechanism is not refitted.
    #[serde(default)]
    pub point_located: Option<PointLocated>,
    /// The measurements a per-assembly mechanism acts on (the outliers that screened it):
    /// its refit gives only them the mechanism's coordinates. Empty: every measurement.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub measurements: Vec<String>,
    /// Why it was kept, in words.
    pub reason: String,
}

impl Candidate {
    /// A candidate with no joint, covariate or point yet.
    pub fn new(mechanism: Mechanism, reason: String) -> Candidate {
        Candidate {
            mechanism,
            joint: None,
            joint_xy_m: None,
            covariate: None,
            point_xy_m: None,
            point_located: None,
            measurements: vec![],
            reason,
        }
    }

    /// The id of its refit directory and of `diagnose --only`.
    pub fn id(&self) -> String {
        match self.joint {
            Some(j) => format!("{}_{j}", self.mechanism.id()),
            None => self.mechanism.id().to_string(),
        }
    }

    /// Whether a refit exists for it.
    pub fn refittable(&self) -> bool {
        matches!(
            self.mechanism,
            Mechanism::JointRotation
                | Mechanism::JointMass
                | Mechanism::FixtureCompliance
                | Mechanism::JointStiffnessPerJoint
        ) || (self.mechanism == Mechanism::TemperatureStiffness && self.covariate.is_some())
            || (self.mechanism == Mechanism::AddedMass && self.point_located.is_some())
    }

    /// `location` of diagnosis.json.
    pub fn location_json(&self) -> serde_json::Value {
        match (self.joint, self.joint_xy_m, self.point_xy_m) {
            (Some(j), Some([x, y]), _) => serde_json::json!({"joint": j, "x_m": x, "y_m": y}),
            (None, _, Some([x, y])) => serde_json::json!({"x_m": x, "y_m": y}),
            _ => serde_json::Value::Null,
        }
    }
}

/// The uncertainty of a located point, for its refit (which fixes the point).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, serde::Deserialize, schemars::JsonSchema)]
pub struct PointLocated {
    /// The location's Occam factor
    /// ([`crate::diagnose::localize::LocalFit::log_location_occam`]), added to the
    /// refit's log evidence.
    pub log_occam: f64,
    /// The sd of ln(mass) that the location's uncertainty adds
    /// ([`crate::diagnose::localize::LocalFit::location_ln_amplitude_sd`]): the refit's mass
    /// interval, conditional on the point, is widened by it.
    pub location_ln_mass_sd: f64,
    /// The largest change of a fitted mode's frequency that moving the point one grid step
    /// makes ([`crate::diagnose::localize::LocalFit::step_shift_rel`]), relative: the point
    /// search refines only by steps that change a frequency by the practical threshold.
    #[serde(default)]
    pub step_shift_rel: f64,
}

/// Attach a point mass to the `added_mass` candidate: its location, the reason, and when
/// `located` is `Some(location Occam factor)` the candidate moves ahead of
/// `local_stiffness_loss` and the joint mechanisms (the frequency signature of a mass at that
/// point explains the misfit) and becomes refittable. A located point adds the candidate
/// where the screening did not list it: a covariate trend keeps the board mechanisms out of
/// the screening (it explains a free-free misfit by itself), but a mass that explains the
/// free-free mean shifts is a second effect the trend cannot make.
pub fn attach_point_mass(
    cands: &mut Vec<Candidate>,
    xy_m: [f64; 2],
    located: Option<PointLocated>,
    why: &str,
) {
    let i = match cands
        .iter()
        .position(|c| c.mechanism == Mechanism::AddedMass)
    {
        Some(i) => i,
        None if located.is_some() => {
            cands.push(Candidate::new(
                Mechanism::AddedMass,
                "the free-free mean shifts remain once the covariate trend is set aside".into(),
            ));
            cands.len() - 1
        }
        None => return,
    };
    let mut c = cands.remove(i);
    c.point_xy_m = Some(xy_m);
    c.point_located = located;
    c.reason = format!("{}; {}", c.reason, why.trim_end_matches('.'));
    let at = if located.is_some() {
        cands
            .iter()
            .position(|c| c.mechanism != Mechanism::TemperatureStiffness)
            .unwrap_or(cands.len())
    } else {
        i
    };
    cands.insert(at.min(cands.len()), c);
}

/// Attach a located stiffness loss to the `local_stiffness_loss` candidate: its location and
/// the reason; it moves ahead of the joint mechanisms (after a covariate's candidate) and
/// before `added_mass` (the stiffness signature explained more than the point mass's). It has
/// no refit: it is reported with its location and no Bayes factor.
pub fn attach_stiffness_loss(cands: &mut Vec<Candidate>, xy_m: [f64; 2], why: &str) {
    let Some(i) = cands
        .iter()
        .position(|c| c.mechanism == Mechanism::LocalStiffnessLoss)
    else {
        return;
    };
    let mut c = cands.remove(i);
    c.point_xy_m = Some(xy_m);
    c.reason = format!("{}; {}", c.reason, why.trim_end_matches('.'));
    let at = cands
        .iter()
        .position(|c| c.mechanism != Mechanism::TemperatureStiffness)
        .unwrap_or(cands.len());
    cands.insert(at, c);
}

fn is_temperature(name: &str, unit: &str) -> bool {
    let n = name.to_ascii_lowercase();
    n.contains("temp")
        || unit.contains('°')
        || unit.eq_ignore_ascii_case("K")
        || unit.eq_ignore_ascii_case("degC")
}

/// The candidates for `located`, most plausible first; empty when nothing was located.
pub fn screen(located: &Located, board: &Board) -> Vec<Candidate> {
    let mut out = vec![];
    if !located.any {
        return out;
    }
    let setup_modes = |s: &str| located.modes.iter().filter(|m| m.setup == s).count();
    let bolted_modes = setup_modes("bolted");
    let free_modes = setup_modes("free");
    // Outliers that remain once the located covariates are taken out (a temperature drift
    // makes the measurements at its extremes outliers, a loose bolt stays one) and that
    // stand apart from their board's other assemblies (a board whose assemblies all deviate
    // alike is the board's own, as in free-free, not a joint's of one assembly).
    let bolted_outliers: Vec<&String> = located
        .measurements_after_covariates
        .iter()
        .filter(|m| {
            (located
                .measurement_checks
                .iter()
                .any(|c| &c.measurement_id == *m && c.setup == "bolted")
                || located
                    .shape_checks
                    .iter()
                    .any(|c| &c.measurement_id == *m && c.setup == "bolted"))
                && !located.board_shared.contains(m)
        })
        .collect();
    let recurring_bolted = located
        .unpaired_clusters
        .iter()
        .filter(|c| c.setup == "bolted" && c.recurring)
        .map(|c| c.median_freq_hz)
        .collect::<Vec<_>>();
    let cand = Candidate::new;
    // Covariates first: a trend with a sheet column is the most specific signature.
    for c in &located.covariates {
        if c.slope_rel_per_unit.is_some() && is_temperature(&c.covariate, &c.unit) {
            let mut k = cand(
                Mechanism::TemperatureStiffness,
                format!(
                    "{} frequencies follow the sheet's {} (slope {:+.2e} per {}, q = {:.1e})",
                    c.setup,
                    c.covariate,
                    c.slope_rel_per_unit.unwrap_or(f64::NAN),
                    if c.unit.is_empty() { "unit" } else { &c.unit },
                    c.q_value
                ),
            );
            k.covariate = Some(c.covariate.clone());
            if !out.iter().any(|o: &Candidate| o.mechanism == k.mechanism) {
                out.push(k);
            }
        }
    }
    let bolted_only =
        (bolted_modes > 0 || !bolted_outliers.is_empty() || !recurring_bolted.is_empty())
            && free_modes == 0;
    let per_joint = |why: &str| -> Vec<Candidate> {
        board
            .holes
            .iter()
            .enumerate()
            .map(|(j, h)| Candidate {
                mechanism: Mechanism::JointStiffnessPerJoint,
                joint: Some(j + 1),
                joint_xy_m: Some([h.x_m, h.y_m]),
                covariate: None,
                point_xy_m: None,
                point_located: None,
                measurements: vec![],
                reason: why.to_string(),
            })
            .collect()
    };
    if bolted_only || bolted_modes > 0 || !bolted_outliers.is_empty() {
        let why_modes = format!(
            "{bolted_modes} bolted mode(s) misfit{}",
            if free_modes == 0 {
                " while free-free fits"
            } else {
                ""
            }
        );
        let why_out = format!(
            "{} bolted measurement(s) are outliers: {}",
            bolted_outliers.len(),
            bolted_outliers
                .iter()
                .map(|s| s.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        );
        let mut joint_cands = vec![];
        if !recurring_bolted.is_empty() {
            joint_cands.push(cand(
                Mechanism::FixtureCompliance,
                format!(
                    "an unpaired mode recurs in the bolted measurements near {:.0} Hz",
                    recurring_bolted[0]
                ),
            ));
        }
        // Outliers are the more specific signature: a mechanism acting on all measurements
        // alike cannot make a few of them outliers, while one joint's looseness in some
        // measurements also moves the modes' means a little.
        //
        // First every joint at once, per measurement: the bolt that is loose may differ
        // between assemblies, and that refit finds which joint deviates in which measurement
        // itself (one refit where the single joints would take one each and explain only
        // their own measurements); the single joints follow.
        if !bolted_outliers.is_empty() {
            if board.holes.len() >= 2 {
                let mut every = cand(Mechanism::JointStiffnessPerJoint, why_out.clone());
                every.measurements = bolted_outliers.iter().map(|m| m.to_string()).collect();
                joint_cands.push(every);
            }
            joint_cands.extend(per_joint(&why_out));
        }
        joint_cands.push(cand(Mechanism::JointRotation, why_modes.clone()));
        joint_cands.push(cand(Mechanism::JointMass, why_modes.clone()));
        if recurring_bolted.is_empty() {
            joint_cands.push(cand(Mechanism::FixtureCompliance, why_modes.clone()));
        }
        out.extend(joint_cands);
    }
    if free_modes > 0
        && !out
            .iter()
            .any(|c| c.mechanism == Mechanism::TemperatureStiffness)
    {
        // The joint mechanisms change nothing in free-free: a free-free misfit puts the
        // mechanisms acting on the board itself before them.
        let why = format!("{free_modes} free-free mode(s) misfit without a covariate trend");
        let first_joint = out
            .iter()
            .position(|c| c.mechanism != Mechanism::TemperatureStiffness)
            .unwrap_or(out.len());
        out.insert(
            first_joint,
            cand(Mechanism::LocalStiffnessLoss, why.clone()),
        );
        out.insert(first_joint, cand(Mechanism::AddedMass, why));
    }
    out
}

/// Attach the located board regions to the candidates: a point mass's point (and its
/// uncertainty when located) to `added_mass`, a located loss to `local_stiffness_loss`.
pub fn attach_regions(candidates: &mut Vec<Candidate>, regions: &[BoardRegion]) {
    for r in regions {
        match r.mechanism {
            Mechanism::AddedMass => attach_point_mass(
                candidates,
                [r.fit.x_m, r.fit.y_m],
                r.located.then_some(PointLocated {
                    log_occam: r.fit.log_location_occam,
                    location_ln_mass_sd: r.fit.location_ln_amplitude_sd,
                    step_shift_rel: r.fit.step_shift_rel,
                }),
                &r.sentence,
            ),
            // A located loss is the library's `local_stiffness_loss` there; a stiffening has
            // no mechanism in the library and stays a located, unexplained signature.
            Mechanism::LocalStiffnessLoss if r.located && r.fit.amplitude < 0.0 => {
                attach_stiffness_loss(candidates, [r.fit.x_m, r.fit.y_m], &r.sentence)
            }
            _ => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::diagnose::locate::{
        locate, LocateInput, LocateOptions, LocatedCovariate, LocatedMode, MeasurementCheck,
        UnpairedCluster,
    };

    fn located() -> Located {
        let mut l = locate(&LocateInput::default(), &LocateOptions::default());
        l.any = true;
        l
    }

    fn mode(setup: &str) -> LocatedMode {
        LocatedMode {
            setup: setup.into(),
            label: "bending-x-1".into(),
            mean_rel_residual: -0.01,
            reasons: vec!["mean".into()],
        }
    }

    /// A located free-free trend with the sheet's temperature column.
    fn temperature_trend() -> LocatedCovariate {
        LocatedCovariate {
            setup: "free".into(),
            covariate: "temperature_c".into(),
            q_value: 1e-9,
            slope_rel_per_unit: Some(-2e-3),
            unit: "°C".into(),
        }
    }

    fn ids(c: &[Candidate]) -> Vec<String> {
        c.iter().map(Candidate::id).collect()
    }

    /// Nothing located: nothing screened.
    #[test]
    fn nothing_located_screens_nothing() {
        let mut l = located();
        l.any = false;
        assert!(screen(&l, &crate::fem::tests::helpers::thin_board()).is_empty());
    }

    /// Bolted modes misfit, free-free clean: the joint mechanisms only, rotation first.
    #[test]
    fn a_bolted_misfit_screens_the_joint_mechanisms() {
        let mut l = located();
        l.modes = vec![mode("bolted")];
        let c = screen(&l, &crate::fem::tests::helpers::thin_board());
        assert_eq!(
            ids(&c),
            ["joint_rotation", "joint_mass", "fixture_compliance"]
        );
    }

    /// A bolted outlier by its shapes alone (no frequency check of it) screens the joints.
    #[test]
    fn a_bolted_shape_outlier_screens_every_joint_first() {
        let mut l = located();
        l.measurements = vec!["M-07".into()];
        l.measurements_after_covariates = vec!["M-07".into()];
        l.shape_outliers = vec!["M-07".into()];
        l.shape_checks = vec![crate::diagnose::shapes::ShapeCheck {
            measurement_id: "M-07".into(),
            board_id: "PCB-01".into(),
            setup: "bolted".into(),
            n_modes: 5,
            z: Some(8.0),
            p_value: Some(1e-15),
            q_value: Some(1e-14),
            outlier: true,
            single_mode: None,
            board_shared: false,
            modes: vec![],
        }];
        let c = screen(&l, &crate::fem::tests::helpers::thin_board());
        assert_eq!(ids(&c)[0], "joint_stiffness_per_joint");
        // Board-shared, it is the board's own: no per-joint candidate.
        l.board_shared = vec!["M-07".into()];
        let c = screen(&l, &crate::fem::tests::helpers::thin_board());
        assert!(ids(&c)
            .iter()
            .all(|i| !i.starts_with("joint_stiffness_per_joint")));
    }

    /// Bolted outlier measurements (free-free clean): every joint at once first, then each
    /// joint with its centre, then the mechanisms acting on all measurements alike.
    #[test]
    fn bolted_outliers_put_every_joint_first_then_each_joint() {
        let mut l = located();
        l.measurements_after_covariates = vec!["M-07".into(), "M-19".into()];
        l.measurement_checks = l
            .measurements_after_covariates
            .iter()
            .map(|m| MeasurementCheck {
                measurement_id: m.clone(),
                board_id: "PCB-01".into(),
                setup: "bolted".into(),
                n_modes: 5,
                chi2: 60.0,
                p_value: Some(1e-9),
                q_value: Some(1e-8),
                outlier: true,
                single_mode: None,
                left_out_of_scale: true,
                residuals: vec![],
            })
            .collect();
        let b = crate::fem::tests::helpers::thin_board();
        let c = screen(&l, &b);
        let n = b.holes.len();
        let mut want = vec!["joint_stiffness_per_joint".to_string()];
        want.extend((1..=n).map(|j| format!("joint_stiffness_per_joint_{j}")));
        assert_eq!(ids(&c)[..1 + n], want[..]);
        assert!(c[0].refittable() && c[0].joint.is_none());
        assert!(c[0].reason.contains("M-07"));
        assert_eq!(c[2].joint_xy_m, Some([b.holes[1].x_m, b.holes[1].y_m]));
        assert!(ids(&c).contains(&"joint_rotation".to_string()));
    }

    /// A recurring unpaired bolted mode puts the fixture first: only it adds a mode.
    #[test]
    fn a_recurring_unpaired_bolted_mode_puts_the_fixture_first() {
        let mut l = located();
        l.modes = vec![mode("bolted")];
        l.unpaired_clusters = vec![UnpairedCluster {
            setup: "bolted".into(),
            median_freq_hz: 2765.0,
            min_freq_hz: 2750.0,
            max_freq_hz: 2780.0,
            n_modes: 30,
            n_measurements: 30,
            share_of_setup: 1.0,
            recurring: true,
            measurement_ids: vec![],
        }];
        let c = screen(&l, &crate::fem::tests::helpers::thin_board());
        assert_eq!(c[0].mechanism, Mechanism::FixtureCompliance);
        assert_eq!(
            c.iter()
                .filter(|c| c.mechanism == Mechanism::FixtureCompliance)
                .count(),
            1
        );
    }

    /// A temperature trend names the covariate and comes first; the board mechanisms that a
    /// free-free misfit would add are not screened in when the trend explains it.
    #[test]
    fn a_temperature_trend_comes_first_with_its_column() {
        let mut l = located();
        l.modes = vec![mode("free"), mode("bolted")];
        l.covariates = vec![temperature_trend()];
        let c = screen(&l, &crate::fem::tests::helpers::thin_board());
        assert_eq!(c[0].mechanism, Mechanism::TemperatureStiffness);
        assert_eq!(c[0].covariate.as_deref(), Some("temperature_c"));
        assert!(!c.iter().any(|c| c.mechanism == Mechanism::AddedMass));
    }

    /// A free-free misfit puts the board mechanisms before the joint ones (which change
    /// nothing free-free); a located point mass moves `added_mass` first with its location.
    #[test]
    fn a_free_free_misfit_puts_the_board_mechanisms_first_and_a_located_mass_leads() {
        let mut l = located();
        l.modes = vec![mode("free"), mode("bolted")];
        let mut c = screen(&l, &crate::fem::tests::helpers::thin_board());
        assert_eq!(
            ids(&c)[..3],
            ["added_mass", "local_stiffness_loss", "joint_rotation"]
        );
        c.swap(0, 1);
        attach_point_mass(
            &mut c,
            [0.056, 0.030],
            Some(PointLocated {
                log_occam: -4.0,
                location_ln_mass_sd: 0.02,
                step_shift_rel: 0.0,
            }),
            "a point mass there explains it",
        );
        assert_eq!(c[0].mechanism, Mechanism::AddedMass);
        assert_eq!(c[0].point_xy_m, Some([0.056, 0.030]));
        assert!(c[0].refittable());
        assert_eq!(c[0].location_json()["x_m"], 0.056);
        assert!(c[0].reason.ends_with("a point mass there explains it"));
        // Not located: it keeps its place.
        let mut d = screen(&l, &crate::fem::tests::helpers::thin_board());
        d.swap(0, 1);
        attach_point_mass(&mut d, [0.01, 0.01], None, "weak");
        assert_eq!(d[1].mechanism, Mechanism::AddedMass);
        assert!(!d[1].refittable(), "a point not located is not refitted");
        // A located stiffness loss moves first with its location, and is not refitted.
        attach_stiffness_loss(&mut d, [0.024, 0.033], "a loss there explains it.");
        assert_eq!(d[0].mechanism, Mechanism::LocalStiffnessLoss);
        assert_eq!(d[0].location_json()["y_m"], 0.033);
        assert!(d[0].reason.ends_with("a loss there explains it"));
        assert!(!d[0].refittable());
    }

    /// Two effects: a temperature trend keeps `added_mass` out of the screening, but a located
    /// point mass adds it, right after the covariate's candidate; a point not located does not.
    #[test]
    fn a_located_point_mass_is_a_candidate_beside_a_temperature_trend() {
        let mut l = located();
        l.modes = vec![mode("free"), mode("bolted")];
        l.covariates = vec![temperature_trend()];
        let mut c = screen(&l, &crate::fem::tests::helpers::thin_board());
        let before = c.len();
        attach_point_mass(&mut c, [0.01, 0.01], None, "weak");
        assert_eq!(c.len(), before, "a point not located adds nothing");
        attach_point_mass(
            &mut c,
            [0.058, 0.030],
            Some(PointLocated {
                log_occam: -5.0,
                location_ln_mass_sd: 0.02,
                step_shift_rel: 0.0,
            }),
            "a point mass there explains the free-free mean shifts",
        );
        assert_eq!(
            ids(&c)[..3],
            ["temperature_stiffness", "added_mass", "joint_rotation"]
        );
        assert!(c[1].refittable());
        assert_eq!(c[1].point_xy_m, Some([0.058, 0.030]));
    }
}

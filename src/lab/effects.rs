//! The concealed effects (a)–(e) in plain words, and what a correct diagnosis would say:
//! which setups, measurements and modes are affected, through which covariate or region,
//! and by how much (from the truth model's modes with and without the effects, paired by
//! MAC on the scan grid; see [`super::truth`]). Nothing here reaches the campaign files.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use super::scenario::Scenario;
use super::truth::{MeasurementTruth, SetupKind};

/// Frequency shift statistics of one mode over the affected measurements of one setup.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModeEffect {
    pub setup: SetupKind,
    /// 1-based mode number (ascending frequency, with the effects).
    pub mode: usize,
    /// Mean truth frequency, Hz.
    pub freq_hz: f64,
    pub mean_shift_percent: f64,
    pub min_shift_percent: f64,
    pub max_shift_percent: f64,
    pub n_measurements: usize,
}

/// What a correct diagnosis of one effect would say.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Diagnosis {
    pub setups_affected: Vec<SetupKind>,
    pub measurements_affected: Vec<String>,
    /// The covariate the misfit follows, if any (a sheet column).
    pub covariate: Option<String>,
    /// Where on the board the cause sits, if localised.
    pub region: Option<String>,
    /// In-band modes with their shifts caused by the effect(s).
    pub modes: Vec<ModeEffect>,
    /// In-band modes of the truth with no counterpart without the effect (e.g. a fixture
    /// resonance): `measurement: frequency`.
    pub extra_modes: Vec<String>,
    /// The diagnosis in one paragraph.
    pub statement: String,
}

/// One concealed effect of the scenario.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EffectTruth {
    /// `a`–`e`, as in the issue.
    pub letter: String,
    /// Scenario key, e.g. `rotational_restraint`.
    pub key: String,
    pub enabled: bool,
    /// The physics, in plain words.
    pub description: String,
    /// The effect's parameters (SI, units in the names).
    pub parameters: BTreeMap<String, f64>,
    /// `None` when disabled.
    pub expected_diagnosis: Option<Diagnosis>,
}

/// Per (setup, mode): the setup, the shifts (%) and the frequencies (Hz) collected.
type ShiftAcc = BTreeMap<(u8, usize), (SetupKind, Vec<f64>, Vec<f64>)>;

fn mode_stats(ms: &[&MeasurementTruth]) -> Vec<ModeEffect> {
    let mut acc: ShiftAcc = BTreeMap::new();
    for m in ms {
        for md in m.modes.iter().filter(|md| md.in_band) {
            if let Some(sh) = md.shift_percent {
                let key = (m.setup as u8, md.mode);
                let e = acc.entry(key).or_insert((m.setup, vec![], vec![]));
                e.1.push(sh);
                e.2.push(md.freq_hz);
            }
        }
    }
    acc.into_iter()
        .map(|((_, mode), (setup, sh, f))| {
            let n = sh.len();
            ModeEffect {
                setup,
                mode,
                freq_hz: f.iter().sum::<f64>() / n as f64,
                mean_shift_percent: sh.iter().sum::<f64>() / n as f64,
                min_shift_percent: sh.iter().cloned().fold(f64::INFINITY, f64::min),
                max_shift_percent: sh.iter().cloned().fold(f64::NEG_INFINITY, f64::max),
                n_measurements: n,
            }
        })
        .collect()
}

fn extra_modes(ms: &[&MeasurementTruth]) -> Vec<String> {
    ms.iter()
        .flat_map(|m| {
            m.modes
                .iter()
                .filter(|md| md.in_band && md.freq_without_effects_hz.is_none())
                .map(move |md| format!("{}: {:.1} Hz", m.measurement_id, md.freq_hz))
        })
        .collect()
}

fn shifts_text(modes: &[ModeEffect]) -> String {
    modes
        .iter()
        .map(|m| {
            format!(
                "{} mode {} (~{:.0} Hz) {:+.2} % (range {:+.2} to {:+.2} %)",
                m.setup.as_str(),
                m.mode,
                m.freq_hz,
                m.mean_shift_percent,
                m.min_shift_percent,
                m.max_shift_percent
            )
        })
        .collect::<Vec<_>>()
        .join("; ")
}

fn largest(modes: &[ModeEffect]) -> f64 {
    modes
        .iter()
        .map(|m| {
            m.mean_shift_percent
                .abs()
                .max(m.max_shift_percent.abs())
                .max(m.min_shift_percent.abs())
        })
        .fold(0.0, f64::max)
}

fn diag(
    ms: &[&MeasurementTruth],
    covariate: Option<String>,
    region: Option<String>,
    lead: String,
) -> Diagnosis {
    let mut setups: Vec<SetupKind> = ms.iter().map(|m| m.setup).collect();
    setups.sort_by_key(|s| *s as u8);
    setups.dedup();
    let modes = mode_stats(ms);
    let extra = extra_modes(ms);
    let statement = format!(
        "{lead} Affected: {} measurement(s) ({}). Largest in-band shift {:.2} %. Shifts: {}.{}",
        ms.len(),
        setups
            .iter()
            .map(|s| s.as_str())
            .collect::<Vec<_>>()
            .join(", "),
        largest(&modes),
        shifts_text(&modes),
        if extra.is_empty() {
            String::new()
        } else {
            format!(
                " Extra in-band mode(s) the model cannot have: {}.",
                extra.join(", ")
            )
        }
    );
    Diagnosis {
        setups_affected: setups,
        measurements_affected: ms.iter().map(|m| m.measurement_id.clone()).collect(),
        covariate,
        region,
        modes,
        extra_modes: extra,
        statement,
    }
}

/// Describe all six effects of `s` (enabled or not) with their expected diagnosis.
pub fn describe(s: &Scenario, ms: &[MeasurementTruth]) -> Vec<EffectTruth> {
    let e = &s.effects;
    let bolted: Vec<&MeasurementTruth> =
        ms.iter().filter(|m| m.setup == SetupKind::Bolted).collect();
    let all: Vec<&MeasurementTruth> = ms.iter().collect();
    let several = [
        e.rotational_restraint.is_some(),
        e.loose_bolt.is_some(),
        e.temperature.is_some(),
        e.lumped_mass.is_some(),
        e.compliant_fixture.is_some(),
        e.underfill.is_some(),
    ]
    .iter()
    .filter(|b| **b)
    .count()
        > 1;
    let combined = if several {
        " (several effects are on: the shifts below are their combined effect)"
    } else {
        ""
    };
    let mut out = Vec::new();

    let mut p = BTreeMap::new();
    let d = e.rotational_restraint.as_ref().map(|r| {
        p.insert("k_rot_nm_per_rad".into(), r.k_rot_nm_per_rad);
        diag(
            &bolted,
            None,
            Some("the four clamped patches around the bolt holes".into()),
            format!(
                "The bolted joints transmit bending moment: the clamped patch restrains the board's slopes with {} N·m/rad per joint and axis, which a joint model of out-of-plane springs only lacks. Bolted frequencies are higher than such a model predicts by a mode-dependent amount that no single K_con can reproduce; free-free data are unaffected{combined}.",
                r.k_rot_nm_per_rad
            ),
        )
    });
    out.push(EffectTruth {
        letter: "a".into(),
        key: "rotational_restraint".into(),
        enabled: d.is_some(),
        description:
            "bolted joints transmit bending moment (rotational restraint of the clamped patch)"
                .into(),
        parameters: p,
        expected_diagnosis: d,
    });

    let mut p = BTreeMap::new();
    let d = e.loose_bolt.as_ref().map(|lb| {
        p.insert("share".into(), lb.share);
        p.insert("stiffness_factor".into(), lb.stiffness_factor);
        let loose: Vec<&MeasurementTruth> = bolted.iter().copied().filter(|m| m.loose_joint.is_some()).collect();
        let which = loose
            .iter()
            .map(|m| format!("{} (joint {})", m.measurement_id, m.loose_joint.unwrap_or(0)))
            .collect::<Vec<_>>()
            .join(", ");
        diag(
            &loose,
            None,
            Some(format!("one joint per affected measurement: {which}")),
            format!(
                "In {} of {} bolted measurements one bolt is loose: its contact stiffness is {:.0} % of the others'. Those measurements (only) have lower frequencies and an asymmetric shape change near the loose corner; they are outliers of the K_con population, not a different K_con{combined}.",
                loose.len(),
                bolted.len(),
                100.0 * lb.stiffness_factor
            ),
        )
    });
    out.push(EffectTruth {
        letter: "b".into(),
        key: "loose_bolt".into(),
        enabled: d.is_some(),
        description: "one loose bolt in a share of the bolted measurements".into(),
        parameters: p,
        expected_diagnosis: d,
    });

    let mut p = BTreeMap::new();
    let d = e.temperature.as_ref().map(|t| {
        p.insert("coefficient_per_k".into(), t.coefficient_per_k);
        p.insert("reference_c".into(), t.reference_c);
        let (tmin, tmax) = ms
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), m| (a.min(m.temperature_c), b.max(m.temperature_c)));
        diag(
            &all,
            Some("temperature_c".into()),
            None,
            format!(
                "FR-4 stiffness (E_x, E_y, G_xy) softens with temperature by {:.2} %/K around {:.1} °C, and the lab temperature varied from {:.1} to {:.1} °C. Every frequency of every measurement moves with the sheet's temperature_c by about {:.2} %/K (half the modulus coefficient); the misfit correlates with temperature, not with board or bolt set{combined}.",
                100.0 * t.coefficient_per_k,
                t.reference_c,
                tmin,
                tmax,
                50.0 * t.coefficient_per_k
            ),
        )
    });
    out.push(EffectTruth {
        letter: "c".into(),
        key: "temperature".into(),
        enabled: d.is_some(),
        description: "FR-4 stiffness softens with temperature while the lab temperature varies"
            .into(),
        parameters: p,
        expected_diagnosis: d,
    });

    let mut p = BTreeMap::new();
    let d = e.lumped_mass.as_ref().map(|lm| {
        p.insert("mass_kg".into(), lm.mass_kg);
        p.insert("x_m".into(), lm.x_m);
        p.insert("y_m".into(), lm.y_m);
        diag(
            &all,
            None,
            Some(format!("a point near x = {:.1} mm, y = {:.1} mm", 1e3 * lm.x_m, 1e3 * lm.y_m)),
            format!(
                "Every board carries an unmodelled lumped mass of {:.2} g at ({:.1}, {:.1}) mm, which the balance weighs with the board. Shifts below are against the same board without it; a model that spreads the weighed mass over the board mispredicts the modes by the spread of these shifts (modes with large amplitude at that point drop more){combined}.",
                1e3 * lm.mass_kg,
                1e3 * lm.x_m,
                1e3 * lm.y_m
            ),
        )
    });
    out.push(EffectTruth {
        letter: "d".into(),
        key: "lumped_mass".into(),
        enabled: d.is_some(),
        description: "an unmodelled lumped mass on every board".into(),
        parameters: p,
        expected_diagnosis: d,
    });

    let mut p = BTreeMap::new();
    let d = e.compliant_fixture.as_ref().map(|f| {
        p.insert("k_fix_n_per_m".into(), f.k_fix_n_per_m);
        p.insert("m_fix_kg".into(), f.m_fix_kg);
        let f_alone = (f.k_fix_n_per_m / f.m_fix_kg).sqrt() / (2.0 * std::f64::consts::PI);
        diag(
            &bolted,
            None,
            Some("the shaker fixture (below the board, between armature and bolts)".into()),
            format!(
                "The shaker fixture is compliant: {:.3} kg on {:.3e} N/m (alone {:.0} Hz) between the armature (where the reference is measured) and the bolts. Every bolted transmissibility shows an extra resonance the board model cannot have, and board modes near it are pulled; free-free data are unaffected{combined}.",
                f.m_fix_kg, f.k_fix_n_per_m, f_alone
            ),
        )
    });
    out.push(EffectTruth {
        letter: "e".into(),
        key: "compliant_fixture".into(),
        enabled: d.is_some(),
        description: "a compliant shaker fixture with its own resonance in band".into(),
        parameters: p,
        expected_diagnosis: d,
    });

    let mut p = BTreeMap::new();
    let d = e.underfill.as_ref().map(|dl| {
        p.insert("x_m".into(), dl.x_m);
        p.insert("y_m".into(), dl.y_m);
        p.insert("radius_m".into(), dl.radius_m);
        p.insert("stiffness_factor".into(), dl.stiffness_factor);
        diag(
            &all,
            None,
            Some(format!(
                "a disc of radius {:.1} mm around x = {:.1} mm, y = {:.1} mm",
                1e3 * dl.radius_m,
                1e3 * dl.x_m,
                1e3 * dl.y_m
            )),
            format!(
                "Every board carries epoxy underfill, a disc of radius {:.1} mm at ({:.1}, {:.1}) mm where the core is {:.1} times as stiff in bending; copper and mass are unchanged. No mechanism of the diagnosis's library models a local stiffening: the expected verdict is unexplained_misfit, located in free-free and bolted modes with large curvature there, and no mechanism favoured. Shifts below are against the same board without it{combined}.",
                1e3 * dl.radius_m,
                1e3 * dl.x_m,
                1e3 * dl.y_m,
                dl.stiffness_factor
            ),
        )
    });
    out.push(EffectTruth {
        letter: "f".into(),
        key: "underfill".into(),
        enabled: d.is_some(),
        description:
            "a locally stiffened disc (underfill) in every board, outside the mechanism library"
                .into(),
        parameters: p,
        expected_diagnosis: d,
    });
    out
}

/// One paragraph over all effects (states the null case explicitly).
pub fn summary(effects: &[EffectTruth]) -> String {
    let on: Vec<&EffectTruth> = effects.iter().filter(|e| e.enabled).collect();
    if on.is_empty() {
        return "Null scenario: no concealed effect. Beyond the truth model's finer mesh and per-joint \
                stiffness scatter (small, below the measurement scatter), a correct \
                diagnosis finds no missing physics: residuals are at the noise level and show no \
                trend with setup, temperature, board region or measurement."
            .into();
    }
    on.iter()
        .map(|e| {
            format!(
                "({}) {}: {}",
                e.letter,
                e.description,
                e.expected_diagnosis
                    .as_ref()
                    .map_or("", |d| d.statement.as_str())
            )
        })
        .collect::<Vec<_>>()
        .join("\n")
}

//! Tests of the virtual lab against the truth it reports and the readers of the contract
//! (our own parsers, and pyuff/pandas in `tests/interop/lab_read_campaign.py`).
//!
//! Most tests run a reduced campaign (3 boards, 10 measurements) of the built-in scenarios,
//! so that all of them finish in seconds; the full default campaign is timed once.

use std::collections::{BTreeMap, BTreeSet};

use super::truth::{MeasurementTruth, SetupKind};
use super::*;
use crate::formats::uff::{self, Abscissa, Dataset, FunctionType, Ordinate};

fn small(mut s: Scenario) -> Scenario {
    s.campaign.n_boards = 3;
    s.campaign.free_per_board = 2;
    s.campaign.bolted = vec![
        scenario::BoltedGroup {
            boards: vec![1],
            per_board: 2,
            purpose: "updating".into(),
        },
        scenario::BoltedGroup {
            boards: vec![2, 3],
            per_board: 1,
            purpose: "validation".into(),
        },
    ];
    s
}

fn run(name: &str, seed: u64) -> SimulatedCampaign {
    let s = small(builtin_scenario(name).expect("built-in scenario parses"));
    simulate(&s, &crate::fem::tests::helpers::thin_board(), seed).expect("simulation runs")
}

/// Parsed response spectra of one measurement: node → complex spectrum, plus the axis.
struct Spectra {
    f0: f64,
    df: f64,
    by_node: BTreeMap<i64, Vec<(f64, f64)>>,
    coherence: BTreeMap<i64, Vec<f64>>,
    nodes_m: BTreeMap<i64, [f64; 3]>,
    reference: BTreeSet<i64>,
}

fn read_spectra(bytes: &[u8]) -> Spectra {
    let f = uff::parse(bytes).expect("a UFF");
    assert!(f.issues.is_empty(), "{:?}", f.issues);
    assert!(f.skipped.is_empty());
    let metres = f
        .datasets
        .iter()
        .any(|d| matches!(d, Dataset::Units(u) if u.length_factor == 1.0));
    let mut sp = Spectra {
        f0: 0.0,
        df: 0.0,
        by_node: BTreeMap::new(),
        coherence: BTreeMap::new(),
        nodes_m: BTreeMap::new(),
        reference: BTreeSet::new(),
    };
    for d in &f.datasets {
        match d {
            Dataset::Nodes(ns) => {
                for n in &ns.nodes {
                    let k = if metres { 1.0 } else { 1e-3 };
                    sp.nodes_m.insert(n.id, n.xyz_file_units.map(|c| c * k));
                }
            }
            Dataset::Function(fu) => {
                let Abscissa::Even { min, increment } = fu.abscissa else {
                    panic!("uneven abscissa")
                };
                assert_eq!(fu.response_direction, 3);
                match (&fu.ordinate, fu.function_type) {
                    (
                        Ordinate::Complex { re, im },
                        FunctionType::Frf | FunctionType::Transmissibility,
                    ) => {
                        sp.f0 = min;
                        sp.df = increment;
                        sp.reference.insert(fu.reference_node);
                        sp.by_node.insert(
                            fu.response_node,
                            re.iter().zip(im).map(|(a, b)| (*a, *b)).collect(),
                        );
                    }
                    (Ordinate::Real(v), FunctionType::Coherence) => {
                        sp.coherence.insert(fu.response_node, v.clone());
                    }
                    other => panic!("unexpected record {:?}", other.1),
                }
            }
            Dataset::Units(_) | Dataset::NodalData(_) => {}
        }
    }
    sp
}

/// Sum over the good points of |H|² per line (a CMIF-like indicator).
fn power_sum(sp: &Spectra, t: &MeasurementTruth) -> Vec<f64> {
    let n = sp.by_node.values().next().map_or(0, |v| v.len());
    let mut p = vec![0.0; n];
    for (node, h) in &sp.by_node {
        if t.dropout_nodes.contains(node) {
            continue;
        }
        for (k, (a, b)) in h.iter().enumerate() {
            p[k] += a * a + b * b;
        }
    }
    p
}

/// Frequency of the largest local maximum of `p` within ±`half_hz` of `f_hz`, refined by
/// a parabola through log p at the peak line and its neighbours.
fn peak_near(p: &[f64], f0: f64, df: f64, f_hz: f64, half_hz: f64) -> f64 {
    let lo = (((f_hz - half_hz) - f0) / df).floor().max(1.0) as usize;
    let hi = ((((f_hz + half_hz) - f0) / df).ceil() as usize).min(p.len() - 2);
    let k = (lo..=hi)
        .filter(|&k| p[k] > p[k - 1] && p[k] >= p[k + 1])
        .max_by(|a, b| p[*a].total_cmp(&p[*b]))
        .unwrap_or(lo);
    let (a, b, c) = (p[k - 1].ln(), p[k].ln(), p[k + 1].ln());
    let den = a - 2.0 * b + c;
    let delta = if den < 0.0 { 0.5 * (a - c) / den } else { 0.0 };
    f0 + (k as f64 + delta.clamp(-0.5, 0.5)) * df
}

/// The in-band modes a peak can be attributed to: the mode's own term at its natural
/// frequency is at least 3 times the sum of the other modes' terms there. The other
/// terms are estimated from their peak magnitudes: a mode s contributes about
/// A_s · 2ζ_s ω_s² / |ω_s² − ω_r²| · (ω_r/ω_s)^p at ω_r, p = 1 (mobility) or 2
/// (transmissibility).
fn checkable(t: &MeasurementTruth) -> Vec<(usize, f64)> {
    let p = if t.setup == SetupKind::Free { 1 } else { 2 };
    t.modes
        .iter()
        .filter(|m| m.in_band)
        .filter(|m| {
            let others: f64 = t
                .modes
                .iter()
                .filter(|s| s.mode != m.mode)
                .map(|s| {
                    let (wr, ws) = (m.freq_hz, s.freq_hz);
                    s.peak_magnitude_rms * 2.0 * s.damping_ratio * ws * ws
                        / (ws * ws - wr * wr).abs()
                        * (wr / ws).powi(p)
                })
                .sum();
            m.peak_magnitude_rms >= 3.0 * others
        })
        .map(|m| (m.mode, m.freq_hz))
        .collect()
}

#[test]
fn builtin_scenarios_parse_and_differ_from_null_only_in_their_effect() {
    let null = builtin_scenario("null").unwrap();
    assert!(!null.effects.any());
    // The realistic counterparts: the null on the solid truth with the habits on, nothing else.
    let rnull = builtin_scenario("realistic_null").unwrap();
    let mut back = rnull.clone();
    assert_eq!(back.truth.physics, super::scenario::Physics::Solid);
    assert_eq!(back.preset, super::scenario::Preset::Realistic);
    back.truth.physics = null.truth.physics;
    back.preset = null.preset;
    back.name = null.name.clone();
    back.description = null.description.clone();
    assert_eq!(
        back, null,
        "realistic_null differs from null beyond truth and habits"
    );
    for (name, _) in BUILTIN_SCENARIOS {
        let s = builtin_scenario(name).unwrap();
        let base = if name.starts_with("realistic_") {
            &rnull
        } else {
            &null
        };
        let n_on = [
            s.effects.rotational_restraint.is_some(),
            s.effects.loose_bolt.is_some(),
            s.effects.temperature.is_some(),
            s.effects.lumped_mass.is_some(),
            s.effects.compliant_fixture.is_some(),
            s.effects.underfill.is_some(),
        ]
        .iter()
        .filter(|b| **b)
        .count();
        let expected = match name {
            "null" | "realistic_null" => 0,
            "realistic_mass_and_temperature" => 2,
            _ => 1,
        };
        assert_eq!(n_on, expected, "{name}");
        let mut stripped = s.clone();
        stripped.effects = Default::default();
        stripped.name = base.name.clone();
        stripped.description = base.description.clone();
        if name.ends_with("temperature") {
            stripped.lab = base.lab.clone();
        }
        assert_eq!(
            stripped, *base,
            "{name} differs from null beyond its effect"
        );
    }
    // The default campaign is the paper's plan.
    let p = builtin_scenario("paper").unwrap();
    assert_eq!(p.campaign.n_boards, 7);
    assert_eq!(p.campaign.free_per_board, 5);
    let bolted: Vec<(Vec<usize>, usize)> = p
        .campaign
        .bolted
        .iter()
        .map(|g| (g.boards.clone(), g.per_board))
        .collect();
    assert_eq!(bolted, vec![(vec![1, 2], 9), (vec![3, 4, 5, 6], 3)]);
}

#[test]
fn bad_scenarios_name_the_field() {
    let e = Scenario::from_toml_str("name = \"x\"\n[campaign]\nn_boards = 0\n").unwrap_err();
    assert!(e.to_string().contains("campaign.n_boards"), "{e}");
    let e = Scenario::from_toml_str(
        "name = \"x\"\n[effects.loose_bolt]\nshare = 0.3\nstiffness_factor = 1.5\n",
    )
    .unwrap_err();
    assert!(
        e.to_string()
            .contains("effects.loose_bolt.stiffness_factor"),
        "{e}"
    );
    let e = Scenario::from_toml_str(
        "name = \"x\"\n[population]\ncorrelation = [[1,1,0,0],[1,1,0,0],[0,0,1,0],[0,0,0,1]]\n",
    )
    .unwrap_err();
    assert!(e.to_string().contains("population.correlation"), "{e}");
    let e = Scenario::from_toml_str("name = \"x\"\n[measurement]\nfree_linez = 10\n").unwrap_err();
    assert!(e.to_string().contains("free_linez"), "{e}");
    let e = Scenario::from_toml_str("name = \"x\"\n[campaign]\nstart_date = \"3 March\"\n")
        .unwrap_err();
    assert!(e.to_string().contains("campaign.start_date"), "{e}");
}

#[test]
fn same_scenario_and_seed_give_same_bytes_whatever_the_thread_count() {
    let s = small(builtin_scenario("loose_bolt").unwrap());
    let b = crate::fem::tests::helpers::thin_board();
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let two = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    let a = one.install(|| simulate(&s, &b, 7).unwrap());
    let c = two.install(|| simulate(&s, &b, 7).unwrap());
    assert_eq!(a.files, c.files);
    assert_eq!(
        serde_json::to_vec(&a.truth).unwrap(),
        serde_json::to_vec(&c.truth).unwrap()
    );
    let d = simulate(&s, &b, 8).unwrap();
    assert_ne!(a.files, d.files, "another seed must give another campaign");
}

#[test]
fn campaign_follows_the_contract_for_our_readers() {
    let mut s = small(builtin_scenario("paper").unwrap());
    s.balance.garbled_prob = 0.2; // make sure the deliberate balance glitch occurs
    let c = simulate(&s, &crate::fem::tests::helpers::thin_board(), 11).unwrap();
    let t = &c.truth;
    // Layout: the sheet, one UFF per row, scale logs; nothing else.
    for name in c.files.keys() {
        assert!(
            name == "campaign.csv"
                || (name.starts_with("vibrometer/") && name.ends_with(".uff"))
                || (name.starts_with("scale/") && name.ends_with(".log")),
            "{name}"
        );
    }
    let sheet = crate::formats::sheet::parse(&c.files["campaign.csv"], "campaign.csv").unwrap();
    assert!(sheet.findings.is_empty(), "{:?}", sheet.findings);
    assert_eq!(sheet.rows.len(), t.measurements.len());
    assert!(sheet.extra_columns.is_empty());
    let free_grid = c.truth.measurements.len();
    assert!(free_grid > 0);
    let board = crate::fem::tests::helpers::thin_board();
    let grid = board.scan_points_m();
    for (row, mt) in sheet.rows.iter().zip(&t.measurements) {
        assert_eq!(row.measurement_id, mt.measurement_id);
        assert_eq!(row.board_id, mt.board_id);
        assert_eq!(row.setup.map(|s| s.as_str()), Some(mt.setup.as_str()));
        assert_eq!(row.file, mt.file);
        assert!((row.temperature_c.unwrap() - mt.temperature_c).abs() <= 0.05 + 1e-9);
        assert!(row.date_unix_ns.is_some());
        assert_eq!(row.bolt_set.is_some(), mt.setup == SetupKind::Bolted);
        let sp = read_spectra(&c.files[&row.file]);
        // Geometry: every scan point in metres at the grid, and the reference.
        for (o, p) in grid.iter().enumerate() {
            let q = sp.nodes_m[&(o as i64 + 1)];
            // Dataset 15 holds single precision (E13.5): 1e-7 m is far below any scan tolerance.
            assert!((q[0] - p[0]).abs() < 1e-7 && (q[1] - p[1]).abs() < 1e-7 && q[2] == 0.0);
        }
        assert_eq!(sp.reference, BTreeSet::from([mt.reference_node]));
        assert!(sp.nodes_m.contains_key(&mt.reference_node));
        if mt.setup == SetupKind::Bolted {
            let r = sp.nodes_m[&mt.reference_node];
            let on_board =
                r[0] >= 0.0 && r[0] <= board.length_x_m && r[1] >= 0.0 && r[1] <= board.width_y_m;
            assert!(!on_board, "the shaker reference lies off the board");
        }
        // Records: exactly the points not marked missing.
        let expect: BTreeSet<i64> = (1..=grid.len() as i64)
            .filter(|n| !mt.missing_nodes.contains(n))
            .collect();
        assert_eq!(sp.by_node.keys().copied().collect::<BTreeSet<_>>(), expect);
        if !sp.coherence.is_empty() {
            assert_eq!(
                sp.coherence.keys().copied().collect::<BTreeSet<_>>(),
                expect
            );
            assert!(sp
                .coherence
                .values()
                .flatten()
                .all(|g| (0.0..=1.0).contains(g)));
        }
        let inst = &t.scenario.measurement;
        let (n, top) = match mt.setup {
            SetupKind::Free => (inst.free_lines, inst.free_max_hz),
            SetupKind::Bolted => (inst.bolted_lines, inst.bolted_max_hz),
        };
        assert_eq!(sp.by_node.values().next().unwrap().len(), n);
        assert!((sp.f0 + (n - 1) as f64 * sp.df - top).abs() < 1e-6 * top);
    }
    // Balance logs: parse without findings; stable readings average to the truth mass.
    // The only findings are the garbled lines the truth lists.
    let mut readings = Vec::new();
    let mut reported = Vec::new();
    for (name, bytes) in c.files.iter().filter(|(n, _)| n.starts_with("scale/")) {
        let (r, f) = crate::formats::balance_log::parse(bytes, name);
        for x in f.iter() {
            assert_eq!(x.code, "balance.unknown_response", "{x}");
            reported.push(format!("{}:{}", x.file.clone().unwrap(), x.line.unwrap()));
        }
        readings.extend(r);
    }
    reported.sort();
    let mut listed = t.garbled_balance_lines.clone();
    listed.sort();
    assert!(!listed.is_empty());
    assert_eq!(reported, listed);
    let masses = crate::formats::balance_log::board_masses(&readings, Default::default());
    assert_eq!(masses.len(), t.boards.len());
    let units: BTreeSet<String> = readings.iter().filter_map(|r| r.unit.clone()).collect();
    assert_eq!(
        units,
        BTreeSet::from(["g".into(), "kg".into(), "mg".into()])
    );
    for (m, b) in masses.iter().zip(&t.boards) {
        assert_eq!(m.board_id, b.draw.board_id);
        assert!(!m.inconsistent);
        assert!(m.n_stable >= 2);
        let err = (m.mass_g - 1e3 * b.weighed_mass_kg).abs();
        assert!(
            err <= m.resolution_g,
            "board {}: {} g vs truth {} g",
            m.board_id,
            m.mass_g,
            1e3 * b.weighed_mass_kg
        );
    }
}

#[test]
fn frf_peaks_sit_at_the_truth_frequencies() {
    let c = run("paper", 3);
    let mut n_checked = 0;
    let mut worst: f64 = 0.0;
    for mt in &c.truth.measurements {
        let sp = read_spectra(&c.files[&mt.file]);
        let p = power_sum(&sp, mt);
        for (mode, f) in checkable(mt) {
            let zeta = mt.modes[mode - 1].damping_ratio;
            let fp = peak_near(&p, sp.f0, sp.df, f, 2.0 * zeta * f + 2.0 * sp.df);
            // Peak within half a line plus a small part of the half-power bandwidth 2ζf
            // (neighbouring modes tilt the peak; all are at least 5 % away).
            let tol = 0.5 * sp.df + 0.1 * zeta * f;
            worst = worst.max((fp - f).abs() / tol);
            assert!(
                (fp - f).abs() <= tol,
                "{} mode {mode}: peak {fp:.1} Hz, truth {f:.1} Hz, tol {tol:.2}",
                mt.measurement_id
            );
            n_checked += 1;
        }
    }
    eprintln!("checked {n_checked} peaks; worst error / tolerance = {worst:.2}");
    assert!(n_checked >= 40, "only {n_checked} peaks checkable");
}

#[test]
fn free_measurements_show_eight_elastic_modes_and_bolted_seven() {
    let c = run("paper", 3);
    for mt in &c.truth.measurements {
        let n_in = mt.modes.iter().filter(|m| m.in_band).count();
        let n_out = mt.modes.len() - n_in;
        match mt.setup {
            SetupKind::Free => assert_eq!(n_in, 8, "{}", mt.measurement_id),
            SetupKind::Bolted => assert_eq!(n_in, 7, "{}", mt.measurement_id),
        }
        assert!(n_out >= 2, "out-of-band modes are part of the synthesis");
        assert!(mt
            .modes
            .iter()
            .all(|m| (0.005..=0.02).contains(&m.damping_ratio)));
    }
    // The truth's hierarchy: boards differ, K_con differs per bolted measurement.
    let ex: BTreeSet<u64> = c
        .truth
        .boards
        .iter()
        .map(|b| b.draw.e_x_pa.to_bits())
        .collect();
    assert_eq!(ex.len(), c.truth.boards.len());
    let k: BTreeSet<u64> = c
        .truth
        .measurements
        .iter()
        .filter_map(|m| m.k_con_n_per_m.map(f64::to_bits))
        .collect();
    assert_eq!(k.len(), 4);
}

/// Largest in-band |shift| in %.
fn max_shift(t: &Truth) -> f64 {
    t.measurements
        .iter()
        .flat_map(|m| {
            m.modes
                .iter()
                .filter(|x| x.in_band)
                .filter_map(|x| x.shift_percent)
        })
        .fold(0.0, |a: f64, b| a.max(b.abs()))
}

#[test]
fn null_scenario_changes_nothing_and_each_effect_changes_the_data_by_its_amount() {
    let seed = 5;
    let null = run("null", seed);
    assert!(null
        .truth
        .effects
        .iter()
        .all(|e| !e.enabled && e.expected_diagnosis.is_none()));
    assert_eq!(max_shift(&null.truth), 0.0);
    assert!(null.truth.summary.starts_with("Null scenario"));
    // The truth is richer than the updating model, but by less than the effects: at the
    // same K_con (no mapping between meshes), the null bolted misfit stays well below
    // the effects' 1-2 %.
    let map = &null.truth.model_misfit;
    eprintln!("model misfit: {map:?}");
    assert!(
        map.bolted_misfit_percent.iter().all(|r| r.abs() < 0.6),
        "{map:?}"
    );
    assert!(
        map.free_misfit_percent.iter().all(|r| r.abs() < 0.6),
        "{map:?}"
    );
    for (name, key, setups) in [
        (
            "rotational",
            "rotational_restraint",
            vec![SetupKind::Bolted],
        ),
        ("loose_bolt", "loose_bolt", vec![SetupKind::Bolted]),
        (
            "temperature",
            "temperature",
            vec![SetupKind::Free, SetupKind::Bolted],
        ),
        (
            "lumped_mass",
            "lumped_mass",
            vec![SetupKind::Free, SetupKind::Bolted],
        ),
        ("fixture", "compliant_fixture", vec![SetupKind::Bolted]),
    ] {
        let e = run(name, seed);
        let eff = e.truth.effects.iter().find(|x| x.key == key).unwrap();
        assert!(eff.enabled);
        let d = eff.expected_diagnosis.as_ref().unwrap();
        assert!(!d.measurements_affected.is_empty(), "{name}");
        // Only the fixture brings a mode of its own; the others move the board's modes.
        assert_eq!(
            d.extra_modes.is_empty(),
            name != "fixture",
            "{name}: {:?}",
            d.extra_modes
        );
        assert!(
            d.setups_affected.iter().all(|s| setups.contains(s)),
            "{name}: {:?}",
            d.setups_affected
        );
        // Realistic size: about the paper's 1-2 % misfit, not a caricature.
        let ms = max_shift(&e.truth);
        eprintln!("{name}: largest in-band shift {ms:.2} %");
        assert!((0.4..=3.0).contains(&ms), "{name}: largest shift {ms:.2} %");
        // Same draws as the null scenario: the counterfactual is the null truth.
        assert_eq!(
            e.truth.boards.iter().map(|b| &b.draw).collect::<Vec<_>>(),
            null.truth
                .boards
                .iter()
                .map(|b| &b.draw)
                .collect::<Vec<_>>()
        );
        for (me, mn) in e.truth.measurements.iter().zip(&null.truth.measurements) {
            assert_eq!(me.k_con_n_per_m, mn.k_con_n_per_m);
            let affected = d.measurements_affected.contains(&me.measurement_id);
            if !affected {
                assert!(me
                    .modes
                    .iter()
                    .all(|m| m.shift_percent.is_none_or(|s| s == 0.0)));
            }
            for m in me.modes.iter().filter(|m| m.in_band) {
                let Some(f0) = m.freq_without_effects_hz else {
                    continue;
                };
                // The counterfactual (effect off) is the null scenario's mode.
                let near = mn
                    .modes
                    .iter()
                    .map(|x| (x.freq_hz / f0 - 1.0).abs())
                    .fold(f64::INFINITY, f64::min);
                assert!(
                    near < 1e-9,
                    "{name} {}: counterfactual {f0} Hz not in the null truth",
                    me.measurement_id
                );
            }
        }
        // The data move by that amount: peak of the most-shifted checkable mode in the
        // effect's file vs in the null file.
        let mut checked = 0;
        for (me, mn) in e.truth.measurements.iter().zip(&null.truth.measurements) {
            let cands: Vec<_> = checkable(me)
                .into_iter()
                .filter_map(|(mode, f)| {
                    let m = &me.modes[mode - 1];
                    let f0 = m.freq_without_effects_hz?;
                    let sh = m.shift_percent?;
                    let in_null = checkable(mn)
                        .iter()
                        .any(|(_, g)| (g / f0 - 1.0).abs() < 1e-9);
                    (in_null && sh.abs() > 0.2).then_some((
                        f,
                        f0,
                        m.damping_ratio.max(
                            mn.modes
                                .iter()
                                .find(|x| (x.freq_hz / f0 - 1.0).abs() < 1e-9)
                                .map_or(0.0, |x| x.damping_ratio),
                        ),
                    ))
                })
                .collect();
            if cands.is_empty() {
                continue;
            }
            let spe = read_spectra(&e.files[&me.file]);
            let spn = read_spectra(&null.files[&mn.file]);
            let (pe, pn) = (power_sum(&spe, me), power_sum(&spn, mn));
            for (f, f0, zeta) in cands {
                let fe = peak_near(&pe, spe.f0, spe.df, f, 2.0 * zeta * f + 2.0 * spe.df);
                let fnull = peak_near(&pn, spn.f0, spn.df, f0, 2.0 * zeta * f0 + 2.0 * spn.df);
                let tol = spe.df + 0.2 * zeta * f;
                assert!(
                    ((fe - fnull) - (f - f0)).abs() <= tol,
                    "{name} {}: data shift {:.1} Hz, truth shift {:.1} Hz",
                    me.measurement_id,
                    fe - fnull,
                    f - f0
                );
                checked += 1;
            }
        }
        eprintln!("{name}: {checked} shifted peaks checked in the data");
        if name != "loose_bolt" {
            assert!(checked >= 1, "{name}: no shifted peak could be checked");
        }
    }
}

#[test]
fn fixture_adds_a_resonance_in_band_and_the_truth_says_so() {
    let e = run("fixture", 5);
    let d = e
        .truth
        .effects
        .iter()
        .find(|x| x.key == "compliant_fixture")
        .unwrap();
    let d = d.expected_diagnosis.as_ref().unwrap();
    let n_bolted = e
        .truth
        .measurements
        .iter()
        .filter(|m| m.setup == SetupKind::Bolted)
        .count();
    assert_eq!(d.extra_modes.len(), n_bolted, "{:?}", d.extra_modes);
}

#[test]
fn campaign_directory_never_contains_the_truth() {
    let c = run("lumped_mass", 2);
    let hidden = ["lumped", "k_con", "truth", "effect", "loose", "fixture"];
    for (name, bytes) in &c.files {
        if name.ends_with(".uff") {
            continue; // binary data; its text records are checked below
        }
        let text = String::from_utf8_lossy(bytes).to_lowercase();
        for h in hidden {
            assert!(!text.contains(h), "{name} mentions {h}");
        }
    }
    for mt in &c.truth.measurements {
        let f = uff::parse(&c.files[&mt.file]).unwrap();
        for d in &f.datasets {
            if let Dataset::Function(fu) = d {
                let ids = fu.id_lines.join(" ").to_lowercase();
                assert!(hidden.iter().all(|h| !ids.contains(h)), "{ids}");
            }
        }
    }
}

#[test]
fn pyuff_and_pandas_read_the_campaign() {
    let c = run("paper", 13);
    let dir = tempfile::tempdir().unwrap();
    for (p, b) in &c.files {
        let path = dir.path().join(p);
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(&path, b).unwrap();
    }
    // In the main crate the script sits under the manifest dir; the fallback serves the
    // scratch crate that includes these sources by path.
    let script = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/interop/lab_read_campaign.py"
    );
    let script = if std::path::Path::new(script).exists() {
        script
    } else {
        "/work/main/tests/interop/lab_read_campaign.py"
    };
    let out = std::process::Command::new("python3")
        .arg(script)
        .arg(dir.path())
        .output()
        .expect("python3 runs");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let cols: Vec<&str> = v["columns"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_str().unwrap())
        .collect();
    assert_eq!(
        cols,
        [
            "measurement_id",
            "board_id",
            "setup",
            "file",
            "bolt_set",
            "torque_nm",
            "temperature_c",
            "date",
            "operator",
            "notes"
        ]
    );
    let rows = v["rows"].as_array().unwrap();
    assert_eq!(rows.len(), c.truth.measurements.len());
    let grid = crate::fem::tests::helpers::thin_board().scan_points_m();
    for (row, mt) in rows.iter().zip(&c.truth.measurements) {
        assert_eq!(row["measurement_id"], mt.measurement_id.as_str());
        assert_eq!(row["setup"], mt.setup.as_str());
        let fs = &v["files"][mt.file.as_str()];
        let recs = fs["records"].as_array().unwrap();
        let resp: Vec<_> = recs.iter().filter(|r| r["func_type"] != 6).collect();
        assert_eq!(resp.len(), grid.len() - mt.missing_nodes.len());
        let want_type = if mt.setup == SetupKind::Free { 4 } else { 5 };
        let ours = read_spectra(&c.files[&mt.file]);
        for r in &resp {
            assert_eq!(r["func_type"], want_type);
            assert_eq!(r["rsp_dir"], 3);
            assert_eq!(r["ref_dir"], 3);
            assert_eq!(r["ref_node"], mt.reference_node);
            assert!(r["complex"].as_bool().unwrap());
            let node = r["rsp_node"].as_i64().unwrap();
            let h = &ours.by_node[&node];
            let ours_sum: f64 = h.iter().map(|(a, b)| a.hypot(*b)).sum();
            let theirs = r["abs_sum"].as_f64().unwrap();
            assert!(
                (theirs / ours_sum - 1.0).abs() < 1e-6,
                "node {node}: {theirs} vs {ours_sum}"
            );
        }
        // Coordinates: pyuff gives file units; 164 says metres, else millimetres.
        let k = if fs["units"].is_null() { 1e-3 } else { 1.0 };
        for (o, p) in grid.iter().enumerate() {
            let xyz = &fs["nodes"][(o + 1).to_string().as_str()];
            assert!((xyz[0].as_f64().unwrap() * k - p[0]).abs() < 1e-6);
            assert!((xyz[1].as_f64().unwrap() * k - p[1]).abs() < 1e-6);
        }
    }
}

#[test]
fn default_campaign_is_modest() {
    // Its time goes to `make -C pipelines bench-lab`, not into an assertion here: a timed
    // test fails on a busy machine and proves nothing on an idle one.
    let s = builtin_scenario("paper").unwrap();
    let t = std::time::Instant::now();
    let c = simulate(&s, &crate::fem::tests::helpers::thin_board(), s.seed).unwrap();
    let secs = t.elapsed().as_secs_f64();
    let bytes: usize = c.files.values().map(|v| v.len()).sum();
    eprintln!(
        "default campaign: {secs:.1} s, {} files, {:.0} MB",
        c.files.len(),
        bytes as f64 / 1e6
    );
    assert_eq!(c.truth.measurements.len(), 7 * 5 + 2 * 9 + 4 * 3);
    assert!(bytes < 200_000_000);
    let eff = c
        .truth
        .effects
        .iter()
        .find(|e| e.key == "rotational_restraint")
        .unwrap();
    assert!(eff.enabled);
    let ms = max_shift(&c.truth);
    assert!(
        (1.0..=3.0).contains(&ms),
        "paper default: largest bolted shift {ms:.2} %"
    );
}

#[test]
fn schema_describes_every_scenario_field_and_no_other() {
    let schema: serde_json::Value =
        serde_json::from_str(include_str!("../../schemas/lab_scenario.schema.json")).unwrap();
    let mut s = builtin_scenario("paper").unwrap();
    // All effects present, so that every field is serialised.
    let all = "name = \"all\"\n[effects.loose_bolt]\nshare = 0.3\nstiffness_factor = 0.5\n\
               [effects.temperature]\ncoefficient_per_k = -0.004\nreference_c = 23.0\n\
               [effects.lumped_mass]\nmass_kg = 2e-4\nx_m = 0.06\ny_m = 0.03\n\
               [effects.compliant_fixture]\nk_fix_n_per_m = 3e7\nm_fix_kg = 0.1\n\
               [effects.underfill]\nx_m = 0.024\ny_m = 0.033\nradius_m = 0.006\n\
               stiffness_factor = 3.0\n";
    let other = Scenario::from_toml_str(all).unwrap();
    s.effects.loose_bolt = other.effects.loose_bolt;
    s.effects.temperature = other.effects.temperature;
    s.effects.lumped_mass = other.effects.lumped_mass;
    s.effects.compliant_fixture = other.effects.compliant_fixture;
    s.effects.underfill = other.effects.underfill;
    // The preset and every habit set, so that they are serialised too.
    s.preset = scenario::Preset::Realistic;
    s.habits = scenario::Habits {
        reference_weights: Some(true),
        reweighed_board: Some(false),
        id_variants: Some(true),
        repeated_measurement: Some(true),
        scan_grids: Some(true),
        off_board_points: Some(true),
        sheet_gaps: Some(true),
    };
    // The specimen fields, left out at their defaults.
    s.population.thickness_rel_std = 0.04;
    s.campaign.sheet_dimensions = true;
    let v = serde_json::to_value(&s).unwrap();
    fn walk(v: &serde_json::Value, sch: &serde_json::Value, path: &str) {
        let sch = if sch["type"] == "array" {
            &sch["items"]
        } else {
            sch
        };
        match v {
            serde_json::Value::Object(map) => {
                let props = sch["properties"]
                    .as_object()
                    .unwrap_or_else(|| panic!("{path}: no properties"));
                let keys: BTreeSet<&String> = map.keys().collect();
                let skeys: BTreeSet<&String> = props.keys().collect();
                assert_eq!(keys, skeys, "{path}");
                for (k, x) in map {
                    walk(x, &props[k], &format!("{path}.{k}"));
                }
            }
            serde_json::Value::Array(a) => {
                for x in a {
                    walk(x, sch, path);
                }
            }
            _ => {}
        }
    }
    walk(&v, &schema, "");
}

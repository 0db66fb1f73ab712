//! One test per lab habit: a small campaign simulated with that habit alone, ingested by the
//! campaign checks (`crate::campaign::read_campaign`, the same code `hbmu ingest` runs), and
//! held to the finding (code, file, line or record), to a board population of exactly the
//! sheet's boards, and to the good data coming through. A coarse truth mesh and few spectral
//! lines keep each test to a few seconds; the habits do not depend on either.

use std::collections::{BTreeMap, BTreeSet};

use super::scenario::{Habits, Preset};
use super::*;
use crate::campaign::{read_campaign, InMemory, IngestConfig};
use crate::findings::{Finding, Severity};

/// Three boards, 5 free measurements each, then bolted 2 of board 1 and 1 of board 2: 16
/// measurements a day puts the first bolted one on day one, the other two on day two (a
/// second bolted session); coarse truth, 400 lines.
fn scenario(habits: Habits) -> Scenario {
    let mut s = builtin_scenario("null").unwrap();
    s.campaign.n_boards = 3;
    s.campaign.free_per_board = 5;
    s.campaign.bolted = vec![
        scenario::BoltedGroup {
            boards: vec![1],
            per_board: 2,
            purpose: "updating".into(),
        },
        scenario::BoltedGroup {
            boards: vec![2],
            per_board: 1,
            purpose: "validation".into(),
        },
    ];
    s.truth.mesh_nx = 32;
    s.truth.mesh_ny = 20;
    s.measurement.free_lines = 400;
    s.measurement.bolted_lines = 400;
    s.habits = habits;
    s
}

fn simulate_and_ingest(habits: Habits) -> (SimulatedCampaign, crate::campaign::Campaign) {
    let s = scenario(habits);
    let c = simulate(&s, &crate::fem::tests::helpers::thin_board(), 11).expect("simulation runs");
    let ing = read_campaign(&InMemory(&c.files), &IngestConfig::default(), &|| {})
        .expect("the campaign ingests");
    (c, ing)
}

fn sheet_boards(c: &SimulatedCampaign) -> BTreeSet<String> {
    c.truth
        .boards
        .iter()
        .map(|b| b.draw.board_id.clone())
        .collect()
}

/// The board population after ingest is exactly the sheet's boards: every measurement's
/// board and every mass row is one of them, and every board has its mass.
fn assert_population(c: &SimulatedCampaign, ing: &crate::campaign::Campaign) {
    let boards = sheet_boards(c);
    let of_measurements: BTreeSet<String> = ing
        .measurements
        .iter()
        .map(|m| m.row.board_id.clone())
        .collect();
    assert_eq!(of_measurements, boards, "measurements' boards");
    let of_masses: BTreeSet<String> = ing.masses.iter().map(|m| m.board_id.clone()).collect();
    assert_eq!(of_masses, boards, "masses.parquet's boards");
    // Good data comes through: each mass within 3 balance steps of what was weighed.
    for m in &ing.masses {
        let t = c
            .truth
            .boards
            .iter()
            .find(|b| b.draw.board_id == m.board_id)
            .unwrap();
        let err = (m.mass_g - t.weighed_mass_kg * 1e3).abs();
        assert!(
            err < 3.0 * c.truth.scenario.balance.resolution_g,
            "{}: off by {err} g",
            m.board_id
        );
        assert!(!m.inconsistent, "{m:?}");
    }
}

fn find<'a>(ing: &'a crate::campaign::Campaign, code: &str) -> Vec<&'a Finding> {
    ing.findings.iter().filter(|f| f.code == code).collect()
}

/// The 1-based line of the first line of `file` whose second token is `id`.
fn first_line_of(c: &SimulatedCampaign, file: &str, id: &str) -> Option<u64> {
    let text = String::from_utf8(c.files[file].clone()).unwrap();
    text.lines()
        .position(|l| l.split_whitespace().nth(1) == Some(id))
        .map(|i| i as u64 + 1)
}

/// The sheet line of a measurement, as the sheet parser reports it.
fn sheet_line(ing: &crate::campaign::Campaign, mid: &str) -> u64 {
    ing.measurements
        .iter()
        .find(|m| m.row.measurement_id == mid)
        .unwrap()
        .row
        .line
}

#[test]
fn without_habits_the_campaign_has_none_and_the_realistic_preset_has_all() {
    let (c, ing) = simulate_and_ingest(Habits::default());
    assert!(c.truth.habits.is_none());
    for code in [
        "balance.not_a_board",
        "sheet.board_id_variant",
        "sheet.marked_invalid",
        "uff.point_off_plane",
        "sheet.missing_value",
        "campaign.scan_grid_inconsistent",
    ] {
        assert!(find(&ing, code).is_empty(), "{code} without the habit");
    }
    assert_population(&c, &ing);
    // The preset switches every habit on; `[habits]` switches one off again.
    let s = Scenario::from_toml_str(
        "name = \"r\"\npreset = \"realistic\"\n[habits]\nsheet_gaps = false\n",
    )
    .unwrap();
    let h = s.habits();
    assert!(h.reference_weights && h.reweighed_board && h.id_variants);
    assert!(h.repeated_measurement && h.scan_grids && h.off_board_points);
    assert!(!h.sheet_gaps);
    assert_eq!(s.preset, Preset::Realistic);
    assert!(!builtin_scenario("paper").unwrap().habits().any());
}

#[test]
fn check_weight_and_tray_are_not_boards() {
    let (c, ing) = simulate_and_ingest(Habits {
        reference_weights: Some(true),
        ..Default::default()
    });
    assert_population(&c, &ing);
    let found = find(&ing, "balance.not_a_board");
    let logs: Vec<&String> = c.files.keys().filter(|k| k.starts_with("scale/")).collect();
    for id in [habits::CHECK_WEIGHT_ID, habits::TRAY_ID] {
        for log in &logs {
            let line = first_line_of(&c, log, id).expect("the habit logs the ID in every file");
            assert!(
                found.iter().any(|f| f.file.as_deref() == Some(log.as_str())
                    && f.line == Some(line)
                    && f.message.contains(id)
                    && f.severity == Severity::Info),
                "{id} in {log}:{line}: {found:#?}"
            );
        }
        // Its lines are kept, marked as no board.
        let rs: Vec<_> = ing
            .readings
            .iter()
            .filter(|r| r.board_id.as_deref() == Some(id))
            .collect();
        assert!(!rs.is_empty());
        assert!(rs.iter().all(|r| r.sheet_board_id.is_none()));
    }
    // The balance is right: no check-weight warning.
    assert!(find(&ing, "balance.check_weight_off").is_empty());
    // The check weight reads 10 g within the balance's repeatability.
    let ref_g: Vec<f64> = ing
        .readings
        .iter()
        .filter(|r| r.board_id.as_deref() == Some(habits::CHECK_WEIGHT_ID))
        .filter(|r| r.status == crate::formats::balance_log::Status::Stable)
        .filter_map(|r| r.mass_g)
        .collect();
    assert!(
        ref_g.len() >= 2 && ref_g.iter().all(|g| (g - 10.0).abs() < 1e-3),
        "{ref_g:?}"
    );
    // masses.parquet: one row per sheet board, no REF-10G or TRAY.
    let dir = tempfile::tempdir().unwrap();
    crate::io::ingest_outputs::write_outputs(&ing, dir.path(), "test").unwrap();
    let mut ids = BTreeSet::new();
    for b in crate::io::tables::read_parquet(&dir.path().join("masses.parquet")).unwrap() {
        let col = crate::io::tables::Cols {
            batch: &b,
            path: std::path::Path::new("masses.parquet"),
        };
        let s = col.str("board_id").unwrap();
        ids.extend((0..b.num_rows()).map(|i| s.value(i).to_string()));
    }
    assert_eq!(ids, sheet_boards(&c));
}

#[test]
fn a_check_weight_off_its_nominal_is_warned() {
    let mut files = BTreeMap::new();
    files.insert(
        "campaign.csv".to_string(),
        b"measurement_id,board_id,setup,file\nM1,PCB-01,free,m.uff\n".to_vec(),
    );
    files.insert(
        "scale/a.log".to_string(),
        b"# check\n2025-03-03T08:00:00 REF-10G S S 10.0012 g\n2025-03-03T08:00:05 REF-10G S S 10.0011 g\n\
          2025-03-03T08:01:00 ref_200mg S S 0.2000 g\n2025-03-03T08:02:00 PCB-01 S S 13.0000 g\n"
            .to_vec(),
    );
    let ing = read_campaign(&InMemory(&files), &IngestConfig::default(), &|| {}).unwrap();
    let f = find(&ing, "balance.check_weight_off");
    assert_eq!(f.len(), 1, "{:#?}", ing.findings);
    assert_eq!(
        (f[0].file.as_deref(), f[0].line),
        (Some("scale/a.log"), Some(2))
    );
    assert!(f[0].message.contains("REF-10G"));
    // Neither check weight is a board.
    assert_eq!(ing.masses.len(), 1);
    assert_eq!(find(&ing, "balance.not_a_board").len(), 2);
}

#[test]
fn a_board_weighed_on_another_day_joins_its_own_mass() {
    let (c, ing) = simulate_and_ingest(Habits {
        reweighed_board: Some(true),
        ..Default::default()
    });
    assert_population(&c, &ing);
    let [board, file] = c.truth.habits.as_ref().unwrap().reweighed.clone().unwrap();
    assert!(c.files.contains_key(&file));
    let bal = &c.truth.scenario.balance;
    // Without the habit every board is weighed on the first and the last measurement day.
    let usual_days = 2;
    for m in &ing.masses {
        let (days, n) = if m.board_id == board {
            (
                usual_days + 1,
                (bal.sessions_per_board + 1) * bal.stable_per_session,
            )
        } else {
            (usual_days, bal.sessions_per_board * bal.stable_per_session)
        };
        assert_eq!((m.n_days, m.n_stable), (days, n), "{}", m.board_id);
    }
    assert!(find(&ing, "balance.mass_changed_between_days").is_empty());
}

#[test]
fn a_board_whose_mass_changed_between_days_is_flagged() {
    let mut files = BTreeMap::new();
    files.insert(
        "campaign.csv".to_string(),
        b"measurement_id,board_id,setup,file\nM1,PCB-01,free,m.uff\n".to_vec(),
    );
    files.insert(
        "scale/a.log".to_string(),
        b"2025-03-03T08:00:00 PCB-01 S S 13.0000 g\n2025-03-03T08:00:05 PCB-01 S S 13.0001 g\n\
          2025-03-05T08:00:00 PCB-01 S S 13.0100 g\n2025-03-05T08:00:05 PCB-01 S S 13.0101 g\n"
            .to_vec(),
    );
    let ing = read_campaign(&InMemory(&files), &IngestConfig::default(), &|| {}).unwrap();
    let f = find(&ing, "balance.mass_changed_between_days");
    assert_eq!(f.len(), 1, "{:#?}", ing.findings);
    assert_eq!(ing.masses[0].n_days, 2);
}

#[test]
fn misspelt_board_ids_resolve_to_the_sheet_board() {
    let (c, ing) = simulate_and_ingest(Habits {
        id_variants: Some(true),
        ..Default::default()
    });
    assert_population(&c, &ing);
    let h = c.truth.habits.as_ref().unwrap();
    assert_eq!(h.sheet_id_variants.len(), 2, "{h:?}");
    // The unpadded spelling on one row: resolved, warned with its line.
    let [mid, spelt] = &h.sheet_id_variants[0];
    assert!(!spelt.ends_with(' '));
    let line = sheet_line(&ing, mid);
    let f = find(&ing, "sheet.board_id_variant");
    assert!(
        f.iter().any(|f| f.line == Some(line)
            && f.file.as_deref() == Some("campaign.csv")
            && f.severity == Severity::Warning
            && f.message.contains(spelt.as_str())),
        "{f:#?}"
    );
    // The trailing space on another row.
    let [mid, spelt] = &h.sheet_id_variants[1];
    assert!(spelt.ends_with(' '));
    let line = sheet_line(&ing, mid);
    let f = find(&ing, "sheet.board_id_whitespace");
    assert!(
        f.iter()
            .any(|f| f.line == Some(line) && f.file.as_deref() == Some("campaign.csv")),
        "{f:#?}"
    );
    // The balance line: resolved to its board, warned with file and line.
    let [at, spelt] = &h.balance_id_variants[0];
    let (file, line) = at.rsplit_once(':').unwrap();
    let line: u64 = line.parse().unwrap();
    let f = find(&ing, "balance.board_id_variant");
    assert!(
        f.iter().any(|f| f.file.as_deref() == Some(file)
            && f.line == Some(line)
            && f.message.contains(spelt.as_str())),
        "{f:#?}"
    );
    let r = ing
        .readings
        .iter()
        .find(|r| r.file == file && r.line == line)
        .unwrap();
    assert_eq!(r.board_id.as_deref(), Some(spelt.as_str()));
    let canonical = r.sheet_board_id.clone().unwrap();
    assert!(sheet_boards(&c).contains(&canonical));
    // Its reading counts for that board: all stable readings of it are in the mass.
    let bal = &c.truth.scenario.balance;
    let m = ing.masses.iter().find(|m| m.board_id == canonical).unwrap();
    assert_eq!(m.n_stable, bal.sessions_per_board * bal.stable_per_session);
    assert!(find(&ing, "balance.not_a_board").is_empty());
}

#[test]
fn ambiguous_ids_are_not_joined() {
    assert_eq!(crate::campaign::board_key("PCB-03"), "PCB|3");
    assert_eq!(crate::campaign::board_key(" pcb_3 "), "PCB|3");
    assert_eq!(crate::campaign::board_key("PCB03"), "PCB|3");
    assert_ne!(
        crate::campaign::board_key("PCB-1-2"),
        crate::campaign::board_key("PCB-12")
    );
    assert_eq!(habits::variant_spelling("PCB-03"), "PCB-3");
    // Two rows, two spellings of one key, equally often: two boards, each warned; a balance
    // line `pcb-3` could be either: not joined; `PCB-09` looks like a board but is none.
    let mut files = BTreeMap::new();
    files.insert(
        "campaign.csv".to_string(),
        b"measurement_id,board_id,setup,file\nM1,PCB-03,free,a.uff\nM2,PCB-3,free,b.uff\n".to_vec(),
    );
    files.insert(
        "scale/a.log".to_string(),
        b"2025-03-03T08:00:00 PCB-03 S S 13.0000 g\n2025-03-03T08:00:01 PCB-3 S S 13.0000 g\n\
          2025-03-03T08:00:02 pcb-3 S S 13.0000 g\n2025-03-03T08:00:03 PCB-09 S S 13.0000 g\n"
            .to_vec(),
    );
    let ing = read_campaign(&InMemory(&files), &IngestConfig::default(), &|| {}).unwrap();
    let amb = find(&ing, "sheet.board_id_ambiguous");
    assert_eq!(
        amb.iter().map(|f| f.line).collect::<Vec<_>>(),
        vec![Some(2), Some(3)],
        "{amb:#?}"
    );
    let f = find(&ing, "balance.board_id_ambiguous");
    assert_eq!(f.len(), 1);
    assert_eq!(
        (f[0].file.as_deref(), f[0].line),
        (Some("scale/a.log"), Some(3))
    );
    assert_eq!(f[0].severity, Severity::RecordDropped);
    let f = find(&ing, "balance.unknown_board");
    assert_eq!((f.len(), f[0].line), (1, Some(4)));
    let boards: BTreeSet<&str> = ing.masses.iter().map(|m| m.board_id.as_str()).collect();
    assert_eq!(boards, BTreeSet::from(["PCB-03", "PCB-3"]));
    assert!(ing.masses.iter().all(|m| m.n_stable == 1));
}

#[test]
fn a_repeated_measurement_keeps_the_repeat_and_quarantines_the_invalid_one() {
    let (c, ing) = simulate_and_ingest(Habits {
        repeated_measurement: Some(true),
        ..Default::default()
    });
    assert_population(&c, &ing);
    let [bad, rep] = c.truth.habits.as_ref().unwrap().invalid_measurements[0].clone();
    let f = find(&ing, "sheet.marked_invalid");
    assert_eq!(f.len(), 1, "{f:#?}");
    assert_eq!(f[0].severity, Severity::Quarantined);
    assert_eq!(f[0].file.as_deref(), Some("campaign.csv"));
    assert_eq!(f[0].line, Some(sheet_line(&ing, &bad)));
    assert_eq!(f[0].measurement_id.as_deref(), Some(bad.as_str()));
    let m = |id: &str| {
        ing.measurements
            .iter()
            .find(|m| m.row.measurement_id == id)
            .unwrap()
    };
    assert!(m(&bad).quarantine.is_some() && m(&bad).records.is_empty());
    assert!(m(&rep).quarantine.is_none() && !m(&rep).records.is_empty());
    assert!(find(&ing, "sheet.repeat_of_valid").is_empty());
    assert!(find(&ing, "sheet.repeat_of_unknown").is_empty());
    assert!(find(&ing, "sheet.note_mentions_invalid").is_empty());
    // Every other measurement comes through.
    assert_eq!(
        ing.measurements
            .iter()
            .filter(|m| m.quarantine.is_some())
            .count(),
        1
    );
    // The bad UFF really is bad: its spectra have no resonance standing out of the noise
    // (peak over median |H| at the hammer point), the repeat's do.
    let dyn_range = |file: &str| {
        let u = crate::formats::uff::parse(&c.files[file]).unwrap();
        u.datasets
            .iter()
            .find_map(|d| match d {
                crate::formats::uff::Dataset::Function(f) if f.response_node == 1 => match &f
                    .ordinate
                {
                    crate::formats::uff::Ordinate::Complex { re, im } => {
                        let mut a: Vec<f64> = re.iter().zip(im).map(|(r, i)| r.hypot(*i)).collect();
                        a.sort_by(f64::total_cmp);
                        Some(a[a.len() - 1] / a[a.len() / 2])
                    }
                    _ => None,
                },
                _ => None,
            })
            .unwrap()
    };
    let (rb, rr) = (dyn_range(&m(&bad).row.file), dyn_range(&m(&rep).row.file));
    assert!(rb < 10.0 && rr > 10.0 * rb, "bad {rb:.1}, repeat {rr:.1}");
}

#[test]
fn repeat_of_a_row_not_marked_invalid_is_warned() {
    let mut files = BTreeMap::new();
    files.insert(
        "campaign.csv".to_string(),
        b"measurement_id,board_id,setup,file,notes,valid\n\
          M1,PCB-01,free,a.uff,bad hit,\n\
          M2,PCB-01,free,b.uff,repeat of M1,\n\
          M3,PCB-01,free,c.uff,,no\n\
          M4,PCB-01,free,d.uff,laser invalid on 3 points,\n"
            .to_vec(),
    );
    // The files exist (not UFF: those rows are quarantined for that, after the marks).
    for f in ["a.uff", "b.uff", "c.uff", "d.uff"] {
        files.insert(f.to_string(), b"not a UFF".to_vec());
    }
    let ing = read_campaign(&InMemory(&files), &IngestConfig::default(), &|| {}).unwrap();
    let line = |code: &str| find(&ing, code).iter().map(|f| f.line).collect::<Vec<_>>();
    assert_eq!(line("sheet.repeat_of_valid"), vec![Some(3)]);
    assert_eq!(line("sheet.marked_invalid"), vec![Some(4)]);
    assert_eq!(line("sheet.note_mentions_invalid"), vec![Some(5)]);
}

#[test]
fn scan_grids_differ_between_setups_and_sessions() {
    let (c, ing) = simulate_and_ingest(Habits {
        scan_grids: Some(true),
        ..Default::default()
    });
    assert_population(&c, &ing);
    let h = c.truth.habits.as_ref().unwrap();
    assert!(!h.shifted_grid_measurements.is_empty());
    let f = find(&ing, "campaign.scan_grid_inconsistent");
    for mid in &h.shifted_grid_measurements {
        let file = &ing
            .measurements
            .iter()
            .find(|m| &m.row.measurement_id == mid)
            .unwrap()
            .row
            .file;
        assert!(
            f.iter()
                .any(|f| f.measurement_id.as_deref() == Some(mid.as_str())
                    && f.file.as_deref() == Some(file.as_str())),
            "{mid}: {f:#?}"
        );
    }
    // Every bolted measurement has the coarser grid, every free one the board's; all come
    // through.
    let board = crate::fem::tests::helpers::thin_board();
    let n_free = board.scan_grid.nx * board.scan_grid.ny;
    for m in &ing.measurements {
        assert!(m.quarantine.is_none());
        // Free: the hammer point is a scan point; bolted: the shaker reference is not.
        match m.row.setup {
            Some(crate::formats::sheet::Setup::Free) => assert_eq!(m.points.len(), n_free),
            _ => assert!(
                m.points.len() - 1 < n_free && m.points.len() > 9,
                "{}",
                m.points.len()
            ),
        }
    }
}

#[test]
fn scan_points_off_the_board_are_flagged_with_file_and_node() {
    let (c, ing) = simulate_and_ingest(Habits {
        off_board_points: Some(true),
        ..Default::default()
    });
    assert_population(&c, &ing);
    let h = c.truth.habits.as_ref().unwrap();
    assert!(!h.off_board_nodes.is_empty());
    let f = find(&ing, "uff.point_off_plane");
    assert_eq!(f.len(), h.off_board_nodes.len(), "{f:#?}");
    for (mid, node) in &h.off_board_nodes {
        let m = ing
            .measurements
            .iter()
            .find(|m| &m.row.measurement_id == mid)
            .unwrap();
        assert!(
            f.iter()
                .any(|f| f.measurement_id.as_deref() == Some(mid.as_str())
                    && f.file.as_deref() == Some(m.row.file.as_str())
                    && f.record.as_deref() == Some(format!("node {node}").as_str())),
            "{mid} node {node}: {f:#?}"
        );
        // Its response is the base motion (transmissibility about 1), no board mode.
        let r = m.records.iter().find(|r| r.node == *node);
        if let Some(r) = r {
            let im = r.im.as_ref().unwrap();
            let worst =
                r.re.iter()
                    .zip(im)
                    .map(|(a, b)| (a.hypot(*b) - 1.0).abs())
                    .fold(0.0, f64::max);
            assert!(
                worst < 0.3,
                "{mid} node {node}: |T| departs from 1 by {worst}"
            );
        }
    }
}

#[test]
fn gaps_in_temperature_and_date_are_noted_and_the_rows_kept() {
    let (c, ing) = simulate_and_ingest(Habits {
        sheet_gaps: Some(true),
        ..Default::default()
    });
    assert_population(&c, &ing);
    let h = c.truth.habits.as_ref().unwrap();
    assert!(!h.blank_temperature.is_empty() && !h.blank_date.is_empty());
    let f = find(&ing, "sheet.missing_value");
    assert_eq!(
        f.len(),
        h.blank_temperature.len() + h.blank_date.len(),
        "{f:#?}"
    );
    for (col, ids) in [
        ("temperature_c", &h.blank_temperature),
        ("date", &h.blank_date),
    ] {
        for mid in ids {
            let line = sheet_line(&ing, mid);
            assert!(
                f.iter().any(|f| f.line == Some(line)
                    && f.file.as_deref() == Some("campaign.csv")
                    && f.message.contains(col)),
                "{mid} {col}: {f:#?}"
            );
            let m = ing
                .measurements
                .iter()
                .find(|m| &m.row.measurement_id == mid)
                .unwrap();
            assert!(m.quarantine.is_none() && !m.records.is_empty());
            match col {
                "date" => assert!(m.row.date.is_none()),
                _ => assert!(m.row.temperature_c.is_none()),
            }
        }
    }
}

#[test]
fn the_realistic_preset_ingests_with_every_habit_found() {
    let mut s = scenario(Habits::default());
    s.preset = Preset::Realistic;
    let c = simulate(&s, &crate::fem::tests::helpers::thin_board(), 5).unwrap();
    let ing = read_campaign(&InMemory(&c.files), &IngestConfig::default(), &|| {}).unwrap();
    assert_population(&c, &ing);
    for code in [
        "balance.not_a_board",
        "sheet.board_id_variant",
        "sheet.board_id_whitespace",
        "balance.board_id_variant",
        "sheet.marked_invalid",
        "uff.point_off_plane",
        "campaign.scan_grid_inconsistent",
        "sheet.missing_value",
    ] {
        assert!(!find(&ing, code).is_empty(), "{code}");
    }
    assert_eq!(
        ing.measurements
            .iter()
            .filter(|m| m.quarantine.is_some())
            .count(),
        1
    );
}

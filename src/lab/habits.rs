//! The habits of a real lab in the campaign files (scenario `[habits]`, all on under
//! `preset = "realistic"`), drawn from their own child stream ([`Stream::Habits`]) so that a
//! scenario without habits keeps every other draw and writes the same bytes.
//!
//! - `reference_weights`: a check weight `REF-10G` read at the start of every weighing
//!   session (10 g with the balance's repeatability), and before every board the tray it
//!   sits on zeroed (`Z A`) and tared (`T S <tray>`) under the ID `TRAY`. Neither ID is a
//!   board of the sheet (`measure::balance_logs`).
//! - `reweighed_board`: one board weighed again on a later day, in a log file of its own.
//! - `id_variants`: one sheet row and one stable balance line of a board spell its ID
//!   without zero padding (`PCB-3` for `PCB-03`); another sheet row has a trailing space.
//! - `repeated_measurement`: a free-free measurement is preceded by a bad one of the same
//!   board (hammer double hit: its records are mostly noise); both rows stay on the sheet,
//!   the bad one's note starts with `INVALID`, the repeat's says `repeat of <id>`.
//! - `scan_grids`: bolted measurements on a coarser grid than the free ones, shifted by
//!   1 mm in x on every bolted day after the first (the head re-aligned).
//! - `off_board_points`: two scan points off the board in bolted measurements: the head of
//!   the first bolt (hole centre, 2.5 mm above the board) and the fixture beside the board
//!   edge. Both move with the shaker base (no board mode).
//! - `sheet_gaps`: empty temperature cells on a few rows, an empty date on others.
//!
//! What happened where is kept in the truth ([`HabitsTruth`]) for the tests.

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::scenario::Scenario;
use super::truth::{Plan, SetupKind};
use super::{child_seed, LabError, Stream};
use crate::fem::Board;

/// The ID of the check weight in the balance logs.
pub const CHECK_WEIGHT_ID: &str = "REF-10G";
/// Its nominal mass, g.
pub const CHECK_WEIGHT_G: f64 = 10.0;
/// The ID of the tray the boards are weighed on.
pub const TRAY_ID: &str = "TRAY";
/// Height of a bolt head above the board, m.
const BOLT_HEAD_Z_M: f64 = 2.5e-3;

/// Scan points of one measurement when they differ from the board's scan grid: points on
/// the board (x, y in m, z = 0), then points off it (x, y, z in m), numbered on in that order.
#[derive(Clone, Debug, PartialEq)]
pub struct ScanGrid {
    pub board: Vec<[f64; 2]>,
    pub off_board: Vec<[f64; 3]>,
}

impl ScanGrid {
    /// Every point with its z, board points first (node id = position + 1).
    pub fn all_points(&self) -> Vec<[f64; 3]> {
        self.board
            .iter()
            .map(|p| [p[0], p[1], 0.0])
            .chain(self.off_board.iter().copied())
            .collect()
    }
}

/// What the habits changed in one planned measurement (all default: nothing).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MeasurementHabits {
    /// The board ID as written on the sheet, when it differs from the board's ID.
    pub sheet_board_id: Option<String>,
    /// The temperature cell is left empty.
    pub temperature_blank: bool,
    /// The date cell is left empty.
    pub date_blank: bool,
    /// A bad measurement (repeated afterwards): its records are mostly noise.
    pub invalid: bool,
    /// Its own scan points (`None`: the board's scan grid).
    pub grid: Option<ScanGrid>,
}

/// Where the habits left their marks, for tests and readers of the truth.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct HabitsTruth {
    /// IDs in the balance logs that are not boards.
    pub non_board_ids: Vec<String>,
    /// Bad measurements kept on the sheet and the measurement that repeats each.
    pub invalid_measurements: Vec<[String; 2]>,
    /// Sheet rows whose board_id is spelled otherwise: (measurement_id, spelling).
    pub sheet_id_variants: Vec<[String; 2]>,
    /// Balance lines whose board ID is spelled otherwise: `file:line` and the spelling.
    pub balance_id_variants: Vec<[String; 2]>,
    /// The board weighed again on a later day, and the log file of that weighing.
    pub reweighed: Option<[String; 2]>,
    /// Measurements whose scan grid is shifted from their setup's first session's.
    pub shifted_grid_measurements: Vec<String>,
    /// Scan points off the board: (measurement_id, node id).
    pub off_board_nodes: Vec<(String, i64)>,
    /// Sheet rows with an empty temperature cell.
    pub blank_temperature: Vec<String>,
    /// Sheet rows with an empty date cell.
    pub blank_date: Vec<String>,
}

/// The board's ID as a careless hand writes it: without the zero padding (`PCB-3`), or in
/// lower case where there is no padding to drop.
pub fn variant_spelling(id: &str) -> String {
    match id.rsplit_once('-') {
        Some((head, num)) if num.len() > 1 && num.starts_with('0') => {
            format!("{head}-{}", num.trim_start_matches('0'))
        }
        _ => id.to_ascii_lowercase(),
    }
}

/// The grid of bolted measurements: two columns and a row fewer than the board's scan grid,
/// 1 mm further from the edges (keeps clear of the holes' edges after a 1 mm shift).
fn bolted_grid(board: &Board, shift_x_m: f64) -> Vec<[f64; 2]> {
    let g = &board.scan_grid;
    let (nx, ny) = (g.nx.saturating_sub(2).max(3), g.ny.saturating_sub(1).max(3));
    let margin = g.margin_m + 1e-3;
    let coord =
        |n: usize, len: f64, i: usize| margin + (len - 2.0 * margin) * i as f64 / (n - 1) as f64;
    let mut pts = Vec::with_capacity(nx * ny);
    for j in 0..ny {
        for i in 0..nx {
            pts.push([
                coord(nx, board.length_x_m, i) + shift_x_m,
                coord(ny, board.width_y_m, j),
            ]);
        }
    }
    pts
}

/// Apply the measurement-level habits to the plan: insert the bad measurement before its
/// repeat (renumbering the sheet), then spellings, gaps and grids. Returns what was done.
pub fn apply(s: &Scenario, board: &Board, plan: &mut Plan) -> Result<HabitsTruth, LabError> {
    let h = s.habits();
    let mut t = HabitsTruth::default();
    if !h.any() {
        return Ok(t);
    }
    let mut rng = ChaCha8Rng::seed_from_u64(child_seed(plan.seed, Stream::Habits, 0));
    let ms = &mut plan.measurements;

    if h.repeated_measurement {
        let free: Vec<usize> = (0..ms.len())
            .filter(|&i| ms[i].setup == SetupKind::Free)
            .collect();
        if !free.is_empty() {
            let k = free[((rng.random::<f64>() * free.len() as f64) as usize).min(free.len() - 1)];
            let mut bad = ms[k].clone();
            bad.habits.invalid = true;
            // Ten minutes before the repeat.
            if let Ok(d) = chrono::NaiveDateTime::parse_from_str(&bad.date, "%Y-%m-%dT%H:%M:%S") {
                bad.date = (d - chrono::Duration::minutes(10))
                    .format("%Y-%m-%dT%H:%M:%S")
                    .to_string();
            }
            ms.insert(k, bad);
            for (i, m) in ms.iter_mut().enumerate() {
                m.index = i;
                m.measurement_id = format!("M{:03}", i + 1);
                m.file = format!("vibrometer/M{:03}.uff", i + 1);
            }
            let (bad_id, rep_id) = (
                ms[k].measurement_id.clone(),
                ms[k + 1].measurement_id.clone(),
            );
            ms[k].notes = format!("INVALID - hammer double hit, overload; repeated as {rep_id}");
            ms[k + 1].notes = format!(
                "repeat of {bad_id}: {bad_id} invalid (hammer double hit); {}",
                ms[k + 1].notes
            );
            t.invalid_measurements.push([bad_id, rep_id]);
        }
    }
    // Rows another habit already marks are left alone, so each habit shows on its own.
    let touched = |m: &super::truth::Planned| {
        m.habits.invalid || m.notes.starts_with("repeat of") || m.habits.sheet_board_id.is_some()
    };

    if h.id_variants {
        let n_boards = plan.boards.len();
        // Rows per board, in sheet order.
        let rows_of: Vec<Vec<usize>> = (0..n_boards)
            .map(|b| (0..ms.len()).filter(|&i| ms[i].board == b).collect())
            .collect();
        // The board with the most rows, so the usual spelling stays the majority.
        if let Some(b) = (0..n_boards).max_by_key(|&b| (rows_of[b].len(), usize::MAX - b)) {
            let rows: Vec<usize> = rows_of[b]
                .iter()
                .copied()
                .filter(|&i| !touched(&ms[i]))
                .collect();
            if rows.len() >= 3 {
                let i = rows[1];
                let v = variant_spelling(&ms[i].board_id);
                ms[i].habits.sheet_board_id = Some(v.clone());
                t.sheet_id_variants.push([ms[i].measurement_id.clone(), v]);
            }
            // A trailing space on another board's row (or this board's last row).
            let other = (0..n_boards)
                .find(|&o| o != b && !rows_of[o].is_empty())
                .unwrap_or(b);
            if let Some(&i) = rows_of[other].iter().rev().find(|&&i| !touched(&ms[i])) {
                let v = format!("{} ", ms[i].board_id);
                ms[i].habits.sheet_board_id = Some(v.clone());
                t.sheet_id_variants.push([ms[i].measurement_id.clone(), v]);
            }
        }
    }

    if h.sheet_gaps {
        let n = ms.len();
        let k = (n / 20).max(1);
        let mut free_rows: Vec<usize> = (0..n).filter(|&i| !touched(&ms[i])).collect();
        for what in 0..2 {
            for _ in 0..k {
                if free_rows.is_empty() {
                    break;
                }
                let j = ((rng.random::<f64>() * free_rows.len() as f64) as usize)
                    .min(free_rows.len() - 1);
                let i = free_rows.remove(j);
                if what == 0 {
                    ms[i].habits.temperature_blank = true;
                    t.blank_temperature.push(ms[i].measurement_id.clone());
                } else {
                    ms[i].habits.date_blank = true;
                    t.blank_date.push(ms[i].measurement_id.clone());
                }
            }
        }
    }

    if h.scan_grids || h.off_board_points {
        let first_bolted_day = ms
            .iter()
            .find(|m| m.setup == SetupKind::Bolted)
            .map(|m| m.date[..10].to_string());
        let off_board = if h.off_board_points {
            let hole = board.holes.first();
            let mut v = vec![];
            if let Some(hole) = hole {
                v.push([hole.x_m, hole.y_m, BOLT_HEAD_Z_M]);
            }
            // The fixture beside the board's short edge at x = 0.
            v.push([-3e-3, 0.5 * board.width_y_m, -1.5e-3]);
            v
        } else {
            vec![]
        };
        for m in ms.iter_mut().filter(|m| m.setup == SetupKind::Bolted) {
            let shifted = h.scan_grids && first_bolted_day.as_deref() != Some(&m.date[..10]);
            let board_pts = if h.scan_grids {
                bolted_grid(board, if shifted { 1e-3 } else { 0.0 })
            } else {
                board.scan_points_m()
            };
            if shifted {
                t.shifted_grid_measurements.push(m.measurement_id.clone());
            }
            for (k, _) in off_board.iter().enumerate() {
                t.off_board_nodes
                    .push((m.measurement_id.clone(), (board_pts.len() + k + 1) as i64));
            }
            m.habits.grid = Some(ScanGrid {
                board: board_pts,
                off_board: off_board.clone(),
            });
        }
    }

    if h.reference_weights {
        t.non_board_ids = vec![CHECK_WEIGHT_ID.to_string(), TRAY_ID.to_string()];
    }
    Ok(t)
}

//! Balance logs in MT-SICS form: `<ISO-8601 timestamp> <board_id> <MT-SICS response>` per line.
//!
//! Every non-comment line becomes a [`Reading`] with its parsed status, so the raw table keeps
//! the whole log (busy, dynamic, error and garbage lines included). A board's mass comes only
//! from stable (`S S`) readings, converted to grams; [`board_masses`] reports mean, count and
//! spread, and flags a board whose stable readings disagree more than the balance resolution
//! suggests. The resolution `d` is inferred from the number of decimals the balance printed
//! (MT-SICS prints the value to the readability of the balance).
//!
//! Which board a line's ID names is not decided here: the campaign resolves the IDs against
//! the sheet (`campaign::resolve_balance_ids`) and fills [`Reading::sheet_board_id`]; an ID
//! that is not a board of the sheet (a check weight `REF-10G`, a `TRAY`) stays a reading.

use crate::findings::{Finding, Findings, Severity};
use std::collections::BTreeMap;

/// What a balance line said.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Status {
    /// `S S <value> <unit>`: stable weight, a valid reading.
    Stable,
    /// `S D <value> <unit>`: dynamic, not settled.
    Dynamic,
    /// `S I`, `Z I`, `T I`: balance busy.
    Busy,
    /// `S +`, `Z +`, `T +`: overload.
    Overload,
    /// `S -`, `Z -`, `T -`: underload.
    Underload,
    /// `Z A`: zeroing done.
    Zeroed,
    /// `T S <value> <unit>`: tare done.
    Tared,
    /// `ES`: syntax error.
    SyntaxError,
    /// `ET`: transmission error.
    TransmissionError,
    /// `EL`: logic error.
    LogicError,
    /// The line does not follow `<timestamp> <board> <response>` or the response is unknown.
    Unparsed,
}

impl Status {
    pub fn as_str(self) -> &'static str {
        match self {
            Status::Stable => "stable",
            Status::Dynamic => "dynamic",
            Status::Busy => "busy",
            Status::Overload => "overload",
            Status::Underload => "underload",
            Status::Zeroed => "zeroed",
            Status::Tared => "tared",
            Status::SyntaxError => "syntax_error",
            Status::TransmissionError => "transmission_error",
            Status::LogicError => "logic_error",
            Status::Unparsed => "unparsed",
        }
    }
}

/// One log line.
#[derive(Debug, Clone, PartialEq)]
pub struct Reading {
    pub file: String,
    /// 1-based line number.
    pub line: u64,
    pub timestamp: Option<String>,
    pub time_unix_ns: Option<i64>,
    pub board_id: Option<String>,
    /// The sheet board the line counts for, as the campaign resolved `board_id` against the
    /// sheet (`None`: not a board, or not resolvable). The parser leaves it `None`.
    pub sheet_board_id: Option<String>,
    /// The MT-SICS response as written (after the board id).
    pub response: String,
    pub status: Status,
    /// The value as printed, in `unit`.
    pub value: Option<f64>,
    pub unit: Option<String>,
    /// The value in grams (for weight-carrying responses with a known unit).
    pub mass_g: Option<f64>,
    /// Readability inferred from the printed decimals, in grams.
    pub resolution_g: Option<f64>,
}

fn unit_to_g(unit: &str) -> Option<f64> {
    match unit {
        "g" => Some(1.0),
        "mg" => Some(1e-3),
        "kg" => Some(1e3),
        _ => None,
    }
}

/// Decimals printed in a numeric token (`12.3450` → 4).
fn decimals(token: &str) -> usize {
    token.split_once('.').map(|(_, f)| f.len()).unwrap_or(0)
}

/// Parse the MT-SICS response tokens (after timestamp and board id).
fn parse_response(tokens: &[&str]) -> (Status, Option<(f64, String, f64)>) {
    let weight = |rest: &[&str]| -> Option<(f64, String, f64)> {
        // value and unit may be separated by spaces; some balances glue a sign with spaces
        // (`S S   -  0.0012 g`), so join everything but the unit.
        if rest.len() < 2 {
            return None;
        }
        let unit = rest[rest.len() - 1];
        let factor = unit_to_g(unit)?;
        let num: String = rest[..rest.len() - 1].concat();
        let v: f64 = num.parse().ok()?;
        if !v.is_finite() {
            return None;
        }
        let d = 10f64.powi(-(decimals(&num) as i32)) * factor;
        Some((v, unit.to_string(), d))
    };
    match tokens {
        ["ES"] => (Status::SyntaxError, None),
        ["ET"] => (Status::TransmissionError, None),
        ["EL"] => (Status::LogicError, None),
        ["S" | "Z" | "T" | "SI", "I"] => (Status::Busy, None),
        ["S" | "Z" | "T" | "SI", "+"] => (Status::Overload, None),
        ["S" | "Z" | "T" | "SI", "-"] => (Status::Underload, None),
        ["Z", "A"] => (Status::Zeroed, None),
        ["S" | "SI", "S", rest @ ..] => match weight(rest) {
            Some(w) => (Status::Stable, Some(w)),
            None => (Status::Unparsed, None),
        },
        ["S" | "SI", "D", rest @ ..] => match weight(rest) {
            Some(w) => (Status::Dynamic, Some(w)),
            None => (Status::Unparsed, None),
        },
        ["T", "S", rest @ ..] => match weight(rest) {
            Some(w) => (Status::Tared, Some(w)),
            None => (Status::Unparsed, None),
        },
        _ => (Status::Unparsed, None),
    }
}

/// Parse one log file. Lines starting with `#` and blank lines are skipped; every other line
/// yields a [`Reading`]; unparseable lines yield a reading with [`Status::Unparsed`] and a
/// finding naming the line.
pub fn parse(bytes: &[u8], file: &str) -> (Vec<Reading>, Findings) {
    let mut out = Vec::new();
    let mut findings = Findings::default();
    for (i, raw_line) in bytes.split(|&b| b == b'\n').enumerate() {
        let line_no = i as u64 + 1;
        let text = String::from_utf8_lossy(raw_line);
        let text = text.trim_end_matches('\r').trim();
        if text.is_empty() || text.starts_with('#') {
            continue;
        }
        let tokens: Vec<&str> = text.split_whitespace().collect();
        let (timestamp, time_ns) = match tokens.first() {
            Some(t) => {
                let ns = crate::formats::sheet::parse_iso_datetime_ns(t);
                (ns.map(|_| t.to_string()), ns)
            }
            None => (None, None),
        };
        let mut reading = Reading {
            file: file.to_string(),
            line: line_no,
            timestamp,
            time_unix_ns: time_ns,
            board_id: None,
            sheet_board_id: None,
            response: String::new(),
            status: Status::Unparsed,
            value: None,
            unit: None,
            mass_g: None,
            resolution_g: None,
        };
        if time_ns.is_none() || tokens.len() < 3 {
            reading.response = text.to_string();
            findings.push(
                Finding::new(
                    Severity::RecordDropped,
                    "balance.unparsed_line",
                    format!(
                        "expected `<ISO-8601 timestamp> <board_id> <MT-SICS response>`, found {:?}",
                        truncate(text, 80)
                    ),
                )
                .file(file)
                .line(line_no),
            );
            out.push(reading);
            continue;
        }
        reading.board_id = Some(tokens[1].to_string());
        reading.response = tokens[2..].join(" ");
        let (status, w) = parse_response(&tokens[2..]);
        reading.status = status;
        if let Some((v, unit, d)) = w {
            let f = unit_to_g(&unit).unwrap_or(f64::NAN);
            reading.value = Some(v);
            reading.mass_g = Some(v * f);
            reading.unit = Some(unit);
            reading.resolution_g = Some(d);
        }
        if status == Status::Unparsed {
            findings.push(
                Finding::new(
                    Severity::RecordDropped,
                    "balance.unknown_response",
                    format!(
                        "board {}: expected an MT-SICS response (S S/S D <value> g|mg|kg, S I, S +, S -, Z A, T S, ES, ET, EL), found {:?}",
                        tokens[1],
                        truncate(&reading.response, 60)
                    ),
                )
                .file(file)
                .line(line_no),
            );
        }
        out.push(reading);
    }
    (out, findings)
}

fn truncate(s: &str, n: usize) -> String {
    if s.chars().count() <= n {
        s.to_string()
    } else {
        s.chars().take(n).collect::<String>() + "…"
    }
}

/// Mass of one board from its stable readings.
#[derive(Debug, Clone, PartialEq)]
pub struct BoardMass {
    pub board_id: String,
    pub mass_g: f64,
    pub n_stable: usize,
    /// Sample standard deviation of the stable readings (0 for a single reading), grams.
    pub std_g: f64,
    /// Coarsest readability among the readings used, grams.
    pub resolution_g: f64,
    /// True when the stable readings disagree more than the resolution suggests.
    pub inconsistent: bool,
    /// Days (the timestamps' dates) with a stable reading.
    pub n_days: usize,
    /// Largest minus smallest of the per-day means, grams (0 for one day).
    pub day_spread_g: f64,
    /// Sum of squares of the per-day means about their unweighted mean, g² (0 for one day):
    /// with `n_days - 1` degrees of freedom, what re-placing the board on the pan changes.
    pub day_means_ss_g2: f64,
    /// Σ over the days of (the day's share of the stable readings)²: `mass_g` is the
    /// readings' mean, so its variance is one day mean's times this (1 for one day).
    pub day_share_sq_sum: f64,
}

/// Parameters of the mass summary.
#[derive(Debug, Clone, Copy)]
pub struct MassParams {
    /// A board is flagged when the sample std of its stable readings exceeds this many
    /// resolution steps `d`. Repeatability of a balance is typically about 1 d, and re-placing
    /// the part adds little more; 3 d leaves room for that and still catches a reading taken
    /// with something else on the pan or of the wrong board.
    pub max_std_in_d: f64,
}

impl Default for MassParams {
    fn default() -> Self {
        MassParams { max_std_in_d: 3.0 }
    }
}

/// Summarise stable readings per board (sorted by board id).
pub fn board_masses(readings: &[Reading], params: MassParams) -> Vec<BoardMass> {
    let mut by_board: BTreeMap<&str, Vec<&Reading>> = BTreeMap::new();
    for r in readings {
        if r.status == Status::Stable {
            if let (Some(b), Some(_)) = (&r.board_id, r.mass_g) {
                by_board.entry(b.as_str()).or_default().push(r);
            }
        }
    }
    by_board
        .into_iter()
        .map(|(board, rs)| {
            let n = rs.len();
            let vals: Vec<f64> = rs.iter().filter_map(|r| r.mass_g).collect();
            let mean = vals.iter().sum::<f64>() / n as f64;
            let std = if n > 1 {
                (vals.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n as f64 - 1.0)).sqrt()
            } else {
                0.0
            };
            let d = rs
                .iter()
                .filter_map(|r| r.resolution_g)
                .fold(0.0f64, f64::max);
            // Per-day means (the date part of the timestamp; lines without one count apart).
            let mut by_day: BTreeMap<&str, (f64, usize)> = BTreeMap::new();
            for r in &rs {
                let day = r
                    .timestamp
                    .as_deref()
                    .map_or("", |t| t.get(..10).unwrap_or(t));
                let e = by_day.entry(day).or_default();
                e.0 += r.mass_g.unwrap_or(0.0);
                e.1 += 1;
            }
            let day_means: Vec<f64> = by_day.values().map(|(s, k)| s / *k as f64).collect();
            let day_spread = day_means.iter().copied().fold(f64::MIN, f64::max)
                - day_means.iter().copied().fold(f64::MAX, f64::min);
            let day_mean = day_means.iter().sum::<f64>() / day_means.len() as f64;
            let day_ss = day_means.iter().map(|v| (v - day_mean).powi(2)).sum();
            let share_sq = by_day
                .values()
                .map(|(_, k)| (*k as f64 / n as f64).powi(2))
                .sum();
            BoardMass {
                board_id: board.to_string(),
                mass_g: mean,
                n_stable: n,
                std_g: std,
                resolution_g: d,
                inconsistent: n > 1 && std > params.max_std_in_d * d.max(f64::MIN_POSITIVE),
                n_days: by_day.len(),
                day_spread_g: day_spread,
                day_means_ss_g2: day_ss,
                day_share_sq_sum: share_sq,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    const LOG: &str = "# balance XS205, lab 2\n\
        2025-03-01T09:00:00 PCB-01 S D    12.91 g\n\
        2025-03-01T09:00:01 PCB-01 S I\n\
        2025-03-01T09:00:02 PCB-01 S S    12.9873 g\n\
        2025-03-01T09:00:05 PCB-01 S S 12987.4 mg\n\
        \n\
        2025-03-01T09:01:00 PCB-02 ES\n\
        2025-03-01T09:01:02 PCB-02 S S 0.0130012 kg\n\
        2025-03-01T09:01:03 PCB-02 Z A\n\
        garbage line here\n\
        2025-03-01T09:01:04 PCB-02 S Q 1 g\n";

    #[test]
    fn every_line_is_kept_with_its_status() {
        let (r, f) = parse(LOG.as_bytes(), "scale/a.log");
        let st: Vec<Status> = r.iter().map(|r| r.status).collect();
        assert_eq!(
            st,
            vec![
                Status::Dynamic,
                Status::Busy,
                Status::Stable,
                Status::Stable,
                Status::SyntaxError,
                Status::Stable,
                Status::Zeroed,
                Status::Unparsed,
                Status::Unparsed
            ]
        );
        assert_eq!(r[0].line, 2);
        assert_eq!(f.len(), 2);
        assert_eq!(f.0[0].line, Some(10));
        assert_eq!(f.0[1].line, Some(11));
    }

    #[test]
    fn mass_from_stable_readings_in_grams_with_mixed_units() {
        let (r, _) = parse(LOG.as_bytes(), "a.log");
        let m = board_masses(&r, MassParams::default());
        assert_eq!(m.len(), 2);
        assert_eq!(m[0].board_id, "PCB-01");
        assert_eq!(m[0].n_stable, 2);
        assert!((m[0].mass_g - 12.98735).abs() < 1e-9);
        assert!((m[0].resolution_g - 1e-4).abs() < 1e-15);
        assert!(!m[0].inconsistent);
        assert!((m[1].mass_g - 13.0012).abs() < 1e-9);
        assert_eq!(m[1].n_stable, 1);
        assert_eq!((m[0].n_days, m[0].day_means_ss_g2), (1, 0.0));
        assert_eq!(m[0].day_share_sq_sum, 1.0);
    }

    /// Two days' readings: the day means' sum of squares and each day's share of the mean.
    #[test]
    fn re_weighings_on_other_days_give_the_day_means_scatter() {
        let log = "2025-03-01T09:00:00 B S S 12.0001 g\n\
            2025-03-01T09:00:01 B S S 12.0003 g\n\
            2025-03-01T09:00:02 B S S 12.0002 g\n\
            2025-03-04T09:00:00 B S S 12.0006 g\n";
        let (r, _) = parse(log.as_bytes(), "a.log");
        let m = &board_masses(&r, MassParams::default())[0];
        assert_eq!(m.n_days, 2);
        // Day means 12.0002 and 12.0006: about 12.0004, 2 × (2e-4)².
        assert!(
            (m.day_means_ss_g2 - 8e-8).abs() < 1e-15,
            "{}",
            m.day_means_ss_g2
        );
        assert!((m.day_share_sq_sum - (0.75f64.powi(2) + 0.25f64.powi(2))).abs() < 1e-15);
    }

    #[test]
    fn disagreeing_stable_readings_are_flagged() {
        let log = "2025-03-01T09:00:00 B S S 12.9873 g\n2025-03-01T09:00:01 B S S 12.9950 g\n";
        let (r, _) = parse(log.as_bytes(), "a.log");
        let m = board_masses(&r, MassParams::default());
        assert!(m[0].inconsistent, "{m:?}");
    }
}

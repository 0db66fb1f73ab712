//! The measurement sheet `campaign.csv`: RFC 4180 CSV, one row per vibrometer measurement.
//!
//! Parsing is done by the `csv` crate (quoted fields with commas and newlines, CRLF); this
//! module owns the contract on top of it: the required columns, typed optional columns
//! (`torque_nm`, `temperature_c`, `date`, the specimen's measured `length_mm`, `width_mm`,
//! `thickness_mm`), extra columns kept verbatim, and row-level findings
//! naming the file line. A missing required column or an unreadable header is fatal for the
//! sheet (nothing can be matched without it); a bad row only affects its own measurement.
//!
//! Fields are trimmed; a board_id with spaces around it is a warning (`sheet.board_id_whitespace`:
//! the trimmed ID is used). An empty temperature or date cell in a column that other rows fill
//! is an info finding (`sheet.missing_value`): the value is unknown, the row is kept.

use crate::findings::{Finding, Findings, Severity};
use std::collections::BTreeMap;
use thiserror::Error;

/// Columns every sheet must have, in contract order.
pub const REQUIRED: [&str; 4] = ["measurement_id", "board_id", "setup", "file"];
/// Optional columns with a meaning; anything else is an extra column kept as metadata.
pub const OPTIONAL: [&str; 9] = [
    "bolt_set",
    "torque_nm",
    "temperature_c",
    "date",
    "operator",
    "notes",
    "length_mm",
    "width_mm",
    "thickness_mm",
];

/// The specimen's measured dimensions, mm (a careful lab measures every specimen).
pub const DIMENSIONS: [&str; 3] = ["length_mm", "width_mm", "thickness_mm"];

/// Optional columns whose empty cells are reported when other rows fill them.
const GAP_COLUMNS: [&str; 2] = ["temperature_c", "date"];

#[derive(Debug, Error)]
pub enum SheetError {
    #[error("{file}: the sheet is empty (expected a header row with columns {REQUIRED:?})")]
    Empty { file: String },
    #[error("{file}:1: missing required column(s) {missing:?} in header (found {found:?})")]
    MissingColumns {
        file: String,
        missing: Vec<String>,
        found: Vec<String>,
    },
    #[error("{file}:1: duplicate column {column:?} in header")]
    DuplicateColumn { file: String, column: String },
    #[error("{file}:{line}: {msg}")]
    Csv {
        file: String,
        line: u64,
        msg: String,
    },
}

/// The test setup of a measurement.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Setup {
    Free,
    Bolted,
}

impl Setup {
    pub fn parse(s: &str) -> Option<Setup> {
        match s.trim().to_ascii_lowercase().as_str() {
            "free" => Some(Setup::Free),
            "bolted" => Some(Setup::Bolted),
            _ => None,
        }
    }
    pub fn as_str(self) -> &'static str {
        match self {
            Setup::Free => "free",
            Setup::Bolted => "bolted",
        }
    }
    /// The UFF function type the contract prescribes for this setup's response records.
    pub fn expected_function_type(self) -> i32 {
        match self {
            Setup::Free => 4,
            Setup::Bolted => 5,
        }
    }
}

/// One sheet row, typed where the contract gives a type. Raw strings are kept for the typed
/// optional columns too (`*_raw`), so that nothing the lab wrote is lost.
#[derive(Debug, Clone, PartialEq)]
pub struct SheetRow {
    /// 1-based line in the file where the record starts.
    pub line: u64,
    pub measurement_id: String,
    pub board_id: String,
    /// `None` when the setup value is not one the contract knows (the row is then quarantined).
    pub setup: Option<Setup>,
    pub setup_raw: String,
    pub file: String,
    pub bolt_set: Option<String>,
    pub torque_nm: Option<f64>,
    pub temperature_c: Option<f64>,
    /// The date as written (ISO-8601 date or date-time).
    pub date: Option<String>,
    /// The date as nanoseconds since the Unix epoch (UTC; a date without zone is taken as UTC).
    pub date_unix_ns: Option<i64>,
    pub operator: Option<String>,
    pub notes: Option<String>,
    /// The specimen's measured length, width and overall thickness (over its copper), mm, in
    /// the order of [`DIMENSIONS`]; `None` where not given or not a positive number.
    pub dimensions_mm: [Option<f64>; 3],
    /// Extra columns, by header name, verbatim.
    pub extra: BTreeMap<String, String>,
}

/// A parsed sheet.
#[derive(Debug, Clone, Default)]
pub struct Sheet {
    pub rows: Vec<SheetRow>,
    /// Names of extra columns in header order.
    pub extra_columns: Vec<String>,
    pub findings: Findings,
}

fn non_empty(s: &str) -> Option<String> {
    let t = s.trim();
    (!t.is_empty()).then(|| t.to_string())
}

/// Parse an ISO-8601 date or date-time into ns since the Unix epoch (UTC). Accepts
/// `YYYY-MM-DD`, `YYYY-MM-DDThh:mm[:ss[.f]]` (also with a space), with optional `Z` or offset.
pub fn parse_iso_datetime_ns(s: &str) -> Option<i64> {
    use chrono::{DateTime, NaiveDate, NaiveDateTime};
    let s = s.trim();
    if let Ok(dt) = DateTime::parse_from_rfc3339(s) {
        return dt.timestamp_nanos_opt();
    }
    for fmt in ["%Y-%m-%dT%H:%M:%S%.f%:z", "%Y-%m-%d %H:%M:%S%.f%:z"] {
        if let Ok(dt) = DateTime::parse_from_str(s, fmt) {
            return dt.timestamp_nanos_opt();
        }
    }
    let t = s.trim_end_matches('Z');
    for fmt in [
        "%Y-%m-%dT%H:%M:%S%.f",
        "%Y-%m-%d %H:%M:%S%.f",
        "%Y-%m-%dT%H:%M",
        "%Y-%m-%d %H:%M",
    ] {
        if let Ok(dt) = NaiveDateTime::parse_from_str(t, fmt) {
            return dt.and_utc().timestamp_nanos_opt();
        }
    }
    NaiveDate::parse_from_str(t, "%Y-%m-%d")
        .ok()
        .and_then(|d| d.and_hms_opt(0, 0, 0))
        .and_then(|dt| dt.and_utc().timestamp_nanos_opt())
}

/// Parse the sheet. `file` is the name used in messages (relative to the campaign).
pub fn parse(bytes: &[u8], file: &str) -> Result<Sheet, SheetError> {
    // A UTF-8 byte-order mark (Excel writes one) is not part of the first column's name.
    let bytes = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
    let mut rdr = csv::ReaderBuilder::new()
        .has_headers(true)
        .flexible(true)
        .from_reader(bytes);
    let names = column_names(&mut rdr, file)?;
    let extra_columns: Vec<String> = names
        .iter()
        .filter(|n| !REQUIRED.contains(&n.as_str()) && !OPTIONAL.contains(&n.as_str()))
        .cloned()
        .collect();

    let mut sheet = Sheet {
        extra_columns,
        ..Default::default()
    };
    let mut gaps = Gaps {
        empties: vec![],
        filled: [0usize; GAP_COLUMNS.len()],
    };
    let mut rec = csv::ByteRecord::new();
    let mut lines = LineCounter {
        bytes,
        counted_to: 0,
        counted_lines: 1,
    };
    loop {
        let line_hint = rdr.position().line();
        match rdr.read_byte_record(&mut rec) {
            Ok(false) => break,
            Ok(true) => {}
            Err(e) => {
                let line = e.position().map(|p| p.line()).unwrap_or(line_hint);
                sheet.findings.push(
                    Finding::new(
                        Severity::RecordDropped,
                        "sheet.unreadable_row",
                        format!("row cannot be read as CSV ({e}); the row is dropped"),
                    )
                    .file(file)
                    .line(line),
                );
                // A CSV syntax error (e.g. an unterminated quote) may swallow the rest of the
                // file; stop rather than guess.
                break;
            }
        }
        // The csv crate's line counter skips newlines inside quoted fields; count them from the
        // byte offset instead, so the line we report is the one an editor shows.
        let line = match rec.position() {
            // With CRLF the reported start can sit on the previous line's `\n`; step past it.
            Some(p) => {
                let b = p.byte() as usize;
                lines.line_at(if bytes.get(b) == Some(&b'\n') {
                    b + 1
                } else {
                    b
                })
            }
            None => line_hint,
        };
        let (fields, bad_utf8) = utf8_fields(&rec, names.len());
        if fields.iter().all(|f| f.trim().is_empty()) {
            continue; // blank line
        }
        push_row(&mut sheet, &mut gaps, &names, &fields, bad_utf8, file, line);
    }
    note_gaps(&mut sheet, &gaps, file);
    Ok(sheet)
}

/// The header's column names (trimmed); errors when it is unreadable or empty, names a
/// column twice or lacks a required column.
fn column_names(rdr: &mut csv::Reader<&[u8]>, file: &str) -> Result<Vec<String>, SheetError> {
    let headers = match rdr.byte_headers() {
        Ok(h) => h.clone(),
        Err(e) => {
            return Err(SheetError::Csv {
                file: file.into(),
                line: 1,
                msg: format!("unreadable header: {e}"),
            })
        }
    };
    if headers.is_empty() || (headers.len() == 1 && headers[0].is_empty()) {
        return Err(SheetError::Empty { file: file.into() });
    }
    let names: Vec<String> = headers
        .iter()
        .map(|h| String::from_utf8_lossy(h).trim().to_string())
        .collect();
    for (i, n) in names.iter().enumerate() {
        if names[..i].contains(n) {
            return Err(SheetError::DuplicateColumn {
                file: file.into(),
                column: n.clone(),
            });
        }
    }
    let missing: Vec<String> = REQUIRED
        .iter()
        .filter(|r| !names.iter().any(|n| n == *r))
        .map(|s| s.to_string())
        .collect();
    if !missing.is_empty() {
        return Err(SheetError::MissingColumns {
            file: file.into(),
            missing,
            found: names,
        });
    }
    Ok(names)
}

/// Counts the lines up to byte offsets of the sheet (the line an editor shows).
struct LineCounter<'b> {
    bytes: &'b [u8],
    counted_to: usize,
    counted_lines: u64,
}

impl LineCounter<'_> {
    /// The 1-based line of byte offset `byte`.
    fn line_at(&mut self, byte: usize) -> u64 {
        let byte = byte.min(self.bytes.len());
        if byte >= self.counted_to {
            self.counted_lines +=
                memchr::memchr_iter(b'\n', &self.bytes[self.counted_to..byte]).count() as u64;
            self.counted_to = byte;
        } else {
            self.counted_to = 0;
            self.counted_lines = 1 + memchr::memchr_iter(b'\n', &self.bytes[..byte]).count() as u64;
            self.counted_to = byte;
        }
        self.counted_lines
    }
}

/// A row's fields as text, and whether any was not UTF-8 (its invalid bytes replaced).
fn utf8_fields(rec: &csv::ByteRecord, n_columns: usize) -> (Vec<String>, bool) {
    let mut fields: Vec<String> = Vec::with_capacity(n_columns);
    let mut bad_utf8 = false;
    for f in rec.iter() {
        match std::str::from_utf8(f) {
            Ok(s) => fields.push(s.to_string()),
            Err(_) => {
                bad_utf8 = true;
                fields.push(String::from_utf8_lossy(f).into_owned());
            }
        }
    }
    (fields, bad_utf8)
}

/// Empty cells of the columns checked for gaps: (column, line, measurement_id), and per
/// column the rows that fill it.
struct Gaps {
    empties: Vec<(usize, u64, String)>,
    filled: [usize; GAP_COLUMNS.len()],
}

/// Reads the row `fields` at `line` into `sheet` (its row and findings) and `gaps`.
fn push_row(
    sheet: &mut Sheet,
    gaps: &mut Gaps,
    names: &[String],
    fields: &[String],
    bad_utf8: bool,
    file: &str,
    line: u64,
) {
    let idx = |name: &str| names.iter().position(|n| n == name);
    if bad_utf8 {
        sheet.findings.push(
            Finding::new(
                Severity::Warning,
                "sheet.not_utf8",
                "row is not valid UTF-8 (expected UTF-8); invalid bytes replaced by U+FFFD",
            )
            .file(file)
            .line(line),
        );
    }
    if fields.len() != names.len() {
        sheet.findings.push(
            Finding::new(
                Severity::Warning,
                "sheet.field_count",
                format!(
                    "row has {} fields, header has {} (missing fields taken as empty, surplus ignored)",
                    fields.len(),
                    names.len()
                ),
            )
            .file(file)
            .line(line),
        );
    }
    let get = |name: &str| -> String {
        idx(name)
            .and_then(|i| fields.get(i))
            .map(|s| s.trim().to_string())
            .unwrap_or_default()
    };
    let measurement_id = get("measurement_id");
    let num = |name: &str, findings: &mut Findings| -> Option<f64> {
        let raw = get(name);
        if raw.is_empty() {
            return None;
        }
        match raw.parse::<f64>() {
            Ok(v) if v.is_finite() => Some(v),
            _ => {
                findings.push(
                    Finding::new(
                        Severity::Warning,
                        "sheet.not_a_number",
                        format!(
                            "column {name}: expected a number, found {raw:?}; taken as unknown"
                        ),
                    )
                    .file(file)
                    .line(line)
                    .measurement(measurement_id.clone()),
                );
                None
            }
        }
    };
    let torque_nm = num("torque_nm", &mut sheet.findings);
    let dimensions_mm = DIMENSIONS.map(|col| {
        let v = num(col, &mut sheet.findings)?;
        if v > 0.0 {
            return Some(v);
        }
        sheet.findings.push(
            Finding::new(
                Severity::Warning,
                "sheet.not_a_dimension",
                format!(
                    "column {col}: expected a positive length in mm, found {v}; taken as unknown"
                ),
            )
            .file(file)
            .line(line)
            .measurement(measurement_id.clone()),
        );
        None
    });
    let temperature_c = num("temperature_c", &mut sheet.findings);
    let date = non_empty(&get("date"));
    let date_unix_ns = date.as_deref().and_then(parse_iso_datetime_ns);
    if let (Some(d), None) = (&date, date_unix_ns) {
        sheet.findings.push(
            Finding::new(
                Severity::Warning,
                "sheet.bad_date",
                format!("column date: expected ISO-8601 date or date-time, found {d:?}"),
            )
            .file(file)
            .line(line)
            .measurement(measurement_id.clone()),
        );
    }
    let board_raw = idx("board_id")
        .and_then(|i| fields.get(i))
        .cloned()
        .unwrap_or_default();
    if board_raw.trim() != board_raw && !board_raw.trim().is_empty() {
        sheet.findings.push(
            Finding::new(
                Severity::Warning,
                "sheet.board_id_whitespace",
                format!(
                    "board_id {board_raw:?} has spaces around it (expected the bare ID); taken as {:?}",
                    board_raw.trim()
                ),
            )
            .file(file)
            .line(line)
            .measurement(measurement_id.clone()),
        );
    }
    for (k, col) in GAP_COLUMNS.iter().enumerate() {
        if idx(col).is_some() {
            if get(col).is_empty() {
                gaps.empties.push((k, line, measurement_id.clone()));
            } else {
                gaps.filled[k] += 1;
            }
        }
    }
    let setup_raw = get("setup");
    let extra = sheet
        .extra_columns
        .iter()
        .map(|c| (c.clone(), get(c)))
        .collect();
    sheet.rows.push(SheetRow {
        line,
        measurement_id,
        board_id: get("board_id"),
        setup: Setup::parse(&setup_raw),
        setup_raw,
        file: get("file"),
        bolt_set: non_empty(&get("bolt_set")),
        torque_nm,
        temperature_c,
        date,
        date_unix_ns,
        operator: non_empty(&get("operator")),
        notes: non_empty(&get("notes")),
        dimensions_mm,
        extra,
    });
}

/// Gaps: a finding per empty cell of a column the lab fills on other rows.
fn note_gaps(sheet: &mut Sheet, gaps: &Gaps, file: &str) {
    // Gaps: a column the lab fills, left empty on some rows.
    for (k, col) in GAP_COLUMNS.iter().enumerate() {
        if gaps.filled[k] == 0 {
            continue;
        }
        for (kk, line, mid) in &gaps.empties {
            if *kk == k {
                sheet.findings.push(
                    Finding::new(
                        Severity::Info,
                        "sheet.missing_value",
                        format!("column {col} is empty on this row (other rows fill it); taken as unknown"),
                    )
                    .file(file)
                    .line(*line)
                    .measurement(mid.clone()),
                );
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quoted_fields_with_commas_and_newlines_and_extra_columns() {
        let csv = "measurement_id,board_id,setup,file,notes,rig\r\n\
                   m1,PCB-01,free,vibrometer/m1.uff,\"foam, soft\nsecond line\",A\r\n\
                   m2,PCB-02,bolted,vibrometer/m2.uff,,B\r\n";
        let s = parse(csv.as_bytes(), "campaign.csv").unwrap();
        assert_eq!(s.rows.len(), 2);
        assert_eq!(s.rows[0].notes.as_deref(), Some("foam, soft\nsecond line"));
        assert_eq!(
            s.rows[1].line, 4,
            "record after a quoted newline starts on line 4"
        );
        assert_eq!(s.extra_columns, vec!["rig".to_string()]);
        assert_eq!(s.rows[1].extra["rig"], "B");
        assert_eq!(s.rows[1].setup, Some(Setup::Bolted));
        assert!(s.findings.is_empty());
    }

    #[test]
    fn missing_required_column_is_fatal_and_named() {
        let err = parse(b"measurement_id,board_id,file\nm1,b,f\n", "campaign.csv").unwrap_err();
        let msg = err.to_string();
        assert!(msg.contains("setup"), "{msg}");
        assert!(msg.contains("campaign.csv:1"), "{msg}");
    }

    #[test]
    fn empty_sheet_is_an_error() {
        assert!(matches!(
            parse(b"", "campaign.csv"),
            Err(SheetError::Empty { .. })
        ));
    }

    #[test]
    fn bad_numbers_and_dates_are_findings_not_errors() {
        let csv = "measurement_id,board_id,setup,file,torque_nm,date\nm1,b,free,f,abc,yesterday\n";
        let s = parse(csv.as_bytes(), "c.csv").unwrap();
        assert_eq!(s.rows[0].torque_nm, None);
        assert_eq!(s.findings.len(), 2);
        assert!(s.findings.iter().all(|f| f.line == Some(2)));
    }

    #[test]
    fn iso_dates() {
        assert_eq!(
            parse_iso_datetime_ns("1970-01-02"),
            Some(86_400_000_000_000)
        );
        assert_eq!(
            parse_iso_datetime_ns("1970-01-01T00:00:01Z"),
            Some(1_000_000_000)
        );
        assert_eq!(parse_iso_datetime_ns("1970-01-01T01:00:00+01:00"), Some(0));
        assert_eq!(
            parse_iso_datetime_ns("1970-01-01 00:01"),
            Some(60_000_000_000)
        );
        assert_eq!(parse_iso_datetime_ns("not a date"), None);
    }
}

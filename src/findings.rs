//! Findings: what a stage noticed about its input, with enough context to act on.
//!
//! Every stage reports problems as [`Finding`]s rather than dropping data silently: a finding
//! names the file, the 1-based line and/or the record, says what was expected and what was
//! found, and states what the stage did about it (kept, dropped the record, quarantined the
//! measurement). Stages collect findings in a [`Findings`] list, which is written to the stage's
//! report JSON and summarised on stderr.

use serde::{Deserialize, Serialize};
use std::fmt;

/// How serious a finding is, and therefore what happened to the data it concerns.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize, schemars::JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum Severity {
    /// Informational: expected imperfections (an ignored file, a skipped UFF dataset).
    Info,
    /// Data kept, but something looks off (spread of balance readings, inconsistent grid).
    Warning,
    /// A record (one scan point, one log line) was dropped; the measurement goes on.
    RecordDropped,
    /// A whole measurement was quarantined: no output for it; the others proceed.
    Quarantined,
    /// The stage could not run.
    Fatal,
}

impl fmt::Display for Severity {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Severity::Info => "info",
            Severity::Warning => "warning",
            Severity::RecordDropped => "record dropped",
            Severity::Quarantined => "quarantined",
            Severity::Fatal => "fatal",
        })
    }
}

/// One thing a stage noticed, located as precisely as possible.
/// Also the message type of the campaign MCAP's `/ingest/findings` channel.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
pub struct Finding {
    pub severity: Severity,
    /// A short, stable machine-readable code, e.g. `uff.nan_ordinate`, `sheet.duplicate_id`.
    pub code: String,
    /// File relative to the campaign (or stage input) directory.
    pub file: Option<String>,
    /// 1-based line number in `file`, where it applies.
    pub line: Option<u64>,
    /// Record locator inside the file (e.g. `dataset 58 #12 (node 31)`), where it applies.
    pub record: Option<String>,
    /// Measurement concerned, where it applies.
    pub measurement_id: Option<String>,
    /// Human-readable: what was expected, what was found, and what was done.
    pub message: String,
}

impl fmt::Display for Finding {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: ", self.severity)?;
        if let Some(file) = &self.file {
            write!(f, "{file}")?;
            if let Some(line) = self.line {
                write!(f, ":{line}")?;
            }
            write!(f, ": ")?;
        }
        if let Some(rec) = &self.record {
            write!(f, "{rec}: ")?;
        }
        if let Some(m) = &self.measurement_id {
            write!(f, "[{m}] ")?;
        }
        write!(f, "{} ({})", self.message, self.code)
    }
}

/// Builder-style constructor helpers so call sites stay one line long.
impl Finding {
    pub fn new(severity: Severity, code: &str, message: impl Into<String>) -> Self {
        Finding {
            severity,
            code: code.to_string(),
            file: None,
            line: None,
            record: None,
            measurement_id: None,
            message: message.into(),
        }
    }
    pub fn file(mut self, file: impl Into<String>) -> Self {
        self.file = Some(file.into());
        self
    }
    pub fn line(mut self, line: u64) -> Self {
        self.line = Some(line);
        self
    }
    pub fn record(mut self, record: impl Into<String>) -> Self {
        self.record = Some(record.into());
        self
    }
    pub fn measurement(mut self, id: impl Into<String>) -> Self {
        self.measurement_id = Some(id.into());
        self
    }
}

/// An ordered list of findings. Order is deterministic (the order in which the stage visited
/// its inputs), so reports are byte-identical across runs.
#[derive(Debug, Default, Clone, Serialize, Deserialize)]
pub struct Findings(pub Vec<Finding>);

impl Findings {
    pub fn push(&mut self, f: Finding) {
        self.0.push(f);
    }
    pub fn extend(&mut self, other: Findings) {
        self.0.extend(other.0);
    }
    pub fn count(&self, severity: Severity) -> usize {
        self.0.iter().filter(|f| f.severity == severity).count()
    }
    pub fn iter(&self) -> impl Iterator<Item = &Finding> {
        self.0.iter()
    }
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
    pub fn len(&self) -> usize {
        self.0.len()
    }
    /// Counts per severity, for summaries.
    pub fn summary(&self) -> String {
        let parts: Vec<String> = [
            Severity::Fatal,
            Severity::Quarantined,
            Severity::RecordDropped,
            Severity::Warning,
            Severity::Info,
        ]
        .iter()
        .filter_map(|s| {
            let n = self.count(*s);
            (n > 0).then(|| format!("{n} {s}"))
        })
        .collect();
        if parts.is_empty() {
            "no findings".to_string()
        } else {
            parts.join(", ")
        }
    }
}

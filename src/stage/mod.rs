//! Pipeline stages: one file per stage, each the only place where I/O meets a kernel.
//!
//! [`run`] is the common executor: it hashes the declared inputs and the effective
//! configuration, skips the stage when its manifest says it is up to date, otherwise runs the
//! stage body (which writes its outputs atomically) and writes the manifest last. Exit codes
//! are decided here and turned into a process exit code only in `main`.

pub mod diagnose;
pub mod extract;
pub mod fe;
pub mod ingest;
pub mod lab;
pub mod pair;
pub mod propagate;
pub mod report;
pub mod update;

use crate::io::manifest::{self, Manifest, Prepared, RunInfo, StageSpec};
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Instant;

/// Exit codes shared by all stages.
pub mod exit {
    /// Success; warnings may have been reported.
    pub const OK: i32 = 0;
    /// The stage could not run (bad arguments after parsing, unreadable inputs, I/O failure).
    pub const ERROR: i32 = 1;
    /// Command-line usage error (clap).
    pub const USAGE: i32 = 2;
    /// The stage ran, but some measurements were quarantined (see the stage report).
    pub const QUARANTINED: i32 = 3;
}

/// What a stage body produced.
pub struct StageResult {
    /// Every output file written (hashed into the manifest).
    pub outputs: Vec<PathBuf>,
    pub exit_code: i32,
    pub summary: BTreeMap<String, serde_json::Value>,
}

/// The outcome of running (or skipping) a stage.
pub struct StageOutcome {
    pub manifest: Manifest,
    pub up_to_date: bool,
}

impl StageOutcome {
    pub fn exit_code(&self) -> i32 {
        self.manifest.exit_code
    }
}

/// Run a stage body unless its manifest shows it up to date (or `force`).
pub fn run<F>(spec: StageSpec, force: bool, body: F) -> anyhow::Result<StageOutcome>
where
    F: FnOnce(&Prepared) -> anyhow::Result<StageResult>,
{
    let prep = manifest::prepare(spec)?;
    if !force {
        if let Some(m) = manifest::up_to_date(&prep) {
            return Ok(StageOutcome {
                manifest: m,
                up_to_date: true,
            });
        }
    }
    let started_utc = manifest::now_utc();
    let t0 = Instant::now();
    let result = body(&prep)?;
    let run = RunInfo {
        started_utc,
        wall_seconds: t0.elapsed().as_secs_f64(),
        threads: rayon::current_num_threads(),
    };
    let m = manifest::finish(
        &prep,
        &result.outputs,
        result.exit_code,
        result.summary,
        run,
    )?;
    Ok(StageOutcome {
        manifest: m,
        up_to_date: false,
    })
}

/// A progress bar on stderr when it is a terminal and we are not in CI; hidden otherwise.
pub fn progress_bar(len: u64, what: &str) -> indicatif::ProgressBar {
    use std::io::IsTerminal;
    let visible = std::io::stderr().is_terminal() && std::env::var_os("CI").is_none();
    if !visible {
        return indicatif::ProgressBar::hidden();
    }
    let pb = indicatif::ProgressBar::new(len);
    pb.set_style(
        indicatif::ProgressStyle::with_template("{msg:>12} [{bar:40}] {pos}/{len} {elapsed}")
            .expect("valid template")
            .progress_chars("=> "),
    );
    pb.set_message(what.to_string());
    pb
}

/// Wall time per phase of a stage (an update step, the diagnosis): printed with `--verbose` as each phase ends, and
/// kept in the manifest's summary (`phase_seconds`), never in an output table (outputs stay
/// byte-identical between runs). Where the time goes is an acceptance point of the updating and of the diagnosis.
pub(crate) struct PhaseClock {
    last: std::time::Instant,
    laps: Vec<(&'static str, f64)>,
    verbose: bool,
    what: &'static str,
}

impl PhaseClock {
    pub(crate) fn new(what: &'static str, verbose: bool) -> PhaseClock {
        PhaseClock {
            last: std::time::Instant::now(),
            laps: vec![],
            verbose,
            what,
        }
    }

    /// End the phase `name` now; returns its seconds.
    pub(crate) fn lap(&mut self, name: &'static str) -> f64 {
        let now = std::time::Instant::now();
        let s = now.duration_since(self.last).as_secs_f64();
        self.last = now;
        if self.verbose {
            eprintln!("{}: {name} {s:.1} s", self.what);
        }
        self.laps.push((name, s));
        s
    }

    pub(crate) fn summary(&self) -> serde_json::Value {
        serde_json::Value::Object(
            self.laps
                .iter()
                .map(|(n, s)| (n.to_string(), serde_json::json!(s)))
                .collect(),
        )
    }
}

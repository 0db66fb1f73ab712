//! The `hbmu` command line: argument parsing and dispatch only. Every stage lives in
//! `hbmu::stage`; this is the one place that turns an outcome into a process exit code.

use clap::{Parser, Subcommand};
use hbmu::stage::{self, exit};
use std::path::PathBuf;
use std::process::ExitCode;

/// Hierarchical Bayesian model updating for modal tests of nominally identical parts.
///
/// Each subcommand is one reproducible pipeline stage: it reads declared inputs, writes
/// declared outputs atomically, and records a manifest with the content hashes of both.
/// Re-running a stage whose inputs, configuration and tool version are unchanged does nothing.
///
/// Exit codes: 0 success, 1 error, 2 usage error, 3 success with quarantined measurements.
#[derive(Parser)]
#[command(name = "hbmu", version, about, long_about)]
struct Cli {
    /// Print every finding (not just the summary) and progress details on stderr.
    #[arg(short, long, global = true)]
    verbose: bool,
    /// Worker threads (default: all cores). Outputs are identical whatever the count.
    #[arg(long, global = true)]
    threads: Option<usize>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Read a measurement campaign (sheet, UFF files, balance logs) into campaign.mcap and
    /// Parquet tables (measurements, scan_points, frf, scale_readings, masses), with a report
    /// of every finding. Bad measurements are quarantined; the others go through.
    Ingest {
        /// Campaign directory (campaign.csv, vibrometer/*.uff, scale/*.log).
        campaign: PathBuf,
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
        /// Rerun even when the manifest says the outputs are up to date.
        #[arg(long)]
        force: bool,
        /// Flag a board whose stable balance readings have a std above this many resolution steps.
        #[arg(long, default_value_t = 3.0)]
        mass_max_std_in_d: f64,
    },
    /// Write the JSON schemas of every Parquet table and MCAP channel into a directory
    /// (the repository keeps them under schemas/).
    Schemas {
        /// Output directory (creates tables/ and mcap/ in it).
        #[arg(long)]
        out: PathBuf,
    },
}

fn run(cli: Cli) -> anyhow::Result<i32> {
    if let Some(n) = cli.threads {
        rayon::ThreadPoolBuilder::new()
            .num_threads(n.max(1))
            .build_global()?;
    }
    match cli.command {
        Command::Ingest {
            campaign,
            out,
            force,
            mass_max_std_in_d,
        } => {
            let opts = stage::ingest::IngestOptions {
                campaign,
                out,
                force,
                config: stage::ingest::IngestConfig {
                    mass_max_std_in_d,
                    ..Default::default()
                },
            };
            let outcome = stage::ingest::run(&opts, cli.verbose)?;
            if outcome.up_to_date {
                eprintln!(
                    "ingest: up to date ({}), nothing to do",
                    opts.out.join(stage::ingest::MANIFEST).display()
                );
            }
            Ok(outcome.exit_code())
        }
        Command::Schemas { out } => {
            hbmu::schemas::write_all(&out)?;
            eprintln!("schemas written to {}", out.display());
            Ok(exit::OK)
        }
    }
}

fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(c) => c,
        Err(e) => {
            let _ = e.print();
            return ExitCode::from(if e.use_stderr() { exit::USAGE as u8 } else { 0 });
        }
    };
    match run(cli) {
        Ok(code) => ExitCode::from(code as u8),
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(exit::ERROR as u8)
        }
    }
}

//! Stage `ingest`: a measurement campaign directory → `campaign.mcap` + Parquet tables + report.
//!
//! Wires the campaign directory (`io::campaign_dir`) to the pure campaign model and its
//! cross-checks (`campaign`), and those to the writers (`io::ingest_outputs`). One bad
//! measurement never sinks the campaign: it is quarantined (listed in `measurements.parquet`
//! with its reason, no FRF rows) and the run exits with [`exit::QUARANTINED`]. Every finding
//! is in `ingest_report.json` and summarised on stderr.

pub use crate::campaign::{Campaign, IngestConfig, Measurement, Point, Record};
pub use crate::io::campaign_dir::discover_inputs;
pub use crate::io::ingest_outputs::OUTPUTS;

use crate::campaign::read_campaign;
use crate::findings::Severity;
use crate::io::campaign_dir::CampaignDir;
use crate::io::ingest_outputs::{severity_counts, write_outputs};
use crate::io::manifest::StageSpec;
use crate::stage::{exit, StageOutcome, StageResult};
use std::collections::BTreeMap;
use std::path::PathBuf;

pub const MANIFEST: &str = "ingest.manifest.json";
/// Version of the output layout (2: frf.parquet's axis as start + step, not a list per row;
/// 3: the MCAP's spectra as CBOR with float64 byte strings, not JSON text; 4: what each record
/// measured, `measured_as`, in frf.parquet and on `/frf`).
pub const OUTPUT_LAYOUT: u32 = 4;

/// Options of `hbmu ingest`.
#[derive(Debug, Clone)]
pub struct IngestOptions {
    pub campaign: PathBuf,
    pub out: PathBuf,
    pub force: bool,
    pub config: IngestConfig,
}

/// Run the stage: skip when up to date, else read, check and write. Findings go to stderr
/// (summary always; each finding when `verbose`).
pub fn run(opts: &IngestOptions, verbose: bool) -> anyhow::Result<StageOutcome> {
    let inputs = discover_inputs(&opts.campaign)?;
    let spec = StageSpec {
        stage: "ingest".into(),
        inputs,
        input_base: opts.campaign.clone(),
        // The layout of the outputs is part of the configuration: a new layout reruns ingest.
        config: serde_json::json!({"checks": opts.config, "layout": OUTPUT_LAYOUT}),
        seed: None,
        manifest_path: opts.out.join(MANIFEST),
    };
    crate::stage::run(spec, opts.force, |prep| {
        let t0 = std::time::Instant::now();
        let dir = CampaignDir::open(&opts.campaign)?;
        let pb = crate::stage::progress_bar(0, "UFF files");
        let campaign = read_campaign(&dir, &opts.config, &|| pb.inc(1))?;
        pb.finish_and_clear();
        let t_read = t0.elapsed().as_secs_f64();
        let outputs = write_outputs(&campaign, &opts.out, &prep.fingerprint)?;
        if verbose {
            eprintln!(
                "ingest: read and checked in {t_read:.2} s, outputs written in {:.2} s",
                t0.elapsed().as_secs_f64() - t_read
            );
        }
        let n_q = campaign
            .measurements
            .iter()
            .filter(|m| m.quarantine.is_some())
            .count();
        for f in campaign.findings.iter() {
            if verbose || f.severity >= Severity::Quarantined {
                eprintln!("{f}");
            }
        }
        eprintln!(
            "ingest {}: {} measurements, {} quarantined; {} (details in {})",
            campaign.name,
            campaign.measurements.len(),
            n_q,
            campaign.findings.summary(),
            opts.out.join("ingest_report.json").display()
        );
        let mut summary = BTreeMap::new();
        summary.insert("measurements".into(), campaign.measurements.len().into());
        summary.insert("quarantined".into(), n_q.into());
        summary.insert(
            "findings".into(),
            serde_json::to_value(severity_counts(&campaign.findings))?,
        );
        Ok(StageResult {
            outputs,
            exit_code: if n_q > 0 { exit::QUARANTINED } else { exit::OK },
            summary,
        })
    })
}

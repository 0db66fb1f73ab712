//! Stage `lab simulate`: a scenario → a complete campaign directory in the input contract, plus
//! the truth behind it in a separate JSON file (never inside the campaign directory).
//!
//! The kernel ([`crate::lab::simulate`]) returns the campaign's files as bytes; this stage
//! writes each atomically, removes files of an earlier simulation that the new one does not
//! contain, and records the manifest (scenario and board hashes, seed) next to the truth file
//! so that the campaign directory holds nothing but the campaign.

use crate::fem::Board;
use crate::io::manifest::StageSpec;
use crate::lab::{self, Scenario};
use crate::stage::{exit, StageOutcome, StageResult};
use anyhow::{bail, Context};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Options of `hbmu lab simulate`.
#[derive(Debug, Clone)]
pub struct SimulateOptions {
    /// A scenario file, or the name of a built-in scenario (`paper`, `null`, …).
    pub scenario: String,
    pub board: Option<PathBuf>,
    pub out: PathBuf,
    pub truth: PathBuf,
    /// `None`: the scenario's own seed.
    pub seed: Option<u64>,
    pub force: bool,
}

fn load_scenario(s: &str) -> anyhow::Result<(Scenario, String, Vec<PathBuf>)> {
    let p = Path::new(s);
    if p.is_file() {
        let text = std::fs::read_to_string(p).with_context(|| format!("cannot read {s}"))?;
        let sc = Scenario::from_toml_str(&text).with_context(|| s.to_string())?;
        Ok((sc, text, vec![p.to_path_buf()]))
    } else if s.contains('/') || s.ends_with(".toml") {
        bail!("scenario file {s} does not exist");
    } else {
        let sc = lab::builtin_scenario(s)?;
        Ok((sc, format!("builtin:{s}"), vec![]))
    }
}

/// Run the stage.
pub fn run(opts: &SimulateOptions) -> anyhow::Result<StageOutcome> {
    let (scenario, scenario_text, mut inputs) = load_scenario(&opts.scenario)?;
    let board_text = match &opts.board {
        Some(p) => {
            inputs.push(p.clone());
            std::fs::read_to_string(p).with_context(|| format!("cannot read {}", p.display()))?
        }
        None => crate::fem::board::DEFAULT_BOARD_TOML.to_string(),
    };
    let seed = opts.seed.unwrap_or(scenario.seed);
    let truth_dir = opts
        .truth
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from("."));
    if truth_dir.starts_with(&opts.out) {
        bail!(
            "--truth {} lies inside the campaign directory {}: the truth must be kept apart from the campaign",
            opts.truth.display(),
            opts.out.display()
        );
    }
    let spec = StageSpec {
        stage: "lab-simulate".into(),
        inputs,
        // The scenario and board files count by content; the campaign directory by its place
        // relative to the truth file (a different place must rerun), never by absolute path.
        input_base: PathBuf::new(),
        config: serde_json::json!({
            "scenario": scenario_text,
            "board_blake3": blake3::hash(board_text.as_bytes()).to_hex().to_string(),
            "out": crate::io::manifest::rel_path(&opts.out, &truth_dir),
        }),
        seed: Some(seed),
        manifest_path: crate::io::manifest::manifest_path_for(&opts.truth),
    };
    crate::stage::run(spec, opts.force, |_prep| {
        let board = Board::from_toml_str(&board_text)?;
        let solver: Option<std::sync::Arc<dyn lab::solid::Solver>> = match scenario.truth.physics {
            lab::scenario::Physics::Plate => None,
            lab::scenario::Physics::Solid => Some(std::sync::Arc::new(
                crate::io::external::Calculix::locate().map_err(anyhow::Error::msg)?,
            )),
        };
        let sim = lab::simulate_with(&scenario, &board, seed, solver)?;
        std::fs::create_dir_all(&opts.out)
            .with_context(|| format!("cannot create {}", opts.out.display()))?;
        // Files of an earlier simulation that this one does not write would be ingested as
        // part of the new campaign: remove them (only files our simulations write).
        for sub in ["vibrometer", "scale"] {
            let d = opts.out.join(sub);
            if let Ok(rd) = std::fs::read_dir(&d) {
                for e in rd.flatten() {
                    let rel = format!("{sub}/{}", e.file_name().to_string_lossy());
                    if !sim.files.contains_key(&rel) {
                        std::fs::remove_file(e.path())?;
                    }
                }
            }
        }
        let mut outputs = vec![];
        for (rel, bytes) in &sim.files {
            let p = opts.out.join(rel);
            crate::io::atomic::write_bytes(&p, bytes)
                .with_context(|| format!("writing {}", p.display()))?;
            outputs.push(p);
        }
        let mut t = serde_json::to_vec_pretty(&sim.truth)?;
        t.push(b'\n');
        crate::io::atomic::write_bytes(&opts.truth, &t)
            .with_context(|| format!("writing {}", opts.truth.display()))?;
        outputs.push(opts.truth.clone());
        eprintln!(
            "lab simulate {}: {} files in {}, truth in {}",
            scenario.name,
            sim.files.len(),
            opts.out.display(),
            opts.truth.display()
        );
        let mut summary = BTreeMap::new();
        summary.insert("scenario".into(), scenario.name.clone().into());
        summary.insert("files".into(), sim.files.len().into());
        Ok(StageResult {
            outputs,
            exit_code: exit::OK,
            summary,
        })
    })
}

//! Stage `pair`: identified modes (`modes.parquet` of `extract`) ↔ model modes, by MAC and an
//! optimal one-to-one assignment, with labels from the model shapes, missing and swapped
//! modes, and the paper's presence rule made explicit (`presence.parquet`).
//!
//! Where a measurement's points cannot tell the model's modes apart by MAC (fewer than 3, or
//! two model modes near the band alike there, [`pair::model_mac_max`]: a hammer test with one
//! or two accelerometers), its modes are paired on frequency, visibility and order instead
//! ([`pair::pair_modes_by_frequency`], finding `pair.by_frequency`), with the same labels.
//!
//! The model is the full FE model of a board description (default: the compiled-in board) at
//! its nominal parameters, one per setup, evaluated at each measurement's own scan points.

use crate::fem::{self, Board};
use crate::findings::{Findings, Severity};
use crate::io::manifest::StageSpec;
use crate::io::tables::extract::{read_modes_table, ModeRow};
use crate::io::tables::pairs::{write_pairs, write_presence};
use crate::modal::pair::{
    self, MeasurementModes, PairParams, PairRecord, PresenceRecord, ScanPoint, SetupModel,
};
use crate::stage::{exit, StageOutcome, StageResult};
use anyhow::Context;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

pub const MANIFEST: &str = "pair.manifest.json";

/// Options of `hbmu pair`.
#[derive(Debug, Clone)]
pub struct PairOptions {
    pub extract_dir: PathBuf,
    pub board: Option<PathBuf>,
    pub out: PathBuf,
    pub force: bool,
    pub params: PairParams,
    /// Model modes computed per setup (must cover the identification band).
    pub n_model_modes: usize,
    /// Presence rule: fraction of a setup's measurements a mode must be accepted in.
    pub min_fraction: f64,
    pub plots: bool,
}

/// The rows of modes.parquet grouped per measurement (consecutive rows of one measurement),
/// with the band and scan points of its first row.
fn group_modes(rows: Vec<ModeRow>) -> Vec<MeasurementModes> {
    let mut out: Vec<MeasurementModes> = vec![];
    for r in rows {
        if out.last().map(|m| m.measurement_id.as_str()) != Some(r.measurement_id.as_str()) {
            out.push(MeasurementModes {
                points: r
                    .node
                    .iter()
                    .zip(r.x_m.iter().zip(&r.y_m))
                    .map(|(&n, (&x, &y))| ScanPoint {
                        node_id: n,
                        x_m: x,
                        y_m: y,
                        z_m: 0.0,
                    })
                    .collect(),
                measurement_id: r.measurement_id,
                board_id: r.board_id,
                setup: r.setup,
                band: (r.band_lo_hz, r.band_hi_hz),
                modes: vec![],
            });
        }
        out.last_mut()
            .expect("pushed above")
            .modes
            .push((r.mode, r.freq_hz, r.shape));
    }
    out
}

/// Run the stage.
pub fn run(opts: &PairOptions, verbose: bool) -> anyhow::Result<StageOutcome> {
    let modes_path = opts.extract_dir.join("modes.parquet");
    let mut inputs = vec![modes_path.clone()];
    let board_text = match &opts.board {
        Some(p) => {
            inputs.push(p.clone());
            std::fs::read_to_string(p).with_context(|| format!("cannot read {}", p.display()))?
        }
        None => crate::fem::board::DEFAULT_BOARD_TOML.to_string(),
    };
    let spec = StageSpec {
        stage: "pair".into(),
        inputs,
        // modes.parquet by name; the board file by content (its path is the user's business).
        input_base: opts.extract_dir.clone(),
        config: serde_json::json!({
            "params": opts.params,
            "n_model_modes": opts.n_model_modes,
            "min_fraction": opts.min_fraction,
            "plots": opts.plots,
            "board_blake3": blake3::hash(board_text.as_bytes()).to_hex().to_string(),
        }),
        seed: None,
        manifest_path: opts.out.join(MANIFEST),
    };
    crate::stage::run(spec, opts.force, |prep| {
        let board = Board::from_toml_str(&board_text)?;
        let ms = group_modes(read_modes_table(&modes_path)?);
        // One model per setup present.
        let mut models: BTreeMap<String, SetupModel> = BTreeMap::new();
        for (name, setup) in [("free", fem::Setup::Free), ("bolted", fem::Setup::bolted())] {
            if ms.iter().any(|m| m.setup == name) {
                let sm = SetupModel::build(&board, setup, opts.n_model_modes, &opts.params)?;
                models.insert(name.into(), sm);
            }
        }
        let mut findings = Findings::default();
        let mut rows: Vec<(&MeasurementModes, PairRecord)> = vec![];
        let mut presence: Vec<PresenceRecord> = vec![];
        let mut outputs = vec![];
        for m in &ms {
            let Some(sm) = models.get(&m.setup) else {
                continue;
            };
            let Some(mp) = pair::pair_measurement(m, sm, &opts.params, &mut findings)? else {
                continue;
            };
            if opts.plots {
                let (rl, cl) = pair::mac_plot_labels(m, &mp);
                if let Ok(svg) = crate::report::plots::mac_matrix_svg(
                    &mp.pairing.mac,
                    &rl,
                    &cl,
                    &format!("MAC {} ({})", m.measurement_id, m.setup),
                ) {
                    let p = opts.out.join("plots").join(format!(
                        "{}_mac.svg",
                        crate::io::sanitize(&m.measurement_id)
                    ));
                    crate::io::atomic::write_bytes(&p, svg.as_bytes())?;
                    outputs.push(p);
                }
            }
            rows.extend(mp.rows.into_iter().map(|r| (m, r)));
            presence.push(mp.presence);
        }
        let present = pair::modes_present(&presence, opts.min_fraction);
        outputs.extend(write_tables(&opts.out, &prep.fingerprint, &rows, &present)?);
        finish(&ms, &rows, &findings, outputs, verbose)
    })
}

/// pairs.parquet and presence.parquet.
fn write_tables(
    out: &Path,
    fingerprint: &str,
    rows: &[(&MeasurementModes, PairRecord)],
    present: &[pair::LabelPresence],
) -> anyhow::Result<Vec<PathBuf>> {
    let prov = BTreeMap::from([
        ("hbmu.stage".to_string(), "pair".to_string()),
        ("hbmu.fingerprint".to_string(), fingerprint.to_string()),
        (
            "hbmu.version".to_string(),
            crate::io::manifest::TOOL_VERSION.to_string(),
        ),
        ("hbmu.campaign".to_string(), String::new()),
    ]);
    let p = out.join("pairs.parquet");
    write_pairs(&p, &prov, rows)?;
    let q = out.join("presence.parquet");
    write_presence(&q, &prov, present)?;
    Ok(vec![p, q])
}

/// Report the findings and counts; the stage's result.
fn finish(
    ms: &[MeasurementModes],
    rows: &[(&MeasurementModes, PairRecord)],
    findings: &Findings,
    outputs: Vec<PathBuf>,
    verbose: bool,
) -> anyhow::Result<StageResult> {
    for f in findings.iter() {
        if verbose || f.severity >= Severity::Quarantined {
            eprintln!("{f}");
        }
    }
    let n_acc = rows.iter().filter(|r| r.1.accepted).count();
    let n_missing = rows.iter().filter(|r| r.1.missing).count();
    eprintln!(
        "pair: {} measurements, {} pairs accepted, {} model modes missing, {} failed",
        ms.len(),
        n_acc,
        n_missing,
        findings.count(Severity::Quarantined)
    );
    let mut summary = BTreeMap::new();
    summary.insert("accepted".into(), n_acc.into());
    summary.insert("missing".into(), n_missing.into());
    Ok(StageResult {
        outputs,
        exit_code: if findings.count(Severity::Quarantined) > 0 {
            exit::QUARANTINED
        } else {
            exit::OK
        },
        summary,
    })
}

//! Stage `propagate`: Monte Carlo propagation of the updated posterior (see `uq::propagate`).
//!
//! Inputs: one step-1 directory of `update boards` (population, boards, residuals) and
//! optionally one step-2 directory of `update joints` (population with the carried step-1
//! draw, residuals); `pairs.parquet` of `pair` (labels and their model modes; default: `pair`
//! beside the first update directory) and the ROMs of `fe` (`rom_free.npz`, `rom_bolted.npz`;
//! default: `fe` beside it). Output: `predictions.parquet` (one row per draw, scope, board,
//! setup and label), `propagate_report.json` (labels, counts of failed and out-of-box
//! evaluations, findings). Throughput (wall-clock) goes into the manifest only.

use crate::fem::params::names;
use crate::fem::Rom;
use crate::findings::{Finding, Findings, Severity};
use crate::io::manifest::StageSpec;
use crate::io::tables::pairs::{read_pairs, PairRow};
use crate::io::tables::propagate::{
    classify, fixed_eps, read_rom, read_step1, read_step2, update_rom_options, updated_labels,
    write_predictions, Inputs,
};
use crate::io::tables::update::{read_residuals, MANIFEST_BOARDS, MANIFEST_JOINTS};
use crate::stage::{exit, StageOutcome, StageResult};
use crate::uq::inputs;
use crate::uq::propagate::{self as uq, LabelModel, Models, Posterior};
use anyhow::{anyhow, bail, Context};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

pub const MANIFEST: &str = "propagate.manifest.json";

/// Options of `hbmu propagate`.
#[derive(Debug, Clone, serde::Serialize)]
pub struct PropagateOptions {
    #[serde(skip)]
    pub update_dirs: Vec<PathBuf>,
    #[serde(skip)]
    pub pair_dir: Option<PathBuf>,
    #[serde(skip)]
    pub fe_dir: Option<PathBuf>,
    #[serde(skip)]
    pub out: PathBuf,
    #[serde(skip)]
    pub force: bool,
    pub draws: usize,
    pub seed: u64,
    /// Half-width of the ROMs' verified box, relative (the `fe rom` default).
    pub rom_box: f64,
}

/// [`inputs::positions`], the error naming the ROM file.
fn positions(rom: &Rom, params: &[String], path: &Path) -> anyhow::Result<Vec<usize>> {
    inputs::positions(rom, params).map_err(|e| anyhow!("{}: {e}", path.display()))
}

/// The ROM options the update steps recorded: step 1's and step 2's basis caps, step 1's box.
#[derive(Clone, Copy)]
struct RomCaps {
    basis1: Option<usize>,
    box1: Option<f64>,
    basis2: Option<usize>,
}

/// The stage's hashed inputs and configuration.
fn stage_spec(opts: &PropagateOptions, inp: &Inputs) -> anyhow::Result<(StageSpec, RomCaps)> {
    let mut inputs = vec![
        inp.step1.join("population.parquet"),
        inp.step1.join("boards.parquet"),
        inp.step1.join("residuals.parquet"),
        inp.pairs.clone(),
        inp.rom_free.clone(),
    ];
    // Step 1's evidence.json carries its model-error prior (absent from older outputs).
    let evidence1 = inp.step1.join("evidence.json");
    if evidence1.exists() {
        inputs.push(evidence1.clone());
    }
    if let Some(s2) = &inp.step2 {
        inputs.push(s2.join("population.parquet"));
        inputs.push(s2.join("residuals.parquet"));
        inputs.push(inp.rom_bolted.clone());
    }
    let mut config = serde_json::to_value(opts)?;
    config["step2"] = inp.step2.is_some().into();
    let (basis1, box1) = update_rom_options(&inp.step1.join(MANIFEST_BOARDS));
    let (basis2, _) = match &inp.step2 {
        Some(s2) => update_rom_options(&s2.join(MANIFEST_JOINTS)),
        None => (None, None),
    };
    config["rom_basis_step1"] = basis1.into();
    config["rom_basis_step2"] = basis2.into();
    config["rom_box_step1"] = box1.into();
    config["eps_fixed_step1"] = fixed_eps(&inp.step1.join(MANIFEST_BOARDS)).into();
    if let Some(s2) = &inp.step2 {
        config["eps_fixed_step2"] = fixed_eps(&s2.join(MANIFEST_JOINTS)).into();
    }
    let base = inp
        .step1
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_default();
    let spec = StageSpec {
        stage: "propagate".into(),
        inputs,
        input_base: base,
        config,
        seed: Some(opts.seed),
        manifest_path: opts.out.join(MANIFEST),
    };
    let caps = RomCaps {
        basis1,
        box1,
        basis2,
    };
    Ok((spec, caps))
}

/// (setup, label, model mode) of the accepted pairs.
fn label_keys(pairs: &[PairRow]) -> impl Iterator<Item = (&str, &str, i32)> {
    pairs
        .iter()
        .map(|p| (p.setup.as_str(), p.label.as_str(), p.model_mode))
}

/// Step 1's posterior and the free model: the posterior, its particle index, the free label
/// model, the posterior's parameters' positions in its ROM, and the free labels.
#[allow(clippy::type_complexity)]
fn free_side(
    opts: &PropagateOptions,
    inp: &Inputs,
    caps: RomCaps,
    findings: &mut Findings,
) -> anyhow::Result<(
    Posterior,
    BTreeMap<(i32, i32), usize>,
    LabelModel,
    Vec<usize>,
    Vec<String>,
)> {
    let mut rom_free = read_rom(&inp.rom_free)?;
    // A ROM that records the box it was built over is checked against that box; --rom-box is
    // for one that does not.
    if let Some(b) = caps.box1.filter(|_| rom_free.built_box.is_none()) {
        if (b - opts.rom_box).abs() > 1e-12 {
            findings.push(Finding::new(
                Severity::Warning,
                "propagate.rom_box",
                format!("step 1 ran with a ROM box of ±{:.0} %, propagation checks ±{:.0} % (--rom-box)", 100.0 * b, 100.0 * opts.rom_box),
            ));
        }
    }
    // The same reduced model the posterior was computed with: a basis capped in the
    // update (`--rom-basis`) is the prefix of the fe stage's basis.
    if let Some(r) = caps.basis1 {
        rom_free = inputs::as_updated(rom_free, r);
    }
    let pairs = read_pairs(&inp.pairs)?;
    let (free_labels, free_modes) =
        inputs::labels_of(label_keys(&pairs), "free", rom_free.n_modes, findings);
    if free_labels.is_empty() {
        bail!(
            "{}: no accepted free-free pair: nothing to predict",
            inp.pairs.display()
        );
    }
    let (mut post, index) = read_step1(&inp.step1, &free_labels, findings)?;
    let res_path = inp.step1.join("residuals.parquet");
    let read_res =
        || read_residuals(&res_path).with_context(|| format!("reading {}", res_path.display()));
    // With a per-unit discrepancy, each measured board's own offset per updated label.
    let mut residuals = None;
    if post
        .step1
        .iter()
        .any(|p| p.discrepancy.unit_scale.is_some())
    {
        let rows = read_res()?;
        let updated = updated_labels(&res_path)?;
        post.board_offsets = inputs::board_offsets(&rows, &post.board_ids, &free_labels, &updated);
        residuals = Some(rows);
    }
    let free_idx = positions(&rom_free, &post.params, &inp.rom_free)?;
    let rows = match residuals {
        Some(r) => r,
        None => read_res()?,
    };
    let repeat = inputs::repeatability(&rows, &free_labels, findings);
    let evidence1 = inp.step1.join("evidence.json");
    let ev = evidence1
        .exists()
        .then(|| crate::io::read_json(&evidence1))
        .transpose()?;
    let model_error = inputs::model_error_sd(
        ev.as_ref(),
        &evidence1.display().to_string(),
        &free_labels,
        findings,
    )
    .map_err(anyhow::Error::msg)?;
    let free = LabelModel::new(rom_free, free_labels.clone(), &free_modes, opts.rom_box)?
        .with_repeatability(repeat)?
        .with_model_error(model_error)?;
    Ok((post, index, free, free_idx, free_labels))
}

/// Step 2's particles into `post` and the bolted model with the posterior's parameters' and
/// k_con's positions in its ROM; none without a step 2 (an info finding).
#[allow(clippy::type_complexity)]
fn bolted_side(
    opts: &PropagateOptions,
    inp: &Inputs,
    caps: RomCaps,
    post: &mut Posterior,
    index: &BTreeMap<(i32, i32), usize>,
    findings: &mut Findings,
) -> anyhow::Result<Option<((LabelModel, Vec<usize>, usize), Vec<String>)>> {
    let Some(s2) = &inp.step2 else {
        findings.push(Finding::new(
            Severity::Info,
            "propagate.no_step2",
            "no step-2 (update joints) posterior among the inputs: no bolted predictions",
        ));
        return Ok(None);
    };
    let mut rom_b = read_rom(&inp.rom_bolted)?;
    if let Some(r) = caps.basis2 {
        rom_b = inputs::as_updated(rom_b, r);
    }
    let pairs = read_pairs(&inp.pairs)?;
    let (bl, bm) = inputs::labels_of(label_keys(&pairs), "bolted", rom_b.n_modes, findings);
    if bl.is_empty() {
        bail!(
            "{}: no accepted bolted pair, but a step-2 posterior was given",
            inp.pairs.display()
        );
    }
    post.step2 = Some(read_step2(s2, &bl, index, findings)?);
    let bidx = positions(&rom_b, &post.params, &inp.rom_bolted)?;
    let kidx = rom_b
        .map
        .names
        .iter()
        .position(|n| n == names::K_CON)
        .ok_or_else(|| {
            anyhow!(
                "{}: the bolted ROM has no {} parameter",
                inp.rom_bolted.display(),
                names::K_CON
            )
        })?;
    let model = LabelModel::new(rom_b, bl.clone(), &bm, opts.rom_box)?;
    Ok(Some(((model, bidx, kidx), bl)))
}

/// Run `hbmu propagate`.
pub fn run(opts: &PropagateOptions, verbose: bool) -> anyhow::Result<StageOutcome> {
    if opts.draws == 0 {
        bail!("--draws: expected at least 1");
    }
    let inp = classify(
        &opts.update_dirs,
        opts.pair_dir.as_ref(),
        opts.fe_dir.as_ref(),
    )?;
    let (spec, caps) = stage_spec(opts, &inp)?;
    crate::stage::run(spec, opts.force, |prep| {
        let mut findings = Findings::default();
        let (mut post, index, free, free_idx, free_labels) =
            free_side(opts, &inp, caps, &mut findings)?;
        let (bolted_model, bolted_labels) =
            match bolted_side(opts, &inp, caps, &mut post, &index, &mut findings)? {
                Some((m, labels)) => (Some(m), labels),
                None => (None, vec![]),
            };
        let models = Models {
            free: &free,
            free_idx,
            bolted: bolted_model.as_ref().map(|(m, b, k)| (m, b.clone(), *k)),
        };
        let t0 = std::time::Instant::now();
        let (preds, counts) = uq::propagate(&post, &models, opts.draws, opts.seed)?;
        let seconds = t0.elapsed().as_secs_f64();
        if counts.inadmissible_or_untracked > 0 {
            findings.push(Finding::new(
                Severity::Warning,
                "propagate.no_prediction",
                format!("{} of {} evaluations gave no prediction (inadmissible parameters or a mode that could not be tracked); they have no rows", counts.inadmissible_or_untracked, counts.evaluations),
            ));
        }
        if counts.outside_rom_box > 0 {
            findings.push(Finding::new(
                Severity::Warning,
                "propagate.outside_rom_box",
                format!(
                    "{} of {} evaluations ({} of {} new free-free boards) lie outside the box their ROM was built over (free-free {}{}), where it is not verified",
                    counts.outside_rom_box,
                    counts.evaluations,
                    counts.new_board_outside_box,
                    opts.draws,
                    free.box_description(),
                    bolted_model
                        .as_ref()
                        .map(|(m, _, _)| format!(", bolted {}", m.box_description()))
                        .unwrap_or_default()
                ),
            ));
        }
        let prov = BTreeMap::from([
            ("hbmu.stage".to_string(), "propagate".to_string()),
            ("hbmu.fingerprint".to_string(), prep.fingerprint.clone()),
            (
                "hbmu.version".to_string(),
                crate::io::manifest::TOOL_VERSION.to_string(),
            ),
            ("hbmu.campaign".to_string(), String::new()),
        ]);
        let mut outputs = vec![];
        let path = opts.out.join("predictions.parquet");
        let labels = (free_labels.as_slice(), bolted_labels.as_slice());
        write_predictions(&path, &prov, &preds, labels, &post.board_ids)?;
        outputs.push(path);
        let updated1 = updated_labels(&inp.step1.join("residuals.parquet"))?;
        let report = serde_json::json!({
            "draws": opts.draws,
            "seed": opts.seed,
            "step2": inp.step2.is_some(),
            "parameters": post.params,
            "boards": post.board_ids,
            "labels": {
                "free": free_labels.iter().map(|l| serde_json::json!({"label": l, "used_for_updating": updated1.contains(l)})).collect::<Vec<_>>(),
                "bolted": bolted_labels,
            },
            "counts": counts,
            "findings": findings.0,
        });
        let path = opts.out.join("propagate_report.json");
        crate::io::atomic::write_bytes(&path, serde_json::to_string_pretty(&report)?.as_bytes())?;
        outputs.push(path);
        // One board-frequency vector = one evaluation (all labels of one board and setup).
        let per_s = counts.evaluations as f64 / seconds.max(1e-9);
        eprintln!(
            "propagate: {} draws, {} evaluations ({} rows) in {:.2} s: {:.0} board-frequency vectors per second on {} threads; {}",
            opts.draws,
            counts.evaluations,
            preds.len(),
            seconds,
            per_s,
            rayon::current_num_threads(),
            findings.summary()
        );
        for f in findings.iter() {
            if verbose || f.severity >= Severity::Warning {
                eprintln!("{f}");
            }
        }
        let mut s = BTreeMap::new();
        s.insert("evaluations".into(), serde_json::json!(counts.evaluations));
        s.insert("propagation_seconds".into(), serde_json::json!(seconds));
        s.insert(
            "board_frequency_vectors_per_second".into(),
            serde_json::json!(per_s),
        );
        Ok(StageResult {
            outputs,
            exit_code: exit::OK,
            summary: s,
        })
    })
}

//! `hbmu diagnose WORK_DIR --out DIR`: reads a work directory's posterior tables, locates
//! the misfit ([`crate::diagnose::locate`]), screens the mechanism library against the
//! located signature ([`crate::diagnose::screen`]), refits the screened joint mechanisms with
//! `update joints --enrich` (each refit its own hashed stage under `DIR/refits/<id>`, so a
//! cluster can run them side by side: `--only <id>` runs one and stops), compares them with
//! the work directory's step 2 by log evidence and held-out error
//! ([`crate::diagnose::select`]), and writes `diagnosis.json`, `diagnosis.parquet` and
//! `diagnosis_modes.parquet` (each mode's misfit before and after every refit).
//!
//! The refits run with exactly the options the work directory's step 2 ran with (read from
//! its manifest), so the Bayes factors compare like with like.

mod refit;

pub use crate::diagnose::doc::{
    CandidateDoc, DiagnoseOptions, DiagnosisDoc, FindingDoc, HeldOut, LocatedSummary, Location,
};
use crate::diagnose::library::is_board_mechanism;
use crate::diagnose::locate::{self, LocateOptions, Located};
use crate::diagnose::misfit::{MisfitParts, RefitBudget, RefitShares};
use crate::diagnose::regions::{self, demote_weaker_regions, BoardRegion};
use crate::diagnose::screen::{self, Candidate};
use crate::diagnose::select::{self, Compared, Refit, Verdict};
use crate::diagnose::verdict::{
    self, above_practical_threshold, model_form_pattern, whole_board_outliers, STOP_REMAINING_SHARE,
};
use crate::findings::{Findings, Severity};
use crate::io::diagnose_inputs::{read_inputs, refit_residuals, WorkDirRegions};
use crate::io::manifest::StageSpec;
use crate::io::tables::diagnose::{self as diagnose_tables, DiagnosisRow};
use crate::io::work_dir::WorkDir;
use crate::stage::{exit, PhaseClock, StageOutcome, StageResult};
use anyhow::anyhow;
use anyhow::Context as _;
use refit::{
    baselines, cannot_be_favoured, centre_gate, load_board, refine_point, run_refit, step1_options,
    step2_options, Against,
};
use std::collections::BTreeMap;
use std::path::Path;

pub const MANIFEST: &str = "diagnose.manifest.json";
pub const JSON: &str = "diagnosis.json";

/// The diagnosis stage. None: `--only` named a candidate that its screen says not to refit
/// (the reason is printed; the gathering run records it).
pub fn run(opts: &DiagnoseOptions, verbose: bool) -> anyhow::Result<Option<StageOutcome>> {
    let w = &opts.work_dir;
    let wd = WorkDir::new(w);
    let mut inputs = vec![wd.measurements(), wd.modes(), wd.pairs()];
    for f in ["residuals.parquet", "population.parquet", "boards.parquet"] {
        inputs.push(wd.update_boards().join(f));
    }
    let step2 = wd.update_joints().join("evidence.json").is_file();
    if step2 {
        for f in [
            "residuals.parquet",
            "population.parquet",
            "evidence.json",
            "joints.parquet",
        ] {
            inputs.push(wd.update_joints().join(f));
        }
    }
    if let Some(b) = &opts.board {
        inputs.push(b.clone());
    }
    let mut base = if step2 { Some(step2_options(w)?) } else { None };
    let mut config = serde_json::to_value(opts)?;
    config["step2_options"] = serde_json::to_value(&base)?;
    let mut base1 = step1_options(w)?;
    config["step1_options"] = serde_json::to_value(&base1)?;
    let (cache, _private_cache) = refit_cache()?;
    base1.cache = Some(cache.clone());
    if let Some(b) = base.as_mut() {
        b.cache = Some(cache);
    }
    let spec = StageSpec {
        stage: "diagnose".into(),
        inputs,
        input_base: w.clone(),
        config,
        seed: base.as_ref().map(|b| b.sampler.seed),
        manifest_path: opts.out.join(MANIFEST),
    };
    // The cluster fan-out: one refit, no diagnosis.
    if let Some(only) = &opts.only {
        let (input, _) = read_inputs(w)?;
        let located = locate::locate(&input, &opts.locate);
        let (board, _) = load_board(opts.board.as_deref())?;
        let (_, cands) = screen_candidates(
            w,
            &board,
            &base1.model.params,
            &input,
            &located,
            (&opts.locate, verbose),
        );
        let cand = cands.iter().find(|c| c.id() == *only).ok_or_else(|| {
            anyhow!(
                "--only {only}: not a screened candidate of this work directory (screened: {})",
                cands.iter().map(|c| c.id()).collect::<Vec<_>>().join(", ")
            )
        })?;
        let (cand, _, _) = refine_point(opts, &board, &base1, cand, verbose);
        let (baseline1, baseline) = baselines(w, step2)?;
        let against = Against {
            located: &located,
            input: &input,
            baseline: baseline.as_ref().unwrap_or(&baseline1),
            z1: &baseline1.log_evidence_runs,
        };
        let screened = refit::screen_first(opts, base.as_ref(), &cand, verbose);
        if let Some(why) = screened.skip {
            eprintln!("diagnose --only {only}: {why}");
            return Ok(None);
        }
        if screened
            .screen
            .is_some_and(|s| s.log_bayes_factor.is_some())
        {
            eprintln!("diagnose --only {only}: judged on its per-assembly screen, no sampler's refit: the diagnosis screens it again and records it");
            return Ok(None);
        }
        let decided = || cannot_be_favoured(opts, &cand, &against);
        let gate = centre_gate(opts, base.as_ref(), &cand, &located);
        return run_refit(
            opts,
            (&base1, base.as_ref()),
            &cand,
            (&decided, gate.as_deref()),
            &Default::default(),
            verbose,
        )
        .map(Some);
    }
    crate::stage::run(spec, opts.force, |_prep| {
        let mut clock = PhaseClock::new("diagnose", verbose);
        let mut findings = Findings::default();
        let (input, in_findings) = read_inputs(w)?;
        findings.0.extend(in_findings.0);
        clock.lap("inputs");
        let located = locate::locate(&input, &opts.locate);
        clock.lap("locate");
        let (board, _) = load_board(opts.board.as_deref())?;
        let (regions, candidates) = screen_candidates(
            w,
            &board,
            &base1.model.params,
            &input,
            &located,
            (&opts.locate, verbose),
        );
        clock.lap("regions_and_screen");
        let mut refits: Vec<Refit> = vec![];
        let (baseline1, baseline) = baselines(w, step2)?;
        let mut parts = MisfitParts::new(&located);
        let above = above_practical_threshold(&located, opts.select.practical_threshold_rel);
        // Below the practical threshold nothing is refitted: no finding could be claimed.
        if above {
            // Joint mechanisms need step 2; board mechanisms only step 1. The refits stop
            // once every part of the located misfit (the mean shifts, each covariate trend)
            // has a favoured refit that leaves at most STOP_REMAINING_SHARE of it: the rest
            // of the candidates were screened for a misfit that is then explained, and each
            // would cost a sampler's run (the per-joint refits of a campaign whose joints
            // fit are the slowest); they are reported as not refitted.
            let base_ref = baseline.as_ref().unwrap_or(&baseline1);
            let against = Against {
                located: &located,
                input: &input,
                baseline: base_ref,
                z1: &baseline1.log_evidence_runs,
            };
            // The budget is per part of the misfit (`misfit::Part`): a part a favoured refit
            // has explained takes no more, the others keep theirs.
            let mut budget = RefitBudget::new(opts.max_refits);
            for cand in candidates
                .iter()
                .filter(|c| c.refittable() && (step2 || is_board_mechanism(c.mechanism)))
            {
                if !budget.admit(cand, &parts, STOP_REMAINING_SHARE) {
                    continue;
                }
                let t0 = std::time::Instant::now();
                let mut r = refit::refit(
                    opts,
                    &board,
                    (&base1, base.as_ref()),
                    cand,
                    &against,
                    verbose,
                );
                let shares = if r.failed.is_none() {
                    let after = refit_residuals(&opts.out.join(&r.dir))?;
                    let shares = RefitShares::new(
                        &located,
                        &input,
                        &after,
                        &opts.locate,
                        &cand.measurements,
                    );
                    r.remaining_share = shares.own(cand);
                    r.explained_rel = shares.explained(cand);
                    Some(shares)
                } else {
                    None
                };
                eprintln!(
                    "diagnose: refit {} in {:.1} s{}",
                    cand.id(),
                    t0.elapsed().as_secs_f64(),
                    r.failed
                        .as_ref()
                        .map(|e| format!(": failed: {e}"))
                        .unwrap_or_default()
                );
                if let Some(shares) = shares.filter(|_| {
                    select::compare(base_ref, std::slice::from_ref(&r), &opts.select)
                        .first()
                        .is_some_and(|c| c.favoured)
                }) {
                    parts.record_favoured(&shares);
                }
                refits.push(r);
                if parts.all_explained(STOP_REMAINING_SHARE) {
                    break;
                }
            }
        }
        clock.lap("refits");
        // Against the baseline over the same data: both steps where the campaign has a
        // step 2 (summarize_refit), else step 1 (only board mechanisms are refitted then).
        let compared = select::compare(
            baseline.as_ref().unwrap_or(&baseline1),
            &refits,
            &opts.select,
        );
        let mut verdict = select::verdict(above, &compared);
        let region_limit_m = board.length_x_m.min(board.width_y_m) / 4.0;
        let screens: Vec<_> = refits
            .iter()
            .filter_map(|r| r.joint_screen.as_ref())
            .collect();
        let joint_form = verdict::joint_form_outliers(&located, &screens);
        let mut others = located.clone();
        others.measurements.retain(|m| !joint_form.contains(m));
        let boards_off = whole_board_outliers(&others, &input.measurements);
        if verdict == Verdict::UnexplainedMisfit
            && model_form_pattern(
                &located,
                &regions.0,
                region_limit_m,
                boards_off.is_some(),
                &joint_form,
            )
        {
            verdict = Verdict::ModelForm;
        }
        let joint_form = if verdict == Verdict::ModelForm {
            joint_form
        } else {
            vec![]
        };
        let mut result = write_outputs(
            opts,
            (
                &located,
                above,
                &boards_off.unwrap_or_default(),
                &joint_form,
            ),
            regions,
            &candidates,
            &compared,
            (verdict, board.model_form()),
            parts.unexplained(STOP_REMAINING_SHARE),
            findings,
            verbose,
        )?;
        clock.lap("outputs");
        result
            .summary
            .insert("phase_seconds".into(), clock.summary());
        Ok(result)
    })
    .map(Some)
}

/// The board regions and the screened candidates, a located point mass attached (the same
/// for the diagnosis and for one candidate's refit, `--only`).
fn screen_candidates(
    work: &Path,
    board: &crate::fem::Board,
    params: &[String],
    input: &locate::LocateInput,
    located: &Located,
    (lopts, verbose): (&LocateOptions, bool),
) -> ((Vec<BoardRegion>, String), Vec<Candidate>) {
    let regions = board_regions(work, board, (params, input, located), lopts, verbose);
    let mut candidates = screen::screen(located, board);
    screen::attach_regions(&mut candidates, &regions.0);
    (regions, candidates)
}

/// The board regions of the located free-free misfit and the note on what was (not) done.
fn board_regions(
    work: &Path,
    board: &crate::fem::Board,
    (params, input, located): (&[String], &locate::LocateInput, &Located),
    lopts: &LocateOptions,
    verbose: bool,
) -> (Vec<BoardRegion>, String) {
    if !located.setups.iter().any(|s| s == "free") {
        return (
            vec![],
            "not run: no free-free misfit located (the point-mass and stiffness localisations use the free-free modes)".to_string(),
        );
    }
    let model_freq = regions::free_model_freq(&input.residuals);
    let files = WorkDirRegions { work };
    let inp = regions::RegionInput {
        files: &files,
        board,
        params,
        checks: &located.mode_checks,
        residual_model_freq: &model_freq,
        locate: lopts,
        pairs: &input.pairs,
    };
    let mut clock = PhaseClock::new("diagnose", verbose);
    let fb = match regions::FreeBasis::new(&inp) {
        Ok(fb) => fb,
        Err(e) => return (vec![], format!("localisation failed: {e:#}")),
    };
    clock.lap("free_basis");
    let mut note = vec![];
    if !fb.left_out.is_empty() {
        note.push(format!(
            "free-free modes left out of the localisations (no standard error, as a mode seen in one measurement): {}",
            fb.left_out.join(", ")
        ));
    }
    let mut out = vec![];
    match regions::point_mass_region(&inp, &fb) {
        Ok(r) => {
            note.push("point-mass localisation of the free-free misfit (exact frequency shifts in a modal basis, the stiffness parameters projected off, the measured shapes choosing over the points the frequencies leave open)".to_string());
            out.push(r);
        }
        Err(e) => note.push(format!("point-mass localisation failed: {e:#}")),
    }
    clock.lap("point_mass_region");
    match regions::stiffness_region(&inp, &fb) {
        Ok(r) => {
            note.push(format!("stiffness localisation (first-order signature of a change of the core's bending stiffness over a {:.0} mm disc, either sign, the board parameters projected off, the measured shapes choosing as for the point mass)", 2e3 * regions::STIFFNESS_RADIUS_M));
            out.push(r);
        }
        Err(e) => note.push(format!("stiffness localisation failed: {e:#}")),
    }
    clock.lap("stiffness_region");
    demote_weaker_regions(&mut out);
    (out, note.join("; "))
}

/// Write `diagnosis.json`, `diagnosis.parquet` and `diagnosis_modes.parquet`, and say the
/// verdict.
#[allow(clippy::too_many_arguments)]
fn write_outputs(
    opts: &DiagnoseOptions,
    (located, above, boards_off, joint_form): (&Located, bool, &[(String, String)], &[String]),
    regions: (Vec<BoardRegion>, String),
    candidates: &[Candidate],
    compared: &[Compared],
    (verdict, model_form): (Verdict, &str),
    unexplained: Option<String>,
    mut findings: Findings,
    verbose: bool,
) -> anyhow::Result<StageResult> {
    let rows = verdict::rows(candidates, compared);
    let doc = verdict::document(
        opts,
        (located, above, boards_off, joint_form),
        regions,
        &rows,
        compared,
        (verdict, model_form),
        unexplained,
        &mut findings,
    );
    std::fs::create_dir_all(&opts.out)?;
    let mut outputs = vec![];
    let p = opts.out.join(JSON);
    crate::io::atomic::write_bytes(&p, serde_json::to_string_pretty(&doc)?.as_bytes())?;
    outputs.push(p);
    let table: Vec<DiagnosisRow> = rows.iter().map(DiagnosisRow::of).collect();
    let p = opts.out.join("diagnosis.parquet");
    diagnose_tables::write_diagnosis(&p, &table, &verdict)?;
    outputs.push(p);
    // diagnosis_modes.parquet: each mode's misfit, baseline and every refit that gave one.
    let mut refits = vec![];
    for r in &rows {
        let Some(c) = r.cmp.as_ref().filter(|c| c.refit.failed.is_none()) else {
            continue;
        };
        let after = refit_residuals(&opts.out.join(&c.refit.dir))?;
        refits.push((r.cand.id(), locate::mode_means(&after, &opts.locate)));
    }
    let p = opts.out.join("diagnosis_modes.parquet");
    diagnose_tables::write_modes(&p, &verdict::mode_rows(located, refits))?;
    outputs.push(p);
    for fd in findings.iter() {
        if verbose || fd.severity >= Severity::Warning {
            eprintln!("{fd}");
        }
    }
    eprintln!(
        "diagnose: verdict {}; {} candidates screened, {} refitted; {}",
        serde_json::to_string(&verdict)?.trim_matches('"'),
        candidates.len(),
        compared.len(),
        findings.summary()
    );
    let mut s = BTreeMap::new();
    s.insert("verdict".into(), serde_json::to_value(verdict)?);
    Ok(StageResult {
        outputs,
        exit_code: exit::OK,
        summary: s,
    })
}

/// The cache of model artifacts the refits use: `HBMU_CACHE`'s, or without one a private
/// cache removed with the returned directory. Refits build some artifacts more than once
/// (every step-1 refit the model-error term's mesh study, 19 s on the default board; a
/// located mass's probe and its refit the same ROM, 15 s), and a hit is the build bit for
/// bit, so the diagnosis is the same either way.
fn refit_cache() -> anyhow::Result<(crate::io::cache::Cache, Option<tempfile::TempDir>)> {
    use crate::io::cache::Cache;
    Ok(match Cache::from_env() {
        Some(c) => (c, None),
        None => {
            let dir = tempfile::Builder::new()
                .prefix("hbmu-diagnose-cache-")
                .tempdir()
                .context(
                    "creating the diagnosis's private cache of model artifacts (no HBMU_CACHE)",
                )?;
            (Cache::new(dir.path()), Some(dir))
        }
    })
}

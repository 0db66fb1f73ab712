//! `update boards` (step 1): free-free modes and balance masses of every board; read →
//! [`crate::update::boards`] → write.

use super::*;

/// Step 1: boards, free-free.
pub fn run_boards(opts: &UpdateOptions, verbose: bool) -> anyhow::Result<StageOutcome> {
    let extract_dir = opts.extract_dir();
    let pairs_path = opts.pair_dir.join("pairs.parquet");
    let presence_path = opts.pair_dir.join("presence.parquet");
    let modes_path = extract_dir.join("modes.parquet");
    let masses_path = opts.ingest_dir.join("masses.parquet");
    let measurements_path = opts.ingest_dir.join("measurements.parquet");
    let specimens_path = opts.ingest_dir.join("specimens.parquet");
    if let Some(m) = opts.model.enrich.filter(|m| !is_board_mechanism(*m)) {
        bail!(
            "--enrich {}: not a board mechanism (update boards refits temperature_stiffness, added_mass)",
            m.id()
        );
    }
    if !(opts.model.balance_bias_rel.is_finite() && opts.model.balance_bias_rel >= 0.0) {
        bail!(
            "--balance-bias: expected a finite relative value >= 0, found {}",
            opts.model.balance_bias_rel
        );
    }
    let with_defaults;
    let opts = if opts.model.params.is_empty() {
        let (board, _) = load_board(opts.board.as_deref())?;
        let mut o = opts.clone();
        o.model.params = crate::update::boards::default_params(&board);
        with_defaults = o;
        &with_defaults
    } else {
        opts
    };
    let mut inputs = vec![
        pairs_path.clone(),
        presence_path.clone(),
        modes_path.clone(),
        masses_path.clone(),
    ];
    if opts.model.enrich_covariate.is_some() {
        inputs.push(measurements_path.clone());
    }
    // Older ingest outputs have no specimens table: every board at the board file's thickness.
    if specimens_path.is_file() {
        inputs.push(specimens_path.clone());
    }
    let (board, spec) = step_spec(
        opts,
        "update_boards",
        inputs,
        &[("step", "boards")],
        MANIFEST_BOARDS,
    )?;
    let paths = BoardPaths {
        pairs: pairs_path,
        presence: presence_path,
        modes: modes_path,
        masses: masses_path,
        measurements: measurements_path,
        specimens: specimens_path,
    };
    crate::stage::run(spec, opts.force, |prep| {
        // One attempt at the ROM box `opts.model.rom_box`; `carried` are findings of an
        // earlier one.
        widen_rom_box(opts, |o, carried| {
            boards_attempt(o, carried, &board, &paths, prep, verbose)
        })
    })
}

pub(crate) struct BoardPaths {
    pub(crate) pairs: PathBuf,
    pub(crate) presence: PathBuf,
    pub(crate) modes: PathBuf,
    pub(crate) masses: PathBuf,
    pub(crate) measurements: PathBuf,
    pub(crate) specimens: PathBuf,
}

pub(crate) fn boards_attempt(
    opts: &UpdateOptions,
    carried: &[Finding],
    board: &Board,
    paths: &BoardPaths,
    prep: &crate::io::manifest::Prepared,
    verbose: bool,
) -> anyhow::Result<StageResult> {
    use crate::update::boards;
    let mut clock = PhaseClock::new("update boards", verbose);
    let mut findings = Findings::default();
    findings.0.extend(carried.iter().cloned());
    let pairs = read_pairs(&paths.pairs)?;
    let presence = read_presence(&paths.presence, "free")?;
    let labels = select_labels(&pairs, "free", &opts.model.modes, &presence, &mut findings)?;
    // Boards measured in thickness: the core thickness is a board parameter (exact in the
    // model), each board's reading an observation of it. The sheet gives the overall thickness
    // a micrometer reads over the copper (a finished board's, as a fabrication drawing gives
    // it): the board file's copper layers are taken off.
    let copper_m = board.copper_thickness_m();
    let thickness_m: BTreeMap<String, f64> = read_specimen_thickness(&paths.specimens)?
        .into_iter()
        .map(|(b, h)| (b, h - copper_m))
        .collect();
    let with_thickness;
    let opts =
        if thickness_m.is_empty() || opts.model.params.iter().any(|p| p == names::CORE_THICKNESS) {
            opts
        } else {
            let mut o = opts.clone();
            o.model.params.push(names::CORE_THICKNESS.into());
            with_thickness = o;
            &with_thickness
        };
    let bm = boards::board_model(
        board,
        &opts.model,
        &labels,
        &pairs,
        !thickness_m.is_empty(),
        &mut findings,
    )?;
    let need = bm.need;
    clock.lap("models");
    let cache = opts.cache.as_ref();
    let rom = model_cache::rom(
        cache,
        &bm.model,
        &rom_options_for(&bm.model, need, &bm.log_axes, &opts.model),
    )?;
    rom_centre_check(&bm.model, &rom, need, &mut findings)?;
    clock.lap("rom_build");
    // A widened box (step 1's retries, `widen_rom_box`) is checked against the full model:
    // the build's accuracy tests hold for the default box only.
    if opts.model.rom_box > ModelSpec::DEFAULT_ROM_BOX || opts.model.g_z_log_box.is_some() {
        let worst = rom_box_check(&bm.model, &rom, opts.model.rom_box, need)?;
        findings.push(Finding::new(
            if worst > 1e-4 { Severity::Warning } else { Severity::Info },
            "update.rom_box_check",
            format!(
                "the ROM over ±{:.0} %{}: worst relative frequency error {worst:.1e} against the full model over its first {need} modes at 8 Latin-hypercube points{}",
                100.0 * opts.model.rom_box,
                match opts.model.g_z_log_box {
                    Some(w) => format!(", the transverse shear modulus over × or ÷ {:.2}", w.exp()),
                    None => String::new(),
                },
                if worst > 1e-4 { " (above 1e-4, the accuracy the default box's ROM is held to: raise --rom-basis)" } else { "" }
            ),
        ));
    }
    let masses = read_masses(&paths.masses)?;
    let covariate = match (&opts.model.enrich, &opts.model.enrich_covariate) {
        (Some(Mechanism::TemperatureStiffness), Some(column)) => {
            Some(read_covariate(&paths.measurements, column)?)
        }
        _ => None,
    };
    let mode_rows = read_modes_table(&paths.modes)?;
    let measurements_source = paths.measurements.display().to_string();
    let model_error = if opts.model.model_error {
        let (p, n) = model_error_study(&bm.board_nominal, &labels, &bm.all);
        let spread = model_cache::mesh_study(cache, board, &Setup::Free, &board.mesh, &p, n)
            .context("the model-error term's mesh study")?;
        Some(model_error_from(spread, &labels, &bm.all))
    } else {
        None
    };
    let mut bt = boards::board_target(
        board,
        &bm,
        model_error,
        &rom,
        &opts.model,
        (&labels, &pairs, &mode_rows),
        &masses,
        covariate
            .as_deref()
            .map(|v| (v, measurements_source.as_str())),
        &thickness_m,
        &mut findings,
    )?;
    clock.lap("unit_data");
    let shape_weights = weigh_shapes(
        &mut bt.step.target,
        &opts.model.shape_weights,
        (&[], None),
        &labels.labels,
        opts.sampler.seed,
        "boards",
    )?;
    report_shape_weights(&shape_weights, "boards", verbose, &mut findings);
    clock.lap("shape_weights");
    // The ROM-box rule on the reference first, in the first attempt only: a reference that
    // already leaves the box widens it before any tempering is spent on this ROM. A later
    // attempt samples on its widened ROM, and the posterior decides.
    let first_attempt = carried.is_empty();
    let (results, acceleration) = sample(
        &bt.step.target,
        &opts.sampler,
        "boards",
        &[],
        None,
        &|q, inflation| match first_attempt {
            true => boards::check_board_reference_box(&bm, &bt, q, inflation, &opts.model),
            false => Ok(()),
        },
        verbose,
    )?;
    let sampler_seconds = clock.lap("sampler");
    acceleration_findings(&acceleration, &mut findings);
    boards::check_board_box(&bm, &bt, &results, &opts.model)?;
    let prov = provenance("update_boards", &prep.fingerprint);
    let mut outputs = vec![];
    let boards::BoardTables {
        population: pop,
        boards: boards_t,
        summary,
        physical,
    } = boards::board_tables(
        &bm,
        &bt,
        &results,
        &labels,
        (
            opts.sampler.runs,
            opts.sampler.seed,
            opts.model.balance_bias_rel,
        ),
    );
    let p = opts.out.join("population.parquet");
    write_draws(&p, &POPULATION, &pop, false, &prov)?;
    outputs.push(p);
    let p = opts.out.join("boards.parquet");
    write_draws(&p, &BOARDS, &boards_t, true, &prov)?;
    outputs.push(p);
    let p = opts.out.join("boards_physical.parquet");
    match &physical {
        Some(t) => {
            write_draws(&p, &BOARDS_PHYSICAL, t, true, &prov)?;
            outputs.push(p);
        }
        // Not one of an earlier run's left beside this run's draws.
        None => match std::fs::remove_file(&p) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                return Err(anyhow::Error::from(e).context(format!("removing {}", p.display())))
            }
            _ => {}
        },
    }
    let p = opts.out.join("summary.parquet");
    write_summary(&p, &summary, &prov)?;
    outputs.push(p);
    let stages: Vec<StageInfo> = results.iter().flat_map(|r| r.stages.clone()).collect();
    let p = opts.out.join("stages.parquet");
    write_stages(&p, &stages, &prov)?;
    outputs.push(p);
    clock.lap("tables");
    let (res, lost) = residuals(
        &bt.step,
        (&bm.all.labels, &labels.labels),
        &results,
        "free",
        opts.sampler.residual_draws,
        bt.model_error.as_ref().and_then(|m| m.board_sd(false)),
    );
    lost_finding(&lost, &mut findings);
    let p = opts.out.join("residuals.parquet");
    write_residuals(&p, &res, &prov)?;
    outputs.push(p);
    let p = opts.out.join("rom.npz");
    crate::io::atomic::write_bytes(&p, &bt.step.target.predictor.rom.to_npz_bytes())?;
    outputs.push(p);
    let ev = boards::board_evidence(&bm, &bt, &results, &labels, &shape_weights)?;
    let p = opts.out.join("evidence.json");
    crate::io::atomic::write_bytes(&p, serde_json::to_string_pretty(&ev)?.as_bytes())?;
    outputs.push(p);
    clock.lap("residuals");
    finish(
        opts,
        findings,
        outputs,
        &results,
        &summary,
        ev,
        sampler_seconds,
        &labels.labels,
        verbose,
        "update boards",
        &acceleration,
        &clock,
    )
}

/// Runs a step-1 attempt; when its reference or posterior presses against the ROM's box
/// ([`boards::check_board_reference_box`], [`boards::check_board_box`]) and a box up to
/// [`crate::update::rom_box::MAX_ROM_BOX`] (the shear modulus's axis up to
/// [`crate::update::rom_box::MAX_G_Z_LOG_BOX`]) would hold it, rebuilds the ROM over that box
/// and runs again (the finding `update.rom_box_widened` says so, and the new ROM is checked
/// against the full model), at most [`WIDENINGS`] times. A posterior that still presses, or
/// needs more, stops the stage with the message.
pub(crate) fn widen_rom_box(
    opts: &UpdateOptions,
    attempt: impl Fn(&UpdateOptions, &[Finding]) -> anyhow::Result<StageResult>,
) -> anyhow::Result<StageResult> {
    let mut current = opts.clone();
    let mut notes: Vec<Finding> = vec![];
    let mut widenings = 0;
    loop {
        let e = match attempt(&current, &notes) {
            Err(e) => e,
            ok => return ok,
        };
        let Some(v) = e.downcast_ref::<RomBoxViolation>() else {
            return Err(e);
        };
        if widenings == WIDENINGS {
            return Err(e);
        }
        let Some(model) = widened(&current.model, v) else {
            return Err(e);
        };
        let g_z_wider = v.needed_g_z_log_box;
        let wider = UpdateOptions {
            model,
            ..current.clone()
        };
        let what = v
            .message
            .lines()
            .filter_map(|l| l.strip_prefix("  "))
            .collect::<Vec<_>>()
            .join("; ");
        let by = match v.by {
            "reference" => "reference (checked before sampling)",
            other => other,
        };
        let note = Finding::new(
            Severity::Warning,
            "update.rom_box_widened",
            format!(
                "the {by} pressed against the ROM's ±{:.0} % box ({}): the ROM was rebuilt over ±{:.0} % around the board file's values{}, checked against the full model (update.rom_box_check), and the sampling run again",
                100.0 * current.model.rom_box,
                what.trim(),
                100.0 * wider.model.rom_box,
                match g_z_wider {
                    Some(w) => format!(", the transverse shear modulus's axis over × or ÷ {:.2}", w.exp()),
                    None => String::new(),
                }
            ),
        );
        eprintln!("update boards: {}", note.message);
        notes.push(note);
        current = wider;
        widenings += 1;
    }
}

/// Times step 1 widens the ROM's box: once on the reference's word before sampling, once
/// more on the posterior's (each widening must widen something, [`widened`]).
const WIDENINGS: usize = 2;

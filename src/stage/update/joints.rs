//! `update joints` (step 2): bolted measurements, the boards carried from step 1 (the cut
//! posterior); read → [`crate::update::joints`] → write.

use super::*;

/// The key of a [`JointPrep`]: the step's input files by content and its model spec (not the
/// sampler's parameters, which do not change the preparation), less `enrich_new_modes`: the
/// centre is fitted before the new modes are paired, and a ROM of fewer modes than a new
/// mode needs is rebuilt (`prepare_joints`).
pub(crate) fn joint_prep_key(prep: &crate::io::manifest::Prepared, spec: &ModelSpec) -> String {
    let mut h = blake3::Hasher::new();
    for f in &prep.inputs {
        h.update(f.path.as_bytes());
        h.update(&[0]);
        h.update(f.blake3.as_bytes());
        h.update(&[0]);
    }
    let spec = ModelSpec {
        enrich_new_modes: false,
        ..spec.clone()
    };
    h.update(serde_json::to_string(&spec).unwrap_or_default().as_bytes());
    h.finalize().to_hex().to_string()
}

/// Step 2: the joints, bolted, carrying step 1's posterior (the cut posterior).
pub fn run_joints(
    opts: &UpdateOptions,
    boards_dir: &Path,
    verbose: bool,
) -> anyhow::Result<StageOutcome> {
    run_joints_with(opts, boards_dir, &mut None, None, verbose)
}

/// [`run_joints`] with the caller's preparation: a `memo` prepared for the same model spec and
/// inputs (its key says) spares the centre fit and the ROM; a new preparation is left in it.
pub fn run_joints_with(
    opts: &UpdateOptions,
    boards_dir: &Path,
    memo: &mut Option<JointPrep>,
    gate: Option<&CentreGate>,
    verbose: bool,
) -> anyhow::Result<StageOutcome> {
    let paths = joint_paths(opts, boards_dir);
    let mut inputs = vec![
        paths.pairs.clone(),
        paths.presence.clone(),
        paths.modes.clone(),
        paths.step1.clone(),
        paths.measurements.clone(),
    ];
    if opts.model.enrich.is_some_and(is_board_mechanism) {
        inputs.push(paths.step1_evidence.clone());
        inputs.push(paths.measurements.clone());
    }
    let (board, spec) = step_spec(
        opts,
        "update_joints",
        inputs,
        &[("step", "joints"), ("posterior", "cut")],
        MANIFEST_JOINTS,
    )?;
    crate::stage::run(spec, opts.force, |prep| {
        joints_body(opts, &board, &paths, prep, (memo, gate), verbose)
    })
}

pub(crate) struct JointPaths {
    pub(crate) pairs: PathBuf,
    pub(crate) presence: PathBuf,
    pub(crate) modes: PathBuf,
    pub(crate) step1: PathBuf,
    pub(crate) step1_evidence: PathBuf,
    pub(crate) measurements: PathBuf,
}

/// Step 2's inputs as read: the bolted pairs, the step-1 posterior, a board mechanism's step-1
/// enrichment and covariate column.
pub(crate) struct JointInputs {
    pub(crate) pairs: Vec<PairRow>,
    pub(crate) presence: Vec<String>,
    pub(crate) step1: Step1,
    pub(crate) step1_enrichment: serde_json::Value,
    pub(crate) mode_rows: Vec<ModeRow>,
    pub(crate) covariate: Option<Vec<(String, Option<f64>)>>,
}

pub(crate) fn read_joint_inputs(
    opts: &UpdateOptions,
    paths: &JointPaths,
    pairs: Vec<PairRow>,
) -> anyhow::Result<JointInputs> {
    let step1 = read_step1(&paths.step1)?;
    let presence = read_presence(&paths.presence, "bolted")?;
    let board_mech = opts.model.enrich.filter(|m| is_board_mechanism(*m));
    let step1_enrichment = match board_mech {
        Some(_) => read_step1_enrichment(&paths.step1_evidence)?,
        None => serde_json::Value::Null,
    };
    let mode_rows = read_modes_table(&paths.modes)?;
    let covariate = match board_mech {
        Some(Mechanism::TemperatureStiffness) => match step1_enrichment["covariate"].as_str() {
            Some(column) => Some(read_covariate(&paths.measurements, column)?),
            None => None,
        },
        _ => None,
    };
    Ok(JointInputs {
        pairs,
        presence,
        step1,
        step1_enrichment,
        mode_rows,
        covariate,
    })
}

pub(crate) fn joints_body(
    opts: &UpdateOptions,
    board: &Board,
    paths: &JointPaths,
    prep: &crate::io::manifest::Prepared,
    (memo, gate): (&mut Option<JointPrep>, Option<&CentreGate>),
    verbose: bool,
) -> anyhow::Result<StageResult> {
    use crate::update::joints;
    let mut clock = PhaseClock::new("update joints", verbose);
    let mut findings = Findings::default();
    let pairs = read_pairs(&paths.pairs)?;
    if !pairs.iter().any(|p| p.setup == "bolted") {
        return no_bolted_data(opts, &paths.measurements, findings);
    }
    let PreparedJoints {
        inp,
        jm,
        c,
        centre,
        jt,
        sopts,
        shape_weights,
        cut_basis,
    } = prepare_joints(
        opts,
        board,
        paths,
        pairs,
        joint_prep_key(prep, &opts.model),
        (memo, gate),
        &mut clock,
        &mut findings,
        verbose,
    )?;
    let (results, acceleration) = sample(
        &jt.step.target,
        &sopts.sampler,
        "joints",
        &jt.aux,
        Some(&centre.coords),
        &|_, _| Ok(()),
        verbose,
    )?;
    let sampler_seconds = clock.lap("sampler");
    acceleration_findings(&acceleration, &mut findings);
    joints::check_joint_box(
        (&jm, &c),
        &centre.coords,
        &results,
        &jt.step.unit_names,
        &opts.model,
        verbose,
    )?;
    findings.push(joints::rom_posterior_finding(
        &jm.model,
        &jt.step.target,
        &results,
        c.need,
    ));
    clock.lap("rom_posterior_check");
    let prov = provenance("update_joints", &prep.fingerprint);
    let (res, lost) = residuals(
        &jt.step,
        (&c.all.labels, &c.labels.labels),
        &results,
        "bolted",
        opts.sampler.residual_draws,
        None,
    );
    lost_finding(&lost, &mut findings);
    clock.lap("predictive_residuals");
    let cut = joints::cut_scale(cut_basis.as_ref(), &res, &c.labels.labels);
    if cut_basis.is_some() && cut.is_none() {
        findings.push(Finding::new(
            Severity::Warning,
            "update.cut_scale_none",
            "joints: no model-form scale for the bolted modes step 2 did not update (an updated mode has fewer than two measurements, or its residuals are not finite): their predictions carry ε alone".to_string(),
        ));
    }
    // Its own stream of the seed: the draws do not move the sampler's.
    let cut_seed = opts.sampler.seed ^ 0x6375_745f_7363_616c;
    let tables = joints::joint_tables(
        &jm,
        &jt,
        &results,
        &c.labels,
        &inp.step1,
        (opts.sampler.runs, opts.sampler.seed),
        cut.as_ref()
            .zip(cut_basis.as_ref())
            .map(|(c, b)| (c, b, cut_seed)),
    );
    let mut outputs = write_joint_tables(&opts.out, &tables, &results, &prov)?;
    clock.lap("tables");
    let p = opts.out.join("residuals.parquet");
    write_residuals(&p, &res, &prov)?;
    outputs.push(p);
    let p = opts.out.join("rom.npz");
    crate::io::atomic::write_bytes(&p, &jt.step.target.predictor.rom.to_npz_bytes())?;
    outputs.push(p);
    let mut ev = joints::joint_evidence(
        (&jm, &c),
        &jt.step.target,
        &results,
        &centre,
        &inp.step1_enrichment,
        &shape_weights,
        &opts.model,
    )?;
    ev["predictive_discrepancy"] = joints::cut_scale_json(cut.as_ref());
    let p = opts.out.join("evidence.json");
    crate::io::atomic::write_bytes(&p, serde_json::to_string_pretty(&ev)?.as_bytes())?;
    outputs.push(p);
    clock.lap("residuals");
    finish(
        &sopts,
        findings,
        outputs,
        &results,
        &tables.summary,
        ev,
        sampler_seconds,
        &c.labels.labels,
        verbose,
        "update joints",
        &acceleration,
        &clock,
    )
}

/// Step 2's input files for the options `opts` and the step-1 directory `boards_dir`.
fn joint_paths(opts: &UpdateOptions, boards_dir: &Path) -> JointPaths {
    let extract_dir = opts.extract_dir();
    JointPaths {
        pairs: opts.pair_dir.join("pairs.parquet"),
        presence: opts.pair_dir.join("presence.parquet"),
        modes: extract_dir.join("modes.parquet"),
        step1: boards_dir.join("boards.parquet"),
        step1_evidence: boards_dir.join("evidence.json"),
        measurements: opts.ingest_dir.join("measurements.parquet"),
    }
}

/// The per-assembly screen of `joint_stiffness_per_joint` ([`crate::update::joint_screen`]):
/// step 2 prepared with `opts` (the every-joint enrichment, on `opts.model.enrich_units`),
/// integrated over `draws` rows of the baseline step 2's posterior in `baseline_dir`, each
/// assembly's integrals by `is_draws` importance draws; a joint is named only where it moves
/// the assembly's modes by `practical_rel` (relative frequency); with the screened
/// assemblies' residuals under the screen's model ([`ScreenRun`]). Nothing is written.
pub fn screen_joint_units(
    opts: &UpdateOptions,
    boards_dir: &Path,
    baseline_dir: &Path,
    (draws, is_draws): (usize, usize),
    practical_rel: f64,
    verbose: bool,
) -> anyhow::Result<ScreenRun> {
    use crate::update::joint_screen::{screen_joints, BaselineDraw, ScreenOptions};
    let (board, _) = load_board(opts.board.as_deref())?;
    let paths = joint_paths(opts, boards_dir);
    let pairs = read_pairs(&paths.pairs)?;
    let mut findings = Findings::default();
    let mut clock = PhaseClock::new("diagnose joint screen", verbose);
    let p = prepare_joints(
        opts,
        &board,
        &paths,
        pairs,
        String::new(),
        (&mut None, None),
        &mut clock,
        &mut findings,
        verbose,
    )?;
    let target = &p.jt.step.target;
    let labels = &p.c.labels.labels;
    let pop_path = baseline_dir.join("population.parquet");
    let rows = crate::io::tables::update::read_joint_population(&pop_path, labels, draws)?;
    // x0 = ln(k / k_ref): the baseline's and the enrichment's coordinate 0 share k_ref.
    let k_ref = p.jm.enr.coordinates[0].report_ref;
    let fixed = |e: &crate::bayes::target::ErrorPrior| match e {
        crate::bayes::target::ErrorPrior::Fixed { value } => Some(vec![*value; labels.len()]),
        crate::bayes::target::ErrorPrior::Inferred { .. } => None,
    };
    let mut baseline = vec![];
    for r in rows {
        let aux = p
            .inp
            .step1
            .draws
            .iter()
            .find(|(k, _)| *k == (r.boards_run, r.boards_draw))
            .map(|(_, v)| std::sync::Arc::new(v.clone()))
            .ok_or_else(|| {
                anyhow!(
                    "{}: step-1 draw (run {}, draw {}) is not in {}",
                    pop_path.display(),
                    r.boards_run,
                    r.boards_draw,
                    paths.step1.display()
                )
            })?;
        let eps = r
            .eps
            .or_else(|| fixed(&target.errors.eps))
            .ok_or_else(|| anyhow!("{}: no eps_<mode> columns", pop_path.display()))?;
        let delta = match &target.errors.delta {
            None => vec![],
            Some(d) => r
                .delta
                .or_else(|| fixed(d))
                .ok_or_else(|| anyhow!("{}: no delta_<mode> columns", pop_path.display()))?,
        };
        let unit_sd = target
            .errors
            .unit_model_error_sd_with(r.discrepancy_unit_scale);
        baseline.push(BaselineDraw {
            aux,
            mu: r.mu_ln_k_con - k_ref.ln(),
            sigma: r.sigma_ln_k_con,
            eps,
            delta,
            bias: r.bias.unwrap_or_default(),
            unit_sd,
        });
    }
    let units: Vec<(usize, String)> = opts
        .model
        .enrich_units
        .iter()
        .map(|m| {
            p.jt.step
                .unit_names
                .iter()
                .position(|u| u == m)
                .map(|b| (b, m.clone()))
                .ok_or_else(|| anyhow!("--enrich-units {m}: not a bolted measurement of step 2"))
        })
        .collect::<anyhow::Result<_>>()?;
    let contrast_log_sd =
        p.jm.enr
            .coordinates
            .get(1)
            .map(|c| c.prior_sd)
            .ok_or_else(|| anyhow!("the screen needs the every-joint enrichment's contrasts"))?;
    let screen = screen_joints(
        target,
        board.holes.len(),
        &units,
        &baseline,
        &ScreenOptions {
            contrast_log_sd,
            is_draws,
            seed: opts.sampler.seed,
            practical_rel,
            posterior_draws: SCREEN_RESIDUAL_DRAWS,
        },
    );
    clock.lap("screen");
    // The screened assemblies' posterior-predictive residuals under the screen's model, as
    // step 2 forms them (no model-error term in the predictive sd).
    let rows = units
        .iter()
        .zip(&screen.units)
        .flat_map(|(&(b, _), u)| {
            let coords: Vec<Vec<f64>> = u
                .posterior
                .iter()
                .map(|(_, y)| crate::update::joint_screen::coords_of(y))
                .collect();
            let draws: Vec<crate::update::posterior::PredDraw<'_>> = u
                .posterior
                .iter()
                .zip(&coords)
                .map(|((r, _), x)| crate::update::posterior::PredDraw {
                    aux: &baseline[*r].aux,
                    x,
                    eps: baseline[*r].eps.clone(),
                })
                .collect();
            crate::update::posterior::unit_residuals(
                &p.jt.step,
                (&p.c.all.labels, labels),
                b,
                &draws,
                "bolted",
                None,
            )
        })
        .collect::<Vec<_>>();
    let (residuals, lost) = crate::update::posterior::split_rows(rows.into_iter());
    clock.lap("screen residuals");
    Ok(ScreenRun {
        screen: crate::update::joint_screen::JointScreen {
            untracked: lost
                .iter()
                .map(|l| {
                    format!(
                        "{} {} (tracked at {:.0} % of the draws)",
                        l.measurement_id,
                        l.label,
                        100.0 * l.share_tracked
                    )
                })
                .collect(),
            ..screen
        },
        residuals,
    })
}

/// Equally weighted posterior draws per screened assembly for its residuals: the mean model
/// frequency's Monte Carlo error is then ~1/8 of its posterior sd.
const SCREEN_RESIDUAL_DRAWS: usize = 64;

/// The per-assembly joint screen, and the screened assemblies' posterior-predictive
/// residuals under its model (each assembly's joints their own stiffnesses).
pub struct ScreenRun {
    pub screen: crate::update::joint_screen::JointScreen,
    pub residuals: Vec<crate::update::posterior::Residual>,
}

/// Step 2's model and target as prepared for sampling: the bolted models with the
/// enrichment, the ROM's centre and the ROM, the target with its shape-term weights.
pub(crate) struct PreparedJoints {
    pub(crate) inp: JointInputs,
    pub(crate) jm: crate::update::joints::JointModels,
    pub(crate) c: crate::update::joints::Centred,
    pub(crate) centre: crate::update::centre::CentreFit,
    pub(crate) jt: crate::update::joints::JointTarget,
    pub(crate) sopts: UpdateOptions,
    pub(crate) shape_weights: Vec<crate::bayes::shape_weight::ShapeWeight>,
    /// Without a discrepancy in the likelihood, the basis of its cut scale
    /// (`bayes::discrepancy::CutScale`): the complement of the units' sensitivities with the
    /// bolted model's stated fidelity as the scale's prior.
    pub(crate) cut_basis: Option<crate::bayes::discrepancy::Discrepancy>,
}

/// Prepare step 2 up to the sampler ([`PreparedJoints`]); `key` keys the caller's `memo`
/// (a preparation of the same inputs and model spec spares the centre fit and the ROM).
#[allow(clippy::too_many_arguments)]
pub(crate) fn prepare_joints(
    opts: &UpdateOptions,
    board: &Board,
    paths: &JointPaths,
    pairs: Vec<PairRow>,
    key: String,
    (memo, gate): (&mut Option<JointPrep>, Option<&CentreGate>),
    clock: &mut PhaseClock,
    findings: &mut Findings,
    verbose: bool,
) -> anyhow::Result<PreparedJoints> {
    use crate::update::joints;
    let inp = read_joint_inputs(opts, paths, pairs)?;
    let (step1_source, ev_source) = (
        paths.step1.display().to_string(),
        paths.step1_evidence.display().to_string(),
    );
    let labels = select_labels(
        &inp.pairs,
        "bolted",
        &opts.model.modes,
        &inp.presence,
        findings,
    )?;
    let bolted_rows: Vec<&PairRow> = inp.pairs.iter().filter(|p| p.setup == "bolted").collect();
    let mut jm = joints::joint_models(
        board,
        &opts.model,
        &labels,
        &inp.pairs,
        &inp.step1,
        &step1_source,
        &inp.step1_enrichment,
        findings,
    )?;
    clock.lap("models");
    let t_centre = std::time::Instant::now();
    let remembered = memo.take().filter(|m| m.key == key);
    let fit = match &remembered {
        Some(m) => m.centre.clone(),
        None => joints::fit_joint_centre_of(&jm, &labels, &bolted_rows)?,
    };
    let centre = fit.coords.clone();
    if verbose {
        eprintln!(
            "joints: ROM centre {:?} = {centre:.4?} (ln, relative to the priors' centres), {} in {:.1} s",
            jm.enr.coordinates.iter().map(|c| c.name.as_str()).collect::<Vec<_>>(),
            if remembered.is_some() { "as prepared by the caller's previous run of the same step" } else { "fitted" },
            t_centre.elapsed().as_secs_f64()
        );
    }
    let c = joints::centred(
        &mut jm,
        &centre,
        &labels,
        &opts.model,
        &inp.mode_rows,
        &bolted_rows,
        findings,
    )?;
    let bolted_rows: Vec<&PairRow> = bolted_rows.into_iter().chain(&c.new_rows).collect();
    clock.lap("centre_fit");
    if let Some(why) = gate.and_then(|g| g(&fit)) {
        bail!("{why}");
    }
    let rom_options = rom_options_for(
        &jm.model,
        c.need,
        &c.log_axes,
        &joints::holding_step1_g_z(&opts.model, &inp.step1, &jm.nominal),
    );
    let rom = match remembered {
        Some(m) if m.rom.n_modes >= rom_options.n_modes => m.rom,
        _ => model_cache::rom(opts.cache.as_ref(), &jm.model, &rom_options)?,
    };
    *memo = Some(JointPrep {
        key,
        centre: fit.clone(),
        rom: rom.clone(),
    });
    rom_centre_check(&jm.model, &rom, c.need, findings)?;
    clock.lap("rom_build");
    let measurements_source = paths.measurements.display().to_string();
    let mut jt = joints::joint_target(
        &jm,
        &c,
        &rom,
        &bolted_rows,
        &inp.mode_rows,
        (&inp.step1, &step1_source),
        (&inp.step1_enrichment, &ev_source),
        inp.covariate
            .as_deref()
            .map(|v| (v, measurements_source.as_str())),
        &opts.model,
        &opts.sampler,
        findings,
    )?;
    let mut sopts = opts.clone();
    sopts.sampler = jt.sampler.clone();
    clock.lap("unit_data");
    // The units located for the weights with the step-1 posterior mean of the boards.
    let step1 = &inp.step1;
    let draws_mean: Vec<f64> = match step1.draws.first() {
        None => vec![],
        Some((_, d0)) => (0..d0.len())
            .map(|k| step1.draws.iter().map(|(_, d)| d[k]).sum::<f64>() / step1.draws.len() as f64)
            .collect(),
    };
    jt.step.target.errors.discrepancy = discrepancy_for(
        &jt.step.target,
        (&draws_mean, Some(&centre)),
        // Off unless asked for (`--discrepancy-pct`): bolted, each measurement's joint
        // stiffness is already free, and a per-mode bias common to every assembly spans every
        // shift a common joint effect makes, so no refit could be told from it.
        opts.model.discrepancy_freq.unwrap_or(0.0),
        (&[], "joints"),
        findings,
    )?;
    let cut_basis = match jt.step.target.errors.discrepancy {
        Some(_) => None,
        None => discrepancy_for(
            &jt.step.target,
            (&draws_mean, Some(&centre)),
            crate::bayes::discrepancy::BOLTED_FIDELITY_FREQ,
            (&[], "joints"),
            &mut Findings::default(),
        )
        .unwrap_or(None),
    };
    let shape_weights = weigh_shapes(
        &mut jt.step.target,
        &opts.model.shape_weights,
        (&draws_mean, Some(&centre)),
        &c.labels.labels,
        opts.sampler.seed,
        "joints",
    )?;
    report_shape_weights(&shape_weights, "joints", verbose, findings);
    clock.lap("shape_weights");
    Ok(PreparedJoints {
        inp,
        jm,
        c,
        centre: fit,
        jt,
        sopts,
        shape_weights,
        cut_basis,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::manifest::{FileHash, Prepared};

    fn prepared(input_blake3: &str) -> Prepared {
        Prepared {
            spec: StageSpec {
                stage: "update_joints".into(),
                inputs: vec![],
                input_base: PathBuf::new(),
                config: serde_json::Value::Null,
                seed: Some(1),
                manifest_path: PathBuf::new(),
            },
            inputs: vec![FileHash {
                path: "pairs.parquet".into(),
                blake3: input_blake3.into(),
                bytes: 1,
            }],
            config_blake3: String::new(),
            fingerprint: String::new(),
        }
    }

    fn spec(rom_box: f64, enrich: Mechanism) -> ModelSpec {
        ModelSpec {
            rom_box,
            enrich: Some(enrich),
            ..ModelSpec::for_tests()
        }
    }

    /// A preparation is keyed by the inputs' content and the model spec (the sampler's
    /// parameters are not part of it): another model option or input content changes it.
    #[test]
    fn the_preparation_key_is_the_inputs_and_the_model_spec() {
        let key = joint_prep_key(&prepared("aa"), &spec(0.2, Mechanism::JointRotation));
        assert_eq!(
            joint_prep_key(&prepared("aa"), &spec(0.2, Mechanism::JointRotation)),
            key
        );
        assert_ne!(
            joint_prep_key(&prepared("aa"), &spec(0.3, Mechanism::JointRotation)),
            key
        );
        assert_ne!(
            joint_prep_key(&prepared("aa"), &spec(0.2, Mechanism::JointMass)),
            key
        );
        assert_ne!(
            joint_prep_key(&prepared("ab"), &spec(0.2, Mechanism::JointRotation)),
            key
        );
        // The new-mode refit shares its refit's preparation: the centre is fitted before
        // new modes are paired.
        let new_modes = ModelSpec {
            enrich_new_modes: true,
            ..spec(0.2, Mechanism::JointRotation)
        };
        assert_eq!(joint_prep_key(&prepared("aa"), &new_modes), key);
    }
}

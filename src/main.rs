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
#[command(name = "hbmu", version = hbmu::io::manifest::TOOL_VERSION, about, long_about)]
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
#[allow(
    clippy::large_enum_variant,
    reason = "parsed once per process: boxing the update options would buy nothing"
)]
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
    /// The physics core: full-model modes, the parametric reduced-order model, sensitivities.
    Fe {
        #[command(subcommand)]
        command: FeCommand,
    },
    /// Identify modes (frequency, damping, shape) per measurement from the ingest tables:
    /// LSCF over all scan points, stabilization diagram, automatic pole selection, LSFD shapes.
    Extract {
        /// Output directory of `hbmu ingest`.
        ingest_dir: PathBuf,
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
        /// Identification band in Hz, e.g. `--band 200 4500` (default: the whole axis).
        #[arg(long, num_args = 2, value_names = ["LO_HZ", "HI_HZ"])]
        band: Option<Vec<f64>>,
        /// Highest model order of the stabilization diagram.
        #[arg(long)]
        max_order: Option<usize>,
        /// Do not write the stabilization-diagram SVGs.
        #[arg(long)]
        no_plots: bool,
        #[arg(long)]
        force: bool,
    },
    /// Pair identified modes with the model's by MAC (Hungarian assignment), label them from
    /// the model shapes, detect missing and swapped modes, and apply the presence rule.
    Pair {
        /// Output directory of `hbmu extract`.
        extract_dir: PathBuf,
        /// Board description (TOML) of the model; default: the built-in board.
        #[arg(long = "board", alias = "model", value_name = "BOARD_TOML")]
        model: Option<PathBuf>,
        #[arg(long)]
        out: PathBuf,
        /// Minimum MAC for an accepted pair.
        #[arg(long, default_value_t = 0.8)]
        mac_min: f64,
        /// Presence rule: a mode counts for updating when accepted in at least this fraction
        /// of its setup's measurements (the paper: 1.0, every measurement).
        #[arg(long, default_value_t = 1.0)]
        min_fraction: f64,
        /// Model modes computed per setup.
        #[arg(long, default_value_t = 12)]
        n_model_modes: usize,
        #[arg(long)]
        no_plots: bool,
        #[arg(long)]
        force: bool,
    },
    /// The virtual lab: simulate complete measurement campaigns (with concealed effects).
    Lab {
        #[command(subcommand)]
        command: LabCommand,
    },
    /// Hierarchical Bayesian updating by sequential Monte Carlo: step 1 `boards` (free-free),
    /// step 2 `joints` (bolted, boards carried from step 1).
    Update {
        #[command(subcommand)]
        command: UpdateCommand,
    },
    /// Monte Carlo propagation of the updated posterior: predicted eigenfrequencies of a new
    /// board and of every measured board, free-free, and bolted with a new joint when a step-2
    /// posterior is given (predictions.parquet).
    Propagate {
        /// Output directory of `hbmu update boards`, and optionally of `hbmu update joints`.
        #[arg(required = true)]
        update_dirs: Vec<PathBuf>,
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
        /// Propagation draws (cost is linear in draws).
        #[arg(long, default_value_t = 4000)]
        draws: usize,
        #[arg(long, default_value_t = 20261122)]
        seed: u64,
        /// Output directory of `hbmu pair` (default: `pair` beside the step-1 directory).
        #[arg(long)]
        pair: Option<PathBuf>,
        /// Directory with rom_free.npz and rom_bolted.npz (default: `fe` beside the step-1 directory).
        #[arg(long)]
        fe: Option<PathBuf>,
        /// Half-width of the ROMs' verified box, relative (as built by `fe rom --box-rel`), for
        /// a ROM that does not record the box it was built over (one written before it did).
        #[arg(long, default_value_t = 0.2)]
        rom_box: f64,
        #[arg(long)]
        force: bool,
    },
    /// Diagnose model inadequacy in a work directory: locate the misfit (posterior-predictive
    /// checks per setup, mode, measurement and sheet covariate; unpaired modes), screen the
    /// mechanism library, refit the screened joint mechanisms (each under OUT/refits/<id>, a
    /// hashed stage of its own) and compare them with the step-2 posterior by log Bayes
    /// factor and held-out error. Writes diagnosis.json and diagnosis.parquet.
    Diagnose {
        /// Work directory of one campaign (ingest/, extract/, pair/, update_boards/,
        /// [update_joints/]).
        work_dir: PathBuf,
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
        /// Board file the work directory was updated with (default: the built-in board).
        #[arg(long = "board", alias = "model", value_name = "BOARD_TOML")]
        model: Option<PathBuf>,
        /// Refit at most this many screened candidates per part of the located misfit (its
        /// mean shifts, each covariate trend, the outlier assemblies; 0: locate and screen
        /// only). A part a favoured refit explains takes no more.
        #[arg(long, default_value_t = 3)]
        max_refits: usize,
        /// Run only this candidate's refit (e.g. joint_rotation, joint_stiffness_per_joint_2)
        /// and stop: refits are independent, a cluster runs them side by side.
        #[arg(long)]
        only: Option<String>,
        /// The practical threshold, in % of a frequency: a misfit smaller than this is no
        /// finding, however significant, and a mechanism must remove at least this much
        /// (argued in diagnose::select::DEFAULT_PRACTICAL_THRESHOLD_REL) [default: 0.1]
        #[arg(long, value_name = "PCT")]
        practical_threshold_pct: Option<f64>,
        #[arg(long)]
        force: bool,
    },
    /// The validation report of a work directory: a self-contained HTML page (inline SVG
    /// figures), its tables as Parquet and CSV, and a Markdown summary.
    Report {
        /// Work directory of one campaign (ingest/, extract/, pair/, fe/, update_boards/,
        /// [update_joints/], propagate/).
        work_dir: PathBuf,
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
        #[arg(long)]
        force: bool,
    },
    /// Write the JSON schemas of every Parquet table and MCAP channel into a directory
    /// (the repository keeps them under schemas/).
    Schemas {
        /// Output directory (creates tables/ and mcap/ in it).
        #[arg(long)]
        out: PathBuf,
    },
}

/// Model options shared by the `fe` subcommands.
#[derive(clap::Args, Clone)]
struct ModelArgs {
    /// Board description (TOML); default: the built-in board (data/boards/default.toml).
    #[arg(long)]
    board: Option<PathBuf>,
    /// Boundary conditions.
    #[arg(long, value_enum, default_value = "free")]
    setup: stage::fe::SetupArg,
    /// Parameter override NAME=VALUE (repeatable), e.g. --set e_x_pa=25e9.
    #[arg(long = "set", value_name = "NAME=VALUE")]
    set: Vec<String>,
    /// Mesh override, elements along x and y (default: the board file's mesh).
    #[arg(long, num_args = 2, value_names = ["NX", "NY"])]
    mesh: Option<Vec<usize>>,
    /// Rerun even when up to date.
    #[arg(long)]
    force: bool,
}

impl ModelArgs {
    fn options(&self) -> stage::fe::ModelOptions {
        stage::fe::ModelOptions {
            board: self.board.clone(),
            setup: self.setup,
            set: self.set.clone(),
            mesh: self.mesh.as_ref().map(|v| (v[0], v[1])),
        }
    }
}

/// Options shared by both updating steps.
#[derive(clap::Args, Clone)]
struct UpdateArgs {
    /// Output directory of `hbmu ingest`.
    ingest_dir: PathBuf,
    /// Output directory of `hbmu pair`.
    pair_dir: PathBuf,
    /// Output directory of `hbmu extract` (modes.parquet); default: `extract` beside PAIR_DIR.
    #[arg(long)]
    extract: Option<PathBuf>,
    /// Board description (TOML) of the model; default: the built-in board.
    #[arg(long = "board", alias = "model", value_name = "BOARD_TOML")]
    model: Option<PathBuf>,
    #[arg(long)]
    out: PathBuf,
    #[arg(long, default_value_t = 20_261_122)]
    seed: u64,
    /// Particles per SMC run.
    #[arg(long, default_value_t = 2000)]
    particles: usize,
    /// Independent SMC runs (R-hat, ESS and the evidence's error bar are across runs).
    #[arg(long, default_value_t = 4)]
    runs: usize,
    /// Mode labels to update (comma-separated); default: those pair marks for updating.
    #[arg(long, value_delimiter = ',')]
    modes: Vec<String>,
    /// Fix the relative eigenvalue prediction error of every mode to this value instead of
    /// inferring it per mode.
    #[arg(long)]
    eps_fixed: Option<f64>,
    /// Prior median of the per-mode relative eigenvalue error ε (λ = ω²; ε ≈ 2× the relative
    /// frequency error); ln ε ~ N(ln median, 1.5²).
    #[arg(long, default_value_t = 0.005)]
    eps_median: f64,
    /// Leave the mode-shape terms out of the likelihood.
    #[arg(long)]
    no_shapes: bool,
    /// The power of each mode's shape term: `auto` (1 over the design effect of the shape
    /// residuals' agreement between measurements, evidence.json's shape_weights), `off`
    /// (every measurement's shape independent), or an `update` evidence.json whose
    /// shape_weights to take (a refit compared with that run by its evidence).
    #[arg(long, default_value = "auto", value_parser = stage::update::ShapeWeighting::parse)]
    shape_weights: stage::update::ShapeWeighting,
    /// Fix the mode-shape error δ instead of inferring it per mode.
    #[arg(long)]
    delta_fixed: Option<f64>,
    /// Prior median of the per-mode shape error δ (norm of the unit-shape residual,
    /// δ² ≈ 1 − MAC); ln δ ~ N(ln median, 1.5²).
    #[arg(long, default_value_t = 0.1)]
    delta_median: f64,
    /// LKJ shape of the population correlation prior.
    #[arg(long, default_value_t = 2.0)]
    lkj_eta: f64,
    /// Target ESS fraction when choosing the next temperature.
    #[arg(long, default_value_t = 0.5)]
    target_ess: f64,
    /// Cap the ROM's basis size (faster, less accurate; default: the physics core's).
    #[arg(long)]
    rom_basis: Option<usize>,
    /// Start tempering from the prior instead of a Laplace-type reference fitted to the data
    /// (slower: about as many stages as the data carry information; same posterior).
    #[arg(long)]
    from_prior: bool,
    /// Evaluate the ROM at every step instead of verified local surrogates corrected to the
    /// ROM at the end (slower; same posterior).
    #[arg(long)]
    no_surrogate: bool,
    /// Correct the surrogates to the whole ROM instead of to each unit's verified subspace
    /// of it (slower; the same posterior within the subspaces' verified error).
    #[arg(long)]
    no_subspace: bool,
    /// Rerun even when up to date.
    #[arg(long)]
    force: bool,
    /// Step 1: take the model as exact, without the per-mode model-error term (a relative
    /// eigenvalue error, its prior sd from how the model's frequencies move on finer meshes).
    /// Where step 1 infers the model-form discrepancy (the default) the mesh's error is
    /// common to the boards and part of it, and the mesh study is only recorded; without one
    /// (`--discrepancy-pct 0`) the term is each board's own.
    #[arg(long)]
    no_model_error: bool,
    /// The model's stated fidelity, in % of frequency: the prior median of the scale of the
    /// model-form discrepancy, a per-mode bias common to every unit that the parameters
    /// cannot absorb (bayes::discrepancy). 0 takes the model as exact
    /// [default: 0.5 for boards (free-free); none for joints (bolted), where the bolted
    /// model's stated fidelity is 1.5]
    #[arg(long, value_name = "PCT")]
    discrepancy_pct: Option<f64>,
    /// Step 1: standard deviation of the balance's error common to every board, relative to
    /// the weighed mass. A balance's readability is not its accuracy: weighing a board against
    /// steel calibration weights without the air-buoyancy correction shifts its reading by
    /// about −0.05 %, and calibration scales every reading alike. Each board's mass term
    /// holds its readings' own precision; this common part, which the data cannot inform,
    /// widens the physical masses and moduli (summary.parquet's physical_* columns). 0
    /// trusts the balance's scale (buoyancy-corrected readings on a calibrated balance, or a
    /// virtual lab's)
    /// [default: 3e-4]
    #[arg(long)]
    balance_bias: Option<f64>,
}

#[derive(Subcommand)]
enum UpdateCommand {
    /// Step 1: board parameters and their population from the free-free modes and masses.
    Boards {
        #[command(flatten)]
        common: UpdateArgs,
        /// Updated board parameters (names as in `fe sensitivity`); default
        /// `e_x_pa,e_y_pa,g_xy_pa,mass_scale`, and `g_z_pa` too on a shear-deformable board
        /// (its transverse shear modulus is on no datasheet).
        #[arg(long, value_delimiter = ',')]
        params: Option<Vec<String>>,
        /// Prior sd of the population means, relative to the board file's nominal values.
        #[arg(long, default_value_t = 0.1)]
        prior_width: f64,
        /// Scale of the population sds' prior, relative: the half-normal's scale; the
        /// log-normal's median is 0.6745 × it.
        #[arg(long, default_value_t = 0.05)]
        sigma_scale: f64,
        /// Prior family of the population sds: log-normal (ln σ ~ N(ln of the half-normal's
        /// median, 1.5²), locally the scale-invariant prior, whose new-board prediction is
        /// about the classical prediction interval: the default, since boards do differ), or
        /// half-normal (more mass near σ = 0, wider new-board predictions from few boards).
        #[arg(long, value_enum, default_value = "log-normal")]
        sigma_prior: SigmaPriorArg,
        /// Refit with a board mechanism of the diagnosis's library: `temperature_stiffness`
        /// (the FR-4 moduli follow a sheet column, `--enrich-covariate`) or `added_mass` (a
        /// lumped mass per board at `--enrich-location`).
        #[arg(long, value_parser = mechanism_parser())]
        enrich: Option<hbmu::diagnose::library::Mechanism>,
        /// The numeric sheet column (measurements.parquet) of `--enrich temperature_stiffness`.
        #[arg(long, default_value = "temperature_c")]
        enrich_covariate: String,
        /// The point (x_m,y_m, metres from the board's corner) of `--enrich added_mass`.
        #[arg(long, value_delimiter = ',', value_name = "X_M,Y_M")]
        enrich_location: Option<Vec<f64>>,
        /// Boards left out of the updating (their modes and masses unused), to validate the
        /// new-board prediction on: `report` compares their measurements with it.
        #[arg(long, value_delimiter = ',', value_name = "BOARD,...")]
        hold_out: Vec<String>,
        /// Free-free measurements left out of the updating (their boards are updated from
        /// the others), to validate the own-board prediction out of sample: `report` compares
        /// them with their board's interval.
        #[arg(long, value_delimiter = ',', value_name = "MEASUREMENT,...")]
        hold_out_measurements: Vec<String>,
        /// The board population's coordinates: `per-mass` (with mass_scale updated, every
        /// modulus per unit mass scale, the combination free-free frequencies follow) or
        /// `natural` (every parameter as it is).
        #[arg(long, value_enum, default_value = "per-mass")]
        board_coordinates: BoardCoordinatesArg,
    },
    /// Step 2: joint contact stiffness per bolted measurement and its population, from the
    /// bolted modes, carrying every step-1 draw (the modular, "cut", posterior).
    Joints {
        #[command(flatten)]
        common: UpdateArgs,
        /// Step-1 output directory (boards.parquet).
        #[arg(long)]
        boards: PathBuf,
        /// Prior sd of the population mean of ln k_con around the board file's value.
        #[arg(long, default_value_t = 1.0)]
        prior_width: f64,
        /// Half-normal scale of the population sd of ln k_con.
        #[arg(long, default_value_t = 0.5)]
        sigma_scale: f64,
        /// Refit with a joint mechanism of the diagnosis's library added to the joint model
        /// (joint_rotation, joint_mass, fixture_compliance, joint_stiffness_per_joint).
        #[arg(long, value_parser = mechanism_parser())]
        enrich: Option<hbmu::diagnose::library::Mechanism>,
        /// The joint (1-based, hole order of the board file) of
        /// `--enrich joint_stiffness_per_joint`; without it, every joint gets its own
        /// stiffness ratio in every measurement.
        #[arg(long)]
        enrich_joint: Option<usize>,
        /// With `--enrich`: the bolted measurements (comma-separated ids) that get the
        /// enrichment's own coordinates, e.g. the assemblies the diagnosis found apart from
        /// their board's others; the rest keep the baseline's joint. Default: every one.
        #[arg(long, value_delimiter = ',')]
        enrich_units: Vec<String>,
        /// With `--enrich`: modes the enriched model carries and the baseline lacks (a
        /// fixture's own mode) join the updating where the campaign identified them but
        /// pair left them unpaired (MAC ≥ 0.9 with the enriched model's mode at the fitted
        /// centre, frequency within 5 %, in at least half of the bolted measurements).
        #[arg(long)]
        enrich_new_modes: bool,
    },
}

impl UpdateArgs {
    fn options(
        self,
        params: Vec<String>,
        prior_width: f64,
        sigma_scale: f64,
    ) -> stage::update::UpdateOptions {
        use hbmu::bayes::target::ErrorPrior;
        stage::update::UpdateOptions {
            ingest_dir: self.ingest_dir,
            pair_dir: self.pair_dir,
            extract_dir: self.extract,
            board: self.model,
            out: self.out,
            force: self.force,
            cache: hbmu::io::cache::Cache::from_env(),
            sampler: hbmu::update::sampler::SamplerParams {
                seed: self.seed,
                runs: self.runs.max(1),
                smc: hbmu::bayes::smc::SmcOptions {
                    n_particles: self.particles.max(2),
                    target_ess: self.target_ess,
                    ..Default::default()
                },
                // In all, over the runs: the residuals' predictive mean then carries a Monte
                // Carlo error of at most 1/√500 ≈ 4.5 % of the posterior sd, far below the
                // predictive sd (which adds ε). Each draw is a full ROM solve per unit.
                residual_draws: 500,
                from_prior: self.from_prior,
                surrogate: !self.no_surrogate,
                subspace: !self.no_subspace,
            },
            model: hbmu::update::problem::ModelSpec {
                modes: self.modes,
                params,
                prior_width,
                sigma_scale,
                sigma_prior: Default::default(),
                lkj_eta: self.lkj_eta,
                eps: match self.eps_fixed {
                    Some(v) => ErrorPrior::Fixed { value: v },
                    None => ErrorPrior::Inferred {
                        median: self.eps_median,
                        log_sd: 1.5,
                    },
                },
                delta: if self.no_shapes {
                    None
                } else {
                    Some(match self.delta_fixed {
                        Some(v) => ErrorPrior::Fixed { value: v },
                        None => ErrorPrior::Inferred {
                            median: self.delta_median,
                            log_sd: 1.5,
                        },
                    })
                },
                rom_box: hbmu::update::problem::ModelSpec::DEFAULT_ROM_BOX,
                box_tolerance: 0.01,
                rom_max_basis: self.rom_basis,
                g_z_log_box: None,
                enrich: None,
                enrich_joint: None,
                enrich_units: vec![],
                enrich_covariate: None,
                enrich_location: None,
                enrich_new_modes: false,
                model_error: !self.no_model_error,
                discrepancy_freq: self.discrepancy_pct.map(|p| p / 100.0),
                hold_out_boards: vec![],
                hold_out_measurements: vec![],
                board_coordinates: Default::default(),
                balance_bias_rel: self
                    .balance_bias
                    .unwrap_or(hbmu::update::problem::ModelSpec::DEFAULT_BALANCE_BIAS_REL),
                shape_weights: self.shape_weights,
            },
        }
    }
}

#[derive(Subcommand)]
enum LabCommand {
    /// Write a campaign directory in exactly the input contract, and the truth behind it
    /// (parameters, drawn quantities, the concealed effect and its expected diagnosis) in a
    /// separate JSON file.
    Simulate {
        /// Scenario file (TOML, schemas/lab_scenario.schema.json) or a built-in name:
        /// paper (default campaign), null, rotational, loose_bolt, temperature, lumped_mass,
        /// fixture, underfill (a local stiffening, outside the diagnosis's library). A file's
        /// `preset = "realistic"` (or its `[habits]`) adds the habits of a real lab.
        scenario: String,
        /// Campaign directory to write.
        #[arg(long)]
        out: PathBuf,
        /// Truth file to write (must lie outside the campaign directory).
        #[arg(long)]
        truth: PathBuf,
        /// Seed (default: the scenario's).
        #[arg(long)]
        seed: Option<u64>,
        /// Board description (default: the built-in board).
        #[arg(long)]
        board: Option<PathBuf>,
        #[arg(long)]
        force: bool,
    },
}

#[derive(Subcommand)]
enum FeCommand {
    /// Modes of the full FE model, one row per mode with the shape at the board's scan grid
    /// (or at a measurement's scan points), as Parquet.
    Modes {
        #[command(flatten)]
        model: ModelArgs,
        /// Number of elastic modes.
        #[arg(long, default_value_t = 10)]
        n_modes: usize,
        /// Discretization tolerance: without --mesh, the coarsest mesh whose estimated
        /// relative error (Richardson) of the first 8 frequencies is below it is chosen;
        /// with --mesh, a warning when the estimate exceeds it.
        #[arg(long, default_value_t = hbmu::fem::convergence::DEFAULT_MESH_TOL)]
        mesh_tol: f64,
        /// Report shapes at the scan points of this measurement (needs --ingest).
        #[arg(long, requires = "ingest")]
        measurement: Option<String>,
        /// Ingest output directory holding scan_points.parquet.
        #[arg(long, requires = "measurement")]
        ingest: Option<PathBuf>,
        #[arg(long)]
        out: PathBuf,
    },
    /// Build the parametric reduced-order model over a parameter box and write it as NPZ
    /// (numpy-readable; format documented in src/fem/npz.rs and src/fem/rom.rs).
    Rom {
        #[command(flatten)]
        model: ModelArgs,
        /// Modes the ROM must reproduce.
        #[arg(long, default_value_t = 8)]
        n_modes: usize,
        /// Half-width of the parameter box, relative (0.2 = ±20 %).
        #[arg(long, default_value_t = 0.2)]
        box_rel: f64,
        /// Seed of the snapshot design.
        #[arg(long, default_value_t = 20_240_613)]
        seed: u64,
        #[arg(long)]
        out: PathBuf,
    },
    /// The %/% table of analytic frequency sensitivities (the paper's Table 1) as Parquet.
    Sensitivity {
        #[command(flatten)]
        model: ModelArgs,
        #[arg(long, default_value_t = 8)]
        n_modes: usize,
        #[arg(long)]
        out: PathBuf,
    },
}

fn report(what: &str, out: &std::path::Path, outcome: &stage::StageOutcome) -> i32 {
    if outcome.up_to_date {
        eprintln!("{what}: up to date ({}), nothing to do", out.display());
    }
    outcome.exit_code()
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
        Command::Fe { command } => run_fe(command),
        Command::Extract {
            ingest_dir,
            out,
            band,
            max_order,
            no_plots,
            force,
        } => {
            let mut params = hbmu::modal::ExtractParams::default();
            if let Some(b) = band {
                params.band_hz = Some((b[0], b[1]));
            }
            if let Some(m) = max_order {
                params.lscf.max_order = m;
            }
            let opts = stage::extract::ExtractOptions {
                ingest_dir,
                out,
                force,
                params,
                plots: !no_plots,
            };
            let o = stage::extract::run(&opts, cli.verbose)?;
            Ok(report("extract", &opts.out, &o))
        }
        Command::Pair {
            extract_dir,
            model,
            out,
            mac_min,
            min_fraction,
            n_model_modes,
            no_plots,
            force,
        } => {
            let opts = stage::pair::PairOptions {
                extract_dir,
                board: model,
                out,
                force,
                params: hbmu::modal::pair::PairParams {
                    mac_min,
                    ..Default::default()
                },
                n_model_modes,
                min_fraction,
                plots: !no_plots,
            };
            let o = stage::pair::run(&opts, cli.verbose)?;
            Ok(report("pair", &opts.out, &o))
        }
        Command::Lab {
            command:
                LabCommand::Simulate {
                    scenario,
                    out,
                    truth,
                    seed,
                    board,
                    force,
                },
        } => {
            let opts = stage::lab::SimulateOptions {
                scenario,
                board,
                out,
                truth,
                seed,
                force,
            };
            let o = stage::lab::run(&opts)?;
            Ok(report("lab simulate", &opts.out, &o))
        }
        Command::Update { command } => run_update(command, cli.verbose),
        Command::Diagnose {
            work_dir,
            out,
            model,
            max_refits,
            only,
            practical_threshold_pct,
            force,
        } => {
            let mut select = hbmu::diagnose::select::SelectOptions::default();
            if let Some(p) = practical_threshold_pct {
                if !(p.is_finite() && p >= 0.0) {
                    anyhow::bail!(
                        "--practical-threshold-pct: expected a percentage ≥ 0, found {p}"
                    );
                }
                select.practical_threshold_rel = p / 100.0;
            }
            let opts = stage::diagnose::DiagnoseOptions {
                work_dir,
                out,
                board: model,
                force,
                only,
                locate: Default::default(),
                select,
                max_refits,
            };
            // None: `--only` on a candidate its screen does not refit (printed there).
            Ok(match stage::diagnose::run(&opts, cli.verbose)? {
                Some(o) => report("diagnose", &opts.out, &o),
                None => 0,
            })
        }
        Command::Propagate {
            update_dirs,
            out,
            draws,
            seed,
            pair,
            fe,
            rom_box,
            force,
        } => {
            let opts = stage::propagate::PropagateOptions {
                update_dirs,
                pair_dir: pair,
                fe_dir: fe,
                out,
                force,
                draws,
                seed,
                rom_box,
            };
            let o = stage::propagate::run(&opts, cli.verbose)?;
            Ok(report("propagate", &opts.out, &o))
        }
        Command::Report {
            work_dir,
            out,
            force,
        } => {
            let opts = stage::report::ReportOptions {
                work_dir,
                out,
                force,
            };
            let o = stage::report::run(&opts, cli.verbose)?;
            if o.exit_code() == exit::OK || o.exit_code() == exit::QUARANTINED {
                println!("{}", opts.out.join(stage::report::HTML).display());
            }
            Ok(report("report", &opts.out, &o))
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

/// The command line's spellings of the kernels' choices (the kernels know no clap).
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum SigmaPriorArg {
    HalfNormal,
    LogNormal,
}

impl From<SigmaPriorArg> for hbmu::bayes::population::SigmaPrior {
    fn from(a: SigmaPriorArg) -> Self {
        match a {
            SigmaPriorArg::HalfNormal => Self::HalfNormal,
            SigmaPriorArg::LogNormal => Self::LogNormal,
        }
    }
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum BoardCoordinatesArg {
    PerMass,
    Natural,
}

impl From<BoardCoordinatesArg> for hbmu::update::problem::BoardCoordinates {
    fn from(a: BoardCoordinatesArg) -> Self {
        match a {
            BoardCoordinatesArg::PerMass => Self::PerMass,
            BoardCoordinatesArg::Natural => Self::Natural,
        }
    }
}

/// `--enrich`: a mechanism of the diagnosis's library by its id (`joint_rotation`, …).
fn mechanism_parser(
) -> impl clap::builder::TypedValueParser<Value = hbmu::diagnose::library::Mechanism> {
    use clap::builder::TypedValueParser;
    use hbmu::diagnose::library::Mechanism;
    clap::builder::PossibleValuesParser::new(Mechanism::ALL.map(Mechanism::id))
        .map(|id: String| Mechanism::from_id(&id).expect("a listed mechanism id"))
}

/// `hbmu fe …`.
fn run_fe(command: FeCommand) -> anyhow::Result<i32> {
    match command {
        FeCommand::Modes {
            model,
            n_modes,
            mesh_tol,
            measurement,
            ingest,
            out,
        } => {
            let from = match (ingest, measurement) {
                (Some(ingest_dir), Some(measurement_id)) => Some(stage::fe::PointsFrom {
                    ingest_dir,
                    measurement_id,
                }),
                _ => None,
            };
            if !(mesh_tol > 0.0 && mesh_tol < 1.0) {
                anyhow::bail!("--mesh-tol: expected a relative error in (0, 1), found {mesh_tol}");
            }
            let o = stage::fe::run_modes(
                &model.options(),
                n_modes,
                mesh_tol,
                from.as_ref(),
                &out,
                model.force,
            )?;
            Ok(report("fe modes", &out, &o))
        }
        FeCommand::Rom {
            model,
            n_modes,
            box_rel,
            seed,
            out,
        } => {
            let ro = hbmu::fem::RomOptions {
                n_modes,
                box_rel,
                seed,
                ..Default::default()
            };
            let o = stage::fe::run_rom(&model.options(), &ro, &out, model.force)?;
            Ok(report("fe rom", &out, &o))
        }
        FeCommand::Sensitivity {
            model,
            n_modes,
            out,
        } => {
            let o = stage::fe::run_sensitivity(&model.options(), n_modes, &out, model.force)?;
            Ok(report("fe sensitivity", &out, &o))
        }
    }
}

/// `hbmu update boards|joints …`.
fn run_update(command: UpdateCommand, verbose: bool) -> anyhow::Result<i32> {
    match command {
        UpdateCommand::Boards {
            common,
            params,
            prior_width,
            sigma_scale,
            sigma_prior,
            enrich,
            enrich_covariate,
            enrich_location,
            hold_out,
            hold_out_measurements,
            board_coordinates,
        } => {
            use hbmu::diagnose::library::Mechanism;
            // Empty: the stage chooses the default for the board it loads.
            let mut opts = common.options(params.unwrap_or_default(), prior_width, sigma_scale);
            opts.model.sigma_prior = sigma_prior.into();
            opts.model.enrich = enrich;
            opts.model.hold_out_boards = hold_out;
            opts.model.hold_out_measurements = hold_out_measurements;
            opts.model.board_coordinates = board_coordinates.into();
            if enrich == Some(Mechanism::TemperatureStiffness) {
                opts.model.enrich_covariate = Some(enrich_covariate);
            }
            opts.model.enrich_location = match enrich_location.as_deref() {
                None => None,
                Some([x, y]) => Some([*x, *y]),
                Some(v) => anyhow::bail!(
                    "--enrich-location: expected two numbers X_M,Y_M, found {}",
                    v.len()
                ),
            };
            let o = stage::update::run_boards(&opts, verbose)?;
            Ok(report("update boards", &opts.out, &o))
        }
        UpdateCommand::Joints {
            common,
            boards,
            prior_width,
            sigma_scale,
            enrich,
            enrich_joint,
            enrich_units,
            enrich_new_modes,
        } => {
            // Step 2 has neither a balance term nor a model-error term: say so rather than
            // ignore the step-1 options.
            for (given, flag) in [
                (common.balance_bias.is_some(), "--balance-bias"),
                (common.no_model_error, "--no-model-error"),
            ] {
                if given {
                    anyhow::bail!("update joints: {flag} is an option of update boards (step 1); step 2 has no balance term and no model-error term");
                }
            }
            let mut opts = common.options(vec![], prior_width, sigma_scale);
            opts.model.enrich = enrich;
            opts.model.enrich_joint = enrich_joint;
            opts.model.enrich_units = enrich_units;
            opts.model.enrich_new_modes = enrich_new_modes;
            // Step 2 has no model-error term (its manifest must not claim one).
            opts.model.model_error = false;
            let o = stage::update::run_joints(&opts, &boards, verbose)?;
            Ok(report("update joints", &opts.out, &o))
        }
    }
}

//! Stage `fe`: the physics core from the command line — `fe modes` (full-model modes with
//! shapes at a point set, as Parquet), `fe rom` (the parametric reduced-order model as an NPZ
//! artifact), `fe sensitivity` (the `%/%` table of analytic frequency derivatives).
//!
//! Each subcommand is a hashed stage like any other: its inputs are the board file (or the
//! compiled-in default board, whose text enters the configuration hash) and, for `modes`, the
//! ingest table holding a measurement's scan points; its configuration is every option.

use crate::fem::{self, Board, FeModel, JointModel, Params};
use crate::io::cache::{Cache, Fetch};
use crate::io::manifest::{Prepared, StageSpec};
use crate::io::tables::fe as fe_tables;
use crate::stage::{exit, StageOutcome, StageResult};
use anyhow::{anyhow, Context};
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Which boundary conditions.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum SetupArg {
    Free,
    Bolted,
}

impl SetupArg {
    pub fn as_str(self) -> &'static str {
        match self {
            SetupArg::Free => "free",
            SetupArg::Bolted => "bolted",
        }
    }
    pub fn to_setup(self) -> fem::Setup {
        match self {
            SetupArg::Free => fem::Setup::Free,
            SetupArg::Bolted => fem::Setup::Bolted(JointModel::baseline()),
        }
    }
}

/// Options shared by the `fe` subcommands.
#[derive(Debug, Clone, Serialize)]
pub struct ModelOptions {
    /// Board description (TOML); `None` = the compiled-in default board.
    pub board: Option<PathBuf>,
    pub setup: SetupArg,
    /// `NAME=VALUE` parameter overrides (names as in `fe sensitivity`, units in the names).
    pub set: Vec<String>,
    /// Mesh override `(nx, ny)`; `None` = the board file's mesh.
    pub mesh: Option<(usize, usize)>,
}

/// The board, its text's hash (for the configuration), and the input files.
fn load_board(path: Option<&Path>) -> anyhow::Result<(Board, String, Vec<PathBuf>)> {
    match path {
        Some(p) => {
            // The board and its density maps; all of them are inputs (fingerprinted).
            let (b, files) = crate::io::board_files::read_board(p)?;
            let text = std::fs::read(p)
                .with_context(|| format!("cannot read board file {}", p.display()))?;
            Ok((b, blake3::hash(&text).to_hex().to_string(), files))
        }
        None => Ok((
            Board::default_board(),
            blake3::hash(fem::board::DEFAULT_BOARD_TOML.as_bytes())
                .to_hex()
                .to_string(),
            vec![],
        )),
    }
}

/// Build the model and the parameter point from the options.
pub fn build_model(board: &Board, opts: &ModelOptions) -> anyhow::Result<(FeModel, Params)> {
    let mut mesh = board.mesh_for(&opts.setup.to_setup()).clone();
    if let Some((nx, ny)) = opts.mesh {
        mesh.nx = nx;
        mesh.ny = ny;
    }
    let model = FeModel::build(board, opts.setup.to_setup(), &mesh)?;
    let mut p = model.nominal_params();
    for s in &opts.set {
        let (name, value) = s
            .split_once('=')
            .ok_or_else(|| anyhow!("--set {s:?}: expected NAME=VALUE, e.g. e_x_pa=25e9"))?;
        let v: f64 = value
            .trim()
            .parse()
            .map_err(|_| anyhow!("--set {s:?}: expected a number after '=', found {value:?}"))?;
        p.set(name.trim(), v).map_err(|e| {
            anyhow!(
                "--set {s:?}: {e} (known parameters: {})",
                model.map.names.join(", ")
            )
        })?;
    }
    Ok((model, p))
}

fn spec_for(
    stage: &str,
    opts: &ModelOptions,
    board_hash: &str,
    inputs: Vec<PathBuf>,
    extra_config: serde_json::Value,
    out: &Path,
    seed: Option<u64>,
) -> StageSpec {
    StageSpec {
        stage: stage.into(),
        inputs,
        // The board counts by content (callers name a base when an input's name matters).
        input_base: PathBuf::new(),
        config: serde_json::json!({
            "model": fingerprinted_model_options(opts),
            "board_blake3": board_hash,
            "stage": extra_config,
        }),
        seed,
        manifest_path: crate::io::manifest::manifest_path_for(out),
    }
}

/// The model options as the configuration sees them: without the board's path, which enters
/// by its content (`board_blake3`), so that moving the file or the work directory changes no
/// fingerprint.
fn fingerprinted_model_options(opts: &ModelOptions) -> serde_json::Value {
    let mut v = serde_json::to_value(opts).expect("ModelOptions serialises");
    if let Some(m) = v.as_object_mut() {
        m.remove("board");
    }
    v
}

/// Where `fe modes` reports the shapes: the board's scan grid, or a measurement's points.
#[derive(Debug, Clone, Serialize)]
pub struct PointsFrom {
    /// An ingest output directory (its `scan_points.parquet` is read).
    pub ingest_dir: PathBuf,
    pub measurement_id: String,
}

/// The cache key of an `fe` artifact: stage, tool version, seed and the configuration, which
/// holds the board's content hash and every option, but no path (the board given as a file or
/// as the built-in default with the same text is one artifact).
fn cache_key(prep: &Prepared) -> String {
    let mut h = blake3::Hasher::new();
    h.update(b"hbmu-cache-v1\0");
    h.update(prep.spec.stage.as_bytes());
    h.update(b"\0");
    h.update(crate::io::manifest::TOOL_VERSION.as_bytes());
    h.update(b"\0");
    h.update(fem::MODEL_REVISION.as_bytes());
    h.update(b"\0");
    h.update(prep.config_blake3.as_bytes());
    h.update(b"\0");
    h.update(format!("{:?}", prep.spec.seed).as_bytes());
    h.finalize().to_hex().to_string()
}

/// Produce a single-file artifact at `out` through the shared cache when `HBMU_CACHE` is set:
/// the cached copy when there is one under `key` ([`cache_key`]), else `build` writes `out`
/// and the bytes are published to the cache. Says on stderr which it was.
fn through_cache(
    kind: &str,
    key: &str,
    ext: &str,
    out: &Path,
    build: impl FnOnce(&Path) -> anyhow::Result<()>,
) -> anyhow::Result<()> {
    let Some(cache) = Cache::from_env() else {
        return build(out);
    };
    let (p, how) = cache
        .fetch_or_build(kind, key, ext, || {
            build(out).map_err(std::io::Error::other)?;
            std::fs::read(out)
        })
        .with_context(|| format!("model cache {}", cache.path(kind, key, ext).display()))?;
    match how {
        Fetch::Hit => {
            let bytes =
                std::fs::read(&p).with_context(|| format!("reading cached {}", p.display()))?;
            crate::io::atomic::write_bytes(out, &bytes)
                .with_context(|| format!("writing {}", out.display()))?;
            eprintln!("{kind}: from the cache ({})", p.display());
        }
        Fetch::Built => eprintln!("{kind}: built, published to the cache ({})", p.display()),
    }
    Ok(())
}

/// `hbmu fe modes`.
pub fn run_modes(
    opts: &ModelOptions,
    n_modes: usize,
    mesh_tol: f64,
    points_from: Option<&PointsFrom>,
    out: &Path,
    force: bool,
) -> anyhow::Result<StageOutcome> {
    let (board, board_hash, board_inputs) = load_board(opts.board.as_deref())?;
    let mut inputs = board_inputs;
    if let Some(f) = points_from {
        inputs.push(f.ingest_dir.join("scan_points.parquet"));
    }
    let spec = spec_for(
        "fe-modes",
        opts,
        &board_hash,
        inputs,
        serde_json::json!({
            "n_modes": n_modes,
            "mesh_tol": mesh_tol,
            "points_from_measurement": points_from.map(|f| &f.measurement_id),
        }),
        out,
        None,
    );
    // scan_points.parquet by its name in the ingest directory.
    let spec = StageSpec {
        input_base: points_from
            .map(|f| f.ingest_dir.clone())
            .unwrap_or_default(),
        ..spec
    };
    crate::stage::run(spec, force, |prep| {
        // The mesh: the user's (`--mesh`), checked by Richardson from it and one twice
        // as fine on the first (up to) 8 modes with a warning above the tolerance; or,
        // by default, the coarsest mesh of the board mesh's ladder whose estimate is
        // below the tolerance (`fem::convergence::choose_mesh`).
        let (model0, p) = build_model(&board, opts)?;
        let n_check = n_modes.min(8);
        let (model, check, choice) = match opts.mesh {
            Some(_) => {
                let mesh = fem::MeshOptions {
                    nx: model0.mesh.nx,
                    ny: model0.mesh.ny,
                };
                // The check solves a mesh twice as fine: beyond the choice's limit it is
                // skipped (said on stderr, `null` in the metadata) rather than exhaust memory.
                let check = if 4 * mesh.nx * mesh.ny > fem::convergence::MAX_CHOICE_ELEMENTS {
                    eprintln!(
                        "note: mesh {}x{} not checked: the check's mesh {}x{} exceeds {} elements",
                        mesh.nx,
                        mesh.ny,
                        2 * mesh.nx,
                        2 * mesh.ny,
                        fem::convergence::MAX_CHOICE_ELEMENTS
                    );
                    None
                } else {
                    Some(fem::convergence::mesh_check(
                        &board,
                        &model0.setup,
                        &mesh,
                        &p,
                        n_check,
                    )?)
                };
                (model0, check, None)
            }
            None => {
                let choice = fem::convergence::choose_mesh(
                    &board,
                    &model0.setup,
                    &p,
                    n_check,
                    mesh_tol,
                    fem::convergence::MAX_CHOICE_ELEMENTS,
                )?;
                if !choice.met {
                    eprintln!(
                        "warning: no mesh up to {} elements meets the discretization tolerance {:.3} %; using {}x{} (estimate {:.3} %)",
                        fem::convergence::MAX_CHOICE_ELEMENTS,
                        100.0 * mesh_tol,
                        choice.chosen.mesh[0],
                        choice.chosen.mesh[1],
                        100.0 * choice.chosen.max_rel_error
                    );
                }
                let o = ModelOptions {
                    mesh: Some((choice.chosen.mesh[0], choice.chosen.mesh[1])),
                    ..opts.clone()
                };
                let (model, _) = build_model(&board, &o)?;
                (model, Some(choice.chosen.clone()), Some(choice))
            }
        };
        let (nodes, pts) = fe_tables::report_points(
            &model.board,
            points_from.map(|f| (f.ingest_dir.as_path(), f.measurement_id.as_str())),
        )?;
        let modes = model.modes(&p, n_modes)?;
        let w = model.w_at(&modes, &pts)?;
        let coarse = check
            .as_ref()
            .filter(|c| choice.is_none() && c.max_rel_error > mesh_tol);
        if let Some(check) = coarse {
            eprintln!(
                "warning: mesh {}x{} is coarser than needed: estimated discretization error of the first {} frequencies up to {:.3} % (tolerance {:.3} %; Richardson with {}x{}); pass a finer --mesh, or none to have it chosen",
                check.mesh[0],
                check.mesh[1],
                check.rel_error.len(),
                100.0 * check.max_rel_error,
                100.0 * mesh_tol,
                check.finer_mesh[0],
                check.finer_mesh[1]
            );
        }
        let mut prov = fe_tables::provenance("fe-modes", &prep.fingerprint, &model.board);
        prov.insert(
            "hbmu.fe.discretization".to_string(),
            serde_json::to_string(&check)?,
        );
        prov.insert(
            "hbmu.fe.mesh".to_string(),
            serde_json::to_string(&serde_json::json!({
                "nx": model.mesh.nx,
                "ny": model.mesh.ny,
                "how": if choice.is_some() { "chosen" } else { "given" },
                "tolerance": mesh_tol,
                "choice": choice,
            }))?,
        );
        fe_tables::write_modes(
            out,
            &prov,
            opts.setup.as_str(),
            &modes.freq_hz,
            &nodes,
            &pts,
            &w,
        )?;
        let mut summary = BTreeMap::new();
        summary.insert("freq_hz".into(), serde_json::to_value(&modes.freq_hz)?);
        summary.insert("n_rigid_dropped".into(), modes.n_rigid_dropped.into());
        summary.insert("n_dof".into(), model.n_dof.into());
        summary.insert(
            "mesh".into(),
            serde_json::json!([model.mesh.nx, model.mesh.ny]),
        );
        summary.insert(
            "discretization_rel_error".into(),
            serde_json::to_value(check.as_ref().map(|c| &c.rel_error))?,
        );
        Ok(StageResult {
            outputs: vec![out.to_path_buf()],
            exit_code: exit::OK,
            summary,
        })
    })
}

/// `hbmu fe rom`.
pub fn run_rom(
    opts: &ModelOptions,
    rom_opts: &fem::RomOptions,
    out: &Path,
    force: bool,
) -> anyhow::Result<StageOutcome> {
    let (board, board_hash, board_inputs) = load_board(opts.board.as_deref())?;
    let spec = spec_for(
        "fe-rom",
        opts,
        &board_hash,
        board_inputs,
        serde_json::to_value(rom_opts)?,
        out,
        Some(rom_opts.seed),
    );
    crate::stage::run(spec, force, |prep| {
        through_cache("fe-rom", &cache_key(prep), "npz", out, |out| {
            let (model, _) = build_model(&board, opts)?;
            // The model's own logarithmic axes (a shear-deformable board's G_z) and the basis
            // they need, as the updating's ROM has them: the propagation checks its draws
            // against this box.
            let log_axes = fem::rom::with_own_log_axes(&model.map, &rom_opts.log_axes);
            let ro = fem::RomOptions {
                max_basis: fem::rom::basis_cap(rom_opts.max_basis, log_axes.len()),
                log_axes,
                ..rom_opts.clone()
            };
            let rom = fem::Rom::build(&model, &ro)?;
            crate::io::atomic::write_bytes(out, &rom.to_npz_bytes())
                .with_context(|| format!("writing {}", out.display()))
        })?;
        let mut summary = BTreeMap::new();
        summary.insert("setup".into(), opts.setup.as_str().into());
        Ok(StageResult {
            outputs: vec![out.to_path_buf()],
            exit_code: exit::OK,
            summary,
        })
    })
}

/// `hbmu fe sensitivity`.
pub fn run_sensitivity(
    opts: &ModelOptions,
    n_modes: usize,
    out: &Path,
    force: bool,
) -> anyhow::Result<StageOutcome> {
    let (board, board_hash, board_inputs) = load_board(opts.board.as_deref())?;
    let spec = spec_for(
        "fe-sensitivity",
        opts,
        &board_hash,
        board_inputs,
        serde_json::json!({"n_modes": n_modes}),
        out,
        None,
    );
    crate::stage::run(spec, force, |prep| {
        // The table's `hbmu.fingerprint` is the cache key, so that a cached copy carries the
        // same provenance whichever campaign built it.
        let key = cache_key(prep);
        through_cache("fe-sensitivity", &key, "parquet", out, |out| {
            write_sensitivity(&board, opts, n_modes, &key, out)
        })?;
        Ok(StageResult {
            outputs: vec![out.to_path_buf()],
            exit_code: exit::OK,
            summary: BTreeMap::new(),
        })
    })
}

/// The sensitivity table of the model at its parameter point, written to `out`.
fn write_sensitivity(
    board: &Board,
    opts: &ModelOptions,
    n_modes: usize,
    fingerprint: &str,
    out: &Path,
) -> anyhow::Result<()> {
    let (model, p) = build_model(board, opts)?;
    let modes = model.modes(&p, n_modes)?;
    let d = fem::sensitivity::eigen_derivatives(&model, &p, &modes, false)?;
    let prov = fe_tables::provenance("fe-sensitivity", fingerprint, &model.board);
    fe_tables::write_sensitivity(
        out,
        &prov,
        opts.setup.as_str(),
        &p,
        &modes.freq_hz,
        &d.d_freq_hz,
    )
}

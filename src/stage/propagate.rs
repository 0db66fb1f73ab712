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
use crate::io::tables::{self, c, Col, Cols, TableSpec};
use crate::stage::{exit, StageOutcome, StageResult};
use crate::uq::propagate::{
    self as uq, LabelModel, Models, Posterior, Step1Particle, Step2Particle,
};
use anyhow::{anyhow, bail, Context};
use arrow::array::{Array, ArrayRef, BooleanArray, Float64Array, Int32Array, StringArray};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::Arc;

pub const MANIFEST: &str = "propagate.manifest.json";

pub const PREDICTIONS: TableSpec = TableSpec {
    name: "predictions",
    doc: "Monte Carlo predictions of eigenfrequencies from the updated posterior, one row per draw, scope, board, setup and mode label. scope `new_board`: a board not yet measured (parameters drawn from the population, bolted with a new joint); `board`: a measured board (its posterior draw; bolted: with a new joint drawn from the joint population). freq_hz is the model's frequency; freq_obs_hz a predicted measurement of it (step 1's model-error term drawn where the data have not fixed it: every label of a new board and a measured board's validation labels; then the label's relative eigenvalue error added; a validation mode draws its error from the updated modes' log-normal, or takes its own measurement repeatability where that is larger, see eps_pooled). Evaluations at inadmissible parameters or where a label cannot be tracked give no row (counted in propagate_report.json).",
    open: false,
    columns: &[
        c("draw", Col::Int32, false, "", "Propagation draw (each draw has its own random stream of the seed)."),
        c("scope", Col::Utf8, false, "", "`new_board` or `board`."),
        c("board_id", Col::Utf8, true, "", "Board for scope `board`; null for a new board."),
        c("setup", Col::Utf8, false, "", "`free` or `bolted`."),
        c("label", Col::Utf8, false, "", "Mode label (from pair)."),
        c("freq_hz", Col::Float64, false, "Hz", "Model eigenfrequency at the drawn parameters."),
        c("freq_obs_hz", Col::Float64, false, "Hz", "Predicted measurement: eigenvalue λ (1 + d)(1 + ε z), z ~ N(0,1), d the model-form discrepancy (discrepancy_rel)."),
        c("eps_pooled", Col::Bool, false, "", "True when the label was not updated: its ε is drawn per row from the log-normal fitted to ln ε of the setup's updated labels at that particle, or (free-free) is its measurement repeatability when that is larger (2 × the pooled within-board sd of its relative frequency residuals in the step-1 residuals; the info finding propagate.validation_repeatability lists the values)."),
        c("discrepancy_rel", Col::Float64, false, "", "The model-form discrepancy in freq_obs_hz, relative to the frequency (√(1 + d) − 1): the step's posterior draw d of the label (common to every board), or for a label the step did not update a draw from N(0, τ²) at the draw's scale τ; 0 where the step ran without a discrepancy."),
    ],
};

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

/// Where the inputs are.
struct Inputs {
    step1: PathBuf,
    step2: Option<PathBuf>,
    pairs: PathBuf,
    rom_free: PathBuf,
    rom_bolted: PathBuf,
}

fn classify(opts: &PropagateOptions) -> anyhow::Result<Inputs> {
    let mut step1 = None;
    let mut step2 = None;
    for d in &opts.update_dirs {
        if d.join("joints.parquet").is_file() {
            if step2.replace(d.clone()).is_some() {
                bail!("more than one step-2 (update joints) directory given; expected at most one");
            }
        } else if d.join("boards.parquet").is_file() {
            if step1.replace(d.clone()).is_some() {
                bail!("more than one step-1 (update boards) directory given; expected one");
            }
        } else {
            bail!(
                "{}: expected the output of `hbmu update boards` (boards.parquet) or `hbmu update joints` (joints.parquet), found neither",
                d.display()
            );
        }
    }
    let step1 = step1.ok_or_else(|| {
        anyhow!("no step-1 directory (with boards.parquet) among the inputs; propagation needs the boards' posterior")
    })?;
    let sibling = |name: &str| {
        step1
            .parent()
            .map(|p| p.join(name))
            .unwrap_or_else(|| PathBuf::from(name))
    };
    let fe = opts.fe_dir.clone().unwrap_or_else(|| sibling("fe"));
    let pair = opts.pair_dir.clone().unwrap_or_else(|| sibling("pair"));
    // The ROM an update step ran with (it writes it as rom.npz: step 2's is re-centred on
    // the joint stiffness the bolted modes imply), else fe's.
    let own = |dir: Option<&PathBuf>, fallback: PathBuf| -> PathBuf {
        match dir.map(|d| d.join("rom.npz")) {
            Some(p) if p.is_file() => p,
            _ => fallback,
        }
    };
    Ok(Inputs {
        pairs: pair.join("pairs.parquet"),
        rom_free: own(Some(&step1), fe.join("rom_free.npz")),
        rom_bolted: own(step2.as_ref(), fe.join("rom_bolted.npz")),
        step1,
        step2,
    })
}

/// Labels of a setup's accepted pairs with their most frequent model mode (0-based), in model
/// order; labels whose mode lies beyond the ROM are reported and left out.
fn labels_of(
    pairs: &Path,
    setup: &str,
    rom: &Rom,
    findings: &mut Findings,
) -> anyhow::Result<(Vec<String>, Vec<usize>)> {
    let mut by: BTreeMap<String, BTreeMap<i32, usize>> = BTreeMap::new();
    for b in tables::read_parquet(pairs)? {
        let c = Cols {
            batch: &b,
            path: pairs,
        };
        let (s, l, mm, acc) = (
            c.str("setup")?,
            c.str("label")?,
            c.i32("model_mode")?,
            c.bool("accepted")?,
        );
        for i in 0..b.num_rows() {
            if s.value(i) != setup || !acc.value(i) || mm.is_null(i) || l.is_null(i) {
                continue;
            }
            *by.entry(l.value(i).to_string())
                .or_default()
                .entry(mm.value(i))
                .or_default() += 1;
        }
    }
    let mut v = vec![];
    for (l, counts) in by {
        let Some((mm, _)) = counts.into_iter().max_by_key(|(m, n)| (*n, -*m)) else {
            continue;
        };
        if mm < 1 || mm as usize > rom.n_modes {
            findings.push(Finding::new(
                Severity::Warning,
                "propagate.label_beyond_rom",
                format!("{setup} mode {l:?} pairs with model mode {mm}, beyond the ROM's {} modes; not predicted (build the ROM with more modes: `hbmu fe rom --n-modes`)", rom.n_modes),
            ));
            continue;
        }
        v.push(((mm - 1) as usize, l));
    }
    v.sort();
    Ok((
        v.iter().map(|(_, l)| l.clone()).collect(),
        v.iter().map(|(m, _)| *m).collect(),
    ))
}

/// Labels used for updating in a step (from its residuals).
fn updated_labels(residuals: &Path) -> anyhow::Result<BTreeSet<String>> {
    let mut out = BTreeSet::new();
    for b in tables::read_parquet(residuals)? {
        let c = Cols {
            batch: &b,
            path: residuals,
        };
        let (l, u) = (c.str("label")?, c.bool("used_for_updating")?);
        for i in 0..b.num_rows() {
            if u.value(i) {
                out.insert(l.value(i).to_string());
            }
        }
    }
    Ok(out)
}

/// A fixed ε from a step's manifest config (`--eps-fixed`), if any.
fn fixed_eps(manifest: &Path) -> Option<f64> {
    let m = crate::io::manifest::read_manifest(manifest)?;
    m.config.get("eps")?.get("Fixed")?.get("value")?.as_f64()
}

fn f64_col<'a>(
    b: &'a arrow::array::RecordBatch,
    name: &str,
    path: &'a Path,
) -> anyhow::Result<&'a Float64Array> {
    Ok(Cols { batch: b, path }.f64(name)?)
}

/// ε per label of a population table row set: the label's `eps_<label>` column when the
/// label was updated, else the fixed value, else none.
fn eps_columns(
    b: &arrow::array::RecordBatch,
    labels: &[String],
    updated: &BTreeSet<String>,
) -> Vec<Option<String>> {
    labels
        .iter()
        .map(|l| {
            let name = format!("eps_{l}");
            (updated.contains(l) && b.column_by_name(&name).is_some()).then_some(name)
        })
        .collect()
}

/// The model-form discrepancy columns of a population table (`discrepancy_scale`,
/// `discrepancy_<label>` of the updated labels); both `None` where the step ran without one.
struct DiscrepancyCols<'a> {
    scale: Option<&'a Float64Array>,
    unit_scale: Option<&'a Float64Array>,
    d: Vec<Option<&'a Float64Array>>,
}

impl<'a> DiscrepancyCols<'a> {
    fn read(
        b: &'a arrow::array::RecordBatch,
        labels: &[String],
        path: &'a Path,
    ) -> anyhow::Result<DiscrepancyCols<'a>> {
        if b.column_by_name("discrepancy_scale").is_none() {
            return Ok(DiscrepancyCols {
                scale: None,
                unit_scale: None,
                d: vec![None; labels.len()],
            });
        }
        Ok(DiscrepancyCols {
            scale: Some(f64_col(b, "discrepancy_scale", path)?),
            unit_scale: b
                .column_by_name("discrepancy_unit_scale")
                .is_some()
                .then(|| f64_col(b, "discrepancy_unit_scale", path))
                .transpose()?,
            d: labels
                .iter()
                .map(|l| {
                    let n = format!("discrepancy_{l}");
                    b.column_by_name(&n)
                        .is_some()
                        .then(|| f64_col(b, &n, path))
                        .transpose()
                })
                .collect::<Result<_, _>>()?,
        })
    }

    fn at(&self, r: usize) -> uq::Discrepancy {
        uq::Discrepancy {
            d: self.d.iter().map(|c| c.map(|a| a.value(r))).collect(),
            scale: self.scale.map(|a| a.value(r)),
            unit_scale: self.unit_scale.map(|a| a.value(r)),
        }
    }
}

/// Per free label not used for updating, the relative eigenvalue error its repeat
/// measurements show ([`crate::uq::propagate::repeatability_eps`], boards as groups), from
/// the step-1 residuals; `None` for updated labels and where there are too few repeats. The
/// values used are reported as an info finding.
fn repeatability(
    path: &Path,
    labels: &[String],
    findings: &mut Findings,
) -> anyhow::Result<Vec<Option<f64>>> {
    let mut groups: BTreeMap<&str, BTreeMap<&str, Vec<f64>>> = BTreeMap::new();
    let rows = crate::stage::diagnose::inputs::read_residuals(path)
        .with_context(|| format!("reading {}", path.display()))?;
    let updated: BTreeSet<&str> = rows
        .iter()
        .filter(|r| r.setup == "free" && r.used_for_updating)
        .map(|r| r.label.as_str())
        .collect();
    for r in rows
        .iter()
        .filter(|r| r.setup == "free" && !r.used_for_updating)
    {
        if let Some(l) = labels.iter().find(|l| **l == r.label) {
            groups
                .entry(l.as_str())
                .or_default()
                .entry(r.board_id.as_str())
                .or_default()
                .push(r.rel_residual);
        }
    }
    let out: Vec<Option<f64>> = labels
        .iter()
        .map(|l| {
            if updated.contains(l.as_str()) {
                return None;
            }
            let g: Vec<Vec<f64>> = groups
                .get(l.as_str())
                .map(|m| m.values().cloned().collect())
                .unwrap_or_default();
            crate::uq::propagate::repeatability_eps(&g)
        })
        .collect();
    let used: Vec<String> = labels
        .iter()
        .zip(&out)
        .filter_map(|(l, e)| e.map(|e| format!("{l} {e:.2e}")))
        .collect();
    if !used.is_empty() {
        findings.push(Finding::new(
            Severity::Info,
            "propagate.validation_repeatability",
            format!(
                "free validation modes take the larger of the pooled ε and their repeatability (relative eigenvalue error from the within-board scatter of their measurements): {}",
                used.join(", ")
            ),
        ));
    }
    Ok(out)
}

#[allow(clippy::type_complexity)]
fn read_step1(
    dir: &Path,
    labels: &[String],
    findings: &mut Findings,
) -> anyhow::Result<(Posterior, BTreeMap<(i32, i32), usize>)> {
    let pop_path = dir.join("population.parquet");
    let boards_path = dir.join("boards.parquet");
    let updated = updated_labels(&dir.join("residuals.parquet"))?;
    let fixed = fixed_eps(&dir.join(crate::stage::update::MANIFEST_BOARDS));
    let pop = tables::read_parquet(&pop_path)?;
    let first = pop
        .first()
        .ok_or_else(|| anyhow!("{}: no rows", pop_path.display()))?;
    let params: Vec<String> = first
        .schema()
        .fields()
        .iter()
        .filter_map(|f| f.name().strip_prefix("mu_").map(str::to_string))
        .collect();
    if params.is_empty() {
        bail!(
            "{}: expected mu_<parameter> columns, found none",
            pop_path.display()
        );
    }
    let d = params.len();
    // Moduli per unit mass scale (`update::BoardCoordinates::PerMass`): the population's
    // coordinate `<p>_per_mass_scale_pa` is parameter p over the mass scale.
    let pop_params = params;
    let params: Vec<String> = pop_params
        .iter()
        .map(|c| names::modulus_of_per_mass_scale(c).unwrap_or_else(|| c.clone()))
        .collect();
    let specific: Vec<bool> = pop_params
        .iter()
        .zip(&params)
        .map(|(c, p)| c != p)
        .collect();
    let per_mass = if specific.iter().any(|&s| s) {
        let m = params
            .iter()
            .position(|p| p == names::MASS_SCALE)
            .ok_or_else(|| {
                anyhow!(
                    "{}: moduli per unit mass scale ({:?}) but no mu_{} column",
                    pop_path.display(),
                    pop_params,
                    names::MASS_SCALE
                )
            })?;
        Some(crate::bayes::target::PerMass { mass: m, specific })
    } else {
        None
    };
    let mut index = BTreeMap::new();
    let mut step1 = vec![];
    let mut warned = BTreeSet::new();
    for b in &pop {
        let c = Cols {
            batch: b,
            path: &pop_path,
        };
        let (run, draw) = (c.i32("run")?, c.i32("draw")?);
        let mu: Vec<&Float64Array> = pop_params
            .iter()
            .map(|p| f64_col(b, &format!("mu_{p}"), &pop_path))
            .collect::<Result<_, _>>()?;
        let sg: Vec<&Float64Array> = pop_params
            .iter()
            .map(|p| f64_col(b, &format!("sigma_{p}"), &pop_path))
            .collect::<Result<_, _>>()?;
        let mut corr = vec![];
        for i in 0..d {
            for j in i + 1..d {
                corr.push((
                    (i, j),
                    f64_col(
                        b,
                        &format!("corr_{}_{}", pop_params[i], pop_params[j]),
                        &pop_path,
                    )?,
                ));
            }
        }
        let eps_cols = eps_columns(b, labels, &updated);
        let eps: Vec<Option<&Float64Array>> = eps_cols
            .iter()
            .map(|n| n.as_ref().map(|n| f64_col(b, n, &pop_path)).transpose())
            .collect::<Result<_, _>>()?;
        for (l, e) in labels.iter().zip(&eps) {
            if e.is_none() && updated.contains(l) && fixed.is_none() && warned.insert(l.clone()) {
                findings.push(Finding::new(
                    Severity::Warning,
                    "propagate.eps_missing",
                    format!("free mode {l:?} was updated but {} has no eps_{l} column and no fixed ε is recorded; it borrows ε like a validation mode", pop_path.display()),
                ));
            }
        }
        let disc = DiscrepancyCols::read(b, labels, &pop_path)?;
        for r in 0..b.num_rows() {
            let mut om = vec![0.0; d * d];
            for i in 0..d {
                om[i * d + i] = 1.0;
            }
            for ((i, j), a) in &corr {
                om[i * d + j] = a.value(r);
                om[j * d + i] = a.value(r);
            }
            index.insert((run.value(r), draw.value(r)), step1.len());
            step1.push(Step1Particle {
                population: uq::Population {
                    mu: mu.iter().map(|a| a.value(r)).collect(),
                    sigma: sg.iter().map(|a| a.value(r)).collect(),
                    corr: om,
                },
                boards: vec![],
                eps: labels
                    .iter()
                    .zip(&eps)
                    .map(|(l, e)| match e {
                        Some(a) => Some(a.value(r)),
                        None if updated.contains(l) => fixed,
                        None => None,
                    })
                    .collect(),
                discrepancy: disc.at(r),
            });
        }
    }
    // Boards: every board of the table, in sorted order.
    let mut rows: BTreeMap<(usize, String), Vec<f64>> = BTreeMap::new();
    for b in tables::read_parquet(&boards_path)? {
        let c = Cols {
            batch: &b,
            path: &boards_path,
        };
        let (run, draw, bid) = (c.i32("run")?, c.i32("draw")?, c.str("board_id")?);
        let cols: Vec<&Float64Array> = params
            .iter()
            .map(|p| f64_col(&b, p, &boards_path))
            .collect::<Result<_, _>>()?;
        for r in 0..b.num_rows() {
            let key = (run.value(r), draw.value(r));
            let i = *index.get(&key).ok_or_else(|| {
                anyhow!(
                    "{}: row {r}: (run {}, draw {}) has no row in population.parquet",
                    boards_path.display(),
                    key.0,
                    key.1
                )
            })?;
            rows.insert(
                (i, bid.value(r).to_string()),
                cols.iter().map(|a| a.value(r)).collect(),
            );
        }
    }
    let board_ids: Vec<String> = rows
        .keys()
        .map(|(_, b)| b.clone())
        .collect::<BTreeSet<_>>()
        .into_iter()
        .collect();
    for (i, p) in step1.iter_mut().enumerate() {
        for b in &board_ids {
            let v = rows.remove(&(i, b.clone())).ok_or_else(|| {
                anyhow!(
                    "{}: board {b} has no row for particle {i} of population.parquet",
                    boards_path.display()
                )
            })?;
            p.boards.push(v);
        }
    }
    // With a per-unit discrepancy, each measured board's own offset per updated label.
    let board_offsets = if step1.iter().any(|p| p.discrepancy.unit_scale.is_some()) {
        board_offsets(&dir.join("residuals.parquet"), &board_ids, labels, &updated)?
    } else {
        vec![]
    };
    Ok((
        Posterior {
            params,
            per_mass,
            board_ids,
            step1,
            step2: None,
            board_offsets,
        },
        index,
    ))
}

/// Per board (order of `board_ids`) and free label: the mean measured eigenvalue (2π f̂)²
/// over the board's measurements in the step-1 residuals and their number; `None` for a
/// label not updated or without a measurement of the board.
fn board_offsets(
    path: &Path,
    board_ids: &[String],
    labels: &[String],
    updated: &BTreeSet<String>,
) -> anyhow::Result<Vec<Vec<Option<uq::BoardMean>>>> {
    let rows = crate::stage::diagnose::inputs::read_residuals(path)
        .with_context(|| format!("reading {}", path.display()))?;
    let mut acc: BTreeMap<(&str, &str), (f64, usize)> = BTreeMap::new();
    let two_pi = 2.0 * std::f64::consts::PI;
    for r in rows
        .iter()
        .filter(|r| r.setup == "free" && r.freq_hz.is_finite())
    {
        let e = acc
            .entry((r.board_id.as_str(), r.label.as_str()))
            .or_default();
        e.0 += (two_pi * r.freq_hz).powi(2);
        e.1 += 1;
    }
    Ok(board_ids
        .iter()
        .map(|b| {
            labels
                .iter()
                .map(|l| {
                    let (sum, n) = acc.get(&(b.as_str(), l.as_str())).copied()?;
                    (updated.contains(l) && n > 0).then(|| (sum / n as f64, n))
                })
                .collect()
        })
        .collect())
}

fn read_step2(
    dir: &Path,
    labels: &[String],
    index: &BTreeMap<(i32, i32), usize>,
    findings: &mut Findings,
) -> anyhow::Result<Vec<Step2Particle>> {
    let pop_path = dir.join("population.parquet");
    let updated = updated_labels(&dir.join("residuals.parquet"))?;
    let fixed = fixed_eps(&dir.join("update_joints.manifest.json"));
    let mut out = vec![];
    let mut warned = BTreeSet::new();
    for b in tables::read_parquet(&pop_path)? {
        let c = Cols {
            batch: &b,
            path: &pop_path,
        };
        let (br, bd) = (c.i32("boards_run")?, c.i32("boards_draw")?);
        let (mu, sg) = (c.f64("mu_ln_k_con")?, c.f64("sigma_ln_k_con")?);
        let eps_cols = eps_columns(&b, labels, &updated);
        let eps: Vec<Option<&Float64Array>> = eps_cols
            .iter()
            .map(|n| n.as_ref().map(|n| f64_col(&b, n, &pop_path)).transpose())
            .collect::<Result<_, _>>()?;
        for (l, e) in labels.iter().zip(&eps) {
            if e.is_none() && updated.contains(l) && fixed.is_none() && warned.insert(l.clone()) {
                findings.push(Finding::new(
                    Severity::Warning,
                    "propagate.eps_missing",
                    format!("bolted mode {l:?} was updated but {} has no eps_{l} column; it borrows ε like a validation mode", pop_path.display()),
                ));
            }
        }
        let disc = DiscrepancyCols::read(&b, labels, &pop_path)?;
        for r in 0..b.num_rows() {
            let key = (br.value(r), bd.value(r));
            let step1 = *index.get(&key).ok_or_else(|| {
                anyhow!(
                    "{}: row {r}: carries step-1 draw (run {}, draw {}), which the step-1 population does not have (was step 2 run on another step-1 result?)",
                    pop_path.display(), key.0, key.1
                )
            })?;
            out.push(Step2Particle {
                step1,
                mu_ln_k: mu.value(r),
                sigma_ln_k: sg.value(r),
                eps: labels
                    .iter()
                    .zip(&eps)
                    .map(|(l, e)| match e {
                        Some(a) => Some(a.value(r)),
                        None if updated.contains(l) => fixed,
                        None => None,
                    })
                    .collect(),
                discrepancy: disc.at(r),
            });
        }
    }
    Ok(out)
}

fn read_rom(path: &Path) -> anyhow::Result<Rom> {
    let bytes =
        std::fs::read(path).with_context(|| format!("cannot read ROM {}", path.display()))?;
    Rom::from_npz_bytes(&bytes).map_err(|e| anyhow!("{}: {e}", path.display()))
}

/// The ROM's first `r` basis vectors: the ROM an update stage ran with when it capped the basis
/// (`--rom-basis r`). The basis is an M-orthonormalised POD basis ordered by singular value, so
/// a ROM built with a cap of r spans the first r vectors of one built with a larger cap (same
/// snapshots and options), and its reduced matrices are the leading r × r blocks.
fn truncate_rom(rom: Rom, r: usize) -> Rom {
    if r >= rom.dim() {
        return rom;
    }
    let lead = |m: &faer::Mat<f64>| faer::Mat::from_fn(r, r, |i, j| m[(i, j)]);
    Rom::from_parts(
        rom.map.clone(),
        rom.k_r.iter().map(lead).collect(),
        rom.m_r.iter().map(lead).collect(),
        faer::Mat::from_fn(rom.basis.nrows(), r, |i, j| rom.basis[(i, j)]),
        rom.n_rigid,
        rom.n_modes,
        rom.setup.clone(),
    )
}

/// The ROM options an update stage recorded: (basis cap, box half-width).
fn update_rom_options(manifest: &Path) -> (Option<usize>, Option<f64>) {
    match crate::io::manifest::read_manifest(manifest) {
        Some(m) => (
            m.config
                .get("rom_max_basis")
                .and_then(|v| v.as_u64())
                .map(|v| v as usize),
            m.config.get("rom_box").and_then(|v| v.as_f64()),
        ),
        None => (None, None),
    }
}

/// The model-error term's prior sd per free label from step 1's evidence.json
/// (`model_error`: `labels`, `sd`); zeros when step 1 ran without it. A label step 1 did not
/// give an sd (paired differently since) gets the largest of the others, and a finding.
fn model_error_sd(
    path: &Path,
    labels: &[String],
    findings: &mut Findings,
) -> anyhow::Result<Vec<f64>> {
    if !path.exists() {
        return Ok(vec![0.0; labels.len()]);
    }
    let ev = crate::io::read_json(path)?;
    let me = &ev["model_error"];
    if me.is_null() {
        return Ok(vec![0.0; labels.len()]);
    }
    let (Some(ls), Some(sd)) = (me["labels"].as_array(), me["sd"].as_array()) else {
        bail!(
            "{}: model_error: expected arrays `labels` and `sd`",
            path.display()
        );
    };
    if ls.len() != sd.len() {
        bail!(
            "{}: model_error: expected as many sds as labels, found {} labels and {} sds",
            path.display(),
            ls.len(),
            sd.len()
        );
    }
    let mut by_label = BTreeMap::new();
    for (l, v) in ls.iter().zip(sd) {
        match (l.as_str(), v.as_f64()) {
            (Some(l), Some(v)) if v.is_finite() && v >= 0.0 => {
                by_label.insert(l.to_string(), v);
            }
            _ => bail!(
                "{}: model_error: expected a label and a finite sd ≥ 0, found {l} and {v}",
                path.display()
            ),
        }
    }
    let top = by_label.values().copied().fold(0.0, f64::max);
    let mut missing = vec![];
    let out = labels
        .iter()
        .map(|l| {
            by_label.get(l).copied().unwrap_or_else(|| {
                missing.push(l.clone());
                top
            })
        })
        .collect();
    if !missing.is_empty() {
        findings.push(Finding::new(
            Severity::Info,
            "propagate.model_error_missing",
            format!(
                "{}: no model-error sd for free label(s) {missing:?}; they take the largest of the others ({top:.2e})",
                path.display()
            ),
        ));
    }
    Ok(out)
}

fn positions(rom: &Rom, params: &[String], path: &Path) -> anyhow::Result<Vec<usize>> {
    params
        .iter()
        .map(|p| {
            rom.map.names.iter().position(|n| n == p).ok_or_else(|| {
                anyhow!("{}: the posterior's parameter {p:?} is not a parameter of this ROM (expected one of {:?})", path.display(), rom.map.names)
            })
        })
        .collect()
}

/// Run `hbmu propagate`.
pub fn run(opts: &PropagateOptions, verbose: bool) -> anyhow::Result<StageOutcome> {
    if opts.draws == 0 {
        bail!("--draws: expected at least 1");
    }
    let inp = classify(opts)?;
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
    let (basis1, box1) = update_rom_options(&inp.step1.join(crate::stage::update::MANIFEST_BOARDS));
    let (basis2, _) = match &inp.step2 {
        Some(s2) => update_rom_options(&s2.join("update_joints.manifest.json")),
        None => (None, None),
    };
    config["rom_basis_step1"] = basis1.into();
    config["rom_basis_step2"] = basis2.into();
    config["rom_box_step1"] = box1.into();
    config["eps_fixed_step1"] =
        fixed_eps(&inp.step1.join(crate::stage::update::MANIFEST_BOARDS)).into();
    if let Some(s2) = &inp.step2 {
        config["eps_fixed_step2"] = fixed_eps(&s2.join("update_joints.manifest.json")).into();
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
    crate::stage::run(spec, opts.force, |prep| {
        let mut findings = Findings::default();
        let mut rom_free = read_rom(&inp.rom_free)?;
        if let Some(b) = box1 {
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
        if let Some(r) = basis1 {
            rom_free = truncate_rom(rom_free, r);
        }
        let (free_labels, free_modes) = labels_of(&inp.pairs, "free", &rom_free, &mut findings)?;
        if free_labels.is_empty() {
            bail!(
                "{}: no accepted free-free pair: nothing to predict",
                inp.pairs.display()
            );
        }
        let (mut post, index) = read_step1(&inp.step1, &free_labels, &mut findings)?;
        let free_idx = positions(&rom_free, &post.params, &inp.rom_free)?;
        let repeat = repeatability(
            &inp.step1.join("residuals.parquet"),
            &free_labels,
            &mut findings,
        )?;
        let model_error = model_error_sd(&evidence1, &free_labels, &mut findings)?;
        let free = LabelModel::new(rom_free, free_labels.clone(), &free_modes, opts.rom_box)?
            .with_repeatability(repeat)?
            .with_model_error(model_error)?;
        let mut bolted_model = None;
        let mut bolted_labels = vec![];
        match &inp.step2 {
            Some(s2) => {
                let mut rom_b = read_rom(&inp.rom_bolted)?;
                if let Some(r) = basis2 {
                    rom_b = truncate_rom(rom_b, r);
                }
                let (bl, bm) = labels_of(&inp.pairs, "bolted", &rom_b, &mut findings)?;
                if bl.is_empty() {
                    bail!(
                        "{}: no accepted bolted pair, but a step-2 posterior was given",
                        inp.pairs.display()
                    );
                }
                post.step2 = Some(read_step2(s2, &bl, &index, &mut findings)?);
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
                bolted_model = Some((
                    LabelModel::new(rom_b, bl.clone(), &bm, opts.rom_box)?,
                    bidx,
                    kidx,
                ));
                bolted_labels = bl;
            }
            None => findings.push(Finding::new(
                Severity::Info,
                "propagate.no_step2",
                "no step-2 (update joints) posterior among the inputs: no bolted predictions",
            )),
        }
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
                format!("{} of {} evaluations ({} of {} new free-free boards) lie outside the ROM's ±{:.0} % box, where it is not verified", counts.outside_rom_box, counts.evaluations, counts.new_board_outside_box, opts.draws, 100.0 * opts.rom_box),
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
        let label_of = |p: &uq::Prediction| -> &str {
            match p.setup {
                uq::SetupKind::Free => &free_labels[p.label],
                uq::SetupKind::Bolted => &bolted_labels[p.label],
            }
        };
        let cols: Vec<ArrayRef> = vec![
            Arc::new(Int32Array::from_iter_values(
                preds.iter().map(|p| p.draw as i32),
            )),
            Arc::new(StringArray::from_iter_values(
                preds.iter().map(|p| p.scope.as_str()),
            )),
            Arc::new(StringArray::from_iter(
                preds
                    .iter()
                    .map(|p| p.board.map(|b| post.board_ids[b].as_str())),
            )),
            Arc::new(StringArray::from_iter_values(
                preds.iter().map(|p| p.setup.as_str()),
            )),
            Arc::new(StringArray::from_iter_values(preds.iter().map(label_of))),
            Arc::new(Float64Array::from_iter_values(
                preds.iter().map(|p| p.freq_hz),
            )),
            Arc::new(Float64Array::from_iter_values(
                preds.iter().map(|p| p.freq_obs_hz),
            )),
            Arc::new(BooleanArray::from_iter(
                preds.iter().map(|p| Some(p.eps_pooled)),
            )),
            Arc::new(Float64Array::from_iter_values(
                preds.iter().map(|p| p.discrepancy_rel),
            )),
        ];
        let schema = PREDICTIONS.schema(&[], &tables::table_metadata(&PREDICTIONS, &prov));
        let mut outputs = vec![];
        let path = opts.out.join("predictions.parquet");
        tables::write_parquet(&path, &tables::batch(schema, cols)?)?;
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fem::model::Setup;
    use crate::fem::rom::RomOptions;
    use crate::fem::tests::helpers::{build, plain_board};

    #[test]
    fn a_truncated_rom_is_the_rom_built_with_that_cap() {
        let board = plain_board(0.2, 0.15, 1.6e-3, 24e9, 20e9, 8e9, 0.15, 1900.0);
        let fe = build(&board, Setup::Free, 8, 6);
        let opts = |max_basis| RomOptions {
            n_modes: 4,
            n_random: 6,
            max_basis,
            ..RomOptions::default()
        };
        let full = Rom::build(&fe, &opts(64)).unwrap();
        let capped = Rom::build(&fe, &opts(12)).unwrap();
        assert!(
            full.dim() > 12 && capped.dim() == 12,
            "{} {}",
            full.dim(),
            capped.dim()
        );
        let cut = truncate_rom(full.clone(), 12);
        for p in crate::fem::rom::latin_hypercube_params(&fe.map, 5, 0.2, 3) {
            let c = fe.map.coefficients(&p).unwrap();
            let a = capped.eval_lowest(&c.k, &c.m, 4).unwrap();
            let b = cut.eval_lowest(&c.k, &c.m, 4).unwrap();
            let f = full.eval_lowest(&c.k, &c.m, 4).unwrap();
            for j in 0..4 {
                let e = (a.eigenvalues[j] - b.eigenvalues[j]).abs() / a.eigenvalues[j];
                assert!(e < 1e-9, "mode {j}: capped vs truncated differ by {e:e}");
                // Rayleigh–Ritz: the smaller subspace bounds the eigenvalues from above.
                assert!(
                    a.eigenvalues[j] >= f.eigenvalues[j] * (1.0 - 1e-12),
                    "mode {j}"
                );
            }
        }
    }
}

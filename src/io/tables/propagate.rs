//! The spec, row types, reader and writer of propagate's predictions.parquet, and
//! propagate's readers of the update steps' outputs (posterior draws, residuals, manifests,
//! ROMs).

use crate::fem::params::names;
use crate::fem::Rom;
use crate::findings::{Finding, Findings, Severity};
use crate::io::tables::update::{MANIFEST_BOARDS, MANIFEST_JOINTS};
use crate::io::tables::{self, c, Col, Cols, TableSpec};
use crate::report::validation::Pred;
use crate::uq::propagate::{self as uq, Posterior, Step1Particle, Step2Particle};
use anyhow::{anyhow, bail, Context};
use arrow::array::{Array, ArrayRef, BooleanArray, Float64Array, Int32Array, StringArray};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::Arc;

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

/// Write predictions.parquet at `path`: a prediction's label is its index into the free or
/// the bolted labels, its board an index into `board_ids`.
pub fn write_predictions(
    path: &Path,
    prov: &BTreeMap<String, String>,
    preds: &[uq::Prediction],
    (free_labels, bolted_labels): (&[String], &[String]),
    board_ids: &[String],
) -> anyhow::Result<()> {
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
            preds.iter().map(|p| p.board.map(|b| board_ids[b].as_str())),
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
    let schema = PREDICTIONS.schema(&[], &tables::table_metadata(&PREDICTIONS, prov));
    tables::write_parquet(path, &tables::batch(schema, cols)?)?;
    Ok(())
}

/// Labels used for updating in a step (from its residuals).
pub fn updated_labels(residuals: &Path) -> anyhow::Result<BTreeSet<String>> {
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
pub fn fixed_eps(manifest: &Path) -> Option<f64> {
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

/// The population ε per label of a population table's batch: the label's `eps_<label>` column
/// when the label was updated, else none (the fixed value, or borrowed as for a validation
/// mode). An updated `setup` label with neither a column nor a `fixed` ε is warned about
/// once (`warned`).
fn eps_arrays<'a>(
    b: &'a arrow::array::RecordBatch,
    pop_path: &'a Path,
    labels: &[String],
    (updated, fixed): (&BTreeSet<String>, Option<f64>),
    setup: &str,
    warned: &mut BTreeSet<String>,
    findings: &mut Findings,
) -> anyhow::Result<Vec<Option<&'a Float64Array>>> {
    let mut out = Vec::with_capacity(labels.len());
    for l in labels {
        let name = format!("eps_{l}");
        let col = (updated.contains(l) && b.column_by_name(&name).is_some())
            .then(|| f64_col(b, &name, pop_path))
            .transpose()?;
        if col.is_none() && updated.contains(l) && fixed.is_none() && warned.insert(l.clone()) {
            findings.push(Finding::new(
                Severity::Warning,
                "propagate.eps_missing",
                format!("{setup} mode {l:?} was updated but {} has no eps_{l} column and no fixed ε is recorded; it borrows ε like a validation mode", pop_path.display()),
            ));
        }
        out.push(col);
    }
    Ok(out)
}

/// The model-form discrepancy columns of a population table (`discrepancy_scale`,
/// `discrepancy_<label>` of the updated labels); both `None` where the step ran without one.
/// A step without one in its likelihood may carry the cut estimate of its scale
/// (`predictive_discrepancy_scale`, step 2: `bayes::discrepancy::CutScale`): then every
/// label in `updated` has d = 0 (its ε holds its misfit) and the others draw d ~ N(0, τ²).
struct DiscrepancyCols<'a> {
    scale: Option<&'a Float64Array>,
    unit_scale: Option<&'a Float64Array>,
    d: Vec<Option<&'a Float64Array>>,
    /// With the cut scale: per label, whether it was updated (d = 0).
    cut_updated: Option<Vec<bool>>,
}

impl<'a> DiscrepancyCols<'a> {
    fn read(
        b: &'a arrow::array::RecordBatch,
        labels: &[String],
        updated: &BTreeSet<String>,
        path: &'a Path,
    ) -> anyhow::Result<DiscrepancyCols<'a>> {
        if b.column_by_name("discrepancy_scale").is_none() {
            let cut = b
                .column_by_name("predictive_discrepancy_scale")
                .is_some()
                .then(|| f64_col(b, "predictive_discrepancy_scale", path))
                .transpose()?;
            return Ok(DiscrepancyCols {
                scale: cut,
                unit_scale: None,
                d: vec![None; labels.len()],
                cut_updated: cut.map(|_| labels.iter().map(|l| updated.contains(l)).collect()),
            });
        }
        Ok(DiscrepancyCols {
            cut_updated: None,
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
        let d = match &self.cut_updated {
            Some(u) => u.iter().map(|&u| u.then_some(0.0)).collect(),
            None => self.d.iter().map(|c| c.map(|a| a.value(r))).collect(),
        };
        uq::Discrepancy {
            d,
            scale: self.scale.map(|a| a.value(r)),
            unit_scale: self.unit_scale.map(|a| a.value(r)),
        }
    }
}

#[allow(clippy::type_complexity)]
/// Step 1's posterior (`update boards` output `dir`) for the free `labels`, without the
/// boards' offsets (see [`crate::uq::inputs::board_offsets`]), and the particle of each
/// (run, draw).
pub fn read_step1(
    dir: &Path,
    labels: &[String],
    findings: &mut Findings,
) -> anyhow::Result<(Posterior, BTreeMap<(i32, i32), usize>)> {
    let pop_path = dir.join("population.parquet");
    let boards_path = dir.join("boards.parquet");
    let updated = updated_labels(&dir.join("residuals.parquet"))?;
    let fixed = fixed_eps(&dir.join(MANIFEST_BOARDS));
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
        let eps = eps_arrays(
            b,
            &pop_path,
            labels,
            (&updated, fixed),
            "free",
            &mut warned,
            findings,
        )?;
        let disc = DiscrepancyCols::read(b, labels, &BTreeSet::new(), &pop_path)?;
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
                eps: eps_at(labels, &eps, &updated, fixed, r),
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
    Ok((
        Posterior {
            params,
            per_mass,
            board_ids,
            step1,
            step2: None,
            board_offsets: vec![],
        },
        index,
    ))
}

/// Step 2's particles (`update joints` output `dir`) for the bolted `labels`, each pointing
/// at its step-1 particle through `index`.
pub fn read_step2(
    dir: &Path,
    labels: &[String],
    index: &BTreeMap<(i32, i32), usize>,
    findings: &mut Findings,
) -> anyhow::Result<Vec<Step2Particle>> {
    let pop_path = dir.join("population.parquet");
    let updated = updated_labels(&dir.join("residuals.parquet"))?;
    let fixed = fixed_eps(&dir.join(MANIFEST_JOINTS));
    let mut out = vec![];
    let mut warned = BTreeSet::new();
    for b in tables::read_parquet(&pop_path)? {
        let c = Cols {
            batch: &b,
            path: &pop_path,
        };
        let (br, bd) = (c.i32("boards_run")?, c.i32("boards_draw")?);
        let (mu, sg) = (c.f64("mu_ln_k_con")?, c.f64("sigma_ln_k_con")?);
        let eps = eps_arrays(
            &b,
            &pop_path,
            labels,
            (&updated, fixed),
            "bolted",
            &mut warned,
            findings,
        )?;
        let disc = DiscrepancyCols::read(&b, labels, &updated, &pop_path)?;
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
                eps: eps_at(labels, &eps, &updated, fixed, r),
                discrepancy: disc.at(r),
            });
        }
    }
    Ok(out)
}

/// A ROM from its NPZ file.
pub fn read_rom(path: &Path) -> anyhow::Result<Rom> {
    let bytes =
        std::fs::read(path).with_context(|| format!("cannot read ROM {}", path.display()))?;
    Rom::from_npz_bytes(&bytes).map_err(|e| anyhow!("{}: {e}", path.display()))
}

/// The ROM options an update stage recorded: (basis cap, box half-width).
pub fn update_rom_options(manifest: &Path) -> (Option<usize>, Option<f64>) {
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

/// The rows of predictions.parquet.
pub fn read_preds(path: &Path) -> anyhow::Result<Vec<Pred>> {
    let mut out = vec![];
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let (sc, bid, st, l, f, fo) = (
            c.str("scope")?,
            c.str("board_id")?,
            c.str("setup")?,
            c.str("label")?,
            c.f64("freq_hz")?,
            c.f64("freq_obs_hz")?,
        );
        // Absent from the predictions of a posterior without a discrepancy (older outputs).
        let disc = b
            .column_by_name("discrepancy_rel")
            .is_some()
            .then(|| c.f64("discrepancy_rel"))
            .transpose()?;
        for i in 0..b.num_rows() {
            out.push(Pred {
                scope: sc.value(i).into(),
                board_id: (!bid.is_null(i)).then(|| bid.value(i).to_string()),
                setup: st.value(i).into(),
                label: l.value(i).into(),
                freq_hz: f.value(i),
                freq_obs_hz: fo.value(i),
                discrepancy_rel: disc.map_or(0.0, |d| d.value(i)),
            });
        }
    }
    Ok(out)
}

/// Where the inputs are.
pub struct Inputs {
    pub step1: PathBuf,
    pub step2: Option<PathBuf>,
    pub pairs: PathBuf,
    pub rom_free: PathBuf,
    pub rom_bolted: PathBuf,
}

/// Classify propagate's update directories (`update boards`: step 1, `update joints`: step 2)
/// and find the pairs and the ROMs: the ROM an update step ran with, else fe's (`fe_dir`,
/// default `fe` beside step 1); pairs in `pair_dir`, default `pair` beside step 1.
pub fn classify(
    update_dirs: &[PathBuf],
    pair_dir: Option<&PathBuf>,
    fe_dir: Option<&PathBuf>,
) -> anyhow::Result<Inputs> {
    let mut step1 = None;
    let mut step2 = None;
    for d in update_dirs {
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
    let fe = fe_dir.cloned().unwrap_or_else(|| sibling("fe"));
    let pair = pair_dir.cloned().unwrap_or_else(|| sibling("pair"));
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

/// Each label's ε at row `r`: its column's value, else the recorded fixed ε for an updated
/// label, else none (a validation mode borrows one).
fn eps_at(
    labels: &[String],
    eps: &[Option<&Float64Array>],
    updated: &BTreeSet<String>,
    fixed: Option<f64>,
    r: usize,
) -> Vec<Option<f64>> {
    labels
        .iter()
        .zip(eps)
        .map(|(l, e)| match e {
            Some(a) => Some(a.value(r)),
            None if updated.contains(l) => fixed,
            None => None,
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use arrow::array::RecordBatch;
    use arrow::datatypes::{DataType, Field, Schema};

    fn batch(cols: &[(&str, Vec<f64>)]) -> RecordBatch {
        let schema = Schema::new(
            cols.iter()
                .map(|(n, _)| Field::new(*n, DataType::Float64, false))
                .collect::<Vec<_>>(),
        );
        let arrays: Vec<ArrayRef> = cols
            .iter()
            .map(|(_, v)| Arc::new(Float64Array::from(v.clone())) as ArrayRef)
            .collect();
        RecordBatch::try_new(Arc::new(schema), arrays).unwrap()
    }

    /// Step 2's cut scale: the updated labels keep d = 0, the others draw at the row's τ;
    /// without the column, no discrepancy; with the likelihood's own columns, those.
    #[test]
    fn the_cut_scale_spreads_only_the_labels_step_2_did_not_update() {
        let labels = vec!["plate-0-0".to_string(), "bending-x-2".to_string()];
        let updated: BTreeSet<String> = ["plate-0-0".to_string()].into();
        let path = Path::new("population.parquet");
        let b = batch(&[("predictive_discrepancy_scale", vec![0.01, 0.02])]);
        let d = DiscrepancyCols::read(&b, &labels, &updated, path).unwrap();
        let at = d.at(1);
        assert_eq!(at.d, vec![Some(0.0), None]);
        assert_eq!((at.scale, at.unit_scale), (Some(0.02), None));
        let none = batch(&[("eps_plate-0-0", vec![0.01, 0.02])]);
        let d = DiscrepancyCols::read(&none, &labels, &updated, path).unwrap();
        assert_eq!(d.at(0), uq::Discrepancy::none(2));
        let own = batch(&[
            ("discrepancy_scale", vec![0.03]),
            ("discrepancy_plate-0-0", vec![0.004]),
            ("predictive_discrepancy_scale", vec![0.5]),
        ]);
        let d = DiscrepancyCols::read(&own, &labels, &updated, path).unwrap();
        let at = d.at(0);
        assert_eq!((at.d, at.scale), (vec![Some(0.004), None], Some(0.03)));
    }
}

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

use crate::fem::{Board, FeModel};
use crate::findings::{Finding, Findings, Severity};
use crate::io::manifest::StageSpec;
use crate::io::modes_table::{read_modes_table, ModeRow};
use crate::io::tables::{self, c, Col, TableSpec};
use crate::modal::pair::{self, IdentifiedShape, ModelMode, PairParams, PresenceRecord, ScanPoint};
use crate::stage::fe::SetupArg;
use crate::stage::{exit, StageOutcome, StageResult};
use anyhow::Context;
use arrow::array::{ArrayRef, BooleanArray, Float64Array, Int32Array, StringArray};
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;

pub const PAIRS: TableSpec = TableSpec {
    name: "pairs",
    doc: "Pairing of identified modes with model modes per measurement. One row per identified mode (model_mode null when unpaired) plus one row per model mode in the band that found no partner (mode null, `missing` true).",
    open: false,
    columns: &[
        c("measurement_id", Col::Utf8, false, "", "Measurement id."),
        c("board_id", Col::Utf8, false, "", "Board."),
        c("setup", Col::Utf8, false, "", "`free` or `bolted`."),
        c("mode", Col::Int32, true, "", "Identified mode number (as in modes.parquet); null for a missing model mode."),
        c("freq_hz", Col::Float64, true, "Hz", "Identified frequency."),
        c("model_mode", Col::Int32, true, "", "Model mode number, 1-based; null when unpaired."),
        c("model_freq_hz", Col::Float64, true, "Hz", "Model frequency at nominal parameters."),
        c("label", Col::Utf8, false, "", "Label derived from the model shape (e.g. torsion-1, bending-x-1)."),
        c("mac", Col::Float64, true, "", "MAC between the identified and the model shape."),
        c("accepted", Col::Bool, false, "", "Pair passes the MAC and frequency thresholds."),
        c("missing", Col::Bool, false, "", "A model mode in the band with no accepted partner."),
        c("swapped", Col::Bool, false, "", "The pair's order differs from the model's frequency order (mode swap)."),
    ],
};

pub const PRESENCE: TableSpec = TableSpec {
    name: "presence",
    doc: "The presence rule: per setup and mode label, in how many measurements the mode was accepted, and whether it counts for updating (present in at least `min_fraction` of the setup's measurements; the paper: every measurement).",
    open: false,
    columns: &[
        c("setup", Col::Utf8, false, "", "`free` or `bolted`."),
        c("label", Col::Utf8, false, "", "Mode label."),
        c("n_present", Col::Int32, false, "", "Measurements of the setup in which the mode was accepted."),
        c("n_measurements", Col::Int32, false, "", "Measurements of the setup."),
        c("used_for_updating", Col::Bool, false, "", "n_present >= min_fraction * n_measurements."),
    ],
};

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

struct Identified {
    measurement_id: String,
    board_id: String,
    setup: String,
    band: (f64, f64),
    points: Vec<ScanPoint>,
    modes: Vec<(i32, f64, Vec<f64>)>,
}

/// The rows of modes.parquet grouped per measurement (consecutive rows of one measurement),
/// with the band and scan points of its first row.
fn group_modes(rows: Vec<ModeRow>) -> Vec<Identified> {
    let mut out: Vec<Identified> = vec![];
    for r in rows {
        if out.last().map(|m| m.measurement_id.as_str()) != Some(r.measurement_id.as_str()) {
            out.push(Identified {
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
        // Each model mode is labelled once per setup, on a grid over the whole board, so it
        // keeps its label in every measurement whatever part of the board was scanned.
        type SetupModel = (FeModel, crate::fem::Modes, Vec<String>, Vec<f64>);
        let mut models: BTreeMap<String, SetupModel> = BTreeMap::new();
        for setup in [SetupArg::Free, SetupArg::Bolted] {
            if ms.iter().any(|m| m.setup == setup.as_str()) {
                let fe_setup = setup.to_setup();
                let model = FeModel::build(&board, fe_setup.clone(), board.mesh_for(&fe_setup))?;
                let p = model.nominal_params();
                let modes = model.modes(&p, opts.n_model_modes)?;
                let (labels, board_max) = board_grid_labels(&board, &model, &modes, &opts.params)?;
                models.insert(setup.as_str().into(), (model, modes, labels, board_max));
            }
        }
        let mut findings = Findings::default();
        let mut rows: Vec<Row> = vec![];
        let mut presence: Vec<PresenceRecord> = vec![];
        let mut outputs = vec![];
        for m in &ms {
            let Some((model, fe_modes, labels, board_max)) = models.get(&m.setup) else {
                continue;
            };
            // Scan points the model cannot evaluate (outside the outline, inside a hole) are
            // left out of this measurement's MAC, and reported.
            let mut keep = vec![];
            for (i, p) in m.points.iter().enumerate() {
                if model.w_at(fe_modes, &[[p.x_m, p.y_m]]).is_ok() {
                    keep.push(i);
                } else {
                    findings.push(
                        Finding::new(
                            Severity::Warning,
                            "pair.point_outside_model",
                            format!(
                                "scan point node {} at ({:.4}, {:.4}) m is outside the model board or inside a hole; left out of the MAC",
                                p.node_id, p.x_m, p.y_m
                            ),
                        )
                        .measurement(m.measurement_id.clone()),
                    );
                }
            }
            if keep.is_empty() {
                findings.push(
                    Finding::new(
                        Severity::Quarantined,
                        "pair.points",
                        "no scan point lies on the model board (expected at least 1)",
                    )
                    .measurement(m.measurement_id.clone()),
                );
                continue;
            }
            let points: Vec<ScanPoint> = keep.iter().map(|&i| m.points[i]).collect();
            let model_modes = modes_at(model, fe_modes, &points)?;
            let identified: Vec<IdentifiedShape> = m
                .modes
                .iter()
                .map(|(_, f, s)| IdentifiedShape {
                    freq_hz: *f,
                    shape: keep.iter().map(|&i| s[i]).collect(),
                })
                .collect();
            // The MAC pairs modes only where these points tell the model's own modes apart.
            let p = &opts.params;
            let alike = pair::model_mac_max(&model_modes, m.band, p.freq_gate_sd * p.freq_sd_rel);
            let by_mac = points.len() >= 3 && alike < p.mac_min;
            let paired = if by_mac {
                pair::pair_modes_labelled(&identified, &model_modes, labels.clone(), m.band, p)
            } else {
                let visibility: Vec<f64> = model_modes
                    .iter()
                    .zip(board_max)
                    .map(|(mm, &big)| {
                        let here = mm.shape.iter().fold(0.0f64, |a, v| a.max(v.abs()));
                        if big > 0.0 {
                            (here / big).min(1.0)
                        } else {
                            0.0
                        }
                    })
                    .collect();
                findings.push(
                    Finding::new(
                        Severity::Info,
                        "pair.by_frequency",
                        format!(
                            "{} scan point(s) cannot tell the model's modes apart by MAC (two model modes near the band have MAC {alike:.2} at them, against {} for a pair); paired on frequency (prior predictive sd {} of ln f, at most {} sd apart), on each model mode's amplitude at the points (under {} of its largest on the board: near a node there, less likely seen, not missing when unseen) and on the modes' order",
                            points.len(),
                            p.mac_min,
                            p.freq_sd_rel,
                            p.freq_gate_sd,
                            p.min_visibility
                        ),
                    )
                    .measurement(m.measurement_id.clone()),
                );
                pair::pair_modes_by_frequency(
                    &identified,
                    &model_modes,
                    labels.clone(),
                    &visibility,
                    m.band,
                    p,
                )
            };
            let pairing = match paired {
                Ok(p) => p,
                Err(e) => {
                    findings.push(
                        Finding::new(Severity::Quarantined, "pair.failed", e.to_string())
                            .measurement(m.measurement_id.clone()),
                    );
                    continue;
                }
            };
            let swapped: std::collections::BTreeSet<usize> =
                pairing.swaps.iter().flat_map(|&(a, b)| [a, b]).collect();
            let mut accepted_labels = vec![];
            for pr in &pairing.pairs {
                let (mode_no, f, _) = &m.modes[pr.mode];
                if pr.accepted {
                    accepted_labels.push(pr.label.clone());
                }
                rows.push(Row {
                    m,
                    mode: Some(*mode_no),
                    freq_hz: Some(*f),
                    model_mode: pr.model_mode.map(|j| j as i32 + 1),
                    model_freq_hz: pr.model_mode.map(|j| model_modes[j].freq_hz),
                    label: pr.label.clone(),
                    mac: pr.model_mode.map(|_| pr.mac),
                    accepted: pr.accepted,
                    missing: false,
                    swapped: swapped.contains(&pr.mode),
                });
            }
            for &j in &pairing.missing {
                rows.push(Row {
                    m,
                    mode: None,
                    freq_hz: None,
                    model_mode: Some(j as i32 + 1),
                    model_freq_hz: Some(model_modes[j].freq_hz),
                    label: pairing.model_labels[j].clone(),
                    mac: None,
                    accepted: false,
                    missing: true,
                    swapped: false,
                });
            }
            presence.push(PresenceRecord {
                measurement_id: m.measurement_id.clone(),
                setup: m.setup.clone(),
                accepted_labels,
            });
            if opts.plots {
                let rl: Vec<String> = m
                    .modes
                    .iter()
                    .map(|(k, f, _)| format!("{k}: {f:.0} Hz"))
                    .collect();
                let cl: Vec<String> = pairing
                    .model_labels
                    .iter()
                    .zip(&model_modes)
                    .map(|(l, mm)| format!("{l} {:.0}", mm.freq_hz))
                    .collect();
                if let Ok(svg) = crate::report::plots::mac_matrix_svg(
                    &pairing.mac,
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
        }
        let present = pair::modes_present(&presence, opts.min_fraction);
        let prov = BTreeMap::from([
            ("hbmu.stage".to_string(), "pair".to_string()),
            ("hbmu.fingerprint".to_string(), prep.fingerprint.clone()),
            (
                "hbmu.version".to_string(),
                crate::io::manifest::TOOL_VERSION.to_string(),
            ),
            ("hbmu.campaign".to_string(), String::new()),
        ]);
        let p = opts.out.join("pairs.parquet");
        let cols: Vec<ArrayRef> = vec![
            Arc::new(StringArray::from_iter_values(
                rows.iter().map(|r| r.m.measurement_id.as_str()),
            )),
            Arc::new(StringArray::from_iter_values(
                rows.iter().map(|r| r.m.board_id.as_str()),
            )),
            Arc::new(StringArray::from_iter_values(
                rows.iter().map(|r| r.m.setup.as_str()),
            )),
            Arc::new(Int32Array::from_iter(rows.iter().map(|r| r.mode))),
            Arc::new(Float64Array::from_iter(rows.iter().map(|r| r.freq_hz))),
            Arc::new(Int32Array::from_iter(rows.iter().map(|r| r.model_mode))),
            Arc::new(Float64Array::from_iter(
                rows.iter().map(|r| r.model_freq_hz),
            )),
            Arc::new(StringArray::from_iter_values(
                rows.iter().map(|r| r.label.as_str()),
            )),
            Arc::new(Float64Array::from_iter(rows.iter().map(|r| r.mac))),
            Arc::new(BooleanArray::from_iter(
                rows.iter().map(|r| Some(r.accepted)),
            )),
            Arc::new(BooleanArray::from_iter(
                rows.iter().map(|r| Some(r.missing)),
            )),
            Arc::new(BooleanArray::from_iter(
                rows.iter().map(|r| Some(r.swapped)),
            )),
        ];
        let schema = PAIRS.schema(&[], &tables::table_metadata(&PAIRS, &prov));
        tables::write_parquet(&p, &tables::batch(schema, cols)?)?;
        outputs.push(p);
        let p = opts.out.join("presence.parquet");
        let cols: Vec<ArrayRef> = vec![
            Arc::new(StringArray::from_iter_values(
                present.iter().map(|r| r.setup.as_str()),
            )),
            Arc::new(StringArray::from_iter_values(
                present.iter().map(|r| r.label.as_str()),
            )),
            Arc::new(Int32Array::from_iter_values(
                present.iter().map(|r| r.n_present as i32),
            )),
            Arc::new(Int32Array::from_iter_values(
                present.iter().map(|r| r.n_measurements as i32),
            )),
            Arc::new(BooleanArray::from_iter(
                present.iter().map(|r| Some(r.used_for_updating)),
            )),
        ];
        let schema = PRESENCE.schema(&[], &tables::table_metadata(&PRESENCE, &prov));
        tables::write_parquet(&p, &tables::batch(schema, cols)?)?;
        outputs.push(p);
        for f in findings.iter() {
            if verbose || f.severity >= Severity::Quarantined {
                eprintln!("{f}");
            }
        }
        let n_acc = rows.iter().filter(|r| r.accepted).count();
        let n_missing = rows.iter().filter(|r| r.missing).count();
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
    })
}

struct Row<'a> {
    m: &'a Identified,
    mode: Option<i32>,
    freq_hz: Option<f64>,
    model_mode: Option<i32>,
    model_freq_hz: Option<f64>,
    label: String,
    mac: Option<f64>,
    accepted: bool,
    missing: bool,
    swapped: bool,
}

/// Grid points along the board's longer side for labelling model modes (25 on an 80 mm board): a
/// mode's nodal lines are resolved up to order ~8 whatever the scan grid was.
const LABEL_GRID_POINTS: usize = 25;

/// Labels of the model's modes from their shapes on a regular grid over the whole board
/// (cell centres of a `LABEL_GRID_POINTS`-per-longer-side grid; points in holes or off the
/// outline are left out), made unique ([`pair::label_modes`]); and each mode's largest
/// |amplitude| on that grid (the scale of its visibility at a measurement's points).
fn board_grid_labels(
    board: &Board,
    model: &FeModel,
    modes: &crate::fem::Modes,
    params: &PairParams,
) -> anyhow::Result<(Vec<String>, Vec<f64>)> {
    let (lx, ly) = (board.length_x_m, board.width_y_m);
    let step = lx.max(ly) / LABEL_GRID_POINTS as f64;
    let (nx, ny) = (
        ((lx / step).round() as usize).max(3),
        ((ly / step).round() as usize).max(3),
    );
    let mut points = vec![];
    for j in 0..ny {
        for i in 0..nx {
            let (x, y) = (
                (i as f64 + 0.5) * lx / nx as f64,
                (j as f64 + 0.5) * ly / ny as f64,
            );
            if model.w_at(modes, &[[x, y]]).is_ok() {
                points.push(ScanPoint {
                    node_id: (j * nx + i) as i64,
                    x_m: x,
                    y_m: y,
                    z_m: 0.0,
                });
            }
        }
    }
    let shapes = modes_at(model, modes, &points)?;
    let board_max = shapes
        .iter()
        .map(|m| m.shape.iter().fold(0.0f64, |a, v| a.max(v.abs())))
        .collect();
    Ok((pair::label_modes(&shapes, &points, params), board_max))
}

/// The model's modes as shapes at `points`.
fn modes_at(
    model: &FeModel,
    modes: &crate::fem::Modes,
    points: &[ScanPoint],
) -> anyhow::Result<Vec<ModelMode>> {
    let pts: Vec<[f64; 2]> = points.iter().map(|p| [p.x_m, p.y_m]).collect();
    let w = model.w_at(modes, &pts)?;
    Ok((0..modes.freq_hz.len())
        .map(|j| ModelMode {
            freq_hz: modes.freq_hz[j],
            shape: (0..pts.len()).map(|i| w[(i, j)]).collect(),
        })
        .collect())
}

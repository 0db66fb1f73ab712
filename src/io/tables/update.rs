//! The spec, row types, reader and writer of update's tables (both steps).

use crate::bayes::smc::StageInfo;
use crate::diagnose::locate::ResidualObs;
pub use crate::io::tables::pairs::{read_pairs, read_presence};
use crate::io::tables::{self, c, Col, Cols, TableSpec};
use crate::update::posterior::{DrawTable, Residual, SummaryRow};
use crate::update::problem::MassRow;
use crate::update::step1::Step1;
use anyhow::{anyhow, bail, Context};
use arrow::array::{ArrayRef, BooleanArray, Float64Array, Int32Array, StringArray};
use arrow::datatypes::{DataType, Field};
use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use std::sync::Arc;

/// The manifests of the two steps in their output directories.
pub const MANIFEST_BOARDS: &str = "update_boards.manifest.json";
pub const MANIFEST_JOINTS: &str = "update_joints.manifest.json";

pub const JOINTS: TableSpec = TableSpec {
    name: "joints",
    doc: "Step-2 posterior draws of every bolted measurement's joint stiffness, one row per particle and measurement. The modular (cut) posterior: every particle carries one step-1 draw of the boards (population.parquet's boards_run/boards_draw), and the bolted data updated only the joint parameters. A refit with an enrichment (`--enrich`, the diagnosis's candidates) adds one column per extra coordinate, named with its unit (e.g. k_rot_nm_per_rad, joint_mass_kg, m_fix_kg, f_fix_hz, k_ratio_<j>); with `joint_stiffness_per_joint` at one joint k_con_n_per_m is the stiffness of the other joints and k_ratio_<j> that joint's over theirs; with every joint (no joint named) k_con_n_per_m is the joints' geometric mean and k_ratio_<j> each joint's stiffness over the mean of the others' in that measurement.",
    open: true,
    columns: &[
        c("run", Col::Int32, false, "", "Independent SMC run (ArviZ chain)."),
        c("draw", Col::Int32, false, "", "Particle index within the run."),
        c("measurement_id", Col::Utf8, false, "", "Bolted measurement."),
        c("board_id", Col::Utf8, false, "", "Board of the measurement."),
        c("k_con_n_per_m", Col::Float64, false, "N/m", "Total joint contact stiffness of the measurement's fixing."),
    ],
};

pub const POPULATION_JOINTS: TableSpec = TableSpec {
    name: "population_joints",
    doc: "Step-2 (joints) population draws, one row per particle, written as population.parquet in the step-2 directory: the step-1 draw the particle carries, the population of ln k_con (natural log of N/m), with an enrichment (`--enrich`) `mu_<coord>`/`sigma_<coord>` of every extra coordinate (natural logs of the parameter in its unit, e.g. mu_ln_k_rot), and the bolted modes' prediction errors `eps_<label>`, `delta_<label>` (when inferred); with the model-form discrepancy in the likelihood (off unless `--discrepancy-pct` sets it), `discrepancy_scale` (its scale τ, relative eigenvalue), `discrepancy_unit_scale` (σ_u, the sd of the part that differs between measurements, integrated out per measurement) and `discrepancy_<label>` (the bolted mode's discrepancy d: the model eigenvalue is λ (1 + d) for every measurement); without it, `predictive_discrepancy_scale`: a draw of the cut estimate of that scale τ (relative eigenvalue) from the updated modes' mean residuals, with the bolted model's stated fidelity (1.5 %) as its prior median. It enters only the predictions of the bolted modes step 2 did not update (d ~ N(0, τ²)), never the fit or its evidence.",
    open: true,
    columns: &[
        c("run", Col::Int32, false, "", "Independent SMC run (ArviZ chain)."),
        c("draw", Col::Int32, false, "", "Particle index within the run (ArviZ draw)."),
        c("boards_run", Col::Int32, false, "", "run of the step-1 draw (boards.parquet) this particle carries."),
        c("boards_draw", Col::Int32, false, "", "draw of the step-1 draw this particle carries."),
        c("mu_ln_k_con", Col::Float64, false, "ln(N/m)", "Population mean of ln k_con_n_per_m."),
        c("sigma_ln_k_con", Col::Float64, false, "ln(N/m)", "Population standard deviation of ln k_con_n_per_m."),
    ],
};

pub const POPULATION: TableSpec = TableSpec {
    name: "population",
    doc: "Posterior draws of the population (hyper-)parameters, one row per particle; run = independent SMC run (ArviZ: chain = run, draw = draw). Step 1 (boards): for every updated parameter <p> (unit in its name) `mu_<p>` (population mean, unit of <p>), `sigma_<p>` (population standard deviation, unit of <p>), `corr_<p>_<q>` (population correlation). By default (`--board-coordinates per-mass`), where mass_scale is updated, the population of every modulus <m>_pa is formed per unit mass scale: its coordinate is `<m>_per_mass_scale_pa` = <m>_pa / mass_scale (Pa; free-free frequencies follow it), so the columns are e.g. `mu_e_x_per_mass_scale_pa`, `sigma_e_x_per_mass_scale_pa`, `corr_e_x_per_mass_scale_pa_mass_scale`; boards.parquet keeps the moduli themselves. A parameter on a logarithmic coordinate (added_mass_kg of `--enrich added_mass`) has `mu_<p>` = the population median (reference · e^μ, unit of <p>) and `sigma_<p>` in natural-log units; beside that point mass the mass scale's coordinate is `total_mass_scale`, the weighed total (board and point mass) over its nominal (the board's nominal mass plus the point mass's reference), so `mu_total_mass_scale`, `sigma_total_mass_scale` and its correlations (boards.parquet keeps the board's own mass_scale). Prediction errors per mode label <l>: `eps_<l>` (relative standard deviation of the eigenvalue λ = ω², dimensionless) and `delta_<l>` (standard deviation of the unit-norm shape residual), when inferred. With the model-form discrepancy (the default, `--discrepancy-pct`): `discrepancy_scale` (its scale τ, relative eigenvalue), `discrepancy_unit_scale` (σ_u, the sd of the part that differs between boards, integrated out per board) and `discrepancy_<l>` (the updated mode's discrepancy d, common to every board: the model eigenvalue is λ (1 + d); orthogonal to what the board parameters can absorb).",
    open: true,
    columns: &[
        c("run", Col::Int32, false, "", "Independent SMC run (ArviZ chain)."),
        c("draw", Col::Int32, false, "", "Particle index within the run (ArviZ draw)."),
    ],
};

pub const BOARDS: TableSpec = TableSpec {
    name: "boards",
    doc: "Step-1 posterior draws of every board's parameters, one row per particle and board; one column per updated parameter, named with its unit (e.g. e_x_pa, e_y_pa, g_xy_pa, mass_scale); a refit with `--enrich added_mass` adds added_mass_kg (the lumped mass at the enrichment's point; mass_g then includes it, as the balance weighs it), one with `--enrich temperature_stiffness` temperature_coefficient_per_k. Where the sheet gave boards' thickness_mm (ingest's specimens.parquet), core_thickness_m (m): the board's core thickness, updated from its measurement and its frequencies.",
    open: true,
    columns: &[
        c("run", Col::Int32, false, "", "Independent SMC run (ArviZ chain)."),
        c("draw", Col::Int32, false, "", "Particle index within the run."),
        c("board_id", Col::Utf8, false, "", "Board."),
        c("mass_g", Col::Float64, false, "g", "Model mass of the board at this draw."),
    ],
};

pub const BOARDS_PHYSICAL: TableSpec = TableSpec {
    name: "boards_physical",
    doc: "Step-1 physical draws of every board's parameters, beside boards.parquet and with its columns, rows and draws, where step 1 inferred the model-form discrepancy or weighed the boards: each draw less what the data cannot inform, one draw of it per particle. The discrepancy's part the parameters absorb moves the boards' common centre (a: the population's physical means are the fitted ones less a), each board's deviation from the population mean is carried to the modes' sensitivities at that physical centre (the deviation there that moves the modes as the fitted one does), and the balance's common bias divides every mass scale. The summary's physical_q05/q50/q95 are these draws' quantiles; the fitted draws (boards.parquet) are the ones the predictions use. A contrast between boards (a board's value over the boards' mean) is to be read here.",
    open: true,
    columns: &[
        c("run", Col::Int32, false, "", "Independent SMC run (ArviZ chain)."),
        c("draw", Col::Int32, false, "", "Particle index within the run."),
        c("board_id", Col::Utf8, false, "", "Board."),
        c("mass_g", Col::Float64, false, "g", "Model mass of the board at this physical draw."),
    ],
};

pub const SUMMARY: TableSpec = TableSpec {
    name: "summary",
    doc: "Posterior summary, one row per parameter (and board or measurement where it has one): moments and quantiles over all runs' draws; rank-normalised split R-hat and bulk/tail ESS across runs (Vehtari et al. 2021, the definitions ArviZ uses).",
    open: false,
    columns: &[
        c("parameter", Col::Utf8, false, "", "Column name in population/boards (unit in the name)."),
        c("board_id", Col::Utf8, true, "", "Board, for per-board parameters."),
        c("measurement_id", Col::Utf8, true, "", "Measurement, for per-measurement parameters (none yet: step 2 is to come)."),
        c("mean", Col::Float64, false, "", "Posterior mean (unit of the parameter)."),
        c("sd", Col::Float64, false, "", "Posterior standard deviation."),
        c("q05", Col::Float64, false, "", "5 % quantile."),
        c("q50", Col::Float64, false, "", "Median."),
        c("q95", Col::Float64, false, "", "95 % quantile."),
        c("r_hat", Col::Float64, false, "", "Rank-normalised split R-hat across runs."),
        c("ess_bulk", Col::Float64, false, "", "Bulk effective sample size."),
        c("ess_tail", Col::Float64, false, "", "Tail effective sample size."),
        c("physical_q05", Col::Float64, true, "", "5 % quantile of the physical parameter: the draws less the model-form discrepancy's part that the parameters absorb, drawn from its prior at its scale τ (the data cannot inform it). Step 1 (a discrepancy in the likelihood): at the inferred τ, each board's deviation from the population mean carried to the modes' sensitivities at the physical centre (boards_physical.parquet holds these draws); the draws in population/boards are the fitted values, which reproduce the data together with the inferred discrepancy. Step 2 (none in the likelihood): at the cut scale's draw of τ (evidence.json `predictive_discrepancy`), the likelihood and predictions left as they are. Step 1 where boards were weighed: also the balance's error common to every board, drawn from its prior (`--balance-bias`), which divides every mass scale, the moduli of a per-mass population and the masses by 1 + β (each board's mass term holds only its readings' own precision). A physical value lies within these wider bounds. Null without either (no discrepancy, cut scale or weighed board)."),
        c("physical_q50", Col::Float64, true, "", "Median of the physical parameter (see physical_q05)."),
        c("physical_q95", Col::Float64, true, "", "95 % quantile of the physical parameter (see physical_q05)."),
    ],
};

pub const STAGES: TableSpec = TableSpec {
    name: "stages",
    doc: "The tempering path: one row per SMC run and tempering stage.",
    open: false,
    columns: &[
        c("run", Col::Int32, false, "", "Independent SMC run."),
        c("stage", Col::Int32, false, "", "Tempering stage, 1-based."),
        c(
            "beta",
            Col::Float64,
            false,
            "",
            "Inverse temperature after the stage.",
        ),
        c(
            "ess",
            Col::Float64,
            false,
            "",
            "Effective sample size of the incremental weights, particles.",
        ),
        c(
            "log_evidence_increment",
            Col::Float64,
            false,
            "",
            "log mean of the incremental weights.",
        ),
        c(
            "acceptance_unit",
            Col::Float64,
            true,
            "",
            "Acceptance rate of the per-unit moves.",
        ),
        c(
            "acceptance_global",
            Col::Float64,
            true,
            "",
            "Acceptance rate of the centred population moves.",
        ),
        c(
            "acceptance_noncentred",
            Col::Float64,
            true,
            "",
            "Acceptance rate of the non-centred population moves.",
        ),
        c(
            "acceptance_rescale",
            Col::Float64,
            true,
            "",
            "Acceptance rate of the moves that scale one mode's prediction-error scale together with the units' residuals of that mode (null where no error scale is inferred).",
        ),
        c("mutation_steps", Col::Int32, false, "", "Mutation sweeps."),
        c(
            "unique_after_resampling",
            Col::Int32,
            false,
            "",
            "Distinct particles after resampling.",
        ),
        c(
            "model_evals",
            Col::Float64,
            false,
            "",
            "Model evaluations of the stage (ROM or verified surrogate).",
        ),
        c(
            "screened_out",
            Col::Float64,
            false,
            "",
            "Proposals the delayed-acceptance screen rejected without a model evaluation (where a surrogate's extrapolation stood in for the ROM beyond the surrogate's box).",
        ),
        c(
            "kind",
            Col::Utf8,
            false,
            "",
            "`temper`: a tempering stage; `correct`: the final correction from the surrogates to the ROM at β = 1 (weights L_ROM / L_surrogate, the ROM solved in each unit's verified subspace inside its box, resampling, and mutation under the ROM only when resampling left fewer than 98 % of the particles distinct).",
        ),
    ],
};

pub const RESIDUALS: TableSpec = TableSpec {
    name: "residuals",
    doc: "Measured vs posterior-predictive model modes, one row per measurement and accepted paired mode of the step's setup (updating and validation modes).",
    open: false,
    columns: &[
        c("measurement_id", Col::Utf8, false, "", "Measurement."),
        c("board_id", Col::Utf8, false, "", "Board."),
        c("setup", Col::Utf8, false, "", "`free` or `bolted`."),
        c("label", Col::Utf8, false, "", "Mode label (from pair)."),
        c("freq_hz", Col::Float64, false, "Hz", "Identified frequency."),
        c("model_freq_hz_mean", Col::Float64, false, "Hz", "Posterior mean of the model frequency of this board/measurement."),
        c("model_freq_hz_sd", Col::Float64, false, "Hz", "Posterior standard deviation of the model frequency (parameter uncertainty)."),
        c("predictive_sd_hz", Col::Float64, false, "Hz", "Posterior-predictive standard deviation of a measurement: parameter uncertainty, for updated modes the inferred prediction error, and (step 1 with its model-error term each board's own, evidence.json's model_error.per_board) the model error's prior spread of the label."),
        c("rel_residual", Col::Float64, false, "", "(freq_hz - model_freq_hz_mean) / model_freq_hz_mean."),
        c("std_residual", Col::Float64, false, "", "(freq_hz - model_freq_hz_mean) / predictive_sd_hz."),
        c("mac", Col::Float64, true, "", "MAC of the measured shape and the model shape (posterior mean); null without a usable shape."),
        c("used_for_updating", Col::Bool, false, "", "The mode's label was used for updating."),
    ],
};

pub fn read_masses(path: &Path) -> anyhow::Result<BTreeMap<String, MassRow>> {
    let mut out = BTreeMap::new();
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let (bid, m, n, s, r, inc) = (
            c.str("board_id")?,
            c.f64("mass_g")?,
            c.i32("n_stable")?,
            c.f64("std_g")?,
            c.f64("resolution_g")?,
            c.bool("inconsistent")?,
        );
        let (days, ss, share) = (
            c.i32("n_days")?,
            c.f64("day_means_ss_g2")?,
            c.f64("day_share_sq_sum")?,
        );
        for i in 0..b.num_rows() {
            out.insert(
                bid.value(i).to_string(),
                MassRow {
                    mass_g: m.value(i),
                    n_stable: n.value(i),
                    std_g: s.value(i),
                    resolution_g: r.value(i),
                    inconsistent: inc.value(i),
                    n_days: days.value(i),
                    day_means_ss_g2: ss.value(i),
                    day_share_sq_sum: share.value(i),
                },
            );
        }
    }
    Ok(out)
}

/// Each board's measured overall thickness from ingest's specimens.parquet, m (boards the
/// sheet gives none for are absent; no table: empty).
pub fn read_specimen_thickness(path: &Path) -> anyhow::Result<BTreeMap<String, f64>> {
    let mut out = BTreeMap::new();
    if !path.is_file() {
        return Ok(out);
    }
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let (bid, h) = (c.str("board_id")?, c.f64("thickness_mm")?);
        for i in 0..b.num_rows() {
            if arrow::array::Array::is_valid(h, i) {
                out.insert(bid.value(i).to_string(), 1e-3 * h.value(i));
            }
        }
    }
    Ok(out)
}

pub fn provenance(stage: &str, fingerprint: &str) -> BTreeMap<String, String> {
    BTreeMap::from([
        ("hbmu.stage".to_string(), stage.to_string()),
        ("hbmu.fingerprint".to_string(), fingerprint.to_string()),
        (
            "hbmu.version".to_string(),
            crate::io::manifest::TOOL_VERSION.to_string(),
        ),
        ("hbmu.campaign".to_string(), String::new()),
    ])
}

/// Write a table of `spec` with extra float columns (name, unit) after the spec's columns.
pub fn write_table(
    path: &Path,
    spec: &TableSpec,
    mut cols: Vec<ArrayRef>,
    extra: &[(String, String, Vec<f64>)],
    prov: &BTreeMap<String, String>,
) -> anyhow::Result<()> {
    let fields: Vec<Field> = extra
        .iter()
        .map(|(n, u, _)| {
            let mut md = std::collections::HashMap::new();
            if !u.is_empty() {
                md.insert("unit".to_string(), u.clone());
            }
            Field::new(n, DataType::Float64, false).with_metadata(md)
        })
        .collect();
    let mut md = tables::table_metadata(spec, prov);
    let mut units = spec.units();
    for (n, u, _) in extra {
        if !u.is_empty() {
            units.insert(n.clone(), u.clone());
        }
    }
    md.insert("hbmu.units".into(), serde_json::to_string(&units)?);
    let schema = spec.schema(&fields, &md);
    for (_, _, v) in extra {
        cols.push(Arc::new(Float64Array::from(v.clone())));
    }
    tables::write_parquet(path, &tables::batch(schema, cols)?)?;
    Ok(())
}

pub fn write_draws(
    path: &Path,
    spec: &TableSpec,
    t: &DrawTable,
    with_key: bool,
    prov: &BTreeMap<String, String>,
) -> anyhow::Result<()> {
    let mut cols: Vec<ArrayRef> = vec![
        Arc::new(Int32Array::from(t.run.clone())),
        Arc::new(Int32Array::from(t.draw.clone())),
    ];
    if with_key {
        cols.push(Arc::new(StringArray::from_iter_values(
            t.key.iter().map(|k| k.as_deref().unwrap_or("")),
        )));
    }
    // Spec float columns are taken from the table by name, the rest are extra.
    let spec_names: Vec<&str> = spec.columns.iter().map(|c| c.name).collect();
    let mut extra = vec![];
    for col in &t.cols {
        if spec_names.contains(&col.0.as_str()) {
            cols.push(Arc::new(Float64Array::from(col.2.clone())));
        } else {
            extra.push(col.clone());
        }
    }
    write_table(path, spec, cols, &extra, prov)
}

pub fn write_summary(
    path: &Path,
    rows: &[SummaryRow],
    prov: &BTreeMap<String, String>,
) -> anyhow::Result<()> {
    let f = |g: fn(&crate::bayes::diagnostics::Summary) -> f64| -> ArrayRef {
        Arc::new(Float64Array::from_iter_values(rows.iter().map(|r| g(&r.s))))
    };
    let mut cols: Vec<ArrayRef> = vec![
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|r| r.parameter.as_str()),
        )),
        Arc::new(StringArray::from_iter(
            rows.iter().map(|r| r.board_id.as_deref()),
        )),
        Arc::new(StringArray::from_iter(
            rows.iter().map(|r| r.measurement_id.as_deref()),
        )),
        f(|s| s.mean),
        f(|s| s.sd),
        f(|s| s.q05),
        f(|s| s.q50),
        f(|s| s.q95),
        f(|s| s.r_hat),
        f(|s| s.ess_bulk),
        f(|s| s.ess_tail),
    ];
    for g in [
        (|s: &crate::bayes::diagnostics::Summary| s.q05) as fn(&_) -> f64,
        |s| s.q50,
        |s| s.q95,
    ] {
        cols.push(Arc::new(Float64Array::from_iter(
            rows.iter().map(|r| r.physical.as_ref().map(g)),
        )));
    }
    write_table(path, &SUMMARY, cols, &[], prov)
}

pub fn write_stages(
    path: &Path,
    st: &[StageInfo],
    prov: &BTreeMap<String, String>,
) -> anyhow::Result<()> {
    let nan_null = |v: f64| if v.is_finite() { Some(v) } else { None };
    let cols: Vec<ArrayRef> = vec![
        Arc::new(Int32Array::from_iter_values(
            st.iter().map(|s| s.run as i32),
        )),
        Arc::new(Int32Array::from_iter_values(
            st.iter().map(|s| s.stage as i32),
        )),
        Arc::new(Float64Array::from_iter_values(st.iter().map(|s| s.beta))),
        Arc::new(Float64Array::from_iter_values(st.iter().map(|s| s.ess))),
        Arc::new(Float64Array::from_iter_values(
            st.iter().map(|s| s.log_evidence_increment),
        )),
        Arc::new(Float64Array::from_iter(
            st.iter().map(|s| nan_null(s.acceptance_unit)),
        )),
        Arc::new(Float64Array::from_iter(
            st.iter().map(|s| nan_null(s.acceptance_global)),
        )),
        Arc::new(Float64Array::from_iter(
            st.iter().map(|s| nan_null(s.acceptance_noncentred)),
        )),
        Arc::new(Float64Array::from_iter(
            st.iter().map(|s| nan_null(s.acceptance_rescale)),
        )),
        Arc::new(Int32Array::from_iter_values(
            st.iter().map(|s| s.sweeps as i32),
        )),
        Arc::new(Int32Array::from_iter_values(
            st.iter().map(|s| s.unique_after_resampling as i32),
        )),
        Arc::new(Float64Array::from_iter_values(
            st.iter().map(|s| s.model_evals as f64),
        )),
        Arc::new(Float64Array::from_iter_values(
            st.iter().map(|s| s.screened_out as f64),
        )),
        Arc::new(StringArray::from_iter_values(st.iter().map(|s| s.kind))),
    ];
    write_table(path, &STAGES, cols, &[], prov)
}

pub fn write_residuals(
    path: &Path,
    rows: &[Residual],
    prov: &BTreeMap<String, String>,
) -> anyhow::Result<()> {
    let cols: Vec<ArrayRef> = vec![
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|r| r.measurement_id.as_str()),
        )),
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|r| r.board_id.as_str()),
        )),
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|r| r.setup.as_str()),
        )),
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|r| r.label.as_str()),
        )),
        Arc::new(Float64Array::from_iter_values(
            rows.iter().map(|r| r.freq_hz),
        )),
        Arc::new(Float64Array::from_iter_values(rows.iter().map(|r| r.mean))),
        Arc::new(Float64Array::from_iter_values(rows.iter().map(|r| r.sd))),
        Arc::new(Float64Array::from_iter_values(
            rows.iter().map(|r| r.pred_sd),
        )),
        Arc::new(Float64Array::from_iter_values(
            rows.iter().map(|r| (r.freq_hz - r.mean) / r.mean),
        )),
        Arc::new(Float64Array::from_iter_values(
            rows.iter().map(|r| (r.freq_hz - r.mean) / r.pred_sd),
        )),
        Arc::new(Float64Array::from_iter(rows.iter().map(|r| r.mac))),
        Arc::new(BooleanArray::from_iter(rows.iter().map(|r| Some(r.used)))),
    ];
    write_table(path, &RESIDUALS, cols, &[], prov)
}

/// The rows of a residuals.parquet ([`RESIDUALS`]), as [`write_residuals`] takes them.
pub fn read_residual_rows(path: &Path) -> anyhow::Result<Vec<Residual>> {
    let mut out = vec![];
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let (m, bid, setup, label) = (
            c.str("measurement_id")?,
            c.str("board_id")?,
            c.str("setup")?,
            c.str("label")?,
        );
        let (f, mean, sd, psd, mac, used) = (
            c.f64("freq_hz")?,
            c.f64("model_freq_hz_mean")?,
            c.f64("model_freq_hz_sd")?,
            c.f64("predictive_sd_hz")?,
            c.f64("mac")?,
            c.bool("used_for_updating")?,
        );
        for i in 0..b.num_rows() {
            out.push(Residual {
                measurement_id: m.value(i).to_string(),
                board_id: bid.value(i).to_string(),
                setup: setup.value(i).to_string(),
                label: label.value(i).to_string(),
                freq_hz: f.value(i),
                mean: mean.value(i),
                sd: sd.value(i),
                pred_sd: psd.value(i),
                mac: arrow::array::Array::is_valid(mac, i).then(|| mac.value(i)),
                used: used.value(i),
            });
        }
    }
    Ok(out)
}

/// The `enrichment` of a step-1 refit's evidence.json (null for the baseline).
pub fn read_step1_enrichment(path: &Path) -> anyhow::Result<serde_json::Value> {
    Ok(crate::io::read_json(path)?["enrichment"].clone())
}

pub fn read_step1(path: &Path) -> anyhow::Result<Step1> {
    let batches = tables::read_parquet(path)?;
    let Some(first) = batches.first() else {
        bail!("{}: no rows: the step-1 posterior is empty", path.display());
    };
    let (coefs, params): (Vec<String>, Vec<String>) = first
        .schema()
        .fields()
        .iter()
        .filter(|f| f.data_type() == &DataType::Float64 && f.name() != "mass_g")
        .map(|f| f.name().clone())
        .partition(|n| crate::diagnose::library::is_board_coefficient(n));
    if params.is_empty() {
        bail!(
            "{}: no parameter columns (expected e.g. e_x_pa, mass_scale)",
            path.display()
        );
    }
    let mut by: BTreeMap<(i32, i32), BTreeMap<String, Vec<f64>>> = BTreeMap::new();
    let mut board_ids: BTreeSet<String> = BTreeSet::new();
    for b in &batches {
        let c = Cols { batch: b, path };
        let (run, draw, bid) = (c.i32("run")?, c.i32("draw")?, c.str("board_id")?);
        let cols: Vec<&Float64Array> = params
            .iter()
            .chain(&coefs)
            .map(|p| c.f64(p))
            .collect::<Result<_, _>>()?;
        for i in 0..b.num_rows() {
            board_ids.insert(bid.value(i).to_string());
            by.entry((run.value(i), draw.value(i))).or_default().insert(
                bid.value(i).to_string(),
                cols.iter().map(|a| a.value(i)).collect(),
            );
        }
    }
    let board_ids: Vec<String> = board_ids.into_iter().collect();
    let mut draws = vec![];
    for (k, m) in by {
        let mut v = Vec::with_capacity(board_ids.len() * params.len());
        for bid in &board_ids {
            let Some(x) = m.get(bid) else {
                bail!(
                    "{}: draw (run {}, draw {}) has no row for board {bid}",
                    path.display(),
                    k.0,
                    k.1
                );
            };
            v.extend(x);
        }
        draws.push((k, v));
    }
    Ok(Step1 {
        board_ids,
        params,
        coefs,
        draws,
    })
}

/// The numeric column `column` of measurements.parquet per measurement, in file order (`None`
/// where it has no finite value): the covariate of a temperature enrichment.
pub fn read_covariate(path: &Path, column: &str) -> anyhow::Result<Vec<(String, Option<f64>)>> {
    let mut out = vec![];
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let mid = c.str("measurement_id")?;
        let col = b.column_by_name(column).ok_or_else(|| {
            anyhow!(
                "{}: no column {column:?} (the covariate of the enrichment); columns: {}",
                path.display(),
                b.schema()
                    .fields()
                    .iter()
                    .map(|f| f.name().as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        })?;
        let col = arrow::compute::cast(col, &DataType::Float64).with_context(|| {
            format!(
                "{}: column {column:?} is not numeric (expected a number per measurement)",
                path.display()
            )
        })?;
        let a = col
            .as_any()
            .downcast_ref::<Float64Array>()
            .ok_or_else(|| anyhow!("{}: column {column:?}: expected float64", path.display()))?;
        for i in 0..b.num_rows() {
            let v = arrow::array::Array::is_valid(a, i) && a.value(i).is_finite();
            out.push((mid.value(i).to_string(), v.then(|| a.value(i))));
        }
    }
    Ok(out)
}

/// Step 2's population, joints, summary and stages tables in `out`; returns their paths.
pub fn write_joint_tables(
    out: &Path,
    t: &crate::update::joints::JointTables,
    results: &crate::update::sampler::Results,
    prov: &BTreeMap<String, String>,
) -> anyhow::Result<Vec<std::path::PathBuf>> {
    let (pop, jt) = (&t.pop, &t.jt);
    let mut outputs = vec![];
    let p = out.join("population.parquet");
    let cols: Vec<ArrayRef> = vec![
        Arc::new(Int32Array::from(pop.run.clone())),
        Arc::new(Int32Array::from(pop.draw.clone())),
        Arc::new(Int32Array::from(t.b_run.clone())),
        Arc::new(Int32Array::from(t.b_draw.clone())),
        Arc::new(Float64Array::from(pop.cols[0].2.clone())),
        Arc::new(Float64Array::from(pop.cols[1].2.clone())),
    ];
    write_table(&p, &POPULATION_JOINTS, cols, &pop.cols[2..], prov)?;
    outputs.push(p);
    let p = out.join("joints.parquet");
    let cols: Vec<ArrayRef> = vec![
        Arc::new(Int32Array::from(jt.run.clone())),
        Arc::new(Int32Array::from(jt.draw.clone())),
        Arc::new(StringArray::from_iter_values(
            jt.key.iter().map(|k| k.as_deref().unwrap_or("")),
        )),
        Arc::new(StringArray::from_iter_values(t.joint_boards.iter())),
        Arc::new(Float64Array::from(jt.cols[0].2.clone())),
    ];
    write_table(&p, &JOINTS, cols, &jt.cols[1..], prov)?;
    outputs.push(p);
    let p = out.join("summary.parquet");
    write_summary(&p, &t.summary, prov)?;
    outputs.push(p);
    let stages: Vec<StageInfo> = results.iter().flat_map(|r| r.stages.clone()).collect();
    let p = out.join("stages.parquet");
    write_stages(&p, &stages, prov)?;
    outputs.push(p);
    Ok(outputs)
}

/// The rows of an update step's residuals.parquet as the later stages use them: its relative
/// and standardized residuals as [`write_residuals`] forms them.
pub fn read_residuals(path: &Path) -> anyhow::Result<Vec<ResidualObs>> {
    Ok(read_residual_rows(path)?
        .into_iter()
        .map(|r| ResidualObs {
            rel_residual: (r.freq_hz - r.mean) / r.mean,
            std_residual: (r.freq_hz - r.mean) / r.pred_sd,
            measurement_id: r.measurement_id,
            board_id: r.board_id,
            setup: r.setup,
            label: r.label,
            freq_hz: r.freq_hz,
            model_freq_hz_mean: r.mean,
            predictive_sd_hz: r.pred_sd,
            used_for_updating: r.used,
            mac: r.mac,
        })
        .collect())
}

/// One row of step 2's `population.parquet` as the per-assembly screen reads it: the step-1
/// draw the particle carried, the population of ln k_con, and per mode of `labels` the error
/// scales (None where the column is absent: the scale was fixed) and the discrepancy.
#[derive(Clone, Debug)]
pub struct JointPopulationRow {
    pub boards_run: i32,
    pub boards_draw: i32,
    pub mu_ln_k_con: f64,
    pub sigma_ln_k_con: f64,
    pub eps: Option<Vec<f64>>,
    pub delta: Option<Vec<f64>>,
    pub bias: Option<Vec<f64>>,
    pub discrepancy_unit_scale: Option<f64>,
}

/// `count` rows of step 2's `population.parquet` at `path`, evenly spaced over the file
/// (every row where it has fewer); `labels` the modes whose columns are read.
pub fn read_joint_population(
    path: &Path,
    labels: &[String],
    count: usize,
) -> anyhow::Result<Vec<JointPopulationRow>> {
    let batches = tables::read_parquet(path)?;
    let mut rows = vec![];
    for b in &batches {
        let c = Cols { batch: b, path };
        let has = |n: &str| b.schema().field_with_name(n).is_ok();
        let per_mode = |prefix: &str| -> anyhow::Result<Option<Vec<&Float64Array>>> {
            let names: Vec<String> = labels.iter().map(|l| format!("{prefix}_{l}")).collect();
            let present = names.iter().filter(|n| has(n)).count();
            if present == 0 {
                return Ok(None);
            }
            if present < names.len() {
                bail!(
                    "{}: has some {prefix}_<mode> columns but not every one of {}",
                    path.display(),
                    names.join(", ")
                );
            }
            Ok(Some(
                names.iter().map(|n| c.f64(n)).collect::<Result<_, _>>()?,
            ))
        };
        let (run, draw) = (c.i32("boards_run")?, c.i32("boards_draw")?);
        let (mu, sigma) = (c.f64("mu_ln_k_con")?, c.f64("sigma_ln_k_con")?);
        let (eps, delta, bias) = (
            per_mode("eps")?,
            per_mode("delta")?,
            per_mode("discrepancy")?,
        );
        let unit = if has("discrepancy_unit_scale") {
            Some(c.f64("discrepancy_unit_scale")?)
        } else {
            None
        };
        let at = |cols: &Option<Vec<&Float64Array>>, i: usize| -> Option<Vec<f64>> {
            cols.as_ref()
                .map(|v| v.iter().map(|a| a.value(i)).collect())
        };
        for i in 0..b.num_rows() {
            rows.push(JointPopulationRow {
                boards_run: run.value(i),
                boards_draw: draw.value(i),
                mu_ln_k_con: mu.value(i),
                sigma_ln_k_con: sigma.value(i),
                eps: at(&eps, i),
                delta: at(&delta, i),
                bias: at(&bias, i),
                discrepancy_unit_scale: unit.map(|a| a.value(i)),
            });
        }
    }
    if rows.is_empty() {
        bail!("{}: no rows: step 2's posterior is empty", path.display());
    }
    let n = rows.len();
    let k = count.min(n).max(1);
    Ok((0..k)
        .map(|i| rows[(i * n + n / (2 * k)) / k % n].clone())
        .collect())
}

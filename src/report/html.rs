//! The validation report as one self-contained HTML page and a Markdown summary (pure: from
//! plain data to strings; `stage::report` reads the artifacts and writes the files).
//!
//! Figures are inline SVG (no network, no script); every table cell that carries a number
//! has it at full precision in `data-value` (Rust's shortest round-trip formatting) next to
//! the rounded text, so a reader (and the browser test) can compare it with the Parquet
//! table it comes from. Nothing time-dependent goes into the page.

use super::figures::{self, BoxItem};
use super::plots::PlotError;
use super::validation::{Interval, Table2Row};
use std::collections::BTreeMap;
use std::fmt::Write;

/// One stage's posterior, as the report shows it.
#[derive(Clone, Debug, Default)]
pub struct StepData {
    /// "boards (step 1)" or "joints (step 2)".
    pub name: String,
    /// Population columns (name, draws), run/draw excluded.
    pub population: Vec<(String, Vec<f64>)>,
    /// Per-unit draws: (parameter, unit id, draws).
    pub units: Vec<(String, String, Vec<f64>)>,
    pub summary: Vec<SummaryRow>,
    /// Tempering path per run: (stage, β, ESS).
    pub stages: Vec<Vec<(f64, f64, f64)>>,
    pub evidence: serde_json::Value,
}

/// One row of summary.parquet.
#[derive(Clone, Debug)]
pub struct SummaryRow {
    pub parameter: String,
    pub unit: Option<String>,
    pub mean: f64,
    pub sd: f64,
    pub q05: f64,
    pub q50: f64,
    pub q95: f64,
    pub r_hat: f64,
    pub ess_bulk: f64,
    pub ess_tail: f64,
    /// The physical parameter's 90 % bounds (NaN where there are none: summary.parquet).
    pub physical_q05: f64,
    pub physical_q95: f64,
}

/// A finding to show.
#[derive(Clone, Debug)]
pub struct FindingRow {
    pub stage: String,
    pub severity: String,
    pub code: String,
    pub where_: String,
    pub message: String,
}

/// A stage's manifest, for the provenance section.
#[derive(Clone, Debug)]
pub struct Provenance {
    pub stage: String,
    pub manifest: String,
    pub tool_version: String,
    pub fingerprint: String,
    /// (path, blake3) of its outputs.
    pub outputs: Vec<(String, String)>,
}

/// Everything the page shows.
#[derive(Clone, Debug, Default)]
pub struct ReportData {
    pub title: String,
    pub tool_version: String,
    pub step1: StepData,
    pub step2: Option<StepData>,
    /// Why step 2 is absent, when it is.
    pub step2_absent: Option<String>,
    pub table2: Vec<Table2Row>,
    pub intervals: Vec<Interval>,
    /// Measured frequencies per (board, setup, label) for the boxes.
    pub measured: BTreeMap<(String, String, String), Vec<f64>>,
    pub propagate: serde_json::Value,
    /// (measurement id, kind, relative link).
    pub plot_links: Vec<(String, String, String)>,
    pub ingest_measurements: usize,
    pub quarantined: Vec<(String, String)>,
    /// The boards' measured dimensions (length, width, overall thickness, mm), when the sheet
    /// gave any (ingest's specimens.parquet).
    pub specimens: Vec<(String, [Option<f64>; 3])>,
    pub ingest_counts: BTreeMap<String, u64>,
    pub findings: Vec<FindingRow>,
    pub provenance: Vec<Provenance>,
    /// Inputs of the report itself: (path, blake3).
    pub inputs: Vec<(String, String)>,
    /// The diagnose stage's output (`diagnose/diagnosis.json`), when it ran.
    pub diagnosis: Option<super::diagnosis::DiagnosisData>,
}

/// What [`render`] produces.
pub struct Rendered {
    pub html: String,
    pub markdown: String,
    /// Number of figures in the page.
    pub figures: usize,
}

fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// A numeric cell: rounded text, the full value in `data-value`; NaN is an empty cell.
fn num(col: &str, v: f64, digits: usize) -> String {
    if v.is_finite() {
        format!("<td class=\"n\" data-col=\"{col}\" data-value=\"{v}\">{v:.digits$}</td>")
    } else {
        format!("<td class=\"n\" data-col=\"{col}\" data-value=\"\">–</td>")
    }
}

/// A numeric cell in scientific notation with `sig` significant digits.
fn sci(col: &str, v: f64, sig: usize) -> String {
    if v.is_finite() {
        let d = sig.saturating_sub(1);
        format!("<td class=\"n\" data-col=\"{col}\" data-value=\"{v}\">{v:.d$e}</td>")
    } else {
        format!("<td class=\"n\" data-col=\"{col}\" data-value=\"\">–</td>")
    }
}

fn int(col: &str, v: usize) -> String {
    format!("<td class=\"n\" data-col=\"{col}\" data-value=\"{v}\">{v}</td>")
}

fn txt(col: &str, v: &str) -> String {
    format!("<td data-col=\"{col}\" data-value=\"{0}\">{0}</td>", esc(v))
}

fn pct(x: f64) -> String {
    if x.is_finite() {
        format!("{:.1} %", 100.0 * x)
    } else {
        "–".into()
    }
}

/// Display scale and unit of a parameter from its name.
pub fn display_unit(name: &str) -> (f64, &'static str) {
    if name.ends_with("_pa") {
        (1e9, "GPa")
    } else if name.ends_with("_n_per_m") {
        (1e6, "MN/m")
    } else {
        (1.0, "")
    }
}

struct Page {
    body: String,
    figures: usize,
    toc: Vec<(String, String)>,
}

impl Page {
    fn section(&mut self, id: &str, title: &str) {
        self.toc.push((id.into(), title.into()));
        let _ = writeln!(self.body, "<h2 id=\"{id}\">{}</h2>", esc(title));
    }
    fn p(&mut self, html: &str) {
        let _ = writeln!(self.body, "<p>{html}</p>");
    }
    fn figure(&mut self, svg: Result<String, PlotError>, caption: &str) {
        match svg {
            Ok(s) => {
                self.figures += 1;
                let _ = writeln!(
                    self.body,
                    "<figure class=\"plot\" data-figure=\"{}\">{}<figcaption>{}</figcaption></figure>",
                    self.figures,
                    s.trim(),
                    caption
                );
            }
            Err(e) => self.p(&format!(
                "<strong>figure not drawn:</strong> {}",
                esc(&e.to_string())
            )),
        }
    }
}

const CSS: &str = "body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;max-width:1100px;margin:0 auto;padding:1em;color:#222;line-height:1.45}
h1{font-size:1.6em}h2{border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:2em}
table{border-collapse:collapse;margin:.8em 0;font-size:.9em;display:block;overflow-x:auto;max-width:100%}
th,td{border:1px solid #ccc;padding:.25em .5em;white-space:nowrap}th{background:#f0f0f0}td.n{text-align:right;font-variant-numeric:tabular-nums}
figure.plot{margin:1em 0}figure.plot svg{max-width:100%;height:auto;display:block}figcaption{font-size:.9em;color:#444}
.bad{color:#a00;font-weight:600}.ok{color:#060}code{background:#f4f4f4;padding:0 .2em}
.verdict{border:2px solid #888;border-radius:4px;padding:.2em 1em;background:#fafafa;font-size:1.05em}
.grid{display:flex;flex-wrap:wrap;gap:1em}.grid figure{flex:1 1 480px}
nav ul{columns:2}@media print{nav{display:none}figure{break-inside:avoid}}";

/// Render the page and the Markdown summary.
pub fn render(d: &ReportData) -> Rendered {
    let mut pg = Page {
        body: String::new(),
        figures: 0,
        toc: vec![],
    };
    let mut md = String::new();
    let _ = writeln!(md, "# {}\n", d.title);
    let _ = writeln!(
        md,
        "hbmu {} — validation report (open `report.html` for figures).\n",
        d.tool_version
    );

    summary_section(&mut pg, &mut md, d);
    diagnosis_section(&mut pg, &mut md, d.diagnosis.as_ref());
    table2_section(&mut pg, &mut md, d);
    figure6_section(&mut pg, d);
    for step in std::iter::once(&d.step1).chain(d.step2.as_ref()) {
        posterior_section(&mut pg, step);
    }
    diagnostics_section(&mut pg, &mut md, d);
    propagation_section(&mut pg, d);
    findings_section(&mut pg, &mut md, d);
    plots_section(&mut pg, d);
    provenance_section(&mut pg, &mut md, d);
    let html = page_html(d, &pg);
    Rendered {
        html,
        markdown: md,
        figures: pg.figures,
    }
}

/// The summary: coverage of the predicted 90 % intervals per setup and scope.
fn summary_section(pg: &mut Page, md: &mut String, d: &ReportData) {
    pg.section("summary", "Summary");
    let cov = |scope: &str, setup: &str, updating: Option<bool>| {
        super::validation::coverage(d.intervals.iter().filter(|i| {
            i.scope == scope
                && i.setup == setup
                && updating.is_none_or(|u| i.used_for_updating == u)
        }))
    };
    let mut rows = vec![];
    for setup in ["free", "bolted"] {
        for (what, scope, upd) in [
            ("validation modes, own board", "board", Some(false)),
            ("updating modes, own board", "board", Some(true)),
            ("all modes, new board", "new_board", None),
        ] {
            let (k, n) = cov(scope, setup, upd);
            if n > 0 {
                rows.push((setup, what, k, n));
            }
        }
        let (k, n) = super::validation::held_out_coverage(
            d.intervals
                .iter()
                .filter(|i| i.scope == "board" && i.setup == setup && i.used_for_updating),
        );
        if n > 0 {
            rows.push((
                setup,
                "updating modes, own board, held-out measurements",
                k,
                n,
            ));
        }
        let (k, n) = super::validation::held_out_coverage(
            d.intervals
                .iter()
                .filter(|i| i.scope == "new_board" && i.setup == setup),
        );
        if n > 0 {
            rows.push((setup, "all modes, new board, held-out boards", k, n));
        }
    }
    // Boards the population was learnt from: the new board's interval covers them more
    // often than 90 % (they are in-sample); the reference rate for their number.
    let n_boards = d
        .intervals
        .iter()
        .filter(|i| i.scope == "board" && i.setup == "free")
        .filter_map(|i| i.board_id.as_deref())
        .collect::<std::collections::BTreeSet<_>>()
        .len();
    let in_sample = super::validation::in_sample_coverage_90(n_boards);
    let mut t = String::from("<table data-table=\"coverage\"><tr><th>setup</th><th>predicted 90 % interval</th><th>measurements inside</th><th>measurements</th><th>coverage</th></tr>\n");
    let _ = writeln!(md, "## Coverage of the predicted 90 % intervals\n\n| setup | interval | inside | measurements | coverage |\n|---|---|---:|---:|---:|");
    for (setup, what, k, n) in &rows {
        let _ = writeln!(
            t,
            "<tr>{}{}{}{}<td class=\"n\">{}</td></tr>",
            txt("setup", setup),
            txt("interval", what),
            int("inside", *k),
            int("measured", *n),
            pct(*k as f64 / *n as f64)
        );
        let _ = writeln!(
            md,
            "| {setup} | {what} | {k} | {n} | {} |",
            pct(*k as f64 / *n as f64)
        );
    }
    t.push_str("</table>");
    pg.p("The predicted 90 % interval (5 % to 95 % quantile of a predicted measurement: the model at posterior draws plus the mode's inferred prediction error) of each board and mode, against the measurements of that board; and the interval of a <em>new</em> board (parameters drawn from the population) against every board's measurements. A calibrated model covers about 90 % of measurements it was not updated with: a board's validation modes, a board's measurements held out of the updating (<code>update boards --hold-out-measurements</code>), and boards held out of it (<code>update boards --hold-out</code>). Its updating modes' own measurements are in-sample: the interval covers them more often.");
    if in_sample.is_finite() {
        let msg = format!(
            "The new-board interval is also compared with the {n_boards} boards the population was learnt from. Those are in-sample, so a calibrated hierarchy covers them more often than 90 %: about {} for {n_boards} boards drawn from a normal population (the classical predictive interval x̄ ± t s √(1 + 1/n)).",
            pct(in_sample)
        );
        pg.p(&esc(&msg));
        let _ = writeln!(md, "\n{msg}");
    }
    pg.body.push_str(&t);
    if let Some(why) = &d.step2_absent {
        pg.p(&format!(
            "<strong>Bolted predictions absent:</strong> {}",
            esc(why)
        ));
        let _ = writeln!(md, "\n**Bolted predictions absent:** {why}");
    }
    let _ = writeln!(md);
}

/// Measured against simulated frequencies per mode (the paper's Table 2).
fn table2_section(pg: &mut Page, md: &mut String, d: &ReportData) {
    pg.section(
        "table2",
        "Measured vs simulated frequencies (Table 2 analog)",
    );
    pg.p("Per mode: mean and standard deviation of every measurement of every board, each board weighted equally (a board measured n times gives each measurement 1/n of a board's weight), against the prediction for a new board from the posterior population (model frequency: mean and sd, the parameters' spread; model discrepancy: the model-form discrepancy's mean and sd in % of the frequency, common to every board; predictive sd: with the discrepancy and the prediction error). Errors are (simulated − measured) / measured, without and with the discrepancy. Validation modes were not used for updating.");
    let _ = writeln!(md, "## Measured vs simulated (Table 2 analog)\n\n| setup | mode | role | n | boards | measured mean [Hz] | measured sd [Hz] | simulated mean [Hz] | simulated sd [Hz] | predictive sd [Hz] | model discrepancy [%] | mean error [%] | mean error with discrepancy [%] | sd error [%] |\n|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    let mut t = String::from("<table data-table=\"table2\"><tr><th>setup</th><th>mode</th><th>role</th><th>n</th><th>boards</th><th>measured mean [Hz]</th><th>measured sd [Hz]</th><th>simulated mean [Hz]</th><th>simulated sd [Hz]</th><th>predictive sd [Hz]</th><th>model discrepancy [%]</th><th>discrepancy sd [%]</th><th>mean error [%]</th><th>mean error with discrepancy [%]</th><th>sd error [%]</th><th>own-board coverage</th><th>new-board coverage</th><th>held-out boards' coverage</th></tr>\n");
    for r in &d.table2 {
        let role = if r.used_for_updating {
            "updating"
        } else {
            "validation"
        };
        let _ = writeln!(
            t,
            "<tr>{}{}{}{}{}{}{}{}{}{}{}{}{}{}{}{}{}{}</tr>",
            txt("setup", &r.setup),
            txt("label", &r.label),
            txt("role", role),
            int("n_measured", r.n_measured),
            int("n_boards", r.n_boards),
            num("measured_mean_hz", r.measured_mean_hz, 2),
            num("measured_sd_hz", r.measured_sd_hz, 3),
            num("simulated_mean_hz", r.simulated_mean_hz, 2),
            num("simulated_sd_hz", r.simulated_sd_hz, 3),
            num("predictive_sd_hz", r.predictive_sd_hz, 3),
            num("discrepancy_mean_pct", r.discrepancy_mean_pct, 3),
            num("discrepancy_sd_pct", r.discrepancy_sd_pct, 3),
            num("mean_error_pct", r.mean_error_pct, 3),
            num(
                "mean_error_with_discrepancy_pct",
                r.mean_error_with_discrepancy_pct,
                3,
            ),
            num("sd_error_pct", r.sd_error_pct, 1),
            num("board_coverage_90", r.board_coverage_90, 3),
            num("new_board_coverage_90", r.new_board_coverage_90, 3),
            num("held_out_coverage_90", r.held_out_coverage_90, 3),
        );
        let _ = writeln!(
            md,
            "| {} | {} | {role} | {} | {} | {:.2} | {:.3} | {:.2} | {:.3} | {:.3} | {:.3} ± {:.3} | {:.3} | {:.3} | {:.1} |",
            r.setup,
            r.label,
            r.n_measured,
            r.n_boards,
            r.measured_mean_hz,
            r.measured_sd_hz,
            r.simulated_mean_hz,
            r.simulated_sd_hz,
            r.predictive_sd_hz,
            r.discrepancy_mean_pct,
            r.discrepancy_sd_pct,
            r.mean_error_pct,
            r.mean_error_with_discrepancy_pct,
            r.sd_error_pct
        );
    }
    t.push_str("</table>");
    pg.body.push_str(&t);
    let _ = writeln!(md);
}

/// The predicted distributions per board and setup with the measurements (the paper's
/// Figure 6), and every interval.
fn figure6_section(pg: &mut Page, d: &ReportData) {
    pg.section(
        "figure6",
        "Predicted distributions per board (Figure 6 analog)",
    );
    pg.p("Per board and setup: box = predicted lower to upper quartile, whiskers = 5 % and 95 %, bar = median (of a predicted measurement), on a relative axis; measurements overlaid: <span style=\"color:#005aa0\">●</span> updating modes, <span style=\"color:#c85000\">△</span> validation modes. The table below lists every interval in Hz.");
    let mut keys: Vec<(String, Option<String>)> = d
        .intervals
        .iter()
        .map(|i| (i.setup.clone(), i.board_id.clone()))
        .collect();
    keys.sort_by(|a, b| (a.0 != "free", &a.1).cmp(&(b.0 != "free", &b.1)));
    keys.dedup();
    pg.body.push_str("<div class=\"grid\">");
    for (setup, board) in &keys {
        let items: Vec<BoxItem> = d
            .intervals
            .iter()
            .filter(|i| &i.setup == setup && &i.board_id == board)
            .map(|i| BoxItem {
                label: i.label.clone(),
                q05: i.q05_hz,
                q25: i.q25_hz,
                q50: i.q50_hz,
                q75: i.q75_hz,
                q95: i.q95_hz,
                measured: match board {
                    Some(b) => d
                        .measured
                        .get(&(b.clone(), setup.clone(), i.label.clone()))
                        .cloned()
                        .unwrap_or_default(),
                    None => d
                        .measured
                        .iter()
                        .filter(|((_, s, l), _)| s == setup && *l == i.label)
                        .flat_map(|(_, v)| v.iter().copied())
                        .collect(),
                },
                used_for_updating: i.used_for_updating,
            })
            .collect();
        let who = board
            .clone()
            .unwrap_or_else(|| "new board (all boards' measurements)".into());
        let setup_name = if setup == "free" {
            "free-free"
        } else {
            "bolted"
        };
        pg.figure(
            figures::boxes_svg(&format!("{who}, {setup_name}"), &items),
            &format!(
                "{}, {setup_name}: predicted distribution per mode and measurements.",
                esc(&who)
            ),
        );
    }
    pg.body.push_str("</div>");
    let mut t = String::from("<details><summary>Every predicted interval (Hz)</summary><table data-table=\"intervals\"><tr><th>scope</th><th>board</th><th>setup</th><th>mode</th><th>draws</th><th>model mean</th><th>model sd</th><th>q05</th><th>q25</th><th>q50</th><th>q75</th><th>q95</th><th>measured</th><th>inside 90 %</th></tr>\n");
    for i in &d.intervals {
        let _ = writeln!(
            t,
            "<tr>{}{}{}{}{}{}{}{}{}{}{}{}{}{}</tr>",
            txt("scope", &i.scope),
            txt("board_id", i.board_id.as_deref().unwrap_or("")),
            txt("setup", &i.setup),
            txt("label", &i.label),
            int("n_draws", i.n_draws),
            num("model_mean_hz", i.model_mean_hz, 2),
            num("model_sd_hz", i.model_sd_hz, 3),
            num("q05_hz", i.q05_hz, 2),
            num("q25_hz", i.q25_hz, 2),
            num("q50_hz", i.q50_hz, 2),
            num("q75_hz", i.q75_hz, 2),
            num("q95_hz", i.q95_hz, 2),
            int("n_measured", i.n_measured),
            int("n_inside_90", i.n_inside_90),
        );
    }
    t.push_str("</table></details>");
    pg.body.push_str(&t);
}

/// Sampler diagnostics and evidence per step: tempering paths, evidence, R-hat, ESS and
/// the posterior summary.
fn diagnostics_section(pg: &mut Page, md: &mut String, d: &ReportData) {
    pg.section("diagnostics", "Sampler diagnostics and evidence");
    let _ = writeln!(md, "## Sampler\n");
    for step in std::iter::once(&d.step1).chain(d.step2.as_ref()) {
        let runs: Vec<Vec<(f64, f64)>> = step
            .stages
            .iter()
            .map(|r| r.iter().map(|(s, b, _)| (*s, *b)).collect())
            .collect();
        pg.figure(
            figures::tempering_svg(&format!("Tempering path, {}", step.name), &runs),
            &format!(
                "Tempering path of every independent SMC run, {} (β = 1: the posterior).",
                esc(&step.name)
            ),
        );
        let ev = &step.evidence;
        let f = |k: &str| ev.get(k).and_then(|v| v.as_f64()).unwrap_or(f64::NAN);
        let runs_z: Vec<String> = ev
            .get("log_evidence_runs")
            .and_then(|v| v.as_array())
            .map(|a| {
                a.iter()
                    .filter_map(|x| x.as_f64())
                    .map(|x| format!("{x:.2}"))
                    .collect()
            })
            .unwrap_or_default();
        let max_rhat = step
            .summary
            .iter()
            .map(|r| r.r_hat)
            .fold(f64::NAN, f64::max);
        let min_ess = step
            .summary
            .iter()
            .map(|r| r.ess_bulk.min(r.ess_tail))
            .fold(f64::NAN, f64::min);
        let rhat_class = if max_rhat <= 1.01 { "ok" } else { "bad" };
        pg.p(&format!(
            "<strong>{}</strong>: log evidence {:.2} ± {:.2} (standard error over {} runs: {}); largest R-hat <span class=\"{rhat_class}\">{:.4}</span>, smallest bulk/tail ESS {:.0}. Stages per run: {}.",
            esc(&step.name),
            f("log_evidence_mean"),
            f("log_evidence_standard_error"),
            runs_z.len(),
            runs_z.join(", "),
            max_rhat,
            min_ess,
            step.stages.iter().map(|r| r.len().to_string()).collect::<Vec<_>>().join(", ")
        ));
        let _ = writeln!(
            md,
            "- {}: log evidence {:.2} ± {:.2} ({} runs); max R-hat {:.4}; min ESS {:.0}",
            step.name,
            f("log_evidence_mean"),
            f("log_evidence_standard_error"),
            runs_z.len(),
            max_rhat,
            min_ess
        );
        let mut t = format!("<details><summary>Posterior summary, {} ({} rows)</summary><table data-table=\"summary\"><tr><th>parameter</th><th>board / measurement</th><th>mean</th><th>sd</th><th>q05</th><th>q50</th><th>q95</th><th title=\"The physical parameter: the draws less the part of the model-form discrepancy the parameters absorb\">physical q05</th><th>physical q95</th><th>R-hat</th><th>ESS bulk</th><th>ESS tail</th></tr>\n", esc(&step.name), step.summary.len());
        for r in &step.summary {
            let _ = writeln!(
                t,
                "<tr>{}{}{}{}{}{}{}{}{}{}{}{}</tr>",
                txt("parameter", &r.parameter),
                txt("unit", r.unit.as_deref().unwrap_or("")),
                sci("mean", r.mean, 6),
                sci("sd", r.sd, 3),
                sci("q05", r.q05, 6),
                sci("q50", r.q50, 6),
                sci("q95", r.q95, 6),
                sci("physical_q05", r.physical_q05, 6),
                sci("physical_q95", r.physical_q95, 6),
                num("r_hat", r.r_hat, 4),
                num("ess_bulk", r.ess_bulk, 0),
                num("ess_tail", r.ess_tail, 0),
            );
        }
        t.push_str("</table></details>");
        pg.body.push_str(&t);
    }
    let _ = writeln!(md);
}

/// The propagation's draws and counts.
fn propagation_section(pg: &mut Page, d: &ReportData) {
    pg.section("propagation", "Propagation");
    pg.p(&format!(
        "Monte Carlo propagation: {} draws (seed {}); evaluations {}, without a prediction {}, outside the ROM's box {}. Full output: <code>propagate/predictions.parquet</code>.",
        d.propagate.get("draws").map(|v| v.to_string()).unwrap_or_default(),
        d.propagate.get("seed").map(|v| v.to_string()).unwrap_or_default(),
        d.propagate.pointer("/counts/evaluations").map(|v| v.to_string()).unwrap_or_default(),
        d.propagate.pointer("/counts/inadmissible_or_untracked").map(|v| v.to_string()).unwrap_or_default(),
        d.propagate.pointer("/counts/outside_rom_box").map(|v| v.to_string()).unwrap_or_default(),
    ));
}

/// Ingest's counts, the quarantined measurements, the specimens and the findings that
/// matter.
fn findings_section(pg: &mut Page, md: &mut String, d: &ReportData) {
    pg.section("findings", "Findings that matter");
    pg.p(&format!(
        "Ingest: {} measurements, {} quarantined. Finding counts: {}.",
        d.ingest_measurements,
        d.quarantined.len(),
        esc(&d
            .ingest_counts
            .iter()
            .map(|(k, v)| format!("{k} {v}"))
            .collect::<Vec<_>>()
            .join(", "))
    ));
    if !d.quarantined.is_empty() {
        let mut t = String::from(
            "<table data-table=\"quarantined\"><tr><th>measurement</th><th>reason</th></tr>\n",
        );
        for (m, r) in &d.quarantined {
            let _ = writeln!(
                t,
                "<tr>{}{}</tr>",
                txt("measurement_id", m),
                txt("reason", r)
            );
        }
        t.push_str("</table>");
        pg.body.push_str(&t);
    }
    if !d.specimens.is_empty() {
        pg.p("Measured specimens (the sheet's dimensions; the thickness, less the board file's copper, measures each board's core thickness in step 1; length and width are shown, not modelled):");
        let mut t = String::from("<table data-table=\"specimens\"><tr><th>board</th><th>length, mm</th><th>width, mm</th><th>thickness, mm</th></tr>\n");
        let mm = |v: Option<f64>| v.map_or(String::from("–"), |x| format!("{x:.3}"));
        for (b, dims) in &d.specimens {
            let _ = writeln!(
                t,
                "<tr>{}{}{}{}</tr>",
                txt("board_id", b),
                txt("length_mm", &mm(dims[0])),
                txt("width_mm", &mm(dims[1])),
                txt("thickness_mm", &mm(dims[2]))
            );
        }
        t.push_str("</table>");
        pg.body.push_str(&t);
    }
    if d.findings.is_empty() {
        pg.p("No warnings or errors in ingest, updating or propagation.");
    } else {
        let mut t = String::from("<table data-table=\"findings\"><tr><th>stage</th><th>severity</th><th>code</th><th>where</th><th>message</th></tr>\n");
        for f in &d.findings {
            let _ = writeln!(
                t,
                "<tr>{}{}{}{}<td style=\"white-space:normal\">{}</td></tr>",
                txt("stage", &f.stage),
                txt("severity", &f.severity),
                txt("code", &f.code),
                txt("where", &f.where_),
                esc(&f.message)
            );
        }
        t.push_str("</table>");
        pg.body.push_str(&t);
    }
    let _ = writeln!(
        md,
        "## Findings\n\n{} warnings/errors; {} measurements quarantined.\n",
        d.findings.len(),
        d.quarantined.len()
    );
}

/// Links to the stabilization diagrams and MAC matrices.
fn plots_section(pg: &mut Page, d: &ReportData) {
    pg.section("plots", "Stabilization diagrams and MAC matrices");
    if d.plot_links.is_empty() {
        pg.p("No stabilization or MAC plots in the work directory (extract/pair ran with --no-plots?).");
    } else {
        let mut by: BTreeMap<&str, Vec<(&str, &str)>> = BTreeMap::new();
        for (m, k, l) in &d.plot_links {
            by.entry(m).or_default().push((k, l));
        }
        let mut s = String::from("<p>Copied next to this page (<code>plots/</code>): ");
        let items: Vec<String> = by
            .iter()
            .map(|(m, v)| {
                format!(
                    "{}: {}",
                    esc(m),
                    v.iter()
                        .map(|(k, l)| format!("<a href=\"{}\">{}</a>", esc(l), esc(k)))
                        .collect::<Vec<_>>()
                        .join(" · ")
                )
            })
            .collect();
        s.push_str(&items.join("; "));
        s.push_str("</p>");
        pg.body.push_str(&s);
    }
}

/// The report's inputs and every stage's outputs with their BLAKE3.
fn provenance_section(pg: &mut Page, md: &mut String, d: &ReportData) {
    pg.section("provenance", "Provenance");
    pg.p(&format!(
        "Built by hbmu {} from the artifacts below (BLAKE3 of each file, as recorded in each stage's manifest). Generation time is recorded in <code>report.manifest.json</code> only.",
        esc(&d.tool_version)
    ));
    let mut t = String::from(
        "<table data-table=\"inputs\"><tr><th>report input</th><th>BLAKE3</th></tr>\n",
    );
    for (p, h) in &d.inputs {
        let _ = writeln!(
            t,
            "<tr>{}<td><code>{}</code></td></tr>",
            txt("path", p),
            esc(h)
        );
    }
    t.push_str("</table>");
    pg.body.push_str(&t);
    let mut t = String::from("<details><summary>Every stage's outputs</summary><table data-table=\"provenance\"><tr><th>stage</th><th>manifest</th><th>tool</th><th>fingerprint</th><th>output</th><th>BLAKE3</th></tr>\n");
    for p in &d.provenance {
        for (o, h) in &p.outputs {
            let _ = writeln!(
                t,
                "<tr>{}{}{}<td><code>{}</code></td>{}<td><code>{}</code></td></tr>",
                txt("stage", &p.stage),
                txt("manifest", &p.manifest),
                txt("tool_version", &p.tool_version),
                esc(&p.fingerprint[..p.fingerprint.len().min(16)]),
                txt("output", o),
                esc(h)
            );
        }
    }
    t.push_str("</table></details>");
    pg.body.push_str(&t);
    let _ = writeln!(md, "## Provenance\n\nhbmu {}; inputs:\n", d.tool_version);
    for (p, h) in &d.inputs {
        let _ = writeln!(md, "- `{p}` blake3 `{h}`");
    }
}

/// The HTML page: head, table of contents and `pg`'s body.
fn page_html(d: &ReportData, pg: &Page) -> String {
    let mut html = String::new();
    let _ = write!(
        html,
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n<title>{}</title>\n<style>{CSS}</style>\n</head>\n<body>\n<h1>{}</h1>\n<p>hbmu {} · validation report</p>\n<nav><ul>",
        esc(&d.title),
        esc(&d.title),
        esc(&d.tool_version)
    );
    for (id, t) in &pg.toc {
        let _ = write!(html, "<li><a href=\"#{id}\">{}</a></li>", esc(t));
    }
    html.push_str("</ul></nav>\n");
    html.push_str(&pg.body);
    html.push_str("</body>\n</html>\n");
    html
}

/// One table of the diagnosis section; "none" in one line when it has no rows.
fn diagnosis_table(pg: &mut Page, title: &str, t: &super::diagnosis::Table) {
    use super::diagnosis::Cell;
    if t.rows.is_empty() {
        pg.p(&format!("<strong>{}:</strong> none.", esc(title)));
        return;
    }
    pg.p(&format!("<strong>{}</strong>", esc(title)));
    let mut h = format!("<table data-table=\"{}\"><tr>", t.spec.name);
    for c in t.headers {
        let _ = write!(h, "<th>{}</th>", esc(c));
    }
    h.push_str("</tr>\n");
    for r in &t.rows {
        h.push_str("<tr>");
        for ((cell, col), digits) in r.iter().zip(t.spec.columns).zip(t.digits) {
            let name = col.name;
            h.push_str(&match cell {
                Cell::Str(Some(v)) if v.len() > 60 => format!(
                    "<td data-col=\"{name}\" data-value=\"{0}\" style=\"white-space:normal;min-width:20em\">{0}</td>",
                    esc(v)
                ),
                Cell::Str(v) => txt(name, v.as_deref().unwrap_or("")),
                Cell::F64(v) => num(name, v.unwrap_or(f64::NAN), *digits),
                Cell::Int(Some(v)) => {
                    format!("<td class=\"n\" data-col=\"{name}\" data-value=\"{v}\">{v}</td>")
                }
                Cell::Int(None) => format!("<td class=\"n\" data-col=\"{name}\" data-value=\"\">–</td>"),
                Cell::Bool(b) => txt(name, if *b { "yes" } else { "no" }),
            });
        }
        h.push_str("</tr>\n");
    }
    h.push_str("</table>");
    pg.body.push_str(&h);
}

/// The diagnosis: verdict first, then the located evidence, the candidates and the misfit per
/// mode before and after the best refit.
fn diagnosis_section(pg: &mut Page, md: &mut String, d: Option<&super::diagnosis::DiagnosisData>) {
    use super::diagnosis::{self, Cell};
    pg.section("diagnosis", "Diagnosis");
    let Some(d) = d else {
        pg.p("The diagnose stage has not run (no <code>diagnose/diagnosis.json</code>): no verdict on missing physics.");
        let _ = writeln!(md, "**Diagnosis:** the diagnose stage has not run.\n");
        return;
    };
    let doc = &d.doc;
    let statement = diagnosis::verdict_statement(doc);
    let class = if doc.verdict == "no_missing_physics" {
        "ok"
    } else {
        "bad"
    };
    let _ = writeln!(
        pg.body,
        "<div class=\"verdict\" data-verdict=\"{0}\"><p><strong>Verdict: <span class=\"{class}\">{0}</span></strong></p><p>{1}</p></div>",
        esc(&doc.verdict),
        esc(&statement)
    );
    let _ = writeln!(
        md,
        "**Diagnosis — verdict `{}`:** {statement}\n",
        doc.verdict
    );
    if doc.verdict == "unexplained_misfit" || doc.verdict == "model_form" {
        pg.p(&format!(
            "<strong>Remaining discrepancy:</strong> {}",
            esc(&doc.remaining_discrepancy)
        ));
        let _ = writeln!(md, "Remaining discrepancy: {}\n", doc.remaining_discrepancy);
    }
    pg.p(&format!(
        "Located evidence (the baseline's posterior-predictive checks): setups {}. Full detail: <code>diagnose/diagnosis.json</code>; refits under <code>diagnose/refits/</code>.",
        if doc.located.setups.is_empty() {
            "none".to_string()
        } else {
            esc(&doc.located.setups.join(", "))
        }
    ));
    let tables = diagnosis::tables(d);
    // Titles by table (not by position: a table added to the section keeps every title on
    // its own table).
    let title = |name: &str| match name {
        n if n == diagnosis::LOCATED_MODES.name => "Misfitting modes",
        n if n == diagnosis::OUTLIERS.name => "Outlier measurements",
        n if n == diagnosis::IDENTIFICATION_OUTLIERS.name => {
            "Likely identification slips (one mode of one measurement)"
        }
        n if n == diagnosis::COVARIATES.name => "Significant covariates",
        n if n == diagnosis::CLUSTERS.name => "Recurring unpaired-mode clusters",
        n if n == diagnosis::NEVER_SEEN.name => "Model modes never seen",
        n if n == diagnosis::REGIONS.name => "Where on the board",
        n if n == diagnosis::CANDIDATES.name => "Candidate mechanisms",
        _ => "Diagnosis table",
    };
    for t in &tables {
        if t.spec.name == diagnosis::BEFORE_AFTER.name {
            break;
        }
        diagnosis_table(pg, title(t.spec.name), t);
        if t.spec.name == diagnosis::REGIONS.name {
            for r in &doc.located.board_regions {
                pg.p(&esc(&r.sentence));
            }
            if !doc.located.board_regions_note.is_empty() {
                pg.p(&esc(&doc.located.board_regions_note));
            }
        }
    }
    let Some(ba) = tables.last() else {
        return;
    };
    if d.modes.is_none() {
        pg.p("<strong>Before/after per mode:</strong> not available: <code>diagnose/diagnosis_modes.parquet</code> is missing (written by a diagnose stage of an older version; rerun it).");
        return;
    }
    let best = diagnosis::best_refit(d);
    let one_setup = ba.rows.windows(2).all(|w| w[0][0] == w[1][0]);
    let items: Vec<figures::BeforeAfter> = ba
        .rows
        .iter()
        .map(|r| {
            let g = |k: usize| match &r[k] {
                Cell::F64(v) => *v,
                _ => None,
            };
            let st = |k: usize| match &r[k] {
                Cell::Str(Some(v)) => v.clone(),
                _ => String::new(),
            };
            figures::BeforeAfter {
                label: if one_setup {
                    st(1)
                } else {
                    format!("{} {}", st(0), st(1))
                },
                before_pct: g(5).unwrap_or(f64::NAN),
                after_pct: g(8),
                located: matches!(r[3], Cell::Bool(true)),
            }
        })
        .collect();
    if items.is_empty() {
        pg.p("<strong>Misfit per mode, before and after:</strong> none (no located mode and no refit).");
        return;
    }
    let caption = match &best {
        Some(id) => format!(
            "Mean relative residual per mode (every mode of the setups the refit covers), baseline against the refit <code>{}</code>; bars from zero, the model's mean prediction. Values in the table below and in <code>diagnosis_before_after.csv</code>.",
            esc(id)
        ),
        None => "Mean relative residual of the located modes in the baseline (no refit gave a posterior). Values in the table below.".to_string(),
    };
    pg.figure(
        figures::before_after_svg(
            &match (one_setup, ba.rows.first().map(|r| &r[0])) {
                (true, Some(Cell::Str(Some(st)))) => {
                    format!("Misfit per mode before and after, {st}")
                }
                _ => "Misfit per mode before and after".to_string(),
            },
            &items,
            best.as_deref(),
        ),
        &caption,
    );
    diagnosis_table(pg, "Misfit per mode, before and after the best refit", ba);
}

/// Per updated mode, the posterior median and 90 % interval of the model-form discrepancy
/// (the step's `discrepancy_<label>` draws, relative eigenvalue) in % of the frequency; empty
/// where the step ran without one.
pub fn discrepancy_bars(step: &StepData) -> Vec<figures::DiscrepancyBar> {
    use super::validation::quantile_sorted;
    step.population
        .iter()
        .filter(|(n, _)| n != "discrepancy_scale" && n != "discrepancy_unit_scale")
        .filter_map(|(n, v)| {
            let label = n.strip_prefix("discrepancy_")?;
            let mut f: Vec<f64> = v
                .iter()
                .map(|d| 100.0 * crate::bayes::discrepancy::freq_of_eigenvalue(*d))
                .filter(|x| x.is_finite())
                .collect();
            f.sort_by(f64::total_cmp);
            (!f.is_empty()).then(|| figures::DiscrepancyBar {
                label: label.to_string(),
                q05_pct: quantile_sorted(&f, 0.05),
                q50_pct: quantile_sorted(&f, 0.5),
                q95_pct: quantile_sorted(&f, 0.95),
            })
        })
        .collect()
}

fn posterior_section(pg: &mut Page, step: &StepData) {
    let id = if step.name.contains("step 2") {
        "posterior2"
    } else {
        "posterior1"
    };
    pg.section(id, &format!("Posterior, {}", step.name));
    let params: Vec<String> = step
        .population
        .iter()
        .filter_map(|(n, _)| n.strip_prefix("mu_").map(str::to_string))
        .collect();
    pg.body.push_str("<div class=\"grid\">");
    let draws_of = |q: &str, u: &str| {
        step.units
            .iter()
            .find(|(n, v, _)| n == q && v == u)
            .map(|(_, _, d)| d)
    };
    // A modulus per unit mass scale (step 1's population coordinate): each unit's draws of
    // it are its modulus over its mass scale, draw by draw.
    let unit_series = |p: &str| -> Vec<(String, Vec<f64>)> {
        match crate::fem::params::names::modulus_of_per_mass_scale(p) {
            Some(q) => step
                .units
                .iter()
                .filter(|(n, _, _)| *n == q)
                .filter_map(|(_, u, v)| {
                    let m = draws_of(crate::fem::params::names::MASS_SCALE, u)?;
                    Some((u.clone(), v.iter().zip(m).map(|(a, b)| a / b).collect()))
                })
                .collect(),
            None => step
                .units
                .iter()
                .filter(|(q, _, _)| q == p)
                .map(|(_, u, v)| (u.clone(), v.clone()))
                .collect(),
        }
    };
    // The units' own parameters that are no population coordinate (the moduli themselves,
    // where the population takes them per unit mass): per-unit densities alone.
    let mut own: Vec<String> = vec![];
    for (q, _, _) in &step.units {
        if !params.contains(q) && !own.contains(q) {
            own.push(q.clone());
        }
    }
    for p in params.iter().chain(&own) {
        let (scale, unit) = display_unit(p);
        let mut series = unit_series(p);
        if let Some((_, v)) = step
            .population
            .iter()
            .find(|(n, _)| *n == format!("mu_{p}"))
        {
            series.push(("μ (population mean)".to_string(), v.clone()));
        }
        let xd = if unit.is_empty() {
            p.clone()
        } else {
            format!("{p} [{unit}]")
        };
        pg.figure(
            figures::density_svg(&format!("Posterior of {p}"), &xd, &series, scale),
            &if params.contains(p) {
                format!(
                    "Posterior density of <code>{}</code> per unit and of the population mean.",
                    esc(p)
                )
            } else {
                format!("Posterior density of <code>{}</code> per unit.", esc(p))
            },
        );
    }
    // Population spreads as coefficients of variation.
    let cv: Vec<(String, Vec<f64>)> = params
        .iter()
        .filter_map(|p| {
            let mu = step
                .population
                .iter()
                .find(|(n, _)| *n == format!("mu_{p}"))?;
            let sg = step
                .population
                .iter()
                .find(|(n, _)| *n == format!("sigma_{p}"))?;
            let v = if p.starts_with("ln_") {
                sg.1.clone()
            } else {
                mu.1.iter().zip(&sg.1).map(|(m, s)| 100.0 * s / m).collect()
            };
            Some((p.clone(), v))
        })
        .collect();
    if !cv.is_empty() {
        let is_ln = params.iter().all(|p| p.starts_with("ln_"));
        let xd = if is_ln { "σ (of ln k)" } else { "σ / μ [%]" };
        pg.figure(
            figures::density_svg("Population spread", xd, &cv, 1.0),
            "Posterior of the population standard deviations (relative to the population mean; for ln k, absolute).",
        );
    }
    let eps: Vec<(String, Vec<f64>)> = step
        .population
        .iter()
        .filter_map(|(n, v)| n.strip_prefix("eps_").map(|l| (l.to_string(), v.clone())))
        .collect();
    if !eps.is_empty() {
        pg.figure(
            figures::density_svg(
                "Prediction errors ε per mode",
                "ε, relative sd of λ = ω² [10⁻³]",
                &eps,
                1e-3,
            ),
            "Posterior of the relative eigenvalue prediction error of each updated mode.",
        );
    }
    let bars = discrepancy_bars(step);
    if !bars.is_empty() {
        pg.figure(
            figures::discrepancy_svg(&format!("Model-form discrepancy, {}", step.name), &bars),
            &format!(
                "The model-form discrepancy of each updated mode, common to every unit of {}: posterior median (bar) and 90 % interval (whisker), in % of the frequency. It is what no parameter of the model can absorb; the predicted measurements include it.",
                esc(&step.name)
            ),
        );
    }
    pg.body.push_str("</div>");
    // Correlation: posterior mean of Ω.
    let d = params.len();
    if d > 1 {
        let mut m = vec![0.0; d * d];
        let mut all = true;
        for i in 0..d {
            m[i * d + i] = 1.0;
            for j in i + 1..d {
                match step
                    .population
                    .iter()
                    .find(|(n, _)| *n == format!("corr_{}_{}", params[i], params[j]))
                {
                    Some((_, v)) => {
                        let x = v.iter().sum::<f64>() / v.len().max(1) as f64;
                        m[i * d + j] = x;
                        m[j * d + i] = x;
                    }
                    None => all = false,
                }
            }
        }
        if all {
            pg.figure(
                figures::correlation_svg("Population correlation Ω (posterior mean)", &params, &m),
                "Posterior mean of the population correlation matrix; intervals in the posterior summary (corr_* rows).",
            );
        }
    }
}

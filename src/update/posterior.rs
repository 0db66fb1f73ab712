//! Posterior draws to the tables' rows: population and board columns, summaries with R-hat and
//! ESS, the convergence verdict, the posterior-predictive residuals, the evidence.

use crate::bayes::smc::{self};
use crate::bayes::target::{Compose, ErrorPrior, ModalTarget};
use crate::findings::{Finding, Findings, Severity};
use crate::update::problem::StepTarget;
use std::collections::BTreeSet;

/// The seed stream of the draws of the discrepancy's part the parameters absorb.
const CONFOUNDED_STREAM: u64 = 0x6d66_7061_7274;

/// One draw, for particle `i` of run `r`, of the part `a` of the model-form discrepancy
/// that the unit coordinates absorb (`Discrepancy::confounded_shift` at the particle's scale
/// τ, from the stream keyed by `seed`): a step's physical unit coordinates, and its
/// population means μ in the same coordinates, are the fitted ones less `a`. Empty without
/// a discrepancy in the likelihood.
pub fn confounded_draw(target: &ModalTarget, g: &[f64], seed: u64, at: (usize, usize)) -> Vec<f64> {
    let Some(disc) = target.errors.discrepancy.as_ref() else {
        return vec![];
    };
    let tau = target
        .errors
        .discrepancy_scale(&g[target.prior.dim()..])
        .unwrap_or(0.0);
    confounded_draw_at(disc, tau, seed, at)
}

/// [`confounded_draw`] for a discrepancy `disc` of scale `tau` given from outside the
/// likelihood (step 2's cut scale).
pub fn confounded_draw_at(
    disc: &crate::bayes::discrepancy::Discrepancy,
    tau: f64,
    seed: u64,
    (r, i): (usize, usize),
) -> Vec<f64> {
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(smc::stream_key(&[
        seed,
        CONFOUNDED_STREAM,
        r as u64,
        i as u64,
    ]));
    let z: Vec<f64> = (0..disc.unit_dim)
        .map(|_| StandardNormal.sample(&mut rng))
        .collect();
    disc.confounded_shift(tau, &z)
}

/// A unit's deviation `dev` from the units' centre, fitted with the relative eigenvalue
/// sensitivities `fitted` (n_modes × c row-major, at the fitted centre), carried to the
/// physical centre, where the sensitivities are `physical`: the deviation there that moves
/// the modes as the fitted one does, Δ' = argmin ‖S_p Δ' − S_f Δ‖² over the `absorbing`
/// coordinates, the others (held by data of their own, or unseen by the modes) kept as they
/// are. `None` where that least-squares problem is singular.
///
/// Why: the data fix how far a board's frequencies lie from the other boards', S_f Δ; what
/// deviation of the parameters that is depends on the sensitivities, which depend on where the
/// parameters are. The discrepancy's absorbed part moves the physical centre from the fitted
/// one (`confounded_draw`); a model whose transverse shear modulus absorbed part of its form
/// error has the wrong shear share in its bending modes, so its E_x contrasts between boards
/// are scaled by the ratio of the two sensitivities. At the physical centre the model's
/// sensitivities are those of the physical parameters.
pub fn carried_deviation(
    (fitted, physical): (&[f64], &[f64]),
    n_modes: usize,
    absorbing: &[usize],
    dev: &[f64],
) -> Option<Vec<f64>> {
    let c = dev.len();
    let q = absorbing.len();
    // The modes' move the fitted deviation makes, less what the kept coordinates make at the
    // physical centre.
    let r: Vec<f64> = (0..n_modes)
        .map(|m| {
            (0..c)
                .map(|k| {
                    let kept = if absorbing.contains(&k) {
                        0.0
                    } else {
                        physical[m * c + k]
                    };
                    (fitted[m * c + k] - kept) * dev[k]
                })
                .sum()
        })
        .collect();
    let s: Vec<f64> = (0..n_modes)
        .flat_map(|m| absorbing.iter().map(move |&k| physical[m * c + k]))
        .collect();
    let v = crate::update::problem::weighted_offset(&s, &r, &vec![1.0; n_modes], q)?;
    let mut out = dev.to_vec();
    for (j, &k) in absorbing.iter().enumerate() {
        out[k] = v[j];
    }
    Some(out)
}

/// The unit coordinates `x` less the confounded part `a` (coordinates beyond `a` as they are).
pub fn less_confounded(x: &[f64], a: &[f64]) -> Vec<f64> {
    x.iter()
        .enumerate()
        .map(|(k, v)| v - a.get(k).copied().unwrap_or(0.0))
        .collect()
}

/// Draws of named scalar columns, one row per (run, draw[, key]).
pub struct DrawTable {
    pub run: Vec<i32>,
    pub draw: Vec<i32>,
    /// board_id or measurement_id (None for population draws).
    pub key: Vec<Option<String>>,
    /// Column names (unit in the name) and values, one value per row.
    pub cols: Vec<(String, String, Vec<f64>)>,
}

impl DrawTable {
    pub fn new(names_units: &[(String, String)]) -> DrawTable {
        DrawTable {
            run: vec![],
            draw: vec![],
            key: vec![],
            cols: names_units
                .iter()
                .map(|(n, u)| (n.clone(), u.clone(), vec![]))
                .collect(),
        }
    }
    pub fn push(&mut self, run: usize, draw: usize, key: Option<&str>, values: &[f64]) {
        self.run.push(run as i32);
        self.draw.push(draw as i32);
        self.key.push(key.map(str::to_string));
        for (c, v) in self.cols.iter_mut().zip(values) {
            c.2.push(*v);
        }
    }

    /// Summary rows: per column and key, chains = runs.
    pub fn summarize(&self, runs: usize, key_is_board: bool) -> Vec<SummaryRow> {
        let keys: BTreeSet<Option<String>> = self.key.iter().cloned().collect();
        let mut out = vec![];
        for k in &keys {
            for (name, _, vals) in &self.cols {
                let mut chains: Vec<Vec<f64>> = vec![vec![]; runs];
                for i in 0..vals.len() {
                    if &self.key[i] == k {
                        chains[self.run[i] as usize].push(vals[i]);
                    }
                }
                let s = crate::bayes::diagnostics::summarize(&chains);
                out.push(SummaryRow {
                    parameter: name.clone(),
                    board_id: if key_is_board { k.clone() } else { None },
                    measurement_id: if key_is_board { None } else { k.clone() },
                    s,
                    physical: None,
                });
            }
        }
        out
    }
}

/// Largest split R-hat across runs that counts as agreement (Vehtari et al. 2021 advise 1.01
/// for a final analysis; at the pipeline's few runs of a few hundred particles, 1.05 is the
/// level below which the runs' differences are within their Monte Carlo error).
pub const MAX_R_HAT: f64 = 1.05;

/// Smallest bulk or tail ESS (over all runs) below which quantiles are unreliable.
pub const MIN_ESS: f64 = 100.0;

/// A warning when the independent runs disagree (R-hat above [`MAX_R_HAT`]) or the effective
/// sample size is small (below [`MIN_ESS`]), naming the worst parameters: the posterior
/// and the evidence's error bar are then not to be trusted as they stand (more particles or
/// runs; a multimodal posterior, e.g. of a model that misses physics, needs more of both).
pub fn convergence_finding(summary: &[SummaryRow], runs: usize) -> Option<Finding> {
    let name = |r: &SummaryRow| {
        let mut n = r.parameter.clone();
        if let Some(m) = r.measurement_id.as_ref().or(r.board_id.as_ref()) {
            n.push_str(&format!(" [{m}]"));
        }
        n
    };
    let mut bad_r: Vec<&SummaryRow> = summary
        .iter()
        .filter(|r| runs >= 2 && r.s.r_hat > MAX_R_HAT)
        .collect();
    bad_r.sort_by(|a, b| b.s.r_hat.total_cmp(&a.s.r_hat));
    let ess = |r: &SummaryRow| r.s.ess_bulk.min(r.s.ess_tail);
    let mut bad_e: Vec<&SummaryRow> = summary.iter().filter(|r| ess(r) < MIN_ESS).collect();
    bad_e.sort_by(|a, b| ess(a).total_cmp(&ess(b)));
    if bad_r.is_empty() && bad_e.is_empty() {
        return None;
    }
    let list = |v: &[&SummaryRow], f: &dyn Fn(&SummaryRow) -> String| {
        let mut s: Vec<String> = v.iter().take(4).map(|r| f(r)).collect();
        if v.len() > 4 {
            s.push(format!("{} more", v.len() - 4));
        }
        s.join(", ")
    };
    let mut parts = vec![];
    if !bad_r.is_empty() {
        parts.push(format!(
            "{} parameter(s) with R-hat above {MAX_R_HAT} ({}): the independent runs disagree",
            bad_r.len(),
            list(&bad_r, &|r| format!("{} {:.3}", name(r), r.s.r_hat))
        ));
    }
    if !bad_e.is_empty() {
        parts.push(format!(
            "{} parameter(s) with bulk or tail ESS below {MIN_ESS:.0} ({})",
            bad_e.len(),
            list(&bad_e, &|r| format!("{} {:.0}", name(r), ess(r)))
        ));
    }
    Some(Finding::new(
        Severity::Warning,
        "update.not_converged",
        format!(
            "{}; the posterior and the evidence's error bar are not reliable as they stand: rerun with more particles or runs (a posterior with several modes, as a model missing physics can have, needs both)",
            parts.join("; ")
        ),
    ))
}

pub struct SummaryRow {
    pub parameter: String,
    pub board_id: Option<String>,
    pub measurement_id: Option<String>,
    pub s: crate::bayes::diagnostics::Summary,
    /// The physical parameter's summary where a model-form discrepancy is inferred: the
    /// draws less the discrepancy's part that the parameters absorb ([`confounded_draw`]).
    pub physical: Option<crate::bayes::diagnostics::Summary>,
}

/// One residual row.
#[derive(Clone, Debug)]
pub struct Residual {
    pub measurement_id: String,
    pub board_id: String,
    pub setup: String,
    pub label: String,
    pub freq_hz: f64,
    pub mean: f64,
    pub sd: f64,
    pub pred_sd: f64,
    pub mac: Option<f64>,
    pub used: bool,
}

/// The population columns of a step's discrepancy: its scale, its per-unit scale and d per
/// label (relative eigenvalue), in the order of [`discrepancy_values`].
pub fn discrepancy_columns(labels: &[String]) -> Vec<(String, String)> {
    [
        "discrepancy_scale".to_string(),
        "discrepancy_unit_scale".to_string(),
    ]
    .into_iter()
    .chain(labels.iter().map(|l| format!("discrepancy_{l}")))
    .map(|n| (n, String::new()))
    .collect()
}

/// The values of [`discrepancy_columns`] at the global vector g (its context `ctx`).
pub fn discrepancy_values(
    target: &ModalTarget,
    g: &[f64],
    ctx: &crate::bayes::target::Ctx,
) -> Vec<f64> {
    let h = &g[target.prior.dim()..];
    let e = &target.errors;
    [
        e.discrepancy_scale(h).unwrap_or(f64::NAN),
        e.discrepancy_unit_scale(h).unwrap_or(f64::NAN),
    ]
    .into_iter()
    .chain(ctx.bias.iter().copied())
    .collect()
}

/// evidence.json's `discrepancy`: the prior of the model-form discrepancy (null without one).
pub fn discrepancy_json(target: &ModalTarget, labels: &[String]) -> serde_json::Value {
    match &target.errors.discrepancy {
        None => serde_json::Value::Null,
        Some(d) => serde_json::json!({
            "labels": labels,
            "fidelity_freq": crate::bayes::discrepancy::freq_of_eigenvalue(d.scale_median),
            "scale_median": d.scale_median,
            "scale_log_sd": d.scale_log_sd,
            "unit_scale_median": d.unit_scale_median,
            "unit_scale_log_sd": d.unit_scale_log_sd,
            "k": d.k,
            "basis": d.basis,
        }),
    }
}

/// Evidence of the runs: each run's log evidence, their mean and standard error.
pub fn evidence_json(log_z: &[f64], posterior: &str) -> serde_json::Value {
    let n = log_z.len() as f64;
    let mean = log_z.iter().sum::<f64>() / n;
    let sd = if log_z.len() > 1 {
        (log_z.iter().map(|z| (z - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt()
    } else {
        f64::NAN
    };
    serde_json::json!({
        "posterior": posterior,
        "log_evidence_runs": log_z,
        "log_evidence_mean": mean,
        "log_evidence_sd_across_runs": if sd.is_finite() { serde_json::json!(sd) } else { serde_json::Value::Null },
        "log_evidence_standard_error": if sd.is_finite() { serde_json::json!(sd / n.sqrt()) } else { serde_json::Value::Null },
        "note": "log p(data | model) from independent SMC runs (product of the mean incremental weights); standard error = sd across runs / sqrt(runs)",
    })
}

/// A function from a global vector to the population table's values.
pub type PopulationRow<'a> = Box<dyn Fn(&[f64]) -> Vec<f64> + 'a>;

/// Population columns of a draw, in physical units of the parameters.
pub fn population_columns<'a>(
    target: &'a ModalTarget,
    param_names: &[String],
    reference: &[f64],
    labels: &[String],
) -> (Vec<(String, String)>, PopulationRow<'a>) {
    let d = param_names.len();
    // Parameters on a logarithmic coordinate (p = ref e^x): μ is reported as the population
    // median ref e^μ, σ in ln units.
    let log: Vec<bool> = match &target.compose {
        Compose::Boards { log, .. } => (0..d)
            .map(|k| log.get(k).copied().unwrap_or(false))
            .collect(),
        Compose::Joints { .. } => vec![false; d],
    };
    let unit = |n: &str| -> String {
        if n.ends_with("_pa") {
            "Pa".into()
        } else if n.ends_with("_n_per_m") {
            "N/m".into()
        } else if n.ends_with("_kg") {
            "kg".into()
        } else {
            String::new()
        }
    };
    let mut cols: Vec<(String, String)> = vec![];
    cols.extend(param_names.iter().map(|n| (format!("mu_{n}"), unit(n))));
    cols.extend(param_names.iter().zip(&log).map(|(n, &l)| {
        (
            format!("sigma_{n}"),
            if l { "ln".to_string() } else { unit(n) },
        )
    }));
    for i in 0..d {
        for j in i + 1..d {
            cols.push((
                format!("corr_{}_{}", param_names[i], param_names[j]),
                String::new(),
            ));
        }
    }
    let infer_eps = matches!(target.errors.eps, ErrorPrior::Inferred { .. });
    let infer_delta = matches!(target.errors.delta, Some(ErrorPrior::Inferred { .. }));
    if infer_eps {
        cols.extend(labels.iter().map(|l| (format!("eps_{l}"), String::new())));
    }
    if infer_delta {
        cols.extend(labels.iter().map(|l| (format!("delta_{l}"), String::new())));
    }
    let with_discrepancy = target.errors.discrepancy.is_some();
    if with_discrepancy {
        cols.extend(discrepancy_columns(labels));
    }
    // The covariate coefficient (absolute, the unit coordinate after the parameters).
    if let Some(c) = &target.covariate {
        let unit = format!("1/(unit of {})", c.covariate);
        cols.push((format!("mu_{}", c.name), unit.clone()));
        cols.push((format!("sigma_{}", c.name), unit));
    }
    let with_beta = target.covariate.is_some();
    let reference = reference.to_vec();
    let f = Box::new(move |g: &[f64]| -> Vec<f64> {
        let ctx = smc::Target::ctx(target, g);
        let mut v: Vec<f64> = reference
            .iter()
            .zip(&ctx.pop.mu)
            .zip(&log)
            .map(|((r, m), &l)| if l { r * m.exp() } else { r * (1.0 + m) })
            .collect();
        v.extend(
            reference
                .iter()
                .zip(&ctx.pop.sigma)
                .zip(&log)
                .map(|((r, s), &l)| if l { *s } else { r * s }),
        );
        let o = ctx.pop.correlation();
        let dd = ctx.pop.mu.len();
        for i in 0..d {
            for j in i + 1..d {
                v.push(o[i * dd + j]);
            }
        }
        if infer_eps {
            v.extend(&ctx.eps);
        }
        if infer_delta {
            v.extend(&ctx.delta);
        }
        if with_discrepancy {
            v.extend(discrepancy_values(target, g, &ctx));
        }
        if with_beta {
            v.push(ctx.pop.mu[d]);
            v.push(ctx.pop.sigma[d]);
        }
        v
    });
    (cols, f)
}

/// Posterior-predictive residuals of every accepted paired mode (updating and validation
/// labels) of the units, from up to `draws` equally spaced draws in all, spread evenly over
/// the runs.
#[allow(clippy::too_many_arguments)]
pub fn residuals(
    st: &StepTarget,
    (all_labels, updated): (&[String], &[String]),
    results: &[smc::RunResult<crate::bayes::modal::Terms>],
    setup: &str,
    draws: usize,
    model_error_sd: Option<&[f64]>,
) -> (Vec<Residual>, Vec<Lost>) {
    use rayon::prelude::*;
    let target = &st.target;
    let draws_per_run = draws.div_ceil(results.len().max(1));
    let out: Vec<Vec<ResidualRow>> = (0..st.units_all.len())
        .into_par_iter()
        .map(|b| {
            let draws: Vec<PredDraw<'_>> = results
                .iter()
                .flat_map(|r| {
                    let step = (r.particles.len() / draws_per_run.max(1)).max(1);
                    r.particles.iter().step_by(step)
                })
                .map(|p| PredDraw {
                    aux: &p.aux,
                    x: &p.x[b],
                    eps: smc::Target::ctx(target, &p.g).eps,
                })
                .collect();
            unit_residuals(st, (all_labels, updated), b, &draws, setup, model_error_sd)
        })
        .collect();
    split_rows(out.into_iter().flatten())
}

/// One posterior draw of a unit, as its predictions need it: the step-1 draw it carries, the
/// unit's coordinates and the error scales ε per updated mode.
pub struct PredDraw<'a> {
    pub aux: &'a [f64],
    pub x: &'a [f64],
    pub eps: Vec<f64>,
}

/// A unit's residual row, or the label lost at every draw; with the share of draws it was
/// tracked at when below 90 %.
pub type ResidualRow = Result<(Residual, Option<Lost>), Lost>;

/// The rows and the lost labels of [`unit_residuals`]' results.
pub fn split_rows(rows: impl Iterator<Item = ResidualRow>) -> (Vec<Residual>, Vec<Lost>) {
    let mut out = vec![];
    let mut lost = vec![];
    for r in rows {
        match r {
            Ok((row, partial)) => {
                out.push(row);
                lost.extend(partial);
            }
            Err(l) => lost.push(l),
        }
    }
    (out, lost)
}

/// Posterior-predictive residuals of unit `b`'s accepted paired modes over equally weighted
/// `draws` of its posterior: the model frequency's mean and sd over the draws, and the
/// predictive sd with the inferred error ε/2 · f of an updated mode (and `model_error_sd`).
pub fn unit_residuals(
    st: &StepTarget,
    (all_labels, updated): (&[String], &[String]),
    b: usize,
    draws: &[PredDraw<'_>],
    setup: &str,
    model_error_sd: Option<&[f64]>,
) -> Vec<ResidualRow> {
    let (target, all_pred) = (&st.target, &st.all_pred);
    let (data, meta) = &st.units_all[b];
    let upd_idx: Vec<Option<usize>> = all_labels
        .iter()
        .map(|l| updated.iter().position(|u| u == l))
        .collect();
    let nf = data.freq.len();
    let mut s1 = vec![0.0; nf];
    let mut s2 = vec![0.0; nf];
    let mut se = vec![0.0; nf];
    let mut mac = vec![0.0; data.shapes.len()];
    let mut nmac = vec![0.0; data.shapes.len()];
    let mut nk = vec![0.0; nf];
    let mut n_all = 0.0;
    for p in draws {
        let v = target.values(p.aux, b, p.x);
        n_all += 1.0;
        // A label lost at this draw (its mode not trackable) leaves the others.
        // With a covariate effect: one prediction per condition.
        let vs = target
            .condition_values(b, &v, p.x)
            .unwrap_or_else(|| vec![Some(v.clone())]);
        let Some(tracked_preds) = vs
            .iter()
            .map(|vk| all_pred.predict_tracked(vk.as_ref()?))
            .collect::<Option<Vec<_>>>()
        else {
            continue;
        };
        let nm = all_labels.len();
        let tracked: Vec<bool> = tracked_preds
            .iter()
            .flat_map(|(_, t)| t.iter().copied())
            .collect();
        let preds: Vec<_> = tracked_preds.into_iter().map(|(p, _)| p).collect();
        let t = all_pred.terms_conditions(&preds, data, &v);
        for (k, f) in data.freq.iter().enumerate() {
            let slot = f.cond * nm + f.mode;
            if !tracked[slot] {
                continue;
            }
            let fm = t.lambda[slot].max(0.0).sqrt() / (2.0 * std::f64::consts::PI);
            s1[k] += fm;
            s2[k] += fm * fm;
            nk[k] += 1.0;
            if let Some(u) = upd_idx[f.mode] {
                let e = p.eps[u] * fm / 2.0;
                se[k] += e * e;
            }
            // The model-error term's spread (relative on λ: half on f).
            if let Some(sd) = model_error_sd {
                let e = sd[f.mode] * fm / 2.0;
                se[k] += e * e;
            }
        }
        for (k, omm) in t.one_minus_mac.iter().enumerate() {
            let sh = &data.shapes[k];
            if tracked[sh.cond * nm + sh.mode] {
                mac[k] += 1.0 - omm;
                nmac[k] += 1.0;
            }
        }
    }
    meta.iter()
        .enumerate()
        .map(|(k, m)| {
            let label = all_labels[m.label].clone();
            let n = nk[k];
            if n == 0.0 {
                return Err(Lost {
                    measurement_id: m.measurement_id.clone(),
                    label,
                    share_tracked: 0.0,
                });
            }
            let mean = s1[k] / n;
            let var = (s2[k] / n - mean * mean).max(0.0);
            Ok((
                Residual {
                    measurement_id: m.measurement_id.clone(),
                    board_id: m.board_id.clone(),
                    setup: setup.to_string(),
                    label: label.clone(),
                    freq_hz: m.freq_hz,
                    mean,
                    sd: var.sqrt(),
                    pred_sd: (var + se[k] / n).sqrt().max(1e-12),
                    mac: m
                        .shape
                        .and_then(|i| (nmac[i] > 0.0).then(|| mac[i] / nmac[i])),
                    used: upd_idx[m.label].is_some(),
                },
                (n < 0.9 * n_all).then(|| Lost {
                    measurement_id: m.measurement_id.clone(),
                    label,
                    share_tracked: n / n_all,
                }),
            ))
        })
        .collect()
}

/// A residual row whose label could not be tracked at every posterior draw (the row is left
/// out when it never was).
pub struct Lost {
    pub measurement_id: String,
    pub label: String,
    pub share_tracked: f64,
}

/// The finding for rows of the residual table left out or averaged over fewer draws because
/// their label's mode could not be tracked (its overlap with the reference mode fell below
/// 1/√2): nothing is dropped silently.
pub fn lost_finding(lost: &[Lost], findings: &mut Findings) {
    if lost.is_empty() {
        return;
    }
    let dropped: Vec<String> = lost
        .iter()
        .filter(|l| l.share_tracked == 0.0)
        .map(|l| format!("{} {}", l.measurement_id, l.label))
        .collect();
    let partial: Vec<String> = lost
        .iter()
        .filter(|l| l.share_tracked > 0.0)
        .map(|l| {
            format!(
                "{} {} ({:.0} %)",
                l.measurement_id,
                l.label,
                100.0 * l.share_tracked
            )
        })
        .collect();
    let show = |v: &[String]| {
        let mut s = v.iter().take(8).cloned().collect::<Vec<_>>().join(", ");
        if v.len() > 8 {
            s.push_str(&format!(", … ({} in all)", v.len()));
        }
        s
    };
    let mut msg = String::from("posterior-predictive residuals: some modes could not be tracked at every posterior draw (overlap with the label's reference mode below 1/√2)");
    if !dropped.is_empty() {
        msg.push_str(&format!(
            "; left out of residuals.parquet, never tracked: {}",
            show(&dropped)
        ));
    }
    if !partial.is_empty() {
        msg.push_str(&format!(
            "; averaged over the draws where tracked: {}",
            show(&partial)
        ));
    }
    findings.push(Finding::new(
        Severity::Warning,
        "update.residual_label_lost",
        msg,
    ));
}

#[cfg(test)]
mod convergence_tests {
    use super::*;
    use crate::bayes::diagnostics::summarize;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use rand_distr::{Distribution, Normal};

    fn row(name: &str, chains: &[Vec<f64>]) -> SummaryRow {
        SummaryRow {
            parameter: name.into(),
            board_id: None,
            measurement_id: Some("M001".into()),
            s: summarize(chains),
            physical: None,
        }
    }

    fn chains(seed: u64, shifts: &[f64], n: usize) -> Vec<Vec<f64>> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let d = Normal::new(0.0, 1.0).unwrap();
        shifts
            .iter()
            .map(|s| (0..n).map(|_| s + d.sample(&mut rng)).collect())
            .collect()
    }

    #[test]
    fn agreeing_runs_raise_nothing_and_disagreeing_runs_are_named() {
        let good = row("k_con_n_per_m", &chains(1, &[0.0, 0.0], 400));
        assert!(good.s.r_hat < MAX_R_HAT && good.s.ess_bulk > MIN_ESS);
        assert!(convergence_finding(&[good], 2).is_none());
        // Two runs in different modes (two sd apart): R-hat far above 1.05.
        let good = row("mu_ln_k_con", &chains(2, &[0.0, 0.0], 400));
        let bad = row("eps_plate-0-0", &chains(3, &[0.0, 2.0], 400));
        assert!(bad.s.r_hat > 1.3, "{}", bad.s.r_hat);
        let f = convergence_finding(&[good, bad], 2).expect("a warning");
        assert_eq!(f.code, "update.not_converged");
        assert!(f.message.contains("eps_plate-0-0 [M001]"), "{}", f.message);
        assert!(!f.message.contains("mu_ln_k_con"), "{}", f.message);
        // Too few effective draws: 2 runs of 30.
        let short = row("sigma_ln_k_con", &chains(4, &[0.0, 0.0], 30));
        let f = convergence_finding(&[short], 2).expect("a warning");
        assert!(f.message.contains("ESS below 100"), "{}", f.message);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A deviation carried to the sensitivities it was fitted with is itself; the kept
    /// coordinates never move; and on an analytic model (two modes λ_m = E a_m / (1 + E b_m / G),
    /// a shear-flexible plate's form) a board's E deviation fitted where G is 30 % too stiff,
    /// carried to the physical G, is the deviation the physical model gives the same
    /// frequencies (within 0.2 % of it at 2 %), where uncarried it is off by the
    /// sensitivities' ratio (0.7 %).
    #[test]
    fn a_deviation_carried_to_the_physical_centre_is_the_physical_models() {
        let s = [1.0, 0.3, 0.0, 0.8, 0.5, 0.2, 0.9, 0.1, 0.4];
        let dev = [0.02, -0.01, 0.005];
        let same = carried_deviation((&s, &s), 3, &[0, 1], &dev).unwrap();
        for (a, b) in same.iter().zip(&dev) {
            assert!((a - b).abs() < 1e-12, "{same:?}");
        }
        let other = [1.1, 0.3, 0.2, 0.7, 0.5, 0.3, 0.9, 0.2, 0.1];
        let moved = carried_deviation((&s, &other), 3, &[0, 1], &dev).unwrap();
        assert_eq!(moved[2], dev[2]);
        assert!((moved[0] - dev[0]).abs() > 1e-4, "{moved:?}");

        // Coordinates x = (ln E, ln G) about (E0, G); modes with shear shares 3 % and 8 %.
        let (e0, a, b) = (24e9, [1.0, 3.0], [0.03 / 24e9 * 3e9, 0.08 / 24e9 * 3e9]);
        let lambda = |x: &[f64], g: f64| -> Vec<f64> {
            let (e, g) = (e0 * x[0].exp(), g * x[1].exp());
            (0..2).map(|m| e * a[m] / (1.0 + e * b[m] / g)).collect()
        };
        let sens = |g: f64| {
            crate::bayes::discrepancy::sensitivities(|x| Some(lambda(x, g)), &[0.0, 0.0], 2, 1e-4)
                .unwrap()
        };
        let (g_phys, g_fit) = (3e9, 3.9e9);
        // The truth: a board 2 % stiffer in E at the physical G. Its relative eigenvalue shift
        // of the first mode alone fixes the fitted deviation (G held: a board's G is the
        // others').
        let d_true = 0.02;
        let shift = (lambda(&[d_true, 0.0], g_phys)[0] / lambda(&[0.0, 0.0], g_phys)[0]).ln();
        let (sf, sp) = (sens(g_fit), sens(g_phys));
        let d_fit = shift / sf[0];
        let carried = carried_deviation((&sf[..2], &sp[..2]), 1, &[0], &[d_fit, 0.0]).unwrap();
        assert!(
            (d_fit - d_true).abs() > 0.005 * d_true,
            "the fitted deviation is off by the sensitivities' ratio: {d_fit} vs {d_true}"
        );
        assert!(
            (carried[0] - d_true).abs() < 0.002 * d_true,
            "carried {} vs {d_true}",
            carried[0]
        );
    }
}

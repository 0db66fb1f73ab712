//! The per-assembly screen of `joint_stiffness_per_joint`: for each bolted assembly that
//! stands apart (by its shapes or frequencies), the Bayes factor of "its joints each have
//! their own stiffness" over "its joints share one", given the baseline step 2's posterior,
//! and which joint differs.
//!
//! The identity it rests on. Let M1 be the baseline M0 with, for the assemblies U only, a
//! contrast c_u ~ N(0, s² I) per joint (ln k_j = x0 + c_j − c̄; s = 0.7, the enrichment's
//! prior: a loose bolt halves a joint, a missing washer doubles it). Only U's likelihoods
//! change, and given the globals g (the population of ln k_con, the error scales) and the
//! step-1 draw the units are independent, so
//!   p(y | M1) / p(y | M0) = E_{g | y, M0} [ Π_{u ∈ U} Z1_u(g) / Z0_u(g) ],
//!   Zi_u(g) = ∫ p(θ_u | g, Mi) L_u(θ_u) dθ_u,
//! exactly: the expectation is over the baseline's posterior draws (its population table)
//! and each Z by importance sampling at its Laplace point ([`crate::bayes::laplace_is`]).
//! Both Z are computed with the enriched model's ROM (Z0 with every contrast 0), so the
//! ROMs' errors cancel. One assembly costs ~10³ ROM calls per draw, against ~10⁵ per
//! tempering stage for the every-joint SMC refit of all assemblies and their population.
//!
//! What it is not: the refit's model, whose contrasts have a population of their own
//! learnt across the assemblies. The screen's contrasts keep the prior's scale; with one
//! loose bolt in a few assemblies there is nothing for a population to learn but that
//! scale. The evidence of the two differs by how well that prior matches.

use std::sync::Arc;

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::Serialize;

use crate::bayes::laplace_is::{laplace_is, IsEvidence};
use crate::bayes::modal::{log_lik_with, ErrorLogs};
use crate::bayes::resample::systematic;
use crate::bayes::smc::{self, Target};
use crate::bayes::stats::{cholesky_jittered, ess, log_mean_exp, normalize};
use crate::bayes::target::ModalTarget;

/// One draw of the baseline step 2's posterior, as the screen needs it.
#[derive(Clone, Debug)]
pub struct BaselineDraw {
    /// The step-1 draw the particle carried (every board's parameters).
    pub aux: Arc<Vec<f64>>,
    /// The population of the contact stiffness in the unit coordinate x0 = ln(k / k_ref).
    pub mu: f64,
    pub sigma: f64,
    /// Error scales per mode (the target's order).
    pub eps: Vec<f64>,
    pub delta: Vec<f64>,
    /// A model-form discrepancy per mode and its per-unit sd (empty: none).
    pub bias: Vec<f64>,
    pub unit_sd: Vec<f64>,
}

/// Settings of the screen.
#[derive(Clone, Copy, Debug)]
pub struct ScreenOptions {
    /// Log-sd of a joint's stiffness ratio (the enrichment's prior).
    pub contrast_log_sd: f64,
    /// Importance draws per assembly and baseline draw (the 1-coordinate Z0 takes half).
    pub is_draws: usize,
    pub seed: u64,
    /// The practical threshold, relative frequency: a joint is named only where its own
    /// stiffness moves the assembly's modes by at least this much.
    pub practical_rel: f64,
    /// Equally weighted posterior draws kept per assembly ([`ScreenUnit::posterior`]).
    pub posterior_draws: usize,
}

/// One joint's stiffness over the geometric mean of the assembly's other joints.
#[derive(Clone, Debug, Serialize, PartialEq, schemars::JsonSchema)]
pub struct ScreenJoint {
    /// 1-based, hole order of the board file.
    pub joint: usize,
    pub ratio_median: f64,
    pub ratio_q05: f64,
    pub ratio_q95: f64,
}

/// The screen of one assembly.
#[derive(Clone, Debug, Serialize, PartialEq, schemars::JsonSchema)]
pub struct ScreenUnit {
    pub measurement_id: String,
    /// ln p(y_u | M1, baseline) − ln p(y_u | M0, baseline), averaged over the draws.
    pub log_bayes_factor: f64,
    pub log_bayes_factor_se: f64,
    pub joints: Vec<ScreenJoint>,
    /// The largest change of an updated mode's frequency, relative, between the assembly's
    /// fit with one stiffness and with the joints' own (at the posterior means); None where
    /// the model could not be evaluated there.
    pub freq_effect_rel: Option<f64>,
    /// The joint whose ratio is furthest from 1 with its 90 % interval excluding 1, where
    /// `freq_effect_rel` reaches the practical threshold (None: no joint differs).
    pub deviating_joint: Option<usize>,
    /// The smallest effective sample size of its importance weights over the draws.
    pub min_ess: f64,
    /// Equally weighted draws of the assembly's posterior under the screen's model (its
    /// joints' own stiffnesses), resampled from the pooled importance draws: the baseline
    /// draw each was drawn under (an index into the screen's draws) and the joints'
    /// log-stiffnesses y. For its posterior-predictive residuals; not written.
    #[serde(skip)]
    pub posterior: Vec<(usize, Vec<f64>)>,
}

/// The screen of every listed assembly together.
#[derive(Clone, Debug, Serialize, PartialEq, schemars::JsonSchema)]
pub struct JointScreen {
    pub units: Vec<ScreenUnit>,
    /// The Bayes factor of all the listed assemblies' joints at once (the refit's question);
    /// None where the screen failed.
    pub log_bayes_factor: Option<f64>,
    pub log_bayes_factor_se: Option<f64>,
    /// Baseline posterior draws averaged over.
    pub baseline_draws: usize,
    /// Baseline draws left out of the average (every assembly's), each with why: an
    /// assembly whose integrand could not be evaluated around its mode under that draw.
    #[serde(skip_serializing_if = "Vec::is_empty", default)]
    pub dropped_draws: Vec<String>,
    pub contrast_log_sd: f64,
    pub model_evals: u64,
    /// Why there is no screen (no draws, or more than half of them left out:
    /// `dropped_draws`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub failed: Option<String>,
    /// Rows of the screened assemblies' residuals averaged over part of the posterior draws
    /// or left out: a label whose mode could not be tracked, with the share of draws it was.
    #[serde(skip_serializing_if = "Vec::is_empty", default)]
    pub untracked: Vec<String>,
}

impl JointScreen {
    /// A screen that could not be run, and why (recorded, so the diagnosis says so).
    pub fn failed(why: String) -> JointScreen {
        JointScreen {
            units: vec![],
            log_bayes_factor: None,
            log_bayes_factor_se: None,
            baseline_draws: 0,
            dropped_draws: vec![],
            contrast_log_sd: 0.0,
            model_evals: 0,
            failed: Some(why),
            untracked: vec![],
        }
    }
}

/// The unit coordinates (x0, contrasts) of joint log-stiffnesses y (relative to k_ref):
/// x0 = ȳ and c_j = y_j − ȳ, so ln k_j = x0 + c_j − c̄ = y_j.
pub fn coords_of(y: &[f64]) -> Vec<f64> {
    let mean = y.iter().sum::<f64>() / y.len() as f64;
    std::iter::once(mean)
        .chain(y.iter().map(|v| v - mean))
        .collect()
}

/// The prior of y under M1: y = x0 1 + (I − J/n) c, x0 ~ N(μ, σ²), c ~ N(0, s² I), so
/// y ~ N(μ 1, σ² J + s² (I − J/n)); its mean and lower Cholesky factor.
pub fn joint_prior(n: usize, mu: f64, sigma: f64, s: f64) -> (Vec<f64>, Vec<f64>) {
    let inv = 1.0 / n as f64;
    let cov: Vec<f64> = (0..n * n)
        .map(|k| {
            let (i, j) = (k / n, k % n);
            sigma * sigma + s * s * (if i == j { 1.0 } else { 0.0 } - inv)
        })
        .collect();
    (vec![mu; n], cholesky_jittered(&cov, n).0)
}

/// The draws every one of `n_units` units could be evaluated under (`ok(u, r)`), and the
/// others, each with the first unit that could not.
fn split_draws(
    n_units: usize,
    n_draws: usize,
    ok: impl Fn(usize, usize) -> bool,
) -> (Vec<usize>, Vec<(usize, usize)>) {
    let mut kept = vec![];
    let mut dropped = vec![];
    for r in 0..n_draws {
        match (0..n_units).find(|&u| !ok(u, r)) {
            Some(u) => dropped.push((r, u)),
            None => kept.push(r),
        }
    }
    (kept, dropped)
}

/// ln E_r[exp(d_r)] over equally weighted draws, its standard error from the draws' spread
/// (1/ESS − 1/R of the weights) and the IS errors `se2` (variances) averaged by the
/// weights; and the normalised weights.
fn mean_exp(d: &[f64], se2: &[f64]) -> (f64, f64, Vec<f64>) {
    let w = normalize(d);
    let r = d.len() as f64;
    let var =
        (1.0 / ess(d) - 1.0 / r).max(0.0) + w.iter().zip(se2).map(|(a, b)| a * b).sum::<f64>();
    (log_mean_exp(d), var.sqrt(), w)
}

/// Weighted quantile q of values v (weights w summing to 1).
fn weighted_quantile(v: &[f64], w: &[f64], q: f64) -> f64 {
    let mut idx: Vec<usize> = (0..v.len()).collect();
    idx.sort_by(|&a, &b| v[a].total_cmp(&v[b]));
    let mut acc = 0.0;
    for &i in &idx {
        acc += w[i];
        if acc >= q {
            return v[i];
        }
    }
    idx.last().map_or(f64::NAN, |&i| v[i])
}

/// The screen of the assemblies `units` (unit index in `target`, measurement id), each with
/// `n_joints` joints, over the baseline's `draws`. `target` is the every-joint enriched
/// step-2 target (coordinates x0 and one contrast per joint).
pub fn screen_joints(
    target: &ModalTarget,
    n_joints: usize,
    units: &[(usize, String)],
    draws: &[BaselineDraw],
    opts: &ScreenOptions,
) -> JointScreen {
    let n = n_joints;
    let jobs: Vec<(usize, usize)> = (0..units.len())
        .flat_map(|u| (0..draws.len()).map(move |r| (u, r)))
        .collect();
    let one = |u: usize, r: usize| -> Option<(IsEvidence, IsEvidence)> {
        let b = units[u].0;
        let d = &draws[r];
        // As the target's context forms them (empty: no model error, no discrepancy).
        let logs = ErrorLogs::new(&d.eps, &d.delta)
            .with_model_error(&d.unit_sd)
            .with_bias(&d.bias);
        let ll = |y: &[f64]| -> Option<f64> {
            let x = coords_of(y);
            let t = target.model(&d.aux, b, &x)?;
            let v = log_lik_with(&target.units[b], &t, &d.eps, &d.delta, &logs);
            v.is_finite().then_some(v)
        };
        let key = |which: u64| smc::stream_key(&[opts.seed, 0x15, which, b as u64, r as u64]);
        let ll0 = |x0: &[f64]| ll(&vec![x0[0]; n]);
        let z0 = laplace_is(
            &[d.mu],
            &[d.sigma],
            &ll0,
            &[d.mu],
            (opts.is_draws / 2).max(50),
            &mut ChaCha8Rng::seed_from_u64(key(0)),
        )?;
        let (m, l) = joint_prior(n, d.mu, d.sigma, opts.contrast_log_sd);
        let z1 = laplace_is(
            &m,
            &l,
            &ll,
            &vec![z0.mode[0]; n],
            opts.is_draws,
            &mut ChaCha8Rng::seed_from_u64(key(1)),
        )?;
        Some((z0, z1))
    };
    let results: Vec<Option<(IsEvidence, IsEvidence)>> =
        jobs.par_iter().map(|&(u, r)| one(u, r)).collect();
    let model_evals = results
        .iter()
        .flatten()
        .map(|(a, b)| a.evals + b.evals)
        .sum();
    let empty = |why: String| JointScreen {
        baseline_draws: draws.len(),
        contrast_log_sd: opts.contrast_log_sd,
        model_evals,
        ..JointScreen::failed(why)
    };
    if draws.is_empty() || units.is_empty() {
        return empty("no baseline draws or no assemblies to screen".into());
    }
    // A draw under which some assembly's integrand cannot be evaluated around its mode (on
    // the realistic loose-bolt campaign one of 16 draws: none of a loose assembly's 300
    // importance draws had a prediction, though its mode had) is left out of the average
    // for every assembly, and said. With more than half of them left out, the average no
    // longer stands for the baseline's posterior but for a minority of it: no screen.
    let (kept, dropped) = split_draws(units.len(), draws.len(), |u, r| {
        results[u * draws.len() + r].is_some()
    });
    let dropped_draws: Vec<String> = dropped
        .iter()
        .map(|&(r, u)| {
            format!(
                "baseline draw {r}: {}: the likelihood could not be evaluated near its mode",
                units[u].1
            )
        })
        .collect();
    if kept.len() < dropped.len() || kept.is_empty() {
        return empty(format!(
            "{} of {} baseline draws could not be evaluated, e.g. {}",
            dropped.len(),
            draws.len(),
            dropped_draws[0]
        ));
    }
    let at = |u: usize, r: usize| results[u * draws.len() + r].as_ref().expect("kept");
    let mut total_d = vec![0.0; kept.len()];
    let mut total_se2 = vec![0.0; kept.len()];
    let mut out_units = vec![];
    for (u, (_, name)) in units.iter().enumerate() {
        let d: Vec<f64> = kept
            .iter()
            .map(|&r| at(u, r).1.log_z - at(u, r).0.log_z)
            .collect();
        let se2: Vec<f64> = kept
            .iter()
            .map(|&r| at(u, r).1.log_z_se.powi(2) + at(u, r).0.log_z_se.powi(2))
            .collect();
        for k in 0..kept.len() {
            total_d[k] += d[k];
            total_se2[k] += se2[k];
        }
        let (lbf, se, w) = mean_exp(&d, &se2);
        // The posterior of y under M1 pooled over the draws (each draw weighted by its
        // share of the Bayes factor).
        let mut ratios: Vec<Vec<f64>> = vec![vec![]; n];
        let mut weights = vec![];
        let mut pooled: Vec<(usize, &Vec<f64>)> = vec![];
        for (&r, wr) in kept.iter().zip(&w) {
            let z1 = &at(u, r).1;
            for (y, lw) in z1.draws.iter().zip(&z1.log_w) {
                weights.push(wr * lw.exp());
                pooled.push((r, y));
                for (j, rj) in ratios.iter_mut().enumerate() {
                    let others = (y.iter().sum::<f64>() - y[j]) / (n - 1) as f64;
                    rj.push((y[j] - others).exp());
                }
            }
        }
        let sw: f64 = weights.iter().sum();
        weights.iter_mut().for_each(|v| *v /= sw);
        let joints: Vec<ScreenJoint> = ratios
            .iter()
            .enumerate()
            .map(|(j, v)| ScreenJoint {
                joint: j + 1,
                ratio_median: weighted_quantile(v, &weights, 0.5),
                ratio_q05: weighted_quantile(v, &weights, 0.05),
                ratio_q95: weighted_quantile(v, &weights, 0.95),
            })
            .collect();
        // The frequency effect, at the draw that weighs most: the modes with the joints' own
        // stiffnesses (posterior mean) against those with the one stiffness (its mode).
        let r_top = kept[(0..w.len())
            .max_by(|&a, &b| w[a].total_cmp(&w[b]))
            .unwrap_or(0)];
        let mut y_mean = vec![0.0; n];
        for ((_, y), wi) in pooled.iter().zip(&weights) {
            for (m, v) in y_mean.iter_mut().zip(y.iter()) {
                *m += wi * v;
            }
        }
        let lambda = |y: &[f64]| {
            target
                .model(&draws[r_top].aux, units[u].0, &coords_of(y))
                .map(|t| t.lambda)
        };
        let freq_effect_rel = match (lambda(&y_mean), lambda(&vec![at(u, r_top).0.mode[0]; n])) {
            (Some(a), Some(b)) => Some(
                a.iter()
                    .zip(&b)
                    .map(|(x, y)| ((x / y).sqrt() - 1.0).abs())
                    .fold(0.0, f64::max),
            ),
            _ => None,
        };
        let deviating_joint = joints
            .iter()
            .filter(|_| freq_effect_rel.is_some_and(|e| e >= opts.practical_rel))
            .filter(|j| j.ratio_q95 < 1.0 || j.ratio_q05 > 1.0)
            .max_by(|a, b| {
                a.ratio_median
                    .ln()
                    .abs()
                    .total_cmp(&b.ratio_median.ln().abs())
            })
            .map(|j| j.joint);
        let min_ess = kept
            .iter()
            .map(|&r| at(u, r).1.ess.min(at(u, r).0.ess))
            .fold(f64::INFINITY, f64::min);
        let u0 = ChaCha8Rng::seed_from_u64(smc::stream_key(&[opts.seed, 0x16, u as u64]))
            .random::<f64>();
        let posterior = systematic(&weights, opts.posterior_draws, u0)
            .into_iter()
            .map(|i| (pooled[i].0, pooled[i].1.clone()))
            .collect();
        out_units.push(ScreenUnit {
            measurement_id: name.clone(),
            log_bayes_factor: lbf,
            log_bayes_factor_se: se,
            joints,
            freq_effect_rel,
            deviating_joint,
            min_ess,
            posterior,
        });
    }
    let (lbf, se, _) = mean_exp(&total_d, &total_se2);
    JointScreen {
        units: out_units,
        log_bayes_factor: Some(lbf),
        log_bayes_factor_se: Some(se),
        baseline_draws: draws.len(),
        dropped_draws,
        contrast_log_sd: opts.contrast_log_sd,
        model_evals,
        failed: None,
        untracked: vec![],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn coordinates_reproduce_the_joint_stiffnesses() {
        let y = [0.1, -0.5, 0.3, 0.02];
        let x = coords_of(&y);
        let cbar = x[1..].iter().sum::<f64>() / 4.0;
        for j in 0..4 {
            assert!((x[0] + x[1 + j] - cbar - y[j]).abs() < 1e-12);
        }
    }

    #[test]
    fn the_prior_of_the_joints_is_the_coordinates_prior() {
        // Monte Carlo of y = x0 1 + (I − J/n) c against the closed-form covariance.
        use rand_distr::{Distribution, StandardNormal};
        let (n, mu, sigma, s) = (4, 0.2, 0.3, 0.7);
        let (m, l) = joint_prior(n, mu, sigma, s);
        let mut cov = vec![0.0; n * n];
        for i in 0..n {
            for j in 0..n {
                cov[i * n + j] = (0..n).map(|k| l[i * n + k] * l[j * n + k]).sum();
            }
        }
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let k = 200_000;
        let mut acc = vec![0.0; n * n];
        let mut mean = vec![0.0; n];
        for _ in 0..k {
            let x0 = mu
                + sigma * <StandardNormal as Distribution<f64>>::sample(&StandardNormal, &mut rng);
            let c: Vec<f64> = (0..n)
                .map(|_| {
                    s * <StandardNormal as Distribution<f64>>::sample(&StandardNormal, &mut rng)
                })
                .collect();
            let cbar = c.iter().sum::<f64>() / n as f64;
            let y: Vec<f64> = c.iter().map(|v| x0 + v - cbar).collect();
            for i in 0..n {
                mean[i] += y[i] / k as f64;
                for j in 0..n {
                    acc[i * n + j] += (y[i] - mu) * (y[j] - mu) / k as f64;
                }
            }
        }
        for i in 0..n {
            assert!((mean[i] - m[i]).abs() < 0.01);
            for j in 0..n {
                assert!((acc[i * n + j] - cov[i * n + j]).abs() < 0.01, "{i},{j}");
            }
        }
    }

    #[test]
    fn mean_exp_of_equal_draws_is_their_value_with_the_is_error() {
        let (l, se, w) = mean_exp(&[2.0, 2.0, 2.0, 2.0], &[0.01, 0.01, 0.01, 0.01]);
        assert!((l - 2.0).abs() < 1e-12);
        assert!((se - 0.1).abs() < 1e-12);
        assert!(w.iter().all(|v| (v - 0.25).abs() < 1e-12));
        // One draw dominating: ln mean exp ≈ its value − ln R, with a large spread error.
        let (l, se, _) = mean_exp(&[0.0, 0.0, 10.0], &[0.0; 3]);
        assert!((l - (10.0 - 3f64.ln())).abs() < 1e-3);
        assert!(se > 0.8, "{se}");
    }

    /// A draw is kept only where every unit could be evaluated under it; a dropped draw
    /// names the first unit that could not.
    #[test]
    fn a_draw_any_unit_fails_under_is_left_out_for_all() {
        let bad = [(1usize, 2usize), (0, 2), (2, 4)];
        let (kept, dropped) = split_draws(3, 6, |u, r| !bad.contains(&(u, r)));
        assert_eq!(kept, vec![0, 1, 3, 5]);
        assert_eq!(dropped, vec![(2, 0), (4, 2)]);
        let (kept, dropped) = split_draws(2, 3, |_, _| true);
        assert_eq!((kept, dropped), (vec![0, 1, 2], vec![]));
    }

    #[test]
    fn weighted_quantiles() {
        let v = [3.0, 1.0, 2.0, 4.0];
        let w = [0.25; 4];
        assert_eq!(weighted_quantile(&v, &w, 0.5), 2.0);
        assert_eq!(weighted_quantile(&v, &w, 0.05), 1.0);
        assert_eq!(weighted_quantile(&v, &w, 0.95), 4.0);
    }
}

//! What propagation takes from the update steps' outputs, pure: the labels to predict and
//! their model modes, the validation modes' repeatability, the measured boards' mean
//! eigenvalues, the model-error prior, and the ROM an update step ran with (a truncation).

use super::propagate::{repeatability_eps, BoardMean};
use crate::diagnose::locate::ResidualObs;
use crate::fem::Rom;
use crate::findings::{Finding, Findings, Severity};
use std::collections::{BTreeMap, BTreeSet};

/// Labels of a setup's accepted pairs (`pairs`: setup, label, model mode 1-based) with their
/// most frequent model mode (0-based), in model order; labels whose mode lies beyond the ROM's
/// `rom_modes` are reported and left out.
pub fn labels_of<'a>(
    pairs: impl IntoIterator<Item = (&'a str, &'a str, i32)>,
    setup: &str,
    rom_modes: usize,
    findings: &mut Findings,
) -> (Vec<String>, Vec<usize>) {
    let mut by: BTreeMap<String, BTreeMap<i32, usize>> = BTreeMap::new();
    for (s, l, mm) in pairs {
        if s != setup {
            continue;
        }
        *by.entry(l.to_string()).or_default().entry(mm).or_default() += 1;
    }
    let mut v = vec![];
    for (l, counts) in by {
        let Some((mm, _)) = counts.into_iter().max_by_key(|(m, n)| (*n, -*m)) else {
            continue;
        };
        if mm < 1 || mm as usize > rom_modes {
            findings.push(Finding::new(
                Severity::Warning,
                "propagate.label_beyond_rom",
                format!("{setup} mode {l:?} pairs with model mode {mm}, beyond the ROM's {} modes; not predicted (build the ROM with more modes: `hbmu fe rom --n-modes`)", rom_modes),
            ));
            continue;
        }
        v.push(((mm - 1) as usize, l));
    }
    v.sort();
    (
        v.iter().map(|(_, l)| l.clone()).collect(),
        v.iter().map(|(m, _)| *m).collect(),
    )
}

/// Per free label not used for updating, the relative eigenvalue error its repeat
/// measurements show ([`crate::uq::propagate::repeatability_eps`], boards as groups), from
/// the step-1 residuals (`rows`); `None` for updated labels and where there are too few repeats. The
/// values used are reported as an info finding.
pub fn repeatability(
    rows: &[ResidualObs],
    labels: &[String],
    findings: &mut Findings,
) -> Vec<Option<f64>> {
    let mut groups: BTreeMap<&str, BTreeMap<&str, Vec<f64>>> = BTreeMap::new();
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
            repeatability_eps(&g)
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
    out
}

/// Per board (order of `board_ids`) and free label: the mean measured eigenvalue (2π f̂)²
/// over the board's measurements in the step-1 residuals (`rows`) and their number; `None` for a
/// label not updated or without a measurement of the board.
pub fn board_offsets(
    rows: &[ResidualObs],
    board_ids: &[String],
    labels: &[String],
    updated: &BTreeSet<String>,
) -> Vec<Vec<Option<BoardMean>>> {
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
    board_ids
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
        .collect()
}

/// The model-error term's prior sd per free label from step 1's evidence.json
/// (`model_error`: `labels`, `sd`; `ev` is the document, None when there is none, `source` names
/// it in messages); zeros when step 1 ran without it, or where its discrepancy took it
/// (`per_board: false`). A label step 1 did not
/// give an sd (paired differently since) gets the largest of the others, and a finding.
pub fn model_error_sd(
    ev: Option<&serde_json::Value>,
    source: &str,
    labels: &[String],
    findings: &mut Findings,
) -> Result<Vec<f64>, String> {
    let Some(ev) = ev else {
        return Ok(vec![0.0; labels.len()]);
    };
    let me = &ev["model_error"];
    if me.is_null() {
        return Ok(vec![0.0; labels.len()]);
    }
    // `per_board: false`: the discrepancy common to the boards took the term (step 1's
    // `ModelErrorPrior::common_to_boards`); absent in step-1 outputs from before it existed,
    // where the term was each board's.
    match &me["per_board"] {
        serde_json::Value::Null | serde_json::Value::Bool(true) => {}
        serde_json::Value::Bool(false) => return Ok(vec![0.0; labels.len()]),
        other => {
            return Err(format!(
                "{source}: model_error: expected `per_board` true or false, found {other}"
            ))
        }
    }
    let (Some(ls), Some(sd)) = (me["labels"].as_array(), me["sd"].as_array()) else {
        return Err(format!(
            "{}: model_error: expected arrays `labels` and `sd`",
            source
        ));
    };
    if ls.len() != sd.len() {
        return Err(format!(
            "{}: model_error: expected as many sds as labels, found {} labels and {} sds",
            source,
            ls.len(),
            sd.len()
        ));
    }
    let mut by_label = BTreeMap::new();
    for (l, v) in ls.iter().zip(sd) {
        match (l.as_str(), v.as_f64()) {
            (Some(l), Some(v)) if v.is_finite() && v >= 0.0 => {
                by_label.insert(l.to_string(), v);
            }
            _ => {
                return Err(format!(
                    "{}: model_error: expected a label and a finite sd ≥ 0, found {l} and {v}",
                    source
                ))
            }
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
                source
            ),
        ));
    }
    Ok(out)
}

/// Positions of the posterior's `params` among the ROM's parameters; the error names the
/// first missing one.
pub fn positions(rom: &Rom, params: &[String]) -> Result<Vec<usize>, String> {
    params
        .iter()
        .map(|p| {
            rom.map.names.iter().position(|n| n == p).ok_or_else(|| {
                format!("the posterior's parameter {p:?} is not a parameter of this ROM (expected one of {:?})", rom.map.names)
            })
        })
        .collect()
}

/// The ROM's first `r` basis vectors: the ROM an update stage ran with when it capped the basis
/// (`--rom-basis r`). The basis is an M-orthonormalised POD basis ordered by singular value, so
/// a ROM built with a cap of r spans the first r vectors of one built with a larger cap (same
/// snapshots and options), and its reduced matrices are the leading r × r blocks.
pub fn truncate_rom(rom: Rom, r: usize) -> Rom {
    if r >= rom.dim() {
        return rom;
    }
    let lead = |m: &faer::Mat<f64>| faer::Mat::from_fn(r, r, |i, j| m[(i, j)]);
    let mut cut = Rom::from_parts(
        rom.map.clone(),
        rom.k_r.iter().map(lead).collect(),
        rom.m_r.iter().map(lead).collect(),
        faer::Mat::from_fn(rom.basis.nrows(), r, |i, j| rom.basis[(i, j)]),
        rom.n_rigid,
        rom.n_modes,
        rom.setup.clone(),
    );
    cut.built_box = rom.built_box;
    cut
}

/// The `fe rom` stage's ROM cut to the one an update step sampled on when it ran with the
/// basis cap `cap` (`--rom-basis`): the updating raises that cap for the model's own
/// logarithmic axes and a split mass ([`crate::fem::rom::updating_basis`]), and so must the cut.
/// Cut to the bare cap, a shear-deformable board's ROM lost the vectors its G_z axis needs.
pub fn as_updated(rom: Rom, cap: usize) -> Rom {
    let r = crate::fem::rom::updating_basis(&rom.map, cap, &[]);
    truncate_rom(rom, r)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Step 1's model-error sds reach propagate where they were each board's own term
    /// (`per_board` true, or absent in outputs from before the field), by label, a label
    /// without one taking the largest with a finding; none where the common discrepancy took
    /// the term (`per_board` false) or step 1 had none; a malformed `per_board` is an error
    /// naming the file.
    #[test]
    fn the_model_error_sds_reach_propagate_only_where_they_are_each_boards_own() {
        let labels: Vec<String> = ["a", "b", "c"].iter().map(|s| s.to_string()).collect();
        let doc = |per_board: serde_json::Value| {
            let mut me = serde_json::json!({"labels": ["a", "b"], "sd": [1e-4, 3e-4]});
            if !per_board.is_null() {
                me["per_board"] = per_board;
            }
            serde_json::json!({ "model_error": me })
        };
        for pb in [serde_json::Value::Null, serde_json::json!(true)] {
            let mut f = Findings::default();
            let sd = model_error_sd(Some(&doc(pb.clone())), "ev.json", &labels, &mut f).unwrap();
            assert_eq!(sd, vec![1e-4, 3e-4, 3e-4], "per_board {pb}");
            assert_eq!(f.0.len(), 1, "{:?}", f.0);
            assert_eq!(f.0[0].code, "propagate.model_error_missing");
        }
        let mut f = Findings::default();
        let none = vec![0.0; 3];
        let common = doc(serde_json::json!(false));
        assert_eq!(
            model_error_sd(Some(&common), "ev.json", &labels, &mut f),
            Ok(none.clone())
        );
        let absent = serde_json::json!({"model_error": null});
        assert_eq!(
            model_error_sd(Some(&absent), "ev.json", &labels, &mut f),
            Ok(none.clone())
        );
        assert_eq!(model_error_sd(None, "ev.json", &labels, &mut f), Ok(none));
        assert!(f.0.is_empty(), "{:?}", f.0);
        let bad = doc(serde_json::json!("no"));
        let err = model_error_sd(Some(&bad), "ev.json", &labels, &mut f).unwrap_err();
        assert!(
            err.contains("ev.json") && err.contains("per_board"),
            "{err}"
        );
    }
    use crate::fem::model::Setup;
    use crate::fem::rom::RomOptions;
    use crate::fem::tests::helpers::{build, plain_board};

    /// On a shear-deformable board the `fe rom` stage's ROM, cut for a step that ran with a cap
    /// of 12, is the ROM that step built (`update::rom_box::rom_for`), along the G_z axis as
    /// well. Cut to the bare 12 it was not: on the realistic null it put the free bending-y-1
    /// 8e-4 above the full model at the boards' posterior medians.
    #[test]
    fn the_fe_rom_cut_for_a_capped_step_is_that_steps_rom_on_a_shear_deformable_board() {
        let mut board = plain_board(0.2, 0.15, 1.6e-3, 24e9, 20e9, 8e9, 0.15, 1900.0);
        board.core.g_xz_pa = Some(3e9);
        board.core.g_yz_pa = Some(3e9);
        let fe = build(&board, Setup::Free, 8, 6);
        // As `fe rom` builds it (src/stage/fe.rs).
        let axes = crate::fem::rom::with_own_log_axes(&fe.map, &[]);
        assert_eq!(axes.len(), 1, "G_z is a log axis");
        let stage_rom = Rom::build(
            &fe,
            &RomOptions {
                max_basis: crate::fem::rom::basis_cap(RomOptions::default().max_basis, 1),
                log_axes: axes,
                ..RomOptions::default()
            },
        )
        .unwrap();
        let spec = crate::update::problem::ModelSpec {
            rom_max_basis: Some(12),
            g_z_log_box: None,
            ..crate::update::problem::ModelSpec::for_tests()
        };
        let step_rom = crate::update::rom_box::rom_for(&fe, 4, &[], &spec).unwrap();
        let cut = as_updated(stage_rom.clone(), 12);
        assert!(step_rom.dim() > 12, "the cap is raised: {}", step_rom.dim());
        assert_eq!(cut.dim(), step_rom.dim());
        let bare = truncate_rom(stage_rom, 12);
        let k = fe
            .map
            .nominal_params()
            .position(crate::fem::params::names::G_Z)
            .unwrap();
        let mut worst_bare = 0.0f64;
        for mut p in crate::fem::rom::latin_hypercube_params(&fe.map, 4, 0.2, 5) {
            for g in [1.6e9, 3e9, 5.8e9] {
                p.values[k] = g;
                let c = fe.map.coefficients(&p).unwrap();
                let a = step_rom.eval_lowest(&c.k, &c.m, 4).unwrap();
                let b = cut.eval_lowest(&c.k, &c.m, 4).unwrap();
                let z = bare.eval_lowest(&c.k, &c.m, 4).unwrap();
                for j in 0..4 {
                    let e = (a.eigenvalues[j] - b.eigenvalues[j]).abs() / a.eigenvalues[j];
                    assert!(e < 1e-9, "G_z {g:e}, mode {j}: step vs cut differ by {e:e}");
                    let e = (a.eigenvalues[j] - z.eigenvalues[j]).abs() / a.eigenvalues[j];
                    worst_bare = worst_bare.max(e);
                }
            }
        }
        // What the cut must not lose: the bare cap is visibly another model.
        assert!(worst_bare > 1e-6, "bare cap differs by only {worst_bare:e}");
    }

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

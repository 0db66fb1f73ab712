//! The ROM a step samples on and its checks against the full model: at its centre, over its
//! box and where the posterior lies; the box rule's violation.

use crate::bayes::smc::{self};
use crate::bayes::target::ModalTarget;
use crate::fem::{FeModel, Rom, RomOptions};
use crate::findings::{Finding, Findings, Severity};
use crate::update::problem::ModelSpec;
use crate::update::sampler::{particles_of, Results};

/// The updating's ROM of `model` ([`rom_options_for`]).
pub fn rom_for(
    model: &FeModel,
    n_modes_needed: usize,
    log_axes: &[(String, f64)],
    opts: &ModelSpec,
) -> anyhow::Result<Rom> {
    Ok(Rom::build(
        model,
        &rom_options_for(model, n_modes_needed, log_axes, opts),
    )?)
}

/// The options of the updating's ROM of `model`: `n_modes_needed` modes, the step's box, the
/// basis cap raised for the log axes ([`crate::fem::rom::updating_basis`]).
pub fn rom_options_for(
    model: &FeModel,
    n_modes_needed: usize,
    log_axes: &[(String, f64)],
    opts: &ModelSpec,
) -> RomOptions {
    let d = RomOptions::default();
    let log_axes = &rom_log_axes(&model.map, log_axes, opts);
    let max_basis = crate::fem::rom::updating_basis(
        &model.map,
        opts.rom_max_basis.unwrap_or(d.max_basis),
        log_axes,
    );
    RomOptions {
        n_modes: n_modes_needed.max(d.n_modes),
        box_rel: opts.rom_box,
        max_basis,
        log_axes: log_axes.to_vec(),
        ..d
    }
}

/// The logarithmic axes of the updating's ROM of a model with parameter map `map`:
/// `log_axes` (an enrichment's), the transverse shear modulus's at the spec's width where step 1
/// widened it, then the map's own ([`crate::fem::rom::with_own_log_axes`]).
pub fn rom_log_axes(
    map: &crate::fem::params::ParamMap,
    log_axes: &[(String, f64)],
    opts: &ModelSpec,
) -> Vec<(String, f64)> {
    let g_z = crate::fem::params::names::G_Z;
    let mut axes = log_axes.to_vec();
    if let Some(w) = opts.g_z_log_box {
        if map.names.iter().any(|n| n == g_z) && !axes.iter().any(|(n, _)| n == g_z) {
            axes.push((g_z.to_string(), w));
        }
    }
    crate::fem::rom::with_own_log_axes(map, &axes)
}

/// The half-width that holds a sampled reach (relative, or ln on a log axis): 15 % beyond it,
/// rounded up to the next 0.05. Step 1's box and both steps' shear-modulus axis use it.
pub fn holding(reach: f64) -> f64 {
    (reach * 1.15 / 0.05).ceil() * 0.05
}

/// Widest half-width (ln) of the transverse shear modulus's axis step 1 rebuilds to: × or ÷ 4
/// about the board file's value. Micromechanics puts woven FR-4's modulus within ±17 % of its
/// middle (`update::boards::G_Z_PRIOR_WIDTH`); a posterior beyond a factor 4 has the parameter
/// absorbing something else, and the board file or `--params` needs changing, not the ROM.
pub const MAX_G_Z_LOG_BOX: f64 = 1.3862943611198906;

/// Widest ROM box step 1 rebuilds to, relative half-width: beyond it a parameter is so far from
/// the board file's value, or so little informed, that the board file (or `--params`) needs
/// changing, not the ROM.
pub const MAX_ROM_BOX: f64 = 0.5;

/// Step 1's reference (before sampling) or posterior pressing against the ROM's box: which
/// (`by`: "reference" or "posterior"), the stage's message, and the relative half-width (and,
/// where the transverse shear modulus's axis is pressed, its ln half-width) that would hold
/// what was drawn.
#[derive(Debug)]
pub struct RomBoxViolation {
    pub by: &'static str,
    pub message: String,
    pub needed_half_width: f64,
    pub needed_g_z_log_box: Option<f64>,
}

impl std::fmt::Display for RomBoxViolation {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.message)
    }
}

impl std::error::Error for RomBoxViolation {}

/// The spec step 1 runs again with after `v`: its box widened to what holds the posterior,
/// the shear modulus's axis too where it was pressed; `None` where that exceeds
/// [`MAX_ROM_BOX`] or [`MAX_G_Z_LOG_BOX`], or widens nothing (the stage then stops with
/// `v`'s message).
pub fn widened(spec: &ModelSpec, v: &RomBoxViolation) -> Option<ModelSpec> {
    let g_z = v.needed_g_z_log_box;
    if v.needed_half_width > MAX_ROM_BOX
        || g_z.is_some_and(|w| w > MAX_G_Z_LOG_BOX)
        || (v.needed_half_width <= spec.rom_box && g_z.is_none())
    {
        return None;
    }
    Some(ModelSpec {
        rom_box: v.needed_half_width.max(spec.rom_box),
        g_z_log_box: g_z.or(spec.g_z_log_box),
        ..spec.clone()
    })
}

/// The ROM against the full model at the ROM's centre (one full solve): the worst relative
/// frequency error of the `n_modes` lowest modes, as an info finding, a warning above 1e-5
/// (the order of the measurements' frequency noise). A ROM is exact at its centre up to
/// round-off; anything more is a construction error (as a mass coefficient other than 1
/// at the centre once was: every frequency 0.39 % high).
pub fn rom_centre_check(
    model: &FeModel,
    rom: &Rom,
    n_modes: usize,
    findings: &mut Findings,
) -> anyhow::Result<()> {
    let worst = worst_frequency_error(model, rom, &[model.nominal_params()], n_modes)?;
    findings.push(Finding::new(
        if worst > 1e-5 {
            Severity::Warning
        } else {
            Severity::Info
        },
        "update.rom_centre_check",
        format!(
            "the ROM's {n_modes} lowest frequencies at its centre differ from the full model's by at most {:.2e} (relative)",
            worst
        ),
    ));
    Ok(())
}

/// The worst relative difference between the ROM's and the full model's `n_modes` lowest
/// frequencies over `points` (one full solve each).
pub fn worst_frequency_error(
    model: &FeModel,
    rom: &Rom,
    points: &[crate::fem::Params],
    n_modes: usize,
) -> anyhow::Result<f64> {
    use rayon::prelude::*;
    let sop = rom.shape_operator(model, &[[0.0, 0.0]])?;
    // One sequential sparse factorisation per point, the points in parallel (the maximum
    // does not depend on the order).
    let per_point: Vec<f64> = points
        .par_iter()
        .map(|p| -> anyhow::Result<f64> {
            let full = model.modes(p, n_modes)?;
            let red = rom.eval(p, &sop)?;
            Ok(red
                .freq_hz
                .iter()
                .zip(&full.freq_hz)
                .take(n_modes)
                .map(|(a, b)| (a - b).abs() / b)
                .fold(0.0f64, f64::max))
        })
        .collect::<anyhow::Result<_>>()?;
    Ok(per_point.into_iter().fold(0.0f64, f64::max))
}

/// The ROM's worst relative frequency error against the full model over the first `n_modes`
/// modes, at 8 Latin-hypercube points of its box (a design apart from the build's): ±`box_rel`,
/// and its logarithmic axes (the transverse shear modulus's, an enrichment's) over the widths
/// it was built for.
pub fn rom_box_check(
    model: &FeModel,
    rom: &Rom,
    box_rel: f64,
    n_modes: usize,
) -> anyhow::Result<f64> {
    let points = rom_box_points(&model.map, rom.built_box.as_ref(), box_rel);
    worst_frequency_error(model, rom, &points, n_modes)
}

/// [`rom_box_check`]'s 8 points: ±`box_rel`, and the logarithmic axes the ROM records it was
/// built over (`built`) over their widths.
fn rom_box_points(
    map: &crate::fem::params::ParamMap,
    built: Option<&crate::fem::rom::RomBox>,
    box_rel: f64,
) -> Vec<crate::fem::Params> {
    let log_axes = built.map_or(&[][..], |b| b.log_axes.as_slice());
    crate::fem::rom::latin_hypercube_params_log(map, 8, box_rel, log_axes, 0x00B0_C5EC)
}

/// The ROM against the full model where the posterior lies: at `n_points` particles spread
/// evenly over every run's output (each at one unit, cycling through the units), the worst
/// relative difference of the `n_modes` lowest frequencies, and the smallest relative
/// frequency noise of the updated modes (half the posterior median of ε, which is relative on
/// λ = ω²) it is to be compared with. The box checks ask whether the ROM holds over its box;
/// this asks whether it holds where the answer is, at the accuracy the answer claims.
pub fn rom_posterior_check(
    model: &FeModel,
    target: &ModalTarget,
    results: &Results,
    n_points: usize,
    n_modes: usize,
) -> anyhow::Result<(f64, f64)> {
    let all = particles_of(results);
    let n = n_points.min(all.len());
    let points: Vec<crate::fem::Params> = (0..n)
        .map(|k| {
            let (_, _, p) = all[k * all.len() / n];
            let b = k % target.units.len();
            let mut params = model.nominal_params();
            params.values = target.values(&p.aux, b, &p.x[b]);
            params
        })
        .collect();
    let worst = worst_frequency_error(model, &target.predictor.rom, &points, n_modes)?;
    let mut eps: Vec<Vec<f64>> = vec![vec![]; target.errors.n_modes];
    for (_, _, p) in &all {
        let ctx = smc::Target::ctx(target, &p.g);
        for (m, e) in ctx.eps.iter().enumerate() {
            eps[m].push(*e);
        }
    }
    let noise = eps
        .iter_mut()
        .map(|v| {
            v.sort_by(f64::total_cmp);
            0.5 * v[v.len() / 2]
        })
        .fold(f64::INFINITY, f64::min);
    Ok((worst, noise))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn violation(linear: f64, g_z: Option<f64>) -> RomBoxViolation {
        RomBoxViolation {
            by: "posterior",
            message: String::new(),
            needed_half_width: linear,
            needed_g_z_log_box: g_z,
        }
    }

    /// The box check moves a parameter the ROM was built over on a logarithmic axis across
    /// that axis (a widened shear modulus, × or ÷ 4 here), the others across ±box_rel; without
    /// a recorded box, every parameter across ±box_rel.
    #[test]
    fn the_box_check_covers_the_axes_the_rom_was_built_over() {
        let g_z = crate::fem::params::names::G_Z;
        let map = crate::fem::params::ParamMap {
            names: vec!["e_x_pa".into(), g_z.into()],
            nominal: vec![24e9, 3e9],
            k_coefs: vec![],
            m_coefs: vec![],
            core_idx: [0; 4],
        };
        let built = crate::fem::rom::RomBox {
            box_rel: 0.2,
            log_axes: vec![(g_z.into(), MAX_G_Z_LOG_BOX)],
        };
        let rel = |p: &crate::fem::Params, k: usize| p.values[k] / map.nominal[k];
        let wide = rom_box_points(&map, Some(&built), 0.2);
        assert_eq!(wide.len(), 8);
        assert!(wide.iter().all(|p| (rel(p, 0) - 1.0).abs() <= 0.2 + 1e-12));
        assert!(wide
            .iter()
            .all(|p| rel(p, 1).ln().abs() <= MAX_G_Z_LOG_BOX + 1e-12));
        // 8 Latin-hypercube strata over ln 4 either way: some beyond × or ÷ 2.
        assert!(wide
            .iter()
            .any(|p| rel(p, 1).ln().abs() > std::f64::consts::LN_2));
        let plain = rom_box_points(&map, None, 0.2);
        assert!(plain.iter().all(|p| (rel(p, 1) - 1.0).abs() <= 0.2 + 1e-12));
    }

    /// Step 1 widens what the posterior pressed, up to the widest boxes, and nothing else.
    #[test]
    fn the_box_widens_what_was_pressed_and_stops_beyond_the_widest() {
        let spec = ModelSpec::for_tests();
        let w = widened(&spec, &violation(0.3, None)).expect("a wider linear box");
        assert_eq!((w.rom_box, w.g_z_log_box), (0.3, None));
        // The shear modulus's axis alone: the linear box stays.
        let w = widened(&spec, &violation(0.15, Some(1.0))).expect("a wider shear axis");
        assert_eq!((w.rom_box, w.g_z_log_box), (spec.rom_box, Some(1.0)));
        // The ROM's own axes follow the spec: the shear modulus's at the wider width.
        let model = crate::fem::FeModel::build(
            &crate::fem::Board::default_board(),
            crate::fem::Setup::Free,
            &crate::fem::MeshOptions { nx: 16, ny: 10 },
        )
        .unwrap();
        let g_z = crate::fem::params::names::G_Z.to_string();
        let axes = rom_log_axes(&model.map, &[], &w);
        assert_eq!(axes, vec![(g_z.clone(), 1.0)]);
        let axes = rom_log_axes(&model.map, &[], &spec);
        assert_eq!(axes, vec![(g_z, crate::fem::rom::G_Z_LOG_BOX)]);
        // Beyond the widest, or nothing to widen: the stage stops.
        assert!(widened(&spec, &violation(MAX_ROM_BOX + 0.05, None)).is_none());
        assert!(widened(&spec, &violation(0.3, Some(MAX_G_Z_LOG_BOX + 0.05))).is_none());
        assert!(widened(&spec, &violation(spec.rom_box, None)).is_none());
    }
}

//! Modal identification from measured spectra and pairing with model modes.
//!
//! This module owns the numerical path from one measurement's spectra (one complex
//! spectrum per scan point on a common frequency axis, single reference) to a list of
//! identified modes (natural frequency, damping ratio, real-normalised shape at the scan
//! points, quality indicators), and from there to a one-to-one pairing with the modes of a
//! finite-element model. Everything here is a pure function over plain data: no file I/O,
//! no global state, randomness only through an explicit RNG argument (`frf` noise).
//!
//! Pipeline of [`extract`]:
//! 1. [`quality::screen_points`]: scan points with low coherence or a noise-like spectrum
//!    are excluded from the pole estimation (the reason is recorded).
//! 2. [`lscf::lscf_poles_with`]: least-squares complex-frequency (LSCF, common denominator,
//!    z-domain basis, built once per measurement) estimate of the poles for every model order
//!    of the stabilization diagram. Then
//!    `sk_passes` (default 1) Sanathanan–Koerner passes: the LSCF is rerun with line weights
//!    `1/|A(Omega)|` from the poles selected in the previous pass, which turns the linearised
//!    equation error into an approximate output error and removes the bias that otherwise
//!    merges modes closer than their half-power bandwidth (steps 3–4 run after every pass).
//! 3. [`stabilization::flag_stability`]: each pole is compared with the poles of the previous
//!    order (frequency, damping, shape).
//! 4. [`poles::select_physical_poles`]: automatic selection by clustering stable poles across
//!    orders; no list of approximate frequencies, no human.
//! 5. [`refine::refine_poles`]: each selected pole is refined by a local output-error
//!    (maximum-likelihood) fit, which removes the low-SNR damping bias of the linearised LSCF.
//! 6. [`lsfd::lsfd`]: residues and residual terms per scan point for the refined poles,
//!    real-normalised shapes, modal phase collinearity (MPC), mean phase deviation (MPD),
//!    fit error per scan point.
//! 7. Scan points whose fit error is an outlier are flagged and steps 2–6 are rerun without
//!    them (once).
//!
//! Pairing ([`pair`]) uses the modal assurance criterion ([`mac`]) and an optimal one-to-one
//! assignment ([`assign`]).
//!
//! Conventions: `lambda = -zeta*omega_n + i*omega_n*sqrt(1-zeta^2)` in rad/s; `freq_hz` is the
//! undamped natural frequency `|lambda| / (2 pi)`; `damping_ratio = -Re(lambda)/|lambda|`.
//! Spectra follow `H(omega) = sum_r [A_r/(i omega - lambda_r) + conj(A_r)/(i omega -
//! conj(lambda_r))] + sum_p c_p (i omega)^p` with real residual coefficients `c_p`.

pub mod assign;
pub mod frf;
mod linls;
pub mod lscf;
pub mod lsfd;
pub mod mac;
pub mod pair;
pub mod poles;
pub mod quality;
pub mod refine;
pub mod roots;
pub mod rows;
pub mod stabilization;

#[cfg(test)]
mod tests;

use faer::c64;
use serde::{Deserialize, Serialize};

pub use lscf::LscfParams;
pub use lsfd::LsfdParams;
pub use poles::SelectionParams;
pub use quality::{PointFlag, QualityParams};
pub use refine::RefineParams;
pub use stabilization::{StabilityParams, StabilizationDiagram};

/// Errors of the modal kernels. Each names what was expected and what was found.
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum ModalError {
    #[error("frequency axis: expected at least {expected} strictly increasing, finite, non-negative lines, found {found}")]
    FrequencyAxis { expected: usize, found: String },
    #[error(
        "scan point {index} (node {node_id}): expected {expected} spectral lines, found {found}"
    )]
    SpectrumLength {
        index: usize,
        node_id: i64,
        expected: usize,
        found: usize,
    },
    #[error("band: expected f_lo < f_hi inside [{axis_lo_hz}, {axis_hi_hz}] Hz with at least {min_lines} lines, found [{lo_hz}, {hi_hz}] Hz with {lines} lines")]
    Band {
        lo_hz: f64,
        hi_hz: f64,
        axis_lo_hz: f64,
        axis_hi_hz: f64,
        lines: usize,
        min_lines: usize,
    },
    #[error("expected at least {expected} usable scan points, found {found} ({excluded} excluded by screening)")]
    TooFewPoints {
        expected: usize,
        found: usize,
        excluded: usize,
    },
    #[error("model orders: expected 2 <= min_order <= max_order and order_step >= 1, found min {min}, max {max}, step {step}")]
    Orders { min: usize, max: usize, step: usize },
    #[error("numerical failure in {stage}: {detail}")]
    Numerical { stage: &'static str, detail: String },
    #[error("shape length mismatch in {context}: expected {expected}, found {found}")]
    ShapeLength {
        context: &'static str,
        expected: usize,
        found: usize,
    },
    #[error("invalid parameter {name}: expected {expected}, found {found}")]
    Param {
        name: &'static str,
        expected: &'static str,
        found: String,
    },
}

/// What the spectra measure; decides nothing in the fit by itself but chooses the default
/// residual terms (see [`LsfdParams::for_kind`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum FunctionKind {
    /// UFF function type 4 with velocity response: mobility in (m/s)/N, free-free.
    Mobility,
    /// UFF function type 5: base-excitation transmissibility (board velocity over base
    /// velocity), dimensionless; contains a rigid-body "1".
    Transmissibility,
    /// Anything else (receptance, accelerance): residual terms must be given explicitly.
    Other,
}

/// One scan point's spectrum (single reference).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PointSpectrum {
    /// Node id from the UFF (kept for traceability, never interpreted).
    pub node_id: i64,
    /// Real part of the ordinate at each line of the frequency axis.
    pub re: Vec<f64>,
    /// Imaginary part of the ordinate at each line.
    pub im: Vec<f64>,
    /// Ordinary coherence in [0, 1] at each line, if measured.
    pub coherence: Option<Vec<f64>>,
}

/// All spectra of one measurement on a common frequency axis.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MeasurementSpectra {
    /// Frequency axis in Hz, strictly increasing (evenly spaced in practice, not required).
    pub freq_hz: Vec<f64>,
    /// One spectrum per scan point, in the order the caller wants shapes reported.
    pub points: Vec<PointSpectrum>,
    pub kind: FunctionKind,
}

/// Parameters of [`extract`]. `Default` is meant to work on unseen campaigns; every
/// threshold is documented where it lives.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ExtractParams {
    /// Analysis band in Hz; `None` uses the whole axis above 0 Hz.
    pub band_hz: Option<(f64, f64)>,
    pub lscf: LscfParams,
    pub stability: StabilityParams,
    pub selection: SelectionParams,
    /// Residual terms of the LSFD; `None` chooses from [`FunctionKind`].
    pub lsfd: Option<LsfdParams>,
    pub quality: QualityParams,
    /// Rerun the pole estimation without the points flagged after the first LSFD
    /// (fit-error outliers). 1 = one rerun (default), 0 = none.
    pub refit_passes: usize,
    /// Local output-error (maximum-likelihood) refinement of the selected poles before the
    /// LSFD ([`refine`]); `None` keeps the LSCF cluster medians. Default on.
    pub refine: Option<RefineParams>,
    /// Sanathanan–Koerner passes: rerun the LSCF with line weights `1/|A|` built from the
    /// poles selected in the previous pass ([`lscf::sk_line_weights`]). Default 1: it is what
    /// separates close pairs; with the output-error refinement after it a second pass
    /// changes nothing measurable.
    pub sk_passes: usize,
}

impl Default for ExtractParams {
    fn default() -> Self {
        Self {
            band_hz: None,
            lscf: LscfParams::default(),
            stability: StabilityParams::default(),
            selection: SelectionParams::default(),
            lsfd: None,
            quality: QualityParams::default(),
            refit_passes: 1,
            sk_passes: 1,
            refine: Some(RefineParams::default()),
        }
    }
}

/// One identified mode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct IdentifiedMode {
    /// Undamped natural frequency `|lambda|/(2 pi)` in Hz.
    pub freq_hz: f64,
    /// Viscous damping ratio `-Re(lambda)/|lambda|` (dimensionless).
    pub damping_ratio: f64,
    /// Real-normalised shape at the scan points (largest |component| = +1); `NaN` at
    /// excluded points.
    pub shape: Vec<f64>,
    /// Complex residues per scan point (`NaN` at excluded points), units of the spectrum
    /// times rad/s.
    pub residue_re: Vec<f64>,
    pub residue_im: Vec<f64>,
    /// Modal phase collinearity in [0, 1] (1 = real mode), over the used points.
    pub mpc: f64,
    /// Mean phase deviation in degrees from the best-fit straight line (0 = real mode),
    /// weighted by the residue magnitude.
    pub mpd_deg: f64,
    /// Number of stabilization-diagram poles in this mode's cluster.
    pub cluster_size: usize,
    /// The mode's share of the fitted response at its natural frequency, the largest over
    /// the used points ([`lsfd::peak_shares`]); `NaN` for a mode identified elsewhere.
    pub peak_share: f64,
    /// Spread (median absolute deviation) of the cluster's frequencies in Hz and damping
    /// ratios: a cheap uncertainty indicator.
    pub freq_mad_hz: f64,
    pub damping_mad: f64,
}

/// Result of [`extract`] for one measurement.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Extraction {
    /// Identified modes sorted by frequency.
    pub modes: Vec<IdentifiedMode>,
    /// Band actually analysed, Hz.
    pub band_hz: (f64, f64),
    /// Stabilization diagram of the last pass.
    pub stabilization: StabilizationDiagram,
    /// Per scan point: why it was excluded (empty list = used).
    pub point_flags: Vec<Vec<PointFlag>>,
    /// Per scan point: relative LSFD fit error `||H - H_fit|| / ||H||` over the band.
    pub fit_error: Vec<f64>,
    /// Fit error over all used points together.
    pub overall_fit_error: f64,
}

/// Below this many used response points a mode's MPC cannot judge it (one point's is 1,
/// two points' is a single phase difference): pole selection then asks for the mode's share
/// of the response at its own frequency instead ([`SelectionParams::min_peak_share`]).
pub const FEW_POINTS: usize = 3;

/// A mode identified elsewhere (a lab's modal software, UFF dataset 55), its shape already
/// real-normalised at the measurement's scan points (`NaN` where it has no value).
#[derive(Debug, Clone, PartialEq)]
pub struct GivenMode {
    pub freq_hz: f64,
    pub damping_ratio: f64,
    pub mpc: f64,
    pub mpd_deg: f64,
    pub shape: Vec<f64>,
}

/// The [`Extraction`] of a measurement whose modes were identified elsewhere: the modes
/// ascending in frequency as given, no stabilization diagram (no pole support:
/// `cluster_size` 0, spreads and fit errors `NaN`), no point excluded, and the band the modes span (the lab's band is not in a mode set; the modes' span is
/// the part of it they vouch for).
pub fn pass_through(modes: &[GivenMode]) -> Extraction {
    let mut modes = modes.to_vec();
    modes.sort_by(|a, b| a.freq_hz.total_cmp(&b.freq_hz));
    let n_points = modes.first().map_or(0, |m| m.shape.len());
    let band_hz = (
        modes.first().map_or(f64::NAN, |m| m.freq_hz),
        modes.last().map_or(f64::NAN, |m| m.freq_hz),
    );
    Extraction {
        modes: modes
            .into_iter()
            .map(|m| IdentifiedMode {
                freq_hz: m.freq_hz,
                damping_ratio: m.damping_ratio,
                residue_re: vec![f64::NAN; m.shape.len()],
                residue_im: vec![f64::NAN; m.shape.len()],
                shape: m.shape,
                mpc: m.mpc,
                mpd_deg: m.mpd_deg,
                cluster_size: 0,
                peak_share: f64::NAN,
                freq_mad_hz: f64::NAN,
                damping_mad: f64::NAN,
            })
            .collect(),
        band_hz,
        stabilization: StabilizationDiagram {
            band_hz,
            orders: vec![],
            poles: vec![],
        },
        point_flags: vec![vec![]; n_points],
        fit_error: vec![f64::NAN; n_points],
        overall_fit_error: f64::NAN,
    }
}

/// Validated complex view of the spectra restricted to the analysis band.
#[derive(Debug, Clone)]
pub(crate) struct BandData {
    pub freq_hz: Vec<f64>,
    /// `h[point][line]`.
    pub h: Vec<Vec<c64>>,
    /// `coherence[point][line]` if present.
    pub coherence: Vec<Option<Vec<f64>>>,
    /// First line (index on the full axis) with a non-finite value, per point; such a
    /// point's spectrum is zeroed here and flagged by the screening.
    pub non_finite: Vec<Option<usize>>,
}

/// Check the spectra and cut them to the band.
pub(crate) fn band_data(
    spectra: &MeasurementSpectra,
    band_hz: Option<(f64, f64)>,
) -> Result<BandData, ModalError> {
    const MIN_LINES: usize = 8;
    let f = &spectra.freq_hz;
    let axis_ok = f.len() >= MIN_LINES
        && f.iter().all(|v| v.is_finite() && *v >= 0.0)
        && f.windows(2).all(|w| w[1] > w[0]);
    if !axis_ok {
        return Err(ModalError::FrequencyAxis {
            expected: MIN_LINES,
            found: format!("{} lines (or unsorted/non-finite)", f.len()),
        });
    }
    for (i, p) in spectra.points.iter().enumerate() {
        for len in [p.re.len(), p.im.len()]
            .into_iter()
            .chain(p.coherence.as_ref().map(|c| c.len()))
        {
            if len != f.len() {
                return Err(ModalError::SpectrumLength {
                    index: i,
                    node_id: p.node_id,
                    expected: f.len(),
                    found: len,
                });
            }
        }
    }
    let (axis_lo, axis_hi) = (f[0], f[f.len() - 1]);
    let (lo, hi) = band_hz.unwrap_or((axis_lo, axis_hi));
    let idx: Vec<usize> = (0..f.len())
        .filter(|&k| f[k] >= lo && f[k] <= hi && f[k] > 0.0)
        .collect();
    if lo.is_nan() || hi.is_nan() || lo >= hi || idx.len() < MIN_LINES {
        return Err(ModalError::Band {
            lo_hz: lo,
            hi_hz: hi,
            axis_lo_hz: axis_lo,
            axis_hi_hz: axis_hi,
            lines: idx.len(),
            min_lines: MIN_LINES,
        });
    }
    let mut h = Vec::with_capacity(spectra.points.len());
    let mut coherence = Vec::with_capacity(spectra.points.len());
    let mut non_finite = Vec::with_capacity(spectra.points.len());
    for p in spectra.points.iter() {
        let mut row = Vec::with_capacity(idx.len());
        let mut bad_line = None;
        for &k in &idx {
            let v = c64::new(p.re[k], p.im[k]);
            if v.re.is_finite() && v.im.is_finite() {
                row.push(v);
            } else {
                bad_line.get_or_insert(k);
                row.push(c64::new(0.0, 0.0));
            }
        }
        if bad_line.is_some() {
            // A corrupt record is excluded (flagged), not fatal for the measurement.
            row.iter_mut().for_each(|v| *v = c64::new(0.0, 0.0));
        }
        non_finite.push(bad_line);
        h.push(row);
        coherence.push(
            p.coherence
                .as_ref()
                .map(|c| idx.iter().map(|&k| c[k]).collect()),
        );
    }
    Ok(BandData {
        freq_hz: idx.iter().map(|&k| f[k]).collect(),
        h,
        coherence,
        non_finite,
    })
}

/// Identify the modes of one measurement: see the module documentation for the steps.
///
/// Errors if the spectra are malformed or no scan point survives screening. With fewer than
/// [`FEW_POINTS`] used points the modes are kept on their share of the response at their own
/// frequency rather than on their MPC.
pub fn extract(
    spectra: &MeasurementSpectra,
    params: &ExtractParams,
) -> Result<Extraction, ModalError> {
    let data = band_data(spectra, params.band_hz)?;
    let n_points = data.h.len();
    let band = (data.freq_hz[0], data.freq_hz[data.freq_hz.len() - 1]);
    let lsfd_params = params
        .lsfd
        .clone()
        .unwrap_or_else(|| LsfdParams::for_kind(spectra.kind));
    let mut flags = quality::screen_points(&data, &params.quality);
    let basis = lscf::LscfBasis::new(&data.freq_hz, params.lscf.max_order);

    let mut pass = 0;
    loop {
        let used: Vec<usize> = (0..n_points).filter(|&i| flags[i].is_empty()).collect();
        if used.is_empty() {
            return Err(ModalError::TooFewPoints {
                expected: 1,
                found: used.len(),
                excluded: n_points - used.len(),
            });
        }
        let h_used: Vec<&[c64]> = used.iter().map(|&i| data.h[i].as_slice()).collect();
        // Noise-level weights (1/sigma) drive the refinement; the LSCF uses them too unless
        // told otherwise. Computed once per set of used points.
        let noise_weights = lscf::point_weights(&h_used, lscf::Weighting::NoiseEstimate);
        let other_weights = (params.lscf.weighting != lscf::Weighting::NoiseEstimate)
            .then(|| lscf::point_weights(&h_used, params.lscf.weighting));
        let lscf_weights = other_weights.as_deref().unwrap_or(&noise_weights);
        let orders = lscf::lscf_poles_with(&basis, &h_used, lscf_weights, None, &params.lscf)?;
        let mut diagram = stabilization::flag_stability(orders, band, &params.stability);
        let mut selected = poles::select_physical_poles(&diagram, &params.selection);
        for _ in 0..params.sk_passes {
            if selected.is_empty() {
                break;
            }
            let lam: Vec<c64> = selected.iter().map(|s| s.lambda).collect();
            let lw = lscf::sk_line_weights(&data.freq_hz, &lam);
            let orders =
                lscf::lscf_poles_with(&basis, &h_used, lscf_weights, Some(&lw), &params.lscf)?;
            let d2 = stabilization::flag_stability(orders, band, &params.stability);
            let s2 = poles::select_physical_poles(&d2, &params.selection);
            if s2.is_empty() {
                break;
            }
            diagram = d2;
            selected = s2;
        }
        let mut lambdas: Vec<c64> = selected.iter().map(|s| s.lambda).collect();
        if let Some(rp) = &params.refine {
            lambdas = refine::refine_poles(&data.freq_hz, &h_used, &noise_weights, &lambdas, rp);
        }
        // LSFD on every point (flagged ones too, to report their fit error).
        let all_rows: Vec<&[c64]> = data.h.iter().map(|r| r.as_slice()).collect();
        let fit = lsfd::lsfd(&data.freq_hz, &all_rows, &lambdas, &lsfd_params)?;
        let new_flags = quality::flag_fit_outliers(&fit.fit_error, &flags, &params.quality);
        let changed = new_flags != flags;
        flags = new_flags;
        if changed && pass < params.refit_passes {
            pass += 1;
            continue;
        }
        let used_mask: Vec<bool> = flags.iter().map(|f| f.is_empty()).collect();
        let shares = lsfd::peak_shares(&lambdas, &fit, &lsfd_params.residual_powers, &used_mask);
        let mut modes = Vec::with_capacity(selected.len());
        for (r, sel) in selected.iter().enumerate() {
            let residues: Vec<c64> = (0..n_points).map(|o| fit.residues[o][r]).collect();
            let shape = lsfd::real_normalise(&residues, &used_mask);
            let (mpc, mpd_deg) = lsfd::mpc_mpd(&residues, &used_mask);
            let lam = lambdas[r];
            let mask_nan = |v: f64, i: usize| if used_mask[i] { v } else { f64::NAN };
            modes.push(IdentifiedMode {
                freq_hz: lam.norm() / (2.0 * std::f64::consts::PI),
                damping_ratio: -lam.re / lam.norm(),
                shape,
                residue_re: residues
                    .iter()
                    .enumerate()
                    .map(|(i, a)| mask_nan(a.re, i))
                    .collect(),
                residue_im: residues
                    .iter()
                    .enumerate()
                    .map(|(i, a)| mask_nan(a.im, i))
                    .collect(),
                mpc,
                mpd_deg,
                cluster_size: sel.cluster_size,
                peak_share: shares[r],
                freq_mad_hz: sel.freq_mad_hz,
                damping_mad: sel.damping_mad,
            });
        }
        // Many points: the residues' phase collinearity tells a mode from noise. Few: it
        // cannot (one point's MPC is 1), and the mode must stand out of the response instead.
        let few = used.len() < FEW_POINTS;
        let keep: Vec<bool> = modes
            .iter()
            .map(|m| {
                if few {
                    m.peak_share >= params.selection.min_peak_share
                } else {
                    m.mpc >= params.selection.min_mpc
                }
            })
            .collect();
        let modes: Vec<IdentifiedMode> = modes
            .into_iter()
            .zip(keep)
            .filter_map(|(m, k)| k.then_some(m))
            .collect();
        let overall_fit_error = fit.overall_error(&used_mask);
        return Ok(Extraction {
            modes,
            band_hz: band,
            stabilization: diagram,
            point_flags: flags,
            fit_error: fit.fit_error,
            overall_fit_error,
        });
    }
}

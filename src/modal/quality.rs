//! Scan-point screening: which points may inform the poles and shapes, and why not.
//!
//! Before the pole estimation ([`screen_points`]):
//! - *low coherence*: mean coherence over the band below `min_mean_coherence`;
//! - *noise-like spectrum*: roughness `rho = sum|H_{k+1} - H_k|^2 / (2 sum|H_k|^2)` is about 1
//!   for white noise and far below 1 for a resolved structural spectrum. A point is flagged
//!   if `rho > max_roughness` **and** `rho > roughness_ratio x median(rho)`: the relative
//!   condition keeps every point when the whole measurement is coarsely resolved (sharp
//!   peaks spanning a line or two make all spectra rough), so it adapts to the data.
//! - *dead*: a spectrum with zero energy; *non-finite*: a record with NaN/inf values.
//!
//! After the first LSFD ([`flag_fit_outliers`]):
//! - *fit outlier*: relative fit error above `max_fit_error` (unless the median point is
//!   above it too: then the model, not the points, fails), or above
//!   `median + fit_mad_k x 1.4826 MAD` of all points' errors and above `min_outlier_fit_error`
//!   (a robust z-score, so that a uniformly noisier measurement flags nothing extra).

use super::BandData;
use serde::{Deserialize, Serialize};

/// Why a scan point was excluded.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum PointFlag {
    LowCoherence {
        mean_coherence: f64,
    },
    NoiseLike {
        roughness: f64,
        median_roughness: f64,
    },
    Dead,
    /// The record holds NaN or infinite values (first such line on the full axis).
    NonFinite {
        line: usize,
    },
    FitOutlier {
        fit_error: f64,
        median_fit_error: f64,
    },
}

impl PointFlag {
    /// Short reason for tables.
    pub fn reason(&self) -> String {
        match self {
            PointFlag::LowCoherence { mean_coherence } => {
                format!("low coherence (mean {mean_coherence:.3})")
            }
            PointFlag::NoiseLike {
                roughness,
                median_roughness,
            } => format!(
                "noise-like spectrum (roughness {roughness:.3}, median {median_roughness:.3})"
            ),
            PointFlag::Dead => "no signal".to_string(),
            PointFlag::NonFinite { line } => format!("non-finite value at line {line}"),
            PointFlag::FitOutlier {
                fit_error,
                median_fit_error,
            } => format!("fit outlier (error {fit_error:.3}, median {median_fit_error:.3})"),
        }
    }
}

/// Screening thresholds; see the module documentation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct QualityParams {
    /// Default 0.5: below this, more than half of the response power is uncorrelated with
    /// the reference on average.
    pub min_mean_coherence: f64,
    /// Default 0.5 (white noise gives 1).
    pub max_roughness: f64,
    /// Default 3.
    pub roughness_ratio: f64,
    /// Default 0.7: a point whose model explains less than half of its energy
    /// (`1 - 0.7^2 = 0.51`) carries no usable shape information.
    pub max_fit_error: f64,
    /// Default 6 (robust z-score).
    pub fit_mad_k: f64,
    /// Default 0.2: fit errors below this are never outliers.
    pub min_outlier_fit_error: f64,
}

impl Default for QualityParams {
    fn default() -> Self {
        Self {
            min_mean_coherence: 0.5,
            max_roughness: 0.5,
            roughness_ratio: 3.0,
            max_fit_error: 0.7,
            fit_mad_k: 6.0,
            min_outlier_fit_error: 0.2,
        }
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.retain(|x| x.is_finite());
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Roughness `sum|H_{k+1} - H_k|^2 / (2 sum|H_k|^2)` of one spectrum (about 1 for white noise).
pub fn roughness(row: &[faer::c64]) -> f64 {
    let e: f64 = row.iter().map(|v| v.norm_sqr()).sum();
    if e <= 0.0 {
        return f64::NAN;
    }
    row.windows(2)
        .map(|w| (w[1] - w[0]).norm_sqr())
        .sum::<f64>()
        / (2.0 * e)
}

/// Flags before the pole estimation (coherence, roughness, dead points).
pub(crate) fn screen_points(data: &BandData, params: &QualityParams) -> Vec<Vec<PointFlag>> {
    let rough: Vec<f64> = data.h.iter().map(|r| roughness(r)).collect();
    let med = median(rough.clone());
    data.h
        .iter()
        .enumerate()
        .map(|(o, row)| {
            let mut flags = Vec::new();
            if let Some(line) = data.non_finite[o] {
                flags.push(PointFlag::NonFinite { line });
                return flags;
            }
            if row.iter().all(|v| v.norm_sqr() == 0.0) {
                flags.push(PointFlag::Dead);
                return flags;
            }
            if let Some(c) = &data.coherence[o] {
                let m = c.iter().sum::<f64>() / c.len() as f64;
                if m < params.min_mean_coherence {
                    flags.push(PointFlag::LowCoherence { mean_coherence: m });
                }
            }
            let r = rough[o];
            if r > params.max_roughness && r > params.roughness_ratio * med {
                flags.push(PointFlag::NoiseLike {
                    roughness: r,
                    median_roughness: med,
                });
            }
            flags
        })
        .collect()
}

/// Add fit-outlier flags to the existing ones (points already flagged keep their flags and
/// do not enter the statistics).
pub(crate) fn flag_fit_outliers(
    fit_error: &[f64],
    flags: &[Vec<PointFlag>],
    params: &QualityParams,
) -> Vec<Vec<PointFlag>> {
    let used: Vec<f64> = fit_error
        .iter()
        .zip(flags)
        .filter(|(_, f)| f.is_empty())
        .map(|(e, _)| *e)
        .collect();
    let med = median(used.clone());
    let mad = 1.4826 * median(used.iter().map(|e| (e - med).abs()).collect());
    fit_error
        .iter()
        .zip(flags)
        .map(|(&e, f)| {
            let mut f = f.clone();
            // The absolute rule only applies while the typical point fits: if the median
            // error itself is above it, the model (not the points) is what fails, and
            // flagging everything would only hide that.
            let outlier = !e.is_finite()
                || (e > params.max_fit_error && med <= params.max_fit_error)
                || (e > params.min_outlier_fit_error && e > med + params.fit_mad_k * mad);
            if f.is_empty() && outlier {
                f.push(PointFlag::FitOutlier {
                    fit_error: e,
                    median_fit_error: med,
                });
            }
            f
        })
        .collect()
}

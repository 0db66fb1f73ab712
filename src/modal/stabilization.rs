//! Stabilization diagram: the poles of every model order with stability flags.
//!
//! A pole of order `n` is compared with the closest-in-frequency pole of the previous
//! evaluated order. It is *stable in frequency* if `|df|/f <= freq_tol`, *in damping* if
//! `|dzeta|/zeta <= damping_tol`, *in shape* if the complex MAC of the two shape estimates is
//! at least `mac_min`. The defaults (1 %, 5 %, 0.98) are the customary criteria of commercial
//! and academic modal software (e.g. Peeters et al. 2004); they only decide the symbols on the
//! diagram and which poles enter the clustering of [`super::poles`].

use super::lscf::OrderPoles;
use super::mac::mac_complex;
use faer::c64;
use serde::{Deserialize, Serialize};

/// Tolerances of the stability flags.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StabilityParams {
    /// Relative frequency change allowed between consecutive orders (default 0.01).
    pub freq_tol: f64,
    /// Relative damping change allowed between consecutive orders (default 0.05).
    pub damping_tol: f64,
    /// Minimum complex MAC between the shape estimates of consecutive orders (default 0.98).
    pub mac_min: f64,
}

impl Default for StabilityParams {
    fn default() -> Self {
        Self {
            freq_tol: 0.01,
            damping_tol: 0.05,
            mac_min: 0.98,
        }
    }
}

/// One pole on the diagram.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DiagramPole {
    /// Model order (denominator degree) at which the pole was estimated.
    pub order: usize,
    pub freq_hz: f64,
    pub damping_ratio: f64,
    /// Pole in rad/s.
    pub lambda_re: f64,
    pub lambda_im: f64,
    pub stable_freq: bool,
    pub stable_damping: bool,
    pub stable_shape: bool,
    /// Shape estimate at the used points (not serialised: large and only used for the
    /// clustering).
    #[serde(skip)]
    pub shape: Vec<c64>,
}

impl DiagramPole {
    /// Stable in frequency, damping and shape.
    pub fn fully_stable(&self) -> bool {
        self.stable_freq && self.stable_damping && self.stable_shape
    }
}

/// All poles of all orders of one measurement.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StabilizationDiagram {
    /// Analysed band, Hz.
    pub band_hz: (f64, f64),
    /// Evaluated model orders, ascending.
    pub orders: Vec<usize>,
    /// Poles sorted by order, then frequency.
    pub poles: Vec<DiagramPole>,
}

/// Flag every pole against the previous evaluated order.
pub fn flag_stability(
    orders: Vec<OrderPoles>,
    band_hz: (f64, f64),
    params: &StabilityParams,
) -> StabilizationDiagram {
    let mut out = Vec::new();
    let mut order_list = Vec::with_capacity(orders.len());
    let mut prev: Option<&OrderPoles> = None;
    for op in &orders {
        order_list.push(op.order);
        for p in &op.poles {
            let mut flags = (false, false, false);
            if let Some(pr) = prev {
                let best = pr.poles.iter().min_by(|a, b| {
                    (a.freq_hz - p.freq_hz)
                        .abs()
                        .total_cmp(&(b.freq_hz - p.freq_hz).abs())
                });
                if let Some(q) = best {
                    let df = (q.freq_hz - p.freq_hz).abs() / p.freq_hz;
                    let dz = (q.damping_ratio - p.damping_ratio).abs() / p.damping_ratio.abs();
                    flags.0 = df <= params.freq_tol;
                    flags.1 = flags.0 && dz <= params.damping_tol;
                    flags.2 = flags.0 && mac_complex(&p.shape, &q.shape) >= params.mac_min;
                }
            }
            out.push(DiagramPole {
                order: op.order,
                freq_hz: p.freq_hz,
                damping_ratio: p.damping_ratio,
                lambda_re: p.lambda.re,
                lambda_im: p.lambda.im,
                stable_freq: flags.0,
                stable_damping: flags.1,
                stable_shape: flags.2,
                shape: p.shape.clone(),
            });
        }
        prev = Some(op);
    }
    StabilizationDiagram {
        band_hz,
        orders: order_list,
        poles: out,
    }
}

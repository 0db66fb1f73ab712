//! Automatic selection of the physical poles from a stabilization diagram.
//!
//! Rules, in order (all thresholds in [`SelectionParams`]):
//! 1. *Candidates*: poles stable in frequency and shape against the previous order, with
//!    `0 < zeta <= max_damping` (negative damping = unstable, computational pole; very high
//!    damping = pole absorbing out-of-band or noise energy).
//! 2. *Clustering across orders*, ascending order: each candidate joins the cluster whose
//!    latest member is within `cluster_freq_tol` in relative frequency and `cluster_mac_min`
//!    in complex MAC (a combined normalised distance decides between several; at most one
//!    pole per order per cluster, assigned greedily by distance). Otherwise it opens a new
//!    cluster. The MAC term is what separates close modes: two modes 0.3 % apart have
//!    different shapes, a physical pole at successive orders has the same shape.
//! 3. *Persistence*: a cluster is kept if it has at least `min_cluster_poles` members and
//!    is present in at least `min_presence` of the evaluated orders from its first
//!    appearance to the highest order. Physical poles, once the order suffices, persist;
//!    noise poles come and go. Relating presence to the first appearance (instead of all
//!    orders) keeps weakly excited or high modes that need a high order to appear.
//! 4. *Duplicates*: of two kept clusters closer than `cluster_freq_tol` with shape MAC above
//!    `duplicate_mac`, the smaller is dropped (over-modelling splits a mode in two poles).
//! 5. *Band edges*: clusters whose median frequency lies within `edge_margin` (fraction of
//!    the band width) of a band limit are dropped: poles there model out-of-band modes.
//! 6. The mode's pole is the median frequency and median damping of its cluster.
//!
//! After LSFD, [`super::extract`] also drops modes whose modal phase collinearity is below
//! `min_mpc`.

use super::mac::mac_complex;
use super::stabilization::StabilizationDiagram;
use crate::bayes::stats::median;
use faer::c64;
use serde::{Deserialize, Serialize};

/// Thresholds of the automatic pole selection. Defaults are generic (not fitted to a data
/// set): see each field.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SelectionParams {
    /// Upper damping ratio bound for a physical pole (default 0.2; lightly damped
    /// structures tested for modal analysis rarely exceed a few per cent).
    pub max_damping: f64,
    /// Relative frequency tolerance for joining a cluster (default 0.005). Smaller than the
    /// 1 % of the diagram flags so that close modes do not merge on frequency alone.
    pub cluster_freq_tol: f64,
    /// Minimum complex MAC with the cluster's latest member (default 0.9).
    pub cluster_mac_min: f64,
    /// Minimum cluster size in poles (default 4).
    pub min_cluster_poles: usize,
    /// Minimum fraction of orders, from the cluster's first order up to the highest, at
    /// which the cluster has a pole (default 0.5).
    pub min_presence: f64,
    /// MAC above which two nearby clusters are the same mode (default 0.9).
    pub duplicate_mac: f64,
    /// Band-edge margin as a fraction of the band width (default 0.01).
    pub edge_margin: f64,
    /// Minimum modal phase collinearity of the LSFD residues (default 0.5; real structures
    /// with noticeable non-proportional damping still have MPC well above this, noise
    /// poles have random-phase residues).
    pub min_mpc: f64,
    /// With fewer than [`super::FEW_POINTS`] response points the MPC cannot judge a mode (one
    /// point's is always 1); a mode is then kept when its term is at least this share of the
    /// fitted response at its own natural frequency, at some point (|its term| over the sum
    /// of every term's and the residual terms' magnitudes). Default 0.1: a lightly damped
    /// mode seen at a point rises to 1/(2ζ) ≈ 25–100 times its off-resonance level and
    /// dominates there (share near 1) unless another mode lies within a few half-power
    /// bandwidths (two equal modes share about half each); a term under a tenth of the
    /// response at its own peak (−20 dB) is one a single FRF cannot tell from the other modes'
    /// tails and the out-of-band residuals.
    pub min_peak_share: f64,
}

impl Default for SelectionParams {
    fn default() -> Self {
        Self {
            max_damping: 0.2,
            cluster_freq_tol: 0.005,
            cluster_mac_min: 0.9,
            min_cluster_poles: 4,
            min_presence: 0.5,
            duplicate_mac: 0.9,
            edge_margin: 0.01,
            min_mpc: 0.5,
            min_peak_share: 0.1,
        }
    }
}

/// A selected physical pole.
#[derive(Debug, Clone, PartialEq)]
pub struct SelectedPole {
    /// Pole in rad/s built from the cluster's median frequency and damping.
    pub lambda: c64,
    pub freq_hz: f64,
    pub damping_ratio: f64,
    pub cluster_size: usize,
    /// Median absolute deviation of the cluster's frequencies (Hz) and damping ratios.
    pub freq_mad_hz: f64,
    pub damping_mad: f64,
}

struct Cluster {
    members: Vec<usize>,
    last_freq: f64,
    last_order: usize,
    first_order: usize,
}

/// Select physical poles (sorted by frequency); see the module documentation for the rules.
pub fn select_physical_poles(
    diagram: &StabilizationDiagram,
    params: &SelectionParams,
) -> Vec<SelectedPole> {
    let poles = &diagram.poles;
    let mut clusters: Vec<Cluster> = Vec::new();
    for &order in &diagram.orders {
        let cand: Vec<usize> = (0..poles.len())
            .filter(|&i| {
                let p = &poles[i];
                p.order == order
                    && p.stable_freq
                    && p.stable_shape
                    && p.damping_ratio > 0.0
                    && p.damping_ratio <= params.max_damping
            })
            .collect();
        // All admissible (distance, pole, cluster) pairs.
        let mut pairs = Vec::new();
        for &i in &cand {
            let p = &poles[i];
            for (c, cl) in clusters.iter().enumerate() {
                if cl.last_order == order {
                    continue;
                }
                let df = (p.freq_hz - cl.last_freq).abs() / cl.last_freq;
                if df > params.cluster_freq_tol {
                    continue;
                }
                let last = &poles[*cl.members.last().expect("cluster has members")];
                let m = mac_complex(&p.shape, &last.shape);
                if m < params.cluster_mac_min {
                    continue;
                }
                let d = df / params.cluster_freq_tol
                    + (1.0 - m) / (1.0 - params.cluster_mac_min).max(1e-12);
                pairs.push((d, i, c));
            }
        }
        pairs.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
        let mut pole_used = vec![false; poles.len()];
        let mut cl_used = vec![false; clusters.len()];
        for (_, i, c) in pairs {
            if pole_used[i] || cl_used[c] {
                continue;
            }
            pole_used[i] = true;
            cl_used[c] = true;
            let cl = &mut clusters[c];
            cl.members.push(i);
            cl.last_freq = poles[i].freq_hz;
            cl.last_order = order;
        }
        for &i in &cand {
            if !pole_used[i] {
                clusters.push(Cluster {
                    members: vec![i],
                    last_freq: poles[i].freq_hz,
                    last_order: order,
                    first_order: order,
                });
            }
        }
    }

    // Persistence.
    let n_from = |first: usize| diagram.orders.iter().filter(|&&o| o >= first).count();
    let mut kept: Vec<&Cluster> = clusters
        .iter()
        .filter(|c| {
            c.members.len() >= params.min_cluster_poles
                && c.members.len() as f64 >= params.min_presence * n_from(c.first_order) as f64
        })
        .collect();
    // Duplicates: larger clusters first.
    kept.sort_by(|a, b| {
        b.members
            .len()
            .cmp(&a.members.len())
            .then(a.first_order.cmp(&b.first_order))
    });
    let (lo, hi) = diagram.band_hz;
    let margin = params.edge_margin * (hi - lo);
    let mut result: Vec<(SelectedPole, usize)> = Vec::new();
    for c in kept {
        let f: Vec<f64> = c.members.iter().map(|&i| poles[i].freq_hz).collect();
        let z: Vec<f64> = c.members.iter().map(|&i| poles[i].damping_ratio).collect();
        let f_med = median(&f);
        let z_med = median(&z);
        if f_med < lo + margin || f_med > hi - margin {
            continue;
        }
        let rep = *c.members.last().expect("cluster has members");
        let dup = result.iter().any(|(s, r)| {
            (s.freq_hz - f_med).abs() / f_med <= params.cluster_freq_tol
                && mac_complex(&poles[*r].shape, &poles[rep].shape) >= params.duplicate_mac
        });
        if dup {
            continue;
        }
        let fd: Vec<f64> = f.iter().map(|v| (v - f_med).abs()).collect();
        let zd: Vec<f64> = z.iter().map(|v| (v - z_med).abs()).collect();
        result.push((
            SelectedPole {
                lambda: super::frf::pole(f_med, z_med),
                freq_hz: f_med,
                damping_ratio: z_med,
                cluster_size: c.members.len(),
                freq_mad_hz: median(&fd),
                damping_mad: median(&zd),
            },
            rep,
        ));
    }
    let mut out: Vec<SelectedPole> = result.into_iter().map(|(s, _)| s).collect();
    out.sort_by(|a, b| a.freq_hz.total_cmp(&b.freq_hz));
    out
}

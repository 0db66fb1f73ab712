//! How much independent information a mode's shape observations carry: the weight of their
//! term in the likelihood, from the agreement of their residuals between measurements.
//!
//! The shape term ([`super::modal::log_lik_with`]) treats each measurement's shape error as
//! independent of every other measurement's. Extracted shapes are not: leakage from a
//! neighbouring mode, a residual term the modal fit left out, a scan grid's misalignment, or
//! a discrepancy of the model's own, move every measurement of a mode the same way. A part
//! b common to J measurements (r_j = b + e_j) is then counted J times, and a parameter
//! shared by the measurements (a joint's rotational stiffness) is pulled towards whatever
//! absorbs b with an interval √J too narrow: the posterior is confidently wrong.
//!
//! With b ~ N(0, τ²) and e_j ~ N(0, σ²) per scan point, and the shape error scale fitted to the
//! total spread s² = τ² + σ² (as δ is), the information the measurements hold on a
//! shared direction is J/(s² (1 + (J − 1) ρ)) with ρ = τ²/s², against J/s² that the
//! independent term assumes: Kish's design effect of a cluster sample (Kish, *Survey
//! Sampling*, 1965, §5.4). Raising the mode's shape term to the power w = 1/(1 + (J − 1) ρ) (a
//! power likelihood: Holmes & Walker 2017; Miller & Dunson 2019) gives the term the
//! information its data hold on what the measurements share, and leaves the error scale's
//! estimate where it was. ρ is estimated as the mean correlation of the residuals of every
//! pair of the mode's measurements over their common scan points, at a point estimate of the
//! parameters; without two measurements on common points, or with no positive correlation,
//! the weight is 1.
//!
//! The weight is a property of the data and the model, fixed before sampling: models that
//! are compared by their evidence (a diagnosis's baseline and its candidate enrichments) must
//! be given the same weights, or their likelihoods are not the same function of the data.

use serde::{Deserialize, Serialize};

/// One mode-shape observation at its scan points, with what its model shape needs.
#[derive(Clone, Debug)]
pub struct PointShape {
    /// The updated mode's index.
    pub mode: usize,
    /// The scan points' coordinates in units of 10 µm (points of two measurements are the
    /// same point when these agree).
    pub keys: Vec<(i64, i64)>,
    /// The measured shape at the points, unit norm.
    pub u: Vec<f64>,
    /// The model's interpolation from reduced coordinates to the points, n × r row-major.
    pub p: Vec<f64>,
}

/// The key of a scan point at (x, y) in metres: 10 µm cells, far finer than any scan grid
/// and coarser than the rounding of coordinates written in mm with a few decimals.
pub fn point_key(x_m: f64, y_m: f64) -> (i64, i64) {
    ((x_m * 1e5).round() as i64, (y_m * 1e5).round() as i64)
}

/// The residual of one observation against the model's reduced vector `y` (oriented by
/// `orient`, the mode's reference vector, so that every measurement's residual is taken
/// against the same sign of the mode): û − (|c|/|s|²) s with s = P y, c = ⟨u, s⟩ and
/// û = sign(c) u; its squared norm is 1 − MAC. `None` where the model shape vanishes at the
/// points.
pub fn residual(ps: &PointShape, y: &[f64], orient: &[f64]) -> Option<Vec<f64>> {
    let r = y.len();
    let sign = if y.iter().zip(orient).map(|(a, b)| a * b).sum::<f64>() < 0.0 {
        -1.0
    } else {
        1.0
    };
    let s: Vec<f64> =
        ps.p.chunks_exact(r)
            .map(|row| sign * row.iter().zip(y).map(|(a, b)| a * b).sum::<f64>())
            .collect();
    let ss: f64 = s.iter().map(|v| v * v).sum();
    if ss.is_nan() || ss <= 0.0 {
        return None;
    }
    let c: f64 = ps.u.iter().zip(&s).map(|(a, b)| a * b).sum();
    let su = if c < 0.0 { -1.0 } else { 1.0 };
    let a = c.abs() / ss;
    Some(ps.u.iter().zip(&s).map(|(u, s)| su * u - a * s).collect())
}

/// One observation's residual at its points (keys sorted as in [`PointShape::keys`]).
#[derive(Clone, Debug)]
pub struct ModeResidual {
    pub mode: usize,
    pub keys: Vec<(i64, i64)>,
    pub r: Vec<f64>,
}

/// The weight of one mode's shape term and what it came from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ShapeWeight {
    /// The updated mode's label.
    pub label: String,
    /// Shape observations of the mode (J).
    pub n_observations: usize,
    /// Pairs of observations with at least 3 common scan points.
    pub n_pairs: usize,
    /// Mean correlation of the residuals of those pairs (ρ; may be negative; `None` without
    /// pairs, or where the weight was given rather than estimated).
    pub correlation: Option<f64>,
    /// The design effect 1 + (J − 1) max(ρ, 0).
    pub design_effect: f64,
    /// The power of the mode's shape term: 1 / design effect.
    pub weight: f64,
}

/// Σ a_k b_k, Σ a_k², Σ b_k² over the points the two residuals share (keys matched by
/// value; each residual's keys in any order) and the number of those points.
fn common_moments(a: &ModeResidual, b: &ModeResidual) -> (f64, f64, f64, usize) {
    let mut ib: Vec<usize> = (0..b.keys.len()).collect();
    ib.sort_by_key(|&i| b.keys[i]);
    let (mut ab, mut aa, mut bb, mut n) = (0.0, 0.0, 0.0, 0);
    for (ka, ra) in a.keys.iter().zip(&a.r) {
        if let Ok(pos) = ib.binary_search_by_key(ka, |&i| b.keys[i]) {
            let rb = b.r[ib[pos]];
            ab += ra * rb;
            aa += ra * ra;
            bb += rb * rb;
            n += 1;
        }
    }
    (ab, aa, bb, n)
}

/// The weights of every mode's shape term (labels[m] names mode m) from the residuals of
/// its observations: ρ = Σ⟨r_j, r_k⟩ / Σ √(|r_j|² |r_k|²) over the pairs j < k of the
/// mode's observations, each over their common points (at least 3).
pub fn design_weights(residuals: &[ModeResidual], labels: &[String]) -> Vec<ShapeWeight> {
    labels
        .iter()
        .enumerate()
        .map(|(m, label)| {
            let obs: Vec<&ModeResidual> = residuals.iter().filter(|r| r.mode == m).collect();
            let (mut num, mut den, mut pairs) = (0.0, 0.0, 0);
            for (j, a) in obs.iter().enumerate() {
                for b in &obs[j + 1..] {
                    let (ab, aa, bb, n) = common_moments(a, b);
                    if n >= 3 && aa > 0.0 && bb > 0.0 {
                        num += ab;
                        den += (aa * bb).sqrt();
                        pairs += 1;
                    }
                }
            }
            let rho = (pairs > 0).then(|| num / den);
            let j = obs.len() as f64;
            let deff = 1.0 + (j - 1.0) * rho.unwrap_or(0.0).max(0.0);
            ShapeWeight {
                label: label.clone(),
                n_observations: obs.len(),
                n_pairs: pairs,
                correlation: rho,
                design_effect: deff,
                weight: 1.0 / deff,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};

    fn normal(rng: &mut rand_chacha::ChaCha8Rng) -> f64 {
        StandardNormal.sample(rng)
    }

    fn grid(n: usize) -> Vec<(i64, i64)> {
        (0..n).map(|i| (i as i64 * 500, 0)).collect()
    }

    /// Residuals b + e_j with b ~ N(0, τ²) shared and e_j ~ N(0, σ²) independent: the
    /// estimated ρ is τ²/(τ² + σ²) (to its sampling error), the weight 1/(1 + (J − 1) ρ); with
    /// τ = 0 the weight is 1 within the noise of ρ, and a mode seen once has weight 1.
    #[test]
    fn the_weight_is_kishs_design_effect_of_a_shared_residual() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let (n, jn) = (400, 20);
        for (tau, sigma) in [(0.0, 1.0), (1.0, 1.0), (1.0, 3.0)] {
            let b: Vec<f64> = (0..n).map(|_| tau * normal(&mut rng)).collect();
            let res: Vec<ModeResidual> = (0..jn)
                .map(|_| ModeResidual {
                    mode: 0,
                    keys: grid(n),
                    r: b.iter().map(|v| v + sigma * normal(&mut rng)).collect(),
                })
                .collect();
            let w = &design_weights(&res, &["m".into()])[0];
            let rho = tau * tau / (tau * tau + sigma * sigma);
            assert_eq!((w.n_observations, w.n_pairs), (jn, jn * (jn - 1) / 2));
            // sd of one pair's correlation ≈ 1/√n; of the mean of 190 (dependent) pairs
            // no more.
            let got = w.correlation.expect("pairs");
            assert!(
                (got - rho).abs() < 3.0 / (n as f64).sqrt(),
                "{w:?} vs {rho}"
            );
            let expect = 1.0 / (1.0 + (jn as f64 - 1.0) * got.max(0.0));
            assert!((w.weight - expect).abs() < 1e-12);
            if tau == 0.0 {
                assert!(w.weight > 0.7, "{w:?}");
            } else {
                assert!(w.weight < 0.6, "{w:?}");
            }
        }
        let once = design_weights(
            &[ModeResidual {
                mode: 0,
                keys: grid(5),
                r: vec![1.0; 5],
            }],
            &["a".into(), "b".into()],
        );
        assert_eq!((once[0].weight, once[0].n_pairs), (1.0, 0));
        assert_eq!(once[0].correlation, None);
        assert_eq!((once[1].weight, once[1].n_observations), (1.0, 0));
    }

    /// Pairs are taken over their common points only, whatever order the keys come in; a
    /// pair sharing fewer than 3 points is left out.
    #[test]
    fn pairs_meet_on_their_common_points() {
        let a = ModeResidual {
            mode: 0,
            keys: vec![(0, 0), (1, 0), (2, 0), (3, 0)],
            r: vec![1.0, -1.0, 2.0, 5.0],
        };
        // b shares (2,0), (0,0), (1,0) (listed out of order) and has a point a lacks.
        let b = ModeResidual {
            mode: 0,
            keys: vec![(2, 0), (9, 9), (0, 0), (1, 0)],
            r: vec![2.0, 7.0, 1.0, -1.0],
        };
        let w = &design_weights(&[a.clone(), b], &["m".into()])[0];
        assert_eq!(w.n_pairs, 1);
        assert!((w.correlation.unwrap() - 1.0).abs() < 1e-12, "{w:?}");
        assert!((w.weight - 0.5).abs() < 1e-12);
        let c = ModeResidual {
            mode: 0,
            keys: vec![(0, 0), (1, 0), (8, 8)],
            r: vec![1.0, 1.0, 1.0],
        };
        assert_eq!(design_weights(&[a, c], &["m".into()])[0].n_pairs, 0);
    }

    /// The residual is the measured shape less its best multiple of the model's, taken with
    /// the mode's reference sign: |r|² = 1 − MAC, and flipping the measured shape, the model's
    /// reduced vector, or both gives the same residual.
    #[test]
    fn a_residual_is_signed_by_the_mode_not_by_the_measurement() {
        // Two reduced coordinates, three points.
        let p = vec![1.0, 0.0, 0.0, 1.0, 1.0, 1.0];
        let u0 = [0.9, 0.1, 1.1];
        let nu = u0.iter().map(|v| v * v).sum::<f64>().sqrt();
        let u: Vec<f64> = u0.iter().map(|v| v / nu).collect();
        let y = [1.0, 0.05];
        let base = residual(
            &PointShape {
                mode: 0,
                keys: grid(3),
                u: u.clone(),
                p: p.clone(),
            },
            &y,
            &y,
        )
        .unwrap();
        let s: Vec<f64> = p.chunks(2).map(|r| r[0] * y[0] + r[1] * y[1]).collect();
        let c: f64 = u.iter().zip(&s).map(|(a, b)| a * b).sum();
        let mac = c * c / s.iter().map(|v| v * v).sum::<f64>();
        assert!((base.iter().map(|v| v * v).sum::<f64>() - (1.0 - mac)).abs() < 1e-14);
        let neg_u: Vec<f64> = u.iter().map(|v| -v).collect();
        let neg_y = [-y[0], -y[1]];
        for (uu, yy) in [(&neg_u, y), (&u, neg_y), (&neg_u, neg_y)] {
            let r = residual(
                &PointShape {
                    mode: 0,
                    keys: grid(3),
                    u: uu.clone(),
                    p: p.clone(),
                },
                &yy,
                &y,
            )
            .unwrap();
            for (a, b) in r.iter().zip(&base) {
                assert!((a - b).abs() < 1e-14);
            }
        }
        assert!(residual(
            &PointShape {
                mode: 0,
                keys: grid(3),
                u,
                p
            },
            &[0.0, 0.0],
            &y
        )
        .is_none());
    }
}

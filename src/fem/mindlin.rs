//! A shear-deformable (Mindlin–Reissner) rectangle built on the BFS element of
//! [`super::plate`]: the deflection w keeps the BFS's bicubic Hermite field (16 DOFs), and the
//! transverse shear strains γ = (γx, γy) are bilinear (4 + 4 DOFs), the normal's rotation
//! being θ = ∇w − γ.
//!
//! Why: the virtual lab's solid truth (a layered 3-D solid in CalculiX) sits 0.18–2.13 % below
//! the Kirchhoff plate in the default board's eight free-free modes; with its transverse shear
//! moduli raised a hundredfold the gap is −0.15 … −0.50 % in every mode (`benches/solid_truth.rs`,
//! `SOLID_G_Z_PA`). The twisting modes' share is the free edges' boundary layer, which Kirchhoff
//! theory cannot have; the rest grows with the wavenumber.
//!
//! Why γ and not (w, θ) as unknowns: with γ itself the unknown, the Kirchhoff limit (γ → 0 as
//! the shear stiffness grows) is the BFS element exactly, so there is no shear locking and no
//! reduced integration, and w keeps the BFS's O(h⁴) convergence; only the shear correction
//! (a few per cent of a frequency) converges at the bilinear field's O(h²).
//!
//! Energies (D as in [`super::plate`], κ = (θx,x, θy,y, θx,y + θy,x)):
//! U = ½ ∫ κᵀ D κ + ½ ∫ (S_x γx² + S_y γy²), T = ½ ω² ∫ (ρh w² + I |θ|²),
//! with S = k G h (shear correction k, N/m) and the rotary inertia I = ∫ ρ z² dz (kg).
//! Element DOFs: the BFS's 16 (node by node), then γx at the 4 nodes, then γy.

use super::plate::{gauss4, shape, NODE_IJ};

/// DOFs of one element.
pub const DOFS: usize = 24;

/// 24 × 24 element matrix, row-major.
pub type Mat24 = [[f64; DOFS]; DOFS];

/// The unit matrices of one `a_m × b_m` element: each times its coefficient and summed gives
/// the element's stiffness or mass.
#[derive(Clone, Debug)]
pub struct ElementMatrices {
    /// Bending `[K₁₁, K₂₂, K₁₂, K₆₆]`, times D11, D22, D12, D66 (N·m).
    pub k_bend: [Mat24; 4],
    /// Transverse shear `[∫ γx², ∫ γy²]`, times S_x, S_y (N/m).
    pub k_shear: [Mat24; 2],
    /// ∫ w², times ρh (kg/m²).
    pub m_trans: Mat24,
    /// ∫ |θ|², times the rotary inertia I (kg).
    pub m_rot: Mat24,
}

/// Bilinear functions of the nodes (order [`NODE_IJ`]) at (ξ, η) ∈ [0,1]²: values and x-, y-
/// derivatives (1/m).
fn bilinear(xi: f64, eta: f64, a_m: f64, b_m: f64) -> [[f64; 4]; 3] {
    let mut out = [[0.0; 4]; 3];
    for (k, &(i, j)) in NODE_IJ.iter().enumerate() {
        let (fx, dfx) = if i == 1 { (xi, 1.0) } else { (1.0 - xi, -1.0) };
        let (fy, dfy) = if j == 1 {
            (eta, 1.0)
        } else {
            (1.0 - eta, -1.0)
        };
        out[0][k] = fx * fy;
        out[1][k] = dfx * fy / a_m;
        out[2][k] = fx * dfy / b_m;
    }
    out
}

/// Integrate the unit matrices of an `a_m × b_m` element (4 × 4 Gauss points: exact, every
/// integrand being of degree ≤ 6 in each direction).
pub fn element_matrices(a_m: f64, b_m: f64) -> ElementMatrices {
    let (pts, wts) = gauss4();
    let z = [[0.0; DOFS]; DOFS];
    let mut e = ElementMatrices {
        k_bend: [z; 4],
        k_shear: [z; 2],
        m_trans: z,
        m_rot: z,
    };
    let add = |m: &mut Mat24, w: f64, u: &[f64; DOFS], v: &[f64; DOFS]| {
        for r in 0..DOFS {
            if u[r] == 0.0 {
                continue;
            }
            for c in 0..DOFS {
                m[r][c] += w * u[r] * v[c];
            }
        }
    };
    for (ix, &xi) in pts.iter().enumerate() {
        for (iy, &eta) in pts.iter().enumerate() {
            let w = wts[ix] * wts[iy] * a_m * b_m;
            let n = shape(xi, eta, a_m, b_m);
            let l = bilinear(xi, eta, a_m, b_m);
            // Rows over the 24 DOFs: κ's three components, γ, θ and w.
            let mut kxx = [0.0; DOFS];
            let mut kyy = [0.0; DOFS];
            let mut kxy = [0.0; DOFS];
            let mut gx = [0.0; DOFS];
            let mut gy = [0.0; DOFS];
            let mut tx = [0.0; DOFS];
            let mut ty = [0.0; DOFS];
            let mut w0 = [0.0; DOFS];
            for k in 0..16 {
                kxx[k] = n[3][k];
                kyy[k] = n[4][k];
                kxy[k] = 2.0 * n[5][k];
                tx[k] = n[1][k];
                ty[k] = n[2][k];
                w0[k] = n[0][k];
            }
            for k in 0..4 {
                let (ix_, iy_) = (16 + k, 20 + k);
                kxx[ix_] = -l[1][k];
                kyy[iy_] = -l[2][k];
                kxy[ix_] = -l[2][k];
                kxy[iy_] = -l[1][k];
                gx[ix_] = l[0][k];
                gy[iy_] = l[0][k];
                tx[ix_] = -l[0][k];
                ty[iy_] = -l[0][k];
            }
            add(&mut e.k_bend[0], w, &kxx, &kxx);
            add(&mut e.k_bend[1], w, &kyy, &kyy);
            add(&mut e.k_bend[2], w, &kxx, &kyy);
            add(&mut e.k_bend[2], w, &kyy, &kxx);
            add(&mut e.k_bend[3], w, &kxy, &kxy);
            add(&mut e.k_shear[0], w, &gx, &gx);
            add(&mut e.k_shear[1], w, &gy, &gy);
            add(&mut e.m_trans, w, &w0, &w0);
            add(&mut e.m_rot, w, &tx, &tx);
            add(&mut e.m_rot, w, &ty, &ty);
        }
    }
    for m in e
        .k_bend
        .iter_mut()
        .chain(e.k_shear.iter_mut())
        .chain([&mut e.m_trans, &mut e.m_rot])
    {
        for r in 0..DOFS {
            for c in 0..r {
                let v = 0.5 * (m[r][c] + m[c][r]);
                m[r][c] = v;
                m[c][r] = v;
            }
        }
    }
    e
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An orthotropic plate a × b, thickness h (SI units).
    struct Plate {
        a: f64,
        b: f64,
        d: [f64; 4],
        s: [f64; 2],
        rho_h: f64,
        inertia: f64,
    }

    fn plate(g_z_pa: f64) -> Plate {
        let (a, b, h) = (0.16, 0.10, 1.6e-3);
        let (ex, ey, nu, gxy, rho) = (22e9, 19e9, 0.13, 3.5e9, 1900.0);
        let den = 1.0 - nu * nu * ey / ex;
        let h3 = h * h * h / 12.0;
        Plate {
            a,
            b,
            d: [ex * h3 / den, ey * h3 / den, nu * ey * h3 / den, gxy * h3],
            s: [5.0 / 6.0 * g_z_pa * h; 2],
            rho_h: rho * h,
            inertia: rho * h3,
        }
    }

    /// Navier's solution of the hard simply supported Mindlin plate, mode (m, n): w = W sin sin,
    /// θx = X cos sin, θy = Y sin cos; the lowest root of the 3 × 3 pencil, in Hz.
    fn navier_hz(p: &Plate, m: usize, n: usize) -> f64 {
        let (al, be) = (
            m as f64 * std::f64::consts::PI / p.a,
            n as f64 * std::f64::consts::PI / p.b,
        );
        let [d11, d22, d12, d66] = p.d;
        let [sx, sy] = p.s;
        let k = [
            [sx * al * al + sy * be * be, -sx * al, -sy * be],
            [
                -sx * al,
                d11 * al * al + d66 * be * be + sx,
                (d12 + d66) * al * be,
            ],
            [
                -sy * be,
                (d12 + d66) * al * be,
                d22 * be * be + d66 * al * al + sx,
            ],
        ];
        // M = diag(ρh, I, I): the symmetric C = M^-½ K M^-½, its lowest eigenvalue by the
        // dense solver of the ROM.
        let ms = [p.rho_h, p.inertia, p.inertia];
        let mut c: Vec<f64> = (0..9)
            .map(|q| k[q / 3][q % 3] / (ms[q / 3] * ms[q % 3]).sqrt())
            .collect();
        let e = crate::fem::dense::lowest_eigenpairs(&mut c, 3, 0, 1);
        e.values[0].sqrt() / (2.0 * std::f64::consts::PI)
    }

    /// The lowest `count` frequencies (Hz) of the simply supported plate on an nx × ny mesh.
    fn fe_hz(p: &Plate, nx: usize, ny: usize, count: usize) -> Vec<f64> {
        let (ea, eb) = (p.a / nx as f64, p.b / ny as f64);
        let nodes = (nx + 1) * (ny + 1);
        let per = 6;
        let n = nodes * per;
        let mut k = vec![0.0; n * n];
        let mut m = vec![0.0; n * n];
        let e = element_matrices(ea, eb);
        let ke: Vec<f64> = (0..DOFS * DOFS)
            .map(|q| {
                let (r, c) = (q / DOFS, q % DOFS);
                (0..4).map(|t| p.d[t] * e.k_bend[t][r][c]).sum::<f64>()
                    + p.s[0] * e.k_shear[0][r][c]
                    + p.s[1] * e.k_shear[1][r][c]
            })
            .collect();
        let me: Vec<f64> = (0..DOFS * DOFS)
            .map(|q| {
                let (r, c) = (q / DOFS, q % DOFS);
                p.rho_h * e.m_trans[r][c] + p.inertia * e.m_rot[r][c]
            })
            .collect();
        let nd = DOFS;
        for ex in 0..nx {
            for ey in 0..ny {
                let map: Vec<usize> = (0..nd)
                    .map(|l| {
                        let (node, local) = if l < 16 {
                            (l / 4, l % 4)
                        } else {
                            ((l - 16) % 4, 4 + (l - 16) / 4)
                        };
                        let (i, j) = NODE_IJ[node];
                        ((ey + j) * (nx + 1) + ex + i) * per + local
                    })
                    .collect();
                for r in 0..nd {
                    for c in 0..nd {
                        k[map[r] * n + map[c]] += ke[r * nd + c];
                        m[map[r] * n + map[c]] += me[r * nd + c];
                    }
                }
            }
        }
        // Hard simple support: w = 0 on every edge, its tangential slope 0, and the
        // tangential shear strain 0 (θ's tangential component then vanishes too).
        let mut fixed = vec![false; n];
        for jn in 0..=ny {
            for inn in 0..=nx {
                let base = (jn * (nx + 1) + inn) * per;
                let x_edge = inn == 0 || inn == nx;
                let y_edge = jn == 0 || jn == ny;
                if x_edge || y_edge {
                    fixed[base] = true;
                }
                if x_edge {
                    fixed[base + 2] = true;
                    fixed[base + 5] = true;
                }
                if y_edge {
                    fixed[base + 1] = true;
                    fixed[base + 4] = true;
                }
            }
        }
        let free: Vec<usize> = (0..n).filter(|&i| !fixed[i]).collect();
        let r = free.len();
        let kf = faer::Mat::from_fn(r, r, |i, j| k[free[i] * n + free[j]]);
        let mf = faer::Mat::from_fn(r, r, |i, j| m[free[i] * n + free[j]]);
        let (_, ct) = crate::fem::rom::whiten(kf, &mf).expect("positive mass");
        let mut a: Vec<f64> = (0..r * r).map(|q| ct[(q / r, q % r)]).collect();
        let e = crate::fem::dense::lowest_eigenpairs(&mut a, r, 0, 0);
        e.values[..count]
            .iter()
            .map(|v| v.sqrt() / (2.0 * std::f64::consts::PI))
            .collect()
    }

    /// Kirchhoff's plate with rotary inertia (Rayleigh's), mode (m, n), in Hz: the limit of
    /// [`navier_hz`] as the shear stiffness grows.
    fn rayleigh_hz(p: &Plate, m: usize, n: usize) -> f64 {
        let (al, be) = (
            m as f64 * std::f64::consts::PI / p.a,
            n as f64 * std::f64::consts::PI / p.b,
        );
        let [d11, d22, d12, d66] = p.d;
        let k = d11 * al.powi(4) + 2.0 * (d12 + 2.0 * d66) * al * al * be * be + d22 * be.powi(4);
        (k / (p.rho_h + p.inertia * (al * al + be * be))).sqrt() / (2.0 * std::f64::consts::PI)
    }

    /// The simply supported orthotropic plate (16 × 10 elements) against Navier's Mindlin
    /// solution: the six lowest modes within 3e-4 (measured: 0.4–9.7e-5), where the shear
    /// makes them 0.55–2.8 % lower than Rayleigh's plate (G_z = 0.5 GPa). With ten thousand
    /// times the shear stiffness the element does not lock: Rayleigh's frequencies within
    /// 3e-4 (measured: the BFS's own discretization error, 0.4–9.5e-5).
    #[test]
    fn simply_supported_plate_matches_navier_and_does_not_lock() {
        let modes = [(1, 1), (2, 1), (1, 2), (3, 1), (2, 2), (3, 2)];
        let sorted = |mut v: Vec<f64>| {
            v.sort_by(f64::total_cmp);
            v
        };
        let p = plate(0.5e9);
        let mindlin = sorted(modes.iter().map(|&(m, n)| navier_hz(&p, m, n)).collect());
        let rayleigh = sorted(modes.iter().map(|&(m, n)| rayleigh_hz(&p, m, n)).collect());
        let fe = fe_hz(&p, 16, 10, modes.len());
        for ((f, exact), r) in fe.iter().zip(&mindlin).zip(&rayleigh) {
            let shear = r / exact - 1.0;
            assert!(
                shear > 5e-3,
                "the shear effect {shear} is too small to test"
            );
            assert!(
                (f / exact - 1.0).abs() < 3e-4,
                "FE {f} Hz against Navier's Mindlin {exact} Hz (Rayleigh {r} Hz)"
            );
        }
        let stiff = Plate {
            s: [1e4 * p.s[0]; 2],
            ..plate(0.5e9)
        };
        let fe = fe_hz(&stiff, 16, 10, modes.len());
        for (f, r) in fe.iter().zip(&rayleigh) {
            assert!(
                (f / r - 1.0).abs() < 3e-4,
                "stiff shear: FE {f} Hz against Rayleigh {r} Hz"
            );
        }
    }
}

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
//! Element DOFs: the BFS's 16 (node by node), then γx at the 4 nodes, then γy. With γ left
//! out (the leading 16 × 16 blocks, `n` = [`BFS_DOFS`]) the matrices are the BFS element's
//! own: the board model ([`super::model`]) takes them either way.

use super::plate::{gauss4, shape, NODE_IJ};

/// DOFs of one shear-deformable element; the first [`BFS_DOFS`] are the BFS element's.
pub const DOFS: usize = 24;

/// DOFs of the BFS (Kirchhoff) element: the same matrices' leading block.
pub const BFS_DOFS: usize = 16;

/// 24 × 24 element matrix, row-major.
pub type Mat24 = [[f64; DOFS]; DOFS];

/// The unit matrices of one element (or of part of it, see [`ElementMatrices::add_points`]):
/// each times its coefficient and summed gives the element's stiffness or mass. Only the
/// leading `n × n` block is used: `n` = [`BFS_DOFS`] is the Kirchhoff (BFS) element, whose
/// matrices are exactly that block of the shear-deformable one (γ = 0), and whose shear and
/// rotary-inertia matrices stay zero; `n` = [`DOFS`] the shear-deformable element.
#[derive(Clone, Debug)]
pub struct ElementMatrices {
    /// DOFs in use: [`BFS_DOFS`] or [`DOFS`].
    pub n: usize,
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

impl ElementMatrices {
    /// All zero, with `n` DOFs in use ([`BFS_DOFS`] or [`DOFS`]).
    pub fn zero(n: usize) -> ElementMatrices {
        assert!(
            n == BFS_DOFS || n == DOFS,
            "an element has 16 or 24 DOFs, not {n}"
        );
        let z = [[0.0; DOFS]; DOFS];
        ElementMatrices {
            n,
            k_bend: [z; 4],
            k_shear: [z; 2],
            m_trans: z,
            m_rot: z,
        }
    }

    /// Add `sign` × the integrals over the quadrature points `pts` (global `(x_m, y_m,
    /// weight_m2)`, all inside the element of size `a_m × b_m` whose lower-left corner is
    /// `(x0_m, y0_m)`): with `sign = -1` and the points of a hole, the element's matrices
    /// become integrals over its material part only (cut-cell quadrature).
    pub fn add_points(
        &mut self,
        pts: &[(f64, f64, f64)],
        x0_m: f64,
        y0_m: f64,
        a_m: f64,
        b_m: f64,
        sign: f64,
    ) {
        let nd = self.n;
        let shear = nd == DOFS;
        let add = |m: &mut Mat24, w: f64, u: &[f64; DOFS], v: &[f64; DOFS]| {
            for r in 0..nd {
                if u[r] == 0.0 {
                    continue;
                }
                let wu = w * u[r];
                for c in 0..nd {
                    m[r][c] += wu * v[c];
                }
            }
        };
        for &(x, y, wq) in pts {
            let (xi, eta) = ((x - x0_m) / a_m, (y - y0_m) / b_m);
            let w = sign * wq;
            let n = shape(xi, eta, a_m, b_m);
            // Rows over the DOFs: κ's three components, γ, θ and w.
            let [kxx, kyy, kxy] = curvature_rows(&n, xi, eta, a_m, b_m, shear);
            let mut w0 = [0.0; DOFS];
            w0[..BFS_DOFS].copy_from_slice(&n[0]);
            if shear {
                let l = bilinear(xi, eta, a_m, b_m);
                let mut gx = [0.0; DOFS];
                let mut gy = [0.0; DOFS];
                let mut tx = [0.0; DOFS];
                let mut ty = [0.0; DOFS];
                tx[..BFS_DOFS].copy_from_slice(&n[1]);
                ty[..BFS_DOFS].copy_from_slice(&n[2]);
                for k in 0..4 {
                    let (ix, iy) = (16 + k, 20 + k);
                    gx[ix] = l[0][k];
                    gy[iy] = l[0][k];
                    tx[ix] = -l[0][k];
                    ty[iy] = -l[0][k];
                }
                add(&mut self.k_shear[0], w, &gx, &gx);
                add(&mut self.k_shear[1], w, &gy, &gy);
                add(&mut self.m_rot, w, &tx, &tx);
                add(&mut self.m_rot, w, &ty, &ty);
            }
            add(&mut self.k_bend[0], w, &kxx, &kxx);
            add(&mut self.k_bend[1], w, &kyy, &kyy);
            add(&mut self.k_bend[2], w, &kxx, &kyy);
            add(&mut self.k_bend[2], w, &kyy, &kxx);
            add(&mut self.k_bend[3], w, &kxy, &kxy);
            add(&mut self.m_trans, w, &w0, &w0);
        }
        // Exactly symmetric: (w·a)·b and (w·b)·a differ in the last bit.
        for m in self
            .k_bend
            .iter_mut()
            .chain(self.k_shear.iter_mut())
            .chain([&mut self.m_trans, &mut self.m_rot])
        {
            for r in 0..nd {
                for c in 0..r {
                    let v = 0.5 * (m[r][c] + m[c][r]);
                    m[r][c] = v;
                    m[c][r] = v;
                }
            }
        }
    }
}

/// The curvature rows of an element at (ξ, η), over its DOFs: κxx, κyy and 2κxy (the
/// engineering twist) of the bending rotations, `n` being [`shape`] there. On a
/// shear-deformable element the rotations are w's slopes less the shear strains' bilinear
/// fields (DOFs 16–23), else w's slopes alone.
pub fn curvature_rows(
    n: &[[f64; 16]; 6],
    xi: f64,
    eta: f64,
    a_m: f64,
    b_m: f64,
    shear: bool,
) -> [[f64; DOFS]; 3] {
    let mut kxx = [0.0; DOFS];
    let mut kyy = [0.0; DOFS];
    let mut kxy = [0.0; DOFS];
    for k in 0..BFS_DOFS {
        kxx[k] = n[3][k];
        kyy[k] = n[4][k];
        kxy[k] = 2.0 * n[5][k];
    }
    if shear {
        let l = bilinear(xi, eta, a_m, b_m);
        for k in 0..4 {
            let (ix, iy) = (16 + k, 20 + k);
            kxx[ix] = -l[1][k];
            kyy[iy] = -l[2][k];
            kxy[ix] = -l[2][k];
            kxy[iy] = -l[1][k];
        }
    }
    [kxx, kyy, kxy]
}

/// Integrate the unit matrices of an `a_m × b_m` element with `n` DOFs ([`BFS_DOFS`] or
/// [`DOFS`]) by 4 × 4 Gauss points: exact, every integrand being of degree ≤ 6 in each
/// direction.
pub fn element_matrices(a_m: f64, b_m: f64, n: usize) -> ElementMatrices {
    let (pts, wts) = gauss4();
    let mut q = Vec::with_capacity(16);
    for (ix, &xi) in pts.iter().enumerate() {
        for (iy, &eta) in pts.iter().enumerate() {
            q.push((xi * a_m, eta * b_m, wts[ix] * wts[iy] * a_m * b_m));
        }
    }
    let mut e = ElementMatrices::zero(n);
    e.add_points(&q, 0.0, 0.0, a_m, b_m, 1.0);
    e
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::fem::tests::helpers::MindlinPlate as Plate;

    fn plate(g_z_pa: f64) -> Plate {
        let core = (22e9, 19e9, 3.5e9, 0.13);
        Plate::homogeneous(0.16, 0.10, 1.6e-3, core, (g_z_pa, g_z_pa), 1900.0)
    }

    /// The lowest `count` frequencies (Hz) of the simply supported plate on an nx × ny mesh.
    fn fe_hz(p: &Plate, nx: usize, ny: usize, count: usize) -> Vec<f64> {
        let (ea, eb) = (p.a / nx as f64, p.b / ny as f64);
        let nodes = (nx + 1) * (ny + 1);
        let per = 6;
        let n = nodes * per;
        let mut k = vec![0.0; n * n];
        let mut m = vec![0.0; n * n];
        let e = element_matrices(ea, eb, DOFS);
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
        let mindlin = sorted(modes.iter().map(|&(m, n)| p.navier_hz(m, n)).collect());
        let rayleigh = sorted(modes.iter().map(|&(m, n)| p.rayleigh_hz(m, n)).collect());
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

//! Classical lamination theory for the PCB stack: plane-stress stiffnesses of the
//! orthotropic FR-4 core and of isotropic copper, and the bending stiffness D
//! (N·m) of the core plus locally covered copper layers.
//!
//! For a layer k between heights z₁ < z₂ (m, measured from the core mid-plane) with
//! plane-stress stiffness Q (Pa):
//! A += Q (z₂ − z₁),  B += Q (z₂² − z₁²)/2,  D += Q (z₂³ − z₁³)/3.
//! The orthotropic Q has the four independent entries
//! Q₁₁ = E_x/(1 − ν_xy ν_yx), Q₂₂ = E_y/(1 − ν_xy ν_yx), Q₁₂ = ν_xy E_y/(1 − ν_xy ν_yx),
//! Q₆₆ = G_xy, with ν_yx = ν_xy E_y / E_x; every stiffness here is stored as the four
//! components `[c11, c22, c12, c66]` (the 16/26 terms vanish for a stack aligned with x, y).
//!
//! What we neglect, and why: the plate model carries only the out-of-plane DOFs, so
//! an asymmetric copper coverage (B ≠ 0) cannot couple to in-plane stretching. We
//! account for it by the reduced bending stiffness D* = D − B A⁻¹ B (the stiffness of
//! bending about the shifted neutral plane when the in-plane forces vanish), computed
//! When every copper layer is of one material (Q_cu, scaled by ε = E_cu/E_cu,0), an
//! element's stack is A = h Q_core + ε s Q_cu and B = ε t Q_cu with its two copper
//! variables s = Σ f_l t_l (m) and t = Σ f_l (z₂² − z₁²)/2 (m², f_l the coverage), so
//! the correction is −t² G(s; p) with G(s; p) = ε² Q_cu (h Q_core + ε s Q_cu)⁻¹ Q_cu
//! ([`coupling_kernel`]). G is smooth in s on [0, Σ t_l] (its pole lies at
//! s ≈ −h Q_core/(ε Q_cu), far outside), so Chebyshev interpolation in s with a few
//! nodes s_k is exact to ~1e-9 (of G, a few % of D) and gives an affine expansion
//! −Σ_k G(s_k; p) Σ_e t_e² ℓ_k(s_e) K_e that follows the moduli exactly (see the model).
//! With copper layers of different materials the correction is computed at the
//! nominal moduli and kept constant (a documented approximation, a few 1e-4 in
//! frequency over ±20 %).

/// Four plane-stress components `[c11, c22, c12, c66]`, in the unit of the context.
pub type Comp4 = [f64; 4];

/// Plane-stress stiffness of the orthotropic core, `[Q11, Q22, Q12, Q66]` in Pa.
pub fn orthotropic_q(e_x_pa: f64, e_y_pa: f64, g_xy_pa: f64, nu_xy: f64) -> Comp4 {
    let nu_yx = nu_xy * e_y_pa / e_x_pa;
    let den = 1.0 - nu_xy * nu_yx;
    [e_x_pa / den, e_y_pa / den, nu_xy * e_y_pa / den, g_xy_pa]
}

/// Plane-stress stiffness of an isotropic layer, `[Q11, Q22, Q12, Q66]` in Pa.
pub fn isotropic_q(e_pa: f64, nu: f64) -> Comp4 {
    let q = e_pa / (1.0 - nu * nu);
    [q, q, nu * q, e_pa / (2.0 * (1.0 + nu))]
}

/// The Q at which the core's stiffness terms are assembled: the nominal Q, except that a
/// component that is zero there (Q12 of a core with ν_xy = 0) is assembled at ½(Q11 + Q22)
/// instead, so that each term's coefficient Q_c(p) / scale_c stays finite.
pub fn core_q_scale(q_nominal: Comp4) -> Comp4 {
    let fallback = 0.5 * (q_nominal[0] + q_nominal[1]);
    q_nominal.map(|v| if v == 0.0 { fallback } else { v })
}

/// A/B/D integrals of a layer between `z1_m < z2_m`: returns
/// `(z₂ − z₁, (z₂² − z₁²)/2, (z₂³ − z₁³)/3)`, the factors multiplying Q.
pub fn layer_factors(z1_m: f64, z2_m: f64) -> (f64, f64, f64) {
    (
        z2_m - z1_m,
        0.5 * (z2_m * z2_m - z1_m * z1_m),
        (z2_m.powi(3) - z1_m.powi(3)) / 3.0,
    )
}

fn to_mat(c: Comp4) -> [[f64; 3]; 3] {
    [[c[0], c[2], 0.0], [c[2], c[1], 0.0], [0.0, 0.0, c[3]]]
}

/// Correction −B A⁻¹ B (N·m) to the bending stiffness of a stack with membrane
/// stiffness `a` (N/m) and coupling `b` (N), both as `[c11, c22, c12, c66]`.
/// Returns zeros when B = 0.
pub fn coupling_correction(a: Comp4, b: Comp4) -> Comp4 {
    if b.iter().all(|v| *v == 0.0) {
        return [0.0; 4];
    }
    // A is block diagonal: 2×2 normal block plus the shear entry.
    let det = a[0] * a[1] - a[2] * a[2];
    let ai = [a[1] / det, a[0] / det, -a[2] / det, 1.0 / a[3]];
    let (bm, aim) = (to_mat(b), to_mat(ai));
    let mut t = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            t[i][j] = (0..3).map(|k| aim[i][k] * bm[k][j]).sum();
        }
    }
    let mut r = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            r[i][j] = (0..3).map(|k| bm[i][k] * t[k][j]).sum();
        }
    }
    [-r[0][0], -r[1][1], -r[0][1], -r[2][2]]
}

type M3 = [[f64; 3]; 3];

fn mul3(a: &M3, b: &M3) -> M3 {
    let mut r = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            r[i][j] = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    r
}

fn inv_block(n: &M3) -> M3 {
    // Block diagonal: 2×2 normal block and the shear entry.
    let det = n[0][0] * n[1][1] - n[0][1] * n[1][0];
    [
        [n[1][1] / det, -n[0][1] / det, 0.0],
        [-n[1][0] / det, n[0][0] / det, 0.0],
        [0.0, 0.0, 1.0 / n[2][2]],
    ]
}

fn comp(m: &M3) -> Comp4 {
    [m[0][0], m[1][1], m[0][1], m[2][2]]
}

/// G of [`coupling_kernel`] alone, for the sampler's hot path (the same operations, so
/// the same bits).
pub fn coupling_value(q_core: Comp4, h_m: f64, q_cu: Comp4, eps: f64, s_m: f64) -> Comp4 {
    coupling_parts(q_core, h_m, q_cu, eps, s_m).0
}

/// (G, N⁻¹ Q_cu, Q_cu N⁻¹ Q_cu) of the coupling kernel.
#[inline(always)]
fn coupling_parts(q_core: Comp4, h_m: f64, q_cu: Comp4, eps: f64, s_m: f64) -> (Comp4, M3, M3) {
    let qc = to_mat(q_cu);
    let n = to_mat(std::array::from_fn(|k| {
        h_m * q_core[k] + eps * s_m * q_cu[k]
    }));
    let ni = inv_block(&n);
    let x = mul3(&ni, &qc); // N⁻¹ Q_cu
    let qx = mul3(&qc, &x); // Q_cu N⁻¹ Q_cu
    let g = comp(&qx).map(|v| eps * eps * v);
    (g, x, qx)
}

/// The coupling kernel G(s; p) = ε² Q_cu (h Q_core + ε s Q_cu)⁻¹ Q_cu (N·m per m² of
/// t², see the module doc) and its derivatives: returns `(G, ∂G/∂Q_core[j] for the four
/// core components j, ∂G/∂ε)`, all as `[c11, c22, c12, c66]`.
pub fn coupling_kernel(
    q_core: Comp4,
    h_m: f64,
    q_cu: Comp4,
    eps: f64,
    s_m: f64,
) -> (Comp4, [Comp4; 4], Comp4) {
    let (g, x, qx) = coupling_parts(q_core, h_m, q_cu, eps, s_m);
    // ∂G/∂Q_core[j] = −ε² h (N⁻¹ Q_cu)ᵀ E_j (N⁻¹ Q_cu), E_j the unit pattern of j.
    let d_core = std::array::from_fn(|j| {
        let mut e = [0.0; 4];
        e[j] = h_m;
        let ej = to_mat(e);
        let xt: M3 = std::array::from_fn(|r| std::array::from_fn(|c| x[c][r]));
        comp(&mul3(&xt, &mul3(&ej, &x))).map(|v| -eps * eps * v)
    });
    // ∂G/∂ε = 2ε Q N⁻¹ Q − ε² s Q N⁻¹ Q N⁻¹ Q.
    let qxx = mul3(&qx, &x);
    let d_eps = std::array::from_fn(|k| 2.0 * eps * comp(&qx)[k] - eps * eps * s_m * comp(&qxx)[k]);
    (g, d_core, d_eps)
}

/// Chebyshev points of the second kind on `[0, s_max]`, `n` ≥ 2 of them (ends included).
pub fn chebyshev_nodes(n: usize, s_max: f64) -> Vec<f64> {
    (0..n)
        .map(|k| 0.5 * s_max * (1.0 - (std::f64::consts::PI * k as f64 / (n - 1) as f64).cos()))
        .collect()
}

/// Lagrange basis values ℓ_k(s) of the nodes `nodes` at `s`.
pub fn lagrange_basis(nodes: &[f64], s: f64) -> Vec<f64> {
    (0..nodes.len())
        .map(|k| {
            nodes
                .iter()
                .enumerate()
                .filter(|(j, _)| *j != k)
                .map(|(_, sj)| (s - sj) / (nodes[k] - sj))
                .product()
        })
        .collect()
}

/// One layer of a stack for [`transverse_shear_stiffness`]: between heights `z1_m < z2_m`,
/// its plane-stress stiffness along the bending direction `q_pa` (Q11 for x, Q22 for y) and
/// its transverse shear modulus in that plane `g_z_pa` (G_xz, G_yz).
#[derive(Clone, Copy, Debug)]
pub struct ShearLayer {
    pub z1_m: f64,
    pub z2_m: f64,
    pub q_pa: f64,
    pub g_z_pa: f64,
}

/// The transverse shear stiffness S (N/m) of a stack in one direction, energy-consistent
/// (Whitney 1973; the laminate form of Reissner's 5/6): in cylindrical bending the shear
/// stress follows from equilibrium, τ(z) = Q_x g(z)/D* with g(z) = ∫_bottom^z q (ζ − z_n) dζ
/// about the neutral plane z_n = B/A, and S is set so that Q_x²/(2S) is its strain energy
/// ½ ∫ τ²/G dz: S = D*² / ∫ g²/G dz. A homogeneous layer gives 5/6 G h; a sandwich of thin
/// stiff faces on a soft core, G_core d²/c (faces' centroids d apart, core thickness c).
/// Layers are taken in order of height; each layer's integral is exact (3-point Gauss on
/// g², a quartic). Needs at least one layer with q > 0 and every g > 0.
pub fn transverse_shear_stiffness(layers: &[ShearLayer]) -> f64 {
    let mut ls = layers.to_vec();
    ls.sort_by(|a, b| a.z1_m.total_cmp(&b.z1_m));
    let a: f64 = ls.iter().map(|l| l.q_pa * (l.z2_m - l.z1_m)).sum();
    let b: f64 = ls
        .iter()
        .map(|l| l.q_pa * 0.5 * (l.z2_m * l.z2_m - l.z1_m * l.z1_m))
        .sum();
    let zn = b / a;
    let d_star: f64 = ls
        .iter()
        .map(|l| l.q_pa * ((l.z2_m - zn).powi(3) - (l.z1_m - zn).powi(3)) / 3.0)
        .sum();
    // 3-point Gauss-Legendre on [−1, 1].
    let (gp, gw) = (
        [-(0.6f64).sqrt(), 0.0, (0.6f64).sqrt()],
        [5.0 / 9.0, 8.0 / 9.0, 5.0 / 9.0],
    );
    let mut g0 = 0.0;
    let mut energy = 0.0;
    for l in &ls {
        let g = |z: f64| g0 + 0.5 * l.q_pa * ((z - zn).powi(2) - (l.z1_m - zn).powi(2));
        let (mid, half) = (0.5 * (l.z1_m + l.z2_m), 0.5 * (l.z2_m - l.z1_m));
        energy += gp
            .iter()
            .zip(&gw)
            .map(|(p, w)| w * half * g(mid + half * p).powi(2) / l.g_z_pa)
            .sum::<f64>();
        g0 = g(l.z2_m);
    }
    d_star * d_star / energy
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn isotropic_q_matches_orthotropic_with_equal_moduli() {
        let (e, nu) = (70e9, 0.33);
        let iso = isotropic_q(e, nu);
        let ort = orthotropic_q(e, e, e / (2.0 * (1.0 + nu)), nu);
        for k in 0..4 {
            assert!((iso[k] - ort[k]).abs() <= 1e-12 * iso[0]);
        }
    }

    #[test]
    fn symmetric_layer_has_d_equal_q_h3_over_12_and_no_coupling() {
        let h = 1.5e-3;
        let (a, b, d) = layer_factors(-h / 2.0, h / 2.0);
        assert!((a - h).abs() < 1e-18);
        assert!(b.abs() < 1e-18);
        assert!((d - h.powi(3) / 12.0).abs() < 1e-22);
    }

    #[test]
    fn coupling_kernel_reproduces_the_correction_and_its_interpolation_is_exact() {
        let h = 1.5e-3;
        let q_core = orthotropic_q(26e9, 24e9, 6e9, 0.14);
        let q_cu = isotropic_q(117e9, 0.34);
        let (t_top, t_bot) = (35e-6, 18e-6);
        let (fa_t, fb_t, _) = layer_factors(h / 2.0, h / 2.0 + t_top);
        let (fa_b, fb_b, _) = layer_factors(-h / 2.0 - t_bot, -h / 2.0);
        let nodes = chebyshev_nodes(8, t_top + t_bot);
        for (f_top, f_bot, eps) in [(1.0, 0.0, 1.0), (0.37, 0.81, 1.2), (0.5, 0.5, 0.8)] {
            let s = f_top * fa_t + f_bot * fa_b;
            let t = f_top * fb_t + f_bot * fb_b;
            let a: Comp4 = std::array::from_fn(|k| h * q_core[k] + eps * s * q_cu[k]);
            let b: Comp4 = std::array::from_fn(|k| eps * t * q_cu[k]);
            let direct = coupling_correction(a, b);
            let (g, _, _) = coupling_kernel(q_core, h, q_cu, eps, s);
            let l = lagrange_basis(&nodes, s);
            for k in 0..4 {
                assert!((direct[k] + t * t * g[k]).abs() <= 1e-12 * direct[0].abs());
                let interp: f64 = nodes
                    .iter()
                    .zip(&l)
                    .map(|(sk, lk)| lk * coupling_kernel(q_core, h, q_cu, eps, *sk).0[k])
                    .sum();
                assert!(
                    (interp - g[k]).abs() <= 1e-8 * g[0].abs(),
                    "{interp} vs {}",
                    g[k]
                );
            }
            // Derivatives against central differences.
            let (_, dq, de) = coupling_kernel(q_core, h, q_cu, eps, s);
            for j in 0..4 {
                let dh = 1e-6 * q_core[j].abs();
                let mut qp = q_core;
                qp[j] += dh;
                let mut qm = q_core;
                qm[j] -= dh;
                let fd: Comp4 = std::array::from_fn(|k| {
                    (coupling_kernel(qp, h, q_cu, eps, s).0[k]
                        - coupling_kernel(qm, h, q_cu, eps, s).0[k])
                        / (2.0 * dh)
                });
                for k in 0..4 {
                    assert!(
                        (fd[k] - dq[j][k]).abs()
                            <= 1e-6 * g[0].abs() / q_core[0] + 1e-7 * fd[k].abs()
                    );
                }
            }
            let fd: Comp4 = std::array::from_fn(|k| {
                (coupling_kernel(q_core, h, q_cu, eps + 1e-6, s).0[k]
                    - coupling_kernel(q_core, h, q_cu, eps - 1e-6, s).0[k])
                    / 2e-6
            });
            for k in 0..4 {
                assert!((fd[k] - de[k]).abs() <= 1e-6 * g[0].abs());
            }
        }
    }

    #[test]
    fn coupling_correction_matches_neutral_axis_shift_for_isotropic_bimaterial() {
        // Two isotropic layers with the same ν: D* equals the bending stiffness about
        // the neutral axis, Σ Q_k ((z₂−e)³ − (z₁−e)³)/3 with e = B/A (closed form).
        let nu = 0.3;
        let (q1, q2) = (isotropic_q(20e9, nu), isotropic_q(120e9, nu));
        let layers = [(q1, -0.75e-3, 0.75e-3), (q2, 0.75e-3, 0.785e-3)];
        let (mut a, mut b, mut d) = ([0.0; 4], [0.0; 4], [0.0; 4]);
        for (q, z1, z2) in layers {
            let (fa, fb, fd) = layer_factors(z1, z2);
            for k in 0..4 {
                a[k] += q[k] * fa;
                b[k] += q[k] * fb;
                d[k] += q[k] * fd;
            }
        }
        let corr = coupling_correction(a, b);
        let e = b[0] / a[0];
        let d_na: f64 = layers
            .iter()
            .map(|(q, z1, z2)| q[0] * ((z2 - e).powi(3) - (z1 - e).powi(3)) / 3.0)
            .sum();
        let d_star = d[0] + corr[0];
        assert!((d_star - d_na).abs() < 1e-9 * d_na, "{d_star} vs {d_na}");
    }

    /// Against closed forms: a homogeneous layer gives 5/6 G h wherever it sits (to 1e-12); a
    /// sandwich of thin faces (t = c/100, q 1e6 times the core's) on a soft core gives
    /// G_core d²/c within 2 % (the faces' own shear and the core's bending are of order t/c
    /// and q_core/q_face). The PCB stack's stiff copper faces make the core's shear stress
    /// more uniform than a homogeneous layer's: its S (5.07e6 N/m) lies between the
    /// homogeneous 5/6 G h of its thickness (4.58e6) and the sandwich limit G d²/c (5.50e6).
    #[test]
    fn transverse_shear_stiffness_against_closed_forms() {
        use super::{transverse_shear_stiffness as s, ShearLayer as L};
        let (g, h) = (3.5e9, 1.6e-3);
        for z0 in [-0.8e-3, 0.0, 2.0e-3] {
            let v = s(&[L {
                z1_m: z0,
                z2_m: z0 + h,
                q_pa: 22e9,
                g_z_pa: g,
            }]);
            let exact = 5.0 / 6.0 * g * h;
            assert!((v / exact - 1.0).abs() < 1e-12, "{v} vs {exact}");
        }
        let (c, t, gc) = (10e-3, 0.1e-3, 50e6);
        let layers = [
            L {
                z1_m: -0.5 * c - t,
                z2_m: -0.5 * c,
                q_pa: 70e9,
                g_z_pa: 26e9,
            },
            L {
                z1_m: -0.5 * c,
                z2_m: 0.5 * c,
                q_pa: 70e3,
                g_z_pa: gc,
            },
            L {
                z1_m: 0.5 * c,
                z2_m: 0.5 * c + t,
                q_pa: 70e9,
                g_z_pa: 26e9,
            },
        ];
        let exact = gc * (c + t).powi(2) / c;
        let v = s(&layers);
        assert!((v / exact - 1.0).abs() < 0.02, "sandwich {v} vs {exact}");
        // The layers in any order give the same S.
        let rev: Vec<L> = layers.iter().rev().copied().collect();
        assert_eq!(v, s(&rev));
        // PCB: 1.5 mm FR-4 core, 35 µm copper each side.
        let (hc, tc) = (1.5e-3, 35e-6);
        let pcb = [
            L {
                z1_m: -0.5 * hc - tc,
                z2_m: -0.5 * hc,
                q_pa: 131e9,
                g_z_pa: 45e9,
            },
            L {
                z1_m: -0.5 * hc,
                z2_m: 0.5 * hc,
                q_pa: 22e9,
                g_z_pa: g,
            },
            L {
                z1_m: 0.5 * hc,
                z2_m: 0.5 * hc + tc,
                q_pa: 131e9,
                g_z_pa: 45e9,
            },
        ];
        let v = s(&pcb);
        let (homogeneous, sandwich) = (5.0 / 6.0 * g * (hc + 2.0 * tc), g * (hc + tc).powi(2) / hc);
        assert!(
            v > homogeneous && v < sandwich,
            "{v} outside {homogeneous} … {sandwich}"
        );
    }
}

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
//! at the nominal moduli and kept as a constant correction. For a 35 µm copper layer
//! on one face of a 1.5 mm core the correction is a few per cent of D; freezing it
//! over a ±20 % modulus change moves D by well under 1 %, and where both faces carry
//! the same copper B = 0 and the correction vanishes.

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
}

//! The Bogner–Fox–Schmit (BFS) thin-plate rectangle: a conforming Kirchhoff element
//! with 4 nodes and the DOFs (w, ∂w/∂x, ∂w/∂y, ∂²w/∂x∂y) per node, 16 in all.
//!
//! The shape functions are tensor products of 1-D cubic Hermite polynomials on the
//! element `[0, a] × [0, b]` (m), so w is C¹ across element edges: the element is
//! conforming, free of shear locking (there is no shear strain), reproduces the rigid
//! modes 1, x, y exactly, and its frequencies converge as O(h⁴).
//!
//! Local node order: (0,0), (a,0), (a,b), (0,b); DOF order per node as above.
//! The bending energy is U = ½ ∫ κᵀ D κ dA with κ = (w_xx, w_yy, 2 w_xy) and
//! D = [[D11, D12, 0], [D12, D22, 0], [0, 0, D66]] (N·m), so
//! K_e = D11 K₁₁ + D22 K₂₂ + D12 K₁₂ + D66 K₆₆ with the four "unit" matrices
//! K₁₁ = ∫ N_xx N_xxᵀ, K₂₂ = ∫ N_yy N_yyᵀ, K₁₂ = ∫ (N_xx N_yyᵀ + N_yy N_xxᵀ),
//! K₆₆ = ∫ 4 N_xy N_xyᵀ; the consistent mass is M_e = ρh ∫ N Nᵀ (rotary inertia
//! neglected, as in Kirchhoff theory). Integrals use 4 × 4 Gauss points, exact for
//! these polynomial degrees (≤ 6 per direction).

/// 16 × 16 element matrix, row-major.
pub type Mat16 = [[f64; 16]; 16];

/// Local node offsets (i, j) ∈ {0,1}² in the node order of the module doc.
pub const NODE_IJ: [(usize, usize); 4] = [(0, 0), (1, 0), (1, 1), (0, 1)];

/// Cubic Hermite functions on s ∈ [0,1] for an edge of length `len_m`:
/// returns `[f0, g0, f1, g1]` and their first and second derivatives in s, where
/// f_k is 1 at end k in value, g_k has unit slope (per metre) at end k.
fn hermite(s: f64, len_m: f64) -> [[f64; 4]; 3] {
    let (s2, s3) = (s * s, s * s * s);
    [
        [
            1.0 - 3.0 * s2 + 2.0 * s3,
            len_m * (s - 2.0 * s2 + s3),
            3.0 * s2 - 2.0 * s3,
            len_m * (-s2 + s3),
        ],
        [
            -6.0 * s + 6.0 * s2,
            len_m * (1.0 - 4.0 * s + 3.0 * s2),
            6.0 * s - 6.0 * s2,
            len_m * (-2.0 * s + 3.0 * s2),
        ],
        [
            -6.0 + 12.0 * s,
            len_m * (-4.0 + 6.0 * s),
            6.0 - 12.0 * s,
            len_m * (-2.0 + 6.0 * s),
        ],
    ]
}

/// Shape functions and derivatives at local coordinates (ξ, η) ∈ [0,1]²:
/// `[N, N_x, N_y, N_xx, N_yy, N_xy]`, each of length 16 (derivatives in 1/m, 1/m²).
pub fn shape(xi: f64, eta: f64, a_m: f64, b_m: f64) -> [[f64; 16]; 6] {
    let hx = hermite(xi, a_m);
    let hy = hermite(eta, b_m);
    let mut out = [[0.0; 16]; 6];
    for (node, &(i, j)) in NODE_IJ.iter().enumerate() {
        // (x-function index, y-function index) for w, w_x, w_y, w_xy.
        let pairs = [
            (2 * i, 2 * j),
            (2 * i + 1, 2 * j),
            (2 * i, 2 * j + 1),
            (2 * i + 1, 2 * j + 1),
        ];
        for (d, &(fx, fy)) in pairs.iter().enumerate() {
            let k = 4 * node + d;
            out[0][k] = hx[0][fx] * hy[0][fy];
            out[1][k] = hx[1][fx] * hy[0][fy] / a_m;
            out[2][k] = hx[0][fx] * hy[1][fy] / b_m;
            out[3][k] = hx[2][fx] * hy[0][fy] / (a_m * a_m);
            out[4][k] = hx[0][fx] * hy[2][fy] / (b_m * b_m);
            out[5][k] = hx[1][fx] * hy[1][fy] / (a_m * b_m);
        }
    }
    out
}

/// Gauss–Legendre 4-point rule on [0,1]: (points, weights).
pub(crate) fn gauss4() -> ([f64; 4], [f64; 4]) {
    let p1 = (3.0 / 7.0 - 2.0 / 7.0 * (6.0f64 / 5.0).sqrt()).sqrt();
    let p2 = (3.0 / 7.0 + 2.0 / 7.0 * (6.0f64 / 5.0).sqrt()).sqrt();
    let w1 = (18.0 + 30.0f64.sqrt()) / 36.0;
    let w2 = (18.0 - 30.0f64.sqrt()) / 36.0;
    (
        [
            0.5 - 0.5 * p2,
            0.5 - 0.5 * p1,
            0.5 + 0.5 * p1,
            0.5 + 0.5 * p2,
        ],
        [0.5 * w2, 0.5 * w1, 0.5 * w1, 0.5 * w2],
    )
}

/// Make a 16 × 16 matrix exactly symmetric (quadrature sums differ in the last bit).
fn symmetrize16(mat: &mut Mat16) {
    for r in 0..16 {
        for c in 0..r {
            let v = 0.5 * (mat[r][c] + mat[c][r]);
            mat[r][c] = v;
            mat[c][r] = v;
        }
    }
}

/// Integrals of one element's shape functions over part of it (a joint patch):
/// `nn` = ∫ N Nᵀ dA (m²), `n` = ∫ N dA (m²), `grad` = ∫ (N_x N_xᵀ + N_y N_yᵀ) dA
/// (dimensionless), `area_m2` = ∫ dA, and the moments a stuck contact's in-plane springs
/// need (x, y in the board's frame).
#[derive(Clone, Debug)]
pub struct PartIntegrals {
    /// ∫ N Nᵀ dA, m².
    pub nn: Mat16,
    /// ∫ N dA, m².
    pub n: [f64; 16],
    /// ∫ (N_x N_xᵀ + N_y N_yᵀ) dA.
    pub grad: Mat16,
    /// ∫ dA, m².
    pub area_m2: f64,
    /// ∫ N_x dA and ∫ N_y dA, m.
    pub n_x: [f64; 16],
    pub n_y: [f64; 16],
    /// ∫ (x N_y − y N_x) dA, m²: the slopes' work against an in-plane rotation about z.
    pub n_rot: [f64; 16],
    /// ∫ x dA and ∫ y dA, m³.
    pub x_m3: f64,
    pub y_m3: f64,
    /// ∫ (x² + y²) dA, m⁴.
    pub r2_m4: f64,
}

/// [`PartIntegrals`] over the quadrature points `pts` of the element with lower-left
/// corner `(x0_m, y0_m)` and size `a_m × b_m`.
pub fn part_integrals(
    pts: &[(f64, f64, f64)],
    x0_m: f64,
    y0_m: f64,
    a_m: f64,
    b_m: f64,
) -> PartIntegrals {
    let mut out = PartIntegrals {
        nn: [[0.0; 16]; 16],
        n: [0.0; 16],
        grad: [[0.0; 16]; 16],
        area_m2: 0.0,
        n_x: [0.0; 16],
        n_y: [0.0; 16],
        n_rot: [0.0; 16],
        x_m3: 0.0,
        y_m3: 0.0,
        r2_m4: 0.0,
    };
    for &(x, y, w) in pts {
        let s = shape((x - x0_m) / a_m, (y - y0_m) / b_m, a_m, b_m);
        out.area_m2 += w;
        out.x_m3 += w * x;
        out.y_m3 += w * y;
        out.r2_m4 += w * (x * x + y * y);
        for r in 0..16 {
            out.n[r] += w * s[0][r];
            out.n_x[r] += w * s[1][r];
            out.n_y[r] += w * s[2][r];
            out.n_rot[r] += w * (x * s[2][r] - y * s[1][r]);
            for c in 0..16 {
                out.nn[r][c] += w * s[0][r] * s[0][c];
                out.grad[r][c] += w * (s[1][r] * s[1][c] + s[2][r] * s[2][c]);
            }
        }
    }
    symmetrize16(&mut out.nn);
    symmetrize16(&mut out.grad);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shape_functions_interpolate_nodal_dofs() {
        let (a, b) = (0.003, 0.002);
        for (node, &(i, j)) in NODE_IJ.iter().enumerate() {
            let n = shape(i as f64, j as f64, a, b);
            for k in 0..16 {
                let want = |d: usize| if k == 4 * node + d { 1.0 } else { 0.0 };
                assert!((n[0][k] - want(0)).abs() < 1e-12);
                assert!((n[1][k] - want(1)).abs() < 1e-9);
                assert!((n[2][k] - want(2)).abs() < 1e-9);
                assert!((n[5][k] - want(3)).abs() < 1e-6);
            }
        }
    }
}

//! Shared builders for the tests: plain plates and constrained eigen-solves.

use faer::linalg::solvers::Solve;
use faer::sparse::linalg::solvers::{Llt, SymbolicLlt};
use faer::Side;

use crate::fem::board::{Board, CoreMaterial, JointData, MeshOptions, ScanGrid};
use crate::fem::eigen::{shift_invert_lanczos, EigenOptions};
use crate::fem::model::{FeModel, Setup};
use crate::fem::sparse::Pattern;

/// The built-in board as a thin (Kirchhoff) plate (`data/boards/paper_thin.toml`, the
/// built-in board before it became shear-deformable): the fixture of the kernels' tests,
/// whose references and tolerances are the thin plate's and whose meshes it converges on.
pub fn thin_board() -> Board {
    Board::from_toml_str(include_str!("../../../data/boards/paper_thin.toml"))
        .expect("data/boards/paper_thin.toml parses")
}

/// A plain plate: no copper, no holes.
#[allow(
    clippy::too_many_arguments,
    reason = "test helper mirroring the material constants one to one"
)]
pub fn plain_board(lx: f64, ly: f64, h: f64, ex: f64, ey: f64, g: f64, nu: f64, rho: f64) -> Board {
    Board {
        name: "plain".into(),
        length_x_m: lx,
        width_y_m: ly,
        core: CoreMaterial {
            thickness_m: h,
            e_x_pa: ex,
            e_y_pa: ey,
            g_xy_pa: g,
            nu_xy: nu,
            density_kg_per_m3: rho,
            g_xz_pa: None,
            g_yz_pa: None,
        },
        copper: vec![],
        holes: vec![],
        joint: Some(JointData {
            clamp_diameter_m: 1e-3,
            k_con_n_per_m: 1e6,
            bolt_mass_kg: 0.0,
            tangential_over_normal: 0.0,
        }),
        mesh: MeshOptions { nx: 8, ny: 8 },
        mesh_bolted: None,
        scan_grid: ScanGrid {
            nx: 3,
            ny: 3,
            margin_m: 0.0,
        },
        gerber: None,
    }
}

/// Lowest `nev` eigenvalues (rad²/s²) of the nominal model with the DOFs in `fixed`
/// removed (homogeneous Dirichlet conditions).
pub fn constrained_eigenvalues(
    model: &FeModel,
    fixed: &[usize],
    nev: usize,
    shift: f64,
) -> Vec<f64> {
    let n = model.n_dof;
    let mut keep = vec![true; n];
    for &d in fixed {
        keep[d] = false;
    }
    let mut map = vec![None; n];
    let mut m = 0;
    for i in 0..n {
        if keep[i] {
            map[i] = Some(m);
            m += 1;
        }
    }
    reduced_eigenvalues(model, &model.nominal_params(), &map, m, nev, shift)
}

/// Lowest `nev` eigenvalues (rad²/s²) of the model at `p` on the subspace u = T v,
/// where T has one entry 1 per kept DOF: DOF i is `v[map[i]]`, or 0 when `map[i]` is
/// `None` (several DOFs may share a reduced index: they are tied equal). The pencil is
/// (Tᵀ K T, Tᵀ M T) on `m` reduced DOFs, assembled from the model's triplets.
pub fn reduced_eigenvalues(
    model: &FeModel,
    p: &crate::fem::Params,
    map: &[Option<usize>],
    m: usize,
    nev: usize,
    shift: f64,
) -> Vec<f64> {
    let red = |t: Vec<(usize, usize, f64)>| -> Vec<(usize, usize, f64)> {
        t.into_iter()
            .filter_map(|(r, c, v)| Some((map[r]?, map[c]?, v)))
            .collect()
    };
    let kt = red(model.stiffness_triplets(p).unwrap());
    let mt = red(model.mass_triplets(p).unwrap());
    let pat = Pattern::from_entries(m, kt.iter().chain(&mt).map(|&(r, c, _)| (r, c)));
    let mut kv = vec![0.0; pat.row_idx.len()];
    let mut mv = vec![0.0; pat.row_idx.len()];
    for (r, c, v) in kt {
        kv[pat.index(r, c)] += v;
    }
    for (r, c, v) in mt {
        mv[pat.index(r, c)] += v;
    }
    let opts = EigenOptions {
        shift,
        ..EigenOptions::default()
    };
    let a: Vec<f64> = kv.iter().zip(&mv).map(|(k, mm)| k - shift * mm).collect();
    let sym = SymbolicLlt::try_new(pat.symbolic.as_ref(), Side::Lower).unwrap();
    let llt = Llt::try_new_with_symbolic(sym, pat.view(&a), Side::Lower).unwrap();
    let (l, _) = shift_invert_lanczos(
        m,
        nev,
        &opts,
        |x| llt.solve_in_place(x.as_mut()),
        |x, y| pat.matvec(&mv, x, y),
    )
    .unwrap();
    l
}

/// DOFs to fix for simple supports on all four edges of a hole-free plate:
/// w on every edge node, the tangential slope along each edge.
pub fn simply_supported_dofs(model: &FeModel) -> Vec<usize> {
    let (nx, ny) = (model.mesh.nx, model.mesh.ny);
    let mut fixed = Vec::new();
    for j in 0..=ny {
        for i in 0..=nx {
            let Some(d) = model.mesh.node_dof[j * (nx + 1) + i] else {
                continue;
            };
            let on_x_edge = i == 0 || i == nx; // edge x = const: w and w_y vanish
            let on_y_edge = j == 0 || j == ny; // edge y = const: w and w_x vanish
            if on_x_edge || on_y_edge {
                fixed.push(d);
            }
            // Hard support: the tangential slope vanishes, and on a shear-deformable plate
            // the tangential shear strain too (so does the normal's tangential rotation).
            let shear = model.mesh.dofs_per_node == 6;
            if on_x_edge {
                fixed.push(d + 2);
                if shear {
                    fixed.push(d + 5);
                }
            }
            if on_y_edge {
                fixed.push(d + 1);
                if shear {
                    fixed.push(d + 4);
                }
            }
        }
    }
    fixed
}

pub fn build(board: &Board, setup: Setup, nx: usize, ny: usize) -> FeModel {
    FeModel::build(board, setup, &MeshOptions { nx, ny }).unwrap()
}

/// A specially orthotropic plate for the shear-deformable references: size a × b (m),
/// bending stiffnesses D = [D11, D22, D12, D66] (N·m), transverse shear stiffnesses
/// S = [S_x, S_y] (N/m), mass per area ρh (kg/m²) and rotary inertia I = ρh³/12 (kg).
#[derive(Clone, Copy, Debug)]
pub struct MindlinPlate {
    pub a: f64,
    pub b: f64,
    pub d: [f64; 4],
    pub s: [f64; 2],
    pub rho_h: f64,
    pub inertia: f64,
}

impl MindlinPlate {
    /// Of a homogeneous orthotropic core: S = 5/6 G h (Reissner), I = ρ h³/12.
    pub fn homogeneous(
        a: f64,
        b: f64,
        h: f64,
        (ex, ey, gxy, nu): (f64, f64, f64, f64),
        (gxz, gyz): (f64, f64),
        rho: f64,
    ) -> MindlinPlate {
        let den = 1.0 - nu * nu * ey / ex;
        let h3 = h * h * h / 12.0;
        MindlinPlate {
            a,
            b,
            d: [ex * h3 / den, ey * h3 / den, nu * ey * h3 / den, gxy * h3],
            s: [5.0 / 6.0 * gxz * h, 5.0 / 6.0 * gyz * h],
            rho_h: rho * h,
            inertia: rho * h3,
        }
    }

    /// Navier's solution of the hard simply supported plate, mode (m, n): w = W sin sin,
    /// θx = X cos sin, θy = Y sin cos; the lowest root of the 3 × 3 pencil, in Hz.
    pub fn navier_hz(&self, m: usize, n: usize) -> f64 {
        let (al, be) = (
            m as f64 * std::f64::consts::PI / self.a,
            n as f64 * std::f64::consts::PI / self.b,
        );
        let [d11, d22, d12, d66] = self.d;
        let [sx, sy] = self.s;
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
                d22 * be * be + d66 * al * al + sy,
            ],
        ];
        // M = diag(ρh, I, I): the symmetric C = M^-½ K M^-½, its lowest eigenvalue.
        let ms = [self.rho_h, self.inertia, self.inertia];
        let mut c: Vec<f64> = (0..9)
            .map(|q| k[q / 3][q % 3] / (ms[q / 3] * ms[q % 3]).sqrt())
            .collect();
        let e = crate::fem::dense::lowest_eigenpairs(&mut c, 3, 0, 1);
        e.values[0].sqrt() / (2.0 * std::f64::consts::PI)
    }

    /// Kirchhoff's plate with rotary inertia (Rayleigh's), mode (m, n), in Hz: the limit of
    /// [`Self::navier_hz`] as the shear stiffness grows.
    pub fn rayleigh_hz(&self, m: usize, n: usize) -> f64 {
        let (al, be) = (
            m as f64 * std::f64::consts::PI / self.a,
            n as f64 * std::f64::consts::PI / self.b,
        );
        let [d11, d22, d12, d66] = self.d;
        let k = d11 * al.powi(4) + 2.0 * (d12 + 2.0 * d66) * al * al * be * be + d22 * be.powi(4);
        (k / (self.rho_h + self.inertia * (al * al + be * be))).sqrt()
            / (2.0 * std::f64::consts::PI)
    }
}

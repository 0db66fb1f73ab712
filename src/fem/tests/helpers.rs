//! Shared builders for the tests: plain plates and constrained eigen-solves.

use faer::linalg::solvers::Solve;
use faer::sparse::linalg::solvers::{Llt, SymbolicLlt};
use faer::Side;

use crate::fem::board::{Board, CoreMaterial, JointData, MeshOptions, ScanGrid};
use crate::fem::eigen::{shift_invert_lanczos, EigenOptions};
use crate::fem::model::{FeModel, Setup};
use crate::fem::sparse::Pattern;

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
        },
        copper: vec![],
        holes: vec![],
        joint: Some(JointData {
            clamp_diameter_m: 1e-3,
            k_con_n_per_m: 1e6,
            bolt_mass_kg: 0.0,
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
            if on_x_edge {
                fixed.push(d + 2);
            }
            if on_y_edge {
                fixed.push(d + 1);
            }
        }
    }
    fixed
}

pub fn build(board: &Board, setup: Setup, nx: usize, ny: usize) -> FeModel {
    FeModel::build(board, setup, &MeshOptions { nx, ny }).unwrap()
}

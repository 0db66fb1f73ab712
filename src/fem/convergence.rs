//! Discretization-error estimate of a mesh: the same board and parameters solved on the
//! mesh and on one twice as fine in each direction, and Richardson extrapolation
//! f_R = f_{h/2} + (f_{h/2} − f_h)/(2ᵖ − 1), error estimate |f_h − f_R| / f_R.
//!
//! The order assumed is p = 2, not the BFS element's O(h⁴): holes are exact cut cells,
//! joints exact annulus layers and copper is integrated exactly per piece, but a copper
//! edge is a jump in the bending stiffness, across which the exact curvature has a kink
//! no element captures unless its edges follow it. The mesh puts node lines on the
//! copper's axis-parallel edges where it can ([`super::grading::snap_to_interfaces`]);
//! slanted edges, Gerber layers and edges closer together than the elements stay inside
//! elements, and the frequencies then converge at a lower, board-dependent rate (on `data/boards/realistic.toml`, between ~1 and ~2.5
//! over 40 × 25 … 160 × 100). With p = 2 the estimate is 1.25 × the true error where the
//! convergence is O(h⁴) and optimistic where the order is below 2; it is an estimate,
//! not a bound, hence the default tolerance of `fe modes` well below the target.

use super::model::{FeModel, Setup};
use super::{Board, FemError, MeshOptions, Params};

/// The convergence target of `hbmu fe modes`: 0.05 % on the first modes.
pub const TARGET_REL_ERROR: f64 = 5e-4;

/// Largest mesh (elements, of the finer mesh of a pair) `hbmu fe modes` tries when
/// choosing the mesh: ~180 × 110 on an 8:5 board, ~80 k DOFs (measured: 170 × 106 bolted,
/// 2.7 GB peak for the whole `fe modes` run).
pub const MAX_CHOICE_ELEMENTS: usize = 20_000;

/// Default tolerance of the mesh choice of `hbmu fe modes`: 0.02 %, well below the
/// ~0.1 % scatter of measured frequencies and below the 0.05 % target, with
/// room for the estimate's optimism on coarse meshes (on the default board the 14 × 9
/// estimate was 0.036 % against a true 0.047 %).
pub const DEFAULT_MESH_TOL: f64 = 2e-4;

/// Convergence order assumed by the Richardson estimate (see the module doc).
const ORDER: i32 = 2;

/// Outcome of [`mesh_check`].
#[derive(Clone, Debug, serde::Serialize)]
pub struct MeshCheck {
    /// The mesh checked, `[nx, ny]`.
    pub mesh: [usize; 2],
    /// The finer mesh used for the estimate, `[2 nx, 2 ny]`.
    pub finer_mesh: [usize; 2],
    /// Frequencies on the mesh, Hz.
    pub freq_hz: Vec<f64>,
    /// Frequencies on the finer mesh, Hz.
    pub freq_finer_hz: Vec<f64>,
    /// Richardson-extrapolated frequencies, Hz.
    pub freq_richardson_hz: Vec<f64>,
    /// Estimated relative discretization error of each frequency on the mesh.
    pub rel_error: Vec<f64>,
    /// Largest of `rel_error`.
    pub max_rel_error: f64,
}

fn solve(
    board: &Board,
    setup: &Setup,
    p: &Params,
    m: &MeshOptions,
    n_modes: usize,
) -> Result<Vec<f64>, FemError> {
    let model = FeModel::build(board, setup.clone(), m)?;
    let mut q = model.nominal_params();
    for (name, v) in p.names.iter().zip(&p.values) {
        q.set(name, *v)?;
    }
    Ok(model.modes(&q, n_modes)?.freq_hz)
}

fn richardson(mesh: &MeshOptions, f_h: Vec<f64>, f_f: Vec<f64>) -> MeshCheck {
    let rich: Vec<f64> = f_h
        .iter()
        .zip(&f_f)
        .map(|(a, b)| b + (b - a) / (2f64.powi(ORDER) - 1.0))
        .collect();
    let rel_error: Vec<f64> = f_h
        .iter()
        .zip(&rich)
        .map(|(a, r)| (a - r).abs() / r)
        .collect();
    let max_rel_error = rel_error.iter().copied().fold(0.0, f64::max);
    MeshCheck {
        mesh: [mesh.nx, mesh.ny],
        finer_mesh: [2 * mesh.nx, 2 * mesh.ny],
        freq_hz: f_h,
        freq_finer_hz: f_f,
        freq_richardson_hz: rich,
        rel_error,
        max_rel_error,
    }
}

/// Estimate the discretization error of the first `n_modes` frequencies of `board` in
/// `setup` on `mesh`, at the parameter values of `p` (matched by name on the finer
/// model, whose parameter list is the same).
pub fn mesh_check(
    board: &Board,
    setup: &Setup,
    mesh: &MeshOptions,
    p: &Params,
    n_modes: usize,
) -> Result<MeshCheck, FemError> {
    let finer = MeshOptions {
        nx: 2 * mesh.nx,
        ny: 2 * mesh.ny,
    };
    let f_h = solve(board, setup, p, mesh, n_modes)?;
    let f_f = solve(board, setup, p, &finer, n_modes)?;
    Ok(richardson(mesh, f_h, f_f))
}

/// Outcome of [`mesh_spread`].
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct MeshSpread {
    /// The mesh of the model, `[nx, ny]`.
    pub mesh: [usize; 2],
    /// The finer meshes it was compared with, `[nx, ny]` each.
    pub finer_meshes: Vec<[usize; 2]>,
    /// Frequencies on the mesh, Hz.
    pub freq_hz: Vec<f64>,
    /// Per mode, the largest |f_mesh / f_finer − 1| over the finer meshes.
    pub rel_spread: Vec<f64>,
}

/// How far the first `n_modes` frequencies on `mesh` move against two finer meshes, the
/// √2 and the 2 × refinement: the scale of the model's discretization error as a
/// model-form uncertainty (the updating's model-error term, `bayes::target`).
///
/// Why not [`mesh_check`]'s Richardson estimate: that assumes a smooth h-expansion, true
/// for nested meshes (h, h/2) but not between meshes whose element edges fall differently
/// on copper edges and holes. On the built-in board at 40 × 25, before node lines were
/// put on the copper's edges, the nested estimate of the 4th mode was 0.002 % while the
/// 57 × 35 and 56 × 35 meshes sat 0.011 % away (measured with `hbmu fe modes`); a
/// non-nested mesh (√2) shows such jitter (from holes, slanted or Gerber copper edges),
/// the nested one (2 ×) the smooth part. Each mode is compared with the nearest frequency of the finer mesh, so a
/// pair of near-coincident modes that swaps order between meshes is not read as an error.
pub fn mesh_spread(
    board: &Board,
    setup: &Setup,
    mesh: &MeshOptions,
    p: &Params,
    n_modes: usize,
) -> Result<MeshSpread, FemError> {
    let s2 = std::f64::consts::SQRT_2;
    let finer = [
        MeshOptions {
            nx: (mesh.nx as f64 * s2).round() as usize,
            ny: (mesh.ny as f64 * s2).round() as usize,
        },
        MeshOptions {
            nx: 2 * mesh.nx,
            ny: 2 * mesh.ny,
        },
    ];
    let f_h = solve(board, setup, p, mesh, n_modes)?;
    let mut rel_spread = vec![0.0f64; f_h.len()];
    for m in &finer {
        // One more mode than needed, so the last mode has a neighbour to be matched with.
        let f_f = solve(board, setup, p, m, n_modes + 1)?;
        for (s, &f) in rel_spread.iter_mut().zip(&f_h) {
            let d = f_f
                .iter()
                .map(|&g| (f / g - 1.0).abs())
                .fold(f64::INFINITY, f64::min);
            *s = s.max(d);
        }
    }
    Ok(MeshSpread {
        mesh: [mesh.nx, mesh.ny],
        finer_meshes: finer.iter().map(|m| [m.nx, m.ny]).collect(),
        freq_hz: f_h,
        rel_spread,
    })
}

/// Outcome of [`choose_mesh`].
#[derive(Clone, Debug, serde::Serialize)]
pub struct MeshChoice {
    /// The tolerance on the estimated relative error of every frequency checked.
    pub tolerance: f64,
    /// Whether a mesh of the ladder met it (else the finest one tried is chosen).
    pub met: bool,
    /// The chosen mesh's check.
    pub chosen: MeshCheck,
    /// Estimated largest relative error of each mesh tried, coarse to fine.
    pub tried: Vec<([usize; 2], f64)>,
}

/// The ladder of candidate meshes: the board's mesh scaled by 2^((k − 4)/2), k = 0, 1,
/// … (k = 4 is the board's mesh; each rung √2 finer than the previous, so keeping the
/// board mesh's element shape), from the first rung with at least 4 elements each way.
pub fn mesh_ladder(board_mesh: &MeshOptions) -> impl Iterator<Item = MeshOptions> {
    // From the board's mesh up, even rungs are the board mesh doubled and odd rungs
    // the √2-scaled mesh doubled, so a pair's finer mesh is a later rung, solved once.
    let (nx0, ny0) = (board_mesh.nx as f64, board_mesh.ny as f64);
    let scaled = move |c: f64| MeshOptions {
        nx: (nx0 * c).round().max(1.0) as usize,
        ny: (ny0 * c).round().max(1.0) as usize,
    };
    let odd = scaled(std::f64::consts::SQRT_2);
    (0..24usize)
        .map(move |k| {
            if k < 4 {
                scaled(2f64.powf((k as f64 - 4.0) / 2.0))
            } else {
                let j = (k - 4) / 2;
                let m = if k % 2 == 0 { scaled(1.0) } else { odd.clone() };
                MeshOptions {
                    nx: m.nx << j,
                    ny: m.ny << j,
                }
            }
        })
        .skip_while(|m| m.nx < 4 || m.ny < 4)
}

/// Choose the coarsest mesh of [`mesh_ladder`] whose estimated discretization error
/// (Richardson from it and the mesh twice as fine, first `n_modes` frequencies) is
/// below `tolerance`, trying pairs whose finer mesh has at most `max_elements`
/// elements. Every mesh is solved once (the finer mesh of a pair is solved again by
/// no later pair).
pub fn choose_mesh(
    board: &Board,
    setup: &Setup,
    p: &Params,
    n_modes: usize,
    tolerance: f64,
    max_elements: usize,
) -> Result<MeshChoice, FemError> {
    let mut solved: Vec<((usize, usize), Vec<f64>)> = Vec::new();
    let mut get = |m: &MeshOptions| -> Result<Vec<f64>, FemError> {
        if let Some((_, f)) = solved.iter().find(|(k, _)| *k == (m.nx, m.ny)) {
            return Ok(f.clone());
        }
        let f = solve(board, setup, p, m, n_modes)?;
        solved.push(((m.nx, m.ny), f.clone()));
        Ok(f)
    };
    let mut tried = Vec::new();
    let mut last: Option<MeshCheck> = None;
    for m in mesh_ladder(&board.mesh) {
        let finer = MeshOptions {
            nx: 2 * m.nx,
            ny: 2 * m.ny,
        };
        if finer.nx * finer.ny > max_elements {
            break;
        }
        let c = richardson(&m, get(&m)?, get(&finer)?);
        tried.push((c.mesh, c.max_rel_error));
        if c.max_rel_error < tolerance {
            return Ok(MeshChoice {
                tolerance,
                met: true,
                chosen: c,
                tried,
            });
        }
        last = Some(c);
    }
    match last {
        Some(chosen) => Ok(MeshChoice {
            tolerance,
            met: false,
            chosen,
            tried,
        }),
        None => Err(FemError::Mesh(format!(
            "mesh choice: expected a pair of meshes from the ladder of {}x{} within {max_elements} elements, found none",
            board.mesh.nx, board.mesh.ny
        ))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// On a free square plate with a central hole (cut cells at every mesh) the estimate
    /// on a 12 × 12 mesh is within a factor of 2 of the true error (from a 48 × 48 mesh,
    /// itself within ~1e-5 of the independent scikit-fem reference, see verification).
    #[test]
    fn richardson_estimate_tracks_the_true_error() {
        let (a, h, e, nu, rho) = (0.2, 2e-3, 70e9, 0.3, 2700.0);
        let mut board =
            crate::fem::tests::helpers::plain_board(a, a, h, e, e, e / (2.0 * (1.0 + nu)), nu, rho);
        board.holes.push(crate::fem::board::Hole {
            x_m: 0.5 * a,
            y_m: 0.5 * a,
            diameter_m: 0.3 * a,
        });
        let model = FeModel::build(&board, Setup::Free, &MeshOptions { nx: 48, ny: 48 }).unwrap();
        let truth = model.modes(&model.nominal_params(), 5).unwrap().freq_hz;
        let p = model.nominal_params();
        let c = mesh_check(&board, &Setup::Free, &MeshOptions { nx: 12, ny: 12 }, &p, 5).unwrap();
        for j in 0..5 {
            let true_err = (c.freq_hz[j] - truth[j]).abs() / truth[j];
            assert!(
                c.rel_error[j] > 0.5 * true_err && c.rel_error[j] < 2.0 * true_err,
                "mode {j}: estimate {:.2e}, true {true_err:.2e}",
                c.rel_error[j]
            );
        }
    }

    /// The spread of the plate with a hole covers the true error of every mode (the nested
    /// 2 × mesh alone sees the smooth part; the √2 mesh the rest), and it is of the true
    /// error's order, not orders above it.
    #[test]
    fn mesh_spread_covers_the_true_error() {
        let (a, h, e, nu, rho) = (0.2, 2e-3, 70e9, 0.3, 2700.0);
        let mut board =
            crate::fem::tests::helpers::plain_board(a, a, h, e, e, e / (2.0 * (1.0 + nu)), nu, rho);
        board.holes.push(crate::fem::board::Hole {
            x_m: 0.43 * a,
            y_m: 0.57 * a,
            diameter_m: 0.3 * a,
        });
        let model = FeModel::build(&board, Setup::Free, &MeshOptions { nx: 48, ny: 48 }).unwrap();
        let truth = model.modes(&model.nominal_params(), 5).unwrap().freq_hz;
        let p = model.nominal_params();
        let s = mesh_spread(&board, &Setup::Free, &MeshOptions { nx: 10, ny: 10 }, &p, 5).unwrap();
        assert_eq!(s.finer_meshes, vec![[14, 14], [20, 20]]);
        for j in 0..5 {
            let true_err = (s.freq_hz[j] / truth[j] - 1.0).abs();
            assert!(
                s.rel_spread[j] > 0.5 * true_err && s.rel_spread[j] < 3.0 * true_err.max(1e-5),
                "mode {j}: spread {:.2e}, true {true_err:.2e}",
                s.rel_spread[j]
            );
        }
    }

    /// One mesh errs alike on boards a few per cent apart: the true discretization error
    /// (against a 4 × finer mesh) of an FR-4-like shear-deformable board with a hole, at the
    /// nominal moduli and thickness and at moduli 4 % apart (two sds of a lot's boards, the
    /// orthotropy ratio 8 % apart) and a core 2 % thicker. Over the first 7 modes the
    /// difference is under 0.15 × the error in rms, the two error vectors correlate above 0.95.
    /// (A pair of modes near veering exchanges part of its error: 1.57e-3 and 1.40e-3 on one
    /// board, 2.02e-3 and 1.09e-3 on the other.) Step 1 takes the mesh's error into the
    /// discrepancy common to the boards for this reason
    /// (`update::problem::ModelErrorPrior::common_to_boards`).
    #[test]
    fn one_meshs_error_is_nearly_the_same_on_boards_a_few_per_cent_apart() {
        use crate::fem::params::names;
        let mut board = crate::fem::tests::helpers::plain_board(
            0.16, 0.1, 1.5e-3, 24e9, 21e9, 4.5e9, 0.14, 1900.0,
        );
        board.core.g_xz_pa = Some(3e9);
        board.core.g_yz_pa = Some(3e9);
        board.holes.push(crate::fem::board::Hole {
            x_m: 0.043,
            y_m: 0.057,
            diameter_m: 0.012,
        });
        let (coarse, fine) = (
            MeshOptions { nx: 16, ny: 10 },
            MeshOptions { nx: 64, ny: 40 },
        );
        let err = |shift: &[(&str, f64)]| -> Vec<f64> {
            let mut b = board.clone();
            b.core.thickness_m *= shift
                .iter()
                .find(|(n, _)| *n == names::CORE_THICKNESS)
                .map_or(1.0, |s| s.1);
            let at = |mesh: &MeshOptions| {
                let model = FeModel::build(&b, Setup::Free, mesh).unwrap();
                let mut p = model.nominal_params();
                for (n, f) in shift.iter().filter(|(n, _)| *n != names::CORE_THICKNESS) {
                    let v = p.get(n).unwrap();
                    p.set(n, v * f).unwrap();
                }
                model.modes(&p, 7).unwrap().freq_hz
            };
            let (c, f) = (at(&coarse), at(&fine));
            c.iter().zip(&f).map(|(c, f)| c / f - 1.0).collect()
        };
        let a = err(&[]);
        let b = err(&[
            (names::E_X, 1.04),
            (names::E_Y, 0.96),
            (names::G_XY, 1.04),
            (names::CORE_THICKNESS, 1.02),
        ]);
        let rms = |v: &mut dyn Iterator<Item = f64>| {
            let (s, n) = v.fold((0.0, 0.0), |(s, n), x| (s + x * x, n + 1.0));
            (s / n).sqrt()
        };
        let (ra, rb) = (rms(&mut a.iter().copied()), rms(&mut b.iter().copied()));
        let rd = rms(&mut a.iter().zip(&b).map(|(a, b)| a - b));
        assert!(ra > 1e-4, "the coarse mesh's error is resolved: {a:?}");
        assert!(
            rd < 0.15 * ra,
            "difference {rd:.2e} rms, error {ra:.2e}: {a:?} {b:?}"
        );
        let corr = a.iter().zip(&b).map(|(a, b)| a * b).sum::<f64>() / (7.0 * ra * rb);
        assert!(corr > 0.95, "correlation {corr:.3}: {a:?} {b:?}");
    }

    /// The chosen mesh is the first rung whose estimate is below the tolerance, every
    /// coarser rung tried was above it, and its true error (against 48 × 48) is within
    /// twice the tolerance.
    #[test]
    fn choose_mesh_takes_the_coarsest_rung_below_the_tolerance() {
        let (a, h, e, nu, rho) = (0.2, 2e-3, 70e9, 0.3, 2700.0);
        let mut board =
            crate::fem::tests::helpers::plain_board(a, a, h, e, e, e / (2.0 * (1.0 + nu)), nu, rho);
        board.holes.push(crate::fem::board::Hole {
            x_m: 0.5 * a,
            y_m: 0.5 * a,
            diameter_m: 0.3 * a,
        });
        board.mesh = MeshOptions { nx: 12, ny: 12 };
        let ladder: Vec<[usize; 2]> = mesh_ladder(&board.mesh)
            .take(6)
            .map(|m| [m.nx, m.ny])
            .collect();
        assert_eq!(
            ladder,
            vec![[4, 4], [6, 6], [8, 8], [12, 12], [17, 17], [24, 24]]
        );
        let truth_model =
            FeModel::build(&board, Setup::Free, &MeshOptions { nx: 48, ny: 48 }).unwrap();
        let p = truth_model.nominal_params();
        let truth = truth_model.modes(&p, 5).unwrap().freq_hz;
        let tol = 2e-4;
        let c = choose_mesh(&board, &Setup::Free, &p, 5, tol, 5000).unwrap();
        assert!(c.met && c.chosen.max_rel_error < tol, "{:?}", c.tried);
        let n = c.tried.len();
        assert!(c.tried[..n - 1].iter().all(|t| t.1 >= tol), "{:?}", c.tried);
        assert_eq!(c.tried[n - 1].0, c.chosen.mesh);
        for j in 0..5 {
            let err = (c.chosen.freq_hz[j] / truth[j] - 1.0).abs();
            assert!(
                err < 2.0 * tol,
                "mode {j}: true error {err:.2e} on {:?}",
                c.chosen.mesh
            );
        }
    }
}

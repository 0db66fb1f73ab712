//! The full finite-element model: structured BFS mesh of the board with holes,
//! per-element laminate stiffness, the affine stiffness and mass terms on one shared
//! sparse pattern, the setups (free, bolted with a [`JointModel`]), and the queries the
//! rest of hbmu needs: modes, out-of-plane displacement at arbitrary points, the mass
//! matrix, the rigid z vector and lumped point masses.
//!
//! Mesh: `nx × ny` equal rectangles over the outline. Holes are cut cells: an
//! element's stiffness and mass are integrated over its material part only (the
//! element minus its intersection with each hole, by the polar cut-cell quadrature of
//! [`super::geometry`]), so results change smoothly with the mesh and a hole never
//! vanishes, whatever its size relative to the elements. Since the BFS space restricted
//! to the material is still conforming, the eigenvalues remain Rayleigh–Ritz upper
//! bounds. Elements with no material are dropped; nodes that belong to no remaining
//! element carry no DOF.
//!
//! Affine terms (stiffness): the FR-4 core's Q₁₁, Q₂₂, Q₁₂, Q₆₆ contributions
//! (D_core = Q h³/12), copper (∝ E_Cu), the coupling correction −B A⁻¹ B as an exact
//! expansion in Chebyshev nodes of the copper variable whose coefficients follow the
//! moduli (frozen at nominal only when copper layers differ in material; see
//! [`super::laminate`]), and the joint terms; (mass): the board (∝ `mass_scale`),
//! point masses (constant) and joint terms. A core with transverse shear moduli makes the
//! plate shear-deformable ([`super::mindlin`]: 6 DOFs a node), adding the transverse shear
//! (∝ `g_z_pa`) and the rotary inertia (∝ `mass_scale`) terms.

use std::sync::Arc;

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::sparse::linalg::cholesky::{factorize_symbolic_cholesky, LltRef, SymbolicCholesky};
use faer::{Conj, Mat, MatMut, Par, Side};

use super::board::{Board, MeshOptions, Side as LayerSide};
use super::copper::CopperMap;
use super::eigen::{self, EigenOptions};
use super::geometry::{
    annulus_convex_quadrature, annulus_rect_quadrature, polygon_quadrature, QPoint, Rect,
};
use super::joints::{joint_terms, Contact, JointModel, Patch, Which};
use super::laminate::{
    chebyshev_nodes, core_q_scale, coupling_correction, coupling_kernel, isotropic_q,
    lagrange_basis, layer_factors, orthotropic_q, transverse_shear_stiffness, Comp4, ShearLayer,
};
use super::mindlin::{element_matrices, ElementMatrices, Mat24, BFS_DOFS, DOFS};
use super::params::{names, Coef, Coefficients, ParamMap, Params};
use super::plate::{part_integrals, shape, NODE_IJ};
use super::sparse::Pattern;
use super::FemError;

/// Boundary conditions of the analysis.
#[derive(Clone, Debug, PartialEq)]
pub enum Setup {
    /// Free-free (on foam): three rigid-body modes.
    Free,
    /// Bolted to a rigid shaker fixture through the given joint model; fixed-base modes.
    Bolted(JointModel),
}

impl Setup {
    /// The paper's bolted setup (one K_con for all joints).
    pub fn bolted() -> Setup {
        Setup::Bolted(JointModel::baseline())
    }
}

/// Modes of the full model, ascending in frequency, rigid-body modes removed.
#[derive(Clone, Debug)]
pub struct Modes {
    /// Natural frequencies, Hz.
    pub freq_hz: Vec<f64>,
    /// Eigenvalues λ = ω², rad²/s².
    pub eigenvalues: Vec<f64>,
    /// Mass-normalised shapes (φᵀ M φ = 1, unit 1/√kg), one column per mode.
    pub shapes: Mat<f64>,
    /// Number of rigid-body modes found and dropped (3 for a free board, else 0).
    pub n_rigid_dropped: usize,
}

/// Interpolation operator from DOFs to out-of-plane displacement at given points:
/// w(x_m, y_m) = Σ N_k(x, y) u_k over the 16 DOFs of the element holding the point.
#[derive(Clone, Debug)]
pub struct ShapeOperator {
    /// Points, `[x_m, y_m]`.
    pub points_m: Vec<[f64; 2]>,
    /// Per point, 16 (DOF, weight) pairs.
    pub rows: Vec<[(usize, f64); 16]>,
}

impl ShapeOperator {
    /// w at the points for each column of `u` (n_dof × k) → (n_points × k).
    pub fn apply(&self, u: faer::MatRef<'_, f64>) -> Mat<f64> {
        Mat::from_fn(self.rows.len(), u.ncols(), |i, j| {
            self.rows[i].iter().map(|&(d, w)| w * u[(d, j)]).sum()
        })
    }
}

/// Elements with a smaller material fraction than this are dropped (see `FeModel::build`).
const MIN_MATERIAL_FRACTION: f64 = 1e-12;

/// Stiffness of the void part of a cut element relative to material (finite-cell
/// stabilisation): a node whose elements hold only slivers of material would otherwise
/// make K − σM singular to working precision. It only adds stiffness (eigenvalues rise
/// by at most ~1e-10 relative); the void carries no mass, so no spurious mode can live
/// in a hole.
const VOID_STIFFNESS: f64 = 1e-10;

/// Number of Chebyshev nodes in the copper variable s ∈ [0, s_max] for an
/// interpolation error of G(s) below ~1e-9 relative anywhere in a ±50 % box: G has its
/// pole at s = −h Q_core/(ε Q_cu), and the error of n-point interpolation falls like
/// ρ⁻ⁿ with ρ = |x| + √(x² − 1), x the pole mapped to [−1, 1].
fn coupling_nodes(q_core: &Comp4, h: f64, q_cu: &Comp4, s_max: f64) -> usize {
    // Pole of each block (normal: worst of the diagonal entries; shear), with the core
    // at half and copper at 1.5 × nominal.
    let pole = [0usize, 1, 3]
        .iter()
        .map(|&k| h * 0.5 * q_core[k] / (1.5 * q_cu[k]))
        .fold(f64::INFINITY, f64::min);
    let x = 1.0 + 2.0 * pole / s_max;
    let rho = x + (x * x - 1.0).sqrt();
    // Interpolation error ~ρ⁻ⁿ below 1e-9 of G; G is a few % of D, so D is exact to
    // ~1e-10 relative.
    ((9.0 / rho.log10()).ceil() as usize + 1).clamp(3, 16)
}

/// Quadrature of a cut element: its material part directly (one hole), or its void
/// parts to subtract from the whole element (several holes).
#[derive(Clone, Debug)]
enum CutCell {
    Material(Vec<QPoint>),
    Void(Vec<QPoint>),
}

/// Unit matrices of a cut element over its material part, plus `VOID_STIFFNESS` × the
/// stiffness of its void part.
fn cut_cell_matrices(
    full: &ElementMatrices,
    cc: &CutCell,
    mesh: &Mesh,
    ex: usize,
    ey: usize,
) -> ElementMatrices {
    let (x0, y0) = (mesh.x_m[ex], mesh.y_m[ey]);
    let (a, b) = mesh.size(ex, ey);
    let n = full.n;
    let mut m = match cc {
        CutCell::Material(pts) => {
            let mut m = ElementMatrices::zero(n);
            m.add_points(pts, x0, y0, a, b, 1.0);
            m
        }
        CutCell::Void(pts) => {
            let mut m = full.clone();
            m.add_points(pts, x0, y0, a, b, -1.0);
            m
        }
    };
    let stiff = m.k_bend.iter_mut().chain(m.k_shear.iter_mut());
    for (mk, fk) in stiff.zip(full.k_bend.iter().chain(&full.k_shear)) {
        for r in 0..n {
            for c in 0..n {
                mk[r][c] += VOID_STIFFNESS * (fk[r][c] - mk[r][c]);
            }
        }
    }
    m
}

/// A piece of an element with constant copper: the coverage of each layer, and its
/// unit matrices over the piece's material part (`None`: the whole element's).
struct Cell {
    coverage: Vec<f64>,
    matrices: Option<ElementMatrices>,
}

/// Laminate quantities of one copper state (see `FeModel::build`).
struct Stack {
    a: Comp4,
    b: Comp4,
    d_cu: Comp4,
    /// D_cu split by powers of the core thickness h, the factors h₀^k included: a layer at
    /// the surface (z from h/2 to h/2 + t) has (z₂³ − z₁³)/3 = h² t/4 + h t²/2 + t³/3.
    d_cu_pow: [Comp4; 3],
    rho_h_cu: f64,
    /// Copper's rotary inertia Σ f ρ (z₂³ − z₁³)/3, kg, and the same split by powers of h
    /// (as `d_cu_pow`).
    rho_i_cu: f64,
    rho_i_cu_pow: [f64; 3],
    s: f64,
    t: f64,
    /// t = h u + v: the coupling variable's parts, u = Σ ±f t_l/2 and v = Σ ±f t_l²/2.
    t_pow: [f64; 2],
}

/// What a model takes as parameters beyond the standard ones.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ModelOptions {
    /// The FR-4 core thickness as a parameter (`core_thickness_m`, nominal: the board
    /// file's), for specimens whose measured thickness differs: every term that depends on
    /// it is split into its powers of h (core bending h³; a surface copper layer's h², h,
    /// 1; the coupling correction's t² = (h u + v)²; the core's mass h), so the model
    /// stays affine and exact in h. Needs copper of one material, if any.
    pub core_thickness: bool,
}

/// Quadrature of the part of the convex piece `poly` outside every hole: directly
/// (rays from the centre outward) when one hole meets it, else the piece minus the
/// holes' parts.
fn piece_material_quadrature(poly: &[[f64; 2]], holes: &[super::board::Hole]) -> Vec<QPoint> {
    let mut voids: Vec<(usize, Vec<QPoint>)> = Vec::new();
    for (hi, h) in holes.iter().enumerate() {
        let q = annulus_convex_quadrature(h.x_m, h.y_m, 0.0, 0.5 * h.diameter_m, poly);
        if !q.is_empty() {
            voids.push((hi, q));
        }
    }
    match voids.len() {
        0 => polygon_quadrature(poly),
        1 => {
            let h = &holes[voids[0].0];
            let far = poly
                .iter()
                .map(|p| (p[0] - h.x_m).hypot(p[1] - h.y_m))
                .fold(0.0, f64::max)
                * 1.01;
            annulus_convex_quadrature(h.x_m, h.y_m, 0.5 * h.diameter_m, far, poly)
        }
        _ => {
            let mut pts = polygon_quadrature(poly);
            pts.extend(
                voids
                    .into_iter()
                    .flat_map(|v| v.1)
                    .map(|(x, y, w)| (x, y, -w)),
            );
            pts
        }
    }
}

/// Structured (tensor-product) mesh data: node lines x_0 < … < x_nx along x and
/// y_0 < … < y_ny along y, uniform or graded ([`super::grading`]).
#[derive(Clone, Debug)]
pub struct Mesh {
    /// Elements along x, y.
    pub nx: usize,
    pub ny: usize,
    /// Node lines along x (`nx + 1`) and y (`ny + 1`), m.
    pub x_m: Vec<f64>,
    pub y_m: Vec<f64>,
    /// Element sizes along x (`nx`) and y (`ny`), m: exactly L / n on a uniform mesh, so
    /// every element shares one set of unit matrices.
    pub hx_m: Vec<f64>,
    pub hy_m: Vec<f64>,
    /// Whether element `ey * nx + ex` is present.
    pub active: Vec<bool>,
    /// Fraction of element `ey * nx + ex` that is material (not hole), exact to
    /// quadrature accuracy (~1e-12).
    pub material_fraction: Vec<f64>,
    /// First DOF of node `j * (nx + 1) + i`, if the node carries DOFs: w, ∂w/∂x, ∂w/∂y,
    /// ∂²w/∂x∂y from there, then γx, γy on a shear-deformable plate.
    pub node_dof: Vec<Option<usize>>,
    /// DOFs per node: 4 (Kirchhoff) or 6 (shear-deformable).
    pub dofs_per_node: usize,
}

/// Refinement of a bolted board's mesh at its joints ([`super::grading`]): elements at a
/// joint are about `1 + JOINT_GRADING` times smaller than far from it. Measured on the
/// realistic board (`fem::tests::convergence`, first 7 bolted modes, 40 × 25 against
/// 160 × 100 at fixed K_con): uniform 0.145 %, A = 2 0.024 %, A = 4 0.025 %. At A = 3
/// one of the four meshes failed to factorise (a non-positive pivot of K − σM, cause not
/// yet found), so the refinement stays at the smallest value that does the job.
pub const JOINT_GRADING: f64 = 2.0;

/// Width of the refined zone round a joint, in clamp radii ([`super::grading`]).
pub const JOINT_GRADING_WIDTH: f64 = 1.0;

/// Refinement of a shear-deformable board's mesh at its edges ([`super::grading`]). A free
/// edge of a Mindlin plate carries a boundary layer of the twisting moment and shear force,
/// decaying over δ = h √(G_xy / (10 G_z)) (h/√10 when isotropic), that the bilinear shear
/// strains resolve at O(h²) only: measured on the plain 80 × 50 × 2 mm plate of
/// `fem::tests::shear` (G_z 1 GPa, δ 1.2 mm) at 56 × 35 against the Ritz reference, the
/// eight lowest modes were up to 1666 ppm off on the uniform mesh, 221 ppm with
/// A = 3 over 2δ, 54 ppm with A = 15 over 2δ (narrower zones or larger A did no better).
pub const EDGE_GRADING: f64 = 15.0;

/// Width of the refined zone at an edge, in boundary-layer lengths δ.
pub const EDGE_GRADING_WIDTH: f64 = 2.0;

/// Refinement of a shear-deformable free board's mesh at its holes ([`super::grading`]): a
/// hole's rim is a free edge too, with the same boundary layer, but cut through elements
/// (cut cells) rather than followed by them, so it converges slower still. Measured on the
/// built-in board with G_xz = G_yz = 3 GPa (δ 0.67 mm, holes Ø 2.7 mm), free-free, first 8
/// modes at 56 × 35 against 160 × 100 on the same grading: uniform at the holes 1149 ppm;
/// over r + 2δ, A = 3: 395, A = 5: 343, A = 8: 293, A = 15: 425 ppm (A = 8 over r + δ: 333,
/// over r + 4δ: 322). Against the ungraded 160 × 100 the order is the same (A = 8: 215 ppm).
/// The rest converges between O(h) and O(h^1.5) (56 × 35 and 80 × 50 against 160 × 100:
/// 293 and 153 ppm), the rim's cut cells. The width follows the physics (the hole and its
/// boundary layer); the amplitude is a discretisation choice, the best of those five on this
/// one board. Bolted, the clamp holds the rim and the joints' own grading applies.
pub const HOLE_GRADING: f64 = 8.0;

/// The decay length δ (m) of a shear-deformable board's edge boundary layer, or `None` for
/// a Kirchhoff board (see [`EDGE_GRADING`]); the softer of the two transverse shear moduli.
pub fn shear_boundary_layer_m(board: &Board) -> Option<f64> {
    let c = &board.core;
    let (gxz, gyz) = c.transverse_shear()?;
    Some(c.thickness_m * (c.g_xy_pa / (10.0 * gxz.min(gyz))).sqrt())
}

impl Mesh {
    /// The node lines (x, y) of `nx × ny` elements for `board` in `setup`: uniform for a free
    /// board; for a bolted one graded towards the joints (the holes' centres), where the
    /// field varies on the scale of the clamp: a small stiff support is resolved by the
    /// mesh's total element count rather than by a uniformly finer mesh (see
    /// `fem::tests::convergence`). A shear-deformable board's are also graded towards its
    /// edges ([`EDGE_GRADING`]) and, free, its holes ([`HOLE_GRADING`]). The map does not
    /// depend on nx, ny: meshes n ⊂ 2n stay nested. Then the lines nearest the copper's
    /// edges move onto them
    /// ([`super::grading::snap_to_interfaces`]), so no stiffness jump lies inside an
    /// element where a line can take it.
    pub fn lines(board: &Board, setup: &Setup, nx: usize, ny: usize) -> (Vec<f64>, Vec<f64>) {
        let (lx, ly) = (board.length_x_m, board.width_y_m);
        let cx: Vec<f64> = board.holes.iter().map(|h| h.x_m).collect();
        let cy: Vec<f64> = board.holes.iter().map(|h| h.y_m).collect();
        let (mut bx, mut by) = match setup {
            Setup::Bolted(_) => {
                let w = JOINT_GRADING_WIDTH * 0.5 * board.joint().clamp_diameter_m;
                (
                    super::grading::merged_bumps(&cx, w, JOINT_GRADING),
                    super::grading::merged_bumps(&cy, w, JOINT_GRADING),
                )
            }
            Setup::Free => (vec![], vec![]),
        };
        if let Some(delta) = shear_boundary_layer_m(board) {
            let w = EDGE_GRADING_WIDTH * delta;
            bx.extend(super::grading::merged_bumps(&[0.0, lx], w, EDGE_GRADING));
            by.extend(super::grading::merged_bumps(&[0.0, ly], w, EDGE_GRADING));
            if matches!(setup, Setup::Free) {
                let r = board
                    .holes
                    .iter()
                    .map(|h| 0.5 * h.diameter_m)
                    .fold(0.0, f64::max);
                bx.extend(super::grading::merged_bumps(&cx, r + w, HOLE_GRADING));
                by.extend(super::grading::merged_bumps(&cy, r + w, HOLE_GRADING));
            }
        }
        let (x_m, y_m) = (
            super::grading::graded_lines(lx, nx, &bx),
            super::grading::graded_lines(ly, ny, &by),
        );
        let (at_x, at_y) = board.copper_interfaces();
        (
            super::grading::snap_to_interfaces(&x_m, &at_x),
            super::grading::snap_to_interfaces(&y_m, &at_y),
        )
    }

    /// A mesh skeleton (element data left empty) on node lines over an `lx × ly` board.
    fn from_lines(x_m: Vec<f64>, y_m: Vec<f64>, lx: f64, ly: f64) -> Mesh {
        let sizes = |l: &[f64], len: f64| -> Vec<f64> {
            let n = l.len() - 1;
            if l == super::grading::uniform_lines(len, n).as_slice() {
                vec![len / n as f64; n]
            } else {
                l.windows(2).map(|p| p[1] - p[0]).collect()
            }
        };
        Mesh {
            nx: x_m.len() - 1,
            ny: y_m.len() - 1,
            hx_m: sizes(&x_m, lx),
            hy_m: sizes(&y_m, ly),
            x_m,
            y_m,
            active: vec![],
            material_fraction: vec![],
            node_dof: vec![],
            dofs_per_node: 4,
        }
    }

    /// Element (ex, ey) as a rectangle, m.
    pub fn rect(&self, ex: usize, ey: usize) -> Rect {
        Rect {
            x0: self.x_m[ex],
            y0: self.y_m[ey],
            x1: self.x_m[ex + 1],
            y1: self.y_m[ey + 1],
        }
    }

    /// Size (a, b) of element (ex, ey), m.
    pub fn size(&self, ex: usize, ey: usize) -> (f64, f64) {
        (self.hx_m[ex], self.hy_m[ey])
    }

    /// Coordinates of node `n = j * (nx + 1) + i`, m.
    pub fn node_xy(&self, n: usize) -> (f64, f64) {
        (self.x_m[n % (self.nx + 1)], self.y_m[n / (self.nx + 1)])
    }

    /// Whether all elements have one size (one set of unit matrices serves them all).
    pub fn is_uniform(&self) -> bool {
        self.hx_m.iter().all(|h| *h == self.hx_m[0]) && self.hy_m.iter().all(|h| *h == self.hy_m[0])
    }

    /// The element that contains (x, y) (clamped to the mesh).
    pub fn element_at(&self, x_m: f64, y_m: f64) -> (usize, usize) {
        (
            super::grading::element_of(&self.x_m, x_m),
            super::grading::element_of(&self.y_m, y_m),
        )
    }

    fn element_nodes(&self, ex: usize, ey: usize) -> [usize; 4] {
        NODE_IJ.map(|(i, j)| (ey + j) * (self.nx + 1) + ex + i)
    }

    /// DOFs per element: 16 (BFS) or 24 (shear-deformable, [`super::mindlin`]).
    pub fn element_dof_count(&self) -> usize {
        if self.dofs_per_node == 6 {
            DOFS
        } else {
            BFS_DOFS
        }
    }

    /// DOFs of element (ex, ey) in the element's order ([`super::mindlin`]: the BFS's 16,
    /// then γx and γy at the four nodes; only the first [`Self::element_dof_count`] are
    /// meaningful), if all nodes carry DOFs.
    fn element_dofs(&self, ex: usize, ey: usize) -> Option<[usize; DOFS]> {
        let nodes = self.element_nodes(ex, ey);
        let mut d = [0usize; DOFS];
        for (k, n) in nodes.iter().enumerate() {
            let base = self.node_dof[*n]?;
            for c in 0..4 {
                d[4 * k + c] = base + c;
            }
            if self.dofs_per_node == 6 {
                d[16 + k] = base + 4;
                d[20 + k] = base + 5;
            }
        }
        Some(d)
    }
}

/// The assembled full model.
#[derive(Clone, Debug)]
pub struct FeModel {
    /// The board it was built from.
    pub board: Board,
    /// Its setup.
    pub setup: Setup,
    /// The mesh.
    pub mesh: Mesh,
    /// Number of DOFs (board DOFs plus the fixture DOF if any).
    pub n_dof: usize,
    /// Index of the fixture DOF, if any.
    pub fixture_dof: Option<usize>,
    /// The board's in-plane rigid motion `[u, v, φ]` (m, m, rad about z at the frame's
    /// origin), when bolted joints hold it through tangential springs
    /// ([`super::joints::Contact`]). Its mass is the board's own, in-plane.
    pub inplane_dofs: Option<[usize; 3]>,
    /// Parameter names, nominal values and coefficient map.
    pub map: ParamMap,
    /// Human-readable name of each stiffness / mass term.
    pub k_term_names: Vec<String>,
    pub m_term_names: Vec<String>,
    /// Joint patches: the w-DOFs of the nodes of every element each joint's clamped
    /// annulus covers (the joint acts through all of them, weighted by the shape
    /// functions over the annulus).
    pub patches: Vec<Vec<usize>>,
    pub(crate) pattern: Pattern,
    pub(crate) k_terms: Vec<Vec<f64>>,
    /// Per stiffness term, the runs of its value array that hold its nonzeros
    /// ([`Pattern::nonzero_runs`]): a joint's or a copper region's term stores the whole
    /// pattern, mostly zeros, and K(p) is formed for every full solve and every candidate
    /// point of the ROM's adaptive design.
    k_runs: Vec<Vec<(usize, usize)>>,
    pub(crate) m_terms: Vec<Vec<f64>>,
    symbolic: Arc<SymbolicCholesky<usize>>,
}

/// The unit element matrices of a mesh's elements: computed once on a uniform mesh, per
/// element on a graded one (a graded 160 × 100 mesh would hold 160 MB of them; computing
/// one takes ~10 µs).
struct UnitMatrices<'m> {
    mesh: &'m Mesh,
    /// DOFs per element.
    n: usize,
    uniform: Option<ElementMatrices>,
}

impl<'m> UnitMatrices<'m> {
    fn new(mesh: &'m Mesh) -> Self {
        let n = mesh.element_dof_count();
        let uniform = mesh
            .is_uniform()
            .then(|| element_matrices(mesh.hx_m[0], mesh.hy_m[0], n));
        UnitMatrices { mesh, n, uniform }
    }

    fn get(&self, ex: usize, ey: usize) -> std::borrow::Cow<'_, ElementMatrices> {
        match &self.uniform {
            Some(em) => std::borrow::Cow::Borrowed(em),
            None => {
                let (a, b) = self.mesh.size(ex, ey);
                std::borrow::Cow::Owned(element_matrices(a, b, self.n))
            }
        }
    }
}

/// A numeric sparse Cholesky factor of K − σM, computed and applied with `Par::Seq`
/// so that results do not depend on the thread count (faer's high-level solvers use
/// its global parallelism setting).
pub(crate) struct SeqLlt<'a> {
    symbolic: &'a SymbolicCholesky<usize>,
    values: Vec<f64>,
}

impl SeqLlt<'_> {
    /// rhs ← (K − σM)⁻¹ rhs.
    pub(crate) fn solve_in_place(&self, rhs: MatMut<'_, f64>) {
        let req = self
            .symbolic
            .solve_in_place_scratch::<f64>(rhs.ncols(), Par::Seq);
        let mut buf = MemBuffer::new(req);
        LltRef::new(self.symbolic, &self.values).solve_in_place_with_conj(
            Conj::No,
            rhs,
            Par::Seq,
            MemStack::new(&mut buf),
        );
    }
}

struct TermBuilder {
    names: Vec<String>,
    coefs: Vec<Coef>,
    trip: Vec<Vec<(usize, usize, f64)>>,
}

impl TermBuilder {
    fn new() -> Self {
        TermBuilder {
            names: vec![],
            coefs: vec![],
            trip: vec![],
        }
    }
    fn push(&mut self, name: &str, coef: Coef, trip: Vec<(usize, usize, f64)>) {
        self.names.push(name.to_string());
        self.coefs.push(coef);
        self.trip.push(trip);
    }

    /// Terms with the same coefficient merged into one (names joined by `+`), in order of
    /// first appearance: the model is affine, so the sum is exact. Why: the shear-deformable
    /// plate's rotary inertia scales with `mass_scale` as the board's mass does, and as two
    /// terms they made M(p) look like a pencil of two matrices, so every ROM evaluation
    /// whitened it by a Cholesky factor (`fem::rom`), where one term is M(p) ∝ M₀.
    fn merged(self) -> Self {
        let mut out = TermBuilder::new();
        for ((name, coef), trip) in self.names.into_iter().zip(self.coefs).zip(self.trip) {
            match out.coefs.iter().position(|c| *c == coef) {
                Some(i) => {
                    out.names[i] = format!("{}+{name}", out.names[i]);
                    out.trip[i].extend(trip);
                }
                None => out.push(&name, coef, trip),
            }
        }
        out
    }
}

/// Triplets of one term: (row, column, value).
type Triplets = Vec<(usize, usize, f64)>;

/// Checks that `x_m` and `y_m` are node lines of `board`: at least 2 elements each way,
/// strictly increasing from 0 to the board's length (width).
fn check_node_lines(board: &Board, x_m: &[f64], y_m: &[f64]) -> Result<(), FemError> {
    for (axis, l, len) in [("x", x_m, board.length_x_m), ("y", y_m, board.width_y_m)] {
        let tol = 1e-9 * len;
        if l.len() < 3
            || l[0] != 0.0
            || (l[l.len() - 1] - len).abs() > tol
            || l.windows(2).any(|p| !(p[1] > p[0]))
        {
            let bad = l.windows(2).position(|p| !(p[1] > p[0]));
            return Err(FemError::Mesh(format!(
                "expected at least 2 elements along {axis}: node lines strictly increasing from 0 to {len} m, found {} lines from {:?} to {:?}{}",
                l.len(),
                l.first(),
                l.last(),
                bad.map_or(String::new(), |i| format!(", not increasing at line {}", i + 1))
            )));
        }
    }
    Ok(())
}

/// Per element: whether it keeps material, its material fraction, and its cut-cell
/// quadrature when a hole cuts it.
struct CutCells {
    active: Vec<bool>,
    material_fraction: Vec<f64>,
    cut_points: Vec<Option<CutCell>>,
}

/// The cut cells of `board`'s holes on the `nx × ny` mesh `mesh`.
fn cut_cells(board: &Board, mesh: &Mesh, nx: usize, ny: usize) -> CutCells {
    // Cut cells: per element, the quadrature points of its part inside each hole
    // (holes do not overlap, see `Board::validate`), and its material fraction.
    // An element with (almost) no material is dropped; below 1e-12 of its area the
    // material it would carry changes no frequency by more than rounding, while its
    // DOFs would make K − σM singular to working precision.
    let mut active = vec![true; nx * ny];
    let mut material_fraction = vec![1.0; nx * ny];
    let mut cut_points: Vec<Option<CutCell>> = vec![None; nx * ny];
    for ey in 0..ny {
        for ex in 0..nx {
            let e = ey * nx + ex;
            let rect = mesh.rect(ex, ey);
            let mut voids: Vec<(usize, Vec<QPoint>)> = Vec::new();
            for (hi, h) in board.holes.iter().enumerate() {
                let q = annulus_rect_quadrature(h.x_m, h.y_m, 0.0, 0.5 * h.diameter_m, &rect);
                if !q.is_empty() {
                    voids.push((hi, q));
                }
            }
            if voids.is_empty() {
                continue;
            }
            let void: f64 = voids.iter().flat_map(|v| &v.1).map(|q| q.2).sum();
            material_fraction[e] = (1.0 - void / rect.area()).clamp(0.0, 1.0);
            // An element whose four corners lie in one hole lies in it whole (a disc
            // is convex): decided exactly, since 1 − void/area leaves ~1e-11 of
            // rounding there, which once kept such an element and its DOFs.
            let inside = |h: &super::board::Hole| {
                let r2 = (0.5 * h.diameter_m).powi(2);
                [rect.x0, rect.x1].iter().all(|x| {
                    [rect.y0, rect.y1]
                        .iter()
                        .all(|y| (x - h.x_m).powi(2) + (y - h.y_m).powi(2) <= r2)
                })
            };
            if board.holes.iter().any(inside) {
                material_fraction[e] = 0.0;
            }
            if material_fraction[e] < MIN_MATERIAL_FRACTION {
                active[e] = false;
                continue;
            }
            cut_points[e] = Some(if voids.len() == 1 {
                // Integrate the material part directly (rays from the hole centre,
                // from its radius to the far side of the element): no cancellation
                // when little material is left.
                let h = &board.holes[voids[0].0];
                let far = (rect.x1 - rect.x0).hypot(rect.y1 - rect.y0)
                    + (h.x_m - rect.x0).abs()
                    + (h.y_m - rect.y0).abs();
                CutCell::Material(annulus_rect_quadrature(
                    h.x_m,
                    h.y_m,
                    0.5 * h.diameter_m,
                    far,
                    &rect,
                ))
            } else {
                CutCell::Void(voids.into_iter().flat_map(|v| v.1).collect())
            });
        }
    }
    CutCells {
        active,
        material_fraction,
        cut_points,
    }
}

/// Per node, its first DOF (`per_node` per node; `None`: the node is in no active
/// element), and the number of DOFs.
fn number_dofs(
    active: &[bool],
    nx: usize,
    ny: usize,
    per_node: usize,
) -> (Vec<Option<usize>>, usize) {
    let n_nodes = (nx + 1) * (ny + 1);
    let mut used = vec![false; n_nodes];
    for ey in 0..ny {
        for ex in 0..nx {
            if active[ey * nx + ex] {
                for (i, j) in NODE_IJ {
                    used[(ey + j) * (nx + 1) + ex + i] = true;
                }
            }
        }
    }
    let mut node_dof = vec![None; n_nodes];
    let mut n_dof = 0;
    for (n, u) in used.iter().enumerate() {
        if *u {
            node_dof[n] = Some(n_dof);
            n_dof += per_node;
        }
    }
    (node_dof, n_dof)
}

/// The plate's parameters (the core's moduli, the copper's modulus, the mass scale, and
/// the core thickness when `core_thickness`) with their nominal values, the mass scale's
/// index and the core thickness's.
fn plate_params(
    board: &Board,
    core_thickness: bool,
) -> (Vec<String>, Vec<f64>, usize, Option<usize>) {
    let c = &board.core;
    let mut pnames: Vec<String> = [names::E_X, names::E_Y, names::G_XY, names::NU_XY]
        .iter()
        .map(|s| s.to_string())
        .collect();
    let mut nominal = vec![c.e_x_pa, c.e_y_pa, c.g_xy_pa, c.nu_xy];
    if !board.copper.is_empty() {
        pnames.push(names::E_CU.into());
        nominal.push(board.copper[0].e_pa);
    }
    pnames.push(names::MASS_SCALE.into());
    nominal.push(1.0);
    let i_mass = pnames.len() - 1;
    // The core thickness's index, when it is a parameter.
    let i_h = core_thickness.then(|| {
        pnames.push(names::CORE_THICKNESS.into());
        nominal.push(c.thickness_m);
        pnames.len() - 1
    });
    (pnames, nominal, i_mass, i_h)
}

/// `base` times (h/h₀)^`power` when the core thickness h is parameter `i_h`, else `base`.
fn thickness_power(i_h: Option<usize>, nominal_m: f64, base: Coef, power: i32) -> Coef {
    match i_h {
        Some(param) => Coef::ThicknessPower {
            base: Box::new(base),
            param,
            nominal_m,
            power,
        },
        None => base,
    }
}

/// Appends Σ_k comp_k K[k] of the element with DOFs `dofs` to `t`.
fn add_components(t: &mut Triplets, em: &ElementMatrices, dofs: &[usize; DOFS], comp: Comp4) {
    let n = em.n;
    for r in 0..n {
        for cc in 0..n {
            let v: f64 = (0..4).map(|k| comp[k] * em.k_bend[k][r][cc]).sum::<f64>();
            t.push((dofs[r], dofs[cc], v));
        }
    }
}

/// Appends the leading `n × n` block of the element matrix `m` with DOFs `dofs` to `t`.
fn push_block(t: &mut Triplets, dofs: &[usize; DOFS], m: &Mat24, n: usize) {
    for r in 0..n {
        for cc in 0..n {
            t.push((dofs[r], dofs[cc], m[r][cc]));
        }
    }
}

/// dst += s × src on the leading `n × n` block.
fn add_scaled(dst: &mut Mat24, s: f64, src: &Mat24, n: usize) {
    if s == 0.0 {
        return;
    }
    for r in 0..n {
        for cc in 0..n {
            dst[r][cc] += s * src[r][cc];
        }
    }
}

/// Σ over cells of Σ_k comp_k(cell) K_cell[k].
fn combine(cells: &[Cell], eme: &ElementMatrices, f: &dyn Fn(&Cell) -> Comp4) -> Mat24 {
    let mut out = [[0.0; DOFS]; DOFS];
    for cell in cells {
        let m = cell.matrices.as_ref().unwrap_or(eme);
        let comp = f(cell);
        for k in 0..4 {
            add_scaled(&mut out, comp[k], &m.k_bend[k], eme.n);
        }
    }
    out
}

/// The BFS (w) DOFs among an element's DOFs.
fn bfs_dofs(d: &[usize; DOFS]) -> [usize; BFS_DOFS] {
    std::array::from_fn(|i| d[i])
}

/// What the element loop and the coupling expansion share: the board on its mesh with
/// its cut cells and copper, and the core's laminate data.
struct Plate<'a> {
    board: &'a Board,
    mesh: &'a Mesh,
    cut_points: &'a [Option<CutCell>],
    units: UnitMatrices<'a>,
    copper: CopperMap,
    /// The core's nominal Q.
    q_core: Comp4,
    /// The core's A factor (its thickness).
    a_core: f64,
    /// The core's thickness, m.
    h: f64,
    /// The core's transverse shear moduli (G_xz, G_yz), Pa, when the plate is
    /// shear-deformable.
    g_z: Option<(f64, f64)>,
}

/// The element loop's triplets, per term.
#[derive(Default)]
struct PlateTriplets {
    core: [Triplets; 4],
    cu: Triplets,
    cu_pow: [Triplets; 3],
    corr: Triplets,
    mass: Triplets,
    mass_core: Triplets,
    any_corr: bool,
    /// Shear-deformable plates: transverse shear (S per piece), rotary inertia (core and
    /// copper together; with the thickness a parameter, the core's ∝ h³ and copper's split
    /// by powers of h).
    shear: Triplets,
    rot: Triplets,
    rot_core: Triplets,
    rot_cu_pow: [Triplets; 3],
}

impl Plate<'_> {
    /// The pieces of constant copper of element (ex, ey).
    fn cells_of(&self, ex: usize, ey: usize) -> Vec<Cell> {
        // Copper is integrated exactly: each element is split into convex pieces of
        // constant coverage (see `fem::copper`), each piece integrated over its
        // material part (holes cut out) by the polygon / polar cut-cell quadrature.
        let nx = self.mesh.nx;
        let rect = self.mesh.rect(ex, ey);
        let (a, b) = self.mesh.size(ex, ey);
        let mut pieces = self.copper.pieces(&rect);
        if pieces.len() == 1 {
            let coverage = pieces.pop().map(|p| p.coverage).unwrap_or_default();
            return vec![Cell {
                coverage,
                matrices: None,
            }];
        }
        pieces
            .into_iter()
            .map(|p| {
                let mut m = ElementMatrices::zero(self.units.n);
                let pts = if self.cut_points[ey * nx + ex].is_some() {
                    piece_material_quadrature(&p.polygon, &self.board.holes)
                } else {
                    polygon_quadrature(&p.polygon)
                };
                m.add_points(&pts, rect.x0, rect.y0, a, b, 1.0);
                Cell {
                    coverage: p.coverage,
                    matrices: Some(m),
                }
            })
            .collect()
    }

    /// Per copper state: D_cu, ρh of copper, A and B of the stack, and the two copper
    /// variables s, t of the coupling expansion.
    fn stack(&self, cov: &[f64]) -> Stack {
        let h = self.h;
        let mut st = Stack {
            a: self.q_core.map(|q| q * self.a_core),
            b: [0.0; 4],
            d_cu: [0.0; 4],
            d_cu_pow: [[0.0; 4]; 3],
            rho_h_cu: 0.0,
            rho_i_cu: 0.0,
            rho_i_cu_pow: [0.0; 3],
            s: 0.0,
            t: 0.0,
            t_pow: [0.0; 2],
        };
        for (l, frac) in self.board.copper.iter().zip(cov) {
            if *frac == 0.0 {
                continue;
            }
            let (z1, z2) = match l.side {
                LayerSide::Top => (h / 2.0, h / 2.0 + l.thickness_m),
                LayerSide::Bottom => (-h / 2.0 - l.thickness_m, -h / 2.0),
            };
            let (fa, fb, fd) = layer_factors(z1, z2);
            let q = isotropic_q(l.e_pa, l.nu);
            let tl = l.thickness_m;
            let fd_pow = [tl.powi(3) / 3.0, h * tl * tl / 2.0, h * h * tl / 4.0];
            let sign = if fb < 0.0 { -1.0 } else { 1.0 };
            for k in 0..4 {
                st.a[k] += frac * q[k] * fa;
                st.b[k] += frac * q[k] * fb;
                st.d_cu[k] += frac * q[k] * fd;
                for (pw, f) in fd_pow.iter().enumerate() {
                    st.d_cu_pow[pw][k] += frac * q[k] * f;
                }
            }
            st.rho_h_cu += frac * l.density_kg_per_m3 * l.thickness_m;
            st.rho_i_cu += frac * l.density_kg_per_m3 * fd;
            for (pw, f) in fd_pow.iter().enumerate() {
                st.rho_i_cu_pow[pw] += frac * l.density_kg_per_m3 * f;
            }
            st.s += frac * fa;
            st.t += frac * fb;
            st.t_pow[0] += sign * frac * tl / 2.0;
            st.t_pow[1] += sign * frac * tl * tl / 2.0;
        }
        st
    }

    /// The transverse shear stiffnesses (S_x, S_y), N/m, of a piece with copper coverage
    /// `cov`, the core's moduli being `(g_xz, g_yz)`: each layer's coverage splits the piece
    /// into the stacks with and without it, side by side (their S in parallel, weighted by
    /// area, the layers' coverages taken as independent), and each stack's S is Whitney's
    /// ([`transverse_shear_stiffness`]). It does not follow the moduli parameters: the
    /// in-plane moduli move S only through the shape of the shear-stress profile, a
    /// second-order effect on the frequencies the shear itself changes by a few per cent.
    fn shear_stiffness(&self, cov: &[f64], (g_xz, g_yz): (f64, f64)) -> [f64; 2] {
        let h = self.h;
        let layers: Vec<(&super::board::CopperLayer, f64)> = self
            .board
            .copper
            .iter()
            .zip(cov)
            .filter(|(_, f)| **f > 0.0)
            .map(|(l, f)| (l, *f))
            .collect();
        let mut out = [0.0; 2];
        for config in 0..(1usize << layers.len()) {
            let mut weight = 1.0;
            for (bit, (_, f)) in layers.iter().enumerate() {
                weight *= if config >> bit & 1 == 1 { *f } else { 1.0 - f };
            }
            if weight == 0.0 {
                continue;
            }
            for (axis, g_core) in [g_xz, g_yz].into_iter().enumerate() {
                let mut stack = vec![ShearLayer {
                    z1_m: -h / 2.0,
                    z2_m: h / 2.0,
                    q_pa: self.q_core[axis],
                    g_z_pa: g_core,
                }];
                for (bit, (l, _)) in layers.iter().enumerate() {
                    if config >> bit & 1 == 1 {
                        let (z1_m, z2_m) = match l.side {
                            LayerSide::Top => (h / 2.0, h / 2.0 + l.thickness_m),
                            LayerSide::Bottom => (-h / 2.0 - l.thickness_m, -h / 2.0),
                        };
                        stack.push(ShearLayer {
                            z1_m,
                            z2_m,
                            q_pa: isotropic_q(l.e_pa, l.nu)[axis],
                            g_z_pa: l.e_pa / (2.0 * (1.0 + l.nu)),
                        });
                    }
                }
                out[axis] += weight * transverse_shear_stiffness(&stack);
            }
        }
        out
    }

    /// The element matrices of (ex, ey) over its material part only.
    fn material_matrices(&self, ex: usize, ey: usize) -> std::borrow::Cow<'_, ElementMatrices> {
        let nx = self.mesh.nx;
        let em = self.units.get(ex, ey);
        match &self.cut_points[ey * nx + ex] {
            None => em,
            Some(cc) => std::borrow::Cow::Owned(cut_cell_matrices(&em, cc, self.mesh, ex, ey)),
        }
    }

    /// The plate's triplets of every active element (core per Q component, copper, the
    /// frozen coupling correction, mass), and the elements with B ≠ 0 somewhere (for the
    /// exact coupling expansion, when `uniform_cu`). With `thickness`, copper and the
    /// core's mass are split by powers of the core thickness.
    fn element_triplets(
        &self,
        thickness: bool,
        uniform_cu: bool,
        q_core_scale: Comp4,
        d_core: f64,
    ) -> (PlateTriplets, Vec<(usize, usize)>) {
        let mesh = self.mesh;
        let (nx, ny) = (mesh.nx, mesh.ny);
        let has_cu = !self.board.copper.is_empty();
        let mut t = PlateTriplets::default();
        // Elements with B ≠ 0 somewhere, for the exact expansion.
        let mut coupled: Vec<(usize, usize)> = Vec::new();
        for ey in 0..ny {
            for ex in 0..nx {
                if !mesh.active[ey * nx + ex] {
                    continue;
                }
                let Some(dofs) = mesh.element_dofs(ex, ey) else {
                    unreachable!("active element without DOFs")
                };
                // The element's matrices over its material part only.
                let em = self.material_matrices(ex, ey);
                let eme = &*em;
                // Core: one term per Q component, assembled at the nominal Q (or, where a
                // component is zero there, at the scale its coefficient divides by).
                for k in 0..4 {
                    let mut unit = [0.0; 4];
                    unit[k] = q_core_scale[k] * d_core;
                    add_components(&mut t.core[k], eme, &dofs, unit);
                }
                let cells = self.cells_of(ex, ey);
                let n = eme.n;
                if has_cu && thickness {
                    for (pw, tp) in t.cu_pow.iter_mut().enumerate() {
                        let k_cu = combine(&cells, eme, &|c| self.stack(&c.coverage).d_cu_pow[pw]);
                        push_block(tp, &dofs, &k_cu, n);
                    }
                } else if has_cu {
                    let k_cu = combine(&cells, eme, &|c| self.stack(&c.coverage).d_cu);
                    push_block(&mut t.cu, &dofs, &k_cu, n);
                }
                if uniform_cu {
                    if cells.iter().any(|c| self.stack(&c.coverage).t != 0.0) {
                        coupled.push((ex, ey));
                    }
                } else {
                    let corr = combine(&cells, eme, &|c| {
                        let st = self.stack(&c.coverage);
                        coupling_correction(st.a, st.b)
                    });
                    if corr.iter().flatten().any(|v| *v != 0.0) {
                        t.any_corr = true;
                        push_block(&mut t.corr, &dofs, &corr, n);
                    }
                }
                let z = [[0.0; DOFS]; DOFS];
                let (mut mass, mut shear, mut rot) = (z, z, z);
                let mut rot_cu_pow = [z; 3];
                let rho_core_h = self.board.core.density_kg_per_m3 * self.h;
                let rho_core_i = rho_core_h * self.h * self.h / 12.0;
                for cell in &cells {
                    let cm = cell.matrices.as_ref().unwrap_or(eme);
                    let st = self.stack(&cell.coverage);
                    add_scaled(&mut mass, st.rho_h_cu, &cm.m_trans, n);
                    if let Some(g_z) = self.g_z {
                        let [s_x, s_y] = self.shear_stiffness(&cell.coverage, g_z);
                        add_scaled(&mut shear, s_x, &cm.k_shear[0], n);
                        add_scaled(&mut shear, s_y, &cm.k_shear[1], n);
                        if thickness {
                            for (pw, r) in rot_cu_pow.iter_mut().enumerate() {
                                add_scaled(r, st.rho_i_cu_pow[pw], &cm.m_rot, n);
                            }
                        } else {
                            add_scaled(&mut rot, st.rho_i_cu, &cm.m_rot, n);
                        }
                    }
                }
                if thickness {
                    // The core's mass in a term of its own (∝ h), its rotary inertia too (∝ h³).
                    let mut core = z;
                    add_scaled(&mut core, rho_core_h, &eme.m_trans, n);
                    push_block(&mut t.mass_core, &dofs, &core, n);
                } else {
                    add_scaled(&mut mass, rho_core_h, &eme.m_trans, n);
                }
                push_block(&mut t.mass, &dofs, &mass, n);
                if self.g_z.is_some() {
                    push_block(&mut t.shear, &dofs, &shear, n);
                    if thickness {
                        let mut core = z;
                        add_scaled(&mut core, rho_core_i, &eme.m_rot, n);
                        push_block(&mut t.rot_core, &dofs, &core, n);
                        for (tp, r) in t.rot_cu_pow.iter_mut().zip(&rot_cu_pow) {
                            push_block(tp, &dofs, r, n);
                        }
                    } else {
                        add_scaled(&mut rot, rho_core_i, &eme.m_rot, n);
                        push_block(&mut t.rot, &dofs, &rot, n);
                    }
                }
            }
        }
        (t, coupled)
    }

    /// The exact coupling expansion's terms over the elements `coupled` (copper of modulus
    /// `e_cu0` and Q `q_cu`, its modulus parameter `i_cu`): names, coefficients and values
    /// on `pattern`.
    fn coupling_terms(
        &self,
        coupled: &[(usize, usize)],
        pattern: &Pattern,
        (e_cu0, q_cu): (f64, Comp4),
        i_cu: usize,
        i_h: Option<usize>,
        h_pow: &dyn Fn(Coef, i32) -> Coef,
    ) -> (Vec<String>, Vec<Coef>, Vec<Vec<f64>>) {
        let mut names = Vec::new();
        let mut coefs = Vec::new();
        let s_max = self.board.copper_thickness_m();
        let nodes = chebyshev_nodes(coupling_nodes(&self.q_core, self.h, &q_cu, s_max), s_max);
        let (scales, vals) = self.coupling_values(coupled, pattern, &nodes, q_cu, i_h.is_some());
        let n_pow: usize = if i_h.is_some() { 3 } else { 1 };
        for pw in 0..n_pow {
            for (k, sk) in nodes.iter().enumerate() {
                for comp in 0..4 {
                    let coupling = Coef::Coupling {
                        s_node_m: *sk,
                        comp,
                        scale: scales[k][comp],
                        h_core_m: self.h,
                        q_cu_pa: q_cu,
                        e_cu_param: i_cu,
                        e_cu_nominal_pa: e_cu0,
                        h_param: i_h,
                    };
                    names.push(match i_h {
                        Some(_) => format!("coupling_s{k}_c{comp}_h{pw}"),
                        None => format!("coupling_s{k}_c{comp}"),
                    });
                    coefs.push(h_pow(coupling, pw as i32));
                }
            }
        }
        (names, coefs, vals)
    }

    /// The exact coupling expansion's values on `pattern` over the elements `coupled`, one
    /// per power of h (one power without the thickness parameter), Chebyshev node and Q
    /// component, and the components' scales per node.
    fn coupling_values(
        &self,
        coupled: &[(usize, usize)],
        pattern: &Pattern,
        nodes: &[f64],
        q_cu: Comp4,
        thickness: bool,
    ) -> (Vec<[f64; 4]>, Vec<Vec<f64>>) {
        let h = self.h;
        // With the thickness a parameter, t² = h² u² + 2 h u v + v²: one set of terms
        // per power of h (highest last), each with its h₀ factors.
        let n_pow = if thickness { 3 } else { 1 };
        let n_set = 4 * nodes.len();
        let mut vals = vec![vec![0.0; pattern.row_idx.len()]; n_pow * n_set];
        let scales: Vec<[f64; 4]> = nodes
            .iter()
            .map(|sk| {
                coupling_kernel(self.q_core, h, q_cu, 1.0, *sk).0.map(|g| {
                    if g != 0.0 {
                        g
                    } else {
                        1.0
                    }
                })
            })
            .collect();
        for &(ex, ey) in coupled {
            let em = self.material_matrices(ex, ey);
            let eme = &*em;
            let Some(dofs) = self.mesh.element_dofs(ex, ey) else {
                unreachable!("active element without DOFs")
            };
            let nd = eme.n;
            let idx: Vec<usize> = (0..nd * nd)
                .map(|q| pattern.index(dofs[q / nd], dofs[q % nd]))
                .collect();
            for cell in self.cells_of(ex, ey) {
                let st = self.stack(&cell.coverage);
                if st.t == 0.0 {
                    continue;
                }
                let m = cell.matrices.as_ref().unwrap_or(eme);
                let l = lagrange_basis(nodes, st.s);
                let t2: Vec<f64> = if thickness {
                    let (hu, v) = (h * st.t_pow[0], st.t_pow[1]);
                    vec![v * v, 2.0 * hu * v, hu * hu]
                } else {
                    vec![st.t * st.t]
                };
                for (pw, t2) in t2.iter().enumerate() {
                    for (k, lk) in l.iter().enumerate() {
                        for comp in 0..4 {
                            let w = -t2 * lk * scales[k][comp];
                            let v = &mut vals[pw * n_set + 4 * k + comp];
                            for (q, &iq) in idx.iter().enumerate() {
                                v[iq] += w * m.k_bend[comp][q / nd][q % nd];
                            }
                        }
                    }
                }
            }
        }
        (scales, vals)
    }
}

impl PlateTriplets {
    /// The plate's stiffness and mass terms, named and with their coefficients (`i_mass`:
    /// the mass scale's index; `i_h`: the core thickness's, when a parameter; `i_gz`: the
    /// transverse shear modulus's and its nominal value, on a shear-deformable plate).
    fn push_terms(
        self,
        kb: &mut TermBuilder,
        mb: &mut TermBuilder,
        board: &Board,
        (i_mass, i_h, i_gz): (usize, Option<usize>, Option<(usize, f64)>),
        h_pow: &dyn Fn(Coef, i32) -> Coef,
    ) {
        let has_cu = !board.copper.is_empty();
        let core_names = ["core_q11", "core_q22", "core_q12", "core_q66"];
        for (k, t) in self.core.into_iter().enumerate() {
            kb.push(core_names[k], h_pow(Coef::CoreQ { comp: k }, 3), t);
        }
        if has_cu && i_h.is_some() {
            let scale = board.copper[0].e_pa;
            for (pw, t) in self.cu_pow.into_iter().enumerate() {
                let coef = h_pow(Coef::Linear { param: 4, scale }, pw as i32);
                kb.push(&format!("copper_h{pw}"), coef, t);
            }
        } else if has_cu {
            let scale = board.copper[0].e_pa;
            kb.push("copper", Coef::Linear { param: 4, scale }, self.cu);
        }
        if self.any_corr {
            kb.push("coupling_correction", Coef::Const, self.corr);
        }
        // Without copper, a thickness parameter leaves the core's mass term alone.
        if i_h.is_none() || has_cu {
            mb.push(
                "board_mass",
                Coef::Linear {
                    param: i_mass,
                    scale: 1.0,
                },
                self.mass,
            );
        }
        if i_h.is_some() {
            let coef = Coef::Linear {
                param: i_mass,
                scale: 1.0,
            };
            mb.push("core_mass", h_pow(coef, 1), self.mass_core);
        }
        let Some((param, scale)) = i_gz else {
            return;
        };
        // Transverse shear: S ∝ G_xz h to first order (the core carries the shear).
        let coef = h_pow(Coef::Linear { param, scale }, 1);
        kb.push("transverse_shear", coef, self.shear);
        let mass = Coef::Linear {
            param: i_mass,
            scale: 1.0,
        };
        if i_h.is_some() {
            mb.push("rotary_inertia_core", h_pow(mass.clone(), 3), self.rot_core);
            if has_cu {
                for (pw, t) in self.rot_cu_pow.into_iter().enumerate() {
                    let name = format!("rotary_inertia_copper_h{pw}");
                    mb.push(&name, h_pow(mass.clone(), pw as i32), t);
                }
            }
        } else {
            mb.push("rotary_inertia", mass, self.rot);
        }
    }
}

/// Per hole of a bolted board, the DOFs of w in its clamped annulus and its patch (the
/// annulus's area and per-element integrals).
fn joint_patches(board: &Board, mesh: &Mesh) -> Result<(Vec<Vec<usize>>, Vec<Patch>), FemError> {
    let (nx, ny) = (mesh.nx, mesh.ny);
    let r_clamp = 0.5 * board.joint().clamp_diameter_m;
    let mut patches = Vec::new();
    let mut jpatches = Vec::new();
    for (hi, hole) in board.holes.iter().enumerate() {
        let r_hole = 0.5 * hole.diameter_m;
        let mut parts = Vec::new();
        let mut w_dofs = Vec::new();
        for ey in 0..ny {
            for ex in 0..nx {
                if !mesh.active[ey * nx + ex] {
                    continue;
                }
                let rect = mesh.rect(ex, ey);
                let (a, b) = mesh.size(ex, ey);
                let pts = annulus_rect_quadrature(hole.x_m, hole.y_m, r_hole, r_clamp, &rect);
                if pts.is_empty() {
                    continue;
                }
                let Some(dofs) = mesh.element_dofs(ex, ey) else {
                    unreachable!("active element without DOFs")
                };
                let pi = part_integrals(&pts, rect.x0, rect.y0, a, b);
                for k in 0..4 {
                    w_dofs.push(dofs[4 * k]);
                }
                parts.push((bfs_dofs(&dofs), pi));
            }
        }
        let area_m2: f64 = parts.iter().map(|(_, p)| p.area_m2).sum();
        if !(area_m2 > 0.0) {
            return Err(FemError::Mesh(format!(
                "hole {hi} at ({}, {}) m: expected a clamped annulus of positive area between the hole radius {r_hole} m and the clamp radius {r_clamp} m, found none",
                hole.x_m, hole.y_m
            )));
        }
        w_dofs.sort_unstable();
        w_dofs.dedup();
        patches.push(w_dofs);
        jpatches.push(Patch { area_m2, parts });
    }
    Ok((patches, jpatches))
}

/// The deflection fields w = 1, w = x and w = y as DOF vectors (exact in the Hermite
/// element: w, w_x at every node), whose quadratic forms in a mass term give that mass's
/// in-plane rigid inertia: an in-plane motion (u − φ y, v + φ x) has the kinetic energy of
/// the same mass moving out of plane. (The rotary inertia adds I × area to the w = x form,
/// (h/L)²/12 of it, negligible.)
struct RigidFields {
    one: Vec<f64>,
    x: Vec<f64>,
    y: Vec<f64>,
}

impl RigidFields {
    fn new(mesh: &Mesh, n_dof: usize) -> RigidFields {
        let (mut one, mut x, mut y) = (vec![0.0; n_dof], vec![0.0; n_dof], vec![0.0; n_dof]);
        for (n, d) in mesh.node_dof.iter().enumerate() {
            if let Some(d) = *d {
                let (xn, yn) = mesh.node_xy(n);
                one[d] = 1.0;
                (x[d], x[d + 1]) = (xn, 1.0);
                (y[d], y[d + 2]) = (yn, 1.0);
            }
        }
        RigidFields { one, x, y }
    }

    /// The in-plane inertia triplets `[u, v, φ]` of the mass term `t`.
    fn inplane_mass(
        &self,
        t: &[(usize, usize, f64)],
        [u, v, phi]: [usize; 3],
    ) -> Vec<(usize, usize, f64)> {
        let form =
            |a: &[f64], b: &[f64]| -> f64 { t.iter().map(|&(r, c, m)| a[r] * m * b[c]).sum() };
        let m = form(&self.one, &self.one);
        let (mx, my) = (form(&self.one, &self.x), form(&self.one, &self.y));
        let j = form(&self.x, &self.x) + form(&self.y, &self.y);
        if m == 0.0 && j == 0.0 {
            return Vec::new();
        }
        inplane_inertia([u, v, phi], m, [mx, my], j)
    }
}

/// The in-plane inertia triplets on `[u, v, φ]` (φ about the frame's z axis) of a mass `m`
/// (kg) with first moments `[∫x dm, ∫y dm]` and polar moment `j` about the origin: the
/// kinetic energy of the motion (u − φ y, v + φ x).
fn inplane_inertia(
    [u, v, phi]: [usize; 3],
    m: f64,
    [mx, my]: [f64; 2],
    j: f64,
) -> Vec<(usize, usize, f64)> {
    vec![
        (u, u, m),
        (v, v, m),
        (phi, phi, j),
        (u, phi, -my),
        (phi, u, -my),
        (v, phi, mx),
        (phi, v, mx),
    ]
}

/// Adds the joint terms `terms` to the stiffness (`kb`) or mass (`mb`) terms, each joint
/// parameter appended to `pnames` and `nominal` when first seen.
fn push_joint_terms(
    terms: Vec<super::joints::JointTerm>,
    pnames: &mut Vec<String>,
    nominal: &mut Vec<f64>,
    kb: &mut TermBuilder,
    mb: &mut TermBuilder,
    h_pow: &dyn Fn(Coef, i32) -> Coef,
) {
    for t in terms {
        let param = match pnames.iter().position(|n| *n == t.param) {
            Some(i) => i,
            None => {
                pnames.push(t.param.clone());
                nominal.push(t.nominal);
                pnames.len() - 1
            }
        };
        let coef = Coef::Linear {
            param,
            scale: t.scale,
        };
        let coef = if t.h_power == 0 {
            coef
        } else {
            h_pow(coef, t.h_power)
        };
        match t.which {
            Which::K => kb.push(&t.param, coef, t.triplets),
            Which::M => mb.push(&t.param, coef, t.triplets),
        }
    }
}

impl FeModel {
    /// Build the model of `board` in `setup` on the mesh `mesh`.
    /// Free boards get a uniform mesh, bolted ones a mesh graded towards the joints
    /// ([`JOINT_GRADING`]).
    pub fn build(board: &Board, setup: Setup, mesh: &MeshOptions) -> Result<FeModel, FemError> {
        Self::build_with(board, setup, mesh, ModelOptions::default())
    }

    /// [`Self::build`] with the parameters `opts` adds.
    pub fn build_with(
        board: &Board,
        setup: Setup,
        mesh: &MeshOptions,
        opts: ModelOptions,
    ) -> Result<FeModel, FemError> {
        if mesh.nx < 2 || mesh.ny < 2 {
            return Err(FemError::Mesh(format!(
                "expected at least 2 × 2 elements, found {} × {}",
                mesh.nx, mesh.ny
            )));
        }
        let (x_m, y_m) = Mesh::lines(board, &setup, mesh.nx, mesh.ny);
        Self::build_on_lines_with(board, setup, x_m, y_m, opts)
    }

    /// Build the model of `board` in `setup` on the tensor-product mesh with node lines
    /// `x_m` (0 … length) and `y_m` (0 … width), m, each strictly increasing: e.g. a free
    /// board on a bolted model's graded mesh, or a bolted board on a uniform one.
    pub fn build_on_lines(
        board: &Board,
        setup: Setup,
        x_m: Vec<f64>,
        y_m: Vec<f64>,
    ) -> Result<FeModel, FemError> {
        Self::build_on_lines_with(board, setup, x_m, y_m, ModelOptions::default())
    }

    /// [`Self::build_on_lines`] with the parameters `opts` adds.
    pub fn build_on_lines_with(
        board: &Board,
        setup: Setup,
        x_m: Vec<f64>,
        y_m: Vec<f64>,
        opts: ModelOptions,
    ) -> Result<FeModel, FemError> {
        board.validate()?;
        check_node_lines(board, &x_m, &y_m)?;
        if let Setup::Bolted(j) = &setup {
            j.validate()?;
            if board.holes.is_empty() {
                return Err(FemError::BoardInvalid(
                    "bolted setup: expected at least one hole, found none".into(),
                ));
            }
        }
        let (nx, ny) = (x_m.len() - 1, y_m.len() - 1);
        let mut mesh_data = Mesh::from_lines(x_m, y_m, board.length_x_m, board.width_y_m);
        let cuts = cut_cells(board, &mesh_data, nx, ny);
        let g_z = board.core.transverse_shear();
        mesh_data.dofs_per_node = if g_z.is_some() { 6 } else { 4 };
        let (node_dof, mut n_dof) = number_dofs(&cuts.active, nx, ny, mesh_data.dofs_per_node);
        mesh_data.active = cuts.active;
        mesh_data.material_fraction = cuts.material_fraction;
        mesh_data.node_dof = node_dof;
        let mesh_data = mesh_data;
        let cut_points = cuts.cut_points;

        // Parameters.
        let c = &board.core;
        let (mut pnames, mut nominal, i_mass, i_h) = plate_params(board, opts.core_thickness);
        // A shear-deformable board's transverse shear modulus (its term ∝ G_xz: the copper's
        // share of Whitney's S is a few per cent, at the faces where the shear is small).
        let i_gz = board.core.transverse_shear().map(|(gxz, _)| {
            pnames.push(names::G_Z.into());
            nominal.push(gxz);
            (pnames.len() - 1, gxz)
        });
        let has_cu = !board.copper.is_empty();
        // A term's coefficient times (h/h₀)^power where h is a parameter.
        let h_pow = |base: Coef, power: i32| thickness_power(i_h, c.thickness_m, base, power);

        // Per-element laminate data.
        let h = c.thickness_m;
        let q_core = orthotropic_q(c.e_x_pa, c.e_y_pa, c.g_xy_pa, c.nu_xy);
        let q_core_scale = core_q_scale(q_core);
        let (a_core, _, d_core) = layer_factors(-h / 2.0, h / 2.0);
        // Exact coupling expansion when all copper is one material (see `laminate`).
        let uniform_cu = board
            .copper
            .first()
            .filter(|l0| {
                board
                    .copper
                    .iter()
                    .all(|l| l.e_pa == l0.e_pa && l.nu == l0.nu)
            })
            .map(|l0| (l0.e_pa, isotropic_q(l0.e_pa, l0.nu)));
        if i_h.is_some() && has_cu && uniform_cu.is_none() {
            return Err(FemError::Param(format!(
                "{}: the core thickness as a parameter needs every copper layer of one material (the exact coupling expansion), found layers of different moduli",
                names::CORE_THICKNESS
            )));
        }
        let plate = Plate {
            board,
            mesh: &mesh_data,
            cut_points: &cut_points,
            units: UnitMatrices::new(&mesh_data),
            copper: CopperMap::new(board),
            q_core,
            a_core,
            h,
            g_z,
        };
        let mut kb = TermBuilder::new();
        let mut mb = TermBuilder::new();
        let (trips, coupled) =
            plate.element_triplets(i_h.is_some(), uniform_cu.is_some(), q_core_scale, d_core);
        trips.push_terms(&mut kb, &mut mb, board, (i_mass, i_h, i_gz), &h_pow);

        // Joints.
        let mut patches = Vec::new();
        let mut fixture_dof = None;
        let mut inplane_dofs = None;
        if let Setup::Bolted(jm) = &setup {
            let jpatches;
            (patches, jpatches) = joint_patches(board, &mesh_data)?;
            if jm.has_fixture() {
                fixture_dof = Some(n_dof);
                n_dof += 1;
            }
            if board.joint().tangential_over_normal > 0.0 {
                inplane_dofs = Some([n_dof, n_dof + 1, n_dof + 2]);
                n_dof += 3;
            }
            let contact = Contact::of_board(board, i_h.is_some(), inplane_dofs);
            let terms = joint_terms(jm, &jpatches, fixture_dof, contact);
            push_joint_terms(terms, &mut pnames, &mut nominal, &mut kb, &mut mb, &h_pow);
            if let Some(ip) = inplane_dofs {
                let rigid = RigidFields::new(&mesh_data, n_dof);
                for t in &mut mb.trip {
                    let extra = rigid.inplane_mass(t, ip);
                    t.extend(extra);
                }
            }
        }

        let mb = mb.merged();
        // Shared pattern: all element blocks plus joint entries.
        let pattern = Pattern::from_entries(
            n_dof,
            kb.trip
                .iter()
                .chain(mb.trip.iter())
                .flat_map(|t| t.iter().map(|&(r, c, _)| (r, c))),
        );
        let scatter = |trips: &[Vec<(usize, usize, f64)>]| -> Vec<Vec<f64>> {
            trips
                .iter()
                .map(|t| {
                    let mut v = vec![0.0; pattern.row_idx.len()];
                    for &(r, c, x) in t {
                        v[pattern.index(r, c)] += x;
                    }
                    v
                })
                .collect()
        };
        let mut k_terms = scatter(&kb.trip);
        let m_terms = scatter(&mb.trip);
        if let (Some((e_cu0, q_cu)), false) = (uniform_cu, coupled.is_empty()) {
            let i_cu = pnames
                .iter()
                .position(|n| n == names::E_CU)
                .unwrap_or_else(|| unreachable!("copper without e_cu_pa"));
            let (names, coefs, vals) =
                plate.coupling_terms(&coupled, &pattern, (e_cu0, q_cu), i_cu, i_h, &h_pow);
            kb.names.extend(names);
            kb.coefs.extend(coefs);
            k_terms.extend(vals);
        }
        let symbolic = factorize_symbolic_cholesky(
            pattern.symbolic.as_ref(),
            Side::Lower,
            Default::default(),
            Default::default(),
        )
        .map_err(|e| FemError::Factorisation(format!("symbolic analysis: {e:?}")))?;
        let symbolic = Arc::new(symbolic);
        let map = ParamMap {
            names: pnames,
            nominal,
            k_coefs: kb.coefs,
            m_coefs: mb.coefs,
            core_idx: [0, 1, 2, 3],
        };
        Ok(FeModel {
            board: board.clone(),
            setup,
            mesh: mesh_data,
            n_dof,
            fixture_dof,
            inplane_dofs,
            map,
            k_term_names: kb.names,
            m_term_names: mb.names,
            patches,
            k_runs: k_terms.iter().map(|t| Pattern::nonzero_runs(t)).collect(),
            pattern,
            k_terms,
            m_terms,
            symbolic,
        })
    }

    /// BLAKE3 of everything a computation on this model reads: the setup, the DOF layout, the
    /// parameter map, the sparse pattern, every stiffness and mass term and the joint
    /// patches, the mesh lines and the board. Two models with the same hash give the same
    /// bytes from any deterministic computation on them (a reduced model, a mesh study):
    /// the key under which the model cache keeps those (`io::cache`).
    pub fn content_blake3(&self) -> String {
        let mut h = blake3::Hasher::new();
        let words = |h: &mut blake3::Hasher, v: &[usize]| {
            h.update(&(v.len() as u64).to_le_bytes());
            for x in v {
                h.update(&(*x as u64).to_le_bytes());
            }
        };
        let floats = |h: &mut blake3::Hasher, v: &[f64]| {
            h.update(&(v.len() as u64).to_le_bytes());
            for x in v {
                h.update(&x.to_bits().to_le_bytes());
            }
        };
        // Debug of these plain structs prints every f64 in its shortest round-trip form and
        // holds no hash map: a deterministic, complete text.
        h.update(format!("{:?}\0{:?}\0{:?}\0", self.setup, self.board, self.map).as_bytes());
        h.update(
            format!(
                "{:?}\0{}\0{:?}\0{:?}\0",
                self.mesh, self.n_dof, self.fixture_dof, self.inplane_dofs
            )
            .as_bytes(),
        );
        words(
            &mut h,
            &[
                self.pattern.n,
                self.k_terms.len(),
                self.m_terms.len(),
                self.patches.len(),
            ],
        );
        words(&mut h, &self.pattern.col_ptr);
        words(&mut h, &self.pattern.row_idx);
        for t in self.k_terms.iter().chain(&self.m_terms) {
            floats(&mut h, t);
        }
        for p in &self.patches {
            words(&mut h, p);
        }
        h.finalize().to_hex().to_string()
    }

    /// The nominal parameters of this model (from the board).
    pub fn nominal_params(&self) -> Params {
        self.map.nominal_params()
    }

    /// Coefficients (and their gradients) at `p`.
    pub fn coefficients(&self, p: &Params) -> Result<Coefficients, FemError> {
        self.map.coefficients(p)
    }

    /// Values of K(p) on the shared pattern.
    pub(crate) fn k_values(&self, coefs: &[f64]) -> Vec<f64> {
        self.pattern
            .combine_runs(coefs, &self.k_terms, &self.k_runs)
    }

    /// Values of M(p) on the shared pattern.
    pub(crate) fn m_values(&self, coefs: &[f64]) -> Vec<f64> {
        self.pattern.combine(coefs, &self.m_terms)
    }

    /// y = K(p) x.
    pub fn stiffness_apply(&self, p: &Params, x: &[f64]) -> Result<Vec<f64>, FemError> {
        let c = self.coefficients(p)?;
        self.check_len(x)?;
        let mut y = vec![0.0; self.n_dof];
        self.pattern.matvec(&self.k_values(&c.k), x, &mut y);
        Ok(y)
    }

    /// y = M(p) x (kg-consistent; the mass matrix for participation factors).
    pub fn mass_apply(&self, p: &Params, x: &[f64]) -> Result<Vec<f64>, FemError> {
        let c = self.coefficients(p)?;
        self.check_len(x)?;
        let mut y = vec![0.0; self.n_dof];
        self.pattern.matvec(&self.m_values(&c.m), x, &mut y);
        Ok(y)
    }

    /// M(p) as (row, col, value) triplets, both triangles.
    pub fn mass_triplets(&self, p: &Params) -> Result<Vec<(usize, usize, f64)>, FemError> {
        let c = self.coefficients(p)?;
        Ok(self.triplets(&self.m_values(&c.m)))
    }

    /// K(p) as (row, col, value) triplets, both triangles.
    pub fn stiffness_triplets(&self, p: &Params) -> Result<Vec<(usize, usize, f64)>, FemError> {
        let c = self.coefficients(p)?;
        Ok(self.triplets(&self.k_values(&c.k)))
    }

    fn triplets(&self, val: &[f64]) -> Vec<(usize, usize, f64)> {
        let mut t = Vec::with_capacity(val.len());
        for c in 0..self.n_dof {
            for q in self.pattern.col_ptr[c]..self.pattern.col_ptr[c + 1] {
                t.push((self.pattern.row_idx[q], c, val[q]));
            }
        }
        t
    }

    fn check_len(&self, x: &[f64]) -> Result<(), FemError> {
        if x.len() != self.n_dof {
            return Err(FemError::Request(format!(
                "vector length: expected {} DOFs, found {}",
                self.n_dof,
                x.len()
            )));
        }
        Ok(())
    }

    /// Rigid-body z-translation vector r: w = 1 at every node (and the fixture DOF),
    /// slopes 0. The participation of mode φ in a base motion along z is Γ = φᵀ M r.
    pub fn rigid_z_vector(&self) -> Vec<f64> {
        let mut r = vec![0.0; self.n_dof];
        for d in self.mesh.node_dof.iter().flatten() {
            r[*d] = 1.0;
        }
        if let Some(f) = self.fixture_dof {
            r[f] = 1.0;
        }
        r
    }

    /// Modal participation factors Γᵢ = φᵢᵀ M r (√kg) of `modes` for base motion in z.
    pub fn participation_z(&self, p: &Params, modes: &Modes) -> Result<Vec<f64>, FemError> {
        let mr = self.mass_apply(p, &self.rigid_z_vector())?;
        Ok((0..modes.shapes.ncols())
            .map(|j| (0..self.n_dof).map(|i| modes.shapes[(i, j)] * mr[i]).sum())
            .collect())
    }

    /// Total mass rᵀ M r, kg (board, point masses, joint and fixture masses).
    pub fn total_mass_kg(&self, p: &Params) -> Result<f64, FemError> {
        let r = self.rigid_z_vector();
        let mr = self.mass_apply(p, &r)?;
        Ok(r.iter().zip(&mr).map(|(a, b)| a * b).sum())
    }

    /// Add a lumped mass `mass_kg` at (x_m, y_m), consistent with the element shape
    /// functions (M += m N Nᵀ). It enters a constant mass term.
    pub fn add_point_mass(&mut self, x_m: f64, y_m: f64, mass_kg: f64) -> Result<(), FemError> {
        if !(mass_kg.is_finite() && mass_kg >= 0.0) {
            return Err(FemError::Param(format!(
                "point mass: expected a finite non-negative mass in kg, found {mass_kg}"
            )));
        }
        let row = self.interp_row(x_m, y_m)?;
        let idx = match self.m_term_names.iter().position(|n| n == "point_masses") {
            Some(i) => i,
            None => {
                self.m_term_names.push("point_masses".into());
                self.map.m_coefs.push(Coef::Const);
                self.m_terms.push(vec![0.0; self.pattern.row_idx.len()]);
                self.m_terms.len() - 1
            }
        };
        for &(r, wr) in &row {
            for &(c, wc) in &row {
                let q = self.pattern.index(r, c);
                self.m_terms[idx][q] += mass_kg * wr * wc;
            }
        }
        for (r, c, m) in self.inplane_point_mass(x_m, y_m, mass_kg) {
            let q = self.pattern.index(r, c);
            self.m_terms[idx][q] += m;
        }
        Ok(())
    }

    /// The in-plane inertia entries of a point mass `mass_kg` at (x_m, y_m) moving with the
    /// board's in-plane rigid motion (none when the model has none).
    fn inplane_point_mass(&self, x_m: f64, y_m: f64, mass_kg: f64) -> Vec<(usize, usize, f64)> {
        let Some(dofs) = self.inplane_dofs else {
            return Vec::new();
        };
        let m = mass_kg;
        inplane_inertia(dofs, m, [m * x_m, m * y_m], m * (x_m * x_m + y_m * y_m))
    }

    /// Add a lumped mass at (x_m, y_m) whose value is a parameter `name` (kg, nominal
    /// `nominal_kg`): a mass term N Nᵀ (1 kg) with the coefficient p / 1 kg, so the model is
    /// affine in it like in every other parameter and a ROM can carry it along an axis. The
    /// diagnosis's `added_mass` refit updates it. Errors: a name already taken, a point off
    /// the board or in a hole, a nominal value that is not positive (a ROM axis is centred
    /// on it).
    pub fn add_point_mass_param(
        &mut self,
        name: &str,
        x_m: f64,
        y_m: f64,
        nominal_kg: f64,
    ) -> Result<(), FemError> {
        if self.map.names.iter().any(|n| n == name) {
            return Err(FemError::Param(format!(
                "point-mass parameter {name:?}: the model already has a parameter of that name"
            )));
        }
        if !(nominal_kg.is_finite() && nominal_kg > 0.0) {
            return Err(FemError::Param(format!(
                "point-mass parameter {name:?}: expected a finite positive nominal mass in kg, found {nominal_kg}"
            )));
        }
        let row = self.interp_row(x_m, y_m)?;
        let mut term = vec![0.0; self.pattern.row_idx.len()];
        for &(r, wr) in &row {
            for &(c, wc) in &row {
                term[self.pattern.index(r, c)] += wr * wc;
            }
        }
        for (r, c, m) in self.inplane_point_mass(x_m, y_m, 1.0) {
            term[self.pattern.index(r, c)] += m;
        }
        self.map.names.push(name.to_string());
        self.map.nominal.push(nominal_kg);
        let param = self.map.names.len() - 1;
        self.m_term_names.push(name.to_string());
        self.map.m_coefs.push(Coef::Linear { param, scale: 1.0 });
        self.m_terms.push(term);
        Ok(())
    }

    /// Scale the FR-4 core's bending stiffness by `factor` over the disc of `radius_m` around
    /// (x_m, y_m): below 1 a delaminated or cracked region, above 1 a stiffened one (epoxy
    /// underfill under a BGA); the copper layers and the mass are unchanged. The disc's share
    /// of every element is integrated by cut-cell quadrature (as the holes are), and the
    /// change, (factor − 1) × the core's stiffness over the disc, joins the core's own terms,
    /// so it follows the core moduli of the parameters exactly. The virtual lab's
    /// out-of-library effect. Errors: a negative or non-finite factor, a disc that leaves the
    /// board or meets a hole.
    pub fn add_core_stiffness_change(
        &mut self,
        x_m: f64,
        y_m: f64,
        radius_m: f64,
        factor: f64,
    ) -> Result<(), FemError> {
        if !(factor.is_finite() && factor >= 0.0) {
            return Err(FemError::Param(format!(
                "core stiffness change: expected a finite non-negative factor, found {factor}"
            )));
        }
        let (lx, ly) = (self.board.length_x_m, self.board.width_y_m);
        if !(radius_m > 0.0
            && x_m - radius_m >= 0.0
            && y_m - radius_m >= 0.0
            && x_m + radius_m <= lx
            && y_m + radius_m <= ly)
        {
            return Err(FemError::Param(format!(
                "core stiffness change: expected a disc of positive radius inside the {lx} × {ly} m board, found radius {radius_m} m at ({x_m}, {y_m}) m"
            )));
        }
        if let Some(h) = self
            .board
            .holes
            .iter()
            .find(|h| (x_m - h.x_m).hypot(y_m - h.y_m) < radius_m + 0.5 * h.diameter_m)
        {
            return Err(FemError::Param(format!(
                "core stiffness change: the disc at ({x_m}, {y_m}) m meets the hole at ({}, {}) m",
                h.x_m, h.y_m
            )));
        }
        let core_names = ["core_q11", "core_q22", "core_q12", "core_q66"];
        let idx: Vec<usize> = core_names
            .iter()
            .map(|n| {
                self.k_term_names
                    .iter()
                    .position(|t| t == n)
                    .ok_or_else(|| FemError::Mesh(format!("no core term {n}")))
            })
            .collect::<Result<_, _>>()?;
        let (elements, qd) = self.core_disc(x_m, y_m, radius_m);
        let touched = elements.len();
        for (dofs, disc) in elements {
            for k in 0..4 {
                let s = (factor - 1.0) * qd[k];
                for r in 0..disc.n {
                    for cc in 0..disc.n {
                        let q = self.pattern.index(dofs[r], dofs[cc]);
                        self.k_terms[idx[k]][q] += s * disc.k_bend[k][r][cc];
                    }
                }
            }
        }
        if touched == 0 {
            return Err(FemError::Mesh(format!(
                "core stiffness change: the disc at ({x_m}, {y_m}) m covers no element"
            )));
        }
        Ok(())
    }

    /// The elements a disc of the board overlaps, each with its DOFs and the disc's part of
    /// its unit bending matrices (cut-cell quadrature), and the core's factors Q_k h³/12 (at
    /// the board file's core moduli) that turn them into the core's bending stiffness.
    fn core_disc(
        &self,
        x_m: f64,
        y_m: f64,
        radius_m: f64,
    ) -> (Vec<([usize; DOFS], ElementMatrices)>, [f64; 4]) {
        let c = &self.board.core;
        let h = c.thickness_m;
        let q_core = orthotropic_q(c.e_x_pa, c.e_y_pa, c.g_xy_pa, c.nu_xy);
        let (_, _, d_core) = layer_factors(-h / 2.0, h / 2.0);
        let mut out = vec![];
        for (ex, ey) in self.disc_elements(x_m, y_m, radius_m) {
            let rect = self.mesh.rect(ex, ey);
            let (a, b) = self.mesh.size(ex, ey);
            let pts = annulus_rect_quadrature(x_m, y_m, 0.0, radius_m, &rect);
            if pts.is_empty() {
                continue;
            }
            let Some(dofs) = self.mesh.element_dofs(ex, ey) else {
                continue;
            };
            let mut disc = ElementMatrices::zero(self.mesh.element_dof_count());
            disc.add_points(&pts, rect.x0, rect.y0, a, b, 1.0);
            out.push((dofs, disc));
        }
        (out, q_core.map(|q| q * d_core))
    }

    /// The active elements of the bounding box of the disc of radius `radius_m` at (x_m,
    /// y_m), one more each way (only these can overlap it), row by row.
    fn disc_elements(&self, x_m: f64, y_m: f64, radius_m: f64) -> Vec<(usize, usize)> {
        let m = &self.mesh;
        let (ex0, ey0) = m.element_at(x_m - radius_m, y_m - radius_m);
        let (ex1, ey1) = m.element_at(x_m + radius_m, y_m + radius_m);
        let mut out = vec![];
        for ey in ey0.saturating_sub(1)..(ey1 + 2).min(m.ny) {
            for ex in ex0.saturating_sub(1)..(ex1 + 2).min(m.nx) {
                if m.active[ey * m.nx + ex] {
                    out.push((ex, ey));
                }
            }
        }
        out
    }

    /// The core's bending stiffness over a disc, as a form on the columns of `vectors`
    /// (DOF vectors, e.g. mode shapes): E_jk = v_jᵀ K_disc v_k, with K_disc the core's
    /// bending stiffness (board file's core moduli) over the disc of radius `radius_m` at
    /// (x_m, y_m), clipped to the board. A core stiffness change of factor f there changes
    /// an eigenvalue by (f − 1) E_jj to first order, and couples the modes by (f − 1) E_jk:
    /// the signature of a local stiffness change for the diagnosis's localisation.
    pub fn core_stiffness_form(
        &self,
        x_m: f64,
        y_m: f64,
        radius_m: f64,
        vectors: faer::MatRef<'_, f64>,
    ) -> Mat<f64> {
        // Per element, the core's bending stiffness over the disc (one matrix, Σ_k q_k of
        // the bending unit matrices, accumulated as Bᵀ D B at each quadrature point, upper
        // triangle only), then its form on the vectors: the diagnosis asks for this form at
        // ~600 discs, and building all six unit matrices of each cut element at every point
        // of the cut-cell quadrature (`core_disc`) took 80 s of it on the default board.
        let n = vectors.ncols();
        let mut e = Mat::<f64>::zeros(n, n);
        let c = &self.board.core;
        let q = orthotropic_q(c.e_x_pa, c.e_y_pa, c.g_xy_pa, c.nu_xy);
        let (_, _, d_core) = layer_factors(-c.thickness_m / 2.0, c.thickness_m / 2.0);
        let q = q.map(|q| q * d_core);
        let nd = self.mesh.element_dof_count();
        let shear = nd == DOFS;
        let (g, gw) = super::plate::gauss4();
        for (ex, ey) in self.disc_elements(x_m, y_m, radius_m) {
            let rect = self.mesh.rect(ex, ey);
            let (a, b) = self.mesh.size(ex, ey);
            let Some(dofs) = self.mesh.element_dofs(ex, ey) else {
                continue;
            };
            let corners = [
                (rect.x0, rect.y0),
                (rect.x1, rect.y0),
                (rect.x0, rect.y1),
                (rect.x1, rect.y1),
            ];
            let inside = corners
                .iter()
                .all(|(px, py)| (px - x_m).hypot(py - y_m) <= radius_m);
            // An element inside the disc: its own 4 × 4 Gauss rule, exact (the integrand's
            // degree is ≤ 6 each way); a cut one: the disc's cut-cell quadrature.
            let pts: Vec<(f64, f64, f64)> = if inside {
                (0..16)
                    .map(|i| {
                        let (ix, iy) = (i / 4, i % 4);
                        (
                            rect.x0 + g[ix] * a,
                            rect.y0 + g[iy] * b,
                            gw[ix] * gw[iy] * a * b,
                        )
                    })
                    .collect()
            } else {
                annulus_rect_quadrature(x_m, y_m, 0.0, radius_m, &rect)
            };
            if pts.is_empty() {
                continue;
            }
            let mut kel = [[0.0; DOFS]; DOFS];
            for (px, py, w) in pts {
                let (xi, eta) = ((px - rect.x0) / a, (py - rect.y0) / b);
                let sh = shape(xi, eta, a, b);
                let [kx, ky, kt] = super::mindlin::curvature_rows(&sh, xi, eta, a, b, shear);
                for r in 0..nd {
                    // Row r of Bᵀ D, times the weight.
                    let (ux, uy, ut) = (
                        w * (q[0] * kx[r] + q[2] * ky[r]),
                        w * (q[2] * kx[r] + q[1] * ky[r]),
                        w * q[3] * kt[r],
                    );
                    if ux == 0.0 && uy == 0.0 && ut == 0.0 {
                        continue;
                    }
                    for c in r..nd {
                        kel[r][c] += ux * kx[c] + uy * ky[c] + ut * kt[c];
                    }
                }
            }
            for r in 0..nd {
                for c in 0..r {
                    kel[r][c] = kel[c][r];
                }
            }
            // The vectors' values at the element's DOFs (contiguous), K_el v_k, then v_jᵀ of it.
            let vloc: Vec<[f64; DOFS]> = (0..n)
                .map(|k| {
                    let mut out = [0.0; DOFS];
                    for (o, &d) in out.iter_mut().zip(&dofs[..nd]) {
                        *o = vectors[(d, k)];
                    }
                    out
                })
                .collect();
            let kv: Vec<[f64; DOFS]> = vloc
                .iter()
                .map(|v| {
                    let mut out = [0.0; DOFS];
                    for (o, row) in out.iter_mut().zip(&kel[..nd]) {
                        *o = row[..nd].iter().zip(&v[..nd]).map(|(a, b)| a * b).sum();
                    }
                    out
                })
                .collect();
            for j in 0..n {
                for k in j..n {
                    let v: f64 = vloc[j][..nd]
                        .iter()
                        .zip(&kv[k][..nd])
                        .map(|(a, b)| a * b)
                        .sum();
                    e[(j, k)] += v;
                    if k != j {
                        e[(k, j)] += v;
                    }
                }
            }
        }
        e
    }

    fn interp_row(&self, x_m: f64, y_m: f64) -> Result<[(usize, f64); 16], FemError> {
        let (lx, ly) = (self.board.length_x_m, self.board.width_y_m);
        let tol = 1e-9 * lx.max(ly);
        let out = FemError::PointOutside { x_m, y_m };
        if !(x_m >= -tol && x_m <= lx + tol && y_m >= -tol && y_m <= ly + tol) {
            return Err(out);
        }
        let m = &self.mesh;
        let (ex, ey) = m.element_at(x_m, y_m);
        if self
            .board
            .holes
            .iter()
            .any(|h| (x_m - h.x_m).hypot(y_m - h.y_m) < 0.5 * h.diameter_m)
        {
            return Err(out);
        }
        let dofs = bfs_dofs(&m.element_dofs(ex, ey).ok_or(out)?);
        let (a, b) = m.size(ex, ey);
        let xi = ((x_m - m.x_m[ex]) / a).clamp(0.0, 1.0);
        let eta = ((y_m - m.y_m[ey]) / b).clamp(0.0, 1.0);
        let n = shape(xi, eta, a, b);
        let mut row = [(0usize, 0.0); 16];
        for k in 0..16 {
            row[k] = (dofs[k], n[0][k]);
        }
        Ok(row)
    }

    /// Operator giving w at `points_m` (m, board frame) from a DOF vector.
    pub fn shape_operator(&self, points_m: &[[f64; 2]]) -> Result<ShapeOperator, FemError> {
        let rows = points_m
            .iter()
            .map(|p| self.interp_row(p[0], p[1]))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(ShapeOperator {
            points_m: points_m.to_vec(),
            rows,
        })
    }

    /// Out-of-plane shapes of `modes` at `points_m`: (n_points × n_modes), 1/√kg.
    pub fn w_at(&self, modes: &Modes, points_m: &[[f64; 2]]) -> Result<Mat<f64>, FemError> {
        Ok(self.shape_operator(points_m)?.apply(modes.shapes.as_ref()))
    }

    /// Numeric Cholesky of K − σM on the cached symbolic analysis.
    pub(crate) fn factor(
        &self,
        kv: &[f64],
        mv: &[f64],
        sigma: f64,
    ) -> Result<SeqLlt<'_>, FemError> {
        let a: Vec<f64> = kv.iter().zip(mv).map(|(k, m)| k - sigma * m).collect();
        let sym: &SymbolicCholesky<usize> = &self.symbolic;
        let mut values = vec![0.0; sym.len_val()];
        let req = sym.factorize_numeric_llt_scratch::<f64>(Par::Seq, Default::default());
        let mut buf = MemBuffer::try_new(req)
            .map_err(|e| FemError::Factorisation(format!("workspace: {e:?}")))?;
        sym.factorize_numeric_llt::<f64>(
            &mut values,
            self.pattern.view(&a),
            Side::Lower,
            Default::default(),
            Par::Seq,
            MemStack::new(&mut buf),
            Default::default(),
        )
        .map(|_| ())
        .map_err(|e| {
            FemError::Factorisation(format!(
                "K − σM with σ = {sigma:e}: expected positive definite, found {e:?}"
            ))
        })?;
        Ok(SeqLlt {
            symbolic: sym,
            values,
        })
    }

    /// The lowest `n_modes` elastic modes at `p` (shift-invert Lanczos, see
    /// [`super::eigen`]). For the free setup three extra modes are computed and the
    /// rigid-body ones (frequency below 1 % of the highest computed) are dropped.
    pub fn modes(&self, p: &Params, n_modes: usize) -> Result<Modes, FemError> {
        self.modes_with(p, n_modes, &EigenOptions::default())
    }

    /// [`FeModel::modes`] with explicit solver options.
    pub fn modes_with(
        &self,
        p: &Params,
        n_modes: usize,
        opts: &EigenOptions,
    ) -> Result<Modes, FemError> {
        Ok(self.modes_and_rigid(p, n_modes, opts)?.0)
    }

    /// [`FeModel::modes_with`] and the rigid-body modes it dropped (mass-normalised, one
    /// column each; none for a bolted board). Modal perturbation sums over a free board need
    /// them: a point mass couples every elastic mode to the rigid-body ones.
    pub fn modes_and_rigid(
        &self,
        p: &Params,
        n_modes: usize,
        opts: &EigenOptions,
    ) -> Result<(Modes, Mat<f64>), FemError> {
        if n_modes == 0 {
            return Err(FemError::Request("n_modes: expected >= 1, found 0".into()));
        }
        let c = self.coefficients(p)?;
        let kv = self.k_values(&c.k);
        let mv = self.m_values(&c.m);
        let free = matches!(self.setup, Setup::Free);
        let extra = if free { 3 } else { 0 };
        let nev = (n_modes + extra).min(self.n_dof);
        let llt = self.factor(&kv, &mv, opts.shift)?;
        let solve = |x: &mut Mat<f64>| llt.solve_in_place(x.as_mut());
        let mmul = |x: &[f64], y: &mut [f64]| self.pattern.matvec(&mv, x, y);
        let (lams, vecs) = eigen::shift_invert_lanczos(self.n_dof, nev, opts, solve, mmul)?;
        let lam_max = lams.last().copied().unwrap_or(0.0).max(0.0);
        let mut n_rigid = 0;
        if free {
            while n_rigid < lams.len() && lams[n_rigid] < 1e-4 * lam_max {
                n_rigid += 1;
            }
        }
        let keep: Vec<usize> = (n_rigid..lams.len()).take(n_modes).collect();
        if keep.len() < n_modes {
            return Err(FemError::Request(format!(
                "expected {n_modes} elastic modes, found {} (model has {} DOFs)",
                keep.len(),
                self.n_dof
            )));
        }
        let eigenvalues: Vec<f64> = keep.iter().map(|&i| lams[i]).collect();
        let freq_hz = eigenvalues
            .iter()
            .map(|l| l.max(0.0).sqrt() / (2.0 * std::f64::consts::PI))
            .collect();
        let shapes = Mat::from_fn(self.n_dof, keep.len(), |i, j| vecs[(i, keep[j])]);
        let rigid = Mat::from_fn(self.n_dof, n_rigid, |i, j| vecs[(i, j)]);
        Ok((
            Modes {
                freq_hz,
                eigenvalues,
                shapes,
                n_rigid_dropped: n_rigid,
            },
            rigid,
        ))
    }
}

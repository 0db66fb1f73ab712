//! The physics core: a thin orthotropic-laminate plate model of the PCB (conforming
//! BFS Kirchhoff elements on a structured mesh, copper homogenised by classical
//! lamination theory), the free and bolted setups with a family of bolted-joint
//! models, a sparse shift-invert Lanczos eigen-solver, a parametric reduced-order
//! model (ROM) with an NPZ export, and analytic eigen-sensitivities.
//!
//! Everything here is pure computation over plain data: no file I/O, no CLI, no global
//! state; the only randomness (Lanczos start vectors, ROM snapshot design) comes from
//! explicitly seeded `ChaCha8Rng`s, so equal inputs give equal bytes.
//!
//! The model is exactly affine in its coefficients: K(p) = Σᵢ cᵢ(p) Kᵢ and
//! M(p) = Σⱼ dⱼ(p) Mⱼ, where the user-facing parameters p (`e_x_pa`, `e_y_pa`,
//! `g_xy_pa`, `nu_xy`, `e_cu_pa`, `mass_scale`, `k_con_n_per_m`, …) map to the
//! coefficients by cheap scalar functions ([`params`]).

#![allow(
    clippy::needless_range_loop,
    reason = "matrix kernels index several arrays with one loop index; iterator chains would hide the math"
)]
#![allow(
    clippy::neg_cmp_op_on_partial_ord,
    reason = "`!(x > 0.0)` deliberately also rejects NaN"
)]

pub mod board;
pub mod convergence;
pub mod copper;
pub mod dense;
pub mod eigen;
pub mod geometry;
pub mod gerber;
pub mod grading;
pub mod joints;
pub mod laminate;
pub mod mindlin;
pub mod model;
pub mod npz;
pub mod params;
pub mod plate;
pub mod rom;
pub mod sensitivity;
mod sparse;

/// Revision of the discretization: changes whenever the same board, options and seed
/// give different model numbers (it keys the shared cache of model artifacts, which
/// otherwise would serve a ROM built by an older model).
pub const MODEL_REVISION: &str = "3: copper integrated per convex piece";

pub use board::{Board, MeshOptions};
pub use joints::{JointFeature, JointModel};
pub use model::{FeModel, ModelOptions, Modes, Setup, ShapeOperator};
pub use params::Params;
pub use rom::{Rom, RomDerivatives, RomModes, RomOptions, RomShapeOperator};

/// Errors of the physics core; each names what was expected and what was found.
#[derive(Debug, thiserror::Error)]
pub enum FemError {
    /// The board TOML could not be parsed.
    #[error("board description: {0}")]
    BoardParse(String),
    /// The board parsed but a quantity is out of its physical range.
    #[error("board description: {0}")]
    BoardInvalid(String),
    /// The mesh cannot represent the board (e.g. no node in a clamped patch).
    #[error("mesh: {0}")]
    Mesh(String),
    /// A parameter name is unknown or a value is out of range.
    #[error("parameter: {0}")]
    Param(String),
    /// A point lies outside the board or inside a hole.
    #[error("point ({x_m}, {y_m}) m: expected inside the board outline and not in a hole")]
    PointOutside {
        /// x, m.
        x_m: f64,
        /// y, m.
        y_m: f64,
    },
    /// A factorisation failed (matrix not positive definite at these parameters).
    #[error("factorisation: {0}")]
    Factorisation(String),
    /// The eigen-solver did not converge.
    #[error("eigen-solver: {0}")]
    Eigen(String),
    /// A request is inconsistent with the model (e.g. more modes than the ROM holds).
    #[error("request: {0}")]
    Request(String),
    /// A serialised ROM could not be read.
    #[error("ROM file: {0}")]
    RomFormat(String),
}

#[cfg(test)]
pub(crate) mod tests;

//! Tests of the physics core against closed forms, published tables and identities.

mod board_default;
mod convergence;
pub(crate) mod helpers;
mod joints;
mod rom;
mod sensitivity;
mod shear;
mod thickness;
mod verification;

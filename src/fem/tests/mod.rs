//! Tests of the physics core against closed forms, published tables and identities.

mod helpers;
mod verification;
mod board_default;
mod rom;
mod sensitivity;
mod joints;

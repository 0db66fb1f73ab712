//! Bayesian updating: the sampler kernel and the hierarchical models it runs on. Pure: no
//! I/O, randomness only through explicit seeds (see `stage::update` for the wiring).
//!
//! - [`smc`]: tempered SMC over a [`smc::Target`] with unit-blocked, centred and
//!   non-centred mutations; log evidence.
//! - [`resample`]: resampling schemes.
//! - [`diagnostics`]: rank-normalised split R-hat, bulk/tail ESS (as ArviZ), posterior summaries.
//! - [`population`]: the MVN + LKJ population prior and its unconstrained transforms.
//! - [`stats`]: log-space helpers, small dense Cholesky.
//! - [`modal`]: the Vanik–Beck–Au modal likelihood over a ROM (eigenvalue, shape, mass terms).
//! - [`shape_weight`]: the power of each mode's shape term, from how much its measurements'
//!   residuals share (a design effect).
//! - [`discrepancy`]: the model-form discrepancy shared by the units, orthogonal to what
//!   the parameters absorb.
//! - [`target`]: the hierarchical targets of step 1 (boards) and step 2 (joints).
//! - [`laplace_is`]: a few coordinates' evidence by importance sampling at the Laplace point.

pub mod diagnostics;
pub mod discrepancy;
pub mod laplace_is;
pub mod modal;
pub mod population;
pub mod reference;
pub mod resample;
pub mod shape_weight;
pub mod smc;
pub mod stats;
pub mod surrogate;
pub mod target;
pub mod unit_quadrature;

#[cfg(test)]
mod funnel_tests;
#[cfg(test)]
pub(crate) mod sbc_tests;
#[cfg(test)]
mod surrogate_tests;
#[cfg(test)]
mod tests;

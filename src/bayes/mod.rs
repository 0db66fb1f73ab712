//! Bayesian updating: the sampler kernel and the hierarchical models it runs on. Pure: no
//! I/O, randomness only through explicit seeds (see `stage::update` for the wiring).
//!
//! - [`smc`]: tempered SMC over a [`smc::Target`] with unit-blocked, centred and
//!   non-centred mutations; log evidence.
//! - [`resample`]: resampling schemes.
//! - [`population`]: the MVN + LKJ population prior and its unconstrained transforms.
//! - [`stats`]: log-space helpers, small dense Cholesky.

pub mod population;
pub mod resample;
pub mod smc;
pub mod stats;

#[cfg(test)]
mod tests;

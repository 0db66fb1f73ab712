//! Uncertainty quantification, pure: Monte Carlo propagation of the updated posterior through
//! the reduced-order model ([`propagate`]). No I/O; `stage::propagate` reads the posterior
//! tables and writes the predictions.

pub mod inputs;
pub mod propagate;

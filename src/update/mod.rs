//! The two-step hierarchical Bayesian updating as pure functions over plain data: no paths,
//! no Arrow, no command line. `stage::update` reads the campaign's tables, calls these and
//! writes the posteriors.
//!
//! - [`problem`]: paired data → the likelihood's units (frequencies, shapes, masses,
//!   thicknesses, covariates), the labels, the shape-term weights, the model-error prior and
//!   the model-form discrepancy.
//! - [`enrichment`]: the model enrichments (the mechanisms the diagnosis names).
//! - [`rom_box`]: the ROM for a step and its checks against the full model.
//! - [`centre`]: step 2's joint centre fitted to the bolted modes.
//! - [`prepare`]: step 2's model preparation (centre and ROM), a value the caller keeps.
//! - [`sampler`]: the SMC pipeline (reference → pilot → surrogates → tempering → correction).
//! - [`posterior`]: draws to tables' rows, summaries, convergence verdicts and residuals.
//! - [`boards`]: step 1 (boards) phase by phase.
//! - [`joints`]: step 2 (joints) phase by phase.
//! - [`joint_screen`]: the per-assembly Bayes factor of a joint of its own, given step 2.
//! - [`step1`]: the step-1 posterior as step 2 carries it.
//! - [`new_modes`]: an enriched model's own modes paired with unpaired identified ones.

pub mod boards;
pub mod centre;
pub mod enrichment;
pub mod joint_screen;
pub mod joints;
pub mod new_modes;
pub mod posterior;
pub mod prepare;
pub mod problem;
pub mod rom_box;
pub mod sampler;
#[cfg(test)]
mod sampler_tests;
pub mod step1;

//! Step 2's preparation (the joint centre and the ROM around it) as a value: the caller keeps
//! it and passes it to every refit of the same model, instead of a process-global memo.

use crate::fem::Rom;

/// Step 2's preparation: the fitted ROM centre and the ROM. It depends on the step's inputs
/// and model spec alone (`key`), not on the sampler, so a caller that runs the same step again
/// with more particles (the diagnosis's gate runs a refit twice) passes it back and spares the
/// centre fit and the ROM build.
#[derive(Clone)]
pub struct JointPrep {
    /// Opaque: the hash of the inputs and model spec the preparation was made for.
    pub key: String,
    pub centre: Vec<f64>,
    pub rom: Rom,
}

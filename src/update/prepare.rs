//! Step 2's preparation (the joint centre and the ROM around it) as a value: the caller keeps
//! it and passes it to every refit of the same model, instead of a process-global memo.

use crate::fem::Rom;
use crate::update::centre::CentreFit;

/// Step 2's preparation: the fitted ROM centre and the ROM. It depends on the step's inputs
/// and model spec alone (`key`), not on the sampler, so a caller that runs the same step again
/// with more particles (the diagnosis's gate runs a refit twice) passes it back and spares the
/// centre fit and the ROM build.
#[derive(Clone)]
pub struct JointPrep {
    /// Opaque: the hash of the inputs and model spec the preparation was made for.
    pub key: String,
    pub centre: CentreFit,
    pub rom: Rom,
}

/// A caller's gate on step 2 after its centre fit, before the ROM and the sampler: `Some(why)`
/// stops the step there with `why` as its error (the diagnosis's screen of a refit that its
/// centre fit shows cannot explain the misfit it was screened for).
pub type CentreGate<'a> = dyn Fn(&CentreFit) -> Option<String> + 'a;

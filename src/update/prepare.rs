//! Step 2's preparation (the joint centre and the ROM around it) as a value: the caller keeps
//! it and passes it to every refit of the same model, instead of a process-global memo.

use crate::fem::Rom;

/// The joint step's preparation that depends on nothing but its inputs and the options other
/// than the sampler's (the fitted ROM centre and the ROM), remembered within the process for
/// one key ([`joint_prep_key`]). The diagnosis's gate (`stage::diagnose`, `run_gated`) runs a
/// refit's step 2 a second time with more particles and runs; on the paper campaign's rotation
/// refit the centre fit and the ROM took 34 s of each attempt (0.8 s remembered; the whole
/// diagnosis 267 s before, 239 s after, same tables). Not a file cache: the stage's
/// manifest already decides when a whole step is reused, and this only spares a re-run in the
/// same process the identical work.
#[derive(Clone)]
pub(crate) struct JointPrep {
    pub(crate) key: String,
    pub(crate) centre: Vec<f64>,
    pub(crate) rom: Rom,
}

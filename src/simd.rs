//! Vector-register hygiene after faer's dense kernels.
//!
//! faer's matrix products run on the `gemm` crate's runtime-dispatched AVX2/AVX-512
//! micro-kernels, which return with the upper halves of the vector registers still in use
//! (no `vzeroupper`). Our own code is compiled for the baseline x86-64 target (SSE2,
//! non-VEX instructions); on CPUs that track the dirty upper state, every such instruction
//! afterwards carries a false dependency on it. Measured on this project's machines (AMD
//! EPYC with AVX-512): the scalar pole refinement and LSFD that follow the LSCF ran 2.9x
//! slower after a faer `matmul` until the state was cleared. No crate offers this, so it
//! is the one-line intrinsic below, called in the modal kernels after each block of faer
//! products. (The FE solves, on faer's sparse Cholesky, showed no such effect: the same
//! call after each factorisation and solve changed nothing measurable.)

/// Clear the upper halves of the AVX registers (`vzeroupper`) if the CPU has AVX; a no-op
/// elsewhere. Cheap (a few cycles) and safe to call from any code.
#[inline]
pub fn clear_upper_vector_state() {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx") {
            // SAFETY: `vzeroupper` needs AVX, which was detected at run time just above.
            // It only zeroes bits 128 and up of the vector registers; code compiled without
            // AVX (all of ours, the caller included) never keeps values there, and the
            // intrinsic is an opaque call for it, so no live value is touched.
            unsafe { std::arch::x86_64::_mm256_zeroupper() }
        }
    }
}

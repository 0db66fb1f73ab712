//! Numerical optimisation shared by the kernels.

pub mod lm;

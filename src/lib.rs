//! hbmu: hierarchical Bayesian model updating for modal tests of nominally identical parts.
//!
//! Data flows `io` (parse/write) → `stage` (one file per pipeline stage, the only place that
//! wires I/O to kernels) → numerical kernels (`fem`, `modal`, `lab`) that are pure functions
//! over plain data. See ARCHITECTURE.md.

pub mod bayes;
pub mod campaign;
pub mod diagnose;
pub mod fem;
pub mod findings;
pub mod formats;
pub mod io;
pub mod lab;
pub mod modal;
pub mod optim;
pub mod report;
pub mod schemas;
pub mod simd;
pub mod stage;
pub mod table_spec;
pub mod update;
pub mod uq;

//! `hbmu diagnose`: reads a work directory's posterior tables, locates the misfit,
//! screens and refits candidate mechanisms, writes the diagnosis.

pub mod inputs;

//! Diagnosis of model inadequacy, pure: locate the mismatch between the updated model and
//! the recordings ([`locate`]; where on the board: [`localize`]), screen a library of physical mechanisms by how well their
//! sensitivity pattern explains it, select by refitting (Bayes factors from the SMC and
//! held-out error), and explain.

pub mod doc;
/// The mechanisms the diagnosis names; the model enrichments themselves belong to the updating.
pub use crate::update::enrichment as library;
pub mod localize;
pub mod locate;
pub mod misfit;
pub mod point_search;
pub mod regions;
pub mod screen;
pub mod select;
pub mod shapes;
pub mod verdict;

//! Report rendering, pure: plots (SVG strings), the validation tables (`validation`: predicted
//! intervals, their coverage, the Table-2 analog) and the HTML page and Markdown summary
//! (`html`), the diagnosis section's data and tables (`diagnosis`). The stages read the
//! artifacts and write the files.

pub mod diagnosis;
pub mod figures;
pub mod html;
pub mod plots;
pub mod sources;
pub mod validation;

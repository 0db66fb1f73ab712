//! Report rendering: plots (SVG strings) and, later, validation tables. Pure: the stages write
//! the files.

pub mod plots;

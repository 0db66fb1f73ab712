//! `extract/modes.parquet` read back (moved to [`crate::io::tables::extract`], the table's
//! home; this path stays for the stages that import it from here).

pub use crate::io::tables::extract::{read_modes_table, ModeRow};

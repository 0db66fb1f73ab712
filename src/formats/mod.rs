//! Byte-level readers and writers of the lab formats: UFF, the measurement sheet, MT-SICS
//! balance logs and Gerber. They work over `&[u8]` or `&str`, never paths; the io module reads
//! the files.

pub mod balance_log;
pub mod gerber;
pub mod sheet;
pub mod uff;

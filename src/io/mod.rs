//! Everything that touches files: parsers over bytes (UFF, balance logs, the sheet), writers
//! of our artifacts (Parquet tables, the campaign MCAP, manifests), and atomic writes. Kernels
//! never import this module; stages call it.

pub mod atomic;
pub mod balance_log;
pub mod board_files;
pub mod cache;
pub mod campaign_dir;
pub mod gerber;
pub mod ingest_outputs;
pub mod manifest;
pub mod mcap_writer;
pub mod sheet;
pub mod tables;
pub mod uff;

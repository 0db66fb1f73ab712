//! Everything that touches files: reading the lab's files (whose bytes `crate::formats`
//! parses), writers of our artifacts (Parquet tables, the campaign MCAP, manifests), and
//! atomic writes. Kernels never import this module; stages call it.

pub mod atomic;
pub mod board_files;
pub mod cache;
pub mod campaign_dir;
pub mod diagnose_inputs;
pub mod external;
pub mod ingest_outputs;
pub mod manifest;
pub mod mcap_writer;
pub mod model_cache;
pub mod modes_table;
pub mod tables;
pub mod work_dir;

/// A JSON document read from `path`; errors name the file (unreadable, or not JSON).
pub fn read_json(path: &std::path::Path) -> anyhow::Result<serde_json::Value> {
    use anyhow::Context;
    let b = std::fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
    serde_json::from_slice(&b).with_context(|| format!("{}: not valid JSON", path.display()))
}

/// A file-name-safe version of an id (for plot file names).
pub fn sanitize(id: &str) -> String {
    id.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' || c == '.' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

//! Stage manifests: content hashes of inputs, configuration and outputs, and the up-to-date check.
//!
//! Every stage writes, next to its outputs, a manifest JSON recording the stage name, the tool
//! version, the BLAKE3 hash of every input file and of the effective configuration (canonical
//! JSON), the seed where there is one, and the hash of every output. The *fingerprint* is the
//! hash of everything that determines the outputs (stage, tool version, config, seed, input
//! hashes, and input names relative to the stage's input directory, never absolute paths); a stage whose manifest has the same fingerprint and whose outputs still hash to
//! the recorded values is up to date and is not rerun. Wall-clock facts (start time, duration,
//! thread count) live only in the manifest, never inside data files, and never enter the
//! fingerprint. The manifest is written last and atomically, so a killed stage leaves either
//! the old complete manifest (whose output hashes then no longer match) or none.

use crate::io::atomic;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fs::File;
use std::io::{self, Read};
use std::path::{Path, PathBuf};

/// Version string recorded in manifests, Parquet metadata and model-cache keys; part of the
/// fingerprint. The package version with the source revision as build metadata
/// (`0.1.0+src.<16 hex>`, see build.rs): a changed source reruns every stage and never
/// reuses a cached model artifact built by other code.
pub const TOOL_VERSION: &str = concat!(env!("CARGO_PKG_VERSION"), "+src.", env!("HBMU_SOURCE_ID"));

/// One hashed file, with its path relative to a base directory where possible.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct FileHash {
    pub path: String,
    pub blake3: String,
    pub bytes: u64,
}

/// Hash one file with BLAKE3 (streamed, 1 MiB buffer).
pub fn hash_file(path: &Path) -> io::Result<(String, u64)> {
    let mut f = File::open(path)?;
    let mut hasher = blake3::Hasher::new();
    let mut buf = vec![0u8; 1 << 20];
    let mut n_total = 0u64;
    loop {
        let n = f.read(&mut buf)?;
        if n == 0 {
            break;
        }
        n_total += n as u64;
        hasher.update(&buf[..n]);
    }
    Ok((hasher.finalize().to_hex().to_string(), n_total))
}

/// Path of `p` relative to `base` when it lies under it, else `p` as given; `/` separators.
pub fn rel_path(p: &Path, base: &Path) -> String {
    p.strip_prefix(base)
        .unwrap_or(p)
        .to_string_lossy()
        .replace('\\', "/")
}

/// What a stage is about to do: enough to compute its fingerprint before running it.
#[derive(Debug, Clone)]
pub struct StageSpec {
    pub stage: String,
    /// Input files (hashed). Paths are recorded relative to `input_base`.
    pub inputs: Vec<PathBuf>,
    /// The directory that names the inputs: an input under it enters the fingerprint by its
    /// path relative to it and its content; an input elsewhere (a board file, a scenario) by
    /// its content alone. Use the stage's input directory (campaign, ingest or extract
    /// output), never the current directory, and an empty path when no input has a name that
    /// matters: absolute paths differ between work directories and cluster nodes, and must
    /// never reach a fingerprint.
    pub input_base: PathBuf,
    /// The effective configuration: every option that can change the outputs.
    pub config: serde_json::Value,
    pub seed: Option<u64>,
    /// Where the manifest goes; outputs are recorded relative to its directory.
    pub manifest_path: PathBuf,
}

/// Wall-clock facts about one run: recorded, never fingerprinted.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunInfo {
    pub started_utc: String,
    pub wall_seconds: f64,
    pub threads: usize,
}

/// The manifest as written to disk.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Manifest {
    pub stage: String,
    pub tool: String,
    pub tool_version: String,
    pub fingerprint: String,
    pub config: serde_json::Value,
    pub config_blake3: String,
    pub seed: Option<u64>,
    pub inputs: Vec<FileHash>,
    pub outputs: Vec<FileHash>,
    /// Exit code the stage returned (0 clean, 3 some measurements quarantined), so that an
    /// up-to-date no-op reports the same outcome as the run it skips.
    pub exit_code: i32,
    /// Stage-specific summary (counts of findings, records, …).
    pub summary: BTreeMap<String, serde_json::Value>,
    pub run: RunInfo,
}

/// Inputs hashed once: the fingerprint and the per-file hashes.
#[derive(Debug, Clone)]
pub struct Prepared {
    pub spec: StageSpec,
    pub inputs: Vec<FileHash>,
    pub config_blake3: String,
    pub fingerprint: String,
}

/// Canonical JSON (serde_json's `Value` keeps object keys sorted with default features).
fn canonical_json(v: &serde_json::Value) -> String {
    serde_json::to_string(v).expect("serde_json::Value always serialises")
}

/// Hash the inputs and configuration; compute the fingerprint.
pub fn prepare(spec: StageSpec) -> io::Result<Prepared> {
    let mut inputs = Vec::with_capacity(spec.inputs.len());
    let mut keys = Vec::with_capacity(spec.inputs.len());
    // Files are hashed in parallel (a campaign is tens of files and hundreds of MB) and taken
    // in input order, so the result does not depend on the thread count.
    let hashes: Vec<io::Result<(String, u64)>> = spec
        .inputs
        .par_iter()
        .map(|p| {
            hash_file(p).map_err(|e| {
                io::Error::new(e.kind(), format!("cannot hash input {}: {e}", p.display()))
            })
        })
        .collect();
    for (p, hash) in spec.inputs.iter().zip(hashes) {
        let (h, n) = hash?;
        keys.push((fingerprint_name(p, &spec.input_base), h.clone()));
        inputs.push(FileHash {
            path: recorded_path(p, &spec.input_base, &spec.manifest_path),
            blake3: h,
            bytes: n,
        });
    }
    inputs.sort_by(|a, b| a.path.cmp(&b.path));
    keys.sort();
    let config_blake3 = blake3::hash(canonical_json(&spec.config).as_bytes())
        .to_hex()
        .to_string();
    let mut h = blake3::Hasher::new();
    h.update(b"hbmu-fingerprint-v1\0");
    h.update(spec.stage.as_bytes());
    h.update(b"\0");
    h.update(TOOL_VERSION.as_bytes());
    h.update(b"\0");
    h.update(config_blake3.as_bytes());
    h.update(b"\0");
    h.update(format!("{:?}", spec.seed).as_bytes());
    for (name, blake3) in &keys {
        h.update(b"\0");
        h.update(name.as_bytes());
        h.update(b"=");
        h.update(blake3.as_bytes());
    }
    let fingerprint = h.finalize().to_hex().to_string();
    Ok(Prepared {
        spec,
        inputs,
        config_blake3,
        fingerprint,
    })
}

/// How an input is named in the manifest: relative to `base` when it lies under it; else, when
/// it lies in the stage directory's parent (another stage's output in the same work
/// directory, as the updating's inputs are), relative to the stage directory
/// (`../ingest/masses.parquet`), so that the manifest does not depend on where the work
/// directory lies; else as given. The fingerprint does not use it ([`fingerprint_name`]).
fn recorded_path(p: &Path, base: &Path, manifest_path: &Path) -> String {
    if base.as_os_str().is_empty() || p.strip_prefix(base).is_err() {
        let work = manifest_path.parent().and_then(Path::parent);
        if let Some(rel) = work
            .filter(|w| !w.as_os_str().is_empty())
            .and_then(|w| p.strip_prefix(w).ok())
        {
            return format!("../{}", rel.to_string_lossy().replace('\\', "/"));
        }
    }
    rel_path(p, base)
}

/// An input's name in the fingerprint: its path relative to `base` when it lies under a
/// non-empty base, else empty (the input then counts by its content alone).
fn fingerprint_name(p: &Path, base: &Path) -> String {
    match p.strip_prefix(base) {
        Ok(rel) if !base.as_os_str().is_empty() => rel.to_string_lossy().replace('\\', "/"),
        _ => String::new(),
    }
}

/// Read a manifest if present and parseable.
pub fn read_manifest(path: &Path) -> Option<Manifest> {
    let bytes = std::fs::read(path).ok()?;
    serde_json::from_slice(&bytes).ok()
}

/// The existing manifest when the stage is up to date: same fingerprint, and every recorded
/// output still exists with the recorded hash.
pub fn up_to_date(prep: &Prepared) -> Option<Manifest> {
    let m = read_manifest(&prep.spec.manifest_path)?;
    if m.fingerprint != prep.fingerprint || m.stage != prep.spec.stage {
        return None;
    }
    let dir = prep.spec.manifest_path.parent().unwrap_or(Path::new("."));
    let all_match = m
        .outputs
        .par_iter()
        .all(|o| matches!(hash_file(&dir.join(&o.path)), Ok((h, _)) if h == o.blake3));
    if !all_match {
        return None;
    }
    Some(m)
}

/// Hash the outputs and write the manifest atomically (last, after all outputs are in place).
pub fn finish(
    prep: &Prepared,
    outputs: &[PathBuf],
    exit_code: i32,
    summary: BTreeMap<String, serde_json::Value>,
    run: RunInfo,
) -> io::Result<Manifest> {
    let dir = prep
        .spec
        .manifest_path
        .parent()
        .unwrap_or(Path::new("."))
        .to_path_buf();
    let mut outs = Vec::with_capacity(outputs.len());
    let hashes: Vec<io::Result<(String, u64)>> = outputs.par_iter().map(|p| hash_file(p)).collect();
    for (p, hash) in outputs.iter().zip(hashes) {
        let (h, n) = hash?;
        outs.push(FileHash {
            path: rel_path(p, &dir),
            blake3: h,
            bytes: n,
        });
    }
    let m = Manifest {
        stage: prep.spec.stage.clone(),
        tool: "hbmu".into(),
        tool_version: TOOL_VERSION.into(),
        fingerprint: prep.fingerprint.clone(),
        config: prep.spec.config.clone(),
        config_blake3: prep.config_blake3.clone(),
        seed: prep.spec.seed,
        inputs: prep.inputs.clone(),
        outputs: outs,
        exit_code,
        summary,
        run,
    };
    let mut bytes = serde_json::to_vec_pretty(&m).map_err(io::Error::other)?;
    bytes.push(b'\n');
    atomic::write_bytes(&prep.spec.manifest_path, &bytes)?;
    Ok(m)
}

/// Current UTC time as RFC 3339, for the manifest's run info only.
pub fn now_utc() -> String {
    chrono::Utc::now().to_rfc3339_opts(chrono::SecondsFormat::Millis, true)
}

/// `<out>.manifest.json` next to a single-file output.
pub fn manifest_path_for(out: &Path) -> PathBuf {
    let mut s = out.as_os_str().to_owned();
    s.push(".manifest.json");
    PathBuf::from(s)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inputs_of_sibling_stages_are_recorded_relative_to_the_stage_directory() {
        let m = Path::new("/w/work/update_boards/update_boards.manifest.json");
        let none = Path::new("");
        assert_eq!(
            recorded_path(Path::new("/w/work/ingest/masses.parquet"), none, m),
            "../ingest/masses.parquet"
        );
        // Outside the work directory: as given. Under the base: relative to it.
        assert_eq!(
            recorded_path(Path::new("/repo/data/boards/b.toml"), none, m),
            "/repo/data/boards/b.toml"
        );
        assert_eq!(
            recorded_path(
                Path::new("/w/work/pair/pairs.parquet"),
                Path::new("/w/work"),
                m
            ),
            "pair/pairs.parquet"
        );
    }

    #[test]
    fn tool_version_carries_the_source_revision() {
        let (pkg, rev) = TOOL_VERSION
            .split_once("+src.")
            .expect("version has +src.<id>");
        assert_eq!(pkg, env!("CARGO_PKG_VERSION"));
        assert_eq!(rev.len(), 16, "{TOOL_VERSION}");
        assert!(rev.bytes().all(|b| b.is_ascii_hexdigit()), "{TOOL_VERSION}");
    }
}

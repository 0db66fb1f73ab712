//! A campaign directory as a [`Source`] of the pure campaign checks: listing (hidden files
//! skipped), reading, and the input files that fingerprint the ingest stage.

use crate::campaign::Source;
use crate::formats::sheet;
use crate::io::manifest;
use anyhow::{bail, Context};
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

/// A campaign directory on disk.
pub struct CampaignDir {
    dir: PathBuf,
}

impl CampaignDir {
    /// The directory, after checking that it holds a sheet (else a clear error).
    pub fn open(dir: &Path) -> anyhow::Result<CampaignDir> {
        check_campaign_dir(dir)?;
        Ok(CampaignDir {
            dir: dir.to_path_buf(),
        })
    }
}

impl Source for CampaignDir {
    fn name(&self) -> String {
        self.dir
            .canonicalize()
            .ok()
            .and_then(|p| p.file_name().map(|n| n.to_string_lossy().into_owned()))
            .unwrap_or_else(|| "campaign".into())
    }
    fn describe(&self) -> String {
        self.dir.display().to_string()
    }
    fn list(&self) -> std::io::Result<Vec<String>> {
        Ok(list_files(&self.dir)?
            .iter()
            .map(|p| manifest::rel_path(p, &self.dir))
            .collect())
    }
    fn is_file(&self, rel: &str) -> bool {
        self.dir.join(rel).is_file()
    }
    fn identity(&self, rel: &str) -> String {
        let p = self.dir.join(rel);
        p.canonicalize().unwrap_or(p).to_string_lossy().into_owned()
    }
    fn read(&self, rel: &str) -> std::io::Result<Vec<u8>> {
        std::fs::read(self.dir.join(rel))
    }
}

/// Recursively list regular files under `dir`, sorted.
fn list_files(dir: &Path) -> std::io::Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d)? {
            let e = e?;
            let ft = e.file_type()?;
            let name = e.file_name();
            if name.to_string_lossy().starts_with('.') {
                continue;
            }
            if ft.is_dir() {
                stack.push(e.path());
            } else if ft.is_file() {
                out.push(e.path());
            }
        }
    }
    out.sort();
    Ok(out)
}

/// The campaign directory and its sheet exist; else a clear error naming what is missing.
fn check_campaign_dir(dir: &Path) -> anyhow::Result<()> {
    if !dir.is_dir() {
        bail!(
            "campaign directory {} does not exist or is not a directory",
            dir.display()
        );
    }
    let sheet_path = dir.join("campaign.csv");
    if !sheet_path.is_file() {
        bail!(
            "{}: no measurement sheet (expected campaign.csv in the campaign directory; see campaign-format.md)",
            dir.display()
        );
    }
    Ok(())
}

/// The files that determine the stage's outputs: the sheet, every file it names that exists,
/// and every balance log. Fails with a clear message when the campaign cannot be read at all.
pub fn discover_inputs(dir: &Path) -> anyhow::Result<Vec<PathBuf>> {
    check_campaign_dir(dir)?;
    let sheet_path = dir.join("campaign.csv");
    let mut inputs: BTreeSet<PathBuf> = BTreeSet::new();
    inputs.insert(sheet_path.clone());
    let bytes = std::fs::read(&sheet_path)
        .with_context(|| format!("cannot read {}", sheet_path.display()))?;
    if let Ok(s) = sheet::parse(&bytes, "campaign.csv") {
        for r in &s.rows {
            let p = dir.join(&r.file);
            if !r.file.is_empty() && p.is_file() {
                inputs.insert(p);
            }
        }
    }
    for sub in ["vibrometer", "scale"] {
        let d = dir.join(sub);
        if d.is_dir() {
            inputs.extend(list_files(&d)?);
        }
    }
    Ok(inputs.into_iter().collect())
}

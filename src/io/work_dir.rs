//! The work directory's layout: one directory per stage under one root, named as the
//! Makefile's targets and the subcommands are. The stage directories and the files one stage
//! reads from another's are named here once.

use std::path::{Path, PathBuf};

pub const INGEST: &str = "ingest";
pub const EXTRACT: &str = "extract";
pub const PAIR: &str = "pair";
pub const FE: &str = "fe";
pub const UPDATE_BOARDS: &str = "update_boards";
pub const UPDATE_JOINTS: &str = "update_joints";
pub const PROPAGATE: &str = "propagate";
pub const DIAGNOSE: &str = "diagnose";
pub const REPORT: &str = "report";

/// Every stage's directory, in the order of the DAG.
pub const STAGES: [&str; 9] = [
    INGEST,
    EXTRACT,
    PAIR,
    FE,
    UPDATE_BOARDS,
    UPDATE_JOINTS,
    PROPAGATE,
    DIAGNOSE,
    REPORT,
];

/// A work directory: the paths of its stages and of the tables stages share.
#[derive(Clone, Copy, Debug)]
pub struct WorkDir<'a> {
    root: &'a Path,
}

impl<'a> WorkDir<'a> {
    pub fn new(root: &'a Path) -> Self {
        WorkDir { root }
    }

    /// The directory of stage `name` (one of [`STAGES`]).
    fn stage(&self, name: &str) -> PathBuf {
        self.root.join(name)
    }

    pub fn ingest(&self) -> PathBuf {
        self.stage(INGEST)
    }

    pub fn extract(&self) -> PathBuf {
        self.stage(EXTRACT)
    }

    pub fn pair(&self) -> PathBuf {
        self.stage(PAIR)
    }

    pub fn update_boards(&self) -> PathBuf {
        self.stage(UPDATE_BOARDS)
    }

    pub fn update_joints(&self) -> PathBuf {
        self.stage(UPDATE_JOINTS)
    }

    pub fn propagate(&self) -> PathBuf {
        self.stage(PROPAGATE)
    }

    /// Ingest's measurement table.
    pub fn measurements(&self) -> PathBuf {
        self.ingest().join("measurements.parquet")
    }

    /// Ingest's balance table.
    pub fn masses(&self) -> PathBuf {
        self.ingest().join("masses.parquet")
    }

    /// Extract's identified modes.
    pub fn modes(&self) -> PathBuf {
        self.extract().join("modes.parquet")
    }

    /// Pair's experimental–model pairs.
    pub fn pairs(&self) -> PathBuf {
        self.pair().join("pairs.parquet")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The stage directories are the Makefile's: each appears as `$(WORK)/<name>` there.
    #[test]
    fn the_stage_directories_are_the_makefiles() {
        let mk = std::fs::read_to_string(
            Path::new(env!("CARGO_MANIFEST_DIR")).join("pipelines/Makefile"),
        )
        .unwrap();
        for s in STAGES {
            assert!(
                mk.contains(&format!("$(WORK)/{s}")),
                "{s} not in pipelines/Makefile"
            );
        }
    }
}

//! The external programs of the virtual lab's solid truth: gmsh (meshing) and CalculiX
//! (`ccx`, the eigen-solve), run as subprocesses in a private scratch directory that is
//! removed afterwards. Both run single-threaded (`-nt 1`; `OMP_NUM_THREADS=1`), so that
//! their outputs do not depend on the machine's thread count; the lab runs several at once.
//!
//! `HBMU_SOLID_KEEP=DIR` keeps every run's input and output files under DIR (for debugging).
//!
//! The programs are found as `HBMU_GMSH` / `HBMU_CCX` when set, else `gmsh` / `ccx` on the
//! PATH (Debian packages `gmsh` and `calculix-ccx`; `make -C pipelines tools` installs them).

use std::path::{Path, PathBuf};
use std::process::Command;

use crate::lab::solid::Solver;

/// gmsh and CalculiX, located.
#[derive(Clone, Debug)]
pub struct Calculix {
    pub gmsh: PathBuf,
    pub ccx: PathBuf,
}

fn find(var: &str, name: &str) -> Option<PathBuf> {
    if let Some(p) = std::env::var_os(var) {
        return Some(PathBuf::from(p));
    }
    std::env::var_os("PATH").and_then(|paths| {
        std::env::split_paths(&paths)
            .map(|d| d.join(name))
            .find(|p| p.is_file())
    })
}

impl Calculix {
    /// Locate both programs; the error says what is missing and how to install it.
    pub fn locate() -> Result<Calculix, String> {
        let gmsh = find("HBMU_GMSH", "gmsh");
        let ccx = find("HBMU_CCX", "ccx");
        match (gmsh, ccx) {
            (Some(gmsh), Some(ccx)) => Ok(Calculix { gmsh, ccx }),
            (g, c) => Err(format!(
                "the solid truth needs gmsh and CalculiX: {}{}not found (Debian: apt-get install gmsh calculix-ccx, or `make -C pipelines tools`; or set HBMU_GMSH / HBMU_CCX)",
                if g.is_none() { "gmsh " } else { "" },
                if c.is_none() { "ccx " } else { "" }
            )),
        }
    }
}

/// Copy a finished run's scratch directory under `HBMU_SOLID_KEEP`, when set.
fn keep(dir: &Path, what: &str) {
    let Some(root) = std::env::var_os("HBMU_SOLID_KEEP") else {
        return;
    };
    let Ok(target) = tempfile::Builder::new()
        .prefix(&format!("{what}-"))
        .tempdir_in(&root)
        .map(tempfile::TempDir::keep)
    else {
        return;
    };
    if let Ok(rd) = std::fs::read_dir(dir) {
        for e in rd.flatten() {
            let _ = std::fs::copy(e.path(), target.join(e.file_name()));
        }
    }
}

fn run(cmd: &mut Command, what: &str, dir: &Path) -> Result<(), String> {
    let out = cmd
        .current_dir(dir)
        .env("OMP_NUM_THREADS", "1")
        .env("CCX_NPROC_EQUATION_SOLVER", "1")
        .output()
        .map_err(|e| format!("{what}: cannot start: {e}"))?;
    let tail = |b: &[u8]| {
        let s = String::from_utf8_lossy(b);
        let lines: Vec<&str> = s.lines().collect();
        lines[lines.len().saturating_sub(8)..].join("\n")
    };
    if !out.status.success() {
        return Err(format!(
            "{what} failed ({}):\n{}\n{}",
            out.status,
            tail(&out.stdout),
            tail(&out.stderr)
        ));
    }
    // ccx reports input errors on stdout and may still exit 0.
    let stdout = String::from_utf8_lossy(&out.stdout);
    if let Some(l) = stdout.lines().find(|l| l.contains("*ERROR")) {
        return Err(format!("{what}: {}", l.trim()));
    }
    Ok(())
}

impl Solver for Calculix {
    fn mesh(&self, geo_script: &str) -> Result<String, String> {
        let dir = tempfile::tempdir().map_err(|e| format!("gmsh scratch directory: {e}"))?;
        std::fs::write(dir.path().join("board.geo"), geo_script)
            .map_err(|e| format!("gmsh input: {e}"))?;
        run(
            Command::new(&self.gmsh).args([
                "-2",
                "board.geo",
                "-nt",
                "1",
                "-format",
                "inp",
                "-o",
                "mesh.inp",
                "-v",
                "1",
            ]),
            "gmsh",
            dir.path(),
        )?;
        keep(dir.path(), "gmsh");
        std::fs::read_to_string(dir.path().join("mesh.inp"))
            .map_err(|e| format!("gmsh wrote no mesh: {e}"))
    }

    fn solve(&self, deck: &str) -> Result<String, String> {
        let dir = tempfile::tempdir().map_err(|e| format!("ccx scratch directory: {e}"))?;
        std::fs::write(dir.path().join("job.inp"), deck).map_err(|e| format!("ccx input: {e}"))?;
        run(
            Command::new(&self.ccx).args(["-i", "job"]),
            "ccx",
            dir.path(),
        )?;
        keep(dir.path(), "ccx");
        std::fs::read_to_string(dir.path().join("job.dat"))
            .map_err(|e| format!("ccx wrote no results: {e}"))
    }
}

//! Helpers shared by the integration tests: running the binary, copying fixtures, Python peers.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

pub fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

pub fn example_campaign() -> PathBuf {
    repo().join("data/example/campaign")
}

/// Run `hbmu` with arguments.
pub fn hbmu(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_hbmu"))
        .args(args)
        .env("CI", "1")
        .output()
        .expect("run hbmu")
}

pub fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// Recursively copy a directory.
pub fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let dst = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &dst);
        } else {
            std::fs::copy(e.path(), dst).unwrap();
        }
    }
}

/// A fresh copy of the example campaign in a temp dir: (tempdir guard, campaign path).
pub fn campaign_copy() -> (tempfile::TempDir, PathBuf) {
    let t = tempfile::tempdir().unwrap();
    let c = t.path().join("campaign");
    copy_dir(&example_campaign(), &c);
    (t, c)
}

/// True when python3 can import every module; when it cannot, interop tests skip with a notice
/// unless `HBMU_REQUIRE_INTEROP=1` (set by CI), in which case they fail.
pub fn python_has(modules: &[&str]) -> bool {
    let code = modules
        .iter()
        .map(|m| format!("import {m}"))
        .collect::<Vec<_>>()
        .join("; ");
    let ok = Command::new("python3")
        .args(["-c", &code])
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false);
    if !ok {
        if std::env::var("HBMU_REQUIRE_INTEROP").as_deref() == Ok("1") {
            panic!(
                "python3 with {modules:?} is required (HBMU_REQUIRE_INTEROP=1) but not available"
            );
        }
        eprintln!("SKIP: python3 with {modules:?} not available (set HBMU_REQUIRE_INTEROP=1 to fail instead)");
    }
    ok
}

/// Run a Python script from tests/interop with arguments; panic with its output on failure.
pub fn python(script: &str, args: &[&str]) -> String {
    let o = Command::new("python3")
        .arg(repo().join("tests/interop").join(script))
        .args(args)
        .output()
        .expect("run python3");
    let out = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(
        o.status.success(),
        "{script} failed:\nstdout:\n{out}\nstderr:\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
    out
}

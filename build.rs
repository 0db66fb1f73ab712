//! Source revision of the build: the BLAKE3 hash of every file under `src/` (by relative
//! path and content, in sorted order), `Cargo.toml` and `Cargo.lock`, exported as
//! `HBMU_SOURCE_ID` (16 hex digits). It joins the tool version in every stage fingerprint and
//! every model-cache key (`crate::io::manifest::TOOL_VERSION`), so a code change reruns the
//! stages and rebuilds the cached artifacts it may affect, while the same sources give the
//! same id in any checkout, with or without git (a `git describe` would depend on the clone
//! and be missing in a source tarball).

use std::path::{Path, PathBuf};

fn collect(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let p = e.path();
        if p.is_dir() {
            collect(&p, out);
        } else if p.is_file() {
            out.push(p);
        }
    }
}

fn main() {
    println!("cargo:rerun-if-env-changed=HBMU_SOURCE_ID_OVERRIDE");
    // A build that must stamp another build's id (to show that a change of the sources alone
    // changes no output byte: `HBMU_SOURCE_ID_OVERRIDE=<16 hex>`).
    if let Ok(id) = std::env::var("HBMU_SOURCE_ID_OVERRIDE") {
        assert!(
            id.len() == 16 && id.bytes().all(|b| b.is_ascii_hexdigit()),
            "HBMU_SOURCE_ID_OVERRIDE: expected 16 hex digits, found {id:?}"
        );
        println!("cargo:rustc-env=HBMU_SOURCE_ID={id}");
        return;
    }
    let root = PathBuf::from(std::env::var("CARGO_MANIFEST_DIR").expect("set by cargo"));
    let mut files = Vec::new();
    collect(&root.join("src"), &mut files);
    for f in ["Cargo.toml", "Cargo.lock", "build.rs"] {
        files.push(root.join(f));
    }
    let mut rel: Vec<(String, PathBuf)> = files
        .into_iter()
        .filter(|p| p.is_file())
        .map(|p| {
            let r = p
                .strip_prefix(&root)
                .unwrap_or(&p)
                .to_string_lossy()
                .replace('\\', "/");
            (r, p)
        })
        .collect();
    rel.sort();
    let mut h = blake3::Hasher::new();
    h.update(b"hbmu-source-v1\0");
    for (name, path) in &rel {
        let bytes = std::fs::read(path).expect("source file readable");
        h.update(name.as_bytes());
        h.update(b"\0");
        h.update(&(bytes.len() as u64).to_le_bytes());
        h.update(&bytes);
    }
    let id = h.finalize().to_hex();
    println!("cargo:rustc-env=HBMU_SOURCE_ID={}", &id[..16]);
    // A directory makes cargo rerun this script when anything under it changes.
    println!("cargo:rerun-if-changed=src");
    println!("cargo:rerun-if-changed=Cargo.toml");
    println!("cargo:rerun-if-changed=Cargo.lock");
    println!("cargo:rerun-if-changed=build.rs");
}

//! The shared cache of model artifacts (ROMs, sensitivity tables): content-addressed, safe for
//! many concurrent writers on one machine or on many nodes over a shared filesystem.
//!
//! An artifact is stored under the hash of everything that determines it, which for an `fe`
//! stage is its fingerprint (stage, tool version, board file content, every option, the seed;
//! no path): `$HBMU_CACHE/<kind>/<key[..2]>/<key>.<ext>`. Campaigns that use the same board
//! therefore share one build. Publishing is atomic: the builder writes a temp file with a
//! unique name in the destination directory, syncs it, and renames it into place. No lock is
//! held while building: two jobs that miss at once both build, and the second rename replaces
//! the first with the same bytes (builds are deterministic), so a reader sees either nothing
//! or a complete artifact. Each artifact has a `.blake3` sidecar written after it; an entry
//! whose sidecar is missing or disagrees with the artifact (a damaged file, a crash between the
//! two renames) is treated as absent and rebuilt.

use crate::io::{atomic, manifest};
use std::io;
use std::path::{Path, PathBuf};

/// The environment variable naming the cache directory; unset or empty = no cache.
pub const ENV: &str = "HBMU_CACHE";

/// How an artifact was obtained.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fetch {
    /// Built by this call (and published to the cache).
    Built,
    /// Found complete in the cache.
    Hit,
}

impl Fetch {
    pub fn as_str(self) -> &'static str {
        match self {
            Fetch::Built => "built",
            Fetch::Hit => "hit",
        }
    }
}

/// A cache rooted at a directory.
#[derive(Debug, Clone)]
pub struct Cache {
    root: PathBuf,
}

impl Cache {
    pub fn new(root: impl Into<PathBuf>) -> Cache {
        Cache { root: root.into() }
    }

    /// The cache named by `HBMU_CACHE`, if set and non-empty.
    pub fn from_env() -> Option<Cache> {
        std::env::var_os(ENV)
            .filter(|v| !v.is_empty())
            .map(Cache::new)
    }

    /// Where the artifact `key` of `kind` lives (whether or not it exists yet).
    pub fn path(&self, kind: &str, key: &str, ext: &str) -> PathBuf {
        let shard = key.get(..2).unwrap_or("00");
        self.root
            .join(kind)
            .join(shard)
            .join(format!("{key}.{ext}"))
    }

    /// The artifact's path when a complete copy is in the cache.
    pub fn lookup(&self, kind: &str, key: &str, ext: &str) -> Option<PathBuf> {
        let p = self.path(kind, key, ext);
        let want = std::fs::read_to_string(sidecar(&p)).ok()?;
        match manifest::hash_file(&p) {
            Ok((h, _)) if h == want.trim() => Some(p),
            _ => None,
        }
    }

    /// The artifact `key` of `kind`: from the cache when complete there, else built by
    /// `build` and published. Returns its path in the cache and how it was obtained.
    pub fn fetch_or_build<F>(
        &self,
        kind: &str,
        key: &str,
        ext: &str,
        build: F,
    ) -> io::Result<(PathBuf, Fetch)>
    where
        F: FnOnce() -> io::Result<Vec<u8>>,
    {
        if let Some(p) = self.lookup(kind, key, ext) {
            return Ok((p, Fetch::Hit));
        }
        let bytes = build()?;
        let p = self.path(kind, key, ext);
        atomic::write_bytes(&p, &bytes)?;
        let h = blake3::hash(&bytes).to_hex().to_string();
        atomic::write_bytes(&sidecar(&p), format!("{h}\n").as_bytes())?;
        Ok((p, Fetch::Built))
    }
}

fn sidecar(p: &Path) -> PathBuf {
    let mut s = p.as_os_str().to_owned();
    s.push(".blake3");
    PathBuf::from(s)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Arc;

    /// A deterministic artifact of `n` bytes for `key` (what a build returns).
    fn artifact(key: &str, n: usize) -> Vec<u8> {
        let mut out = Vec::with_capacity(n);
        let mut h = blake3::Hasher::new();
        h.update(key.as_bytes());
        let mut r = h.finalize_xof();
        out.resize(n, 0);
        r.fill(&mut out);
        out
    }

    #[test]
    fn second_fetch_is_a_hit_with_the_same_bytes() {
        let t = tempfile::tempdir().unwrap();
        let c = Cache::new(t.path());
        let builds = AtomicUsize::new(0);
        let build = || {
            builds.fetch_add(1, Ordering::SeqCst);
            Ok(artifact("k1", 1000))
        };
        let (p1, f1) = c.fetch_or_build("rom", "ab12", "npz", build).unwrap();
        let (p2, f2) = c
            .fetch_or_build("rom", "ab12", "npz", || {
                builds.fetch_add(1, Ordering::SeqCst);
                Ok(artifact("k1", 1000))
            })
            .unwrap();
        assert_eq!((f1, f2), (Fetch::Built, Fetch::Hit));
        assert_eq!(p1, p2);
        assert_eq!(builds.load(Ordering::SeqCst), 1);
        assert_eq!(std::fs::read(&p1).unwrap(), artifact("k1", 1000));
        // Another key is another artifact.
        let (_, f3) = c
            .fetch_or_build("rom", "cd34", "npz", || Ok(artifact("k2", 10)))
            .unwrap();
        assert_eq!(f3, Fetch::Built);
    }

    #[test]
    fn a_damaged_or_unsealed_entry_is_rebuilt() {
        let t = tempfile::tempdir().unwrap();
        let c = Cache::new(t.path());
        let (p, _) = c
            .fetch_or_build("rom", "ef56", "npz", || Ok(artifact("k", 500)))
            .unwrap();
        // Truncated artifact: its sidecar disagrees.
        std::fs::write(&p, &artifact("k", 500)[..100]).unwrap();
        assert!(c.lookup("rom", "ef56", "npz").is_none());
        let (_, f) = c
            .fetch_or_build("rom", "ef56", "npz", || Ok(artifact("k", 500)))
            .unwrap();
        assert_eq!(f, Fetch::Built);
        assert_eq!(std::fs::read(&p).unwrap(), artifact("k", 500));
        // No sidecar (a crash between the two renames): absent.
        std::fs::remove_file(sidecar(&p)).unwrap();
        assert!(c.lookup("rom", "ef56", "npz").is_none());
    }

    /// Many writers on a few keys at once, each build slow and large: every caller gets a
    /// complete artifact of its key, the cache ends with exactly one valid entry per key and
    /// no temp file, and readers racing the writers never see a partial file.
    #[test]
    fn concurrent_writers_never_corrupt_the_cache() {
        let t = tempfile::tempdir().unwrap();
        let c = Arc::new(Cache::new(t.path()));
        let keys = ["aa01", "aa02", "bb03"];
        let n = 1 << 20;
        let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
        // Readers: whatever they find through `lookup` must be complete.
        let readers: Vec<_> = (0..2)
            .map(|_| {
                let (c, stop) = (c.clone(), stop.clone());
                std::thread::spawn(move || {
                    let mut seen = 0;
                    while !stop.load(Ordering::SeqCst) {
                        for k in keys {
                            if let Some(p) = c.lookup("rom", k, "npz") {
                                // The file may be replaced between lookup and read, by the
                                // same bytes: still complete.
                                assert_eq!(std::fs::read(p).unwrap(), artifact(k, n));
                                seen += 1;
                            }
                        }
                    }
                    seen
                })
            })
            .collect();
        let writers: Vec<_> = (0..12)
            .map(|i| {
                let c = c.clone();
                std::thread::spawn(move || {
                    let k = keys[i % keys.len()];
                    let (p, _) = c
                        .fetch_or_build("rom", k, "npz", || {
                            std::thread::sleep(std::time::Duration::from_millis(20));
                            Ok(artifact(k, n))
                        })
                        .unwrap();
                    assert_eq!(std::fs::read(p).unwrap(), artifact(k, n));
                })
            })
            .collect();
        for w in writers {
            w.join().unwrap();
        }
        stop.store(true, Ordering::SeqCst);
        for r in readers {
            r.join().unwrap();
        }
        for k in keys {
            let p = c.lookup("rom", k, "npz").expect("every key published");
            assert_eq!(std::fs::read(p).unwrap(), artifact(k, n));
        }
        let mut leftovers = vec![];
        for e in walk(t.path()) {
            let name = e.file_name().unwrap().to_string_lossy().into_owned();
            if name.starts_with('.') {
                leftovers.push(name);
            }
        }
        assert!(leftovers.is_empty(), "temp files left: {leftovers:?}");
        assert_eq!(walk(t.path()).len(), 2 * keys.len());
    }

    fn walk(d: &Path) -> Vec<PathBuf> {
        let mut out = vec![];
        for e in std::fs::read_dir(d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                out.extend(walk(&p));
            } else {
                out.push(p);
            }
        }
        out
    }
}

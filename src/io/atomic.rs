//! Atomic artifact writes: temp file in the destination directory, fsync, rename.
//!
//! A stage killed half way must never leave a file that looks complete. Every artifact is
//! written to `.<name>.tmp-<random>` next to its destination (created exclusively, so that
//! concurrent writers of one destination, threads or jobs on other nodes of a shared
//! filesystem, never share a temp file) and renamed into place only after it has been fully
//! written and synced; rename within one directory is atomic on POSIX.

use std::fs::{self, File};
use std::io::{self, BufWriter, Write};
use std::path::Path;

/// A new, exclusively created temp file next to `dest`; removed on drop unless persisted.
fn temp_file(dest: &Path) -> io::Result<tempfile::NamedTempFile> {
    let name = dest
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "artifact".into());
    let dir = match dest.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    // 0o666 less the umask, as File::create (tempfile's default 0o600 would hide artifacts
    // from the other users of a shared cache or work directory).
    #[cfg(unix)]
    let perms = {
        use std::os::unix::fs::PermissionsExt;
        Some(fs::Permissions::from_mode(0o666))
    };
    #[cfg(not(unix))]
    let perms: Option<fs::Permissions> = None;
    let prefix = format!(".{name}.tmp-");
    let mut b = tempfile::Builder::new();
    b.prefix(&prefix);
    if let Some(p) = perms {
        b.permissions(p);
    }
    b.tempfile_in(dir)
}

/// Rename the temp file onto `dest`.
fn publish(tmp: tempfile::NamedTempFile, dest: &Path) -> io::Result<()> {
    tmp.persist(dest).map(|_| ()).map_err(|e| e.error)
}

/// Write `dest` atomically by streaming into `write`. On error the temp file is removed and
/// `dest` is untouched.
pub fn write_with<F>(dest: &Path, write: F) -> io::Result<()>
where
    F: FnOnce(&mut BufWriter<&mut File>) -> io::Result<()>,
{
    if let Some(dir) = dest.parent() {
        if !dir.as_os_str().is_empty() {
            fs::create_dir_all(dir)?;
        }
    }
    let mut tmp = temp_file(dest)?;
    {
        let mut w = BufWriter::with_capacity(1 << 20, tmp.as_file_mut());
        write(&mut w)?;
        w.flush()?;
    }
    tmp.as_file().sync_all()?;
    publish(tmp, dest)
}

/// Write a byte slice atomically.
pub fn write_bytes(dest: &Path, bytes: &[u8]) -> io::Result<()> {
    write_with(dest, |w| w.write_all(bytes))
}

/// Write a seekable artifact (MCAP needs `Seek`) atomically: the closure gets the temp `File`.
pub fn write_file_with<F>(dest: &Path, write: F) -> io::Result<()>
where
    F: FnOnce(&mut File) -> io::Result<()>,
{
    if let Some(dir) = dest.parent() {
        if !dir.as_os_str().is_empty() {
            fs::create_dir_all(dir)?;
        }
    }
    let mut tmp = temp_file(dest)?;
    write(tmp.as_file_mut())?;
    tmp.as_file().sync_all()?;
    publish(tmp, dest)
}

//! The updating's model computations through the shared model cache (`HBMU_CACHE`,
//! [`super::cache`]): its ROM and the model-error term's mesh study. Each is a deterministic
//! function of the model and its options, and a step of one campaign's DAG rebuilt both every
//! time: step 1, step 2 and each of the diagnosis's refits, 28 s and 15 s apiece on the
//! built-in shear-deformable board (2 cores), about a minute and a half of a diagnosis
//! that refits one board mechanism. The key hashes the model's content
//! ([`FeModel::content_blake3`]), the options, the tool version (with the source revision)
//! and the model revision; the value is the exact bytes (NPZ of f64, JSON with round-trip
//! floats), so a hit gives the computation's result bit for bit.

use super::cache::Cache;
use crate::fem::convergence::{mesh_spread, MeshSpread};
use crate::fem::{Board, FeModel, MeshOptions, Params, Rom, RomOptions, Setup};
use anyhow::Context;

fn key(kind: &str, parts: &[&str]) -> String {
    let mut h = blake3::Hasher::new();
    for p in [
        kind,
        super::manifest::TOOL_VERSION,
        crate::fem::MODEL_REVISION,
    ]
    .iter()
    .chain(parts)
    {
        h.update(p.as_bytes());
        h.update(b"\0");
    }
    h.finalize().to_hex().to_string()
}

/// `compute`'s value through `cache` (bytes `encode`d, read back with `decode`); computed
/// when there is no cache.
fn through<T>(
    cache: Option<&Cache>,
    kind: &str,
    key: &str,
    ext: &str,
    compute: impl FnOnce() -> anyhow::Result<T>,
    encode: impl Fn(&T) -> anyhow::Result<Vec<u8>>,
    decode: impl Fn(&[u8]) -> anyhow::Result<T>,
) -> anyhow::Result<T> {
    let Some(cache) = cache else {
        return compute();
    };
    let mut built = None;
    let (p, _) = cache
        .fetch_or_build(kind, key, ext, || {
            let v = compute().map_err(std::io::Error::other)?;
            let b = encode(&v).map_err(std::io::Error::other)?;
            built = Some(v);
            Ok(b)
        })
        .with_context(|| format!("model cache {}", cache.path(kind, key, ext).display()))?;
    match built {
        Some(v) => Ok(v),
        None => {
            let b = std::fs::read(&p).with_context(|| format!("reading cached {}", p.display()))?;
            decode(&b).with_context(|| format!("cached {}", p.display()))
        }
    }
}

/// `Rom::build(model, opts)`, through `cache` (the update steps' `UpdateOptions::cache`).
pub fn rom(cache: Option<&Cache>, model: &FeModel, opts: &RomOptions) -> anyhow::Result<Rom> {
    let k = key(
        "update-rom",
        &[&model.content_blake3(), &serde_json::to_string(opts)?],
    );
    through(
        cache,
        "update-rom",
        &k,
        "npz",
        || Ok(Rom::build(model, opts)?),
        |r| Ok(r.to_npz_bytes()),
        |b| Ok(Rom::from_npz_bytes(b)?),
    )
}

/// `fem::convergence::mesh_spread(board, setup, mesh, p, n_modes)`, through `cache`.
pub fn mesh_study(
    cache: Option<&Cache>,
    board: &Board,
    setup: &Setup,
    mesh: &MeshOptions,
    p: &Params,
    n_modes: usize,
) -> anyhow::Result<MeshSpread> {
    let k = key(
        "mesh-spread",
        &[
            &serde_json::to_string(board)?,
            &format!("{setup:?}"),
            &serde_json::to_string(mesh)?,
            &serde_json::to_string(p)?,
            &n_modes.to_string(),
        ],
    );
    through(
        cache,
        "mesh-spread",
        &k,
        "json",
        || Ok(mesh_spread(board, setup, mesh, p, n_modes)?),
        |s| Ok(serde_json::to_vec(s)?),
        |b| Ok(serde_json::from_slice(b)?),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A hit gives the built value bit for bit (the ROM's every array, the mesh study's
    /// spreads), one model is one entry, and another model is another key.
    #[test]
    fn a_cache_hit_is_the_computation_bit_for_bit() {
        let t = tempfile::tempdir().unwrap();
        let cache = Cache::new(t.path());
        let board =
            Board::from_toml_str(include_str!("../../data/boards/paper_thin.toml")).unwrap();
        let mesh = MeshOptions { nx: 12, ny: 8 };
        let model = FeModel::build(&board, Setup::Free, &mesh).unwrap();
        let opts = RomOptions {
            n_modes: 4,
            max_basis: 12,
            ..RomOptions::default()
        };
        let direct = Rom::build(&model, &opts).unwrap().to_npz_bytes();
        let built = rom(Some(&cache), &model, &opts).unwrap().to_npz_bytes();
        let hit = rom(Some(&cache), &model, &opts).unwrap().to_npz_bytes();
        assert!(direct == built && built == hit);
        let entries = |kind: &str| {
            walk(&t.path().join(kind))
                .iter()
                .filter(|p| !p.to_string_lossy().ends_with(".blake3"))
                .count()
        };
        assert_eq!(entries("update-rom"), 1, "one entry for one model");
        let coarser = FeModel::build(&board, Setup::Free, &MeshOptions { nx: 10, ny: 8 }).unwrap();
        assert_ne!(model.content_blake3(), coarser.content_blake3());
        assert_eq!(
            model.content_blake3(),
            FeModel::build(&board, Setup::Free, &mesh)
                .unwrap()
                .content_blake3()
        );
        let p0 = model.nominal_params();
        let s0 = mesh_spread(&board, &Setup::Free, &mesh, &p0, 4).unwrap();
        for _ in 0..2 {
            let s = mesh_study(Some(&cache), &board, &Setup::Free, &mesh, &p0, 4).unwrap();
            assert_eq!(
                (s.freq_hz, s.rel_spread),
                (s0.freq_hz.clone(), s0.rel_spread.clone())
            );
        }
        assert_eq!(entries("mesh-spread"), 1);
    }

    fn walk(d: &std::path::Path) -> Vec<std::path::PathBuf> {
        let mut out = vec![];
        for e in std::fs::read_dir(d).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                out.extend(walk(&p));
            } else {
                out.push(p);
            }
        }
        out
    }
}

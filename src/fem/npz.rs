//! NPZ export and import of a [`Rom`]: a ZIP archive (stored, no compression) of
//! NumPy `.npy` version-1.0 arrays, loadable with `numpy.load(path)`.
//!
//! Entries (all little-endian, C order):
//! - `k_terms.npy`: float64, shape (n_k, r, r), the reduced stiffness terms Kᵢʳ (N/m
//!   in reduced coordinates of the M₀-orthonormal basis);
//! - `m_terms.npy`: float64, shape (n_m, r, r), the reduced mass terms Mⱼʳ;
//! - `basis.npy`: float64, shape (n_dof, r), the basis V (w, ∂w/∂x, ∂w/∂y, ∂²w/∂x∂y
//!   per node, node-major);
//! - `meta_json.npy`: uint8, shape (len,), UTF-8 JSON with `names`, `nominal`,
//!   `k_coefs`, `m_coefs`, `core_idx`, `n_rigid`, `n_modes`, `setup`, and `built_box`
//!   (`{"box_rel": b, "log_axes": [[name, w], …]}`: the box the snapshots spanned, ±b
//!   relative about `nominal` except the named parameters over e^{±w}; absent from files
//!   written before it was recorded).
//!
//! The model at parameters p is K(p) = Σᵢ cᵢ(p) Kᵢʳ, M(p) = Σⱼ dⱼ(p) Mⱼʳ with each
//! coefficient given in `k_coefs` / `m_coefs` as one of
//! `{"CoreQ": {"comp": c}}` → Q_c(p)/Q_c(nominal) (where Q_c(nominal) = 0, i.e. Q₂ of a
//! core with ν_xy = 0: Q_c(p)/(½(Q₀ + Q₁)(nominal))), where with ν_yx = ν_xy E_y/E_x and
//! δ = 1 − ν_xy ν_yx: Q₀ = E_x/δ, Q₁ = E_y/δ, Q₂ = ν_xy E_y/δ, Q₃ = G_xy
//! (E_x, E_y, G_xy, ν_xy at the indices `core_idx`);
//! `{"Linear": {"param": k, "scale": s}}` → p_k / s; `"Const"` → 1.
//! Eigenvalues λ = ω² (rad²/s²) of (K(p), M(p)), ascending; the first `n_rigid` are the
//! free board's rigid-body modes and are dropped. In Python:
//! `z = np.load(f); meta = json.loads(bytes(z["meta_json"]).decode())`.
//!
//! Written by hand (≈150 lines) because the format is tiny and fixed, and a ZIP crate
//! would add a dependency tree for what is 3 fixed headers and a CRC-32.

use faer::Mat;
use serde::{Deserialize, Serialize};

use super::params::ParamMap;
use super::rom::Rom;
use super::FemError;

#[derive(Serialize, Deserialize)]
struct Meta {
    #[serde(flatten)]
    map: ParamMap,
    n_rigid: usize,
    n_modes: usize,
    setup: String,
    /// The box the ROM was built over (absent from older files).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    built_box: Option<super::rom::RomBox>,
}

fn crc32(data: &[u8]) -> u32 {
    let mut table = [0u32; 256];
    for (i, t) in table.iter_mut().enumerate() {
        let mut c = i as u32;
        for _ in 0..8 {
            c = if c & 1 != 0 {
                0xEDB8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
        }
        *t = c;
    }
    let mut crc = 0xFFFF_FFFFu32;
    for &b in data {
        crc = table[((crc ^ b as u32) & 0xFF) as usize] ^ (crc >> 8);
    }
    crc ^ 0xFFFF_FFFF
}

/// A `.npy` v1.0 file for `data` with NumPy dtype string `descr` and `shape`.
pub fn npy(descr: &str, shape: &[usize], data: &[u8]) -> Vec<u8> {
    let shape_s = match shape.len() {
        1 => format!("({},)", shape[0]),
        _ => format!(
            "({})",
            shape
                .iter()
                .map(|s| s.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    let mut header =
        format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape_s}, }}");
    // Pad so that magic (6) + version (2) + length (2) + header is a multiple of 64.
    let total = 10 + header.len() + 1;
    header.push_str(&" ".repeat((64 - total % 64) % 64));
    header.push('\n');
    let mut out = Vec::with_capacity(10 + header.len() + data.len());
    out.extend_from_slice(b"\x93NUMPY\x01\x00");
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    out.extend_from_slice(data);
    out
}

fn f64_bytes(v: impl Iterator<Item = f64>) -> Vec<u8> {
    v.flat_map(|x| x.to_le_bytes()).collect()
}

fn zip(entries: &[(&str, Vec<u8>)]) -> Vec<u8> {
    let mut out = Vec::new();
    let mut central = Vec::new();
    // Fixed DOS date 1980-01-01 00:00 so equal ROMs give equal bytes.
    let (time, date) = (0u16, 33u16);
    for (name, data) in entries {
        let offset = out.len() as u32;
        let crc = crc32(data);
        let size = data.len() as u32;
        let mut local = Vec::new();
        local.extend_from_slice(&0x0403_4b50u32.to_le_bytes());
        local.extend_from_slice(&20u16.to_le_bytes());
        local.extend_from_slice(&0u16.to_le_bytes());
        local.extend_from_slice(&0u16.to_le_bytes());
        local.extend_from_slice(&time.to_le_bytes());
        local.extend_from_slice(&date.to_le_bytes());
        local.extend_from_slice(&crc.to_le_bytes());
        local.extend_from_slice(&size.to_le_bytes());
        local.extend_from_slice(&size.to_le_bytes());
        local.extend_from_slice(&(name.len() as u16).to_le_bytes());
        local.extend_from_slice(&0u16.to_le_bytes());
        local.extend_from_slice(name.as_bytes());
        out.extend_from_slice(&local);
        out.extend_from_slice(data);
        central.extend_from_slice(&0x0201_4b50u32.to_le_bytes());
        central.extend_from_slice(&20u16.to_le_bytes());
        central.extend_from_slice(&20u16.to_le_bytes());
        central.extend_from_slice(&0u16.to_le_bytes());
        central.extend_from_slice(&0u16.to_le_bytes());
        central.extend_from_slice(&time.to_le_bytes());
        central.extend_from_slice(&date.to_le_bytes());
        central.extend_from_slice(&crc.to_le_bytes());
        central.extend_from_slice(&size.to_le_bytes());
        central.extend_from_slice(&size.to_le_bytes());
        central.extend_from_slice(&(name.len() as u16).to_le_bytes());
        central.extend_from_slice(&[0u8; 12]); // extra, comment, disk, int attr (2+2+2+2) + ext attr lo (4)
        central.extend_from_slice(&offset.to_le_bytes());
        central.extend_from_slice(name.as_bytes());
    }
    let cd_offset = out.len() as u32;
    let cd_size = central.len() as u32;
    out.extend_from_slice(&central);
    out.extend_from_slice(&0x0605_4b50u32.to_le_bytes());
    out.extend_from_slice(&[0u8; 4]);
    out.extend_from_slice(&(entries.len() as u16).to_le_bytes());
    out.extend_from_slice(&(entries.len() as u16).to_le_bytes());
    out.extend_from_slice(&cd_size.to_le_bytes());
    out.extend_from_slice(&cd_offset.to_le_bytes());
    out.extend_from_slice(&0u16.to_le_bytes());
    out
}

pub(crate) fn rom_to_npz(rom: &Rom) -> Vec<u8> {
    let r = rom.dim();
    let stack = |ms: &[Mat<f64>]| {
        f64_bytes(
            ms.iter()
                .flat_map(|m| (0..r).flat_map(move |i| (0..r).map(move |j| m[(i, j)]))),
        )
    };
    let n = rom.basis.nrows();
    let basis = f64_bytes((0..n).flat_map(|i| (0..r).map(move |j| rom.basis[(i, j)])));
    let meta = Meta {
        map: rom.map.clone(),
        n_rigid: rom.n_rigid,
        n_modes: rom.n_modes,
        setup: rom.setup.clone(),
        built_box: rom.built_box.clone(),
    };
    // Serialising plain data with string keys cannot fail.
    let meta = serde_json::to_vec(&meta).unwrap_or_default();
    zip(&[
        (
            "k_terms.npy",
            npy("<f8", &[rom.k_r.len(), r, r], &stack(&rom.k_r)),
        ),
        (
            "m_terms.npy",
            npy("<f8", &[rom.m_r.len(), r, r], &stack(&rom.m_r)),
        ),
        ("basis.npy", npy("<f8", &[n, r], &basis)),
        ("meta_json.npy", npy("|u1", &[meta.len()], &meta)),
    ])
}

fn u16_at(b: &[u8], o: usize) -> Result<u16, FemError> {
    b.get(o..o + 2)
        .map(|s| u16::from_le_bytes([s[0], s[1]]))
        .ok_or_else(|| FemError::RomFormat(format!("truncated at byte {o}")))
}
fn u32_at(b: &[u8], o: usize) -> Result<u32, FemError> {
    b.get(o..o + 4)
        .map(|s| u32::from_le_bytes([s[0], s[1], s[2], s[3]]))
        .ok_or_else(|| FemError::RomFormat(format!("truncated at byte {o}")))
}

/// Entries of a stored (uncompressed) ZIP: (name, data).
fn unzip(b: &[u8]) -> Result<Vec<(String, Vec<u8>)>, FemError> {
    let mut out = Vec::new();
    let mut o = 0;
    while u32_at(b, o)? == 0x0403_4b50 {
        let method = u16_at(b, o + 8)?;
        if method != 0 {
            return Err(FemError::RomFormat(format!(
                "entry at byte {o}: expected stored (method 0), found method {method}"
            )));
        }
        let crc = u32_at(b, o + 14)?;
        let size = u32_at(b, o + 18)? as usize;
        let nlen = u16_at(b, o + 26)? as usize;
        let elen = u16_at(b, o + 28)? as usize;
        let name_b = b
            .get(o + 30..o + 30 + nlen)
            .ok_or_else(|| FemError::RomFormat("truncated entry name".into()))?;
        let name = String::from_utf8_lossy(name_b).into_owned();
        let start = o + 30 + nlen + elen;
        let data = b
            .get(start..start + size)
            .ok_or_else(|| FemError::RomFormat(format!("{name}: truncated data")))?;
        if crc32(data) != crc {
            return Err(FemError::RomFormat(format!("{name}: CRC-32 mismatch")));
        }
        out.push((name, data.to_vec()));
        o = start + size;
    }
    Ok(out)
}

/// Parse a `.npy` v1: (descr, shape, data bytes).
fn parse_npy(name: &str, b: &[u8]) -> Result<(String, Vec<usize>, Vec<u8>), FemError> {
    if b.len() < 10 || &b[..6] != b"\x93NUMPY" || b[6] != 1 {
        return Err(FemError::RomFormat(format!(
            "{name}: expected a .npy version 1.0 array"
        )));
    }
    let hl = u16_at(b, 8)? as usize;
    let header = std::str::from_utf8(
        b.get(10..10 + hl)
            .ok_or_else(|| FemError::RomFormat(format!("{name}: truncated header")))?,
    )
    .map_err(|_| FemError::RomFormat(format!("{name}: header is not UTF-8")))?;
    let field = |key: &str| -> Result<&str, FemError> {
        let k = header
            .find(&format!("'{key}':"))
            .ok_or_else(|| FemError::RomFormat(format!("{name}: header lacks '{key}'")))?;
        Ok(header[k + key.len() + 3..].trim_start())
    };
    let descr = field("descr")?;
    let descr = descr
        .trim_start_matches('\'')
        .split('\'')
        .next()
        .unwrap_or("")
        .to_string();
    if field("fortran_order")?.starts_with("True") {
        return Err(FemError::RomFormat(format!(
            "{name}: expected C order, found Fortran order"
        )));
    }
    let sh = field("shape")?;
    let inner = sh.trim_start_matches('(').split(')').next().unwrap_or("");
    let shape = inner
        .split(',')
        .map(|s| s.trim())
        .filter(|s| !s.is_empty())
        .map(|s| {
            s.parse::<usize>()
                .map_err(|_| FemError::RomFormat(format!("{name}: bad shape entry {s:?}")))
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok((descr, shape, b[10 + hl..].to_vec()))
}

fn f64_array(
    name: &str,
    entries: &[(String, Vec<u8>)],
    dims: usize,
) -> Result<(Vec<usize>, Vec<f64>), FemError> {
    let (_, raw) = entries
        .iter()
        .find(|(n, _)| n == name)
        .ok_or_else(|| FemError::RomFormat(format!("expected entry {name}, found none")))?;
    let (descr, shape, data) = parse_npy(name, raw)?;
    if descr != "<f8" || shape.len() != dims {
        return Err(FemError::RomFormat(format!(
            "{name}: expected '<f8' with {dims} dimensions, found {descr:?} with shape {shape:?}"
        )));
    }
    let count: usize = shape.iter().product();
    if data.len() != 8 * count {
        return Err(FemError::RomFormat(format!(
            "{name}: expected {} data bytes, found {}",
            8 * count,
            data.len()
        )));
    }
    let v = data
        .chunks_exact(8)
        .map(|c| f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]))
        .collect();
    Ok((shape, v))
}

pub(crate) fn rom_from_npz(bytes: &[u8]) -> Result<Rom, FemError> {
    let entries = unzip(bytes)?;
    let (_, meta_raw) = entries
        .iter()
        .find(|(n, _)| n == "meta_json.npy")
        .ok_or_else(|| FemError::RomFormat("expected entry meta_json.npy, found none".into()))?;
    let (_, _, meta_b) = parse_npy("meta_json.npy", meta_raw)?;
    let meta: Meta = serde_json::from_slice(&meta_b)
        .map_err(|e| FemError::RomFormat(format!("meta_json.npy: {e}")))?;
    let (ks, kv) = f64_array("k_terms.npy", &entries, 3)?;
    let (ms, mv) = f64_array("m_terms.npy", &entries, 3)?;
    let (bs, bv) = f64_array("basis.npy", &entries, 2)?;
    let r = bs[1];
    if ks[1] != r || ks[2] != r || ms[1] != r || ms[2] != r {
        return Err(FemError::RomFormat(format!(
            "expected {r} × {r} reduced terms, found k {ks:?}, m {ms:?}"
        )));
    }
    if ks[0] != meta.map.k_coefs.len() || ms[0] != meta.map.m_coefs.len() {
        return Err(FemError::RomFormat(format!(
            "expected {} stiffness and {} mass terms (meta), found {} and {}",
            meta.map.k_coefs.len(),
            meta.map.m_coefs.len(),
            ks[0],
            ms[0]
        )));
    }
    let unstack = |n: usize, v: &[f64]| -> Vec<Mat<f64>> {
        (0..n)
            .map(|t| Mat::from_fn(r, r, |i, j| v[t * r * r + i * r + j]))
            .collect()
    };
    let mut rom = Rom::from_parts(
        meta.map,
        unstack(ks[0], &kv),
        unstack(ms[0], &mv),
        Mat::from_fn(bs[0], r, |i, j| bv[i * r + j]),
        meta.n_rigid,
        meta.n_modes,
        meta.setup,
    );
    rom.built_box = meta.built_box;
    Ok(rom)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc32_matches_the_standard_check_value() {
        // CRC-32/ISO-HDLC check value of "123456789".
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
    }

    #[test]
    fn npy_header_is_64_byte_aligned_and_parses_back() {
        let data = f64_bytes([1.0, 2.0, 3.0, 4.0, 5.0, 6.0].into_iter());
        let f = npy("<f8", &[2, 3], &data);
        let hl = u16::from_le_bytes([f[8], f[9]]) as usize;
        assert_eq!((10 + hl) % 64, 0);
        let (d, s, b) = parse_npy("x", &f).unwrap();
        assert_eq!((d.as_str(), s, b), ("<f8", vec![2, 3], data));
    }
}

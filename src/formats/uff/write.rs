//! UFF writers for datasets 58 (ASCII or binary 58b), 2411, 15 and 164, in the standard's
//! fixed-width records (the same layout `pyuff` writes, so that pyuff and other readers that
//! slice columns read our files). Fields that do not fit their width are an error, never a
//! silently shifted record.

use std::io::Write;

use super::{Abscissa, AxisSpec, Function58, Node, Ordinate, Units164};

/// Encoding of the data records of dataset 58.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    /// ASCII records: `4E20.12` (double) or `6E13.5` (single).
    Ascii,
    /// Binary 58b, little-endian IEEE 754, in the ordinate data type's precision.
    Binary,
}

/// Why a dataset could not be written.
#[derive(Debug, thiserror::Error)]
pub enum UffWriteError {
    #[error("I/O error while writing UFF: {0}")]
    Io(#[from] std::io::Error),
    #[error("{field}: value {found:?} does not fit the standard's {width}-character field")]
    FieldTooWide {
        field: &'static str,
        width: usize,
        found: String,
    },
    #[error("{field}: expected a finite number, found {found} (at index {index})")]
    NonFinite {
        field: &'static str,
        index: usize,
        found: f64,
    },
    #[error("{what}: expected {expected} values (num_points), found {found}")]
    LengthMismatch {
        what: &'static str,
        expected: usize,
        found: usize,
    },
}

/// Appends `v` as a Fortran/C `E` field: right-justified in `width`, `prec` digits after the
/// point, exponent with sign and at least two digits, exponent letter `letter` (`E` or `D`).
fn put_e(out: &mut Vec<u8>, v: f64, width: usize, prec: usize, letter: u8) {
    let mut buf = [0u8; 48];
    let mut c = std::io::Cursor::new(&mut buf[..]);
    // Cannot fail: 48 bytes hold any `{:.17e}` rendering of a finite f64.
    let _ = write!(c, "{v:.prec$e}");
    let len = c.position() as usize;
    let s = &buf[..len];
    let e_at = s.iter().position(|&b| b == b'e').unwrap_or(len);
    let (mant, exp) = (&s[..e_at], &s[(e_at + 1).min(len)..]);
    let (eneg, edigits) = match exp.first() {
        Some(b'-') => (true, &exp[1..]),
        _ => (false, exp),
    };
    let body_len = mant.len() + 2 + edigits.len().max(2);
    out.extend(std::iter::repeat_n(b' ', width.saturating_sub(body_len)));
    out.extend_from_slice(mant);
    out.push(letter);
    out.push(if eneg { b'-' } else { b'+' });
    if edigits.len() < 2 {
        out.push(b'0');
    }
    out.extend_from_slice(edigits);
}

fn put_int(
    out: &mut Vec<u8>,
    v: i64,
    width: usize,
    field: &'static str,
) -> Result<(), UffWriteError> {
    let s = v.to_string();
    if s.len() > width {
        return Err(UffWriteError::FieldTooWide {
            field,
            width,
            found: s,
        });
    }
    out.extend(std::iter::repeat_n(b' ', width - s.len()));
    out.extend_from_slice(s.as_bytes());
    Ok(())
}

fn put_str(
    out: &mut Vec<u8>,
    s: &str,
    width: usize,
    left: bool,
    field: &'static str,
) -> Result<(), UffWriteError> {
    let n = s.chars().count();
    if n > width || s.contains(['\n', '\r']) {
        return Err(UffWriteError::FieldTooWide {
            field,
            width,
            found: s.to_owned(),
        });
    }
    if !left {
        out.extend(std::iter::repeat_n(b' ', width - n));
    }
    out.extend_from_slice(s.as_bytes());
    if left {
        out.extend(std::iter::repeat_n(b' ', width - n));
    }
    Ok(())
}

fn check_finite(field: &'static str, v: &[f64]) -> Result<(), UffWriteError> {
    match v.iter().position(|x| !x.is_finite()) {
        Some(index) => Err(UffWriteError::NonFinite {
            field,
            index,
            found: v[index],
        }),
        None => Ok(()),
    }
}

fn number_line(out: &mut Vec<u8>, number: i64) {
    out.extend_from_slice(b"    -1\n");
    let _ = put_int(out, number, 6, "dataset number");
    out.extend(std::iter::repeat_n(b' ', 74));
    out.push(b'\n');
}

fn axis_record(out: &mut Vec<u8>, a: &AxisSpec) -> Result<(), UffWriteError> {
    put_int(out, a.spec_data_type, 10, "specific data type")?;
    put_int(out, a.length_exp, 5, "length units exponent")?;
    put_int(out, a.force_exp, 5, "force units exponent")?;
    put_int(out, a.temperature_exp, 5, "temperature units exponent")?;
    out.push(b' ');
    put_str(out, &a.label, 20, true, "axis label")?;
    out.push(b' ');
    put_str(out, &a.units_label, 20, true, "axis units label")?;
    out.push(b'\n');
    Ok(())
}

/// Writes one dataset 58 (function at nodal DOF) in the standard's records 1–11 followed by
/// the data, ASCII or binary 58b.
pub fn write_58(f: &Function58, format: Format, w: &mut impl Write) -> Result<(), UffWriteError> {
    let n = f.num_points;
    let odt = f.ordinate_data_type;
    let (re, im): (&[f64], Option<&[f64]>) = match &f.ordinate {
        Ordinate::Real(v) => (v, None),
        Ordinate::Complex { re, im } => (re, Some(im)),
    };
    if re.len() != n {
        return Err(UffWriteError::LengthMismatch {
            what: "ordinate",
            expected: n,
            found: re.len(),
        });
    }
    if let Some(im) = im {
        if im.len() != n {
            return Err(UffWriteError::LengthMismatch {
                what: "ordinate imaginary part",
                expected: n,
                found: im.len(),
            });
        }
    }
    if im.is_some() != odt.is_complex() {
        return Err(UffWriteError::LengthMismatch {
            what: "ordinate parts (complex ordinate data type needs re and im)",
            expected: if odt.is_complex() { 2 } else { 1 },
            found: if im.is_some() { 2 } else { 1 },
        });
    }
    check_finite("ordinate", re)?;
    if !odt.is_double() {
        // Single precision must hold the values (f32 overflow would write inf).
        let all = re.iter().chain(im.unwrap_or(&[]));
        if let Some((index, &v)) = all.enumerate().find(|(_, v)| v.abs() > f64::from(f32::MAX)) {
            return Err(UffWriteError::NonFinite {
                field: "ordinate (in single precision)",
                index,
                found: v,
            });
        }
    }
    if let Some(im) = im {
        check_finite("ordinate imaginary part", im)?;
    }
    let (even, xs, min, inc): (bool, &[f64], f64, f64) = match &f.abscissa {
        Abscissa::Even { min, increment } => (true, &[], *min, *increment),
        Abscissa::Uneven(x) => (false, x, 0.0, 0.0),
    };
    if !even && xs.len() != n {
        return Err(UffWriteError::LengthMismatch {
            what: "uneven abscissa",
            expected: n,
            found: xs.len(),
        });
    }
    check_finite("abscissa", xs)?;
    check_finite(
        "abscissa minimum/increment, z value",
        &[min, inc, f.z_axis_value],
    )?;

    let vpp = usize::from(!even) + if im.is_some() { 2 } else { 1 };
    let size = if odt.is_double() { 8 } else { 4 };
    let value = |k: usize| -> f64 {
        let (p, j) = (k / vpp, k % vpp);
        let j = if even { j + 1 } else { j };
        match j {
            0 => xs[p],
            1 => re[p],
            _ => im.map_or(0.0, |im| im[p]),
        }
    };
    let total = n * vpp;

    let mut out: Vec<u8> = Vec::with_capacity(1200 + total * 21);
    out.extend_from_slice(b"    -1\n    58");
    match format {
        Format::Ascii => out.extend(std::iter::repeat_n(b' ', 74)),
        Format::Binary => {
            out.push(b'b');
            put_int(&mut out, 1, 6, "byte order")?;
            put_int(&mut out, 2, 6, "floating-point format")?;
            put_int(&mut out, 11, 12, "ASCII lines")?;
            put_int(&mut out, (total * size) as i64, 12, "binary bytes")?;
            for (wd, name) in [(6, "unused"), (6, "unused"), (12, "unused"), (12, "unused")] {
                put_int(&mut out, 0, wd, name)?;
            }
        }
    }
    out.push(b'\n');
    for id in &f.id_lines {
        put_str(&mut out, id, 80, true, "ID line")?;
        out.push(b'\n');
    }
    // Record 6: FORMAT(2(I5,I10),2(1X,10A1,I10,I4)).
    put_int(&mut out, f.function_type.code(), 5, "function type")?;
    put_int(&mut out, f.function_id, 10, "function id")?;
    put_int(&mut out, f.version, 5, "version number")?;
    put_int(&mut out, f.load_case, 10, "load case")?;
    out.push(b' ');
    put_str(&mut out, &f.response_entity, 10, false, "response entity")?;
    put_int(&mut out, f.response_node, 10, "response node")?;
    put_int(&mut out, f.response_direction, 4, "response direction")?;
    out.push(b' ');
    put_str(&mut out, &f.reference_entity, 10, false, "reference entity")?;
    put_int(&mut out, f.reference_node, 10, "reference node")?;
    put_int(&mut out, f.reference_direction, 4, "reference direction")?;
    out.push(b'\n');
    // Record 7: FORMAT(3I10,3E13.5).
    put_int(&mut out, odt.code(), 10, "ordinate data type")?;
    put_int(&mut out, n as i64, 10, "number of points")?;
    put_int(&mut out, i64::from(even), 10, "abscissa spacing")?;
    put_e(&mut out, min, 13, 5, b'E');
    put_e(&mut out, inc, 13, 5, b'E');
    put_e(&mut out, f.z_axis_value, 13, 5, b'E');
    out.push(b'\n');
    for a in [
        &f.abscissa_axis,
        &f.ordinate_axis,
        &f.denominator_axis,
        &f.z_axis,
    ] {
        axis_record(&mut out, a)?;
    }
    w.write_all(&out)?;
    out.clear();

    match format {
        Format::Binary => {
            for k in 0..total {
                let v = value(k);
                if size == 8 {
                    out.extend_from_slice(&v.to_le_bytes());
                } else {
                    out.extend_from_slice(&(v as f32).to_le_bytes());
                }
            }
        }
        Format::Ascii => {
            // Per point layout of the standard: single precision 6E13.5 throughout; double
            // precision 4E20.12 (even), 2(E13.5,E20.12) (uneven real), E13.5,2E20.12 (uneven
            // complex). pyuff writes 12 significant digits as `%20.11e`, as do we.
            let per_line = if !odt.is_double() {
                6
            } else if even {
                4
            } else if im.is_some() {
                3
            } else {
                4
            };
            for k in 0..total {
                let v = value(k);
                let is_x = !even && k % vpp == 0;
                if !odt.is_double() || is_x {
                    put_e(&mut out, v, 13, 5, b'E');
                } else {
                    put_e(&mut out, v, 20, 11, b'E');
                }
                if (k + 1) % per_line == 0 || k + 1 == total {
                    out.push(b'\n');
                }
                if out.len() > 1 << 16 {
                    w.write_all(&out)?;
                    out.clear();
                }
            }
        }
    }
    out.extend_from_slice(b"    -1\n");
    w.write_all(&out)?;
    Ok(())
}

/// Writes nodes as dataset 2411: per node `4I10` (label, export CS, displacement CS, colour)
/// then `1P3D25.16` (coordinates, file length units).
pub fn write_2411(nodes: &[Node], w: &mut impl Write) -> Result<(), UffWriteError> {
    let mut out = Vec::with_capacity(200 + nodes.len() * 120);
    number_line(&mut out, 2411);
    for (k, nd) in nodes.iter().enumerate() {
        check_finite("node coordinates", &nd.xyz_file_units).map_err(|e| match e {
            UffWriteError::NonFinite { field, found, .. } => UffWriteError::NonFinite {
                field,
                index: k,
                found,
            },
            e => e,
        })?;
        put_int(&mut out, nd.id, 10, "node label")?;
        put_int(&mut out, nd.def_cs, 10, "export coordinate system")?;
        put_int(&mut out, nd.disp_cs, 10, "displacement coordinate system")?;
        put_int(&mut out, nd.color, 10, "color")?;
        out.push(b'\n');
        for c in nd.xyz_file_units {
            put_e(&mut out, c, 25, 16, b'D');
        }
        out.push(b'\n');
    }
    out.extend_from_slice(b"    -1\n");
    w.write_all(&out)?;
    Ok(())
}

/// Writes nodes as dataset 15: per node `4I10,1P3E13.5`.
pub fn write_15(nodes: &[Node], w: &mut impl Write) -> Result<(), UffWriteError> {
    let mut out = Vec::with_capacity(200 + nodes.len() * 90);
    number_line(&mut out, 15);
    for (k, nd) in nodes.iter().enumerate() {
        if let Some(&c) = nd.xyz_file_units.iter().find(|c| !c.is_finite()) {
            return Err(UffWriteError::NonFinite {
                field: "node coordinates",
                index: k,
                found: c,
            });
        }
        put_int(&mut out, nd.id, 10, "node label")?;
        put_int(&mut out, nd.def_cs, 10, "definition coordinate system")?;
        put_int(&mut out, nd.disp_cs, 10, "displacement coordinate system")?;
        put_int(&mut out, nd.color, 10, "color")?;
        for c in nd.xyz_file_units {
            put_e(&mut out, c, 13, 5, b'E');
        }
        out.push(b'\n');
    }
    out.extend_from_slice(b"    -1\n");
    w.write_all(&out)?;
    Ok(())
}

/// Writes units as dataset 164: `I10,20A1,I10` then the four factors as `1P3D25.17` (two
/// records).
pub fn write_164(u: &Units164, w: &mut impl Write) -> Result<(), UffWriteError> {
    check_finite(
        "unit factors",
        &[
            u.length_factor,
            u.force_factor,
            u.temperature_factor,
            u.temperature_offset,
        ],
    )?;
    let mut out = Vec::with_capacity(400);
    number_line(&mut out, 164);
    put_int(&mut out, i64::from(u.units_code), 10, "units code")?;
    put_str(&mut out, &u.description, 20, true, "units description")?;
    put_int(
        &mut out,
        i64::from(u.temperature_mode),
        10,
        "temperature mode",
    )?;
    out.push(b'\n');
    put_e(&mut out, u.length_factor, 25, 17, b'D');
    put_e(&mut out, u.force_factor, 25, 17, b'D');
    put_e(&mut out, u.temperature_factor, 25, 17, b'D');
    out.push(b'\n');
    put_e(&mut out, u.temperature_offset, 25, 17, b'D');
    out.push(b'\n');
    out.extend_from_slice(b"    -1\n");
    w.write_all(&out)?;
    Ok(())
}

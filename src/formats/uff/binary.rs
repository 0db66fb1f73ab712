//! Binary dataset 58b: the extended number line (`58b` byte order, floating-point format,
//! number of ASCII lines, number of bytes), the 11 ASCII header records, then the declared
//! number of bytes of IEEE 754 values (little or big endian, f32 for ordinate data types 2/5,
//! f64 for 4/6; every value of a point, abscissa included, in that size, as pyuff does).
//!
//! Real exports deviate: some put a line end, or a few other bytes, between the data and the
//! closing `-1` (e.g. Simcenter Test.Lab); some put the `-1` right after the data. The data are
//! read by the declared byte count, never by line, and whatever follows up to a line that ends
//! in `-1` is ignored.

use super::ascii::{excerpt, is_space, parse_int, trim, Lines};
use super::read::{parse_header_58, skip_to_delimiter, Ctx};
use super::{Function58, IssueKind, UffIssue};

/// The integer fields after the `b` of a binary dataset's number line:
/// `    58b     1     2          11        4096     0     0           0           0`
/// gives (byte order, floating-point format, number of ASCII lines, number of bytes).
fn binary_header(text: &[u8]) -> Option<[i64; 4]> {
    let b_at = text.iter().position(|&b| b == b'b' || b == b'B')?;
    let mut fields = text[b_at + 1..]
        .split(|&b| is_space(b))
        .filter(|t| !t.is_empty());
    let mut out = [0i64; 4];
    for v in &mut out {
        *v = parse_int(fields.next()?)?;
    }
    Some(out)
}

/// Skips a binary dataset of a number this reader does not decode, using the byte count of
/// its number line (the 58b layout, which the standard keeps for every binary dataset).
pub(super) fn skip_binary(
    cur: &mut Lines<'_>,
    text: &[u8],
    number_line: usize,
    ctx: Ctx,
) -> Result<(), UffIssue> {
    let Some([_, _, n_ascii, n_bytes]) = binary_header(text) else {
        skip_to_delimiter(cur);
        return Err(ctx.issue(
            number_line,
            IssueKind::BadBinaryHeader {
                expected: "4 integers after `b`: byte order, float format, ASCII lines, bytes",
                found: excerpt(text),
            },
        ));
    };
    for _ in 0..n_ascii.max(0) {
        if cur.next_line().is_none() {
            break;
        }
    }
    let to = usize::try_from(n_bytes).unwrap_or(usize::MAX);
    let avail = cur.s.len() - cur.pos;
    if to > avail {
        cur.advance_to(cur.s.len());
        return Err(ctx.issue(
            cur.line,
            IssueKind::Truncated {
                expected: format!("{n_bytes} bytes of binary data"),
                found: format!("{avail} bytes before the end of file"),
            },
        ));
    }
    cur.advance_to(cur.pos + to);
    if find_terminator(cur) {
        Ok(())
    } else {
        Err(ctx.issue(
            cur.line.saturating_sub(1),
            IssueKind::Truncated {
                expected: "a closing `-1` after the binary data".into(),
                found: "end of file".into(),
            },
        ))
    }
}

/// Reads one 58b dataset whose number line (`text`, on line `number_line`) has been consumed.
/// On error the cursor is left past the dataset where possible.
pub(super) fn read_58b(
    cur: &mut Lines<'_>,
    text: &[u8],
    number_line: usize,
    ctx: Ctx,
) -> Result<Function58, UffIssue> {
    let bad_header = |expected: &'static str| {
        ctx.issue(
            number_line,
            IssueKind::BadBinaryHeader {
                expected,
                found: excerpt(text),
            },
        )
    };
    let Some(ints) = binary_header(text) else {
        skip_to_delimiter(cur);
        return Err(bad_header(
            "4 integers after `58b`: byte order, float format, ASCII lines, bytes",
        ));
    };
    let (byte_order, fp_format, n_ascii, n_bytes) = (ints[0], ints[1], ints[2], ints[3]);
    if n_ascii != 11 {
        skip_to_delimiter(cur);
        return Err(bad_header("11 ASCII header lines (field 5)"));
    }
    // Header records.
    let first_line = cur.line;
    let mut recs: [&[u8]; 11] = [&[]; 11];
    for (k, r) in recs.iter_mut().enumerate() {
        match cur.next_line() {
            Some((_, t)) => *r = t,
            None => {
                return Err(ctx.issue(
                    cur.line.saturating_sub(1),
                    IssueKind::Truncated {
                        expected: "11 header records".into(),
                        found: format!("{k} before the end of file"),
                    },
                ))
            }
        }
    }
    let header = parse_header_58(&recs, first_line, ctx);
    let data_start = cur.pos;
    let data_line = cur.line;
    let avail = cur.s.len() - data_start;
    let declared = usize::try_from(n_bytes).unwrap_or(usize::MAX);
    // The byte count the header implies; pyuff declares points × value size even when a point
    // has 2 or 3 values, so a count that disagrees with the header is accepted if the implied
    // count is followed by the closing `-1`.
    let implied = header.as_ref().ok().map(|h| {
        let size = if h.f.ordinate_data_type.is_double() {
            8
        } else {
            4
        };
        h.f.num_points
            .saturating_mul(h.values_per_point())
            .saturating_mul(size)
    });
    let n_bytes = match implied {
        Some(im) if im != declared && im <= avail && closes_at(cur.s, data_start + im) => im,
        _ => declared,
    };
    if n_bytes > avail {
        cur.advance_to(cur.s.len());
        return Err(ctx.issue(
            data_line,
            IssueKind::Truncated {
                expected: format!("{} bytes of binary data", ints[3]),
                found: format!("{avail} bytes before the end of file"),
            },
        ));
    }
    let data = &cur.s[data_start..data_start + n_bytes];
    cur.advance_to(data_start + n_bytes);
    let closed = find_terminator(cur);
    let h = header?;
    let little = match byte_order {
        1 => true,
        2 => false,
        _ => return Err(bad_header("byte order 1 (little endian) or 2 (big endian)")),
    };
    if fp_format != 2 {
        return Err(bad_header("floating-point format 2 (IEEE 754)"));
    }
    if !closed {
        return Err(ctx.issue(
            cur.line.saturating_sub(1),
            IssueKind::Truncated {
                expected: "a closing `-1` after the binary data".into(),
                found: "end of file".into(),
            },
        ));
    }
    let size = if h.f.ordinate_data_type.is_double() {
        8
    } else {
        4
    };
    let vpp = h.values_per_point();
    let expected = h.f.num_points.saturating_mul(vpp);
    let found = n_bytes / size;
    if found != expected || n_bytes % size != 0 {
        return Err(ctx.issue(
            data_line,
            IssueKind::WrongValueCount {
                expected,
                points: h.f.num_points,
                found,
            },
        ));
    }
    let values: Vec<f64> = if size == 8 {
        data.chunks_exact(8)
            .map(|c| {
                let a: [u8; 8] = [c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]];
                if little {
                    f64::from_le_bytes(a)
                } else {
                    f64::from_be_bytes(a)
                }
            })
            .collect()
    } else {
        data.chunks_exact(4)
            .map(|c| {
                let a: [u8; 4] = [c[0], c[1], c[2], c[3]];
                f64::from(if little {
                    f32::from_le_bytes(a)
                } else {
                    f32::from_be_bytes(a)
                })
            })
            .collect()
    };
    if let Some(k) = values.iter().position(|v| !v.is_finite()) {
        let kind = if !h.even && k.is_multiple_of(vpp) {
            IssueKind::NonNumeric {
                value_index: k,
                found: values[k].to_string(),
            }
        } else {
            IssueKind::NonFiniteOrdinate {
                point: k / vpp,
                value: values[k],
            }
        };
        return Err(ctx.issue(data_line, kind));
    }
    Ok(h.into_function(&values, true, ctx))
}

/// Whether the bytes at `at` are (after blanks and line ends) a `-1` ending its line.
fn closes_at(s: &[u8], at: usize) -> bool {
    let mut i = at;
    while i < s.len() && is_space(s[i]) {
        i += 1;
    }
    s.get(i..i + 2) == Some(b"-1") && s.get(i + 2).is_none_or(|&b| is_space(b))
}

/// After the binary data: consumes lines until one whose text ends in a `-1` token (alone,
/// after blanks, or after stray bytes). Returns whether it was found.
fn find_terminator(cur: &mut Lines<'_>) -> bool {
    while let Some((_, t)) = cur.next_line() {
        let t = trim(t);
        if t == b"-1" || (t.ends_with(b"-1") && is_space(t[t.len() - 3])) {
            return true;
        }
    }
    false
}

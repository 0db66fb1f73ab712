//! Scanning of numbers in UFF ASCII records: Fortran `E`/`D` formatted floats (which can run
//! together with no blank between fixed-width fields), integers, fixed-width field slicing, and
//! line splitting that tolerates CRLF and trailing blanks.
//!
//! Hand-written because the standard's fields need Fortran semantics no crate offers: `D`
//! exponents and fields that touch (`-1.23456E+00-2.34567E+00`, `1.0E+001.0E+00`). The common
//! case (≤ 19 significant digits, decimal exponent within ±22) is converted exactly with one
//! IEEE multiplication or division (Clinger's fast path); anything else goes through
//! `f64::from_str`, so every result is correctly rounded.

/// Exact powers of ten representable in f64.
const POW10: [f64; 23] = [
    1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9, 1e10, 1e11, 1e12, 1e13, 1e14, 1e15, 1e16,
    1e17, 1e18, 1e19, 1e20, 1e21, 1e22,
];

#[inline]
pub(crate) fn is_space(b: u8) -> bool {
    matches!(b, b' ' | b'\t' | b'\r' | b'\n' | b'\x0c')
}

/// A number token that could not be read: byte range within the scanned slice.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct BadToken {
    pub start: usize,
    pub end: usize,
}

/// Scans the next number of `s` from `*pos`, skipping blanks and line ends. Returns `None` at the
/// end of `s`. `NaN`/`Inf` spellings are returned as such (the caller decides whether they are
/// acceptable). On a malformed token, `*pos` moves past it (to the next blank).
#[inline(always)]
pub(crate) fn next_number(s: &[u8], pos: &mut usize) -> Option<Result<f64, BadToken>> {
    let n = s.len();
    let mut i = *pos;
    while i < n && is_space(s[i]) {
        i += 1;
    }
    if i >= n {
        *pos = n;
        return None;
    }
    let start = i;
    let mut neg = false;
    if s[i] == b'+' || s[i] == b'-' {
        neg = s[i] == b'-';
        i += 1;
    }
    if let Some((mant, exp10, end)) = fast_e_field(s, i) {
        *pos = end;
        return Some(Ok(to_f64(mant, exp10, neg)
            .unwrap_or_else(|| slow_parse(&s[start..end]).unwrap_or(f64::NAN))));
    }
    let mut mant: u64 = 0;
    let mut exact = true;
    let (j, _) = digit_run(s, i, &mut mant, &mut exact);
    let mut any_digit = j > i;
    i = j;
    // Integer digits beyond the mantissa's capacity clear `exact`: the slow path rescans.
    let mut exp10: i64 = 0;
    if i < n && s[i] == b'.' {
        let j = i + 1;
        let (k, frac_digits) = digit_run(s, j, &mut mant, &mut exact);
        any_digit |= k > j;
        // Only the digits that entered the mantissa scale it (the rest made it inexact).
        exp10 -= frac_digits as i64;
        i = k;
    }
    if !any_digit {
        return Some(special_or_bad(s, start, pos));
    }
    let mut gave_back = false;
    if i < n && matches!(s[i], b'E' | b'e' | b'D' | b'd') {
        let mut j = i + 1;
        let mut eneg = false;
        if j < n && (s[j] == b'+' || s[j] == b'-') {
            eneg = s[j] == b'-';
            j += 1;
        }
        let dstart = j;
        while j < n && s[j].is_ascii_digit() {
            j += 1;
        }
        if j == dstart {
            return Some(bad_to_blank(s, start, pos));
        }
        // Touching fields: `1.0E+001.0E+00` scans as exponent digits `001` followed by `.`;
        // E-format mantissas have one digit before the point, so that digit is the next field's.
        if j < n && s[j] == b'.' && j - dstart >= 2 {
            j -= 1;
            gave_back = true;
        }
        let mut e: i64 = 0;
        for &d in &s[dstart..j] {
            e = (e * 10 + i64::from(d - b'0')).min(100_000);
        }
        exp10 += if eneg { -e } else { e };
        i = j;
    }
    // What may follow a number: a blank, the end, or the start of a touching field.
    if i < n && !(is_space(s[i]) || s[i] == b'+' || s[i] == b'-' || gave_back) {
        return Some(bad_to_blank(s, start, pos));
    }
    *pos = i;
    if exact {
        if let Some(v) = to_f64(mant, exp10, neg) {
            return Some(Ok(v));
        }
    }
    Some(slow_parse(&s[start..i]).ok_or(BadToken { start, end: i }))
}

/// `±mant · 10^exp10` when exactly computable with one IEEE operation (Clinger's fast path:
/// both operands exact, so the one rounding is the correct one), else `None`.
#[inline(always)]
fn to_f64(mant: u64, exp10: i64, neg: bool) -> Option<f64> {
    if mant == 0 {
        return Some(if neg { -0.0 } else { 0.0 });
    }
    if mant <= (1u64 << 53) && (-22..=22).contains(&exp10) {
        let m = mant as f64;
        let v = if exp10 >= 0 {
            m * POW10[exp10 as usize]
        } else {
            m / POW10[(-exp10) as usize]
        };
        return Some(if neg { -v } else { v });
    }
    None
}

#[inline(always)]
fn load8(s: &[u8], i: usize) -> Option<u64> {
    s.get(i..i.checked_add(8)?)
        .and_then(|b| <[u8; 8]>::try_from(b).ok())
        .map(u64::from_le_bytes)
}

/// Value of the first `nd` (< 8) digits of `chunk`.
#[inline(always)]
fn partial_digits(chunk: u64, nd: usize) -> u64 {
    if nd == 0 {
        0
    } else {
        parse_8_digits((chunk << (8 * (8 - nd))) | (0x3030_3030_3030_3030 >> (8 * nd)))
    }
}

/// Fast path for the standard's E-format fields after the sign: `d.ddd…d(E|e|D|d)(+|-)dd`
/// with 1 to 15 fraction digits and a two-digit exponent, ending at a blank, a sign (touching
/// field) or the end. Returns (mantissa digits, decimal exponent, end), or `None` for the
/// general scanner to handle (other shapes, touching fields after the exponent, end of input
/// within 8 bytes).
#[inline(always)]
fn fast_e_field(s: &[u8], i: usize) -> Option<(u64, i64, usize)> {
    let d0 = s.get(i)?.wrapping_sub(b'0');
    if d0 > 9 || *s.get(i + 1)? != b'.' {
        return None;
    }
    let c1 = load8(s, i + 2)?;
    let n1 = leading_digits(c1);
    let (mant, k) = if n1 < 8 {
        (u64::from(d0) * POW10_U64[n1] + partial_digits(c1, n1), n1)
    } else {
        let c2 = load8(s, i + 10)?;
        let n2 = leading_digits(c2);
        if n2 > 7 {
            return None;
        }
        let head = u64::from(d0) * 100_000_000 + parse_8_digits(c1);
        (head * POW10_U64[n2] + partial_digits(c2, n2), 8 + n2)
    };
    if k == 0 {
        return None;
    }
    let j = i + 2 + k;
    if !matches!(*s.get(j)?, b'E' | b'e' | b'D' | b'd') {
        return None;
    }
    let eneg = match *s.get(j + 1)? {
        b'-' => true,
        b'+' => false,
        _ => return None,
    };
    let a = s.get(j + 2)?.wrapping_sub(b'0');
    let b = s.get(j + 3)?.wrapping_sub(b'0');
    if a > 9 || b > 9 {
        return None;
    }
    let end = j + 4;
    if let Some(&c) = s.get(end) {
        if !(is_space(c) || c == b'-' || c == b'+') {
            return None;
        }
    }
    let e = i64::from(a * 10 + b);
    Some((mant, if eneg { -e } else { e } - k as i64, end))
}

const POW10_U64: [u64; 9] = [
    1,
    10,
    100,
    1_000,
    10_000,
    100_000,
    1_000_000,
    10_000_000,
    100_000_000,
];

/// Number of leading ASCII digits among the 8 bytes of `v` (first byte lowest). SWAR: a byte's
/// high bit is set in the mask iff it is not a digit; borrows and carries only move upwards,
/// so the lowest flagged byte is the first non-digit.
#[inline(always)]
fn leading_digits(v: u64) -> usize {
    let a = v.wrapping_add(0x4646_4646_4646_4646);
    let b = v.wrapping_sub(0x3030_3030_3030_3030);
    let m = (a | b) & 0x8080_8080_8080_8080;
    (m.trailing_zeros() / 8) as usize
}

/// Scans a run of decimal digits from `i` into `mant` (8 at a time where possible). Digits
/// that no longer fit 18 significant digits clear `exact` and are not counted. Returns the
/// index after the run and the number of digits that entered `mant`.
#[inline(always)]
fn digit_run(s: &[u8], mut i: usize, mant: &mut u64, exact: &mut bool) -> (usize, usize) {
    let mut used = 0usize;
    while *mant < 10_000_000_000 {
        let Some(chunk) = load8(s, i) else {
            break;
        };
        let nd = leading_digits(chunk);
        if nd == 0 {
            return (i, used);
        }
        let v = if nd == 8 {
            parse_8_digits(chunk)
        } else {
            partial_digits(chunk, nd)
        };
        *mant = *mant * POW10_U64[nd] + v;
        used += nd;
        i += nd;
        if nd < 8 {
            return (i, used);
        }
    }
    while i < s.len() && s[i].is_ascii_digit() {
        if *mant < 100_000_000_000_000_000 {
            *mant = *mant * 10 + u64::from(s[i] - b'0');
            used += 1;
        } else {
            *exact = false;
        }
        i += 1;
    }
    (i, used)
}

/// Value of 8 ASCII digits (first digit in the lowest byte of `v`), SWAR as in fast_float.
#[inline]
fn parse_8_digits(v: u64) -> u64 {
    const MASK: u64 = 0x0000_00FF_0000_00FF;
    const MUL1: u64 = 0x000F_4240_0000_0064; // 100 + (1_000_000 << 32)
    const MUL2: u64 = 0x0000_2710_0000_0001; // 1 + (10_000 << 32)
    let mut v = v.wrapping_sub(0x3030_3030_3030_3030);
    v = v.wrapping_mul(10).wrapping_add(v >> 8);
    (v & MASK)
        .wrapping_mul(MUL1)
        .wrapping_add(((v >> 16) & MASK).wrapping_mul(MUL2))
        >> 32
}

/// Correctly rounded conversion of a token already checked to be `[+-]d*[.d*][(E|D)[+-]d+]`.
#[cold]
fn slow_parse(tok: &[u8]) -> Option<f64> {
    let text: String = tok
        .iter()
        .map(|&b| match b {
            b'D' | b'd' => 'e',
            b => char::from(b),
        })
        .collect();
    text.parse::<f64>().ok()
}

#[cold]
fn special_or_bad(s: &[u8], start: usize, pos: &mut usize) -> Result<f64, BadToken> {
    let mut end = start;
    while end < s.len() && !is_space(s[end]) {
        end += 1;
    }
    *pos = end;
    let tok = &s[start..end];
    let (neg, body) = match tok.first() {
        Some(b'-') => (true, &tok[1..]),
        Some(b'+') => (false, &tok[1..]),
        _ => (false, tok),
    };
    let v = if body.eq_ignore_ascii_case(b"nan") {
        f64::NAN
    } else if body.eq_ignore_ascii_case(b"inf") || body.eq_ignore_ascii_case(b"infinity") {
        f64::INFINITY
    } else {
        return Err(BadToken { start, end });
    };
    Ok(if neg { -v } else { v })
}

#[cold]
fn bad_to_blank(s: &[u8], start: usize, pos: &mut usize) -> Result<f64, BadToken> {
    let mut end = start;
    while end < s.len() && !is_space(s[end]) {
        end += 1;
    }
    *pos = end;
    Err(BadToken { start, end })
}

/// Trims blanks (space, tab, CR, LF) from both ends.
pub(crate) fn trim(s: &[u8]) -> &[u8] {
    let mut a = 0;
    let mut b = s.len();
    while a < b && is_space(s[a]) {
        a += 1;
    }
    while b > a && is_space(s[b - 1]) {
        b -= 1;
    }
    &s[a..b]
}

/// Bytes `[from, from + width)` of a record, cut at the record's end (short lines are
/// implicitly blank-padded, as Fortran reads them).
pub(crate) fn field(rec: &[u8], from: usize, width: usize) -> &[u8] {
    let a = from.min(rec.len());
    let b = from.saturating_add(width).min(rec.len());
    &rec[a..b]
}

/// Parses an integer field; a blank field reads as `Some(0)` (Fortran `I` semantics).
pub(crate) fn int_field(f: &[u8]) -> Option<i64> {
    let t = trim(f);
    if t.is_empty() {
        return Some(0);
    }
    parse_int(t)
}

/// Parses `[+-]digits` (no blanks) into an i64, `None` on anything else or overflow.
pub(crate) fn parse_int(t: &[u8]) -> Option<i64> {
    let (neg, digits) = match t.first()? {
        b'-' => (true, &t[1..]),
        b'+' => (false, &t[1..]),
        _ => (false, t),
    };
    if digits.is_empty() {
        return None;
    }
    let mut v: i64 = 0;
    for &d in digits {
        if !d.is_ascii_digit() {
            return None;
        }
        v = v.checked_mul(10)?.checked_add(i64::from(d - b'0'))?;
    }
    Some(if neg { -v } else { v })
}

/// A text field as a `String` (lossy UTF-8), blanks trimmed.
pub(crate) fn text_field(f: &[u8]) -> String {
    String::from_utf8_lossy(trim(f)).into_owned()
}

/// Up to 80 characters of a record for an error message.
pub(crate) fn excerpt(s: &[u8]) -> String {
    let t = trim(s);
    let t = &t[..t.len().min(80)];
    String::from_utf8_lossy(t).into_owned()
}

/// Line iterator over a byte slice that tracks 1-based line numbers (a line number is 1 + the
/// number of `\n` bytes before it) and strips `\n` / `\r\n`.
pub(crate) struct Lines<'a> {
    pub s: &'a [u8],
    /// Offset of the next line.
    pub pos: usize,
    /// 1-based number of the next line.
    pub line: usize,
}

impl<'a> Lines<'a> {
    pub fn new(s: &'a [u8]) -> Self {
        Lines { s, pos: 0, line: 1 }
    }

    /// Next line as (line number, text without line end), or `None` at the end.
    pub fn next_line(&mut self) -> Option<(usize, &'a [u8])> {
        if self.pos >= self.s.len() {
            return None;
        }
        let rest = &self.s[self.pos..];
        let (text, adv) = match memchr::memchr(b'\n', rest) {
            Some(k) => (&rest[..k], k + 1),
            None => (rest, rest.len()),
        };
        let text = text.strip_suffix(b"\r").unwrap_or(text);
        let no = self.line;
        self.pos += adv;
        self.line += 1;
        Some((no, text))
    }

    /// Moves to byte offset `to` (≥ pos), counting the line ends passed over.
    pub fn advance_to(&mut self, to: usize) {
        let to = to.min(self.s.len());
        if to > self.pos {
            self.line += memchr::memchr_iter(b'\n', &self.s[self.pos..to]).count();
            self.pos = to;
        }
    }
}

/// Whether a line is a dataset delimiter: `-1` with optional blanks around it.
pub(crate) fn is_delimiter(text: &[u8]) -> bool {
    trim(text) == b"-1"
}

/// Line number of byte `offset` in `s`, given that `s` starts on line `first_line`.
pub(crate) fn line_at(s: &[u8], offset: usize, first_line: usize) -> usize {
    first_line + memchr::memchr_iter(b'\n', &s[..offset.min(s.len())]).count()
}

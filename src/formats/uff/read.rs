//! The UFF reader: splits a file's bytes into `-1`-delimited datasets and decodes 58 (ASCII),
//! 58b (via `binary`), 55 (via `ds55`), 2411, 15 and 164; lists every other dataset as
//! skipped; turns every malformed dataset into an [`UffIssue`] and carries on with the next.

use super::ascii::{
    excerpt, field, int_field, is_delimiter, line_at, next_number, parse_int, text_field, trim,
    BadToken, Lines,
};
use super::{
    Abscissa, AxisSpec, Dataset, Function58, FunctionType, IssueKind, Node, NodeSet, NodeSource,
    Ordinate, OrdinateDataType, SkippedDataset, UffError, UffFile, UffIssue, Units164,
};

/// Where a dataset is: its opening-delimiter line and its position in the file.
#[derive(Clone, Copy)]
pub(super) struct Ctx {
    pub open_line: usize,
    pub number: u32,
    pub index: usize,
}

impl Ctx {
    pub fn issue(&self, line: usize, kind: IssueKind) -> UffIssue {
        UffIssue {
            line,
            number: Some(self.number),
            index: self.index,
            kind,
        }
    }
}

/// Parses a whole Universal File held in memory.
///
/// Returns every dataset that could be read, one issue per dataset that could not (the line,
/// dataset number and index, what was expected and what was found), and the list of datasets
/// of other numbers (skipped). Fails only if the bytes hold no dataset at all.
pub fn parse(bytes: &[u8]) -> Result<UffFile, UffError> {
    let mut out = UffFile::default();
    let mut cur = Lines::new(bytes);
    // A UTF-8 byte-order mark (some Windows exporters) is not part of the first line.
    if bytes.starts_with(b"\xEF\xBB\xBF") {
        cur.pos = 3;
    }
    let mut index = 0usize;
    let mut in_stray_run = false;
    while let Some((ln, text)) = cur.next_line() {
        if trim(text).is_empty() {
            continue;
        }
        if !is_delimiter(text) {
            if !in_stray_run {
                out.issues.push(UffIssue {
                    line: ln,
                    number: None,
                    index,
                    kind: IssueKind::StrayText {
                        found: excerpt(text),
                    },
                });
                in_stray_run = true;
            }
            continue;
        }
        in_stray_run = false;
        // Opening delimiter; repeated delimiters (`-1` / `-1`) open at the last one.
        let mut open_line = ln;
        let number_line = loop {
            match cur.next_line() {
                None => break None,
                Some((l, t)) if is_delimiter(t) => open_line = l,
                Some((_, t)) if trim(t).is_empty() => {}
                Some(x) => break Some(x),
            }
        };
        let Some((nl, ntext)) = number_line else {
            break;
        };
        let this_index = index;
        index += 1;
        let Some((number, binary)) = parse_number_line(ntext) else {
            out.issues.push(UffIssue {
                line: nl,
                number: None,
                index: this_index,
                kind: IssueKind::BadNumberLine {
                    found: excerpt(ntext),
                },
            });
            skip_to_delimiter(&mut cur);
            continue;
        };
        let ctx = Ctx {
            open_line,
            number,
            index: this_index,
        };
        if number == 58 && binary {
            match super::binary::read_58b(&mut cur, ntext, nl, ctx) {
                Ok(f) => out.datasets.push(Dataset::Function(f)),
                Err(issue) => out.issues.push(issue),
            }
            continue;
        }
        if binary {
            match super::binary::skip_binary(&mut cur, ntext, nl, ctx) {
                Ok(()) => out.skipped.push(SkippedDataset {
                    number,
                    line: open_line,
                    index: this_index,
                }),
                Err(issue) => out.issues.push(issue),
            }
            continue;
        }
        if number == 58 {
            match read_58_ascii(&mut cur, ctx) {
                Ok(f) => out.datasets.push(Dataset::Function(f)),
                Err(issue) => out.issues.push(issue),
            }
            continue;
        }
        let body_start = cur.pos;
        let body_line = cur.line;
        let mut body_end = None;
        loop {
            let before = cur.pos;
            let Some((_, t)) = cur.next_line() else {
                break;
            };
            if is_delimiter(t) {
                body_end = Some(before);
                break;
            }
        }
        let Some(body_end) = body_end else {
            out.issues.push(ctx.issue(
                cur.line.saturating_sub(1).max(nl),
                IssueKind::Truncated {
                    expected: "a closing `-1` delimiter line".into(),
                    found: "end of file".into(),
                },
            ));
            break;
        };
        let body = &bytes[body_start..body_end];
        let result = match number {
            2411 => parse_nodes(body, body_line, ctx, NodeSource::Ds2411).map(Dataset::Nodes),
            15 => parse_nodes(body, body_line, ctx, NodeSource::Ds15).map(Dataset::Nodes),
            164 => parse_164(body, body_line, ctx).map(Dataset::Units),
            55 => super::ds55::parse_55(body, body_line, ctx).map(Dataset::NodalData),
            _ => {
                out.skipped.push(SkippedDataset {
                    number,
                    line: open_line,
                    index: this_index,
                });
                continue;
            }
        };
        match result {
            Ok(d) => out.datasets.push(d),
            Err(issue) => out.issues.push(issue),
        }
    }
    if !out.issues.is_empty() {
        // An issue found at the end of the input names the input's last line.
        let last_line = 1 + memchr::memchr_iter(b'\n', bytes).count();
        for i in &mut out.issues {
            i.line = i.line.clamp(1, last_line);
        }
    }
    if index == 0 {
        return Err(if trim(bytes).is_empty() {
            UffError::Empty
        } else {
            let first = bytes.split(|&b| b == b'\n').next().unwrap_or(&[]);
            UffError::NotUff {
                first_line: excerpt(first),
            }
        });
    }
    Ok(out)
}

/// Dataset number line: `[blanks]digits[b ...]`. Returns (number, binary flag).
fn parse_number_line(text: &[u8]) -> Option<(u32, bool)> {
    let mut i = 0;
    while i < text.len() && text[i] == b' ' {
        i += 1;
    }
    let s = i;
    while i < text.len() && text[i].is_ascii_digit() {
        i += 1;
    }
    if i == s || i - s > 9 {
        return None;
    }
    let number = parse_int(&text[s..i])? as u32;
    let binary = matches!(text.get(i), Some(b'b' | b'B'));
    Some((number, binary))
}

/// Consumes lines up to and including the next delimiter.
pub(super) fn skip_to_delimiter(cur: &mut Lines<'_>) {
    while let Some((_, t)) = cur.next_line() {
        if is_delimiter(t) {
            break;
        }
    }
}

/// The 11 header records of dataset 58 (ID lines 1–5, records 6–11): the dataset with its
/// data records still to read.
pub(super) struct Header58 {
    /// Every header field; `abscissa` holds the even spacing (or an empty uneven list) and
    /// `ordinate` is empty until the data are read.
    pub f: Function58,
    pub even: bool,
}

impl Header58 {
    /// Values per point in the data records: x (if uneven) + 1 (real) or 2 (complex).
    pub fn values_per_point(&self) -> usize {
        usize::from(!self.even)
            + if self.f.ordinate_data_type.is_complex() {
                2
            } else {
                1
            }
    }

    /// Builds the dataset from the flat list of data values (already checked for count).
    pub fn into_function(self, values: &[f64], binary: bool, ctx: Ctx) -> Function58 {
        let vpp = self.values_per_point();
        let (xs, ordinate) = split_values(
            values,
            self.f.num_points,
            vpp,
            self.even,
            self.f.ordinate_data_type,
        );
        self.into_function_parts(xs, ordinate, binary, ctx)
    }

    /// Builds the dataset from the uneven abscissa (empty if even) and the ordinate.
    pub fn into_function_parts(
        self,
        abscissa: Vec<f64>,
        ordinate: Ordinate,
        binary: bool,
        ctx: Ctx,
    ) -> Function58 {
        let mut f = self.f;
        if !self.even {
            f.abscissa = Abscissa::Uneven(abscissa);
        }
        f.ordinate = ordinate;
        f.binary = binary;
        f.line = ctx.open_line;
        f
    }
}

fn split_values(
    values: &[f64],
    n: usize,
    vpp: usize,
    even: bool,
    odt: OrdinateDataType,
) -> (Vec<f64>, Ordinate) {
    let off = usize::from(!even);
    let x: Vec<f64> = if even {
        Vec::new()
    } else {
        values.chunks_exact(vpp).map(|c| c[0]).collect()
    };
    debug_assert_eq!(values.len(), n * vpp);
    let ord = if odt.is_complex() {
        let mut re = Vec::with_capacity(n);
        let mut im = Vec::with_capacity(n);
        for c in values.chunks_exact(vpp) {
            re.push(c[off]);
            im.push(c[off + 1]);
        }
        Ordinate::Complex { re, im }
    } else if even {
        Ordinate::Real(values.to_vec())
    } else {
        Ordinate::Real(values.chunks_exact(vpp).map(|c| c[off]).collect())
    };
    (x, ord)
}

/// Parses header records 1–11 of dataset 58; `recs[k]` is record k+1, `first_line` its line.
pub(super) fn parse_header_58(
    recs: &[&[u8]; 11],
    first_line: usize,
    ctx: Ctx,
) -> Result<Header58, UffIssue> {
    let id_lines = [
        text_field(recs[0]),
        text_field(recs[1]),
        text_field(recs[2]),
        text_field(recs[3]),
        text_field(recs[4]),
    ];
    // Record 6: FORMAT(2(I5,I10),2(1X,10A1,I10,I4)).
    let r6 = recs[5];
    let l6 = first_line + 5;
    let fixed = [
        (0, 5, "function type"),
        (5, 10, "function id"),
        (15, 5, "version number"),
        (20, 10, "load case"),
        (41, 10, "response node"),
        (51, 4, "response direction"),
        (66, 10, "reference node"),
        (76, 4, "reference direction"),
    ];
    let mut ints = [0i64; 8];
    let mut fixed_ok = true;
    for (k, &(from, w, _)) in fixed.iter().enumerate() {
        match int_field(field(r6, from, w)) {
            Some(v) => ints[k] = v,
            None => fixed_ok = false,
        }
    }
    let (resp_ent, ref_ent);
    if fixed_ok {
        resp_ent = text_field(field(r6, 30, 11));
        ref_ent = text_field(field(r6, 55, 11));
    } else {
        // Not in the standard's columns: accept 10 blank-separated fields.
        let toks: Vec<&[u8]> = r6
            .split(|b| super::ascii::is_space(*b))
            .filter(|t| !t.is_empty())
            .collect();
        let pos = [0, 1, 2, 3, 5, 6, 8, 9];
        let parsed: Option<Vec<i64>> = if toks.len() == 10 {
            pos.iter().map(|&p| parse_int(toks[p])).collect()
        } else {
            None
        };
        let Some(parsed) = parsed else {
            let bad = fixed
                .iter()
                .find(|&&(from, w, _)| int_field(field(r6, from, w)).is_none())
                .copied()
                .unwrap_or(fixed[0]);
            return Err(ctx.issue(
                l6,
                IssueKind::BadField {
                    record: 6,
                    field: bad.2,
                    expected: "an integer in the standard's columns",
                    found: excerpt(field(r6, bad.0, bad.1)),
                },
            ));
        };
        ints.copy_from_slice(&parsed);
        resp_ent = String::from_utf8_lossy(toks[4]).into_owned();
        ref_ent = String::from_utf8_lossy(toks[7]).into_owned();
    }
    // Record 7: FORMAT(3I10,3E13.5).
    let r7 = recs[6];
    let l7 = first_line + 6;
    let mut vals = [0f64; 6];
    let names = [
        "ordinate data type",
        "number of points",
        "abscissa spacing",
        "abscissa minimum",
        "abscissa increment",
        "z-axis value",
    ];
    let mut p = 0;
    for (k, v) in vals.iter_mut().enumerate() {
        match next_number(r7, &mut p) {
            Some(Ok(x)) if x.is_finite() && (k >= 3 || x.fract() == 0.0) => *v = x,
            Some(Ok(x)) => {
                return Err(ctx.issue(
                    l7,
                    IssueKind::BadField {
                        record: 7,
                        field: names[k],
                        expected: if k < 3 {
                            "an integer"
                        } else {
                            "a finite number"
                        },
                        found: x.to_string(),
                    },
                ))
            }
            Some(Err(BadToken { start, end })) => {
                return Err(ctx.issue(
                    l7,
                    IssueKind::BadField {
                        record: 7,
                        field: names[k],
                        expected: "a number",
                        found: excerpt(&r7[start..end]),
                    },
                ))
            }
            None => {
                return Err(ctx.issue(
                    l7,
                    IssueKind::BadField {
                        record: 7,
                        field: names[k],
                        expected: "6 fields (3 integers, 3 reals)",
                        found: format!("{k} fields"),
                    },
                ))
            }
        }
    }
    let odt_code = vals[0] as i64;
    let Some(ordinate_data_type) = OrdinateDataType::from_code(odt_code) else {
        return Err(ctx.issue(l7, IssueKind::UnknownOrdinateDataType { found: odt_code }));
    };
    if vals[1] < 0.0 || vals[1] > 1e12 {
        return Err(ctx.issue(
            l7,
            IssueKind::BadField {
                record: 7,
                field: names[1],
                expected: "a non-negative count",
                found: vals[1].to_string(),
            },
        ));
    }
    let spacing = vals[2] as i64;
    let even = match spacing {
        0 => false,
        1 => true,
        s => return Err(ctx.issue(l7, IssueKind::UnknownSpacing { found: s })),
    };
    // Records 8–11: FORMAT(I10,3I5,2(1X,20A1)).
    let mut axes: [AxisSpec; 4] = Default::default();
    for (k, axis) in axes.iter_mut().enumerate() {
        let r = recs[7 + k];
        let ln = first_line + 7 + k;
        let mut iv = [0i64; 4];
        let widths = [(0, 10), (10, 5), (15, 5), (20, 5)];
        let fnames = [
            "specific data type",
            "length units exponent",
            "force units exponent",
            "temperature units exponent",
        ];
        for (j, &(from, w)) in widths.iter().enumerate() {
            iv[j] = int_field(field(r, from, w)).ok_or_else(|| {
                ctx.issue(
                    ln,
                    IssueKind::BadField {
                        record: 8 + k,
                        field: fnames[j],
                        expected: "an integer",
                        found: excerpt(field(r, from, w)),
                    },
                )
            })?;
        }
        *axis = AxisSpec {
            spec_data_type: iv[0],
            length_exp: iv[1],
            force_exp: iv[2],
            temperature_exp: iv[3],
            label: text_field(field(r, 25, 21)),
            units_label: text_field(field(r, 46, 21)),
        };
    }
    let [abscissa_axis, ordinate_axis, denominator_axis, z_axis] = axes;
    Ok(Header58 {
        f: Function58 {
            id_lines,
            function_type: FunctionType::from_code(ints[0]),
            function_id: ints[1],
            version: ints[2],
            load_case: ints[3],
            response_entity: resp_ent,
            response_node: ints[4],
            response_direction: ints[5],
            reference_entity: ref_ent,
            reference_node: ints[6],
            reference_direction: ints[7],
            ordinate_data_type,
            num_points: vals[1] as usize,
            z_axis_value: vals[5],
            abscissa_axis,
            ordinate_axis,
            denominator_axis,
            z_axis,
            abscissa: if even {
                Abscissa::Even {
                    min: vals[3],
                    increment: vals[4],
                }
            } else {
                Abscissa::Uneven(Vec::new())
            },
            ordinate: Ordinate::Real(Vec::new()),
            binary: false,
            line: ctx.open_line,
        },
        even,
    })
}

/// Reads one ASCII dataset 58 whose number line has been consumed, up to and including its
/// closing `-1`. The data are scanned once: the closing delimiter is recognised by the number
/// scanner (a `-1` alone on its line), not by a separate pass over lines.
fn read_58_ascii(cur: &mut Lines<'_>, ctx: Ctx) -> Result<Function58, UffIssue> {
    let first_line = cur.line;
    let mut recs: [&[u8]; 11] = [&[]; 11];
    for (k, r) in recs.iter_mut().enumerate() {
        match cur.next_line() {
            Some((_, t)) if !is_delimiter(t) => *r = t,
            next => {
                let line = next.map_or(cur.line.saturating_sub(1).max(first_line), |(l, _)| l);
                return Err(ctx.issue(
                    line,
                    IssueKind::Truncated {
                        expected: "11 header records".into(),
                        found: format!(
                            "{k} before the {}",
                            if next.is_some() {
                                "closing `-1`"
                            } else {
                                "end of file"
                            }
                        ),
                    },
                ));
            }
        }
    }
    let h = match parse_header_58(&recs, first_line, ctx) {
        Ok(h) => h,
        Err(e) => {
            skip_to_delimiter(cur);
            return Err(e);
        }
    };
    let s = cur.s;
    let n = s.len();
    let data_start = cur.pos;
    let data_line = cur.line;
    let line_of = |at: usize| line_at(&s[data_start..], at - data_start, data_line);
    let vpp = h.values_per_point();
    let expected = h.f.num_points.saturating_mul(vpp);
    // Capacity bounded by what the bytes can hold (a hostile count must not allocate).
    let cap = h.f.num_points.min((n - data_start) / (2 * vpp) + 1);
    let mut xs = Vec::with_capacity(if h.even { 0 } else { cap });
    let mut re = Vec::with_capacity(cap);
    let mut im = Vec::with_capacity(if h.f.ordinate_data_type.is_complex() {
        cap
    } else {
        0
    });
    let first_component = usize::from(h.even);
    let mut pos = data_start;
    let mut found = 0usize;
    let mut slot = 0usize;
    let mut last_start = data_start;
    let mut first_err: Option<UffIssue> = None;
    loop {
        while pos < n && super::ascii::is_space(s[pos]) {
            pos += 1;
        }
        if pos >= n {
            cur.advance_to(n);
            return Err(ctx.issue(
                cur.line.saturating_sub(1),
                IssueKind::Truncated {
                    expected: "a closing `-1` delimiter line".into(),
                    found: "end of file".into(),
                },
            ));
        }
        if s[pos] == b'-' && delimiter_at(s, pos) {
            cur.advance_to(pos);
            cur.next_line();
            break;
        }
        let start = pos;
        match next_number(s, &mut pos) {
            Some(Ok(v)) => {
                if first_err.is_none() {
                    if !v.is_finite() {
                        let kind = if slot + first_component == 0 {
                            IssueKind::NonNumeric {
                                value_index: found,
                                found: v.to_string(),
                            }
                        } else {
                            IssueKind::NonFiniteOrdinate {
                                point: found / vpp,
                                value: v,
                            }
                        };
                        first_err = Some(ctx.issue(line_of(start), kind));
                    } else if found < expected {
                        match slot + first_component {
                            0 => xs.push(v),
                            1 => re.push(v),
                            _ => im.push(v),
                        }
                    }
                }
            }
            Some(Err(BadToken { start, end })) => {
                if first_err.is_none() {
                    first_err = Some(ctx.issue(
                        line_of(start),
                        IssueKind::NonNumeric {
                            value_index: found,
                            found: excerpt(&s[start..end]),
                        },
                    ));
                }
            }
            None => pos = n,
        }
        last_start = start;
        found += 1;
        slot += 1;
        if slot == vpp {
            slot = 0;
        }
    }
    if let Some(e) = first_err {
        return Err(e);
    }
    if found != expected {
        return Err(ctx.issue(
            line_of(last_start),
            IssueKind::WrongValueCount {
                expected,
                points: h.f.num_points,
                found,
            },
        ));
    }
    let ordinate = if h.f.ordinate_data_type.is_complex() {
        Ordinate::Complex { re, im }
    } else {
        Ordinate::Real(re)
    };
    Ok(h.into_function_parts(xs, ordinate, false, ctx))
}

/// Whether `s[at..]` starts a delimiter line: `-1` with only blanks before it on its line and
/// only blanks after it up to the line end.
fn delimiter_at(s: &[u8], at: usize) -> bool {
    if s.get(at..at + 2) != Some(b"-1") {
        return false;
    }
    let mut j = at + 2;
    while j < s.len() && s[j] != b'\n' {
        if !matches!(s[j], b' ' | b'\t' | b'\r') {
            return false;
        }
        j += 1;
    }
    let mut i = at;
    while i > 0 && matches!(s[i - 1], b' ' | b'\t') {
        i -= 1;
    }
    i == 0 || s[i - 1] == b'\n'
}

/// Start of the token that ends at `end` (for error positions).
fn token_start(s: &[u8], end: usize) -> usize {
    let mut a = end.min(s.len());
    while a > 0 && !super::ascii::is_space(s[a - 1]) {
        a -= 1;
    }
    a
}

/// Datasets 2411 (two records per node: 4I10 / 3D25.16) and 15 (one record: 4I10,3E13.5):
/// seven numbers per node in the same order.
fn parse_nodes(
    body: &[u8],
    body_line: usize,
    ctx: Ctx,
    source: NodeSource,
) -> Result<NodeSet, UffIssue> {
    let mut nodes = Vec::with_capacity(body.len() / 80 + 1);
    let mut pos = 0;
    let mut vals = [0f64; 7];
    let mut k = 0usize;
    let mut total = 0usize;
    while let Some(r) = next_number(body, &mut pos) {
        let start = token_start(body, pos);
        let v = match r {
            Ok(v) if v.is_finite() && (k >= 4 || (v.fract() == 0.0 && v.abs() < 9.0e15)) => v,
            Ok(v) => {
                return Err(ctx.issue(
                    line_at(body, start, body_line),
                    IssueKind::NonNumeric {
                        value_index: total,
                        found: format!(
                            "{v} where {} was expected",
                            if k < 4 {
                                "an integer"
                            } else {
                                "a finite number"
                            }
                        ),
                    },
                ))
            }
            Err(BadToken { start, end }) => {
                return Err(ctx.issue(
                    line_at(body, start, body_line),
                    IssueKind::NonNumeric {
                        value_index: total,
                        found: excerpt(&body[start..end]),
                    },
                ))
            }
        };
        vals[k] = v;
        k += 1;
        total += 1;
        if k == 7 {
            nodes.push(Node {
                id: vals[0] as i64,
                def_cs: vals[1] as i64,
                disp_cs: vals[2] as i64,
                color: vals[3] as i64,
                xyz_file_units: [vals[4], vals[5], vals[6]],
            });
            k = 0;
        }
    }
    if k != 0 {
        return Err(ctx.issue(
            line_at(body, body.len(), body_line),
            IssueKind::WrongValueCount {
                expected: (nodes.len() + 1) * 7,
                points: nodes.len() + 1,
                found: total,
            },
        ));
    }
    Ok(NodeSet {
        source,
        nodes,
        line: ctx.open_line,
    })
}

/// Dataset 164: FORMAT(I10,20A1,I10) then FORMAT(3D25.17) (4 factors over 2 records).
fn parse_164(body: &[u8], body_line: usize, ctx: Ctx) -> Result<Units164, UffIssue> {
    let mut cur = Lines::new(body);
    let Some((_, r1)) = cur.next_line() else {
        return Err(ctx.issue(
            body_line,
            IssueKind::Truncated {
                expected: "record 1 (units code, description, temperature mode)".into(),
                found: "the closing `-1`".into(),
            },
        ));
    };
    let bad = |field: &'static str, f: &[u8]| {
        ctx.issue(
            body_line,
            IssueKind::BadField {
                record: 1,
                field,
                expected: "an integer",
                found: excerpt(f),
            },
        )
    };
    let units_code =
        int_field(field(r1, 0, 10)).ok_or_else(|| bad("units code", field(r1, 0, 10)))?;
    let temperature_mode =
        int_field(field(r1, 30, 10)).ok_or_else(|| bad("temperature mode", field(r1, 30, 10)))?;
    let description = text_field(field(r1, 10, 20));
    let rest = &body[cur.pos..];
    let rest_line = body_line + 1;
    let mut f = [0f64; 4];
    let names = ["length", "force", "temperature", "temperature offset"];
    let mut pos = 0;
    for (k, slot) in f.iter_mut().enumerate() {
        match next_number(rest, &mut pos) {
            Some(Ok(v)) if v.is_finite() && (k == 3 || v != 0.0) => *slot = v,
            Some(Ok(v)) => {
                return Err(ctx.issue(
                    line_at(rest, token_start(rest, pos), rest_line),
                    IssueKind::BadField {
                        record: 2 + k / 3,
                        field: names[k],
                        expected: "a finite, non-zero conversion factor",
                        found: v.to_string(),
                    },
                ))
            }
            Some(Err(BadToken { start, end })) => {
                return Err(ctx.issue(
                    line_at(rest, start, rest_line),
                    IssueKind::BadField {
                        record: 2 + k / 3,
                        field: names[k],
                        expected: "a number",
                        found: excerpt(&rest[start..end]),
                    },
                ))
            }
            None => {
                return Err(ctx.issue(
                    line_at(rest, rest.len(), rest_line),
                    IssueKind::WrongValueCount {
                        expected: 4,
                        points: 4,
                        found: k,
                    },
                ))
            }
        }
    }
    Ok(Units164 {
        units_code: units_code as i32,
        description,
        temperature_mode: temperature_mode as i32,
        length_factor: f[0],
        force_factor: f[1],
        temperature_factor: f[2],
        temperature_offset: f[3],
        line: ctx.open_line,
    })
}

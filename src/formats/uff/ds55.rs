//! Dataset 55, data at nodes: how modal-analysis software (Simcenter Testlab, ME'scope,
//! ARTeMIS, I-DEAS Test) hands over an identified mode set, one dataset per mode. Records 1–5
//! are ID lines, record 6 the data definition (6I10), records 7–8 the analysis type's integer
//! and real parameters (NINT, NRVAL, then the values), and records 9–10 repeat per node: its
//! number, then its NDV values (real, or real and imaginary pairs). The layout follows the
//! SDRC/I-DEAS description as reproduced by pyuff (`pyuff.datasets.dataset_55`).
//!
//! Records 7–10 are read as a stream of numbers rather than by column: writers differ in how
//! they wrap record 8 and 10 (pyuff writes one line of up to six values, I-DEAS wraps at six),
//! and the count of each record is known from the ones before it.

use super::ascii::{excerpt, line_at, next_number, BadToken, Lines};
use super::read::Ctx;
use super::{IssueKind, ModeParams, NodalData55, NodeValues, UffIssue};

/// Parses the body of a dataset 55 (the lines between its number line and closing `-1`).
pub(super) fn parse_55(body: &[u8], body_line: usize, ctx: Ctx) -> Result<NodalData55, UffIssue> {
    let mut cur = Lines::new(body);
    let mut id_lines: [String; 5] = Default::default();
    for (k, slot) in id_lines.iter_mut().enumerate() {
        let Some((_, t)) = cur.next_line() else {
            return Err(ctx.issue(
                body_line + k,
                IssueKind::Truncated {
                    expected: format!("ID line {} (record {})", k + 1, k + 1),
                    found: "the closing `-1`".into(),
                },
            ));
        };
        *slot = String::from_utf8_lossy(t).trim_end().to_string();
    }
    let mut st = Stream {
        s: &body[cur.pos..],
        pos: 0,
        first_line: body_line + 5,
        ctx,
    };
    let rest_line = st.first_line;
    let mut r6 = [0i64; 6];
    let names6 = [
        "model type",
        "analysis type",
        "data characteristic",
        "specific data type",
        "data type",
        "number of data values per node",
    ];
    for (v, name) in r6.iter_mut().zip(names6) {
        *v = st.number(name, 6, true)? as i64;
    }
    let [model_type, analysis_type, data_characteristic, specific_data_type, data_type, ndv] = r6;
    let complex = match data_type {
        2 => false,
        5 => true,
        _ => {
            return Err(ctx.issue(
                rest_line,
                IssueKind::BadField {
                    record: 6,
                    field: "data type",
                    expected: "2 (real) or 5 (complex)",
                    found: data_type.to_string(),
                },
            ))
        }
    };
    // The standard sets no maximum (its note 13); a count the file cannot hold ends in a
    // truncation issue below, nothing is allocated for it up front.
    if ndv < 1 {
        return Err(ctx.issue(
            rest_line,
            IssueKind::BadField {
                record: 6,
                field: "number of data values per node",
                expected: "at least 1",
                found: ndv.to_string(),
            },
        ));
    }
    let nint = st.number("number of integer data values", 7, true)? as i64;
    let nreal = st.number("number of real data values", 7, true)? as i64;
    // The standard's general form has at most 10 and 12; writers that add parameters are
    // read up to 100.
    if !(0..=100).contains(&nint) || !(0..=100).contains(&nreal) {
        return Err(ctx.issue(
            rest_line + 1,
            IssueKind::BadField {
                record: 7,
                field: "numbers of integer and real data values",
                expected: "0 to 100 each",
                found: format!("{nint}, {nreal}"),
            },
        ));
    }
    let int_params = (0..nint)
        .map(|_| {
            st.number("type-specific integer parameter", 7, true)
                .map(|v| v as i64)
        })
        .collect::<Result<Vec<_>, _>>()?;
    let real_params = (0..nreal)
        .map(|_| st.number("type-specific real parameter", 8, false))
        .collect::<Result<Vec<_>, _>>()?;
    let per_node = (ndv as usize).saturating_mul(if complex { 2 } else { 1 });
    let mut nodes = vec![];
    while !st.at_end() {
        let node = st.number("node number", 9, true)? as i64;
        let mut vals = vec![];
        for _ in 0..per_node {
            vals.push(st.number("data value at the node", 10, false)?);
        }
        let (re, im) = if complex {
            let re = vals.iter().step_by(2).copied().collect();
            let im = vals.iter().skip(1).step_by(2).copied().collect();
            (re, Some(im))
        } else {
            (vals, None)
        };
        nodes.push(NodeValues { node, re, im });
    }
    Ok(NodalData55 {
        id_lines,
        model_type,
        analysis_type,
        data_characteristic,
        specific_data_type,
        complex,
        values_per_node: ndv as usize,
        int_params,
        real_params,
        nodes,
        line: ctx.open_line,
    })
}

impl NodalData55 {
    /// The mode this dataset describes, for the modal analysis types: 2 (normal mode: record 8
    /// holds the frequency in Hz, the modal mass and the viscous and hysteretic damping
    /// ratios), 3 and 7 (complex eigenvalue, first and second order: record 8 holds the
    /// eigenvalue λ = σ + iω_d in rad/s, so f = |λ|/2π and ζ = −σ/|λ|). `None` for any other
    /// analysis type or too few parameters.
    pub fn mode(&self) -> Option<ModeParams> {
        let mode_number = self.int_params.get(1).copied();
        match self.analysis_type {
            2 if self.real_params.len() >= 3 => Some(ModeParams {
                mode_number,
                freq_hz: self.real_params[0],
                damping_ratio: self.real_params[2],
                modal_mass: Some(self.real_params[1]).filter(|m| *m != 0.0),
            }),
            3 | 7 if self.real_params.len() >= 2 => {
                let (sigma, wd) = (self.real_params[0], self.real_params[1]);
                let wn = sigma.hypot(wd);
                (wn > 0.0).then(|| ModeParams {
                    mode_number,
                    freq_hz: wn / std::f64::consts::TAU,
                    damping_ratio: -sigma / wn,
                    modal_mass: None,
                })
            }
            _ => None,
        }
    }
}

/// Records 7–10 of a dataset 55 as a stream of numbers, with the line of each for errors.
struct Stream<'a> {
    s: &'a [u8],
    pos: usize,
    first_line: usize,
    ctx: Ctx,
}

impl Stream<'_> {
    fn at_end(&self) -> bool {
        let mut p = self.pos;
        next_number(self.s, &mut p).is_none()
    }

    /// The next number, an integer if `integer`; `what` and `record` name it in an issue.
    fn number(
        &mut self,
        what: &'static str,
        record: usize,
        integer: bool,
    ) -> Result<f64, UffIssue> {
        let (s, ctx) = (self.s, self.ctx);
        match next_number(s, &mut self.pos) {
            Some(Ok(v)) if v.is_finite() && (!integer || v.fract() == 0.0) => Ok(v),
            Some(Ok(v)) => Err(ctx.issue(
                line_at(s, self.pos, self.first_line),
                IssueKind::BadField {
                    record,
                    field: what,
                    expected: if integer {
                        "an integer"
                    } else {
                        "a finite number"
                    },
                    found: v.to_string(),
                },
            )),
            Some(Err(BadToken { start, end })) => Err(ctx.issue(
                line_at(s, start, self.first_line),
                IssueKind::BadField {
                    record,
                    field: what,
                    expected: if integer { "an integer" } else { "a number" },
                    found: excerpt(&s[start..end]),
                },
            )),
            None => Err(ctx.issue(
                line_at(s, s.len(), self.first_line),
                IssueKind::Truncated {
                    expected: format!("record {record} ({what})"),
                    found: "the closing `-1`".into(),
                },
            )),
        }
    }
}

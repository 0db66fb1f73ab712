//! Reading Gerber RS-274X files into the statements of [`crate::fem::gerber`], with the
//! 1-based line and text of every command so that any error names file, line and command.
//!
//! Hand-written on purpose. The maintained crate (`gerber_parser` 0.5 over `gerber-types`
//! 0.7) was evaluated first and does not do the job: it reads one command per line, so a
//! line holding several commands (legal RS-274X, e.g. `%FSLAX46Y46*%%MOMM*%` or
//! `D10*X0Y0D03*`) loses commands without an error, a line it cannot classify at all is
//! dropped silently, its parsed commands carry no line number (so errors found while
//! executing them, e.g. an undefined aperture, could not name the line), and it rejects
//! files of the writer we test against (gerbonara 1.5 writes `P,1.5X6.0` and `G01**`).
//! This reader covers what copper and profile layers use: FS (absolute or incremental),
//! MO, AD (C, R, O, P and aperture macros), AM (primitives 0, 1, 4, 5, 7, 20, 21 with
//! variables, assignments and arithmetic), LP, LM, LR, LS, SR, G01/G02/G03, G74/G75,
//! G36/G37, D01/D02/D03, Dnn, M02, comments and attributes (ignored), and the common
//! deprecated codes (G54, G70/G71, G90/G91, IPPOS, …). Block apertures (AB) and image
//! transforms other than the identity are refused with an error naming the line.

use crate::fem::gerber::{
    macro_primitive, render, ApertureShape, Cmd, Image, Interp, MacroPrimitive, SrcPos, Stmt,
};
use anyhow::bail;

/// A parse error at a position.
fn perr(name: &str, pos: &SrcPos, msg: impl std::fmt::Display) -> anyhow::Error {
    anyhow::anyhow!("{name}:{}: `{}`: {msg}", pos.line, pos.command)
}

/// A raw command: an extended (`%…%`) word or a function-code word, with its position.
struct Word {
    extended: bool,
    pos: SrcPos,
}

/// Split the text into words (terminated by `*`), grouping the words of `%…%` blocks.
/// Tolerates a missing `*` after a lone G-code at the end of a line (gerbonara 1.5
/// writes `G75` so) and empty words (`G01**`).
fn words(text: &str, name: &str) -> anyhow::Result<Vec<Word>> {
    let mut out = Vec::new();
    let mut line = 1usize;
    let mut cur = String::new();
    let mut start = 1usize;
    let mut in_ext = false;
    // A word still open at a line end or a `%` must be a lone G-code (its `*` omitted).
    let close_lone_g = |out: &mut Vec<Word>, cur: &mut String, start: usize, found: &str| {
        let lone_g =
            cur.len() >= 2 && cur.starts_with('G') && cur[1..].bytes().all(|b| b.is_ascii_digit());
        if !lone_g {
            bail!("{name}:{start}: `{cur}`: expected `*` to end the command, found {found}");
        }
        out.push(Word {
            extended: false,
            pos: SrcPos {
                line: start,
                command: std::mem::take(cur),
            },
        });
        Ok(())
    };
    for ch in text.chars() {
        match ch {
            '\n' | '\r' => {
                if ch == '\n' {
                    if !in_ext && !cur.is_empty() {
                        close_lone_g(&mut out, &mut cur, start, "the end of the line")?;
                    }
                    line += 1;
                }
            }
            '%' => {
                if !in_ext && !cur.is_empty() {
                    close_lone_g(&mut out, &mut cur, start, "`%`")?;
                }
                if in_ext && !cur.trim().is_empty() {
                    bail!(
                        "{name}:{start}: `{}`: expected `*` before the closing `%`",
                        cur.trim()
                    );
                }
                cur.clear();
                in_ext = !in_ext;
            }
            '*' => {
                let w = cur.trim().to_string();
                if !w.is_empty() {
                    out.push(Word {
                        extended: in_ext,
                        pos: SrcPos {
                            line: start,
                            command: w,
                        },
                    });
                }
                cur.clear();
            }
            c if c.is_whitespace() && !in_ext => {}
            c => {
                if cur.is_empty() {
                    start = line;
                }
                cur.push(c);
            }
        }
    }
    if in_ext {
        bail!(
            "{name}:{start}: expected `%` to close the extended command, found the end of the file"
        );
    }
    if !cur.trim().is_empty() {
        bail!(
            "{name}:{start}: `{}`: expected `*` to end the command, found the end of the file",
            cur.trim()
        );
    }
    Ok(out)
}

/// Coordinate format of `%FS…%`.
#[derive(Clone, Copy)]
struct Format {
    trailing: bool,
    int: usize,
    dec: usize,
}

fn parse_decimal(s: &str) -> Option<f64> {
    let v: f64 = s.trim().parse().ok()?;
    v.is_finite().then_some(v)
}

/// Evaluate an aperture-macro arithmetic expression (Gerber 2021 §4.5.4): decimals,
/// variables `$n`, unary `+`/`-`, binary `+`, `-`, `x` (times), `/`, parentheses.
fn eval_expr(s: &str, vars: &std::collections::HashMap<usize, f64>) -> Result<f64, String> {
    struct P<'a> {
        b: &'a [u8],
        k: usize,
        vars: &'a std::collections::HashMap<usize, f64>,
    }
    impl P<'_> {
        fn peek(&mut self) -> Option<u8> {
            while self.k < self.b.len() && self.b[self.k].is_ascii_whitespace() {
                self.k += 1;
            }
            self.b.get(self.k).copied()
        }
        fn expr(&mut self) -> Result<f64, String> {
            let mut v = self.term()?;
            while let Some(c @ (b'+' | b'-')) = self.peek() {
                self.k += 1;
                let t = self.term()?;
                v = if c == b'+' { v + t } else { v - t };
            }
            Ok(v)
        }
        fn term(&mut self) -> Result<f64, String> {
            let mut v = self.factor()?;
            while let Some(c @ (b'x' | b'X' | b'/')) = self.peek() {
                self.k += 1;
                let f = self.factor()?;
                v = if c == b'/' { v / f } else { v * f };
            }
            Ok(v)
        }
        fn factor(&mut self) -> Result<f64, String> {
            match self.peek() {
                Some(b'+') => {
                    self.k += 1;
                    self.factor()
                }
                Some(b'-') => {
                    self.k += 1;
                    Ok(-self.factor()?)
                }
                Some(b'(') => {
                    self.k += 1;
                    let v = self.expr()?;
                    if self.peek() != Some(b')') {
                        return Err("expected `)`".into());
                    }
                    self.k += 1;
                    Ok(v)
                }
                Some(b'$') => {
                    self.k += 1;
                    let s = self.k;
                    while self.k < self.b.len() && self.b[self.k].is_ascii_digit() {
                        self.k += 1;
                    }
                    let n: usize = std::str::from_utf8(&self.b[s..self.k])
                        .ok()
                        .and_then(|t| t.parse().ok())
                        .ok_or("expected a variable number after `$`")?;
                    self.vars.get(&n).copied().ok_or_else(|| {
                        format!("expected ${n} defined (by the AD parameters or an assignment), found it undefined")
                    })
                }
                Some(c) if c.is_ascii_digit() || c == b'.' => {
                    let s = self.k;
                    while self.k < self.b.len()
                        && (self.b[self.k].is_ascii_digit() || self.b[self.k] == b'.')
                    {
                        self.k += 1;
                    }
                    let t = std::str::from_utf8(&self.b[s..self.k]).unwrap_or("");
                    parse_decimal(t).ok_or_else(|| format!("expected a decimal, found {t:?}"))
                }
                Some(c) => Err(format!(
                    "expected a number, `$n` or `(`, found `{}`",
                    c as char
                )),
                None => Err("expected a number, `$n` or `(`, found the end".into()),
            }
        }
    }
    let mut p = P {
        b: s.as_bytes(),
        k: 0,
        vars,
    };
    let v = p.expr()?;
    if p.peek().is_some() {
        return Err(format!(
            "expected an operator or the end of {s:?}, found `{}`",
            &s[p.k..]
        ));
    }
    if !v.is_finite() {
        return Err(format!("expected a finite value of {s:?}, found {v}"));
    }
    Ok(v)
}

/// Instantiate the aperture macro `body` (its words after `%AMname*`) with the AD
/// parameters `params` (file units): each primitive evaluated to contours, m.
fn instantiate_macro(
    name: &str,
    macro_name: &str,
    body: &[SrcPos],
    params: &[f64],
    unit_m: f64,
    ad: &SrcPos,
) -> anyhow::Result<Vec<MacroPrimitive>> {
    let mut vars: std::collections::HashMap<usize, f64> = params
        .iter()
        .enumerate()
        .map(|(k, v)| (k + 1, *v))
        .collect();
    let mut out = Vec::new();
    for w in body {
        let e = |m: String| {
            perr(
                name,
                w,
                format!("macro {macro_name} (instantiated at line {}): {m}", ad.line),
            )
        };
        let t = w.command.trim();
        if let Some(rest) = t.strip_prefix('$') {
            let Some((var, expr)) = rest.split_once('=') else {
                return Err(e("expected a variable assignment `$n=expression`".into()));
            };
            let n: usize = var
                .trim()
                .parse()
                .map_err(|_| e(format!("expected a variable number, found {var:?}")))?;
            let v = eval_expr(expr, &vars).map_err(e)?;
            vars.insert(n, v);
            continue;
        }
        // A comment primitive: `0` then free text.
        if t == "0" || t.starts_with("0 ") {
            continue;
        }
        let mut fields = t.split(',');
        let code_s = fields.next().unwrap_or("").trim();
        let code: u32 = code_s
            .parse()
            .map_err(|_| e(format!("expected a primitive code, found {code_s:?}")))?;
        let vals: Vec<f64> = fields
            .map(|f| eval_expr(f, &vars))
            .collect::<Result<_, _>>()
            .map_err(e)?;
        if let Some(p) = macro_primitive(code, &vals, unit_m).map_err(e)? {
            out.push(p);
        }
    }
    if out.is_empty() {
        return Err(perr(
            name,
            ad,
            format!("expected macro {macro_name} to hold at least one primitive, found none"),
        ));
    }
    Ok(out)
}

/// Coordinate format, unit, modes and aperture macros while reading a Gerber file's words.
struct Parser<'n> {
    /// The file, for error messages.
    name: &'n str,
    out: Vec<Stmt>,
    format: Option<(Format, Format)>,
    unit_m: Option<f64>,
    last_d: Option<u8>,
    /// Aperture macros: name and the words of its body.
    macros: Vec<(String, Vec<SrcPos>)>,
    in_macro: bool,
    /// Incremental coordinates (FS…I… or G91) and the current point they add to, m
    /// (the origin before the first operation).
    incremental: bool,
    cur: [f64; 2],
}

/// The codes and coordinates of a function-code word.
struct CodeWord<'c> {
    g: Option<u32>,
    d: Option<u32>,
    m: Option<u32>,
    /// X, Y, I, J as written.
    xy: [Option<&'c str>; 4],
}

/// Parse Gerber text into statements (coordinates and sizes in metres). `name` is used
/// in error messages (the file).
pub fn parse_gerber(text: &str, name: &str) -> anyhow::Result<Vec<Stmt>> {
    let ws = words(text, name)?;
    let mut p = Parser {
        name,
        out: Vec::new(),
        format: None,
        unit_m: None,
        last_d: None,
        macros: Vec::new(),
        in_macro: false,
        incremental: false,
        cur: [0.0f64; 2],
    };
    for w in ws {
        if w.extended {
            p.extended(&w.pos)?;
        } else {
            p.function_code(&w.pos)?;
        }
    }
    let out = p.out;
    if !out.iter().any(|s| s.cmd == Cmd::End) {
        bail!("{name}: expected M02 at the end of the file, found none (truncated file?)");
    }
    Ok(out)
}

impl Parser<'_> {
    fn push(&mut self, pos: &SrcPos, cmd: Cmd) {
        self.out.push(Stmt {
            pos: pos.clone(),
            cmd,
        })
    }

    /// The unit, m, which must be known before `what`.
    fn unit(&self, pos: &SrcPos, what: &str) -> anyhow::Result<f64> {
        self.unit_m.ok_or_else(|| {
            perr(
                self.name,
                pos,
                format!("expected the unit (%MOMM*% or %MOIN*%) before {what}"),
            )
        })
    }

    /// An extended (`%…%`) word, or a word of an aperture macro's body.
    fn extended(&mut self, pos: &SrcPos) -> anyhow::Result<()> {
        let name = self.name;
        let c = pos.command.as_str();
        // Words after `%AMname*` up to the closing `%` are the macro's body.
        if self.in_macro
            && !c.starts_with("AM")
            && !c
                .get(0..2)
                .is_some_and(|p| p.chars().all(|ch| ch.is_ascii_uppercase()))
        {
            if let Some(m) = self.macros.last_mut() {
                m.1.push(pos.clone());
            }
            return Ok(());
        }
        self.in_macro = false;
        let (code, rest) = c.split_at(c.len().min(2));
        match code {
            "FS" => {
                let b = rest.as_bytes();
                let ok = b.len() == 8 && (b[0] == b'L' || b[0] == b'T') && b[2] == b'X' && b[5] == b'Y';
                if !ok {
                    return Err(perr(name, pos, "expected the format `FS` L|T A X<int><dec> Y<int><dec>, e.g. FSLAX46Y46"));
                }
                if b[1] != b'A' && b[1] != b'I' {
                    return Err(perr(name, pos, "expected absolute (FSLA…) or incremental (FSLI…) coordinates"));
                }
                self.incremental = b[1] == b'I';
                let d = |k: usize| (b[k] as char).to_digit(10).map(|v| v as usize);
                let (Some(xi), Some(xd), Some(yi), Some(yd)) = (d(3), d(4), d(6), d(7)) else {
                    return Err(perr(name, pos, "expected digit counts after X and Y, e.g. FSLAX46Y46"));
                };
                let t = b[0] == b'T';
                self.format = Some((
                    Format { trailing: t, int: xi, dec: xd },
                    Format { trailing: t, int: yi, dec: yd },
                ));
            }
            "MO" => {
                self.unit_m = Some(match rest {
                    "MM" => 1e-3,
                    "IN" => 25.4e-3,
                    _ => return Err(perr(name, pos, format!("expected MOMM or MOIN, found MO{rest}"))),
                })
            }
            "AD" => {
                let cmd = self.aperture_def(pos, rest)?;
                self.push(pos, cmd);
            }
            "AM" => {
                if rest.is_empty() || self.macros.iter().any(|(n, _)| n == rest) {
                    return Err(perr(name, pos, format!("expected a new macro name after AM, found {rest:?}")));
                }
                self.macros.push((rest.to_string(), Vec::new()));
                self.in_macro = true;
            }
            "LP" => match rest {
                "D" => self.push(pos, Cmd::Polarity { dark: true }),
                "C" => self.push(pos, Cmd::Polarity { dark: false }),
                _ => return Err(perr(name, pos, format!("expected LPD or LPC, found LP{rest}"))),
            },
            "LM" => {
                let (x, y) = match rest {
                    "N" => (false, false),
                    "X" => (true, false),
                    "Y" => (false, true),
                    "XY" => (true, true),
                    _ => return Err(perr(name, pos, format!("expected LMN, LMX, LMY or LMXY, found LM{rest}"))),
                };
                self.push(pos, Cmd::Mirror { x, y });
            }
            "LR" | "LS" => {
                let v = parse_decimal(rest).ok_or_else(|| perr(name, pos, format!("expected a decimal after {code}, found {rest:?}")))?;
                self.push(pos, if code == "LR" { Cmd::Rotate(v) } else { Cmd::Scale(v) });
            }
            "SR" => {
                if rest.is_empty() {
                    self.push(pos, Cmd::StepRepeatEnd);
                } else {
                    let u = self.unit(pos, "a step-and-repeat")?;
                    let field = |k: char| -> Option<&str> {
                        let i = rest.find(k)?;
                        let tail = &rest[i + 1..];
                        let e = tail.find(|ch: char| ch.is_ascii_alphabetic()).unwrap_or(tail.len());
                        Some(&tail[..e])
                    };
                    let parsed = (|| {
                        Some((
                            field('X')?.parse::<u32>().ok()?,
                            field('Y')?.parse::<u32>().ok()?,
                            parse_decimal(field('I')?)?,
                            parse_decimal(field('J')?)?,
                        ))
                    })();
                    let Some((nx, ny, i, j)) = parsed else {
                        return Err(perr(name, pos, "expected SRX<copies>Y<copies>I<step>J<step>"));
                    };
                    self.push(pos, Cmd::StepRepeat { nx, ny, dx_m: i * u, dy_m: j * u });
                }
            }
            // Attributes, image name, layer name: no effect on the image.
            "TF" | "TA" | "TO" | "TD" | "IN" | "LN" => {}
            "IP" if rest == "POS" => {}
            "AS" if rest == "AXBY" => {}
            "MI" if matches!(rest, "" | "A0B0" | "A0" | "B0") => {}
            "IR" if rest == "0" => {}
            "OF" if rest.chars().all(|ch| "AB0.+-".contains(ch)) => {}
            "SF" if matches!(rest, "" | "A1B1" | "A1.0B1.0" | "A1" | "B1") => {}
            "AB" => return Err(perr(name, pos, "block apertures (AB) are not supported yet")),
            _ => return Err(perr(name, pos, format!("expected a supported extended command (FS, MO, AD, AM, LP, LM, LR, LS, SR, attributes), found %{c}%"))),
        }
        Ok(())
    }

    /// The aperture definition `%ADD<rest>%`.
    fn aperture_def(&self, pos: &SrcPos, rest: &str) -> anyhow::Result<Cmd> {
        let name = self.name;
        let u = self.unit(pos, "an aperture definition")?;
        let body = rest
            .strip_prefix('D')
            .ok_or_else(|| perr(name, pos, "expected ADD<number><template>"))?;
        let nd = body.bytes().take_while(|b| b.is_ascii_digit()).count();
        let code: u32 = body[..nd]
            .parse()
            .map_err(|_| perr(name, pos, "expected an aperture number after ADD"))?;
        let (tmpl, params) = match body[nd..].split_once(',') {
            Some((t, p)) => (t, p),
            None => (&body[nd..], ""),
        };
        let ps: Vec<f64> = if params.is_empty() {
            Vec::new()
        } else {
            params
                .split('X')
                .map(|p| {
                    parse_decimal(p).ok_or_else(|| {
                        perr(
                            name,
                            pos,
                            format!("expected a decimal aperture parameter, found {p:?}"),
                        )
                    })
                })
                .collect::<anyhow::Result<_>>()?
        };
        let need = |lo: usize, hi: usize| -> anyhow::Result<()> {
            if ps.len() < lo || ps.len() > hi {
                Err(perr(
                    name,
                    pos,
                    format!(
                        "expected {lo} to {hi} parameters for template {tmpl}, found {}",
                        ps.len()
                    ),
                ))
            } else {
                Ok(())
            }
        };
        let m = |k: usize| ps.get(k).map(|v| v * u);
        let shape = match tmpl {
            "C" => {
                need(1, 2)?;
                ApertureShape::Circle { d_m: ps[0] * u, hole_m: m(1) }
            }
            "R" => {
                need(2, 3)?;
                ApertureShape::Rect { w_m: ps[0] * u, h_m: ps[1] * u, hole_m: m(2) }
            }
            "O" => {
                need(2, 3)?;
                ApertureShape::Obround { w_m: ps[0] * u, h_m: ps[1] * u, hole_m: m(2) }
            }
            "P" => {
                need(2, 4)?;
                if ps[1].fract() != 0.0 {
                    return Err(perr(name, pos, format!("expected a whole number of polygon vertices, found {}", ps[1])));
                }
                ApertureShape::Polygon {
                    d_m: ps[0] * u,
                    n: ps[1].max(0.0) as u32,
                    rotation_deg: ps.get(2).copied().unwrap_or(0.0),
                    hole_m: m(3),
                }
            }
            t if self.macros.iter().any(|(n, _)| n == t) => {
                let body = &self.macros.iter().rev().find(|(n, _)| n == t).unwrap_or_else(|| unreachable!()).1;
                ApertureShape::Macro {
                    name: t.to_string(),
                    primitives: instantiate_macro(name, t, body, &ps, u, pos)?,
                }
            }
            t => return Err(perr(name, pos, format!("expected an aperture template C, R, O or P (or a macro defined by AM), found {t:?}"))),
        };
        Ok(Cmd::ApertureDef { code, shape })
    }

    /// A function-code word: G, D and M codes and an operation's coordinates.
    fn function_code(&mut self, pos: &SrcPos) -> anyhow::Result<()> {
        let name = self.name;
        let c = pos.command.as_str();
        // Function-code word: letter + number pairs.
        if c.starts_with("G04")
            || c.starts_with("G4") && c[2..].starts_with(|ch: char| !ch.is_ascii_digit())
            || c == "G4"
        {
            return Ok(()); // comment
        }
        let CodeWord { g, d, m, xy } = code_word(c, name, pos)?;
        if let Some(g) = g {
            match g {
                1 => self.push(pos, Cmd::Interp(Interp::Linear)),
                2 => self.push(pos, Cmd::Interp(Interp::Clockwise)),
                3 => self.push(pos, Cmd::Interp(Interp::CounterClockwise)),
                74 => self.push(pos, Cmd::Quadrant { multi: false }),
                75 => self.push(pos, Cmd::Quadrant { multi: true }),
                36 => self.push(pos, Cmd::Region(true)),
                37 => self.push(pos, Cmd::Region(false)),
                54 | 55 => {}
                90 => self.incremental = false,
                91 => self.incremental = true,
                70 => self.unit_m = Some(25.4e-3),
                71 => self.unit_m = Some(1e-3),
                _ => return Err(perr(name, pos, format!("expected a supported G code (01, 02, 03, 04, 36, 37, 74, 75), found G{g:02}"))),
            }
        }
        if let Some(m) = m {
            match m {
                2 | 0 | 30 => self.push(pos, Cmd::End),
                1 => {}
                _ => return Err(perr(name, pos, format!("expected M02, found M{m:02}"))),
            }
            return Ok(());
        }
        let has_xy = xy.iter().any(|v| v.is_some());
        let op = match d {
            Some(n) if n >= 10 => {
                if has_xy {
                    return Err(perr(
                        name,
                        pos,
                        "expected no coordinates with an aperture selection",
                    ));
                }
                self.push(pos, Cmd::Select(n));
                self.last_d = None;
                return Ok(());
            }
            Some(n @ 1..=3) => n as u8,
            Some(n) => {
                return Err(perr(
                    name,
                    pos,
                    format!("expected D01, D02, D03 or an aperture Dnn (nn ≥ 10), found D{n:02}"),
                ))
            }
            None if has_xy => match self.last_d {
                // Deprecated modal D01: coordinates alone repeat the last D01.
                Some(1) => 1,
                _ => {
                    return Err(perr(
                        name,
                        pos,
                        "expected an operation code (D01, D02 or D03) after the coordinates",
                    ))
                }
            },
            None => return Ok(()),
        };
        let Some((fx, fy)) = self.format else {
            return Err(perr(
                name,
                pos,
                "expected the coordinate format (%FS…%) before the first coordinate",
            ));
        };
        let Some(u) = self.unit_m else {
            return Err(perr(
                name,
                pos,
                "expected the unit (%MOMM*% or %MOIN*%) before the first coordinate",
            ));
        };
        let coord = |k: usize, f: Format| -> anyhow::Result<Option<f64>> {
            let Some(s) = xy[k] else { return Ok(None) };
            let (neg, digits) = match s.as_bytes()[0] {
                b'-' => (true, &s[1..]),
                b'+' => (false, &s[1..]),
                _ => (false, s),
            };
            if digits.len() > f.int + f.dec {
                return Err(perr(
                    name,
                    pos,
                    format!(
                        "expected at most {} digits (format {}{}), found {s:?}",
                        f.int + f.dec,
                        f.int,
                        f.dec
                    ),
                ));
            }
            let v: f64 = digits
                .parse::<u64>()
                .map_err(|_| perr(name, pos, format!("expected digits, found {s:?}")))?
                as f64;
            let scale = if f.trailing {
                10f64.powi((f.int + f.dec - digits.len()) as i32 - f.dec as i32)
            } else {
                10f64.powi(-(f.dec as i32))
            };
            Ok(Some(if neg { -v } else { v } * scale * u))
        };
        let (mut x, mut y) = (coord(0, fx)?, coord(1, fy)?);
        if self.incremental {
            // Both coordinates become absolute: a missing one is an increment of 0.
            x = Some(self.cur[0] + x.unwrap_or(0.0));
            y = Some(self.cur[1] + y.unwrap_or(0.0));
        }
        self.cur = [x.unwrap_or(self.cur[0]), y.unwrap_or(self.cur[1])];
        let cmd = Cmd::Op {
            d: op,
            x,
            y,
            i: coord(2, fx)?,
            j: coord(3, fy)?,
        };
        self.push(pos, cmd);
        self.last_d = Some(op);
        Ok(())
    }
}

/// The G, D and M codes and the X, Y, I, J coordinates (as written) of the function-code
/// word `c` at `pos`.
fn code_word<'c>(c: &'c str, name: &str, pos: &SrcPos) -> anyhow::Result<CodeWord<'c>> {
    let b = c.as_bytes();
    let mut k = 0;
    let (mut g, mut d, mut m) = (None::<u32>, None::<u32>, None::<u32>);
    let mut xy: [Option<&str>; 4] = [None; 4];
    while k < b.len() {
        let letter = b[k] as char;
        let s = k + 1;
        let mut e = s;
        while e < b.len() && (b[e].is_ascii_digit() || ((b[e] == b'+' || b[e] == b'-') && e == s)) {
            e += 1;
        }
        if e == s || (e == s + 1 && !b[s].is_ascii_digit()) {
            return Err(perr(
                name,
                pos,
                format!("expected a number after `{letter}`"),
            ));
        }
        let num = &c[s..e];
        let int = || {
            num.parse::<u32>().map_err(|_| {
                perr(
                    name,
                    pos,
                    format!("expected a whole number after `{letter}`, found {num:?}"),
                )
            })
        };
        match letter {
            'G' => g = Some(int()?),
            'D' => d = Some(int()?),
            'M' => m = Some(int()?),
            'X' => xy[0] = Some(num),
            'Y' => xy[1] = Some(num),
            'I' => xy[2] = Some(num),
            'J' => xy[3] = Some(num),
            _ => {
                return Err(perr(
                    name,
                    pos,
                    format!("expected a G, D, M code or X, Y, I, J coordinates, found `{letter}`"),
                ))
            }
        }
        k = e;
    }
    Ok(CodeWord { g, d, m, xy })
}

/// Parse and render a Gerber file's text; errors name `name`, the line and the command.
pub fn read_gerber_str(text: &str, name: &str) -> anyhow::Result<Image> {
    let stmts = parse_gerber(text, name)?;
    render(&stmts).map_err(|e| perr(name, &e.pos, e.message))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fem::geometry::Rect;
    use crate::fem::gerber::rasterize;

    const HEAD: &str = "%FSLAX46Y46*%\n%MOMM*%\n";

    #[test]
    fn several_commands_per_line_and_deprecated_forms_parse() {
        let t = "%FSLAX46Y46*%%MOMM*%\n%ADD10C,0.5*%%ADD11P,1.5X6.0*%\nG54D10*X0Y0D03*X1000000Y0D03*\nG01X0Y0D02*X2000000D01*\nG75\nM02*\n";
        let s = parse_gerber(t, "a.gbr").unwrap();
        let flashes = s
            .iter()
            .filter(|s| matches!(s.cmd, Cmd::Op { d: 3, .. }))
            .count();
        assert_eq!(flashes, 2);
        assert_eq!(s.iter().filter(|s| s.pos.line == 3).count(), 3);
        let img = render(&s).unwrap();
        // Two 0.5 mm discs at 0 and 1 mm, a 2 mm stroke of the same aperture over them.
        let e = Rect {
            x0: -1e-3,
            y0: -1e-3,
            x1: 3e-3,
            y1: 1e-3,
        };
        let g = rasterize(&img, &e, 40, 20);
        let area: f64 = g.values.iter().sum::<f64>() * 1e-8;
        let exact = 2e-3 * 0.5e-3 + std::f64::consts::PI * 0.0625e-6;
        assert!((area / exact - 1.0).abs() < 1e-3, "{area:e} vs {exact:e}");
    }

    #[test]
    fn coordinates_follow_the_format_and_unit() {
        let t = "%FSTAX24Y24*%\n%MOIN*%\n%ADD10C,0.01*%\nD10*\nX15Y-025D03*\nM02*\n";
        let s = parse_gerber(t, "b.gbr").unwrap();
        let Cmd::Op { x, y, .. } = &s[2].cmd else {
            panic!("{s:?}")
        };
        // Trailing zeros omitted: X15 → 15 0000 → 15.0000? no: 2+4 digits, "15" → 150000 → 15.0000 in.
        assert!((x.unwrap() - 15.0 * 25.4e-3).abs() < 1e-12, "{x:?}");
        assert!((y.unwrap() + 2.5 * 25.4e-3).abs() < 1e-12, "{y:?}");
    }

    #[test]
    fn malformed_gerber_errors_name_file_line_and_command() {
        let cases = [
            (format!("{HEAD}%ADD10C,0.5*%\nD10*\nX0Y0D03*\nD11*\nM02*\n"), ":6: `D11`", "undefined"),
            (format!("{HEAD}%ADD10Q,0.5*%\nM02*\n"), ":3: `ADD10Q,0.5`", "template"),
            (format!("{HEAD}%ADD10C,0.5*%\nD10*\nX0Y0D03\nM02*\n"), ":5: `X0Y0D03`", "expected `*`"),
            (format!("{HEAD}G36*\nX0Y0D02*\nG01*\nX1000000Y0D01*\nX1000000Y1000000D01*\nG37*\nM02*\n"), ":8: `G37`", "closed"),
            (format!("{HEAD}%ADD10C,0.5*%\nD10*\nX0Y0D02*\nG03*\nX1000000Y0I300000J0D01*\nM02*\n"), ":7: `X1000000Y0I300000J0D01`", "same distance"),
            (format!("{HEAD}%ADD10C,0.5*%\nD10*\nXY0D03*\nM02*\n"), ":5: `XY0D03`", "number after `X`"),
            (format!("{HEAD}%ADD10C,0.5*%\n"), "c.gbr", "M02"),
            ("%MOMM*%\n%ADD10C,0.5*%\nD10*\nX0Y0D03*\nM02*\n".to_string(), ":4: `X0Y0D03`", "%FS"),
        ];
        for (text, at, what) in cases {
            let e = read_gerber_str(&text, "c.gbr").unwrap_err().to_string();
            assert!(
                e.starts_with("c.gbr") && e.contains(at) && e.contains(what),
                "{e}\nexpected {at} … {what}"
            );
        }
    }

    /// Total copper area of an image over `e`, m² (raster cells 10 µm).
    fn area(img: &Image, e: &Rect) -> f64 {
        let (nx, ny) = (
            ((e.x1 - e.x0) / 1e-5).round() as usize,
            ((e.y1 - e.y0) / 1e-5).round() as usize,
        );
        let g = rasterize(img, e, nx, ny);
        g.values.iter().sum::<f64>() * (e.x1 - e.x0) * (e.y1 - e.y0) / (nx * ny) as f64
    }

    /// A macro with variables, an assignment, arithmetic, several primitives and an
    /// exposure-off primitive, flashed over a dark region: the macro's image is a 2 mm
    /// disc with a 1 mm disc erased, plus a 3 × 0.4 mm bar (rotated 90°, crossing the
    /// erased disc and so filling part of it again); the erased disc does not clear the
    /// region beneath (exposure acts within the aperture), while a clear flash of the
    /// same macro clears exactly its image.
    #[test]
    fn aperture_macros_evaluate_variables_and_exposure_within_the_aperture() {
        let mac = "%AMDONUT*\n0 a ring and a bar*\n$3=$1x0.5*\n1,1,$1,0,0*\n1,0,$3,0,0*\n21,1,(1+2),$2,0,0,90*%\n";
        let t = format!("{HEAD}{mac}%ADD10DONUT,2.0X0.4*%\nD10*\nX0Y0D03*\nM02*\n");
        let img = read_gerber_str(&t, "m.gbr").unwrap();
        let e = Rect {
            x0: -2e-3,
            y0: -2e-3,
            x1: 2e-3,
            y1: 2e-3,
        };
        let pi = std::f64::consts::PI;
        // Ring π(1² − 0.5²) mm², plus the bar (0.4 × 3 mm along y) outside the outer
        // disc (2 × 0.4 × (1.5 − ~1) mm) and inside the hole (0.4 × ~1 mm): the bar's
        // area minus its overlap with the ring, computed from segment areas.
        let seg = |r: f64, h: f64| {
            // Area of the disc of radius r within |x| ≤ h.
            2.0 * (h * (r * r - h * h).sqrt() + r * r * (h / r).asin())
        };
        let ring_in_bar = seg(1.0, 0.2) - seg(0.5, 0.2);
        let exact_mm2 = pi * (1.0 - 0.25) + 0.4 * 3.0 - ring_in_bar;
        let got = area(&img, &e) * 1e6;
        assert!(
            (got / exact_mm2 - 1.0).abs() < 2e-3,
            "{got} vs {exact_mm2} mm²"
        );
        // Over a dark 3 × 3 mm square the erased disc stays dark.
        let t = format!("{HEAD}{mac}%ADD10DONUT,2.0X0.4*%\nG36*\nX-1500000Y-1500000D02*\nG01*\nX1500000Y-1500000D01*\nX1500000Y1500000D01*\nX-1500000Y1500000D01*\nX-1500000Y-1500000D01*\nG37*\nD10*\nX0Y0D03*\nM02*\n");
        let img = read_gerber_str(&t, "m.gbr").unwrap();
        let got = area(&img, &e) * 1e6;
        let exact = 9.0 + 2.0 * 0.4 * 0.5 * 0.0 + 0.0;
        // Square 9 mm² plus the bar's two ends beyond it (|y| ≤ 1.5 = the square's
        // edge, so none): exactly the square.
        assert!((got / exact - 1.0).abs() < 1e-3, "{got} vs {exact} mm²");
        // A clear flash of the macro over the square removes exactly the macro's image.
        let t = t.replace("D10*\nX0Y0D03*", "%LPC*%\nD10*\nX0Y0D03*");
        let img = read_gerber_str(&t, "m.gbr").unwrap();
        let got = area(&img, &e) * 1e6;
        assert!(
            (got / (9.0 - exact_mm2) - 1.0).abs() < 2e-3,
            "{got} vs {} mm²",
            9.0 - exact_mm2
        );
    }

    /// Incremental coordinates (FS…I…, and G91): each coordinate adds to the current
    /// point, a missing one adds 0; G90 returns to absolute.
    #[test]
    fn incremental_coordinates_add_to_the_current_point() {
        let t = "%FSLIX24Y24*%\n%MOMM*%\n%ADD10C,0.1*%\nD10*\nX010000Y020000D02*\nX005000D03*\nY-010000D03*\nG90*\nX000000Y000000D03*\nG91*\nX001000Y001000D03*\nM02*\n";
        let s = parse_gerber(t, "i.gbr").unwrap();
        let pts: Vec<(f64, f64)> = s
            .iter()
            .filter_map(|s| match s.cmd {
                Cmd::Op { x, y, .. } => Some((x.unwrap() * 1e3, y.unwrap() * 1e3)),
                _ => None,
            })
            .collect();
        let want = [(1.0, 2.0), (1.5, 2.0), (1.5, 1.0), (0.0, 0.0), (0.1, 0.1)];
        assert_eq!(pts.len(), want.len());
        for (g, w) in pts.iter().zip(&want) {
            assert!(
                (g.0 - w.0).abs() < 1e-9 && (g.1 - w.1).abs() < 1e-9,
                "{pts:?}"
            );
        }
    }

    #[test]
    fn malformed_macros_name_file_line_and_command() {
        let cases = [
            // Unknown primitive code, on the body's line.
            (
                format!("{HEAD}%AMX1*\n9,1,1,0,0*%\n%ADD10X1*%\nM02*\n"),
                ":4: `9,1,1,0,0`",
                "primitive code",
            ),
            // Wrong parameter count of a circle.
            (
                format!("{HEAD}%AMX1*\n1,1,1*%\n%ADD10X1*%\nM02*\n"),
                ":4: `1,1,1`",
                "4 to 5 parameters",
            ),
            // A variable the AD does not give.
            (
                format!("{HEAD}%AMX1*\n1,1,$2,0,0*%\n%ADD10X1,1.0*%\nM02*\n"),
                ":4: `1,1,$2,0,0`",
                "$2",
            ),
            // A bad expression.
            (
                format!("{HEAD}%AMX1*\n1,1,(1+2,0,0*%\n%ADD10X1*%\nM02*\n"),
                ":4: `1,1,(1+2,0,0`",
                "`)`",
            ),
            // An open outline.
            (
                format!("{HEAD}%AMX1*\n4,1,3,0,0,1,0,1,1,0,1,0*%\n%ADD10X1*%\nM02*\n"),
                ":4: `4,1,3,0,0,1,0,1,1,0,1,0`",
                "last point",
            ),
            // Exposure neither 0 nor 1.
            (
                format!("{HEAD}%AMX1*\n1,2,1,0,0*%\n%ADD10X1*%\nM02*\n"),
                ":4: `1,2,1,0,0`",
                "exposure",
            ),
            // A macro redefined.
            (
                format!("{HEAD}%AMX1*\n1,1,1,0,0*%\n%AMX1*\n1,1,1,0,0*%\nM02*\n"),
                ":5: `AMX1`",
                "new macro name",
            ),
            // A macro flashed in a draw.
            (
                format!(
                    "{HEAD}%AMX1*\n1,1,1,0,0*%\n%ADD10X1*%\nD10*\nX0Y0D02*\nX1000000Y0D01*\nM02*\n"
                ),
                ":8: `X1000000Y0D01`",
                "circular aperture",
            ),
        ];
        for (text, at, what) in cases {
            let e = read_gerber_str(&text, "c.gbr").unwrap_err().to_string();
            assert!(
                e.starts_with("c.gbr") && e.contains(at) && e.contains(what),
                "{e}\nexpected {at} … {what}"
            );
        }
    }
}

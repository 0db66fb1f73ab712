//! Tests of the UFF reader and writer. References: files written by the third-party package
//! `pyuff` (and read back by it), literal values in hand-made quirk fixtures, and Rust's
//! `f64::from_str` (correctly rounded) for the number scanner. Python-based tests skip with a
//! notice when python3/pyuff are missing, unless `HBMU_REQUIRE_INTEROP=1`.

use super::ascii::next_number;
use super::*;
use proptest::prelude::*;

// ---------------------------------------------------------------------------------------------
// Number scanning

fn scan_all(s: &str) -> Vec<Result<f64, ()>> {
    let b = s.as_bytes();
    let mut pos = 0;
    let mut out = Vec::new();
    while let Some(r) = next_number(b, &mut pos) {
        out.push(r.map_err(|_| ()));
    }
    out
}

#[test]
fn fortran_fields_scan_to_their_values() {
    let cases: &[(&str, &[f64])] = &[
        ("1.0D+03", &[1000.0]),
        ("2.5d-2", &[0.025]),
        ("-1.23456E+00-2.34567E+00", &[-1.23456, -2.34567]),
        ("1.0E+001.0E+00", &[1.0, 1.0]),
        ("1.0E+001.0E+001.0E+00", &[1.0, 1.0, 1.0]),
        ("0.12345E+010.12345E+01", &[1.2345, 1.2345]),
        ("1.0E+1001.0E+00", &[1e100, 1.0]),
        ("  4.00000e+00  -5.00000e-01\r\n", &[4.0, -0.5]),
        ("7 -8 +9", &[7.0, -8.0, 9.0]),
        ("1.5 .5 5.", &[1.5, 0.5, 5.0]),
        (
            "1e-320 1.7976931348623157e308",
            &[1e-320, 1.7976931348623157e308],
        ),
    ];
    for (text, want) in cases {
        let got: Vec<f64> = scan_all(text)
            .into_iter()
            .map(|r| r.unwrap_or_else(|()| panic!("{text:?} did not scan")))
            .collect();
        assert_eq!(&got, want, "{text:?}");
    }
    // More significant digits than a u64 holds: the slow path, checked against std.
    let long = "-1.2345678901234567890123E-05";
    assert_eq!(scan_all(long), vec![Ok(long.parse::<f64>().unwrap())]);
    let z = scan_all("-0.0");
    assert!(matches!(z[..], [Ok(v)] if v == 0.0 && v.is_sign_negative()));
    let nan = scan_all("nan -inf");
    assert!(matches!(nan[..], [Ok(a), Ok(b)] if a.is_nan() && b == f64::NEG_INFINITY));
    for bad in ["abc", "1.0E", "1.0E+", "1.0E+00x", "--1", "1.2.3", "."] {
        assert!(
            scan_all(bad).iter().any(|r| r.is_err()),
            "{bad:?} should not scan"
        );
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(4000))]
    /// Every E-format rendering of any f64 scans to exactly what `f64::from_str` gives.
    #[test]
    fn scanner_agrees_with_std(bits in any::<u64>(), prec in 0usize..18, letter in 0usize..4) {
        let v = f64::from_bits(bits);
        prop_assume!(v.is_finite());
        let text = format!("{v:.prec$e}");
        let reference: f64 = text.parse().unwrap();
        let l = ["E", "e", "D", "d"][letter];
        let fortran = text.replace('e', l);
        let got = scan_all(&fortran);
        prop_assert_eq!(got.len(), 1);
        prop_assert_eq!(got[0].unwrap().to_bits(), reference.to_bits(), "{}", fortran);
    }

    /// The standard's (and Python's `%.pE`) layout: sign, one digit, point, p digits, `E`,
    /// exponent sign, at least two digits; alone and as touching fields.
    #[test]
    fn scanner_agrees_with_std_on_fortran_layout(
        a in any::<u64>(), b in any::<u64>(), prec in 0usize..18, letter in 0usize..4
    ) {
        let (va, vb) = (f64::from_bits(a), f64::from_bits(b));
        prop_assume!(va.is_finite() && vb.is_finite());
        let l = ["E", "e", "D", "d"][letter];
        let fa = fortran_e(va, prec, l);
        let fb = fortran_e(vb, prec, l);
        let ra: f64 = fa.replace(['D', 'd'], "e").parse().unwrap();
        let rb: f64 = fb.replace(['D', 'd'], "e").parse().unwrap();
        let spaced = scan_all(&format!("  {fa}   {fb}\n"));
        prop_assert_eq!(spaced.len(), 2);
        prop_assert_eq!(spaced[0].unwrap().to_bits(), ra.to_bits(), "{}", fa);
        prop_assert_eq!(spaced[1].unwrap().to_bits(), rb.to_bits(), "{}", fb);
        // Touching fields are unambiguous when the second starts with a sign, or has a point
        // (the digit before it is given back from the first field's exponent).
        if fb.starts_with('-') || prec > 0 {
            let touching = scan_all(&format!("{fa}{fb}"));
            prop_assert_eq!(touching.len(), 2, "{}{}", fa, fb);
            prop_assert_eq!(touching[0].unwrap().to_bits(), ra.to_bits(), "{}{}", fa, fb);
            prop_assert_eq!(touching[1].unwrap().to_bits(), rb.to_bits(), "{}{}", fa, fb);
        }
    }

    /// Random digit strings (mantissa up to 25 digits, any exponent) agree with std.
    #[test]
    fn scanner_agrees_with_std_on_digit_strings(
        int in "[0-9]{1,12}", frac in "[0-9]{0,13}", exp in -330i32..330, neg in any::<bool>()
    ) {
        let text = format!("{}{int}.{frac}E{exp:+03}", if neg { "-" } else { "" });
        let reference: f64 = text.parse().unwrap();
        let got = scan_all(&text);
        prop_assert_eq!(got.len(), 1);
        prop_assert_eq!(got[0].unwrap().to_bits(), reference.to_bits(), "{}", text);
    }
}

/// `v` as C/Python `%.{prec}E` (exponent sign and at least two digits), letter `l`.
fn fortran_e(v: f64, prec: usize, l: &str) -> String {
    let r = format!("{v:.prec$e}");
    let (m, e) = r.split_once('e').unwrap();
    let e: i32 = e.parse().unwrap();
    format!("{m}{l}{}{:02}", if e < 0 { '-' } else { '+' }, e.abs())
}

// ---------------------------------------------------------------------------------------------
// Hand-made fixtures (values are the literals printed in them)

/// A dataset 58, complex double, 3 points, even abscissa, as the standard lays it out.
const DS58_COMPLEX: &str = "    -1
    58
Point 12 FRF
NONE
07-Jun-24 12:00:00
NONE
NONE
    4         1    0         0      BOARD        12   3     HAMMER        99   3
         6         3         1  5.00000E+00  6.25000E-01  0.00000E+00
        18    0    0    0 Frequency            Hz
        11    1   -1    0 Mobility             m/s/N
        13    0    1    0 Force                N
         0    0    0    0 NONE                 NONE
  1.00000000000E+00 -2.00000000000E+00  3.50000000000E-01  4.25000000000E+02
 -5.00000000000E-07  6.00000000000E+00
    -1
";

const DS58_RE: [f64; 3] = [1.0, 0.35, -5.0e-7];
const DS58_IM: [f64; 3] = [-2.0, 425.0, 6.0];

const DS2411: &str = "    -1
  2411
         1         0         0        11
   1.0000000000000000D+01   2.0000000000000000D+01   0.0000000000000000D+00
        99         0         0        11
  -5.0000000000000000D+00   2.5000000000000000D+01   1.5000000000000000D+00
    -1
";

const DS164: &str = "    -1
   164
         5mm (milli newton)            2
    1.00000000000000000D+03    1.00000000000000000D+03    1.00000000000000000D+00
    2.73150000000000000D+02
    -1
";

fn only_function(f: &UffFile) -> &Function58 {
    let fs: Vec<&Function58> = f
        .datasets
        .iter()
        .filter_map(|d| match d {
            Dataset::Function(f) => Some(f),
            _ => None,
        })
        .collect();
    assert_eq!(fs.len(), 1, "expected one function, got {:?}", f.issues);
    fs[0]
}

fn assert_ds58_values(f: &Function58) {
    assert_eq!(f.function_type, FunctionType::Frf);
    assert_eq!(f.ordinate_data_type, OrdinateDataType::ComplexDouble);
    assert_eq!(f.response_node, 12);
    assert_eq!(f.response_direction, 3);
    assert_eq!(f.reference_node, 99);
    assert_eq!(f.reference_entity, "HAMMER");
    assert_eq!(f.id_lines[0], "Point 12 FRF");
    assert_eq!(
        f.abscissa,
        Abscissa::Even {
            min: 5.0,
            increment: 0.625
        }
    );
    assert_eq!(f.abscissa_axis.units_label, "Hz");
    assert_eq!(f.ordinate_axis.label, "Mobility");
    assert_eq!(f.ordinate_axis.force_exp, -1);
    assert_eq!(
        f.ordinate,
        Ordinate::Complex {
            re: DS58_RE.to_vec(),
            im: DS58_IM.to_vec()
        }
    );
}

#[test]
fn reads_the_standard_layout() {
    let text = format!("{DS164}{DS2411}{DS58_COMPLEX}");
    let f = parse(text.as_bytes()).unwrap();
    assert!(f.issues.is_empty(), "{:?}", f.issues);
    assert_eq!(f.datasets.len(), 3);
    let Dataset::Units(u) = &f.datasets[0] else {
        panic!("first dataset should be units")
    };
    assert_eq!((u.units_code, u.temperature_mode), (5, 2));
    assert_eq!(u.description, "mm (milli newton)");
    assert_eq!(u.length_factor, 1000.0);
    assert_eq!(u.temperature_offset, 273.15);
    assert_eq!(u.length_to_metres(5.0), 0.005);
    let Dataset::Nodes(n) = &f.datasets[1] else {
        panic!("second dataset should be nodes")
    };
    assert_eq!(n.source, NodeSource::Ds2411);
    assert_eq!(n.line, 7);
    assert_eq!(n.nodes.len(), 2);
    assert_eq!(n.nodes[1].id, 99);
    assert_eq!(n.nodes[1].color, 11);
    assert_eq!(n.nodes[1].xyz_file_units, [-5.0, 25.0, 1.5]);
    let fun = only_function(&f);
    assert_eq!(fun.line, 14);
    assert_eq!(fun.abscissa_at(2), Some(6.25));
    assert_eq!(fun.abscissa_at(3), None);
    assert_ds58_values(fun);
}

#[test]
fn quirks_crlf_trailing_spaces_blank_lines_indented_delimiters() {
    let crlf = DS58_COMPLEX.replace('\n', "\r\n");
    let trailing = DS58_COMPLEX.replace('\n', "   \n");
    let blank = format!("\n\n{DS2411}\n   \n\n{DS58_COMPLEX}\n\n");
    let indented = DS58_COMPLEX.replace("    -1\n", "        -1  \n");
    let unindented = DS58_COMPLEX.replace("    -1\n", "-1\n");
    let tabs = DS58_COMPLEX.replace("  1.0000", "\t1.0000");
    let bom = format!("\u{feff}{DS58_COMPLEX}");
    let blank_after_open = DS58_COMPLEX.replacen("    -1\n", "    -1\n\n", 1);
    for (name, text) in [
        ("crlf", crlf),
        ("trailing", trailing),
        ("blank", blank),
        ("indented", indented),
        ("unindented", unindented),
        ("tabs", tabs),
        ("byte-order mark", bom),
        ("blank line after the opening -1", blank_after_open),
    ] {
        let f = parse(text.as_bytes()).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert!(f.issues.is_empty(), "{name}: {:?}", f.issues);
        assert_ds58_values(only_function(&f));
    }
}

#[test]
fn quirks_fields_run_together_and_d_exponents() {
    let data_old = "  1.00000000000E+00 -2.00000000000E+00  3.50000000000E-01  4.25000000000E+02
 -5.00000000000E-07  6.00000000000E+00";
    let run_together = "1.00000000000D+00-2.00000000000D+003.50000000000D-014.25000000000D+02
-5.00000000000E-076.00000000000E+00";
    let text = DS58_COMPLEX.replace(data_old, run_together);
    assert_ne!(text, DS58_COMPLEX);
    let f = parse(text.as_bytes()).unwrap();
    assert!(f.issues.is_empty(), "{:?}", f.issues);
    assert_ds58_values(only_function(&f));
}

/// Single precision, real, uneven abscissa (pairs), 6E13.5.
#[test]
fn reads_real_single_uneven_and_other_function_types() {
    let text = "    -1
    58
NONE
NONE
NONE
NONE
NONE
    1         0    0         0       NONE         1   3       NONE         1   3
         2         3         0  0.00000E+00  0.00000E+00  0.00000E+00
        17    0    0    0 Time                 s
         0    0    0    0 NONE                 NONE
         0    0    0    0 NONE                 NONE
         0    0    0    0 NONE                 NONE
  0.00000E+00  1.50000E+00  1.00000E-03 -2.50000E+00  3.00000E-03  1.00000E+02
    -1
";
    let f = parse(text.as_bytes()).unwrap();
    let fun = only_function(&f);
    assert_eq!(fun.function_type, FunctionType::Other(1));
    assert_eq!(fun.ordinate_data_type, OrdinateDataType::RealSingle);
    assert_eq!(fun.abscissa, Abscissa::Uneven(vec![0.0, 1e-3, 3e-3]));
    assert_eq!(fun.ordinate, Ordinate::Real(vec![1.5, -2.5, 100.0]));
}

/// Header text of a 58b with `n_bytes` declared, complex double, 3 points.
fn ds58b_header(byte_order: u8, odt: u8, n_bytes: usize) -> String {
    let mut h = String::from("    -1\n");
    h.push_str(&format!(
        "    58b{byte_order:>6}{:>6}{:>12}{n_bytes:>12}{:>6}{:>6}{:>12}{:>12}\n",
        2, 11, 0, 0, 0, 0
    ));
    let ascii_header: Vec<&str> = DS58_COMPLEX.lines().skip(2).take(11).collect();
    for (k, l) in ascii_header.iter().enumerate() {
        if k == 6 {
            h.push_str(&format!("{odt:>10}{}\n", &l[10..]));
        } else {
            h.push_str(l);
            h.push('\n');
        }
    }
    h
}

fn interleaved() -> Vec<f64> {
    DS58_RE
        .iter()
        .zip(DS58_IM)
        .flat_map(|(&r, i)| [r, i])
        .collect()
}

#[test]
fn binary_58b_byte_orders_precisions_and_trailers() {
    let vals = interleaved();
    let le: Vec<u8> = vals.iter().flat_map(|v| v.to_le_bytes()).collect();
    let be: Vec<u8> = vals.iter().flat_map(|v| v.to_be_bytes()).collect();
    let le32: Vec<u8> = vals
        .iter()
        .flat_map(|v| (*v as f32).to_le_bytes())
        .collect();
    let cases: Vec<(&str, Vec<u8>, bool)> = vec![
        // name, whole file, single precision
        (
            "le, -1 right after data",
            [
                ds58b_header(1, 6, 48).into_bytes(),
                le.clone(),
                b"    -1\n".to_vec(),
            ]
            .concat(),
            false,
        ),
        (
            "be",
            [
                ds58b_header(2, 6, 48).into_bytes(),
                be,
                b"    -1\n".to_vec(),
            ]
            .concat(),
            false,
        ),
        (
            "stray newline (Test.Lab)",
            [
                ds58b_header(1, 6, 48).into_bytes(),
                le.clone(),
                b"\n    -1\n".to_vec(),
            ]
            .concat(),
            false,
        ),
        (
            "CRLF and trailing bytes",
            [
                ds58b_header(1, 6, 48)
                    .into_bytes()
                    .iter()
                    .flat_map(|&b| {
                        if b == b'\n' {
                            vec![b'\r', b'\n']
                        } else {
                            vec![b]
                        }
                    })
                    .collect(),
                le.clone(),
                b"\r\n\x00\x00\x01\r\n    -1\r\n".to_vec(),
            ]
            .concat(),
            false,
        ),
        (
            "no final line end",
            [
                ds58b_header(1, 6, 48).into_bytes(),
                le.clone(),
                b"    -1".to_vec(),
            ]
            .concat(),
            false,
        ),
        (
            "pyuff byte count (points x 8)",
            [
                ds58b_header(1, 6, 24).into_bytes(),
                le.clone(),
                b"    -1\n".to_vec(),
            ]
            .concat(),
            false,
        ),
        (
            "single",
            [
                ds58b_header(1, 5, 24).into_bytes(),
                le32,
                b"    -1\n".to_vec(),
            ]
            .concat(),
            true,
        ),
    ];
    for (name, mut bytes, single) in cases {
        // A second dataset after it must still be found.
        let at_eof = name == "no final line end";
        if !at_eof {
            bytes.extend_from_slice(DS2411.as_bytes());
        }
        let f = parse(&bytes).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert!(f.issues.is_empty(), "{name}: {:?}", f.issues);
        assert_eq!(f.datasets.len(), if at_eof { 1 } else { 2 }, "{name}");
        let fun = only_function(&f);
        assert!(fun.binary);
        let Ordinate::Complex { re, im } = &fun.ordinate else {
            panic!("{name}: not complex")
        };
        if single {
            let r32: Vec<f64> = DS58_RE.iter().map(|&v| f64::from(v as f32)).collect();
            let i32_: Vec<f64> = DS58_IM.iter().map(|&v| f64::from(v as f32)).collect();
            assert_eq!((re, im), (&r32, &i32_), "{name}");
        } else {
            assert_eq!((&re[..], &im[..]), (&DS58_RE[..], &DS58_IM[..]), "{name}");
        }
    }
}

#[test]
fn bad_datasets_become_issues_and_the_others_come_through() {
    let good = DS2411;
    // Line numbers below count from the start of the file: `good` has 7 lines.
    type Case = (&'static str, String, usize, fn(&IssueKind) -> bool);
    let cases: Vec<Case> = vec![
        (
            "wrong count",
            DS58_COMPLEX.replace(
                " -5.00000000000E-07  6.00000000000E+00\n",
                " -5.00000000000E-07\n",
            ),
            7 + 15,
            |k| {
                matches!(
                    k,
                    IssueKind::WrongValueCount {
                        expected: 6,
                        points: 3,
                        found: 5
                    }
                )
            },
        ),
        (
            "non-numeric",
            DS58_COMPLEX.replace("3.50000000000E-01", "3.5000000000OE-01"),
            7 + 14,
            |k| matches!(k, IssueKind::NonNumeric { value_index: 2, .. }),
        ),
        (
            "NaN ordinate",
            DS58_COMPLEX.replace(" 4.25000000000E+02", "               NaN"),
            7 + 14,
            |k| matches!(k, IssueKind::NonFiniteOrdinate { point: 1, .. }),
        ),
        (
            "unknown ordinate type",
            DS58_COMPLEX.replace(
                "         6         3         1",
                "         3         3         1",
            ),
            7 + 9,
            |k| matches!(k, IssueKind::UnknownOrdinateDataType { found: 3 }),
        ),
        (
            "non-numeric header",
            DS58_COMPLEX.replace("    4         1    0", "    x         1    0"),
            7 + 8,
            |k| matches!(k, IssueKind::BadField { record: 6, .. }),
        ),
    ];
    for (name, bad, line, kind_ok) in cases {
        let text = format!("{good}{bad}{good}");
        let f = parse(text.as_bytes()).unwrap();
        assert_eq!(f.issues.len(), 1, "{name}: {:?}", f.issues);
        let issue = &f.issues[0];
        assert_eq!(issue.number, Some(58), "{name}");
        assert_eq!(issue.index, 1, "{name}");
        assert_eq!(issue.line, line, "{name}: {issue}");
        assert!(kind_ok(&issue.kind), "{name}: {issue}");
        assert_eq!(f.datasets.len(), 2, "{name}");
        assert!(!issue.to_string().is_empty());
    }
}

#[test]
fn truncated_file_keeps_the_datasets_before_the_cut() {
    let text = format!("{DS2411}{DS58_COMPLEX}");
    let cut = &text.as_bytes()[..text.len() - 30];
    let f = parse(cut).unwrap();
    assert_eq!(f.datasets.len(), 1);
    assert_eq!(f.issues.len(), 1);
    assert!(
        matches!(f.issues[0].kind, IssueKind::Truncated { .. }),
        "{}",
        f.issues[0]
    );
    // Binary truncated inside the data.
    let mut b = ds58b_header(1, 6, 48).into_bytes();
    b.extend_from_slice(&[0u8; 20]);
    let f = parse(&[DS2411.as_bytes(), &b].concat()).unwrap();
    assert_eq!(f.datasets.len(), 1);
    assert!(matches!(
        f.issues[..],
        [UffIssue {
            kind: IssueKind::Truncated { .. },
            number: Some(58),
            ..
        }]
    ));
}

#[test]
fn other_datasets_are_skipped_and_listed() {
    let text = format!(
        "{DS164}    -1\n  2412\n         1        41         1         1         7         3\n         1         2         3\n    -1\n{DS58_COMPLEX}    -1\n   151\nmodel\n    -1\n"
    );
    let f = parse(text.as_bytes()).unwrap();
    assert!(f.issues.is_empty(), "{:?}", f.issues);
    assert_eq!(f.datasets.len(), 2);
    assert_eq!(
        f.skipped,
        vec![
            SkippedDataset {
                number: 2412,
                line: 7,
                index: 1
            },
            SkippedDataset {
                number: 151,
                line: 28,
                index: 3
            },
        ]
    );
}

/// A normal mode as I-DEAS writes it (record 8 wrapped at six values is the same stream).
const DS55_MODE: &str = "    -1
    55
mode 2
NONE
NONE
NONE
NONE
         1         2         2         8         2         3
         2         4         1         2
  1.03375e+03  0.00000e+00  8.50000e-03  0.00000e+00
         7
  0.00000e+00  0.00000e+00  1.00000e+00
        14
  1.00000e-03 -2.00000e-03 -5.00000e-01
    -1
";

#[test]
fn mode_sets_are_read_and_a_bad_one_is_an_issue_naming_its_record() {
    let f = parse(DS55_MODE.as_bytes()).unwrap();
    assert!(f.issues.is_empty(), "{:?}", f.issues);
    let Dataset::NodalData(m) = &f.datasets[0] else {
        panic!("{:?}", f.datasets)
    };
    let p = m.mode().unwrap();
    assert_eq!(
        (p.mode_number, p.freq_hz, p.damping_ratio),
        (Some(2), 1033.75, 0.0085)
    );
    assert_eq!(m.nodes.len(), 2);
    assert_eq!(m.nodes[1].node, 14);
    assert_eq!(m.nodes[1].re, vec![1e-3, -2e-3, -0.5]);
    // A value that is no number, and a node cut short: each an issue with its line and
    // record; the good mode set and the function after them come through.
    let bad = DS55_MODE.replace("-5.00000e-01", "-5.0000Xe-01");
    let cut = DS55_MODE.replace(
        "  1.00000e-03 -2.00000e-03 -5.00000e-01\n",
        "  1.00000e-03\n",
    );
    let text = format!("{bad}{cut}{DS55_MODE}{DS58_COMPLEX}");
    let f = parse(text.as_bytes()).unwrap();
    assert_eq!(f.issues.len(), 2, "{:?}", f.issues);
    assert_eq!(f.issues[0].line, 14);
    assert!(
        f.issues[0].to_string().contains(
            "record 10, data value at the node: expected a number, found \"-5.0000Xe-01\""
        ),
        "{}",
        f.issues[0]
    );
    assert!(
        f.issues[1]
            .to_string()
            .contains("truncated: expected record 10"),
        "{}",
        f.issues[1]
    );
    assert_eq!(f.datasets.len(), 2);
    assert!(matches!(f.datasets[0], Dataset::NodalData(_)));
    assert!(matches!(f.datasets[1], Dataset::Function(_)));
}

#[test]
fn empty_and_non_uff_inputs_are_errors() {
    assert_eq!(parse(b""), Err(UffError::Empty));
    assert_eq!(parse(b"  \n\r\n"), Err(UffError::Empty));
    let e = parse(b"measurement_id,board_id\nM1,PCB-03\n").unwrap_err();
    assert!(
        matches!(&e, UffError::NotUff { first_line } if first_line == "measurement_id,board_id")
    );
    assert!(e.to_string().contains("not a Universal File"));
}

// ---------------------------------------------------------------------------------------------
// Fuzz-like properties: never panic, whatever the bytes

fn sample_file() -> Vec<u8> {
    let vals = interleaved();
    let le: Vec<u8> = vals.iter().flat_map(|v| v.to_le_bytes()).collect();
    [
        DS164.as_bytes().to_vec(),
        DS2411.as_bytes().to_vec(),
        DS58_COMPLEX.as_bytes().to_vec(),
        ds58b_header(1, 6, 48).into_bytes(),
        le,
        b"\n    -1\n".to_vec(),
    ]
    .concat()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(3000))]
    #[test]
    fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..600)) {
        check_invariants(&bytes)?;
    }

    #[test]
    fn mutated_files_never_panic(
        edits in proptest::collection::vec((any::<usize>(), any::<u8>(), 0u8..4), 1..8),
        cut in any::<usize>(),
    ) {
        let mut b = sample_file();
        for (at, byte, op) in edits {
            let i = at % (b.len() + 1);
            match op {
                0 if i < b.len() => b[i] = byte,
                1 => b.insert(i, byte),
                2 if i < b.len() => { b.remove(i); }
                _ => b.insert(i, [b'-', b'1', b'\n', b' ', b'5', b'8', b'b', b'.'][byte as usize % 8]),
            }
        }
        let n = cut % (b.len() + 1);
        check_invariants(&b)?;
        check_invariants(&b[..n])?;
    }
}

/// What any parse result must satisfy: every line number lies in the input, every opened
/// dataset is reported at most once (issue or skipped), and `Ok` means something was opened.
fn check_invariants(b: &[u8]) -> Result<(), TestCaseError> {
    let last_line = b.iter().filter(|&&c| c == b'\n').count() + 1;
    match parse(b) {
        Ok(f) => {
            let mut seen = std::collections::HashSet::new();
            for i in &f.issues {
                prop_assert!(i.line >= 1 && i.line <= last_line, "{} of {}", i, last_line);
                if !matches!(i.kind, IssueKind::StrayText { .. }) {
                    prop_assert!(seen.insert(i.index), "index {} twice", i.index);
                }
            }
            for sk in &f.skipped {
                prop_assert!(sk.line >= 1 && sk.line <= last_line);
                prop_assert!(seen.insert(sk.index), "index {} twice", sk.index);
            }
            let lines = f.datasets.iter().map(|d| match d {
                Dataset::Units(u) => u.line,
                Dataset::Nodes(n) => n.line,
                Dataset::Function(f) => f.line,
                Dataset::NodalData(m) => m.line,
            });
            for l in lines {
                prop_assert!(l >= 1 && l <= last_line);
            }
            prop_assert!(f.datasets.len() + seen.len() >= 1);
        }
        Err(UffError::Empty) => prop_assert!(b.iter().all(|c| c.is_ascii_whitespace())),
        Err(UffError::NotUff { .. }) => {}
    }
    Ok(())
}

#[test]
fn binary_datasets_of_other_numbers_are_skipped_by_byte_count() {
    // The payload contains a delimiter-like line: only the byte count can skip it.
    let payload = b"\x00\x01\n    -1\n  2411\n\x02\x03";
    let text = [
        format!("    -1\n  2414b     1     2           2{:>12}     0     0           0           0\nline 1\nline 2\n", payload.len()).into_bytes(),
        payload.to_vec(),
        b"\n    -1\n".to_vec(),
        DS2411.as_bytes().to_vec(),
    ]
    .concat();
    let f = parse(&text).unwrap();
    assert!(f.issues.is_empty(), "{:?}", f.issues);
    assert_eq!(
        f.skipped,
        vec![SkippedDataset {
            number: 2414,
            line: 1,
            index: 0
        }]
    );
    assert_eq!(f.datasets.len(), 1);
}

// ---------------------------------------------------------------------------------------------
// Writer: exact records of the standard

#[test]
fn writer_records_match_the_standard_layout() {
    let f = parse(DS58_COMPLEX.as_bytes()).unwrap();
    let fun = only_function(&f);
    let mut out = Vec::new();
    write_58(fun, Format::Ascii, &mut out).unwrap();
    let text = String::from_utf8(out).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    // Record 6: FORMAT(2(I5,I10),2(1X,10A1,I10,I4)); record 7: FORMAT(3I10,3E13.5);
    // data 4E20.12 (12 significant digits).
    assert_eq!(
        lines[7],
        "    4         1    0         0      BOARD        12   3     HAMMER        99   3"
    );
    assert_eq!(
        lines[8],
        "         6         3         1  5.00000E+00  6.25000E-01  0.00000E+00"
    );
    assert_eq!(
        lines[9],
        "        18    0    0    0 Frequency            Hz                  "
    );
    // References: Python's `'%20.11e' % v` (what pyuff writes), upper-cased.
    assert_eq!(
        lines[13],
        "   1.00000000000E+00  -2.00000000000E+00   3.50000000000E-01   4.25000000000E+02"
    );
    assert_eq!(lines[14], "  -5.00000000000E-07   6.00000000000E+00");
    assert_eq!(lines[15], "    -1");
    assert_eq!(lines[1].len(), 80);
}

// ---------------------------------------------------------------------------------------------
// Interop with pyuff

fn interop_dir() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/interop")
}

/// Whether python3 with pyuff can run; panics if it cannot and `HBMU_REQUIRE_INTEROP=1`.
fn pyuff_available(test: &str) -> bool {
    let ok = std::process::Command::new("python3")
        .args(["-c", "import pyuff, numpy"])
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false);
    if !ok {
        if std::env::var("HBMU_REQUIRE_INTEROP").as_deref() == Ok("1") {
            panic!("{test}: python3 with pyuff and numpy is required (HBMU_REQUIRE_INTEROP=1)");
        }
        eprintln!("NOTICE: {test} skipped: python3 with pyuff and numpy not found");
    }
    ok
}

fn close(got: f64, want: f64, rel_tol: f64, scale: f64) -> bool {
    (got - want).abs() <= rel_tol * want.abs() + rel_tol * 1e-6 * scale || got == want
}

/// A JSON array of integers (the fixtures' node labels, colours).
fn json_i64s(v: &serde_json::Value) -> Vec<i64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_i64().unwrap())
        .collect()
}

fn check_array(what: &str, got: &[f64], want: &[serde_json::Value], rel_tol: f64) {
    assert_eq!(got.len(), want.len(), "{what}: length");
    let want: Vec<f64> = want.iter().map(|v| v.as_f64().unwrap()).collect();
    let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    for (k, (g, w)) in got.iter().zip(&want).enumerate() {
        assert!(
            close(*g, *w, rel_tol, scale),
            "{what}[{k}]: expected {w:e}, found {g:e} (rel_tol {rel_tol})"
        );
    }
}

#[test]
fn reads_every_value_pyuff_wrote() {
    if !pyuff_available("reads_every_value_pyuff_wrote") {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let st = std::process::Command::new("python3")
        .arg(interop_dir().join("pyuff_write_fixtures.py"))
        .arg(dir.path())
        .status()
        .unwrap();
    assert!(st.success(), "pyuff_write_fixtures.py failed");
    let exp: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("expected.json")).unwrap()).unwrap();
    let files = exp["files"].as_object().unwrap();
    assert_eq!(files.len(), 6);
    let mut n_checked = 0;
    for (name, spec) in files {
        let bytes = std::fs::read(dir.path().join(name)).unwrap();
        let f = parse(&bytes).unwrap();
        assert!(f.issues.is_empty(), "{name}: {:?}", f.issues);
        assert!(f.skipped.is_empty(), "{name}: {:?}", f.skipped);
        let want = spec["datasets"].as_array().unwrap();
        assert_eq!(f.datasets.len(), want.len(), "{name}");
        let tol = spec["rel_tol"].as_f64().unwrap();
        for (k, (d, w)) in f.datasets.iter().zip(want).enumerate() {
            let tag = format!("{name} #{k}");
            match (d, w["type"].as_u64().unwrap()) {
                (Dataset::Units(u), 164) => {
                    assert_eq!(i64::from(u.units_code), w["units_code"].as_i64().unwrap());
                    assert_eq!(
                        i64::from(u.temperature_mode),
                        w["temp_mode"].as_i64().unwrap()
                    );
                    assert_eq!(u.description, w["description"].as_str().unwrap());
                    let got = [
                        u.length_factor,
                        u.force_factor,
                        u.temperature_factor,
                        u.temperature_offset,
                    ];
                    let keys = ["length", "force", "temp", "temp_offset"];
                    let want: Vec<serde_json::Value> = keys.iter().map(|k| w[*k].clone()).collect();
                    check_array(&tag, &got, &want, 1e-15);
                }
                (Dataset::Nodes(n), t @ (2411 | 15)) => {
                    assert_eq!(u64::from(n.source.number()), t, "{tag}");
                    let ids: Vec<i64> = n.nodes.iter().map(|n| n.id).collect();
                    let want_ids = json_i64s(&w["node_nums"]);
                    assert_eq!(ids, want_ids, "{tag}");
                    let colors: Vec<i64> = n.nodes.iter().map(|n| n.color).collect();
                    let want_c = json_i64s(&w["color"]);
                    assert_eq!(colors, want_c, "{tag}");
                    let ntol = if t == 15 {
                        spec["node_rel_tol"].as_f64().unwrap()
                    } else {
                        1e-15
                    };
                    for (c, key) in ["x", "y", "z"].iter().enumerate() {
                        let got: Vec<f64> = n.nodes.iter().map(|n| n.xyz_file_units[c]).collect();
                        check_array(
                            &format!("{tag} {key}"),
                            &got,
                            w[*key].as_array().unwrap(),
                            ntol,
                        );
                    }
                }
                (Dataset::Function(fun), 58) => {
                    assert_eq!(
                        fun.function_type.code(),
                        w["func_type"].as_i64().unwrap(),
                        "{tag}"
                    );
                    assert_eq!(
                        fun.ordinate_data_type.code(),
                        w["ord_data_type"].as_i64().unwrap(),
                        "{tag}"
                    );
                    assert_eq!(
                        fun.num_points as u64,
                        w["num_pts"].as_u64().unwrap(),
                        "{tag}"
                    );
                    assert_eq!(fun.response_node, w["rsp_node"].as_i64().unwrap(), "{tag}");
                    assert_eq!(
                        fun.response_direction,
                        w["rsp_dir"].as_i64().unwrap(),
                        "{tag}"
                    );
                    assert_eq!(fun.reference_node, w["ref_node"].as_i64().unwrap(), "{tag}");
                    assert_eq!(
                        fun.reference_direction,
                        w["ref_dir"].as_i64().unwrap(),
                        "{tag}"
                    );
                    assert_eq!(
                        fun.response_entity,
                        w["rsp_ent_name"].as_str().unwrap(),
                        "{tag}"
                    );
                    assert_eq!(
                        fun.reference_entity,
                        w["ref_ent_name"].as_str().unwrap(),
                        "{tag}"
                    );
                    assert_eq!(fun.id_lines[0], w["id1"].as_str().unwrap(), "{tag}");
                    assert_eq!(
                        fun.abscissa_axis.units_label,
                        w["abscissa_units"].as_str().unwrap(),
                        "{tag}"
                    );
                    assert_eq!(
                        fun.ordinate_axis.units_label,
                        w["ordinate_units"].as_str().unwrap(),
                        "{tag}"
                    );
                    assert_eq!(
                        fun.ordinate_axis.length_exp,
                        w["ordinate_len_exp"].as_i64().unwrap(),
                        "{tag}"
                    );
                    assert_eq!(
                        fun.ordinate_axis.force_exp,
                        w["ordinate_force_exp"].as_i64().unwrap(),
                        "{tag}"
                    );
                    let wx = w["x"].as_array().unwrap();
                    let x: Vec<f64> = match &fun.abscissa {
                        Abscissa::Even { min, increment } => {
                            assert!(w["even"].as_bool().unwrap(), "{tag}");
                            (0..fun.num_points)
                                .map(|k| min + k as f64 * increment)
                                .collect()
                        }
                        Abscissa::Uneven(x) => {
                            assert!(!w["even"].as_bool().unwrap(), "{tag}");
                            x.clone()
                        }
                    };
                    // Record 7 prints min and increment as E13.5; uneven x are E13.5 too.
                    check_array(
                        &format!("{tag} x"),
                        &x,
                        wx,
                        spec.get("x_rel_tol")
                            .and_then(|v| v.as_f64())
                            .unwrap_or(1e-12)
                            .max(1e-12),
                    );
                    match &fun.ordinate {
                        Ordinate::Real(v) => {
                            assert!(w.get("im").is_none(), "{tag}: expected complex");
                            check_array(&format!("{tag} re"), v, w["re"].as_array().unwrap(), tol);
                        }
                        Ordinate::Complex { re, im } => {
                            check_array(&format!("{tag} re"), re, w["re"].as_array().unwrap(), tol);
                            check_array(&format!("{tag} im"), im, w["im"].as_array().unwrap(), tol);
                        }
                    }
                }
                (Dataset::NodalData(m), 55) => {
                    assert_eq!(
                        m.analysis_type,
                        w["analysis_type"].as_i64().unwrap(),
                        "{tag}"
                    );
                    assert_eq!(m.complex, w["complex"].as_bool().unwrap(), "{tag}");
                    assert_eq!(
                        m.values_per_node as u64,
                        w["ndv"].as_u64().unwrap(),
                        "{tag}"
                    );
                    let mode = m.mode().unwrap();
                    assert_eq!(mode.mode_number, w["mode_n"].as_i64(), "{tag}");
                    // Record 8 is printed as E13.5 (6 significant digits; ζ of a complex mode
                    // carries the rounding of both parts of its eigenvalue).
                    check_array(
                        &format!("{tag} freq, damping"),
                        &[mode.freq_hz, mode.damping_ratio],
                        &[w["freq"].clone(), w["damp"].clone()],
                        1e-5,
                    );
                    let ids: Vec<i64> = m.nodes.iter().map(|n| n.node).collect();
                    let want_ids = json_i64s(&w["node_nums"]);
                    assert_eq!(ids, want_ids, "{tag}");
                    let re: Vec<f64> = m.nodes.iter().flat_map(|n| n.re.clone()).collect();
                    check_array(&format!("{tag} re"), &re, w["re"].as_array().unwrap(), tol);
                    match w.get("im") {
                        Some(want) => {
                            let im: Vec<f64> =
                                m.nodes.iter().flat_map(|n| n.im.clone().unwrap()).collect();
                            check_array(&format!("{tag} im"), &im, want.as_array().unwrap(), tol);
                        }
                        None => assert!(m.nodes.iter().all(|n| n.im.is_none()), "{tag}"),
                    }
                }
                (d, t) => panic!("{tag}: expected dataset type {t}, found {d:?}"),
            }
            n_checked += 1;
        }
    }
    assert_eq!(n_checked, 18);
}

/// A deterministic pseudo-random sequence over many decades (no RNG crate needed here).
fn test_values(n: usize, seed: u64) -> Vec<f64> {
    let mut s = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    (0..n)
        .map(|k| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let u = (s >> 11) as f64 / (1u64 << 53) as f64;
            let e = ((s >> 3) % 14) as i32 - 9;
            if k % 13 == 0 {
                0.0
            } else {
                (u - 0.5) * 2.0 * 10f64.powi(e)
            }
        })
        .collect()
}

fn function(
    function_type: FunctionType,
    odt: OrdinateDataType,
    abscissa: Abscissa,
    n: usize,
    seed: u64,
) -> Function58 {
    let ordinate = if odt.is_complex() {
        Ordinate::Complex {
            re: test_values(n, seed),
            im: test_values(n, seed + 1),
        }
    } else {
        Ordinate::Real(test_values(n, seed).iter().map(|v| v.abs()).collect())
    };
    Function58 {
        id_lines: [
            format!("hbmu writer test {seed}"),
            "NONE".into(),
            "07-Jun-24 12:00:00".into(),
            "NONE".into(),
            "NONE".into(),
        ],
        function_type,
        function_id: 0,
        version: 0,
        load_case: 0,
        response_entity: "BOARD".into(),
        response_node: 100 + seed as i64,
        response_direction: 3,
        reference_entity: "SHAKER".into(),
        reference_node: 999,
        reference_direction: -3,
        ordinate_data_type: odt,
        num_points: n,
        z_axis_value: 0.0,
        abscissa_axis: AxisSpec {
            spec_data_type: 18,
            label: "Frequency".into(),
            units_label: "Hz".into(),
            ..Default::default()
        },
        ordinate_axis: AxisSpec {
            spec_data_type: 12,
            label: "Transmissibility".into(),
            units_label: "1".into(),
            ..Default::default()
        },
        denominator_axis: AxisSpec::default(),
        z_axis: AxisSpec::default(),
        abscissa,
        ordinate,
        binary: false,
        line: 0,
    }
}

fn expected_json(f: &Function58, binary: bool) -> serde_json::Value {
    let n = f.num_points;
    let x: Vec<f64> = match &f.abscissa {
        Abscissa::Even { min, increment } => (0..n).map(|k| min + k as f64 * increment).collect(),
        Abscissa::Uneven(x) => x.clone(),
    };
    let single = !f.ordinate_data_type.is_double();
    // pyuff always reports double-precision data for binary sets it reads as written.
    let tol = if binary {
        if single {
            1e-7
        } else {
            0.0
        }
    } else if single {
        5e-6
    } else {
        5e-12
    };
    let mut v = serde_json::json!({
        "type": 58,
        "func_type": f.function_type.code(),
        "ord_data_type": f.ordinate_data_type.code(),
        "binary": i64::from(binary),
        "num_pts": n,
        "rsp_node": f.response_node,
        "rsp_dir": f.response_direction,
        "ref_node": f.reference_node,
        "ref_dir": f.reference_direction,
        "id1": f.id_lines[0],
        "x": x,
        "rel_tol": tol,
        "x_rel_tol": 5e-6,
    });
    match &f.ordinate {
        Ordinate::Real(r) => v["re"] = serde_json::json!(r),
        Ordinate::Complex { re, im } => {
            v["re"] = serde_json::json!(re);
            v["im"] = serde_json::json!(im);
        }
    }
    v
}

#[test]
fn pyuff_reads_every_value_we_wrote() {
    if !pyuff_available("pyuff_reads_every_value_we_wrote") {
        return;
    }
    use OrdinateDataType::*;
    let even = Abscissa::Even {
        min: 5.0,
        increment: 0.625,
    };
    let uneven = Abscissa::Uneven((0..41).map(|k| 1.0 + (k * k) as f64 * 0.25).collect());
    let mut out = Vec::new();
    let mut exp = Vec::new();
    let units = Units164 {
        units_code: 5,
        description: "mm (milli newton)".into(),
        temperature_mode: 2,
        length_factor: 1000.0,
        force_factor: 1000.0,
        temperature_factor: 1.0,
        temperature_offset: 273.15,
        line: 0,
    };
    write_164(&units, &mut out).unwrap();
    exp.push(
        serde_json::json!({"type": 164, "units_code": 5, "description": "mm (milli newton)",
        "temp_mode": 2, "length": 1000.0, "force": 1000.0, "temp": 1.0, "temp_offset": 273.15,
        "rel_tol": 1e-15}),
    );
    let nodes: Vec<Node> = (0..12)
        .map(|k| Node {
            id: 1 + k * 3,
            def_cs: 0,
            disp_cs: 0,
            color: 11,
            xyz_file_units: [
                80.0 * test_values(12, 7)[k as usize].abs().fract(),
                50.0 / (k + 1) as f64,
                -1.0e-3 * k as f64,
            ],
        })
        .collect();
    for (number, tol) in [(2411, 1e-15), (15, 5e-6)] {
        if number == 2411 {
            write_2411(&nodes, &mut out).unwrap();
        } else {
            write_15(&nodes, &mut out).unwrap();
        }
        exp.push(serde_json::json!({"type": number,
            "node_nums": nodes.iter().map(|n| n.id).collect::<Vec<_>>(),
            "x": nodes.iter().map(|n| n.xyz_file_units[0]).collect::<Vec<_>>(),
            "y": nodes.iter().map(|n| n.xyz_file_units[1]).collect::<Vec<_>>(),
            "z": nodes.iter().map(|n| n.xyz_file_units[2]).collect::<Vec<_>>(),
            "rel_tol": tol}));
    }
    let cases = [
        (
            FunctionType::Frf,
            ComplexDouble,
            even.clone(),
            Format::Ascii,
        ),
        (
            FunctionType::Transmissibility,
            ComplexSingle,
            even.clone(),
            Format::Ascii,
        ),
        (
            FunctionType::Coherence,
            RealDouble,
            even.clone(),
            Format::Ascii,
        ),
        (
            FunctionType::Coherence,
            RealSingle,
            even.clone(),
            Format::Ascii,
        ),
        (FunctionType::Frf, RealDouble, uneven.clone(), Format::Ascii),
        (
            FunctionType::Frf,
            ComplexDouble,
            uneven.clone(),
            Format::Ascii,
        ),
        (
            FunctionType::Frf,
            ComplexSingle,
            uneven.clone(),
            Format::Ascii,
        ),
        (
            FunctionType::Transmissibility,
            ComplexDouble,
            even.clone(),
            Format::Binary,
        ),
        (
            FunctionType::Frf,
            ComplexSingle,
            even.clone(),
            Format::Binary,
        ),
        (
            FunctionType::Coherence,
            RealDouble,
            even.clone(),
            Format::Binary,
        ),
    ];
    for (k, (ft, odt, x, format)) in cases.into_iter().enumerate() {
        let f = function(ft, odt, x, 41, k as u64);
        write_58(&f, format, &mut out).unwrap();
        exp.push(expected_json(&f, format == Format::Binary));
    }
    let dir = tempfile::tempdir().unwrap();
    let uff = dir.path().join("ours.uff");
    let json = dir.path().join("ours.json");
    std::fs::write(&uff, &out).unwrap();
    std::fs::write(
        &json,
        serde_json::to_vec(&serde_json::json!({"datasets": exp})).unwrap(),
    )
    .unwrap();
    let o = std::process::Command::new("python3")
        .arg(interop_dir().join("pyuff_read_check.py"))
        .arg(&uff)
        .arg(&json)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "pyuff_read_check.py: {stdout}{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(stdout.contains("OK 13 datasets"), "{stdout}");
    // Our reader reads our file too (no issue, same count).
    let f = parse(&out).unwrap();
    assert!(f.issues.is_empty(), "{:?}", f.issues);
    assert_eq!(f.datasets.len(), 13);
}

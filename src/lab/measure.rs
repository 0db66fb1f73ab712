//! The virtual instruments: what the vibrometer, the hammer, the shaker and the balance
//! write, as bytes in the formats of `shared/campaign-format.md`.
//!
//! Spectra by modal superposition of the truth modes (mass-normalised shapes φ in 1/√kg,
//! ω in rad/s, damping ratios ζ_r):
//! - free-free hammer mobility, (m/s)/N, driving point d, including the three rigid-body
//!   modes on the foam (suspension frequencies of a few Hz to tens of Hz) and the modes
//!   above the band: H_od(ω) = Σ_r iω φ_or φ_dr / (ω_r² − ω² + 2iζ_r ω_r ω);
//! - bolted base-excitation absolute-velocity transmissibility (board over shaker
//!   reference), dimensionless: T_o(ω) = b_o + Σ_r Γ_r φ_or ω² / (ω_r² − ω² + 2iζ_r ω_r ω),
//!   Γ_r = φ_rᵀ M r, where the rigid base motion r (and b_o, its value at point o) is a
//!   unit translation plus a small rocking about the reference point (the shaker's
//!   cross-axis motion, drawn per measurement), so that antisymmetric modes show too.
//!
//! Noise: circular complex Gaussian with standard deviation σ_o(f) = floor · max|H| +
//! prop · |H_o(f)| per line; coherence γ² = |H|² / (|H|² + σ²). Drop-out points keep 3 %
//! of their signal under ten times the floor; missing points have no record. The file
//! variants rotate with the measurement index so that a campaign exercises every form of
//! the contract: dataset 164 with metres or no 164 (millimetres), 2411 or 15, ASCII or
//! binary 58b, single or double precision.

use faer::c64;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

use super::scenario::Scenario;
use super::truth::{
    BoardDraw, BoardTruth, MeasurementModes, Plan, Planned, SetupKind, HAMMER_POINT,
    SHAKER_REFERENCE_NODE,
};
use super::{child_seed, LabError, Stream};
use crate::fem::Board;
use crate::formats::sheet;
use crate::formats::uff::{
    write_15, write_164, write_2411, write_58, Abscissa, AxisSpec, Format, Function58,
    FunctionType, Node, Ordinate, OrdinateDataType, Units164,
};

/// Shaker reference point in the board frame, m (beside the board, on the armature table).
pub const SHAKER_REFERENCE_M: [f64; 3] = [-0.012, 0.025, -0.008];
/// Damping ratio of the rigid-body modes on the foam.
const SUSPENSION_DAMPING: f64 = 0.05;

/// How one measurement's UFF is written.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FileVariant {
    /// Dataset 164 (SI, metres) present; else coordinates in millimetres.
    pub units_164: bool,
    /// Dataset 15 instead of 2411.
    pub nodes_15: bool,
    pub format: Format,
    pub double: bool,
    pub coherence: bool,
}

/// The variant of measurement `index` (rotates through the contract's forms; mostly
/// binary single precision, which keeps a campaign small: about 1.2 MB per 77 × 2000 lines).
pub fn file_variant(s: &Scenario, index: usize) -> FileVariant {
    let v = index % 6;
    FileVariant {
        units_164: matches!(v, 0 | 3 | 5),
        nodes_15: v == 2,
        format: if v == 0 {
            Format::Ascii
        } else {
            Format::Binary
        },
        double: (v == 0 && index.is_multiple_of(12)) || v == 2,
        coherence: s.measurement.coherence && index % 4 == 1,
    }
}

/// Noise-free spectra of one measurement at `freq_hz`: `h[point][line]`.
pub fn clean_spectra(setup: SetupKind, mm: &MeasurementModes, freq_hz: &[f64]) -> Vec<Vec<c64>> {
    let set = &mm.set;
    let n_pts = set.shapes.first().map_or(0, |s| s.len());
    let two_pi = 2.0 * std::f64::consts::PI;
    // (ω_r, ζ_r, coefficient per point) of every term.
    let mut terms: Vec<(f64, f64, Vec<f64>)> = Vec::new();
    match setup {
        SetupKind::Free => {
            let d = HAMMER_POINT;
            for (k, sh) in set.rigid.iter().enumerate() {
                let w = two_pi * mm.truth.suspension_hz[k];
                terms.push((
                    w,
                    SUSPENSION_DAMPING,
                    sh.iter().map(|p| p * sh[d]).collect(),
                ));
            }
            for (r, sh) in set.shapes.iter().enumerate() {
                let w = two_pi * set.freq_hz[r];
                terms.push((w, mm.damping[r], sh.iter().map(|p| p * sh[d]).collect()));
            }
        }
        SetupKind::Bolted => {
            for (r, sh) in set.shapes.iter().enumerate() {
                let w = two_pi * set.freq_hz[r];
                terms.push((
                    w,
                    mm.damping[r],
                    sh.iter().map(|p| p * set.gamma[r]).collect(),
                ));
            }
        }
    }
    let mut h = vec![vec![c64::new(0.0, 0.0); freq_hz.len()]; n_pts];
    for (k, &f) in freq_hz.iter().enumerate() {
        let w = two_pi * f;
        for (wr, z, coef) in &terms {
            let den = c64::new(wr * wr - w * w, 2.0 * z * wr * w);
            let num = match setup {
                SetupKind::Free => c64::new(0.0, w),
                SetupKind::Bolted => c64::new(w * w, 0.0),
            };
            let g = num / den;
            for (o, c) in coef.iter().enumerate() {
                h[o][k] += g * *c;
            }
        }
        if setup == SetupKind::Bolted {
            for (row, b) in h.iter_mut().zip(&mm.base_motion) {
                row[k] += c64::new(*b, 0.0);
            }
        }
    }
    h
}

fn axis(spec: i64, length_exp: i64, force_exp: i64, label: &str, units: &str) -> AxisSpec {
    AxisSpec {
        spec_data_type: spec,
        length_exp,
        force_exp,
        temperature_exp: 0,
        label: label.into(),
        units_label: units.into(),
    }
}

/// The UFF bytes of one measurement; `points` are its scan points (x, y, z in m), node id =
/// position + 1.
pub fn measurement_uff(
    s: &Scenario,
    points: &[[f64; 3]],
    m: &Planned,
    mm: &MeasurementModes,
    seed: u64,
) -> Result<Vec<u8>, LabError> {
    let inst = &s.measurement;
    let (n, max_hz) = match m.setup {
        SetupKind::Free => (inst.free_lines, inst.free_max_hz),
        SetupKind::Bolted => (inst.bolted_lines, inst.bolted_max_hz),
    };
    let df = max_hz / n as f64;
    let freq: Vec<f64> = (1..=n).map(|k| k as f64 * df).collect();
    let clean = clean_spectra(m.setup, mm, &freq);
    let peak = clean
        .iter()
        .flat_map(|r| r.iter().map(|v| v.norm()))
        .fold(0.0, f64::max);
    let floor = inst.noise_floor_rel * peak;
    let mut rng = ChaCha8Rng::seed_from_u64(child_seed(
        seed,
        Stream::Measurement,
        (1 << 40) | m.index as u64,
    ));
    let var = file_variant(s, m.index);
    let werr = |e: crate::formats::uff::UffWriteError| LabError::Write {
        file: m.file.clone(),
        message: e.to_string(),
    };
    let mut out = Vec::new();
    let scale = if var.units_164 { 1.0 } else { 1e3 };
    if var.units_164 {
        write_164(
            &Units164 {
                units_code: 1,
                description: "SI".into(),
                temperature_mode: 2,
                length_factor: 1.0,
                force_factor: 1.0,
                temperature_factor: 1.0,
                temperature_offset: 273.15,
                line: 0,
            },
            &mut out,
        )
        .map_err(werr)?;
    }
    let mut nodes: Vec<Node> = points
        .iter()
        .enumerate()
        .map(|(o, p)| Node {
            id: o as i64 + 1,
            def_cs: 1,
            disp_cs: 1,
            color: 11,
            xyz_file_units: [p[0] * scale, p[1] * scale, p[2] * scale],
        })
        .collect();
    if m.setup == SetupKind::Bolted {
        nodes.push(Node {
            id: SHAKER_REFERENCE_NODE,
            def_cs: 1,
            disp_cs: 1,
            color: 8,
            xyz_file_units: SHAKER_REFERENCE_M.map(|c| c * scale),
        });
    }
    if var.nodes_15 {
        write_15(&nodes, &mut out).map_err(werr)?;
    } else {
        write_2411(&nodes, &mut out).map_err(werr)?;
    }
    let (ftype, ref_node, ord_axis, den_axis) = match m.setup {
        SetupKind::Free => (
            FunctionType::Frf,
            HAMMER_POINT as i64 + 1,
            axis(11, 1, 0, "Velocity", "m/s"),
            axis(13, 0, 1, "Force", "N"),
        ),
        SetupKind::Bolted => (
            FunctionType::Transmissibility,
            SHAKER_REFERENCE_NODE,
            axis(11, 1, 0, "Velocity", "m/s"),
            axis(11, 1, 0, "Reference velocity", "m/s"),
        ),
    };
    let id_lines = |what: &str| -> [String; 5] {
        [
            format!("hbmu virtual lab: {what}"),
            format!("{} {} {}", m.measurement_id, m.board_id, m.setup.as_str()),
            m.date.clone(),
            "scanning laser vibrometer".into(),
            String::new(),
        ]
    };
    let mut coherence = Vec::new();
    for (o, h0) in clean.iter().enumerate() {
        let node = o as i64 + 1;
        let (u_sig, u_floor) = if m.habits.invalid {
            // A bad measurement (hammer double hit, overload): mostly noise everywhere.
            (0.02, 300.0)
        } else if mm.truth.dropout_nodes.contains(&node) {
            (0.03, 10.0)
        } else {
            (1.0, 1.0)
        };
        // Draw the noise of every point (also missing ones) to keep streams aligned.
        let mut re = Vec::with_capacity(n);
        let mut im = Vec::with_capacity(n);
        let mut coh = Vec::with_capacity(n);
        for v in h0 {
            let sig = *v * u_sig;
            let sigma = floor * u_floor + inst.noise_prop_rel * sig.norm();
            let a: f64 = StandardNormal.sample(&mut rng);
            let b: f64 = StandardNormal.sample(&mut rng);
            let s2 = sigma / std::f64::consts::SQRT_2;
            re.push(sig.re + s2 * a);
            im.push(sig.im + s2 * b);
            let p = sig.norm_sqr();
            coh.push(if p + sigma * sigma > 0.0 {
                p / (p + sigma * sigma)
            } else {
                0.0
            });
        }
        if mm.truth.missing_nodes.contains(&node) {
            continue;
        }
        let f = Function58 {
            id_lines: id_lines(match m.setup {
                SetupKind::Free => "mobility",
                SetupKind::Bolted => "transmissibility",
            }),
            function_type: ftype,
            function_id: node,
            version: 0,
            load_case: 0,
            response_entity: "NONE".into(),
            response_node: node,
            response_direction: 3,
            reference_entity: "NONE".into(),
            reference_node: ref_node,
            reference_direction: 3,
            ordinate_data_type: if var.double {
                OrdinateDataType::ComplexDouble
            } else {
                OrdinateDataType::ComplexSingle
            },
            num_points: n,
            z_axis_value: 0.0,
            abscissa_axis: axis(18, 0, 0, "Frequency", "Hz"),
            ordinate_axis: ord_axis.clone(),
            denominator_axis: den_axis.clone(),
            z_axis: axis(0, 0, 0, "", ""),
            abscissa: Abscissa::Even {
                min: df,
                increment: df,
            },
            ordinate: Ordinate::Complex { re, im },
            binary: var.format == Format::Binary,
            line: 0,
        };
        write_58(&f, var.format, &mut out).map_err(werr)?;
        if var.coherence {
            coherence.push(Function58 {
                id_lines: id_lines("coherence"),
                function_type: FunctionType::Coherence,
                ordinate_data_type: OrdinateDataType::RealSingle,
                ordinate_axis: axis(0, 0, 0, "Coherence", ""),
                denominator_axis: axis(0, 0, 0, "", ""),
                ordinate: Ordinate::Real(coh),
                ..f
            });
        }
    }
    for c in &coherence {
        write_58(c, var.format, &mut out).map_err(werr)?;
    }
    Ok(out)
}

/// The sheet `campaign.csv` (RFC 4180; fields with commas, quotes or newlines are quoted).
/// With `dimensions` (the board file and the drawn boards, scenario
/// `campaign.sheet_dimensions`), each row also gets its board's `length_mm`, `width_mm`
/// (caliper, 0.01 mm) and `thickness_mm` (micrometer, 0.001 mm: the overall thickness, the
/// board's FR-4 core plus the board file's copper layers) as the last columns.
pub fn sheet_csv(
    ms: &[Planned],
    dimensions: Option<(&Board, &[BoardDraw])>,
) -> Result<Vec<u8>, LabError> {
    let werr = |e: csv::Error| LabError::Write {
        file: "campaign.csv".into(),
        message: e.to_string(),
    };
    let mut w = csv::WriterBuilder::new()
        .terminator(csv::Terminator::CRLF)
        .from_writer(Vec::new());
    // The contract's columns in its order; the board dimensions only where they were measured.
    let header: Vec<&str> = sheet::REQUIRED
        .into_iter()
        .chain(sheet::OPTIONAL)
        .filter(|c| dimensions.is_some() || !sheet::DIMENSIONS.contains(c))
        .collect();
    w.write_record(&header).map_err(werr)?;
    for m in ms {
        let h = &m.habits;
        let mut row = vec![
            m.measurement_id.clone(),
            h.sheet_board_id
                .clone()
                .unwrap_or_else(|| m.board_id.clone()),
            m.setup.as_str().to_string(),
            m.file.clone(),
            m.bolted
                .as_ref()
                .map_or(String::new(), |b| b.bolt_set.clone()),
            m.torque_nm.map_or(String::new(), |t| format!("{t}")),
            if h.temperature_blank {
                String::new()
            } else {
                format!("{:.1}", m.temperature_c)
            },
            if h.date_blank {
                String::new()
            } else {
                m.date.clone()
            },
            m.operator.clone(),
            m.notes.clone(),
        ];
        if let Some((board, draws)) = dimensions {
            row.extend([
                format!("{:.2}", 1e3 * board.length_x_m),
                format!("{:.2}", 1e3 * board.width_y_m),
                format!(
                    "{:.3}",
                    1e3 * (draws[m.board].core_thickness_m + board.copper_thickness_m())
                ),
            ]);
        }
        w.write_record(&row).map_err(werr)?;
    }
    w.into_inner().map_err(|e| LabError::Write {
        file: "campaign.csv".into(),
        message: e.to_string(),
    })
}

/// The balance logs and where their deliberate imperfections are.
#[derive(Clone, Debug, Default)]
pub struct BalanceLogs {
    /// (path relative to the campaign, bytes).
    pub files: Vec<(String, Vec<u8>)>,
    /// Garbled stable readings, `file:line` (1-based).
    pub garbled: Vec<String>,
    /// Habit `id_variants`: the stable reading logged under another spelling of its board,
    /// [`file:line`, spelling].
    pub id_variants: Vec<[String; 2]>,
    /// Habit `reweighed_board`: [board_id, file] of the weighing on a later day.
    pub reweighed: Option<[String; 2]>,
}

/// Append `<timestamp> <id> <text>` to a log after advancing the clock by 1–3 s; returns
/// where the line went, `file:line` (1-based).
fn log_line(
    file: &mut (String, String),
    day: &str,
    clock: &mut usize,
    id: &str,
    text: &str,
) -> String {
    *clock += 1 + (*clock % 3);
    let t = *clock;
    file.1.push_str(&format!(
        "{}T{:02}:{:02}:{:02} {} {}\n",
        day,
        t / 3600,
        (t / 60) % 60,
        t % 60,
        id,
        text
    ));
    format!("{}:{}", file.0, file.1.lines().count())
}

/// Habit `reference_weights`: the check weight on the zeroed pan at the start of a
/// session, one unsettled and two stable readings in g (its true mass within ±0.05 mg of
/// 10 g, class E2, plus the balance's repeatability), then taken off and the pan zeroed.
fn check_weight(
    file: &mut (String, String),
    day: &str,
    clock: &mut usize,
    bal: &super::scenario::Balance,
    rng: &mut ChaCha8Rng,
) {
    use super::habits::{CHECK_WEIGHT_G, CHECK_WEIGHT_ID};
    let dec = (-bal.resolution_g.log10()).round() as usize;
    let id = CHECK_WEIGHT_ID;
    log_line(file, day, clock, id, "Z A");
    let true_g = CHECK_WEIGHT_G + 5e-5 * (2.0 * rng.random::<f64>() - 1.0);
    log_line(
        file,
        day,
        clock,
        id,
        &format!("S D {:>12.*} g", dec, true_g + 2e-3),
    );
    for _ in 0..2 {
        let z: f64 = StandardNormal.sample(rng);
        let v = true_g + bal.repeatability_d * bal.resolution_g * z;
        let v = (v / bal.resolution_g).round() * bal.resolution_g;
        log_line(file, day, clock, id, &format!("S S {:>12.*} g", dec, v));
    }
    *clock += 20;
}

/// Balance logs: one file per weighing day; per board and session a tare, unsettled
/// (`S D`) readings converging on the weight, occasional busy/error lines, then stable
/// readings (`S S`) of the weighed mass with the balance's repeatability, rounded to its
/// readability, in g, mg or kg by turns. Now and then a stable reading arrives garbled
/// (a digit replaced by `?`): the ingest reports and drops that line. The habits
/// (`super::habits`) add the check weight and the tray, one misspelt board ID and a board
/// weighed again on a later day.
pub fn balance_logs(s: &Scenario, plan: &Plan, boards: &[BoardTruth]) -> BalanceLogs {
    let bal = &s.balance;
    let hb = s.habits();
    let days = [plan.first_day.clone(), plan.last_day.clone()];
    let mut files: Vec<(String, String)> = days
        .iter()
        .enumerate()
        .map(|(k, d)| {
            (
                format!(
                    "scale/balance_{d}{}.log",
                    if k == 1 && days[0] == days[1] {
                        "_b"
                    } else {
                        ""
                    }
                ),
                format!(
                    "# balance XPR205 (readability {} g), weighing day {d}\n",
                    bal.resolution_g
                ),
            )
        })
        .collect();
    let dec_g = (-bal.resolution_g.log10()).round() as usize;
    let mut out = BalanceLogs::default();
    // The habits draw from their own stream; the tray weighs 2.5–3.5 g.
    let mut hrng = ChaCha8Rng::seed_from_u64(child_seed(plan.seed, Stream::Habits, 1));
    let tray_g = 2.5 + hrng.random::<f64>();
    // The board with the most measurements gets the misspelt line (as on the sheet).
    let variant_board = (0..boards.len()).max_by_key(|&b| {
        (
            plan.measurements.iter().filter(|m| m.board == b).count(),
            usize::MAX - b,
        )
    });
    for sess in 0..bal.sessions_per_board {
        let fi = sess % 2;
        let mut clock = 8 * 3600 + 600 * (sess / 2);
        if hb.reference_weights {
            check_weight(&mut files[fi], &days[fi], &mut clock, bal, &mut hrng);
        }
        for (b, bt) in boards.iter().enumerate() {
            let mut rng = ChaCha8Rng::seed_from_u64(child_seed(
                seed_of(plan),
                Stream::Balance,
                (b * 1000 + sess) as u64,
            ));
            let true_g = bt.weighed_mass_kg * 1e3;
            let (unit, factor, dec) = match (b + sess) % 3 {
                0 => ("g", 1.0, dec_g),
                1 => ("mg", 1e3, dec_g.saturating_sub(3)),
                _ => ("kg", 1e-3, dec_g + 3),
            };
            let id = bt.draw.board_id.as_str();
            let day = days[fi].clone();
            let file = &mut files[fi];
            let fmt = |v_g: f64| format!("{:>12.*} {unit}", dec, v_g * factor);
            if hb.reference_weights {
                // The empty pan zeroed between boards, the tray put on and tared.
                log_line(file, &day, &mut clock, super::habits::TRAY_ID, "Z A");
                log_line(
                    file,
                    &day,
                    &mut clock,
                    super::habits::TRAY_ID,
                    &format!("T S {}", fmt(tray_g)),
                );
            } else {
                log_line(file, &day, &mut clock, id, "Z A");
                log_line(file, &day, &mut clock, id, &format!("T S {}", fmt(0.0)));
            }
            for k in 0..bal.stable_per_session {
                if rng.random::<f64>() < bal.glitch_prob {
                    let g = ["S I", "ES", "S I", "EL"][(rng.random::<f64>() * 4.0) as usize % 4];
                    log_line(file, &day, &mut clock, id, g);
                }
                let n_dyn = if k == 0 { 3 } else { 1 };
                for j in 0..n_dyn {
                    let off = 1e-3 * (1.0 + 20.0 * rng.random::<f64>()) * 0.25f64.powi(j);
                    let sign = if rng.random::<f64>() < 0.5 { -1.0 } else { 1.0 };
                    log_line(
                        file,
                        &day,
                        &mut clock,
                        id,
                        &format!("S D {}", fmt(true_g + sign * off)),
                    );
                }
                let z: f64 = StandardNormal.sample(&mut rng);
                let v = true_g + bal.repeatability_d * bal.resolution_g * z;
                let v = (v / bal.resolution_g).round() * bal.resolution_g;
                if rng.random::<f64>() < bal.garbled_prob {
                    // The garbled line replaces nothing: a clean repeat follows it.
                    let text = fmt(v);
                    let k = text.rfind(|c: char| c.is_ascii_digit()).unwrap_or(0);
                    let bad = format!("{}?{}", &text[..k], &text[k + 1..]);
                    out.garbled
                        .push(log_line(file, &day, &mut clock, id, &format!("S S {bad}")));
                }
                if hb.id_variants && sess == 0 && k == 0 && Some(b) == variant_board {
                    let v_id = super::habits::variant_spelling(id);
                    let at = log_line(file, &day, &mut clock, &v_id, &format!("S S {}", fmt(v)));
                    out.id_variants.push([at, v_id]);
                } else {
                    log_line(file, &day, &mut clock, id, &format!("S S {}", fmt(v)));
                }
            }
            clock += 40;
        }
    }
    if hb.reweighed_board && !boards.is_empty() {
        // One board weighed again two days after the last measurement day, in grams.
        let b = ((hrng.random::<f64>() * boards.len() as f64) as usize).min(boards.len() - 1);
        let bt = &boards[b];
        let day = chrono::NaiveDate::parse_from_str(&plan.last_day, "%Y-%m-%d")
            .map(|d| (d + chrono::Days::new(2)).format("%Y-%m-%d").to_string())
            .unwrap_or_else(|_| plan.last_day.clone());
        let mut file = (
            format!("scale/balance_{day}_recheck.log"),
            format!(
                "# balance XPR205 (readability {} g), re-weighing on {day}\n",
                bal.resolution_g
            ),
        );
        let mut clock = 14 * 3600;
        if hb.reference_weights {
            check_weight(&mut file, &day, &mut clock, bal, &mut hrng);
        }
        let id = bt.draw.board_id.as_str();
        log_line(&mut file, &day, &mut clock, id, "Z A");
        let true_g = bt.weighed_mass_kg * 1e3;
        for _ in 0..bal.stable_per_session {
            let z: f64 = StandardNormal.sample(&mut hrng);
            let v = true_g + bal.repeatability_d * bal.resolution_g * z;
            let v = (v / bal.resolution_g).round() * bal.resolution_g;
            log_line(
                &mut file,
                &day,
                &mut clock,
                id,
                &format!("S S {:>12.*} g", dec_g, v),
            );
        }
        out.reweighed = Some([id.to_string(), file.0.clone()]);
        files.push(file);
    }
    out.files = files
        .into_iter()
        .map(|(n, t)| (n, t.into_bytes()))
        .collect();
    out
}

fn seed_of(plan: &Plan) -> u64 {
    plan.seed
}

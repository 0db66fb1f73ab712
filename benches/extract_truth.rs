//! Modal extraction against the virtual lab's truth: for a work directory whose campaign the
//! lab simulated (`scenario.toml` and `truth.json` next to `extract/`), every identified mode
//! is matched to the truth mode of its measurement with the largest MAC, and per setup and
//! truth mode this prints
//! - the frequency error (mean and sd over the measurements, ppm) and the damping error (%);
//! - the shape residual: the identified shape, unit norm, less its projection on the truth
//!   shape, as a share of the shape (median over the measurements);
//! - whether that residual is common to the measurements: the RMS over the points of its mean
//!   over the measurements, against the RMS a mean of independent residuals would have
//!   (per-measurement RMS / √n). A ratio well above 1 is a systematic extraction error, which
//!   repeated measurements do not average out and which biases what the updating infers from
//!   the shapes (issue 13's compliant fixture: plate-2-2's ratio 1.7).
//!
//! Usage: `cargo bench --bench extract_truth -- WORK_DIR` (default `target/work/paper`).
//! The board is the built-in one (`HBMU_BOARD=FILE` for another). Prints numbers; passes or
//! fails nothing.

use hbmu::bayes::stats::median;
use hbmu::fem::Board;
use hbmu::io::modes_table::read_modes_table;
use hbmu::lab::{truth, Scenario};
use hbmu::modal::mac::mac_real;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// One identified mode matched to its truth mode.
struct Matched {
    setup: String,
    truth_mode: usize,
    truth_hz: f64,
    freq_err_ppm: f64,
    damping_err_percent: f64,
    /// Shape residual at every scan point of the board (NaN where the mode has no value).
    residual: Vec<f64>,
    residual_share: f64,
}

fn main() {
    let work = std::env::args()
        .skip(1)
        .find(|a| !a.starts_with("--"))
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("target/work/paper"));
    for f in ["scenario.toml", "truth.json", "extract/modes.parquet"] {
        if !work.join(f).is_file() {
            eprintln!(
                "extract_truth: no {} in {} (a lab campaign's work directory, e.g. after benches/diagnose_blind.sh)",
                f,
                work.display()
            );
            return;
        }
    }
    let scenario =
        Scenario::from_toml_str(&std::fs::read_to_string(work.join("scenario.toml")).unwrap())
            .expect("scenario.toml");
    let board = match std::env::var_os("HBMU_BOARD") {
        Some(p) => {
            hbmu::io::board_files::read_board(Path::new(&p))
                .expect("HBMU_BOARD")
                .0
        }
        None => Board::default_board(),
    };
    let t: serde_json::Value =
        serde_json::from_slice(&std::fs::read(work.join("truth.json")).unwrap()).unwrap();
    let seed = t["seed"].as_u64().expect("truth.json: seed");
    let plan = truth::plan(&scenario, &board, seed).expect("plan");
    // A solid-truth scenario recomputes its modes with gmsh and CalculiX.
    let solver: Option<std::sync::Arc<dyn hbmu::lab::solid::Solver>> = match scenario.truth.physics
    {
        hbmu::lab::scenario::Physics::Plate => None,
        hbmu::lab::scenario::Physics::Solid => Some(std::sync::Arc::new(
            hbmu::io::external::Calculix::locate().expect("gmsh and ccx"),
        )),
    };
    let models = truth::Models::build(&scenario, &board, solver).expect("truth models");
    let cache = truth::free_board_modes(&scenario, &plan, &models).expect("free modes");
    let mut truths = BTreeMap::new();
    for m in &plan.measurements {
        let ms = truth::measurement_modes(&scenario, &plan, &models, &cache, m).expect("modes");
        truths.insert(m.measurement_id.clone(), ms);
    }
    let n_points = models.points.len();
    let mut matched = vec![];
    for row in read_modes_table(&work.join("extract/modes.parquet")).expect("modes.parquet") {
        let Some(ms) = truths.get(&row.measurement_id) else {
            continue;
        };
        // Node ids are scan points 1..n in the lab's order.
        let pts: Vec<(usize, f64)> = row
            .node
            .iter()
            .zip(&row.shape)
            .filter(|(n, v)| v.is_finite() && **n >= 1 && (**n as usize) <= n_points)
            .map(|(n, v)| (*n as usize - 1, *v))
            .collect();
        let un = pts.iter().map(|(_, v)| v * v).sum::<f64>().sqrt();
        if pts.len() < 3 || un == 0.0 {
            continue;
        }
        let u: Vec<f64> = pts.iter().map(|(_, v)| *v).collect();
        let at_points = |s: &[f64]| -> Vec<f64> { pts.iter().map(|(o, _)| s[*o]).collect() };
        let Some((r, _)) = ms
            .set
            .shapes
            .iter()
            .enumerate()
            .map(|(r, s)| (r, mac_real(&u, &at_points(s))))
            .max_by(|a, b| a.1.total_cmp(&b.1))
        else {
            continue;
        };
        // The truth shape with a sign fixed by the shape itself (its largest entry
        // positive), so that the residuals of different measurements can be averaged;
        // the identified shape turned to agree with it.
        let s = &ms.set.shapes[r];
        let big = s
            .iter()
            .copied()
            .max_by(|a, b| a.abs().total_cmp(&b.abs()))
            .unwrap_or(1.0);
        let sn = pts.iter().map(|(o, _)| s[*o] * s[*o]).sum::<f64>().sqrt() * big.signum();
        let a: f64 = pts.iter().map(|(o, v)| v / un * s[*o] / sn).sum();
        let mut residual = vec![f64::NAN; n_points];
        let mut rr = 0.0;
        for (o, v) in &pts {
            let e = a.signum() * v / un - a.abs() * s[*o] / sn;
            residual[*o] = e;
            rr += e * e;
        }
        matched.push(Matched {
            setup: row.setup.clone(),
            truth_mode: r,
            truth_hz: ms.set.freq_hz[r],
            freq_err_ppm: 1e6 * (row.freq_hz / ms.set.freq_hz[r] - 1.0),
            damping_err_percent: 100.0 * (row.damping_ratio / ms.damping[r] - 1.0),
            residual,
            residual_share: rr.sqrt(),
        });
    }
    let mut groups: BTreeMap<(String, usize), Vec<&Matched>> = BTreeMap::new();
    for m in &matched {
        groups
            .entry((m.setup.clone(), m.truth_mode))
            .or_default()
            .push(m);
    }
    println!(
        "extract vs truth: {} ({} identified modes matched)",
        work.display(),
        matched.len()
    );
    println!(
        "{:<7} {:>4} {:>9} {:>3} {:>9} {:>9} {:>8} {:>10} {:>10} {:>6}",
        "setup", "mode", "truth Hz", "n", "df ppm", "sd ppm", "dζ %", "resid", "mean/rand", "ratio"
    );
    for ((setup, r), v) in groups {
        let n = v.len() as f64;
        let mean = |g: &dyn Fn(&Matched) -> f64| v.iter().map(|m| g(m)).sum::<f64>() / n;
        let df = mean(&|m| m.freq_err_ppm);
        let sd = (v.iter().map(|m| (m.freq_err_ppm - df).powi(2)).sum::<f64>()
            / (n - 1.0).max(1.0))
        .sqrt();
        let dz = mean(&|m| m.damping_err_percent);
        let med = median(&v.iter().map(|m| m.residual_share).collect::<Vec<_>>());
        // RMS over points of the mean residual, and per measurement.
        let (mut ms2, mut np) = (0.0, 0usize);
        let mut per = 0.0;
        for o in 0..n_points {
            let vals: Vec<f64> = v
                .iter()
                .map(|m| m.residual[o])
                .filter(|x| x.is_finite())
                .collect();
            if vals.len() < 2 {
                continue;
            }
            let mu = vals.iter().sum::<f64>() / vals.len() as f64;
            ms2 += mu * mu;
            per += vals.iter().map(|x| x * x).sum::<f64>() / vals.len() as f64;
            np += 1;
        }
        let (mean_rms, rand_rms) = if np > 0 {
            ((ms2 / np as f64).sqrt(), (per / np as f64 / n).sqrt())
        } else {
            (f64::NAN, f64::NAN)
        };
        println!(
            "{setup:<7} {:>4} {:>9.1} {:>3} {df:>9.1} {sd:>9.1} {dz:>8.2} {med:>10.2e} {:>10} {:>6.2}",
            r + 1,
            v[0].truth_hz,
            v.len(),
            format!("{mean_rms:.1e}/{rand_rms:.1e}"),
            mean_rms / rand_rms
        );
    }
}

//! Benchmark and side-by-side check of the modal extraction against sdypy-EMA.
//!
//! Synthesises free-free mobility FRFs of an 80 x 50 mm plate (77 scan points on an 11 x 7
//! grid, 2000 lines to 2 kHz, 8 plate-like modes including a pair 0.6 % apart, rigid-body
//! and upper residuals, 0.5 % noise floor + 1 % proportional noise), for several seeds;
//! writes them with the truth to a temporary directory (.npy + .json), times
//! `hbmu::modal::extract` (model orders up to 60), then runs
//! `benches/modal_vs_sdypy.py`, which times sdypy-EMA's LSCF + LSFD on the same files
//! (given the true frequencies as pole-picking hints) and prints the comparison table.
//!
//! Run: `cargo bench --bench modal` (needs `python3` with `sdypy-EMA` and `numpy`; without
//! them only our numbers are printed).

use std::path::Path;
use std::time::Instant;

use hbmu::modal::{self, frf, ExtractParams, FunctionKind, MeasurementSpectra, PointSpectrum};

const MODES: [(usize, usize, f64, f64); 8] = [
    (1, 1, 182.0, 0.012),
    (0, 2, 341.0, 0.010),
    (2, 0, 452.0, 0.008),
    (2, 1, 601.0, 0.011),
    (1, 2, 604.6, 0.009),
    (3, 0, 1012.0, 0.010),
    (0, 3, 1187.0, 0.013),
    (3, 1, 1530.0, 0.015),
];

struct Synth {
    freq_hz: Vec<f64>,
    h: Vec<Vec<faer::c64>>,
    shapes: Vec<Vec<f64>>,
}

fn synth(seed: u64) -> Synth {
    use rand::SeedableRng;
    let (l, w) = (0.08, 0.05);
    let grid = frf::grid_points(11, 7, l, w);
    let n_lines = 2000;
    let freq_hz: Vec<f64> = (1..=n_lines).map(|k| k as f64).collect();
    let amp = (1.0f64 / 0.02).sqrt();
    let mut modes = Vec::new();
    let mut shapes = Vec::new();
    for &(kx, ky, f, z) in &MODES {
        let phi: Vec<f64> = grid
            .iter()
            .map(|&(x, y)| amp * frf::plate_like_shape(kx, ky, x / l, y / w))
            .collect();
        let lam = frf::pole(f, z);
        modes.push(frf::SynthMode {
            lambda: lam,
            residues: frf::mobility_residues(lam, &phi, phi[0]),
        });
        shapes.push(phi);
    }
    let residuals = vec![
        frf::ResidualTerm {
            power: -1,
            coeffs: grid
                .iter()
                .map(|&(x, _)| 50.0 * (1.0 - 0.8 * (2.0 * x / l - 1.0)))
                .collect(),
        },
        frf::ResidualTerm {
            power: 1,
            coeffs: vec![2e-5; grid.len()],
        },
    ];
    let mut h = frf::synthesize(&freq_hz, &modes, &residuals);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    frf::add_noise(&mut h, 0.005, 0.01, &mut rng);
    Synth { freq_hz, h, shapes }
}

/// Write a .npy file (format 1.0, little-endian, C order) with the crate's NPY encoder.
fn write_npy(path: &Path, descr: &str, shape: &[usize], data: &[u8]) -> std::io::Result<()> {
    std::fs::write(path, hbmu::fem::npz::npy(descr, shape, data))
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let seeds: Vec<u64> = (1..=5).collect();
    let dir = std::env::temp_dir().join(format!("hbmu-modal-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let params = ExtractParams::default();
    let reps = 5;
    // Our time on one thread (like sdypy-EMA, whose LSCF is a Python loop over orders) and
    // on the machine's default rayon pool (the extract stage instead runs one measurement
    // per core, so the one-thread number is also its per-core cost).
    let pool1 = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
    let threads = rayon::current_num_threads();
    let mut all_times = Vec::new();
    let mut all_times_pool = Vec::new();
    for &seed in &seeds {
        let s = synth(seed);
        let spectra = MeasurementSpectra {
            freq_hz: s.freq_hz.clone(),
            points: s
                .h
                .iter()
                .enumerate()
                .map(|(i, row)| PointSpectrum {
                    node_id: i as i64 + 1,
                    re: row.iter().map(|v| v.re).collect(),
                    im: row.iter().map(|v| v.im).collect(),
                    coherence: None,
                })
                .collect(),
            kind: FunctionKind::Mobility,
        };
        let median_time = |f: &dyn Fn() -> Result<modal::Extraction, modal::ModalError>| {
            let mut times = Vec::new();
            let mut ex = None;
            for _ in 0..reps {
                let t0 = Instant::now();
                let r = f();
                times.push(t0.elapsed().as_secs_f64());
                ex = Some(r);
            }
            times.sort_by(|a, b| a.total_cmp(b));
            (times[times.len() / 2], ex.expect("reps > 0"))
        };
        let (t_med, ex) = median_time(&|| pool1.install(|| modal::extract(&spectra, &params)));
        let ex = ex?;
        let (t_pool, ex_pool) = median_time(&|| modal::extract(&spectra, &params));
        assert_eq!(ex, ex_pool?, "result depends on the thread count");
        all_times.push(t_med);
        all_times_pool.push(t_pool);
        // For information: only the steps sdypy-EMA runs (one LSCF pass, then LSFD; plus
        // our automatic selection, which sdypy leaves to the user), i.e. no second
        // Sanathanan-Koerner pass, no output-error refinement, no refit without outliers.
        let lean_params = ExtractParams {
            sk_passes: 0,
            refine: None,
            refit_passes: 0,
            ..params.clone()
        };
        let (t_lean, ex_lean) =
            median_time(&|| pool1.install(|| modal::extract(&spectra, &lean_params)));
        let ex_lean = ex_lean?;
        let lean: Vec<serde_json::Value> = ex_lean
            .modes
            .iter()
            .map(|m| serde_json::json!({"freq_hz": m.freq_hz, "damping_ratio": m.damping_ratio, "shape": m.shape}))
            .collect();
        // Files for the Python side.
        let sub = dir.join(format!("seed{seed}"));
        std::fs::create_dir_all(&sub)?;
        let fb: Vec<u8> = s.freq_hz.iter().flat_map(|v| v.to_le_bytes()).collect();
        write_npy(&sub.join("freq.npy"), "<f8", &[s.freq_hz.len()], &fb)?;
        let hb: Vec<u8> =
            s.h.iter()
                .flat_map(|row| {
                    row.iter()
                        .flat_map(|v| [v.re.to_le_bytes(), v.im.to_le_bytes()].concat())
                })
                .collect();
        write_npy(
            &sub.join("frf.npy"),
            "<c16",
            &[s.h.len(), s.freq_hz.len()],
            &hb,
        )?;
        let ours: Vec<serde_json::Value> = ex
            .modes
            .iter()
            .map(|m| serde_json::json!({"freq_hz": m.freq_hz, "damping_ratio": m.damping_ratio, "shape": m.shape}))
            .collect();
        let j = serde_json::json!({
            "truth": {
                "freq_hz": MODES.iter().map(|m| m.2).collect::<Vec<_>>(),
                "damping_ratio": MODES.iter().map(|m| m.3).collect::<Vec<_>>(),
                "shapes": s.shapes,
            },
            "ours": {"modes": ours, "time_s": t_med, "time_s_pool": t_pool, "threads": threads, "max_order": params.lscf.max_order},
            "ours_lean": {"modes": lean, "time_s": t_lean},
        });
        std::fs::write(sub.join("case.json"), serde_json::to_string(&j)?)?;
        println!(
            "seed {seed}: ours {} modes in {:.1} ms on 1 thread, {:.1} ms on {threads} (median of {reps})",
            ex.modes.len(),
            1e3 * t_med,
            1e3 * t_pool
        );
    }
    all_times.sort_by(|a, b| a.total_cmp(b));
    all_times_pool.sort_by(|a, b| a.total_cmp(b));
    println!(
        "ours: extraction per measurement (77 points x 2000 lines, orders 4..{} step {}, {} SK passes): median {:.1} ms on 1 thread, {:.1} ms on {threads}",
        params.lscf.max_order,
        params.lscf.order_step,
        params.sk_passes,
        1e3 * all_times[all_times.len() / 2],
        1e3 * all_times_pool[all_times_pool.len() / 2]
    );
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/modal_vs_sdypy.py");
    match std::process::Command::new("python3")
        .arg(&script)
        .arg(&dir)
        .status()
    {
        Ok(st) if st.success() => {}
        Ok(st) => println!("sdypy comparison failed ({st}); our numbers above stand alone"),
        Err(e) => println!("python3 not runnable ({e}); our numbers above stand alone"),
    }
    std::fs::remove_dir_all(&dir)?;
    Ok(())
}

//! Propagation throughput: board-frequency vectors (one ROM evaluation: every label of one
//! board in one setup) per second, on the posterior of a work directory (default: the demo's,
//! `target/work/paper`; `HBMU_PROPAGATE_BENCH_WORK=DIR` for another), at 1 and 2 threads and
//! several draw counts (the cost is linear in draws). Prints numbers; passes or fails nothing.

use hbmu::stage::propagate::{run, PropagateOptions};
use std::path::PathBuf;

fn main() {
    let work = std::env::var_os("HBMU_PROPAGATE_BENCH_WORK")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("target/work/paper"));
    let mut dirs = vec![work.join("update_boards")];
    if work.join("update_joints/joints.parquet").is_file() {
        dirs.push(work.join("update_joints"));
    }
    if !dirs[0].join("boards.parquet").is_file() {
        eprintln!(
            "propagate bench: no step-1 posterior in {} (run `make -C pipelines demo` first)",
            dirs[0].display()
        );
        return;
    }
    let out = tempfile::tempdir().expect("temp dir");
    println!(
        "propagate: posterior {} ({} step(s))",
        work.display(),
        dirs.len()
    );
    for threads in [1usize, 2] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("pool");
        for draws in [1000usize, 4000, 16000] {
            let opts = PropagateOptions {
                update_dirs: dirs.clone(),
                pair_dir: None,
                fe_dir: None,
                out: out.path().join(format!("t{threads}_d{draws}")),
                force: true,
                draws,
                seed: 1,
                rom_box: 0.2,
            };
            let o = pool.install(|| run(&opts, false)).expect("propagate");
            let s = &o.manifest.summary;
            println!(
                "threads {threads} draws {draws:6}: {} evaluations in {:.3} s = {:.0} board-frequency vectors/s",
                s["evaluations"],
                s["propagation_seconds"].as_f64().unwrap_or(f64::NAN),
                s["board_frequency_vectors_per_second"].as_f64().unwrap_or(f64::NAN)
            );
        }
    }
}

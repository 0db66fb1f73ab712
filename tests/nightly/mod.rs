//! The pipeline as a whole, through `pipelines/Makefile`: outputs independent of where the work
//! directory lies, and the nightly on a real (single-node, localhost) Slurm cluster: same bytes
//! as the local run, a cancelled stage redone by the next nightly, a second nightly a no-op,
//! only a changed campaign reprocessed.
//!
//! Every stage runs through a wrapper around the real `hbmu` (written by [`Wrapper`]) that logs
//! each invocation, so that "what ran" is observed, not inferred from timestamps; it can also
//! hold one chosen stage at its start, so that the test can cancel it while it runs.

use crate::common::repo;
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::{Duration, Instant};

fn small_scenario() -> PathBuf {
    repo().join("tests/nightly/small.toml")
}

/// The board these tests' pipelines run on: the built-in board as a thin plate
/// (`data/boards/paper_thin.toml`). What they check (bytes, caching, scheduling, recovery
/// from a cancel) does not depend on the plate theory, and the thin plate's models build in
/// a fifth of a shear-deformable board's time; the built-in board runs end to end in the
/// demo (CI's main job), tests/lab and tests/report.
fn thin_board() -> PathBuf {
    repo().join("data/boards/paper_thin.toml")
}

/// `make -C pipelines ARGS` with our binary, never rebuilding it (CARGO=true), and no model
/// cache unless `envs` names one (HBMU_CACHE); on [`thin_board`] unless ARGS name a BOARD.
fn make(args: &[String], envs: &[(&str, &Path)]) -> Output {
    let mut c = Command::new("make");
    c.arg("-C")
        .arg(repo().join("pipelines"))
        .arg("--no-print-directory")
        .arg("CARGO=true")
        .args(args)
        .env("CI", "1")
        .env("HBMU_CACHE", "");
    if !args.iter().any(|a| a.starts_with("BOARD=")) {
        c.arg(format!("BOARD={}", thin_board().display()));
    }
    for (k, v) in envs {
        c.env(k, v);
    }
    c.output().expect("run make")
}

fn assert_ok(o: &Output, what: &str) {
    assert!(
        o.status.success(),
        "{what} failed ({}):\nstdout:\n{}\nstderr:\n{}",
        o.status,
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
}

/// Every file under `dir`, relative, sorted.
fn files_under(dir: &Path) -> Vec<PathBuf> {
    fn walk(base: &Path, d: &Path, out: &mut Vec<PathBuf>) {
        for e in std::fs::read_dir(d).unwrap() {
            let e = e.unwrap();
            let p = e.path();
            if e.file_type().unwrap().is_dir() {
                walk(base, &p, out);
            } else {
                out.push(p.strip_prefix(base).unwrap().to_path_buf());
            }
        }
    }
    let mut out = vec![];
    walk(dir, dir, &mut out);
    out.sort();
    out
}

/// A manifest without its wall-clock facts (`run`: start time, duration, threads; and the
/// timings some stages add to their summary: `*_seconds`, throughputs `*_per_second`), which
/// are the only part allowed to differ between two runs.
fn manifest_without_run(p: &Path) -> serde_json::Value {
    let mut v: serde_json::Value = serde_json::from_slice(&std::fs::read(p).unwrap()).unwrap();
    let m = v.as_object_mut().unwrap();
    m.remove("run");
    if let Some(s) = m.get_mut("summary").and_then(|s| s.as_object_mut()) {
        s.retain(|k, _| !k.ends_with("_seconds") && !k.ends_with("_per_second"));
    }
    v
}

/// The two trees hold the same files with the same bytes (manifests: the same apart from
/// `run`); `skip` names relative paths left out (logs of the scheduler).
fn assert_same_tree(a: &Path, b: &Path, skip: &dyn Fn(&Path) -> bool) {
    let fa: Vec<_> = files_under(a).into_iter().filter(|p| !skip(p)).collect();
    let fb: Vec<_> = files_under(b).into_iter().filter(|p| !skip(p)).collect();
    assert_eq!(fa, fb, "the two work directories hold different files");
    assert!(fa.len() > 10, "too few outputs to compare: {fa:?}");
    for rel in &fa {
        let (pa, pb) = (a.join(rel), b.join(rel));
        if rel.to_string_lossy().ends_with(".manifest.json") {
            assert_eq!(
                manifest_without_run(&pa),
                manifest_without_run(&pb),
                "manifest {} differs",
                rel.display()
            );
        } else {
            assert!(
                std::fs::read(&pa).unwrap() == std::fs::read(&pb).unwrap(),
                "{} differs between {} and {}",
                rel.display(),
                a.display(),
                b.display()
            );
        }
    }
}

#[test]
fn whole_dag_gives_the_same_bytes_in_two_work_directories() {
    let t = tempfile::tempdir().unwrap();
    // Two places of different depth and parent names; each run simulates its own campaign.
    // The work directory's own name is the same: the report takes its title from it.
    let a = t.path().join("a/work");
    let b = t.path().join("elsewhere/deeper/b/work");
    for w in [&a, &b] {
        let o = make(
            &[
                "all".into(),
                format!("SCENARIO={}", small_scenario().display()),
                format!("WORK={}", w.display()),
                format!("HBMU={}", env!("CARGO_BIN_EXE_hbmu")),
                "UPDATE_PARTICLES=100".into(),
                "PROPAGATE_DRAWS=400".into(),
            ],
            &[],
        );
        assert_ok(&o, &format!("make all in {}", w.display()));
    }
    // `all` is the whole job up to the report: both steps of the updating included.
    for stage in [
        "ingest",
        "extract",
        "pair",
        "fe",
        "update_boards",
        "update_joints",
        "propagate",
        "report",
    ] {
        assert!(a.join(stage).is_dir(), "stage {stage} wrote nothing");
    }
    assert!(a.join("update_joints/joints.parquet").is_file());
    assert!(a.join("report/report.html").is_file());
    assert_same_tree(&a, &b, &|_| false);
}

/// Campaigns with the same board share the model artifacts: the second builds none of them
/// (the board given as a copy at another path: keys hold no path), gets the same bytes, and a
/// changed board builds its own.
#[test]
fn model_artifacts_are_built_once_for_campaigns_with_the_same_board() {
    let t = tempfile::tempdir().unwrap();
    let cache = t.path().join("cache");
    let board_copy = t.path().join("boards/same-board.toml");
    std::fs::create_dir_all(board_copy.parent().unwrap()).unwrap();
    std::fs::copy(thin_board(), &board_copy).unwrap();
    let changed = t.path().join("boards/thicker.toml");
    let text = std::fs::read_to_string(thin_board()).unwrap();
    assert!(text.contains("thickness_m = 1.5e-3"));
    std::fs::write(
        &changed,
        text.replace("thickness_m = 1.5e-3", "thickness_m = 1.6e-3"),
    )
    .unwrap();
    let run = |work: &str, board: Option<&Path>| -> (usize, usize) {
        let mut args = vec![
            "fe".to_string(),
            format!("WORK={}", t.path().join(work).display()),
            format!("HBMU={}", env!("CARGO_BIN_EXE_hbmu")),
        ];
        if let Some(b) = board {
            args.push(format!("BOARD={}", b.display()));
        }
        let o = make(&args, &[("HBMU_CACHE", cache.as_path())]);
        assert_ok(&o, &format!("make fe WORK={work}"));
        let err = String::from_utf8_lossy(&o.stderr);
        (
            err.matches("built, published to the cache").count(),
            err.matches("from the cache").count(),
        )
    };
    // rom_free, rom_bolted, sensitivity_free: three artifacts.
    assert_eq!(
        run("w1", None),
        (3, 0),
        "first campaign builds every artifact"
    );
    assert_eq!(run("w2", Some(&board_copy)), (0, 3), "same board: no build");
    for f in ["rom_free.npz", "rom_bolted.npz", "sensitivity_free.parquet"] {
        let a = std::fs::read(t.path().join("w1/fe").join(f)).unwrap();
        let b = std::fs::read(t.path().join("w2/fe").join(f)).unwrap();
        assert!(a == b, "{f} differs between the built and the cached copy");
    }
    assert_eq!(
        run("w3", Some(&changed)),
        (3, 0),
        "a changed board builds its own"
    );
    let a = std::fs::read(t.path().join("w1/fe/rom_free.npz")).unwrap();
    let c = std::fs::read(t.path().join("w3/fe/rom_free.npz")).unwrap();
    assert!(a != c, "the changed board's ROM is a different artifact");
}

/// Jobs that miss the cache at the same moment (four `hbmu fe rom` processes, one key) all
/// succeed with the same bytes, and leave one valid entry and no temp file in the cache.
#[test]
fn concurrent_jobs_on_one_cache_key_leave_a_valid_artifact() {
    let t = tempfile::tempdir().unwrap();
    let cache = t.path().join("cache");
    let children: Vec<_> = (0..4)
        .map(|i| {
            Command::new(env!("CARGO_BIN_EXE_hbmu"))
                // A coarse mesh and few modes: the race is on the cache key, not the model
                // (the default board's ROM took 70 s of CPU per job here).
                .args(["fe", "rom", "--setup", "free", "--mesh", "16", "10"])
                .args(["--n-modes", "4", "--out"])
                .arg(t.path().join(format!("w{i}/rom_free.npz")))
                .env("HBMU_CACHE", &cache)
                .env("CI", "1")
                .stderr(std::process::Stdio::piped())
                .spawn()
                .unwrap()
        })
        .collect();
    let mut built = 0;
    for c in children {
        let o = c.wait_with_output().unwrap();
        assert_ok(&o, "hbmu fe rom");
        built += String::from_utf8_lossy(&o.stderr)
            .matches("built, published")
            .count();
    }
    assert!((1..=4).contains(&built), "{built} builds");
    let first = std::fs::read(t.path().join("w0/rom_free.npz")).unwrap();
    for i in 1..4 {
        let other = std::fs::read(t.path().join(format!("w{i}/rom_free.npz"))).unwrap();
        assert!(first == other, "job {i} got other bytes");
    }
    let entries = files_under(&cache);
    assert_eq!(
        entries.len(),
        2,
        "one artifact and its sidecar: {entries:?}"
    );
    let npz = entries
        .iter()
        .find(|p| p.extension().is_some_and(|e| e == "npz"))
        .unwrap();
    assert!(std::fs::read(cache.join(npz)).unwrap() == first);
    let sidecar = std::fs::read_to_string(cache.join(format!("{}.blake3", npz.display()))).unwrap();
    assert_eq!(sidecar.trim(), blake3::hash(&first).to_hex().as_str());
}

/// `pipelines/slurm/fanout.sh` under a scheduler: every task runs once with its index in the
/// arguments and the environment; the status is 0, 3 when some quarantined, 1 naming the
/// failed tasks.
fn check_fanout(scheduler: &str, dir: &Path, envs: &[(&str, &Path)]) {
    let fanout = repo().join("pipelines/slurm/fanout.sh");
    let run = |name: &str, fail: &str| -> Output {
        let script = format!(
            "echo \"$HBMU_TASK/$HBMU_TASKS\" > '{}/{name}-part-'\"$1\"; case \" {fail} \" in *\" $1 \"*) exit $1 ;; esac",
            dir.display()
        );
        let mut c = Command::new(&fanout);
        c.args([scheduler, name, "4"])
            .arg(dir.join("logs"))
            .args(["--time=5", "--", "sh", "-c", &script, "task", "{task}"]);
        for (k, v) in envs {
            c.env(k, v);
        }
        c.output().expect("run fanout.sh")
    };
    let o = run("ok", "");
    assert_ok(&o, "fanout with no failure");
    for t in 0..4 {
        let part = std::fs::read_to_string(dir.join(format!("ok-part-{t}"))).unwrap();
        assert_eq!(part.trim(), format!("{t}/4"));
    }
    // Task 3 exits 3 (quarantined): success with 3.
    assert_eq!(run("q", "3").status.code(), Some(3));
    // Task 1 fails, task 3 quarantines: failure, naming task 1; every task still ran.
    let o = run("f", "1 3");
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains(" 1(1)") && !err.contains(" 3(3)"), "{err}");
    for t in 0..4 {
        assert!(
            dir.join(format!("f-part-{t}")).exists(),
            "task {t} did not run"
        );
    }
}

#[test]
fn fanout_runs_every_task_once_and_reports_failures_locally() {
    let t = tempfile::tempdir().unwrap();
    check_fanout("local", t.path(), &[]);
}

/// A shell wrapper around `hbmu` that appends each invocation (its arguments) to `log`, and
/// holds an invocation whose arguments contain every word of the `gate` file's first line at
/// its start (writing `held` with its Slurm job id) until the gate file is removed.
struct Wrapper {
    path: PathBuf,
    log: PathBuf,
    gate: PathBuf,
    held: PathBuf,
}

impl Wrapper {
    fn new(dir: &Path) -> Wrapper {
        let w = Wrapper {
            path: dir.join("hbmu-logged"),
            log: dir.join("invocations.log"),
            gate: dir.join("gate"),
            held: dir.join("held"),
        };
        let script = format!(
            r#"#!/bin/sh
echo "$*" >> '{log}'
if [ -f '{gate}' ]; then
  match=1
  for word in $(head -n 1 '{gate}'); do
    case " $* " in *" $word "*) ;; *) match=0 ;; esac
  done
  if [ $match = 1 ]; then
    echo "${{SLURM_JOB_ID:-none}}" > '{held}'
    while [ -f '{gate}' ]; do sleep 0.2; done
  fi
fi
exec '{hbmu}' "$@"
"#,
            log = w.log.display(),
            gate = w.gate.display(),
            held = w.held.display(),
            hbmu = env!("CARGO_BIN_EXE_hbmu"),
        );
        std::fs::write(&w.path, script).unwrap();
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&w.path, std::fs::Permissions::from_mode(0o755)).unwrap();
        w
    }

    /// Invocations logged since the last call, as (campaign, stage) pairs: the campaign is the
    /// path component under `work`, the stage the first one or two arguments.
    fn take(&self, work: &Path) -> BTreeSet<(String, String)> {
        let text = std::fs::read_to_string(&self.log).unwrap_or_default();
        std::fs::write(&self.log, "").unwrap();
        let prefix = format!("{}/", work.display());
        text.lines()
            .map(|l| {
                let words: Vec<&str> = l.split_whitespace().collect();
                let stage = if words.first() == Some(&"fe") {
                    format!("fe {}", words.get(1).unwrap_or(&""))
                } else {
                    words.first().unwrap_or(&"").to_string()
                };
                let campaign = words
                    .iter()
                    .find_map(|w| w.strip_prefix(&prefix))
                    .and_then(|rest| rest.split('/').next())
                    .unwrap_or("?")
                    .to_string();
                (campaign, stage)
            })
            .collect()
    }
}

fn pairs(v: &[(&str, &str)]) -> BTreeSet<(String, String)> {
    v.iter()
        .map(|(a, b)| (a.to_string(), b.to_string()))
        .collect()
}

/// A Slurm cluster to run on: the one `SLURM_CONF` points at when it answers (CI starts one),
/// else a single-node cluster started here with `pipelines/slurm/local-cluster.sh` (stopped on
/// drop). `Err(reason)` when neither is possible.
struct Cluster {
    conf: PathBuf,
    own: Option<PathBuf>,
}

impl Drop for Cluster {
    fn drop(&mut self) {
        if let Some(dir) = &self.own {
            let _ = Command::new(repo().join("pipelines/slurm/local-cluster.sh"))
                .arg("stop")
                .arg(dir)
                .output();
        }
    }
}

fn sinfo_answers(conf: &Path) -> bool {
    Command::new("sinfo")
        .args(["-h", "-o", "%t"])
        .env("SLURM_CONF", conf)
        .output()
        .map(|o| {
            o.status.success()
                && String::from_utf8_lossy(&o.stdout)
                    .lines()
                    .any(|l| ["idle", "mix", "alloc"].contains(&l.trim()))
        })
        .unwrap_or(false)
}

fn cluster(dir: &Path) -> Result<Cluster, String> {
    if let Some(conf) = std::env::var_os("SLURM_CONF").map(PathBuf::from) {
        if sinfo_answers(&conf) {
            return Ok(Cluster { conf, own: None });
        }
    }
    let o = Command::new(repo().join("pipelines/slurm/local-cluster.sh"))
        .arg("start")
        .arg(dir)
        .output()
        .map_err(|e| format!("cannot run pipelines/slurm/local-cluster.sh: {e}"))?;
    let c = Cluster {
        conf: dir.join("slurm.conf"),
        own: Some(dir.to_path_buf()),
    };
    if !o.status.success() || !sinfo_answers(&c.conf) {
        return Err(format!(
            "the local Slurm cluster did not start: {}",
            String::from_utf8_lossy(&o.stderr).trim()
        ));
    }
    Ok(c)
}

/// The job is known to Slurm and running.
fn squeue_running(conf: &Path, job: &str) -> bool {
    Command::new("squeue")
        .args(["-h", "-t", "RUNNING", "-j", job, "-o", "%i"])
        .env("SLURM_CONF", conf)
        .output()
        .map(|o| String::from_utf8_lossy(&o.stdout).trim() == job)
        .unwrap_or(false)
}

fn simulate(campaign: &Path, truth: &Path, seed: u64) {
    let o = crate::common::hbmu(&[
        "lab",
        "simulate",
        small_scenario().to_str().unwrap(),
        "--board",
        thin_board().to_str().unwrap(),
        "--out",
        campaign.to_str().unwrap(),
        "--truth",
        truth.to_str().unwrap(),
        "--seed",
        &seed.to_string(),
        "--force",
    ]);
    assert_ok(&o, "lab simulate");
}

#[test]
fn slurm_nightly_matches_local_recovers_a_cancel_and_redoes_only_what_changed() {
    let t = tempfile::tempdir().unwrap();
    let cl = match cluster(&t.path().join("slurm")) {
        Ok(c) => c,
        Err(reason) => {
            if std::env::var("HBMU_REQUIRE_SLURM").as_deref() == Ok("1") {
                panic!("Slurm is required (HBMU_REQUIRE_SLURM=1) but: {reason}");
            }
            eprintln!("SKIP slurm nightly: {reason} (set HBMU_REQUIRE_SLURM=1 to fail instead)");
            return;
        }
    };
    // Three campaigns; the third is a symbolic link to a directory elsewhere.
    let campaigns = t.path().join("campaigns");
    let truths = t.path().join("truths");
    simulate(&campaigns.join("c1"), &truths.join("c1.json"), 1);
    simulate(&campaigns.join("c2"), &truths.join("c2.json"), 2);
    let real_c3 = t.path().join("lab-share/2026-11-22");
    simulate(&real_c3, &truths.join("c3.json"), 3);
    std::os::unix::fs::symlink(&real_c3, campaigns.join("c3")).unwrap();

    let w = Wrapper::new(t.path());
    let local = t.path().join("local");
    let slurm = t.path().join("slurm-work");
    let args = |work: &Path, scheduler: &str| -> Vec<String> {
        vec![
            "-j4".into(),
            "nightly".into(),
            format!("CAMPAIGNS={}", campaigns.display()),
            format!("NIGHTLY_WORK={}", work.display()),
            format!("HBMU={}", w.path.display()),
            format!("SCHEDULER={scheduler}"),
            // The scheduling is what this test is about: the measurement-side stages of each
            // campaign (the whole chain, `all`, is the other test's and the demo's).
            "NIGHTLY_GOAL=prepare".into(),
            format!("BOARD={}", thin_board().display()),
        ]
    };
    let conf = cl.conf.clone();
    let env = [("SLURM_CONF", conf.as_path())];
    let all_stages = |c: &str| -> Vec<(String, String)> {
        // (`prepare` builds the sensitivity table; the ROMs are each update step's own.)
        ["ingest", "extract", "pair", "fe sensitivity"]
            .iter()
            .map(|s| (c.to_string(), s.to_string()))
            .collect()
    };

    // The reference: the local nightly.
    assert_ok(&make(&args(&local, "local"), &env), "local nightly");
    let ran = w.take(&local);
    for c in ["c1", "c2", "c3"] {
        for s in all_stages(c) {
            assert!(ran.contains(&s), "local nightly did not run {s:?}: {ran:?}");
        }
    }

    // The Slurm nightly, with c2's extract held at its start and cancelled while it runs.
    std::fs::write(&w.gate, format!("extract {}/c2/ingest\n", slurm.display())).unwrap();
    let child = Command::new("make")
        .arg("-C")
        .arg(repo().join("pipelines"))
        .args(["--no-print-directory", "CARGO=true"])
        .args(args(&slurm, "slurm"))
        .env("SLURM_CONF", &conf)
        .env("CI", "1")
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    let job = loop {
        let held = std::fs::read_to_string(&w.held).unwrap_or_default();
        let id = held.trim();
        if !id.is_empty() && squeue_running(&conf, id) {
            break id.to_string();
        }
        assert!(
            t0.elapsed() < Duration::from_secs(600),
            "c2's extract never ran as a Slurm job"
        );
        std::thread::sleep(Duration::from_millis(200));
    };
    let o = Command::new("scancel")
        .arg(&job)
        .env("SLURM_CONF", &conf)
        .output()
        .unwrap();
    assert_ok(&o, "scancel");
    let out = child.wait_with_output().unwrap();
    std::fs::remove_file(&w.gate).unwrap();
    assert!(
        !out.status.success(),
        "the nightly with a cancelled stage must fail; stdout:\n{}",
        String::from_utf8_lossy(&out.stdout)
    );
    assert!(
        String::from_utf8_lossy(&out.stdout).contains("nightly: c2 failed"),
        "the failed campaign is named: {}",
        String::from_utf8_lossy(&out.stdout)
    );
    assert!(
        !slurm.join("c2/extract/extract.manifest.json").exists(),
        "the cancelled extract left a manifest"
    );
    let ran = w.take(&slurm);
    assert!(ran.contains(&("c2".into(), "extract".into())));
    assert!(
        !ran.contains(&("c2".into(), "pair".into())),
        "pair ran after a cancelled extract"
    );

    // The next nightly redoes exactly the cancelled stage and what depends on it.
    assert_ok(
        &make(&args(&slurm, "slurm"), &env),
        "slurm nightly after the cancel",
    );
    assert_eq!(w.take(&slurm), pairs(&[("c2", "extract"), ("c2", "pair")]));

    // Same bytes as the local run.
    assert_same_tree(&local, &slurm, &|p| {
        p.components().any(|c| c.as_os_str() == "logs")
    });

    // A second nightly is a no-op.
    assert_ok(&make(&args(&slurm, "slurm"), &env), "second slurm nightly");
    assert_eq!(
        w.take(&slurm),
        BTreeSet::new(),
        "a second nightly ran stages"
    );

    // The fan-out as a job array.
    let fo = t.path().join("fanout");
    std::fs::create_dir_all(&fo).unwrap();
    check_fanout("slurm", &fo, &env);

    // Only a changed campaign is reprocessed (c3, through its link).
    simulate(&real_c3, &truths.join("c3.json"), 33);
    assert_ok(
        &make(&args(&slurm, "slurm"), &env),
        "slurm nightly after a change",
    );
    let ran = w.take(&slurm);
    assert!(ran.contains(&("c3".into(), "ingest".into())), "{ran:?}");
    assert!(
        ran.iter().all(|(c, s)| c == "c3" && !s.starts_with("fe")),
        "only c3's campaign stages should rerun: {ran:?}"
    );
}

/// A stage killed (SIGKILL, as a cancelled or timed-out job is in the end) while it writes
/// leaves no manifest and no output under its final name that was not complete; the rerun
/// redoes the stage and gives the same bytes as an uninterrupted run.
#[test]
fn a_stage_killed_while_writing_is_redone_with_the_same_bytes() {
    let t = tempfile::tempdir().unwrap();
    let campaign = t.path().join("campaign");
    // Large enough that the kill lands while the outputs are written: 35 measurements.
    let scenario = t.path().join("bigger.toml");
    std::fs::write(
        &scenario,
        "name = \"bigger\"\nseed = 11\n[campaign]\nn_boards = 7\nfree_per_board = 5\nbolted = []\n",
    )
    .unwrap();
    let o = crate::common::hbmu(&[
        "lab",
        "simulate",
        scenario.to_str().unwrap(),
        "--out",
        campaign.to_str().unwrap(),
        "--truth",
        t.path().join("truth.json").to_str().unwrap(),
    ]);
    assert_ok(&o, "lab simulate");
    let reference = t.path().join("reference");
    let o = crate::common::hbmu(&[
        "ingest",
        campaign.to_str().unwrap(),
        "--out",
        reference.to_str().unwrap(),
    ]);
    assert_ok(&o, "uninterrupted ingest");

    let out = t.path().join("killed");
    let mut child = Command::new(env!("CARGO_BIN_EXE_hbmu"))
        .args([
            "ingest",
            campaign.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ])
        .env("CI", "1")
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    // Kill as soon as a temp file shows that an output is being written.
    let t0 = Instant::now();
    let writing = loop {
        let temp = std::fs::read_dir(&out).ok().and_then(|rd| {
            rd.flatten()
                .find(|e| e.file_name().to_string_lossy().contains(".tmp-"))
        });
        if temp.is_some() {
            child.kill().unwrap();
            break true;
        }
        if child.try_wait().unwrap().is_some() || t0.elapsed() > Duration::from_secs(120) {
            break false;
        }
        std::thread::sleep(Duration::from_millis(2));
    };
    let _ = child.wait();
    assert!(
        writing,
        "ingest finished before a temp file was seen: the campaign is too small for this machine"
    );
    assert!(
        !out.join("ingest.manifest.json").exists(),
        "a killed stage must not leave a manifest"
    );
    // Whatever lies under a final name is complete: identical to the reference.
    for name in hbmu::stage::ingest::OUTPUTS {
        let p = out.join(name);
        if p.exists() {
            assert!(
                std::fs::read(&p).unwrap() == std::fs::read(reference.join(name)).unwrap(),
                "{name} is under its final name but not complete"
            );
        }
    }
    // The rerun (what the next nightly does) redoes the stage: same bytes as uninterrupted.
    let o = crate::common::hbmu(&[
        "ingest",
        campaign.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_ok(&o, "ingest after the kill");
    assert!(!crate::common::stderr(&o).contains("up to date"));
    for name in hbmu::stage::ingest::OUTPUTS {
        assert!(
            std::fs::read(out.join(name)).unwrap() == std::fs::read(reference.join(name)).unwrap(),
            "{name} differs after the rerun"
        );
    }
}

/// Another specimen through the whole DAG: a 300 × 200 × 3 mm orthotropic plate without copper
/// or holes (`data/boards/plate_300x200x3.toml`), measured free-free only. The DAG builds no
/// bolted model (the board has no holes), step 2 says there is nothing to update, and the
/// report predicts the free-free modes; step 1 gives every board's moduli.
#[test]
fn a_plate_of_another_size_without_holes_runs_free_free_only() {
    let t = tempfile::tempdir().unwrap();
    let scenario = t.path().join("plate.toml");
    std::fs::write(
        &scenario,
        "name = \"plate_free\"\nseed = 7\n[campaign]\nn_boards = 4\nfree_per_board = 2\nbolted = []\n[truth]\nphysics = \"plate\"\n[measurement]\nfree_max_hz = 1500.0\nfree_lines = 1500\n",
    )
    .unwrap();
    let w = t.path().join("work");
    let board = repo().join("data/boards/plate_300x200x3.toml");
    let o = make(
        &[
            "all".into(),
            format!("SCENARIO={}", scenario.display()),
            format!("BOARD={}", board.display()),
            format!("WORK={}", w.display()),
            format!("HBMU={}", env!("CARGO_BIN_EXE_hbmu")),
            "UPDATE_PARTICLES=100".into(),
            "PROPAGATE_DRAWS=400".into(),
        ],
        &[],
    );
    assert_ok(&o, "make all on the 300 x 200 x 3 mm plate");
    // Step 1 samples on its own ROM and the propagation reads it; `make all` builds no model
    // artifact nothing reads, and `make fe` would build no bolted ROM for a board without holes.
    assert!(w.join("update_boards/rom.npz").is_file());
    assert!(
        !w.join("fe/rom_free.npz").exists(),
        "fe's ROM is not in all"
    );
    let prop = std::fs::read_to_string(w.join("propagate/propagate.manifest.json")).unwrap();
    assert!(prop.contains("update_boards/rom.npz"), "{prop}");
    let dry = make(
        &[
            "-n".into(),
            "fe".into(),
            format!("SCENARIO={}", scenario.display()),
            format!("BOARD={}", board.display()),
            format!("WORK={}", w.display()),
            format!("HBMU={}", env!("CARGO_BIN_EXE_hbmu")),
        ],
        &[],
    );
    assert_ok(&dry, "make -n fe on the plate without holes");
    let dry = String::from_utf8_lossy(&dry.stdout);
    assert!(dry.contains("--setup free"), "{dry}");
    assert!(
        !dry.contains("--setup bolted"),
        "a bolted ROM for a board without holes: {dry}"
    );
    let joints = std::fs::read_to_string(w.join("update_joints/update_report.json")).unwrap();
    assert!(joints.contains("update.no_bolted_data"), "{joints}");
    assert!(w.join("report/report.html").is_file());
    use parquet::file::reader::{FileReader, SerializedFileReader};
    let summary = std::fs::File::open(w.join("update_boards/summary.parquet")).unwrap();
    let rows = SerializedFileReader::new(summary)
        .unwrap()
        .metadata()
        .file_metadata()
        .num_rows();
    assert!(
        rows > 4 * 4,
        "step 1's summary has {rows} rows for 4 boards x 4 parameters"
    );
}

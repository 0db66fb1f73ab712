//! The DAG reruns what changed (issue 51): a changed option of a stage (`UPDATE_ARGS`,
//! `PROPAGATE_DRAWS`, `BOARD`, …) makes `pipelines/Makefile` rerun that stage and those after
//! it, and unchanged options rerun nothing.
//!
//! Dry runs (`make -n`) on a work directory of fake, up-to-date outputs: no stage runs, the
//! `hbmu` given to make is a plain file it never runs or rebuilds (`-o`).

use crate::common::repo;
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, SystemTime};

/// Each stage's outputs under WORK, in the DAG's order, with its stamp under `.options/`.
/// (The model's ROMs, `make fe`, are not in `all`: each update step builds its own.)
const STAGES: [(&str, &str, &[&str]); 10] = [
    ("lab", "lab", &["truth.json", "campaign/campaign.csv"]),
    ("ingest", "ingest", &["ingest/ingest.manifest.json"]),
    ("extract", "extract", &["extract/extract.manifest.json"]),
    ("pair", "pair", &["pair/pair.manifest.json"]),
    ("fe sensitivity", "fe", &["fe/sensitivity_free.parquet"]),
    (
        "update boards",
        "update-boards",
        &["update_boards/update_boards.manifest.json"],
    ),
    (
        "update joints",
        "update-joints",
        &["update_joints/update_joints.manifest.json"],
    ),
    (
        "propagate",
        "propagate",
        &["propagate/propagate.manifest.json"],
    ),
    ("report", "report", &["report/report.manifest.json"]),
    ("diagnose", "diagnose", &["diagnose/diagnose.manifest.json"]),
];

struct Dag {
    _t: tempfile::TempDir,
    dir: PathBuf,
    hbmu: PathBuf,
    work: PathBuf,
}

fn set_mtime(p: &Path, t: SystemTime) {
    std::fs::File::options()
        .write(true)
        .open(p)
        .unwrap()
        .set_modified(t)
        .unwrap();
}

impl Dag {
    /// A scenario's work directory whose outputs are all up to date for the baseline options.
    fn new() -> Dag {
        let t = tempfile::tempdir().unwrap();
        let dir = t.path().to_path_buf();
        let d = Dag {
            hbmu: dir.join("bin/hbmu"),
            work: dir.join("work"),
            dir,
            _t: t,
        };
        std::fs::create_dir_all(d.hbmu.parent().unwrap()).unwrap();
        for f in ["scenario.toml", "other.toml", "board1.toml", "board2.toml"] {
            std::fs::write(d.dir.join(f), f).unwrap();
        }
        std::fs::write(&d.hbmu, "not run by a dry run\n").unwrap();
        std::fs::create_dir_all(&d.work).unwrap();
        std::fs::write(d.work.join(".hbmu-revision"), "hbmu test\n").unwrap();
        for (_, _, outputs) in STAGES {
            for o in outputs {
                let p = d.work.join(o);
                std::fs::create_dir_all(p.parent().unwrap()).unwrap();
                std::fs::write(&p, "fake output\n").unwrap();
            }
        }
        d.reset();
        d
    }

    /// `make -n all diagnose` with the baseline options and `changed` on top: the stages make
    /// would run, as the first words of each `hbmu` command ("update boards", "fe rom", …),
    /// with the command lines (whitespace collapsed).
    fn dry_run(&self, changed: &[&str]) -> Vec<(String, String)> {
        let hbmu = self.hbmu.to_str().unwrap();
        let o = Command::new("make")
            .arg("-C")
            .arg(repo().join("pipelines"))
            .args([
                "--no-print-directory",
                "-n",
                "all",
                "diagnose",
                "CARGO=true",
            ])
            .arg(format!("HBMU={hbmu}"))
            .args(["-o", hbmu])
            .arg(format!("WORK={}", self.work.display()))
            .arg(format!(
                "SCENARIO={}",
                self.dir.join("scenario.toml").display()
            ))
            .arg(format!("BOARD={}", self.dir.join("board1.toml").display()))
            .args(changed)
            .env("CI", "1")
            .env("HBMU_CACHE", "")
            .env_remove("MAKEFLAGS")
            .env_remove("MFLAGS")
            .output()
            .expect("run make");
        let out = String::from_utf8_lossy(&o.stdout);
        assert!(
            o.status.success(),
            "make -n {changed:?} failed ({}):\nstdout:\n{out}\nstderr:\n{}",
            o.status,
            String::from_utf8_lossy(&o.stderr)
        );
        out.lines()
            .filter_map(|l| {
                let words: Vec<&str> = l.split_whitespace().collect();
                if words.len() < 2 || words[0] != hbmu || words[1] == "--version" {
                    return None;
                }
                let n = if matches!(words[1], "fe" | "update") {
                    3
                } else {
                    2
                };
                Some((words[1..n].join(" "), words[1..].join(" ")))
            })
            .collect()
    }

    fn stages(&self, changed: &[&str]) -> BTreeSet<String> {
        self.dry_run(changed).into_iter().map(|(s, _)| s).collect()
    }

    /// Back to the baseline: the stamps hold the baseline options (a dry run rewrites them)
    /// and are older than every output, whose times follow the DAG; then nothing reruns.
    fn reset(&self) {
        self.dry_run(&[]);
        let t0 = SystemTime::now() - Duration::from_secs(3600);
        let options = self.work.join(".options");
        if let Ok(rd) = std::fs::read_dir(&options) {
            for e in rd {
                set_mtime(&e.unwrap().path(), t0 + Duration::from_secs(1));
            }
        }
        for f in ["scenario.toml", "other.toml", "board1.toml", "board2.toml"] {
            set_mtime(&self.dir.join(f), t0);
        }
        set_mtime(&self.hbmu, t0);
        set_mtime(&self.work.join(".hbmu-revision"), t0);
        for (i, (_, _, outputs)) in STAGES.iter().enumerate() {
            for o in *outputs {
                set_mtime(&self.work.join(o), t0 + Duration::from_secs(10 + i as u64));
            }
        }
        assert_eq!(
            self.stages(&[]),
            BTreeSet::new(),
            "unchanged options rerun nothing"
        );
    }
}

fn set(v: &[&str]) -> BTreeSet<String> {
    v.iter().map(|s| s.to_string()).collect()
}

#[test]
fn a_changed_stage_option_reruns_that_stage_and_those_after_it() {
    let d = Dag::new();
    let all: Vec<&str> = STAGES.iter().map(|(s, _, _)| *s).collect();
    let updating = [
        "update boards",
        "update joints",
        "propagate",
        "report",
        "diagnose",
    ];
    let campaign: Vec<&str> = all
        .iter()
        .copied()
        .filter(|s| !s.starts_with("fe "))
        .collect();
    let board2 = format!("BOARD={}", d.dir.join("board2.toml").display());
    let other = format!("SCENARIO={}", d.dir.join("other.toml").display());
    let cases: Vec<(&str, &[&str])> = vec![
        ("UPDATE_ARGS=--rom-basis 20", &updating),
        // Step 1's own options: step 2 reads step 1's posterior, so it reruns too.
        ("UPDATE_BOARDS_ARGS=--hold-out PCB-03", &updating),
        ("UPDATE_PARTICLES=300", &updating),
        ("UPDATE_RUNS=3", &updating),
        ("UPDATE_SEED=7", &updating),
        ("HOLD_OUT=PCB-02", &updating),
        ("PROPAGATE_DRAWS=500", &["propagate", "report"]),
        ("PROPAGATE_SEED=7", &["propagate", "report"]),
        ("DIAGNOSE_REFITS=2", &["diagnose"]),
        // The board reaches the model's artifacts and, through the simulated campaign, all.
        (&board2, &all[..]),
        // Another scenario: a new campaign, the same model artifacts.
        (&other, &campaign[..]),
    ];
    for (change, expected) in cases {
        let ran = d.dry_run(&[change]);
        let stages: BTreeSet<String> = ran.iter().map(|(s, _)| s.clone()).collect();
        assert_eq!(stages, set(expected), "after {change}");
        // Each stamp holds exactly the options its stage's command line is given.
        for (stage, line) in &ran {
            let stamp = STAGES.iter().find(|(s, _, _)| s == stage).unwrap().1;
            let text = std::fs::read_to_string(d.work.join(".options").join(stamp)).unwrap();
            let text = text.split_whitespace().collect::<Vec<_>>().join(" ");
            assert!(
                line.contains(&text),
                "{stamp} stamp {text:?} is not in {line:?}"
            );
        }
        d.reset();
    }
}

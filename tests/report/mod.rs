//! The validation report in a real browser: headless Chromium opens `report.html` of a small
//! virtual campaign run through the whole DAG (lab → … → update boards → propagate → report)
//! on the thin-plate board ([`thin_board`]),
//! with no console errors; every figure renders with a non-empty box; the screenshot is kept
//! under `target/test-artifacts/`; the numbers in the page's tables equal the Parquet tables
//! they come from. Without Chromium the test prints SKIP, unless `HBMU_REQUIRE_BROWSER=1`
//! (set by CI), in which case it fails.

use crate::common::repo;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn chromium() -> Option<String> {
    for c in ["chromium", "chromium-browser", "google-chrome"] {
        if Command::new(c)
            .arg("--version")
            .output()
            .is_ok_and(|o| o.status.success())
        {
            return Some(c.to_string());
        }
    }
    None
}

fn browser(bin: &str, args: &[&str]) -> Output {
    Command::new(bin)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--no-first-run",
            "--disable-extensions",
            "--enable-logging=stderr",
            "--v=0",
        ])
        .args(args)
        .output()
        .expect("run chromium")
}

/// A checker injected at the start of a copy of the page: records errors (script and resource
/// load, console.error), then, once loaded, measures every figure and image and serialises the
/// tables' cells into `<pre id="hbmu-check">` for `--dump-dom`.
const CHECKER: &str = r#"<script>
window.__errs = [];
window.addEventListener('error', function (e) {
  window.__errs.push(String(e.message || (e.target && (e.target.src || e.target.href)) || 'error'));
}, true);
(function () { var ce = console.error; console.error = function () { window.__errs.push(Array.prototype.join.call(arguments, ' ')); ce.apply(console, arguments); }; })();
window.addEventListener('load', function () {
  var figs = document.querySelectorAll('figure.plot');
  var empty = [];
  figs.forEach(function (f, i) {
    var s = f.querySelector('svg');
    var r = s ? s.getBoundingClientRect() : null;
    var b = s ? s.getBBox() : null;
    var drawn = s ? s.querySelectorAll('line,polyline,rect,circle,path,polygon,text').length : 0;
    if (!s || r.width < 50 || r.height < 50 || b.width <= 0 || b.height <= 0 || drawn < 5) empty.push(i + 1);
  });
  var imgs = document.querySelectorAll('img');
  imgs.forEach(function (im, i) { if (!im.complete || im.naturalWidth === 0) empty.push('img' + i); });
  var tables = {};
  document.querySelectorAll('table[data-table]').forEach(function (t) {
    var name = t.getAttribute('data-table');
    var rows = [];
    t.querySelectorAll('tr').forEach(function (tr) {
      var cells = tr.querySelectorAll('td[data-col]');
      if (!cells.length) return;
      var row = {};
      cells.forEach(function (c) { row[c.getAttribute('data-col')] = [c.getAttribute('data-value'), c.textContent]; });
      rows.push(row);
    });
    (tables[name] = tables[name] || []).push(rows);
  });
  var pre = document.createElement('pre');
  pre.id = 'hbmu-check';
  pre.textContent = JSON.stringify({ errors: window.__errs, figures: figs.length, empty: empty, tables: tables });
  document.body.appendChild(pre);
});
</script>"#;

/// The board of the small campaign: the built-in board as a thin plate. What these tests
/// check (the page, its tables against the Parquet, bytes, held-out boards, the verdict's
/// rules) does not depend on the plate theory, and its models build in a fifth of the
/// shear-deformable board's time; the built-in board's report is CI's demo.
fn thin_board() -> PathBuf {
    repo().join("data/boards/paper_thin.toml")
}

/// The small campaign run once through the DAG for every test here: (guard, work dir).
fn small_work() -> &'static Path {
    static WORK: std::sync::OnceLock<(tempfile::TempDir, PathBuf)> = std::sync::OnceLock::new();
    let (_, w) = WORK.get_or_init(|| {
        let t = tempfile::tempdir().unwrap();
        let w = t.path().join("small");
        run_small_pipeline(&w);
        (t, w)
    });
    w
}

#[test]
fn propagate_and_report_give_the_same_bytes_whatever_the_threads_and_the_directory() {
    let work = small_work();
    let t = tempfile::tempdir().unwrap();
    // Propagation at 1 thread into another directory: the pipeline's predictions (2 threads
    // or as many as the machine has), byte for byte.
    let other = t.path().join("p1");
    let boards = work.join("update_boards");
    let joints = work.join("update_joints");
    let mut args = vec![
        "--threads",
        "1",
        "propagate",
        boards.to_str().unwrap(),
        "--draws",
        "400",
        "--out",
        other.to_str().unwrap(),
    ];
    // The pipeline's propagation includes the step-2 posterior when it ran.
    if joints.join("joints.parquet").is_file() {
        args.insert(4, joints.to_str().unwrap());
    }
    let o = crate::common::hbmu(&args);
    assert!(o.status.success(), "{}", crate::common::stderr(&o));
    for f in ["predictions.parquet", "propagate_report.json"] {
        assert_eq!(
            std::fs::read(other.join(f)).unwrap(),
            std::fs::read(work.join("propagate").join(f)).unwrap(),
            "{f} differs between thread counts"
        );
    }
    // The work directory copied elsewhere (same name): the same report.
    let copy = t.path().join("elsewhere").join("small");
    crate::common::copy_dir(work, &copy);
    std::fs::remove_dir_all(copy.join("report")).unwrap();
    let o = crate::common::hbmu(&[
        "report",
        copy.to_str().unwrap(),
        "--out",
        copy.join("report").to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", crate::common::stderr(&o));
    for f in [
        "report.html",
        "summary.md",
        "table2.parquet",
        "table2.csv",
        "intervals.parquet",
        "intervals.csv",
    ] {
        assert_eq!(
            std::fs::read(copy.join("report").join(f)).unwrap(),
            std::fs::read(work.join("report").join(f)).unwrap(),
            "{f} differs between work directories"
        );
    }
}

/// A board held out of step 1 (`update boards --hold-out`) is not updated, and the report
/// compares its measurements with the new-board prediction, apart from the in-sample boards.
/// A measurement held out (`--hold-out-measurements`) is compared with its own board's
/// prediction only, apart from that board's in-sample measurements.
#[test]
fn a_held_out_board_is_compared_with_the_new_board_prediction_only() {
    use arrow::array::{Array, BooleanArray, StringArray};
    let work = small_work();
    let t = tempfile::tempdir().unwrap();
    let w = t.path().join("held");
    for d in ["ingest", "extract", "pair"] {
        crate::common::copy_dir(&work.join(d), &w.join(d));
    }
    // The held-out board: the second board of the campaign (sorted ids).
    let mut boards = vec![];
    // (board, label) of every accepted, labelled free-free pair, and its measurement.
    let mut pairs_free: Vec<(String, String)> = vec![];
    let mut meas_free: Vec<String> = vec![];
    for b in hbmu::io::tables::read_parquet(&w.join("pair/pairs.parquet")).unwrap() {
        let col = |n: &str| b.column(b.schema().index_of(n).unwrap()).clone();
        let bid = col("board_id");
        let bid = bid.as_any().downcast_ref::<StringArray>().unwrap();
        let st = col("setup");
        let st = st.as_any().downcast_ref::<StringArray>().unwrap();
        let acc = col("accepted");
        let acc = acc.as_any().downcast_ref::<BooleanArray>().unwrap();
        let lab = col("label");
        let lab = lab.as_any().downcast_ref::<StringArray>().unwrap();
        let mid = col("measurement_id");
        let mid = mid.as_any().downcast_ref::<StringArray>().unwrap();
        for i in 0..b.num_rows() {
            boards.push(bid.value(i).to_string());
            if st.value(i) == "free" && acc.value(i) && !lab.is_null(i) {
                pairs_free.push((bid.value(i).to_string(), lab.value(i).to_string()));
                meas_free.push(mid.value(i).to_string());
            }
        }
    }
    boards.sort();
    boards.dedup();
    assert_eq!(boards.len(), 2, "{boards:?}");
    let held = boards[1].clone();
    let step1 = w.join("update_boards");
    let (ingest, pair) = (w.join("ingest"), w.join("pair"));
    let board = thin_board();
    let run = |extra: &[&str]| {
        let mut a = vec![
            "update",
            "boards",
            ingest.to_str().unwrap(),
            pair.to_str().unwrap(),
            "--particles",
            "100",
            "--runs",
            "2",
            "--out",
            step1.to_str().unwrap(),
            "--board",
            board.to_str().unwrap(),
        ];
        a.extend_from_slice(extra);
        crate::common::hbmu(&a)
    };
    // A board that is not in the campaign: a clear error naming it and the boards there are.
    let o = run(&["--hold-out", "NO-SUCH-BOARD"]);
    assert!(!o.status.success());
    let e = crate::common::stderr(&o);
    assert!(
        e.contains("NO-SUCH-BOARD") && e.contains(&held),
        "expected the board and the campaign's boards named: {e}"
    );
    let o = run(&["--hold-out", &held]);
    assert!(o.status.success(), "{}", crate::common::stderr(&o));
    let rep: serde_json::Value =
        serde_json::from_slice(&std::fs::read(step1.join("update_report.json")).unwrap()).unwrap();
    assert_eq!(rep["held_out_boards"], serde_json::json!([held]));
    let updated: Vec<String> = hbmu::io::tables::read_parquet(&step1.join("boards.parquet"))
        .unwrap()
        .iter()
        .flat_map(|b| {
            let c = b.column(b.schema().index_of("board_id").unwrap()).clone();
            let c = c.as_any().downcast_ref::<StringArray>().unwrap().clone();
            (0..c.len()).map(move |i| c.value(i).to_string())
        })
        .collect();
    assert!(!updated.is_empty() && updated.iter().all(|b| *b != held));
    let o = crate::common::hbmu(&[
        "propagate",
        step1.to_str().unwrap(),
        "--draws",
        "400",
        "--out",
        w.join("propagate").to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", crate::common::stderr(&o));
    let o = crate::common::hbmu(&[
        "report",
        w.to_str().unwrap(),
        "--out",
        w.join("report").to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", crate::common::stderr(&o));
    let e = crate::common::stderr(&o);
    assert!(e.contains("held-out boards by the new board"), "{e}");
    // Every accepted, labelled free-free pair of the held-out board is compared once, with
    // the new board's intervals only (the table counts it apart from the in-sample boards).
    let t2 = hbmu::io::tables::read_parquet(&w.join("report/table2.parquet")).unwrap();
    let (mut n_held, mut n_in, mut labels) = (0, 0, vec![]);
    for b in &t2 {
        let (st, lab) = (text_column(b, "setup"), text_column(b, "label"));
        let (nh, nm) = (int_column(b, "n_held_out"), int_column(b, "n_measured"));
        for i in 0..b.num_rows() {
            if st[i] == "free" {
                n_held += nh[i] as usize;
                n_in += nm[i] as usize;
                labels.push(lab[i].clone());
            }
        }
    }
    let count = |board: &str| {
        pairs_free
            .iter()
            .filter(|(b, l)| b == board && labels.contains(l))
            .count()
    };
    assert!(n_held > 0);
    assert_eq!(n_held, count(&held), "held-out measurements compared");
    assert_eq!(n_in, count(&boards[0]), "in-sample measurements compared");
    let html = std::fs::read_to_string(w.join("report/report.html")).unwrap();
    assert!(html.contains("all modes, new board, held-out boards"));

    // One free-free measurement of the first board held out, the board updated from the
    // others. The small campaign measures each board once free-free, so the board keeps only
    // its mass: the mass scale alone is updated (the moduli at the board file's), which tests
    // where the held-out measurement goes, not how well it is predicted (that is
    // benches/own_board_holdout.sh). A measurement that is not in the campaign: an error
    // naming it.
    let o = run(&["--hold-out-measurements", "NO-SUCH-MEASUREMENT"]);
    assert!(!o.status.success());
    let e = crate::common::stderr(&o);
    assert!(e.contains("NO-SUCH-MEASUREMENT"), "{e}");
    let (k, _) = pairs_free
        .iter()
        .enumerate()
        .find(|(_, (b, _))| *b == boards[0])
        .expect("a free-free pair of the first board");
    let m = meas_free[k].clone();
    let n_m = meas_free
        .iter()
        .zip(&pairs_free)
        .filter(|(x, (_, l))| **x == m && labels.contains(l))
        .count();
    let o = run(&["--hold-out-measurements", &m, "--params", "mass_scale"]);
    assert!(o.status.success(), "{}", crate::common::stderr(&o));
    let rep: serde_json::Value =
        serde_json::from_slice(&std::fs::read(step1.join("update_report.json")).unwrap()).unwrap();
    assert_eq!(rep["held_out_measurements"], serde_json::json!([m]));
    let residual_measurements: Vec<String> =
        hbmu::io::tables::read_parquet(&step1.join("residuals.parquet"))
            .unwrap()
            .iter()
            .flat_map(|b| text_column(b, "measurement_id"))
            .collect();
    assert!(!residual_measurements.contains(&m), "{m} was used");
    for (stage, args) in [
        ("propagate", vec![step1.to_str().unwrap(), "--draws", "400"]),
        ("report", vec![w.to_str().unwrap()]),
    ] {
        let out = w.join(stage);
        let mut a = vec![stage];
        a.extend(args);
        a.extend(["--out", out.to_str().unwrap(), "--force"]);
        let o = crate::common::hbmu(&a);
        assert!(o.status.success(), "{stage}: {}", crate::common::stderr(&o));
    }
    let iv = hbmu::io::tables::read_parquet(&w.join("report/intervals.parquet")).unwrap();
    let (mut own_held, mut new_held) = (0, 0);
    for b in &iv {
        let (scope, st) = (text_column(b, "scope"), text_column(b, "setup"));
        let nh = int_column(b, "n_held_out");
        for i in 0..b.num_rows() {
            if st[i] == "free" {
                match scope[i].as_str() {
                    "board" => own_held += nh[i] as usize,
                    _ => new_held += nh[i] as usize,
                }
            }
        }
    }
    assert!(n_m > 0);
    assert_eq!(
        own_held, n_m,
        "the held-out measurement's modes, by its own board"
    );
    assert_eq!(
        new_held, 0,
        "a held-out measurement of an updated board is no new-board test"
    );
    let html = std::fs::read_to_string(w.join("report/report.html")).unwrap();
    assert!(html.contains("own board, held-out measurements"));
}

/// A string column of a record batch.
fn text_column(b: &arrow::record_batch::RecordBatch, name: &str) -> Vec<String> {
    use arrow::array::{Array, StringArray};
    let c = b.column(b.schema().index_of(name).unwrap()).clone();
    let c = c.as_any().downcast_ref::<StringArray>().unwrap();
    (0..c.len()).map(|i| c.value(i).to_string()).collect()
}

/// An Int32 column of a record batch.
fn int_column(b: &arrow::record_batch::RecordBatch, name: &str) -> Vec<i32> {
    use arrow::array::{Array, Int32Array};
    let c = b.column(b.schema().index_of(name).unwrap()).clone();
    let c = c.as_any().downcast_ref::<Int32Array>().unwrap();
    (0..c.len()).map(|i| c.value(i)).collect()
}

fn run_small_pipeline(work: &Path) {
    let o = Command::new("make")
        .arg("-C")
        .arg(repo().join("pipelines"))
        .args([
            "--no-print-directory",
            "prepare",
            "update-boards",
            "propagate",
            "report",
        ])
        .arg(format!(
            "SCENARIO={}",
            repo().join("tests/nightly/small.toml").display()
        ))
        .arg(format!("WORK={}", work.display()))
        .arg(format!("BOARD={}", thin_board().display()))
        .arg(format!("HBMU={}", env!("CARGO_BIN_EXE_hbmu")))
        .args([
            "CARGO=true",
            "UPDATE_PARTICLES=100",
            "UPDATE_RUNS=2",
            "PROPAGATE_DRAWS=400",
        ])
        .env("CI", "1")
        .env("HBMU_CACHE", "")
        .output()
        .expect("run make");
    assert!(
        o.status.success(),
        "pipeline failed:\n{}\n{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
}

/// Parquet column `col` of a table as strings the way the page writes `data-value`.
fn parquet_values(path: &Path, col: &str) -> Vec<String> {
    use arrow::array::{Array, Float64Array, Int32Array, StringArray};
    let mut out = vec![];
    for b in hbmu::io::tables::read_parquet(path).unwrap() {
        let a = b
            .column_by_name(col)
            .unwrap_or_else(|| panic!("{col} in {}", path.display()));
        for i in 0..b.num_rows() {
            out.push(if a.is_null(i) {
                String::new()
            } else if let Some(x) = a.as_any().downcast_ref::<Float64Array>() {
                x.value(i).to_string()
            } else if let Some(x) = a.as_any().downcast_ref::<Int32Array>() {
                x.value(i).to_string()
            } else if let Some(x) = a.as_any().downcast_ref::<StringArray>() {
                x.value(i).to_string()
            } else {
                panic!("unexpected type of {col}")
            });
        }
    }
    out
}

fn compare_table(check: &serde_json::Value, name: &str, parquet: &Path, columns: &[(&str, &str)]) {
    let rows = check["tables"][name][0]
        .as_array()
        .unwrap_or_else(|| panic!("table {name} in the page"));
    assert!(!rows.is_empty(), "table {name} is empty");
    for (html_col, pq_col) in columns {
        let want = parquet_values(parquet, pq_col);
        assert_eq!(
            rows.len(),
            want.len(),
            "{name}: rows in the page vs {}",
            parquet.display()
        );
        for (k, (r, w)) in rows.iter().zip(&want).enumerate() {
            let cell = &r[*html_col];
            let v = cell[0].as_str().unwrap_or_default();
            assert_eq!(
                v, w,
                "{name} row {k} column {html_col}: page {v:?} vs parquet {w:?}"
            );
            // The text shown is the value rounded: within half a unit of its last digit
            // (fixed or scientific notation), plus the rounding of the comparison itself.
            let text = cell[1].as_str().unwrap_or_default();
            if let (Ok(x), Ok(t)) = (v.parse::<f64>(), text.parse::<f64>()) {
                let (mantissa, exp) = match text.split_once('e') {
                    Some((m, e)) => (m, e.parse::<i32>().unwrap()),
                    None => (text, 0),
                };
                let digits = mantissa.split('.').nth(1).map_or(0, |d| d.len()) as i32;
                let tol = 0.5 * 10f64.powi(exp - digits) + 8.0 * f64::EPSILON * x.abs();
                assert!(
                    (x - t).abs() <= tol,
                    "{name} row {k} column {html_col}: shows {text} for {x}"
                );
            }
        }
    }
}

#[test]
fn report_opens_in_chromium_without_errors_and_its_tables_equal_the_parquet() {
    let Some(bin) = chromium() else {
        if std::env::var("HBMU_REQUIRE_BROWSER").as_deref() == Ok("1") {
            panic!("Chromium is required (HBMU_REQUIRE_BROWSER=1) but none of chromium, chromium-browser, google-chrome runs");
        }
        eprintln!("SKIP report in browser: Chromium not found (Debian: apt-get install chromium; set HBMU_REQUIRE_BROWSER=1 to fail instead)");
        return;
    };
    let work = small_work();
    let dir = work.join("report");
    let html = std::fs::read_to_string(dir.join("report.html")).unwrap();
    // No external resource: the only URLs allowed are the SVG/XLink namespace names.
    let stripped = html
        .replace("http://www.w3.org/2000/svg", "")
        .replace("http://www.w3.org/1999/xlink", "");
    assert!(
        !stripped.contains("http://")
            && !stripped.contains("https://")
            && !stripped.contains("<script")
            && !stripped.contains("<img"),
        "the page must not reach the network or run a script"
    );
    // The DAG up to report only: the diagnosis section says in one line that diagnose has not
    // run (src/report/diagnosis.rs tests the section's tables against their sources).
    assert!(
        html.contains("<h2 id=\"diagnosis\">") && html.contains("The diagnose stage has not run"),
        "no diagnosis section"
    );
    // The unmodified page: a screenshot, and no console message at all (it has no script, so
    // any console line is the browser complaining about the page).
    let artifacts = repo().join("target/test-artifacts");
    std::fs::create_dir_all(&artifacts).unwrap();
    let shot = artifacts.join("report-screenshot.png");
    let _ = std::fs::remove_file(&shot);
    let url = format!("file://{}", dir.join("report.html").display());
    let o = browser(
        &bin,
        &[
            &format!("--screenshot={}", shot.display()),
            "--window-size=1200,2400",
            "--hide-scrollbars",
            &url,
        ],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    let console: Vec<&str> = err.lines().filter(|l| l.contains("CONSOLE")).collect();
    assert!(console.is_empty(), "console messages: {console:?}");
    let png =
        std::fs::read(&shot).unwrap_or_else(|_| panic!("no screenshot; chromium said:\n{err}"));
    assert!(
        png.starts_with(b"\x89PNG") && png.len() > 10_000,
        "screenshot of {} bytes",
        png.len()
    );
    // The checked copy.
    let checked = dir.join("check.html");
    let injected = html.replacen("<head>", &format!("<head>\n{CHECKER}"), 1);
    std::fs::write(&checked, injected).unwrap();
    let o = browser(
        &bin,
        &[
            "--dump-dom",
            "--virtual-time-budget=10000",
            &format!("file://{}", checked.display()),
        ],
    );
    let dom = String::from_utf8_lossy(&o.stdout);
    let start = dom.find("<pre id=\"hbmu-check\">").unwrap_or_else(|| {
        panic!(
            "no check output; stderr:\n{}",
            String::from_utf8_lossy(&o.stderr)
        )
    });
    let rest = &dom[start + "<pre id=\"hbmu-check\">".len()..];
    let json = &rest[..rest.find("</pre>").unwrap()];
    let json = json
        .replace("&lt;", "<")
        .replace("&gt;", ">")
        .replace("&quot;", "\"")
        .replace("&amp;", "&");
    let check: serde_json::Value = serde_json::from_str(&json).unwrap();
    assert_eq!(check["errors"], serde_json::json!([]), "errors in the page");
    assert_eq!(
        check["empty"],
        serde_json::json!([]),
        "figures or images that did not render"
    );
    let n_fig = check["figures"].as_u64().unwrap();
    assert_eq!(
        n_fig as usize,
        html.matches("<figure class=\"plot\"").count()
    );
    assert!(n_fig >= 6, "only {n_fig} figures");
    let t2 = [
        ("setup", "setup"),
        ("label", "label"),
        ("n_measured", "n_measured"),
        ("measured_mean_hz", "measured_mean_hz"),
        ("measured_sd_hz", "measured_sd_hz"),
        ("simulated_mean_hz", "simulated_mean_hz"),
        ("simulated_sd_hz", "simulated_sd_hz"),
        ("predictive_sd_hz", "predictive_sd_hz"),
        ("mean_error_pct", "mean_error_pct"),
        ("sd_error_pct", "sd_error_pct"),
        ("board_coverage_90", "board_coverage_90"),
        ("new_board_coverage_90", "new_board_coverage_90"),
    ];
    compare_table(&check, "table2", &dir.join("table2.parquet"), &t2);
    let iv = [
        ("scope", "scope"),
        ("setup", "setup"),
        ("label", "label"),
        ("n_draws", "n_draws"),
        ("model_mean_hz", "model_mean_hz"),
        ("model_sd_hz", "model_sd_hz"),
        ("q05_hz", "q05_hz"),
        ("q25_hz", "q25_hz"),
        ("q50_hz", "q50_hz"),
        ("q75_hz", "q75_hz"),
        ("q95_hz", "q95_hz"),
        ("n_measured", "n_measured"),
        ("n_inside_90", "n_inside_90"),
    ];
    compare_table(&check, "intervals", &dir.join("intervals.parquet"), &iv);
    // The posterior summary shown equals summary.parquet.
    let summary: Vec<(&str, &str)> = [
        "parameter",
        "mean",
        "sd",
        "q05",
        "q50",
        "q95",
        "physical_q05",
        "physical_q95",
        "r_hat",
        "ess_bulk",
        "ess_tail",
    ]
    .iter()
    .map(|c| (*c, *c))
    .collect();
    compare_table(
        &check,
        "summary",
        &work.join("update_boards/summary.parquet"),
        &summary,
    );
    // The CSV twin has the same numbers.
    let csv = std::fs::read_to_string(dir.join("table2.csv")).unwrap();
    let means = parquet_values(&dir.join("table2.parquet"), "measured_mean_hz");
    for m in means.iter().filter(|m| !m.is_empty()) {
        assert!(csv.contains(m.as_str()), "table2.csv lacks {m}");
    }
    eprintln!(
        "report in chromium: {n_fig} figures, screenshot {}",
        shot.display()
    );
    let _: PathBuf = shot;
}

/// `hbmu diagnose` on the small campaign: the document names a verdict consistent with the
/// located evidence, nothing is favoured without a refit, its table has one row
/// per screened candidate, and the same work directory elsewhere gives the same bytes.
#[test]
fn diagnose_writes_a_verdict_and_the_same_bytes_in_another_directory() {
    let work = small_work();
    let t = tempfile::tempdir().unwrap();
    let board = thin_board();
    let run = |w: &Path, out: &Path| {
        let o = crate::common::hbmu(&[
            "diagnose",
            w.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--board",
            board.to_str().unwrap(),
            "--max-refits",
            "0",
        ]);
        assert!(o.status.success(), "{}", crate::common::stderr(&o));
    };
    let out = t.path().join("d1");
    run(work, &out);
    let doc: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("diagnosis.json")).unwrap()).unwrap();
    let verdict = doc["verdict"].as_str().unwrap();
    assert!(
        [
            "no_missing_physics",
            "mechanism_found",
            "unexplained_misfit",
            "model_form"
        ]
        .contains(&verdict),
        "{verdict}"
    );
    // Without a structured misfit above the practical threshold the verdict is the null one
    // (whatever the tests located), and the other way round; below it the sentence
    // quantifies how far the model is from the boards.
    let any = doc["located"]["any"].as_bool().unwrap();
    let above = doc["located"]["above_practical_threshold"]
        .as_bool()
        .unwrap();
    assert!(any || !above, "{doc:#}");
    assert_eq!(above, verdict != "no_missing_physics", "{doc:#}");
    if !above {
        let s = doc["remaining_discrepancy"].as_str().unwrap();
        assert!(
            s.contains("the model differs from these boards by at most"),
            "{s}"
        );
    }
    // No refit (--max-refits 0): nothing favoured, every candidate unrefitted; when step 2
    // did not run, that is reported, not fatal.
    assert!(doc["findings"].as_array().unwrap().is_empty());
    assert!(doc["candidates"]
        .as_array()
        .unwrap()
        .iter()
        .all(|c| c["refit"].is_null()));
    if !work.join("update_joints/evidence.json").is_file() {
        let msgs = doc["stage_findings"].to_string();
        assert!(msgs.contains("update_joints"), "{msgs}");
    }
    let batches = {
        let f = std::fs::File::open(out.join("diagnosis.parquet")).unwrap();
        parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder::try_new(f)
            .unwrap()
            .build()
            .unwrap()
            .collect::<Result<Vec<_>, _>>()
            .unwrap()
    };
    let rows: usize = batches.iter().map(|b| b.num_rows()).sum();
    assert_eq!(rows, doc["candidates"].as_array().unwrap().len());
    // The work directory copied elsewhere: the same bytes.
    let copy = t.path().join("elsewhere").join("small");
    crate::common::copy_dir(work, &copy);
    let out2 = t.path().join("d2");
    run(&copy, &out2);
    for f in ["diagnosis.json", "diagnosis.parquet"] {
        assert_eq!(
            std::fs::read(out.join(f)).unwrap(),
            std::fs::read(out2.join(f)).unwrap(),
            "{f} differs between directories"
        );
    }
}

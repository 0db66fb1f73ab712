//! Gerber import against third-party tools: boards written by gerbonara (a Gerber writer)
//! are read by hbmu and their per-element copper coverage is compared with pygerber's
//! raster rendering of the same files (`gerber_boards.py`; the top layer includes pads
//! flashed with aperture macros, whose row is compared with a finer rendering of that part
//! of the layer); malformed files get errors naming the file, line and command.

use crate::common::*;
use hbmu::fem::copper::CopperMap;
use hbmu::fem::geometry::Rect;
use hbmu::io::board_files::read_board;
use std::path::Path;

/// Reference rendering resolution, pixels per mm (5 µm pixels; pygerber snaps every edge
/// to a pixel, about 1 % of a 1 mm element's coverage at 10 µm). About 30 s and 4.7 GB
/// for the renderer. `HBMU_GERBER_DPMM` overrides it.
const DPMM: &str = "200";

/// Resolution of the second rendering, of the top layer's macro-pad row alone (elements
/// x 17–58 mm, y 5–8 mm of the 1 mm grid), pixels per mm. pygerber draws each macro flash on
/// its own pixel-snapped sub-image, ~2 pixels off: 10 µm at 200 px/mm, which is ~1.2 % of a
/// 1 mm element's coverage there, and 2.5 µm (~0.3 %) at 800. About 35 s and 5 GB for the
/// renderer. `HBMU_GERBER_WINDOW_DPMM` overrides it.
const WINDOW_DPMM: &str = "800";
/// The macro-pad row's elements on the 80 × 50 grid, board mm (x0, y0, x1, y1).
const MACRO_ROW_MM: [f64; 4] = [17.0, 5.0, 58.0, 8.0];

fn board_toml(outline: &str) -> String {
    format!(
        r#"name = "gerber-two-layer"
length_x_m = 0.080
width_y_m = 0.050

[core]
thickness_m = 1.5e-3
e_x_pa = 26.3e9
e_y_pa = 24.5e9
g_xy_pa = 5.9e9
nu_xy = 0.14
density_kg_per_m3 = 2000.0

[gerber]
outline = "{outline}"
resolution_m = 1e-4

[[copper]]
name = "top"
side = "top"
thickness_m = 35e-6
e_pa = 117e9
nu = 0.34
density_kg_per_m3 = 8960.0
gerber = "top.gbr"

[[copper]]
name = "bottom"
side = "bottom"
thickness_m = 35e-6
e_pa = 117e9
nu = 0.34
density_kg_per_m3 = 8960.0
gerber = "bottom.gbr"

[[holes]]
x_m = 0.004
y_m = 0.004
diameter_m = 2.7e-3

[joint]
clamp_diameter_m = 6.0e-3
k_con_n_per_m = 5.0e6
bolt_mass_kg = 1.2e-3

[mesh]
nx = 40
ny = 25

[scan_grid]
nx = 11
ny = 7
margin_m = 2.0e-3
"#
    )
}

fn write_board(dir: &Path, outline: &str) -> std::path::PathBuf {
    let p = dir.join("board.toml");
    std::fs::write(&p, board_toml(outline)).unwrap();
    p
}

#[test]
fn gerbonara_boards_match_pygerber_coverage_per_element() {
    if !python_has(&["gerbonara", "pygerber", "numpy", "PIL"]) {
        return;
    }
    let t = tempfile::tempdir().unwrap();
    let dir = t.path();
    let grids = [(40usize, 25usize), (37, 23), (80, 50)];
    let dpmm = std::env::var("HBMU_GERBER_DPMM").unwrap_or_else(|_| DPMM.to_string());
    let wdpmm =
        std::env::var("HBMU_GERBER_WINDOW_DPMM").unwrap_or_else(|_| WINDOW_DPMM.to_string());
    let mut args = vec![dir.to_str().unwrap().to_string(), dpmm];
    for (nx, ny) in grids {
        args.push(nx.to_string());
        args.push(ny.to_string());
    }
    args.push("--window".into());
    args.push("top".into());
    args.extend(MACRO_ROW_MM.iter().map(|v| v.to_string()));
    args.push(wdpmm);
    let args: Vec<&str> = args.iter().map(|s| s.as_str()).collect();
    let out = python("gerber_boards.py", &args);
    let reference: serde_json::Value = serde_json::from_str(out.trim()).unwrap();

    let window = &reference["window"]["coverage"]["80x50"];
    assert_eq!(
        window.as_object().map(|m| m.len()),
        Some(41 * 3),
        "the macro row's elements in the finer rendering"
    );
    let (board, files) = read_board(&write_board(dir, "outline.gbr")).unwrap();
    assert_eq!(files.len(), 4, "{files:?}");
    let map = CopperMap::new(&board);
    for (layer, name) in ["top", "bottom"].iter().enumerate() {
        for (nx, ny) in grids {
            let want = reference["layers"][name]["coverage"][format!("{nx}x{ny}")]
                .as_array()
                .unwrap();
            assert_eq!(want.len(), nx * ny);
            let (dx, dy) = (board.length_x_m / nx as f64, board.width_y_m / ny as f64);
            let (mut worst, mut sum, mut covered) = (0.0f64, 0.0, 0usize);
            let mut at = (0, 0);
            let (mut worst_macro, mut worst_macro_coarse) = (0.0f64, 0.0f64);
            for j in 0..ny {
                for i in 0..nx {
                    let r = Rect {
                        x0: i as f64 * dx,
                        y0: j as f64 * dy,
                        x1: (i + 1) as f64 * dx,
                        y1: (j + 1) as f64 * dy,
                    };
                    let got = map.mean_coverage(layer, &r);
                    let w = want[j * nx + i].as_f64().unwrap();
                    let d = (got - w).abs();
                    // The top layer's row of macro pads (centres y = 6.2 mm, x = 19 …
                    // 56.4 mm, at most 1.1 mm from the centre): on the 1 mm grid, compared
                    // with the finer rendering of that row (the coarse one's difference is
                    // printed).
                    let in_macro_row = layer == 0
                        && r.y1 > 5.0e-3
                        && r.y0 < 7.4e-3
                        && r.x1 > 17.8e-3
                        && r.x0 < 57.6e-3;
                    if in_macro_row && nx == 80 {
                        let fine = window[format!("{i},{j}")].as_f64().unwrap_or_else(|| {
                            panic!("element ({i}, {j}) missing from the finer rendering")
                        });
                        worst_macro = worst_macro.max((got - fine).abs());
                        worst_macro_coarse = worst_macro_coarse.max(d);
                        continue;
                    }
                    if d > worst {
                        worst = d;
                        at = (i, j);
                    }
                    sum += d;
                    covered += usize::from(w > 0.0);
                }
            }
            eprintln!(
                "gerber {name} {nx}x{ny}: max |hbmu − pygerber| coverage {worst:.4} at element {at:?}, mean {:.5}, {covered} elements with copper",
                sum / (nx * ny) as f64
            );
            assert!(covered > nx * ny / 4, "{name}: too few covered elements");
            // The acceptance bound: 1 % coverage per element, on the board's mesh, an
            // unaligned one and a 1 mm one.
            let tol = 0.01;
            assert!(
                worst <= tol,
                "{name} {nx}x{ny}: coverage differs from pygerber's by {worst} at element {at:?}"
            );
            // pygerber 2.4.3 places a macro flash on its own pixel-snapped sub-image: at
            // 200 px/mm its rounded-rectangle pad comes out ~2 pixels (10 µm) off in y
            // against an exact evaluation of the macro as written (element (25, 5):
            // pygerber 0.2436, point sampling of the written primitives 0.2320, hbmu
            // 0.2320), with the pad's total area right (1.5228 mm² both), which on the 1 mm
            // grid is 1.2 %. The row is held to the same 1 % against the finer rendering of
            // the row alone, where the snap is a quarter as large; on the coarser grids the
            // row is inside the bound at 200 px/mm with everything else.
            if nx == 80 && layer == 0 {
                eprintln!(
                    "gerber top 80x50 macro-pad row: max |hbmu − pygerber| {worst_macro:.4} at {wdpmm_used} px/mm ({worst_macro_coarse:.4} at the whole board's resolution)",
                    wdpmm_used = reference["window"]["dpmm"]
                );
                assert!(
                    worst_macro <= tol,
                    "macro row: coverage differs from pygerber's finer rendering by {worst_macro}"
                );
            }
        }
    }
}

#[test]
fn malformed_gerber_and_wrong_outline_are_refused_with_file_line_and_command() {
    if !python_has(&["gerbonara", "pygerber", "numpy", "PIL"]) {
        return;
    }
    let t = tempfile::tempdir().unwrap();
    let dir = t.path();
    python("gerber_boards.py", &[dir.to_str().unwrap(), "5"]);
    // A board whose outline is not the board's size.
    let text = std::fs::read_to_string(dir.join("outline.gbr")).unwrap();
    let big = text.replace("X018000000", "X018100000");
    assert_ne!(big, text, "expected the outline's right edge at x = 180 mm");
    std::fs::write(dir.join("big.gbr"), big).unwrap();
    let e = format!(
        "{:#}",
        read_board(&write_board(dir, "big.gbr")).unwrap_err()
    );
    assert!(
        e.contains("big.gbr") && e.contains("0.081"),
        "expected the outline size named: {e}"
    );
    // A flash with an aperture that is never defined, in the top layer.
    let top = std::fs::read_to_string(dir.join("top.gbr")).unwrap();
    let lines: Vec<&str> = top.lines().collect();
    let k = lines.iter().position(|l| l.ends_with("D03*")).unwrap();
    let mut bad = lines.clone();
    bad.insert(k, "D99*");
    std::fs::write(dir.join("top.gbr"), bad.join("\n")).unwrap();
    let e = format!(
        "{:#}",
        read_board(&write_board(dir, "outline.gbr")).unwrap_err()
    );
    let at = format!("top.gbr:{}: `D99`", k + 1);
    assert!(
        e.contains(&at) && e.contains("undefined"),
        "expected {at}: {e}"
    );
    // A coordinate word cut short.
    let mut bad = lines.clone();
    bad[k] = "X12Y";
    std::fs::write(dir.join("top.gbr"), bad.join("\n")).unwrap();
    let e = format!(
        "{:#}",
        read_board(&write_board(dir, "outline.gbr")).unwrap_err()
    );
    let at = format!("top.gbr:{}: `X12Y", k + 1);
    assert!(e.contains(&at), "expected {at}: {e}");
}

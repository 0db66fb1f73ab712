//! Reading a board description with the files it names: the TOML itself, each copper
//! layer's raster density maps (CSV grids) and Gerber files, and the Gerber board
//! outline (paths relative to the board file).

use crate::fem::board::{Board, GerberLayerImage, Grid};
use anyhow::{bail, Context};
use std::path::{Path, PathBuf};

/// Parse a density-map CSV: one line per row of cells (first line = lowest row), one
/// comma-separated fraction per cell, `#` comment lines. Errors name the file and line.
pub fn parse_density_csv(bytes: &[u8], name: &str) -> anyhow::Result<Grid> {
    let mut rdr = csv::ReaderBuilder::new()
        .has_headers(false)
        .comment(Some(b'#'))
        .trim(csv::Trim::All)
        .flexible(true)
        .from_reader(bytes);
    let mut values = Vec::new();
    let (mut nx, mut ny) = (0usize, 0usize);
    for rec in rdr.records() {
        let rec = rec.with_context(|| format!("{name}: malformed CSV"))?;
        let line = rec.position().map(|p| p.line()).unwrap_or(0);
        if rec.iter().all(|f| f.is_empty()) {
            continue;
        }
        if ny == 0 {
            nx = rec.len();
        } else if rec.len() != nx {
            bail!(
                "{name}:{line}: expected {nx} values per row (as in the first row), found {}",
                rec.len()
            );
        }
        for (k, f) in rec.iter().enumerate() {
            let v: f64 = f.parse().map_err(|_| {
                anyhow::anyhow!(
                    "{name}:{line}: value {}: expected a copper fraction in [0, 1], found {f:?}",
                    k + 1
                )
            })?;
            if !(0.0..=1.0).contains(&v) {
                bail!(
                    "{name}:{line}: value {}: expected a copper fraction in [0, 1], found {v}",
                    k + 1
                );
            }
            values.push(v);
        }
        ny += 1;
    }
    if nx == 0 || ny == 0 {
        bail!("{name}: expected at least one row of values, found none");
    }
    Ok(Grid { nx, ny, values })
}

/// Read a board file and the density maps it names; returns the board (validated),
/// and every file read (the board first) so a stage can fingerprint them.
pub fn read_board(path: &Path) -> anyhow::Result<(Board, Vec<PathBuf>)> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read board file {}", path.display()))?;
    let mut b =
        Board::from_toml_str_unvalidated(&text).with_context(|| format!("{}", path.display()))?;
    let dir = path.parent().unwrap_or(Path::new("."));
    let mut files = vec![path.to_path_buf()];
    for l in &mut b.copper {
        for d in &mut l.density_maps {
            let f = dir.join(&d.file);
            let bytes = std::fs::read(&f).with_context(|| {
                format!(
                    "{}: copper layer {:?}: cannot read density map {}",
                    path.display(),
                    l.name,
                    f.display()
                )
            })?;
            d.grid = Some(parse_density_csv(&bytes, &f.display().to_string())?);
            files.push(f);
        }
    }
    read_gerber_layers(&mut b, path, dir, &mut files)?;
    b.validate()
        .with_context(|| format!("{}", path.display()))?;
    Ok((b, files))
}

/// Largest difference between the outline's size and the board's, m.
const OUTLINE_TOL_M: f64 = 1e-4;

/// Rasterize each copper layer's Gerber file over the board (frame from the outline
/// file or `origin_m`).
fn read_gerber_layers(
    b: &mut Board,
    path: &Path,
    dir: &Path,
    files: &mut Vec<PathBuf>,
) -> anyhow::Result<()> {
    let any_layer = b.copper.iter().any(|l| l.gerber.is_some());
    let Some(opts) = b.gerber.clone() else {
        if any_layer {
            // Defaults: Gerber origin at the board corner, 0.1 mm raster.
            b.gerber = Some(crate::fem::board::GerberOptions {
                outline: None,
                origin_m: None,
                resolution_m: 1e-4,
            });
            return read_gerber_layers(b, path, dir, files);
        }
        return Ok(());
    };
    let mut origin = opts.origin_m.unwrap_or([0.0, 0.0]);
    if let Some(o) = &opts.outline {
        if opts.origin_m.is_some() {
            bail!("{}: gerber: expected either `outline` or `origin_m`, found both (the outline sets the origin)", path.display());
        }
        let f = dir.join(o);
        let img = read_gerber(&f)?;
        let Some(bb) = img.path_bbox else {
            bail!(
                "{}: expected the board outline drawn (D01 strokes or regions), found nothing drawn",
                f.display()
            );
        };
        let (lx, ly) = (bb.x1 - bb.x0, bb.y1 - bb.y0);
        if (lx - b.length_x_m).abs() > OUTLINE_TOL_M || (ly - b.width_y_m).abs() > OUTLINE_TOL_M {
            bail!(
                "{}: expected a board outline of {} × {} m (length_x_m × width_y_m of {}), found {lx:.6} × {ly:.6} m",
                f.display(),
                b.length_x_m,
                b.width_y_m,
                path.display()
            );
        }
        origin = [bb.x0, bb.y0];
        files.push(f);
    }
    if !(opts.resolution_m.is_finite() && opts.resolution_m > 0.0) {
        bail!(
            "{}: gerber.resolution_m: expected a finite positive number, found {}",
            path.display(),
            opts.resolution_m
        );
    }
    for l in &mut b.copper {
        let Some(g) = &l.gerber else { continue };
        let f = dir.join(g);
        // The error names the Gerber file, line and command.
        let mut image = read_gerber(&f)?;
        image.translate(-origin[0], -origin[1]);
        l.gerber_image = Some(std::sync::Arc::new(GerberLayerImage {
            image,
            resolution_m: opts.resolution_m,
        }));
        files.push(f);
    }
    Ok(())
}

/// Read, parse and render a Gerber file.
pub fn read_gerber(path: &Path) -> anyhow::Result<crate::fem::gerber::Image> {
    let bytes = std::fs::read(path)
        .with_context(|| format!("cannot read Gerber file {}", path.display()))?;
    let text = String::from_utf8_lossy(&bytes);
    crate::formats::gerber::read_gerber_str(&text, &path.display().to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn density_csv_parses_rows_bottom_up_and_names_bad_lines() {
        let g = parse_density_csv(b"# map\n0.1, 0.2, 0.3\n0.4,0.5,0.6\n", "m.csv").unwrap();
        assert_eq!((g.nx, g.ny), (3, 2));
        assert_eq!(g.values, vec![0.1, 0.2, 0.3, 0.4, 0.5, 0.6]);
        let e = parse_density_csv(b"0.1,0.2\n0.3\n", "m.csv")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("m.csv:2") && e.contains("expected 2 values"),
            "{e}"
        );
        let e = parse_density_csv(b"0.1,x\n", "m.csv")
            .unwrap_err()
            .to_string();
        assert!(e.contains("m.csv:1") && e.contains("value 2"), "{e}");
        let e = parse_density_csv(b"0.1,1.5\n", "m.csv")
            .unwrap_err()
            .to_string();
        assert!(e.contains("found 1.5"), "{e}");
        assert!(parse_density_csv(b"# nothing\n", "m.csv").is_err());
    }
}

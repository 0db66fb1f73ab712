//! Reading a board description with the files it names: the TOML itself and each
//! copper layer's raster density maps (CSV grids, paths relative to the board file).

use crate::fem::board::{Board, Grid};
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
    b.validate()
        .with_context(|| format!("{}", path.display()))?;
    Ok((b, files))
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

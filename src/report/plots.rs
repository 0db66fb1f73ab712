//! SVG rendering of the stabilization diagram and the MAC matrix (pure, into a `String`).
//!
//! Rendering only: the callers (stages) decide file names and write the strings. Uses
//! plotters' SVG backend, which needs no font files (text is emitted as SVG `<text>`).

use crate::modal::stabilization::StabilizationDiagram;
use plotters::prelude::*;

/// A plot could not be drawn (message from plotters).
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
#[error("plot {plot}: {detail}")]
pub struct PlotError {
    pub plot: &'static str,
    pub detail: String,
}

fn perr<E: std::fmt::Debug>(plot: &'static str) -> impl Fn(E) -> PlotError {
    move |e| PlotError {
        plot,
        detail: format!("{e:?}"),
    }
}

/// Stabilization diagram: poles per model order (x: frequency in Hz, y: order).
///
/// Symbols: green filled circle = stable in frequency, damping and shape; blue circle =
/// stable in frequency and shape; orange cross = stable in frequency only; grey dot = new
/// or unstable. Red vertical lines mark `selected_freq_hz`. If `spectrum` is given as
/// `(freq_hz, magnitude)` (e.g. the sum of |H| over points), its log magnitude is drawn in
/// the background, scaled to the order axis.
pub fn stabilization_svg(
    diagram: &StabilizationDiagram,
    selected_freq_hz: &[f64],
    spectrum: Option<(&[f64], &[f64])>,
    title: &str,
) -> Result<String, PlotError> {
    const P: &str = "stabilization";
    let mut out = String::new();
    {
        let root = SVGBackend::with_string(&mut out, (1000, 600)).into_drawing_area();
        root.fill(&WHITE).map_err(perr(P))?;
        let (lo, hi) = diagram.band_hz;
        let max_order = diagram.orders.iter().copied().max().unwrap_or(2) as f64 + 2.0;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 20))
            .margin(10)
            .x_label_area_size(40)
            .y_label_area_size(50)
            .build_cartesian_2d(lo..hi, 0.0..max_order)
            .map_err(perr(P))?;
        chart
            .configure_mesh()
            .x_desc("frequency [Hz]")
            .y_desc("model order")
            .disable_mesh()
            .draw()
            .map_err(perr(P))?;
        if let Some((f, mag)) = spectrum {
            let logs: Vec<(f64, f64)> = f
                .iter()
                .zip(mag)
                .filter(|(x, m)| **x >= lo && **x <= hi && **m > 0.0)
                .map(|(x, m)| (*x, m.log10()))
                .collect();
            let (mn, mx) = logs
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), (_, v)| {
                    (a.min(*v), b.max(*v))
                });
            if mx > mn {
                chart
                    .draw_series(LineSeries::new(
                        logs.iter()
                            .map(|(x, v)| (*x, 1.0 + (v - mn) / (mx - mn) * (max_order - 2.0))),
                        RGBColor(160, 160, 160).stroke_width(1),
                    ))
                    .map_err(perr(P))?;
            }
        }
        for f in selected_freq_hz {
            chart
                .draw_series(LineSeries::new(
                    vec![(*f, 0.0), (*f, max_order)],
                    RED.mix(0.6).stroke_width(1),
                ))
                .map_err(perr(P))?;
        }
        let pts = |pred: &dyn Fn(&crate::modal::stabilization::DiagramPole) -> bool| {
            diagram
                .poles
                .iter()
                .filter(|p| pred(p) && p.freq_hz >= lo && p.freq_hz <= hi)
                .map(|p| (p.freq_hz, p.order as f64))
                .collect::<Vec<_>>()
        };
        let unstable = pts(&|p| !p.stable_freq);
        let f_only = pts(&|p| p.stable_freq && !p.stable_shape && !p.fully_stable());
        let f_shape = pts(&|p| p.stable_freq && p.stable_shape && !p.stable_damping);
        let all = pts(&|p| p.fully_stable());
        let grey = RGBColor(150, 150, 150);
        chart
            .draw_series(unstable.iter().map(|&c| Circle::new(c, 1, grey.filled())))
            .map_err(perr(P))?;
        let orange = RGBColor(230, 140, 0);
        chart
            .draw_series(
                f_only
                    .iter()
                    .map(|&c| Cross::new(c, 3, orange.stroke_width(1))),
            )
            .map_err(perr(P))?;
        chart
            .draw_series(
                f_shape
                    .iter()
                    .map(|&c| Circle::new(c, 3, BLUE.stroke_width(1))),
            )
            .map_err(perr(P))?;
        let green = RGBColor(0, 150, 0);
        chart
            .draw_series(all.iter().map(|&c| Circle::new(c, 3, green.filled())))
            .map_err(perr(P))?;
        root.present().map_err(perr(P))?;
    }
    Ok(out)
}

/// MAC matrix as a grey-scale heat map (black = 1), value printed in each cell when the
/// matrix has at most 20 rows and columns. `mac[i][j]` is drawn at row `i` (from the top,
/// labelled `row_labels[i]`) and column `j` (`col_labels[j]`).
pub fn mac_matrix_svg(
    mac: &[Vec<f64>],
    row_labels: &[String],
    col_labels: &[String],
    title: &str,
) -> Result<String, PlotError> {
    const P: &str = "mac matrix";
    let nr = mac.len();
    let nc = mac.first().map_or(0, |r| r.len());
    if mac.iter().any(|r| r.len() != nc) || row_labels.len() != nr || col_labels.len() != nc {
        return Err(PlotError {
            plot: P,
            detail: format!(
                "expected a rectangular {nr}x{nc} matrix with {nr} row and {nc} column labels, found {} row and {} column labels",
                row_labels.len(),
                col_labels.len()
            ),
        });
    }
    let mut out = String::new();
    {
        let cell = 48u32;
        let w = 180 + cell * nc.max(1) as u32;
        let h = 160 + cell * nr.max(1) as u32;
        let root = SVGBackend::with_string(&mut out, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(perr(P))?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 18))
            .margin(10)
            .x_label_area_size(90)
            .y_label_area_size(120)
            .build_cartesian_2d(0.0..nc.max(1) as f64, 0.0..nr.max(1) as f64)
            .map_err(perr(P))?;
        chart
            .configure_mesh()
            .disable_mesh()
            .disable_x_axis()
            .disable_y_axis()
            .draw()
            .map_err(perr(P))?;
        for (i, row) in mac.iter().enumerate() {
            let y0 = (nr - 1 - i) as f64;
            for (j, v) in row.iter().enumerate() {
                let g = (255.0 * (1.0 - v.clamp(0.0, 1.0))).round() as u8;
                chart
                    .draw_series(std::iter::once(Rectangle::new(
                        [(j as f64, y0), (j as f64 + 1.0, y0 + 1.0)],
                        RGBColor(g, g, g).filled(),
                    )))
                    .map_err(perr(P))?;
                if nr <= 20 && nc <= 20 {
                    let color = if *v > 0.5 { WHITE } else { BLACK };
                    chart
                        .draw_series(std::iter::once(Text::new(
                            format!("{v:.2}"),
                            (j as f64 + 0.2, y0 + 0.6),
                            ("sans-serif", 12).into_font().color(&color),
                        )))
                        .map_err(perr(P))?;
                }
            }
        }
        // Labels drawn in pixel space around the plotting area.
        let (xr, yr) = chart.plotting_area().get_pixel_range();
        let cw = (xr.end - xr.start) as f64 / nc.max(1) as f64;
        let ch = (yr.end - yr.start) as f64 / nr.max(1) as f64;
        for (i, l) in row_labels.iter().enumerate() {
            root.draw(&Text::new(
                l.clone(),
                (5, yr.start + (ch * (i as f64 + 0.5)) as i32),
                ("sans-serif", 12).into_font(),
            ))
            .map_err(perr(P))?;
        }
        for (j, l) in col_labels.iter().enumerate() {
            root.draw(&Text::new(
                l.clone(),
                (
                    xr.start + (cw * j as f64) as i32 + 2,
                    yr.end + 8 + 14 * (j % 2) as i32,
                ),
                ("sans-serif", 11).into_font(),
            ))
            .map_err(perr(P))?;
        }
        root.present().map_err(perr(P))?;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::modal::stabilization::DiagramPole;

    #[test]
    fn renders_valid_svg_with_all_elements() {
        let poles = (0..3)
            .map(|k| DiagramPole {
                order: 10 + 2 * k,
                freq_hz: 100.0,
                damping_ratio: 0.01,
                lambda_re: -6.0,
                lambda_im: 628.0,
                stable_freq: k > 0,
                stable_damping: k > 0,
                stable_shape: k > 0,
                shape: vec![],
            })
            .collect();
        let d = StabilizationDiagram {
            band_hz: (10.0, 200.0),
            orders: vec![10, 12, 14],
            poles,
        };
        let svg = stabilization_svg(
            &d,
            &[100.0],
            Some((&[50.0, 100.0, 150.0], &[1.0, 10.0, 1.0])),
            "m1",
        )
        .unwrap();
        assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
        // 1 unstable dot + 2 stable filled circles.
        assert_eq!(svg.matches("<circle").count(), 3);
        let mac = vec![vec![1.0, 0.1], vec![0.05, 0.97]];
        let labels = |v: &[&str]| v.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        let svg = mac_matrix_svg(
            &mac,
            &labels(&["a", "b"]),
            &labels(&["torsion-1", "bending-x-1"]),
            "MAC",
        )
        .unwrap();
        assert!(svg.contains("torsion-1") && svg.contains("0.97"));
        assert!(mac_matrix_svg(&mac, &labels(&["a"]), &labels(&["x", "y"]), "bad").is_err());
    }
}

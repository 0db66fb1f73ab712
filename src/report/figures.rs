//! SVG figures of the validation report (pure, into `String`s), with plotters' SVG backend
//! like [`super::plots`]: the Figure-6 analog (predicted boxes with measurements overlaid),
//! posterior densities, the correlation matrix, the tempering path and the diagnosis's
//! before/after misfit per mode.

use super::plots::PlotError;
use plotters::prelude::*;

fn perr<E: std::fmt::Debug>(plot: &'static str) -> impl Fn(E) -> PlotError {
    move |e| PlotError {
        plot,
        detail: format!("{e:?}"),
    }
}

/// Colour-blind-safe qualitative palette (Okabe & Ito 2008).
pub const PALETTE: [RGBColor; 8] = [
    RGBColor(0, 114, 178),
    RGBColor(230, 159, 0),
    RGBColor(0, 158, 115),
    RGBColor(204, 121, 167),
    RGBColor(86, 180, 233),
    RGBColor(213, 94, 0),
    RGBColor(240, 228, 66),
    RGBColor(0, 0, 0),
];

fn colour(i: usize) -> RGBColor {
    PALETTE[i % PALETTE.len()]
}

/// One box of the Figure-6 analog: a predicted distribution and the measurements of it.
#[derive(Clone, Debug)]
pub struct BoxItem {
    pub label: String,
    pub q05: f64,
    pub q25: f64,
    pub q50: f64,
    pub q75: f64,
    pub q95: f64,
    /// Measured frequencies, Hz, and whether the mode was used for updating.
    pub measured: Vec<f64>,
    pub used_for_updating: bool,
}

/// Figure-6 analog: per mode label, the predicted distribution as a box (quartiles), whiskers
/// (5 % and 95 %) and median, on a common relative axis (f / predicted median − 1, in %, so
/// modes hundreds of Hz apart share one legible scale), measurements overlaid: filled circles
/// for updating modes, open diamonds for validation modes.
pub fn boxes_svg(title: &str, items: &[BoxItem]) -> Result<String, PlotError> {
    const P: &str = "boxes";
    let rel = |f: f64, m: f64| 100.0 * (f / m - 1.0);
    let mut lo = f64::INFINITY;
    let mut hi = f64::NEG_INFINITY;
    for it in items {
        for v in [it.q05, it.q95]
            .into_iter()
            .chain(it.measured.iter().copied())
        {
            let r = rel(v, it.q50);
            if r.is_finite() {
                lo = lo.min(r);
                hi = hi.max(r);
            }
        }
    }
    if hi.partial_cmp(&lo) != Some(std::cmp::Ordering::Greater) {
        lo = -1.0;
        hi = 1.0;
    }
    let pad = 0.08 * (hi - lo);
    let (lo, hi) = (lo - pad, hi + pad);
    let n = items.len().max(1);
    let mut out = String::new();
    {
        let w = (160 + 90 * n as u32).max(520);
        let root = SVGBackend::with_string(&mut out, (w, 420)).into_drawing_area();
        root.fill(&WHITE).map_err(perr(P))?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 18))
            .margin(12)
            .x_label_area_size(70)
            .y_label_area_size(70)
            .build_cartesian_2d(0.0..n as f64, lo..hi)
            .map_err(perr(P))?;
        let labels: Vec<String> = items.iter().map(|i| i.label.clone()).collect();
        chart
            .configure_mesh()
            .disable_x_mesh()
            .x_labels(n * 2 + 1)
            .x_label_formatter(&|x| pick(&labels, *x, false))
            .x_label_style(("sans-serif", 13))
            .y_label_style(("sans-serif", 13))
            .y_desc("f / predicted median − 1 [%]")
            .x_desc("mode")
            .axis_desc_style(("sans-serif", 14))
            .draw()
            .map_err(perr(P))?;
        let box_c = RGBColor(120, 120, 120);
        for (k, it) in items.iter().enumerate() {
            let x = k as f64 + 0.5;
            let m = it.q50;
            let (a, b, c, d, e) = (
                rel(it.q05, m),
                rel(it.q25, m),
                0.0,
                rel(it.q75, m),
                rel(it.q95, m),
            );
            let fill = if it.used_for_updating {
                RGBColor(200, 220, 240)
            } else {
                RGBColor(250, 225, 190)
            };
            chart
                .draw_series(std::iter::once(Rectangle::new(
                    [(x - 0.25, b), (x + 0.25, d)],
                    fill.filled(),
                )))
                .map_err(perr(P))?;
            chart
                .draw_series(std::iter::once(Rectangle::new(
                    [(x - 0.25, b), (x + 0.25, d)],
                    box_c.stroke_width(1),
                )))
                .map_err(perr(P))?;
            for seg in [
                vec![(x, a), (x, b)],
                vec![(x, d), (x, e)],
                vec![(x - 0.12, a), (x + 0.12, a)],
                vec![(x - 0.12, e), (x + 0.12, e)],
            ] {
                chart
                    .draw_series(LineSeries::new(seg, box_c.stroke_width(1)))
                    .map_err(perr(P))?;
            }
            chart
                .draw_series(LineSeries::new(
                    vec![(x - 0.25, c), (x + 0.25, c)],
                    BLACK.stroke_width(2),
                ))
                .map_err(perr(P))?;
            let nm = it.measured.len().max(1) as f64;
            for (j, f) in it.measured.iter().enumerate() {
                // Spread the points sideways a little so repeated values stay visible.
                let xj = x - 0.15 + 0.3 * (j as f64 + 0.5) / nm;
                let y = rel(*f, m);
                if it.used_for_updating {
                    chart
                        .draw_series(std::iter::once(Circle::new(
                            (xj, y),
                            4,
                            RGBColor(0, 90, 160).filled(),
                        )))
                        .map_err(perr(P))?;
                } else {
                    chart
                        .draw_series(std::iter::once(TriangleMarker::new(
                            (xj, y),
                            5,
                            RGBColor(200, 80, 0).stroke_width(2),
                        )))
                        .map_err(perr(P))?;
                }
            }
        }
        root.present().map_err(perr(P))?;
    }
    Ok(out)
}

/// A histogram density of each series (normalised to unit area) on one axis: `series` are
/// (name, samples); values are divided by `scale` for display (e.g. 1e9 for GPa).
pub fn density_svg(
    title: &str,
    x_desc: &str,
    series: &[(String, Vec<f64>)],
    scale: f64,
) -> Result<String, PlotError> {
    const P: &str = "density";
    let all: Vec<f64> = series
        .iter()
        .flat_map(|(_, v)| v.iter().map(|x| x / scale))
        .filter(|x| x.is_finite())
        .collect();
    let (mut lo, mut hi) = all
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(*v), b.max(*v))
        });
    if hi.partial_cmp(&lo) != Some(std::cmp::Ordering::Greater) {
        let c = if lo.is_finite() { lo } else { 0.0 };
        lo = c - 1.0;
        hi = c + 1.0;
    }
    let bins = 30usize;
    let width = (hi - lo) / bins as f64;
    let hists: Vec<Vec<f64>> = series
        .iter()
        .map(|(_, v)| {
            let mut h = vec![0.0; bins];
            let n = v.iter().filter(|x| x.is_finite()).count().max(1) as f64;
            for x in v.iter().map(|x| x / scale).filter(|x| x.is_finite()) {
                let k = (((x - lo) / width) as usize).min(bins - 1);
                h[k] += 1.0 / (n * width);
            }
            h
        })
        .collect();
    let ymax = hists
        .iter()
        .flatten()
        .fold(0.0f64, |a, b| a.max(*b))
        .max(1e-300)
        * 1.08;
    let mut out = String::new();
    {
        let root = SVGBackend::with_string(&mut out, (640, 380)).into_drawing_area();
        root.fill(&WHITE).map_err(perr(P))?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 17))
            .margin(12)
            .x_label_area_size(50)
            .y_label_area_size(70)
            .build_cartesian_2d(lo..hi, 0.0..ymax)
            .map_err(perr(P))?;
        chart
            .configure_mesh()
            .x_desc(x_desc)
            .y_desc("density")
            .x_labels(6)
            .y_labels(5)
            .y_label_formatter(&|v| {
                if *v == 0.0 {
                    "0".to_string()
                } else if v.abs() >= 0.01 && v.abs() < 1000.0 {
                    format!("{v:.3}")
                } else {
                    format!("{v:.1e}")
                }
            })
            .label_style(("sans-serif", 13))
            .axis_desc_style(("sans-serif", 14))
            .disable_mesh()
            .draw()
            .map_err(perr(P))?;
        for (i, ((name, _), h)) in series.iter().zip(&hists).enumerate() {
            let c = colour(i);
            let pts: Vec<(f64, f64)> = h
                .iter()
                .enumerate()
                .flat_map(|(k, v)| {
                    let x0 = lo + k as f64 * width;
                    [(x0, *v), (x0 + width, *v)]
                })
                .collect();
            chart
                .draw_series(LineSeries::new(pts, c.stroke_width(2)))
                .map_err(perr(P))?
                .label(name.clone())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 16, y)], c.stroke_width(3))
                });
        }
        if series.len() > 1 {
            chart
                .configure_series_labels()
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK.mix(0.3))
                .label_font(("sans-serif", 12))
                .position(SeriesLabelPosition::UpperRight)
                .draw()
                .map_err(perr(P))?;
        }
        root.present().map_err(perr(P))?;
    }
    Ok(out)
}

/// A correlation matrix as a diverging heat map (blue −1, white 0, red +1), values printed.
pub fn correlation_svg(title: &str, names: &[String], corr: &[f64]) -> Result<String, PlotError> {
    const P: &str = "correlation";
    let d = names.len();
    if corr.len() != d * d {
        return Err(PlotError {
            plot: P,
            detail: format!("expected a {d}x{d} matrix, found {} values", corr.len()),
        });
    }
    let mut out = String::new();
    {
        let cell = 70u32;
        let root =
            SVGBackend::with_string(&mut out, (200 + cell * d as u32, 120 + cell * d as u32))
                .into_drawing_area();
        root.fill(&WHITE).map_err(perr(P))?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 17))
            .margin(10)
            .x_label_area_size(40)
            .y_label_area_size(150)
            .build_cartesian_2d(0.0..d.max(1) as f64, 0.0..d.max(1) as f64)
            .map_err(perr(P))?;
        let nm = names.to_vec();
        let nm2 = names.to_vec();
        chart
            .configure_mesh()
            .disable_mesh()
            .x_labels(2 * d + 1)
            .y_labels(2 * d + 1)
            .x_label_formatter(&|x| pick(&nm, *x, false))
            .y_label_formatter(&|y| pick(&nm2, *y, true))
            .label_style(("sans-serif", 12))
            .draw()
            .map_err(perr(P))?;
        for i in 0..d {
            for j in 0..d {
                let v = corr[i * d + j].clamp(-1.0, 1.0);
                let t = v.abs();
                let mixc = |c: u8| (255.0 - t * (255.0 - c as f64)).round() as u8;
                let c = if v >= 0.0 {
                    RGBColor(mixc(200), mixc(40), mixc(40))
                } else {
                    RGBColor(mixc(30), mixc(90), mixc(200))
                };
                let y0 = (d - 1 - i) as f64;
                chart
                    .draw_series(std::iter::once(Rectangle::new(
                        [(j as f64, y0), (j as f64 + 1.0, y0 + 1.0)],
                        c.filled(),
                    )))
                    .map_err(perr(P))?;
                let tc = if t > 0.6 { WHITE } else { BLACK };
                chart
                    .draw_series(std::iter::once(Text::new(
                        format!("{v:+.2}"),
                        (j as f64 + 0.25, y0 + 0.6),
                        ("sans-serif", 14).into_font().color(&tc),
                    )))
                    .map_err(perr(P))?;
            }
        }
        root.present().map_err(perr(P))?;
    }
    Ok(out)
}

fn pick(names: &[String], x: f64, reversed: bool) -> String {
    let k = (x - 0.5).round();
    if (x - 0.5 - k).abs() > 1e-6 || k < 0.0 || k as usize >= names.len() {
        return String::new();
    }
    let k = k as usize;
    if reversed {
        names[names.len() - 1 - k].clone()
    } else {
        names[k].clone()
    }
}

/// The tempering path of each run: log10 β against the stage (β = 1 at the end).
pub fn tempering_svg(title: &str, runs: &[Vec<(f64, f64)>]) -> Result<String, PlotError> {
    const P: &str = "tempering";
    let xmax = runs.iter().flatten().map(|p| p.0).fold(1.0f64, f64::max);
    let ymin = runs
        .iter()
        .flatten()
        .map(|p| p.1.max(1e-300).log10())
        .fold(0.0f64, f64::min)
        .min(-1.0);
    let mut out = String::new();
    {
        let root = SVGBackend::with_string(&mut out, (640, 360)).into_drawing_area();
        root.fill(&WHITE).map_err(perr(P))?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 17))
            .margin(12)
            .x_label_area_size(50)
            .y_label_area_size(60)
            .build_cartesian_2d(0.0..xmax + 1.0, ymin * 1.05..0.5)
            .map_err(perr(P))?;
        chart
            .configure_mesh()
            .x_desc("tempering stage")
            .y_desc("log10 β")
            .label_style(("sans-serif", 13))
            .axis_desc_style(("sans-serif", 14))
            .disable_mesh()
            .draw()
            .map_err(perr(P))?;
        for (i, r) in runs.iter().enumerate() {
            let c = colour(i);
            let pts: Vec<(f64, f64)> = r.iter().map(|(s, b)| (*s, b.max(1e-300).log10())).collect();
            chart
                .draw_series(LineSeries::new(pts.clone(), c.stroke_width(2)))
                .map_err(perr(P))?
                .label(format!("run {}", i))
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 16, y)], c.stroke_width(3))
                });
            chart
                .draw_series(pts.iter().map(|p| Circle::new(*p, 3, c.filled())))
                .map_err(perr(P))?;
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK.mix(0.3))
            .label_font(("sans-serif", 12))
            .position(SeriesLabelPosition::LowerRight)
            .draw()
            .map_err(perr(P))?;
        root.present().map_err(perr(P))?;
    }
    Ok(out)
}

/// One mode of the before/after figure: its mean relative residual (percent) in the baseline
/// and after the refit (`None`: no refit).
#[derive(Clone, Debug)]
pub struct BeforeAfter {
    pub label: String,
    pub before_pct: f64,
    pub after_pct: Option<f64>,
    /// Located as misfitting in the baseline (drawn with a darker outline).
    pub located: bool,
}

/// Per mode, the baseline's mean relative residual against the refit's, as side-by-side bars
/// from zero (the model's mean prediction), in percent; `after_name` names the refit in the
/// legend.
pub fn before_after_svg(
    title: &str,
    items: &[BeforeAfter],
    after_name: Option<&str>,
) -> Result<String, PlotError> {
    const P: &str = "before_after";
    let vals = items
        .iter()
        .flat_map(|i| std::iter::once(i.before_pct).chain(i.after_pct))
        .filter(|v| v.is_finite());
    let (mut lo, mut hi) = vals.fold((0.0f64, 0.0f64), |(a, b), v| (a.min(v), b.max(v)));
    if hi - lo <= 0.0 {
        lo = -0.1;
        hi = 0.1;
    }
    let pad = 0.1 * (hi - lo);
    let (lo, hi) = (lo - pad, hi + pad);
    let n = items.len().max(1);
    let mut out = String::new();
    {
        let w = (160 + 110 * n as u32).max(560);
        let root = SVGBackend::with_string(&mut out, (w, 420)).into_drawing_area();
        root.fill(&WHITE).map_err(perr(P))?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 18))
            .margin(12)
            .x_label_area_size(70)
            .y_label_area_size(80)
            .build_cartesian_2d(0.0..n as f64, lo..hi)
            .map_err(perr(P))?;
        let labels: Vec<String> = items
            .iter()
            .map(|i| {
                if i.located {
                    format!("{} *", i.label)
                } else {
                    i.label.clone()
                }
            })
            .collect();
        chart
            .configure_mesh()
            .disable_x_mesh()
            .x_labels(n * 2 + 1)
            .x_label_formatter(&|x| pick(&labels, *x, false))
            .x_label_style(("sans-serif", 13))
            .y_label_style(("sans-serif", 13))
            .y_desc("mean (f_measured − f_model) / f_model [%]")
            .x_desc("mode (* located as misfitting)")
            .axis_desc_style(("sans-serif", 14))
            .draw()
            .map_err(perr(P))?;
        chart
            .draw_series(LineSeries::new(
                vec![(0.0, 0.0), (n as f64, 0.0)],
                BLACK.stroke_width(1),
            ))
            .map_err(perr(P))?;
        let (cb, ca) = (colour(1), colour(0));
        let bar = |x0: f64, x1: f64, v: f64, c: RGBColor, located: bool| {
            let outline = if located { BLACK } else { c };
            [
                Rectangle::new([(x0, 0.0), (x1, v)], c.filled()),
                Rectangle::new([(x0, 0.0), (x1, v)], outline.stroke_width(1)),
            ]
        };
        let (mut need_b, mut need_a) = (true, true);
        for (k, it) in items.iter().enumerate() {
            let x = k as f64 + 0.5;
            if it.before_pct.is_finite() {
                let s = chart
                    .draw_series(bar(x - 0.32, x, it.before_pct, cb, it.located))
                    .map_err(perr(P))?;
                if need_b {
                    need_b = false;
                    s.label("baseline").legend(move |(x, y)| {
                        Rectangle::new([(x, y - 5), (x + 14, y + 5)], cb.filled())
                    });
                }
            }
            if let Some(a) = it.after_pct.filter(|a| a.is_finite()) {
                let s = chart
                    .draw_series(bar(x, x + 0.32, a, ca, it.located))
                    .map_err(perr(P))?;
                if need_a {
                    need_a = false;
                    s.label(format!("after: {}", after_name.unwrap_or("refit")))
                        .legend(move |(x, y)| {
                            Rectangle::new([(x, y - 5), (x + 14, y + 5)], ca.filled())
                        });
                }
            }
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK.mix(0.3))
            .label_font(("sans-serif", 12))
            .position(SeriesLabelPosition::UpperRight)
            .draw()
            .map_err(perr(P))?;
        root.present().map_err(perr(P))?;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn figures_are_svg_with_their_elements() {
        let it = BoxItem {
            label: "torsion-1".into(),
            q05: 99.0,
            q25: 99.5,
            q50: 100.0,
            q75: 100.5,
            q95: 101.0,
            measured: vec![100.2, 99.9],
            used_for_updating: true,
        };
        let v = BoxItem {
            label: "bending-x-2".into(),
            used_for_updating: false,
            measured: vec![100.7],
            ..it.clone()
        };
        let s = boxes_svg("PCB-01 free-free", &[it, v]).unwrap();
        assert!(s.starts_with("<svg") && s.trim_end().ends_with("</svg>"));
        assert!(s.contains("torsion-1") && s.contains("bending-x-2"));
        // Two filled measurement circles (updating mode), one triangle (validation mode).
        assert_eq!(s.matches("<circle").count(), 2, "{s}");
        let d = density_svg(
            "e_x",
            "E_x [GPa]",
            &[("PCB-01".into(), vec![24e9, 25e9, 25.5e9])],
            1e9,
        )
        .unwrap();
        assert!(d.contains("E_x [GPa]") && d.contains("<polyline"));
        let names = vec!["a".to_string(), "b".to_string()];
        let c = correlation_svg("Ω", &names, &[1.0, -0.5, -0.5, 1.0]).unwrap();
        assert!(c.contains("-0.50") && c.contains("+1.00"));
        assert!(correlation_svg("bad", &names, &[1.0]).is_err());
        let t = tempering_svg("path", &[vec![(1.0, 1e-4), (2.0, 1e-2), (3.0, 1.0)]]).unwrap();
        assert_eq!(t.matches("<circle").count(), 3);
    }
}

/// One mode of the model-form discrepancy figure: the posterior median and 90 % interval of
/// its relative frequency discrepancy, in percent.
#[derive(Clone, Debug)]
pub struct DiscrepancyBar {
    pub label: String,
    pub q05_pct: f64,
    pub q50_pct: f64,
    pub q95_pct: f64,
}

/// Per mode, the model-form discrepancy as a bar from zero to its posterior median with the
/// 90 % interval as a whisker, in percent of the frequency.
pub fn discrepancy_svg(title: &str, items: &[DiscrepancyBar]) -> Result<String, PlotError> {
    const P: &str = "discrepancy";
    let mut lo = 0.0f64;
    let mut hi = 0.0f64;
    for it in items {
        for v in [it.q05_pct, it.q50_pct, it.q95_pct] {
            if v.is_finite() {
                lo = lo.min(v);
                hi = hi.max(v);
            }
        }
    }
    if hi - lo <= 0.0 {
        (lo, hi) = (-0.1, 0.1);
    }
    let pad = 0.1 * (hi - lo);
    let (lo, hi) = (lo - pad, hi + pad);
    let n = items.len().max(1);
    let mut out = String::new();
    {
        let w = (160 + 80 * n as u32).max(480);
        let root = SVGBackend::with_string(&mut out, (w, 360)).into_drawing_area();
        root.fill(&WHITE).map_err(perr(P))?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 17))
            .margin(12)
            .x_label_area_size(70)
            .y_label_area_size(70)
            .build_cartesian_2d(0.0..n as f64, lo..hi)
            .map_err(perr(P))?;
        let labels: Vec<String> = items.iter().map(|i| i.label.clone()).collect();
        chart
            .configure_mesh()
            .disable_x_mesh()
            .x_labels(n * 2 + 1)
            .x_label_formatter(&|x| pick(&labels, *x, false))
            .label_style(("sans-serif", 13))
            .y_desc("discrepancy [% of frequency]")
            .x_desc("mode")
            .axis_desc_style(("sans-serif", 14))
            .draw()
            .map_err(perr(P))?;
        chart
            .draw_series(LineSeries::new(
                vec![(0.0, 0.0), (n as f64, 0.0)],
                BLACK.stroke_width(1),
            ))
            .map_err(perr(P))?;
        for (k, it) in items.iter().enumerate() {
            let x = k as f64 + 0.5;
            chart
                .draw_series(std::iter::once(Rectangle::new(
                    [(x - 0.25, 0.0), (x + 0.25, it.q50_pct)],
                    colour(0).mix(0.6).filled(),
                )))
                .map_err(perr(P))?;
            for seg in [
                vec![(x, it.q05_pct), (x, it.q95_pct)],
                vec![(x - 0.1, it.q05_pct), (x + 0.1, it.q05_pct)],
                vec![(x - 0.1, it.q95_pct), (x + 0.1, it.q95_pct)],
            ] {
                chart
                    .draw_series(LineSeries::new(seg, BLACK.stroke_width(2)))
                    .map_err(perr(P))?;
            }
        }
        root.present().map_err(perr(P))?;
    }
    Ok(out)
}

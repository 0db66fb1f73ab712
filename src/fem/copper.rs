//! Copper as it is drawn, integrated exactly inside each element: the coverage of a
//! layer at a point is `clamp(max of the coverage regions holding it − max of the
//! cut-outs holding it, 0, 1)`, a piecewise-constant field. For an element, the
//! rectangle is partitioned into convex pieces on which every layer's coverage is
//! constant (the regions, rectangles or ear-clipped polygons, split the pieces
//! one convex part at a time, and only where they raise a piece's maximum), so the
//! element's stiffness and mass can be integrated piece by piece with the exact
//! polygon quadrature of [`super::geometry`]: a copper edge crossing an element
//! counts exactly where it lies instead of being smeared over the element.

use std::sync::Arc;

use super::board::{Board, GerberLayerImage, Grid, Region};
use super::geometry::{rect_polygon, signed_area, split_convex, triangulate, Rect};

/// A convex counter-clockwise polygon, vertices m.
pub type Convex = Vec<[f64; 2]>;

/// One region of one layer, prepared for splitting.
#[derive(Clone, Debug)]
struct Part {
    layer: usize,
    cutout: bool,
    fraction: f64,
    /// Bounding box.
    bbox: Rect,
    /// Convex parts (the rectangle, or the polygon's triangles).
    convex: Vec<Convex>,
}

/// A raster density map of one layer.
#[derive(Clone, Debug)]
struct Raster {
    layer: usize,
    extent: Rect,
    grid: Grid,
}

/// The copper layers of a board, prepared for per-element integration.
#[derive(Clone, Debug)]
pub struct CopperMap {
    n_layers: usize,
    parts: Vec<Part>,
    rasters: Vec<Raster>,
    /// Gerber layer images, rasterized on a sub-grid of each element (so the grid's
    /// cells never straddle an element edge).
    gerbers: Vec<(usize, Arc<GerberLayerImage>)>,
}

/// A piece of an element with constant copper: its polygon and each layer's coverage.
#[derive(Clone, Debug, PartialEq)]
pub struct Piece {
    /// Convex counter-clockwise polygon, m.
    pub polygon: Convex,
    /// Coverage fraction of each copper layer on the piece, in [0, 1].
    pub coverage: Vec<f64>,
}

fn bbox_of(pts: &[[f64; 2]]) -> Rect {
    let mut r = Rect {
        x0: f64::INFINITY,
        y0: f64::INFINITY,
        x1: f64::NEG_INFINITY,
        y1: f64::NEG_INFINITY,
    };
    for p in pts {
        r.x0 = r.x0.min(p[0]);
        r.y0 = r.y0.min(p[1]);
        r.x1 = r.x1.max(p[0]);
        r.y1 = r.y1.max(p[1]);
    }
    r
}

/// Whether the bounding boxes of two polygons overlap with positive area.
fn overlaps_pair(a: &[[f64; 2]], b: &[[f64; 2]]) -> bool {
    let (p, q) = (bbox_of(a), bbox_of(b));
    !(p.x1 <= q.x0 || p.x0 >= q.x1 || p.y1 <= q.y0 || p.y0 >= q.y1)
}

/// Convex parts of a region: the rectangle itself, or the triangles of the polygon.
pub fn convex_parts(r: &Region) -> Vec<Convex> {
    match r {
        Region::Rect {
            x0_m,
            y0_m,
            x1_m,
            y1_m,
            ..
        } => vec![rect_polygon(&Rect {
            x0: *x0_m,
            y0: *y0_m,
            x1: *x1_m,
            y1: *y1_m,
        })],
        Region::Polygon { vertices_m, .. } => triangulate(vertices_m)
            .into_iter()
            .map(|t| t.to_vec())
            .collect(),
    }
}

impl CopperMap {
    /// Prepare the copper of `board` (triangulate polygons once).
    pub fn new(board: &Board) -> CopperMap {
        let mut parts = Vec::new();
        for (layer, l) in board.copper.iter().enumerate() {
            for (cutout, regions) in [(false, &l.coverage), (true, &l.cutouts)] {
                for r in regions {
                    let fraction = r.fraction();
                    if fraction <= 0.0 {
                        continue;
                    }
                    let convex = convex_parts(r);
                    let all: Vec<[f64; 2]> = convex.iter().flatten().copied().collect();
                    if all.is_empty() {
                        continue;
                    }
                    parts.push(Part {
                        layer,
                        cutout,
                        fraction,
                        bbox: bbox_of(&all),
                        convex,
                    });
                }
            }
        }
        let rasters = board
            .copper
            .iter()
            .enumerate()
            .flat_map(|(layer, l)| {
                let maps = l.density_maps.iter().filter_map(move |d| {
                    d.grid.as_ref().map(|g| Raster {
                        layer,
                        extent: Rect {
                            x0: d.x0_m,
                            y0: d.y0_m,
                            x1: d.x1_m,
                            y1: d.y1_m,
                        },
                        grid: g.clone(),
                    })
                });
                maps
            })
            .collect();
        let gerbers = board
            .copper
            .iter()
            .enumerate()
            .filter_map(|(layer, l)| l.gerber_image.clone().map(|g| (layer, g)))
            .collect();
        CopperMap {
            n_layers: board.copper.len(),
            parts,
            rasters,
            gerbers,
        }
    }

    /// Partition `rect` into convex pieces of constant coverage in every layer.
    /// Returns one piece (the whole rectangle) when the coverage is uniform over it.
    /// Pieces below 1e-12 of the rectangle's area are dropped (their share of any
    /// integral is below rounding of the element's).
    pub fn pieces(&self, rect: &Rect) -> Vec<Piece> {
        let min_area = 1e-12 * rect.area();
        // Per piece, per layer: (max coverage, max cut-out).
        let mut pieces: Vec<(Convex, Vec<(f64, f64)>)> =
            vec![(rect_polygon(rect), vec![(0.0, 0.0); self.n_layers])];
        let overlaps =
            |t: &Rect| !(t.x1 <= rect.x0 || t.x0 >= rect.x1 || t.y1 <= rect.y0 || t.y0 >= rect.y1);
        // Raise the coverage (or cut-out) of `layer` to `fraction` on `t` (convex).
        let apply = |pieces: Vec<(Convex, Vec<(f64, f64)>)>,
                     layer: usize,
                     cutout: bool,
                     fraction: f64,
                     t: &[[f64; 2]]| {
            let mut next = Vec::with_capacity(pieces.len() + 4);
            for (poly, st) in pieces {
                let cur = if cutout { st[layer].1 } else { st[layer].0 };
                if cur >= fraction || !overlaps(&bbox_of(&poly)) || !overlaps_pair(&poly, t) {
                    next.push((poly, st));
                    continue;
                }
                match split_convex(&poly, t, min_area) {
                    (None, _) => next.push((poly, st)),
                    (Some(inside), outside) => {
                        for o in outside {
                            next.push((o, st.clone()));
                        }
                        let mut s2 = st;
                        if cutout {
                            s2[layer].1 = fraction;
                        } else {
                            s2[layer].0 = fraction;
                        }
                        next.push((inside, s2));
                    }
                }
            }
            next
        };
        for part in &self.parts {
            if !overlaps(&part.bbox) {
                continue;
            }
            for t in &part.convex {
                if overlaps(&bbox_of(t)) {
                    pieces = apply(pieces, part.layer, part.cutout, part.fraction, t);
                }
            }
        }
        // Raise each layer to the cells of a raster over `e`.
        let apply_grid =
            |mut pieces: Vec<(Convex, Vec<(f64, f64)>)>, layer: usize, e: &Rect, grid: &Grid| {
                if !overlaps(e) {
                    return pieces;
                }
                let (dx, dy) = (
                    (e.x1 - e.x0) / grid.nx as f64,
                    (e.y1 - e.y0) / grid.ny as f64,
                );
                let range = |lo: f64, hi: f64, o: f64, d: f64, n: usize| {
                    let i0 = (((lo - o) / d).floor().max(0.0) as usize).min(n);
                    let i1 = (((hi - o) / d).ceil().max(0.0) as usize).min(n);
                    i0..i1
                };
                // Cells of equal value are merged into rectangles first (runs along x, then
                // equal runs in consecutive rows): the same field, far fewer pieces.
                let cell_rect = |i0: usize, i1: usize, j0: usize, j1: usize| Rect {
                    x0: e.x0 + i0 as f64 * dx,
                    y0: e.y0 + j0 as f64 * dy,
                    x1: e.x0 + i1 as f64 * dx,
                    y1: e.y0 + j1 as f64 * dy,
                };
                let xr = range(rect.x0, rect.x1, e.x0, dx, grid.nx);
                let yr = range(rect.y0, rect.y1, e.y0, dy, grid.ny);
                // Open runs: (i0, i1, value, first row).
                let mut open: Vec<(usize, usize, f64, usize)> = Vec::new();
                let mut done: Vec<(Rect, f64)> = Vec::new();
                for j in yr.clone() {
                    let mut next = Vec::new();
                    let mut i = xr.start;
                    while i < xr.end {
                        let v = grid.values[j * grid.nx + i];
                        let mut k = i + 1;
                        while k < xr.end && grid.values[j * grid.nx + k] == v {
                            k += 1;
                        }
                        if v > 0.0 {
                            match open.iter().position(|o| o.0 == i && o.1 == k && o.2 == v) {
                                Some(p) => next.push(open.swap_remove(p)),
                                None => next.push((i, k, v, j)),
                            }
                        }
                        i = k;
                    }
                    for o in open.drain(..) {
                        done.push((cell_rect(o.0, o.1, o.3, j), o.2));
                    }
                    open = next;
                }
                for o in open {
                    done.push((cell_rect(o.0, o.1, o.3, yr.end), o.2));
                }
                for (cell, v) in done {
                    if overlaps(&cell) {
                        pieces = apply(pieces, layer, false, v, &rect_polygon(&cell));
                    }
                }
                pieces
            };
        for r in &self.rasters {
            pieces = apply_grid(pieces, r.layer, &r.extent, &r.grid);
        }
        for (layer, g) in &self.gerbers {
            let res = g.resolution_m;
            let kx = (((rect.x1 - rect.x0) / res).ceil() as usize).max(1);
            let ky = (((rect.y1 - rect.y0) / res).ceil() as usize).max(1);
            let grid = super::gerber::rasterize(&g.image, rect, kx, ky);
            pieces = apply_grid(pieces, *layer, rect, &grid);
        }
        let out: Vec<Piece> = pieces
            .into_iter()
            .map(|(polygon, st)| Piece {
                polygon,
                coverage: st.iter().map(|(c, k)| (c - k).clamp(0.0, 1.0)).collect(),
            })
            .collect();
        if out.iter().all(|p| p.coverage == out[0].coverage) {
            return vec![Piece {
                polygon: rect_polygon(rect),
                coverage: out[0].coverage.clone(),
            }];
        }
        out
    }

    /// Exact area-weighted mean coverage of layer `layer` over `rect`.
    pub fn mean_coverage(&self, layer: usize, rect: &Rect) -> f64 {
        self.pieces(rect)
            .iter()
            .map(|p| p.coverage[layer] * signed_area(&p.polygon))
            .sum::<f64>()
            / rect.area()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fem::geometry::polygon_quadrature;

    #[test]
    fn pieces_partition_the_element_with_max_and_cutout_rules() {
        let mut b = crate::fem::tests::helpers::thin_board();
        b.copper.truncate(1);
        let rect = |x0, y0, x1, y1, fraction| Region::Rect {
            x0_m: x0,
            y0_m: y0,
            x1_m: x1,
            y1_m: y1,
            fraction,
        };
        // A 40 % pour over the cell, a solid diagonal trace (triangle), and a cut-out
        // removing 50 % over the top quarter.
        b.copper[0].coverage = vec![
            rect(-1.0, -1.0, 1.0, 1.0, 0.4),
            Region::Polygon {
                vertices_m: vec![[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]],
                fraction: 1.0,
            },
        ];
        b.copper[0].cutouts = vec![rect(-1.0, 0.75, 2.0, 2.0, 0.5)];
        let map = CopperMap::new(&b);
        let cell = Rect {
            x0: 0.0,
            y0: 0.0,
            x1: 1.0,
            y1: 1.0,
        };
        let pieces = map.pieces(&cell);
        let area: f64 = pieces.iter().map(|p| signed_area(&p.polygon)).sum();
        assert!((area - 1.0).abs() < 1e-14, "{area}");
        // ∬ c(x, y) y dA row by row: c = 1 under x + y ≤ 1 and 0.4 above it; for
        // y ≥ 0.75 the cut-out removes 0.5 (1 → 0.5, 0.4 → 0 by the cap).
        let iy = |y0: f64, y1: f64, f: &dyn Fn(f64) -> f64| {
            // Simpson is exact for cubics; the integrands are.
            let n = 64;
            let h = (y1 - y0) / n as f64;
            (0..=n)
                .map(|i| {
                    let w = if i == 0 || i == n {
                        1.0
                    } else if i % 2 == 1 {
                        4.0
                    } else {
                        2.0
                    };
                    w * f(y0 + i as f64 * h)
                })
                .sum::<f64>()
                * h
                / 3.0
        };
        // Row y: covered width in the triangle 1 − y (value 1, or 0.5 under the cut);
        // the rest y (value 0.4, or 0 under the cut since 0.4 − 0.5 < 0).
        let exact = iy(0.0, 0.75, &|y| y * ((1.0 - y) + 0.4 * y))
            + iy(0.75, 1.0, &|y| y * (0.5 * (1.0 - y)));
        let got: f64 = pieces
            .iter()
            .map(|p| {
                polygon_quadrature(&p.polygon)
                    .iter()
                    .map(|q| q.2 * q.1 * p.coverage[0])
                    .sum::<f64>()
            })
            .sum();
        assert!((got - exact).abs() < 1e-12, "{got} vs {exact}");
        // A cell inside the pour only: one piece, coverage 0.4.
        let far = Rect {
            x0: 0.8,
            y0: 0.3,
            x1: 0.9,
            y1: 0.4,
        };
        let p = map.pieces(&far);
        assert_eq!(p.len(), 1);
        assert!((p[0].coverage[0] - 0.4).abs() < 1e-15);
    }

    #[test]
    fn gerber_image_is_integrated_on_each_elements_own_sub_grid() {
        use crate::fem::gerber::{render, ApertureShape, Cmd, SrcPos, Stmt};
        let st = |cmd| Stmt {
            pos: SrcPos {
                line: 1,
                command: String::new(),
            },
            cmd,
        };
        // A 3 mm disc flashed at (10.3, 7.1) mm with a 1 mm hole, over six 2.3 × 2.7 mm
        // elements (a board-wide 0.1 mm grid's cells would straddle their edges).
        let image = render(&[
            st(Cmd::ApertureDef {
                code: 10,
                shape: ApertureShape::Circle {
                    d_m: 3e-3,
                    hole_m: Some(1e-3),
                },
            }),
            st(Cmd::Select(10)),
            st(Cmd::Op {
                d: 3,
                x: Some(10.3e-3),
                y: Some(7.1e-3),
                i: None,
                j: None,
            }),
        ])
        .unwrap();
        let mut b = crate::fem::tests::helpers::thin_board();
        b.copper.truncate(1);
        b.copper[0].coverage.clear();
        b.copper[0].gerber = Some("top.gbr".into());
        b.copper[0].gerber_image = Some(Arc::new(GerberLayerImage {
            image,
            resolution_m: 1e-4,
        }));
        let map = CopperMap::new(&b);
        let (ex, ey) = (2.3e-3, 2.7e-3);
        let mut total = 0.0;
        for (i, j) in (3..=5).flat_map(|i| (2..=3).map(move |j| (i, j))) {
            let r = Rect {
                x0: i as f64 * ex,
                y0: j as f64 * ey,
                x1: (i + 1) as f64 * ex,
                y1: (j + 1) as f64 * ey,
            };
            total += map.mean_coverage(0, &r) * r.area();
        }
        let exact = std::f64::consts::PI * (1.5e-3f64.powi(2) - 0.5e-3f64.powi(2));
        // The residue is the sub-row midpoint rule at the circles' tops and bottoms,
        // where the chord length varies like a square root (1.5e-4 here).
        assert!((total / exact - 1.0).abs() < 3e-4, "{total:e} vs {exact:e}");
    }
}

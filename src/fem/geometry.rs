//! Cut-cell geometry: quadrature over the part of an element rectangle that lies in a
//! disc (holes, clamp annuli), and exact clipped areas of polygons (copper regions).
//!
//! Disc ∩ rectangle is integrated in polar coordinates about the disc centre c: a ray
//! c + ρ(cos θ, sin θ) meets the (convex) rectangle in one interval [ρ_in(θ), ρ_out(θ)]
//! (clipped to [0, R]), and between the breakpoints (the angles of the rectangle's
//! corners and of the circle's crossings with its edges) both ends are smooth in θ
//! (0, R, or the distance to one edge line). Each piece gets a Gauss rule in θ and, per
//! θ, a Gauss rule in ρ. Along a ray, x and y are linear in ρ, so a polynomial
//! integrand of total degree d (≤ 12 for the BFS mass matrix) times the Jacobian ρ is
//! integrated exactly in ρ by `N_RHO` = 8 points; in θ the integrand is smooth
//! (rational-trigonometric) and the rule is accurate to ~1e-12 relative (tested
//! against closed-form areas and moments). No crate offers this for a polynomial
//! integrand on a cut rectangle, hence by hand.

/// Gauss points per θ piece.
const N_THETA: usize = 16;
/// Gauss points per ray (exact for degree ≤ 15 in ρ).
const N_RHO: usize = 8;

/// An axis-aligned rectangle `[x0, x1] × [y0, y1]`, m.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Rect {
    /// Lower x, m.
    pub x0: f64,
    /// Lower y, m.
    pub y0: f64,
    /// Upper x, m.
    pub x1: f64,
    /// Upper y, m.
    pub y1: f64,
}

impl Rect {
    /// Area, m².
    pub fn area(&self) -> f64 {
        (self.x1 - self.x0) * (self.y1 - self.y0)
    }
}

/// A polygon, vertices `[x_m, y_m]`.
pub type Polygon = Vec<[f64; 2]>;

/// A quadrature point `(x_m, y_m, weight_m2)`.
pub type QPoint = (f64, f64, f64);

/// Gauss–Legendre nodes and weights on [0, 1] (Golub–Welsch would be overkill for
/// two fixed orders: the nodes come from Newton on the Legendre recurrence).
fn gauss_legendre(n: usize) -> (Vec<f64>, Vec<f64>) {
    let mut x = vec![0.0; n];
    let mut w = vec![0.0; n];
    for i in 0..n {
        let mut z = (std::f64::consts::PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
        for _ in 0..100 {
            let (mut p0, mut p1) = (1.0, z);
            for k in 2..=n {
                let p2 = ((2 * k - 1) as f64 * z * p1 - (k - 1) as f64 * p0) / k as f64;
                p0 = p1;
                p1 = p2;
            }
            let (pn, pn1) = if n == 1 { (z, 1.0) } else { (p1, p0) };
            let dp = n as f64 * (z * pn - pn1) / (z * z - 1.0);
            let dz = pn / dp;
            z -= dz;
            if dz.abs() < 1e-16 {
                break;
            }
        }
        let (mut p0, mut p1) = (1.0, z);
        for k in 2..=n {
            let p2 = ((2 * k - 1) as f64 * z * p1 - (k - 1) as f64 * p0) / k as f64;
            p0 = p1;
            p1 = p2;
        }
        let dp = n as f64 * (z * p1 - p0) / (z * z - 1.0);
        x[i] = 0.5 * (1.0 - z);
        w[i] = 1.0 / ((1.0 - z * z) * dp * dp);
    }
    (x, w)
}

/// Interval of ρ ≥ 0 for which c + ρ d lies in the convex counter-clockwise polygon
/// `poly` (intersection of its edges' half-planes), if any.
fn ray_interval(cx: f64, cy: f64, dx: f64, dy: f64, poly: &[[f64; 2]]) -> Option<(f64, f64)> {
    let (mut lo, mut hi) = (0.0f64, f64::INFINITY);
    let n = poly.len();
    for i in 0..n {
        let (p, q) = (poly[i], poly[(i + 1) % n]);
        // Inside: cross(q − p, x − p) ≥ 0, i.e. nx·x ≤ nx·p with the outward normal
        // n = (ey, −ex) of edge e = q − p.
        let (nx, ny) = (q[1] - p[1], p[0] - q[0]);
        let rhs = nx * (p[0] - cx) + ny * (p[1] - cy);
        let nd = nx * dx + ny * dy;
        if nd.abs() < 1e-300 {
            if rhs < 0.0 {
                return None;
            }
        } else if nd > 0.0 {
            hi = hi.min(rhs / nd);
        } else {
            lo = lo.max(rhs / nd);
        }
    }
    (hi > lo).then_some((lo, hi))
}

/// The rectangle as a counter-clockwise polygon.
pub fn rect_polygon(r: &Rect) -> Vec<[f64; 2]> {
    vec![[r.x0, r.y0], [r.x1, r.y0], [r.x1, r.y1], [r.x0, r.y1]]
}

/// Quadrature points covering `rect` ∩ {ρ_in ≤ |p − c| ≤ ρ_out} (an annulus, or a disc
/// when `r_in` = 0). Empty when they do not meet.
pub fn annulus_rect_quadrature(
    cx: f64,
    cy: f64,
    r_in: f64,
    r_out: f64,
    rect: &Rect,
) -> Vec<QPoint> {
    annulus_convex_quadrature(cx, cy, r_in, r_out, &rect_polygon(rect))
}

/// Quadrature points covering the convex counter-clockwise polygon `poly` ∩
/// {ρ_in ≤ |p − c| ≤ ρ_out}. Empty when they do not meet.
pub fn annulus_convex_quadrature(
    cx: f64,
    cy: f64,
    r_in: f64,
    r_out: f64,
    poly: &[[f64; 2]],
) -> Vec<QPoint> {
    let mut out = Vec::new();
    let n = poly.len();
    if n < 3 {
        return out;
    }
    // Quick rejection: nearest point of the polygon farther than r_out (centre
    // outside and every edge farther), or the farthest vertex inside r_in.
    let inside_c = ray_interval(cx, cy, 1.0, 0.0, poly).is_some_and(|(lo, _)| lo <= 0.0);
    let edge_dist = |p: [f64; 2], q: [f64; 2]| {
        let (ex, ey) = (q[0] - p[0], q[1] - p[1]);
        let l2 = ex * ex + ey * ey;
        let u = if l2 > 0.0 {
            (((cx - p[0]) * ex + (cy - p[1]) * ey) / l2).clamp(0.0, 1.0)
        } else {
            0.0
        };
        (p[0] + u * ex - cx).hypot(p[1] + u * ey - cy)
    };
    let near = (0..n)
        .map(|i| edge_dist(poly[i], poly[(i + 1) % n]))
        .fold(f64::INFINITY, f64::min);
    if !inside_c && near >= r_out {
        return out;
    }
    let far = poly
        .iter()
        .map(|p| (p[0] - cx).hypot(p[1] - cy))
        .fold(0.0, f64::max);
    if far <= r_in {
        return out;
    }
    // Breakpoints: vertex angles and circle/edge crossings of both radii.
    let mut brk: Vec<f64> = vec![-std::f64::consts::PI, std::f64::consts::PI];
    for p in poly {
        if (p[0] - cx).hypot(p[1] - cy) > 0.0 {
            brk.push((p[1] - cy).atan2(p[0] - cx));
        }
    }
    for rad in [r_in, r_out] {
        if rad <= 0.0 {
            continue;
        }
        for i in 0..n {
            let (p, q) = (poly[i], poly[(i + 1) % n]);
            let (ex, ey) = (q[0] - p[0], q[1] - p[1]);
            let (fx, fy) = (p[0] - cx, p[1] - cy);
            // |f + u e|² = R²: a u² + 2 b u + c = 0.
            let (qa, qb, qc) = (
                ex * ex + ey * ey,
                fx * ex + fy * ey,
                fx * fx + fy * fy - rad * rad,
            );
            let disc = qb * qb - qa * qc;
            if qa <= 0.0 || disc < 0.0 {
                continue;
            }
            for s in [-1.0, 1.0] {
                let u = (-qb + s * disc.sqrt()) / qa;
                if (0.0..=1.0).contains(&u) {
                    brk.push((fy + u * ey).atan2(fx + u * ex));
                }
            }
        }
    }
    brk.sort_by(f64::total_cmp);
    brk.dedup_by(|a, b| (*a - *b).abs() < 1e-14);
    // Pieces wider than π/8 are split: the edge-distance integrands (∝ 1/cos² θ)
    // vary strongly over wide pieces, and 16 points then lose a few digits.
    let mut fine = Vec::with_capacity(2 * brk.len());
    for seg in brk.windows(2) {
        let k = ((seg[1] - seg[0]) / (std::f64::consts::PI / 8.0))
            .ceil()
            .max(1.0) as usize;
        for i in 0..k {
            fine.push(seg[0] + (seg[1] - seg[0]) * i as f64 / k as f64);
        }
    }
    fine.push(std::f64::consts::PI);
    let brk = fine;
    let (gt, wt) = gauss_legendre(N_THETA);
    let (gr, wr) = gauss_legendre(N_RHO);
    for seg in brk.windows(2) {
        let (ta, tb) = (seg[0], seg[1]);
        if tb - ta < 1e-15 {
            continue;
        }
        // Skip pieces the polygon does not cover (test the mid-angle).
        let tm = 0.5 * (ta + tb);
        if ray_interval(cx, cy, tm.cos(), tm.sin(), poly)
            .map(|(lo, hi)| lo.max(r_in) >= hi.min(r_out))
            .unwrap_or(true)
        {
            continue;
        }
        for (t, wtt) in gt.iter().zip(&wt) {
            let th = ta + (tb - ta) * t;
            let (dx, dy) = (th.cos(), th.sin());
            let Some((lo, hi)) = ray_interval(cx, cy, dx, dy, poly) else {
                continue;
            };
            let (lo, hi) = (lo.max(r_in), hi.min(r_out));
            if hi <= lo {
                continue;
            }
            for (s, wrr) in gr.iter().zip(&wr) {
                let rho = lo + (hi - lo) * s;
                let w = wtt * (tb - ta) * wrr * (hi - lo) * rho;
                out.push((cx + rho * dx, cy + rho * dy, w));
            }
        }
    }
    out
}

/// Gauss points per edge of the Green quadrature below.
const N_EDGE: usize = 7;
/// Gauss points along x from the reference line of the Green quadrature.
const N_X: usize = 4;

/// Quadrature points covering a simple polygon (vertices m, counter-clockwise), exact
/// for polynomials of degree ≤ 7 in x and ≤ 6 in y jointly with total degree along
/// an edge ≤ 13 (the BFS mass integrand has degree 6 in each of x and y): by Green's
/// theorem ∬ f dA = ∮ F dy with F(x, y) = ∫_{x_ref}^x f(s, y) ds, x_ref the polygon's
/// least x; each edge gets `N_EDGE` Gauss points and each F a `N_X`-point rule in s.
/// All points lie in the polygon's bounding box; weights may be negative (a
/// non-convex polygon, or the far side of a convex one), their sum is the area.
/// Sommariva & Vianello, "Product Gauss cubature over polygons based on Green's
/// integration formula", BIT 47 (2007).
pub fn polygon_quadrature(poly: &[[f64; 2]]) -> Vec<QPoint> {
    let n = poly.len();
    let mut out = Vec::with_capacity(n * N_EDGE * N_X);
    if n < 3 {
        return out;
    }
    // An axis-aligned rectangle (raster cells, most pieces): the tensor rule, exact
    // to degree 2 N_X − 1 = 7 in each of x and y, with a third of the points.
    if n == 4 {
        let xs = [poly[0][0], poly[1][0], poly[2][0], poly[3][0]];
        let ys = [poly[0][1], poly[1][1], poly[2][1], poly[3][1]];
        let axis = (xs[0] == xs[3] && xs[1] == xs[2] && ys[0] == ys[1] && ys[2] == ys[3])
            || (xs[0] == xs[1] && xs[2] == xs[3] && ys[1] == ys[2] && ys[0] == ys[3]);
        if axis {
            let (x0, x1) = (
                xs.iter().copied().fold(f64::INFINITY, f64::min),
                xs.iter().copied().fold(f64::NEG_INFINITY, f64::max),
            );
            let (y0, y1) = (
                ys.iter().copied().fold(f64::INFINITY, f64::min),
                ys.iter().copied().fold(f64::NEG_INFINITY, f64::max),
            );
            let (g, w) = gauss_legendre(N_X);
            for (sy, wy) in g.iter().zip(&w) {
                for (sx, wx) in g.iter().zip(&w) {
                    out.push((
                        x0 + sx * (x1 - x0),
                        y0 + sy * (y1 - y0),
                        wx * wy * (x1 - x0) * (y1 - y0),
                    ));
                }
            }
            return out;
        }
    }
    let x_ref = poly.iter().map(|p| p[0]).fold(f64::INFINITY, f64::min);
    let (gt, wt) = gauss_legendre(N_EDGE);
    let (gs, ws) = gauss_legendre(N_X);
    for i in 0..n {
        let (p, q) = (poly[i], poly[(i + 1) % n]);
        let dy = q[1] - p[1];
        if dy == 0.0 {
            continue;
        }
        for (t, wtt) in gt.iter().zip(&wt) {
            let x = p[0] + t * (q[0] - p[0]);
            let y = p[1] + t * dy;
            let len = x - x_ref;
            if len == 0.0 {
                continue;
            }
            for (s, wss) in gs.iter().zip(&ws) {
                out.push((x_ref + s * len, y, wtt * dy * wss * len));
            }
        }
    }
    out
}

/// Signed area of a polygon (positive when counter-clockwise), m².
pub fn signed_area(poly: &[[f64; 2]]) -> f64 {
    let n = poly.len();
    0.5 * (0..n)
        .map(|i| {
            let (a, b) = (poly[i], poly[(i + 1) % n]);
            a[0] * b[1] - b[0] * a[1]
        })
        .sum::<f64>()
}

/// Split the convex polygon `p` by the line through `a`, `b`: returns the parts on
/// the left (cross(b − a, x − a) ≥ 0) and on the right, either possibly empty.
fn split_by_line(p: &[[f64; 2]], a: [f64; 2], b: [f64; 2]) -> (Vec<[f64; 2]>, Vec<[f64; 2]>) {
    let side = |x: [f64; 2]| (b[0] - a[0]) * (x[1] - a[1]) - (b[1] - a[1]) * (x[0] - a[0]);
    let (mut left, mut right) = (Vec::new(), Vec::new());
    let n = p.len();
    for i in 0..n {
        let (u, v) = (p[i], p[(i + 1) % n]);
        let (su, sv) = (side(u), side(v));
        if su >= 0.0 {
            left.push(u);
        }
        if su <= 0.0 {
            right.push(u);
        }
        if (su > 0.0 && sv < 0.0) || (su < 0.0 && sv > 0.0) {
            let t = su / (su - sv);
            let x = [u[0] + t * (v[0] - u[0]), u[1] + t * (v[1] - u[1])];
            left.push(x);
            right.push(x);
        }
    }
    (left, right)
}

/// Split the convex counter-clockwise polygon `p` by the convex counter-clockwise
/// polygon `t`: returns `p ∩ t` (if of area above `min_area`) and convex pieces
/// covering `p \ t` (each of area above `min_area`; slivers below it are dropped).
pub fn split_convex(
    p: &[[f64; 2]],
    t: &[[f64; 2]],
    min_area: f64,
) -> (Option<Polygon>, Vec<Polygon>) {
    let mut outside = Vec::new();
    let mut rest = p.to_vec();
    let n = t.len();
    for i in 0..n {
        let (left, right) = split_by_line(&rest, t[i], t[(i + 1) % n]);
        if right.len() >= 3 && signed_area(&right) > min_area {
            outside.push(right);
        }
        rest = left;
        if rest.len() < 3 || signed_area(&rest) <= min_area {
            return (None, vec![p.to_vec()]);
        }
    }
    (Some(rest), outside)
}

/// Triangles (counter-clockwise) covering a simple polygon (either orientation), by
/// ear clipping. Board polygons have a few to a few hundred vertices, for which the
/// O(n²) clipping is instantaneous; written by hand because it is 40 lines and the
/// triangulation crates bring hole and float-type generality the board does not need.
/// Collinear and repeated vertices are removed first.
pub fn triangulate(poly: &[[f64; 2]]) -> Vec<[[f64; 2]; 3]> {
    let mut v: Vec<[f64; 2]> = poly.to_vec();
    if signed_area(&v) < 0.0 {
        v.reverse();
    }
    let cross = |a: [f64; 2], b: [f64; 2], c: [f64; 2]| {
        (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
    };
    let scale = v
        .iter()
        .flat_map(|p| p.iter())
        .fold(0.0f64, |m, x| m.max(x.abs()))
        .max(1e-300);
    let eps = 1e-14 * scale * scale;
    let mut tris = Vec::new();
    let mut guard = 0;
    while v.len() >= 3 && guard < 10_000 {
        guard += 1;
        let n = v.len();
        // Drop degenerate (collinear / repeated) vertices.
        if let Some(i) =
            (0..n).find(|&i| cross(v[(i + n - 1) % n], v[i], v[(i + 1) % n]).abs() <= eps)
        {
            v.remove(i);
            continue;
        }
        let ear = (0..n).find(|&i| {
            let (a, b, c) = (v[(i + n - 1) % n], v[i], v[(i + 1) % n]);
            cross(a, b, c) > 0.0
                && (0..n).all(|j| {
                    if j == i || j == (i + 1) % n || j == (i + n - 1) % n {
                        return true;
                    }
                    let p = v[j];
                    !(cross(a, b, p) >= 0.0 && cross(b, c, p) >= 0.0 && cross(c, a, p) >= 0.0)
                })
        });
        match ear {
            Some(i) => {
                tris.push([v[(i + n - 1) % n], v[i], v[(i + 1) % n]]);
                v.remove(i);
            }
            // Not simple (self-intersecting): give up on the rest rather than loop.
            None => break,
        }
    }
    tris
}

/// Area of `rect` ∩ annulus, m² (by the quadrature above).
pub fn annulus_rect_area(cx: f64, cy: f64, r_in: f64, r_out: f64, rect: &Rect) -> f64 {
    annulus_rect_quadrature(cx, cy, r_in, r_out, rect)
        .iter()
        .map(|q| q.2)
        .sum()
}

/// Exact area of polygon `poly` (vertices m, either orientation, simple) clipped to
/// `rect` (Sutherland–Hodgman against the four edges, then the shoelace formula).
pub fn polygon_rect_area(poly: &[[f64; 2]], rect: &Rect) -> f64 {
    let mut pts: Vec<[f64; 2]> = poly.to_vec();
    // (axis, bound, keep >= bound?)
    for (axis, bound, keep_ge) in [
        (0usize, rect.x0, true),
        (0, rect.x1, false),
        (1, rect.y0, true),
        (1, rect.y1, false),
    ] {
        if pts.is_empty() {
            return 0.0;
        }
        let inside = |p: &[f64; 2]| {
            if keep_ge {
                p[axis] >= bound
            } else {
                p[axis] <= bound
            }
        };
        let mut out = Vec::with_capacity(pts.len() + 4);
        for i in 0..pts.len() {
            let a = pts[i];
            let b = pts[(i + 1) % pts.len()];
            let (ia, ib) = (inside(&a), inside(&b));
            if ia {
                out.push(a);
            }
            if ia != ib {
                let t = (bound - a[axis]) / (b[axis] - a[axis]);
                out.push([a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])]);
            }
        }
        pts = out;
    }
    let n = pts.len();
    if n < 3 {
        return 0.0;
    }
    let s: f64 = (0..n)
        .map(|i| {
            let (a, b) = (pts[i], pts[(i + 1) % n]);
            a[0] * b[1] - b[0] * a[1]
        })
        .sum();
    0.5 * s.abs()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    fn rel(a: f64, b: f64) -> f64 {
        (a - b).abs() / b.abs()
    }

    #[test]
    fn gauss_rules_integrate_polynomials_exactly() {
        for n in [4, 8, 16] {
            let (x, w) = gauss_legendre(n);
            for d in 0..2 * n {
                let s: f64 = x.iter().zip(&w).map(|(x, w)| w * x.powi(d as i32)).sum();
                assert!(rel(s, 1.0 / (d as f64 + 1.0)) < 1e-13, "n {n} d {d}: {s}");
            }
        }
    }

    #[test]
    fn disc_inside_rect_has_area_and_second_moment_of_disc() {
        let r = Rect {
            x0: 0.0,
            y0: 0.0,
            x1: 1.0,
            y1: 1.0,
        };
        let q = annulus_rect_quadrature(0.4, 0.55, 0.0, 0.3, &r);
        let a: f64 = q.iter().map(|p| p.2).sum();
        assert!(rel(a, PI * 0.09) < 1e-13, "{a}");
        // ∫ (x − cx)² dA = π R⁴ / 4.
        let i2: f64 = q.iter().map(|p| p.2 * (p.0 - 0.4).powi(2)).sum();
        assert!(rel(i2, PI * 0.3f64.powi(4) / 4.0) < 1e-13, "{i2}");
        // Annulus.
        let a2 = annulus_rect_area(0.4, 0.55, 0.1, 0.3, &r);
        assert!(rel(a2, PI * (0.09 - 0.01)) < 1e-13);
    }

    #[test]
    fn circular_segment_and_corner_cases_match_closed_forms() {
        // Disc of radius R centred at distance d left of the edge x = 0 of a big rect:
        // the covered part is a circular segment, area R² acos(d/R) − d √(R² − d²).
        let big = Rect {
            x0: 0.0,
            y0: -5.0,
            x1: 5.0,
            y1: 5.0,
        };
        let (rr, d) = (1.0f64, 0.37f64);
        let seg = rr * rr * (d / rr).acos() - d * (rr * rr - d * d).sqrt();
        let a = annulus_rect_area(-d, 0.2, 0.0, rr, &big);
        assert!(rel(a, seg) < 1e-12, "{a} vs {seg}");
        // Disc centred on a rect corner: a quarter disc.
        let a = annulus_rect_area(0.0, -5.0, 0.0, 0.8, &big);
        assert!(rel(a, PI * 0.64 / 4.0) < 1e-12, "{a}");
        // Small rect fully inside the disc: its own area; fully outside: nothing.
        let small = Rect {
            x0: 0.1,
            y0: 0.1,
            x1: 0.3,
            y1: 0.2,
        };
        assert!(rel(annulus_rect_area(0.2, 0.15, 0.0, 1.0, &small), 0.02) < 1e-12);
        assert_eq!(annulus_rect_area(3.0, 3.0, 0.0, 1.0, &small), 0.0);
        // Partition: the areas over a 7 × 5 grid of cells add up to the disc area.
        let mut tot = 0.0;
        for i in 0..7 {
            for j in 0..5 {
                let c = Rect {
                    x0: i as f64 * 0.3,
                    y0: j as f64 * 0.3,
                    x1: (i + 1) as f64 * 0.3,
                    y1: (j + 1) as f64 * 0.3,
                };
                tot += annulus_rect_area(1.03, 0.71, 0.2, 0.55, &c);
            }
        }
        assert!(rel(tot, PI * (0.55f64.powi(2) - 0.04)) < 1e-12, "{tot}");
    }

    #[test]
    fn polygon_clipping_gives_exact_areas() {
        let r = Rect {
            x0: 0.0,
            y0: 0.0,
            x1: 1.0,
            y1: 1.0,
        };
        // Triangle half over the cell: (−1, 0), (2, 0), (−1, 3) ∩ unit square = square
        // minus the corner triangle above x + y = 2 (empty) → the whole square (1).
        assert!(
            rel(
                polygon_rect_area(&[[-1.0, 0.0], [2.0, 0.0], [-1.0, 3.0]], &r),
                1.0
            ) < 1e-14
        );
        // Diagonal half-plane triangle: area 0.5.
        assert!(
            rel(
                polygon_rect_area(&[[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], &r),
                0.5
            ) < 1e-14
        );
        // Clockwise rectangle shifted by (0.25, 0.5): overlap 0.75 × 0.5.
        let p = [[0.25, 0.5], [0.25, 1.5], [1.25, 1.5], [1.25, 0.5]];
        assert!(rel(polygon_rect_area(&p, &r), 0.375) < 1e-14);
        assert_eq!(
            polygon_rect_area(&[[2.0, 2.0], [3.0, 2.0], [3.0, 3.0]], &r),
            0.0
        );
    }

    /// ∬ over the triangle (0,0), (1,0), (0,1) of x^p y^q = p! q! / (p + q + 2)!.
    fn tri_moment(p: u32, q: u32) -> f64 {
        let f = |n: u32| (1..=n).map(f64::from).product::<f64>();
        f(p) * f(q) / f(p + q + 2)
    }

    #[test]
    fn green_quadrature_is_exact_for_the_bfs_degrees() {
        // Unit triangle and an L-shaped (non-convex) hexagon, clockwise given reversed.
        let tri = [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]];
        let q = polygon_quadrature(&tri);
        for p in 0..=6 {
            for r in 0..=6 {
                let s: f64 = q.iter().map(|(x, y, w)| w * x.powi(p) * y.powi(r)).sum();
                let e = tri_moment(p as u32, r as u32);
                assert!(rel(s, e) < 1e-12, "x^{p} y^{r}: {s} vs {e}");
            }
        }
        // L = [0,2]×[0,1] ∪ [0,1]×[1,2]; ∬ x² y³ = ∫₀² x² dx ∫₀¹ y³ + ∫₀¹ x² ∫₁² y³.
        let l = [
            [0.0, 0.0],
            [2.0, 0.0],
            [2.0, 1.0],
            [1.0, 1.0],
            [1.0, 2.0],
            [0.0, 2.0],
        ];
        let q = polygon_quadrature(&l);
        let s: f64 = q.iter().map(|(x, y, w)| w * x * x * y.powi(3)).sum();
        let e = 8.0 / 3.0 * 0.25 + 1.0 / 3.0 * 15.0 / 4.0;
        assert!(rel(s, e) < 1e-12, "{s} vs {e}");
        // Every point lies in the bounding box.
        assert!(q
            .iter()
            .all(|p| (0.0..=2.0).contains(&p.0) && (0.0..=2.0).contains(&p.1)));
    }

    #[test]
    fn convex_split_partitions_and_triangulation_covers() {
        let sq = rect_polygon(&Rect {
            x0: 0.0,
            y0: 0.0,
            x1: 1.0,
            y1: 1.0,
        });
        let t = [[0.5, -1.0], [2.0, 0.5], [0.5, 2.0]];
        let (inside, outside) = split_convex(&sq, &t, 0.0);
        let ai = signed_area(&inside.unwrap());
        let ao: f64 = outside.iter().map(|p| signed_area(p)).sum();
        assert!(rel(ai + ao, 1.0) < 1e-14);
        // Inside: the triangle's other two edges miss the square, so x ≥ 0.5 is all.
        assert!(rel(ai, 0.5) < 1e-14, "{ai}");
        assert!(outside.iter().all(|p| signed_area(p) > 0.0));
        // No overlap: (None, whole).
        let (i2, o2) = split_convex(&sq, &[[2.0, 2.0], [3.0, 2.0], [3.0, 3.0]], 0.0);
        assert!(i2.is_none() && o2.len() == 1);
        // Triangulation of the L (clockwise input, one collinear vertex added).
        let l = [
            [0.0, 0.0],
            [0.0, 2.0],
            [1.0, 2.0],
            [1.0, 1.0],
            [2.0, 1.0],
            [2.0, 0.0],
            [1.0, 0.0],
        ];
        let tris = triangulate(&l);
        let a: f64 = tris.iter().map(|t| signed_area(t)).sum();
        assert!(rel(a, 3.0) < 1e-14 && tris.iter().all(|t| signed_area(t) > 0.0));
    }

    #[test]
    fn disc_in_a_triangle_and_a_segment_cut_by_a_slanted_edge() {
        let tri = [[0.0, 0.0], [4.0, 0.0], [0.0, 4.0]];
        let a = annulus_rect_area(
            0.0,
            0.0,
            0.0,
            1.0,
            &Rect {
                x0: -9.0,
                y0: -9.0,
                x1: 9.0,
                y1: 9.0,
            },
        );
        assert!(rel(a, PI) < 1e-12);
        let q = annulus_convex_quadrature(1.0, 1.0, 0.0, 0.5, &tri);
        let a: f64 = q.iter().map(|p| p.2).sum();
        assert!(rel(a, PI * 0.25) < 1e-12, "{a}");
        // Disc centred at distance d below the hypotenuse x + y = 4: segment area.
        let (r, d) = (1.0f64, 0.3f64);
        let c = 2.0 - d / 2f64.sqrt();
        let q = annulus_convex_quadrature(c, c, 0.0, r, &tri);
        let a: f64 = q.iter().map(|p| p.2).sum();
        let seg = r * r * (d / r).acos() - d * (r * r - d * d).sqrt();
        assert!(rel(a, PI - seg) < 1e-12, "{a} vs {}", PI - seg);
    }
}

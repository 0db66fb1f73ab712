"""Generate two-layer test boards with a third-party Gerber writer (gerbonara) and render them
with an independent third-party renderer (pygerber's raster backend), for the Gerber import
test (tests/interop/gerber.rs).

Usage: gerber_boards.py OUT_DIR DPMM NX NY [NX NY ...] [--window LAYER X0 Y0 X1 Y1 WDPMM]

Writes OUT_DIR/{top,bottom,outline}.gbr (gerbonara, the files hbmu reads unchanged) and prints
JSON: for each copper layer and each NX × NY grid of elements over the board, the copper
coverage fraction of every element (row-major from the lowest row), as rendered by pygerber at
DPMM pixels per mm; plus the board corner in Gerber coordinates (mm). With --window, the part
of LAYER inside the box X0 Y0 X1 Y1 (board mm) is written again on its own
(OUT_DIR/window_LAYER.gbr: the objects that meet it, strokes clipped) and rendered at WDPMM,
and the coverage of every element lying inside the box is printed under "window": pygerber
draws each macro flash on its own pixel-snapped sub-image, which at 200 px/mm puts a pad
~2 pixels (10 µm) off, ~1 % of a 1 mm element; a finer rendering of the part that holds the
macro pads shrinks that in proportion, where the whole board at that resolution would not fit
in memory.

The boards hold what real copper layers hold: hatched pours (diagonal and orthogonal hatch
lines), pads flashed with circle (with a hole), rectangle, obround and polygon apertures,
pads flashed with aperture macros (gerbonara writes rotated rectangles, obrounds and
rounded rectangles as macros of vector-line (20) and circle (1) primitives, a trapezoid as an
outline (4), and holes as exposure-off circles), traces and arcs (G02/G03, a full circle), regions, and a ground plane with clear-polarity
(LPC) cut-outs, anti-pads and slots, with dark pads drawn again inside a cut-out. (Regions
with arc edges are not in the comparison: pygerber 2.4's raster backend bends region arcs
the wrong way; src/fem/gerber.rs tests them against closed-form areas.) The board's corner sits at (100, 60) mm in Gerber coordinates.

pygerber's tokenizer is stricter than gerbonara's writer in two places: gerbonara 1.5 writes
`G75` without its `*` and polygon vertex counts as decimals (`P,1.5X6.0`). The copy handed to
pygerber gets those two spellings fixed (same image); hbmu reads the files as written.
"""

import json
import math
import re
import sys
from io import BytesIO
from pathlib import Path

import numpy as np
from PIL import Image

Image.MAX_IMAGE_PIXELS = None  # our own renderings, not untrusted input

from gerbonara import GerberFile
from gerbonara.aperture_macros.parse import GenericMacros
from gerbonara.apertures import (
    ApertureMacroInstance,
    CircleAperture,
    ObroundAperture,
    PolygonAperture,
    RectangleAperture,
)
from gerbonara.graphic_objects import Arc, Flash, Line, Region
from gerbonara.utils import MM
from pygerber.common.rgba import RGBA
from pygerber.gerberx3.api.v2 import ColorScheme, GerberFile as PgFile, ImageFormatEnum

OX, OY = 100.0, 60.0  # board corner in Gerber coordinates, mm
L, W = 80.0, 50.0  # board size, mm
# Two marker squares outside the board, diagonal corners: they fix the rendered image's
# placement (their centroids) without touching any element.
MARK = 0.5
MARKS = [(OX - 2.0, OY - 2.0), (OX + L + 2.0, OY + W + 2.0)]


def P(x, y):
    return (OX + x, OY + y)


def hatch(g, ap, x0, y0, x1, y1, pitch, angle_deg):
    """Hatch lines at `angle_deg` clipped to the rectangle, plus its frame."""
    a = math.radians(angle_deg)
    d = (math.cos(a), math.sin(a))
    n = (-d[1], d[0])
    corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    offs = [c[0] * n[0] + c[1] * n[1] for c in corners]
    s = math.ceil(min(offs) / pitch) * pitch
    while s <= max(offs):
        # Intersect the line {p : p·n = s} with the rectangle.
        pts = []
        for k in range(4):
            p, q = corners[k], corners[(k + 1) % 4]
            dp = p[0] * n[0] + p[1] * n[1] - s
            dq = q[0] * n[0] + q[1] * n[1] - s
            if (dp <= 0) != (dq <= 0):
                t = dp / (dp - dq)
                pts.append((p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])))
        if len(pts) == 2:
            g.objects.append(Line(*P(*pts[0]), *P(*pts[1]), aperture=ap, unit=MM))
        s += pitch
    for k in range(4):
        p, q = corners[k], corners[(k + 1) % 4]
        g.objects.append(Line(*P(*p), *P(*q), aperture=ap, unit=MM))


def marks(g):
    m = RectangleAperture(MARK, MARK, unit=MM)
    for x, y in MARKS:
        g.objects.append(Flash(x, y, m, unit=MM))


def top_layer():
    g = GerberFile()
    h = CircleAperture(0.25, unit=MM)
    hatch(g, h, 8.5, 8.5, 39.3, 41.7, 0.9, 0.0)
    hatch(g, CircleAperture(0.2, unit=MM), 42.1, 10.3, 71.6, 39.8, 1.1, 0.0)
    hatch(g, CircleAperture(0.2, unit=MM), 42.1, 10.3, 71.6, 39.8, 1.1, 90.0)
    # A row of pads along the bottom edge, four aperture types.
    aps = [
        RectangleAperture(1.5, 0.6, unit=MM),
        ObroundAperture(2.0, 1.0, unit=MM),
        PolygonAperture(1.5, 5, unit=MM),
        CircleAperture(1.2, hole_dia=0.5, unit=MM),
    ]
    for k in range(16):
        g.objects.append(Flash(*P(19.0 + 2.6 * k, 3.4), aps[k % 4], unit=MM))
    # A second row of pads, flashed with aperture macros (AM): rotated apertures and
    # gerbonara's generic rounded rectangle and trapezoid macros.
    r = math.radians
    macros = [
        RectangleAperture(1.5, 0.6, unit=MM).rotated(r(30)),
        ObroundAperture(2.0, 1.0, unit=MM).rotated(r(60)),
        ApertureMacroInstance(GenericMacros.rounded_rect, (1.6, 1.0, 0.3, 0, 0, r(15)), unit=MM),
        ApertureMacroInstance(GenericMacros.isosceles_trapezoid, (1.6, 1.0, 0.8, 0, 0, r(25)), unit=MM),
        RectangleAperture(1.5, 0.8, hole_dia=0.4, unit=MM).rotated(r(40)),
    ]
    for k in range(12):
        g.objects.append(Flash(*P(19.0 + 3.4 * k, 6.2), macros[k % 5], unit=MM))
    # Traces: straight, diagonal, dog-leg, and arcs.
    t3 = CircleAperture(0.3, unit=MM)
    t2 = CircleAperture(0.2, unit=MM)
    g.objects.append(Line(*P(10.2, 45.25), *P(69.8, 45.25), aperture=t3, unit=MM))
    g.objects.append(Line(*P(40.0, 8.0), *P(70.0, 44.0), aperture=t2, unit=MM))
    g.objects.append(Line(*P(5.0, 15.1), *P(35.0, 15.1), aperture=t3, unit=MM))
    g.objects.append(Line(*P(35.0, 15.1), *P(35.0, 30.0), aperture=t3, unit=MM))
    # Quarter and half arcs (relative centre offsets), both directions, and a full circle.
    g.objects.append(Arc(*P(74.0, 10.0), *P(78.0, 14.0), 0.0, 4.0, True, t3, unit=MM))
    g.objects.append(Arc(*P(72.0, 20.0), *P(72.0, 30.0), 0.0, 5.0, False, t2, unit=MM))
    g.objects.append(Arc(*P(2.0, 38.0), *P(2.0, 38.0), 1.5, 0.0, True, t2, unit=MM))
    # A region (straight edges, non-convex). Regions with arc edges are left to the
    # closed-form unit tests of src/fem/gerber.rs: pygerber 2.4's raster backend draws
    # region arcs bent the wrong way (rounded corners come out concave).
    pts = [(3, 20), (7, 20), (7, 30), (5.5, 30), (5.5, 24), (4.5, 24), (4.5, 30), (3, 30), (3, 20)]
    g.objects.append(Region([P(*p) for p in pts], unit=MM))
    marks(g)
    return g


def bottom_layer():
    g = GerberFile()
    g.objects.append(
        Region([P(1.5, 1.5), P(78.5, 1.5), P(78.5, 48.5), P(1.5, 48.5), P(1.5, 1.5)], unit=MM)
    )
    anti = CircleAperture(4.0, unit=MM)
    for x, y in [(4, 4), (76, 4), (4, 46), (76, 46)]:
        g.objects.append(Flash(*P(x, y), anti, unit=MM, polarity_dark=False))
    # An L-shaped cut-out under a component, clear polarity.
    g.objects.append(
        Region(
            [P(28.0, 18.0), P(50.0, 18.0), P(50.0, 32.0), P(40.0, 32.0), P(40.0, 26.0), P(28.0, 26.0), P(28.0, 18.0)],
            unit=MM,
            polarity_dark=False,
        )
    )
    # Slots (clear strokes) and dark pads drawn again inside the cut-out.
    slot = CircleAperture(0.8, unit=MM)
    g.objects.append(Line(*P(10.0, 12.0), *P(22.0, 12.0), aperture=slot, unit=MM, polarity_dark=False))
    g.objects.append(Line(*P(60.0, 10.0), *P(66.0, 40.0), aperture=slot, unit=MM, polarity_dark=False))
    pad = RectangleAperture(1.8, 1.2, unit=MM)
    for k in range(6):
        g.objects.append(Flash(*P(31.0 + 3.0 * k, 25.0), pad, unit=MM))
    g.objects.append(Line(*P(30.0, 21.0), *P(48.0, 21.0), aperture=CircleAperture(0.4, unit=MM), unit=MM))
    marks(g)
    return g


def outline_layer():
    g = GerberFile()
    e = CircleAperture(0.1, unit=MM)
    c = [P(0, 0), P(L, 0), P(L, W), P(0, W)]
    for k in range(4):
        g.objects.append(Line(*c[k], *c[(k + 1) % 4], aperture=e, unit=MM))
    return g


def render(path, dpmm):
    src = path.read_text()
    src = re.sub(r"^G75$", "G75*", src, flags=re.M)
    src = re.sub(r"(%ADD\d+P,[0-9.]+X\d+)\.0(?=[X*])", r"\1", src)
    white = RGBA.from_rgba(255, 255, 255, 255)
    black = RGBA.from_rgba(0, 0, 0, 255)
    scheme = ColorScheme(
        background_color=black,
        clear_color=black,
        solid_color=white,
        clear_region_color=black,
        solid_region_color=white,
        debug_1_color=black,
        debug_2_color=black,
    )
    buf = BytesIO()
    PgFile.from_str(src).parse().render_raster(
        buf, color_scheme=scheme, dpmm=dpmm, image_format=ImageFormatEnum.PNG
    )
    img = np.asarray(Image.open(buf).convert("L"), dtype=np.float32) / 255.0
    return img[::-1, :]  # row 0 = lowest y


def placement(img, dpmm, marks=MARKS, search_mm=2.0):
    """Pixel coordinate (continuous, pixel k spans [k, k+1)) of Gerber x, y: from the
    centroids of the two marker squares, the image's extreme features (lower-left and
    upper-right), found within `search_mm` of the image's corners."""
    h, w = img.shape
    ys, xs = np.nonzero(img > 0.5)
    r = search_mm * dpmm
    lo = (xs < r) & (ys < r)
    hi = (xs >= w - r) & (ys >= h - r)
    out = [(xs[sel].mean() + 0.5, ys[sel].mean() + 0.5) for sel in (lo, hi)]
    (px0, py0), (px1, py1) = out
    sx = (px1 - px0) / (marks[1][0] - marks[0][0])
    sy = (py1 - py0) / (marks[1][1] - marks[0][1])
    return (px0 - sx * marks[0][0], sx), (py0 - sy * marks[0][1], sy)


def clip_segment(p, q, box):
    """The part of segment p–q inside box = (x0, y0, x1, y1) (Liang–Barsky), or None."""
    (x0, y0, x1, y1) = box
    t0, t1 = 0.0, 1.0
    dx, dy = q[0] - p[0], q[1] - p[1]
    for d, lo, hi, v in ((dx, x0, x1, p[0]), (dy, y0, y1, p[1])):
        if d == 0.0:
            if v < lo or v > hi:
                return None
            continue
        a, b = (lo - v) / d, (hi - v) / d
        t0, t1 = max(t0, min(a, b)), min(t1, max(a, b))
    if t0 > t1:
        return None
    return (p[0] + t0 * dx, p[1] + t0 * dy), (p[0] + t1 * dx, p[1] + t1 * dy)


def window_layer(g, box):
    """A copy of layer `g` that draws the same image inside `box` (Gerber mm) and as little
    as it can outside: the objects whose bounding box meets the box grown by 0.3 mm, with
    straight strokes clipped to that grown box (a round-capped stroke clipped to a box grown
    by at least its half width draws the same image inside the box), and two marks 1.5 mm
    beyond the kept objects' bounding box at its diagonal corners. Returns the layer and its
    marks. pygerber renders an image as large as the layer's extent, so this is how a part of
    a board is rendered at a resolution the whole board would not fit in memory at."""
    m = 0.3
    grown = (box[0] - m, box[1] - m, box[2] + m, box[3] + m)
    w = GerberFile()
    lo, hi = [math.inf, math.inf], [-math.inf, -math.inf]
    for obj in g.objects:
        (bx0, by0), (bx1, by1) = obj.bounding_box(MM)
        if bx1 < grown[0] or bx0 > grown[2] or by1 < grown[1] or by0 > grown[3]:
            continue
        if isinstance(obj, Line):
            seg = clip_segment((obj.x1, obj.y1), (obj.x2, obj.y2), grown)
            if seg is None:
                continue
            obj = Line(*seg[0], *seg[1], aperture=obj.aperture, unit=MM, polarity_dark=obj.polarity_dark)
            (bx0, by0), (bx1, by1) = obj.bounding_box(MM)
        elif not isinstance(obj, Flash):
            raise ValueError(f"window_layer: {type(obj).__name__} meets the window; not handled")
        w.objects.append(obj)
        lo = [min(lo[0], bx0), min(lo[1], by0)]
        hi = [max(hi[0], bx1), max(hi[1], by1)]
    mk = [(lo[0] - 1.5, lo[1] - 1.5), (hi[0] + 1.5, hi[1] + 1.5)]
    sq = RectangleAperture(MARK, MARK, unit=MM)
    for x, y in mk:
        w.objects.append(Flash(x, y, sq, unit=MM))
    return w, mk


def weights(n_el, lo_mm, hi_mm, a, s, npx):
    """Overlap (in pixels) of element k's interval with pixel p: matrix n_el × npx."""
    m = np.zeros((n_el, npx))
    for k in range(n_el):
        u0 = a + s * (lo_mm + (hi_mm - lo_mm) * k / n_el)
        u1 = a + s * (lo_mm + (hi_mm - lo_mm) * (k + 1) / n_el)
        p0, p1 = int(math.floor(u0)), int(math.ceil(u1))
        for p in range(max(p0, 0), min(p1, npx)):
            m[k, p] = max(0.0, min(u1, p + 1) - max(u0, p))
    return m


def element_coverage(img, placement_xy, grids, box_mm=None):
    """Per element of each grid over the board, the mean of `img` over the element. With
    `box_mm` (board mm: x0, y0, x1, y1), only the elements lying inside that box, as a
    {"i,j": coverage} map; otherwise every element, row-major from the lowest row."""
    (ax, sx), (ay, sy) = placement_xy
    h, w = img.shape
    per = {}
    for nx, ny in grids:
        wx = weights(nx, OX, OX + L, ax, sx, w)
        wy = weights(ny, OY, OY + W, ay, sy, h)
        if box_mm is None:
            cov = (wy @ img @ wx.T) / np.outer(wy.sum(1), wx.sum(1))
            per[f"{nx}x{ny}"] = cov.ravel().tolist()
            continue
        eps = 1e-9
        ii = [i for i in range(nx) if box_mm[0] - eps <= L * i / nx and L * (i + 1) / nx <= box_mm[2] + eps]
        jj = [j for j in range(ny) if box_mm[1] - eps <= W * j / ny and W * (j + 1) / ny <= box_mm[3] + eps]
        cov = (wy[jj] @ img @ wx[ii].T) / np.outer(wy[jj].sum(1), wx[ii].sum(1))
        per[f"{nx}x{ny}"] = {f"{i},{j}": cov[b, a] for b, j in enumerate(jj) for a, i in enumerate(ii)}
    return per


def main():
    args = sys.argv[1:]
    window = None
    if "--window" in args:
        k = args.index("--window")
        name, *rest = args[k + 1 : k + 7]
        window = (name, [float(v) for v in rest[:4]], int(rest[4]))
        del args[k : k + 7]
    out = Path(args[0])
    dpmm = int(args[1])
    grids = [(int(a), int(b)) for a, b in zip(args[2::2], args[3::2])]
    out.mkdir(parents=True, exist_ok=True)
    layers = {"top": top_layer(), "bottom": bottom_layer(), "outline": outline_layer()}
    for name, g in layers.items():
        g.save(out / f"{name}.gbr")
    res = {"corner_mm": [OX, OY], "size_mm": [L, W], "dpmm": dpmm, "layers": {}}
    for name in ["top", "bottom"]:
        img = render(out / f"{name}.gbr", dpmm)
        pl = placement(img, dpmm)
        cov = element_coverage(img, pl, grids)
        res["layers"][name] = {"scale_px_per_mm": [pl[0][1], pl[1][1]], "coverage": cov}
        del img
    if window is not None:
        # One part of a layer again, at a finer resolution, from a file that draws only
        # that part (the same objects, written by gerbonara again).
        name, box, wdpmm = window
        gbox = (OX + box[0], OY + box[1], OX + box[2], OY + box[3])
        wl, wmarks = window_layer(layers[name], gbox)
        wpath = out / f"window_{name}.gbr"
        wl.save(wpath)
        img = render(wpath, wdpmm)
        pl = placement(img, wdpmm, wmarks, search_mm=1.0)
        res["window"] = {
            "layer": name,
            "box_mm": box,
            "dpmm": wdpmm,
            "objects": len(wl.objects) - 2,
            "coverage": element_coverage(img, pl, grids, box),
        }
    print(json.dumps(res))


if __name__ == "__main__":
    main()

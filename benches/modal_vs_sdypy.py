#!/usr/bin/env python3
"""Side-by-side check of hbmu's modal extraction against sdypy-EMA's LSCF + LSFD.

Usage: python3 benches/modal_vs_sdypy.py DIR
DIR holds one sub-directory per synthetic measurement with freq.npy, frf.npy (complex,
points x lines) and case.json (truth and hbmu's result + timing), as written by
`cargo bench --bench modal`. sdypy-EMA cannot pick poles by itself: it is given the TRUE
natural frequencies as hints (select_closest_poles), which is generous to it.
Its accuracy is taken at the same maximum polynomial degree as ours
(pol_order_high = max_order / 2, since sdypy doubles it); its time is reported both at that
setting and at pol_order_high = max_order, i.e. sdypy told "model orders up to 60" through its
own documented parameter ("Highest order of the polynomial"), which it runs to degree 120.
Our time is on one thread (sdypy's LSCF is single-threaded Python/NumPy) and, for
information, on the default thread pool. Both timings include pole estimation at every
order and the LSFD; ours also includes what sdypy leaves out: automatic pole selection, a
second (Sanathanan-Koerner) LSCF pass, the output-error refinement and the point screening.
For information it also times our extraction restricted to the steps sdypy runs (one LSCF
pass and the LSFD, with our automatic selection; no second pass, no refinement, no refit).
Prints per-mode errors against the truth, timings and the speed ratios.
"""
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

warnings.filterwarnings("ignore")
try:
    import sdypy.EMA as EMA
except ImportError:  # older packaging
    import pyEMA as EMA


def mac(a, b):
    a = np.asarray(a, dtype=complex)
    b = np.asarray(b, dtype=complex)
    ok = np.isfinite(a) & np.isfinite(b)
    a, b = a[ok], b[ok]
    return float(abs(np.vdot(a, b)) ** 2 / (np.vdot(a, a).real * np.vdot(b, b).real))


def run_sdypy(freq, frf, hints, pol_order_high):
    t0 = time.perf_counter()
    m = EMA.Model(frf=frf, freq=freq, lower=float(freq[0]), upper=float(freq[-1]),
                  pol_order_high=pol_order_high, frf_form="mobility")
    m.get_poles(show_progress=False)
    m.select_closest_poles(hints)
    H, A = m.get_constants(whose_poles="own", FRF_ind="all")
    dt = time.perf_counter() - t0
    return np.asarray(m.nat_freq), np.asarray(m.nat_xi), np.asarray(A), dt


def match_mode(modes, f, z, shape):
    """Relative frequency and damping errors and MAC of the identified mode (dicts with
    freq_hz, damping_ratio, shape) that stands for the true mode (f, z, shape): of those
    within 2 % in frequency, the best MAC (the closest in frequency may be the partner of
    a close pair). NaNs if none is within 2 %."""
    cand = [k for k, m in enumerate(modes) if abs(m["freq_hz"] - f) / f < 0.02]
    if not cand:
        return (np.nan, np.nan, np.nan)
    m = modes[max(cand, key=lambda k: mac(modes[k]["shape"], shape))]
    return ((m["freq_hz"] - f) / f, (m["damping_ratio"] - z) / z, mac(m["shape"], shape))


def main():
    root = Path(sys.argv[1])
    cases = sorted(p for p in root.iterdir() if (p / "case.json").exists())
    rows = []  # (case, mode, f_true, z_true, ours f err, ours z err, ours mac, sd f err, sd z err, sd mac)
    t_ours, t_pool, t_sd, t_sd_own, t_lean = [], [], [], [], []
    lean_rows = []
    threads = 1
    for c in cases:
        case = json.loads((c / "case.json").read_text())
        freq = np.load(c / "freq.npy")
        frf = np.load(c / "frf.npy")
        tf = case["truth"]["freq_hz"]
        tz = case["truth"]["damping_ratio"]
        ts = case["truth"]["shapes"]
        ours = case["ours"]["modes"]
        max_order = case["ours"]["max_order"]
        # Same highest polynomial degree as ours (sdypy's degree is 2 x pol_order_high).
        sf, sz, sA, dt = run_sdypy(freq, frf, tf, max_order // 2)
        # sdypy's own meaning of "model order 60": pol_order_high = 60 (degree 120).
        _, _, _, dt_own = run_sdypy(freq, frf, tf, max_order)
        t_ours.append(case["ours"]["time_s"])
        t_pool.append(case["ours"]["time_s_pool"])
        t_lean.append(case["ours_lean"]["time_s"])
        lean_rows += [match_mode(case["ours_lean"]["modes"], f, z, shp) for f, z, shp in zip(tf, tz, ts)]
        threads = case["ours"]["threads"]
        t_sd.append(dt)
        t_sd_own.append(dt_own)
        for r, (f, z, shp) in enumerate(zip(tf, tz, ts)):
            o = match_mode(ours, f, z, shp)
            s = ((sf[r] - f) / f, (sz[r] - z) / z, mac(sA[:, r], shp))
            rows.append((c.name, r, f, z) + o + s)
    print()
    print("per-mode errors against truth (relative; MAC of shape with the true shape)")
    print(f"{'case':8} {'mode':>4} {'f_true':>8} {'z_true':>7} | {'ours df%':>9} {'ours dz%':>9} {'ours MAC':>8} | {'sdypy df%':>9} {'sdypy dz%':>9} {'sdypy MAC':>9}")
    for r in rows:
        print(f"{r[0]:8} {r[1]:4d} {r[2]:8.1f} {r[3]:7.4f} | {100*r[4]:+9.4f} {100*r[5]:+9.2f} {r[6]:8.5f} | {100*r[7]:+9.4f} {100*r[8]:+9.2f} {r[9]:9.5f}")
    a = np.array([r[4:] for r in rows], dtype=float)
    def summary(cols, name):
        fe, ze, mc = np.abs(a[:, cols[0]]), np.abs(a[:, cols[1]]), a[:, cols[2]]
        print(f"{name:6}: |df| median {100*np.nanmedian(fe):.4f} % max {100*np.nanmax(fe):.4f} % | "
              f"|dz| median {100*np.nanmedian(ze):.2f} % max {100*np.nanmax(ze):.2f} % | "
              f"MAC min {np.nanmin(mc):.5f} | missed {int(np.isnan(fe).sum())}")
    print()
    summary((0, 1, 2), "ours")
    summary((3, 4, 5), "sdypy")
    a = np.array(lean_rows, dtype=float)
    summary((0, 1, 2), "lean")
    to, tp, ts_, tso = (float(np.median(t)) for t in (t_ours, t_pool, t_sd, t_sd_own))
    print(f"time per measurement (median over {len(cases)}): ours {1e3*to:.1f} ms on 1 thread "
          f"({1e3*tp:.1f} ms on {threads})")
    print(f"  sdypy-EMA pol_order_high={max_order} (its 'model orders up to {max_order}', degree {2*max_order}): "
          f"{1e3*tso:.1f} ms, ours is {tso/to:.1f}x faster on 1 thread ({tso/tp:.1f}x on {threads})")
    print(f"  sdypy-EMA pol_order_high={max_order // 2} (same polynomial degree {max_order} as ours): "
          f"{1e3*ts_:.1f} ms, ours is {ts_/to:.1f}x faster on 1 thread ({ts_/tp:.1f}x on {threads})")
    tl = float(np.median(t_lean))
    print(f"  for information, ours with only sdypy's steps ('lean': one LSCF pass + LSFD, no SK pass, "
          f"refinement or refit): {1e3*tl:.1f} ms on 1 thread, {ts_/tl:.1f}x faster than sdypy at the same degree")


if __name__ == "__main__":
    main()

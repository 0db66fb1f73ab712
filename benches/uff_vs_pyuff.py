#!/usr/bin/env python3
"""Time the third-party UFF reader pyuff on the files written by `cargo bench --bench uff`.

Usage: uff_vs_pyuff.py DIR [N_FILES]

pyuff is slow, so only the first N_FILES (default 2) *.uff files of DIR (sorted) are read with
`pyuff.UFF(path).read_sets()`; the MB/s printed is measured on that subset and extrapolated to
the whole directory (time for all = bytes of all / measured MB/s), and says so.
"""
import glob
import os
import sys
import time

import pyuff


def main():
    d = sys.argv[1]
    n = int(sys.argv[2]) if len(sys.argv) > 2 else 2
    paths = sorted(glob.glob(os.path.join(d, "*.uff")))
    if not paths:
        sys.exit(f"no *.uff files in {d}")
    subset = paths[:n]
    nbytes = sum(os.path.getsize(p) for p in subset)
    t = time.perf_counter()
    c = time.process_time()
    nsets = 0
    for p in subset:
        sets = pyuff.UFF(p).read_sets()
        nsets += len(sets) if isinstance(sets, list) else 1
    dt = time.perf_counter() - t
    dc = time.process_time() - c
    mbs = nbytes / 1e6 / dt
    total = sum(os.path.getsize(p) for p in paths)
    print(f"pyuff {pyuff.__version__}: {len(subset)} of {len(paths)} files, {nbytes/1e6:.1f} MB, "
          f"{nsets} datasets in {dt:.2f} s: {mbs:.2f} MB/s (wall, measured on the subset)")
    print(f"pyuff: {dc:.2f} s CPU: {nbytes / 1e6 / dc:.2f} MB/s per CPU second")
    print(f"extrapolated: all {total/1e6:.1f} MB would take {total/1e6/mbs:.0f} s at that rate")


if __name__ == "__main__":
    main()

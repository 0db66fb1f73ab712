#!/usr/bin/env python3
"""Time the third-party UFF reader pyuff on the files written by `cargo bench --bench uff`.

Usage: uff_vs_pyuff.py DIR [N_FILES]

Each measurement is repeated (env HBMU_UFF_BENCH_ROUNDS, default 3) and the best is printed,
as benches/uff.rs does, because the machine may be shared. pyuff is slow, so only the first N_FILES (default 2) *.uff files of DIR (sorted) are read with
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
    rounds = int(os.environ.get("HBMU_UFF_BENCH_ROUNDS", "3"))
    best_wall = best_cpu = float("inf")
    for _ in range(rounds):
        t = time.perf_counter()
        c = time.process_time()
        nsets = 0
        for p in subset:
            sets = pyuff.UFF(p).read_sets()
            nsets += len(sets) if isinstance(sets, list) else 1
        best_wall = min(best_wall, time.perf_counter() - t)
        best_cpu = min(best_cpu, time.process_time() - c)
    mbs = nbytes / 1e6 / best_wall
    print(f"pyuff {pyuff.__version__}, best of {rounds}: {len(subset)} of {len(paths)} files, "
          f"{nbytes/1e6:.1f} MB, {nsets} datasets in {best_wall:.2f} s: {mbs:.2f} MB/s "
          f"(wall, measured on the subset)")
    print(f"pyuff, best of {rounds}: {best_cpu:.2f} s CPU: {nbytes / 1e6 / best_cpu:.2f} MB/s "
          f"per CPU second")
    total = sum(os.path.getsize(p) for p in paths)
    print(f"extrapolated: all {total/1e6:.1f} MB would take {total/1e6/mbs:.0f} s at that rate (wall)")


if __name__ == "__main__":
    main()

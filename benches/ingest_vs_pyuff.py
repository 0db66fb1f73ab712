#!/usr/bin/env python3
"""The ingest stage end to end against pyuff, on one campaign directory.

Usage: ingest_vs_pyuff.py CAMPAIGN_DIR HBMU OUT_DIR

Prints the best of 3 wall times of `HBMU ingest CAMPAIGN_DIR --out OUT_DIR --force` (read,
check and write every output, fsync and manifest included, process start too), the bytes it
wrote, the best of 3 of pyuff reading every UFF file of the campaign (`UFF(path).read_sets()`,
nothing written), and the ratio. A virtual-lab campaign mixes ASCII and binary UFF as labs do;
the count of binary files is printed because pyuff reads those much faster than ASCII.
"""
import glob
import os
import subprocess
import sys
import time

import pyuff


def best_of(n, f):
    best = float("inf")
    for _ in range(n):
        t = time.perf_counter()
        f()
        best = min(best, time.perf_counter() - t)
    return best


def main():
    campaign, hbmu, out = sys.argv[1], sys.argv[2], sys.argv[3]

    def ingest():
        r = subprocess.run([hbmu, "ingest", campaign, "--out", out, "--force"],
                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        if r.returncode not in (0, 3):  # 3: some measurements quarantined
            sys.exit(f"hbmu ingest failed ({r.returncode}): {r.stderr.decode()[-2000:]}")

    paths = sorted(glob.glob(os.path.join(campaign, "**", "*.uff"), recursive=True))
    if not paths:
        sys.exit(f"no *.uff files under {campaign}")
    in_mb = sum(os.path.getsize(p) for p in paths) / 1e6
    binary = sum(1 for p in paths if b"\n    58b" in open(p, "rb").read())
    t_hbmu = best_of(3, ingest)
    out_mb = sum(os.path.getsize(os.path.join(out, f)) for f in os.listdir(out)
                 if not f.startswith(".")) / 1e6
    print(f"hbmu ingest, best of 3: {in_mb:.1f} MB of UFF ({len(paths)} files, {binary} binary) "
          f"in {t_hbmu:.2f} s wall, {out_mb:.1f} MB written")
    t_pyuff = best_of(3, lambda: [pyuff.UFF(p).read_sets() for p in paths])
    print(f"pyuff {pyuff.__version__}, best of 3: read in {t_pyuff:.2f} s wall")
    print(f"hbmu ingest end to end is {t_pyuff / t_hbmu:.1f}x pyuff reading")


if __name__ == "__main__":
    main()

#!/usr/bin/env python3
"""Recovery of a virtual-lab campaign's truth by the step-1 posterior (issue 9's acceptance).

Usage: benches/recovery.py WORK_DIR [WORK_DIR...]   (each with truth.json and update_boards/)

For every work directory, and pooled over all of them, prints:
- how many of the truth's per-board values (e_x_pa, e_y_pa, g_xy_pa, mass_scale, and every
  other parameter the truth and the posterior share) lie inside their 90 % posterior
  intervals, against the nominal 90 %: the physical parameter's interval
  (physical_q05-physical_q95 of summary.parquet, which holds the model-form discrepancy's
  part the parameters absorb) where step 1 inferred a discrepancy, else q05-q95; the
  fitted draws' q05-q95 count is printed beside it (HBMU_RECOVERY_FIT=1 scores that one);
- the same for the population means (mu_*) and spreads (sigma_*: the truth's rel_std times
  its mean, the parameterisation hbmu uses);
- a binomial two-sided p-value of the pooled count against 0.9;
- the Table-2 analog: per free-free updating mode, the mean relative error of the
  posterior-predictive mean over the measurements (residuals.parquet), and its worst |value|;
- the largest R-hat and the spread of the runs' log evidence.

The truth's generating population mean is what mu_* should cover; the boards' values are the
realised draws the per-board rows should cover.
"""
import json
import math
import os
import sys

import numpy as np
import pandas as pd


def binom_two_sided(k, n, p):
    """Exact two-sided binomial p-value (sum of outcomes no more likely than k)."""
    pk = math.comb(n, k) * p**k * (1 - p) ** (n - k)
    tot = 0.0
    for i in range(n + 1):
        pi = math.comb(n, i) * p**i * (1 - p) ** (n - i)
        if pi <= pk * (1 + 1e-9):
            tot += pi
    return min(1.0, tot)


USE_FIT = os.environ.get("HBMU_RECOVERY_FIT") == "1"


def bounds(row):
    """The physical interval where the summary has one, else the draws' (see the doc)."""
    if not USE_FIT and "physical_q05" in row and pd.notna(row["physical_q05"]):
        return row["physical_q05"], row["physical_q95"]
    return row["q05"], row["q95"]


def inside(row, value):
    lo, hi = bounds(row)
    return bool(lo <= value <= hi)


def one(work):
    truth = json.load(open(f"{work}/truth.json"))
    s = pd.read_parquet(f"{work}/update_boards/summary.parquet")
    ev = json.load(open(f"{work}/update_boards/evidence.json"))
    res = pd.read_parquet(f"{work}/update_boards/residuals.parquet")
    pop = truth["population"]
    out = {"board": [], "mu": [], "sigma": []}
    board_rows = s[s["board_id"].notna() & s["measurement_id"].isna()]
    for b in truth["boards"]:
        for p in pop["parameters"]:
            r = board_rows[(board_rows["board_id"] == b["board_id"]) & (board_rows["parameter"] == p)]
            if len(r) == 1 and p in b:
                out["board"].append((b["board_id"], p, inside(r.iloc[0], b[p]), b[p], *bounds(r.iloc[0])))
    glob = s[s["board_id"].isna() & s["measurement_id"].isna()].set_index("parameter")
    # The population's coordinates: a modulus per unit mass scale (update's default
    # `--board-coordinates per-mass`, column <m>_per_mass_scale_pa) has the truth's mean and
    # sd of modulus / mass_scale, by Monte Carlo from the truth's normal population.
    names = list(pop["parameters"])
    rng = np.random.default_rng(0)
    draws = rng.multivariate_normal(pop["mean"], pop["covariance"], size=400_000)
    coords = [(p, pop["mean"][i], pop["rel_std"][i] * pop["mean"][i]) for i, p in enumerate(names)]
    if "mass_scale" in names:
        ms = draws[:, names.index("mass_scale")]
        for i, p in enumerate(names):
            if p.endswith("_pa"):
                r = draws[:, i] / ms
                coords.append((p[: -len("_pa")] + "_per_mass_scale_pa", r.mean(), r.std()))
    for p, m, sd in coords:
        if f"mu_{p}" in glob.index:
            r = glob.loc[f"mu_{p}"]
            out["mu"].append((p, inside(r, m), m, *bounds(r)))
        if f"sigma_{p}" in glob.index:
            r = glob.loc[f"sigma_{p}"]
            out["sigma"].append((p, inside(r, sd), sd, *bounds(r)))
    upd = res[(res["setup"] == "free") & res["used_for_updating"]]
    table2 = upd.groupby("label")["rel_residual"].mean()
    runs = ev.get("log_evidence_runs", [])
    return out, table2, float(s["r_hat"].max()), runs


def main(works):
    pooled = {"board": [], "mu": [], "sigma": []}
    worst_t2 = 0.0
    for w in works:
        out, t2, rhat, runs = one(w)
        for k in pooled:
            pooled[k] += out[k]
        counts = ", ".join(
            f"{k} {sum(x[-4 if k == 'board' else 1] for x in v)}/{len(v)}" for k, v in out.items()
        )
        spread = (max(runs) - min(runs)) if runs else float("nan")
        worst = float(t2.abs().max())
        worst_t2 = max(worst_t2, worst)
        print(f"{w}: inside 90 % intervals: {counts}; max R-hat {rhat:.4f}; "
              f"log Z runs {[round(x, 2) for x in runs]} (spread {spread:.2f}); "
              f"Table-2 worst |mean rel error| {100 * worst:.4f} %")
        for k in ("mu", "sigma"):
            for x in out[k]:
                if not x[1]:
                    print(f"    {k}_{x[0]}: truth {x[2]:.6g} outside [{x[3]:.6g}, {x[4]:.6g}]")
        for x in out["board"]:
            if not x[2]:
                print(f"    {x[0]} {x[1]}: truth {x[3]:.6g} outside [{x[4]:.6g}, {x[5]:.6g}]")
    print("pooled:")
    for k, v in pooled.items():
        n = len(v)
        inside_n = sum(x[2] if k == "board" else x[1] for x in v)
        if n:
            print(f"  {k}: {inside_n}/{n} = {100 * inside_n / n:.1f} % inside (nominal 90 %), "
                  f"binomial two-sided p = {binom_two_sided(inside_n, n, 0.9):.3f}")
    print(f"  Table-2 analog: worst |posterior-predictive mean error| of a free-free updating mode "
          f"{100 * worst_t2:.4f} % (target < 0.2 %)")


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    main(sys.argv[1:])

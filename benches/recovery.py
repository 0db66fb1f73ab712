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

The board rows of one campaign are not independent trials: every board's physical interval
holds the same shared uncertainty (the model-form discrepancy's part the parameters absorb,
the balance's common bias), so they cover or miss together, and a binomial test over them tests one draw many times. The
contrasts take that shared part out: per parameter and draw, a board's ln value less the mean
over the campaign's boards (a shift common to the boards cancels; n boards leave n - 1 free
contrasts a parameter, so the test is slightly optimistic). Their 90 % intervals (from the
physical draws, boards_physical.parquet, where step 1 wrote them, else boards.parquet's
fitted draws; HBMU_RECOVERY_FIT=1 takes the fitted ones) against the truth's contrasts,
pooled, get the binomial test too, with the z-scores' sd (1 when the widths are right).
"""
import json
import math
import os
import sys

import numpy as np
import pandas as pd


def inside_flag(kind, row):
    """Whether a scored row (board and contrast rows: (board, parameter, inside, ...); the
    population's: (parameter, inside, ...)) lies inside its interval."""
    return row[2] if kind in ("board", "contrast") else row[1]


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
    out["contrast"], out["contrast_z"] = contrasts(work, truth)
    upd = res[(res["setup"] == "free") & res["used_for_updating"]]
    table2 = upd.groupby("label")["rel_residual"].mean()
    runs = ev.get("log_evidence_runs", [])
    return out, table2, float(s["r_hat"].max()), runs


def contrasts(work, truth):
    """Per parameter and board: whether the truth's contrast (ln value less the boards' mean ln
    value) is inside the 90 % interval of the draws' contrasts, and its z-score."""
    phys = f"{work}/update_boards/boards_physical.parquet"
    b = pd.read_parquet(phys if os.path.exists(phys) and not USE_FIT else f"{work}/update_boards/boards.parquet")
    tb = {x["board_id"]: x for x in truth["boards"]}
    ids = sorted(i for i in b["board_id"].unique() if i in tb)
    inside_c, zs = [], []
    for p in truth["population"]["parameters"]:
        if p not in b.columns or any(p not in tb[i] for i in ids) or len(ids) < 3:
            continue
        wide = b[b["board_id"].isin(ids)].pivot_table(index=["run", "draw"], columns="board_id", values=p)[ids]
        ln = np.log(wide.to_numpy())
        c = ln - ln.mean(axis=1, keepdims=True)
        t = np.log([tb[i][p] for i in ids])
        tc = t - t.mean()
        lo, hi = np.quantile(c, [0.05, 0.95], axis=0)
        for k, i in enumerate(ids):
            inside_c.append((i, p, bool(lo[k] <= tc[k] <= hi[k])))
            zs.append((p, (tc[k] - c[:, k].mean()) / c[:, k].std()))
    return inside_c, zs


def main(works):
    pooled = {"board": [], "mu": [], "sigma": [], "contrast": []}
    z_all = []
    worst_t2 = 0.0
    for w in works:
        out, t2, rhat, runs = one(w)
        z_all += out.pop("contrast_z")
        for k in pooled:
            pooled[k] += out[k]
        counts = ", ".join(
            f"{k} {sum(inside_flag(k, x) for x in v)}/{len(v)}" for k, v in out.items()
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
        inside_n = sum(inside_flag(k, x) for x in v)
        if n:
            print(f"  {k}: {inside_n}/{n} = {100 * inside_n / n:.1f} % inside (nominal 90 %), "
                  f"binomial two-sided p = {binom_two_sided(inside_n, n, 0.9):.3f}")
    if z_all:
        zs = np.array([z for _, z in z_all])
        print(f"  contrast z-scores: sd {np.std(zs):.2f} over {len(zs)} (1 when the widths are right)")
        by = {}
        for p, z in z_all:
            by.setdefault(p, []).append(z)
        print("    per parameter: " + ", ".join(
            f"{p} {np.std(v):.2f} ({sum(abs(x) <= 1.645 for x in v)}/{len(v)} within ±1.645)" for p, v in by.items()))
    print(f"  Table-2 analog: worst |posterior-predictive mean error| of a free-free updating mode "
          f"{100 * worst_t2:.4f} % (target < 0.2 %)")


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    main(sys.argv[1:])

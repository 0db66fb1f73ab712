#!/usr/bin/env python3
"""Check hbmu's posterior summary against ArviZ, the third-party reference for MCMC/SMC
convergence diagnostics.

Usage: arviz_check.py DRAWS.parquet SUMMARY.parquet

DRAWS.parquet: columns `run` (int; one run = one chain), `draw` (int), optional `board_id`
and `measurement_id` (strings, may be null), optional integer index columns `boards_run`,
`boards_draw` (the step-1 draw a step-2 particle carries; not parameters), and one float
column per parameter. When
`board_id`/`measurement_id` exist, each distinct (board_id, measurement_id) value is a
separate quantity per parameter; rows of a group with no value for a parameter (NaN in every
row of that group) are not compared for that parameter.

SUMMARY.parquet: columns parameter, board_id (nullable), measurement_id (nullable), mean, sd,
q05, q50, q95, r_hat, ess_bulk, ess_tail.

For every (parameter, board_id, measurement_id) the draws are loaded into ArviZ as
(chain = run, draw) and compared with the summary row:
  r_hat     arviz.rhat(method="rank")   absolute tolerance 1e-9
  ess_bulk  arviz.ess(method="bulk")    relative tolerance 1e-6
  ess_tail  arviz.ess(method="tail")    relative tolerance 1e-6
  mean, sd (ddof=1), q05/q50/q95 (numpy linear quantiles) of all draws pooled, tolerance
            1e-9 relative to max(|value|, sd), or 1e-12 of the largest |draw| (rounding level)
NaN agrees only with NaN. Documented exception: R-hat above 1e6 on both sides agrees (chains
constant within but different between: ArviZ divides by a within-chain variance made of
rounding error, hbmu reports +inf). A summary row without draws, or draws without a summary
row, is an error. Prints one line per compared quantity and the ArviZ version; exits 1 with
the list of disagreements, 2 on unusable input.
"""
import math
import sys

import arviz as az
import numpy as np
import pandas as pd

GROUP_COLS = ("board_id", "measurement_id")
# Integer index columns that are not parameters: the step-1 draw a step-2 particle carries.
INDEX_COLS = ("boards_run", "boards_draw")
STATS = ("mean", "sd", "q05", "q50", "q95", "r_hat", "ess_bulk", "ess_tail")


def fail_input(msg):
    print(f"arviz_check: {msg}", file=sys.stderr)
    sys.exit(2)


def key_part(v):
    return None if v is None or (isinstance(v, float) and math.isnan(v)) or v is pd.NA else str(v)


def chains_array(group, param, where):
    """(run, draw) array of one parameter; every run must have the same draws."""
    try:
        wide = group.pivot(index="run", columns="draw", values=param)
    except ValueError as e:
        fail_input(f"{where}: cannot arrange draws as (run, draw): {e}")
    wide = wide.sort_index().sort_index(axis=1)
    if wide.isna().to_numpy().any() and not group[param].isna().any():
        fail_input(f"{where}: runs do not all have the same draw indices")
    return wide.to_numpy(dtype=float)


def reference(x):
    ds = az.convert_to_dataset({"x": x})  # dims (chain, draw)
    flat = x.ravel()
    with np.errstate(all="ignore"):
        q = np.quantile(flat, [0.05, 0.5, 0.95])
        sd = float(np.std(flat, ddof=1)) if flat.size > 1 else float("nan")
    return {
        "mean": float(np.mean(flat)),
        "sd": sd,
        "q05": float(q[0]),
        "q50": float(q[1]),
        "q95": float(q[2]),
        "r_hat": float(az.rhat(ds, method="rank")["x"].values),
        "ess_bulk": float(az.ess(ds, method="bulk")["x"].values),
        "ess_tail": float(az.ess(ds, method="tail")["x"].values),
    }


def disagreement(stat, got, want, sd, max_abs):
    """None when got agrees with want, else the size of the disagreement."""
    if math.isnan(want) or math.isnan(got):
        return None if math.isnan(want) and math.isnan(got) else math.inf
    if got == want:
        return None
    if stat == "r_hat":
        if want > 1e6 and got > 1e6:
            return None
        d = abs(got - want)
        return d if d > 1e-9 else None
    if stat.startswith("ess"):
        d = abs(got - want) / abs(want)
        return d if d > 1e-6 else None
    scale = max(abs(want), sd if math.isfinite(sd) else 0.0)
    d = abs(got - want) / scale if scale > 0 else math.inf
    return d if d > 1e-9 and abs(got - want) > 1e-12 * max_abs else None


def main():
    if len(sys.argv) != 3:
        fail_input("usage: arviz_check.py DRAWS.parquet SUMMARY.parquet")
    draws_path, summary_path = sys.argv[1:]
    draws = pd.read_parquet(draws_path)
    summary = pd.read_parquet(summary_path)
    for col in ("run", "draw"):
        if col not in draws.columns:
            fail_input(f"{draws_path}: missing column {col!r}")
    for col in ("parameter",) + STATS:
        if col not in summary.columns:
            fail_input(f"{summary_path}: missing column {col!r}")
    groups = [c for c in GROUP_COLS if c in draws.columns]
    params = [c for c in draws.columns if c not in ("run", "draw") + GROUP_COLS + INDEX_COLS]
    for p in params:
        if not pd.api.types.is_float_dtype(draws[p]):
            fail_input(f"{draws_path}: parameter column {p!r} is {draws[p].dtype}, expected float")

    rows = {}
    for i, r in enumerate(summary.itertuples(index=False)):
        key = (r.parameter,) + tuple(key_part(getattr(r, c, None)) for c in GROUP_COLS)
        # One summary.parquet covers several draw tables (population, boards, joints): only
        # the rows of this table's parameters (with its grouping) are checked, and every one
        # of them must have draws here.
        if r.parameter not in params:
            continue
        if any((key_part(getattr(r, c, None)) is None) == (c in groups) for c in GROUP_COLS if c in groups):
            continue
        if key in rows:
            fail_input(f"{summary_path}: row {i}: duplicate summary for {key}")
        rows[key] = r

    print(f"ArviZ {az.__version__} (numpy {np.__version__})")
    bad, seen = [], set()
    grouped = draws.groupby(groups, dropna=False, sort=True) if groups else [((), draws)]
    for gkey, group in grouped:
        gkey = gkey if isinstance(gkey, tuple) else (gkey,)
        gvals = dict(zip(groups, (key_part(v) for v in gkey)))
        for p in params:
            if group[p].isna().all():
                continue
            key = (p,) + tuple(gvals.get(c) for c in GROUP_COLS)
            where = f"{p} board_id={key[1]} measurement_id={key[2]}"
            x = chains_array(group, p, where)
            if key not in rows:
                bad.append(f"{where}: no row in {summary_path}")
                continue
            seen.add(key)
            ref = reference(x)
            row = rows[key]
            errs = []
            for stat in STATS:
                got = float(getattr(row, stat))
                d = disagreement(stat, got, ref[stat], ref["sd"], float(np.nanmax(np.abs(x))))
                if d is not None:
                    errs.append(f"{stat} hbmu {got!r} vs ArviZ/numpy {ref[stat]!r} (off by {d:.3g})")
            status = "OK  " if not errs else "FAIL"
            print(
                f"{status} {where} chains={x.shape[0]} draws={x.shape[1]} "
                f"r_hat={ref['r_hat']:.6g} ess_bulk={ref['ess_bulk']:.6g} ess_tail={ref['ess_tail']:.6g}"
            )
            bad.extend(f"{where}: {e}" for e in errs)
    for key in rows.keys() - seen:
        bad.append(f"summary row {key} has no draws in {draws_path}")
    if bad:
        print(f"\n{len(bad)} disagreement(s) with ArviZ {az.__version__}:", file=sys.stderr)
        for b in bad:
            print(f"  {b}", file=sys.stderr)
        sys.exit(1)
    print(f"all {len(seen)} quantities agree with ArviZ {az.__version__}")


if __name__ == "__main__":
    main()

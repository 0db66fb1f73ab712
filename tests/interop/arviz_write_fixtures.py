#!/usr/bin/env python3
"""Reference values for hbmu's convergence diagnostics (src/bayes/diagnostics.rs), computed by
the third-party package ArviZ on random draws generated here.

Usage: arviz_write_fixtures.py [--cases-per-kind K] [--seed S]  > fixture.json

Prints one JSON object to stdout:
  {"arviz_version": "...", "numpy_version": "...",
   "normal_quantile": [[p, scipy.special.ndtri(p)], ...],
   "cases": [{"name": "...", "chains": [[draw, ...], ...],
              "r_hat": x, "ess_bulk": x, "ess_tail": x,        # arviz.rhat(method="rank"), arviz.ess(method="bulk"/"tail")
              "mean": x, "sd": x, "q05": x, "q50": x, "q95": x  # numpy mean, std(ddof=1), quantile (linear)
             }, ...]}
Every number is written as the integer bit pattern of its IEEE 754 double (so NaN and
infinities are strict JSON, and the draws reach the Rust test bit for bit whatever the JSON
parser's float rounding).

Kinds of draws (each K times with random sizes): iid normal, AR(1) with strong
autocorrelation, chains with shifted means, heavy tails (Cauchy, Student t3), ties as after
SMC resampling (runs of identical values), coarse rounding (massive ties), odd draw counts,
1 to 4 chains; plus fixed edge cases: constant draws, chains constant within but different
between, fewer than 4 draws, exactly 4 and 5 draws, a NaN draw, infinite draws.
"""
import argparse
import json
import math
import struct
import sys

import arviz as az
import numpy as np
import scipy
from scipy import special

p = argparse.ArgumentParser()
p.add_argument("--cases-per-kind", type=int, default=4)
p.add_argument("--seed", type=int, default=20261122)
p.add_argument("--max-draws", type=int, default=400)
args = p.parse_args()
rng = np.random.default_rng(args.seed)


def enc(x):
    """IEEE 754 bit pattern of x as an unsigned integer."""
    return struct.unpack("<Q", struct.pack("<d", float(x)))[0]


def shape():
    n_chain = int(rng.choice([1, 2, 3, 4]))
    n_draw = int(rng.integers(4, args.max_draws + 1))
    return n_chain, n_draw


def ar1(n_chain, n_draw, phi):
    x = np.empty((n_chain, n_draw))
    x[:, 0] = rng.standard_normal(n_chain) / math.sqrt(1 - phi * phi)
    for d in range(1, n_draw):
        x[:, d] = phi * x[:, d - 1] + rng.standard_normal(n_chain)
    return x


def resampled(n_chain, n_draw):
    """Runs of identical values: each chain a sequence of values each repeated a random count,
    and values shared between chains (a common particle population)."""
    pool = rng.standard_normal(int(rng.integers(5, 60)))
    out = np.empty((n_chain, n_draw))
    for c in range(n_chain):
        d = 0
        while d < n_draw:
            run = int(rng.geometric(rng.uniform(0.05, 0.6)))
            out[c, d : d + run] = pool[rng.integers(len(pool))]
            d += run
    return out


KINDS = {
    "iid_normal": lambda c, n: rng.standard_normal((c, n)) * rng.uniform(0.1, 10) + rng.uniform(-5, 5),
    "ar1_0.9": lambda c, n: ar1(c, n, 0.9),
    "ar1_0.99": lambda c, n: ar1(c, n, 0.99),
    "shifted_means": lambda c, n: rng.standard_normal((c, n)) + rng.uniform(0, 2) * np.arange(c)[:, None],
    "cauchy": lambda c, n: rng.standard_cauchy((c, n)),
    "student_t3": lambda c, n: rng.standard_t(3, (c, n)),
    "resampled_ties": resampled,
    "rounded_ties": lambda c, n: np.round(rng.standard_normal((c, n)), 1),
    "odd_draws": lambda c, n: ar1(c, n | 1, 0.5),
    "four_chains_ar1": lambda c, n: ar1(4, n, 0.8),
    "one_chain_ar1": lambda c, n: ar1(1, n, 0.7),
}

FIXED = {
    "constant": np.full((4, 50), 2.5),
    "constant_within_chains": np.repeat(np.array([[0.0], [1.0], [1.0], [3.0]]), 40, axis=1),
    "three_draws": rng.standard_normal((4, 3)),
    "four_draws": rng.standard_normal((3, 4)),
    "five_draws": rng.standard_normal((2, 5)),
    "nan_draw": np.where(np.arange(200).reshape(2, 100) == 57, np.nan, rng.standard_normal((2, 100))),
    "one_chain_iid": rng.standard_normal((1, 301)),
    "two_values": rng.integers(0, 2, (4, 100)).astype(float),
    "infinite_draw": np.where(np.arange(300).reshape(3, 100) == 123, np.inf, rng.standard_normal((3, 100))),
    "infinite_tail": np.where(rng.uniform(size=(4, 60)) < 0.1, -np.inf, rng.standard_normal((4, 60))),
}


def reference(name, x):
    x = np.asarray(x, dtype=float)
    ds = az.convert_to_dataset({"x": x})  # dims (chain, draw)
    rhat = az.rhat(ds, method="rank")["x"].values
    bulk = az.ess(ds, method="bulk")["x"].values
    tail = az.ess(ds, method="tail")["x"].values
    flat = x.ravel()
    with np.errstate(all="ignore"):
        q = np.quantile(flat, [0.05, 0.5, 0.95])
        sd = np.std(flat, ddof=1)
    return {
        "name": name,
        "chains": [[enc(v) for v in row] for row in x],
        "r_hat": enc(rhat),
        "ess_bulk": enc(bulk),
        "ess_tail": enc(tail),
        "mean": enc(np.mean(flat)),
        "sd": enc(sd),
        "q05": enc(q[0]),
        "q50": enc(q[1]),
        "q95": enc(q[2]),
    }


cases = []
for kind, gen in KINDS.items():
    for i in range(args.cases_per_kind):
        c, n = shape()
        cases.append(reference(f"{kind}#{i}", gen(c, n)))
for name, x in FIXED.items():
    cases.append(reference(name, x))

probs = [1e-300, 1e-20, 1e-10, 1e-5, 0.001, 0.02, 0.075, 0.1, 0.3, 0.5, 0.7, 0.925, 0.95, 0.999, 1 - 1e-12]
probs += list(rng.uniform(0, 1, 30))
json.dump(
    {
        "arviz_version": az.__version__,
        "numpy_version": np.__version__,
        "scipy_version": scipy.__version__,
        "normal_quantile": [[enc(p_), enc(special.ndtri(p_))] for p_ in probs],
        "cases": cases,
    },
    sys.stdout,
)

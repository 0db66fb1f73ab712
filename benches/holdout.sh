#!/usr/bin/env bash
# The out-of-sample test of the new-board prediction (issue 10): leave-one-board-out on the
# lab's null scenario (data/lab/null.toml) under several seeds. Per seed, the campaign goes
# through the DAG up to `pair` once; then, per board, step 1 runs without that board
# (`update boards --hold-out B`), `propagate` predicts a new board, and `report` counts how
# many of the held-out board's free-free measurements lie inside the new board's 90 %
# intervals. A calibrated hierarchy covers about 90 % of them; the same report's in-sample
# count (the other boards against the same interval) is printed beside it, with the rate the
# classical predictive interval gives in-sample for that many boards.
#
# Usage: benches/holdout.sh [SEED...] (default 1 2 3); work directories under
# target/work/null-<seed> (shared with benches/diagnose_null.sh), folds under
# target/work/null-<seed>/holdout/<boards>. HOLDOUT_PARTICLES, HOLDOUT_RUNS (default 200, 2:
# the pipeline's) and HOLDOUT_DRAWS (propagate, default 2000) set the sizes.
# HOLDOUT_N=N runs a free-free campaign of N boards instead (the null scenario's population,
# 5 hammer measurements a board; work directories target/work/null<N>-<seed>), and
# HOLDOUT_GROUP=K holds K boards out per fold (default 1): with many boards the population's
# covariance is learnt well and the held-out coverage should approach 90 %. Extra options of
# `update boards` (e.g. a prior) go in HOLDOUT_UPDATE_ARGS; HOLDOUT_LABEL=X puts the folds
# under holdout-X instead of holdout, so two settings can be kept side by side.
#
# Besides the counts, the summary gives the reference this is judged against: per held-out
# board and mode, the classical prediction interval from the other boards' means of that
# mode, x̄ ± t(0.95, n−1) s √(1 + 1/n), exact for normal board-to-board scatter. Its
# coverage on the same folds says how easy the folds happened to be; the ratio of the
# hierarchy's 90 % half-width to it says how much wider the hierarchy predicts; the PIT
# (the held-out board mean's rank among the new-board draws) should be uniform, and the
# coverage is given at 50, 80 and 90 %.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
seeds=("$@")
if [ ${#seeds[@]} -eq 0 ]; then seeds=(1 2 3); fi
particles=${HOLDOUT_PARTICLES:-200}
runs=${HOLDOUT_RUNS:-2}
draws=${HOLDOUT_DRAWS:-2000}
nboards=${HOLDOUT_N:-}
group=${HOLDOUT_GROUP:-1}
tag=null${nboards}
scenario=${HOLDOUT_SCENARIO:-}
campaign=${HOLDOUT_CAMPAIGN:-}
if [ -n "$scenario" ]; then tag=$(basename "$scenario" .toml); fi
if [ -n "$campaign" ]; then
  campaign=$(cd "$campaign" && pwd)
  tag=$(basename "$(dirname "$campaign")"); seeds=(given)
fi
holdout=holdout${HOLDOUT_LABEL:+-$HOLDOUT_LABEL}
# HOLDOUT_SCENARIO=FILE runs a lab scenario file instead of the null's (its seed and name
# replaced per seed, e.g. data/lab/realistic_null.toml, the independent truth; work
# directories target/work/<file's name>-<seed>), and HOLDOUT_CAMPAIGN=DIR a campaign
# already written (one "seed", `given`: the DAG runs on it as on a user's campaign). Only the
# free-free modes are held out: step 1 predicts a new board, whatever the campaign's bolted
# measurements.
#
# HOLDOUT_BOLTED=1 also runs step 2 per fold (HOLDOUT_JOINTS_ARGS: its extra options, e.g.
# --board) and scores the held-out boards' bolted measurements against the new board's bolted
# prediction (a new board in a new mounting).
#
# HBMU=binary runs that binary (e.g. a frozen copy while the tree is being edited; the
# pipeline's make honours it too); otherwise the tree's debug build, built first.
if [ -n "${HBMU:-}" ]; then
  hbmu=$HBMU
  export HBMU
else
  make -C "$root/pipelines" --no-print-directory build >/dev/null
  hbmu=$root/target/debug/hbmu
fi
# The pipeline's model cache: the folds share the campaign's ROM instead of building it each.
export HBMU_CACHE=${HBMU_CACHE-$root/target/cache}
for s in "${seeds[@]}"; do
  work=$root/target/work/$tag-$s
  mkdir -p "$work"
  input=(SCENARIO="$work/scenario.toml")
  if [ -n "$campaign" ]; then
    input=(CAMPAIGN="$campaign")
  elif [ -n "$scenario" ]; then
    sed -E "s/^seed = .*/seed = $s/; s/^name = .*/name = \"$tag-$s\"/" "$scenario" > "$work/scenario.toml"
  elif [ -z "$nboards" ]; then
    sed -E "s/^seed = .*/seed = $s/; s/^name = .*/name = \"null-$s\"/" "$root/data/lab/null.toml" > "$work/scenario.toml"
  else
    cat > "$work/scenario.toml" <<EOF
name = "$tag-$s"
description = "hold-out bench: $nboards boards of the null scenario's population, free-free only"
seed = $s

[campaign]
n_boards = $nboards
free_per_board = 5
bolted = []
EOF
  fi
  make -C "$root/pipelines" --no-print-directory all "${input[@]}" WORK="$work" > "$work/make-holdout.log" 2>&1 || {
    echo "seed $s: pipeline failed (see $work/make-holdout.log)"; tail -5 "$work/make-holdout.log"; continue; }
  boards=$(python3 -c "import pandas as pd, sys; print(' '.join(sorted(pd.read_parquet(sys.argv[1]).query('setup == \"free\"').board_id.unique())))" "$work/pair/pairs.parquet")
  # Folds of $group boards each, in id order.
  folds=$(python3 -c "import sys; b = sys.argv[2:]; k = int(sys.argv[1]); print(' '.join(','.join(b[i:i + k]) for i in range(0, len(b), k)))" "$group" $boards)
  for b in $folds; do
    f=$work/$holdout/$b
    mkdir -p "$f"
    for d in ingest extract pair; do ln -sfn "$work/$d" "$f/$d"; done
    SECONDS=0
    "$hbmu" update boards "$f/ingest" "$f/pair" --extract "$f/extract" --particles "$particles" --runs "$runs" \
      --seed 20261122 --rom-basis 30 --hold-out "$b" ${HOLDOUT_UPDATE_ARGS:-} --out "$f/update_boards" > "$f/log" 2>&1
    joints=()
    if [ -n "${HOLDOUT_BOLTED:-}" ]; then
      # Step 2 without the held-out board (it has no step-1 posterior: its bolted
      # measurements are left out, and the report compares them with the new board's
      # bolted prediction, a new board in a new mounting).
      "$hbmu" update joints "$f/ingest" "$f/pair" --extract "$f/extract" --boards "$f/update_boards" \
        --particles "$particles" --runs "$runs" --seed 20261122 ${HOLDOUT_JOINTS_ARGS:-} \
        --out "$f/update_joints" >> "$f/log" 2>&1
      joints=("$f/update_joints")
    fi
    "$hbmu" propagate "$f/update_boards" "${joints[@]}" --fe "$work/fe" --draws "$draws" --out "$f/propagate" >> "$f/log" 2>&1
    "$hbmu" report "$f" --out "$f/report" >> "$f/log" 2>&1
    echo "seed $s board $b: $(grep -o 'free-free coverage.*' "$f/log" | head -1) (${SECONDS} s)"
  done
done
python3 - "$root/target/work" "$tag" "$holdout" "${seeds[@]}" <<'PY'
import json, sys, math
from pathlib import Path
import numpy as np
import pandas as pd
from scipy import stats
base, tag, holdout, seeds = Path(sys.argv[1]), sys.argv[2], sys.argv[3], sys.argv[4:]
held = [0, 0]
ins = [0, 0]
per_board = []
nb = set()
for s in seeds:
    folds = sorted((base / f"{tag}-{s}" / holdout).glob("*"))
    n_all = sum(len(f.name.split(",")) for f in folds)
    for f in folds:
        m = json.loads((f / "report" / "report.manifest.json").read_text())
        summ = m.get("summary", {})
        h = summ.get("held_out_coverage_free")
        n = summ.get("new_board_coverage_free")
        if not h:
            print(f"{f}: no held-out coverage in the report's manifest"); continue
        held[0] += h[0]; held[1] += h[1]
        ins[0] += n[0]; ins[1] += n[1]
        per_board.append(h[0] == h[1])
        nb.add(n_all - len(f.name.split(",")))
k, n = held
p = stats.binomtest(k, n, 0.9).pvalue if n else float("nan")
print(f"held-out boards: {k}/{n} measurements inside the new board's 90 % interval ({100 * k / max(n, 1):.1f} %, binomial p = {p:.3g} against 90 %; measurements of a board are not independent)")
print(f"  folds with every held-out measurement inside: {sum(per_board)}/{len(per_board)}")
print(f"in-sample (the other boards, same intervals): {ins[0]}/{ins[1]} ({100 * ins[0] / max(ins[1], 1):.1f} %)")
# Bolted (HOLDOUT_BOLTED=1): the held-out boards' bolted measurements against the new board's
# bolted 90 % interval (report/intervals.parquet), per label.
bolted = []
for s in seeds:
    for f in sorted((base / f"{tag}-{s}" / holdout).glob("*")):
        p = f / "report" / "intervals.parquet"
        if (f / "update_joints").is_dir() and p.exists():
            iv = pd.read_parquet(p)
            bolted.append(iv[(iv.scope == "new_board") & (iv.setup == "bolted")])
if bolted:
    b = pd.concat(bolted).groupby("label")[["n_held_out", "n_held_out_inside_90"]].sum()
    k, n = int(b.n_held_out_inside_90.sum()), int(b.n_held_out.sum())
    p = stats.binomtest(k, n, 0.9).pvalue if n else float("nan")
    print(f"held-out boards, bolted: {k}/{n} measurements inside the new board's bolted 90 % interval ({100 * k / max(n, 1):.1f} %, binomial p = {p:.3g}); per label:")
    for lab, r in b.iterrows():
        print(f"  {lab}: {int(r.n_held_out_inside_90)}/{int(r.n_held_out)}")
for m in sorted(nb):
    t = stats.t.ppf(0.95, m - 1)
    z = t * t * (m + 1) / (m - 1) ** 2
    print(f"  classical in-sample rate for {m} boards: {100 * (1.0 if z >= 1 else stats.beta.cdf(z, 0.5, (m - 2) / 2)):.1f} %")
# Against the classical prediction interval, per held-out board and mode (board means).
rows = []
for s in seeds:
    work = base / f"{tag}-{s}"
    pairs = pd.read_parquet(work / "pair" / "pairs.parquet")
    pairs = pairs[pairs.setup == "free"]
    if "accepted" in pairs:
        pairs = pairs[pairs.accepted]
    for f in sorted((work / holdout).glob("*")):
        held = f.name.split(",")
        pr = pd.read_parquet(f / "propagate" / "predictions.parquet")
        nb = pr[(pr.scope == "new_board") & (pr.setup == "free")]
        for lab, g in nb.groupby("label"):
            d = np.sort(g.freq_hz.values)
            bm = pairs[pairs.label == lab].groupby("board_id").freq_hz.mean()
            ins = bm[~bm.index.isin(held)]
            n = len(ins)
            if n < 3:
                continue
            half = stats.t.ppf(0.95, n - 1) * ins.std(ddof=1) * math.sqrt(1 + 1 / n)
            ours = (np.quantile(d, 0.95) - np.quantile(d, 0.05)) / 2
            for b in held:
                if b in bm:
                    y = bm[b]
                    rows.append(dict(pit=np.searchsorted(d, y) / len(d), ratio=ours / half,
                                     classical=abs(y - ins.mean()) <= half))
if rows:
    df = pd.DataFrame(rows)
    cov = lambda lv: ((df.pit >= (1 - lv) / 2) & (df.pit <= (1 + lv) / 2)).mean()
    print(f"per held-out board and mode ({len(df)}): coverage 50 % {100 * cov(0.5):.1f} %, 80 % {100 * cov(0.8):.1f} %, 90 % {100 * cov(0.9):.1f} %")
    print(f"  classical prediction interval (90 %) on the same folds: {100 * df.classical.mean():.1f} %")
    print(f"  hierarchy's 90 % half-width / classical: median {df.ratio.median():.3f} (range {df.ratio.min():.3f}-{df.ratio.max():.3f})")
    print(f"  PIT in tenths: {np.histogram(df.pit, bins=10, range=(0, 1))[0].tolist()}")
PY

#!/usr/bin/env bash
# Issue 50's re-proof on the solid truth: for each scenario (default: realistic_null and
# realistic_paper), the campaign and the stages before the updating at the DAG's defaults, then
# both updating steps at 2000 particles × 4 runs, propagation, the report and the blind
# diagnosis with one refit, in target/work/reproof-<scenario>. Prints per scenario: wall times
# and sampler diagnostics of both steps, benches/recovery.py (the solid truth's drawn values
# inside the 90 % intervals, the Table-2 analog), the 90 % coverage per setup and mode (own
# board and new board), and the diagnosis's verdict. Needs gmsh and ccx.
# Usage: benches/reproof.sh [SCENARIO|SCENARIO_FILE...]
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
hbmu=${HBMU:-$root/target/debug/hbmu}
names=("$@")
if [ ${#names[@]} -eq 0 ]; then names=(realistic_null realistic_paper); fi
mkdir -p "$root/target/work"
for s in "${names[@]}"; do
  # A built-in name or a scenario file (e.g. a null under another seed).
  w=$root/target/work/reproof-$(basename "$s" .toml)
  echo "== $s ($w)"
  make -C "$root/pipelines" --no-print-directory prepare SCENARIO="$s" WORK="$w" > "$w.prepare.log" 2>&1 \
    || { echo "prepare failed, see $w.prepare.log"; continue; }
  /usr/bin/env time -f "boards: %e s wall, %U s user" "$hbmu" update boards "$w/ingest" "$w/pair" \
    --extract "$w/extract" --particles 2000 --runs 4 --seed 20261122 --out "$w/update_boards" --force 2>&1 \
    | grep -E "^update|wall|^error"
  /usr/bin/env time -f "joints: %e s wall, %U s user" "$hbmu" update joints "$w/ingest" "$w/pair" \
    --extract "$w/extract" --boards "$w/update_boards" --particles 2000 --runs 4 --seed 20261122 \
    --out "$w/update_joints" --force 2>&1 | grep -E "^update|wall|^error"
  "$hbmu" propagate "$w/update_boards" "$w/update_joints" --draws 4000 --seed 20261122 \
    --out "$w/propagate" --force > /dev/null 2>&1
  "$hbmu" report "$w" --out "$w/report" --force 2>&1 | grep -E "^report"
  python3 "$root/benches/recovery.py" "$w" | grep -vE "outside \["
  python3 - "$w/report/intervals.parquet" <<'PY'
import sys
import pandas as pd
d = pd.read_parquet(sys.argv[1])
g = d.groupby(["scope", "setup", "label"])[["n_measured", "n_inside_90"]].sum()
print("90 % coverage (inside/measured) per scope, setup and mode:")
print(g.to_string())
PY
  /usr/bin/env time -f "diagnose: %e s wall" "$hbmu" diagnose "$w" --out "$w/diagnose" --max-refits 1 --force 2>&1 \
    | grep -E "^diagnose|wall|^warning" | cut -c1-600
done

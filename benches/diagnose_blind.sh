#!/usr/bin/env bash
# Blind discovery: each concealed-effect scenario of the virtual lab (data/lab/<name>.toml)
# through the whole DAG up to `diagnose`, which is told nothing about the scenario. Afterwards,
# and only then, this script reads the lab's truth.json (kept outside the campaign) and scores
# the diagnosis against the issue's acceptance: the right mechanism first, its joint /
# location (within 10 mm) / covariate, a 90 % interval that covers the true parameter, and a
# held-out mean absolute frequency error at least 2x smaller.
#
# Usage: benches/diagnose_blind.sh [SCENARIO...]   (a built-in name or a scenario file such as
# benches/scenarios/mass_and_temperature.toml; default: the five effect scenarios and
# underfill, the effect kept out of the library)
# Env: REFITS (candidate refits per diagnosis, default 3). Work dirs: target/work/blind-<name>.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
scen=("$@")
if [ ${#scen[@]} -eq 0 ]; then scen=(rotational loose_bolt temperature lumped_mass fixture underfill); fi
refits=${REFITS:-3}
for s in "${scen[@]}"; do
  # A built-in name (data/lab/<name>.toml) or a scenario file's path.
  src=$root/data/lab/$s.toml
  if [ -f "$s" ]; then src=$s; s=$(basename "$s" .toml); fi
  work=$root/target/work/blind-$s
  mkdir -p "$work"
  cp "$src" "$work/scenario.toml"
  start=$(date +%s)
  make -C "$root/pipelines" --no-print-directory all update-boards update-joints diagnose \
    SCENARIO="$work/scenario.toml" WORK="$work" DIAGNOSE_REFITS="$refits" > "$work/make.log" 2>&1 || {
    echo "$s: pipeline failed (see $work/make.log)"; tail -5 "$work/make.log"; continue; }
  python3 "$root/benches/score_diagnosis.py" "$work" "$s" "$(( $(date +%s) - start ))"
done

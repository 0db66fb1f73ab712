#!/usr/bin/env bash
# Issue 9's recovery check on campaigns whose measurement chain the step-1 likelihood
# describes exactly: the lab's truth model on the updating model's own free-free mesh (the
# board file's [mesh], 56 x 35 for the shipped board), so no discretization error is shared
# by the boards, and the update told that the balance readings carry no buoyancy or
# calibration error (`--balance-bias 0`; the virtual lab's balance has neither) and that the
# model is exact (`--no-model-error`). On campaigns with the lab's finer truth mesh the
# boards share the model's discretization error, and per-board coverage is then all or none
# per parameter whatever the intervals (see the closing notes of issue 9).
#
# Usage: benches/recovery_exact.sh [SCENARIO...]   (default: null seeds 1 2 3 and paper)
#   a SCENARIO is null-<seed> or paper; work directories under target/work/exact-<name>.
# Prints the update's summary line per campaign, then benches/recovery.py over all of them
# (coverage of the 90 % intervals with binomial p-values, Table-2 analog, R-hat, log Z spread).
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
hbmu=${HBMU:-$root/target/debug/hbmu}
names=("$@")
if [ ${#names[@]} -eq 0 ]; then names=(null-1 null-2 null-3 paper); fi
read -r nx ny < <(python3 -c "
import sys, tomllib
m = tomllib.load(open('$root/data/boards/default.toml', 'rb'))['mesh']
print(m['nx'], m['ny'])")
dirs=()
for n in "${names[@]}"; do
  work=$root/target/work/exact-$n
  mkdir -p "$work"
  case $n in
    null-*) s=${n#null-}
            sed -E "s/^seed = .*/seed = $s/; s/^name = .*/name = \"exact-$n\"/" "$root/data/lab/null.toml" > "$work/scenario.toml" ;;
    paper)  sed -E "s/^name = .*/name = \"exact-paper\"/" "$root/data/lab/paper.toml" > "$work/scenario.toml" ;;
    *) echo "unknown scenario $n (null-<seed> or paper)"; exit 2 ;;
  esac
  printf '\n[truth]\nmesh_nx = %s\nmesh_ny = %s\n' "$nx" "$ny" >> "$work/scenario.toml"
  make -C "$root/pipelines" --no-print-directory lab ingest extract pair \
    SCENARIO="$work/scenario.toml" WORK="$work" HBMU="$hbmu" > "$work/make.log" 2>&1 || {
    echo "$n: pipeline failed (see $work/make.log)"; tail -5 "$work/make.log"; continue; }
  start=$(date +%s.%N)
  "$hbmu" update boards "$work/ingest" "$work/pair" --extract "$work/extract" \
    --particles 2000 --runs 4 --no-model-error --balance-bias 0 \
    --out "$work/update_boards" --force > "$work/update_boards.log" 2>&1 || {
    echo "$n: update boards failed (see $work/update_boards.log)"; tail -5 "$work/update_boards.log"; continue; }
  echo "$n: $(tail -1 "$work/update_boards.log") [wall $(python3 -c "print(f'{$(date +%s.%N) - $start:.1f}')") s]"
  dirs+=("$work")
done
python3 "$root/benches/recovery.py" "${dirs[@]}"

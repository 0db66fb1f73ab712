#!/usr/bin/env bash
# Step-1 cost against the number of boards (issue 9): virtual-lab campaigns of N nominally
# identical boards (the null scenario's physics, free-free only, 5 hammer measurements per
# board), each taken through lab → ingest → extract → pair by the pipeline, then `hbmu update
# boards` at PARTICLES × RUNS on the machine's cores, timed. Prints wall and CPU seconds, the
# sampler's own diagnostics per N, and the least-squares exponent b of wall ∝ N^b (near-linear
# is the target: boards are conditionally independent given the hyperparameters).
#
# Usage: benches/scaling.sh [PARTICLES [RUNS [N ...]]]   (defaults: 2000 4 7 30 99; 99 is the
# lab's largest campaign). Work directories: $HBMU_SCALING_DIR (default target/work/scaling).
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
particles=${1:-2000}
runs=${2:-4}
shift $(( $# < 2 ? $# : 2 ))
ns=("$@")
if [ ${#ns[@]} -eq 0 ]; then ns=(7 30 99); fi
work=${HBMU_SCALING_DIR:-$root/target/work/scaling}
mkdir -p "$work"
make -C "$root/pipelines" --no-print-directory build >/dev/null
hbmu=${HBMU:-$root/target/debug/hbmu}
results=()
for n in "${ns[@]}"; do
  scen="$work/boards-$n.toml"
  cat > "$scen" <<EOF
name = "boards-$n"
description = "scaling bench: $n boards, free-free only, no concealed effect"
seed = 20240601

[campaign]
n_boards = $n
free_per_board = 5
bolted = []
EOF
  w="$work/boards-$n"
  make -C "$root/pipelines" --no-print-directory pair SCENARIO="$scen" WORK="$w" HBMU="$hbmu" >/dev/null
  out="$w/update_boards_bench"
  rm -rf "$out"
  /usr/bin/env time -f "%e %U %S %M" -o "$w/time.txt" \
    "$hbmu" update boards "$w/ingest" "$w/pair" --extract "$w/extract" \
    --particles "$particles" --runs "$runs" --rom-basis 30 --out "$out" >/dev/null
  read -r wall user sys rss < "$w/time.txt"
  sampler=$(python3 -c 'import json,sys; print(json.load(open(sys.argv[1]))["summary"]["sampler_seconds"])' "$out/update_boards.manifest.json")
  python3 - "$out/update_report.json" "$n" "$wall" "$user" "$sys" "$rss" "$sampler" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
n, wall, user, sys_s, rss, sampler = sys.argv[2:]
ev = d["evidence"]["log_evidence_runs"]
print(f"{n} boards: {float(wall):.1f} s wall (sampler {float(sampler):.1f} s), "
      f"{float(user) + float(sys_s):.1f} s CPU, "
      f"{int(rss) / 1024:.0f} MB max RSS; stages per run {d['stages_per_run']}, "
      f"max R-hat {d['max_r_hat']:.4f}, min ESS {d['min_ess']:.0f}, "
      f"log evidence runs {[round(x, 2) for x in ev]}")
PY
  results+=("$n $wall $sampler")
done
printf '%s\n' "${results[@]}" | python3 -c '
import math, sys
rows = [tuple(map(float, l.split())) for l in sys.stdin if l.strip()]
def exponent(col):
    xs = [math.log(r[0]) for r in rows]
    ys = [math.log(r[col]) for r in rows]
    mx, my = sum(xs) / len(xs), sum(ys) / len(ys)
    return sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sum((x - mx) ** 2 for x in xs)
if len(rows) >= 2:
    ns = [int(r[0]) for r in rows]
    print(f"fitted exponent over {ns} boards: wall ∝ boards^{exponent(1):.2f}, sampler ∝ boards^{exponent(2):.2f}")
'

#!/usr/bin/env bash
# Fan-out and gather: run independent pieces of one stage as tasks, wait for all of them.
#
#   fanout.sh SCHEDULER NAME N LOG_DIR 'SBATCH FLAGS' -- COMMAND ARG...
#
# runs COMMAND N times; in its arguments every `{task}` becomes the task index 0..N-1, and
# HBMU_TASK / HBMU_TASKS are set in its environment. SCHEDULER `local`: the tasks one after
# another on this machine (each uses its cores through its own threads). SCHEDULER `slurm`:
# one job array (`sbatch --wait --array=0-(N-1)`) with the stage's resources as FLAGS, one log
# per task in LOG_DIR/NAME-<task>.log. Returns when every task has ended. Exit status: 0 when
# all tasks exited 0; 3 when all exited 0 or 3 (some measurements quarantined); otherwise 1,
# naming the tasks that failed or never finished (cancelled, killed, timed out). The gather is
# the stage's next command, which reads the tasks' outputs; a task that is itself a hashed
# `hbmu` stage is skipped when a rerun finds it up to date, so a rerun after a cancel redoes
# only the tasks that did not finish.
set -uo pipefail

if [ "${1:-}" = --task ]; then
  # One task: fanout.sh --task ARGS_FILE STATUS_DIR [INDEX] (INDEX defaults to Slurm's).
  args_file=$2 status_dir=$3 index=${4:-${SLURM_ARRAY_TASK_ID:?no task index}}
  mapfile -d '' argv < "$args_file"
  HBMU_TASKS=${argv[0]}
  cmd=()
  for a in "${argv[@]:1}"; do cmd+=("${a//\{task\}/$index}"); done
  HBMU_TASK=$index HBMU_TASKS=$HBMU_TASKS "${cmd[@]}"
  status=$?
  echo "$status" > "$status_dir/.task-$index.status.tmp" &&
    mv "$status_dir/.task-$index.status.tmp" "$status_dir/task-$index.status"
  exit "$status"
fi

[ $# -ge 7 ] && [ "$6" = -- ] || {
  echo "usage: fanout.sh SCHEDULER NAME N LOG_DIR 'SBATCH FLAGS' -- COMMAND ARG..." >&2
  exit 2
}
scheduler=$1 name=$2 n=$3 log_dir=$4 flags=$5
shift 6
[[ "$n" =~ ^[1-9][0-9]*$ ]] || { echo "fanout.sh: task count must be a positive integer, got '$n'" >&2; exit 2; }
mkdir -p "$log_dir"
run_dir=$(mktemp -d "$log_dir/.$name.fanout.XXXXXX")
trap 'rm -rf "$run_dir"' EXIT
printf '%s\0' "$n" "$@" > "$run_dir/args"
self=$(cd "$(dirname "$0")" && pwd)/$(basename "$0")

case $scheduler in
  local)
    for ((t = 0; t < n; t++)); do
      "$self" --task "$run_dir/args" "$run_dir" "$t" > "$log_dir/$name-$t.log" 2>&1
    done
    ;;
  slurm)
    # shellcheck disable=SC2086 # FLAGS are words on purpose
    sbatch --wait --quiet --array=0-$((n - 1)) --job-name="$name" \
      --output="$log_dir/$name-%a.log" $flags "$self" --task "$run_dir/args" "$run_dir"
    ;;
  *) echo "fanout.sh: SCHEDULER must be local or slurm, got '$scheduler'" >&2; exit 2 ;;
esac

worst=0 failed=""
for ((t = 0; t < n; t++)); do
  s=$(cat "$run_dir/task-$t.status" 2>/dev/null || echo unfinished)
  case $s in
    0) ;;
    3) [ "$worst" -ne 0 ] || worst=3 ;;
    *) failed="$failed $t($s)"; worst=1 ;;
  esac
done
if [ -n "$failed" ]; then
  echo "fanout $name: tasks failed or unfinished:$failed (logs: $log_dir/$name-<task>.log)" >&2
fi
exit "$worst"

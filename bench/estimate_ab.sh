#!/usr/bin/env bash
# Side-by-side timing of `hydrolens estimate` binaries (e.g. before and after a change), alternating runs so that the
# machine's drift hits all alike. Each run writes a new file. Prints the median wall time (bash's clock) and the
# median CPU time (`perf stat -e task-clock`, ms) of each binary. Not part of CI (README "Benchmarks").
#   usage: bench/estimate_ab.sh REC.csv RUNS BIN...      environment: METHOD (rls-sgd), MODEL (config/plant.toml),
#   REPLACE=1: each run replaces the output of the run before, written a moment earlier, instead of a new file
set -euo pipefail
REC=$1
RUNS=$2
shift 2
MODEL=${MODEL:-config/plant.toml}
METHOD=${METHOD:-rls-sgd}
OUT=$(mktemp -d)
trap 'rm -rf "$OUT"' EXIT
declare -A WALL CPU
median() { tr ' ' '\n' | grep -v '^$' | sort -g | awk '{a[NR]=$1} END {print a[int((NR+1)/2)]}'; }
for _ in $(seq "$RUNS"); do
  for bin in "$@"; do
    # in the page cache before each run: this guest drops file pages idle for a minute (DAMON reclaim)
    cat "$REC" >/dev/null
    [[ ${REPLACE:-0} == 1 ]] || rm -f "$OUT/est.csv"
    cpu=$(timeout 300 perf stat -x, -e task-clock "$bin" estimate "$REC" --model "$MODEL" --method "$METHOD" \
      --out "$OUT/est.csv" 2>&1 >/dev/null | grep task-clock | cut -d, -f1)
    [[ ${REPLACE:-0} == 1 ]] || rm -f "$OUT/est.csv"
    t0=$EPOCHREALTIME
    timeout 300 "$bin" estimate "$REC" --model "$MODEL" --method "$METHOD" --out "$OUT/est.csv" >/dev/null 2>&1
    t1=$EPOCHREALTIME
    WALL[$bin]+="$(awk -v a="$t0" -v b="$t1" 'BEGIN { printf "%.4f", b - a }') "
    CPU[$bin]+="$cpu "
  done
done
for bin in "$@"; do
  echo "$bin wall_s=$(median <<<"${WALL[$bin]}") cpu_ms=$(median <<<"${CPU[$bin]}")"
done

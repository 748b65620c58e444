#!/usr/bin/env bash
# Side-by-side timing of `hydrolens estimate` binaries (e.g. before and after a change), alternating runs so that the
# machine's drift hits all alike. Each run writes a new file. Prints the median wall time (bash's clock), rows a
# second and the median CPU time (`perf stat -e task-clock`, ms) of each binary. With PADASIP_PYTHON (a python with
# numpy and padasip, bench/requirements.txt) each round also times padasip on the same job (bench/padasip_rls.py: load
# the CSV, FilterRLS, write the estimates; its own clock) and prints each binary's ratio to it. Not part of CI.
#   usage: bench/estimate_ab.sh REC.csv RUNS BIN...      environment: METHOD (rls-sgd), MODEL (config/plant.toml),
#   PADASIP_PYTHON; REPLACE=1: each run replaces the output of the run before, written a moment earlier
set -euo pipefail
REC=$1
RUNS=$2
shift 2
MODEL=${MODEL:-config/plant.toml}
METHOD=${METHOD:-rls-sgd}
OUT=$(mktemp -d)
trap 'rm -rf "$OUT"' EXIT
declare -A WALL CPU
PADASIP=""
median() { tr ' ' '\n' | { grep -v '^$' || true; } | sort -g | awk '{a[NR]=$1} END {print a[int((NR+1)/2)]}'; }
rows=$(($(wc -l <"$REC") - 1))
for _ in $(seq "$RUNS"); do
  if [[ -n ${PADASIP_PYTHON:-} ]]; then
    cat "$REC" >/dev/null
    line=$(timeout 900 "$PADASIP_PYTHON" "$(dirname "$0")/padasip_rls.py" "$REC" 1 "$OUT/padasip.csv")
    rm -f "$OUT/padasip.csv"
    PADASIP+="$(sed -n 's/.* job_s=\([^ ]*\).*/\1/p' <<<"$line") "
  fi
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
pad=$(median <<<"$PADASIP")
[[ -n $pad ]] && echo "padasip job_s=$pad rows_per_s=$(awk -v n="$rows" -v s="$pad" 'BEGIN { printf "%.0f", n / s }')"
for bin in "$@"; do
  wall=$(median <<<"${WALL[$bin]}")
  line="$bin wall_s=$wall rows_per_s=$(awk -v n="$rows" -v s="$wall" 'BEGIN { printf "%.0f", n / s }')"
  line+=" cpu_ms=$(median <<<"${CPU[$bin]}")"
  [[ -n $pad ]] && line+=" vs_padasip=$(awk -v a="$pad" -v b="$wall" 'BEGIN { printf "%.1f", a / b }')x"
  echo "$line"
done

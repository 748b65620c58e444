#!/usr/bin/env bash
# Runs hydrolens side by side with the Python peers a user might reach for, on this machine, and prints one markdown
# table. Idempotent; every step is bounded by `timeout`. Not part of CI (README "Benchmarks").
#   (a) Modbus: one read of 6 input registers, tokio-modbus (benches/modbus.rs) vs pymodbus, same `hydrolens sim`
#   (b) estimation: `hydrolens estimate` vs padasip's RLS on the same 60 s recording
#   (c) analysis: `hydrolens analyze` vs PySINDy on the same recording
#   (d) HTTP: wrk on /api/status of `hydrolens demo`
# Environment: REQUESTS (Modbus requests per run, 5000), ROUNDS (alternating runs per client, 3),
# REPEATS (timed runs of each offline tool, 3), DURATION_S (recording length, 60),
# HYDROLENS_BIN (the binary to measure, target/release/hydrolens). A failed run of ours counts as nan.
set -euo pipefail
cd "$(dirname "$0")/.."
REQUESTS=${REQUESTS:-5000}
ROUNDS=${ROUNDS:-3}
REPEATS=${REPEATS:-3}
DURATION_S=${DURATION_S:-60}
WORK=bench/.work
VENV=bench/.venv
BIN=${HYDROLENS_BIN:-target/release/hydrolens}
mkdir -p "$WORK"
RESULTS="$WORK/results.md"
: >"$RESULTS"
PIDS=()
cleanup() {
  for pid in "${PIDS[@]}"; do kill "$pid" 2>/dev/null || true; done
  for pid in "${PIDS[@]}"; do wait "$pid" 2>/dev/null || true; done
}
trap cleanup EXIT

say() { echo "peers: $*" >&2; }
row() { echo "| $1 | $2 | $3 | $4 |" >>"$RESULTS"; }
# field NAME LINE: the value of NAME=… in a result line
field() { sed -n "s/.*[[:space:]]$1=\([^[:space:]]*\).*/\1/p" <<<"$2" | head -n1; }
median() { sort -g | awk '{a[NR]=$1} END {if (NR == 0) print "nan"; else if (NR % 2) print a[(NR+1)/2]; else print (a[NR/2]+a[NR/2+1])/2}'; }
# seconds of wall time a command takes (its output to $WORK/last.log)
wall_s() {
  local t0 t1
  t0=$(date +%s.%N)
  timeout 120 "$@" >"$WORK/last.log" 2>&1 || return 1
  t1=$(date +%s.%N)
  awk -v a="$t0" -v b="$t1" 'BEGIN { printf "%.3f", b - a }'
}
ratio() { awk -v a="$1" -v b="$2" 'BEGIN { if (a + 0 == 0 || b + 0 == 0) print "n/a"; else printf "%.1f×", a / b }'; }
free_port() { "$VENV/bin/python" -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
has_command() { timeout 10 "$BIN" "$1" --help >/dev/null 2>&1; }

say "building the release binary and the Modbus bench"
timeout 1200 cargo build --release --locked --quiet
timeout 1200 cargo bench --locked --quiet --bench modbus --no-run 2>/dev/null

if [ ! -x "$VENV/bin/python" ]; then
  say "creating $VENV"
  python3 -m venv "$VENV"
fi
if ! cmp -s bench/requirements.txt "$VENV/.installed" 2>/dev/null; then
  say "installing the Python peers (bench/requirements.txt)"
  timeout 900 "$VENV/bin/pip" install --quiet --disable-pip-version-check -r bench/requirements.txt
  cp bench/requirements.txt "$VENV/.installed"
fi
PY="$VENV/bin/python"

REC="$WORK/rec${DURATION_S}s.csv"
if [ ! -s "$REC" ]; then
  say "recording: simulate ${DURATION_S} s"
  timeout 120 "$BIN" simulate --model config/plant.toml --duration "$DURATION_S" --seed 1 --out "$REC" 2>/dev/null
fi
ROWS=$(($(wc -l <"$REC") - 1))

# (a) Modbus round trip against one `hydrolens sim`, the two clients alternating
PORT=$(free_port)
"$BIN" sim --model config/plant.toml --listen "127.0.0.1:$PORT" >"$WORK/sim.log" 2>&1 &
PIDS+=($!)
for _ in $(seq 100); do
  grep -q "plant simulator on" "$WORK/sim.log" && break
  sleep 0.1
done
say "Modbus: $ROUNDS rounds of $REQUESTS reads per client against 127.0.0.1:$PORT"
: >"$WORK/modbus.txt"
for round in $(seq "$ROUNDS"); do
  HYDROLENS_BENCH_ADDR="127.0.0.1:$PORT" HYDROLENS_BENCH_REQUESTS="$REQUESTS" \
    timeout 120 cargo bench --locked --quiet --bench modbus -- modbus_read6 2>/dev/null | grep modbus_read6 >>"$WORK/modbus.txt"
  timeout 120 "$PY" bench/modbus_latency.py 127.0.0.1 "$PORT" "$REQUESTS" >>"$WORK/modbus.txt"
  say "  round $round done"
done
HYDROLENS_BENCH_REQUESTS="$REQUESTS" timeout 120 cargo bench --locked --quiet --bench modbus -- modbus_read6 2>/dev/null \
  | grep modbus_read6 >>"$WORK/modbus.txt"
kill "${PIDS[-1]}" 2>/dev/null || true
wait "${PIDS[-1]}" 2>/dev/null || true
cat "$WORK/modbus.txt" >&2
for q in p50 p99; do
  rust=$(grep 'rust-tokio-modbus simulator=external' "$WORK/modbus.txt" | while read -r l; do field ${q}_us "$l"; done | median)
  py=$(grep 'python-pymodbus' "$WORK/modbus.txt" | while read -r l; do field ${q}_us "$l"; done | median)
  row "Modbus read of 6 input registers, $q (µs), median of $ROUNDS alternating runs × $REQUESTS" \
    "$rust (tokio-modbus)" "$py (pymodbus)" "$(ratio "$py" "$rust") (peer ÷ ours)"
done
inproc=$(grep 'simulator=in-process' "$WORK/modbus.txt" | tail -n1)
row "Modbus read of 6, simulator in the same process (µs)" \
  "p50 $(field p50_us "$inproc"), p99 $(field p99_us "$inproc")" "—" "—"

# (b) estimation: padasip's RLS vs `hydrolens estimate`
say "padasip RLS on $ROWS rows"
pad=$(timeout 300 "$PY" bench/padasip_rls.py "$REC" "$REPEATS")
echo "$pad" >&2
pad_rps=$(field rows_per_s "$pad")
if has_command estimate; then
  times=()
  for _ in $(seq "$REPEATS"); do
    times+=("$(wall_s "$BIN" estimate "$REC" --model config/plant.toml --out "$WORK/est.csv" || echo nan)")
  done
  est_s=$(printf '%s\n' "${times[@]}" | grep -v nan | median)
  ours_rps=$(awk -v n="$ROWS" -v s="$est_s" 'BEGIN { if (s + 0 > 0) printf "%.0f", n / s; else print "failed" }')
  row "RLS on a ${DURATION_S} s recording, rows/s end to end incl. CSV (median of $REPEATS)" \
    "$ours_rps (hydrolens estimate)" "$pad_rps (padasip FilterRLS, numpy.loadtxt)" "$(ratio "$ours_rps" "$pad_rps") (ours ÷ peer)"
else
  row "RLS on a ${DURATION_S} s recording, rows/s end to end incl. CSV (median of $REPEATS)" \
    "not available yet (no \`estimate\`)" "$pad_rps (padasip FilterRLS, numpy.loadtxt)" "—"
fi
row "padasip RLS alone (CSV load excluded), rows/s" "—" "$(field rls_rows_per_s "$pad")" "—"

# (c) analysis: PySINDy vs `hydrolens analyze`
say "PySINDy on $ROWS rows"
sindy=$(timeout 300 "$PY" bench/pysindy_fit.py "$REC" "$REPEATS")
echo "$sindy" >&2
while read -r line; do
  eq=$(sed -n 's/.*equation="\(.*\)"/\1/p' <<<"$line")
  row "PySINDy fit (STLSQ) of omega' on ω, $(field inputs "$line"), sign(ω), 1: s, median of $REPEATS" "—" \
    "$(field fit_s "$line") s (+ $(field load_s "$line") s numpy.loadtxt): \`$eq\`" "—"
done <<<"$sindy"
if has_command analyze; then
  times=()
  for _ in $(seq "$REPEATS"); do
    times+=("$(wall_s "$BIN" analyze "$REC" --model config/plant.toml --json "$WORK/analysis.json" || echo nan)")
  done
  an_s=$(printf '%s\n' "${times[@]}" | grep -v nan | median)
  found=$("$PY" -c 'import json,sys; d=json.load(open(sys.argv[1])); print(", ".join(f["effect"] for f in d.get("findings", [])) or "no findings")' "$WORK/analysis.json" 2>/dev/null || echo "?")
  row "analyze a ${DURATION_S} s recording: s incl. CSV (median of $REPEATS)" "$an_s s: $found" "see the PySINDy rows" "—"
else
  row "analyze a ${DURATION_S} s recording" "not available yet (no \`analyze\`)" "see the PySINDy rows" "—"
fi

# (d) HTTP: wrk on /api/status of the demo
if has_command demo; then
  if ! command -v wrk >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
    say "installing wrk"
    (apt-get install -y -qq wrk >/dev/null 2>&1 || (apt-get update -qq && apt-get install -y -qq wrk >/dev/null 2>&1)) || true
  fi
  if curl -s -o /dev/null --max-time 2 http://127.0.0.1:8080/ 2>/dev/null; then
    row "HTTP GET /api/status" "not measured: something else already serves 127.0.0.1:8080" "—" "—"
  elif command -v wrk >/dev/null 2>&1; then
    "$BIN" demo >"$WORK/demo.log" 2>&1 &
    PIDS+=($!)
    for _ in $(seq 100); do
      curl -sf http://127.0.0.1:8080/api/status >/dev/null 2>&1 && break
      sleep 0.1
    done
    out=$(timeout 60 wrk -t2 -c32 -d10s --latency http://127.0.0.1:8080/api/status 2>&1 || true)
    echo "$out" >&2
    rps=$(sed -n 's/^Requests\/sec:[[:space:]]*\([0-9.]*\).*/\1/p' <<<"$out")
    p99=$(sed -n 's/^[[:space:]]*99%[[:space:]]*\([^[:space:]]*\).*/\1/p' <<<"$out")
    bad=$(sed -n 's/^[[:space:]]*Non-2xx or 3xx responses:[[:space:]]*\([0-9]*\).*/, \1 of them not 2xx/p' <<<"$out")
    row "HTTP GET /api/status, wrk -t2 -c32 -d10s (demo running)" "${rps:-?} req/s, p99 ${p99:-?}${bad}" "—" "—"
    kill "${PIDS[-1]}" 2>/dev/null || true
    wait "${PIDS[-1]}" 2>/dev/null || true
  else
    row "HTTP GET /api/status" "not measured: wrk could not be installed" "—" "—"
  fi
else
  row "HTTP GET /api/status" "not available yet (no \`demo\`)" "—" "—"
fi

echo
echo "Peers on $(nproc) cores, $(date -u +%Y-%m-%dT%H:%MZ), load average $(cut -d' ' -f1-3 /proc/loadavg); recording ${DURATION_S} s = $ROWS rows"
echo
echo "| measure | hydrolens | peer | ratio |"
echo "|---|---|---|---|"
cat "$RESULTS"

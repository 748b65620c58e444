#!/usr/bin/env bash
# Runs hydrolens side by side with the Python peers a user might reach for, on this machine, and prints one markdown
# table. Idempotent; every step is bounded by `timeout`. Not part of CI (docs/performance.md).
#   (a) Modbus: one read of 6 input registers, tokio-modbus (benches/modbus.rs) vs pymodbus, same `hydrolens sim`
#   (b) estimation: `hydrolens estimate` vs padasip's RLS on the same 60 s and 10-minute recordings, the peer timed
#       doing the same job (load, filter, write its estimates with numpy.savetxt) and without the writing; and the
#       estimator alone against padasip's filter alone on the same rows (benches/replay_rows.rs)
#   (c) analysis: `hydrolens analyze` vs PySINDy, what each finds and how long it takes, on a clean recording and on
#       one with concealed effects (dead time 30 ms + Coulomb friction 0.6 N·m, the nominal model without them);
#       then wall time, user CPU and max RSS of both on longer concealed-effects recordings
#   (d) HTTP: wrk on /api/status of `hydrolens demo`
# Environment: REQUESTS (Modbus requests per run, 5000), ROUNDS (alternating runs per client, 3),
# REPEATS (timed runs of each offline tool, 3), DURATION_S (recording length, 60),
# ESTIMATE_DURATIONS (lengths in s of the further recordings timed in (b), "600"),
# ANALYSIS_DURATIONS (lengths in s of the concealed-effects recordings timed in (c), "600 3600"),
# PYSINDY_MAX_S (skip PySINDy on a recording where its projected time is longer, 300), PEERS_STEPS (which steps to
# run, "a b c d"),
# HYDROLENS_BIN (the binary to measure, target/release/hydrolens). A failed run of ours counts as nan.
set -euo pipefail
cd "$(dirname "$0")/.."
REQUESTS=${REQUESTS:-5000}
ROUNDS=${ROUNDS:-3}
REPEATS=${REPEATS:-3}
DURATION_S=${DURATION_S:-60}
ESTIMATE_DURATIONS=${ESTIMATE_DURATIONS:-600}
ANALYSIS_DURATIONS=${ANALYSIS_DURATIONS:-600 3600}
PYSINDY_MAX_S=${PYSINDY_MAX_S:-300}
PEERS_STEPS=${PEERS_STEPS:-a b c d}
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
# median_field NAME FILE: the median of NAME=… over the lines of FILE
median_field() { while read -r l; do field "$1" "$l"; done <"$2" | median; }
# per_s ROWS SECONDS: rows a second, or nan
per_s() { awk -v n="$1" -v s="$2" 'BEGIN { if (s + 0 > 0) printf "%.0f", n / s; else print "nan" }'; }
# seconds of wall time a command takes (its output to $WORK/last.log)
wall_s() {
  local t0 t1
  # bash's own clock: no `date` process inside the timed window
  t0=$EPOCHREALTIME
  timeout 120 "$@" >"$WORK/last.log" 2>&1 || return 1
  t1=$EPOCHREALTIME
  awk -v a="$t0" -v b="$t1" 'BEGIN { printf "%.3f", b - a }'
}
ratio() { awk -v a="$1" -v b="$2" 'BEGIN { if (a == "nan" || b == "nan" || a + 0 == 0 || b + 0 == 0) print "n/a"; else printf "%.1f×", a / b }'; }
free_port() { "$VENV/bin/python" -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
has_command() { timeout 10 "$BIN" "$1" --help >/dev/null 2>&1; }
step() { [[ " $PEERS_STEPS " == *" $1 "* ]]; }
# qfield NAME LINE: the value of NAME="…" in a result line
qfield() { sed -n "s/.*[[:space:]]$1=\"\([^\"]*\)\".*/\1/p" <<<"$2" | head -n1; }
# timed LIMIT_S CMD…: "wall_s user_s max_rss_kb", medians of REPEATS runs under /usr/bin/time (output of the last
# run in $WORK/last.log); "nan nan nan" if none succeeded
timed() {
  local limit=$1
  shift
  : >"$WORK/times.txt"
  for _ in $(seq "$REPEATS"); do
    if timeout "$limit" /usr/bin/time -f '%e %U %M' -o "$WORK/time1.txt" "$@" >"$WORK/last.log" 2>&1; then
      tail -n1 "$WORK/time1.txt" >>"$WORK/times.txt"
    fi
  done
  local col meds=()
  for col in 1 2 3; do meds+=("$(awk -v c="$col" '{ print $c }' "$WORK/times.txt" | median)"); done
  echo "${meds[*]}"
}
mb() { awk -v k="$1" 'BEGIN { if (k == "nan") print "nan"; else printf "%.0f", k / 1024 }'; }
# recording MODEL DURATION_S OUT: simulate it unless OUT exists and was made from the same model
recording() {
  if [ ! -s "$3" ] || ! cmp -s "$1" "$3.model"; then
    say "recording: simulate $2 s of $1"
    rm -f "$3" "$3.model"
    timeout $((120 + $2 / 10)) "$BIN" simulate --model "$1" --duration "$2" --seed 1 --out "$3.tmp" 2>/dev/null
    mv "$3.tmp" "$3"
    cp "$1" "$3.model"
  fi
}

say "building the release binary and the Modbus bench"
timeout 1200 cargo build --release --locked --quiet
if step a; then timeout 1200 cargo bench --locked --quiet --bench modbus --no-run 2>/dev/null; fi
if step b; then timeout 1200 cargo bench --locked --quiet --bench replay_rows --no-run 2>/dev/null; fi

if [ ! -x "$VENV/bin/python" ]; then
  say "creating $VENV"
  python3 -m venv "$VENV"
fi
if ! cmp -s bench/requirements.txt "$VENV/.installed" 2>/dev/null; then
  say "installing the Python peers (bench/requirements.txt)"
  timeout 900 "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check -r bench/requirements.txt
  cp bench/requirements.txt "$VENV/.installed"
fi
PY="$VENV/bin/python"

REC="$WORK/rec${DURATION_S}s.csv"
recording config/plant.toml "$DURATION_S" "$REC"
ROWS=$(($(wc -l <"$REC") - 1))

# (a) Modbus round trip against one `hydrolens sim`, the two clients alternating
if step a; then
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
fi

# (b) estimation: padasip's RLS vs `hydrolens estimate`, on the DURATION_S recording and on each of
# ESTIMATE_DURATIONS, ROUNDS rounds: padasip once, then `estimate` once untimed and REPEATS times timed, each
# writing a new file (replacing the file the run before wrote would add the kernel's work of dropping its pages)
if step b; then
  for d in "$DURATION_S" $ESTIMATE_DURATIONS; do
    rec="$WORK/rec${d}s.csv"
    recording config/plant.toml "$d" "$rec"
    rows=$(($(wc -l <"$rec") - 1))
    : >"$WORK/padasip.txt"
    : >"$WORK/replay.txt"
    ours=()
    for round in $(seq "$ROUNDS"); do
      say "padasip RLS and hydrolens estimate on $rows rows, round $round"
      # the recording read into the page cache before each timed run: this guest drops file pages idle for a minute
      # (DAMON reclaim), and a run that finds them gone reads the disk
      cat "$rec" >/dev/null
      timeout 900 "$PY" bench/padasip_rls.py "$rec" 1 "$WORK/padasip_est.csv" >>"$WORK/padasip.txt"
      rm -f "$WORK/padasip_est.csv"
      # our estimator alone on the same rows (benches/replay_rows.rs: loaded first, not timed), beside padasip's filter alone
      timeout 300 cargo bench --locked --quiet --bench replay_rows -- "$rec" 5 2>/dev/null | grep '^replay' >>"$WORK/replay.txt" || true
      if has_command estimate; then
        # one untimed run first, as padasip_rls.py times its load and fit inside a warm process
        timeout 120 "$BIN" estimate "$rec" --model config/plant.toml --out "$WORK/est.csv" >/dev/null 2>&1 || true
        for _ in $(seq "$REPEATS"); do
          rm -f "$WORK/est.csv"
          cat "$rec" >/dev/null
          ours+=("$(wall_s "$BIN" estimate "$rec" --model config/plant.toml --out "$WORK/est.csv" || echo nan)")
        done
      fi
    done
    cat "$WORK/padasip.txt" >&2
    pad_s=$(median_field total_s "$WORK/padasip.txt")
    pad_rls_s=$(median_field rls_s "$WORK/padasip.txt")
    pad_rps=$(per_s "$rows" "$pad_s")
    pad_rls_rps=$(per_s "$rows" "$pad_rls_s")
    pad_job_s=$(median_field job_s "$WORK/padasip.txt")
    pad_job_rps=$(per_s "$rows" "$pad_job_s")
    est_s=$(printf '%s\n' "${ours[@]}" | grep -v nan | median)
    ours_rps=$(per_s "$rows" "$est_s")
    row "RLS on a ${d} s recording ($rows rows), the same job: read the CSV, estimate, write the estimates CSV, rows/s (median of $ROUNDS alternating rounds; ours ${REPEATS}× a round)" \
      "$ours_rps (hydrolens estimate, ${est_s} s)" "$pad_job_rps (padasip FilterRLS + numpy.loadtxt + numpy.savetxt, ${pad_job_s} s)" \
      "$(ratio "$ours_rps" "$pad_job_rps") (ours ÷ peer)"
    row "RLS on a ${d} s recording ($rows rows), rows/s end to end incl. CSV (median of $ROUNDS alternating rounds; ours ${REPEATS}× a round)" \
      "$ours_rps (hydrolens estimate, ${est_s} s)" "$pad_rps (padasip FilterRLS + numpy.loadtxt, ${pad_s} s)" \
      "$(ratio "$ours_rps" "$pad_rps") (ours ÷ peer)"
    row "padasip RLS alone on the ${d} s recording (CSV load excluded), rows/s" "—" "$pad_rls_rps" \
      "$(ratio "$ours_rps" "$pad_rls_rps") (ours end to end ÷ peer's filter alone)"
    replay_s=$(median_field s "$WORK/replay.txt")
    replay_rps=$(per_s "$rows" "$replay_s")
    row "the estimator alone on the ${d} s recording's rows (CSV excluded on both sides), rows/s (median of $ROUNDS alternating rounds)" \
      "$replay_rps (RLS+SGD, benches/replay_rows.rs, one thread)" "$pad_rls_rps (padasip FilterRLS)" \
      "$(ratio "$replay_rps" "$pad_rls_rps") (ours ÷ peer)"
  done
fi

# (c) analysis: `hydrolens analyze` vs PySINDy, what each finds and how long it takes. PySINDy fits the speed equation
# with the candidate terms of the analysis it can express (ω, Δp, the measured load, sign(ω), a constant; not a dead
# time, entrained air, leakage/slip or Stribeck: see bench/pysindy_fit.py), and its coefficients are turned into the
# parameters `analyze` reports. Recordings: the reference plant clean, and with a dead time of 30 ms and a Coulomb
# friction of 0.6 N·m that the nominal model (config/plant.toml, the one both are given) does not have.
if step c; then
  EFFECTS="$WORK/plant_dead_time_coulomb.toml"
  {
    cat config/plant.toml
    printf '\n[effects.dead_time]\nms = 30.0\n\n[effects.coulomb_friction]\ntorque_nm = 0.6\n'
  } >"$EFFECTS.tmp"
  if cmp -s "$EFFECTS.tmp" "$EFFECTS"; then rm -f "$EFFECTS.tmp"; else mv "$EFFECTS.tmp" "$EFFECTS"; fi
  J=$(sed -n 's/^inertia_kg_m2[[:space:]]*=[[:space:]]*//p' config/plant.toml)
  B=$(sed -n 's/^viscous_nm_s_rad[[:space:]]*=[[:space:]]*//p' config/plant.toml)
  has_analyze=$(has_command analyze && echo yes || echo no)
  # summary JSON: one line of what an analysis found
  summary() { "$PY" bench/analysis_summary.py "$1" 2>/dev/null || echo "no analysis (failed)"; }
  SINDY_RATE="" # s of PySINDy (CSV load + REPEATS fits of the full library) per row, from the DURATION_S runs

  # side LABEL TRUTH REC TAG: what each finds on one recording, and in what time
  side() {
    local label=$1 truth=$2 rec=$3 tag=$4 rows sindy full issue ours t w u m
    rows=$(($(wc -l <"$rec") - 1))
    say "analysis, $label: PySINDy, then hydrolens analyze ($rows rows)"
    sindy=$(timeout 300 "$PY" bench/pysindy_fit.py "$rec" "$REPEATS" || true)
    echo "$sindy" >&2
    full=$(grep 'inputs=dP+load ' <<<"$sindy" || true)
    issue=$(grep 'inputs=dP ' <<<"$sindy" || true)
    if [ "$has_analyze" = yes ]; then
      rm -f "$WORK/analysis_$tag.json"
      read -r w u m <<<"$(timed 300 "$BIN" analyze "$rec" --model config/plant.toml --json "$WORK/analysis_$tag.json")"
      ours=$(summary "$WORK/analysis_$tag.json")
    else
      w=nan u=nan m=nan ours="not available yet (no \`analyze\`)"
    fi
    row "$label, ${DURATION_S} s: what is found (truth: $truth)" "$ours" \
      "PySINDy ω' on ω, Δp, load, sign(ω), 1: ${full:+$(qfield found "$full"); \`$(qfield equation "$full")\`}" "—"
    row "$label, ${DURATION_S} s: PySINDy with the issue's terms only (no load)" "—" \
      "${issue:+$(qfield found "$issue"); \`$(qfield equation "$issue")\`}" "—"
    t=$(awk -v f="$(field fit_s "$full")" -v l="$(field load_s "$full")" 'BEGIN { if (f == "") print "nan"; else printf "%.3f", f + l }')
    row "$label, ${DURATION_S} s: s incl. reading the CSV (median of $REPEATS)" \
      "$w s wall, $u s user, $(mb "$m") MB max RSS" \
      "${full:+$(field fit_s "$full") s fit (Δp+load) + $(field load_s "$full") s numpy.loadtxt}" \
      "$(ratio "$w" "$t") (ours ÷ peer, time)"
    if [ -n "$full" ]; then
      SINDY_RATE=$(awk -v f="$(field fit_s "$full")" -v l="$(field load_s "$full")" -v r="$REPEATS" -v n="$rows" \
        'BEGIN { printf "%.3g", (l + r * f) / n }')
    fi
  }

  REC_EFFECTS="$WORK/rec_dead_time_coulomb_${DURATION_S}s.csv"
  recording "$EFFECTS" "$DURATION_S" "$REC_EFFECTS"
  side "clean recording" "nothing missing; J $J, B $B" "$REC" clean
  side "concealed effects" "dead_time 30 ms, coulomb_friction 0.6 N·m; J $J, B $B" "$REC_EFFECTS" effects

  # timing rows: longer concealed-effects recordings
  for d in $ANALYSIS_DURATIONS; do
    rec="$WORK/rec_dead_time_coulomb_${d}s.csv"
    recording "$EFFECTS" "$d" "$rec"
    rows=$(($(wc -l <"$rec") - 1))
    label="concealed effects, ${d} s ($rows rows): wall / user CPU / max RSS incl. CSV"
    if [ "$has_analyze" = yes ]; then
      say "hydrolens analyze on $d s ($rows rows), $REPEATS runs"
      rm -f "$WORK/analysis_effects_${d}s.json"
      read -r w u m <<<"$(timed $((120 + d / 5)) "$BIN" analyze "$rec" --model config/plant.toml --json "$WORK/analysis_effects_${d}s.json")"
      ours="$w s / $u s / $(mb "$m") MB (median of $REPEATS); $(summary "$WORK/analysis_effects_${d}s.json")"
    else
      w=nan ours="not available yet (no \`analyze\`)"
    fi
    projected=$(awk -v r="${SINDY_RATE:-0}" -v n="$rows" 'BEGIN { printf "%.1f", r * n }')
    if [ -z "$SINDY_RATE" ]; then
      peer="not run: PySINDy failed on the ${DURATION_S} s recordings"
      t=nan
    elif awk -v p="$projected" -v m="$PYSINDY_MAX_S" 'BEGIN { exit !(p > m) }'; then
      peer="skipped: projected ${projected} s (> ${PYSINDY_MAX_S} s) for the CSV load and $REPEATS fits"
      t=nan
    else
      say "PySINDy on $d s ($rows rows), $REPEATS fits"
      if out=$(timeout 600 /usr/bin/time -f '%e %U %M' -o "$WORK/time1.txt" \
        "$PY" bench/pysindy_fit.py "$rec" "$REPEATS" --only dP+load 2>/dev/null); then
        echo "$out" >&2
        read -r pw pu pm <<<"$(tail -n1 "$WORK/time1.txt")"
        t=$(awk -v f="$(field fit_s "$out")" -v l="$(field load_s "$out")" 'BEGIN { printf "%.3f", f + l }')
        peer="$(field fit_s "$out") s fit (median of $REPEATS) + $(field load_s "$out") s numpy.loadtxt; process (import, load, $REPEATS fits) $pw s / $pu s / $(mb "$pm") MB; $(qfield found "$out")"
      else
        peer="failed or over 600 s"
        t=nan
      fi
    fi
    row "$label" "$ours" "$peer" "$(ratio "$w" "$t") (ours ÷ peer, time)"
  done
fi

# (d) HTTP: wrk on /api/status of the demo
if step d; then
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
fi

echo
echo "Peers on $(nproc) cores, $(date -u +%Y-%m-%dT%H:%MZ), load average $(cut -d' ' -f1-3 /proc/loadavg); recording ${DURATION_S} s = $ROWS rows"
echo
echo "| measure | hydrolens | peer | ratio |"
echo "|---|---|---|---|"
cat "$RESULTS"

#!/bin/bash
# Why J comes out high under a smooth random load (docs/estimator.md, Limits): per-window least-squares fits of J and B
# on `hydrolens simulate` recordings, forward (the speed on ∫τ, as src/estimator/windows.rs fits), reverse (∫τ on the
# speed) and instrumental variables (the drive frequency and its integral), beside the fit with the true load known.
# Plain Python 3.11 (tomllib), no numpy; about 3 minutes on two cores.
#   bash bench/window_bias/run.sh OUT_DIR [HYDROLENS_BINARY]   (default target/release/hydrolens; build it first)
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../.." && pwd)
out=${1:?usage: run.sh OUT_DIR [HYDROLENS_BINARY]}
hl=$(realpath "${2:-$root/target/release/hydrolens}")
mkdir -p "$out" && cd "$out"
mkdir -p models recs fits est
# a model of the reference plant with its [load] table replaced and the given sample period
mk() {
  local name=$1 ms=$2; shift 2
  sed -e "s/^sample_ms = .*/sample_ms = $ms/" -e '/^\[load\]/,$d' "$root/config/plant.toml" > "models/$name.toml"
  { printf '[load]\n'; printf '%s\n' "$@"; } >> "models/$name.toml"
}
for ms in 1 10; do
  for s in 11 12 13; do
    mk "brake_ms${ms}_s$s" "$ms" 'kind = "recorded"'
    for sd in 2 5 8; do for c in 0.5 1.0 2.0; do
      mk "rand_sd${sd}_c${c}_ms${ms}_s$s" "$ms" 'kind = "random"' 'mean_nm = 8.0' "sd_nm = $sd.0" "correlation_s = $c" "seed = $s"
    done; done
  done
done
for m in models/*.toml; do
  b=$(basename "$m" .toml); s=${b##*_s}
  nice "$hl" simulate --model "$m" --duration 60 --seed "$s" --out "recs/$b.csv" > /dev/null
  nice python3 "$here/fitwin.py" "recs/$b.csv" "$m" "fits/$b.poly2.jsonl"
  nice python3 "$here/fitwin.py" "recs/$b.csv" "$m" "fits/$b.step.jsonl" --step
  # rls-sgd on the same recording from a nominal J of 0.05 (true 0.08): its final J
  sed "s/^inertia_kg_m2 = .*/inertia_kg_m2 = 0.05/" "$m" > "est/$b.nom.toml"
  nice "$hl" estimate "recs/$b.csv" --model "est/$b.nom.toml" --out "est/$b.est.csv" > /dev/null
  tail -1 "est/$b.est.csv" | cut -d, -f4,6,8 > "est/$b.final"
  rm "est/$b.est.csv" "recs/$b.csv"
done
# random loads on the poly2 nuisance, the brake steps on poly2 plus one GLR step, windows where the drive moved ≥ 2 Hz
PYTHONPATH="$here" python3 "$here/table.py" poly2 f step

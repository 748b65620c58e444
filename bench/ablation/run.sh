#!/bin/bash
# Each mechanism of rls-sgd off in turn (docs/estimator.md, "Each mechanism, off in turn"): applies ablate.patch (one
# switch per mechanism, read from HL_ABLATE) to a copy of HEAD's tree, builds the battery there, runs the twelve seed
# sets of the six and the new families with each mechanism off, and prints the table. The service's code has no such
# switches. About 30 minutes on two cores (a cold release build, then about 50 s a row).
#   bash bench/ablation/run.sh OUT_DIR [MECHANISM...]    (default: every mechanism of the patch)
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../.." && pwd)
out=$(realpath -m "${1:?usage: run.sh OUT_DIR [MECHANISM...]}")
shift
mechanisms=("$@")
if [ ${#mechanisms[@]} -eq 0 ]; then
  mapfile -t mechanisms < <(grep -o 'abl("[a-z_]*")' "$here/ablate.patch" | cut -d'"' -f2 | sort -u)
fi
mkdir -p "$out/tree"
git -C "$root" archive HEAD | tar -x -C "$out/tree"
(cd "$out/tree" && git apply "$here/ablate.patch")
(cd "$out/tree" && CARGO_TARGET_DIR="$out/target" nice cargo build --release --locked --example estimator_battery)
battery="$out/target/release/examples/estimator_battery"
sets="tuned held-out fresh unseen final sealed novel last spare reserve blind untouched"
for m in none "${mechanisms[@]}"; do
  mkdir -p "$out/$m"
  for s in $sets; do
    HL_ABLATE=$m nice "$battery" set=$s runs=24 polls=1,2,5,10 lost=0 > "$out/$m/${s}_six.txt"
    HL_ABLATE=$m nice "$battery" set=$s runs=28 polls=1,2,5,10 loads=new > "$out/$m/${s}_new.txt"
  done
done
python3 "$here/table.py" "$out" none "${mechanisms[@]}"

#!/usr/bin/env bash
# Runs every fuzz target for a bounded time (default 60 s each). Needs cargo-fuzz (`cargo install cargo-fuzz`);
# RUSTC_BOOTSTRAP lets the stable toolchain accept the sanitizer flags cargo-fuzz passes.
set -euo pipefail
cd "$(dirname "$0")/.."
seconds="${1:-60}"
for target in register_decode recording_csv plant_config service_config; do
  mkdir -p "fuzz/corpus/$target"
  echo "== $target ($seconds s)"
  RUSTC_BOOTSTRAP=1 cargo fuzz run -O "$target" "fuzz/corpus/$target" "fuzz/seeds/$target" -- \
    -max_total_time="$seconds" 2>&1 | grep -E "^Done|panicked|SUMMARY|Failing input" || true
done

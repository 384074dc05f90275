#!/usr/bin/env bash
# Runs every benchmark suite on the present device and keeps the records: the device report
# (info.json), then kernels, attention, layers, raster and models, each as JSON and as the
# printed table. Usage: tools/bench-all.sh [OUT_DIR [SUITE...]] (default bench-out, every
# suite; name suites to split the run across calls with a time limit). VELOX_BIN picks the
# binary (default target/release/velox, built with `cargo build --release`).
set -euo pipefail
bin=${VELOX_BIN:-target/release/velox}
out=${1:-bench-out}
shift || true
suites=("$@")
[ ${#suites[@]} -gt 0 ] || suites=(kernels attention layers raster models)
if [ ! -x "$bin" ]; then
  echo "no velox binary at $bin: run \`cargo build --release\` or set VELOX_BIN" >&2
  exit 1
fi
mkdir -p "$out"
"$bin" info --json "$out/info.json" | tee "$out/info.txt"
for suite in "${suites[@]}"; do
  echo "== bench $suite"
  "$bin" bench "$suite" --json "$out/$suite.json" 2>&1 | tee "$out/$suite.txt"
done
echo "records in $out"

#!/usr/bin/env bash
# Runs every benchmark suite on the present device and keeps the records: the device report
# (info.json), then kernels, attention, layers, raster, models and train (a training step in
# f32 and f16: the autoencoder at the small config against the batch and at the paper config
# at batch 1, the voxel decoder, tracker and generator at the small and paper configs), each
# as JSON and as the printed table. Usage: tools/bench-all.sh [OUT_DIR [SUITE...]] (default bench-out, every
# suite; name suites to split the run across calls with a time limit). VELOX_BIN picks the
# binary (default target/release/velox, built with `cargo build --release`).
set -euo pipefail
bin=${VELOX_BIN:-target/release/velox}
out=${1:-bench-out}
shift || true
suites=("$@")
[ ${#suites[@]} -gt 0 ] || suites=(kernels attention layers raster models train)
if [ ! -x "$bin" ]; then
  echo "no velox binary at $bin: run \`cargo build --release\` or set VELOX_BIN" >&2
  exit 1
fi
mkdir -p "$out"
"$bin" info --json "$out/info.json" | tee "$out/info.txt"
for suite in "${suites[@]}"; do
  echo "== bench $suite"
  if [ "$suite" = train ]; then
    "$bin" bench train --config small --json "$out/train.json" 2>&1 | tee "$out/train.txt"
    "$bin" bench train --config paper --batches 1 --repeats 3 --json "$out/train-paper.json" 2>&1 \
      | tee "$out/train-paper.txt"
    for model in voxels tracker generator; do
      for config in small paper; do
        "$bin" bench train --model "$model" --config "$config" --repeats 3 \
          --json "$out/train-$model-$config.json" 2>&1 | tee "$out/train-$model-$config.txt"
      done
    done
  else
    "$bin" bench "$suite" --json "$out/$suite.json" 2>&1 | tee "$out/$suite.txt"
  fi
done
echo "records in $out"

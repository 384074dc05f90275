#!/usr/bin/env bash
# Packs what a GPU machine without a Rust toolchain needs to test and benchmark this tree:
# the release `velox` binary and the test binaries of the GPU-specific kernels (cooperative
# matrices, attention, matmul, FPS, the autoencoder), stripped, into target/device/ (ignored by
# git, so pass it to the machine explicitly, e.g. as a carried path). There, run
# `tools/device-check.sh OUT [SUITE...]`.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release
mapfile -t bins < <(cargo test --release --no-run 2>&1 | grep -o 'target/release/deps/[A-Za-z0-9_-]*' | sort -u)
rm -rf target/device
mkdir -p target/device/tests
cp target/release/velox target/device/velox
for b in "${bins[@]}"; do
    name=$(basename "$b")
    case $name in
        attention-* | matmul-* | assign-* | autoencoder-* | attention_layer-*) cp "$b" target/device/tests/ ;;
    esac
done
strip target/device/velox target/device/tests/*
du -sh target/device
ls target/device/tests

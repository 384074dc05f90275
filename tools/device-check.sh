#!/usr/bin/env bash
# Runs, on a GPU machine, what tools/device-pack.sh packed into target/device/: the test
# binaries (the cooperative-matrix kernels' tests among them, which only a device with
# cooperative matrices exercises) and then the benchmark suites through tools/bench-all.sh.
# Everything goes under OUT: device.txt (velox info), one .txt per test binary, bench/.
# Usage: tools/device-check.sh OUT [SUITE...] (suites as for bench-all.sh; default all).
# Tests read ../shared/assets where it exists; those that need it fail without it.
set -uo pipefail
cd "$(dirname "$0")/.."
out=${1:?usage: tools/device-check.sh OUT [SUITE...]}
shift
mkdir -p "$out"
target/device/velox info > "$out/device.txt" 2>&1
status=0
for b in target/device/tests/*; do
    name=$(basename "$b")
    if "$b" -q > "$out/$name.txt" 2>&1; then
        echo "ok      $name"
    else
        echo "FAILED  $name (see $out/$name.txt)"
        status=1
    fi
done
VELOX_BIN=target/device/velox tools/bench-all.sh "$out/bench" "$@" || status=1
exit $status

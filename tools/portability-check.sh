#!/usr/bin/env bash
# The test suite in every configuration a GPU may present, each imitated on a CPU: Vulkan
# validation (synchronization checks over the whole suite, GPU-assisted checks over the op-level
# tests), lavapipe's subgroup widths 4, 16 and 32, poisoned allocations, staging as on a discrete
# GPU, each fallback a GPU may need (no f16, no f32 atomics, no push descriptors, a small
# storage-binding limit), and SwiftShader, a second Vulkan implementation with a compiler of its
# own. Prints a table: configuration, tests passed and failed, validation errors, crashes at exit
# (after every result was printed), minutes.
#
# Usage: tools/portability-check.sh [--quick] [CONFIG...]
#   CONFIG   names from the table below (default: all); --list prints them.
#   --quick  the op-level tests only, in every configuration (about a tenth of the time).
# Needs: lavapipe (mesa-vulkan-drivers), the validation layer (vulkan-validationlayers) and
# Debian's chromium-common (SwiftShader and the newer validation layer tools/vvl names);
# tools/setup.sh --tests installs what is missing. Logs go to target/portability/<config>.log.
# The full matrix takes about two hours on 2 cores.
set -uo pipefail
cd "$(dirname "$0")/.."

# The op-level tests: the engine's and the file formats' crates (every op against its reference,
# staging, validation), for the GPU-assisted row and --quick.
OPS="-p velox-engine -p velox-io"

# name | environment | scope (all = the whole suite, ops = the binaries above)
# small-bindings runs the op-level tests: they size their cases by the device's limit so that
# every chunked path runs (and a tensor no op can split is refused by name). The model and CLI
# tests hold single tensors of 5 to 12 MiB (a voxel decoder's [2, 12288, 128] activations), which
# a 4 MiB limit refuses as it should; Vulkan requires every device to bind at least 128 MiB.
CONFIGS=(
  "lavapipe||all"
  "validation-sync|VELOX_VALIDATE=1|all"
  # An absolute path: cargo runs each crate's tests in that crate's folder.
  "validation-sync-newer|VELOX_VALIDATE=1 VK_LAYER_PATH=$PWD/tools/vvl|ops"
  "validation-gpu-assisted|VELOX_VALIDATE=gpu VK_LAYER_PATH=$PWD/tools/vvl|ops"
  "subgroup-4|LP_NATIVE_VECTOR_WIDTH=128|all"
  "subgroup-16|LP_NATIVE_VECTOR_WIDTH=512|all"
  "subgroup-32|LP_NATIVE_VECTOR_WIDTH=1024|all"
  # The GPU kernel variants on a CPU device, at lavapipe's width and NVIDIA's.
  "gpu-kernels|VELOX_CPU_KERNELS=0|all"
  "gpu-kernels-32|VELOX_CPU_KERNELS=0 LP_NATIVE_VECTOR_WIDTH=1024|ops"
  "poisoned-memory|LVP_POISON_MEMORY=true|all"
  "staging|VELOX_FORCE_STAGING=1|all"
  "no-f16|VELOX_DISABLE=f16|all"
  "no-float-atomics|VELOX_DISABLE=float-atomics|all"
  "descriptor-sets|VELOX_DISABLE=push-descriptors|all"
  "small-bindings|VELOX_MAX_BINDING=4M|ops"
  "swiftshader|VK_DRIVER_FILES=/usr/lib/chromium/vk_swiftshader_icd.json|all"
)

quick=0
wanted=()
for a in "$@"; do
  case $a in
    --quick) quick=1 ;;
    --list) for c in "${CONFIGS[@]}"; do echo "${c%%|*}"; done; exit 0 ;;
    -h | --help) sed -n '2,16p' "$0"; exit 0 ;;
    *) wanted+=("$a") ;;
  esac
done
for w in "${wanted[@]}"; do
  found=0
  for c in "${CONFIGS[@]}"; do [ "${c%%|*}" = "$w" ] && found=1; done
  [ $found = 1 ] || { echo "unknown configuration $w (see --list)" >&2; exit 2; }
done

tools/setup.sh --tests
cargo build --release --tests -q || exit 1
mkdir -p target/portability
export VK_LAYER_SETTINGS_PATH=$PWD/vk_layer_settings.txt

rows=()
status=0
for c in "${CONFIGS[@]}"; do
  IFS='|' read -r name envs scope <<<"$c"
  if [ ${#wanted[@]} -gt 0 ] && ! printf '%s\n' "${wanted[@]}" | grep -qx "$name"; then
    continue
  fi
  targets=()
  what="whole suite"
  if [ "$scope" = ops ] || [ $quick = 1 ]; then
    read -ra targets <<<"$OPS"
    what="op-level tests"
  fi
  log=target/portability/$name.log
  echo "== $name (${envs:-no switches}, $what) -> $log" >&2
  start=$(date +%s)
  # shellcheck disable=SC2086
  env $envs cargo test --release --no-fail-fast "${targets[@]}" >"$log" 2>&1
  end=$(date +%s)
  passed=$(grep -E '^test result:' "$log" | awk '{s += $4} END {print s + 0}')
  failed=$(grep -E '^test result:' "$log" | awk '{s += $6} END {print s + 0}')
  errors=$(grep -c 'velox: validation error' "$log")
  # A test binary that died before its summary (a crash, an abort) counts as a failure: each
  # binary prints "Running" (or "Doc-tests") first and "test result:" last. A crash after the
  # summary, in the Vulkan layers' own teardown at exit, fails no test and is counted apart:
  # the newer validation layer (Chromium's build) crashes there in its synchronization mode
  # once the tests' shared device is closed from the exit handler, and aborts in its
  # GPU-assisted mode when it is not.
  started=$(grep -cE '^ +(Running|Doc-tests) ' "$log")
  crashed=$((started - $(grep -cE '^test result:' "$log")))
  at_exit=$(grep -cE 'process didn.t exit successfully.*signal' "$log")
  at_exit=$((at_exit - crashed))
  failed=$((failed + crashed))
  minutes=$(awk -v s=$((end - start)) 'BEGIN {printf "%.1f", s / 60}')
  rows+=("$(printf '%-24s %7s %7s %8s %8s %8s' "$name" "$passed" "$failed" "$errors" "$at_exit" "$minutes")")
  if [ "$failed" -gt 0 ] || [ "$errors" -gt 0 ] || [ "$passed" -eq 0 ]; then status=1; fi
done

printf '\n%-24s %7s %7s %8s %8s %8s\n' configuration passed failed "val.err" "exit-crash" minutes
printf '%s\n' "${rows[@]}"
exit $status

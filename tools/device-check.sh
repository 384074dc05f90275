#!/usr/bin/env bash
# One call on a GPU machine without a Rust toolchain or a network, from a tree that
# tools/device-pack.sh prepared (target/device/ and .gl/): everything a first GPU can tell, in
# phases of priority order, each in its own time box, with what comes back packed after every
# phase into at most 8 files (tools/device-results.sh), so that a cut run returns what it did:
#   0. set-up: the Vulkan loader from .gl/ where the machine has none, the driver's manifest
#      (NVIDIA's first), the newer validation layer (.gl/vvl, which knows
#      VK_KHR_cooperative_matrix), the exec bits;
#   1. the device: velox info --probe;
#   2. the op tests: under validation (the newer layer; with Debian 12's only with
#      VELOX_DISABLE=coop-matrix, which knows no KHR cooperative matrices), once without it on
#      the real tensor cores, once with robust buffer access (VELOX_ROBUST=1); the staging tests
#      and the autoencoder's under validation;
#   3. the benchmarks (kernels, attention, raster, layers, models), then PyTorch at the same
#      shapes (tools/peers/torch_bench.py, where `import torch` works);
#   4. training the small autoencoder on procedural scenes the GPU renders, at the largest
#      micro-batch (1, 4, 16, 64) that runs, for the minutes left (a cooldown over the last
#      fifth);
#   5. eval recon on held-out scenes, and the weights as f16 safetensors (velox weights).
# OUT gets summary.md, logs.tar.gz and weights.safetensors (see tools/device-results.sh); the
# dataset stays on the machine. Every wait is bounded: a submit waits VELOX_WAIT_TIMEOUT seconds
# (120 here) and a phase its box.
# Usage: tools/device-check.sh OUT [MINUTES]   (default 9). SCENES, RES and POINTS size the
# dataset (256, 128, 100000); CONFIG the model (small). A dry run on lavapipe:
#   tools/device-pack.sh && SCENES=4 RES=32 tools/device-check.sh /tmp/out 3
set -uo pipefail
cd "$(dirname "$0")/.."
repo=$PWD
out=${1:?usage: tools/device-check.sh OUT [MINUTES]}
minutes=${2:-9}
[[ $minutes =~ ^[0-9]+$ ]] && [ "$minutes" -ge 1 ] || { echo "MINUTES must be a whole number of minutes, got $minutes" >&2; exit 2; }
start=$(date +%s)
# The last 15 s are kept for the final packing.
deadline=$((start + minutes * 60 - 15))
left() { echo $((deadline - $(date +%s))); }
# A box of FRACTION (percent) of what is left.
box() { echo $(($(left) * $1 / 100)); }
work=${TMPDIR:-/tmp}/velox-device-check
# What is unpacked to run (the loader, the layer) lives beside the results, not among them.
tools_dir=${TMPDIR:-/tmp}/velox-device-tools
rm -rf "$work" "$tools_dir"
mkdir -p "$tools_dir"
mkdir -p "$work/tests" "$work/bench" "$work/train" "$work/eval" "$out" || exit 1
bin=$repo/target/device/velox
export VELOX_BIN=$bin
export VELOX_WAIT_TIMEOUT=${VELOX_WAIT_TIMEOUT:-120}
export VK_LAYER_SETTINGS_PATH=$repo/vk_layer_settings.txt
status=0
say() { echo "[$(($(date +%s) - start))s] $*" | tee -a "$work/check.log"; }
# phase NAME STATUS SECONDS NOTE: a row of the summary's phase table.
phase_start=$start
phase() {
    local now
    now=$(date +%s)
    printf '%s\t%s\t%s\t%s\n' "$1" "$2" "$((now - phase_start))" "${3:-}" >>"$work/phases.tsv"
    phase_start=$now
    tools/device-results.sh "$work" "$out" 2>>"$work/check.log" || true
}
# run BOX LOG CMD...: CMD under a time limit of BOX seconds, its output in LOG; 124 when cut.
run() {
    local limit=$1 log=$2
    shift 2
    [ "$limit" -ge 5 ] || { echo "not run: no time left in its box" >"$log"; return 124; }
    timeout -k 10 "$limit" "$@" >"$log" 2>&1
}

# 0. Set-up.
[ -x "$bin" ] || chmod +x target/device/velox target/device/tests/* 2>/dev/null
[ -x "$bin" ] || { echo "no $bin: run tools/device-pack.sh first (and carry target/device)" >&2; exit 1; }
chmod +x tools/*.sh tools/peers/*.py 2>/dev/null
if ! ldconfig -p 2>/dev/null | grep 'libvulkan\.so\.1' >/dev/null; then
    loader=$(ls .gl/libvulkan1_*.deb 2>/dev/null | head -1)
    if [ -n "$loader" ] && [ "$(id -u)" -eq 0 ]; then
        dpkg -x "$loader" / && ldconfig
        say "unpacked the Vulkan loader from $loader"
    elif [ -n "$loader" ]; then
        dpkg -x "$loader" "$tools_dir/gl" && export LD_LIBRARY_PATH=$tools_dir/gl/usr/lib/x86_64-linux-gnu:${LD_LIBRARY_PATH:-}
        say "unpacked the Vulkan loader from $loader into $tools_dir/gl (not root)"
    else
        say "no Vulkan loader on this machine and none in .gl/ (tools/device-pack.sh packs one)"
    fi
fi
if [ -z "${VK_DRIVER_FILES:-}${VK_ICD_FILENAMES:-}" ]; then
    for icd in /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json /usr/share/vulkan/icd.d/nvidia_icd.json \
        /etc/vulkan/icd.d/nvidia_icd.json; do
        if [ -e "$icd" ]; then
            export VK_DRIVER_FILES=$icd
            say "driver manifest $icd"
            break
        fi
    done
fi
# The newer validation layer (it validates the cooperative-matrix kernels), else Debian 12's.
validate=none
if [ -e .gl/vvl/libVkLayer_khronos_validation.so.xz ]; then
    mkdir -p "$tools_dir/vvl"
    if xz -dc .gl/vvl/libVkLayer_khronos_validation.so.xz >"$tools_dir/vvl/libVkLayer_khronos_validation.so" 2>/dev/null ||
        python3 -c 'import lzma, sys; sys.stdout.buffer.write(lzma.open(sys.argv[1]).read())' \
            .gl/vvl/libVkLayer_khronos_validation.so.xz >"$tools_dir/vvl/libVkLayer_khronos_validation.so"; then
        sed "s|\"library_path\": *\"[^\"]*\"|\"library_path\": \"$tools_dir/vvl/libVkLayer_khronos_validation.so\"|" \
            .gl/vvl/VkLayer_khronos_validation.json >"$tools_dir/vvl/VkLayer_khronos_validation.json"
        export VK_LAYER_PATH=$tools_dir/vvl
        validate=newer
    fi
fi
if [ $validate = none ]; then
    layer_deb=$(ls .gl/vulkan-validationlayers_*.deb 2>/dev/null | head -1)
    [ -n "$layer_deb" ] && [ "$(id -u)" -eq 0 ] && dpkg -x "$layer_deb" /
    [ -e /usr/share/vulkan/explicit_layer.d/VkLayer_khronos_validation.json ] && validate=debian
fi
say "validation layer: $validate"
manifest=${VK_DRIVER_FILES:-none named (the loader searches)}
phase set-up ok "loader, driver manifest $manifest, validation layer $validate"

# 1. The device.
if run 60 "$work/device.txt" "$bin" info --probe --json "$work/info.json"; then
    grep -m1 '^Chosen device' "$work/device.txt" | tee -a "$work/check.log"
    phase device ok "$(grep -m1 '^Chosen device' "$work/device.txt")"
else
    status=1
    say "velox info failed: $(tail -1 "$work/device.txt")"
    phase device FAILED "$(tail -1 "$work/device.txt")"
fi
coop=yes
grep -q 'coop matrices     none' "$work/device.txt" && coop=no

# 2. The op tests, in priority order, within 30% of what is left.
tests_end=$(($(date +%s) + $(box 30)))
test_run() { # NAME BINARY [ENV=VALUE...] -- [FILTER...]
    local name=$1 b=target/device/tests/$2 code
    shift 2
    local envs=()
    while [ $# -gt 0 ] && [ "$1" != -- ]; do envs+=("$1"); shift; done
    shift
    if [ ! -x "$b" ]; then
        say "tests $name: no $b"
        return
    fi
    run $((tests_end - $(date +%s))) "$work/tests/$name.txt" env "${envs[@]}" "$b" -q "$@"
    code=$?
    # The summary reads the result lines; the newer layer's own teardown can crash at exit after
    # them, so the code alone does not decide.
    if grep -q '^test result: ok' "$work/tests/$name.txt" && ! grep -q 'velox: validation error' "$work/tests/$name.txt"; then
        say "tests $name: $(grep '^test result' "$work/tests/$name.txt" | tail -1)"
    elif grep -q '^not run' "$work/tests/$name.txt"; then
        say "tests $name: not run (no time left in the tests' box)"
        status=1
    elif [ $code -eq 124 ]; then
        say "tests $name: cut by the time box"
        status=1
    else
        say "tests $name: FAILED ($code; see tests/$name.txt in logs.tar.gz)"
        status=1
    fi
}
ops=$(ls target/device/tests/ | grep '^ops-' | head -1)
staging=$(ls target/device/tests/ | grep '^staging-' | head -1)
models=$(ls target/device/tests/ | grep '^models-' | head -1)
case $validate in
    newer) test_run ops-validated "$ops" VELOX_VALIDATE=1 -- ;;
    debian) test_run ops-validated-no-coop "$ops" VELOX_VALIDATE=1 VELOX_DISABLE=coop-matrix -- ;;
    none) say "tests: no validation layer; the op tests run without it only" ;;
esac
[ $coop = yes ] || [ $validate = none ] || say "tests: the device has no cooperative matrices; the unvalidated run repeats the portable kernels"
test_run ops "$ops" VELOX_VALIDATE=0 --
test_run ops-robust "$ops" VELOX_ROBUST=1 --
[ $validate = none ] || test_run staging-validated "$staging" VELOX_VALIDATE=1 --
# Of the model tests, the autoencoder's (the others read fixtures the tree carries too, but
# take longer than they tell about the device).
test_run models-autoencoder "$models" VELOX_VALIDATE=$([ $validate = none ] && echo 0 || echo 1) -- autoencoder::
phase tests "$([ $status = 0 ] && echo ok || echo 'failed or cut')" "see the Tests table"

# 3. Benchmarks: ours in 60% of 45% of what is left, then PyTorch in the rest of that box.
bench_box=$(box 45)
bench_end=$(($(date +%s) + bench_box))
ours_end=$(($(date +%s) + bench_box * 60 / 100))
suites=(kernels attention raster layers models)
for i in "${!suites[@]}"; do
    suite=${suites[$i]}
    # An equal share of the time left for the suites not yet run.
    now=$(date +%s)
    # An equal share of what is left for the suites not yet run, and at least 30 s (or what is
    # left) for each in priority order.
    share=$(( (ours_end - now) / (${#suites[@]} - i) ))
    [ "$share" -ge 30 ] || share=$(( ours_end - now < 30 ? ours_end - now : 30 ))
    if [ "$share" -lt 10 ]; then
        say "bench $suite: skipped (time)"
        continue
    fi
    if run "$share" "$work/bench/$suite.txt" "$bin" bench "$suite" --json "$work/bench/$suite.json"; then
        say "bench $suite: done"
    else
        say "bench $suite: cut at ${share}s or failed (the records it finished are kept)"
    fi
done
torch_left=$((bench_end - $(date +%s)))
if [ "$torch_left" -ge 20 ] && python3 -c 'import torch' 2>/dev/null; then
    device=cuda
    python3 -c 'import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)' 2>/dev/null || device=cpu
    run "$torch_left" "$work/bench/torch.txt" python3 tools/peers/torch_bench.py --records "$work/bench" \
        --out "$work/bench/torch.json" --device $device --time-limit $((torch_left - 15))
    say "PyTorch beside us: $(grep -c '' "$work/bench/torch.txt") lines (bench/torch.txt)"
else
    say "PyTorch: not run ($([ "$torch_left" -ge 20 ] && echo 'import torch failed' || echo 'no time left'))"
fi
phase benchmarks done "$(ls "$work"/bench/*.json 2>/dev/null | wc -l) record files"

# 4. Training. The data first (a GPU renders it in seconds; it stays on the machine).
train_end=$(($(date +%s) + $(box 60)))
data=${TMPDIR:-/tmp}/velox-device-data-${SCENES:-256}-${RES:-128}
config=${CONFIG:-small}
if [ ! -d "$data/held-out" ]; then
    rm -rf "$data"
    run $((train_end - $(date +%s))) "$work/train/data.txt" "$bin" data synth --out "$data/train" \
        --scenes "${SCENES:-256}" --res "${RES:-128}" --points "${POINTS:-100000}" --seed 0 &&
        "$bin" data synth --out "$data/held-out" --scenes 4 --res "${RES:-128}" --points "${POINTS:-100000}" \
            --seed 100000 >>"$work/train/data.txt" 2>&1 || say "data: failed or cut (see train/data.txt)"
fi
say "data: $(ls "$data/train" 2>/dev/null | grep -c scene) training scenes"
precision=f32
[ $coop = yes ] && precision=f16
# Micro-batch 1 unless a larger one is measured to run; without a measured rate the time box
# alone ends the run (with its checkpoint).
batch=1
rate=0
kind=$(grep -o '"kind": *"[^"]*"' "$work/info.json" 2>/dev/null | head -1)
batches=(1 4 16 64)
[[ $kind == *CPU* ]] && batches=(1)
for b in "${batches[@]}"; do
    now=$(date +%s)
    probe_box=$(( (train_end - now) / 3 ))
    [ "$probe_box" -ge 15 ] || break
    "$bin" config "$config" | sed "s/\"batch\": [0-9]*/\"batch\": $b/" >"$work/train/config-b$b.json"
    if run "$probe_box" "$work/bench/train-batch$b.txt" "$bin" bench train --config "$work/train/config-b$b.json" \
        --batches "$b" --repeats 2 --precision "$precision" --json "$work/bench/train-batch$b.json" &&
        grep -q '"throughput"' "$work/bench/train-batch$b.json"; then
        batch=$b
        rate=$(grep -o '"throughput": [0-9.e+-]*' "$work/bench/train-batch$b.json" | tail -1 | awk '{print $2}')
    else
        break
    fi
done
rm -f "$work"/train/config-b*.json
code=1
while [ "$batch" -gt 0 ]; do
    "$bin" config "$config" | sed "s/\"batch\": [0-9]*/\"batch\": $batch/" >"$work/train/config.json"
    seconds=$((train_end - $(date +%s)))
    [ "$seconds" -ge 15 ] || break
    # Steps the box allows at the measured rate (a tenth kept for loading and checkpoints).
    steps=$(awk -v r="$rate" -v b="$batch" -v s="$seconds" 'BEGIN {n = r > 0 ? int(0.8 * s * r / b) : 100000; print (n < 5 ? 5 : n)}')
    say "training: $config config, micro-batch $batch, $rate samples/s ($precision), $steps steps in ${seconds}s"
    # SIGINT at the box: the run finishes its step, writes its checkpoint and exits with 130.
    timeout -k 30 --preserve-status -s INT "$seconds" "$bin" train autoencoder --data "$data/train" \
        --config "$work/train/config.json" --out "$work/train" --steps "$steps" --cooldown $((steps / 5)) \
        --checkpoint-every 200 --precision "$precision" >"$work/train/train.txt" 2>&1
    code=$?
    if [ $code -ne 0 ] && [ $code -ne 130 ] && [ "$batch" -gt 1 ] &&
        grep -q 'too large for this device' "$work/train/train.txt"; then
        say "micro-batch $batch is too large for the dataset's scenes; trying $((batch / 4))"
        batch=$((batch / 4))
        rate=$(awk -v r="$rate" 'BEGIN {print r / 2}')
        continue
    fi
    break
done
if [ -f "$work/train/checkpoint.safetensors" ]; then
    say "training: $(tail -2 "$work/train/train.txt" | head -1)"
    phase training "$([ $code = 0 ] || [ $code = 130 ] && echo ok || echo "failed ($code)")" "micro-batch $batch, $precision"
else
    status=1
    say "training: no checkpoint (see train/train.txt and bench/train-batch1.txt)"
    phase training FAILED "no checkpoint"
fi

# 5. Evaluation and the weights.
if [ -f "$work/train/checkpoint.safetensors" ]; then
    "$bin" weights "$work/train/checkpoint.safetensors" --out "$work/weights.safetensors" --max-part-mib 15 \
        >"$work/weights.txt" 2>&1 || { say "weights: failed (see weights.txt)"; status=1; }
    # A CPU device (a dry run) evaluates one scene at two frames and two views, with a short
    # sampling of the surface.
    small_eval=()
    [[ $kind == *CPU* ]] && small_eval=(--scenes 1 --frame-step 12 --views 2 --steps 4 --sampler euler --points 2000)
    if run $(($(left) - 10)) "$work/eval/eval.txt" "$bin" eval recon --data "$data/held-out" \
        --checkpoint "$work/weights.safetensors" --out "$work/eval" --precision "$precision" "${small_eval[@]}"; then
        say "eval: $(grep -m1 '^mean' "$work/eval/eval.txt")"
        phase evaluation ok "held-out scenes, from the weights file"
    else
        say "eval recon: failed or cut (see eval/eval.txt)"
        phase evaluation "failed or cut" ""
    fi
fi

say "done in $(($(date +%s) - start)) s"
phase packing done ""
if ! tools/device-results.sh "$work" "$out"; then
    echo "the results in $out break the limits above" >&2
    status=1
fi
ls -la "$out"
exit $status

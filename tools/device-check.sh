#!/usr/bin/env bash
# One call on a GPU machine, within a time budget, from what tools/device-pack.sh packed
# (target/device/ and .gl/): everything a first GPU can tell, and a trained model to bring back.
#   1. velox info (with the subgroup probe): OUT/device.txt, OUT/info.json;
#   2. the packed test binaries under the Khronos validation layer (synchronization checks,
#      descriptor-set binding): OUT/tests/<binary>.txt, one line each on the terminal;
#   3. the benchmark suites (tools/bench-all.sh), each within its share of the time:
#      OUT/bench/;
#   4. a training run of the small autoencoder on a procedural dataset made on the GPU: the
#      largest micro-batch (1, 4, 16, 64) that runs, its samples/s measured first, as many steps
#      as the minutes left allow (a cooldown over the last fifth), then `eval recon` on held-out
#      scenes: OUT/train/ (checkpoint, log.jsonl, loss.png, config), OUT/eval/ (eval.json,
#      side-by-side images). The dataset stays on the machine (the seed makes it again).
# Usage: tools/device-check.sh OUT [MINUTES]   (default 9; phases are cut to fit, and what a
# phase wrote before its cut is kept). Everything under OUT stays well under 60 MiB.
# SCENES and RES (default 256 and 128) size the dataset: a dry run on lavapipe takes
# SCENES=8 RES=48.
# Prepare the machine first (root): `for f in .gl/*.deb; do dpkg -x $f /; done; ldconfig` and,
# on NVIDIA, VK_DRIVER_FILES naming the driver's manifest.
set -uo pipefail
cd "$(dirname "$0")/.."
out=${1:?usage: tools/device-check.sh OUT [MINUTES]}
minutes=${2:-9}
start=$(date +%s)
deadline=$((start + minutes * 60 - 15))
left() { echo $((deadline - $(date +%s))); }
bin=target/device/velox
[ -x "$bin" ] || { echo "no $bin: run tools/device-pack.sh first" >&2; exit 1; }
mkdir -p "$out/tests" "$out/bench" "$out/train" "$out/eval"
data=${TMPDIR:-/tmp}/velox-device-data-${SCENES:-256}-${RES:-128}
status=0
say() { echo "[$(($(date +%s) - start))s] $*"; }

# 1. The device.
"$bin" info --probe --json "$out/info.json" >"$out/device.txt" 2>&1 || status=1
head -3 "$out/device.txt" | tail -1
say "info done"

# 2. Tests under validation (the layer unpacked from .gl; without it, plain, and said so).
export VK_LAYER_SETTINGS_PATH=$PWD/vk_layer_settings.txt
validate=1
[ -e /usr/share/vulkan/explicit_layer.d/VkLayer_khronos_validation.json ] || {
    validate=0
    echo "no validation layer installed (.gl/vulkan-validationlayers*.deb): tests run without it"
}
for b in target/device/tests/*; do
    name=$(basename "$b")
    name=${name%-*}
    budget=$(($(left) - 6 * 60))
    if [ "$budget" -lt 10 ]; then
        echo "SKIPPED $name (time)"
        continue
    fi
    # Of the model tests, the autoencoder's (the others read fixtures from the source tree).
    filter=()
    [ "$name" = models ] && filter=(autoencoder::)
    VELOX_VALIDATE=$validate timeout "$budget" "$b" -q "${filter[@]}" >"$out/tests/$name.txt" 2>&1
    code=$?
    if [ $code -eq 0 ]; then
        echo "ok      $name $(grep -o 'test result.*' "$out/tests/$name.txt" | tail -1)"
    elif [ $code -eq 124 ]; then
        echo "CUT     $name at ${budget}s (time; see tests/$name.txt)"
        status=1
    else
        echo "FAILED  $name (see tests/$name.txt)"
        status=1
    fi
done
say "tests done"

# 3. Benchmarks: each suite gets a share of what is left before the training's 5 minutes.
for suite in kernels attention layers raster models; do
    budget=$(($(left) - 5 * 60))
    [ "$budget" -gt 20 ] || { echo "bench $suite skipped (time)"; continue; }
    share=$((budget / 2 > 90 ? 90 : budget / 2))
    VELOX_BIN=$bin timeout "$share" tools/bench-all.sh "$out/bench" "$suite" >"$out/bench/$suite.log" 2>&1 ||
        echo "bench $suite: cut at ${share}s or failed (see bench/$suite.log)"
done
say "benchmarks done"

# 4. Training. The data first (the GPU renders it in seconds): 256 training scenes, 4 held out.
if [ ! -d "$data/train" ]; then
    "$bin" data synth --out "$data/train" --scenes "${SCENES:-256}" --res "${RES:-128}" --points "${POINTS:-100000}" \
        --seed 0 >"$out/train/data.txt" 2>&1 || status=1
    "$bin" data synth --out "$data/held-out" --scenes 4 --res "${RES:-128}" --points "${POINTS:-100000}" \
        --seed 100000 >>"$out/train/data.txt" 2>&1 || status=1
fi
say "data done"
# The largest micro-batch that runs, with its throughput, in the precision training takes by
# default (f16 where the device has cooperative matrices, else f32).
precision=f16
grep -q 'coop matrices     none' "$out/device.txt" && precision=f32
batch=0
rate=0
for b in 1 4 16 64; do
    [ "$(left)" -gt 200 ] || break
    "$bin" config small | sed "s/\"batch\": [0-9]*/\"batch\": $b/" >"$out/train/config-b$b.json"
    if timeout 60 "$bin" bench train --config "$out/train/config-b$b.json" --batches "$b" --repeats 3 \
        --precision "$precision" --json "$out/bench/train-batch$b.json" >"$out/bench/train-batch$b.txt" 2>&1; then
        batch=$b
        rate=$(grep -o '"throughput": [0-9.e+-]*' "$out/bench/train-batch$b.json" | tail -1 | awk '{print $2}')
    else
        break
    fi
done
rm -f "$out"/train/config-b*.json
# The benchmark's scenes are smaller than the dataset's (fewer points), so a micro-batch it ran
# can still be too large for the training's tensors: then a quarter of it is tried.
while [ "$batch" -gt 0 ]; do
    "$bin" config small | sed "s/\"batch\": [0-9]*/\"batch\": $batch/" >"$out/train/config.json"
    seconds=$(($(left) - 75))
    # Steps the time allows at the measured rate (a tenth kept for checkpoints and loading).
    steps=$(awk -v r="$rate" -v b="$batch" -v s="$seconds" 'BEGIN {n = int(0.9 * s * r / b); print (n < 10 ? 10 : n)}')
    say "training: micro-batch $batch, $rate samples/s ($precision), $steps steps in ${seconds}s"
    timeout --preserve-status -s INT "$seconds" "$bin" train autoencoder --data "$data/train" --config "$out/train/config.json" \
        --out "$out/train" --steps "$steps" --cooldown $((steps / 5)) --checkpoint-every 500 \
        --precision "$precision" \
        >"$out/train/train.txt" 2>&1
    code=$?
    if [ $code -ne 0 ] && [ $code -ne 130 ] && [ "$batch" -gt 1 ] &&
        grep -q 'stopped at step 1: too large for this device' "$out/train/train.txt"; then
        say "micro-batch $batch is too large for the dataset's scenes; trying $((batch / 4))"
        batch=$((batch / 4))
        # Its rate is not measured: half the larger batch's, a guess on the safe side (the
        # time box stops the run, with its checkpoint, either way).
        rate=$(awk -v r="$rate" 'BEGIN {print r / 2}')
        continue
    fi
    break
done
if [ "$batch" -gt 0 ]; then
    # 130: stopped by the time box after writing its checkpoint; --resume continues it.
    [ $code -eq 0 ] || [ $code -eq 130 ] || { echo "training failed ($code): see train/train.txt"; status=1; }
    tail -2 "$out/train/train.txt"
    if [ -f "$out/train/checkpoint.safetensors" ]; then
        timeout $(($(left) > 20 ? $(left) : 20)) "$bin" eval recon --data "$data/held-out" \
            --checkpoint "$out/train/checkpoint.safetensors" --out "$out/eval" >"$out/eval/eval.txt" 2>&1 ||
            { echo "eval recon failed or cut: see eval/eval.txt"; status=1; }
        tail -4 "$out/eval/eval.txt"
    fi
else
    echo "no batch of the small autoencoder ran: see bench/train-batch1.txt"
    status=1
fi
du -sh "$out"
say "done"
exit $status

#!/usr/bin/env bash
# Runs spirv-val on every SPIR-V module the build wrote, with the options the Khronos validation
# layer gives it on the devices the engine opens (Vulkan 1.3 rules, relaxed block layout, which
# Vulkan 1.1 made core, and LocalSizeId, which maintenance4, enabled by the engine, allows).
# Debian 12's spirv-val (2023.1) does not know the cooperative-matrix capability (6022), so the
# modules that use it are checked only by a newer one: tools/coop-check.sh runs this script in
# its Debian sid chroot. Usage: tools/spirv-check.sh [SPIRV_VAL]   (default: spirv-val on PATH)
set -uo pipefail
cd "$(dirname "$0")/.."
val=${1:-spirv-val}
command -v "$val" >/dev/null || { echo "spirv-check: no $val (Debian: apt-get install spirv-tools)" >&2; exit 1; }
out=$(ls -td target/release/build/velox-engine-*/out 2>/dev/null | head -1)
[ -n "$out" ] || { echo "spirv-check: no build output; run cargo build --release first" >&2; exit 1; }
checked=0
failed=0
skipped=0
for f in "$out"/*.spv; do
    if ! msg=$("$val" --target-env vulkan1.3 --relax-block-layout --allow-localsizeid "$f" 2>&1); then
        if grep -q 'Invalid capability operand: 6022' <<<"$msg"; then
            skipped=$((skipped + 1))
            continue
        fi
        echo "$(basename "$f"): $msg"
        failed=$((failed + 1))
    fi
    checked=$((checked + 1))
done
echo "spirv-check: $checked modules valid$([ $failed -gt 0 ] && echo ", $failed invalid")$([ $skipped -gt 0 ] && echo "; $skipped cooperative-matrix modules need a newer spirv-val than $("$val" --version | head -1)")"
[ $failed -eq 0 ]

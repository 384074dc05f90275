#!/usr/bin/env bash
# Packs what a GPU machine without a Rust toolchain or a network needs to test, benchmark and
# train with this tree, into two ignored folders to carry to it:
#   target/device/   the release `velox` and the engine-level test binaries (every op against its
#                    reference, the cooperative-matrix kernels among them, staging, the
#                    autoencoder's tests), stripped;
#   .gl/             the Vulkan loader's Debian package (amd64; unpacked there only where the
#                    machine has no loader) and, in .gl/vvl/, the newer Khronos validation layer
#                    (the build in Debian's chromium-common, xz-compressed, with its manifest):
#                    Debian 12's layer knows no VK_KHR_cooperative_matrix, so only this one can
#                    validate the tensor-core kernels.
# There, `tools/device-check.sh OUT [MINUTES]` does the rest (the README's "A first GPU, in one
# call" gives the call). The carried total must stay under the call's 64 MiB with the tree:
# this script prints it and fails when it is over.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release
mapfile -t bins < <(cargo test --release --no-run 2>&1 | grep -o 'target/release/deps/[A-Za-z0-9_-]*' | sort -u)
rm -rf target/device
mkdir -p target/device/tests
cp target/release/velox target/device/velox
for b in "${bins[@]}"; do
    name=$(basename "$b")
    case ${name%-*} in
        ops | staging | models) cp "$b" target/device/tests/ ;;
    esac
done
strip target/device/velox target/device/tests/*

grep -qx '/.gl/' .git/info/exclude 2>/dev/null || echo '/.gl/' >>.git/info/exclude
mkdir -p .gl/vvl
if ! ls .gl/libvulkan1_*.deb >/dev/null 2>&1; then
    command -v apt-get >/dev/null || { echo "device-pack: apt-get is needed to fetch libvulkan1" >&2; exit 1; }
    mkdir -p /tmp/amd64/partial
    o=(-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64)
    apt-get "${o[@]}" update -qq
    (cd .gl && apt-get "${o[@]}" download libvulkan1 >/dev/null)
fi
rm -f .gl/vulkan-validationlayers_*.deb
layer=/usr/lib/chromium/libVkLayer_khronos_validation.so
if [ ! -e "$layer" ]; then
    echo "device-pack: no $layer: install chromium-common (tools/setup.sh --tests does) for the newer validation layer" >&2
    exit 1
fi
if [ ! -e .gl/vvl/libVkLayer_khronos_validation.so.xz ] || [ "$layer" -nt .gl/vvl/libVkLayer_khronos_validation.so.xz ]; then
    xz -T0 -9 -c "$layer" >.gl/vvl/libVkLayer_khronos_validation.so.xz
fi
# The manifest names the library where device-check.sh unpacks it.
sed 's|"library_path": *"[^"]*"|"library_path": "./libVkLayer_khronos_validation.so"|' \
    tools/vvl/VkLayer_khronos_validation.json >.gl/vvl/VkLayer_khronos_validation.json

tree=$(git ls-files -z | xargs -0 du -cb 2>/dev/null | tail -1 | cut -f1)
carried=$(du -cb target/device .gl | tail -1 | cut -f1)
total=$((tree + carried))
echo "carried: target/device and .gl, $((carried / 1048576)) MiB; with the tree, $((total / 1048576)) MiB of the 64 MiB a call takes"
ls target/device/tests
[ "$total" -le $((64 * 1048576)) ] || { echo "device-pack: over 64 MiB" >&2; exit 1; }

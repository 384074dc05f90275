#!/usr/bin/env bash
# Packs what a GPU machine without a Rust toolchain or a network needs to test, benchmark and
# train with this tree, into ignored folders to pass to it (for example as carried paths):
#   target/device/   the release `velox` and the engine-level test binaries (every op against its
#                    reference, the cooperative-matrix kernels among them, the kernel-limit and
#                    subgroup checks, the autoencoder), stripped: about 45 MiB;
#   .gl/             the Debian packages of the Vulkan loader and the Khronos validation layer
#                    (amd64), unpacked there by tools/device-check.sh.
# There, run `tools/device-check.sh OUT [MINUTES]`.
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

# The loader and the validation layer, as packages for the machine's dpkg -x.
if command -v apt-get >/dev/null; then
    grep -qx '/.gl/' .git/info/exclude 2>/dev/null || echo '/.gl/' >>.git/info/exclude
    mkdir -p .gl /tmp/amd64/partial
    o=(-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64)
    apt-get "${o[@]}" update -qq
    (cd .gl && apt-get "${o[@]}" download libvulkan1 vulkan-validationlayers >/dev/null)
fi
du -sh target/device .gl 2>/dev/null
ls target/device/tests

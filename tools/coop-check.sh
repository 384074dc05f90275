#!/usr/bin/env bash
# Runs the test suite on lavapipe from Mesa 26 or later, which offers cooperative matrices
# (8x8x8 f16 fragments), so that the cooperative-matrix matmul and attention kernels run and
# are checked against their references on a machine without a GPU. CI's lavapipe (Mesa 25,
# bookworm-backports) has no cooperative matrices and runs the portable kernels instead.
#
# Needs root, debootstrap and network the first time: it builds a minimal Debian sid tree at
# $CHROOT (default /opt/velox-sid) with mesa-vulkan-drivers, spirv-tools and the validation
# layers, then bind-mounts the repository into it and, inside it, checks every SPIR-V module with
# sid's spirv-val (tools/spirv-check.sh: the only one here that knows cooperative matrices) and
# runs the test binaries built here (`cargo test --release --no-run`). VELOX_VALIDATE=1 runs them
# under sid's validation layer, which knows VK_KHR_cooperative_matrix (Debian 12's does not).
#
#   sudo tools/coop-check.sh            # every test binary
#   sudo tools/coop-check.sh ops        # only binaries whose name starts with "ops"
set -euo pipefail

repo=$(cd "$(dirname "$0")/.." && pwd)
chroot_dir=${CHROOT:-/opt/velox-sid}
filter=${1:-}

if [ ! -e "$chroot_dir/usr/share/vulkan/icd.d/lvp_icd.json" ]; then
    command -v debootstrap >/dev/null || apt-get install -y debootstrap
    [ -e "$chroot_dir/bin/sh" ] || debootstrap --variant=minbase sid "$chroot_dir" http://deb.debian.org/debian
    # A sid snapshot's Release file may be past its Valid-Until date; the packages are fine.
    chroot "$chroot_dir" apt-get -o Acquire::Check-Valid-Until=false update
    chroot "$chroot_dir" env DEBIAN_FRONTEND=noninteractive \
        apt-get -o Acquire::Check-Valid-Until=false install -y mesa-vulkan-drivers libvulkan1
fi
for p in spirv-tools vulkan-validationlayers; do
    chroot "$chroot_dir" dpkg -s "$p" >/dev/null 2>&1 || chroot "$chroot_dir" env DEBIAN_FRONTEND=noninteractive \
        apt-get -o Acquire::Check-Valid-Until=false install -y "$p"
done

# The same path inside as outside, so the binaries find the repository's files.
mkdir -p "$chroot_dir$repo" "$chroot_dir/proc" "$chroot_dir/dev"
mountpoint -q "$chroot_dir$repo" || mount --bind "$repo" "$chroot_dir$repo"
mountpoint -q "$chroot_dir/proc" || mount -t proc proc "$chroot_dir/proc"
mountpoint -q "$chroot_dir/dev" || mount --bind /dev "$chroot_dir/dev"

cd "$repo"
mapfile -t bins < <(cargo test --release --no-run 2>&1 | grep -o 'target/release/deps/[A-Za-z0-9_-]*' | sort -u)
echo "device inside the chroot:"
chroot "$chroot_dir" sh -c "cd '$repo' && ./target/release/velox info | grep -E 'Chosen|coop matrices|  (attention|matmul) f16'"
failed=0
chroot "$chroot_dir" sh -c "cd '$repo' && tools/spirv-check.sh" || failed=1
export VK_LAYER_SETTINGS_PATH=$repo/vk_layer_settings.txt
for b in "${bins[@]}"; do
    name=$(basename "$b")
    [[ -n $filter && $name != "$filter"* ]] && continue
    echo "== $name"
    if ! chroot "$chroot_dir" sh -c "cd '$repo' && ./$b -q"; then
        failed=1
    fi
done
exit $failed

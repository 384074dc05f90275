#!/usr/bin/env bash
# Runs the test suite on lavapipe from Mesa 26 or later, which offers cooperative matrices
# (8x8x8 f16 fragments), so that the cooperative-matrix matmul and attention kernels run and
# are checked against their references on a machine without a GPU. CI's lavapipe (Mesa 25,
# bookworm-backports) has no cooperative matrices and runs the portable kernels instead.
#
# Needs root (or sudo), and debootstrap and network the first time: it builds a minimal Debian sid tree at
# $CHROOT (default /opt/velox-sid) with mesa-vulkan-drivers, spirv-tools and the validation
# layers, then bind-mounts the repository into it and, inside it, checks every SPIR-V module with
# sid's spirv-val (tools/spirv-check.sh: the only one here that knows cooperative matrices) and
# runs the test binaries built here (`cargo test --release --no-run`) with the GPU kernel
# variants (VELOX_CPU_KERNELS=0: on a CPU device the engine otherwise keeps its CPU kernels,
# faster there than emulated fragments). VELOX_VALIDATE=1 runs them under sid's validation
# layer, which knows VK_KHR_cooperative_matrix (Debian 12's does not).
#
#   tools/coop-check.sh                  # every test binary
#   tools/coop-check.sh ops training     # only the binaries of these names
#   tools/coop-check.sh models:attention # only the models binary's tests matching "attention"
# Exit status: 0 passed, 1 a check failed, 2 this machine cannot run it (no root or sudo, no
# network for the first build, bind mounts refused); tools/test.sh runs it where it can.
set -euo pipefail

repo=$(cd "$(dirname "$0")/.." && pwd)
chroot_dir=${CHROOT:-/opt/velox-sid}
filters=("$@")
SUDO=""
[ "$(id -u)" -eq 0 ] || SUDO="sudo"

# Exit status 2: this machine cannot run the check (no root, no network for the first build,
# no bind mounts), as opposed to 1, a check that ran and failed.
cannot() {
    echo "coop-check: cannot run here: $*" >&2
    exit 2
}
[ -z "$SUDO" ] || command -v sudo >/dev/null || cannot "needs root or sudo (chroot, mount)"

if [ ! -e "$chroot_dir/usr/share/vulkan/icd.d/lvp_icd.json" ]; then
    echo "coop-check: building a Debian sid tree with Mesa's lavapipe at $chroot_dir (once, about a minute)"
    command -v debootstrap >/dev/null || $SUDO apt-get install -y -qq debootstrap >/dev/null ||
        cannot "apt-get could not install debootstrap"
    [ -e "$chroot_dir/bin/sh" ] ||
        $SUDO debootstrap --variant=minbase sid "$chroot_dir" http://deb.debian.org/debian >/dev/null ||
        cannot "debootstrap could not build the sid tree (network?)"
    # A sid snapshot's Release file may be past its Valid-Until date; the packages are fine.
    $SUDO chroot "$chroot_dir" apt-get -qq -o Acquire::Check-Valid-Until=false update ||
        cannot "apt-get update in the sid tree failed (network?)"
    $SUDO chroot "$chroot_dir" env DEBIAN_FRONTEND=noninteractive \
        apt-get -qq -o Acquire::Check-Valid-Until=false install -y mesa-vulkan-drivers libvulkan1 >/dev/null ||
        cannot "apt-get could not install Mesa in the sid tree"
fi
for p in spirv-tools vulkan-validationlayers; do
    $SUDO chroot "$chroot_dir" dpkg -s "$p" >/dev/null 2>&1 || $SUDO chroot "$chroot_dir" env DEBIAN_FRONTEND=noninteractive \
        apt-get -qq -o Acquire::Check-Valid-Until=false install -y "$p" >/dev/null ||
        cannot "apt-get could not install $p in the sid tree"
done

# The same path inside as outside, so the binaries find the repository's files.
$SUDO mkdir -p "$chroot_dir$repo" "$chroot_dir/proc" "$chroot_dir/dev"
mountpoint -q "$chroot_dir$repo" || $SUDO mount --bind "$repo" "$chroot_dir$repo" || cannot "bind mount refused"
mountpoint -q "$chroot_dir/proc" || $SUDO mount -t proc proc "$chroot_dir/proc" || cannot "mounting /proc refused"
mountpoint -q "$chroot_dir/dev" || $SUDO mount --bind /dev "$chroot_dir/dev" || cannot "bind mount refused"

cd "$repo"
# The executables' paths as cargo names them (absolute), wherever the target directory is:
# CARGO_TARGET_DIR, a build target or a symlinked target/ may put it outside the repository.
mapfile -t exes < <(cargo test --release --no-run --message-format=json 2>/dev/null |
    grep -o '"executable":"[^"]*"' | sed 's/^"executable":"//; s/"$//' | sort -u)
bins=() velox=""
for e in "${exes[@]}"; do
    case $e in
    */deps/*) bins+=("$e") ;;
    */velox) velox=$e ;;
    esac
done
[ ${#bins[@]} -gt 0 ] || { echo "coop-check: cargo test --no-run built no test binaries" >&2; exit 1; }
[ -n "$velox" ] || { echo "coop-check: cargo test --no-run built no velox command" >&2; exit 1; }
# A target directory outside the repository is mounted into the tree at its own path too (the
# real path: a symlink to it, in the repository, then resolves inside the tree as well).
target=$(realpath "$(dirname "$velox")")
case $target/ in
"$(realpath "$repo")"/*) ;;
*)
    $SUDO mkdir -p "$chroot_dir$target"
    mountpoint -q "$chroot_dir$target" || $SUDO mount --bind "$target" "$chroot_dir$target" || cannot "bind mount refused"
    ;;
esac
# A mount the tree does not see through (a filesystem that refuses bind mounts quietly) is
# this machine's limit, not a failed check.
for f in "$velox" "${bins[0]}"; do
    $SUDO chroot "$chroot_dir" test -x "$f" || cannot "the sid tree does not see $f through its mounts"
done
echo "device inside the chroot:"
$SUDO chroot "$chroot_dir" env VELOX_CPU_KERNELS=0 sh -c "cd '$repo' && '$velox' info | grep -E 'Chosen|coop matrices|  (attention|matmul) f16'"
failed=0
$SUDO chroot "$chroot_dir" sh -c "cd '$repo' && tools/spirv-check.sh" || failed=1
export VK_LAYER_SETTINGS_PATH=$repo/vk_layer_settings.txt
log=$(mktemp)
trap 'rm -f "$log"' EXIT
run_bin() { # binary, test filter (may be empty)
    echo "== $(basename "$1") $2"
    local rc=0
    $SUDO chroot "$chroot_dir" env VELOX_CPU_KERNELS=0 VELOX_VALIDATE="${VELOX_VALIDATE:-}" \
        VK_LAYER_SETTINGS_PATH="$VK_LAYER_SETTINGS_PATH" sh -c "cd '$repo' && '$1' -q $2" 2>&1 |
        tee "$log" || rc=${PIPESTATUS[0]}
    # sid's validation layer sometimes crashes in its own teardown at exit (abort or segfault
    # in vkDestroyDevice's layer code, after the last test): with every test passed, and any
    # validation error that arrived after a submit reported before exit (exit status 1,
    # engine/tests/common), that is the layer's failure, not the kernels'.
    if [[ -n ${VELOX_VALIDATE:-} && ($rc == 134 || $rc == 139) ]] && grep -q '^test result: ok' "$log"; then
        echo "(the validation layer crashed at exit after every test passed: counted as passed)"
        rc=0
    fi
    [ $rc = 0 ] || failed=1
}
for b in "${bins[@]}"; do
    name=$(basename "$b")
    if [ ${#filters[@]} -eq 0 ]; then
        run_bin "$b" ""
        continue
    fi
    for f in "${filters[@]}"; do
        # NAME or NAME:FILTER (the binary's tests whose names contain FILTER).
        [[ $name == "${f%%:*}"-* ]] || continue
        if [[ $f == *:* ]]; then run_bin "$b" "${f#*:}"; else run_bin "$b" ""; fi
    done
done
exit $failed

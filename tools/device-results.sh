#!/usr/bin/env bash
# Packs a device check's results (tools/device-check.sh's scratch folder WORK) into OUT as the few
# files a GPU machine's call can return, and checks them against those limits:
#   OUT/summary.md      `velox bench report WORK`: device, tests, every bench row beside PyTorch's,
#                       training, evaluation;
#   OUT/logs.tar.gz     everything else in WORK (logs, JSON records, loss plot, eval images), the
#                       dataset and checkpoints left out; split into logs.tar.gz.NN parts of the
#                       per-file limit where larger (`cat logs.tar.gz.* > logs.tar.gz` joins them);
#   OUT/weights*.safetensors   the trained model's weights (`velox weights`), as WORK holds them.
# Limits (environment, for tests): RESULT_MAX_FILES (8), RESULT_MAX_FILE_BYTES (16 MiB),
# RESULT_MAX_TOTAL_BYTES (64 MiB), RESULT_MAX_DEPTH (2 folders below OUT); names of letters,
# digits, '.', '_' and '-' only. A result that breaks one is named with the limit, and the exit
# status is 1. VELOX_BIN names the velox binary (default target/device/velox, else
# target/release/velox). Usage: tools/device-results.sh WORK OUT
set -uo pipefail
cd "$(dirname "$0")/.."
work=${1:?usage: tools/device-results.sh WORK OUT}
out=${2:?usage: tools/device-results.sh WORK OUT}
max_files=${RESULT_MAX_FILES:-8}
max_file=${RESULT_MAX_FILE_BYTES:-16777216}
max_total=${RESULT_MAX_TOTAL_BYTES:-67108864}
max_depth=${RESULT_MAX_DEPTH:-2}
bin=${VELOX_BIN:-target/device/velox}
[ -x "$bin" ] || bin=target/release/velox
mkdir -p "$out" || exit 1
size() { stat -c %s "$1"; }

# 1. The summary (written to a temporary name, then renamed: a cut leaves the last whole one).
if ! "$bin" bench report "$work" --out "$out/.summary.md.tmp" >/dev/null 2>"$work/report-error.txt"; then
    { echo "# Velox on this device"; echo; echo "The report could not be made:"; cat "$work/report-error.txt"; } \
        >"$out/.summary.md.tmp"
fi
mv -f "$out/.summary.md.tmp" "$out/summary.md"

# 2. The logs. Images go first when the archive is over the per-file limit, then it is split.
rm -f "$out"/logs.tar.gz*
archive() {
    tar -C "$work" --exclude=./data --exclude='*.safetensors' --exclude='*.partial' "$@" -czf "$out/.logs.tmp" . &&
        mv -f "$out/.logs.tmp" "$out/logs.tar.gz"
}
archive || echo "device-results: could not archive $work" >&2
if [ -f "$out/logs.tar.gz" ] && [ "$(size "$out/logs.tar.gz")" -gt "$max_file" ]; then
    archive --exclude='*.png' --exclude='*.gif'
    echo "- logs.tar.gz leaves out the images: with them it was over $max_file bytes" >>"$out/summary.md"
fi
if [ -f "$out/logs.tar.gz" ] && [ "$(size "$out/logs.tar.gz")" -gt "$max_file" ]; then
    split -d -b "$max_file" "$out/logs.tar.gz" "$out/logs.tar.gz." && rm -f "$out/logs.tar.gz"
    echo "- logs.tar.gz is in parts: \`cat logs.tar.gz.* > logs.tar.gz\`" >>"$out/summary.md"
fi

# 3. The weights.
rm -f "$out"/weights*.safetensors
for w in "$work"/weights*.safetensors; do
    [ -e "$w" ] && cp "$w" "$out/"
done

# The files that come back, listed at the end of the summary.
{
    echo
    echo "## Files"
    echo
    (cd "$out" && find . -type f ! -name summary.md -printf '%P\t%s\n' | sort) |
        while IFS=$'\t' read -r name bytes; do echo "- $name ($bytes bytes)"; done
} >>"$out/summary.md"

# The limits.
status=0
broke() { echo "device-results: $*" >&2; status=1; }
files=0
total=0
while IFS= read -r -d '' f; do
    rel=${f#"$out"/}
    files=$((files + 1))
    bytes=$(size "$f")
    total=$((total + bytes))
    [ "$bytes" -le "$max_file" ] || broke "$rel: $bytes bytes, over the limit of $max_file bytes a file"
    depth=$(($(tr -cd / <<<"$rel" | wc -c)))
    [ "$depth" -le "$max_depth" ] || broke "$rel: $depth folders down, over the limit of $max_depth"
    # Every part of the path, folders included.
    [[ $rel =~ ^[A-Za-z0-9._/-]+$ ]] || broke "$rel: a name with characters other than letters, digits, '.', '_' and '-'"
done < <(find "$out" -type f -print0)
[ "$files" -le "$max_files" ] || broke "$out holds $files files, over the limit of $max_files"
[ "$total" -le "$max_total" ] || broke "$out holds $total bytes, over the limit of $max_total bytes in all"
exit $status

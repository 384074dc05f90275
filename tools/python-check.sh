#!/usr/bin/env bash
# The Python package's tests (python/tests, pytest), as a user gets the package: its wheel
# built from ./python by pip (maturin, the same build `pip install ./python` runs), then
# installed with its dependencies into a fresh venv on a PATH without Rust, and the tests run
# against the `velox` command the suite built (target/release/velox).
# Usage: tools/python-check.sh [pytest arguments]
set -euo pipefail
cd "$(dirname "$0")/.."

work=target/python-check
rm -rf "$work"
python3 -m venv "$work/build"
"$work/build/bin/pip" install -q --upgrade pip
"$work/build/bin/pip" wheel -q --no-deps ./python -w "$work/wheels"
wheel=$(ls "$work"/wheels/velox-*.whl)

python3 -m venv "$work/venv"
# No cargo on the PATH: the wheel installs and runs without Rust.
env PATH="$PWD/$work/venv/bin:/usr/bin:/bin" "$work/venv/bin/pip" install -q "$wheel" pytest
cargo build --release -q --bin velox
cd "$work"
env PATH="$PWD/venv/bin:/usr/bin:/bin" VELOX_BIN="$OLDPWD/target/release/velox" \
  venv/bin/python -m pytest -q "$OLDPWD/python/tests" "$@"

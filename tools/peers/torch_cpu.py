#!/usr/bin/env python3
# PyTorch on the CPU beside lavapipe: tools/peers/torch_bench.py with --device cpu and the
# thread count lavapipe uses (LP_NUM_THREADS, else 1), so our kernels on lavapipe and PyTorch's
# run on the same cores. Usage: python3 tools/peers/torch_cpu.py --records DIR --out FILE [...]
"""tools/peers/torch_bench.py on the CPU with lavapipe's thread count (LP_NUM_THREADS)."""

import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import torch_bench  # noqa: E402 (found beside this file)

if __name__ == "__main__":
    threads = os.environ.get("LP_NUM_THREADS", "1")
    sys.exit(torch_bench.main(sys.argv[1:] + ["--device", "cpu", "--threads", threads]))

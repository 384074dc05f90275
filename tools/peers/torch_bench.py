#!/usr/bin/env python3
# PyTorch beside `velox bench`: times PyTorch at the shape and precision of every record our
# benchmarks wrote, so a summary can print each of our rows with PyTorch's time and the ratio.
#
# Usage:
#   python3 tools/peers/torch_bench.py --records DIR_OR_FILE... --out torch.json \
#       [--device cuda|cpu] [--threads N] [--repeats N] [--time-limit SECONDS] \
#       [--suites kernels,attention,layers,models]
# DIR_OR_FILE: record files of `velox bench kernels|attention|layers|models --json FILE`, or
# folders of them (every *.json that holds a list of records; others are passed over).
# tools/peers/torch_cpu.py runs this on the CPU with lavapipe's thread count.
"""Times PyTorch at the shapes and precisions of our benchmark records.

For every record it can map (matmuls, softmax, scan, sort, scatter-add, row gathers; fused
attention; the layers; the encoder network) it builds the same computation in PyTorch on random inputs and
times it with our policy (`tools/src/bench/mod.rs`, `time_gpu`): one warm-up run, then the
record's `repeats` runs (or `--repeats`), each timed alone with an idle gap after it, the
median (the upper one for an even count, as ours) and the minimum reported; no cache flush on
either side. Ours: GPU timestamps around one submission, a wait after each. PyTorch on CUDA:
CUDA events around the call and a synchronize after each; on the CPU: time.perf_counter
around the call. f32 matrix products run without TF32 and f16 products reduce in f32.

What cannot be mapped faithfully (farthest point sampling, the nearest-query assignment, the
decoders and the other models) is skipped with the reason printed. Each record's `note` says
where PyTorch's computation differs from ours (output precision, equal segments, what the
encoder leaves out). The output file is rewritten after every case, so a stopped run keeps
what it measured.
"""

import argparse
import contextlib
import gc
import glob
import json
import math
import os
import re
import sys
import tempfile
import time
from dataclasses import dataclass
from typing import Callable, NamedTuple, Optional

try:
    import torch
    import torch.nn.functional as F
except (ImportError, OSError) as error:  # OSError: a wheel whose CUDA libraries do not load
    torch = None
    TORCH_IMPORT_ERROR = error

SUITES = ("kernels", "attention", "layers", "models")
RECORD_KEYS = ("name", "shape", "precision", "median_ms", "repeats")
# Name prefixes of each suite's records (tools/src/bench/*.rs).
SUITE_PREFIXES = {
    "kernels": ("matmul", "softmax", "exclusive scan", "radix sort", "scatter-add", "gather rows",
                "farthest point sampling", "nearest-query assignment"),
    "attention": ("attn ", "window matmuls"),
    "layers": ("linear (bias)", "rmsnorm", "layernorm (affine)", "swiglu feed-forward",
               "gelu feed-forward", "fourier embedding"),
    "models": ("encoder", "gaussian decoder", "surface decoder", "voxel decoder",
               "tracking network", "DINOv2", "generator"),
}
NORM_EPS = 1e-6  # models/src/velox/blocks.rs NORM_EPS, tools/src/bench/layers.rs
WINDOW = 32  # tokens of an encoder self-attention window (tools/src/bench/attention.rs)


class Unmapped(Exception):
    """A record this script has no faithful PyTorch counterpart for; the message says why."""


@dataclass
class Case:
    torch_op: str
    note: str
    run: Callable[[], object]
    # Backward rows: the forward alone; the backward's time is run's minus this one's.
    forward: Optional[Callable[[], object]] = None


def suite_of(name):
    for suite, prefixes in SUITE_PREFIXES.items():
        if name.startswith(prefixes):
            return suite
    return None


def parse(pattern, shape, what):
    """The integers of `shape` matched against `pattern`, or Unmapped."""
    match = re.fullmatch(pattern, shape)
    if not match:
        raise Unmapped(f"shape {shape!r} is not the {what} shape this script reads")
    return [int(g) if g and g.isdigit() else g for g in match.groups()]


def plural(count, noun, nouns=None):
    return f"{count} {noun if count == 1 else nouns or noun + 's'}"


def normal(shape, dev, dtype=None):
    x = torch.randn(shape, device=dev)
    return x if dtype is None else x.to(dtype)


def float_dtype(precision, f16=True):
    """torch.float32 for our "f32"; torch.float16 for our f16 precisions ("f16", "f16->f32",
    "f16 coop", ...: f16 operands) where the case has an f16 form."""
    if precision == "f32":
        return torch.float32
    if f16 and precision.startswith("f16"):
        return torch.float16
    raise Unmapped(f"precision {precision!r} has no mapping here")


def rms_norm(x, weight):
    if hasattr(F, "rms_norm"):  # torch >= 2.4; the weight in x's dtype keeps the fused kernel
        return F.rms_norm(x, (x.shape[-1],), weight.to(x.dtype), NORM_EPS)
    return x * torch.rsqrt(x.pow(2).mean(-1, keepdim=True) + NORM_EPS) * weight


def log_spaced(count, max_octave, dev):
    """Frequencies 2^0 .. 2^max_octave evenly spaced in log2 (Fourier::log_spaced)."""
    step = max_octave / (count - 1) if count > 1 else 0.0
    return torch.tensor([2.0 ** (step * f) for f in range(count)], device=dev)


def fourier(x, freqs):
    """[x, sin(pi w_f x_i) at i F + f, cos(pi w_f x_i) at c F + i F + f] (layers/fourier.rs)."""
    angles = (math.pi * x.unsqueeze(-1) * freqs).flatten(-2)
    return torch.cat([x, torch.sin(angles), torch.cos(angles)], -1)


def with_grads(f, inputs, dy):
    """Forward and the backward of `(f() * dy).sum()` w.r.t. `inputs`."""
    return lambda: torch.autograd.grad(f(), inputs, dy)


# --- kernels ---------------------------------------------------------------------------------

def matmul_case(record, dev):
    m, n, k, transposed = parse(r"(\d+)x(\d+)x(\d+)( \(a\^T\))?", record["shape"], "matmul")
    dtype = float_dtype(record["precision"])
    b = normal([k, n], dev, dtype)
    if transposed:
        a_stored = normal([k, m], dev, dtype)
        run, op = (lambda: torch.matmul(a_stored.t(), b)), "torch.matmul(a.t(), b)"
        layout = "a stored [k, m] as ours, passed transposed (a view); "
    else:
        a = normal([m, k], dev, dtype)
        run, op, layout = (lambda: torch.matmul(a, b)), "torch.matmul", ""
    if dtype == torch.float16:
        return Case(f"{op} f16 (f16 output)", layout + "f16 operands; torch writes an f16 "
                    "output where ours writes f32 (half the output bytes)", run)
    return Case(f"{op} f32", layout + "TF32 off", run)


def softmax_case(record, dev):
    rows, length = parse(r"(\d+)x(\d+)", record["shape"], "softmax")
    float_dtype(record["precision"], f16=False)
    x = normal([rows, length], dev) * 10.0
    return Case("torch.softmax(x, -1) f32", "rows of normal * 10, as ours", lambda: torch.softmax(x, -1))


def scan_case(record, dev):
    (n,) = parse(r"(\d+)", record["shape"], "scan")
    if record["precision"] != "u32":
        raise Unmapped(f"precision {record['precision']!r} has no mapping here")
    x = torch.randint(0, 1000, (n,), device=dev, dtype=torch.int32)
    return Case("torch.cumsum(x, 0, dtype=int32) - x", "int32 for our u32 (the same bytes); "
                "exclusive = inclusive cumsum minus x, both kernels timed",
                lambda: torch.cumsum(x, 0, dtype=torch.int32) - x)


def sort_case(record, dev):
    n, bits = parse(r"(\d+) x (\d+) bits", record["shape"], "sort")
    if record["precision"] != "u32" or not 1 <= bits <= 32:
        raise Unmapped(f"{bits}-bit {record['precision']} keys have no mapping here")
    # int32 keys hold our u32 keys shifted by 2^31 for 32 bits (the same order), as they are below.
    low = -(2 ** 31) if bits == 32 else 0
    keys = torch.randint(low, low + 2 ** bits, (n,), device=dev, dtype=torch.int32)
    values = torch.arange(n, device=dev, dtype=torch.int32)

    def run():
        sorted_keys, order = torch.sort(keys, stable=True)
        return sorted_keys, values[order]
    return Case("torch.sort(int32 keys, stable=True) + values[indices]",
                f"int32 keys of {bits} random bits (our u32 keys, the same width); torch sorts on "
                f"all 32 key bits where ours sorts on {bits}; the value gather is timed", run)


def scatter_case(record, dev):
    rows, width, dst_rows = parse(r"(\d+)x(\d+) -> (\d+)", record["shape"], "scatter-add")
    float_dtype(record["precision"], f16=False)
    src = normal([rows, width], dev)
    index = torch.randint(0, dst_rows, (rows,), device=dev)
    out = torch.empty(dst_rows, width, device=dev)

    def run():
        out.zero_()
        return out.index_add_(0, index, src)
    return Case("out.zero_(); out.index_add_(0, index, src)", "int64 row indices (ours: u32); "
                "the zero fill is timed, as ours", run)


def gather_case(record, dev):
    rows, src_rows, width = parse(r"(\d+) of (\d+)x(\d+)", record["shape"], "gather rows")
    float_dtype(record["precision"], f16=False)
    src = normal([src_rows, width], dev)
    index = torch.randint(0, src_rows, (rows,), device=dev)
    return Case("src.index_select(0, index)", "int64 row indices (ours: u32)",
                lambda: src.index_select(0, index))


# --- attention -------------------------------------------------------------------------------

def sdpa_kernels(q, k, v):
    """Which fused SDPA kernels accept these CUDA inputs, as a note ('' where torch cannot say)."""
    cuda = torch.backends.cuda
    checks = [("flash", "can_use_flash_attention"), ("mem-efficient", "can_use_efficient_attention"),
              ("cudnn", "can_use_cudnn_attention")]
    try:
        params = cuda.SDPAParams(q, k, v, None, 0.0, False, False)
        usable = [name for name, check in checks
                  if hasattr(cuda, check) and getattr(cuda, check)(params, False)]
    except (AttributeError, TypeError, RuntimeError):
        return ""
    return "; SDPA kernels that accept these inputs: " + (", ".join(usable) or "none (math)")


def attention_case(record, dev):
    what, passes = parse(r"attn (.+) (fwd|bwd)", record["name"], "attention name")
    nq, nk, heads, d, segments = parse(r"(\d+)x(\d+) h(\d+) d(\d+) \((\d+) seg\)", record["shape"],
                                       "attention")
    dtype = float_dtype(record["precision"])
    lq, lk = math.ceil(nq / segments), math.ceil(nk / segments)
    self_attention = "self" in what
    q = normal([segments, heads, lq, d], dev, dtype)
    k = q if self_attention else normal([segments, heads, lk, d], dev, dtype)
    v = normal([segments, heads, lk, d], dev, dtype)
    note = (f"{plural(segments, 'equal segment')} of {plural(lq, 'query', 'queries')} "
            f"and {plural(lk, 'key')}, layout [batch, heads, len, d] (ours: {plural(segments, 'segment')} of "
            f"varying length, {nq} queries and {nk} keys in all): the most favourable case for PyTorch")
    if self_attention:
        note += "; q and k one tensor, as ours"
    if dtype == torch.float16:
        note += ("; f16 q, k, v, output and output gradient (ours: f32 output and gradient)"
                 + ("; ours: the cooperative-matrix kernel" if "coop" in record["precision"] else ""))

    def attend():
        return F.scaled_dot_product_attention(q, k, v)  # scale 1/sqrt(d), as ours
    op = f"F.scaled_dot_product_attention {'f16' if dtype == torch.float16 else 'f32'}"
    if passes == "fwd":
        return Case(op, note + (sdpa_kernels(q, k, v) if dev.type == "cuda" else ""), attend)
    leaves = (q, v) if self_attention else (q, k, v)
    for t in leaves:
        t.requires_grad_(True)
    dy = normal([segments, heads, lq, d], dev, dtype)
    note += ("; backward = (forward + torch.autograd.grad w.r.t. q, k, v) minus the forward, each "
             "timed as above, medians and minima apart" +
             (" (autograd sums q's and k's gradients)" if self_attention else ""))
    return Case(op + " backward", note + (sdpa_kernels(q, k, v) if dev.type == "cuda" else ""),
                with_grads(attend, leaves, dy), forward=attend)


def window_matmuls_case(record, dev):
    batch, rows, rows_again, d = parse(r"(\d+) x \((\d+)x(\d+)x(\d+)\) x2", record["shape"],
                                       "window matmuls")
    dtype = float_dtype(record["precision"])
    q = normal([batch, rows, d], dev, dtype)
    p = normal([batch, rows, rows_again], dev, dtype)

    def run():
        return torch.bmm(q, q.transpose(1, 2)), torch.bmm(p, q)
    output = "f16 outputs (ours: f32)" if dtype == torch.float16 else "TF32 off"
    return Case("torch.bmm(q, q^T), torch.bmm(p, q)", f"S = Q Q^T and O = P Q as ours; {output}", run)


# --- layers ----------------------------------------------------------------------------------

def layer_case(record, dev):
    base, passes = parse(r"(.+) (fwd|fwd\+bwd)", record["name"], "layer name")
    float_dtype(record["precision"], f16=False)
    shape = record["shape"]
    if base == "fourier embedding":
        points, width = parse(r"(\d+)x3 -> (\d+)", shape, "fourier embedding")
        if (width - 3) % 6:
            raise Unmapped(f"width {width} is not 3 + 6 F for F frequencies")
        freqs = log_spaced((width - 3) // 6, 12.0, dev)
        x, params = torch.rand(points, 3, device=dev) * 2 - 1, []

        def layer():
            return fourier(x, freqs)
        op = "sin, cos of pi w_f x, torch.cat"
        note = (f"{(width - 3) // 6} frequencies 2^0..2^12 log-spaced, the input kept, in our layout "
                "(models/src/layers/fourier.rs)")
    elif base == "linear (bias)":
        rows, d_in, d_out = parse(r"(\d+)x(\d+) -> (\d+)", shape, "linear")
        x, b = normal([rows, d_in], dev), normal([d_out], dev)
        w = normal([d_out, d_in], dev) / math.sqrt(d_in)
        params, op, note = [w, b], "F.linear (nn.Linear, bias)", "TF32 off"

        def layer():
            return F.linear(x, w, b)
    elif base == "rmsnorm":
        rows, d = parse(r"(\d+)x(\d+)", shape, base)
        x, g = normal([rows, d], dev), normal([d], dev)
        params, op, note = [g], "F.rms_norm", f"eps {NORM_EPS}"

        def layer():
            return rms_norm(x, g)
    elif base == "layernorm (affine)":
        rows, d = parse(r"(\d+)x(\d+)", shape, base)
        x, g, b = normal([rows, d], dev), normal([d], dev), normal([d], dev)
        params, op, note = [g, b], "F.layer_norm (affine)", f"eps {NORM_EPS}"

        def layer():
            return F.layer_norm(x, (d,), g, b, NORM_EPS)
    elif base in ("swiglu feed-forward", "gelu feed-forward"):
        rows, d, hidden, d_out = parse(r"(\d+)x(\d+) -> (\d+) -> (\d+)", shape, base)
        x = normal([rows, d], dev)
        w1, w3 = (normal([hidden, d], dev) / math.sqrt(d) for _ in range(2))
        w2 = normal([d_out, hidden], dev) / math.sqrt(hidden)
        b1, b2 = normal([hidden], dev), normal([d_out], dev)
        if base == "swiglu feed-forward":
            params, op, note = [w1, w3, w2], "w2(silu(x w1) * (x w3)), no biases", "TF32 off"

            def layer():
                return F.linear(F.silu(F.linear(x, w1)) * F.linear(x, w3), w2)
        else:
            params, op = [w1, b1, w2, b2], "w2(gelu(x w1 + b1)) + b2"
            note = "exact (erf) GELU, as ours; TF32 off"

            def layer():
                return F.linear(F.gelu(F.linear(x, w1, b1)), w2, b2)
    else:
        raise Unmapped(f"layer {base!r} has no mapping here")
    if passes == "fwd":
        return Case(op, note + "; nothing requires grad: no autograd graph", layer)
    inputs = [x] + params
    for t in inputs:
        t.requires_grad_(True)
    dy = torch.randn_like(layer().detach())
    grads_of = "x and every parameter, as ours" if params else "x"
    return Case(op + " forward + backward", note + f"; torch.autograd.grad w.r.t. {grads_of}",
                with_grads(layer, inputs, dy))


# --- models: the encoder ---------------------------------------------------------------------

class EncoderConfig(NamedTuple):
    name: str
    width: int
    heads: int
    tokens: int
    token_dim: int
    xyz_freqs: int
    xyz_max_octave: float
    tau_freqs: int
    tau_max_octave: float
    blocks: int
    self_layers: int
    ffn_ratio: int


# models/src/config/autoencoder.rs: paper() and small(), the two `velox bench models` runs.
ENCODER_CONFIGS = [
    EncoderConfig("paper", 512, 16, 8192, 32, 32, 12.0, 8, 7.0, 2, 6, 4),
    EncoderConfig("small", 64, 4, 256, 32, 8, 6.0, 4, 4.0, 1, 2, 4),
]


def encoder_weights(cfg, dev):
    """Random weights in F.linear's [out, in] layout; q, k, v (and W1, W3) stacked as ours."""
    w, hidden = cfg.width, cfg.ffn_ratio * cfg.width

    def linear(i, o):
        return normal([o, i], dev) / math.sqrt(i)

    def ones():
        return torch.ones(w, device=dev)

    def ff():
        return {"norm": ones(), "w13": linear(w, 2 * hidden), "w2": linear(hidden, w)}
    features = (3 + 6 * cfg.xyz_freqs) + 3 + (1 + 2 * cfg.tau_freqs)
    return {
        "xyz_freqs": log_spaced(cfg.xyz_freqs, cfg.xyz_max_octave, dev),
        "tau_freqs": log_spaced(cfg.tau_freqs, cfg.tau_max_octave, dev),
        "input": (linear(features, w), 0.02 * normal([w], dev)),
        "blocks": [{
            "norm_q": ones(), "norm_kv": ones(), "q": linear(w, w), "kv": linear(w, 2 * w),
            "o": linear(w, w), "ff": ff(),
            "layers": [{"norm": ones(), "qkv": linear(w, 3 * w), "o": linear(w, w), "ff": ff()}
                       for _ in range(cfg.self_layers)],
        } for _ in range(cfg.blocks)],
        "out_norm": ones(),
        "out": (linear(w, cfg.token_dim), 0.02 * normal([cfg.token_dim], dev)),
    }


def split_heads(t, heads):
    """[B, L, heads * d] -> [B, heads, L, d] (a view)."""
    b, length, _ = t.shape
    return t.view(b, length, heads, -1).transpose(1, 2)


def merge_heads(t):
    """[B, heads, L, d] -> [B, L, heads * d]."""
    b, heads, length, d = t.shape
    return t.transpose(1, 2).reshape(b, length, heads * d)


def feed_forward(x, p):
    """x + SwiGLU(RMSNorm(x)), W1 and W3 in one product."""
    a, b = F.linear(rms_norm(x, p["norm"]), p["w13"]).chunk(2, -1)
    return x + F.linear(F.silu(a) * b, p["w2"])


def encoder_forward(wts, cfg, cloud, layout):
    """models/src/velox/encoder.rs forward_with, on padded cells and windows of WINDOW tokens."""
    queries, cells, windows = layout
    features = torch.cat([fourier(cloud[:, 0:3], wts["xyz_freqs"]), cloud[:, 3:6],
                          fourier(cloud[:, 6:7], wts["tau_freqs"])], -1)
    tokens = F.linear(features, *wts["input"])
    kv = tokens[cells].view(cfg.tokens, -1, cfg.width)
    q = tokens[queries]
    for block in wts["blocks"]:
        # Cell cross-attention: query c over the points of its cell, one query per batch row.
        context = rms_norm(kv, block["norm_kv"])
        k, v = (split_heads(t, cfg.heads) for t in F.linear(context, block["kv"]).chunk(2, -1))
        qh = split_heads(F.linear(rms_norm(q, block["norm_q"]).unsqueeze(1), block["q"]), cfg.heads)
        q = q + F.linear(merge_heads(F.scaled_dot_product_attention(qh, k, v)).squeeze(1), block["o"])
        q = feed_forward(q, block["ff"])
        for i, layer in enumerate(block["layers"]):
            order, inverse = windows[i % 2]  # every second layer on the shifted windows
            n = rms_norm(q, layer["norm"])[order].view(-1, WINDOW, cfg.width)
            qkv = F.linear(n, layer["qkv"]).view(n.shape[0], WINDOW, 3, cfg.heads, -1)
            qw, kw, vw = qkv.permute(2, 0, 3, 1, 4).unbind(0)
            a = F.linear(merge_heads(F.scaled_dot_product_attention(qw, kw, vw)), layer["o"])
            q = feed_forward(q + a.reshape(-1, cfg.width)[inverse], layer["ff"])
    return F.linear(rms_norm(q, wts["out_norm"]), *wts["out"])


def window_layout(k, dev):
    """A random grouping of k tokens into ceil(k / WINDOW) full windows (the last one padded
    with repeated tokens): the gather order and, for each token, its row in that order."""
    perm = torch.randperm(k, device=dev)
    order = perm[torch.arange(math.ceil(k / WINDOW) * WINDOW, device=dev) % k]
    return order, torch.argsort(perm)


def encoder_case(record, dev):
    points, tokens, token_dim = parse(r"(\d+) points -> (\d+)x(\d+)", record["shape"], "encoder")
    dtype = float_dtype(record["precision"])
    cfg = next((c for c in ENCODER_CONFIGS if (c.tokens, c.token_dim) == (tokens, token_dim)), None)
    if cfg is None:
        raise Unmapped(f"no encoder config has {tokens}x{token_dim} tokens (known: "
                       + ", ".join(f"{c.name} {c.tokens}x{c.token_dim}" for c in ENCODER_CONFIGS) + ")")
    per_cell = math.ceil(points / tokens)
    cloud = torch.rand(points, 7, device=dev)
    cloud[:, :3] = cloud[:, :3] * 2 - 1
    cloud[:, 6] *= 0.23
    cells = torch.randperm(points, device=dev)[torch.arange(tokens * per_cell, device=dev) % points]
    queries = torch.randperm(points, device=dev)[:tokens]
    layout = (queries, cells, [window_layout(tokens, dev) for _ in range(2)])
    wts = encoder_weights(cfg, dev)
    precision = (torch.autocast(device_type=dev.type, dtype=torch.float16) if dtype == torch.float16
                 else contextlib.nullcontext())

    def run():
        with torch.no_grad(), precision:
            return encoder_forward(wts, cfg, cloud, layout)
    # An untimed first run before the clock's warm-up, as ours (models.rs timed_outputs); some
    # builds turn autocast off on the CPU for f16 with a warning instead of failing.
    if run().dtype != dtype:
        raise Unmapped(f"torch.autocast to float16 is not supported on {dev.type} by this PyTorch")
    windows = math.ceil(tokens / WINDOW)
    note = (f"the {cfg.name} config (width {cfg.width}, {cfg.heads} heads, {plural(cfg.blocks, 'block')} "
            f"of cell cross-attention + {cfg.self_layers} window self-attention layers, SwiGLU "
            f"x{cfg.ffn_ratio}), "
            f"random weights, torch.no_grad(): Fourier features, input linear, {tokens} cells padded to "
            f"{per_cell} points (one query each), {windows} windows of {WINDOW} queries, RMSNorms, output "
            "linear; not timed on the torch side: FPS query sampling, the nearest-query assignment and the "
            "window grouping (ours includes them) and uneven cells and windows (favourable to PyTorch)")
    if dtype == torch.float16:
        note += "; torch.autocast(float16): f16 activations between layers where ours keeps f32"
    op = "encoder network forward" + (" under torch.autocast(float16)" if dtype == torch.float16 else " f32")
    return Case(op, note, run)


# --- records, timing, output -----------------------------------------------------------------

def case_for(record, dev):
    name = record["name"]
    if name == "matmul" or name.startswith("matmul "):
        return matmul_case(record, dev)
    builders = {"softmax": softmax_case, "exclusive scan": scan_case,
                "window matmuls alone": window_matmuls_case, "encoder": encoder_case}
    if name in builders:
        return builders[name](record, dev)
    if name.startswith("radix sort"):
        return sort_case(record, dev)
    if name.startswith("scatter-add"):
        return scatter_case(record, dev)
    if name.startswith("gather rows"):
        return gather_case(record, dev)
    if name.startswith("attn "):
        return attention_case(record, dev)
    if suite_of(name) == "layers":
        return layer_case(record, dev)
    if name in ("farthest point sampling", "nearest-query assignment"):
        raise Unmapped("PyTorch has no such kernel; a composition of other ops would time something else")
    if suite_of(name) == "models":
        raise Unmapped("only the encoder is ported to PyTorch here")
    raise Unmapped("no mapping for this record")


def read_records(paths, out_path):
    """Our records from files and folders (each *.json that is a list of records), in order,
    without duplicates, and never the output file."""
    files = []
    for path in paths:
        files += sorted(glob.glob(os.path.join(path, "*.json"))) if os.path.isdir(path) else [path]
    records, seen = [], set()
    for path in files:
        if os.path.abspath(path) == os.path.abspath(out_path):
            continue
        try:
            with open(path) as f:
                data = json.load(f)
        except (OSError, ValueError) as error:
            print(f"passing over {path}: cannot read it as JSON ({error})")
            continue
        if not (isinstance(data, list) and data and all(
                isinstance(r, dict) and all(k in r for k in RECORD_KEYS) for r in data)):
            print(f"passing over {path}: not a list of bench records")
            continue
        if not any(suite_of(r["name"]) for r in data):
            print(f"passing over {path}: none of its {len(data)} records is in a suite this script times")
            continue
        for r in data:
            key = (r["name"], r["shape"], r["precision"])
            if key not in seen:
                seen.add(key)
                records.append(r)
    return records


class Clock:
    """Our policy: one warm-up, then `repeats` runs each timed alone with an idle gap after it;
    the median (element len // 2 of the sorted times, as time_gpu) and the minimum, in ms."""

    def __init__(self, dev):
        self.cuda = dev.type == "cuda"

    def time(self, run, repeats):
        run()
        if self.cuda:
            torch.cuda.synchronize()
        times = []
        for _ in range(repeats):
            if self.cuda:
                start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
                start.record()
                run()
                end.record()
                torch.cuda.synchronize()
                times.append(start.elapsed_time(end))
            else:
                t0 = time.perf_counter()
                run()
                times.append((time.perf_counter() - t0) * 1e3)
        times.sort()
        return times[len(times) // 2], times[0]


def measure(record, case, clock, repeats):
    """The output record of a case: its times under our policy, backward rows by difference."""
    median, low = clock.time(case.run, repeats)
    extra = {}
    if case.forward is not None:
        forward_median, forward_min = clock.time(case.forward, repeats)
        extra = {"fwd_bwd_ms": round(median, 6), "fwd_ms": round(forward_median, 6)}
        median, low = median - forward_median, low - forward_min
    return dict({"suite": suite_of(record["name"]), "name": record["name"], "shape": record["shape"],
                 "precision": record["precision"], "torch_op": case.torch_op, "median_ms": round(median, 6),
                 "min_ms": round(low, 6), "repeats": repeats, "note": case.note}, **extra)


def write_atomically(path, document):
    folder = os.path.dirname(os.path.abspath(path))
    fd, temporary = tempfile.mkstemp(prefix=".torch_bench.", dir=folder)
    try:
        os.fchmod(fd, 0o644)
        with os.fdopen(fd, "w") as f:
            json.dump(document, f, indent=1)
            f.write("\n")
        os.replace(temporary, path)
    except BaseException:
        os.unlink(temporary)
        raise


def free_memory(dev):
    gc.collect()
    if dev.type == "cuda":
        torch.cuda.empty_cache()


def parse_args(argv):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--records", nargs="+", required=True, help="record files or folders of them")
    p.add_argument("--out", required=True, help="the JSON file to write")
    p.add_argument("--device", choices=("cuda", "cpu"), help="default: cuda where available, else cpu")
    p.add_argument("--threads", type=int, help="CPU threads [default: LP_NUM_THREADS, else 1]")
    p.add_argument("--repeats", type=int, help="timed runs per case [default: each record's own]")
    p.add_argument("--time-limit", type=float, help="start no new case after this many seconds")
    p.add_argument("--suites", default=",".join(SUITES), help="comma-separated [default: all four]")
    args = p.parse_args(argv)
    args.suites = [s.strip() for s in args.suites.split(",") if s.strip()]
    unknown = [s for s in args.suites if s not in SUITES]
    if unknown:
        p.error(f"unknown suites {', '.join(unknown)} (known: {', '.join(SUITES)})")
    if args.repeats is not None and args.repeats < 1:
        p.error("--repeats must be at least 1")
    if args.threads is None:
        lavapipe = os.environ.get("LP_NUM_THREADS", "")
        args.threads = int(lavapipe) if lavapipe.isdigit() and int(lavapipe) > 0 else 1
    if args.threads < 1:
        p.error("--threads must be at least 1")
    return args


def main(argv=None):
    if torch is None:
        print(f"PyTorch is not available (import torch failed: {TORCH_IMPORT_ERROR})")
        return 0
    args = parse_args(sys.argv[1:] if argv is None else argv)
    started = time.monotonic()
    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    if device == "cuda" and not torch.cuda.is_available():
        print(f"--device cuda: PyTorch {torch.__version__} sees no CUDA device "
              f"(built for CUDA {torch.version.cuda})", file=sys.stderr)
        return 1
    dev = torch.device(device)
    if device == "cuda":
        torch.backends.cuda.matmul.allow_tf32 = False
        torch.backends.cudnn.allow_tf32 = False
        torch.backends.cuda.matmul.allow_fp16_reduced_precision_reduction = False
        device_name = torch.cuda.get_device_name(dev)
        policy = ("one warm-up, then the record's repeats, each timed alone (CUDA events, a synchronize "
                  "after each), median; no L2 flush; TF32 off; f16 products reduce in f32")
    else:
        torch.set_num_threads(args.threads)
        device_name = f"cpu, {args.threads} thread{'s' if args.threads != 1 else ''}"
        policy = ("one warm-up, then the record's repeats, each timed alone (time.perf_counter), median; "
                  "no cache flush")
    torch.manual_seed(0)
    records = [r for r in read_records(args.records, args.out) if suite_of(r["name"]) in args.suites]
    records.sort(key=lambda r: SUITES.index(suite_of(r["name"])))  # stable: file order within a suite
    document = {"peer": "torch", "torch_version": torch.__version__, "device": device_name,
                "policy": policy, "records": []}
    write_atomically(args.out, document)
    print(f"PyTorch {torch.__version__} on {device_name}; {len(records)} records; {policy}")
    print(f"{'name':<28} {'shape':<34} {'precision':<9} {'ours ms':>10} {'torch ms':>10} {'ours/torch':>10}")
    clock = Clock(dev)
    for i, record in enumerate(records):
        if args.time_limit is not None and time.monotonic() - started > args.time_limit:
            print(f"time limit of {args.time_limit:g} s reached: {len(records) - i} records not started")
            break
        label = f"{record['name']} | {record['shape']} | {record['precision']}"
        repeats = args.repeats or int(record["repeats"])
        try:
            out = measure(record, case_for(record, dev), clock, repeats)
        except Unmapped as reason:
            print(f"skipped {label}: {reason}")
            continue
        except Exception as error:  # out of memory, a dtype the device lacks: the next case runs
            first_line = (str(error).splitlines() or [""])[0]
            print(f"skipped {label}: {type(error).__name__}: {first_line}")
            continue
        finally:
            free_memory(dev)
        document["records"].append(out)
        write_atomically(args.out, document)
        ours, theirs = float(record["median_ms"]), out["median_ms"]
        ratio = f"{ours / theirs:10.2f}" if theirs > 0 else f"{'-':>10}"
        print(f"{record['name']:<28} {record['shape']:<34} {record['precision']:<9} "
              f"{ours:10.3f} {theirs:10.3f} {ratio}")
    print(f"wrote {args.out}: {len(document['records'])} records")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Writes the DINOv2 test fixture: a small randomly initialised `Dinov2Model` from the
`transformers` package, its weights in the Hugging Face layout, input images and the model's
outputs, computed in float64.

    python tools/dinov2_fixture.py tests/fixtures/dinov2

Needs `torch`, `transformers` and `safetensors` (any CPU install; nothing is downloaded: the
model is built from a config). The tests in `tests/models/dinov2.rs` run the engine's DINOv2 on the
same weights and images and compare `last_hidden_state`, with positions both at the trained
grid (no interpolation) and interpolated to a larger, non-square grid.
"""

import json
import sys
from pathlib import Path

import numpy as np
import torch
import transformers
from safetensors.torch import save_file
from transformers import Dinov2Config, Dinov2Model


def main(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(20261130)
    # Same architecture as facebook/dinov2-large, narrower and shallower: patch 14, LayerScale,
    # GELU feed-forward, qkv bias, LayerNorm eps 1e-6; a 4 x 4 trained position grid.
    config = Dinov2Config(
        hidden_size=64,
        num_hidden_layers=2,
        num_attention_heads=4,
        mlp_ratio=4,
        image_size=56,
        patch_size=14,
        layer_norm_eps=1e-6,
        qkv_bias=True,
        layerscale_value=1.0,
        use_swiglu_ffn=False,
    )
    model = Dinov2Model(config).eval()
    # Random values everywhere, LayerScale and norms included, so that no term can hide.
    with torch.no_grad():
        for name, p in model.named_parameters():
            if name.endswith("lambda1"):
                p.copy_(torch.rand_like(p) * 1.5 + 0.25)
            elif "norm" in name and name.endswith("weight"):
                p.copy_(1.0 + 0.2 * torch.randn_like(p))
            else:
                p.copy_(0.1 * torch.randn_like(p) if p.dim() > 1 else 0.05 * torch.randn_like(p))
    # Saved under the names of the published `facebook/dinov2-large` file (transformers 5
    # renames them on load; the engine reads both).
    hub_names = {
        "attention.q_proj": "attention.attention.query",
        "attention.k_proj": "attention.attention.key",
        "attention.v_proj": "attention.attention.value",
        "attention.o_proj": "attention.output.dense",
    }
    weights = {}
    for k, v in model.state_dict().items():
        for new, old in hub_names.items():
            k = k.replace(new, old)
        weights[k] = v.detach().clone().float().contiguous()
    save_file(weights, str(out / "weights.safetensors"))

    model = model.double()
    # (images, height, width): the trained 4 x 4 grid, and a 5 x 7 grid that interpolates.
    cases = {"trained_grid": (1, 56, 56), "interpolated": (2, 70, 98)}
    tensors = {}
    for name, (n, h, w) in cases.items():
        # Pixel values as the model reads them (already normalised), rounded to f32 so that
        # both sides read the same input.
        pixels = torch.randn(n, 3, h, w).double()
        with torch.no_grad():
            hidden = model(pixel_values=pixels).last_hidden_state
        tensors[f"{name}.pixels"] = pixels.float().contiguous()
        # Rounding the f64 output to f32 adds an NMSE near 1e-15, far below any bound tested.
        tensors[f"{name}.hidden"] = hidden.float().contiguous()
    save_file(tensors, str(out / "cases.safetensors"))
    (out / "config.json").write_text(
        json.dumps(
            {
                "made_by": f"tools/dinov2_fixture.py with transformers {transformers.__version__}, torch {torch.__version__}",
                "hidden_size": config.hidden_size,
                "num_hidden_layers": config.num_hidden_layers,
                "num_attention_heads": config.num_attention_heads,
                "mlp_ratio": config.mlp_ratio,
                "image_size": config.image_size,
                "patch_size": config.patch_size,
                "layer_norm_eps": config.layer_norm_eps,
                "cases": {k: list(v) for k, v in cases.items()},
            },
            indent=2,
        )
        + "\n"
    )
    for k, v in tensors.items():
        print(k, tuple(v.shape), v.dtype, float(v.abs().mean()))


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "tests/fixtures/dinov2"))

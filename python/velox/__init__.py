"""Velox from Python: 4D dynamic tokens on a Vulkan compute runtime, numpy in, numpy out.

Every call runs on the default device (the one the engine prefers; ``VELOX_DEVICE`` overrides)
unless given ``device=velox.Device(...)``. Arrays going in must be ``float32`` of the shape
each function names (``bool`` for visibility); anything else raises ``ValueError`` naming the
argument, its dtype and its shape, and is never converted silently.

    >>> import velox
    >>> g = velox.read_gaussians("scene.ply")            # dict of float32 arrays
    >>> cam = {"world_to_camera": np.eye(4), "fx": 300, "fy": 300, "cx": 128, "cy": 128}
    >>> rgb = velox.render(g, cam, 256, 256)             # [256, 256, 3] float32
"""

import sys as _sys

from . import _velox
from ._velox import (
    Autoencoder,
    Device,
    Generator,
    Tracker,
    __version__,
    devices,
    encode_dataset,
    export,
    mesh_of_points,
    read_gaussians,
    read_image,
    read_mesh,
    render,
    write_gaussians,
    write_image,
    write_mesh,
)
from . import data, metrics
from .viewer import view

__all__ = [
    "Autoencoder",
    "Device",
    "Generator",
    "Tracker",
    "__version__",
    "data",
    "devices",
    "encode_dataset",
    "export",
    "mesh_of_points",
    "metrics",
    "read_gaussians",
    "read_image",
    "read_mesh",
    "render",
    "train",
    "view",
    "write_gaussians",
    "write_image",
    "write_mesh",
]


class _Progress:
    """Shows a run's events: a tqdm bar when tqdm is installed (notes above it), else a line
    every few seconds on stderr; `progress=False` shows nothing."""

    def __init__(self, unit, total=None):
        self.unit, self.total, self.bar, self.last = unit, total, None, 0.0
        try:
            import tqdm  # noqa: F401

            self.tqdm = tqdm.tqdm
        except ImportError:
            self.tqdm = None

    def __call__(self, event):
        kind = event["event"]
        if kind == "note":
            self._write(f"note: {event['text']}")
        elif kind == "begin":
            if self.tqdm is not None:
                self.bar = self.tqdm(total=event["steps"], initial=event["step"], unit=self.unit)
        elif kind == "step":
            if self.bar is not None:
                self.bar.set_postfix(loss=f"{event['loss']:.4f}", refresh=False)
                self.bar.update(event["step"] - self.bar.n)
            else:
                import time

                now = time.monotonic()
                if now - self.last > 5.0:
                    self.last = now
                    print(f"step {event['step']}: loss {event['loss']:.4f}", file=_sys.stderr)
        elif kind == "frame":
            if self.bar is None and self.tqdm is not None:
                self.bar = self.tqdm(total=self.total, unit=self.unit)
            if self.bar is not None:
                self.bar.set_postfix_str(event["scene"], refresh=False)
                self.bar.update(1)
                if self.total is not None and self.bar.n >= self.total:
                    self.bar.close()
                    self.bar = None
        elif kind == "end" and self.bar is not None:
            self.bar.close()
            self.bar = None

    def _write(self, text):
        if self.bar is not None:
            self.bar.write(text, file=_sys.stderr)
        else:
            print(text, file=_sys.stderr)


def _progress_of(progress, unit, total=None):
    if progress is None:
        return _Progress(unit, total)
    if progress is False:
        return None
    if not callable(progress):
        raise ValueError("progress must be a callable taking an event dict, None (a bar) or False (silent)")
    return progress


def train(kind, data, out, *, config=None, steps=None, seed=None, resume=False, init=None,
          steps_per_scene=None, accumulate=None, cooldown=None, precision=None,
          checkpoint_every=200, plot_every=25, stop_at=None, tokens=None, checkpoint=None,
          task="video", dinov2=None, progress=None, device=None, overlap=None):
    """Trains `kind` ("autoencoder", "voxels", "tracker", "generator") on the dataset folder
    `data` into the run folder `out`, exactly as `velox train KIND` does with the same
    settings (the same checkpoint, bit for bit, on the same device).

    `config` is "paper", "small", "tiny" or a JSON file (default "small"; with `init`, that
    checkpoint's). `resume=True` continues the run in `out` from its checkpoint with the
    settings it started with; `init=CHECKPOINT` starts a new run from another run's
    parameters. `seed`, `steps`, `steps_per_scene`, `accumulate`, `cooldown`, `precision`
    ("f32" or "f16"), `stop_at` and `overlap` (True, False or None for the device's
    default: `--overlap on|off`) are `velox train`'s options; `tokens`, `checkpoint`, `task`
    and `dinov2` those of the models trained on stored tokens. `progress`: None shows a bar
    (tqdm when installed), False nothing, a callable gets each event dict.

    Ctrl-C stops after the step under way, writes the checkpoint and raises KeyboardInterrupt
    naming it. Returns a dict: checkpoint, step, steps, seed, precision, first_loss,
    last_loss, seconds, samples_per_second, stopped (None, "stop_at" or "asked")."""
    return _velox.train(
        kind, str(data), str(out), config=None if config is None else str(config), steps=steps,
        seed=seed, resume=resume, init=None if init is None else str(init),
        steps_per_scene=steps_per_scene, accumulate=accumulate, cooldown=cooldown,
        precision=precision, checkpoint_every=checkpoint_every, plot_every=plot_every,
        stop_at=stop_at, tokens=None if tokens is None else str(tokens),
        checkpoint=None if checkpoint is None else str(checkpoint), task=task,
        dinov2=None if dinov2 is None else str(dinov2), progress=_progress_of(progress, "step"),
        device=device, overlap=overlap,
    )

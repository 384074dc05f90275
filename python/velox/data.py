"""Training data: procedural scenes in the project's scene format, as `velox data synth`
writes them."""

from . import _velox
from ._velox import read_cloud

__all__ = ["read_cloud", "synth"]


def synth(out, *, scenes=8, seed=0, res=128, points=200_000, tracks=1024, supersample=2,
          progress=None, device=None):
    """Writes `scenes` procedural scenes (`scene_SSSSS`, seeds `seed` on) into the folder `out`
    and returns their folders: what `velox data synth --out OUT --scenes N --seed S --res R
    --points P --tracks T --supersample K` writes, byte for byte. `progress`: None shows a
    bar (tqdm when installed), False nothing, a callable gets each event dict."""
    from . import _progress_of

    return _velox.synth(
        str(out), scenes=scenes, seed=seed, res=res, points=points, tracks=tracks,
        supersample=supersample, progress=_progress_of(progress, "frame", scenes * 24), device=device,
    )

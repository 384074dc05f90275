"""Training data: procedural scenes in the project's scene format, as `velox data synth`
writes them."""

from . import _velox
from ._velox import import_rgbd, import_video, read_cloud

__all__ = ["gltf", "import_rgbd", "import_video", "read_cloud", "synth"]


def synth(out, *, scenes=8, seed=0, res=128, points=200_000, tracks=1024, supersample=2,
          background=(0.0, 0.0, 0.0), progress=None, device=None):
    """Writes `scenes` procedural scenes (`scene_SSSSS`, seeds `seed` on) into the folder `out`
    and returns their folders: what `velox data synth --out OUT --scenes N --seed S --res R
    --points P --tracks T --supersample K --background R,G,B` writes, byte for byte. `progress`: None shows a
    bar (tqdm when installed), False nothing, a callable gets each event dict."""
    from . import _progress_of

    return _velox.synth(
        str(out), scenes=scenes, seed=seed, res=res, points=points, tracks=tracks,
        supersample=supersample, background=tuple(map(float, background)),
        progress=_progress_of(progress, "frame", scenes * 24), device=device,
    )


def gltf(files, out, *, animation=None, seed=0, res=128, points=200_000, tracks=1024, supersample=2,
         background=(0.0, 0.0, 0.0), progress=None, device=None):
    """Writes a scene of each glTF 2.0 file (`.gltf` or `.glb`; a path or a list of them) into
    `out`, named `STEM_III`, as `velox data gltf FILES --out OUT` does (scene i seeded with
    `seed + i`, animation `animation` or the first). A scene already complete is kept; a file
    that cannot be imported does not stop the others. Returns a dict of `written` and `kept`
    (scene folders) and `failed` (file: reason)."""
    from . import _progress_of

    files = [files] if isinstance(files, (str, bytes)) or hasattr(files, "__fspath__") else list(files)
    return _velox.gltf(
        [str(f) for f in files], str(out), animation=animation, seed=seed, res=res, points=points,
        tracks=tracks, supersample=supersample, background=tuple(map(float, background)),
        progress=_progress_of(progress, "frame", len(files) * 24),
        device=device,
    )

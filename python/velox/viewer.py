"""`velox.view`: watch a 4D result in a browser, as `velox view` shows it."""

import os
import tempfile
from pathlib import Path

from . import _velox


def _as_folder(gaussians):
    """Gaussians (a dict, or a list of dicts, one a frame) written as PLYs in a new folder."""
    from ._velox import write_gaussians

    frames = [gaussians] if isinstance(gaussians, dict) else gaussians
    if not isinstance(frames, (list, tuple)) or not frames or not all(isinstance(g, dict) for g in frames):
        raise ValueError("view takes a path, a dict of Gaussians, or a list of them (one a frame)")
    if len(frames) > 24:
        raise ValueError(f"a clip holds at most 24 frames, got {len(frames)}")
    folder = Path(tempfile.mkdtemp(prefix="velox-view-"))
    for f, g in enumerate(frames):
        write_gaussians(folder / f"gaussians_f{f:02}.ply", g)
    return folder if len(frames) > 1 else folder / "gaussians_f00.ply"


def view(path_or_gaussians, html=None, *, compare=None, scene=None, no_compare=False,
         host="127.0.0.1", port=0, open_browser=None):
    """Shows a result in a browser: a folder of per-frame Gaussian PLYs (gaussians_fFF.ply) or
    surface points (points_fFF.ply), another tool's numbered PLY sequence (frame_0000.ply, ...),
    a dataset scene, one Gaussian PLY, or Gaussians in memory
    (a dict as `velox.read_gaussians` gives, or a list of them, one a frame).

    With `html`, writes the viewer with every frame inside it to that file (it opens offline)
    and returns its path. Else serves it from a thread of this process on `host:port` (0: a
    free port) and returns its address, opening it in the browser when `open_browser` (the
    default outside notebooks and without a display, off). `compare` shows a second result
    beside it (default: the ground truth's points of the scene a decode output names, unless
    `no_compare`); `scene` the scene whose cameras the page offers."""
    if isinstance(path_or_gaussians, (str, os.PathLike)):
        path = Path(path_or_gaussians)
    else:
        path = _as_folder(path_or_gaussians)
    options = dict(compare=None if compare is None else str(compare),
                   scene=None if scene is None else str(scene), no_compare=no_compare)
    if html is not None:
        page, _ = _velox.view_page(str(path), **options)
        html = Path(html)
        html.write_text(page, encoding="utf-8")
        return html
    url, title = _velox.view_serve(str(path), host=host, port=port, **options)
    if open_browser is None:
        open_browser = bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    if open_browser:
        import webbrowser

        webbrowser.open(url)
    print(f"velox.view: {title} at {url} (served while this Python runs)")
    return url

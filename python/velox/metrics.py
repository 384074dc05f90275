"""The paper's metrics on numpy arrays, by the code Velox's evaluations use: PSNR and SSIM
(as scikit-image computes them), the symmetric Chamfer distance, and TAPVid-3D's metrics, on
arrays or on the benchmark's own files."""

from ._velox import chamfer, psnr, ssim, tapvid3d, tapvid3d_files

__all__ = ["chamfer", "psnr", "ssim", "tapvid3d", "tapvid3d_files"]

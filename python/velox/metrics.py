"""The paper's metrics on numpy arrays, by the code Velox's evaluations use: PSNR and SSIM
(as scikit-image computes them), the symmetric Chamfer distance, and TAPVid-3D's metrics."""

from ._velox import chamfer, psnr, ssim, tapvid3d

__all__ = ["chamfer", "psnr", "ssim", "tapvid3d"]

"""Image operations behind detection, description and matching, in two interchangeable backends.

The geometry of the matcher (rays, plane-induced warps, the camera model) stays in numpy; what touches pixels
goes through a backend:

* ``pyramid(image, levels)``: the image (float32 (H, W)) and ``levels`` 2x-subsampled versions (Gaussian 5-tap,
  as ``cv2.pyrDown``), in the backend's own array type;
* ``patch_ncc(level_image, ref_samples, pts)``: bilinear samples of one pyramid level at ``pts`` (..., G, 2)
  (pixel coordinates of that level) compared by zero-mean NCC with ``ref_samples`` (numpy, any shape that
  broadcasts against (..., G)): the patch
  descriptor and the matching score in one step, returned as numpy float32 (...); NaN where a sample falls
  outside the image, 0 where a patch is flat;
* ``sample(level_image, pts)``: the bilinear samples themselves as numpy float32 (...) (NaN outside);
* ``corner_response(gray, block_size)``: the Shi–Tomasi response (the smaller eigenvalue of the structure
  tensor summed over a ``block_size`` box, Sobel 3x3 derivatives, as ``cv2.cornerMinEigenVal``).

:class:`OpenCVBackend` (the default) uses cv2 and numpy; ``heartcv.backends.kornia_backend.KorniaBackend`` does
the same on torch tensors with kornia (CPU or CUDA). Both must give the same matches to within float32
rounding (tests/heartcv/test_backends.py).
"""

from __future__ import annotations

import numpy as np

from .features import ncc, sample_at

__all__ = ["OpenCVBackend", "get_backend"]


class OpenCVBackend:
    """cv2 + numpy image operations (float32)."""

    name = "opencv"

    def pyramid(self, image, levels):
        import cv2

        pyr = [np.ascontiguousarray(image, np.float32)]
        for _ in range(levels):
            pyr.append(cv2.pyrDown(pyr[-1]))
        return pyr

    def sample(self, level_image, pts):
        return sample_at(level_image, pts)

    def patch_ncc(self, level_image, ref_samples, pts):
        b = sample_at(level_image, pts)
        a = np.asarray(ref_samples, np.float32)
        if a.ndim != b.ndim or a.shape[-2] != 1 or b.ndim < 2:
            return ncc(a, b)
        # one reference patch against many: normalise it once, then the cross term is a batched matmul
        G = a.shape[-1]
        a0 = a - a.mean(axis=-1, keepdims=True)
        sa = np.sqrt((a0 * a0).sum(axis=-1, keepdims=True))
        an = a0 / np.where(sa > 0, sa, 1.0)                                    # (..., 1, G)
        mb = b.mean(axis=-1, keepdims=True)
        b0 = b - mb                                   # centred first: no float32 cancellation on bright patches
        std_b = np.sqrt(np.einsum("...g,...g->...", b0, b0))
        cross = np.matmul(b0, np.swapaxes(an, -1, -2))[..., 0]                 # sum(an * b0)
        sb = mb[..., 0]
        flat = (sa[..., 0] < 1e-3 * np.sqrt(G)) | (std_b < 1e-3 * np.sqrt(G))
        with np.errstate(invalid="ignore", divide="ignore"):
            out = np.where(flat, 0.0, cross / np.where(std_b > 0, std_b, 1.0))
        return np.where(np.isnan(sb), np.nan, out).astype(np.float32)

    def corner_response(self, gray, block_size=7):
        import cv2

        return cv2.cornerMinEigenVal(np.asarray(gray), block_size, ksize=3)


def get_backend(name="opencv", device=None):
    """The backend called ``name`` ('opencv' or 'kornia'); ``device`` ('cpu', 'cuda', ...) for kornia.

    ValueError for an unknown name; ImportError (naming the extra to install) when kornia is missing."""
    if name == "opencv":
        return OpenCVBackend()
    if name == "kornia":
        try:
            from .backends.kornia_backend import KorniaBackend
        except ImportError as exc:
            raise ImportError(f"the kornia backend needs torch and kornia (pip install 'heartcv[kornia]'): {exc}") \
                from None
        return KorniaBackend(device=device)
    raise ValueError(f"backend: 'opencv' or 'kornia' expected, got {name!r}")

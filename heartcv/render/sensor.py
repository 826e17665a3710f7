"""Image formation after shading: lens blur, sensor noise and quantisation.

``expose`` turns linear radiance (1 = white Lambertian at the working distance, see ``shading``) into digital
numbers: the optics blur it with a Gaussian point-spread function (``psf_sigma_px``; symmetric, so it moves
no edge), the sensor collects ``e = gain * radiance * full_well_e`` electrons per pixel (clipped at the full
well: saturation), adds shot noise and read noise, and the converter maps ``[0, full_well_e]`` linearly onto
``[0, 2^bits - 1]`` and rounds (no gamma: a machine-vision camera).

Shot noise is Poisson-Gaussian in its standard heteroscedastic-Gaussian form: ``e + sqrt(e + read^2) z`` with
standard normal ``z`` (Foi et al., IEEE TIP 2008); at the default full well (10 000 e-) every pixel brighter
than 1 % of the range holds more than 100 electrons, where the Gaussian approximation of the Poisson law is
far below the quantisation step. ``z`` comes from :func:`standard_normal` (inverse-CDF table lookup).
"""

from __future__ import annotations

import numpy as np

__all__ = ["expose", "psf_blur", "standard_normal"]

_QUANTILES = None


def standard_normal(rng: np.random.Generator, shape) -> np.ndarray:
    """Standard normal float32 samples by inverse-CDF lookup of uniform 16-bit integers from ``rng``: the 65 536
    equiprobable quantiles ``Phi^-1((i + 1/2) / 65536)`` (tails beyond +-4.3 sigma are cut; the std is
    0.99998). About 4x faster than ``Generator.standard_normal`` for the millions of pixels of a frame."""
    global _QUANTILES
    if _QUANTILES is None:
        from scipy.special import ndtri

        _QUANTILES = ndtri((np.arange(65536) + 0.5) / 65536).astype(np.float32)
    n = int(np.prod(shape))
    idx = np.frombuffer(rng.bytes(2 * n), dtype=np.uint16)
    return _QUANTILES[idx].reshape(shape)


def psf_blur(image, sigma_px) -> np.ndarray:
    """Gaussian PSF of standard deviation ``sigma_px`` (float32 image (H, W) or (H, W, C))."""
    import cv2

    if sigma_px <= 0:
        return image
    return cv2.GaussianBlur(image, (0, 0), float(sigma_px), borderType=cv2.BORDER_REFLECT)


def expose(radiance, noise, rng: np.random.Generator | None, psf_sigma_px=0.0) -> np.ndarray:
    """Digital image (uint8 or uint16, same shape as ``radiance``) of a linear radiance image.

    Parameters
    ----------
    radiance : ndarray (H, W) or (H, W, C), float32
    noise : heartcv.render.scene.NoiseSpec
        ``full_well_e``, ``read_noise_e``, ``shot_noise``, ``gain``, ``bits``.
    rng : numpy.random.Generator or None
        None renders without noise (quantisation only).
    """
    img = psf_blur(np.asarray(radiance, np.float32), psf_sigma_px)
    fw = np.float32(noise.full_well_e)
    top = (1 << noise.bits) - 1
    e = np.multiply(img, np.float32(noise.gain) * fw, dtype=np.float32)
    np.clip(e, 0, fw, out=e)
    if rng is not None and (noise.shot_noise or noise.read_noise_e > 0):
        sd = e.copy() if noise.shot_noise else np.zeros_like(e)
        if noise.read_noise_e > 0:
            sd += np.float32(noise.read_noise_e ** 2)
        np.sqrt(sd, out=sd)
        sd *= standard_normal(rng, e.shape)
        e += sd
        del sd
    e *= np.float32(top / noise.full_well_e)
    np.rint(e, out=e)
    np.clip(e, 0, top, out=e)
    return e.astype(np.uint8 if noise.bits == 8 else np.uint16)

"""Procedural epicardium texture on the phantom's material coordinates (sigma, t), with optional fiducial dots.

The texture is an RGB image over the phantom's parameter domain: rows follow the meridian arc length ``sigma``
(from the apex to the base), columns the circumferential coordinate ``t = b R2`` over one period
``[-pi R2, pi R2)`` (periodic). A surface point is coloured by looking up its *material* coordinates, so the
pattern is attached to the tissue and moves with it. Layers, all drawn with ``rng``:

* tissue: the base colour with low-frequency mottling (two octaves of smooth noise);
* fat: yellowish patches that follow the vessels and thicken towards the base (a ``fat`` fraction of the area);
* vessels: branching random trees running from the base towards the apex, tapering, drawn anti-aliased;
* speckle: fine multiplicative noise at 0.1-0.3 mm, band-limited near the pixel footprint of the default rig
  (89 um), which gives trackers something to lock onto;
* fiducials (optional): bright dots on a regular grid over the patch, at known material coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from ..targets import MAX_TEXTURE_TEXELS
from ..tracker.files import InputError

__all__ = ["Texture", "make_texture", "fiducial_grid"]


@dataclass(frozen=True)
class Texture:
    """An RGB texture over (sigma, t).

    Attributes
    ----------
    image : ndarray (H, W, 3) uint8     RGB; row i covers sigma in ``sigma0 + [i, i+1) * texel_sigma``, column j
                                        covers t in ``-period/2 + [j, j+1) * texel_t``
    sigma0 : float                      sigma of the top edge of row 0 (m)
    texel_sigma, texel_t : float        texel size along sigma and t (m)
    period_m : float                    circumferential period (m)
    fiducials : ndarray (n, 2)          material coordinates (sigma, t) of the fiducial dot centres (may be empty)
    """

    image: np.ndarray
    sigma0: float
    texel_sigma: float
    texel_t: float
    period_m: float
    fiducials: np.ndarray

    def lookup(self, sigma, t) -> np.ndarray:
        """Bilinear RGB albedo in [0, 1] (N, 3) float32 at material coordinates (N,), t taken modulo the period."""
        import cv2

        sigma = np.asarray(sigma, np.float64).ravel()
        t = np.asarray(t, np.float64).ravel()
        H, W = self.image.shape[:2]
        col = np.mod(t + self.period_m / 2, self.period_m) / self.texel_t - 0.5
        row = np.clip((sigma - self.sigma0) / self.texel_sigma - 0.5, 0.0, H - 1.0)
        n = col.size
        width = 4096
        pad = (-n) % width
        mx = np.pad(col.astype(np.float32), (0, pad)).reshape(-1, width)
        my = np.pad(row.astype(np.float32), (0, pad)).reshape(-1, width)
        out = np.empty((0, 3), np.float32)
        if n:
            out = cv2.remap(self.image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
            out = out.reshape(-1, 3)[:n].astype(np.float32) * np.float32(1 / 255)
        return out


def _smooth_noise(shape, scale_px, rng, wrap_cols=True) -> np.ndarray:
    """Zero-mean, unit-std Gaussian-filtered white noise (float32) with correlation length ``scale_px`` texels,
    drawn on a coarse grid and upsampled; periodic across the columns."""
    import cv2

    H, W = shape
    f = max(1.0, scale_px / 4.0)
    h, w = max(4, int(math.ceil(H / f))), max(4, int(math.ceil(W / f)))
    n = rng.standard_normal((h, w)).astype(np.float32)
    s = scale_px / f
    pad = int(math.ceil(3 * s)) + 1
    if wrap_cols:
        n = np.pad(n, ((0, 0), (pad, pad)), mode="wrap")
    n = cv2.GaussianBlur(n, (0, 0), s, borderType=cv2.BORDER_REFLECT)
    if wrap_cols:
        n = n[:, pad:-pad]
    n = cv2.resize(n, (W, H), interpolation=cv2.INTER_CUBIC)
    n -= n.mean()
    return n / max(float(n.std()), 1e-12)


def _draw_wrapped(draw, pts_px, W):
    """Call ``draw(points)`` for a polyline and its copies shifted by one period left and right."""
    for shift in (-W, 0, W):
        draw(pts_px + np.array([shift, 0.0]))


def _vessel_mask(shape, texel, rng, n_trees, sigma_range, period):
    """Anti-aliased vessel coverage in [0, 1] (float32) and a centre-line mask for the fat model."""
    import cv2

    H, W = shape
    cov = np.zeros((H, W), np.uint8)
    shift = 4  # sub-texel precision of cv2 drawing (1/16 texel)
    s_lo, s_hi = sigma_range
    length = s_hi - s_lo

    def line(p, q, width_m):
        th = max(1, int(round(width_m / texel)))
        for dx in (-W, 0, W):
            a = np.round((p + [dx, 0]) * (1 << shift)).astype(np.int64)
            b = np.round((q + [dx, 0]) * (1 << shift)).astype(np.int64)
            cv2.line(cov, tuple(int(v) for v in a), tuple(int(v) for v in b), 255, th, cv2.LINE_AA, shift)

    def to_px(sigma, t):
        return np.array([(np.mod(t + period / 2, period)) / texel, (sigma - s_lo) / texel])

    stack = []
    for k in range(n_trees):
        t0 = -period / 2 + period * (k + rng.uniform(0.2, 0.8)) / max(n_trees, 1)
        stack.append((s_hi - rng.uniform(0.0, 0.1) * length, t0, math.pi + rng.normal(0, 0.25),
                      rng.uniform(1.2e-3, 2.0e-3), 0))
    step = 0.8e-3
    while stack:
        sigma, t, heading, width, depth = stack.pop()
        while width > 2.5e-4 and s_lo + 0.05 * length < sigma < s_hi + 1e-9:
            heading += rng.normal(0, 0.12)
            heading = math.pi + float(np.clip(heading - math.pi, -1.1, 1.1))  # keep running apex-wards
            s1, t1 = sigma + step * math.cos(heading), t + step * math.sin(heading)
            p, q = to_px(sigma, t), to_px(s1, t1)
            if abs(p[0] - q[0]) < W / 2:  # skip the wrap step itself
                line(p, q, width)
            if depth == 0 and rng.random() < 0.002:
                break
            sigma, t = s1, t1
            width *= 0.992
            if depth < 2 and rng.random() < (0.03 if depth == 0 else 0.015):
                side = rng.choice((-1.0, 1.0))
                stack.append((sigma, t, heading + side * rng.uniform(0.5, 1.0), width * rng.uniform(0.4, 0.65),
                              depth + 1))
    return cov.astype(np.float32) / 255.0


def fiducial_grid(geometry, spacing_m, margin_m) -> np.ndarray:
    """Material coordinates (n, 2) of dots on a regular (sigma, t) grid over the patch, ``margin_m`` inside its
    rim, centred on the patch centre."""
    out = []
    for half in (geometry.length / 2 - margin_m, geometry.width / 2 - margin_m):
        k = int(math.floor(max(half, 0.0) / spacing_m + 1e-9))
        out.append(np.arange(-k, k + 1) * spacing_m)
    S, T = np.meshgrid(*out, indexing="ij")
    return np.stack([S.ravel(), T.ravel()], axis=1)


def make_texture(spec, sigma_range, period_m, rng: np.random.Generator, fiducials=None,
                 fiducial_spec=None) -> Texture:
    """Draw the texture (module docstring).

    Parameters
    ----------
    spec : heartcv.render.scene.TextureSpec
    sigma_range : (float, float)     meridian arc length of the apex and the base (m)
    period_m : float                 2 pi R2 (m)
    rng : numpy.random.Generator
    fiducials : ndarray (n, 2), optional   dot centres (sigma, t)
    fiducial_spec : heartcv.render.scene.FiducialSpec, optional   dot radius and colour
    """
    import cv2

    texel = spec.texel_m
    s_lo, s_hi = sigma_range
    H = int(math.ceil((s_hi - s_lo) / texel)) + 2
    W = int(round(period_m / texel))
    if H * W > MAX_TEXTURE_TEXELS:  # memory bound: the texture and its intermediates are float32 (H, W, 3)
        raise InputError(None, f"a texture of {H} x {W} texels for this phantom (more than {MAX_TEXTURE_TEXELS:.0e}); "
                               "use larger texels", "texture.texel_m")
    texel_t = period_m / W
    s0 = s_lo - texel
    shape = (H, W)
    mm = 1e-3 / texel  # texels per millimetre
    tissue = np.asarray(spec.tissue_rgb, np.float32)
    mott = 0.65 * _smooth_noise(shape, 3.0 * mm, rng) + 0.35 * _smooth_noise(shape, 0.8 * mm, rng)
    img = tissue[None, None, :] * (1.0 + spec.mottling * mott)[..., None]
    vessels = _vessel_mask(shape, texel, rng, spec.vessels, (s0, s0 + H * texel), period_m)
    if spec.fat > 0:
        small = cv2.resize(vessels, (max(1, W // 8), max(1, H // 8)), interpolation=cv2.INTER_AREA)
        near = cv2.resize(cv2.GaussianBlur(small, (0, 0), 2.5 * mm / 8), (W, H), interpolation=cv2.INTER_LINEAR)
        near /= max(float(near.max()), 1e-6)
        rows = (s0 + (np.arange(H) + 0.5) * texel - s_lo) / (s_hi - s_lo)  # 0 at the apex, 1 at the base
        score = _smooth_noise(shape, 4.0 * mm, rng) + 2.0 * near + 1.5 * smootherstep_rows(rows)[:, None]
        thr = float(np.quantile(score[:: 8, :: 8], 1.0 - spec.fat))
        fat = np.clip((score - thr) / 0.6 + 0.5, 0.0, 1.0)
        fat = fat * fat * (3 - 2 * fat)
        fat_col = np.asarray(spec.fat_rgb, np.float32)[None, None, :] * (
            1.0 + 0.06 * _smooth_noise(shape, 0.6 * mm, rng))[..., None]
        img = img * (1 - fat[..., None]) + fat_col * fat[..., None]
        del near, score, fat, fat_col
    if spec.vessels > 0:
        alpha = cv2.GaussianBlur(vessels, (0, 0), 0.8) * 0.9
        vcol = np.asarray(spec.vessel_rgb, np.float32)[None, None, :]
        img = img * (1 - alpha[..., None]) + vcol * alpha[..., None]
        del alpha
    if spec.speckle > 0:
        sp = 0.7 * _white_blur(shape, 2.5, rng) + 0.3 * _white_blur(shape, 6.0, rng)
        img *= (1.0 + spec.speckle * sp / max(float(sp.std()), 1e-12))[..., None]
    fid = np.zeros((0, 2)) if fiducials is None else np.asarray(fiducials, float).reshape(-1, 2)
    if fid.size and fiducial_spec is not None:
        dots = np.zeros(shape, np.uint8)
        shift = 4
        r = int(round(fiducial_spec.radius_m / texel * (1 << shift)))
        for sigma, t in fid:
            c = np.array([(np.mod(t + period_m / 2, period_m)) / texel_t - 0.5, (sigma - s0) / texel - 0.5])
            cv2.circle(dots, tuple(int(v) for v in np.round(c * (1 << shift))), r, 255, -1, cv2.LINE_AA, shift)
        a = dots.astype(np.float32)[..., None] / 255.0
        img = img * (1 - a) + np.asarray(fiducial_spec.rgb, np.float32)[None, None, :] * a
    image = np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)
    image.setflags(write=False)
    return Texture(image, s0, texel, texel_t, float(period_m), fid)


def smootherstep_rows(x):
    x = np.clip(x, 0.0, 1.0)
    return (x * x * x * (x * (6 * x - 15) + 10)).astype(np.float32)


def _white_blur(shape, sigma_px, rng) -> np.ndarray:
    import cv2

    n = rng.standard_normal(shape, dtype=np.float32)
    return cv2.GaussianBlur(n, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT)

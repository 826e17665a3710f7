"""Automatic region of interest on endoscope video: the tissue, without instruments, highlights or dark borders.

:func:`tissue_region` looks at a few frames of the reference camera and keeps the pixels that are tissue worth
tracking; :func:`specular_mask` finds the specular highlights of one frame (cheap enough for every frame). Both
are pure functions on arrays (8-bit BGR (H, W, 3) as read by ``cv2.imread``, or 8-bit gray (H, W)).

Method
------
A pixel is removed from the tissue region, in this order (each pixel is counted under the first cause that
removes it, so the four fractions in :class:`TissueRegion` add up):

1. **dark**: the brightest channel, averaged over the frames, below ``DARK_FRACTION`` of the scene's bright level
   (its 95th percentile) or below ``DARK_MIN`` grey levels, in a region connected to the image border. This is
   the black frame around the image, vignetting and the unlit background (the phantom's surroundings); dark
   spots inside the tissue (blood pools) are left to the texture test. The brightest channel, not the grey
   level, so that dark-red blood, which has signal in red, is not called dark.
2. **specular**: the union over the frames of :func:`specular_mask`: bright, near-white (all three channels
   high) pixels that are either clipped or small bright blobs (white top-hat), grown by a few pixels.
3. **instrument** (colour only): instruments are metal, black or white plastic: near-neutral under the white
   endoscope light, while living tissue is chromatic (red muscle and blood, pink, yellow fat). Chromaticness is
   the CIELAB saturation ``s = C*ab / L*`` (chroma over lightness, so that shading and vignetting do not change
   it). The instrument is the pixels with ``s < NEUTRAL_SATURATION`` in any frame, in regions connected to the
   image border (directly or through the dark border): instruments enter the view from outside, while neutral
   spots inside the tissue (highlights, pale fibres) do not. Colour is believed only when the scene is clearly
   chromatic: the median saturation of the lit, non-specular pixels (the bulk of the view, i.e. the tissue) at
   least ``CHROMA_CONTRAST`` times ``NEUTRAL_SATURATION``. A pale scene (a silicone phantom, s ~ 0.4) fails this
   and gets no instrument test, and ``reasons`` says so; so does gray input (no colour).

   Why not Otsu's split of the saturation histogram: measured on the Hamlyn in-vivo heart, ``log s`` has no
   valley between instrument and tissue (tinted reflections on metal, pale tissue and blood fill it), Otsu's
   effectiveness wanders between 0.59 and 0.74 from one window of frames to the next, so any bimodality gate
   flips on and off; and in the right camera, where the instruments are 1-2 % of the view, Otsu splits two
   shades of red. An absolute colorimetric limit plus a contrast gate was stable on every window of both cameras.
4. **untextured**: the local gradient energy (gradient of the image smoothed with sigma 1.5 px, root mean square
   over a window of about a twelfth of the image's smaller side, highlights left out), averaged over the frames,
   below ``TEXTURE_SNR`` times what the image noise alone would give. The noise is estimated from the image
   itself (Immerkaer's Laplacian-difference estimator, strongest edges left out), so the test is on signal to
   noise, not on a grey-level constant: pure noise is untextured, and so is a flat or blank image. The large
   window keeps smooth patches of tissue that are surrounded by texture.

Then: small holes in the region (up to ``HOLE_FRACTION`` of the image, not highlights) are filled, the region is
eroded by ``margin_px`` away from the dark, instrument and untextured parts (not from highlights, which are
small and move, nor from the image border), and islands smaller than ``ISLAND_FRACTION`` of the image are
dropped. Less than ``MIN_TISSUE_FRACTION`` of the image left: :class:`TissueNotFound`, whose message says what
was removed and to pass ``--mask``.

Constants
---------
The constants are fractions of the image's own brightness distribution, signal-to-noise ratios, colorimetric
quantities (CIELAB saturation) or fractions of the image area; none is a grey level tuned to one recording,
except the two 8-bit floors ``DARK_MIN`` and ``SPECULAR_CLIP`` (the bottom and top of the 8-bit range).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import functools
import logging

import numpy as np

__all__ = ["TissueNotFound", "TissueRegion", "specular_mask", "tissue_region", "noise_sigma", "neutral_mask",
           "DARK_FRACTION", "DARK_MIN",
           "SPECULAR_LEVEL_FRACTION", "SPECULAR_CONTRAST_FRACTION", "SPECULAR_CLIP", "SPECULAR_BLOB_FRACTION",
           "NEUTRAL_SATURATION", "CHROMA_CONTRAST", "TEXTURE_SNR", "HOLE_FRACTION", "ISLAND_FRACTION",
           "MIN_TISSUE_FRACTION"]

log = logging.getLogger(__name__)

#: Dark: the brightest channel below this fraction of the scene's bright level (95th percentile of the brightest
#: channel). The endoscope's light falls off to black at the rim of the view, so the unlit border and background
#: sit far below any lit tissue (Hamlyn in-vivo: black frame 0-10 against a bright level ~220, dark-red blood
#: ~110; phantom background 5-20 against 168); a fifth leaves a wide gap on both sides, whatever the exposure.
DARK_FRACTION = 0.2
#: Dark whatever the scene: the brightest channel below this many grey levels (the bottom 6 % of the 8-bit
#: range; a black or nearly black image is all dark).
DARK_MIN = 16
#: Specular, adaptive level: the smallest channel at or above ``median + SPECULAR_LEVEL_FRACTION * (255 -
#: median)`` of the smallest channel, i.e. closer to white than to the typical surface in every channel.
SPECULAR_LEVEL_FRACTION = 0.6
#: Specular, blob contrast: the smallest channel's white top-hat at least this fraction of ``255 - median``
#: (a highlight stands out of its surroundings, a pale surface does not).
SPECULAR_CONTRAST_FRACTION = 0.2
#: Specular whatever its size: all three channels at or above this level (clipped by the 8-bit sensor range).
SPECULAR_CLIP = 250
#: Highlights are blobs narrower than this fraction of the image's smaller side (the top-hat's square side;
#: 15 px at 288 rows); wider bright areas must be clipped to count as specular.
SPECULAR_BLOB_FRACTION = 0.05
#: CIELAB saturation ``C*ab / L*`` below which a surface is near-neutral (grey, white, black, metal). Tissue under
#: the white endoscope light is well above it (red muscle and blood 1-2.5, fat about 0.5, a pale yellow
#: silicone phantom about 0.3); bare instruments are about 0.05-0.15, tinted a little by the tissue they mirror.
NEUTRAL_SATURATION = 0.25
#: Colour tells instruments from tissue only where the tissue is clearly chromatic: the lit pixels' median
#: saturation (the bulk of the view, which is tissue) at least this many times ``NEUTRAL_SATURATION``.
CHROMA_CONTRAST = 3.0
#: Near-neutral pieces smaller than this fraction of the image are not called instrument (specks, noise).
INSTRUMENT_MIN_FRACTION = 0.0005
#: Textured: local gradient energy at least this many times the energy that the image noise alone gives (a
#: three-sigma-like detection threshold on the gradient-energy signal-to-noise ratio).
TEXTURE_SNR = 3.0
#: Holes up to this fraction of the image are filled (not highlights).
HOLE_FRACTION = 0.005
#: Islands smaller than this fraction of the image are dropped.
ISLAND_FRACTION = 0.01
#: Less tissue than this fraction of the image: :class:`TissueNotFound`.
MIN_TISSUE_FRACTION = 0.05

_TEXTURE_SIGMA = 1.5      # px, smoothing before the gradient (keeps structure, halves the noise's gradient)
_CHROMA_SIGMA = 1.5       # px, smoothing of the Lab image before the saturation (instrument texture, sensor noise)
_L_FLOOR = 10.0           # L* units: the saturation's denominator is at least this (dark pixels are noisy)


class TissueNotFound(RuntimeError):
    """:func:`tissue_region` found too little tissue in the frames: the user should pass a hand-made mask."""


@dataclass(frozen=True)
class TissueRegion:
    """The automatic tissue region and how it was found.

    Attributes
    ----------
    mask : ndarray (H, W) bool
        True on tissue to track.
    dark, specular, instrument, untextured : float
        Fractions of the image removed by each cause (each pixel counted under the first cause that removed it,
        in this order; the margin and the island removal are not counted).
    method : str
        ``"colour+chroma"`` (colour frames, near-neutral instrument test done), ``"colour"`` (colour frames, scene
        too pale for the test: no instrument removed) or ``"gray"`` (no colour: no instrument test).
    reasons : list of str
        What each step found, in words (thresholds used, why the instrument test was done or not).
    """

    mask: np.ndarray
    dark: float
    specular: float
    instrument: float
    untextured: float
    method: str
    reasons: list = field(default_factory=list)

    @property
    def fraction(self) -> float:
        """Fraction of the image in the mask."""
        return float(self.mask.mean())

    @property
    def area_px(self) -> int:
        """Pixels in the mask."""
        return int(self.mask.sum())


def _ellipse(radius):
    import cv2

    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def _hist_quantile(img_u8, q) -> float:
    """The ``q`` quantile (0-1) of an 8-bit image, from its histogram (much faster than np.percentile)."""
    import cv2

    h = cv2.calcHist([img_u8], [0], None, [256], [0, 256]).ravel()
    c = np.cumsum(h)
    return float(np.searchsorted(c, q * c[-1]))


def _as_image(image):
    """``image`` as a uint8 (H, W) or (H, W, 3) array (checked)."""
    a = np.asarray(image)
    if a.dtype != np.uint8:
        raise ValueError(f"image: 8-bit (uint8) expected, got {a.dtype}")
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 3)):
        raise ValueError(f"image: (H, W) gray or (H, W, 3) BGR expected, got shape {a.shape}")
    return a


def _min_channel(a):
    """Smallest of the three channels (the image itself if gray)."""
    import cv2

    if a.ndim == 2:
        return a
    b, g, r = cv2.split(a)
    return cv2.min(cv2.min(b, g), r)


def _channels(image):
    """(min channel, max channel, gray, is_colour) of an 8-bit BGR or gray image."""
    import cv2

    a = _as_image(image)
    if a.ndim == 2:
        return a, a, a, False
    b, g, r = cv2.split(a)
    mn = cv2.min(cv2.min(b, g), r)
    mx = cv2.max(cv2.max(b, g), r)
    colour = not (np.array_equal(b, g) and np.array_equal(g, r))
    gray = cv2.cvtColor(a, cv2.COLOR_BGR2GRAY) if colour else b
    return mn, mx, gray, colour


def specular_mask(image, *, level=None, grow_px=2) -> np.ndarray:
    """Specular highlights of one frame: bright, near-white pixels, grown by ``grow_px``.

    Parameters
    ----------
    image : ndarray (H, W, 3) BGR or (H, W) gray, uint8
        One frame.
    level : int, optional
        Fixed level: a pixel is specular when its smallest channel (its grey level for gray input) is at or
        above it. Default (None): adaptive to the frame. With ``m`` the smallest channel and ``med`` its median,
        a pixel is specular when ``m >= med + SPECULAR_LEVEL_FRACTION * (255 - med)`` and it is a small bright
        blob (white top-hat of ``m`` over a square of ``SPECULAR_BLOB_FRACTION`` of the image's smaller side at
        least ``SPECULAR_CONTRAST_FRACTION * (255 - med)``), or when ``m >= SPECULAR_CLIP`` (clipped, any size).
        The smallest channel is high only where all channels are: near-white, low-saturation pixels, which
        red or yellow tissue is not however bright.
    grow_px : int
        Dilate the highlights by this many pixels (their blurred rims, and the patches around points near them).

    Returns
    -------
    ndarray (H, W) bool
        True on highlights.

    Notes
    -----
    About 0.25 ms at 360 x 288 (histogram, one grey opening, one dilation); about 10 ms at 1920 x 1080 (the
    opening on the image shrunk 3 x, the median from every third pixel).
    """
    import cv2

    m = _min_channel(_as_image(image))

    def at_least(img, v):     # 0/1 uint8 image of img >= v (img integer: >= ceil(v))
        v = int(np.ceil(v))
        if v <= 0:
            return np.ones(img.shape, np.uint8)
        return cv2.threshold(img, v - 1, 1, cv2.THRESH_BINARY)[1]

    if level is not None:
        spec = at_least(m, level)
    else:
        k = max(1, min(m.shape) // 300)     # the median from every k-th pixel on large images
        med = _hist_quantile(m if k == 1 else np.ascontiguousarray(m[::k, ::k]), 0.5)
        lvl = med + SPECULAR_LEVEL_FRACTION * (255.0 - med)
        contrast = SPECULAR_CONTRAST_FRACTION * (255.0 - med)
        blob = cv2.bitwise_and(at_least(m, lvl), at_least(cv2.subtract(m, _opening(m)), contrast))
        spec = cv2.bitwise_or(blob, at_least(m, SPECULAR_CLIP))
    if grow_px > 0 and cv2.countNonZero(spec):
        spec = cv2.dilate(spec, _ellipse(int(grow_px)))
    return spec.view(bool)


def _opening(m) -> np.ndarray:
    """Grey opening of ``m`` by a square of ``SPECULAR_BLOB_FRACTION`` of its smaller side (the background that
    blobs narrower than the square stand out of). Above 600 px per side it is computed on the image shrunk by
    an integer factor (pixel averages) and enlarged back (bilinear), which keeps the square near 15-30 px: the
    opening is a smooth background, and the full-size square costs 25 ms a frame at 1920 x 1080."""
    import cv2

    H, W = m.shape
    f = max(1, min(H, W) // 300)
    small = m if f == 1 else cv2.resize(m, (W // f, H // f), interpolation=cv2.INTER_AREA)
    side = max(3, int(round(SPECULAR_BLOB_FRACTION * min(small.shape))) | 1)
    opened = cv2.morphologyEx(small, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_RECT, (side, side)))
    if f > 1:
        opened = cv2.resize(opened, (W, H), interpolation=cv2.INTER_LINEAR)
    return opened


@functools.lru_cache(maxsize=8)
def _noise_gain(window) -> float:
    """RMS of :func:`_gradient_energy` on unit white noise (the factor from noise sigma to its gradient energy)."""
    rng = np.random.default_rng(0)
    n = rng.standard_normal((256 + 2 * window, 256 + 2 * window)).astype(np.float32)
    e = _gradient_energy(n, window)
    return float(np.sqrt(np.mean(e[window:-window, window:-window])))


def _gradient_energy(gray, window, weight=None) -> np.ndarray:
    """Mean squared gradient (grey levels per pixel, squared) of the smoothed image over a ``window`` box, where
    ``weight`` (float32 0/1) is 1 (normalised convolution: excluded pixels do not count)."""
    import cv2

    b = cv2.GaussianBlur(np.asarray(gray, np.float32), (0, 0), _TEXTURE_SIGMA)
    gx = cv2.Sobel(b, cv2.CV_32F, 1, 0, ksize=3) * 0.125
    gy = cv2.Sobel(b, cv2.CV_32F, 0, 1, ksize=3) * 0.125
    g2 = gx * gx + gy * gy
    if weight is None:
        return cv2.boxFilter(g2, -1, (window, window))
    num = cv2.boxFilter(g2 * weight, -1, (window, window))
    den = cv2.boxFilter(weight, -1, (window, window))
    return num / np.maximum(den, 1e-3)


def noise_sigma(gray) -> float:
    """Noise standard deviation (grey levels) of an image: Immerkaer's estimator (mean absolute response to the
    difference of two Laplacians, zero on any locally linear image) over the pixels away from strong edges
    (the 10 % strongest gradients left out, as edges leak into the estimator)."""
    import cv2

    g = np.asarray(gray, np.float32)
    k = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    r = np.abs(cv2.filter2D(g, -1, k, borderType=cv2.BORDER_REFLECT))[1:-1, 1:-1]
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)[1:-1, 1:-1]
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)[1:-1, 1:-1]
    gm = gx * gx + gy * gy
    keep = gm <= np.percentile(gm, 90)
    if keep.sum() < 100:
        keep = np.ones_like(keep)
    return float(np.mean(r[keep])) * np.sqrt(np.pi / 2) / 6.0


def _touching_border(mask_u8) -> np.ndarray:
    """The 8-connected components of a 0/1 image that touch the image border (bool)."""
    import cv2

    n, labels = cv2.connectedComponents(mask_u8, connectivity=8)
    if n <= 1:
        return np.zeros(mask_u8.shape, bool)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    border = border[border > 0]
    lut = np.zeros(n, bool)
    lut[border] = True
    return lut[labels]


def _drop_small(mask, min_px) -> np.ndarray:
    """``mask`` without its 8-connected components smaller than ``min_px``."""
    import cv2

    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    keep = stats[:, cv2.CC_STAT_AREA] >= min_px
    keep[0] = False
    return keep[labels]


def _saturation(frame_bgr) -> np.ndarray:
    """CIELAB saturation ``C*ab / L*`` of a BGR uint8 image, smoothed over ``_CHROMA_SIGMA`` (float32)."""
    import cv2

    lab = cv2.cvtColor(frame_bgr, cv2.COLOR_BGR2LAB).astype(np.float32)
    lab = cv2.GaussianBlur(lab, (0, 0), _CHROMA_SIGMA)
    lstar = lab[..., 0] * (100.0 / 255.0)
    chroma = cv2.magnitude(lab[..., 1] - 128.0, lab[..., 2] - 128.0)
    return chroma / np.maximum(lstar, _L_FLOOR)


def neutral_mask(frame_bgr, region=None, grow_px=0) -> np.ndarray | None:
    """Near-neutral pixels of one colour frame (CIELAB saturation below :data:`NEUTRAL_SATURATION`: metal and
    plastic instruments, not red tissue), grown by ``grow_px``; None when the frame is gray or too pale (the median
    saturation over ``region``, default the whole frame, below ``CHROMA_CONTRAST * NEUTRAL_SATURATION``) for colour
    to tell instruments from tissue. The per-frame counterpart of the instrument test of :func:`tissue_region`
    (instruments move into the view after the first frames)."""
    import cv2

    frame_bgr = np.asarray(frame_bgr)
    if frame_bgr.ndim != 3 or frame_bgr.shape[2] != 3:
        return None
    sat = _saturation(frame_bgr)
    sample = sat[::2, ::2] if region is None else sat[::2, ::2][np.asarray(region, bool)[::2, ::2]]
    if sample.size == 0 or float(np.median(sample)) < CHROMA_CONTRAST * NEUTRAL_SATURATION:
        return None
    neutral = (sat < NEUTRAL_SATURATION).astype(np.uint8)
    if grow_px > 0 and cv2.countNonZero(neutral):
        neutral = cv2.dilate(neutral, _ellipse(int(grow_px)))
    return neutral.view(bool)


def _instrument(frames, lit, spec_frames, dark, reasons):
    """Near-neutral regions connected to the border, if colour can tell instruments from tissue (else None)."""
    H, W = lit.shape
    sats = [_saturation(f) for f in frames]
    samples = [s[::2, ::2][(lit & ~sp)[::2, ::2]] for s, sp in zip(sats, spec_frames)]
    x = np.concatenate(samples)
    if x.size < 0.05 * H * W / 4:
        reasons.append("instrument: too few lit pixels to judge colour; no instrument removed")
        return None
    bulk = float(np.median(x))
    neutral_share = float((x < NEUTRAL_SATURATION).mean())
    desc = (f"instrument (colour): lit pixels' median CIELAB saturation {bulk:.2f}, "
            f"{100 * neutral_share:.1f} % near-neutral (s < {NEUTRAL_SATURATION})")
    if bulk < CHROMA_CONTRAST * NEUTRAL_SATURATION:
        reasons.append(f"{desc}: the scene is too pale (median < {CHROMA_CONTRAST} x {NEUTRAL_SATURATION}) to tell "
                       f"instruments from tissue by colour; no instrument removed (pass --mask if one is in view)")
        return None
    neutral = np.zeros((H, W), bool)
    for s in sats:
        neutral |= s < NEUTRAL_SATURATION
    neutral &= lit
    inst = neutral & _touching_border((neutral | dark).view(np.uint8))
    inst = _drop_small(inst, int(INSTRUMENT_MIN_FRACTION * H * W) + 1)
    reasons.append(f"{desc}: instrument = near-neutral regions connected to the image border: "
                   f"{100 * inst.mean():.1f} % of the image")
    return inst


def tissue_region(frames, *, margin_px=None, min_fraction=MIN_TISSUE_FRACTION) -> TissueRegion:
    """The tissue seen in a few frames of the reference camera, without instruments, highlights and dark borders.

    Parameters
    ----------
    frames : sequence of ndarray, uint8
        A few frames (one is enough, 3-10 is better: highlights and instruments move) of one camera, all of one
        shape: (H, W, 3) BGR as read by ``cv2.imread``, or (H, W) gray. Gray (or BGR with equal channels) gets
        no instrument test.
    margin_px : int, optional
        Erode the region by this many pixels away from the dark, instrument and untextured parts, so that patches
        around tracked points stay on tissue. Default: 2 % of the image's smaller side (6 px at 288 rows), at
        least 2.
    min_fraction : float
        Less tissue than this fraction of the image: :class:`TissueNotFound`.

    Returns
    -------
    TissueRegion
        ``mask`` and the diagnostics (see the module docstring for the method).

    Raises
    ------
    TissueNotFound
        Less than ``min_fraction`` of the image is tissue; the message says what was removed and to pass
        ``--mask``.
    ValueError
        No frames, frames of different shapes, or not 8-bit images.
    """
    import cv2

    frames = [np.asarray(f) for f in frames]
    if not frames:
        raise ValueError("frames: at least one image expected")
    frames = [f[:, :, 0] if f.ndim == 3 and f.shape[2] == 1 else f for f in frames]
    shape = frames[0].shape
    if any(f.shape != shape for f in frames):
        raise ValueError(f"frames: all of one shape expected, got {sorted({f.shape for f in frames})}")
    chans = [_channels(f) for f in frames]
    colour = all(c[3] for c in chans)
    H, W = shape[:2]
    n_px = H * W
    side = min(H, W)
    margin = max(2, int(round(0.02 * side))) if margin_px is None else int(margin_px)
    reasons = []

    # 1. dark, connected to the border
    vmax = np.mean([c[1] for c in chans], axis=0).astype(np.float32) if len(chans) > 1 else chans[0][1]
    vmax_u8 = np.asarray(np.clip(vmax, 0, 255), np.uint8)
    bright = _hist_quantile(vmax_u8, 0.95)
    dark_level = max(DARK_FRACTION * bright, DARK_MIN)
    dark = _touching_border((vmax_u8 < dark_level).view(np.uint8))
    reasons.append(f"dark: brightest channel < {dark_level:.0f} (max of {DARK_MIN} and {DARK_FRACTION:.0%} of the "
                   f"95th percentile {bright:.0f}), connected to the border: {100 * dark.mean():.1f} % of the image")

    # 2. specular highlights, union over the frames
    spec_frames = [specular_mask(f) for f in frames]
    specular = np.logical_or.reduce(spec_frames)
    reasons.append(f"specular: union of {len(frames)} frame(s): {100 * specular.mean():.1f} % of the image")

    # 3. instruments (colour)
    lit = ~dark
    instrument = None
    if colour:
        instrument = _instrument(frames, lit, spec_frames, dark, reasons)
        method = "colour+chroma" if instrument is not None else "colour"
    else:
        reasons.append("gray frames: no colour, so no instrument test (pass --mask if an instrument is in view)")
        method = "gray"
    if instrument is None:
        instrument = np.zeros((H, W), bool)
    elif instrument.any():
        # close the instrument's own texture (sparkles, engravings) and its highlights into one piece
        instrument = cv2.morphologyEx(instrument.view(np.uint8), cv2.MORPH_CLOSE, _ellipse(2)).astype(bool) & lit

    # 4. texture: gradient-energy signal-to-noise over a large window, highlights left out
    window = max(9, int(round(side / 12)) | 1)
    energy = np.zeros((H, W), np.float32)
    noise = []
    for (_, _, gray, _), sp in zip(chans, spec_frames):
        energy += _gradient_energy(gray, window, (~sp).astype(np.float32))
        noise.append(noise_sigma(gray))
    energy /= len(chans)
    sigma = max(float(np.median(noise)), 0.3)   # 0.3: 8-bit quantisation noise (1/sqrt(12)) at least
    snr = np.sqrt(np.maximum(energy, 0.0)) / (_noise_gain(window) * sigma)
    untextured_all = snr < TEXTURE_SNR
    reasons.append(f"texture: noise sigma {sigma:.2f} grey levels, gradient-energy SNR over {window} px windows "
                   f"< {TEXTURE_SNR}: {100 * untextured_all.mean():.1f} % of the image")

    # disjoint accounting, in the order dark, specular, instrument, untextured
    f_dark = float(dark.mean())
    f_spec = float((specular & ~dark).mean())
    f_inst = float((instrument & ~dark & ~specular).mean())
    untextured = untextured_all & ~dark & ~specular & ~instrument
    f_untex = float(untextured.mean())

    # 5. morphology
    hard = dark | instrument | untextured_all
    tissue = ~(hard | specular)
    # fill small holes that are not highlights
    holes = ~tissue & ~_touching_border((~tissue).view(np.uint8))
    small_holes = holes & ~_drop_small(holes, int(HOLE_FRACTION * n_px) + 1)
    tissue |= small_holes & ~specular
    hard &= ~small_holes
    if margin > 0 and hard.any():
        tissue &= ~cv2.dilate(hard.view(np.uint8), _ellipse(margin)).astype(bool)
    tissue = _drop_small(tissue, int(ISLAND_FRACTION * n_px))

    frac = float(tissue.mean())
    summary = (f"dark {100 * f_dark:.1f} %, specular {100 * f_spec:.1f} %, instrument {100 * f_inst:.1f} %, "
               f"untextured {100 * f_untex:.1f} %")
    log.info("tissue region (%s): %.1f %% of the image (%d px); removed %s; margin %d px", method, 100 * frac,
             int(tissue.sum()), summary, margin)
    for r in reasons:
        log.debug("tissue region: %s", r)
    if frac < min_fraction:
        # the cause that alone removes the most (black: dark; noise or a flat image: untextured)
        alone = [("dark", dark.mean()), ("specular", specular.mean()), ("instrument", instrument.mean()),
                 ("untextured", untextured_all.mean())]
        worst = max(alone, key=lambda kv: kv[1])[0]
        raise TissueNotFound(
            f"no tissue region found automatically: only {int(tissue.sum())} px ({100 * frac:.1f} % of the "
            f"{W}x{H} image, at least {100 * min_fraction:.0f} % needed) look like textured tissue; removed: "
            f"{summary} (mostly {worst}; method {method}). Pass --mask with an image of the tissue region "
            f"(nonzero = tissue) for the reference camera.")
    return TissueRegion(mask=tissue, dark=f_dark, specular=f_spec, instrument=f_inst, untextured=f_untex,
                        method=method, reasons=reasons)

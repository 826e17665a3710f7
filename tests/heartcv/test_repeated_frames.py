"""Frames that repeat their previous one (heartcv.measure.changed_share, RepeatedViews, run_frames' drop_repeats):
a frame-rate conversion or a capture that froze delivers the same exposure twice; measured as a frame of its own
it says the surface stood still for a frame and then moved twice as far. The changed share against closed forms,
the repeats found among moving frames exactly (copied, and copied with re-encoding noise), never in a still scene or
a slow frame. (The synthetic trinocular sequence with a repeated instant and a camera out of step:
test_measure_core.py.)"""

import numpy as np
import pytest

from heartcv.measure import (
    REPEAT_LEVEL,
    REPEAT_SHARE,
    REPEAT_UNCHANGED,
    RepeatedViews,
    changed_share,
    unchanged_share,
)


def _texture(rng, shape=(120, 160)):
    """A smooth random 8-bit texture (mid-grey, contrast about +-60 levels)."""
    import cv2

    noise = rng.normal(0.0, 1.0, shape).astype(np.float32)
    smooth = cv2.GaussianBlur(noise, (0, 0), 2.0)
    return np.clip(128 + 60 * smooth / smooth.std(), 0, 255).astype(np.uint8)


def _shifted(image, dx):
    """``image`` moved right by ``dx`` px (linear interpolation; the edge replicated)."""
    import cv2

    M = np.array([[1.0, 0.0, dx], [0.0, 1.0, 0.0]])
    return cv2.warpAffine(image, M, image.shape[::-1], flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


# -- changed_share ------------------------------------------------------------------------------------------------
def test_changed_share_counts_the_pixels_beyond_the_level_on_every_second_row_and_column():
    a = np.full((40, 60), 100, np.uint8)
    assert changed_share(a, a) == 0.0
    b = a.copy()
    b[:8] += 9                     # rows 0..7: rows 0, 2, 4, 6 of the 20 sampled rows change by more than 8 levels
    assert changed_share(b, a) == pytest.approx(4 / 20)
    c = a.copy()
    c[:8] += 8                     # exactly the level: not more
    assert changed_share(c, a) == 0.0
    d = a.copy()
    d[1::2] = 0                    # odd rows only: never sampled
    assert changed_share(d, a) == 0.0
    assert changed_share(a[:, :50], a) == 1.0          # another shape: a change


def test_changed_share_colour_16_bit_and_float_scales():
    rng = np.random.default_rng(0)
    a = rng.integers(50, 200, (30, 30, 3), dtype=np.uint8)
    b = a.copy()
    b[::2, ::2, 2][:5] += 20                            # one channel of 5 of the 15 sampled rows
    assert changed_share(b, a) == pytest.approx(5 / 15)
    w = rng.integers(100, 4000, (30, 30)).astype(np.uint16)   # a 12-bit camera in 16-bit files
    scale = float(w[::2, ::2].max())
    step = REPEAT_LEVEL * scale
    v = w.copy()
    v[::2, ::2][:3] = (w[::2, ::2][:3] + np.floor(step)).astype(np.uint16)   # within the level
    assert changed_share(v, w) == 0.0
    v[::2, ::2][:3] = (w[::2, ::2][:3] + np.ceil(step) + 1).astype(np.uint16)
    assert changed_share(v, w) == pytest.approx(3 / 15)
    f = w.astype(np.float32) / 4000
    g = f.copy()
    g[::2, ::2][:6] += 0.5
    assert changed_share(g, f) == pytest.approx(6 / 15)


def test_unchanged_share_counts_the_live_pixels_kept_exactly():
    a = np.full((40, 60), 100, np.uint8)
    a[:, :30] = 0                                       # clipped black: not live
    b = a.copy()
    b[:10, 30:] += 1                                    # rows 0..9: 5 of the 20 sampled rows of the live half
    assert unchanged_share(a, a) == 1.0
    assert unchanged_share(b, a) == pytest.approx(15 / 20)
    b[:, :30] = 3                                       # within 2 % of the scale: still not live
    assert unchanged_share(b, a) == pytest.approx(15 / 20)
    assert np.isnan(unchanged_share(np.zeros((8, 8), np.uint8), np.zeros((8, 8), np.uint8)))
    assert np.isnan(unchanged_share(a[:, :50], a))
    rng = np.random.default_rng(7)                      # fresh noise of 1.5 levels: few pixels keep their value
    t = _texture(rng)
    n1, n2 = (np.clip(t + rng.normal(0, 1.5, t.shape), 0, 255).astype(np.uint8) for _ in range(2))
    assert unchanged_share(n2, n1) < 0.3 < REPEAT_UNCHANGED
    c = np.dstack([a, a, a])
    d = c.copy()
    d[::2, ::2][:4, 15:, 1] += 1                        # one channel of 4 of the 20 sampled rows
    assert unchanged_share(d, c) == pytest.approx(16 / 20)


# -- RepeatedViews ------------------------------------------------------------------------------------------------
def _moving(rng, n=30, speed=0.7):
    """``n`` frames of a texture moving ``speed`` px a frame, with 1.5 levels of sensor noise."""
    base = _texture(rng)
    return [np.clip(_shifted(base, speed * k) + rng.normal(0, 1.5, base.shape), 0, 255).astype(np.uint8)
            for k in range(n)]


def _found(frames):
    """The frame indices RepeatedViews calls repeats of a one-camera sequence."""
    rv = RepeatedViews(1)
    return [k for k, im in enumerate(frames) if rv([im])]


def test_copied_frames_among_moving_ones_are_found_exactly():
    rng = np.random.default_rng(1)
    frames = _moving(rng)
    copies = [6, 12, 13, 18, 24]                 # every 6th, and two in a row
    seq = list(frames)
    for k in copies:
        seq[k] = seq[k - 1]
    assert _found(seq) == copies


def test_copies_with_reencoding_noise_are_found():
    """A copy re-encoded: most pixels unchanged, a few by up to the level, a handful of block edges beyond it."""
    rng = np.random.default_rng(2)
    frames = _moving(rng)
    seq = list(frames)
    for k in (7, 14, 21):
        prev = seq[k - 1].astype(np.int16)
        noisy = prev + rng.integers(-2, 3, prev.shape) * (rng.random(prev.shape) < 0.3)
        edge = rng.random(prev.shape) < 0.004
        noisy[edge] += 20
        seq[k] = np.clip(noisy, 0, 255).astype(np.uint8)
        assert 0 < changed_share(seq[k], seq[k - 1]) <= REPEAT_SHARE
    assert _found(seq) == [7, 14, 21]


def test_a_still_scene_and_a_slow_frame_are_not_repeats():
    rng = np.random.default_rng(3)
    still = [_texture(np.random.default_rng(9))] * 12             # a noise-free still scene: identical frames
    assert _found(still) == []
    base = _texture(np.random.default_rng(4))
    # one frame moves a quarter of the others' 0.7 px (a turning point); not a copy. (On this smooth texture a
    # frame moving 0.07 px changes under 0.1 % of the pixels beyond the level: as little as a re-encoded copy.)
    slow = [np.clip(_shifted(base, 0.7 * k - (0.525 if k >= 10 else 0.0)) + rng.normal(0, 1.5, base.shape), 0, 255)
            .astype(np.uint8) for k in range(30)]
    assert changed_share(slow[10], slow[9]) > REPEAT_SHARE
    assert changed_share(slow[10], slow[9]) < 0.2 * np.median([changed_share(b, a) for a, b in
                                                                 zip(slow, slow[1:], strict=False)])
    assert _found(slow) == []
    # a frame that barely moves (0.02 px: fewer pixels change beyond the level than in a re-encoded copy) is a new
    # exposure all the same: its fresh noise tells it from a copy
    seq = [np.clip(_shifted(base, 0.7 * k - (0.68 if k >= 10 else 0.0)) + rng.normal(0, 1.5, base.shape), 0, 255)
           .astype(np.uint8) for k in range(30)]
    assert changed_share(seq[10], seq[9]) < REPEAT_SHARE and unchanged_share(seq[10], seq[9]) < REPEAT_UNCHANGED
    assert _found(seq) == []
    seq[10] = seq[9]
    assert _found(seq) == [10]


def test_a_small_moving_region_never_makes_repeats():
    """Only 0.5 % of the view moves (shares below REPEAT_SHARE): detection stays off, even for exact copies."""
    base = np.full((120, 160), 90, np.uint8)
    seq = []
    for k in range(20):
        im = base.copy()
        im[10:14, 20 + k:30 + k] = 200
        seq.append(im)
    seq[8] = seq[7]
    assert max(changed_share(b, a) for a, b in zip(seq, seq[1:], strict=False)) < REPEAT_SHARE
    assert _found(seq) == []


def test_views_are_judged_each_on_its_own_and_a_missing_image_keeps_the_previous():
    rng = np.random.default_rng(6)
    a, b = _moving(rng, 12), _moving(rng, 12, speed=-0.9)
    rv = RepeatedViews(2)
    got = []
    for k in range(12):
        images = [a[k], b[k]]
        if k == 5:
            images[1] = b[4]                       # camera 1 out of step
        if k == 8:
            images[0] = None                       # camera 0's image missing ...
        if k == 9:
            images[0] = a[7]                       # ... then its frame before the gap again: a repeat
        got.append(rv(images))
    assert got == [[], [], [], [], [], [1], [], [], [], [0], [], []]
    assert len(rv.shares[0]) == 10 and len(rv.shares[1]) == 11


def test_frame_spans_as_runs():
    from heartcv.measure_data import frame_spans

    assert frame_spans([150, 4, 100, 101, 102, 101]) == "4, 100-102, 150"
    assert frame_spans([7]) == "7" and frame_spans([]) == ""
    assert frame_spans(range(0, 40, 2), most=3) == "0, 2, 4, ... (17 more runs)"

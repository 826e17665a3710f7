"""heartcv.overlay: track statistics and the pictures of ``measure --overlay``, checked pixel by pixel.

Drawing is checked on black images with 8-connected (not anti-aliased) lines, where every drawn pixel has exactly
its track's colour: a segment's pixels are coloured, a NaN gap leaves the pixels between two segments untouched
(and the same trail without the gap colours them: the control), the current position gets a dot only when seen,
sub-pixel positions land on the nearest pixel, and the region of interest is outlined on its border pixels only.
"""

from __future__ import annotations

import numpy as np
import pytest

from heartcv.measure import MeasureResult
from heartcv.overlay import (
    MISSING_GRAY,
    ROI_COLOR,
    draw_tracks,
    overlay_frame,
    track_colors,
    track_lengths,
    track_subset,
)

NAN = np.nan

# The synthetic result: 5 instants (frame indices 10..14), 3 tracks, 2 cameras of 64x48 px.
#   track 0 (id 0): seen in every instant                       span 5, count 5
#   track 1 (id 1): seen in instants 0, 1 and 3 (gap at 2)      span 4, count 3
#   track 2 (id 7): born in instant 2, seen in 2, 3, 4           span 3, count 3
SEEN = np.array([[1, 1, 0],
                 [1, 1, 0],
                 [1, 0, 1],
                 [1, 1, 1],
                 [1, 0, 1]], bool)
IMAGE_W, IMAGE_H = 64, 48


def synthetic_result() -> MeasureResult:
    """A hand-made :class:`MeasureResult` following :data:`SEEN`; track ``p`` sits at ``u = 10 + 20 p + 2 k``,
    ``v = 12 + 8 p`` in camera 0 and 4 px further left in camera 1 (instant ``k``)."""
    K, P, C = SEEN.shape[0], SEEN.shape[1], 2
    uv = np.full((K, P, C, 2), NAN, np.float32)
    pos = np.full((K, P, 3), NAN)
    for k in range(K):
        for p in range(P):
            if SEEN[k, p]:
                u, v = 10 + 20 * p + 2 * k, 12 + 8 * p
                uv[k, p, 0] = (u, v)
                uv[k, p, 1] = (u - 4, v)
                pos[k, p] = (0.001 * p, 0.0, 0.05)
    cov = np.where(SEEN[..., None, None], np.eye(3) * 1e-8, NAN)
    roi = np.zeros((IMAGE_H, IMAGE_W), bool)
    roi[4:44, 4:60] = True
    return MeasureResult(
        frames=np.arange(10, 10 + K), point_ids=np.array([0, 1, 7]), birth_frame=np.array([0, 0, 2]),
        positions=pos, covariances=cov, reference=pos[[0, 0, 2], np.arange(P)], uv=uv,
        views=np.where(SEEN, 2, 0), reprojection_rms=np.where(SEEN, 0.1, NAN), sigma_px=0.5,
        sigma_estimated=False, roi=roi, timings={}, problems=[])


def _color(track_id) -> np.ndarray:
    return track_colors([track_id])[0]


# -- track_lengths, track_colors, track_subset --------------------------------------------------------------------
def test_track_lengths_hand_made():
    seen = np.array([[1, 0, 0, 0, 1],
                     [1, 1, 0, 0, 0],
                     [1, 0, 0, 0, 0],
                     [1, 0, 0, 1, 0],
                     [1, 1, 0, 0, 0],
                     [1, 0, 0, 0, 0]], bool)
    span, count = track_lengths(seen)
    assert span.tolist() == [6, 4, 0, 1, 1]
    assert count.tolist() == [6, 2, 0, 1, 1]
    assert span.dtype == count.dtype == np.int64


def test_track_lengths_of_the_synthetic_result_and_bad_shape():
    span, count = track_lengths(synthetic_result().seen)
    assert span.tolist() == [5, 4, 3]
    assert count.tolist() == [5, 3, 3]
    assert [a.tolist() for a in track_lengths(np.zeros((0, 2), bool))] == [[0, 0], [0, 0]]
    with pytest.raises(ValueError, match="shape"):
        track_lengths(np.ones(4, bool))


def test_track_colors_stable_and_distinct():
    c = track_colors([0, 1, 2, 3, 7])
    assert c.dtype == np.uint8 and c.shape == (5, 3)
    assert c[0].tolist() == [25, 25, 255]                    # hue 0: red (BGR), saturation 0.9, value 1
    assert np.array_equal(track_colors([7, 0])[0], c[4])      # a track's colour does not depend on the others
    assert len({tuple(v) for v in c.tolist()}) == 5


def test_track_subset():
    ids = np.arange(1000)
    assert track_subset(ids, 1.0).all() and not track_subset(ids, 0.0).any()
    sub = track_subset(ids, 0.1)
    assert 90 <= sub.sum() <= 110                             # equidistributed: 100 +- the discrepancy
    assert np.array_equal(track_subset(ids[::-1], 0.1), sub[::-1])
    # not tied to the colour: the kept tracks span the hues
    hues = np.mod(ids[sub] * (5 ** 0.5 - 1) / 2, 1.0)
    assert np.histogram(hues, bins=4, range=(0, 1))[0].min() >= 15
    with pytest.raises(ValueError, match="fraction"):
        track_subset(ids, 1.5)


# -- draw_tracks -----------------------------------------------------------------------------------------------------
def _draw(trail, seen_now=(True,), ids=(3,), image=None, **kw):
    image = np.zeros((40, 40), np.uint8) if image is None else image
    return draw_tracks(image, np.asarray(trail, float)[:, None, :] if np.ndim(trail) == 2 else trail,
                       np.asarray(seen_now), np.asarray(ids), antialias=False, **kw)


def test_draw_tracks_line_and_dot_in_the_track_colour():
    out = _draw([(5, 10), (15, 10), (25, 10)], radius=3)
    col = _color(3)
    assert out.shape == (40, 40, 3) and out.dtype == np.uint8
    for x in (5, 10, 15, 20):                                  # on the trail
        assert out[10, x].tolist() == col.tolist()
    for x, y in ((25, 10), (27, 10), (25, 12), (23, 10)):     # the dot (radius 3) around (25, 10)
        assert out[y, x].tolist() == col.tolist()
    assert out[14, 25].tolist() == [0, 0, 0]                   # outside the dot
    assert out[10, 2].tolist() == [0, 0, 0]                    # before the trail's start
    assert out[11, 10].tolist() == [0, 0, 0]                   # a 1-px line


def test_draw_tracks_nan_gap_breaks_the_trail():
    col = _color(3).tolist()
    gap = _draw([(5, 20), (10, 20), (NAN, NAN), (25, 20), (30, 20)], seen_now=(False,))
    joined = _draw([(5, 20), (10, 20), (25, 20), (30, 20)], seen_now=(False,))
    assert gap[20, 7].tolist() == col and gap[20, 27].tolist() == col
    assert gap[20, 13:23].tolist() == [[0, 0, 0]] * 10         # nothing between the two segments
    assert joined[20, 13:23].tolist() == [col] * 10            # the control: without the gap they are joined
    # a single seen position between two gaps is no segment, and without seen_now no dot either
    lone = _draw([(NAN, NAN), (20, 20), (NAN, NAN)], seen_now=(False,))
    assert not lone.any()


def test_draw_tracks_dot_only_where_seen_now():
    trail = np.array([[(5, 5), (5, 30)], [(15, 5), (15, 30)]], float)      # (T=2, P=2, 2)
    out = draw_tracks(np.zeros((40, 40), np.uint8), trail, np.array([True, False]), np.array([1, 2]),
                      radius=3, antialias=False)
    assert out[7, 15].tolist() == _color(1).tolist()           # dot of track 1 (2 px below its line)
    assert out[32, 15].tolist() == [0, 0, 0]                   # track 2 not seen now: its line, no dot
    assert out[30, 10].tolist() == _color(2).tolist()


def test_draw_tracks_sub_pixel_positions():
    # a vertical trail at u = 12.4 is drawn in column 12, at u = 12.6 in column 13 (1/16 px fixed point)
    left = _draw([(12.4, 5), (12.4, 30)], seen_now=(False,))
    right = _draw([(12.6, 5), (12.6, 30)], seen_now=(False,))
    assert left[10:25, 12].any(axis=1).all() and not left[10:25, 13].any()
    assert right[10:25, 13].any(axis=1).all() and not right[10:25, 12].any()


def test_draw_tracks_roi_outline():
    roi = np.zeros((40, 40), bool)
    roi[5:31, 8:36] = True
    out = _draw(np.full((2, 1, 2), NAN), seen_now=(False,), roi=roi)
    for y, x in ((5, 20), (30, 20), (15, 8), (15, 35), (5, 8)):      # border pixels of the region
        assert out[y, x].tolist() == list(ROI_COLOR)
    for y, x in ((15, 20), (6, 20), (4, 20), (31, 20), (15, 7), (15, 36)):  # inside and outside: untouched
        assert out[y, x].tolist() == [0, 0, 0]
    assert (out.any(axis=2)).sum() == 2 * (26 + 28) - 4       # the outline and nothing else
    with pytest.raises(ValueError, match="roi"):
        _draw(np.full((2, 1, 2), NAN), seen_now=(False,), roi=roi[:30])


def test_draw_tracks_input_untouched_and_antialiased_dot_centre():
    image = np.full((40, 40, 3), 50, np.uint8)
    before = image.copy()
    out = draw_tracks(image, np.array([[(20.0, 20.0)]]), np.array([True]), np.array([5]), radius=4)
    assert np.array_equal(image, before)
    assert out[20, 20].tolist() == _color(5).tolist()          # anti-aliased: the centre is the full colour
    assert out[0, 0].tolist() == [50, 50, 50]
    gray = draw_tracks(np.full((10, 12), 9, np.uint8), np.zeros((0, 0, 2)), np.zeros(0, bool), np.zeros(0))
    assert gray.shape == (10, 12, 3) and (gray == 9).all()
    with pytest.raises(ValueError, match="uv_trail"):
        draw_tracks(image, np.zeros((3, 2)), np.zeros(2, bool), np.zeros(2))


# -- overlay_frame ---------------------------------------------------------------------------------------------------
def _images(seed=0):
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 60, (IMAGE_H, IMAGE_W, 3), dtype=np.uint8) for _ in range(2)]


def test_overlay_frame_tiles_and_dots():
    res = synthetic_result()
    images = _images()
    out = overlay_frame(images, res, 3, 0, trail=3, names=["left", "right"])
    band = out.shape[0] - IMAGE_H
    assert out.shape[1:] == (2 * IMAGE_W, 3) and 20 <= band <= 60
    assert not out[band:].all(axis=2).all()
    for p, track_id in enumerate(res.point_ids):               # every track is seen in instant 3: a dot each
        u, v = 10 + 20 * p + 6, 12 + 8 * p
        assert out[band + v, u].tolist() == _color(track_id).tolist()
        assert out[band + v, IMAGE_W + u - 4].tolist() == _color(track_id).tolist()
    # the reference camera's tile has the ROI outline, the other one not
    assert out[band + 4, 30].tolist() == list(ROI_COLOR)
    assert out[band + 4, IMAGE_W + 30].tolist() == images[1][4, 30].tolist()
    # away from tracks and outline the image is unchanged
    assert np.array_equal(out[band + 40:band + 43, 20:30], images[0][40:43, 20:30])


def test_overlay_frame_missing_image_and_gaps():
    res = synthetic_result()
    images = _images()
    out = overlay_frame([images[0], None], res, 2, 0)
    band = out.shape[0] - IMAGE_H
    tile = out[band:, IMAGE_W:]
    assert tile[45, 2].tolist() == [MISSING_GRAY] * 3
    # instant 2: track 1 (gap) has no dot, its older trail is drawn; track 2 (just born) has a dot
    assert out[band + 20, 10 + 20 + 4].tolist() == images[0][20, 34].tolist()
    assert out[band + 28, 50 + 4].tolist() == _color(7).tolist()


def test_overlay_frame_max_tracks_draws_a_stable_subset():
    res = synthetic_result()
    images = [np.zeros((IMAGE_H, IMAGE_W, 3), np.uint8)] * 2
    keep = track_subset(res.point_ids, 1 / 3)
    out = overlay_frame(images, res, 3, 0, trail=1, max_tracks=1)
    band = out.shape[0] - IMAGE_H
    for p, track_id in enumerate(res.point_ids):
        u, v = 10 + 20 * p + 6, 12 + 8 * p
        drawn = out[band + v, u].tolist() == _color(track_id).tolist()
        assert drawn == bool(keep[p])
    assert keep.sum() < 3


def test_overlay_frame_bad_arguments():
    res = synthetic_result()
    with pytest.raises(ValueError, match="images"):
        overlay_frame(_images()[:1], res, 0)
    with pytest.raises(ValueError, match="instant"):
        overlay_frame(_images(), res, 5)
    with pytest.raises(ValueError, match="trail"):
        overlay_frame(_images(), res, 0, trail=0)

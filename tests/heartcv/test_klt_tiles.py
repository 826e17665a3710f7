"""Template tracking with per-point tiles (heartcv.klt: cut_tiles, track_tiles, flow_step, expected_ncc) against
exact answers: crops against array slicing, known sub-pixel shifts of a smooth random texture, the full-image
tracker (track_from_template, an independent code path), and the noise-only NCC against Monte Carlo."""

from __future__ import annotations

import numpy as np
import pytest

from heartcv.klt import (
    ACCEPTED,
    FORWARD_BACKWARD,
    LOST,
    PHOTOMETRIC,
    LKParams,
    TileSet,
    cut_tiles,
    expected_ncc,
    flow_step,
    template_patches,
    track_from_template,
    track_tiles,
)


def _texture(shape=(240, 320), seed=0, sigma=2.0):
    import cv2

    rng = np.random.default_rng(seed)
    t = cv2.GaussianBlur(rng.uniform(0, 255, shape).astype(np.float32), (0, 0), sigma)
    t = (t - t.min()) / (t.max() - t.min()) * 200 + 25
    return t


def _shift(img, dx, dy):
    """The image moved by (dx, dy) px (content at x appears at x + dx), bicubic, as uint8."""
    import cv2

    M = np.float32([[1, 0, dx], [0, 1, dy]])
    return np.clip(cv2.warpAffine(img, M, img.shape[::-1], flags=cv2.INTER_CUBIC,
                                  borderMode=cv2.BORDER_REFLECT), 0, 255).round().astype(np.uint8)


def _tiles(gray, uv, params, noise_var=1.0):
    tiles, origin = cut_tiles(gray, uv, params.tile_half)
    patch = template_patches(gray, uv, params)
    return TileSet(tiles, origin, np.asarray(uv, float), patch, expected_ncc(patch, noise_var))


def test_cut_tiles_are_the_slices_and_replicate_the_border():
    g = np.arange(30 * 40, dtype=np.int64).reshape(30, 40)
    tiles, origin = cut_tiles(g, np.array([[10.4, 12.6], [0.2, 0.0], [39.0, 29.0]]), 3)
    assert tiles.shape == (3, 7, 7)
    assert np.array_equal(origin[0], [7, 10]) and np.array_equal(tiles[0], g[10:17, 7:14])
    # outside the image: the nearest border pixel (cv2.BORDER_REPLICATE)
    ys = np.clip(np.arange(-3, 4), 0, 29)
    xs = np.clip(np.arange(-3, 4), 0, 39)
    assert np.array_equal(tiles[1], g[np.ix_(ys, xs)])
    ys = np.clip(np.arange(26, 33), 0, 29)
    xs = np.clip(np.arange(36, 43), 0, 39)
    assert np.array_equal(tiles[2], g[np.ix_(ys, xs)])


def test_expected_ncc_matches_monte_carlo():
    """Two noisy copies of one patch: the mean NCC over many noise draws is s / (s + n) to within the small-sample
    bias of the NCC (< 0.01 for 225 samples)."""
    from heartcv.features import ncc

    rng = np.random.default_rng(7)
    G = 225
    for signal_var, noise_var in ((100.0, 4.0), (20.0, 10.0), (5.0, 5.0)):
        signal = rng.standard_normal(G) * np.sqrt(signal_var)
        a = signal + rng.standard_normal((4000, G)) * np.sqrt(noise_var)
        b = signal + rng.standard_normal((4000, G)) * np.sqrt(noise_var)
        mc = float(np.mean(ncc(a, b)))
        exp = expected_ncc(a, noise_var)               # estimated from each noisy template patch
        assert abs(np.mean(exp) - mc) < 0.02, (signal_var, noise_var, np.mean(exp), mc)
        assert abs(signal_var / (signal_var + noise_var) - mc) < 0.02


@pytest.mark.parametrize("dx,dy", [(0.3, -0.45), (2.7, 1.2), (-5.4, 3.8)])
def test_track_tiles_recovers_a_known_shift(dx, dy):
    lk = LKParams(window=15, ncc_radius=5, fb_max_px=0.3, ncc_allowance=0.25)
    img = _texture()
    a = img.round().astype(np.uint8)
    b = _shift(img, dx, dy)
    rng = np.random.default_rng(1)
    uv = rng.uniform([60, 60], [260, 180], (40, 2))
    init = uv + np.round([dx, dy]) * 0.5                      # a rough starting guess (half the motion)
    got, why, fb, score = track_tiles(_tiles(a, uv, lk), b, init, lk)
    assert (why == ACCEPTED).all(), why
    # OpenCV's LK (fixed-point interpolation weights) leaves ~0.06 px on this 8-bit texture, with either tracker
    err = np.linalg.norm(got - (uv + [dx, dy]), axis=1)
    assert np.median(err) < 0.1 and err.max() < 0.15
    assert (fb < 0.1).all() and (score > 0.99).all()
    # the full-image tracker (another code path: cropped images, one template image) gives the same positions
    # (measured: within 0.001 px)
    ref, ok, _, _ = track_from_template(a, b, uv, template_patches(a, uv, lk), init, lk)
    assert ok.all() and np.abs(ref - got).max() < 0.005


def test_track_tiles_rejects_with_the_reason():
    lk = LKParams(window=15, ncc_radius=5, fb_max_px=0.3, ncc_allowance=0.25)
    img = _texture(seed=3)
    a = img.round().astype(np.uint8)
    b = _shift(img, 1.0, 0.0)
    uv = np.array([[100.0, 100.0], [200.0, 120.0], [150.0, 180.0]])
    b[90:111, 90:111] = 128                                   # a flat occluder over point 0
    b[110:131, 190:211] = _texture((21, 21), seed=99).astype(np.uint8)   # other texture over point 1
    got, why, _, _ = track_tiles(_tiles(a, uv, lk), b, uv, lk)
    assert why[2] == ACCEPTED and np.allclose(got[2], uv[2] + [1, 0], atol=0.05)
    assert why[0] in (LOST, FORWARD_BACKWARD, PHOTOMETRIC) and why[1] in (LOST, FORWARD_BACKWARD, PHOTOMETRIC)
    assert np.isnan(got[:2]).all()
    # a starting guess farther than the tile reaches is lost, not silently wrong
    far = uv + [[lk.tile_half + 30, 0]] * 3
    _, why, _, _ = track_tiles(_tiles(a, uv, lk), _shift(img, 0, 0), far, lk)
    assert (why != ACCEPTED).all()


def _track_tiles_all_back(templates, cur_gray, uv_init, params, ncc_floor=0.5):
    """Oracle: the tile tracker with the LK back run on every point (the whole mosaic), the gates applied after."""
    import cv2

    from heartcv.features import ncc, sample_patches
    from heartcv.klt import tile_mosaics
    from heartcv.matching import patch_offsets

    S = 2 * params.tile_half + 1
    A, B, pos, cur_origin, p0, p1 = tile_mosaics(templates, cur_gray, uv_init, params.tile_half)
    win = (params.window, params.window)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, params.iterations, params.epsilon_px)
    flags = cv2.OPTFLOW_USE_INITIAL_FLOW
    p1, st, _ = cv2.calcOpticalFlowPyrLK(A, B, p0, p1.copy(), winSize=win, maxLevel=params.refine_levels,
                                         criteria=crit, flags=flags)
    back, st2, _ = cv2.calcOpticalFlowPyrLK(B, A, p1, p0.copy(), winSize=win, maxLevel=params.refine_levels,
                                            criteria=crit, flags=flags)
    local = p1.reshape(-1, 2).astype(float) - pos
    uv = local + cur_origin
    fb = np.linalg.norm(back.reshape(-1, 2) - p0.reshape(-1, 2), axis=1)
    m = params.window / 2
    inside = (local >= m).all(axis=1) & (local <= S - 1 - m).all(axis=1)
    score = np.nan_to_num(ncc(templates.patch, sample_patches(cur_gray.astype(np.float32), uv,
                                                              patch_offsets(params.ncc_radius))), nan=-1.0)
    gate = np.maximum(ncc_floor, templates.expected - params.ncc_allowance)
    lost = (st.ravel() != 1) | ~inside
    photo = ~lost & (score < gate)
    fbad = ~lost & ~photo & ((st2.ravel() != 1) | ~(fb <= params.fb_max_px))
    return uv, lost, photo, fbad


def test_track_tiles_gate_order_changes_no_decision():
    """The LK back runs only on the points that passed ``lost`` and ``photometric``: on a scene with occluders,
    foreign texture, a flat patch and far starting guesses, every point gets the reason and position of the oracle
    that runs it on all points, and each gate removes some point."""
    rng = np.random.default_rng(11)
    lk = LKParams(window=11, ncc_radius=4, fb_max_px=0.5, ncc_allowance=0.25)
    img = _texture(seed=7)
    a = img.round().astype(np.uint8)
    b = _shift(img, 0.7, -0.4)
    uv = np.stack([rng.uniform(40, 280, 120), rng.uniform(40, 200, 120)], axis=1)
    for k in range(0, 120, 6):                       # flat occluders and foreign texture over some points
        x, y = np.rint(uv[k]).astype(int)
        b[y - 8:y + 9, x - 8:x + 9] = 128 if k % 12 else _texture((17, 17), seed=k).astype(np.uint8)
    init = uv + [0.7, -0.4]
    init[1::7] += rng.uniform(-6, 6, (len(init[1::7]), 2))        # poor starting guesses
    init[3::11] += 60.0                                           # beyond the tile
    tiles = _tiles(a, uv, lk, noise_var=4.0)
    got, why, fb, _ = track_tiles(tiles, b, init, lk)
    uv_o, lost, photo, fbad = _track_tiles_all_back(tiles, b, init, lk)
    assert np.array_equal(why == LOST, lost) and np.array_equal(why == PHOTOMETRIC, photo)
    assert np.array_equal(why == FORWARD_BACKWARD, fbad)
    ok = why == ACCEPTED
    assert np.array_equal(got[ok], uv_o[ok]) and np.isnan(got[~ok]).all()
    assert lost.any() and photo.any() and fbad.any() and ok.sum() >= 60
    assert np.isnan(fb[lost | photo]).all() and np.isfinite(fb[ok]).all()


def test_noise_adaptive_gate_follows_the_expected_ncc():
    """A fixed shift with a photometric change: accepted while NCC >= expected - allowance, rejected with a smaller
    allowance; the fixed gate (allowance None) uses min_ncc."""
    img = _texture(seed=5)
    a = img.round().astype(np.uint8)
    rng = np.random.default_rng(4)
    b = np.clip(_shift(img, 0.5, 0.5) + rng.normal(0, 12, img.shape), 0, 255).round().astype(np.uint8)
    uv = np.array([[80.0, 80.0], [160.0, 100.0], [240.0, 160.0]])
    loose = LKParams(window=15, ncc_radius=5, fb_max_px=5.0, ncc_allowance=0.5)
    _, why, _, score = track_tiles(_tiles(a, uv, loose, noise_var=1.0), b, uv, loose)
    tiles = _tiles(a, uv, loose, noise_var=1.0)
    assert (why == ACCEPTED).all() and (score >= tiles.expected - 0.5).all()
    strict = LKParams(window=15, ncc_radius=5, fb_max_px=5.0, ncc_allowance=0.5 * float(np.min(1 - score)))
    _, why, _, _ = track_tiles(_tiles(a, uv, strict, noise_var=1.0), b, uv, strict)
    assert (why == PHOTOMETRIC).all()
    fixed = LKParams(window=15, ncc_radius=5, fb_max_px=5.0, min_ncc=float(score.max()) + 1e-3)
    _, why, _, _ = track_tiles(_tiles(a, uv, fixed), b, uv, fixed)
    assert (why == PHOTOMETRIC).all()


def test_flow_step_recovers_a_large_shift():
    lk = LKParams(window=15, levels=3)
    img = _texture(seed=2)
    a = img.round().astype(np.uint8)
    b = _shift(img, 11.3, -7.6)
    uv = np.random.default_rng(2).uniform([60, 60], [240, 160], (30, 2))
    got = flow_step(a, b, uv, lk)
    assert np.abs(got - (uv + [11.3, -7.6])).max() < 0.1

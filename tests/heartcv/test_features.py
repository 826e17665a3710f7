"""heartcv.features: NCC against its closed-form invariances and np.corrcoef, bilinear sampling against a hand
implementation, Shi–Tomasi corners at known blob centres (mask, min_distance, exclude, max_points, spread), and the
region of interest on a moving textured disk beside a larger static distractor."""

import numpy as np
import pytest

from heartcv.features import detect_corners, ncc, region_of_interest, sample_at, sample_patches


# -- ncc ------------------------------------------------------------------------------------------------------
def test_ncc_invariances_and_flat_patches():
    rng = np.random.default_rng(1)
    a = rng.uniform(0, 255, (6, 49)).astype(np.float32)
    assert np.allclose(ncc(a, a), 1.0, atol=1e-6)
    assert np.allclose(ncc(a, 2.5 * a + 17.0), 1.0, atol=1e-6)         # gain and bias
    assert np.allclose(ncc(a, 300.0 - 0.5 * a), -1.0, atol=1e-6)       # negative (with any gain and bias)
    flat = np.full_like(a, 128.0)
    assert np.array_equal(ncc(a, flat), np.zeros(6, np.float32))
    assert np.array_equal(ncc(flat, flat), np.zeros(6, np.float32))
    b = a.copy()
    b[2, 10] = np.nan
    out = ncc(a, b)
    assert np.isnan(out[2]) and np.isfinite(np.delete(out, 2)).all()


def test_ncc_equals_pearson_correlation_along_any_axis():
    rng = np.random.default_rng(2)
    a = rng.normal(size=(5, 81))
    b = 0.6 * a + rng.normal(size=(5, 81))
    want = np.array([np.corrcoef(a[i], b[i])[0, 1] for i in range(5)])
    assert np.allclose(ncc(a, b), want, atol=1e-6)
    assert np.allclose(ncc(a.T, b.T, axis=0), want, atol=1e-6)


# -- sampling ---------------------------------------------------------------------------------------------------
def _bilinear(img, p):
    """Bilinear interpolation by hand (pixel centres at integers), for 0 <= x < W - 1, 0 <= y < H - 1."""
    x, y = p[:, 0], p[:, 1]
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    I = img.astype(float)
    top = (1 - fx) * I[y0, x0] + fx * I[y0, x0 + 1]
    bottom = (1 - fx) * I[y0 + 1, x0] + fx * I[y0 + 1, x0 + 1]
    return (1 - fy) * top + fy * bottom


def test_sample_at_is_exact_bilinear_interpolation():
    rng = np.random.default_rng(3)
    img = rng.uniform(0, 255, (20, 30)).astype(np.float32)
    pts = rng.uniform([0, 0], [29, 19], (2000, 2))
    got = sample_at(img, pts)
    assert got.dtype == np.float32 and got.shape == (2000,)
    # float32 coordinates and weights: |error| <= 255 * a few float32 ulps of the coordinate
    assert np.abs(got - _bilinear(img, pts)).max() < 2e-3
    assert np.allclose(sample_at(img, [[3.0, 4.0], [7.0, 11.0]]), img[[4, 11], [3, 7]])   # at pixel centres
    # batched shapes are kept
    assert sample_at(img, pts.reshape(4, 25, 20, 2)).shape == (4, 25, 20)
    # a sample needing a pixel outside the image is NaN
    outside = np.array([[-0.3, 5.0], [5.0, -0.01], [29.2, 5.0], [5.0, 19.5], [-40.0, -40.0], [100.0, 5.0]])
    assert np.isnan(sample_at(img, outside)).all()


def test_sample_patches_offsets_the_centres():
    rng = np.random.default_rng(4)
    img = rng.uniform(0, 255, (40, 50)).astype(np.float32)
    uv = rng.uniform(5, 30, (7, 2))
    offs = np.array([[0.0, 0.0], [1.5, -0.25], [-2.0, 3.0]])
    got = sample_patches(img, uv, offs)
    assert got.shape == (7, 3)
    want = _bilinear(img, (uv[:, None, :] + offs[None]).reshape(-1, 2)).reshape(7, 3)
    assert np.abs(got - want).max() < 2e-3


# -- corners ----------------------------------------------------------------------------------------------------
BLOBS = [(20, 20), (60, 25), (100, 30), (140, 22), (30, 70), (75, 80), (120, 90)]


def _blob_image(blobs=BLOBS, shape=(120, 160)):
    """Uniform 5x5 bright squares on a dark background: the minimum-eigenvalue response (7x7 block) has its unique
    maximum at each square's centre pixel; later blobs are brighter, so they are stronger."""
    img = np.full(shape, 20, np.uint8)
    for i, (x, y) in enumerate(blobs):
        img[y - 2:y + 3, x - 2:x + 3] = 150 + 10 * i
    return img


def test_detect_corners_finds_blob_centres_strongest_first():
    uv, resp = detect_corners(_blob_image(), max_points=100, min_distance=10)
    assert uv.dtype == np.float64 and uv.shape == (len(BLOBS), 2)
    assert np.array_equal(uv, np.array(BLOBS[::-1], float))           # exact centres, brightest first
    assert np.all(np.diff(resp) < 0)


def test_detect_corners_mask_min_distance_exclude_and_max_points():
    img = _blob_image()
    mask = np.zeros(img.shape, bool)
    mask[:, :90] = True
    uv, _ = detect_corners(img, mask, max_points=100, min_distance=10)
    assert {tuple(p) for p in uv} == {b for b in BLOBS if b[0] < 90}
    # two blobs 8 px apart: min_distance 10 keeps only the stronger (later) one
    pair = [(40, 40), (48, 40)]
    uv, _ = detect_corners(_blob_image(pair), max_points=100, min_distance=10)
    assert np.array_equal(uv, [[48.0, 40.0]])
    uv, _ = detect_corners(_blob_image(pair), max_points=1000, min_distance=5)     # cells of 5 px: both kept
    assert {tuple(p) for p in uv} == set(pair)
    # exclude: nothing within min_distance of an existing point
    uv, _ = detect_corners(img, max_points=100, min_distance=10, exclude=np.array([[62.0, 28.0], [119.0, 85.0]]))
    assert {tuple(p) for p in uv} == set(BLOBS) - {(60, 25), (120, 90)}
    # max_points: the strongest ones
    uv, _ = detect_corners(img, max_points=3, min_distance=10)
    assert len(uv) <= 3 and {tuple(p) for p in uv} <= set(BLOBS[-4:])
    with pytest.raises(ValueError, match="shape"):
        detect_corners(img, mask[:10])
    assert detect_corners(np.zeros((50, 50), np.uint8))[0].shape == (0, 2)


def test_detect_corners_spread_over_a_uniform_texture():
    import cv2

    rng = np.random.default_rng(5)
    z = cv2.GaussianBlur(rng.normal(size=(200, 240)).astype(np.float32), (0, 0), 1.5)
    img = np.clip(128 + 40 * z / z.std(), 0, 255).astype(np.uint8)
    uv, _ = detect_corners(img, max_points=40, min_distance=8)
    assert 30 <= len(uv) <= 40
    d = np.linalg.norm(uv[:, None] - uv[None], axis=2) + np.eye(len(uv)) * 1e9
    assert d.min() >= 8
    quadrant = (uv[:, 0] >= 120).astype(int) + 2 * (uv[:, 1] >= 100)
    assert np.bincount(quadrant, minlength=4).min() >= 5          # 40 / 4 = 10 expected in each


# -- region of interest --------------------------------------------------------------------------------------------
def _roi_frames(n=3, radius=60):
    """A textured disk moving by (2, 1) px per frame and a larger static textured square, on a dark noisy
    background; returns the frames and the disk of frame 0."""
    import cv2

    rng = np.random.default_rng(6)
    H, W = 300, 400
    tex = cv2.GaussianBlur(rng.normal(size=(H + 40, W + 40)).astype(np.float32), (0, 0), 1.5)
    tex /= tex.std()
    vv, uu = np.mgrid[0:H, 0:W]
    square = (uu >= 10) & (uu < 120) & (vv >= 10) & (vv < 120)         # 12100 px > the disk's 11310
    frames = []
    for k in range(n):
        img = 20 + rng.normal(0, 2, (H, W))
        disk = (uu - 250 - 2 * k) ** 2 + (vv - 150 - k) ** 2 <= radius ** 2
        moving = 140 + 40 * tex[20 - k:20 - k + H, 20 - 2 * k:20 - 2 * k + W]     # content moves with the disk
        img[disk] = moving[disk]
        img[square] = (140 + 40 * tex[20:20 + H, 20:20 + W])[square]
        frames.append(np.clip(np.rint(img), 0, 255).astype(np.uint8))
    disk0 = (uu - 250) ** 2 + (vv - 150) ** 2 <= radius ** 2
    return frames, disk0, (uu, vv)


def _iou(a, b):
    return (a & b).sum() / (a | b).sum()


def test_region_of_interest_finds_the_moving_textured_disk():
    frames, disk, (uu, vv) = _roi_frames()
    mask, info = region_of_interest(frames, margin=0)
    assert info["moving"] and info["area_px"] == mask.sum()
    assert _iou(mask, disk) > 0.9
    # the default margin erodes it by 12 px
    mask, _ = region_of_interest(frames)
    assert _iou(mask, (uu - 250) ** 2 + (vv - 150) ** 2 <= 48 ** 2) > 0.9
    # from one frame there is no motion: the larger static square wins
    mask, info = region_of_interest(frames[:1], margin=0)
    assert not info["moving"] and _iou(mask, disk) == 0.0


def test_region_of_interest_rejects_blank_and_bad_input():
    rng = np.random.default_rng(7)
    blank = [np.clip(np.rint(30 + rng.normal(0, 2, (200, 300))), 0, 255).astype(np.uint8) for _ in range(3)]
    with pytest.raises(ValueError, match="region of interest"):
        region_of_interest(blank)
    with pytest.raises(ValueError):
        region_of_interest([np.zeros((10, 10, 3), np.uint8)])
    frames, _, _ = _roi_frames()
    with pytest.raises(ValueError, match="at least"):
        region_of_interest(frames, min_area=20000)

"""Image-ops backends (heartcv.backend): the kornia backend against the OpenCV one, op by op on random and real
images, then through corner detection and the plane-sweep matcher on a small rendered 3-camera scene.

Tolerances (float32 throughout; the kornia ops reproduce OpenCV's border rules, so they hold up to the border):
pyramid 1e-4 grey levels; samples 1e-3 grey levels (NaN pattern identical); NCC 1e-5 against the centred
float64 formula (:func:`heartcv.features.ncc`); corner response 1e-3 relative (to 1e-6 of the image's maximum);
matched positions 1e-3 px.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from heartcv.backend import OpenCVBackend, get_backend
from heartcv.camera import Camera
from heartcv.features import detect_corners, ncc, sample_at
from heartcv.matching import match_points, patch_offsets
from tests.conftest import SHARED_DATA
from tests.heartcv.test_calibration import paper_rig

F7 = SHARED_DATA / "hamlyn_heart_phantom_f7"


def test_get_backend_names():
    assert get_backend("opencv").name == "opencv"
    with pytest.raises(ValueError, match="opencv"):
        get_backend("nope")


# -- fixtures -------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module", params=["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
def kb(request):
    """The kornia backend on the CPU, with one torch thread while this module runs: on a busy 2-core machine
    torch's intra-op threads wait on each other (9x slower matching), like BLAS's (tests/conftest.py); and on a
    CUDA device (marker ``cuda``: deselected by default, ``make test-gpu`` runs them where a GPU is present)."""
    torch = pytest.importorskip("torch")
    pytest.importorskip("kornia")
    if request.param == "cuda" and not torch.cuda.is_available():
        pytest.skip("no CUDA device (torch.cuda.is_available() is False)")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield get_backend("kornia", request.param)
    torch.set_num_threads(threads)


def _real(name):
    cv2 = pytest.importorskip("cv2")
    path = F7 / name
    if not path.exists():
        pytest.skip(f"{path} missing")
    return cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)


def _smooth_random(rng, shape, sigma=1.5):
    """A random texture with gradients up to ~100 grey levels per pixel (float32, 0..255)."""
    import cv2

    img = cv2.GaussianBlur(rng.uniform(0, 255, shape).astype(np.float32), (0, 0), sigma)
    return ((img - img.min()) / np.ptp(img) * 255).astype(np.float32)


IMAGES = {
    "random_odd": lambda rng: rng.uniform(0, 255, (301, 401)).astype(np.float32),
    "random_even": lambda rng: rng.uniform(0, 255, (300, 400)).astype(np.float32),
    "smooth": lambda rng: _smooth_random(rng, (241, 322)),
    "f7_left": lambda rng: _real("f7_dynamic_deint_L_0100.png").astype(np.float32),
    "f7_right": lambda rng: _real("f7_dynamic_deint_R_0100.png").astype(np.float32),
}


@pytest.fixture(params=sorted(IMAGES))
def image(request, rng):
    return IMAGES[request.param](rng)


# -- op by op -------------------------------------------------------------------------------------------------------
def test_kornia_backend_identity(kb):
    assert kb.name == "kornia" and kb.device.type in ("cpu", "cuda")
    assert get_backend("kornia").device.type in ("cpu", "cuda")
    from heartcv.tracker.files import InputError

    with pytest.raises(InputError, match="--device: .nope. is not a torch device"):
        get_backend("kornia", "nope")


def test_pyramid(kb, image):
    ref = OpenCVBackend().pyramid(image, 3)
    out = kb.pyramid(image, 3)
    assert len(out) == 4
    for a, b in zip(ref, out):
        b = b.cpu().numpy()
        assert b.shape == a.shape and b.dtype == np.float32           # ((W + 1) // 2, (H + 1) // 2) per level
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-4)


def test_sample(kb, image, rng):
    H, W = image.shape
    pts = rng.uniform([-3, -3], [W + 2, H + 2], (50_000, 2))
    edges = np.array([[0, 0], [W - 1, 5], [5, H - 1], [W - 1 - 1e-3, H - 1 - 1e-3], [-1e-6, 5], [5, -1e-6],
                      [W - 2, H - 2], [np.nan, 3]])
    pts = np.concatenate([pts, edges])
    ref = sample_at(image, pts)
    out = kb.sample(image, pts)
    assert out.dtype == np.float32 and out.shape == ref.shape
    np.testing.assert_array_equal(np.isnan(out), np.isnan(ref))        # NaN outside [0, W - 1) x [0, H - 1)
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-3)
    # shapes pass through, and a tensor pyramid level is accepted
    grid = pts[:24].reshape(2, 3, 4, 2)
    np.testing.assert_allclose(kb.sample(kb.pyramid(image, 0)[0], grid), ref[:24].reshape(2, 3, 4), atol=1e-3)


def test_sample_table_cache(kb, rng):
    """Levels are sampled through a cached neighbour table: an in-place change of the level invalidates it."""
    level = kb.pyramid(_smooth_random(rng, (60, 80)), 0)[0]
    pts = rng.uniform(0, 59, (100, 2))
    first = kb.sample(level, pts)
    level.mul_(2.0)
    np.testing.assert_allclose(kb.sample(level, pts), 2 * first, rtol=1e-6)
    n = len(kb._tables)
    del level
    assert len(kb._tables) == n - 1


def _patch_problem(image, rng, n=48, J=40, radius=4):
    """Reference patches (n, 1, G) and many warped candidate grids (n, J, G, 2), some partly outside."""
    H, W = image.shape
    offs = patch_offsets(radius)
    c = rng.uniform([radius, radius], [W - 1 - radius, H - 1 - radius], (n, 1, 1, 2))
    ref = sample_at(image, c[:, 0] + offs)[:, None]                               # (n, 1, G)
    A = np.eye(2) + rng.normal(0, 0.15, (n, J, 1, 2, 2))
    grid = c + rng.normal(0, 4, (n, J, 1, 2)) + (A @ offs[:, :, None])[..., 0]  # (n, J, G, 2)
    return ref.astype(np.float32), grid.astype(np.float32)


def test_patch_ncc(kb, image, rng):
    ref, grid = _patch_problem(image, rng)
    b = sample_at(image, grid)
    exact = ncc(ref.astype(np.float64), b.astype(np.float64))                    # centred, float64
    exact = np.where(np.isnan(b).any(axis=-1), np.nan, exact)
    out = kb.patch_ncc(image, ref, grid)
    cv = OpenCVBackend().patch_ncc(image, ref, grid)
    assert out.dtype == np.float32 and out.shape == cv.shape == (48, 40)
    assert np.isnan(out).any() and np.isfinite(out).any()
    np.testing.assert_array_equal(np.isnan(out), np.isnan(cv))
    np.testing.assert_allclose(out, exact, rtol=0, atol=1e-5)
    # both backends centre the patches before the products (float32 without cancellation)
    np.testing.assert_allclose(out, cv, rtol=0, atol=1e-5)


def test_patch_ncc_rules_and_chunks(rng):
    pytest.importorskip("kornia")
    from heartcv.backends.kornia_backend import KorniaBackend

    image = _smooth_random(rng, (120, 160))
    ref, grid = _patch_problem(image, rng, n=7, J=9, radius=3)
    small = KorniaBackend("cpu", chunk=50)                      # blocks smaller than one row of patches
    np.testing.assert_allclose(small.patch_ncc(image, ref, grid), KorniaBackend("cpu").patch_ncc(image, ref, grid),
                               rtol=0, atol=1e-6)
    # flat reference patch: 0 (NaN where the candidate is partly outside, as OpenCVBackend)
    flat = np.full_like(ref, 7.0)
    out = small.patch_ncc(image, flat, grid)
    cv = OpenCVBackend().patch_ncc(image, flat, grid)
    np.testing.assert_array_equal(out, cv)
    # general broadcasting (features.ncc's rule: flat wins over NaN) and a single patch
    b = sample_at(image, grid)
    np.testing.assert_allclose(small.patch_ncc(image, ref[:, 0, None, :].repeat(9, 1), grid),
                               ncc(ref, b), rtol=0, atol=1e-5, equal_nan=True)
    np.testing.assert_allclose(small.patch_ncc(image, ref[0, 0], grid[0, 0]), ncc(ref[0, 0], b[0, 0]), atol=1e-5)


@pytest.mark.parametrize("block_size", [3, 4, 7])
def test_corner_response(kb, image, block_size):
    import cv2

    for gray in (image, np.clip(np.rint(image), 0, 255).astype(np.uint8)):   # uint8: cv2 scales by 1/255^2
        ref = cv2.cornerMinEigenVal(gray, block_size, ksize=3)
        out = kb.corner_response(gray, block_size)
        assert out.dtype == np.float32 and out.shape == ref.shape
        np.testing.assert_allclose(out, ref, rtol=1e-3, atol=1e-6 * float(ref.max()))


def test_detect_corners_same(kb):
    gray = _real("f7_dynamic_deint_L_0100.png")
    mask = _real("f7_dynamic_deint_mask_0100.png") > 0
    for m, quality, least in ((mask, 0.005, 40), (None, 0.001, 200)):      # the phantom; the whole frame
        uv_cv, r_cv = detect_corners(gray, m, max_points=300, min_distance=6, quality=quality)
        uv_k, r_k = detect_corners(gray, m, max_points=300, min_distance=6, quality=quality, backend=kb)
        assert len(uv_cv) >= least
        np.testing.assert_array_equal(uv_k, uv_cv)
        np.testing.assert_allclose(r_k, r_cv, rtol=1e-3)


# -- the matcher on a rendered scene --------------------------------------------------------------------------------
def _small_rig(scale=0.25):
    """The paper rig (test_calibration.paper_rig) at ``scale`` x the resolution (480 x 270): same field of view."""
    cams, cam0_from_world = paper_rig()
    out = []
    for c in cams:
        K = np.array(c.K, float)
        K[:2, :2] *= scale
        K[:2, 2] = (K[:2, 2] + 0.5) * scale - 0.5
        out.append(Camera(c.name, round(c.width * scale), round(c.height * scale), K, c.dist, c.cam_from_rig))
    return out, cam0_from_world


def _render_sphere(cams, cam0_from_world, rng, radius=0.2, n_waves=60):
    """Gray images (float32) of a sphere (centre on the world z axis, front at the world origin) textured with a
    smooth random pattern of plane waves (wavelengths 2-6 mm) in world x, y."""
    centre = (cam0_from_world @ [0.0, 0.0, radius, 1.0])[:3]
    k = rng.normal(size=(n_waves, 2))
    k *= (2 * np.pi / rng.uniform(0.002, 0.006, n_waves) / np.linalg.norm(k, axis=1))[:, None]
    phase = rng.uniform(0, 2 * np.pi, n_waves)
    world_from_cam0 = np.linalg.inv(cam0_from_world)
    images = []
    for cam in cams:
        v, u = np.mgrid[0:cam.height, 0:cam.width]
        o, d = cam.rays(np.stack([u.ravel(), v.ravel()], axis=1).astype(float))
        oc = o - centre
        b = (oc * d).sum(axis=1)
        disc = b * b - ((oc * oc).sum(axis=1) - radius ** 2)
        t = -b - np.sqrt(np.maximum(disc, 0.0))
        X = o + t[:, None] * d
        Xw = X @ world_from_cam0[:3, :3].T + world_from_cam0[:3, 3]
        tex = np.sin(Xw[:, :2] @ k.T + phase).sum(axis=1) / np.sqrt(n_waves / 2)
        img = np.where(disc > 0, 128 + 45 * tex, 20.0)
        images.append(np.clip(np.rint(img), 0, 255).astype(np.uint8).reshape(cam.height, cam.width))
    return images, centre


@pytest.fixture(scope="module")
def sphere_scene():
    cams, cam0_from_world = _small_rig()
    images, centre = _render_sphere(cams, cam0_from_world, np.random.default_rng(7))
    return cams, images, centre


def test_match_points_same(kb, sphere_scene):
    cams, images, centre = sphere_scene
    H, W = images[0].shape
    mask = np.zeros((H, W), bool)
    mask[60:H - 60, 100:W - 100] = True
    uv, _ = detect_corners(images[0], mask, max_points=40, min_distance=12)
    assert len(uv) >= 20
    imgs = [im.astype(np.float32) for im in images]
    kw = dict(coarse_level=1, max_seeds=16)
    t0 = time.perf_counter()
    m_cv = match_points(cams, imgs, 0, uv, **kw)
    t1 = time.perf_counter()
    m_k = match_points(cams, imgs, 0, uv, backend=kb, **kw)
    t2 = time.perf_counter()
    print(f"match_points on {len(uv)} corners: opencv {t1 - t0:.2f} s, kornia ({kb.device}) {t2 - t1:.2f} s")
    assert m_cv.ok.sum() >= 0.8 * len(uv)
    np.testing.assert_array_equal(m_k.ok, m_cv.ok)
    np.testing.assert_allclose(m_k.uv, m_cv.uv, rtol=0, atol=1e-3, equal_nan=True)
    np.testing.assert_allclose(m_k.score, m_cv.score, rtol=0, atol=1e-5, equal_nan=True)
    # and the matches are right: the matched points lie on the sphere (0.1 mm ~ 0.3 px of depth here)
    r = np.linalg.norm(m_k.points[m_k.ok] - centre, axis=1)
    np.testing.assert_allclose(r, 0.2, atol=1e-4)

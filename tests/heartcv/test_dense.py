"""heartcv.dense: the dense stereo measurement (SGBM disparities, DIS-flow tracks, closed-form triangulation).

Synthetic scenes: a tilted plane with a smoothed random texture, rendered exactly (ray-plane intersection, bilinear
texture sampling, 1 grey level of noise) into the cameras of a rig, translating by a known 3-D step per frame.
Every measured point is compared with the intersection of its reference camera ray with the true plane (its depth
error), with its expected position on the plane's texture (the drift of its track), and its error along the ray
with the covariance along the ray (normalised errors). Real data: the Hamlyn in-vivo heart (rectified, 360x288).
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from heartcv.camera import Camera, Rig, pose_matrix
from heartcv.dense import DenseOptions, DenseTracker, StereoPair, dense_sequence, refine_disparity
from heartcv.measure import MeasureFailed
from heartcv.rig_formats import rectified_rig
from heartcv.triangulation import triangulate
from tests.conftest import SHARED_DATA

INVIVO = SHARED_DATA / "hamlyn_invivo_heart"

W, H, F, B = 360, 288, 390.0, 0.0055           # the in-vivo rig's working assumption (its README)
TEXEL = 0.03e-3                                 # texture sample (m): ~half an image pixel at 25 mm
NORMAL = (0.25, -0.15, -1.0)                    # plane normal (towards the cameras)
P0 = np.array([0.0, 0.0, 0.025])                # plane point (m) at frame 0
STEP = np.array([0.06e-3, 0.03e-3, 0.1e-3])     # translation per frame (m): ~0.9 px, 0.3 % of the depth


# -- the synthetic plane ---------------------------------------------------------------------------------------------
def _basis():
    n = np.asarray(NORMAL, float)
    n /= np.linalg.norm(n)
    e1 = np.cross([0.0, 1.0, 0.0], n)
    e1 /= np.linalg.norm(e1)
    return n, e1, np.cross(n, e1)


def _texture(n=1400, seed=1):
    import cv2

    rng = np.random.default_rng(seed)
    fine = cv2.GaussianBlur(rng.standard_normal((n, n)).astype(np.float32), (0, 0), 2.0)
    coarse = cv2.GaussianBlur(rng.standard_normal((n, n)).astype(np.float32), (0, 0), 8.0)
    t = fine / fine.std() + 0.7 * coarse / coarse.std()
    return (128 + 35 * t / t.std()).astype(np.float32)


class Plane:
    """Renders the translating textured plane into the cameras of a rig (rays cached per camera)."""

    def __init__(self):
        self.tex = _texture()
        self.n, self.e1, self.e2 = _basis()
        self._rays = {}

    def origin(self, k):
        """The plane point of frame(s) k (..., 3)."""
        return P0 + np.asarray(k, float)[..., None] * STEP

    def _cam_rays(self, cam):
        if cam.name not in self._rays:
            v, u = np.mgrid[0:cam.height, 0:cam.width].astype(float)
            self._rays[cam.name] = cam.rays(np.stack([u.ravel(), v.ravel()], axis=1))
        return self._rays[cam.name]

    def _hit(self, o, d, k):
        t = ((self.origin(k) - o) @ self.n) / (d @ self.n)
        return o + t[:, None] * d

    def render(self, cam, k, rng, noise=1.0):
        import cv2

        X = self._hit(*self._cam_rays(cam), k)
        st = self.texture_coords(X, k) / TEXEL + np.array(self.tex.shape[::-1]) / 2
        m = st.reshape(cam.height, cam.width, 2).astype(np.float32)
        img = cv2.remap(self.tex, m[..., 0], m[..., 1], cv2.INTER_LINEAR)
        img = img + noise * rng.standard_normal(img.shape)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)

    def texture_coords(self, X, k):
        """Coordinates (m) of points (N, 3) on the plane in its own (moving) frame at frame(s) k."""
        D = X - self.origin(k)
        return np.stack([D @ self.e1, D @ self.e2], axis=-1)

    def on_ray(self, cam, uv, k):
        """The true point on the ray of pixels uv of camera cam."""
        return self._hit(*cam.rays(uv), k)

    def frames(self, rig, K, noise=1.0, seed=7):
        rng = np.random.default_rng(seed)
        return [(k, [self.render(c, k, rng, noise) for c in rig.cameras], []) for k in range(K)]


@pytest.fixture(scope="module")
def plane():
    return Plane()


def _errors(plane, res, cam, K):
    """Relative depth errors, normalised errors along the ray and track drift (px at 25 mm) of all seen points."""
    rel, nz, drift = [], [], []
    for k in range(K):
        sk = res.seen[k]
        X = res.positions[k, sk]
        Xt = plane.on_ray(cam, cam.project(X), k)
        ray = Xt - cam.centre
        dist = np.linalg.norm(ray, axis=1)
        ray /= dist[:, None]
        e = ((X - Xt) * ray).sum(axis=1)
        var = np.einsum("ni,nij,nj->n", ray, res.covariances[k, sk], ray)
        rel.append(np.abs(e) / dist)
        nz.append(e / np.sqrt(var))
        born = plane.texture_coords(res.reference[sk], res.birth_frame[sk])      # where the track started
        drift.append(np.linalg.norm(plane.texture_coords(X, k) - born, axis=1) / (P0[2] / F))
    return np.concatenate(rel), np.concatenate(nz), np.concatenate(drift)


def _spans(res):
    """Frames from first to last seen of every track."""
    S = res.seen
    K = len(S)
    first = np.argmax(S, axis=0)
    last = K - 1 - np.argmax(S[::-1], axis=0)
    return np.where(S.any(axis=0), last - first + 1, 0)


# -- options ---------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kw", [dict(grid_step_px=0), dict(disparity_range_px=(10, 5)),
                                dict(disparity_range_px=(-1, 5)), dict(depth_range_m=(0.03, 0.02)),
                                dict(block_size=4), dict(block_size=13), dict(grid_step_px=2.5),
                                dict(sgbm_mode="bm"), dict(lr_tolerance_px=0), dict(fb_tolerance_px=-1),
                                dict(flow_preset="slow"), dict(reseed_fraction=0), dict(reseed_fraction=1.5),
                                dict(max_gap_frames=-1), dict(max_tracks=0), dict(saturation_level=300),
                                dict(pixel_sigma=0.0), dict(min_pixel_sigma=0), dict(ref_camera=-1),
                                dict(range_margin=2.0), dict(flow_finest_scale=-1)])
def test_options_rejected(kw):
    with pytest.raises(ValueError):
        DenseOptions(**kw)


def test_tracker_rejects_bad_setup():
    rig = rectified_rig(W, H, F, B)
    with pytest.raises(ValueError, match="ref_camera"):
        DenseTracker(rig, DenseOptions(ref_camera=2))
    with pytest.raises(ValueError, match="roi"):
        DenseTracker(rig, roi=np.ones((H, W + 1), bool))
    a, b = rig.cameras
    with pytest.raises(ValueError, match="vertical"):
        StereoPair.from_cameras([a, b.with_pose(pose_matrix(np.eye(3), [0.0, -B, 0.0]))])
    with pytest.raises(ValueError, match="coincident"):
        StereoPair.from_cameras([a, Camera("c", W, H, a.K)])


@pytest.mark.parametrize("kw, expected", [(dict(depth_range_m=(0.02, 0.035)), (61, 108)),
                                          (dict(disparity_range_px=(50, 100)), (50, 113))])
def test_disparity_range_from_options(plane, kw, expected):
    """f B / z: 2.145 / 0.035 = 61.3 -> 61, 2.145 / 0.02 = 107.3 -> 108; the count rounded up to 16."""
    rig = rectified_rig(W, H, F, B)
    tracker = DenseTracker(rig, DenseOptions(**kw))
    tracker.step(0, plane.frames(rig, 1)[0][1])
    assert tracker.disparity_range == expected


def test_disparity_range_measured_on_the_first_pair(plane):
    """The plane's disparities (76..92 px) lie inside the measured range."""
    rig = rectified_rig(W, H, F, B)
    tracker = DenseTracker(rig)
    n = tracker.step(0, plane.frames(rig, 1)[0][1])
    d = F * B / tracker.result().positions[0, :n, 2]
    lo, hi = tracker.disparity_range
    assert lo < d.min() and d.max() < hi and hi - lo < 96


def test_disparity_beyond_the_range_is_not_clamped_to_its_end(plane, caplog):
    """A plane (76..92 px) nearer than the range searched (50..65 px): SGBM clamps its matches to the range's end,
    65 px (a depth 15-30 % too far); none may be measured there, and a warning says why."""
    rig = rectified_rig(W, H, F, B)
    with caplog.at_level("WARNING", logger="heartcv.dense"):
        try:
            run = dense_sequence(plane.frames(rig, 2), rig, DenseOptions(disparity_range_px=(50, 60)))
        except MeasureFailed:
            run = None
    if run is not None:
        d = F * B / run.result.positions[..., 2]
        assert not (np.abs(d[np.isfinite(d)] - 65) < 0.5).any()
    assert "end of the disparity range" in caplog.text


# -- the rectified pair and the closed form ---------------------------------------------------------------------------
def test_rectified_rig_is_the_identity():
    rig = rectified_rig(W, H, F, B)
    p = StereoPair.from_cameras(rig, 0)
    assert p.identity and p.maps is None and p.other == 1
    assert (p.f, p.cx, p.cy) == (F, (W - 1) / 2, (H - 1) / 2)
    assert p.baseline == pytest.approx(B, rel=1e-12)
    np.testing.assert_array_equal(p.rig_from_rect, np.eye(4))
    q = StereoPair.from_cameras(rig, 1)                          # the partner is to the left
    assert q.identity and q.other == 0 and q.baseline == pytest.approx(-B, rel=1e-12)
    a, b = rig.cameras
    d = StereoPair.from_cameras([Camera("a", W, H, a.K, [0.01, 0, 0, 0, 0]), b])    # distortion: remapped
    assert not d.identity and d.maps is not None


def _moved_rig(T):
    """The rectified rig with its rig frame moved: cam_from_rig <- cam_from_rig @ T."""
    return Rig(tuple(c.with_pose(c.cam_from_rig @ T) for c in rectified_rig(W, H, F, B).cameras))


@pytest.mark.parametrize("ref", [0, 1])
def test_closed_form_equals_triangulate(ref):
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(3)
    T = pose_matrix(Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix(), [0.01, -0.02, 0.005])
    rig = _moved_rig(T)
    cams = rig.cameras
    pair = StereoPair.from_cameras(rig, ref)
    assert pair.identity
    # points in front of camera 0 at 15..45 mm over the whole image
    uv0 = rng.uniform([0, 0], [W - 1, H - 1], (200, 2))
    z = rng.uniform(0.015, 0.045, 200)
    Xc = np.c_[(uv0 - [(W - 1) / 2, (H - 1) / 2]) / F * z[:, None], z]
    X_true = (Xc - cams[0].t) @ cams[0].R                         # rig frame
    uv = np.stack([c.project(X_true) for c in cams], axis=1)
    d = uv[:, ref, 0] - uv[:, pair.other, 0]
    X, cov = pair.triangulate(uv[:, ref], d)
    tri = triangulate(cams, uv, sigma_px=1.0, min_angle_deg=0.0)
    assert tri.ok.all()
    scale = np.linalg.norm(tri.points - cams[0].centre, axis=1)
    assert (np.linalg.norm(X - tri.points, axis=1) / scale).max() < 1e-6
    assert (np.linalg.norm(X - X_true, axis=1) / scale).max() < 1e-9
    cnorm = np.linalg.norm(tri.covariances, axis=(1, 2))
    assert (np.linalg.norm(cov - tri.covariances, axis=(1, 2)) / cnorm).max() < 1e-6
    # the pixels it reports are those observations
    a, b = pair.original_pixels(uv[:, ref], d, X)
    np.testing.assert_allclose(a, uv[:, ref], atol=1e-9)
    np.testing.assert_allclose(b, uv[:, pair.other], atol=1e-9)


def test_closed_form_behind_is_nan():
    pair = StereoPair.from_cameras(rectified_rig(W, H, F, B))
    X, cov = pair.triangulate([[10.0, 20.0], [30.0, 40.0]], [0.0, -5.0])
    assert np.isnan(X).all() and np.isnan(cov).all()


@pytest.mark.parametrize("shift", [3.3, -2.25])
def test_refine_disparity_recovers_a_subpixel_shift(shift):
    tex = _texture(400)[100:300, :].astype(float)
    fx = np.fft.fftfreq(tex.shape[1])
    moved = np.fft.ifft(np.fft.fft(tex, axis=1) * np.exp(2j * np.pi * fx * shift), axis=1).real   # tex(x + shift)
    ref, other = (np.clip(np.rint(t), 0, 255).astype(np.uint8) for t in (tex, moved))
    uv = np.random.default_rng(0).uniform([20, 20], [370, 180], (300, 2))
    # ref's pixel x is other's x - shift: disparity +shift; started 0.7 px off
    d = refine_disparity(ref, other, uv, np.full(300, shift + 0.7))
    assert np.median(np.abs(d - shift)) < 0.02
    assert abs(np.median(d - shift)) < 0.005


# -- synthetic sequences ---------------------------------------------------------------------------------------------
K_PLANE = 10


@pytest.fixture(scope="module")
def plane_run(plane):
    rig = rectified_rig(W, H, F, B)
    frames = plane.frames(rig, K_PLANE)
    t = time.perf_counter()
    run = dense_sequence(frames, rig)
    return rig, run, time.perf_counter() - t


def test_plane_positions_covariances_and_tracks(plane, plane_run):
    rig, run, elapsed = plane_run
    res = run.result
    K = K_PLANE
    seen = res.seen.sum(axis=1)
    rel, nz, drift = _errors(plane, res, rig.cameras[0], K)
    spans = _spans(res)
    print(f"\nplane: points/frame {seen.min()}..{seen.max()}, {len(res.point_ids)} tracks, depth error median "
          f"{np.median(rel):.2e} p95 {np.percentile(rel, 95):.2e}, normalised RMS {np.sqrt(np.mean(nz ** 2)):.2f}, "
          f"sigma {res.sigma_px:.3f} px, drift median {np.median(drift):.2f} px, median span {np.median(spans)}, "
          f"{K / elapsed:.1f} pairs/s")
    assert seen.min() >= 2500                          # ~3000 grid cells see the plane in the partner
    assert np.median(rel) < 0.005 and np.percentile(rel, 95) < 0.01
    # covariances: sigma estimated from the data, errors along the ray within a factor 1.6 of it
    assert res.sigma_estimated and 0.02 < res.sigma_px < 0.3
    assert 0.6 < np.sqrt(np.mean(nz ** 2)) < 1.6
    assert 0.6 < 1.4826 * np.median(np.abs(nz)) < 1.6
    # tracks: the first frame's points are seen to the end, and stay on their piece of texture
    assert np.median(spans) >= K - 1
    assert (res.birth_frame == 0).mean() > 0.9
    assert np.median(drift) < 0.5 and np.percentile(drift, 95) < 1.5
    np.testing.assert_array_equal(res.point_ids, np.arange(len(res.point_ids)))


def test_plane_result_fields(plane_run):
    rig, run, _ = plane_run
    res = run.result
    P = len(res.point_ids)
    C = 2
    assert res.positions.shape == (K_PLANE, P, 3) and res.covariances.shape == (K_PLANE, P, 3, 3)
    assert res.uv.shape == (K_PLANE, P, C, 2) and res.uv.dtype == np.float32
    seen = res.seen
    assert (res.views[seen] == 2).all() and (res.views[~seen] == 0).all()
    assert (res.reprojection_rms[seen] == 0).all() and np.isnan(res.reprojection_rms[~seen]).all()
    assert np.isnan(res.covariances[~seen]).all() and np.isfinite(res.covariances[seen]).all()
    np.testing.assert_array_equal(res.frames, np.arange(K_PLANE))
    # the reference is the position in the birth frame
    np.testing.assert_array_equal(res.reference, res.positions[res.birth_frame, np.arange(P)])
    # uv: the projections of the point in both cameras (reprojection error 0)
    X = res.positions[seen]
    for c, cam in enumerate(rig.cameras):
        np.testing.assert_allclose(res.uv[seen][:, c], cam.project(X), atol=1e-3)
    assert np.abs(res.uv[seen][:, 0, 1] - res.uv[seen][:, 1, 1]).max() == 0       # same rows
    # covariances: symmetric positive definite, the unit covariance times sigma^2
    Cs = res.covariances[seen][:200]
    np.testing.assert_allclose(Cs, np.swapaxes(Cs, 1, 2), rtol=1e-12, atol=0)
    assert (np.linalg.eigvalsh(Cs) > 0).all()
    pair = StereoPair.from_cameras(rig)
    _, unit = pair.triangulate(res.uv[seen][:200, 0], res.uv[seen][:200, 0, 0] - res.uv[seen][:200, 1, 0])
    np.testing.assert_allclose(Cs, unit * res.sigma_px ** 2, rtol=1e-4)
    assert set(res.timings) == {"tracking", "triangulation", "detection"}
    assert len(run.frames) == K_PLANE and run.frames[0].detected and not any(f.skipped for f in run.frames)
    assert [f.seen for f in run.frames] == seen.sum(axis=1).tolist()
    assert res.roi.all() and res.problems == [] and run.problems == ()


def test_plane_reference_camera_right(plane):
    """The right camera as the reference: the partner is on its left (negative disparities internally)."""
    rig = rectified_rig(W, H, F, B)
    K = 4
    res = dense_sequence(plane.frames(rig, K), rig, DenseOptions(ref_camera=1)).result
    rel, nz, _ = _errors(plane, res, rig.cameras[1], K)
    assert res.seen.sum(axis=1).min() >= 2500
    assert np.median(rel) < 0.005
    assert 0.6 < 1.4826 * np.median(np.abs(nz)) < 1.6


@pytest.mark.parametrize("aspect", [0.5, 1.09])
def test_plane_non_square_pixels_keep_the_horizontal_resolution(plane, aspect):
    """Cameras whose pixels are not square (fy = aspect fx): one field of interlaced video (0.5, half the rows) and a
    de-interlaced rig such as Hamlyn's (1.09). The rectified focal length is the larger of fx and fy: for the
    field fx, on rows resampled to cover the same view (stereoRectify alone takes fy, which squeezed the columns:
    1 179 points a frame, depth errors 2.4 times larger); fy as before for the other. The plane is measured as
    well as with square pixels: at least 2 500 points in every frame (the square-pixel run's bound), depth
    errors median < 0.5 %, normalised errors of unit spread."""
    h = int(round(H * aspect))
    Kc = np.array([[F, 0, (W - 1) / 2], [0, aspect * F, (h - 1) / 2], [0, 0, 1]])
    rig = Rig(tuple(Camera(f"{c.name}_{aspect}", W, h, Kc, np.zeros(5), c.cam_from_rig)    # own names: ray cache
                    for c in rectified_rig(W, H, F, B).cameras))
    pair = StereoPair.from_cameras(rig)
    assert not pair.identity and pair.f == pytest.approx(F * max(1.0, aspect), rel=2e-3)
    assert (pair.rect_width, pair.rect_height) == (W, max(h, H)) and (pair.width, pair.height) == (W, h)
    K = 4
    res = dense_sequence(plane.frames(rig, K), rig).result
    rel, nz, _ = _errors(plane, res, rig.cameras[0], K)
    print(f"\naspect {aspect}: points/frame {res.seen.sum(axis=1).min()}, depth error median {np.median(rel):.2e}")
    assert res.seen.sum(axis=1).min() >= 2500
    assert np.median(rel) < 0.005 and np.percentile(rel, 99) < 0.02
    assert 0.6 < 1.4826 * np.median(np.abs(nz)) < 1.6


def test_plane_convergent_rig_with_distortion(plane):
    """A toed-in pair with different intrinsics and radial distortion: rectified by remapping."""
    from scipy.spatial.transform import Rotation

    Ra = Rotation.from_euler("y", 1.5, degrees=True).as_matrix()
    Rb = Rotation.from_euler("yx", [-1.5, 0.3], degrees=True).as_matrix()
    cb = np.array([B, 0.0002, 0.0])
    rig = Rig((Camera("a", W, H, [[392.0, 0, 181], [0, 388, 142], [0, 0, 1]], [-0.05, 0.01, 0, 0, 0],
                      pose_matrix(Ra, [0, 0, 0])),
               Camera("b", W, H, [[386.0, 0, 177], [0, 390, 146], [0, 0, 1]], [-0.04, 0, 0, 0, 0],
                      pose_matrix(Rb, -Rb @ cb))))
    pair = StereoPair.from_cameras(rig)
    assert not pair.identity
    K = 4
    res = dense_sequence(plane.frames(rig, K), rig).result
    rel, nz, drift = _errors(plane, res, rig.cameras[0], K)
    assert res.seen.sum(axis=1).min() >= 2000
    assert np.median(rel) < 0.005
    assert 0.6 < 1.4826 * np.median(np.abs(nz)) < 1.6
    assert np.median(drift) < 0.5


def test_three_cameras_use_the_widest_baseline(plane):
    c0, c1 = rectified_rig(W, H, F, B).cameras
    mid = Camera("mid", W, H, c0.K, np.zeros(5), pose_matrix(np.eye(3), [-B / 2, 0.0, 0.0]))
    rig = Rig((c0, mid, c1))
    assert StereoPair.from_cameras(rig, 0).other == 2
    res = dense_sequence(plane.frames(rig, 3), rig).result
    seen = res.seen
    assert np.isnan(res.uv[:, :, 1]).all()
    assert np.isfinite(res.uv[seen][:, [0, 2]]).all()
    rel, _, _ = _errors(plane, res, c0, 3)
    assert np.median(rel) < 0.005


def test_missing_images_skip_the_instant_and_tracks_resume(plane):
    rig = rectified_rig(W, H, F, B)
    frames = plane.frames(rig, 5)
    frames[2] = (2, [frames[2][1][0], None], ["cam1/000002.png: unreadable"])
    run = dense_sequence(frames, rig)
    res = run.result
    assert [f.skipped for f in run.frames] == [False, False, True, False, False]
    assert run.frames[2].seen == 0 and not res.seen[2].any()
    assert run.problems == ((2, "cam1/000002.png: unreadable"),)
    assert len(res.problems) == 1 and "frame 2" in res.problems[0]
    # the points of frame 1 are found again after the gap (flow from frame 1 to frame 3)
    both = res.seen[1] & res.seen[3]
    assert both.sum() > 0.9 * res.seen[1].sum()


def test_roi_and_track_cap(plane):
    """Points are born inside the region of interest only (as in the sparse mode); a point the motion carries out of
    it is still measured: a region ending a few pixels before the plane's motion takes the points over its edge."""
    rig = rectified_rig(W, H, F, B)
    roi = np.zeros((H, W), bool)
    roi[50:200, 150:300] = True
    res = dense_sequence(plane.frames(rig, 8), rig, roi=roi).result     # 7 frames of about 1 px each
    ids = np.arange(res.seen.shape[1])
    first = res.seen.argmax(axis=0)
    born = np.rint(res.uv[first, ids, 0]).astype(int)                  # the reference camera's pixel at birth
    assert len(born) > 0 and roi[born[:, 1], born[:, 0]].all()
    np.testing.assert_array_equal(res.roi, roi)
    late = np.rint(res.uv[7, res.seen[7], 0]).astype(int)
    outside = ~roi[np.clip(late[:, 1], 0, H - 1), np.clip(late[:, 0], 0, W - 1)]
    assert outside.any(), "the motion takes no point out of the region: the test does not test it"
    capped = dense_sequence(plane.frames(rig, 3), rig, DenseOptions(max_tracks=500)).result
    assert len(capped.point_ids) == 500


def test_nothing_measurable_fails():
    rig = rectified_rig(W, H, F, B)
    blank = np.full((H, W), 90, np.uint8)
    with pytest.raises(MeasureFailed):
        dense_sequence([(k, [blank, blank], []) for k in range(3)], rig)
    with pytest.raises(MeasureFailed):
        dense_sequence([(0, [blank, None], [])], rig)


# -- real data ------------------------------------------------------------------------------------------------------
@pytest.mark.skipif(not INVIVO.is_dir(), reason="shared data not available (hamlyn_invivo_heart)")
def test_invivo_heart_first_30_frames():
    """At least 1000 points in every frame of the real beating heart, at physically plausible depths."""
    from heartcv.io import FrameReader, open_frame_source

    rig = rectified_rig(W, H, F, B)
    source = open_frame_source(INVIVO, cameras=["cam0", "cam1"])
    with FrameReader(source, frames=range(30)) as reader:
        t = time.perf_counter()
        run = dense_sequence(reader, rig)
        elapsed = time.perf_counter() - t
    res = run.result
    seen = res.seen.sum(axis=1)
    z = res.positions[..., 2][res.seen]
    print(f"\nin vivo, 30 frames: points/frame min {seen.min()} mean {seen.mean():.0f}, {len(res.point_ids)} tracks, "
          f"median depth {np.median(z) * 1e3:.1f} mm, sigma {res.sigma_px:.3f} px, {30 / elapsed:.1f} pairs/s")
    assert len(res.frames) == 30 and not run.skipped
    assert seen.min() >= 1000
    assert 0.015 < np.median(z) < 0.045
    # the middle 90 % of the depths stay within the README's range, widened by 15 % (f and B uncertainty)
    lo, hi = np.percentile(z, [5, 95])
    assert 0.017 < lo and hi < 0.040
    assert res.sigma_estimated and 0.05 < res.sigma_px < 1.0

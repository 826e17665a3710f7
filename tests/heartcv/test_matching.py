"""heartcv.matching on the synthetic trinocular scene (tests/heartcv/synthetic_scene.py, 480x270, ~0.36 mm per px):
plane-sweep matches against the analytic ray-surface intersection, the planar-patch bias on a heart-sized sphere
against the least-squares plane of the patch footprint, a camera showing unrelated texture, and the geometric
helpers (depth range, normal hypotheses, local planes) against exact answers."""

import numpy as np
import pytest

from heartcv.camera import Camera, pose_matrix
from heartcv.features import detect_corners
from heartcv.matching import (
    bisector_normals,
    descriptor_epipolar_distance,
    descriptor_front_fraction,
    descriptor_inliers,
    descriptor_matches,
    descriptor_v_offset,
    local_planes,
    match_points,
    near_search_depth,
    normal_hypotheses,
    patch_offsets,
    ray_depth_range,
)

from .synthetic_scene import translating_scene


def _corners(scene, image, n=60, min_distance=10):
    """Corners of camera 0 on the central part of the cap (2 cm of its 3 cm radius: seen by every camera)."""
    uv, _ = detect_corners(image, scene.cap_mask(0, 0, 0.02), max_points=n, min_distance=min_distance)
    return uv


def _px_equivalent(cams, X, X_true):
    """Displacement (N,) of X from X_true in the other cameras' images: the largest over cameras 1 and 2 (px)."""
    return np.max([np.linalg.norm(c.project(X) - c.project(X_true), axis=1) for c in cams[1:]], axis=0)


@pytest.fixture(scope="module")
def gentle():
    """A gently curved cap (sphere radius 1 m, sag 0.45 mm at its 3 cm edge), noise-free, matched once."""
    scene = translating_scene(1, radius_m=1.0)
    images = scene.render_frame(0)
    uv = _corners(scene, images[0])
    m = match_points(scene.cameras, [im.astype(np.float32) for im in images], 0, uv)
    return scene, images, uv, m


def test_the_synthetic_scene_is_consistent(gentle):
    """The helper's ground truth: a pixel's surface point projects back onto it, and the camera-1 ray through
    that projection meets the surface at the same point; rendering is deterministic."""
    scene, images, uv, _ = gentle
    cams = scene.cameras
    X = scene.surface_point(0, uv, 0)
    assert np.abs(cams[0].project(X) - uv).max() < 1e-9
    X1 = scene.surface_point(1, cams[1].project(X), 0)
    assert np.abs(X1 - X).max() < 1e-12
    assert np.array_equal(scene.render(2, 0), images[2])
    noisy = [scene.render(0, 0, noise=2.0, rng=np.random.default_rng(5)) for _ in range(2)]
    assert np.array_equal(noisy[0], noisy[1]) and not np.array_equal(noisy[0], images[0])


def test_match_points_recovers_the_surface_point(gentle):
    scene, _, uv, m = gentle
    cams = scene.cameras
    X_true = scene.surface_point(0, uv, 0)
    assert len(uv) >= 30 and np.isfinite(X_true).all()
    assert m.ok.all() and np.isfinite(m.uv).all()
    assert np.array_equal(m.uv[:, 0], uv) and np.all(m.score[:, 0] == 1.0)
    # the matched point lies on the reference ray, at the true depth: within 0.05 px of the truth in the other
    # images (18 um laterally at 0.53 m) for at least 90 % of the corners (measured: p90 0.029 px, max 0.045 px)
    e = _px_equivalent(cams, m.points, X_true)
    assert np.mean(e < 0.05) >= 0.9
    o, d = cams[0].rays(uv)
    assert np.allclose(m.points, o + m.depth[:, None] * d, atol=1e-12)
    assert np.allclose(np.linalg.norm(m.normals, axis=1), 1.0)
    # the matched pixels: the projection of the true point to < 0.1 px (measured: max 0.049 px)
    for c in (1, 2):
        assert np.linalg.norm(m.uv[:, c] - cams[c].project(X_true), axis=1).max() < 0.1
    assert (m.score[:, 1:] > 0.95).all()


def test_known_surface_points_replace_the_seed_sweep(gentle, monkeypatch):
    """Corners near known surface points (here: other corners' true 3-D points, as the tracked points of an earlier
    detection) skip the full-range seed sweep and are matched from the plane through the known points as well as
    by the sweep: within 0.05 px of the truth in the other images for >= 90 % (the seed sweep's own bound); a
    corner far from every known point is still swept."""
    import heartcv.matching as matching

    scene, images, uv, _ = gentle
    cams = scene.cameras
    imgs = [im.astype(np.float32) for im in images]
    X_true = scene.surface_point(0, uv, 0)
    half = np.arange(len(uv)) % 2 == 0             # the known points: every second corner
    swept = []
    real = matching._candidate_depths
    monkeypatch.setattr(matching, "_candidate_depths", lambda *a, **k: swept.append(len(a[2])) or real(*a, **k))
    m = match_points(cams, imgs, 0, uv[~half], known=(uv[half], X_true[half]))
    assert swept == []                              # no seed sweep: every corner had known neighbours
    assert m.ok.mean() >= 0.95
    e = _px_equivalent(cams, m.points[m.ok], X_true[~half][m.ok])
    assert np.mean(e < 0.05) >= 0.9, np.sort(e)
    # three known points span no plane to predict from: every corner gets the seed sweep, as without them
    m2 = match_points(cams, imgs, 0, uv[~half], known=(uv[half][:3], X_true[half][:3]))
    assert swept and swept[0] == (~half).sum()
    e2 = _px_equivalent(cams, m2.points[m2.ok], X_true[~half][m2.ok])
    assert m2.ok.mean() >= 0.95 and np.mean(e2 < 0.05) >= 0.9


def test_match_points_on_a_heart_sized_sphere_finds_the_best_plane():
    """With a 5 cm sphere the planar patch model has a known bias: the sweep finds the plane that best fits the
    patch footprint, which lies behind the tangent plane by the mean sag of the footprint (~70 um here, 0.15 px).
    The matched depth equals the ray's intersection with the least-squares plane through the footprint's
    true surface points (the (2 r + 1)^2 pixels of the reference patch, ray cast) to 0.07 px for >= 90 %."""
    scene = translating_scene(1, radius_m=0.05)
    images = scene.render_frame(0)
    uv = _corners(scene, images[0], n=40)
    m = match_points(scene.cameras, [im.astype(np.float32) for im in images], 0, uv)
    assert m.ok.all()
    cams = scene.cameras
    o, d = cams[0].rays(uv)
    offs = patch_offsets(7)
    best = np.empty((len(uv), 3))
    for i in range(len(uv)):
        P = scene.surface_point(0, uv[i] + offs, 0)
        c = P.mean(axis=0)
        n = np.linalg.svd(P - c)[2][-1]
        best[i] = o[i] + (n @ (c - o[i])) / (n @ d[i]) * d[i]
    X_true = scene.surface_point(0, uv, 0)
    bias = ((best - X_true) * d).sum(axis=1)
    assert (bias > 3e-5).all()                               # the footprint plane is deeper than the surface point
    assert np.mean(_px_equivalent(cams, m.points, best) < 0.07) >= 0.9
    assert np.median(_px_equivalent(cams, m.points, X_true)) > 0.1          # ... and the bias is really there


@pytest.mark.parametrize("bad, kind", [(1, "texture"), (2, "noise")])
def test_a_camera_with_unrelated_content_is_never_matched(gentle, bad, kind):
    """Camera ``bad`` shows unrelated content (the same cap with another texture, or smoothed noise over the whole
    image): its view must not be matched, and a point kept in the two remaining views must pass the stricter
    two-view NCC and be the right point.

    The normal refinement and a last depth sweep use only the cameras that accept the point, so the two-view
    points stay precise (measured: 0.098 / 0.087 px in uv, 0.090 / 0.079 px-equivalent in depth; when the
    rejected camera still took part: 0.3 px and 0.7 px)."""
    import dataclasses

    import cv2

    scene, images, uv, _ = gentle
    imgs = [im.astype(np.float32) for im in images]
    if kind == "texture":
        imgs[bad] = dataclasses.replace(scene, seed=123).render(bad, 0).astype(np.float32)
    else:
        z = cv2.GaussianBlur(np.random.default_rng(9).normal(size=images[bad].shape).astype(np.float32), (0, 0), 1.5)
        imgs[bad] = np.clip(np.rint(120 + 40 * z / z.std()), 0, 255).astype(np.float32)
    m = match_points(scene.cameras, imgs, 0, uv)
    good = 3 - bad
    assert np.isnan(m.uv[:, bad]).all()
    assert m.ok.sum() >= 5
    assert (m.score[m.ok, good] >= 0.95).all()
    assert np.isnan(m.points[~m.ok]).all() and np.isnan(m.uv[~m.ok, good]).all()
    X_true = scene.surface_point(0, uv[m.ok], 0)
    cam = scene.cameras[good]
    e_uv = np.linalg.norm(m.uv[m.ok, good] - cam.project(X_true), axis=1).max()
    e_depth = np.linalg.norm(cam.project(m.points[m.ok]) - cam.project(X_true), axis=1).max()
    assert e_uv < 0.15
    assert e_depth < 0.15


def test_match_points_input_checks(gentle):
    scene, images, uv, _ = gentle
    with pytest.raises(ValueError, match="one per camera"):
        match_points(scene.cameras, images[:2], 0, uv)
    with pytest.raises(ValueError, match="reference"):
        match_points(scene.cameras, [None, images[1], images[2]], 0, uv)
    m = match_points(scene.cameras, images, 0, np.zeros((0, 2)))
    assert m.uv.shape == (0, 3, 2) and m.ok.shape == (0,)


# -- geometric helpers ---------------------------------------------------------------------------------------------
def test_ray_depth_range_brackets_the_surface_and_follows_its_sampling(gentle):
    scene, _, uv, _ = gentle
    cams = scene.cameras
    o, d = cams[0].rays(uv)
    r = ray_depth_range(cams, 0, o, d)
    depth = np.linalg.norm(scene.surface_point(0, uv, 0) - o, axis=1)
    assert (r[:, 0] < depth).all() and (depth < r[:, 1]).all()
    # the ends are the first and last of the 1024 log-spaced samples inside every other image (20 px margin)
    ratio = (5.0 / 0.02) ** (1 / 1023)

    def inside(t):
        X = o + t[:, None] * d
        return np.all([c.in_image(c.project(X), 20) for c in cams[1:]], axis=0)

    assert inside(r[:, 0]).all() and inside(r[:, 1]).all()
    assert not inside(r[:, 0] / ratio).any() and not inside(r[:, 1] * ratio).any()
    # rays whose whole interval is out of the other cameras' views: NaN
    assert np.isnan(ray_depth_range(cams, 0, o, d, near=0.02, far=0.1)).all()


def test_normal_hypotheses_are_unit_vectors_at_the_requested_tilts():
    rng = np.random.default_rng(1)
    axis = rng.normal(size=(5, 3))
    axis[0] = [1.0, 0.0, 0.0]                                # the other helper vector
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    h = normal_hypotheses(axis, (0.0, 12.0, 30.0), per_ring=6)
    assert h.shape == (5, 13, 3)
    assert np.abs(np.linalg.norm(h, axis=2) - 1).max() < 1e-12
    assert np.array_equal(h[:, 0], axis)
    tilt = np.degrees(np.arccos(np.clip(np.einsum("nhk,nk->nh", h, axis), -1, 1)))
    assert np.abs(tilt[:, 1:7] - 12.0).max() < 1e-6 and np.abs(tilt[:, 7:] - 30.0).max() < 1e-6
    # each ring: azimuths 60 degrees apart around the axis
    for ring in (slice(1, 7), slice(7, 13)):
        p = h[:, ring] - np.einsum("nhk,nk->nh", h[:, ring], axis)[..., None] * axis[:, None]
        p /= np.linalg.norm(p, axis=2, keepdims=True)
        step = np.einsum("nhk,nhk->nh", p, np.roll(p, -1, axis=1))
        assert np.abs(step - 0.5).max() < 1e-12


def _plane_setup(rng, n_seeds=30):
    cam = Camera("c", 400, 300, [[500.0, 0, 199.5], [0, 500.0, 149.5], [0, 0, 1]], np.zeros(5),
                 pose_matrix(np.eye(3), [0.01, -0.02, 0.0]))
    normal = np.array([0.2, -0.3, -1.0])
    normal /= np.linalg.norm(normal)
    dist = normal @ [0.0, 0.0, 0.5]                          # plane n.X = dist through (0, 0, 0.5)
    seed_uv = rng.uniform([50, 40], [350, 260], (n_seeds, 2))
    o, d = cam.rays(seed_uv)
    seeds = o + ((dist - o @ normal) / (d @ normal))[:, None] * d
    return cam, normal, dist, seed_uv, seeds


def test_local_planes_recovers_an_exact_plane():
    rng = np.random.default_rng(2)
    cam, normal, dist, seed_uv, seeds = _plane_setup(rng)
    uv = rng.uniform([60, 50], [340, 250], (10, 2))
    o, d = cam.rays(uv)
    depth, n = local_planes(uv, seed_uv, seeds, o, d, k=10, max_px=400)
    want = (dist - o @ normal) / (d @ normal)
    assert np.abs(depth - want).max() < 1e-12
    facing = normal if normal @ d[0] < 0 else -normal
    assert np.abs(n - facing).max() < 1e-12 and (np.einsum("nk,nk->n", n, d) < 0).all()


def test_local_planes_needs_four_near_non_collinear_seeds():
    rng = np.random.default_rng(3)
    cam, normal, dist, seed_uv, seeds = _plane_setup(rng)
    uv = np.array([[200.0, 150.0]])
    o, d = cam.rays(uv)
    depth, n = local_planes(uv, seed_uv[:3], seeds[:3], o, d)
    assert np.isnan(depth).all() and np.isnan(n).all()
    # seeds farther than max_px from the ray's pixel do not count
    far = np.linalg.norm(seed_uv - uv, axis=1) > 100
    depth, _ = local_planes(uv, seed_uv[far], seeds[far], o, d, max_px=100)
    assert np.isnan(depth).all()
    # collinear seeds (one image row on a plane through the camera centre's row) span no plane
    line_uv = np.stack([np.linspace(100, 300, 6), np.full(6, 150.0)], axis=1)
    lo, ld = cam.rays(line_uv)
    line = lo + 0.5 * ld
    depth, _ = local_planes(uv, line_uv, line, o, d)
    assert np.isnan(depth).all()


def _local_planes_loop(uv_ref, seed_uv, seed_points, origins, dirs, k=10, max_px=200.0):
    """Oracle: one point at a time, a k-d tree query and an SVD of the centred neighbours per point."""
    from scipy.spatial import cKDTree

    N = len(uv_ref)
    depth, normal = np.full(N, np.nan), np.full((N, 3), np.nan)
    if len(seed_uv) < 4:
        return depth, normal
    dist, nb = cKDTree(seed_uv).query(uv_ref, k=min(k, len(seed_uv)))
    for i in range(N):
        nn = nb[i][dist[i] <= max_px]
        if nn.size < 4:
            continue
        P = seed_points[nn]
        c = P.mean(axis=0)
        _, sv, vt = np.linalg.svd(P - c, full_matrices=False)
        if sv[1] < 1e-6 or abs(vt[-1] @ dirs[i]) < 0.2:
            continue
        n = vt[-1] if vt[-1] @ dirs[i] < 0 else -vt[-1]
        depth[i], normal[i] = n @ (c - origins[i]) / (n @ dirs[i]), n
    return depth, normal


def test_local_planes_equals_the_per_point_svd_on_a_curved_noisy_surface():
    """The batched plane fits against a per-point SVD loop, on a curved surface with noise and holes (some rays
    with fewer than 4 seeds within max_px), and the leave-self-out variant against the loop without the point."""
    rng = np.random.default_rng(5)
    cam, _, _, seed_uv, _ = _plane_setup(rng)
    seed_uv = np.concatenate([seed_uv, rng.uniform([20, 20], [380, 280], (60, 2))])
    o, d = cam.rays(seed_uv)
    depth = 0.5 + 0.05 * np.sin(seed_uv[:, 0] / 40.0) + rng.normal(scale=2e-4, size=len(seed_uv))
    seeds = o + depth[:, None] * d
    uv = np.concatenate([rng.uniform([0, 0], [400, 300], (200, 2)), [[2000.0, 2000.0]]])
    uo, ud = cam.rays(uv)
    got_d, got_n = local_planes(uv, seed_uv, seeds, uo, ud, k=8, max_px=60)
    want_d, want_n = _local_planes_loop(uv, seed_uv, seeds, uo, ud, k=8, max_px=60)
    assert np.array_equal(np.isnan(got_d), np.isnan(want_d)) and np.isfinite(got_d).sum() > 150
    assert np.isnan(got_d).sum() >= 1
    assert np.nanmax(np.abs(got_d - want_d)) < 1e-9 and np.nanmax(np.abs(got_n - want_n)) < 1e-6
    loo_d, _ = local_planes(seed_uv, seed_uv, seeds, o, d, k=8, max_px=60, leave_self_out=True)
    for i in range(len(seed_uv)):
        others = np.arange(len(seed_uv)) != i
        w, _ = _local_planes_loop(seed_uv[i:i + 1], seed_uv[others], seeds[others], o[i:i + 1], d[i:i + 1], k=8,
                                  max_px=60)
        assert np.isnan(w[0]) == np.isnan(loo_d[i]) and (np.isnan(w[0]) or abs(w[0] - loo_d[i]) < 1e-9)


def test_bisector_normals_and_patch_offsets(gentle):
    scene = gentle[0]
    cams = scene.cameras
    X = np.array([[0.0, 0.0, 0.53], [0.01, -0.02, 0.5]])
    n = bisector_normals(cams, X)
    want = sum((c.centre - X) / np.linalg.norm(c.centre - X, axis=1, keepdims=True) for c in cams)
    assert np.abs(n - want / np.linalg.norm(want, axis=1, keepdims=True)).max() < 1e-15
    offs = patch_offsets(2, 0.5)
    assert offs.shape == (25, 2) and np.array_equal(offs[0], [-1.0, -1.0]) and np.array_equal(offs[7], [0.0, -0.5])


def _shifted_pair(rng, dx, dy, size=(240, 320)):
    """A blurred-noise texture and the same texture moved dx px left and dy px down (cubic interpolation)."""
    import cv2

    h, w = size
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (h + 40, w + 120)).astype(np.float32), (0, 0), 1.5)
    tex = cv2.normalize(tex, None, 20, 235, cv2.NORM_MINMAX).astype(np.uint8)
    a = cv2.warpAffine(tex, np.float32([[1, 0, -60], [0, 1, -20]]), (w, h), flags=cv2.INTER_CUBIC)
    b = cv2.warpAffine(tex, np.float32([[1, 0, -60 - dx], [0, 1, -20 + dy]]), (w, h), flags=cv2.INTER_CUBIC)
    return a, b


def _offset(pairs, mask=None):
    return descriptor_v_offset([descriptor_matches(a, b, mask) for a, b in pairs])


@pytest.mark.parametrize("dy", [-6.3, 0.0, 0.45, 3.7])
def test_descriptor_v_offset_recovers_a_vertical_shift(dy):
    """A rectified pair whose second views lie dy px below the first (a disparity of 40 px besides): the SIFT
    descriptors' pooled offset is dy within 0.1 px (no geometry involved; SIFT's sub-pixel positions are biased by a
    few hundredths of a pixel, more than the standard error of thousands of matches, so measure's probes refine it
    with the rig's own matching); a mask that keeps only the left half gives it too, from fewer matches; colour and
    16-bit copies give the same."""
    rng = np.random.default_rng(11)
    pairs = [_shifted_pair(rng, 40.0, dy) for _ in range(3)]
    off, se, n = _offset(pairs)
    assert n >= 100 and abs(off - dy) < 0.1 and se < 0.05, (off, se, n)
    mask = np.zeros(pairs[0][0].shape, np.uint8)
    mask[:, :160] = 1
    off_m, _, n_m = _offset(pairs, mask)
    assert 20 <= n_m < n and abs(off_m - dy) < 0.15, (off_m, n_m, n)
    colour = [(np.dstack([a] * 3), np.dstack([b] * 3)) for a, b in pairs]
    deep = [(a.astype(np.uint16) * 257, b.astype(np.uint16) * 257) for a, b in pairs]
    assert _offset(colour)[0] == off and _offset(deep)[0] == off


def test_descriptor_v_offset_without_texture_is_nan():
    """Flat views (no features) and unrelated textures (matches do not agree): NaN, with the count."""
    flat = np.full((120, 160), 90, np.uint8)
    off, se, n = _offset([(flat, flat)])
    assert np.isnan(off) and np.isnan(se) and n == 0
    a, _ = _shifted_pair(np.random.default_rng(2), 0.0, 0.0)
    _, b = _shifted_pair(np.random.default_rng(99), 0.0, 0.0)
    off, se, n = _offset([(a, b)])
    assert np.isnan(off) and n < 20, (off, n)


def test_descriptor_matches_keeps_the_strongest_features():
    """A finely textured HD-sized view holds tens of thousands of SIFT features; at most ``features`` are matched
    (the view against itself: every match exact)."""
    rng = np.random.default_rng(5)
    a, _ = _shifted_pair(rng, 0.0, 0.0, size=(540, 960))
    ua, ub = descriptor_matches(a, a, features=500)
    assert 400 <= len(ua) <= 500 and np.abs(ua - ub).max() < 1e-3, len(ua)


def test_descriptor_epipolar_distance_against_the_rig():
    """Two calibrated cameras 6 mm apart (distortion included) seeing a textured plane: matches of their rendered
    views lie a median < 0.3 px from the rig's epipolar lines; with the second camera tilted 1 degree about the
    baseline in the rig (a stale calibration) they lie ~ f tan(1 deg) = 7 px off (5-10); with the cameras swapped
    over 1 px (2 px: a nearly horizontal baseline keeps most of the rows); no matches: NaN. The matches' rays meet
    in front of both cameras (> 90 %); with the views swapped behind them (< 10 % in front). Among 1.5 times as many
    random wrong matches the inliers of one epipolar geometry found without the rig are the true ones, and judge
    the rig as before."""
    import cv2

    from heartcv.camera import Camera, pose_matrix

    w, h, f = 320, 240, 400.0
    K = np.array([[f, 0, 159.5], [0, f, 119.5], [0, 0, 1.0]])
    dist = np.array([-0.05, 0.01, 0, 0, 0])
    cams = [Camera("a", w, h, K, dist, pose_matrix(np.eye(3), np.zeros(3))),
            Camera("b", w, h, K, dist, pose_matrix(cv2.Rodrigues(np.array([0.0, 0.03, 0.0]))[0],
                                                   np.array([-0.006, 0.0005, 0.0])))]
    rng = np.random.default_rng(8)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (600, 600)).astype(np.float32), (0, 0), 1.2)
    tex = cv2.normalize(tex, None, 10, 245, cv2.NORM_MINMAX)
    # the plane z = 40 mm (rig frame), textured at 0.1 mm per texel around the optical axis; each view by remap
    views = []
    for cam in cams:
        uu, vv = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
        o, d = cam.rays(np.c_[uu.ravel(), vv.ravel()])
        t = (0.04 - o[:, 2]) / d[:, 2]
        X = o + t[:, None] * d
        mx = (X[:, 0] / 1e-4 + 300).reshape(h, w).astype(np.float32)
        my = (X[:, 1] / 1e-4 + 300).reshape(h, w).astype(np.float32)
        views.append(cv2.remap(tex, mx, my, cv2.INTER_CUBIC).astype(np.uint8))
    m = [descriptor_matches(views[0], views[1])]
    med, n = descriptor_epipolar_distance(cams[0], cams[1], m)
    assert n >= 100 and med < 0.3, (med, n)
    R, tvec = cams[1].cam_from_rig[:3, :3], cams[1].cam_from_rig[:3, 3]
    tilt = cv2.Rodrigues(np.array([np.radians(1.0), 0.0, 0.0]))[0]
    stale = Camera("b", w, h, K, dist, pose_matrix(tilt @ R, tilt @ tvec))
    med_t, _ = descriptor_epipolar_distance(cams[0], stale, m)
    assert 5.0 < med_t < 10.0, med_t
    med_s, _ = descriptor_epipolar_distance(cams[1], cams[0], m)
    assert med_s > 1.0, med_s
    assert np.isnan(descriptor_epipolar_distance(cams[0], cams[1], [(np.zeros((0, 2)), np.zeros((0, 2)))])[0])
    # the rays of the matches meet in front of both cameras; with the views swapped (left for right) behind them
    front, n_front = descriptor_front_fraction(cams[0], cams[1], m)
    assert n_front >= 100 and front > 0.9, (front, n_front)
    back, _ = descriptor_front_fraction(cams[0], cams[1], [(ub, ua) for ua, ub in m])
    assert back < 0.1, back
    assert np.isnan(descriptor_front_fraction(cams[0], cams[1], [(np.zeros((0, 2)), np.zeros((0, 2)))])[0])
    # wrong matches (views far apart): 1.5 times as many random pairs as true ones. Their median distance from the
    # rig's lines is large; the inliers of one epipolar geometry found without the rig are the true ones, judged
    # as before (< 0.3 px, and the stale rig 5-10 px)
    ua, ub = m[0]
    rng = np.random.default_rng(4)
    k = int(1.5 * len(ua))
    noisy = [(np.r_[ua, rng.uniform(0, [w, h], (k, 2))], np.r_[ub, rng.uniform(0, [w, h], (k, 2))])]
    assert descriptor_epipolar_distance(cams[0], cams[1], noisy)[0] > 5.0
    inl = descriptor_inliers(cams[0], cams[1], noisy)
    assert len(ua) * 0.9 <= len(inl[0][0]) <= len(ua) + 0.05 * k, (len(inl[0][0]), len(ua), k)
    assert descriptor_epipolar_distance(cams[0], cams[1], inl)[0] < 0.3
    assert 5.0 < descriptor_epipolar_distance(cams[0], stale, descriptor_inliers(cams[0], stale, noisy))[0] < 10.0
    assert len(descriptor_inliers(cams[0], cams[1], [(ua[:5], ub[:5])])[0][0]) == 0


def test_the_nearest_depth_searched_follows_the_shortest_baseline():
    """2 cm for a rig whose baselines are at least 1 cm; twice the shortest baseline from the reference camera
    below that (a close endoscopic view: 5 mm -> 10 mm, 2.5 mm -> 5 mm); a single camera or coincident centres:
    2 cm. A three-camera rig: the baselines from the reference camera only."""
    K = np.array([[390.0, 0.0, 179.5], [0.0, 390.0, 143.5], [0.0, 0.0, 1.0]])

    def cam(x):
        return Camera("c", 360, 288, K, np.zeros(0), pose_matrix(np.eye(3), [-x, 0.0, 0.0]))

    assert near_search_depth([cam(0.0), cam(0.05)], 0) == 0.02
    assert near_search_depth([cam(0.0), cam(0.005)], 0) == pytest.approx(0.01, rel=1e-12)
    assert near_search_depth([cam(0.0), cam(0.0025)], 1) == pytest.approx(0.005, rel=1e-12)
    assert near_search_depth([cam(0.0)], 0) == 0.02
    assert near_search_depth([cam(0.0), cam(0.0)], 0) == 0.02
    trio = [cam(0.0), cam(0.003), cam(0.1)]
    assert near_search_depth(trio, 2) == pytest.approx(0.02)
    assert near_search_depth(trio, 0) == pytest.approx(0.006, rel=1e-12)

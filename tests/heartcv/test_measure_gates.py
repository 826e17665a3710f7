"""The gates of heartcv.measure against closed forms: the depth-uncertainty gate on a rectified stereo pair
(sigma_Z = sqrt(2) sigma Z^2 / (f B)), the image-size defaults, the per-gate counts and the failure message that
names the gate which emptied the candidate set; the rig-scale check."""

from __future__ import annotations

import numpy as np
import pytest

from heartcv.camera import Camera
from heartcv.measure import GATES, MeasureFailed, MeasureOptions, Measurer, emptied_by, measure_sequence
from heartcv.triangulation import triangulate

F, B, W, H = 390.0, 0.0055, 360, 288


def _rectified_pair():
    K = np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1]])
    T = np.eye(4)
    T[0, 3] = -B                                               # the right camera 5.5 mm along +x
    return [Camera("cam0", W, H, K), Camera("cam1", W, H, K, cam_from_rig=T)]


def test_depth_gate_matches_the_rectified_closed_form():
    cams = _rectified_pair()
    sigma, ratio = 0.5, 0.05
    m = Measurer(cams, MeasureOptions(pixel_sigma=sigma, max_depth_std_ratio=ratio), roi=np.ones((H, W), bool))
    # on the optical axis: Z = f B / d, var(d) = 2 sigma^2, so sigma_Z / Z = sqrt(2) sigma Z / (f B)
    z_star = ratio * F * B / (np.sqrt(2) * sigma)             # 0.152 m
    Z = np.array([0.5, 0.9, 0.99, 1.01, 1.1, 2.0]) * z_star
    X = np.stack([np.zeros_like(Z), np.zeros_like(Z), Z], axis=1)
    uv = np.stack([c.project(X) for c in cams], axis=1)
    tri = triangulate(cams, uv, sigma_px=1.0)
    rel = sigma * np.sqrt(tri.covariances[:, 2, 2]) / Z
    assert np.allclose(rel, np.sqrt(2) * sigma * Z / (F * B), rtol=1e-3)
    assert np.array_equal(m._depth_ok(tri.points, tri.covariances), [True, True, True, False, False, False])


def test_defaults_follow_the_image_size():
    big = MeasureOptions().for_image(1920, 1080)
    assert (big.min_distance_px, big.corner_block_size, big.match_radius) == (15.0, 7, 7)
    assert big.lk.window == 21 and big.lk.ncc_radius == 7
    small = MeasureOptions().for_image(360, 288)
    assert (small.min_distance_px, small.corner_block_size, small.match_radius) == (5.0, 3, 4)
    assert small.lk.window == 11 and small.lk.ncc_radius == 4 and small.lk.ncc_allowance == 0.25
    fixed = MeasureOptions(window_px=15, fb_max_px=0.3, track_min_ncc=0.8).for_image(360, 288).lk
    assert (fixed.window, fixed.fb_max_px, fixed.min_ncc, fixed.ncc_allowance) == (15, 0.3, 0.8, None)
    # explicit values are kept, and resolving twice changes nothing
    o = MeasureOptions(min_distance_px=9.0, corner_block_size=5).for_image(360, 288)
    assert (o.min_distance_px, o.corner_block_size) == (9.0, 5) and o.for_image(1920, 1080) == o


def test_emptied_by_names_the_gate_and_its_option():
    msg = emptied_by({"match": 3, "depth_uncertainty": 40, "reprojection": 0})
    assert msg.index("depth_uncertainty gate 40 (--max-depth-std)") < msg.index("match gate 3")
    assert "reprojection" not in msg
    assert "no corner was detected" in emptied_by(dict.fromkeys(GATES, 0))


def test_a_too_strict_depth_gate_empties_the_set_and_says_so():
    """Two views of a textured plane 30 mm away, a tolerance no point can meet: exit as MeasureFailed naming the
    depth-uncertainty gate, after counting every removed point there."""
    import cv2

    cams = _rectified_pair()
    rng = np.random.default_rng(0)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (H, W + 200)).astype(np.float32), (0, 0), 1.5)
    tex = cv2.normalize(tex, None, 20, 230, cv2.NORM_MINMAX).astype(np.uint8)
    d = F * B / 0.03                                           # disparity of the plane, 71.5 px
    left = tex[:, 100:100 + W]
    right = cv2.warpAffine(tex, np.float32([[1, 0, -100 - d], [0, 1, 0]]), (W, H), flags=cv2.INTER_CUBIC)
    frames = [(0, [left, right], [])]
    run = measure_sequence(iter(frames), cams, MeasureOptions(pixel_sigma=0.5), roi=np.ones((H, W), bool))
    n = int(run.result.seen.sum())
    assert n >= 50
    Z = run.result.positions[0][run.result.seen[0], 2]
    assert np.allclose(Z, 0.03, atol=0.0005)                   # the plane, single instant accepted
    with pytest.raises(MeasureFailed, match=r"depth_uncertainty gate \d+ \(--max-depth-std\)") as exc:
        measure_sequence(iter(frames), cams, MeasureOptions(pixel_sigma=0.5, max_depth_std_ratio=1e-4),
                         roi=np.ones((H, W), bool))
    assert "match" not in str(exc.value).split("gate")[0]


def test_rig_in_millimetres_is_refused():
    from heartcv.measure_data import MAX_BASELINE_M, check_rig_scale
    from heartcv.tracker.files import InputError

    cams = _rectified_pair()
    check_rig_scale(cams, "rig.yaml")                          # 5.5 mm: fine
    T = np.eye(4)
    T[0, 3] = -5.5                                             # the same rig written in millimetres
    mm = [cams[0], cams[1].with_pose(T)]
    with pytest.raises(InputError, match=r"cam0 and cam1 are 5.5 m apart.*millimetres") as exc:
        check_rig_scale(mm, "rig.yaml")
    assert exc.value.field == "cam_from_rig" and MAX_BASELINE_M == 1.0
    same = [cams[0], cams[1].with_pose(np.eye(4))]              # both at the origin: no baseline
    with pytest.raises(InputError, match=r"all 2 cameras share one centre \(at most 0 m apart\)") as exc:
        check_rig_scale(same, "rig.yaml")
    assert exc.value.field == "cam_from_rig"


def test_a_rectified_rig_s_meta_is_checked_against_its_poses():
    """``rectified`` must be true or false; a ``baseline_m`` more than 1 % from the cameras' distance (a hand-edited
    file: the poses are what the measurement uses) is refused naming it; the rig as written passes."""
    from heartcv.camera import Rig
    from heartcv.measure_data import check_rectified_meta
    from heartcv.tracker.files import InputError

    cams = tuple(_rectified_pair())
    d = float(np.linalg.norm(cams[1].centre - cams[0].centre))
    check_rectified_meta(Rig(cams, {"rectified": True, "baseline_m": d}), "rig.yaml")
    check_rectified_meta(Rig(cams, {"rectified": True, "baseline_m": 1.005 * d}), "rig.yaml")
    check_rectified_meta(Rig(cams, {}), "rig.yaml")
    for meta, field, message in [({"rectified": 5}, "rectified", "true or false expected, got 5"),
                                 ({"rectified": True, "baseline_m": 0.01}, "baseline_m",
                                  f"0.01 m, but the cameras cam0 and cam1 are {d:g} m apart"),
                                 ({"rectified": True, "baseline_m": "5 mm"}, "baseline_m",
                                  "a positive number of metres expected")]:
        with pytest.raises(InputError, match=message) as exc:
            check_rectified_meta(Rig(cams, meta), "rig.yaml")
        assert exc.value.field == field


def test_highlights_at_points_equal_the_dilated_mask():
    """Highlights.at (the ellipse under each point, without dilating the frame) against cv2.dilate of the whole
    mask read at the points: random sparse blobs, some on the image border, points everywhere (borders, outside,
    NaN); and grown() equals specular_mask's own dilation."""
    import cv2

    from heartcv.measure import Highlights, _mask_at
    from heartcv.tissue import specular_mask

    rng = np.random.default_rng(3)
    H, W = 90, 130
    raw = np.zeros((H, W), bool)
    raw[rng.integers(0, H, 40), rng.integers(0, W, 40)] = True
    raw[0, 5] = raw[H - 1, W - 1] = raw[40, 0] = True
    uv = np.concatenate([rng.uniform(-3, [W + 2, H + 2], (3000, 2)), [[np.nan, 4.0], [2.0, np.inf]]])
    for g in (0, 1, 4, 7):
        hl = Highlights(raw, g)
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * g + 1, 2 * g + 1))
        want = _mask_at(cv2.dilate(raw.astype(np.uint8), k).astype(bool) if g else raw, uv)
        got = hl.at(uv)
        assert np.array_equal(got, want) and want.sum() > (5 if g == 0 else 50) and (~want).sum() > 50
        assert np.array_equal(hl.grown(), cv2.dilate(raw.astype(np.uint8), k).astype(bool) if g else raw)
        assert np.array_equal(hl.at(uv), want)                  # also once the grown mask is cached
    assert not Highlights(np.zeros((H, W), bool), 5).at(uv).any()
    # a real colour frame: the grown mask is specular_mask's own dilation
    frame = np.full((120, 160, 3), (60, 70, 170), np.uint8)
    frame[50:53, 80:84] = 255
    frame[10, 10] = 255
    hl = Highlights(specular_mask(frame, grow_px=0), 4)
    assert np.array_equal(hl.grown(), specular_mask(frame, grow_px=4)) and hl.grown().sum() > 12


def test_size_factor_scales_every_pixel_size_and_threshold():
    """``size_factor`` k: every size of the rules (or given) times k, windows and blocks rounded up to odd, the
    high-pass, forward-backward, reprojection and outlier limits times k; k = 1 is exactly the unscaled options;
    resolving twice changes nothing more."""
    base = MeasureOptions().for_image(360, 288)
    assert MeasureOptions(size_factor=1.0).for_image(360, 288) == base
    o = MeasureOptions(size_factor=2.0).for_image(360, 288)
    assert (o.min_distance_px, o.corner_block_size, o.match_radius) == (10.0, 7, 8)
    assert (o.lk.window, o.lk.ncc_radius, o.lk.fb_max_px) == (23, 8, 2.0)
    assert (o.highpass_sigma, o.max_reprojection_px, o.outlier_px, o.size_factor) == (6.0, 2.0, 2.0, 1.0)
    assert o.for_image(360, 288) == o
    g = MeasureOptions(size_factor=1.5, window_px=21, highpass_sigma=None).for_image(1920, 1080)
    assert (g.lk.window, g.corner_block_size, g.match_radius, g.min_distance_px) == (33, 11, 10, 22.5)
    assert g.highpass_sigma is None
    with pytest.raises(ValueError, match="size_factor"):
        MeasureOptions(size_factor=0.0)


def test_texture_blur_is_the_blur_sigma_of_white_noise_and_doubles_with_upsampling():
    """Closed form: white noise blurred by a Gaussian of sigma has E|grad|^2 / E(lap)^2 = sigma^2 / 2, so the
    estimate is sigma (within 5 % for sigma >= 2 px on a 400 x 500 image; the finite differences read finer blur
    low: 0.85 at 1 px, still increasing); upsampling by 2 (Lanczos) doubles it (10 %; the artefacts of cubic
    interpolation and pixel noise read as sharp texture, so the estimate errs low); the automatic factor is 1 up to
    SHARP_BLUR_PX and blur / SHARP_BLUR_PX beyond; a flat image gives 1."""
    import cv2

    from heartcv.measure import SHARP_BLUR_PX, auto_size_factor, texture_blur_px

    rng = np.random.default_rng(7)
    noise = rng.standard_normal((400, 500)) * 30 + 128
    for sigma in (2.0, 3.0, 4.0):
        assert texture_blur_px(cv2.GaussianBlur(noise, (0, 0), sigma)) == pytest.approx(sigma, rel=0.05)
    fine = [texture_blur_px(cv2.GaussianBlur(noise, (0, 0), s)) for s in (0.7, 1.0, 1.5, 2.0)]
    assert np.all(np.diff(fine) > 0) and 0.8 < fine[1] < 0.9
    img = cv2.GaussianBlur(noise, (0, 0), 2.0).astype(np.float32)
    up = cv2.resize(img, (1000, 800), interpolation=cv2.INTER_LANCZOS4)
    assert texture_blur_px(up) / texture_blur_px(img) == pytest.approx(2.0, rel=0.1)
    k, blur = auto_size_factor([up, up])
    assert k == pytest.approx(blur / SHARP_BLUR_PX) and k > 2.0
    assert auto_size_factor([cv2.GaussianBlur(noise, (0, 0), 0.7)])[0] == 1.0
    assert auto_size_factor([np.full((50, 60), 9, np.uint8)]) == (1.0, pytest.approx(np.nan, nan_ok=True))


def test_reduced_camera_sees_what_the_reduced_image_shows():
    """A camera reduced by f projects every point where the full camera's projection lands in the image reduced
    by area averaging: ``(u + 0.5) s - 0.5`` with s the ratio of the sides (closed form, with distortion and a
    skew, to 1e-9 px); f = 1 changes nothing. The reduction of an image and of a mask follow the same sizes, and
    a bright dot moves where that map sends it (to 0.05 px, by its centroid in the reduced image)."""
    import cv2

    from heartcv.measure import reduce_image, reduce_mask, reduced_camera, reduced_size

    K = np.array([[812.0, 0.7, 401.3], [0.0, 805.0, 297.9], [0.0, 0.0, 1.0]])
    cam = Camera("c", 800, 600, K, np.array([-0.21, 0.07, 1e-3, -2e-3, 0.01]),
                 np.array([[1, 0, 0, 0.01], [0, 1, 0, -0.02], [0, 0, 1, 0.05], [0, 0, 0, 1.0]]))
    rng = np.random.default_rng(3)
    X = np.column_stack([rng.uniform(-0.02, 0.02, (50, 2)), rng.uniform(0.05, 0.1, 50)])
    uv = cam.project(X)
    for f in (1.0, 1.5, 2.0, 2.37):
        small = reduced_camera(cam, f)
        w, h = reduced_size(800, 600, f)
        assert (small.width, small.height) == (w, h)
        s = np.array([w / 800, h / 600])
        np.testing.assert_allclose(small.project(X), (uv + 0.5) * s - 0.5, atol=1e-9)
        np.testing.assert_array_equal(small.dist, cam.dist)
        np.testing.assert_array_equal(small.cam_from_rig, cam.cam_from_rig)
    same = reduced_camera(cam, 1.0)
    assert same.size == cam.size and np.array_equal(same.K, cam.K)
    img = np.zeros((600, 800), np.float32)
    cv2.circle(img, (400, 300), 12, 255.0, -1)
    for f in (2.0, 2.5):
        small = reduce_image(img, f)
        assert small.shape == reduced_size(800, 600, f)[::-1]
        yy, xx = np.mgrid[:small.shape[0], :small.shape[1]]
        centroid = np.array([(xx * small).sum(), (yy * small).sum()]) / small.sum()
        yy, xx = np.mgrid[:600, :800]
        full = np.array([(xx * img).sum(), (yy * img).sum()]) / img.sum()
        s = np.array([small.shape[1] / 800, small.shape[0] / 600])
        np.testing.assert_allclose(centroid, (full + 0.5) * s - 0.5, atol=0.05)
        m = reduce_mask(img > 0, f)
        assert m.shape == small.shape and m.dtype == bool and 0.8 < m.sum() * f * f / (img > 0).sum() < 1.2


def test_auto_reduction_reduces_blurry_frames_until_they_read_sharp():
    """Sharp frames (blur <= SHARP_BLUR_PX, or up to NEAR_SHARP times it) and a flat image keep factor 1. Blurry frames
    (white noise blurred by sigma = 3 and 5 px) get the smallest factor of the sequence blur, blur x 1.1, ... at which
    the frames reduced by area averaging read at most SHARP_BLUR_PX (brute force: the factor before it reads more), and
    the factor is about sigma (a reduction by f divides a Gaussian blur by f; the reduced pixels' area adds a little). A
    small image stops at MIN_REDUCED_SIDE_PX."""
    import cv2

    from heartcv.measure import (
        MIN_REDUCED_SIDE_PX,
        NEAR_SHARP,
        REDUCTION_STEP,
        SHARP_BLUR_PX,
        auto_reduction,
        reduce_image,
        texture_blur_px,
    )

    rng = np.random.default_rng(11)
    noise = rng.standard_normal((1200, 1600)) * 30 + 128
    sharp = cv2.GaussianBlur(noise, (0, 0), 0.7)
    f, blur, reduced = auto_reduction([sharp, sharp])
    assert f == 1.0 and blur == reduced and blur <= SHARP_BLUR_PX
    f, blur, reduced = auto_reduction([np.full((50, 60), 9, np.uint8)])
    assert f == 1.0 and np.isnan(blur)
    # just over the line (the in-vivo right camera reads 1.006): left as it is, not reduced ~1.6x (area averaging
    # near factor 1 adds blur of its own, so the first factor that reads sharp again was far larger)
    near = cv2.GaussianBlur(noise, (0, 0), 1.3)
    f, blur, reduced = auto_reduction([near])
    assert SHARP_BLUR_PX < blur < NEAR_SHARP * SHARP_BLUR_PX and f == 1.0 and reduced == blur
    for sigma in (3.0, 5.0):
        img = cv2.GaussianBlur(noise, (0, 0), sigma)
        f, blur, reduced = auto_reduction([img])
        assert blur == pytest.approx(sigma, rel=0.05)
        assert reduced == pytest.approx(texture_blur_px(reduce_image(img, f))) and reduced <= SHARP_BLUR_PX
        if f > blur / SHARP_BLUR_PX + 1e-12:
            assert texture_blur_px(reduce_image(img, f / REDUCTION_STEP)) > SHARP_BLUR_PX
        assert sigma * 0.8 < f < sigma * 1.1     # a Gaussian blur over f, plus the reduced pixels' own area
    small = cv2.GaussianBlur(rng.standard_normal((160, 200)) * 30 + 128, (0, 0), 4.0)
    f, blur, reduced = auto_reduction([small])
    assert f == pytest.approx(160 / MIN_REDUCED_SIDE_PX) and reduced > SHARP_BLUR_PX


def test_combing_ratio_tells_interlaced_frames():
    """White noise reads 1 (both second differences have variance 1.5 sigma^2; 5 % on 400 x 500), smooth texture
    less (noise blurred by 1.5 px: below 0.3), an image whose odd rows come from a copy moved by 3 px (two fields,
    two instants) more than COMBING_RATIO, the same image progressive less; a flat image NaN; over frames the median
    of the finite ones."""
    import cv2

    from heartcv.measure import COMBING_RATIO, combing_ratio

    rng = np.random.default_rng(4)
    noise = rng.standard_normal((400, 500)) * 20 + 128
    assert combing_ratio(noise) == pytest.approx(1.0, rel=0.05)
    smooth = cv2.GaussianBlur(noise, (0, 0), 1.5)
    assert combing_ratio(smooth) < 0.3
    moved = np.roll(smooth, 3, axis=1)
    woven = smooth.copy()
    woven[1::2] = moved[1::2]
    assert combing_ratio(woven) > COMBING_RATIO > combing_ratio(smooth)
    assert np.isnan(combing_ratio(np.full((50, 60), 7.0)))
    from heartcv.measure import frames_combing_ratio

    frames = [smooth, woven, noise, np.full((400, 500), 7.0)]
    assert frames_combing_ratio(frames) == np.median([combing_ratio(f) for f in frames[:3]])   # the flat one left out
    assert np.isnan(frames_combing_ratio([]))


def test_working_view_maps_working_pixels_back_to_the_full_images():
    """WorkingView.of (one field, then reduced; or either alone): for each camera, ``a * uv_work + b`` of the working
    camera's projection is the full camera's projection (with distortion, to 1e-6 px), the working cameras' sizes
    are those of the working images, and the pixel scale is the geometric mean of ``a``."""
    from heartcv.measure import WorkingView, reduce_image

    K = np.array([[812.0, 0.7, 401.3], [0.0, 805.0, 297.9], [0.0, 0.0, 1.0]])
    cams = [Camera("a", 800, 601, K, np.array([-0.21, 0.07, 1e-3, -2e-3, 0.01])),
            Camera("b", 800, 601, K, np.zeros(5), np.r_[np.c_[np.eye(3), [-0.005, 0, 0]], [[0, 0, 0, 1]]])]
    rng = np.random.default_rng(6)
    X = np.column_stack([rng.uniform(-0.02, 0.02, (40, 2)), rng.uniform(0.05, 0.1, 40)])
    img = rng.integers(0, 255, (601, 800), dtype=np.uint8)
    roi = np.ones((601, 800), bool)
    for field, reduction in ((None, 1.0), (0, 1.0), (1, 1.0), (None, 2.3), (1, 1.7)):
        view = WorkingView.of(cams, roi, field=field, reduction=reduction)
        assert view.transformed == (field is not None or reduction > 1)
        (_, [w0, _], _), = view.frames([(0, [img, img], [])])
        assert w0.shape == view.roi.shape == (view.cameras[0].height, view.cameras[0].width)
        expected = img if field is None else img[field::2]
        if reduction == 1.0:
            np.testing.assert_array_equal(w0, expected)
        else:
            np.testing.assert_array_equal(w0, reduce_image(expected, reduction))
        for c, cam in enumerate(cams):
            a, b = view.maps[c]
            np.testing.assert_allclose(view.cameras[c].project(X) * a + b, cam.project(X), atol=1e-6)
            assert view.pixel_scale(c) == pytest.approx(np.sqrt(a[0] * a[1]))
    with pytest.raises(ValueError, match="field"):
        WorkingView.of(cams, roi, field=2)
    with pytest.raises(ValueError, match="reduction"):
        WorkingView.of(cams, roi, reduction=0.5)


def test_field_camera_sees_what_the_field_shows():
    """One field of an interlaced image (rows field, field + 2, ...): the field camera projects every point at
    ``(u, (v - field) / 2)`` of the full camera's projection (closed form, with distortion, to 1e-9 px); its height
    is the field's row count."""
    from heartcv.measure import field_camera, field_image

    K = np.array([[812.0, 0.7, 401.3], [0.0, 805.0, 297.9], [0.0, 0.0, 1.0]])
    cam = Camera("c", 800, 601, K, np.array([-0.21, 0.07, 1e-3, -2e-3, 0.01]))
    rng = np.random.default_rng(5)
    X = np.column_stack([rng.uniform(-0.02, 0.02, (40, 2)), rng.uniform(0.05, 0.1, 40)])
    uv = cam.project(X)
    img = np.arange(601 * 3).reshape(601, 3)
    for f in (0, 1):
        fc = field_camera(cam, f)
        assert fc.height == field_image(img, f).shape[0] == len(range(f, 601, 2)) and fc.width == 800
        np.testing.assert_allclose(fc.project(X), np.column_stack([uv[:, 0], (uv[:, 1] - f) / 2]), atol=1e-9)
        np.testing.assert_array_equal(field_image(img, f), img[f::2])


def test_auto_field_takes_the_first_field_of_combed_frames_only():
    """auto_field: frames woven from two instants of a moving texture (combing ratio above 1) get the first field
    (0); the progressive frames, white noise (its ratio 1 within 1 %, just under it here) and a flat image (NaN) get
    the whole frames (None)."""
    import cv2

    from heartcv.measure import COMBING_RATIO, auto_field, frames_combing_ratio

    rng = np.random.default_rng(8)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (200, 260)).astype(np.float32), (0, 0), 2.0)
    prog = [np.clip(np.roll(tex, k, axis=1), 0, 255).astype(np.uint8)[:, :240] for k in range(4)]
    woven = []
    for im in prog:
        w = im.copy()
        w[1::2] = np.roll(im, 4, axis=1)[1::2]                  # the second field 4 px later
        woven.append(w)
    field, ratio = auto_field(woven)
    assert field == 0 and ratio > COMBING_RATIO and ratio == frames_combing_ratio(woven)
    assert auto_field(prog)[0] is None and auto_field(prog)[1] < COMBING_RATIO
    noise = [rng.normal(128, 20, (200, 240)).clip(0, 255).astype(np.uint8) for _ in range(9)]
    field, ratio = auto_field(noise)                          # white noise sits at the threshold (0.997 here)
    assert abs(ratio - 1.0) < 0.01 and field is None
    flat = [np.full((50, 60), 90, np.uint8)]
    field, ratio = auto_field(flat)
    assert field is None and np.isnan(ratio)


def test_bob_field_keeps_its_rows_and_fills_the_others_at_its_phase():
    """bob_field(image, f): the rows f, f + 2, ... as they are, every other row the mean of its two neighbours (the
    nearest one at an edge), the dtype kept (8-bit rounded). A vertical linear ramp is reproduced exactly by both
    fields away from the edge rows, so the two fields of a progressive image are images of one geometry (no
    half-row shift); colour images per channel."""
    from heartcv.measure import bob_field

    rng = np.random.default_rng(11)
    img = rng.integers(0, 256, (7, 5, 3), dtype=np.uint8)
    for f in (0, 1):
        out = bob_field(img, f)
        assert out.dtype == np.uint8 and out.shape == img.shape
        np.testing.assert_array_equal(out[f::2], img[f::2])
        for v in range(1 - f, 7, 2):
            nb = [r for r in (v - 1, v + 1) if 0 <= r < 7]
            expected = np.rint(np.mean([img[r].astype(float) for r in nb], axis=0))
            np.testing.assert_array_equal(out[v], expected.astype(np.uint8))
    ramp = np.repeat((3.0 * np.arange(12))[:, None], 4, axis=1)
    for f in (0, 1):
        np.testing.assert_allclose(bob_field(ramp, f)[1:-1], ramp[1:-1], atol=1e-12)
    with pytest.raises(ValueError, match="field"):
        bob_field(img, 2)


def test_field_instants_are_both_fields_in_the_order_taken():
    """FieldInstants: frame k gives instants 2k (the field taken first) and 2k + 1, each bob_field of its images,
    with the frame's problems; read(i) gives what the iteration gives at i; a missing image stays missing."""
    from heartcv.measure import FieldInstants, bob_field

    rng = np.random.default_rng(12)
    frames = [[rng.integers(0, 256, (6, 4), dtype=np.uint8), None if k == 1 else
               rng.integers(0, 256, (6, 4), dtype=np.uint8)] for k in range(3)]

    class Reader:
        def read(self, k):
            return frames[k], ([f"p{k}"] if k == 1 else [])

        def __iter__(self):
            return ((k, *self.read(k)) for k in range(3))

    for first in (0, 1):
        inst = FieldInstants(Reader(), first)
        got = list(inst)
        assert [i for i, _, _ in got] == list(range(6))
        for i, images, problems in got:
            k, f = i // 2, (first if i % 2 == 0 else 1 - first)
            assert problems == (["p1"] if k == 1 else [])
            np.testing.assert_array_equal(images[0], bob_field(frames[k][0], f))
            assert (images[1] is None) == (k == 1)
            r_images, r_problems = inst.read(i)
            assert r_problems == problems and all(
                (a is None and b is None) or np.array_equal(a, b) for a, b in zip(r_images, images))
    with pytest.raises(ValueError, match="first"):
        FieldInstants(Reader(), 2)


def _woven(first, moves, shift=3, K=12, seed=9):
    """K interlaced frames of a texture panning ``shift`` px per field time (``moves``), its ``first`` field taken
    first: frame k's first field shows instant 2k, its other field instant 2k + 1."""
    import cv2

    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (120, 400)).astype(np.float32), (0, 0), 2.0)
    def at(i):
        return np.roll(tex, shift * i if moves else 0, axis=1)[:, :200]
    frames = []
    for k in range(K):
        a, b = at(2 * k), at(2 * k + 1)
        w = np.empty_like(a)
        w[first::2], w[1 - first::2] = a[first::2], b[1 - first::2]
        frames.append(np.clip(w, 0, 255).astype(np.uint8))
    return frames


def test_field_order_tells_which_field_was_taken_first():
    """field_order on a panning texture woven with the top field first: 0, every frame votes for it and the ratio
    is above 1; with the bottom field first: 1, all votes, ratio below 1; a still scene cannot tell (no vote, ratio
    1). Fewer than 3 frames: no pairs, NaN."""
    from heartcv.measure import field_order

    first, ratio, votes, pairs = field_order(_woven(0, True))
    assert (first, votes, pairs) == (0, 10, 10) and ratio > 1.2
    first, ratio, votes, pairs = field_order(_woven(1, True))
    assert (first, votes, pairs) == (1, 10, 10) and ratio < 1 / 1.2
    assert field_order(_woven(0, False)) == (0, 1.0, 0, 0)          # a still scene: every frame a tie, no vote
    first, ratio, votes, pairs = field_order(_woven(0, True)[:2])
    assert (first, votes, pairs) == (0, 0, 0) and np.isnan(ratio)


def test_field_times_put_the_second_field_half_a_frame_later():
    from heartcv.measure_data import field_times

    np.testing.assert_allclose(field_times([0.0, 0.04, 0.1]), [0.0, 0.02, 0.04, 0.07, 0.1, 0.13])
    for bad in ([0.0], [0.0, 0.0], [0.1, 0.0]):
        with pytest.raises(ValueError, match="times"):
            field_times(bad)

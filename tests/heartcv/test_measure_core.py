"""heartcv.measure.Measurer on the synthetic trinocular sequence (tests/heartcv/synthetic_scene.py): a gently curved
textured cap translating by ~1 mm per frame, 2 grey levels of image noise, 8 frames at 480x270; positions against
the exact material points, covariances against an independent Jacobian propagation, the pooled pixel sigma against
the true pixel errors, and a dark occluder in one camera for three frames.

Error unit: an observation's 3-D error divided by ``sqrt(trace(C / sigma_px^2))`` -- the 3-D RMS error that one
pixel of isotropic image noise causes at that point with its views (~0.5 mm per px on this rig at 1/4 scale) --
is the error in *pixel equivalents*. The budget: matching at birth <= 0.05 px (test_matching), template LK
<= 0.02 px (test_klt), and the image noise."""

import numpy as np
import pytest

from heartcv.measure import MeasureOptions, Measurer

from .synthetic_scene import Occluder, translating_scene

NOISE = 2.0                       # grey levels
OCCLUDED_FRAMES = (2, 3, 4)


@pytest.fixture(scope="module")
def scene():
    return translating_scene(8, radius_m=1.0)


@pytest.fixture(scope="module")
def frames(scene):
    rng = np.random.default_rng(2024)
    return [scene.render_frame(k, noise=NOISE, rng=rng) for k in range(scene.n_frames)]


@pytest.fixture(scope="module")
def occluder(scene):
    """A 22 px dark disk in camera 1 over the surface point 5 mm from the apex (where it is in frame 3)."""
    centre = scene.cameras[1].project(scene.position(np.array([[0.004, 0.003, 0.0]]), 3))[0]
    return Occluder(1, tuple(centre), 22.0, OCCLUDED_FRAMES)


def _measure(scene, frames):
    m = Measurer(scene.cameras, MeasureOptions(max_points=40, min_distance_px=10), roi=scene.cap_mask(0, 0, 0.02))
    for k, images in enumerate(frames):
        m.step(k, images)
    return m.result()


def _truth(scene, r):
    """True positions (K, P, 3) of the tracks' material points: the ray of each track's reference pixel in its
    birth frame, cast onto the surface, followed through the frames."""
    P = len(r.point_ids)
    uv_birth = r.uv[r.birth_frame, np.arange(P), 0].astype(float)
    assert np.isfinite(uv_birth).all()                       # the reference view is used at birth
    m = np.array([scene.material_point(0, uv_birth[p:p + 1], r.birth_frame[p])[0] for p in range(P)])
    assert np.isfinite(m).all()
    return np.stack([scene.position(m, k) for k in range(scene.n_frames)])


@pytest.fixture(scope="module")
def clean(scene, frames):
    r = _measure(scene, frames)
    return r, _truth(scene, r)


@pytest.fixture(scope="module")
def occluded(scene, frames, occluder):
    painted = [[occluder.paint(im, c, k) for c, im in enumerate(images)] for k, images in enumerate(frames)]
    r = _measure(scene, painted)
    return r, _truth(scene, r)


def _px_equivalent(r, err):
    """Errors (K, P, 3) of the seen observations in pixel equivalents (module docstring), flat."""
    seen = r.seen
    unit = r.covariances[seen] / r.sigma_px ** 2
    return np.linalg.norm(err[seen], axis=1) / np.sqrt(np.trace(unit, axis1=1, axis2=2))


def _px_equivalent_errors(r, X_true):
    return _px_equivalent(r, r.positions - X_true)


def test_tracks_bookkeeping(clean, scene):
    r, _ = clean
    K, P = len(r.frames), len(r.point_ids)
    assert np.array_equal(r.frames, np.arange(scene.n_frames))
    assert P >= 25 and np.array_equal(r.point_ids, np.arange(P))            # unique, in order of birth
    assert np.array_equal(r.birth_frame, np.zeros(P, int))                  # all born in frame 0, none lost
    # every point seen in every frame; at most one view in 100 left out by the noise-adaptive photometric gate (a
    # weakly textured patch in 2 grey levels of noise; measured: 1 of 816)
    assert r.seen.all() and (r.views >= 2).all() and (r.views == 3).mean() >= 0.99
    assert sum(r.rejected.values()) == r.rejected["photometric"] == (r.views < 3).sum()
    assert r.positions.shape == (K, P, 3) and r.covariances.shape == (K, P, 3, 3) and r.uv.shape == (K, P, 3, 2)
    assert np.array_equal(r.reference, r.positions[r.birth_frame, np.arange(P)])
    assert (r.reprojection_rms[r.seen] <= 1.0).all() and not r.problems


def test_positions_match_the_truth(clean):
    r, X_true = clean
    e = _px_equivalent_errors(r, X_true)
    # measured: RMS 0.024 px, max 0.047 px (12 um RMS, 23 um at most)
    assert np.sqrt(np.mean(e ** 2)) < 0.05
    assert e.max() < 0.1
    # the displacements from the reference positions (a track's birth matching error cancels): measured max 0.037
    d = (r.positions - r.reference[None]) - (X_true - X_true[r.birth_frame, np.arange(len(r.point_ids))][None])
    assert _px_equivalent(r, d).max() < 0.08


def test_covariances_are_the_propagated_pixel_noise(clean, scene):
    r, _ = clean
    C = r.covariances[r.seen]
    assert np.abs(C - np.swapaxes(C, 1, 2)).max() <= 1e-12 * np.abs(C).max()
    assert (np.linalg.eigvalsh(C) > 0).all()
    # independent propagation: sigma^2 (sum over used views of J_c^T J_c)^-1, J_c from Camera.project
    for k in (0, 5):
        for p in range(0, len(r.point_ids), 7):
            JtJ = np.zeros((3, 3))
            for c, cam in enumerate(scene.cameras):
                if np.isfinite(r.uv[k, p, c, 0]):
                    _, J = cam.project(r.positions[k, p], jacobian=True)
                    JtJ += J[0].T @ J[0]
            want = r.sigma_px ** 2 * np.linalg.inv(JtJ)
            assert np.abs(r.covariances[k, p] - want).max() < 1e-6 * np.abs(want).max()


def test_pixel_sigma_matches_the_true_pixel_errors(clean, scene):
    """The pooled sigma_px against the RMS per coordinate of the used views' errors (measured pixel minus the
    true point's projection), leaving out the reference view in the birth frame, exact by construction."""
    r, X_true = clean
    assert r.sigma_estimated and r.sigma_px >= 0.01
    err = []
    for k in range(len(r.frames)):
        for c, cam in enumerate(scene.cameras):
            used = np.isfinite(r.uv[k, :, c, 0]) & ~((c == 0) & (r.birth_frame == k))
            err.append((r.uv[k, used, c] - cam.project(X_true[k, used])).ravel())
    true_sigma = np.sqrt(np.mean(np.concatenate(err) ** 2))
    # measured: 0.015 px estimated, 0.02 px true; mean NEES per dof ~2
    assert 0.5 < r.sigma_px / true_sigma < 2.0
    # and the covariances describe the 3-D errors: mean NEES per degree of freedom within a factor 4 of 1
    seen = r.seen
    e = (r.positions - X_true)[seen]
    nees = np.einsum("ni,ni->n", e, np.linalg.solve(r.covariances[seen], e[..., None])[..., 0])
    assert 0.25 < nees.mean() / 3 < 4.0


def test_an_occluder_hides_views_until_it_leaves(occluded, occluder, scene):
    r, X_true = occluded
    cam1 = scene.cameras[1]
    K, P = len(r.frames), len(r.point_ids)
    hidden = np.zeros((K, P), bool)
    for k in range(K):
        hidden[k] = occluder.hides(1, k, cam1.project(X_true[k]))
    assert hidden[list(OCCLUDED_FRAMES)].any(axis=0).sum() >= 4           # the disk covers several tracks
    # no camera-1 observation of a hidden point, and none on the disk at all
    assert np.isnan(r.uv[..., 1, 0][hidden]).all()
    for k in OCCLUDED_FRAMES:
        u = r.uv[k, :, 1].astype(float)
        on = np.isfinite(u[:, 0])
        assert not occluder.hides(1, k, u[on]).any()
    # the hidden points stay measured from cameras 0 and 2, accurately (measured: RMS 0.038 px, max 0.182 px with the
    # default high-pass prefilter, which doubles the noise the tracker sees; 0.025 / 0.117 px on raw gray)
    assert r.seen[hidden].all() and (r.views[hidden] == 2).all()
    e = _px_equivalent_errors(r, X_true)
    assert np.sqrt(np.mean(e ** 2)) < 0.05 and e.max() < 0.25
    # after the occluder leaves, every track is seen by camera 1 again
    after = [k for k in range(K) if k > max(OCCLUDED_FRAMES)]
    assert np.isfinite(r.uv[after, :, 1, 0]).all() and (r.views[after] == 3).all()
    # before it comes, nothing is missing
    assert (r.views[:min(OCCLUDED_FRAMES)] == 3).all()


# -- the frame loop (heartcv.measure.measure_sequence) -----------------------------------------------------------------
def _stream(frames, drop=()):
    """(k, images, problems) per instant, as heartcv.io.FrameReader yields them; ``drop``: (k, c) left out."""
    for k, images in enumerate(frames):
        images = [None if (k, c) in drop else im for c, im in enumerate(images)]
        yield k, images, [f"frame {k} camera {c}: dropped" for c in range(len(images)) if (k, c) in drop]


def test_measure_sequence_is_the_measurer_loop(scene, frames, clean):
    """The same result as feeding the Measurer by hand, one FrameStats per instant."""
    from heartcv.measure import measure_sequence

    ticks = iter(range(1000))
    run = measure_sequence(_stream(frames), scene.cameras, MeasureOptions(max_points=40, min_distance_px=10),
                           roi=scene.cap_mask(0, 0, 0.02), clock=lambda: float(next(ticks)))
    r, _ = clean
    for name in ("frames", "point_ids", "birth_frame", "positions", "covariances", "views"):
        np.testing.assert_array_equal(getattr(run.result, name), getattr(r, name))
    assert run.result.sigma_px == r.sigma_px
    assert [f.frame for f in run.frames] == list(range(scene.n_frames)) and run.problems == () and run.skipped == []
    assert [f.detected for f in run.frames] == [True] + [False] * (scene.n_frames - 1)
    assert [f.seen for f in run.frames] == [len(r.point_ids)] * scene.n_frames
    # the fake clock ticks once per call: set-up 1 tick; per instant 2 ticks waiting (before and after next()),
    # 3 in all since the end of the previous one
    assert run.setup_s == 1.0 and run.wait_s == scene.n_frames * 1.0
    assert all(f.total_s == 3.0 and f.wait_s == 1.0 for f in run.frames)


def test_measure_sequence_skips_instants_with_fewer_than_two_images(scene, frames):
    from heartcv.measure import measure_sequence

    drop = {(3, 0), (3, 2), (5, 1)}
    run = measure_sequence(_stream(frames, drop), scene.cameras, MeasureOptions(max_points=40, min_distance_px=10),
                           roi=scene.cap_mask(0, 0, 0.02))
    assert run.skipped == [3]
    assert run.problems == ((3, "frame 3 camera 0: dropped"), (3, "frame 3 camera 2: dropped"),
                            (5, "frame 5 camera 1: dropped"))
    r = run.result
    assert not r.seen[3].any() and r.problems == ["frame 3: fewer than two readable images"]
    assert r.seen[5].sum() == r.seen[4].sum() and (r.views[5][r.seen[5]] == 2).all()


def _run_repeats(scene, frames, **kw):
    from heartcv.measure import measure_sequence

    return measure_sequence(_stream(frames), scene.cameras, MeasureOptions(max_points=40, min_distance_px=10),
                            roi=scene.cap_mask(0, 0, 0.02), **kw)


def test_a_repeated_instant_is_empty_and_a_camera_out_of_step_is_left_out(scene, frames):
    """Images that repeat their camera's previous one (heartcv.measure.RepeatedViews) are left out as missing;
    kept (drop_repeats=False), the repeated instant says the surface stood still."""
    seq = [list(f) for f in frames]
    seq[4] = list(seq[3])                                  # every camera repeats frame 3
    seq[6][1] = seq[5][1]                                  # camera 1 alone repeats frame 5
    run = _run_repeats(scene, seq)
    assert run.repeated == ((4, 0), (4, 1), (4, 2), (6, 1))
    assert run.skipped == [4]
    r = run.result
    assert not r.seen[4].any()
    assert any("frame 4: fewer than two readable images (views repeating their previous image left out" in p
               for p in r.problems)
    assert r.seen[6].sum() >= r.seen[5].sum() // 2 >= 1
    assert (r.views[6][r.seen[6]] == 2).all() and np.isnan(r.uv[6][r.seen[6]][:, 1]).all()
    kept = _run_repeats(scene, seq, drop_repeats=False)
    assert kept.repeated == () and kept.skipped == [] and kept.result.seen[4].sum() >= 1
    # kept, the repeated instant says the surface stood still for a frame (it moves about 1 mm a frame)
    k = kept.result
    stood = np.linalg.norm(k.positions[4] - k.positions[3], axis=1)[k.seen[3] & k.seen[4]]
    moved = np.linalg.norm(k.positions[3] - k.positions[2], axis=1)[k.seen[2] & k.seen[3]]
    assert np.median(stood) < 0.05 * np.median(moved)


def test_moving_frames_are_not_repeats(scene, frames):
    run = _run_repeats(scene, frames)
    plain = _run_repeats(scene, frames, drop_repeats=False)
    assert run.repeated == () and run.skipped == []
    np.testing.assert_array_equal(run.result.positions, plain.result.positions)


def test_measure_sequence_failures(scene, frames):
    from heartcv.measure import MeasureFailed, measure_sequence
    from heartcv.tracker.files import InputError

    opts = MeasureOptions(max_points=40, min_distance_px=10)
    with pytest.raises(InputError, match=r"^images: none of the reference camera's frames 0, 3, \.\.\. can be read"):
        measure_sequence(_stream(frames), scene.cameras, opts, roi_frames=[])
    black = np.zeros_like(frames[0][0])
    with pytest.raises(MeasureFailed, match="automatic region of interest: no tissue region found.*Pass --mask"):
        measure_sequence(_stream(frames), scene.cameras, opts, roi_frames=[black, black])
    corner = np.zeros(black.shape, bool)
    corner[:20, :20] = True                                     # the black background: nothing to track
    with pytest.raises(MeasureFailed, match=r"no surface point could be tracked \(region of interest 400 px in "):
        measure_sequence(_stream(frames), scene.cameras, opts, roi=corner)


def test_reference_frames_reads_every_third_of_the_first_30():
    from heartcv.measure import reference_frames

    asked = []

    def read(k):
        asked.append(k)
        return [None if k == 6 else np.full((2, 2), k, np.uint8), None], []

    got = reference_frames(read, 20, 0)
    assert asked == [0, 3, 6, 9, 12, 15, 18]
    assert [int(im[0, 0]) for im in got] == [0, 3, 9, 12, 15, 18]
    assert len(reference_frames(read, 100, 0)) == 9 and reference_frames(read, 100, 1) == []


# -- frame times, inputs, truth, CSV (heartcv.measure_data) ------------------------------------------------------------
def test_frame_times_and_units():
    from heartcv.measure_data import frame_times, split_unit

    np.testing.assert_array_equal(frame_times(3, timestamps=[0.0, 0.5, 0.75, 1.0]), [0.0, 0.5, 0.75])
    np.testing.assert_array_equal(frame_times(3, fps=4.0, video_fps=25.0), [0.0, 0.25, 0.5])
    np.testing.assert_array_equal(frame_times(3, video_fps=25.0), [0.0, 0.04, 0.08])
    np.testing.assert_array_equal(frame_times(2), [0.0, 1 / 30])
    assert split_unit("pressure_mmhg") == ("pressure", "Pa", 133.322387415)
    assert split_unit("Pressure_KPa") == ("Pressure", "Pa", 1e3)
    assert split_unit("shift_mm") == ("shift", "m", 1e-3)
    assert split_unit("tension") == ("tension", "", 1.0)


def test_inputs_at_frames_interpolates_in_si_units():
    from heartcv.measure_data import inputs_at_frames

    cols = {"time_s": np.array([0.0, 1.0, 2.0]), "pressure_mmhg": np.array([0.0, 10.0, 30.0]),
            "x_mm": np.array([1.0, 1.0, 3.0])}
    names, units, values = inputs_at_frames(cols, np.array([0.5, 1.5, 2.0]))
    assert names == ("pressure", "x") and units == ("Pa", "m")
    np.testing.assert_allclose(values, [[5 * 133.322387415, 1e-3], [20 * 133.322387415, 2e-3],
                                        [30 * 133.322387415, 3e-3]], rtol=1e-15)
    names, units, values = inputs_at_frames({"time_s": np.array([0.0, 1.0])}, np.array([0.0, 1.0]))
    assert names == () and values.shape == (2, 0)


@pytest.mark.parametrize("cols, message", [
    ({"p_pa": np.zeros(3)}, "time_s: a 'time_s' column expected, got ['p_pa']"),
    ({"time_s": np.array([0.0, 1.0, 1.0])}, "time_s: at least two finite, strictly increasing values expected"),
    ({"time_s": np.array([0.0])}, "time_s: at least two finite, strictly increasing values expected"),
    ({"time_s": np.array([0.0, 0.1])}, "time_s: the inputs cover 0..0.1 s, the frames 0..1 s"),
    ({"time_s": np.array([0.0, 1.0]), "p_pa": np.array([1.0, np.nan])}, "column 'p_pa': non-finite values"),
    ({"time_s": np.array([0.0, 1.0]), "pressure": np.array([80.0, 120.0])},
     "column 'pressure': a pressure column needs its unit in its name: pressure_mmhg, pressure_kpa or pressure_pa "
     "(without one it would be read as pascals)"),
    ({"time_s": np.array([0.0, 1.0]), "Pressure_psi": np.array([1.5, 2.3])},
     "column 'Pressure_psi': a pressure column needs its unit in its name: pressure_mmhg, pressure_kpa or "
     "pressure_pa (without one it would be read as pascals)"),
    # the model's other inputs likewise (a breathing column in mm was read as metres: 1000 x too large)
    ({"time_s": np.array([0.0, 1.0]), "respiration_x": np.array([1.0, 2.0])},
     "column 'respiration_x': a respiration column needs its unit in its name: respiration_x_mm or respiration_x_m "
     "(without one it would be read as metres)"),
    ({"time_s": np.array([0.0, 1.0]), "active_tension": np.array([1.0, 2.0])},
     "column 'active_tension': an active tension column needs its unit in its name: active_tension_kpa or "
     "active_tension_pa (without one it would be read as pascals)"),
    ({"time_s": np.array([0.0, 1.0]), "respiration_y_kpa": np.array([1.0, 2.0])},
     "column 'respiration_y_kpa': a respiration column in Pa: metres expected (_m, _mm)"),
    ({"time_s": np.array([0.0, 1.0]), "pressure_mm": np.array([1.0, 2.0])},
     "column 'pressure_mm': a load column in m: pascals expected (_pa, _kpa, _mmhg)"),
    ({"time_s": np.array([0.0, 1.0]), "pressure_mmhg": np.array([80.0, 90.0]), "pressure_kpa": np.ones(2)},
     "column 'pressure_kpa': input 'pressure' given twice (as 'pressure_kpa' and an earlier column): one column "
     "per input"),
])
def test_inputs_at_frames_refuses(cols, message):
    from heartcv.measure_data import inputs_at_frames
    from heartcv.tracker.files import InputError

    with pytest.raises(InputError) as info:
        inputs_at_frames(cols, np.array([0.0, 1.0]))
    assert str(info.value) == message and info.value.path is None
    assert str(info.value.in_file("in.csv")) == f"in.csv: {message}"


def test_reference_pixels_project_a_point_born_without_the_reference_view():
    """Each point's reference-camera pixel in its birth frame, for the measurement file's ``reference_uv``: the
    observed pixel, and for a point whose reference view the robust triangulation left out at birth (NaN there; a
    rendered noisy 3-camera scene made ``measure`` fail writing NaN to the file's metadata) the projection of its
    reference position, finite."""
    from types import SimpleNamespace

    from heartcv.camera import Camera
    from heartcv.measure_data import reference_pixels

    cam = Camera("c0", 640, 480, np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]), np.zeros(5), np.eye(4))
    X = np.array([[0.01, -0.005, 0.2], [-0.02, 0.01, 0.25], [0.0, 0.0, 0.3]])
    K, P, C = 3, 3, 2
    uv = np.full((K, P, C, 2), np.nan, np.float32)
    birth = np.array([0, 1, 2])
    for p in range(P):
        uv[birth[p]:, p, 0] = cam.project(X[p][None])[0] + 0.25          # observed, a quarter pixel off
    uv[2, 2, 0] = np.nan                                                 # point 2: no reference view at birth
    uv[2, 2, 1] = [10.0, 20.0]
    res = SimpleNamespace(point_ids=np.arange(P), uv=uv, birth_frame=birth, reference=X)
    got = reference_pixels(res, cam, 0)
    np.testing.assert_allclose(got[:2], cam.project(X[:2]) + 0.25, atol=1e-4)
    np.testing.assert_allclose(got[2], cam.project(X[2:])[0], atol=1e-9)
    assert np.isfinite(got).all()


def test_check_image_sizes_names_the_image_and_both_sizes():
    from heartcv.camera import Camera
    from heartcv.measure_data import check_image_sizes
    from heartcv.tracker.files import InputError

    cams = [Camera(f"c{i}", 4, 3, np.diag([1.0, 1.0, 1.0]), np.zeros(5), np.eye(4)) for i in range(2)]
    good, wide = np.zeros((3, 4), np.uint8), np.zeros((3, 5), np.uint8)
    frames = {0: [None, wide], 1: [good, good]}
    with pytest.raises(InputError) as info:
        check_image_sizes(cams, lambda k: (frames[k], []), 2, lambda c, k: f"cam{c}/{k}.png")
    assert str(info.value) == ("cam1/0.png: image is 5x3 px, but the rig's camera c1 is 4x3: the rig does not "
                               "belong to these images")
    with pytest.raises(InputError, match=r"^images: none of the 2 images of camera c0 can be read$"):
        check_image_sizes(cams, lambda k: ([None, good], []), 2, lambda c, k: "x")
    # only each camera's first readable image is compared (isolated odd images are left out while measuring)
    frames = {0: [None, good], 1: [good, wide]}
    assert check_image_sizes(cams, lambda k: (frames[k], []), 2, lambda c, k: "x") is None


def test_truth_for_frames():
    from heartcv.measure_data import truth_for_frames
    from heartcv.tracker.files import InputError

    arrays = {"vertex_positions": np.zeros((5, 4, 3)), "instrument_mask": np.ones((5, 2, 3, 1), np.uint8),
              "faces": np.zeros((1, 3), int)}
    meta = {"kind": "sequence", "camera_names": ["a", "b"]}
    out = truth_for_frames(arrays, meta, 3, ["a", "b"])
    assert out["vertex_positions"].shape == (3, 4, 3) and out["instrument_mask"].shape == (3, 2, 3, 1)
    assert out["faces"] is arrays["faces"] and arrays["vertex_positions"].shape == (5, 4, 3)
    for bad_meta, count, names, message in [
        ({"kind": "calibration"}, 3, ["a", "b"], "meta.kind: a sequence truth expected, got kind 'calibration'"),
        (meta, 6, ["a", "b"], "vertex_positions: 5 frames of truth for 6 measured"),
        (meta, 3, ["a", "c"], "meta.camera_names: cameras ['a', 'b'] differ from the rig's ['a', 'c']"),
    ]:
        with pytest.raises(InputError) as info:
            truth_for_frames(arrays, bad_meta, count, names)
        assert str(info.value) == message


def test_measurement_csv_lines():
    from heartcv.measure_data import measurement_csv_lines
    from heartcv.tracker.measurements import MeasurementSet

    pos = np.full((2, 2, 3), np.nan)
    pos[0, 1] = [1.0, 2.0, 3.0]
    pos[1, 0] = [0.5, 0.25, 0.125]
    cov = np.full((2, 2, 3, 3), np.nan)
    cov[0, 1] = cov[1, 0] = np.array([[4.0, 1.0, 1.0], [1.0, 5.0, 2.0], [1.0, 2.0, 6.0]])
    mset = MeasurementSet(times=np.array([0.0, 0.5]), point_ids=np.array([7, 9]), positions=pos, covariances=cov,
                          reference=np.array([[0.5, 0.25, 0.125], [1.0, 2.0, 3.0]]), inputs=np.zeros((2, 0)),
                          views=np.array([[0, 2], [2, 0]]), reprojection_rms=np.array([[np.nan, 0.25], [0.5, np.nan]]))
    uv = np.full((2, 2, 2, 2), np.nan)
    uv[0, 1] = [[10.0, 11.0], [12.0, 13.0]]
    uv[1, 0, 1] = [1.5, 2.5]
    lines = measurement_csv_lines(mset, uv, ["L", "R"])
    assert lines == [
        "# heartcv measure: tracked points in the rig frame (docs/formats.md, measurement CSV)",
        "frame,time_s,point_id,x_m,y_m,z_m,cxx_m2,cxy_m2,cxz_m2,cyy_m2,cyz_m2,czz_m2,views,reprojection_rms_px,"
        "u_L_px,v_L_px,u_R_px,v_R_px",
        "0,0.0,9,1.0,2.0,3.0,4.0,1.0,1.0,5.0,2.0,6.0,2,0.25,10.0,11.0,12.0,13.0",
        "1,0.5,7,0.5,0.25,0.125,4.0,1.0,1.0,5.0,2.0,6.0,2,0.5,,,1.5,2.5",
    ]


def test_frame_grid_puts_jittered_and_dropped_frames_on_their_points():
    """frame_grid against the truth it was drawn from: 29.97 fps (an interval of 33.3667 ms, not a whole number of
    ms) over 1 000 frames with frames 50, 51 and 700 dropped, each time jittered by up to 4 ms and rounded to 1 ms
    (what capture software logs): every frame on its own grid point, the interval within 1e-6 s, the grid's
    points within 1 ms of the true times, the offsets the jitter over the interval (to 0.6 ms). Equally spaced
    times read as uniform (uniform_times), jittered ones not. Two frames less than half an interval apart, or one
    0.4 of an interval off the grid, are refused naming the frame; expand_to_grid fills the dropped rows."""
    from heartcv.measure_data import GRID_TOLERANCE, expand_to_grid, frame_grid, uniform_times

    rng = np.random.default_rng(3)
    dt = 1 / 29.97
    true_index = np.delete(np.arange(1000), [50, 51, 700])
    exact = true_index * dt
    jitter = rng.uniform(-0.004, 0.004, exact.size)
    t = np.round(exact + jitter, 3)
    index, grid, got_dt, offset = frame_grid(t)
    np.testing.assert_array_equal(index, true_index)
    assert abs(got_dt - dt) < 1e-6 and grid.size == 1000
    np.testing.assert_allclose(grid, np.arange(1000) * dt, atol=1e-3)
    np.testing.assert_allclose(offset * got_dt, t - grid[index], atol=1e-12)
    np.testing.assert_allclose(offset * got_dt, t - exact, atol=3e-4)          # the jitter and the rounding
    assert np.abs(offset).max() < GRID_TOLERANCE
    assert uniform_times(np.arange(10) * 0.04) and uniform_times([0.0]) and not uniform_times(t[:10])
    with pytest.raises(ValueError, match="frames 3 and 4"):
        frame_grid([0.0, 0.04, 0.08, 0.12, 0.13, 0.16, 0.2])
    with pytest.raises(ValueError, match="frame 3 .* of an interval from a uniform grid"):
        frame_grid(np.r_[np.arange(3) * 0.04, 3 * 0.04 + 0.4 * 0.04, np.arange(4, 12) * 0.04])
    v = np.arange(6.0).reshape(3, 2)
    np.testing.assert_array_equal(expand_to_grid(v, [0, 2, 3], 5, np.nan),
                                  [[0, 1], [np.nan, np.nan], [2, 3], [4, 5], [np.nan, np.nan]])


def test_container_times_are_used_only_where_the_stated_rate_does_not_hold():
    """container_times: a video's own times rounded by its container (25 fps, times to the millisecond, off k/25
    by under 0.5 ms) are not used (None: the stated rate describes the frames); a variable rate or a dropped frame
    (a frame half an interval or more off k / fps) is, from 0; without a stated rate they are; without times None."""
    from heartcv.measure_data import container_times

    k = np.arange(50)
    assert container_times(np.round(2.0 + k / 25.0, 3), 25.0, 50) is None
    dropped = np.r_[k[:20], k[21:51]] / 25.0 + 2.0
    np.testing.assert_allclose(container_times(dropped, 25.0, 40), dropped[:40] - 2.0)
    vfr = 2.0 + np.cumsum(np.r_[0.0, np.full(49, 1 / 30.0)])
    np.testing.assert_allclose(container_times(vfr, 25.0, 50), vfr - 2.0)
    np.testing.assert_allclose(container_times(np.round(k / 25.0, 3), None, 10), np.round(k / 25.0, 3)[:10])
    assert container_times(None, 25.0, 50) is None


def test_rectified_v_offsets_per_track_median():
    """rectified_v_offsets on 400 tracks of 30 frames: each track's views offset by 0.45 px plus a constant of its
    own (sd 0.2 px: its template) plus per-frame noise, some frames unseen: the median over the tracks' medians is
    0.45 within 3 of its standard errors, the standard error 1.4826 MAD / sqrt(400) of the track medians (about
    0.2 / 20); the reference camera (0, 0, 0); a camera seen with the reference in fewer than 3 tracks NaN."""
    from heartcv.measure_data import rectified_v_offsets

    rng = np.random.default_rng(7)
    K, P = 30, 400
    uv = np.full((K, P, 3, 2), np.nan)
    uv[:, :, 0] = rng.uniform(0, 300, (K, P, 2))
    track = rng.normal(0, 0.2, P)
    uv[:, :, 1] = uv[:, :, 0] + np.stack([-50 + 0 * track, 0.45 + track], axis=-1)[None]
    uv[:, :, 1, 1] += rng.normal(0, 0.1, (K, P))
    uv[rng.random((K, P)) < 0.3, 1] = np.nan
    uv[:, :2, 2] = uv[:, :2, 0]
    (o0, s0, n0), (o1, s1, n1), (o2, s2, n2) = rectified_v_offsets(uv, 0)
    assert (o0, s0, n0) == (0.0, 0.0, 0) and n1 == P and n2 == 2 and np.isnan(o2) and np.isnan(s2)
    per = np.nanmedian(uv[:, :, 1, 1] - uv[:, :, 0, 1], axis=0)
    assert o1 == pytest.approx(np.median(per)) and s1 == pytest.approx(1.4826 * np.median(np.abs(per - o1)) / 20)
    assert abs(o1 - 0.45) < 3 * s1 and 0.005 < s1 < 0.02


def test_rectified_cameras_moves_only_significant_offsets():
    """rectified_cameras: a camera whose measured offset differs from the rig's cy difference by more than 3
    standard errors gets cy = cy_ref + offset, others keep theirs; with ``among`` exactly those move; the
    reference never."""
    from heartcv.camera import Camera
    from heartcv.measure_data import rectified_cameras

    K = np.array([[390.0, 0, 179.5], [0, 390.0, 143.5], [0, 0, 1]])
    K2 = K.copy()
    K2[1, 2] = 143.9
    cams = [Camera("a", 360, 288, K), Camera("b", 360, 288, K), Camera("c", 360, 288, K2)]
    offsets = [(0.0, 0.0, 0), (0.45, 0.01, 300), (0.42, 0.01, 300)]     # c: 0.42 against the rig's 0.4
    out, moved = rectified_cameras(cams, offsets, 0)
    assert moved == [1] and out[1].K[1, 2] == pytest.approx(143.95) and out[2] is cams[2] and out[0] is cams[0]
    out, moved = rectified_cameras(cams, offsets, 0, among=[2])
    assert moved == [2] and out[2].K[1, 2] == pytest.approx(143.92) and out[1] is cams[1]


def test_field_order_clear_is_a_sign_test():
    """field_order_clear: one-sided binomial sign test at 5 % (9 of 10: p = 0.011; 8 of 10: 0.055)."""
    from heartcv.measure import field_order_clear

    assert field_order_clear(9, 10) and not field_order_clear(8, 10)
    assert field_order_clear(23, 28) and not field_order_clear(4, 4) and not field_order_clear(0, 0)

"""The renderer (heartcv/render): scene validation, the rig, the phantom mesh and its motion, ray casting, texture,
shading, noise, the instrument and calibration renders. Small images: the default rig with image size and focal
length in pixels divided by a scale factor (same field of view)."""

from dataclasses import replace
import math

import numpy as np
import pytest
import scipy.sparse as sp

from heartcv.render.scene import SceneError, build_rig, ring_poses, scene_from_dict
from tests.heartcv.render_scenes import scene_dict, write_truth_model


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    return write_truth_model(tmp_path_factory.mktemp("render") / "truth.yaml")


@pytest.fixture(scope="module")
def model_config(model_file):
    from heartcv.tracker.io import read_model

    return read_model(model_file)


def _prepare(model_config, model_file, **sections):
    from heartcv.render.sequence import prepare_sequence

    return prepare_sequence(scene_from_dict(scene_dict(model_file, **sections)), model_config)


@pytest.fixture(scope="module")
def setup(model_config, model_file):
    """Scale 4, an instrument present from frame 3 on, seeded."""
    return _prepare(model_config, model_file,
                    instrument={"enabled": True, "window_s": [0.1, 1.0], "enter_s": 0.0, "travel_m": 0.0})


# -- scene file ---------------------------------------------------------------------------------------------------
def test_default_rig_matches_design():
    """docs/design.md §7: three cameras 0.5 m apart on a triangle, f = 35 mm / 5.86 um, 1920x1080, converging on the
    heart 0.53 m from the cameras' plane (about 29 deg off axis); the world frame is camera 0's."""
    scene = scene_from_dict({"motion": {"model": "m.yaml"}})
    rig = build_rig(scene.rig)
    assert rig.names == ["cam0", "cam1", "cam2"]
    assert rig[0].K[0, 0] == pytest.approx(35e-3 / 5.86e-6) and (rig[0].width, rig[0].height) == (1920, 1080)
    assert np.allclose(list(rig.baselines().values()), 0.5, atol=1e-12)
    assert np.allclose(rig[0].cam_from_rig, np.eye(4), atol=1e-12)
    C = scene.convergence_point
    for cam in rig.cameras:
        assert np.allclose(cam.project(C), cam.K[:2, 2], atol=1e-9)  # principal point
    world_from_ring, _ = ring_poses(scene.rig)
    axis = world_from_ring[:3, 2]
    off = [math.degrees(math.acos(np.dot(axis, cam.R[2]))) for cam in rig.cameras]
    assert np.allclose(off, math.degrees(math.atan(0.5 / math.sqrt(3) / 0.53)), atol=1e-9)  # 28.6 deg


@pytest.mark.parametrize("patch, field", [
    ({"phantom": {"texture": {"vesels": 3}}}, "phantom.texture.vesels"),
    ({"rig": {"cameras": 0}}, "rig.cameras"),
    ({"rig": {"image_size": [640]}}, "rig.image_size"),
    ({"noise": {"bits": 12}}, "noise.bits"),
    ({"motion": {"duration_s": -1}}, "motion.duration_s"),
    ({"motion": {"model": None}}, "motion.model"),
    ({"instrument": {"window_s": [2.0, 1.0]}}, "instrument.window_s"),
    ({"phantom": {"world_from_patch": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}},
     "phantom.world_from_patch"),
    ({"lighting": {"kind": "sun"}}, "lighting.kind"),
    ({"surprise": 1}, "surprise"),
    # hardened: huge integers, NaN, ragged or non-numeric matrices, mixed key types, size caps
    ({"rig": {"working_distance_m": 10**400}}, "rig.working_distance_m"),
    ({"seed": 10**30}, "seed"),
    ({"seed": 1.5}, "seed"),
    ({"rig": {"distortion": [10**60, 0, 0, 0]}}, "rig.distortion"),
    ({"rig": {"image_size": [20000, 20000]}}, "rig.image_size"),
    ({"rig": {"per_camera": [{"focal_mm": float("nan")}]}}, "rig.per_camera[0].focal_mm"),
    ({"phantom": {"world_from_patch": [[1, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}},
     "phantom.world_from_patch"),
    ({"phantom": {"world_from_patch": [["a", 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}},
     "phantom.world_from_patch"),
    ({"phantom": {"world_from_patch": [[1, 0, 0, 1e300], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}},
     "phantom.world_from_patch"),
    ({"noise": {"bits": 8.0}}, "noise.bits"),
    ({"noise": {"bits": True}}, "noise.bits"),
    ({"motion_blur": {1: "a", "b": 2}}, "motion_blur.1"),
    ({"format_version": True}, "format_version"),
])
def test_scene_errors_name_the_field(patch, field):
    from heartcv.tracker.files import InputError

    d = {"motion": {"model": "m.yaml"}}
    for key, val in patch.items():
        d[key] = {**d.get(key, {}), **val} if isinstance(val, dict) else val
    with pytest.raises(SceneError) as err:
        scene_from_dict(d)
    assert isinstance(err.value, InputError) and err.value.path is None
    assert err.value.field == field and str(err.value).startswith(field + ": ")


@pytest.mark.parametrize("data", [[1, 2], "scene", 3])
def test_scene_document_must_be_a_mapping(data):
    with pytest.raises(SceneError, match="a mapping expected") as err:
        scene_from_dict(data)
    assert err.value.field is None


# -- phantom -----------------------------------------------------------------------------------------------------
def test_phantom_is_watertight_and_contains_the_patch():
    from heartcv.render.phantom import build_phantom, locate, surface_points
    from heartcv.render.scene import PhantomSpec
    from heartcv.tracker.geometry import PatchGeometry, build_mesh

    g = PatchGeometry(grid=(9, 4, 2))
    ph = build_phantom(g, PhantomSpec(mesh_edge_m=0.002))
    tm = ph.trimesh()
    assert tm.is_watertight and tm.is_winding_consistent and tm.volume > 0
    # patch vertices lie exactly on the model's epicardium, at their material coordinates
    s, t = ph.material[ph.in_patch].T
    assert np.abs(ph.vertices[ph.in_patch] - g.to_patch(s, t, 0.0)).max() == 0.0
    # every epicardial node of the model lies on the surface (up to the chord error of 2 mm triangles)
    mesh = build_mesh(g)
    nodes = mesh.param[mesh.epicardial_nodes]
    face, bary = locate(ph, nodes[:, :2])
    on = surface_points(ph, face, bary, ph.vertices)
    chord = 0.002**2 / (8 * g.radius_circ)
    assert np.linalg.norm(on - mesh.points[mesh.epicardial_nodes], axis=1).max() < 2 * chord
    # outward normal at the patch centre is the patch's +y
    centre = np.argmin(np.linalg.norm(ph.material, axis=1))
    assert np.allclose(ph.normals[centre], [0, 1, 0], atol=1e-9)


def test_surface_motion_is_continuous_at_the_patch_rim(model_config):
    """A random state: inside the patch the vertices follow the FE interpolation; across the rim the displacement
    has no jump (edge differences there are no larger than inside); the surface stays closed."""
    from heartcv.render.motion import surface_motion
    from heartcv.render.phantom import build_phantom
    from heartcv.render.scene import PhantomSpec
    from heartcv.tracker.model import build_model

    model = build_model(model_config)
    ph = build_phantom(model.mesh.geometry, PhantomSpec(mesh_edge_m=0.002))
    q = np.random.default_rng(0).standard_normal(model.r) * 1e-3
    truth = _static_truth(np.concatenate([q, 0 * q]))
    sm = surface_motion(ph, model, truth, np.eye(4), outside_motion_m=0.001)
    d = sm.displacement(0.0)
    U = model.node_displacements(np.concatenate([q, 0 * q]))
    S = model.shape_matrix(np.c_[ph.material[ph.in_patch], np.zeros(ph.in_patch.sum())])
    assert np.allclose(d[ph.in_patch], S @ U, atol=1e-15)
    edges = ph.trimesh().edges_unique
    jump = np.linalg.norm(d[edges[:, 0]] - d[edges[:, 1]], axis=1)
    length = np.linalg.norm(ph.vertices[edges[:, 0]] - ph.vertices[edges[:, 1]], axis=1)
    crossing = ph.in_patch[edges[:, 0]] != ph.in_patch[edges[:, 1]]
    inside = ph.in_patch[edges[:, 0]] & ph.in_patch[edges[:, 1]]
    assert (jump / length)[crossing].max() <= (jump / length)[inside].max()
    assert ph.trimesh(ph.vertices + d).is_watertight


def _static_truth(x):
    from heartcv.render.motion import TruthMotion

    return TruthMotion(np.zeros(1), np.array([0.0, 1.0]), np.stack([x, x]), np.zeros(1, int), np.zeros((1, 5)),
                       np.zeros((1, 1)), ("pressure",), np.zeros((0, 3)), np.zeros((1, 0, 3)), None,
                       lambda t: np.ones(np.atleast_1d(t).shape))


# -- truth motion -----------------------------------------------------------------------------------------------
def test_truth_equals_the_simulator(setup, model_config):
    """The rendered surface's patch vertices and the model points move exactly as tracker.simulate says, with
    the stiffness following the pressure."""
    from heartcv.tracker.simulate import InputSignals, input_signals, simulate

    truth, model, sm = setup.surface.truth, setup.model, setup.surface
    sig = input_signals(model)
    theta = truth.theta
    assert theta[:, 3].max() > 1.2 * model.config.theta[3] and np.allclose(theta[:, [0, 1, 2, 4]],
                                                                          model.config.theta[[0, 1, 2, 4]])
    p_max = sig.load(np.linspace(0, 3.0, 3001))[:, 0].max()  # three beats at 60 bpm

    def stiffness(t):  # E (1 + a p / p_max), a = 0.5 (the scene's stiffness_cycle)
        th = model.config.theta.copy()
        th[3] *= 1 + 0.5 * max(sig.load(np.atleast_1d(t))[0, 0], 0) / p_max
        return th

    sim = simulate(model, setup.frame_times[-1], np.random.default_rng(0), theta=stiffness,
                   signals=InputSignals(sig.names, sig.load, None), substeps=2, process_noise=False,
                   initial_noise=False)
    assert np.allclose(sim.theta, theta, rtol=1e-14)
    assert np.allclose(truth.point_positions, sim.positions, rtol=0, atol=1e-12)
    ph = sm.phantom
    S = model.shape_matrix(np.c_[ph.material[ph.in_patch], np.zeros(ph.in_patch.sum())])
    for k in (0, 3, setup.n_frames - 1):
        U = model.node_displacements(sim.states[k])
        expect = ph.vertices[ph.in_patch] + S @ U
        assert np.allclose(sm.positions_patch(setup.frame_times[k])[ph.in_patch], expect, rtol=0, atol=1e-12)
    assert np.linalg.norm(truth.point_positions - truth.point_positions[:1], axis=2).max() > 1e-4  # it moves


def test_sequence_truth_arrays(setup):
    from heartcv.render.sequence import inputs_table, sequence_truth

    arrays, meta = sequence_truth(setup)
    K, V = setup.n_frames, setup.surface.phantom.n_vertices
    assert arrays["vertex_positions"].shape == (K, V, 3) and arrays["faces"].shape[1] == 3
    T = arrays["world_from_patch"]
    X = setup.surface.positions_patch(setup.frame_times[2]) @ T[:3, :3].T + T[:3, 3]
    assert np.abs(arrays["vertex_positions"][2] - X).max() < 1e-7  # float32 of the world positions
    assert arrays["point_positions"].shape == (K, 20, 3) and meta["world_frame"] == "cam0"
    cols, vals = inputs_table(setup)
    assert cols == ["time_s", "pressure_pa"] and vals.shape == (K, 2)
    assert np.allclose(vals[:, 0], setup.frame_times)


# -- rendering ---------------------------------------------------------------------------------------------------
def test_render_is_deterministic_per_seed(setup):
    from heartcv.render.sequence import render_frame, render_sequence

    a = render_frame(setup, 1)
    b = render_frame(setup, 1)
    assert all(np.array_equal(x, y) for x, y in zip(a.images, b.images))
    other = replace(setup, scene=replace(setup.scene, seed=setup.scene.seed + 1))
    c = render_frame(other, 1)
    assert not np.array_equal(a.images[0], c.images[0])
    assert np.abs(a.images[0].astype(int) - c.images[0]).mean() < 3  # noise only
    par = list(render_sequence(setup, frames=[0, 1], workers=2))
    assert all(np.array_equal(x, y) for x, y in zip(par[1].images, a.images))


def test_instrument_mask_is_exactly_the_occluded_pixels(setup):
    """Noise-free, no blur: the pixels that change when the instrument is removed are its mask; it appears only
    inside its time window."""
    from heartcv.render.sequence import render_frame

    s = replace(setup, scene=replace(setup.scene, optics=replace(setup.scene.optics, psf_sigma_px=0.0)))
    k = 4
    with_i = render_frame(s, k, noise=False)
    without = render_frame(replace(s, instrument=None), k, noise=False)
    for c in range(len(s.rig)):
        changed = (with_i.images[c] != without.images[c]).any(axis=-1)
        mask = with_i.instrument_mask[c]
        assert mask.sum() > 50
        assert np.array_equal(changed & ~mask, np.zeros_like(mask))
        assert (changed | ~mask).mean() > 0.999 and (changed[mask]).mean() > 0.95
    early = render_frame(s, 1, noise=False)
    assert not early.instrument_mask.any()


def test_textured_point_projects_to_its_true_position(model_config, model_file):
    """Fiducial dots are drawn at known material coordinates on the moving surface. Each dot's image centroid
    lands on the centroid of its outline's projection (the outline's material points mapped to their true 3-D
    positions at that instant, then Camera.project): motion, material-coordinate texture lookup and rays
    together. (The outline centroid differs from the projected centre by the surface's curvature and facets,
    up to ~0.3 px here; 4x4 rays per pixel remove aliasing of the dots' sharp edges.)"""
    from heartcv.render.phantom import locate, surface_points
    from heartcv.render.sequence import render_frame

    radius = 0.001
    s = _prepare(model_config, model_file, rig={"distortion": [], "image_size": [960, 540],
                                                "pixel_pitch_m": 2 * 5.86e-6},
                 lighting={"specular": 0.0}, optics={"supersampling": 4},
                 phantom={"texture": {"vessels": 0, "fat": 0.0, "speckle": 0.0, "mottling": 0.0},
                          "fiducials": {"enabled": True, "spacing_m": 0.008, "radius_m": radius}},
                 motion={"respiration": {"amplitude_m": 0.003, "phase": 1.0}})
    ph = s.surface.phantom
    k = s.n_frames - 1
    V = s.surface.positions_world(s.frame_times[k])
    assert np.abs(s.surface.truth.shift(s.frame_times[k])).max() > 1e-3  # respiration moved the heart
    img = render_frame(s, k, noise=False).images
    ang = np.linspace(0, 2 * np.pi, 180, endpoint=False)
    errors, offsets = [], []
    for m0 in s.texture.fiducials:
        centre = surface_points(ph, *locate(ph, m0[None]), V)
        outline = surface_points(ph, *locate(ph, m0 + radius * np.c_[np.cos(ang), np.sin(ang)]), V)
        for c, cam in enumerate(s.rig.cameras):
            p = cam.project(centre)[0]
            q = cam.project(outline)
            if not cam.in_image(p, margin=20) or not _facing(cam, centre[0], outline):
                continue
            expect = _polygon_centroid(q)
            errors.append(np.linalg.norm(_centroid(img[c].astype(float).sum(axis=2), p, 10) - expect))
            offsets.append(np.linalg.norm(expect - p))
    errors = np.array(errors)
    assert errors.size > 60
    assert np.median(errors) < 0.02 and errors.max() < 0.05
    assert max(offsets) < 0.4


def _facing(cam, centre, outline, max_deg=45):
    n = np.cross(outline[45] - outline[135], outline[0] - outline[90])
    n /= np.linalg.norm(n)
    to_cam = (cam.centre - centre) / np.linalg.norm(cam.centre - centre)
    return abs(n @ to_cam) > math.cos(math.radians(max_deg))


def _polygon_centroid(q):
    x, y = q[:, 0], q[:, 1]
    x1, y1 = np.roll(x, -1), np.roll(y, -1)
    a = x * y1 - x1 * y
    return np.array([((x + x1) * a).sum(), ((y + y1) * a).sum()]) / (3 * a.sum())


def _centroid(img, p, r):
    """Intensity centroid of a bright dot near ``p``: a background plane fitted on the ring 0.75 r..r is
    subtracted, then the residual is averaged over the disc of radius 0.7 r."""
    x0, y0 = int(round(p[0])), int(round(p[1]))
    win = img[y0 - r:y0 + r + 1, x0 - r:x0 + r + 1]
    yy, xx = np.mgrid[y0 - r:y0 + r + 1, x0 - r:x0 + r + 1]
    dist = np.hypot(xx - p[0], yy - p[1])
    ring = (dist > 0.75 * r) & (dist <= r)
    A = np.stack([np.ones(ring.sum()), xx[ring] - p[0], yy[ring] - p[1]], axis=1)
    coef = np.linalg.lstsq(A, win[ring], rcond=None)[0]
    w = (win - coef[0] - coef[1] * (xx - p[0]) - coef[2] * (yy - p[1])) * (dist < 0.7 * r)
    return np.array([(w * xx).sum(), (w * yy).sum()]) / w.sum()


# -- sensor -----------------------------------------------------------------------------------------------------
def test_sensor_noise_and_quantisation():
    from heartcv.render.scene import NoiseSpec
    from heartcv.render.sensor import expose, standard_normal

    z = standard_normal(np.random.default_rng(1), (1_000_000,))
    assert abs(z.mean()) < 5e-3 and abs(z.std() - 1) < 5e-3 and abs(np.abs(z).max() - 4.33) < 0.01
    spec = NoiseSpec(full_well_e=10000, read_noise_e=10.0)
    flat = np.full((400, 500), 0.5, np.float32)
    assert np.all(expose(flat, spec, None) == 128)  # 0.5 * 255 = 127.5 -> 128
    assert np.all(expose(flat * 3, spec, None) == 255)  # saturation
    noisy = expose(flat, spec, np.random.default_rng(2)).astype(float)
    expect = math.sqrt(5000 + 100) * 255 / 10000  # DN
    assert noisy.std() == pytest.approx(math.sqrt(expect**2 + 1 / 12), rel=0.02)


# -- calibration renders ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def calib_setup(model_file):
    from heartcv.render.board import prepare_calibration
    from heartcv.targets import TargetSpec

    scene = scene_from_dict(scene_dict(model_file, scale=3, optics={"psf_sigma_px": 0.7},
                                       calibration={"views": 3, "partial_fraction": 0.34}))
    return prepare_calibration(scene, TargetSpec("charuco", (11, 8), 0.012, 0.009, "DICT_5X5_250"))


def test_charuco_corners_land_on_the_true_projections(calib_setup):
    """OpenCV's CharucoDetector on rendered views (lens distortion, noise, a partial view) finds the corners
    where Camera.project puts the board's corners at the true pose: rays, distortion and texture together."""
    import cv2

    from heartcv.render.board import calibration_truth, render_calibration

    arrays, meta = calibration_truth(calib_setup)
    assert calib_setup.partial.sum() == 1 and meta["target"]["type"] == "charuco"
    det = cv2.aruco.CharucoDetector(calib_setup.target.cv_board())
    errors, partial_seen = [], 0
    for view in render_calibration(calib_setup):
        for c, img in enumerate(view.images):
            corners, ids, _, _ = det.detectBoard(img)
            if ids is None:
                continue
            ids = ids.ravel()
            assert arrays["corners_visible"][view.index, c][ids].all()
            errors.append(np.linalg.norm(corners.reshape(-1, 2) - arrays["corners_uv"][view.index, c][ids], axis=1))
            partial_seen += bool(calib_setup.partial[view.index]) and ids.size < arrays["object_points"].shape[0]
    e = np.concatenate(errors)
    assert e.size > 300 and partial_seen >= 1
    # OpenCV's corner refinement itself scatters by a few hundredths of a pixel on synthetic corners
    assert np.sqrt(np.mean(e**2)) < 0.1 and np.median(e) < 0.06 and np.percentile(e, 95) < 0.15


def test_board_render_equals_brute_force_supersampling(model_file):
    """A pinhole camera's render (1 ray per pixel, 12x12 where the board's pattern changes) equals an independent
    render with 12x12 rays in every pixel (sub-pixel rays from K alone, averaged), to the grey level."""
    from heartcv.render.board import _radiance, prepare_calibration, render_view
    from heartcv.targets import TargetSpec

    scene = scene_from_dict(scene_dict(model_file, scale=8, rig={"distortion": []}, optics={"psf_sigma_px": 0.0},
                                       lighting={"ambient": 1.0, "intensity": 0.0},
                                       calibration={"views": 1, "supersampling": 12, "black": 0.0, "white": 1.0}))
    s = prepare_calibration(scene, TargetSpec("chessboard", (9, 6), 0.012))
    cam, T = s.rig.cameras[1], s.world_from_board[0]
    img = render_view(s, 0, noise=False).images[1].astype(float)
    n = 12
    sub = (np.arange(n) + 0.5) / n - 0.5
    u = (np.arange(cam.width)[:, None] + sub).ravel()
    v = (np.arange(cam.height)[:, None] + sub).ravel()
    U, Vv = np.meshgrid(u, v)
    K = cam.K
    d = np.stack([(U - K[0, 2]) / K[0, 0], (Vv - K[1, 2]) / K[1, 1], np.ones_like(U)], -1).reshape(-1, 3) @ cam.R
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ref = _radiance(s, cam, T, d)[0].reshape(cam.height, n, cam.width, n).mean(axis=(1, 3))
    diff = np.abs(img - np.rint(ref * 255))
    assert diff.max() <= 1 and diff.mean() < 0.01  # DN


def test_calibration_poses_tilt_and_partial(calib_setup):
    from heartcv.render.board import corner_visibility

    for T, partial in zip(calib_setup.world_from_board, calib_setup.partial):
        _, seen, inc = corner_visibility(calib_setup.rig, calib_setup.target, T)
        frac = seen.mean(axis=1)
        good = inc <= calib_setup.scene.calibration.max_incidence_deg
        assert (good & (seen.sum(axis=1) >= 12)).sum() >= 2
        assert (frac[good] < 1).any() if partial else (frac[good] == 1).all()


def test_phantom_outside_patch_operator_is_sparse(model_config):
    from heartcv.render.phantom import build_phantom, displacement_operator
    from heartcv.render.scene import PhantomSpec
    from heartcv.tracker.model import build_model

    model = build_model(model_config)
    ph = build_phantom(model.mesh.geometry, PhantomSpec(mesh_edge_m=0.003))
    D = displacement_operator(ph, model)
    assert sp.issparse(D) and D.shape == (ph.n_vertices, model.mesh.n_nodes)
    assert np.allclose(np.asarray(D.sum(axis=1)).ravel()[ph.in_patch], 1.0)  # partition of unity on the patch

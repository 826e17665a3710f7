"""heartcv.evaluate: Kabsch fit against exact transforms and scipy, truth errors on a tiny deforming mesh whose
material points are known by construction (barycentric coordinates), the rigid-gauge alignment, the count of
observations on a packed instrument mask against brute force, and displacement consistency against closed forms."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from heartcv.camera import Camera, pose_matrix
from heartcv.evaluate import displacement_consistency, occluded_observations, rigid_fit, truth_errors


# -- rigid_fit --------------------------------------------------------------------------------------------------
def test_rigid_fit_recovers_an_exact_transform():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(12, 3)) * 0.02
    R = Rotation.from_rotvec([0.3, -0.5, 0.8]).as_matrix()
    t = np.array([0.01, -0.02, 0.5])
    T = rigid_fit(A, A @ R.T + t)
    assert np.abs(T - pose_matrix(R, t)).max() < 1e-12


def test_rigid_fit_least_squares_and_reflection_guard():
    rng = np.random.default_rng(2)
    A = rng.normal(size=(30, 3))
    R = Rotation.from_rotvec([-1.0, 0.2, 0.4]).as_matrix()
    B = A @ R.T + [1.0, 2.0, 3.0] + 0.05 * rng.normal(size=A.shape)
    T = rigid_fit(A, B)
    # scipy's Kabsch on the centred points is an independent implementation
    R_ref, _ = Rotation.align_vectors(B - B.mean(axis=0), A - A.mean(axis=0))
    assert np.abs(T[:3, :3] - R_ref.as_matrix()).max() < 1e-10
    assert np.abs(T[:3, 3] - (B.mean(axis=0) - T[:3, :3] @ A.mean(axis=0))).max() < 1e-12
    # a mirror image cannot be fitted by a reflection: the result stays a rotation
    M = rigid_fit(A, A * [1.0, 1.0, -1.0])[:3, :3]
    assert np.isclose(np.linalg.det(M), 1.0) and np.abs(M.T @ M - np.eye(3)).max() < 1e-12


# -- truth_errors on a tiny mesh ---------------------------------------------------------------------------------
def _mesh_truth(K_frames=3):
    """A 3x3-vertex grid (8 triangles) 0.5 m in front of camera 0, translating and bending over the frames, seen
    by two cameras (camera 1 on the side, converging); 320x240 images, mild distortion."""
    g = np.linspace(-0.03, 0.03, 3)
    xx, yy = np.meshgrid(g, g)
    V0 = np.stack([xx.ravel(), yy.ravel(), np.full(9, 0.5)], axis=1)
    faces = []
    for r in range(2):
        for c in range(2):
            a = 3 * r + c
            faces += [[a, a + 1, a + 4], [a, a + 4, a + 3]]
    verts = []
    for k in range(K_frames):
        V = V0 + [1e-3 * k, -0.5e-3 * k, 0.7e-3 * k]
        V[4, 2] -= 2e-3 * k                                 # the centre vertex comes forward: not rigid
        verts.append(V)
    Kmat = np.array([[600.0, 0, 159.5], [0, 600.0, 119.5], [0, 0, 1]])
    R1 = Rotation.from_rotvec([0, -0.4, 0]).as_matrix()
    c1 = np.array([0.2, 0.0, 0.04])
    truth = {"vertex_positions": np.array(verts), "faces": np.array(faces), "K": np.stack([Kmat, Kmat]),
             "dist": np.array([[-0.05, 0.02, 0, 0, 0], [0.03, 0, 0, 0, 0]]),
             "cam_from_world": np.stack([np.eye(4), pose_matrix(R1, -R1 @ c1)]), "image_size": np.array([320, 240])}
    return truth


# material points: (face, barycentric) and birth frame, chosen inside the triangles
MATERIAL = [(0, (0.2, 0.3, 0.5), 0), (3, (0.6, 0.2, 0.2), 0), (5, (0.1, 0.1, 0.8), 1), (6, (0.3, 0.3, 0.4), 2),
            (7, (0.5, 0.25, 0.25), 1)]


def _material_truth(truth):
    """True positions (K, P, 3) of MATERIAL by construction, birth frames, and the birth pixels in camera 0."""
    V, F = truth["vertex_positions"], truth["faces"]
    pos = np.stack([np.array([np.asarray(w) @ V[k][F[f]] for f, w, _ in MATERIAL]) for k in range(len(V))])
    birth = np.array([b for _, _, b in MATERIAL])
    cam = Camera("c0", 320, 240, truth["K"][0], truth["dist"][0], truth["cam_from_world"][0])
    uv = np.array([cam.project(pos[b, p])[0] for p, b in enumerate(birth)])
    return pos, birth, uv


# the ray-mesh intersection and the barycentric transfer are exact up to float64 rounding (1e-16 m measured)
EXACT_M = 1e-12


def test_truth_errors_exact_and_displaced_positions():
    truth = _mesh_truth()
    true, birth, uv = _material_truth(truth)
    e = truth_errors(true, uv, birth, truth)
    assert np.array_equal(e.material_face, [f for f, _, _ in MATERIAL])
    assert np.abs(e.true_positions - true).max() < EXACT_M
    assert e.n == true.shape[0] * true.shape[1] and e.max_m < EXACT_M
    # known displacements: the errors are their lengths; a missing observation is NaN and not counted
    rng = np.random.default_rng(3)
    d = rng.normal(size=true.shape) * 1e-4
    meas = true + d
    meas[1, 2] = np.nan
    e = truth_errors(meas, uv, birth, truth)
    want = np.linalg.norm(d, axis=2)
    want[1, 2] = np.nan
    assert np.isnan(e.errors[1, 2]) and e.n == want.size - 1
    assert np.nanmax(np.abs(e.errors - want)) < EXACT_M
    w = want[np.isfinite(want)]
    assert abs(e.rms_m - np.sqrt(np.mean(w ** 2))) < EXACT_M and abs(e.max_m - w.max()) < EXACT_M
    assert abs(e.mean_m - w.mean()) < EXACT_M and abs(e.p99_m - np.percentile(w, 99)) < EXACT_M


def test_truth_errors_alignment_removes_a_global_rigid_offset():
    truth = _mesh_truth()
    true, birth, uv = _material_truth(truth)
    T = pose_matrix(Rotation.from_rotvec([0.002, -0.001, 0.003]).as_matrix(), [4e-4, -2e-4, 1e-3])
    meas = true @ T[:3, :3].T + T[:3, 3]                    # the measurements in a slightly different frame
    e = truth_errors(meas, uv, birth, truth)
    assert e.rms_m > 5e-4                                    # raw errors: the offset
    assert e.aligned.max_m < EXACT_M and e.aligned.n == e.n
    assert np.abs(e.truth_from_rig @ T - np.eye(4)).max() < 1e-5
    # the alignment is fitted to the birth positions only: a motion error after birth is not aligned away
    meas[2, 0] += [3e-4, 0, 0]
    e = truth_errors(meas, uv, birth, truth)
    others = np.ones(e.errors.shape, bool)
    others[2, 0] = False
    assert abs(e.aligned.errors[2, 0] - 3e-4) < 1e-5 and e.aligned.errors[others].max() < 1e-5


def test_truth_errors_missed_rays_reference_camera_and_frame_count():
    truth = _mesh_truth()
    true, birth, uv = _material_truth(truth)
    uv2 = uv.copy()
    uv2[1] = [5.0, 5.0]                                      # a corner pixel: its ray misses the mesh
    e = truth_errors(true, uv2, birth, truth)
    assert e.material_face[1] == -1 and np.isnan(e.errors[:, 1]).all()
    assert np.nanmax(e.errors) < EXACT_M
    # the same material points seen from camera 1
    cam1 = Camera("c1", 320, 240, truth["K"][1], truth["dist"][1], truth["cam_from_world"][1])
    uv1 = np.array([cam1.project(true[b, p])[0] for p, b in enumerate(birth)])
    e = truth_errors(true, uv1, birth, truth, ref_camera=1)
    assert np.array_equal(e.material_face, [f for f, _, _ in MATERIAL]) and e.max_m < EXACT_M
    with pytest.raises(ValueError, match="frames"):
        truth_errors(true[:2], uv, birth, truth)


# -- occluded observations ---------------------------------------------------------------------------------------
def test_occluded_observations_counts_hits_on_the_packed_mask():
    rng = np.random.default_rng(4)
    K, P, C, H, W = 3, 40, 2, 17, 21                         # W not a multiple of 8: padded bytes
    mask = rng.random((K, C, H, W)) < 0.3
    truth = {"instrument_mask": np.packbits(mask, axis=-1), "image_size": np.array([W, H])}
    uv = rng.uniform([-0.45, -0.45], [W - 0.55, H - 0.55], (K, P, C, 2))
    uv[rng.random((K, P, C)) < 0.2] = np.nan
    want = 0
    for k in range(K):
        for p in range(P):
            for c in range(C):
                if np.isfinite(uv[k, p, c]).all():
                    x, y = (int(np.floor(v + 0.5)) for v in uv[k, p, c])     # nearest pixel
                    want += bool(mask[k, c, y, x])
    assert want > 10
    assert occluded_observations(uv, truth) == want
    assert occluded_observations(uv, {"image_size": np.array([W, H])}) == 0
    assert occluded_observations(np.full((K, P, C, 2), np.nan), truth) == 0


# -- displacement consistency -------------------------------------------------------------------------------------
def test_displacement_consistency_closed_form():
    rng = np.random.default_rng(5)
    K, P = 4, 3
    true = rng.normal(size=(K, P, 3)) * 1e-3
    birth = np.array([0, 1, 0])
    bias = rng.normal(size=(1, P, 3)) * 1e-4
    cov = np.broadcast_to(np.diag([1e-8, 4e-8, 9e-8]), (K, P, 3, 3)).copy()
    # a constant error per track cancels in the displacements
    d = displacement_consistency(true + bias, cov, true, birth)
    assert d["rms_m"] < 1e-15 and d["n"] == K * P - P
    # one displacement error e at (k=2, p=1): NEES e^T (C_k + C_b)^-1 e over the 9 displacements, per dof
    meas = true.copy()
    e = np.array([1e-4, -2e-4, 3e-4])
    meas[2, 1] += e
    d = displacement_consistency(meas, cov, true, birth)
    nees = e @ np.linalg.solve(2 * cov[0, 0], e)
    assert np.isclose(d["nees_per_dof"], nees / 9 / 3, rtol=1e-9)
    assert np.isclose(d["rms_m"], np.linalg.norm(e) / 3, rtol=1e-9)
    # the rotation to the truth frame is applied to the measurements and their covariances
    R = Rotation.from_rotvec([0.1, 0.2, -0.3]).as_matrix()
    d2 = displacement_consistency(meas @ R, R.T @ cov @ R, true, birth, rotation=R)     # rig = R^T truth
    assert np.isclose(d2["rms_m"], d["rms_m"], rtol=1e-9) and np.isclose(d2["nees_per_dof"], d["nees_per_dof"])

"""Accuracy of measured surface points against the renderer's ground truth (``truth.npz`` of
``heartcv render sequence``, docs/formats.md §11.2).

Each track is identified with a material point of the rendered surface: the point its reference camera pixel
sees in its birth frame (the true camera's ray through the tracked pixel, intersected with the true mesh of
that frame). That material point is followed through the frames by its barycentric coordinates in its
triangle (the rendered surface is the piecewise-linear interpolation of the mesh vertices, so this is exact).
The error of an observation is the distance between the measured and the true position of its material point:
it contains the depth error of the triangulation and any drift of the tracker along the surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import Camera

__all__ = ["TRUTH_FOR_ERRORS", "TruthErrors", "truth_errors", "occluded_observations", "rigid_fit",
           "displacement_consistency"]


@dataclass(frozen=True)
class TruthErrors:
    """Errors (m) of the observations against the truth.

    Attributes
    ----------
    errors : ndarray (K, P)       3-D error of each observation (NaN where not seen or no material point)
    material_face : ndarray (P,)  triangle of each track's material point (-1 if the ray missed the mesh)
    rms_m, p99_m, mean_m, max_m : float   over all observations
    n : int                       observations compared
    aligned : TruthErrors or None the same after one rigid transform of all measured positions, fitted (Kabsch)
                                  to the tracks' birth positions only; it removes the gauge of a calibrated rig
                                  frame (camera 0 as calibrated differs from the true camera 0 by a small pose),
                                  not the errors of the motion
    truth_from_rig : ndarray (4, 4) or None   that transform
    true_positions : ndarray (K, P, 3) or None  the true position of each track's material point per frame
    """

    errors: np.ndarray
    material_face: np.ndarray
    rms_m: float
    p99_m: float
    mean_m: float
    max_m: float
    n: int
    aligned: "TruthErrors | None" = None
    truth_from_rig: np.ndarray | None = None
    true_positions: np.ndarray | None = None


#: The render-truth arrays :func:`truth_errors` reads (docs/formats.md §11.2)
TRUTH_FOR_ERRORS = ("K", "dist", "cam_from_world", "image_size", "faces", "vertex_positions")

def _true_camera(truth, c) -> Camera:
    W, H = (int(v) for v in truth["image_size"])
    return Camera(f"true{c}", W, H, truth["K"][c], truth["dist"][c], truth["cam_from_world"][c])


def _barycentric(p, a, b, c):
    v0, v1, v2 = b - a, c - a, p - a
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
    den = d00 * d11 - d01 * d01
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    return np.stack([1 - v - w, v, w], axis=1)


def truth_errors(positions, uv_ref, birth_frame, truth, ref_camera=0) -> TruthErrors:
    """Errors of measured positions against a render truth.

    Parameters
    ----------
    positions : ndarray (K, P, 3)     measured positions, rig frame = the truth's world frame (camera 0)
    uv_ref : ndarray (P, 2)           each track's pixel in the reference camera in its birth frame
    birth_frame : ndarray (P,)        index of each track's birth frame into the K frames
    truth : dict                      arrays of ``truth.npz`` whose frames are the K measured frames
    ref_camera : int
    """
    import trimesh

    positions = np.asarray(positions, float)
    K, P = positions.shape[:2]
    verts = truth["vertex_positions"]
    if verts.shape[0] != K:
        raise ValueError(f"truth: {verts.shape[0]} frames, the measurements have {K}")
    faces = np.asarray(truth["faces"], np.int64)
    cam = _true_camera(truth, ref_camera)
    face = np.full(P, -1, np.int64)
    bary = np.zeros((P, 3))
    for b in np.unique(birth_frame):
        sel = np.flatnonzero(birth_frame == b)
        ok = np.isfinite(uv_ref[sel]).all(axis=1)
        sel = sel[ok]
        if sel.size == 0:
            continue
        mesh = trimesh.Trimesh(np.asarray(verts[b], float), faces, process=False)
        o, d = cam.rays(uv_ref[sel])
        loc, ir, it = mesh.ray.intersects_location(o, d, multiple_hits=False)
        face[sel[ir]] = it
        tri = mesh.vertices[faces[it]]
        bary[sel[ir]] = _barycentric(loc, tri[:, 0], tri[:, 1], tri[:, 2])
    true_pos = np.full((K, P, 3), np.nan)
    have = face >= 0
    if have.any():
        V = np.asarray(verts, float)[:, faces[face[have]]]                        # (K, p, 3, 3)
        true_pos[:, have] = np.einsum("pj,kpjx->kpx", bary[have], V)
    plain = _errors(positions, true_pos, face)
    plain = TruthErrors(*[getattr(plain, f) for f in ("errors", "material_face", "rms_m", "p99_m", "mean_m",
                                                      "max_m", "n")], true_positions=true_pos)
    born = np.array([positions[b, p] for p, b in enumerate(birth_frame)]).reshape(P, 3)
    born_true = np.array([true_pos[b, p] for p, b in enumerate(birth_frame)]).reshape(P, 3)
    ok = np.isfinite(born).all(axis=1) & np.isfinite(born_true).all(axis=1)
    if ok.sum() < 3:
        return plain
    T = rigid_fit(born[ok], born_true[ok])
    moved = positions @ T[:3, :3].T + T[:3, 3]
    aligned = _errors(moved, true_pos, face)
    return TruthErrors(plain.errors, face, plain.rms_m, plain.p99_m, plain.mean_m, plain.max_m, plain.n,
                       aligned, T, true_pos)


def displacement_consistency(positions, covariances, true_positions, birth_frame, rotation=None) -> dict:
    """Errors of the measured displacements from each track's reference position, and their consistency with
    the covariances.

    The estimators use a point's motion relative to its reference position (the birth-frame position), so a
    constant error of a track (a matching bias that stays with the track) cancels; what remains is compared
    with the covariance of a difference of two observations, ``C_k + C_b`` (independent frames). Returns
    ``rms_m`` (3-D RMS of the displacement errors), ``nees_per_dof`` (mean of e^T (C_k + C_b)^-1 e / 3: 1 for
    consistent covariances, below 1 for conservative ones) and ``n``. Frames where a track is born are left
    out (zero displacement). ``rotation`` (3, 3) rotates the measurements into the truth frame (the aligned
    gauge).
    """
    X = np.asarray(positions, float)
    Cv = np.asarray(covariances, float)
    if rotation is not None:
        R = np.asarray(rotation, float)
        X = X @ R.T
        Cv = R @ Cv @ R.T
    K, P = X.shape[:2]
    cols = np.arange(P)
    b = np.asarray(birth_frame, int)
    de = (X - X[b, cols][None]) - (true_positions - true_positions[b, cols][None])
    S = Cv + Cv[b, cols][None]
    ok = np.isfinite(de).all(axis=2) & np.isfinite(S).all(axis=(2, 3)) & (np.arange(K)[:, None] != b[None])
    if not ok.any():
        return {"rms_m": float("nan"), "nees_per_dof": float("nan"), "n": 0}
    e = de[ok]
    z = np.einsum("ni,ni->n", e, np.linalg.solve(S[ok], e[..., None])[..., 0])
    return {"rms_m": float(np.sqrt(np.mean(np.sum(e ** 2, axis=1)))), "nees_per_dof": float(z.mean() / 3),
            "n": int(ok.sum())}


def _errors(positions, true_pos, face) -> TruthErrors:
    errors = np.linalg.norm(positions - true_pos, axis=2)
    e = errors[np.isfinite(errors)]
    if e.size == 0:
        return TruthErrors(errors, face, np.nan, np.nan, np.nan, np.nan, 0)
    return TruthErrors(errors, face, float(np.sqrt(np.mean(e ** 2))), float(np.percentile(e, 99)),
                       float(e.mean()), float(e.max()), int(e.size))


def rigid_fit(A, B) -> np.ndarray:
    """The rigid transform (4, 4) minimising sum |R a + t - b|^2 over rows of A, B (N, 3) (Kabsch, with the
    reflection guard; Umeyama, PAMI 1991)."""
    ca, cb = A.mean(axis=0), B.mean(axis=0)
    U, _, Vt = np.linalg.svd((A - ca).T @ (B - cb))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = cb - R @ ca
    return T


def occluded_observations(uv, truth) -> int:
    """How many views used by the observations (K, P, C, 2) fall on pixels that the truth's instrument mask
    marks as hidden in that camera and frame (0 without an instrument mask)."""
    if "instrument_mask" not in truth:
        return 0
    packed = truth["instrument_mask"]
    W = int(truth["image_size"][0])
    K, P, C, _ = uv.shape
    count = 0
    for k in range(K):
        for c in range(C):
            u = uv[k, :, c]
            ok = np.isfinite(u).all(axis=1)
            if not ok.any():
                continue
            mask = np.unpackbits(packed[k, c], axis=-1)[:, :W].astype(bool)
            px = np.rint(u[ok]).astype(int)
            px[:, 0] = np.clip(px[:, 0], 0, W - 1)
            px[:, 1] = np.clip(px[:, 1], 0, mask.shape[0] - 1)
            count += int(mask[px[:, 1], px[:, 0]].sum())
    return count

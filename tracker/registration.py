"""Registration: place the patch model on a measured surface (rig frame -> patch frame).

A rig-frame measurement set (``heartcv measure``) holds points all over the visible surface; the model is a
patch somewhere in it. :func:`register` finds the rigid pose ``patch_from_rig`` from the points seen in the
first frames, and :func:`to_patch_frame` turns the set into the patch-frame set that
:func:`tracker.tracking.locate_points` places on the mesh (host element and shape-function weights of every
point, rows of H for the points seen in each frame).

Method (docs/model.md, "Registration"):

1. **Surface fit.** The pose is fitted so that the epicardium ``d = 0`` passes through the points' reference
   positions: robust (soft-L1) least squares over a rotation vector and a translation of the normal
   distances ``d_i`` (closed-form inverse map, :meth:`PatchGeometry.from_patch`) of the points whose
   ``(s, t)`` fall on the patch, with trimming in ``|d|`` re-selected ICP-style. Without ``initial`` it starts
   from the surface point nearest the points that move most, the local plane normal turned towards the rig
   origin, and six in-plane angles (the radii differ along s and t), keeping the best trimmed cost.
2. **Motion fit.** A surface of revolution slides along itself (rotation about its axis) without changing
   the distances, and the heart around the patch has nearly the patch's curvature; the surface alone does
   not fix where on it the patch lies. The model does: under the known inputs its quasi-static displacement
   ``alpha G(s, t) (u_k - u_ref)`` (``G`` the static response to a unit input, ``alpha`` a free scale for the
   unknown stiffness) vanishes at the clamped rim and peaks inside. The in-plane position and angle are
   searched on a grid for the largest motion explained by that field (per-frame offsets ``beta_k`` absorb
   any rigid motion), then all six pose coordinates are refined on distances and motion together.

The patch is symmetric under a half-turn about its normal, ``(s, t) -> (-s, -t)``; of the two equivalent
poses the one whose +x axis is closest to ``initial``'s (else to the rig's +x axis) is returned.

The reference positions are deformed positions (each point's birth frame), not the undeformed surface: the
deformation (1-2 mm) is small against the patch (several cm) and enters the distances as a small bias; the
motion fit uses the change of the inputs since each point's reference frame.

Curvature is not fitted (the model's radii are used as configured).
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from .files import InputError
from .measurements import MeasurementSet
from .model import PatchModel

__all__ = ["Registration", "register", "to_patch_frame", "register_rig_measurements", "registration_to_dict",
           "apply_stored_registration", "deformation_signal"]

MIN_POINTS = 6
ALL_DOF = np.arange(6)  # pose increment: rotation vector (x, y, z), translation (x, y, z), patch frame
NO_SLIDE = np.array([0, 1, 2, 4])  # translation along the surface held (nothing observes it without motion)
_HALF_TURN = np.diag([-1.0, 1.0, -1.0, 1.0])  # (s, t) -> (-s, -t): a symmetry of the patch


@dataclass(frozen=True)
class Registration:
    """Result of :func:`register`.

    Attributes
    ----------
    patch_from_rig : ndarray of shape (4, 4)
        Rigid pose, ``x_patch = R x_rig + t``.
    rms_m : float
        RMS distance (m) of the on-patch reference points to the epicardial surface after the fit.
    on_patch : ndarray of shape (P,) bool
        Per point of the measurement set: its reference lies on the patch (``(s, t)`` inside, ``|d|`` at most
        ``max_depth``).
    n_points : int
        Points used in the fit.
    converged : bool
    message : str
    """

    patch_from_rig: np.ndarray
    rms_m: float
    on_patch: np.ndarray
    n_points: int
    converged: bool
    message: str

    def __post_init__(self):
        T = np.array(self.patch_from_rig, float)
        if T.shape != (4, 4):
            raise ValueError(f"patch_from_rig: shape (4, 4) expected, got {T.shape}")
        T.setflags(write=False)
        on = np.array(self.on_patch, bool).reshape(-1)
        on.setflags(write=False)
        object.__setattr__(self, "patch_from_rig", T)
        object.__setattr__(self, "on_patch", on)

    @property
    def rotation(self) -> np.ndarray:
        return self.patch_from_rig[:3, :3]

    @property
    def translation(self) -> np.ndarray:
        return self.patch_from_rig[:3, 3]

    def info(self) -> dict:
        """JSON-ready summary (recorded in the patch-frame set's ``meta['registration']``)."""
        return {"patch_from_rig": self.patch_from_rig.tolist(), "rms_m": float(self.rms_m),
                "n_points": int(self.n_points), "on_patch": int(self.on_patch.sum()),
                "converged": bool(self.converged), "message": self.message}


# -- geometry helpers ----------------------------------------------------------------------------------

def _pose(R, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _apply(T, X) -> np.ndarray:
    return X @ T[:3, :3].T + T[:3, 3]


def _check_pose(T, name) -> np.ndarray:
    """``T`` as a (4, 4) float array; InputError (field ``name``, no file) unless it is a finite rigid transform."""
    T = np.asarray(T, float)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise InputError(None, f"finite (4, 4) rigid transform expected, got shape {T.shape}", name)
    R = T[:3, :3]
    if (np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0
            or np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-9):
        raise InputError(None, "not a rigid transform (rotation block not orthonormal or last row not 0 0 0 1)",
                         name)
    return T


def _inside(std, g):
    """(s, t) on the patch (the tolerance of locate_points)."""
    return (np.abs(std[:, 0]) <= g.length / 2 * (1 + 1e-9)) & (np.abs(std[:, 1]) <= g.width / 2 * (1 + 1e-9))


def _increment(xi) -> np.ndarray:
    """Pose increment in the patch frame: rotation vector xi[:3] about the patch origin, then xi[3:6]."""
    return _pose(Rotation.from_rotvec(xi[:3]).as_matrix(), xi[3:6])


def _surface_frame(g, s, t) -> np.ndarray:
    """``patch_from_local`` (4, 4) of the epicardial point ``(s, t)``: axes (e_s, n, e_t) as the patch's."""
    h = 1e-6 * max(g.length, g.width)
    e_s = g.to_patch(s + h, t, 0.0) - g.to_patch(s - h, t, 0.0)
    e_s /= np.linalg.norm(e_s)
    n = g.epicardial_normal(s, t)
    e_t = np.cross(e_s, n)
    return _pose(np.stack([e_s, n, e_t], axis=1), g.to_patch(s, t, 0.0))


def _spin(gamma) -> np.ndarray:
    """Rotation (4, 4) by gamma about the patch normal (+y)."""
    return _pose(Rotation.from_rotvec([0.0, gamma, 0.0]).as_matrix(), np.zeros(3))


# -- data ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class _Data:
    X: np.ndarray          # (N, 3) reference positions (rig) of the fitted points
    idx: np.ndarray        # (N,) their indices in the measurement set
    disp: np.ndarray       # (S, 3) measured displacement samples since the reference (rig frame)
    du: np.ndarray         # (S, n_u) input change since the reference frame
    pt: np.ndarray         # (S,) sample -> fitted point (0..N-1)
    fr: np.ndarray         # (S,) sample -> frame of the window
    n_frames: int


def _data(meas: MeasurementSet, model: PatchModel, frames: int, inputs=None) -> _Data:
    K = min(frames, meas.n_frames)
    seen = meas.seen[:K]
    rfi = meas.meta.get("reference_frame_index")
    rfi = np.zeros(meas.n_points, np.int64) if rfi is None else np.asarray(rfi, np.int64).reshape(-1)
    if rfi.size != meas.n_points:
        raise InputError(None, f"{meas.n_points} entries expected, got {rfi.size}", "meta.reference_frame_index")
    used = seen.any(axis=0) & (rfi < K)
    idx = np.flatnonzero(used)
    if idx.size < MIN_POINTS:
        raise InputError(None, f"registration onto the patch needs at least {MIN_POINTS} points seen in the first "
                               f"{K} frames, got {idx.size}", "positions")
    if inputs is not None:
        u = np.asarray(inputs, float).reshape(meas.n_frames, -1)
    else:
        try:
            u = meas.input_columns(model.input_names)
        except InputError:  # an input the model needs is missing: the surface alone places the patch
            u = np.zeros((meas.n_frames, 0))
    # undeformed reference (u = 0) unless the file says in which frame each point was born
    u_ref = u[rfi[idx]] if "reference_frame_index" in meas.meta else np.zeros((idx.size, u.shape[1]))
    k_idx, j_idx = np.nonzero(seen[:, idx] & (np.arange(K)[:, None] > rfi[idx][None, :]))
    disp = meas.positions[k_idx, idx[j_idx]] - meas.reference[idx[j_idx]]
    du = u[k_idx] - u_ref[j_idx]
    return _Data(meas.reference[idx].copy(), idx, disp, du, j_idx, k_idx, K)


class _Compliance:
    """Static epicardial displacement per unit input (the model at its configured theta), bilinear in
    ``(s, t)`` on the mesh's epicardial nodes (patch frame)."""

    def __init__(self, model: PatchModel):
        mesh = model.mesh
        n_u = model.loads.shape[1]
        epi = mesh.node_index[:, :, 0]
        fields = [model.node_displacements(model.static_state(model.config.theta, np.eye(n_u)[j]))[epi]
                  for j in range(n_u)]  # (n_s, n_t, 3) each
        self.values = np.stack(fields, axis=-1) if fields else np.zeros(epi.shape + (3, 0))
        self.scale = float(np.abs(self.values).max()) if self.values.size else 0.0
        self.axes = mesh.axes[:2]

    def __call__(self, st, du) -> np.ndarray:
        """Displacement (..., 3) at ``st`` (..., 2) (clipped to the patch) for input changes ``du`` (..., n_u)."""
        idx, frac = [], []
        for a, ax in enumerate(self.axes):
            h = ax[1] - ax[0]
            x = np.clip((st[..., a] - ax[0]) / h, 0.0, ax.size - 1)
            i = np.minimum(x.astype(int), ax.size - 2)
            idx.append(i)
            frac.append((x - i)[..., None, None])
        (i, j), (fs, ft) = idx, frac
        V = self.values
        G = ((1 - fs) * (1 - ft) * V[i, j] + fs * (1 - ft) * V[i + 1, j]
             + (1 - fs) * ft * V[i, j + 1] + fs * ft * V[i + 1, j + 1])
        return np.einsum("...ij,...j->...i", G, du)


def _centre(v, fr, n_frames, w2=None):
    """Samples (S, 3) minus the (``w2``-weighted) mean of their frame."""
    w2 = np.ones(fr.size) if w2 is None else w2
    sums = np.zeros((n_frames, 3))
    np.add.at(sums, fr, v * w2[:, None])
    tot = np.bincount(fr, weights=w2, minlength=n_frames)
    return v - (sums / np.where(tot > 0, tot, 1.0)[:, None])[fr]


def _motion_fit(m, p, fr, n_frames, w2=None):
    """Closed-form fit of ``m ~ alpha p + beta_k`` (per-frame offsets beta_k absorb any rigid motion).

    Returns the centred residuals (S, 3), alpha and the explained (weighted) sum of squares."""
    w2 = np.ones(fr.size) if w2 is None else w2
    mc, pc = _centre(m, fr, n_frames, w2), _centre(p, fr, n_frames, w2)
    pp = float(np.sum(w2 * np.sum(pc * pc, axis=1)))
    if pp <= 0:
        return mc, 0.0, 0.0
    mp = float(np.sum(w2 * np.sum(mc * pc, axis=1)))
    alpha = mp / pp
    return mc - alpha * pc, alpha, mp * mp / pp


# -- stage 1: surface ----------------------------------------------------------------------------------

def _trimmed_cost(T, X, g, tau):
    std = g.from_patch(_apply(T, X))
    r = np.where(_inside(std, g), np.minimum((std[:, 2] / tau) ** 2, 1.0), 1.0)
    return float(r.sum())


def _expand(z, free):
    xi = np.zeros(6)
    xi[free] = z
    return xi


def _fit_surface(T, X, g, taus, free=ALL_DOF):
    """ICP-style trimmed surface fit over the pose coordinates ``free``; returns the refined pose."""
    for tau in taus:
        prev = None
        for _ in range(8):
            std = g.from_patch(_apply(T, X))
            sel = _inside(std, g) & (np.abs(std[:, 2]) <= tau)
            if sel.sum() < MIN_POINTS or (prev is not None and np.array_equal(sel, prev)):
                break
            prev = sel
            P = _apply(T, X[sel])

            def res(z, P=P):
                return g.from_patch(_apply(_increment(_expand(z, free)), P))[:, 2]

            sol = least_squares(res, np.zeros(free.size), loss="soft_l1", f_scale=tau / 3,
                                x_scale=_xscale(g)[free])
            T = _increment(_expand(sol.x, free)) @ T
    return T


def _xscale(g):
    size = max(g.length, g.width)
    return np.r_[np.full(3, g.thickness / size), np.full(3, g.thickness)]


def _automatic_starts(data: _Data, g) -> list:
    """Candidate poses: centre near the points that move most, local normal towards the rig origin."""
    X = data.X
    amp = np.zeros(X.shape[0])
    if data.pt.size:
        np.maximum.at(amp, data.pt, np.linalg.norm(data.disp, axis=1))
    top = np.quantile(amp, 0.98)
    movers = amp >= 0.7 * top if top > 0 else np.ones(X.shape[0], bool)
    c = X[movers].mean(axis=0)
    p0 = X[np.argmin(np.linalg.norm(X - c, axis=1))]
    radius = 0.5 * min(g.length, g.width)
    near = X[np.linalg.norm(X - p0, axis=1) <= radius]
    if near.shape[0] < 3:
        near = X
    _, V = np.linalg.eigh(np.cov((near - near.mean(axis=0)).T))
    n = V[:, 0] if np.dot(V[:, 0], -p0) >= 0 else -V[:, 0]
    ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e_x = ref - n * np.dot(ref, n)
    e_x /= np.linalg.norm(e_x)
    starts = []
    for gamma in np.deg2rad(np.arange(0, 180, 30)):
        ex = math.cos(gamma) * e_x + math.sin(gamma) * np.cross(n, e_x)
        R = np.stack([ex, n, np.cross(ex, n)])  # rows: patch axes in rig coordinates
        starts.append(_pose(R, -R @ p0))
    return starts


# -- stage 2: in-plane search on the motion --------------------------------------------------------------

def _search_in_plane(T, data: _Data, g, comp: _Compliance, max_depth):
    """Move the patch origin over the fitted surface to ``(s0, t0)`` and turn it by ``gamma`` about the
    normal: coarse-to-fine grid search for the largest motion explained by the model's static response."""
    P = _apply(T, data.X)
    m = data.disp @ T[:3, :3].T
    hs, ht = g.length / 12, g.width / 8
    if g.flat:
        gammas, hg = np.deg2rad(np.arange(0, 180, 15)), np.deg2rad(15)
    else:
        gammas, hg = np.deg2rad(np.arange(-20, 21, 10)), np.deg2rad(10)
    grid = [np.arange(-6, 7) * hs, np.arange(-4, 5) * ht, gammas]
    best = None
    for _ in range(2):
        cand = np.stack(np.meshgrid(*grid, indexing="ij"), axis=-1).reshape(-1, 3)
        D = np.stack([_spin(c[2]) @ np.linalg.inv(_surface_frame(g, c[0], c[1])) for c in cand])
        score = np.concatenate([_motion_scores(D[i:i + 128], P, m, data, g, comp, max_depth)
                                for i in range(0, len(D), 128)])
        k = int(np.argmax(score))
        if score[k] <= 0:
            return T
        best = D[k]
        fine = np.arange(-4, 5) / 4
        grid = [cand[k, 0] + fine * hs, cand[k, 1] + fine * ht, cand[k, 2] + np.arange(-2, 3) / 4 * hg]
    return best @ T


def _motion_scores(D, P, m, data, g, comp, max_depth):
    """Explained motion (C,) for candidate moves D (C, 4, 4) of the patch-frame points P (N, 3); -1 where
    fewer than 6 points stay on the patch or the motion opposes the model's (alpha <= 0)."""
    std = g.from_patch(np.einsum("cij,nj->cni", D[:, :3, :3], P) + D[:, None, :3, 3])
    sel = _inside(std.reshape(-1, 3), g).reshape(std.shape[:2]) & (np.abs(std[..., 2]) <= max_depth)
    w = sel[:, data.pt].astype(float)  # (C, S)
    mm = m @ np.swapaxes(D[:, :3, :3], 1, 2)  # (C, S, 3)
    pp = comp(std[:, data.pt, :2], data.du[None])
    onehot = np.eye(data.n_frames)[data.fr]  # (S, nf)
    tot = (w @ onehot).clip(1e-12)

    def centred(v):
        mean = np.swapaxes(np.swapaxes(w[..., None] * v, 1, 2) @ onehot, 1, 2) / tot[..., None]
        return v - mean[:, data.fr]

    mc, pc = centred(mm), centred(pp)
    wpc = w[..., None] * pc
    mp = (wpc * mc).sum(axis=(1, 2))
    p2 = (wpc * pc).sum(axis=(1, 2))
    ess = np.where((p2 > 0) & (mp > 0), mp**2 / np.where(p2 > 0, p2, 1.0), -1.0)
    return np.where(sel.sum(axis=1) >= MIN_POINTS, ess, -1.0)


# -- stage 3: joint refinement -------------------------------------------------------------------------

def _refine(T, data: _Data, g, comp, max_depth, use_motion, free=ALL_DOF):
    """Distances and motion together over the six pose coordinates, outer re-selection of the points.

    The motion's ``alpha`` and ``beta_k`` are eliminated in closed form (variable projection). Residuals are
    scaled by robust (MAD) scales re-estimated per round; each point's motion samples together weigh as much
    as its one distance: the motion only has to fix the in-plane position, which the distances leave loose,
    and its model error must not tilt the surface. Returns (pose, selection, least-squares result, alpha,
    success)."""
    sig_d, sig_m = max(max_depth / 10, 2e-5), 1.0
    nf = data.n_frames
    prev, sol, sel, alpha = None, None, None, 0.0
    for _ in range(10):
        std = g.from_patch(_apply(T, data.X))
        sel = _inside(std, g) & (np.abs(std[:, 2]) <= max_depth)
        if sel.sum() < MIN_POINTS:
            return T, sel, sol, alpha, False
        if prev is not None and np.array_equal(sel, prev):
            break
        prev = sel
        X = data.X[sel]
        s_ok = sel[data.pt] & use_motion
        pt = (np.cumsum(sel) - 1)[data.pt[s_ok]]
        fr, disp, du = data.fr[s_ok], data.disp[s_ok], data.du[s_ok]
        w2 = 1.0 / np.bincount(pt, minlength=X.shape[0]).clip(1)[pt]
        if use_motion and sol is None:  # first round: scale of the motion misfit at the start
            r_m, alpha, _ = _motion_fit(disp @ T[:3, :3].T, comp(std[sel][pt, :2], du), fr, nf, w2)
            sig_m = max(1.4826 * np.median(np.abs(r_m)), 1e-7)

        def raw(xi, T=T, X=X, pt=pt, fr=fr, disp=disp, du=du, w2=w2):
            Tz = _increment(xi) @ T
            std = g.from_patch(_apply(Tz, X))
            if not pt.size:
                return std[:, 2], np.zeros((0, 3)), 0.0
            r_m, a, _ = _motion_fit(disp @ Tz[:3, :3].T, comp(std[pt, :2], du), fr, nf, w2)
            return std[:, 2], r_m, a

        w = np.sqrt(w2)

        def res(z, w=w, sig_d=sig_d, sig_m=sig_m):
            xi = _expand(z, free)
            r_d, r_m, _ = raw(xi)
            # a weak pull to the start keeps directions along which the surface slides into itself put
            return np.r_[r_d / sig_d, (r_m * (w / sig_m)[:, None]).ravel(), 1e-3 * xi / _xscale(g)]

        sol = least_squares(res, np.zeros(free.size), loss="soft_l1", f_scale=3.0, x_scale=_xscale(g)[free],
                            xtol=1e-10, ftol=1e-10)
        T = _increment(_expand(sol.x, free)) @ T
        r_d, r_m, alpha = raw(np.zeros(6))
        sig_d = max(1.4826 * np.median(np.abs(r_d)), 1e-6)
        if r_m.size:
            sig_m = max(1.4826 * np.median(np.abs(r_m)), 1e-7)
    return T, sel, sol, alpha, True


def _choose_turn(T, initial):
    """Of the two poses related by the half-turn about the normal, the one nearest ``initial`` (else the one
    whose +x axis points along the rig's +x, or +y when it is perpendicular)."""
    F = _HALF_TURN @ T
    if initial is not None:
        return T if np.trace(T[:3, :3] @ initial[:3, :3].T) >= np.trace(F[:3, :3] @ initial[:3, :3].T) else F
    x_axis = T[0, :3]
    key = x_axis[0] if abs(x_axis[0]) > 1e-3 else x_axis[1]
    return T if key >= 0 else F


# -- public --------------------------------------------------------------------------------------------

def register(meas: MeasurementSet, model: PatchModel, *, frames: int = 10, initial: np.ndarray | None = None,
             max_depth=None, inputs=None) -> Registration:
    """Fit the rigid pose of the model's patch to the points seen in the first ``frames`` frames.

    Parameters
    ----------
    meas : MeasurementSet
        Rig-frame set (``frame == 'rig'``); ``reference`` of each point is its position in its birth frame
        (``meta['reference_frame_index']``; without it, the undeformed position at zero input).
    model : PatchModel
        Its geometry (and the static response to the inputs, for the in-plane position) is used.
    frames : int
        Points seen (and born) in the first ``frames`` frames are fitted; their motion there places the patch
        in its plane.
    initial : ndarray of shape (4, 4), optional
        Starting ``patch_from_rig``; without it the start is found automatically.
    max_depth : float, optional
        Points farther than this from the epicardium (m) are off the patch; default a quarter of the
        thickness, as :func:`tracker.tracking.locate_points`.
    inputs : ndarray of shape (n_frames, n_u), optional
        Input columns in the model's order replacing the recorded ones for the motion fit: without a recorded
        input, :func:`deformation_signal` (the motion fit's scale ``alpha`` is free, so a signal proportional to
        the input's change is all it needs).

    Returns
    -------
    Registration
        ``converged=False`` with a message when the surface does not explain the points it covers.

    Raises
    ------
    InputError
        Fewer than 6 points in the first frames, a ``meta.reference_frame_index`` of the wrong length (no file
        named: the caller attaches it).
    ValueError
        Wrong frame, bad ``frames`` or ``max_depth``, a bad ``initial`` (InputError, field ``initial``).
    """
    if meas.frame != "rig":
        raise ValueError(f"measurements: frame 'rig' expected for registration, got {meas.frame!r}")
    if int(frames) < 1:
        raise ValueError(f"frames: >= 1 expected, got {frames}")
    g = model.mesh.geometry
    max_depth = 0.25 * g.thickness if max_depth is None else float(max_depth)
    if not max_depth > 0:
        raise ValueError(f"max_depth: positive distance in m expected, got {max_depth}")
    initial = None if initial is None else _check_pose(initial, "initial")
    data = _data(meas, model, int(frames), inputs)
    comp = _Compliance(model)
    if inputs is not None and data.du.shape[1] != comp.values.shape[-1]:
        raise ValueError(f"inputs: {comp.values.shape[-1]} columns expected, got {data.du.shape[1]}")
    notes = []
    moving = data.du.size > 0 and comp.scale > 0 and np.abs(data.du).max() > 0
    if not moving:
        notes.append("no input change in the first frames: position along the surface from the start, "
                     "turn from the curvature")

    taus = [g.thickness, 0.5 * g.thickness, max_depth]
    if initial is None:
        starts = [_fit_surface(T0, data.X, g, taus) for T0 in _automatic_starts(data, g)]
        T = min(starts, key=lambda T: _trimmed_cost(T, data.X, g, max_depth))
        if moving:
            T = _search_in_plane(T, data, g, comp, max_depth)
    else:
        T = _fit_surface(initial, data.X, g, taus[1:], ALL_DOF if moving else NO_SLIDE)
    T, sel, sol, alpha, ok = _refine(T, data, g, comp, max_depth, moving, ALL_DOF if moving else NO_SLIDE)
    T = _choose_turn(T, initial)
    T[:3, :3] = Rotation.from_matrix(T[:3, :3]).as_matrix()  # re-orthonormalise

    std_all = g.from_patch(_apply(T, meas.reference))
    on_patch = _inside(std_all, g) & (np.abs(std_all[:, 2]) <= max_depth)
    rms = float(np.sqrt(np.mean(std_all[on_patch, 2] ** 2))) if on_patch.any() else float("nan")
    n_points = int(sel.sum()) if ok else 0
    failure = _failure(ok, n_points, sel, _inside(g.from_patch(_apply(T, data.X)), g), rms, sol, max_depth)
    if failure is None and moving and alpha <= 0:
        notes.append("the measured motion opposes the model's response to the inputs (alpha <= 0)")
    head = (f"{n_points} points fitted, RMS distance {rms * 1e3:.3g} mm, {int(on_patch.sum())} of "
            f"{meas.n_points} points on the patch") if failure is None else f"registration failed; {failure}"
    return Registration(T, rms, on_patch, n_points, failure is None, "; ".join([head] + notes))


def _failure(ok, n_points, sel, footprint, rms, sol, max_depth) -> str | None:
    """Why the fit is not accepted (None if it is)."""
    if not ok or n_points < MIN_POINTS:
        return f"fewer than {MIN_POINTS} points within {max_depth * 1e3:.2g} mm of the patch's surface"
    frac = sel.sum() / max(footprint.sum(), 1)
    if frac < 0.5:
        return (f"the surface explains only {frac:.0%} of the {int(footprint.sum())} points over the patch "
                f"(within {max_depth * 1e3:.2g} mm)")
    if not rms <= 0.5 * max_depth:
        return f"RMS distance {rms * 1e3:.3g} mm to the surface exceeds {0.5 * max_depth * 1e3:.3g} mm"
    if sol is not None and sol.status <= 0:
        return f"least squares did not converge: {sol.message}"
    return None


def deformation_signal(meas: MeasurementSet, frames: int = 10) -> np.ndarray:
    """A stand-in for an unrecorded input in the motion fit: the dominant deformation of the first frames.

    The displacements since the first frame of the points seen in every one of the first ``frames`` frames, less
    each frame's mean displacement over the points (a rigid translation, which the motion fit's offsets absorb
    anyway), stacked per frame into a (K, 3N) matrix; its first left singular vector times its singular value is
    the signal, one value per frame (zero after the window). A patch loaded by one input deforms in proportion to
    that input's change (docs/model.md "Registration"), so its time course is, up to the scale the motion fit
    leaves free, the input's. Returns (n_frames, 1); all zeros when fewer than :data:`MIN_POINTS` points are seen
    throughout the window (the surface alone then places the patch).
    """
    K = min(int(frames), meas.n_frames)
    out = np.zeros((meas.n_frames, 1))
    if K < 2:
        return out
    P = meas.positions[:K]
    full = np.isfinite(P).all(axis=(0, 2))
    if full.sum() < MIN_POINTS:
        return out
    D = P[:, full] - P[0, full]
    D = D - D.mean(axis=1, keepdims=True)
    U, S, _ = np.linalg.svd(D.reshape(K, -1), full_matrices=False)
    s = U[:, 0] * S[0]
    out[:K, 0] = s if s.sum() >= 0 else -s
    return out


def to_patch_frame(meas: MeasurementSet, reg: Registration) -> MeasurementSet:
    """The set in the patch frame: positions, covariances (``R C R^T``) and reference transformed; points off
    the patch (``reg.on_patch`` false) dropped, ids of the others kept; ``meta['registration']`` records the
    pose and the dropped ids.

    Inputs are copied unchanged (``respiration_*`` columns are defined in the patch frame).

    Raises
    ------
    InputError
        None of the points lies on the patch (field ``registration``; no file named).
    """
    if meas.frame != "rig":
        raise ValueError(f"measurements: frame 'rig' expected, got {meas.frame!r}")
    if reg.on_patch.shape != (meas.n_points,):
        raise ValueError(f"registration: on_patch for {meas.n_points} points expected, got {reg.on_patch.shape}")
    keep = np.flatnonzero(reg.on_patch)
    if keep.size == 0:
        raise InputError(None, f"none of the {meas.n_points} points lies on the patch", "registration")
    R, t = reg.rotation, reg.translation
    pos = meas.positions[:, keep] @ R.T + t  # NaN stays NaN
    cov = _rotated_covariances(meas.covariances, keep, R)
    meta = dict(meas.meta)
    meta["frame"] = "patch"
    info = reg.info()
    info["dropped_point_ids"] = meas.point_ids[~reg.on_patch].tolist()
    meta["registration"] = info
    rfi = meta.get("reference_frame_index")
    if rfi is not None:
        meta["reference_frame_index"] = np.asarray(rfi).reshape(-1)[keep].tolist()
    # the same points in another frame (R C R^T of a validated C is one): not validated again
    return MeasurementSet._derived(meas, point_ids=meas.point_ids[keep], positions=pos, covariances=cov,
                                   reference=meas.reference[keep] @ R.T + t, frame="patch",
                                   views=meas.views[:, keep], reprojection_rms=meas.reprojection_rms[:, keep],
                                   meta=meta)


_ROTATE_POINTS = 64
"""Points whose covariances :func:`_rotated_covariances` rotates at a time."""


def _rotated_covariances(cov: np.ndarray, keep: np.ndarray, R: np.ndarray) -> np.ndarray:
    """``R @ cov[:, keep] @ R.T`` (K, P_keep, 3, 3), :data:`_ROTATE_POINTS` points at a time: the result is the
    only array of its size made (the expression makes three), with the same numbers and the same memory layout
    (that of ``cov[:, keep]``, which later reductions follow)."""
    probe = cov[: min(2, cov.shape[0]), keep[:2]]     # the layout numpy gives cov[:, keep]
    order = np.argsort(probe.strides, kind="stable")[::-1]   # outermost axis first
    out = np.empty(tuple((cov.shape[0], keep.size, 3, 3)[i] for i in order)).transpose(np.argsort(order))
    for j in range(0, keep.size, _ROTATE_POINTS):
        out[:, j:j + _ROTATE_POINTS] = R @ cov[:, keep[j:j + _ROTATE_POINTS]] @ R.T
    return out


# -- registration as the stages use it (heartcv fit, heartcv track --params) --------------------------------

def register_rig_measurements(meas: MeasurementSet, model: PatchModel, frames: int = 10, inputs=None):
    """Register a rig-frame measurement set onto the model (:func:`register`) and bring it into the patch frame.

    Returns
    -------
    patch_meas : MeasurementSet or None
        The patch-frame set (:func:`to_patch_frame`), None when the registration did not converge.
    registration : Registration
        ``converged`` False, with the reason in ``message``, when the surface does not explain the points.

    Raises
    ------
    InputError
        Too few points, or none on the patch (no file named: the caller attaches it).
    """
    reg = register(meas, model, frames=frames, inputs=inputs)
    if not reg.converged:
        return None, reg
    return to_patch_frame(meas, reg), reg


def registration_to_dict(reg: Registration, meas: MeasurementSet) -> dict:
    """The ``registration`` entry of a parameters file (docs/formats.md §12): the transform, its RMS and the ids
    of the points on the patch (ids survive filtering, so the registration can be applied to the same file
    again, :func:`apply_stored_registration`)."""
    return {
        "patch_from_rig": np.asarray(reg.patch_from_rig, float).tolist(),
        "rms_m": float(reg.rms_m),
        "points_on_patch": [int(i) for i in np.asarray(meas.point_ids)[np.asarray(reg.on_patch, bool)]],
        "message": str(reg.message),
    }


def apply_stored_registration(meas: MeasurementSet, registration: dict, source: str = "the parameters file"):
    """Apply a registration stored by :func:`registration_to_dict` to a rig-frame measurement set (``heartcv
    track --params``): the transform of the file, the points selected by id.

    Parameters
    ----------
    meas : MeasurementSet
        Rig frame.
    registration : dict
        ``patch_from_rig`` (4x4), ``rms_m``, ``points_on_patch`` (point ids).
    source : str
        Where the registration was read (for the ``message`` of the rebuilt :class:`Registration`).

    Raises
    ------
    InputError
        A transform that is not rigid (field ``registration.patch_from_rig``), or none of the registered points
        in the measurement set (``registration.points_on_patch``: the parameters were fitted to another file);
        no file named: the caller attaches the parameters file.
    """
    T = _check_pose(registration.get("patch_from_rig"), "registration.patch_from_rig")
    ids = registration.get("points_on_patch") or []
    on_patch = np.isin(np.asarray(meas.point_ids), np.asarray(ids, np.int64))
    if not on_patch.any():
        raise InputError(None, "none of the registered points is in the measurement file: the parameters were "
                               "fitted to another file", "registration.points_on_patch")
    rms = registration.get("rms_m")
    reg = Registration(patch_from_rig=T, rms_m=float(rms) if isinstance(rms, (int, float)) else float("nan"),
                       on_patch=on_patch, n_points=int(on_patch.sum()), converged=True, message=f"stored in {source}")
    return to_patch_frame(meas, reg)

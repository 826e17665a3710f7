"""One predict/update shape for every estimator, one frame loop, one divergence policy, one registry of names.

Every estimator of heartcv (docs/estimators.md) is a Gaussian filter on a joint state ``z = [x_n; x_l]``: ``x_n``
the M estimated parameters in phi coordinates (M = 0 for the KF, whose parameters are held), ``x_l`` the linear
block (the kinematic state, and the static reference states of :mod:`tracker.reference` when they are estimated).
A variant (:class:`Estimator`) overrides small hooks only:

* ``predict(state, u0, u1, Q_n)``: how the joint density is propagated over one frame (the KF: the linear
  prediction at fixed theta; GE: Rao-Blackwellised Dirac-mixture sampling of the parameter block with exact
  conditional propagation of the linear block; UKF / EKF: the joint unscented / linearised transforms);
* ``constrain(state)``: what is done to the parameter block after a prediction and an update (truncation to the
  box; nothing by default);
* ``parameters(state)``: the physical theta and its standard deviation.

Everything else is shared and lives here (:func:`run_filter`): the measurement update (:func:`tracker.kalman.update`
on ``H_z = [0, H]``), the records per frame, the noise adaptation (:mod:`tracker.adaptive`) and the divergence
policy: a non-finite or runaway state (|phi| > 1e3, |x_l| > 1e3) or a failed factorisation stops the run with
:class:`tracker.tracking.EstimationDiverged`, whose ``partial`` holds the completed steps.

The registry :data:`NAMES` is the one list of estimator names; :func:`variant` returns a variant's class.
"""

from __future__ import annotations

import logging
import time
from typing import Callable

import numpy as np
import scipy.linalg as sla

from .estimator_names import JOINT, MODEL, NAMES  # noqa: F401  (re-exported; the names live in a light module)
from .kalman import GaussianState, update, update_blocks
from .measurements import EstimateSet
from .overdispersion import adjusted, tempered_marginal

__all__ = ["NAMES", "JOINT", "Estimator", "register", "variant", "run_filter", "holdout_points", "RUNAWAY_PHI",
           "RUNAWAY_STATE"]

log = logging.getLogger(__name__)

_VARIANTS: dict[str, type] = {}

# A state beyond these is a diverged filter, not an estimate: stop before it reaches the model (e.g. a Poisson
# ratio that rounds to exactly 0 or 0.5, or displacements of kilometres).
RUNAWAY_PHI = 1e3   # |phi| (log-parameters: a factor e^1000)
RUNAWAY_STATE = 1e3  # |x_l| (m, m/s)


def register(name: str):
    """Class decorator: the variant that implements estimator ``name`` (one of :data:`MODEL`)."""
    if name not in MODEL:
        raise ValueError(f"estimator: one of {MODEL} expected, got {name!r}")

    def deco(cls):
        _VARIANTS[name] = cls
        cls.name = name
        return cls
    return deco


def variant(name: str) -> type:
    """The :class:`Estimator` subclass of ``name`` (one of :data:`MODEL`; the baselines are not Gaussian filters)."""
    if name not in MODEL:
        raise ValueError(f"estimator: one of {MODEL} expected, got {name!r}")
    if name not in _VARIANTS:  # the variants register themselves on import
        from . import joint, tracking  # noqa: F401
    return _VARIANTS[name]


class Estimator:
    """The hooks of one estimator variant (see the module docstring). ``M`` is the size of the parameter block."""

    name = "?"
    M = 0

    def predict(self, state: GaussianState, u0, u1, Q_n) -> tuple[GaussianState, dict]:
        """The one-frame prediction and counters ``{'clipped', 'samples', 'jitter'}``."""
        raise NotImplementedError

    def constrain(self, state: GaussianState) -> tuple[GaussianState, int, int]:
        """``(state, truncation events, low-mass events)``; the default leaves the state alone."""
        return state, 0, 0

    def parameters(self, state: GaussianState) -> tuple[np.ndarray, np.ndarray]:
        """Physical theta (5,) and its standard deviation (5,) at ``state``."""
        raise NotImplementedError

    def meta(self) -> dict:
        """Provenance of the variant's settings for the estimate file."""
        return {}

    @property
    def M_theta(self) -> int:
        """The physical parameters' share of the parameter block (the rest: sampled rates)."""
        return self.M

    @property
    def sampled_rate_names(self) -> tuple:
        """The rates the variant samples, of ``('heart_rate', 'respiration_rate')``; none by default."""
        return ()

    def rate(self, state: GaussianState, name: str):
        """``(mean, std)`` of a sampled rate (Hz) at ``state``; None when the variant does not sample it."""
        return None


class _Runaway(FloatingPointError):
    pass


def _check_runaway(state: GaussianState, M: int, where: str):
    mu, C = state.mean, state.cov
    if not (np.isfinite(mu).all() and np.isfinite(C).all()):
        raise _Runaway(f"non-finite {where}")
    if np.abs(mu[:M]).max(initial=0) > RUNAWAY_PHI or np.abs(mu[M:]).max(initial=0) > RUNAWAY_STATE:
        raise _Runaway(f"runaway {where}: |phi| up to {np.abs(mu[:M]).max(initial=0):.3g}, "
                       f"|x_l| up to {np.abs(mu[M:]).max(initial=0):.3g}")


def _use_block_update(rows, seen, n) -> bool:
    """Whether a frame's update takes :func:`kalman.update_blocks` (O(m n^2)) rather than :func:`kalman.update`
    (O(m^3)): when it has more measurement rows than states and every seen point is seen in all three coordinates
    (its noise a whole 3 x 3 block)."""
    m = 3 * seen.size
    return m > n and bool(rows.reshape(-1, 3)[seen].all())


def block_diag_R(cov_k: np.ndarray) -> np.ndarray:
    """Block-diagonal R (3P, 3P) of per-point covariances (P, 3, 3); unseen points get an identity block
    (their rows are dropped by the update anyway)."""
    P = cov_k.shape[0]
    blocks = np.where(np.isfinite(cov_k).all(axis=(1, 2))[:, None, None], cov_k, np.eye(3))
    R = np.zeros((P, 3, P, 3))
    R[np.arange(P), :, np.arange(P), :] = blocks
    return R.reshape(3 * P, 3 * P)


def _mix64(x) -> np.ndarray:
    """splitmix64's finaliser (Steele, Lea & Flood 2014), elementwise on uint64: a bijection that scatters
    neighbouring integers over the whole range."""
    z = np.asarray(x, np.uint64).copy()
    with np.errstate(over="ignore"):
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def holdout_points(candidates, fraction: float, rng: np.random.Generator, ids=None) -> np.ndarray:
    """The held-out points: ``round(fraction * n)`` of the ``n`` candidates (indices into a measurement set), sorted.

    Each candidate gets a key from its identifier (``ids``, the candidates' point ids in the same order; default the
    candidates themselves) and one 64-bit salt drawn from ``rng``; those with the smallest keys are held out. So a
    track is held out or not whatever the other candidates are: a run whose candidates differ by one track (a
    registration that drops one more point) holds out the same tracks but for one or two (the count follows n),
    and its held-out error compares. Every estimator given the same candidates, fraction and seed holds out the
    same points."""
    c = np.asarray(candidates, int).reshape(-1)
    if not 0.0 <= fraction < 1.0:
        raise ValueError(f"holdout: a fraction in [0, 1) expected, got {fraction}")
    key_ids = c if ids is None else np.asarray(ids, int).reshape(-1)
    if key_ids.shape != c.shape:
        raise ValueError(f"holdout: {c.size} ids expected, got {key_ids.size}")
    n = int(round(fraction * c.size))
    salt = rng.integers(0, np.iinfo(np.int64).max, dtype=np.int64, endpoint=True)
    if not n:
        return np.zeros(0, int)
    keys = _mix64(key_ids.astype(np.int64).view(np.uint64) ^ np.uint64(salt))
    order = np.lexsort((key_ids, keys))
    return np.sort(c[order[:n]])


NEIGHBOURS = 8
"""Updated points whose offsets a point never updated takes the mean of (:meth:`TrackOffsets.fill`)."""


def _innovation_precision(res):
    """``S^{-1} e`` as (P, 3) and the diagonal 3 x 3 blocks of ``S^{-1}`` of a dense :func:`kalman.update` result."""
    L = res.innovation_chol
    L = np.linalg.cholesky(res.innovation_cov) if L is None else np.asarray(L)
    m = L.shape[0]
    ebar = sla.solve_triangular(L, np.asarray(res.innovation), lower=True, check_finite=False)
    s_e = sla.solve_triangular(L, ebar, lower=True, trans="T", check_finite=False).reshape(-1, 3)  # S^-1 e
    Linv, info = sla.lapack.dtrtri(np.asfortranarray(L), lower=1)                   # L^-1 (m^3 / 3 flops)
    if info != 0:
        raise np.linalg.LinAlgError(f"track offsets: singular innovation factor (dtrtri info {info})")
    A = np.ascontiguousarray(np.tril(Linv).reshape(m, -1, 3).transpose(1, 2, 0))   # (P, 3, m)
    return s_e, A @ A.transpose(0, 2, 1)                   # diagonal 3 x 3 blocks of S^-1 = L^-T L^-1


class TrackOffsets:
    """Per-track offsets ``b_p`` (3 per kept point), random walks beside the estimator's state (docs/estimators.md
    §3.9): what a point does that the model cannot (a track sliding on the tissue, motion finer than the mesh).

    Decoupled: the joint update of ``[state; b]`` is done exactly for each frame from a prior without cross-
    covariance (``b`` enters the update as measurement noise of covariance ``P_b``, its gain is ``P_b S^-1``),
    and afterwards the cross-covariance of ``b`` with the state and between points is dropped, keeping one 3 x 3
    covariance per point. The state's update is therefore the estimator's own with ``R + P_b``; the cost is one
    triangular inverse of the innovation's factor per frame.
    """

    def __init__(self, n_points: int, std_per_frame: float):
        if not (np.isfinite(std_per_frame) and std_per_frame > 0):
            raise ValueError(f"drift: a positive standard deviation per frame expected, got {std_per_frame}")
        self.q2 = float(std_per_frame) ** 2
        self.mean = np.zeros(3 * n_points)
        self.cov = np.zeros((n_points, 3, 3))
        self.n_updates = 0
        self.updated = np.zeros(n_points, bool)
        self._fill = None     # (updated mask, points filled, their neighbours) of the last fill

    def predict(self) -> None:
        self.cov += self.q2 * np.eye(3)

    def covariance(self) -> np.ndarray:
        """Block-diagonal (3P, 3P) covariance of the offsets."""
        P = self.cov.shape[0]
        out = np.zeros((P, 3, P, 3))
        out[np.arange(P), :, np.arange(P), :] = self.cov
        return out.reshape(3 * P, 3 * P)

    def update(self, res, points=None) -> None:
        """The offsets' part of the frame's update from the estimator's :class:`UpdateResult`: of an update over
        all the points' rows (NaN where unseen; ``points`` None), or over the rows of ``points`` (indices, each
        seen in its three coordinates) only."""
        if res.dof == 0:
            return
        if points is None:
            used = np.asarray(res.used).reshape(-1, 3)
            pts = np.flatnonzero(used.all(axis=1))
        else:
            pts = np.asarray(points, np.int64).reshape(-1)
        if pts.size * 3 != res.dof:
            raise ValueError("track offsets: a point must be seen in all three coordinates or none")
        if res.innovation_factor is not None:             # S factored low-rank (kalman.update_blocks)
            s_e = res.innovation_factor.solve(res.innovation).reshape(-1, 3)
            s_pp = res.innovation_factor.inverse_blocks()
        else:
            s_e, s_pp = _innovation_precision(res)
        Pb = self.cov[pts]
        b = self.mean.reshape(-1, 3)
        b[pts] += np.einsum("pij,pj->pi", Pb, s_e)
        Pb_new = Pb - Pb @ s_pp @ Pb
        self.cov[pts] = 0.5 * (Pb_new + np.swapaxes(Pb_new, 1, 2))
        self.updated[pts] = True
        self.n_updates += 1

    def recentre(self, points=None) -> np.ndarray:
        """Remove the offsets' common translation: ``c`` (3,), the mean offset of ``points`` (indices: the points
        of this frame's update; None: every point updated so far), is subtracted from their offsets and returned,
        for the caller to add to the state's rigid translation (docs/estimators.md §3.9 "Common motion"). The
        other points keep theirs, so their predictions move with the translation."""
        sel = np.flatnonzero(self.updated) if points is None else np.asarray(points, np.int64).reshape(-1)
        if sel.size == 0:
            return np.zeros(3)
        b = self.mean.reshape(-1, 3)
        c = b[sel].mean(axis=0)
        b[sel] -= c
        return c

    def fill(self, positions, neighbours: int = NEIGHBOURS) -> None:
        """Give the points never updated (held out, not yet seen) the mean offset of their ``neighbours`` nearest
        updated points (by ``positions`` (P, 3), the points' references): the offsets' field where a point was
        never measured, from the other tracks only (docs/estimators.md §3.9 "Points never updated")."""
        from scipy.spatial import cKDTree

        if self.updated.all() or not self.updated.any():
            return
        if self._fill is None or not np.array_equal(self._fill[0], self.updated):   # the neighbours change only
            src = np.flatnonzero(self.updated)                                     # when points get updated
            dst = np.flatnonzero(~self.updated)
            n = min(int(neighbours), src.size)
            _, idx = cKDTree(np.asarray(positions)[src]).query(np.asarray(positions)[dst], k=n)
            self._fill = (self.updated.copy(), dst, src[np.asarray(idx).reshape(dst.size, n)])
        _, dst, near = self._fill
        b = self.mean.reshape(-1, 3)
        b[dst] = b[near].mean(axis=1)

    def summary(self) -> dict:
        b = np.linalg.norm(self.mean.reshape(-1, 3), axis=1)
        return {"std_per_frame_m": float(np.sqrt(self.q2)), "final_norm_median_m": float(np.median(b)),
                "final_norm_max_m": float(b.max(initial=0.0))}


def run_filter(est: Estimator, meas, prior: GaussianState, H, reference, keep, u, trans, Q_n, *,
               joseph: bool = False, adapt=None, progress: Callable[[int, int], None] | None = None,
               meta: dict | None = None, heldout=None, drift: float | None = None,
               translation=None, overdispersion=None) -> EstimateSet:
    """The frame loop shared by every estimator.

    Per frame k: ``k > 0``: predict (``est.predict``), constrain; record the one-step prediction
    ``reference + r(t_k) + H x_l`` of every kept point; update with the points seen in frame k (NaN rows dropped),
    constrain; record the filtered positions, the state, the parameters and the NIS.

    Parameters
    ----------
    est : Estimator
    meas : MeasurementSet (patch frame)
    prior : GaussianState           the joint prior of ``[x_n; x_l]`` (size M + n_l)
    H : ndarray (3 P_used, n_l)     measurement matrix of the kept points on the linear block
    reference : ndarray (P_used, 3) their reference positions
    keep : ndarray (P_used,) int    the kept points' indices in ``meas``
    u : ndarray (K, n_u)            the model's inputs per frame
    trans : ndarray (K, 3)          the known rigid translation per frame
    Q_n : ndarray (M, M)            the parameters' random walk per frame (the adaptation may change it)
    adapt : tracker.adaptive.NoiseAdaptation, optional
        Sets the parameters' random walk and the scale of the measurement covariances from the innovations so far.
    meta : dict                     merged into the estimate file's meta
    heldout : (H,) int, optional    points (indices into ``meas``, among ``keep``) left out of every update: their
        one-step predictions and innovations are recorded as for the others (the model's prediction of a point it
        never saw); ``meta.heldout_points`` lists their ids
    drift : float, optional
        Per-track offsets (docs/estimators.md §3.9): each kept point's measurement is ``y_p = ... + b_p + v_p`` with
        ``b_p`` a random walk of this standard deviation per coordinate and frame (m), estimated beside the state by
        the decoupled update of :class:`TrackOffsets`. None or 0: no offsets.
    translation : sequence of int, optional
        Where the linear block's rigid translation (3 states moving every point alike) and its previous values
        (:attr:`tracker.unknown_input.InputBlock.translation_states`) start in ``x_l``. With offsets, after every
        update their common translation moves into these (:meth:`TrackOffsets.recentre`): the seen points'
        predictions are unchanged, the model's rigid motion carries what all the tracks share, and the points it
        never updated (held out, born later) get it.
    overdispersion : tracker.overdispersion.Overdispersion, optional
        With estimated parameters (M > 0): their update tempered by the over-dispersion of their shifts over the
        frames so far (docs/estimators.md §3.11); None: the plain update.

    Raises
    ------
    tracker.tracking.EstimationDiverged
        The state became non-finite or ran away, or a factorisation failed; ``partial`` holds the steps done.
    """
    from .tracking import EstimationDiverged

    M = est.M
    K = meas.n_frames
    n_l = prior.mean.size - M
    Hz = np.hstack([np.zeros((H.shape[0], M)), H])
    y_all = meas.positions[:, keep, :].reshape(K, -1)
    P_all = meas.n_points
    held_rows = np.zeros(y_all.shape[1], bool)
    if heldout is not None and len(heldout):
        held_rows = np.repeat(np.isin(np.asarray(keep), np.asarray(heldout)), 3)

    state_mean = np.full((K, n_l), np.nan)
    state_var = np.full((K, n_l), np.nan)
    theta = np.full((K, 5), np.nan)
    theta_std = np.full((K, 5), np.nan)
    Mp = est.M_theta                       # the physical parameters' phi (a sampled heart rate follows them)
    phi_mean = np.full((K, Mp), np.nan) if Mp else None
    phi_cov = np.full((K, Mp, Mp), np.nan) if Mp else None
    rates = {name: np.full((K, 2), np.nan) for name in est.sampled_rate_names}
    predictions = np.full((K, P_all, 3), np.nan)
    filtered = np.full((K, P_all, 3), np.nan)
    innovations = np.full((K, P_all, 3), np.nan)
    nis = np.full(K, np.nan)
    dof = np.zeros(K, np.int64)
    trunc = np.zeros(K, np.int64)
    step_time = np.zeros(K)
    counters = {"clipped": 0, "low_mass": 0, "jitter": 0}
    Q_n = np.asarray(Q_n, float)
    loglik = np.full(K, np.nan)

    def result(done):
        md = dict(meta or {})
        md.update(est.meta())
        md["counters"] = dict(counters, **md.get("counters", {}))
        if adapt is not None:
            md["adaptation"] = adapt.summary()
        md["log_likelihood"] = float(np.nansum(loglik[1:done]))   # innovations of frames 1 .. done-1
        if held_rows.any():
            md["heldout_points"] = [int(i) for i in np.asarray(meas.point_ids)[np.asarray(heldout)]]
        if offsets is not None:
            md["track_offsets"] = offsets.summary()
        if od is not None:
            md["parameter_overdispersion"] = od.summary()
        return EstimateSet(est.name, meas.times, meas.point_ids, state_mean, state_var, theta, theta_std,
                           predictions, innovations, nis, dof, trunc, step_time, done, meta=md, phi_mean=phi_mean,
                           phi_cov=phi_cov, filtered=filtered, heart_rate=rates.get("heart_rate"),
                           respiration_rate=rates.get("respiration_rate"),
                           log_likelihood=np.where(np.arange(K) < done, loglik, np.nan))

    offsets = TrackOffsets(len(keep), drift) if drift else None
    od = overdispersion if M else None

    state = prior
    for k in range(K):
        t0 = time.perf_counter()
        events = 0
        try:
            if k > 0:
                if offsets is not None:
                    offsets.predict()
                q_n = Q_n if adapt is None else adapt.random_walk(k, Q_n)
                state, info = est.predict(state, u[k - 1], u[k], q_n)
                counters["clipped"] += info.get("clipped", 0)
                counters["jitter"] += info.get("jitter", 0)
                _check_runaway(state, M, "prediction")
                state, ev, low = est.constrain(state)
                events += ev
                counters["low_mass"] += low
            predicted = state
            offset = (reference + trans[k]).reshape(-1)
            if offsets is not None:
                offset = offset + offsets.mean
            pred_y = offset + H @ state.mean[M:]
            y_k = np.where(held_rows, np.nan, y_all[k]) if held_rows.any() else y_all[k]
            rows = np.isfinite(y_k)                 # the update uses these rows only: R is built for their
            seen = np.flatnonzero(rows.reshape(-1, 3).any(axis=1))     # points (3 rows each), never 3P x 3P
            sub = rows.reshape(-1, 3)[seen].reshape(-1)
            blocks = meas.covariances[k, keep][seen]     # one frame's: no copy of all frames'
            blocks = np.where(np.isfinite(blocks).all(axis=(1, 2))[:, None, None], blocks, np.eye(3))
            if adapt is not None:
                blocks = adapt.measurement_scale(k) * blocks
            if offsets is not None:
                blocks = blocks + offsets.cov[seen]
            res = None
            if _use_block_update(rows, seen, Hz.shape[1]):   # many points: S is never formed
                try:
                    res = update_blocks(state, y_k[rows], Hz[rows], blocks, offset[rows])
                except np.linalg.LinAlgError:   # a block of R not positive definite: the dense form needs only S
                    res = None
            if res is None:
                R = block_diag_R(blocks)[np.ix_(sub, sub)]
                res = update(state, y_k[rows], Hz[rows], R, offset[rows], joseph=joseph)
            if od is not None and res.dof:
                posterior = res.state
                if od.kappa > 1.0:             # the parameters' likelihood raised to 1 / kappa
                    try:
                        posterior = adjusted(res.state, *tempered_marginal(state, res.state, M, od.kappa), M)
                        od.frames_adjusted += 1
                    except (np.linalg.LinAlgError, sla.LinAlgError):   # a marginal not positive definite
                        posterior = res.state
                od.observe(state, res.state, M)   # state: this frame's prediction
                state = posterior
            else:
                state = res.state
            if offsets is not None:
                offsets.update(res, points=seen)
                if translation:
                    c = offsets.recentre(seen)
                    mean = np.array(state.mean)
                    for i in translation:
                        mean[M + i:M + i + 3] += c
                    state = GaussianState(mean, state.cov)
                offsets.fill(reference)
            counters["jitter"] += res.jitter_events
            _check_runaway(state, M, "update")
            state, ev, low = est.constrain(state)
            events += ev
            counters["low_mass"] += low
            if adapt is not None:
                adapt.observe(k, predicted, state, res)
        except (_Runaway, FloatingPointError, np.linalg.LinAlgError, sla.LinAlgError) as exc:
            log.warning("%s: the estimate diverged at step %d (%s)", est.name, k, exc)
            raise EstimationDiverged(k, result(k)) from None
        step_time[k] = time.perf_counter() - t0
        predictions[k, keep] = pred_y.reshape(-1, 3)
        filtered[k, keep] = ((reference + trans[k]).reshape(-1) + (0 if offsets is None else offsets.mean)
                             + H @ state.mean[M:]).reshape(-1, 3)
        innovations[k, keep] = (y_all[k] - pred_y).reshape(-1, 3)
        state_mean[k] = state.mean[M:]
        state_var[k] = np.diag(state.cov)[M:]
        if Mp:
            phi_mean[k] = state.mean[:Mp]
            phi_cov[k] = state.cov[:Mp, :Mp]
        for name, trace in rates.items():
            trace[k] = est.rate(state, name)
        theta[k], theta_std[k] = est.parameters(state)
        nis[k] = res.nis
        loglik[k] = res.log_likelihood if res.dof else np.nan
        dof[k] = res.dof
        trunc[k] = events
        if progress is not None:
            progress(k + 1, K)
    return result(K)

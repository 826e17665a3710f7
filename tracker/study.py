"""Monte-Carlo study of the parameter estimators on the model itself (paper §VI.A, Fig. 2).

Protocol of run ``r`` of a study with ``runs`` runs and seed ``seed`` (every run is independent and can be
recomputed alone):

1. ``g = default_rng(SeedSequence(seed).spawn(runs)[r])``;
2. draw the initial parameter estimate ``phi0 ~ N(phi_true, diag(prior_std_phi^2))`` from ``g`` in the
   estimator's coordinates (:mod:`tracker.params`), redrawing until it lies strictly inside the box
   (at most :data:`MAX_PRIOR_TRIES` draws); ``theta0 = theta_from_x(phi0)`` for the estimated parameters,
   the model file's values for the others;
3. simulate the model with the model file's theta for ``steps`` frames with the generator
   ``g.spawn(1)[0]`` (independent of the number of redraws) and convert it to measurements;
4. run every requested estimator from ``theta0``: ``ge``/``ukf``/``ekf`` with
   :func:`tracker.joint.run_joint`, ``kf`` with :func:`tracker.tracking.run_kalman` (the parameters held
   at the initial guess). A run that diverges is recorded and left out of that estimator's statistics.

Statistics per estimator (:func:`estimator_statistics`), per step k and estimated parameter j, over the
runs it completed: the paper's mean absolute error ``mean_r |theta_hat - theta_true|`` and its variance
(ddof 1), the RMSE, the NEES of the parameter block in phi coordinates ``e^T C^-1 e`` and its average over
runs (ANEES) against the two-sided 95 % chi-square band of :func:`chi2_band`, and NIS per degree of freedom.
"""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
import hashlib
import logging
from typing import Callable

import numpy as np
from scipy import stats

from .estimators import JOINT as JOINT_ESTIMATORS
from .estimators import MODEL as ESTIMATORS
from .files import InputError
from .joint import run_joint
from .model import PatchModel
from .params import NAMES
from .simulate import simulate, to_measurements
from .tracking import EstimationDiverged, locate_points, run_kalman

__all__ = ["ESTIMATORS", "MAX_PRIOR_TRIES", "EstimatorRuns", "RunResult", "StudyResult", "EstimatorStats",
           "chi2_band", "draw_initial_phi", "run_single", "run_study", "estimator_statistics",
           "check_estimators", "model_fingerprint", "summary", "arrays"]

log = logging.getLogger(__name__)

MAX_PRIOR_TRIES = 1000


# -- one run ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Trace:
    """One estimator over one run: per-step arrays (NaN after a divergence), ``diverged_step`` -1 if none."""

    theta: np.ndarray  # (K, 5) SI
    phi_mean: np.ndarray | None  # (K, M) joint estimators only
    phi_cov: np.ndarray | None  # (K, M, M)
    nis: np.ndarray  # (K,)
    nis_dof: np.ndarray  # (K,) int
    step_time: np.ndarray  # (K,) s
    diverged_step: int = -1


@dataclass(frozen=True)
class RunResult:
    """Run ``index``: the initial draw ``phi0`` (M,) / ``theta0`` (5,), its tries and a trace per estimator."""

    index: int
    phi0: np.ndarray
    theta0: np.ndarray
    tries: int
    traces: dict


def check_estimators(estimators, n_estimated: int) -> tuple:
    """Validated, de-duplicated estimator names; ValueError naming an unknown one, InputError (field
    ``estimation.estimate``, no file named) for a joint estimator on a model that estimates no parameter."""
    names = tuple(dict.fromkeys(estimators))
    if not names:
        raise ValueError(f"estimators: at least one of {ESTIMATORS} expected")
    for n in names:
        if n not in ESTIMATORS:
            raise ValueError(f"estimators: unknown estimator {n!r}; choose from {ESTIMATORS}")
    joint = [n for n in names if n in JOINT_ESTIMATORS]
    if joint and n_estimated == 0:
        raise InputError(None, f"empty, but {', '.join(joint)} need at least one estimated parameter (the kf "
                               "alone runs without)", "estimation.estimate")
    return names


def draw_initial_phi(phi_true, std, lower, upper, rng: np.random.Generator, accept=None,
                     max_tries: int = MAX_PRIOR_TRIES):
    """Draw ``phi0 ~ N(phi_true, diag(std^2))`` until ``lower < phi0 < upper`` (and ``accept(phi0)``).

    Parameters
    ----------
    phi_true, std, lower, upper : ndarray of shape (M,)
    rng : numpy.random.Generator
    accept : callable(phi0) -> bool, optional
        Extra acceptance test (e.g. the theta box after the round trip).

    Returns
    -------
    phi0 : ndarray of shape (M,)
    tries : int
        Draws used (1 if the first was inside).

    Raises
    ------
    InputError
        If no draw of ``max_tries`` lies inside the box: the model file's prior is too wide for its box (field
        ``estimation.prior_std``, no file named).
    """
    phi_true, std = np.asarray(phi_true, float), np.asarray(std, float)
    for tries in range(1, max_tries + 1):
        phi0 = phi_true + std * rng.standard_normal(phi_true.size)
        if np.all(phi0 > lower) and np.all(phi0 < upper) and (accept is None or accept(phi0)):
            return phi0, tries
    raise InputError(None, f"none of {max_tries} draws of the initial parameters N(phi_true, "
                           f"diag({np.round(std, 6).tolist()}^2)) lies inside the box estimation.bounds",
                     "estimation.prior_std")


def _trace(est, has_phi: bool) -> Trace:
    return Trace(np.array(est.theta), np.array(est.phi_mean) if has_phi else None,
                 np.array(est.phi_cov) if has_phi else None, np.array(est.nis), np.array(est.nis_dof),
                 np.array(est.step_time))


def _diverged_trace(K: int, M: int, has_phi: bool, step: int) -> Trace:
    nan = lambda *s: np.full(s, np.nan)  # noqa: E731
    return Trace(nan(K, 5), nan(K, M) if has_phi else None, nan(K, M, M) if has_phi else None, nan(K),
                 np.zeros(K, np.int64), nan(K), int(step))


def _prior_draw(model: PatchModel, seed_sequence: np.random.SeedSequence):
    """Steps 1 and 2 of a run (module docstring): ``(generator, phi0, theta0, tries)``."""
    cfg = model.config
    space = cfg.parameter_space()
    g = np.random.default_rng(seed_sequence)
    lower, upper = space.bounds_phi
    idx = space.index

    def inside_theta(phi0):
        th = space.theta_from_x(phi0)[idx]
        return bool(np.all(th >= space.lower[idx]) and np.all(th <= space.upper[idx]))

    phi0, tries = draw_initial_phi(space.x_from_theta(cfg.theta), cfg.prior_std_phi(), lower, upper, g,
                                   accept=inside_theta)
    theta0 = np.array(cfg.theta, float)  # fixed parameters exactly as in the model file (no phi round trip)
    theta0[idx] = space.theta_from_x(phi0)[idx]
    return g, phi0, theta0, tries


def run_single(model: PatchModel, index: int, *, seed: int, runs: int, steps: int, estimators) -> RunResult:
    """Run ``index`` of the study (module docstring): prior draw, simulation, every estimator."""
    cfg = model.config
    M = cfg.parameter_space().dim
    g, phi0, theta0, tries = _prior_draw(model, np.random.SeedSequence(seed).spawn(runs)[index])
    sim = simulate(model, (steps - 1) / cfg.frame_rate, g.spawn(1)[0])
    meas = to_measurements(sim)
    if meas.n_frames != steps:  # pragma: no cover - guards the duration arithmetic
        raise RuntimeError(f"simulation gave {meas.n_frames} frames, {steps} expected")
    pts = locate_points(model, meas)
    traces = {}
    for name in estimators:
        joint = name in JOINT_ESTIMATORS
        try:
            if joint:
                est = run_joint(model, meas, name, theta0=theta0, points=pts)
            else:
                est = run_kalman(model, meas, theta=theta0, points=pts)
        except (EstimationDiverged, np.linalg.LinAlgError) as exc:
            traces[name] = _diverged_trace(steps, M, joint, getattr(exc, "step", 0))
            continue
        traces[name] = _trace(est, joint)
    return RunResult(index, phi0, theta0, tries, traces)


# -- the study ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class EstimatorRuns:
    """One estimator over all runs (diverged runs hold NaN)."""

    theta: np.ndarray  # (R, K, 5)
    phi_mean: np.ndarray | None  # (R, K, M)
    phi_cov: np.ndarray | None  # (R, K, M, M)
    nis: np.ndarray  # (R, K)
    nis_dof: np.ndarray  # (R, K)
    step_time: np.ndarray  # (R, K)
    diverged_step: np.ndarray  # (R,) int, -1 where the run completed

    @property
    def ok(self) -> np.ndarray:
        return self.diverged_step < 0


@dataclass(frozen=True)
class StudyResult:
    """All runs of a study. ``theta_true`` (5,) SI, ``phi_true`` (M,), ``theta0`` (R, 5), ``phi0`` (R, M)."""

    seed: int
    runs: int
    steps: int
    dt: float
    estimators: tuple
    estimated: tuple
    index: np.ndarray  # (M,) into NAMES
    theta_true: np.ndarray
    phi_true: np.ndarray
    theta0: np.ndarray
    phi0: np.ndarray
    prior_tries: np.ndarray  # (R,)
    results: dict  # name -> EstimatorRuns

    def statistics(self) -> dict:
        """``{name: EstimatorStats}`` in estimator order."""
        return {name: estimator_statistics(r, self.theta_true, self.phi_true, self.theta0, self.index)
                for name, r in self.results.items()}


def _collect(parts: list, estimators, steps: int, M: int) -> dict:
    out = {}
    for name in estimators:
        tr = [p.traces[name] for p in parts]
        joint = tr[0].phi_mean is not None
        out[name] = EstimatorRuns(
            np.stack([t.theta for t in tr]),
            np.stack([t.phi_mean for t in tr]) if joint else None,
            np.stack([t.phi_cov for t in tr]) if joint else None,
            np.stack([t.nis for t in tr]), np.stack([t.nis_dof for t in tr]).astype(np.int64),
            np.stack([t.step_time for t in tr]), np.array([t.diverged_step for t in tr], np.int64))
    return out


def model_fingerprint(model: PatchModel) -> str:
    """SHA-256 of the model's (projected) matrices: equal for two builds that give the same results."""
    h = hashlib.sha256()
    for a in (model.K_lambda, model.K_mu, model.M0, model.loads):
        h.update(np.ascontiguousarray(a, float).tobytes())
    return h.hexdigest()


_WORKER: dict = {}


def _init_worker(config_dict):
    """Process-pool initializer: one BLAS thread, the model built once per worker from its config."""
    import signal

    from threadpoolctl import threadpool_limits

    from .config import model_config_from_dict
    from .model import build_model

    signal.signal(signal.SIGINT, signal.SIG_IGN)     # the parent stops the pool on Ctrl-C (no worker traceback)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    _WORKER["limits"] = threadpool_limits(1)
    _WORKER["model"] = build_model(model_config_from_dict(config_dict))
    _WORKER["fingerprint"] = model_fingerprint(_WORKER["model"])


def _worker_run(index, kwargs):
    return run_single(_WORKER["model"], index, **kwargs), _WORKER["fingerprint"]


def run_study(model: PatchModel, *, runs: int, steps: int, seed: int = 0, estimators=ESTIMATORS,
              workers: int = 1, progress: Callable[[int, int], None] | None = None) -> StudyResult:
    """Run the Monte-Carlo study.

    Parameters
    ----------
    model : PatchModel
        Used as is with ``workers == 1``; with more workers each worker process rebuilds it once from
        ``model.config.raw`` (the parsed model file) and limits BLAS to one thread.
    runs, steps : int
        R >= 2 runs of K >= 2 frames each.
    seed : int
        Root of the per-run seed sequences; results do not depend on ``workers``.
    estimators : sequence of {'ge', 'ukf', 'ekf', 'kf'}
    progress : callable(done, total), optional
        Called in this process after each finished run.
    """
    if runs < 2 or steps < 2:
        raise ValueError(f"runs and steps: >= 2 expected, got runs={runs}, steps={steps}")
    if workers < 1:
        raise ValueError(f"workers: >= 1 expected, got {workers}")
    cfg = model.config
    space = cfg.parameter_space()
    estimators = check_estimators(estimators, space.dim)
    kwargs = {"seed": int(seed), "runs": int(runs), "steps": int(steps), "estimators": estimators}
    parts: list = [None] * runs
    if workers == 1:
        for r in range(runs):
            parts[r] = run_single(model, r, **kwargs)
            if progress is not None:
                progress(r + 1, runs)
    else:
        # the prior draws are checked here first: a model whose prior misses its box fails in this process
        for child in np.random.SeedSequence(int(seed)).spawn(runs):
            _prior_draw(model, child)
        mine, other = model_fingerprint(model), set()
        ex = ProcessPoolExecutor(max_workers=min(workers, runs), initializer=_init_worker, initargs=(cfg.raw,))
        try:
            futures = {ex.submit(_worker_run, r, kwargs): r for r in range(runs)}
            for done, fut in enumerate(as_completed(futures), 1):
                parts[futures[fut]], fingerprint = fut.result()
                other.add(fingerprint)
                if progress is not None:
                    progress(done, runs)
        except KeyboardInterrupt:       # Ctrl-C or SIGTERM: the workers ignore them; stop them now
            for proc in list((getattr(ex, "_processes", None) or {}).values()):
                proc.terminate()
            ex.shutdown(wait=True, cancel_futures=True)     # quick: the pool is broken, its manager ends
            raise
        except BaseException:
            ex.shutdown(wait=True, cancel_futures=True)
            raise
        ex.shutdown(wait=True)
        if other != {mine}:
            log.warning("the model built in the worker processes differs from this process's (its build is not "
                        "deterministic): the results differ from a run with workers=1")
    M = space.dim
    return StudyResult(
        int(seed), int(runs), int(steps), cfg.dt, estimators, space.estimated, space.index,
        np.array(cfg.theta, float), space.x_from_theta(cfg.theta),
        np.stack([p.theta0 for p in parts]), np.stack([p.phi0 for p in parts]).reshape(runs, M),
        np.array([p.tries for p in parts], np.int64), _collect(parts, estimators, steps, M))


# -- statistics ---------------------------------------------------------------------------------------
def chi2_band(n: int, dof: int, level: float = 0.95) -> tuple[float, float]:
    """Two-sided ``level`` band of the average of ``n`` independent chi-square(``dof``) statistics:
    ``[chi2.ppf(a/2, n dof) / n, chi2.ppf(1 - a/2, n dof) / n]`` with ``a = 1 - level``."""
    if n < 1 or dof < 1:
        raise ValueError(f"chi2_band: n >= 1 and dof >= 1 expected, got n={n}, dof={dof}")
    a = 1.0 - level
    return float(stats.chi2.ppf(a / 2, n * dof) / n), float(stats.chi2.ppf(1 - a / 2, n * dof) / n)


def _finite_mean(a, axis=None):
    """Mean over the finite entries (NaN where there is none), without warnings."""
    a = np.asarray(a, float)
    fin = np.isfinite(a)
    count = fin.sum(axis=axis)
    total = np.where(fin, a, 0.0).sum(axis=axis)
    with np.errstate(invalid="ignore", divide="ignore"):
        return total / count


@dataclass(frozen=True)
class EstimatorStats:
    """Statistics of one estimator over its completed runs (n = ``runs_used``); M estimated parameters.

    Arrays per step have K rows; parameters are in SI units, NEES in phi coordinates. Entries that are not
    defined are NaN (``abs_error_var`` with n < 2, the NEES of the ``kf``, everything with n = 0).
    """

    runs_used: int
    diverged: int
    abs_error_mean: np.ndarray  # (K, M) mean_r |theta_hat - theta_true|
    abs_error_var: np.ndarray  # (K, M) its variance over runs, ddof 1
    rmse: np.ndarray  # (K, M)
    rmse_initial: np.ndarray  # (M,) of the prior draws theta0
    nees: np.ndarray | None  # (R, K) per run (NaN for diverged runs)
    anees: np.ndarray | None  # (K,)
    anees_time_avg: float  # mean of anees over k >= 1
    anees_band: tuple | None  # chi2_band(n, M)
    anees_in_band_fraction: float  # over k >= 1
    nees_per_parameter_final: np.ndarray  # (M,) mean_r e_j^2 / C_jj at the last step
    nis_per_dof: np.ndarray  # (K,) mean over runs of NIS / dof
    nis_per_dof_mean: float  # over all runs and steps
    nis_band: tuple | None  # chi2_band(n, dof) / dof for the median dof
    step_ms_median: float

    @property
    def rmse_final(self) -> np.ndarray:
        return self.rmse[-1]


def estimator_statistics(runs: EstimatorRuns, theta_true, phi_true, theta0, index) -> EstimatorStats:
    """Statistics of :class:`EstimatorStats` from one estimator's runs.

    Parameters
    ----------
    runs : EstimatorRuns
    theta_true : ndarray of shape (5,)
    phi_true : ndarray of shape (M,)
    theta0 : ndarray of shape (R, 5)
        Prior draws (the same for every estimator).
    index : ndarray of shape (M,)
        Indices of the estimated parameters in ``NAMES``.
    """
    ok = runs.ok
    n = int(ok.sum())
    R, K = runs.nis.shape
    M = len(index)
    nan_k = np.full((K, M), np.nan)
    e = runs.theta[ok][:, :, index] - np.asarray(theta_true)[index]  # (n, K, M)
    e0 = np.asarray(theta0)[ok][:, index] - np.asarray(theta_true)[index]
    if n:
        abs_mean = np.abs(e).mean(axis=0)
        abs_var = np.abs(e).var(axis=0, ddof=1) if n > 1 else nan_k
        rmse = np.sqrt((e**2).mean(axis=0))
        rmse0 = np.sqrt((e0**2).mean(axis=0))
    else:
        abs_mean, abs_var, rmse, rmse0 = nan_k, nan_k, nan_k, np.full(M, np.nan)

    nees = anees = band = None
    anees_avg = in_band = np.nan
    per_param = np.full(M, np.nan)
    if runs.phi_mean is not None:
        ep = runs.phi_mean - np.asarray(phi_true)  # (R, K, M)
        nees = np.full((R, K), np.nan)
        if n:
            sol = np.linalg.solve(runs.phi_cov[ok], ep[ok][..., None])[..., 0]
            nees[ok] = np.einsum("rkm,rkm->rk", ep[ok], sol)
            anees = nees[ok].mean(axis=0)
            band = chi2_band(n, M)
            anees_avg = float(anees[1:].mean())
            in_band = float(np.mean((anees[1:] >= band[0]) & (anees[1:] <= band[1])))
            var_final = np.diagonal(runs.phi_cov[ok][:, -1], axis1=-2, axis2=-1)
            per_param = (ep[ok][:, -1] ** 2 / var_final).mean(axis=0)
        else:
            anees = np.full(K, np.nan)

    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(runs.nis_dof[ok] > 0, runs.nis[ok] / runs.nis_dof[ok], np.nan)
    nis_per_dof = _finite_mean(ratio, axis=0) if n else np.full(K, np.nan)
    nis_mean = float(_finite_mean(ratio)) if n else np.nan
    dofs = runs.nis_dof[ok][runs.nis_dof[ok] > 0]
    nis_band = None
    if dofs.size:
        d = int(np.median(dofs))
        lo, hi = chi2_band(n, d)
        nis_band = (lo / d, hi / d)
    step_ms = float(np.median(runs.step_time[ok]) * 1e3) if n else np.nan
    return EstimatorStats(n, R - n, abs_mean, abs_var, rmse, rmse0, nees, anees, anees_avg, band, in_band,
                          per_param, nis_per_dof, nis_mean, nis_band, step_ms)


# -- summaries ------------------------------------------------------------------------------------------
def _num(x):
    """float, or None where not finite (JSON has no NaN)."""
    x = float(x)
    return x if np.isfinite(x) else None


def summary(study: StudyResult, statistics: dict) -> dict:
    """The study's summary as plain JSON values (SI units; None where a value is not defined)."""
    names = list(study.estimated)
    per = lambda v: {n: _num(x) for n, x in zip(names, v, strict=True)}  # noqa: E731
    band = lambda b: None if b is None else [_num(b[0]), _num(b[1])]  # noqa: E731
    out = {}
    for name, s in statistics.items():
        out[name] = {
            "runs_used": s.runs_used,
            "diverged": s.diverged,
            "rmse_initial": per(s.rmse_initial),
            "rmse_final": per(s.rmse_final),
            "abs_error_mean_final": per(s.abs_error_mean[-1]),
            "anees": _num(s.anees_time_avg),
            "anees_band": band(s.anees_band),
            "anees_in_band_fraction": _num(s.anees_in_band_fraction),
            "nees_per_parameter_final": per(s.nees_per_parameter_final),
            "nis_per_dof_mean": _num(s.nis_per_dof_mean),
            "nis_per_dof_band": band(s.nis_band),
            "step_ms_median": _num(s.step_ms_median),
        }
    return {
        "runs": study.runs,
        "steps": study.steps,
        "seed": study.seed,
        "dt_s": study.dt,
        "estimated": names,
        "theta_true": {n: float(v) for n, v in zip(NAMES, study.theta_true, strict=True)},
        "estimators": out,
    }


def arrays(study: StudyResult, statistics: dict) -> dict:
    """The study's arrays, keyed as in the ``heartcv.study`` file (docs/formats.md); joint-only arrays are
    left out for the ``kf``."""
    out = {
        "times": np.arange(study.steps) * study.dt,
        "estimators": np.array(study.estimators),
        "estimated": np.array(study.estimated, dtype="<U6"),
        "seed": np.int64(study.seed), "runs": np.int64(study.runs), "steps": np.int64(study.steps),
        "theta_true": study.theta_true, "phi_true": study.phi_true,
        "theta0": study.theta0, "phi0": study.phi0, "prior_tries": study.prior_tries,
    }
    for name, r in study.results.items():
        s = statistics[name]
        fields = {
            "theta": r.theta, "diverged_step": r.diverged_step, "phi_mean": r.phi_mean, "phi_cov": r.phi_cov,
            "nis": r.nis, "nis_dof": r.nis_dof, "step_time": r.step_time,
            "abs_error_mean": s.abs_error_mean, "abs_error_var": s.abs_error_var, "rmse": s.rmse,
            "rmse_initial": s.rmse_initial, "nees": s.nees, "anees": s.anees, "nis_per_dof": s.nis_per_dof,
        }
        out.update({f"{name}_{k}": v for k, v in fields.items() if v is not None})
    return out

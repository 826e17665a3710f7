"""Noise levels chosen from the data while the filter runs (issue 15, docs/estimators.md §3.8).

Two quantities of the estimators' noise model are not known in advance; both are estimated from the innovations by
covariance matching (Mehra 1972; Myers & Tapley 1976) with fading memory (Sage & Husa 1969), using only past
frames: frame k is predicted and updated with the levels estimated up to frame k - 1.

1. **The measurement covariances' scale** ``lam`` (``R_k = lam_k R_k^file``). A measurement file's covariances
   describe the whole error of a point, but part of it is constant over a point's life (a template that sits a
   little off its feature, a calibration error): that part is a reference error, absorbed by the points' reference
   offsets (:mod:`tracker.reference`), not noise from frame to frame. What the filter must be told is the variance
   of what changes between frames, plus what the model cannot represent (a coarse mesh, a stiffness that changes
   faster than the random walk allows). With ``S = H C H^T + lam R`` dominated by ``lam R``,
   ``E[NIS_k] = m_k lam*/lam``, so ``lam * NIS_k / m_k`` is a one-step estimate of ``lam*``; ``log lam`` is its
   exponentially weighted mean over ``window_s`` seconds, kept in ``[scale_min, scale_max]``. On the rendered
   phantom the frame-to-frame part is ~0.1 of the file's variance in diastole, and the scale rises in systole where
   the model's error adds to it (docs/estimators.md §3.8 has the measurements).
2. **The parameters' random walk** ``Q_n``. For a random walk the update moves the parameter mean by
   ``delta_k = x_n,k|k - x_n,k|k-1``; a consistent filter expects ``E[delta_k^2] = c_k|k-1 - c_k|k`` (the variance
   the update removed), so

       q_hat_k = delta_k^2 - (c_k|k-1 - c_k|k) + q_k           (per parameter, the diagonal of Q_n)

   estimates the true random-walk variance; ``Q_n`` is its weighted mean, at least the model file's
   ``random_walk_std`` (the floor: how fast the parameter may change where the data cannot show it) and at most
   ``q_max_std``. Where the data move the parameter faster than the floor allows (a stiffness rising in systole)
   the random walk grows for as long as they do.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["AdaptationOptions", "NoiseAdaptation"]


@dataclass(frozen=True)
class AdaptationOptions:
    """Settings of :class:`NoiseAdaptation`.

    random_walk : adapt the parameters' random walk (never below the model file's); off by default: on both
        rendered scenes it did not improve the parameters (docs/estimators.md 3.8)
    measurement_scale : adapt the scale of the measurement covariances
    window_s : memory of the weighted means (s); a frame's weight decays as exp(-age / window_s)
    q_max_std : largest random-walk std per square-root second (phi units)
    scale_min, scale_max : bounds of the measurement scale
    """

    random_walk: bool = False
    measurement_scale: bool = True
    window_s: float = 0.03
    q_max_std: float = 5.0
    scale_min: float = 1e-3
    scale_max: float = 1e3

    def __post_init__(self):
        if not (np.isfinite(self.window_s) and self.window_s > 0):
            raise ValueError(f"window_s: positive seconds expected, got {self.window_s}")
        if not (np.isfinite(self.q_max_std) and self.q_max_std > 0):
            raise ValueError(f"q_max_std: a positive value expected, got {self.q_max_std}")
        if not 0 < self.scale_min <= 1 <= self.scale_max < np.inf:
            raise ValueError(f"scale_min, scale_max: 0 < min <= 1 <= max expected, got {self.scale_min}, "
                             f"{self.scale_max}")


class NoiseAdaptation:
    """Covariance matching of the measurement scale and the random walk over one run (module docstring).

    Parameters
    ----------
    M : int          parameters in the parameter block (0: the KF)
    dt : float       frame interval (s)
    Q_n0 : (M, M)    the model file's random walk per frame of ``dt`` (the floor and the starting value)
    options : AdaptationOptions
    """

    def __init__(self, M: int, dt: float, Q_n0, options: AdaptationOptions = AdaptationOptions()):
        self.M = int(M)
        self.dt = float(dt)
        self.options = options
        self.alpha = 1.0 - np.exp(-self.dt / options.window_s)      # weight of the newest frame
        q0 = np.diag(np.asarray(Q_n0, float)).copy() if self.M else np.zeros(0)
        self.q_lo = q0
        self.q_hi = np.maximum(options.q_max_std ** 2 * self.dt, q0)
        self.q = q0.copy()
        self.lam = 1.0
        self.lam_history: list = []
        self.q_history: list = []

    # -- what the filter asks -----------------------------------------------------------------------
    def random_walk(self, k: int, Q_n) -> np.ndarray:
        """``Q_n`` for the prediction into frame k (estimated up to frame k - 1)."""
        if not self.options.random_walk or self.M == 0:
            return np.asarray(Q_n, float)
        return np.diag(self.q)

    def measurement_scale(self, k: int) -> float:
        """Factor on the measurement covariances in frame k."""
        return self.lam if self.options.measurement_scale else 1.0

    # -- what the filter tells ----------------------------------------------------------------------
    def observe(self, k: int, predicted, posterior, res) -> None:
        """Frame k's prediction, posterior (after truncation) and update result
        (:class:`tracker.kalman.UpdateResult`)."""
        a = self.alpha
        if self.options.random_walk and self.M and k > 0:
            M = self.M
            delta = posterior.mean[:M] - predicted.mean[:M]
            removed = np.diag(predicted.cov)[:M] - np.diag(posterior.cov)[:M]
            q_hat = delta ** 2 - removed + self.q
            self.q = np.clip((1 - a) * self.q + a * q_hat, self.q_lo, self.q_hi)
        if self.options.measurement_scale and res.dof > 0 and np.isfinite(res.nis):
            ratio = max(res.nis / res.dof, 1e-12)
            log_lam = (1 - a) * np.log(self.lam) + a * np.log(self.lam * ratio)
            self.lam = float(np.clip(np.exp(log_lam), self.options.scale_min, self.options.scale_max))
        self.lam_history.append(self.lam)
        self.q_history.append(self.q.copy())

    def summary(self) -> dict:
        """Provenance for the estimate file: the options and the median and final levels."""
        q = np.array(self.q_history) if self.q_history else np.zeros((0, self.M))
        lam = np.array(self.lam_history)
        o = self.options
        return {"random_walk": o.random_walk, "measurement_scale": o.measurement_scale, "window_s": o.window_s,
                "random_walk_std_per_frame_median": np.sqrt(np.median(q, axis=0)).tolist() if q.size else [],
                "random_walk_std_per_frame_max": np.sqrt(q.max(axis=0)).tolist() if q.size else [],
                "measurement_scale_median": float(np.median(lam)) if lam.size else 1.0,
                "measurement_scale_min": float(lam.min()) if lam.size else 1.0,
                "measurement_scale_max": float(lam.max()) if lam.size else 1.0}

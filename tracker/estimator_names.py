"""The one list of estimator names (no heavy imports, so that the command line can build its choices quickly);
the variants that implement them register in :mod:`tracker.estimators`, the baselines live in
:mod:`tracker.baselines`."""

MODEL = ("kf", "ge", "ukf", "ekf")
"""The estimators on the physics model (Gaussian filters of :mod:`tracker.estimators`)."""

JOINT = ("ge", "ukf", "ekf")
"""The estimators of state and parameters (a parameter block, M > 0)."""

BASELINES = ("hold", "constvel", "harmonic")
"""Per-point predictors that need no physics (:mod:`tracker.baselines`)."""

NAMES = MODEL + BASELINES
"""Every estimator's name, in report order."""

"""The one list of estimator names (no heavy imports, so that the command line can build its choices quickly);
the variants that implement them register in :mod:`tracker.estimators`."""

NAMES = ("kf", "ge", "ukf", "ekf")
"""Every estimator's name, in report order."""

JOINT = ("ge", "ukf", "ekf")
"""The estimators of state and parameters (a parameter block, M > 0)."""

"""tracker: physics model of the heart-wall patch and its estimators.

Pure computation on arrays and typed objects; file I/O lives in :mod:`heartcv.tracker.io` only.
"""

__version__ = "0.1.0"

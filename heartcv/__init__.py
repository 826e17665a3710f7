"""heartcv: the vision front end (cameras, rig, targets, renderer, measurement)."""

__version__ = "0.1.0"

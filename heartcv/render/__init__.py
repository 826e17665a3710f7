"""The renderer: scene files, the heart phantom and its texture, truth motion, ray casting, calibration and
sequence renders (docs/design.md §1, ``heartcv render``).

Modules: ``scene`` (scene file as typed values, the true rig), ``phantom`` (surface mesh containing the model's
patch), ``texture`` (procedural epicardium), ``motion`` (truth motion from ``tracker.simulate``), ``raycast``
(Embree), ``shading``, ``sensor`` (blur, noise, quantisation), ``instrument``, ``board`` (calibration renders),
``sequence`` (sequence renders), ``parallel`` (ordered process pool). No file access here: ``heartcv.io`` reads
scenes and writes the renders.
"""

from .scene import Scene, SceneError, build_rig, scene_from_dict

__all__ = ["Scene", "SceneError", "build_rig", "scene_from_dict"]

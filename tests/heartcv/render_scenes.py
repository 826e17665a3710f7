"""Small, fast scenes for the renderer's tests: the default rig scaled down (image size and focal length in pixels
divided by ``scale``, so the field of view is the paper rig's), a coarse truth model and a coarse texture."""

from __future__ import annotations

import copy

import yaml

from tests.conftest import SAMPLES


def write_truth_model(path, grid=(13, 9, 2)):
    """A small full (unreduced) model with the paper patch's geometry, LV pressure, written to ``path``."""
    d = yaml.safe_load((SAMPLES / "paper_patch.yaml").read_text())
    d["name"] = "render_test_truth"
    d["geometry"]["grid"] = list(grid)
    d["observation"] = {"points": {"grid": [5, 4]}, "margin": 0.1}
    path.write_text(yaml.safe_dump(d))
    return path


def scene_dict(model_path, scale=4, **sections) -> dict:
    """A scene with the default rig at ``1/scale`` resolution, the given model and section overrides
    (``sections`` maps a section name to the keys to update)."""
    d = {
        "format": "heartcv.scene", "format_version": 1, "name": "test", "seed": 5,
        "rig": {"image_size": [1920 // scale, 1080 // scale], "pixel_pitch_m": 5.86e-6 * scale,
                "distortion": [-0.06, 0.12, 0.0004, -0.0003, 0.0]},
        "optics": {"psf_sigma_px": 0.5},
        "calibration": {"target": None, "views": 3, "max_tilt_deg": 30},
        "phantom": {"mesh_edge_m": 0.002, "texture": {"texel_m": 1.0e-4}},
        "motion": {"model": str(model_path), "duration_s": 0.2, "substeps": 2,
                   "stiffness_cycle": {"amplitude": 0.5, "shape": "pressure"}},
    }
    for key, val in sections.items():
        if isinstance(val, dict) and isinstance(d.get(key), dict):
            merged = copy.deepcopy(d[key])
            for k, v in val.items():
                if isinstance(v, dict) and isinstance(merged.get(k), dict):
                    merged[k] = {**merged[k], **v}
                else:
                    merged[k] = v
            d[key] = merged
        else:
            d[key] = val
    return d

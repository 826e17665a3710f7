"""Monte-Carlo check that the rig calibration's reported standard deviations are honest (issue 13: "a simulation
with a known rig shows them neither over- nor under-confident by more than 1.5x").

A known rig (tests/heartcv/test_calibration.py ``_wide_rig``: 1920x1080 cameras, f ~ 2000 px, a ChArUco board of
36 mm squares) sees the same board poses in every run; only the corner noise changes (fixed seeds). For every
run and every estimated quantity, z = (estimate - truth) / reported std; over the runs, the RMS of z per group
(rotations and translations of cameras 1.., focal lengths and principal points of every camera) must lie in
[1 / 1.5, 1.5]. The rotation error is the rotation vector of ``R_est R_true^T``: the left increment
``R = exp([w]x) R0`` of the covariance. The rig frame is camera 0's, so the truth is ``cam_from_cam0``
(``Camera.cam_from_rig`` of the synthetic cameras).

Two noise models:

* white: independent Gaussian corner noise (0.2 px), the model the formal covariance assumes. Both the reported
  ``std`` (formal times the k-fold scale, never below 1) and ``std_formal`` are honest; the scaled one is slightly
  conservative (the scale is ~1.01 in the median, up to ~1.3). 80 runs: RMS z of the scaled std 0.89 .. 0.95 per
  group, of the formal std 0.94 .. 1.00.
* per-view offsets: on top, every camera view's corners share one Gaussian offset (0.3 or 0.4 px per axis), as a
  detector biased per image would give. The formal std, which assumes independent corners, is over-confident by
  ~2x (80 runs: RMS z 1.9 .. 2.2 at 0.3 px, 2.1 .. 2.6 at 0.4 px); the k-fold jackknife sees the view-to-view
  scatter and scales the std by ~1.7 .. 1.9 (median). The scaled std is within the 1.5x, but the translations
  only just: 80 runs give RMS z 1.13 .. 1.36 at 0.3 px and 1.16 .. 1.43 at 0.4 px, translations the largest. One
  scale for every parameter (the median jackknife / formal ratio) falls short for the translations, whose
  formal std is the most over-confident, and the 5-fold scale varies from run to run (1.0 .. 3.4), which raises
  the RMS of z further. So a 20-run sample at 0.4 px can exceed 1.5 (seed 2, runs 0..19: translation 1.56); the
  fast test uses 0.3 px and 24 runs, the slow one 0.4 px and 80 runs. Three cameras (slow, 0.4 px, 90 runs): scaled
  1.19 .. 1.41, the focal lengths nearest the bound (camera 1's fx, fy 1.6 alone; 30 of the runs: focal 1.58).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
import os

import numpy as np
import pytest

from heartcv.calibration_rig import calibrate_rig_detailed
from heartcv.detect import Detection
from tests.heartcv.test_calibration import _rotvec, _wide_rig, board_poses, observe

BOUND = 1.5  # the issue's: neither over- nor under-confident by more than 1.5x
GROUPS = ("rotation", "translation", "focal", "principal_point")
NOISE_PX = 0.2


def _one_run(cams, c0w, spec, poses, seed, view_offset_px):
    """Calibrate one noisy copy of the views; z per group for the scaled and the formal std, and the run's
    k-fold scale, coverage and how the intrinsics were obtained."""
    rng = np.random.default_rng(seed)
    dets = observe(cams, c0w, poses, spec, rng, noise=NOISE_PX)
    if view_offset_px:
        dets = [[None if d is None else Detection(d.ids, d.uv + view_offset_px * rng.standard_normal(2))
                 for d in row] for row in dets]
    rig = calibrate_rig_detailed(dets, spec, [(c.width, c.height) for c in cams]).rig
    meta = rig.meta
    z = {}
    for key in ("std", "std_formal"):
        zk = {g: [] for g in GROUPS}
        for c, cam in enumerate(cams):
            s, est = meta["cameras"][cam.name][key], rig[c]
            zk["focal"] += [(est.K[0, 0] - cam.K[0, 0]) / s["fx"], (est.K[1, 1] - cam.K[1, 1]) / s["fy"]]
            zk["principal_point"] += [(est.K[0, 2] - cam.K[0, 2]) / s["cx"], (est.K[1, 2] - cam.K[1, 2]) / s["cy"]]
            if c:  # camera 0 is the rig frame: its pose is not estimated
                zk["rotation"] += list(np.degrees(_rotvec(est.R @ cam.R.T)) / np.asarray(s["rotation_deg"]))
                zk["translation"] += list((est.t - cam.t) / np.asarray(s["translation_m"]))
        z[key] = zk
    return {"z": z, "scale": meta["uncertainty"]["std_scale"],
            "coverage": [meta["cameras"][c.name]["coverage"] for c in cams],
            "intrinsics": [meta["cameras"][c.name]["intrinsics"] for c in cams]}


def monte_carlo(n_cam, n_views, n_runs, *, view_offset_px=0.0, seed=0):
    """``n_runs`` calibrations of the same ``n_views`` board poses with fresh noise. Returns ``rms[key][group]``
    (RMS of z over runs and components, key ``std`` or ``std_formal``), the k-fold scales (n_runs,), the
    smallest coverage and the set of how the intrinsics were obtained."""
    cams, c0w, spec = _wide_rig(n_cam)
    poses = board_poses(n_views, np.random.default_rng(15), spec, spread=0.1)
    with ThreadPoolExecutor(min(4, os.cpu_count() or 1)) as pool:
        runs = list(pool.map(lambda r: _one_run(cams, c0w, spec, poses, [seed, r], view_offset_px), range(n_runs)))
    rms = {key: {g: float(np.sqrt(np.mean(np.square([r["z"][key][g] for r in runs])))) for g in GROUPS}
           for key in ("std", "std_formal")}
    return {"rms": rms, "scale": np.array([r["scale"] for r in runs]),
            "coverage": min(min(r["coverage"]) for r in runs),
            "how": {h for r in runs for d in r["intrinsics"] for h in d.values()}}


def _check_setup(mc):
    """Every intrinsic estimated from corners covering at least half of every image."""
    assert mc["coverage"] >= 0.5
    assert all(h.startswith("estimated") for h in mc["how"]), mc["how"]


def _assert_honest(rms, what):
    for g, v in rms.items():
        assert 1 / BOUND <= v <= BOUND, f"{what}: RMS z of {g} is {v:.3f}, outside [{1 / BOUND:.3f}, {BOUND}]"


def _assert_scaled_closer(mc):
    """Over-confident formal std (RMS z > 1.5 in every group); the scaled std honest and closer to 1."""
    for g in GROUPS:
        formal, scaled = mc["rms"]["std_formal"][g], mc["rms"]["std"][g]
        assert formal > BOUND, f"{g}: the formal std is not over-confident here (RMS z {formal:.3f})"
        assert abs(np.log(scaled)) < abs(np.log(formal)), f"{g}: scaled RMS z {scaled:.3f}, formal {formal:.3f}"
    _assert_honest(mc["rms"]["std"], "scaled std, per-view offsets")
    assert np.median(mc["scale"]) > 1.5  # the k-fold check saw it


# -- fast: two cameras, 20 views, 20 runs of white noise and 24 with per-view offsets ---------------------------
@pytest.fixture(scope="module")
def white_runs():
    return monte_carlo(2, 20, 20, seed=1)


@pytest.fixture(scope="module")
def offset_runs():
    return monte_carlo(2, 20, 24, view_offset_px=0.3, seed=2)


def test_scaled_std_honest_white_noise(white_runs):
    """Measured RMS z (20 runs): rotation 0.87, translation 0.79, focal 0.90, principal point 0.86."""
    _check_setup(white_runs)
    _assert_honest(white_runs["rms"]["std"], "scaled std, white noise")
    assert np.all(white_runs["scale"] >= 1) and np.median(white_runs["scale"]) < 1.2


def test_formal_std_honest_white_noise(white_runs):
    """The noise the formal covariance assumes: it is honest too (20 runs: RMS z 0.82 .. 0.93)."""
    _assert_honest(white_runs["rms"]["std_formal"], "formal std, white noise")


def test_scaled_std_honest_per_view_offsets(offset_runs):
    """Corners sharing an offset per camera view (0.3 px): the formal std over-confident ~2x (24 runs: RMS z
    1.92 .. 2.12), the scaled one within 1.5x (1.22 .. 1.41; the translations nearest the bound, module
    docstring)."""
    _check_setup(offset_runs)
    _assert_scaled_closer(offset_runs)


# -- slow: more runs, a larger offset, three cameras ----------------------------------------------------------
@pytest.mark.slow
def test_scaled_std_honest_per_view_offsets_80_runs():
    """0.4 px offsets, 80 runs: formal RMS z 2.13 .. 2.56, scaled 1.16 .. 1.43 (translations)."""
    mc = monte_carlo(2, 20, 80, view_offset_px=0.4, seed=2)
    _check_setup(mc)
    _assert_scaled_closer(mc)


@pytest.mark.slow
@pytest.mark.parametrize(("view_offset_px", "n_runs"), [(0.0, 30), (0.4, 90)])
def test_three_camera_rig_monte_carlo(view_offset_px, n_runs):
    """Three cameras, 24 views. White noise, 30 runs: RMS z of the scaled std 0.97 .. 1.00, of the formal std
    0.99 .. 1.02. Offsets of 0.4 px, 90 runs: formal 2.36 .. 2.75, scaled 1.19 .. 1.41 (focal lengths the largest:
    camera 1's fx and fy 1.6 alone); 30 runs of these (seed 3, runs 0..29) gave focal 1.58, over the bound, hence
    the 90 runs (the criterion is about the expected RMS z; 30 runs estimate it to ~+-0.1)."""
    mc = monte_carlo(3, 24, n_runs, view_offset_px=view_offset_px, seed=3)
    _check_setup(mc)
    if view_offset_px:
        _assert_scaled_closer(mc)
    else:
        _assert_honest(mc["rms"]["std"], "scaled std, white noise")
        _assert_honest(mc["rms"]["std_formal"], "formal std, white noise")

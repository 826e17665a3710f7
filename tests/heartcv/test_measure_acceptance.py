"""Issue 5 acceptance on the rendered phantom (slow: renders a calibration set and two sequences, about 6 minutes
on 2 cores): `heartcv measure` with the rig from `heartcv calibrate` (not the true rig) tracks >= 100 points in
every frame with a 3-D RMS error <= 0.05 mm and a 99th percentile <= 0.15 mm against truth.npz; with an
occluding instrument no observation uses a hidden pixel, and views hidden by it are used again after it leaves.

The errors are judged modulo the gauge of the calibrated rig frame (one rigid transform fitted to the tracks'
birth positions only; docs/cli.md §10): the issue's own calibration tolerances (principal point within 2 px,
rotations within 0.02°) allow the calibrated camera 0, which defines the rig frame, to be rotated against the
true one by up to 2/5970 rad, i.e. 0.2 mm at the working distance, four times the 0.05 mm budget of the
measurement. The raw errors are checked too, against that calibration-implied bound.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

from click.testing import CliRunner
import numpy as np
import pytest

from heartcv.cli.main import main

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
PHANTOM = ROOT / "sample_sequences" / "phantom"
TARGET = ROOT / "calibration_targets" / "charuco_11x8_12mm.yaml"


def _run(args):
    res = CliRunner().invoke(main, args, catch_exceptions=False)
    assert res.exit_code == 0, res.output
    return res


@pytest.fixture(scope="module")
def rig_file(tmp_path_factory):
    d = tmp_path_factory.mktemp("calib")
    _run(["render", "calibration", str(PHANTOM / "scene.yaml"), "-o", str(d / "calib"), "--workers", "2"])
    _run(["calibrate", str(d / "calib"), "--target", str(TARGET), "-o", str(d / "rig.yaml")])
    return d / "rig.yaml"


def _measure(tmp, scene, frames, rig_file, csv_file=None):
    seq = tmp / "seq"
    _run(["render", "sequence", str(scene), "-o", str(seq), "--workers", "2", "--frames", str(frames)])
    args = ["measure", str(seq), "--rig", str(rig_file), "-o", str(tmp / "meas.npz"), "--truth",
            str(seq / "truth.npz"), "--json"]
    if csv_file:
        args += ["--csv", str(csv_file)]
    res = _run(args)
    return seq, json.loads(res.stdout)


def test_phantom_sequence_accuracy(tmp_path, rig_file):
    from heartcv.io import read_scene
    from heartcv.tracker.io import read_measurements

    _, s = _measure(tmp_path, PHANTOM / "scene.yaml", 60, rig_file)
    assert s["frames"] == 60 and len(s["cameras"]) == 3
    assert s["points_min"] >= 100
    assert s["tracks_off_surface"] == 0
    assert s["aligned_error_rms_m"] <= 0.05e-3
    assert s["aligned_error_p99_m"] <= 0.15e-3
    # the raw error is the gauge: a rotation within the calibration's tolerance, errors within what it implies.
    # The calibrated rig frame is camera 0 as calibrated: its principal point (tolerance 2 px = 0.019 deg at
    # f = 5973 px) and the camera-to-camera rotations (0.02 deg) tilt the triangulated points together, so the
    # gauge may reach ~0.04 deg; fitted from the tracks' birth positions over a 40 mm patch it also carries their
    # depth errors (10 um across 40 mm is 0.014 deg). Measured: 0.018 deg (30 fps render), 0.028 deg (60 fps).
    assert s["rig_gauge_rotation_deg"] <= 0.04
    assert s["error_rms_m"] <= 0.05e-3 + np.radians(s["rig_gauge_rotation_deg"]) * 0.7
    m = read_measurements(tmp_path / "meas.npz")
    assert m.frame == "rig" and m.n_frames == 60
    assert m.input_names == ("pressure",) and m.input_units == ("Pa",)
    rate = read_scene(PHANTOM / "scene.yaml").motion.frame_rate_hz
    assert rate == 60 and np.allclose(np.diff(m.times), 1 / rate)
    # the covariances describe the scatter of the displacements from the reference positions (what the
    # estimators use; a constant error of a track cancels there): mean NEES per degree of freedom near 1
    assert s["displacement_error_rms_m"] <= s["aligned_error_rms_m"]
    # Never over-confident (<= 2); conservative by at most 2x in sigma (>= 0.25): the pixel sigma is pooled from the
    # reprojection residuals, which also hold static errors of the rig (constant per point, they cancel in a
    # displacement). Measured: 1.1 (60 frames at 30 fps), 0.59 (150 at 30 fps), 0.41 (60 at 60 fps; less motion
    # per frame, smaller tracking errors), 0.37 (240 at 60 fps).
    assert 0.25 <= s["displacement_nees_per_dof"] <= 2.0


def test_instrument_occlusion(tmp_path, rig_file):
    from heartcv.io import read_render_truth

    csv_file = tmp_path / "meas.csv"
    seq, s = _measure(tmp_path, PHANTOM / "instrument.yaml", 72, rig_file, csv_file)
    assert s["occluded_observations"] == 0
    assert s["points_min"] >= 100
    assert s["aligned_error_rms_m"] <= 0.05e-3
    truth, _ = read_render_truth(seq / "truth.npz")
    present = np.flatnonzero(truth["instrument_present"])
    assert present.size and present[-1] < 71            # it comes and it leaves within the sequence
    with open(csv_file) as f:
        rows = list(csv.DictReader(line for line in f if not line.startswith("#")))
    ids = sorted({int(r["point_id"]) for r in rows})
    idx = {p: i for i, p in enumerate(ids)}
    used = np.zeros((72, len(ids), 3), bool)
    for r in rows:
        for c in range(3):
            if r[f"u_cam{c}_px"]:
                used[int(r["frame"]), idx[int(r["point_id"])], c] = True
    first, last = present[0], present[-1]
    lost = used[first - 1] & ~used[first:last + 1].all(axis=0)       # views hidden at some instant
    assert lost.sum() >= 10                                           # the instrument did hide some
    back = lost & used[-5:].any(axis=0)
    assert back.sum() >= 0.8 * lost.sum()                             # and they resume afterwards
    seen = used.any(axis=2).sum(axis=1)
    assert seen[-1] >= 0.9 * seen[first - 1]

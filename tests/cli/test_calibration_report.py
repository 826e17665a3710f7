"""The calibration report (``heartcv.cli.calibration_report``) on a synthetic three-camera rig whose detections
are exact projections of a ChArUco target, with a known residual injected into one camera: files, PNGs,
coverage against an independent rasterisation, the RMS on the page, escaped warnings, output safety."""

from __future__ import annotations

from html import escape
import re

import cv2
import numpy as np
from PIL import Image
import pytest

from heartcv.calibration_rig import RigCalibration
from heartcv.camera import Camera, Rig, pose_matrix
from heartcv.cli.calibration_report import FIGURES, PRODUCER, write_calibration_report
from heartcv.detect import Detection
from heartcv.targets import TargetSpec
from heartcv.tracker.files import InputError, read_manifest

SIZE = (640, 480)
SHIFT_U = 0.5  # px added to cam1's detected u
WARNINGS = ['cam2: view 5 rejected (RMS 3.0 px > 1.5 px) <b>&amp; "odd"</b>', "plain warning"]


def _look_at(centre, target, down=(0, 1, 0)) -> np.ndarray:
    """cam_from_rig of a camera at ``centre`` looking at ``target`` (OpenCV axes: z forward, y down)."""
    z = np.asarray(target, float) - centre
    z /= np.linalg.norm(z)
    x = np.cross(down, z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])  # rows: camera axes in the rig frame
    return pose_matrix(R, -R @ centre)


def _rotation(rx, ry, rz) -> np.ndarray:
    return cv2.Rodrigues(np.array([rx, ry, rz], float))[0]


@pytest.fixture(scope="module")
def scene():
    """Rig, spec, detections and a RigCalibration built directly (no solver)."""
    rng = np.random.default_rng(7)
    spec = TargetSpec("charuco", (8, 6), 0.02, 0.015, "DICT_5X5_250", name="t8x6")
    centre = np.array([0.0, 0.0, 0.5])
    K = np.array([[800.0, 0, 319.5], [0, 810.0, 239.5], [0, 0, 1]])
    cams = [Camera("cam0", *SIZE, K)]
    for i, pos in enumerate(([0.12, 0.0, 0.02], [0.06, -0.1, 0.0]), start=1):
        cams.append(Camera(f"cam{i}", *SIZE, K, np.zeros(5), _look_at(np.array(pos), centre)))
    rig = Rig(tuple(cams), {"cameras": {"cam0": {"std": {"fx": 0.41, "fy": 0.43, "cx": 0.3, "cy": 0.31}},
                                        "cam1": {"heldout_rms_px": 0.61},
                                        "cam2": {"outlier_threshold_px": 1.5}},
                            "heldout_rms_px": 0.55, "warnings": ["from the rig's metadata"]})
    n_views = 9
    w, h = spec.board_size_m
    rig_from_board = np.empty((n_views, 4, 4))
    for v in range(n_views):
        R = _rotation(*rng.uniform(-0.45, 0.45, 3))
        board_mid = centre + np.r_[rng.uniform(-0.06, 0.06, 2), rng.uniform(-0.05, 0.05)]
        rig_from_board[v] = pose_matrix(R, board_mid - R @ [w / 2, h / 2, 0])
    obj = spec.object_points()
    detections = [[None] * n_views for _ in cams]
    used = np.ones((len(cams), n_views), bool)
    view_rms = np.zeros((len(cams), n_views))
    for c, cam in enumerate(cams):
        for v in range(n_views):
            X = obj @ rig_from_board[v, :3, :3].T + rig_from_board[v, :3, 3]
            uv = cam.project(X)
            keep = cam.in_image(uv, margin=2)
            assert keep.sum() >= 20, "the synthetic board should stay in the image"
            uv = uv[keep] + (np.array([SHIFT_U, 0.0]) if c == 1 else 0.0)
            detections[c][v] = Detection(np.flatnonzero(keep), uv)
        view_rms[c] = SHIFT_U if c == 1 else 0.0
    detections[0][8] = None  # cam0 did not see view 8
    used[0, 8], view_rms[0, 8] = False, np.nan
    used[2, 5], view_rms[2, 5] = False, 3.0  # rejected as an outlier
    used[2, 6], view_rms[2, 6] = False, np.nan  # corners found, view not used
    cal = RigCalibration(rig, rig_from_board, used, view_rms)
    return cal, detections, spec


def _oracle_coverage(cam, dets, used) -> float:
    """Share of the image pixels inside the union of the used views' convex hulls (integer rasterisation)."""
    mask = np.zeros((cam.height, cam.width), np.uint8)
    for d, u in zip(dets, used):
        if u and d is not None:
            cv2.fillConvexPoly(mask, cv2.convexHull(np.round(d.uv).astype(np.int32)), 1)
    return float(mask.mean())


@pytest.fixture(scope="module")
def report(scene, tmp_path_factory):
    cal, detections, spec = scene
    folder = tmp_path_factory.mktemp("rep") / "calib_report"
    out = write_calibration_report(folder, cal, detections, spec, title="Rig <A&B> calibration",
                                   warnings=WARNINGS)
    return folder, out


def test_files_are_valid_pngs_and_a_page(report):
    folder, out = report
    assert out["index"] == folder / "index.html" and out["index"].is_file()
    assert set(out["figures"]) == set(FIGURES)
    for name in FIGURES:
        path = folder / name
        assert out["figures"][name] == path
        with Image.open(path) as im:
            im.verify()
        with Image.open(path) as im:
            assert im.format == "PNG" and im.width >= 400 and im.height >= 300, (name, im.size)
            assert np.asarray(im.convert("L")).std() > 5, f"{name} looks blank"
    page = out["index"].read_text(encoding="utf-8")
    for name in FIGURES:
        assert f'src="{name}"' in page
    assert "<script" not in page.lower()
    assert not re.search(r'(?:src|href)="(?:/|[a-z]+:)', page), "only relative links"
    assert read_manifest(folder)["producer"] == PRODUCER
    assert sorted(p.name for p in folder.iterdir()) == sorted(["index.html", "heartcv-manifest.json", *FIGURES])


def test_coverage_matches_an_independent_rasterisation(scene, report):
    cal, detections, _ = scene
    _, out = report
    for c, cam in enumerate(cal.rig.cameras):
        expected = _oracle_coverage(cam, detections[c], cal.used[c])
        assert 0.05 < expected < 0.95
        assert out["coverage"][cam.name] == pytest.approx(expected, abs=0.01)
    # cam2 without its views 5 and 6 covers less than with them: the mask follows `used`
    all_views = _oracle_coverage(cal.rig[2], detections[2], np.ones(cal.used.shape[1], bool))
    assert out["coverage"]["cam2"] <= all_views + 1e-9


def test_page_reports_the_injected_residual(report):
    _, out = report
    page = out["index"].read_text(encoding="utf-8")
    cells = dict(re.findall(r"<tr><td>(cam\d)</td>.*?data-rms-px=\"([^\"]+)\"", page))
    assert set(cells) == {"cam0", "cam1", "cam2"}
    assert float(cells["cam1"]) == pytest.approx(SHIFT_U, abs=1e-6)
    assert float(cells["cam0"]) < 1e-6 and float(cells["cam2"]) < 1e-6
    assert out["rms_px"]["cam1"] == pytest.approx(SHIFT_U, abs=1e-6)
    assert re.search(r"<tr><td>cam1</td>.*?>0\.5000</td>", page)
    assert "<td>800.00 ± 0.41</td>" in page  # cam0's fx with its standard deviation
    assert "<td>8 of 8</td>" in page  # cam0: 8 views used of the 8 with corners
    assert "<li>Held-out RMS: 0.5500 px.</li>" in page
    assert re.search(r"<tr><td>cam1</td>.*?<td>0\.6100</td></tr>", page)
    assert re.search(r"<tr><td>cam0</td>.*?<td>–</td></tr>", page)  # no held-out RMS for cam0


def test_warnings_are_escaped(report):
    _, out = report
    page = out["index"].read_text(encoding="utf-8")
    for w in WARNINGS + ["from the rig's metadata"]:
        assert f"<li>{escape(w)}</li>" in page
    assert "<b>&amp;" not in page and "<A&B>" not in page
    assert "<title>Rig &lt;A&amp;B&gt; calibration</title>" in page


def test_baselines_on_the_page(scene, report):
    cal, _, _ = scene
    _, out = report
    page = out["index"].read_text(encoding="utf-8")
    b = np.linalg.norm(cal.rig[0].centre - cal.rig[1].centre) * 1e3
    assert f"<td>cam0–cam1</td><td>{b:.2f}</td>" in page


def test_replaces_its_own_report_and_refuses_other_folders(scene, tmp_path):
    cal, detections, spec = scene
    folder = tmp_path / "report"
    write_calibration_report(folder, cal, detections, spec, title="first", warnings=[])
    out = write_calibration_report(folder, cal, detections, spec, title="second", warnings=[])
    assert "<h1>second</h1>" in out["index"].read_text(encoding="utf-8")
    assert "No warnings" not in out["index"].read_text(encoding="utf-8")  # the rig's own warning is still shown
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]  # no temporary folder left behind

    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    with pytest.raises(InputError):
        write_calibration_report(mine, cal, detections, spec, title="x", warnings=[])
    assert [p.name for p in mine.iterdir()] == ["notes.txt"]
    assert (mine / "notes.txt").read_text() == "keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine", "report"]


def test_threshold_line_only_when_the_metadata_gives_one(scene):
    """view_errors.png: a horizontal line at cam2's outlier_threshold_px in cam2's panel, none elsewhere, and none
    once the threshold is dropped from the metadata."""
    from heartcv.cli.calibration_report import _view_error_figure

    def levels(cal):
        fig = _view_error_figure(cal, detections)
        return [sorted({float(ln.get_ydata()[0]) for ln in ax.get_lines()
                        if len(ln.get_ydata()) == 2 and np.ptp(ln.get_ydata()) == 0 and ln.get_linestyle() == "--"})
                for ax in fig.axes]

    cal, detections, _ = scene
    assert levels(cal) == [[], [], [1.5]]
    meta = {k: v for k, v in cal.rig.meta.items() if k != "cameras"}
    bare = RigCalibration(Rig(cal.rig.cameras, meta), cal.rig_from_board, cal.used, cal.view_rms)
    assert levels(bare) == [[], [], []]
    top = RigCalibration(Rig(cal.rig.cameras, {"outlier_threshold_px": {"cam0": 0.25, "cam1": 0.75}}),
                         cal.rig_from_board, cal.used, cal.view_rms)
    assert levels(top) == [[0.25], [0.75], []]


def test_a_camera_without_used_views_and_an_odd_name(scene, tmp_path):
    """No residuals for a camera (RMS '–', coverage 0) and a '$' in its name (mathtext in matplotlib) still give
    a report."""
    from dataclasses import replace

    cal, detections, spec = scene
    cams = list(cal.rig.cameras)
    cams[2] = replace(cams[2], name="c$a$m2")
    used, view_rms = cal.used.copy(), cal.view_rms.copy()
    used[2], view_rms[2] = False, np.nan
    odd = RigCalibration(Rig(tuple(cams), {"cameras": None}), cal.rig_from_board, used, view_rms)
    out = write_calibration_report(tmp_path / "r", odd, detections, spec, title="t", warnings=[])
    assert out["coverage"]["c$a$m2"] == 0.0 and np.isnan(out["rms_px"]["c$a$m2"])
    assert out["rms_px"]["cam1"] == pytest.approx(SHIFT_U, abs=1e-6)
    page = out["index"].read_text(encoding="utf-8")
    assert re.search(r"<tr><td>c\$a\$m2</td>.*?>–</td><td>0 of 9</td><td>0.0 %</td>", page)
    assert "<p>No warnings.</p>" in page

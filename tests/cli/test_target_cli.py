"""CLI: heartcv target (CliRunner, exit codes, artifacts read back, the shipped default target)."""

import json

from click.testing import CliRunner
import cv2
import numpy as np
import pytest
import yaml

from heartcv.cli.main import main
from heartcv.io import read_image, read_target
from heartcv.targets import TargetSpec
from tests.conftest import ROOT

DEFAULT = ROOT / "calibration_targets" / "charuco_11x8_12mm.yaml"
CHARUCO_ARGS = ["target", "--type", "charuco", "--squares", "11x8", "--square-mm", "12", "--marker-mm", "9",
                "--dict", "DICT_5X5_250"]


@pytest.fixture
def runner():
    return CliRunner()


def _json(result):
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)


def test_charuco_target(runner, tmp_path):
    out = _json(runner.invoke(main, CHARUCO_ARGS + ["-o", str(tmp_path / "T.yaml"), "--json"]))
    assert (out["name"], out["type"]) == ("T", "charuco")
    assert out["board_size_mm"] == pytest.approx([132.0, 96.0]) and out["page_size_mm"] == pytest.approx([156, 120])
    assert out["dpi"] == pytest.approx(298.45) and out["dpi_requested"] == 300 and out["square_px"] == 141
    assert out["png"] == str(tmp_path / "T.png") and out["pdf"] == str(tmp_path / "T.pdf")
    assert out["corners"] == 70 and out["image_size_px"] == [1833, 1410]
    spec = read_target(tmp_path / "T.yaml")
    assert spec == TargetSpec("charuco", (11, 8), 0.012, 0.009, "DICT_5X5_250", name="T")
    img = read_image(tmp_path / "T.png")
    assert img.shape == (1410, 1833)
    small = cv2.resize(img, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    _, ids, _, _ = cv2.aruco.CharucoDetector(spec.cv_board()).detectBoard(small)
    assert len(ids) == 70
    assert (tmp_path / "T.pdf").read_bytes().startswith(b"%PDF")


def test_chessboard_target(runner, tmp_path):
    out = _json(runner.invoke(main, ["target", "--type", "chessboard", "--inner-corners", "9x6", "--square-mm", "25",
                                     "--margin-mm", "10", "--dpi", "150", "--name", "board", "-o",
                                     str(tmp_path / "c.yaml"), "--json"]))
    assert out["name"] == "board" and out["type"] == "chessboard" and out["inner_corners"] == [9, 6]
    assert out["board_size_mm"] == pytest.approx([250.0, 175.0])
    assert out["px_per_m"] == 5920 and out["dpi"] == pytest.approx(150.368) and out["square_px"] == 148
    assert out["margin_mm"] == pytest.approx(59 / 5.92)  # 10 mm rounded to whole pixels (59 px)
    d = yaml.safe_load((tmp_path / "c.yaml").read_text())
    assert d["inner_corners"] == [9, 6] and d["square_m"] == 0.025 and "marker_m" not in d
    img = read_image(tmp_path / "c.png")
    ok, _ = cv2.findChessboardCornersSB(img, (9, 6))
    assert ok


def test_log_line_without_json(runner, tmp_path):
    """The summary is one INFO line (not a warning); -q hides it."""
    res = runner.invoke(main, CHARUCO_ARGS + ["-o", str(tmp_path / "T.yaml")])
    assert res.exit_code == 0 and res.stdout == ""
    assert res.stderr.startswith(f"INFO heartcv.cli.target: wrote {tmp_path / 'T.yaml'} (+ T.png, T.pdf)")
    assert "298.45 dpi" in res.stderr and "141 px per 12 mm square" in res.stderr and "WARNING" not in res.stderr
    res = runner.invoke(main, ["-q"] + CHARUCO_ARGS + ["-o", str(tmp_path / "T.yaml")])
    assert res.exit_code == 0 and res.stderr == ""


@pytest.mark.parametrize("args, message", [
    (["--type", "charuco", "--squares", "5x4", "--square-mm", "10", "--marker-mm", "10"], "marker size"),
    (["--type", "charuco", "--squares", "5x4", "--square-mm", "10", "--marker-mm", "7", "--dict", "DICT_3X3_9"],
     "dictionary"),
    (["--type", "charuco", "--squares", "11x10", "--square-mm", "10", "--marker-mm", "7", "--dict", "DICT_4X4_50"],
     "DICT_4X4_50 has 50 markers, the board needs 55"),
    (["--type", "chessboard", "--inner-corners", "9x6", "--square-mm", "0.5"], "squares too small"),
    (["--type", "charuco", "--squares", "5x4", "--square-mm", "2", "--marker-mm", "1.5"], "markers too small"),
    (["--type", "charuco", "--squares", "5x4", "--square-mm", "10"], "--marker-mm is required"),
    (["--type", "charuco", "--inner-corners", "5x4", "--square-mm", "10", "--marker-mm", "7"], "--squares"),
    (["--type", "chessboard", "--squares", "5x4", "--square-mm", "10"], "--inner-corners"),
    (["--type", "chessboard", "--inner-corners", "5x4", "--square-mm", "10", "--legacy"], "ChArUco boards only"),
    (["--type", "chessboard", "--inner-corners", "5by4", "--square-mm", "10"], "COLSxROWS"),
    (["--type", "chessboard", "--inner-corners", "5x4", "--square-mm", "-3"], "-3 is not in the range (0, 1000)"),
    (["--type", "chessboard", "--inner-corners", "5x4", "--square-mm", "nan"], "'nan': a finite number expected"),
    (["--type", "chessboard", "--inner-corners", "5x4", "--square-mm", "1000"], "1000 is not in the range (0, 1000)"),
    (["--type", "charuco", "--squares", "5x4", "--square-mm", "10", "--marker-mm", "inf"],
     "'inf': a finite number expected"),
    (["--type", "chessboard", "--inner-corners", "5x4", "--square-mm", "10", "--margin-mm", "nan"],
     "'nan': a finite number expected"),
    (["--type", "chessboard", "--inner-corners", "5x4", "--square-mm", "10", "--dpi", "-inf"],
     "'-inf': a finite number expected"),
    (["--type", "chessboard", "--inner-corners", "5x4", "--square-mm", "10", "--dpi", "10001"],
     "10001 is not in the range (0, 10000]"),
    (["--type", "chessboard", "--inner-corners", "101x4", "--square-mm", "10"], "101x4: 3 to 100 each way"),
    (["--type", "charuco", "--squares", "2x5", "--square-mm", "10", "--marker-mm", "7"], "2x5: 3 to 100 each way"),
    (["--type", "chessboard", "--inner-corners", "9x6", "--square-mm", "100", "--dpi", "1000"],
     "image too large: 39370 x 27559 px"),
    (["--type", "chessboard", "--inner-corners", "5x4", "--square-mm", "10", "--margin-mm", "-1"], "--margin-mm"),
    (["--type", "chessboard", "--inner-corners", "5x4", "--square-mm", "10", "--dpi", "0"],
     "0 is not in the range (0, 10000]"),
])
def test_bad_values_exit_2_and_write_nothing(runner, tmp_path, args, message):
    res = runner.invoke(main, ["target"] + args + ["-o", str(tmp_path / "t.yaml")])
    assert res.exit_code == 2, res.output
    assert message in res.stderr
    assert list(tmp_path.iterdir()) == []


def test_output_must_be_yaml(runner, tmp_path):
    res = runner.invoke(main, CHARUCO_ARGS + ["-o", str(tmp_path / "t.png")])
    assert res.exit_code == 2 and "a .yaml file expected" in res.stderr


def test_shipped_default_target_is_what_the_command_writes(runner, tmp_path):
    """calibration_targets/charuco_11x8_12mm.* were generated by the command: regenerate and compare."""
    assert read_target(DEFAULT) == TargetSpec("charuco", (11, 8), 0.012, 0.009, "DICT_5X5_250",
                                              name="charuco_11x8_12mm")
    out = tmp_path / "charuco_11x8_12mm.yaml"
    _json(runner.invoke(main, CHARUCO_ARGS + ["-o", str(out), "--json"]))
    shipped, fresh = (yaml.safe_load(p.read_text()) for p in (DEFAULT, out))
    shipped.pop("heartcv_version"), fresh.pop("heartcv_version")
    assert fresh == shipped
    assert np.array_equal(read_image(out.with_suffix(".png")), read_image(DEFAULT.with_suffix(".png")))
    assert DEFAULT.with_suffix(".pdf").is_file()
    # sized for the rig's field of view (about 17 cm across): the board is 13.2 x 9.6 cm
    assert TargetSpec.from_dict(yaml.safe_load(DEFAULT.read_text())).board_size_m == pytest.approx((0.132, 0.096))


def test_a_target_of_the_same_stem_keeps_its_printable_files(runner, tmp_path):
    """a.yml beside a.yaml would write a.png/a.pdf, which a.yaml names: refused (exit 2) and every byte kept; the
    rerun of a.yaml itself, and a target of another stem, are written."""
    base = ["target", "--type", "charuco", "--square-mm", "12", "--marker-mm", "9"]
    assert runner.invoke(main, base + ["--squares", "11x8", "-o", str(tmp_path / "a.yaml")]).exit_code == 0
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    res = runner.invoke(main, base + ["--squares", "5x7", "-o", str(tmp_path / "a.yml")])
    assert res.exit_code == 2 and "a.png and a.pdf belong to the target" in res.stderr, res.output
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    assert runner.invoke(main, base + ["--squares", "5x7", "-o", str(tmp_path / "a.yaml")]).exit_code == 0
    assert read_target(tmp_path / "a.yaml").squares == (5, 7)
    assert runner.invoke(main, base + ["--squares", "5x7", "-o", str(tmp_path / "b.yml")]).exit_code == 0

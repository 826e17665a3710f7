"""``heartcv measure`` on a small rendered sequence (3 cameras, 480x270, 10 frames, the true rig): the --json
summary, and bad input. Isolated bad images (a missing or truncated file) are named in a warning and that camera
is left out of that instant (exit 0); inconsistent input (frame counts, image size, camera names, inputs time
range, output suffix, no such folder) exits 2 naming the culprit. Every failure leaves no output behind, and no
run touches its inputs."""

from __future__ import annotations

import csv
import hashlib
import json
from pathlib import Path
import shutil

from click.testing import CliRunner
import numpy as np
import pytest
import yaml

from heartcv.cli.main import main
from tests.heartcv.render_scenes import scene_dict, write_truth_model

FRAMES = 10
SUMMARY_KEYS = {"frames", "points_mean", "points_min", "reprojection_rms_px", "frames_per_s"}
TRUTH_KEYS = {"error_rms_m", "error_p99_m"}


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """A 10-frame sequence of the default scene at 1/4 resolution (coarse truth model: ~5 s to render)."""
    root = tmp_path_factory.mktemp("measure_render")
    model = write_truth_model(root / "model.yaml", grid=(7, 5, 2))
    scene = root / "scene.yaml"
    scene.write_text(yaml.safe_dump(scene_dict(model, motion={"duration_s": 0.4})))
    res = CliRunner().invoke(main, ["render", "sequence", str(scene), "-o", str(root / "seq"), "--frames",
                                    str(FRAMES), "--workers", "2"])
    assert res.exit_code == 0, res.output
    return root / "seq"


@pytest.fixture
def case(tmp_path, rendered):
    """A private copy of the sequence (cameras, timestamps.csv, inputs.csv), its rig, and an empty output folder."""
    seq = tmp_path / "seq"
    for cam in ("cam0", "cam1", "cam2"):
        shutil.copytree(rendered / cam, seq / cam)
    for name in ("timestamps.csv", "inputs.csv"):
        shutil.copy(rendered / name, seq / name)
    rig = tmp_path / "rig.yaml"
    shutil.copy(rendered / "rig_truth.yaml", rig)
    out = tmp_path / "out"
    out.mkdir()
    return {"seq": seq, "rig": rig, "out": out, "truth": rendered / "truth.npz", "root": tmp_path}


def _snapshot(*paths):
    """sha256 of every file under the given files/folders."""
    files = {}
    for p in paths:
        for f in ([p] if p.is_file() else sorted(q for q in p.rglob("*") if q.is_file())):
            files[str(f)] = hashlib.sha256(f.read_bytes()).hexdigest()
    return files


def _measure(case, *extra, seq=None, rig=None, out=None):
    """Run ``heartcv measure`` with -o out/meas.npz --csv out/meas.csv; check the inputs are unchanged."""
    seq = case["seq"] if seq is None else seq
    rig = case["rig"] if rig is None else rig
    out = case["out"] / "meas.npz" if out is None else out
    inputs = [p for p in (seq, rig) if Path(p).exists()]
    before = _snapshot(*inputs)
    res = CliRunner().invoke(main, ["measure", str(seq), "--rig", str(rig), "-o", str(out), "--csv",
                                    str(case["out"] / "meas.csv"), "--points", "100", *map(str, extra)])
    assert _snapshot(*inputs) == before, "heartcv measure changed its inputs"
    return res


def _assert_failed_cleanly(res, *words):
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output
    for w in words:
        assert str(w) in res.stderr, (w, res.stderr)


def _assert_no_output(case):
    left = sorted(p.name for p in case["out"].iterdir())
    assert left == [], f"left behind: {left}"


def _read_csv(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(line for line in fh if not line.startswith("#")))


# -- a segment of a recording ------------------------------------------------------------------------------------
def test_a_segment_is_measured_as_the_recording_cut_to_it(case, tmp_path):
    """--start 3 --frames 5 measures frames 3-7 exactly as a copy of the recording holding only those frames: the
    same points, positions, covariances, views bit for bit, the same truth errors (against the truth of those
    frames). Unlike the copy, whose clock starts at its first frame, the segment keeps the recording's: its times
    and inputs are the whole recording's of frames 3-7, its frame names those frames', and its metadata says where
    it starts. Without a timestamps.csv the times follow the frame rate from the start frame. A start beyond the
    recording exits 2."""
    from heartcv.tracker.io import read_measurements

    seq, names = case["seq"], sorted(p.stem for p in (case["seq"] / "cam0").iterdir())
    cut = tmp_path / "cut"
    for cam in ("cam0", "cam1", "cam2"):
        (cut / cam).mkdir(parents=True)
        for p in sorted((seq / cam).iterdir())[3:8]:
            shutil.copy(p, cut / cam / p.name)
    lines = (seq / "timestamps.csv").read_text().splitlines()
    head = [ln for ln in lines if ln.startswith("#")] + [next(ln for ln in lines if not ln.startswith("#"))]
    rows = lines[len(head):]
    assert len(rows) == FRAMES
    (cut / "timestamps.csv").write_text("\n".join(head + rows[3:8]) + "\n")
    shutil.copy(seq / "inputs.csv", cut / "inputs.csv")
    truth = np.load(case["truth"], allow_pickle=True)
    cut_truth = tmp_path / "cut_truth.npz"
    per_frame = ("times", "theta", "inputs", "translation", "vertex_positions", "point_positions",
                 "fiducial_positions", "instrument_mask")
    np.savez(cut_truth, **{k: (truth[k][3:8] if k in per_frame else truth[k]) for k in truth.files})
    res = _measure(case, out=case["out"] / "full.npz")
    assert res.exit_code == 0, res.output
    res = _measure(case, "--start", 3, "--frames", 5, "--truth", case["truth"], "--json",
                   out=case["out"] / "seg.npz")
    assert res.exit_code == 0, res.output
    seg_json = json.loads(res.stdout)
    res = _measure(case, "--truth", cut_truth, "--json", seq=cut, out=case["out"] / "cut.npz")
    assert res.exit_code == 0, res.output
    cut_json = json.loads(res.stdout)
    a, b = read_measurements(case["out"] / "seg.npz"), read_measurements(case["out"] / "cut.npz")
    full = read_measurements(case["out"] / "full.npz")
    assert a.n_frames == 5 and np.array_equal(a.times, full.times[3:8]) and np.array_equal(a.inputs, full.inputs[3:8])
    assert a.times[0] > 0.05 and np.allclose(b.times, a.times - a.times[0])
    for field in ("point_ids", "positions", "covariances", "reference", "views", "reprojection_rms"):
        assert np.array_equal(getattr(a, field), getattr(b, field), equal_nan=True), field
    assert a.meta["frame_names"] == b.meta["frame_names"] == names[3:8]
    assert a.meta["start_frame"] == 3 and b.meta["start_frame"] == 0
    for key in ("error_rms_m", "error_p99_m", "points_mean"):
        assert seg_json[key] == cut_json[key], key
    (seq / "timestamps.csv").unlink()
    (seq / "inputs.csv").unlink()
    res = _measure(case, "--start", 6, "--fps", 20, out=case["out"] / "fps.npz")
    assert res.exit_code == 0, res.output
    f = read_measurements(case["out"] / "fps.npz")
    assert f.n_frames == FRAMES - 6 and np.allclose(f.times, np.arange(6, FRAMES) / 20.0)
    res = _measure(case, "--start", FRAMES, out=case["out"] / "none.npz")
    _assert_failed_cleanly(res, "--start", f"has {FRAMES} frames")
    assert not (case["out"] / "none.npz").exists()


def test_fps_given_replaces_timestamps_with_a_warning(case):
    """--fps beside a timestamps.csv: the frames at k / fps (not the file's times), and a warning naming the file
    it did not read; without --fps the file's times."""
    from heartcv.tracker.io import read_measurements

    stamps = [float(r["time_s"]) for r in _read_csv(case["seq"] / "timestamps.csv")]
    res = _measure(case, "--frames", 3, "--fps", 7, out=case["out"] / "fps.npz")
    assert res.exit_code == 0, res.output
    assert "--fps 7 given" in res.stderr and "timestamps.csv is not read" in res.stderr, res.stderr
    assert np.allclose(read_measurements(case["out"] / "fps.npz").times, np.arange(3) / 7.0)
    assert not np.allclose(np.arange(3) / 7.0, np.asarray(stamps[:3]) - stamps[0])
    res = _measure(case, "--frames", 3, out=case["out"] / "ts.npz")
    assert res.exit_code == 0, res.output
    assert "timestamps.csv is not read" not in res.stderr
    assert np.allclose(read_measurements(case["out"] / "ts.npz").times, np.asarray(stamps[:3]) - stamps[0])
    from heartcv.io import file_hash

    # provenance: the timestamps read are hashed with the other inputs; with --fps they were not read
    assert read_measurements(case["out"] / "ts.npz").meta["inputs_hash"]["timestamps"] == \
        file_hash(case["seq"] / "timestamps.csv")
    assert "timestamps" not in read_measurements(case["out"] / "fps.npz").meta["inputs_hash"]
    assert "milliseconds" not in res.stderr
    # the same times in milliseconds under time_s: read as written (seconds), with a warning naming the file
    rows = _read_csv(case["seq"] / "timestamps.csv")
    cols = list(rows[0])
    (case["seq"] / "timestamps.csv").write_text(",".join(cols) + "\n" + "".join(
        ",".join(str(1e3 * float(r[c])) if c == "time_s" else r[c] for c in cols) + "\n" for r in rows))
    res = _measure(case, "--frames", 3, out=case["out"] / "ms.npz")
    assert res.exit_code == 2 and "inputs.csv: time_s: the inputs cover 0..0.3 s" in res.output  # its inputs' clock
    (case["seq"] / "inputs.csv").unlink()
    res = _measure(case, "--frames", 3, out=case["out"] / "ms.npz")
    assert res.exit_code == 0, res.output
    assert "timestamps.csv: a median frame interval of" in res.stderr and "milliseconds?" in res.stderr
    assert np.allclose(read_measurements(case["out"] / "ms.npz").times, 1e3 * (np.asarray(stamps[:3]) - stamps[0]))


# -- a good run -------------------------------------------------------------------------------------------------
def test_json_summary_keys_with_and_without_truth(case):
    from heartcv.tracker.io import read_measurements

    res = _measure(case, "--json", "--truth", case["truth"])
    assert res.exit_code == 0, res.output
    s = json.loads(res.stdout)
    assert SUMMARY_KEYS | TRUTH_KEYS <= set(s)
    assert s["frames"] == FRAMES and s["points_min"] >= 3 and s["points_mean"] >= s["points_min"]
    assert 0 < s["reprojection_rms_px"] < 0.5 and s["frames_per_s"] > 0
    assert 0 < s["error_rms_m"] <= s["error_p99_m"] < 2e-3     # the phantom, seen through the true rig
    assert sorted(p.name for p in case["out"].iterdir()) == ["meas.csv", "meas.npz"]   # no temporary files
    mset = read_measurements(case["out"] / "meas.npz")
    assert mset.positions.shape[:1] == (FRAMES,)
    assert np.isfinite(mset.positions).all(axis=2).sum(axis=1).min() == s["points_min"]
    assert len(_read_csv(case["out"] / "meas.csv")) == np.isfinite(mset.positions).all(axis=2).sum()
    # each point's reference-camera pixel at birth (for the exact truth comparison of heartcv report) and its
    # birth frame: the reference position is the position in that frame
    uv, birth = np.asarray(mset.meta["reference_uv"]), np.asarray(mset.meta["reference_frame_index"])
    assert uv.shape == (mset.n_points, 2) and np.isfinite(uv).all()
    np.testing.assert_array_equal(mset.reference, mset.positions[birth, np.arange(mset.n_points)])

    res = _measure(case, "--json")
    assert res.exit_code == 0, res.output
    s = json.loads(res.stdout)
    assert SUMMARY_KEYS <= set(s) and not TRUTH_KEYS & set(s)


# -- isolated bad images: warn, leave that camera out of that instant, exit 0 ----------------------------------------
def _views_in_frame(case, frame, camera):
    """(rows of frame, of which use ``camera``) in the written CSV, and the rows of the frame before."""
    rows = _read_csv(case["out"] / "meas.csv")
    here = [r for r in rows if int(r["frame"]) == frame]
    before = [r for r in rows if int(r["frame"]) == frame - 1]
    using = [r for r in here if r[f"u_{camera}_px"] != ""]
    return here, using, before


def test_missing_frame_in_one_camera_is_left_out(case):
    (case["seq"] / "cam1" / "000004.png").unlink()
    res = _measure(case)
    assert res.exit_code == 0, res.output
    assert "cam1" in res.stderr and "000004" in res.stderr
    assert "no point was measured" not in res.stderr and "repeat" not in res.stderr
    here, using, before = _views_in_frame(case, 4, "cam1")
    assert using == []                                       # nothing observed in the missing image
    assert len(here) >= len(before) // 2 >= 1                # still triangulated from cam0 and cam2
    assert all(int(r["views"]) == 2 for r in here)
    _, using_next, _ = _views_in_frame(case, 5, "cam1")
    assert using_next                                        # cam1 is used again in the next instant


def test_repeated_images_are_left_out_named_and_recorded(case):
    """cam1's frame 4 a copy of its frame 3 (out of step), every camera's frame 7 a copy of frame 6: cam1 is left
    out of instant 4, instant 7 is empty; warned, counted in --json and listed in the file; keep measures them."""
    from heartcv.tracker.io import read_measurements

    for cam, k in (("cam1", 4), ("cam0", 7), ("cam1", 7), ("cam2", 7)):
        shutil.copy(case["seq"] / cam / f"{k - 1:06d}.png", case["seq"] / cam / f"{k:06d}.png")
    res = _measure(case, "--json")
    assert res.exit_code == 0, res.output
    assert "1 of 10 images of camera cam0, 2 of 10 images of camera cam1, 1 of 10 images of camera cam2 repeat" \
        in res.stderr, res.stderr
    s = json.loads(res.stdout)
    assert s["repeated_frames"] == "drop" and s["repeated_views"] == {"cam0": 1, "cam1": 2, "cam2": 1}
    meta = read_measurements(case["out"] / "meas.npz").meta
    assert meta["repeated_views"] == {"cam0": [7], "cam1": [4, 7], "cam2": [7]}
    here, using, before = _views_in_frame(case, 4, "cam1")
    assert using == [] and len(here) >= len(before) // 2 >= 1
    assert _views_in_frame(case, 7, "cam0")[0] == []
    (case["out"] / "meas.npz").unlink()
    (case["out"] / "meas.csv").unlink()
    kept = _measure(case, "--json", "--repeated-frames", "keep")
    assert kept.exit_code == 0, kept.output
    assert "repeat" not in kept.stderr and "repeated_views" not in json.loads(kept.stdout)
    assert "repeated_views" not in read_measurements(case["out"] / "meas.npz").meta
    assert len(_views_in_frame(case, 7, "cam0")[0]) >= 1


def test_frames_where_nothing_was_measured_are_named(case):
    """Frames 5-6 black in every camera (a capture glitch): no point there, and a warning naming them."""
    import cv2

    for cam in ("cam0", "cam1", "cam2"):
        for k in (5, 6):
            path = case["seq"] / cam / f"{k:06d}.png"
            cv2.imwrite(str(path), np.zeros_like(cv2.imread(str(path))))
    res = _measure(case, "--json")
    assert res.exit_code == 0, res.output
    assert "no point was measured in 2 of 10 frames (5-6)" in res.stderr, res.stderr
    assert json.loads(res.stdout)["points_min"] == 0


def test_missing_first_reference_image_starts_a_frame_later(case):
    """Without cam0's first image nothing can be detected in frame 0: it is empty, tracking starts in frame 1."""
    (case["seq"] / "cam0" / "000000.png").unlink()
    res = _measure(case, "--json")
    assert res.exit_code == 0, res.output
    assert "cam0" in res.stderr and "000000" in res.stderr
    s = json.loads(res.stdout)
    assert s["frames"] == FRAMES and s["points_min"] == 0
    here, _, _ = _views_in_frame(case, 0, "cam0")
    later, _, _ = _views_in_frame(case, 1, "cam0")
    assert here == [] and len(later) >= 3


@pytest.mark.parametrize("camera", ["cam2", "cam0"])
def test_truncated_image_is_named_and_left_out(case, camera):
    """A PNG cut short in one camera (the reference camera cam0 included) is named in a warning; the other two
    views carry that instant."""
    bad = case["seq"] / camera / "000005.png"
    data = bad.read_bytes()
    bad.write_bytes(data[: len(data) // 2])
    res = _measure(case)
    assert res.exit_code == 0, res.output
    assert f"{camera}/000005.png" in res.stderr and "truncated" in res.stderr
    here, using, before = _views_in_frame(case, 5, camera)
    assert using == []
    # the points seen by the two other cameras in the frame before are carried by them (points matched in only two
    # cameras, one of them the lost one, cannot be: measured 21 of the 21 carried for cam0, of 47 seen before)
    others = [c for c in ("cam0", "cam1", "cam2") if c != camera]
    both = [r for r in before if all(r[f"u_{c}_px"] != "" for c in others)]
    assert len(here) >= len(both) // 2 >= 1
    assert all(int(r["views"]) == 2 for r in here)


# -- inconsistent input: exit 2, nothing written -------------------------------------------------------------------
def test_different_frame_counts_exit_2_naming_the_counts(case):
    for k in (7, 8, 9):
        (case["seq"] / "cam2" / f"{k:06d}.png").unlink()
    res = _measure(case)
    _assert_failed_cleanly(res, "different frame counts", "cam0 10", "cam1 10", "cam2 7")
    _assert_no_output(case)


def test_many_images_of_another_size_exit_2_a_single_one_is_left_out(case):
    """One of cam2's 10 images halved: left out of its frame with a warning; two (20 %, more than a tenth): exit 2
    before any work, naming the camera, the count and the first such image (before 2026-11-29 the run went on)."""
    import cv2

    def halve(k):
        path = case["seq"] / "cam2" / f"{k:06d}.png"
        im = cv2.imread(str(path))
        cv2.imwrite(str(path), cv2.resize(im, (im.shape[1] // 2, im.shape[0] // 2)))

    halve(6)
    res = _measure(case)
    assert res.exit_code == 0, res.output
    assert "000006.png" in res.stderr
    _, using, _ = _views_in_frame(case, 6, "cam2")
    assert using == []
    for p in case["out"].iterdir():
        p.unlink()
    halve(3)
    res = _measure(case)
    _assert_failed_cleanly(res, "cam2/000003.png: images: 2 of camera cam2's 10 images are of another size than "
                                "the rig's")
    _assert_no_output(case)


def test_rig_of_another_image_size_exit_2(case):
    from heartcv.camera import Camera, Rig
    from heartcv.io import read_rig, write_rig

    rig = read_rig(case["rig"])
    cams = list(rig.cameras)
    c = cams[1]
    cams[1] = Camera(c.name, 2 * c.width, 2 * c.height, np.diag([2.0, 2.0, 1.0]) @ c.K, c.dist, c.cam_from_rig)
    write_rig(case["rig"], Rig(tuple(cams)))
    res = _measure(case)
    _assert_failed_cleanly(res, "cam1", "000000.png", "480x270", "960x540")
    _assert_no_output(case)


def test_rig_camera_names_not_in_sequence_exit_2(case):
    from dataclasses import replace

    from heartcv.camera import Rig
    from heartcv.io import read_rig, write_rig

    rig = read_rig(case["rig"])
    write_rig(case["rig"], Rig(tuple(replace(c, name=n) for c, n in zip(rig.cameras, ("left", "cam1", "right")))))
    res = _measure(case)
    _assert_failed_cleanly(res, "'left'", "'right'", "cam0")
    _assert_no_output(case)


@pytest.mark.parametrize("where", ["option", "sequence"])
def test_inputs_not_covering_the_frames_exit_2(case, where):
    """Inputs sampled over 0..0.1 s for frames over 0..0.3 s, given by --inputs or as SEQUENCE/inputs.csv."""
    short = "time_s,pressure_pa\n0.0,1000.0\n0.05,1500.0\n0.1,2000.0\n"
    if where == "option":
        path = case["root"] / "short_inputs.csv"
        path.write_text(short)
        res = _measure(case, "--inputs", path)
    else:
        path = case["seq"] / "inputs.csv"
        path.write_text(short)
        res = _measure(case)
    _assert_failed_cleanly(res, path.name, "0..0.1 s", "0..0.3 s")
    _assert_no_output(case)


def test_nothing_trackable_exit_1_without_output(case):
    """A mask over the black background: no point, exit 1 (the stage failed), nothing written."""
    import cv2

    mask = np.zeros((270, 480), np.uint8)
    mask[5:60, 5:60] = 255
    cv2.imwrite(str(case["root"] / "mask.png"), mask)
    res = _measure(case, "--mask", case["root"] / "mask.png")
    assert res.exit_code == 1, res.output
    assert "no surface point could be tracked" in res.stderr and "Traceback" not in res.output
    assert f"(cameras of {case['rig']})" in res.stderr      # the rig is named beside the sequence
    _assert_no_output(case)


def test_output_not_npz_exit_2(case):
    res = _measure(case, out=case["out"] / "meas.txt")
    _assert_failed_cleanly(res, "meas.txt", ".npz")
    _assert_no_output(case)


def test_no_such_sequence_exit_2(case):
    missing = case["root"] / "no_such_sequence"
    res = _measure(case, seq=missing)
    _assert_failed_cleanly(res, "no_such_sequence", "no such folder")
    _assert_no_output(case)


def test_size_factor_auto_reports_the_blur_and_a_given_factor_scales_the_prefilter(case):
    """--size-factor auto (the default) reports the texture blur it chose from, the size factor 1 and no reduction
    of these sharp frames (blur <= 1 px); a given factor is reported as such, scales the high-pass recorded in the
    file's meta (3 px x 2), and needs no blur; a value that is neither 'auto' nor a number in (0, 100] is exit 2
    with nothing written."""
    from heartcv.tracker.io import read_measurements

    s = json.loads(_measure(case, "--json").stdout)
    assert 0 < s["texture_blur_px"] <= 1.0 and s["size_factor"] == 1.0 and s["reduction"] == 1.0
    assert "texture_blur_reduced_px" not in s
    res = _measure(case, "--json", "--size-factor", "2")
    assert res.exit_code == 0, res.output
    s = json.loads(res.stdout)
    assert s["size_factor"] == 2.0 and "texture_blur_px" not in s
    assert read_measurements(case["out"] / "meas.npz").meta["highpass_sigma"] == 6.0
    for bad in ("0", "-1", "nan", "big", "101"):
        for p in case["out"].iterdir():
            p.unlink()
        _assert_failed_cleanly(_measure(case, "--size-factor", bad), "--size-factor", repr(bad))
        _assert_no_output(case)
        # with --dense too (a bad value was not even checked there)
        _assert_failed_cleanly(_measure(case, "--dense", "--size-factor", bad), "--size-factor", repr(bad))
        _assert_no_output(case)
    # the sparse mode's options given with --dense (this helper always gives --points): named (they were accepted
    # and ignored)
    _assert_failed_cleanly(_measure(case, "--dense", "--size-factor", "2"), "--dense: --points, --size-factor apply "
                           "to the sparse mode only")
    _assert_failed_cleanly(_measure(case, "--dense", "--window", "21", "--backend", "opencv"),
                           "--dense: --points, --window, --backend apply to the sparse mode only")
    _assert_no_output(case)


def test_oversampled_frames_are_measured_reduced_and_reported_in_their_own_pixels(case, tmp_path):
    """The sequence upsampled 2x (bicubic, 960 x 540; its rig's cameras scaled to match, the inverse of
    heartcv.measure.reduced_camera) reads blurrier than 1 px: --size-factor auto tracks it on frames reduced until
    they read sharp (reported: a reduction between 1.5 and 2.5, the reduced blur <= 1 px, size factor 1), and its
    tracks are as long and as accurate as the native frames' (truth RMS within 1.5x, seen-median frames within 1). Its
    2-D positions are in the upsampled frames' pixels: each point's first position (meta reference_uv) is where
    the upsampled camera projects its first 3-D position (within 3 px of 960; the native camera's pixels would be
    half of that) and lies inside 960 x 540. A --pixel-sigma is taken and reported in those pixels too."""
    import cv2

    from heartcv.evaluate import truth_errors
    from heartcv.io import read_render_truth, read_rig, write_rig
    from heartcv.measure import reduced_camera
    from heartcv.measure_data import truth_for_frames
    from heartcv.tracker.io import read_measurements

    native = json.loads(_measure(case, "--json", "--truth", case["truth"]).stdout)
    up = tmp_path / "up"
    for cam in ("cam0", "cam1", "cam2"):
        (up / cam).mkdir(parents=True)
        for f in sorted((case["seq"] / cam).iterdir()):
            im = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
            cv2.imwrite(str(up / cam / f.name), cv2.resize(im, (2 * im.shape[1], 2 * im.shape[0]),
                                                            interpolation=cv2.INTER_CUBIC))
    for name in ("timestamps.csv", "inputs.csv"):
        shutil.copy(case["seq"] / name, up / name)
    rig = read_rig(case["rig"])
    big = type(rig)([reduced_camera(c, 0.5) for c in rig.cameras])
    write_rig(tmp_path / "rig_up.yaml", big)
    out = tmp_path / "up_meas.npz"
    res = _measure(case, "--json", seq=up, rig=tmp_path / "rig_up.yaml", out=out)
    assert res.exit_code == 0, res.output
    s = json.loads(res.stdout)
    assert s["texture_blur_px"] > 1.0 and 1.5 < s["reduction"] < 2.5 and s["texture_blur_reduced_px"] <= 1.0
    assert s["size_factor"] == 1.0
    assert s["track_seen_median_frames"] >= native["track_seen_median_frames"] - 1
    m = read_measurements(out)
    uv0 = np.array(m.meta["reference_uv"], float)
    assert ((uv0 >= 0) & (uv0 < [960, 540])).all()
    born = np.asarray(m.meta["reference_frame_index"])
    X0 = m.positions[born, np.arange(m.n_points)]
    proj = big.cameras[0].project(X0)
    assert np.nanmedian(np.linalg.norm(proj - uv0, axis=1)) < 3.0
    # the truth is the native frames': look each track up at its native pixel
    arrays, meta = read_render_truth(case["truth"])
    truth = truth_for_frames(arrays, meta, FRAMES, ["cam0", "cam1", "cam2"])
    te = truth_errors(m.positions, (uv0 + 0.5) / 2 - 0.5, born, truth, ref_camera=0)
    assert te.rms_m < 1.5 * native["error_rms_m"]
    # a given pixel noise is in the frames' own pixels, and reported so
    out.unlink()
    res = _measure(case, "--json", "--pixel-sigma", "0.7", seq=up, rig=tmp_path / "rig_up.yaml", out=out)
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["sigma_px"] == pytest.approx(0.7)
    assert read_measurements(out).meta["sigma_px"] == pytest.approx(0.7)


def test_interlaced_frames_are_measured_one_field(case, tmp_path):
    """Interlaced frames built so that their first field is exactly the sequence (960 x 540 would be the frame:
    here 480 x 540, rows 0, 2, ... the sequence's frame, rows 1, 3, ... the same view moved 3 px sideways, a second
    instant as an interlaced camera records a fast pan; the rig's cameras with twice the vertical focal length and
    principal point). By default (--fields auto) measure sees that they look interlaced (combing ratio above 1
    in --json; the sequence as it is reads below 1), says so, and measures their first field: exactly the sequence
    (with the same region of interest, row-doubled), the same positions as the progressive run, bit for bit, its
    pixel rows mapped to the full frames (v = 2 v_field); --fields first does the same without the warning, and
    --fields none measures the whole frames with a warning naming --fields first. (--fields with --dense:
    tests/cli/test_measure_endoscope.py.)"""
    import cv2

    from heartcv.camera import Camera
    from heartcv.io import read_rig, write_rig
    from heartcv.tracker.io import read_measurements

    rig = read_rig(case["rig"])
    W, H = rig.cameras[0].size
    mask = np.zeros((H, W), np.uint8)
    mask[H // 6:H - H // 6, W // 6:W - W // 6] = 255
    cv2.imwrite(str(tmp_path / "mask.png"), mask)
    cv2.imwrite(str(tmp_path / "mask2.png"), np.repeat(mask, 2, axis=0))
    native = json.loads(_measure(case, "--json", "--mask", tmp_path / "mask.png").stdout)
    assert native["combing_ratio"] < 1.0 and native["fields"] is None
    ref = read_measurements(case["out"] / "meas.npz")
    woven = tmp_path / "woven"
    for cam in ("cam0", "cam1", "cam2"):
        (woven / cam).mkdir(parents=True)
        for f in sorted((case["seq"] / cam).iterdir()):
            im = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
            out = np.repeat(im, 2, axis=0)
            out[0::2], out[1::2] = im, np.roll(im, 3, axis=1)
            cv2.imwrite(str(woven / cam / f.name), out)
    for name in ("timestamps.csv", "inputs.csv"):
        shutil.copy(case["seq"] / name, woven / name)
    tall = []
    for c in rig.cameras:
        K = np.array(c.K, float)
        K[1] *= 2.0
        K[2] = [0.0, 0.0, 1.0]
        tall.append(Camera(c.name, c.width, 2 * c.height, K, c.dist, c.cam_from_rig))
    write_rig(tmp_path / "rig2.yaml", type(rig)(tall))
    out = tmp_path / "w.npz"
    args = ("--json", "--mask", tmp_path / "mask2.png")
    for extra, warned in (((), "measuring the first field"), (("--fields", "first"), None)):
        res = _measure(case, *args, *extra, seq=woven, rig=tmp_path / "rig2.yaml", out=out)
        assert res.exit_code == 0, res.output
        s = json.loads(res.stdout)
        assert s["combing_ratio"] > 1.0 and s["fields"] == "first"
        assert (warned in res.stderr) if warned else "look interlaced" not in res.stderr, res.stderr
        m = read_measurements(out)
        np.testing.assert_array_equal(m.positions, ref.positions)
        np.testing.assert_array_equal(m.point_ids, ref.point_ids)
        uv, uv_ref = np.array(m.meta["reference_uv"]), np.array(ref.meta["reference_uv"])
        np.testing.assert_allclose(uv, uv_ref * [1.0, 2.0], atol=1e-3)     # float32 pixel positions
        out.unlink()
    res = _measure(case, *args, "--fields", "none", seq=woven, rig=tmp_path / "rig2.yaml", out=out)
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["fields"] is None
    assert "look interlaced" in res.stderr and "--fields first" in res.stderr, res.stderr
    assert read_measurements(out).positions.shape != ref.positions.shape      # other tracks, from combed frames


def test_both_fields_are_measured_as_instants_of_their_own(case, tmp_path):
    """--fields both: 5 interlaced frames woven from the 10 rendered ones (frame k: rows 0, 2, ... of instant 2k,
    rows 1, 3, ... of instant 2k + 1) are measured exactly as a progressive folder of their 10 fields, each
    interpolated back to the frame's rows (heartcv.measure.bob_field, written as images): the same points,
    positions and covariances bit for bit. The instants' times are the frames' and half a frame later
    (measure_data.field_times), their names the frame's with the field, and --field-order bottom swaps each frame's
    two instants. --field-order without --fields both, --truth with it, or a single frame exit 2."""
    import cv2

    from heartcv.measure import bob_field
    from heartcv.measure_data import field_times
    from heartcv.tracker.io import read_measurements

    seq = case["seq"]
    names = sorted(p.stem for p in (seq / "cam0").iterdir())
    woven, bobbed = tmp_path / "woven", tmp_path / "bobbed"
    for cam in ("cam0", "cam1", "cam2"):
        (woven / cam).mkdir(parents=True)
        (bobbed / cam).mkdir(parents=True)
        files = sorted((seq / cam).iterdir())
        for k in range(FRAMES // 2):
            a = cv2.imread(str(files[2 * k]), cv2.IMREAD_UNCHANGED)
            b = cv2.imread(str(files[2 * k + 1]), cv2.IMREAD_UNCHANGED)
            w = a.copy()
            w[1::2] = b[1::2]
            cv2.imwrite(str(woven / cam / files[2 * k].name), w)
            for j, f in enumerate((0, 1)):
                cv2.imwrite(str(bobbed / cam / f"{2 * k + j:06d}.png"), bob_field(w, f))
    t_frames = np.arange(FRAMES // 2) / 15.0
    (woven / "timestamps.csv").write_text("time_s\n" + "".join(f"{float(t)!r}\n" for t in t_frames))
    (bobbed / "timestamps.csv").write_text("time_s\n" + "".join(f"{float(t)!r}\n" for t in field_times(t_frames)))
    res = _measure(case, "--fields", "both", "--field-order", "top", "--json", seq=woven, out=case["out"] / "b.npz")
    assert res.exit_code == 0, res.output
    s = json.loads(res.stdout)
    assert s["fields"] == "both" and s["field_order"] == "top first" and s["frames"] == FRAMES
    res = _measure(case, "--fields", "none", seq=bobbed, out=case["out"] / "p.npz")
    assert res.exit_code == 0, res.output
    a, b = read_measurements(case["out"] / "b.npz"), read_measurements(case["out"] / "p.npz")
    np.testing.assert_allclose(a.times, field_times(t_frames), rtol=0, atol=1e-12)
    np.testing.assert_allclose(b.times, a.times, rtol=0, atol=1e-12)
    for field in ("point_ids", "positions", "covariances", "reference", "views"):
        assert np.array_equal(getattr(a, field), getattr(b, field), equal_nan=True), field
    assert a.meta["frame_names"][:4] == [f"{names[0]}.top", f"{names[0]}.bottom", f"{names[2]}.top",
                                         f"{names[2]}.bottom"]
    res = _measure(case, "--fields", "both", "--field-order", "bottom", seq=woven, out=case["out"] / "bb.npz")
    assert res.exit_code == 0, res.output
    assert read_measurements(case["out"] / "bb.npz").meta["frame_names"][:2] == [f"{names[0]}.bottom",
                                                                                   f"{names[0]}.top"]
    res = _measure(case, "--fields", "both", "--json", seq=woven, out=case["out"] / "auto.npz")
    assert res.exit_code == 0, res.output
    s = json.loads(res.stdout)
    assert s["field_order_pairs"] <= 3 and s["field_order"] in ("top first", "bottom first")
    for extra, words in ((("--field-order", "top"), ("--field-order", "--fields both")),
                         (("--fields", "both", "--truth", case["truth"]), ("--truth", "--fields both")),
                         (("--fields", "both", "--frames", 1), ("--fields both", "at least 2"))):
        res = _measure(case, *extra, seq=woven, out=case["out"] / "x.npz")
        _assert_failed_cleanly(res, *words)
        assert not (case["out"] / "x.npz").exists()


def test_jittered_and_dropped_frames_are_put_on_a_uniform_grid(case, tmp_path):
    """A timestamps.csv whose times jitter (by up to 3 ms, rounded to 1 ms) and skip a frame (the fourth image
    removed from every camera): the measurement file has the frames on a uniform grid (the estimators need a
    constant interval): 10 frames, the missing one empty (nothing seen, views 0, named '(missing)'), the others'
    positions those of the same images measured with --fps (bit for bit: the times do not enter the tracking),
    the birth frames mapped onto the grid; --json's frame_grid says so, and a warning names the file. Times too
    irregular for a grid exit 2 naming timestamps.csv."""
    from heartcv.tracker.io import read_measurements

    seq = case["seq"]
    for cam in ("cam0", "cam1", "cam2"):
        sorted((seq / cam).iterdir())[3].unlink()
    (seq / "inputs.csv").unlink()
    rng = np.random.default_rng(2)
    kept = np.delete(np.arange(FRAMES), 3)
    t = np.round(kept / 30.0 + rng.uniform(-0.003, 0.003, kept.size), 3)
    (seq / "timestamps.csv").write_text("time_s\n" + "".join(f"{float(x)!r}\n" for x in t))
    res = _measure(case, "--json", out=case["out"] / "g.npz")
    assert res.exit_code == 0, res.output
    s = json.loads(res.stdout)
    assert s["frame_grid"]["frames"] == FRAMES and s["frame_grid"]["missing_frames"] == 1
    assert abs(s["frame_grid"]["interval_s"] - 1 / 30) < 5e-4 and "uniform grid" in res.stderr
    g = read_measurements(case["out"] / "g.npz")
    assert g.n_frames == FRAMES and np.allclose(np.diff(g.times), s["frame_grid"]["interval_s"], rtol=1e-9)
    assert not np.isfinite(g.positions[3]).any() and not g.views[3].any() and g.meta["frame_names"][3] == "(missing)"
    assert g.meta["frame_grid"] == s["frame_grid"] and s["frame_grid"]["measured_frames"] == FRAMES - 1
    (seq / "timestamps.csv").unlink()
    res = _measure(case, "--fps", 30, out=case["out"] / "u.npz")
    assert res.exit_code == 0, res.output
    u = read_measurements(case["out"] / "u.npz")
    rows = np.r_[0:3, 4:FRAMES]
    for field in ("positions", "covariances", "views"):
        assert np.array_equal(getattr(g, field)[rows], getattr(u, field), equal_nan=True), field
    assert g.meta["reference_frame_index"] == [int(rows[b]) for b in u.meta["reference_frame_index"]]
    assert [g.meta["frame_names"][r] for r in rows] == u.meta["frame_names"]
    t_bad = np.r_[kept[:4] / 30.0, kept[4] / 30.0 + 0.012, kept[5:] / 30.0]
    (seq / "timestamps.csv").write_text("time_s\n" + "".join(f"{float(x)!r}\n" for x in t_bad))
    res = _measure(case, out=case["out"] / "bad.npz")
    _assert_failed_cleanly(res, "timestamps.csv", "time_s", "too irregular")
    assert not (case["out"] / "bad.npz").exists()


def test_a_video_whose_own_times_skip_a_frame_goes_on_the_grid(case, tmp_path, monkeypatch):
    """The rendered sequence as one MJPG video per camera (stated 30 fps). Where the videos' own presentation times
    follow the stated rate (MJPG in AVI: k / 30 s), measure uses the rate as before. Where they skip an interval
    after the fourth frame (a dropped frame; heartcv.video's probe reports it, stood in for here because OpenCV
    writes only constant-rate videos), measure takes the container's times and puts the frames on the uniform
    grid: 11 grid frames, the fifth empty, the others' positions those measured at the stated rate, bit for bit."""
    import dataclasses

    import cv2

    from heartcv.tracker.io import read_measurements
    import heartcv.video as video

    vids = tmp_path / "vids"
    vids.mkdir()
    for cam in ("cam0", "cam1", "cam2"):
        files = sorted((case["seq"] / cam).iterdir())
        first = cv2.imread(str(files[0]))
        w = cv2.VideoWriter(str(vids / f"{cam}.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 30.0,
                            (first.shape[1], first.shape[0]))
        if not w.isOpened():
            pytest.skip("this OpenCV build cannot write MJPG")
        for f in files:
            w.write(cv2.imread(str(f)))
        w.release()
    res = _measure(case, "--json", seq=vids, out=case["out"] / "rate.npz")
    assert res.exit_code == 0, res.output
    assert "frame_grid" not in json.loads(res.stdout) and "presentation times" not in res.stderr
    rate = read_measurements(case["out"] / "rate.npz")
    np.testing.assert_allclose(rate.times, np.arange(FRAMES) / 30.0, rtol=0, atol=1e-12)
    real = video.check_videos

    def skipping(paths, *a, **kw):
        infos = real(paths, *a, **kw)
        t = np.r_[np.arange(4), np.arange(5, FRAMES + 1)] / 30.0
        return [dataclasses.replace(i, times_s=t) for i in infos]

    monkeypatch.setattr(video, "check_videos", skipping)
    res = _measure(case, "--json", seq=vids, out=case["out"] / "own.npz")
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["frame_grid"]["missing_frames"] == 1 and "presentation times" in res.stderr
    own = read_measurements(case["out"] / "own.npz")
    assert own.n_frames == FRAMES + 1 and not np.isfinite(own.positions[4]).any()
    rows = np.r_[0:4, 5:FRAMES + 1]
    for field in ("positions", "covariances", "views"):
        assert np.array_equal(getattr(own, field)[rows], getattr(rate, field), equal_nan=True), field

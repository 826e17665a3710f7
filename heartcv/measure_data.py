"""The data around the measurement stage (``heartcv measure``, docs/cli.md §10): frame times, the known inputs
at the frame times, the check that a rig fits a sequence's images, the render truth of the measured frames and
the comparison with it, the run's summary and the long-form CSV rows.

Pure functions on arrays and typed objects: the files are read and written by :mod:`heartcv.io` and the command
line. Input that fails validation raises :class:`heartcv.tracker.files.InputError` with the field (column,
camera, array) and no file; the caller attaches the file (:meth:`InputError.in_file`).
"""

from __future__ import annotations

import math

import numpy as np

from .tracker.files import InputError

__all__ = ["UNIT_SUFFIXES", "DEFAULT_FPS", "split_unit", "frame_times", "field_times", "GRID_TOLERANCE",
           "uniform_times", "frame_grid", "container_times", "expand_to_grid", "rectified_v_offsets",
           "rectified_cameras", "inputs_at_frames", "check_image_sizes", "truth_for_frames", "truth_statistics",
           "reference_pixels", "measurement_summary", "CSV_HEADER", "measurement_csv_lines", "frame_spans",
           "OTHER_SIZE_FRACTION", "check_image_size_census",
           "check_rectified_meta"]

# inputs.csv column suffix -> (unit written to the measurement file, factor to SI)
UNIT_SUFFIXES = {"_pa": ("Pa", 1.0), "_kpa": ("Pa", 1e3), "_mmhg": ("Pa", 133.322387415), "_m": ("m", 1.0),
                 "_mm": ("m", 1e-3)}
DEFAULT_FPS = 30.0     # frame rate without timestamps, --fps or a video's own rate

CSV_HEADER = "heartcv measure: tracked points in the rig frame (docs/formats.md, measurement CSV)"


# -- frame times and inputs -------------------------------------------------------------------------------------------
def split_unit(column: str) -> tuple[str, str, float]:
    """``(input name, SI unit, factor to SI)`` of an inputs.csv column: ``pressure_mmhg`` -> ``('pressure', 'Pa',
    133.32...)``; a column without a known suffix keeps its name, with no unit and factor 1."""
    for suffix, (unit, factor) in UNIT_SUFFIXES.items():
        if column.lower().endswith(suffix):
            return column[: -len(suffix)], unit, factor
    return column, "", 1.0


def frame_times(count: int, *, timestamps=None, fps: float | None = None, video_fps: float | None = None):
    """Times (count,) of the frames in seconds: the first ``count`` timestamps when given, else ``k / rate`` with
    the rate ``fps``, else ``video_fps``, else :data:`DEFAULT_FPS`."""
    if timestamps is not None:
        return np.asarray(timestamps, float)[:count]
    rate = fps or video_fps or DEFAULT_FPS
    return np.arange(count) / rate


GRID_TOLERANCE = 0.25
"""How far (in frame intervals) a frame may lie from its point of the uniform grid :func:`frame_grid` fits: a
quarter interval keeps every frame nearer its own grid point than any other by a factor of three."""


def uniform_times(times, rtol: float = 1e-6) -> bool:
    """Whether frame times are equally spaced to ``rtol`` of their median interval (what the estimators require,
    ``tracker.tracking.frame_interval``); a single frame is."""
    d = np.diff(np.asarray(times, float))
    return d.size == 0 or bool(np.abs(d - np.median(d)).max() <= rtol * np.median(d))


def frame_grid(times, tolerance: float = GRID_TOLERANCE):
    """A uniform grid for frame times that jitter (timestamps rounded, a capture's clock) or skip frames (dropped
    frames): ``(index (K,), grid (G,), dt, offset (K,))``, frame k on grid point ``index[k]``, ``grid = t0 + dt
    arange(G)`` with ``G = index[-1] + 1`` (grid points with no frame: the dropped frames), ``offset`` each frame's
    time minus its grid point's, in intervals.

    Each interval between consecutive frames counts ``round(d / median d)`` grid steps (at least 1), so a slowly
    drifting clock does not move later frames to the wrong point; ``t0`` and ``dt`` are then the least-squares line
    through (index, time).

    Raises
    ------
    ValueError
        Fewer than 2 frames, times not finite and strictly increasing, two frames less than half the median
        interval apart (two frames on one grid point), or a frame farther than ``tolerance`` intervals from its
        grid point (timing too irregular for a constant frame interval); the message names the frame.
    """
    t = np.asarray(times, float)
    if t.ndim != 1 or t.size < 2:
        raise ValueError(f"times: at least 2 frames expected, got {t.size}")
    d = np.diff(t)
    if not (np.isfinite(t).all() and (d > 0).all()):
        raise ValueError("times: finite and strictly increasing expected")
    median = float(np.median(d))
    steps = np.rint(d / median).astype(np.int64)
    if (steps < 1).any():
        k = int(np.argmax(steps < 1))
        raise ValueError(f"frames {k} and {k + 1} are {1e3 * d[k]:.4g} ms apart, less than half the median interval "
                         f"{1e3 * median:.4g} ms (two frames on one point of a uniform grid)")
    index = np.r_[0, np.cumsum(steps)]
    A = np.column_stack([np.ones(t.size), index.astype(float)])
    (t0, dt), *_ = np.linalg.lstsq(A, t, rcond=None)
    offset = (t - (t0 + dt * index)) / dt
    worst = int(np.argmax(np.abs(offset)))
    if abs(offset[worst]) > tolerance:
        raise ValueError(f"frame {worst} (t = {t[worst]:.6g} s) lies {offset[worst]:+.2f} of an interval from a "
                         f"uniform grid of {1e3 * dt:.6g} ms fitted to the frame times (at most {tolerance:g} "
                         "allowed): timing too irregular for a constant frame interval")
    return index, t0 + dt * np.arange(index[-1] + 1), float(dt), offset


def container_times(times_s, fps: float | None, count: int):
    """A video's own frame times (its container's presentation times, ``heartcv.video.VideoInfo.times_s``) for its
    first ``count`` frames, from 0, when they are what the frames' timing is: when the container states no rate
    (``fps`` None), or when some frame lies more than :data:`GRID_TOLERANCE` of an interval from ``k / fps`` (a
    variable frame rate, dropped frames). None otherwise (the nominal rate describes the frames; times rounded by
    the container do not count), and None without such times."""
    if times_s is None:
        return None
    t = np.asarray(times_s, float)[:count]
    t = t - t[0]
    if fps is None:
        return t
    nominal = np.arange(t.size) / fps
    return t if np.abs(t - nominal).max() * fps > GRID_TOLERANCE else None


def expand_to_grid(values, index, count: int, fill):
    """``values`` (K, ...) placed on the rows ``index`` (K,) of an array of ``count`` rows, the others ``fill``."""
    values = np.asarray(values)
    out = np.full((count,) + values.shape[1:], fill, dtype=values.dtype)
    out[np.asarray(index)] = values
    return out


def rectified_v_offsets(uv, ref: int = 0):
    """The vertical offset of every camera's views from the reference camera's in a rectified rig's measurement:
    ``[(offset_px, standard_error_px, tracks)]`` per camera (the reference camera's ``(0, 0, 0)``; NaN where fewer
    than 3 tracks were seen in both). In a rectified pair a surface point lies on the same row in every view, so a
    camera whose observations lie ``offset`` px below the reference camera's on average (``v_c - v_ref``) was
    rectified ``offset`` px off; its principal point ``cy + offset`` describes it. Per track the median of
    ``v_c - v_ref`` over the frames seen in both (a track's frames share its template, so they are not independent
    samples); then the median over tracks, and ``1.4826 MAD / sqrt(tracks)`` its standard error.

    Parameters
    ----------
    uv : ndarray (K, P, C, 2)   observed pixels (NaN: not observed)
    """
    uv = np.asarray(uv, float)
    K, P, C, _ = uv.shape
    out = []
    for c in range(C):
        if c == ref:
            out.append((0.0, 0.0, 0))
            continue
        d = uv[:, :, c, 1] - uv[:, :, ref, 1]                        # (K, P)
        have = np.isfinite(d).any(axis=0)
        if have.sum() < 3:
            out.append((math.nan, math.nan, int(have.sum())))
            continue
        per_track = np.nanmedian(d[:, have], axis=0)
        med = float(np.median(per_track))
        se = 1.4826 * float(np.median(np.abs(per_track - med))) / math.sqrt(per_track.size)
        out.append((med, se, int(per_track.size)))
    return out


def rectified_cameras(cameras, offsets, ref: int = 0, among=None, sigmas: float = 3.0):
    """``(cameras, moved)``: a rectified rig's cameras with each camera whose measured vertical offset
    (:func:`rectified_v_offsets`) differs from the rig's own (``cy_c - cy_ref``) by more than ``sigmas`` standard
    errors given the principal point ``cy_ref + offset``; ``moved`` the indices of those cameras. ``among``: only
    these cameras may move (default: every one but the reference)."""
    from dataclasses import replace

    cams = list(cameras)
    cy = [float(np.asarray(c.K)[1, 2]) for c in cams]
    moved = []
    for c, (off, se, _) in enumerate(offsets):
        if c == ref or (among is not None and c not in among) or not (math.isfinite(off) and math.isfinite(se)):
            continue
        if among is not None or abs(off - (cy[c] - cy[ref])) > sigmas * se:
            K = np.array(cams[c].K, float)
            K[1, 2] = cy[ref] + off
            cams[c] = replace(cams[c], K=K)
            moved.append(c)
    return cams, moved


def field_times(times) -> np.ndarray:
    """Times (2 K,) of the two fields of K interlaced frames taken at ``times`` (K,), as instants of their own
    (:class:`heartcv.measure.FieldInstants`): the first field at the frame's time, the second half a frame later
    (half the interval to the next frame; for the last frame, to the one before). ValueError for fewer than 2
    frames or times that do not increase."""
    t = np.asarray(times, float)
    if t.ndim != 1 or t.size < 2:
        raise ValueError(f"times: at least 2 frames expected, got {t.size}")
    dt = np.diff(t)
    if not (np.isfinite(t).all() and (dt > 0).all()):
        raise ValueError("times: finite and strictly increasing expected")
    half = 0.5 * np.r_[dt, dt[-1]]
    return np.stack([t, t + half], axis=1).reshape(-1)


def inputs_at_frames(columns: dict, times) -> tuple[tuple, tuple, np.ndarray]:
    """The known inputs at the frame times: ``(names, units, values (K, n))``, SI units (:func:`split_unit`),
    interpolated linearly (first-order hold) from the table's ``time_s``.

    Parameters
    ----------
    columns : dict of {name: ndarray}
        The table's numeric columns (``heartcv.io.read_inputs_csv_columns``), ``time_s`` among them.
    times : ndarray (K,)
        Frame times, s.

    Raises
    ------
    InputError
        No ``time_s`` column, fewer than two or not strictly increasing times, times that do not cover the
        frames (half a sample of slack at either end), a column with non-finite values, a pressure column without
        a known unit suffix (``pressure``, ``pressure_psi``: it would be taken as pascals). The field names the
        column; no file.
    """
    times = np.asarray(times, float)
    cols = dict(columns)
    if "time_s" not in cols:
        raise InputError(None, f"a 'time_s' column expected, got {list(cols)}", "time_s")
    t = np.asarray(cols.pop("time_s"), float)
    if t.size < 2 or not np.isfinite(t).all() or (np.diff(t) <= 0).any():
        raise InputError(None, "at least two finite, strictly increasing values expected", "time_s")
    half = 0.5 * float(np.median(np.diff(t)))
    if times[0] < t[0] - half or times[-1] > t[-1] + half:
        raise InputError(None, f"the inputs cover {t[0]:.4g}..{t[-1]:.4g} s, the frames {times[0]:.4g}.."
                               f"{times[-1]:.4g} s", "time_s")
    names, units, vals = [], [], []
    for name, v in cols.items():
        v = np.asarray(v, float)
        if not np.isfinite(v).all():
            raise InputError(None, "non-finite values", f"column {name!r}")
        base, unit, factor = split_unit(name)
        low = base.lower()
        if not unit and low.startswith("pressure"):
            raise InputError(None, "a pressure column needs its unit in its name: pressure_mmhg, pressure_kpa or "
                                   "pressure_pa (without one it would be read as pascals)", f"column {name!r}")
        if not unit and low.startswith("active_tension"):
            raise InputError(None, "an active tension column needs its unit in its name: active_tension_kpa or "
                                   "active_tension_pa (without one it would be read as pascals)", f"column {name!r}")
        if not unit and low.startswith("respiration_"):
            raise InputError(None, f"a respiration column needs its unit in its name: {base}_mm or {base}_m "
                                   "(without one it would be read as metres)", f"column {name!r}")
        if unit and ((low.startswith(("pressure", "active_tension")) and unit != "Pa")
                     or (low.startswith("respiration_") and unit != "m")):
            raise InputError(None, f"a {'respiration' if low.startswith('respiration_') else 'load'} column in "
                                   f"{unit}: " + ("metres expected (_m, _mm)" if low.startswith("respiration_")
                                                  else "pascals expected (_pa, _kpa, _mmhg)"), f"column {name!r}")
        if base in names:
            raise InputError(None, f"input {base!r} given twice (as {name!r} and an earlier column): one column "
                                   "per input", f"column {name!r}")
        names.append(base)
        units.append(unit)
        vals.append(np.interp(times, t, v) * factor)
    return tuple(names), tuple(units), np.stack(vals, axis=1) if vals else np.zeros((times.size, 0))


#: More than this fraction of a camera's images of another size than the rig's (as for missing images,
#: ``heartcv.io.open_frame_source``'s ``max_missing_fraction``) is an error, not a few bad frames
OTHER_SIZE_FRACTION = 0.1


def check_image_size_census(cameras, files, rig_name: str = "the rig") -> None:
    """Read the header of every image file (``files[c][k]``, None where missing) and raise :class:`InputError`
    naming the camera, the count and the first such file where more than :data:`OTHER_SIZE_FRACTION` of a camera's
    images (at least 2) have another size than the rig's camera: the folder mixes recordings, or the rig is not
    theirs. Fewer are left out frame by frame, each with a warning, when read. Unreadable headers are skipped
    (their frames name them)."""
    from PIL import Image

    for cam, fs in zip(cameras, files, strict=True):
        present = [f for f in fs if f is not None]
        other = []
        for f in present:
            try:
                with Image.open(f) as im:
                    size = im.size
            except Exception:       # noqa: BLE001 -- unreadable: named when its frame is read
                continue
            if tuple(size) != tuple(cam.size):
                other.append((f, size))
        if len(other) >= 2 and len(other) > OTHER_SIZE_FRACTION * len(present):
            f, (w, h) = other[0]
            raise InputError(f, f"{len(other)} of camera {cam.name}'s {len(present)} images are of another size "
                                f"than the rig's {cam.width}x{cam.height} (this one {w}x{h}); more than "
                                f"{OTHER_SIZE_FRACTION:.0%} is not a few bad frames: the folder mixes recordings, or "
                                f"{rig_name} is not theirs", "images")


def check_image_sizes(cameras, read, count: int, locate, rig_name: str = "the rig") -> None:
    """Check that every camera's first readable image has the rig's image size for that camera.

    Parameters
    ----------
    cameras : sequence of Camera
    read : callable
        ``read(k) -> (images, problems)`` of instant ``k`` without a size check (``heartcv.io.FrameReader``).
    count : int
        Instants to look through for a readable image.
    locate : callable
        ``locate(c, k)`` -> the file of camera ``c``'s image of instant ``k`` (named in the error).

    Raises
    ------
    InputError
        Naming the image and both sizes (the rig does not belong to these images), or the camera none of whose
        ``count`` images can be read.
    """
    pending = list(range(len(cameras)))
    for k in range(count):
        if not pending:
            return
        images, _ = read(k)
        for c in [c for c in pending if images[c] is not None]:
            pending.remove(c)
            cam, (h, w) = cameras[c], images[c].shape[:2]
            if (w, h) != tuple(cam.size):
                raise InputError(locate(c, k), f"image is {w}x{h} px, but the rig's camera {cam.name} is "
                                               f"{cam.width}x{cam.height}: {rig_name} does not belong to these images")
    if pending:
        raise InputError(None, f"none of the {count} images of camera {cameras[pending[0]].name} can be read",
                         "images")


# -- truth ------------------------------------------------------------------------------------------------------------
def truth_for_frames(arrays: dict, meta: dict, count: int, names, start: int = 0) -> dict:
    """The render truth (``heartcv.io.read_render_truth``) of the ``count`` frames from ``start`` of a sequence seen
    by the cameras ``names``.

    Raises
    ------
    InputError
        Not a sequence's truth, fewer frames than measured, other cameras (field ``meta.kind``,
        ``vertex_positions`` or ``meta.camera_names``; no file).
    """
    if meta.get("kind") != "sequence":
        raise InputError(None, f"a sequence truth expected, got kind {meta.get('kind')!r}", "meta.kind")
    if "vertex_positions" not in arrays:
        raise InputError(None, "missing: a sequence truth holds the vertex positions per frame", "vertex_positions")
    n = arrays["vertex_positions"].shape[0]
    if n < start + count:
        raise InputError(None, f"{n} frames of truth for {count} measured" + (f" from frame {start}" if start else ""),
                         "vertex_positions")
    if list(meta.get("camera_names", names)) != list(names):
        raise InputError(None, f"cameras {meta.get('camera_names')} differ from the rig's {list(names)}",
                         "meta.camera_names")
    out = dict(arrays)
    for key in ("vertex_positions", "instrument_mask"):
        if key in out:
            out[key] = out[key][start:start + count]
    return out


def reference_pixels(res, camera, ref: int) -> np.ndarray:
    """Each point's pixel (P, 2) in the reference camera ``ref`` in its birth frame: where it was observed there,
    else (a point born without the reference camera's view: the robust triangulation of three or more views left
    it out as an outlier) the projection of its reference position through ``camera``, the reference camera."""
    P = res.point_ids.size
    uv = np.array([res.uv[res.birth_frame[p], p, ref] for p in range(P)], float).reshape(P, 2)
    missing = ~np.isfinite(uv).all(axis=1)
    if missing.any():
        uv[missing] = camera.project(np.asarray(res.reference, float)[missing])
    return uv


def truth_statistics(res, truth: dict, ref: int, camera) -> dict:
    """Errors of a measurement (:class:`heartcv.measure.MeasureResult`; ``camera`` its reference camera) against
    the render truth (:func:`truth_for_frames`): the ``error_*``, ``aligned_error_*``, ``displacement_*`` and gauge
    keys of the summary (docs/cli.md §10; :func:`heartcv.evaluate.truth_errors`)."""
    from .evaluate import displacement_consistency, occluded_observations, truth_errors

    uv_ref = reference_pixels(res, camera, ref)
    te = truth_errors(res.positions, uv_ref, res.birth_frame, truth, ref_camera=ref)
    out = {"error_rms_m": te.rms_m, "error_p99_m": te.p99_m, "error_mean_m": te.mean_m, "error_max_m": te.max_m,
           "error_observations": te.n, "tracks_off_surface": int((te.material_face < 0).sum()),
           "occluded_observations": occluded_observations(res.uv, truth)}
    if te.aligned is not None:
        R = te.truth_from_rig[:3, :3]
        dc = displacement_consistency(res.positions, res.covariances, te.true_positions, res.birth_frame, R)
        out.update({"displacement_error_rms_m": dc["rms_m"], "displacement_nees_per_dof": dc["nees_per_dof"],
                    "aligned_error_rms_m": te.aligned.rms_m, "aligned_error_p99_m": te.aligned.p99_m,
                    "aligned_error_mean_m": te.aligned.mean_m, "aligned_error_max_m": te.aligned.max_m,
                    "rig_gauge_rotation_deg": float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))),
                    "rig_gauge_translation_m": float(np.linalg.norm(te.truth_from_rig[:3, 3]))})
    return out


# -- summary and CSV --------------------------------------------------------------------------------------------------
#: Cameras of one rig farther apart than this (m) mean a rig file not in metres (docs/cli.md, measure): heartcv
#: watches a surface within reach of surgical instruments; a stereo endoscope's baseline is about 0.005 m.
MAX_BASELINE_M = 1.0
#: Cameras of one rig all closer than this (m) have no baseline to triangulate from (a micrometre: far below any
#: stereo endoscope's 4-6 mm).
MIN_BASELINE_M = 1e-6


def check_rectified_meta(rig, source) -> None:
    """Raise :class:`InputError` for a rig file whose ``rectified`` is not true or false, or whose recorded
    ``baseline_m`` (``heartcv rig rectified``) differs from its first two cameras' distance by more than 1 %: a file
    edited by hand where the poses, which the measurement uses, were left as they were."""
    meta = rig.meta or {}
    rect = meta.get("rectified", False)
    if not isinstance(rect, bool):
        raise InputError(source, f"true or false expected, got {rect!r}", "rectified")
    b = meta.get("baseline_m")
    if rect and b is not None and len(rig.cameras) >= 2:
        if isinstance(b, bool) or not isinstance(b, (int, float)) or not np.isfinite(b) or b <= 0:
            raise InputError(source, f"a positive number of metres expected, got {b!r}", "baseline_m")
        d = float(np.linalg.norm(rig.cameras[1].centre - rig.cameras[0].centre))
        if abs(d - b) > 0.01 * b:
            raise InputError(source, f"{b:g} m, but the cameras {rig.cameras[0].name} and {rig.cameras[1].name} are "
                                     f"{d:g} m apart (cam_from_rig, which the measurement uses): edit both, or write "
                                     "the rig again with heartcv rig rectified", "baseline_m")


def check_rig_scale(cameras, source) -> None:
    """Raise :class:`InputError` (field ``cam_from_rig``) when two cameras are farther apart than
    :data:`MAX_BASELINE_M` (the rig was most likely written in millimetres), or when no two are more than
    :data:`MIN_BASELINE_M` apart (no baseline: poses missing, e.g. every ``cam_from_rig`` the identity)."""
    centres = np.array([c.centre for c in cameras])
    d = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    i, j = np.unravel_index(int(np.argmax(d)), d.shape)
    if len(cameras) >= 2 and d[i, j] < MIN_BASELINE_M:
        raise InputError(source, f"all {len(cameras)} cameras share one centre (at most {d[i, j]:.3g} m apart): no "
                                 "baseline to triangulate from; the cameras' poses are missing or wrong",
                         "cam_from_rig")
    if d[i, j] > MAX_BASELINE_M:
        raise InputError(source, f"cameras {cameras[i].name} and {cameras[j].name} are {d[i, j]:g} m apart (more "
                                 f"than {MAX_BASELINE_M:g} m): is the rig in millimetres? heartcv rig files are in "
                                 f"metres (a stereo endoscope's baseline is about 0.005 m)", "cam_from_rig")


def track_lengths(seen) -> tuple[np.ndarray, np.ndarray]:
    """Per track seen at least once: its span (frames from its first to its last frame seen, inclusive) and the
    number of frames it was seen in."""
    seen = np.asarray(seen, bool)
    ever = seen.any(axis=0)
    if not ever.any():
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    first = np.argmax(seen, axis=0)
    last = seen.shape[0] - 1 - np.argmax(seen[::-1], axis=0)
    return (last - first + 1)[ever], seen.sum(axis=0)[ever]


def measurement_summary(res, times, wall_s: float, decode_s: float) -> dict:
    """The numbers of a run's summary (docs/cli.md §10, ``--json``): frames, tracks, points per frame, track
    lengths, reprojection RMS, sigma, views, rate and timings, region of interest, candidates removed per gate."""
    seen = res.seen
    per_frame = seen.sum(axis=1)
    span, count = track_lengths(seen)
    r = res.reprojection_rms[seen]
    n = int(len(times))
    return {"frames": n, "tracks": int(res.point_ids.size), "points_mean": float(per_frame.mean()),
            "points_min": int(per_frame.min()), "points_max": int(per_frame.max()),
            "reprojection_rms_px": float(np.sqrt(np.mean(r ** 2))) if r.size else None,
            "sigma_px": res.sigma_px, "sigma_estimated": res.sigma_estimated,
            "views_mean": float(res.views[seen].mean()) if seen.any() else 0.0,
            "frames_per_s": n / wall_s if wall_s > 0 else None, "wall_s": wall_s,
            "timings_s": {"decode": decode_s, **res.timings}, "roi_px": int(res.roi.sum()),
            "track_length_median_frames": float(np.median(span)) if span.size else 0.0,
            "track_seen_median_frames": float(np.median(count)) if count.size else 0.0,
            "rejected": {g: int(n) for g, n in getattr(res, "rejected", {}).items()}}


def _num(v) -> str:
    return repr(float(v))


def measurement_csv_lines(mset, uv, names) -> list[str]:
    """The long-form CSV of a measurement (docs/cli.md §10, ``--csv``): a comment line, the header row, then one
    row per (frame, seen point): frame, time, id, position, covariance (6 entries), views, reprojection RMS and the
    pixel position in each camera (empty where that view was not used).

    Parameters
    ----------
    mset : heartcv.tracker.measurements.MeasurementSet
    uv : ndarray (K, P, C, 2)
        Pixel positions of the views used (NaN: not used).
    names : sequence of str
        Camera names.
    """
    cols = ["frame", "time_s", "point_id", "x_m", "y_m", "z_m", "cxx_m2", "cxy_m2", "cxz_m2", "cyy_m2",
            "cyz_m2", "czz_m2", "views", "reprojection_rms_px"]
    cols += [f"{axis}_{n}_px" for n in names for axis in ("u", "v")]
    lines = [f"# {CSV_HEADER}", ",".join(cols)]
    ks, ps = np.nonzero(mset.seen)
    X = mset.positions[ks, ps]
    cov = mset.covariances[ks, ps][:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]]
    pix = np.asarray(uv)[ks, ps].reshape(len(ks), -1)
    for i, (k, p) in enumerate(zip(ks, ps, strict=True)):
        row = [str(k), _num(mset.times[k]), str(int(mset.point_ids[p])), *map(_num, X[i]), *map(_num, cov[i]),
               str(int(mset.views[k, p])), _num(mset.reprojection_rms[k, p])]
        row += ["" if not np.isfinite(v) else _num(v) for v in pix[i]]
        lines.append(",".join(row))
    return lines


def frame_spans(frames, most: int = 8) -> str:
    """Frame indices as runs of consecutive ones, e.g. ``"4, 100-102, 150"``; after ``most`` runs ``", ... (N more
    runs)"``."""
    ks = sorted({int(k) for k in frames})
    runs = []
    for k in ks:
        if runs and k == runs[-1][1] + 1:
            runs[-1][1] = k
        else:
            runs.append([k, k])
    text = ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in runs[:most])
    return text + (f", ... ({len(runs) - most} more runs)" if len(runs) > most else "")

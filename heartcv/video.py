"""Video input: quiet decoding, every video checked before any processing, and per-camera frame times.

A sequence or calibration folder may hold one video file per camera. Reading them goes through this module:

- :func:`silence_ffmpeg` keeps FFmpeg's own messages (one line per damaged packet: thousands on a corrupt file)
  off the terminal unless the user asked for them; ``cli/main.py`` calls it once at start-up;
- :func:`check_videos` (and :func:`probe_video` for one file) decodes every frame of every video once, without
  keeping the frames, *before* any processing: a file that cannot be opened, holds no frame, decodes fewer frames
  than its container declares (truncated or corrupt), changes its frame size or has timestamps that go backwards
  raises :class:`~heartcv.tracker.files.InputError` naming the file (exit 2), and never after the other cameras
  were processed;
- :func:`iter_frames` and :class:`VideoReader` read the frames for the processing pass (frame ``k`` is the
  ``k``-th decoded frame, counted exactly as :func:`probe_video` counts them);
- :func:`read_camera_times` reads a per-camera ``timestamps.csv`` (one row per camera per frame, as written by
  multi-camera recorders such as caliscope).

Videos are opened with OpenCV's FFmpeg backend only (``cv2.CAP_FFMPEG``, when this OpenCV build has it): the
other backends OpenCV would try on failure (its own MJPEG/AVI reader, image sequences, V4L2) print their own
complaints about a file that is not theirs. docs/cli.md §8.2 has the experiments behind these choices.
"""

from __future__ import annotations

from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
import os
from pathlib import Path
import re
import sys
import threading

import numpy as np

from .tracker.files import InputError, read_csv_table

__all__ = ["VideoInfo", "silence_ffmpeg", "open_video", "probe_video", "check_videos", "iter_frames",
           "VideoReader", "read_camera_times", "camera_number"]

#: av_log level that prints nothing (libavutil/log.h: AV_LOG_QUIET)
AV_LOG_QUIET = -8
#: A video may decode this many frames fewer than its container declares (the count is often an estimate from
#: the duration and the frame rate): at most ``max(TRUNCATION_FRAMES, TRUNCATION_FRACTION * declared)``
TRUNCATION_FRAMES = 1
TRUNCATION_FRACTION = 0.01
#: Declared frame counts beyond this are taken as "unknown" (FFmpeg reports INT64_MIN for raw streams)
_MAX_DECLARED = 10**9
#: After this many failed grabs in a row the stream is taken to have ended (truncated files fail at every grab)
_MAX_FAILED_GRABS = 256


# =====================================================================================================================
# FFmpeg's logging
# =====================================================================================================================
def silence_ffmpeg(verbose: bool) -> None:
    """Silence FFmpeg's and OpenCV's video-decoding chatter on stderr, unless ``verbose``.

    OpenCV's FFmpeg backend reads the environment variable ``OPENCV_FFMPEG_LOGLEVEL`` (an ``av_log`` level) once,
    when the backend is first initialised in the process (the first ``VideoCapture`` or ``VideoWriter`` it opens);
    without it FFmpeg prints every error (e.g. ``[mpeg4 @ 0x…] header damaged``) to stderr. This sets it to
    ``AV_LOG_QUIET`` (-8), and OpenCV's own log level (``OPENCV_LOG_LEVEL``, e.g. ``[ WARN:0@0.02] … can't be used
    to capture by name``) to ``ERROR``. Call it before the first video is opened. Variables the user has set
    are left alone, as is ``OPENCV_VIDEOIO_DEBUG`` (a debugging switch only the user turns on).

    With ``verbose`` nothing is set, so FFmpeg keeps printing its errors to stderr: setting
    ``OPENCV_FFMPEG_LOGLEVEL`` to any other level would make OpenCV install its own log callback, which prints to
    *stdout* (``[OPENCV:FFMPEG:16] …``), the stream that carries ``--json``.

    Parameters
    ----------
    verbose : bool
        Keep FFmpeg's and OpenCV's messages (``heartcv -v``).
    """
    if verbose:
        return
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", str(AV_LOG_QUIET))
    if "OPENCV_LOG_LEVEL" not in os.environ:
        os.environ["OPENCV_LOG_LEVEL"] = "ERROR"
        cv2 = sys.modules.get("cv2")
        if cv2 is not None:  # OpenCV reads OPENCV_LOG_LEVEL when it is imported: too late for the variable
            cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)


# =====================================================================================================================
# Opening and probing
# =====================================================================================================================
@dataclass(frozen=True)
class VideoInfo:
    """What :func:`probe_video` found by decoding a whole video.

    Attributes
    ----------
    path : Path
    n_frames : int                  frames that decode (frame ``k`` of :func:`iter_frames` is the ``k``-th of them)
    fps : float or None             the container's frame rate (None when it states none)
    width, height : int             frame size in pixels (of the decoded frames, rotation metadata applied)
    times_s : ndarray of shape (n_frames,) or None
                                    each frame's presentation time in seconds from the stream's start
                                    (``CAP_PROP_POS_MSEC``), strictly increasing; None when the container gives
                                    none (every time zero)
    container_frames : int or None  the frame count the container declares (``CAP_PROP_FRAME_COUNT``; None when
                                    unknown)
    """

    path: Path
    n_frames: int
    fps: float | None
    width: int
    height: int
    times_s: np.ndarray | None
    container_frames: int | None

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels."""
        return self.width, self.height


def _check_file(path: Path) -> None:
    if not path.exists():
        raise InputError(path, "no such file")
    if not path.is_file():
        raise InputError(path, "not a file")
    if not os.access(path, os.R_OK):
        raise InputError(path, "cannot read the file (permissions)")


def open_video(path):
    """An opened ``cv2.VideoCapture`` of the video file ``path`` (FFmpeg backend where this OpenCV has it).

    Raises
    ------
    InputError
        No such file, not a file, unreadable, or OpenCV cannot open it (not a video, an unsupported codec or
        container, a corrupt or truncated header).
    """
    import cv2

    path = Path(path)
    _check_file(path)
    api = cv2.CAP_FFMPEG if cv2.videoio_registry.hasBackend(cv2.CAP_FFMPEG) else cv2.CAP_ANY
    cap = cv2.VideoCapture(str(path), api)
    if not cap.isOpened():
        cap.release()
        raise InputError(path, "cannot open the video (not a video, an unsupported format, or a corrupt or "
                               "truncated header)")
    return cap


def _declared_frames(cap) -> int | None:
    import cv2

    n = cap.get(cv2.CAP_PROP_FRAME_COUNT)
    return int(n) if np.isfinite(n) and 0 < n < _MAX_DECLARED else None


class _Cancelled(Exception):
    """A probe stopped because another video already failed (never leaves this module)."""


def probe_video(path) -> VideoInfo:
    """Open ``path`` and decode every frame once (``grab``, nothing kept): its frame count, size, rate and times.

    Parameters
    ----------
    path : path
        A video file.

    Returns
    -------
    VideoInfo

    Raises
    ------
    InputError
        Naming the file: it cannot be opened (:func:`open_video`); no frame decodes; fewer frames decode than
        the container declares, by more than ``max(1, 1 %)`` of them, or a frame inside the stream does not
        decode while later ones do ("truncated or corrupt: N of M frames decode"); the frame size changes; the
        frame times go backwards or repeat.

    Notes
    -----
    A frame that does not decode in the middle of a stream is an error even when the count is within the
    tolerance: skipping it would shift every later frame against the other cameras' frames of the same index.
    OpenCV's FFmpeg backend converts every frame to the stream's declared size, so a size change inside the
    stream does not show through it; the check reads the size OpenCV reports for each frame.
    """
    return _probe(Path(path), None)


def _probe(path: Path, stop: threading.Event | None) -> VideoInfo:
    import cv2

    cap = open_video(path)
    try:
        declared = _declared_frames(cap)
        fps = cap.get(cv2.CAP_PROP_FPS)
        fps = float(fps) if np.isfinite(fps) and fps > 0 else None
        times, size, reported, n = [], None, None, 0
        first_failed, failed, in_a_row = None, 0, 0
        while True:
            if stop is not None and stop.is_set():
                raise _Cancelled
            if not cap.grab():
                # the end, or a damaged frame (the next may decode again): try on up to the declared count
                first_failed = n if first_failed is None else first_failed
                failed, in_a_row = failed + 1, in_a_row + 1
                if declared is None or n + failed >= declared or in_a_row >= _MAX_FAILED_GRABS:
                    break
                continue
            in_a_row = 0
            if size is None:  # the first frame's true size (rotation metadata applied)
                ok, img = cap.retrieve()
                if not ok or img is None:
                    raise InputError(path, "frame 0 decodes but cannot be converted to an image")
                size, reported = (img.shape[1], img.shape[0]), _reported_size(cap)
            elif _reported_size(cap) != reported:
                w, h = _reported_size(cap)
                raise InputError(path, f"the frame size changes at frame {n}: {w}x{h} px after "
                                       f"{reported[0]}x{reported[1]} px")
            times.append(cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0)
            n += 1
    finally:
        cap.release()
    if n == 0:
        raise InputError(path, "no frame decodes" + (f" ({declared} declared)" if declared else "")
                         + ": corrupt, empty or an unsupported codec")
    short = declared is not None and declared - n > max(TRUNCATION_FRAMES, int(TRUNCATION_FRACTION * declared))
    inside = first_failed is not None and first_failed < n
    if short or inside:
        where = f" (frame {first_failed} is the first that does not, later ones do)" if inside else ""
        raise InputError(path, f"truncated or corrupt: {n} of {declared if declared else '?'} frames decode{where}")
    return VideoInfo(path, n, fps, size[0], size[1], _frame_times(path, times), declared)


def _reported_size(cap) -> tuple[int, int]:
    import cv2

    return int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))


def _frame_times(path, times) -> np.ndarray | None:
    """The frames' times (s), None when the container gives none; InputError when they do not increase."""
    t = np.asarray(times, float)
    if not np.isfinite(t).all() or (t.size > 1 and not t.any()):
        return None
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        k = int(bad[0]) + 1
        raise InputError(path, f"frame timestamps do not increase: frame {k} at {t[k]:.6f} s after frame {k - 1} "
                               f"at {t[k - 1]:.6f} s")
    return t


def check_videos(paths, progress=None, *, workers: int | None = None) -> list[VideoInfo]:
    """Probe every video (:func:`probe_video`, in parallel threads) before any of them is processed.

    Parameters
    ----------
    paths : sequence of path
        One video per camera.
    progress : callable, optional
        Called as ``progress(info)`` with each :class:`VideoInfo` as its probe completes (in the calling thread).
    workers : int, optional
        Threads; default ``min(len(paths), 4)``.

    Returns
    -------
    list of VideoInfo
        In the order of ``paths``.

    Raises
    ------
    InputError
        The first problem found, naming its file; the probes still running are stopped.
    """
    paths = [Path(p) for p in paths]
    if not paths:
        return []
    stop = threading.Event()
    infos, errors = [None] * len(paths), {}
    workers = max(1, min(len(paths), 4 if workers is None else int(workers)))
    with ThreadPoolExecutor(workers) as pool:
        futures = {pool.submit(_probe, p, stop): i for i, p in enumerate(paths)}
        try:
            for fut in as_completed(futures):
                i = futures[fut]
                try:
                    infos[i] = fut.result()
                except _Cancelled:
                    continue
                except InputError as exc:
                    errors[i] = exc
                    stop.set()
                    continue
                if progress is not None and not errors:
                    progress(infos[i])
        finally:
            stop.set()  # whatever ends the loop (an error, a bug, Ctrl-C) stops the probes still running
    if errors:
        raise errors[min(errors)]
    return infos


# =====================================================================================================================
# Reading frames
# =====================================================================================================================
class VideoReader:
    """Frame ``k`` of one video on request, reading forward (``grab``): frame ``k`` is the ``k``-th decoded frame,
    as :func:`probe_video` counts them (it refuses videos in which a frame fails to decode inside the stream, so
    the first failure is the end). Going back reopens the file. Use as a context manager, or call :meth:`close`.

    Parameters
    ----------
    path : path
    size : (width, height), optional
        The size every frame must have (e.g. :attr:`VideoInfo.size`).
    """

    def __init__(self, path, size=None):
        self.path = Path(path)
        self.size = None if size is None else (int(size[0]), int(size[1]))
        self._cap = None
        self._next = 0  # index of the frame the next grab returns

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def read(self, k: int, gray: bool = False):
        """Frame ``k`` (8-bit BGR, or gray with ``gray``), or None when it does not decode.

        Raises
        ------
        InputError
            The video cannot be opened, or frame ``k`` does not have the expected size.
        """
        import cv2

        k = int(k)
        if self._cap is None or k < self._next:
            self.close()
            self._cap, self._next = open_video(self.path), 0
        while self._next < k:  # frames in between are decoded, not converted
            if not self._cap.grab():
                return None
            self._next += 1
        ok = self._cap.grab()
        self._next += 1
        img = self._cap.retrieve()[1] if ok else None
        if img is None:
            return None
        if self.size is not None and (img.shape[1], img.shape[0]) != self.size:
            raise InputError(self.path, f"frame {k} is {img.shape[1]}x{img.shape[0]} px, {self.size[0]}x"
                                        f"{self.size[1]} px expected (the frame size changes inside the video)")
        if gray and img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        return img


def iter_frames(path, every: int = 1, *, gray: bool = False, size=None):
    """Yield ``(k, frame)`` for the frames ``k = 0, every, 2·every, …`` of a video (8-bit BGR, or gray).

    Frames in between are decoded but not converted (``grab``). Run :func:`check_videos` first: this stops at the
    end of the stream without judging whether it ended early.

    Parameters
    ----------
    path : path
    every : int
        Use every ``every``-th frame (>= 1).
    gray : bool
        Convert to 8-bit gray.
    size : (width, height), optional
        The size every frame must have; default the first frame's.

    Raises
    ------
    InputError
        The video cannot be opened, or a frame's size differs.
    """
    every = int(every)
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    with VideoReader(path, size) as reader:
        k = 0
        while True:
            img = reader.read(k, gray)
            if img is None:
                return
            if reader.size is None:
                reader.size = (img.shape[1], img.shape[0])
            yield k, img
            k += every


# =====================================================================================================================
# Per-camera frame times (timestamps.csv of multi-camera recorders)
# =====================================================================================================================
_ORDER_COLUMNS = ("sync_index", "frame_index")
_CAMERA_COLUMNS = ("cam_id", "camera")
_TIME_COLUMNS = ("frame_time", "time_s")


def camera_number(name: str) -> int | None:
    """The trailing integer of a camera name (``cam_0`` -> 0, ``cam3`` -> 3, ``left`` -> None)."""
    m = re.search(r"(\d+)$", str(name))
    return int(m.group(1)) if m else None


def _pick(path, columns, choices, what):
    found = [c for c in choices if c in columns]
    if len(found) != 1:
        field = "column " + " or ".join(repr(c) for c in choices)
        reason = (f"missing: the {what} column expected; the header has {', '.join(columns)}" if not found
                  else f"both present; one {what} column expected")
        raise InputError(path, reason, field)
    return found[0]


def _match_cameras(path, values, col, camera_names):
    """Per row, the index of the camera of ``camera_names`` it belongs to (-1: none of them)."""
    keys = []
    for name in camera_names:
        keys.append({str(name), *(() if camera_number(name) is None else (camera_number(name),))})
    by_key = {}
    for c, ks in enumerate(keys):
        for key in ks:
            if key in by_key and by_key[key] != c:
                raise InputError(path, f"cameras {camera_names[by_key[key]]!r} and {camera_names[c]!r} both match "
                                       f"{col} {key!r}; rename one", f"column {col!r}")
            by_key[key] = c
    out = np.full(len(values), -1, int)
    for r, v in enumerate(values):
        if isinstance(v, str):
            key = v if v in by_key else (camera_number(v) if v.isdigit() else None)
        else:
            if v != int(v):
                raise InputError(path, f"integer camera ids expected, got {v!r} in row {r + 1}", f"column {col!r}")
            key = int(v)
        out[r] = by_key.get(key, -1)
    return out


def read_camera_times(path, camera_names, frame_counts) -> dict[str, np.ndarray]:
    """Each camera's frame times (s) from a multi-camera ``timestamps.csv``.

    The table (comma-separated, a header row, ``#`` comments) has one row per camera per frame, with columns

    - ``sync_index`` (or ``frame_index``): the order of the rows; frame ``k`` of a camera's video is that camera's
      ``k``-th row in this order (caliscope's files start at any index: 35 in its sample session);
    - ``cam_id`` (integers) or ``camera`` (names): the camera. A row belongs to the camera whose name equals the
      value, or whose name ends in that integer (``cam_0``, ``cam0`` and ``0`` match 0; ``cam3`` matches 3); rows
      of other cameras are ignored;
    - ``frame_time`` (or ``time_s``): the frame's time in seconds, on one clock shared by the cameras (returned
      as written, not shifted to zero).

    Parameters
    ----------
    path : path
    camera_names : sequence of str
        The sequence's cameras.
    frame_counts : sequence of int, or mapping name -> int
        Each camera's frame count (e.g. :attr:`VideoInfo.n_frames`).

    Returns
    -------
    dict
        Camera name -> ndarray of shape (frame count,): strictly increasing times in seconds.

    Raises
    ------
    InputError
        Naming the file and the column or row: not a valid table (:func:`heartcv.tracker.files.read_csv_table`),
        a column missing, non-numeric, NaN or infinite cells, an order index repeated within a camera, a camera
        of the sequence absent, a camera's row count different from its frame count, times that do not strictly
        increase within a camera.
    """
    names = [str(n) for n in camera_names]
    counts = ([int(frame_counts[n]) for n in names] if isinstance(frame_counts, Mapping)
              else [int(c) for c in frame_counts])
    if len(counts) != len(names):
        raise ValueError(f"{len(counts)} frame counts for {len(names)} cameras")
    table, _ = read_csv_table(path, ("camera",), "timestamps table")
    order_col = _pick(path, list(table), _ORDER_COLUMNS, "frame order")
    cam_col = _pick(path, list(table), _CAMERA_COLUMNS, "camera")
    time_col = _pick(path, list(table), _TIME_COLUMNS, "frame time")
    order, times = table[order_col], table[time_col]
    which = _match_cameras(path, table[cam_col], cam_col, names)
    out = {}
    for c, (name, count) in enumerate(zip(names, counts)):
        rows = np.flatnonzero(which == c)
        if rows.size == 0:
            raise InputError(path, f"no rows for camera {name!r} (matched by name or by its number "
                                   f"{camera_number(name)})", f"column {cam_col!r}")
        rows = rows[np.argsort(order[rows], kind="stable")]
        dup = np.flatnonzero(np.diff(order[rows]) == 0)
        if dup.size:
            r = rows[dup[0] + 1]
            raise InputError(path, f"{order_col} {order[r]:g} repeated for camera {name!r} (row {r + 1})",
                             f"column {order_col!r}")
        if rows.size != count:
            raise InputError(path, f"{rows.size} rows for camera {name!r}, whose video has {count} frames",
                             f"column {cam_col!r}")
        t = times[rows]
        bad = np.flatnonzero(np.diff(t) <= 0)
        if bad.size:
            (r0, r1), (t0, t1) = rows[bad[0]:bad[0] + 2], t[bad[0]:bad[0] + 2].tolist()
            raise InputError(path, f"camera {name!r}: times must strictly increase in {order_col} order, "
                                   f"row {r1 + 1} has {t1!r} after row {r0 + 1} with {t0!r}", f"column {time_col!r}")
        out[name] = t.copy()
    return out

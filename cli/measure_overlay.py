"""``heartcv measure --overlay DIR``: something to look at — the tracks drawn on the images, and their statistics.

:func:`write_overlay` writes, with :func:`heartcv.tracker.files.atomic_folder` (producer ``heartcv measure
--overlay``: an existing folder is replaced only if it is empty or an earlier overlay wrote it, see
:func:`check_overlay_dir`), a folder of

- ``frames/<frame name>.png``: per instant, all cameras side by side, each with the recent trail of every track
  (of a stable subset of them when there are many: ``max_tracks``) and a dot where it is now, the reference camera
  with its region of interest outlined (:func:`heartcv.overlay.overlay_frame`); or, with ``video=True``, one
  ``overlay.mp4`` (MPEG-4 part 2, ``mp4v``) of the same pictures;
- ``tracks.png``: the points seen per frame (minimum and mean marked) and the histogram of the track spans (first
  to last frame seen; median marked) (:func:`tracks_figure`).

Every file is written atomically and the folder appears only when complete, so a crash never leaves a
half-written picture behind.
"""

from __future__ import annotations

from contextlib import nullcontext, suppress
from pathlib import Path

import numpy as np

from .options import StageFailed
from .plots import save_png

__all__ = ["PRODUCER", "LABEL", "FOURCC", "check_overlay_dir", "tracks_figure", "write_overlay"]

PRODUCER = "heartcv measure --overlay"
LABEL = "--overlay"
FOURCC = "mp4v"


def _empty_folder(folder: Path) -> bool:
    try:
        return folder.is_dir() and not folder.is_symlink() and next(folder.iterdir(), None) is None
    except OSError:
        return False


def check_overlay_dir(folder, label: str = LABEL) -> None:
    """Refuse, before any work, an overlay folder that exists, is not empty and was not written by an earlier
    overlay (it holds no heartcv manifest naming :data:`PRODUCER`): a person's folder, or another stage's, is never
    replaced. A missing or empty folder, or an earlier overlay, may be (re)written.

    Raises
    ------
    heartcv.tracker.files.InputError
        Naming the folder and ``label`` (the command line's exit 2).
    """
    from heartcv.tracker.files import check_output_folder

    folder = Path(folder)
    if not _empty_folder(folder):
        check_output_folder(folder, PRODUCER, label)


def tracks_figure(result, *, title: str | None = None):
    """Two panels: points seen per frame (minimum and mean marked) and the histogram of track spans (median marked).

    Parameters
    ----------
    result : heartcv.measure.MeasureResult
        Only ``frames`` and ``seen`` are read.
    title : str, optional

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib.figure import Figure

    from heartcv.overlay import track_lengths

    seen = result.seen
    frames = np.asarray(result.frames)
    per_frame = seen.sum(axis=1)
    span, _ = track_lengths(seen)
    span = span[span > 0]
    fig = Figure(figsize=(10.0, 3.8), layout="constrained")
    ax, hx = fig.subplots(1, 2)

    ax.plot(frames, per_frame, color="#1f77b4", lw=1.6, label="points seen")
    if per_frame.size:
        mean, i_min = float(per_frame.mean()), int(np.argmin(per_frame))
        ax.axhline(mean, color="0.3", ls="--", lw=1.2, label=f"mean {mean:.1f}")
        ax.plot(frames[i_min], per_frame[i_min], "v", color="#d62728", ms=8,
                label=f"min {int(per_frame[i_min])} (frame {int(frames[i_min])})")
        ax.set_xlim(frames[0], max(frames[-1], frames[0] + 1))
    ax.set_ylim(0, max(1, int(per_frame.max(initial=0))) * 1.08)
    ax.set_xlabel("frame index")
    ax.set_ylabel("points seen [count]")
    ax.set_title(f"Points seen per frame ({len(frames)} frames)", fontsize=10)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="best")

    if span.size:
        top = int(span.max())
        step = max(1, int(np.ceil(top / 60)))
        edges = np.arange(0.5, top + step + 0.5, step)
        hx.hist(span, bins=edges, color="#2ca02c", alpha=0.85, label="tracks")
        med = float(np.median(span))
        hx.axvline(med, color="#d62728", lw=1.6, label=f"median {med:g} frames")
        hx.set_xlim(0, top + step)
        hx.legend(fontsize=8, loc="best")
    else:
        hx.text(0.5, 0.5, "no track was seen", ha="center", va="center", transform=hx.transAxes)
    hx.set_xlabel("track span: first to last frame seen [frames]")
    hx.set_ylabel("tracks [count]")
    hx.set_title(f"Track lengths ({span.size} tracks)", fontsize=10)
    hx.grid(True, alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=11)
    return fig


def _fit(image, shape) -> np.ndarray:
    """``image`` cropped or padded with black (bottom, right) to ``shape`` (H, W, 3): a video's frames all have one
    size."""
    if image.shape == shape:
        return image
    out = np.zeros(shape, np.uint8)
    h, w = min(shape[0], image.shape[0]), min(shape[1], image.shape[1])
    out[:h, :w] = image[:h, :w]
    return out


def _video_writer(path, fps: float, size):
    import cv2

    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*FOURCC), float(fps), tuple(int(v) for v in size))
    if not writer.isOpened():
        raise StageFailed(f"{LABEL}: OpenCV {cv2.__version__} cannot write {FOURCC} MP4 video here (its build has "
                          "no such encoder); write PNG frames instead (without the video option)")
    return writer


def write_overlay(folder, reader, result, camera_names, frame_names, *, ref: int = 0, fps: float = 25.0,
                  video: bool = False, trail: int = 15, max_tracks: int | None = None, progress=None,
                  dpi: int = 110) -> dict:
    """Write the overlay folder (module docstring) atomically.

    Parameters
    ----------
    folder : path
        The overlay folder; an existing one is replaced only if it is empty or an earlier overlay wrote it
        (:func:`check_overlay_dir`, checked again here before any image is read).
    reader : iterable of (int, list, list)
        ``(k, images, problems)`` for exactly the instants of ``result.frames``, in order: one 8-bit gray or BGR
        image per camera, None where missing (e.g. a :class:`heartcv.io.FrameReader` with ``mode="color"`` and
        ``frames=result.frames``, entered). ``problems`` are not reported again here.
    result : heartcv.measure.MeasureResult
    camera_names : sequence of str
        One per camera of the result (written on the tiles).
    frame_names : sequence of str
        The sequence's instant names (:attr:`heartcv.io.FrameSource.frame_names`), indexed by frame index:
        instant ``k`` is written as ``frames/<frame_names[k]>.png``.
    ref : int
        Reference camera (the region of interest is outlined on it).
    fps : float
        Frame rate of the video, Hz.
    video : bool
        Write one ``overlay.mp4`` instead of the PNG frames.
    trail : int
        Instants of history drawn behind each point.
    max_tracks : int, optional
        Draw about this many tracks at most (:func:`heartcv.overlay.overlay_frame`); default one per 20 x 20 px of
        the reference camera's image (e.g. 259 at 360 x 288, 5184 at 1920 x 1080): a dense result stays readable.
    progress : callable, optional
        ``progress(done, total)`` after each instant.
    dpi : int
        Resolution of ``tracks.png``.

    Returns
    -------
    dict
        ``folder`` (Path), ``files`` (paths written, relative to the folder, sorted), ``frames`` (instants drawn),
        ``video`` (Path or None), ``tracks_png`` (Path), ``tracks`` (tracks seen at least once),
        ``track_span_median_frames`` (None without tracks), ``points_min``, ``points_mean``.

    Raises
    ------
    heartcv.tracker.files.InputError
        The folder exists, is not empty and an earlier overlay did not write it; or it cannot be written.
    StageFailed
        ``video`` and OpenCV cannot write ``mp4v`` video.
    ValueError
        ``reader`` does not give exactly the instants of ``result.frames``; a result without frames; names, ``ref``
        and result disagree.
    """
    import math

    from heartcv.io import write_image
    from heartcv.overlay import overlay_frame, track_lengths
    from heartcv.tracker.files import atomic_folder, atomic_path

    folder = Path(folder)
    check_overlay_dir(folder)
    K, P, C = result.uv.shape[:3]
    if K == 0:
        raise ValueError("result: no frames to draw")
    if not 0 <= ref < C:
        raise ValueError(f"ref: a camera 0..{C - 1} expected, got {ref}")
    if len(camera_names) != C:
        raise ValueError(f"camera_names: {C} expected (one per camera of the result), got {len(camera_names)}")
    if video and not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps: a positive frame rate expected, got {fps}")
    if max_tracks is None:
        max_tracks = max(1, result.roi.size // 400)
    index = {int(f): i for i, f in enumerate(result.frames)}
    bad = [int(f) for f in result.frames if not 0 <= int(f) < len(frame_names)]
    if bad:
        raise ValueError(f"frame_names: {len(frame_names)} names, but the result has frame {bad[0]}")
    seen = result.seen
    per_frame = seen.sum(axis=1)
    span, _ = track_lengths(seen)
    span = span[span > 0]
    summary = {"tracks": int(span.size),
               "track_span_median_frames": float(np.median(span)) if span.size else None,
               "points_min": int(per_frame.min()) if K else 0,
               "points_mean": float(per_frame.mean()) if K else 0.0}
    manifest = {"frames": K, "video": bool(video), "trail": int(trail), "max_tracks": int(max_tracks),
                "ref_camera": str(camera_names[ref]),
                "files": ["tracks.png", "overlay.mp4" if video else "frames/"], **summary}
    if _empty_folder(folder):
        with suppress(OSError):  # an empty folder (made by hand) holds nothing to lose; if it fills meanwhile,
            folder.rmdir()       # atomic_folder refuses it
    files = []
    with atomic_folder(folder, PRODUCER, manifest) as tmp:
        done, shape, writer = [], None, None
        sizes = [None] * C
        try:
            with atomic_path(tmp / "overlay.mp4") if video else nullcontext() as mp4:
                for k, images, _ in reader:
                    if int(k) not in index:
                        raise ValueError(f"reader: frame {k} is not a frame of the result")
                    for c, im in enumerate(images):
                        if im is not None and sizes[c] is None:
                            sizes[c] = (im.shape[1], im.shape[0])
                    known = [s for s in sizes if s is not None]
                    fill = [s or (known[0] if known and c != ref else result.roi.shape[::-1])
                            for c, s in enumerate(sizes)]
                    picture = overlay_frame(images, result, index[int(k)], ref, trail, names=camera_names,
                                            sizes=fill, max_tracks=max_tracks)
                    if video:
                        if writer is None:
                            h, w = picture.shape[:2]
                            shape = (h + h % 2, w + w % 2, 3)  # even sides: what MPEG-4 encoders expect
                            writer = _video_writer(mp4, fps, (shape[1], shape[0]))
                        writer.write(_fit(picture, shape))
                    else:
                        name = f"frames/{frame_names[int(k)]}.png"
                        write_image(tmp / name, picture)
                        files.append(name)
                    done.append(int(k))
                    if progress is not None:
                        progress(len(done), K)
                if writer is not None:
                    writer.release()
                    writer = None
        finally:
            if writer is not None:
                writer.release()
        if done != [int(f) for f in result.frames]:
            raise ValueError(f"reader: the {K} frames of the result expected in order, got {len(done)} "
                             f"({done[:3]}...)")
        if video:
            files.append("overlay.mp4")
        fig = tracks_figure(result, title=f"Tracks over {K} frames ({', '.join(map(str, camera_names))})")
        save_png(fig, tmp / "tracks.png", dpi=dpi)
        files.append("tracks.png")
    return {"folder": folder, "files": sorted(files), "frames": K, "video": folder / "overlay.mp4" if video else None,
            "tracks_png": folder / "tracks.png", **summary}

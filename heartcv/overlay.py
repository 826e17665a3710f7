"""Pictures of a measurement: the tracks of :class:`heartcv.measure.MeasureResult` drawn on the camera images.

Pure functions on arrays (no file is read or written here; ``heartcv measure --overlay DIR`` writes them, see
``cli/measure_overlay.py``):

- :func:`track_lengths`: per track, the span from its first to its last seen frame and the frames it was seen in;
- :func:`track_colors`: a stable, well-spread colour per track id (golden-ratio hue steps);
- :func:`draw_tracks`: one camera image with each track's recent trail (a polyline broken where the track was not
  seen), a dot where it is now, and the region of interest outlined;
- :func:`overlay_frame`: all cameras of one instant side by side, each with its tracks, under a caption band.

Pixel coordinates are OpenCV's (the centre of the top-left pixel is (0, 0)); sub-pixel positions are drawn with
OpenCV's fixed-point ``shift`` (1/16 px).
"""

from __future__ import annotations

import colorsys

import numpy as np

__all__ = ["SHIFT", "ROI_COLOR", "MISSING_GRAY", "track_lengths", "track_colors", "track_subset", "draw_tracks",
           "overlay_frame"]

#: Fractional bits of the fixed-point coordinates given to OpenCV's drawing functions (1/16 px)
SHIFT = 4
#: BGR colour of the region-of-interest outline (neutral light gray)
ROI_COLOR = (200, 200, 200)
#: Gray level of the tile of a camera whose image is missing
MISSING_GRAY = 96
_GOLDEN = (5 ** 0.5 - 1) / 2  # 0.618...: hue step between consecutive ids
_SAMPLE = 2 ** 0.5 - 1        # 0.414...: an independent step for the subset of tracks drawn (not tied to the hue)


def track_lengths(seen) -> tuple[np.ndarray, np.ndarray]:
    """How long each track lived.

    Parameters
    ----------
    seen : array_like of bool, shape (K, P)
        Whether track ``p`` was seen in instant ``k`` (:attr:`heartcv.measure.MeasureResult.seen`).

    Returns
    -------
    span : ndarray of int, shape (P,)
        Instants from the first to the last one the track was seen in, both included (gaps count); 0 for a track
        never seen.
    count : ndarray of int, shape (P,)
        Instants the track was seen in (``count <= span``).
    """
    seen = np.asarray(seen, bool)
    if seen.ndim != 2:
        raise ValueError(f"seen: shape (K, P) expected, got {seen.shape}")
    K = seen.shape[0]
    if K == 0:
        return np.zeros(seen.shape[1], np.int64), np.zeros(seen.shape[1], np.int64)
    count = seen.sum(axis=0).astype(np.int64)
    any_seen = count > 0
    first = np.argmax(seen, axis=0)
    last = K - 1 - np.argmax(seen[::-1], axis=0)
    span = np.where(any_seen, last - first + 1, 0).astype(np.int64)
    return span, count


def track_colors(ids) -> np.ndarray:
    """A colour per track id: hue ``frac(id * 0.618...)`` (the golden-ratio sequence, so consecutive ids get
    far-apart hues and an id keeps its colour in every frame and camera), full saturation and value.

    Parameters
    ----------
    ids : array_like of int, shape (P,)

    Returns
    -------
    ndarray of uint8, shape (P, 3)
        BGR.
    """
    ids = np.asarray(ids, np.int64).reshape(-1)
    hue = np.mod(ids * _GOLDEN, 1.0)
    rgb = np.array([colorsys.hsv_to_rgb(h, 0.9, 1.0) for h in hue]).reshape(-1, 3)
    return np.round(rgb[:, ::-1] * 255).astype(np.uint8)


def track_subset(ids, fraction) -> np.ndarray:
    """A stable pseudo-random subset of the tracks, about ``fraction`` of them: those whose ``frac(id * (sqrt(2) -
    1))`` is below ``fraction`` (the same ids in every frame; independent of the hue of :func:`track_colors`).

    Parameters
    ----------
    ids : array_like of int, shape (P,)
    fraction : float
        In [0, 1]; 1 keeps every track.

    Returns
    -------
    ndarray of bool, shape (P,)
    """
    if not 0 <= fraction <= 1:
        raise ValueError(f"fraction: in [0, 1] expected, got {fraction}")
    ids = np.asarray(ids, np.int64).reshape(-1)
    return np.ones(ids.shape, bool) if fraction >= 1 else np.mod(ids * _SAMPLE, 1.0) < fraction


def _bgr(image) -> np.ndarray:
    import cv2

    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise ValueError(f"image: 8-bit expected, got {image.dtype}")
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if image.ndim == 3 and image.shape[2] == 3:
        return image.copy()
    raise ValueError(f"image: shape (H, W) or (H, W, 3) expected, got {image.shape}")


def _fixed(uv) -> np.ndarray:
    """Fixed-point pixel coordinates for OpenCV's ``shift`` (int32)."""
    return np.round(np.asarray(uv, float) * (1 << SHIFT)).astype(np.int32)


def _runs(ok) -> list[tuple[int, int]]:
    """``[(start, stop)]`` of the runs of True in a 1-D bool array."""
    d = np.diff(np.concatenate([[0], ok.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)))


def draw_tracks(image, uv_trail, seen_now, ids, *, roi=None, radius=None, thickness=1,
                antialias=True) -> np.ndarray:
    """Draw the recent trail and the current position of every track on one camera image.

    Parameters
    ----------
    image : ndarray of uint8, shape (H, W) or (H, W, 3)
        Gray or BGR; not modified.
    uv_trail : array_like, shape (T, P, 2)
        The last ``T`` pixel positions of each of ``P`` tracks in this camera, oldest first (the last row is now);
        NaN where the track was not seen (the trail is broken there: no segment bridges a gap).
    seen_now : array_like of bool, shape (P,)
        Tracks to mark with a filled dot at their current position ``uv_trail[-1]`` (where it is finite).
    ids : array_like of int, shape (P,)
        Track ids: the colour of each track (:func:`track_colors`).
    roi : ndarray of bool, shape (H, W), optional
        Region of interest: its outline (the region's border pixels, 8-connected) is drawn in :data:`ROI_COLOR`,
        under the tracks.
    radius : float, optional
        Dot radius in px; default ``max(2, min(H, W) / 150)``.
    thickness : int
        Line thickness of the trails, px.
    antialias : bool
        Anti-aliased trails and dots (``cv2.LINE_AA``); False draws 8-connected ones, each drawn pixel exactly in
        its track's colour.

    Returns
    -------
    ndarray of uint8, shape (H, W, 3)
        A BGR copy of ``image`` with the drawing.
    """
    import cv2

    out = _bgr(image)
    H, W = out.shape[:2]
    uv_trail = np.asarray(uv_trail, float)
    if uv_trail.ndim != 3 or uv_trail.shape[2] != 2:
        raise ValueError(f"uv_trail: shape (T, P, 2) expected, got {uv_trail.shape}")
    T, P = uv_trail.shape[:2]
    seen_now = np.asarray(seen_now, bool).reshape(-1)
    ids = np.asarray(ids).reshape(-1)
    if seen_now.shape != (P,) or ids.shape != (P,):
        raise ValueError(f"seen_now, ids: shape ({P},) expected, got {seen_now.shape} and {ids.shape}")
    line = cv2.LINE_AA if antialias else cv2.LINE_8
    if roi is not None:
        roi = np.asarray(roi, bool)
        if roi.shape != (H, W):
            raise ValueError(f"roi: shape {(H, W)} expected, got {roi.shape}")
        contours, _ = cv2.findContours(roi.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(out, contours, -1, ROI_COLOR, 1, cv2.LINE_8)  # on the border pixels: nothing to smooth
    colors = [tuple(int(v) for v in c) for c in track_colors(ids)]
    ok = np.isfinite(uv_trail).all(axis=2)                      # (T, P)
    fixed = _fixed(np.where(ok[..., None], uv_trail, 0.0))
    for p in np.flatnonzero(ok.sum(axis=0) >= 2):
        segments = [np.ascontiguousarray(fixed[a:b, p]).reshape(-1, 1, 2) for a, b in _runs(ok[:, p]) if b - a >= 2]
        if segments:
            cv2.polylines(out, segments, False, colors[p], thickness, line, SHIFT)
    r = max(2.0, min(H, W) / 150) if radius is None else float(radius)
    r_fixed = int(round(r * (1 << SHIFT)))
    if T:
        for p in np.flatnonzero(seen_now & ok[-1]):
            cv2.circle(out, tuple(int(v) for v in fixed[-1, p]), r_fixed, colors[p], -1, line, SHIFT)
    return out


def _banner(width, rows, scale) -> np.ndarray:
    """A black band of text rows above the tiles: ``rows`` is a list of ``[(x, text)]``, white text."""
    import cv2

    font, thick = cv2.FONT_HERSHEY_SIMPLEX, max(1, int(round(scale * 2)))
    (_, h), base = cv2.getTextSize("Ag", font, scale, thick)
    pitch = h + base + max(2, int(round(h * 0.3)))
    band = np.zeros((pitch * len(rows) + base, width, 3), np.uint8)
    pad = max(3, int(round(h * 0.5)))
    for r, row in enumerate(rows):
        for x, text in row:
            cv2.putText(band, text, (x + pad, (r + 1) * pitch - base), font, scale, (255, 255, 255), thick,
                        cv2.LINE_AA)
    return band


def overlay_frame(images, result, k, ref=0, trail=15, *, names=None, sizes=None,
                  max_tracks=None) -> np.ndarray:
    """All cameras of one instant side by side, each with its tracks (:func:`draw_tracks`), under a caption band.

    Parameters
    ----------
    images : sequence of (ndarray of uint8 or None), one per camera
        Gray or BGR images of instant ``k``; None draws that camera's tile in :data:`MISSING_GRAY`.
    result : heartcv.measure.MeasureResult
        Only ``frames``, ``point_ids``, ``positions`` (through ``seen``), ``uv`` and ``roi`` are read.
    k : int
        The instant: an index into ``result.frames`` (not the frame index itself).
    ref : int
        Reference camera: its tile also shows the outline of ``result.roi``.
    trail : int
        Instants of history drawn behind each point (the current one included).
    names : sequence of str, optional
        Camera names, written above each tile (default ``camera <c>``).
    sizes : sequence of (width, height), optional
        Per camera, the size of its tile when its image is missing; default the reference camera's region of
        interest size for it and the first given image's size otherwise.
    max_tracks : int, optional
        Draw about this many tracks at most (a dense result has thousands): the stable subset
        :func:`track_subset` with ``fraction = max_tracks / (most points seen in one instant)``, stated in the
        caption; default all.

    Returns
    -------
    ndarray of uint8, shape (B + max H, sum W, 3)
        BGR: a black band of ``B`` rows of text on top (``frame <frame index>: <n> points seen``, then the camera
        names, each above its tile), the tiles below it side by side, padded with black at the bottom where their
        heights differ.
    """
    uv = result.uv
    K, P, C = uv.shape[:3]
    if len(images) != C:
        raise ValueError(f"images: {C} expected (one per camera of the result), got {len(images)}")
    if not 0 <= k < K:
        raise ValueError(f"k: an instant 0..{K - 1} expected, got {k}")
    if not 0 <= ref < C:
        raise ValueError(f"ref: a camera 0..{C - 1} expected, got {ref}")
    if trail < 1:
        raise ValueError(f"trail: at least 1 expected, got {trail}")
    if names is not None and len(names) != C:
        raise ValueError(f"names: {C} expected, got {len(names)}")
    seen = np.isfinite(result.positions[k]).all(axis=1)         # result.seen[k], without the other instants
    lo = max(0, k - trail + 1)
    keep, fraction = np.ones(P, bool), 1.0
    if max_tracks is not None:
        most = int(np.isfinite(result.positions[..., 0]).sum(axis=1).max(initial=0))
        fraction = min(1.0, max(0, int(max_tracks)) / most) if most else 1.0
        keep = track_subset(result.point_ids, fraction)
    first = next((im for im in images if im is not None), None)
    tiles = []
    for c, im in enumerate(images):
        if im is None:
            if sizes is not None:
                w, h = sizes[c]
            elif c == ref or first is None:
                h, w = result.roi.shape
            else:
                h, w = first.shape[:2]
            im = np.full((h, w), MISSING_GRAY, np.uint8)
        window = uv[lo:k + 1, :, c]                              # (T, P, 2)
        shown = keep & np.isfinite(window).all(axis=2).any(axis=0)  # tracks with a view in the window
        now = seen & np.isfinite(uv[k, :, c]).all(axis=1)
        tile = draw_tracks(im, window[:, shown], now[shown], result.point_ids[shown],
                           roi=result.roi if c == ref and result.roi.shape == im.shape[:2] else None)
        tiles.append(tile)
    H = max(t.shape[0] for t in tiles)
    picture = np.concatenate([np.pad(t, ((0, H - t.shape[0]), (0, 0), (0, 0))) for t in tiles], axis=1)
    drawn = f", {int((seen & keep).sum())} drawn" if fraction < 1 else ""
    head = [(0, f"frame {int(result.frames[k])}: {int(seen.sum())} points seen{drawn}; trails of {trail} frames")]
    x = np.concatenate([[0], np.cumsum([t.shape[1] for t in tiles])])
    label = [(str(names[c]) if names is not None else f"camera {c}") + (" (reference, ROI outlined)" if c == ref
             else "") + (": missing" if images[c] is None else "") for c in range(C)]
    scale = max(0.4, min(t.shape[0] for t in tiles) / 650)
    band = _banner(picture.shape[1], [head, list(zip(x[:-1].tolist(), label))], scale)
    return np.concatenate([band, picture], axis=0)

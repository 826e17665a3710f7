"""Calibration-target detection: chessboard and ChArUco corners with their ids.

:func:`detect` returns a :class:`Detection`: the ids of the corners found (indices into
:meth:`heartcv.targets.TargetSpec.object_points`) and their sub-pixel positions (OpenCV pixel convention:
the centre of the top-left pixel is (0, 0)).

Chessboards (``cv2.findChessboardCornersSB`` with ``CALIB_CB_ACCURACY``, [1]_) are all-or-nothing: either
every inner corner is found or none. OpenCV also finds a pattern of the target's size inside a larger board,
which would number the corners differently from view to view; such a grid is rejected when the cells 1.5
squares beyond it, where the board's plain margin should be, still alternate like a chessboard
(:func:`_board_extends`; a target file that does not match the board thus finds nothing), and so is a grid
whose light squares hold markers (:func:`_cells_hold_markers`: a ChArUco board). ChArUco boards
(``cv2.aruco.CharucoDetector``, [2]_) carry their ids in the markers, so partial views are fine; the detection
also counts the board's markers found, markers the board does not have, and the corners the markers found
promise, from which :func:`heartcv.calibration.target_mismatch` tells a board of another layout.

**Sub-pixel refinement.** Neither detector's corners are best everywhere: on sharp images ``cornerSubPix``
over a window of a fifth of a square is more precise than the saddle-point fit of ``findChessboardCornersSB``
(OpenCV's stereo images: calibration RMS 0.27 -> 0.20 px), on soft ones (the 1920x1080 laparoscope images) it
is much worse (0.53 -> 0.81 px). Each view therefore keeps whichever of the two corner sets fits a smooth
board-to-image map better: a homography plus a low-order polynomial in the board coordinates
(:func:`smooth_fit_rms`; the image of a planar grid through a lens is smooth, detection noise is not). ChArUco
corners try two windows, 0.8 and 0.5 of the margin between a square's side and its marker: on tilted boards
the larger one reaches the markers (the phantom scene's rendered views, 216 images: corner RMS against the
truth 0.051 px with the larger window alone, 0.048 px with both).

**Orientation rule.** OpenCV orders chessboard corners row by row but may start at any of the board's
corners that the pattern's symmetry allows. heartcv fixes the order so that ids match
``TargetSpec.object_points()`` in every view:

1. *Handedness*: the board is seen from its printed side, so its x axis (along a row) turned by +90° in the
   image (towards +v) must give its y axis (along a column); a mirrored order is flipped.
2. *Colour* (boards whose 180° turn swaps the colours, i.e. ``cols + rows`` odd, such as 9x6): id 0 is the
   inner corner whose diagonal outer square (the board's top-left square) is **black**, as in OpenCV's
   printed patterns and OpenCV's sample images. This is a property of the board, so every camera and every
   view agree whatever the camera roll.
3. *Image position* (boards that look the same after a 180° turn, ``cols + rows`` even such as 14x10, and the
   90° turns of square boards): among the orders still allowed, id 0 is the one nearest the image's top-left
   corner (smallest ``u + v``). Cameras of a rig agree as long as the board's diagonal does not run near
   perpendicular to the image diagonal in one view and not in another (rolls differing by < ~45°); prefer an
   odd ``cols + rows`` or a ChArUco board for rigs with rolled cameras.

Images may be greyscale, BGR or BGRA, 8- or 16-bit or float; anything but 8-bit is stretched to 0..255.

References
----------
.. [1] Duda, Frese, "Accurate Detection and Localization of Checkerboard Corners for Calibration", BMVC 2018.
.. [2] Garrido-Jurado et al., "Automatic generation and detection of highly reliable fiducial markers under
   occlusion", Pattern Recognition 47(6), 2014; OpenCV ``objdetect/aruco`` (CharucoDetector).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

__all__ = ["Detection", "detect", "to_gray8", "smooth_fit_rms"]


@dataclass(frozen=True)
class Detection:
    """Target corners found in one image.

    Parameters
    ----------
    ids : ndarray of shape (n,), int
        Corner ids (rows of ``TargetSpec.object_points()``), unique, ascending.
    uv : ndarray of shape (n, 2), float
        Pixel positions of those corners.
    markers : int
        ChArUco: ArUco markers of the board found in the image (0 for chessboards).
    foreign_markers : int
        ChArUco: markers of the board's dictionary found whose ids the board does not have (a larger board,
        or another one, in view).
    corners_expected : int
        ChArUco: inner corners both of whose neighbouring markers were found, i.e. the corners the board's
        layout promises; far more than ``len(ids)`` when the layout differs from the board in the image.
    other_polarity_markers : int
        ChArUco, counted only where no marker of the board was found: markers of the board found in the image
        with black and white swapped (the target's ``inverted`` flag does not match the printed board).
    """

    ids: np.ndarray
    uv: np.ndarray
    markers: int = 0
    foreign_markers: int = 0
    corners_expected: int = 0
    other_polarity_markers: int = 0

    def __post_init__(self):
        ids = np.asarray(self.ids).reshape(-1)
        if ids.size and not np.issubdtype(ids.dtype, np.integer):
            raise ValueError(f"ids: integers expected, got {ids.dtype}")
        ids = ids.astype(np.int64)
        uv = np.asarray(self.uv, float).reshape(-1, 2) if np.size(self.uv) else np.zeros((0, 2))
        if uv.shape != (ids.size, 2) or not np.isfinite(uv).all():
            raise ValueError(f"uv: finite array of shape ({ids.size}, 2) expected, got {np.shape(self.uv)}")
        if np.unique(ids).size != ids.size or (ids.size and ids.min() < 0):
            raise ValueError("ids: unique non-negative integers expected")
        order = np.argsort(ids, kind="stable")
        ids, uv = ids[order], uv[order]
        for n, v in (("ids", ids), ("uv", uv)):
            v.setflags(write=False)
            object.__setattr__(self, n, v)

    def __len__(self):
        return int(self.ids.size)

    @classmethod
    def empty(cls) -> "Detection":
        return cls(np.zeros(0, np.int64), np.zeros((0, 2)))


def to_gray8(image) -> np.ndarray:
    """8-bit greyscale copy of an image (H, W), (H, W, 1), (H, W, 3) BGR or (H, W, 4) BGRA of any depth."""
    import cv2

    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 3 and img.shape[2] in (3, 4):
        if img.dtype not in (np.uint8, np.uint16, np.float32):
            img = img.astype(np.float32)
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if img.ndim != 2 or min(img.shape) < 8:
        raise ValueError(f"image: shape (H, W), (H, W, 1), (H, W, 3) or (H, W, 4) expected, got {np.shape(image)}")
    if img.dtype == np.uint8:
        return np.ascontiguousarray(img)
    img = img.astype(np.float64)
    if not np.isfinite(img).all():
        raise ValueError("image: non-finite pixel values")
    lo, hi = float(img.min()), float(img.max())
    if hi <= lo:
        return np.zeros(img.shape, np.uint8)
    return np.round((img - lo) * (255.0 / (hi - lo))).astype(np.uint8)


def detect(image, spec) -> Detection:
    """Corners of the target ``spec`` in ``image``.

    Parameters
    ----------
    image : ndarray of shape (H, W) or (H, W, C)
        Greyscale, BGR or BGRA; uint8, uint16 or float.
    spec : heartcv.targets.TargetSpec

    Returns
    -------
    Detection
        Empty when the target was not found (a chessboard that is not entirely visible is not found).
    """
    gray = to_gray8(image)
    if spec.type == "chessboard":
        return _detect_chessboard(gray, spec)
    return _detect_charuco(gray, spec)


# -- chessboard ------------------------------------------------------------------------------------------
# flag sets tried in turn: NORMALIZE|ACCURACY finds all 26 OpenCV stereo images, the others rescue the rest;
# CALIB_CB_LARGER: a board with more corners than the target is often found whole (and rejected below) rather
# than as a part of the target's size
def _sb_flag_sets():
    import cv2

    A, N, E, L = cv2.CALIB_CB_ACCURACY, cv2.CALIB_CB_NORMALIZE_IMAGE, cv2.CALIB_CB_EXHAUSTIVE, cv2.CALIB_CB_LARGER
    return (N | A | L, A | L, N | E | A | L, E | A | L)


def _detect_chessboard(gray, spec) -> Detection:
    import cv2

    cols, rows = spec.inner_size
    for flags in _sb_flag_sets():
        ok, corners = cv2.findChessboardCornersSB(gray, (cols, rows), flags=flags)
        if ok and corners is not None and len(corners) > cols * rows:
            return Detection.empty()  # the board in the image is larger than the target: not this target
        if ok and corners is not None and len(corners) == cols * rows:
            grid = corners.reshape(rows, cols, 2).astype(float)
            if _board_extends(grid, gray) or _cells_hold_markers(grid, gray):
                return Detection.empty()  # a part of a larger board, a ChArUco board, or not a board at all
            grid = _orient_grid(grid, gray)
            spacing = min(np.median(np.linalg.norm(np.diff(grid, axis=a), axis=2)) for a in (0, 1))
            uv = _refine(gray, grid.reshape(-1, 2), spec.object_points()[:, :2] / spec.square_m,
                         [SUBPIX_WINDOW * spacing])
            return Detection(np.arange(cols * rows), uv)
    return Detection.empty()


def _candidate_grids(grid):
    """The orders of a (rows, cols, 2) corner grid that describe the same board seen from its front."""
    # handedness: image of the board x axis (along a row) x image of its y axis must be > 0 (v points down)
    ex = grid[:, -1].mean(axis=0) - grid[:, 0].mean(axis=0)
    ey = grid[-1].mean(axis=0) - grid[0].mean(axis=0)
    if ex[0] * ey[1] - ex[1] * ey[0] < 0:
        grid = grid[:, ::-1]
    cands = [grid, grid[::-1, ::-1]]  # 180° turn keeps the shape
    if grid.shape[0] == grid.shape[1]:  # square: the 90° turns too (transpose + flip keeps handedness)
        g90 = np.transpose(grid, (1, 0, 2))[:, ::-1]
        cands += [g90, g90[::-1, ::-1]]
    return cands


class _GridSampler:
    """Mean grey levels of board cells around a (rows, cols, 2) corner grid, through the grid's homography
    (grid coordinates: corner (i, j) at (x, y) = (j, i); the cell centred at (x, y) = (j + 0.5, i + 0.5) lies
    between corners (i, j) and (i + 1, j + 1))."""

    def __init__(self, grid, gray):
        import cv2

        rows, cols = grid.shape[:2]
        j, i = np.meshgrid(np.arange(cols), np.arange(rows))
        self.H, _ = cv2.findHomography(np.stack([j.ravel(), i.ravel()], 1).astype(np.float64), grid.reshape(-1, 2))
        spacing = np.median(np.linalg.norm(np.diff(grid, axis=1), axis=2))
        k = int(max(1, min(7, spacing // 8))) * 2 + 1
        self.blurred = cv2.blur(gray, (k, k)).astype(np.float32)
        self.shape = grid.shape[:2]

    def __call__(self, xy):
        """Grey levels (n,) at grid coordinates (n, 2) and whether each lies inside the image."""
        import cv2

        uv = cv2.perspectiveTransform(np.asarray(xy, np.float64)[None], self.H)[0]
        h, w = self.blurred.shape
        inside = (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
        v = cv2.remap(self.blurred, uv[:, :1].astype(np.float32)[None], uv[:, 1:].astype(np.float32)[None],
                      cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).ravel()
        return v, inside

    @staticmethod
    def parity(xy):
        """+1 for cells of the colour of the cell at (0.5, 0.5), -1 for the others."""
        return np.where((np.floor(xy[:, 0]) + np.floor(xy[:, 1])) % 2 == 0, 1.0, -1.0)

    def inner(self):
        """Grid coordinates of the centres of the cells inside the corner grid (n, 2)."""
        rows, cols = self.shape
        cj, ci = np.meshgrid(np.arange(cols - 1) + 0.5, np.arange(rows - 1) + 0.5)
        return np.stack([cj.ravel(), ci.ravel()], 1)


def _origin_square_dark(grid, gray) -> bool:
    """Whether the squares of the colour of the one diagonal to corner (0, 0) are the darker ones (the inner
    squares with ``i + j`` even have that colour)."""
    sample = _GridSampler(grid, gray)
    xy = sample.inner()
    v, _ = sample(xy)
    p = sample.parity(xy)
    return float(v[p > 0].mean()) < float(v[p < 0].mean())


MARGIN_SCORE = 0.6  # |checker score| above which a ring of cells is not the board's plain margin


def _board_extends(grid, gray) -> bool:
    """Whether the cells 1.5 squares outside the corner grid (beyond the board's outer squares, where the
    printed margin is) still look like a chessboard: then the grid is part of a larger board, i.e. the target
    does not match (or the grid is spurious). Each side gets a checker score: the mean of (grey - mid) x the
    continued colour pattern, over half the inner squares' contrast; about 1 where the pattern continues, about
    0 over a plain margin."""
    sample = _GridSampler(grid, gray)
    xy = sample.inner()
    v, _ = sample(xy)
    p = sample.parity(xy)
    light, dark = v[p > 0].mean(), v[p < 0].mean()
    mid, half = (light + dark) / 2, (light - dark) / 2
    if abs(half) < 1:
        return True  # no contrast between the squares: not a chessboard
    rows, cols = grid.shape[:2]
    xs, ys = np.arange(-1, cols) + 0.5, np.arange(-1, rows) + 0.5
    for pts in (np.column_stack([xs, np.full(xs.size, -1.5)]), np.column_stack([xs, np.full(xs.size, rows + 0.5)]),
                np.column_stack([np.full(ys.size, -1.5), ys]), np.column_stack([np.full(ys.size, cols + 0.5), ys])):
        v, inside = sample(pts)
        if inside.sum() >= 3 and abs(np.mean((v[inside] - mid) * sample.parity(pts)[inside]) / half) > MARGIN_SCORE:
            return True
    return False


MARKER_SPREAD = 0.3  # grey-level spread inside light squares (over the contrast) above which they hold markers


def _cells_hold_markers(grid, gray) -> bool:
    """Whether the light squares inside the corner grid hold patterns (ArUco markers: a ChArUco board, which a
    chessboard target does not describe) rather than a plain colour: the median over the light squares of the
    spread of 25 grey levels on a 5 x 5 grid within +-0.2 squares of the centre, over the contrast, exceeds
    ``MARKER_SPREAD`` (plain chessboards, OpenCV's and the laparoscope's photographs included: below 0.04; ChArUco:
    0.63 on OpenCV's tutorial photograph, whose markers are half the square: the 9 levels at +-0.25 squares used
    before 2026-11-29 fell on the markers' edges there, 0.37, and the board was taken for a chessboard)."""
    sample = _GridSampler(grid, gray)
    xy = sample.inner()
    p = sample.parity(xy)
    v, _ = sample(xy)
    light = 1.0 if v[p > 0].mean() > v[p < 0].mean() else -1.0
    cells = xy[p == light]
    if cells.size == 0 or (p != light).sum() == 0:
        return False
    steps = np.linspace(-0.2, 0.2, 5)      # inside a marker of half the square (OpenCV's tutorial board) too
    offsets = [(a, b) for a in steps for b in steps]
    vals = np.stack([sample(cells + np.asarray(o))[0] for o in offsets], axis=1)
    contrast = np.percentile(vals, 95) - np.median(v[p != light])
    if contrast <= 0:
        return False
    return bool(np.median(vals.max(axis=1) - vals.min(axis=1)) / contrast > MARKER_SPREAD)


def _orient_grid(grid, gray):
    """Apply the module's orientation rule to a (rows, cols, 2) grid of corners."""
    rows, cols = grid.shape[:2]
    cands = _candidate_grids(grid)
    if (rows + cols) % 2 == 1 and rows > 1 and cols > 1:
        dark = [c for c in cands if _origin_square_dark(c, gray)]
        cands = dark or cands
    return min(cands, key=lambda c: c[0, 0, 0] + c[0, 0, 1])


# -- ChArUco ----------------------------------------------------------------------------------------------
@lru_cache(maxsize=8)
def _charuco_layout(spec):
    """The board's marker ids (frozenset) and, per inner corner, the ids of its two neighbouring markers
    (the markers in the two white squares that touch the corner; (n_corners, 2))."""
    board = spec.cv_board()
    marker_ids = np.asarray(board.getIds()).reshape(-1)
    centres = np.array([np.asarray(c).reshape(-1, 3)[:, :2].mean(axis=0) for c in board.getObjPoints()])
    corners = np.asarray(board.getChessboardCorners()).reshape(-1, 3)[:, :2]
    d = np.linalg.norm(corners[:, None] - centres[None], axis=2)
    near = np.argsort(d, axis=1)[:, :2]  # at sqrt(2) / 2 squares; the next markers are >= 1.58 squares away
    return frozenset(marker_ids.tolist()), marker_ids[near]


def _detect_charuco(gray, spec) -> Detection:
    import cv2

    if spec.inverted:  # white markers on black squares: the negative is an ordinary board
        gray = 255 - gray
    detector = cv2.aruco.CharucoDetector(spec.cv_board())
    corners, ids, _, marker_ids = detector.detectBoard(gray)
    found = set() if marker_ids is None else set(np.asarray(marker_ids).reshape(-1).tolist())
    board_ids, neighbours = _charuco_layout(spec)
    counts = {"markers": len(found & board_ids), "foreign_markers": len(found - board_ids),
              "corners_expected": int(np.isin(neighbours, list(found)).all(axis=1).sum())}
    if not counts["markers"]:
        counts["other_polarity_markers"] = _other_polarity_markers(gray, spec, board_ids)
    if ids is None or len(ids) == 0:
        return Detection(np.zeros(0, np.int64), np.zeros((0, 2)), **counts)
    corners = corners.reshape(-1, 2).astype(float)
    ids = ids.reshape(-1).astype(np.int64)
    if len(ids) < 2:
        return Detection(ids, corners, **counts)
    # local square size in pixels, from each corner's nearest neighbour on the board
    obj = spec.object_points()[ids, :2] / spec.square_m
    d_obj = np.linalg.norm(obj[:, None] - obj[None], axis=2)
    np.fill_diagonal(d_obj, np.inf)
    nearest = d_obj.argmin(axis=1)
    d_img = np.linalg.norm(corners - corners[nearest], axis=1)
    spacing = float(np.median(d_img / d_obj[np.arange(len(ids)), nearest]))
    # the window must stay clear of the markers inside the white squares
    margin_px = spacing * (spec.square_m - spec.marker_m) / 2 / spec.square_m
    halves = [min(SUBPIX_WINDOW * spacing, f * margin_px) for f in CHARUCO_WINDOWS]
    return Detection(ids, _refine(gray, corners, obj, halves), **counts)


def _other_polarity_markers(gray, spec, board_ids) -> int:
    """Markers of the board found in the negative of ``gray`` (the image as the detector saw it)."""
    import cv2

    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, spec.dictionary))
    _, ids, _ = cv2.aruco.ArucoDetector(d).detectMarkers(255 - gray)
    return 0 if ids is None else len(set(np.asarray(ids).reshape(-1).tolist()) & board_ids)


# -- sub-pixel refinement -------------------------------------------------------------------------------
SUBPIX_WINDOW = 0.2  # cornerSubPix half-window, as a fraction of the square size in pixels (chessboards)
CHARUCO_WINDOWS = (0.8, 0.5)  # ChArUco: half-windows tried, as fractions of the margin between a square's side
#                               and its marker (the larger one touches the markers of tilted boards)


def smooth_fit_rms(board_xy, uv) -> float:
    """RMS (px) of corners (n, 2) about the smooth map that best fits them: a homography from the board
    coordinates ``board_xy`` (n, 2) followed by a polynomial correction in them (degree 3 for n >= 30,
    2 for n >= 15, none below). 0 for fewer than 5 corners."""
    import cv2

    board_xy = np.asarray(board_xy, float)
    uv = np.asarray(uv, float)
    n = len(uv)
    if n < 5:
        return 0.0
    H, _ = cv2.findHomography(board_xy, uv)
    if H is None:
        return float("inf")
    r = uv - cv2.perspectiveTransform(board_xy[None], H)[0]
    deg = 3 if n >= 30 else 2 if n >= 15 else 0
    if deg:
        x = (board_xy - board_xy.mean(axis=0)) / max(np.ptp(board_xy, axis=0).max(), 1e-12)
        A = np.stack([x[:, 0] ** i * x[:, 1] ** j for i in range(deg + 1) for j in range(deg + 1 - i)], axis=1)
        r = r - A @ np.linalg.lstsq(A, r, rcond=None)[0]
    return float(np.sqrt((r ** 2).sum(axis=1).mean()))


def _refine(gray, uv, board_xy, halves_px) -> np.ndarray:
    """The detector's corners or their ``cornerSubPix`` refinement with one of the half-windows ``halves_px``
    (px), whichever fits a smooth map best."""
    import cv2

    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-3)
    best, best_fit = np.asarray(uv, float), smooth_fit_rms(board_xy, uv)
    for half in sorted({int(np.clip(round(h), 2, 11)) for h in halves_px}, reverse=True):
        sub = cv2.cornerSubPix(gray, np.array(uv, np.float32).reshape(-1, 1, 2), (half, half), (-1, -1),
                               crit).reshape(-1, 2).astype(float)
        fit = smooth_fit_rms(board_xy, sub)
        if fit < best_fit:
            best, best_fit = sub, fit
    return best

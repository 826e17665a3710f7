"""Calibration targets: ChArUco boards and chessboards (docs/design.md §4, target file).

A target is described by a :class:`TargetSpec` (what the target YAML holds). Its corners are numbered like
OpenCV: chessboard inner corners row by row (``cols x rows`` inner corners, id = row * cols + col), ChArUco
inner corners as ``cv2.aruco.CharucoBoard.getChessboardCorners()`` (``(sq_x - 1) * (sq_y - 1)`` of them). The
board frame has its origin at the board's outer top-left corner for ChArUco (OpenCV's convention) and at the
first inner corner for chessboards, x along the columns, y along the rows, z = 0 on the board (so z points
into the board, away from a camera that sees its printed side).

Printable images and the renderer's texture (:func:`render_board`, :func:`board_texture`,
:func:`board_reflectance`) use one pixel grid aligned with the squares: ``px_per_m`` pixels per metre with a whole
number of pixels per square (:func:`exact_px_per_m`), so every square edge falls on a pixel edge. Pixel
``(col, row)`` of a texture covers the board-frame square ``[x0 + col / px_per_m, x0 + (col + 1) / px_per_m) x
[y0 + row / px_per_m, ...)`` where ``(x0, y0) = spec.squares_origin_m`` is the outer top-left corner of the
squares; its centre (OpenCV's pixel coordinate ``(col, row)``) is at ``x0 + (col + 0.5) / px_per_m``.
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction
import functools
import math
import numbers

import numpy as np

from .tracker.files import InputError
from .tracker.files import show as _show

__all__ = ["TargetSpec", "TARGET_TYPES", "DICTIONARIES", "INCH_M", "exact_px_per_m", "board_texture",
           "render_board", "board_reflectance", "board_extent_m"]

INCH_M = 0.0254
MIN_SQUARE_PX = 10       # a printed square must span at least this many pixels
MIN_MARKER_CELL_PX = 3   # and an ArUco marker cell (one bit) at least this many
MAX_IMAGE_PX = 30000     # longest side of a printable image (A0 at 600 dpi is 28 000 px)
MAX_SQUARES = 100        # squares (ChArUco) or inner corners (chessboard) along one side
MAX_BOARD_M = 1.2        # longest side of the squares area (A0 paper is 1.19 m)

TARGET_TYPES = ("charuco", "chessboard")
DICTIONARIES = (
    "DICT_4X4_50", "DICT_4X4_100", "DICT_4X4_250", "DICT_4X4_1000",
    "DICT_5X5_50", "DICT_5X5_100", "DICT_5X5_250", "DICT_5X5_1000",
    "DICT_6X6_50", "DICT_6X6_100", "DICT_6X6_250", "DICT_6X6_1000",
    "DICT_7X7_50", "DICT_7X7_100", "DICT_7X7_250", "DICT_7X7_1000",
    "DICT_ARUCO_ORIGINAL",
)


@dataclass(frozen=True)
class TargetSpec:
    """A calibration target.

    Parameters
    ----------
    type : {'charuco', 'chessboard'}
    squares : (int, int)
        ChArUco: number of squares ``(sq_x, sq_y)`` across and down. Chessboard: number of *inner corners*
        ``(cols, rows)`` (OpenCV's ``patternSize``); the printed board has one more square each way.
    square_m : float
        Square side in metres.
    marker_m : float, optional
        ChArUco marker side in metres (< square_m).
    dictionary : str, optional
        ChArUco ArUco dictionary name (``DICT_5X5_250``...).
    legacy : bool
        ChArUco legacy pattern (OpenCV < 4.6 boards with an even number of rows).
    name : str
    inverted : bool
        ChArUco printed with its colours swapped: white markers on black squares (caliscope's and some vendors'
        boards). Detection looks for the markers in the negative image; printable images and the renderer's
        texture swap black and white inside the squares area (the margin stays white).
    """

    type: str
    squares: tuple
    square_m: float
    marker_m: float | None = None
    dictionary: str | None = None
    legacy: bool = False
    name: str = "target"
    inverted: bool = False

    def __post_init__(self):
        # errors are InputError (a ValueError) naming the target file's key; heartcv.io.read_target adds the file
        if not isinstance(self.type, str) or self.type not in TARGET_TYPES:
            raise InputError(None, f"one of {TARGET_TYPES} expected, got {_show(self.type)}", "type")
        key = "squares" if self.type == "charuco" else "inner_corners"
        what = "squares" if self.type == "charuco" else "inner corners"
        sq = tuple(self.squares) if isinstance(self.squares, (list, tuple)) else ()
        if len(sq) != 2 or not all(_is_int(v) for v in sq):
            raise InputError(None, f"{what}: two integers (cols, rows) expected, got {_show(self.squares)}", key)
        sq = (int(sq[0]), int(sq[1]))
        # OpenCV: a ChArUco board needs >= 3 squares each way for an inner corner grid; findChessboardCorners(SB)
        # needs more than 2 inner corners each way
        if min(sq) < 3:
            raise InputError(None, f"at least 3 {what} each way for a {self.type}, got {sq[0]}x{sq[1]}", key)
        if max(sq) > MAX_SQUARES:
            raise InputError(None, f"at most {MAX_SQUARES} {what} each way, got {sq[0]}x{sq[1]}", key)
        if not (_is_real(self.square_m) and 1e-4 <= self.square_m < 1):
            raise InputError(None, f"square size: metres in [0.0001, 1) expected, got {_show(self.square_m)}",
                             "square_m")
        if self.type == "charuco":
            # a marker below a tenth of its square cannot be printed or detected (OpenCV's boards use 0.5-0.8)
            if not (_is_real(self.marker_m) and 0.1 * self.square_m <= self.marker_m < self.square_m):
                raise InputError(None, f"marker size: 0.1 square <= marker < square ({self.square_m} m) expected, "
                                       f"got {_show(self.marker_m)}", "marker_m")
            if not isinstance(self.dictionary, str) or self.dictionary not in DICTIONARIES:
                raise InputError(None, f"one of {DICTIONARIES} expected, got {_show(self.dictionary)}", "dictionary")
            n_markers = (sq[0] * sq[1]) // 2
            size = int(self.dictionary.split("_")[-1]) if self.dictionary != "DICT_ARUCO_ORIGINAL" else 1024
            if n_markers > size:
                raise InputError(None, f"{self.dictionary} has {size} markers, the board needs {n_markers}",
                                 "dictionary")
        else:
            if self.marker_m is not None or self.dictionary is not None:
                raise InputError(None, "marker size and dictionary apply to ChArUco targets only",
                                 "marker_m" if self.marker_m is not None else "dictionary")
            if isinstance(self.legacy, (bool, np.bool_)) and self.legacy:
                raise InputError(None, "legacy pattern applies to ChArUco targets only", "legacy_pattern")
            if isinstance(self.inverted, (bool, np.bool_)) and self.inverted:
                raise InputError(None, "inverted colours apply to ChArUco targets only (a chessboard with its "
                                       "colours swapped is the same chessboard)", "inverted")
        if not isinstance(self.legacy, (bool, np.bool_)):
            raise InputError(None, f"legacy pattern: true or false expected, got {_show(self.legacy)}",
                             "legacy_pattern")
        if not isinstance(self.inverted, (bool, np.bool_)):
            raise InputError(None, f"inverted: true or false expected, got {_show(self.inverted)}", "inverted")
        if not isinstance(self.name, str) or not self.name.strip():
            raise InputError(None, f"a non-empty string expected, got {_show(self.name)}", "name")
        n_side = max(sq) if self.type == "charuco" else max(sq) + 1
        if n_side * float(self.square_m) > MAX_BOARD_M:
            raise InputError(None, f"square size: the squares area would be {n_side * float(self.square_m):.3g} m "
                                   f"long; at most {MAX_BOARD_M} m allowed", "square_m")
        object.__setattr__(self, "squares", sq)
        object.__setattr__(self, "square_m", float(self.square_m))
        object.__setattr__(self, "legacy", bool(self.legacy))
        object.__setattr__(self, "inverted", bool(self.inverted))
        if self.marker_m is not None:
            object.__setattr__(self, "marker_m", float(self.marker_m))

    # -- geometry -------------------------------------------------------------------------------------
    @property
    def n_corners(self) -> int:
        if self.type == "chessboard":
            return self.squares[0] * self.squares[1]
        return (self.squares[0] - 1) * (self.squares[1] - 1)

    @property
    def inner_size(self) -> tuple[int, int]:
        """Inner corners ``(cols, rows)``."""
        if self.type == "chessboard":
            return self.squares
        return self.squares[0] - 1, self.squares[1] - 1

    @property
    def board_size_m(self) -> tuple[float, float]:
        """Printed board (all squares), width x height in metres."""
        cols, rows = self.inner_size
        return (cols + 1) * self.square_m, (rows + 1) * self.square_m

    @property
    def squares_origin_m(self) -> tuple[float, float]:
        """Board-frame position of the outer top-left corner of the squares: (0, 0) for ChArUco, one square up
        and left of the first inner corner, (-square, -square), for a chessboard."""
        return (0.0, 0.0) if self.type == "charuco" else (-self.square_m, -self.square_m)

    @property
    def squares_count(self) -> tuple[int, int]:
        """Printed squares ``(across, down)``."""
        cols, rows = self.inner_size
        return cols + 1, rows + 1

    def object_points(self) -> np.ndarray:
        """Corner positions (n_corners, 3) in the board frame, indexed by corner id."""
        cols, rows = self.inner_size
        j, i = np.meshgrid(np.arange(cols), np.arange(rows))
        pts = np.stack([j.ravel(), i.ravel(), np.zeros(j.size)], axis=1) * self.square_m
        if self.type == "charuco":
            pts[:, :2] += self.square_m  # origin at the outer corner (OpenCV)
        return pts

    def cv_board(self):
        """The ``cv2.aruco.CharucoBoard`` (ChArUco only)."""
        import cv2

        if self.type != "charuco":
            raise ValueError("cv_board: ChArUco targets only")
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        b = cv2.aruco.CharucoBoard(self.squares, self.square_m, self.marker_m, d)
        b.setLegacyPattern(bool(self.legacy))
        return b

    def to_dict(self) -> dict:
        d = {"format": "heartcv.target", "format_version": 1, "name": self.name, "type": self.type,
             "squares" if self.type == "charuco" else "inner_corners": list(self.squares),
             "square_m": self.square_m}
        if self.type == "charuco":
            d.update({"marker_m": self.marker_m, "dictionary": self.dictionary, "legacy_pattern": bool(self.legacy)})
            if self.inverted:  # written only when true: files of normal boards stay as they were
                d["inverted"] = True
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "TargetSpec":
        """Inverse of :meth:`to_dict`; :class:`~heartcv.tracker.files.InputError` (a ValueError) naming the bad
        field."""
        if not isinstance(d, dict):
            raise InputError(None, f"target: a mapping expected, got {type(d).__name__}")
        fmt = d.get("format", "heartcv.target")
        if fmt != "heartcv.target":
            raise InputError(None, f"'heartcv.target' expected, got {_show(fmt)}", "format")
        ver = d.get("format_version", 1)
        if isinstance(ver, bool) or ver != 1:
            raise InputError(None, f"1 supported, got {_show(ver)}", "format_version")
        typ = d.get("type")
        if not isinstance(typ, str) or typ not in TARGET_TYPES:
            raise InputError(None, f"one of {TARGET_TYPES} expected, got {_show(typ)}", "type")
        key = "squares" if typ == "charuco" else "inner_corners"
        # informative keys written by heartcv.io.write_target: accepted, not part of the spec
        known = {"format", "format_version", "name", "type", key, "square_m", "marker_m", "dictionary",
                 "legacy_pattern", "inverted", "image", "dpi", "heartcv_version", "board_size_m", "producer",
                 "description"}
        unknown = sorted(set(d) - known, key=str)
        if unknown:
            raise InputError(None, f"unknown field (known: {sorted(known)})", str(unknown[0]))
        for k in (key, "square_m"):
            if k not in d:
                raise InputError(None, "missing (required)", k)
        sq = d[key]
        if not isinstance(sq, (list, tuple)):
            raise InputError(None, f"a list [cols, rows] expected, got {_show(sq)}", key)
        return cls(typ, tuple(sq), d["square_m"], d.get("marker_m"), d.get("dictionary"),
                   d.get("legacy_pattern", False), d.get("name", "target"), d.get("inverted", False))


def _is_int(v) -> bool:
    return isinstance(v, numbers.Integral) and not isinstance(v, (bool, np.bool_)) or (
        isinstance(v, float) and v.is_integer())


def _is_real(v) -> bool:
    if not isinstance(v, numbers.Real) or isinstance(v, (bool, np.bool_)):
        return False
    try:
        return math.isfinite(float(v))
    except OverflowError:  # an integer beyond the float range
        return False


# -- pixel grids ------------------------------------------------------------------------------------------------
def exact_px_per_m(spec: TargetSpec, px_per_m: float, *, tolerance=0.05) -> float:
    """The pixel density nearest to ``px_per_m`` that gives every square a whole number of pixels.

    The result is a whole number of pixels per metre (what a PNG ``pHYs`` chunk stores) whenever one lies within
    ``tolerance`` (relative) of the request -- e.g. 12 mm squares at 300 dpi (11 811 px/m) give 11 750 px/m
    (298.45 dpi, 141 px per square), 25 mm squares give 11 800 px/m (299.72 dpi, 295 px). Otherwise (a square
    size that is no simple fraction of a metre) it is ``round(square_m * px_per_m) / square_m``, exact for the
    squares but not a whole number.
    """
    if not (_is_real(px_per_m) and px_per_m > 0):
        raise ValueError(f"pixel density: a positive number expected, got {px_per_m!r}")
    # square_m = p / q exactly (to 1 nm): square_m * P is whole for every multiple P of q
    q = Fraction(spec.square_m).limit_denominator(10**9).denominator
    k = max(1, round(px_per_m / q))
    if abs(k * q - px_per_m) <= tolerance * px_per_m:
        return float(k * q)
    n = max(1, round(spec.square_m * px_per_m))
    return n / spec.square_m


def _square_px(spec: TargetSpec, px_per_m: float) -> int:
    n = spec.square_m * px_per_m
    if abs(n - round(n)) > 1e-6 or round(n) < 1:
        raise ValueError(f"pixel density {px_per_m} px/m gives {n:.6g} px per {spec.square_m * 1e3:g} mm square; "
                         f"a whole number is needed (use exact_px_per_m)")
    return int(round(n))


def _check_printable(spec: TargetSpec, square_px: int, px_per_m: float):
    """InputError (no file, no field: the values are the caller's options) for squares or marker cells too small
    to print at this density, or an image too large."""
    dpi = px_per_m * INCH_M
    if square_px < MIN_SQUARE_PX:
        raise InputError(None, f"squares too small: {spec.square_m * 1e3:g} mm is {square_px} px at {dpi:.4g} dpi "
                               f"(at least {MIN_SQUARE_PX} px needed); raise the DPI or the square size")
    if spec.type == "charuco":
        cell_px = spec.marker_m / (_marker_bits(spec) + 2) * px_per_m
        if cell_px < MIN_MARKER_CELL_PX:
            raise InputError(None, f"markers too small: a {spec.marker_m * 1e3:g} mm {spec.dictionary} marker has "
                                   f"cells of {cell_px:.2g} px at {dpi:.4g} dpi (at least {MIN_MARKER_CELL_PX} px "
                                   "needed); raise the DPI or the marker size")
    cols, rows = spec.squares_count
    if max(cols, rows) * square_px > MAX_IMAGE_PX:
        raise InputError(None, f"image too large: {cols * square_px} x {rows * square_px} px at {dpi:.4g} dpi "
                               f"(at most {MAX_IMAGE_PX} px a side)")


def _marker_bits(spec: TargetSpec) -> int:
    import cv2

    return int(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, spec.dictionary)).markerSize)


# -- images -----------------------------------------------------------------------------------------------------
def board_texture(spec: TargetSpec, px_per_m: float) -> np.ndarray:
    """Reflectance of the squares area (white 1, black 0), float32 of shape (rows * n, cols * n), read-only.

    ``n = square_m * px_per_m`` must be a whole number (:func:`exact_px_per_m`). Pixel ``(col, row)`` covers the
    board-frame cell starting at ``spec.squares_origin_m + (col, row) / px_per_m`` (module docstring). ChArUco
    squares and markers come from ``cv2.aruco.CharucoBoard.generateImage`` (1-bit marker border), so marker ids
    and the legacy pattern are OpenCV's, with black and white swapped for an inverted target; chessboards have a
    black top-left square. Results are cached.
    """
    return _texture(spec, _square_px(spec, px_per_m))


@functools.lru_cache(maxsize=2)
def _texture(spec: TargetSpec, n: int) -> np.ndarray:
    cols, rows = spec.squares_count
    if spec.type == "charuco":
        img = spec.cv_board().generateImage((cols * n, rows * n), marginSize=0, borderBits=1)
        tex = img.astype(np.float32) / 255.0
        if spec.inverted:
            tex = 1.0 - tex
    else:
        small = (np.add.outer(np.arange(rows), np.arange(cols)) % 2).astype(np.float32)  # (0, 0) black
        tex = np.repeat(np.repeat(small, n, axis=0), n, axis=1)
    tex.setflags(write=False)
    return tex


def render_board(spec: TargetSpec, dpi: float = 300, margin_m: float = 0.01) -> tuple[np.ndarray, float]:
    """A printable image of the target: uint8 (H, W), white margin around the squares.

    The pixel density is :func:`exact_px_per_m` of ``dpi``: each square is exactly ``square_m * px_per_m``
    pixels, so printed at ``px_per_m * 0.0254`` dpi (what the PNG and PDF written by
    :func:`heartcv.io.write_board_image` state) the squares have their nominal size. The margin is rounded to
    whole pixels: ``round(margin_m * px_per_m)`` on every side.

    Returns
    -------
    image : ndarray of shape (H, W), uint8
        ``H = rows * n + 2 * m``, ``W = cols * n + 2 * m`` with ``n`` pixels per square and ``m`` margin pixels.
        Pixel centre ``(col, row)`` lies at board-frame ``squares_origin_m + (col - m + 0.5, row - m + 0.5) /
        px_per_m``.
    px_per_m : float
        Pixels per metre (a whole number for square sizes that are simple fractions of a metre).

    Raises
    ------
    InputError
        Squares under ``MIN_SQUARE_PX`` or marker cells under ``MIN_MARKER_CELL_PX`` pixels at this density, or an
        image over ``MAX_IMAGE_PX`` pixels a side (no file, no field: the caller's values).
    """
    if not (_is_real(dpi) and dpi > 0):
        raise ValueError(f"dpi: a positive number expected, got {dpi!r}")
    if not (_is_real(margin_m) and 0 <= margin_m < 1):
        raise ValueError(f"margin: metres in [0, 1) expected, got {margin_m!r}")
    px_per_m = exact_px_per_m(spec, dpi / INCH_M)
    n = _square_px(spec, px_per_m)
    _check_printable(spec, n, px_per_m)
    m = int(round(margin_m * px_per_m))
    tex = np.rint(board_texture(spec, px_per_m) * 255).astype(np.uint8)
    return np.pad(tex, m, constant_values=255), px_per_m


def board_extent_m(spec: TargetSpec, margin_m: float = 0.0) -> tuple[float, float, float, float]:
    """``(x_min, y_min, x_max, y_max)`` of the squares area grown by ``margin_m``, in the board frame (m)."""
    x0, y0 = spec.squares_origin_m
    w, h = spec.board_size_m
    return x0 - margin_m, y0 - margin_m, x0 + w + margin_m, y0 + h + margin_m


DEFAULT_TEXTURE_PX_PER_M = 20000.0  # 50 um texels: 0.56 px of the default rig (89 um per pixel at the heart)
MAX_TEXTURE_TEXELS = 40e6  # renderer textures (board, phantom): at most 40 Mtexels (float32: 160 MB per channel)


def board_reflectance(spec: TargetSpec, xy_board_m, *, px_per_m: float | None = None, margin_m: float = 0.01,
                      outside: float = 1.0, interpolation: str = "bilinear") -> np.ndarray:
    """Reflectance in [0, 1] (white 1, black 0) of board-frame points, for the renderer.

    Parameters
    ----------
    xy_board_m : array_like of shape (N, 2) or (N, 3)
        Board-frame points in metres (a z column is ignored).
    px_per_m : float, optional
        Texture density; default :func:`exact_px_per_m` of 20 000 px/m (50 um texels). Must give whole pixels
        per square.
    margin_m : float
        White margin around the squares area.
    outside : float
        Value beyond the margin (off the board; use :func:`board_extent_m` to tell hits from misses).
    interpolation : {'bilinear', 'nearest'}
        Bilinear interpolation between texel centres (clamped at the edge of the squares area, so the step from
        the outer squares to the white margin stays at the board edge) or the texel that contains the point.

    Returns
    -------
    ndarray of shape (N,), float64
    """
    xy = np.asarray(xy_board_m, float)
    if xy.ndim != 2 or xy.shape[1] not in (2, 3):
        raise ValueError(f"points: shape (N, 2) or (N, 3) expected, got {xy.shape}")
    if interpolation not in ("bilinear", "nearest"):
        raise ValueError(f"interpolation: 'bilinear' or 'nearest' expected, got {interpolation!r}")
    if px_per_m is None:
        # 50 um texels, coarser for boards so large that the texture would pass MAX_TEXTURE_TEXELS (memory bound)
        w, h = spec.board_size_m
        px_per_m = exact_px_per_m(spec, min(DEFAULT_TEXTURE_PX_PER_M, math.sqrt(MAX_TEXTURE_TEXELS / (w * h))))
    tex = board_texture(spec, px_per_m)
    H, W = tex.shape
    x0, y0 = spec.squares_origin_m
    u = (xy[:, 0] - x0) * px_per_m  # texel units from the squares' outer corner
    v = (xy[:, 1] - y0) * px_per_m
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    ex = board_extent_m(spec, margin_m)
    on_board = (xy[:, 0] >= ex[0]) & (xy[:, 0] <= ex[2]) & (xy[:, 1] >= ex[1]) & (xy[:, 1] <= ex[3])
    out = np.where(on_board, 1.0, float(outside))
    u, v = u[inside], v[inside]
    if interpolation == "nearest":
        out[inside] = tex[np.minimum(v.astype(int), H - 1), np.minimum(u.astype(int), W - 1)]
        return out
    cu = np.clip(u - 0.5, 0, W - 1)  # texel-centre coordinates, clamped to the squares area
    cv = np.clip(v - 0.5, 0, H - 1)
    c0 = np.minimum(cu.astype(int), W - 2) if W > 1 else np.zeros(cu.shape, int)
    r0 = np.minimum(cv.astype(int), H - 2) if H > 1 else np.zeros(cv.shape, int)
    fu, fv = cu - c0, cv - r0
    c1, r1 = np.minimum(c0 + 1, W - 1), np.minimum(r0 + 1, H - 1)
    t = tex.astype(np.float64, copy=False)
    out[inside] = ((1 - fv) * ((1 - fu) * t[r0, c0] + fu * t[r0, c1])
                   + fv * ((1 - fu) * t[r1, c0] + fu * t[r1, c1]))
    return out

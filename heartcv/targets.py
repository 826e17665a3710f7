"""Calibration targets: ChArUco boards and chessboards (DESIGN.md §4, target file).

A target is described by a :class:`TargetSpec` (what the target YAML holds). Its corners are numbered like
OpenCV: chessboard inner corners row by row (``cols x rows`` inner corners, id = row * cols + col), ChArUco
inner corners as ``cv2.aruco.CharucoBoard.getChessboardCorners()`` (``(sq_x - 1) * (sq_y - 1)`` of them). The
board frame has its origin at the board's outer top-left corner for ChArUco (OpenCV's convention) and at the
first inner corner for chessboards, x along the columns, y along the rows, z = 0 on the board (so z points
into the board, away from a camera that sees its printed side).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["TargetSpec", "TARGET_TYPES", "DICTIONARIES"]

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
    """

    type: str
    squares: tuple
    square_m: float
    marker_m: float | None = None
    dictionary: str | None = None
    legacy: bool = False
    name: str = "target"

    def __post_init__(self):
        if self.type not in TARGET_TYPES:
            raise ValueError(f"type: one of {TARGET_TYPES} expected, got {self.type!r}")
        sq = tuple(self.squares)
        if len(sq) != 2 or any(isinstance(v, bool) or int(v) != v for v in sq):
            raise ValueError(f"squares: two integers expected, got {self.squares!r}")
        sq = (int(sq[0]), int(sq[1]))
        lo = 3 if self.type == "charuco" else 2
        if min(sq) < lo:
            raise ValueError(f"squares: at least {lo} each way for a {self.type}, got {sq}")
        if not (np.isfinite(self.square_m) and 0 < self.square_m < 1):
            raise ValueError(f"square size: metres in (0, 1) expected, got {self.square_m}")
        if self.type == "charuco":
            if self.marker_m is None or not (0 < self.marker_m < self.square_m):
                raise ValueError(f"marker size: 0 < marker < square ({self.square_m} m) expected, got {self.marker_m}")
            if self.dictionary not in DICTIONARIES:
                raise ValueError(f"dictionary: one of {DICTIONARIES} expected, got {self.dictionary!r}")
            n_markers = (sq[0] * sq[1]) // 2
            size = int(self.dictionary.split("_")[-1]) if self.dictionary != "DICT_ARUCO_ORIGINAL" else 1024
            if n_markers > size:
                raise ValueError(f"dictionary: {self.dictionary} has {size} markers, the board needs {n_markers}")
        else:
            if self.marker_m is not None or self.dictionary is not None:
                raise ValueError("marker size and dictionary apply to ChArUco targets only")
        object.__setattr__(self, "squares", sq)
        object.__setattr__(self, "square_m", float(self.square_m))
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
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "TargetSpec":
        """Inverse of :meth:`to_dict`; ValueError naming the bad field."""
        if not isinstance(d, dict):
            raise ValueError("target: a mapping expected")
        if d.get("format", "heartcv.target") != "heartcv.target":
            raise ValueError(f"format: 'heartcv.target' expected, got {d.get('format')!r}")
        if d.get("format_version", 1) != 1:
            raise ValueError(f"format_version: 1 supported, got {d.get('format_version')!r}")
        typ = d.get("type")
        key = "squares" if typ == "charuco" else "inner_corners"
        known = {"format", "format_version", "name", "type", key, "square_m", "marker_m", "dictionary",
                 "legacy_pattern", "image", "dpi", "heartcv_version"}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"{unknown[0]}: unknown field (known: {sorted(known)})")
        if key not in d:
            raise ValueError(f"{key}: missing")
        return cls(typ, tuple(d[key]), d.get("square_m", float("nan")), d.get("marker_m"), d.get("dictionary"),
                   bool(d.get("legacy_pattern", False)), str(d.get("name", "target")))

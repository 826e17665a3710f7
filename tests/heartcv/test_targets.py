"""Calibration targets: TargetSpec validation, exact printable images, detection by OpenCV of the rendered boards,
and the renderer's texture lookup."""

import cv2
import numpy as np
import pytest

from heartcv.targets import (
    INCH_M,
    TargetSpec,
    board_extent_m,
    board_reflectance,
    board_texture,
    exact_px_per_m,
    render_board,
)

CHARUCO = TargetSpec("charuco", (11, 8), 0.012, 0.009, "DICT_5X5_250", name="default")
CHESS = TargetSpec("chessboard", (9, 6), 0.025)
SUBPIX = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-5)


def _camera_image(spec, H, size, margin_m, ss=4):
    """The board image seen through the homography H (board-image pixels -> camera pixels), anti-aliased by
    rendering at ss x the resolution and area-averaging; plus the exact camera-pixel position of every corner.

    Pixel convention (OpenCV): pixel (0, 0)'s centre is at (0, 0). Area-averaging ss x ss blocks maps the low-
    resolution coordinate u to ss * u + (ss - 1) / 2 at high resolution, hence S below.
    """
    img, ppm = render_board(spec, 300, margin_m)
    m = int(round(margin_m * ppm))
    S = np.array([[ss, 0, (ss - 1) / 2], [0, ss, (ss - 1) / 2], [0, 0, 1.0]])
    hi = cv2.warpPerspective(img, S @ H, (size[0] * ss, size[1] * ss), flags=cv2.INTER_LINEAR, borderValue=255)
    lo = cv2.resize(hi, size, interpolation=cv2.INTER_AREA)
    x0, y0 = spec.squares_origin_m
    P = spec.object_points()
    u = np.c_[(P[:, 0] - x0) * ppm + m - 0.5, (P[:, 1] - y0) * ppm + m - 0.5, np.ones(len(P))] @ H.T
    return lo, u[:, :2] / u[:, 2:]


# -- exact physical size ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("spec, ppm, square_px", [(CHARUCO, 11750.0, 141), (CHESS, 11800.0, 295)])
def test_pixel_density_is_exact(spec, ppm, square_px):
    assert exact_px_per_m(spec, 300 / INCH_M) == ppm  # nearest whole px/m giving whole pixels per square
    img, got = render_board(spec, dpi=300, margin_m=0.01)
    assert got == ppm and spec.square_m * ppm == pytest.approx(square_px, abs=1e-9)
    m = round(0.01 * ppm)  # 118 px
    cols, rows = spec.squares_count
    assert img.shape == (rows * square_px + 2 * m, cols * square_px + 2 * m) and img.dtype == np.uint8
    # physical size at the stated DPI equals the nominal board size exactly
    assert (img.shape[1] - 2 * m) / ppm == pytest.approx(spec.board_size_m[0], abs=1e-15)
    # margin white; every square uniform at its corners and centre, colours alternating, edges on pixel edges
    assert (img[:m] == 255).all() and (img[:, :m] == 255).all() and (img[-m:] == 255).all()
    sq = img[m:-m, m:-m].reshape(rows, square_px, cols, square_px)
    black = (sq[:, 0, :, 0] == 0) & (sq[:, -1, :, -1] == 0) & (sq[:, square_px // 2, :, square_px // 2] == 0)
    white = (sq[:, 0, :, 0] == 255) & (sq[:, -1, :, -1] == 255)
    assert (black ^ white).all()
    i, j = np.indices((rows, cols))
    assert (black == ((i + j) % 2 == 0)).all()  # top-left square black (default pattern)
    assert ((sq == 0).all(axis=(1, 3)) == black).all()  # black squares are entirely black


def test_exact_px_per_m_fallback_and_texture_grid_check():
    odd = TargetSpec("chessboard", (4, 3), 0.0123456)
    ppm = exact_px_per_m(odd, 11811.0)
    assert odd.square_m * ppm == pytest.approx(round(odd.square_m * 11811.0), abs=1e-9)
    with pytest.raises(ValueError, match="whole number"):
        board_texture(CHARUCO, 11811.0)


def test_printability_checks():
    with pytest.raises(ValueError, match="squares too small"):
        render_board(TargetSpec("chessboard", (4, 3), 0.0005), dpi=300)
    with pytest.raises(ValueError, match="markers too small"):
        render_board(TargetSpec("charuco", (5, 4), 0.002, 0.0015, "DICT_6X6_50"), dpi=300)
    with pytest.raises(ValueError, match="dpi"):
        render_board(CHESS, dpi=0)


# -- detection by OpenCV -------------------------------------------------------------------------------------------
def test_charuco_detected_scaled():
    H = np.array([[0.5, 0, 30.3], [0, 0.5, 20.7], [0, 0, 1.0]])
    img, expected = _camera_image(CHARUCO, H, (1000, 800), 0.012)
    corners, ids, _, marker_ids = cv2.aruco.CharucoDetector(CHARUCO.cv_board()).detectBoard(img)
    assert len(marker_ids) == 44 and len(ids) == CHARUCO.n_corners
    ids = ids.ravel()
    assert np.abs(corners.reshape(-1, 2) - expected[ids]).max() < 0.3  # the detector's own refinement
    refined = cv2.cornerSubPix(img, corners.astype(np.float32), (5, 5), (-1, -1), SUBPIX).reshape(-1, 2)
    assert np.abs(refined - expected[ids]).max() < 0.05


def test_charuco_detected_through_homography():
    H = np.array([[0.55, 0.05, 40], [-0.03, 0.5, 60], [1e-5, 2e-5, 1]])
    img, expected = _camera_image(CHARUCO, H, (1100, 900), 0.012)
    corners, ids, _, _ = cv2.aruco.CharucoDetector(CHARUCO.cv_board()).detectBoard(img)
    assert len(ids) == CHARUCO.n_corners
    refined = cv2.cornerSubPix(img, corners.astype(np.float32), (5, 5), (-1, -1), SUBPIX).reshape(-1, 2)
    err = refined - expected[ids.ravel()]
    assert np.abs(err.mean(axis=0)).max() < 0.01  # no systematic offset: the pixel mapping is exact
    assert np.abs(err).max() < 0.1  # cornerSubPix's own bias on perspective-warped saddles is ~0.07 px


def test_chessboard_detected_through_homography():
    H = np.array([[0.25, 0.02, 40], [-0.01, 0.24, 60], [1e-5, 2e-5, 1]])
    img, expected = _camera_image(CHESS, H, (1100, 900), 0.025)
    ok, corners = cv2.findChessboardCornersSB(img, CHESS.inner_size, flags=cv2.CALIB_CB_ACCURACY)
    assert ok and len(corners) == CHESS.n_corners
    c = corners.reshape(-1, 2)
    # a 9x6 board (odd x even) has no 180-degree ambiguity in principle, but accept either corner order
    err = min(np.abs(c - expected).max(), np.abs(c[::-1] - expected).max())
    assert err < 0.05


def test_legacy_pattern_differs_and_is_detected_with_its_own_board():
    legacy = TargetSpec("charuco", (5, 4), 0.012, 0.009, "DICT_4X4_50", legacy=True)
    modern = TargetSpec("charuco", (5, 4), 0.012, 0.009, "DICT_4X4_50")
    a, _ = render_board(legacy)
    b, _ = render_board(modern)
    assert a.shape == b.shape and (a != b).any()  # even number of rows: the patterns differ
    img = cv2.resize(a, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    _, ids, _, _ = cv2.aruco.CharucoDetector(legacy.cv_board()).detectBoard(img)
    assert ids is not None and len(ids) == legacy.n_corners


# -- texture for the renderer -----------------------------------------------------------------------------------------
def test_board_reflectance_matches_texture_and_margin():
    ppm = exact_px_per_m(CHARUCO, 20000)
    tex = board_texture(CHARUCO, ppm)
    assert tex.dtype == np.float32 and not tex.flags.writeable
    assert tex.shape == (8 * 240, 11 * 240)
    rng = np.random.default_rng(3)
    r, c = rng.integers(0, tex.shape[0], 500), rng.integers(0, tex.shape[1], 500)
    centres = np.c_[(c + 0.5) / ppm, (r + 0.5) / ppm]  # texel centres in the board frame (origin: outer corner)
    assert np.allclose(board_reflectance(CHARUCO, centres, px_per_m=ppm), tex[r, c], rtol=0, atol=1e-9)
    assert np.array_equal(board_reflectance(CHARUCO, centres + 0.3 / ppm, px_per_m=ppm, interpolation="nearest"),
                          tex[r, c].astype(float))
    # step edges stay where the squares end: 0.5 exactly at a black/white boundary inside the board
    edge = np.array([[0.012, 0.006]])  # right edge of the top-left (black) square, a marker-free stretch
    assert board_reflectance(CHARUCO, edge, px_per_m=ppm)[0] == pytest.approx(0.5)
    # margin white, outside value beyond it, z column ignored
    pts = np.array([[-0.005, 0.05, 0.0], [0.05, 0.1, 0.0], [-0.02, 0.0, 1.0], [0.0005, 0.0005, 0.0]])
    out = board_reflectance(CHARUCO, pts, px_per_m=ppm, margin_m=0.01, outside=0.25)
    assert out.tolist() == [1.0, 1.0, 0.25, 0.0]
    assert board_extent_m(CHARUCO, 0.01) == pytest.approx((-0.01, -0.01, 0.142, 0.106))
    # chessboard: origin at the first inner corner, the outer top-left square is black
    assert board_reflectance(CHESS, np.array([[-0.02, -0.02], [0.005, -0.005]]), px_per_m=2000).tolist() == [0, 1]
    assert board_extent_m(CHESS) == pytest.approx((-0.025, -0.025, 0.225, 0.15))


def test_board_reflectance_bad_input():
    with pytest.raises(ValueError, match="shape"):
        board_reflectance(CHARUCO, np.zeros(3))
    with pytest.raises(ValueError, match="interpolation"):
        board_reflectance(CHARUCO, np.zeros((1, 2)), interpolation="cubic")


# -- TargetSpec -----------------------------------------------------------------------------------------------------
def test_object_points_match_opencv():
    assert np.allclose(CHARUCO.object_points(), CHARUCO.cv_board().getChessboardCorners(), atol=1e-12)
    assert CHARUCO.n_corners == 70 and CHARUCO.board_size_m == pytest.approx((0.132, 0.096))
    assert CHESS.object_points()[10].tolist() == pytest.approx([0.025, 0.025, 0.0])
    assert CHESS.squares_count == (10, 7) and CHESS.squares_origin_m == (-0.025, -0.025)


def test_dict_round_trip():
    for spec in (CHARUCO, CHESS, TargetSpec("charuco", (5, 4), 0.02, 0.015, "DICT_4X4_50", legacy=True)):
        assert TargetSpec.from_dict(spec.to_dict()) == spec


@pytest.mark.parametrize("kwargs, match", [
    (dict(type="aruco", squares=(5, 4), square_m=0.01), "type"),
    (dict(type="charuco", squares=(2, 4), square_m=0.01, marker_m=0.007, dictionary="DICT_4X4_50"), "at least 3"),
    (dict(type="chessboard", squares=(2, 5), square_m=0.01), "at least 3"),
    (dict(type="chessboard", squares=(4, 5.5), square_m=0.01), "two integers"),
    (dict(type="chessboard", squares=7, square_m=0.01), "two integers"),
    (dict(type="chessboard", squares=(True, 5), square_m=0.01), "two integers"),
    (dict(type="chessboard", squares=(4, 5), square_m=0.0), "square size"),
    (dict(type="chessboard", squares=(4, 5), square_m="0.01"), "square size"),
    (dict(type="chessboard", squares=(4, 5), square_m=float("nan")), "square size"),
    (dict(type="charuco", squares=(5, 4), square_m=0.01, marker_m=0.01, dictionary="DICT_4X4_50"), "marker size"),
    (dict(type="charuco", squares=(5, 4), square_m=0.01, marker_m=None, dictionary="DICT_4X4_50"), "marker size"),
    (dict(type="charuco", squares=(5, 4), square_m=0.01, marker_m=0.007, dictionary="DICT_9X9_1"), "dictionary"),
    (dict(type="charuco", squares=(11, 10), square_m=0.01, marker_m=0.007, dictionary="DICT_4X4_50"),
     "has 50 markers, the board needs 55"),
    (dict(type="chessboard", squares=(4, 5), square_m=0.01, marker_m=0.007), "ChArUco targets only"),
    (dict(type="chessboard", squares=(4, 5), square_m=0.01, legacy=True), "ChArUco targets only"),
    (dict(type="chessboard", squares=(4, 5), square_m=0.01, name=""), "name"),
])
def test_validation_errors(kwargs, match):
    with pytest.raises(ValueError, match=match):
        TargetSpec(**kwargs)


@pytest.mark.parametrize("d, match", [
    ({"type": "charuco", "squares": 11, "square_m": 0.01}, "squares: a list"),
    ({"type": "chessboard", "square_m": 0.01}, "inner_corners: missing"),
    ({"type": "chessboard", "inner_corners": [4, 5]}, "square_m: missing"),
    ({"type": "chessboard", "inner_corners": [4, 5], "square_m": 0.01, "colour": 1}, "colour: unknown field"),
    ({"type": "chessboard", "inner_corners": [4, 5], "square_m": 0.01, "format_version": 2}, "format_version"),
    ({"type": "disc"}, "type"),
    ([1, 2], "mapping"),
])
def test_from_dict_errors(d, match):
    with pytest.raises(ValueError, match=match):
        TargetSpec.from_dict(d)


_CHESS = {"type": "chessboard", "inner_corners": [9, 6], "square_m": 0.025}
_CHARUCO = {"type": "charuco", "squares": [11, 8], "square_m": 0.012, "marker_m": 0.009, "dictionary": "DICT_5X5_250"}


@pytest.mark.parametrize("d, field", [
    ({**_CHESS, "square_m": 10**400}, "square_m"),
    ({**_CHESS, "square_m": -10**30}, "square_m"),
    ({**_CHESS, "square_m": 0.5}, "square_m"),  # a 5 m board
    ({**_CHESS, "inner_corners": [10**7, 6]}, "inner_corners"),
    ({**_CHESS, "inner_corners": [9, 6e10]}, "inner_corners"),
    ({**_CHESS, "inner_corners": [9, 6, 3]}, "inner_corners"),
    ({**_CHESS, 1: "x"}, "1"),
    ({**_CHESS, "format_version": True}, "format_version"),
    ({**_CHESS, "legacy_pattern": True}, "legacy_pattern"),
    ({**_CHESS, "dictionary": "DICT_4X4_50"}, "dictionary"),
    ({**_CHESS, "name": None}, "name"),
    ({**_CHESS, "type": ["chessboard"]}, "type"),
    ({**_CHARUCO, "marker_m": 10**60}, "marker_m"),
    ({**_CHARUCO, "marker_m": float("nan")}, "marker_m"),
    ({**_CHARUCO, "dictionary": ["DICT_5X5_250"]}, "dictionary"),
    ({**_CHARUCO, "squares": [40, 40]}, "dictionary"),  # 800 markers for a dictionary of 250
    ({**_CHARUCO, "legacy_pattern": ""}, "legacy_pattern"),
    ({**_CHARUCO, "squares": "11x8"}, "squares"),
    ([_CHESS], None),
])
def test_target_errors_are_input_errors_naming_the_field(d, field):
    """docs/formats.md §7.1: every malformed target mapping raises InputError (a ValueError) naming its key."""
    from heartcv.tracker.files import InputError

    with pytest.raises(InputError) as err:
        TargetSpec.from_dict(d)
    assert err.value.field == field and err.value.path is None
    assert str(err.value).startswith(f"{field}: " if field else "target: ")

"""File I/O of the heartcv package: images, target files, rig files and the rig's COLMAP and Kalibr exports.

All reading and writing of ``heartcv/`` happens here, called from ``cli/`` (docs/style.md: pure cores, I/O at the
edge). Formats are documented in ``docs/formats.md``. Conventions:

- Built on :mod:`heartcv.tracker.files`, the one file-handling foundation (atomic writes, hashes, safe YAML and
  ``.npz`` reading with limits, output safety). Every write is atomic.
- Every problem with an input file raises :class:`~heartcv.tracker.files.InputError` (exported here under its old
  name :data:`HeartcvIOError`) naming the file and the field; the command line turns it into exit code 2.
- YAML files are written so that both a YAML library (PyYAML ``safe_load``) and OpenCV's ``cv2.FileStorage``
  read them (:func:`dump_yaml`); floats are written with Python's ``repr`` and read back exactly.

The module is split into sections with ``# ====`` headers. Other parts of heartcv (calibration, renderer) may
append their own clearly delimited sections at the end.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import logging
import math
import os
from pathlib import Path
import re

import numpy as np

from . import __version__
from .camera import Camera, Rig
from .targets import INCH_M, TargetSpec
from .tracker.files import (
    ArraySpec,
    InputError,
    atomic_path,
    check_format,
    dump_yaml,
    file_hash,
    get_field,
    get_matrix,
    plain,
    read_csv_table,
    read_npz,
    show,
    write_npz,
    write_yaml,
)
from .tracker.files import read_yaml as _read_yaml

log = logging.getLogger(__name__)

__all__ = [
    "HeartcvIOError", "atomic_path", "file_hash", "dump_yaml", "read_yaml", "write_yaml",
    "IMAGE_SUFFIXES", "read_image", "write_image", "list_image_folder", "natural_key", "sort_names", "pair_instants",
    "TARGET_FORMAT", "read_target", "write_target", "write_board_image",
    "RIG_FORMAT", "DIST_NAMES", "rig_to_dict", "rig_from_dict", "read_rig", "write_rig",
    "write_colmap", "colmap_camera", "write_kalibr", "kalibr_camchain",
    "VIDEO_SUFFIXES", "FrameSource", "open_frame_source", "camera_entries", "FrameReader", "read_timestamps",
    "PACKINGS", "unpack_views",
    "read_mask", "read_inputs_csv_columns",
]


# =====================================================================================================================
# Common: the foundation (heartcv.tracker.files) under the names this module has always exported
# =====================================================================================================================
#: The error of every reader: heartcv's one error type for input that failed validation (file and field)
HeartcvIOError = InputError
_plain = plain


def read_yaml(path, what: str = "YAML file"):
    """Parse a YAML file with the foundation's limits (:func:`heartcv.tracker.files.read_yaml`)."""
    return _read_yaml(path, what)


def _check_format(path, d, fmt, required=False):
    check_format(path, d, fmt, required)


def _read_typed_yaml(path, what: str, fmt, from_dict):
    """``from_dict(d)`` of a YAML file of format ``fmt``; the InputError of ``from_dict`` gets the file attached."""
    d = read_yaml(path, what)
    _check_format(path, d, fmt)
    try:
        return from_dict(d)
    except InputError as exc:
        raise exc.in_file(path) from None


# =====================================================================================================================
# Images
# =====================================================================================================================
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
_IMREAD = {"gray": "IMREAD_GRAYSCALE", "color": "IMREAD_COLOR", "unchanged": "IMREAD_UNCHANGED"}


def natural_key(name: str):
    """Sort key ordering embedded numbers by value (``img2`` before ``img10``), case-insensitively."""
    parts = re.split(r"(\d+)", name)
    return [(0, int(p), "") if p.isdigit() else (1, 0, p.lower()) for p in parts], name


_DECIMAL = re.compile(r"[+-]?\d+\.\d+")


def sort_names(names, stem=lambda n: n) -> list:
    """``names`` in frame order: by the value of the stems when every stem is a decimal number with a fractional
    part (times in seconds, as some recorders name frames: ``0.04`` before ``0.2``, where natural order would put
    ``0.2`` first), else in natural order (:func:`natural_key`; of a path's name). ``stem`` maps a name to its
    stem."""
    from decimal import Decimal

    def label(n):
        return natural_key(n.name if isinstance(n, Path) else str(n))

    names = list(names)
    if names and all(_DECIMAL.fullmatch(stem(n)) for n in names):
        return sorted(names, key=lambda n: (Decimal(stem(n)), label(n)))
    return sorted(names, key=label)


def _linked(keys) -> list:
    """Indices of the cameras linked to the first by shared keys (directly or through others)."""
    group, todo = {0}, [0]
    while todo:
        i = todo.pop()
        for j in range(len(keys)):
            if j not in group and keys[i] & keys[j]:
                group.add(j)
                todo.append(j)
    return sorted(group)


_LAST_NUMBER = re.compile(r"(\d+)(?!.*\d)")


def pair_instants(names, files):
    """Pair the cameras' image files into instants.

    ``files`` holds one list of image paths per camera (``names``). The same file stem is the same instant. Where
    that links no camera to the first (files named per camera: ``left-1095.png`` / ``right-1095.png``,
    ``f7_L_0100.png`` / ``f7_R_0100.png``), the last number in each stem is the instant, provided it is unique
    within every camera and links them all.

    Returns
    -------
    instants : list of str      instant names in frame order (:func:`sort_names`; the stems; numbered: the first
                                camera's stem that holds the number, else the first other camera's)
    per_cam : list of dict      per camera, instant name -> path
    by : str                    ``"stem"`` or ``"number"``

    Raises
    ------
    ValueError
        Neither links the cameras: the message names the unlinked cameras and an example stem of each.
    """
    stems = [{p.stem: p for p in fs} for fs in files]
    linked = _linked([set(d) for d in stems])
    if len(linked) == len(stems) or len(stems) < 2:
        return sort_names(set().union(*stems)), stems, "stem"
    numbered = []
    for d in stems:
        keyed = {}
        for stem, path in d.items():
            m = _LAST_NUMBER.search(stem)
            if m is None or int(m.group(1)) in keyed:
                keyed = None
                break
            keyed[int(m.group(1))] = (stem, path)
        numbered.append(keyed)
    if all(k is not None for k in numbered) and len(_linked([set(k) for k in numbered])) == len(stems):
        keys = sorted(set().union(*numbered))
        label = {k: next(d[k][0] for d in numbered if k in d) for k in keys}
        per_cam = [{label[k]: d[k][1] for k in d} for d in numbered]
        return [label[k] for k in keys], per_cam, "number"

    def example(j):
        return repr(min(stems[j], key=natural_key)) if stems[j] else "no files"

    apart = [j for j in range(len(stems)) if j not in linked and stems[j]]
    shown = ", ".join(f"{names[j]} ({example(j)})" for j in apart[:4])
    raise ValueError(f"camera(s) {shown} share no file name (stem) with {names[0]} ({example(0)}), nor a frame number "
                     "(the last number in the names, unique in each camera): an instant is the same stem in every "
                     "camera's folder; rename the files so that an instant has one name (e.g. 0001.png in each "
                     "folder)")


def list_image_folder(folder) -> list[Path]:
    """The image files (PNG, JPEG, TIFF, BMP; any case of suffix) of a folder, naturally sorted by name.

    Hidden files (names starting with '.', e.g. the temporary files of an interrupted write) and sub-folders
    are skipped. An empty list if the folder holds no images; HeartcvIOError if it is not a folder.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise HeartcvIOError(folder, "no such folder" if not folder.exists() else "not a folder")
    files = [p for p in folder.iterdir()
             if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".") and p.is_file()]
    return sort_names(files, stem=lambda p: p.stem)


def read_image(path, mode: str = "gray", expected_size=None) -> np.ndarray:
    """Read an image file.

    Parameters
    ----------
    mode : {'gray', 'color', 'unchanged'}
        8-bit grayscale (H, W), 8-bit BGR (H, W, 3), or the file's own depth and channels.
    expected_size : (width, height), optional
        Reject an image of another size.

    Raises
    ------
    HeartcvIOError
        Missing or empty file, unreadable or corrupt data (including PNG and JPEG files cut short, which
        OpenCV would otherwise decode partially), or the wrong size. The message names the file.
    """
    import cv2

    if mode not in _IMREAD:
        raise ValueError(f"mode: one of {sorted(_IMREAD)} expected, got {mode!r}")
    path = Path(path)
    if not path.is_file():
        raise HeartcvIOError(path, "no such image file" if not path.exists() else "not a file (image expected)")
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise HeartcvIOError(path, f"cannot read image ({exc.strerror})") from None
    if data.size == 0:
        raise HeartcvIOError(path, "empty file (image expected)")
    raw = data[:16].tobytes()
    if raw.startswith(b"\x89PNG\r\n\x1a\n") and b"IEND" not in data[-16:].tobytes():
        raise HeartcvIOError(path, "truncated PNG image (no IEND chunk)")
    if raw.startswith(b"\xff\xd8") and b"\xff\xd9" not in data[-64:].tobytes():
        raise HeartcvIOError(path, "truncated JPEG image (no end-of-image marker)")
    img = cv2.imdecode(data, getattr(cv2, _IMREAD[mode]))
    if img is None or img.size == 0:
        raise HeartcvIOError(path, "not a readable image (corrupt or unsupported format)")
    if expected_size is not None and (img.shape[1], img.shape[0]) != tuple(expected_size):
        raise HeartcvIOError(path, f"image is {img.shape[1]}x{img.shape[0]} px, "
                                   f"{expected_size[0]}x{expected_size[1]} expected")
    return img


def write_image(path, image: np.ndarray) -> None:
    """Write an image (format from the suffix: PNG, JPEG, TIFF, BMP) atomically with OpenCV."""
    import cv2

    path = Path(path)
    if path.suffix.lower() not in IMAGE_SUFFIXES:
        raise ValueError(f"{path}: image suffix one of {IMAGE_SUFFIXES} expected")
    ok, buf = cv2.imencode(path.suffix.lower(), np.asarray(image))
    if not ok:
        raise ValueError(f"{path}: OpenCV could not encode an image of shape {np.shape(image)}")
    with atomic_path(path) as tmp:
        buf.tofile(tmp)


# =====================================================================================================================
# Calibration targets (heartcv.target v1) and their printable images
# =====================================================================================================================
TARGET_FORMAT = ("heartcv.target", 1)


def write_board_image(png_path, pdf_path, image: np.ndarray, dpi: float, size_m) -> None:
    """Write a printable target image as PNG and/or PDF, each atomically.

    Parameters
    ----------
    png_path, pdf_path : path or None
        Files to write (either may be None).
    image : ndarray of shape (H, W), uint8
        From :func:`heartcv.targets.render_board`.
    dpi : float
        Pixels per inch of ``image`` (``px_per_m * 0.0254``). The PNG carries it in its ``pHYs`` chunk, which
        stores whole pixels per metre: ``round(dpi / 0.0254)``.
    size_m : (width, height)
        Physical size of the whole image in metres (``(W, H) / px_per_m``); the PDF page has exactly this size
        and the image fills it, so printing at 100 % ("actual size") reproduces the squares' nominal size.
    """
    image = np.asarray(image)
    if image.ndim != 2 or image.dtype != np.uint8:
        raise ValueError(f"image: 2-D uint8 expected, got {image.dtype} of shape {image.shape}")
    w_m, h_m = (float(v) for v in size_m)
    px_per_m = float(dpi) / INCH_M
    if abs(image.shape[1] - w_m * px_per_m) > 0.5 or abs(image.shape[0] - h_m * px_per_m) > 0.5:
        raise ValueError(f"image of {image.shape[1]}x{image.shape[0]} px is not {w_m} x {h_m} m at {dpi} dpi")
    if png_path is not None:
        from PIL import Image, PngImagePlugin

        info = PngImagePlugin.PngInfo()
        info.add_text("Software", f"heartcv {__version__}")  # marks the file as heartcv's (is_heartcv_file)
        with atomic_path(png_path, suffix=".png") as tmp:
            Image.fromarray(image).save(tmp, format="PNG", dpi=(dpi, dpi), optimize=True, pnginfo=info)
    if pdf_path is not None:
        from matplotlib.figure import Figure

        fig = Figure(figsize=(w_m / INCH_M, h_m / INCH_M))
        ax = fig.add_axes((0, 0, 1, 1))
        ax.set_axis_off()
        # interpolation 'none': the PDF embeds the pixels unresampled and the printer scales them to the page
        ax.imshow(image, cmap="gray", vmin=0, vmax=255, interpolation="none", aspect="auto",
                  extent=(0, image.shape[1], image.shape[0], 0))
        with atomic_path(pdf_path, suffix=".pdf") as tmp:
            fig.savefig(tmp, format="pdf", metadata={"Creator": f"heartcv {__version__}", "Producer": None,
                                                     "CreationDate": None})


def write_target(path, spec: TargetSpec, *, png=None, pdf=None, px_per_m=None, image_size=None,
                 producer: str = "heartcv target") -> None:
    """Write a target file (``heartcv.target`` v1, YAML) atomically.

    ``png``/``pdf`` are the printable images' paths (written beside the YAML, stored relative to its folder);
    ``px_per_m`` and ``image_size`` (W, H pixels) describe them. Layout: ``docs/formats.md``, target file.
    """
    path = Path(path)
    d = spec.to_dict()
    d["heartcv_version"] = __version__
    d["producer"] = producer
    d["board_size_m"] = list(spec.board_size_m)
    if png is not None or pdf is not None:
        if px_per_m is None or image_size is None:
            raise ValueError("write_target: px_per_m and image_size describe the images and are required with them")
        w, h = (int(v) for v in image_size)
        n = spec.square_m * px_per_m
        cols, rows = spec.squares_count
        image = {"dpi": float(px_per_m) * INCH_M, "px_per_m": float(px_per_m), "square_px": int(round(n)),
                 "size_px": [w, h], "page_size_m": [w / px_per_m, h / px_per_m],
                 "margin_m": (w - cols * round(n)) / 2 / px_per_m}
        for key, p in (("png", png), ("pdf", pdf)):
            if p is not None:
                image[key] = os.path.relpath(Path(p).resolve(), path.resolve().parent)
        d["image"] = image
    header = (f"heartcv calibration target ({spec.type}); print the PDF at 100 % (actual size, no fit-to-page)\n"
              f"and measure a square: it must be {spec.square_m * 1e3:g} mm. Format: docs/formats.md (target file).")
    write_yaml(path, d, header)


_TARGET_IMAGE_NUMBERS = {"dpi": 0, "px_per_m": 0, "square_px": 0, "margin_m": None}
_TARGET_IMAGE_PAIRS = ("size_px", "page_size_m")


def _check_target_image(image) -> None:
    """A target file's ``image`` block (docs/formats.md §7.3; informative): known keys, finite positive numbers."""
    if not isinstance(image, dict):
        raise InputError(None, "a mapping expected", "image")
    known = set(_TARGET_IMAGE_NUMBERS) | set(_TARGET_IMAGE_PAIRS) | {"png", "pdf"}
    for key, v in image.items():
        if key not in known:
            raise InputError(None, f"unknown key (known: {sorted(known)})", f"image.{key}")
        if key in ("png", "pdf"):
            if not isinstance(v, str) or not v:
                raise InputError(None, f"a file name expected, got {show(v)}", f"image.{key}")
            continue
        values = v if key in _TARGET_IMAGE_PAIRS else [v]
        if (key in _TARGET_IMAGE_PAIRS and (not isinstance(v, list) or len(v) != 2)) or not all(
                _is_num(x) and (x > 0 or (key == "margin_m" and x >= 0)) for x in values):
            want = "two finite positive numbers" if key in _TARGET_IMAGE_PAIRS else (
                "a finite number >= 0" if key == "margin_m" else "a finite positive number")
            raise InputError(None, f"{want} expected, got {show(v)}", f"image.{key}")


def read_target(path) -> TargetSpec:
    """Read and validate a target file; HeartcvIOError naming the file and the bad field."""
    def from_dict(d):
        if "image" in d:
            _check_target_image(d["image"])
        spec = TargetSpec.from_dict(d)
        size = d.get("board_size_m")
        if size is not None and not (isinstance(size, list) and len(size) == 2 and all(_is_num(v) for v in size)
                                     and np.allclose(size, spec.board_size_m, rtol=1e-6, atol=0)):
            raise InputError(None, f"[{spec.board_size_m[0]:g}, {spec.board_size_m[1]:g}] (the board the other keys "
                                   f"describe) expected, got {show(size)}", "board_size_m")
        return spec

    return _read_typed_yaml(path, "target file", TARGET_FORMAT, from_dict)


# =====================================================================================================================
# Rig files (heartcv.rig v1)
# =====================================================================================================================
RIG_FORMAT = ("heartcv.rig", 1)
DIST_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4", "tau_x", "tau_y")
_CAMERA_KEYS = ("name", "image_size", "distortion_model", "dist_names", "K", "dist", "cam_from_rig")
_RIG_DERIVED = ("format", "format_version", "heartcv_version", "rig_frame", "baselines_m", "cameras")


def rig_to_dict(rig: Rig) -> dict:
    """The rig file's content as plain data (the layout of ``docs/formats.md``, rig file).

    Rig-level ``rig.meta`` entries are written at the top level, ``rig.meta['cameras'][name]`` entries inside
    that camera's entry; ``heartcv_version`` is the running version, ``rig_frame`` and ``baselines_m`` are
    derived from the cameras.
    """
    meta = dict(rig.meta)
    cam_meta = meta.pop("cameras", None) or {}
    if not isinstance(cam_meta, dict):
        raise ValueError("rig.meta['cameras']: a mapping camera name -> per-camera data expected")
    unknown = sorted(set(cam_meta) - set(rig.names))
    if unknown:
        raise ValueError(f"rig.meta['cameras']: no camera named {unknown} in the rig ({rig.names})")
    for k in ("format", "format_version", "heartcv_version", "rig_frame", "baselines_m"):
        meta.pop(k, None)
    c0 = rig.cameras[0]
    d = {"format": RIG_FORMAT[0], "format_version": RIG_FORMAT[1], "heartcv_version": __version__,
         "rig_frame": c0.name if np.array_equal(c0.cam_from_rig, np.eye(4)) else "custom"}
    d.update(meta)
    d["baselines_m"] = rig.baselines()
    cams = []
    for c in rig.cameras:
        e = {"name": c.name, "image_size": [c.width, c.height], "distortion_model": "opencv",
             "dist_names": list(DIST_NAMES[:c.dist.size]), "K": c.K, "dist": c.dist, "cam_from_rig": c.cam_from_rig}
        extra = dict(cam_meta.get(c.name, {}))
        clash = sorted(set(extra) & set(_CAMERA_KEYS))
        if clash:
            raise ValueError(f"rig.meta['cameras'][{c.name!r}]: reserved keys {clash}")
        e.update(extra)
        cams.append(e)
    d["cameras"] = cams
    return _plain(d)


def rig_from_dict(d: dict) -> Rig:
    """Inverse of :func:`rig_to_dict`; ValueError naming the bad field. ``baselines_m`` is ignored (derived)."""
    if not isinstance(d, dict):
        raise InputError(None, "rig: a mapping expected")
    if d.get("format", RIG_FORMAT[0]) != RIG_FORMAT[0]:
        raise InputError(None, f"format: {RIG_FORMAT[0]!r} expected, got {d.get('format')!r}")
    if d.get("format_version", RIG_FORMAT[1]) != RIG_FORMAT[1]:
        raise InputError(None, f"format_version: {RIG_FORMAT[1]} supported, got {d.get('format_version')!r}")
    entries = d.get("cameras")
    if not isinstance(entries, list) or not entries:
        raise InputError(None, "cameras: a non-empty list of cameras expected")
    cameras, cam_meta = [], {}
    for i, e in enumerate(entries):
        where = f"cameras[{i}]"
        if not isinstance(e, dict):
            raise InputError(None, f"{where}: a mapping expected")
        missing = [k for k in ("name", "image_size", "K", "dist", "cam_from_rig") if k not in e]
        if missing:
            raise InputError(None, f"{where}: missing {missing}")
        name = e["name"]
        if not isinstance(name, str) or not name:
            raise InputError(None, f"cameras[{i}].name: a non-empty string expected, got {str(name)[:40]!r}")
        where = f"cameras[{i}] ({name})"
        if e.get("distortion_model", "opencv") != "opencv":
            raise InputError(None, f"{where}.distortion_model: 'opencv' expected, got {e['distortion_model']!r}")
        size = e["image_size"]
        if not (isinstance(size, list) and len(size) == 2
                and all(isinstance(v, int) and not isinstance(v, bool) and 0 < v <= 65536 for v in size)):
            raise InputError(None, f"{where}.image_size: [width, height] expected, got {size!r}")
        # plausibility: focal lengths and principal points within 1e6 px, coefficients within 1e4, poses within 1 km
        K = _matrix(e["K"], (3, 3), f"{where}.K", 1e6)
        dist = _matrix(e["dist"], None, f"{where}.dist", 1e4)
        T = _matrix(e["cam_from_rig"], (4, 4), f"{where}.cam_from_rig", 1e3)
        try:
            cameras.append(Camera(name, size[0], size[1], K, dist, T))
        except (ValueError, TypeError, OverflowError) as exc:
            raise InputError(None, f"{where}: {exc}") from None
        names = e.get("dist_names")
        if names is not None and (not isinstance(names, list) or names != list(DIST_NAMES[:dist.size])):
            raise InputError(None, f"{where}.dist_names: {list(DIST_NAMES[:dist.size])} expected for {dist.size} "
                             f"coefficients (OpenCV order), got {e['dist_names']!r}")
        extra = {k: v for k, v in e.items() if k not in _CAMERA_KEYS}
        _check_residuals(extra, where)
        if extra:
            cam_meta[name] = extra
    try:
        rig = Rig(tuple(cameras))
    except ValueError as exc:
        raise InputError(None, f"cameras: {exc}") from None
    meta = {k: v for k, v in d.items() if k not in _RIG_DERIVED}
    if "heartcv_version" in d:
        meta["heartcv_version"] = d["heartcv_version"]
    _check_residuals(meta, "rig")
    if "target" in meta:
        try:
            TargetSpec.from_dict(meta["target"])
        except ValueError as exc:
            raise InputError(None, f"target.{exc}") from None
    frame = d.get("rig_frame")
    if frame is not None and frame != "custom":
        if frame not in rig.names:
            raise InputError(None, f"rig_frame: a camera name or 'custom' expected, got {frame!r}")
        if np.abs(rig[frame].cam_from_rig - np.eye(4)).max() > 1e-12:
            raise InputError(None, f"rig_frame: {frame}'s cam_from_rig is not the identity; write 'custom'")
    if cam_meta:
        meta["cameras"] = cam_meta
    return Rig(rig.cameras, meta)


def _matrix(v, shape, where, max_abs=None) -> np.ndarray:
    """A finite matrix field of a rig file (:func:`heartcv.tracker.files.get_matrix`), at most ``max_abs`` in size."""
    a = get_matrix(v, shape, None, where)
    if max_abs is not None and np.abs(a).max(initial=0) > max_abs:
        raise InputError(None, f"values beyond +-{max_abs:g}: not plausible", where)
    return a


def _is_num(v) -> bool:
    """A finite int or float, not a bool (an integer beyond the float range is not one)."""
    if not isinstance(v, (int, float)) or isinstance(v, bool):
        return False
    try:
        return math.isfinite(float(v))
    except OverflowError:
        return False


def _check_residuals(d: dict, where: str):
    if "rms_px" in d and not (_is_num(d["rms_px"]) and d["rms_px"] >= 0):
        raise InputError(None, f"{where}.rms_px: a number >= 0 expected, got {d['rms_px']!r}")
    if "per_view_errors" in d:
        v = d["per_view_errors"]
        if not isinstance(v, list) or not all(x is None or (_is_num(x) and x >= 0) for x in v):
            raise InputError(None, f"{where}.per_view_errors: a list of numbers >= 0 (or null) expected")
    if "std" in d:
        std = d["std"]
        ok = isinstance(std, dict) and all(
            _is_num(x) or (isinstance(x, list) and all(_is_num(y) for y in x)) for x in std.values())
        if not ok:
            raise InputError(None, f"{where}.std: a mapping of numbers or lists of numbers expected")


def write_rig(path, rig: Rig) -> None:
    """Write a rig file (``heartcv.rig`` v1, YAML) atomically; layout in ``docs/formats.md``."""
    header = ("heartcv rig: cameras as OpenCV (pinhole + distortion, pixel (0, 0) = centre of the top-left pixel);\n"
              "cam_from_rig maps rig-frame points (m) into the camera: x_cam = R x_rig + t. docs/formats.md, rig file.")
    write_yaml(path, rig_to_dict(rig), header)


def read_rig(path) -> Rig:
    """Read and validate a rig file; HeartcvIOError naming the file and the bad field."""
    return _read_typed_yaml(path, "rig file", RIG_FORMAT, rig_from_dict)


# =====================================================================================================================
# Exports: COLMAP (cameras.txt, rigs.txt) and Kalibr (camchain YAML)
# =====================================================================================================================
# COLMAP text model, as read by ReadCamerasText / ReadRigsText in colmap/src/colmap/scene/reconstruction_io_text.cc
# and described in colmap/doc/format.rst ("rigs.txt", "cameras.txt"; COLMAP >= 3.12, pycolmap 4):
#   cameras.txt: CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]
#       OPENCV      = fx fy cx cy k1 k2 p1 p2
#       FULL_OPENCV = fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6   (radial (1 + k1 r2 + k2 r4 + k3 r6) / (1 + k4 r2 + ...))
#   rigs.txt:    RIG_ID NUM_SENSORS REF_SENSOR_TYPE REF_SENSOR_ID then, per other sensor,
#                SENSOR_TYPE SENSOR_ID HAS_POSE [QW QX QY QZ TX TY TZ]  (sensor_from_rig, Hamilton quaternion;
#                the reference sensor defines the rig frame: identity sensor_from_rig)
# Pixel convention: COLMAP puts the centre of the top-left pixel at (0.5, 0.5), OpenCV at (0, 0), so
# cx_colmap = cx_opencv + 0.5 (same for cy); focal lengths and distortion carry over unchanged (colmap/colmap
# issue #2587 and the FAQ entry of pull request #4566).
_COLMAP_HEADER_CAMERAS = ("# Camera list with one line of data per camera:\n"
                          "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n")
_COLMAP_HEADER_RIGS = ("# Rig calib list with one line of data per calib:\n"
                       "#   RIG_ID, NUM_SENSORS, REF_SENSOR_TYPE, REF_SENSOR_ID, SENSORS[] as (SENSOR_TYPE, SENSOR_ID, "
                       "HAS_POSE, [QW, QX, QY, QZ, TX, TY, TZ])\n")


def colmap_camera(cam: Camera) -> tuple[str, list[float]]:
    """COLMAP model name and parameters of a camera (COLMAP pixel convention: principal point + 0.5).

    No coefficients -> ``PINHOLE``; 4 or 5 with k3 = 0 -> ``OPENCV``; otherwise ``FULL_OPENCV``. ValueError
    for what COLMAP cannot represent: a skewed K, or non-zero thin-prism (s1..s4) or tilt (tau_x, tau_y)
    coefficients.
    """
    K, d = cam.K, cam.dist
    if K[0, 1] != 0:
        raise ValueError(f"{cam.name}: K has skew {K[0, 1]}; COLMAP's camera models have none")
    if d.size > 8 and np.any(d[8:] != 0):
        bad = {n: float(v) for n, v in zip(DIST_NAMES[8:], d[8:]) if v != 0}
        raise ValueError(f"{cam.name}: COLMAP's OPENCV/FULL_OPENCV models have no thin-prism or tilt coefficients; "
                         f"non-zero {bad}")
    pp = [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5]
    if d.size == 0:
        return "PINHOLE", pp
    full = np.zeros(8)
    full[:min(d.size, 8)] = d[:8]
    if d.size <= 5 and full[4] == 0:
        return "OPENCV", pp + list(full[:4])
    return "FULL_OPENCV", pp + list(full)


def _quaternion_wxyz(R) -> list[float]:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()  # scipy: scalar last
    q = np.array([w, x, y, z])
    return list(q if q[0] >= 0 else -q)


def _fmt(v: float) -> str:
    return repr(float(v))


def write_colmap(folder, rig: Rig, *, first_camera_id: int = 1, rig_id: int = 1) -> dict:
    """Write ``cameras.txt`` and ``rigs.txt`` of the rig into ``folder`` (created), each atomically.

    Camera ids are ``first_camera_id + idx`` in rig order; one rig whose reference sensor is camera 0, the other
    cameras posed by ``cam_from_cam0`` (COLMAP's ``sensor_from_rig``). Returns ``{camera name: camera id}``.
    Add ``frames.txt``, ``images.txt`` and ``points3D.txt`` of your own to make a full COLMAP model.
    """
    folder = Path(folder)
    lines_cam, ids = [], {}
    for idx, cam in enumerate(rig.cameras):
        model, params = colmap_camera(cam)
        cid = first_camera_id + idx
        ids[cam.name] = cid
        lines_cam.append(" ".join([str(cid), model, str(cam.width), str(cam.height)] + [_fmt(p) for p in params]))
    ref = rig.cameras[0]
    sensors = []
    for idx in range(1, len(rig.cameras)):
        T = rig.cam_from_cam(idx, 0)
        pose = _quaternion_wxyz(T[:3, :3]) + list(T[:3, 3])
        sensors.append(f"CAMERA {first_camera_id + idx} 1 " + " ".join(_fmt(v) for v in pose))
    rig_line = " ".join([str(rig_id), str(len(rig)), "CAMERA", str(ids[ref.name])] + sensors)
    names = ", ".join(f"{n} = {i}" for n, i in ids.items())
    with atomic_path(folder / "cameras.txt") as tmp:
        tmp.write_text(_COLMAP_HEADER_CAMERAS + f"# Number of cameras: {len(rig)} (heartcv: {names})\n"
                       + "\n".join(lines_cam) + "\n", encoding="utf-8")
    with atomic_path(folder / "rigs.txt") as tmp:
        tmp.write_text(_COLMAP_HEADER_RIGS + "# Number of rigs: 1\n" + rig_line + "\n", encoding="utf-8")
    return ids


# Kalibr camchain (ethz-asl/kalibr wiki, "YAML formats"): camN: camera_model pinhole, intrinsics [fu, fv, pu, pv],
# distortion_model radtan with distortion_coeffs [k1, k2, r1, r2], resolution [w, h], rostopic, and for N >= 1
# T_cn_cnm1 = T_c(n)_c(n-1) (takes camera n-1 coordinates to camera n). Kalibr's pixel convention is OpenCV's
# (no 0.5 shift).
def kalibr_camchain(rig: Rig, rostopics: dict | None = None) -> dict:
    """The Kalibr camchain of the rig as plain data (cameras in rig order as cam0..camN)."""
    from .calibration_rig import kalibr_limitation

    why = kalibr_limitation(rig)
    if why is not None:
        raise ValueError(why)
    out = {}
    for idx, cam in enumerate(rig.cameras):
        K, d = cam.K, cam.dist
        coeffs = np.zeros(4)
        coeffs[:min(d.size, 4)] = d[:4]
        e = {"camera_model": "pinhole", "intrinsics": [K[0, 0], K[1, 1], K[0, 2], K[1, 2]],
             "distortion_model": "radtan", "distortion_coeffs": coeffs, "resolution": [cam.width, cam.height],
             "rostopic": (rostopics or {}).get(cam.name, f"/{cam.name}/image_raw")}
        if idx > 0:
            e["T_cn_cnm1"] = rig.cam_from_cam(idx, idx - 1)
        out[f"cam{idx}"] = e
    return _plain(out)


def write_kalibr(path, rig: Rig, rostopics: dict | None = None) -> None:
    """Write the rig as a Kalibr camchain YAML atomically (:func:`kalibr_camchain`)."""
    names = ", ".join(f"cam{i} = {c.name}" for i, c in enumerate(rig.cameras))
    write_yaml(path, kalibr_camchain(rig, rostopics), f"Kalibr camchain written by heartcv {__version__} ({names})")


# =====================================================================================================================
# -- scenes and rendered sequences (heartcv.scene v1, heartcv.render_truth v1; the renderer's section)
# =====================================================================================================================
SCENE_FORMAT = ("heartcv.scene", 1)
RENDER_TRUTH_FORMAT = ("heartcv.render_truth", 1)
__all__ += ["SCENE_FORMAT", "RENDER_TRUTH_FORMAT", "read_scene", "scene_file_path", "encode_png",
            "write_inputs_csv", "read_inputs_csv", "write_render_truth", "read_render_truth"]


def read_scene(path):
    """Read and validate a scene file (``heartcv.render.scene``); HeartcvIOError naming the file and the field."""
    from .render.scene import scene_from_dict

    return _read_typed_yaml(path, "scene file", SCENE_FORMAT, scene_from_dict)


def scene_file_path(scene_path, relative) -> Path:
    """A path named in a scene file, resolved against the scene file's folder (absolute paths unchanged)."""
    p = Path(os.path.expanduser(str(relative)))
    return p if p.is_absolute() else Path(scene_path).resolve().parent / p


def encode_png(image) -> bytes:
    """PNG bytes of an 8- or 16-bit image, RGB (H, W, 3) or gray (H, W) (picklable: used by render workers)."""
    import cv2

    img = np.asarray(image)
    if img.ndim == 3:
        img = img[..., ::-1]  # RGB -> OpenCV's BGR
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img))
    if not ok:
        raise ValueError(f"OpenCV could not encode an image of shape {img.shape} as PNG")
    return buf.tobytes()


def write_inputs_csv(path, columns, values, header=None) -> None:
    """``inputs.csv`` of a sequence folder: optional ``#`` comment lines, one header row of column names, then
    one row per frame (``repr`` precision). Written atomically."""
    values = np.asarray(values, float)
    if values.ndim != 2 or values.shape[1] != len(columns):
        raise ValueError(f"inputs: shape (K, {len(columns)}) expected, got {values.shape}")
    lines = [f"# {h}" for h in (header or "").splitlines()]
    lines.append(",".join(columns))
    lines += [",".join(repr(float(v)) for v in row) for row in values]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")


def read_inputs_csv(path) -> tuple[list, np.ndarray]:
    """``(columns, values (K, n))`` of an ``inputs.csv`` (comment lines skipped; every column numeric)."""
    cols, n = read_inputs_csv_columns(path)
    columns = list(cols)
    return columns, (np.stack([cols[c] for c in columns], axis=1) if columns else np.zeros((n, 0)))


def write_render_truth(path, arrays: dict, meta: dict) -> None:
    """The truth of a render (``heartcv.render_truth`` v1): arrays plus a ``meta_json`` entry, written
    atomically (layout: docs/formats.md §11)."""
    write_npz(path, RENDER_TRUTH_FORMAT, arrays, meta)


_FLAG = "biu"
_RENDER_TRUTH_SCHEMA = {
    # cameras (NC), boards views (NB), corners (C); sequence frames (T), vertices (V), points (P), dots (D)
    "K": ArraySpec("f", ("NC", 3, 3)), "dist": ArraySpec("f", ("NC", None)),
    "cam_from_world": ArraySpec("f", ("NC", 4, 4)), "cam_from_rig": ArraySpec("f", ("NC", 4, 4)),
    "image_size": ArraySpec("iuf", (2,)),
    "world_from_board": ArraySpec("f", ("NB", 4, 4)), "board_from_world": ArraySpec("f", ("NB", 4, 4)),
    "cam_from_board": ArraySpec("f", ("NB", "NC", 4, 4)), "object_points": ArraySpec("f", ("C", 3)),
    "corners_uv": ArraySpec("f", ("NB", "NC", "C", 2), finite="nan"),
    "corners_visible": ArraySpec(_FLAG, ("NB", "NC", "C")), "incidence_deg": ArraySpec("f", ("NB", "NC"), finite="nan"),
    "partial": ArraySpec(_FLAG, ("NB",)),
    "times": ArraySpec("f", ("T",)), "theta": ArraySpec("f", ("T", 5)), "inputs": ArraySpec("f", ("T", "NU")),
    "translation": ArraySpec("f", ("T", 3)), "world_from_patch": ArraySpec("f", (4, 4)),
    "faces": ArraySpec("iu", ("F", 3)), "reference_vertices": ArraySpec("f", ("V", 3)),
    "vertex_material": ArraySpec("f", ("V", 2)), "vertex_in_patch": ArraySpec(_FLAG, ("V",)),
    "vertex_positions": ArraySpec("f", ("T", "V", 3)), "point_param": ArraySpec("f", ("P", 3)),
    "point_positions": ArraySpec("f", ("T", "P", 3)), "fiducial_material": ArraySpec("f", ("D", 2)),
    "fiducial_positions": ArraySpec("f", ("T", "D", 3)), "instrument_tip": ArraySpec("f", ("T", 3), finite="nan"),
    "instrument_present": ArraySpec(_FLAG, ("T",)), "instrument_mask": ArraySpec("u", ("T", "NC", None, None)),
}
# optional, each bounded: 1e7 for pixels, seconds and pascals, 1e3 m for lengths (docs/formats.md §11)
_RENDER_TRUTH_SCHEMA = {k: ArraySpec(v.kinds, v.shape, v.finite, required=False, max_abs=None if v.kinds != "f" else (
    1e7 if k in ("K", "corners_uv", "times", "theta", "inputs", "incidence_deg", "dist") else 1e3))
                        for k, v in _RENDER_TRUTH_SCHEMA.items()}


def _check_rigid(T, path, field):
    """Rigid transforms (..., 4, 4): orthonormal rotation with determinant 1, last row 0 0 0 1."""
    R = T[..., :3, :3]
    err = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max(initial=0)
    if err > 1e-6 or np.abs(np.linalg.det(R) - 1).max(initial=0) > 1e-6 or \
            np.abs(T[..., 3, :] - [0, 0, 0, 1]).max(initial=0) > 0:
        raise InputError(path, "rigid transforms (rotation, translation, last row 0 0 0 1) expected", field)


def read_render_truth(path, require=(), what: str | None = None) -> tuple[dict, dict]:
    """``(arrays, meta)`` of a render truth file, validated against docs/formats.md §11 (dtypes, shapes that agree,
    finite values, face indices inside the mesh, rigid poses, camera matrices); InputError naming the file and the
    array. ``require`` names the arrays the caller needs (``what`` says for what, in the message)."""
    data, meta = read_npz(path, RENDER_TRUTH_FORMAT, _RENDER_TRUTH_SCHEMA)
    kind = get_field(meta, "kind", "str", path, default=None, prefix="meta.")
    if kind is not None and kind not in ("calibration", "sequence"):
        raise InputError(path, f"'calibration' or 'sequence' expected, got {kind[:40]!r}", "meta.kind")
    missing = [k for k in require if k not in data]
    if missing:
        raise InputError(path, f"missing arrays {missing} ({what or 'needed here'})")
    if "K" in data:
        K = data["K"]
        if (K[:, 0, 0] <= 0).any() or (K[:, 1, 1] <= 0).any() or np.abs(K[:, 2] - [0, 0, 1]).max(initial=0) > 0 \
                or np.abs(K[:, 1, 0]).max(initial=0) > 0:
            raise InputError(path, "camera matrices [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0 expected",
                             "K")
    for key in ("cam_from_world", "cam_from_rig", "world_from_board", "board_from_world", "world_from_patch"):
        if key in data:
            _check_rigid(data[key], path, key)
    if "camera_names" in meta:
        get_field(meta, "camera_names", "str-list", path, prefix="meta.")
    if "faces" in data:
        V = data["reference_vertices"].shape[0] if "reference_vertices" in data else 0
        f = data["faces"]
        if f.size and (f.min() < 0 or f.max() >= V):
            raise InputError(path, f"vertex indices 0..{V - 1} expected", "faces")
    if "times" in data and (data["times"].size < 1 or (np.diff(data["times"]) <= 0).any()):
        raise InputError(path, "at least one frame, strictly increasing times expected", "times")
    if "image_size" in data and (data["image_size"] < 1).any():
        raise InputError(path, "positive [width, height] expected", "image_size")
    if "inputs" in data:
        names = get_field(meta, "input_names", "str-list", path, default=None, prefix="meta.")
        if names is not None and len(names) != data["inputs"].shape[1]:
            raise InputError(path, f"{data['inputs'].shape[1]} names expected", "meta.input_names")
    return data, meta


# =====================================================================================================================
# Image sequences: one folder of images or one video per camera (heartcv measure; docs/formats.md §11.2, §13)
# =====================================================================================================================
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".mpg", ".mpeg", ".wmv", ".webm")

#: How the views of a stereo (or multi-view) camera can be packed into one frame (``heartcv measure --packed``):
#: equal columns left to right, equal bands top to bottom, or interleaved rows (an interlaced frame whose fields
#: are the views: view c holds rows c, c + n, c + 2n, ...). View c is the rig's c-th camera.
PACKINGS = ("side-by-side", "top-bottom", "rows")


def unpack_views(frame: np.ndarray, packing: str, n_views: int = 2) -> list:
    """The ``n_views`` views packed into one frame (:data:`PACKINGS`), each a contiguous copy, in packing order.

    Raises
    ------
    ValueError
        An unknown packing, fewer than two views, or a frame that does not divide into ``n_views`` views of one
        size (the message gives the frame's size).
    """
    if packing not in PACKINGS:
        raise ValueError(f"packing: one of {PACKINGS} expected, got {packing!r}")
    n = int(n_views)
    if n < 2:
        raise ValueError(f"n_views: at least 2 expected, got {n_views}")
    h, w = frame.shape[:2]
    axis_len = w if packing == "side-by-side" else h
    if axis_len % n:
        what = "columns" if packing == "side-by-side" else "rows"
        raise ValueError(f"the frame is {w}x{h} px: its {axis_len} {what} do not split into {n} {packing} views "
                         "of one size")
    m = axis_len // n
    if packing == "side-by-side":
        views = [frame[:, c * m:(c + 1) * m] for c in range(n)]
    elif packing == "top-bottom":
        views = [frame[c * m:(c + 1) * m] for c in range(n)]
    else:
        views = [frame[c::n] for c in range(n)]
    return [np.ascontiguousarray(v) for v in views]


@dataclass(frozen=True)
class FrameSource:
    """The cameras and instants of a recorded or rendered sequence folder.

    Attributes
    ----------
    folder : Path
    kind : {'images', 'video'}
    camera_names : tuple of str          sub-folder names (images) or video stems, in natural order
    frame_names : tuple of str           instants: file stems shared across cameras (images) or ``frameNNNNNN``
    files : tuple                        per camera, per instant, the image Path or None where that camera has
                                         no file for the instant (images); per camera ``(video path,)`` (video)
    fps : float or None                  the videos' frame rate when their containers state one
    videos : tuple of VideoInfo or None  per camera, what :func:`heartcv.video.check_videos` found by decoding its
                                         whole video (frame count, size, rate, each frame's container time);
                                         None for image folders
    packing : str or None                one of :data:`PACKINGS` when every frame holds all the cameras' views
                                         (one image folder or one video, named in every camera's ``files``)
    start : int                          the recording's index of instant 0 (a segment of it, :meth:`segment`;
                                         frame ``k`` of a video is its decoded frame ``start + k``)
    """

    folder: Path
    kind: str
    camera_names: tuple
    frame_names: tuple
    files: tuple
    fps: float | None = None
    videos: tuple | None = None
    packing: str | None = None
    start: int = 0

    def segment(self, start: int, count: int | None = None) -> "FrameSource":
        """The instants ``start`` to ``start + count`` (default: to the end) of this source as a source of their
        own: instant ``k`` of the segment is instant ``start + k`` of this one. ValueError when ``start`` is not
        an instant of this source or ``count`` is below 1."""
        start = int(start)
        if not 0 <= start < self.n_frames:
            raise ValueError(f"start: an instant in 0..{self.n_frames - 1} expected, got {start}")
        end = self.n_frames if count is None else start + int(count)
        if count is not None and int(count) < 1:
            raise ValueError(f"count: at least 1 expected, got {count}")
        files = tuple(tuple(f[start:end]) for f in self.files) if self.kind == "images" else self.files
        return replace(self, frame_names=tuple(self.frame_names[start:end]), files=files, start=self.start + start)

    @property
    def n_frames(self) -> int:
        return len(self.frame_names)

    @property
    def n_cameras(self) -> int:
        return len(self.camera_names)

    def missing(self) -> list:
        """``[(camera name, frame name)]`` of the instants a camera has no image for."""
        if self.kind != "images":
            return []
        files = self.files[:1] if self.packing else self.files
        names = ("all cameras (packed)",) if self.packing else self.camera_names
        return [(c, n) for c, fs in zip(names, files) for n, f in zip(self.frame_names, fs) if f is None]


def camera_entries(folder: Path):
    """The cameras of a sequence or calibration folder: ``(cams, videos)`` with ``cams`` the ``[(name, image
    files)]`` of its sub-folders that hold images (natural order; hidden and empty ones left out) and ``videos``
    its video files (``VIDEO_SUFFIXES``); HeartcvIOError when it holds both kinds."""
    subdirs = sorted((p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")),
                     key=lambda p: natural_key(p.name))
    cams = [(d.name, list_image_folder(d)) for d in subdirs]
    cams = [(n, fs) for n, fs in cams if fs]
    videos = sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES),
                    key=lambda p: natural_key(p.name))
    if cams and videos:
        raise HeartcvIOError(folder, f"holds both image folders ({', '.join(c[0] for c in cams)}) and videos "
                                     f"({', '.join(v.name for v in videos)}); one kind expected")
    return cams, videos


def open_frame_source(folder, *, cameras=None, max_missing_fraction=0.1, cameras_source=None,
                      packing=None) -> FrameSource:
    """List the cameras and instants of a sequence folder.

    Parameters
    ----------
    folder : path
        One sub-folder of images per camera (the same file stem in two folders is the same instant) or one
        video file per camera (the same frame index is the same instant).
    cameras : sequence of str, optional
        Use these cameras, in this order (e.g. the rig file's names); default: all, in natural name order.
    cameras_source : path, optional
        Where ``cameras`` come from (the rig file), named in the message when one of them is absent.
    max_missing_fraction : float
        A camera may lack an image for at most this fraction of the instants, and for one instant in any case
        (each such image is reported by
        :meth:`FrameSource.missing` and read as missing); more, and the cameras are taken to have different
        frame counts, which is an error.
    packing : str, optional
        One of :data:`PACKINGS`: the folder holds one source (one sub-folder of images, one video, or its own
        images) whose every frame packs the views of all ``cameras`` (default two, ``cam0`` and ``cam1``), in
        their order; :class:`FrameReader` splits the frames (:func:`unpack_views`).

    Every video is decoded once here (:func:`heartcv.video.check_videos`), before any frame is processed: a
    video that cannot be opened, is truncated or corrupt, changes its frame size or has timestamps that go
    backwards is refused now, naming the file, and the frame counts compared are the decoded ones.

    Raises
    ------
    HeartcvIOError
        Not a folder, fewer than two cameras, a named camera absent, a video that fails
        :func:`heartcv.video.probe_video`, or cameras with different frame counts (the counts are named).
    """
    from .video import check_videos

    folder = Path(folder)
    if not folder.is_dir():
        raise HeartcvIOError(folder, "no such folder" if not folder.exists() else "not a folder")
    cams, videos = camera_entries(folder)
    if packing is not None:
        return _open_packed(folder, cams, videos, cameras, packing)
    entries = [(n, fs) for n, fs in cams] if cams else [(v.stem, [v]) for v in videos]
    found = [e[0] for e in entries]
    if cameras is not None:
        missing = [c for c in cameras if c not in found]
        if missing:
            named = f" named in {cameras_source}" if cameras_source is not None else ""
            raise HeartcvIOError(folder, f"no images or video for camera(s) {missing}{named}; found {found or 'none'}")
        entries = [next(e for e in entries if e[0] == c) for c in cameras]
    if len(entries) < 2:
        raise HeartcvIOError(folder, f"{len(entries)} camera(s) found ({found}); at least 2 expected (one "
                                     "sub-folder of images or one video file per camera)")
    names = [e[0] for e in entries]
    if cams:
        try:
            instants, per_cam, by = pair_instants(names, [fs for _, fs in entries])
        except ValueError as exc:
            raise HeartcvIOError(folder, str(exc)) from None
        if by == "number":
            log.info("%s: the cameras' files share no name; instants paired by the last number in the names (%s)",
                     folder, ", ".join(f"{n} {min(d.values(), key=lambda q: natural_key(q.stem)).stem!r}"
                                       for n, d in zip(names, per_cam) if d))
        counts = [len(d) for d in per_cam]
        allowed = max(1, int(max_missing_fraction * len(instants)))
        if min(counts) < len(instants) - allowed:
            raise HeartcvIOError(folder, "cameras with different frame counts: " + ", ".join(
                f"{n} {c}" for n, c in zip(names, counts)) + f" ({len(instants)} instants in all)")
        files = tuple(tuple(d.get(i) for i in instants) for d in per_cam)
        return FrameSource(folder, "images", tuple(names), tuple(instants), files)
    infos = check_videos([path for _, (path,) in entries])
    counts, rates = [i.n_frames for i in infos], [i.fps or 0.0 for i in infos]
    if len(set(counts)) > 1:
        raise HeartcvIOError(folder, "cameras with different frame counts: " + ", ".join(
            f"{n} {c}" for n, c in zip(names, counts)))
    stated = [(n, r) for n, r in zip(names, rates) if r > 0]
    if stated and max(r for _, r in stated) > 1.01 * min(r for _, r in stated):
        raise HeartcvIOError(folder, "cameras' videos at different frame rates (" + ", ".join(
            f"{n} {r:g} fps" for n, r in stated) + f") with {counts[0]} frames each: their frame k are not one instant "
            "(give each camera's video at one rate, or image folders with timestamps.csv)")
    fps = rates[0] if rates and rates[0] > 0 and all(abs(r - rates[0]) < 1e-6 * rates[0] for r in rates) else None
    return FrameSource(folder, "video", tuple(names), tuple(f"frame{k:06d}" for k in range(counts[0])),
                       tuple((e[1][0],) for e in entries), fps, tuple(infos))


def _open_packed(folder: Path, cams, videos, cameras, packing) -> FrameSource:
    """:func:`open_frame_source` of a folder whose one source packs every camera's view into each frame."""
    from .video import check_videos

    if packing not in PACKINGS:
        raise ValueError(f"packing: one of {PACKINGS} expected, got {packing!r}")
    names = tuple(cameras) if cameras is not None else ("cam0", "cam1")
    if len(names) < 2:
        raise HeartcvIOError(folder, f"{len(names)} camera(s) ({list(names)}) to unpack from {packing} frames; at "
                                     "least 2 expected")
    own = list_image_folder(folder) if not cams and not videos else []
    sources = [f"{n}/" for n, _ in cams] + [v.name for v in videos] + (["its own images"] if own else [])
    if len(sources) != 1:
        raise HeartcvIOError(folder, f"holds {len(sources)} image sources ({', '.join(sources) or 'none'}); packed "
                                     f"{packing} frames are read from one sub-folder of images or one video holding "
                                     "all the views")
    C = len(names)
    if videos:
        (info,) = check_videos(videos)
        fps = info.fps if info.fps and info.fps > 0 else None
        return FrameSource(folder, "video", names, tuple(f"frame{k:06d}" for k in range(info.n_frames)),
                           ((videos[0],),) * C, fps, (info,) * C, packing)
    files = tuple(cams[0][1] if cams else own)
    return FrameSource(folder, "images", names, tuple(p.stem for p in files), (files,) * C, packing=packing)


class FrameReader:
    """Read the instants of a :class:`FrameSource` in order, all cameras at once (threads for image files).

    Iterating yields ``(k, images, problems)``: ``images`` one array per camera (8-bit, gray or BGR per
    ``mode``) or None where that camera's image is missing, unreadable, corrupt or of the wrong size, and
    ``problems`` the messages (each naming the file) for those. Use as a context manager (videos are closed).
    Videos are read with :class:`heartcv.video.VideoReader` (frame ``k`` is the ``k``-th decoded frame); a
    source whose videos were not checked yet (``source.videos`` None) is checked with
    :func:`heartcv.video.check_videos` on entering, before any frame is read. A packed source
    (``source.packing``) is read once per instant and split into the cameras' views (:func:`unpack_views`); a
    frame that does not split, or whose views do not have the expected sizes, is a problem of every camera.

    Parameters
    ----------
    sizes : sequence of (width, height), optional
        Expected image size per camera; other sizes are reported as problems.
    frames : sequence of int, optional
        Instants to read (increasing); default all.
    """

    def __init__(self, source: FrameSource, *, mode="gray", sizes=None, frames=None, workers=2):
        self.source = source
        self.mode = mode
        self.sizes = list(sizes) if sizes is not None else [None] * source.n_cameras
        self.frames = list(range(source.n_frames)) if frames is None else [int(k) for k in frames]
        self.workers = max(1, int(workers))
        self._videos = None
        self._pool = None

    def __enter__(self):
        from concurrent.futures import ThreadPoolExecutor

        if self.source.kind == "video":
            from .video import VideoReader, check_videos

            files = self.source.files[:1] if self.source.packing else self.source.files
            if self.source.videos is None:
                check_videos([f[0] for f in files])
            self._videos = [VideoReader(f[0]) for f in files]
        self._pool = ThreadPoolExecutor(self.workers)
        return self

    def __exit__(self, *exc):
        if self._videos:
            for v in self._videos:
                v.close()
        if self._pool:
            self._pool.shutdown()
        return False

    def _read_file(self, c, path, k=None):
        if path is None:
            name = self.source.frame_names[k] if k is not None else "?"
            # (the folder, not a file name: instants paired by number are named after another camera's files)
            return None, f"{self.source.folder / self.source.camera_names[c]}: no image for instant {name!r}"
        try:
            return read_image(path, self.mode, self.sizes[c]), None
        except HeartcvIOError as exc:
            return None, str(exc)

    def _read_video(self, c, k):
        video = self._videos[c]
        k = self.source.start + k
        try:
            img = video.read(k, gray=self.mode == "gray")
        except HeartcvIOError as exc:
            return None, str(exc)
        if img is None:
            return None, f"{video.path}: frame {k} cannot be decoded"
        size = self.sizes[c]
        if size is not None and (img.shape[1], img.shape[0]) != tuple(size):
            return None, f"{video.path}: frame {k} is {img.shape[1]}x{img.shape[0]} px, {size[0]}x{size[1]} expected"
        return img, None

    def read_packed(self, k):
        """``(frame, problem)``: the whole frame of instant ``k`` of a packed source, unsplit and unchecked (None
        and the message naming the file where it is missing or does not decode)."""
        if self._pool is None:
            raise RuntimeError("FrameReader: use it as a context manager")
        if not self.source.packing:
            raise ValueError("read_packed: the source is not packed")
        if self.source.kind == "images":
            path = self.source.files[0][k]
            if path is None:
                return None, f"{self.source.folder}: no packed image for instant {self.source.frame_names[k]}"
            try:
                return read_image(path, self.mode), None
            except HeartcvIOError as exc:
                return None, str(exc)
        video = self._videos[0]
        k = self.source.start + k
        try:
            img = video.read(k, gray=self.mode == "gray")
        except HeartcvIOError as exc:
            return None, str(exc)
        return (img, None) if img is not None else (None, f"{video.path}: frame {k} cannot be decoded")

    def _read_unpacked(self, k):
        C = self.source.n_cameras
        frame, problem = self.read_packed(k)
        if frame is None:
            return [None] * C, [problem]
        where = self.source.files[0][k] if self.source.kind == "images" else \
            f"{self.source.files[0][0]}: frame {self.source.start + k}"
        try:
            views = unpack_views(frame, self.source.packing, C)
        except ValueError as exc:
            return [None] * C, [f"{where}: {exc}"]
        h, w = views[0].shape[:2]
        bad = [c for c in range(C) if self.sizes[c] is not None and (w, h) != tuple(self.sizes[c])]
        if bad:
            expected = ", ".join(f"{self.sizes[c][0]}x{self.sizes[c][1]}" for c in bad)
            return [None] * C, [f"{where}: its {self.source.packing} views are {w}x{h} px, {expected} expected"]
        return views, []

    def read(self, k):
        """``(images, problems)`` of instant ``k``."""
        if self._pool is None:
            raise RuntimeError("FrameReader: use it as a context manager")
        if self.source.packing:
            return self._read_unpacked(k)
        C = self.source.n_cameras
        if self.source.kind == "images":
            res = list(self._pool.map(self._read_file, range(C), [self.source.files[c][k] for c in range(C)],
                                      [k] * C))
        else:
            res = list(self._pool.map(self._read_video, range(C), [k] * C))
        return [r[0] for r in res], [r[1] for r in res if r[1]]

    def __iter__(self):
        """Instants in order; the next instant's images are decoded while the caller works on the current one
        (image folders; a video is read in sequence)."""
        if self.source.kind != "images" or self._pool is None:
            for k in self.frames:
                images, problems = self.read(k)
                yield k, images, problems
            return
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(1) as ahead:
            pending = ahead.submit(self.read, self.frames[0]) if self.frames else None
            for i, k in enumerate(self.frames):
                images, problems = pending.result()
                if i + 1 < len(self.frames):
                    pending = ahead.submit(self.read, self.frames[i + 1])
                yield k, images, problems


def read_timestamps(path, frame_names) -> np.ndarray:
    """Frame times (K,) in seconds from ``timestamps.csv``: a header row with a ``time_s`` column (and an optional
    ``frame`` column of file stems), one row per instant; times are shifted to start at 0. HeartcvIOError for a
    count or name mismatch or times that do not increase."""
    cols, _ = read_inputs_csv_columns(path, numeric_except=("frame",))
    if "time_s" not in cols:
        raise HeartcvIOError(path, f"a 'time_s' column expected, got {list(cols)}", "time_s")
    t = np.asarray(cols["time_s"], float)
    if t.size != len(frame_names):
        raise HeartcvIOError(path, f"{t.size} rows for the sequence's {len(frame_names)} instants (one row per "
                                   "instant of the recording, --start and --frames notwithstanding)", "time_s")
    if "frame" in cols:
        names = [str(n) for n in cols["frame"]]
        if names != [str(n) for n in frame_names]:
            bad = next(i for i, (a, b) in enumerate(zip(names, frame_names)) if a != str(b))
            raise HeartcvIOError(path, f"row {bad + 1} names frame {names[bad]!r}, the sequence has "
                                       f"{frame_names[bad]!r} there", "frame")
    if not np.isfinite(t).all() or (np.diff(t) <= 0).any():
        raise HeartcvIOError(path, "finite and strictly increasing values expected", "time_s")
    return t - t[0]


def read_inputs_csv_columns(path, numeric_except=()) -> tuple[dict, int]:
    """``({column: values}, n_rows)`` of a comma-separated table with ``#`` comment lines and a header row;
    columns named in ``numeric_except`` are kept as strings, the others parsed as finite floats
    (:func:`heartcv.tracker.files.read_csv_table`)."""
    return read_csv_table(path, numeric_except, "table")


def read_mask(path, expected_size=None) -> np.ndarray:
    """A region-of-interest mask image as bool (H, W): nonzero pixels are inside."""
    img = read_image(path, "gray", expected_size)
    mask = img > 0
    if not mask.any():
        raise HeartcvIOError(path, "the mask is empty (no nonzero pixel)")
    return mask

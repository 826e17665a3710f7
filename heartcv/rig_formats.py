"""Rigs calibrated elsewhere -> :class:`heartcv.camera.Rig` (``heartcv rig import``), and the rig of a pre-rectified
stereo pair (``heartcv rig rectified``).

Readers (I/O: they read foreign files; each problem raises :class:`~heartcv.tracker.files.InputError` naming the
file and the field):

- ``opencv``: OpenCV FileStorage (YAML, XML or JSON; ``camera_matrix`` + ``distortion_coefficients`` of one
  camera, or ``M1 D1 M2 D2`` + ``R T`` as OpenCV's ``samples/cpp/stereo_calib.cpp`` writes them, where
  cam1_from_cam0 = [R | T]); also the plain-YAML ``{rows, cols, data}`` layout of ROS camera_info files;
- ``kalibr``: a Kalibr camchain (``cam0``, ``cam1``, ...: pinhole, radtan, ``T_cn_cnm1`` = cam_n_from_cam_{n-1});
- ``colmap``: a COLMAP text model's ``cameras.txt`` + ``rigs.txt`` (COLMAP >= 3.12; pixel centre at (0.5, 0.5));
- ``caliscope``: ``camera_array.toml`` or ``config.toml`` (x_cam = R x_world + t; rig frame = caliscope's world);
- ``text``: plain-text matrices in camera order (K 3x3, a distortion row, a 4x4 or 3x4 pose cam_from_cam0), or a
  folder in the Hamlyn datasets' layout (``*.left.intrinsic.txt``, ``*.l2r.4x4``, ...).

Pure conversions: :func:`colmap_to_opencv` (COLMAP camera models -> K and OpenCV coefficients),
:func:`orthonormalise` (rotations printed to few decimals), :func:`convert_units` (the units rule),
:func:`rectified_rig`. The conventions of each source are documented in docs/cli.md (``heartcv rig import``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import math
from pathlib import Path
import re

import numpy as np

from .camera import DIST_SIZES, Camera, Rig, pose_matrix
from .io import rig_from_dict, rig_to_dict
from .tracker.files import LIMITS, InputError, file_hash, get_matrix, parse_yaml, read_text, show

__all__ = [
    "FORMATS", "UNITS", "MAX_SPAN_M", "ORTHO_TOL", "COLMAP_MODELS", "ImportedRig", "detect_format", "plan_import",
    "read_foreign", "finish_import", "colmap_to_opencv", "orthonormalise", "rig_span", "units_message",
    "convert_units", "rename_cameras", "rectified_rig", "side_warnings",
]

FORMATS = ("opencv", "kalibr", "colmap", "caliscope", "text")
#: --units: factor from the source's length unit to metres
UNITS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}
#: without --units, a rig whose camera centres lie further apart than this is refused (units message)
MAX_SPAN_M = 2.0
#: rotations with max |R^T R - I| up to ORTHO_TOL are projected onto SO(3); beyond it they are refused
ORTHO_TOL = 1e-4
#: below this deviation a rotation is kept bit for bit (it is a rotation to double precision)
_EXACT_TOL = 1e-12
_TEXT_BYTES = 1 << 20
_MAX_CAMERAS = 256
_MAX_SIDE = 65536


@dataclass(frozen=True)
class ImportedRig:
    """What a reader found, before the units rule and renaming (:func:`finish_import`).

    Attributes
    ----------
    rig : Rig
        Cameras with translations in the source's units.
    source_format : str
    files : tuple of Path
        The files read, in order.
    corrections : tuple of dict
        Rotations re-orthonormalised: ``file``, ``field``, ``deviation`` (max |R^T R - I|), ``angle_deg``.
    translations : (path, field)
        Where the translations come from (named by the units message).
    warnings : tuple of str
        Things skipped (e.g. caliscope cameras marked ``ignore``).
    rig_frame : str
        What the rig frame is, in words.
    """

    rig: Rig
    source_format: str
    files: tuple
    corrections: tuple = ()
    translations: tuple = (None, None)
    warnings: tuple = ()
    rig_frame: str = "the first camera"


# =====================================================================================================================
# Format detection and the files an import reads
# =====================================================================================================================
_HAMLYN_K = re.compile(r"^(?P<prefix>.*)\.(?P<name>[^.\s]+)\.intrinsic\.txt$")


def detect_format(path) -> str:
    """The format of one input (a file or a folder), from its name and content; InputError naming it and listing
    the formats when none fits."""
    p = Path(path)
    if p.is_dir():
        if (p / "cameras.txt").is_file():
            return "colmap"
        if any(_HAMLYN_K.match(q.name) for q in _listdir(p)):
            return "text"
        raise InputError(p, "a folder with neither cameras.txt (COLMAP) nor *.NAME.intrinsic.txt files (text); "
                            f"formats: {', '.join(FORMATS)}", "format")
    if p.is_file() and _binary(p):
        raise _unrecognised(p, " (a binary file)")
    text = read_text(p, "calibration file", LIMITS["yaml_bytes"])
    if p.name in ("cameras.txt", "rigs.txt"):
        return "colmap"
    if p.suffix.lower() == ".toml":
        return "caliscope"
    if _is_filestorage(text):
        return "opencv"
    if _numeric_text(text):
        return "text"
    if p.suffix.lower() in (".yaml", ".yml", ".json"):
        d = parse_yaml(text, p)
        if isinstance(d, dict):
            if str(d.get("format", "")).startswith("heartcv."):
                raise InputError(p, f"already a heartcv file ({d['format']}); nothing to import", "format")
            if any(re.fullmatch(r"cam\d+", str(k)) and isinstance(v, dict) and "intrinsics" in v
                   for k, v in d.items()):
                return "kalibr"
            if "camera_matrix" in d or "M1" in d or ("R" in d and "T" in d):
                return "opencv"
    raise _unrecognised(p)


def _listdir(folder: Path) -> list[Path]:
    try:
        return sorted(folder.iterdir())
    except OSError as exc:
        raise InputError(folder, f"cannot list the folder ({exc.strerror or exc})", "FILE") from None


def _unrecognised(p, why: str = "") -> InputError:
    return InputError(p, f"not recognised as any of the formats heartcv imports{why} (opencv: camera_matrix or "
                         "M1/D1/M2/D2 + R/T; kalibr: cam0.intrinsics; colmap: cameras.txt; caliscope: .toml; text: "
                         f"rows of numbers); formats: {', '.join(FORMATS)}; pass --format if it is one of them",
                      "format")


def _binary(p: Path) -> bool:
    """Whether a file's first 8 KiB hold a NUL byte or are not UTF-8."""
    import codecs

    try:
        with open(p, "rb") as f:
            head = f.read(8192)
    except OSError as exc:
        raise InputError(p, f"cannot read ({exc.strerror or exc})") from None
    try:
        codecs.getincrementaldecoder("utf-8")().decode(head, final=False)
    except UnicodeDecodeError:
        return True
    return b"\x00" in head


def _is_filestorage(text: str) -> bool:
    """OpenCV's own YAML header (``%YAML:1.0``), its matrix tag, or its XML root."""
    head = text.lstrip()[:4096]
    return head.startswith("%YAML:") or "!!opencv-matrix" in text or "<opencv_storage" in head


def _numeric_text(text: str) -> bool:
    rows = [ln.split("#", 1)[0].replace(",", " ").split() for ln in text.splitlines()[:64]]
    rows = [r for r in rows if r]
    if not rows:
        return False
    try:
        [float(x) for r in rows for x in r]
    except ValueError:
        return False
    return True


def plan_import(paths, fmt: str | None = None) -> tuple[str, list[Path]]:
    """The format and the files an import will read (folders expanded), without parsing them, so that the outputs
    can be checked against every input before any work.

    Parameters
    ----------
    paths : list of path
        The FILE arguments.
    fmt : str, optional
        One of :data:`FORMATS`; detected from each input (all must agree) when None.
    """
    paths = [Path(p) for p in paths]
    if not paths:
        raise InputError(None, "at least one file expected", "FILE")
    if fmt is None:
        found = {p: detect_format(p) for p in paths}
        kinds = sorted(set(found.values()))
        if len(kinds) > 1:
            listing = ", ".join(f"{p} ({k})" for p, k in found.items())
            raise InputError(paths[0], f"the files are of different formats: {listing}; give one rig's files", "format")
        fmt = kinds[0]
    elif fmt not in FORMATS:
        raise InputError(None, f"one of {FORMATS} expected, got {fmt!r}", "--format")
    if fmt == "colmap":
        return fmt, _colmap_files(paths)
    if fmt == "text" and len(paths) == 1 and paths[0].is_dir():
        return fmt, _hamlyn_files(paths[0])
    for p in paths:
        if p.is_dir():
            raise InputError(p, f"a folder; {fmt} files expected", "FILE")
    if fmt in ("kalibr", "caliscope") and len(paths) > 1:
        raise InputError(paths[1], f"{fmt}: one file holds the whole rig; got {len(paths)} files", "FILE")
    if fmt == "opencv" and len(paths) > 3:
        raise InputError(paths[3], "opencv: at most 3 files (two cameras' intrinsics and the extrinsics R, T)", "FILE")
    return fmt, paths


def _colmap_files(paths) -> list[Path]:
    """[cameras.txt, rigs.txt (when there is one)] of a model folder, or of the files given (a file not named
    rigs.txt is the cameras file; the missing one is looked for beside the other)."""
    if len(paths) == 1 and paths[0].is_dir():
        folder = paths[0]
        cams, rigs = folder / "cameras.txt", folder / "rigs.txt"
    else:
        if len(paths) > 2 or any(p.is_dir() for p in paths):
            raise InputError(paths[0], "COLMAP: one model folder, or its cameras.txt (and rigs.txt), expected", "FILE")
        named = [p for p in paths if p.name == "rigs.txt"]
        others = [p for p in paths if p.name != "rigs.txt"]
        if len(named) > 1 or len(others) > 1:
            raise InputError(paths[0], "COLMAP: one cameras file and one rigs.txt expected", "FILE")
        rigs = named[0] if named else others[0].parent / "rigs.txt"
        cams = others[0] if others else rigs.parent / "cameras.txt"
    return [cams] + ([rigs] if rigs.exists() else [])


def _hamlyn_files(folder: Path) -> list[Path]:
    """The files of a folder in the Hamlyn layout, in camera order: ``P.left.intrinsic.txt``,
    ``P.left.distortion.txt``, ``P.right.intrinsic.txt``, ``P.right.distortion.txt``, ``P.l2r.4x4``."""
    found = [m for m in (_HAMLYN_K.match(q.name) for q in _listdir(folder)) if m]
    prefixes = sorted({m["prefix"] for m in found})
    if len(prefixes) != 1:
        raise InputError(folder, f"*.NAME.intrinsic.txt files with {len(prefixes)} different prefixes "
                                 f"({', '.join(prefixes)}); give the files in camera order instead", "FILE")
    prefix = prefixes[0]
    names = [m["name"] for m in found]
    if len(names) == 1:
        order = names
    elif sorted(names) == ["left", "right"]:
        order = ["left", "right"]
    else:
        raise InputError(folder, f"intrinsics of cameras {names}: a folder is read in the Hamlyn layout (left, right, "
                                 f"{prefix}.l2r.4x4); give the files in camera order instead", "FILE")
    files = []
    for name in order:
        files.append(folder / f"{prefix}.{name}.intrinsic.txt")
        dist = folder / f"{prefix}.{name}.distortion.txt"
        if dist.exists():
            files.append(dist)
        if name == "right":
            pose = folder / f"{prefix}.l2r.4x4"
            if not pose.exists():
                raise InputError(pose, "no such file: the right camera's pose (right_from_left, 4x4) is missing",
                                 "pose")
            files.append(pose)
    return files


# =====================================================================================================================
# Pure conversions
# =====================================================================================================================
#: COLMAP camera models heartcv converts exactly, and their number of parameters
COLMAP_MODELS = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8, "FULL_OPENCV": 12}


def colmap_to_opencv(model: str, params) -> tuple[np.ndarray, np.ndarray]:
    """K (OpenCV pixel convention) and OpenCV distortion coefficients of a COLMAP camera.

    COLMAP puts the centre of the top-left pixel at (0.5, 0.5), OpenCV at (0, 0): ``cx = cx_colmap - 0.5``.
    COLMAP's SIMPLE_RADIAL (``f cx cy k``) and RADIAL (``f cx cy k1 k2``) are OpenCV's model with
    ``(k1, k2, p1, p2) = (k, 0, 0, 0)`` and ``(k1, k2, 0, 0)``; OPENCV and FULL_OPENCV carry OpenCV's coefficients
    in OpenCV's order (colmap/src/colmap/sensor/models.h). PINHOLE models give no coefficients.

    Raises
    ------
    InputError
        (without a file) for another model or a wrong number of parameters.
    """
    if model not in COLMAP_MODELS:
        raise InputError(None, f"camera model {model}: not supported; heartcv converts {', '.join(COLMAP_MODELS)} "
                               "exactly to OpenCV's model (fisheye and other models have no exact equivalent)", "MODEL")
    p = [float(v) for v in params]
    if len(p) != COLMAP_MODELS[model]:
        raise InputError(None, f"{model} has {COLMAP_MODELS[model]} parameters, got {len(p)}", "PARAMS")
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx = fy = p[0]
        cx, cy, extra = p[1], p[2], p[3:]
    else:
        fx, fy, cx, cy = p[:4]
        extra = p[4:]
    K = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
    if model in ("SIMPLE_PINHOLE", "PINHOLE"):
        dist = np.zeros(0)
    elif model == "SIMPLE_RADIAL":
        dist = np.array([extra[0], 0.0, 0.0, 0.0])
    elif model == "RADIAL":
        dist = np.array([extra[0], extra[1], 0.0, 0.0])
    else:
        dist = np.array(extra)
    return K, dist


def orthonormalise(R, path=None, field: str | None = None) -> tuple[np.ndarray, dict | None]:
    """A rotation matrix, projected onto SO(3) when it was printed with few decimals.

    ``d = max |R^T R - I|``. Up to 1e-12 R is returned unchanged; up to :data:`ORTHO_TOL` (1e-4: six printed
    decimals give ~1e-6) it is replaced by its nearest rotation ``U V^T`` (SVD ``R = U S V^T``, the orthogonal
    polar factor) and the correction is returned: ``{file, field, deviation: d, angle_deg}``, the angle being the
    largest angle between a column of R and the same column of the projection. Beyond, or with det R <= 0, it
    raises InputError naming the file and field.
    """
    R = np.asarray(R, float)
    if R.shape != (3, 3) or not np.isfinite(R).all():
        raise InputError(path, f"a finite 3x3 rotation expected, got shape {R.shape}", field)
    det = float(np.linalg.det(R))
    if det <= 0:
        raise InputError(path, f"not a rotation: det R = {det:.6g} (a reflection or a singular matrix)", field)
    dev = float(np.abs(R.T @ R - np.eye(3)).max())
    if dev <= _EXACT_TOL:
        return R, None
    if dev > ORTHO_TOL:
        raise InputError(path, f"not a rotation: max |R^T R - I| = {dev:.3g} > {ORTHO_TOL:g} (rotations printed to 6 "
                               "decimals are re-orthonormalised; this one is too far from a rotation)", field)
    U, _, Vt = np.linalg.svd(R)
    Q = U @ Vt
    cols = R / np.linalg.norm(R, axis=0)
    sin = np.linalg.norm(np.cross(cols.T, Q.T), axis=1)
    angle = float(np.degrees(np.arctan2(sin, np.sum(cols * Q, axis=0))).max())
    return Q, {"file": None if path is None else str(path), "field": field, "deviation": dev, "angle_deg": angle}


def rig_span(rig: Rig) -> tuple[float, str | None]:
    """Largest distance between two camera centres (the rig's units) and the pair (``'a-b'``; None for one
    camera)."""
    best, pair = 0.0, None
    for key, d in rig.baselines().items():
        if pair is None or d > best:
            best, pair = d, key
    return best, pair


def units_message(span: float, pair: str | None = None) -> str:
    """The refusal of a rig that spans more than :data:`MAX_SPAN_M` without --units."""
    where = f" ({pair})" if pair else ""
    metres = f" (or --units m if the rig really spans {span:.3g} m)" if span <= 1000 else ""
    return (f"baseline {span:.3g} m{where}: translations look like millimetres; pass --units mm{metres}. A file of "
            "OpenCV's stereo_calib.cpp holds T in board squares: multiply it by the square size first")


def convert_units(rig: Rig, units: str | None, path=None, field: str | None = None) -> tuple[Rig, dict]:
    """The rig with its translations in metres, and a record of the conversion.

    With ``units`` (``'m'``, ``'cm'``, ``'mm'``) every translation is multiplied by :data:`UNITS`; without,
    translations are taken as metres and a rig whose camera centres lie more than :data:`MAX_SPAN_M` apart is
    refused (InputError naming ``path`` and ``field``, :func:`units_message`).
    """
    span, pair = rig_span(rig)
    if units is None:
        if span > MAX_SPAN_M:
            raise InputError(path, units_message(span, pair), field)
        scale = 1.0
    elif units in UNITS:
        scale = UNITS[units]
    else:
        raise InputError(None, f"one of {tuple(UNITS)} expected, got {units!r}", "--units")
    cams = []
    for c in rig.cameras:
        T = c.cam_from_rig.copy()
        T[:3, 3] *= scale
        cams.append(c.with_pose(T))
    record = {"units": units if units is not None else "m (assumed: no --units)", "scale_to_m": scale,
              "largest_baseline_source_units": span}
    return Rig(tuple(cams), rig.meta), record


def rename_cameras(rig: Rig, names) -> Rig:
    """The rig with its cameras renamed in order (per-camera ``meta['cameras']`` entries follow)."""
    names = list(names)
    if len(names) != len(rig):
        raise InputError(None, f"{len(names)} names for {len(rig)} cameras ({', '.join(rig.names)})", "--names")
    if len(set(names)) != len(names) or any(not n or any(ch.isspace() for ch in n) for n in names):
        raise InputError(None, f"unique names without spaces expected, got {names}", "--names")
    old = dict(zip(rig.names, names))
    meta = dict(rig.meta)
    if "cameras" in meta:
        meta["cameras"] = {old[k]: v for k, v in meta["cameras"].items()}
    return Rig(tuple(replace(c, name=n) for c, n in zip(rig.cameras, names)), meta)


def rectified_rig(width: int, height: int, focal_px: float, baseline_m: float, principal_point=None,
                  names=("cam0", "cam1")) -> Rig:
    """Two ideal cameras of a rectified stereo pair: ``K = [[f, 0, cx], [0, f, cy], [0, 0, 1]]`` for both (principal
    point at the image centre ``((W - 1) / 2, (H - 1) / 2)`` unless given, OpenCV convention), no distortion, the
    left camera the rig frame and the right one at ``cam_from_rig = [I | (-B, 0, 0)]`` (its centre B to the right)."""
    if not (focal_px > 0 and baseline_m > 0):
        raise ValueError(f"focal_px and baseline_m must be positive, got {focal_px}, {baseline_m}")
    cx, cy = ((width - 1) / 2, (height - 1) / 2) if principal_point is None else principal_point
    K = np.array([[focal_px, 0.0, cx], [0.0, focal_px, cy], [0.0, 0.0, 1.0]])
    left, right = names
    return Rig((Camera(left, width, height, K, np.zeros(5)),
                Camera(right, width, height, K, np.zeros(5), pose_matrix(np.eye(3), [-baseline_m, 0.0, 0.0]))))


# =====================================================================================================================
# Finishing: units, names, provenance
# =====================================================================================================================
def read_foreign(fmt: str, files, image_sizes=()) -> ImportedRig:
    """Read the files of :func:`plan_import` with the reader of ``fmt``.

    Parameters
    ----------
    image_sizes : sequence of (width, height)
        ``--image-size``: one for every camera, or one per camera; needed where the files hold no image size
        (stereo_calib.cpp's files, text files), checked against the files where they hold one.
    """
    readers = {"opencv": _read_opencv, "kalibr": _read_kalibr, "colmap": _read_colmap, "caliscope": _read_caliscope,
               "text": _read_text}
    return readers[fmt]([Path(f) for f in files], [tuple(s) for s in image_sizes])


def finish_import(imp: ImportedRig, units: str | None = None, names=None, producer: str = "heartcv rig import") -> Rig:
    """The rig to write: translations in metres (:func:`convert_units`), cameras renamed, and the provenance in
    ``meta``: ``producer``, ``source_format``, ``source_files`` (path and sha256), ``inputs_hash`` (``source_i``
    -> sha256, in ``source_files`` order), ``units_conversion``, ``orthonormalised``, ``source_rig_frame``. The rig
    is checked to read back from its file (the rig file's plausibility bounds) before it is returned."""
    rig, record = convert_units(imp.rig, units, *imp.translations)
    if names is not None:
        rig = rename_cameras(rig, names)
    hashes = [{"file": str(f), "sha256": file_hash(f)} for f in imp.files]
    meta = dict(rig.meta)
    # inputs_hash keys are roles (source_0, source_1, ...): OpenCV's FileStorage cannot read quoted keys (paths)
    meta.update({"producer": producer, "inputs_hash": {f"source_{i}": h["sha256"] for i, h in enumerate(hashes)},
                 "source_format": imp.source_format, "source_files": hashes, "source_rig_frame": imp.rig_frame,
                 "units_conversion": record, "orthonormalised": list(imp.corrections)})
    rig = Rig(rig.cameras, meta)
    try:
        rig_from_dict(rig_to_dict(rig))
    except InputError as exc:
        raise exc.in_file(imp.files[0]) from None
    for c in rig.cameras:
        cx, cy = float(c.K[0, 2]), float(c.K[1, 2])
        if not (-0.5 <= cx <= c.width - 0.5 and -0.5 <= cy <= c.height - 0.5):
            raise InputError(imp.files[0], f"camera {c.name}: principal point ({cx:g}, {cy:g}) lies outside its "
                                           f"{c.width}x{c.height} image (-0.5 .. W-0.5, -0.5 .. H-0.5): is the image "
                                           "size right (--image-size), or the matrix another camera's?", "K")
    return rig


def side_warnings(rig: Rig) -> list[str]:
    """Warnings for camera names that contradict the geometry: a camera named ``right`` (any name holding
    ``right``) whose centre lies to the left of the one named ``left`` in that camera's frame, as when poses of a
    ``l2r`` file are read as ``r2l`` or the files were given in the other order. Only mostly horizontal baselines
    (the x offset at least half the baseline) are judged."""
    def side(name, word):
        return word in name.lower()

    out = []
    lefts = [c for c in rig.cameras if side(c.name, "left") and not side(c.name, "right")]
    rights = [c for c in rig.cameras if side(c.name, "right") and not side(c.name, "left")]
    for a in lefts:
        for b in rights:
            T = a.cam_from_rig @ np.linalg.inv(b.cam_from_rig)      # b's frame into a's
            p = T[:3, 3]                                             # b's centre in a's frame
            base = float(np.linalg.norm(p))
            if base > 0 and p[0] < -0.5 * base:
                out.append(f"camera {b.name!r} lies {-1e3 * p[0]:.3g} mm to the left of camera {a.name!r} (in "
                           f"{a.name}'s frame): are the poses inverted (a left-to-right transform read as "
                           "right-to-left), or the cameras' files given in the other order? heartcv measure's rig "
                           "check would show it as an epipolar error")
    return out


# =====================================================================================================================
# Shared checks
# =====================================================================================================================
def _camera(name, size, K, dist, T, path, field) -> Camera:
    try:
        return Camera(name, size[0], size[1], K, dist, T)
    except (ValueError, TypeError) as exc:
        raise InputError(path, str(exc), field) from None


def _size(v, path, field) -> tuple[int, int]:
    ok = (isinstance(v, (list, tuple)) and len(v) == 2
          and all(isinstance(x, (int, float)) and not isinstance(x, bool) and 0 < x <= _MAX_SIDE
                  and float(x).is_integer() for x in v))
    if not ok:
        raise InputError(path, f"[width, height] in pixels expected, got {show(v)}", field)
    return int(v[0]), int(v[1])


def _sizes(found: list, image_sizes: list, path) -> list[tuple[int, int]]:
    """Each camera's image size: from the file where it has one (checked against --image-size when given), else
    from --image-size (one for all cameras, or one per camera)."""
    n = len(found)
    if image_sizes and len(image_sizes) not in (1, n):
        raise InputError(None, f"{len(image_sizes)} image sizes for {n} cameras: give one for all or one per camera",
                         "--image-size")
    out = []
    for i, s in enumerate(found):
        given = None if not image_sizes else image_sizes[0 if len(image_sizes) == 1 else i]
        if s is None and given is None:
            raise InputError(path, "the image size is not in the file: pass --image-size WxH (e.g. --image-size "
                                   "640x480)", "image size")
        if s is not None and given is not None and tuple(s) != tuple(given):
            raise InputError(path, f"camera {i}: the file says {s[0]}x{s[1]}, --image-size {given[0]}x{given[1]}",
                             "image size")
        out.append(tuple(s) if s is not None else tuple(given))
    return out


def _nested(v) -> bool:
    """Whether a list read from a file is a list of lists (a matrix) rather than a flat list."""
    return isinstance(v, (list, tuple)) and bool(v) and isinstance(v[0], (list, tuple))


def _array(v, path, field) -> np.ndarray:
    """A value read from a file as a float array: an array (OpenCV matrices), or a list of numbers."""
    if isinstance(v, np.ndarray) and v.dtype.kind in "fiu":
        return v.astype(float)
    if isinstance(v, (list, tuple)):
        return get_matrix(list(v), (None, None) if _nested(v) else None, path, field)
    raise InputError(path, f"a matrix of numbers expected, got {show(v)}", field)


def _dist(v, path, field) -> np.ndarray:
    d = _array(v, path, field).reshape(-1)
    if d.size not in DIST_SIZES:
        raise InputError(path, f"{d.size} distortion coefficients; one of {DIST_SIZES[1:]} (OpenCV order k1 k2 p1 "
                               "p2 [k3 [k4 k5 k6 ...]]) expected", field)
    if not np.isfinite(d).all():
        raise InputError(path, f"finite distortion coefficients expected, got {int((~np.isfinite(d)).sum())} NaN or "
                               "infinite", field)
    return d


def _pose(R, t, path, field) -> tuple[np.ndarray, dict | None]:
    R, corr = orthonormalise(R, path, f"{field} (rotation)")
    return pose_matrix(R, np.asarray(t, float).reshape(3)), corr


def _rigid4(a, path, field) -> tuple[np.ndarray, dict | None]:
    """A 4x4 (or 3x4) rigid transform, its rotation re-orthonormalised."""
    a = np.asarray(a, float)
    if a.shape == (4, 4) and np.abs(a[3] - [0, 0, 0, 1]).max() > 1e-9:
        raise InputError(path, f"last row [0 0 0 1] expected, got {a[3].tolist()}", field)
    if a.shape not in ((4, 4), (3, 4)):
        raise InputError(path, f"a 4x4 or 3x4 transform expected, got shape {a.shape}", field)
    return _pose(a[:3, :3], a[:3, 3], path, field)


# =====================================================================================================================
# Text: K, distortion rows and poses in camera order (and the Hamlyn folder layout)
# =====================================================================================================================
def _numbers(path) -> np.ndarray:
    text = read_text(path, "text matrix file", _TEXT_BYTES)
    rows = []
    for i, line in enumerate(text.splitlines(), 1):
        s = line.split("#", 1)[0].replace(",", " ").split()
        if not s:
            continue
        try:
            row = [float(x) for x in s]
        except ValueError:
            raise InputError(path, f"numbers expected, got {show(line.strip())}", f"line {i}") from None
        if rows and len(row) != len(rows[0]):
            raise InputError(path, f"{len(row)} numbers; {len(rows[0])} in the rows above", f"line {i}")
        if not all(math.isfinite(x) for x in row):
            raise InputError(path, "finite numbers expected", f"line {i}")
        rows.append(row)
    if not rows:
        raise InputError(path, "no numbers in it", None)
    return np.array(rows)


def _text_role(a: np.ndarray, path) -> str:
    if a.shape == (3, 3):
        return "K"
    if a.shape in ((4, 4), (3, 4)):
        return "pose"
    if min(a.shape) == 1:
        return "distortion"
    raise InputError(path, f"a {a.shape[0]}x{a.shape[1]} matrix: K (3x3), a distortion row (4, 5, 8, 12 or 14 "
                           "numbers) or a pose (4x4 or 3x4) expected", None)


def _read_text(files, image_sizes) -> ImportedRig:
    """Files in camera order: each K (3x3) starts a camera; a distortion row after it is that camera's; a pose
    (4x4 or 3x4) after it is its cam_from_cam0 (x_cam = R x_cam0 + t), required for every camera but the first."""
    cams, corrections = [], []
    for p in files:
        a = _numbers(p)
        role = _text_role(a, p)
        if role == "K":
            m = _HAMLYN_K.match(p.name)
            cams.append({"K": a, "dist": None, "pose": None, "file": p, "pose_file": None,
                         "name": m["name"] if m else None})
            continue
        if not cams:
            raise InputError(p, f"a {role} before any K: give each camera's K (3x3) first, then its distortion and "
                                "pose", role)
        cam = cams[-1]
        if cam[role if role == "pose" else "dist"] is not None:
            raise InputError(p, f"a second {role} for the camera of {cam['file'].name}", role)
        if role == "distortion":
            cam["dist"] = _dist(a, p, "distortion")
        elif len(cams) == 1:
            raise InputError(p, "a pose after the first camera's K: the first camera is the rig frame; a pose "
                                "(cam_from_cam0) follows the K of each later camera", "pose")
        else:
            cam["pose"], corr = _rigid4(a, p, "pose")
            cam["pose_file"] = p
            corrections += [corr] if corr else []
    if not cams:
        raise InputError(files[0], "no intrinsic matrix (3x3) among the files", "K")
    for c in cams[1:]:
        if c["pose"] is None:
            raise InputError(c["file"], "no pose for this camera: give its cam_from_cam0 (4x4) after its K", "pose")
    names = [c["name"] or f"cam{i}" for i, c in enumerate(cams)]
    if len(set(names)) != len(names):
        names = [f"cam{i}" for i in range(len(cams))]
    sizes = _sizes([None] * len(cams), image_sizes, files[0])
    out = []
    for i, (c, name, size) in enumerate(zip(cams, names, sizes)):
        T = np.eye(4) if i == 0 else c["pose"]
        out.append(_camera(name, size, c["K"], np.zeros(5) if c["dist"] is None else c["dist"], T, c["file"], "K"))
    where = (cams[1]["pose_file"] if len(cams) > 1 else files[0], "pose (translation)")
    return ImportedRig(Rig(tuple(out)), "text", tuple(files), tuple(corrections), where,
                       rig_frame=f"the first camera ({names[0]})")


# =====================================================================================================================
# OpenCV FileStorage
# =====================================================================================================================
_OPENCV_KEYS = ("camera_matrix", "distortion_coefficients", "image_width", "image_height", "avg_reprojection_error",
                "distortion_model", "M1", "D1", "M2", "D2", "R", "T")


def _opencv_fields(path) -> dict:
    """The keys heartcv uses from an OpenCV FileStorage file (YAML/XML/JSON via cv2.FileStorage; plain YAML with
    ``{rows, cols, data}`` matrices, as ROS camera_info files, via the safe YAML reader)."""
    text = read_text(path, "OpenCV FileStorage file", LIMITS["yaml_bytes"])
    if _is_filestorage(text) or text.lstrip().startswith("{"):
        return _filestorage_fields(path, text)
    d = parse_yaml(text, path)
    if not isinstance(d, dict):
        raise InputError(path, "a mapping of OpenCV keys (camera_matrix, ... or M1, D1, ...) expected", None)
    out = {}
    for k in _OPENCV_KEYS:
        v = d.get(k)
        if isinstance(v, dict) and "data" in v:
            data = get_matrix(v["data"], None, path, f"{k}.data")
            rows, cols = v.get("rows"), v.get("cols")
            if not (isinstance(rows, int) and isinstance(cols, int) and rows * cols == data.size):
                raise InputError(path, f"rows x cols ({show(rows)} x {show(cols)}) does not match {data.size} values",
                                 k)
            out[k] = data.reshape(rows, cols)
        elif isinstance(v, list):
            out[k] = get_matrix(v, (None, None) if _nested(v) else None, path, k)
        elif v is not None:
            out[k] = v
    return out


def _filestorage_fields(path, text: str) -> dict:
    import cv2

    fs = cv2.FileStorage()  # open() raises cv2.error for a parse error (the constructor a SystemError)
    try:
        if not fs.open(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY):
            raise InputError(path, "not a valid OpenCV FileStorage file", None)
        return {k: v for k in _OPENCV_KEYS if (v := _fs_value(fs.getNode(k), path, k)) is not None}
    except cv2.error as exc:
        msg = (str(exc).strip().splitlines() or ["?"])[-1][:300]
        raise InputError(path, f"not a valid OpenCV FileStorage file ({msg})", None) from None
    finally:
        fs.release()


def _fs_value(node, path, key):
    """A node's value: a matrix (float array), a number or a string; None when absent."""
    if node.empty() or node.isNone():
        return None
    if node.isMap():
        m = node.mat()
        if m is None:
            raise InputError(path, "an OpenCV matrix (!!opencv-matrix) expected", key)
        return np.asarray(m, float)
    if node.isSeq():
        return _fs_seq(node, path, key)
    if node.isString():
        return node.string()
    return node.real()


def _fs_seq(node, path, key) -> np.ndarray:
    rows = []
    for i in range(node.size()):
        item = node.at(i)
        rows.append([item.at(j).real() for j in range(item.size())] if item.isSeq() else item.real())
    return get_matrix(rows, (None, None) if _nested(rows) else None, path, key)


def _opencv_matrix(f, key, path, shape) -> np.ndarray:
    a = _array(f[key], path, key)
    if a.shape != shape:
        raise InputError(path, f"a finite {shape[0]}x{shape[1]} matrix expected, got shape {a.shape}", key)
    if not np.isfinite(a).all():
        raise InputError(path, f"a finite {shape[0]}x{shape[1]} matrix expected, got "
                               f"{int((~np.isfinite(a)).sum())} NaN or infinite entries", key)
    return a


def _read_opencv(files, image_sizes) -> ImportedRig:
    cams, extr = [], None  # cams: (K, dist, size or None, rms, file, K key)
    for p in files:
        f = _opencv_fields(p)
        model = f.get("distortion_model")
        if model is not None and model not in ("plumb_bob", "rational_polynomial"):
            raise InputError(p, f"{show(model)}: not supported (plumb_bob or rational_polynomial: OpenCV's pinhole "
                                "model; a fisheye model has no exact equivalent)", "distortion_model")
        if "camera_matrix" in f:
            if "distortion_coefficients" not in f:
                raise InputError(p, "missing (the camera's distortion)", "distortion_coefficients")
            w, h = f.get("image_width"), f.get("image_height")
            size = None if w is None or h is None else _size([w, h], p, "image_width, image_height")
            rms = f.get("avg_reprojection_error")
            cams.append((_opencv_matrix(f, "camera_matrix", p, (3, 3)),
                         _dist(f["distortion_coefficients"], p, "distortion_coefficients"), size,
                         rms if isinstance(rms, float) and rms >= 0 else None, p, "camera_matrix"))
        if "M1" in f or "M2" in f:
            for j in (1, 2):
                for key in (f"M{j}", f"D{j}"):
                    if key not in f:
                        raise InputError(p, "missing (stereo_calib.cpp writes M1 D1 M2 D2)", key)
                cams.append((_opencv_matrix(f, f"M{j}", p, (3, 3)), _dist(f[f"D{j}"], p, f"D{j}"), None, None, p,
                             f"M{j}"))
        if "R" in f or "T" in f:
            for key in ("R", "T"):
                if key not in f:
                    raise InputError(p, "missing (the second camera's pose is [R | T])", key)
            if extr is not None:
                raise InputError(p, f"R and T given twice (also in {extr[0]})", "R")
            extr = (p, f["R"], f["T"])
    if not cams:
        raise InputError(files[0], "no camera_matrix (one camera) or M1/M2 (stereo_calib.cpp) in the files", "M1")
    if len(cams) > 2:
        raise InputError(files[0], f"{len(cams)} cameras: opencv files hold one camera or a stereo pair", "M1")
    if len(cams) == 2 and extr is None:
        raise InputError(cams[1][4], "the second camera's pose is missing: give the extrinsics file (R, T, as "
                                     "stereo_calib.cpp's extrinsics.yml) too", "R")
    if len(cams) == 1 and extr is not None:
        raise InputError(extr[0], "R and T given for a single camera", "R")
    corrections, poses = [], [np.eye(4)]
    if extr is not None:
        p, R, T = extr
        R = _array(R, p, "R")
        if R.size == 3:  # a rotation vector (Rodrigues)
            from scipy.spatial.transform import Rotation

            R = Rotation.from_rotvec(R.reshape(3)).as_matrix()
        T = _array(T, p, "T")
        if T.size != 3 or not np.isfinite(T).all():
            raise InputError(p, f"3 finite numbers expected, got shape {T.shape}", "T")
        pose, corr = _pose(R, T, p, "R")
        poses.append(pose)
        corrections += [corr] if corr else []
    sizes = _sizes([c[2] for c in cams], image_sizes, cams[0][4])
    out, meta = [], {}
    for i, ((K, dist, _, rms, p, key), size, T) in enumerate(zip(cams, sizes, poses)):
        out.append(_camera(f"cam{i}", size, K, dist, T, p, key))
        if rms is not None:
            meta[f"cam{i}"] = {"rms_px": rms}
    where = (extr[0], "T") if extr else (files[0], "T")
    frame = "the first camera (cam0: M1 of stereo_calib.cpp)" if cams[0][5] == "M1" else "the first camera (cam0)"
    return ImportedRig(Rig(tuple(out), {"cameras": meta} if meta else {}), "opencv", tuple(files),
                       tuple(corrections), where, rig_frame=frame)


# =====================================================================================================================
# Kalibr camchain
# =====================================================================================================================
def _read_kalibr(files, image_sizes) -> ImportedRig:
    (path,) = files
    text = read_text(path, "Kalibr camchain", LIMITS["yaml_bytes"])
    d = parse_yaml(text, path)
    keys = sorted((k for k in (d if isinstance(d, dict) else {}) if re.fullmatch(r"cam\d+", str(k))),
                  key=lambda k: int(k[3:]))
    if not keys:
        raise InputError(path, "no cameras (cam0, cam1, ...) in it", "cam0")
    if keys != [f"cam{i}" for i in range(len(keys))] or len(keys) > _MAX_CAMERAS:
        raise InputError(path, f"cameras cam0 .. cam{len(keys) - 1} expected, got {keys[:16]}", "cam0")
    cams, sizes, corrections, T = [], [], [], np.eye(4)
    for i, key in enumerate(keys):
        e = d[key]
        if not isinstance(e, dict):
            raise InputError(path, "a mapping expected", key)
        model = e.get("camera_model", "pinhole")
        if model != "pinhole":
            raise InputError(path, f"{show(model)}: not supported (heartcv imports pinhole cameras)",
                             f"{key}.camera_model")
        dm = e.get("distortion_model", "radtan")
        if dm not in ("radtan", "none"):
            raise InputError(path, f"{show(dm)}: not supported; heartcv imports radtan (OpenCV's k1 k2 p1 p2) or "
                                   "none: equidistant and fov have no exact equivalent in OpenCV's pinhole model",
                             f"{key}.distortion_model")
        fu, fv, pu, pv = get_matrix(e.get("intrinsics"), (4,), path, f"{key}.intrinsics")
        if dm == "radtan":
            dist = get_matrix(e.get("distortion_coeffs"), (4,), path, f"{key}.distortion_coeffs")
        else:
            dist = np.zeros(4)
        sizes.append(_size(e.get("resolution"), path, f"{key}.resolution"))
        if i > 0:
            a = get_matrix(e.get("T_cn_cnm1"), (4, 4), path, f"{key}.T_cn_cnm1")
            step, corr = _rigid4(a, path, f"{key}.T_cn_cnm1")
            corrections += [corr] if corr else []
            T = step @ T
        cams.append((key, np.array([[fu, 0.0, pu], [0.0, fv, pv], [0.0, 0.0, 1.0]]), dist, T))
    sizes = _sizes(sizes, image_sizes, path)
    out = [_camera(n, s, K, dist, T, path, f"{n}.intrinsics") for (n, K, dist, T), s in zip(cams, sizes)]
    return ImportedRig(Rig(tuple(out)), "kalibr", (path,), tuple(corrections), (path, "T_cn_cnm1"),
                       rig_frame="the first camera (cam0)")


# =====================================================================================================================
# COLMAP text model: cameras.txt + rigs.txt
# =====================================================================================================================
def _data_lines(path):
    text = read_text(path, "COLMAP text file", LIMITS["yaml_bytes"])
    for i, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if s and not s.startswith("#"):
            yield i, s.split()


def _colmap_cameras(path) -> dict:
    cams = {}
    for i, tok in _data_lines(path):
        where = f"line {i}"
        if len(tok) < 4:
            raise InputError(path, "CAMERA_ID MODEL WIDTH HEIGHT PARAMS[] expected", where)
        try:
            cid, w, h = int(tok[0]), int(tok[2]), int(tok[3])
            params = [float(x) for x in tok[4:]]
        except ValueError:
            raise InputError(path, f"CAMERA_ID MODEL WIDTH HEIGHT PARAMS[] expected, got {show(' '.join(tok))}",
                             where) from None
        if cid in cams:
            raise InputError(path, f"camera {cid} defined twice", where)
        if not all(math.isfinite(x) for x in params):
            raise InputError(path, "finite parameters expected", where)
        try:
            K, dist = colmap_to_opencv(tok[1], params)
        except InputError as exc:
            raise InputError(path, f"camera {cid}: {exc.reason}", f"{where} {exc.field}") from None
        cams[cid] = (_size([w, h], path, f"{where} WIDTH HEIGHT"), K, dist, i)
        if len(cams) > _MAX_CAMERAS:
            raise InputError(path, f"more than {_MAX_CAMERAS} cameras", where)
    if not cams:
        raise InputError(path, "no cameras in it", None)
    return cams


def _colmap_rigs(path) -> list:
    """[(rig id, line, [(sensor type, id, pose 4x4 or None, quaternion correction)])]; the reference sensor first
    (identity)."""
    rigs = []
    for i, tok in _data_lines(path):
        where = f"line {i}"
        try:
            rid, n = int(tok[0]), int(tok[1])
            sensors, k = [(tok[2], int(tok[3]), np.eye(4), None)], 4
            for _ in range(n - 1):
                typ, sid, has = tok[k], int(tok[k + 1]), tok[k + 2]
                k += 3
                if has == "1":
                    q, t = [float(x) for x in tok[k:k + 4]], [float(x) for x in tok[k + 4:k + 7]]
                    if len(t) != 3:
                        raise IndexError
                    k += 7
                    sensors.append((typ, sid, *_colmap_pose(q, t, path, f"{where} sensor {typ} {sid}")))
                else:
                    sensors.append((typ, sid, None, None))
        except InputError:      # (a ValueError too: the pose's own reason, not the layout's)
            raise
        except (ValueError, IndexError):
            raise InputError(path, "RIG_ID NUM_SENSORS REF_SENSOR_TYPE REF_SENSOR_ID then per sensor SENSOR_TYPE "
                                   "SENSOR_ID HAS_POSE [QW QX QY QZ TX TY TZ] expected", where) from None
        if k != len(tok):
            raise InputError(path, f"{len(tok) - k} values after the {n} sensors", where)
        rigs.append((rid, i, sensors))
    return rigs


def _colmap_pose(q, t, path, field):
    """sensor_from_rig of a Hamilton quaternion (QW QX QY QZ; normalised as COLMAP does when within
    :data:`ORTHO_TOL` of unit length) and a translation."""
    from scipy.spatial.transform import Rotation

    q = np.asarray(q, float)
    norm = float(np.linalg.norm(q))
    if not (np.isfinite(q).all() and np.isfinite(t).all()) or abs(norm - 1) > ORTHO_TOL:
        raise InputError(path, f"a unit quaternion QW QX QY QZ expected, got norm {norm:.6g}", field)
    R = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
    corr = None
    if abs(norm - 1) > _EXACT_TOL:
        corr = {"file": str(path), "field": f"{field} (quaternion)", "deviation": abs(norm - 1), "angle_deg": 0.0}
    return pose_matrix(R, t), corr


def _read_colmap(files, image_sizes) -> ImportedRig:
    cam_path = files[0]
    cams = _colmap_cameras(cam_path)
    rigs_path = files[1] if len(files) > 1 else None
    corrections, warnings = [], []
    if rigs_path is None:
        if len(cams) > 1:
            raise InputError(cam_path, f"{len(cams)} cameras and no rigs.txt beside it: their relative poses are "
                                       "unknown (COLMAP >= 3.12 writes rigs.txt)", "rigs.txt")
        order = [(next(iter(cams)), np.eye(4))]
    else:
        rigs = _colmap_rigs(rigs_path)
        with_cams = [r for r in rigs if any(s[0] == "CAMERA" for s in r[2])]
        if len(with_cams) != 1:
            raise InputError(rigs_path, f"{len(with_cams)} rigs with cameras (ids {[r[0] for r in with_cams]}): "
                                        "heartcv imports one rig holding every camera of cameras.txt", "RIG_ID")
        rid, line, sensors = with_cams[0]
        if sensors[0][0] != "CAMERA":
            raise InputError(rigs_path, f"rig {rid}: the reference sensor is a {sensors[0][0]}; heartcv needs a "
                                        "camera as the rig frame", f"line {line}")
        order = []
        for typ, sid, T, corr in sensors:
            if typ != "CAMERA":
                warnings.append(f"{rigs_path}: rig {rid}: sensor {typ} {sid} is not a camera; skipped")
                continue
            if sid not in cams:
                raise InputError(rigs_path, f"rig {rid}: camera {sid} is not in {cam_path.name}", f"line {line}")
            if T is None:
                raise InputError(rigs_path, f"rig {rid}: camera {sid} has no pose (HAS_POSE 0): its place in the "
                                            "rig is unknown", f"line {line}")
            order.append((sid, T))
            corrections += [corr] if corr else []
        missing = sorted(set(cams) - {sid for sid, _ in order})
        if missing:
            raise InputError(rigs_path, f"cameras {missing} of {cam_path.name} are not in rig {rid}; heartcv imports "
                                        "one rig holding every camera", f"line {line}")
    sizes = _sizes([cams[sid][0] for sid, _ in order], image_sizes, cam_path)
    out = [_camera(f"cam{sid}", size, cams[sid][1], cams[sid][2], T, cam_path, f"line {cams[sid][3]}")
           for (sid, T), size in zip(order, sizes)]
    return ImportedRig(Rig(tuple(out)), "colmap", tuple(files), tuple(corrections),
                       (rigs_path or cam_path, "TX TY TZ"), tuple(warnings),
                       rig_frame=f"the rig's reference sensor (cam{order[0][0]})")


# =====================================================================================================================
# caliscope: camera_array.toml ([cameras.N]) or config.toml ([cam_N])
# =====================================================================================================================
def _toml(path) -> dict:
    try:
        import tomllib
    except ImportError:  # Python 3.10
        try:
            import tomli as tomllib
        except ImportError:
            raise InputError(path, "reading TOML needs Python >= 3.11 (tomllib) or the tomli package", None) from None
    text = read_text(path, "TOML file", LIMITS["yaml_bytes"])
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(path, f"not valid TOML: {str(exc)[:300]}", None) from None
    except RecursionError:
        raise InputError(path, "refused: the TOML document is nested too deeply", None) from None


def _read_caliscope(files, image_sizes) -> ImportedRig:
    (path,) = files
    d = _toml(path)
    if isinstance(d.get("cameras"), dict):
        entries = [(f"cameras.{k}", k, v) for k, v in d["cameras"].items()]
    else:
        entries = [(k, k[4:], v) for k, v in d.items() if re.fullmatch(r"cam_\d+", k)]
    if not entries:
        raise InputError(path, "no cameras: [cameras.N] tables (camera_array.toml) or [cam_N] tables (config.toml) "
                               "expected", "cameras")
    found, warnings = [], []
    for table, key, e in entries:
        if not isinstance(e, dict):
            raise InputError(path, "a table expected", table)
        cid = e.get("cam_id", e.get("port", int(key) if str(key).isdigit() else key))
        if isinstance(cid, bool) or not isinstance(cid, int) or cid < 0:
            raise InputError(path, f"a camera id (integer >= 0) expected, got {show(cid)}", f"{table}.cam_id")
        if e.get("ignore") is True:
            warnings.append(f"{path}: {table}: camera {cid} is marked ignore = true; skipped")
            continue
        found.append((cid, table, e))
    found.sort(key=lambda x: x[0])
    if not found:
        raise InputError(path, "every camera is marked ignore = true", "cameras")
    if len({c for c, _, _ in found}) != len(found):
        raise InputError(path, f"camera ids {[c for c, _, _ in found]} repeat", "cameras")
    cams, corrections = [], []
    for cid, table, e in found:
        cams.append(_caliscope_camera(cid, table, e, path, len(found), corrections))
    sizes = _sizes([c[1] for c in cams], image_sizes, path)
    out = [_camera(n, s, K, dist, T, path, f"{table}.matrix") for (n, _, K, dist, T, table, _), s in zip(cams, sizes)]
    meta = {c[0]: {"rms_px": c[6]} for c in cams if c[6] is not None}
    return ImportedRig(Rig(tuple(out), {"cameras": meta} if meta else {}), "caliscope", (path,), tuple(corrections),
                       (path, "translation"), tuple(warnings), rig_frame="caliscope's world frame (rig_frame: custom)")


def _caliscope_camera(cid, table, e, path, n_cams, corrections):
    """(name, size, K, dist, cam_from_world, table, rms) of one caliscope camera table."""
    if e.get("rotation_count", 0) not in (0, None):
        raise InputError(path, f"{show(e['rotation_count'])}: caliscope rotated this camera's images; heartcv imports "
                               "unrotated cameras only (rotation_count = 0)", f"{table}.rotation_count")
    if e.get("fisheye") is True:
        raise InputError(path, "a fisheye camera: OpenCV's pinhole model has no exact equivalent", f"{table}.fisheye")
    size = _size(e.get("size"), path, f"{table}.size")
    K = get_matrix(e.get("matrix"), (3, 3), path, f"{table}.matrix")
    dist = _dist(get_matrix(e.get("distortions"), None, path, f"{table}.distortions"), path, f"{table}.distortions")
    rot, trans = e.get("rotation"), e.get("translation")
    if rot is None or trans is None:
        if n_cams > 1:
            raise InputError(path, "missing: the camera's pose is unknown (run caliscope's extrinsic calibration "
                                   "first)", f"{table}.{'rotation' if rot is None else 'translation'}")
        T = np.eye(4)
    else:
        R = get_matrix(rot, (3, 3) if _nested(rot) else (3,), path, f"{table}.rotation")
        if R.shape == (3,):  # caliscope >= 0.5 stores a rotation vector (cv2.Rodrigues)
            from scipy.spatial.transform import Rotation

            R = Rotation.from_rotvec(R).as_matrix()
        t = get_matrix(trans, (3,), path, f"{table}.translation")
        R, corr = orthonormalise(R, path, f"{table}.rotation")
        corrections += [corr] if corr else []
        T = pose_matrix(R, t)
    rms = e.get("error")
    rms = float(rms) if isinstance(rms, (int, float)) and not isinstance(rms, bool) and rms >= 0 else None
    return f"cam_{cid}", size, K, dist, T, table, rms


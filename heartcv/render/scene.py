"""The scene file (``heartcv.scene`` v1) as typed, validated values, and the rig it describes.

:func:`scene_from_dict` takes the parsed YAML mapping, fills the documented defaults (docs/design.md §7: three
cameras on an equilateral triangle of side 0.5 m, 35 mm lenses, 5.86 um pixels, 1920x1080) and rejects an
unknown key or an out-of-range value with a :class:`SceneError` that names the field (``phantom.texture.fat``).
Paths in the file (``motion.model``, ``calibration.target``) stay strings here; ``heartcv.io.read_scene``
resolves them against the scene file's folder. The layout is documented in ``docs/formats.md`` (scene file).

Frames. The **world frame is camera 0's frame** (OpenCV axes), as in the rig file that calibration writes. The
rig is built in a *ring frame*: the cameras sit on a regular polygon in the plane z = 0 around the central axis
+z (y down, x right), each looking at the convergence point ``(0, 0, working_distance_m)``; camera 0 is at the
top (-y). ``Scene.world_from_ring`` maps the ring frame to the world frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math

import numpy as np

from ..tracker.files import InputError
from ..tracker.files import show as _show
from .rig import build_rig, default_world_from_patch, ring_poses

__all__ = ["SceneError", "Scene", "scene_from_dict", "build_rig", "ring_poses", "default_world_from_patch",
           "FORMAT", "FORMAT_VERSION", "DEFAULT_TARGET"]

FORMAT = "heartcv.scene"
FORMAT_VERSION = 1
DEFAULT_TARGET = {"format": "heartcv.target", "format_version": 1, "name": "charuco_11x8_12mm", "type": "charuco",
                  "squares": [11, 8], "square_m": 0.012, "marker_m": 0.009, "dictionary": "DICT_5X5_250"}
"""The target used when ``calibration.target`` is null (calibration_targets/charuco_11x8_12mm.yaml)."""


MAX_IMAGE_PIXELS = 25_000_000
"""Largest ``rig.image_size`` width x height (25 MP): one RGB float image stays below 1 GB."""


class SceneError(InputError):
    """A scene field is missing, unknown or out of range; ``field`` names it (dotted path; None for the file as a
    whole). An :class:`~heartcv.tracker.files.InputError` without a file (``heartcv.io.read_scene`` names it)."""

    def __init__(self, field_name: str | None, message: str):
        super().__init__(None, message, field_name)


# -- typed sections -------------------------------------------------------------------------------
@dataclass(frozen=True)
class RigSpec:
    cameras: int = 3
    side_m: float = 0.5
    working_distance_m: float = 0.53
    focal_mm: float = 35.0
    pixel_pitch_m: float = 5.86e-6
    image_size: tuple = (1920, 1080)
    distortion: tuple = ()
    per_camera: tuple = ()  # one mapping per camera: focal_mm, principal_point_px, distortion


@dataclass(frozen=True)
class OpticsSpec:
    psf_sigma_px: float = 0.5
    supersampling: int = 1
    color: bool = True


@dataclass(frozen=True)
class LightingSpec:
    kind: str = "camera"  # camera | ring
    intensity: float = 1.5
    ambient: float = 0.1
    light_offset_m: tuple = (0.0, -0.04, 0.0)
    ring_radius_m: float = 0.35
    ring_count: int = 12
    specular: float = 1.0
    shininess: float = 60.0
    background: float = 0.05


@dataclass(frozen=True)
class CalibrationSpec:
    target: str | None = None
    views: int = 24
    max_tilt_deg: float = 60.0
    max_roll_deg: float = 30.0
    max_incidence_deg: float = 75.0
    partial_fraction: float = 0.25
    offset_m: float = 0.02
    depth_m: float = 0.04
    min_corners: int = 12
    supersampling: int = 4
    board_margin_m: float = 0.01
    background: float = 0.25
    white: float = 0.85
    black: float = 0.04


@dataclass(frozen=True)
class TextureSpec:
    texel_m: float = 5e-5
    vessels: int = 10
    fat: float = 0.2
    speckle: float = 0.12
    mottling: float = 0.15
    tissue_rgb: tuple = (0.50, 0.16, 0.13)
    fat_rgb: tuple = (0.72, 0.62, 0.42)
    vessel_rgb: tuple = (0.30, 0.07, 0.10)


@dataclass(frozen=True)
class FiducialSpec:
    enabled: bool = False
    spacing_m: float = 0.006
    radius_m: float = 0.0007
    margin_m: float = 0.004
    rgb: tuple = (0.75, 0.75, 0.72)


@dataclass(frozen=True)
class PhantomSpec:
    world_from_patch: np.ndarray | None = None
    apex_m: float = 0.075
    base_m: float = 0.055
    apex_radius_m: float = 0.012
    base_radius_m: float = 0.035
    mesh_edge_m: float = 0.0012
    outside_motion_m: float = 0.0008
    falloff_m: float = 0.012
    texture: TextureSpec = field(default_factory=TextureSpec)
    fiducials: FiducialSpec = field(default_factory=FiducialSpec)


@dataclass(frozen=True)
class MotionSpec:
    model: str = "model.yaml"
    duration_s: float = 4.0
    frame_rate_hz: float = 30.0
    substeps: int = 4
    stiffness_amplitude: float = 0.0
    stiffness_shape: str = "pressure"  # pressure | active
    respiration: dict | None = None  # amplitude (m), frequency_hz, direction (patch frame), n, phase
    process_noise: bool = False


@dataclass(frozen=True)
class NoiseSpec:
    full_well_e: float = 10000.0
    read_noise_e: float = 8.0
    shot_noise: bool = True
    gain: float = 1.0
    bits: int = 8


@dataclass(frozen=True)
class BlurSpec:
    exposure_fraction: float = 0.3
    subsamples: int = 1


@dataclass(frozen=True)
class InstrumentSpec:
    enabled: bool = False
    radius_m: float = 0.0035
    length_m: float = 0.15
    tip_m: tuple = (0.004, 0.010, 0.004)
    direction: tuple = (0.3, 1.0, 0.5)
    travel_m: float = 0.08
    window_s: tuple = (1.0, 3.0)
    enter_s: float = 0.5
    reflectance: float = 0.55


@dataclass(frozen=True)
class Scene:
    """A validated scene (see the module docstring and docs/formats.md)."""

    name: str
    seed: int
    rig: RigSpec
    optics: OpticsSpec
    lighting: LightingSpec
    calibration: CalibrationSpec
    phantom: PhantomSpec
    motion: MotionSpec
    noise: NoiseSpec
    motion_blur: BlurSpec
    instrument: InstrumentSpec
    raw: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def world_from_ring(self) -> np.ndarray:
        return ring_poses(self.rig)[0]

    @property
    def convergence_point(self) -> np.ndarray:
        """The point the cameras converge on, world frame (3,)."""
        T = self.world_from_ring
        return T[:3, :3] @ np.array([0.0, 0.0, self.rig.working_distance_m]) + T[:3, 3]


# -- validation --------------------------------------------------------------------------------------
def _as_float(v):
    """A finite float of a YAML number (or numeric string), or None."""
    if isinstance(v, str):  # PyYAML reads 1.0e-5 (no sign after e) as a string
        try:
            v = float(v)
        except ValueError:
            return None
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    try:
        v = float(v)
    except OverflowError:  # an integer beyond the float range
        return None
    return v if math.isfinite(v) else None


class _Fields:
    """Reads one mapping, tracking its dotted path for error messages and rejecting unknown keys."""

    def __init__(self, data, path: str):
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise SceneError(path or None, f"a mapping expected, got {type(data).__name__}"
                             + ("" if path else " (a scene file is a YAML mapping, docs/formats.md §10)"))
        self.data, self.path, self.seen = dict(data), path, set()

    def name(self, key):
        return f"{self.path}.{key}" if self.path else str(key)

    def raw(self, key, default=None):
        self.seen.add(key)
        return self.data.get(key, default)

    def number(self, key, default, lo=-math.inf, hi=math.inf, *, lo_open=False, integer=False):
        v = self.raw(key, default)
        if integer and isinstance(v, int) and not isinstance(v, bool):  # exact, however large
            x = v
        else:
            x = _as_float(v)
            if x is None:
                raise SceneError(self.name(key), f"a finite number expected, got {_show(v)}")
            if integer:
                if not x.is_integer():
                    raise SceneError(self.name(key), f"an integer expected, got {_show(v)}")
                x = int(x)
        if (x <= lo if lo_open else x < lo) or x > hi:
            raise SceneError(self.name(key), f"must lie in {'(' if lo_open else '['}{lo:g}, {hi:g}], got {_show(v)}")
        return int(x) if integer else float(x)

    def flag(self, key, default):
        v = self.raw(key, default)
        if not isinstance(v, bool):
            raise SceneError(self.name(key), f"true or false expected, got {_show(v)}")
        return v

    def choice(self, key, default, options):
        v = self.raw(key, default)
        if isinstance(v, (bool, float)) or not isinstance(v, (str, int)) or v not in options:
            raise SceneError(self.name(key), f"one of {list(options)} expected, got {_show(v)}")
        return v

    def vector(self, key, default, n=None, lo=-math.inf, hi=math.inf, *, n_allowed=None):
        v = self.raw(key, default)
        sizes = n_allowed or ((n,) if n is not None else None)
        xs = [_as_float(x) for x in v] if isinstance(v, (list, tuple)) and len(v) <= 64 else None
        ok = xs is not None and all(x is not None and lo <= x <= hi for x in xs)
        if not ok or (sizes is not None and len(xs) not in sizes):
            want = f"{n} numbers" if n is not None else f"a list of {sizes} numbers" if sizes else "a list of numbers"
            raise SceneError(self.name(key), f"{want} in [{lo:g}, {hi:g}] expected, got {_show(v)}")
        return tuple(xs)

    def section(self, key):
        self.seen.add(key)
        return _Fields(self.data.get(key), self.name(key))

    def done(self):
        unknown = sorted(set(self.data) - self.seen, key=str)
        if unknown:
            raise SceneError(self.name(unknown[0]), f"unknown field (known: {sorted(self.seen, key=str)})")


_DIST_SIZES = (0, 4, 5, 8, 12, 14)


def _rig(f: _Fields) -> RigSpec:
    d = RigSpec()
    n = f.number("cameras", d.cameras, 1, 16, integer=True)
    size = f.vector("image_size", d.image_size, 2, 16, 20000)
    if any(s != int(s) for s in size):
        raise SceneError(f.name("image_size"), f"two integers [width, height] expected, got {list(size)}")
    if size[0] * size[1] > MAX_IMAGE_PIXELS:
        raise SceneError(f.name("image_size"), f"{int(size[0])} x {int(size[1])} px; at most {MAX_IMAGE_PIXELS} "
                                               "pixels allowed")
    dist = f.vector("distortion", d.distortion, n_allowed=_DIST_SIZES, lo=-10, hi=10)
    per = f.raw("per_camera", [])
    if per is None:
        per = []
    if not isinstance(per, list) or len(per) > n:
        raise SceneError(f.name("per_camera"), f"a list of at most {n} mappings (one per camera) expected, got "
                                               f"{_show(per)}")
    per_camera = []
    for i, entry in enumerate(per):
        p = _Fields(entry, f.name(f"per_camera[{i}]"))
        over = {}
        if "focal_mm" in p.data:
            over["focal_mm"] = p.number("focal_mm", None, 0, 2000, lo_open=True)
        if "principal_point_px" in p.data:
            over["principal_point_px"] = p.vector("principal_point_px", None, 2, -1e5, 1e5)
        if "distortion" in p.data:
            over["distortion"] = p.vector("distortion", None, n_allowed=_DIST_SIZES, lo=-10, hi=10)
        p.done()
        per_camera.append(over)
    spec = RigSpec(n, f.number("side_m", d.side_m, 0, 10, lo_open=True),
                   f.number("working_distance_m", d.working_distance_m, 0.01, 100),
                   f.number("focal_mm", d.focal_mm, 0, 2000, lo_open=True),
                   f.number("pixel_pitch_m", d.pixel_pitch_m, 0, 1e-3, lo_open=True),
                   (int(size[0]), int(size[1])), dist, tuple(per_camera))
    f.done()
    return spec


def _optics(f: _Fields) -> OpticsSpec:
    d = OpticsSpec()
    spec = OpticsSpec(f.number("psf_sigma_px", d.psf_sigma_px, 0, 10),
                      f.number("supersampling", d.supersampling, 1, 8, integer=True), f.flag("color", d.color))
    f.done()
    return spec


def _lighting(f: _Fields) -> LightingSpec:
    d = LightingSpec()
    spec = LightingSpec(f.choice("kind", d.kind, ("camera", "ring")), f.number("intensity", d.intensity, 0, 100),
                        f.number("ambient", d.ambient, 0, 10), f.vector("light_offset_m", d.light_offset_m, 3, -5, 5),
                        f.number("ring_radius_m", d.ring_radius_m, 0, 10),
                        f.number("ring_count", d.ring_count, 1, 256, integer=True),
                        f.number("specular", d.specular, 0, 10), f.number("shininess", d.shininess, 1, 10000),
                        f.number("background", d.background, 0, 10))
    f.done()
    return spec


def _calibration(f: _Fields) -> CalibrationSpec:
    d = CalibrationSpec()
    target = f.raw("target", d.target)
    if target is not None and (not isinstance(target, str) or not target.strip()):
        raise SceneError(f.name("target"), f"a target file path or null expected, got {_show(target)}")
    white = f.number("white", d.white, 0, 1)
    black = f.number("black", d.black, 0, 1)
    if black >= white:
        raise SceneError(f.name("black"), f"must be darker than white ({white}), got {black}")
    spec = CalibrationSpec(target, f.number("views", d.views, 1, 1000, integer=True),
                           f.number("max_tilt_deg", d.max_tilt_deg, 0, 85),
                           f.number("max_roll_deg", d.max_roll_deg, 0, 180),
                           f.number("max_incidence_deg", d.max_incidence_deg, 10, 89),
                           f.number("partial_fraction", d.partial_fraction, 0, 1),
                           f.number("offset_m", d.offset_m, 0, 1), f.number("depth_m", d.depth_m, 0, 1),
                           f.number("min_corners", d.min_corners, 4, 10000, integer=True),
                           f.number("supersampling", d.supersampling, 1, 16, integer=True),
                           f.number("board_margin_m", d.board_margin_m, 0, 0.5),
                           f.number("background", d.background, 0, 1), white, black)
    f.done()
    return spec


def _texture(f: _Fields) -> TextureSpec:
    d = TextureSpec()
    spec = TextureSpec(f.number("texel_m", d.texel_m, 1e-5, 1e-3), f.number("vessels", d.vessels, 0, 100, integer=True),
                       f.number("fat", d.fat, 0, 1), f.number("speckle", d.speckle, 0, 1),
                       f.number("mottling", d.mottling, 0, 1), f.vector("tissue_rgb", d.tissue_rgb, 3, 0, 1),
                       f.vector("fat_rgb", d.fat_rgb, 3, 0, 1), f.vector("vessel_rgb", d.vessel_rgb, 3, 0, 1))
    f.done()
    return spec


def _fiducials(f: _Fields) -> FiducialSpec:
    d = FiducialSpec()
    spec = FiducialSpec(f.flag("enabled", d.enabled), f.number("spacing_m", d.spacing_m, 1e-3, 0.1),
                        f.number("radius_m", d.radius_m, 1e-4, 0.01), f.number("margin_m", d.margin_m, 0, 0.05),
                        f.vector("rgb", d.rgb, 3, 0, 1))
    f.done()
    if spec.radius_m * 2 >= spec.spacing_m:
        raise SceneError(f.name("radius_m"), f"dots overlap: 2 x radius must be below spacing_m ({spec.spacing_m})")
    return spec


def _pose(f: _Fields, key):
    v = f.raw(key)
    if v is None:
        return None
    rows = [[_as_float(x) for x in r] if isinstance(r, list) and len(r) == 4 else None
            for r in v] if isinstance(v, list) and len(v) == 4 else None
    T = np.array(rows, float) if rows is not None and all(r is not None and None not in r for r in rows) else None
    if T is None:
        raise SceneError(f.name(key), "a 4x4 matrix (list of 4 rows of 4 finite numbers) or null expected")
    if np.abs(T).max() > 100:
        raise SceneError(f.name(key), "entries within [-100, 100] expected (a rotation and a translation in m)")
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0 or np.abs(T[3] - [0, 0, 0, 1]).max() > 0:
        raise SceneError(f.name(key), "not a rigid transform (R^T R = I, det R = +1, last row [0 0 0 1])")
    return T


def _phantom(f: _Fields) -> PhantomSpec:
    d = PhantomSpec()
    spec = PhantomSpec(_pose(f, "world_from_patch"), f.number("apex_m", d.apex_m, 0, 0.5, lo_open=True),
                       f.number("base_m", d.base_m, 0, 0.5, lo_open=True),
                       f.number("apex_radius_m", d.apex_radius_m, 0, 0.5, lo_open=True),
                       f.number("base_radius_m", d.base_radius_m, 0, 0.5, lo_open=True),
                       f.number("mesh_edge_m", d.mesh_edge_m, 2e-4, 0.01),
                       f.number("outside_motion_m", d.outside_motion_m, -0.02, 0.02),
                       f.number("falloff_m", d.falloff_m, 0, 0.2, lo_open=True),
                       _texture(f.section("texture")), _fiducials(f.section("fiducials")))
    f.done()
    return spec


def _motion(f: _Fields) -> MotionSpec:
    d = MotionSpec()
    model = f.raw("model", None)
    if not isinstance(model, str) or not model.strip():
        raise SceneError(f.name("model"), f"a model file path is required, got {_show(model)}")
    st = f.section("stiffness_cycle")
    amp = st.number("amplitude", d.stiffness_amplitude, 0, 20)
    shape = st.choice("shape", d.stiffness_shape, ("pressure", "active"))
    st.done()
    resp = f.raw("respiration", False)
    respiration = None
    if resp is not False and resp is not None:
        r = _Fields({} if resp is True else resp, f.name("respiration"))
        respiration = {"amplitude": r.number("amplitude_m", 0.004, 0, 0.05),
                       "frequency_hz": r.number("frequency_hz", 0.25, 0.01, 2.0),
                       "direction": r.vector("direction", (1.0, 0.3, 0.0), 3, -1e3, 1e3),
                       "n": r.number("n", 2, 1, 10, integer=True), "phase": r.number("phase", 0.0, -100, 100)}
        if np.linalg.norm(respiration["direction"]) == 0:
            raise SceneError(r.name("direction"), "a non-zero vector expected")
        r.done()
    duration = f.number("duration_s", d.duration_s, 0, 3600, lo_open=True)
    rate = f.number("frame_rate_hz", d.frame_rate_hz, 1, 1000)
    if duration * rate < 1 - 1e-9:  # K = floor(duration * rate) + 1 frames: at least two
        raise SceneError(f.name("duration_s"), f"at least one frame interval (1 / frame_rate_hz = {1 / rate:.4g} s) "
                                               f"expected, got {duration!r}")
    spec = MotionSpec(model, duration, rate,
                      f.number("substeps", d.substeps, 1, 100, integer=True), amp, shape, respiration,
                      f.flag("process_noise", d.process_noise))
    f.done()
    return spec


def _noise(f: _Fields) -> NoiseSpec:
    d = NoiseSpec()
    spec = NoiseSpec(f.number("full_well_e", d.full_well_e, 1, 1e7), f.number("read_noise_e", d.read_noise_e, 0, 1e4),
                     f.flag("shot_noise", d.shot_noise), f.number("gain", d.gain, 0, 100, lo_open=True),
                     f.choice("bits", d.bits, (8, 16)))
    f.done()
    return spec


def _blur(f: _Fields) -> BlurSpec:
    d = BlurSpec()
    spec = BlurSpec(f.number("exposure_fraction", d.exposure_fraction, 0, 1),
                    f.number("subsamples", d.subsamples, 1, 64, integer=True))
    f.done()
    return spec


def _instrument(f: _Fields) -> InstrumentSpec:
    d = InstrumentSpec()
    window = f.vector("window_s", d.window_s, 2, 0, 1e5)
    if window[1] <= window[0]:
        raise SceneError(f.name("window_s"), f"[start, end] with end > start expected, got {list(window)}")
    direction = f.vector("direction", d.direction, 3, -1e3, 1e3)
    if np.linalg.norm(direction) == 0:
        raise SceneError(f.name("direction"), "a non-zero vector expected")
    spec = InstrumentSpec(f.flag("enabled", d.enabled), f.number("radius_m", d.radius_m, 1e-4, 0.05),
                          f.number("length_m", d.length_m, 1e-3, 1.0), f.vector("tip_m", d.tip_m, 3, -1, 1),
                          direction, f.number("travel_m", d.travel_m, 0, 1), window,
                          f.number("enter_s", d.enter_s, 0, 1e5), f.number("reflectance", d.reflectance, 0, 1))
    f.done()
    return spec


def scene_from_dict(data) -> Scene:
    """Validate a parsed scene file; :class:`SceneError` names the first offending field."""
    root = _Fields(data, "")
    fmt = root.raw("format", FORMAT)
    if fmt != FORMAT:
        raise SceneError("format", f"{FORMAT!r} expected, got {_show(fmt)}")
    ver = root.raw("format_version", FORMAT_VERSION)
    if isinstance(ver, bool) or ver != FORMAT_VERSION:
        raise SceneError("format_version", f"{FORMAT_VERSION} supported, got {_show(ver)}")
    name = root.raw("name", "scene")
    if not isinstance(name, str) or not name.strip():
        raise SceneError("name", f"a non-empty string expected, got {_show(name)}")
    root.raw("description")
    seed = root.number("seed", 0, 0, 2**63 - 1, integer=True)
    scene = Scene(name, seed, _rig(root.section("rig")), _optics(root.section("optics")),
                  _lighting(root.section("lighting")), _calibration(root.section("calibration")),
                  _phantom(root.section("phantom")), _motion(root.section("motion")), _noise(root.section("noise")),
                  _blur(root.section("motion_blur")), _instrument(root.section("instrument")), raw=dict(data or {}))
    root.done()
    return scene

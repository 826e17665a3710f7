"""Sequence rendering: the moving, textured phantom seen by the rig, frame by frame (pure; no file access).

``prepare_sequence`` does the one-off work (model build and truth simulation, phantom mesh and texture, the
exact ray of every pixel of every camera); ``render_frame`` renders one instant for all cameras;
``render_sequence`` runs the frames on worker processes in order; ``sequence_truth`` and ``inputs_table`` give
what ``heartcv render sequence`` writes beside the images. Randomness: the texture is drawn from
``default_rng([seed, 1])``, process noise (if enabled) from ``[seed, 2]``, the sensor noise of frame k, camera c
from ``[seed, 3, k, c]`` -- independent of the number of workers.

Per frame and sub-frame instant (motion blur averages ``motion_blur.subsamples`` instants spread over
``exposure_fraction`` of the frame interval, centred on the frame time): the deformed mesh (and the instrument)
go into a fresh Embree scene; per camera only the pixels inside the convex hull of the projected geometry cast
rays (the rest see the background); a hit is shaded at its interpolated position and normal with the texture
looked up at its *material* coordinates (barycentric interpolation of the corners' (sigma, t)). The diffuse
irradiance (Lambert) is evaluated at the vertices and interpolated (Gouraud: it varies little across a
1.2 mm triangle); the Blinn-Phong specular term is evaluated per pixel, from the interpolated normal, on every
face where a corner's highlight exceeds ``SPECULAR_CUT`` (elsewhere it is below a quarter of a grey level).
"""

from __future__ import annotations

from dataclasses import dataclass
import time

import numpy as np

from .instrument import Instrument, make_instrument
from .motion import SurfaceMotion, simulate_truth, surface_motion
from .parallel import imap_ordered
from .phantom import build_phantom, locate, vertex_normals
from .raycast import EmbreeScene, hull_mask, pixel_grid
from .scene import Scene, build_rig, default_world_from_patch
from .sensor import expose
from .shading import Lights, light_terms, make_lights, shade
from .texture import Texture, fiducial_grid, make_texture

__all__ = ["SequenceSetup", "FrameResult", "prepare_sequence", "render_frame", "render_sequence",
           "sequence_truth", "inputs_table", "camera_directions"]

_LUMA = np.array([0.299, 0.587, 0.114], np.float32)
INSTRUMENT_SPECULAR, INSTRUMENT_SHININESS = 0.6, 60.0
SPECULAR_CUT = 1e-3
"""Specular radiance below which a face's highlight is taken from its corners (Gouraud) rather than per pixel."""


@dataclass(frozen=True)
class SequenceSetup:
    scene: Scene
    rig: object  # heartcv.camera.Rig (truth)
    directions: tuple  # per camera: (H*W, 3) float32 unit ray directions, world frame
    grids: tuple  # per camera: PixelGrid (for supersampling)
    surface: SurfaceMotion
    texture: Texture
    corner_uv: np.ndarray  # (F, 3, 2) float32
    lights: Lights
    instrument: Instrument | None
    model: object  # tracker.model.PatchModel (at the simulation rate)
    frame_times: np.ndarray

    @property
    def n_frames(self) -> int:
        return self.frame_times.size


@dataclass(frozen=True)
class FrameResult:
    """One rendered instant: ``images`` per camera (uint8/uint16 RGB (H, W, 3) or gray (H, W); or whatever the
    ``encode`` hook returned), ``instrument_mask`` (n_cam, H, W) bool or None, ``timings`` (s) by stage
    (``mesh_s``: deformed vertices, normals and pixel masks; ``bvh_s``: Embree scene; ``cast_s``; ``shade_s``:
    interpolation, texture and lighting; ``expose_s``: PSF, noise, quantisation; ``encode_s`` with an encoder),
    and ``rays``: rays cast (all cameras and sub-frame instants)."""

    index: int
    images: list
    instrument_mask: np.ndarray | None
    timings: dict
    rays: int


def camera_directions(rig, workers=1):
    """Pixel grids and full-resolution unit ray directions of every camera (the slow, one-off part)."""
    grids = list(imap_ordered(lambda cams, i: pixel_grid(cams[i]), rig.cameras, range(len(rig)), workers))
    return tuple(grids), tuple(g.directions() for g in grids)


def prepare_sequence(scene: Scene, model_config, *, workers=1) -> SequenceSetup:
    """Everything that does not change from frame to frame (module docstring)."""
    rig = build_rig(scene.rig)
    world_from_patch = (scene.phantom.world_from_patch if scene.phantom.world_from_patch is not None
                        else default_world_from_patch(scene.rig))
    model, truth = simulate_truth(model_config, scene.motion, scene.motion_blur,
                                  np.random.default_rng([scene.seed, 2]))
    phantom = build_phantom(model.mesh.geometry, scene.phantom)
    surface = surface_motion(phantom, model, truth, world_from_patch, scene.phantom.outside_motion_m)
    fid = None
    if scene.phantom.fiducials.enabled:
        fid = fiducial_grid(model.mesh.geometry, scene.phantom.fiducials.spacing_m, scene.phantom.fiducials.margin_m)
    texture = make_texture(scene.phantom.texture, phantom.sigma_range, phantom.period_m,
                           np.random.default_rng([scene.seed, 1]), fid, scene.phantom.fiducials)
    lights = make_lights(scene.lighting, rig, scene.world_from_ring, scene.rig.working_distance_m)
    grids, dirs = camera_directions(rig, workers)
    return SequenceSetup(scene, rig, dirs, grids, surface, texture, phantom.corner_uv.astype(np.float32), lights,
                         make_instrument(scene.instrument, world_from_patch), model, truth.frame_times)


def _subframe_times(setup: SequenceSetup, k):
    t = setup.frame_times[k]
    b = setup.scene.motion_blur
    n = b.subsamples
    if n <= 1:
        return [t]
    span = b.exposure_fraction / setup.scene.motion.frame_rate_hz
    return [t + ((j + 0.5) / n - 0.5) * span for j in range(n)]


def _interpolate(corners, hits, sel):
    """Barycentric interpolation (N, k) at the selected hits of per-face-corner attributes ``corners`` (F, 3, k)
    (one gather per hit)."""
    u, v = hits.u[sel], hits.v[sel]
    w = np.empty((u.size, 3), np.float32)
    np.subtract(1, u, out=w[:, 0])
    w[:, 0] -= v
    w[:, 1] = u
    w[:, 2] = v
    return np.einsum("nck,nc->nk", np.take(corners, hits.prim[sel], axis=0), w)


def _surface_point(origin, d, hits, sel):
    return np.asarray(origin, np.float32) + hits.distance[sel][:, None] * d[sel]


def _shade_heart(setup, corners, hot_face, normal_corners, hits, sel, origin, d, color):
    """Radiance of phantom hits. ``corners`` (F, 3, 4): irradiance, specular term and material coordinates
    (sigma, t) at each face corner (Gouraud); pixels on faces with a highlight (``hot_face``) get their specular
    term per pixel from the interpolated normal (``normal_corners`` (F, 3, 3))."""
    a = _interpolate(corners, hits, sel)
    albedo = setup.texture.lookup(a[:, 2], a[:, 3])
    if not color:
        albedo = (albedo @ _LUMA)[:, None]
    out = albedo * a[:, :1]
    spec = a[:, 1]
    hot = np.flatnonzero(hot_face[hits.prim[sel]])
    if hot.size:
        sub = sel[hot]
        n = _interpolate(normal_corners, hits, sub)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        spec[hot] = light_terms(_surface_point(origin, d, hits, sub), n, -d[sub], setup.lights)[1]
    out += spec[:, None]
    return out


def _shade_instrument(setup, IN, hits, sel, origin, d, channels):
    n = _interpolate(IN[setup.instrument.faces], hits, sel)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    albedo = np.full((n.shape[0], channels), setup.instrument.reflectance, np.float32)
    return shade(_surface_point(origin, d, hits, sel), n, -d[sel], albedo, setup.lights, INSTRUMENT_SPECULAR,
                 INSTRUMENT_SHININESS)


@dataclass
class _Instant:
    """One instant's geometry, shared by the cameras: deformed phantom (and instrument) and its Embree scene."""

    V: np.ndarray  # (V, 3) float32 world
    Vn: np.ndarray  # (V, 3) vertex normals
    normal_corners: np.ndarray  # (F, 3, 3)
    corners: np.ndarray  # (F, 3, 4): irradiance and highlight (per camera), material coordinates
    scene: EmbreeScene
    IV: np.ndarray | None = None  # instrument vertices and normals, if present
    IN: np.ndarray | None = None


def _instant(setup, t, tm) -> _Instant:
    t0 = time.perf_counter()
    faces = setup.surface.phantom.faces
    V = setup.surface.positions_world(t).astype(np.float32)
    Vn = vertex_normals(V, faces)
    corners = np.empty(faces.shape + (4,), np.float32)
    corners[..., 2:] = setup.corner_uv
    meshes = [(V, faces)]
    IV = IN = None
    if setup.instrument is not None and setup.instrument.present(t):
        IV, IN = (a.astype(np.float32) for a in setup.instrument.mesh(t))
        meshes.append((IV, setup.instrument.faces))
    t1 = time.perf_counter()
    es = EmbreeScene(meshes, origin=V.mean(axis=0))
    tm["mesh_s"] += t1 - t0
    tm["bvh_s"] += time.perf_counter() - t1
    return _Instant(V, Vn, Vn[faces], corners, es, IV, IN)


def _render_camera(setup, inst: _Instant, c, tm, inst_mask):
    """Radiance (n, C) of the pixels ``idx`` (n,) of camera c that may see the geometry (the rest see the
    background) at one instant, averaged over the sub-pixel rays."""
    cam = setup.rig.cameras[c]
    W = cam.width
    C = 3 if setup.scene.optics.color else 1
    bg = np.float32(setup.scene.lighting.background)
    t0 = time.perf_counter()
    mask = hull_mask(cam, inst.V)
    if inst.IV is not None:
        mask |= hull_mask(cam, inst.IV)
    idx = np.flatnonzero(mask.ravel())
    faces = setup.surface.phantom.faces
    diffuse, spec = light_terms(inst.V, inst.Vn, cam.centre, setup.lights)  # Gouraud terms at the vertices
    inst.corners[..., 0] = diffuse[faces]
    inst.corners[..., 1] = spec[faces]
    hot_face = (inst.corners[..., 1] > SPECULAR_CUT).any(axis=1)
    tm["mesh_s"] += time.perf_counter() - t0
    ss = setup.scene.optics.supersampling
    offsets = [((i + 0.5) / ss - 0.5, (j + 0.5) / ss - 0.5) for j in range(ss) for i in range(ss)]
    rad = np.zeros((idx.size, C), np.float32)
    for ox, oy in offsets:
        t0 = time.perf_counter()
        d = setup.directions[c][idx] if ss == 1 else setup.grids[c].directions(idx % W + ox, idx // W + oy)
        hits = inst.scene.cast(cam.centre, d)
        t1 = time.perf_counter()
        tm["cast_s"] += t1 - t0
        sample = np.full((idx.size, C), bg, np.float32)
        heart = np.flatnonzero(hits.geom == 0)
        if heart.size:
            sample[heart] = _shade_heart(setup, inst.corners, hot_face, inst.normal_corners, hits, heart, cam.centre,
                                         d, C == 3)
        on = np.flatnonzero(hits.geom == 1)
        if on.size:
            sample[on] = _shade_instrument(setup, inst.IN, hits, on, cam.centre, d, C)
            inst_mask[c, idx[on]] = True
        rad += sample
        tm["shade_s"] += time.perf_counter() - t1
    if len(offsets) > 1:
        rad *= np.float32(1 / len(offsets))
    return idx, rad, idx.size * len(offsets)


def render_frame(setup: SequenceSetup, k: int, *, noise=True, encode=None) -> FrameResult:
    """Render frame ``k`` for every camera (module docstring). ``noise=False`` skips the sensor noise;
    ``encode(image)``, if given, replaces each image by its return value (e.g. PNG bytes)."""
    scene = setup.scene
    C = 3 if scene.optics.color else 1
    cams = setup.rig.cameras
    H, W = cams[0].height, cams[0].width
    bg = np.float32(scene.lighting.background)
    times = _subframe_times(setup, k)
    acc = [np.full((H * W, C), bg, np.float32) for _ in cams]
    inst_mask = np.zeros((len(cams), H * W), bool) if setup.instrument is not None else None
    tm = {"mesh_s": 0.0, "bvh_s": 0.0, "cast_s": 0.0, "shade_s": 0.0, "expose_s": 0.0}
    n_rays = 0
    for j, t in enumerate(times):
        inst = _instant(setup, t, tm)
        for c in range(len(cams)):
            idx, rad, n = _render_camera(setup, inst, c, tm, inst_mask)
            n_rays += n
            if len(times) == 1:
                acc[c][idx] = rad
            else:  # running mean over the exposure
                if j > 0:
                    acc[c] += np.float32(bg)
                acc[c][idx] += rad - bg
    images = []
    for c in range(len(cams)):
        t0 = time.perf_counter()
        img = acc[c].reshape(H, W, C)
        if len(times) > 1:
            img *= np.float32(1 / len(times))
        if C == 1:
            img = img[..., 0]
        rng = np.random.default_rng([scene.seed, 3, k, c]) if noise else None
        out = expose(img, scene.noise, rng, scene.optics.psf_sigma_px)
        t1 = time.perf_counter()
        tm["expose_s"] += t1 - t0
        if encode is not None:
            out = encode(out)
            tm["encode_s"] = tm.get("encode_s", 0.0) + time.perf_counter() - t1
        images.append(out)
    mask = None if inst_mask is None else inst_mask.reshape(len(cams), H, W)
    return FrameResult(k, images, mask, tm, n_rays)


def _job(setup, k_args):
    k, noise, encode = k_args
    return render_frame(setup, k, noise=noise, encode=encode)


def render_sequence(setup: SequenceSetup, *, frames=None, workers=1, noise=True, encode=None):
    """Yield :class:`FrameResult` for ``frames`` (default: all), in order, rendered by ``workers`` processes."""
    frames = range(setup.n_frames) if frames is None else frames
    yield from imap_ordered(_job, setup, [(k, noise, encode) for k in frames], workers)


def inputs_table(setup: SequenceSetup):
    """``(columns, values)``: the known inputs at the frame times, as ``inputs.csv`` holds them.

    Columns: ``time_s``, one ``<load>_pa`` per model load (``pressure_pa``, ``active_tension_pa``) and, with
    respiration, ``respiration_x_m``, ``respiration_y_m``, ``respiration_z_m`` (patch frame).
    """
    truth = setup.surface.truth
    cols = ["time_s"] + [f"{n}_pa" for n in truth.input_names]
    vals = [truth.frame_times[:, None], truth.inputs]
    if truth.translation is not None:
        cols += ["respiration_x_m", "respiration_y_m", "respiration_z_m"]
        vals.append(truth.translation(truth.frame_times))
    return cols, np.hstack(vals)


def sequence_truth(setup: SequenceSetup, instrument_masks=None, frames: int | None = None) -> tuple[dict, dict]:
    """Arrays and metadata of ``truth.npz`` (format ``heartcv.render_truth`` v1, kind ``sequence``; see
    docs/formats.md). ``instrument_masks``: the rendered frames' instrument masks bit-packed along the rows,
    ``numpy.packbits(mask, axis=-1)`` of each (n_cam, H, W) mask, stacked (K, n_cam, H, ceil(W / 8)), if any.
    ``frames``: the truth of the first ``frames`` frames only (every per-frame array; default all)."""
    s, truth, ph = setup.surface, setup.surface.truth, setup.surface.phantom
    T = s.world_from_patch
    K = setup.n_frames if frames is None else min(int(frames), setup.n_frames)
    times = np.asarray(setup.frame_times)[:K]
    verts = np.empty((K, ph.n_vertices, 3), np.float32)
    for k, t in enumerate(times):
        verts[k] = s.positions_world(t)
    to_world = lambda X: X @ T[:3, :3].T + T[:3, 3]  # noqa: E731
    cams = setup.rig.cameras
    arrays = {
        "times": times, "theta": truth.theta[:K], "inputs": truth.inputs[:K],
        "translation": truth.translation(times) if truth.translation else np.zeros((K, 3)),
        "world_from_patch": T, "faces": ph.faces, "reference_vertices": to_world(ph.vertices),
        "vertex_material": ph.material, "vertex_in_patch": ph.in_patch, "vertex_positions": verts,
        "point_param": truth.point_param, "point_positions": to_world(truth.point_positions[:K]),
        "fiducial_material": setup.texture.fiducials,
        "K": np.stack([c.K for c in cams]), "cam_from_world": np.stack([c.cam_from_rig for c in cams]),
        "cam_from_rig": np.stack([c.cam_from_rig for c in cams]),
        "image_size": np.array([cams[0].width, cams[0].height]),
    }
    nd = max(c.dist.size for c in cams)
    arrays["dist"] = np.stack([np.pad(c.dist, (0, nd - c.dist.size)) for c in cams])
    if setup.texture.fiducials.size:
        face, bary = locate(ph, setup.texture.fiducials)
        arrays["fiducial_positions"] = np.einsum("nc,kncj->knj", bary, verts[:, ph.faces[face]]).astype(np.float32)
    if setup.instrument is not None:
        arrays["instrument_tip"] = np.array([setup.instrument.tip(t) for t in times])
        arrays["instrument_present"] = np.array([setup.instrument.present(t) for t in times])
        if instrument_masks is not None:
            arrays["instrument_mask"] = np.asarray(instrument_masks, np.uint8)
    meta = {"kind": "sequence", "scene": setup.scene.name, "seed": setup.scene.seed,
            "seeds": {"texture": [setup.scene.seed, 1], "process_noise": [setup.scene.seed, 2],
                      "sensor_noise": [setup.scene.seed, 3, "frame", "camera"]},
            "camera_names": [c.name for c in cams], "input_names": list(truth.input_names),
            "world_frame": "cam0", "frame_rate_hz": setup.scene.motion.frame_rate_hz,
            "stiffness_cycle": {"amplitude": setup.scene.motion.stiffness_amplitude,
                                "shape": setup.scene.motion.stiffness_shape},
            "model": setup.model.info() | {"frame_rate_hz": setup.scene.motion.frame_rate_hz},
            "image_width": int(cams[0].width), "image_height": int(cams[0].height)}
    return arrays, meta

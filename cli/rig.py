"""``heartcv rig``: rig files from elsewhere.

- ``heartcv rig import``: a rig calibrated by another tool (OpenCV FileStorage, Kalibr camchain, COLMAP text model,
  caliscope TOML, plain-text matrices) -> a heartcv rig file (:mod:`heartcv.rig_formats` reads and converts);
- ``heartcv rig rectified``: the rig of a pre-rectified stereo pair from its focal length and baseline.

Both write one rig file (``heartcv.io.write_rig``), guarded before any work (docs/cli.md §1.4).
"""

from __future__ import annotations

import functools
import logging
from pathlib import Path

import click

from .options import MAX_IMAGE_SIDE, BadInput, Float, IntPair, announce, emit_json, guard_outputs, json_opt

log = logging.getLogger(__name__)

# heartcv.rig_formats.FORMATS and UNITS, repeated so that `heartcv --help` does not import numpy (checked by a test)
FORMATS = ("opencv", "kalibr", "colmap", "caliscope", "text")
UNITS = ("m", "cm", "mm")
MAX_BASELINE_M = 2.0


ImageSize = functools.partial(IntPair, "WxH", "360x288", MAX_IMAGE_SIDE, " px")  # (width, height)


class NameList(click.ParamType):
    """``a,b,...`` -> camera names (unique, non-empty, no spaces)."""

    name = "NAMES"

    def convert(self, value, param, ctx):
        if isinstance(value, (list, tuple)):
            return list(value)
        names = [n.strip() for n in str(value).split(",")]
        if any(not n or any(ch.isspace() for ch in n) for n in names) or len(set(names)) != len(names):
            self.fail(f"comma-separated unique names without spaces expected, got {value!r}", param, ctx)
        return names


class Point(click.ParamType):
    """``CX,CY`` -> two finite floats."""

    name = "CX,CY"

    def convert(self, value, param, ctx):
        if isinstance(value, tuple):
            return value
        try:
            x, y = (float(p) for p in str(value).split(","))
        except ValueError:
            self.fail(f"CX,CY expected (e.g. 179.5,143.5), got {value!r}", param, ctx)
        if not all(abs(v) < float("inf") for v in (x, y)):
            self.fail(f"{value!r}: finite numbers expected", param, ctx)
        return x, y


def _yaml_output(output) -> Path:
    out = Path(output)
    if out.suffix.lower() not in (".yaml", ".yml"):
        raise BadInput(f"-o/--output: a .yaml file expected, got {output}")
    return out


@click.group()
def rig():
    """Rig files from elsewhere: import another tool's calibration (`rig import`), or describe a pre-rectified
    stereo pair (`rig rectified`)."""


@rig.command("import")
@click.argument("files", nargs=-1, required=True, type=click.Path())
@click.option("--format", "fmt", type=click.Choice(FORMATS), default=None,
              help="Source format (default: detected from each file's name and content).")
@click.option("--units", type=click.Choice(UNITS), default=None,
              help="Length unit of the source's translations, converted to metres. Without it translations are "
                   "taken as metres, and a rig whose camera centres lie more than 2 m apart is refused.")
@click.option("--names", type=NameList(), default=None, metavar="A,B,...",
              help="Camera names in rig order (default: from the source: cam0.., cam_<id>, cam<id>, left/right).")
@click.option("--image-size", "image_sizes", type=ImageSize(), multiple=True, metavar="WxH",
              help="Image size where the files hold none (stereo_calib.cpp's files, text files): once for all "
                   "cameras or once per camera. Checked against the files that hold one.")
@click.option("-o", "--output", type=click.Path(dir_okay=False), required=True, help="Rig file to write (.yaml).")
@json_opt
def import_(files, fmt, units, names, image_sizes, output, as_json):
    """Import the rig in FILE... (one rig's files) into a heartcv rig file.

    \b
    opencv     FileStorage YAML/XML: camera_matrix + distortion_coefficients (one camera), or
               stereo_calib.cpp's intrinsics.yml (M1 D1 M2 D2) + extrinsics.yml (R T): cam1_from_cam0 = [R|T]
    kalibr     camchain YAML: cam0, cam1, ... (pinhole, radtan), T_cn_cnm1 = cam_n_from_cam_(n-1)
    colmap     a model folder (or its cameras.txt): cameras.txt + rigs.txt (COLMAP >= 3.12)
    caliscope  camera_array.toml or config.toml: x_cam = R x_world + t; rig frame = caliscope's world
    text       K (3x3), distortion rows and poses (4x4 cam_from_cam0) in camera order, or a folder in the
               Hamlyn layout (P.left.intrinsic.txt, P.left.distortion.txt, P.right.*, P.l2r.4x4)

    The rig frame is the first camera's, except for caliscope (its world frame). Rotations printed to few
    decimals (|R^T R - I| <= 1e-4) are re-orthonormalised. Exit 2 for a file that cannot be imported, naming it
    and the field.
    """
    from heartcv.io import write_rig
    from heartcv.rig_formats import finish_import, plan_import, read_foreign, side_warnings

    out = _yaml_output(output)
    fmt, sources = plan_import(files, fmt)
    inputs = {("FILE" if len(files) == 1 else f"FILE {i + 1}"): p for i, p in enumerate(files)}
    inputs.update({f"FILE ({p.name})": p for p in sources if p not in [Path(f) for f in files]})
    guard_outputs({"-o/--output": out}, inputs, files=[("-o/--output", out, ("heartcv.rig",))])
    imported = read_foreign(fmt, sources, image_sizes)
    for msg in imported.warnings:
        log.warning("%s", msg)
    for c in imported.corrections:
        log.info("%s: %s: re-orthonormalised (max |R^T R - I| = %.2g; correction %.3g deg)", c["file"], c["field"],
                 c["deviation"], c["angle_deg"])
    result = finish_import(imported, units, names)
    sides = side_warnings(result)
    for msg in sides:
        log.warning("%s", msg)
    write_rig(out, result)
    _summarise(result, output, as_json, warnings=list(imported.warnings) + sides)


@rig.command("rectified")
@click.option("--image-size", type=ImageSize(), default=None, metavar="WxH",
              help="Image size of both cameras (or --size-of).")
@click.option("--size-of", "size_of", type=click.Path(exists=True, file_okay=False), default=None,
              metavar="SEQUENCE", help="Take the image size from a sequence folder as `heartcv measure` reads it (its "
                                       "cameras --names; their first frames must agree) instead of --image-size.")
@click.option("--packed", type=click.Choice(("side-by-side", "top-bottom", "rows")), default=None,
              help="With --size-of: SEQUENCE packs both views into every frame (as `heartcv measure --packed`); the "
                   "size of one view.")
@click.option("--focal-px", type=Float(0, 1e6, lo_open=True), default=None,
              help="Focal length f in pixels (or --hfov-deg).")
@click.option("--hfov-deg", type=Float(0, 180, lo_open=True, hi_open=True), default=None,
              help="Horizontal field of view instead of --focal-px: f = (W / 2) / tan(hfov / 2).")
@click.option("--principal-point", type=Point(), default=None, metavar="CX,CY",
              help="Principal point in pixels, OpenCV convention (default: the image centre ((W-1)/2, (H-1)/2)).")
@click.option("--baseline-m", type=Float(0, 1e3, lo_open=True), required=True,
              help="Distance between the two projection centres, in metres (at most 2 m).")
@click.option("--names", type=NameList(), default="cam0,cam1", show_default=True, metavar="LEFT,RIGHT",
              help="The two camera names, left first (default: heartcv's folder names, as `heartcv measure` reads "
                   "them: SEQUENCE/cam0, SEQUENCE/cam1).")
@click.option("-o", "--output", type=click.Path(dir_okay=False), required=True, help="Rig file to write (.yaml).")
@json_opt
def rectified(image_size, size_of, packed, focal_px, hfov_deg, principal_point, baseline_m, names, output, as_json):
    """Write the rig of a pre-rectified stereo pair: both cameras K = [[f, 0, cx], [0, f, cy], [0, 0, 1]], no
    distortion; the left camera is the rig frame, the right one sits baseline metres to its right
    (cam_from_rig = [I | (-B, 0, 0)])."""
    import math

    from heartcv.io import write_rig
    from heartcv.rig_formats import rectified_rig

    if len(names) != 2:
        raise BadInput(f"--names: two names expected (left,right), got {len(names)}")
    if (image_size is None) == (size_of is None):
        raise BadInput("--image-size or --size-of: one of them expected" if image_size is None else
                       "--image-size and --size-of: one of them, not both")
    if packed is not None and size_of is None:
        raise BadInput("--packed: only with --size-of (the sequence whose frames pack the views)")
    if (focal_px is None) == (hfov_deg is None):
        raise BadInput("--focal-px or --hfov-deg: one of them expected" if focal_px is None else
                       "--focal-px and --hfov-deg: one of them, not both")
    w, h = image_size if image_size is not None else _sequence_size(size_of, names, packed)
    if hfov_deg is not None:
        focal_px = (w / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
    if baseline_m > MAX_BASELINE_M:
        raise BadInput(f"--baseline-m: baseline {baseline_m:.3g} m: looks like millimetres; give it in metres (e.g. "
                       f"--baseline-m {baseline_m / 1000:.3g} for {baseline_m:.3g} mm); a rectified rig spans at most "
                       f"{MAX_BASELINE_M:g} m")
    if principal_point is not None:
        cx, cy = principal_point
        if not (-0.5 <= cx <= w - 0.5 and -0.5 <= cy <= h - 0.5):
            raise BadInput(f"--principal-point: {cx:g},{cy:g} lies outside the {w}x{h} image (-0.5 .. W-0.5, "
                           "-0.5 .. H-0.5)")
    out = _yaml_output(output)
    guard_outputs({"-o/--output": out}, {}, files=[("-o/--output", out, ("heartcv.rig",))])
    result = rectified_rig(w, h, focal_px, baseline_m, principal_point, names)
    result = type(result)(result.cameras, {"producer": "heartcv rig rectified", "rectified": True,
                                           "focal_px": focal_px, "baseline_m": baseline_m,
                                           "principal_point": list(result.cameras[0].K[:2, 2])})
    write_rig(out, result)
    _summarise(result, output, as_json)


def _sequence_size(sequence, names, packed):
    """``(W, H)`` of the views of a sequence folder as ``heartcv measure`` reads it (cameras ``names``, ``packed``):
    the first instant where both cameras' images read; exit 2 naming the sequence where they differ or none
    reads."""
    from heartcv.io import FrameReader, open_frame_source
    from heartcv.tracker.files import InputError

    source = open_frame_source(sequence, cameras=names, packing=packed)
    with FrameReader(source, frames=range(source.n_frames), workers=1) as reader:
        for k in range(source.n_frames):
            views, _ = reader.read(k)
            if all(v is not None for v in views):
                sizes = [(v.shape[1], v.shape[0]) for v in views]
                if len(set(sizes)) > 1:
                    raise InputError(sequence, f"instant {source.frame_names[k]}: the views are "
                                     + " and ".join(f"{a}x{b}" for a, b in sizes) + " px: a rectified pair's views "
                                     "have one size", "image size")
                log.info("image size %dx%d px, from %s (instant %s)", *sizes[0], sequence, source.frame_names[k])
                return sizes[0]
    raise InputError(sequence, "no instant where both cameras' images read", "image size")


def _summarise(result, output, as_json, warnings=()):
    meta = result.meta
    cams = [{"name": c.name, "image_size": [c.width, c.height], "fx": c.K[0, 0], "fy": c.K[1, 1], "cx": c.K[0, 2],
             "cy": c.K[1, 2], "dist": c.dist.tolist(), "centre_m": c.centre.tolist()} for c in result.cameras]
    import numpy as np

    c0 = result.cameras[0]
    rig_frame = c0.name if np.array_equal(c0.cam_from_rig, np.eye(4)) else "custom"
    summary = {"output": output, "producer": meta["producer"], "cameras": cams, "baselines_m": result.baselines(),
               "rig_frame": rig_frame}
    for key in ("source_format", "source_files", "source_rig_frame", "units_conversion", "orthonormalised",
                "rectified", "focal_px", "baseline_m", "principal_point"):
        if key in meta:
            summary[key] = meta[key]
    if warnings:
        summary["warnings"] = list(warnings)
    if as_json:
        emit_json(summary)
        return
    base = ", ".join(f"{k} {v * 1e3:.6g} mm" for k, v in summary["baselines_m"].items()) or "none (one camera)"
    src = f" from {meta['source_format']}" if "source_format" in meta else ""
    announce(log, "wrote %s: %d camera%s (%s)%s, rig frame %s, baselines %s", output, len(cams), "s"[:len(cams) > 1],
             ", ".join(c["name"] for c in cams), src, rig_frame, base)

"""The calibration report of ``heartcv calibrate --report DIR``: figures and a page a person looks at.

:func:`write_calibration_report` writes, with :func:`heartcv.tracker.files.atomic_folder` (producer
``heartcv calibrate --report``), a folder of

- ``coverage.png``: per camera, where in the image the target's corners were seen (2-D histogram of the corners
  of the used views, the union of their convex hulls tinted, unused views' corners as grey points);
- ``residuals.png``: per camera, the reprojection residual of every corner as an arrow (projected minus
  detected, magnified by one stated factor for all cameras) and the histogram of the residual norms;
- ``view_errors.png``: per camera, the RMS of every view, rejected views marked, and the outlier threshold
  when the rig's metadata gives one;
- ``poses.png``: the cameras as frustums and the board poses as quadrilaterals in the rig frame (metres);
- ``index.html``: per-camera table (intrinsics with their standard deviations, RMS, views, coverage), the
  warnings, the baselines, and the figures with what to look for (relative links only, no JavaScript).

Residuals are recomputed here from the calibration: ``camera.project(rig_from_board[v] X_board) - uv`` for
every corner of every used camera view; the RMS is over corners of the pixel distance (OpenCV's).
"""

from __future__ import annotations

from html import escape
import math
from pathlib import Path

import numpy as np

from .plots import save_png

__all__ = ["PRODUCER", "CAPTIONS", "write_calibration_report", "hull_coverage", "corner_residuals"]

PRODUCER = "heartcv calibrate --report"
FIGURES = ("coverage.png", "residuals.png", "view_errors.png", "poses.png")
CAPTIONS = {
    "coverage.png": "Where the target's corners were seen in each image: 2-D histogram of the corners of the views "
                    "used (colour: corners per bin), the union of those views' convex hulls tinted and outlined in "
                    "green, corners of views not used as grey points. Look for: the green area reaching the corners "
                    "and edges of the image; the distortion is only measured where corners were seen.",
    "residuals.png": "Reprojection residual of every corner of the views used (projected minus detected, magnified "
                     "by the factor in the legend), and the histogram of the residual norms. Look for: arrows of "
                     "random direction and no pattern; arrows that line up or grow towards the image edges mean "
                     "a distortion model too small or a bent board; a long tail in the histogram, bad detections.",
    "view_errors.png": "RMS of each view per camera (view index across); views rejected as outliers marked with a "
                       "red cross (a red triangle with the value when off the axis), views with corners that were "
                       "not used with a grey triangle, the outlier threshold (dashed red) when the rig file gives "
                       "one. Look for: single views far above the rest (motion blur, a wrong detection) and drifts "
                       "along the sequence.",
    "poses.png": "Cameras (frustums, labelled) and board poses (grey outlines) in the rig frame, metres, equal "
                 "scale on every axis (vertical axis: y, pointing down). Look for: the cameras where the rig has "
                 "them (baselines, convergence), boards spread over the working volume and tilted in several "
                 "directions; a camera far off or boards behind a camera mean a failed calibration.",
}
_MAX_MASK_PX = 4096  # coverage masks are rasterised with at most this many pixels along the longer side
_COLS = 3


# -- numbers ------------------------------------------------------------------------------------------------
def corner_residuals(cal, detections, spec) -> list[dict]:
    """Residuals of the corners of the used camera views, per camera.

    Returns
    -------
    list (n_cameras) of dict
        ``uv`` (N, 2) detected pixels, ``r`` (N, 2) projected minus detected pixels, ``view`` (N,) view index.
    """
    obj = spec.object_points()
    out = []
    for c, cam in enumerate(cal.rig.cameras):
        uv, r, view = [np.zeros((0, 2))], [np.zeros((0, 2))], [np.zeros(0, int)]
        for v in np.flatnonzero(cal.used[c]):
            det, T = detections[c][v], np.asarray(cal.rig_from_board[v], float)
            if det is None or not len(det.ids) or not np.isfinite(T).all():
                continue
            X_rig = obj[det.ids] @ T[:3, :3].T + T[:3, 3]
            uv.append(det.uv)
            r.append(cam.project(X_rig) - det.uv)
            view.append(np.full(len(det.ids), v))
        out.append({"uv": np.concatenate(uv), "r": np.concatenate(r), "view": np.concatenate(view)})
    return out


def _rms(r) -> float:
    return float(np.sqrt((r ** 2).sum(axis=1).mean())) if len(r) else math.nan


def hull_coverage(size, point_sets) -> tuple[float, np.ndarray]:
    """Fraction of the image covered by the union of the convex hulls of point sets, and the mask (on a grid
    whose longer side has at most 4096 pixels): :func:`heartcv.calibration_checks.coverage_mask`."""
    from heartcv.calibration_checks import coverage_mask

    return coverage_mask(point_sets, size, _MAX_MASK_PX)


def _views_points(cal, detections, c, used: bool) -> list:
    return [detections[c][v].uv for v in range(cal.used.shape[1])
            if bool(cal.used[c, v]) == used and detections[c][v] is not None and len(detections[c][v].ids)]


def _threshold(meta, name):
    """Outlier threshold (px) of a camera from the rig's metadata, or None."""
    t = ((meta.get("cameras") or {}).get(name) or {}).get("outlier_threshold_px")
    if t is None:
        t = meta.get("outlier_threshold_px")
        t = t.get(name) if isinstance(t, dict) else t
    return float(t) if isinstance(t, (int, float)) and math.isfinite(t) else None


def _tex(text: str) -> str:
    """Text for matplotlib, where ``$`` would start mathtext."""
    return text.replace("$", r"\$")


def _nice(x) -> float:
    """The largest of 1, 2, 5 x 10^k not above x."""
    e = 10 ** math.floor(math.log10(x))
    return max(m * e for m in (1, 2, 5) if m * e <= x * (1 + 1e-12))


# -- figures ------------------------------------------------------------------------------------------------
def _grid(n_cam, aspect, width=4.6):
    """Panels per camera: ``len(aspect)`` rows each (height / width of each row), at most 3 cameras across."""
    from matplotlib.figure import Figure

    ncols = min(n_cam, _COLS)
    nrows = math.ceil(n_cam / ncols)
    heights = [width * a + 0.9 for a in aspect]
    fig = Figure(figsize=(width * ncols, nrows * sum(heights)), layout="constrained")
    axes = fig.subplots(nrows * len(aspect), ncols, squeeze=False, height_ratios=heights * nrows)
    panels = [[axes[(c // ncols) * len(aspect) + k, c % ncols] for k in range(len(aspect))] for c in range(n_cam)]
    shown = {id(ax) for p in panels for ax in p}
    for ax in axes.ravel():
        ax.set_visible(id(ax) in shown)
    return fig, panels


def _image_axes(ax, cam, below=0.0):
    """Axes showing the image rectangle (true aspect, rows downwards), with ``below`` (share of the height) of
    blank space under it."""
    from matplotlib.patches import Rectangle

    ax.add_patch(Rectangle((-0.5, -0.5), cam.width, cam.height, fill=False, lw=1.0, color="0.2", zorder=5))
    ax.set_xlim(-0.5, cam.width - 0.5)
    ax.set_ylim(cam.height - 0.5 + below * cam.height, -0.5)
    ax.set_aspect("equal")
    ax.set_xlabel("u [px]", fontsize=8)
    ax.set_ylabel("v [px]", fontsize=8)
    ax.tick_params(labelsize=7)


def _coverage_figure(cal, detections, coverage, masks):
    from matplotlib.ticker import MaxNLocator

    cams = cal.rig.cameras
    fig, panels = _grid(len(cams), [max(c.height / c.width for c in cams)])
    for c, cam in enumerate(cams):
        ax = panels[c][0]
        used_pts = _views_points(cal, detections, c, True)
        other = _views_points(cal, detections, c, False)
        m = masks[c][::max(1, max(masks[c].shape) // 1000), ::max(1, max(masks[c].shape) // 1000)]  # display
        ax.imshow(np.where(m, 1.0, np.nan), cmap="Greens", vmin=0, vmax=3, interpolation="nearest",
                  extent=(-0.5, cam.width - 0.5, cam.height - 0.5, -0.5), zorder=1)
        if other:
            p = np.concatenate(other)
            ax.scatter(p[:, 0], p[:, 1], s=3, color="0.55", alpha=0.6, lw=0, zorder=2)
        bin_px = max(cam.width, cam.height) / 24
        ex, ey = (np.linspace(-0.5, n - 0.5, max(1, round(n / bin_px)) + 1) for n in cam.size)
        p = np.concatenate(used_pts) if used_pts else np.zeros((0, 2))
        H, _, _ = np.histogram2d(p[:, 0], p[:, 1], bins=(ex, ey))
        im = ax.pcolormesh(ex, ey, np.ma.masked_equal(H.T, 0), cmap="viridis", alpha=0.85, zorder=3)
        cb = fig.colorbar(im, ax=ax, shrink=0.8, pad=0.01)
        cb.set_label("corners per bin", fontsize=7)
        cb.ax.tick_params(labelsize=7)
        cb.locator = MaxNLocator(integer=True)
        cb.update_ticks()
        if m.any():
            mh, mw = m.shape
            ax.contour((np.arange(mw) + 0.5) * cam.width / mw - 0.5, (np.arange(mh) + 0.5) * cam.height / mh - 0.5,
                       m.astype(float), levels=[0.5], colors="#2a8c3a", linewidths=1.2, zorder=4)
        _image_axes(ax, cam)
        ax.set_title(f"{_tex(cam.name)}: coverage {100 * coverage[c]:.1f} % ({len(used_pts)} views used)",
                     fontsize=9)
    return fig


def _residual_figure(cal, res):
    from matplotlib.lines import Line2D

    cams = cal.rig.cameras
    norms = [np.linalg.norm(x["r"], axis=1) for x in res]
    allnorm = np.concatenate(norms)
    p95 = float(np.percentile(allnorm, 95)) if allnorm.size and allnorm.max() > 0 else 1.0
    key = _nice(p95)
    mag = _nice(0.05 * max(c.width for c in cams) / key)  # a typical residual is drawn ~5 % of the image width
    top = float(allnorm.max()) * 1.05 if allnorm.size and allnorm.max() > 0 else 1e-3
    bins = np.linspace(0, top, 41)  # the same bins for every camera
    fig, panels = _grid(len(cams), [max(c.height / c.width for c in cams) * 1.1, 0.45])
    for c, cam in enumerate(cams):
        ax, hx = panels[c]
        uv, r = res[c]["uv"], res[c]["r"]
        ax.scatter(uv[:, 0], uv[:, 1], s=2, color="0.45", lw=0, zorder=2)
        q = ax.quiver(uv[:, 0], uv[:, 1], r[:, 0], r[:, 1], angles="xy", scale_units="xy", scale=1 / mag,
                      color="#1f4e9c", width=0.0035, zorder=3)
        _image_axes(ax, cam, below=0.1)
        ax.quiverkey(q, 0.5, 0.045, key, f"{key:g} px (arrow ×{mag:g}) ", labelpos="W", coordinates="axes",
                     color="k", fontproperties={"size": 7})
        rms = _rms(r)
        ax.set_title(f"{_tex(cam.name)}: " + (f"RMS {rms:.3f} px, {len(r)} corners" if len(r) else
                                              "no corners in the views used"), fontsize=9)
        hx.hist(norms[c], bins=bins, color="#1f77b4", alpha=0.8)
        hx.set_xlim(0, top)
        hx.ticklabel_format(axis="x", useOffset=False)
        if math.isfinite(rms):
            hx.axvline(rms, color="k", ls="--", lw=1.0)
        hx.set_xlabel("residual norm [px]", fontsize=8)
        hx.set_ylabel("corners", fontsize=8)
        hx.tick_params(labelsize=7)
        if len(r):
            hx.legend(handles=[Line2D([], [], color="k", ls="--", lw=1.0, label=f"RMS {rms:.3f} px")], fontsize=7,
                      frameon=False)
    return fig, mag


def _view_error_figure(cal, detections):
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
    from matplotlib.ticker import MaxNLocator

    cams, meta = cal.rig.cameras, cal.rig.meta
    n_views = cal.used.shape[1]
    fig = Figure(figsize=(min(16.0, 6.4 + 0.06 * n_views), 0.4 + 1.9 * len(cams)), layout="constrained")
    axes = fig.subplots(len(cams), 1, sharex=True, squeeze=False)[:, 0]
    x = np.arange(n_views)
    has = {"thr": False, "rej": False, "unused": False}
    for c, (ax, cam) in enumerate(zip(axes, cams)):
        rms, used = np.asarray(cal.view_rms[c], float), np.asarray(cal.used[c], bool)
        rejected = ~used & np.isfinite(rms)
        seen = np.array([d is not None and len(d.ids) > 0 for d in detections[c]])
        idle = ~used & ~rejected & seen
        good = np.where(used, rms, np.nan)
        thr = _threshold(meta, cam.name)
        top = np.nanmax(np.r_[good[np.isfinite(good)], [thr or 0.0], [1e-3]]) * 1.25
        ax.bar(x[used], good[used], width=0.8, color="#1f77b4")
        clip = rejected & (rms > top)
        ax.plot(x[rejected & ~clip], rms[rejected & ~clip], "x", color="#d62728", ms=7, mew=2)
        ax.plot(x[clip], np.full(clip.sum(), top * 0.96), "^", color="#d62728", ms=6)
        for v in np.flatnonzero(clip):
            ax.annotate(f"{rms[v]:.3g}", (v, top * 0.96), xytext=(5, 0), textcoords="offset points",
                        fontsize=7, color="#d62728", va="center")
        ax.plot(x[idle], np.full(idle.sum(), 0.03 * top), "v", color="0.5", ms=5)
        if thr is not None:
            ax.axhline(thr, color="#d62728", ls="--", lw=1.0)
        has["thr"] |= thr is not None
        has["rej"] |= bool(rejected.any())
        has["unused"] |= bool(idle.any())
        ax.set_ylim(0, top)
        ax.set_ylabel(f"{_tex(cam.name)}\nview RMS [px]", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(True, axis="y", alpha=0.3)
        notes = [f"{int(used.sum())} views used"] + [f"{int(m.sum())} {what}" for m, what in (
            (rejected, "rejected"), (idle, "not used"), (~seen, "without corners")) if m.any()]
        ax.set_title(f"{_tex(cam.name)}: " + ", ".join(notes), fontsize=9, loc="left")
    axes[-1].set_xlabel("view index")
    axes[-1].xaxis.set_major_locator(MaxNLocator(integer=True))
    axes[-1].set_xlim(-0.7, n_views - 0.3)
    handles = [Patch(color="#1f77b4", label="used view")]
    if has["rej"]:
        handles.append(Line2D([], [], marker="x", ls="", color="#d62728", mew=2, label="rejected (▲: off the axis)"))
    if has["unused"]:
        handles.append(Line2D([], [], marker="v", ls="", color="0.5", label="not used"))
    if has["thr"]:
        handles.append(Line2D([], [], color="#d62728", ls="--", label="outlier threshold"))
    fig.legend(handles=handles, loc="outside lower center", ncol=len(handles), fontsize=8, frameon=False)
    return fig


def _board_outlines(cal, spec) -> np.ndarray:
    """Board corner outlines (n, 4, 3) in the rig frame, for the views with a finite pose."""
    (ox, oy), (w, h) = spec.squares_origin_m, spec.board_size_m
    quad = np.array([[ox, oy, 0], [ox + w, oy, 0], [ox + w, oy + h, 0], [ox, oy + h, 0]], float)
    T = np.asarray(cal.rig_from_board, float)
    T = T[np.isfinite(T).all(axis=(1, 2))]
    return np.einsum("vij,kj->vki", T[:, :3, :3], quad) + T[:, None, :3, 3]


def _frustum(cam, depth) -> np.ndarray:
    """Centre and the four image corners at ``depth`` (5, 3), rig frame."""
    corners = np.array([[-0.5, -0.5], [cam.width - 0.5, -0.5], [cam.width - 0.5, cam.height - 0.5],
                        [-0.5, cam.height - 0.5]])
    xy = np.linalg.solve(cam.K, np.c_[corners, np.ones(4)].T).T  # pinhole rays, z = 1
    X_cam = np.r_[np.zeros((1, 3)), xy * depth]
    return (X_cam - cam.t) @ cam.R  # R^T (X - t)


def _pose_figure(cal, spec):
    from matplotlib.figure import Figure

    cams = cal.rig.cameras
    boards = _board_outlines(cal, spec)
    centres = np.array([c.centre for c in cams])
    pts = np.concatenate([centres, boards.reshape(-1, 3)])
    extent = float(np.ptp(pts, axis=0).max()) or 0.1
    # frustums about 12 % of the scene wide (long for narrow lenses: they point at what the camera sees)
    frusta = [_frustum(c, float(np.clip(0.12 * extent * c.K[0, 0] / c.width, 0.1 * extent, 0.5 * extent)))
              for c in cams]
    pts = np.concatenate([pts] + frusta)
    fig = Figure(figsize=(7.5, 6.5), layout="constrained")
    ax = fig.add_subplot(projection="3d")
    show = [0, 2, 1]  # plot axes (x, z, y): the depth axis recedes, y (down) is vertical and inverted
    for quad in boards:
        q = np.r_[quad, quad[:1]][:, show]
        ax.plot(q[:, 0], q[:, 1], q[:, 2], color="0.55", lw=0.7, alpha=0.8)
    for i, (cam, F) in enumerate(zip(cams, frusta)):
        color = f"C{i % 10}"
        F = F[:, show]
        for k in range(1, 5):
            ax.plot(*np.c_[F[0], F[k]], color=color, lw=1.2)
        ring = F[[1, 2, 3, 4, 1]]
        ax.plot(ring[:, 0], ring[:, 1], ring[:, 2], color=color, lw=1.8)
        ax.plot(*F[1:3].T, color=color, lw=3.5)  # the top edge of the image (v = 0)
        ax.text(F[0, 0], F[0, 1], F[0, 2] - 0.05 * extent, _tex(cam.name), color=color, fontsize=10,
                fontweight="bold", ha="center")  # above the centre: the vertical plot axis is y (down), inverted
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    mid, half = (lo + hi) / 2, (hi - lo).max() / 2 * 1.05
    for k, setlim in zip(show, (ax.set_xlim, ax.set_ylim, ax.set_zlim)):
        setlim(mid[k] - half, mid[k] + half)
    ax.invert_zaxis()
    ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel("x (right) [m]")
    ax.set_ylabel("z (forward) [m]")
    ax.set_zlabel("y (down) [m]")
    ax.view_init(elev=22, azim=-62)
    ax.tick_params(labelsize=7)
    ax.set_title(f"{len(cams)} cameras (thick edge: top of the image), {len(boards)} board poses; rig frame = "
                 f"{_tex(cams[0].name)}'s", fontsize=9)
    return fig


# -- page ---------------------------------------------------------------------------------------------------
def _table(head, rows, attrs=None) -> str:
    attrs = attrs or [[""] * len(r) for r in rows]
    return ("<table><tr>" + "".join(f"<th>{escape(h)}</th>" for h in head) + "</tr>"
            + "".join("<tr>" + "".join(f"<td{a}>{escape(c)}</td>" for c, a in zip(r, ra)) + "</tr>"
                      for r, ra in zip(rows, attrs)) + "</table>")


def _camera_rows(cal, detections, res, coverage):
    meta = cal.rig.meta
    cam_meta = [((meta.get("cameras") or {}).get(cam.name) or {}) for cam in cal.rig.cameras]
    held = meta.get("heldout_rms_px")
    held = [m.get("heldout_rms_px", held.get(cam.name) if isinstance(held, dict) else None)
            for m, cam in zip(cam_meta, cal.rig.cameras)]
    with_held = any(isinstance(h, (int, float)) for h in held)
    head = ["camera", "image [px]", "fx [px]", "fy [px]", "cx [px]", "cy [px]", "RMS [px]", "views used",
            "coverage"] + (["held-out RMS [px]"] if with_held else [])
    rows, attrs = [], []
    for c, cam in enumerate(cal.rig.cameras):
        std = cam_meta[c].get("std") or {}
        vals = {"fx": cam.K[0, 0], "fy": cam.K[1, 1], "cx": cam.K[0, 2], "cy": cam.K[1, 2]}
        cells = [f"{v:.2f}" + (f" ± {std[k]:#.2g}" if isinstance(std.get(k), (int, float)) else "")
                 for k, v in vals.items()]
        rms = _rms(res[c]["r"])
        seen = sum(d is not None and len(d.ids) > 0 for d in detections[c])
        row = [cam.name, f"{cam.width}×{cam.height}", *cells, "–" if math.isnan(rms) else f"{rms:.4f}",
               f"{int(cal.used[c].sum())} of {seen}", f"{100 * coverage[c]:.1f} %"]
        if with_held:
            row.append(f"{held[c]:.4f}" if isinstance(held[c], (int, float)) else "–")
        rows.append(row)
        a = [""] * len(row)
        a[6] = f' class="rms" data-rms-px="{rms!r}"'
        attrs.append(a)
    return head, rows, attrs


def _baseline_rows(rig):
    rows = []
    for i, a in enumerate(rig.cameras):
        for b in rig.cameras[i + 1:]:
            cos = float(np.clip(a.R[2] @ b.R[2], -1, 1))  # optical axes in the rig frame: the rows z of R
            rows.append([f"{a.name}–{b.name}", f"{1e3 * np.linalg.norm(a.centre - b.centre):.2f}",
                         f"{math.degrees(math.acos(cos)):.2f}"])
    return ["cameras", "baseline [mm]", "angle between optical axes [°]"], rows


def _page(cal, detections, spec, res, coverage, title, warnings, mag) -> str:
    rig, meta = cal.rig, cal.rig.meta
    allr = np.concatenate([x["r"] for x in res])
    total = _rms(allr)
    facts = [f"Target: {spec.type} {spec.inner_size[0]}×{spec.inner_size[1]} inner corners, squares of "
             f"{spec.square_m * 1e3:g} mm.",
             f"Views: {int(cal.used.any(axis=0).sum())} of {cal.used.shape[1]} instants used by at least one "
             f"camera; {len(allr)} corners in the residuals.",
             f"Reprojection RMS over all cameras: {total:.4f} px (projected minus detected corner, the views used)."]
    held = meta.get("heldout_rms_px")
    if isinstance(held, (int, float)):
        facts.append(f"Held-out RMS: {held:.4f} px.")
    warn = list(warnings) + [w for w in meta.get("warnings") or [] if w not in warnings]
    wl = ("<ul class=\"warnings\">" + "".join(f"<li>{escape(str(w))}</li>" for w in warn) + "</ul>" if warn
          else "<p>No warnings.</p>")
    figs = "".join(f'<figure><a href="{n}"><img src="{n}" alt="{escape(n)}"></a><figcaption><b>{escape(n)}</b>: '
                   f"{escape(CAPTIONS[n])}" + (f" Arrows are magnified ×{mag:g}." if n == "residuals.png" else "")
                   + "</figcaption></figure>" for n in FIGURES)
    style = ("body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}"
             "table{border-collapse:collapse;font-size:90%;margin:0.5em 0}td,th{border:1px solid #ccc;"
             "padding:3px 8px;text-align:right}td:first-child,th:first-child{text-align:left}"
             "figure{margin:2em 0}img{max-width:100%}figcaption{font-size:90%;color:#444}"
             ".warnings li{color:#a00}")
    return ("<!DOCTYPE html>\n<!-- heartcv calibration report -->\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{escape(title)}</title><style>{style}</style></head><body><h1>{escape(title)}</h1>"
            "<ul>" + "".join(f"<li>{escape(f)}</li>" for f in facts) + "</ul>"
            f"<h2>Cameras</h2>{_table(*_camera_rows(cal, detections, res, coverage))}"
            "<p>± one standard deviation from the joint refinement, where the rig file gives one. Coverage: the "
            "share of the image inside the union of the convex hulls of the used views' corners.</p>"
            f"<h2>Warnings</h2>{wl}<h2>Baselines</h2>{_table(*_baseline_rows(rig))}"
            f"<h2>Figures</h2>{figs}</body></html>\n")


# -- the report ---------------------------------------------------------------------------------------------
def write_calibration_report(folder: Path, cal, detections, spec, *, title: str, warnings: list[str],
                             dpi: int = 110) -> dict:
    """Write the calibration report folder (module docstring) atomically.

    Parameters
    ----------
    folder : Path
        The report folder; an existing one is replaced only if an earlier report wrote it
        (:func:`heartcv.tracker.files.atomic_folder`, which raises InputError otherwise, before any work).
    cal : heartcv.calibration_rig.RigCalibration
        Only ``rig``, ``rig_from_board`` (n_views, 4, 4), ``used`` and ``view_rms`` (n_cameras, n_views) are read.
    detections : sequence (n_cameras) of sequences (n_views) of heartcv.detect.Detection or None
    spec : heartcv.targets.TargetSpec
    title : str
        Page title.
    warnings : list of str
        Shown on the page (with any ``rig.meta['warnings']`` not among them), HTML-escaped.

    Returns
    -------
    dict
        ``folder``, ``index`` (Paths), ``figures`` {file name: Path}, ``coverage`` {camera: fraction in [0, 1]},
        ``rms_px`` {camera: RMS px, NaN without residuals}, ``arrow_scale`` (magnification of residuals.png).
    """
    from heartcv.tracker.files import atomic_folder, check_output_folder

    folder = Path(folder)
    check_output_folder(folder, PRODUCER, "--report")  # refused before any work (atomic_folder checks again)
    n_cam, n_views = np.shape(cal.used)
    if len(cal.rig) != n_cam or len(detections) != n_cam or any(len(d) != n_views for d in detections) \
            or np.shape(cal.rig_from_board) != (n_views, 4, 4) or np.shape(cal.view_rms) != (n_cam, n_views):
        raise ValueError(f"calibration report: {n_cam} cameras x {n_views} views expected in rig, detections, "
                         "rig_from_board and view_rms")
    names = cal.rig.names
    res = corner_residuals(cal, detections, spec)
    cov = [hull_coverage(cam.size, _views_points(cal, detections, c, True)) for c, cam in enumerate(cal.rig.cameras)]
    coverage = [f for f, _ in cov]
    rms = {n: _rms(x["r"]) for n, x in zip(names, res)}
    manifest = {"title": title, "files": ["index.html", *FIGURES], "coverage": dict(zip(names, coverage)),
                "rms_px": {n: (None if math.isnan(v) else v) for n, v in rms.items()}}
    with atomic_folder(folder, PRODUCER, manifest) as tmp:
        residual_fig, mag = _residual_figure(cal, res)
        for name, fig in zip(FIGURES, (_coverage_figure(cal, detections, coverage, [m for _, m in cov]),
                                       residual_fig, _view_error_figure(cal, detections), _pose_figure(cal, spec))):
            save_png(fig, tmp / name, dpi=dpi)
        page = _page(cal, detections, spec, res, coverage, title, warnings, mag)
        (tmp / "index.html").write_text(page, encoding="utf-8")
    return {"folder": folder, "index": folder / "index.html", "figures": {n: folder / n for n in FIGURES},
            "coverage": dict(zip(names, coverage)), "rms_px": rms, "arrow_scale": mag}

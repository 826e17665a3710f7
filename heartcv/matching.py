"""Cross-view association of reference corners: a plane sweep along each corner's viewing ray.

The rig's cameras are far apart (docs/design.md §7: the pairs see the surface 43–57° apart), so a patch looks
different in every view and plain descriptor matching is unreliable. Instead, for each corner of the reference
camera, candidate 3-D points are taken along its viewing ray (every ``step_px`` pixels of motion along the
epipolar curves of the other cameras, only where the ray is inside every other image); at each candidate the
reference patch is mapped into every other camera through the plane through the candidate with normal ``n``
(the homography induced by that plane, with the full distortion model), and the zero-mean NCC of the mapped
patch with the other camera's image is computed. The score of a candidate is the mean NCC over the other
cameras, so a depth must agree in all of them at once (trinocular consistency removes nearly all ambiguity).

The sweep runs coarse to fine: on the images blurred and subsampled to ``coarse_level`` (every ``2**level``
pixels), then at full resolution around the coarse optimum with sub-pixel steps and a parabola through the
best three scores. Normals: first the bisector of the directions to the cameras (the surface faces the rig);
after a first pass, each point's normal is fitted to its triangulated neighbours and the fine sweep repeated.

The epipolar constraint is built in (candidates lie on the ray); photometric verification is the NCC
threshold ``min_ncc`` per view. Okutomi & Kanade, "A multiple-baseline stereo", PAMI 1993; Collins, "A
space-sweep approach to true multi-image matching", CVPR 1996; Gallup et al., "Real-time plane-sweeping stereo
with multiple sweeping directions", CVPR 2007.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .backend import OpenCVBackend

__all__ = ["MatchResult", "match_points", "ray_depth_range", "patch_offsets", "normal_hypotheses",
           "local_planes", "bisector_normals", "descriptor_matches", "descriptor_v_offset",
           "descriptor_epipolar_distance", "descriptor_front_fraction", "descriptor_inliers"]


@dataclass(frozen=True)
class MatchResult:
    """Correspondences of reference corners in every camera.

    Attributes
    ----------
    uv : ndarray (N, C, 2)        matched pixel position per camera (the reference camera's is the corner itself);
                                  NaN where not matched
    score : ndarray (N, C)        NCC of the warped reference patch in each camera (1 for the reference camera)
    depth : ndarray (N,)          distance along the reference ray (m), NaN where no depth was found
    points : ndarray (N, 3)       the matched 3-D point on the reference ray (rig frame)
    normals : ndarray (N, 3)      the plane normal used last
    ok : ndarray (N,)             matched in at least ``min_views`` cameras (the reference included)
    """

    uv: np.ndarray
    score: np.ndarray
    depth: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    ok: np.ndarray


def patch_offsets(radius, step=1.0) -> np.ndarray:
    """Offsets (G, 2) of a square patch of (2 radius + 1)^2 samples, ``step`` pixels apart."""
    r = np.arange(-radius, radius + 1, dtype=float) * step
    dx, dy = np.meshgrid(r, r)
    return np.stack([dx.ravel(), dy.ravel()], axis=1)


NEAR_M = 0.02
"""The nearest depth (m) the matcher searches for a rig whose baselines are all at least ``NEAR_M / 2``."""


def near_search_depth(cameras, ref: int) -> float:
    """The nearest depth along the reference camera's rays that :func:`match_points` searches: :data:`NEAR_M`, or
    twice the shortest baseline from the reference camera where that is nearer. A point at twice the baseline is
    seen by the two cameras ~27 deg apart (a disparity of half the focal length): nearer, the views of its surface
    differ too much for patch matching, and far enough for a close endoscopic view (10-20 mm with a 5 mm
    baseline), which a fixed 2 cm floor lost (the points of a rig with a 2.5 mm baseline at 10-26 mm: 151 points
    per frame and matches up to 86 mm, against 222 with the floor at twice the baseline). A rig scaled by any
    factor below that finds the same points."""
    base = [float(np.linalg.norm(cam.centre - cameras[ref].centre)) for c, cam in enumerate(cameras) if c != ref]
    base = [b for b in base if b > 0]
    return min(NEAR_M, 2.0 * min(base)) if base else NEAR_M


def ray_depth_range(cameras, ref, origins, dirs, *, near=NEAR_M, far=5.0, margin_px=20, samples=1024):
    """Depth interval (N, 2) along each ray where its point lies in front of and inside every other camera.

    Sampled on ``samples`` log-spaced depths in [near, far]; NaN rows where no such depth exists.
    """
    t = np.geomspace(near, far, samples)
    X = origins[:, None, :] + t[None, :, None] * dirs[:, None, :]
    inside = np.ones(X.shape[:2], bool)
    for c, cam in enumerate(cameras):
        if c == ref:
            continue
        uv = cam.project(X.reshape(-1, 3)).reshape(X.shape[0], samples, 2)
        inside &= np.isfinite(uv).all(axis=-1) & cam.in_image(uv, margin_px)
    out = np.full((len(origins), 2), np.nan)
    any_in = inside.any(axis=1)
    first = np.argmax(inside, axis=1)
    last = samples - 1 - np.argmax(inside[:, ::-1], axis=1)
    out[any_in, 0] = t[first[any_in]]
    out[any_in, 1] = t[last[any_in]]
    return out


def _candidate_depths(cameras, ref, origins, dirs, t_range, step_px, max_candidates):
    """Depth candidates (N, J) at about ``step_px`` pixels of motion in the fastest-moving other camera."""
    n = len(origins)
    fine = 256
    s = np.linspace(0.0, 1.0, fine)
    # inverse depth is close to linear in the epipolar coordinate: sample it uniformly first
    inv = 1.0 / t_range[:, :1] + s[None, :] * (1.0 / t_range[:, 1:] - 1.0 / t_range[:, :1])
    t = 1.0 / inv
    X = origins[:, None, :] + t[..., None] * dirs[:, None, :]
    arc = np.zeros((n, fine))
    for c, cam in enumerate(cameras):
        if c == ref:
            continue
        uv = cam.project(X.reshape(-1, 3)).reshape(n, fine, 2)
        seg = np.linalg.norm(np.diff(uv, axis=1), axis=-1)
        arc = np.maximum(arc, np.concatenate([np.zeros((n, 1)), np.cumsum(np.nan_to_num(seg), axis=1)], axis=1))
    length = arc[:, -1]
    J = int(min(max_candidates, max(2, np.ceil(np.nanmax(length, initial=1.0) / step_px) + 1)))
    out = np.full((n, J), np.nan)
    for i in range(n):
        m = int(min(J, max(2, np.ceil(length[i] / step_px) + 1)))
        a = np.linspace(0.0, length[i], m)
        out[i, :m] = np.interp(a, arc[i], t[i])
    return out


def _plane_points(origin, ray_dirs, X0, normal):
    """Intersections (..., G, 3) of rays ``origin + s ray_dirs`` (N, G, 3) with the planes through X0 (N, J, 3)
    of normals (N, 3): (N, J, G, 3)."""
    num = ((X0 - origin[:, None, :]) * normal[:, None, :]).sum(axis=-1)     # n.(X0 - o)   (N, J)
    den = (ray_dirs * normal[:, None, :]).sum(axis=-1)                       # n.d_g        (N, G)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = num[:, :, None] / np.where(np.abs(den) > 1e-9, den, np.nan)[:, None, :]
    return origin[:, None, None, :] + s[..., None] * ray_dirs[:, None, :, :]


def _pyramid_coords(uv, level):
    """Full-resolution pixel coordinates -> coordinates in an image subsampled ``level`` times by 2 (pyrDown)."""
    f = 2.0 ** level
    return (uv + 0.5) / f - 0.5


def _scores(backend, cameras, ref, images, origins, centre_dirs, axis_dirs, h, offsets, ref_samples, X0, normals,
            level, chunk=64):
    """NCC (N, J, C) of the reference patches against the other cameras at candidate points X0 (N, J, 3).

    The plane-induced mapping of the reference patch into a camera is linearised at the patch centre (an
    affine map from the images of the centre ray and of two rays ``h`` pixels beside it): exact to far below
    a pixel over a patch, and it costs three projections per candidate instead of one per patch sample.
    """
    N, J = X0.shape[:2]
    C = len(cameras)
    out = np.full((N, J, C), np.nan, np.float32)
    rays = np.concatenate([centre_dirs[:, None, :], axis_dirs], axis=1)             # (N, 3, 3)
    offsets = np.asarray(offsets, np.float32)
    for a in range(0, N, chunk):
        sl = slice(a, a + chunk)
        P = _plane_points(origins[sl], rays[sl], X0[sl], normals[sl])                # (n, J, 3, 3)
        for c, cam in enumerate(cameras):
            if c == ref or images[c] is None:
                continue
            uv = cam.project(P.reshape(-1, 3)).reshape(P.shape[:3] + (2,))          # (n, J, 3, 2)
            f = 2.0 ** level
            A = ((uv[:, :, 1:, :] - uv[:, :, :1, :]) / (h * f)).astype(np.float32)   # level px per full px
            centre = ((uv[:, :, :1, :] + 0.5) / f - 0.5).astype(np.float32)          # (n, J, 1, 2), level px
            grid = np.matmul(offsets, A)              # (G, 2) @ (n, J, 2, 2) -> (n, J, G, 2): offsets mapped by A
            grid += centre
            out[sl, :, c] = backend.patch_ncc(images[c], ref_samples[sl][:, None, :], grid)
    return out


def _sweep(backend, cameras, ref, images, origins, dirs, uv_ref, depths, normals, radius, level):
    """Scores of the candidate depths (N, J): combined (mean over the other cameras) and per camera (N, J, C)."""
    cam = cameras[ref]
    step = 2.0 ** level
    offs = patch_offsets(radius, step)
    h = step
    side = np.stack([uv_ref + [h, 0.0], uv_ref + [0.0, h]], axis=1)
    _, sd = cam.rays(side.reshape(-1, 2))
    ref_samples = backend.sample(images[ref], _pyramid_coords(uv_ref[:, None, :] + offs[None], level))
    X0 = origins[:, None, :] + depths[..., None] * dirs[:, None, :]
    per_cam = _scores(backend, cameras, ref, images, origins, dirs, sd.reshape(-1, 2, 3), h, offs, ref_samples, X0,
                      normals, level)
    others = [c for c in range(len(cameras)) if c != ref and images[c] is not None]
    sc = per_cam[:, :, others]
    combined = np.where(np.isfinite(sc), sc, -1.0).mean(axis=2)
    combined = np.where(np.isfinite(depths), combined, -np.inf)
    return combined, per_cam


def bisector_normals(cameras, points) -> np.ndarray:
    """Unit normals (N, 3): the mean of the unit directions from each point to the camera centres."""
    d = np.zeros_like(points)
    for cam in cameras:
        v = cam.centre[None, :] - points
        d += v / np.linalg.norm(v, axis=1, keepdims=True)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _refine_parabola(combined, j):
    """Sub-sample offset in [-0.5, 0.5] of the optimum at index j (N,) by a parabola through its neighbours."""
    N, J = combined.shape
    jm = np.clip(j - 1, 0, J - 1)
    jp = np.clip(j + 1, 0, J - 1)
    r = np.arange(N)
    f0, fm, fp = combined[r, j], combined[r, jm], combined[r, jp]
    den = fm - 2 * f0 + fp
    ok = (jm != j) & (jp != j) & np.isfinite(fm) & np.isfinite(fp) & (den < 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        off = np.where(ok, 0.5 * (fm - fp) / np.where(ok, den, 1.0), 0.0)
    return np.clip(off, -0.5, 0.5)


def normal_hypotheses(axis, tilt_deg=(0.0, 30.0), per_ring=6) -> np.ndarray:
    """Unit normals (N, H, 3) around each ``axis`` (N, 3): the axis itself and rings of ``per_ring`` normals
    tilted by each nonzero angle in ``tilt_deg``."""
    axis = np.asarray(axis, float)
    helper = np.where(np.abs(axis[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(axis, e1)
    out = []
    for a in tilt_deg:
        a = np.radians(a)
        if a == 0:
            out.append(axis)
            continue
        for phi in 2 * np.pi * np.arange(per_ring) / per_ring:
            out.append(np.cos(a) * axis + np.sin(a) * (np.cos(phi) * e1 + np.sin(phi) * e2))
    return np.stack(out, axis=1)


def local_planes(uv_ref, seed_uv, seed_points, origins, dirs, k=10, max_px=200.0, *, leave_self_out=False):
    """Depth (N,) and normal (N, 3) predicted for each ray from the plane through its ``k`` nearest seeds
    (nearest in the reference image, within ``max_px``); NaN where fewer than 4 seeds are near, where they are
    collinear (second singular value of the centred seeds below 1e-6 m) or where the ray grazes the plane.

    The plane is the total-least-squares fit: through the seeds' centroid, normal the eigenvector of the smallest
    eigenvalue of their scatter matrix (the last right singular vector of the centred seeds), all rays at once.
    With ``leave_self_out`` the rays are the seeds themselves (``uv_ref`` is ``seed_uv``) and each one's own seed
    is left out of its plane (the leave-one-out check of :func:`match_points`)."""
    from scipy.spatial import cKDTree

    N = len(uv_ref)
    depth = np.full(N, np.nan)
    normal = np.full((N, 3), np.nan)
    n_seeds = len(seed_uv) - (1 if leave_self_out else 0)
    if n_seeds < 4 or N == 0:
        return depth, normal
    kk = min(k, n_seeds)
    tree = cKDTree(seed_uv)
    dist, nb = tree.query(uv_ref, k=kk + 1 if leave_self_out else kk)
    dist, nb = np.atleast_2d(dist).reshape(N, -1), np.atleast_2d(nb).reshape(N, -1)
    if leave_self_out:
        own = nb == np.arange(N)[:, None]
        # drop each point's own index (or, if a duplicate position displaced it, the farthest neighbour)
        drop = np.where(own.any(axis=1), np.argmax(own, axis=1), kk)
        keep = np.ones_like(own)
        keep[np.arange(N), drop] = False
        dist, nb = dist[keep].reshape(N, kk), nb[keep].reshape(N, kk)
    near = dist <= max_px                                                          # (N, kk)
    cnt = near.sum(axis=1)
    P = np.asarray(seed_points, float)[np.minimum(nb, len(seed_points) - 1)]      # (N, kk, 3)
    w = near[..., None].astype(float)
    c = (P * w).sum(axis=1) / np.maximum(cnt, 1)[:, None]
    D = (P - c[:, None, :]) * w
    S = np.einsum("nki,nkj->nij", D, D)
    ev, V = np.linalg.eigh(S)                                                      # ascending eigenvalues
    n = V[:, :, 0]
    sv1 = np.sqrt(np.maximum(ev[:, 1], 0.0))                                       # second singular value
    den = np.einsum("ni,ni->n", n, dirs)
    ok = (cnt >= 4) & (sv1 >= 1e-6) & (np.abs(den) >= 0.2)
    with np.errstate(invalid="ignore", divide="ignore"):
        depth[ok] = np.einsum("ni,ni->n", n, c - origins)[ok] / den[ok]
    sign = np.where(den < 0, 1.0, -1.0)                                            # facing the reference camera
    normal[ok] = (n * sign[:, None])[ok]
    return depth, normal


def match_points(cameras, images, ref, uv_ref, *, radius=7, coarse_level=2, coarse_radius=4, step_px=1.0,
                 fine_step_px=0.2, fine_span_px=None, min_ncc=0.85, min_views=2, max_candidates=4000,
                 depth_range=None, tilt_deg=(0.0, 30.0), surface_passes=2, surface_span_px=(16.0, 6.0, 3.0),
                 max_seeds=48, refine_tilt_deg=(12.0, 6.0, 3.0), refine_span_px=1.0, min_ncc_two_view=0.95,
                 max_plane_dev_m=0.003, refine_2d_px=1.0, pyramids=None, known=None,
                 backend=None) -> MatchResult:
    """Match corners of the reference camera in every other camera by a plane sweep (module docstring).

    Parameters
    ----------
    cameras : sequence of Camera (C)
    images : sequence of ndarray (H, W) (C)
        Gray images of one instant (float32 or uint8); None for a camera without an image.
    ref : int
        The reference camera (where ``uv_ref`` was detected).
    uv_ref : ndarray (N, 2)
    radius : int
        Patch radius at full resolution ((2 radius + 1)^2 samples).
    coarse_level, coarse_radius, step_px, tilt_deg :
        The seed sweep: images subsampled ``coarse_level`` times, patches of ``coarse_radius``, candidates every
        ``step_px`` pixels of that level, plane normals tilted by ``tilt_deg`` around the cameras' bisector.
    fine_step_px, fine_span_px :
        The fine sweep at full resolution: steps of ``fine_step_px`` pixels over +- ``fine_span_px`` around the
        coarse optimum (default: two coarse steps).
    min_ncc : float or ndarray (N,)
        A camera's match is kept if its NCC reaches this (one value, or one per point).
    max_seeds : int
        The full-range seed sweep runs on at most this many points spread over the image (and on any point
        with no matched neighbours); the others are found by the surface passes.
    surface_passes, surface_span_px :
        After the seed sweep, every point is matched again ``surface_passes + 1`` times with the depth and
        normal predicted by the plane through its nearest matched neighbours, over +- ``surface_span_px[p]``
        pixels in pass p (the last value for later passes).
    refine_tilt_deg, refine_span_px :
        Finally, for each angle in ``refine_tilt_deg``, six normals tilted by it around each point's normal are
        tried with a fine sweep over +- ``refine_span_px``; the best-scoring (depth, normal) is kept.
    min_ncc_two_view, max_plane_dev_m :
        Verification: with three or more cameras, a point seen in only two needs this NCC in both; and a point
        whose depth lies farther than ``max_plane_dev_m`` from the plane through its matched neighbours is
        dropped (None: no such check).
    refine_2d_px : float
        Last, each other view's match is refined freely in 2-D (not along the epipolar curve): the warped
        reference patch is compared at shifts of up to +- ``refine_2d_px`` pixels (quarter-pixel grid, then a
        parabola per axis), so the triangulation's reprojection errors measure the matching error (0: off).
    depth_range : (near, far), optional
        Limit the search along the rays (metres from the reference camera's centre).
    pyramids : sequence of list, optional
        Precomputed ``backend.pyramid(image, coarse_level)`` per camera (None for a missing image).
    known : (ndarray (M, 2), ndarray (M, 3)), optional
        Surface points already measured in this instant (e.g. the tracked points): their pixels in the reference
        camera and their 3-D positions (rig frame). They join the matched neighbours whose plane predicts each
        corner's depth and normal in the surface passes, and a corner they predict skips the full-range seed
        sweep (the seed sweep runs only on corners with no known surface near them).
    backend : OpenCVBackend or KorniaBackend, optional
        The image operations (heartcv.backend); default OpenCV.

    Returns
    -------
    MatchResult
    """
    cameras = list(cameras)
    C = len(cameras)
    uv_ref = np.atleast_2d(np.asarray(uv_ref, float))
    N = len(uv_ref)
    if len(images) != C:
        raise ValueError(f"images: {C} expected (one per camera), got {len(images)}")
    if images[ref] is None:
        raise ValueError("images: the reference camera's image is missing")
    backend = backend or OpenCVBackend()
    if pyramids is None:
        pyramids = [None if im is None else backend.pyramid(np.asarray(im, np.float32), coarse_level)
                    for im in images]
    full = [None if p is None else p[0] for p in pyramids]
    coarse = [None if p is None else p[coarse_level] for p in pyramids]
    empty = MatchResult(np.full((N, C, 2), np.nan), np.full((N, C), np.nan), np.full(N, np.nan),
                        np.full((N, 3), np.nan), np.full((N, 3), np.nan), np.zeros(N, bool))
    if N == 0:
        return empty
    origins, dirs = cameras[ref].rays(uv_ref)
    if depth_range is None:
        t_range = ray_depth_range(cameras, ref, origins, dirs, near=near_search_depth(cameras, ref))
    else:
        t_range = np.broadcast_to(np.asarray(depth_range, float), (N, 2)).copy()
    searchable = np.isfinite(t_range).all(axis=1)
    if not searchable.any():
        return empty
    idx = np.flatnonzero(searchable)
    thr = np.broadcast_to(np.asarray(min_ncc, float), (N,))[idx]          # per point NCC gate
    o, d, uv0 = origins[idx], dirs[idx], uv_ref[idx]
    n = len(idx)
    others = [c for c in range(C) if c != ref and images[c] is not None]

    def fine(sub, t_center, normals, span, use=None):
        """Full-resolution sweep over +- span px: steps of max(fine_step_px, span / 8), then, if coarser than
        fine_step_px, fine_step_px steps over +- one coarse step around the best; parabola on the last.
        ``use``: the cameras to score (default all)."""
        imgs = full if use is None else [im if (c == ref or c in use) else None for c, im in enumerate(full)]
        dt = _depth_per_pixel(cameras, ref, o[sub], d[sub], t_center)
        rows = np.arange(len(sub))
        step = max(fine_step_px, span / 8.0)
        t = t_center
        while True:
            m = int(np.ceil(span / step))
            steps = np.arange(-m, m + 1) * step
            cand = t[:, None] + steps[None, :] * dt[:, None]
            comb, per_cam = _sweep(backend, cameras, ref, imgs, o[sub], d[sub], uv0[sub], cand, normals, radius, 0)
            j = np.argmax(comb, axis=1)
            if step <= fine_step_px * 1.0001:
                off = _refine_parabola(comb, j)
                return t + (steps[j] + off * step) * dt, per_cam[rows, j]
            t = t + steps[j] * dt
            span, step = step, fine_step_px

    def seed_sweep(sub):
        """Coarse sweep over the whole visible depth range and a few normals, then a fine sweep."""
        depths = _candidate_depths(cameras, ref, o[sub], d[sub], t_range[idx[sub]],
                                   step_px * 2.0 ** coarse_level, max_candidates)
        mid = o[sub] + np.nanmean(depths, axis=1)[:, None] * d[sub]
        hyp = normal_hypotheses(bisector_normals(cameras, mid), tilt_deg)
        m = len(sub)
        rr = np.arange(m)
        best_score = np.full(m, -np.inf)
        t_best = np.full(m, np.nan)
        n_best = hyp[:, 0].copy()
        for h in range(hyp.shape[1]):
            comb, _ = _sweep(backend, cameras, ref, coarse, o[sub], d[sub], uv0[sub], depths, hyp[:, h], coarse_radius,
                             coarse_level)
            j = np.argmax(comb, axis=1)
            better = comb[rr, j] > best_score
            best_score[better] = comb[rr, j][better]
            t_best[better] = depths[rr, j][better]
            n_best[better] = hyp[better, h]
        span = fine_span_px if fine_span_px is not None else 2.0 * step_px * 2.0 ** coarse_level
        t, pc = fine(sub, t_best, n_best, span)
        return t, pc, n_best

    def mean_score(pc):
        return np.where(np.isfinite(pc[:, others]), pc[:, others], -1.0).mean(axis=1) if others else \
            np.full(len(pc), -1.0)

    # 1. seed sweep on a spread subset (all points when few) of the corners no known surface point predicts
    t_fine = np.full(n, np.nan)
    per_cam = np.full((n, C), np.nan, np.float32)
    normals = np.full((n, 3), np.nan)
    known_uv, known_X = (np.zeros((0, 2)), np.zeros((0, 3))) if known is None else \
        (np.asarray(known[0], float).reshape(-1, 2), np.asarray(known[1], float).reshape(-1, 3))
    keep_known = np.isfinite(known_uv).all(axis=1) & np.isfinite(known_X).all(axis=1)
    known_uv, known_X = known_uv[keep_known], known_X[keep_known]
    unknown = np.arange(n)
    if len(known_X):
        unknown = np.flatnonzero(~np.isfinite(local_planes(uv0, known_uv, known_X, o, d)[0]))
    seeds = unknown[_spread_subset(uv0[unknown], max_seeds)] if unknown.size else unknown
    if seeds.size:
        t_fine[seeds], per_cam[seeds], normals[seeds] = seed_sweep(seeds)
    swept = np.zeros(n, bool)
    swept[seeds] = True

    # 2. surface passes: depth and normal from the plane through the matched neighbours (and the known points)
    for p in range(surface_passes + 1):
        good = np.isfinite(t_fine) & (np.all(per_cam[:, others] >= thr[:, None], axis=1) if others else False)
        X = o + t_fine[:, None] * d
        t_pred, n_pred = local_planes(uv0, np.concatenate([uv0[good], known_uv]),
                                      np.concatenate([X[good], known_X]), o, d)
        usable = np.flatnonzero(np.isfinite(t_pred))
        if usable.size:
            span_p = surface_span_px[min(p, len(surface_span_px) - 1)]
            t2, pc2 = fine(usable, t_pred[usable], n_pred[usable], span_p)
            old = mean_score(per_cam[usable])
            take = ~np.isfinite(t_fine[usable]) | (mean_score(pc2) >= old - 0.02)
            u = usable[take]
            t_fine[u], per_cam[u], normals[u] = t2[take], pc2[take], n_pred[u]
        # points no plane could predict: a seed sweep of their own
        lone = np.flatnonzero(~np.isfinite(t_pred) & ~swept)
        if lone.size and p < surface_passes:
            t_fine[lone], per_cam[lone], normals[lone] = seed_sweep(lone)
            swept[lone] = True

    # 3. normal refinement: rings of tilted normals around each point's normal, keep the best fine sweep; each
    #    point is scored on the cameras that currently accept it (a camera that sees something else must not
    #    pull the normal), grouped by that set of cameras
    def accepted(pc):
        return np.nan_to_num(pc[:, others], nan=-1.0) >= thr[:, None] if others else np.zeros((len(pc), 0), bool)

    acc = accepted(per_cam)
    for tilt in refine_tilt_deg:
        live = np.isfinite(t_fine)
        for pattern in {tuple(r) for r in acc[live]}:
            use = [c for c, on in zip(others, pattern) if on] or others
            sub = np.flatnonzero(live & np.all(acc == pattern, axis=1))
            hyp = normal_hypotheses(normals[sub], (0.0, tilt))
            best = np.where(np.isfinite(per_cam[sub][:, use]), per_cam[sub][:, use], -1.0).mean(axis=1)
            # every tilted normal of every point in one sweep, each around the point's current depth
            m, H = len(sub), hyp.shape[1] - 1
            t2, pc2 = fine(np.repeat(sub, H), np.repeat(t_fine[sub], H), hyp[:, 1:].reshape(-1, 3),
                           refine_span_px, use=use)
            t2, pc2 = t2.reshape(m, H), pc2.reshape(m, H, C)
            sc = np.where(np.isfinite(pc2[..., use]), pc2[..., use], -1.0).mean(axis=2)      # (m, H)
            j = np.argmax(sc, axis=1)                                  # the first best, as a sequential scan
            rr = np.arange(m)
            better = sc[rr, j] > best
            u, jb = sub[better], j[better]
            t_fine[u], normals[u] = t2[better, jb], hyp[better, 1 + jb]
            per_cam[u[:, None], use] = pc2[better, jb][:, use]

    # 4. verification: per-view NCC, a stricter NCC when only two views agree, and the depth must lie near the
    #    plane through the point's matched neighbours (leave-one-out), which removes gross depth errors
    view_ok = np.zeros((n, C), bool)
    view_ok[:, ref] = True
    for c in others:
        view_ok[:, c] = np.nan_to_num(per_cam[:, c], nan=-1.0) >= thr
    n_ok = view_ok.sum(axis=1)
    two = n_ok == 2
    if len(others) >= 2:
        strict = np.all(np.where(view_ok[:, others], np.nan_to_num(per_cam[:, others], nan=-1.0), 1.0)
                        >= min_ncc_two_view, axis=1)
        view_ok[two & ~strict] = False
        view_ok[two & ~strict, ref] = True
    # points that lost a camera: depth again from the accepted cameras alone (the rejected one's scores would
    # otherwise still pull the combined optimum)
    partial = np.isfinite(t_fine) & (view_ok.sum(axis=1) >= 2) & (view_ok[:, others].sum(axis=1) < len(others))
    for pattern in {tuple(r) for r in view_ok[partial][:, others]}:
        use = [c for c, on in zip(others, pattern) if on]
        sub = np.flatnonzero(partial & np.all(view_ok[:, others] == pattern, axis=1))
        t2, pc2 = fine(sub, t_fine[sub], normals[sub], 1.0, use=use)
        keep = np.all(np.nan_to_num(pc2[:, use], nan=-1.0) >= thr[sub, None], axis=1)
        t_fine[sub[keep]] = t2[keep]
        per_cam[sub[keep][:, None], use] = pc2[keep][:, use]
    good = np.isfinite(t_fine) & (view_ok.sum(axis=1) >= min_views)
    X = o + t_fine[:, None] * d
    if max_plane_dev_m is not None and good.sum() >= 5:
        dev = np.full(n, np.nan)
        gi = np.flatnonzero(good)
        tp, _ = local_planes(uv0[gi], uv0[gi], X[gi], o[gi], d[gi], leave_self_out=True)
        dev[gi] = t_fine[gi] - tp
        far = good & np.isfinite(dev) & (np.abs(dev) > max_plane_dev_m)
        view_ok[far] = False

    uv = np.full((N, C, 2), np.nan)
    score = np.full((N, C), np.nan)
    for c, cam in enumerate(cameras):
        if c == ref:
            uv[idx, c] = uv0
            score[idx, c] = 1.0
            continue
        if images[c] is None:
            continue
        p = cam.project(X)
        keep = view_ok[:, c]
        if refine_2d_px > 0 and keep.any():
            p[keep] = _refine_2d(backend, cameras, ref, c, full, o[keep], uv0[keep], X[keep], normals[keep],
                                 radius, refine_2d_px)
        uv[idx[keep], c] = p[keep]
        score[idx, c] = np.where(np.isfinite(per_cam[:, c]), per_cam[:, c], np.nan)
    n_views = np.isfinite(uv).all(axis=2).sum(axis=1)
    ok = n_views >= min_views
    depth = np.full(N, np.nan)
    depth[idx] = t_fine
    pts = np.full((N, 3), np.nan)
    pts[idx] = X
    nrm = np.full((N, 3), np.nan)
    nrm[idx] = normals
    depth[~ok] = np.nan
    pts[~ok] = np.nan
    uv[~ok] = np.nan
    uv[~ok, ref] = uv_ref[~ok]
    return MatchResult(uv, score, depth, pts, nrm, ok)


def _refine_2d(backend, cameras, ref, c, images, origins, uv_ref, X, normals, radius, search_px, step=0.25):
    """Free 2-D sub-pixel position (n, 2) in camera ``c`` of the reference patches warped through their planes:
    NCC on a grid of shifts of +- ``search_px`` in ``step`` increments, then a parabola per axis."""
    h = 1.0
    side = np.stack([uv_ref + [h, 0.0], uv_ref + [0.0, h]], axis=1)
    _, sd = cameras[ref].rays(side.reshape(-1, 2))
    rays = np.concatenate([cameras[ref].rays(uv_ref)[1][:, None, :], sd.reshape(-1, 2, 3)], axis=1)
    P = _plane_points(origins, rays, X[:, None, :], normals)[:, 0]                  # (n, 3, 3)
    uv = cameras[c].project(P.reshape(-1, 3)).reshape(-1, 3, 2)
    A = (uv[:, 1:] - uv[:, :1]) / h                                                 # (n, 2, 2)
    offs = patch_offsets(radius).astype(np.float32)
    ref_samples = backend.sample(images[ref], uv_ref[:, None, :] + offs[None])
    m = int(round(search_px / step))
    sh = np.arange(-m, m + 1) * step
    dx, dy = np.meshgrid(sh, sh)
    shifts = np.stack([dx.ravel(), dy.ravel()], axis=1)                              # (S, 2), row-major in y
    base = uv[:, 0, None, None, :] + np.matmul(offs.astype(float), A)[:, None]      # (n, 1, G, 2)
    grid = (base + shifts[None, :, None, :]).astype(np.float32)                      # (n, S, G, 2)
    sc = backend.patch_ncc(images[c], ref_samples[:, None, :], grid)                 # (n, S)
    sc = np.where(np.isfinite(sc), sc, -np.inf)
    k = len(sh)
    best = np.argmax(sc, axis=1)
    iy, ix = np.divmod(best, k)
    S = sc.reshape(-1, k, k)
    rows = np.arange(len(best))

    def parabola(f0, fm, fp):
        with np.errstate(invalid="ignore", divide="ignore"):    # (-inf scores, shifts off the image: no vertex)
            den = fm - 2 * f0 + fp
            ok = np.isfinite(fm) & np.isfinite(fp) & np.isfinite(f0) & (den < 0)
            return np.where(ok, np.clip(0.5 * (fm - fp) / np.where(ok, den, 1.0), -0.5, 0.5), 0.0)

    f0 = S[rows, iy, ix]
    ox = parabola(f0, S[rows, iy, np.maximum(ix - 1, 0)], S[rows, iy, np.minimum(ix + 1, k - 1)])
    oy = parabola(f0, S[rows, np.maximum(iy - 1, 0), ix], S[rows, np.minimum(iy + 1, k - 1), ix])
    ox = np.where((ix == 0) | (ix == k - 1), 0.0, ox)
    oy = np.where((iy == 0) | (iy == k - 1), 0.0, oy)
    return uv[:, 0] + np.stack([sh[ix] + ox * step, sh[iy] + oy * step], axis=1)


def _spread_subset(uv, m) -> np.ndarray:
    """Indices of at most ``m`` points of ``uv`` (N, 2) spread by greedy farthest-point sampling."""
    n = len(uv)
    if n <= m:
        return np.arange(n)
    chosen = [int(np.argmin(np.linalg.norm(uv - uv.mean(axis=0), axis=1)))]
    dist = np.linalg.norm(uv - uv[chosen[0]], axis=1)
    for _ in range(m - 1):
        i = int(np.argmax(dist))
        chosen.append(i)
        dist = np.minimum(dist, np.linalg.norm(uv - uv[i], axis=1))
    return np.array(sorted(chosen))


def _depth_per_pixel(cameras, ref, o, d, t):
    """Metres along the ray per pixel of motion in the fastest-moving other camera, at depth t (N,)."""
    h = 1e-5
    rate = np.zeros(len(t))
    for c, cam in enumerate(cameras):
        if c == ref:
            continue
        a = cam.project(o + (t - h)[:, None] * d)
        b = cam.project(o + (t + h)[:, None] * d)
        rate = np.maximum(rate, np.nan_to_num(np.linalg.norm(b - a, axis=1) / (2 * h)))
    return 1.0 / np.maximum(rate, 1e-9)


def _gray8(image) -> np.ndarray:
    """An image as 8-bit gray (SIFT's input): colour (BGR) to gray, other integer depths scaled by their range,
    floating point stretched from its minimum to its maximum."""
    import cv2

    img = np.asarray(image)
    if img.ndim == 3:
        img = img[..., 0] if img.shape[2] == 1 else cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2GRAY)
    if img.dtype == np.uint8:
        return img
    if np.issubdtype(img.dtype, np.integer):
        return (img.astype(np.float64) * (255.0 / np.iinfo(img.dtype).max)).round().clip(0, 255).astype(np.uint8)
    img = img.astype(np.float32)
    lo, hi = float(np.nanmin(img)), float(np.nanmax(img))
    return np.zeros(img.shape, np.uint8) if hi <= lo else cv2.convertScaleAbs(img, alpha=255.0 / (hi - lo),
                                                                               beta=-255.0 * lo / (hi - lo))


def descriptor_matches(a, b, mask=None, *, ratio=0.75, features=2000):
    """SIFT features of view ``a`` matched in view ``b`` by Lowe's ratio test: ``(uv_a (N, 2), uv_b (N, 2))``, pixels
    (gray or colour views of any depth; ``mask``: where ``a``'s features may lie, non-zero). No geometry is used, so
    the matches say where the views agree whatever a rig says (some of them wrong: use robust statistics). At most
    ``features`` per view, the strongest (a finely textured HD view holds tens of thousands, and brute-force
    matching them takes tens of seconds)."""
    import cv2

    sift = cv2.SIFT_create(nfeatures=features)
    m8 = None if mask is None else (np.asarray(mask) > 0).astype(np.uint8) * 255
    ka, da = sift.detectAndCompute(_gray8(a), m8)
    kb, db = sift.detectAndCompute(_gray8(b), None)
    empty = (np.zeros((0, 2)), np.zeros((0, 2)))
    if da is None or db is None or len(ka) < 2 or len(kb) < 2:
        return empty
    good = [p[0] for p in cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
            if len(p) == 2 and p[0].distance < ratio * p[1].distance]
    if not good:
        return empty
    return (np.array([ka[m.queryIdx].pt for m in good], float).reshape(-1, 2),
            np.array([kb[m.trainIdx].pt for m in good], float).reshape(-1, 2))


def descriptor_inliers(cam_a, cam_b, matches, *, threshold_px=2.0):
    """The ``matches`` (a sequence of ``(uv_a (N, 2), uv_b (N, 2))``, pooled) that agree with one epipolar geometry
    of the two views, found without the rig: a fundamental matrix by RANSAC (OpenCV, ``threshold_px`` in the
    cameras' undistorted pixels, confidence 0.999) over all of them, the rig being the same for every instant.
    ``[(uv_a_in, uv_b_in)]`` (empty arrays with fewer than 8 matches or no model). Between views from far apart
    (a room seen by cameras a metre apart) most descriptor matches are wrong and their median distance from any
    epipolar line says nothing; the inliers are the matches a rig can be judged by. A near-planar scene makes the
    fundamental matrix degenerate, but its inliers are still the matches consistent with the views' geometry."""
    import cv2

    from .triangulation import _undistorted_pixels

    ua = np.concatenate([np.asarray(m[0], float).reshape(-1, 2) for m in matches]) if matches else np.zeros((0, 2))
    ub = np.concatenate([np.asarray(m[1], float).reshape(-1, 2) for m in matches]) if matches else np.zeros((0, 2))
    empty = [(np.zeros((0, 2)), np.zeros((0, 2)))]
    if len(ua) < 8:
        return empty
    pa, pb = _undistorted_pixels(cam_a, ua)[:, :2], _undistorted_pixels(cam_b, ub)[:, :2]
    ok = np.isfinite(pa).all(axis=1) & np.isfinite(pb).all(axis=1)
    if ok.sum() < 8:
        return empty
    try:
        _, mask = cv2.findFundamentalMat(pa[ok], pb[ok], cv2.FM_RANSAC, float(threshold_px), 0.999, 10000)
    except cv2.error:               # degenerate configurations (all matches on a line or a point)
        return empty
    if mask is None or len(mask) != ok.sum():
        return empty
    keep = np.flatnonzero(ok)[mask.ravel().astype(bool)]
    return [(ua[keep], ub[keep])]


def descriptor_epipolar_distance(cam_a, cam_b, matches, *, min_matches=20):
    """How far two calibrated cameras' views disagree with their epipolar geometry: ``(median_px, matches)``, the
    median symmetric epipolar distance (:func:`heartcv.triangulation.epipolar_distance`, lens distortion included)
    of ``matches`` between their views (a sequence of ``(uv_a (N, 2), uv_b (N, 2))``, e.g. :func:`descriptor_matches`
    of a few instants), pooled; NaN with fewer than ``min_matches``. A rig that describes the cameras gives a fraction
    of a pixel (the matches' own error; the wrong ones, fewer than half, do not move the median much); a calibration
    from before the focus or zoom changed, swapped cameras or another rig's file give pixels to hundreds."""
    from .triangulation import epipolar_distance

    d = [epipolar_distance(cam_a, cam_b, ua, ub) for ua, ub in matches if len(ua)]
    d = np.concatenate(d) if d else np.zeros(0)
    d = d[np.isfinite(d)]
    return (float(np.median(d)) if d.size >= min_matches else float("nan")), int(d.size)


def descriptor_front_fraction(cam_a, cam_b, matches, *, min_matches=20):
    """Whether the rig puts what two cameras see in front of them: ``(fraction, matches)``, the share of ``matches``
    (a sequence of ``(uv_a (N, 2), uv_b (N, 2))``, e.g. :func:`descriptor_matches`) whose rays through the two
    cameras come closest in front of both (positive distance along both rays: the midpoint method), among those whose
    rays are not parallel; NaN with fewer than ``min_matches`` such. A rig that describes the cameras puts nearly
    all of them in front (the wrong matches scatter either way); with its two cameras swapped (left for right), or
    its baseline pointing the wrong way, the rays diverge and nearly all of them lie behind."""
    s_all, t_all = [], []
    for ua, ub in matches:
        if not len(ua):
            continue
        oa, da = cam_a.rays(np.asarray(ua, float))
        ob, db = cam_b.rays(np.asarray(ub, float))
        w0 = oa - ob
        b = np.einsum("ij,ij->i", da, db)
        d, e = np.einsum("ij,ij->i", da, w0), np.einsum("ij,ij->i", db, w0)
        denom = 1.0 - b * b                                  # unit directions: a = c = 1
        ok = denom > 1e-12
        s_all.append(np.where(ok, (b * e - d) / np.where(ok, denom, 1.0), np.nan))
        t_all.append(np.where(ok, (e - b * d) / np.where(ok, denom, 1.0), np.nan))
    s_ = np.concatenate(s_all) if s_all else np.zeros(0)
    t_ = np.concatenate(t_all) if t_all else np.zeros(0)
    ok = np.isfinite(s_) & np.isfinite(t_)
    if ok.sum() < min_matches:
        return float("nan"), int(ok.sum())
    return float(np.mean((s_[ok] > 0) & (t_[ok] > 0))), int(ok.sum())


def descriptor_v_offset(matches, *, min_matches=20):
    """The vertical offset of a rectified pair's second views from its first ones, measured without any geometry:
    ``(offset_px, standard_error_px, matches)``, NaN offset and error where fewer than ``min_matches`` agree.

    In a rectified pair a surface point lies on the same row in both views; where the pair was rectified off by
    ``offset`` px, the second view's pixel lies that far below (``v_2 - v_1``). Geometry-guided matching cannot
    see an offset larger than the reach of its search around the epipolar line; SIFT descriptors matched between
    the views (:func:`descriptor_matches`) can. Over all ``matches`` (a sequence of ``(uv_1 (N, 2), uv_2 (N, 2))``,
    one per instant) their ``v_2 - v_1`` are pooled; their median, then again the median of those within three
    robust standard deviations (1.4826 MAD, at least 0.5 px) of it; the standard error ``1.4826 MAD / sqrt(matches)``
    of those. SIFT's sub-pixel positions are biased by a few hundredths of a pixel, more than that standard error
    when there are thousands of matches.
    """
    dv = [np.asarray(ub, float)[:, 1] - np.asarray(ua, float)[:, 1] for ua, ub in matches if len(ua)]
    dv = np.concatenate(dv) if dv else np.zeros(0)
    dv = np.asarray(dv, float)
    if dv.size < min_matches:
        return float("nan"), float("nan"), int(dv.size)
    med = float(np.median(dv))
    spread = max(1.4826 * float(np.median(np.abs(dv - med))), 0.5)
    inl = dv[np.abs(dv - med) <= 3.0 * spread]
    if inl.size < min_matches:
        return float("nan"), float("nan"), int(inl.size)
    med = float(np.median(inl))
    se = 1.4826 * float(np.median(np.abs(inl - med))) / np.sqrt(inl.size)
    return med, se, int(inl.size)

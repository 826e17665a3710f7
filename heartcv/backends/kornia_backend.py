"""The image operations of :mod:`heartcv.backend` on torch tensors with kornia (CPU or CUDA).

Each operation reproduces its OpenCV counterpart, border rules included, so that both backends give the same
corners and matches to within float32 rounding (tests/heartcv/test_backends.py):

* ``pyramid``: ``cv2.pyrDown`` is the separable 5-tap Gaussian [1, 4, 6, 4, 1] / 16 with BORDER_REFLECT_101,
  kept at the even pixels, so a level has ((W + 1) // 2, (H + 1) // 2) pixels. kornia's own ``pyrdown``
  resamples bilinearly to (W // 2, H // 2) instead; here the blur is ``kornia.filters.filter2d_separable``
  (its ``'reflect'`` border is REFLECT_101) followed by taking every other pixel.
* ``sample``: bilinear interpolation at OpenCV pixel coordinates (the centre of the top-left pixel is (0, 0)),
  NaN where the sample needs a pixel outside the image, which for ``cv2.remap`` with a NaN constant border
  (:func:`heartcv.features.sample_at`) means outside the half-open box [0, W - 1) x [0, H - 1): a sample exactly
  on the last column or row already reads a NaN neighbour with weight 0. Each sample gathers its four
  neighbours as one row of a per-level table (4 x the level's memory, cached while the level tensor lives) and
  weights them directly, rather than through ``torch.nn.functional.grid_sample``: its normalised coordinates
  (``2 u / (W - 1) - 1`` and back) lose about one float32 ulp of position (1e-4 px at u ~ 1900), which on a
  high-contrast texture is 1e-2 grey levels.
* ``patch_ncc``: those samples compared by zero-mean NCC (:func:`heartcv.features.ncc`: 0 where either patch's
  centred norm is below 1e-3 sqrt(G)), computed on the device; only the scores come back.
* ``corner_response``: ``cv2.cornerMinEigenVal(gray, block_size, ksize=3)`` scales the Sobel derivatives by
  ``1 / (4 block_size)`` (and by a further 1/255 for uint8 images) and box-sums their products over
  ``block_size`` x ``block_size`` pixels (anchor ``block_size // 2``, BORDER_REFLECT_101). With kornia's raw
  Sobel stencils (``get_spatial_gradient_kernel2d('sobel', 1)``, 8 per unit slope) and a box *mean*, the
  response is therefore the smaller eigenvalue of the box-mean structure tensor times 1/16 (float images) or
  1/(16 * 255^2) (uint8 images) -- equivalently 4 or 4/255^2 with kornia's normalised Sobel
  (``spatial_gradient(normalized=True)``). ``kornia.feature.gftt_response`` is not used: it weights the tensor
  with a 7x7 Gaussian, not a box, so it is not proportional to OpenCV's response.

Large point sets are processed in blocks of at most ``chunk`` samples, so memory stays bounded whatever the
caller passes (the matcher sends up to 64 x 500 x 81 samples per call).

On the CPU each call is a few dozen element-wise torch operations; with other processes on the cores torch's
intra-op threads wait on one another (on a loaded 2-core machine ``match_points`` ran 9x slower with 2 threads
than with ``torch.set_num_threads(1)``). The backend leaves the thread count to the caller.
"""

from __future__ import annotations

import numpy as np

__all__ = ["KorniaBackend"]

_PYR_TAPS = (1.0, 4.0, 6.0, 4.0, 1.0)


def _blocks(shape, limit):
    """Index tuples of slices that cut an array of ``shape`` along its leading axes into blocks of at most
    ``limit`` elements (at least one element of the last axis listed)."""
    if len(shape) == 0:
        yield ()
        return
    inner = int(np.prod(shape[1:], dtype=np.int64))
    if inner <= limit or len(shape) == 1:
        step = max(1, limit // max(inner, 1))
        for a in range(0, shape[0], step):
            yield (slice(a, a + step),)
        return
    for i in range(shape[0]):
        for rest in _blocks(shape[1:], limit):
            yield (slice(i, i + 1),) + rest


def _take(array, index):
    """``array[index]`` where axes of length 1 broadcast (are kept whole) instead of being sliced."""
    return array[tuple(slice(None) if n == 1 else s for n, s in zip(array.shape, index))]


class KorniaBackend:
    """torch + kornia image operations (float32) on ``device``.

    Parameters
    ----------
    device : str or torch.device, optional
        'cpu', 'cuda', 'cuda:1', ... (default: 'cuda' if available, else 'cpu'). InputError for a device that
        torch does not know or that is not available.
    chunk : int
        At most this many samples per block on the device (:meth:`patch_ncc`: ``chunk // G`` patches).
    """

    name = "kornia"

    def __init__(self, device=None, chunk=1 << 21):
        import torch

        from ..tracker.files import InputError

        if device is None:
            device = "cuda" if torch.cuda.is_available() else "cpu"
        try:
            self.device = torch.device(device)
        except (RuntimeError, TypeError) as exc:  # torch's parser of device strings: the user's option
            raise InputError(None, f"{device!r} is not a torch device ({exc})", "--device") from None
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise InputError(None, f"{device!r}: torch sees no CUDA device", "--device")
        if chunk < 1:
            raise ValueError(f"chunk: positive integer expected, got {chunk}")
        self.chunk = int(chunk)
        self._tables = {}

    def __repr__(self):
        return f"KorniaBackend(device={str(self.device)!r})"

    # -- conversions ---------------------------------------------------------------------------------------------
    def _image(self, image):
        """A 2-D float32 tensor on the device (from a numpy array or a tensor)."""
        import torch

        if isinstance(image, torch.Tensor):
            t = image.to(self.device, torch.float32)
        else:
            t = torch.from_numpy(np.ascontiguousarray(image, np.float32)).to(self.device)
        if t.ndim != 2:
            raise ValueError(f"image: (H, W) expected, got shape {tuple(t.shape)}")
        return t

    def _array(self, a):
        import torch

        return torch.from_numpy(np.ascontiguousarray(a, np.float32)).to(self.device)

    # -- the interface ---------------------------------------------------------------------------------------------
    def pyramid(self, image, levels):
        """The image and ``levels`` halvings as ``cv2.pyrDown`` makes them: a list of 2-D float32 tensors."""
        from kornia.filters import filter2d_separable
        import torch

        pyr = [self._image(image)]
        taps = torch.tensor([_PYR_TAPS], dtype=torch.float32, device=self.device) / 16.0
        for _ in range(levels):
            x = pyr[-1]
            if min(x.shape) < 3:
                raise ValueError(f"pyramid: level of shape {tuple(x.shape)} too small to halve again")
            blur = filter2d_separable(x[None, None], taps, taps, border_type="reflect")
            pyr.append(blur[0, 0, ::2, ::2].contiguous())
        return pyr

    def _table(self, level_image):
        """The bilinear neighbours of every pixel: (H + 2) (W + 2) x 4 float32 (pixel, right, below, below-right)
        of the image framed by one NaN pixel, so that a sample needing any pixel outside the image -- outside
        [0, W - 1) x [0, H - 1), weighted 0 or not -- is NaN, as cv2.remap's with a NaN border. One gather of a
        row per sample instead of four scattered reads. Cached per pyramid-level tensor (not for numpy input,
        which may change in place)."""
        import weakref

        import torch

        key = id(level_image)
        hit = self._tables.get(key)
        if hit is not None and hit[0]() is level_image and hit[1] == level_image._version:
            return hit[2]
        img = self._image(level_image)
        H, W = img.shape
        P = torch.nn.functional.pad(img[None], (1, 2, 1, 2), value=float("nan"))[0]        # (H + 3, W + 3)
        table = torch.stack([P[:-1, :-1], P[:-1, 1:], P[1:, :-1], P[1:, 1:]], dim=-1).reshape(-1, 4)
        if isinstance(level_image, torch.Tensor):
            self._tables[key] = (weakref.ref(level_image), level_image._version, (table, (H, W)))
            weakref.finalize(level_image, self._tables.pop, key, None)
        return table, (H, W)

    def _bilinear(self, table, pts):
        """Bilinear samples (M,) at ``pts`` (M, 2) (float32 tensor) from a :meth:`_table`."""
        import torch

        table, (H, W) = table
        Wp = W + 2
        p = torch.nan_to_num(pts, nan=-1.0)
        p = torch.clamp(p, min=-1.0).clamp_(max=self._hi(H, W))      # far outside -> onto the NaN frame
        p0 = p.floor()
        f = p - p0
        i = torch.addmv(self._one(Wp + 1.0), p0, self._one([1.0, float(Wp)])).to(torch.int64)
        v = table.index_select(0, i).view(-1, 2, 2)                  # [[v00, v01], [v10, v11]]
        rows = torch.lerp(v[:, :, 0], v[:, :, 1], f[:, :1])          # (M, 2): along x, on both rows
        return torch.lerp(rows[:, 0], rows[:, 1], f[:, 1])

    def _one(self, value):
        import torch

        return torch.tensor(value, dtype=torch.float32, device=self.device)

    def _hi(self, H, W):
        return self._one([W - 0.5, H - 0.5])

    def sample(self, level_image, pts):
        """Bilinear samples (float32 numpy (...)) at ``pts`` (..., 2); NaN outside (``features.sample_at``)."""
        table = self._table(level_image)
        pts = np.asarray(pts, np.float32)
        if pts.shape[-1:] != (2,):
            raise ValueError(f"pts: (..., 2) expected, got shape {pts.shape}")
        flat = pts.reshape(-1, 2)
        out = np.empty(len(flat), np.float32)
        for a in range(0, len(flat), self.chunk):
            out[a:a + self.chunk] = self._bilinear(table, self._array(flat[a:a + self.chunk])).cpu().numpy()
        return out.reshape(pts.shape[:-1])

    def patch_ncc(self, level_image, ref_samples, pts, min_std=1e-3):
        """Zero-mean NCC (float32 numpy (...)) of ``ref_samples`` (..., G) with the samples of ``level_image`` at
        ``pts`` (..., G, 2), broadcast against each other; NaN where a sample is outside, 0 where a patch is flat.

        Same rules as ``OpenCVBackend.patch_ncc``: against one reference patch per row (``ref_samples`` of shape
        (..., 1, G) and as many axes as the samples) a NaN sample gives NaN even when the reference is flat;
        otherwise :func:`heartcv.features.ncc`'s rule (flat wins)."""
        import torch

        table = self._table(level_image)
        a = np.asarray(ref_samples, np.float32)
        pts = np.asarray(pts, np.float32)
        if pts.ndim < 2 or pts.shape[-1] != 2:
            raise ValueError(f"pts: (..., G, 2) expected, got shape {pts.shape}")
        b_shape = pts.shape[:-1]
        nan_wins = a.ndim == len(b_shape) and len(b_shape) >= 2 and a.shape[-2] == 1
        shape = np.broadcast_shapes(a.shape, b_shape)
        G = shape[-1]
        a = a.reshape((1,) * (len(shape) - a.ndim) + a.shape)
        pts = pts.reshape((1,) * (len(shape) - len(b_shape)) + pts.shape)
        thr = min_std * float(np.sqrt(G))
        out = np.empty(shape[:-1], np.float32)
        for idx in _blocks(shape[:-1], max(1, self.chunk // max(G, 1))):
            ta = self._array(_take(a, idx))
            p = self._array(_take(pts, idx))
            tb = self._bilinear(table, p.reshape(-1, 2)).reshape(p.shape[:-1])
            a0 = ta - ta.mean(dim=-1, keepdim=True)
            sa = torch.linalg.vector_norm(a0, dim=-1)
            an = a0 / torch.where(sa > 0, sa, torch.ones_like(sa))[..., None]
            b0 = tb - tb.mean(dim=-1, keepdim=True)                      # centred: no cancellation in float32
            sb = torch.linalg.vector_norm(b0, dim=-1)
            num = torch.linalg.vecdot(an, b0)                             # sum(a0 b0) / |a0|
            flat = (sa < thr) | (sb < thr)
            r = torch.where(flat, torch.zeros_like(num), num / torch.where(sb > 0, sb, torch.ones_like(sb)))
            if nan_wins:
                r = torch.where(torch.isnan(sb), torch.full_like(r, float("nan")), r)
            out[idx] = r.cpu().numpy()
        return out

    def corner_response(self, gray, block_size=7):
        """``cv2.cornerMinEigenVal(gray, block_size, ksize=3)`` (float32 numpy (H, W)); module docstring."""
        from kornia.filters import filter2d, filter2d_separable, get_spatial_gradient_kernel2d
        import torch

        g = np.asarray(gray)
        if g.ndim != 2:
            raise ValueError(f"gray: (H, W) image expected, got shape {g.shape}")
        if block_size < 1:
            raise ValueError(f"block_size: positive integer expected, got {block_size}")
        scale = 1.0 / (16.0 * 255.0 ** 2) if g.dtype == np.uint8 else 1.0 / 16.0
        x = self._image(g)[None, None]
        k = get_spatial_gradient_kernel2d("sobel", 1, device=self.device, dtype=torch.float32)   # (2, 3, 3) raw
        dx = filter2d(x, k[0:1], border_type="reflect")
        dy = filter2d(x, k[1:2], border_type="reflect")
        prod = torch.cat([dx * dx, dx * dy, dy * dy], dim=1)                                   # (1, 3, H, W)
        lo = block_size // 2                                                                    # cv2's anchor
        prod = torch.nn.functional.pad(prod, (lo, block_size - 1 - lo, lo, block_size - 1 - lo), mode="reflect")
        box = torch.full((1, block_size), 1.0 / block_size, dtype=torch.float32, device=self.device)
        m = filter2d_separable(prod, box, box, padding="valid")
        xx, xy, yy = m[0, 0], m[0, 1], m[0, 2]
        lam = 0.5 * (xx + yy) - torch.sqrt(0.25 * (xx - yy) ** 2 + xy * xy)
        return (lam * scale).cpu().numpy().astype(np.float32)

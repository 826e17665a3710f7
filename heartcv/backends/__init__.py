"""Optional image-ops backends beside the default :class:`heartcv.backend.OpenCVBackend`.

``kornia_backend.KorniaBackend`` runs the same operations on torch tensors (CPU or CUDA) with kornia; it needs
the ``kornia`` extra (``pip install 'heartcv[kornia]'``). Get backends by name with
:func:`heartcv.backend.get_backend`; importing this package does not import torch.
"""

__all__ = ["KorniaBackend"]


def __getattr__(name):
    if name == "KorniaBackend":
        from .kornia_backend import KorniaBackend

        return KorniaBackend
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

"""Ordered parallel map over worker processes that share one read-only state.

The state (camera rays, texture, mesh, motion: tens of MB) reaches the workers by ``fork`` (copy-on-write, no
pickling); each job gets only its index. Results come back in order. With ``workers <= 1`` (or where ``fork``
is unavailable) the jobs run in the calling process. Every job's randomness must be derived from its index, so
the output does not depend on the number of workers. OpenCV runs single-threaded while a pool is open: its
own thread pool does not survive ``fork``.
"""

from __future__ import annotations

import multiprocessing as mp
import os

__all__ = ["imap_ordered", "default_workers"]

_STATE = None
_FN = None


def default_workers() -> int:
    """All cores of this machine (the renderer's default: both cores of the project's 2-core machine)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def _init(fn, state):
    global _STATE, _FN
    _STATE, _FN = state, fn
    _ignore_interrupts()


def _ignore_interrupts():
    """Workers leave Ctrl-C and SIGTERM to the parent, which stops the pool and cleans its outputs up (a worker
    that took them printed a traceback of its own)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _call(i):
    return _FN(_STATE, i)


def imap_ordered(fn, state, items, workers=1):
    """Yield ``fn(state, item)`` for each item, in order, computed by ``workers`` processes."""
    items = list(items)
    if workers <= 1 or len(items) <= 1 or "fork" not in mp.get_all_start_methods():
        for i in items:
            yield fn(state, i)
        return
    import cv2

    ctx = mp.get_context("fork")
    # OpenCV's thread pool does not survive fork (a forked child that touches it hangs): run OpenCV single-threaded
    # while the workers live (each worker is one of the cores anyway)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with ctx.Pool(min(workers, len(items)), initializer=_init, initargs=(fn, state)) as pool:
            yield from pool.imap(_call, items, chunksize=1)
    finally:
        cv2.setNumThreads(threads)

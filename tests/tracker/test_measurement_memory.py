"""Sets derived from a validated measurement set (subsets, first frames, the patch frame, undeformed references) take
no more memory than their own arrays, share none that can be written, and skip no validation of a set a user gives."""

import dataclasses
import tracemalloc

import numpy as np
import pytest

from heartcv.tracker.files import InputError
from heartcv.tracker.fit import UndeformedReferences, _subset_points, undeformed_references
from heartcv.tracker.io import read_measurements, write_measurements
from heartcv.tracker.measurements import MeasurementSet
from heartcv.tracker.registration import Registration, _rotated_covariances, to_patch_frame
from heartcv.tracker.simulate import simulate, to_measurements
from heartcv.tracker.tracking import first_frames

K, P = 120, 400


def _random_set(seed=0, frame="patch") -> MeasurementSet:
    """K x P points with anisotropic covariances, some unseen."""
    rng = np.random.default_rng(seed)
    pos = 1e-2 * rng.standard_normal((K, P, 3))
    pos[rng.random((K, P)) < 0.2] = np.nan
    A = 1e-4 * rng.standard_normal((K, P, 3, 3))
    cov = A @ np.swapaxes(A, -1, -2) + 1e-9 * np.eye(3)
    cov[~np.isfinite(pos).all(axis=2)] = np.nan
    return MeasurementSet(np.arange(K) / 25, np.arange(P) + 7, pos, cov, 1e-2 * rng.standard_normal((P, 3)),
                          np.zeros((K, 1)), ("pressure",), ("Pa",), frame)


def _writable_views(a) -> bool:
    """Whether ``a`` or any array it views can be written."""
    while isinstance(a, np.ndarray):
        if a.flags.writeable:
            return True
        a = a.base
    return False


def _arrays(m: MeasurementSet) -> dict:
    return {f.name: getattr(m, f.name) for f in dataclasses.fields(m) if isinstance(getattr(m, f.name), np.ndarray)}


def test_a_subset_of_points_allocates_its_arrays_once():
    """``_subset_points`` (fancy indexing, one copy) used to copy its arrays a second time and validate them again:
    its peak allocation is now about the size of what it returns."""
    meas = _random_set()
    idx = np.arange(0, P, 2)[::-1].copy()
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        base = tracemalloc.get_traced_memory()[0]
        sub = _subset_points(meas, idx)
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    size = sum(a.nbytes for a in _arrays(sub).values() if not np.shares_memory(a, meas.times))
    assert size > 0.9 * (3 + 9 + 1 + 1) * 8 * K * idx.size
    assert peak < 1.2 * size + 200_000, (peak, size)
    for name, a in _arrays(sub).items():
        assert not _writable_views(a), name
    np.testing.assert_array_equal(sub.covariances, meas.covariances[:, idx])
    np.testing.assert_array_equal(sub.point_ids, meas.point_ids[idx])


def test_the_first_frames_are_views_of_the_set():
    meas = _random_set()
    head = first_frames(meas, 30)
    assert head.n_frames == 30
    for name in ("positions", "covariances", "views", "reprojection_rms", "times", "inputs"):
        assert np.shares_memory(getattr(head, name), getattr(meas, name)), name
        assert not _writable_views(getattr(head, name)), name


def test_the_patch_frame_rotates_the_covariances_as_the_expression_does():
    """The same numbers and memory layout as ``R @ cov[:, keep] @ R.T``, a few points at a time."""
    meas = _random_set(1, frame="rig")
    c, s = np.cos(0.3), np.sin(0.3)
    T = np.eye(4)
    T[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ np.array([[1, 0, 0], [0, c, s], [0, -s, c]])
    T[:3, 3] = [1e-3, -2e-3, 5e-3]
    on = np.ones(P, bool)
    on[::7] = False
    keep = np.flatnonzero(on)
    R = T[:3, :3]
    expected = R @ meas.covariances[:, keep] @ R.T
    got = _rotated_covariances(meas.covariances, keep, R)
    assert got.strides == expected.strides
    np.testing.assert_array_equal(got, expected)
    reg = Registration(patch_from_rig=T, rms_m=0.0, on_patch=on, n_points=int(on.sum()), converged=True, message="")
    patch = to_patch_frame(meas, reg)
    np.testing.assert_array_equal(patch.covariances, expected)
    for name, a in _arrays(patch).items():
        assert not _writable_views(a), name


def test_undeformed_references_asked_twice_share_the_arrays(paper_model):
    """:class:`UndeformedReferences` gives the set of :func:`undeformed_references`; a second ``apply`` with the same
    points shares the first's frames x points arrays (no second copy)."""
    meas = to_measurements(simulate(paper_model, 1.0, np.random.default_rng(3)))
    once = undeformed_references(paper_model, meas, paper_model.config.theta, 10)
    refs = UndeformedReferences(paper_model, meas, paper_model.config.theta, 10)
    a, b = refs.apply(), refs.apply(causal_ids=[])
    for name in ("point_ids", "positions", "covariances", "reference", "views", "reprojection_rms"):
        np.testing.assert_array_equal(getattr(a, name), getattr(once, name))
    assert a.meta == once.meta
    assert np.shares_memory(a.covariances, b.covariances) and np.shares_memory(a.positions, b.positions)
    assert not np.shares_memory(a.covariances, meas.covariances)
    assert not _writable_views(a.covariances) and not _writable_views(a.reference)


def test_a_set_given_by_a_user_is_still_validated(tmp_path):
    """Through the constructor, ``dataclasses.replace`` and a file: a covariance that is not positive definite is
    refused; a set read from a file takes the file's arrays without a copy, read-only."""
    meas = _random_set(2)
    bad = np.array(meas.covariances)
    k, p = np.argwhere(np.isfinite(meas.positions).all(axis=2))[5]
    bad[k, p] = -np.eye(3)
    with pytest.raises(InputError, match="positive definite"):
        dataclasses.replace(meas, covariances=bad)
    with pytest.raises(InputError, match="positive definite"):
        MeasurementSet(meas.times, meas.point_ids, meas.positions, bad, meas.reference, meas.inputs,
                       meas.input_names, meas.input_units)
    path = tmp_path / "meas.npz"
    write_measurements(path, meas)
    back = read_measurements(path)
    np.testing.assert_array_equal(back.covariances, meas.covariances)
    for name, a in _arrays(back).items():
        assert not _writable_views(a), name
    object.__setattr__(meas, "covariances", bad)    # a file holding the bad covariance
    write_measurements(path, meas)
    with pytest.raises(InputError, match="positive definite"):
        read_measurements(path)

"""Fuzzing every file reader through the CLI (tests/fuzz_harness.py): seeded mutations of a small valid file, run
with the command that reads it; no case may end in a Python exception, a traceback, an 'internal error', an exit
code other than 0, 1 or 2, an exit 1 or 2 that does not name the file, or a run past the per-case limit.

The fast test runs ~30 cases per reader (at most 6 s each); ``make fuzz`` runs the slow one, 1000 per reader,
and writes the counts to ``$HEARTCV_FUZZ_REPORT``. A failure is reproduced from its seed and index:
``.venv/bin/python -m tests.fuzz_harness READER --seed S --index I --keep /tmp/case``."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from tests import fuzz_harness as fh

SEED = int(os.environ.get("HEARTCV_FUZZ_SEED", "20240611"))
FAST_CASES, FAST_BUDGET_S = 30, 6.0
SLOW_CASES = int(os.environ.get("HEARTCV_FUZZ_CASES", "1000"))


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    return fh.Seeds(tmp_path_factory.mktemp("fuzz_seeds"))


def _message(results) -> str:
    return "\n".join(r.report() for r in results if r.failures)


@pytest.mark.parametrize("reader", fh.READERS)
def test_fuzz_reader(reader, seeds, tmp_path):
    res = fh.run_reader(reader, FAST_CASES, SEED, seeds=seeds, workdir=tmp_path, budget_s=FAST_BUDGET_S)
    assert res.run >= min(5, FAST_CASES), res.report()
    if res.failures:
        pytest.fail(_message([res]), pytrace=False)


@pytest.mark.slow
def test_fuzz_readers_full(tmp_path_factory):
    """1000 cases per reader (HEARTCV_FUZZ_CASES); the counts per reader as JSON to $HEARTCV_FUZZ_REPORT."""
    seeds = fh.Seeds(tmp_path_factory.mktemp("fuzz_seeds_full"))
    work = tmp_path_factory.mktemp("fuzz_full")
    results, report = [], {}
    path = os.environ.get("HEARTCV_FUZZ_REPORT")
    for reader in fh.READERS:
        res = fh.run_reader(reader, SLOW_CASES, SEED, seeds=seeds, workdir=work / reader.replace(".", "_"))
        results.append(res)
        report[reader] = res.as_dict()
        if path:    # written after every reader, so a long run that is stopped still leaves its counts
            Path(path).write_text(json.dumps({"seed": SEED, "cases_per_reader": SLOW_CASES, "readers": report},
                                             indent=2))
    assert all(r.run == SLOW_CASES for r in results)
    if any(r.failures for r in results):
        pytest.fail(_message(results), pytrace=False)

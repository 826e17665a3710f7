"""CLI: the bootstrap intervals of ``heartcv report`` (``--resamples``, ``--seed``): in metrics.json and the summary,
equal to the library's on the same files and seed, reproducible, off with 0, bad values exit 2."""

import json

from click.testing import CliRunner
import numpy as np
import pytest

from heartcv.cli.main import main
from tests.conftest import SAMPLES

PAPER = str(SAMPLES / "paper_patch.yaml")


def _run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("intervals")
    assert _run("-q", "model", "simulate", PAPER, "--duration", "1.5", "--seed", "3", "-o", d / "m.npz").exit_code == 0
    for e in ("ge", "kf", "hold"):
        res = _run("-q", "track", d / "m.npz", "--model", PAPER, "--estimator", e, "--holdout", "0.2", "--seed", "4",
                   "-o", d / f"{e}.npz")
        assert res.exit_code == 0, res.output
    return d


def _report(files, out, *extra):
    return _run("report", files / "ge.npz", files / "kf.npz", files / "hold.npz", "-o", out, "--json", *extra)


def test_intervals_in_metrics_and_summary_equal_the_library(files, tmp_path):
    from heartcv.tracker.io import read_estimates
    from heartcv.tracker.metrics import compare_runs

    res = _report(files, tmp_path / "rep", "--seed", "5", "--resamples", "400")
    assert res.exit_code == 0, res.output
    doc = json.loads((tmp_path / "rep" / "metrics.json").read_text())
    runs = {k: read_estimates(files / f"{k}.npz") for k in ("ge", "kf", "hold")}
    lib = compare_runs(runs, rng=np.random.default_rng(5), resamples=400)
    for label in ("ge", "kf"):
        for key in ("ratio_to_hold_interval", "heldout_ratio_to_hold_interval"):
            assert doc["estimators"][label][key] == pytest.approx(lib["per_run"][label][key], rel=1e-12)
            assert doc["estimators"][label][key]["resamples"] == 400
    assert doc["estimators"]["hold"]["ratio_to_hold_interval"] is None
    ci = doc["ratio_ge_to_kf_prediction_error_interval"]
    assert ci == pytest.approx(lib["ratio_ge_to_kf_prediction_error_interval"], rel=1e-12)
    summary = (tmp_path / "rep" / "summary.md").read_text()
    assert f"GE / KF mean prediction error: {doc['ratio_ge_to_kf_prediction_error']:.3f}; over the observations both " \
           f"predicted {ci['ratio']:.3f} (95 % interval {ci['low']:.3f}–{ci['high']:.3f}" in summary
    ge = doc["estimators"]["ge"]["ratio_to_hold_interval"]
    assert f"ge {ge['ratio']:.3f} (95 % interval {ge['low']:.3f}–{ge['high']:.3f}" in summary


def test_reproducible_with_a_seed_and_off_with_zero(files, tmp_path):
    docs = {}
    for name, extra in (("a", ()), ("b", ()), ("c", ("--seed", "1")), ("off", ("--resamples", "0"))):
        assert _report(files, tmp_path / name, *extra).exit_code == 0
        docs[name] = json.loads((tmp_path / name / "metrics.json").read_text())
    key = "ratio_ge_to_kf_prediction_error_interval"
    assert docs["a"][key] == docs["b"][key] and docs["a"][key]["resamples"] == 2000
    assert docs["c"][key]["ratio"] == docs["a"][key]["ratio"] and docs["c"][key]["low"] != docs["a"][key]["low"]
    assert docs["off"][key] is None and docs["off"]["estimators"]["ge"]["ratio_to_hold_interval"] is None
    assert "% interval" not in (tmp_path / "off" / "summary.md").read_text()


@pytest.mark.parametrize("value", ["50", "-1"])
def test_bad_resamples_exit_2(files, tmp_path, value):
    res = _report(files, tmp_path / "rep", "--resamples", value)
    assert res.exit_code == 2 and "--resamples" in res.output and "Traceback" not in res.output
    assert not (tmp_path / "rep").exists()


def test_the_software_of_every_input_is_recorded_and_reported(files, tmp_path):
    """Every .npz records the versions it was written with (``meta.software``); the report lists them."""
    import platform

    import scipy

    from heartcv.tracker.io import read_estimates

    expected = {"python": platform.python_version(), "numpy": np.__version__, "scipy": scipy.__version__}
    for name in ("ge", "kf", "hold"):
        sw = read_estimates(files / f"{name}.npz").meta["software"]
        assert {k: sw[k] for k in expected} == expected
    assert _report(files, tmp_path / "rep", "--resamples", "0").exit_code == 0
    doc = json.loads((tmp_path / "rep" / "metrics.json").read_text())
    assert {k: doc["software"][k] for k in expected} == expected
    assert set(doc["inputs_software"]) == {"ge", "kf", "hold"}
    summary = (tmp_path / "rep" / "summary.md").read_text()
    assert "Software the inputs were written with: ge, kf, hold: " in summary
    assert f"numpy {np.__version__}" in summary and f"scipy {scipy.__version__}" in summary


def test_runs_with_other_held_out_tracks_or_missing_predictions_are_flagged(files, tmp_path):
    """hold made with another --seed holds out other tracks: a warning, and no ratio to it (the audit's 1.506 over
    a tenth of the held-out observations). A kf file with its worst fifth of predictions removed (NaN): a warning
    counting them (its mean and ratio to hold otherwise look better, silently)."""
    import dataclasses

    from heartcv.tracker.io import read_estimates, write_estimates

    res = _run("-q", "track", files / "m.npz", "--model", PAPER, "--estimator", "hold", "--holdout", "0.2", "--seed",
               "9", "-o", tmp_path / "hold9.npz")
    assert res.exit_code == 0, res.output
    out = _run("report", files / "ge.npz", tmp_path / "hold9.npz", "-o", tmp_path / "rep", "--json")
    assert out.exit_code == 0, out.output
    assert "hold out different tracks" in out.stderr
    doc = json.loads((tmp_path / "rep" / "metrics.json").read_text())
    assert doc["estimators"]["ge"]["ratio_to_hold_interval"] is None
    kf = read_estimates(files / "kf.npz")
    inn = np.array(kf.innovations, float)
    norms = np.linalg.norm(inn, axis=-1)
    worst = norms > np.nanquantile(norms[1:], 0.8)
    worst[0] = False
    inn[worst] = np.nan
    pred = np.array(kf.predictions, float)
    pred[worst] = np.nan
    write_estimates(tmp_path / "kf_worst.npz", dataclasses.replace(kf, innovations=inn, predictions=pred),
                    dict(kf.meta))
    out = _run("report", tmp_path / "kf_worst.npz", files / "hold.npz", "-o", tmp_path / "rep2", "--json")
    assert out.exit_code == 0, out.output
    doc = json.loads((tmp_path / "rep2" / "metrics.json").read_text())
    missing = doc["estimators"]["kf"]["ratio_to_hold_interval"]["numerator_missing"]
    assert missing > 0 and f"no prediction for {missing} observations that hold predicted" in out.stderr

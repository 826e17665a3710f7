import copy
from pathlib import Path

import numpy as np
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "sample_sequences"
SHARED_DATA = ROOT.parent / "shared" / "data"


def assert_exit_2(res, out, *words):
    """A CliRunner result of a refused command: exit 2, no traceback, every word in the message, ``out`` not
    written."""
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output
    for w in words:
        assert w in res.output, (w, res.output)
    assert not out.exists()


def load_yaml(name):
    return yaml.safe_load((SAMPLES / name).read_text())


@pytest.fixture(scope="session")
def paper_dict():
    return load_yaml("paper_patch.yaml")


@pytest.fixture(scope="session")
def paper_model(paper_dict):
    from heartcv.tracker.config import model_config_from_dict
    from heartcv.tracker.model import build_model

    return build_model(model_config_from_dict(copy.deepcopy(paper_dict)))


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture(scope="session", autouse=True)
def single_threaded_blas():
    """Small matrices: one BLAS thread is faster and keeps timings stable on 2 cores."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        yield

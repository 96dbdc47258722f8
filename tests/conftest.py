"""Fixtures every test package shares: a tiny untrained model pair and a real photograph."""

from __future__ import annotations

import numpy as np
import pytest

from fixtures.memory_alarm import from_environment
from fixtures.tiny_models import save_tiny_models

_ALARM = from_environment()
if _ALARM is not None:  # at import: a conftest below the rootdir may be loaded after pytest_sessionstart
    _ALARM.start()


def pytest_configure(config):
    if _ALARM is not None:
        _ALARM.write = lambda text: _to_terminal(config, text)


def _to_terminal(config, text: str) -> None:
    """Past pytest's output capture (which would drop it with a passing test) to its terminal writer."""
    capman = config.pluginmanager.getplugin("capturemanager")
    with capman.global_and_fixture_disabled():
        config.get_terminal_writer().write(text, flush=True)


def pytest_runtest_logstart(nodeid, location):
    if _ALARM is not None:
        _ALARM.current = nodeid


def pytest_sessionfinish(session, exitstatus):
    if _ALARM is not None:
        _ALARM.stop()


@pytest.fixture(scope="session")
def tiny_models(tmp_path_factory):
    """A tiny untrained pair of models in the models/ layout (built once per session)."""
    return save_tiny_models(tmp_path_factory.mktemp("models"))


@pytest.fixture(scope="session")
def astronaut():
    """A real photograph that ships with scikit-image (512 x 512 sRGB, uint8)."""
    data = pytest.importorskip("skimage.data", reason="scikit-image (the test extra) is not installed")
    return np.ascontiguousarray(data.astronaut())


@pytest.fixture
def astronaut_png(tmp_path, astronaut):
    from PIL import Image

    path = tmp_path / "astronaut.png"
    Image.fromarray(astronaut).save(path)
    return path

"""Fixtures every test package shares: a tiny untrained model pair and a real photograph."""

from __future__ import annotations

import numpy as np
import pytest

from fixtures.tiny_models import save_tiny_models


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

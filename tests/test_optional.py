"""transformers is the `pretrained` extra, not a core dependency (pilight/optional.py): the photo
command relights with the shipped base where it is missing, and a params key that needs it, set where
it is missing, is refused naming the key and the extra."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from PIL import Image
from pydantic import ValidationError

import pilight.params as params_module
from pilight import optional
from pilight.failure import CommandFailure
from pilight.params import ConditioningParams, RelightParams

ROOT = Path(__file__).resolve().parents[1]

# sys.modules["transformers"] = None is an environment without the package to importlib: find_spec
# (what diffusers asks) says absent and `import transformers` fails.
WITHOUT_TRANSFORMERS = """
import sys
sys.modules["transformers"] = None
from pilight.cli import main
rc = main(sys.argv[1:])
loaded = sorted(k for k, v in sys.modules.items() if v is not None and k.split(".")[0] == "transformers")
assert not loaded, loaded
sys.exit(rc)
"""


def test_the_photo_command_relights_without_transformers(tmp_path, astronaut):
    Image.fromarray(astronaut[::8, ::8]).save(tmp_path / "photo.png")
    run = subprocess.run(
        [sys.executable, "-c", WITHOUT_TRANSFORMERS, "relight", "photo.png", "-o", "out", "--light", "left"],
        cwd=tmp_path,  # no models/ here: the shipped base
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    assert "pilight-base" in run.stderr
    assert (tmp_path / "out" / "photo").is_dir()


@pytest.mark.parametrize(
    ("section", "values", "key"),
    [
        (ConditioningParams, {"kind": "clip", "clip_path": "clip"}, "conditioning.kind: clip"),
        (RelightParams, {"rec_features": "dinov2", "dinov2_path": "dinov2"}, "rec_features: dinov2"),
    ],
)
def test_a_key_that_needs_transformers_is_refused_where_it_is_missing(monkeypatch, section, values, key):
    section.model_validate(values, context={"check_paths": False})  # accepted where it is installed
    monkeypatch.setattr(params_module, "installed", lambda package: False)
    with pytest.raises(ValidationError, match=rf"{key} needs the transformers package.*'\.\[pretrained\]'"):
        section.model_validate(values, context={"check_paths": False})


def test_require_names_the_key_and_the_extra(monkeypatch):
    def absent(name):
        raise ModuleNotFoundError(f"No module named {name!r}")

    monkeypatch.setattr(optional, "import_module", absent)
    with pytest.raises(CommandFailure, match=r"rec_features: dinov2 needs the transformers package") as failure:
        optional.require("transformers", "rec_features: dinov2")
    assert failure.value.code == 2 and ".[pretrained]" in str(failure.value)

"""`pilight app` as a command: bad options and a missing extra end with a message and exit 2 before any
model is loaded; the model options given are repeated in the app's reproducing command."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from pilight.cli import build_parser, main, model_arguments


@pytest.mark.parametrize("port", ["0", "70000"])
def test_a_bad_port_is_refused(capsys, port):
    assert main(["app", "--port", port]) == 2
    assert f"--port must lie in [1, 65535], got {port}" in capsys.readouterr().err


def test_without_the_app_extra_it_says_which_to_install(capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "gradio", None)  # as if `pip install -e .` without [app]
    monkeypatch.delitem(sys.modules, "pilight.app.ui", raising=False)
    assert main(["app", "--port", "7999"]) == 2
    assert "pip install -e '.[app]'" in capsys.readouterr().err


def test_the_model_options_given_go_into_the_reproducing_command():
    args = build_parser().parse_args(["app", "--models", "mine", "--resolution", "256", "--steps", "4"])
    assert model_arguments(args) == ["--models", "mine", "--resolution", "256", "--steps", "4"]
    assert model_arguments(build_parser().parse_args(["app"])) == []
    assert (
        build_parser().parse_args(["app"]).models == Path("models") and build_parser().parse_args(["app"]).port == 7860
    )

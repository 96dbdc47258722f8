"""pilight/stage_cli.py: the exit codes every stage script shares (0 done, 1 bad data or input, 2 bad params)."""

from __future__ import annotations

from pathlib import Path

import pytest

from fixtures.stage_scripts import REPO
from pilight.data.schema import DataError
from pilight.failure import CommandFailure
from pilight.params import load_section
from pilight.stage_cli import fails_on, run_stage

PARAMS = REPO / "params.yaml"


def _options(ap) -> None:
    ap.add_argument("--out", type=Path, default=Path("x"))


def _run(body, argv=("--params", str(PARAMS))):
    return run_stage("demo", "demo stage", list(argv), ["base"], _options, body)


def test_body_gets_args_and_sections_and_its_code_is_the_exit_code():
    seen = []
    assert _run(lambda args, base: seen.append((args.out, base.seed)) or 3) == 3
    assert seen == [(Path("x"), load_section("base", PARAMS).seed)]


def test_bad_params_exit_2_before_the_body_runs(tmp_path, capsys):
    bad = tmp_path / "p.yaml"
    bad.write_text("base: {seed: not-a-number}\n")
    assert _run(lambda args, base: pytest.fail("the body must not run"), ("--params", str(bad))) == 2
    assert capsys.readouterr().err.startswith(f"demo: {bad}")


@pytest.mark.parametrize(
    "error, code",
    [
        (DataError("a.tar: damaged shard"), 1),
        (OSError("a.tar: disk full"), 1),
        (CommandFailure("a.tar: weights do not load", code=2), 2),
    ],
)
def test_failures_are_one_line_and_their_code(error, code, capsys):
    def body(args, base):
        with fails_on(OSError):
            raise error

    assert _run(body) == code
    err = capsys.readouterr().err
    assert err == f"demo: {error}\n"


def test_errors_not_listed_are_not_swallowed():
    def body(args, base):
        with fails_on(OSError):
            raise KeyError("a bug")

    with pytest.raises(KeyError):
        _run(body)

"""What every DVC stage script in stages/ does around its work, written once: the argument parser
(``--params`` plus the stage's own options; the script's docstring is its --help), the params
sections it reads, and the exit codes DVC and users see:

* 0: done;
* 2: bad params, found before anything heavy is imported (bpy and torch take seconds to load);
* 1: bad data or a missing input (``DataError``, or what a stage lists with ``fails_on``), as one
  line naming the file, never a traceback.

A stage script is then its docstring, its options and a ``body(args, *sections)``:

    def main(argv=None) -> int:
        return run_stage("shard", __doc__, argv, ["base", "shard", "render"], options, body, outputs=lambda a: [a.out])

``outputs`` names the stage's outputs (its dvc.yaml outs, metrics and plots): before the body runs, the
temporaries that a killed earlier run of the stage left beside or inside them are removed, and said
(pilight.atomic.sweep_temporaries; issue 36: killed stages left `data/.<out>.tmp-*` that nothing swept).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from pilight import atomic, process_gc
from pilight.data.schema import DataError
from pilight.failure import CommandFailure
from pilight.params import ParamsError, load_section


@contextmanager
def fails_on(*errors: type[BaseException]) -> Iterator[None]:
    """Inside the block, ``errors`` (the stage's own: RenderError, ModelError, OSError, ...) end the
    stage with exit 1 and their message. The classes are named where they can happen, after the
    stage imported its heavy modules."""
    try:
        yield
    except errors as exc:
        raise CommandFailure(str(exc)) from exc


def run_stage(
    name: str,
    doc: str,
    argv: list[str] | None,
    sections: Sequence[str],
    options: Callable[[argparse.ArgumentParser], None],
    body: Callable[..., int],
    outputs: Callable[[argparse.Namespace], Iterable[Path | None]] | None = None,
) -> int:
    """Parse ``argv``, load ``sections`` from --params, sweep the stale temporaries of ``outputs(args)``, run
    ``body(args, *sections)``; the exit code."""
    process_gc.freeze_at_exit()  # the stage process's exit skips a last walk of torch's objects (~0.8 s)
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--params", default="params.yaml")
    options(ap)
    args = ap.parse_args(argv)
    try:
        params = [load_section(s, args.params) for s in sections]
    except ParamsError as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        return 2
    try:
        swept = atomic.sweep_temporaries(*outputs(args)) if outputs is not None else []
        if swept:
            shown = ", ".join(map(str, swept[:3])) + (f" and {len(swept) - 3} more" if len(swept) > 3 else "")
            print(f"{name}: removed {len(swept)} temporary output(s) left by a killed run: {shown}", file=sys.stderr)
        return body(args, *params)
    except (CommandFailure, DataError) as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        return exc.code if isinstance(exc, CommandFailure) else 1

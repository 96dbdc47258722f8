"""DVC stage `export` of the base pipeline (base/dvc.yaml): the trained models -> the shipped pilight-base.

    python stages/export_model.py --params base/params.yaml --models base/models --out weights/pilight-base \\
        --metrics base/metrics/headline.json base/metrics/headline_heldout.json --live base/dvclive

Loads both stages as the photo pipeline does, stores their weights in half precision (both stages
together within the 40 MB git budget; they load back as float32), writes pipeline.json from the
params (processing resolution, samplers) and MODEL_CARD.md: what the base saw, how it was trained,
how long on what machine, and its figures on both test splits beside their baselines. The folder is
written under a temporary name and renamed, so a killed export leaves the old base whole.

A retrain of one stage: put the previous base's other stage in --models and name it with --keep-stage;
the card keeps that stage's training line from the card now in --out, marked as kept. A stage tuned from
its prior (for example base/tune.yaml, run by hand): --tuned intrinsics=tune.yaml adds the tune's own line,
read from that params file and from --live/intrinsics_tune. Both on one stage: the tune went on from the
previous release's weights, whose line is kept and marked as its prior.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

from pilight.failure import CommandFailure
from pilight.stage_cli import fails_on, run_stage

MAX_BYTES = 40 * 1024 * 1024  # both stages' safetensors together: the shipped base lives in git


def options(ap) -> None:
    ap.add_argument("--models", type=Path, default=Path("base/models"))
    ap.add_argument("--out", type=Path, default=Path("weights/pilight-base"))
    ap.add_argument("--metrics", type=Path, nargs="*", default=[], help="headline.json of each test split")
    ap.add_argument("--live", type=Path, default=None, help="dvclive folder of both training stages")
    ap.add_argument(
        "--keep-stage",
        choices=["intrinsics", "relight"],
        action="append",
        default=[],
        help="a stage not retrained: its weights in --models are the previous base's, and the card keeps its "
        "training line from the card now in --out (its dvclive is not needed); with --tuned on the same stage, "
        "--models holds the tune's weights and the kept line is marked as the tune's prior",
    )
    ap.add_argument(
        "--tuned",
        action="append",
        default=[],
        metavar="STAGE=PARAMS",
        help="a stage whose weights in --models were tuned from its prior by the params file PARAMS; the card "
        "adds the tune's line from PARAMS and --live/STAGE_tune",
    )


def _read(path: Path) -> dict:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise CommandFailure(f"{path}: unreadable ({exc})") from None


KEPT_NOTE = " (not retrained since; kept from the previous card)"
# a kept stage that this export's --tuned went on from: the previous release's weights were its prior
PRIOR_NOTE = " (the previous release's; kept from its card, and tuned since as the next line says)"


def _kept_line(card: Path, stage: str, tuned_since: bool = False) -> str:
    """The previous card's Training line of ``stage`` (and its tune's, if any), marked as kept, or as the
    prior of this export's tune when ``tuned_since``."""
    try:
        lines = card.read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        raise CommandFailure(f"--keep-stage {stage}: no previous card to keep its training line from ({exc})") from None
    found = [line for line in lines if line.startswith((f"- **{stage}**:", f"- **{stage}, tuned**"))]
    if not found or not found[0].startswith(f"- **{stage}**:"):
        raise CommandFailure(f"--keep-stage {stage}: {card} has no '- **{stage}**:' training line")
    # a tune's line goes with its prior's: both made the kept weights
    note = PRIOR_NOTE if tuned_since else KEPT_NOTE
    return "\n".join(line.removesuffix(KEPT_NOTE).removesuffix(PRIOR_NOTE) + note for line in found)


def _run_log(live: Path) -> dict:
    """A training run's dvclive summary with the machine it ran on (the card's Training line)."""
    return _read(live / "metrics.json") | {"machine": _read(live / "machine.json")}


def _tunes(args) -> dict[str, tuple]:
    """{stage: (the tune's params section, its run's log)} for each --tuned STAGE=PARAMS."""
    from pilight.params import load_section

    tunes = {}
    for item in args.tuned:
        stage, _, path = item.partition("=")
        if stage not in ("intrinsics", "relight") or not path:
            raise CommandFailure(f"--tuned {item!r}: expected intrinsics=PARAMS or relight=PARAMS")
        if args.live is None:
            raise CommandFailure(f"--tuned {item}: needs --live (the tune's log is --live/{stage}_tune)")
        log = _run_log(args.live / f"{stage}_tune")
        tunes[stage] = (load_section(stage, Path(path), check_paths=False), log)
    return tunes


def body(args, base, render, intrinsics, relight) -> int:
    import torch

    from pilight.base_model import CARD
    from pilight.eval.model_card import model_card
    from pilight.pipeline import PILightPipeline, PipelineError

    with fails_on(PipelineError):
        pipe = PILightPipeline.from_pretrained(args.models, device="cpu", params=args.params)
    metrics = {p.stem: _read(p) for p in args.metrics}
    tuned = _tunes(args)
    kept = {stage: _kept_line(args.out / CARD, stage, tuned_since=stage in tuned) for stage in args.keep_stage}
    training = {}
    if args.live is not None:
        for stage in sorted({"intrinsics", "relight"} - set(kept)):
            training[stage] = _run_log(args.live / stage)
    tmp = args.out.with_name(f".{args.out.name}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    pipe.save_pretrained(tmp, dtype=torch.float16)
    size = sum(f.stat().st_size for f in tmp.rglob("*.safetensors"))
    if size > MAX_BYTES:
        shutil.rmtree(tmp)
        raise CommandFailure(f"{args.out}: the weights take {size / 2**20:.1f} MB, over the 40 MB git budget")
    card = model_card(
        base,
        render,
        intrinsics,
        relight,
        metrics=metrics,
        training=training,
        weights_bytes=size,
        kept=kept,
        tuned=tuned,
    )
    (tmp / CARD).write_text(card, encoding="utf-8")
    old = args.out.with_name(f".{args.out.name}.old")
    shutil.rmtree(old, ignore_errors=True)
    if args.out.exists():
        args.out.rename(old)
    tmp.rename(args.out)
    shutil.rmtree(old, ignore_errors=True)
    print(f"export: {args.out} ({size / 2**20:.1f} MB of weights, float16) with {CARD}")
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_stage(
        "export", __doc__, argv, ["base", "render", "intrinsics", "relight"], options, body, outputs=lambda a: [a.out]
    )


if __name__ == "__main__":
    sys.exit(main())

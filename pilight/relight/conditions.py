"""The intrinsics stage 2 is conditioned on: ground truth, or stage-1 predictions of the input image.

`relight.conditions` (gt | pred | mix) chooses per training sample; the relight stage and the
oracles use stage-1 predictions whenever the prediction folder holds the split.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from pilight.data import schema
from pilight.data.pairs import read_pairs
from pilight.data.predictions import read_predictions
from pilight.data.schema import DataError
from pilight.params import DOMAINS


def _sample_keys(batch: dict) -> list[str]:
    """Stage-1 prediction keys of the INPUT images: `<scene>_vNN_lNN` of meta_a."""
    metas = [json.loads(m) if isinstance(m, str) else m for m in batch["meta_a"]]
    return [schema.sample_key(m["scene"], m["view"], m["light"]) for m in metas]


def load_condition_predictions(
    shard_dir: Path, pred_dir: Path | None, split: str, why: str
) -> dict[str, dict[str, np.ndarray]]:
    """Stage-1 predictions for every input image of `split`'s pairs; DataError naming what is missing."""
    if pred_dir is None or not (Path(pred_dir) / "index.json").is_file():
        raise DataError(
            f"{why} needs stage-1 predictions of the {split!r} split, but {pred_dir}/index.json "
            "was not found: run infer_intrinsics (with infer_intrinsics.splits including "
            f"{split!r}) first, or set relight.conditions: gt"
        )
    try:
        preds = read_predictions(Path(pred_dir), split)
    except DataError as exc:
        raise DataError(f"{why}: {exc}") from None
    needed = sorted(
        {schema.sample_key(p.scene, p.view, p.a) for p in read_pairs(Path(shard_dir) / "pairs" / f"{split}.tsv")}
    )
    missing = [k for k in needed if k not in preds]
    if missing:
        raise DataError(
            f"{why}: {pred_dir} has no {split!r} predictions for {len(missing)} input image(s), e.g. "
            f"{missing[:3]}; rerun infer_intrinsics on the current shards"
        )
    short = sorted({d for k in needed for d in DOMAINS if d not in preds[k]})
    if short:
        raise DataError(
            f"{why}: {pred_dir} lacks predicted {short} (infer_intrinsics.domains must include all of {list(DOMAINS)})"
        )
    return preds


def optional_predictions(shard_dir: Path, pred_dir: Path, split: str, why: str) -> dict | None:
    """Stage-1 predictions of ``split`` when ``pred_dir`` holds them, else None: the caller then
    conditions on ground truth and must say so in what it writes."""
    index = Path(pred_dir) / "index.json"
    if not index.is_file() or split not in json.loads(index.read_text()).get("splits", {}):
        return None
    return load_condition_predictions(shard_dir, pred_dir, split, why)


def choose_intrinsics(batch: dict, use_pred: torch.Tensor, preds: dict | None) -> dict[str, torch.Tensor]:
    """Per sample: stage-1 predictions of image a where use_pred, ground truth elsewhere."""
    out = {d: batch[d].clone() for d in DOMAINS}
    if not bool(use_pred.any()):
        return out
    for i, key in enumerate(_sample_keys(batch)):
        if not use_pred[i]:
            continue
        if preds is None or key not in preds:
            raise DataError(f"no stage-1 prediction for input image {key}")
        for d in DOMAINS:
            out[d][i] = torch.from_numpy(preds[key][d]).permute(2, 0, 1).to(out[d])
    return out


def oracle_conditions(
    b: dict, preds: dict | None, *, only: str | None = None, at_gt_level: bool = False
) -> dict[str, torch.Tensor]:
    """The conditions of an oracle study (benchmarks/oracle_relight.py): ground truth (preds None) or
    stage-1 predictions; ``only``: that map from stage 1 and the rest
    ground truth; ``at_gt_level``: the albedo rescaled per image and channel to the truth's mean on
    the mask (its pattern kept, its level the truth's)."""
    c = choose_intrinsics(b, torch.full((len(b["meta_a"]),), preds is not None), preds)
    if only is not None:
        c = {d: (c[d] if d == only else b[d].clone()) for d in c}
    if at_gt_level:
        inside = (b["mask"] > 0.5).float()
        truth = (b["albedo"].float() * inside).sum((2, 3), keepdim=True)
        pred = (c["albedo"].float() * inside).sum((2, 3), keepdim=True).clamp_min(1e-6)
        c["albedo"] = c["albedo"] * (truth / pred)
    return c

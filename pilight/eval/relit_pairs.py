"""What the relight stage writes to data/relit, as generators for write_predictions: the held-out pairs
relit by the trained stage-2 model (DDIM or single-step, CFG; the relit image, D and S of a pair in
one batched pass), keyed by the pair key `<scene>_vNN_lAA_to_lBB`, and the light-following probes;
``relight_split`` runs them all, writes data/relit and returns what the run measured.

Splits of data/relit, per method and conditions (stage-1 predictions when the prediction folder
holds the split: no ground-truth intrinsics at test time; else ground truth) and intensity (the
evaluation's tiers, pilight.eval.relight):

    <split>                 model, relative intensity, every pair (cross-light and identity)
    <split>_gt              model, relative, cross-light pairs, ground-truth conditions (when <split> used predictions)
    <split>_abs, <split>_gt_abs         the same with absolute intensity (the ball as rendered: the paper's setting)
    <split>_anchor, <split>_gt_anchor, <split>_anchor_abs, <split>_gt_anchor_abs
                            the physics-first anchor with zero gains (no network), the same four settings
    probes                  PROBE_IMAGES test images under the probe lights (pilight.eval.light_following)

Relative intensity tells the model k = r = level(ball_b) / level(ball_a) of the rendered pair, as a
user states k (pilight.relight.intensity). With relight.physics_first the outputs also hold "albedo",
the A_x of I_relit = A_x D + S.

``task`` is anything with ``predict(batch, sampling, generator, intrinsics)``, ``branches`` and
``describe()`` (pilight.train.relight's RelightTask); eval never imports pilight.train.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import torch
from tqdm import tqdm

from pilight.data.predictions import write_predictions
from pilight.data.shard_reader import eval_dataset, make_loader
from pilight.eval.flip_check import FLIP_CHECK_BATCHES, flip_check
from pilight.eval.light_following import PROBE_LIGHTS, PROBE_SPLIT, cross_light, probe_batch, probe_key, select_probes
from pilight.params import DOMAINS
from pilight.relight.conditions import choose_intrinsics
from pilight.relight.intensity import relative_pair

PROBE_IMAGES = 12  # light-following probe images (the issue asks for at least 12)


class RunStats:
    """What the main pass measures: seconds and pairs, the physics-first identity residual
    |I_relit - A_x D - S| against |I_relit| on the mask (float32 outputs), and the first batches
    (the flipped-normal check reuses them)."""

    def __init__(self, keep_batches: int):
        self.pairs, self.seconds, self.identity_abs, self.identity_ref = 0, 0.0, 0.0, 0.0
        self.keep_batches, self.first = keep_batches, []

    def add(self, batch: dict, out: dict, seconds: float) -> None:
        self.seconds += seconds
        self.pairs += len(batch["key"])
        if "albedo" in out:  # physics_first: the relit image is A_x D + S on the mask
            m = batch["mask"].expand_as(out["relit"]) > 0.5
            composed = out["albedo"] * out["diffuse"] + out["specular"]
            self.identity_abs += float((out["relit"] - composed).abs()[m].sum())
            self.identity_ref += float(out["relit"].abs()[m].sum())
        if len(self.first) < self.keep_batches:
            self.first.append(batch)

    def identity_residual(self) -> float | None:
        return self.identity_abs / self.identity_ref if self.identity_ref > 0 else None


def relit_pairs(
    task,
    shards: Path,
    split: str,
    ip,
    seed: int,
    conditions: str,
    preds: dict | None,
    cross_only: bool = False,
    stats: RunStats | None = None,
    intensity: str = "relative",
    method: str = "model",
):
    """(key, {branch: H x W x C}, meta JSON) of every pair of ``split`` (only the cross-light ones with
    ``cross_only``), conditioned on ``conditions`` ("pred": ``preds``, "gt": ground truth), with the
    target light's ``intensity`` relative or absolute; ``method`` "anchor": the zero-gain physics anchor."""
    gen = torch.Generator().manual_seed(seed)
    desc = f"relight {split} ({method}, {conditions} conditions, {intensity})"
    with tqdm(desc=desc, unit="pair") as bar:
        for batch in make_loader(eval_dataset(shards, split, "relight"), ip.batch_size):
            if cross_only:
                batch = cross_light(batch)
                if batch is None:
                    continue
            B = len(batch["key"])
            intr = choose_intrinsics(batch, torch.full((B,), conditions == "pred"), preds)
            given = relative_pair(batch) if intensity == "relative" else batch
            t0 = time.perf_counter()
            out = task.predict(given, ip, gen, intr, intensity=intensity, zero_gains=method == "anchor")
            if stats is not None:
                stats.add(batch, out, time.perf_counter() - t0)
            for i, key in enumerate(batch["key"]):
                ma, mb = json.loads(batch["meta_a"][i]), json.loads(batch["meta_b"][i])
                meta = json.dumps(
                    {
                        "scene": ma["scene"],
                        "view": ma["view"],
                        "light_a": ma["light"],
                        "light_b": mb["light"],
                        "conditions": conditions,
                        "intensity": intensity,
                        "method": method,
                    },
                    sort_keys=True,
                )
                yield key, {b: v[i].cpu().numpy().transpose(1, 2, 0) for b, v in out.items()}, meta
            bar.update(B)


def relit_probes(task, shards: Path, split: str, ip, seed: int, preds: dict | None):
    """The light-following probes (pilight.eval.light_following): each probe image under the four
    PROBE_LIGHTS, conditioned like the main pass."""
    source = "pred" if preds is not None else "gt"
    chosen = select_probes(make_loader(eval_dataset(shards, split, "relight"), 8), PROBE_IMAGES)
    for probe in tqdm(chosen, desc="relight probes", unit="image"):
        batch = probe_batch(probe)
        intr = choose_intrinsics(batch, torch.full((len(PROBE_LIGHTS),), preds is not None), preds)
        out = task.predict(batch, ip, torch.Generator().manual_seed(seed), intr)
        for i, light in enumerate(PROBE_LIGHTS):
            meta = json.dumps({"probe_light": light, "conditions": source}, sort_keys=True)
            yield probe_key(probe, light), {"relit": out["relit"][i].cpu().numpy().transpose(1, 2, 0)}, meta


def index_info(task, ip, source: str, written: dict[str, str]) -> dict:
    """What data/relit's index records beside the splits: branches, sampling, conditions, the model's parts."""
    return {
        "branches": list(task.branches),
        "sampling": ip.model_dump(mode="json"),
        "conditions": source,
        "condition_domains": list(DOMAINS),
        "parts": task.describe(),
        "splits_written": written,
    }


def relit_jobs(task, shards: Path, split: str, ip, seed: int, preds: dict | None, stats: RunStats):
    """{split name: (generator, what it holds)}: the splits of the module docstring. The first one
    (the model, relative, every pair) feeds ``stats``."""
    source = "pred" if preds is not None else "gt"
    anchor = task.physics_first
    jobs = {}
    for intensity, tail in (("relative", ""), ("absolute", "_abs")):
        for method in ("model", "anchor") if anchor else ("model",):
            mid = "_anchor" if method == "anchor" else ""
            how = {"intensity": intensity, "method": method}
            first = not jobs
            jobs[f"{split}{mid}{tail}"] = (
                relit_pairs(task, shards, split, ip, seed, source, preds, stats=stats if first else None, **how),
                f"{method}, every pair, {source} conditions, {intensity} intensity",
            )
            if source == "pred":
                jobs[f"{split}_gt{mid}{tail}"] = (
                    relit_pairs(task, shards, split, ip, seed, "gt", preds, cross_only=True, **how),
                    f"{method}, cross-light pairs, ground-truth conditions, {intensity} intensity",
                )
    return jobs


def relight_split(
    task, shards: Path, out: Path, split: str, ip, seed: int, preds: dict | None, check_flip: bool = True
) -> dict:
    """Relight ``split`` into ``out`` (data/relit: the splits above, conditioned on ``preds`` when given,
    else on ground truth), then the flipped-normal check (pilight.eval.flip_check) on the first batches
    when ``check_flip`` and the model has the diffuse branch. Returns metrics/relight.json: timings,
    the identity residual and the flip check vary or are checks, so they stay out of ``out``, which is
    byte-deterministic."""
    source = "pred" if preds is not None else "gt"
    stats = RunStats(FLIP_CHECK_BATCHES)
    described = relit_jobs(task, shards, split, ip, seed, preds, stats)
    jobs = {name: gen for name, (gen, _) in described.items()}
    jobs[PROBE_SPLIT] = relit_probes(task, shards, split, ip, seed, preds)
    written = {name: what for name, (_, what) in described.items()}
    written[PROBE_SPLIT] = "probe images under the light-following probe lights"
    out_index = write_predictions(out, jobs, index_info(task, ip, source, written))
    out = {
        "seconds_per_pair": stats.seconds / max(stats.pairs, 1),
        "pairs": stats.pairs,
        "samples": out_index["splits"][split]["samples"],
    }  # numbers only: the conditions are in data/relit/index.json
    if stats.identity_residual() is not None:
        out["identity_residual_relative"] = stats.identity_residual()
    if check_flip and stats.first and "diffuse" in task.branches:  # needs the diffuse branch
        out["flip_check_d_pred"] = flip_check(task, stats.first, ip, seed)
    return out

"""DVC stage `relight`: relight the test pairs with the trained stage-2 model (DDIM or single-step,
CFG; the relit image, D and S of a pair in one batched pass) and write them in the prediction
shard format, keyed by the pair key `<scene>_vNN_lAA_to_lBB`.

    python stages/relight.py

A stage of its own so that changing relight_infer (cfg_scale, steps) reruns sampling only, never
training. Conditions: stage-1 predictions of the input image when data/intrinsics_pred holds the
split (the realistic setting: no ground-truth intrinsics at test time), else ground truth; the
output index records which. The mask and the target light ball always come from the shards.

Also the paper's appendix check on the first FLIP_CHECK_BATCHES batches of pairs, conditioned on
ground-truth intrinsics: the same pairs with the x channel of N flipped; the left/right asymmetry of
D_pred should change sign (metrics/relight.json).

Splits written to data/relit: `<split>` (every pair, the conditions above), `<split>_gt` (the
cross-light pairs again with ground-truth conditions, when the first used stage-1 predictions) and
`probes` (PROBE_IMAGES test images under the light-following probe lights: pilight.eval.light_following).
With relight.physics_first the outputs also hold "albedo", the A_x of I_relit = A_x D + S.

Reads params `base`, `relight` (the model) and `relight_infer`; models/relight + data/shards
(+ data/intrinsics_pred) -> data/relit; timings and the identity residual -> metrics/relight.json
(never into data/relit, which is byte-deterministic).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pilight import atomic  # noqa: E402
from pilight.params import ParamsError, load_section  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--params", default="params.yaml")
    ap.add_argument("--shards", type=Path, default=Path("data/shards"))
    ap.add_argument("--pred", type=Path, default=Path("data/intrinsics_pred"))
    ap.add_argument("--model", type=Path, default=Path("models/relight"))
    ap.add_argument("--out", type=Path, default=Path("data/relit"))
    ap.add_argument("--metrics", type=Path, default=Path("metrics/relight.json"))
    ap.add_argument("--no-flip-check", action="store_true", help="skip the flipped-normal check (one extra batch)")
    args = ap.parse_args(argv)
    try:
        base = load_section("base", args.params)
        p, ip = load_section("relight", args.params), load_section("relight_infer", args.params)
    except ParamsError as exc:
        print(f"relight: {exc}", file=sys.stderr)
        return 2
    import torch
    from tqdm import tqdm

    from pilight.data.predictions import write_predictions
    from pilight.data.schema import DataError
    from pilight.data.shards import eval_dataset, make_loader, read_index
    from pilight.eval.light_following import (PROBE_LIGHTS, PROBE_SPLIT, cross_light, probe_batch, probe_key,
                                              select_probes)
    from pilight.train.build import ModelError, check_image_size, load_model
    from pilight.relight.conditions import PRED_DOMAINS, choose_intrinsics, optional_predictions
    from pilight.train.relight import RelightTask

    split = ip.split
    try:
        index = read_index(args.shards)
        if not index["splits"].get(split, {}).get("shards"):
            raise DataError(f"{args.shards}: the {split} split has no shards")
        # Conditions for the model are chosen below, not by relight.conditions (a training setting).
        task = RelightTask(p.model_copy(update={"conditions": "gt"}), args.shards, seed=base.seed)
        check_image_size(tuple(index["sizes"]["image"][:2]), task.stack.codec.factor, f"{args.shards}/index.json")
        load_model(task.stack, args.model)
        preds = optional_predictions(args.shards, args.pred, split, "relight")
    except (DataError, ModelError, FileNotFoundError, ValueError) as exc:
        print(f"relight: {exc}", file=sys.stderr)
        return 1
    source = "pred" if preds is not None else "gt"
    task.stack.model.eval()
    timing = {"pairs": 0, "seconds": 0.0}
    identity = {"abs": 0.0, "ref": 0.0}  # |I_relit - A D - S| and |I_relit| on the mask, float32 outputs
    first: list[dict] = []  # the batches the flipped-normal check reuses

    def relit(conditions: str, cross_only: bool = False):
        loader = make_loader(eval_dataset(args.shards, split, "relight"), ip.batch_size)
        gen = torch.Generator().manual_seed(base.seed)
        main = conditions == source
        with tqdm(desc=f"relight {split} ({conditions} conditions)", unit="pair") as bar:
            for batch in loader:
                if cross_only:
                    batch = cross_light(batch)
                    if batch is None:
                        continue
                B = len(batch["key"])
                intr = choose_intrinsics(batch, torch.full((B,), conditions == "pred"), preds)
                t0 = time.perf_counter()
                out = task.predict(batch, ip, gen, intr)
                if main:
                    timing["seconds"] += time.perf_counter() - t0
                    timing["pairs"] += B
                    if "albedo" in out:  # physics_first: the relit image is A_x D + S on the mask
                        m = batch["mask"].expand_as(out["relit"]) > 0.5
                        composed = out["albedo"] * out["diffuse"] + out["specular"]
                        identity["abs"] += float((out["relit"] - composed).abs()[m].sum())
                        identity["ref"] += float(out["relit"].abs()[m].sum())
                    if len(first) < FLIP_CHECK_BATCHES:
                        first.append(batch)
                for i, key in enumerate(batch["key"]):
                    ma, mb = json.loads(batch["meta_a"][i]), json.loads(batch["meta_b"][i])
                    meta = json.dumps({"scene": ma["scene"], "view": ma["view"], "light_a": ma["light"],
                                       "light_b": mb["light"], "conditions": conditions}, sort_keys=True)
                    yield key, {b: v[i].cpu().numpy().transpose(1, 2, 0) for b, v in out.items()}, meta
                bar.update(B)

    def probes():
        """The light-following probes (pilight.eval.light_following): each probe image under four lights."""
        chosen = select_probes(make_loader(eval_dataset(args.shards, split, "relight"), 8), PROBE_IMAGES)
        for probe in tqdm(chosen, desc="relight probes", unit="image"):
            batch = probe_batch(probe)
            intr = choose_intrinsics(batch, torch.full((len(PROBE_LIGHTS),), preds is not None), preds)
            out = task.predict(batch, ip, torch.Generator().manual_seed(base.seed), intr)
            for i, light in enumerate(PROBE_LIGHTS):
                meta = json.dumps({"probe_light": light, "conditions": source}, sort_keys=True)
                yield probe_key(probe, light), {"relit": out["relit"][i].cpu().numpy().transpose(1, 2, 0)}, meta

    info = {"branches": list(task.branches), "sampling": ip.model_dump(mode="json"), "conditions": source,
            "condition_domains": list(PRED_DOMAINS), "parts": task.describe(),
            "splits_written": {split: f"every pair, {source} conditions",
                               f"{split}_gt": "cross-light pairs, ground-truth conditions",
                               PROBE_SPLIT: "probe images under the light-following probe lights"}}
    jobs = {split: relit(source)}
    if source == "pred":
        jobs[f"{split}_gt"] = relit("gt", cross_only=True)
    jobs[PROBE_SPLIT] = probes()
    out_index = write_predictions(args.out, jobs, info)

    flip = {"pairs": 0, "note": "needs the diffuse branch (relight.decomposition: true)"}
    if not args.no_flip_check and first and "diffuse" in task.branches:
        flip = flip_check(task, first, ip, base.seed)
    per_pair = timing["seconds"] / max(timing["pairs"], 1)
    ident = identity["abs"] / identity["ref"] if identity["ref"] > 0 else None
    atomic.write_json(args.metrics, {"seconds_per_pair": per_pair, "pairs": timing["pairs"], "conditions": source,
                                     "identity_residual_relative": ident,
                                     "samples": out_index["splits"][split]["samples"], "flip_check_d_pred": flip},
                      sort_keys=True)
    print(f"relight: {timing['pairs']} pairs, {per_pair:.3f} s/pair ({ip.mode}, {ip.steps} steps, cfg {ip.cfg_scale}, "
          f"ensemble {ip.ensemble}, conditions {source}) -> {args.out}")
    return 0


PROBE_IMAGES = 12        # light-following probe images (the issue asks for at least 12)
FLIP_CHECK_BATCHES = 3  # relight_infer.batch_size pairs each (12 with the default 4)
FLIP_VISIBLE = 0.1      # |(R - L) / (R + L)| of D_pred above which a pair shows a side at all


def flip_check(task, batches: list[dict], ip, seed: int, visible_above: float = FLIP_VISIBLE) -> dict:
    """The paper's appendix check on the model: D_pred with N and with N_x flipped, on GROUND-TRUTH
    intrinsics (the paper edits the normal map; stage-1 errors would only blur what is being tested).
    If the shading follows N, the left/right asymmetry changes sign."""
    import torch

    from pilight.eval.light_following import lr_asymmetry
    from pilight.relight.conditions import choose_intrinsics

    a, b = [], []
    for batch in batches:
        intr = choose_intrinsics(batch, torch.zeros(len(batch["key"]), dtype=torch.bool), None)
        flipped = {k: v.clone() for k, v in intr.items()}
        flipped["normal"][:, 0] *= -1
        # The same generator seed for both: only the normals differ.
        d = task.predict(batch, ip, torch.Generator().manual_seed(seed), intr)["diffuse"]
        d_flip = task.predict(batch, ip, torch.Generator().manual_seed(seed), flipped)["diffuse"]
        a.append(lr_asymmetry(d, intr["normal"], batch["mask"]))  # unflipped N classifies right/left-facing pixels
        b.append(lr_asymmetry(d_flip, intr["normal"], batch["mask"]))
    a, b = torch.cat(a), torch.cat(b)
    visible = a.abs() > visible_above
    return {"pairs": len(a), "conditions": "gt", "asymmetry_with_n": a.tolist(), "asymmetry_with_flipped_n": b.tolist(),
            "pairs_considered": int(visible.sum()),
            "sign_flipped_fraction": float(((a * b) < 0)[visible].float().mean()) if visible.any() else None,
            "moved_toward_flip_fraction": float(((b - a) * a < 0)[visible].float().mean()) if visible.any() else None,
            "what": f"(R - L) / (R + L) of masked D_pred over right-/left-facing pixels (unflipped n_x > 0.2 / < -0.2), "
                    f"ground-truth intrinsics; over pairs with |asymmetry| > {visible_above}: the share whose sign "
                    "flips when N_x is flipped, and the share that moves toward the flipped side"}


if __name__ == "__main__":
    sys.exit(main())

"""The paper's appendix check on the trained stage-2 model: the diffuse shading D_pred with the
normals N and with N_x flipped, on GROUND-TRUTH intrinsics (the paper edits the normal map; stage-1
errors would only blur what is being tested). If the shading follows N, the left/right asymmetry
(pilight.eval.light_following.lr_asymmetry) changes sign. The relight stage runs it on its first
FLIP_CHECK_BATCHES batches of pairs and writes the result to metrics/relight.json."""

from __future__ import annotations

import torch

from pilight.eval.light_following import lr_asymmetry
from pilight.relight.conditions import choose_intrinsics

FLIP_CHECK_BATCHES = 3  # relight_infer.batch_size pairs each (12 with the default 4)
FLIP_VISIBLE = 0.1  # |(R - L) / (R + L)| of D_pred above which a pair shows a side at all


def flip_check(task, batches: list[dict], ip, seed: int, visible_above: float = FLIP_VISIBLE) -> dict:
    """``task.predict(batch, ip, generator, intrinsics)`` gives "diffuse"; the shares of pairs whose
    asymmetry flips sign, and moves toward the flipped side, among those with a visible side."""
    a, b = [], []
    for batch in batches:
        intr = choose_intrinsics(batch, torch.zeros(len(batch["key"]), dtype=torch.bool), None)
        flipped = {k: v.clone() for k, v in intr.items()}
        flipped["normal"][:, 0] *= -1
        # The same generator seed for both: only the normals differ.
        # absolute: the rendered ball as it is (the check is about D's sides, not its level)
        d = task.predict(batch, ip, torch.Generator().manual_seed(seed), intr, intensity="absolute")["diffuse"]
        d_flip = task.predict(batch, ip, torch.Generator().manual_seed(seed), flipped, intensity="absolute")["diffuse"]
        a.append(lr_asymmetry(d, intr["normal"], batch["mask"]))  # unflipped N classifies right/left-facing pixels
        b.append(lr_asymmetry(d_flip, intr["normal"], batch["mask"]))
    a, b = torch.cat(a), torch.cat(b)
    visible = a.abs() > visible_above
    # numbers only (metrics/relight.json); what they measure is this function's docstring. Ground-truth
    # intrinsics; asymmetry = (R - L) / (R + L) of masked D_pred over right-/left-facing pixels (unflipped
    # n_x > 0.2 / < -0.2); over pairs with |asymmetry| > visible_above: the share whose sign flips when N_x
    # is flipped, and the share that moves toward the flipped side.
    out = {"pairs": len(a), "pairs_considered": int(visible.sum())}
    if visible.any():
        out["sign_flipped_fraction"] = float(((a * b) < 0)[visible].float().mean())
        out["moved_toward_flip_fraction"] = float(((b - a) * a < 0)[visible].float().mean())
    return out

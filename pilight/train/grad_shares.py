"""Each loss term's share of the gradient: how much of the training signal a term carries.

The paper weighs its physics terms by 1/t. Where single-step training happens (t = T-1 = 999) that is
0.001, so the terms may carry under 1% of the signal, and an ablation that removes them cannot show
an effect at this scale. `train.grad_share_every: N` measures it every N loss calls: the norm of the
gradient of each weighted term alone, over the trainable parameters, divided by the sum of the norms.
One backward pass per term, so it is off (0) in the default and on for the ablation's runs.
"""

from __future__ import annotations

import math

import torch


def grad_shares(terms: dict[str, torch.Tensor], params: list[torch.nn.Parameter]) -> dict[str, float]:
    """{"grad_share_<term>": ||d term / d params|| / sum of the terms' norms}; a term without a graph is 0."""
    norms = {}
    for name, value in terms.items():
        if not (torch.is_tensor(value) and value.requires_grad):
            norms[name] = 0.0
            continue
        grads = torch.autograd.grad(value, params, retain_graph=True, allow_unused=True)
        norms[name] = math.sqrt(sum(float((g.float() ** 2).sum()) for g in grads if g is not None))
    total = sum(norms.values())
    return {f"grad_share_{k}": (v / total if total > 0 else 0.0) for k, v in norms.items()}

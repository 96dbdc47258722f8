"""Each loss term's share of the gradient norm (pilight.train.grad_shares), and stage 2 logging it."""

from __future__ import annotations

import pytest
import torch

from pilight.train.grad_shares import grad_shares


def test_shares_are_the_terms_gradient_norms_over_their_sum():
    w = torch.nn.Parameter(torch.tensor([1.0, 2.0]))
    terms = {"a": (w * torch.tensor([3.0, 4.0])).sum(), "b": 3 * (w * torch.tensor([3.0, 4.0])).sum()}
    terms["none"] = torch.tensor(5.0)  # no graph: carries no signal
    shares = grad_shares(terms, [w])
    assert shares == pytest.approx({"grad_share_a": 0.25, "grad_share_b": 0.75, "grad_share_none": 0.0})
    w.grad = None
    assert w.grad is None  # autograd.grad, not backward: the training step's gradients are untouched


def test_stage_two_logs_shares_summing_to_one(tmp_path):
    from fixtures.relight_pairs import physics_pair, tiny_relight_task

    task = tiny_relight_task(tmp_path, train={"grad_share_every": 1}, lambda_image=1.0)
    b = physics_pair()
    b |= {"diffuse_a": b["image_a"], "specular_a": torch.zeros_like(b["image_a"])}
    task.stack.model.train()
    _, logs = task.loss(b, torch.Generator().manual_seed(0))
    shares = {k: v for k, v in logs.items() if k.startswith("grad_share_")}
    assert set(shares) == {f"grad_share_{k}" for k in ("vpred", "ds", "ps", "rec", "image")}
    assert sum(shares.values()) == pytest.approx(1.0)
    _, quiet = tiny_relight_task(tmp_path, lambda_image=1.0).loss(b, torch.Generator().manual_seed(0))
    assert not any(k.startswith("grad_share_") for k in quiet)  # off by default: no extra backward passes

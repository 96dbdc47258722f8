"""Stage 2's objective in one place (pilight.relight.objective): which terms are on, the 1/t weight,
and the image loss on the terminal samples only."""

from __future__ import annotations

import pytest
import torch

from fixtures.tiny_models import REPO
from pilight.params import load_section
from pilight.relight import objective
from pilight.relight.encoding import tonemap


@pytest.fixture(scope="module")
def p():
    return load_section("relight", REPO / "params.yaml")


def test_the_no_physics_ablation_decodes_nothing(p):
    off = p.model_copy(update={"lambda_ds": 0.0, "lambda_ps": 0.0, "lambda_rec": 0.0, "lambda_image": 0.0})
    assert not objective.needs_decode(off)
    assert objective.needs_decode(off.model_copy(update={"lambda_image": 1.0}))
    assert objective.needs_decode(p)


def test_time_weight_floors_t_at_t_min(p):
    w = objective.time_weight(torch.tensor([0, 1, 4]), p.model_copy(update={"t_min": 2.0}))
    assert w.tolist() == [0.5, 0.5, 0.25]


def test_the_image_loss_counts_only_the_samples_at_the_terminal_timestep():
    target = torch.zeros(2, 3, 4, 4)
    relit = torch.stack([tonemap(target[0]) + 0.5, tonemap(target[1]) + 3.0])  # errors 0.25 and 9 per pixel
    loss, logged = objective.image_loss(relit, target, torch.tensor([999, 10]), 1000)
    assert logged == pytest.approx(0.25)  # the mean over the terminal samples
    assert float(loss) == pytest.approx(0.25 / 2)  # the batch mean, the other sample weighted 0

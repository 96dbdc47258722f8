"""relight.level_prior: the input light's estimated level shrunk toward the training lights', in training
and at inference alike (pilight.relight.level_prior)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from pydantic import ValidationError

from fixtures.relight_pairs import TINY, physics_pair, tiny_relight_task
from pilight.base_model import mismatches
from pilight.params import RelightParams
from pilight.physics.envmap import light_level
from pilight.relight import physics_first as pf
from pilight.relight.intensity import relative_pair, to_source_level
from pilight.relight.level_prior import fit_level_prior, shrink_level


def test_the_fit_recovers_the_line_through_the_logs():
    rng = np.random.default_rng(0)
    est = np.exp(rng.uniform(-2, 2, 400))
    true = np.exp(-0.3 + 0.45 * np.log(est) + rng.normal(0, 0.05, 400))
    fit = fit_level_prior(est, true)
    assert fit["alpha"] == pytest.approx(-0.3, abs=0.02)
    assert fit["beta"] == pytest.approx(0.45, abs=0.02)
    assert fit["inputs"] == 400
    assert fit["rms_log_error_after"] == pytest.approx(0.05, abs=0.01)
    assert fit["rms_log_error_before"] > 0.5


@pytest.mark.parametrize(
    "est, true, message",
    [
        ([1.0, 2.0], [1.0, 2.0], "at least 3"),
        ([1.0, 0.0, 2.0], [1.0, 1.0, 2.0], "positive"),
        ([2.0, 2.0, 2.0], [1.0, 2.0, 3.0], "undetermined"),
        ([1.0, 2.0, 3.0], [1.0, 2.0], "one length"),
    ],
)
def test_the_fit_refuses_what_it_cannot_fit(est, true, message):
    with pytest.raises(ValueError, match=message):
        fit_level_prior(np.array(est), np.array(true))


def test_shrinking_is_the_line_and_zero_one_is_the_identity():
    level = torch.tensor([0.05, 0.5, 3.0])
    torch.testing.assert_close(shrink_level(level, 0.0, 1.0), level)
    torch.testing.assert_close(shrink_level(level, -0.27, 0.43), torch.exp(-0.27 + 0.43 * torch.log(level)))


def test_to_source_level_scales_found_inputs_to_the_shrunk_level_only():
    b = physics_pair()
    rel = relative_pair(b)["ball_b"]
    source = b["ball_a"] * torch.tensor([3.0, 0.2]).view(2, 1, 1, 1)
    found = torch.tensor([True, False])
    out = to_source_level({"ball_b": rel}, source, found, prior=(-0.27, 0.43))["ball_b"]
    want = light_level(rel[:1]) * shrink_level(light_level(source[:1]), -0.27, 0.43)
    torch.testing.assert_close(light_level(out[:1]), want)
    torch.testing.assert_close(out[1], rel[1])  # not found: the relative ball as it is


def test_the_model_sets_relative_lights_at_the_shrunk_level(tmp_path):
    """Training and inference both form their conditions through RelightModel._conditions: with a prior the
    target ball sits at k x the shrunk estimate, without one at k x the estimate; absolute lights ignore it."""
    b = relative_pair(physics_pair())
    intr = {k: b[k] for k in ("albedo", "normal", "roughness", "metallic")}
    plain = tiny_relight_task(tmp_path / "plain", intensity="relative")
    prior = tiny_relight_task(tmp_path / "prior", intensity="relative", level_prior={"alpha": -0.27, "beta": 0.43})
    est, found = pf.source_balls(b["image_a"], intr, b["mask"], b["ball_b"].shape[-1], level=True)
    assert bool(found.all())
    k = light_level(b["ball_b"])
    _, _, balls_plain = plain._conditions(b, intr, torch.device("cpu"))
    _, _, balls_prior = prior._conditions(b, intr, torch.device("cpu"))
    torch.testing.assert_close(light_level(balls_plain["ball_b"]), k * light_level(est))
    torch.testing.assert_close(light_level(balls_prior["ball_b"]), k * shrink_level(light_level(est), -0.27, 0.43))
    _, _, absolute = prior._conditions(physics_pair(), intr, torch.device("cpu"), intensity="absolute")
    torch.testing.assert_close(absolute["ball_b"], physics_pair()["ball_b"])


def test_the_prior_is_checked_and_named():
    ok = RelightParams.model_validate({**TINY, "level_prior": {"alpha": -0.27, "beta": 0.43}})
    assert ok.level_prior.alpha == -0.27
    assert RelightParams.model_validate(TINY).level_prior is None
    for bad in ({"alpha": -0.27, "beta": 0.0}, {"alpha": 9.0, "beta": 0.5}, {"alpha": 0.0}):
        with pytest.raises(ValidationError, match="level_prior"):
            RelightParams.model_validate({**TINY, "level_prior": bad})


def test_a_fine_tune_must_keep_its_bases_prior():
    """init: base refuses params whose prior differs from the base's (its gains were learnt at that level);
    a base saved before the key existed has none."""
    plain = RelightParams.model_validate(TINY).model_dump(mode="json")
    older = {k: v for k, v in plain.items() if k != "level_prior"}
    with_prior = RelightParams.model_validate({**TINY, "level_prior": {"alpha": -0.27, "beta": 0.43}})
    assert mismatches("relight", plain, older) == []
    wrong = mismatches("relight", with_prior.model_dump(mode="json"), older)
    assert len(wrong) == 1 and wrong[0].startswith("relight.level_prior: the base has None")

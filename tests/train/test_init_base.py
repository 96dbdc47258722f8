"""`unet.init: base`: training starts from a pilight-base folder's weights, and a base that does not fit
the params is refused naming the key (pilight/base_model.py). `scratch` and `pretrained` are tested in
tests/diffusion/test_diffusion_unet.py and tests/train/test_intrinsics_stage.py."""

from __future__ import annotations

import json

import pytest
import torch
import yaml
from safetensors.torch import load_file

from fixtures.stage_scripts import TINY_NETWORK, params_file, run_stage, tiny_shards, training_outputs
from pilight.base_model import BaseModelError, init_from_base
from pilight.models.folder import save_model, trainable_state
from pilight.params import IntrinsicsParams
from pilight.train.intrinsics import IntrinsicsTask


def _params(**unet) -> IntrinsicsParams:
    return IntrinsicsParams.model_validate({**TINY_NETWORK, "unet": {**TINY_NETWORK["unet"], **unet}})


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """A tiny base saved as the export stage saves the real one (float16), from its own seed."""
    folder = tmp_path_factory.mktemp("base")
    torch.manual_seed(7)
    p = _params(init="scratch")
    task = IntrinsicsTask(p, folder, seed=0)
    save_model(task.stack, folder / "intrinsics", p.model_dump(mode="json"), dtype=torch.float16)
    return folder, {k: v.clone() for k, v in trainable_state(task.stack.model).items()}


def test_init_base_loads_the_base_weights(base, tmp_path):
    folder, saved = base
    torch.manual_seed(8)  # another random init, which the base must replace entirely
    p = _params(init="base", path=str(folder))
    task = IntrinsicsTask(p, tmp_path, seed=0)
    before = trainable_state(task.stack.model)
    assert any(not torch.equal(before[k], saved[k]) for k in saved)
    assert init_from_base(task.stack, p, "intrinsics") == folder / "intrinsics"
    after = trainable_state(task.stack.model)
    for k, v in saved.items():  # stored in float16: equal to the saved weights at half precision
        torch.testing.assert_close(after[k], v.half().float(), rtol=0, atol=0)


def test_a_base_with_another_network_is_refused_naming_the_key(base, tmp_path):
    folder, _ = base
    p = _params(init="base", path=str(folder), attention_head_dim=16)
    task = IntrinsicsTask(p, tmp_path, seed=0)
    with pytest.raises(
        BaseModelError, match=r"intrinsics\.unet\.attention_head_dim: the base has 8, the params ask for 16"
    ):
        init_from_base(task.stack, p, "intrinsics")


def test_a_missing_base_names_the_file_and_the_key(tmp_path):
    (tmp_path / "nowhere").mkdir()  # a folder that is not a base (a missing one fails params validation)
    p = _params(init="base", path=str(tmp_path / "nowhere"))
    task = IntrinsicsTask(p, tmp_path, seed=0)
    with pytest.raises(BaseModelError, match=r"intrinsics\.unet\.init is 'base' but .*nowhere/intrinsics/config\.json"):
        init_from_base(task.stack, p, "intrinsics")


def test_zero_steps_ships_the_base_as_the_stage_model(tmp_path):
    """`intrinsics.train.steps: 0` (the embedded default: the base's stage 1 unchanged): the stage saves
    the base's weights as its model, trains nothing, and still writes the metrics and previews dvc.yaml
    declares."""
    shards = tiny_shards(tmp_path / "data")
    unet = {**TINY_NETWORK["unet"], "init": "base", "path": str(tmp_path / "base")}
    section = {**TINY_NETWORK, "unet": unet, "train": {"steps": 0, "batch_size": 2, "warmup_steps": 0}}
    params = params_file(tmp_path, {"intrinsics": section})
    p = IntrinsicsParams.model_validate(
        {**yaml.safe_load(params.read_text())["intrinsics"], "unet": TINY_NETWORK["unet"]}
    )
    torch.manual_seed(7)
    stack = IntrinsicsTask(p, shards, seed=0).stack  # a base of exactly the params' network, saved as the real one
    save_model(stack, tmp_path / "base" / "intrinsics", p.model_dump(mode="json"), dtype=torch.float16)
    saved = trainable_state(stack.model)
    r = run_stage("train_intrinsics.py", "--params", params, "--shards", shards, *training_outputs(tmp_path))
    assert r.returncode == 0, r.stderr
    assert "intrinsics.train.steps is 0, so the base weights are the model, untrained" in r.stdout
    model = load_file(tmp_path / "model" / "model.safetensors")
    for k, v in saved.items():
        torch.testing.assert_close(model[k].float(), v.half().float(), rtol=0, atol=0)
    assert json.loads((tmp_path / "live" / "metrics.json").read_text())["steps"] == 0
    assert (tmp_path / "live" / "plots" / "images" / "intrinsics_grid.png").is_file()
    assert (tmp_path / "live" / "plots" / "metrics" / "loss.tsv").is_file()

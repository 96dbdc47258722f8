"""Stage 1 (intrinsics): the task's loss and prediction, and the train / infer / evaluate scripts."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from fixtures.stage_scripts import TINY_NETWORK, params_file, run_stage, tiny_shards, training_outputs
from pilight.data.shard_reader import intrinsics_dataset, make_loader
from pilight.models.intrinsics import targets_to_maps
from pilight.params import DOMAINS, IntrinsicsParams, SamplingParams
from pilight.train.intrinsics import IntrinsicsTask, decoded_maps, domain_targets, latent_mask, masked_latent_mse
from pilight.train.map_losses import angular_loss

TINY = {
    **TINY_NETWORK,
    "train": {"steps": 4, "batch_size": 2, "checkpoint_every": 2, "image_every": 2, "log_every": 1, "warmup_steps": 0},
}


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    return tiny_shards(tmp_path_factory.mktemp("s1"))


def _batch(shards, n=2):
    return next(iter(make_loader(intrinsics_dataset(shards, "train", shuffle=False), n)))


def test_masked_latent_loss_is_zero_on_an_empty_mask():
    v, t = torch.randn(4, 12, 4, 4), torch.randn(4, 12, 4, 4)
    assert masked_latent_mse(v, t, torch.zeros(4, 1, 4, 4)) == 0
    full = masked_latent_mse(v, t, torch.ones(4, 1, 4, 4))
    assert torch.isclose(full, torch.nn.functional.mse_loss(v, t))


def test_latent_mask_keeps_majority_cells():
    m = torch.zeros(1, 1, 8, 8)
    m[..., :4, :] = 1
    m[..., 4, 0] = 1  # a stray pixel does not make its cell reliable
    z = latent_mask(m, 4)
    assert z.shape == (1, 1, 2, 2) and z[0, 0].tolist() == [[1.0, 1.0], [0.0, 0.0]]


@pytest.mark.parametrize("space", ["linear", "srgb"])
def test_targets_round_trip(shards, space):
    b = _batch(shards)
    back = targets_to_maps(domain_targets(b, DOMAINS, space), DOMAINS, space)
    for d in ("albedo", "roughness", "metallic"):
        torch.testing.assert_close(back[d], b[d], atol=1e-5, rtol=0)
    m = b["mask"] > 0.5
    cos = (back["normal"] * b["normal"]).sum(1, keepdim=True)
    assert (cos[m] > 0.999).all()


def test_inference_reads_the_normal_the_angular_loss_trains():
    """The task loss scores the direction of the raw output (decoded_maps leaves it unclamped, the angular
    loss normalises it), so inference must read that direction: a component beyond 1 must not be clamped
    first. The shipped base outputs such normals; clamping them tilted its test normals by ~12 degrees."""
    raw = torch.zeros(1, len(DOMAINS), 3, 2, 2)
    i = DOMAINS.index("normal")
    raw[:, i, 1], raw[:, i, 2] = 2.5, 0.9  # a floor's normal, (0, 0.94, 0.34) once normalised, at a large scale
    raw[:, i, 0, 0, 0] = -3.0  # and one leaning far left
    decoded = decoded_maps(raw, DOMAINS, "linear")["normal"]
    gt = torch.nn.functional.normalize(decoded, dim=1)
    predicted = targets_to_maps(raw, DOMAINS, "linear")["normal"]
    assert float(angular_loss(predicted, gt, torch.ones(1, 1, 2, 2))) < 0.01  # radians; the clamp gave 0.3
    torch.testing.assert_close(predicted, gt)


@pytest.mark.parametrize("t_fixed", [0, 999, None])
def test_loss_finite_at_both_ends_of_the_schedule(shards, t_fixed, monkeypatch):
    task = IntrinsicsTask(IntrinsicsParams.model_validate(TINY), shards, seed=0)
    if t_fixed is not None:
        monkeypatch.setattr(torch, "randint", lambda lo, hi, size, generator=None: torch.full(size, t_fixed))
    loss, logs = task.loss(_batch(shards), torch.Generator().manual_seed(0))
    assert torch.isfinite(loss) and loss > 0
    loss.backward()
    assert all(torch.isfinite(p.grad).all() for p in task.trainable().parameters() if p.grad is not None)


def test_bf16_autocast_loss_is_finite(shards):
    task = IntrinsicsTask(IntrinsicsParams.model_validate(TINY), shards, seed=0)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        loss, _ = task.loss(_batch(shards), torch.Generator().manual_seed(0))
    assert torch.isfinite(loss)


@pytest.mark.parametrize("layout", ["joint", "domains"])
def test_grad_shares_of_the_maps_are_logged_and_change_nothing(shards, layout):
    """train.grad_share_every with objective: task: each map's share of the gradient norm is logged every
    N calls, the shares sum to 1, and the loss and its gradient are those of a run without it."""
    params = {**TINY, "objective": "task", "layout": layout}
    params["schedule"] = {"rescale_zero_snr": True, "terminal_input": "zero"}
    runs = {}
    for every in (0, 2):
        p = IntrinsicsParams.model_validate({**params, "train": {**TINY["train"], "grad_share_every": every}})
        torch.manual_seed(0)
        task = IntrinsicsTask(p, shards, seed=0)
        logs = [task.loss(_batch(shards), torch.Generator().manual_seed(0))[1] for _ in range(2)]
        loss, last = task.loss(_batch(shards), torch.Generator().manual_seed(0))
        loss.backward()
        runs[every] = (loss.detach(), [p.grad.clone() for p in task.trainable().parameters()], logs + [last])
    assert all(not any(k.startswith("grad_share") for k in log) for log in runs[0][2])
    first, second, third = runs[2][2]
    assert not any(k.startswith("grad_share") for k in first) and not any(k.startswith("grad_share") for k in third)
    shares = {k: v for k, v in second.items() if k.startswith("grad_share_")}
    assert set(shares) == {f"grad_share_{d}" for d in DOMAINS}
    assert sum(shares.values()) == pytest.approx(1.0) and all(v > 0 for v in shares.values())
    assert torch.equal(runs[0][0], runs[2][0])
    assert all(torch.equal(a, b) for a, b in zip(runs[0][1], runs[2][1], strict=True))


def test_predict_a_subset_of_domains(shards):
    task = IntrinsicsTask(IntrinsicsParams.model_validate(TINY), shards, seed=0)
    b = _batch(shards)
    sp = SamplingParams(steps=2)
    full = task.predict(b["image"], DOMAINS, sp, torch.Generator().manual_seed(1))
    sub = task.predict(b["image"], ("albedo", "normal"), sp, torch.Generator().manual_seed(1))
    assert set(full) == set(DOMAINS) and set(sub) == {"albedo", "normal"}
    assert full["roughness"].shape == (2, 1, 16, 16) and full["albedo"].shape == (2, 3, 16, 16)
    assert (full["albedo"] >= 0).all() and (full["albedo"] <= 1).all()
    torch.testing.assert_close(full["normal"].norm(dim=1), torch.ones(2, 16, 16), atol=1e-4, rtol=0)
    assert task.stack.model.items_per_sample == 4, "a subset call leaves the model's view count as it was"


def _params(tmp_path, **intrinsics) -> Path:
    return params_file(
        tmp_path, {"intrinsics": {**TINY, **intrinsics}, "infer_intrinsics": {"steps": 2, "splits": ["train", "test"]}}
    )


_run = run_stage


@pytest.mark.slow
def test_train_infer_evaluate_scripts(shards, tmp_path):
    params = _params(tmp_path)
    r = _run(
        "train_intrinsics.py",
        "--params",
        params,
        "--shards",
        shards,
        *training_outputs(tmp_path),
    )
    assert r.returncode == 0, r.stderr
    assert json.loads((tmp_path / "live" / "metrics.json").read_text())["steps"] == 4
    assert (tmp_path / "live" / "plots" / "images" / "intrinsics_grid.png").is_file()
    r = _run(
        "infer_intrinsics.py",
        "--params",
        params,
        "--shards",
        shards,
        "--model",
        tmp_path / "model",
        "--out",
        tmp_path / "pred",
        "--metrics",
        tmp_path / "infer.json",
    )
    assert r.returncode == 0, r.stderr
    index = json.loads((tmp_path / "pred" / "index.json").read_text())
    assert index["splits"]["train"]["samples"] == 9 and index["parts"]["conditioning"] == "learned-embedding"
    r = _run(
        "evaluate.py",
        "--params",
        params,
        "--shards",
        shards,
        "--pred",
        tmp_path / "pred",
        "--metrics",
        tmp_path / "eval.json",
        "--reports",
        tmp_path / "reports",
    )
    assert r.returncode == 0, r.stderr
    result = json.loads((tmp_path / "eval.json").read_text())["intrinsics"]
    assert set(result["model"]) >= {"albedo_psnr", "normal_mean_deg", "roughness_mae", "metallic_mae"}
    assert "| albedo PSNR" in (tmp_path / "reports" / "intrinsics.md").read_text()


@pytest.mark.slow
@pytest.mark.parametrize("script", ["train_intrinsics.py", "train_relight.py"])
def test_two_training_runs_give_the_same_bytes(shards, tmp_path, script):
    """Same seed, same data: same weights, in two fresh processes (DVC must never see a retrain
    change its output). The model is initialised from the global RNG, so it must be seeded first."""
    params = params_file(tmp_path, {"intrinsics": TINY, "relight": {**TINY, "conditions": "gt"}})
    for run in ("a", "b"):
        r = _run(
            script,
            "--params",
            params,
            "--shards",
            shards,
            *training_outputs(tmp_path / run),
        )
        assert r.returncode == 0, r.stderr
    weights = [(tmp_path / run / "model" / "model.safetensors").read_bytes() for run in ("a", "b")]
    assert weights[0] == weights[1]


@pytest.mark.parametrize(
    "change, needle, code",
    [
        ({"unet": {"init": "pretrained", "path": "/no/such/unet"}}, "unet.path '/no/such/unet' does not exist", 2),
        ({"codec": {"kind": "vae", "path": None}}, "codec.path is not set", 2),
        ({"codec": {"kind": "pixel", "factor": 3}}, "not divisible by the codec factor 3", 1),
    ],
)
def test_bad_model_input_fails_before_training(shards, tmp_path, change, needle, code):
    r = _run(
        "train_intrinsics.py",
        "--params",
        _params(tmp_path, **change),
        "--shards",
        shards,
        *training_outputs(tmp_path),
    )
    assert r.returncode == code and needle in r.stderr, r.stderr
    assert not (tmp_path / "ckpt").exists()


def test_empty_shard_list_is_an_error(tmp_path):
    (tmp_path / "shards").mkdir()
    (tmp_path / "shards" / "index.json").write_text(
        json.dumps({"splits": {"train": {"shards": [], "samples": 0}}, "sizes": {}})
    )
    r = _run(
        "train_intrinsics.py",
        "--params",
        _params(tmp_path),
        "--shards",
        tmp_path / "shards",
        *training_outputs(tmp_path),
    )
    assert r.returncode == 1 and "train split has no shards" in r.stderr, r.stderr

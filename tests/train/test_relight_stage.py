"""Stage 2 (relighting): the task's loss and prediction, and the train / relight / evaluate scripts."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from fixtures.stage_scripts import TINY_NETWORK, params_file, run_stage, tiny_shards, training_outputs
from pilight.data.predictions import write_predictions
from pilight.data.schema import DataError
from pilight.data.shard_reader import intrinsics_dataset, make_loader, relight_dataset
from pilight.params import DOMAINS, RelightParams, SamplingParams
from pilight.relight.branches import encode_conditions
from pilight.relight.conditions import choose_intrinsics
from pilight.relight.encoding import tonemap
from pilight.relight.physics_terms import physics_terms
from pilight.train.relight import RelightTask

TINY = {
    **TINY_NETWORK,
    "conditions": "gt",
    "train": {"steps": 3, "batch_size": 2, "checkpoint_every": 3, "image_every": 3, "log_every": 1, "warmup_steps": 0},
}


def _p(**kw) -> RelightParams:
    return RelightParams.model_validate({**TINY, **kw})


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    return tiny_shards(tmp_path_factory.mktemp("s2"))


@pytest.fixture(scope="module")
def preds(shards, tmp_path_factory):
    """Fake stage-1 predictions of every train/test image: ground truth, with albedo halved."""
    out = tmp_path_factory.mktemp("pred") / "pred"

    def items(split):
        for b in make_loader(intrinsics_dataset(shards, split, shuffle=False), 4):
            for i, key in enumerate(b["key"]):
                maps = {d: b[d][i].numpy().transpose(1, 2, 0) for d in DOMAINS}
                maps["albedo"] = maps["albedo"] * 0.5
                yield key, maps, b["meta"][i]

    write_predictions(out, {s: items(s) for s in ("train", "test")}, {"domains": list(DOMAINS)})
    return out


def _batch(shards, n=2):
    return next(iter(make_loader(relight_dataset(shards, "train", shuffle=False), n)))


def _fixed_t(monkeypatch, value):
    """Every training timestep of RelightTask.loss is ``value`` (its one call of sample_timesteps)."""
    import pilight.train.relight as task_module

    monkeypatch.setattr(task_module, "sample_timesteps", lambda n, T, frac, generator=None: torch.full((n,), value))


@pytest.mark.parametrize("t_fixed", [0, 999])
def test_loss_finite_at_both_ends_with_all_lambdas(shards, t_fixed, monkeypatch):
    task = RelightTask(_p(lambda_ds=1.0, lambda_ps=1.0, lambda_rec=1.0), shards, seed=0)
    _fixed_t(monkeypatch, t_fixed)
    loss, logs = task.loss(_batch(shards), torch.Generator().manual_seed(0))
    assert logs["t_mean"] == t_fixed
    assert torch.isfinite(loss) and loss > 0
    assert {"l_vpred", "l_ds", "l_ps", "l_rec", "l_physics"} <= set(logs)
    loss.backward()
    grads = [p.grad for p in task.trainable().parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)


def test_physics_terms_reach_the_unet_through_the_decoded_x0(shards, monkeypatch):
    _fixed_t(monkeypatch, 3)  # small t: the 1/t weight makes the physics part visible
    b = _batch(shards)
    on = RelightTask(_p(), shards, seed=0)
    off = RelightTask(_p(lambda_ds=0, lambda_ps=0, lambda_rec=0), shards, seed=0)
    off.stack.model.load_state_dict(on.stack.model.state_dict())
    l_on, logs_on = on.loss(b, torch.Generator().manual_seed(0))
    l_off, logs_off = off.loss(b, torch.Generator().manual_seed(0))
    assert logs_on["t_mean"] == logs_off["t_mean"] == 3
    assert logs_on["l_vpred"] == pytest.approx(logs_off["l_vpred"])
    assert l_on > l_off and logs_on["l_physics"] > 0 and logs_off["l_physics"] == 0
    # Same weights, same draws, the same L_vpred: what the two gradients differ by is the physics part's own.
    l_on.backward()
    l_off.backward()
    own = [
        (a.grad - (b.grad if b.grad is not None else 0)).abs().sum()
        for a, b in zip(on.trainable().parameters(), off.trainable().parameters())
        if a.grad is not None
    ]
    assert own and sum(own) > 0


def test_tonemapped_physics_stays_bounded_where_linear_explodes():
    torch.manual_seed(0)
    y = torch.randn(2, 3, 3, 8, 8) * 2  # decoded x0 at high noise: far outside [-1, 1]
    y.requires_grad_(True)
    kw = dict(
        albedo=torch.rand(2, 3, 8, 8),
        d_calc=torch.rand(2, 3, 8, 8),
        mask=torch.ones(2, 1, 8, 8),
        image_a=torch.rand(2, 3, 8, 8),
        extractor=torch.nn.Identity(),
    )
    tm = physics_terms(y, space="tonemapped", **kw)
    lin = physics_terms(y, space="linear", **kw)
    assert all(((v >= 0) & (v <= 4)).all() for v in tm.values())  # values in [-1, 1]: MSE <= 4
    assert lin["ps"].max() > 100 * tm["ps"].max()
    sum(v.sum() for v in tm.values()).backward()
    assert torch.isfinite(y.grad).all()
    zero = torch.full((1, 3, 4, 4), -1.0, requires_grad=True)  # black: the tone map's 1/2.2 power at 0
    tonemap(zero.clamp(-1, 1) + 1).sum().backward()
    assert torch.isfinite(zero.grad).all()


def test_conditions_are_padded_to_one_width(shards):
    task = RelightTask(_p(), shards, seed=0)
    b = _batch(shards)
    lc = task.stack.codec.latent_channels
    from pilight.relight.branches import condition_images

    z = encode_conditions(task.stack.codec, condition_images(b["image_a"], b, b["ball_b"], b["mask"]), task.layout, 5)
    assert z.shape == (2 * 3, 5 * lc, 4, 4)
    assert (z[0, 2 * lc :] == 0).all() and (z[1, 3 * lc :] == 0).all() and (z[2, 4 * lc :] != 0).any()


def test_d_calc_condition_adds_the_lookup_of_the_conditioning_normals(shards):
    from pilight.data import schema
    from pilight.physics.calculated import diffuse_calculated
    from pilight.relight.branches import condition_images

    task = RelightTask(_p(d_calc_condition=["relit", "diffuse"]), shards, seed=0)
    assert task.layout == {
        "relit": ("image", "albedo", "d_calc"),
        "diffuse": ("normal", "ball", "mask", "d_calc"),
        "specular": ("normal", "ball", "metallic", "roughness", "mask"),
    }
    assert task.width == 5
    b = _batch(shards)
    intr = {d: b[d] for d in DOMAINS}
    intr["normal"] = -b["normal"]  # conditioning normals, not the ground truth, drive the lookup
    maps = condition_images(b["image_a"], intr, b["ball_b"], b["mask"], with_d_calc=True)
    want = schema.to_model("image", diffuse_calculated(b["ball_b"], -b["normal"], b["mask"], b["metallic"]))
    torch.testing.assert_close(maps["d_calc"], want)
    assert not torch.allclose(
        want, schema.to_model("image", diffuse_calculated(b["ball_b"], b["normal"], b["mask"], b["metallic"]))
    )
    lc = task.stack.codec.latent_channels
    z = encode_conditions(task.stack.codec, maps, task.layout, task.width).unflatten(0, (2, 3))
    d_lat = task.stack.codec.encode(want)
    torch.testing.assert_close(z[:, 0, 2 * lc : 3 * lc], d_lat)  # relit: image, albedo, d_calc
    torch.testing.assert_close(z[:, 1, 3 * lc : 4 * lc], d_lat)  # diffuse: normal, ball, mask, d_calc
    loss, _ = task.loss(b, torch.Generator().manual_seed(0))
    assert torch.isfinite(loss)
    out = task.predict(b, SamplingParams(mode="single_step"), torch.Generator().manual_seed(0))
    assert out["relit"].shape == (2, 3, 16, 16)
    with pytest.warns(UserWarning):
        ablation = RelightTask(_p(decomposition=False, d_calc_condition=["diffuse"]), shards, seed=0)
    assert ablation.layout["relit"][-1] == "d_calc" and ablation.width == 8
    with pytest.raises(ValueError, match="twice"):
        _p(d_calc_condition=["relit", "relit"])


def test_decomposition_false_is_one_branch(shards):
    with pytest.warns(UserWarning, match="L_DS and L_PS are undefined"):
        task = RelightTask(_p(decomposition=False), shards, seed=0)
    assert task.V == 1 and task.branches == ("relit",)
    loss, logs = task.loss(_batch(shards), torch.Generator().manual_seed(0))
    assert torch.isfinite(loss) and logs["l_ds"] == 0 and logs["l_ps"] == 0 and logs["ds_ps_defined"] == 0
    loss.backward()
    out = task.predict(_batch(shards), SamplingParams(steps=1, cfg_scale=1.5), torch.Generator().manual_seed(0))
    assert set(out) == {"relit"} and out["relit"].shape == (2, 3, 16, 16)


@pytest.mark.parametrize("conditions", ["pred", "mix"])
def test_conditions_needing_predictions_fail_clearly_without_them(shards, tmp_path, conditions):
    with pytest.raises(DataError, match=f"relight.conditions is '{conditions}'.*infer_intrinsics"):
        RelightTask(_p(conditions=conditions), shards, seed=0, pred_dir=tmp_path / "none")


def test_predicted_conditions_replace_ground_truth(shards, preds):
    task = RelightTask(_p(conditions="pred"), shards, seed=0, pred_dir=preds)
    b = _batch(shards)
    intr = choose_intrinsics(b, torch.tensor([True, False]), task.preds)
    torch.testing.assert_close(intr["albedo"][0], b["albedo"][0] * 0.5, atol=2e-3, rtol=1e-2)
    assert torch.equal(intr["albedo"][1], b["albedo"][1])
    loss, logs = task.loss(b, torch.Generator().manual_seed(0))
    assert torch.isfinite(loss) and logs["pred_conditions"] == 1.0


def test_bf16_autocast_loss_is_finite(shards):
    task = RelightTask(_p(), shards, seed=0)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        loss, _ = task.loss(_batch(shards), torch.Generator().manual_seed(0))
    assert torch.isfinite(loss)
    loss.backward()


def _params(tmp_path, **relight) -> Path:
    return params_file(tmp_path, {"relight": {**TINY, **relight}, "relight_infer": {"steps": 2, "batch_size": 4}})


_run = run_stage


@pytest.mark.slow
def test_train_relight_evaluate_scripts(shards, preds, tmp_path):
    params = _params(tmp_path, conditions="mix")
    r = _run(
        "train_relight.py",
        "--params",
        params,
        "--shards",
        shards,
        "--pred",
        preds,
        *training_outputs(tmp_path),
    )
    assert r.returncode == 0, r.stderr
    live = json.loads((tmp_path / "live" / "metrics.json").read_text())
    assert live["steps"] == 3 and {"l_vpred", "l_ds", "l_ps", "l_rec"} <= set(live)
    assert (tmp_path / "live" / "plots" / "images" / "relight_grid.png").is_file()
    assert json.loads((tmp_path / "model" / "task.json").read_text())["rec_features"] == "pooled-rgb-8x8"
    relit = shards.parent / "relit"  # evaluate's default: beside the shards
    outs = []
    for _ in range(2):
        r = _run(
            "relight.py",
            "--params",
            params,
            "--shards",
            shards,
            "--pred",
            preds,
            "--model",
            tmp_path / "model",
            "--out",
            relit,
            "--metrics",
            tmp_path / "relight.json",
        )
        assert r.returncode == 0, r.stderr
        outs.append(sorted((p.name, p.read_bytes()) for p in relit.rglob("*") if p.is_file()))
    assert outs[0] == outs[1], "relit output must be byte-deterministic"
    index = json.loads((relit / "index.json").read_text())
    assert index["conditions"] == "pred" and index["splits"]["test"]["samples"] == 8
    timing = json.loads((tmp_path / "relight.json").read_text())
    flip = timing["flip_check_d_pred"]
    assert flip["pairs"] == 8 and "seconds_per_pair" in timing
    r = _run(
        "evaluate.py",
        "--params",
        params,
        "--shards",
        shards,
        "--pred",
        preds,
        "--metrics",
        tmp_path / "eval.json",
        "--reports",
        tmp_path / "reports",
    )
    assert r.returncode == 0, r.stderr
    res = json.loads((tmp_path / "eval.json").read_text())
    assert "model" in res["intrinsics"]
    rel = res["relight"]
    for tier in ("absolute", "relative", "scale_invariant"):  # every tier, with the model and its anchor
        assert {"model", "model_gt", "anchor", "copy_input"} <= set(rel[tier]) and rel[tier]["model"]["psnr"] > 0
    assert "exposure_matched_copy" in rel["relative"]
    assert rel["absolute"]["copy_input"]["reconstruction_psnr"] == 100.0  # identical images: the documented cap
    assert all(v == v for v in rel["components_psnr"].values())  # no NaN
    report = (tmp_path / "reports" / "relight.md").read_text()
    assert "| copy the input" in report and "evaluate.lpips_backbone" in report  # notes go to the report
    assert rel["residual_abs_mean"]["ground_truth"] < 0.05
    # physics_first (the repo's default): the identity on the mask, and the light-following measures
    splits = {"test", "test_gt", "test_abs", "test_gt_abs", "test_anchor", "test_anchor_abs", "probes"}
    assert index["parts"]["form"]["kind"] == "physics_first" and splits <= set(index["splits"])
    assert timing["identity_residual_relative"] < 1e-6  # float32 outputs, before the float16 EXRs
    assert rel["identity_residual_relative"] < 2e-3  # from the float16 EXRs
    lf = rel["light_following"]
    assert lf["probes"] == index["splits"]["probes"]["samples"] // 4 and lf["probes"] > 0
    assert 0.0 <= lf["direction"] <= 1.0 and lf["linearity"] == pytest.approx(2.0, rel=1e-2)
    assert "Light-following of the model" in report
    headline = json.loads((tmp_path / "headline_eval.json").read_text())
    assert {"albedo_db", "normal_deg", "abs_db", "rel_r2", "si_base_db"} <= set(headline)


def test_missing_model_is_a_clear_error(shards, tmp_path):
    r = _run(
        "relight.py",
        "--params",
        _params(tmp_path),
        "--shards",
        shards,
        "--pred",
        tmp_path / "nopred",
        "--model",
        tmp_path / "nomodel",
        "--out",
        tmp_path / "relit",
        "--metrics",
        tmp_path / "m.json",
    )
    assert r.returncode == 1 and "trained model not found" in r.stderr, r.stderr


def test_a_model_run_with_another_level_prior_is_refused(shards, tmp_path):
    """The relight stage builds the model from the params: run without the prior it was trained with, a model
    would relight at another level without a word. The stage refuses, names the key, and writes nothing."""
    from pilight.models.folder import save_model
    from pilight.params import load_section

    (tmp_path / "plain").mkdir()
    (tmp_path / "prior").mkdir()
    plain = _params(tmp_path / "plain", level_prior=None)
    with_prior = _params(tmp_path / "prior", level_prior={"alpha": -0.27, "beta": 0.43})
    p = load_section("relight", with_prior)
    torch.manual_seed(0)
    save_model(RelightTask(p, shards, seed=0).stack, tmp_path / "model", p.model_dump(mode="json"))
    args = ["--shards", shards, "--pred", tmp_path / "nopred", "--model", tmp_path / "model"]
    outs = ["--out", tmp_path / "relit", "--metrics", tmp_path / "m.json"]
    r = _run("relight.py", "--params", plain, *args, *outs)
    assert r.returncode == 1, r.stderr
    assert "relight.level_prior: " in r.stderr and "has {'alpha': -0.27, 'beta': 0.43}" in r.stderr, r.stderr
    assert not (tmp_path / "relit").exists() and not (tmp_path / "m.json").exists()
    r = _run("relight.py", "--params", with_prior, *args, *outs)
    assert r.returncode == 0, r.stderr


def test_train_without_predictions_is_a_clear_error(shards, tmp_path):
    r = _run(
        "train_relight.py",
        "--params",
        _params(tmp_path, conditions="mix"),
        "--shards",
        shards,
        "--pred",
        tmp_path / "nopred",
        *training_outputs(tmp_path),
    )
    assert r.returncode == 1 and "needs stage-1 predictions" in r.stderr, r.stderr
    assert not (tmp_path / "ckpt").exists()


def test_empty_shard_list_is_an_error(tmp_path):
    (tmp_path / "shards").mkdir()
    (tmp_path / "shards" / "index.json").write_text(
        json.dumps({"splits": {"train": {"shards": [], "samples": 0}}, "sizes": {}})
    )
    r = _run(
        "train_relight.py",
        "--params",
        _params(tmp_path),
        "--shards",
        tmp_path / "shards",
        *training_outputs(tmp_path),
    )
    assert r.returncode == 1 and "train split has no shards" in r.stderr, r.stderr


@pytest.mark.parametrize(
    "target,resolution",
    [("image", "full"), ("residual", "full"), ("gain", "full"), ("residual", "cell"), ("gain", "cell")],
)
def test_residual_target_makes_the_zero_prediction_copy_the_input(shards, monkeypatch, target, resolution):
    """form.target residual or gain: x0 = 0 decodes to the input image on the relit branch, and D, S are untouched."""
    from pilight.data import schema

    task = RelightTask(
        _p(form={"kind": "free", "target": target, "resolution": resolution}, schedule={"rescale_zero_snr": True}),
        shards,
        seed=0,
    )  # x_T is pure noise
    monkeypatch.setattr(task.stack.model, "forward", lambda x, *a, **k: torch.zeros_like(x))  # v = 0 -> x0 = -v = 0
    b = _batch(shards)
    out = task.predict(b, SamplingParams(mode="single_step", cfg_scale=1.5), torch.Generator().manual_seed(0))
    zero = schema.from_model("image", torch.zeros(1))
    copy = schema.from_model("image", schema.to_model("image", b["image_a"])).clamp(0, schema.HDR_MAX)
    if target != "image":
        torch.testing.assert_close(out["relit"], copy, rtol=1e-4, atol=1e-5)
    else:
        assert torch.allclose(out["relit"], zero.expand_as(out["relit"]))
    assert torch.allclose(out["diffuse"], zero.expand_as(out["diffuse"]))
    monkeypatch.undo()
    loss, _ = task.loss(_batch(shards), torch.Generator().manual_seed(0))
    loss.backward()
    assert torch.isfinite(loss)


@pytest.mark.parametrize("target", ["residual", "gain"])
def test_cell_resolution_ignores_everything_inside_a_cell(shards, monkeypatch, target):
    """form.resolution cell: a model output with zero mean in every codec cell changes nothing (the relit
    image is the input), while the same output at full resolution does; the training targets are cell-constant."""
    from pilight.data import schema
    from pilight.diffusion.codec import cell_mean

    b = _batch(shards)
    copy = schema.from_model("image", schema.to_model("image", b["image_a"])).clamp(0, schema.HDR_MAX)
    out = {}
    for resolution in ("cell", "full"):
        task = RelightTask(
            _p(form={"kind": "free", "target": target, "resolution": resolution}, schedule={"rescale_zero_snr": True}),
            shards,
            seed=0,
        )
        f = task.stack.codec.factor

        def v_zero_cell_mean(x, *a, **k):  # x0 = -v at t = T-1; in pixels: +-0.3 alternating, mean 0 per cell
            h, w = x.shape[-2] * f, x.shape[-1] * f  # noqa: B023 (called within this iteration)
            checker = 0.3 * (1 - 2 * ((torch.arange(h)[:, None] + torch.arange(w)[None]) % 2)).float()
            return -task.stack.codec.encode(checker.expand(x.shape[0], 3, h, w))  # noqa: B023 (called within this iteration)

        monkeypatch.setattr(task.stack.model, "forward", v_zero_cell_mean)
        out[resolution] = task.predict(b, SamplingParams(mode="single_step"), torch.Generator().manual_seed(0))["relit"]
        monkeypatch.undo()
        y_a, y_b = schema.to_model("image", b["image_a"]), schema.to_model("image", b["image_b"])
        change = task._relit_target(y_b, y_a) - (y_a if target == "residual" else 0)
        if resolution == "cell":
            torch.testing.assert_close(change, cell_mean(change, f))
    torch.testing.assert_close(out["cell"], copy, rtol=1e-4, atol=1e-5)
    assert (out["full"] - copy).abs().max() > 1e-2


def test_gain_round_trip_and_bounds():
    """gain_decode(gain_encode(y_b, y_a), y_a) = y_b over the whole model range, and G stays within GAIN_MAX."""
    from pilight.relight.encoding import GAIN_MAX, gain_decode, gain_encode

    g = torch.Generator().manual_seed(0)
    y_a, y_b = torch.rand(2, 4, 3, 16, 16, generator=g) * 1.999 - 1
    y_b[0, 0] = -1.0  # black targets and inputs: the bounds of G
    y_a[1, 0] = -1.0
    G = gain_encode(y_b, y_a)
    assert G.abs().max() <= GAIN_MAX + 1e-6
    torch.testing.assert_close(gain_decode(G, y_a), y_b, atol=1e-5, rtol=0)


def test_cell_resolution_needs_a_change_target():
    with pytest.raises(ValueError, match="form.resolution 'cell' .* needs form.target 'residual' or 'gain'"):
        _p(form={"kind": "free", "target": "image", "resolution": "cell"})


def test_flip_check_tells_a_shading_that_follows_n_from_one_that_does_not(shards):
    """pilight/eval/flip_check.py: D_pred = the Lambertian lookup of the conditioning normals flips sign in
    every pair with a visible side; a D_pred that ignores N flips in none."""
    from pilight.eval.flip_check import flip_check
    from pilight.physics.calculated import diffuse_calculated

    batches = list(make_loader(relight_dataset(shards, "test", shuffle=False), 4))

    class Stub:
        def __init__(self, follows_n):
            self.follows_n = follows_n

        def predict(self, batch, sp, generator, intr, intensity="absolute"):
            n = intr["normal"] if self.follows_n else batch["normal"]
            return {
                "diffuse": diffuse_calculated(batch["ball_b"], n, batch["mask"], torch.zeros_like(batch["metallic"]))
            }

    # the tiny scenes' shading is nearly symmetric (|asymmetry| <= 0.09), hence the low threshold
    follows = flip_check(Stub(True), batches, SamplingParams(), 0, visible_above=0.01)
    ignores = flip_check(Stub(False), batches, SamplingParams(), 0, visible_above=0.01)
    assert follows["pairs"] == ignores["pairs"] == 8 and follows["pairs_considered"] > 0
    assert follows["sign_flipped_fraction"] > 0.5 and follows["moved_toward_flip_fraction"] == 1.0
    assert ignores["sign_flipped_fraction"] == 0.0 and ignores["moved_toward_flip_fraction"] == 0.0

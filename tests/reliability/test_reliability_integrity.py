"""Issue 36, integrity by content: every file that decides what a model computes (weights, config.json,
pipeline.json) is covered by a manifest of hashes, and a missing manifest is an error, not a pass. The one
exception, a folder made by hand, is a named flag that is announced. Checkpoints too."""

from __future__ import annotations

import json
import os
import shutil
import stat
import struct
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from pilight.cli import main
from pilight.models.folder import CHECKSUM_FILE, MODEL_FILE, load_model, save_model
from pilight.models.stack import ModelError
from pilight.pipeline import PILightPipeline, PipelineError
from pilight.train import checkpoint as ckpt

FAST = ["--resolution", "32", "--device", "cpu"]


def _stack(seed: int = 0) -> SimpleNamespace:
    torch.manual_seed(seed)
    return SimpleNamespace(model=torch.nn.Sequential(torch.nn.Linear(3, 4)), describe=lambda: {"codec": "toy"})


def _flip_a_weight(path: Path) -> None:
    raw = bytearray(path.read_bytes())
    (n,) = struct.unpack("<Q", raw[:8])
    raw[8 + n : 8 + n + 64] = bytes(b ^ 0xFF for b in raw[8 + n : 8 + n + 64])
    path.write_bytes(bytes(raw))


# --- a saved model ------------------------------------------------------------------------------------
def test_a_model_without_its_manifest_is_refused_naming_it_and_the_flag(tmp_path):
    save_model(_stack(), tmp_path / "m", {"p": 1})
    (tmp_path / "m" / CHECKSUM_FILE).unlink()
    _flip_a_weight(tmp_path / "m" / MODEL_FILE)
    # Before: the damaged weights loaded without a word.
    with pytest.raises(ModelError, match=rf"{tmp_path / 'm' / CHECKSUM_FILE}: missing.*--trust-unverified"):
        load_model(_stack(1), tmp_path / "m")


def test_the_named_flag_loads_a_hand_made_folder_and_says_so(tmp_path):
    stack = _stack()
    save_model(stack, tmp_path / "m", {"p": 1})
    (tmp_path / "m" / CHECKSUM_FILE).unlink()
    other = _stack(1)
    with pytest.warns(UserWarning, match=rf"{tmp_path / 'm'}: no checksums.json: loading .*UNVERIFIED"):
        load_model(other, tmp_path / "m", trust_unverified=True)
    assert torch.equal(other.model[0].weight, stack.model[0].weight)


def test_the_flag_does_not_excuse_a_manifest_that_disagrees(tmp_path):
    save_model(_stack(), tmp_path / "m", {"p": 1})
    _flip_a_weight(tmp_path / "m" / MODEL_FILE)
    with pytest.raises(ModelError, match="sha256 differs"):
        load_model(_stack(), tmp_path / "m", trust_unverified=True)


def test_the_saved_config_is_covered(tmp_path):
    save_model(_stack(), tmp_path / "m", {"p": 1})
    cfg = tmp_path / "m" / "config.json"
    cfg.write_text(cfg.read_text().replace('"p": 1', '"p": 2'))
    # Before: only the weights were hashed; a config that decides the network could change unseen.
    with pytest.raises(ModelError, match=rf"{cfg}: sha256 differs from .*checksums.json"):
        load_model(_stack(), tmp_path / "m")


def test_a_manifest_that_leaves_the_config_out_is_refused(tmp_path):
    save_model(_stack(), tmp_path / "m", {"p": 1})
    sums = tmp_path / "m" / CHECKSUM_FILE
    recorded = json.loads(sums.read_text())
    del recorded["sha256"]["config.json"]  # the format before issue 36
    sums.write_text(json.dumps(recorded))
    with pytest.raises(ModelError, match=rf"{sums}: does not cover config.json"):
        load_model(_stack(), tmp_path / "m")


# --- checkpoints ----------------------------------------------------------------------------------------
def _checkpoint(folder: Path, step: int) -> Path:
    model = torch.nn.Linear(2, 2)
    opt = torch.optim.AdamW(model.parameters())
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 1.0)
    model(torch.ones(1, 2)).sum().backward()
    opt.step()
    rng = {"rank0.generator": torch.Generator().get_state()}
    return ckpt.save_checkpoint(folder, step, model=model, optimizer=opt, scheduler=sched, rng=rng, progress={}, keep=5)


def test_a_checkpoint_without_its_manifest_is_not_resumed(tmp_path):
    good = _checkpoint(tmp_path, 1)
    newest = _checkpoint(tmp_path, 2)
    (newest / ckpt.CHECKSUM_FILE).unlink()
    _flip_a_weight(newest / ckpt.MODEL_FILE)
    # Before: resumed from the damaged weights, which then reached models/ with a fresh checksum.
    path, notes = ckpt.find_resume(tmp_path)
    assert path == good
    assert any(str(newest) in n and "checksums.json missing" in n for n in notes), notes


def test_a_checkpoint_manifest_must_cover_every_file(tmp_path):
    p = _checkpoint(tmp_path, 1)
    sums = p / ckpt.CHECKSUM_FILE
    recorded = json.loads(sums.read_text())
    del recorded["sha256"][ckpt.OPTIMIZER_FILE]
    sums.write_text(json.dumps(recorded))
    assert ckpt.damage(p) == f"{ckpt.CHECKSUM_FILE} does not cover {ckpt.OPTIMIZER_FILE}"


def test_checkpoint_files_get_the_umask_mode(tmp_path):
    old = os.umask(0o022)
    try:
        p = _checkpoint(tmp_path, 1)
    finally:
        os.umask(old)
    modes = {f.name: stat.S_IMODE(f.stat().st_mode) for f in p.iterdir()}
    # Before: the safetensors files were 0600 whatever the umask.
    assert set(modes.values()) == {0o644}, modes


# --- the pipeline folder and the CLI ----------------------------------------------------------------------
@pytest.fixture(scope="module")
def saved(tiny_models, tmp_path_factory):
    """A save_pretrained folder of the tiny models (pipeline.json and its manifest included)."""
    folder = tmp_path_factory.mktemp("saved") / "pipe"
    PILightPipeline.from_pretrained(tiny_models, device="cpu", processing_resolution=32).save_pretrained(folder)
    return folder


def test_what_save_pretrained_writes_always_loads(saved):
    assert json.loads((saved / CHECKSUM_FILE).read_text())["sha256"].keys() == {
        "pipeline.json",
        "intrinsics/checksums.json",
        "relight/checksums.json",
    }
    assert PILightPipeline.from_pretrained(saved, device="cpu").config.processing_resolution == 32


@pytest.mark.parametrize("damage", ["edit pipeline.json", "drop the manifest", "drop a stage manifest"])
def test_the_pipeline_file_and_the_stage_manifests_are_covered(saved, tmp_path, damage):
    bad = tmp_path / "bad"
    shutil.copytree(saved, bad)
    if damage == "edit pipeline.json":
        cfg = json.loads((bad / "pipeline.json").read_text())
        cfg["relight_sampling"]["cfg_scale"] = 7.0  # valid, but not what was saved
        (bad / "pipeline.json").write_text(json.dumps(cfg))
        match = rf"{bad / 'pipeline.json'}: sha256 differs"
    elif damage == "drop the manifest":
        (bad / CHECKSUM_FILE).unlink()
        match = rf"{bad / CHECKSUM_FILE}: missing, so nothing vouches for pipeline.json"
    else:
        (bad / "relight" / CHECKSUM_FILE).unlink()
        match = rf"{bad / 'relight' / CHECKSUM_FILE}: missing \(listed in {bad / CHECKSUM_FILE}\)"
    with pytest.raises(PipelineError, match=match):
        PILightPipeline.from_pretrained(bad, device="cpu")


def test_a_saved_processing_resolution_is_validated(saved, tmp_path):
    bad = tmp_path / "bad"
    shutil.copytree(saved, bad)
    cfg = json.loads((bad / "pipeline.json").read_text())
    cfg["processing_resolution"] = -5
    (bad / "pipeline.json").write_text(json.dumps(cfg))
    (bad / CHECKSUM_FILE).unlink()  # a hand-made folder: trusted, still validated
    # Before: a torch traceback at the first photo.
    with (
        pytest.warns(UserWarning),
        pytest.raises(
            PipelineError, match=r"pipeline.json: .*processing_resolution = -5: .*greater than or equal to 0"
        ),
    ):
        PILightPipeline.from_pretrained(bad, device="cpu", trust_unverified=True)
    with pytest.raises(PipelineError, match=r"processing_resolution = -5"):
        PILightPipeline.from_pretrained(saved, device="cpu", processing_resolution=-5)


def test_a_saved_config_is_validated_by_the_params_models(tiny_models, tmp_path):
    bad = tmp_path / "bad"
    shutil.copytree(tiny_models, bad)
    cfg = json.loads((bad / "intrinsics" / "config.json").read_text())
    cfg["params"]["unet"]["block_out_channels"] = [0, 16]
    (bad / "intrinsics" / "config.json").write_text(json.dumps(cfg))
    (bad / "intrinsics" / CHECKSUM_FILE).unlink()
    with pytest.warns(UserWarning), pytest.raises(PipelineError, match=r"block_out_channels\.0 = 0"):
        PILightPipeline.from_pretrained(bad, device="cpu", trust_unverified=True)


def test_the_cli_refuses_a_models_folder_without_manifests(tiny_models, tmp_path, capsys, astronaut_png):
    bad = tmp_path / "models"
    shutil.copytree(tiny_models, bad)
    for stage in ("intrinsics", "relight"):
        (bad / stage / CHECKSUM_FILE).unlink()
    _flip_a_weight(bad / "intrinsics" / MODEL_FILE)
    out = tmp_path / "out"
    rc = main(["decompose", str(astronaut_png), "-o", str(out), "--models", str(bad), *FAST])
    err = capsys.readouterr().err
    # Before: exit 0 and a saturated albedo.
    assert rc == 1 and f"{bad / 'intrinsics' / CHECKSUM_FILE}: missing" in err and "--trust-unverified" in err, err
    assert not out.exists()


def test_the_cli_flag_loads_it_and_says_so(tiny_models, tmp_path, capsys, astronaut_png):
    hand = tmp_path / "models"
    shutil.copytree(tiny_models, hand)
    for stage in ("intrinsics", "relight"):
        (hand / stage / CHECKSUM_FILE).unlink()
    out = tmp_path / "out"
    rc = main(["decompose", str(astronaut_png), "-o", str(out), "--models", str(hand), "--trust-unverified", *FAST])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert err.count("pilight: warning: ") == 2 and "UNVERIFIED" in err, err
    assert (out / "astronaut" / "albedo.exr").is_file()


def test_the_base_model_is_verified_the_same_way(saved, tmp_path):
    from pilight.base_model import BaseModelError, init_from_base
    from pilight.params import IntrinsicsParams
    from pilight.train.intrinsics import IntrinsicsTask

    base = tmp_path / "base"
    shutil.copytree(saved, base)
    cfg = json.loads((base / "intrinsics" / "config.json").read_text())["params"]
    p = IntrinsicsParams.model_validate({**cfg, "unet": {**cfg["unet"], "init": "base", "path": str(base)}})
    task = IntrinsicsTask(p, base, seed=0)
    assert init_from_base(task.stack, p, "intrinsics") == base / "intrinsics"
    (base / "intrinsics" / CHECKSUM_FILE).unlink()
    with pytest.raises(BaseModelError, match=rf"{base / 'intrinsics' / CHECKSUM_FILE}: missing"):
        init_from_base(task.stack, p, "intrinsics")

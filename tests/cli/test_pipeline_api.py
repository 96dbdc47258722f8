"""The Python API: from_pretrained / save_pretrained round trip, output dataclasses, stage 1 once."""

from __future__ import annotations

import numpy as np
import pytest

from pilight import lights
from pilight.pipeline import MemoryLimitError, PILightPipeline, PipelineError


@pytest.fixture(scope="module")
def pipe(tiny_models):
    return PILightPipeline.from_pretrained(tiny_models, device="cpu", processing_resolution=32)


def test_round_trip_gives_the_same_output_bytes(tmp_path, pipe, astronaut, tiny_models):
    two = [lights.named("left"), lights.named("top")]
    a_dec, a_rel = pipe.decompose(astronaut), pipe.relight(astronaut, two)
    pipe.save_pretrained(tmp_path / "saved")
    assert (tmp_path / "saved" / "pipeline.json").is_file()
    again = PILightPipeline.from_pretrained(tmp_path / "saved", device="cpu")
    assert again.config == pipe.config  # pipeline.json carries the processing resolution and samplers
    b_dec, b_rel = again.decompose(astronaut), again.relight(astronaut, two)
    for k in ("albedo", "normal", "roughness", "metallic"):
        assert getattr(a_dec, k).tobytes() == getattr(b_dec, k).tobytes(), k
    for k in ("relit", "diffuse", "specular", "balls"):
        assert getattr(a_rel, k).tobytes() == getattr(b_rel, k).tobytes(), k
    for stage in ("intrinsics", "relight"):
        assert (tmp_path / "saved" / stage / "model.safetensors").read_bytes() == (
            tiny_models / stage / "model.safetensors"
        ).read_bytes()


def test_outputs_at_input_size_and_intrinsics_reused(pipe, astronaut):
    img = astronaut[:200, :300]
    d = pipe.decompose(img)
    assert d.albedo.shape == (200, 300, 3) and d.roughness.shape == (200, 300, 1) and d.processing_size == (24, 32)
    np.testing.assert_allclose(np.linalg.norm(d.normal, axis=-1), 1.0, atol=1e-4)
    out = pipe.relight(img, [lights.named(n) for n in ("left", "right", "front")], intrinsics=d)
    assert out.relit.shape == (3, 200, 300, 3) and out.diffuse.shape == out.specular.shape == out.relit.shape
    assert out.balls.shape == (3, 32, 32, 3) and [l.name for l in out.lights] == ["left", "right", "front"]
    assert out.intrinsics is d
    # Stage 1 is deterministic, so relight() without intrinsics gives the same result.
    alone = pipe.relight(img, [lights.named(n) for n in ("left", "right", "front")])
    assert alone.relit.tobytes() == out.relit.tobytes()


def test_stage1_runs_once_for_k_lights(pipe, astronaut, monkeypatch):
    calls = []
    real = pipe.intrinsics_model.predict
    monkeypatch.setattr(pipe.intrinsics_model, "predict", lambda *a, **k: calls.append(1) or real(*a, **k))
    pipe.relight(astronaut, [lights.named(n) for n in lights.NAMED])
    assert len(calls) == 1


def test_alpha_mask_zeroes_normals_off_the_mask(pipe, astronaut):
    rgba = np.concatenate([astronaut, np.zeros((512, 512, 1), np.uint8)], axis=2)
    rgba[:, 256:, 3] = 255
    d = pipe.decompose(rgba)
    assert np.all(d.normal[:, :250] == 0)
    np.testing.assert_allclose(np.linalg.norm(d.normal[:, 262:], axis=-1), 1.0, atol=1e-4)


def test_memory_guard_before_allocation(pipe):
    with pytest.raises(MemoryLimitError, match="--max-memory"):
        pipe.check_memory(100_000, 100_000, lights=6, name="huge.png")
    pipe.check_memory(512, 512, lights=6, name="small.png")  # fits the default limit


def test_missing_or_mismatched_model(tmp_path, tiny_models):
    with pytest.raises(PipelineError, match="dvc repro train_relight"):
        PILightPipeline.from_pretrained(tmp_path / "absent")
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(tiny_models, bad)
    # A config that no longer describes the weights (wider UNet) is a clear error, not a crash.
    import json

    cfg = json.loads((bad / "relight" / "config.json").read_text())
    cfg["params"]["unet"]["block_out_channels"] = [16, 32]
    (bad / "relight" / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(PipelineError, match="relight"):
        PILightPipeline.from_pretrained(bad, device="cpu")


def _mean_y(rgb: np.ndarray) -> float:
    return float((rgb @ np.array([0.2126, 0.7152, 0.0722], np.float32)).mean())


def test_exposure_photo_keeps_k_times_the_photos_mean_luminance(pipe, astronaut):
    """exposure="photo" (the default): at k = 1 the relit image's mean luminance is the photo's, at k = 2 twice
    it, each light scaled once so that k stays linear; exposure="light" multiplies by nothing."""
    photo = astronaut.astype(np.float32) / 255  # linear already: the comparison needs no decoding
    ls = [lights.named("left", 1.0), lights.named("right", 2.0)]
    kept = pipe.relight(photo, ls)
    raw = pipe.relight(photo, ls, exposure="light")
    np.testing.assert_array_equal(raw.exposure_gain, [1.0, 1.0])
    assert not np.allclose(kept.exposure_gain, 1.0)  # the tiny model does not keep it by itself
    for i, k in enumerate((1.0, 2.0)):
        # fitted at the processing size (32^2 here); the full-size detail transfer moves the mean by 1 %
        assert _mean_y(kept.relit[i]) == pytest.approx(k * _mean_y(photo), rel=0.02)
        np.testing.assert_allclose(kept.relit[i], raw.relit[i] * kept.exposure_gain[i], rtol=1e-4, atol=1e-6)
        np.testing.assert_allclose(kept.diffuse[i], raw.diffuse[i] * kept.exposure_gain[i], rtol=1e-4, atol=1e-6)
    with pytest.raises(PipelineError, match="exposure must be one of photo, light, got 'camera'"):
        pipe.relight(photo, ls, exposure="camera")


def test_sampling_settings_per_call_and_to(pipe, astronaut):
    """diffusers' habits: sampling settings are arguments of each call (defaults from the saved config),
    a per-call generator, and .to(device)."""
    import torch

    one = pipe.decompose(astronaut)
    assert np.array_equal(pipe.decompose(astronaut, num_inference_steps=1).albedo, one.albedo)  # the config's
    two = pipe.decompose(astronaut, num_inference_steps=2)
    assert not np.array_equal(two.albedo, one.albedo)  # DDIM with 2 steps is another prediction
    g = lambda: torch.Generator().manual_seed(7)
    a = pipe.relight(astronaut, [lights.named("left")], intrinsics=one, guidance_scale=1.0, generator=g())
    b = pipe.relight(astronaut, [lights.named("left")], intrinsics=one, guidance_scale=1.0, generator=g())
    assert a.relit.tobytes() == b.relit.tobytes()
    assert pipe.config.relight_sampling.cfg_scale != 1.0  # so guidance_scale=1.0 was this call's own
    with pytest.raises(PipelineError, match="sampling settings of this call: sampling.cfg_scale"):
        pipe.decompose(astronaut, guidance_scale=-1.0)
    assert pipe.to("cpu") is pipe and pipe.device.type == "cpu"


def test_loaded_models_hold_exactly_the_saved_weights(tiny_models):
    """Every parameter and buffer of a loaded model is the saved one (none keeps its random initial value:
    load_model loads non-strictly, so a key it skipped would pass unnoticed without this)."""
    import torch
    from safetensors.torch import load_file

    from pilight.pipeline import load_stage

    for stage in ("intrinsics", "relight"):
        model, _ = load_stage(tiny_models, stage, torch.device("cpu"))
        saved = load_file(str(tiny_models / stage / "model.safetensors"))
        state = model.stack.model.state_dict()
        assert set(state) == set(saved), (stage, sorted(set(state) ^ set(saved))[:3])
        for k, t in state.items():
            assert torch.equal(t, saved[k].to(t.dtype)), (stage, k)

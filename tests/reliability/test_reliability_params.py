"""Issue 36, validation by meaning: every params key has a type, a range and a resource bound; an empty,
null or non-mapping section is an error naming it; a file that is not UTF-8 is exit 2 naming it; the
structural keys are checked against each other. Each case below passed validation before (and then
rendered 144 class-default bundles, allocated 40 GB, or died in a modulo by zero)."""

from __future__ import annotations

import typing
from pathlib import Path

import pytest
import yaml
from pydantic import BaseModel

from fixtures.script_modules import load_stage
from pilight import params as P
from pilight.params import ParamsError, load_section

ROOT = Path(__file__).resolve().parents[2]


def _params(tmp_path: Path, **edits) -> Path:
    """The repo's params.yaml with ``a__b__c=value`` edits (value DELETE removes the key)."""
    raw = yaml.safe_load((ROOT / "params.yaml").read_text())
    for dotted, value in edits.items():
        *keys, last = dotted.split("__")
        d = raw
        for k in keys:
            d = d[k]
        d[last] = value
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


def _stage_main(script: str):
    return load_stage(script).main


# --- empty, null and non-mapping sections ------------------------------------------------------------
@pytest.mark.parametrize(
    "value, shown", [([], r"a list \(\[\]\)"), (0, r"a number \(0\)"), (None, "null"), ("x", "a string")]
)
def test_a_section_that_is_not_a_mapping_is_an_error_naming_it(tmp_path, value, shown):
    with pytest.raises(ParamsError, match=rf"section 'render' is {shown}"):
        load_section("render", _params(tmp_path, render=value))


@pytest.mark.parametrize("section", sorted(P.SECTIONS))
def test_an_empty_section_is_an_error_naming_it(tmp_path, section):
    with pytest.raises(ParamsError, match=rf"section '{section}' is empty"):
        load_section(section, _params(tmp_path, **{section: {}}))


@pytest.mark.parametrize("key", ["render__cycles", "render__light", "intrinsics__train", "evaluate__trade"])
def test_an_empty_sub_section_is_an_error_naming_it(tmp_path, key):
    with pytest.raises(ParamsError, match=rf"{key.replace('__', '.')} = {{}}: .*an empty section"):
        load_section(key.split("__")[0], _params(tmp_path, **{key: {}}))


def test_the_render_stage_refuses_a_null_section_with_exit_2_before_blender(tmp_path, capsys):
    # Before: exit 0 after 144 bundles of the class defaults (bpy is only imported in the body).
    rc = _stage_main("render")(["--params", str(_params(tmp_path, render=None)), "--out", str(tmp_path / "r")])
    err = capsys.readouterr().err
    assert rc == 2 and "section 'render' is null" in err, err
    assert not (tmp_path / "r").exists()


def test_a_params_file_that_is_not_utf8_is_exit_2_naming_it(tmp_path, capsys):
    path = tmp_path / "params.yaml"
    path.write_bytes((ROOT / "params.yaml").read_bytes().replace(b"# the paper fixes 42", b"# the paper \xe9 42", 1))
    rc = _stage_main("shard")(["--params", str(path), "--renders", str(tmp_path / "r"), "--out", str(tmp_path / "s")])
    err = capsys.readouterr().err
    # Before: a UnicodeDecodeError traceback and exit 1.
    assert rc == 2 and f"{path}: not UTF-8 text (byte 0xe9" in err and "Traceback" not in err, err


# --- ranges and resource bounds -------------------------------------------------------------------
@pytest.mark.parametrize(
    "section, edits, key",
    [
        (
            "intrinsics",
            {"intrinsics__schedule__num_train_timesteps": 10**10},
            "intrinsics.schedule.num_train_timesteps",
        ),
        ("render", {"render__scenes__train": 10**9}, "render.scenes.train"),
        ("render", {"render__views_per_scene": 10**6}, "render.views_per_scene"),
        ("render", {"render__lights_per_view": 10**6}, "render.lights_per_view"),
        ("relight", {"relight__train__batch_size": 10**6}, "relight.train.batch_size"),
        ("infer_intrinsics", {"infer_intrinsics__ensemble": 10**6}, "infer_intrinsics.ensemble"),
        ("intrinsics", {"intrinsics__train__grad_accum": 10**6}, "intrinsics.train.grad_accum"),
        ("intrinsics", {"intrinsics__train__weight_decay": 1e6}, "intrinsics.train.weight_decay"),
        ("relight", {"relight__train__checkpoint_every": 10**12}, "relight.train.checkpoint_every"),
        ("base", {"base__seed": 2**70}, "base.seed"),
        ("render", {"render__light__strength": {"lo": -5, "hi": 20}}, "render.light.strength.lo"),
        ("render", {"render__cycles__max_bounces": 10**6}, "render.cycles.max_bounces"),
        ("shard", {"shard__maxcount": 10**12}, "shard.maxcount"),
        ("shard", {"shard__maxcount": True}, "shard.maxcount"),
        ("evaluate", {"evaluate__trade__steps": [1, 10**9]}, "evaluate.trade.steps.1"),
        ("relight", {"relight__lambda_ps": 1e9}, "relight.lambda_ps"),
    ],
)
def test_runaway_values_are_refused_by_key(tmp_path, section, edits, key):
    with pytest.raises(ParamsError, match=key.replace(".", r"\.") + " ="):
        load_section(section, _params(tmp_path, **edits))


def test_the_render_size_is_estimated_before_anything_runs(tmp_path):
    # Each count within its own range; together ~370 TiB of renders (the paper's profile: 30 TiB).
    edits = {"render__scenes": {"train": 500_000, "val": 0, "test": 0}, "render__resolution": 2048}
    with pytest.raises(ParamsError, match=r"would write about \d+ TiB of renders .* over the limit of 256 TiB"):
        load_section("render", _params(tmp_path, **edits))
    p = load_section("render", ROOT / "params.yaml")
    assert p.estimated_bytes() < 2**30  # the embedded default: well under a GiB


def test_the_unet_size_is_estimated_before_anything_is_built(tmp_path):
    edits = {"relight__unet__block_out_channels": [4096, 8192, 8192], "relight__unet__layers_per_block": 4}
    with pytest.raises(ParamsError, match=r"relight\.unet = .*UNet of about [\d.]+e9 parameters .* over the limit"):
        load_section("relight", _params(tmp_path, **edits))


def test_the_unet_estimate_is_close_to_the_real_count():
    import torch

    from pilight.models.stack import build_stack

    for channels in ((64, 128, 128), (32, 32)):
        p = P.IntrinsicsParams(unet=P.UNetParams(block_out_channels=channels))
        with torch.device("meta"):
            real = sum(t.numel() for t in build_stack(p, num_domains=4).model.unet.parameters())
        assert 0.8 < p.unet.estimated_parameters() / real < 1.2, (channels, real)


# --- structural cross-checks --------------------------------------------------------------------------
@pytest.mark.parametrize(
    "unet, match",
    [
        ({"block_out_channels": [0, 32]}, r"block_out_channels\.0 = 0: Input should be greater than or equal to 1"),
        ({"block_out_channels": []}, r"block_out_channels = \[\]: .*at least 1 item"),
        (
            {"block_out_channels": [48, 96]},
            r"\[48, 96\]: every level.*divisible by 32, the GroupNorm groups .*\[48\] are not",
        ),
        ({"block_out_channels": [24, 40]}, r"divisible by 24, the GroupNorm groups .*\[40\] are not"),
        ({"block_out_channels": [16], "attention_head_dim": 32}, r"attention_head_dim 32 .* \[16\] of block_out"),
        ({"block_out_channels": [64, 96], "attention_head_dim": 64}, r"attention_head_dim 64 .*\[96\]"),
    ],
)
def test_structural_keys_are_checked_against_each_other(tmp_path, unet, match):
    # Before: [0, 32] died in a modulo by zero, [] in min(), the others in GroupNorm or attention at build time.
    edits = {f"intrinsics__unet__{k}": v for k, v in unet.items()}
    with pytest.raises(ParamsError, match=match):
        load_section("intrinsics", _params(tmp_path, **edits))


# --- the whole class: every number has a range ----------------------------------------------------------
def _bounded(metadata) -> tuple[bool, bool]:
    lower = any(hasattr(m, "ge") or hasattr(m, "gt") for m in metadata)
    upper = any(hasattr(m, "le") or hasattr(m, "lt") for m in metadata)
    return lower, upper


def _numbers(model: type[BaseModel], prefix: str, seen: set) -> list[tuple[str, object, list]]:
    out = []
    for name, field in model.model_fields.items():
        key = f"{prefix}.{name}"
        args = [a for a in typing.get_args(field.annotation) or (field.annotation,) if a is not type(None)]
        for a in args:
            if isinstance(a, type) and issubclass(a, BaseModel):
                out += _numbers(a, key, seen)
            elif a in (int, float):
                out.append((key, a, field.metadata))
            elif typing.get_origin(a) is tuple:
                item = typing.get_args(a)[0]
                if typing.get_origin(item) is typing.Annotated:
                    base, *meta = typing.get_args(item)
                    if base in (int, float):
                        out.append((f"{key}[]", base, [m for f in meta for m in getattr(f, "metadata", [f])]))
                        out.append((f"{key} length", "length", field.metadata))
                elif item in (int, float):
                    out.append((f"{key}[]", item, []))
    return out


def test_every_numeric_params_key_has_a_range():
    """Each int or float key (and each item of a list of numbers) of every section has a lower and an upper
    bound, and each list of numbers a maximum length: nothing can ask for 1e9 of anything."""
    missing = []
    for section, model in P.SECTIONS.items():
        for key, kind, meta in _numbers(model, section, set()):
            if kind == "length":
                if not any(hasattr(m, "max_length") for m in meta):
                    missing.append(f"{key}: no max_length")
                continue
            lower, upper = _bounded(meta)
            if not (lower and upper):
                missing.append(f"{key}: {'no upper bound' if not upper else 'no lower bound'}")
    assert not missing, "\n".join(missing)

"""dvc.yaml declares every params key a stage's output depends on (else DVC never reruns it)."""

from pathlib import Path

import pytest
import yaml

from pilight import params as P

ROOT = Path(__file__).resolve().parents[1]

# stage -> (params section, the section's model): every field of these changes the stage's outputs.
STAGE_SECTIONS = {
    "render": ("render", P.RenderParams),
    "train_intrinsics": ("intrinsics", P.IntrinsicsParams),
    "infer_intrinsics": ("infer_intrinsics", P.InferIntrinsicsParams),
    "train_relight": ("relight", P.RelightParams),
    "relight": ("relight_infer", P.RelightInferParams),
}


# Fields that change where or how fast a stage runs, never a byte of its outputs, so changing them must
# NOT rerun it. render.cluster: the Dask executor gives the in-process bytes (tests/render/test_render_stage.py).
NOT_OUTPUT_PARAMS = {"render.cluster"}


@pytest.mark.parametrize("stage", sorted(STAGE_SECTIONS))
def test_every_field_of_a_stages_section_is_a_declared_param(stage):
    section, model = STAGE_SECTIONS[stage]
    declared = [
        k
        for k in yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"][stage].get("params", [])
        if isinstance(k, str)
    ]
    assert not NOT_OUTPUT_PARAMS & set(declared), "a field that changes no output would rerun the stage"
    covered = lambda f: any(k in (section, f"{section}.{f}") or k.startswith(f"{section}.{f}.") for k in declared)
    missing = [
        f"{section}.{f}" for f in model.model_fields if not covered(f) and f"{section}.{f}" not in NOT_OUTPUT_PARAMS
    ]
    assert not missing, f"dvc.yaml stage {stage!r} does not declare {missing}: changing them would not rerun it"

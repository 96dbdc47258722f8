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


@pytest.mark.parametrize("stage", sorted(STAGE_SECTIONS))
def test_every_field_of_a_stages_section_is_a_declared_param(stage):
    section, model = STAGE_SECTIONS[stage]
    declared = [k for k in yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"][stage].get("params", [])
                if isinstance(k, str)]
    covered = lambda f: any(k in (section, f"{section}.{f}") or k.startswith(f"{section}.{f}.") for k in declared)
    missing = [f"{section}.{f}" for f in model.model_fields if not covered(f)]
    assert not missing, f"dvc.yaml stage {stage!r} does not declare {missing}: changing them would not rerun it"

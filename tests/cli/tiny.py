"""A tiny pair of models (random init) saved in the models/ layout, for interface tests."""

from __future__ import annotations

from pathlib import Path

from pilight.models.folder import save_model
from pilight.params import UNetParams, load_section

REPO = Path(__file__).resolve().parents[2]
# Two UNet levels of 8 and 16 channels: a forward pass at 32^2 takes milliseconds.
TINY_UNET = UNetParams(block_out_channels=(8, 16), layers_per_block=1, attention_head_dim=8, cross_attention_dim=16)


def save_tiny_models(folder: Path, seed: int = 0, unet: UNetParams | None = TINY_UNET) -> Path:
    """folder/intrinsics and folder/relight: the repo's params sections with ``unet`` (None: the
    params' own UNet, untrained: what benchmarks time)."""
    import torch

    from pilight.train.intrinsics import IntrinsicsTask
    from pilight.train.relight import RelightTask

    torch.manual_seed(seed)
    p0 = {s: load_section(s, REPO / "params.yaml") for s in ("intrinsics", "relight")}
    p1 = load_section("intrinsics", REPO / "params.yaml").model_copy(update={"unet": unet or p0["intrinsics"].unet})
    p2 = load_section("relight", REPO / "params.yaml").model_copy(
        update={"unet": unet or p0["relight"].unet, "conditions": "gt"}
    )
    t1 = IntrinsicsTask(p1, folder, seed=seed)
    t2 = RelightTask(p2, folder, seed=seed)
    save_model(t1.stack, folder / "intrinsics", p1.model_dump(mode="json"))
    save_model(t2.stack, folder / "relight", p2.model_dump(mode="json"))
    return folder

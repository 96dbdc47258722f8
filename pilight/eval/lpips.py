"""LPIPS (Zhang et al. 2018) with weights from local files only: nothing is ever downloaded.

LPIPS has two sets of weights:

- the linear 1x1 "lin" layers: bundled inside the torchmetrics package
  (``torchmetrics/functional/image/lpips_models/{alex,vgg,squeeze}.pth``). They are read here with
  ``torch.load(..., weights_only=True)`` (tensors only, no arbitrary unpickling) and loaded strictly
  (every key must match; torchmetrics itself loads them with ``strict=False`` and, before torch 2.6,
  without ``weights_only``, which is why we do not go through its loader);
- the ImageNet backbone (torchvision's ``alexnet`` / ``vgg16`` / ``squeezenet1_1`` ``.features``):
  torchmetrics would download it through torchvision. Here it comes from a LOCAL safetensors file
  (``evaluate.lpips_backbone``); no file -> LPIPS is unavailable and the caller reports it as null
  with the reason. A missing file or keys / shapes that do not match the backbone raise.

The backbone is implemented here in plain torch, layer for layer as torchvision builds it (same
module indices, so torchvision's state-dict keys load unchanged), because torchvision is not
usable in this project: the PyPI torchvision wheels for Linux are linked against CUDA torch
(``torchvision/_C.so`` needs ``libtorch_cuda.so``) and ``import torchvision`` fails with the CPU
torch wheel this project installs. The LPIPS computation itself follows torchmetrics'
``_LPIPS.forward`` exactly (scaling layer, taps after the same ReLUs, unit-normalised channel
features, squared difference, lin layer, spatial mean, sum over layers);
``tests/eval/test_lpips.py`` checks the numbers against torchmetrics' own ``_LPIPS`` fed with the
same backbone.

The backbone file (safetensors; keys either ``features.<i>.*`` from the full torchvision model's
state dict, whose other keys such as ``classifier.*`` are ignored, or ``<i>.*`` from
``model.features.state_dict()``). Make it on a machine with network access::

    pip install torch torchvision safetensors
    python -c "import torchvision; from safetensors.torch import save_file; m = torchvision.models.alexnet(weights='DEFAULT'); save_file({k: v.contiguous() for k, v in m.features.state_dict().items()}, 'lpips_alexnet_features.safetensors')"
    # then copy the file here and set evaluate.lpips_backbone: <path> (vgg: vgg16, squeeze: squeezenet1_1)
"""

from __future__ import annotations

import importlib.resources
import os
from collections.abc import Callable
from pathlib import Path

import torch
from torch import Tensor, nn

PARAM_KEY = "evaluate.lpips_backbone"
TORCHVISION_NAME = {"alex": "alexnet", "vgg": "vgg16", "squeeze": "squeezenet1_1"}
# Index (in torchvision's `features`) of the ReLU after which LPIPS taps a feature map; these are the
# ends of torchmetrics' slices (alex: range(2), range(2, 5), ...; squeeze: range(2), range(2, 5), ...).
TAPS = {"alex": (1, 4, 7, 9, 11), "vgg": (3, 8, 15, 22, 29), "squeeze": (1, 4, 7, 9, 10, 11, 12)}
CHANNELS = {
    "alex": (64, 192, 384, 256, 256),
    "vgg": (64, 128, 256, 512, 512),
    "squeeze": (64, 128, 256, 384, 384, 512, 512),
}


# --- backbones, as torchvision.models builds their `features` ------------------------------------


def _alexnet_features() -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2),
        nn.ReLU(),
        nn.MaxPool2d(kernel_size=3, stride=2),
        nn.Conv2d(64, 192, kernel_size=5, padding=2),
        nn.ReLU(),
        nn.MaxPool2d(kernel_size=3, stride=2),
        nn.Conv2d(192, 384, kernel_size=3, padding=1),
        nn.ReLU(),
        nn.Conv2d(384, 256, kernel_size=3, padding=1),
        nn.ReLU(),
        nn.Conv2d(256, 256, kernel_size=3, padding=1),
        nn.ReLU(),
        nn.MaxPool2d(kernel_size=3, stride=2),
    )


def _vgg16_features() -> nn.Sequential:
    layers: list[nn.Module] = []
    c_in = 3
    for v in (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M"):
        if v == "M":
            layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
        else:
            layers += [nn.Conv2d(c_in, v, kernel_size=3, padding=1), nn.ReLU()]
            c_in = v
    return nn.Sequential(*layers)


class _Fire(nn.Module):
    """torchvision.models.squeezenet.Fire (same attribute names, so the same state-dict keys)."""

    def __init__(self, c_in: int, squeeze: int, e1: int, e3: int) -> None:
        super().__init__()
        self.squeeze = nn.Conv2d(c_in, squeeze, kernel_size=1)
        self.expand1x1 = nn.Conv2d(squeeze, e1, kernel_size=1)
        self.expand3x3 = nn.Conv2d(squeeze, e3, kernel_size=3, padding=1)

    def forward(self, x: Tensor) -> Tensor:
        x = torch.relu(self.squeeze(x))
        return torch.cat([torch.relu(self.expand1x1(x)), torch.relu(self.expand3x3(x))], 1)


def _squeezenet1_1_features() -> nn.Sequential:
    pool = lambda: nn.MaxPool2d(kernel_size=3, stride=2, ceil_mode=True)  # noqa: E731
    return nn.Sequential(
        nn.Conv2d(3, 64, kernel_size=3, stride=2),
        nn.ReLU(),
        pool(),
        _Fire(64, 16, 64, 64),
        _Fire(128, 16, 64, 64),
        pool(),
        _Fire(128, 32, 128, 128),
        _Fire(256, 32, 128, 128),
        pool(),
        _Fire(256, 48, 192, 192),
        _Fire(384, 48, 192, 192),
        _Fire(384, 64, 256, 256),
        _Fire(512, 64, 256, 256),
    )


BACKBONES: dict[str, Callable[[], nn.Sequential]] = {
    "alex": _alexnet_features,
    "vgg": _vgg16_features,
    "squeeze": _squeezenet1_1_features,
}


# --- LPIPS -------------------------------------------------------------------------------------


class LPIPS(nn.Module):
    """lpips(pred, target): (B, 3, H, W) in [0, 1] -> (B,) LPIPS distances (lower = more similar).

    Always in eval mode, no gradients, float32; follows the inputs' device. Minimum image size:
    alex ~ 32 px, squeeze ~ 16 px, vgg ~ 16 px (torch raises below that)."""

    def __init__(self, net: str) -> None:
        super().__init__()
        self.net = net
        self.features = BACKBONES[net]()
        self.taps = TAPS[net]
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, kernel_size=1, bias=False) for c in CHANNELS[net])
        # torchmetrics ScalingLayer: inputs in [-1, 1] -> ImageNet-ish normalisation
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1), persistent=False)
        self.requires_grad_(False)
        self.eval()

    def train(self, mode: bool = True) -> LPIPS:  # never leaves eval mode
        return super().train(False)

    def _taps(self, x: Tensor) -> list[Tensor]:
        out, taps = [], set(self.taps)
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in taps:
                out.append(x)
            if i == self.taps[-1]:
                break
        return out

    @torch.no_grad()
    def forward(self, pred: Tensor, target: Tensor) -> Tensor:
        for name, x in (("pred", pred), ("target", target)):
            if x.ndim != 4 or x.shape[1] != 3:
                raise ValueError(f"LPIPS expects (B, 3, H, W) images; got {name} of shape {tuple(x.shape)}")
            if not torch.isfinite(x).all() or x.min() < -1e-4 or x.max() > 1 + 1e-4:
                raise ValueError(
                    f"LPIPS expects {name} values in [0, 1]; got [{float(x.min()):.4g}, {float(x.max()):.4g}]"
                )
        if pred.shape != target.shape:
            raise ValueError(f"LPIPS: pred {tuple(pred.shape)} and target {tuple(target.shape)} differ in shape")
        if self.shift.device != pred.device:
            self.to(pred.device)
        x0 = ((2 * pred.float().clamp(0, 1) - 1) - self.shift) / self.scale
        x1 = ((2 * target.float().clamp(0, 1).to(pred.device) - 1) - self.shift) / self.scale
        total = torch.zeros(pred.shape[0], device=pred.device)
        for lin, f0, f1 in zip(self.lins, self._taps(x0), self._taps(x1), strict=True):
            f0 = f0 / torch.sqrt(1e-8 + (f0**2).sum(1, keepdim=True))  # torchmetrics _normalize_tensor
            f1 = f1 / torch.sqrt(1e-8 + (f1**2).sum(1, keepdim=True))
            total = total + lin((f0 - f1) ** 2).mean((1, 2, 3))
        return total


def bundled_lin_path(net: str) -> Path:
    """torchmetrics' bundled LPIPS linear-layer weights for `net`."""
    return Path(str(importlib.resources.files("torchmetrics.functional.image") / "lpips_models" / f"{net}.pth"))


def _load_lins(model: LPIPS, net: str) -> Path:
    path = bundled_lin_path(net)
    if not path.is_file():
        raise FileNotFoundError(
            f"LPIPS linear-layer weights {path} not found: expected them bundled with torchmetrics "
            f"(functional/image/lpips_models/{net}.pth); is torchmetrics installed intact?"
        )
    sd = torch.load(path, map_location="cpu", weights_only=True)  # tensors only: nothing untrusted is unpickled
    # torchmetrics' keys: lin{k}.model.1.weight (model.0 is a Dropout)
    want = {f"lin{k}.model.1.weight": lin.weight for k, lin in enumerate(model.lins)}
    if set(sd) != set(want):
        raise ValueError(f"{path}: expected keys {sorted(want)}, found {sorted(sd)}")
    for k, p in want.items():
        if sd[k].shape != p.shape:
            raise ValueError(f"{path}: {k} has shape {tuple(sd[k].shape)}, expected {tuple(p.shape)}")
        p.copy_(sd[k].float())
    return path


def _load_backbone(model: LPIPS, net: str, path: Path) -> None:
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    tv = TORCHVISION_NAME[net]
    how = f"torchvision.models.{tv}().features.state_dict() (or the full {tv} state dict), saved with safetensors"
    if not path.is_file():
        raise FileNotFoundError(f"{PARAM_KEY} = {str(path)!r}: no such file (expected the {tv} backbone as {how})")
    try:
        sd = load_file(str(path), device="cpu")
    except (SafetensorError, OSError, ValueError) as e:
        raise ValueError(f"{PARAM_KEY} = {str(path)!r}: not a readable safetensors file ({e}); expected {how}") from e
    if any(k.startswith("features.") for k in sd):  # the full torchvision model: keep features.* only
        sd = {k.removeprefix("features."): v for k, v in sd.items() if k.startswith("features.")}
    want = model.features.state_dict()
    missing, unexpected = sorted(set(want) - set(sd)), sorted(set(sd) - set(want))
    if missing or unexpected:
        raise ValueError(
            f"{PARAM_KEY} = {str(path)!r} does not match the {tv} backbone ({how}): "
            f"missing keys {missing[:6]}{' ...' if len(missing) > 6 else ''} ({len(missing)}), "
            f"unexpected keys {unexpected[:6]}{' ...' if len(unexpected) > 6 else ''} ({len(unexpected)}); "
            f"expected keys like {sorted(want)[:4]}"
        )
    bad = [f"{k}: {tuple(sd[k].shape)} != {tuple(v.shape)}" for k, v in want.items() if sd[k].shape != v.shape]
    if bad:
        raise ValueError(f"{PARAM_KEY} = {str(path)!r}: tensor shapes do not match the {tv} backbone: {bad[:6]}")
    model.features.load_state_dict({k: v.float() for k, v in sd.items()}, strict=True)


def load_lpips(
    net: str, backbone_path: str | os.PathLike | None
) -> tuple[Callable[[Tensor, Tensor], Tensor] | None, str]:
    """(lpips, note). lpips(pred, target) maps (B, 3, H, W) images in [0, 1] to per-image LPIPS (B,).

    backbone_path None -> (None, reason): LPIPS is unavailable and is reported as null with the reason.
    Otherwise the backbone is read from that local safetensors file (see the module docstring);
    a missing or mismatching file raises (never a silent fallback, never a download)."""
    if net not in TORCHVISION_NAME:
        raise ValueError(f"LPIPS net must be one of {sorted(TORCHVISION_NAME)}; got {net!r}")
    tv = TORCHVISION_NAME[net]
    if backbone_path is None:
        return None, (
            f"unavailable: {PARAM_KEY} is not set (LPIPS-{net} needs the {tv} backbone weights from a "
            f"local safetensors file; nothing is downloaded)"
        )
    path = Path(backbone_path).expanduser()
    model = LPIPS(net)
    _load_backbone(model, net, path)
    lin_path = _load_lins(model, net)
    import torchmetrics

    note = (
        f"LPIPS-{net}: {tv} backbone from {str(backbone_path)!r}, linear layers from torchmetrics "
        f"{torchmetrics.__version__} ({lin_path.name})"
    )
    return model, note

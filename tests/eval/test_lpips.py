"""LPIPS from local weights only: no backbone -> (None, reason); a local safetensors backbone -> per-image
LPIPS; bad files raise naming the file. Backbones here are random (the test writes its own file), so
the numbers only check the plumbing, and parity with torchmetrics' own _LPIPS given the same backbone."""

from __future__ import annotations

import math

import pytest
import torch
from safetensors.torch import save_file

from pilight.eval.lpips import BACKBONES, TORCHVISION_NAME, load_lpips

# torchvision.models.alexnet() state dict: features (written out independently of pilight's
# implementation, so a layout mistake there shows up here) plus the classifier, which must be ignored.
ALEXNET_SHAPES = {
    "features.0.weight": (64, 3, 11, 11),
    "features.0.bias": (64,),
    "features.3.weight": (192, 64, 5, 5),
    "features.3.bias": (192,),
    "features.6.weight": (384, 192, 3, 3),
    "features.6.bias": (384,),
    "features.8.weight": (256, 384, 3, 3),
    "features.8.bias": (256,),
    "features.10.weight": (256, 256, 3, 3),
    "features.10.bias": (256,),
    "classifier.1.weight": (8, 9216),
    "classifier.1.bias": (8,),  # (4096, 9216) in torchvision; shrunk, ignored
}


def random_state(shapes: dict[str, tuple[int, ...]], seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    out = {}
    for k, s in shapes.items():
        if k.endswith("weight"):  # He init, so activations neither die nor explode through the layers
            out[k] = torch.randn(s, generator=g) * math.sqrt(2.0 / math.prod(s[1:]))
        else:
            out[k] = torch.randn(s, generator=g) * 0.01
    return out


@pytest.fixture(scope="module")
def alex_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("lpips") / "alexnet.safetensors"
    save_file(random_state(ALEXNET_SHAPES), str(path))
    return path


@pytest.fixture(scope="module")
def alex(alex_file):
    return load_lpips("alex", str(alex_file))


def images(b=2, size=64, seed=1):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, 3, size, size, generator=g), torch.randn(b, 3, size, size, generator=g)


@pytest.mark.parametrize("net", ["alex", "vgg", "squeeze"])
def test_no_backbone_is_unavailable_with_reason(net):
    fn, note = load_lpips(net, None)
    assert fn is None
    assert note.startswith("unavailable") and "evaluate.lpips_backbone" in note
    assert TORCHVISION_NAME[net] in note and "nothing is downloaded" in note and "\n" not in note


def test_unknown_net_rejected():
    with pytest.raises(ValueError, match="alex"):
        load_lpips("resnet", None)


def test_local_backbone_loads_without_network(alex_file, monkeypatch):
    def no_network(*a, **k):
        raise AssertionError("LPIPS tried to download something")

    import urllib.request

    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", no_network)
    monkeypatch.setattr(torch.hub, "download_url_to_file", no_network)
    monkeypatch.setattr(urllib.request, "urlopen", no_network)
    fn, note = load_lpips("alex", str(alex_file))
    assert callable(fn)
    assert "alex" in note and str(alex_file) in note


def test_identical_is_zero_and_noise_grows(alex):
    fn, _ = alex
    x, n = images(b=3)
    same = fn(x, x)
    assert same.shape == (3,)
    assert same.abs().max().item() <= 1e-6
    levels = [fn(x, (x + s * n).clamp(0, 1)) for s in (0.02, 0.1, 0.3)]
    for d in levels:
        assert d.shape == (3,) and (d > 0).all()
    for lo, hi in zip(levels, levels[1:]):
        assert (hi > lo).all(), (lo, hi)
    # per image: each row is scored on its own, independent of the rest of the batch
    torch.testing.assert_close(fn(x[1:2], (x + 0.1 * n).clamp(0, 1)[1:2]), levels[1][1:2])


def test_batch_of_one_keeps_shape(alex):
    fn, _ = alex
    x, n = images(b=1)
    assert fn(x, (x + 0.1 * n).clamp(0, 1)).shape == (1,)


def test_inputs_validated(alex):
    fn, _ = alex
    x, _ = images()
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        fn(x * 2 - 1, x)
    with pytest.raises(ValueError, match="B, 3, H, W"):
        fn(x[:, :1], x[:, :1])
    with pytest.raises(ValueError, match="shape"):
        fn(x, x[:1])


def test_features_only_file_gives_same_result(alex, alex_file, tmp_path):
    fn, _ = alex
    full = random_state(ALEXNET_SHAPES)
    path = tmp_path / "features_only.safetensors"
    save_file({k.removeprefix("features."): v for k, v in full.items() if k.startswith("features.")}, str(path))
    fn2, _ = load_lpips("alex", str(path))
    x, n = images()
    y = (x + 0.1 * n).clamp(0, 1)
    torch.testing.assert_close(fn2(x, y), fn(x, y), rtol=0, atol=0)


def test_missing_file_names_path(tmp_path):
    path = tmp_path / "nope.safetensors"
    with pytest.raises(FileNotFoundError, match="nope.safetensors") as e:
        load_lpips("alex", str(path))
    assert "alexnet" in str(e.value) and "safetensors" in str(e.value)


def test_wrong_keys_name_path_and_backbone(tmp_path):
    path = tmp_path / "wrong.safetensors"
    save_file({"conv1.weight": torch.zeros(64, 3, 7, 7)}, str(path))
    with pytest.raises(ValueError, match="wrong.safetensors") as e:
        load_lpips("alex", str(path))
    msg = str(e.value)
    assert "alexnet" in msg and "missing keys" in msg and "conv1.weight" in msg
    # a real backbone of another net: vgg16 features do not fit alexnet
    vgg = tmp_path / "vgg.safetensors"
    save_file({k: v.contiguous() for k, v in BACKBONES["vgg"]().state_dict().items()}, str(vgg))
    with pytest.raises(ValueError, match="vgg.safetensors"):
        load_lpips("alex", str(vgg))


def test_wrong_shapes_name_path(tmp_path):
    shapes = dict(ALEXNET_SHAPES, **{"features.3.weight": (192, 64, 3, 3)})
    path = tmp_path / "shapes.safetensors"
    save_file(random_state(shapes), str(path))
    with pytest.raises(ValueError, match="shapes.safetensors") as e:
        load_lpips("alex", str(path))
    assert "3.weight" in str(e.value)


def test_pickle_is_refused(tmp_path):
    path = tmp_path / "alexnet.pth"
    torch.save(random_state(ALEXNET_SHAPES), path)
    with pytest.raises(ValueError, match="alexnet.pth.*safetensors"):
        load_lpips("alex", str(path))


@pytest.mark.parametrize("net", ["alex", "squeeze", "vgg"])
def test_matches_torchmetrics_lpips(net, tmp_path, monkeypatch):
    """Same backbone weights in torchmetrics' own _LPIPS (its torchvision hook patched to hand over our
    plain-torch backbone, so no torchvision is needed): identical numbers."""
    tml = pytest.importorskip("torchmetrics.functional.image.lpips")
    if not hasattr(tml, "_LPIPS") or not hasattr(tml, "_get_tv_model_features"):
        pytest.skip("torchmetrics' private LPIPS internals changed; parity not checked")
    torch.manual_seed(0)
    features = BACKBONES[net]()
    path = tmp_path / f"{net}.safetensors"
    save_file({f"features.{k}": v.contiguous() for k, v in features.state_dict().items()}, str(path))
    monkeypatch.setattr(tml, "_get_tv_model_features", lambda name, pretrained=False: features)
    ref = tml._LPIPS(pretrained=True, net=net, pnet_rand=True).eval()
    fn, _ = load_lpips(net, str(path))
    x, n = images(b=2, size=48)
    y = (x + 0.2 * n).clamp(0, 1)
    want = ref(x, y, normalize=True).flatten()
    got = fn(x, y)
    assert (want > 0).all()
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-7)

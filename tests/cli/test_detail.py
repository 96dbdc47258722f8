"""The relit photo keeps the input's full-resolution detail (pilight.detail)."""

from __future__ import annotations

import torch

from pilight.detail import resize, with_input_detail


def _photo(h=128, w=96) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    fine = 0.5 + 0.4 * torch.rand(1, 3, h, w, generator=g)  # texture the processing size cannot hold
    ramp = torch.linspace(0.2, 1.0, w).view(1, 1, 1, w)  # smooth shading
    return fine * ramp


def _grad(x: torch.Tensor) -> float:
    lum = x.mean(1)
    return float((lum[..., 1:] - lum[..., :-1]).abs().mean() + (lum[..., 1:, :] - lum[..., :-1, :]).abs().mean())


def test_identity_at_the_processing_size():
    x = _photo(32, 24)
    relit = x * 1.7
    assert torch.equal(with_input_detail(relit, None, x, x), relit)


def test_an_unchanged_photo_comes_back_whole_and_a_changed_one_keeps_its_detail():
    full = _photo()
    proc = resize(full, (32, 24))
    same = with_input_detail(proc, None, proc, full)
    assert float((same - full).abs().max()) < 1e-2 * float(full.max())  # k = 1, own light: the photo itself
    # a smooth change of light (brighter on the left), applied at the processing size
    change = torch.linspace(2.0, 0.5, 24).view(1, 1, 1, 24)
    relit = with_input_detail(proc * change, None, proc, full)
    plain = resize(proc * change, full.shape[-2:])  # what upsampling alone gives
    assert _grad(relit) > 0.8 * _grad(full * resize(change, full.shape[-2:]))
    assert _grad(plain) < 0.5 * _grad(relit)
    # the specular part is added, not scaled by the input's texture
    spec = torch.zeros_like(proc)
    spec[..., 10:14, 10:14] = 3.0
    lit = with_input_detail(proc * change + spec, spec, proc, full)
    torch.testing.assert_close(lit - relit, resize(spec, full.shape[-2:]), atol=1e-5, rtol=1e-5)

"""Physics in fp32 under a bf16 training or inference loop.

The anchors, light fits and condition images are data, not a network. Under accelerate's bf16 autocast
their matrix products run in bf16, and the closed-form least squares of the light fits subtract nearly
equal sums (det = k S_cc - S_c^2): in bf16 that difference is noise, the fitted intensity blows up, and
I * D_GGX * 0 at the terminator gave NaN. That was base stage 2's non-finite loss at step 626 in bf16,
which 'fp32' only hid (docs: lab notebook 2026-12-05, fifth session)."""

from __future__ import annotations

import contextlib
import functools

import torch


@contextlib.contextmanager
def full_precision():
    """Autocast off on every device type: what runs inside computes in its tensors' own dtype."""
    with torch.autocast("cpu", enabled=False), torch.autocast("cuda", enabled=False):
        yield


def in_full_precision(fn):
    """``fn`` always runs with autocast off (``full_precision``)."""

    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        with full_precision():
            return fn(*args, **kwargs)

    return wrapped

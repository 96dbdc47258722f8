"""Optional packages: installed by an extra, imported only where a params key asks for them, and
missed with an error that names the key and the extra.

transformers is one. Only a CLIP image encoder (`conditioning.kind: clip`) and DINOv2 features
(`relight.rec_features: dinov2`), each from a local folder, use it, while diffusers imports it
whenever it is installed: 0.5 s of every `pilight relight` (docs/performance.md). So it is the
`pretrained` extra, not a core dependency.
"""

from __future__ import annotations

from importlib import import_module
from importlib.util import find_spec
from types import ModuleType

from pilight.failure import CommandFailure

EXTRA = {"transformers": "pretrained"}


def installed(package: str) -> bool:
    """Whether ``package`` can be imported, without importing it (params validation stays light)."""
    return find_spec(package) is not None


def missing(package: str, key: str) -> str:
    """The message for a params ``key`` whose setting needs ``package``, which is not installed."""
    return (
        f"{key} needs the {package} package, which is not installed here: "
        f"pip install -e '.[{EXTRA[package]}]' (or pip install {package})"
    )


def require(package: str, key: str) -> ModuleType:
    """``package`` imported, or a CommandFailure (exit 2, a params value unusable here) naming ``key``."""
    try:
        return import_module(package)
    except ImportError as exc:
        raise CommandFailure(missing(package, key), code=2) from exc

"""Relighting pairs for stage 2: input under light a -> target under light b, same scene and view.

Every view gets its identity pairs a -> a (the paper's reconstruction setting, when asked) plus
`pairs_per_view` cross-light pairs drawn without replacement, or all of them. The draw for a view
depends only on (seed, scene, view), so adding a scene never changes another scene's pairs.
The list is written as `<shard_dir>/pairs/<split>.tsv` and read back by the stage-2 loader.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterable
from pathlib import Path
from typing import NamedTuple

import numpy as np

from pilight.data.schema import DataError

HEADER = "scene\tview\tlight_a\tlight_b"


class Pair(NamedTuple):
    scene: str
    view: int
    a: int  # input light
    b: int  # target light


def view_pairs(
    scene: str, view: int, lights: int, *, seed: int, pairs_per_view: int | None, identity: bool = True
) -> list[Pair]:
    """Pairs for one view, sorted by (a, b)."""
    cross = [(a, b) for a in range(lights) for b in range(lights) if a != b]
    if pairs_per_view is not None and pairs_per_view < len(cross):
        # crc32, not hash(): Python salts str hashes per process.
        rng = np.random.default_rng([seed, zlib.crc32(scene.encode()), view])
        cross = [cross[i] for i in rng.choice(len(cross), size=pairs_per_view, replace=False)]
    chosen = cross + ([(a, a) for a in range(lights)] if identity else [])
    return [Pair(scene, view, a, b) for a, b in sorted(chosen)]


def make_pairs(
    views: Iterable[tuple[str, int, int]], *, seed: int, pairs_per_view: int | None, identity: bool = True
) -> list[Pair]:
    """Pairs for every (scene, view, number of lights), in the order given."""
    return [
        p
        for scene, view, lights in views
        for p in view_pairs(scene, view, lights, seed=seed, pairs_per_view=pairs_per_view, identity=identity)
    ]


def write_pairs(path: Path, pairs: Iterable[Pair]) -> None:
    lines = [HEADER] + [f"{p.scene}\t{p.view}\t{p.a}\t{p.b}" for p in pairs]
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text("\n".join(lines) + "\n")


def read_pairs(path: Path) -> list[Pair]:
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: pairs file not found; run the shard stage")
    lines = path.read_text().splitlines()
    if not lines or lines[0] != HEADER:
        raise DataError(f"{path}: first line must be {HEADER!r}")
    pairs = []
    for n, line in enumerate(lines[1:], start=2):
        fields = line.split("\t")
        try:
            pairs.append(Pair(fields[0], int(fields[1]), int(fields[2]), int(fields[3])))
        except (IndexError, ValueError):
            raise DataError(f"{path}:{n}: want 4 tab-separated fields scene, view, a, b; got {line!r}") from None
    return pairs

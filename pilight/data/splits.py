"""Split lists: the render stage assigns splits (scene ids carry them); we check and record them.

`<shard_dir>/splits/<split>.txt` holds one scene id a line, sorted; `splits/hdris.json` records
which HDRIs each split uses and their overlap, so a reader can see the held-out set at a glance.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from pilight.data.schema import SPLITS, DataError

SCENE_ID = re.compile(r"^(train|val|test)_[0-9A-Za-z_-]+$")


class SplitError(DataError):
    """The manifest's splits are malformed or leak a scene into two splits."""


def check_splits(scenes: Iterable[Mapping[str, Any]], where: str = "manifest.json") -> dict[str, list[str]]:
    """{split: sorted scene ids}; raises SplitError on a leak, a bad split or a bad scene id."""
    seen: dict[str, str] = {}
    for entry in scenes:
        sid, split = entry.get("id"), entry.get("split")
        if split not in SPLITS:
            raise SplitError(f"{where}: scene {sid!r}: split {split!r} not in {SPLITS}")
        if not isinstance(sid, str) or not SCENE_ID.match(sid):
            raise SplitError(f"{where}: scene id {sid!r} must look like '<split>_<index>' (letters, digits, _ or -)")
        if sid in seen:
            leak = "in two splits" if seen[sid] != split else "listed twice"
            raise SplitError(f"{where}: scene {sid!r} is {leak} ({seen[sid]!r} and {split!r})")
        if not sid.startswith(split + "_"):
            raise SplitError(f"{where}: scene {sid!r} is marked {split!r} but its id names another split")
        seen[sid] = split
    return {s: sorted(i for i, sp in seen.items() if sp == s) for s in SPLITS}


def check_hdri_holdout(
    scenes: Iterable[Mapping[str, Any]], heldout: Iterable[str], where: str = "manifest.json"
) -> None:
    """Raise SplitError if a train/val scene uses an HDRI held out for test (render.hdri.test_holdout)."""
    heldout = set(heldout)
    for entry in scenes:
        if entry.get("split") != "test":
            leaked = sorted(heldout & set(_names(entry)))
            if leaked:
                raise SplitError(
                    f"{where}: scene {entry.get('id')!r} ({entry.get('split')}) uses HDRIs held out for test: {leaked}"
                )


def _names(entry: Mapping[str, Any]) -> list[str]:
    return [h for h in entry.get("hdris") or [] if isinstance(h, str)]


def hdri_summary(scenes: Iterable[Mapping[str, Any]]) -> dict[str, Any]:
    """HDRI names per split (from the manifest's opaque "hdris" field) and test's overlap with train/val."""
    used: dict[str, set[str]] = {s: set() for s in SPLITS}
    for entry in scenes:
        used[entry["split"]].update(_names(entry))
    seen = used["train"] | used["val"]
    return {
        "per_split": {s: sorted(v) for s, v in used.items()},
        "only_in_test": sorted(used["test"] - seen),
        "test_also_in_train_or_val": sorted(used["test"] & seen),
    }


def write_splits(shard_dir: Path, splits: Mapping[str, list[str]], hdris: Mapping[str, Any]) -> None:
    d = Path(shard_dir) / "splits"
    d.mkdir(parents=True, exist_ok=True)
    for split in SPLITS:
        (d / f"{split}.txt").write_text("".join(f"{sid}\n" for sid in splits[split]))
    (d / "hdris.json").write_text(json.dumps(hdris, indent=1, sort_keys=True) + "\n")


def read_split(shard_dir: Path, split: str) -> list[str]:
    path = Path(shard_dir) / "splits" / f"{split}.txt"
    if not path.is_file():
        raise SplitError(f"{path}: split list not found; run the shard stage")
    return path.read_text().split()

"""Shard writer and readers on a synthetic render folder written exactly as pilight.data.layout says."""

from __future__ import annotations

import hashlib
import json
import os
import stat
import subprocess
import sys
import tarfile
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
import torch
import webdataset as wds
from pydantic import ValidationError

from fixtures.fake_renders import write_fake_renders
from pilight.data import layout
from pilight.data.exr import read_exr, write_exr
from pilight.data.pairs import read_pairs
from pilight.data.schema import DataError, SampleError
from pilight.data.shard_params import ShardParams
from pilight.data.shard_reader import (
    eval_dataset,
    exr_decoder,
    intrinsics_dataset,
    make_loader,
    read_index,
    relight_dataset,
)
from pilight.data.shard_writer import write_shards
from pilight.data.splits import SplitError, read_split

REPO = Path(__file__).resolve().parents[2]
SEED = 7


@pytest.fixture
def renders(tmp_path):
    return write_fake_renders(tmp_path / "renders")


@pytest.fixture
def shards(renders, tmp_path):
    out = tmp_path / "shards"
    write_shards(renders, out, ShardParams(maxcount=4), seed=SEED)
    return out


def folder_hash(d: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(d.rglob("*")):
        if p.is_file():
            h.update(str(p.relative_to(d)).encode() + b"\0" + p.read_bytes())
    return h.hexdigest()


def f16(path: Path) -> np.ndarray:
    return read_exr(path).astype(np.float16).astype(np.float32)


def test_round_trip_is_float16_exact(renders, shards):
    seen = 0
    for s in eval_dataset(shards, "train", task="intrinsics"):
        m = json.loads(s["meta"])
        for name in ("image", "albedo", "normal", "roughness", "metallic", "mask"):
            light = m["light"] if name == "image" else None
            want = f16(layout.map_path(renders, m["scene"], m["view"], name, light))
            assert np.array_equal(s[name].numpy().transpose(1, 2, 0), want), (s["key"], name)
        assert m["camera"]["view"] == m["view"] and m["light_params"]["light"] == m["light"]
        assert m["light_params"]["points"][0]["power"] == 10.0 + m["view"]  # this view's light
        assert m["manifest_extra"]["hdris"] and m["render"]["blender_version"] == "5.0.1"
        seen += 1
    assert seen == 2 * 3 + 1 * 3
    for p in relight_dataset(shards, "test", shuffle=False):
        m = json.loads(p["meta_b"])
        for name in ("image", "ball", "diffuse", "specular", "ball_lambertian"):
            want = f16(layout.map_path(renders, m["scene"], m["view"], name, m["light"]))
            assert np.array_equal(p[f"{name}_b"].numpy().transpose(1, 2, 0), want)


def test_byte_identical_and_views_never_straddle_shards(renders, tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    write_shards(renders, a, ShardParams(maxcount=4), seed=SEED)
    write_shards(renders, b, ShardParams(maxcount=4), seed=SEED)
    assert folder_hash(a) == folder_hash(b)
    index = read_index(a)
    assert index["splits"]["train"]["shards"] == ["train-000000.tar", "train-000001.tar", "train-000002.tar"]
    for name in index["splits"]["train"]["shards"]:  # maxcount 4, 3 lights a view: one view a shard
        keys = {s["__key__"].rsplit("_l", 1)[0] for s in wds.tarfile_samples([{"url": str(a / "train" / name)}])}
        assert len(keys) == 1
    assert not list(tmp_path.glob(".*"))  # no temporaries left beside the outputs


def test_rewrite_replaces_previous_output(renders, shards):
    before = folder_hash(shards)
    write_shards(renders, shards, ShardParams(maxcount=4), seed=SEED)
    assert folder_hash(shards) == before


def _write_raw_exr(path: Path, arr: np.ndarray) -> None:
    # Bypasses write_exr, which (rightly) refuses NaN/Inf: a corrupt render must still be caught.
    chans = {c: np.ascontiguousarray(arr[..., i]) for i, c in enumerate("RGB")}
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, chans) as f:
        f.write(str(path))


def corrupt(root: Path, case: str) -> tuple[Path, str]:
    """Break one file; return its path and the first sample that reads it."""
    img = layout.map_path(root, "train_0001", 0, "image", 1)
    if case in ("nan", "inf"):
        arr = read_exr(img)
        arr[3, 5, 1] = np.nan if case == "nan" else np.inf
        _write_raw_exr(img, arr)
    elif case == "shape":
        write_exr(img, read_exr(img)[:15], half=False)
    elif case == "missing":
        img = layout.map_path(root, "train_0001", 0, "specular", 1)
        img.unlink()
    elif case == "range":
        img = layout.map_path(root, "train_0001", 0, "roughness")  # per view: light 0 reads it first
        write_exr(img, read_exr(img) + 1.0, half=True)
        return img, "train_0001_v00_l00"
    elif case == "truncated":
        data = img.read_bytes()
        img.write_bytes(data[: len(data) // 2])
    return img, "train_0001_v00_l01"


CASES = ["nan", "inf", "shape", "missing", "range", "truncated"]


@pytest.mark.parametrize("case", CASES)
def test_corrupt_input_is_named_and_leaves_nothing(renders, tmp_path, case):
    bad, key = corrupt(renders, case)
    out = tmp_path / "out"
    with pytest.raises((SampleError, DataError)) as err:
        write_shards(renders, out, ShardParams(), seed=SEED)
    assert key in str(err.value) and str(bad) in str(err.value)
    assert not out.exists() and not list(tmp_path.glob(".out*"))


@pytest.mark.parametrize("case", CASES)
def test_stage_script_exits_nonzero_with_clear_message(renders, tmp_path, case):
    bad, key = corrupt(renders, case)
    params = tmp_path / "params.yaml"
    params.write_text("base:\n  seed: 3\nrender: {resolution: 128}\nshard:\n  maxcount: 8\n")
    out = tmp_path / "out"
    proc = subprocess.run(
        [
            sys.executable,
            str(REPO / "stages" / "shard.py"),
            "--params",
            str(params),
            "--renders",
            str(renders),
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 1
    assert key in proc.stderr and str(bad) in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not out.exists() and not list(tmp_path.glob(".out*"))


def test_stage_script_succeeds_and_rejects_bad_params(renders, tmp_path):
    params = tmp_path / "params.yaml"
    params.write_text("base:\n  seed: 3\nrender: {resolution: 128}\nshard:\n  maxcount: 0\n")
    cmd = [
        sys.executable,
        str(REPO / "stages" / "shard.py"),
        "--params",
        str(params),
        "--renders",
        str(renders),
        "--out",
        str(tmp_path / "out"),
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode == 2 and "shard.maxcount = 0" in proc.stderr, proc.stderr
    params.write_text("base:\n  seed: 3\nrender: {resolution: 128}\nshard:\n  maxcount: 8\n")
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert read_index(tmp_path / "out")["splits"]["train"]["samples"] == 9


def test_incomplete_view_is_refused(renders, tmp_path):
    (layout.view_dir(renders, "val_0000", 0) / layout.DONE_MARKER).unlink()
    with pytest.raises(DataError, match=r"val_0000_v00_l00.*\.done"):
        write_shards(renders, tmp_path / "out", ShardParams(), seed=SEED)


def test_flat_light_list_in_scene_json_is_accepted(renders, tmp_path):
    path = renders / "val_0000" / "scene.json"
    info = json.loads(path.read_text())
    info["lights"] = info["lights"][0]  # one list for all views, as the brief first described
    path.write_text(json.dumps(info))
    write_shards(renders, tmp_path / "out", ShardParams(), seed=SEED)


def test_splits_are_disjoint_and_written(shards):
    lists = {s: read_split(shards, s) for s in ("train", "val", "test")}
    assert lists == {"train": ["train_0000", "train_0001"], "val": ["val_0000"], "test": ["test_0000"]}
    hdris = json.loads((shards / "splits" / "hdris.json").read_text())
    assert hdris["test_also_in_train_or_val"] == [] and hdris["only_in_test"] == ["hdri0_test"]


def test_heldout_hdri_in_train_is_refused(renders, tmp_path):
    with pytest.raises(SplitError, match=r"train_0000.*hdri0_train"):
        write_shards(renders, tmp_path / "out", ShardParams(), seed=SEED, heldout_hdris=["hdri0_train"])
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("leak", ["two_splits", "id_names_other_split"])
def test_leaky_manifest_is_refused(renders, tmp_path, leak):
    mpath = renders / "manifest.json"
    manifest = json.loads(mpath.read_text())
    if leak == "two_splits":
        manifest["scenes"].append({**manifest["scenes"][0], "split": "test"})
    else:
        manifest["scenes"][0]["split"] = "val"
    mpath.write_text(json.dumps(manifest))
    with pytest.raises(SplitError, match="train_0000"):
        write_shards(renders, tmp_path / "out", ShardParams(), seed=SEED)
    assert not (tmp_path / "out").exists()


def test_pairs_share_scene_and_view_and_include_identity(shards):
    listed = {(p.scene, p.view, p.a, p.b) for p in read_pairs(shards / "pairs" / "train.tsv")}
    got = []
    for p in relight_dataset(shards, "train", shuffle=True, seed=1):
        a, b = json.loads(p["meta_a"]), json.loads(p["meta_b"])
        assert (a["scene"], a["view"]) == (b["scene"], b["view"])
        assert p["image_a"].shape == (3, 16, 16) and p["ball_b"].shape == (3, 8, 8)
        got.append((a["scene"], a["view"], a["light"], b["light"]))
    assert sorted(got) == sorted(listed) and len(got) == len(listed) == 3 * 9
    assert all((s, v, li, li) in listed for s, v, li, _ in listed)
    again = [p["key"] for p in relight_dataset(shards, "train", shuffle=True, seed=1)]
    assert again == [f"{s}_v{v:02d}_l{a:02d}_to_l{b:02d}" for s, v, a, b in got]


def test_cross_only_drops_exactly_the_identity_pairs(shards):
    listed = {(p.scene, p.view, p.a, p.b) for p in read_pairs(shards / "pairs" / "train.tsv")}
    got = set()
    for p in relight_dataset(shards, "train", shuffle=True, seed=1, cross_only=True):
        a, b = json.loads(p["meta_a"]), json.loads(p["meta_b"])
        got.add((a["scene"], a["view"], a["light"], b["light"]))
    assert got == {k for k in listed if k[2] != k[3]} and len(got) == 3 * 6


@pytest.mark.parametrize("task", ["intrinsics", "relight"])
def test_two_workers_over_one_shard_terminate_and_see_each_item_once(renders, tmp_path, task):
    out = tmp_path / "one"
    write_shards(renders, out, ShardParams(), seed=SEED)
    assert len(read_index(out)["splits"]["train"]["shards"]) == 1
    ds = (intrinsics_dataset if task == "intrinsics" else relight_dataset)(out, "train", shuffle=True)
    keys = [k for batch in make_loader(ds, batch_size=2, num_workers=2) for k in batch["key"]]
    assert len(keys) == len(set(keys)) == (9 if task == "intrinsics" else 27)


def test_two_workers_over_three_shards(shards):
    assert len(read_index(shards)["splits"]["train"]["shards"]) == 3  # the shard-level split path
    keys = [k for b in make_loader(intrinsics_dataset(shards, "train"), batch_size=1, num_workers=2) for k in b["key"]]
    assert len(keys) == len(set(keys)) == 9


@pytest.mark.parametrize("split", ["train", "val"])  # 3 shards / 1 shard over 2 ranks
def test_ranks_partition_the_data(shards, monkeypatch, split):
    per_rank = []
    for rank in (0, 1):  # what split_by_node sees under torchrun
        monkeypatch.setenv("RANK", str(rank))
        monkeypatch.setenv("WORLD_SIZE", "2")
        per_rank.append({s["key"] for s in intrinsics_dataset(shards, split, seed=5)})
    assert not per_rank[0] & per_rank[1]
    assert len(per_rank[0] | per_rank[1]) == read_index(shards)["splits"][split]["samples"]


def test_shuffle_is_seeded_and_complete(shards):
    order = lambda seed: [s["key"] for s in intrinsics_dataset(shards, "train", seed=seed, buffer=4)]  # noqa: E731
    assert order(0) == order(0) and sorted(order(0)) == sorted(order(1))
    assert order(0) != [s["key"] for s in eval_dataset(shards, "train", task="intrinsics")]


def test_repeat_keeps_going_across_epochs(shards):
    it = iter(intrinsics_dataset(shards, "val", repeat=True, buffer=2))
    keys = [next(it)["key"] for _ in range(5)]  # val has 2 samples: 5 draws span 3 passes
    assert set(keys) == {"val_0000_v00_l00", "val_0000_v00_l01"}


def test_plain_webdataset_with_registered_exr_decoder(shards):
    url = str(shards / "val" / "val-000000.tar")
    sample = next(iter(wds.WebDataset(url, shardshuffle=False).decode(exr_decoder)))
    assert sample["image.exr"].shape == (16, 16, 3) and sample["mask.exr"].dtype == np.float32


def test_batches_collate(shards):
    batch = next(iter(make_loader(relight_dataset(shards, "train"), batch_size=4)))
    assert batch["image_a"].shape == (4, 3, 16, 16) and batch["mask"].shape == (4, 1, 16, 16)
    assert batch["image_a"].dtype == torch.float32 and len(batch["meta_b"]) == 4


def test_shard_params_validation():
    with pytest.raises(ValidationError, match="extra"):
        ShardParams(maxcnt=3)
    with pytest.raises(ValidationError, match="pairs_per_view must be >= 0"):
        ShardParams(pairs_per_view=-1)
    with pytest.raises(ValidationError, match="maxsize must be a positive"):
        ShardParams(maxsize=0)


# --- issue 18: shards verified against index.json -------------------------------------------
def _first_train_shard(shards: Path) -> tuple[Path, list[tarfile.TarInfo]]:
    path = shards / "train" / read_index(shards)["splits"]["train"]["shards"][0]
    with tarfile.open(path) as tf:
        return path, tf.getmembers()


def _writable(path: Path) -> None:
    os.chmod(path, 0o644)  # the writer makes shards read-only; the tests damage them on purpose


def test_index_records_count_and_sha256_per_shard(shards):
    for split, entry in read_index(shards)["splits"].items():
        checks = entry["shard_checks"]
        assert sorted(checks) == sorted(entry["shards"])
        assert sum(c["samples"] for c in checks.values()) == entry["samples"]
        for name, c in checks.items():
            path = shards / split / name
            assert c["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
            with tarfile.open(path) as tf:
                assert len({m.name.split(".", 1)[0] for m in tf.getmembers()}) == c["samples"]


def test_shard_cut_at_a_member_boundary_fails_by_name(shards):
    path, members = _first_train_shard(shards)
    keys = sorted({m.name.split(".", 1)[0] for m in members})
    assert len(keys) >= 3
    third = next(m for m in members if m.name.startswith(keys[2] + "."))
    _writable(path)
    with open(path, "r+b") as fh:  # still a valid tar, with the first two samples only
        fh.truncate(third.offset)
    # Before: the loader streamed 2 of the samples and training ended with exit 0.
    with pytest.raises(DataError, match=rf"{path}: damaged shard: sha256 differs .* 2 of its \d+ samples"):
        intrinsics_dataset(shards, "train")


def test_shard_cut_mid_member_fails_by_name(shards):
    path, members = _first_train_shard(shards)
    meta = next(m for m in members if m.name.endswith(".meta.json"))
    _writable(path)
    with open(path, "r+b") as fh:
        fh.truncate(meta.offset_data + 5)
    with pytest.raises(DataError, match=rf"{path}: damaged shard"):
        relight_dataset(shards, "train")


@pytest.mark.parametrize("where", ["header", "data"])
def test_cut_shard_is_named_at_read_time_without_recorded_checks(shards, where):
    # An index.json written before the checks existed: the reader itself names the shard.
    index = read_index(shards)
    for entry in index["splits"].values():
        entry.pop("shard_checks", None)
    (shards / "index.json").write_text(json.dumps(index))
    path, members = _first_train_shard(shards)
    second = sorted({m.name.split(".", 1)[0] for m in members})[1]
    # Its second member: the first one survives, meta.json (sorted last but one) does not.
    member = [m for m in members if m.name.startswith(second + ".")][1]
    _writable(path)
    with open(path, "r+b") as fh:
        fh.truncate(member.offset + 100 if where == "header" else member.offset_data + 5)
    # Before: a raw KeyError: 'meta.json' (cut in a header) or tarfile.ReadError (cut in the data).
    with pytest.raises(DataError, match=rf"{path}: (sample '{second}' lacks|unreadable shard)"):
        list(intrinsics_dataset(shards, "train", shuffle=False))


def test_missing_shard_fails_by_name(shards):
    path, _ = _first_train_shard(shards)
    path.unlink()
    with pytest.raises(DataError, match=rf"{path}: shard missing"):
        eval_dataset(shards, "train", "intrinsics")


def test_shard_folder_follows_the_umask(renders, tmp_path):
    old = os.umask(0o027)
    try:
        write_shards(renders, tmp_path / "s", ShardParams(maxcount=4), seed=SEED)
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "s").stat().st_mode) == 0o750  # mkdtemp alone gives 0700


def test_full_disk_names_the_shard_folder(renders, tmp_path, monkeypatch):
    import errno

    import pilight.data.shard_writer as shards_mod

    def full(*args, **kw):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(shards_mod, "write_splits", full)
    out = tmp_path / "s"
    with pytest.raises(OSError, match="No space left on device") as info:
        write_shards(renders, out, ShardParams(maxcount=4), seed=SEED)
    assert str(out) in str(info.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["renders"]

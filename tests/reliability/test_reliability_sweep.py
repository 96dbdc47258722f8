"""Issue 36, whole or nothing: every stage sweeps the temporaries that a killed run of it left beside or
inside its outputs, at its start, and says so. Before, killed shard, infer and relight stages left
`data/.<out>.tmp-*` folders that nothing ever removed."""

from __future__ import annotations

import shlex
from pathlib import Path

import pytest
import yaml

from fixtures.fake_renders import write_fake_renders
from fixtures.script_modules import load_stage
from pilight import atomic

ROOT = Path(__file__).resolve().parents[2]


def test_the_sweep_removes_what_killed_writers_leave_and_nothing_else(tmp_path):
    data = tmp_path / "data"
    shards = data / "shards"
    (shards / "train").mkdir(parents=True)
    stale = [
        data / ".shards.tmp-k2x9_a0b",  # write_shards / write_predictions killed mid-write (mkdtemp)
        data / ".shards.old-4242",  # killed between the two renames of a swap
        shards / "train" / ".index.json.a1b2c3d4.tmp",  # atomic.write_with inside the output
        shards / ".render_tmp_abc",  # the render's scratch
        shards / ".tmp-step_0000002-77",  # a checkpoint folder being written
        data / ".metrics.json.x_9y8z7w.tmp",  # a metrics file being written
    ]
    kept = [
        shards / "index.json",
        shards / "train" / "train-000000.tar",
        shards / "train" / ".done",
        shards / ".partitions" / "a--b.done",
        data / ".relit.tmp-k2x9_a0b",  # another output's temporary: not this stage's to remove
        data / "metrics.json",
    ]
    for p in stale + kept:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.mkdir() if "tmp-" in p.name or "old-" in p.name or "render_tmp" in p.name else p.write_text("x")
    removed = atomic.sweep_temporaries(shards, data / "metrics.json", None)
    assert sorted(removed) == sorted(stale)
    assert all(p.exists() for p in kept)


def _declared_outputs(stage: dict) -> list[str]:
    out = []
    for kind in ("outs", "metrics", "plots"):
        for entry in stage.get(kind, []):
            out.append(next(iter(entry)) if isinstance(entry, dict) else entry)
    return out


STAGES = [(f, name) for f in ("dvc.yaml", "base/dvc.yaml") for name in yaml.safe_load((ROOT / f).read_text())["stages"]]


@pytest.mark.parametrize("dvc_file, name", STAGES)
def test_every_stage_sweeps_every_output_it_declares(dvc_file, name, monkeypatch):
    """Each stage script hands run_stage the paths of all its dvc.yaml outs, metrics and plots (for the
    command dvc.yaml runs), so a killed run of any stage leaves nothing that its next run keeps."""
    stage = yaml.safe_load((ROOT / dvc_file).read_text())["stages"][name]
    wdir = (ROOT / dvc_file).parent / stage.get("wdir", ".")
    argv = shlex.split(stage["cmd"])
    script = next(a for a in argv if a.endswith(".py"))
    path = (wdir / script).resolve()
    assert path.parent == ROOT / "stages", path
    mod = load_stage(path.stem)
    seen = {}

    def fake_run_stage(name, doc, argv, sections, options, body, outputs=None):
        import argparse

        ap = argparse.ArgumentParser()
        ap.add_argument("--params", default="params.yaml")
        options(ap)
        seen["outputs"] = outputs(ap.parse_args(argv)) if outputs is not None else []
        return 0

    monkeypatch.setattr(mod, "run_stage", fake_run_stage)
    mod.main(argv[argv.index(script) + 1 :])
    swept = [Path(p) for p in seen["outputs"] if p is not None]
    missing = [o for o in _declared_outputs(stage) if not any(Path(o) == s or s in Path(o).parents for s in swept)]
    assert not missing, f"{dvc_file} stage {name}: outputs not swept at start: {missing} (swept: {swept})"


def test_a_killed_shard_runs_temporaries_are_removed_by_the_next_run(tmp_path, capsys):
    renders = write_fake_renders(tmp_path / "renders", size=16, ball=8)
    out = tmp_path / "shards"
    left = [tmp_path / ".shards.tmp-q1w2e3r4", tmp_path / ".shards.old-31337"]
    for p in left:
        (p / "train").mkdir(parents=True)
        (p / "train" / "train-000000.tar").write_bytes(b"partial")
    params = tmp_path / "params.yaml"
    params.write_text((ROOT / "params.yaml").read_text())
    rc = load_stage("shard").main(["--params", str(params), "--renders", str(renders), "--out", str(out)])
    err = capsys.readouterr().err
    # Before: both stayed in the data folder (and in `dvc status`' view of it) for good.
    assert rc == 0 and "shard: removed 2 temporary output(s) left by a killed run" in err, err
    assert not any(p.exists() for p in left) and (out / "index.json").is_file()

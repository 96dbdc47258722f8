"""pilight/seeds.py (claims over seeds): the statistics against values computed by hand, the -S parsing
and its refusals (exit 2 before anything runs), and when an experiment may stand for a run."""

from __future__ import annotations

import importlib
import math
import shutil
import tomllib

import pytest
import yaml

from fixtures.stage_scripts import REPO
from pilight import seeds

# Two-sided 95% Student-t quantiles, from printed tables (and scipy.stats.t.ppf(0.975, df))
T95 = {1: 12.7062047, 2: 4.30265273, 4: 2.77644511, 9: 2.26215716, 30: 2.04227246}


@pytest.mark.parametrize("df", sorted(T95))
def test_t_quantile_matches_the_table(df):
    assert seeds.t_quantile(df) == pytest.approx(T95[df], abs=1e-6)


def test_t_quantile_at_other_confidences():
    assert seeds.t_quantile(5, 0.90) == pytest.approx(2.01504837, abs=1e-6)
    assert seeds.t_quantile(10_000) == pytest.approx(1.95996398, abs=1e-3)  # the normal's 1.96


def test_mean_and_sample_sd():
    s = seeds.mean_sd([1.0, 2.0, 3.0, 4.0])
    assert s["n"] == 4 and s["mean"] == 2.5
    assert s["sd"] == pytest.approx(math.sqrt(5 / 3))  # sum of squares 5 over n - 1 = 3
    assert seeds.mean_sd([3.0]) == {"n": 1, "mean": 3.0, "sd": None}


def test_paired_difference_pairs_by_seed_not_by_order():
    default = {42: 1.0, 43: 2.0, 44: 3.0}
    variant = {44: 5.0, 42: 2.0, 43: 4.0}  # another order: pairs are by seed
    d = seeds.paired_difference(default, variant)
    assert d["seeds"] == [42, 43, 44] and d["values"] == [1.0, 2.0, 2.0]
    assert d["mean"] == pytest.approx(5 / 3)
    assert d["sd"] == pytest.approx(math.sqrt(1 / 3))  # (4/9 + 1/9 + 1/9) / 2
    half = 4.30265273 * math.sqrt(1 / 3) / math.sqrt(3)  # t(0.975, 2) sd / sqrt(n) = 1.4342176
    assert d["ci95"] == pytest.approx([5 / 3 - half, 5 / 3 + half])
    assert d["ci95"] == pytest.approx([0.2324491, 3.1008842])


def test_paired_difference_uses_only_the_seeds_both_arms_hold():
    d = seeds.paired_difference({1: 1.0, 2: 1.0}, {2: 3.0, 3: 9.0})
    assert d["seeds"] == [2] and d["mean"] == 2.0 and d["sd"] is None and d["ci95"] is None


def test_summary_shape_and_table():
    summary = seeds.summarise({"psnr": {"default": {42: 20.0, 43: 21.0}, "variant": {42: 19.0, 43: 21.5}}})
    row = summary["psnr"]
    assert set(row) == {"default", "variant", "difference"}
    assert row["default"]["values"] == [20.0, 21.0] and row["default"]["mean"] == 20.5
    assert row["difference"]["values"] == [-1.0, 0.5]
    table = seeds.format_table(summary, [42, 43])
    assert (
        "20.5 ± 0.7071" in table and "-0.25 ± 1.061" in table and "[-9.78, +9.28]" in table
    )  # -0.25 -+ 12.706 * 1.0607 / sqrt(2)
    only_default = seeds.summarise({"psnr": {"default": {42: 20.0, 43: 21.0}}})
    assert set(only_default["psnr"]) == {"default"} and "variant" not in seeds.format_table(only_default, [42, 43])


PARAMS = {"base": {"seed": 42, "train_seed": None}, "relight": {"lambda_ds": 1.0, "train": {"lr": 1e-4}}}


@pytest.mark.parametrize(
    "text, key, value",
    [
        ("relight.lambda_ds=0", "relight.lambda_ds", "0"),
        ("params.yaml:relight.train.lr=3e-4", "relight.train.lr", "3e-4"),
        ("relight.train={lr: 1}", "relight.train", "{lr: 1}"),
    ],
)
def test_an_override_of_a_key_params_yaml_holds(text, key, value):
    assert seeds.parse_override(text, PARAMS) == seeds.Override(key, value)


@pytest.mark.parametrize(
    "text, says",
    [
        ("relight.lamda_ds=0", "has no key 'relight.lamda_ds'; did you mean lambda_ds"),
        ("relight.train.lr.x=1", "has no key 'relight.train.lr.x'"),
        ("relite.lambda_ds=0", "did you mean relight"),
        ("relight.lambda_ds", "want key=value"),
        ("+relight.new=1", "no + or ~"),
        ("other.yaml:relight.lambda_ds=0", "only params.yaml"),
    ],
)
def test_an_override_params_yaml_lacks_is_refused_with_its_key(text, says):
    with pytest.raises(seeds.UsageError) as exc:
        seeds.parse_override(text, PARAMS)
    assert says in str(exc.value) and text in str(exc.value)


@pytest.fixture
def project(tmp_path, monkeypatch):
    """A DVC project with this repository's dvc.yaml and params.yaml, in which nothing may run."""
    from dvc.repo import Repo

    shutil.copy(REPO / "dvc.yaml", tmp_path / "dvc.yaml")
    shutil.copy(REPO / "params.yaml", tmp_path / "params.yaml")
    Repo.init(str(tmp_path), no_scm=True).close()
    monkeypatch.chdir(tmp_path)

    def refuse(*args, **kwargs):
        raise AssertionError(f"ran {args} before refusing the command line")

    monkeypatch.setattr(seeds, "_dvc", refuse)
    monkeypatch.setattr(seeds, "_git", refuse)
    monkeypatch.setattr(seeds, "_prepare_data", refuse)
    return tmp_path


@pytest.mark.parametrize(
    "argv, says",
    [
        (["-S", "relight.lamda_ds=0"], "params.yaml has no key 'relight.lamda_ds'; did you mean lambda_ds"),
        (["-S", "render.resolution=64"], "stage 'render' reads render.resolution"),
        (["-S", "shard.pairs_per_view=1"], "stage 'shard' reads shard.pairs_per_view"),
        (["-S", "render=1"], "stage 'render' reads"),  # a whole data section
        (["-S", "base.train_seed=3"], "--seeds"),
        (["-S", "base.seed=3"], "--seeds"),
        (["-S", "relight.train.seed=3"], "relight.train.seed is 3, which pins that stage's training seed"),
        (["-S", "relight.lambda_ds=abc"], "relight.lambda_ds = 'abc'"),  # the params' own validation
        (["--seeds", "42", "42"], "distinct"),
        (["--metrics-file", "metrics/nothing.json"], "no stage of dvc.yaml declares it"),
        (["--target", "nowhere"], "not a stage of dvc.yaml"),
        # the default metrics file (metrics/headline.json, or metrics/evaluate.json before it) is evaluate's
        (["--target", "train_intrinsics"], ".json is written by stage 'evaluate', which --target train_intrinsics"),
    ],
)
def test_bad_command_lines_exit_2_before_anything_runs(project, argv, says, capsys):
    assert seeds.main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("pilight-seeds: ") and says in err, err


def test_a_params_file_that_pins_a_stage_seed_is_refused(project, capsys):
    """A stage with its own train.seed ignores base.train_seed: the seeds would not vary it."""
    params = yaml.safe_load((project / "params.yaml").read_text())
    params["intrinsics"]["train"]["seed"] = 5
    (project / "params.yaml").write_text(yaml.safe_dump(params))
    assert seeds.main([]) == 2
    assert "intrinsics.train.seed is 5, which pins" in capsys.readouterr().err


def test_a_project_without_base_train_seed_is_refused(project, capsys):
    dvc = yaml.safe_load((project / "dvc.yaml").read_text())
    for stage in dvc["stages"].values():
        stage["params"] = [p for p in stage.get("params", []) if p != "base.train_seed"]
    (project / "dvc.yaml").write_text(yaml.safe_dump(dvc))
    assert seeds.main([]) == 2
    assert "no stage of dvc.yaml declares base.train_seed" in capsys.readouterr().err


def test_the_data_stages_are_render_and_shard(project):
    pipeline = seeds.read_pipeline(project)
    assert pipeline.data_stages == ["render", "shard"]
    assert set(pipeline.seeded) == {"train_intrinsics", "infer_intrinsics", "train_relight", "relight", "trade"}
    assert pipeline.metrics["metrics/evaluate.json"] == "evaluate"
    assert pipeline.run_stages(["train_intrinsics"]) == {"render", "shard", "train_intrinsics"}


@pytest.mark.parametrize("headline", [False, True])
def test_the_default_metrics_are_the_headline_file_once_declared(project, headline):
    dvc = yaml.safe_load((project / "dvc.yaml").read_text())
    metrics = [m for m in dvc["stages"]["evaluate"]["metrics"] if "metrics/headline.json" not in m]
    dvc["stages"]["evaluate"]["metrics"] = metrics + ([{"metrics/headline.json": {"cache": False}}] if headline else [])
    (project / "dvc.yaml").write_text(yaml.safe_dump(dvc))
    params = yaml.safe_load((project / "params.yaml").read_text())
    _, files, keys, targets = seeds._resolve(seeds._parser().parse_args([]), seeds.read_pipeline(project), params)
    assert targets == ["evaluate"]
    if headline:
        assert files == ["metrics/headline.json"] and keys == ["*"]
    else:
        assert files == ["metrics/evaluate.json"] and keys == list(seeds.DEFAULT_EVALUATE_KEYS)


def test_the_runs_interleave_seeds_and_pass_the_base_seed_as_null(project):
    runs = seeds.plan([42, 43], [seeds.Override("relight.lambda_ds", "0")], 42, ["evaluate"], "seeds")
    assert [(r.arm, r.seed) for r in runs] == [("default", 42), ("variant", 42), ("default", 43), ("variant", 43)]
    assert runs[0].overrides == ["base.train_seed=null"]
    assert runs[3].overrides == ["base.train_seed=43", "relight.lambda_ds=0"]
    assert runs[3].params["relight"]["lambda_ds"] == 0 and runs[3].params["base"]["train_seed"] == 43
    assert runs[0].params == yaml.safe_load((project / "params.yaml").read_text())  # the workspace's own run
    assert len({r.name for r in runs}) == 4 and runs[1].name.startswith("seeds-variant-s42-")


def _lock(train_seed, models="m1", pred_dep="m1"):
    return {
        "shard": {"outs": [{"path": "data/shards", "md5": "s1.dir"}]},
        "train": {
            "deps": [{"path": "data/shards", "md5": "s1.dir"}, {"path": "train.py", "md5": "c1"}],
            "params": {"params.yaml": {"base.train_seed": train_seed, "train": {"lr": 1}}},
            "outs": [{"path": "models", "md5": models}],
        },
        "infer": {
            "deps": [{"path": "models", "md5": pred_dep}],
            "params": {"params.yaml": {"base.train_seed": train_seed}},
            "outs": [{"path": "pred", "md5": "p1"}],
        },
    }


DECLARED = {"shard": [], "train": ["base.train_seed", "train"], "infer": ["base.train_seed"]}


def test_a_lock_is_consistent_only_with_the_params_and_hashes_of_the_run():
    params = {"base": {"train_seed": 7}, "train": {"lr": 1}}
    stages = ["shard", "train", "infer"]
    assert seeds.lock_consistent(_lock(7), params, stages, DECLARED)
    assert not seeds.lock_consistent(_lock(None), params, stages, DECLARED)  # another seed
    assert not seeds.lock_consistent(_lock(7), {**params, "train": {"lr": 2}}, stages, DECLARED)  # a whole section
    # infer's entry left from the baseline: it read other weights than this run's train wrote
    assert not seeds.lock_consistent(_lock(7, models="m2"), params, stages, DECLARED)
    assert seeds.lock_consistent(_lock(7, models="m2"), params, ["shard", "train"], DECLARED)  # not asked for
    assert not seeds.lock_consistent(_lock(7), params, [*stages, "evaluate"], {**DECLARED, "evaluate": []})
    # dvc.yaml declares a key the entry never recorded (a lock older than the key)
    assert not seeds.lock_consistent(_lock(7), params, stages, {**DECLARED, "infer": ["base.train_seed", "x"]})


def test_the_console_script_is_the_command():
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    module, _, name = scripts["pilight-seeds"].partition(":")
    assert getattr(importlib.import_module(module), name) is seeds.main

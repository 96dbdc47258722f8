"""Claims over seeds: run the pipeline for several training seeds, for the default and for a variant,
on the same renders and shards, and print each metric's mean +- sd per arm and the paired difference
(variant - default, paired by seed) with its 95% t-interval.

    pilight-seeds                                                    # the default over seeds 42 43 44
    pilight-seeds -S relight.lambda_ds=0 -S relight.lambda_ps=0      # default against a variant
    pilight-seeds -S relight.lambda_ds=0 --seeds 42 43 44 45 --json /tmp/no_ds.json
    pilight-seeds --target train_intrinsics --metrics-file dvclive/intrinsics/metrics.json --keys final_loss
    python -m pilight.seeds ...                                      # the same

Run it in the project (the folder of dvc.yaml, or below it). Every (arm, seed) is one named DVC
experiment, run with DVC's own machinery, one at a time:

    dvc exp run --temp -n seeds-<arm>-s<seed>-<hash> -S base.train_seed=<seed> [-S <override> ...] <target>

`base.train_seed` seeds every stage after the shards; `base.seed` (which seeds the renders and
shards) is never changed, so every run checks the same renders and shards out of the DVC cache.
A seed equal to `base.seed` is passed as `base.train_seed=null` (the same seed), so the default arm's
run for it is the workspace's own pipeline and skips whatever dvc.lock already holds. The results are
read back with `dvc exp show --json`.

Before anything runs: every -S key must exist in params.yaml and must not be read by the render or
shard stages (they would change the data the arms share), and every run's params must validate;
otherwise exit 2. Then, if `dvc status` finds the render and shard stages out of date, they are
reproduced once in the workspace (`dvc repro render shard`), and dvc.lock must be tracked by git
(experiments start from git's dvc.lock; an untracked one would make every run render again).

A run already present is reused, not rerun: a finished experiment of the same baseline commit (by any
name, run by this command or by hand) with the same params.yaml and the metrics files asked for, no
code difference to the workspace in the stages' dependencies and dvc.yaml (`git diff`), the
workspace's renders and shards, and a dvc.lock whose entries for the stages wanted are results of
those params (not entries left from the baseline by a run with a nearer target). DVC's run cache
cannot do this for the training stages: their persistent checkpoints and dvclive outputs make them
ineligible (dvc/stage/cache.py). Each run's DVC output goes to logs/seeds/<experiment>.log.

Metrics: --metrics-file (default metrics/headline.json when a stage declares it, all of its numeric
keys; else metrics/evaluate.json filtered by DEFAULT_EVALUATE_KEYS) and --keys (fnmatch patterns on
the flattened, dotted keys). --target defaults to the stages that write the metrics files.
"""

from __future__ import annotations

import argparse
import dataclasses
import difflib
import fnmatch
import hashlib
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

PARAMS = "params.yaml"
HEADLINE = "metrics/headline.json"
EVALUATE = "metrics/evaluate.json"
SEED_KEY = "base.train_seed"
DEFAULT_SEEDS = (42, 43, 44)
# metrics/evaluate.json's figures of the trained models, until metrics/headline.json exists
DEFAULT_EVALUATE_KEYS = (
    "intrinsics.model.albedo_psnr",
    "intrinsics.model.normal_mean_deg",
    "intrinsics.model.roughness_mae",
    "intrinsics.model.metallic_mae",
    "relight.absolute.model.psnr",
    "relight.relative.model.psnr",
    "relight.relative.model.change_r2_mask",
    "relight.scale_invariant.model.psnr",
)
ARMS = ("default", "variant")
MESSAGE = "pilight-seeds"  # the experiments' commit message: "pilight-seeds: <arm> seed <s>; targets: <stages>"


class UsageError(ValueError):
    """A bad command line or params value, found before anything runs: exit 2."""


class RunError(RuntimeError):
    """A DVC command failed or the project is not ready: exit 1."""


# ---------------------------------------------------------------------------------------------------
# Statistics


def t_quantile(df: int, confidence: float = 0.95) -> float:
    """The two-sided Student-t quantile: P(|T| <= t) = confidence for ``df`` degrees of freedom.

    Exact for integer df through the closed form of the t distribution's CDF (Abramowitz & Stegun
    26.7.3-4), inverted by bisection."""
    if df < 1:
        raise ValueError(f"df must be >= 1, got {df}")

    def central(t: float) -> float:  # P(|T| <= t)
        theta = math.atan(t / math.sqrt(df))
        c2, s = math.cos(theta) ** 2, math.sin(theta)
        if df % 2:  # odd: (2/pi)(theta + sin cos (1 + 2/3 cos^2 + 2*4/(3*5) cos^4 + ...))
            term, acc = 1.0, 0.0
            for k in range(1, (df - 1) // 2 + 1):
                acc += term
                term *= c2 * (2 * k) / (2 * k + 1)
            return 2 / math.pi * (theta + (s * math.cos(theta) * acc if df > 1 else 0.0))
        term, acc = 1.0, 0.0  # even: sin (1 + 1/2 cos^2 + 1*3/(2*4) cos^4 + ...)
        for k in range(1, df // 2 + 1):
            acc += term
            term *= c2 * (2 * k - 1) / (2 * k)
        return s * acc

    lo, hi = 0.0, 1.0
    while central(hi) < confidence:
        hi *= 2
    for _ in range(200):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if central(mid) < confidence else (lo, mid)
    return (lo + hi) / 2


def mean_sd(values: Sequence[float]) -> dict[str, Any]:
    """n, mean and the sample sd (n - 1; None for one value)."""
    n = len(values)
    return {
        "n": n,
        "mean": statistics.fmean(values),
        "sd": statistics.stdev(values) if n > 1 else None,
    }


def paired_difference(default: dict[int, float], variant: dict[int, float], confidence: float = 0.95) -> dict:
    """variant - default paired by seed (the seeds both hold): mean, sd and the t-interval of the mean."""
    seeds = sorted(set(default) & set(variant))
    diffs = [variant[s] - default[s] for s in seeds]
    out = {"seeds": seeds, "values": diffs, **mean_sd(diffs), "ci95": None}
    if len(diffs) > 1:
        half = t_quantile(len(diffs) - 1, confidence) * out["sd"] / math.sqrt(len(diffs))
        out["ci95"] = [out["mean"] - half, out["mean"] + half]
    return out


def summarise(values: dict[str, dict[str, dict[int, float]]]) -> dict[str, dict]:
    """values[metric][arm][seed] -> per metric: each arm's values, mean and sd, and (with both arms) the
    paired difference."""
    out = {}
    for metric, arms in values.items():
        row: dict[str, Any] = {
            arm: {
                "values": [by_seed[s] for s in sorted(by_seed)],
                "seeds": sorted(by_seed),
                **mean_sd(list(by_seed.values())),
            }
            for arm, by_seed in arms.items()
        }
        if "default" in arms and "variant" in arms:
            row["difference"] = paired_difference(arms["default"], arms["variant"])
        out[metric] = row
    return out


# ---------------------------------------------------------------------------------------------------
# Overrides (DVC's -S: [params.yaml:]key=value)


@dataclasses.dataclass(frozen=True)
class Override:
    key: str
    value: str

    def __str__(self) -> str:
        return f"{self.key}={self.value}"


def parse_override(text: str, params: dict) -> Override:
    """``key=value`` of a key params.yaml holds (``params.yaml:`` may prefix it); else UsageError."""
    spec = text
    if ":" in spec.split("=", 1)[0]:
        file, spec = spec.split(":", 1)
        if file != PARAMS:
            raise UsageError(f"-S {text}: only {PARAMS} is varied here, not {file}")
    key, eq, value = spec.partition("=")
    key = key.strip()
    if not eq or not key:
        raise UsageError(f"-S {text}: want key=value (a dotted key of {PARAMS})")
    if key[0] in "+~":
        raise UsageError(f"-S {text}: only keys {PARAMS} already holds can be overridden (no + or ~)")
    node: Any = params
    for i, part in enumerate(key.split(".")):
        if not isinstance(node, dict) or part not in node:
            where = ".".join(key.split(".")[:i]) or PARAMS
            known = list(node) if isinstance(node, dict) else []
            close = difflib.get_close_matches(part, known, n=3)
            hint = (
                f"; did you mean {', '.join(close)}?"
                if close
                else (f"; {where} has: {', '.join(known)}" if known else "")
            )
            raise UsageError(f"-S {text}: {PARAMS} has no key {key!r}{hint}")
        node = node[part]
    return Override(key, value)


def _touches(key: str, declared: str) -> bool:
    """An override of ``key`` changes the declared params dep ``declared`` (same key, parent or child)."""
    return key == declared or key.startswith(declared + ".") or declared.startswith(key + ".")


# ---------------------------------------------------------------------------------------------------
# The project, through DVC


@dataclasses.dataclass
class Pipeline:
    stages: list[str]
    params: dict[str, list[str]]  # stage -> its params.yaml keys
    metrics: dict[str, str]  # metrics file -> the stage that writes it
    upstream: dict[str, set[str]]  # stage -> itself and every stage it depends on
    code: dict[str, list[str]]  # stage -> its dependencies that no stage writes (code, configs)
    outs: dict[str, list[str]]

    @property
    def seeded(self) -> list[str]:
        return [s for s in self.stages if SEED_KEY in self.params[s]]

    @property
    def data_stages(self) -> list[str]:
        """The stages the seeded ones depend on that do not read the training seed: render, shard."""
        ups = set().union(*(self.upstream[s] for s in self.seeded)) if self.seeded else set()
        return [s for s in self.stages if s in ups and s not in self.seeded]

    def run_stages(self, targets: Sequence[str]) -> set[str]:
        return set().union(*(self.upstream[t] for t in targets))


def read_pipeline(root: Path) -> Pipeline:
    from dvc.dependency.param import ParamsDependency
    from dvc.repo import Repo

    with Repo(str(root)) as repo:
        stages = list(repo.index.stages)
        names = [s.addressing for s in stages]
        params, metrics, outs, deps = {}, {}, {}, {}
        for s in stages:
            params[s.addressing] = [
                k for d in s.deps if isinstance(d, ParamsDependency) and d.def_path == PARAMS for k in d.params
            ]
            deps[s.addressing] = [d.def_path for d in s.deps if not isinstance(d, ParamsDependency)]
            outs[s.addressing] = [o.def_path for o in s.outs]
            metrics.update({o.def_path: s.addressing for o in s.outs if o.metric})
        upstream = {n: {s.addressing for s in repo.stage.collect(n, with_deps=True)} for n in names}
    written = {o for os_ in outs.values() for o in os_}
    code = {n: [d for d in deps[n] if d not in written] for n in names}
    return Pipeline(names, params, metrics, upstream, code, outs)


def _dvc(*args: str, log: Path | None = None, check: bool = True) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "dvc", *args]
    if log is None:
        r = subprocess.run(cmd, capture_output=True, text=True)
    else:
        with log.open("w") as f:
            r = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, text=True)
    if check and r.returncode != 0:
        detail = log.read_text()[-3000:] if log is not None else (r.stdout + r.stderr)[-3000:]
        raise RunError(f"`dvc {' '.join(args)}` failed (exit {r.returncode}):\n{detail}")
    return r


def _git(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["git", *args], capture_output=True, text=True)


def _jsonable(x: Any) -> Any:
    return json.loads(json.dumps(x))


def desired_params(overrides: Sequence[str]) -> dict:
    """params.yaml as `dvc exp run -S` writes it for the experiment: DVC's own override code on a copy."""
    from dvc.utils.hydra import apply_overrides
    from dvc.utils.serialize import load_yaml

    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d) / PARAMS
        shutil.copy(PARAMS, tmp)
        if overrides:
            apply_overrides(str(tmp), list(overrides))
        return _jsonable(load_yaml(str(tmp)))


@dataclasses.dataclass
class Run:
    arm: str
    seed: int
    overrides: list[str]  # every -S of this run, base.train_seed first
    params: dict
    name: str
    experiment: str | None = None  # the experiment that holds the results (reused or run)
    rev: str | None = None
    reused: bool = False
    seconds: float | None = None


def plan(
    seeds: Sequence[int], variant: Sequence[Override], base_seed: int, targets: Sequence[str], prefix: str
) -> list[Run]:
    """Every (seed, arm), interleaved by seed so pairs complete early; params as DVC will write them."""
    from pilight.params import ParamsError, validate_sections

    runs = []
    for seed in seeds:
        for arm in ARMS if variant else ARMS[:1]:
            seed_value = "null" if seed == base_seed else str(seed)  # null = base.seed: the same seed
            overrides = [f"{SEED_KEY}={seed_value}", *(str(o) for o in (variant if arm == "variant" else ()))]
            try:
                params = desired_params(overrides)
                validate_sections(params, f"{PARAMS} with -S {' -S '.join(overrides)}")
            except ParamsError as exc:
                raise UsageError(str(exc)) from None
            except Exception as exc:  # DVC's Hydra errors: a value its grammar refuses
                raise UsageError(f"-S {' -S '.join(overrides)}: {exc}") from None
            for section in ("intrinsics", "relight"):  # a pinned stage would not vary with --seeds
                pinned = params.get(section, {}).get("train", {}).get("seed")
                if pinned is not None:
                    raise UsageError(
                        f"{PARAMS} with -S {' -S '.join(overrides)}: {section}.train.seed "
                        f"is {pinned}, which pins that stage's training seed, so --seeds would not vary it; set it "
                        "to null"
                    )
            digest = hashlib.sha1(json.dumps([params, sorted(targets)], sort_keys=True).encode()).hexdigest()[:7]
            runs.append(Run(arm, seed, overrides, params, f"{prefix}-{arm}-s{seed}-{digest}"))
    return runs


def show_experiments(baseline: str) -> list[dict]:
    """The finished experiments of ``baseline`` as `dvc exp show --json` gives them: {name, rev, data}."""
    shown = json.loads(_dvc("exp", "show", "--json", "--rev", baseline).stdout)
    found = []
    for entry in shown:
        if entry.get("rev") == "workspace":
            continue
        for exp in entry.get("experiments") or []:
            revs = exp.get("revs") or []
            if exp.get("executor") or not revs or revs[0].get("error"):  # queued, running or failed
                continue
            found.append(
                {"name": exp.get("name") or revs[0].get("name"), "rev": revs[0]["rev"], "data": revs[0]["data"]}
            )
    return found


def _metrics_ok(data: dict, files: Sequence[str]) -> bool:
    return all("data" in ((data.get("metrics") or {}).get(f) or {}) for f in files)


_MISSING = object()


def _get(params: dict, dotted: str) -> Any:
    node: Any = params
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            return _MISSING
        node = node[part]
    return node


def _lock_stages(text: str) -> dict:
    from dvc.utils.serialize import parse_yaml

    return (parse_yaml(text, "dvc.lock") or {}).get("stages") or {}


def _written(lock: dict) -> dict[str, str | None]:
    return {o["path"]: o.get("md5") for e in lock.values() for o in e.get("outs") or []}


def lock_consistent(lock: dict, params: dict, stages: Sequence[str], declared: dict[str, list[str]]) -> bool:
    """Whether dvc.lock's entries of ``stages`` are results of these inputs, not entries a run left as
    its baseline had them: each records the params keys dvc.yaml declares (``declared``) at the values
    ``params`` hold, and each dependency another stage writes at the hash that stage's entry records."""
    written = _written(lock)
    for s in stages:
        entry = lock.get(s)
        if entry is None:
            return False
        recorded = (entry.get("params") or {}).get(PARAMS) or {}
        if set(recorded) != set(declared[s]) or any(_jsonable(v) != _get(params, k) for k, v in recorded.items()):
            return False
        if any(d["path"] in written and d.get("md5") != written[d["path"]] for d in entry.get("deps") or []):
            return False
    return True


@dataclasses.dataclass
class Reuse:
    """What an experiment must match to stand for a run (see _reusable)."""

    pipeline: Pipeline
    targets: list[str]
    files: list[str]
    workspace_lock: dict

    def __post_init__(self):
        self.stages = sorted(self.pipeline.run_stages(self.targets))
        self.data_outs = [o for s in self.pipeline.data_stages for o in self.pipeline.outs[s]]
        self.code = sorted({c for s in self.stages for c in self.pipeline.code[s]} | {"dvc.yaml"})


def _message(run: Run, targets: Sequence[str]) -> str:
    return f"{MESSAGE}: {run.arm} seed {run.seed}; targets: {' '.join(targets)}"


def _reusable(exp: dict, run: Run, reuse: Reuse) -> bool:
    """An experiment stands for ``run`` when it has the run's params.yaml and the metrics files, the
    workspace's code in the stages' dependencies (`git diff`: tracked content, so no __pycache__), the
    workspace's renders and shards, a dvc.lock whose entries are results of these params
    (lock_consistent), and, when this command ran it, targets that cover the stages wanted."""
    data, rev = exp["data"], exp["rev"]
    if _jsonable(((data.get("params") or {}).get(PARAMS) or {}).get("data")) != run.params:
        return False
    if not _metrics_ok(data, reuse.files):
        return False
    if _git("diff", "--quiet", rev, "--", *reuse.code).returncode != 0:
        return False
    message = _git("log", "-1", "--format=%B", rev).stdout.strip()
    if message.startswith(f"{MESSAGE}:") and "; targets: " in message:
        theirs = message.split("; targets: ", 1)[1].split()
        if not set(theirs) <= set(reuse.pipeline.stages) or not set(reuse.stages) <= reuse.pipeline.run_stages(theirs):
            return False
    shown = _git("show", f"{rev}:dvc.lock")
    if shown.returncode != 0:
        return False
    lock = _lock_stages(shown.stdout)
    mine, theirs_out = _written(reuse.workspace_lock), _written(lock)
    if any(mine.get(o) is None or theirs_out.get(o) != mine[o] for o in reuse.data_outs):
        return False
    return lock_consistent(lock, run.params, reuse.stages, reuse.pipeline.params)


def _flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(d, dict):
        return {prefix: d}
    out = {}
    for k, v in d.items():
        out.update(_flatten(v, f"{prefix}{k}."))
    return {k.rstrip("."): v for k, v in out.items()}


def collect_values(
    runs: Sequence[Run], data_by_rev: dict[str, dict], files: Sequence[str], patterns: Sequence[str]
) -> tuple[dict[str, dict[str, dict[int, float]]], list[str]]:
    """values[metric][arm][seed] of the numeric keys matching ``patterns`` that every run holds, and
    warnings (a pattern matching nothing, a key some runs lack)."""
    values: dict[str, dict[str, dict[int, float]]] = {}
    seen: dict[str, int] = {}
    warnings = []
    label = (lambda f, k: k) if len(files) == 1 else (lambda f, k: f"{f}:{k}")
    matched: set[str] = set()
    for f in files:
        for run in runs:
            flat = _flatten(data_by_rev[run.rev]["metrics"][f]["data"])
            for k, v in flat.items():
                if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                    continue
                if not any(fnmatch.fnmatchcase(k, p) for p in patterns):
                    continue
                matched.add(k)
                m = label(f, k)
                values.setdefault(m, {}).setdefault(run.arm, {})[run.seed] = float(v)
                seen[m] = seen.get(m, 0) + 1
    for p in patterns:
        if not any(fnmatch.fnmatchcase(k, p) for k in matched):
            warnings.append(f"no numeric key of {', '.join(files)} matches {p!r}")
    for m in [m for m, n in seen.items() if n < len(runs)]:
        warnings.append(f"{m}: only {seen[m]} of {len(runs)} runs hold it; left out")
        del values[m]
    return values, warnings


# ---------------------------------------------------------------------------------------------------
# Printing


def _g(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.4g}"


def format_table(summary: dict[str, dict], seeds: Sequence[int]) -> str:
    both = any("difference" in row for row in summary.values())
    head = ["metric", "default (mean ± sd)"] + (["variant (mean ± sd)", "variant - default", "95% CI"] if both else [])
    rows = [head]
    for metric, row in summary.items():
        cells = [metric, f"{_g(row['default']['mean'])} ± {_g(row['default']['sd'])}"]
        if both:
            d = row["difference"]
            ci = "n/a" if d["ci95"] is None else f"[{d['ci95'][0]:+.4g}, {d['ci95'][1]:+.4g}]"
            cells += [
                f"{_g(row['variant']['mean'])} ± {_g(row['variant']['sd'])}",
                f"{d['mean']:+.4g} ± {_g(d['sd'])}",
                ci,
            ]
        rows.append(cells)
    widths = [max(len(r[i]) for r in rows) for i in range(len(head))]
    lines = ["  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths))) for r in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    note = f"{len(seeds)} seeds ({' '.join(map(str, seeds))}); sd over seeds; difference paired by seed, t-interval"
    return "\n".join([*lines, note])


def _duration(s: float) -> str:
    return f"{s:.0f} s" if s < 90 else f"{s / 60:.1f} min" if s < 5400 else f"{s / 3600:.1f} h"


# ---------------------------------------------------------------------------------------------------
# The command


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="pilight-seeds", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "-S",
        "--set-param",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="the variant, as `dvc exp run -S` overrides (repeat); none: the default alone",
    )
    ap.add_argument(
        "--seeds", type=int, nargs="+", default=list(DEFAULT_SEEDS), help="training seeds (default 42 43 44)"
    )
    ap.add_argument(
        "--metrics-file",
        action="append",
        default=None,
        metavar="FILE",
        help=f"a metrics file of dvc.yaml to summarise (repeat; default {HEADLINE} when declared, else {EVALUATE})",
    )
    ap.add_argument(
        "--keys",
        nargs="+",
        default=None,
        metavar="PATTERN",
        help="fnmatch patterns on the flattened dotted keys (default: all, or DEFAULT_EVALUATE_KEYS for evaluate.json)",
    )
    ap.add_argument(
        "--target",
        nargs="+",
        default=None,
        metavar="STAGE",
        help="the stage(s) to run up to (default: the stages that write the metrics files)",
    )
    ap.add_argument("--json", type=Path, default=None, help="also write the summary (runs, values, statistics) here")
    ap.add_argument("--prefix", default="seeds", help="experiment names: <prefix>-<arm>-s<seed>-<params hash>")
    return ap


def _resolve(args, pipeline: Pipeline, params: dict) -> tuple[list[Override], list[str], list[str], list[str]]:
    """Overrides, metrics files, key patterns and targets, checked; UsageError on anything wrong."""
    if not pipeline.seeded:
        raise UsageError(f"no stage of dvc.yaml declares {SEED_KEY}: the training seed cannot be varied")
    variant = [parse_override(o, params) for o in args.overrides]
    for o in variant:
        if _touches(o.key, SEED_KEY) or _touches(o.key, "base.seed"):
            raise UsageError(f"-S {o}: the seeds are this command's to set (--seeds)")
        for stage in pipeline.data_stages:
            hit = [p for p in pipeline.params[stage] if _touches(o.key, p)]
            if hit:
                raise UsageError(
                    f"-S {o}: stage {stage!r} reads {hit[0]}, so the arms would not share the renders and shards"
                )
    if len(set(args.seeds)) != len(args.seeds) or any(s < 0 for s in args.seeds):
        raise UsageError(f"--seeds {' '.join(map(str, args.seeds))}: want distinct seeds >= 0")
    files = args.metrics_file or [HEADLINE if HEADLINE in pipeline.metrics else EVALUATE]
    patterns = args.keys or (list(DEFAULT_EVALUATE_KEYS) if files == [EVALUATE] else ["*"])
    for f in files:
        if f not in pipeline.metrics:
            raise UsageError(
                f"--metrics-file {f}: no stage of dvc.yaml declares it a metric ({', '.join(pipeline.metrics)})"
            )
    targets = args.target or sorted({pipeline.metrics[f] for f in files}, key=pipeline.stages.index)
    for t in targets:
        if t not in pipeline.stages:
            raise UsageError(f"--target {t}: not a stage of dvc.yaml ({', '.join(pipeline.stages)})")
    runs = pipeline.run_stages(targets)
    for f in files:
        if pipeline.metrics[f] not in runs:
            raise UsageError(
                f"{f} is written by stage {pipeline.metrics[f]!r}, which --target {' '.join(targets)} does not run"
            )
    return variant, files, patterns, targets


def _prepare_data(pipeline: Pipeline) -> None:
    """The render and shard stages up to date in the workspace and dvc.lock in git, so that every
    experiment checks the same renders and shards out of the cache."""
    from dvc.repo import Repo

    with Repo(".") as repo:
        stale = repo.status(targets=pipeline.data_stages, with_deps=True)
    if stale:
        print(
            f"seeds: {', '.join(stale)} out of date; once, in the workspace: dvc repro {' '.join(pipeline.data_stages)}"
        )
        _dvc("repro", *pipeline.data_stages)
    if _git("ls-files", "--error-unmatch", "dvc.lock").returncode != 0:
        raise RunError(
            "dvc.lock is not tracked by git, so the experiments would not see the renders and shards and "
            "would render again: `git add dvc.lock` (and commit it) first"
        )


def execute(args) -> int:
    from dvc.repo import Repo
    from dvc.utils.serialize import load_yaml

    try:
        root = Path(Repo.find_root())
    except Exception as exc:
        raise UsageError(f"not in a DVC project: {exc}") from None
    os.chdir(root)
    params = _jsonable(load_yaml(PARAMS))
    pipeline = read_pipeline(root)
    variant, files, patterns, targets = _resolve(args, pipeline, params)
    base_seed = int(params["base"]["seed"])
    runs = plan(args.seeds, variant, base_seed, targets, args.prefix)

    _prepare_data(pipeline)
    baseline = _git("rev-parse", "HEAD").stdout.strip()
    existing = show_experiments(baseline)
    reuse = Reuse(pipeline, targets, files, _lock_stages(Path("dvc.lock").read_text()))
    logs = Path("logs/seeds")
    logs.mkdir(parents=True, exist_ok=True)

    print(
        f"seeds: {len(runs)} runs ({'default and variant' if variant else 'default'} x seeds {' '.join(map(str, args.seeds))}) "
        f"up to {' '.join(targets)}; variant: {' '.join(f'-S {o}' for o in variant) or 'none'}"
    )
    for run in runs:
        hit = next((e for e in existing if _reusable(e, run, reuse)), None)
        if hit is not None:
            run.experiment, run.rev, run.reused = hit["name"], hit["rev"], True
    spent: list[float] = []
    baselines = {baseline}
    for i, run in enumerate(runs, 1):
        tag = f"[{i}/{len(runs)}] {run.arm} seed {run.seed}"
        if run.reused:
            print(f"{tag}: reused experiment {run.experiment} ({run.rev[:7]})", flush=True)
            continue
        left = sum(1 for r in runs[i - 1 :] if not r.reused)
        eta = (
            f"ETA {_duration(statistics.fmean(spent) * left)} for {left} run(s)" if spent else "ETA after the first run"
        )
        print(
            f"{tag}: dvc exp run --temp -n {run.name} {' '.join(f'-S {o}' for o in run.overrides)} {' '.join(targets)} ({eta})",
            flush=True,
        )
        if any(e["name"] == run.name for e in existing):  # same name, not reusable (other code or data)
            _dvc("exp", "remove", run.name)
        t0 = time.perf_counter()
        log = logs / f"{run.name}.log"
        sets = [a for o in run.overrides for a in ("-S", o)]
        cmd = ["exp", "run", "--temp", "-n", run.name, "-m", _message(run, targets), *sets, *targets]
        try:
            _dvc(*cmd, log=log)
        except RunError as exc:
            raise RunError(
                f"{tag}: {exc}\n(the whole log: {log}; finished runs are reused when the command runs again)"
            ) from None
        run.seconds = time.perf_counter() - t0
        spent.append(run.seconds)
        run.experiment = run.name
        head = _git("rev-parse", "HEAD").stdout.strip()
        if head not in baselines:
            print(f"seeds: warning: HEAD moved to {head[:7]} during the runs; later runs use its code", file=sys.stderr)
            baselines.add(head)
        print(f"{tag}: done in {_duration(run.seconds)} -> {run.name} (log: {log})", flush=True)

    data_by_rev: dict[str, dict] = {}
    for b in baselines:
        for e in show_experiments(b):
            data_by_rev[e["rev"]] = e["data"]
            for run in runs:
                if run.rev is None and run.experiment == e["name"]:
                    run.rev = e["rev"]
    missing = [r for r in runs if r.rev is None or not _metrics_ok(data_by_rev.get(r.rev, {}), files)]
    if missing:
        raise RunError(
            "`dvc exp show --json` lacks the results of "
            + ", ".join(f"{r.experiment} ({', '.join(files)})" for r in missing)
        )
    values, warnings = collect_values(runs, data_by_rev, files, patterns)
    for w in warnings:
        print(f"seeds: warning: {w}", file=sys.stderr)
    if not values:
        raise RunError(f"no numeric metric of {', '.join(files)} matches {' '.join(patterns)}")
    summary = summarise(values)
    print()
    print(format_table(summary, args.seeds))
    if args.json is not None:
        doc = {
            "seeds": list(args.seeds),
            "variant": [str(o) for o in variant],
            "targets": targets,
            "metrics_files": files,
            "keys": patterns,
            "runs": [{k: v for k, v in dataclasses.asdict(r).items() if k != "params"} for r in runs],
            "metrics": summary,
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(doc, indent=2) + "\n")
        print(f"summary -> {args.json}")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.json is not None:
        args.json = args.json.resolve()  # before the command moves to the project's root
    try:
        return execute(args)
    except UsageError as exc:
        print(f"pilight-seeds: {exc}", file=sys.stderr)
        return 2
    except RunError as exc:
        print(f"pilight-seeds: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())

"""The `pilight` console script: decompose and relight your own photos (a thin layer on
``pilight.pipeline``).

    pilight decompose photo.jpg -o out/                       albedo, normal, roughness, metallic
    pilight relight photos/ -o out/ --light left --light right relit image, D, S, contact sheet
    pilight relight 'shots/*.png' -o out/ --hdri studio.exr --rotate 0 --rotate 90
    pilight ball -o balls/ --azimuth 45 --elevation 30         see a light before using it

Photos: PNG / JPEG / TIFF (sRGB, 8 or 16 bit, EXIF orientation, alpha = mask, gray) and EXR / HDR
(linear); files, folders (their photos, not recursive) or quoted globs. Outputs go to
OUT/<photo name>/ (relight: OUT/<photo name>/<light>/), EXR linear plus PNG previews. A light's
folder is written under a temporary name and renamed into place whole, so it appears complete or not
at all; a killed run's temporaries are swept by the next one. Outputs already complete are skipped
(--overwrite redoes them).

Models: every file that decides what they compute (weights, config.json, pipeline.json) is checked
against its folder's checksums.json; a folder without one (made by hand) loads only with
--trust-unverified, which is said on stderr.

Light directions are in camera space: azimuth 0 = from the camera, +90 = from the picture's right,
-90 = from its left, 180 = from behind the subject; elevation 0 = level with the camera, +90 = from
straight above. Named lights: left (-90, 30), right (90, 30), top (0, 90), bottom (0, -90),
front (0, 0) as (azimuth, elevation). An HDRI is a 2:1 lat-long panorama whose centre lies straight
ahead of the camera; --rotate +DEG turns it clockwise seen from above (what was DEG to the left
comes from straight ahead).

Several processes (one per GPU, or CPU processes) share a folder of photos when launched by
`accelerate launch` or `torchrun`: each takes its own contiguous share of the photos (accelerate's
split_between_processes), so every output is written by exactly one process, and a rerun skips
what is complete:

    accelerate launch --num_processes 8 -m pilight.cli relight photos/ -o out/ --light left
    OMP_NUM_THREADS=1 torchrun --standalone --nproc_per_node 2 -m pilight.cli decompose photos/ -o out/

Exit status: 0 done, 1 bad input, model or output folder (nothing written), 2 bad options.
"""

from __future__ import annotations

import argparse
import glob
import math
import os
import re
import shutil
import socket
import sys
import tempfile
import warnings
from contextlib import contextmanager
from pathlib import Path

from pilight.failure import CommandFailure
from pilight.params import DOMAINS

CONTACT_HEIGHT = 512  # contact sheets are at most this tall, so a 24-megapixel photo gives a viewable PNG


# --- arguments ---------------------------------------------------------------------------------
def _light_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("light (repeat any of them: one output per light)")
    g.add_argument(
        "--light",
        action="append",
        default=[],
        metavar="NAME",
        help="a named direction: left | right | top | bottom | front",
    )
    g.add_argument(
        "--azimuth",
        action="append",
        type=float,
        default=[],
        metavar="DEG",
        help="direction toward the light, camera space: 0 = from the camera, +90 = from the right, "
        "-90 = from the left, 180 = from behind the subject (pair with --elevation)",
    )
    g.add_argument(
        "--elevation",
        action="append",
        type=float,
        default=[],
        metavar="DEG",
        help="0 = level with the camera, +90 = from straight above, -90 = from below "
        "(one for all --azimuth values, or one each)",
    )
    g.add_argument(
        "--ball",
        action="append",
        type=Path,
        default=[],
        metavar="FILE",
        help="a gray light ball (rendered or photographed), cropped square, touching the borders",
    )
    g.add_argument(
        "--hdri",
        action="append",
        type=Path,
        default=[],
        metavar="FILE",
        help="an equirectangular 2:1 panorama (.exr / .hdr linear; PNG/JPEG sRGB); its centre is "
        "straight ahead of the camera",
    )
    g.add_argument(
        "--rotate",
        action="append",
        type=float,
        default=[],
        metavar="DEG",
        help="turn the HDRI about the vertical axis, clockwise seen from above; several values with one "
        "--hdri give one light each",
    )
    g.add_argument(
        "--intensity",
        type=float,
        default=1.0,
        help="k: each light's level is k times the photo's own estimated light (1 keeps the photo's exposure); "
        "with --absolute it multiplies the light as made (1 = a directional light at the training data's "
        "typical level, or a ball/HDRI as stored)",
    )


def _model_options(p: argparse.ArgumentParser, stage: str) -> None:
    what = (
        "stage 1; defaults: params.yaml's infer_intrinsics"
        if stage == "intrinsics"
        else "stage 2; defaults: params.yaml's relight_infer (stage 1 runs with infer_intrinsics)"
    )
    g = p.add_argument_group(f"model and sampling ({what}, or a saved pipeline's pipeline.json)")
    g.add_argument(
        "--models",
        type=Path,
        default=Path("models"),
        help="folder with intrinsics/ and relight/ (default: models, where `dvc repro` puts them)",
    )
    g.add_argument(
        "--params",
        type=Path,
        default=Path("params.yaml"),
        help="params file for the defaults (ignored when it does not exist or --models holds pipeline.json)",
    )
    g.add_argument(
        "--resolution",
        type=int,
        default=None,
        metavar="PX",
        help="processing size of the longer side, rounded to the models' size multiple, aspect kept "
        "(default: render.resolution, the training size; 0 = the photo's own size). Outputs are "
        "always at the photo's size",
    )
    g.add_argument("--mode", choices=("ddim", "single_step"), default=None, help="sampler")
    g.add_argument("--steps", type=int, default=None, help="DDIM steps (implies --mode ddim)")
    g.add_argument("--cfg", type=float, default=None, help="classifier-free guidance scale")
    g.add_argument("--ensemble", type=int, default=None, help="noise draws averaged per output")
    g.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda", "mps"))
    g.add_argument(
        "--max-memory",
        type=float,
        default=None,
        metavar="GIB",
        help="refuse photos whose processing would need more (default: 80%% of RAM, or of GPU memory)",
    )
    g.add_argument(
        "--trust-unverified",
        action="store_true",
        help="load a models folder that has no checksums.json (made by hand): its files are used unverified, "
        "which is said on stderr. Without it such a folder is refused",
    )


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="pilight", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = ap.add_subparsers(dest="command", required=True)
    d = sub.add_parser(
        "decompose",
        help="albedo, normal, roughness, metallic of each photo",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=__doc__,
    )
    d.add_argument("photos", nargs="+", metavar="PHOTO", help="files, folders or quoted globs")
    d.add_argument("-o", "--out", type=Path, required=True, metavar="OUT")
    d.add_argument("--overwrite", action="store_true", help="redo outputs that are already complete")
    _model_options(d, "intrinsics")
    r = sub.add_parser(
        "relight",
        help="each photo under each light: relit image, D, S, contact sheet",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=__doc__,
    )
    r.add_argument("photos", nargs="+", metavar="PHOTO", help="files, folders or quoted globs")
    r.add_argument("-o", "--out", type=Path, required=True, metavar="OUT")
    r.add_argument("--overwrite", action="store_true", help="redo outputs that are already complete")
    _light_options(r)
    r.add_argument(
        "--absolute",
        action="store_true",
        help="the lights' intensity is absolute, not relative to the photo's own light (a calibrated plate, "
        "e.g. a gray ball photographed in the scene)",
    )
    r.add_argument(
        "--exposure",
        choices=("photo", "light"),
        default="photo",
        help="what --intensity 1 keeps (relative intensity): photo = the relit picture's mean luminance is k "
        "times the photo's (default, as a camera keeps its exposure); light = the light's level is k times the "
        "photo's estimated light, so a light from the side darkens the picture",
    )
    _model_options(r, "relight")
    b = sub.add_parser(
        "ball",
        help="write the light ball each light spec makes (no model needed)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=__doc__,
    )
    b.add_argument("-o", "--out", type=Path, required=True, metavar="OUT")
    b.add_argument("--size", type=int, default=256, help="ball image size in pixels")
    _light_options(b)
    a = sub.add_parser(
        "app",
        help="relight in the browser, the light following the pointer (the app extra: pip install -e '.[app]')",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=__doc__,
    )
    a.add_argument("--port", type=int, default=7860, help="port to serve on (default 7860)")
    a.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1: this machine only)")
    _model_options(a, "relight")
    pr = sub.add_parser(
        "profile",
        help="compose a profile overlay (e.g. profiles/paper.yaml) with params.yaml",
        description="Write BASE with PROFILE's keys over it, validated (pilight/profiles.py).",
    )
    pr.add_argument("profile", type=Path, metavar="PROFILE", help="the overlay: only the keys that differ")
    pr.add_argument("-o", "--out", type=Path, required=True, help="the composed params file (may be BASE itself)")
    pr.add_argument("--base", type=Path, default=Path("params.yaml"), help="default: params.yaml")
    pr.add_argument(
        "--no-check-paths",
        action="store_true",
        help="do not require the weight folders (codec, unet, CLIP, DINOv2 paths) to exist here",
    )
    return ap


# --- inputs and outputs --------------------------------------------------------------------------
def expand_inputs(items: list[str]) -> list[Path]:
    """Files as given, folders' photos (sorted), globs' matches (sorted); duplicates once."""
    from pilight.photo import PHOTO_SUFFIXES

    out: list[Path] = []
    for item in items:
        p = Path(item)
        if p.is_dir():
            found = sorted(f for f in p.iterdir() if f.is_file() and f.suffix.lower() in PHOTO_SUFFIXES)
            if not found:
                raise CommandFailure(f"{p}: folder holds no photos ({', '.join(PHOTO_SUFFIXES)})")
            out += found
        elif not p.exists() and glob.has_magic(item):
            found = sorted(Path(f) for f in glob.glob(item) if Path(f).is_file())
            if not found:
                raise CommandFailure(f"{item}: no file matches")
            out += found
        else:
            out.append(p)  # missing or unreadable files are reported by the header check, with the others
    seen, unique = set(), []
    for p in out:
        key = p.resolve()
        if key not in seen:
            seen.add(key)
            unique.append(p)
    return unique


def output_names(photos: list[Path]) -> dict[Path, str]:
    """Each photo's output folder name (its stem); two photos with one stem would overwrite each other."""
    by_name: dict[str, list[Path]] = {}
    for p in photos:
        by_name.setdefault(p.stem, []).append(p)
    clash = {n: ps for n, ps in by_name.items() if len(ps) > 1}
    if clash:
        n, ps = next(iter(clash.items()))
        raise CommandFailure(
            f"{', '.join(map(str, ps))}: these photos would all write OUT/{n}/; rename one, or run them "
            "with different -o folders"
        )
    return {p: p.stem for p in photos}


def check_writable(out: Path) -> None:
    """Fail now, not after minutes of work, when OUT cannot hold files. Nothing is created: OUT is made by
    the first output written, so a run refused later (a bad photo, a model) leaves no empty folder."""
    probe = out
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    try:
        if not probe.is_dir():
            raise NotADirectoryError(20, "Not a directory", str(probe))
        fd, tmp = tempfile.mkstemp(dir=probe, prefix=".pilight-write-test.")
        os.close(fd)
        os.unlink(tmp)
    except OSError as exc:
        raise CommandFailure(f"{out}: cannot write outputs there ({exc.strerror or exc})") from None


# Temporaries of this process: .<final name>.tmp-<host>-<pid>-<random> (and .old- for a folder being
# replaced), beside their final name. A killed run cannot remove its own; the next run on this host
# removes those of processes that no longer exist (``sweep_stale``), never a live process's.
_HOST = re.sub(r"[^A-Za-z0-9_]", "_", socket.gethostname())[:32] or "host"
_TEMP = re.compile(r"^\..+\.(?:tmp|old)-(?P<host>[A-Za-z0-9_]+)-(?P<pid>\d+)-[^/]*$")


def _tag(kind: str) -> str:
    return f"{kind}-{_HOST}-{os.getpid()}-"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def sweep_stale(folder: Path) -> list[Path]:
    """Remove the temporaries (``_TEMP``) in ``folder`` left by processes of this host that are gone; the
    paths removed."""
    removed = []
    if not folder.is_dir():
        return removed
    for p in sorted(folder.iterdir()):
        m = _TEMP.match(p.name)
        if m and m["host"] == _HOST and int(m["pid"]) != os.getpid() and not _alive(int(m["pid"])):
            shutil.rmtree(p, ignore_errors=True) if p.is_dir() and not p.is_symlink() else p.unlink(missing_ok=True)
            removed.append(p)
    return removed


def _swap_into_place(tmp: Path, final: Path) -> None:
    """Rename the folder ``tmp`` to ``final``; a ``final`` already there is first renamed aside (onto an empty
    temporary folder) and removed after, so at no moment does a partial folder carry the final name."""
    from pilight import atomic

    os.chmod(tmp, atomic.dir_mode())  # mkdtemp makes 0700 whatever the umask
    old = None
    if final.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{final.name}.{_tag('old')}", dir=final.parent))
        os.replace(final, old)  # a folder renamed onto an empty folder replaces it
    os.replace(tmp, final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def write_folder(final: Path, files: dict[str, object]) -> None:
    """``files`` ({file name: array}, written as ``write_group`` does) as the folder ``final``: written into
    a temporary sibling, then renamed into place whole. On any error the temporary is removed and
    ``final`` keeps what it held; an OSError names ``final``."""
    from pilight import atomic

    tmp = None
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.{_tag('tmp')}", dir=final.parent))
        write_group({tmp / name: arr for name, arr in files.items()})
        _swap_into_place(tmp, final)
    except BaseException as exc:
        atomic.abandon_folder(exc, tmp, final)


def write_into(folder: Path, files: dict[str, object]) -> None:
    """``files`` into an existing ``folder`` that holds other outputs (a photo's folder with its lights'):
    all written into a temporary folder inside it first, then renamed into place one by one (the renames
    take microseconds; a kill between them leaves a set ``_complete`` does not accept, redone next run)."""
    from pilight import atomic

    tmp = None
    try:
        tmp = Path(tempfile.mkdtemp(prefix=f".decompose.{_tag('tmp')}", dir=folder))
        write_group({tmp / name: arr for name, arr in files.items()})
        for name in files:
            os.replace(tmp / name, folder / name)
        tmp.rmdir()
    except BaseException as exc:
        atomic.abandon_folder(exc, tmp, folder)


def write_group(files: dict[Path, object]) -> None:
    """Write several files (EXR arrays or PNG uint8 arrays by suffix), each to a temporary, then
    renamed; if any fails, the ones already renamed are removed."""
    import numpy as np

    from pilight import atomic
    from pilight.data.exr import write_exr

    done: list[Path] = []
    try:
        for path, arr in files.items():
            if path.suffix == ".exr":
                write_exr(path, np.asarray(arr, np.float32), half=True)
            else:  # zlib level 1: 3-4x faster than PIL's 6 for 10-15 % more bytes (photos compress little)
                atomic.write_png(path, arr, compress_level=1)
            done.append(path)
    except BaseException:
        for p in done:
            p.unlink(missing_ok=True)
        raise


def _complete(paths) -> bool:
    return all(p.is_file() for p in paths)


def decompose_files(folder: Path) -> list[Path]:
    return [folder / f"{m}.{ext}" for m in DOMAINS for ext in ("exr", "png")]


def relight_files(folder: Path, branches) -> list[Path]:
    return [folder / f"{b}.{ext}" for b in branches for ext in ("exr", "png")] + [
        folder / "ball.exr",
        folder / "ball.png",
        folder / "contact.png",
    ]


# --- several processes ------------------------------------------------------------------------------
def _launched_processes():
    """accelerate's process state under `accelerate launch` / torchrun (WORLD_SIZE > 1), else None."""
    if int(os.environ.get("WORLD_SIZE", "1")) <= 1:
        return None
    import torch
    from accelerate import PartialState

    # cpu=True when there is no GPU: accelerate then starts the gloo process group (multi-CPU)
    return PartialState(cpu=not torch.cuda.is_available())


def _my_share(photos: list[Path], state) -> list[Path]:
    """This process's contiguous share of ``photos`` (all of them on one process). The split is of the
    full, sorted input list, before any completeness check: a check made while another process writes
    could differ between processes and give a photo to two of them, or to none."""
    if state is None:
        return photos
    with state.split_between_processes(photos) as mine:
        return list(mine)


# --- commands --------------------------------------------------------------------------------------
_SAID = ("UnverifiedModelWarning", "PhotoWarning", "LightWarning")  # our warnings, said as one line each


@contextmanager
def _say_warnings():
    """Inside the block, pilight's own warnings (an unverified model, a photo or light read with a change)
    go to stderr as "pilight: warning: ..." lines; any other warning is shown as Python shows it.

    The warnings are said after the recording has ended: inside it, ``warnings.showwarning`` is the
    recorder, so re-showing one appended it to the list being read, forever (CI's 24 GB OOM kills,
    whenever a library warned inside the block)."""
    caught: list[warnings.WarningMessage] = []
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            yield
    finally:
        for w in caught:
            if type(w.message).__name__ in _SAID:
                print(f"pilight: warning: {w.message}", file=sys.stderr)
            else:
                warnings.showwarning(w.message, w.category, w.filename, w.lineno)


def check_model_options(args) -> None:
    """The model and sampling options, checked by the models that check params.yaml's keys (exit 2),
    before anything is loaded or created: `--cfg nan` was a sampler traceback after the models loaded."""
    from pydantic import ValidationError

    from pilight.params import SamplingParams
    from pilight.pipeline import MAX_PROCESSING_RESOLUTION

    if args.resolution is not None and not 0 <= args.resolution <= MAX_PROCESSING_RESOLUTION:
        raise CommandFailure(
            f"--resolution must lie in [0, {MAX_PROCESSING_RESOLUTION}] (0 = the photo's own size), got {args.resolution}",
            2,
        )
    for flag, key, v in (
        ("--steps", "steps", args.steps),
        ("--cfg", "cfg_scale", args.cfg),
        ("--ensemble", "ensemble", args.ensemble),
    ):
        if v is None:
            continue
        try:
            SamplingParams.model_validate({key: v})
        except ValidationError as exc:
            raise CommandFailure(f"{flag} {v}: {exc.errors()[0]['msg']}", 2) from None
    if args.max_memory is not None and not (math.isfinite(args.max_memory) and args.max_memory > 0):
        raise CommandFailure(f"--max-memory must be a finite number of GiB > 0, got {args.max_memory}", 2)


def _pipeline(args, stage: str, state=None):
    from pilight import process_gc
    from pilight.params import ParamsError
    from pilight.pipeline import PIPELINE_FILE, PILightPipeline, PipelineError

    check_model_options(args)
    device = args.device
    if state is not None and device == "auto":  # one device per process: cuda:<local rank>, or the CPU
        device = str(state.device)
    if args.models == Path("models"):  # the default: the pipeline's models/, else the shipped base
        from pilight.base_model import default_models

        args.models, note = default_models(args.models)
        if note:
            print(f"pilight: {note}", file=sys.stderr)
    try:
        with _say_warnings():
            pipe = PILightPipeline.from_pretrained(
                args.models, device=device, params=args.params, trust_unverified=args.trust_unverified
            )
    except ParamsError as exc:
        raise CommandFailure(str(exc), 2) from None
    except PipelineError as exc:
        raise CommandFailure(str(exc)) from None
    process_gc.release_collection()  # imports and weights are in: the work collects as usual
    # Only the checkout's own models/ are expected to match its params.yaml; another folder is
    # the user's choice and is used as its config.json says.
    print(f"pilight: models: {args.models.resolve()}", file=sys.stderr)
    dvc_models = args.params.is_file() and args.models.resolve() == (args.params.resolve().parent / "models")
    if dvc_models and not (args.models / PIPELINE_FILE).is_file():
        try:
            stale = {s: k for s, k in pipe.stale_keys(args.params).items() if k}
        except ParamsError:
            stale = {}
        for s, keys in stale.items():
            shown = ", ".join(keys[:5]) + (f" and {len(keys) - 5} more" if len(keys) > 5 else "")
            print(
                f"pilight: warning: {args.models / s} was trained with other values of {shown} than "
                f"{args.params} now holds; `dvc repro train_relight` retrains it (the saved model is used as is)",
                file=sys.stderr,
            )
    from dataclasses import replace

    key = "intrinsics_sampling" if stage == "intrinsics" else "relight_sampling"
    sp = getattr(pipe.config, key)
    update = {
        k: v
        for k, v in (
            ("steps", args.steps),
            ("cfg_scale", args.cfg),
            ("ensemble", args.ensemble),
            ("mode", args.mode or ("ddim" if args.steps is not None else None)),
        )
        if v is not None
    }
    pipe.config = replace(pipe.config, **{key: sp.model_copy(update=update)})
    if args.resolution is not None:
        pipe.config = replace(pipe.config, processing_resolution=args.resolution)
    return pipe


def _check_photos(pipe, photos: list[Path], lights: int, max_memory_gib: float | None) -> None:
    """Header of every photo read and checked (size, memory) before any is processed."""
    from pilight.photo import PhotoError, check_size, probe
    from pilight.pipeline import MemoryLimitError

    errors = []
    limit = None if max_memory_gib is None else max_memory_gib * 1024**3
    for p in photos:
        try:
            h, w = probe(p)  # the header only: nothing of the pixels is allocated yet
            check_size(h, w, str(p))
            pipe.check_memory(h, w, lights, name=str(p), max_memory=limit)
        except (PhotoError, MemoryLimitError) as exc:
            errors.append(str(exc))
    if errors:
        raise CommandFailure(
            "\n".join(errors) + f"\nnothing was written ({len(errors)} of {len(photos)} photo(s) refused)"
        )


def _progress(total: int, desc: str, state=None):
    from tqdm import tqdm

    if state is not None:
        desc = f"{desc} [process {state.process_index}/{state.num_processes}]"
    return tqdm(
        total=total,
        desc=desc,
        unit="photo",
        dynamic_ncols=True,
        file=sys.stderr,
        position=0 if state is None else state.process_index,
    )


def _done_together(state) -> None:
    if state is not None:
        state.wait_for_everyone()


def _sweep(out: Path, folders) -> None:
    """A killed run's temporaries in OUT and in the photo folders this process writes (``sweep_stale``)."""
    gone = sweep_stale(out) + [p for f in folders for p in sweep_stale(f)]
    if gone:
        print(f"pilight: removed {len(gone)} temporary output(s) left by a killed run", file=sys.stderr)


def cmd_decompose(args) -> int:
    from pilight.photo import PhotoError, read_photo
    from pilight.pictures import linear_to_srgb8, normal_preview

    check_model_options(args)  # exit 2 before anything is read, loaded or created
    photos = expand_inputs(args.photos)
    names = output_names(photos)
    check_writable(args.out)
    state = _launched_processes()
    pipe = _pipeline(args, "intrinsics", state)
    _check_photos(pipe, photos, 0, args.max_memory)
    mine = _my_share(photos, state)
    _sweep(args.out, [args.out / names[p] for p in mine])
    todo = [p for p in mine if args.overwrite or not _complete(decompose_files(args.out / names[p]))]
    if len(todo) < len(mine):
        print(
            f"pilight: {len(mine) - len(todo)} photo(s) already decomposed in {args.out}, skipped "
            "(--overwrite redoes them)",
            file=sys.stderr,
        )
    failed = 0
    with _progress(len(todo), "decompose", state) as bar:
        for done, p in enumerate(todo):
            try:
                with _say_warnings():
                    photo = read_photo(p)
                    d = pipe.decompose(photo, name=str(p))
            except PhotoError as exc:
                print(f"pilight: {exc}", file=sys.stderr)
                failed += 1
                bar.update(1)
                continue
            folder = args.out / names[p]
            a = d.mask
            files = {
                "albedo.exr": d.albedo,
                "albedo.png": linear_to_srgb8(d.albedo, a),
                "normal.exr": d.normal,
                "normal.png": normal_preview(d.normal, a),
                "roughness.exr": d.roughness,
                "roughness.png": linear_to_srgb8(d.roughness, a),
                "metallic.exr": d.metallic,
                "metallic.png": linear_to_srgb8(d.metallic, a),
            }
            try:
                write_into(folder, files) if folder.is_dir() else write_folder(folder, files)
            except (OSError, ValueError) as exc:  # ExrError is a ValueError (a full disk inside OpenEXR)
                raise CommandFailure(
                    f"{folder}: cannot write the decomposition ({getattr(exc, 'strerror', None) or exc}); nothing of "
                    f"it was kept. {done - failed} photo(s) before it are complete; rerun to continue"
                ) from None
            bar.set_postfix_str(f"{p.name} at {d.processing_size[1]}x{d.processing_size[0]}")
            bar.update(1)
    print(f"pilight: decomposed {len(todo) - failed} photo(s) into {args.out}", file=sys.stderr)
    _done_together(state)
    return 1 if failed else 0


def contact_sheet(photo_rgb, ball, relit):
    """input | light ball | relit, side by side at most CONTACT_HEIGHT tall, 4 white pixels apart (sRGB uint8)."""
    import numpy as np
    import torch
    import torch.nn.functional as F

    from pilight.eval.grids import labelled_grid
    from pilight.pictures import linear_to_srgb8

    h, w = photo_rgb.shape[:2]
    th = min(h, CONTACT_HEIGHT)
    tw = max(1, round(w * th / h))

    def fit(a, size):
        t = torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)).permute(2, 0, 1)[None]
        t = F.interpolate(t, size=size, mode="bilinear", align_corners=False, antialias=True)
        return t[0].permute(1, 2, 0).numpy()

    tiles = [
        linear_to_srgb8(fit(photo_rgb, (th, tw))),
        linear_to_srgb8(fit(ball, (th, th))),
        linear_to_srgb8(fit(relit, (th, tw))),
    ]
    return labelled_grid([tiles], None, gap=4, margin=0, tight=True)


def _lights(args, size: int):
    from pilight.lights import LightError, parse_lights

    try:
        with _say_warnings():
            return parse_lights(
                args.light, args.azimuth, args.elevation, args.ball, args.hdri, args.rotate, args.intensity, size
            )
    except LightError as exc:
        raise CommandFailure(str(exc), 2) from None


def cmd_relight(args) -> int:
    from pilight.lights import BALL_SIZE, ball_preview
    from pilight.photo import PhotoError, read_photo
    from pilight.pictures import linear_to_srgb8

    check_model_options(args)  # exit 2 before anything is read, loaded or created
    lights = _lights(args, BALL_SIZE)  # bad light options fail before any model is loaded
    photos = expand_inputs(args.photos)
    names = output_names(photos)
    check_writable(args.out)
    state = _launched_processes()
    pipe = _pipeline(args, "relight", state)
    _check_photos(pipe, photos, len(lights), args.max_memory)
    branches = pipe.relight_model.branches
    mine = _my_share(photos, state)
    _sweep(args.out, [args.out / names[p] for p in mine])
    pending = {
        p: [l for l in lights if args.overwrite or not _complete(relight_files(args.out / names[p] / l.name, branches))]
        for p in mine
    }
    todo = [p for p in pending if pending[p]]
    skipped = sum(len(lights) - len(v) for v in pending.values())
    if skipped:
        print(
            f"pilight: {skipped} (photo, light) output(s) already complete in {args.out}, skipped "
            "(--overwrite redoes them)",
            file=sys.stderr,
        )
    failed = 0
    with _progress(len(todo), f"relight x{len(lights)} light(s)", state) as bar:
        for done, p in enumerate(todo):
            try:
                with _say_warnings():
                    photo = read_photo(p)
                    out = pipe.relight(photo, pending[p], name=str(p), absolute=args.absolute, exposure=args.exposure)
            except PhotoError as exc:
                print(f"pilight: {exc}", file=sys.stderr)
                failed += 1
                bar.update(1)
                continue
            asked = {l.name for l in pending[p]}
            complete = [l.name for l in lights if l.name not in asked]  # this photo's lights already on disk
            for i, light in enumerate(out.lights):
                folder = args.out / names[p] / light.name
                files = {}
                for b in branches:
                    arr = getattr(out, b)[i]
                    files[f"{b}.exr"] = arr
                    files[f"{b}.png"] = linear_to_srgb8(arr)
                files["ball.exr"] = out.balls[i]
                files["ball.png"] = ball_preview(light.ball)
                files["contact.png"] = contact_sheet(photo.rgb, light.ball.permute(1, 2, 0).numpy(), out.relit[i])
                try:
                    write_folder(folder, files)
                except (OSError, ValueError) as exc:  # ExrError is a ValueError (a full disk inside OpenEXR)
                    kept = f"; its light(s) {', '.join(complete)} are complete" if complete else ""
                    raise CommandFailure(
                        f"{folder}: cannot write this light's outputs ({getattr(exc, 'strerror', None) or exc}); "
                        f"nothing of this light was kept{kept}. {done - failed} photo(s) before it are complete; "
                        "rerun to continue"
                    ) from None
                complete.append(light.name)
            bar.set_postfix_str(p.name)
            bar.update(1)
    print(f"pilight: relit {len(todo) - failed} photo(s) under {len(lights)} light(s) into {args.out}", file=sys.stderr)
    _done_together(state)
    return 1 if failed else 0


def cmd_ball(args) -> int:
    from pilight.lights import ball_preview

    if not 8 <= args.size <= 8192:
        raise CommandFailure(f"--size must lie in [8, 8192] pixels, got {args.size}", 2)
    lights = _lights(args, args.size)
    check_writable(args.out)
    for done, light in enumerate(lights):
        try:
            write_group(
                {
                    args.out / f"{light.name}.exr": light.ball.permute(1, 2, 0).numpy(),
                    args.out / f"{light.name}.png": ball_preview(light.ball),
                }
            )
        except (OSError, ValueError) as exc:
            raise CommandFailure(
                f"{args.out / light.name}: cannot write the ball ({getattr(exc, 'strerror', None) or exc}); nothing "
                f"of it was kept, {done} ball(s) before it are complete"
            ) from None
        print(f"{args.out / light.name}.png  {light.description}")
    return 0


def model_arguments(args) -> list[str]:
    """The model and sampling options a user gave, as command-line words (the app's reproducing command)."""
    given = [
        ("--models", args.models if args.models != Path("models") else None),
        ("--resolution", args.resolution),
        ("--mode", args.mode),
        ("--steps", args.steps),
        ("--cfg", args.cfg),
        ("--ensemble", args.ensemble),
    ]
    return [w for flag, v in given if v is not None for w in (flag, str(v))]


def cmd_app(args) -> int:
    if not 1 <= args.port <= 65535:
        raise CommandFailure(f"--port must lie in [1, 65535], got {args.port}", 2)
    try:
        from pilight.app.ui import launch
    except ImportError as exc:
        raise CommandFailure(f"the app needs its extra ({exc}): pip install -e '.[app]'", 2) from None
    extra = model_arguments(args)  # before _pipeline replaces the default --models by the shipped base
    pipe = _pipeline(args, "relight")
    print(f"pilight app: http://{args.host}:{args.port} (Ctrl+C stops it)", file=sys.stderr)
    launch(pipe, port=args.port, host=args.host, models_note=f"Models: `{args.models}`.", extra_args=extra)
    return 0


def cmd_profile(args) -> int:
    from pilight.params import ParamsError
    from pilight.profiles import write_profile

    try:
        raw = write_profile(args.base, args.profile, args.out, check_paths=not args.no_check_paths)
    except ParamsError as exc:
        raise CommandFailure(str(exc), code=2) from None
    print(f"{args.out}: {args.base} with {args.profile} over it ({len(raw)} sections, validated)")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return {
            "decompose": cmd_decompose,
            "relight": cmd_relight,
            "ball": cmd_ball,
            "app": cmd_app,
            "profile": cmd_profile,
        }[args.command](args)
    except CommandFailure as exc:
        print(f"pilight {args.command}: {exc}", file=sys.stderr)
        return exc.code
    except KeyboardInterrupt:
        print(
            f"pilight {args.command}: interrupted; outputs written so far are complete, rerun to continue",
            file=sys.stderr,
        )
        return 130


def console() -> int:
    """The ``pilight`` command: ``main()`` in a process of its own, whose garbage collector is kept off
    the import-heavy start and the exit (``pilight.process_gc``; about 1.4 s of a 5.9 s relight)."""
    from pilight import process_gc

    process_gc.hold_collection()
    process_gc.freeze_at_exit()
    return main()


if __name__ == "__main__":
    sys.exit(console())

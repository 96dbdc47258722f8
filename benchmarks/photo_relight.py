"""A real photo relit from the left and from the right: does the light follow, and does the photo keep its
detail and exposure? (The figures of tests/cli/test_light_flip.py, printed; pilight.eval.photo_measures.)

    python benchmarks/photo_relight.py [--models DIR] [--photo FILE] [--intensity 1] [--absolute] [--exposure photo|light]

Default photo: scikit-image's astronaut (512^2). Default models: the pipeline's models/, else the
shipped base. Prints, per light, the relit left/right luminance asymmetry (R - L)/(R + L), the detail
ratio (mean luminance gradient, relit / photo) and the exposure ratio (mean luminance, relit / photo),
and the seconds of one `relight` call for both lights (stage 1 once), with the machine.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from pilight.eval.photo_measures import detail, exposure, halves_asymmetry  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", type=Path, default=REPO / "models")
    ap.add_argument("--photo", type=Path, default=None)
    ap.add_argument("--intensity", type=float, default=1.0)
    ap.add_argument("--absolute", action="store_true")
    ap.add_argument("--exposure", choices=("photo", "light"), default="photo", help="pilight relight --exposure")
    args = ap.parse_args(argv)
    from pilight import lights, machine
    from pilight.base_model import default_models
    from pilight.photo import as_photo, read_photo
    from pilight.pipeline import PILightPipeline

    models, note = default_models(args.models)
    if note:
        print(note)
    if args.photo is None:
        from skimage import data

        photo = as_photo(np.ascontiguousarray(data.astronaut()), "astronaut")
    else:
        photo = read_photo(args.photo)
    pipe = PILightPipeline.from_pretrained(models, device="cpu", params=REPO / "params.yaml")
    ls = [lights.named(n, args.intensity) for n in ("left", "right")]
    t0 = time.perf_counter()
    out = pipe.relight(photo, ls, absolute=args.absolute, exposure=args.exposure)
    seconds = time.perf_counter() - t0
    rgb = photo.rgb
    print(f"{photo.name}: {rgb.shape[1]}x{rgb.shape[0]}, asymmetry {halves_asymmetry(rgb):+.3f}; models {models}")
    print(f"exposure: {args.exposure}")
    print("| light | asymmetry | detail ratio | exposure ratio | exposure gain |\n|---|---|---|---|---|")
    for light, relit, gain in zip(ls, out.relit, out.exposure_gain):
        print(
            f"| {light.name} | {halves_asymmetry(relit):+.3f} | {detail(relit) / detail(rgb):.2f} | {exposure(relit, rgb):.2f} "
            f"| {gain:.2f} |"
        )
    print(f"{seconds:.2f} s for both lights (one relight call, stage 1 once) on {machine.one_line()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

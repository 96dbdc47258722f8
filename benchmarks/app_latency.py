"""How long a change of light takes in `pilight app` (issue #35's budget: 250 ms for a 512^2 photo on 2 cores).

    python benchmarks/app_latency.py [--models DIR] [--photo FILE] [--changes 24] [--no-server]

The photo (default: scikit-image's astronaut, 512^2) is decomposed once; then the light is moved
across the ball picker, ``--changes`` positions from left to right and back, and each change is timed
twice:
- **handler**: what the server computes per change (pilight.app): the picker picture and the relit
  image, D and S (stage 2 only, stage 1's maps kept) as 8-bit pictures;
- **round trip** (unless --no-server): the app served on localhost, the change sent through its API
  (`gradio_client`, the /drag endpoint the page's pointer uses) until the three pictures are back on
  the client: the handler plus Gradio's queue, PNG encoding and transfer.
Prints the median, 90th percentile and maximum of each, with the machine.
"""

from __future__ import annotations

import argparse
import socket
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _row(name: str, seconds: list[float]) -> str:
    ms = sorted(1000 * s for s in seconds)
    p90 = ms[min(len(ms) - 1, round(0.9 * (len(ms) - 1)))]
    return f"| {name} | {statistics.median(ms):.0f} | {p90:.0f} | {ms[-1]:.0f} | {len(ms)} |"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", type=Path, default=REPO / "models")
    ap.add_argument("--photo", type=Path, default=None)
    ap.add_argument("--changes", type=int, default=24)
    ap.add_argument("--no-server", action="store_true", help="time the handler only")
    args = ap.parse_args(argv)
    from pilight import machine
    from pilight.app.lighting import LightSpec, mix, picker_direction, picker_picture
    from pilight.app.session import PhotoSession
    from pilight.base_model import default_models
    from pilight.pipeline import PILightPipeline

    models, note = default_models(args.models)
    if note:
        print(note)
    photo_path = args.photo
    if photo_path is None:
        from PIL import Image
        from skimage import data

        photo_path = Path(tempfile.mkdtemp()) / "astronaut.png"
        Image.fromarray(np.ascontiguousarray(data.astronaut())).save(photo_path)
    pipe = PILightPipeline.from_pretrained(models, device="cpu", params=REPO / "params.yaml")
    session = PhotoSession.open(pipe, photo_path)
    h, w = session.photo.size
    size = 256
    xs = list(np.linspace(0.05, 0.95, args.changes // 2)) + list(
        np.linspace(0.95, 0.05, args.changes - args.changes // 2)
    )
    handler = []
    for x in xs:
        t0 = time.perf_counter()
        az, el = picker_direction(x * size, 0.4 * size, size)
        specs = [LightSpec(az, el)]
        picker_picture(specs, size)
        session.relight(mix([s.light() for s in specs]))
        handler.append(time.perf_counter() - t0)
    rows = [_row("handler (server side)", handler)]
    if not args.no_server:
        from gradio_client import Client, handle_file

        from pilight.app.ui import launch

        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        app = launch(pipe, port=port, block=False)
        try:
            client = Client(f"http://127.0.0.1:{port}/", verbose=False)
            client.predict(handle_file(str(photo_path)), "default", 0, 1.0, True, api_name="/open_photo")
            trip = []
            for i, x in enumerate(xs):
                t0 = time.perf_counter()
                client.predict(f"{x:.4f},0.4,{i}", 0, 1.0, True, api_name="/drag")
                trip.append(time.perf_counter() - t0)
            rows.append(_row("round trip (API, localhost)", trip))
        finally:
            app.close()
    print(f"{photo_path.name}: {w}x{h}, processed at {session.decomposition.processing_size}; models {models}")
    print("| per change of light | median (ms) | p90 (ms) | max (ms) | changes |\n|---|---|---|---|---|")
    print("\n".join(rows))
    print(f"machine: {machine.one_line()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""`pilight app`: the web page (Gradio) where the light follows the pointer.

Upload a photo: stage 1 runs once (pilight.app.session) and its maps and estimated light are shown.
Place the light by clicking or dragging on the gray ball (pilight.app.lighting), or with the sliders
(azimuth and elevation in pilight.lights' convention), with its relative intensity and colour; add
more lights to mix them, or an HDRI that the rotation slider turns. Every change relights at once
(stage 2 only); the relit image, D and S are on tabs, and "Prepare downloads" writes the EXR and PNG
files with the `pilight relight` command that reproduces the result.

The page runs offline: no analytics, no web fonts, nothing fetched. Handlers never raise to the page:
what a user can fix is said in the status line (AppError, LightError, PhotoError).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path

os.environ.setdefault("GRADIO_ANALYTICS_ENABLED", "False")  # nothing leaves the machine

import gradio as gr  # noqa: E402  (after the analytics switch)
import numpy as np  # noqa: E402
import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402

from pilight.app.lighting import LightSpec, hex_colour, mix, picker_direction, picker_picture  # noqa: E402
from pilight.app.session import AppError, PhotoSession, relight_command  # noqa: E402
from pilight.lights import LightError, check_panorama, from_hdri  # noqa: E402
from pilight.photo import PhotoError, read_photo  # noqa: E402
from pilight.pipeline import PILightPipeline  # noqa: E402

PICKER_SIZE = 256
VIEWS = ("relit", "diffuse", "specular")  # the tabs, in the order of the outputs
HDRI_WIDTH = 512  # an uploaded panorama is area-averaged to this width: its light is kept, turning it is fast
FIRST_LIGHT = LightSpec(azimuth=-60.0, elevation=30.0)
PHOTO_TYPES = [".png", ".jpg", ".jpeg", ".tif", ".tiff", ".webp", ".bmp", ".exr", ".hdr"]

# The ball follows the pointer: on a press and while a button is held over the picker, its position
# (0..1 of the picture) goes into the hidden #ball-drag box, whose change relights. (Gradio's own
# `select` event reports clicks only, and did not fire for Chromium's pointer here.)
DRAG_JS = """
() => {
  /* A pointer at (cx, cy) -> (x, y) as fractions 0..1 of the picture shown in the element's rect r. Gradio may
     letterbox the picture (object-fit); while a new picture loads (the picker is redrawn after every
     relighting) its natural size reads 0, and then the element's own size is the picture's. */
  window.pilightPickerFraction = (r, naturalWidth, naturalHeight, cx, cy) => {
    const nw = naturalWidth || r.width, nh = naturalHeight || r.height;
    const k = Math.min(r.width / nw, r.height / nh), w = nw * k, h = nh * k;
    return [(cx - r.left - (r.width - w) / 2) / w, (cy - r.top - (r.height - h) / 2) / h];
  };
  const attach = () => {
    const host = document.querySelector('#ball-picker');
    const box = document.querySelector('#ball-drag textarea, #ball-drag input');
    if (!host || !box) { setTimeout(attach, 200); return; }
    let down = false, last = 0;
    const send = (e) => {
      const img = host.querySelector('img');
      if (!img) return;
      const [x, y] = window.pilightPickerFraction(img.getBoundingClientRect(), img.naturalWidth, img.naturalHeight,
                                                  e.clientX, e.clientY);
      if (x < -0.1 || x > 1.1 || y < -0.1 || y > 1.1) return;
      box.value = x.toFixed(4) + ',' + y.toFixed(4) + ',' + (last++);
      box.dispatchEvent(new Event('input', {bubbles: true}));
    };
    host.addEventListener('pointerdown', (e) => { down = true; e.preventDefault(); send(e); });
    window.addEventListener('pointerup', (e) => { if (down) { send(e); } down = false; });
    host.addEventListener('pointermove', (e) => { if (down) send(e); });
  };
  attach();
}
"""
CSS = ".pilight-hidden {display: none !important;} #ball-picker img {cursor: crosshair; touch-action: none;}"


@dataclass
class AppState:
    """Per browser tab: the decomposed photo, the lights (the last one is the one the controls move) and
    an HDRI panorama, when one was uploaded."""

    session: PhotoSession | None = None
    specs: list[LightSpec] = field(default_factory=lambda: [FIRST_LIGHT])
    hdri: np.ndarray | None = None
    hdri_name: str = ""
    view: str = "relit"  # the tab on show: only its picture is sent on a change of light (PNG/JPEG encoding
    # and transfer of all three would double the time of a change)

    def light(self, rotate: float, hdri_intensity: float):
        lights = [s.light() for s in self.specs]
        if self.hdri is not None:
            lights.append(from_hdri(self.hdri, rotate, hdri_intensity, name=self.hdri_name))
        return mix(lights)


def _small_panorama(rgb: np.ndarray) -> np.ndarray:
    if rgb.shape[1] <= HDRI_WIDTH:
        return rgb
    t = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1)[None]
    t = F.interpolate(t, size=(HDRI_WIDTH // 2, HDRI_WIDTH), mode="area")
    return t[0].permute(1, 2, 0).contiguous().numpy()


def build_app(pipe: PILightPipeline, models_note: str = "", extra_args: list[str] | None = None) -> gr.Blocks:
    """The page, on ``pipe`` (loaded once, shared by every tab). ``extra_args``: the model options the app was
    started with, repeated in the reproducing command."""

    def relit_outputs(state: AppState, rotate: float, hdri_k: float, keep: bool):
        """(picker, relit, diffuse, specular, status) for the state's lights."""
        picker = picker_picture(state.specs, PICKER_SIZE)
        if state.session is None:
            return picker, None, None, None, "Upload a photo to relight it."
        try:
            light = state.light(rotate, hdri_k)
            r = state.session.relight(light, keep_exposure=keep)
        except (AppError, LightError) as exc:
            return picker, None, None, None, f"**Error:** {exc}"
        n = len(state.specs) + (state.hdri is not None)
        said = f"{n} light(s) mixed" if n > 1 else state.specs[0].light().description
        status = f"Relit in {1000 * r.seconds:.0f} ms: {said}."
        pictures = [r.pictures.get(k) if k == state.view else gr.update() for k in VIEWS]
        return picker, *pictures, status

    def on_view(view: str):
        def show(state: AppState):
            state = state or AppState()
            state.view = view
            last = state.session.last if state.session is not None else None
            return state, (last.pictures.get(view) if last is not None else None)

        return show

    def on_photo(path, resolution: str, state: AppState, rotate, hdri_k, keep):
        state = state or AppState()
        try:
            session = PhotoSession.open(pipe, path, None if resolution == "default" else int(resolution))
        except AppError as exc:
            state.session = None
            return state, [], picker_picture(state.specs, PICKER_SIZE), None, None, None, f"**Error:** {exc}"
        state.session = session
        gallery = [(pic, name) for name, pic in session.maps().items()]
        return state, gallery, *relit_outputs(state, rotate, hdri_k, keep)

    def on_controls(azimuth, elevation, intensity, colour, state: AppState, rotate, hdri_k, keep):
        state = state or AppState()
        try:
            spec = LightSpec(float(azimuth), float(elevation), float(intensity), hex_colour(colour))
        except LightError as exc:
            return state, picker_picture(state.specs, PICKER_SIZE), None, None, None, f"**Error:** {exc}"
        state.specs = [*state.specs[:-1], spec]
        return state, *relit_outputs(state, rotate, hdri_k, keep)

    def place(x: float, y: float, state: AppState, rotate, hdri_k, keep):
        state = state or AppState()
        azimuth, elevation = picker_direction(x, y, PICKER_SIZE)
        state.specs = [*state.specs[:-1], replace(state.specs[-1], azimuth=azimuth, elevation=elevation)]
        return state, round(azimuth, 1), round(elevation, 1), *relit_outputs(state, rotate, hdri_k, keep)

    def on_drag(text: str, state, rotate, hdri_k, keep):
        try:
            fx, fy = (float(v) for v in text.split(",")[:2])
        except ValueError:
            return (state, gr.update(), gr.update(), gr.update(), gr.update(), gr.update(), gr.update(), gr.update())
        return place(fx * PICKER_SIZE - 0.5, fy * PICKER_SIZE - 0.5, state, rotate, hdri_k, keep)

    def on_add(state: AppState, rotate, hdri_k, keep):
        state = state or AppState()
        if len(state.specs) >= 8:
            return state, *relit_outputs(state, rotate, hdri_k, keep)[:-1], "**Error:** at most 8 lights can be mixed"
        state.specs = [*state.specs, replace(FIRST_LIGHT, azimuth=-FIRST_LIGHT.azimuth)]
        return state, *relit_outputs(state, rotate, hdri_k, keep)

    def on_reset(state: AppState, rotate, hdri_k, keep):
        state = state or AppState()
        state.specs, state.hdri = [FIRST_LIGHT], None
        s = FIRST_LIGHT
        return (
            state,
            s.azimuth,
            s.elevation,
            s.intensity,
            "#ffffff",
            None,
            *relit_outputs(state, rotate, hdri_k, keep),
        )

    def on_hdri(path, state: AppState, rotate, hdri_k, keep):
        state = state or AppState()
        state.hdri = None
        if path is not None:
            try:
                rgb = read_photo(path).rgb
                check_panorama(*rgb.shape[:2], Path(path).name)
                state.hdri, state.hdri_name = _small_panorama(rgb), Path(path).name
            except (PhotoError, LightError) as exc:
                picker = picker_picture(state.specs, PICKER_SIZE)
                return state, picker, None, None, None, f"**Error:** {str(exc).replace(str(path), Path(path).name)}"
        return state, *relit_outputs(state, rotate, hdri_k, keep)

    def on_export(state: AppState, keep):
        state = state or AppState()
        if state.session is None or state.session.last is None:
            return None, "", "**Error:** nothing to download yet: upload a photo and place a light"
        single = len(state.specs) == 1 and state.specs[0].white and state.hdri is None
        direction = (state.specs[0].azimuth, state.specs[0].elevation) if single else None
        extra = list(extra_args or [])
        if state.session.resolution is not None:  # the page's processing size replaces the command line's
            if "--resolution" in extra:
                i = extra.index("--resolution")
                del extra[i : i + 2]
            extra += ["--resolution", str(state.session.resolution)]
        command = relight_command(
            state.session.path.name, state.session.last.light, keep_exposure=keep, direction=direction, extra=extra
        )
        files = state.session.export(command)
        return [str(f) for f in files], command, f"{len(files)} files ready."

    with gr.Blocks(title="pilight: relight a photo", analytics_enabled=False) as app:
        gr.Markdown(
            "## pilight: relight a photo\nUpload a photo, then click or drag on the gray ball: the light comes "
            "from where you point. " + models_note
        )
        state = gr.State(None)
        with gr.Row():
            with gr.Column(scale=1):
                photo = gr.File(label="Photo", file_types=PHOTO_TYPES, type="filepath", elem_id="photo")
                resolution = gr.Dropdown(
                    [(f"the models' ({pipe.config.processing_resolution} px)", "default")]
                    + [(f"{r} px", str(r)) for r in (256, 512, 768)]
                    + [("the photo's own size", "0")],
                    value="default",
                    label="Processing size (longer side; the CLI's --resolution)",
                )
                gallery = gr.Gallery(label="Decomposition and estimated light", columns=3, height="auto")
            with gr.Column(scale=1):
                picker = gr.Image(
                    value=picker_picture([FIRST_LIGHT], PICKER_SIZE),
                    label="Light: click or drag on the ball",
                    interactive=False,
                    elem_id="ball-picker",
                    show_label=True,
                )
                drag = gr.Textbox(elem_id="ball-drag", elem_classes="pilight-hidden", container=False)
                azimuth = gr.Slider(
                    -180, 180, FIRST_LIGHT.azimuth, step=0.1, label="Azimuth (deg; -90 left, +90 right)"
                )
                elevation = gr.Slider(-90, 90, FIRST_LIGHT.elevation, step=0.1, label="Elevation (deg)")
                intensity = gr.Slider(0, 4, 1.0, step=0.05, label="Intensity k (1 = the photo's own light level)")
                colour = gr.ColorPicker("#ffffff", label="Colour")
                with gr.Row():
                    add = gr.Button("Add another light")
                    reset = gr.Button("Reset lights")
                hdri = gr.File(label="HDRI (2:1 panorama, optional)", file_types=PHOTO_TYPES, type="filepath")
                rotate = gr.Slider(-180, 180, 0, step=1, label="HDRI rotation (deg)")
                hdri_k = gr.Slider(0, 4, 1.0, step=0.05, label="HDRI intensity")
                keep = gr.Checkbox(True, label="Keep the photo's exposure")
            with gr.Column(scale=2):
                status = gr.Markdown("Upload a photo to relight it.", elem_id="status")
                with gr.Tabs():
                    with gr.Tab("Relit") as relit_tab:
                        relit = gr.Image(label="Relit", interactive=False, elem_id="relit", format="jpeg")
                    with gr.Tab("Diffuse D") as diffuse_tab:
                        diffuse = gr.Image(label="Diffuse shading D", interactive=False, format="jpeg")
                    with gr.Tab("Specular S") as specular_tab:
                        specular = gr.Image(label="Specular S", interactive=False, format="jpeg")
                export = gr.Button("Prepare downloads")
                files = gr.File(label="Downloads (EXR, PNG, the light, the command)", file_count="multiple")
                command = gr.Textbox(label="The command that reproduces this", interactive=False)
        common = [rotate, hdri_k, keep]
        shown = [picker, relit, diffuse, specular, status]
        live = {"trigger_mode": "always_last", "show_progress": "hidden"}
        photo.change(on_photo, [photo, resolution, state, *common], [state, gallery, *shown], api_name="open_photo")
        resolution.change(on_photo, [photo, resolution, state, *common], [state, gallery, *shown], api_name=False)
        controls = [azimuth, elevation, intensity, colour, state, *common]
        for c in (azimuth, elevation, intensity):
            c.input(on_controls, controls, [state, *shown], api_name=False, **live)
        colour.input(on_controls, controls, [state, *shown], api_name=False, **live)
        gr.Button("Relight", visible=False).click(on_controls, controls, [state, *shown], api_name="set_light")
        drag.change(on_drag, [drag, state, *common], [state, azimuth, elevation, *shown], api_name="drag", **live)
        add.click(on_add, [state, *common], [state, *shown], api_name="add_light")
        reset.click(
            on_reset, [state, *common], [state, azimuth, elevation, intensity, colour, hdri, *shown], api_name="reset"
        )
        hdri.change(on_hdri, [hdri, state, *common], [state, *shown], api_name="set_hdri")
        for c in (rotate, hdri_k, keep):
            c.input(on_controls, controls, [state, *shown], api_name=False, **live)
        export.click(on_export, [state, keep], [files, command, status], api_name="export")
        for tab, view, image in (
            (relit_tab, "relit", relit),
            (diffuse_tab, "diffuse", diffuse),
            (specular_tab, "specular", specular),
        ):
            tab.select(on_view(view), [state], [state, image], api_name=False)
    return app


def launch(
    pipe: PILightPipeline,
    *,
    port: int,
    host: str = "127.0.0.1",
    models_note: str = "",
    extra_args: list[str] | None = None,
    block: bool = True,
):
    """Serve the page on http://host:port (localhost by default); returns the Blocks."""
    app = build_app(pipe, models_note, extra_args)
    app.queue(default_concurrency_limit=1)  # one relight at a time: two would share 2 cores and both lag
    app.launch(
        server_name=host,
        server_port=port,
        prevent_thread_lock=not block,
        quiet=not block,
        max_file_size="200mb",
        footer_links=[],
        ssr_mode=False,
        theme=gr.themes.Base(font=["system-ui", "sans-serif"], font_mono=["ui-monospace", "monospace"]),
        css=CSS,
        js=DRAG_JS,
    )
    return app

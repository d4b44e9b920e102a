"""The viser scene and controls of the viewer: the textured mesh with a map selector, a movable
light, the views' frusta (a click moves the camera there and compares photo / estimate / ours /
GT), evidence colour maps and the loss / PSNR curves, refreshed while the run goes on."""

from __future__ import annotations

import logging
import math
import threading

import numpy as np
import viser
import viser.uplot

from jaxdistill.viewer import display
from jaxdistill.viewer.run import RunDir, Snapshot, photo

log = logging.getLogger(__name__)

COLOUR_BY = {"the map": "map", "relit by the light (PBR)": "relit", "visibility (views per texel)": "visibility",
             "disagreement between views": "disagreement"}
METRIC_LABELS = {"albedo_psnr": "albedo PSNR (dB)", "albedo_ssim": "albedo SSIM", "normal_angular_deg": "normal error (°)",
                 "roughness_mse": "roughness MSE", "metallic_mse": "metallic MSE",
                 "irradiance_si_psnr": "irradiance si-PSNR (dB)"}
PANEL_WIDTH = 200          # pixels across each image of the per-view comparison


class QuietHandshakes(logging.Filter):
    """Drops websockets' "opening handshake failed" tracebacks: browsers open speculative
    connections to a page's host and close them unused, which is harmless."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.getMessage() != "opening handshake failed"


QUIET_HANDSHAKES = QuietHandshakes()


class Viewer:
    """Serves `run` on host:port until `close()`; `refresh()` reloads what changed on disk."""

    def __init__(self, run: RunDir, host: str = "127.0.0.1", port: int = 8080):
        self.run = run
        logging.getLogger("websockets.server").addFilter(QUIET_HANDSHAKES)     # once: the same filter object
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.gui.configure_theme(titlebar_content=None, control_width="large", dark_mode=False)
        self.url = f"http://{host}:{self.server.get_port()}"
        self.lock = threading.RLock()
        self.snapshot: Snapshot | None = None
        self.version = None
        self.selected_view: int | None = None
        self.textured = None            # (colour by, map, snapshot source) of the mesh shown
        scene = run.scene
        self.centre = scene.mesh.vertices.mean(axis=0)
        self.extent = float(np.linalg.norm(np.ptp(scene.mesh.vertices, axis=0)))
        up = display.up_direction([v.camera for v in scene.views])
        self.server.scene.set_up_direction(tuple(float(x) for x in up))
        self.server.scene.configure_environment_map(hdri=None)
        self.server.scene.configure_default_lights(enabled=False)
        self.server.scene.add_light_ambient("/ambient", intensity=0.4)
        self.light_handle = self.server.scene.add_transform_controls(
            "/light", scale=0.1 * self.extent, disable_rotations=True, position=tuple(self.centre + 0.3 * self.extent * up),
            visible=False)
        self.light = self.server.scene.add_light_point("/light/point", intensity=2.0 * self.extent ** 2, decay=2.0)
        side = np.cross(up, np.eye(3)[int(np.argmin(np.abs(up)))])
        side /= np.linalg.norm(side)
        self.server.initial_camera.position = tuple(self.centre + 1.0 * self.extent * up + 0.6 * self.extent * side)
        self.server.initial_camera.look_at = tuple(self.centre)
        self._build_gui()
        self.frusta = self._add_frusta()
        self.mesh = None
        self.refresh(force=True)

    # -- GUI ------------------------------------------------------------------------------

    def _build_gui(self) -> None:
        gui = self.server.gui
        gui.add_markdown(f"**jaxdistill** · `{self.run.out}`")
        self.status = gui.add_markdown("")
        self.map_choice = gui.add_dropdown("Map", tuple(self.run.maps), initial_value=self.run.maps[0])
        self.colour_choice = gui.add_dropdown("Colour by", tuple(COLOUR_BY), initial_value="the map")
        self.legend = gui.add_markdown("")
        self.show_frusta = gui.add_checkbox("Show the views", True)
        self.map_choice.on_update(lambda _: self._map_chosen())
        self.colour_choice.on_update(lambda _: self.show_textures())
        self.show_frusta.on_update(lambda _: self._set_frusta_visible(self.show_frusta.value))
        with gui.add_folder("Progress"):
            self.curves = gui.add_markdown("no history yet")
            self.plot = None
        with gui.add_folder("Selected view"):
            names = ("(none)",) + tuple(v.name for v in self.run.scene.views)
            self.view_choice = gui.add_dropdown("Go to view", names, initial_value="(none)")
            self.view_choice.on_update(self._view_chosen)
            self.view_title = gui.add_markdown("click a camera frustum in the scene, or choose a view")
            self.view_image = gui.add_image(np.zeros((8, 8, 3), np.uint8), label=None,
                                            visible=False)
            self.view_metrics = gui.add_markdown("")

    def _add_frusta(self) -> list:
        frusta = []
        for i, view in enumerate(self.run.scene.views):
            cam = view.camera
            thumb = photo(self.run.scene, i)
            step = max(1, cam.width // 96)
            frustum = self.server.scene.add_camera_frustum(
                f"/views/{view.name}", fov=display.vertical_fov(cam), aspect=cam.width / cam.height,
                scale=0.03 * self.extent, thickness=1.5, thickness_units="screen", color=(230, 120, 40),
                image=display.to_uint8(thumb[::step, ::step]), wxyz=display.rotation_to_wxyz(np.asarray(cam.c2w)[:3, :3]),
                position=tuple(cam.center))
            frustum.on_click(lambda event, index=i: self.select_view(index, event.client))
            frusta.append(frustum)
        return frusta

    def _set_frusta_visible(self, visible: bool) -> None:
        for f in self.frusta:
            f.visible = visible

    # -- the mesh -------------------------------------------------------------------------

    def refresh(self, force: bool = False) -> bool:
        """Reloads maps and curves when the out_dir changed; True when it did."""
        with self.lock:
            version = self.run.version()
            if not force and version == self.version:
                return False
            self.version = version
            self.snapshot = self.run.snapshot()
            self.show_textures()
            self._show_history()
            self._show_status()
            if self.selected_view is not None:
                self._show_view(self.selected_view)
            return True

    def show_textures(self) -> None:
        with self.lock:
            name, colour_by = self.map_choice.value, COLOUR_BY[self.colour_choice.value]
            key = (colour_by, name, self.snapshot.source)
            if key == self.textured:
                return
            run, legend = self.run, ""
            if colour_by == "relit":
                glb = display.pbr_glb(run.scene.mesh, run.object_page, self.snapshot.pages)
                legend = "albedo, roughness, metallic and normal maps lit by a point light: drag the gizmo to move it"
            elif colour_by in ("visibility", "disagreement"):
                pages = run.evidence(colour_by, name)
                if pages is None:
                    self.legend.content = f"*no {colour_by} map in this run yet (written when the run finishes)*"
                    return
                images, (low, high) = display.evidence_display_pages(colour_by, pages)
                glb = display.unlit_glb(run.scene.mesh, run.object_page, images)
                what = "views that see the texel" if colour_by == "visibility" else \
                    f"RMS spread of the views' {name} estimates"
                legend = (f"{what}: {display.COLOUR_MAPS[colour_by]} colour map from {low:.3g} to {high:.3g}; "
                          "grey: fewer than two views")
            else:
                glb = display.unlit_glb(run.scene.mesh, run.object_page,
                                        display.map_display_pages(name, self.snapshot.pages[name]))
                legend = {"normal": "world-space normal as (n + 1) / 2",
                          "irradiance": "irradiance scaled so that its 99th percentile is 0.9 (known up to scale)"}.get(
                    name, f"{name} as stored (sRGB display)")
            self.mesh = self.server.scene.add_glb("/mesh", glb)
            self.light_handle.visible = colour_by == "relit"
            self.legend.content = legend
            self.textured = key

    def _show_status(self) -> None:
        snap, summary = self.snapshot, self.run.summary()
        steps = self.run.config.get("steps")
        lines = [f"**{'finished' if snap.finished else 'running'}** · step {snap.step} of {steps} · "
                 f"{self.run.config.get('prior_kind', self.run.config.get('prior'))} prior", f"maps from {snap.source}"]
        if summary.get("ours"):
            ours, base = summary["ours"], summary.get("baseline_per_view_estimates", {})
            lines.append("| all views | ours | per-view estimates |\n|---|---|---|")
            for key, label in METRIC_LABELS.items():
                if key in ours:
                    lines.append(f"| {label} | {ours[key]:.4g} | {base.get(key, math.nan):.4g} |")
        self.status.content = "\n\n".join(lines[:2]) + ("\n\n" + "\n".join(lines[2:]) if len(lines) > 2 else "")

    def _show_history(self) -> None:
        history = self.run.history()
        if not history or not history.get("step"):
            return
        steps = np.asarray(history["step"], np.float64)
        loss = np.asarray(history["loss"], np.float64)
        psnr = np.full(len(steps), np.nan)
        for s, value in zip(history.get("eval_step", []), history.get("albedo_psnr", [])):
            psnr[np.searchsorted(steps, s)] = np.nan if value is None else value
        data = (steps, loss, psnr)
        series = (viser.uplot.Series(label="step"),
                  viser.uplot.Series(label="loss", stroke="#1f77b4", width=2, scale="loss"),
                  viser.uplot.Series(label="albedo PSNR (dB)", stroke="#ff7f0e", width=2, scale="dB",
                                     points={"show": True}, spanGaps=True))
        axes = (viser.uplot.Axis(), viser.uplot.Axis(scale="loss", label="loss"),
                viser.uplot.Axis(scale="dB", side=1, label="dB", grid={"show": False}))
        scales = {"x": viser.uplot.Scale(time=False, auto=True), "loss": viser.uplot.Scale(auto=True),
                  "dB": viser.uplot.Scale(auto=True)}
        if self.plot is None:
            self.plot = self.server.gui.add_uplot(data, series, axes=axes, scales=scales, aspect=1.6,
                                                  title="loss and albedo PSNR")
        else:
            self.plot.data = data
        last = [f"step {int(steps[-1])}: loss {loss[-1]:.4g}"]
        if np.isfinite(psnr).any():
            last.append(f"albedo PSNR {psnr[np.isfinite(psnr)][-1]:.2f} dB")
        self.curves.content = ", ".join(last)

    # -- one view -------------------------------------------------------------------------

    def select_view(self, index: int, client=None) -> None:
        """Moves the client's camera (all clients' when None) to view `index` and compares there."""
        cam = self.run.scene.views[index].camera
        clients = [client] if client is not None else list(self.server.get_clients().values())
        for c in clients:
            with c.atomic():
                c.camera.wxyz = display.rotation_to_wxyz(np.asarray(cam.c2w)[:3, :3])
                c.camera.position = tuple(cam.center)
                c.camera.fov = display.vertical_fov(cam)
        with self.lock:
            self.selected_view = index
            self.show_frusta.value = False          # from inside the room, neighbouring frusta cover the view
            self._set_frusta_visible(False)
            if self.view_choice.value != self.run.scene.views[index].name:
                self.view_choice.value = self.run.scene.views[index].name
            self._show_view(index)

    def _map_chosen(self) -> None:
        with self.lock:
            self.show_textures()
            if self.selected_view is not None:
                self._show_view(self.selected_view)

    def _view_chosen(self, event) -> None:
        names = [v.name for v in self.run.scene.views]
        if self.view_choice.value in names and names.index(self.view_choice.value) != self.selected_view:
            self.select_view(names.index(self.view_choice.value), event.client)

    def _show_view(self, index: int) -> None:
        name = self.map_choice.value
        view = self.run.scene.views[index]
        images = self.run.view_images(index, self.snapshot.pages)
        scale = display.irradiance_scale([images[name]["ours"]]) if name == "irradiance" else 1.0
        cells = [photo(self.run.scene, index)] + [
            None if images[name][k] is None else display.display_values(name, images[name][k], scale)
            for k in ("estimate", "ours", "gt")]
        self.view_image.image = display.to_uint8(display.comparison_grid(cells, PANEL_WIDTH))
        self.view_image.visible = True
        self.view_title.content = (f"**{view.name}** · {name} (maps from {self.snapshot.source})\n\n"
                                   "top: photo | per-view estimate; bottom: ours | ground truth (grey: none)")
        scores = self.run.view_metrics(index, images)
        rows = [f"| {view.name} | ours | estimate |", "|---|---|---|"]
        for key, label in METRIC_LABELS.items():
            if key in scores.get("ours", {}):
                rows.append(f"| {label} | {scores['ours'][key]:.4g} | "
                            f"{scores.get('estimate', {}).get(key, math.nan):.4g} |")
        self.view_metrics.content = "\n".join(rows) if len(rows) > 2 else "*no ground truth for this view*"

    # -- serving --------------------------------------------------------------------------

    def follow(self, stop: threading.Event, interval: float = 2.0) -> None:
        """Refreshes every `interval` seconds until `stop` is set (errors are logged, not fatal:
        a file caught mid-write is read again next time)."""
        while not stop.wait(interval):
            try:
                self.refresh()
            except Exception as err:          # noqa: BLE001 - keep serving whatever one refresh hit
                log.warning("viewer refresh failed (will retry): %s", err)

    def close(self) -> None:
        self.server.stop()


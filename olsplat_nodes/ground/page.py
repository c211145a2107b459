"""The ground station's page on viser: the map as splats, the flight, queries, pictures, status.

Thin: every figure comes from a source (``review.RunReview`` for a run folder, ``link.LinkSource``
for a running graph over the ground link) and every colour from ``colours``.
One background thread polls the source once a second; a new map version re-colours the splats
with the last query, so the page never needs a reload. viser serves its own web client from the
Python wheel, so the page works without internet.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import numpy as np

from .colours import colour_bar_html, relevance_colours
from .review import DEFAULT_NEGATIVES, WebAnswer, answer_geojson, split_negatives

log = logging.getLogger(__name__)
LEVEL_COLOURS = {"OK": "#2b8a3e", "WARN": "#e67700", "ERROR": "#c92a2a", "STALE": "#868e96"}
MAX_INSTANCE_BUTTONS = 12


def camera_pose(camera) -> tuple[np.ndarray, np.ndarray]:
    """(wxyz quaternion, position) of a view in world coordinates. Our cameras and viser's
    frustums share the OpenCV convention (x right, y down, z forward)."""
    from ..scene.rotations import rotmat_to_quat

    pose = np.asarray(camera.world_from_camera, np.float64)
    return rotmat_to_quat(pose[:3, :3]), pose[:3, 3].copy()


class GroundPage:
    def __init__(
        self,
        source,
        host: str = "127.0.0.1",
        port: int = 8080,
        title: str = "olsplat ground station",
        negatives: str = ", ".join(DEFAULT_NEGATIVES),
    ):
        import viser

        self.source = source
        self.lock = threading.RLock()  # callbacks run in viser's threads, polling in ours
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.port = self.server.get_port()
        public = host not in ("127.0.0.1", "localhost", "::1")
        if public:
            title += f" - served on {host}: visible to other hosts"
        self.server.gui.configure_theme(
            titlebar_content=None, control_layout="fixed", control_width="large", show_share_button=False
        )
        self.server.gui.set_panel_label(title)
        self.last_query: tuple[str, list[str]] | None = None
        self.coloured: tuple | None = None  # (text, negatives, map version) the splats show
        self.previews_shown = 0  # previews drawn before their full answers (tests read it)
        self.shown_views = 0
        self.instance_buttons: list = []
        self.answer: WebAnswer | None = None
        self.splats: Any = None  # viser's GaussianSplatHandle, once the source has the prior map
        self._build_gui(negatives)
        self._draw_map()
        self.stop = threading.Event()
        self.poller = threading.Thread(target=self._poll, name="ground-web-poll", daemon=True)

    # -- layout -------------------------------------------------------------------------------
    def _build_gui(self, negatives: str) -> None:
        gui = self.server.gui
        with gui.add_folder("Status"):
            self.status = gui.add_html("<div>no map yet</div>")
        with gui.add_folder("Query"):
            self.query_text = gui.add_text("query", "", hint="what to look for, e.g. red roof buildings")
            self.negatives_text = gui.add_text("negatives", negatives, hint="comma-separated")
            # a change query: what changed since an earlier flight of a per-flight map (a run
            # folder with flights/), the query text optional; "none": an ordinary query
            flights = self.source.flights() if hasattr(self.source, "flights") else []
            self.since_choice = gui.add_dropdown(
                "since flight", ["none", *flights], initial_value="none", visible=bool(flights)
            )
            self.gone_box = gui.add_checkbox("gone (with a text)", False, visible=bool(flights))
            self.ask_button = gui.add_button("Ask")
            self.query_message = gui.add_markdown("Type a query and press Ask.")
            self.colour_bar = gui.add_html(colour_bar_html(), visible=False)
            # the answer's 3D instances in WGS-84, when the map has a georeference
            self.geojson_button = gui.add_button("Download GeoJSON", visible=False)
        self.instances_folder = gui.add_folder("Instances")
        with gui.add_folder("View"):
            self.view_choice = gui.add_dropdown("view", ["(none)"], initial_value="(none)")
            self.heatmap_image = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="heatmap", visible=False)
            self.mask_image = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="mask", visible=False)
        with gui.add_folder("Map"):
            self.map_caption = gui.add_markdown("waiting for the prior map ...")
        self.ask_button.on_click(lambda _event: self._ask())
        self.geojson_button.on_click(lambda event: self._download_geojson(event.client))
        # a view chosen with a query typed: its heatmap at once
        self.view_choice.on_update(lambda _event: self._ask() if self.query_text.value.strip() else None)

    def _draw_map(self) -> None:
        """The prior map's splats, once the source has them (over a link: when they came)."""
        s = self.source.splats
        if s is None or self.splats is not None:
            return
        # the whole map in view: from the south, as high as the map is wide (z up)
        self.server.scene.set_up_direction("+z")
        if len(s.centers):
            low, high = np.percentile(s.centers, [2, 98], axis=0)
            centre, width = (low + high) / 2, float(np.max(high - low))
            position = centre + np.array([0.0, -0.8 * width, 0.9 * width])
            self.server.initial_camera.look_at = centre
            self.server.initial_camera.position = position
            for client in self.server.get_clients().values():  # pages opened before the map came
                with client.atomic():
                    client.camera.position = position
                    client.camera.look_at = centre
        self.splats = self.server.scene.add_gaussian_splats(
            "/map/splats", centers=s.centers, covariances=s.covariances, rgbs=s.rgbs, opacities=s.opacities
        )
        self.map_caption.content = s.caption

    # -- updates ------------------------------------------------------------------------------
    def start(self) -> None:
        self.poller.start()

    def close(self) -> None:
        """Stop serving, then let the source finish its background work (a run folder's
        service warms its kernels and text encoder in threads): a process that exits while one
        is inside onnxruntime or numba is aborted by the C++ runtime ("terminate called
        without an active exception")."""
        self.stop.set()
        self.server.stop()
        if self.poller.is_alive():
            self.poller.join(10.0)
        close_source = getattr(self.source, "close", None)
        if close_source is not None:
            close_source()

    def _poll(self) -> None:
        while not self.stop.is_set():
            try:
                self.refresh()
            except Exception as exc:  # the page shows it and keeps polling
                log.exception("refresh failed")
                self.status.content = f'<div style="color:{LEVEL_COLOURS["ERROR"]}">{_escape(str(exc))}</div>'
            self.stop.wait(1.0)

    def refresh(self) -> None:
        """Read the source; draw new views, a new map version's status and colours."""
        with self.lock:
            changed = self.source.refresh()
            self._draw_status()
            if not changed:
                return
            self._draw_map()
            self._draw_views()
            if self.last_query is not None:  # a new map version: the same question again
                self._ask(*self.last_query)

    def _draw_status(self) -> None:
        rows = "".join(
            f'<tr><td>{_escape(what)}</td><td style="color:{LEVEL_COLOURS.get(level, "#000")}">'
            f"<b>{level}</b></td><td>{_escape(text)}</td></tr>"
            for what, level, text in self.source.status_rows()
        )
        version = self.source.state.version
        self.status.content = (
            f'<div id="olsplat-status" data-map-version="{version}">map version <b>{version}</b>'
            f'<table style="font-size:0.8em">{rows}</table></div>'
        )

    def _draw_views(self) -> None:
        cameras = self.source.cameras()
        for camera in cameras[self.shown_views :]:
            wxyz, position = camera_pose(camera)
            fov = 2 * np.arctan2(camera.height / 2, camera.fy)
            self.server.scene.add_camera_frustum(
                f"/flight/views/{camera.name.replace('/', '_')}",
                fov=float(fov),
                aspect=camera.width / camera.height,
                scale=4.0,
                color=(255, 140, 0),
                wxyz=wxyz,
                position=position,
            )
        if len(cameras) >= 2:
            centres = np.array([camera_pose(c)[1] for c in cameras], np.float32)
            segments = np.stack([centres[:-1], centres[1:]], axis=1)
            self.server.scene.add_line_segments(
                "/flight/path", segments, colors=(255, 140, 0), thickness=2.0, thickness_units="screen"
            )
        if len(cameras) != self.shown_views:
            names = [c.name for c in cameras]
            self.view_choice.options = ["(none)", *names]  # views are only added: the choice stays
        self.shown_views = len(cameras)

    # -- queries ------------------------------------------------------------------------------
    def _ask(self, text: str | None = None, negatives: list[str] | None = None) -> None:
        with self.lock:
            text = self.query_text.value if text is None else text
            negatives = split_negatives(self.negatives_text.value) if negatives is None else negatives
            view = self.view_choice.value if self.view_choice.value != "(none)" else ""
            since = self.since_choice.value if self.since_choice.value != "none" else ""
            self.query_message.content = f"asking *{_escape(text[:60])}* ..."
            if since:  # a run folder's source only (the dropdown is shown for it alone)
                answer = self.source.ask(text, negatives, view, since=since, gone=self.gone_box.value)
            else:
                if view:  # the view's pictures at once, small; the full answer replaces them
                    self._show_preview(self.source.ask(text, negatives, view, preview=True))
                answer = self.source.ask(text, negatives, view)
            self.query_message.content = f"**{answer.status}**: {_escape(answer.message)}" + (
                f" ({answer.seconds * 1000:.0f} ms, map v{answer.map_version})" if answer.status == "ok" else ""
            )
            if answer.status != "ok":
                return
            self.last_query = (answer.text, negatives)
            self.answer = answer
            self.geojson_button.visible = answer_geojson(answer) is not None
            shown = answer.heatmap_picture is not None
            if shown:  # the pictures first: the one thing that changes when only the view does
                self.heatmap_image.image = answer.heatmap_picture
                self.mask_image.image = answer.mask_picture
            self.heatmap_image.visible = self.mask_image.visible = shown
            question = (answer.text, tuple(negatives), answer.map_version, since, self.gone_box.value)
            if question != self.coloured:  # else a view chosen for the same question: colours stand
                assert answer.margin is not None and self.splats is not None
                self.splats.rgbs = relevance_colours(answer.margin)  # ~3.6 MB to each browser
                self.colour_bar.visible = True
                self._draw_instances(answer)
                self.coloured = question

    def _show_preview(self, preview: WebAnswer) -> None:
        """Show a preview's pictures (``ask(preview=True)``) until the full answer replaces them."""
        if preview.status != "ok" or preview.heatmap_picture is None or preview.mask_picture is None:
            return  # the full answer says why
        self.heatmap_image.image = preview.heatmap_picture
        self.mask_image.image = preview.mask_picture
        self.heatmap_image.visible = self.mask_image.visible = True
        self.query_message.content = f"*{_escape(preview.message)}* ({preview.seconds * 1000:.0f} ms) ..."
        self.previews_shown += 1

    def _draw_instances(self, answer: WebAnswer) -> None:
        for handle in self.instance_buttons:
            handle.remove()
        self.instance_buttons = []
        self.server.scene.add_frame("/query", show_axes=False)  # replaces the last query's boxes
        for i, inst in enumerate(answer.instances[:MAX_INSTANCE_BUTTONS]):
            low, high = np.asarray(inst.box_min), np.asarray(inst.box_max)
            size = high - low
            label = f"#{i} {answer.text}: {inst.gaussians:,} Gaussians, {size[0]:.0f} x {size[1]:.0f} x {size[2]:.0f} m"
            self.server.scene.add_box(
                f"/query/box_{i}",
                color=(255, 40, 40),
                dimensions=tuple(size),
                wireframe=True,
                position=(low + high) / 2,
            )
            self.server.scene.add_label(f"/query/label_{i}", label, position=high)
            with self.instances_folder:
                button = self.server.gui.add_button(label)
            button.on_click(self._flier(np.asarray(inst.centre), float(size.max())))
            self.instance_buttons.append(button)

    def _download_geojson(self, client) -> None:
        """The current answer's GeoJSON to the browser that asked, as a file."""
        with self.lock:
            text = None if self.answer is None else answer_geojson(self.answer)
        if client is not None and text is not None:
            name = "".join(c if c.isalnum() else "_" for c in self.answer.text)[:40] if self.answer else "answer"
            client.send_file_download(f"{name}.geojson", text.encode(), save_immediately=True)

    def _flier(self, centre: np.ndarray, extent: float):
        return lambda _event: self._fly(centre, extent)

    def _fly(self, centre: np.ndarray, extent: float) -> None:
        """Every connected browser's camera to look at ``centre`` from above and aside."""
        distance = max(20.0, 3.0 * extent)
        for client in self.server.get_clients().values():
            with client.atomic():
                client.camera.position = centre + np.array([distance * 0.5, -distance * 0.5, distance])
                client.camera.look_at = centre


def _escape(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def serve(page: GroundPage, seconds: float | None = None) -> None:
    """Poll and serve until Ctrl-C (or for ``seconds``)."""
    page.refresh()
    page.start()
    try:
        end = None if seconds is None else time.monotonic() + seconds
        while end is None or time.monotonic() < end:
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    finally:
        page.close()

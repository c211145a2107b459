"""``olsplat ground web`` in a real browser: Debian's headless Chromium, driven by playwright.

The page is served by the real command (a subprocess): over a run folder the real graph wrote
(the tiny replay; a post-flight review), and over the CURVE ground link of a live graph (the
tiny replay while it flies). Screenshots go to build/test-artifacts/ground_web/ (kept).
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from olsplat_nodes.launcher import Supervisor
from tests.helpers import free_port
from tests.nodes.conftest import launch_tiny
from tests.promised import skip_unless_ci

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
ARTIFACTS = Path(__file__).resolve().parents[2] / "build" / "test-artifacts" / "ground_web"


@pytest.fixture(scope="module", autouse=True)
def _chromium():
    if CHROMIUM is None:
        skip_unless_ci("browser", "Debian's chromium is not installed (make setup installs it when run as root)")


OLSPLAT = str(Path(sys.executable).parent / "olsplat")
LABELS = ["red roof buildings", "blue roof buildings", "white roof buildings", "grey roof buildings", "road", "tree"]


def serve_page(source: list[str], log: Path) -> tuple[subprocess.Popen, str]:
    """``olsplat ground web`` with ``source`` (--run ... or --connect ...), its output in
    ``log``, and its address, once it says it serves."""
    port = free_port()
    with log.open("w") as out:
        process = subprocess.Popen(
            [OLSPLAT, "ground", "web", *source, "--port", str(port)], stdout=out, stderr=subprocess.STDOUT
        )
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and process.poll() is None:
        if "ground station: http://" in log.read_text():
            return process, f"http://127.0.0.1:{port}"
        time.sleep(0.2)
    process.kill()
    raise AssertionError(f"olsplat ground web did not serve: {log.read_text()[-2000:]}")


def browser(playwright):
    return playwright.chromium.launch(
        executable_path=CHROMIUM,
        args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"],
    )


def field(page, label: str):
    """The input of the page's row labelled ``label`` (viser's labels do not point at their inputs)."""
    return page.locator(f"xpath=//label[normalize-space()='{label}']/ancestor::div[1]/parent::*//input").first


def canvas_pixels(page, name: str) -> np.ndarray:
    """A screenshot of the 3D view (left of the control panel) as [H, W, 3] uint8, kept as an artefact."""
    import cv2

    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    path = ARTIFACTS / f"{name}.png"
    page.screenshot(path=str(path), clip={"x": 0, "y": 160, "width": 860, "height": 620})
    return cv2.imread(str(path))[..., ::-1]


def splats_drawn(pixels: np.ndarray) -> bool:
    """Most of the 3D view is the map's colours, not viser's white background."""
    return bool(pixels.std() > 10 and (pixels.min(axis=2) < 200).mean() > 0.2)


def relevance_coloured(pixels: np.ndarray) -> bool:
    """The splats wear the relevance ramp (navy to yellow; a query's answer): a fifth of the view
    or more is the ramp's blue (0.3-0.4 after a query here, under 0.01 in the map's own colours)."""
    r, g, b = (pixels[..., k].astype(int) for k in range(3))
    return bool(((b > r + 40) & (b > g + 20)).mean() > 0.2)


def drawn_canvas(page, name: str, ready, timeout_s: float = 60.0) -> np.ndarray:
    """The 3D view once ``ready(pixels)`` holds: waits on the picture itself, not a fixed sleep
    (a screenshot of software WebGL takes 5-25 s here, so the first one that shows it is taken)."""
    deadline = time.monotonic() + timeout_s
    while True:
        pixels = canvas_pixels(page, name)
        if ready(pixels):
            return pixels
        if time.monotonic() > deadline:
            raise AssertionError(f"{name}: the 3D view did not show the expected picture in {timeout_s:.0f} s")
        time.sleep(0.5)


def map_version(page) -> int:
    return int(page.locator("#olsplat-status").get_attribute("data-map-version") or 0)


@pytest.fixture(scope="module")
def finished_run(tiny, tmp_path_factory):
    scene, _ = tiny
    run_dir = tmp_path_factory.mktemp("web") / "run"
    assert Supervisor(launch_tiny(scene, run_dir, free_port(), "launch.compose=true")).run() == 0
    return scene, run_dir


def test_the_page_shows_the_map_answers_a_query_and_shows_a_views_heatmap(finished_run):
    from playwright.sync_api import sync_playwright

    from olsplat_nodes.evaluate.scene_eval import label_texts, load_queries

    scene, run_dir = finished_run
    ply = scene / "map" / "point_cloud.ply"
    process, address = serve_page(["--run", str(run_dir), "--map", str(ply)], run_dir.parent / "web.log")
    try:
        with sync_playwright() as playwright:
            page = browser(playwright).new_page(viewport={"width": 1280, "height": 800})
            page.goto(address)
            page.wait_for_selector("#olsplat-status", timeout=60_000)
            page.wait_for_function(
                "() => Number(document.querySelector('#olsplat-status').dataset.mapVersion) >= 1", timeout=60_000
            )
            before = drawn_canvas(page, "1_map", splats_drawn)  # the splats arrive in the browser
            assert not relevance_coloured(before)  # in the map's own colours

            # the first negatives: the flight's labels (its queries.json lies beside the map's folder)
            assert field(page, "negatives").input_value() == ", ".join(label_texts(*load_queries(scene)))
            field(page, "negatives").fill(", ".join(LABELS[1:]))
            field(page, "query").fill(LABELS[0])
            page.get_by_role("button", name="Ask").click()
            page.get_by_text("Gaussians pick it").wait_for(timeout=60_000)
            page.get_by_role("button", name=f"#0 {LABELS[0]}").wait_for(timeout=30_000)
            drawn_canvas(page, "2_query", relevance_coloured)  # the splats take the answer's colours

            # bad input: a sentence on the page, the page keeps answering
            field(page, "query").fill("roof\u0007")
            page.get_by_role("button", name="Ask").click()
            page.get_by_text("control characters").wait_for(timeout=30_000)

            field(page, "query").fill(LABELS[0])
            width = json.loads(sorted((run_dir / "views").glob("*.json"))[0].read_text())["width"]
            # the heatmap and mask pictures are the view's width (viser's logos are not)
            pictures = (
                f"[...document.querySelectorAll('img')].filter(i => i.naturalWidth === {width} && i.offsetParent)"
            )
            assert page.evaluate(f"() => {pictures}.length") == 0  # no view chosen yet: no heatmap, no mask
            field(page, "view").click()
            page.get_by_role("option").nth(1).click()  # the first view ("(none)" is option 0)
            page.wait_for_function(f"() => {pictures}.length >= 2", timeout=60_000)
            page.screenshot(path=str(ARTIFACTS / "3_view.png"), full_page=True)
            assert map_version(page) >= 1
    finally:
        process.terminate()
        process.wait(timeout=30)


def wait_map_version(page, condition: str, timeout_ms: int) -> None:
    page.wait_for_function(
        f"() => Number(document.querySelector('#olsplat-status').dataset.mapVersion) {condition}", timeout=timeout_ms
    )


def test_the_page_follows_a_live_graph_over_the_curve_link_without_a_reload(tiny, tmp_path):
    """The page is opened on the ground link before the drone's graph runs ("link lost -
    retrying"), then, over CURVE, shows the prior map the drone sends, "no map yet", each new
    map version up to the final one without a reload, the nodes' levels, and answers a query;
    when the drone goes away it says so again."""
    from playwright.sync_api import sync_playwright

    from olsplat_nodes.storage import latest_map
    from olsplat_nodes.transport import curve

    scene, _ = tiny
    _, server_secret = curve.generate(tmp_path / "server", "query_server")
    ground_public, ground_secret = curve.generate(tmp_path / "ground", "ground")
    (tmp_path / "allow").mkdir()
    shutil.copy(ground_public, tmp_path / "allow")
    port = free_port()
    link = [
        "--connect",
        f"tcp://127.0.0.1:{port}",
        "--client-key",
        str(ground_secret),
        "--server-key",
        str(tmp_path / "server" / "query_server.key"),
        "--timeout",
        "3",
    ]
    process, address = serve_page(link, tmp_path / "web.log")
    run_dir = tmp_path / "run"
    supervisor = Supervisor(
        launch_tiny(
            scene,
            run_dir,
            port,
            "refiner.period_s=1",
            f"query_server.server_secret={server_secret}",
            f"query_server.allow_dir={tmp_path / 'allow'}",
            "launch.exit_when=[]",  # the drone stays up after the final map, until stopped
        )
    )
    seen: list[int] = []
    graph = threading.Thread(target=supervisor.run)
    try:
        with sync_playwright() as playwright:
            page = browser(playwright).new_page(viewport={"width": 1280, "height": 800})
            page.goto(address)
            page.wait_for_selector("#olsplat-status", timeout=60_000)
            page.get_by_text("link lost - retrying").first.wait_for(timeout=30_000)
            seen.append(map_version(page))
            graph.start()
            page.get_by_text(re.compile(r"Gaussians.* drawn")).first.wait_for(timeout=120_000)  # the prior map came
            final = None
            while final is None or not final["final"] or map_version(page) < final["version"]:
                assert graph.is_alive() and len(seen) < 3000, "the flight did not reach its final map in 10 min"
                seen.append(map_version(page))
                final = latest_map(run_dir / "map")
                time.sleep(0.2)
            page.get_by_text("final (the flight ended)").wait_for(timeout=10_000)
            seen.append(map_version(page))
            for node in ("accumulator", "refiner", "region_encoder"):
                assert page.locator("#olsplat-status td", has_text=node).count() >= 1, f"{node} not in the status"
            assert page.locator("#olsplat-status", has_text="CURVE").count() == 1

            # a query over the link answers on the page (that the answer recolours the splats is the
            # run-folder test's: the same page code, and each settled screenshot costs 5-25 s of
            # software WebGL here)
            field(page, "negatives").fill(", ".join(LABELS[1:]))
            field(page, "query").fill(LABELS[0])
            page.get_by_role("button", name="Ask").click()
            page.get_by_text("Gaussians pick it").wait_for(timeout=60_000)
            page.get_by_role("button", name=f"#0 {LABELS[0]}").wait_for(timeout=30_000)

            supervisor.request_stop()  # the drone goes away: the page says so, and keeps its map
            graph.join(120)
            page.get_by_text("link lost - retrying").first.wait_for(timeout=30_000)
            page.get_by_text("last heard").first.wait_for(timeout=10_000)
            assert splats_drawn(canvas_pixels(page, "6_link_lost"))  # the drone went away: the map stays
    finally:
        supervisor.request_stop()
        if graph.is_alive():
            graph.join(120)
        process.terminate()
        process.wait(timeout=30)
    versions = sorted(set(seen))
    assert seen[0] == 0 and seen == sorted(seen), seen  # never goes back
    assert versions[-1] == final["version"] and len(versions) >= 2, versions


def test_the_page_follows_a_run_folder_being_written_without_a_reload(tiny, tmp_path):
    """On the machine that holds the run folder, the page opened before the flight ("no map
    yet") shows each new map version the graph writes, up to the final one."""
    from playwright.sync_api import sync_playwright

    from olsplat_nodes.storage import latest_map

    scene, _ = tiny
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    ply = scene / "map" / "point_cloud.ply"
    process, address = serve_page(["--run", str(run_dir), "--map", str(ply)], tmp_path / "web.log")
    seen: list[int] = []
    try:
        with sync_playwright() as playwright:
            page = browser(playwright).new_page(viewport={"width": 1280, "height": 800})
            page.goto(address)
            page.wait_for_selector("#olsplat-status", timeout=60_000)
            page.get_by_text("no map yet").wait_for(timeout=30_000)
            seen.append(map_version(page))
            graph = threading.Thread(
                target=lambda: Supervisor(launch_tiny(scene, run_dir, free_port(), "refiner.period_s=1")).run()
            )
            graph.start()
            while graph.is_alive():
                seen.append(map_version(page))
                time.sleep(0.2)
            final = latest_map(run_dir / "map")
            assert final is not None and final["final"]
            wait_map_version(page, f"=== {final['version']}", 30_000)
            page.get_by_text("final (the flight ended)").wait_for(timeout=10_000)
            seen.append(map_version(page))
    finally:
        process.terminate()
        process.wait(timeout=30)
    versions = sorted(set(seen))
    assert seen[0] == 0 and seen == sorted(seen), seen  # never goes back
    assert versions[-1] == final["version"] and len(versions) >= 2, versions

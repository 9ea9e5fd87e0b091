"""`hfrad view` end to end in a real headless browser (Debian's chromium, driven by Playwright).

The page must load without console errors; moving the light's intensity
slider in the page must change the drawn picture the right way (darker at 0,
brighter at the top of the range) within a stated time.
"""

from __future__ import annotations

import io
import os
import shutil
import socket
import time

import numpy as np
import pytest

import hfrad

CHROMIUM = os.environ.get("HFRAD_CHROMIUM", "/usr/bin/chromium")
#: Longest accepted time from a slider key press to the changed picture on screen, seconds.
#: Generous: chromium draws with SwiftShader (software WebGL) on a shared 2-core machine.
ARRIVAL_LIMIT = 5.0

sync_api = pytest.importorskip("playwright.sync_api", reason="needs Playwright (pip install playwright)")
if not (os.path.exists(CHROMIUM) or shutil.which("chromium")):
    pytest.skip(f"needs chromium at {CHROMIUM} (apt-get install chromium) or HFRAD_CHROMIUM",
                allow_module_level=True)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def view_stats(page) -> np.ndarray:
    """(mean luminance, fraction of dark pixels) of the 3D view, right of the notifications, left of the panel."""
    from PIL import Image

    png = page.screenshot(clip={"x": 330, "y": 170, "width": 440, "height": 560})
    rgb = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.float64)
    lum = rgb @ [0.2126, 0.7152, 0.0722]
    return np.array([lum.mean(), (lum < 20).mean()])


def wait_change(page, before: np.ndarray, limit: float) -> tuple[np.ndarray, float]:
    t0 = time.perf_counter()
    while True:
        now = view_stats(page)
        if abs(now[0] - before[0]) > 3.0 or time.perf_counter() - t0 > limit:
            return now, time.perf_counter() - t0
        page.wait_for_timeout(50)


def test_page_relights_in_browser(tmp_path):
    from hfrad.viewer import ViewerApp

    scene = hfrad.load_scene("cornell", patches=500)
    fac = hfrad.factorize(scene, eps=0.05)
    app = ViewerApp(fac, port=free_port(), save_dir=tmp_path)
    problems = []
    try:
        with sync_api.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM if os.path.exists(CHROMIUM) else
                                        shutil.which("chromium"),
                                        args=["--use-angle=swiftshader", "--enable-unsafe-swiftshader"])
            page = browser.new_page(viewport={"width": 1200, "height": 800})
            page.on("console", lambda m: problems.append(m.text) if m.type == "error" else None)
            page.on("pageerror", lambda e: problems.append(str(e)))
            page.goto(app.url)                                   # with its ?token=...
            # loading viser's 0.8 MB client under SwiftShader took 13-31 s at load average 15-18 on 2 cores
            page.get_by_text("Connected").first.wait_for(timeout=60_000)
            # the mesh is drawn once the picture is no longer plain background
            t0 = time.perf_counter()
            while view_stats(page)[0] > 250 and time.perf_counter() - t0 < 20:
                page.wait_for_timeout(100)
            # fixed exposure, so the picture follows the light's intensity
            page.get_by_role("checkbox").nth(1).uncheck()   # 0: the light's "on", 1: "auto exposure"
            assert app.wait_idle(10)
            page.wait_for_timeout(500)
            before = view_stats(page)
            assert before[0] < 250, "the radiosity mesh was never drawn"

            intensity = page.get_by_role("slider").first       # the light's intensity (17 W/m2)
            assert intensity.get_attribute("aria-valuenow") == "17"
            intensity.focus()
            page.keyboard.press("Home")                          # 0 W/m2: no light, black room
            dark, t_dark = wait_change(page, before, ARRIVAL_LIMIT)
            page.keyboard.press("End")                           # 4 x 17 W/m2
            bright, t_bright = wait_change(page, dark, ARRIVAL_LIMIT)
            assert intensity.get_attribute("aria-valuenow") == "68"
            # "save PNG": the tab's view through `hfrad render`'s renderer, downloaded by the browser
            with page.expect_download(timeout=30_000) as download:
                page.get_by_role("button", name="save PNG").click()
            saved = tmp_path / "download.png"
            download.value.save_as(saved)
            saved_name = download.value.suggested_filename
            # a browser without the token (a fresh context: no cookie) gets the refusal, not the page
            stranger = browser.new_page()
            refused = stranger.goto(app.url.split("?")[0])
            assert refused.status == 403 and "refused" in stranger.inner_text("body")
            browser.close()
    finally:
        app.close()
    print(f"\nbrowser: mean luminance {before[0]:.1f} -> {dark[0]:.1f} (intensity 0, {t_dark:.2f} s) -> "
          f"{bright[0]:.1f} (intensity 68 W/m2, {t_bright:.2f} s); server: solve {1e3 * app.last.solve:.2f} ms, "
          f"colours sent {1e3 * app.last.sent:.1f} ms after the change")
    assert not problems, f"console errors: {problems}"
    assert app.state.emitters[0].intensity == 68.0
    assert dark[0] < before[0] - 20 and dark[1] > before[1] + 0.2    # the room went dark
    assert bright[0] > before[0] + 5                                 # and brighter than at 17 W/m2
    assert t_dark < ARRIVAL_LIMIT and t_bright < ARRIVAL_LIMIT
    from PIL import Image
    picture = np.asarray(Image.open(saved).convert("RGB"))
    assert picture.shape[0] == 720 and abs(picture.shape[1] / 720 - 1200 / 800) < 0.02   # the tab's aspect
    assert picture.mean() > 10                                                          # lit, not blank
    assert (tmp_path / saved_name).exists()                      # also in --save-dir

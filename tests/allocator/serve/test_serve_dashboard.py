"""The dashboard in a real headless Chromium (Debian's ``chromium``, driven by Playwright):
loaded from a running ``agv serve --simulate``, its AGVs appear and move; a screenshot is
saved (to the test's folder; with ``AGV_UPDATE_FIGURES=1`` also to
``docs/figures/service_dashboard.png``, the figure of docs/service.md)."""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path

import httpx
import pytest

import sim
from allocator.serve.process import ServiceProcess

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser") or "/usr/bin/chromium"
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync"]
FIGURE = Path(__file__).resolve().parents[3] / "docs" / "figures" / "service_dashboard.png"

pytestmark = pytest.mark.skipif(not os.path.exists(CHROMIUM),
                                reason=f"no Chromium binary at {CHROMIUM} (Debian: apt-get "
                                "install chromium)")


def test_dashboard_shows_agvs_moving(tmp_path) -> None:
    sync_api = pytest.importorskip("playwright.sync_api",
                                   reason="needs playwright (the [serve-test] extra)")
    w = sim.warehouse_floor(20)
    svc = ServiceProcess(tmp_path, ["--simulate", "warehouse-20", "--sim-faults",
                                    "0.002:40"]).start()
    try:
        with httpx.Client(base_url=svc.url, headers=svc.headers) as c:
            orders = [{"id": f"d-{k}", "pickup": w.pickups[(7 * k) % len(w.pickups)].tolist(),
                       "dropoff": w.stations[k % len(w.stations)].tolist()}
                      for k in range(30)]
            assert c.post("/v1/orders", json={"orders": orders}).status_code == 201
        with sync_api.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=FLAGS,
                                        headless=True)
            try:
                page = browser.new_page(viewport={"width": 1200, "height": 800})
                errors: list[str] = []
                page.on("pageerror", lambda e: errors.append(str(e)))
                page.goto(f"{svc.url}/#key={svc.key}")
                page.wait_for_function("() => window.agvDashboard.plan && "
                                       "window.agvDashboard.plan.agents.length === 20",
                                       timeout=30_000)
                assert page.text_content("#conn") == "live"
                assert "key=" not in page.url  # the key leaves the address bar
                first = page.evaluate("() => window.agvDashboard.plan.agents.map("
                                      "a => a.position)")
                frames = page.evaluate("() => window.agvDashboard.frames")
                # Polled, not a fixed sleep: on a loaded machine the service's first plans
                # (the floor's distance table, a cold solve) can take several seconds.
                deadline = time.monotonic() + 60.0
                moved = 0
                while moved < 3 and time.monotonic() < deadline:
                    time.sleep(0.5)
                    later = page.evaluate("() => window.agvDashboard.plan.agents.map("
                                          "a => a.position)")
                    moved = sum(abs(a[0] - b[0]) + abs(a[1] - b[1]) > 0.05
                                for a, b in zip(first, later, strict=True))
                assert moved >= 3, f"only {moved} AGVs moved in 60 s"
                assert page.evaluate("() => window.agvDashboard.frames") > frames
                # Something was drawn: the canvas is not blank.
                painted = page.evaluate("""() => {
                    const c = document.getElementById('floor');
                    const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
                    let n = 0; for (let i = 0; i < d.length; i += 4) if (d[i + 3]) n++;
                    return n; }""")
                assert painted > 10_000
                time.sleep(2.0)
                assert int(page.text_content("#f-agents")) == 20
                shot = tmp_path / "service_dashboard.png"
                page.screenshot(path=str(shot))
                assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
                if os.environ.get("AGV_UPDATE_FIGURES") == "1":
                    FIGURE.parent.mkdir(parents=True, exist_ok=True)
                    FIGURE.write_bytes(shot.read_bytes())
                assert not errors, errors
            finally:
                browser.close()
    finally:
        svc.stop()


def test_wrong_key_asks_for_the_key(tmp_path, service) -> None:
    sync_api = pytest.importorskip("playwright.sync_api",
                                   reason="needs playwright (the [serve-test] extra)")
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=FLAGS, headless=True)
        try:
            page = browser.new_page()
            page.goto(f"{service.url}/#key=not-the-right-key-at-all")
            page.wait_for_function("() => document.getElementById('conn').textContent "
                                   "=== 'wrong API key'", timeout=20_000)
            assert page.is_visible("#key")
            page.fill("#key", service.key)
            page.click("button[type=submit]")
            page.wait_for_function("() => window.agvDashboard.floor !== null",
                                   timeout=20_000)
        finally:
            browser.close()

"""`e3dpsm serve` in a real browser: headless Chromium (Debian's chromium + chromedriver) driven
by Selenium opens the URL the command prints (with its token), which must trade the token for a
cookie and land on the clean URL, run its script and style under the page's Content-Security-
Policy, connect, draw skeleton updates and show a rate; reopened at the clean URL, the cookie
alone must let it draw again.
Skipped, with the reason, where the browser, its driver or selenium is absent (.ci/run
installs them when it can)."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from _runtime_helpers import exported_tiny
from _serve_helpers import ServerProcess, write_recording

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMEDRIVER = shutil.which("chromedriver") or "/usr/bin/chromedriver"
MIN_POSES = 20
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--window-size=1000,700")


def headless_chromium(user_data_dir: Path):
    """A Selenium driver of headless Chromium, or pytest.skip saying what is missing."""
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed (pip install -e .[test])")
    for path in (CHROMIUM, CHROMEDRIVER):
        if not Path(path).exists():
            pytest.skip(f"{path} is absent (apt-get install chromium chromium-driver)")
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in (*CHROMIUM_FLAGS, f"--user-data-dir={user_data_dir}"):
        options.add_argument(flag)
    return webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)


def test_printed_url_draws_poses_under_the_csp_and_the_cookie_reopens_it(tmp_path_factory, tmp_path):
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    graph = exported_tiny(str(tmp_path_factory.getbasetemp()))[1]
    recording = write_recording(tmp_path / "seq", 60)
    driver = headless_chromium(tmp_path / "chromium-profile")
    out = tmp_path / "report"
    try:
        with ServerProcess(["--model", str(graph), "--source", str(recording), "--loop", "--wait-clients", "1",
                            "--threads", "1", "--out", str(out)]) as server:
            driver.get(server.url)
            clean_url = driver.current_url  # after the redirect that set the cookie
            wait = WebDriverWait(driver, 60, poll_frequency=0.1)
            wait.until(lambda d: int(d.find_element(By.ID, "pose-count").text) >= MIN_POSES)
            # The rate readout refreshes once a second: wait for a number there.
            wait.until(lambda d: d.find_element(By.ID, "hz").text.strip().isdigit())
            wait.until(lambda d: d.find_element(By.ID, "latency").text.strip() != "–")
            hz = int(driver.find_element(By.ID, "hz").text)
            page = driver.execute_script(
                "return {count: e3dpsm.poseCount, received: e3dpsm.received, gaps: e3dpsm.gaps, "
                "outOfOrder: e3dpsm.outOfOrder, lat: e3dpsm.latencies.slice(0, 50), legend: "
                "document.getElementById('legend').textContent, status: document.getElementById('status').textContent}")
            # The skeleton canvas has been drawn on: some pixel is not the background.
            painted = driver.execute_script(
                "const c = document.getElementById('skeleton'); const d = c.getContext('2d')"
                ".getImageData(0, 0, c.width, c.height).data; let n = 0; "
                "for (let i = 3; i < d.length; i += 4) if (d[i]) n++; return n;")
            driver.save_screenshot(str(tmp_path / "serve.png"))
            cookies = driver.get_cookies()
            script_sees = driver.execute_script("return document.cookie")
            background = driver.execute_script("return getComputedStyle(document.body).backgroundColor")
            driver.get(clean_url)  # a fresh page load: only the cookie carries the token now
            wait.until(lambda d: int(d.find_element(By.ID, "pose-count").text) >= 5)
            reopened = driver.execute_script("return {count: e3dpsm.poseCount, gaps: e3dpsm.gaps, "
                                             "status: document.getElementById('status').textContent}")
            server.interrupt()
            rc, _, stderr = server.wait(timeout_s=30)
    finally:
        driver.quit()
    assert rc == 0, stderr
    assert clean_url == f"http://127.0.0.1:{server.port}/"  # the token left the address bar
    assert [(c["name"], c["httpOnly"], c["sameSite"], c["path"]) for c in cookies] == [
        (f"e3dpsm-serve-{server.port}", True, "Strict", "/")]
    assert script_sees == "" and server.token not in cookies[0]["value"]  # HttpOnly: no script reads it
    assert background == "rgb(21, 23, 28)"  # the inlined style ran under the CSP (its hash admitted it)
    assert reopened["count"] >= 5 and reopened["gaps"] == 0 and "disconnected" not in reopened["status"]
    assert page["count"] >= MIN_POSES and page["received"] >= page["count"] - 1
    assert page["gaps"] == 0 and page["outOfOrder"] == 0
    assert 1 <= hz <= 80  # 50 Hz replay; a loaded machine draws fewer, never more than the server sends
    assert "ground truth" in page["legend"] and "tiny_step.onnx" in page["legend"]
    assert painted > 200
    assert all(0 <= value < 5000 for value in page["lat"])  # window end -> drawn, same clock
    assert (tmp_path / "serve.png").stat().st_size > 10_000
    report = json.loads((out / "serve.report.json").read_text())
    assert report["latency_ms"]["page"]["count"] > 0  # the page reported what it measured
    assert report["clients"][0]["page"]["drawn"] > 0 and "Chrome" in report["clients"][0]["agent"]

"""The live view in a real browser: ``up --live`` opened in headless Chromium.

The browser is driven over the DevTools protocol on a pipe
(``--remote-debugging-pipe``: fd 3 in, fd 4 out, NUL-separated JSON), with
the standard library only. Skipped, with the reason, where Chromium or the
rerun-sdk package is missing or Chromium cannot start.
"""
from __future__ import annotations

import base64
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from diskf_mesh.live.view import MOBILE, STATIC, CHI2_95_2D, covariance_ellipses
from sim.launcher import free_port

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1"]  # nothing leaves the machine
WINDOW = (1100, 700)
SLOW = 240.0  # seconds: the Wasm viewer in a software rasteriser on a busy 2-core machine is slow to start


class Browser:
    """Headless Chromium over the DevTools protocol on a pipe."""

    def __init__(self, exe: str, user_data_dir: str):
        to_r, to_w = os.pipe()
        from_r, from_w = os.pipe()

        def fds():
            os.dup2(to_r, 3)
            os.dup2(from_w, 4)

        self.proc = subprocess.Popen([exe, *FLAGS, f"--user-data-dir={user_data_dir}", "--remote-debugging-pipe",
                                      f"--window-size={WINDOW[0]},{WINDOW[1]}", "about:blank"],
                                     pass_fds=(3, 4), preexec_fn=fds, stdin=subprocess.DEVNULL,
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        os.close(to_r)
        os.close(from_w)
        self._w, self._r, self._buf, self._id, self.session = to_w, from_r, b"", 0, None

    def call(self, method: str, params=None, timeout: float = 60.0):
        self._id += 1
        msg = {"id": self._id, "method": method, "params": params or {}}
        if self.session:
            msg["sessionId"] = self.session
        os.write(self._w, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + timeout
        while True:
            while b"\0" not in self._buf:
                if time.monotonic() > deadline:
                    raise TimeoutError(method)
                chunk = os.read(self._r, 1 << 20)
                if not chunk:
                    raise RuntimeError("the browser closed its pipe")
                self._buf += chunk
            raw, self._buf = self._buf.split(b"\0", 1)
            m = json.loads(raw)
            if m.get("id") == self._id:
                if "error" in m:
                    raise RuntimeError(f"{method}: {m['error']}")
                return m["result"]

    def open(self, url: str) -> None:
        target = self.call("Target.createTarget", {"url": url})["targetId"]
        self.session = self.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]

    def eval(self, expression: str):
        return self.call("Runtime.evaluate", {"expression": expression, "returnByValue": True})["result"].get("value")

    def screenshot(self) -> bytes:
        return base64.b64decode(self.call("Page.captureScreenshot", {"format": "png"}, timeout=SLOW)["data"])

    def close(self) -> None:
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.proc.wait(10)
        os.close(self._w)
        os.close(self._r)


def wait_for(what: str, check, timeout: float = SLOW, every: float = 0.25):
    deadline = time.monotonic() + timeout
    while True:
        value = check()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(every)


def pixels(png: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)


def blobs(img: np.ndarray, rgb, tol: int = 40, min_px: int = 12) -> int:
    """Connected regions (4-neighbour) of at least ``min_px`` pixels within
    ``tol`` of colour ``rgb``: the rendered agents."""
    mask = (np.abs(img - np.array(rgb)) <= tol).all(axis=-1)
    seen = np.zeros_like(mask)
    count = 0
    for y, x in zip(*np.nonzero(mask)):
        if seen[y, x]:
            continue
        stack, size = [(y, x)], 0
        seen[y, x] = True
        while stack:
            cy, cx = stack.pop()
            size += 1
            for ny, nx in ((cy + 1, cx), (cy - 1, cx), (cy, cx + 1), (cy, cx - 1)):
                if 0 <= ny < mask.shape[0] and 0 <= nx < mask.shape[1] and mask[ny, nx] and not seen[ny, nx]:
                    seen[ny, nx] = True
                    stack.append((ny, nx))
        count += size >= min_px
    return count


def chromium_or_skip(tmp: str) -> Browser:
    if CHROMIUM is None:
        pytest.skip("no chromium on this machine (Debian: apt-get install chromium; .ci/run installs it)")
    pytest.importorskip("rerun", reason="the live view needs rerun-sdk (pip install 'diskf-mesh[live]')")
    pytest.importorskip("PIL", reason="reading the screenshots needs Pillow (a dependency of rerun-sdk)")
    b = Browser(CHROMIUM, tmp)
    try:
        b.call("Browser.getVersion", timeout=60)
    except (RuntimeError, TimeoutError, OSError) as e:
        b.close()
        pytest.skip(f"chromium cannot run here: {e}")
    return b


def status(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def test_covariance_ellipse_is_the_95_percent_contour():
    mean = np.array([[1.0, -2.0], [0.0, 0.0]])
    P = np.array([[[4.0, 1.0], [1.0, 2.0]], [[1.0, 0.0], [0.0, 9.0]]])
    e = covariance_ellipses(mean, P)
    d = e - mean[:, None, :]
    q = np.einsum("npi,nij,npj->np", d, np.linalg.inv(P), d)
    np.testing.assert_allclose(q, CHI2_95_2D, rtol=1e-12)
    np.testing.assert_allclose(e[:, 0], e[:, -1], atol=1e-12)  # closed
    # the axis-aligned one reaches sqrt(chi2 * variance) along each axis
    np.testing.assert_allclose(np.abs(d[1]).max(axis=0), np.sqrt(CHI2_95_2D * np.array([1.0, 9.0])), rtol=1e-3)


def test_live_view_renders_the_run_in_a_browser(tmp_path):
    profile = tempfile.mkdtemp(prefix="diskf-chromium-")
    browser = chromium_or_skip(profile)
    port = free_port()
    logs = tmp_path / "logs"
    state = logs / "live-status.json"
    # a long run: the test watches a part of it, then stops it (Ctrl-C)
    up = subprocess.Popen([sys.executable, "-m", "sim.launcher", "--scenario", "dynamic", "--ticks", "50000",
                           "--live", str(port), "--logs", str(logs), "--json", str(tmp_path / "r.json"), "--quiet"],
                          stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                          start_new_session=True)
    lines = []
    threading.Thread(target=lambda: lines.extend(up.stderr), daemon=True).start()
    try:
        url = wait_for("the live view's address", lambda: next((ln.split()[-1] for ln in lines
                                                               if ln.startswith("live view: ")), None), 120)
        assert url.startswith(f"http://127.0.0.1:{port}/")
        # nobody watches yet: the viewer holds no zenoh session while the run ticks
        wait_for("the viewer to start", lambda: state.exists(), 120)
        assert status(state)["watching"] is False and status(state)["frames"] == 0

        browser.open(url)
        wait_for("the viewer's page to start (its canvas shown)",
                 lambda: browser.eval("document.getElementById('the_canvas_id')?.classList.contains('visible')"))
        wait_for("the view to subscribe and show ticks", lambda: status(state).get("shown", 0) > 2)
        shots = []
        for _ in range(2):
            time.sleep(3.0)
            before = status(state)["tick"]
            wait_for("a new tick", lambda: status(state)["tick"] > before + 10)
            time.sleep(1.0)  # for the page to draw it
            png = browser.screenshot()
            shots.append((status(state)["tick"], png))
        (tmp_path / "live-a.png").write_bytes(shots[0][1])
        (tmp_path / "live-b.png").write_bytes(shots[1][1])
        (ka, a), (kb, b) = [(k, pixels(png)) for k, png in shots]
        assert kb > ka  # two different ticks went to the view
        assert a.shape == b.shape == (WINDOW[1], WINDOW[0], 3)
        changed = (np.abs(a - b).sum(axis=-1) > 30).sum()
        assert changed > 500, f"only {changed} pixels differ between ticks {ka} and {kb}"
        for img in (a, b):  # the agents are drawn: 4 static (red) and 5 mobile (green), some may overlap
            assert blobs(img, STATIC) >= 2 and blobs(img, MOBILE) >= 2, (blobs(img, STATIC), blobs(img, MOBILE))

        browser.close()  # nobody watches any more: the viewer drops its zenoh session
        wait_for("the view to stop watching", lambda: status(state).get("watching") is False, 60)
        shown = status(state)["frames"]
        time.sleep(2.0)
        assert status(state)["frames"] == shown
    finally:
        if browser.proc.poll() is None:
            browser.close()
        shutil.rmtree(profile, ignore_errors=True)
        if up.poll() is None:
            up.send_signal(signal.SIGINT)
            try:
                up.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(up.pid, signal.SIGKILL)
                up.wait(10)

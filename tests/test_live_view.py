"""The live view in a real browser: ``up --live`` opened in headless Chromium.

The browser is driven over the DevTools protocol on a pipe
(``--remote-debugging-pipe``: fd 3 in, fd 4 out, NUL-separated JSON), with
the standard library only. Skipped, with the reason, where Chromium is
missing or cannot start.
"""
from __future__ import annotations

import base64
import io
import json
import os
import select
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
from PIL import Image

from diskf_mesh.live.view import MOBILE, STATIC, CHI2_95_2D, covariance_ellipses
from sim.launcher import free_port

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1",  # nothing leaves the machine
         # the page draws on animation frames: never throttle them (headless counts as hidden)
         "--disable-renderer-backgrounding", "--disable-background-timer-throttling",
         "--disable-backgrounding-occluded-windows"]
WINDOW = (1100, 700)
SLOW = 180.0  # seconds: generous, for a slow or busy 2-core machine


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
                left = deadline - time.monotonic()
                if left <= 0 or not select.select([self._r], [], [], left)[0]:
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
        """Load ``url`` in the browser's first page (the foreground one)."""
        pages = [t for t in self.call("Target.getTargets")["targetInfos"] if t["type"] == "page"]
        self.session = self.call("Target.attachToTarget", {"targetId": pages[0]["targetId"],
                                                           "flatten": True})["sessionId"]
        self.call("Page.enable")
        self.call("Emulation.setFocusEmulationEnabled", {"enabled": True})
        self.call("Emulation.setDeviceMetricsOverride", {"width": WINDOW[0], "height": WINDOW[1],
                                                         "deviceScaleFactor": 1, "mobile": False})
        self.call("Page.navigate", {"url": url})

    def eval(self, expression: str):
        return self.call("Runtime.evaluate", {"expression": expression, "returnByValue": True})["result"].get("value")

    def screenshot(self) -> bytes:
        return base64.b64decode(self.call("Page.captureScreenshot", {"format": "png"}, timeout=120)["data"])

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
        page_tick = lambda: int(browser.eval("document.body.dataset.tick") or 0)  # noqa: E731
        wait_for("the page to draw a tick", lambda: page_tick() > 0)
        assert status(state)["watching"] is True
        shots = []
        for _ in range(2):
            before = page_tick()
            wait_for("the page to draw a later tick", lambda: page_tick() > before + 5)
            tick, png = page_tick(), browser.screenshot()
            shots.append((tick, png, browser.eval("document.body.dataset.agents"),
                          browser.eval("document.querySelectorAll('#mesh circle.agent').length"),
                          browser.eval("(r => [r.left, r.top, r.right, r.bottom])"
                                       "(document.getElementById('mesh').getBoundingClientRect())")))
        (tmp_path / "live-a.png").write_bytes(shots[0][1])
        (tmp_path / "live-b.png").write_bytes(shots[1][1])
        assert shots[1][0] > shots[0][0]  # two different ticks were drawn
        a, b = pixels(shots[0][1]), pixels(shots[1][1])
        assert a.shape == b.shape == (WINDOW[1], WINDOW[0], 3)
        changed = (np.abs(a - b).sum(axis=-1) > 30).sum()
        assert changed > 500, f"only {changed} pixels differ between ticks {shots[0][0]} and {shots[1][0]}"
        for (tick, _, agents, circles, rect), img in zip(shots, (a, b)):
            assert agents == "9" and circles == 9  # every agent of Scenario 2 drawn
            x0, y0, x1, y1 = (int(round(v)) for v in rect)
            mesh = img[max(y0, 0):y1, max(x0, 0):x1]
            # on screen: 4 static (red) and 5 mobile (green) discs; two may overlap at a tick
            assert blobs(mesh, STATIC) >= 3 and blobs(mesh, MOBILE) >= 3, (tick, blobs(mesh, STATIC),
                                                                          blobs(mesh, MOBILE))

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


# --------------------------------------------------------------------------
# the frames, without a browser or a mesh
# --------------------------------------------------------------------------
def _engine_run(ticks: int = 60):
    from diskf_mesh.engine import batch as engine
    from diskf_mesh.mesh.runspec import RunSpec
    from diskf_mesh.data.scenario import simulate

    scn = RunSpec().load(ticks)
    trace = simulate(scn, [0])
    return scn, trace, engine.run(trace, "diskf", scn.params)


def _samples(scn, trace, est, k: int, live=None):
    from diskf_mesh.mesh import wire

    ids = [a.id for a in scn.agents]
    live = tuple(ids if live is None else live)
    tick = wire.Tick("r", k, trace.has.shape[1], 0, "diskf", scn.topology, scn.comm_range, trace.positions[k - 1],
                     live)
    reports = [wire.Report("r", i, k, est.x[0, k - 1, j], est.P[0, k - 1, j], est.d[0, k - 1, j],
                           bool(est.d_valid[0, k - 1, j]), {"published": k, "fused": 2 * k})
               for j, i in enumerate(ids) if i in live]
    return tick, reports


def test_frames_show_the_engine_errors_whatever_the_order_of_arrival():
    """Reports may come before their tick or after the next one: every frame
    still holds every report of its tick, in tick order, and the running MAE
    is ``experiment``'s MAE(state) over the ticks shown."""
    from diskf_mesh.data import metrics
    from diskf_mesh.live.view import LiveView

    scn, trace, est = _engine_run()
    K = trace.has.shape[1]
    view = LiveView(scn, trace)
    frames = []
    samples = [_samples(scn, trace, est, k) for k in range(1, K + 1)]
    for k in range(1, K + 1):
        tick, reports = samples[k - 1]
        if k % 3 == 0:   # all reports before their tick
            for r in reports:
                view.on_report(r)
            view.on_tick(tick)
        else:            # the tick, half of the reports, the next tick, the rest
            view.on_tick(tick)
            for r in reports[:4]:
                view.on_report(r)
            if k < K:
                view.on_tick(samples[k][0])
            for r in reports[4:]:
                view.on_report(r)
        if (f := view.take()) is not None:
            frames.append(f)
    view.on_stop()
    if (f := view.take()) is not None:
        frames.append(f)
    assert view.frames == K and view.late == 0
    assert [f.tick for f in frames] == sorted({f.tick for f in frames})  # newest only, in order
    e_state = metrics.errors(trace, est)[0][0]
    last = frames[-1]
    assert last.tick == K and last.reported.all()
    np.testing.assert_allclose(last.error, e_state[K - 1], rtol=1e-12)
    np.testing.assert_allclose(last.estimate, est.x[0, K - 1][:, list(trace.position_dims)])
    assert last.running_mae == pytest.approx(metrics.compute(trace, est)["mae_state"], rel=1e-12)
    assert last.counters[scn.agents[0].id] == {"published": K, "fused": 2 * K}


def test_frame_links_are_those_of_the_tick_between_live_agents():
    from diskf_mesh.live.view import LiveView
    from diskf_mesh.data.scenario import links_for

    scn, trace, est = _engine_run(20)
    k, ids = 7, [a.id for a in scn.agents]
    gone = ids[4]
    view = LiveView(scn, trace)
    tick, reports = _samples(scn, trace, est, k, live=[i for i in ids if i != gone])
    view.on_tick(tick)
    for r in reports:
        view.on_report(r)  # every live agent reported: the frame is made at once
    f = view.take()
    L = links_for(scn, trace.positions[k - 1:k])[0]
    want = {(i, j) for i in range(len(ids)) for j in range(i + 1, len(ids)) if L[i, j] and gone not in (ids[i], ids[j])}
    assert set(f.links) == want and not f.live[4] and not f.reported[4] and np.isnan(f.error[4])
    np.testing.assert_allclose(f.truth, trace.truth_x[0, k - 1, list(trace.position_dims)])


@pytest.mark.parametrize("flag", [["--live", "70000"], ["--live", "x"]])
def test_up_live_bad_port_is_an_input_error(tmp_path, flag):
    done = subprocess.run([sys.executable, "-m", "sim.launcher", "--ticks", "5", "--logs", str(tmp_path), *flag],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert len(done.stderr.strip().splitlines()) == 1 and done.stderr.startswith("error:")
    assert not list(tmp_path.glob("*.log"))  # nothing was started

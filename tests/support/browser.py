"""A page opened in a real headless Chromium over the DevTools protocol: what it logged, the
exceptions it threw, and the state of its images once loaded (for the HTML report's test)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome")


def chromium() -> str | None:
    """The Chromium executable on PATH (Debian's `chromium`, `make setup-test` installs it)."""
    return next((p for p in map(shutil.which, CHROMIUM_NAMES) if p), None)


@dataclass
class PageReport:
    errors: list[str] = field(default_factory=list)  # console errors, exceptions, failed loads
    images: list[dict] = field(default_factory=list)  # {src prefix, complete, width, height}
    title: str = ""
    text_length: int = 0


def open_page(path: Path, timeout: float = 60.0) -> PageReport:
    """Load `path` (file://) in headless Chromium and report what happened."""
    from websockets.sync.client import connect

    exe = chromium()
    profile = tempfile.mkdtemp(prefix="slamkit-chromium-")
    # Its own process group: Chromium's helpers (renderer, crashpad) outlive the browser process
    # and keep writing into the profile, so all of them are stopped before it is removed.
    proc = subprocess.Popen([exe, "--headless=new", "--no-sandbox", "--disable-gpu", "--no-first-run",
                             "--remote-debugging-port=0", f"--user-data-dir={profile}", "about:blank"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        port_file = Path(profile) / "DevToolsActivePort"
        deadline = time.monotonic() + timeout
        while not port_file.exists() or len(port_file.read_text().splitlines()) < 2:
            if time.monotonic() > deadline or proc.poll() is not None:
                raise RuntimeError("chromium did not start its DevTools endpoint")
            time.sleep(0.1)
        port = port_file.read_text().splitlines()[0]
        import urllib.request

        targets = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10).read())
        page = next(t for t in targets if t["type"] == "page")
        return _drive(connect(page["webSocketDebuggerUrl"], max_size=None, open_timeout=timeout),
                      Path(path).resolve().as_uri(), timeout)
    finally:
        _stop_group(proc)
        _remove_profile(Path(profile))


def _stop_group(proc: subprocess.Popen) -> None:
    """SIGTERM to the browser's whole process group; SIGKILL to whatever of it is left after 10 s."""
    _signal_group(proc.pid, signal.SIGTERM)
    deadline = time.monotonic() + 10.0
    try:
        proc.wait(10.0)
    except subprocess.TimeoutExpired:
        pass
    while _signal_group(proc.pid, 0) and time.monotonic() < deadline:
        time.sleep(0.1)
    _signal_group(proc.pid, signal.SIGKILL)
    proc.wait(5.0)


def _signal_group(pgid: int, sig: int) -> bool:
    """Send `sig` to the process group; False when none of it is left."""
    try:
        os.killpg(pgid, sig)
    except ProcessLookupError:
        return False
    return True


def _remove_profile(profile: Path) -> None:
    """Remove the profile, retrying while a helper that escaped the group still writes into it."""
    for _ in range(20):
        shutil.rmtree(profile, ignore_errors=True)
        if not profile.exists():
            return
        time.sleep(0.25)
    shutil.rmtree(profile)  # still there after 5 s: let its error say which file


def _drive(ws, url: str, timeout: float) -> PageReport:
    report = PageReport()
    counter = iter(range(1, 10**6))

    def send(method: str, **params) -> int:
        ident = next(counter)
        ws.send(json.dumps({"id": ident, "method": method, "params": params}))
        return ident

    def wait_for(ident: int | None = None, event: str | None = None) -> dict:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            message = json.loads(ws.recv(timeout=max(0.1, deadline - time.monotonic())))
            method = message.get("method")
            if method == "Runtime.consoleAPICalled" and message["params"]["type"] in ("error", "assert"):
                report.errors.append("console: " + " ".join(str(a.get("value", a.get("description")))
                                                             for a in message["params"]["args"]))
            elif method == "Runtime.exceptionThrown":
                report.errors.append("exception: " + message["params"]["exceptionDetails"].get("text", ""))
            elif method == "Log.entryAdded" and message["params"]["entry"]["level"] == "error":
                report.errors.append("log: " + message["params"]["entry"].get("text", ""))
            if (ident is not None and message.get("id") == ident) or (event is not None and method == event):
                return message
        raise TimeoutError(f"no {event or ident} from chromium within {timeout} s")

    with ws:
        for method in ("Runtime.enable", "Log.enable", "Page.enable"):
            wait_for(send(method))
        send("Page.navigate", url=url)
        wait_for(event="Page.loadEventFired")
        script = ("JSON.stringify({title: document.title, text: document.body.innerText.length, images: "
                  "Array.from(document.images).map(i => ({src: i.src.slice(0, 30), complete: i.complete, "
                  "width: i.naturalWidth, height: i.naturalHeight}))})")
        result = wait_for(send("Runtime.evaluate", expression=script, returnByValue=True))
        state = json.loads(result["result"]["result"]["value"])
        time.sleep(0.5)  # late console messages
        report.title, report.text_length, report.images = state["title"], state["text"], state["images"]
    return report

"""Render an HTML file to a PNG in headless Chromium and say what went wrong in it.

The browser is driven over the Chrome DevTools Protocol on a pipe (``--remote-debugging-pipe``:
JSON messages ending in a NUL byte on file descriptors 3 and 4), so no Python package and no
network port is needed. :func:`render_page` loads the page, waits for its load event, counts the
images that decoded (``naturalWidth > 0``), collects console errors, uncaught exceptions and
browser log entries of level error, and captures the whole page.

Used by ``tests/test_report.py`` (the report page is checked in a real browser) and
``scripts/readme_report_figure.py`` (the README's picture of a report).
"""

from __future__ import annotations

import base64
import json
import os
import select
import shutil
import signal
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from raytun3r_plugin.errors import BrowserError, MissingDependencyError

__all__ = ["PageRender", "find_chromium", "render_page"]

#: Executable names of Chromium (Debian's package installs ``chromium``) and Chrome.
CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")

#: Evaluated in the page after its load event: the images and how many decoded.
_IMAGE_CHECK = (
    "JSON.stringify(Array.from(document.images).map(i => "
    "({src: i.src.slice(0, 40), ok: i.complete && i.naturalWidth > 0})))"
)


@dataclass
class PageRender:
    """What :func:`render_page` saw. ``images``: (start of src, decoded) per ``<img>``;
    ``errors``: console errors, uncaught exceptions and browser log errors, in order."""

    images: list[tuple[str, bool]] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    size: tuple[int, int] = (0, 0)

    @property
    def broken_images(self) -> list[str]:
        return [src for src, ok in self.images if not ok]


def find_chromium() -> str:
    """Path of a Chromium (or Chrome) executable; the ``RAYTUN3R_CHROMIUM`` variable wins.

    Raises:
        MissingDependencyError: none found (Debian: ``apt-get install chromium``;
            ``scripts/install.sh`` installs it where it can).
    """
    given = os.environ.get("RAYTUN3R_CHROMIUM")
    if given:
        return given
    for name in CHROMIUM_NAMES:
        path = shutil.which(name)
        if path:
            return path
    raise MissingDependencyError(
        "no Chromium found (looked for " + ", ".join(CHROMIUM_NAMES) + "); install it "
        "(Debian/Ubuntu: apt-get install chromium) or set RAYTUN3R_CHROMIUM"
    )


class _Pipe:
    """One CDP session over the two pipes: numbered requests, events kept as they come."""

    def __init__(self, write_fd: int, read_fd: int, deadline: float):
        self.write_fd, self.read_fd, self.deadline = write_fd, read_fd, deadline
        self.buffer = b""
        self.events: list[dict] = []
        self.next_id = 0

    def _message(self) -> dict:
        while b"\0" not in self.buffer:
            left = self.deadline - time.monotonic()
            if left <= 0 or not select.select([self.read_fd], [], [], left)[0]:
                raise BrowserError("Chromium did not answer in time")
            chunk = os.read(self.read_fd, 1 << 20)
            if not chunk:
                raise BrowserError("Chromium closed the DevTools pipe")
            self.buffer += chunk
        raw, self.buffer = self.buffer.split(b"\0", 1)
        return json.loads(raw)

    def call(self, method: str, session: str | None = None, **params) -> dict:
        """Send one request (to ``session``, a page attached with ``flatten``) and return its
        result; events arriving meanwhile are kept in :attr:`events`."""
        self.next_id += 1
        ident = self.next_id
        message = {"id": ident, "method": method, "params": params}
        if session is not None:
            message["sessionId"] = session
        os.write(self.write_fd, json.dumps(message).encode() + b"\0")
        while True:
            answer = self._message()
            if answer.get("id") == ident:
                if "error" in answer:
                    raise BrowserError(f"Chromium refused {method}: {answer['error']}")
                return answer.get("result", {})
            self.events.append(answer)

    def wait_for(self, method: str) -> dict:
        for index, event in enumerate(self.events):
            if event.get("method") == method:
                return self.events.pop(index)
        while True:
            message = self._message()
            if message.get("method") == method:
                return message
            self.events.append(message)


def _errors(events: list[dict]) -> list[str]:
    """The error-level messages among CDP events."""
    found = []
    for event in events:
        method, params = event.get("method"), event.get("params", {})
        if method == "Runtime.consoleAPICalled" and params.get("type") in ("error", "assert"):
            found.append(
                "console: "
                + " ".join(str(a.get("value", a.get("description"))) for a in params["args"])
            )
        elif method == "Runtime.exceptionThrown":
            details = params.get("exceptionDetails", {})
            found.append(f"exception: {details.get('text')} {details.get('exception', {})}")
        elif method == "Log.entryAdded" and params.get("entry", {}).get("level") == "error":
            entry = params["entry"]
            found.append(f"log ({entry.get('source')}): {entry.get('text')} {entry.get('url', '')}")
    return found


def render_page(
    html_path: str | os.PathLike,
    png_path: str | os.PathLike | None,
    *,
    width: int = 1280,
    timeout_s: float = 60.0,
) -> PageRender:
    """Load ``html_path`` in headless Chromium, check it and (``png_path``) capture it whole.

    The page is shown ``width`` CSS px wide at device scale 1; the capture is as tall as the
    page. Returns what was seen (images and errors); the caller decides what counts as failure.

    Raises:
        MissingDependencyError: no Chromium (:func:`find_chromium`).
        BrowserError: the browser did not start or answer within ``timeout_s``.
    """
    executable = find_chromium()
    page = Path(html_path).resolve()
    to_browser_read, to_browser_write = os.pipe()
    from_browser_read, from_browser_write = os.pipe()

    def _wire_pipes() -> None:
        # In the child: the protocol's fixed descriptors 3 and 4 (inheritable, so they survive
        # exec); copied above 10 first, as a pipe may itself sit on 3 or 4.
        import fcntl

        reading = fcntl.fcntl(to_browser_read, fcntl.F_DUPFD, 10)
        writing = fcntl.fcntl(from_browser_write, fcntl.F_DUPFD, 10)
        os.dup2(reading, 3)
        os.dup2(writing, 4)

    # Cleanup errors ignored: a helper Chromium left behind (which _stop_browser waits out)
    # must not turn a rendered page into a failure; the profile holds nothing of the user's.
    with tempfile.TemporaryDirectory(
        prefix="raytun3r-chromium-", ignore_cleanup_errors=True
    ) as profile:
        try:
            process = subprocess.Popen(
                [
                    executable,
                    "--headless",
                    "--no-sandbox",  # root in containers and CI; the page is a local file we wrote
                    "--disable-gpu",
                    "--no-first-run",
                    "--no-default-browser-check",
                    "--disable-extensions",
                    "--hide-scrollbars",
                    "--remote-debugging-pipe",
                    f"--user-data-dir={profile}",
                    "about:blank",
                ],
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                preexec_fn=_wire_pipes,
                close_fds=False,  # descriptors 3 and 4 must reach the browser; the others are CLOEXEC
                start_new_session=True,  # its helper processes share a group, stopped together
            )
        except OSError as error:
            for fd in (to_browser_read, to_browser_write, from_browser_read, from_browser_write):
                os.close(fd)
            raise MissingDependencyError(
                f"{executable}: cannot start Chromium ({error})"
            ) from error
        os.close(to_browser_read)
        os.close(from_browser_write)
        try:
            return _drive(
                _Pipe(to_browser_write, from_browser_read, time.monotonic() + timeout_s),
                page,
                png_path,
                width,
            )
        finally:
            os.close(to_browser_write)
            os.close(from_browser_read)
            _stop_browser(process)


def _stop_browser(process: subprocess.Popen, timeout_s: float = 10.0) -> None:
    """Stop Chromium and every helper process it started (its process group), and wait until
    they are gone: a helper still writing into the profile folder made removing it fail
    ("Directory not empty") in a test run."""
    group = process.pid
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(group, sig)
        except ProcessLookupError:
            break
        try:
            process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            continue
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                os.killpg(group, 0)  # raises once no process of the group is left
            except ProcessLookupError:
                return
            time.sleep(0.05)
    if process.poll() is None:
        process.kill()
        process.wait()


def _drive(pipe: _Pipe, page: Path, png_path, width: int) -> PageRender:
    targets = pipe.call("Target.getTargets")["targetInfos"]
    target = next(t for t in targets if t["type"] == "page")["targetId"]
    session = pipe.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
    for domain in ("Page", "Runtime", "Log"):
        pipe.call(f"{domain}.enable", session)
    screen = {"width": width, "deviceScaleFactor": 1, "mobile": False}
    pipe.call("Emulation.setDeviceMetricsOverride", session, height=800, **screen)
    pipe.call("Page.navigate", session, url=page.as_uri())
    pipe.wait_for("Page.loadEventFired")
    value = pipe.call("Runtime.evaluate", session, expression=_IMAGE_CHECK, returnByValue=True)[
        "result"
    ]["value"]
    images = [(entry["src"], bool(entry["ok"])) for entry in json.loads(value)]
    height = int(pipe.call("Page.getLayoutMetrics", session)["cssContentSize"]["height"] + 0.999)
    if png_path is not None:
        pipe.call("Emulation.setDeviceMetricsOverride", session, height=height, **screen)
        shot = pipe.call(
            "Page.captureScreenshot", session, format="png", captureBeyondViewport=True
        )
        Path(png_path).write_bytes(base64.b64decode(shot["data"]))
    return PageRender(images=images, errors=_errors(pipe.events), size=(width, height))

"""A headless Chromium driven through the DevTools protocol, with the standard library only.

Chromium started with ``--remote-debugging-pipe`` reads protocol commands from its file
descriptor 3 and writes answers and events to its descriptor 4, each message one JSON text
ended by a NUL byte. The tests open a page, find elements, click them with real mouse
events (``Input.dispatchMouseEvent``: the browser hit-tests the point, as for a user's
click), type into them (``Input.insertText``) and read the page back (``Runtime.evaluate``).
No websocket, no playwright or selenium.
"""

from __future__ import annotations

import json
import os
import select
import subprocess
import time
from typing import Any

FLAGS = (
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
)  # fmt: skip


class DevToolsError(RuntimeError):
    """The browser answered a command with an error, or did not answer in time."""


class Browser:
    """One headless Chromium and one page in it: ``with Browser(chromium, profile) as b: b.open(url)``."""

    def __init__(self, chromium: str, profile: str | os.PathLike[str], timeout: float = 60.0) -> None:
        self.timeout = timeout
        commands_r, self._commands = os.pipe()  # we write, the browser reads (its fd 3)
        self._answers, answers_w = os.pipe()  # the browser writes (its fd 4), we read

        def to_fds_3_and_4() -> None:  # in the child, before exec
            a, b = os.dup(commands_r), os.dup(answers_w)
            os.dup2(a, 3)
            os.dup2(b, 4)

        self.process = subprocess.Popen(
            [chromium, *FLAGS, f"--user-data-dir={profile}", "--remote-debugging-pipe", "about:blank"],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            preexec_fn=to_fds_3_and_4, close_fds=False,
        )  # fmt: skip
        os.close(commands_r)
        os.close(answers_w)
        self._buffer = b""
        self._next_id = 0
        self.session: str | None = None

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        try:
            self.send("Browser.close", session=False)
        except (DevToolsError, OSError):
            pass
        try:
            self.process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        for fd in (self._commands, self._answers):
            try:
                os.close(fd)
            except OSError:
                pass

    def _read_message(self, deadline: float) -> dict[str, Any]:
        while b"\0" not in self._buffer:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self._answers], [], [], left)[0]:
                raise DevToolsError("the browser did not answer in time")
            chunk = os.read(self._answers, 1 << 16)
            if not chunk:
                raise DevToolsError(f"the browser closed the pipe (exit code {self.process.poll()})")
            self._buffer += chunk
        message, self._buffer = self._buffer.split(b"\0", 1)
        return json.loads(message)

    def send(self, method: str, params: dict[str, Any] | None = None, session: bool = True) -> dict[str, Any]:
        """Send one command (to the page's session unless ``session=False``); its result."""
        self._next_id += 1
        message: dict[str, Any] = {"id": self._next_id, "method": method, "params": params or {}}
        if session and self.session is not None:
            message["sessionId"] = self.session
        os.write(self._commands, json.dumps(message).encode() + b"\0")
        deadline = time.monotonic() + self.timeout
        while True:
            answer = self._read_message(deadline)
            if answer.get("id") == self._next_id:  # events and other answers are passed over
                if "error" in answer:
                    raise DevToolsError(f"{method}: {answer['error']}")
                return answer.get("result", {})

    def open(self, url: str) -> None:
        """Open ``url`` in a new page and wait until it has loaded (its scripts have run)."""
        target = self.send("Target.createTarget", {"url": url}, session=False)["targetId"]
        self.session = self.send("Target.attachToTarget", {"targetId": target, "flatten": True}, session=False)[
            "sessionId"
        ]
        deadline = time.monotonic() + self.timeout
        # one evaluation for both: asked apart, the first can read the blank page that is
        # complete and the second the new page that is still loading (rows missing, its
        # script not run: a heading clicked in CI did not sort)
        while self.evaluate("[document.readyState, location.href]") != ["complete", url]:
            if time.monotonic() > deadline:
                raise DevToolsError(f"{url} did not load in time")
            time.sleep(0.05)

    def evaluate(self, expression: str) -> Any:
        """The value (JSON-able) of a JavaScript expression in the page."""
        result = self.send("Runtime.evaluate", {"expression": expression, "returnByValue": True})
        if "exceptionDetails" in result:
            raise DevToolsError(f"{expression}: {result['exceptionDetails']}")
        return result["result"].get("value")

    def click(self, selector: str) -> None:
        """Click the middle of the first element matching the CSS ``selector`` with the mouse
        (scrolled into view first); the browser decides what is under the pointer."""
        box = self.evaluate(
            f"(function(){{var e=document.querySelector({json.dumps(selector)});if(!e)return null;"
            "e.scrollIntoView({block:'center'});var r=e.getBoundingClientRect();"
            "return [r.left+r.width/2, r.top+r.height/2]})()"
        )
        if box is None:
            raise DevToolsError(f"no element matches {selector!r}")
        x, y = box
        for kind in ("mouseMoved", "mousePressed", "mouseReleased"):
            event = {"type": kind, "x": x, "y": y, "button": "left" if kind != "mouseMoved" else "none"}
            if kind != "mouseMoved":
                event["clickCount"] = 1
            self.send("Input.dispatchMouseEvent", event)

    def type_text(self, text: str) -> None:
        """Type ``text`` into the focused element, as a keyboard would (the page sees input events)."""
        self.send("Input.insertText", {"text": text})

"""A small driver of headless Chromium over the DevTools protocol, for the dashboard's tests and its latency
measurement: load a page, evaluate JavaScript in it, wait for a condition, take a screenshot, collect the
page's console errors. It needs Debian's `chromium` (`scripts/browser-setup.sh`, run by `make setup`) and
nothing else: the DevTools WebSocket is spoken with aiohttp's client.

    async with Chromium(tmp_dir) as b:
        await b.navigate("http://127.0.0.1:8765/")
        await b.wait_for("window.HAA.connected")
        n = await b.evaluate("document.getElementById('agent-count').textContent")
        await b.screenshot(tmp_dir / "page.png")

Chromium runs with a fresh `--user-data-dir` under `tmp_dir` and the flags of `FLAGS` (no sandbox — tests run
as root —, no GPU, no background network traffic of its own: no updates, sync, first-run pages or QUIC);
`--remote-debugging-port=0` lets it pick a free port, which it writes to `DevToolsActivePort` in the profile.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import itertools
import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

import aiohttp

#: the flags every run uses (issue 19: headless, offline, a fresh profile)
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-quic",
         "--disable-default-apps", "--disable-extensions", "--mute-audio", "--no-default-browser-check")
BINARIES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


class BrowserError(Exception):
    """Chromium could not be started or driven (one line)."""


def find_chromium() -> str | None:
    """The path of a Chromium binary on PATH (env HAA_CHROMIUM first), else None."""
    env = os.environ.get("HAA_CHROMIUM")
    if env and shutil.which(env):
        return shutil.which(env)
    for name in BINARIES:
        p = shutil.which(name)
        if p:
            return p
    return None


class Chromium:
    """One headless Chromium process with one page, driven over the DevTools protocol."""

    def __init__(self, tmp_dir: Path, width: int = 1600, height: int = 1000, binary: str | None = None) -> None:
        self.tmp_dir = Path(tmp_dir)
        self.width, self.height = width, height
        self.binary = binary or find_chromium()
        self.proc: subprocess.Popen[bytes] | None = None
        self.session: aiohttp.ClientSession | None = None
        self.ws: aiohttp.ClientWebSocketResponse | None = None
        self.ids = itertools.count(1)
        self.pending: dict[int, asyncio.Future[Any]] = {}
        self.console: list[str] = []  # console errors and uncaught exceptions of the page
        self._reader: asyncio.Task[None] | None = None

    async def __aenter__(self) -> Chromium:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def start(self, timeout: float = 30.0) -> None:
        if not self.binary:
            raise BrowserError("no Chromium on PATH (Debian package chromium: scripts/browser-setup.sh)")
        profile = self.tmp_dir / "chromium-profile"
        shutil.rmtree(profile, ignore_errors=True)
        profile.mkdir(parents=True)
        log = open(self.tmp_dir / "chromium.log", "wb")  # noqa: SIM115 - kept open for the process' life
        cmd = [self.binary, *FLAGS, f"--user-data-dir={profile}", "--remote-debugging-port=0",
               f"--window-size={self.width},{self.height}", "about:blank"]
        self.proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=log, stderr=log, start_new_session=True)
        log.close()
        port_file = profile / "DevToolsActivePort"
        deadline = time.monotonic() + timeout
        port = 0
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                log_path = self.tmp_dir / "chromium.log"
                raise BrowserError(f"chromium exited with {self.proc.returncode} (log: {log_path})")
            with contextlib.suppress(OSError, ValueError, IndexError):
                port = int(port_file.read_text().splitlines()[0])
            if port:
                break
            await asyncio.sleep(0.05)
        if not port:
            await self.close()
            raise BrowserError(f"chromium did not open its DevTools port within {timeout:.0f} s")
        self.session = aiohttp.ClientSession()
        url = ""
        while time.monotonic() < deadline and not url:
            with contextlib.suppress(aiohttp.ClientError, ValueError):
                async with self.session.get(f"http://127.0.0.1:{port}/json/list") as r:
                    targets = await r.json(content_type=None)
                url = next((t["webSocketDebuggerUrl"] for t in targets if t.get("type") == "page"), "")
            if not url:
                await asyncio.sleep(0.1)
        if not url:
            await self.close()
            raise BrowserError("chromium shows no page target")
        self.ws = await self.session.ws_connect(url, max_msg_size=256 << 20)
        self._reader = asyncio.create_task(self._read())
        await self.send("Runtime.enable")
        await self.send("Page.enable")

    async def _read(self) -> None:
        assert self.ws is not None
        async for msg in self.ws:
            if msg.type != aiohttp.WSMsgType.TEXT:
                continue
            m = json.loads(msg.data)
            if "id" in m:
                fut = self.pending.pop(m["id"], None)
                if fut is not None and not fut.done():
                    if "error" in m:
                        fut.set_exception(BrowserError(f"DevTools: {m['error'].get('message')}"))
                    else:
                        fut.set_result(m.get("result", {}))
            elif m.get("method") == "Runtime.exceptionThrown":
                d = m["params"]["exceptionDetails"]
                self.console.append(f"exception: {d.get('exception', {}).get('description') or d.get('text')}")
            elif m.get("method") == "Runtime.consoleAPICalled" and m["params"].get("type") == "error":
                self.console.append("console.error: " + " ".join(str(a.get("value", a.get("description", "")))
                                                                 for a in m["params"].get("args", [])))
        for fut in self.pending.values():
            if not fut.done():
                fut.set_exception(BrowserError("the DevTools connection closed"))

    async def send(self, method: str, timeout: float = 30.0, **params: Any) -> dict[str, Any]:
        if self.ws is None:
            raise BrowserError("not started")
        i = next(self.ids)
        fut: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        self.pending[i] = fut
        await self.ws.send_str(json.dumps({"id": i, "method": method, "params": params}))
        return await asyncio.wait_for(fut, timeout)

    async def navigate(self, url: str) -> None:
        await self.send("Page.navigate", url=url)

    async def evaluate(self, expression: str) -> Any:
        r = await self.send("Runtime.evaluate", expression=expression, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in r:
            d = r["exceptionDetails"]
            raise BrowserError(f"{expression[:60]!r}: {d.get('exception', {}).get('description') or d.get('text')}")
        return r.get("result", {}).get("value")

    async def wait_for(self, expression: str, timeout: float = 30.0, period: float = 0.05) -> Any:
        """Evaluate `expression` until it is truthy; its value (BrowserError after `timeout`)."""
        deadline = time.monotonic() + timeout
        last: Any = None
        while True:
            with contextlib.suppress(BrowserError):
                last = await self.evaluate(expression)
                if last:
                    return last
            if time.monotonic() > deadline:
                raise BrowserError(f"timed out after {timeout:.0f} s waiting for {expression!r} (last: {last!r}); "
                                   f"page errors: {self.console[-3:]}")
            await asyncio.sleep(period)

    async def screenshot(self, path: Path) -> Path:
        r = await self.send("Page.captureScreenshot", format="png")
        path = Path(path)
        path.write_bytes(base64.b64decode(r["data"]))
        return path

    async def close(self) -> None:
        if self.ws is not None:
            with contextlib.suppress(Exception):
                await self.ws.close()
        if self._reader is not None:
            self._reader.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._reader
        if self.session is not None:
            await self.session.close()
        p = self.proc
        if p is not None and p.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGTERM)
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGKILL)
                p.wait(5)
        self.proc = None

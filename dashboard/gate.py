"""The dashboard's front door: an access token and an Origin check in front of viser.

viser serves its page and its websocket on one port with no access control. The gate listens
on the dashboard's address, reads each connection's first HTTP request head, and only then
splices the connection through to viser, which listens on loopback only:

- with an access token, a request must carry it, as ``?token=...`` (the URL the service
  announces; answered with a redirect that stores it in an HttpOnly, SameSite=Strict
  cookie) or as that cookie; otherwise ``401``;
- a websocket upgrade must come from the page itself: its ``Origin`` must name the same host
  and port as its ``Host`` (a page of another site cannot drive the view); otherwise ``403``;
- a malformed or oversized request head gets ``400`` and the connection is closed.

Runs its own asyncio loop in its own thread, like viser: it never touches the services' loops.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import logging
import threading
from dataclasses import dataclass
from urllib.parse import parse_qs, urlsplit

log = logging.getLogger(__name__)

COOKIE = "recslam_dashboard"
MAX_HEAD = 16 * 1024
HEAD_TIMEOUT_S = 10.0


@dataclass(frozen=True)
class Verdict:
    """What the gate does with one request: forward it, or answer ``status`` itself."""

    status: int  # 0 = forward to viser
    headers: tuple[tuple[str, str], ...] = ()
    body: str = ""


def judge(head: bytes, token: str | None) -> Verdict:
    """Decide on one HTTP request head (bytes up to and including the blank line)."""
    try:
        lines = head.decode("latin-1").split("\r\n")
        method, target, _ = lines[0].split(" ", 2)
        headers: dict[str, str] = {}
        for line in lines[1:]:
            if line:
                name, _, value = line.partition(":")
                headers[name.strip().lower()] = value.strip()
    except ValueError:
        return Verdict(400, body="malformed request")
    url = urlsplit(target)
    if headers.get("upgrade", "").lower() == "websocket":
        origin = urlsplit(headers.get("origin", ""))
        if not origin.netloc or origin.netloc != headers.get("host"):
            return Verdict(403, body="websocket from another origin refused")
    if token is None:
        return Verdict(0)
    offered = parse_qs(url.query).get("token", [""])[0]
    if offered and hmac.compare_digest(offered, token):
        if method == "GET" and headers.get("upgrade", "").lower() != "websocket":
            cookie = f"{COOKIE}={token}; HttpOnly; SameSite=Strict; Path=/"
            return Verdict(302, (("Location", url.path or "/"), ("Set-Cookie", cookie)))
        return Verdict(0)
    for part in headers.get("cookie", "").split(";"):
        name, _, value = part.strip().partition("=")
        if name == COOKIE and hmac.compare_digest(value, token):
            return Verdict(0)
    return Verdict(401, body="open the dashboard with the URL (and its token) the cloud logged")


_REASONS = {302: "Found", 400: "Bad Request", 401: "Unauthorized", 403: "Forbidden"}


def _response(v: Verdict) -> bytes:
    body = v.body.encode()
    lines = [f"HTTP/1.1 {v.status} {_REASONS[v.status]}"]
    lines += [f"{k}: {val}" for k, val in v.headers]
    lines += [
        "Content-Type: text/plain; charset=utf-8",
        f"Content-Length: {len(body)}",
        "Connection: close",
    ]
    return ("\r\n".join(lines) + "\r\n\r\n").encode() + body


class Gate:
    """Listen on ``host:port`` and pass authorised connections to viser at
    ``127.0.0.1:upstream_port``. ``start()`` / ``stop()``; counters :attr:`refused`."""

    def __init__(self, host: str, port: int, upstream_port: int, token: str | None) -> None:
        self.host, self.port, self.upstream_port, self.token = host, port, upstream_port, token
        self.refused: dict[int, int] = {}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: asyncio.base_events.Server | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._writers: set[asyncio.StreamWriter] = set()  # both ends of every connection
        self._tasks: set[asyncio.Task[None]] = set()

    def start(self) -> None:
        self._thread = threading.Thread(target=self._main, name="dashboard-gate", daemon=True)
        self._thread.start()
        self._ready.wait(10.0)
        if self._error is not None:
            raise self._error

    def stop(self) -> None:
        """Close the listener and every connection, then end the thread."""
        loop = self._loop
        if loop is not None and self._server is not None and loop.is_running():
            future = asyncio.run_coroutine_threadsafe(self._shutdown(), loop)
            with contextlib.suppress(TimeoutError, RuntimeError):
                future.result(5.0)
            loop.call_soon_threadsafe(loop.stop)
        if self._thread is not None:
            self._thread.join(5.0)

    async def _shutdown(self) -> None:
        assert self._server is not None
        self._server.close()
        for writer in list(self._writers):
            writer.close()
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        for writer in list(self._writers):
            with contextlib.suppress(OSError, RuntimeError):
                await writer.wait_closed()
        await self._server.wait_closed()

    def _main(self) -> None:
        loop = self._loop = asyncio.new_event_loop()
        try:
            self._server = loop.run_until_complete(
                asyncio.start_server(self._serve, self.host, self.port)
            )
        except OSError as exc:
            self._error = exc
            self._ready.set()
            return
        self._ready.set()
        try:
            loop.run_forever()
        finally:
            loop.close()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._tasks.add(task)
        self._writers.add(writer)
        try:
            await self._gate(reader, writer)
        finally:
            self._tasks.discard(task)
            self._writers.discard(writer)
            writer.close()

    async def _gate(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), HEAD_TIMEOUT_S)
        except (asyncio.LimitOverrunError, asyncio.IncompleteReadError, TimeoutError, OSError):
            await self._answer(writer, Verdict(400, body="incomplete or oversized request"))
            return
        if len(head) > MAX_HEAD:
            await self._answer(writer, Verdict(400, body="request head too large"))
            return
        verdict = judge(head, self.token)
        if verdict.status:
            if verdict.status != 302:
                self.refused[verdict.status] = self.refused.get(verdict.status, 0) + 1
                log.info("dashboard: %d for %s", verdict.status, writer.get_extra_info("peername"))
            await self._answer(writer, verdict)
            return
        try:
            up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.upstream_port)
        except OSError as exc:
            log.warning("dashboard: viser unreachable: %s", exc)
            writer.close()
            return
        self._writers.add(up_writer)
        try:
            up_writer.write(head)
            await asyncio.gather(_pipe(reader, up_writer), _pipe(up_reader, writer))
        finally:
            self._writers.discard(up_writer)
            up_writer.close()
            with contextlib.suppress(OSError, RuntimeError):
                await up_writer.wait_closed()

    @staticmethod
    async def _answer(writer: asyncio.StreamWriter, verdict: Verdict) -> None:
        with contextlib.suppress(OSError):
            writer.write(_response(verdict))
            await writer.drain()
        writer.close()


async def _pipe(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    try:
        while data := await reader.read(65536):
            writer.write(data)
            await writer.drain()
    except (OSError, asyncio.IncompleteReadError):
        pass
    finally:
        with contextlib.suppress(OSError, RuntimeError):
            writer.close()

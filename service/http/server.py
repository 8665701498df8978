"""``abcns serve``: the app under uvicorn, with the service's connection limits and shutdown.

- A request's headers must arrive within ``header_timeout_s`` of the connection (or of its
  first byte after a keep-alive pause; an idle keep-alive connection closes after 5 s), and
  its body within ``body_timeout_s`` of its headers, else the connection is closed (a 408
  when no answer has started): a slow client cannot hold a connection open. After
  ``body_grace_s`` a body must also come at ``min_body_rate`` bytes/s on average (408
  otherwise): a client sending a byte a second cannot hold a submission slot for long. A request's
  head (its request line and headers) is limited to ``HEADER_LIMIT`` (16 KiB: 431 and the
  connection closed, however the bytes arrive; h11 alone limits only a head that arrives
  in pieces), bodies to ``max_request_bytes`` (413).
- SIGTERM (or Ctrl+C) first ends every event stream and stops the running jobs between
  batches (they are requeued, and resume at the next start), then uvicorn closes the
  connections (waiting at most 3 s for answers in flight) and the app shuts down (running
  jobs get ``shutdown_timeout_s`` to stop).
- The address is printed at start, and every request is logged (uvicorn's access log).
"""

from __future__ import annotations

import asyncio
import logging
import re

import h11
import uvicorn
from fastapi import FastAPI
from uvicorn.protocols.http.h11_impl import H11Protocol

from service.http.api import begin_shutdown, create_app
from service.http.settings import Settings

GRACE_S = 3.0  # uvicorn waits this long for answers in flight after SIGTERM (streams end at once)
HEADER_LIMIT = 16 * 1024  # bytes of a request's head: its request line and headers
RATE_TICK_S = 0.5  # how often a body's rate is checked
_HEAD_END = re.compile(rb"\r?\n\r?\n")  # where h11 sees a head end
log = logging.getLogger("uvicorn.error")


class DeadlineProtocol(H11Protocol):
    """uvicorn's h11 protocol with a deadline for a request's headers and one for its body,
    and a least rate for the body: after ``body_grace_s`` of reading it must have come at
    ``min_body_rate`` bytes/s on average (time while the service itself does not read it,
    a submission waiting for its slot with a full buffer, does not count), else 408 and
    the connection is closed, so that clients sending a byte a second cannot hold every
    submission slot for ``body_timeout_s``."""

    header_timeout_s = 5.0
    body_timeout_s = 30.0
    min_body_rate = 8192.0  # bytes/s; 0: no least rate
    body_grace_s = 2.0

    # as uvicorn's own H11Protocol.connection_made (asyncio.Protocol types it with a BaseTransport)
    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._phase: str | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._rate_timer: asyncio.TimerHandle | None = None
        self._body_bytes, self._reading_s, self._ticked = 0, 0.0, 0.0
        self._watch(new_connection=True)

    def _arm(self, phase: str | None, delay: float = 0.0) -> None:
        for timer in (self._timer, self._rate_timer):
            if timer is not None:
                timer.cancel()
        self._timer = self._rate_timer = None
        self._phase = phase
        if phase is not None:
            self._timer = self.loop.call_later(delay, self._late)
        if phase == "body" and self.min_body_rate > 0:
            self._body_bytes, self._reading_s, self._ticked = 0, 0.0, self.loop.time()
            self._rate_timer = self.loop.call_later(RATE_TICK_S, self._check_rate)

    def _check_rate(self) -> None:
        """Every RATE_TICK_S of a body: the bytes so far against the least rate over the time
        the service was reading it."""
        now = self.loop.time()
        if not self.flow.read_paused:  # paused: the service is not reading it (no slot yet)
            self._reading_s += now - self._ticked
        self._ticked = now
        owed = self.min_body_rate * (self._reading_s - self.body_grace_s)
        if self._body_bytes < owed and not self.transport.is_closing():
            log.warning("%s: closing a connection whose request body came at %.0f bytes/s, under %.0f", self._who(),
                        self._body_bytes / max(self._reading_s, 1e-9), self.min_body_rate)
            self._arm(None)
            self._phase = "body"
            self._late(f"came slower than {self.min_body_rate:.0f} bytes/s")
            return
        self._rate_timer = self.loop.call_later(RATE_TICK_S, self._check_rate)

    def _watch(self, new_connection: bool = False) -> None:
        state = self.conn.their_state
        if state is h11.SEND_BODY:
            if self._phase != "body":
                self._arm("body", self.body_timeout_s)
        elif state is h11.IDLE:
            # a new connection, or bytes of the next request after a keep-alive pause
            if self._phase != "headers" and (new_connection or self.conn.trailing_data[0]):
                self._arm("headers", self.header_timeout_s)
        elif self._phase is not None:
            self._arm(None)

    def data_received(self, data: bytes) -> None:
        if self._phase == "body":
            self._body_bytes += len(data)
        super().data_received(data)
        if not self.transport.is_closing():
            self._watch()

    def on_response_complete(self) -> None:
        self._arm(None)  # uvicorn's keep-alive timeout takes over
        super().on_response_complete()
        if not self.transport.is_closing():
            self._watch()

    def connection_lost(self, exc: Exception | None) -> None:
        self._arm(None)
        super().connection_lost(exc)

    def handle_events(self) -> None:
        """uvicorn's, after a look at a new request's head: one longer than HEADER_LIMIT gets
        431 and the connection is closed before h11 parses it."""
        if self.conn.their_state is h11.IDLE and not self.transport.is_closing():
            buffered = self.conn.trailing_data[0]
            end = _HEAD_END.search(buffered, 0, HEADER_LIMIT + 4)
            if (end.end() if end else len(buffered)) > HEADER_LIMIT:
                log.warning("%s: refusing a request whose head exceeds %d bytes", self._who(), HEADER_LIMIT)
                self._answer_and_close(431, b"Request Header Fields Too Large",
                                       f"the request line and headers exceed {HEADER_LIMIT} bytes\n")
                return
        super().handle_events()

    def _who(self) -> str:
        return f"{self.client[0]}:{self.client[1]}" if self.client else "?"

    def _answer_and_close(self, status: int, reason: bytes, text: str) -> None:
        """A short plain-text answer written as bytes (h11 sends no response before a request
        has been parsed), then the connection closed."""
        body = text.encode()
        self.transport.write(b"HTTP/1.1 %d %s\r\ncontent-type: text/plain; charset=utf-8\r\ncontent-length: %d\r\n"
                             b"connection: close\r\n\r\n%s" % (status, reason, len(body), body))
        self.transport.close()

    def _late(self, why: str = "") -> None:
        phase, self._timer = self._phase, None
        if self.transport.is_closing():
            return
        if not why:
            log.warning("%s: closing a connection whose request %s did not arrive in time", self._who(), phase)
        cycle = self.cycle
        if phase == "body" and cycle is not None and not cycle.response_started:
            cycle.disconnected = True  # the app's receive() now says http.disconnect; its answer goes nowhere
            cycle.message_event.set()
            self._answer_and_close(408, b"Request Timeout", f"the request body {why or 'did not arrive in time'}\n")
            return
        self.transport.close()


class Server(uvicorn.Server):
    """uvicorn's server; a signal to stop first ends the streams and stops the jobs."""

    def __init__(self, config: uvicorn.Config, app: FastAPI):
        super().__init__(config)
        self.abcns_app = app

    def handle_exit(self, sig, frame) -> None:
        if not self.should_exit:
            begin_shutdown(self.abcns_app)
        super().handle_exit(sig, frame)


def serve(settings: Settings, host: str, port: int, access_log: bool = True) -> None:
    app = create_app(settings)
    protocol = type("AbcnsProtocol", (DeadlineProtocol,), {"header_timeout_s": settings.header_timeout_s,
                                                            "body_timeout_s": settings.body_timeout_s,
                                                            "min_body_rate": settings.min_body_rate,
                                                            "body_grace_s": settings.body_grace_s})
    config = uvicorn.Config(app, host=host, port=port, http=protocol, log_level="info", access_log=access_log,
                            timeout_keep_alive=5, timeout_graceful_shutdown=int(GRACE_S),
                            h11_max_incomplete_event_size=HEADER_LIMIT)
    Server(config, app).run()

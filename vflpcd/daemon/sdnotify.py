"""systemd service notifications (the ``sd_notify(3)`` protocol) without libsystemd.

Under a ``Type=notify`` unit, systemd passes the address of a datagram socket in
``NOTIFY_SOCKET``: an absolute filesystem path, or a name in the Linux abstract namespace
when it starts with ``@`` (the ``@`` stands for a leading NUL byte). A notification is one
``AF_UNIX``/``SOCK_DGRAM`` datagram of newline-separated ``KEY=VALUE`` assignments, UTF-8:

* ``READY=1``     start-up is finished; ``systemctl start`` returns.
* ``STATUS=...``  one free-text line shown by ``systemctl status``.
* ``WATCHDOG=1``  keep-alive; with ``WatchdogSec=`` set, systemd exports ``WATCHDOG_USEC``
  and kills the service when no keep-alive arrives within that many microseconds.
  ``WATCHDOG_PID``, when set, names the only process the watchdog is meant for
  (``sd_watchdog_enabled(3)``); ``sd_watchdog_enabled`` recommends petting at half the period.
* ``STOPPING=1``  shutdown has begun.

Without ``NOTIFY_SOCKET`` (not started by systemd) every method is a cheap no-op. Sending
never raises: a failure (socket gone, queue full, ...) is logged once at WARNING and later
ones are dropped silently, so the daemon keeps running when systemd is not listening.
"""

from __future__ import annotations

import errno
import logging
import os
import socket
import threading
from collections.abc import Mapping

log = logging.getLogger("vflpcd.daemon.sdnotify")


def _positive_int(value: str | None) -> int | None:
    try:
        n = int(value) if value is not None else 0
    except ValueError:
        return None
    return n if n > 0 else None


class SystemdNotifier:
    """Sends ``sd_notify`` datagrams to the socket at ``address``; thread-safe.

    ``address`` is the socket address as ``socket.sendto`` takes it (a path, or a string
    starting with NUL for the abstract namespace) or None to disable every method.
    ``watchdog_usec`` is the watchdog period in microseconds, or None when the service has
    no watchdog (then ``watchdog()`` sends nothing). Build it with ``from_env()``.
    """

    def __init__(self, address: str | None, watchdog_usec: int | None = None) -> None:
        self._address = address
        self._watchdog_usec = watchdog_usec if address is not None else None
        self._lock = threading.Lock()
        self._sock: socket.socket | None = None
        self._closed = False
        self._warned = False

    @classmethod
    def from_env(cls, environ: Mapping[str, str] = os.environ) -> SystemdNotifier:
        """The notifier systemd configured through the environment.

        ``NOTIFY_SOCKET`` gives the socket (``@name`` -> abstract ``\\0name``). The watchdog
        is enabled when ``WATCHDOG_USEC`` is a positive integer and ``WATCHDOG_PID`` is either
        unset or this process's pid, as ``sd_watchdog_enabled(3)`` decides.
        """
        raw = environ.get("NOTIFY_SOCKET") or None
        address: str | None = None
        if raw is not None:
            if raw.startswith("@") and len(raw) > 1:
                address = "\0" + raw[1:]
            elif raw.startswith("/"):
                address = raw
            else:  # sd_notify accepts only absolute paths and abstract names
                log.warning("event=sd_notify_disabled reason=unsupported_address address=%r", raw)
        usec = _positive_int(environ.get("WATCHDOG_USEC"))
        pid = environ.get("WATCHDOG_PID")
        if usec is not None and pid is not None and _positive_int(pid) != os.getpid():
            usec = None  # the watchdog belongs to another process (e.g. our parent)
        return cls(address, usec)

    @property
    def enabled(self) -> bool:
        """True when a notification socket is configured."""
        return self._address is not None

    @property
    def watchdog_usec(self) -> int | None:
        """The watchdog period in microseconds, or None when the watchdog is off."""
        return self._watchdog_usec

    @property
    def watchdog_period_s(self) -> float | None:
        """Recommended interval between ``watchdog()`` calls: half the watchdog period, in s."""
        return None if self._watchdog_usec is None else self._watchdog_usec / 2e6

    def ready(self) -> bool:
        """``READY=1``: start-up finished."""
        return self.notify("READY=1")

    def status(self, text: str) -> bool:
        """``STATUS=text``; line breaks in ``text`` become spaces so it stays one assignment."""
        return self.notify("STATUS=" + " ".join(str(text).splitlines()))

    def watchdog(self) -> bool:
        """``WATCHDOG=1`` keep-alive; sends nothing unless the watchdog is enabled."""
        return self._watchdog_usec is not None and self.notify("WATCHDOG=1")

    def stopping(self) -> bool:
        """``STOPPING=1``: shutdown has begun."""
        return self.notify("STOPPING=1")

    def notify(self, *lines: str) -> bool:
        """Send ``lines`` (``KEY=VALUE`` assignments, unchecked) as one datagram.

        Returns True when the datagram was handed to the kernel; False when disabled, closed
        or the send failed (logged once).
        """
        if self._address is None or not lines:
            return False
        data = "\n".join(lines).encode("utf-8")
        with self._lock:
            if self._closed:
                return False
            try:
                if self._sock is None:
                    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
                    sock.setblocking(False)
                    self._sock = sock
                self._sock.sendto(data, self._address)
                return True
            except OSError as exc:
                if not self._warned:
                    self._warned = True
                    reason = errno.errorcode.get(exc.errno or 0, type(exc).__name__)
                    log.warning("event=sd_notify_failed reason=%s address=%r detail=%r later=dropped",
                                reason, self._address, str(exc))
                return False

    def close(self) -> None:
        """Close the socket; later calls send nothing. Idempotent."""
        with self._lock:
            self._closed = True
            if self._sock is not None:
                self._sock.close()
                self._sock = None

    def __repr__(self) -> str:
        return f"SystemdNotifier(address={self._address!r}, watchdog_usec={self._watchdog_usec})"

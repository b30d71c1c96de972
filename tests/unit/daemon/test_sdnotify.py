"""SystemdNotifier against real AF_UNIX datagram sockets standing in for systemd."""

from __future__ import annotations

import logging
import os
import socket
import uuid

import pytest

from vflpcd.daemon.sdnotify import SystemdNotifier

LOGGER = "vflpcd.daemon.sdnotify"


@pytest.fixture
def listener(tmp_path):
    """A bound datagram socket in tmp_path, as systemd provides; yields (socket, path)."""
    path = str(tmp_path / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.settimeout(2.0)
    yield sock, path
    sock.close()


def assert_nothing_queued(sock: socket.socket) -> None:
    sock.setblocking(False)
    try:
        with pytest.raises(BlockingIOError):
            sock.recv(4096)
    finally:
        sock.settimeout(2.0)


def test_exact_datagrams(listener):
    sock, path = listener
    n = SystemdNotifier.from_env({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "2000000"})
    assert n.enabled
    assert n.ready() is True
    assert sock.recv(4096) == b"READY=1"
    n.status("tracking, v=1.20 m/s")
    assert sock.recv(4096) == b"STATUS=tracking, v=1.20 m/s"
    n.watchdog()
    assert sock.recv(4096) == b"WATCHDOG=1"
    n.stopping()
    assert sock.recv(4096) == b"STOPPING=1"
    n.notify("STATUS=été", "EXTEND_TIMEOUT_USEC=5000000")
    assert sock.recv(4096) == "STATUS=été\nEXTEND_TIMEOUT_USEC=5000000".encode()
    assert_nothing_queued(sock)
    n.close()
    n.close()
    assert n.ready() is False


def test_abstract_namespace_address():
    name = f"vflpcd-test-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)
    sock.settimeout(2.0)
    try:
        n = SystemdNotifier.from_env({"NOTIFY_SOCKET": "@" + name})
        assert n.ready()
        assert sock.recv(4096) == b"READY=1"
        n.close()
    finally:
        sock.close()


def test_status_newlines_do_not_split_the_message(listener):
    sock, path = listener
    n = SystemdNotifier.from_env({"NOTIFY_SOCKET": path})
    n.status("line one\nREADY=1\r\nline three\n")
    assert sock.recv(4096) == b"STATUS=line one READY=1 line three"
    assert_nothing_queued(sock)


def test_watchdog_period_is_half_of_watchdog_usec(listener):
    _, path = listener
    n = SystemdNotifier.from_env({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "2000000"})
    assert n.watchdog_usec == 2_000_000
    assert n.watchdog_period_s == pytest.approx(1.0)


@pytest.mark.parametrize("extra", [
    {},                                                   # no WatchdogSec= in the unit
    {"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": str(os.getpid() + 1)},  # meant for another process
    {"WATCHDOG_USEC": "0"},
    {"WATCHDOG_USEC": "soon"},
])
def test_watchdog_disabled(listener, extra):
    sock, path = listener
    n = SystemdNotifier.from_env({"NOTIFY_SOCKET": path, **extra})
    assert n.watchdog_usec is None and n.watchdog_period_s is None
    assert n.watchdog() is False
    n.ready()  # the next datagram is this one: watchdog() sent nothing
    assert sock.recv(4096) == b"READY=1"


def test_watchdog_pid_of_this_process_enables_it(listener):
    sock, path = listener
    n = SystemdNotifier.from_env({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "500000",
                                  "WATCHDOG_PID": str(os.getpid())})
    assert n.watchdog_period_s == pytest.approx(0.25)
    assert n.watchdog()
    assert sock.recv(4096) == b"WATCHDOG=1"


def test_without_socket_every_method_is_a_no_op(caplog):
    caplog.set_level(logging.DEBUG, logger=LOGGER)
    n = SystemdNotifier.from_env({"WATCHDOG_USEC": "2000000"})
    assert not n.enabled
    assert n.watchdog_usec is None and n.watchdog_period_s is None
    assert [n.ready(), n.status("x"), n.watchdog(), n.stopping(), n.notify("A=1")] == [False] * 5
    n.close()
    assert caplog.records == []


def test_missing_socket_warns_once_and_never_raises(tmp_path, caplog):
    caplog.set_level(logging.DEBUG, logger=LOGGER)
    n = SystemdNotifier.from_env({"NOTIFY_SOCKET": str(tmp_path / "gone.sock"), "WATCHDOG_USEC": "1000000"})
    for _ in range(3):
        assert [n.ready(), n.status("x"), n.watchdog(), n.stopping()] == [False] * 4
    records = [r for r in caplog.records if r.name == LOGGER]
    assert len(records) == 1
    assert records[0].levelno == logging.WARNING
    assert "event=sd_notify_failed" in records[0].getMessage()
    assert "reason=ENOENT" in records[0].getMessage()


def test_socket_nobody_listens_on_warns_once(tmp_path, caplog):
    caplog.set_level(logging.DEBUG, logger=LOGGER)
    path = str(tmp_path / "stale.sock")
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    stale.bind(path)
    stale.close()  # the file stays, nobody reads: ECONNREFUSED
    n = SystemdNotifier.from_env({"NOTIFY_SOCKET": path})
    assert n.ready() is False and n.ready() is False
    messages = [r.getMessage() for r in caplog.records if r.name == LOGGER]
    assert len(messages) == 1 and "reason=ECONNREFUSED" in messages[0]


def test_relative_socket_address_is_refused(caplog):
    caplog.set_level(logging.DEBUG, logger=LOGGER)
    n = SystemdNotifier.from_env({"NOTIFY_SOCKET": "notify.sock"})
    assert not n.enabled and n.ready() is False
    assert len([r for r in caplog.records if r.levelno == logging.WARNING]) == 1

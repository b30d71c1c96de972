"""``vflpcd run MISSION --with-sitl``: the mission's vehicle mock started beside the daemon.

For a ``can`` platform on a ``remote`` bus: python-can-remote's hub on the mission's port (unless
one already answers there), then ``vflpcd sitl can-ecu MISSION``; on ``socketcan``: the ECU mock on
the mission's channel. For a ``mavlink`` platform: ``vflpcd sitl quad`` sending to the mission's
``udpin`` port. The mocks log to ``LOG_DIR/sitl-*.log``; they run in their own process group, so
a Ctrl-C in the terminal (SIGINT to the foreground group) reaches the daemon only: the daemon lands
or stops the vehicle on the mock first. Only after the daemon has finished do they get SIGTERM, and
their statistics line is printed. An ``inproc`` mission, or a ``virtual`` bus (one process only), has no
mock to start: ConfigError naming the field.
"""

from __future__ import annotations

import json
import logging
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from urllib.parse import urlparse

from vflpcd.daemon import lifeline
from vflpcd.base.errors import ConfigError

log = logging.getLogger("vflpcd.sitl")


def _answers(host: str, port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex((host, port)) == 0


class SitlProcesses:
    """Context manager: starts the mission's mocks on enter, stops them on exit."""

    def __init__(self, mission, log_dir: Path) -> None:
        self.mission, self.log_dir = mission, Path(log_dir)
        self.procs: list[tuple[str, subprocess.Popen]] = []
        self.commands = self._commands()

    def _commands(self) -> list[tuple[str, list[str], tuple[str, int] | None]]:
        """(name, argv, TCP address it must answer on) for each mock, in start order."""
        m = self.mission
        kind, options = m.platform.kind, m.platform.options
        me = [sys.executable, "-m", "vflpcd"]
        if kind == "can":
            interface = options.get("interface", "socketcan")
            channel = str(options.get("channel", "vcan0"))
            if interface == "virtual":
                raise ConfigError(m.file, "platform.interface", "--with-sitl needs a bus other processes reach "
                                  "(remote or socketcan), not virtual")
            out = []
            if interface == "remote":
                url = urlparse(channel)
                host, port = url.hostname or "127.0.0.1", url.port or 54701
                if not _answers(host, port):
                    out.append(("hub", [sys.executable, "-m", "can_remote", "-H", host, "--interface", "virtual",
                                        "--channel", "vcan0", "--port", str(port)], (host, port)))
            out.append(("ecu", me + ["sitl", "can-ecu", str(m.file)], None))
            return out
        if kind == "mavlink":
            url = str(options.get("url", "udpin://127.0.0.1:14540"))
            parsed = urlparse(url)
            if parsed.scheme != "udpin" or parsed.port is None:
                raise ConfigError(m.file, "platform.url", f"--with-sitl needs a udpin://HOST:PORT url, got {url!r}")
            return [("quad", me + ["sitl", "quad", "--host", parsed.hostname or "127.0.0.1",
                                   "--port", str(parsed.port)], None)]
        raise ConfigError(m.file, "platform.kind", f"--with-sitl starts mocks of can and mavlink platforms, not {kind}")

    def __enter__(self) -> "SitlProcesses":
        self.log_dir.mkdir(parents=True, exist_ok=True)
        try:
            for name, argv, address in self.commands:
                err = open(self.log_dir / f"sitl-{name}.log", "wb")
                # out of the terminal's SIGINT, and killed with the daemon if it is killed itself
                proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=err, stdin=subprocess.DEVNULL,
                                        process_group=0, preexec_fn=lifeline.preexec())
                err.close()
                self.procs.append((name, proc))
                print(f"started {name} (pid {proc.pid}): {' '.join(argv)}", flush=True)
                if address is not None:
                    self._wait_until_it_answers(name, proc, address)
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def _wait_until_it_answers(self, name: str, proc: subprocess.Popen, address: tuple[str, int]) -> None:
        deadline = time.monotonic() + 10.0
        while not _answers(*address):
            if proc.poll() is not None or time.monotonic() > deadline:
                raise OSError(f"the {name} did not start on {address[0]}:{address[1]} "
                              f"(see {self.log_dir / f'sitl-{name}.log'})")
            time.sleep(0.1)

    def __exit__(self, *exc) -> None:
        for name, proc in reversed(self.procs):
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
            try:
                out, _ = proc.communicate(timeout=5.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                out, _ = proc.communicate()
            for line in (out or b"").decode(errors="replace").splitlines():
                if line.startswith("{"):
                    try:
                        print(f"{name}: {json.dumps(json.loads(line))}")
                    except ValueError:
                        pass
        self.procs = []

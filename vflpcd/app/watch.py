"""``vflpcd watch VEHICLE_ID``: a live table of a running daemon's telemetry.

Subscribes ``vflpc/<vehicle_id>/**`` on a Zenoh peer session (multicast scouting off; the
endpoints given with ``--connect`` / ``--listen``; with ``--identity FILE``, TLS with the
identity file's certificate, and, when the file names the ``daemon``, telemetry taken from that
identity only: ``vflpcd.daemon.zenoh_security.IdentityFile``) and, every ``refresh_s``, renders per topic the
message count, the age of the last message and its value in compact form, then the last five
events. On a terminal the table is redrawn in place; otherwise one block is printed per refresh.
Payload fields: ``docs/telemetry.md``.
"""

from __future__ import annotations

import json
import shutil
import sys
import threading
import time
from collections import deque
from typing import Any, TextIO

from vflpcd.base.errors import ConfigError

TOPIC_ORDER = ("state", "command", "reference", "obstacles", "timing", "health", "events", "perception/obstacles")
N_EVENTS = 5
CLEAR = "\x1b[H\x1b[2J"


class Board:
    """What has arrived: per topic the last decoded value, its receive time (monotonic s) and a
    message count; the last ``N_EVENTS`` events. ``on_sample`` runs on Zenoh's thread."""

    def __init__(self, vehicle_id: str) -> None:
        self.prefix = f"vflpc/{vehicle_id}/"
        self._lock = threading.Lock()
        self.last: dict[str, Any] = {}
        self.at: dict[str, float] = {}
        self.counts: dict[str, int] = {}
        self.events: deque = deque(maxlen=N_EVENTS)

    def on_sample(self, sample) -> None:
        key = str(sample.key_expr)
        topic = key[len(self.prefix):] if key.startswith(self.prefix) else key
        raw = sample.payload.to_bytes()
        try:
            value = json.loads(raw)
        except (ValueError, RecursionError):
            value = raw[:80].decode(errors="replace")
        now = time.monotonic()
        with self._lock:
            self.last[topic], self.at[topic] = value, now
            self.counts[topic] = self.counts.get(topic, 0) + 1
            if topic == "events":
                self.events.append(value)

    def copy(self) -> tuple[dict, dict, dict, list]:
        with self._lock:
            return dict(self.last), dict(self.at), dict(self.counts), list(self.events)


# --------------------------------------------------------------------------- formatting
def _num(x: Any, digits: int = 3) -> str:
    if x is None:
        return "-"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, float):
        return f"{x:.{digits}f}"
    return str(x)


def _named(values: list, names: list, fallback: str) -> str:
    names = list(names or ())
    return " ".join(f"{names[i] if i < len(names) else f'{fallback}{i}'}={_num(v)}" for i, v in enumerate(values))


def _ms(x: Any) -> str:
    return "-" if not isinstance(x, (int, float)) else f"{x * 1e3:.2f} ms"


def _kv(d: dict, skip: tuple[str, ...] = ()) -> str:
    return " ".join(f"{k}={_num(v)}" for k, v in d.items() if k not in skip and not isinstance(v, (dict, list)))


def summarize(topic: str, v: Any) -> str:
    """One line for the last value of ``topic``."""
    if not isinstance(v, dict):
        return str(v)[:80]
    if topic == "state":
        return (f"mode={v.get('mode')} t={_num(v.get('t'))} k={v.get('k')} "
                f"{_named(v.get('state') or [], v.get('state_names'), 'x')} (state age {_ms(v.get('age_s'))})")
    if topic == "command":
        cmd = v.get("command") or []
        return _named(cmd, v.get("control_names"), "u") if cmd else "(no command)"
    if topic == "reference":
        ref = "[" + ", ".join(_num(x) for x in v.get("reference") or []) + "]"
        return f"ref={ref} plan={v.get('plan_version')} model={v.get('model_version')}"
    if topic == "obstacles":
        obs = v.get("obstacles") or []
        n_per = sum(1 for o in obs if isinstance(o, dict) and o.get("source") == "perception")
        threats = ", ".join(map(str, v.get("threats") or [])) or "none"
        return f"{len(obs)} obstacles ({n_per} from perception), threats: {threats}"
    if topic == "timing":
        return (f"lateness {_ms(v.get('lateness_s'))}  compute {_ms(v.get('compute_s'))}  "
                f"overrun {_num(v.get('overrun'))}")
    if topic == "health":
        return _kv(v)
    if topic == "events":
        return event_line(v)
    if topic == "perception/obstacles":
        stamp = v.get("stamp")
        age = f", stamp age {time.time() - stamp:.2f} s" if isinstance(stamp, (int, float)) else ""
        return f"{len(v.get('obstacles') or [])} obstacles{age}"
    return _kv(v)[:120]


def event_line(v: Any) -> str:
    if not isinstance(v, dict):
        return str(v)[:80]
    if v.get("kind") == "header":
        return (f"header vehicle={v.get('vehicle_id')} platform={v.get('platform')} "
                f"controller={v.get('controller')} dim={v.get('dim')} rate={_num(v.get('rate_hz'), 0)} Hz")
    detail = v.get("detail") if isinstance(v.get("detail"), dict) else {}
    return f"t={_num(v.get('t'))} {v.get('kind')} {_kv(detail)}".rstrip()


def render(vehicle_id: str, board: Board, elapsed_s: float, now: float | None = None) -> str:
    """The table as text (no trailing newline)."""
    last, at, counts, events = board.copy()
    now = time.monotonic() if now is None else now
    topics = list(TOPIC_ORDER) + sorted(t for t in counts if t not in TOPIC_ORDER)
    lines = [f"vflpcd watch {vehicle_id}   {elapsed_s:.1f} s   {sum(counts.values())} messages",
             f"{'topic':<21}{'count':>7}{'age s':>8}  last value"]
    for t in topics:
        if t in counts:
            lines.append(f"{t:<21}{counts[t]:>7}{now - at[t]:>8.2f}  {summarize(t, last[t])}")
        else:
            lines.append(f"{t:<21}{0:>7}{'-':>8}  -")
    lines.append(f"last {N_EVENTS} events:")
    lines += [f"  {event_line(e)}" for e in events] or ["  (none yet)"]
    return "\n".join(lines)


# --------------------------------------------------------------------------- the command
def watch(vehicle_id: str, connect=(), listen=(), duration_s: float | None = None, out: TextIO = sys.stdout,
          refresh_s: float = 0.5, identity=None) -> int:
    """Render the telemetry of ``vehicle_id`` until ``duration_s`` has passed (None: until
    Ctrl-C). ``identity``: the path of an identity file (TLS). Returns 0. Bad arguments raise
    ConfigError("command line", option, ...); a bad identity file, ConfigError naming it."""
    from vflpcd.daemon.telemetry import TelemetryConfig, check_endpoint, check_vehicle_id, open_session
    from vflpcd.daemon.zenoh_security import IdentityFile, endpoint_problem

    try:
        check_vehicle_id(vehicle_id)
    except ValueError as exc:
        raise ConfigError("command line", "vehicle_id", str(exc)) from None
    for option, eps in (("--connect", connect), ("--listen", listen)):
        for ep in eps:
            problem = check_endpoint(ep, listen=option == "--listen")
            if problem is not None:
                raise ConfigError("command line", option, problem)
    ident = IdentityFile.load(identity) if identity is not None else None
    tls = ident.tls if ident is not None else None
    problem = endpoint_problem({"--connect": tuple(connect), "--listen": tuple(listen)}, tls)
    if problem is not None:
        option, reason = problem
        raise ConfigError("command line", option if tls is not None else "--identity",
                          reason + (" (an identity file)" if tls is None else ""))
    cfg = TelemetryConfig(mode="peer", connect=tuple(connect), listen=tuple(listen), multicast_scouting=False,
                          tls=tls, access=ident.policy() if ident is not None else None)
    session = open_session(cfg, vehicle_id=vehicle_id, file="command line",
                           fields={"connect": "--connect", "listen": "--listen", "mode": "watch", "session": "watch",
                                   "tls": "--identity", "access": "--identity"})
    board = Board(vehicle_id)
    tty = bool(getattr(out, "isatty", lambda: False)())
    start = time.monotonic()
    end = None if duration_s is None else start + max(0.0, float(duration_s))
    try:
        sub = session.declare_subscriber(f"vflpc/{vehicle_id}/**", board.on_sample)
        try:
            while True:
                now = time.monotonic()
                text = render(vehicle_id, board, now - start, now)
                if tty:
                    width = shutil.get_terminal_size().columns
                    out.write(CLEAR + "\n".join(line[:width] for line in text.splitlines()) + "\n")
                else:
                    out.write(text + "\n\n")
                out.flush()
                if end is not None and now >= end:
                    break
                time.sleep(max(0.0, refresh_s if end is None else min(refresh_s, end - now)))
        except KeyboardInterrupt:
            pass
        finally:
            sub.undeclare()
    finally:
        session.close()
    return 0

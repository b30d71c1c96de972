"""Telemetry out over Zenoh: the latest tick at a fixed rate, health once a second, every event.

Key expressions (``key_expressions``): ``vflpc/<vehicle_id>/<topic>`` for the topics ``state``,
``command``, ``reference``, ``obstacles``, ``timing``, ``health``, ``events``, and the perception
input ``vflpc/<vehicle_id>/perception/obstacles`` (read by ``vflpcd.daemon.perception``).
Every payload is one UTF-8 JSON object put with the encoding ``application/json``; non-finite
floats are sent as ``null``. The payload fields are documented in ``docs/telemetry.md``.

The link is open by default (plain TCP on loopback, no access control). ``[telemetry.tls]`` and
``[telemetry.access]`` (``vflpcd.daemon.zenoh_security``, ``docs/security.md``) make it TLS or
mutual TLS with Zenoh's access control: then gossip scouting is off as well, so that peers learn
of no other peers through the daemon.

The control thread never waits on the network: ``offer_tick`` stores the newest ``TickRecord``
(one attribute assignment); ``offer_event``/``offer_header`` append to a bounded queue. The thread
"telemetry" publishes the newest tick's payloads every ``1 / rate_hz`` s (only when a newer tick
came in), health every ``1 / health_rate_hz`` s, and queued events as soon as they are offered.
A failed put is logged and counted; it never raises into the caller.
"""

from __future__ import annotations

import ipaddress
import json
import logging
import queue
import re
import threading
import time
from dataclasses import dataclass
from typing import Any

import zenoh

from vflpcd.log.records import json_bytes, Event, MissionHeader, TickRecord
from vflpcd.base.errors import ConfigError
from vflpcd.base.tomlread import Table
from vflpcd.daemon.zenoh_security import AccessConfig, AccessPolicy, TlsConfig, endpoint_problem

log = logging.getLogger("vflpcd.daemon.telemetry")

TICK_TOPICS = ("state", "command", "reference", "obstacles", "timing")
PUBLISHED_TOPICS = TICK_TOPICS + ("health", "events")
MODES = ("peer", "client")
PROTOCOLS = ("tcp", "udp", "quic", "tls")
MAX_RATE_HZ = 200.0
MAX_PERCEPTION_RADIUS_M = 100.0
EVENT_QUEUE_MAX = 1000
JSON = zenoh.Encoding.APPLICATION_JSON

_VEHICLE_ID = re.compile(r"[A-Za-z0-9_-]+")
_ENDPOINT = re.compile(r"(?P<proto>[a-z0-9]+)/(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9](?:[A-Za-z0-9.-]*[A-Za-z0-9])?)"
                       r":(?P<port>[0-9]{1,5})")


# --------------------------------------------------------------------------- names
def check_vehicle_id(vehicle_id: str) -> str:
    """Return ``vehicle_id`` if it can name a Zenoh key segment: non-empty, [A-Za-z0-9_-]+ (so no
    '*', '$', '/', '#', '?'). Raises ValueError naming it otherwise."""
    if not isinstance(vehicle_id, str) or not _VEHICLE_ID.fullmatch(vehicle_id):
        raise ValueError(f"vehicle id {vehicle_id!r} is not valid: expected a non-empty string of "
                         "letters, digits, '_' and '-' (no '*', '$', '/', '#', '?', spaces)")
    return vehicle_id


def key_expressions(vehicle_id: str) -> dict[str, str]:
    """Topic -> key expression: the seven published topics and ``"perception"`` (the input)."""
    base = f"vflpc/{check_vehicle_id(vehicle_id)}"
    keys = {topic: f"{base}/{topic}" for topic in PUBLISHED_TOPICS}
    keys["perception"] = f"{base}/perception/obstacles"
    return keys


def key_space(vehicle_id: str) -> str:
    """``vflpc/<vehicle_id>/**``: every key expression of the vehicle."""
    return f"vflpc/{check_vehicle_id(vehicle_id)}/**"


def check_endpoint(endpoint: Any, *, listen: bool = False) -> str | None:
    """None when ``endpoint`` looks like ``proto/host:port`` (proto tcp|udp|quic|tls; host an IPv4
    address, a host name or ``[IPv6]``; port 1..65535, or 0 for a listen endpoint), else the
    reason."""
    if not isinstance(endpoint, str):
        return f"expected an endpoint string, got {type(endpoint).__name__}"
    m = _ENDPOINT.fullmatch(endpoint)
    if m is None:
        return f"endpoint {endpoint!r} is not of the form proto/host:port (e.g. tcp/127.0.0.1:7447)"
    if m["proto"] not in PROTOCOLS:
        return f"endpoint {endpoint!r}: protocol must be one of {', '.join(PROTOCOLS)}"
    host, port = m["host"], int(m["port"])
    try:
        if host.startswith("["):
            ipaddress.IPv6Address(host[1:-1])
        elif re.fullmatch(r"[0-9.]+", host):
            ipaddress.IPv4Address(host)
    except ValueError:
        return f"endpoint {endpoint!r}: {host} is not a valid IP address"
    if not (0 if listen else 1) <= port <= 65535:
        return f"endpoint {endpoint!r}: port must be in {0 if listen else 1}..65535"
    return None


# --------------------------------------------------------------------------- configuration
@dataclass(frozen=True)
class TelemetryConfig:
    """The ``[telemetry]`` table of a mission.

    mode: Zenoh session mode, "peer" | "client"; connect/listen: endpoints ``proto/host:port``
    (an empty ``listen`` opens no port); multicast_scouting: Zenoh's UDP multicast discovery;
    rate_hz: state/command/reference/obstacles/timing rate (Hz, (0, 200]); health_rate_hz: health
    rate (Hz, (0, 200]); perception: subscribe the perception input; perception_max_age_s: older
    perception messages are ignored (s); perception_area_margin_m: perceived centres must lie in
    the route's bounding box grown by this (m, >= 0); perception_max_speed: largest perceived
    speed (m/s, > 0); perception_max_radius: perceived radii must be below this (m, (0, 100]);
    perception_rate_hz: perception message budget (messages a second, (0, 200]; more are dropped
    unparsed); tls: TLS settings of every endpoint (None: plain links); access: who may do what
    over the link (Zenoh's access control, keyed by certificate common names; None: anyone may
    do anything).
    """

    enabled: bool = True
    mode: str = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    multicast_scouting: bool = False
    rate_hz: float = 10.0
    health_rate_hz: float = 1.0
    perception: bool = False
    perception_max_age_s: float = 0.5
    perception_area_margin_m: float = 50.0
    perception_max_speed: float = 40.0
    perception_max_radius: float = 10.0
    perception_rate_hz: float = 50.0
    tls: TlsConfig | None = None
    access: AccessPolicy | None = None

    @classmethod
    def from_table(cls, table: Table) -> TelemetryConfig:
        """Validate a ``[telemetry]`` table (all keys optional; files of ``tls`` relative to
        ``table.file``'s folder); raises ConfigError naming the field."""
        table.check_known({"enabled", "mode", "connect", "listen", "multicast_scouting", "rate_hz",
                           "health_rate_hz", "perception", "perception_max_age_s", "perception_area_margin_m",
                           "perception_max_speed", "perception_max_radius", "perception_rate_hz", "tls", "access"})
        d = cls()
        tls = TlsConfig.from_table(table.table("tls")) if table.has("tls") else None
        access = AccessConfig.from_table(table.table("access")) if table.has("access") else None
        cfg = cls(enabled=table.boolean("enabled", d.enabled),
                  mode=table.string("mode", d.mode, choices=MODES),
                  connect=_endpoints(table, "connect", listen=False),
                  listen=_endpoints(table, "listen", listen=True),
                  multicast_scouting=table.boolean("multicast_scouting", d.multicast_scouting),
                  rate_hz=table.number("rate_hz", d.rate_hz, positive=True, max=MAX_RATE_HZ),
                  health_rate_hz=table.number("health_rate_hz", d.health_rate_hz, positive=True, max=MAX_RATE_HZ),
                  perception=table.boolean("perception", d.perception),
                  perception_max_age_s=table.number("perception_max_age_s", d.perception_max_age_s, positive=True),
                  perception_area_margin_m=table.number("perception_area_margin_m", d.perception_area_margin_m,
                                                        min=0.0),
                  perception_max_speed=table.number("perception_max_speed", d.perception_max_speed, positive=True),
                  perception_max_radius=table.number("perception_max_radius", d.perception_max_radius,
                                                     positive=True, max=MAX_PERCEPTION_RADIUS_M),
                  perception_rate_hz=table.number("perception_rate_hz", d.perception_rate_hz, positive=True,
                                                  max=MAX_RATE_HZ),
                  tls=tls, access=access)
        problem = endpoint_problem({"listen": cfg.listen, "connect": cfg.connect}, tls)
        if problem is not None:
            key, reason = problem
            if tls is None:
                raise table.error("tls", f"{key}: {reason} (a [telemetry.tls] table)")
            raise table.error(key, reason)
        if access is not None and (tls is None or not tls.mutual):
            raise table.error("access", "access control tells identities apart by their client certificates: "
                                        "it needs [telemetry.tls] with mutual = true")
        if access is not None and cfg.perception and not access.perception:
            raise table.error("access.perception", "perception = true, but no identity may publish it: list the "
                                                   "perception certificates' common names")
        if cfg.enabled and cfg.mode == "client" and not cfg.connect and not cfg.multicast_scouting:
            raise table.error("connect", "client mode needs at least one endpoint to connect to "
                                         "(or multicast_scouting = true)")
        return cfg


def _endpoints(table: Table, key: str, *, listen: bool) -> tuple[str, ...]:
    value = table.data.get(key, [])
    if not isinstance(value, list):
        raise table.error(key, f"expected a list of endpoints such as [\"tcp/127.0.0.1:7447\"], "
                               f"got {type(value).__name__}")
    for i, ep in enumerate(value):
        problem = check_endpoint(ep, listen=listen)
        if problem is not None:
            raise table.error(key, f"[{i}]: {problem}")
    return tuple(value)


_FIELDS = {"mode": "telemetry.mode", "connect": "telemetry.connect", "listen": "telemetry.listen",
           "session": "telemetry", "tls": "telemetry.tls", "access": "telemetry.access"}


def zenoh_config(cfg: TelemetryConfig, *, vehicle_id: str | None = None, file=None,
                 fields: dict[str, str] | None = None) -> zenoh.Config:
    """The zenoh.Config of ``cfg``: mode, connect/endpoints, listen/endpoints,
    scouting/multicast/enabled; with ``cfg.tls`` also transport/link/tls and scouting/gossip/enabled
    = false; with ``cfg.access`` its access_control for the key expressions of ``vehicle_id``
    (required then). A value Zenoh refuses raises ConfigError naming the field."""
    names = {**_FIELDS, **(fields or {})}
    settings = [("mode", cfg.mode, "mode"), ("connect/endpoints", list(cfg.connect), "connect"),
                ("listen/endpoints", list(cfg.listen), "listen"),
                ("scouting/multicast/enabled", bool(cfg.multicast_scouting), "session")]
    if cfg.tls is not None:
        settings += [("transport/link/tls", cfg.tls.zenoh_json(), "tls"), ("scouting/gossip/enabled", False, "tls")]
    if cfg.access is not None:
        if vehicle_id is None:
            raise ValueError("access control needs the vehicle id whose key expressions it guards")
        settings.append(("access_control", cfg.access.access_control(key_expressions(vehicle_id),
                                                                     key_space(vehicle_id)), "access"))
    zc = zenoh.Config()
    for key, value, name in settings:
        try:
            zc.insert_json5(key, json.dumps(value))
        except zenoh.ZError as exc:
            raise ConfigError(file, names[name], f"Zenoh refused {value!r}: {_first_line(exc)}") from None
    return zc


def open_session(cfg: TelemetryConfig, *, vehicle_id: str | None = None, file=None,
                 fields: dict[str, str] | None = None) -> zenoh.Session:
    """Open a Zenoh session for ``cfg`` (``zenoh_config``; ``vehicle_id``: whose key expressions
    the access control guards). A listen endpoint already in use raises
    ``ConfigError(file, "telemetry.listen", "... in use ...")``; certificates or keys Zenoh cannot
    use raise it naming ``telemetry.tls``; any other failure raises a ConfigError naming the
    telemetry field (``fields`` renames them, e.g. for command-line options)."""
    names = {**_FIELDS, **(fields or {})}
    zc = zenoh_config(cfg, vehicle_id=vehicle_id, file=file, fields=fields)
    try:
        return zenoh.open(zc)
    except zenoh.ZError as exc:
        text = str(exc)
        if "in use" in text:          # first: a TLS listener's message says "TLS" too
            eps = [ep for ep in cfg.listen if ep.rsplit(":", 1)[-1] in text] or list(cfg.listen)
            raise ConfigError(file, names["listen"], f"endpoint {', '.join(eps)} is already in use "
                                                     "(another daemon or program listens there)") from None
        if cfg.tls is not None and ("TLS" in text or "certificate" in text.lower()):
            raise ConfigError(file, names["tls"], f"Zenoh cannot use the certificates: {_first_line(exc)}") from None
        if "listener" in text:
            raise ConfigError(file, names["listen"], f"cannot listen: {_first_line(exc)}") from None
        if "connect" in text or "No peer" in text:
            raise ConfigError(file, names["connect"], f"cannot connect: {_first_line(exc)}") from None
        raise ConfigError(file, names["session"], f"cannot open the Zenoh session: {_first_line(exc)}") from None


def _first_line(exc: BaseException) -> str:
    text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return re.sub(r" at /\S+:\d+\.?", "", text)  # drop Zenoh's source locations


# --------------------------------------------------------------------------- payloads
def tick_payloads(rec: TickRecord, state_names=(), control_names=()) -> dict[str, dict[str, Any]]:
    """Topic -> JSON object for the five tick topics (fields in ``docs/telemetry.md``)."""
    head = {"k": rec.k, "t": rec.t, "stamp_ns": rec.stamp_ns}
    return {
        "state": {**head, "mode": rec.mode, "state_names": list(state_names), "state": list(rec.state),
                  "age_s": rec.state_age_s},
        "command": {**head, "mode": rec.mode, "control_names": list(control_names), "command": list(rec.command)},
        "reference": {**head, "reference": list(rec.reference), "plan_version": rec.plan_version,
                      "model_version": rec.model_version},
        "obstacles": {**head, "threats": list(rec.threats), "obstacles": [o.to_json() for o in rec.obstacles]},
        "timing": {**head, "lateness_s": rec.lateness_s, "compute_s": rec.compute_s, "overrun": rec.overrun},
    }


# --------------------------------------------------------------------------- publisher
class TelemetryPublisher:
    """Publishes a daemon's telemetry on ``session`` from its own thread "telemetry".

    ``state_names`` / ``control_names`` (the platform's) go into the state/command payloads.
    Counters: ``published`` (successful puts), ``events_dropped`` (queue full), ``errors``
    (failed puts).
    """

    def __init__(self, session: zenoh.Session, vehicle_id: str, cfg: TelemetryConfig, *,
                 state_names=(), control_names=()) -> None:
        self.keys = key_expressions(vehicle_id)
        self.cfg = cfg
        self.state_names, self.control_names = tuple(state_names), tuple(control_names)
        self.published = self.events_dropped = self.errors = 0
        self._tick: TickRecord | None = None
        self._health: dict | None = None
        self._events: queue.Queue = queue.Queue(maxsize=EVENT_QUEUE_MAX)
        self._wake = threading.Event()
        self._stop = False
        self._failing: set[str] = set()
        self._pubs = {t: session.declare_publisher(self.keys[t], encoding=JSON) for t in PUBLISHED_TOPICS}
        self._thread = threading.Thread(target=self._run, name="telemetry", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ producers (any thread)
    def offer_tick(self, rec: TickRecord) -> None:
        """Keep ``rec`` as the newest tick (non-blocking, O(1))."""
        self._tick = rec

    def offer_health(self, health: dict) -> None:
        """Keep ``health`` (a JSON-ready dict) as the newest health report."""
        self._health = health

    def offer_event(self, ev: Event) -> None:
        """Queue an event for immediate publication; dropped (and counted) only when 1,000 wait."""
        self._enqueue(ev.to_json())

    def offer_header(self, header: MissionHeader) -> None:
        """Queue the mission header, published on ``events`` as ``{"kind": "header", ...}``."""
        self._enqueue({"kind": "header", **header.to_json()})

    def _enqueue(self, obj: dict) -> None:
        try:
            self._events.put_nowait(obj)
        except queue.Full:
            self.events_dropped += 1
            return
        self._wake.set()

    def matched(self, topic: str = "state") -> bool:
        """Whether some subscriber currently matches ``topic``'s key expression."""
        try:
            return bool(self._pubs[topic].matching_status.matching)
        except Exception:  # closed or undeclared
            return False

    # ------------------------------------------------------------------ the thread
    def _run(self) -> None:
        tick_period, health_period = 1.0 / self.cfg.rate_hz, 1.0 / self.cfg.health_rate_hz
        next_tick = next_health = time.monotonic()
        sent_tick = sent_health = None
        while True:
            stopping = self._stop
            self._wake.clear()
            try:
                self._drain_events()
                now = time.monotonic()
                if now >= next_tick or stopping:
                    next_tick = _advance(next_tick, tick_period, now)
                    rec = self._tick
                    if rec is not None and rec is not sent_tick:
                        sent_tick = rec
                        for topic, obj in tick_payloads(rec, self.state_names, self.control_names).items():
                            self._put(topic, obj)
                if now >= next_health or stopping:
                    next_health = _advance(next_health, health_period, now)
                    health = self._health
                    if health is not None and health is not sent_health:
                        sent_health = health
                        self._put("health", health)
            except Exception:  # never let the thread die on a bad record
                log.exception("event=telemetry_error")
            if stopping:
                return
            self._wake.wait(max(0.0, min(next_tick, next_health) - time.monotonic()))

    def _drain_events(self) -> None:
        while True:
            try:
                obj = self._events.get_nowait()
            except queue.Empty:
                return
            self._put("events", obj)

    def _put(self, topic: str, obj: Any) -> None:
        try:
            self._pubs[topic].put(json_bytes(obj), encoding=JSON)
        except Exception as exc:
            self.errors += 1
            if topic not in self._failing:  # log once per failure streak and topic
                self._failing.add(topic)
                log.warning("event=telemetry_put_failed topic=%s error=%s", topic, _first_line(exc))
            return
        self.published += 1
        self._failing.discard(topic)

    def close(self) -> None:
        """Publish what is queued, stop the thread (join at most 1 s), undeclare the publishers."""
        if self._stop and not self._pubs:
            return
        self._stop = True
        self._wake.set()
        self._thread.join(1.0)
        if self._thread.is_alive():
            log.warning("event=telemetry_join_timeout")
        for pub in self._pubs.values():
            try:
                pub.undeclare()
            except Exception:
                pass
        self._pubs = {}


def _advance(due: float, period: float, now: float) -> float:
    """The next deadline after ``now`` on the grid ``due + n * period`` (no bursts after a stall)."""
    due += period
    return due if due > now else now + period

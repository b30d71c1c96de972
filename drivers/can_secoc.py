"""Authenticated CAN frames in the manner of AUTOSAR SecOC: a freshness value and a truncated MAC.

Layout (``config/can/vehicle.dbc``). Every message of the vehicle link (the "authentic PDU",
unchanged: VehicleCmd, VehicleStatus, InsPosition, InsHeadingVelocity) is followed at once by
its cryptographic PDU ``<Name>Auth`` on the id ``0x80`` above it, sent by the same node, 8 bytes:

- ``FreshnessLow`` (bytes 0..3, little-endian): the low ``FRESHNESS_BITS`` bits of the full
  64-bit freshness value;
- ``Mac`` (bytes 4..7): the first 4 bytes of HMAC-SHA256(key, id as 4 bytes big-endian ||
  authentic payload || full freshness value as 8 bytes big-endian).

No message has 32 spare bits (InsPosition has none at all), so the authentication travels in a
PDU of its own, as SecOC's secured PDU collection does; the authentic PDUs keep their alive
counter and checksum. SecOC profile 1 uses AES-128-CMAC; HMAC-SHA256 of the standard library is
used here instead, so that the link needs no cryptography package (and no AES in software). Both
are keyed pseudo-random functions truncated the same way; swapping the MAC changes ``mac`` only.

Freshness (sender, per message): the next value is max(previous + 1, wall clock in ms). It
increases by at least one per frame and keeps up with the clock, so a restarted sender goes on
above everything it sent before (while it sends fewer than 1000 frames a second of a message
and its clock is not set back).

Reception (``Receiver``, per message): a data frame is held until its cryptographic PDU comes;
at most ``PENDING`` frames of an id wait (the oldest beyond them is dropped), so that frames
injected between a sender's data frame and its PDU do not make it lose the frame. With 4, a flood
of 150 frames a second can push a command out when the sender is held off some 30 ms between its
two frames (a loaded machine), and the next command then breaks the ECU's alive-counter
sequence: the SecOC integration test saw one such counter error in some full-suite runs. Each
PDU checks at most that many MACs. A PDU is
checked against the waiting frames, newest first, and takes the one its MAC verifies. The full freshness value is reconstructed from the
received low bits as the value nearest the reference (the newest accepted value; before the
first one, the receiver's own clock): a window of half the low bits' range on either side.
SecOC's rule takes the next value above the newest; reaching back as far as forward lets a
replayed frame be recognised as stale instead of counted as a bad MAC. A frame is accepted when
its MAC verifies and its freshness value is above the newest accepted one; the first one of an
id must also be at most ``clock_skew_s`` behind the receiver's clock (a recording replayed to a
receiver that has just started). Rejected frames are counted by kind (``AUTH_ERRORS``):

- ``replayed``: the MAC verifies, the freshness value is not newer (a replayed or reordered frame);
- ``forged``: a cryptographic PDU whose MAC verifies none of the waiting frames (forged or
  altered, or with no frame before it);
- ``unauthenticated``: a data frame that no cryptographic PDU authenticated while it waited (a
  plain-profile sender's, or the data frame of a forged pair). Each frame is counted once: a
  forged pair counts its PDU as ``forged`` and, once it is pushed out, its data frame as
  ``unauthenticated``.
"""

from __future__ import annotations

import hmac
import struct
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import can

from vflpcd.base.errors import ConfigError
from vflpcd.base.inputfile import read_bytes

AUTH_ERRORS = ("replayed", "forged", "unauthenticated")
FRESHNESS_BITS = 32
MAC_BYTES = 4
AUTH_ID_OFFSET = 0x80          # the cryptographic PDU's id: the authentic PDU's + 0x80
AUTH_SUFFIX = "Auth"           # and its name: the authentic PDU's + "Auth"
MIN_KEY_BYTES = 16             # 128 bits, SecOC's AES-128 key length
KEY_MAX_BYTES = 64 * 1024      # a key file is a few dozen bytes
PENDING = 16                   # data frames of one id waiting for their cryptographic PDU (module docstring)
DEFAULT_CLOCK_SKEW_S = 2.0


def wall_clock_ms() -> int:
    return time.time_ns() // 1_000_000


def mac(key: bytes, frame_id: int, data: bytes, freshness: int) -> bytes:
    """The truncated MAC of an authentic PDU: HMAC-SHA256 over (id, payload, full freshness value)."""
    message = struct.pack(">I", frame_id) + bytes(data) + struct.pack(">Q", freshness)
    return hmac.digest(key, message, "sha256")[:MAC_BYTES]


def reconstruct(low: int, reference: int, bits: int = FRESHNESS_BITS) -> int:
    """The full freshness value whose low ``bits`` bits are ``low``, nearest ``reference``: the one in
    (reference - 2**(bits-1), reference + 2**(bits-1)] (not below 0)."""
    span = 1 << bits
    value = (reference & ~(span - 1)) | (low & (span - 1))
    if value - reference > span // 2:
        value -= span
    elif reference - value >= span // 2:
        value += span
    return value if value >= 0 else value + span


def auth_pdu(frame_id: int, freshness: int, key: bytes, data: bytes) -> can.Message:
    """The cryptographic PDU of the authentic PDU (``frame_id``, ``data``) at ``freshness``."""
    payload = struct.pack("<I", freshness & ((1 << FRESHNESS_BITS) - 1)) + mac(key, frame_id, data, freshness)
    return can.Message(arbitration_id=frame_id + AUTH_ID_OFFSET, data=payload, is_extended_id=False)


class AuthError(ValueError):
    """A frame the receiver drops: ``kind`` is one of AUTH_ERRORS; ``frame_id`` the authentic PDU's."""

    def __init__(self, kind: str, frame_id: int, detail: str) -> None:
        super().__init__(f"{kind}: {detail}")
        self.kind, self.frame_id = kind, frame_id


class Sender:
    """Freshness values and cryptographic PDUs of one node's messages. ``clock_ms``: the wall clock."""

    def __init__(self, key: bytes, clock_ms=wall_clock_ms) -> None:
        self.key, self.clock_ms = key, clock_ms
        self._freshness: dict[int, int] = {}

    def protect(self, frame: can.Message) -> can.Message:
        """The cryptographic PDU to send right after ``frame``."""
        frame_id = frame.arbitration_id
        value = max(self._freshness.get(frame_id, -1) + 1, self.clock_ms())
        self._freshness[frame_id] = value
        return auth_pdu(frame_id, value, self.key, bytes(frame.data))

    def freshness(self, frame_id: int) -> int | None:
        """The freshness value of the newest frame sent on ``frame_id``."""
        return self._freshness.get(frame_id)


class Receiver:
    """Checks the frames of the authentic PDUs ``ids`` (others pass as they are). ``feed`` returns the
    frame to use: an authenticated data frame (when its cryptographic PDU comes) or a frame of
    another id; None while a frame waits or when it was dropped. Each dropped frame is handed to
    ``on_reject(AuthError)``."""

    def __init__(self, key: bytes, ids, on_reject, *, clock_skew_s: float = DEFAULT_CLOCK_SKEW_S,
                 clock_ms=wall_clock_ms) -> None:
        self.key, self.on_reject, self.clock_ms = key, on_reject, clock_ms
        self.ids = frozenset(ids)
        self.skew_ms = int(clock_skew_s * 1000)
        self._auth_ids = {i + AUTH_ID_OFFSET: i for i in self.ids}
        self._pending: dict[int, deque] = {i: deque() for i in self.ids}
        self._newest: dict[int, int] = {}

    def newest(self, frame_id: int) -> int | None:
        """The newest accepted freshness value of ``frame_id``."""
        return self._newest.get(frame_id)

    def raise_floor(self, frame_id: int, freshness: int) -> None:
        """Accept nothing on ``frame_id`` at or below ``freshness`` from now on (the node's own sends:
        the bus does not echo them, and any copy of them is a replay)."""
        self._newest[frame_id] = max(self._newest.get(frame_id, freshness), freshness)

    def feed(self, frame: can.Message) -> can.Message | None:
        frame_id = frame.arbitration_id
        if frame.is_extended_id or frame.is_remote_frame or frame.is_error_frame:
            return frame
        if frame_id in self.ids:
            pending = self._pending[frame_id]
            pending.append(frame)
            if len(pending) > PENDING:
                pending.popleft()
                self._reject("unauthenticated", frame_id, f"0x{frame_id:X} without its authentication PDU")
            return None
        data_id = self._auth_ids.get(frame_id)
        if data_id is None:
            return frame
        return self._authenticate(data_id, bytes(frame.data))

    def _authenticate(self, frame_id: int, auth: bytes) -> can.Message | None:
        pending = self._pending[frame_id]
        if len(auth) != 4 + MAC_BYTES:
            self._reject("forged", frame_id, f"0x{frame_id + AUTH_ID_OFFSET:X} with {len(auth)} bytes")
            return None
        if not pending:
            self._reject("forged", frame_id, f"0x{frame_id + AUTH_ID_OFFSET:X} with no frame to authenticate")
            return None
        low, tag = struct.unpack("<I", auth[:4])[0], auth[4:]
        now = self.clock_ms()
        newest = self._newest.get(frame_id)
        freshness = reconstruct(low, newest if newest is not None else now)
        for k in range(len(pending) - 1, -1, -1):          # newest first; frames injected around ours wait on
            frame = pending[k]
            if hmac.compare_digest(mac(self.key, frame_id, bytes(frame.data), freshness), tag):
                break
        else:
            self._reject("forged", frame_id, f"0x{frame_id + AUTH_ID_OFFSET:X}: the MAC verifies no waiting frame")
            return None
        del pending[k]
        if newest is not None and freshness <= newest:
            self._reject("replayed", frame_id, f"0x{frame_id:X}: freshness {freshness} not above {newest}")
            return None
        if newest is None and freshness < now - self.skew_ms:
            self._reject("replayed", frame_id, f"0x{frame_id:X}: freshness {now - freshness} ms behind the clock")
            return None
        self._newest[frame_id] = freshness
        return frame

    def _reject(self, kind: str, frame_id: int, detail: str) -> None:
        self.on_reject(AuthError(kind, frame_id, detail))


# ---------------------------------------------------------------------- the key and the mission
@dataclass(frozen=True)
class AuthConfig:
    """A link's authentication: the shared ``key`` and how far a sender's clock may lag (s)."""

    key: bytes
    clock_skew_s: float = DEFAULT_CLOCK_SKEW_S


def load_key(path: Path) -> bytes:
    """The key in ``path``: a text file of hex digits (whitespace and lines starting with # ignored),
    else the file's raw bytes; ValueError when it cannot be read or holds fewer than MIN_KEY_BYTES."""
    try:
        raw = read_bytes(path, KEY_MAX_BYTES)
    except ConfigError as exc:
        raise ValueError(f"key file {str(path)!r}: {exc.message}") from None
    key = raw
    try:
        lines = [line for line in raw.decode("ascii").splitlines() if not line.lstrip().startswith("#")]
        key = bytes.fromhex("".join("".join(lines).split()))
    except ValueError:                        # not hex text: the raw bytes are the key
        pass
    if len(key) < MIN_KEY_BYTES:
        raise ValueError(f"the key in {str(path)!r} has {len(key)} bytes; at least {MIN_KEY_BYTES} are needed")
    return key


def auth_config(t, mission_file) -> AuthConfig | None:
    """The authentication named by a ``[platform]`` table (``vflpcd.base.tomlread.Table``):
    ``auth_key`` (a key file, relative to the mission file) and ``auth_clock_skew`` (s); None
    without ``auth_key`` (the plain profile). ConfigError naming the field."""
    skew = t.number("auth_clock_skew", DEFAULT_CLOCK_SKEW_S, min=0.05, max=60.0)
    if not t.has("auth_key"):
        return None
    name = t.string("auth_key")
    path = Path(name).expanduser()
    if not path.is_absolute() and mission_file is not None:
        path = Path(mission_file).parent / path
    try:
        return AuthConfig(load_key(path), skew)
    except ValueError as exc:
        raise t.error("auth_key", str(exc)) from None


def secured_ids(db, names) -> dict[str, int]:
    """The ids of the authentic PDUs ``names`` in the cantools database ``db``, each checked to have
    its cryptographic PDU ``<name>Auth`` (8 bytes, id + 0x80); ValueError naming what is missing."""
    by_name = {m.name: m for m in db.messages}
    out = {}
    for name in names:
        auth = by_name.get(name + AUTH_SUFFIX)
        if name not in by_name or auth is None or auth.frame_id != by_name[name].frame_id + AUTH_ID_OFFSET \
                or auth.length != 4 + MAC_BYTES:
            raise ValueError(f"the CAN database lacks {name}{AUTH_SUFFIX} (8 bytes, the id of {name} + 0x80)")
        out[name] = by_name[name].frame_id
    return out

"""fedmap's frames: the layout of every message between nodes, and of every record a node
writes to its own disk (:mod:`fedmap.mission.network.nodelog`).

A **message frame** (what a transport carries, :func:`pack_message`) is binary and small:
``<BBhII`` = version (:data:`WIRE_VERSION`), kind (:data:`ORDER`, :data:`REPORT`,
:data:`HISTORY`), sender (a rover's number, or -1 for the base station), round, step; then
the kind's body (the strategy's payload inside it, as length-prefixed bytes); then a CRC-32
of everything before it (``<I``). Its layout per kind is in ``docs/protocol.md``; every
length in it is checked against what is left before it is read (:class:`Reader`).

A **record frame** (a log entry or a journal on disk, :func:`pack_frame`) is a version byte
(:data:`RECORD_VERSION`), a CRC-32 check of the rest, a JSON header and length-prefixed blobs
(``<BII`` = version, crc32, header length; then the header; then each blob as ``<I`` length
+ bytes).

A frame that fails its check or its layout is refused with one line
(:class:`CorruptMessage`): a transport sends it again, a reader of a log says which file.
"""

from __future__ import annotations

import json
import struct
import zlib
from dataclasses import dataclass

from fedmap.errors import FedmapError

#: The message frame's version (the first byte of every message between nodes).
WIRE_VERSION = 2
#: The record frame's version (the first byte of every record a node writes to its disk).
RECORD_VERSION = 1
#: Message kinds: the base's order to a rover, a rover's report, every order a rover was sent,
#: a strategy's message from one node to another (an uplink, a downlink, a peer message), and
#: mail between the agents of a peer mission (:mod:`fedmap.mission.network.peers`).
ORDER, REPORT, HISTORY, PAYLOAD, MAIL = 1, 2, 3, 4, 5
KINDS = {ORDER: "order", REPORT: "report", HISTORY: "history", PAYLOAD: "strategy message", MAIL: "mail"}
_MSG = struct.Struct("<BBhII")  # version, kind, sender, round, step
_CRC = struct.Struct("<I")
#: Bytes a message frame adds to its body: its head and its check.
MESSAGE_OVERHEAD = _MSG.size + _CRC.size
_HEAD = struct.Struct("<BII")  # version, crc32 of what follows, header length
_BLOB = struct.Struct("<I")


class CorruptMessage(FedmapError):
    """A frame whose check failed or whose layout is wrong."""


@dataclass(frozen=True)
class Head:
    """A message frame's head."""

    kind: int
    sender: int
    round: int
    step: int


class Writer:
    """A message body, field by field (little-endian)."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []

    def put(self, fmt: str, *values) -> Writer:
        self.parts.append(struct.pack("<" + fmt, *values))
        return self

    def blob(self, data: bytes) -> Writer:
        """``data`` as ``<I`` length + bytes."""
        self.parts.append(_BLOB.pack(len(data)) + bytes(data))
        return self

    def text(self, value: str) -> Writer:
        """``value`` (UTF-8, at most 255 bytes) as ``<B`` length + bytes."""
        b = value.encode()
        if len(b) > 255:
            raise ValueError(f"a name of {len(b)} bytes: names on the wire are at most 255")
        self.parts.append(bytes([len(b)]) + b)
        return self

    def done(self) -> bytes:
        """The body written so far."""
        return b"".join(self.parts)


class Reader:
    """A message body read field by field; every read is checked against what is left
    (:class:`CorruptMessage` when the body is shorter than it says, or longer at :meth:`end`)."""

    def __init__(self, body: bytes, what: str) -> None:
        self.body, self.off, self.what = memoryview(body), 0, what

    def _take(self, n: int) -> memoryview:
        if n < 0 or self.off + n > len(self.body):
            raise CorruptMessage(f"corrupted message: its {self.what} is cut short")
        out = self.body[self.off:self.off + n]
        self.off += n
        return out

    def get(self, fmt: str) -> tuple:
        st = struct.Struct("<" + fmt)
        return st.unpack(self._take(st.size))

    def one(self, fmt: str):
        return self.get(fmt)[0]

    def blob(self) -> bytes:
        return bytes(self._take(self.one("I")))

    def text(self) -> str:
        try:
            return bytes(self._take(self.one("B"))).decode()
        except UnicodeDecodeError:
            raise CorruptMessage(f"corrupted message: its {self.what} holds a name that is not UTF-8") from None

    def end(self) -> None:
        if self.off != len(self.body):
            raise CorruptMessage(f"corrupted message: {len(self.body) - self.off} bytes after its {self.what}")


def pack_message(head: Head, body: bytes) -> bytes:
    """A message frame: ``head``, ``body``, and the check of both."""
    raw = _MSG.pack(WIRE_VERSION, head.kind, head.sender, head.round, head.step) + body
    return raw + _CRC.pack(zlib.crc32(raw))


def unpack_message(raw: bytes, kind: int | None = None) -> tuple[Head, Reader]:
    """The head of a message frame and a :class:`Reader` of its body; :class:`CorruptMessage`
    when its check fails, its version is not this end's, or it is not of ``kind``."""
    raw = bytes(raw)
    if len(raw) < MESSAGE_OVERHEAD:
        raise CorruptMessage(f"corrupted message: {len(raw)} bytes, shorter than a frame's head")
    if raw[0] != WIRE_VERSION:
        raise CorruptMessage(f"message of wire version {raw[0]}, this end speaks {WIRE_VERSION}: update fedmap on "
                             "both ends")
    (crc,) = _CRC.unpack_from(raw, len(raw) - _CRC.size)
    if zlib.crc32(raw[:-_CRC.size]) != crc:
        raise CorruptMessage("corrupted message: its check failed")
    _, k, sender, round_no, step = _MSG.unpack_from(raw)
    if kind is not None and k != kind:
        raise CorruptMessage(f"expected {KINDS[kind]}, got a {KINDS.get(k, f'kind {k}')!r} message")
    return Head(k, sender, round_no, step), Reader(raw[_MSG.size:-_CRC.size], KINDS.get(k, "message"))


def pack_payload(sender: int, to: int, round_no: int, step: int, kind: str, payload: bytes) -> bytes:
    """A strategy's message from node ``sender`` to node ``to`` (-1: the base station or the
    lander) as a message frame: its kind (the strategy's name for it) and its payload."""
    return pack_message(Head(PAYLOAD, sender, round_no, step), Writer().put("h", to).text(kind).blob(payload).done())


def unpack_payload(raw: bytes) -> tuple[Head, int, str, bytes]:
    """The head, receiver, kind and payload of :func:`pack_payload`'s frame."""
    head, r = unpack_message(raw, PAYLOAD)
    to, kind, payload = r.one("h"), r.text(), r.blob()
    r.end()
    return head, to, kind, payload


@dataclass(frozen=True)
class Frame:
    """A strategy's message from node ``sender`` to node ``to`` (:data:`BASE` = -1: the base
    station or the lander), sent in round ``round`` at step ``step``: what nodes hand a
    transport and take from it. ``payload`` None: the sender had something to say but
    nothing fit its budget (the transport records it; nothing crosses)."""

    sender: int
    to: int
    round: int
    step: int
    kind: str
    payload: bytes | None

    def pack(self) -> bytes:
        """The frame on the wire (:func:`pack_payload`)."""
        return pack_payload(self.sender, self.to, self.round, self.step, self.kind, self.payload or b"")

    @classmethod
    def unpack(cls, raw: bytes) -> Frame:
        """The frame in ``raw``; :class:`CorruptMessage` for anything that is not one."""
        head, to, kind, payload = unpack_payload(raw)
        return cls(head.sender, to, head.round, head.step, kind, payload)


def pack_frame(header: dict, blobs: list[bytes] = ()) -> bytes:  # type: ignore[assignment]
    """``header`` (JSON) and ``blobs`` as one checked frame."""
    head = json.dumps(header, separators=(",", ":")).encode()
    body = head + b"".join(_BLOB.pack(len(b)) + bytes(b) for b in blobs)
    return _HEAD.pack(RECORD_VERSION, zlib.crc32(body), len(head)) + body


def unpack_frame(raw: bytes) -> tuple[dict, list[bytes]]:
    """The header and blobs of a frame; :class:`CorruptMessage` when its check or layout fails."""
    if len(raw) < _HEAD.size:
        raise CorruptMessage(f"corrupted message: {len(raw)} bytes, shorter than a header")
    version, crc, n = _HEAD.unpack_from(raw)
    if version != RECORD_VERSION:
        raise CorruptMessage(f"record of version {version}, this fedmap reads {RECORD_VERSION}: update fedmap")
    body = raw[_HEAD.size:]
    if zlib.crc32(body) != crc:
        raise CorruptMessage("corrupted message: its check failed")
    try:
        header = json.loads(body[:n])
        blobs, off = [], n
        while off < len(body):
            (size,) = _BLOB.unpack_from(body, off)
            blobs.append(body[off + _BLOB.size: off + _BLOB.size + size])
            off += _BLOB.size + size
    except (ValueError, struct.error) as e:
        raise CorruptMessage(f"corrupted message: {e}") from None
    if off != len(body):
        raise CorruptMessage("corrupted message: its last blob is cut short")
    if not isinstance(header, dict):
        raise CorruptMessage("corrupted message: its header is not a JSON object")
    return header, blobs


__all__ = ["HISTORY", "KINDS", "MESSAGE_OVERHEAD", "ORDER", "RECORD_VERSION", "REPORT", "WIRE_VERSION", "CorruptMessage",
           "Frame", "Head", "PAYLOAD", "Reader", "Writer", "pack_frame", "pack_message", "pack_payload", "unpack_frame",
           "unpack_message", "unpack_payload"]

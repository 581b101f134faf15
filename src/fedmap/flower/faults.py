"""Faults a rover can inject into its own uplink, for fault-injection tests of a deployment.

``fault=<kind>@<round>`` in a rover's node config (``fedmap rover --fault``) changes the
payload it sends in that round, after its own checks, as a broken radio or a faulty rover
would:

``bitflip``  one bit in the middle of the payload flipped (the base's CRC check catches it)
``nan``      the last weight of an ``fp32`` payload set to NaN with a valid CRC, i.e. a
             well-formed payload a rover should never have sent (the base's finiteness
             check catches it)

The base drops the rover for that round with the reason in ``metrics.json``. Nothing here
imports ``flwr``.
"""

from __future__ import annotations

import struct
import zlib

from fedmap.errors import FedmapError

KINDS = ("bitflip", "nan")


def parse_fault(text: str) -> tuple[str, int]:
    """``"bitflip@2"`` -> ``("bitflip", 2)``; a one-line error for anything else."""
    kind, _, when = str(text).partition("@")
    if kind not in KINDS or not when.isdigit() or int(when) < 1:
        raise FedmapError(f"fault must be <{'|'.join(KINDS)}>@<round >= 1>, got {text!r}")
    return kind, int(when)


def inject(fault: str, payload: bytes, server_round: int) -> bytes:
    """``payload`` with ``fault`` applied when ``server_round`` is the fault's round."""
    kind, when = parse_fault(fault)
    if when != server_round:
        return payload
    b = bytearray(payload)
    if kind == "bitflip":
        b[len(b) // 2] ^= 0x01
        return bytes(b)
    # fp32 dense payloads end with the last weight's 4 bytes, then a CRC-32 of all before it
    if len(b) < 15 or b[5] != 0 or b[6] & ~0x2:
        raise FedmapError("the nan fault needs the fp32 uplink codec")
    b[-8:-4] = struct.pack("<f", float("nan"))
    b[-4:] = struct.pack("<I", zlib.crc32(bytes(b[:-4])))
    return bytes(b)

"""``raw``: lossless sharing of observed cells with the ``context`` codec, on the star
(:class:`RawRover`, :class:`RawBase`) and as gossip on a peer topology (:class:`RawPeer`);
and the two strategies that use no link, ``none`` and the ``central`` oracle.

* ``raw`` on the star: a rover sends the cells it observed since its last *delivered* sync,
  as a class map (other cells UNKNOWN) coded with fedmap's lossless ``context`` codec
  (:mod:`fedmap.coding.mapcodec`). **Over budget**, it sends the newest cells that fit
  (every cell first observed at or after a cut-off step, the earliest cut-off that fits)
  and keeps the rest for the next sync; lost cells are sent again. The base overlays every
  delivered map on its global map (observations are truth, so they never conflict) and
  sends each rover the global map coded *against the last global map that rover
  acknowledged* (unchanged cells cost almost nothing); over budget it sends the cells it
  merged most recently that fit. With an elevation layer (``[mission] layers``) both
  directions also carry the heights of the same cells, quantised to ``elevation_q_m``
  (:class:`~fedmap.federation.heights.HeightCodec` ``lossless``), after the class map.
* ``raw`` on a peer topology: anti-entropy gossip of observed cells, coded the same way.
  Every agent keeps, per other agent, the cells it knows that agent holds (its version
  vector, kept per cell): those it sent and saw acknowledged, and those it received from
  it. A message carries every cell the sender holds that it does not know the receiver
  holds, so nothing is sent twice over a link that acknowledged it, and nothing is sent
  back to where it came from. Over budget, the newest cells that fit; lost cells are sent
  again.
* ``none``: nothing is sent; a rover's belief is its own observations.
* ``central``: the oracle outside the link; every rover and the base see every
  observation (and height) at once, free.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

from fedmap.coding.mapcodec import decode_map, encode_map
from fedmap.errors import RejectedUpdate
from fedmap.federation.heights import HeightCodec
from fedmap.maps.grid import UNKNOWN
from fedmap.mission.ends.protocol import (
    BaseEnd,
    Cell,
    Journal,
    Outgoing,
    PeerEnd,
    RoverEnd,
    cut_to_budget,
    pack_down,
    pack_up,
    unpack_down,
    unpack_up,
)

_LEN = struct.Struct("<I")  # the class map's length, before the heights (elevation layer)


class _Heights:
    """The elevation layer of a ``raw`` message: the class map, then the heights of the same
    cells (None: classes only)."""

    def __init__(self, height_q: float | None) -> None:
        self.codec = None if height_q is None else HeightCodec("lossless", height_q)

    def body(self, classes: bytes, z: np.ndarray | None, mask: np.ndarray) -> bytes:
        if self.codec is None or z is None:
            return classes
        return _LEN.pack(len(classes)) + classes + self.codec.encode(np.where(mask, z, np.nan))

    def split(self, body: bytes) -> tuple[bytes, np.ndarray | None]:
        if self.codec is None:
            return body, None
        (n,) = _LEN.unpack_from(body)
        return body[_LEN.size:_LEN.size + n], HeightCodec.decode(body[_LEN.size + n:])


class RawRover(RoverEnd):
    """A rover's end of ``raw`` on the star."""

    def __init__(self, k: int, rover: Any, starts: list[Cell], *, budget: int | None,
                 height_q: float | None = None) -> None:
        super().__init__(k, rover, starts)
        self.budget, self.layer = budget, _Heights(height_q)
        self.delivered_cells = np.zeros(self.shape, dtype=bool)  # own cells the base has
        self._held = np.full(self.shape, UNKNOWN, dtype=np.uint8)
        self._held_z = np.full(self.shape, np.nan, dtype=np.float32)
        self._z_version = 0
        self._sent: dict[int, np.ndarray] = {}  # round -> the cells of its uplink in flight

    def held(self) -> np.ndarray:
        return self._held

    def heights(self) -> np.ndarray | None:
        return None if self.layer.codec is None else self._held_z

    def heights_version(self) -> int:
        return self._z_version

    def uplink(self, round_no: int) -> Outgoing | None:
        r = self.rover
        pending = (r.local != UNKNOWN) & ~self.delivered_cells

        def make(mask: np.ndarray) -> bytes:
            classes = encode_map(np.where(mask, r.local, UNKNOWN).astype(np.uint8))
            return pack_up("", r.pos, r.target, self.layer.body(classes, r.heights, mask & (r.local != UNKNOWN)))

        payload, self._sent[round_no] = cut_to_budget(make, r.obs_step, pending, self.budget)
        return Outgoing(payload, "cells")

    def delivered(self, round_no: int, ok: bool) -> None:
        sent = self._sent.pop(round_no, None)
        if ok and sent is not None:
            self.delivered_cells |= sent

    def receive(self, payload: bytes) -> bool:
        _, _, reports, body = unpack_down(payload)
        classes, z = self.layer.split(body)
        try:
            m = decode_map(classes, reference=self._held, expected_shape=self.shape)
        except RejectedUpdate:  # coded against a map this rover no longer holds
            return False
        if z is not None and np.isfinite(z).any():
            self._held_z = np.where(np.isfinite(z), z, self._held_z).astype(np.float32)
            self._z_version += 1
        self._held = m
        self.reports.update(reports)
        return True


class RawBase(BaseEnd):
    """The base station's end of ``raw`` on the star."""

    def __init__(self, shape: tuple[int, int], starts: list[Cell], *, budget: int | None,
                 height_q: float | None = None, journal: Journal | None = None) -> None:
        super().__init__(shape, starts)
        self.budget, self.layer = budget, _Heights(height_q)
        self.journal = journal if journal is not None else Journal()
        empty = np.full(shape, UNKNOWN, dtype=np.uint8)
        self.base = empty.copy()
        self.base_z = np.full(shape, np.nan, dtype=np.float32)
        self.base_stamp = np.full(shape, -1, dtype=np.int64)  # round each base cell was merged
        self.acked = [empty.copy() for _ in range(self.n)]  # what the base knows each rover holds
        self._sending: dict[tuple[int, int], np.ndarray] = {}  # (rover, round) -> the map a downlink gives it

    def global_map(self) -> np.ndarray:
        return self.base

    def global_heights(self) -> np.ndarray | None:
        return None if self.layer.codec is None else self.base_z

    def receive(self, k: int, payload: bytes, round_no: int) -> bool:
        _, pos, target, body = unpack_up(payload)
        classes, z = self.layer.split(body)
        cells = decode_map(classes, expected_shape=self.shape)
        if z is not None:
            self.base_z = np.where(np.isfinite(z), z, self.base_z).astype(np.float32)
        self.journal.received.append((round_no, k, payload))
        new = (cells != UNKNOWN) & (self.base == UNKNOWN)
        self.base = np.where(cells != UNKNOWN, cells, self.base).astype(np.uint8)
        self.base_stamp[new] = round_no
        self.reports[k] = (pos, target)
        return True

    def downlinks(self, round_no: int) -> dict[int, Outgoing]:
        out = {}
        for k in range(self.n):
            ref = self.acked[k]  # always sent: even without new cells it carries the team's positions

            def make(mask: np.ndarray, ref: np.ndarray = ref) -> bytes:
                m = np.where(mask | (ref != UNKNOWN), self.base, UNKNOWN).astype(np.uint8)
                body = self.layer.body(encode_map(m, reference=ref), self.base_z, mask & np.isfinite(self.base_z))
                return pack_down("map", "", self.reports, body)

            candidates = self.lacking(k, self.base, ref)
            payload, sent = cut_to_budget(make, self.base_stamp, candidates, self.budget)
            self._sending[k, round_no] = np.where(sent | (ref != UNKNOWN), self.base, UNKNOWN).astype(np.uint8)
            out[k] = Outgoing(payload, "map")
        return out

    def delivered(self, k: int, round_no: int, ok: bool) -> None:
        sent = self._sending.pop((k, round_no), None)
        if ok and sent is not None:
            self.acked[k] = sent


class RawPeer(PeerEnd):
    """An agent's end of ``raw`` gossip on a peer topology."""

    def __init__(self, agent: int, rover: Any, shape: tuple[int, int], starts: list[Cell], *,
                 agents: tuple[int, ...], journal: Journal | None = None) -> None:
        super().__init__(agent, rover, shape, starts)
        self.journal = journal if journal is not None else Journal()
        self.hold = np.full(shape, UNKNOWN, dtype=np.uint8)  # cells received
        self.got = np.full(shape, -1, dtype=np.int64)  # step each was received
        self.has = {j: np.zeros(shape, dtype=bool) for j in agents}  # the cells it knows agent j holds
        self._sent: dict[tuple[int, int], np.ndarray] = {}  # (receiver, round) -> the cells of a message in flight

    def held(self) -> np.ndarray:
        return self.hold

    def shared(self) -> np.ndarray:
        """The cells its messages share (its belief: what it observed and what it received)."""
        return self.belief()

    def message(self, to: int, round_no: int, step: int, budget: int | None) -> Outgoing:
        belief = self.shared()
        r = self.rover
        stamps = self.got if r is None else np.where(r.local != UNKNOWN, r.obs_step, self.got)
        candidates = (belief != UNKNOWN) & ~self.has[to]
        reports = self.own_reports()

        def make(mask: np.ndarray) -> bytes:
            return pack_down("map", "", reports, encode_map(np.where(mask, belief, UNKNOWN).astype(np.uint8)))

        payload, self._sent[to, round_no] = cut_to_budget(make, stamps, candidates, budget)
        return Outgoing(payload, "cells")

    def receive(self, frm: int, payload: bytes, round_no: int, step: int) -> bool:
        _, _, reports, body = unpack_down(payload)
        cells = decode_map(body, expected_shape=self.shape)
        carried = cells != UNKNOWN
        new = carried & (self.hold == UNKNOWN)
        self.hold[new] = cells[new]  # observations are truth: they never conflict
        self.got[new] = step
        self.has[frm] |= carried  # the sender holds what it sent
        self.heard(reports)
        self.journal.deliveries.append((round_no, frm, self.agent, np.flatnonzero(carried)))
        return True

    def delivered(self, to: int, round_no: int, ok: bool) -> None:
        sent = self._sent.pop((to, round_no), None)
        if ok and sent is not None:
            self.has[to] |= sent


class CentralRover(RoverEnd):
    """A rover of the ``central`` oracle: it holds what the whole ``team`` observed, now."""

    def __init__(self, k: int, rover: Any, starts: list[Cell], *, team: list) -> None:
        super().__init__(k, rover, starts)
        self.oracle = CentralBase(self.shape, starts, team=team)

    def held(self) -> np.ndarray:
        return self.oracle.global_map()

    def heights(self) -> np.ndarray | None:
        return self.oracle.global_heights()

    def heights_version(self) -> int:
        return sum(int(np.isfinite(r.heights).sum()) for r in self.oracle.team if r.heights is not None)

    def others(self) -> list[Cell]:
        out = []
        for j, r in enumerate(self.oracle.team):
            if j != self.k:
                out.append(r.pos)
                if r.target is not None:
                    out.append(r.target)
        return out


class CentralBase(BaseEnd):
    """The ``central`` oracle's base: every observation of the ``team``, now."""

    def __init__(self, shape: tuple[int, int], starts: list[Cell], *, team: list) -> None:
        super().__init__(shape, starts)
        self.team = team
        self._map: tuple[tuple[tuple[int, int], ...], np.ndarray] | None = None

    def global_map(self) -> np.ndarray:
        """Every rover's observations laid over each other in team order (read-only).

        Every rover asks for it at every step, and building it reads every rover's whole
        map, so it is kept: after writes (``Rover.writes``) only the boxes they wrote are
        laid again, into a copy (a map handed out never changes)."""
        key = tuple((id(r.local), len(r.writes)) for r in self.team)  # a rover rebuilt has a new map
        if self._map is not None and self._map[0] == key:
            return self._map[1]
        if self._map is not None and all(a[0] == b[0] and a[1] <= b[1] for a, b in zip(self._map[0], key)):
            boxes = [box for (_, seen), r in zip(self._map[0], self.team) for box in r.writes[seen:]]
        else:
            boxes = [None]
        if None in boxes:
            boxes = [(0, self.shape[0], 0, self.shape[1])]
            out = np.empty(self.shape, dtype=np.uint8)
        else:
            assert self._map is not None
            out = self._map[1].copy()
        for r0, r1, c0, c1 in boxes:
            part = np.full((r1 - r0, c1 - c0), UNKNOWN, dtype=np.uint8)
            for r in self.team:
                local = r.local[r0:r1, c0:c1]
                part = np.where(local != UNKNOWN, local, part)
            out[r0:r1, c0:c1] = part
        out.flags.writeable = False
        self._map = (key, out)
        return out

    def global_heights(self) -> np.ndarray | None:
        zs = [r.heights for r in self.team if r.heights is not None]
        if not zs:
            return None
        out = np.full(self.shape, np.nan, dtype=np.float32)
        for z in zs:
            out = np.where(np.isfinite(z), z, out)
        return out

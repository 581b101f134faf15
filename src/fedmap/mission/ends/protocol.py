"""What every strategy's ends share: the message headers, the three kinds of endpoint, and
the journal the ends write what they did to.

A strategy is a set of **endpoints** (:mod:`fedmap.mission.ends.raw`, ``predictive``, ``model``,
``gossip``): a :class:`RoverEnd` per rover and a :class:`BaseEnd` on the star, or a
:class:`PeerEnd` per agent on a peer topology. Each holds only its own end's state and
talks to the other ends only in bytes: a sender offers a payload (:class:`Outgoing`), the
receiver takes the payload and answers whether it could use it, and the sender learns that
answer (``delivered(ok)``: the link-level acknowledgement, one bit, not counted in the
bytes). Nothing else crosses between two ends; the byte layout of every message is in
``docs/protocol.md``.

Every sharing payload starts with a small header (real bytes, counted): the version of the
model an update is relative to, the sender's position and target (uplink, 16 bytes), or
what the body is, the model version a broadcast is relative to and every rover's last
reported position and target (downlink, 10 + 9 per rover bytes); rovers coordinate their
targets with it.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from fedmap._util import cpu_cores
from fedmap.maps.grid import UNKNOWN
from fedmap.mission.world.sensing import disk_offsets

Cell = tuple[int, int]
Reports = dict[int, tuple[Cell, Cell | None]]
_UP = struct.Struct("<8shhhh")  # model version (8 bytes), row, col, target row, target col
_DOWN = struct.Struct("<B8sB")  # kind, reference model version (8 bytes), rovers reported
_REPORT = struct.Struct("<Bhhhh")  # rover, row, col, target row, target col
KINDS = ("map", "broadcast", "keyframe", "chain", "chunk")
#: Bytes of the uplink header (before the payload proper).
UP_HEADER = _UP.size
#: Bytes of the smallest downlink header (no rover reported).
DOWN_HEADER = _DOWN.size
#: Torch threads while a mission trains or renders. The models are small and trained one
#: after another; on a shared 2-core machine two OpenMP threads per process spin against
#: other processes and made one GridNet fit 20x slower than one thread (measured: 17-23 s
#: vs 0.8 s for 20 epochs at 128² under load).
TORCH_THREADS = 1


@contextmanager
def torch_threads(n: int = TORCH_THREADS) -> Iterator[None]:
    """Run the block with ``n`` torch threads, then restore the previous setting."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def side_by_side(calls: list[Callable[[], None]]) -> None:
    """Run ``calls`` (each touching its own rover's state only) on up to one thread per core,
    every one on one torch thread: each computes what it would alone, bit for bit, whatever
    the number of cores (torch releases the GIL in its kernels). A call's error is raised."""
    cores = cpu_cores()
    with torch_threads():  # the calls' own torch_threads() then keep 1: nobody switches it back meanwhile
        if len(calls) < 2 or cores < 2:
            for call in calls:
                call()
            return
        with ThreadPoolExecutor(min(cores, len(calls))) as pool:
            for future in [pool.submit(call) for call in calls]:
                future.result()


def v8(version: str) -> bytes:
    """A model version (hex) as its 8 bytes on the link ("" for none: zeros)."""
    return bytes.fromhex(version) if version else bytes(8)


def unv8(raw: bytes) -> str:
    return "" if raw == bytes(8) else raw.hex()


def pack_up(version: str, pos: Cell, target: Cell | None, body: bytes) -> bytes:
    """Uplink: the version of the model the update is relative to ("" for none), position, target."""
    t = target if target is not None else (-1, -1)
    return _UP.pack(v8(version), pos[0], pos[1], t[0], t[1]) + body


def unpack_up(payload: bytes) -> tuple[str, Cell, Cell | None, bytes]:
    v, r, c, tr, tc = _UP.unpack_from(payload)
    return unv8(v), (r, c), (None if tr < 0 else (tr, tc)), payload[_UP.size:]


def pack_down(kind: str, reference: str, reports: Reports, body: bytes) -> bytes:
    """Downlink: what the body is (map, broadcast, keyframe), the model version a broadcast is
    relative to, and every rover's last reported position and target."""
    head = _DOWN.pack(KINDS.index(kind), v8(reference), len(reports))
    for k, (p, t) in sorted(reports.items()):
        t = t if t is not None else (-1, -1)
        head += _REPORT.pack(k, p[0], p[1], t[0], t[1])
    return head + body


def unpack_down(payload: bytes) -> tuple[str, str, Reports, bytes]:
    kind, ref, n = _DOWN.unpack_from(payload)
    reports, off = {}, _DOWN.size
    for _ in range(n):
        k, r, c, tr, tc = _REPORT.unpack_from(payload, off)
        reports[k] = ((r, c), None if tr < 0 else (tr, tc))
        off += _REPORT.size
    return KINDS[kind], unv8(ref), reports, payload[off:]


@dataclass(frozen=True)
class DroppedUpdate:
    """A model update that did not make it into the base's model: rejected by its rover's
    step (not sent), or delivered but not aggregated (e.g. stale). Its round, its rover
    (-1: the round's every update, when the base could use none) and why."""

    round: int
    rover: int
    why: str

    def to_dict(self) -> dict:
        return {"round": self.round, "rover": self.rover, "why": self.why}


@dataclass(frozen=True)
class Outgoing:
    """A payload an end offers to the link (``payload=None``: nothing fits the budget), and
    what it is (the ledger's ``kind``)."""

    payload: bytes | None
    kind: str


@dataclass
class Journal:
    """What the ends of one strategy did, for the record (never read by an end). In one
    process every end of a run writes to the same journal, in the order things happened."""

    #: model updates that did not make it into a model (None: a strategy without updates)
    dropped: list[DroppedUpdate] | None = None
    lags: list[dict] | None = None  #: model strategies: at every sync, how many models behind each rover is
    losses: list[dict] = field(default_factory=list)  #: per local fit: round, rover, loss
    trained_cells: list[dict] = field(default_factory=list)  #: per local fit: round, rover, cells trained on
    received: list[tuple[int, int, bytes]] = field(default_factory=list)  #: raw: (round, rover, payload) merged
    #: gossip of cells: every delivered message, (round, sender, receiver, flat indices of its cells)
    deliveries: list[tuple[int, int, int, np.ndarray]] = field(default_factory=list)
    rejected: int = 0  #: peer messages a receiver could not use (relative to a model it does not hold)


class RoverEnd:
    """A rover's end of a strategy: ``none`` (it shares nothing; its belief is its own map).

    ``rover`` is its own rover (:class:`~fedmap.mission.sim.Rover`: position, target,
    trail, local map, heights), ``starts`` every rover's start cell (known to every end
    from the mission's config). Subclasses override the link hooks.
    """

    def __init__(self, k: int, rover: Any, starts: list[Cell]) -> None:
        self.k, self.rover = k, rover
        self.shape: tuple[int, int] = rover.local.shape
        self.reports: Reports = {j: (s, None) for j, s in enumerate(starts)}

    # -- what it holds
    def held(self) -> np.ndarray:
        """The latest global map it holds (classes)."""
        return np.full(self.shape, UNKNOWN, dtype=np.uint8)

    def belief(self) -> np.ndarray:
        """Its own observations laid over the global map it holds."""
        local = self.rover.local
        return np.where(local != UNKNOWN, local, self.held()).astype(np.uint8)

    def others(self) -> list[Cell]:
        """The other rovers' positions and targets as it last heard of them."""
        out = []
        for j, (p, t) in self.reports.items():
            if j != self.k:
                out.append(p)
                if t is not None:
                    out.append(t)
        return out

    def heights(self) -> np.ndarray | None:
        """The heights it holds from others (metres, NaN elsewhere), or None when the
        strategy shares no elevation."""
        return None

    def heights_version(self) -> int:
        """A counter that changes whenever :meth:`heights` does."""
        return 0

    # -- the link
    def at_sync(self, round_no: int) -> None:
        """Called at every sync, before the uplinks of round ``round_no``."""

    def prepare(self, round_no: int) -> Callable[[], None] | None:
        """The heavy part of this round's :meth:`uplink` (a model's training) as a call that
        touches this end alone, so a sync can run the rovers' calls side by side before it
        asks them for their uplinks in order; None (the default): nothing worth it."""
        return None

    def uplink(self, round_no: int) -> Outgoing | None:
        """Its uplink of this round; None when it has none (e.g. its update was rejected)."""
        return None

    def delivered(self, round_no: int, ok: bool) -> None:
        """The acknowledgement of its uplink of round ``round_no``: it arrived and the base
        used it (``ok``), or it was lost (not ``ok``)."""

    def receive(self, payload: bytes) -> bool:
        """Apply a delivered downlink; False when it could not be used (stale)."""
        return False


class BaseEnd:
    """The base station's end of a strategy: ``none`` (it receives nothing)."""

    def __init__(self, shape: tuple[int, int], starts: list[Cell]) -> None:
        self.shape = shape
        self.n = len(starts)
        self.reports: Reports = {j: (s, None) for j, s in enumerate(starts)}

    def global_map(self) -> np.ndarray:
        """The base station's global map (classes)."""
        return np.full(self.shape, UNKNOWN, dtype=np.uint8)

    def global_heights(self) -> np.ndarray | None:
        """The heights it holds (NaN elsewhere), or None without them."""
        return None

    def receive(self, k: int, payload: bytes, round_no: int) -> bool:
        """Take rover ``k``'s delivered uplink; False when it could not be used."""
        return False

    def downlinks(self, round_no: int) -> dict[int, Outgoing]:
        """Its round, once the uplinks that arrived are in: a downlink per rover it answers."""
        return {}

    def withheld(self, k: int) -> np.ndarray | None:
        """Cells of the global map a downlink to rover ``k`` leaves out (None: none, it sends
        every cell the rover lacks; a base of maps without a shared frame leaves out the rover's own)."""
        return None

    def lacking(self, k: int, base: np.ndarray, held: np.ndarray) -> np.ndarray:
        """Boolean map of the cells of the global map ``base`` a downlink to rover ``k``, which
        holds ``held``, may carry: known in ``base``, unknown in ``held``, not :meth:`withheld`."""
        out = (base != UNKNOWN) & (held == UNKNOWN)
        w = self.withheld(k)
        return out if w is None else out & ~w

    def delivered(self, k: int, round_no: int, ok: bool) -> None:
        """The acknowledgement of its downlink of round ``round_no`` to rover ``k``."""


class PeerEnd:
    """An agent's end of a peer strategy (a rover, or the lander: ``rover`` None).

    Agents are the rovers ``0..n-1`` and the lander (:data:`~fedmap.mission.network.link.BASE`).
    """

    def __init__(self, agent: int, rover: Any, shape: tuple[int, int], starts: list[Cell]) -> None:
        self.agent, self.rover, self.shape = agent, rover, shape
        self.reports: Reports = {j: (s, None) for j, s in enumerate(starts)}
        self.degree = 0  #: how many agents it exchanges with this round

    def held(self) -> np.ndarray:
        raise NotImplementedError

    def belief(self) -> np.ndarray:
        held = self.held()
        if self.rover is None:
            return held
        return np.where(self.rover.local != UNKNOWN, self.rover.local, held).astype(np.uint8)

    others = RoverEnd.others
    heights = RoverEnd.heights
    heights_version = RoverEnd.heights_version

    @property
    def k(self) -> int:
        return self.agent

    def own_reports(self) -> Reports:
        """Every rover's position and target as it knows them (its own, now)."""
        out = dict(self.reports)
        if self.rover is not None:
            out[self.agent] = (self.rover.pos, self.rover.target)
        return out

    def heard(self, reports: Reports) -> None:
        self.reports.update({j: v for j, v in reports.items() if j != self.agent})

    def at_sync(self, round_no: int) -> None:
        """Called at every sync, before any message of round ``round_no``."""

    def links(self, round_no: int, degree: int) -> None:
        """The number of agents it exchanges with this round, before any message."""
        self.degree = degree

    def message(self, to: int, round_no: int, step: int, budget: int | None) -> Outgoing:
        raise NotImplementedError

    def receive(self, frm: int, payload: bytes, round_no: int, step: int) -> bool:
        raise NotImplementedError

    def delivered(self, to: int, round_no: int, ok: bool) -> None:
        """The acknowledgement of its message of round ``round_no`` to ``to``."""

    def close_round(self, round_no: int) -> None:
        """Close round ``round_no`` once its messages have arrived."""


def largest_fitting(make, longest: int, budget: int | None) -> tuple[int | None, Any]:
    """The largest ``n`` in ``0..longest`` whose ``made = make(n)`` fits ``budget`` (``made``
    is a payload or a tuple that starts with one; sizes grow with ``n``), by binary search
    after trying ``longest``: ``(n, made)``, or ``(None, None)`` when even ``n = 0`` does not fit."""
    def size(made) -> int:
        return len(made[0] if isinstance(made, tuple) else made)

    full = make(longest)
    if budget is None or size(full) <= budget:
        return longest, full
    lo, hi = 0, longest - 1
    best: tuple[int | None, Any] = (None, None)
    while lo <= hi:
        mid = (lo + hi) // 2
        made = make(mid)
        if size(made) <= budget:
            best, lo = (mid, made), mid + 1
        else:
            hi = mid - 1
    return best


def cut_to_budget(make, stamps: np.ndarray, candidates: np.ndarray, budget: int | None) -> tuple[bytes | None,
                                                                                                  np.ndarray]:
    """The payload of the most candidate cells that fits: every candidate cell stamped at or
    after a cut-off, the earliest cut-off that fits (:func:`largest_fitting`). ``make(mask)``
    builds the payload of a cell mask. Returns ``(payload or None, mask sent)``."""
    cuts = np.unique(stamps[candidates])  # ascending: an earlier cut sends more

    def at(m: int) -> tuple[bytes, np.ndarray]:  # m + 1 cut-offs, the newest first
        mask = candidates if m == len(cuts) - 1 else candidates & (stamps >= cuts[len(cuts) - 1 - m])
        return make(mask), mask

    _, made = largest_fitting(at, len(cuts) - 1, budget)
    return (None, np.zeros_like(candidates)) if made is None else made


def cover(positions, shape: tuple[int, int], radius: float) -> np.ndarray:
    """Boolean ``shape`` map of every cell within ``radius`` of any of ``positions`` (the
    footprints of a trail without line of sight: the cells a trail may have observed)."""
    out = np.zeros(shape, dtype=bool)
    p = np.asarray(list(positions), dtype=np.int64).reshape(-1, 2)
    if p.size:
        off = disk_offsets(radius)
        rr = (p[:, None, 0] + off[None, :, 0]).ravel()
        cc = (p[:, None, 1] + off[None, :, 1]).ravel()
        ok = (rr >= 0) & (rr < shape[0]) & (cc >= 0) & (cc < shape[1])
        out[rr[ok], cc[ok]] = True
    return out

"""A rover node on Zenoh (``fedmap node rover``): one process, its node kept in memory.

It declares its queryable (``fedmap/<team>/rover/<k>/order``) and its liveliness token,
and answers each of the base's orders with its report
(:meth:`~fedmap.mission.network.remote.ProcessRover.answer`: the same frames and checks as
on Flower). What it logs of every step goes to its own log, ``log/`` of its state folder
(:func:`~fedmap.flower.mission.task.log_dir`); the mission is scored from the logs. It asks
the base for the mission an order names (``fedmap/<team>/base/mission``) the first time it
meets it.

A damaged order is answered with an error reply ``{"corrupt": true}`` (the base sends it
again); an order that carries on from a step it holds no state for (its process was started
again) with ``{"lost": true}``: the base sends the order again with every order it sent
this rover (the query's attachment) and the node is rebuilt from them, bit for bit.
"""

from __future__ import annotations

import json
import queue
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fedmap.errors import FedmapError
from fedmap.flower.mission.task import damaged, log_dir, parse_mission_fault
from fedmap.mission.network.nodelog import write_log
from fedmap.mission.network.remote import CorruptMessage, LostState, Order, ProcessRover, unpack_history
from fedmap.mission.scoring import mission_from_text
from fedmap.mission.sim import Mission
from fedmap.mission.world.feed import Feed
from fedmap.zenohnet.session import alive_key, done_key, mission_key, order_key

#: Seconds a rover waits for the base to say what a mission is before it gives up on the order.
MISSION_WAIT = 30.0


class RoverService:
    """Rover ``k`` of team ``team`` on the open Zenoh ``session``: its nodes (one per mission
    and strategy), its log in ``state``/log. ``fault``: ``corrupt@STEP`` damages its report
    of the order to STEP once (tests). ``feed``: its observations come from its own mapping
    software; ``bridge``: and it lives in the robot's ROS 2 graph
    (:class:`~fedmap.zenohnet.ros2.Ros2Bridge`: its feed, and the team map it publishes)."""

    def __init__(self, session: Any, team: str, k: int, state: Path, *, feed: Feed | None = None,
                 fault: str | None = None, bridge: Any = None, say: Callable[[str], None] = print) -> None:
        self.session, self.team, self.k, self.state = session, team, k, Path(state)
        self.bridge, self.say = bridge, say
        self.feed = bridge.feed if bridge is not None else feed
        self.fault = parse_mission_fault(fault)[1] if fault else None
        self.faulted: set[tuple[str, str]] = set()
        self.missions: dict[str, Mission] = {}
        self.nodes: dict[tuple[str, str], ProcessRover] = {}
        self.answered = 0
        self.inbox: queue.Queue = queue.Queue()
        self.done = False
        log_dir(self.state).mkdir(parents=True, exist_ok=True)
        self.queryable = session.declare_queryable(f"fedmap/{team}/rover/{k}/*", self.inbox.put)
        self.token = session.liveliness().declare_token(alive_key(team, f"rover/{k}"))

    def _mission(self, mission_id: str) -> Mission:
        if mission_id not in self.missions:
            t_end = time.monotonic() + MISSION_WAIT
            while True:
                for reply in self.session.get(mission_key(self.team), payload=mission_id.encode(), timeout=10.0):
                    if reply.ok is not None:
                        self.missions[mission_id] = mission = mission_from_text(reply.ok.payload.to_string(), frames=1)
                        if self.bridge is not None:
                            self.bridge.on_mission(mission)
                        return mission
                    raise FedmapError(f"rover {self.k}: the base station has no mission {mission_id!r}: "
                                      f"{reply.err.payload.to_string()}")
                if time.monotonic() > t_end:
                    raise FedmapError(f"rover {self.k}: no base station of team {self.team} answered for mission "
                                      f"{mission_id!r} within {MISSION_WAIT:g} s")
                time.sleep(0.2)
        return self.missions[mission_id]

    def answer(self, raw: bytes, history: bytes | None) -> bytes:
        """The report to the order ``raw`` (``history``: every order before it, to rebuild a
        node that lost its state); :class:`CorruptMessage`, :class:`LostState` or one line."""
        order = Order.from_bytes(raw)
        if order.rover != self.k:
            raise FedmapError(f"an order for rover {order.rover} reached rover {self.k}")
        key = (order.mission, order.strategy)
        node = self.nodes.get(key)
        if history is not None:
            node = ProcessRover.rebuild(self._mission(order.mission), order.strategy, self.k,
                                        unpack_history(history), feed=self.feed)
        elif node is None:
            node = ProcessRover(self._mission(order.mission), order.strategy, self.k, feed=self.feed)
        node.on_belief = None if self.bridge is None else self.bridge.on_belief
        self.nodes[key] = node
        report = node.answer(raw)
        if self.bridge is not None:
            self.bridge.on_traffic(len(raw), len(report))
        for entry in node.log:  # its own log (never sent)
            write_log(log_dir(self.state), entry)
        node.log = []
        if order.finish:
            del self.nodes[key]
        if self.fault is not None and order.step == self.fault and key not in self.faulted:
            self.faulted.add(key)  # a test's fault: this report damaged on the way, once
            report = damaged(report)
        return report

    def handle(self, query: Any) -> None:
        """One query: an order (reply: its report, or an error), or the mission's end."""
        try:
            if str(query.key_expr) == done_key(self.team, self.k):
                self.done = True
                query.reply(query.key_expr, b"")
                return
            raw = query.payload.to_bytes() if query.payload is not None else b""
            history = query.attachment.to_bytes() if query.attachment is not None else None
            try:
                report = self.answer(raw, history)
            except CorruptMessage as e:
                query.reply_err(json.dumps({"reason": str(e), "corrupt": True}))
                return
            except LostState as e:
                query.reply_err(json.dumps({"reason": str(e), "lost": True}))
                return
            except FedmapError as e:
                self.say(f"rover {self.k}: {e}")
                query.reply_err(json.dumps({"reason": str(e)}))
                return
            self.answered += 1
            query.reply(query.key_expr, report)
        finally:
            query.drop()  # the reply is final: the base's query completes now

    def serve(self, *, until_done: bool = True, poll: float = 0.5) -> None:
        """Answer queries until the mission is over (``until_done``) or the process is stopped."""
        while not (until_done and self.done):
            try:
                query = self.inbox.get(timeout=poll)
            except queue.Empty:
                continue
            self.handle(query)

    def close(self) -> None:
        self.token.undeclare()
        self.queryable.undeclare()


def serve_rover(session: Any, team: str, k: int, state: Path, **kw: Any) -> int:
    """Rover ``k`` answers until the mission is over; the orders it answered."""
    svc = RoverService(session, team, k, state, **kw)
    try:
        svc.serve()
    finally:
        svc.close()
    return svc.answered


__all__ = ["MISSION_WAIT", "RoverService", "order_key", "serve_rover"]

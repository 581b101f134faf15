"""The base station on Zenoh (``fedmap node base``): the mission clock over rover nodes.

The same base as on Flower (:class:`~fedmap.mission.network.remote.ProcessBase` and
:func:`~fedmap.mission.network.remote.rounds`: its end, the link model and the in-process
transport's rounds over what the rovers report), with each order a Zenoh query to its rover
(:mod:`fedmap.zenohnet.rover`) and the report its reply. All of a round's queries leave
at once. Faults, each a line of the run's ``faults`` and of the base's log:

* a damaged order or report (its check fails): the order goes again;
* a rover that vanishes (its liveliness token goes) or does not answer: the base waits for
  it to come back, for up to ``rejoin`` seconds, and sends the order again;
* a rover that lost its state (its process was started again): the order goes again with
  every order it was sent before, to rebuild it from;
* a base station killed: started again with ``resume``, it replays its journal
  (:class:`~fedmap.flower.mission.task.BaseJournal`) and carries on; the rovers, which kept
  running, answer an order they already answered with the same report.
"""

from __future__ import annotations

import json
import queue
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fedmap.errors import FedmapError
from fedmap.flower.checkpoint import run_dir
from fedmap.flower.mission.task import BaseJournal, JournaledSend, base_dir, base_log, lost_state
from fedmap.mission.network.nodelog import write_log
from fedmap.mission.network.remote import (
    CorruptMessage,
    ProcessBase,
    Report,
    check_deployable,
    deployable_strategies,
    rounds,
)
from fedmap.mission.scoring import mission_from_text, write_run
from fedmap.zenohnet.session import alive_key, done_key, mission_key, order_key

#: Times an order is sent again after a damaged order or report, per rover and round, before the run fails.
RESENDS = 3


class ZenohTeam:
    """The rovers of team ``team`` as the base reaches them over ``session``: who is alive,
    and the sending of orders. ``out``: the run's outputs (the base's log goes to
    ``<out>.run/``). ``watch`` is called every ``poll`` s while the base waits (a launcher's
    check on its rover processes)."""

    def __init__(self, session: Any, team: str, members: int, out: Path, *, deadline: float = 600.0,
                 rejoin: float = 300.0, poll: float = 0.5, watch: Callable[[], None] | None = None) -> None:
        from zenoh.handlers import Callback

        self.session, self.team, self.members, self.out = session, team, members, Path(out)
        self.deadline, self.rejoin, self.poll, self.watch = deadline, rejoin, poll, watch
        self.faults: list[dict] = []
        self.alive: set[int] = set()
        self._lock = threading.Lock()
        self._changed = threading.Event()
        self._callback = Callback
        self.missions: dict[str, str] = {}  # mission id -> its TOML (what rovers ask for)
        self.sub = session.liveliness().declare_subscriber(alive_key(team, "rover/*"), self._on_alive, history=True)
        self.served = session.declare_queryable(mission_key(team), self._on_mission)
        self.token = session.liveliness().declare_token(alive_key(team, "base"))

    def _on_alive(self, sample: Any) -> None:
        import zenoh

        try:
            k = int(str(sample.key_expr).rsplit("/", 1)[1])
        except ValueError:
            return
        with self._lock:
            (self.alive.add if sample.kind == zenoh.SampleKind.PUT else self.alive.discard)(k)
        self._changed.set()

    def _on_mission(self, query: Any) -> None:
        try:
            want = query.payload.to_string() if query.payload is not None else ""
            text = self.missions.get(want)
            if text is None:
                query.reply_err(f"no mission {want!r} here")
            else:
                query.reply(query.key_expr, text)
        finally:
            query.drop()

    def say(self, level: str, line: str) -> None:
        base_log(self.out, level, line)

    def _until_alive(self, rovers: set[int], t_end: float, fail: Callable[[list[int]], str]) -> None:
        """Until every rover of ``rovers`` is alive; ``fail(missing)`` is the line once the
        monotonic clock passes ``t_end``. The launcher's ``watch`` runs while it waits."""
        while True:
            with self._lock:
                missing = sorted(rovers - self.alive)
            if not missing:
                return
            left = t_end - time.monotonic()
            if left <= 0:
                raise FedmapError(fail(missing))
            if self.watch is not None:
                self.watch()
            self._changed.wait(min(left, self.poll))
            self._changed.clear()

    def _not_back(self, missing: list[int]) -> str:
        return f"rover {missing[0]} did not come back within {self.rejoin:g} s"

    def wait_for_rovers(self, timeout: float) -> None:
        """Until every rover of the team is alive; one line naming those that are not."""
        self._until_alive(set(range(self.members)), time.monotonic() + timeout,
                          lambda missing: f"rover(s) {missing} of team {self.team} did not come up within {timeout:g} "
                                          f"s ({self.members - len(missing)} of {self.members} did)")

    def note(self, strategy: str, what: str) -> None:
        """A fault of the base station itself (rover -1)."""
        self.fault(strategy, -1, what)

    def fault(self, strategy: str, k: int, what: str) -> None:
        self.faults.append({"strategy": strategy, "rover": k, "fault": what})
        self.say("WARNING", f"{strategy} rover {k}: {what}")

    def _ask(self, todo: dict[int, bytes], lost: dict[int, bytes]) -> dict[int, Any]:
        """Every order of ``todo`` to its rover at once; each rover's reply (None: none came:
        the query ended empty, or the rover vanished while it held it)."""
        inbox: queue.Queue = queue.Queue()
        for k, raw in todo.items():
            def got(reply: Any, k: int = k) -> None:
                inbox.put((k, reply))

            def ended(k: int = k) -> None:
                inbox.put((k, None))

            self.session.get(order_key(self.team, k), handler=self._callback(got, ended), payload=raw,
                             attachment=lost.get(k), timeout=self.deadline)
        replies: dict[int, Any] = {}
        waiting = set(todo)
        while waiting:
            try:
                k, reply = inbox.get(timeout=self.poll)
            except queue.Empty:
                if self.watch is not None:
                    self.watch()
                with self._lock:
                    vanished = waiting - self.alive
                for k in vanished:  # its process is gone: its query will not be answered
                    waiting.discard(k)
                    replies.setdefault(k, None)
                continue
            if k not in waiting:
                continue  # the end of a query the base already gave up on
            if reply is None:
                waiting.discard(k)
                replies.setdefault(k, None)
            else:
                replies[k] = reply
        return replies

    def send(self, strategy: str, orders: dict[int, bytes], history: dict[int, list[bytes]]) -> dict[int, bytes]:
        """Every order to its rover, every report back (the module's faults handled on the way)."""
        reports: dict[int, bytes] = {}
        todo = dict(orders)
        damaged: dict[int, int] = {}
        gone: dict[int, float] = {}  # rover -> when it first failed to answer
        lost: dict[int, bytes] = {}  # rover -> its order history, sent with its order until it answers
        while todo:
            again: dict[int, bytes] = {}
            for k, reply in self._ask(todo, lost).items():
                if reply is None:
                    if k not in gone:
                        gone[k] = time.monotonic()
                        self.fault(strategy, k, "did not answer; waiting for it to come back")
                    again[k] = todo[k]
                    continue
                if reply.ok is None:
                    try:
                        why = json.loads(reply.err.payload.to_string())
                    except ValueError:
                        why = {"reason": reply.err.payload.to_string()}
                    reason = str(why.get("reason", why))
                    if why.get("lost") and k not in lost:
                        lost[k], line = lost_state(history.get(k, []), reason)
                        again[k] = todo[k]
                        self.fault(strategy, k, line)
                        continue
                    if not why.get("corrupt"):
                        raise FedmapError(f"rover {k}: {reason}")
                    damaged[k] = damaged.get(k, 0) + 1
                    again[k] = todo[k]
                    self.fault(strategy, k, f"order damaged on the way ({reason}); sent again")
                else:
                    raw = reply.ok.payload.to_bytes()
                    try:
                        Report.from_bytes(raw)
                    except CorruptMessage as e:
                        damaged[k] = damaged.get(k, 0) + 1
                        again[k] = todo[k]
                        self.fault(strategy, k, f"report damaged on the way ({e}); order sent again")
                        continue
                    reports[k] = raw
                    if lost.pop(k, None) is not None:
                        self.fault(strategy, k, "rebuilt from its orders; it answered its order")
                    if k in gone:
                        self.fault(strategy, k, f"back after {time.monotonic() - gone.pop(k):.0f} s; it answered")
                if damaged.get(k, 0) > RESENDS:
                    raise FedmapError(f"rover {k}: every copy of the order or report was damaged ({damaged[k]})")
            for k in again:
                if k in gone:  # until it is alive again; one line once ``rejoin`` s have passed since it went
                    self._until_alive({k}, gone[k] + self.rejoin, self._not_back)
            todo = again
        return reports

    def finish(self) -> None:
        """Tell every rover the mission is over (each may stop)."""
        inbox: queue.Queue = queue.Queue()
        for k in range(self.members):
            self.session.get(done_key(self.team, k), handler=self._callback(lambda r: None, lambda: inbox.put(1)),
                             timeout=10.0)
        for _ in range(self.members):
            inbox.get(timeout=15.0)

    def close(self) -> None:
        for h in (self.token, self.served, self.sub):
            h.undeclare()


def run_base(team: ZenohTeam, mission_text: str, *, out: Path, strategies: tuple[str, ...] = (), frames: int = 60,
             resume: bool = False, step_seconds: float = 0.0, connect_timeout: float = 120.0,
             on_step: Callable[[str, int], None] | None = None) -> list[str]:
    """Every strategy's mission over ``team``, each logged by the base in ``<out>.run/base/``
    (the rovers log their own side), and the run's own files (:func:`~fedmap.mission.scoring.write_run`);
    with ``resume``, the rounds in the base's journal are replayed first. The strategies run."""
    t0 = time.perf_counter()
    out = Path(out)
    run_dir(out).mkdir(parents=True, exist_ok=True)
    mission = mission_from_text(mission_text, frames=frames)
    names = strategies or deployable_strategies(mission.config)[0]
    check_deployable(mission.config, names)
    journal = BaseJournal(out, mission_text, resume=resume)
    team.missions[journal.mission_id] = mission_text
    team.wait_for_rovers(connect_timeout)
    for name in names:
        t1 = time.perf_counter()
        team.say("INFO", f"mission {name} on {team.members} rovers")
        base = ProcessBase(mission, name, mission_id=journal.mission_id, pace=round(step_seconds * 1000))
        send = JournaledSend(journal, name, team, lambda line: team.say("INFO", line))
        for step in rounds(base, send):
            if on_step is not None:
                on_step(name, step)
        write_log(base_dir(out), base.record(time.perf_counter() - t1))
    write_run(run_dir(out), mission_text, names, time.perf_counter() - t0, team.faults, mission_id=journal.mission_id)
    return list(names)


__all__ = ["RESENDS", "ZenohTeam", "run_base"]

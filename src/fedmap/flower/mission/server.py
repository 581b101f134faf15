"""The base station of a mission on processes: a Flower ``ServerApp`` that runs the
mission clock (:class:`fedmap.mission.network.remote.ProcessBase`) over the rovers' SuperNodes.

First it asks every connected node which rover it is (a ``query`` message; the SuperNode's
node config ``partition-id``), then for each strategy it sends every rover its order of
each sync round (a ``train`` message carrying the order's bytes) and takes its report.
What crosses is fedmap's own frames (:mod:`fedmap.mission.network.remote`) as a ``uint8`` array
(:mod:`fedmap.flower.records`); the ledger counts the strategy's messages inside them, as
the simulator does. A report or order damaged on the way fails its check and the order
is sent again (the rover answers a repeated order with the same report), and so is an
order that goes unanswered far longer than the other rovers' took (lost on the link:
:func:`~fedmap.flower.polling.exchange` with ``resend``; the first report to either copy
is taken). A rover that lost
its state gets its order again with every order it was sent before, and rebuilds itself
from them (:meth:`~fedmap.mission.network.remote.ProcessRover.rebuild`). Each fault is a line of the
run's ``faults`` and of the log. At the end every rover gets a
``evaluate`` message (its SuperNode may stop). The base logs what it held and sent in
``<out>.run/base/``; the rovers' reports carry no scores (each rover logs its own side),
and the run is scored from the logs (:func:`fedmap.mission.scoring.score_folder`).
"""

from __future__ import annotations

import logging
import time
from logging import INFO, WARNING
from pathlib import Path

from flwr.app import ConfigRecord, Context, Message, MessageType, RecordDict
from flwr.serverapp import Grid, ServerApp
from flwr.supercore import log

from fedmap.errors import FedmapError
from fedmap.flower.checkpoint import run_dir
from fedmap.flower.mission.task import (
    BaseJournal,
    JournaledSend,
    MissionRun,
    base_dir,
    base_log,
    lost_state,
    mission_from_text,
    strategies_of,
)
from fedmap.flower.polling import exchange, quick_pulls
from fedmap.flower.records import from_record, to_record
from fedmap.flower.task import KEY_ROVER, parse_rover_nodes, write_status, wrong_key
from fedmap.mission.network.nodelog import write_log
from fedmap.mission.network.remote import CorruptMessage, ProcessBase, Report, check_deployable, rounds
from fedmap.mission.scoring import write_run

app = ServerApp()
quick_pulls()  # a round is a message per rover: Flower's 1 s first retry would be most of it


def say(out: Path, level: int, line: str) -> None:
    """One line in Flower's log and in the base station's own, ``<out>.run/base.log``."""
    log(level, "fedmap: %s", line)
    base_log(out, logging.getLevelName(level), line)

#: Times an order is sent again after a damaged order or report before the run fails.
RESENDS = 3
#: Seconds the base waits for a node to say which rover (and which process) it is.
ASK_WAIT = 10.0
#: Copies of an order that goes unanswered far longer than the others took (lost on the link).
#: One: a rover whose process was killed runs every copy queued for it when it comes back,
#: each a ClientApp process, before the order the base then sends it to rebuild itself.
ORDER_COPIES = 1


class _Team:
    """The rovers' nodes on the grid, and the sending of orders to them."""

    def __init__(self, grid: Grid, run: MissionRun, members: int) -> None:
        self.grid, self.run, self.members = grid, run, members
        self.faults: list[dict] = []
        self.boot_of: dict[int, str] = {}  # rover -> the rover process its node last said it runs
        self.key_rover = parse_rover_nodes(run.rover_nodes)  # node -> the rover its registered key is for
        self.refused: set[int] = set()  # nodes refused: their key is another rover's
        self.node_of = self._connect()

    def _connect(self) -> dict[int, int]:
        t_end = time.monotonic() + self.run.connect_timeout
        node_of: dict[int, int] = {}
        while len(node_of) < self.members and time.monotonic() < t_end:
            node_of.update(self._which(set(self.grid.get_node_ids()) - set(node_of.values())))
            if len(node_of) < self.members:
                time.sleep(0.5)
        missing = sorted(set(range(self.members)) - set(node_of))
        if missing:
            raise FedmapError(f"rover(s) {missing} did not connect within {self.run.connect_timeout:g} s "
                              f"({len(node_of)} of {self.members} did)")
        return node_of

    def _which(self, nodes: set[int], wait: float | None = None) -> dict[int, int]:
        """Ask ``nodes`` which rover each is: ``{rover: node}`` (a node that does not answer is
        left out). Each answer's process (node config ``boot``) is noted in :attr:`boot_of`."""
        nodes = set(nodes) - self.refused
        if not nodes:
            return {}
        msgs = [Message(RecordDict({"config": ConfigRecord({KEY_ROVER: self.key_rover.get(n, -1)})}), dst_node_id=n,
                        message_type=MessageType.QUERY) for n in sorted(nodes)]
        sent = {m.object_id: n for m, n in zip(msgs, sorted(nodes))}
        found: dict[int, int] = {}
        wait = min(self.run.deadline, 30.0) if wait is None else wait
        for reply in exchange(self.grid, msgs, wait):
            if reply.has_error():
                continue
            node = sent[reply.metadata.reply_to_message_id]
            if "config" not in reply.content.config_records:
                if "error" in reply.content.config_records:  # the rover refused to run as its key's number
                    self.refused.add(node)
                    self._fault("", -1, str(reply.content["error"]["reason"]))
                continue
            k = int(reply.content["config"]["rover"])  # type: ignore[arg-type]
            bound = self.key_rover.get(node)
            if bound is not None and bound != k:  # a rover's key is its number
                self.refused.add(node)
                self._fault("", k, wrong_key(node, bound, k))
                continue
            if not 0 <= k < self.members:
                raise FedmapError(f"a node says it is rover {k}; the mission's team is 0..{self.members - 1}")
            found[k] = node
            self.boot_of[k] = str(reply.content["config"].get("boot", ""))
        return found

    def _restarted(self, owing: dict[int, int]) -> set[int]:
        """The rovers of ``owing`` (``{rover: node}``, each holding an order) whose node now runs
        another rover process than when it last said: a rover killed and started again with
        its registered key is the same node, so the SuperLink never reports the order its
        old process took, and the base would wait for it until the round's deadline."""
        before = {k: self.boot_of.get(k, "") for k in owing}
        now = self._which(set(owing.values()), wait=ASK_WAIT)
        return {k for k, n in now.items() if owing.get(k) == n and before.get(k) and self.boot_of[k] != before[k]}

    def send(self, strategy: str, orders: dict[int, bytes], history: dict[int, list[bytes]]) -> dict[int, bytes]:
        """Every order to its rover, every report back. A damaged order or report: the order
        goes again. A rover that does not answer (its process died, its link is down): the
        order goes again, to its new node once it has come back, for up to ``rejoin`` s. A
        rover that lost its state: the order goes again with ``history[k]``, every order it
        was sent before, to rebuild it from."""
        reports: dict[int, bytes] = {}
        todo = dict(orders)
        damaged = 0
        gone: dict[int, float] = {}  # rover -> when it first failed to answer
        lost: dict[int, bytes] = {}  # rover -> its order history, sent with its order until it answers
        while todo:
            msgs = []
            for r, raw in todo.items():
                content = RecordDict({"order": to_record(raw), "config": ConfigRecord({"strategy": strategy})})
                if r in lost:
                    content["history"] = to_record(lost[r])
                msgs.append(Message(content, dst_node_id=self.node_of[r], message_type=MessageType.TRAIN))
            sent = {m.object_id: k for m, k in zip(msgs, todo)}
            again: dict[int, bytes] = {}
            wait = self.run.deadline if not gone else min(self.run.deadline, 10.0)
            answered: set[int] = set()
            restarted: set[int] = set()

            def overdue(ids: set[str]) -> set[str]:
                owing = {sent[i]: self.node_of[sent[i]] for i in ids if i in sent}
                back = self._restarted(owing)
                restarted.update(back)
                return {i for i in ids if sent.get(i) in back}

            t_sent = time.monotonic()

            def resent(copies: list[Message]) -> None:  # the rover answers a copy with the same report
                rover_of = {n: r for r, n in self.node_of.items()}
                for c in copies:
                    r = rover_of.get(c.metadata.dst_node_id)
                    if r is not None:
                        sent[c.object_id] = r
                        # what the base saw, no more: the order, its pull or the rover's process may be what was lost
                        self._fault(strategy, r, f"its order went unanswered for {time.monotonic() - t_sent:.0f} s, "
                                                 "far longer than the others' took; sent again, the first report "
                                                 "to either taken")

            for reply in exchange(self.grid, msgs, wait, overdue=overdue, resend=True, on_resend=resent,
                                  most=ORDER_COPIES):
                k = sent.get(reply.metadata.reply_to_message_id)
                if k is None or reply.has_error():
                    continue  # a Flower error: the node is gone, as if it had not answered
                answered.add(k)
                if "error" in reply.content.config_records:
                    why = str(reply.content["error"]["reason"])
                    if reply.content["error"].get("lost") and k not in lost:
                        lost[k], line = lost_state(history.get(k, []), why)
                        again[k] = todo[k]
                        self._fault(strategy, k, line)
                        continue
                    if not reply.content["error"].get("corrupt"):
                        raise FedmapError(f"rover {k}: {why}")
                    again[k] = todo[k]
                    damaged += 1
                    self._fault(strategy, k, f"order damaged on the way ({why}); sent again")
                    continue
                raw = from_record(reply.content.array_records.get("report"))
                try:
                    Report.from_bytes(raw)
                except CorruptMessage as e:
                    again[k] = todo[k]
                    damaged += 1
                    self._fault(strategy, k, f"report damaged on the way ({e}); order sent again")
                    continue
                reports[k] = raw
                if "config" in reply.content.config_records:
                    self.boot_of[k] = str(reply.content["config"].get("boot", ""))
                if lost.pop(k, None) is not None:
                    self._fault(strategy, k, "rebuilt from its orders; it answered its order")
                if k in gone:
                    self._fault(strategy, k, f"back after {time.monotonic() - gone.pop(k):.0f} s; its order sent again")
            for k in restarted - answered:
                answered.add(k)
                again[k] = todo[k]
                self._fault(strategy, k, "restarted while it held its order (its node now runs a new rover process); "
                                         "order sent again")
            if damaged > RESENDS * max(len(orders), 1):
                raise FedmapError(f"rover(s) {sorted(again)}: every copy of the order or report was damaged")
            for k in set(todo) - answered:
                if k not in gone:
                    gone[k] = time.monotonic()
                    self._fault(strategy, k, "did not answer; waiting for it to come back")
                elif time.monotonic() - gone[k] > self.run.rejoin:
                    raise FedmapError(f"rover {k} did not come back within {self.run.rejoin:g} s")
                again[k] = todo[k]
            if gone:  # a rover that came back has a new node: find it
                time.sleep(1.0)
                self.node_of.update(self._which(set(self.grid.get_node_ids()) - set(self.node_of.values())))
            todo = again
        return reports

    def note(self, strategy: str, what: str) -> None:
        """A fault of the base station itself (rover -1)."""
        self._fault(strategy, -1, what)

    def _fault(self, strategy: str, k: int, what: str) -> None:
        self.faults.append({"strategy": strategy, "rover": k, "fault": what})
        say(self.run.out, WARNING, f"{strategy} rover {k}: {what}")

    def finish(self) -> None:
        """Tell every rover the mission is over (its SuperNode may stop)."""
        msgs = [Message(RecordDict({"config": ConfigRecord({"done": True})}), dst_node_id=n,
                        message_type=MessageType.EVALUATE) for n in self.node_of.values()]
        exchange(self.grid, msgs, 60)


def run_mission_base(grid: Grid, run: MissionRun) -> None:
    """Every strategy's mission over the rovers on ``grid``, each logged by the base in
    ``<out>.run/base/`` (the rovers log their own side); with ``run.resume``, the rounds in
    the base's journal are replayed first (:class:`~fedmap.flower.mission.task.BaseJournal`)."""
    t0 = time.perf_counter()
    write_status(run.out, "running", message="loading the mission")
    mission = mission_from_text(run.mission, frames=run.frames)
    names = strategies_of(run, mission)
    check_deployable(mission.config, names)
    journal = BaseJournal(run.out, run.mission, resume=run.resume)
    c = mission.config
    team = _Team(grid, run, c.rovers + c.helicopters)
    for name in names:
        t1 = time.perf_counter()
        say(run.out, INFO, f"mission {name} on {team.members} rovers")
        base = ProcessBase(mission, name, mission_id=journal.mission_id, pace=round(run.step_seconds * 1000))
        send = JournaledSend(journal, name, team, lambda line: say(run.out, INFO, line))
        for step in rounds(base, send):
            write_status(run.out, "running", strategy=name, step=step, steps=c.steps)
        write_log(base_dir(run.out), base.record(time.perf_counter() - t1))
    team.finish()
    write_run(run_dir(run.out), run.mission, names, time.perf_counter() - t0, team.faults,
              mission_id=journal.mission_id)


@app.main()
def main(grid: Grid, context: Context) -> None:
    run = MissionRun.from_run_config(dict(context.run_config))
    try:
        run_mission_base(grid, run)
    except Exception as e:  # the command that started the base waits on this file: never leave it "running"
        msg = str(e) if isinstance(e, FedmapError) else f"{type(e).__name__}: {e}".splitlines()[0]
        write_status(run.out, "failed", message=msg)
        say(run.out, INFO, f"error: {msg}")
        raise
    write_status(run.out, "done", message="mission over")

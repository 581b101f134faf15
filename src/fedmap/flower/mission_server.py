"""The base station of a mission on processes: a Flower ``ServerApp`` that runs the
mission clock (:class:`fedmap.mission.remote.BaseNode`) over the rovers' SuperNodes.

First it asks every connected node which rover it is (a ``query`` message; the SuperNode's
node config ``partition-id``), then for each strategy it sends every rover its order of
each sync round (a ``train`` message carrying the order's bytes) and takes its report.
What crosses is fedmap's own frames (:mod:`fedmap.mission.remote`) as a ``uint8`` array
(:mod:`fedmap.flower.records`); the ledger counts the strategy's messages inside them, as
the simulator does. A report or order damaged on the way fails its check and the order
is sent again (the rover answers a repeated order with the same report); each such fault
is a line of the run's ``faults`` and of the log. At the end every rover gets a
``evaluate`` message (its SuperNode may stop) and the result goes to
``<out>.run/result.pickle`` (:mod:`fedmap.flower.mission_task`).
"""

from __future__ import annotations

import time
from logging import INFO, WARNING

from flwr.app import ConfigRecord, Context, Message, MessageType, RecordDict
from flwr.serverapp import Grid, ServerApp
from flwr.supercore import log

from fedmap.errors import FedmapError
from fedmap.flower.mission_task import MissionRun, mission_from_text, strategies_of, write_result
from fedmap.flower.records import from_record, to_record
from fedmap.flower.task import write_status
from fedmap.mission.remote import BaseNode, CorruptMessage, Report, check_deployable, rounds
from fedmap.mission.results import MissionResult

app = ServerApp()

#: Times an order is sent again after a damaged order or report before the run fails.
RESENDS = 3


class _Team:
    """The rovers' nodes on the grid, and the sending of orders to them."""

    def __init__(self, grid: Grid, run: MissionRun, members: int) -> None:
        self.grid, self.run, self.members = grid, run, members
        self.faults: list[dict] = []
        self.node_of = self._connect()

    def _connect(self) -> dict[int, int]:
        t_end = time.monotonic() + self.run.connect_timeout
        while len(nodes := sorted(self.grid.get_node_ids())) < self.members and time.monotonic() < t_end:
            time.sleep(0.5)
        if len(nodes) < self.members:
            raise FedmapError(f"{len(nodes)} of {self.members} rovers connected after {self.run.connect_timeout:g} s")
        msgs = [Message(RecordDict({"config": ConfigRecord({})}), dst_node_id=n, message_type=MessageType.QUERY)
                for n in nodes]
        sent = {m.object_id: n for m, n in zip(msgs, nodes)}
        node_of: dict[int, int] = {}
        for reply in self.grid.send_and_receive(msgs, timeout=self.run.deadline):
            if reply.has_error():
                raise FedmapError(f"a rover did not say which it is: {reply.error.reason}".splitlines()[0])
            k = int(reply.content["config"]["rover"])  # type: ignore[arg-type]
            node = sent[reply.metadata.reply_to_message_id]
            if k in node_of:
                raise FedmapError(f"two nodes ({node_of[k]} and {node}) say they are rover {k}")
            node_of[k] = node
        missing = sorted(set(range(self.members)) - set(node_of))
        if missing or len(node_of) != self.members:
            raise FedmapError(f"the mission needs rovers 0..{self.members - 1}; connected: {sorted(node_of)}"
                              + (f", missing {missing}" if missing else ""))
        return node_of

    def send(self, strategy: str, orders: dict[int, bytes]) -> dict[int, bytes]:
        """Every order to its rover, every report back; a damaged one's order goes again."""
        reports: dict[int, bytes] = {}
        todo = dict(orders)
        for _ in range(RESENDS + 1):
            msgs = [Message(RecordDict({"order": to_record(raw), "config": ConfigRecord({"strategy": strategy})}),
                            dst_node_id=self.node_of[k], message_type=MessageType.TRAIN) for k, raw in todo.items()]
            sent = {m.object_id: k for m, k in zip(msgs, todo)}
            again: dict[int, bytes] = {}
            replies = list(self.grid.send_and_receive(msgs, timeout=self.run.deadline))
            got = set()
            for reply in replies:
                k = sent.get(reply.metadata.reply_to_message_id)
                if k is None:
                    continue
                got.add(k)
                if reply.has_error():
                    raise FedmapError(f"rover {k} failed: {reply.error.reason}".splitlines()[0])
                if "error" in reply.content.config_records:
                    why = str(reply.content["error"]["reason"])
                    if not reply.content["error"].get("corrupt"):
                        raise FedmapError(f"rover {k}: {why}")
                    again[k] = todo[k]
                    self._fault(strategy, k, f"order damaged on the way ({why}); sent again")
                    continue
                raw = from_record(reply.content.array_records.get("report"))
                try:
                    Report.from_bytes(raw)
                except CorruptMessage as e:
                    again[k] = todo[k]
                    self._fault(strategy, k, f"report damaged on the way ({e}); order sent again")
                    continue
                reports[k] = raw
            for k in set(todo) - got:
                raise FedmapError(f"rover {k} did not answer within {self.run.deadline:g} s")
            if not again:
                return reports
            todo = again
        raise FedmapError(f"rover(s) {sorted(todo)}: every copy of the order or report was damaged ({RESENDS + 1} sent)")

    def _fault(self, strategy: str, k: int, what: str) -> None:
        self.faults.append({"strategy": strategy, "rover": k, "fault": what})
        log(WARNING, "fedmap: %s rover %d: %s", strategy, k, what)

    def finish(self) -> None:
        """Tell every rover the mission is over (its SuperNode may stop)."""
        msgs = [Message(RecordDict({"config": ConfigRecord({"done": True})}), dst_node_id=n,
                        message_type=MessageType.EVALUATE) for n in self.node_of.values()]
        list(self.grid.send_and_receive(msgs, timeout=60))


def run_mission_base(grid: Grid, run: MissionRun) -> MissionResult:
    """Every strategy's mission over the rovers on ``grid``."""
    t0 = time.perf_counter()
    write_status(run.out, "running", message="loading the mission")
    mission = mission_from_text(run.mission, frames=run.frames)
    names = strategies_of(run, mission)
    check_deployable(mission, names)
    c = mission.config
    team = _Team(grid, run, c.rovers + c.helicopters)
    runs = {}
    for name in names:
        t1 = time.perf_counter()
        log(INFO, "fedmap: mission %s on %d rovers", name, team.members)
        base = BaseNode(mission, name)
        for step in rounds(base, lambda orders: team.send(name, orders)):
            write_status(run.out, "running", strategy=name, step=step, steps=c.steps)
        runs[name] = base.result(time.perf_counter() - t1)
    team.finish()
    result = MissionResult(c, mission.truth, mission.starts, mission.base, runs, time.perf_counter() - t0,
                           faults=tuple(team.faults))
    write_result(run.out, result)
    return result


@app.main()
def main(grid: Grid, context: Context) -> None:
    run = MissionRun.from_run_config(dict(context.run_config))
    try:
        run_mission_base(grid, run)
    except Exception as e:  # the command that started the base waits on this file: never leave it "running"
        msg = str(e) if isinstance(e, FedmapError) else f"{type(e).__name__}: {e}".splitlines()[0]
        write_status(run.out, "failed", message=msg)
        log(INFO, "fedmap: error: %s", msg)
        raise
    write_status(run.out, "done", message="mission over")

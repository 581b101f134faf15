"""The mission base station's sending of orders (:class:`fedmap.flower.mission.server._Team`)
against a stand-in grid: which faults it sees, and when it sends an order again."""

from __future__ import annotations

import pytest

pytest.importorskip("flwr")

from flwr.app import ConfigRecord, Message, MessageType, RecordDict  # noqa: E402
from tests.test_flower import task_identity  # noqa: E402, F401

from fedmap.flower import polling  # noqa: E402
from fedmap.flower.mission import server as mission_server
from fedmap.flower.mission.task import MissionRun  # noqa: E402
from fedmap.flower.records import to_record  # noqa: E402
from fedmap.mission.network.remote import Report  # noqa: E402

REPORT = Report("raw", 0, 5, (1, 1), None, True, None, [], None, {}).to_bytes()


class OneRoverGrid:
    """Rover 0 on node 7, as Flower's grid shows it to the base. ``dies_holding``: the rover
    process that takes the first order is killed with it, and the rover is started again as
    the same node (its key is registered), so the SuperLink reports nothing about that order.
    ``slow``: the rover answers its first order only after that many pulls (same process)."""

    def __init__(self, *, dies_holding: bool = False, slow: int = 0) -> None:
        self.boot, self.dies_holding, self.slow = "pid1", dies_holding, slow
        self.orders = 0
        self.pending: dict[str, tuple[int, Message]] = {}  # message id -> (pulls before it is there, reply)

    def get_node_ids(self):
        return [7]

    def push_messages(self, msgs):
        ids = []
        for m in msgs:
            m.metadata.__dict__["_message_id"] = m.object_id  # what Flower's grid does when it pushes
            ids.append(m.object_id)
            if m.metadata.message_type == MessageType.QUERY:
                self.pending[m.object_id] = (0, Message(RecordDict({"config": ConfigRecord(
                    {"rover": 0, "boot": self.boot})}), reply_to=m))
                continue
            self.orders += 1
            if self.orders == 1 and self.dies_holding:
                self.boot = "pid2"  # the process is gone with the order; a new one runs as node 7
                continue
            reply = Message(RecordDict({"report": to_record(REPORT), "config": ConfigRecord({"boot": self.boot})}),
                            reply_to=m)
            self.pending[m.object_id] = (self.slow if self.orders == 1 else 0, reply)
        return ids

    def pull_messages(self, ids):
        got = []
        for i in list(ids):
            if i in self.pending:
                wait, reply = self.pending[i]
                if wait:
                    self.pending[i] = (wait - 1, reply)
                else:
                    got.append(self.pending.pop(i)[1])
        return got


def _team(tmp_path, grid):
    run = MissionRun(mission="", strategies=("raw",), out=tmp_path / "m", frames=1, connect_timeout=5.0,
                     deadline=5.0, rejoin=30.0, resume=False)
    (tmp_path / "m.run").mkdir()
    return mission_server._Team(grid, run, 1)


def test_a_rover_restarted_as_the_same_node_holding_its_order_gets_it_again_at_rejoin(tmp_path, monkeypatch):
    monkeypatch.setattr(polling, "OVERDUE", 0.05)
    grid = OneRoverGrid(dies_holding=True)
    team = _team(tmp_path, grid)
    assert team.send("raw", {0: b"order"}, {}) == {0: REPORT}
    assert grid.orders == 2  # sent again once, to the same node
    assert [f["fault"] for f in team.faults] == [
        "restarted while it held its order (its node now runs a new rover process); order sent again"]
    assert team.boot_of == {0: "pid2"}


def test_a_slow_rover_of_the_same_process_is_waited_for_not_sent_its_order_again_at_rejoin(tmp_path, monkeypatch):
    monkeypatch.setattr(polling, "OVERDUE", 0.05)
    grid = OneRoverGrid(slow=40)  # 40 polls of 20 ms: several overdue checks
    team = _team(tmp_path, grid)
    assert team.send("raw", {0: b"order"}, {}) == {0: REPORT}
    assert grid.orders == 1
    assert team.faults == []


class TwoRoverGrid:
    """Rovers 0 and 1 on nodes 7 and 8. The first order to node 8 is lost on the link (the
    SuperLink has it for delivered; the rover never sees it): it is never answered. Every
    other order is answered at the next pull, each with its own rover's report."""

    def __init__(self) -> None:
        self.orders: list[int] = []  # the node of every order pushed
        self.pending: dict[str, Message] = {}

    def get_node_ids(self):
        return [7, 8]

    def push_messages(self, msgs):
        ids = []
        for m in msgs:
            m.metadata.__dict__["_message_id"] = m.object_id
            ids.append(m.object_id)
            node = m.metadata.dst_node_id
            if m.metadata.message_type == MessageType.QUERY:
                self.pending[m.object_id] = Message(RecordDict({"config": ConfigRecord(
                    {"rover": node - 7, "boot": "pid"})}), reply_to=m)
                continue
            self.orders.append(node)
            if node == 8 and self.orders.count(8) == 1:
                continue  # lost
            report = Report("raw", node - 7, 5, (1, 1), None, True, None, [], None, {}).to_bytes()
            self.pending[m.object_id] = Message(RecordDict({"report": to_record(report),
                                                            "config": ConfigRecord({"boot": "pid"})}), reply_to=m)
        return ids

    def pull_messages(self, ids):
        return [self.pending.pop(i) for i in list(ids) if i in self.pending]


def test_an_order_lost_on_the_link_is_sent_again_long_before_the_deadline(tmp_path, monkeypatch):
    """Rover 0 answers at once; rover 1's order never arrives. Once it has gone unanswered
    RESEND_FACTOR times as long as rover 0's report took (at least RESEND_MIN), a copy goes
    to the same node, and rover 1's report to it is taken: well before the round's deadline,
    with the copy in the faults. (Without the resend the base waits out the deadline.)"""
    import time

    monkeypatch.setattr(polling, "RESEND_MIN", 0.3)
    grid = TwoRoverGrid()
    run = MissionRun(mission="", strategies=("raw",), out=tmp_path / "m", frames=1, connect_timeout=5.0,
                     deadline=20.0, rejoin=30.0, resume=False)
    (tmp_path / "m.run").mkdir()
    team = mission_server._Team(grid, run, 2)
    t0 = time.monotonic()
    got = team.send("raw", {0: b"order 0", 1: b"order 1"}, {})
    took = time.monotonic() - t0
    assert {k: Report.from_bytes(v).rover for k, v in got.items()} == {0: 0, 1: 1}
    assert took < 5.0, took  # not the 20 s deadline
    assert sorted(grid.orders) == [7, 8, 8]  # one copy, to rover 1's node
    # what the base saw and nothing it did not (a killed rover's order goes unanswered the same way)
    (fault,) = team.faults
    assert fault["rover"] == 1 and "?" not in fault["fault"]
    assert fault["fault"].split(";")[0] in {f"its order went unanswered for {s} s, far longer than the others' took"
                                            for s in range(0, 5)}
    assert fault["fault"] in (tmp_path / "m.run" / "base.log").read_text()  # the same record in the log


def test_a_node_whose_key_is_another_rovers_is_refused_by_the_base(tmp_path):
    """Node 7 holds rover 1's registered key but says it is rover 0 (a rover that ignores what
    the base tells it): the base never takes it for rover 0, and says so once, in one line."""
    import dataclasses

    from fedmap.errors import FedmapError

    run = MissionRun(mission="", strategies=("raw",), out=tmp_path / "m", frames=1, connect_timeout=2.0,
                     deadline=5.0, rejoin=30.0, resume=False)
    (tmp_path / "m.run").mkdir()
    grid = OneRoverGrid()
    with pytest.raises(FedmapError, match=r"rover\(s\) \[0\] did not connect"):
        mission_server._Team(grid, dataclasses.replace(run, rover_nodes="7=1"), 1)
    log = (tmp_path / "m.run" / "base.log").read_text()
    assert log.count("node 7 holds rover 1's registered key but says it is rover 0: refused") == 1
    team = mission_server._Team(OneRoverGrid(), dataclasses.replace(run, rover_nodes="7=0"), 1)  # its own key
    assert team.node_of == {0: 7}


def test_what_a_strategy_can_do_is_said_by_its_spec_alone():
    """Which strategies run on processes, and which with [frames], come from the registry's
    specs: the lists the CLI, the deployment and the frames check use are the same."""
    from fedmap.errors import FedmapError
    from fedmap.mission import load_mission
    from fedmap.mission.ends.registry import REGISTRY, names_that
    from fedmap.mission.network.remote import check_deployable
    from fedmap.mission.world.frames import check_frames

    deployable, framed = names_that("deployable"), names_that("framed")
    assert "central" not in deployable and {"raw", "predictive", "fedmap", "paper"} <= set(deployable)
    assert set(framed) <= set(deployable) and "fedmap" not in framed
    config, _, _ = load_mission(overrides=[{"mission": {"strategies": list(deployable)}}])
    check_deployable(config, deployable)
    for name in set(REGISTRY) - set(deployable):
        with pytest.raises(FedmapError, match=f"strategy {name} cannot run on processes.*these can: "
                                              + ", ".join(deployable)):
            check_deployable(config, [name])
    config, _, _ = load_mission(overrides=[{"mission": {"strategies": ["raw", "fedmap"]},
                                            "frames": {"start_offset": 1.0}}])
    with pytest.raises(FedmapError, match=r"\[frames\] .* runs none, raw, predictive only, not fedmap"):
        check_frames(config, framed)

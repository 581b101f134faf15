"""A mission whose rovers run elsewhere (:mod:`fedmap.mission.network.remote`): every rover's world
and end behind bytes only, the base station's end and the radio on the other side. With
the same seed and config it records the same mission as the simulator, message for
message; a frame that was damaged on the way is refused by its check."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fedmap.errors import FedmapError
from fedmap.maps.grid import FREE, UNKNOWN
from fedmap.mission import load_mission, mission_terrain
from fedmap.mission.network.nodelog import RoverEntry, read_base_record, read_rover_log, write_log
from fedmap.mission.network.remote import (
    CorruptMessage,
    LostState,
    Order,
    ProcessBase,
    ProcessRover,
    Report,
    loopback,
    pack_frame,
    pack_history,
    rounds,
    unpack_frame,
    unpack_history,
)
from fedmap.mission.outputs.report import metrics, without_timings
from fedmap.mission.results import MissionResult
from fedmap.mission.scoring import score_strategy
from fedmap.mission.sim import prepare_mission, run_mission


def _mission(strategies, *, steps=40, size=64, **link):
    over = {"mission": {"steps": steps, "strategies": list(strategies)}, "terrain": {"size": size}}
    if link:
        over["link"] = link
    config, source, _ = load_mission(overrides=[over])
    truth, elevation, prior, profiles = mission_terrain(config, source)
    kw = dict(elevation=elevation, prior=prior, profiles=profiles, thresholds=source.thresholds, frames=1)
    return config, truth, kw


def _remote(config, truth, kw) -> MissionResult:
    m = prepare_mission(config, truth, **kw)
    runs = {}
    for name in config.strategies:
        base, rovers = ProcessBase(m, name), loopback(m, name)
        steps = list(rounds(base, rovers))
        assert steps == [*config.sync_steps, config.steps][:len(steps)] and steps[-1] == config.steps
        runs[name] = replace(score_strategy(m, base.record(0.0), rovers.logs), sharing=base.sharing)
    return MissionResult(config, truth, m.starts, m.base, runs, 0.0)


@pytest.mark.parametrize("strategies,link", [
    (("none", "raw", "predictive"), {}),  # the default link: 10 % of messages lost
    (("raw", "predictive"), {"loss": 0.4, "uplink_bytes": 300, "downlink_bytes": 600}),  # losses, cut messages
    (("fedmap",), {"loss": 0.0}),
])
def test_a_mission_over_bytes_records_what_the_simulator_records(strategies, link):
    config, truth, kw = _mission(strategies, **link)
    here = run_mission(config, truth, **kw)
    apart = _remote(config, truth, kw)
    a, b = without_timings(metrics(here)), without_timings(metrics(apart))
    for name in strategies:
        ra, rb = here.runs[name], apart.runs[name]
        assert [(m.bytes, m.status) for m in ra.ledger] == [(m.bytes, m.status) for m in rb.ledger]
        if name != "none":
            assert sum(m.bytes for m in rb.ledger) > 0
        assert json.dumps(a["strategies"][name], sort_keys=True) == json.dumps(b["strategies"][name], sort_keys=True)
        np.testing.assert_array_equal(ra.sharing.global_map(), rb.sharing.global_map())
        for va, vb in zip(ra.views, rb.views):
            np.testing.assert_array_equal(va, vb)
        assert ra.trails == rb.trails
    if "raw" in strategies and link.get("loss", 0.1) > 0:  # the lossy link really dropped messages
        assert any(m.status != "delivered" for m in apart.runs["raw"].ledger)


def test_orders_and_reports_survive_bytes():
    config, truth, kw = _mission(("raw",), steps=12)
    m = prepare_mission(config, truth, **kw)
    node = ProcessRover(m, "raw", 1)
    order = Order("raw", 1, 1, config.sync_every, events=[("ack", 0, True), ("down", 0, b"\x00\xffabc")])
    again = Order.from_bytes(order.to_bytes())
    assert again == order
    node_order = Order("raw", 1, 1, config.sync_every)
    rep = node.handle(node_order)
    back = Report.from_bytes(rep.to_bytes())
    assert back == rep
    assert back.uplink is not None and back.uplink.payload
    # what an observer reads of the rover stays in its own log, and survives its bytes too
    (entry,) = node.log
    again = RoverEntry.from_bytes(entry.to_bytes(), shape=truth.shape)
    assert [s.step for s in again.states] == list(range(config.sync_every))
    for s0, s1 in zip(entry.states, again.states):
        np.testing.assert_array_equal(s0.belief, s1.belief)
        np.testing.assert_array_equal(s0.view, s1.view)
        np.testing.assert_array_equal(s0.observed, s1.observed)
        assert (s0.pos, s0.target, s0.distance, s0.trail_len) == (s1.pos, s1.target, s1.distance, s1.trail_len)
    assert again.trail == entry.trail and entry.trail[0] == m.starts[1]
    # the report is the strategy's uplink and a small header: nothing of the maps
    assert len(rep.to_bytes()) < len(back.uplink.payload) + 300 < len(entry.to_bytes())


@settings(max_examples=60, deadline=None)
@given(st.binary(min_size=0, max_size=64), st.data())
def test_a_damaged_frame_is_refused_by_its_check(blob, data):
    raw = bytearray(pack_frame({"kind": "order", "step": 3}, [blob, b"xyz"]))
    assert unpack_frame(bytes(raw)) == ({"kind": "order", "step": 3}, [blob, b"xyz"])
    i = data.draw(st.integers(0, len(raw) - 1))
    raw[i] ^= data.draw(st.integers(1, 255))
    with pytest.raises(CorruptMessage):
        unpack_frame(bytes(raw))
    with pytest.raises(CorruptMessage):
        unpack_frame(bytes(raw[: data.draw(st.integers(0, len(raw) - 1))]))


_events = st.lists(st.one_of(st.tuples(st.just("ack"), st.integers(0, 2**32 - 1), st.booleans()),
                             st.tuples(st.just("down"), st.integers(0, 2**32 - 1), st.binary(max_size=40))),
                   max_size=5)


@settings(max_examples=80, deadline=None)
@given(_events, st.integers(0, 2**31), st.booleans(), st.binary(max_size=40), st.data())
def test_orders_and_reports_are_small_binary_frames_a_damage_anywhere_refuses(events, step, finish, payload, data):
    """An order and a report come back as they went; their framing is tens of bytes (the
    strategy's payload aside); any byte flipped or any cut is refused as a corrupt message."""
    from fedmap.mission.ends.protocol import Outgoing
    from fedmap.mission.network.wire import MESSAGE_OVERHEAD

    order = Order("predictive", 3, 7, step, finish, events, "a1b2c3d4e5f6", max(step - 1, 0))
    report = Report("predictive", 3, step, (120, 7), None if finish else (5, 9), not finish,
                    Outgoing(payload, "cells"), [bool(e[2]) for e in events if e[0] == "ack"], None,
                    {"losses": [{"round": 1, "rover": 3, "loss": 0.25}]} if finish else {})
    for msg, kind in ((order, Order), (report, Report)):
        raw = msg.to_bytes()
        assert kind.from_bytes(raw) == msg
        carried = sum(len(e[2]) for e in events if e[0] == "down") if kind is Order else len(payload)
        framing = len(raw) - carried - MESSAGE_OVERHEAD
        assert framing <= (40 + 10 * len(events) if kind is Order else 120), framing
        bad = bytearray(raw)
        i = data.draw(st.integers(0, len(raw) - 1))
        bad[i] ^= data.draw(st.integers(1, 255))
        with pytest.raises(CorruptMessage):
            kind.from_bytes(bytes(bad))
        with pytest.raises(CorruptMessage):
            kind.from_bytes(raw[:data.draw(st.integers(0, len(raw) - 1))])
    with pytest.raises(CorruptMessage, match="expected order, got a 'report'"):
        Order.from_bytes(report.to_bytes())


def test_what_cannot_run_on_processes_is_refused_in_one_line():
    for over, names, words in [({"link": {"latency": 1}}, ("raw",), "latency"),
                               ({"link": {"topology": "mesh"}}, ("raw",), "star"),
                               ({}, ("central",), "central")]:
        config, source, _ = load_mission(overrides=[{"terrain": {"size": 64}, **over}])
        truth, *_ = mission_terrain(config, source)
        m = prepare_mission(config, truth)
        with pytest.raises(FedmapError, match=words) as e:
            ProcessBase(m, names[0])
        assert "\n" not in str(e.value)


def test_a_stale_or_misdirected_order_is_refused():
    config, truth, kw = _mission(("raw",), steps=12)
    m = prepare_mission(config, truth, **kw)
    node = ProcessRover(m, "raw", 0)
    node.handle(Order("raw", 0, 1, config.sync_every))
    with pytest.raises(FedmapError, match="stale"):
        node.handle(Order("raw", 0, 1, config.sync_every))
    with pytest.raises(FedmapError, match="reached raw rover 0"):
        node.handle(Order("raw", 2, 2, 2 * config.sync_every))
    fresh = ProcessRover(m, "raw", 0)  # a rover that lost its state: the base holds it further on
    with pytest.raises(FedmapError, match="lost its state"):
        fresh.handle(Order("raw", 0, 2, 2 * config.sync_every, since=config.sync_every))
    with pytest.raises(FedmapError, match="reached raw rover 0"):
        node.handle(replace(Order("raw", 0, 2, 2 * config.sync_every), strategy="predictive"))


# -- a rover whose observations come from its own mapping software -----------------------------


def _snapshots(truth, steps, seed=0):
    """What a rover's mapping software might write: the truth around a trail of points,
    growing with the steps (UNKNOWN elsewhere)."""
    rng = np.random.default_rng(seed)
    h, w = truth.shape
    rows, cols = np.indices(truth.shape)
    seen = np.zeros(truth.shape, bool)
    out = []
    for s in steps:
        r, c = rng.integers(8, h - 8), rng.integers(8, w - 8)
        seen |= (rows - r) ** 2 + (cols - c) ** 2 <= 36
        out.append((s, np.where(seen, truth.classes, UNKNOWN).astype(np.uint8)))
    return out


@pytest.mark.parametrize("kind", ["folder", "bag"])
def test_a_rover_fed_by_its_own_maps_shares_every_cell_they_hold(tmp_path, kind):
    from fedmap.maps.io import save_map
    from fedmap.maps.rosbag import write_bag
    from fedmap.mission.world.feed import MapFeed

    config, truth, kw = _mission(("raw",), steps=40, loss=0.0)
    snaps = _snapshots(truth, [0, 10, 20, 30])
    if kind == "folder":
        for s, classes in snaps:
            save_map(truth.with_classes(classes, "feed"), tmp_path / f"map_{s:04d}.png")
        path = tmp_path
    else:
        path = write_bag([("/map", s * 10**9, truth.with_classes(c, "feed")) for s, c in snaps], tmp_path / "bag")
    feed = MapFeed.open(path)
    assert feed.steps == [0, 10, 20, 30]
    for (_, classes), got in zip(snaps, feed.maps):
        np.testing.assert_array_equal(classes, got)
    m = prepare_mission(config, truth, **kw)
    base, rovers = ProcessBase(m, "raw"), loopback(m, "raw", feeds={0: feed})
    for _ in rounds(base, rovers):
        pass
    run = score_strategy(m, base.record(0.0), rovers.logs)
    fed = snaps[-1][1] != UNKNOWN
    g = base.sharing.global_map()
    np.testing.assert_array_equal(g[fed], truth.classes[fed])  # every cell the feed held reached the base
    assert run.trails[0] and all(truth.classes[c] == FREE for c in run.trails[0])


def test_a_bad_map_feed_is_refused_in_one_line(tmp_path):
    from fedmap.maps.io import save_map
    from fedmap.mission.world.feed import MapFeed

    config, truth, kw = _mission(("raw",), steps=12)
    m = prepare_mission(config, truth, **kw)
    with pytest.raises(FedmapError, match="does not exist"):
        MapFeed.open(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FedmapError, match="holds no maps"):
        MapFeed.open(tmp_path / "empty")
    small = tmp_path / "small"
    save_map(truth.with_classes(truth.classes[:32, :32], "small"), small / "map_0005.png")
    with pytest.raises(FedmapError, match="the map of step 5 is 32x32, the mission's grid is 64x64"):
        ProcessRover(m, "raw", 0, feed=MapFeed.open(small))
    save_map(truth, tmp_path / "nostep" / "latest.png")
    with pytest.raises(FedmapError, match="no step number"):
        MapFeed.open(tmp_path / "nostep")


def test_a_rover_that_lost_its_state_is_rebuilt_from_its_orders(tmp_path):
    """Rover 2 loses everything (its process came back without its state folder) at the
    order to step 25: it refuses the order, is rebuilt from every order it was sent
    before (sent again as one frame), and the mission records what the uninterrupted
    mission records (the predictive coder's state on both ends included)."""
    name = "predictive"
    config, truth, kw = _mission([name], steps=40, loss=0.2)
    m = prepare_mission(config, truth, **kw)
    here, rovers = ProcessBase(m, name), loopback(m, name)
    list(rounds(here, rovers))

    nodes: dict[int, ProcessRover] = {}
    history: dict[int, list[bytes]] = {}
    rebuilt = []

    def send(orders: dict[int, bytes]) -> dict[int, bytes]:
        out = {}
        for k, raw in orders.items():
            if k not in nodes or (k == 2 and Order.from_bytes(raw).step >= 25 and not rebuilt):
                nodes[k] = ProcessRover(m, name, k)  # a new rover process with nothing saved
            try:
                out[k] = nodes[k].answer(raw)
            except LostState:
                assert k == 2 and not rebuilt
                old = unpack_history(pack_history(history[k]))
                assert old == history[k] and len(old) >= 2
                nodes[k] = ProcessRover.rebuild(m, name, k, old)
                rebuilt.append(len(old))
                out[k] = nodes[k].answer(raw)
            history.setdefault(k, []).append(raw)
            for entry in nodes[k].log:  # each rover's own log, on its own disk (a rebuilt rover writes it again)
                write_log(tmp_path / f"rover{k}", entry)
            nodes[k].log = []
        return out

    apart = ProcessBase(m, name)
    list(rounds(apart, send))
    assert rebuilt
    logs = [read_rover_log(tmp_path, "", name, k, shape=truth.shape) for k in range(len(m.starts))]
    record = apart.record(0.0)
    write_log(tmp_path / "base", record)
    record_back = read_base_record(tmp_path, "", name, shape=truth.shape)
    assert record_back is not None and read_base_record(tmp_path, "other", name) is None
    a, b = score_strategy(m, here.record(0.0), rovers.logs), score_strategy(m, record_back, logs)
    assert json.dumps(without_timings(a.to_dict()), sort_keys=True) == json.dumps(without_timings(b.to_dict()),
                                                                                 sort_keys=True)
    assert [(x.bytes, x.status) for x in a.ledger] == [(x.bytes, x.status) for x in b.ledger]
    assert a.trails == b.trails
    for va, vb in zip(a.views, b.views):
        np.testing.assert_array_equal(va, vb)
    np.testing.assert_array_equal(here.sharing.global_map(), apart.sharing.global_map())


def test_a_rover_ahead_of_the_base_or_given_a_damaged_history_is_refused():
    config, truth, kw = _mission(["raw"], steps=30)
    m = prepare_mission(config, truth, **kw)
    base = ProcessBase(m, "raw")
    first = base.first_orders()
    node = ProcessRover(m, "raw", 0)
    node.answer(first[0].to_bytes())
    stale = replace(first[0], step=first[0].step + 5, since=0)  # the base holds it at step 0; it is further on
    with pytest.raises(FedmapError, match="ahead of the base"):
        node.answer(stale.to_bytes())
    raw = bytearray(pack_history([first[0].to_bytes()]))
    raw[-3] ^= 0xFF
    with pytest.raises(CorruptMessage):
        unpack_history(bytes(raw))


def _run_folder(folder, config, truth, kw, text):
    """A run folder as nodes on their own machines leave it: every rover's log in a folder of
    its own, the base's records, and what the run says of itself."""
    from fedmap.mission.scoring import write_run

    m = prepare_mission(config, truth, **kw)
    for name in config.strategies:
        base, rovers = ProcessBase(m, name, mission_id="m1"), loopback(m, name)
        list(rounds(base, rovers))
        for k, log in enumerate(rovers.logs):
            for entry in log:
                write_log(folder / f"rover{k}-disk", entry)
        write_log(folder / "base", base.record(1.5))
    write_run(folder, text, config.strategies, 3.0, mission_id="m1")


def test_fedmap_score_of_the_nodes_logs_gives_the_mission_in_process(tmp_path, capsys):
    """``fedmap score RUN_FOLDER`` on what the nodes logged writes the ``metrics.json`` that
    ``fedmap mission`` writes in process (timings aside), from logs alone."""
    from fedmap.cli import main
    from fedmap.mission.settings import mission_toml

    over = {"mission": {"steps": 30, "strategies": ["none", "raw", "predictive"]}, "terrain": {"size": 64}}
    config, source, resolved = load_mission(overrides=[over])
    text = mission_toml(resolved)
    (tmp_path / "mission.toml").write_text(text)
    truth, elevation, prior, profiles = mission_terrain(config, source)
    kw = dict(elevation=elevation, prior=prior, profiles=profiles, thresholds=source.thresholds, frames=1)
    run = tmp_path / "run"
    _run_folder(run, config, truth, kw, text)
    assert main(["score", str(run), "-o", str(tmp_path / "scored"), "--no-animation"]) == 0
    assert main(["mission", str(tmp_path / "mission.toml"), "-o", str(tmp_path / "here"), "--no-animation"]) == 0
    a, b = (json.loads((tmp_path / d / "metrics.json").read_text()) for d in ("here", "scored"))
    assert without_timings(a["strategies"]) == without_timings(b["strategies"])
    assert b["strategies"]["raw"]["seconds"] == 1.5

    # a rover's log missing, or damaged: one line naming it, and the earlier outputs stay
    capsys.readouterr()
    entry = sorted((run / "rover2-disk").glob("*predictive-rover2-*.log"))[1]
    raw = bytearray(entry.read_bytes())
    raw[len(raw) // 2] ^= 0x40
    entry.write_bytes(bytes(raw))
    assert main(["score", str(run), "-o", str(tmp_path / "scored"), "--no-animation"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: {entry}: corrupted message: its check failed") and "\n" not in err, err
    shutil.rmtree(run / "rover1-disk")
    assert main(["score", str(run), "-o", str(tmp_path / "scored"), "--no-animation"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: none: no log of rover 1 in the run folder") and "\n" not in err, err
    assert json.loads((tmp_path / "scored" / "metrics.json").read_text()) == b


@pytest.mark.parametrize("topology,strategies", [("star", ("raw", "predictive")), ("leader", ("raw", "gossip"))])
def test_every_message_in_process_crosses_as_a_frame_and_its_wire_bytes_are_counted(topology, strategies):
    """In process too, every strategy message (uplink, downlink, peer message, each relay hop)
    crosses the transport as a message frame; its wire bytes are the ledger's bytes plus each
    frame's framing, hop by hop (a hand count from the ledger and the layout), and a strategy
    that sends nothing has none."""
    from fedmap.mission.network.wire import MESSAGE_OVERHEAD

    link = {"topology": topology, "loss": 0.2}
    if topology != "star":
        link["peer_range"] = 40.0
    config, truth, kw = _mission(("none", *strategies), steps=30, **link)
    result = run_mission(config, truth, **kw)
    assert result.runs["none"].wire is None
    for name in strategies:
        run = result.runs[name]
        spent = [m for m in run.ledger if m.bytes]
        framing = sum(MESSAGE_OVERHEAD + 2 + 1 + len(m.kind) + 4 for m in spent)
        assert run.wire == {"frames": len(spent), "bytes": sum(m.bytes for m in spent) + framing}
        assert any(m.status == "lost" for m in spent)  # lost frames spent their bytes too
    assert metrics(result)["wire"]["raw"] == result.runs["raw"].wire


class _Clock:
    """A clock in seconds that moves only when someone sleeps on it (the base and every rover read it)."""

    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t

    def sleep(self, d: float) -> None:
        self.t += d


def _own_clock(m, name, pace_ms, rates):
    """Strategy ``name`` with every rover on its own clock, rover k's running ``rates[k]`` times as fast as the base's."""
    clock = _Clock()
    clocks = {k: (lambda r=r: clock() * r) for k, r in enumerate(rates)}
    base, rovers = ProcessBase(m, name, pace=pace_ms), loopback(m, name, clocks=clocks)
    steps = list(rounds(base, rovers, clock=clock, sleep=clock.sleep))
    return base, rovers, steps


def test_rovers_on_their_own_clock_in_step_with_the_base_record_the_lockstep_mission():
    """A rover on its own clock drives as far as its clock says and syncs at its own sync
    steps: when its clock reads the base's step at each of the base's orders, the mission is
    the lockstep one (and the simulator's), message for message."""
    config, truth, kw = _mission(("raw", "predictive"), loss=0.2)
    m = prepare_mission(config, truth, **kw)
    here = run_mission(config, truth, **kw)
    for name in ("raw", "predictive"):
        base, rovers, steps = _own_clock(m, name, 250, [1] * config.rovers)
        assert steps == [*config.sync_steps, config.steps]
        run = score_strategy(m, base.record(0.0), rovers.logs)
        assert [(x.round, x.step, x.bytes, x.status) for x in run.ledger] == \
            [(x.round, x.step, x.bytes, x.status) for x in here.runs[name].ledger]
        np.testing.assert_array_equal(base.node.global_map(), here.runs[name].sharing.global_map())


def test_rovers_ahead_of_the_base_sync_on_their_own_clock_and_the_base_holds_what_they_sent():
    """Rovers whose clocks run fast (1.3 and 2.5 times the base's: the second passes two of
    its sync steps between two of the base's orders) drive on their own: each report is at a
    step of its own clock, its uplink the one of its last own sync (an earlier one that never
    left is not delivered, and its cells go again). On a perfect link the base ends holding
    every cell each rover had observed at its last sync, and the mission is scored from the logs."""
    config, truth, kw = _mission(("raw",), loss=0.0, steps=60)
    m = prepare_mission(config, truth, **kw)
    base, rovers, steps = _own_clock(m, "raw", 100, [1.3, 2.5] + [1] * (config.rovers - 2))
    assert steps[-1] == config.steps
    run = score_strategy(m, base.record(0.0), rovers.logs)  # every rover logged every step of its own
    ups = [x for x in run.ledger if x.direction == "up" and x.status == "delivered"]
    assert {x.step for x in ups if x.rover == 0} <= {t for t in config.sync_steps}
    last_sync = []
    for k, log in enumerate(rovers.logs):
        sent = [x.step for x in ups if x.rover == k]
        assert sent, f"rover {k} sent nothing"
        last_sync.append(max(sent))
        states = {s.step: s for e in log for s in e.states}
        assert sorted(states) == list(range(config.steps + 1))
    # rover 2 (on time) synced once an order: every round went; rover 1 (2.5 times) passed two of
    # its sync steps between two orders: the first uplink never left (and is in no ledger)
    assert [x.round for x in ups if x.rover == 2] == list(range(1, len(config.sync_steps) + 1))
    rounds1 = [x.round for x in ups if x.rover == 1]
    assert rounds1 == sorted(set(rounds1)) and len(rounds1) < len(config.sync_steps) and rounds1[-1] == 6
    assert all(x.step == config.sync_steps[x.round - 1] for x in ups)  # each made at its own sync step
    held = base.node.global_map() != UNKNOWN
    observed = np.zeros_like(held)
    for k, log in enumerate(rovers.logs):
        states = {s.step: s for e in log for s in e.states}
        observed |= states[last_sync[k]].observed
    np.testing.assert_array_equal(held, observed)
    assert run.summary is not None

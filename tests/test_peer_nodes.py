"""A peer mission with one node per agent (:mod:`fedmap.mission.network.peers`): every agent
runs its own side of the topology's rounds and only mail crosses between them. Here the
agents are threads of one process and the mail goes through bytes; the result must be the
in-process mission's, message for message, on every peer topology."""

from __future__ import annotations

import json
import tomllib
from dataclasses import replace

import numpy as np
import pytest

from fedmap.errors import FedmapError
from fedmap.mission import load_mission, mission_terrain, run_mission
from fedmap.mission.network.link import BASE, Message
from fedmap.mission.network.nodelog import PeerRecord
from fedmap.mission.network.peers import (
    FRAME,
    NOTHING,
    Inbox,
    Mail,
    merge_records,
    peer_strategies,
    run_local,
)
from fedmap.mission.network.wire import CorruptMessage
from fedmap.mission.outputs.report import metrics, without_timings
from fedmap.mission.results import MissionResult
from fedmap.mission.scoring import score_strategy
from fedmap.mission.settings import mission_toml
from fedmap.mission.sim import prepare_mission


def _mission(steps: int, strategies, **link):
    _, _, resolved = load_mission(overrides=[{"mission": {"steps": steps, "strategies": list(strategies)},
                                              "link": {"latency": 0, **link}}])
    config, source, _ = load_mission(None, overrides=[tomllib.loads(mission_toml(resolved))])
    truth, elevation, prior, profiles = mission_terrain(config, source)
    kw = dict(elevation=elevation, prior=prior, profiles=profiles, thresholds=source.thresholds, frames=1)
    return config, truth, kw


def _ledger(run):
    return [(m.round, m.step, m.rover, m.to, m.bytes, m.status, m.kind, m.arrival) for m in run.ledger]


CASES = [
    # (topology, strategy, steps, link): losses, drops, budgets, range, relays, a lander cut, no lander
    ("mesh", "raw", 60, {"loss": 0.15, "drop": 0.1, "peer_bytes": 900}),
    ("leader", "raw", 80, {"peer_range": 30.0, "loss": 0.2, "drop": 0.2, "uplink_bytes": 1500,
                           "downlink_bytes": 3000, "lander_cut": [20, 50]}),
    ("leader", "gossip", 30, {"loss": 0.2, "drop": 0.2}),
    ("mesh", "admm", 20, {"lander_agent": False, "loss": 0.1}),
]


@pytest.mark.parametrize("topology,strategy,steps,link", CASES)
def test_a_peer_mission_with_a_node_per_agent_equals_the_mission_in_process(topology, strategy, steps, link):
    config, truth, kw = _mission(steps, [strategy], topology=topology, **link)
    here = run_mission(config, truth, **kw).runs[strategy]
    m = prepare_mission(config, truth, **kw)
    record, logs = run_local(m, strategy, mission_id="t")
    apart = score_strategy(m, record, logs)
    assert _ledger(apart) == _ledger(here)
    assert sum(x.bytes for x in here.ledger) > 0 and {x.status for x in here.ledger} - {"delivered"}  # faults drawn
    assert apart.trails == here.trails
    for a, b in zip(apart.views, here.views):
        np.testing.assert_array_equal(a, b)
    assert apart.wire == here.wire
    res = [MissionResult(config, truth, m.starts, m.base, {strategy: r}, 0.0) for r in (here, apart)]
    a, b = (without_timings(metrics(r)) for r in res)
    assert json.dumps(a["strategies"], sort_keys=True) == json.dumps(b["strategies"], sort_keys=True)


def test_a_leader_is_elected_alike_by_every_agent_and_a_split_mesh_heals():
    """With a short range and rovers driving apart and together, the mesh splits into groups
    and joins again; each group's members reach their leader over relays. Every agent
    elected the same leaders (else a frame would be awaited that nobody sends, or the ledger
    would differ)."""
    config, truth, kw = _mission(90, ["raw"], topology="leader", peer_range=40.0, lander_agent=False)
    here = run_mission(config, truth, **{**kw, "frames": 90}).runs["raw"]
    groups = [len(set(f.leaders)) for f in here.frames if f.leaders]
    whole = [i for i, g in enumerate(groups) if g == 1]
    assert whole and any(g > 1 for g in groups[whole[0]:whole[-1]])  # one group, split, one group again
    m = prepare_mission(config, truth, **kw)
    record, logs = run_local(m, "raw")
    assert _ledger(score_strategy(m, record, logs)) == _ledger(here)


def test_mail_is_checked_and_a_gone_agent_is_one_line():
    mail = Mail(FRAME, 2, BASE, 3, 15, 7, "raw", b"xyz")
    assert Mail.from_bytes(mail.to_bytes()) == mail
    raw = bytearray(mail.to_bytes())
    raw[-6] ^= 1
    with pytest.raises(CorruptMessage, match="check failed"):
        Mail.from_bytes(bytes(raw))
    assert Mail(NOTHING, 2, 0, 3, 15, 7, "raw").key == mail.key  # "nothing comes" answers the same wait
    inbox = Inbox(alive=lambda a: a != 1, timeout=5.0)
    with pytest.raises(FedmapError, match="rover 1 left the team: waiting for its message of step 15"):
        inbox.wait((FRAME, 1, 15, 0))


def test_merging_refuses_a_missing_agent_and_a_star_mission_is_refused():
    config, truth, kw = _mission(10, ["raw"], topology="mesh")
    m = prepare_mission(config, truth, **kw)
    rec = PeerRecord("raw", "", 0, 1.0, [Message(1, 5, 0, "peer", "cells", 10, "delivered", 5, to=1)], [(5, 0, 0)],
                     1, {}, {})
    with pytest.raises(FedmapError, match=r"records of agents \[0\], the team's are \[-1, 0, 1, 2, 3\]"):
        merge_records(m, [rec], [])
    star = replace(config, link=replace(config.link, topology="star"))
    with pytest.raises(FedmapError, match="needs a peer topology"):
        peer_strategies(star)
    names, left = peer_strategies(replace(config, strategies=("none", "raw", "gossip", "central")))
    assert names == ("raw", "gossip") and left == ["none", "central"]


def test_a_round_table_is_the_same_for_everyone_and_names_who_left():
    """The table keeper makes a round's table once every rover posted or left, and hands the
    same one to every agent; a rover that left keeps its last cell and never comes back."""
    from fedmap.mission.network.peers import Tables

    alive = {0: True, 1: True, 2: True}
    made: list = []
    tables = Tables(3, alive=lambda k: alive[k], timeout=5.0,
                    on_table=lambda strategy, step, gone: made.append((strategy, step, sorted(gone))))
    tables.post("raw", 10, 2, (7, 7))
    tables.post("raw", 10, 0, (1, 2))
    assert tables.ready("raw", 10) is None  # rover 1 has not posted
    first = tables.table("raw", 10, 1, (3, 4))
    assert first == ([(1, 2), (3, 4), (7, 7)], frozenset())
    assert tables.table("raw", 10, 0, (9, 9)) == first  # made once: a late post changes nothing
    alive[2] = False  # rover 2's process is killed
    tables.post("raw", 20, 0, (1, 3))
    second = tables.table("raw", 20, 1, (3, 5))
    assert second == ([(1, 3), (3, 5), (7, 7)], frozenset({2}))  # its last cell stands
    alive[2] = True  # (a token seen again): it does not come back
    tables.post("raw", 30, 1, (3, 6))
    assert tables.table("raw", 30, 0, (1, 4))[1] == frozenset({2})
    assert made[:2] == [("raw", 10, []), ("raw", 20, [2])]

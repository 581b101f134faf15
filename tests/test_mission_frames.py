"""Missions with unknown poses and drift (fedmap.mission.world.frames): off is today's mission, the
estimated transforms are what is scored, the gate keeps a map with no true overlap out,
and the drift is seeded."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from fedmap.coding.mapcodec import decode_map, encode_map
from fedmap.errors import FedmapError
from fedmap.maps.grid import IMPASSABLE, UNKNOWN
from fedmap.maps.registration import RigidTransform
from fedmap.mission import mission_terrain, run_mission
from fedmap.mission.ends.framed import (
    TRANSFORM_BYTES,
    FramedPredictiveBase,
    FramedPredictiveRover,
    FramedRawBase,
    FramedRawPeer,
    chain,
    pack_transform,
    track,
    unpack_transform,
)
from fedmap.mission.ends.protocol import pack_down, pack_up, unpack_down
from fedmap.mission.network.link import BASE
from fedmap.mission.network.remote import check_deployable
from fedmap.mission.settings import FramesConfig, load_mission
from fedmap.mission.world.frames import FramedWorld

MISSION = {"rovers": 2, "steps": 40, "sync_every": 8, "sensor_radius": 6.0, "eval_pairs": 8, "strategies": ["raw"]}
DRIFT = {"start_offset": 1.0, "start_heading": 1.0, "drift": 0.03, "heading_drift": 0.01, "lander_view": 12.0}


def _mission(frames: dict | None = None, seed: int = 0):
    over = [{"frames": frames}] if frames else []
    config, source, _ = load_mission(None, size=64, seed=seed, mission=dict(MISSION), overrides=over)
    truth, *_ = mission_terrain(config, source)
    return config, truth


def _run(frames: dict | None = None, seed: int = 0, strategy: str = "raw"):
    config, truth = _mission(frames, seed)
    if strategy != "raw":
        config = load_mission(None, size=64, seed=seed, mission={**MISSION, "strategies": [strategy]},
                              overrides=[{"frames": frames}] if frames else [])[0]
    return run_mission(config, truth).runs[strategy]


@pytest.fixture(scope="module")
def known():
    return _run()


def _site() -> np.ndarray:
    """A 64x64 class map of the built-in Mars terrain (rocks on free ground)."""
    return _mission()[1].classes


# ---------------------------------------------------------------- off is today's mission


def test_frames_off_is_the_mission_as_before(known):
    """An explicit [frames] table with every spread 0 runs exactly today's mission."""
    config, truth = _mission({"start_offset": 0.0, "drift": 0.0, "window": 5, "lander_view": 9.0})
    assert not config.frames.enabled and "frames" not in config.to_dict()
    run = run_mission(config, truth).runs["raw"]
    assert run.trails == known.trails
    assert [m.to_dict() for m in run.ledger] == [m.to_dict() for m in known.ledger]
    assert run.summary.to_dict() == known.summary.to_dict()


def test_negligible_drift_drives_the_known_pose_mission_and_pays_the_transform(known):
    """With the frames machinery on but an error far below a cell (and the lander's image to
    place the rovers on), the rovers drive the same trails and score the same; each
    downlink pays the transform's bytes and leaves out the rover's own cells, so it costs
    at most the transform's bytes more, and the team's downlinks cost less."""
    run = _run({"drift": 1e-12, "lander_view": 12.0})
    assert run.trails == known.trails
    assert run.summary.final_belief_accuracy_mean == known.summary.final_belief_accuracy_mean
    downs = [m for m in known.ledger if m.kind == "map"]
    framed = [m for m in run.ledger if m.kind == "map"]
    assert len(framed) == len(downs) > 0
    assert all(f.bytes <= d.bytes + TRANSFORM_BYTES for f, d in zip(framed, downs))
    assert sum(f.bytes for f in framed) < sum(d.bytes for d in downs)


def test_a_downlink_leaves_out_the_cells_the_rover_gave():
    """The base merges rover 0's cells; its downlink to rover 0 carries none of them (rover 0
    holds them in its own frame), its downlink to rover 1 carries every one."""
    site = _site()
    ring = np.hypot(*np.ogrid[-32:32, -32:32]) <= 20
    frames = FramesConfig(start_offset=1.0, lander_view=20.0)
    base = FramedRawBase(site.shape, [(32, 32), (32, 32)], budget=None, frames=frames,
                         reference=np.where(ring, site, UNKNOWN).astype(np.uint8))
    disk = np.hypot(*np.ogrid[-32:32, -32:32]) <= 10
    base.receive(0, _uplink(np.where(disk, site, UNKNOWN).astype(np.uint8)), 1)
    assert base.log[-1].action == "placed" and (base.base[disk] == site[disk]).all()
    out = base.downlinks(1)
    got = {}
    for k, o in out.items():
        _, _, _, body = unpack_down(o.payload)
        assert unpack_transform(body[:TRANSFORM_BYTES]) == base.transforms[k]
        got[k] = decode_map(body[TRANSFORM_BYTES:], reference=np.full(site.shape, UNKNOWN, dtype=np.uint8),
                            expected_shape=site.shape)
    assert (got[0] == UNKNOWN).all()
    assert np.array_equal(got[1][disk], site[disk]) and (got[1][~disk] == UNKNOWN).all()


def test_framed_rovers_never_enter_impassable_cells():
    config, truth = _mission(DRIFT)
    result = run_mission(config, truth)
    for trail in result.runs["raw"].trails:
        for a, b in zip(trail, trail[1:]):
            assert max(abs(a[0] - b[0]), abs(a[1] - b[1])) == 1
        assert all(truth.classes[c] != IMPASSABLE for c in trail)


# ---------------------------------------------------------------- scores in the true frame


def test_a_belief_is_scored_through_the_estimated_transform():
    """A rover whose frame is the true frame turned by 90 degrees and shifted: its belief,
    put back by the transform the team estimated, is the truth; by the identity it is not."""
    site = _site()
    t = RigidTransform(dy=63.0, dx=0.0, heading_deg=90.0)  # own frame -> true frame: (r, c) -> (63 - c, r)
    belief = t.inverse().apply(site, site.shape)  # what it holds, in its own frame
    world = object.__new__(FramedWorld)
    world.ends = [SimpleNamespace(transform=t, placed=True)]
    scored = world.in_true_frame(0, belief)
    known = scored != UNKNOWN
    assert known.mean() > 0.95
    assert np.array_equal(scored[known], site[known])
    world.ends = [SimpleNamespace(transform=RigidTransform(), placed=False)]
    wrong = world.in_true_frame(0, belief)
    assert (wrong[known] != site[known]).mean() > 0.1


def test_the_global_map_is_scored_in_the_frame_the_team_estimated():
    """Without the lander's image the global frame is the first rover's; the team takes the
    mean of its rovers' placements at their starts, turned back, for the true frame."""
    site = _site()
    base = FramedRawBase(site.shape, [(0, 0), (0, 0)], budget=None, frames=FramesConfig(drift=0.01))
    base.base = site.copy()
    base.first = [RigidTransform(2.0, 0.0, 0.0), RigidTransform(4.0, -2.0, 0.0)]
    assert base.team_frame() == RigidTransform(-3.0, 1.0, 0.0)
    assert np.array_equal(base.global_map(), RigidTransform(-3.0, 1.0, 0.0).apply(site, site.shape))


def test_the_transform_crosses_the_link_in_seven_bytes():
    t = RigidTransform(dy=-3.4375, dx=12.0625, heading_deg=358.5)
    raw = pack_transform(t)
    assert len(raw) == TRANSFORM_BYTES == 7
    back = unpack_transform(raw)
    assert back is not None and abs(back.dy - t.dy) < 1e-9 and abs(back.dx - t.dx) < 1e-9
    assert abs((back.heading_deg - t.heading_deg + 180) % 360 - 180) < 0.006
    assert unpack_transform(pack_transform(None)) is None


# ---------------------------------------------------------------- registration and the gate


def test_tracking_finds_a_known_shift_and_turn():
    site = _site()
    truth_t = RigidTransform(dy=2.0, dx=-1.0, heading_deg=1.0)  # the rover's frame -> the map's
    window = truth_t.inverse().apply(np.where(np.add.outer(np.arange(64), np.arange(64)) < 70, site, UNKNOWN)
                                     .astype(np.uint8), site.shape)
    t, check, verdict, _ = track(site, window, RigidTransform())
    assert verdict == "accepted" and check.kappa > 0.95
    at = np.array([[20.0, 20.0], [40.0, 10.0]])
    assert np.abs(t.map_points(at) - truth_t.map_points(at)).max() < 0.75
    # within a degree: on a window some 60 cells across, 0.75 degree moves no cell half a cell
    assert abs((t.heading_deg - 1.0 + 180) % 360 - 180) <= 1.0


def _uplink(cells: np.ndarray) -> bytes:
    return pack_up("", (32, 32), None, encode_map(cells))


def test_the_gate_keeps_a_map_with_no_true_overlap_out():
    """The base holds the lander's image of one site; a rover's cells of another site laid on
    the same cells share enough known cells to judge, disagree, and are never merged."""
    site = _site()
    other = np.ascontiguousarray(site[::-1, ::-1])  # the site turned half round: no true overlap
    ring = np.hypot(*np.ogrid[-32:32, -32:32]) <= 20
    frames = FramesConfig(start_offset=1.0, lander_view=20.0)
    base = FramedRawBase(site.shape, [(32, 32), (32, 32)], budget=None, frames=frames,
                         reference=np.where(ring, site, UNKNOWN).astype(np.uint8))
    base.receive(0, _uplink(np.where(ring, other, UNKNOWN).astype(np.uint8)), 1)
    (entry,) = base.log
    assert entry.action == "refused" and entry.overlap >= 150
    assert base.transforms[0] is None
    assert (base.base == UNKNOWN).all() and base.pending[0].any()
    # the same cells of the site itself are placed, and merged
    base.receive(1, _uplink(np.where(ring, site, UNKNOWN).astype(np.uint8)), 1)
    assert base.log[-1].action == "placed" and base.transforms[1] == RigidTransform()
    assert np.array_equal(base.base[ring], site[ring])


# ---------------------------------------------------------------- seeds


def test_drift_is_seeded():
    a, b = _run(DRIFT), _run(DRIFT)
    assert a.trails == b.trails
    assert [m.to_dict() for m in a.ledger] == [m.to_dict() for m in b.ledger]
    c = _run(DRIFT, seed=1)
    assert c.trails != a.trails


def test_frames_refuse_what_they_do_not_run():
    config, truth = _mission(DRIFT)
    config = load_mission(None, size=64, mission={**MISSION, "strategies": ["fedmap"]},
                          overrides=[{"frames": DRIFT}])[0]
    with pytest.raises(FedmapError, match="frames"):
        run_mission(config, truth)
    framed = _mission(DRIFT)[0]
    with pytest.raises(FedmapError, match="in process only"):  # a rover process would map in the true frame
        check_deployable(framed, ["raw"])
    check_deployable(_mission()[0], ["raw"])
    with pytest.raises(FedmapError, match="frames"):
        FramesConfig(drift=-0.1)


# ---------------------------------------------------------------- predictive in own frames


def test_predictive_with_negligible_drift_drives_and_scores_as_with_known_poses():
    """``predictive`` through the frames machinery, with errors far below a cell: the rovers
    drive the known-pose mission's trails and their beliefs score the same (a rover's own
    cells come from its own map, the others' from the global map the base placed)."""
    known = _run(strategy="predictive")
    framed = _run({"drift": 1e-12, "lander_view": 12.0}, strategy="predictive")
    assert framed.trails == known.trails
    assert framed.summary.final_belief_accuracy_mean == known.summary.final_belief_accuracy_mean
    assert framed.summary.final_coverage == known.summary.final_coverage


def test_framed_predictive_keeps_both_ends_of_every_link_alike():
    """With drift, each rover's trail as it believes it drove crosses the link in steps
    between neighbouring cells, the base decodes exactly the cells the rover holds it has,
    every cell merged reached the base from a rover, and the same seed sends the same bytes."""
    run = _run(DRIFT, strategy="predictive")
    base, rovers = run.sharing.base, run.sharing.rovers
    assert isinstance(base, FramedPredictiveBase)
    for k, end in enumerate(rovers):
        assert isinstance(end, FramedPredictiveRover)
        assert np.array_equal(end._mine, base.sub[k])  # what the rover knows the base holds of its cells
        assert (end._mine != UNKNOWN).sum() > 100
        own = base.own[k]
        assert own == end.own[:len(own)]
        assert all(max(abs(a[0] - b[0]), abs(a[1] - b[1])) == 1 for a, b in zip(own, own[1:]))
        # the rover's own cells it delivered are what it mapped (its frame, not the truth's)
        mine = end._mine != UNKNOWN
        assert (end._mine[mine] == end.rover.local[mine]).mean() > 0.99
    assert base.log and all(p.action in ("placed", "tracked", "carried", "waiting", "refused") for p in base.log)
    merged = base.base != UNKNOWN
    assert merged.any() and (base.owner[merged] >= 0).all()
    again = _run(DRIFT, strategy="predictive")
    assert [m.to_dict() for m in again.ledger] == [m.to_dict() for m in run.ledger]
    raw = _run(DRIFT)
    assert run.summary.bytes_up + run.summary.bytes_down < raw.summary.bytes_up + raw.summary.bytes_down


def test_chain_steps_between_neighbouring_cells():
    for a, b in [((0, 0), (3, 1)), ((5, 5), (5, 5)), ((4, 2), (0, 7)), ((1, 1), (2, 2))]:
        path = [a, *chain(a, b)]
        assert path[-1] == b
        assert all(max(abs(p[0] - q[0]), abs(p[1] - q[1])) == 1 for p, q in zip(path, path[1:]))
        assert len(path) - 1 == max(abs(a[0] - b[0]), abs(a[1] - b[1]))  # as few steps as a king's walk


def test_the_registrations_are_written_and_reported(known):
    """Every registration the base made is in ``metrics.json`` (known poses: no such entry),
    and the report counts them per strategy."""
    from collections import Counter

    from fedmap.mission.outputs.report import report_md

    config, truth = _mission(DRIFT)
    result = run_mission(config, truth)
    run = result.runs["raw"]
    written = run.to_dict()["registrations"]
    assert written == [p.to_dict() for p in run.sharing.base.log] and len(written) > 0
    assert "registrations" not in known.to_dict() and "registrations" not in result.runs["raw"].to_dict()["summary"]
    counts = Counter(p["action"] for p in written)
    md = report_md(result, title="t")
    header = next(ln for ln in md.splitlines() if ln.startswith("| strategy | ") and "placed" in ln)
    acts = [c.strip() for c in header.strip("|").split("|")[1:]]
    row = next(ln for ln in md.splitlines() if ln.startswith("| raw | ") and len(ln.split("|")) == len(acts) + 3)
    assert [int(c) for c in row.strip("|").split("|")[1:]] == [counts[a] for a in acts]


# ---------------------------------------------------------------- raw gossip on the mesh


def _mesh(frames: dict, lander_agent: bool = True):
    config, source, _ = load_mission(None, size=64, seed=0, mission=dict(MISSION),
                                     overrides=[{"frames": frames},
                                                {"link": {"topology": "mesh", "lander_agent": lander_agent}}])
    truth, *_ = mission_terrain(config, source)
    return config, truth


def test_on_the_mesh_negligible_drift_places_every_message_where_it_belongs():
    """Raw gossip with errors far below a cell: every message an agent accepted was placed
    within a cell and a degree of the identity, and every agent's held cells are the truth's."""
    config, truth = _mesh({"drift": 1e-12, "lander_view": 12.0})
    run = run_mission(config, truth).runs["raw"]
    peers = [e for e in run.sharing.peers.values() if isinstance(e, FramedRawPeer)]
    assert len(peers) == config.rovers + 1  # the lander is an agent
    used = [p for e in peers for p in e.log if p.action in ("placed", "tracked", "carried")]
    assert len(used) >= 5 and any(p.action == "placed" for p in used)
    for p in used:
        dy, dx, h = p.transform
        assert abs(dy) <= 1.0 and abs(dx) <= 1.0 and abs((h + 180) % 360 - 180) <= 1.0, p
    lander = run.sharing.peers[BASE]
    assert all(lander.given[k].any() for k in range(config.rovers))  # it placed every rover's cells
    holding = [e for e in peers if (e.hold != UNKNOWN).any()]
    for e in holding:
        held = e.hold != UNKNOWN
        assert (e.hold[held] == truth.classes[held]).mean() > 0.99
    written = run.to_dict()["registrations"]
    assert len(written) == sum(len(e.log) for e in peers) and all("by" in d for d in written)


def test_on_the_mesh_the_gate_keeps_another_sites_cells_out():
    site = _site()
    other = np.ascontiguousarray(site[::-1, ::-1])
    ring = np.hypot(*np.ogrid[-32:32, -32:32]) <= 20
    frames = FramesConfig(start_offset=1.0, lander_view=20.0)
    rover = SimpleNamespace(local=np.full(site.shape, UNKNOWN, dtype=np.uint8), pos=(32, 32), target=None)
    me = FramedRawPeer(0, rover, site.shape, [(32, 32), (32, 32)], agents=(0, 1), frames=frames)
    rover.local[ring] = site[ring]
    msg = pack_down("map", "", {}, encode_map(np.where(ring, other, UNKNOWN).astype(np.uint8)))
    assert not me.receive(1, msg, 1, 10)  # not used: its sender keeps the cells as not delivered
    assert me.log[-1].action == "refused" and (me.hold == UNKNOWN).all() and 1 not in me.est
    msg = pack_down("map", "", {}, encode_map(np.where(ring, site, UNKNOWN).astype(np.uint8)))
    assert me.receive(1, msg, 1, 10)
    assert me.log[-1].action == "placed" and np.array_equal(me.hold[ring], site[ring])


def test_frames_on_the_mesh_need_the_lander_as_an_agent():
    config, truth = _mesh(DRIFT, lander_agent=False)
    with pytest.raises(FedmapError, match="lander"):
        run_mission(config, truth)


def test_on_the_mesh_without_the_landers_image_the_first_rover_fixes_the_frame():
    """The lander has nothing to register the first message on: it takes the sender's frame
    as the global one; a later sender whose cells are that map shifted by a known amount is
    placed back by that amount."""
    site = _site()
    ring = np.hypot(*np.ogrid[-32:32, -32:32]) <= 22
    lander = FramedRawPeer(BASE, None, site.shape, [(32, 32), (32, 32)], agents=(0, 1, BASE),
                           frames=FramesConfig(start_offset=1.0))
    first = np.where(ring, site, UNKNOWN).astype(np.uint8)
    assert lander.receive(0, pack_down("map", "", {}, encode_map(first)), 1, 10)
    assert lander.log[-1].action == "anchor" and np.array_equal(lander.hold, first)
    shift = RigidTransform(dy=2.0, dx=-1.0, heading_deg=0.0)  # rover 1's frame -> the lander's
    theirs = shift.inverse().apply(first, site.shape)
    assert lander.receive(1, pack_down("map", "", {}, encode_map(theirs)), 1, 10)
    assert lander.log[-1].action == "placed"
    assert lander.est[1].dy == pytest.approx(2.0) and lander.est[1].dx == pytest.approx(-1.0)

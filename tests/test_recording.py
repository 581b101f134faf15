"""Missions as Foxglove messages (fedmap.mission.outputs.recording): an MCAP recording read back with the
``mcap`` reader and decoded with the schemas in the file, a live server spoken to by an
independent WebSocket client, the layout in docs/, and ``fedmap mission --record``."""

from __future__ import annotations

import base64
import json
import struct
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
from affine import Affine

from fedmap.cli import main
from fedmap.errors import FedmapError
from fedmap.maps.grid import GridMap
from fedmap.maps.ros import lower_left_origin
from fedmap.maps.sources import TerrainSource, load_truth
from fedmap.mission import LinkConfig, MissionConfig, run_mission
from fedmap.mission.outputs.recording import (
    STEP_SECONDS,
    Recorded,
    Recorder,
    decode,
    foxglove_layout,
    grid_arrays,
    read_recording,
    topics,
    xy_cell,
)

pytest.importorskip("google.protobuf", reason="decoding Foxglove's protobuf schemas needs protobuf (the test extra)")

ROOT = Path(__file__).resolve().parents[1]
STEP_NS = int(STEP_SECONDS * 1e9)


@pytest.fixture(scope="module")
def small():
    truth = load_truth(TerrainSource(kind="builtin", terrain="mars", size=64))
    config = MissionConfig(rovers=2, steps=12, sync_every=4, sensor_radius=4.0, strategies=("none", "raw"),
                           link=LinkConfig(loss=0.3, seed=1))
    return truth, config


@pytest.fixture(scope="module")
def recorded(small, tmp_path_factory):
    truth, config = small
    path = tmp_path_factory.mktemp("rec") / "mission.mcap"
    z = np.linspace(-5, 5, truth.classes.size, dtype=np.float32).reshape(truth.shape)  # heights for /truth
    with Recorder(config, truth, mcap=path, elevation=z) as rec:
        result = run_mission(config, truth, frames=1000, on_snapshot=rec)  # a frame at every step
    messages, schemas = read_recording(path)
    by_topic: dict[str, list[tuple[int, dict]]] = defaultdict(list)
    for m in messages:
        by_topic[m.topic].append((m.log_time, decode(m, schemas)))
    return result, by_topic, z, path, messages


def test_every_channel_decodes_and_is_declared(small, recorded):
    truth, config = small
    result, by_topic, _, path, messages = recorded
    assert set(by_topic) <= set(topics(config))
    # every topic but the link of a strategy that sends nothing, and its unchanged global map, has messages
    assert set(topics(config)) - set(by_topic) == {"/none/link"}
    assert {m.encoding for m in messages} == {"protobuf", "json"}
    assert len(by_topic["/truth"]) == 1 and len(by_topic["/tf"]) == 1
    for s in config.strategies:
        assert [t for t, _ in by_topic[f"/{s}/scores"]] == [step * STEP_NS for step in range(config.steps + 1)]
        assert [m["step"] for _, m in by_topic[f"/{s}/eval"]] == list(result.runs[s].series.eval.step)
    assert path.stat().st_size > 0 and not list(path.parent.glob(".*.tmp"))


def test_maps_equal_the_runs_frames(small, recorded):
    truth, config = small
    result, by_topic, z, _, _ = recorded
    t = grid_arrays(by_topic["/truth"][0][1])
    assert np.array_equal(t["classes"], truth.classes)
    assert np.array_equal(t["elevation"], z)
    assert (t["red"][truth.classes == 1] == 255).all() and (t["green"][truth.classes == 0] == 255).all()
    tf = by_topic["/tf"][0][1]["transforms"][0]
    assert tf["parent_frame_id"] == "crs" and tf["child_frame_id"] == "map"
    assert tf["translation"] == {"x": 0.0, "y": 0.0, "z": 0.0}  # generated terrain: identity
    for s, run in result.runs.items():
        last_t, last = by_topic[f"/{s}/global_map"][-1]
        assert np.array_equal(grid_arrays(last)["classes"], run.frames[-1].global_map)
        # logged only when it changed: every message differs from the one before
        maps = [grid_arrays(m)["classes"] for _, m in by_topic[f"/{s}/global_map"]]
        assert all(not np.array_equal(a, b) for a, b in zip(maps, maps[1:]))
        # the map logged last at or before each step is that step's global map
        for f in run.frames:
            held = [m for t_ns, m in zip((t for t, _ in by_topic[f"/{s}/global_map"]), maps) if t_ns <= f.step * STEP_NS]
            assert np.array_equal(held[-1], f.global_map), (s, f.step)
        for k in range(config.rovers):
            belief = grid_arrays(by_topic[f"/{s}/belief/{k}"][-1][1])["classes"]
            assert np.array_equal(belief, run.frames[-1].beliefs[k])


def test_rover_poses_equal_the_trails(small, recorded):
    truth, config = small
    result, by_topic, _, _, _ = recorded
    for s, run in result.runs.items():
        poses = by_topic[f"/{s}/poses"]
        assert len(poses) == len(run.frames) == config.steps + 1
        for (t_ns, msg), f in zip(poses, run.frames):
            assert t_ns == f.step * STEP_NS and msg["frame_id"] == "map"
            cells = [xy_cell(p["position"]["x"], p["position"]["y"], truth.shape, truth.pixel_size)
                     for p in msg["poses"]]
            assert cells == [tuple(run.trails[k][f.trail_len[k] - 1]) for k in range(config.rovers)]
        last = poses[-1][1]["poses"]
        assert [xy_cell(p["position"]["x"], p["position"]["y"], truth.shape, 1.0) for p in last] == \
            [tuple(tr[-1]) for tr in run.trails]
        scene = by_topic[f"/{s}/scene"][-1][1]
        ids = {e["id"] for e in scene["entities"]}
        assert {"member/0", "trail/1", "footprint/0", "target/0", "base", "links", "leaders"} <= ids


def test_scores_and_link_messages_equal_the_series_and_ledger(recorded):
    result, by_topic, _, _, _ = recorded
    run = result.runs["raw"]
    scores = [m for _, m in by_topic["/raw/scores"]]
    assert [m["coverage"] for m in scores] == list(run.series.coverage)
    assert [m["bytes_up_total"] for m in scores] == [sum(b) for b in run.series.bytes_up]
    link = [m for _, m in by_topic["/raw/link"]]
    assert len(link) == len(run.ledger) > 0
    assert [(m["bytes"], m["status"], m["direction"]) for m in link] == \
        [(m.bytes, m.status, m.direction) for m in run.ledger]
    assert {m["status"] for m in link} >= {"delivered", "lost"}  # loss 0.3: both fates show


def test_georeferenced_map_frame():
    classes = np.zeros((10, 20), dtype=np.uint8)
    g = GridMap(classes, pixel_size=2.0, transform=Affine(2.0, 0, 500_000.0, 0, -2.0, 4_000_020.0), crs="EPSG:32633")
    assert lower_left_origin(g) == (500_000.0, 4_000_000.0)  # the lower-left corner, in the CRS's metres
    geo = GridMap(classes, pixel_size=2.0, transform=Affine(0.1, 0, 10.0, 0, -0.1, 50.0), crs="EPSG:4326")
    assert lower_left_origin(geo) == (0.0, 0.0)  # degrees are no metres: identity


def test_a_truncated_recording_is_a_one_line_error(recorded, tmp_path):
    path = recorded[3]
    data = path.read_bytes()
    for cut in (len(data) // 2, 20):
        bad = tmp_path / f"cut{cut}.mcap"
        bad.write_bytes(data[:cut])
        with pytest.raises(FedmapError) as err:
            read_recording(bad)
        assert "\n" not in str(err.value) and "not a complete MCAP recording" in str(err.value)
    with pytest.raises(FedmapError, match="cannot read"):
        read_recording(tmp_path / "missing.mcap")


def test_recorder_refuses_bad_targets(small, tmp_path):
    truth, config = small
    with pytest.raises(FedmapError, match="needs an MCAP path"):
        Recorder(config, truth)
    with pytest.raises(FedmapError, match="does not exist"):
        Recorder(config, truth, mcap=tmp_path / "no" / "x.mcap")


def _recv_json(ws, until, deadline: float):
    """Text frames from the server until one satisfies ``until`` (bounded by ``deadline``)."""
    while True:
        msg = ws.recv(timeout=max(deadline - time.monotonic(), 0.01))
        if isinstance(msg, str):
            d = json.loads(msg)
            if until(d):
                return d


def test_live_server_streams_the_global_map_to_an_independent_client(small):
    from google.protobuf import descriptor_pb2
    from websockets.sync.client import connect

    truth, config = small
    deadline = time.monotonic() + 20  # every wait below is bounded by this one deadline
    with Recorder(config, truth, live=True, port=0) as rec:
        assert rec.url.startswith("ws://127.0.0.1:")
        # the SDK's server speaks subprotocol foxglove.sdk.v1 (the ws-protocol spec's successor)
        with connect(rec.url, subprotocols=["foxglove.sdk.v1"], open_timeout=5, close_timeout=2) as ws:
            assert ws.subprotocol == "foxglove.sdk.v1"
            _recv_json(ws, lambda d: d["op"] == "serverInfo", deadline)
            channels: dict[str, dict] = {}

            def advertised(d):
                if d["op"] == "advertise":
                    channels.update({c["topic"]: c for c in d["channels"]})
                return "/raw/global_map" in channels

            _recv_json(ws, advertised, deadline)
            chan = channels["/raw/global_map"]
            assert chan["encoding"] == "protobuf" and chan["schemaName"] == "foxglove.Grid"
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": chan["id"]}]}))
            # the subscription is in place once the server's sink is on the channel: wait for it, then run
            sdk_channel = rec.outs[0].channels["/raw/global_map"]
            while not sdk_channel.has_sinks():
                assert time.monotonic() < deadline, "the server never took the subscription"
                time.sleep(0.005)
            result = run_mission(config, truth, frames=1000, on_snapshot=rec)
            while True:
                msg = ws.recv(timeout=max(deadline - time.monotonic(), 0.01))
                if isinstance(msg, bytes) and msg[0] == 1:
                    break
            sub, log_time = struct.unpack_from("<IQ", msg, 1)
            assert sub == 7
            schema = base64.b64decode(chan["schema"])
            fds = descriptor_pb2.FileDescriptorSet.FromString(schema)
            assert any(m.name == "Grid" for f in fds.file for m in f.message_type)
            grid = grid_arrays(decode(Recorded("/raw/global_map", "foxglove.Grid", "protobuf", log_time, msg[13:]),
                                      {"foxglove.Grid": schema}))
            assert grid["classes"].shape == truth.shape
            # live, strategies follow one another on the clock: raw (the second) starts after none
            start = (config.steps + 1) * STEP_NS
            step = (log_time - start) // STEP_NS
            assert 0 <= step <= config.steps
            assert np.array_equal(grid["classes"], result.runs["raw"].frames[step].global_map)
    assert rec.closed


def test_the_docs_layout_is_the_layout_of_the_default_mission():
    doc = json.loads((ROOT / "docs" / "foxglove_layout.json").read_text())
    c = MissionConfig()
    assert doc == foxglove_layout(c.strategies, c.rovers + c.helicopters, (128, 128), 1.0)
    used = {t for panel in doc["configById"].values() for t in panel.get("topics", {})}
    used |= {p["value"].rsplit(".", 1)[0] for panel in doc["configById"].values() for p in panel.get("paths", [])}
    used |= {panel["topicPath"] for panel in doc["configById"].values() if "topicPath" in panel}
    assert used <= set(topics(c))


def test_mission_cli_records(tmp_path, capsys):
    path = tmp_path / "m.mcap"
    rc = main(["mission", "--size", "64", "--steps", "6", "--sync-every", "3", "--rovers", "2", "--sensor-radius", "4",
               "--strategies", "none,raw", "--no-animation", "-o", str(tmp_path / "out"), "--record", str(path)])
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert f"recording: {path}" in out.out.replace("\n", "")
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    messages, schemas = read_recording(path)
    last = [m for m in messages if m.topic == "/raw/scores"][-1]
    assert decode(last, schemas)["coverage"] == metrics["strategies"]["raw"]["series"]["coverage"][-1]


def test_a_taken_port_is_a_one_line_error(small):
    import socket

    truth, config = small
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        with pytest.raises(FedmapError, match="cannot start the live server") as err:
            Recorder(config, truth, live=True, port=s.getsockname()[1])
    assert "\n" not in str(err.value)


def test_mission_cli_live_prints_the_url_and_stops(tmp_path, capsys):
    rc = main(["mission", "--size", "64", "--steps", "4", "--sync-every", "2", "--rovers", "2", "--sensor-radius", "4",
               "--strategies", "raw", "--no-animation", "-o", str(tmp_path / "out"), "--live", "--port", "0"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert "live: ws://127.0.0.1:" in out.out

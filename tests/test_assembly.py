"""One run assembly: the pipeline, the Flower apps and the mission strategies start from the
same initial weights for the same config, for every init and precision, and build local
maps in one place."""

from __future__ import annotations

import numpy as np
import pytest

import fedmap.pipeline as pipeline
from fedmap.config import method_config
from fedmap.flower.settings import RunSettings
from fedmap.flower.task import initial_weights as flower_initial_weights
from fedmap.flower.task import load_local_map
from fedmap.maps.grid import UNKNOWN
from fedmap.maps.sources import load_truth
from fedmap.mission.ends.registry import Setup, build
from fedmap.mission.network.topology import StarTopology
from fedmap.mission.settings import MissionConfig
from fedmap.mission.world.world import Rover
from fedmap.nets.init import load_init_weights
from fedmap.nets.model import build_model, get_weights
from fedmap.nets.training import native_bf16

SIDE, SEED = 64, 4


class _Captured(Exception):
    pass


def _pipeline_start(cfg, monkeypatch) -> dict:
    """The initial weights run_pipeline hands to the federation (the run stops there)."""
    got: dict = {}

    def capture(init, net_config, maps, fed, **kw):
        got["weights"] = init
        raise _Captured

    monkeypatch.setattr(pipeline, "run_federation", capture)
    with pytest.raises(_Captured):
        pipeline.run_pipeline(cfg)
    return got["weights"]


def _mission_start(settings: dict) -> dict:
    truth = load_truth(method_config(size=SIDE, seed=SEED).terrain, seed=SEED)
    blank = np.full(truth.shape, UNKNOWN, np.uint8)
    team = [Rover(pos=(10 * k, 10), local=blank.copy(), obs_step=np.full(truth.shape, -1)) for k in range(2)]
    config = MissionConfig(rovers=2, strategies=("paper",), methods={"paper": settings}, seed=SEED)
    sharing = build("paper", Setup(config, truth, team, StarTopology((0, 0))))
    return sharing.rovers[0].held_w


def _same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(np.array_equal(np.asarray(a[k], np.float32), np.asarray(b[k], np.float32))
                                        for k in a)


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
@pytest.mark.parametrize("init,net", [("random", "small"), ("empty", "small"), ("meta", "paper")])
def test_pipeline_flower_and_mission_start_from_the_same_weights(init, net, precision, monkeypatch):
    settings = {"net": net, "init": init, "precision": precision, "prior_steps": 3}
    cfg = method_config("paper", **settings, seed=SEED, size=SIDE)
    flower = RunSettings.from_run_config({"net": net, "init": init, "precision": precision, "prior-steps": 3,
                                          "seed": SEED, "size": SIDE})
    assert flower.pipeline.model == cfg.model and flower.pipeline.train.precision == cfg.train.precision
    ref = pipeline.initial_weights(cfg, SIDE)
    assert _same(_pipeline_start(cfg, monkeypatch), ref)
    assert _same(flower_initial_weights(flower, SIDE), ref)
    assert _same(_mission_start(settings), ref)
    # and the start is what the init says, independently of the assembly
    if init == "meta":
        assert _same(ref, load_init_weights(cfg.model.network(SIDE)))
    elif init == "random":
        assert _same(ref, get_weights(build_model(cfg.model.network(SIDE), seed=SEED)))
    else:
        assert not _same(ref, get_weights(build_model(cfg.model.network(SIDE), seed=SEED)))  # the prior was fitted


@pytest.mark.skipif(not native_bf16(), reason="bf16 resolves to fp32 on this CPU")
def test_the_empty_prior_follows_the_precision():
    """The precision reaches the empty-map prior (it once did only in the pipeline)."""
    a = pipeline.initial_weights(method_config("paper", net="small", init="empty", prior_steps=3, precision="fp32",
                                               size=SIDE), SIDE)
    b = pipeline.initial_weights(method_config("paper", net="small", init="empty", prior_steps=3, precision="bf16",
                                               size=SIDE), SIDE)
    assert not _same(a, b)


def test_flower_rovers_take_the_pipelines_local_maps():
    cfg = method_config("paper", terrain="moon", size=SIDE, seed=3, agents=4)
    maps = pipeline.build_local_maps(cfg, load_truth(cfg.terrain, seed=3))
    for k in range(4):
        pid, m = load_local_map({"partition-id": k, "terrain": "moon", "size": SIDE, "agents": 4, "seed": 3})
        assert pid == k and np.array_equal(m.classes, maps[k].classes)

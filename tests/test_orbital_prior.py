"""The orbital prior: its classes against a hand computation, its settings, and how a
mission plans on it (and never counts it as an observation)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from conftest import maze
from fedmap.errors import FedmapError
from fedmap.maps.dem import Dem
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN
from fedmap.maps.orbital import orbital_prior
from fedmap.maps.traversability import TraversabilityThresholds
from fedmap.mission import LinkConfig, MissionConfig, load_mission, mission_terrain, run_mission
from fedmap.mission.settings import PriorConfig


def test_a_ramp_is_impassable_only_where_its_block_mean_is_steep():
    # 32x32 cells of 1 m: flat, except a 45-degree ramp over rows 8..15; block means of
    # 8x8 keep the ramp (slope 45 deg) in the second block row only
    z = np.zeros((32, 32))
    z[8:16, :] = np.arange(8)[:, None] * 1.0
    z[16:, :] = 8.0
    th = TraversabilityThresholds(max_slope_deg=20.0, max_step_m=100.0, max_roughness_m=100.0)
    prior = orbital_prior(Dem(z.astype(np.float32), 1.0, "ramp"), th, 8)
    assert prior.shape == (32, 32)
    coarse = prior[::8, ::8]
    # by hand: block means 0, 3.5, 8, 8 -> slopes between neighbouring block centres (8 m
    # apart) are 3.5/8, 4.5/8, 0: 23.6 and 29.4 degrees around block row 1 and 2, flat after
    assert set(np.unique(prior)) <= {FREE, IMPASSABLE}
    assert (coarse[3] == FREE).all() and (coarse[1] == IMPASSABLE).all()
    assert (prior[8:16] == coarse[1][None, :].repeat(8, axis=1)).all()  # spread back over its 8x8 cells


def test_prior_settings_are_checked():
    with pytest.raises(FedmapError, match="unknown prior kind 'orbitl'"):
        PriorConfig(kind="orbitl")
    with pytest.raises(FedmapError, match="factor must be an integer >= 2"):
        PriorConfig(kind="orbital", factor=1)
    with pytest.raises(FedmapError, match="fewer than 4 cells"):
        orbital_prior(Dem(np.zeros((16, 16), np.float32), 1.0, "flat"), None, 8)
    config, source, resolved = load_mission(None, overrides=[{"prior": {"kind": "orbital", "factor": 4}}])
    assert config.prior == PriorConfig("orbital", 4) and resolved["prior"] == {"kind": "orbital", "factor": 4}
    truth, elevation, prior, _ = mission_terrain(config, source)
    assert elevation is None and prior is not None and prior.shape == truth.shape


def test_a_rover_plans_on_the_prior_but_never_counts_it_as_seen():
    truth = maze(40, 4)
    config = MissionConfig(rovers=2, steps=30, sync_every=5, sensor_radius=4.0, strategies=("none", "raw"),
                           eval_pairs=5, link=LinkConfig(loss=0.0))
    wrong = np.full(truth.shape, IMPASSABLE, np.uint8)  # a prior that says nothing is passable
    plain = run_mission(config, truth, frames=1)
    with_prior = run_mission(config, truth, prior=wrong, frames=1)
    for name in ("none", "raw"):
        a, b = plain.runs[name], with_prior.runs[name]
        # it cannot trap the rovers: with no path on the prior they plan on their beliefs alone
        assert b.summary.final_distance_total > 0
        assert a.trails == b.trails  # a prior that blocks everything changes no plan
        # coverage and beliefs are observations only
        assert a.series.coverage == b.series.coverage and a.series.accuracy == b.series.accuracy
    # a prior of FREE everywhere: every impassable cell a rover has not seen is a false free
    free = np.full(truth.shape, FREE, np.uint8)
    run = run_mission(replace(config, strategies=("none",)), truth, prior=free, frames=1).runs["none"]
    s = run.sharing
    for k, r in enumerate(s.team):
        on = np.where(r.local == UNKNOWN, FREE, r.local)
        want = ((on == FREE) & (truth.classes == IMPASSABLE)).sum() / (on == FREE).sum()
        assert run.series.false_free[-1][k] == pytest.approx(want)

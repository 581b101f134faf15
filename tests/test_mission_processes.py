"""The ends of a strategy really are separate: the default mission with the base station's
end and every rover's end in OS processes of their own (spawned, exchanging only bytes)
gives the same metrics, bytes and ledger as the same mission with every end in one
process."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from fedmap.mission import load_mission, mission_terrain, run_mission
from fedmap.mission.processes import EndProcess, ProcessSharing, close_all, ends_in_processes


def _metrics(run) -> str:
    d = run.to_dict()
    d.pop("seconds")
    d.pop("dropped_updates", None)  # the journals stay with the ends, in their processes
    d.pop("model_lag", None)
    return json.dumps(d, sort_keys=True)


@pytest.mark.slow
@pytest.mark.xdist_group("processes")
def test_the_default_mission_with_every_end_in_its_own_process_matches_one_process():
    config, source, _ = load_mission()  # the default mission: built-in mars 128², 4 rovers, 150 steps
    config = replace(config, strategies=("raw", "predictive", "fedmap"))
    truth, elevation, prior, profiles = mission_terrain(config, source)
    here = run_mission(config, truth, elevation=elevation, prior=prior, profiles=profiles, frames=1)
    apart = run_mission(config, truth, elevation=elevation, prior=prior, profiles=profiles, frames=1,
                        ends=ends_in_processes)
    try:
        for name in config.strategies:
            s = apart.runs[name].sharing
            assert isinstance(s, ProcessSharing)
            assert all(isinstance(e, EndProcess) for e in [*s.rovers, s.base])
            pids = {e._process.pid for e in [*s.rovers, s.base]}
            assert len(pids) == config.rovers + 1  # one process per end
            a, b = here.runs[name], apart.runs[name]
            assert [m.bytes for m in a.ledger] == [m.bytes for m in b.ledger] and sum(m.bytes for m in a.ledger) > 0
            assert _metrics(a) == _metrics(b), name
            np.testing.assert_array_equal(here.runs[name].sharing.global_map(), s.global_map())
    finally:
        close_all(apart)

"""A rover adapts its copy of the predictor to its own map during the mission
(:func:`fedmap.nets.predictor.adapt_predictor`, ``[mission] predictor_adapt``), for planning
only: observed cells stay what was observed, and the coder keeps the shipped weights."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fedmap.errors import FedmapError
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN
from fedmap.mission import load_mission, mission_terrain
from fedmap.mission.ends import predictive
from fedmap.mission.sim import prepare_mission
from fedmap.nets.predictor import (
    SHIPPED_PREDICTOR,
    Adaptation,
    adapt_predictor,
    check_guesses,
    load_predictor,
    predict,
    shipped_predictor,
)


def striped(known_cols: int = 40) -> np.ndarray:
    """A 64x64 map of thin impassable walls every 6 rows (a pattern no training map has),
    known on its first columns."""
    truth = np.full((64, 64), FREE, dtype=np.uint8)
    truth[::6] = IMPASSABLE
    belief = truth.copy()
    belief[:, known_cols:] = UNKNOWN
    return belief


def _state(model) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in model.state_dict().items()}


def test_an_adapted_predictor_changes_no_observed_cell_and_leaves_the_shipped_weights_alone():
    belief = striped()
    shipped = shipped_predictor()
    before = _state(shipped)
    adapted = adapt_predictor(shipped, belief, np.random.default_rng(0), radius=4.0)
    for k, v in shipped.state_dict().items():  # the model it started from is untouched
        assert torch.equal(v, before[k]), k
    assert any(not torch.equal(v, before[k]) for k, v in adapted.state_dict().items())  # it did learn something
    p_free, p_imp = predict(adapted, belief)
    known = belief != UNKNOWN
    assert np.array_equal(p_imp[known], (belief[known] == IMPASSABLE).astype(np.float32))
    assert np.array_equal(p_free[known], (belief[known] == FREE).astype(np.float32))
    assert not np.array_equal(p_imp[~known], predict(shipped, belief)[1][~known])  # the guesses moved


def test_adapting_to_a_map_improves_the_guesses_on_cells_of_it_that_were_hidden():
    """Self-supervised fine-tuning on the walls' first 40 columns makes the masked guesses
    there better than the shipped model's (scored on other draws of hidden patches than it
    trained on: the rover's own check)."""
    belief = striped()
    shipped = shipped_predictor()

    def masked_accuracy(model) -> float:
        return float(np.mean([check_guesses(model, belief, np.random.default_rng(s), radius=4.0).accuracy
                              for s in range(100, 105)]))

    # an adaptation can stall on a plateau: the median of five adaptations (different draws) is the measure
    after = [masked_accuracy(adapt_predictor(shipped, belief, np.random.default_rng(seed), radius=4.0,
                                             adaptation=Adaptation(steps=40, lr=2e-3))) for seed in range(5)]
    assert np.median(after) > masked_accuracy(shipped) + 0.05


def test_the_same_draws_give_the_same_weights():
    belief = striped()
    a = adapt_predictor(shipped_predictor(), belief, np.random.default_rng(3), radius=4.0)
    b = adapt_predictor(shipped_predictor(), belief, np.random.default_rng(3), radius=4.0)
    c = adapt_predictor(shipped_predictor(), belief, np.random.default_rng(4), radius=4.0)
    assert all(torch.equal(v, b.state_dict()[k]) for k, v in a.state_dict().items())
    assert any(not torch.equal(v, c.state_dict()[k]) for k, v in a.state_dict().items())


def test_a_map_with_too_little_known_changes_nothing():
    belief = np.full((64, 64), UNKNOWN, dtype=np.uint8)
    belief[30:33, 30:33] = FREE
    adapted = adapt_predictor(shipped_predictor(), belief, np.random.default_rng(0), radius=4.0)
    assert all(torch.equal(v, shipped_predictor().state_dict()[k]) for k, v in adapted.state_dict().items())


def test_the_coder_guesses_alike_at_both_ends_with_adaptation_on(monkeypatch):
    """A ``predictive`` mission whose coder takes the predictor's guesses (``mix``) while the
    rovers adapt their planning copies: every map the coder guessed on gives the same guesses
    at both ends of its link, and they are the shipped weights' guesses read afresh from the
    file, while the rovers' adapted copies guess otherwise on the same maps."""
    calls: dict[bytes, list[np.ndarray]] = {}
    guess = predictive._Coding.guess

    def record(self, known):
        out = guess(self, known)
        calls.setdefault(np.ascontiguousarray(known, dtype=np.uint8).tobytes(), []).append(out.copy())
        return out

    monkeypatch.setattr(predictive._Coding, "guess", record)
    cfg, src, _ = load_mission(overrides=[{"mission": {"steps": 40, "strategies": ["predictive"],
                                                       "predictor": "learned", "predictor_adapt": True},
                                           "strategies": {"predictive": {"predictor": "mix"}}}])
    truth, elevation, prior, profiles = mission_terrain(cfg, src)
    m = prepare_mission(cfg, truth, elevation=elevation, prior=prior, profiles=profiles, thresholds=src.thresholds,
                        frames=1)
    run = m.new_run("predictive")
    assert run.run().summary.bytes_up > 0
    adapted = [x for x in run.world.models if x is not shipped_predictor()]
    assert len(adapted) == cfg.rovers
    both = {k: v for k, v in calls.items() if len(v) >= 2}
    assert both, "no map was guessed on at both ends"
    fresh = load_predictor(SHIPPED_PREDICTOR)
    shape = truth.classes.shape
    differ = 0
    for key, guesses in both.items():
        known = np.frombuffer(key, dtype=np.uint8).reshape(shape).copy()
        for g in guesses[1:]:
            assert np.array_equal(g, guesses[0])
        assert np.array_equal(guesses[0], predict(fresh, known)[1])
        differ += any(not np.array_equal(predict(m, known)[1], guesses[0]) for m in adapted)
    assert differ > 0, "the rovers' adapted copies guess as the shipped weights: nothing was adapted"


def test_adaptation_without_a_predictor_is_a_one_line_error():
    with pytest.raises(FedmapError, match="predictor_adapt needs predictor"):
        load_mission(overrides=[{"mission": {"predictor_adapt": True}}])


def test_a_mission_with_adaptation_is_reproducible_and_adaptation_changes_the_plans():
    """The same seed gives the same trails with adaptation on; the adapted copies steer the
    rovers otherwise than the shipped weights do (the guesses are in use: no check)."""
    def trails(**mission):
        cfg, src, _ = load_mission(overrides=[{"mission": {"steps": 60, "strategies": ["raw"], "predictor": "learned",
                                                           "predictor_check": False, **mission}}])
        truth, elevation, prior, profiles = mission_terrain(cfg, src)
        m = prepare_mission(cfg, truth, elevation=elevation, prior=prior, profiles=profiles,
                            thresholds=src.thresholds, frames=1)
        return m.new_run("raw").run().trails

    adapted = trails(predictor_adapt=True)
    assert trails(predictor_adapt=True) == adapted
    assert trails() != adapted

"""A rover checks its predictor on its own map and steps aside where the guesses cannot help
(:func:`fedmap.nets.predictor.check_guesses`, ``[mission] predictor_check``)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN
from fedmap.mission import load_mission, mission_terrain, run_mission
from fedmap.nets.predictor import CHECK_MARGIN, MIN_CHECK_CELLS, GuessCheck, MapPredictor, check_guesses, shipped_predictor


def always_impassable() -> MapPredictor:
    """A predictor that guesses every unknown cell impassable, whatever it sees."""
    model = MapPredictor()
    with torch.no_grad():
        for p in model.parameters():
            p.zero_()
        model.head.bias.fill_(20.0)
    return model.eval()


def half_blocked(known_rows: int = 40) -> np.ndarray:
    """A 64x64 map whose right half is one impassable block, known on its first rows."""
    truth = np.full((64, 64), FREE, dtype=np.uint8)
    truth[:, 32:] = IMPASSABLE
    belief = truth.copy()
    belief[known_rows:] = UNKNOWN
    return belief


def test_a_predictor_worse_than_all_free_does_not_pay_and_its_score_is_the_hand_count():
    belief = np.full((64, 64), FREE, dtype=np.uint8)
    belief[::9, ::9] = IMPASSABLE  # a few isolated rocks: "all free" is right on almost every cell
    belief[40:] = UNKNOWN
    got = check_guesses(always_impassable(), belief, np.random.default_rng(0), radius=4.0)
    assert got.cells >= MIN_CHECK_CELLS
    assert got.accuracy == pytest.approx(1.0 - got.all_free)  # every guess "impassable": right on the rocks only
    assert got.all_free > 0.9 and got.pays is False


def test_the_shipped_predictor_pays_where_the_terrain_continues_what_it_saw():
    got = check_guesses(shipped_predictor(), half_blocked(), np.random.default_rng(0), radius=4.0)
    assert got.cells >= MIN_CHECK_CELLS
    assert got.accuracy > got.all_free + 0.2 and got.pays is True  # the block goes on; "all free" misses it


def test_too_few_cells_give_no_verdict():
    belief = np.full((64, 64), UNKNOWN, dtype=np.uint8)
    belief[30:33, 30:33] = FREE
    got = check_guesses(shipped_predictor(), belief, np.random.default_rng(0), radius=4.0)
    assert got.cells == 9 and got.pays is None


def _trails(monkeypatch, **mission):
    monkeypatch.setattr("fedmap.mission.world.world.shipped_predictor", always_impassable)
    cfg, src, _ = load_mission(overrides=[{"mission": {"steps": 80, "strategies": ["raw"], **mission}}])
    truth, elevation, prior, profiles = mission_terrain(cfg, src)
    return run_mission(cfg, truth, elevation=elevation, prior=prior, profiles=profiles, thresholds=src.thresholds,
                       frames=1).runs["raw"].trails


def test_a_rover_steps_aside_from_guesses_worse_than_all_free(monkeypatch):
    """With a predictor that calls every unknown cell impassable, the rovers that check it
    never let it in: they explore exactly as rovers without a predictor do. Without the
    check the same predictor changes (and slows) their exploration."""
    without = _trails(monkeypatch)
    checked = _trails(monkeypatch, predictor="learned", predictor_check=True)
    always = _trails(monkeypatch, predictor="learned", predictor_check=False)
    assert checked == without
    assert always != without


def test_guesses_must_beat_all_free_by_the_margin_to_be_planned_with():
    """Guesses a point or two better than "all free" are no reason to plan with them."""
    assert GuessCheck(200, 0.80 + CHECK_MARGIN / 2, 0.80).pays is False
    assert GuessCheck(200, 0.80 + CHECK_MARGIN * 1.5, 0.80).pays is True
    assert GuessCheck(200, 0.79, 0.80).pays is False

"""The map predictor (fedmap.nets.predictor), its offline training (fedmap.training.predictorprior)
and its zero-byte uses in planning (fedmap.mission.world.frontiers, fedmap.mission.world.world)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from fedmap.errors import FedmapError
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN
from fedmap.meta.collections import earth_like
from fedmap.mission.settings import MissionConfig, load_mission
from fedmap.mission.sim import prepare_mission
from fedmap.mission.world.frontiers import (
    DETOUR,
    cheapest_path,
    choose_target,
    entropy_bits,
    predicted_cost,
    travel_costs,
)
from fedmap.nets.predictor import (
    SHIPPED_PREDICTOR,
    MapPredictor,
    PredictorConfig,
    PredictorTraining,
    count_parameters,
    known_rate,
    load_predictor,
    predict,
    predictor_metadata,
    save_predictor,
    shipped_predictor,
    train_predictor,
)
from fedmap.training.predictorprior import exploration_samples


def test_parameter_count_by_hand_and_under_a_million():
    # conv k x k, c_in -> c_out: c_in c_out k^2 weights + c_out biases
    conv = lambda c_in, c_out, k=3: c_in * c_out * k * k + c_out
    c = PredictorConfig()
    want = (conv(3, c.stem) + conv(c.stem, c.width) + len(c.dilations) * conv(c.width, c.width)
            + conv(c.width + c.stem, c.stem) + conv(c.stem, 1, 1))
    assert count_parameters(MapPredictor(c)) == want == 67_521
    assert count_parameters(shipped_predictor()) <= 1_000_000


def _explored(seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """An Earth-like map and a belief of it: a few seeded disks observed, the rest unknown."""
    truth = earth_like(size=64, per_category=1, seed=seed, categories=("rural",)).maps()[0].classes
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[:64, :64]
    seen = np.zeros((64, 64), dtype=bool)
    for r, c in rng.integers(0, 64, size=(6, 2)):
        seen |= (rows - r) ** 2 + (cols - c) ** 2 <= 64
    return truth, np.where(seen, truth, UNKNOWN).astype(np.uint8)


def test_shipped_weights_give_probabilities_and_keep_known_cells():
    model = load_predictor(SHIPPED_PREDICTOR)
    assert "meta-predictor" in predictor_metadata(SHIPPED_PREDICTOR)["extra"]["command"]
    truth, belief = _explored()
    p_free, p_imp = predict(model, belief)
    assert p_free.shape == p_imp.shape == belief.shape
    assert ((p_free >= 0) & (p_free <= 1) & (p_imp >= 0) & (p_imp <= 1)).all()
    assert (p_free + p_imp <= 1 + 1e-6).all()
    known = belief != UNKNOWN
    assert (p_imp[known] == (belief[known] == IMPASSABLE)).all()  # a guess never overrides an observation
    unknown = ~known
    assert np.ptp(p_imp[unknown]) > 0.1  # the guesses depend on the map, not one constant
    again = predict(model, belief)[1]
    assert np.array_equal(again, p_imp)  # deterministic: rovers holding the same map guess the same


def test_the_guesses_follow_the_maps_own_base_rate():
    model = shipped_predictor()
    _, belief = _explored()
    _, raw = predict(model, belief, adapt=False)
    _, p = predict(model, belief)
    # the impassable share of the known cells, one pseudo-count each way
    assert known_rate(belief) == ((belief == IMPASSABLE).sum() + 1) / ((belief != UNKNOWN).sum() + 2)
    # damped towards a prior share: 100 cells of share 0.3 added (the planning benchmark's shrunk-rate ablation)
    assert known_rate(belief, cells=100, rate=0.3) == pytest.approx(
        ((belief == IMPASSABLE).sum() + 30) / ((belief != UNKNOWN).sum() + 100))
    assert 0.05 < float(model.base_rate) < 0.95  # learned from the training maps, not the 0.5 placeholder
    logit = lambda q: np.log(q) - np.log1p(-q)
    shift = logit(known_rate(belief)) - logit(float(model.base_rate))
    sure = (belief == UNKNOWN) & (raw > 0.01) & (raw < 0.99) & (p > 0.01) & (p < 0.99)
    assert sure.sum() > 100 and abs(shift) > 0.1
    assert np.allclose(logit(p[sure].astype(np.float64)), logit(raw[sure].astype(np.float64)) + shift, atol=1e-3)


def test_predicted_cost_by_hand_and_monotone():
    # (1 - p) * unknown_cost + p * DETOUR, DETOUR = 8
    assert DETOUR == 8.0
    got = predicted_cost(np.array([0.0, 0.25, 0.5, 1.0]), 1.5)
    assert np.allclose(got, [1.5, 0.75 * 1.5 + 0.25 * 8, 0.5 * 1.5 + 0.5 * 8, 8.0])
    p = np.linspace(0, 1, 101)
    assert (np.diff(predicted_cost(p, 1.5)) > 0).all()
    # entropy in bits: H(1/2) = 1, H(0) = H(1) = 0, H(0.11) = 0.4999 (tables of the binary entropy)
    assert np.allclose(entropy_bits(np.array([0.5, 0.0, 1.0, 0.11])), [1.0, 0.0, 0.0, 0.49992], atol=1e-4)


def test_travel_costs_with_a_prediction_by_hand():
    b = np.array([[FREE, UNKNOWN, UNKNOWN]], dtype=np.uint8)
    p = np.array([[0.0, 0.5, 0.0]])
    cum = travel_costs(b, (0, 0), 1.5, p_impassable=p)
    # step cost (a + b) / 2: cells cost 1, 0.5 * 1.5 + 0.5 * 8 = 4.75, 1.5
    assert cum[0, 1] == pytest.approx(0.5 * (1 + 4.75))
    assert cum[0, 2] == pytest.approx(0.5 * (1 + 4.75) + 0.5 * (4.75 + 1.5))
    assert np.allclose(travel_costs(b, (0, 0), 1.5, p_impassable=np.zeros((1, 3))), travel_costs(b, (0, 0), 1.5))


def test_cheapest_path_goes_round_a_predicted_wall():
    b = np.full((7, 9), UNKNOWN, dtype=np.uint8)
    b[3, 0] = b[3, 8] = FREE
    p = np.zeros(b.shape)
    p[:, 4] = 0.95
    p[0, 4] = 0.0  # a gap at the top of the predicted wall
    path = cheapest_path(b, (3, 0), (3, 8), 1.5, p)
    assert path is not None and path[-1] == (3, 8)
    assert (0, 4) in path  # through the gap, not the straight line
    steps = [(3, 0), *path]
    assert all(max(abs(a[0] - c[0]), abs(a[1] - c[1])) == 1 for a, c in zip(steps, steps[1:]))
    costs = np.where(b == FREE, 1.0, predicted_cost(p, 1.5))
    total = sum(math.hypot(a[0] - c[0], a[1] - c[1]) * 0.5 * (costs[a] + costs[c]) for a, c in zip(steps, steps[1:]))
    assert total == pytest.approx(travel_costs(b, (3, 0), 1.5, p_impassable=p)[3, 8])
    b[:, 4] = IMPASSABLE  # observed walls bar the way; guesses never do
    assert cheapest_path(b, (3, 0), (3, 8), 1.5, p) is None


def test_choose_target_prefers_the_frontier_whose_guesses_are_uncertain():
    b = np.full((21, 21), UNKNOWN, dtype=np.uint8)
    b[8:13, 8:13] = FREE  # a known square in the middle, frontiers on every side
    p = np.full(b.shape, 0.5)
    p[b != UNKNOWN] = 0.0
    kw = dict(radius=3.0, unknown_cost=1.5, others=[])
    assert choose_target(b, (10, 10), p_impassable=p, **kw) == (8, 8)  # equal gains: the first corner
    p[b == UNKNOWN] = 0.999  # almost surely impassable everywhere: little to learn, costly to cross ...
    p[:, 13:] = 0.5  # ... but east of the square
    target = choose_target(b, (10, 10), p_impassable=p, **kw)
    assert target is not None and target[1] == 12


def _small_mission(strategy: str):
    truth = earth_like(size=40, per_category=1, seed=5, categories=("rural",)).maps()[0]
    config = replace(MissionConfig(), rovers=2, steps=20, sync_every=5, strategies=(strategy,), predictor="learned",
                     eval_pairs=4, seed=1)
    return truth, prepare_mission(config, truth, frames=1)


@pytest.mark.parametrize("strategy", ["raw", "predictive"])
def test_predicted_cells_are_never_observed_or_shared(strategy):
    truth, mission = _small_mission(strategy)
    holder: dict = {}
    checked = []

    def check(snap) -> None:
        team = holder["run"].team
        seen = np.any([r.local != UNKNOWN for r in team], axis=0)  # sensed by some rover
        for r in team:
            assert np.array_equal(r.local != UNKNOWN, r.obs_step >= 0)
        for b in [*snap.beliefs, snap.global_map]:
            known = b != UNKNOWN
            assert not (known & ~seen).any()  # nothing known that nobody sensed
            assert np.array_equal(b[known], truth.classes[known])
        checked.append(snap.step)

    run = mission.new_run(strategy, on_snapshot=check)
    holder["run"] = run
    result = run.run()  # the world itself stops if a rover would enter an impassable cell
    assert checked == list(range(21))
    views = list(run.world._predicted.values())
    assert views and any(v.predicted.any() for _, v in views)  # the rovers did plan with guesses
    for _, v in views:
        assert set(np.unique(v.classes)) <= {FREE, IMPASSABLE}
    assert result.summary is not None


def test_prediction_scores_by_hand():
    from fedmap.evaluation.metrics import prediction_scores

    got = prediction_scores(np.array([0.1, 0.6, 0.8, 0.3]), np.array([False, True, False, False]))
    # guesses F T T F against F T F F; one cell per calibration bin: |y - p| = .1 .4 .8 .3
    assert got["cells"] == 4 and got["impassable"] == 0.25 and got["accuracy"] == 0.75
    assert got["iou_impassable"] == 0.5 and got["accuracy_all_free"] == 0.75
    assert math.isclose(got["brier"], (0.01 + 0.16 + 0.64 + 0.09) / 4)
    assert math.isclose(got["ece"], (0.1 + 0.4 + 0.8 + 0.3) / 4)
    with pytest.raises(FedmapError, match="3 guesses for 2 cells"):
        prediction_scores(np.zeros(3), np.zeros(2, bool))


def test_the_summary_scores_the_guesses_on_cells_nobody_observed():
    """`none`: a rover's belief is what it sensed, so the cells nobody observed are the
    cells unknown in every final belief. The summary's final_prediction is the shipped
    predictor's guesses there, every rover's pooled, as computed here from the last frame."""
    from fedmap.evaluation.metrics import prediction_scores

    truth, mission = _small_mission("none")
    run = mission.new_run("none").run()
    beliefs = run.frames[-1].beliefs
    nobody = np.all([b == UNKNOWN for b in beliefs], axis=0)
    assert nobody.any()
    p = np.concatenate([predict(shipped_predictor(), b)[1][nobody] for b in beliefs])
    want = prediction_scores(p, np.tile(truth.classes[nobody] == IMPASSABLE, len(beliefs)))
    assert run.summary.final_prediction == want
    assert run.summary.to_dict()["final_prediction"] == want
    plain = replace(mission.config, predictor="none")
    assert "final_prediction" not in prepare_mission(plain, truth, frames=1).new_run("none").run().summary.to_dict()


def test_the_beliefs_with_the_guesses_filled_in_are_scored_strictly_at_every_evaluation():
    """With a predictor every evaluation also scores each rover's belief with the guesses
    filled in: recomputed here from the snapshots' views (predict, a guess impassable above
    1/2, path F1 and false-free by hand), observed cells untouched, and the summary's first
    step the rovers' mean reached 0.9. Without a predictor none of it is written."""
    from fedmap.evaluation.paths import path_f1
    from fedmap.mission.results import F1_GOAL

    truth, mission = _small_mission("raw")
    c = mission.config
    want: dict[int, tuple[list[float], list[float], list[float], list[float]]] = {}

    def look(snap) -> None:
        if snap.eval is None:
            return
        f1s, successes, false_free, right = [], [], [], []
        nobody = ~np.any([r.local != UNKNOWN for r in holder["run"].team], axis=0)
        for view in snap.views:
            p = predict(shipped_predictor(), view)[1]
            filled = np.where(view == UNKNOWN, np.where(p > 0.5, IMPASSABLE, FREE), view)
            known = view != UNKNOWN
            assert np.array_equal(filled[known], view[known])  # a guess never overrides an observed cell
            scores = path_f1(truth.classes, filled, n_pairs=c.eval_pairs, seed=c.seed)
            f1s.append(scores.f1)
            successes.append(scores.success)
            free = filled == FREE
            false_free.append(float((free & (truth.classes == IMPASSABLE)).sum()) / max(int(free.sum()), 1))
            right.append(float((filled == truth.classes)[nobody].mean()) if nobody.any() else 1.0)
        want[snap.step] = (f1s, successes, false_free, right)

    holder: dict = {}
    holder["run"] = mission.new_run("raw", on_snapshot=look)
    run = holder["run"].run()
    ev = run.series.eval
    assert list(ev.step) == sorted(want) and ev.predicted_f1 is not None
    assert ev.predicted_success is not None and ev.predicted_false_free is not None
    for i, t in enumerate(ev.step):
        assert ev.predicted_f1[i] == pytest.approx(want[t][0])
        assert ev.predicted_success[i] == pytest.approx(want[t][1])
        assert ev.predicted_false_free[i] == pytest.approx(want[t][2])
        assert ev.predicted_accuracy_unobserved is not None
        assert ev.predicted_accuracy_unobserved[i] == pytest.approx(want[t][3])
    means = [float(np.mean(want[t][0][:c.rovers])) for t in ev.step]
    first = next((t for t, m in zip(ev.step, means) if m >= F1_GOAL), None)
    summary = run.summary.to_dict()["predicted_belief"]
    assert summary["f1_step"] == first and summary["final_f1"] == pytest.approx(means[-1])
    assert summary["final_false_free"] == pytest.approx(float(np.mean(want[ev.step[-1]][2][:c.rovers])))
    assert any(g != o for g, o in zip(ev.predicted_f1, ev.belief_f1))  # the guesses changed some plans
    plain = prepare_mission(replace(c, predictor="none"), truth, frames=1).new_run("raw").run()
    assert "predicted_belief" not in plain.summary.to_dict()
    assert "predicted_f1" not in plain.series.eval.to_dict()


def test_the_report_tables_the_beliefs_with_the_guesses_even_when_nothing_was_left_unobserved():
    """report.md gives each strategy's filled beliefs: the step their mean reached 0.9 beside the
    observed beliefs', and the final scores, from the summary; the table stays when no cell
    was left unobserved (no guesses to score at the end, but the beliefs were filled before)."""
    from dataclasses import replace as swap

    from fedmap.mission.outputs.report import report_md
    from fedmap.mission.sim import run_mission

    truth, mission = _small_mission("raw")
    result = run_mission(mission.config, truth, frames=1)
    s = result.runs["raw"].summary
    p = s.predicted_belief
    assert p is not None
    row = (f"| raw | {'-' if p['f1_step'] is None else p['f1_step']} | "
           f"{'-' if s.team_f1_step is None else s.team_f1_step} | {p['final_f1']:.2f} | {p['final_success']:.2f} | "
           f"{p['final_false_free']:.3f} |")
    assert row in report_md(result, title="t")
    run = result.runs["raw"]
    seen_all = swap(result, runs={"raw": swap(run, summary=swap(s, final_prediction=None))})
    text = report_md(seen_all, title="t")
    assert row in text and "**The map predictor's guesses**" not in text
    plain = run_mission(swap(mission.config, predictor="none"), truth, frames=1)
    assert "guesses filled in" not in report_md(plain, title="t")


def test_retraining_with_the_same_seed_gives_the_same_bytes(tmp_path):
    coll = earth_like(size=32, per_category=1, seed=0, categories=("urban", "natural"))
    beliefs, truths = exploration_samples(coll, steps=12, every=6, rovers=2)
    assert beliefs.shape == truths.shape and len(beliefs) == 2 * 2 * 2  # maps x snapshots x rovers
    small = PredictorConfig(stem=4, width=8, dilations=(1, 2))

    def fit(seed: int, name: str) -> bytes:
        t = PredictorTraining(steps=3, batch=2, crop=24, seed=seed)
        return save_predictor(train_predictor(beliefs, truths, config=small, training=t), tmp_path / name).read_bytes()

    first, again, other = fit(0, "a"), fit(0, "b"), fit(1, "c")
    assert first == again
    assert first != other
    assert count_parameters(load_predictor(tmp_path / "a")) == count_parameters(MapPredictor(small))


def test_user_mistakes_are_one_line_errors(tmp_path):
    with pytest.raises(FedmapError, match="did you mean 'learned'") as e:
        load_mission(mission={"predictor": "learnd"})
    assert "\n" not in str(e.value)
    with pytest.raises(FedmapError):
        MissionConfig(predictor="neural")
    config, _, resolved = load_mission(mission={"predictor": "learned"})
    assert config.predictor == "learned" and resolved["mission"]["predictor"] == "learned"
    assert "predictor" not in load_mission()[2]["mission"]  # unset: the settings missions had before
    (tmp_path / "bad.safetensors").write_bytes(b"not a model")
    for name, what in (("bad.safetensors", "not a fedmap predictor file"), ("missing", "no such predictor file")):
        with pytest.raises(FedmapError, match=what) as e:
            load_predictor(tmp_path / name)
        assert "\n" not in str(e.value)

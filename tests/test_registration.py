"""Registration of maps in unknown frames, its confidence gate, merging and ``fedmap merge``.

Independent references: ``numpy.rot90`` for the transform's conventions; ``scipy.ndimage.rotate``
(with the source of every cell read back from rotated index grids, so the true transform
is fitted from where the cells went, not computed with fedmap's conventions) for the
synthetic pairs; ``skimage.registration.phase_cross_correlation`` with masks for pure
shifts; Cohen's kappa worked by hand for the gate's statistic.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import ndimage
from skimage.registration import phase_cross_correlation

from fedmap.cli import main
from fedmap.errors import FedmapError
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN, GridMap
from fedmap.maps.io import load_map, save_map
from fedmap.maps.registration import Agreement, RigidTransform, agreement, combine, gate_verdict, merge, register
from fedmap.maps.sources import TerrainSource, load_truth

GALE = Path(__file__).resolve().parents[2] / "shared" / "data" / "mars" / "missionDEM_gale_1m.tif"


@pytest.fixture(scope="module")
def terrain() -> np.ndarray:
    """A seeded built-in Mars-like terrain, 256² classes (25 % impassable)."""
    return load_truth(TerrainSource(size=256), seed=3).classes


@pytest.fixture(scope="module")
def other_terrain() -> np.ndarray:
    """An unrelated terrain: the built-in Moon with another seed."""
    return load_truth(TerrainSource(size=256, terrain="moon"), seed=11).classes


def rotated_pair(terrain: np.ndarray, heading: float, a_box: tuple[int, int, int], offset: tuple[int, int]):
    """Map A = the ``n`` x ``n`` window of ``terrain`` at ``a_box = (row, col, n)``; map B = an
    ``n`` x ``n`` window of ``terrain`` turned by ``ndimage.rotate``, centred ``offset`` cells
    from where A's centre went.

    Returns A, B, and per cell of B the (row, col) in A's frame of the terrain cell it holds
    (read from index grids rotated by the same call: the ground truth) and whether it holds one."""
    rot = lambda x, cval: ndimage.rotate(x, heading, reshape=True, order=0, mode="constant", cval=cval)
    rows, cols = np.mgrid[0:terrain.shape[0], 0:terrain.shape[1]]
    t_rot, r_rot, c_rot = rot(terrain, UNKNOWN), rot(rows, -1), rot(cols, -1)
    ar, ac, n = a_box
    a = terrain[ar:ar + n, ac:ac + n].copy()
    went = np.unravel_index(np.argmin((r_rot - (ar + n // 2)) ** 2 + (c_rot - (ac + n // 2)) ** 2), r_rot.shape)
    br, bc = went[0] + offset[0] - n // 2, went[1] + offset[1] - n // 2
    assert br >= 0 and bc >= 0 and br + n <= t_rot.shape[0] and bc + n <= t_rot.shape[1]
    b = t_rot[br:br + n, bc:bc + n].copy()
    src = np.stack([r_rot[br:br + n, bc:bc + n] - ar, c_rot[br:br + n, bc:bc + n] - ac], axis=-1)
    valid = (r_rot[br:br + n, bc:bc + n] >= 0) & (b != UNKNOWN)
    return a, b, src, valid


def fit_rigid(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray]:
    """Least-squares rotation (degrees, counter-clockwise on (row, col)) and translation taking ``src`` to ``dst``."""
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    u, _, vt = np.linalg.svd((src - ms).T @ (dst - md))
    r = (u @ vt).T
    return float(np.degrees(np.arctan2(r[1, 0], r[0, 0])) % 360), md - r @ ms


def heading_gap(a: float, b: float) -> float:
    d = abs(a - b) % 360
    return min(d, 360 - d)


# --------------------------------------------------------------------------- the transform


def test_a_quarter_turn_is_rot90():
    b = np.random.default_rng(0).integers(0, 3, size=(7, 11)).astype(np.uint8)
    # numpy.rot90 turns counter-clockwise as drawn: B's cell (r, c) lands on (W - 1 - c, r)
    t = RigidTransform(dy=b.shape[1] - 1, dx=0, heading_deg=90)
    assert np.array_equal(t.apply(b, (11, 7)), np.rot90(b))
    assert np.array_equal(RigidTransform().apply(b, b.shape), b)
    shifted = RigidTransform(dy=2, dx=3).apply(b, (9, 14))  # UNKNOWN where B has no cell
    assert np.array_equal(shifted[2:, 3:], b) and (shifted[:2] == UNKNOWN).all() and (shifted[:, :3] == UNKNOWN).all()


@given(st.floats(0, 360), st.floats(-50, 50), st.floats(-50, 50), st.floats(0, 360), st.floats(-50, 50))
def test_compose_and_inverse(h1, y1, x1, h2, y2):
    t, u = RigidTransform(y1, x1, h1), RigidTransform(y2, -y1, h2)
    p = np.array([[3.0, -4.0], [10.0, 20.0]])
    assert np.allclose(t.compose(u).map_points(p), t.map_points(u.map_points(p)))
    assert np.allclose(t.inverse().map_points(t.map_points(p)), p)


# --------------------------------------------------------------------------- the gate statistic


def test_kappa_by_hand():
    F, X, U = FREE, IMPASSABLE, UNKNOWN
    a = np.array([[F, F, X, X, U]], dtype=np.uint8)
    b = np.array([[F, X, X, X, F]], dtype=np.uint8)
    c = agreement(a, b)
    # 4 shared cells, 3 agree; pA(I) = 2/4, pB(I) = 3/4: chance = .5 * .75 + .5 * .25 = .5; kappa = (.75 - .5) / .5
    assert (c.overlap, c.agree, c.chance, c.kappa, c.minority) == (4, 0.75, 0.5, 0.5, 1)
    # the same statistics on 100 copies: enough cells of each class for the gate
    big = agreement(np.tile(a, (100, 1)), np.tile(b, (100, 1)))
    assert (big.overlap, big.kappa, big.minority) == (400, 0.5, 100)
    assert gate_verdict(big, gate=0.5, min_overlap=400) == (True, "")
    assert "below the gate" in gate_verdict(big, gate=0.6, min_overlap=400)[1]
    assert "fewer than 401" in gate_verdict(big, gate=0.5, min_overlap=401)[1]
    assert "ambiguous" in gate_verdict(big, 1.0, gate=0.5, min_overlap=400, min_margin=2.0)[1]
    assert "too little" in gate_verdict(c, gate=0.5, min_overlap=4)[1]  # one impassable cell in B
    one_class = agreement(np.zeros((3, 3), np.uint8), np.zeros((3, 3), np.uint8))
    assert one_class.kappa == 0.0 and one_class.minority == 0


def test_evidence_weighs_a_large_overlap_against_a_close_sliver():
    """The gate's evidence, ``kappa ** 2 * sqrt(shared cells)``: a right placement on a large
    overlap of speckled or blobby maps (numbers from the registration benchmark's misses
    under the earlier fourth power) beats a close fit on a sliver; a close fit still beats
    a loose one on a few more cells, and too few cells of a class are no evidence."""
    ev = lambda kappa, n, minority=200: Agreement(n, 0.0, 0.0, kappa, minority).evidence
    assert ev(0.49, 5566) == pytest.approx(0.49**2 * 5566**0.5)
    assert ev(0.49, 5566) > ev(0.71, 672) and ev(0.70, 5067) > ev(0.91, 657) and ev(0.53, 4749) > ev(0.64, 682)
    assert ev(0.85, 2000) > ev(0.60, 3000)
    assert ev(0.9, 5000, minority=49) == 0.0 and ev(-0.2, 5000) == 0.0


# --------------------------------------------------------------------------- estimates


@settings(max_examples=4, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(heading=st.floats(0.0, 359.0), drow=st.integers(-40, 40), dcol=st.integers(-40, 40))
def test_recovers_a_known_rotation_and_shift(terrain, heading, drow, dcol):
    n = 96
    a, b, src, valid = rotated_pair(terrain, heading, (80, 80, n), (drow, dcol))
    rc = np.argwhere(valid)
    true_heading, _ = fit_rigid(rc.astype(float), src[valid].astype(float))
    # ndimage.rotate turns the terrain counter-clockwise as drawn, so B's frame goes back by -heading
    assert heading_gap(true_heading, -heading) < 0.5
    reg = register(a, b)
    assert reg.accepted, reg.reason
    assert heading_gap(reg.transform.heading_deg, true_heading) <= 2.0
    on_a = np.all((src[valid] >= 0) & (src[valid] < n), axis=1)  # B's cells that lie on A: the true overlap
    err = np.linalg.norm(reg.transform.map_points(rc[on_a]) - src[valid][on_a], axis=1)
    assert np.median(err) <= 1.0, np.median(err)


def test_a_pure_shift_matches_skimage_masked_phase_correlation(terrain):
    a = terrain[40:140, 40:140].copy()
    b = terrain[63:163, 29:129].copy()
    a[:, 80:] = UNKNOWN  # unknown cells on both sides: the masked correlation ignores them
    b[:15] = UNKNOWN
    ref, _, _ = phase_cross_correlation((a == IMPASSABLE).astype(float), (b == IMPASSABLE).astype(float),
                                        reference_mask=a != UNKNOWN, moving_mask=b != UNKNOWN)
    reg = register(a, b)
    assert reg.accepted, reg.reason
    # skimage's shift moves B onto A; ours maps B's cells into A's frame: the same numbers
    assert np.allclose(ref, [23, -11])
    assert heading_gap(reg.transform.heading_deg, 0.0) <= 1.0
    assert np.allclose([reg.transform.dy, reg.transform.dx], ref, atol=1.0)


def test_unrelated_terrains_are_refused(terrain, other_terrain):
    reg = register(terrain[:128, :128], other_terrain[100:228, 60:188])
    assert not reg.accepted and reg.reason


def test_disjoint_crops_are_refused(terrain):
    b = ndimage.rotate(terrain[140:, 140:], 30, reshape=False, order=0, cval=UNKNOWN)
    reg = register(terrain[:112, :112], b)
    assert not reg.accepted and reg.reason


def test_no_shared_cells_is_refused():
    a = np.full((64, 64), UNKNOWN, np.uint8)
    a[:10, :10] = FREE
    reg = register(a, a.copy())
    assert not reg.accepted and "fewer than" in reg.reason


def test_different_cell_sizes_are_an_error():
    c = np.zeros((32, 32), np.uint8)
    with pytest.raises(FedmapError, match="same cell size"):
        register(GridMap(c, 1.0), GridMap(c, 2.0))
    with pytest.raises(FedmapError, match="at least two"):
        merge([GridMap(c, 1.0)])


# --------------------------------------------------------------------------- merging


@given(st.integers(0, 2**32 - 1))
def test_combine_never_puts_free_on_a_hazard(seed):
    rng = np.random.default_rng(seed)
    base, new = rng.integers(0, 3, size=(2, 12, 12)).astype(np.uint8)
    out = combine(base, new)
    hazard = (base == IMPASSABLE) | (new == IMPASSABLE)
    assert (out[hazard] == IMPASSABLE).all()
    assert np.array_equal(out[~hazard], np.where(base == UNKNOWN, new, base)[~hazard])


def test_merge_grows_the_canvas_and_keeps_every_hazard(terrain):
    a = terrain[40:140, 40:140].copy()
    b = terrain[90:190, 100:200].copy()
    a[50:60, 70:90] = IMPASSABLE  # A says hazard where B says free ...
    b[0:10, 10:30] = FREE  # ... the same cells in B's frame
    result = merge([GridMap(a, 2.0, "a"), GridMap(b, 2.0, "b")])
    assert [p.placed for p in result.placements] == [True, True]
    t = result.placements[1].transform
    assert t is not None and heading_gap(t.heading_deg, 0) <= 1 and np.allclose([t.dy, t.dx], [50, 60], atol=1)
    g = result.grid
    assert g.shape == (150, 160) and g.pixel_size == 2.0 and result.origin == (0, 0)
    assert (g.classes[50:60, 70:90] == IMPASSABLE).all()
    # every placed map's hazards are hazards of the merged map
    warped = t.apply(b, g.shape)
    assert (g.classes[warped == IMPASSABLE] == IMPASSABLE).all()
    assert (g.classes[:100, :100][a == IMPASSABLE] == IMPASSABLE).all()


def test_merge_refuses_what_it_cannot_place(terrain, other_terrain):
    maps = [GridMap(terrain[:100, :100], 1.0, "a"), GridMap(other_terrain[:100, :100], 1.0, "stranger"),
            GridMap(terrain[60:160, 50:150], 1.0, "b")]
    result = merge(maps)
    assert [p.placed for p in result.placements] == [True, False, True]
    assert result.placements[1].reason and result.n_placed == 2


# --------------------------------------------------------------------------- fedmap merge


@pytest.mark.parametrize("suffix", [".png", ".tif", ".yaml"])
def test_cli_merge_round_trips(tmp_path, capsys, terrain, suffix):
    a, b = terrain[30:130, 30:130], terrain[70:170, 90:190]
    save_map(GridMap(a, 1.0, "a"), tmp_path / "a.png")
    save_map(GridMap(b, 1.0, "b"), tmp_path / "b.png")
    out = tmp_path / f"merged{suffix}"
    assert main(["merge", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "b.png" in printed and "yes" in printed and "refused" not in printed
    merged = load_map(out).classes
    expected = np.full((140, 160), UNKNOWN, np.uint8)  # the union of the two windows of the terrain
    expected[:100, :100] = a
    expected[40:, 60:] = b
    assert np.array_equal(merged, expected)


def test_cli_bad_input_is_one_line_and_keeps_the_output(tmp_path, capsys, terrain):
    save_map(GridMap(terrain[:100, :100], 1.0, "a"), tmp_path / "a.png")
    (tmp_path / "bad.png").write_bytes(b"not a png at all")
    out = tmp_path / "merged.png"
    out.write_bytes(b"previous result")
    cases = [["a.png", "bad.png"], ["a.png", "missing.png"], ["a.png"], ["a.png", "a.png", "--gate", "2"],
             ["a.png", "a.png", "-o", str(tmp_path / "merged.jpg")]]
    for args in cases:
        args = [str(tmp_path / a) if a.endswith(".png") else a for a in args]
        assert main(["merge", *args, "-o", str(out)] if "-o" not in args else ["merge", *args]) == 2, args
        err = capsys.readouterr().err
        assert err.startswith("error: ") and len(err.strip().splitlines()) == 1, err
        assert out.read_bytes() == b"previous result"
    # the installed command, end to end: one line, no traceback
    r = subprocess.run([sys.executable, "-m", "fedmap", "merge", "a.png", "bad.png", "-o", str(out)], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.startswith("error: cannot read map bad.png"), r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr
    assert out.read_bytes() == b"previous result"


def test_cli_nothing_placed_writes_nothing(tmp_path, capsys, terrain, other_terrain):
    save_map(GridMap(terrain[:100, :100], 1.0, "a"), tmp_path / "a.png")
    save_map(GridMap(other_terrain[:100, :100], 1.0, "x"), tmp_path / "x.png")
    out = tmp_path / "merged.png"
    assert main(["merge", str(tmp_path / "a.png"), str(tmp_path / "x.png"), "-o", str(out)]) == 2
    captured = capsys.readouterr()
    assert "refused" in captured.out and "nothing merged" in captured.err
    assert not out.exists()


# --------------------------------------------------------------------------- real terrain


@pytest.mark.skipif(not GALE.exists(), reason="shared/data is not beside the repo")
def test_gale_pair_is_registered():
    from fedmap.maps.io import load_dem
    from fedmap.maps.traversability import dem_to_traversability

    gale = dem_to_traversability(load_dem(GALE)).classes  # 337 x 348 cells of 1 m
    a, b, src, valid = rotated_pair(gale, 57.0, (40, 60, 128), (30, -45))
    rc = np.argwhere(valid)
    true_heading, _ = fit_rigid(rc.astype(float), src[valid].astype(float))
    reg = register(a, b)
    assert reg.accepted, reg.reason
    assert heading_gap(reg.transform.heading_deg, true_heading) <= 2.0
    on_a = np.all((src[valid] >= 0) & (src[valid] < 128), axis=1)
    assert np.median(np.linalg.norm(reg.transform.map_points(rc[on_a]) - src[valid][on_a], axis=1)) <= 1.0


@pytest.mark.parametrize("seed", [0, 1, 3])
def test_exact_cuts_of_one_map_turned_by_right_angles_are_placed_exactly(seed):
    """`fedmap merge` placed exact cuts of a mission's map one cell off (kappa 0.6-0.76, the
    true placement 1.0): the search's shift sat on a cell boundary, and nearest-neighbour
    warping rounded the whole map one way. Every cut at 0, 90, 180 and 270 degrees now lands
    each of its known cells on the same cell of the first map."""
    from fedmap.maps.terrain import generate_dem
    from fedmap.maps.traversability import dem_to_traversability

    truth = dem_to_traversability(generate_dem("mars", 128, seed=seed)).classes
    rng = np.random.default_rng(seed)
    rr, cc = np.indices(truth.shape)
    seen = np.zeros(truth.shape, bool)
    for _ in range(60):  # what rovers observed: sensor disks here and there
        r, c = rng.integers(0, 128, 2)
        seen |= (rr - r) ** 2 + (cc - c) ** 2 <= 64
    g = np.where(seen, truth, UNKNOWN).astype(np.uint8)
    a = g[:90, :90]
    for k in range(4):
        reg = register(a, np.rot90(g[30:128, 25:123], k))
        placed = reg.transform.apply(np.rot90(g[30:128, 25:123], k), a.shape)
        both = (placed != UNKNOWN) & (a != UNKNOWN)
        assert reg.accepted and both.sum() > 1000, k
        np.testing.assert_array_equal(placed[both], a[both])
        assert reg.transform.heading_deg == pytest.approx((-90 * k) % 360, abs=0.5)  # B turned back onto A


def test_a_merge_says_how_many_known_cells_a_placed_map_changed(tmp_path, capsys):
    """The merge never overwrites a known cell of the maps placed before without saying so:
    a cut that marks 7 of the first map's free cells impassable is placed, and the count is
    reported (by hand: the 7 cells, and only them, changed)."""
    from fedmap.maps.terrain import generate_dem
    from fedmap.maps.traversability import dem_to_traversability

    g = dem_to_traversability(generate_dem("mars", 96, seed=2)).classes
    a, b = g[:70, :70].copy(), g[20:96, 15:91].copy()
    free = np.argwhere(b[:50, :50] == FREE)[:7]  # cells both maps hold (b's (r, c) is a's (r + 20, c + 15))
    b[free[:, 0], free[:, 1]] = IMPASSABLE
    result = merge([GridMap(a, 1.0, "a"), GridMap(b, 1.0, "b")])
    assert result.placements[1].placed and result.placements[1].changed == 7
    save_map(GridMap(a, 1.0), tmp_path / "a.npy")
    save_map(GridMap(b, 1.0), tmp_path / "b.npy")
    assert main(["merge", str(tmp_path / "a.npy"), str(tmp_path / "b.npy"), "-o", str(tmp_path / "m.npy")]) == 0
    assert "changed 7 known cell(s) of the maps placed before it" in " ".join(capsys.readouterr().out.split())


def _correlation_area_by_hand(c: np.ndarray, max_lag: int) -> float:
    """:func:`correlation_area` with loops over every pair of known cells (no FFT)."""
    h, w = c.shape
    known = c != UNKNOWN
    x = (c == IMPASSABLE).astype(float)
    p = x[known].mean()
    rho = {}
    for dy in range(-max_lag, max_lag + 1):
        for dx in range(-max_lag, max_lag + 1):
            total, count = 0.0, 0
            for r in range(h):
                for q in range(w):
                    r2, q2 = r + dy, q + dx
                    if 0 <= r2 < h and 0 <= q2 < w and known[r, q] and known[r2, q2]:
                        total += (x[r, q] - p) * (x[r2, q2] - p)
                        count += 1
            rho[dy, dx] = total / count / (p * (1 - p)) if count >= 50 else 0.0
    rings: dict[int, list[float]] = {}
    for (dy, dx), v in rho.items():
        rings.setdefault(int(np.rint(np.hypot(dy, dx))), []).append(v)
    cut = next((k for k in sorted(rings) if np.mean(rings[k]) <= 0), max_lag + 1)
    return max(sum(v for (dy, dx), v in rho.items() if np.rint(np.hypot(dy, dx)) < cut), 1.0)


@pytest.mark.parametrize("sigma", [0.0, 1.5, 3.0])
def test_the_correlation_area_matches_a_sum_over_every_pair_of_cells(sigma):
    from fedmap.maps.registration import correlation_area

    rng = np.random.default_rng(7)
    field = ndimage.gaussian_filter(rng.random((26, 22)), sigma) if sigma else rng.random((26, 22))
    c = np.where(field > np.median(field), IMPASSABLE, FREE).astype(np.uint8)
    c[rng.random(c.shape) < 0.2] = UNKNOWN
    got = correlation_area(c, max_lag=7)
    assert got == pytest.approx(_correlation_area_by_hand(c, 7), rel=1e-9)
    assert (got < 3.0) if sigma == 0.0 else (got > 5.0)  # white noise: about one cell; blobs: many


def test_a_placement_on_few_independent_patches_of_smooth_terrain_is_flagged(tmp_path, capsys):
    """A window of Hadley 118 m was merged with another window of it that it never met (kappa
    0.72 on 4,309 cells): on smooth maps a look-alike place can beat every other place by the
    margin. Such placements cannot be refused without refusing most right ones there, so the
    merge says on how many independent patches of terrain it rests: the same cut placed on a
    speckled map (many patches) gets no note, on a map of blobs 10 cells across it does."""
    rng = np.random.default_rng(5)
    noise = rng.random((200, 200))
    for sigma, weak in ((1.5, False), (7.0, True)):
        t = np.where(ndimage.gaussian_filter(noise, sigma) > 0.5, IMPASSABLE, FREE).astype(np.uint8)
        a, b = t[:128, :128].copy(), np.rot90(t[64:192, 60:188]).copy()
        save_map(GridMap(a, 1.0), tmp_path / "a.npy")
        save_map(GridMap(b, 1.0), tmp_path / "b.npy")
        reg = register(a, b)
        assert reg.accepted and reg.confidence > 0.95
        assert reg.weak == weak and (reg.patches < 10) == weak
        assert main(["merge", str(tmp_path / "a.npy"), str(tmp_path / "b.npy"), "-o", str(tmp_path / "m.npy")]) == 0
        out = " ".join(capsys.readouterr().out.split())
        assert ("was placed on about" in out) == weak, out

"""The mission link's topology: StarTopology against brute force, and the link asking it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fedmap.mission import LinkConfig
from fedmap.mission.network.link import BASE, UP, Link
from fedmap.mission.network.topology import StarTopology, Topology


def _within(p, base, max_range) -> bool:
    """Brute force: Euclidean distance in cells, at most the range (None: no limit)."""
    if max_range is None:
        return True
    d = math.sqrt((p[0] - base[0]) ** 2 + (p[1] - base[1]) ** 2)
    return d <= max_range or math.isclose(d, max_range)


@pytest.mark.parametrize("seed", range(6))
def test_star_topology_matches_brute_force_on_random_positions(seed):
    rng = np.random.default_rng(seed)
    shape = (int(rng.integers(5, 40)), int(rng.integers(5, 40)))
    base = (int(rng.integers(0, shape[0])), int(rng.integers(0, shape[1])))
    for max_range in (None, 0.5, 5.0, float(rng.uniform(1, 30)), math.sqrt(rng.integers(1, 400))):
        topo = StarTopology(base, max_range)
        for _ in range(20):
            n = int(rng.integers(1, 7))
            positions = [(int(r), int(c)) for r, c in zip(rng.integers(0, shape[0], n), rng.integers(0, shape[1], n))]
            want = tuple(_within(p, base, max_range) for p in positions)
            assert topo.reachable(positions) == want
            # a star: rovers talk to the base only, never to each other
            for k in range(n):
                assert topo.neighbours(k, positions) == ((BASE,) if want[k] else ())
            assert topo.neighbours(BASE, positions) == tuple(k for k in range(n) if want[k])
        region = topo.region(shape)
        if max_range is None:
            assert region is None
        else:
            assert region is not None and region.shape == shape
            for r in range(shape[0]):
                for c in range(shape[1]):
                    assert region[r, c] == _within((r, c), base, max_range)


def test_star_topology_at_exactly_the_range():
    topo = StarTopology((0, 0), 5.0)
    assert topo.reachable([(3, 4), (0, 5), (4, 4), (5, 1)]) == (True, True, False, False)
    assert topo.region((7, 7))[3, 4] and not topo.region((7, 7))[4, 4]


class _Only:
    """A topology where only the given rovers reach the base (a stand-in for another implementation)."""

    def __init__(self, ok: set[int]) -> None:
        self.ok = ok

    def neighbours(self, agent, positions):
        return (BASE,) if agent in self.ok else ()

    def reachable(self, positions):
        return tuple(k in self.ok for k in range(len(positions)))

    def region(self, shape):
        return None


def test_the_link_asks_its_topology():
    only: Topology = _Only({0, 2})
    link = Link(LinkConfig(loss=0.0), only)
    positions = [(0, 0), (0, 0), (0, 0)]
    fates = [link.send(b"x", round_no=1, step=1, rover=k, direction=UP, kind="cells", positions=positions).status
             for k in range(3)]
    assert fates == ["delivered", "out of range", "delivered"]
    assert [m.bytes for m in link.ledger] == [1, 0, 1]
    # the star decides by distance from the base
    star = Link(LinkConfig(loss=0.0, max_range=2.0), StarTopology((0, 0), 2.0))
    far = star.send(b"x", round_no=1, step=1, rover=1, direction=UP, kind="cells", positions=[(0, 0), (3, 0)])
    near = star.send(b"x", round_no=1, step=1, rover=0, direction=UP, kind="cells", positions=[(0, 0), (3, 0)])
    assert (far.status, near.status) == ("out of range", "delivered")

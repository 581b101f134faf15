import os

# Under pytest-xdist (three workers on two cores, see addopts in pyproject.toml) every
# worker, and every process a test starts (rovers, CLI runs), trains with one torch thread:
# two threads per worker only wait on each other, and a test that compares a subprocess's
# model with an in-process one needs both on the same thread count.
WORKER = bool(os.environ.get("PYTEST_XDIST_WORKER"))
if WORKER:
    os.environ["OMP_NUM_THREADS"] = "1"

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

from fedmap.maps.grid import FREE, IMPASSABLE, GridMap  # noqa: E402
from fedmap.nets.model import NetConfig  # noqa: E402

THREADS = 1 if WORKER else 2
torch.set_num_threads(THREADS)


@pytest.fixture(autouse=True)
def _torch_threads_stay_put():
    """A command run in-process may set torch's thread count (``--threads``): put it back, so
    one test cannot leave a worker on two threads that wait on each other under load (a
    worker left on 2 threads made a later 4 s test take 300 s)."""
    yield
    if torch.get_num_threads() != THREADS:
        torch.set_num_threads(THREADS)


def compile_fedmap() -> None:
    """fedmap's sources compiled to bytecode (``__pycache__``, ignored by git) where they are
    not yet.

    Python writes bytecode as it imports, unless told not to (``PYTHONDONTWRITEBYTECODE``, set
    in the shells our CI runs in). Then every process that imports fedmap compiles its sources
    again, and the suite starts hundreds: the CLI runs, and in each loopback mission the rover
    wrappers, the ServerApp, the SuperNodes. Existing bytecode is read all the same. One
    deployed default mission (``test_the_default_mission_on_processes_equals_the_mission_in_process``,
    ``-n 0``, Zen 4) used 85.0-100.2 s of CPU without it and 74.8-75.7 s with it."""
    import compileall
    from pathlib import Path

    import fedmap

    compileall.compile_dir(Path(fedmap.__file__).parent, quiet=2)  # a read-only install has its bytecode


def pytest_configure(config):
    """Before any worker starts (in the controlling process, or the one process with ``-n
    0``): fedmap's bytecode written (:func:`compile_fedmap`), and its numba kernels compiled
    once into their on-disk cache. On a clean clone the numba cache is empty, and every
    worker and every rover process started before the first had written it compiled them
    itself: 3.5 s of CPU each (5.5 s against 2.0 s for the
    planners' warm-up, measured with an empty ``NUMBA_CACHE_DIR``), on a 2-core machine
    already running three workers."""
    if WORKER:
        return
    compile_fedmap()
    from fedmap.evaluation.metrics import image_scores
    from fedmap.mission.network.remote import warm_up

    warm_up()  # the planners: target choice, travel costs, A*
    for side in (8, 160):  # SSIM from classes, in one thread and (maps of 134 cells and more) in two
        image_scores(np.zeros((side, side), np.uint8), np.zeros((side, side), np.uint8))


def pytest_collection_modifyitems(config, items):
    """The loopback lanes (``xdist_group`` "loopback-a" / "-b" / "-c", see addopts in
    pyproject.toml) first, in lane order, then the other ``slow`` tests, then the rest:
    pytest-xdist hands out work in collection order, so each worker starts on its lane at
    once and the short tests fill the gaps around them. A lane reached only after the short
    tests before it ends the run minutes later, and so does a long test handed out last: the
    reproduction's CLI run (55 s under load), last in the alphabet, ran alone at the end of
    the suite for 17 s. The order of tests within a lane and within the rest is kept (a stable
    sort)."""
    def order(item) -> tuple[int, str]:
        mark = item.get_closest_marker("xdist_group")
        if mark:
            return 0, str(mark.args[0])
        return (1 if item.get_closest_marker("slow") else 2), ""

    items.sort(key=order)


#: A small network so tests of training and federation run in milliseconds.
TINY_NET = NetConfig(mapping_size=16, hidden=32)


@pytest.fixture
def tiny_net() -> NetConfig:
    return TINY_NET


@pytest.fixture
def blob_map() -> GridMap:
    """24x24 map: free ground with two impassable rectangles."""
    c = np.full((24, 24), FREE, dtype=np.uint8)
    c[3:9, 4:12] = IMPASSABLE
    c[14:20, 13:21] = IMPASSABLE
    return GridMap(c, 1.0, "blobs")


def maze(n: int = 40, seed: int = 3, blocks: int = 12) -> GridMap:
    """A free map with a few seeded walls and blocks, and a free pad at its centre (the lander's)."""
    rng = np.random.default_rng(seed)
    c = np.zeros((n, n), dtype=np.uint8)
    for _ in range(blocks):
        r0, c0 = rng.integers(0, n - 6, size=2)
        c[r0:r0 + rng.integers(1, 6), c0:c0 + rng.integers(1, 6)] = IMPASSABLE
    c[n // 2 - 2:n // 2 + 3, n // 2 - 2:n // 2 + 3] = FREE  # the lander's pad
    return GridMap(c, 1.0, "test maze")

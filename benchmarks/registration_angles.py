"""How precisely `register` places an exact cut of a map turned by a random angle.

    python benchmarks/registration_angles.py [--pairs 10] [--seed 1]

Map A is a 96 x 96 window of the built-in Mars-like terrain (256², seed 3); map B a 96 x 96
window of the same terrain turned by a random heading (``scipy.ndimage.rotate``, nearest
neighbour) and shifted up to 40 cells. Every cell of B knows which terrain cell it holds,
so the truth is exact: the heading is the least-squares rotation of those cells, and each
of B's cells on A has its true place. Prints per pair the heading error (degrees) and the
median and 90th percentile of the distance (cells) from where the estimate puts B's cells
to where they belong. Nearest-neighbour turning moves cells by up to half a cell itself.
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy import ndimage

from fedmap.maps.grid import UNKNOWN
from fedmap.maps.registration import register
from fedmap.maps.sources import TerrainSource, load_truth


def turned_pair(terrain: np.ndarray, heading: float, corner: tuple[int, int], n: int, offset: tuple[int, int]):
    """A, B, and per cell of B the (row, col) in A's frame of the terrain cell it holds, and whether it holds one."""
    def rot(x, cval):
        return ndimage.rotate(x, heading, reshape=True, order=0, mode="constant", cval=cval)

    rows, cols = np.mgrid[0:terrain.shape[0], 0:terrain.shape[1]]
    t_rot, r_rot, c_rot = rot(terrain, UNKNOWN), rot(rows, -1), rot(cols, -1)
    ar, ac = corner
    a = terrain[ar:ar + n, ac:ac + n].copy()
    went = np.unravel_index(np.argmin((r_rot - (ar + n // 2)) ** 2 + (c_rot - (ac + n // 2)) ** 2), r_rot.shape)
    br, bc = went[0] + offset[0] - n // 2, went[1] + offset[1] - n // 2
    b = t_rot[br:br + n, bc:bc + n].copy()
    src = np.stack([r_rot[br:br + n, bc:bc + n] - ar, c_rot[br:br + n, bc:bc + n] - ac], axis=-1)
    return a, b, src, (r_rot[br:br + n, bc:bc + n] >= 0) & (b != UNKNOWN)


def rigid_heading(src: np.ndarray, dst: np.ndarray) -> float:
    """Least-squares rotation (degrees) taking points ``src`` to ``dst`` (Kabsch)."""
    u, _, vt = np.linalg.svd((src - src.mean(axis=0)).T @ (dst - dst.mean(axis=0)))
    r = (u @ vt).T
    return float(np.degrees(np.arctan2(r[1, 0], r[0, 0])) % 360)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--pairs", type=int, default=10)
    p.add_argument("--seed", type=int, default=1)
    args = p.parse_args()
    terrain = load_truth(TerrainSource(size=256), seed=3).classes
    rng = np.random.default_rng(args.seed)
    n, errors = 96, []
    print("heading  accepted  heading error  median cells  p90 cells")
    for _ in range(args.pairs):
        heading = float(rng.uniform(0.0, 359.0))
        offset = (int(rng.integers(-40, 41)), int(rng.integers(-40, 41)))
        a, b, src, valid = turned_pair(terrain, heading, (80, 80), n, offset)
        rc = np.argwhere(valid)
        truth = rigid_heading(rc.astype(float), src[valid].astype(float))
        reg = register(a, b)
        gap = abs((reg.transform.heading_deg - truth + 180.0) % 360.0 - 180.0)
        on_a = np.all((src[valid] >= 0) & (src[valid] < n), axis=1)
        err = np.linalg.norm(reg.transform.map_points(rc[on_a]) - src[valid][on_a], axis=1)
        errors.append((gap, float(np.median(err))))
        print(f"{heading:7.1f}  {str(reg.accepted):8s}  {gap:13.2f}  {np.median(err):12.2f}  {np.percentile(err, 90):9.2f}")
    gaps, medians = zip(*errors)
    print(f"heading error at most {max(gaps):.2f} deg ({sum(g > 0.5 for g in gaps)} of {len(gaps)} above 0.5); "
          f"median cell error at most {max(medians):.2f} ({sum(m > 0.5 for m in medians)} above 0.5)")


if __name__ == "__main__":
    main()

"""How much does noise removal damage a *perfect* map? Refine the ground truth itself.

    python benchmarks/refine_truth.py

Prints, per built-in terrain and size, path F1 / PSNR of refine(truth) against truth for
several ``min_size`` values. A filter that hurts the truth will hurt a good learned map.
"""

from fedmap.evaluation.scores import score_map
from fedmap.maps.sources import TerrainSource, load_truth
from fedmap.refine import RefineConfig, refine

SIZES = (0, 4, 8, 16, 50, 200)

print(f"{'terrain':8} {'size':>5} {'imp.':>5}  " + "  ".join(f"min_size={m:<3} F1/PSNR" for m in SIZES))
for kind in ("mars", "moon", "ice"):
    for size in (128, 256):
        truth = load_truth(TerrainSource(terrain=kind, size=size))
        cells = []
        for m in SIZES:
            e = score_map(truth.classes, refine(truth.classes, RefineConfig(min_size=m)), pairs=75, seed=0)
            cells.append(f"{e.path.f1:>15.2f}/{e.psnr:<5.1f}")
        print(f"{kind:8} {size:>5} {truth.fractions()['impassable']:>5.2f}  " + "  ".join(cells), flush=True)

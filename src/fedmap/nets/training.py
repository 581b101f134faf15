"""Local training: fit a coordinate network to one map (Adam + MSE on the RGB rendering).

This is the one implementation of local fitting; the in-process federation runner and
the Flower apps both call :func:`fit`.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import os
import platform
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass

import numpy as np
import torch

from fedmap._schema import setting
from fedmap._util import compiled_once
from fedmap.errors import FedmapError, RejectedUpdate
from fedmap.maps.grid import GridMap
from fedmap.nets.model import CoordNet, GridNet, grid_coords

#: Training precisions: ``auto`` resolves to ``bf16`` or ``fp32`` (:func:`resolve_precision`).
PRECISIONS = ("auto", "bf16", "fp32")


@dataclass(frozen=True)
class TrainConfig:
    """Local optimisation settings: the ``[train]`` section of a run config.

    With ``batch`` unset (the paper's setup) one epoch is one Adam step on the full grid;
    otherwise one epoch is a seeded random permutation of all pixels cut into batches of
    ``batch`` cells. ``masked=False`` trains on every cell, UNKNOWN ones towards grey
    (the paper); ``masked=True`` puts the loss on known cells only. ``precision`` is the
    arithmetic of the training step (:data:`PRECISIONS`): ``fp32`` everywhere, or
    ``bf16`` matrix products (bfloat16 autocast; weights, optimiser state, loss and
    rendering stay fp32). ``auto`` becomes ``bf16`` where the CPU multiplies bfloat16
    natively (AVX-512 BF16 or AMX) and ``fp32`` elsewhere; the config always holds the
    resolved value, so ``config.json`` and checkpoints record what ran.
    """

    epochs: int = setting(100, help="Local epochs per round E (passes over the rover's map)", cli="--local-epochs")
    lr: float = setting(1e-3, help="Local Adam learning rate")
    batch: int | None = setting(None, help="Cells per training batch (unset or 0: one full-grid step per epoch)")
    masked: bool = setting(False, help="Loss on known cells only (off: UNKNOWN cells are trained towards grey)")
    precision: str = setting("auto", help="Training arithmetic (auto: bf16 matrix products where the CPU has native "
                             "bf16, else fp32)", choices=PRECISIONS)

    def __post_init__(self) -> None:
        object.__setattr__(self, "precision", resolve_precision(self.precision))
        if self.batch == 0:
            object.__setattr__(self, "batch", None)
        if self.epochs < 0:
            raise FedmapError(f"local epochs must be >= 0, got {self.epochs}")
        if not self.lr > 0:
            raise FedmapError(f"learning rate must be positive, got {self.lr}")
        if self.batch is not None and self.batch <= 1:
            raise FedmapError(f"batch must be > 1 cells (BatchNorm needs a batch), got {self.batch}")

    def to_dict(self) -> dict:
        return asdict(self)




def native_bf16() -> bool:
    """True when this CPU multiplies bfloat16 natively (AVX-512 BF16 or AMX tiles).

    Elsewhere bf16 is emulated and slower than fp32, so ``auto`` keeps fp32 there.
    """
    cpu = torch.cpu
    return bool(getattr(cpu, "_is_avx512_bf16_supported", lambda: False)()
                or getattr(cpu, "_is_amx_tile_supported", lambda: False)())


def resolve_precision(name: str) -> str:
    """``auto`` -> ``bf16`` on a CPU with native bf16, else ``fp32``; other names are checked."""
    if name not in PRECISIONS:
        raise FedmapError(f"unknown precision {name!r}; choose one of {', '.join(PRECISIONS)}")
    if name == "auto":
        return "bf16" if native_bf16() else "fp32"
    return name


def precision_reason(name: str, *, grid: bool = False) -> str:
    """The precision a run asked for as ``name`` (:data:`PRECISIONS`) trains in, and why, in
    words for the console: ``fp32 (auto): this CPU has no native bf16 (no AVX-512 BF16 or
    AMX); bf16 would be emulated and slower``. ``grid``: the network is feature grids, which
    train in fp32 whatever the setting (:func:`fit`). Follows :func:`native_bf16`, as
    :func:`resolve_precision` does.
    """
    used, native = resolve_precision(name), native_bf16()
    cpu = ("this CPU multiplies bfloat16 natively (AVX-512 BF16 or AMX)" if native
           else "this CPU has no native bf16 (no AVX-512 BF16 or AMX)")
    if grid:
        return ("fp32: feature grids always train in fp32 (their step is bilinear sampling, not matrix products, "
                "where bf16 does not pay)" + ("; the bf16 asked is for Fourier networks" if name == "bf16" else ""))
    if name == "auto":
        return f"{used} (auto): {cpu}" + ("" if native else "; bf16 would be emulated and slower")
    if used == "bf16":
        return f"bf16, as asked; {cpu}" + ("" if native else ", so bf16 is emulated and slower than fp32")
    return f"fp32, as asked; {cpu}" + ("; auto would train in bf16" if native else "")


def _tunable_glibc() -> ctypes.CDLL | None:
    """glibc, where the allocator may be tuned: Linux with glibc, unless ``FEDMAP_MALLOC_TUNING=0``."""
    if os.environ.get("FEDMAP_MALLOC_TUNING", "1") == "0":
        return None
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        return ctypes.CDLL("libc.so.6")
    except OSError:
        return None


@functools.cache
def keep_freed_memory() -> bool:
    """Let glibc reuse freed memory for the next large tensor instead of returning it to the OS.

    A full-grid step allocates and frees tensors of tens of MB (``N x 256`` activations and
    their gradients). glibc serves blocks that large with ``mmap`` and unmaps them on free,
    so every step page-faults all of them in again, zero-filled by the kernel: measured
    here, that is a third of the paper network's step. Turning ``mmap`` off for the heap
    (``M_MMAP_MAX = 0``) and raising the trim threshold to 1 GiB makes freed blocks
    reusable: the same arithmetic, 1.5-1.6x faster (``benchmarks/precision_speed.py``). The
    cost is that the process keeps its peak heap (up to 1 GiB more) until it exits.

    Process-wide, applied once, only on Linux with glibc; ``FEDMAP_MALLOC_TUNING=0`` turns
    it off. Returns whether it is applied.
    """
    libc = _tunable_glibc()
    if libc is None:
        return False
    m_trim_threshold, m_mmap_max = -1, -4  # from glibc's malloc.h
    return bool(libc.mallopt(m_mmap_max, 0)) and bool(libc.mallopt(m_trim_threshold, 1 << 30))


def release_freed_memory() -> bool:
    """Give the heap's free pages back to the OS (glibc's ``malloc_trim(0)``), between stages.

    :func:`keep_freed_memory` keeps large blocks on the heap, and a heap only shrinks from
    its top: what a stage frees in the middle stays resident, so a run's peak RSS was the sum
    of its stages' high-water marks, not the largest one (at 1024² it grew from 0.7 GB in
    federated training to 1.85 GB at the end, monotonically). ``malloc_trim(0)`` also returns
    whole free pages inside the heap. Call it after a stage has dropped its big tensors; it
    costs milliseconds. Returns whether memory was released (False off glibc, or with
    ``FEDMAP_MALLOC_TUNING=0``).
    """
    libc = _tunable_glibc()
    if libc is None:
        return False
    return bool(libc.malloc_trim(0))


#: A masked map of more than this many cells, trained by a network without BatchNorm
#: (GridNet, or a Fourier MLP built without it), trains on its known cells only: the same
#: loss and gradients (an UNKNOWN cell's weight is 0) to float rounding, without the work on
#: the cells nobody saw. 0: every such map (a mission's rovers hold a few known cells early
#: on: the fedmap strategy's fits on the default mission took 24 s on every cell).
KNOWN_ONLY_ABOVE = 0
#: The training size Adam's ``eps`` is scaled to for a larger GridNet (:func:`_adam_eps`).
KNOWN_ONLY_CELLS = 1 << 16
#: Above this many training cells, a full-batch step of a network without BatchNorm is
#: computed in chunks of this many cells, its gradients accumulated
#: (:func:`_streamed_step`): the same step in bounded memory. A GridNet's step is streamed
#: from :data:`DECODER_PASS_ABOVE` cells.
STREAM_CELLS = 1 << 20
#: A streamed GridNet step reads its grids at this many cells at a time, and runs its
#: decoder on them in one compiled pass (:func:`decoder_pass`: its activations stay in
#: cache): every backward of torch's ``grid_sample`` zeroes a gradient the size of the
#: whole grid (84 M numbers at 4096²) and adds it to the last, so fewer, longer reads cost
#: less. The reading's own memory is 16 numbers a cell.
GRID_CHUNK = 1 << 22
#: The compiled decoder pass (:func:`decoder_pass`) splits its cells into parts of this
#: many, run on torch's threads; each part's loss is its own sum, and the parts add up in
#: order, so the loss does not depend on the number of threads.
DECODER_PART = 1 << 18
#: A full-batch GridNet step on more than this many cells is a streamed step
#: (:func:`_streamed_step`), whose decoder runs in one compiled pass (:func:`decoder_pass`).
DECODER_PASS_ABOVE = 1 << 16
#: Adam's default ``eps`` (torch's).
ADAM_EPS = 1e-8


def map_targets(grid: GridMap, *, masked: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Coordinates, RGB targets and loss weights of a map, flattened row-major.

    Returns ``coords (N, 2)``, ``target (N, 3)``, ``weight (N,)``. Without masking every
    weight is 1; with masking UNKNOWN cells get 0.
    """
    h, w = grid.shape
    coords = grid_coords(h, w)
    target = torch.from_numpy(grid.to_rgb().reshape(-1, 3))
    if masked:
        weight = torch.from_numpy(grid.known.reshape(-1).astype(np.float32))
    else:
        weight = torch.ones(h * w)
    return coords, target, weight


def map_loss(pred: torch.Tensor, target: torch.Tensor, weight: torch.Tensor,
          total: torch.Tensor | None = None) -> torch.Tensor:
    """Weighted per-cell squared error, summed and divided by ``total`` (default: the
    batch's weight, at least 1; a chunk of a streamed step passes the whole batch's)."""
    per_pixel = ((pred - target) ** 2).mean(dim=1)  # (B,)
    return (per_pixel * weight).sum() / (weight.sum().clamp_min(1.0) if total is None else total)


def fit(
    model: CoordNet | GridNet,
    grid: GridMap,
    config: TrainConfig,
    *,
    seed: int = 0,
    on_step: Callable[[int, float], None] | None = None,
    penalty: Callable[[], torch.Tensor] | None = None,
    select: np.ndarray | None = None,
) -> list[float]:
    """Train ``model`` in place on ``grid``; returns the loss of every step.

    ``on_step(step, loss)`` is called after each optimiser step (progress bars hook here).
    ``penalty()``, when given, is added to the data loss at every step (a term on the
    model's parameters, e.g. the augmented Lagrangian of decentralised ADMM); the losses
    returned include it. ``select`` (boolean, the map's shape), when given, restricts
    training to those cells (e.g. what changed since the last sync and a replay sample).

    With ``config.precision == "bf16"`` the Fourier MLP's matrix products run in bfloat16
    (autocast) on features cached once in bfloat16; the sigmoid, the loss, the gradients'
    accumulation into fp32 weights and Adam stay fp32. A :class:`GridNet` always trains in
    fp32: its step is bilinear sampling, not matrix products, and bf16 does not pay there.
    """
    keep_freed_memory()
    coords, target, weight = map_targets(grid, masked=config.masked)
    if select is not None:
        if np.shape(select) != grid.shape:
            raise FedmapError(f"training selection {np.shape(select)} does not match the map {grid.shape}")
        keep = torch.from_numpy(np.asarray(select, dtype=bool).reshape(-1))
        if config.masked:
            keep &= weight > 0
        coords, target, weight = coords[keep], target[keep], weight[keep]
        if not keep.any():
            raise RejectedUpdate(f"map {grid.source!r} has no selected cell to train on")
    if config.masked and not weight.any():
        raise RejectedUpdate(f"map {grid.source!r} has no known cell to train on")
    per_cell = not any(isinstance(m, torch.nn.BatchNorm1d) for m in model.modules())  # no batch statistics
    if per_cell and config.masked and coords.shape[0] > KNOWN_ONLY_ABOVE and not bool(weight.all()):
        keep = weight > 0  # a zero-weight cell adds nothing to the loss or its gradient
        coords, target, weight = coords[keep], target[keep], weight[keep]
    grid_net = model if isinstance(model, GridNet) else None  # its streamed steps run the compiled decoder pass
    stream = per_cell and config.batch is None and \
        coords.shape[0] > (STREAM_CELLS if grid_net is None else DECODER_PASS_ABOVE)
    bf16 = False
    if getattr(model, "cacheable_features", False):
        bf16 = config.precision == "bf16"
        with torch.no_grad():
            feats = model.features(coords)  # (N, 2*mapping): fixed, so computed once
            if bf16:
                feats = feats.to(torch.bfloat16)  # cast once, not at every step
        head = model.head
    else:
        feats, head = coords, model  # features are trained (grid encodings)
    opt = _adam(model, config.lr, _adam_eps(model, feats.shape[0]))
    gen = torch.Generator().manual_seed(seed)
    n = feats.shape[0]
    model.train()
    losses: list[float] = []
    for _ in range(config.epochs):
        if config.batch is None or config.batch >= n:
            batches: Sequence[torch.Tensor | None] = [None]
        else:
            perm = torch.randperm(n, generator=gen)
            chunks = [perm[a : a + config.batch] for a in range(0, n, config.batch)]
            if len(chunks) > 1 and len(chunks[-1]) < 2:  # BatchNorm cannot take one sample
                chunks = chunks[:-1]
            batches = chunks
        for idx in batches:
            x, y, wt = (feats, target, weight) if idx is None else (feats[idx], target[idx], weight[idx])
            opt.zero_grad(set_to_none=True)
            if stream:  # full batch (config.batch is None) of more than STREAM_CELLS cells (GridNet: DECODER_PASS_ABOVE)
                losses.append(_streamed_step(model.head, x, y, wt, penalty, bf16, grid_net=grid_net))
                opt.step()
                if on_step is not None:
                    on_step(len(losses), losses[-1])
                continue
            with torch.autocast("cpu", dtype=torch.bfloat16) if bf16 else contextlib.nullcontext():
                pred = head(x)
            loss = map_loss(pred.float(), y, wt)
            if penalty is not None:
                loss = loss + penalty()
            loss.backward()
            opt.step()
            losses.append(loss.item())
            if on_step is not None:
                on_step(len(losses), losses[-1])
    if losses and not np.isfinite(losses[-1]):
        raise RejectedUpdate(f"training diverged on {grid.source!r} (loss is {losses[-1]}); lower the learning rate")
    return losses


def _adam(model: torch.nn.Module, lr: float, eps: float) -> torch.optim.Adam:
    """Adam over ``model``'s parameters.

    A :class:`GridNet`'s parameters are its grids, one per map cell and feature at the
    finest level (21 M at 2048², 84 M at 4096²): its Adam is torch's fused CPU kernel, one
    pass over each parameter, moments and gradient with no temporaries. The multi-tensor
    (``foreach``) kernels take several passes and allocate a copy of every parameter for
    the square root of the second moment (0.34 GB at 4096²); at 2048² the fused step took
    4.7 ms against 33.6 ms (``benchmarks/adam_step.py``). The two round differently in the
    last bit. A Fourier MLP (under a million parameters) keeps the ``foreach``
    kernels: the same bits as torch's default loop (the paper network's fit is checked
    bit for bit against a hand-written one), in a few multi-tensor kernels instead of a
    loop of small ones per parameter (torch picks foreach by default on CUDA only)."""
    if isinstance(model, GridNet):
        return torch.optim.Adam(model.parameters(), lr=lr, eps=eps, fused=True)
    return torch.optim.Adam(model.parameters(), lr=lr, eps=eps, foreach=True)


def _adam_eps(model: torch.nn.Module, n: int) -> float:
    """Adam's ``eps`` for a :class:`GridNet` trained on ``n`` > :data:`KNOWN_ONLY_CELLS` cells.

    A grid parameter's gradient is its few cells' error divided by ``n`` (the loss is a
    mean): at 4096² it is about 1e-8, Adam's default ``eps``, and the steps shrink with the
    map (the 4096² fit ended at 2.7x the 2048² loss). Scaling ``eps`` by
    ``KNOWN_ONLY_CELLS / n`` is Adam on a loss scaled to 2^16 cells: the same steps at
    every size. Smaller maps, and networks whose parameters see every cell, keep the
    default."""
    if isinstance(model, GridNet) and n > KNOWN_ONLY_CELLS:
        return ADAM_EPS * KNOWN_ONLY_CELLS / n
    return ADAM_EPS


def _streamed_step(head: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor, y: torch.Tensor,
                   wt: torch.Tensor, penalty: Callable[[], torch.Tensor] | None, bf16: bool, *,
                   grid_net: GridNet | None = None) -> float:
    """The gradient of one full-batch step, accumulated over chunks of :data:`STREAM_CELLS`
    cells (the loss is a weighted sum over cells, so the chunks' gradients add up to the
    whole batch's): memory stays at one chunk's activations whatever the map's size.
    Returns the step's loss.

    ``grid_net``: a :class:`GridNet` (``head`` is its decoder). Its grids are read for
    :data:`GRID_CHUNK` cells at a time; the loss and its gradient on those features are
    computed by :func:`decoder_pass` in one compiled pass, and the gradient is sent back
    through the reading (the decoder is frozen: it has no gradient of its own)."""
    total = wt.sum().clamp_min(1.0)
    value = 0.0
    if grid_net is None:
        for a in range(0, x.shape[0], STREAM_CELLS):
            with torch.autocast("cpu", dtype=torch.bfloat16) if bf16 else contextlib.nullcontext():
                pred = head(x[a:a + STREAM_CELLS])
            part = map_loss(pred.float(), y[a:a + STREAM_CELLS], wt[a:a + STREAM_CELLS], total)
            part.backward()
            value += part.item()
    else:
        for a in range(0, x.shape[0], GRID_CHUNK):
            read = grid_net.features(x[a:a + GRID_CHUNK])
            grad, chunk_loss = decoder_pass(grid_net, read.detach(), y[a:a + GRID_CHUNK], wt[a:a + GRID_CHUNK],
                                             float(total))
            read.backward(grad)
            value += chunk_loss
            del read, grad  # before the next chunk's reading is allocated
    if penalty is not None:
        term = penalty()
        term.backward()
        value += term.item()
    return value


def decoder_pass(net: GridNet, feats: torch.Tensor, y: torch.Tensor, wt: torch.Tensor,
                  total: float) -> tuple[torch.Tensor, float]:
    """``net``'s decoder on ``feats`` (``GridNet.head``), the loss of its output against
    ``y`` with weights ``wt`` over ``total`` (:func:`map_loss`), and the loss's gradient on
    ``feats``: ``(gradient, loss)``.

    Written out in torch, the decoder's 32-wide activations go to memory and back several
    times (forward, loss, backward), in chunks of :data:`STREAM_CELLS`; compiled
    (:func:`_decoder_rows`), they stay in cache, 256 cells at a time. Forward, loss and
    backward on 4 M cells of a 4096² GridNet, 2 threads on Zen 4: 340-412 ms written out,
    120 ms compiled. Every cell's arithmetic is fp32, as torch's, in another order, so the
    gradients agree to float rounding (``tests/test_training.py``); each cell's gradient
    does not depend on how the cells are split, and the loss adds up per
    :data:`DECODER_PART` in order, so the result is the same on any number of threads."""
    kernel = _decoder_kernel()
    f = np.ascontiguousarray(feats.numpy(), dtype=np.float32)
    t = np.ascontiguousarray(y.numpy(), dtype=np.float32)
    w = np.ascontiguousarray(wt.numpy(), dtype=np.float32)
    weights = [np.ascontiguousarray(b.detach().numpy(), dtype=np.float32) for b in (net.w1, net.c1, net.w2, net.r1)]
    grad = np.empty_like(f)
    bounds = list(range(0, f.shape[0], DECODER_PART)) + [f.shape[0]]
    sums = np.zeros(len(bounds) - 1)
    scale = 1.0 / total

    def run(k: int) -> None:
        kernel(f, t, w, scale, *weights, grad, bounds[k], bounds[k + 1], sums[k:k + 1])

    threads = min(torch.get_num_threads(), len(sums))
    if threads > 1:
        with ThreadPoolExecutor(threads) as pool:
            list(pool.map(run, range(len(sums))))
    else:
        for k in range(len(sums)):
            run(k)
    return torch.from_numpy(grad), float(sums.sum()) * scale / 3.0


@compiled_once
def _decoder_kernel():
    """:func:`_decoder_rows` compiled with numba (cached on disk), releasing the GIL.
    Compiled at the first streamed GridNet step, not at import, and once (:func:`~fedmap._util.compiled_once`)."""
    from numba import njit

    kernel = njit(cache=True, nogil=True)(_decoder_rows)
    f = np.zeros((1, 2), np.float32)  # compiled (or loaded) here, once, not by threads racing to do it
    kernel(f, np.zeros((1, 3), np.float32), np.zeros(1, np.float32), 1.0, np.zeros((1, 2), np.float32),
           np.zeros(1, np.float32), np.zeros((3, 1), np.float32), np.zeros(3, np.float32), f.copy(), 0, 1, np.zeros(1))
    return kernel


def _decoder_rows(f: np.ndarray, y: np.ndarray, wt: np.ndarray, scale: float, w1: np.ndarray, c1: np.ndarray,
                  w2: np.ndarray, r1: np.ndarray, grad: np.ndarray, lo: int, hi: int, out: np.ndarray) -> None:
    """For cells ``[lo, hi)``: ``o = sigmoid(max(f w1ᵀ + c1, -r1) w2ᵀ)`` (``GridNet.head``), their weighted
    squared error ``Σ wt · Σ_k (o_k - y_k)²`` into ``out[0]``, and the gradient of
    :func:`map_loss` (that sum over 3, times ``scale`` = 1 / total) on ``f`` into ``grad``.
    256 cells at a time, channel-major, so every inner loop runs along cells (SIMD)."""
    D = f.shape[1]
    H = w1.shape[0]
    B = 256
    ft = np.empty((D, B), np.float32)
    h = np.empty((H, B), np.float32)
    z = np.empty((3, B), np.float32)
    gt = np.empty((D, B), np.float32)
    dh = np.empty(B, np.float32)
    zero = np.float32(0.0)
    one = np.float32(1.0)
    c = np.float32(scale * (2.0 / 3.0))
    total = 0.0
    for s in range(lo, hi, B):
        n = min(B, hi - s)
        for i in range(n):
            for d in range(D):
                ft[d, i] = f[s + i, d]
        for k in range(3):
            for i in range(n):
                z[k, i] = zero
        for j in range(H):  # hidden unit j: its pre-activation, ReLU (shifted), and its share of the logits
            bj = c1[j]
            floor = -r1[j]
            for i in range(n):
                h[j, i] = bj
            for d in range(D):
                w = w1[j, d]
                for i in range(n):
                    h[j, i] += w * ft[d, i]
            a0, a1, a2 = w2[0, j], w2[1, j], w2[2, j]
            for i in range(n):
                v = max(h[j, i], floor)
                h[j, i] = v
                z[0, i] += a0 * v
                z[1, i] += a1 * v
                z[2, i] += a2 * v
        for k in range(3):  # sigmoid, the loss, and the logits' gradient in place of the logits
            for i in range(n):
                o = one / (one + np.exp(-z[k, i]))
                e = o - y[s + i, k]
                we = wt[s + i] * e
                total += we * e
                z[k, i] = c * we * o * (one - o)
        for d in range(D):
            for i in range(n):
                gt[d, i] = zero
        for j in range(H):  # back through hidden unit j (ReLU: only where it was positive)
            a0, a1, a2 = w2[0, j], w2[1, j], w2[2, j]
            floor = -r1[j]
            for i in range(n):
                dh[i] = (a0 * z[0, i] + a1 * z[1, i] + a2 * z[2, i]) if h[j, i] > floor else zero
            for d in range(D):
                w = w1[j, d]
                for i in range(n):
                    gt[d, i] += w * dh[i]
        for i in range(n):
            for d in range(D):
                grad[s + i, d] = gt[d, i]
    out[0] = total


def steps_per_epoch(n_pixels: int, config: TrainConfig) -> int:
    if config.batch is None or config.batch >= n_pixels:
        return 1
    full, rest = divmod(n_pixels, config.batch)
    return full + (1 if rest >= 2 else 0)

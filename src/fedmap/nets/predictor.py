"""The map predictor: a small convolutional network that guesses what unknown cells hold.

For every cell of a class map (FREE / IMPASSABLE / UNKNOWN) it gives P(free) and
P(impassable). Its input is the map's classes as three one-hot channels; heights are not
an input yet (the Earth-like training collection has no heights for most of its maps).
A known cell keeps its class with certainty (:func:`predict`): a guess never overrides an
observation.

Every rover runs the same network on the map it holds, so rovers that hold the same map
make the same guesses, and the guesses cost no link bytes. The shipped weights,
``fedmap/weights/predictor.safetensors``, are learned offline by ``fedmap meta-predictor``
(:mod:`fedmap.training.predictorprior`) on the built-in Earth-like collection, never on a
test site.

Architecture (about 68 k parameters, no normalisation layers, so nothing but the weights
is state)::

    one-hot classes (3, H, W)
      stem   3x3 conv 3 -> s, ReLU                          full resolution
      down   3x3 conv s -> w, stride 2, ReLU                half resolution
      body   3x3 conv w -> w, dilation d, ReLU, residual    for d in dilations (1, 2, 4, 8, 16, 1)
      up     bilinear x2, concat stem, 3x3 conv -> s, ReLU  full resolution
      head   1x1 conv s -> 1: the logit of P(impassable)

The dilated body at half resolution sees about 128 cells either way, so the guess for a
cell deep in unknown ground still comes from the known ground around it, at about a
quarter of the arithmetic of a full-resolution body.

**Base rates.** The Earth-like training maps are 28-76 % impassable; planetary sites are
often 10 % or less, so the raw network over-predicts walls there. :func:`predict`
corrects for this *label shift* (Saerens, Latinne and Decaestecker 2002) with nothing
but the map it is given: it adds ``logit(r_map) - logit(r_train)`` to every logit, where
``r_map`` is the impassable share of the map's known cells and ``r_train`` the same share
averaged over the training maps (stored in the weights file as ``base_rate``).
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
import os
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from fedmap._util import atomic_write_bytes
from fedmap.errors import FedmapError
from fedmap.maps.grid import FREE, IMPASSABLE, UNKNOWN, beside_unknown

#: The shipped weights (learned by ``fedmap meta-predictor``; its command is in the file's metadata).
PREDICTOR_FILE = "predictor.safetensors"
SHIPPED_PREDICTOR = Path(__file__).resolve().parent.parent / "weights" / PREDICTOR_FILE


@dataclass(frozen=True)
class PredictorConfig:
    """The predictor's shape (stored in its weights file, so the file alone rebuilds it)."""

    stem: int = 16  #: channels at full resolution
    width: int = 32  #: channels of the half-resolution body
    dilations: tuple[int, ...] = (1, 2, 4, 8, 16, 1)  #: one residual 3x3 layer per dilation

    def __post_init__(self) -> None:
        if self.stem < 1 or self.width < 1 or not self.dilations or min(self.dilations) < 1:
            raise FedmapError(f"bad predictor shape: {self}")
        object.__setattr__(self, "dilations", tuple(int(d) for d in self.dilations))


class MapPredictor(nn.Module):
    """``(N, 3, H, W)`` one-hot classes -> ``(N, 1, H, W)`` logits of P(impassable)."""

    base_rate: torch.Tensor

    def __init__(self, config: PredictorConfig | None = None) -> None:
        super().__init__()
        self.config = c = config or PredictorConfig()
        self.stem = nn.Conv2d(3, c.stem, 3, padding=1)
        self.down = nn.Conv2d(c.stem, c.width, 3, stride=2, padding=1)
        self.body = nn.ModuleList(nn.Conv2d(c.width, c.width, 3, padding=d, dilation=d) for d in c.dilations)
        self.up = nn.Conv2d(c.width + c.stem, c.stem, 3, padding=1)
        self.head = nn.Conv2d(c.stem, 1, 1)
        #: the impassable share of the known cells of the training maps (see :func:`predict`)
        self.register_buffer("base_rate", torch.tensor(0.5))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        s = F.relu(self.stem(x))  # (N, stem, H, W)
        z = F.relu(self.down(s))  # (N, width, ceil(H/2), ceil(W/2))
        for conv in self.body:
            z = z + F.relu(conv(z))
        z = F.interpolate(z, size=s.shape[-2:], mode="bilinear", align_corners=False)
        return self.head(F.relu(self.up(torch.cat([z, s], dim=1))))  # (N, 1, H, W)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def one_hot(classes: np.ndarray) -> torch.Tensor:
    """``(..., H, W)`` classes -> ``(..., 3, H, W)`` float one-hot (FREE, IMPASSABLE, UNKNOWN)."""
    c = torch.from_numpy(np.ascontiguousarray(classes, dtype=np.uint8)).long()
    return torch.stack([(c == FREE), (c == IMPASSABLE), (c == UNKNOWN)], dim=-3).float()


@contextlib.contextmanager
def one_thread(deterministic: bool = False) -> Iterator[None]:
    """torch on one thread (and deterministic algorithms when asked) inside, as before after."""
    threads, was = torch.get_num_threads(), torch.are_deterministic_algorithms_enabled()
    if threads != 1:
        torch.set_num_threads(1)
    if deterministic:
        torch.use_deterministic_algorithms(True)
    try:
        yield
    finally:
        if threads != 1:
            torch.set_num_threads(threads)
        if deterministic:
            torch.use_deterministic_algorithms(was)


def known_rate(classes: np.ndarray, *, cells: float = 2.0, rate: float = 0.5) -> float:
    """The impassable share of a map's known cells, read with ``cells`` more cells of
    impassable share ``rate`` added: by default one pseudo-count of each class (a map with
    nothing known gives 1/2)."""
    b = np.asarray(classes)
    return (int((b == IMPASSABLE).sum()) + cells * rate) / (int((b != UNKNOWN).sum()) + cells)


def _logit(p: float) -> float:
    return float(np.log(p) - np.log1p(-p))


def base_rate_shift(model: MapPredictor, classes: np.ndarray) -> float:
    """What :func:`predict` adds to every logit of ``classes`` to move the guesses to the map's
    own base rate: ``logit(known_rate(classes)) - logit(model.base_rate)`` (see the module notes)."""
    return _logit(known_rate(classes)) - _logit(float(model.base_rate))


def predict(model: MapPredictor, classes: np.ndarray, *, adapt: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """``(P(free), P(impassable))`` of every cell of the ``(H, W)`` map ``classes``, float32.

    A known cell is certain (1 for its class, 0 for the other); an unknown cell gets the
    network's guess, moved to the map's own base rate when ``adapt`` (see the module
    notes: ``logit(known_rate(classes)) - logit(model.base_rate)`` added to its logit).
    The two sum to 1 (the terrain under an unknown cell is one or the other).
    Runs on one thread whatever torch's setting: the same map gives the same bits on
    every rover, and a second thread gains nothing at 128² (``benchmarks/predictor.py``)
    while it costs many times over on a busy CPU (threads waiting for each other).
    """
    b = np.asarray(classes)
    if b.ndim != 2:
        raise FedmapError(f"the predictor takes one (H, W) class map, got shape {b.shape}")
    shift = base_rate_shift(model, b) if adapt else 0.0
    with one_thread(), torch.inference_mode():
        p = torch.sigmoid(model(one_hot(b)[None]) + shift)[0, 0].numpy()
    p_imp = np.where(b == IMPASSABLE, 1.0, np.where(b == FREE, 0.0, p)).astype(np.float32)
    return (1.0 - p_imp).astype(np.float32), p_imp


#: Hidden cells a check of the guesses needs before its verdict counts (fewer: no verdict).
MIN_CHECK_CELLS = 100
#: How much better than "all free" the guesses must be on a check to be planned with (a share of
#: the hidden cells: 3 points). Guesses only as good as "all free" are no use to plan with, and
#: they cost a rover its straight paths.
CHECK_MARGIN = 0.03


@dataclass(frozen=True)
class GuessCheck:
    """The guesses checked on a map's own known cells (:func:`check_guesses`): how many were
    hidden and scored, the share the guesses got right, and the share "all free" got right."""

    cells: int
    accuracy: float
    all_free: float

    @property
    def pays(self) -> bool | None:
        """Whether the guesses beat "all free" there by :data:`CHECK_MARGIN` (None: too few cells to say)."""
        return None if self.cells < MIN_CHECK_CELLS else self.accuracy >= self.all_free + CHECK_MARGIN


def hide_patches(classes: np.ndarray, rng: np.random.Generator, *, radius: float, patches: int) -> np.ndarray:
    """Which known cells of ``classes`` to hide from the predictor: ``patches`` disks of
    ``radius`` cells, each centred on a known cell next to an unknown one (a rover's
    frontier, where it asks for guesses; any known cell when there is none), drawn from
    ``rng``. All False when the map knows nothing."""
    b = np.asarray(classes)
    known = b != UNKNOWN
    hide = np.zeros_like(known)
    if not known.any():
        return hide
    edge = np.argwhere(known & beside_unknown(b))
    pool = edge if len(edge) else np.argwhere(known)
    centres = pool[rng.choice(len(pool), size=min(patches, len(pool)), replace=False)]
    rows, cols = np.indices(b.shape)
    for r, c in centres:
        hide |= (rows - r) ** 2 + (cols - c) ** 2 <= radius ** 2
    return hide & known


def check_guesses(model: MapPredictor, classes: np.ndarray, rng: np.random.Generator, *, radius: float,
                  patches: int = 8) -> GuessCheck:
    """Masked cross-validation of the guesses on the map ``classes`` alone: ``patches``
    disks of ``radius`` cells, each centred on a known cell next to an unknown one (where a
    rover asks for guesses: its frontier), are hidden; the predictor guesses them from the
    rest, and its guesses (the likelier class) are scored against what the map holds, beside
    "all free". Self-supervised: nothing but the map is read."""
    b = np.asarray(classes)
    hide = hide_patches(b, rng, radius=radius, patches=patches)
    if not hide.any():
        return GuessCheck(0, 0.0, 0.0)
    masked = np.where(hide, UNKNOWN, b).astype(np.uint8)
    _, p_imp = predict(model, masked)
    truth = b[hide]
    guess = np.where(p_imp[hide] > 0.5, IMPASSABLE, FREE)
    n = int(hide.sum())
    return GuessCheck(n, float((guess == truth).mean()) if n else 0.0, float((truth == FREE).mean()) if n else 0.0)


# -- adaptation during a mission -----------------------------------------------------------

def _check_fitting(options, what: str, counts: tuple[str, ...]) -> None:
    """``counts`` of ``options`` >= 1 and its ``lr`` finite and > 0, else a one-line error about ``what``."""
    for name in counts:
        if getattr(options, name) < 1:
            raise FedmapError(f"{what} {name} must be >= 1, got {getattr(options, name)}")
    if not (math.isfinite(options.lr) and options.lr > 0):
        raise FedmapError(f"{what} lr must be finite and > 0, got {options.lr}")


@dataclass(frozen=True)
class Adaptation:
    """How a rover fine-tunes its copy of the predictor on its own map (:func:`adapt_predictor`)."""

    steps: int = 3  #: Adam steps per adaptation (a fresh optimiser each time: nothing but the weights is state)
    lr: float = 3e-4  #: Adam learning rate (a tenth of the offline training's: small moves from the shipped weights)
    crop: int = 64  #: side of the window around the rover it trains on (the whole map when smaller)
    patches: int = 8  #: disks hidden per step, as the check hides (:func:`hide_patches`)

    def __post_init__(self) -> None:
        _check_fitting(self, "predictor adaptation", ("steps", "crop", "patches"))


def copy_predictor(model: MapPredictor) -> MapPredictor:
    """A predictor with ``model``'s config and a copy of its weights (``model`` untouched)."""
    out = MapPredictor(model.config)
    out.load_state_dict({k: v.detach().clone() for k, v in model.state_dict().items()})
    return out.eval()


def adapt_predictor(model: MapPredictor, classes: np.ndarray, rng: np.random.Generator, *, radius: float,
                    around: tuple[int, int] | None = None, adaptation: Adaptation | None = None) -> MapPredictor:
    """A copy of ``model`` fine-tuned on the map ``classes`` alone, self-supervised: every
    step hides patches of its known cells (:func:`hide_patches`, in a ``crop`` window around
    the cell ``around``, or the map's centre), guesses them from the rest with the base-rate
    shift :func:`predict` applies, and takes one Adam step on the binary cross-entropy of
    the hidden cells, in one of the 8 rotations/reflections. No truth is read: only what the
    map holds. ``model`` is never changed (the coder's shipped weights stay the shipped
    weights). One thread and deterministic algorithms, every draw from ``rng``: the same
    map and draws give the same weights bit for bit on one machine. A window with fewer
    than :data:`MIN_CHECK_CELLS` hidden cells in a step is skipped."""
    a = adaptation or Adaptation()
    b = np.asarray(classes)
    if b.ndim != 2:
        raise FedmapError(f"the predictor adapts to one (H, W) class map, got shape {b.shape}")
    h, w = b.shape
    ch, cw = min(a.crop, h), min(a.crop, w)
    r, c = around if around is not None else (h // 2, w // 2)
    r0, c0 = int(np.clip(r - ch // 2, 0, h - ch)), int(np.clip(c - cw // 2, 0, w - cw))
    window = b[r0:r0 + ch, c0:c0 + cw]
    out = copy_predictor(model)
    with one_thread(deterministic=True), torch.enable_grad():
        out.train()
        opt = torch.optim.Adam(out.parameters(), lr=a.lr)
        for _ in range(a.steps):
            hide = hide_patches(window, rng, radius=radius, patches=a.patches)
            k = int(rng.integers(8))
            if int(hide.sum()) < MIN_CHECK_CELLS:
                continue
            masked = np.where(hide, UNKNOWN, window).astype(np.uint8)
            shift = base_rate_shift(out, masked)  # the correction predict() applies: trained as it is used
            x = _dihedral(masked, k)[None]
            target = torch.from_numpy(_dihedral(window == IMPASSABLE, k)[None].astype(np.float32))
            weight = torch.from_numpy(_dihedral(hide, k)[None].astype(np.float32))
            loss = unknown_cell_loss(out(one_hot(x))[:, 0] + shift, target, weight)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
    return out.eval()


# -- training ------------------------------------------------------------------------------

@dataclass(frozen=True)
class PredictorTraining:
    """How :func:`train_predictor` fits the network."""

    steps: int = 600  #: Adam steps
    batch: int = 8  #: samples per step
    crop: int = 96  #: side of the random square crop of every sample (the whole map when larger)
    lr: float = 2e-3  #: Adam learning rate, cosine-decayed to 5 % over the steps
    seed: int = 0

    def __post_init__(self) -> None:
        _check_fitting(self, "predictor training", ("steps", "batch", "crop"))


def _dihedral(a: np.ndarray, k: int) -> np.ndarray:
    """One of the 8 rotations/reflections of the last two axes (terrain has no preferred heading)."""
    a = np.rot90(a, k % 4, axes=(-2, -1))
    return a[..., ::-1] if k >= 4 else a


def training_batch(beliefs: np.ndarray, truths: np.ndarray, rng: np.random.Generator, batch: int,
                   crop: int) -> tuple[np.ndarray, np.ndarray, torch.Tensor, torch.Tensor]:
    """One training batch of ``(N, H, W)`` ``beliefs`` and ``truths``: ``batch`` maps drawn
    from ``rng``, a random ``crop`` x ``crop`` window of each and one of the 8
    rotations/reflections. Returns the maps drawn (their indices), the cropped beliefs,
    the target (1 where the truth is impassable) and the weight of every cell (1 where the
    belief is UNKNOWN and the truth known: the cells the predictor exists for)."""
    n, h, w = beliefs.shape
    ch, cw = min(crop, h), min(crop, w)
    idx = rng.integers(n, size=batch)
    r0, c0 = rng.integers(h - ch + 1, size=batch), rng.integers(w - cw + 1, size=batch)
    flips = rng.integers(8, size=batch)
    xb = np.stack([_dihedral(beliefs[i, r:r + ch, c:c + cw], k) for i, r, c, k in zip(idx, r0, c0, flips)])
    yb = np.stack([_dihedral(truths[i, r:r + ch, c:c + cw], k) for i, r, c, k in zip(idx, r0, c0, flips)])
    target = torch.from_numpy((yb == IMPASSABLE).astype(np.float32))
    weight = torch.from_numpy(((xb == UNKNOWN) & (yb != UNKNOWN)).astype(np.float32))
    return idx, xb, target, weight


def unknown_cell_loss(logits: torch.Tensor, target: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Binary cross-entropy of P(impassable) (``logits``), averaged over the cells ``weight`` keeps."""
    return (F.binary_cross_entropy_with_logits(logits, target, reduction="none") * weight).sum() \
        / weight.sum().clamp(min=1.0)


def train_predictor(beliefs: np.ndarray, truths: np.ndarray, *, config: PredictorConfig | None = None,
                    training: PredictorTraining | None = None,
                    on_step: Callable[[int, float], None] | None = None) -> MapPredictor:
    """Fit a predictor to ``(N, H, W)`` maps ``beliefs`` (what rovers held: classes, UNKNOWN
    where unobserved) and their ``(N, H, W)`` ``truths``.

    Loss: binary cross-entropy of P(impassable) on the cells UNKNOWN in the belief and
    known in the truth (the cells the predictor exists for). The model's ``base_rate`` is
    the mean :func:`known_rate` of ``beliefs``. Every step draws ``batch``
    samples, a random crop and one of the 8 rotations/reflections of each, all from the
    seed. Runs with one thread and deterministic algorithms, so the same inputs and seed
    give the same weights bit for bit. ``on_step(step, loss)`` follows the progress.
    """
    t = training or PredictorTraining()
    b, y = np.asarray(beliefs, dtype=np.uint8), np.asarray(truths, dtype=np.uint8)
    if b.ndim != 3 or b.shape != y.shape or not len(b):
        raise FedmapError(f"need (N, H, W) beliefs and truths of the same shape, got {b.shape} and {y.shape}")
    rng = np.random.default_rng(np.random.SeedSequence([t.seed, 35]))
    with one_thread(deterministic=True):
        torch.manual_seed(t.seed)
        model = MapPredictor(config)
        model.base_rate.fill_(float(np.mean([known_rate(x) for x in b])))
        opt = torch.optim.Adam(model.parameters(), lr=t.lr)
        sched = torch.optim.lr_scheduler.LambdaLR(
            opt, lambda i: 0.05 + 0.95 * 0.5 * (1 + np.cos(np.pi * min(i, t.steps) / t.steps)))
        for step in range(1, t.steps + 1):
            _, xb, target, weight = training_batch(b, y, rng, t.batch, t.crop)
            loss = unknown_cell_loss(model(one_hot(xb))[:, 0], target, weight)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            if on_step is not None:
                on_step(step, loss.item())
    return model.eval()


# -- weights files -------------------------------------------------------------------------

def save_predictor(model: MapPredictor, path: str | os.PathLike, *, extra: dict | None = None) -> Path:
    """Write the weights and the config that built them as safetensors, atomically (one
    metadata key, sorted: the same model gives the same bytes)."""
    from safetensors.torch import save

    state = model.state_dict()
    bad = sum(int((~torch.isfinite(v)).sum()) for v in state.values() if v.is_floating_point())
    if bad:  # a diverged training: never written over a good file
        total = sum(v.numel() for v in state.values() if v.is_floating_point())
        raise FedmapError(f"not writing {path}: {bad:,} of {total:,} predictor weights are NaN or infinite "
                          "(the training diverged: try a smaller learning rate)")
    meta = {"fedmap": json.dumps({"predictor": asdict(model.config), "extra": extra or {}}, sort_keys=True)}
    atomic_write_bytes(path, save({k: v.contiguous() for k, v in state.items()}, metadata=meta))
    return Path(path)


def _read(path: str | os.PathLike) -> tuple[dict[str, torch.Tensor], dict]:
    """The tensors and the ``fedmap`` metadata of a predictor file (one-line errors)."""
    from safetensors import SafetensorError, safe_open

    p = Path(path)
    if not p.is_file():
        raise FedmapError(f"no such predictor file: {p} (fedmap meta-predictor writes it)")
    try:
        with safe_open(str(p), framework="pt") as f:
            meta = json.loads((f.metadata() or {})["fedmap"])
            return {k: f.get_tensor(k) for k in f.keys()}, meta
    except (SafetensorError, OSError, KeyError, ValueError, TypeError) as e:
        raise FedmapError(f"{p} is not a fedmap predictor file ({type(e).__name__}: {e})".splitlines()[0]) from e


def load_predictor(path: str | os.PathLike) -> MapPredictor:
    """Rebuild a predictor from its weights file alone."""
    tensors, meta = _read(path)
    try:
        model = MapPredictor(PredictorConfig(**meta["predictor"]))
        model.load_state_dict(tensors)
    except (KeyError, TypeError, RuntimeError) as e:
        raise FedmapError(f"{path} is not a fedmap predictor file ({type(e).__name__}: {e})".splitlines()[0]) from e
    return model.eval()


def predictor_metadata(path: str | os.PathLike) -> dict:
    """What a predictor file says about itself (config and ``extra``: the command that made it)."""
    return _read(path)[1]


@functools.cache
def shipped_predictor() -> MapPredictor:
    """The shipped predictor (loaded once per process)."""
    return load_predictor(SHIPPED_PREDICTOR)


__all__ = ["Adaptation", "MapPredictor", "PredictorConfig", "PredictorTraining", "SHIPPED_PREDICTOR",
           "adapt_predictor", "base_rate_shift", "copy_predictor", "count_parameters", "hide_patches", "known_rate",
           "load_predictor", "one_hot", "predict", "predictor_metadata", "save_predictor", "shipped_predictor",
           "train_predictor"]

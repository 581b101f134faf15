"""Small helpers every layer uses: atomic writes, JSON for people, key checks.

Writes of results and checkpoints are atomic: a file is written to a temporary sibling
and renamed over its target (:func:`atomic_write_bytes`); a result folder is built in a
temporary sibling folder and swapped into place (:class:`AtomicDir`). A failure leaves
the previous result untouched.
"""

from __future__ import annotations

import difflib
import functools
import json
import math
import os
import shutil
import stat
import tempfile
import threading
import uuid
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from fedmap.errors import FedmapError


def cpu_cores() -> int:
    """The CPU cores this process may run on (its affinity where the OS says, else all)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


_T = TypeVar("_T")

#: Held while a compiled kernel is built or loaded (:func:`compiled_once`): one at a time.
_COMPILING = threading.RLock()


def compiled_once(build: Callable[[], _T]) -> Callable[[], _T]:
    """``build`` (a compiled kernel's builder: numba, compiled and cached on disk) run once per
    process, behind one lock.

    ``functools.cache`` alone runs a builder again in every thread that calls it before
    the first call has returned. A mission's rovers train side by side on threads
    (:func:`fedmap.mission.ends.protocol.side_by_side`), and scoring and planning split their work
    over threads, so two threads could compile the same kernel at once: twice the work, and
    two threads in numba's compiler at once (a prototype's two threads calling one
    uncompiled dispatcher never returned). Here the second waits for the first's kernel. A
    builder that compiles with a first call (the planners', SSIM's, the decoder pass's) is
    done compiling when it returns; one that returns numba's lazy dispatcher (the frontier
    search's) leaves the compilation to its first call, which numba's own compiler lock
    serialises. A builder may use another (the lock is re-entrant)."""
    cached = functools.cache(build)

    @functools.wraps(build)
    def kernel() -> _T:
        with _COMPILING:
            return cached()

    return kernel


def one_line(exc: BaseException) -> str:
    """An exception's message on one line (at most 200 characters)."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 200 else text[:197] + "..."


def varint(n: int) -> bytes:
    """Unsigned LEB128 of ``n >= 0`` (seven bits a byte, low first; the top bit: more follow)."""
    out = bytearray()
    while True:
        b, n = n & 0x7F, n >> 7
        out.append(b | (0x80 if n else 0))
        if not n:
            return bytes(out)


def atomic_write_bytes(path, data: bytes, *, mode: int | None = None) -> None:
    """Write ``data`` to ``path`` atomically.

    The bytes go to a temporary file in the same folder, are flushed to disk, and the
    temporary file is renamed over ``path`` with :func:`os.replace`. Readers see either
    the old file or the new one, never a partial write; if anything fails the temporary
    file is removed and an existing ``path`` is left untouched. The parent folder is
    created if missing. An existing file keeps its permission bits; a new one gets the
    usual ``0o666 & ~umask``. ``mode`` (e.g. ``0o600`` for a private key): the file has these
    bits, from its creation on (never readable by others, not even for a moment).
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise FedmapError(f"cannot create folder {path.parent}: {one_line(exc)}") from exc
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:12]}.tmp")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0),
                     0o666 if mode is None else mode)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        try:
            os.chmod(tmp, stat.S_IMODE(os.stat(path).st_mode) if mode is None else mode)
        except FileNotFoundError:
            pass
        os.replace(tmp, path)
    except BaseException as exc:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if isinstance(exc, OSError):
            raise FedmapError(f"cannot write {path}: {one_line(exc)}") from exc
        raise



def make_dir(path: str | os.PathLike, what: str = "") -> Path:
    """``mkdir -p`` with a one-line error naming the folder (a file in the way, no permission):
    ``cannot write <what> to <path>: <reason>``."""
    path = Path(path)
    head = f"cannot write {what + ' ' if what else ''}to {path}"
    if path.exists() and not path.is_dir():
        raise FedmapError(f"{head}: it exists and is not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise FedmapError(f"{head}: {exc.strerror or one_line(exc)}") from exc
    return path


def check_writable(path: Path, what: str) -> None:
    """``path`` can be written: its folder is made if missing, and a folder is made and removed
    beside it (a root user's ``access()`` says yes even to ``/proc``); otherwise a one-line error
    ``cannot write <what>: <reason> (in <folder>)``."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        os.rmdir(tempfile.mkdtemp(prefix=f".{path.name}.check-", dir=path.parent))
    except OSError as exc:  # the reason without the probe's name
        raise FedmapError(f"cannot write {what}: {exc.strerror or one_line(exc)} (in {path.parent})") from exc


def check_output_file(path: str | os.PathLike) -> Path:
    """Where a result file goes, checked before any work is done: not a folder, and its folder
    can be written (:func:`check_writable`); otherwise a one-line error."""
    path = Path(path)
    if path.is_dir():
        raise FedmapError(f"cannot write {path}: it is a folder")
    check_writable(path, str(path))
    return path


#: The file that marks a folder as written by fedmap (:class:`AtomicDir`): a later run may
#: replace such a folder as a whole, and no other.
OUTPUT_MARKER = ".fedmap-output"


#: The result files by which a folder written before :data:`OUTPUT_MARKER` existed is known,
#: with a key their JSON object holds: a run's or mission's metrics, the reproduction, Table I,
#: Table III and the elevation codecs' report.
_EARLIER_OUTPUTS = {"metrics.json": ("timings", "strategies"), "reproduce.json": ("terrains",),
                    "ablation.json": ("table",), "bandwidth.json": ("table3",), "elevation.json": ("points",)}


def _earlier_output(folder: Path) -> bool:
    """True when ``folder`` is an output an earlier fedmap wrote (before the marker): one of
    :data:`_EARLIER_OUTPUTS` there, a JSON object with one of its keys."""
    for name, keys in _EARLIER_OUTPUTS.items():
        try:
            data = json.loads((folder / name).read_text())
        except (OSError, ValueError):
            continue
        if isinstance(data, dict) and any(k in data for k in keys):
            return True
    return False


def check_output_dir(target: str | os.PathLike) -> Path:
    """Where a result folder goes, checked before any work is done; returns it resolved.

    The folder is replaced as a whole at the end of the run, so it must be new, empty, or an
    earlier output of fedmap (it holds :data:`OUTPUT_MARKER`): a folder of the user's own files
    (``-o ~/data``), a file, or the folder this process runs in is refused in one line, and so is
    a place that cannot be written."""
    out = Path(target).expanduser().resolve()
    shown = os.fspath(target)
    if out == Path(out.anchor):
        raise FedmapError(f"cannot write {shown}: it is the root folder")
    if out.exists() and not out.is_dir():
        raise FedmapError(f"cannot write {shown}: it exists and is not a folder")
    if out.is_dir():
        if Path.cwd().resolve().is_relative_to(out):
            raise FedmapError(f"cannot write {shown}: it is, or holds, the current folder, which the run would replace")
        if os.path.ismount(out):
            raise FedmapError(f"cannot write {shown}: it is a mount point, which the run cannot replace; give a folder "
                              "inside it")
        try:
            mine = (out / OUTPUT_MARKER).is_file() or not any(out.iterdir()) or _earlier_output(out)
        except OSError as exc:
            raise FedmapError(f"cannot write {shown}: {one_line(exc)}") from exc
        if not mine:
            raise FedmapError(f"{shown} exists and is not a fedmap output folder (no {OUTPUT_MARKER} in it); the run "
                              "replaces its output folder as a whole: choose a new --out, or empty or remove this one")
    check_writable(out, shown)
    return out


def _umask() -> int:
    """This process's umask, read without changing it (Linux: ``/proc/self/status``; elsewhere
    the usual 022)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    return 0o022


class AtomicDir:
    """Write a result folder completely or not at all.

    Files go into a temporary sibling folder, swapped into place when the ``with`` block ends
    without an exception (the old folder is removed only after the new one is in place). On an exception nothing of
    the new run is left behind and the old folder is untouched. Only a new or empty folder,
    or one fedmap wrote (:func:`check_output_dir`), is replaced; the new folder holds
    :data:`OUTPUT_MARKER` and keeps the old one's permissions (a new one: the umask's).
    """

    def __init__(self, target: str | os.PathLike) -> None:
        self.target = Path(target)

    def __enter__(self) -> Path:
        self.target = check_output_dir(self.target)
        try:
            self.tmp = Path(tempfile.mkdtemp(prefix=f".{self.target.name}.tmp-", dir=self.target.parent))
            (self.tmp / OUTPUT_MARKER).write_text("written by fedmap: the next run into this folder replaces it\n")
        except OSError as exc:
            raise FedmapError(f"cannot write {self.target}: {one_line(exc)}") from exc
        return self.tmp

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            shutil.rmtree(self.tmp, ignore_errors=True)
            return
        old = None
        try:
            if self.target.exists():
                check_output_dir(self.target)  # still fedmap's (nothing else took the name meanwhile)
                os.chmod(self.tmp, stat.S_IMODE(self.target.stat().st_mode))
                old = self.target.with_name(f".{self.target.name}.old-{uuid.uuid4().hex[:12]}")
                os.replace(self.target, old)
            else:
                os.chmod(self.tmp, 0o777 & ~_umask())
            os.replace(self.tmp, self.target)
        except BaseException as exc:
            if old is not None and not self.target.exists():
                os.replace(old, self.target)  # the old folder back where it was
            if isinstance(exc, OSError):  # the finished result is kept where it was written, and named
                raise FedmapError(f"cannot write {self.target}: {one_line(exc)}; this run's result is in "
                                  f"{self.tmp}") from exc
            shutil.rmtree(self.tmp, ignore_errors=True)
            raise
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)


def clean_json(obj: Any) -> Any:
    """JSON-safe copy: inf/nan -> None, numpy scalars -> Python, keys -> str."""
    if isinstance(obj, dict):
        return {str(k): clean_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [clean_json(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def to_json(obj: Any) -> str:
    """Indented JSON text of ``obj`` after :func:`clean_json`."""
    return json.dumps(clean_json(obj), indent=2, sort_keys=False) + "\n"


def suggest(key: str, allowed: Iterable[str]) -> str:
    """`` (did you mean 'x'?)`` for the closest allowed key, else the list of them."""
    allowed = list(allowed)
    close = difflib.get_close_matches(key, list(allowed), n=1)
    return f" (did you mean {close[0]!r}?)" if close else f"; known: {', '.join(allowed)}"


def check_keys(data: dict, allowed: Iterable[str], where: str) -> None:
    """Raise for the first key of ``data`` not in ``allowed``, suggesting the closest."""
    allowed = list(allowed)
    for key in data:
        if key not in allowed:
            raise FedmapError(f"unknown key {key!r} in {where}{suggest(key, allowed)}")


#: Bytes a bounded decompression produces per read (:func:`inflate_zstd`, :func:`inflate_zlib`).
_INFLATE_CHUNK = 1 << 20


def inflate_zstd(data: bytes | memoryview, limit: int) -> bytes:
    """The zstd frame(s) in ``data`` decoded, refused with :class:`ValueError` as soon as they
    would decode to more than ``limit`` bytes: memory grows with what is decoded, chunk by
    chunk, never with what a frame's header claims (a bomb of 10 kB can claim, and decode
    to, a GB). The caller knows ``limit`` from what its own header announces, and bounds it."""
    import io

    import zstandard

    out = bytearray()
    try:
        with zstandard.ZstdDecompressor().stream_reader(io.BytesIO(bytes(data)), read_across_frames=True) as r:
            while chunk := r.read(_INFLATE_CHUNK):
                out += chunk
                if len(out) > limit:
                    raise ValueError(f"it decodes to more than the {limit} bytes announced")
    except zstandard.ZstdError as e:
        raise ValueError(f"zstd: {e}") from None
    return bytes(out)


def inflate_zlib(data: bytes | memoryview, limit: int) -> bytes:
    """:func:`inflate_zstd` for a zlib stream."""
    import zlib

    d = zlib.decompressobj()
    try:
        out = bytearray(d.decompress(bytes(data), limit + 1))
    except zlib.error as e:
        raise ValueError(f"zlib: {e}") from None
    if len(out) > limit:
        raise ValueError(f"it decodes to more than the {limit} bytes announced")
    return bytes(out)

"""Launching Flower's processes for ``fedmap base-station`` and ``certs``, and what ``rover`` shares.

The commands start Flower's own processes (``flower-superlink``, ``flwr run``; the rover's
SuperNode is started by :mod:`fedmap.flower.rover`) with the right flags and wait for them;
every process is started in its own session and stopped by its PID (its process group),
also on errors and Ctrl-C.
Nothing here imports ``flwr``: the commands check that it is installed and then run its
executables.
"""

from __future__ import annotations

import contextlib
import ipaddress
import json
import os
import random
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from fedmap._util import atomic_write_bytes, make_dir
from fedmap.errors import FedmapError
from fedmap.flower import CONTROL_SECRET_ENV, require_flwr
from fedmap.flower.settings import RunSettings
from fedmap.flower.task import rover_nodes_text, run_dir, run_status_path, truth_shape, write_status

CONNECTION = "fedmap"  # the connection name written to $FLWR_HOME/config.toml
#: The modules the launcher runs as processes: the SuperLink with its front (Control API closed,
#: :mod:`fedmap.flower.gate`), and fedmap's Control API calls.
SUPERLINK_MODULE, CONTROL_MODULE = "fedmap.flower.superlink", "fedmap.flower.control"


def app_dir() -> Path:
    """The Flower App (its ``pyproject.toml``) that ``flwr run`` submits."""
    return Path(__file__).resolve().parent / "snapshot" / "app"


def flower_executable(name: str) -> str:
    """Path of a Flower command next to this Python, with a one-line install hint if absent."""
    require_flwr()
    here = Path(sys.executable).parent / name
    found = str(here) if here.exists() else shutil.which(name)
    if not found:
        raise FedmapError(f"{name} not found; run: pip install 'fedmap[flower]'")
    return found


#: Executables Flower's processes start by name (found on ``PATH``), per side.
SUPERLINK_EXES = ("flower-superlink", "flower-superexec", "flwr-serverapp", "flwr")
SUPERNODE_EXES = ("flower-superexec", "flwr-clientapp")  # the SuperNode itself: fedmap.flower.supernode


def require_executables(names: tuple[str, ...]) -> None:
    """One line naming every Flower executable missing beside this Python (and on PATH)."""
    require_flwr()
    missing = [n for n in names if not (Path(sys.executable).parent / n).exists() and not shutil.which(n)]
    if missing:
        raise FedmapError(f"Flower executable(s) {', '.join(missing)} not found beside {sys.executable} or on PATH; "
                          "run: pip install 'fedmap[flower]'")


def flower_env(flwr_home: Path) -> dict[str, str]:
    """The environment for Flower's processes: own ``FLWR_HOME``, no update check or telemetry,
    unbuffered output (their logs are read while they run: a SuperNode's last lines must not
    wait in a buffer), and this interpreter's ``bin/`` first on ``PATH``: Flower starts its helpers
    (``flower-superexec``, ``flwr-clientapp``, ...) by name, so they must resolve to the
    environment fedmap runs in even when that environment is not activated."""
    path = os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", os.defpath)])
    return {**os.environ, "PATH": path, "FLWR_HOME": str(flwr_home), "FLWR_DISABLE_UPDATE_CHECK": "1",
            "FLWR_TELEMETRY_ENABLED": "0", "PYTHONUNBUFFERED": "1"}


def set_death_signal(parent: int | None = None) -> None:  # pragma: no cover - runs in a forked child
    """Linux: the child gets SIGKILL when the process that started it dies (even by ``kill -9``),
    so a killed base station never leaves a SuperLink listening on its port. ``parent``: that
    process's PID, taken before the fork; if it died before this call (nothing would signal
    the child then) the child ends here."""
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    if parent is not None and os.getppid() != parent:
        os._exit(1)


def output_to(log: Path | str) -> None:  # pragma: no cover - runs in a forked child
    """Send this process's stdout and stderr (file descriptors 1 and 2) to the end of ``log``."""
    fd = os.open(log, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)


#: The longest path a Unix socket may have (Linux: 108 bytes with the terminating zero).
UNIX_SOCKET_PATH_MAX = 107
#: Where Linux says how this process runs; without it (macOS) a process's start time is unknown.
PROC_SELF_STAT = Path("/proc/self/stat")
#: The file in a process's temporary folder naming the process that owns it: its PID, its start
#: time ("-" where unknown) and the host name (a container sharing the folder has another).
OWNER_FILE = "owner"


def _start_time(pid: int) -> str | None:
    """When process ``pid`` started (clock ticks since boot, Linux's ``/proc``), "" where that
    cannot be read (another OS), None when there is no such process or it has exited (a zombie)."""
    if not PROC_SELF_STAT.exists():  # no /proc (macOS): liveness by os.kill alone
        return ""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return None
    except OSError:
        return ""
    fields = stat.rsplit(")", 1)[1].split()  # from field 3 on: the name before it may hold spaces
    return None if fields[0] in ("Z", "X") else fields[19]  # its state; field 22, its start time


def _alive(pid: int, started: str) -> bool:
    if pid <= 0:
        return False
    now = _start_time(pid)
    if now is None:
        return False
    if now == "" or started == "":  # no /proc: a PID in use is taken as the owner
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:
            return True
        return True
    return now == started  # else the PID is another process's now


def sweep_stale_dirs(parent: Path, prefix: str) -> list[Path]:
    """Remove the folders ``parent/prefix*`` that :func:`owned_temp_dir` made for processes that
    are gone (a rover or mission killed with SIGKILL cannot remove its own). A folder is removed
    only when its owner file names a process that no longer runs; one without that file, or not
    this user's, is left alone. Returns the folders removed."""
    removed: list[Path] = []
    try:
        candidates = [d for d in parent.iterdir() if d.name.startswith(prefix)]
    except OSError:
        return removed
    uid, host = os.getuid(), socket.gethostname()
    for d in candidates:
        try:
            if d.is_symlink() or not d.is_dir() or d.stat().st_uid != uid:
                continue
            fields = (d / OWNER_FILE).read_text().split()
            pid, started = int(fields[0]), (fields[1] if len(fields) > 1 else "-")
        except (OSError, ValueError, IndexError):
            continue
        if len(fields) > 2 and fields[2] != host:
            continue  # made on another machine or container sharing this folder: its processes are not visible here
        if not _alive(pid, "" if started == "-" else started):
            shutil.rmtree(d, ignore_errors=True)
            removed.append(d)
    return removed


@contextlib.contextmanager
def owned_temp_dir(prefix: str, *, parent: Path | str | None = None, socket_name: str | None = None) -> Iterator[Path]:
    """A temporary folder for this process, removed on exit, in ``parent`` (default: the usual
    temporary folder, ``TMPDIR``). It holds an owner file naming this process, so that a later
    run can remove it if this process is killed before it can (:func:`sweep_stale_dirs`, which
    runs here first). ``socket_name``: the folder is for a Unix socket of that name, and is made in
    ``/tmp`` where the usual temporary folder's path would be too long for a socket."""
    base = Path(parent) if parent is not None else Path(tempfile.gettempdir())
    if socket_name is not None and len(os.fsencode(base / (prefix + "x" * 8) / socket_name)) > UNIX_SOCKET_PATH_MAX:
        base = Path("/tmp")
    sweep_stale_dirs(base, prefix)
    d = Path(tempfile.mkdtemp(prefix=prefix, dir=base))
    try:
        pid = os.getpid()
        (d / OWNER_FILE).write_text(f"{pid} {_start_time(pid) or '-'} {socket.gethostname()}\n")
        yield d
    finally:
        shutil.rmtree(d, ignore_errors=True)


def socket_dir(prefix: str, name: str) -> contextlib.AbstractContextManager[Path]:
    """A temporary folder for a Unix socket called ``name``, removed on exit: in the usual
    temporary folder (``TMPDIR``), or in ``/tmp`` where that path would be too long for a socket."""
    return owned_temp_dir(prefix, socket_name=name)


#: Where Linux says which ports it draws outgoing connections' source ports from.
EPHEMERAL_RANGE_FILE = Path("/proc/sys/net/ipv4/ip_local_port_range")
#: Linux's default for that range, where the file cannot be read.
EPHEMERAL_DEFAULT = (32768, 60999)
#: The lowest port :func:`free_port` picks (below it: the usual ports of installed services).
LOWEST_PORT = 20000


def ephemeral_ports() -> tuple[int, int]:
    """The range (inclusive) the OS draws outgoing connections' source ports from."""
    try:
        low, high = (int(v) for v in EPHEMERAL_RANGE_FILE.read_text().split())
    except (OSError, ValueError):
        return EPHEMERAL_DEFAULT
    return low, high


def _bindable(host: str, port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that is free right now, outside :func:`ephemeral_ports`.

    A port the OS picks (bind to port 0) comes from that range, and a server is started on
    it seconds later: meanwhile any outgoing connection on the machine may take it as its
    source port, and hold it for as long as it lasts. A rover's SuperNode was refused its
    local port that way for two minutes, on a machine running several Flower runs at once.
    Ports are tried in a random order (not a result: which free port serves changes no
    output), so processes that pick at the same time rarely pick the same one; the OS picks
    if none outside the range is free."""
    low, high = ephemeral_ports()
    spans = [(a, b) for a, b in ((LOWEST_PORT, low - 1), (high + 1, 65535)) if b >= a]
    weights = [b - a + 1 for a, b in spans]
    pick = random.SystemRandom()
    for _ in range(200 if spans else 0):
        a, b = pick.choices(spans, weights=weights)[0]
        port = pick.randint(a, b)
        if _bindable(host, port):
            return port
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def toml_value(v) -> str:
    """One TOML value: strings quoted (JSON escapes are valid TOML), bools lower case."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    return json.dumps(str(v))


def key_values(d: dict) -> str:
    """``k=v k2="s"`` as Flower's ``--node-config`` / ``--run-config`` parse it."""
    return " ".join(f"{k}={toml_value(v)}" for k, v in d.items())


def _pgid(pid: int) -> int:
    try:
        return os.getpgid(pid)
    except ProcessLookupError:
        return -1


class Proc(Protocol):
    """What :class:`Processes` needs of a process: :class:`subprocess.Popen`'s ``pid``,
    ``returncode``, ``poll``, ``wait`` and ``send_signal``."""

    pid: int
    returncode: int | None

    def poll(self) -> int | None: ...

    def wait(self, timeout: float | None = None) -> int: ...

    def send_signal(self, sig: int) -> None: ...


class Processes:
    """Processes started in their own sessions and stopped by PID (process group)."""

    def __init__(self) -> None:
        self.procs: dict[str, Proc] = {}
        self.logs: dict[str, Path] = {}
        self.transient: list[Path] = []  #: files only these processes need: removed when they are stopped

    def start(self, name: str, argv: list[str], *, env: dict, log: Path, new_session: bool = True,
              die_with_parent: bool = False) -> subprocess.Popen:
        """Start ``argv`` logging to ``log``; in its own session (process group) unless
        ``new_session`` is False (then it shares ours: a signal to our group reaches it);
        ``die_with_parent``: killed when this process dies, even by SIGKILL (Linux)."""
        log.parent.mkdir(parents=True, exist_ok=True)
        with open(log, "ab") as fh:
            p = subprocess.Popen(argv, env=env, stdout=fh, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                 start_new_session=new_session,
                                 preexec_fn=set_death_signal if die_with_parent else None)
        self.procs[name], self.logs[name] = p, log
        return p

    def adopt(self, name: str, p: Proc, *, log: Path) -> Proc:
        """Watch and stop ``p``, started another way (in a process group of its own), as ``name``."""
        self.procs[name], self.logs[name] = p, log
        return p

    def stop(self, name: str, *, grace: float = 10.0, sig: int = signal.SIGTERM) -> None:
        """Signal the process group of ``name`` (pgid = its PID), then SIGKILL after ``grace`` s
        (a process sharing our group is signalled alone)."""
        p = self.procs.get(name)
        if p is None:
            return
        if os.getpgid(0) == _pgid(p.pid):
            for s in (sig, signal.SIGKILL):
                if p.poll() is None:
                    p.send_signal(s)
                try:
                    p.wait(timeout=grace)
                    return
                except subprocess.TimeoutExpired:
                    continue
            return
        for s in (sig, signal.SIGKILL):
            try:
                os.killpg(p.pid, s)  # the group we created: the process and its children
            except ProcessLookupError:
                pass
            try:
                p.wait(timeout=grace)
                break
            except subprocess.TimeoutExpired:
                continue
        try:
            os.killpg(p.pid, signal.SIGKILL)  # children that outlived their parent
        except ProcessLookupError:
            pass

    def stop_all(self) -> None:
        for name in reversed(list(self.procs)):
            self.stop(name)

    def check_alive(self, name: str) -> None:
        p = self.procs[name]
        if p.poll() is not None:
            tail = self.logs[name].read_text(errors="replace").strip().splitlines()[-1:] if self.logs[name].exists() else []
            raise FedmapError(f"{name} exited with code {p.returncode}" + (f": {tail[0]}" if tail else ""))

    def __enter__(self) -> Processes:
        return self

    def __exit__(self, *exc) -> None:
        self.stop_all()
        for f in self.transient:
            f.unlink(missing_ok=True)


@dataclass(frozen=True)
class Tls:
    """Certificate files made by ``fedmap certs`` (or your own PKI)."""

    ca: Path
    cert: Path
    key: Path

    @classmethod
    def from_dir(cls, d: Path) -> Tls:
        d = Path(d).resolve()  # Flower wants absolute paths in its config
        t = cls(d / "ca.crt", d / "server.pem", d / "server.key")
        for f in (t.ca, t.cert, t.key):
            if not f.is_file():
                raise FedmapError(f"missing certificate file {f}; make them with: fedmap certs {d}")
        return t


def superlink_argv(*, port: int, tls: Tls | None, auth: bool, secret_file: Path, front: str | None = None,
                   ready: Path | None = None, database: Path | None = None) -> list[str]:
    """The SuperLink on 127.0.0.1:``port``, its Control API closed to requests without the
    secret in ``secret_file``, and (``front``, ``HOST:PORT``) the same SuperLink's Fleet API
    alone where the rovers reach it, over mutual TLS with ``tls``, opened once ``ready``
    exists (:mod:`fedmap.flower.superlink`)."""
    argv = [sys.executable, "-m", SUPERLINK_MODULE, str(secret_file)]
    if front is not None:
        argv += ["--front", front] + (["--front-certs", str(tls.ca.parent)] if tls else [])
        argv += ["--ready", str(ready)] if ready is not None else []
    argv += ["--", "--host", "127.0.0.1", "--port", str(port), "--disable-runtime-dependency-installation"]
    argv += (["--ssl-ca-certfile", str(tls.ca), "--ssl-certfile", str(tls.cert), "--ssl-keyfile", str(tls.key)]
             if tls else ["--insecure"])
    if auth:
        argv.append("--enable-supernode-auth")
    if database is not None:
        argv += ["--database", str(database)]
    return argv


def new_secret(path: Path) -> Path:
    """A fresh control secret in ``path``, readable by its owner only (made so, not chmod-ed after)."""
    import secrets

    atomic_write_bytes(path, (secrets.token_urlsafe(32) + "\n").encode(), mode=0o600)
    return path


def start_superlink(procs: Processes, *, host: str, port: int, tls: Tls | None, auth: bool, env: dict, work: Path,
                    keys: Sequence[Path] = (), database: Path | None = None) -> tuple[str, dict[int, int]]:
    """The base station's SuperLink (on loopback, Control API closed) and its front on
    ``host:port`` (the Fleet API only; mutual TLS with ``tls``), both under ``procs`` and
    listening when this returns; ``env`` gets the control secret's file
    (:data:`fedmap.flower.CONTROL_SECRET_ENV`) and ``$FLWR_HOME`` a connection to the
    SuperLink. The rover ``keys`` are registered before the front opens, so no rover can
    knock before its key is known (:func:`register_keys`). Returns the address the rovers
    reach (``local:port``) and ``{node id: rover}`` of the keys. The secret goes when ``procs``
    stop (:attr:`Processes.transient`)."""
    secret = new_secret(Path(env["FLWR_HOME"]) / "control.secret")
    procs.transient.append(secret)
    env[CONTROL_SECRET_ENV] = str(secret)
    ready = Path(env["FLWR_HOME"]) / "front.ready"
    ready.unlink(missing_ok=True)
    inner = free_port("127.0.0.1")
    local = "127.0.0.1" if host in ("0.0.0.0", "::", "") else host
    front = f"[{host}]:{port}" if ":" in host.strip("[]") else f"{host.strip('[]')}:{port}"
    procs.start("superlink", superlink_argv(port=inner, tls=tls, auth=auth, secret_file=secret, front=front,
                                            ready=ready, database=database),
                env=env, log=work / "superlink.log", die_with_parent=True)
    alive = lambda: procs.check_alive("superlink")  # noqa: E731
    wait_for_port("127.0.0.1", inner, timeout=60, alive=alive)
    write_connection(Path(env["FLWR_HOME"]), address=f"127.0.0.1:{inner}", root_cert=tls.ca if tls else None)
    nodes = register_keys(list(keys), env=env)
    ready.touch()  # the front opens now
    wait_for_port(local, port, timeout=60, alive=alive)
    return f"{local}:{port}", nodes


def write_connection(flwr_home: Path, *, address: str, root_cert: Path | None) -> None:
    """``$FLWR_HOME/config.toml`` with one connection, :data:`CONNECTION`, made the default."""
    lines = ["[superlink]", f'default = "{CONNECTION}"', "", f"[superlink.{CONNECTION}]", f"address = {toml_value(address)}"]
    lines.append(f"root-certificates = {toml_value(str(root_cert))}" if root_cert else "insecure = true")
    flwr_home.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(flwr_home / "config.toml", ("\n".join(lines) + "\n").encode())


def wait_for_port(host: str, port: int, *, timeout: float, alive: Callable[[], None]) -> None:
    """Until something listens on ``host:port``; ``alive()`` raises if the server died."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        alive()
        with socket.socket() as s:
            s.settimeout(0.5)
            if s.connect_ex((host, port)) == 0:
                return
        time.sleep(0.3)
    raise FedmapError(f"nothing listens on {host}:{port} after {timeout:g} s")


def register_keys(keys: list[Path], *, env: dict, timeout: float = 60.0) -> dict[int, int]:
    """``flwr supernode register`` every rover key, all in one process
    (:mod:`fedmap.flower.control`: a Flower CLI process is about a second of CPU, mostly
    its start-up); a failure is one line naming the key. Returns ``{node id: rover}`` for
    the keys named ``roverK.pub`` (:func:`rover_of_key`): the node that key authenticates is
    rover K and no other."""
    if not keys:
        return {}
    out = _control(["register", CONNECTION, *map(str, keys)], what="flwr supernode register", env=env,
                   timeout=timeout * len(keys))
    nodes: dict[int, int] = {}
    for line in out.splitlines():
        if line.startswith("{"):
            got = json.loads(line)
            k = rover_of_key(Path(got["key"]))
            if k is not None:
                nodes[int(got["node-id"])] = k
    return nodes


def rover_of_key(key: Path) -> int | None:
    """The rover a key file is for, by its name (``roverK``, ``roverK.pub``, ``roverK.crt``), or None."""
    m = re.fullmatch(r"rover(\d+)(\.pub|\.crt)?", Path(key).name)
    return int(m.group(1)) if m else None


def _control(args: list[str], *, what: str, env: dict, timeout: float) -> str:
    """``python -m fedmap.flower.control ARGS`` (Flower's CLI with the launcher's secret); its
    output, or a one-line :class:`FedmapError` naming ``what`` failed or timed out."""
    try:
        r = subprocess.run([sys.executable, "-m", CONTROL_MODULE, *args], env=env, capture_output=True, text=True,
                           timeout=timeout, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        raise FedmapError(f"{what} did not finish in {timeout:g} s") from None
    if r.returncode != 0:
        raise FedmapError(f"{what} failed: {_one_line(r.stderr or r.stdout)}")
    return r.stdout


def _one_line(text: str) -> str:
    """Flower's boxed rich error as one line (the box drawing stripped)."""
    words = [ln.strip(" \u2502\u256d\u256e\u2570\u256f\u2500") for ln in text.splitlines()]
    words = [w for w in words if w and w != "Error"]
    return " ".join(words[-6:]) or "(no output)"


def submit_run(flwr_home: Path, run_config: dict, *, env: dict, timeout: float = 120.0, app: Path | None = None) -> None:
    """``flwr run <app> fedmap --run-config <toml>``: submit the base station's run (``app``:
    the Flower App's folder; default :func:`app_dir`, the snapshot federation)."""
    overrides = flwr_home / "fedmap-run-config.toml"
    overrides.write_text("".join(f"{k} = {toml_value(v)}\n" for k, v in run_config.items()))
    _control(["run", str(app or app_dir()), CONNECTION, str(overrides)], what="flwr run", env=env, timeout=timeout)


def read_status(out: Path) -> dict | None:
    p = run_status_path(out)
    try:
        return json.loads(p.read_text())
    except (FileNotFoundError, ValueError):
        return None


def wait_for_result(out: Path, *, since: float, timeout: float, alive: Callable[[], None],
                    on_status: Callable[[dict], None] | None = None) -> dict:
    """Poll ``<out>.run/status.json`` (newer than ``since``) until the run is done or failed."""
    t_end = time.monotonic() + timeout
    last = None
    while time.monotonic() < t_end:
        alive()
        p = run_status_path(out)
        st = read_status(out) if p.exists() and p.stat().st_mtime >= since else None
        if st is not None and st != last:
            last = st
            if on_status is not None:
                on_status(st)
            if st["state"] == "done":
                return st
            if st["state"] == "failed":
                raise FedmapError(st.get("message", "the base station's run failed"))
        time.sleep(0.5)
    raise FedmapError(f"the run did not finish in {timeout:g} s (see the SuperLink log)")


#: The longest certificate lifetime ``make_certs`` accepts, in days (100 years).
MAX_CERT_DAYS = 36_500


def _check_host(h: str) -> str:
    """A host name (RFC 1123 labels) or an IP address, else a one-line error."""
    try:
        ipaddress.ip_address(h)
        return h
    except ValueError:
        pass
    labels = h.rstrip(".").split(".")
    if not h or len(h) > 253 or not all(
            0 < len(lab) <= 63 and lab[0] != "-" and lab[-1] != "-" and all(c.isascii() and (c.isalnum() or c == "-")
                                                                             for c in lab) for lab in labels):
        raise FedmapError(f"--host {h!r} is not a host name or an IP address")
    return h


def make_certs(out_dir: Path, *, hosts: list[str], rovers: int, days: int = 365, overwrite: bool = False,
               keep_ca_key: bool = True) -> list[Path]:
    """A CA, a server certificate for ``hosts`` and one key pair and client certificate per rover.

    Files: ``ca.crt``, ``ca.key``, ``server.pem``, ``server.key`` (TLS; the base station
    uses the last three plus ``ca.crt``, rovers need only ``ca.crt``; the server certificate
    also names 127.0.0.1 and ``localhost``, where the base's own processes reach its
    SuperLink), and per rover ``rover{k}`` / ``rover{k}.pub`` (ECDSA P-384 in OpenSSH format,
    Flower's SuperNode authentication: the rover keeps the private key, the base registers
    the ``.pub``) and ``rover{k}.crt``, the TLS client certificate of that key (common name
    ``rover{k}``) that the base's front asks of every rover, with its key again as
    ``rover{k}.key`` (PEM: what a rover's Zenoh TLS reads). Private keys are readable by
    their owner only. ``keep_ca_key`` False: the CA's key is never written (nobody can make
    another certificate of this CA: a run's own, throw-away CA). A folder that already holds
    a CA is refused unless ``overwrite``: a new CA locks out every base station and rover set
    up with the old one.
    """
    import datetime as dt
    import ipaddress

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    if rovers < 0:
        raise FedmapError(f"rovers must be >= 0, got {rovers}")
    if not 1 <= days <= MAX_CERT_DAYS:
        raise FedmapError(f"days must be in [1, {MAX_CERT_DAYS}], got {days}")
    if not hosts:
        raise FedmapError("give at least one --host")
    hosts = [_check_host(h) for h in hosts]
    out_dir = Path(out_dir)
    held = [n for n in ("ca.crt", "ca.key") if (out_dir / n).exists()]
    if held and not overwrite:
        raise FedmapError(f"{out_dir} already holds a CA ({', '.join(held)}); a new one would lock out every base station "
                          "and rover set up with it: choose another folder, or pass --force to replace it")
    make_dir(out_dir, "certificates")
    now = dt.datetime.now(dt.UTC)
    pem = serialization.Encoding.PEM

    def key_bytes(k) -> bytes:
        return k.private_bytes(pem, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())

    def name(cn: str) -> x509.Name:
        return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])

    ca_key = ec.generate_private_key(ec.SECP384R1())
    ca = (x509.CertificateBuilder().subject_name(name("fedmap base-station CA")).issuer_name(name("fedmap base-station CA"))
          .public_key(ca_key.public_key()).serial_number(x509.random_serial_number())
          .not_valid_before(now - dt.timedelta(minutes=5)).not_valid_after(now + dt.timedelta(days=days))
          .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
          .sign(ca_key, hashes.SHA256()))
    sans: list[x509.GeneralName] = []
    for h in dict.fromkeys([*hosts, "127.0.0.1", "localhost"]):
        try:
            sans.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            sans.append(x509.DNSName(h))
    srv_key = ec.generate_private_key(ec.SECP384R1())
    srv = (x509.CertificateBuilder().subject_name(name(hosts[0])).issuer_name(ca.subject)
           .public_key(srv_key.public_key()).serial_number(x509.random_serial_number())
           .not_valid_before(now - dt.timedelta(minutes=5)).not_valid_after(now + dt.timedelta(days=days))
           .add_extension(x509.SubjectAlternativeName(sans), critical=False)
           .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
           .sign(ca_key, hashes.SHA256()))
    files = {"ca.crt": ca.public_bytes(pem), "ca.key": key_bytes(ca_key), "server.pem": srv.public_bytes(pem),
             "server.key": key_bytes(srv_key)}
    if not keep_ca_key:
        del files["ca.key"]
    for k in range(rovers):
        rk = ec.generate_private_key(ec.SECP384R1())
        files[f"rover{k}"] = rk.private_bytes(pem, serialization.PrivateFormat.OpenSSH, serialization.NoEncryption())
        files[f"rover{k}.pub"] = rk.public_key().public_bytes(serialization.Encoding.OpenSSH,
                                                              serialization.PublicFormat.OpenSSH) + b"\n"
        client = (x509.CertificateBuilder().subject_name(name(f"rover{k}")).issuer_name(ca.subject)
                  .public_key(rk.public_key()).serial_number(x509.random_serial_number())
                  .not_valid_before(now - dt.timedelta(minutes=5)).not_valid_after(now + dt.timedelta(days=days))
                  .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
                  .add_extension(x509.ExtendedKeyUsage([x509.oid.ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
                  .sign(ca_key, hashes.SHA256()))
        files[f"rover{k}.crt"] = client.public_bytes(pem)
        files[f"rover{k}.key"] = key_bytes(rk)  # the same key in PEM (PKCS#8): Zenoh's TLS reads this form
    if held:  # replacing a CA (overwrite): rover keys of the old one beyond the new count would still be registered
        for stale in out_dir.glob("rover*"):
            if re.fullmatch(r"rover\d+(\.pub|\.crt|\.key)?", stale.name) and stale.name not in files:
                stale.unlink()
    written = []
    for fname, data in files.items():
        private = fname.endswith(".key") or re.fullmatch(r"rover\d+", fname) is not None
        atomic_write_bytes(out_dir / fname, data, mode=0o600 if private else None)
        written.append(out_dir / fname)
    return written


# -- the commands ------------------------------------------------------------------------------

def is_loopback(host: str) -> bool:
    """Whether ``host`` is this machine only: ``localhost``, 127.0.0.0/8 or ::1 (a name that
    is not ``localhost`` counts as reachable from elsewhere)."""
    if host.strip("[]").lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def check_exposure(host: str, *, tls: bool, auth: bool, insecure: bool = False) -> None:
    """Refuse a SuperLink that other machines can reach without TLS and rover authentication
    (any host that reaches the port could join as a rover and send an update the base
    aggregates), unless ``insecure`` says the network is trusted. Loopback is always fine."""
    if insecure or (tls and auth) or is_loopback(host):
        return
    missing = " and ".join(what for what, ok in (("TLS (--certs)", tls), ("rover authentication (--auth-keys)", auth))
                           if not ok)
    raise FedmapError(f"refusing to listen on {host} without {missing}: any host that reaches it could join as a "
                      f"rover; make both with `fedmap certs DIR --host BASE_HOST --rovers N`, listen on --host "
                      f"127.0.0.1, or pass --insecure on a network you trust")


def run_base_station(run_config: dict, *, host: str = "0.0.0.0", port: int = 9092, certs: Path | None = None,
                     auth_keys: Path | None = None, on_status: Callable[[dict], None] | None = None,
                     on_ready: Callable[[], None] | None = None, insecure: bool = False) -> dict:
    """Start a SuperLink, submit fedmap's ServerApp, wait for it; returns the final status.

    ``run_config`` holds run-config keys (see :data:`fedmap.flower.settings.RUN_DEFAULTS`);
    ``out`` is made absolute so the ServerApp writes where the user asked. A ``host`` other
    machines can reach needs ``certs`` and ``auth_keys``, or ``insecure``
    (:func:`check_exposure`).
    """
    run_config = {**run_config, "out": str(Path(run_config.get("out", "fedmap-out/flower")).resolve())}
    settings = RunSettings.from_run_config(run_config)  # bad options fail here, before any process starts
    truth_shape(settings)  # so does a missing or unreadable --truth: read it now, not after the run
    check_exposure(host, tls=certs is not None, auth=auth_keys is not None, insecure=insecure)
    require_executables(SUPERLINK_EXES)
    tls = Tls.from_dir(certs) if certs is not None else None
    keys = sorted(Path(auth_keys).resolve().glob("*.pub")) if auth_keys is not None else []
    if auth_keys is not None and not keys:
        raise FedmapError(f"no rover public keys (*.pub) in {auth_keys}; make them with: fedmap certs DIR --rovers N")
    work = run_dir(settings.out)
    flwr_home = work / "flwr-home"
    env = flower_env(flwr_home)
    run_status_path(settings.out).unlink(missing_ok=True)
    try:
        with Processes() as procs, sigterm_as_interrupt():
            return _serve(procs, settings, run_config, host=host, port=port, tls=tls, keys=keys,
                          auth=auth_keys is not None, env=env, on_status=on_status, on_ready=on_ready)
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: our processes are stopped (Processes.__exit__)
        st = read_status(settings.out) or {}
        where = f"during round {st['round']}" if st.get("round") else "before round 1"
        write_status(settings.out, "interrupted", round=st.get("round", 0), message=f"interrupted {where}")
        raise FedmapError(f"base station interrupted {where}; the SuperLink is stopped; "
                          f"checkpoints so far are in {run_dir(settings.out)}") from None


def _serve(procs: Processes, settings: RunSettings, run_config: dict, *, host: str, port: int, tls: Tls | None,
           keys: list[Path], auth: bool, env: dict, on_status, on_ready) -> dict:
    """The base station's processes: SuperLink up, rover keys registered, run submitted, waited for."""
    work = run_dir(settings.out)
    flwr_home = Path(env["FLWR_HOME"])
    _, nodes = start_superlink(procs, host=host, port=port, tls=tls, auth=auth, env=env, work=work, keys=keys)
    run_config = {**run_config, "rover-nodes": rover_nodes_text(nodes)}
    since = time.time() - 1
    submit_run(flwr_home, run_config, env=env)
    if on_ready is not None:
        on_ready()

    alive = lambda: procs.check_alive("superlink")  # noqa: E731
    b = settings.base
    budget = b.connect_timeout + settings.federation.rounds * (b.deadline + b.connect_timeout) + 600
    return wait_for_result(settings.out, since=since, timeout=budget, alive=alive, on_status=on_status)


class sigterm_as_interrupt:
    """SIGTERM raises KeyboardInterrupt (main thread only), so ``finally`` blocks stop our processes."""

    def __enter__(self) -> None:
        import threading

        self.old = None
        if threading.current_thread() is threading.main_thread():
            self.old = signal.signal(signal.SIGTERM, self._raise)

    @staticmethod
    def _raise(signum, frame) -> None:
        raise KeyboardInterrupt

    def __exit__(self, *exc) -> None:
        if self.old is not None:
            signal.signal(signal.SIGTERM, self.old)

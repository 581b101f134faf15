"""``fedmap rover``: one Flower SuperNode per rover, kept connected across a bad link.

The rover runs Flower's ``flower-supernode`` as a child and watches it. Flower 1.41's
SuperNode does not survive every link fault by itself:

- a connection cut during a TLS handshake (``UNEXPECTED_EOF``) is taken for a certificate
  problem: the SuperNode gives up at once instead of retrying (the rover therefore runs it
  through :mod:`fedmap.flower.supernode`, which retries it);
- after giving up it logs ``SuperNode terminated gracefully`` and can then hang in its
  exit handler, so its process never ends;
- a restarted SuperLink (the base station resumed) no longer knows the node (HTTP 401).

So the rover reads the SuperNode's log: a SuperNode that has stopped, or says it has, is
stopped and a new one started, unless its log names a problem a retry cannot fix (the
SuperLink refused the rover's key, the certificate does not verify). Every wait has a bound:

- the rover gives up when its SuperLink has not answered for ``max_wait`` seconds (an
  HTTP(S) probe every :data:`PROBE_EVERY` s, plus the SuperNode's own log of contact): the
  base station is gone, the address is wrong, or the run is over;
- at most :data:`ROVER_RESTARTS` restarts in a row without the SuperNode reaching its
  SuperLink in between, and :data:`ROVER_RESTARTS_TOTAL` in all.

Each failure is one :class:`~fedmap.errors.FedmapError` line naming the rover. Nothing here
imports ``flwr``.
"""

from __future__ import annotations

import json
import os
import re
import select
import signal
import socket
import ssl
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

from fedmap._util import atomic_write_bytes
from fedmap.errors import FedmapError
from fedmap.flower import CLIENT_CERT_ENV, CLIENT_KEY_ENV, HEARTBEAT_ENV, HEARTBEAT_RANGE, POLL_ENV, SUPEREXEC_POLL_ENV
from fedmap.flower import warm as warm_server
from fedmap.flower.faults import parse_fault
from fedmap.flower.launch import (
    SUPERNODE_EXES,
    Proc,
    Processes,
    flower_env,
    free_port,
    key_values,
    output_to,
    owned_temp_dir,
    require_executables,
    set_death_signal,
    sigterm_as_interrupt,
    socket_dir,
)
from fedmap.flower.mission.task import hold_state, node_feed, parse_mission_fault
from fedmap.flower.task import load_local_map

#: Seconds a rover keeps trying to reach its SuperLink before it gives up (``fedmap rover --max-wait``).
ROVER_MAX_WAIT = 120.0
#: SuperNode restarts in a row (without reaching the SuperLink in between) before the rover gives up:
#: with backoff, over a minute, as long as a SuperLink takes to see a SuperNode's heartbeat lapse.
ROVER_RESTARTS = 20
#: SuperNode restarts over the rover's life, however often it reached its SuperLink in between.
ROVER_RESTARTS_TOTAL = 100
#: Seconds between the rover's own probes of its SuperLink.
PROBE_EVERY = 5.0
#: Seconds the probe waits for the SuperLink's answer (TLS handshake included). A SuperLink on
#: a loaded machine can take more than 2 s: with 2 s, on a 2-core machine at load 9, a rover
#: whose key the SuperLink refused was told that no SuperLink had answered for 30 s.
PROBE_TIMEOUT = 5.0
#: Seconds a finished rover leaves its SuperNode running, at least, so the final reply reaches
#: the base: it is stopped as soon as it has sent a reply to every message it received, and
#: waits up to ``max_wait`` while a reply is owed (the SuperNode may be reconnecting to send it).
DONE_GRACE = 5.0
#: Seconds a SuperNode that logged its own end gets to exit before it is stopped.
END_GRACE = 3.0

#: Flower SuperNode log lines that show it reached its SuperLink.
CONTACT = ("SuperNode ID:", "Received successfully", "Sent successfully", "Connection successful after")
#: ... and that show it has stopped, or is about to: after giving up, Flower's SuperNode tries to
#: deactivate its node over the link that failed, and can then hang in its exit handler.
ENDED = ("Giving up reconnection", "SuperNode terminated gracefully", "Exit Code:")


#: The module a rover runs its SuperNode from (Flower's ``flower-supernode``, with fixes).
SUPERNODE_MODULE = "fedmap.flower.supernode"


def supernode_argv(*, superlink: str, port: int, node_config: dict, root_cert: Path | None,
                   auth_key: Path | None, max_wait: float | None = None) -> list[str]:
    """Flower's ``flower-supernode`` through :mod:`fedmap.flower.supernode` (an EOF in a TLS
    handshake is retried rather than taken for a certificate problem)."""
    argv = [sys.executable, "-m", SUPERNODE_MODULE, "--superlink", superlink, "--port", str(port),
            "--node-config", key_values(node_config)]
    argv += ["--root-certificates", str(root_cert)] if root_cert else ["--insecure"]
    if auth_key:
        argv += ["--auth-supernode-private-key", str(auth_key)]
    if max_wait is not None:
        argv += ["--max-wait-time", str(max_wait)]
    return argv


def rover_node_config(*, partition_id: int, map_path: Path | None, terrain: str | None, size: int, agents: int,
                      explore: str, seed: int, out: Path | None, fault: str | None = None,
                      mission: bool = False, state: Path | None = None, feed: Path | None = None,
                      feed_topic: str | None = None) -> dict:
    """The SuperNode's node config for one rover (checked by loading the map once);
    ``fault``: see :mod:`fedmap.flower.faults` (tests only). ``mission``: a rover of a
    mission on processes, which builds its world from the mission the base sends (no map),
    and keeps its state in ``state`` (None: a temporary folder, gone when the rover exits);
    ``feed`` (``feed_topic``): its observations come from its own mapping software
    (:mod:`fedmap.mission.world.feed`; checked by opening it once)."""
    cfg: dict = {"partition-id": partition_id}
    if mission:
        if map_path is not None or terrain is not None or out is not None:
            raise FedmapError("a mission rover (--mission) takes its terrain from the base station's mission: "
                              "no --map, --terrain or --out")
        if fault:
            parse_mission_fault(fault)
            cfg["fault"] = fault
        if state is not None:
            cfg["state-dir"] = str(Path(state).resolve())
        if feed is not None:
            cfg["feed"] = str(Path(feed).resolve())
            if feed_topic:
                cfg["feed-topic"] = feed_topic
            node_feed(cfg)  # a missing or unreadable feed: say so before connecting
        return {**cfg, "mission": True}
    if fault:
        parse_fault(fault)
        cfg["fault"] = fault
    if (map_path is None) == (terrain is None):
        raise FedmapError("give exactly one of --map (the rover's local map) or --terrain (the built-in generator)")
    if map_path is not None:
        cfg["map"] = str(Path(map_path).resolve())
    else:
        cfg.update(terrain=terrain, size=size, agents=agents, explore=explore, seed=seed)
    if out is not None:
        cfg["out"] = str(Path(out).resolve())
    try:
        load_local_map(cfg)
    except FedmapError as e:  # a missing or corrupt map: say which rover, before connecting
        raise FedmapError(f"rover {partition_id}: {e}") from None
    return cfg


#: The stand-in for a Flower program the SuperNode starts by name (``{python}``, ``{program}``
#: and ``{socket}`` filled in): stdlib only, so it starts in milliseconds; it hands its
#: arguments to the warm server, which forks the program, and exits with its exit code. It
#: waits for the server for at most 300 s, and not at all once the process that started it
#: (the SuperNode) or the server's folder is gone.
WARM_SHIM = """#!{python} -I
import json, os, socket, sys, time
t_end, parent = time.monotonic() + 300, os.getppid()
while True:
    try:
        s = socket.socket(socket.AF_UNIX)
        s.connect({socket!r})
        break
    except OSError:
        s.close()
        if time.monotonic() > t_end or os.getppid() != parent or not os.path.isdir({folder!r}):
            sys.exit({program!r} + ": the rover's warm ClientApp server did not answer")
        time.sleep(0.2)
s.sendall(json.dumps([{program!r}, *sys.argv[1:]]).encode() + b"\\n")
reply = s.makefile().readline().strip()
sys.exit(int(reply) if reply.lstrip("-").isdigit() else 1)
"""


def write_shim(bin_dir, sock: str) -> None:
    """Write the stand-ins for the programs the warm server forks (:data:`fedmap.flower.warm.PROGRAMS`:
    ``flower-superexec`` and ``flwr-clientapp``) into ``bin_dir`` (put it first on the SuperNode's PATH)."""
    for program in warm_server.PROGRAMS:
        path = Path(bin_dir) / program
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(WARM_SHIM.format(python=sys.executable, program=program, socket=sock,
                                         folder=str(Path(sock).parent)))
        path.chmod(0o755)


class WarmChild:
    """A process a warm server forked on request, watched and stopped like a
    :class:`subprocess.Popen`: a rover's SuperNode forked by the rover's warm server
    (``program`` :data:`fedmap.flower.warm.SUPERNODE`), or a rover forked by a local deploy's
    host of rovers (:data:`fedmap.flower.warm.ROVER`). Its output is appended to ``log``. The
    server answers with the child's PID, then with its exit code when it ends. The child runs
    in a process group of its own (its PID is the group's) and dies with the server.
    ``alive()`` says whether the server is still there while we wait for it to listen (at
    most ``timeout`` s)."""

    def __init__(self, sock: str, argv: list[str], *, log: Path, alive: Callable[[], bool],
                 timeout: float = 60.0, program: str = warm_server.SUPERNODE) -> None:
        self.args = [program, str(Path(log).resolve()), *argv]
        self.returncode: int | None = None
        what = "the rover's SuperNode" if program == warm_server.SUPERNODE else "a rover"
        t_end = time.monotonic() + timeout
        while True:
            conn = socket.socket(socket.AF_UNIX)
            try:
                conn.connect(sock)
                break
            except OSError:
                conn.close()
                if time.monotonic() > t_end or not alive():
                    raise FedmapError(f"the warm server for {what} did not answer (its log says why)") from None
                time.sleep(0.05)
        self._conn, self._buf = conn, b""
        conn.sendall(json.dumps(self.args).encode() + b"\n")
        line = self._line(timeout)
        if line is None or not line.startswith("pid "):
            conn.close()
            raise FedmapError(f"the warm server for {what} did not start it (its log says why)")
        self.pid = int(line[4:])

    def _line(self, timeout: float | None) -> str | None:
        """The server's next line, waiting at most ``timeout`` s (None: no line yet); at the
        end of the connection without one, ``"-9"`` (the server died, and its children with it)."""
        t_end = None if timeout is None else time.monotonic() + timeout
        while b"\n" not in self._buf:
            left = None if t_end is None else max(t_end - time.monotonic(), 0.0)
            ready, _, _ = select.select([self._conn], [], [], left)
            if not ready:
                return None
            chunk = self._conn.recv(256)
            if not chunk:
                self._buf += b"-9\n"
                break
            self._buf += chunk
        line, _, self._buf = self._buf.partition(b"\n")
        return line.decode().strip()

    def _ended(self, line: str | None) -> int | None:
        if line is not None:
            self.returncode = int(line) if line.lstrip("-").isdigit() else 1
            self._conn.close()
        return self.returncode

    def poll(self) -> int | None:
        return self.returncode if self.returncode is not None else self._ended(self._line(0.0))

    def wait(self, timeout: float | None = None) -> int:
        if self.returncode is None and self._ended(self._line(timeout)) is None:
            raise subprocess.TimeoutExpired(self.args, timeout or 0.0)
        assert self.returncode is not None
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.poll() is None:
            try:
                os.kill(self.pid, sig)
            except ProcessLookupError:
                pass


def superlink_answers(address: str, *, tls: bool, timeout: float = PROBE_TIMEOUT,
                      client: tuple[Path, Path] | None = None) -> bool:
    """Whether an HTTP(S) server answers at ``HOST:PORT`` right now: what Flower's Fleet API
    is. A port that accepts connections and closes them (a relay whose far end is gone)
    does not count. The certificate is not checked here: the SuperNode checks it. ``client``:
    the rover's certificate and PEM key, which the base's front asks of every client."""
    host, _, port = address.rpartition(":")
    host = host.strip("[]")
    try:
        with socket.create_connection((host, int(port)), timeout=timeout) as raw:
            conn: socket.socket = raw
            if tls:
                ctx = ssl.create_default_context()
                ctx.check_hostname, ctx.verify_mode = False, ssl.CERT_NONE
                if client is not None:
                    ctx.load_cert_chain(str(client[0]), str(client[1]))
                conn = ctx.wrap_socket(raw, server_hostname=host)
            conn.sendall(f"HEAD / HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n".encode())
            return conn.recv(5) == b"HTTP/"
    except (OSError, ValueError):  # ssl.SSLError is an OSError
        return False


def _marks(text: str, marks: tuple[str, ...]) -> bool:
    return any(m in text for m in marks)


def _count_marks(text: str, marks: tuple[str, ...]) -> int:
    return sum(text.count(m) for m in marks)


def run_rover(node_config: dict, *, superlink: str, root_cert: Path | None = None, auth_key: Path | None = None,
              port: int = 0, flwr_home: Path | None = None, log: Path | None = None,
              max_wait: float = ROVER_MAX_WAIT, warm: bool = True, poll: float | None = None,
              rejoin: bool = False, heartbeat: float | None = None) -> int:
    """Run this rover's SuperNode until its run ends; returns 0.

    The SuperNode runs in a process group of its own, stopped as a group (with the SuperExec
    and ClientApps it started) when the rover ends, also on Ctrl-C or SIGTERM; it dies with
    the rover even on SIGKILL (Linux). The rover returns as soon as its ClientApp has
    received the run's final model (it writes the node config's ``done-file``). A
    SuperNode that stops for a reason a retry can fix (the link dropped, the base station
    restarted) is replaced, within the bounds in the module's docstring; any other failure
    (TLS, a refused key) and giving up are one-line :class:`FedmapError`\\ s naming the
    rover. Flower's log goes to ``log`` (default: a temporary folder, removed with
    ``flwr_home``'s default when the rover exits). ``warm``: Flower's per-message ClientApp
    processes are forked from one process that imported torch and fedmap and read the map
    once (:mod:`fedmap.flower.warm`) instead of starting cold. ``poll``: seconds between the
    SuperNode's polls of its SuperLink, and its SuperExec's for a task, when idle (None:
    Flower's 3 s and 1 s; a mission sends a message a sync). ``rejoin``: this rover's key was
    accepted before (the rover was restarted), so a refusal may be the SuperLink still
    listing its old node: it keeps trying, within the bounds above. ``heartbeat``: seconds
    between the SuperNode's heartbeats (None: Flower's 30 s); the SuperLink takes a rover
    whose heartbeat lapsed twice for gone, so a dead rover costs a round 2 x ``heartbeat``
    seconds, not its deadline, and a restarted one is let in again after as long.
    """
    pid = node_config.get("partition-id", "?")
    if root_cert is not None and not Path(root_cert).is_file():
        raise FedmapError(f"rover {pid}: no such CA certificate: {root_cert}")
    if auth_key is not None and not Path(auth_key).is_file():
        raise FedmapError(f"rover {pid}: no such SuperNode private key: {auth_key}")
    if not max_wait > 0:
        raise FedmapError(f"rover {pid}: --max-wait must be positive, got {max_wait}")
    low, high = HEARTBEAT_RANGE
    if heartbeat is not None and not low <= heartbeat <= high:
        raise FedmapError(f"rover {pid}: --heartbeat must be in [{low:g}, {high:g}] s (what the SuperLink "
                          f"accepts), got {heartbeat:g}")
    require_executables(SUPERNODE_EXES)
    root_cert = Path(root_cert).resolve() if root_cert is not None else None
    auth_key = Path(auth_key).resolve() if auth_key is not None else None
    client_cert = None
    if root_cert is not None and auth_key is not None:  # the base's front takes rovers with a certificate of its CA
        client_cert = rover_certificate(auth_key, pid)
    with owned_temp_dir("fedmap-rover-flwr-") as tmp, \
            socket_dir("fedmap-rover-", "clientapp.sock") as socks, Processes() as procs, sigterm_as_interrupt():
        done, refused = Path(tmp) / "done", Path(tmp) / "refused"
        joined = None  # in a state folder of the user's: this rover's key was accepted before
        if node_config.get("mission"):
            if node_config.get("state-dir"):
                joined = Path(str(node_config["state-dir"])) / f"rover{pid}.joined"
                rejoin = rejoin or joined.exists()  # restarted as documented: its old node may still be listed
            # the state folder (a temporary one, kept only while this rover runs, unless the user gave
            # one) is held until this rover process and all it forked end; ``boot`` tells this rover
            # process apart from the one before a restart
            state = str(node_config.get("state-dir") or Path(tmp) / "state")
            hold_state(Path(state), int(pid))
            node_config = {**node_config, "state-dir": state, "boot": f"{os.getpid()}-{time.time_ns()}"}
        cfg = {**node_config, "done-file": str(done), "refused-file": str(refused)}
        log = Path(log) if log is not None else Path(tmp) / "supernode.log"
        env = flower_env(Path(flwr_home) if flwr_home else Path(tmp) / "flwr-home")
        client = None
        if client_cert is not None:  # the SuperNode presents the rover's certificate to the base's front
            assert auth_key is not None
            client = (client_cert, pem_key(auth_key, Path(tmp) / "tls.key"))
            env[CLIENT_CERT_ENV], env[CLIENT_KEY_ENV] = str(client[0]), str(client[1])

        def argv_for(local: int) -> list[str]:
            return supernode_argv(superlink=superlink, port=local, node_config=cfg, root_cert=root_cert,
                                  auth_key=auth_key, max_wait=max_wait)
        if poll is not None:  # how often the SuperNode asks for a message, and its SuperExec for a task
            env[POLL_ENV] = env[SUPEREXEC_POLL_ENV] = str(poll)
        if heartbeat is not None:
            env[HEARTBEAT_ENV] = str(heartbeat)
        server = None
        if warm:  # one process imports torch and fedmap once and forks the SuperNode and a ClientApp per message
            sock = str(socks / "clientapp.sock")  # a short path: a long TMPDIR would not fit a socket's
            write_shim(Path(tmp) / "bin", sock)
            env["PATH"] = os.pathsep.join([str(Path(tmp) / "bin"), env["PATH"]])
            server = fork_warm_server(sock, node_config, env=env, log=log)

        def start(argv: list[str]) -> Proc:  # in its own process group: stopping it stops what it started too
            if server is not None and argv[1:3] == ["-m", SUPERNODE_MODULE]:  # the warm server forks it
                child = WarmChild(sock, argv[3:], log=log, alive=lambda: _running(server))
                return procs.adopt("supernode", child, log=log)
            return procs.start("supernode", argv, env=env, log=log, new_session=True, die_with_parent=True)
        try:
            def reached() -> None:
                if joined is not None:
                    atomic_write_bytes(joined, f"{superlink}\n".encode())
            code = _supervise(procs, pid, superlink, argv_for, start, port=port, done=done, log=log,
                              tls=root_cert is not None, max_wait=max_wait, self_registered=auth_key is None,
                              rejoin=rejoin, client=client, refused=refused, on_reach=reached)
            if joined is not None:  # the mission is over for this rover: the next start is a new one
                joined.unlink(missing_ok=True)
            return code
        finally:
            if server is not None:
                _reap(server)


def rover_certificate(auth_key: Path, pid) -> Path:
    """The rover's TLS client certificate, ``<auth key>.crt`` (``fedmap certs`` makes
    ``roverK.crt`` beside ``roverK``), checked to be for this rover's number; else one line."""
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    cert = Path(f"{auth_key}.crt")
    if not cert.is_file():
        raise FedmapError(f"rover {pid}: no client certificate {cert} beside --auth-key: the base station admits only "
                          f"rovers with one; make them with `fedmap certs DIR --host BASE_HOST --rovers N --force` and "
                          f"give every rover its new files")
    try:
        names = x509.load_pem_x509_certificate(cert.read_bytes()).subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    except ValueError as e:
        raise FedmapError(f"rover {pid}: {cert} is not a PEM certificate ({e})") from None
    cn = str(names[0].value) if names else ""
    if cn.startswith("rover") and cn != f"rover{pid}":
        raise FedmapError(f"rover {pid}: {cert} is {cn}'s certificate (a rover's key is its number): start it with "
                          f"--partition-id {cn[5:]}, or with its own key (--auth-key DIR/rover{pid})")
    return cert


def pem_key(key: Path, out: Path) -> Path:
    """The rover's private key ``key`` (OpenSSH, as Flower's SuperNode reads it) as PEM in
    ``out``, readable by its owner only: what TLS takes for the rover's client certificate."""
    from cryptography.hazmat.primitives import serialization

    try:
        private = serialization.load_ssh_private_key(Path(key).read_bytes(), password=None)
    except (ValueError, TypeError) as e:
        raise FedmapError(f"no usable private key in {key} ({e})") from None
    atomic_write_bytes(out, private.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                                  serialization.NoEncryption()), mode=0o600)
    return out


def fork_warm_server(sock: str, node_config: dict, *, env: dict, log: Path) -> int:
    """Start the warm ClientApp server (:mod:`fedmap.flower.warm`) as a fork of this process;
    returns its PID. This process has already imported fedmap (torch included) and read the
    rover's map, so the server starts in a fraction of a second instead of paying a fresh
    Python's 3 s of imports (``benchmarks/flower_startup.py``). It has run no torch
    operation, so the server and its per-message children start from a clean torch state.
    The server dies with this process (Linux), logs to ``log`` and runs in ``env``."""
    sys.stdout.flush()
    sys.stderr.flush()
    rover = os.getpid()
    child = os.fork()
    if child == 0:  # pragma: no cover - the forked server
        try:
            set_death_signal(rover)
            signal.signal(signal.SIGTERM, signal.SIG_DFL)  # not the rover's handler
            signal.signal(signal.SIGINT, signal.SIG_DFL)
            output_to(log)
            os.environ.clear()
            os.environ.update(env)
            warm_server.serve(sock, node_config)
        except BaseException:  # noqa: BLE001 - the server's failure shows in its log; never return into the rover
            import traceback

            traceback.print_exc()
        finally:
            os._exit(1)  # serve() only returns by failing
    return child


def _running(pid: int) -> bool:
    """Whether this process's child ``pid`` is still running."""
    try:
        return os.waitpid(pid, os.WNOHANG) == (0, 0)
    except ChildProcessError:
        return False


def _reap(pid: int) -> None:
    """Stop the forked warm server and collect it."""
    try:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
    except (ProcessLookupError, ChildProcessError):
        pass


def _supervise(procs: Processes, pid, superlink: str, argv_for: Callable[[int], list[str]],
               start: Callable[[list[str]], Proc], *, port: int, log: Path, done: Path, tls: bool, max_wait: float,
               self_registered: bool, rejoin: bool = False, client: tuple[Path, Path] | None = None,
               refused: Path | None = None, on_reach: Callable[[], None] | None = None) -> int:
    """Run SuperNodes until the run ends for this rover (0) or a one-line failure.

    ``argv_for(p)``: a SuperNode's command with its local API on port ``p``: ``port``, or
    (``port`` 0) a free one, picked again for the next SuperNode when this one's was taken.
    ``start(argv)``: starts it, as ``procs``' ``"supernode"``, logging to ``log``."""
    watch = _Watch(superlink, tls=tls, max_wait=max_wait, self_registered=self_registered, client=client)
    watch.ever_reached, watch.on_reach = rejoin, on_reach
    restarts = 0  # in a row, without the SuperNode reaching its SuperLink in between
    local = port or free_port()
    for total in range(1, ROVER_RESTARTS_TOTAL + 2):
        text = watch.run(procs, start, argv_for(local), log=log, done=done, refused=refused)
        if done.exists():
            return 0
        if refused is not None and refused.exists():  # the base registered this rover's key as another rover's
            raise FedmapError(refused.read_text(errors="replace").strip())
        if port_taken(text):
            if port:
                raise FedmapError(f"rover {pid}: port {port} (--port, the SuperNode's local API) is in use on this "
                                  "machine: give another, or 0 for any free port")
            local = free_port()
        why = rover_failure(pid, superlink, text, max_wait=max_wait, code=procs.procs["supernode"].returncode)
        if not watch.retry(text):
            tls_problem = _tls_refused(text.lower())
            raise FedmapError(_gave_up(pid, superlink, max_wait) if watch.silent() and not tls_problem else why)
        restarts = 1 if watch.reached else restarts + 1
        if restarts > ROVER_RESTARTS or total > ROVER_RESTARTS_TOTAL:
            raise FedmapError(f"{why} (after {total - 1} new SuperNodes, {restarts - 1} in a row)")
        print(f"{why}; starting a new SuperNode ({restarts}/{ROVER_RESTARTS})", file=sys.stderr, flush=True)
        time.sleep(min(0.5 * 2 ** (restarts - 1), PROBE_EVERY))
    raise AssertionError("unreachable: the loop returns or raises")  # pragma: no cover


class _Watch:
    """One SuperNode at a time: started, watched until it stops (or says it has), then judged."""

    def __init__(self, superlink: str, *, tls: bool, max_wait: float, self_registered: bool = False,
                 client: tuple[Path, Path] | None = None) -> None:
        self.superlink, self.tls, self.max_wait, self.client = superlink, tls, max_wait, client
        self.self_registered = self_registered  # no --auth-key: each SuperNode registers a key of its own
        self.contact = time.monotonic()  # last time the SuperLink answered (the rover's start counts)
        self.reached = False  # whether the current SuperNode reached its SuperLink
        self.ever_reached = False  # ... or any of this rover's SuperNodes
        self.on_reach: Callable[[], None] | None = None  # called when a SuperNode first reaches the SuperLink

    def run(self, procs: Processes, starter: Callable[[list[str]], Proc], argv: list[str], *, log: Path,
            done: Path, refused: Path | None = None) -> str:
        """Start a SuperNode (``starter(argv)``, in its own process group: stopping it stops the
        processes it started too, a cold SuperExec and ClientApps, which would otherwise outlive
        it briefly and write into the rover's temporary Flower home, or a warm rover's
        stand-ins; a SuperExec forked by the warm server ends when it sees its SuperNode gone,
        Flower's ``--parent-pid`` check) and wait until it stops, the run is over for this
        rover (``done`` exists) or the SuperLink has been silent for ``max_wait``; returns its log."""
        start = log.stat().st_size if log.exists() else 0  # this SuperNode's lines start here
        p = starter(argv)
        self.reached, probed, ended_at = False, time.monotonic(), None
        text, contacts = "", 0
        while p.poll() is None:
            if done.exists():  # the ClientApp has the final model; its reply is still on its way
                # Flower's SuperNode serves on after a run, and can hang on its way out. Once its last
                # reply is at the SuperLink it is killed, not stopped: a SuperNode that stops deactivates
                # its node, and the SuperLink answers the base with "node unavailable" instead of a reply
                # it holds from a node gone offline; a killed one stays listed until its heartbeat lapses
                sent = _wait_for_last_reply(p, log, start, wait=max(DONE_GRACE, self.max_wait))
                if p.poll() is None:
                    procs.stop("supernode", grace=2.0, sig=signal.SIGKILL if sent else signal.SIGTERM)
                return text
            if refused is not None and refused.exists():
                break
            text = _read_from(log, start)
            now = time.monotonic()
            # every exchange the SuperNode logs is an answer from the SuperLink, not only its first:
            # a SuperLink too busy to answer the probe within its timeout is still there
            if (seen := _count_marks(text, CONTACT)) > contacts:
                contacts, self.contact = seen, now
                if not self.reached and self.on_reach is not None:
                    self.on_reach()
                self.reached = self.ever_reached = True
            if _tls_refused(text.lower()):  # TLS with the base's front: no retry fixes it
                break
            if ended_at is None and _marks(text, ENDED):
                ended_at = now  # Flower's SuperNode can hang after this line: give it END_GRACE s
            if ended_at is not None and now - ended_at > END_GRACE:
                break
            if now - probed > PROBE_EVERY:
                probed = now
                if superlink_answers(self.superlink, tls=self.tls, client=self.client):
                    self.contact = now
            if now - self.contact > self.max_wait:
                break  # retry() says no: the SuperLink has been silent for max_wait
            time.sleep(0.3)
        if p.poll() is None:
            procs.stop("supernode", grace=2.0)
        text = _read_from(log, start)
        if _refused(text.lower()):  # a refusal is an answer: the SuperLink is there, the key is the problem
            self.contact = time.monotonic()
        return text

    def silent(self) -> bool:
        """Whether the SuperLink has not answered for ``max_wait`` seconds."""
        return time.monotonic() - self.contact > self.max_wait

    def retry(self, text: str) -> bool:
        """Whether a new SuperNode may fix what stopped this one, and the SuperLink answered
        within ``max_wait``. Not a certificate that does not verify. Not a refused key either,
        unless the refusal may be the SuperLink refusing a second activation of a node that
        is still listed online (until its heartbeat lapses, ~60 s): the key was accepted
        before, the SuperNode registered its own key (no ``--auth-key``), or its activation
        was sent twice (the first answer lost to the link)."""
        low = text.lower()
        if _tls_refused(low):
            return False
        if _refused(low) and not (self.ever_reached or self.self_registered or "connection attempt failed" in low):
            return False
        return not self.silent()


#: Flower 1.41's SuperNode logs each message it takes as ``Receiving: <type> message (ID: <id>)``
#: (before it pulls the body; ``Received successfully`` follows only once the SuperLink confirmed
#: it, and the ClientApp may have run and finished by then), and one it then failed to take as
#: ``Failed to receive message <id>``; each reply it sent as ``Sent successfully``.
_RECEIVING = re.compile(r"Receiving: \w+ message \(ID: (\w+)\)")
_NOT_RECEIVED = re.compile(r"Failed to receive message (\w+)")


def replies_owed(text: str) -> tuple[int, int]:
    """From a SuperNode's log: how many messages it took, and how many of them still want a reply."""
    taken = set(_RECEIVING.findall(text)) - set(_NOT_RECEIVED.findall(text))
    return len(taken), max(len(taken) - text.count("Sent successfully"), 0)


def _wait_for_last_reply(p: Proc, log: Path, start: int, *, wait: float) -> bool:
    """Wait until the SuperNode has sent a reply for every message it took (True: its log
    says so), it exits, or ``wait`` seconds pass."""
    end = time.monotonic() + wait
    while p.poll() is None and time.monotonic() < end:
        taken, owed = replies_owed(_read_from(log, start))
        if taken and not owed:
            return True
        time.sleep(0.1)
    return False


def _read_from(log: Path, start: int) -> str:
    """The log's text from byte ``start`` on (this SuperNode's part of it)."""
    try:
        with open(log, "rb") as fh:
            fh.seek(start)
            return fh.read().decode(errors="replace")
    except FileNotFoundError:
        return ""


#: A TLS handshake with the base's front that no retry fixes: the rover does not trust
#: the base's certificate, or the front does not accept the rover's (OpenSSL's alerts).
CLIENT_CERT_REFUSED = ("alert unknown ca", "alert certificate required", "alert bad certificate",
                       "alert certificate unknown", "alert certificate expired")


def _tls_refused(low: str) -> bool:
    return "certificate verify failed" in low or any(m in low for m in CLIENT_CERT_REFUSED)


def _refused(low: str) -> bool:
    # Flower 1.41 answers an unregistered key with "[code: 2004] Failed to activate SuperNode."
    # ("[code: 23] Public key already in use" is not a refusal: a self-registering SuperNode
    # whose RegisterNode was answered but the answer lost re-sent it; a new one has a new key)
    return "failed to activate supernode" in low or "unauthenticated" in low


def port_taken(log: str) -> bool:
    """Whether a SuperNode's log says its local API's port was in use (Flower 1.41:
    ``[Errno 98] error while attempting to bind on address (...): address already in use``)."""
    low = log.lower()
    return "error while attempting to bind" in low and "address already in use" in low


def rover_failure(pid, superlink: str, log: str, *, max_wait: float, code: int | None) -> str:
    """One line saying why a rover's SuperNode stopped, from Flower's log."""
    low = log.lower()
    if port_taken(log):
        return f"rover {pid}: another process took the port of its SuperNode's local API"
    lines = [_clean(ln) for ln in log.splitlines() if ln.strip()]
    if any(m in low for m in CLIENT_CERT_REFUSED):
        return (f"rover {pid}: the base station at {superlink} refused this rover's TLS certificate (not made by its "
                f"CA, or expired: give the rover the roverK.crt made with the base's certificates)")
    if "certificate verify failed" in low or "wrong version number" in low:
        why = next((ln for ln in lines if "certificate verify failed" in ln.lower()
                    or "wrong version number" in ln.lower()), "TLS handshake failed")
        return f"rover {pid}: TLS certificate problem with {superlink} (wrong --root-cert?): {why}"
    if _refused(low):
        return (f"rover {pid}: the SuperLink at {superlink} refused this rover's key (not registered with "
                f"--auth-keys on the base station, no --auth-key given, or this rover's previous SuperNode "
                f"stopped less than a minute ago and is still listed online: start it again with --rejoin, which "
                f"retries for that minute)")
    if "unexpected_eof" in low or "401 unauthorized" in low or "already in use" in low or code == 0:
        return f"rover {pid}: the link to {superlink} dropped or its SuperLink restarted"
    if "giving up reconnection" in low or "could not establish a connection" in low:
        return _gave_up(pid, superlink, max_wait)
    tail = [ln for ln in log.splitlines() if "ERROR" in ln or "Error" in ln][-1:] or log.strip().splitlines()[-1:]
    return f"rover {pid}: the Flower SuperNode exited with code {code}" + (f": {_clean(tail[0])}" if tail else "")


def _gave_up(pid, superlink: str, max_wait: float) -> str:
    return (f"rover {pid}: no SuperLink answered at {superlink} for {max_wait:g} s; gave up "
            f"(wrong address or port, the base station is down, or its run is over)")


def _clean(line: str) -> str:
    """A Flower log line without its colour codes and level prefix."""
    line = re.sub(r"\x1b\[[0-9;]*m", "", line).strip()
    return re.sub(r"^(INFO|WARNING|ERROR|DEBUG)\s*:\s*", "", line)

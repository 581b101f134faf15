"""A warm ClientApp for one rover: import torch and fedmap once, fork per message.

Flower 1.41's SuperNode runs every message in a new ``flwr-clientapp`` process, which
imports flwr, torch and fedmap and reads the rover's map again: seconds per message before
any training. ``fedmap rover`` therefore runs this module's *server* once, forked from
itself (:func:`fedmap.flower.rover.fork_warm_server`: the rover has already imported fedmap
and read its map, so the server costs no imports): it imports the ClientApp, reads the
rover's map, and listens on a Unix socket. The SuperNode is given a stand-in
``flwr-clientapp`` (:data:`fedmap.flower.rover.WARM_SHIM`, first on its ``PATH``) that
passes its arguments to the server and waits; the server forks a child that runs Flower's
own ``flwr-clientapp`` entry point with those arguments (already imported: nothing to
load), and reports the child's exit code back to the stand-in. Every child it forks dies with
it (a rover's ClientApps too: nothing of a killed rover runs on) and holds none of its sockets.

Each message still runs in its own process, as Flower expects (its state travels in the
message's context); what is saved is the start-up. The server runs no torch operation
before forking, so the children start from a clean torch state.

The SuperNode's SuperExec (``flower-superexec``, which asks the SuperNode for each
message's task and starts its ``flwr-clientapp``) is forked the same way, once, through a
stand-in of the same kind: Flower's own entry point, without a fresh Python importing
Flower's runtime again (1.5 s of CPU per rover). It dies with the server.

The rover's SuperNode itself is forked the same way, at the rover's own request (no
stand-in: :class:`fedmap.flower.rover.WarmChild`): a fresh ``flower-supernode`` process
imports Flower's runtime first (1.7 s of CPU), and a rover starts one at every start and
after every link fault that ends one. It runs in a process group of its own, as it would
as a process of its own (the rover stops it and what it started as one group), and dies
with the server. The server answers that request with the child's PID first, then its exit code.

``fedmap mission --deploy local`` runs every rover of the team on one machine, and each
rover process would import fedmap, torch and Flower's runtime for itself (about 5 s of CPU
before it connects). It starts one *host* instead (:func:`serve_rovers`, run by
:mod:`fedmap.cli.rover_host`), which imports all of that once and forks each rover process
(``fedmap rover ...``, :data:`ROVER`) at the deploy's request, the same way: a process group
of its own, its output to the rover's log, the PID and then the exit code sent back. A rover
then forks its warm server and SuperNode from itself as ever, with nothing left to import.
"""

from __future__ import annotations

import json
import os
import select
import signal
import socket
import sys
import threading
from collections.abc import Callable

#: The Flower programs this server forks, by the name the SuperNode starts them with (each has a
#: stand-in of that name: :func:`fedmap.flower.rover.write_shim`).
PROGRAMS = ("flower-superexec", "flwr-clientapp")
#: The program the rover asks for itself (:class:`fedmap.flower.rover.WarmChild`): its SuperNode
#: (:mod:`fedmap.flower.supernode`), in a process group of its own; the request's first argument
#: is the log its output goes to, and the answer starts with ``pid <PID>``.
SUPERNODE = "flower-supernode"
#: The program a local deploy asks its host of rovers for (:func:`serve_rovers`): a rover process,
#: ``fedmap rover`` with the request's arguments, in a process group of its own; the request's
#: first argument is the log its output goes to, and the answer starts with ``pid <PID>``.
ROVER = "fedmap-rover"
#: Seconds the server, listening, waits for a first request before it loads what the ClientApps
#: need (a rover asks for its SuperNode within 0.05 s; a predictor's site starts its own).
FIRST_WAIT = 1.0


def _run_task(program: str, argv: list[str]) -> None:  # pragma: no cover - runs in a forked child
    """Flower's own ``program`` entry point with ``argv``, in this process, forked by the server."""
    from fedmap.flower.snapshot.client import flower_superexec_main, flwr_clientapp_main

    def run() -> None:
        if program == SUPERNODE:  # a process group of its own, as the rover's Processes give
            from fedmap.flower.supernode import main as supernode_main

            supernode_main(_own_group(argv))
        elif program == "flower-superexec":
            flower_superexec_main(argv)
        else:
            flwr_clientapp_main(argv)
    _exit_with(run)


def _own_group(argv: list[str]) -> list[str]:  # pragma: no cover - runs in a forked child
    """In a child forked at a request for a program in a process group of its own (the request's
    first argument is its log): that group, the output to the log; the program's arguments."""
    from fedmap.flower.launch import output_to

    os.setpgid(0, 0)
    log, *rest = argv
    output_to(log)
    return rest


def _exit_with(run: Callable[[], object]) -> None:  # pragma: no cover - runs in a forked child
    """Run ``run()`` and end this forked child with its exit code, as a process would end: an int
    returned or passed to :class:`SystemExit`, 0 for anything else, 1 for any other exception."""
    code = 0
    try:
        result = run()
        code = result if isinstance(result, int) else 0
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    except BaseException:  # noqa: BLE001 - report any failure as an exit code, like a process would
        import traceback

        traceback.print_exc()
        code = 1
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


#: The requests' connections this server holds open until their child ends (:func:`_answer`): a
#: child forked for one request closes the others', or a requester would wait past the server's
#: death for the end of a connection the child still held (a killed rover's warm server once left
#: its SuperExec's stand-in and a ClientApp running for hours that way).
_HELD: set[socket.socket] = set()


def _answer(conn: socket.socket, pid: int) -> None:
    """Wait for the child ``pid`` and send its exit code to the stand-in."""
    _, status = os.waitpid(pid, 0)
    try:
        conn.sendall(f"{os.waitstatus_to_exitcode(status)}\n".encode())
    except OSError:
        pass
    finally:
        conn.close()  # then forgotten: a child forked in between closes it again, a no-op
        _HELD.discard(conn)


def preload(node_config: dict) -> None:
    """What every child would otherwise import or read for itself: done once, before forking."""
    # torch imports its compiler lazily, at the first optimiser built (torch.optim wraps its methods in
    # torch._dynamo.disable): 1.3 s of imports, paid by every child that trains unless done here
    # (86 % of the children's CPU time in a deployed mission, measured with py-spy). Imports only:
    # still no torch operation before the fork.
    import torch._dynamo  # noqa: F401

    import fedmap.flower.snapshot.client  # noqa: F401 - the imports the children no longer pay (Flower's runtime too)
    import fedmap.flower.supernode  # noqa: F401 - the SuperNode's (nothing more than the ClientApp's, measured)

    if node_config.get("mission"):  # a mission rover: its world comes with the base's first order
        import fedmap.flower.mission.client  # noqa: F401
        from fedmap.mission.network.remote import warm_up

        warm_up()  # the compiled planners, loaded once: the children inherit them
    elif "samples" in node_config:  # a site of the predictor's fine-tuning (fedmap.flower.predictor.deploy)
        import fedmap.flower.predictor.client  # noqa: F401
    else:
        from fedmap.flower.task import load_local_map

        load_local_map(node_config)  # cached: the children inherit the rover's map


def _listen(sock: str) -> socket.socket:
    srv = socket.socket(socket.AF_UNIX)
    srv.bind(sock)
    srv.listen(16)
    return srv


def _request(srv: socket.socket) -> tuple[socket.socket, str, list[str]] | None:
    """The next request: its connection, program and arguments (None: not one)."""
    conn, _ = srv.accept()
    line = conn.makefile().readline()
    try:
        program, *argv = [str(a) for a in json.loads(line)]
    except ValueError:
        conn.close()
        return None
    return conn, program, argv


def _fork(srv: socket.socket, conn: socket.socket, child: Callable[[], None], *, own_group: bool) -> None:
    """Fork ``child()`` (it never returns) and send its exit code on ``conn`` when it ends;
    ``own_group``: it runs in a process group of its own (set here too, so the group exists
    before the requester may signal it), and its PID is sent first. The child dies with this
    server (which answers for it) and holds none of its sockets."""
    server = os.getpid()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the forked child
        try:
            from fedmap.flower.launch import set_death_signal

            for held in (srv, conn, *_HELD):
                held.close()
            _HELD.clear()
            set_death_signal(server)
        except BaseException:  # noqa: BLE001 - never fall back into the server's loop
            os._exit(1)
        child()
    if own_group:
        try:
            os.setpgid(pid, pid)
            conn.sendall(f"pid {pid}\n".encode())
        except OSError:  # the requester is gone: so is the reason for the child
            os.kill(pid, signal.SIGKILL)
    _HELD.add(conn)
    threading.Thread(target=_answer, args=(conn, pid), daemon=True).start()


def serve(sock: str, node_config: dict) -> None:  # pragma: no cover - a long-lived process
    """Import once, then fork a process per request until killed.

    It listens as soon as Flower's SuperNode is imported, and imports the rest
    (:func:`preload`) only after forking the rover's SuperNode, its first request: the SuperNode
    connects to the SuperLink while the server loads what the ClientApps need. A request for a
    ClientApp or a SuperExec made earlier waits until that is loaded."""
    import fedmap.flower.supernode  # noqa: F401 - what a SuperNode needs

    srv = _listen(sock)
    loaded = False
    while True:
        if not loaded:  # the rover asks for its SuperNode as soon as the server listens
            ready, _, _ = select.select([srv], [], [], FIRST_WAIT)
            if not ready:  # nobody asked: load now
                preload(node_config)
                loaded = True
        request = _request(srv)
        if request is None:
            continue
        conn, program, argv = request
        if program not in (*PROGRAMS, SUPERNODE):
            conn.close()
            continue
        if program != SUPERNODE and not loaded:
            preload(node_config)
            loaded = True
        _fork(srv, conn, lambda: _run_task(program, argv), own_group=program == SUPERNODE)


def serve_rovers(sock: str, rover: Callable[[list[str]], object]) -> None:  # pragma: no cover - a long-lived process
    """The host of a local deploy's rovers: import what a mission rover, its warm server and its
    SuperNode need, once, then fork ``rover(argv)`` (``fedmap rover``'s entry point) per
    :data:`ROVER` request until killed. Each rover runs in a process group of its own with its
    output in the request's log, and dies with the host. The host runs no torch operation."""
    preload({"mission": True})
    srv = _listen(sock)
    while True:
        request = _request(srv)
        if request is None:
            continue
        conn, program, argv = request
        if program != ROVER:
            conn.close()
            continue

        def child(argv: list[str] = argv) -> None:  # pragma: no cover - the forked rover
            rest = _own_group(argv)
            _exit_with(lambda: rover(rest))
        _fork(srv, conn, child, own_group=True)


if __name__ == "__main__":  # pragma: no cover - ``python -m fedmap.flower.warm SOCKET NODE_CONFIG_JSON``
    serve(sys.argv[1], json.loads(sys.argv[2]))  # a server started as its own process (the predictor's sites)

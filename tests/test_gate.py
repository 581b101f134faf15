"""Nobody but the rovers reaches a base station, and only its Fleet API.

The attack that worked on Flower 1.41's SuperLink as fedmap used to start it: from a folder
holding only the public ``ca.crt``, ``flwr ls`` listed the runs and ``flwr run ./evilapp``
made the base run that app. Here it is repeated against real processes on loopback: the
base's front on 127.0.0.3, the attacker's ``flwr`` (its own connection, with and without a
rover's key), and requests straight to the front and to the SuperLink behind it.
"""

from __future__ import annotations

import asyncio
import os
import ssl
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("flwr")
httpx = pytest.importorskip("httpx")

from fedmap.errors import FedmapError  # noqa: E402
from fedmap.flower import gate  # noqa: E402
from fedmap.flower.launch import (  # noqa: E402
    CONNECTION,
    Processes,
    Tls,
    flower_env,
    free_port,
    make_certs,
    start_superlink,
    write_connection,
)
from fedmap.flower.rover import rover_certificate  # noqa: E402
from fedmap.flower.task import check_key, parse_rover_nodes, rover_nodes_text  # noqa: E402

EVIL_APP = """
[build-system]
requires = ["hatchling"]
build-backend = "hatchling.build"

[project]
name = "evilapp"
version = "1.0.0"
dependencies = []

[tool.hatch.build.targets.wheel]
packages = ["."]

[tool.flwr.app]
publisher = "evil"

[tool.flwr.app.components]
serverapp = "evil:app"
clientapp = "evil:client"

[tool.flwr.app.config]
marker = "{marker}"
"""

EVIL_CODE = """
from pathlib import Path
from flwr.serverapp import ServerApp
from flwr.clientapp import ClientApp

app = ServerApp()
client = ClientApp()

@app.main()
def main(grid, context):
    Path(context.run_config["marker"]).write_text("foreign code ran on the base station")
"""


def _asgi(app, method: str, path: str, headers: dict | None = None) -> int:
    async def go() -> int:
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://base") as c:
            return (await c.request(method, path, headers=headers or {})).status_code
    return asyncio.run(go())


def test_the_control_guard_lets_through_only_the_secret_or_the_open_routes():
    async def inner(scope, receive, send):
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"ok"})
    guarded = gate.ControlGuard(inner, b"s" * 32)
    assert _asgi(guarded, "POST", "/v1/control/start-run") == 403
    assert _asgi(guarded, "POST", "/v1/control/list-runs", {gate.CONTROL_HEADER: "s" * 31 + "t"}) == 403
    assert _asgi(guarded, "POST", "/v1/control/list-runs", {gate.CONTROL_HEADER: "s" * 32}) == 200
    assert _asgi(guarded, "GET", "/docs") == 403  # anything not known to be open needs the secret
    assert _asgi(guarded, "POST", "/v1/fleet/pull-messages") == 200
    assert _asgi(guarded, "POST", "/v1/runtime/pull-task-input") == 200
    with pytest.raises(ValueError):
        gate.ControlGuard(inner, b"short")


def test_the_front_passes_nothing_but_the_fleet_api_and_bounds_bodies():
    seen = []

    async def inner(scope, receive, send):
        body = b""
        while True:
            event = await receive()
            body += event.get("body", b"")
            if not event.get("more_body"):
                break
        seen.append((scope["path"], len(body), dict(scope["headers"]).get(gate.CONTROL_HEADER.encode())))
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"ok"})
    front = gate.FleetOnly(inner, max_body=1000)
    assert _asgi(front, "POST", "/v1/control/start-run") == 404
    assert _asgi(front, "POST", "/v1/control/list-runs", {gate.CONTROL_HEADER: "guess"}) == 404
    assert _asgi(front, "GET", "/v1/fleet/pull-messages") == 404
    assert _asgi(front, "POST", "/v1/runtime/create-task") == 404
    assert _asgi(front, "POST", "/docs") == 404
    assert seen == []
    assert _asgi(front, "POST", "/v1/fleet/pull-messages", {gate.CONTROL_HEADER: "x"}) == 200  # the only kind it passes
    assert seen == [("/v1/fleet/pull-messages", 0, None)]  # without the header
    assert _asgi(front, "POST", "/v1/fleet/pull-messages", {"content-length": str(1 << 30)}) == 413

    async def big(chunked: bool) -> int:
        async def parts():
            for _ in range(11):
                yield b"x" * 100
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=front), base_url="http://base") as c:
            body = parts() if chunked else b"x" * 1001
            return (await c.post("/v1/fleet/push-object", content=body)).status_code
    assert asyncio.run(big(False)) == 413
    assert asyncio.run(big(True)) == 413


def _flwr(home: Path, *args: str) -> subprocess.CompletedProcess:
    env = flower_env(home)
    env.pop("FEDMAP_CONTROL_SECRET_FILE", None)
    return subprocess.run([str(Path(sys.executable).parent / "flwr"), *args], env=env, capture_output=True, text=True,
                          timeout=120, stdin=subprocess.DEVNULL)


@pytest.mark.slow
@pytest.mark.xdist_group("loopback-c")
def test_the_attack_on_the_control_api_fails_from_another_address_and_a_rover_still_gets_through(tmp_path):
    """The base's front on 127.0.0.3 (TLS, rover keys registered), the attacker's flwr on its
    own connection from a folder with the public ca.crt only: ``flwr ls``, ``flwr run`` of a
    foreign app and ``flwr stop`` all fail and no foreign code runs. A client with a rover's
    certificate reaches the Fleet API and nothing else; the SuperLink behind the front (on
    127.0.0.1) refuses its Control API without the launcher's secret, and answers it with."""
    certs = tmp_path / "certs"
    make_certs(certs, hosts=["127.0.0.3"], rovers=2)
    work = tmp_path / "base"
    env = flower_env(work / "flwr-home")
    port = free_port("127.0.0.3")
    marker = tmp_path / "pwned"
    evil = tmp_path / "evilapp"
    evil.mkdir()
    (evil / "pyproject.toml").write_text(EVIL_APP.format(marker=marker))
    (evil / "evil.py").write_text(EVIL_CODE)
    attacker = tmp_path / "attacker"
    attacker.mkdir()
    (attacker / "ca.crt").write_bytes((certs / "ca.crt").read_bytes())
    with Processes() as procs:
        address, nodes = start_superlink(procs, host="127.0.0.3", port=port, tls=Tls.from_dir(certs), auth=True,
                                         env=env, work=work, keys=sorted(certs.glob("*.pub")))
        assert address == f"127.0.0.3:{port}"  # the launcher's own control calls (registering the keys) work
        assert sorted(nodes.values()) == [0, 1] and parse_rover_nodes(rover_nodes_text(nodes)) == nodes
        write_connection(attacker / "home", address=address, root_cert=attacker / "ca.crt")
        for args in (["ls", CONNECTION], ["run", str(evil), CONNECTION], ["stop", "1234", CONNECTION]):
            r = _flwr(attacker / "home", *args)
            assert r.returncode != 0, (args, r.stdout[-500:], r.stderr[-500:])
        # the attacker's flwr on the base machine itself, straight at the SuperLink (no secret)
        inner = Path(env["FLWR_HOME"], "config.toml").read_text().split('address = "')[1].split('"')[0]
        assert len([p for p in procs.procs if p == "superlink"]) == 1  # one process serves both
        assert inner.startswith("127.0.0.1:") and inner != address
        write_connection(attacker / "local", address=inner, root_cert=certs / "ca.crt")
        for args in (["ls", CONNECTION], ["run", str(evil), CONNECTION]):
            r = _flwr(attacker / "local", *args)
            assert r.returncode != 0, (args, r.stdout[-500:], r.stderr[-500:])

        # with a rover's certificate: the Fleet API is there, the Control API is not
        key = tmp_path / "rover0.pem"
        from cryptography.hazmat.primitives import serialization

        private = serialization.load_ssh_private_key((certs / "rover0").read_bytes(), password=None)
        key.write_bytes(private.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                              serialization.NoEncryption()))
        ctx = ssl.create_default_context(cafile=str(certs / "ca.crt"))
        ctx.load_cert_chain(str(certs / "rover0.crt"), str(key))
        with httpx.Client(verify=ctx, timeout=30) as c:
            assert c.post(f"https://{address}/v1/control/list-runs", content=b"").status_code == 404
            assert c.post(f"https://{address}/v1/control/start-run", content=b"").status_code == 404
            fleet = c.post(f"https://{address}/v1/fleet/get-run", content=b"")
            print("fleet:", fleet.status_code, fleet.text[:200])
            assert fleet.status_code != 404 and "fedmap" not in fleet.text  # Flower answered: the front forwarded it
        # without a certificate of the base's CA no HTTP is read at all
        bare = ssl.create_default_context(cafile=str(certs / "ca.crt"))
        with httpx.Client(verify=bare, timeout=30) as c, pytest.raises(httpx.HTTPError):
            c.post(f"https://{address}/v1/fleet/get-run", content=b"")
        # the SuperLink itself (loopback): the Control API needs the launcher's secret
        plain = ssl.create_default_context(cafile=str(certs / "ca.crt"))
        plain.check_hostname = False
        with httpx.Client(verify=plain, timeout=30) as c:
            assert c.post(f"https://{inner}/v1/control/list-runs", content=b"").status_code == 403
            secret = Path(env["FEDMAP_CONTROL_SECRET_FILE"]).read_text().strip()
            ok = c.post(f"https://{inner}/v1/control/list-runs", content=b"", headers={gate.CONTROL_HEADER: secret})
            assert ok.status_code != 403
        assert os.stat(Path(env["FEDMAP_CONTROL_SECRET_FILE"])).st_mode & 0o077 == 0
    assert not marker.exists()
    assert not Path(env["FEDMAP_CONTROL_SECRET_FILE"]).exists()  # gone with the processes that needed it


def test_a_rovers_key_is_its_number(tmp_path):
    """A certificate made for rover 0 is refused as rover 1 before connecting, and a rover the
    base registered as rover 0 refuses to run as rover 1, saying so in its refused-file."""
    make_certs(tmp_path, hosts=["127.0.0.1"], rovers=2)
    assert rover_certificate(tmp_path / "rover1", 1) == Path(f"{tmp_path / 'rover1'}.crt")
    with pytest.raises(FedmapError, match=r"rover 1: .*rover0's certificate.*--partition-id 0"):
        rover_certificate(tmp_path / "rover0", 1)
    (tmp_path / "rover1.crt").unlink()
    with pytest.raises(FedmapError, match="no client certificate"):
        rover_certificate(tmp_path / "rover1", 1)
    refused = tmp_path / "refused"
    check_key({"partition-id": 0, "refused-file": str(refused)}, 0)
    check_key({"partition-id": 0, "refused-file": str(refused)}, -1)
    assert not refused.exists()
    with pytest.raises(FedmapError, match="registered this rover's key as rover 0's"):
        check_key({"partition-id": 1, "refused-file": str(refused)}, 0)
    assert "rover 1" in refused.read_text()


def test_certificates_are_private_where_they_hold_a_key(tmp_path):
    files = make_certs(tmp_path, hosts=["base.example"], rovers=1, keep_ca_key=False)
    names = {f.name for f in files}
    assert "ca.key" not in names and {"rover0", "rover0.pub", "rover0.crt", "server.key"} <= names
    for f in files:
        private = f.name.endswith(".key") or f.name == "rover0"
        assert (os.stat(f).st_mode & 0o077 == 0) == private, f.name
    from cryptography import x509

    sans = x509.load_pem_x509_certificate((tmp_path / "server.pem").read_bytes()).extensions.get_extension_for_class(
        x509.SubjectAlternativeName).value
    assert {"base.example", "localhost"} <= set(sans.get_values_for_type(x509.DNSName))


def test_a_rover_whose_certificate_the_front_refuses_is_told_so_and_not_retried():
    from fedmap.flower import rover

    log = "ERROR: [SSL: TLSV1_ALERT_UNKNOWN_CA] tlsv1 alert unknown ca (_ssl.c:2580)"
    why = rover.rover_failure(2, "base:9092", log, max_wait=30, code=1)
    assert why.startswith("rover 2: the base station at base:9092 refused this rover's TLS certificate")
    watch = rover._Watch("127.0.0.1:1", tls=True, max_wait=30)
    watch.ever_reached = True
    assert not watch.retry(log)
    assert watch.retry("Connection attempt failed, retrying in 2 s")

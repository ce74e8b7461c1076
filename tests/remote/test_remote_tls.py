"""``tls://``: the clock server's protocol inside TLS 1.3, between machines.

Certificates are made at test time (``trustme``: a CA, a server certificate for 127.0.0.1,
and a second CA that signed nothing of the server's). The simulation runs in the test
process; participants and impostor servers are real processes on 127.0.0.1.
"""

from __future__ import annotations

import asyncio
import json
import os
import secrets
import ssl
from pathlib import Path
from typing import Any

import pytest
from _remote_helpers import ROOT, finish, read_line, spawn

import evclock
from evclock.remote._address import parse_address
from evclock.remote._participant import RemoteClockSource
from evclock.remote._tls import certificate_fingerprint

trustme = pytest.importorskip("trustme")

TOKEN = secrets.token_urlsafe(32)


class Certs:
    """PEM files of a test PKI: the server's CA, its certificate and key, another CA."""

    def __init__(self, folder: Path) -> None:
        ca, other = trustme.CA(), trustme.CA()
        leaf = ca.issue_cert("127.0.0.1", "localhost")
        self.ca = folder / "ca.pem"
        self.other_ca = folder / "other-ca.pem"
        self.cert = folder / "server.pem"
        self.key = folder / "server.key"
        ca.cert_pem.write_to_path(str(self.ca))
        other.cert_pem.write_to_path(str(self.other_ca))
        leaf.private_key_pem.write_to_path(str(self.key))
        leaf.cert_chain_pems[0].write_to_path(str(self.cert))
        for pem in leaf.cert_chain_pems[1:]:
            pem.write_to_path(str(self.cert), append=True)
        der = ssl.PEM_cert_to_DER_cert(leaf.cert_chain_pems[0].bytes().decode())
        self.fingerprint = certificate_fingerprint(der)
        # A certificate of the other CA: an impostor's.
        impostor = other.issue_cert("127.0.0.1")
        self.impostor_cert = folder / "impostor.pem"
        self.impostor_key = folder / "impostor.key"
        impostor.cert_chain_pems[0].write_to_path(str(self.impostor_cert))
        impostor.private_key_pem.write_to_path(str(self.impostor_key))


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Certs:
    return Certs(tmp_path_factory.mktemp("pki"))


# A lockstep participant that exercises the data channel both ways: it publishes what it saw,
# receives the simulation's data (a large payload among it, many TLS records long) and calls
# a service whose answer is large; it prints everything it observed.
WORKER = """
import hashlib, json, sys, evclock

async def main():
    clock = evclock.clock()
    link = evclock.remote.participant()
    seen = []
    link.subscribe("world", lambda m: seen.append(
        [m.time.nanoseconds, clock.now().nanoseconds, m.sender, hashlib.sha256(m.data).hexdigest()]
    ))
    for i in range(40):
        await clock.sleep(0.001 * (1 + i % 3))
        seen.append(["t", clock.now().nanoseconds])
        link.publish("tick", (str(i) * (1 + 5000 * (i % 7))).encode())
        if i % 10 == 9:
            answer = link.call("echo", bytes(range(256)) * (i * 100))
            seen.append(["call", len(answer), hashlib.sha256(answer).hexdigest()])
    print(json.dumps({"seen": seen, "info": link.info, "errors": link.errors}))

evclock.run(main())
"""


def lockstep_run(tmp_path: Path, url: str, clock_url: str, **serve: Any) -> dict[str, Any]:
    """One deterministic run of WORKER against a simulation served at ``url``: everything
    both sides observed."""
    proc = spawn(tmp_path, WORKER, EVCLOCK_CLOCK=f"{clock_url}&name=worker")
    handled: list[Any] = []

    async def main() -> int:
        clock = evclock.clock()
        async with evclock.remote.serve(url, token=TOKEN, info={"seed": 7}, **serve) as server:
            assert server.address.startswith(url.split(":")[0])
            server.provide("echo", lambda data: data[::-1])

            def on_tick(message: evclock.remote.Message) -> None:
                handled.append([message.time.nanoseconds, clock.now().nanoseconds, message.data])
                n = len(handled)
                server.publish("world", bytes([n % 251]) * (n * 3000))

            server.subscribe("tick", on_tick)
            await server.wait_for_participants("worker")
            await server.wait_until_left()
            return clock.now().nanoseconds

    end = evclock.run(main())
    code, out, err = finish(proc)
    assert code == 0, err
    return {"end": end, "handled": handled, "participant": json.loads(out)}


def tls_url(certs: Certs, port_url: str) -> str:
    return f"{port_url}?token={TOKEN}&tls_ca={certs.ca}"


def served_url(scheme: str) -> str:
    return f"{scheme}://127.0.0.1:0"


def test_a_lockstep_run_over_tls_is_bit_identical_to_plain_tcp(
    tmp_path: Path, certs: Certs
) -> None:
    runs = {}
    for scheme in ("tcp", "tls"):
        tls = {"tls_cert": str(certs.cert), "tls_key": str(certs.key)} if scheme == "tls" else {}
        port = _free_port()
        url = f"{scheme}://127.0.0.1:{port}"
        clock_url = f"{url}?token={TOKEN}" + (f"&tls_ca={certs.ca}" if scheme == "tls" else "")
        runs[scheme] = lockstep_run(tmp_path, url, clock_url, **tls)
    assert runs["tls"] == runs["tcp"]
    plain = runs["tcp"]
    # It did exchange what it should: 40 ticks, payloads of up to 60 KB both ways (TLS records
    # are 16 KiB at most), 4 calls with answers up to 100 KB.
    assert len(plain["handled"]) == 40
    assert max(len(data) for _, _, data in plain["handled"]) > 3 * 16384
    calls = [entry for entry in plain["participant"]["seen"] if entry[0] == "call"]
    assert [entry[1] for entry in calls] == [256 * 900, 256 * 1900, 256 * 2900, 256 * 3900]
    assert plain["participant"]["info"] == {"seed": 7}
    assert plain["participant"]["errors"] == []


def test_a_pinned_fingerprint_verifies_the_server(tmp_path: Path, certs: Certs) -> None:
    port = _free_port()
    url = f"tls://127.0.0.1:{port}"
    # Lower case, colons dropped: the same fingerprint.
    pinned = certs.fingerprint.replace(":", "").lower()
    run = lockstep_run(
        tmp_path,
        url,
        f"{url}?token={TOKEN}&tls_fingerprint={pinned}",
        tls_cert=str(certs.cert),
        tls_key=str(certs.key),
    )
    assert len(run["handled"]) == 40


def _free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


# An impostor TLS server (a real process): it presents the certificate it is given, then
# records every byte of the protocol a participant sends it, and prints what happened.
IMPOSTOR = """
import json, socket, ssl, sys

cert, key = sys.argv[1], sys.argv[2]
context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
context.load_cert_chain(cert, key)
listener = socket.socket()
listener.bind(("127.0.0.1", 0))
listener.listen(1)
listener.settimeout(30)
print(listener.getsockname()[1], flush=True)
conn, _ = listener.accept()
conn.settimeout(30)
report = {"handshake": "done", "received": 0}
try:
    tls = context.wrap_socket(conn, server_side=True)
except (ssl.SSLError, OSError) as exc:
    report["handshake"] = f"failed: {exc}"
else:
    try:
        while data := tls.recv(65536):
            report["received"] += len(data)
    except (ssl.SSLError, OSError) as exc:
        report["ended"] = str(exc)
print(json.dumps(report), flush=True)
"""


@pytest.mark.parametrize("verify", ["ca", "fingerprint"])
def test_an_impostor_server_is_refused_before_anything_is_sent(
    tmp_path: Path, certs: Certs, verify: str
) -> None:
    impostor = spawn(tmp_path, IMPOSTOR, str(certs.impostor_cert), str(certs.impostor_key))
    port = int(read_line(impostor))
    url = f"tls://127.0.0.1:{port}?token={TOKEN}&timeout=10"
    if verify == "ca":
        expected = (
            f"the clock server at tls://127.0.0.1:{port} presented a certificate that does not "
            "verify (unable to get local issuer certificate): it is not the simulation you "
            "meant, or tls_ca names another CA"
        )
        with pytest.raises(evclock.remote.JoinRefusedError) as refused:
            RemoteClockSource(f"{url}&tls_ca={certs.ca}")
    else:
        expected = (
            f"the clock server at tls://127.0.0.1:{port} presented a certificate with SHA-256 "
            "fingerprint "
        )
        with pytest.raises(evclock.remote.JoinRefusedError) as refused:
            RemoteClockSource(f"{url}&tls_fingerprint={certs.fingerprint}")
        assert f"not the pinned {certs.fingerprint}" in str(refused.value)
    assert str(refused.value).startswith(expected)
    assert str(refused.value).endswith("nothing was sent to it")
    code, out, err = finish(impostor)
    assert code == 0, err
    report = json.loads(out)
    assert report["received"] == 0  # not a HELLO, not a byte of the protocol
    if verify == "ca":  # the participant ended the TLS handshake itself
        assert report["handshake"].startswith("failed:")
    else:  # TLS was up, the certificate was not the pinned one: closed with nothing said
        assert report["handshake"] == "done"


def test_a_certificate_for_another_host_is_refused(tmp_path: Path) -> None:
    # Signed by the CA the participant trusts, but for another host: not the server at
    # 127.0.0.1.
    ca = trustme.CA()
    leaf = ca.issue_cert("sim.example.org")
    cert, key, ca_file = tmp_path / "named.pem", tmp_path / "named.key", tmp_path / "ca.pem"
    leaf.cert_chain_pems[0].write_to_path(str(cert))
    leaf.private_key_pem.write_to_path(str(key))
    ca.cert_pem.write_to_path(str(ca_file))
    named = spawn(tmp_path, IMPOSTOR, str(cert), str(key))
    port = int(read_line(named))
    with pytest.raises(evclock.remote.JoinRefusedError, match="IP address mismatch"):
        RemoteClockSource(f"tls://127.0.0.1:{port}?token={TOKEN}&timeout=10&tls_ca={ca_file}")
    code, out, err = finish(named)
    assert code == 0, err
    assert json.loads(out)["received"] == 0


def test_a_plain_participant_is_told_the_server_speaks_tls(tmp_path: Path, certs: Certs) -> None:
    async def main() -> tuple[str, str]:
        loop = asyncio.get_running_loop()
        async with evclock.remote.serve(
            "tls://127.0.0.1:0", token=TOKEN, tls_cert=str(certs.cert), tls_key=str(certs.key)
        ) as server:
            plain = server.address.replace("tls://", "tcp://")
            proc = spawn(tmp_path, WORKER, EVCLOCK_CLOCK=f"{plain}?token={TOKEN}&timeout=10")
            code, _, err = await loop.run_in_executor(None, finish, proc)
            assert code == 1
            assert server.participants == ()
        return err.strip().splitlines()[-1], server.address

    error, served = evclock.run(main())
    plain = served.replace("tls://", "tcp://")
    # It refuses in plain text, saying it serves TLS only: the participant (with a token)
    # shows nothing an unproven server wrote, only what to do.
    assert error == (
        f"evclock.remote.JoinRefusedError: the clock server at {plain} serves TLS only: join "
        f"it with {served}, verified with tls_ca or tls_fingerprint (evclock control: "
        "--tls-ca or --tls-fingerprint); nothing but the HELLO was sent to it"
    )


def test_a_tls_participant_is_told_the_server_is_plain(tmp_path: Path, certs: Certs) -> None:
    async def main() -> tuple[str, str]:
        loop = asyncio.get_running_loop()
        async with evclock.remote.serve("tcp://127.0.0.1:0", token=TOKEN) as server:
            tls = server.address.replace("tcp://", "tls://")
            proc = spawn(
                tmp_path, WORKER, EVCLOCK_CLOCK=f"{tls}?token={TOKEN}&timeout=10&tls_ca={certs.ca}"
            )
            code, _, err = await loop.run_in_executor(None, finish, proc)
            assert code == 1
            assert server.participants == ()
        return err.strip().splitlines()[-1], tls

    error, tls = evclock.run(main())
    assert error.startswith(
        f"evclock.ClockLostError: the TLS handshake with the clock server at {tls} failed ("
    )
    assert error.endswith(
        "is it serving tls://? A simulation served on tcp:// speaks plain TCP (join it with tcp://)"
    )


def test_a_stalled_tls_handshake_does_not_hold_up_others(tmp_path: Path, certs: Certs) -> None:
    # A connection that sends half a ClientHello and stops: the server's handshake never
    # blocks on it, and an honest participant joins meanwhile.
    import socket

    async def main() -> dict[str, Any]:
        loop = asyncio.get_running_loop()
        async with evclock.remote.serve(
            "tls://127.0.0.1:0", token=TOKEN, tls_cert=str(certs.cert), tls_key=str(certs.key)
        ) as server:
            host_port = server.address.removeprefix("tls://")
            host, port = host_port.rsplit(":", 1)
            stalled = socket.create_connection((host, int(port)))
            stalled.sendall(b"\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03")
            proc = spawn(
                tmp_path,
                WORKER,
                EVCLOCK_CLOCK=f"{server.address}?token={TOKEN}&tls_ca={certs.ca}&name=worker",
            )
            server.provide("echo", lambda data: data)
            await server.wait_for_participants("worker", timeout=30)
            await server.wait_until_left()
            code, out, err = await loop.run_in_executor(None, finish, proc)
            stalled.close()
        assert code == 0, err
        result: dict[str, Any] = json.loads(out)
        return result

    assert len(evclock.run(main())["seen"]) == 44


def test_allow_remote_needs_tls_and_a_token(certs: Certs) -> None:
    tls = {"tls_cert": str(certs.cert), "tls_key": str(certs.key)}

    def serving(url: str, **options: Any) -> None:
        async def main() -> str:
            async with evclock.remote.serve(url, **options) as server:
                return server.address

        evclock.run(main())

    with pytest.raises(evclock.InvalidArgumentError) as no_token:
        serving("tls://0.0.0.0:0", allow_remote=True, **tls)
    assert str(no_token.value).startswith(
        "serving on tls://0.0.0.0:0 needs a shared token (token=... or ?token=... in the "
        "address): any user of the machine can reach a tls port"
    )
    # allow_remote is for tls:// alone: refused on any tcp:// address, loopback or not, and
    # on a Unix socket.
    for url in ("tcp://0.0.0.0:0", "tcp://127.0.0.1:0"):
        with pytest.raises(evclock.InvalidArgumentError) as plain:
            serving(url, allow_remote=True, token=TOKEN)
        assert str(plain.value) == (
            f"allow_remote=True is for tls:// addresses, not {url}: plain tcp:// stays on "
            "this machine (unencrypted, and any host could pose as the server); serve across "
            "machines on tls://HOST:PORT with a certificate (tls_cert=, tls_key=) and a token"
        )
    with pytest.raises(evclock.InvalidArgumentError) as unix:
        serving("unix:///tmp/evclock-never-made.sock", allow_remote=True)
    assert str(unix.value) == (
        "allow_remote=True is for tls:// addresses, not unix:///tmp/evclock-never-made.sock: a "
        "unix:// socket is reached from this machine only; drop allow_remote"
    )
    with pytest.raises(evclock.InvalidArgumentError) as beyond:
        serving("tcp://0.0.0.0:0", token=TOKEN)
    assert str(beyond.value) == (
        "tcp://0.0.0.0:0 is not a loopback address, and plain tcp:// would carry the "
        "simulation's time and data unencrypted to anyone on the path and let any host pose "
        "as the server: serve across machines on tls://HOST:PORT with a certificate "
        "(tls_cert=, tls_key=) and a token"
    )
    with pytest.raises(evclock.InvalidArgumentError, match="not a loopback address; a clock"):
        serving("tls://0.0.0.0:0", token=TOKEN, **tls)
    with pytest.raises(evclock.InvalidArgumentError) as no_cert:
        serving("tls://127.0.0.1:0", token=TOKEN)
    assert str(no_cert.value) == (
        "serving on tls://127.0.0.1:0 needs the server's certificate and key: "
        "tls_cert='cert.pem', tls_key='key.pem' (CLI: --tls-cert, --tls-key)"
    )
    with pytest.raises(evclock.InvalidArgumentError, match="tls_cert and tls_key are for a tls"):
        serving("tcp://127.0.0.1:0", token=TOKEN, **tls)
    with pytest.raises(evclock.InvalidArgumentError, match="cannot use the TLS certificate"):
        serving("tls://127.0.0.1:0", token=TOKEN, tls_cert=str(certs.cert), tls_key=str(certs.ca))
    # With TLS and a token it serves on every interface (reached here on 127.0.0.1).
    serving("tls://0.0.0.0:0", token=TOKEN, allow_remote=True, **tls)


@pytest.mark.parametrize(
    ("url", "message"),
    [
        ("tcp://127.0.0.1:1?tls_ca=/ca.pem", "tls_ca is an option of a tls:// clock address"),
        ("tls://127.0.0.1:1?tls_fingerprint=abc", "tls_fingerprint must be the SHA-256"),
        ("tls://127.0.0.1", "a tls clock address is tls://HOST:PORT"),
        ("tls://127.0.0.1:1?tls_ca=", "tls_ca must name a CA file"),
    ],
)
def test_bad_tls_addresses_are_refused(url: str, message: str) -> None:
    with pytest.raises(evclock.InvalidArgumentError, match=message):
        parse_address(url)


def test_a_tls_participant_needs_a_way_to_verify_the_server(certs: Certs) -> None:
    with pytest.raises(evclock.InvalidArgumentError) as refused:
        RemoteClockSource(f"tls://127.0.0.1:1?token={TOKEN}")
    assert str(refused.value) == (
        "a tls:// clock address needs a way to verify the server: ?tls_ca=/path/ca.pem (the "
        "CA that signed its certificate) or ?tls_fingerprint=SHA256 (its certificate's "
        "fingerprint)"
    )
    with pytest.raises(evclock.InvalidArgumentError, match="needs its token"):
        RemoteClockSource(f"tls://127.0.0.1:1?tls_ca={certs.ca}")
    with pytest.raises(evclock.InvalidArgumentError, match="verify a tls:// server, not tcp://"):
        RemoteClockSource(f"tcp://127.0.0.1:1?token={TOKEN}", tls_ca=str(certs.ca))
    with pytest.raises(evclock.InvalidArgumentError, match=r"tls_ca '/nonexistent\.pem' is not"):
        RemoteClockSource(f"tls://127.0.0.1:1?token={TOKEN}", tls_ca="/nonexistent.pem")
    parsed = parse_address(f"tls://[::1]:7411?tls_fingerprint={certs.fingerprint}")
    assert str(parsed) == "tls://[::1]:7411"
    assert parsed.tls_fingerprint == bytes.fromhex(certs.fingerprint.replace(":", ""))


def test_a_tls_server_is_verified_one_way(certs: Certs) -> None:
    one_way = (
        "a tls:// server is verified one way: give tls_ca (the CA that signed its "
        "certificate) or tls_fingerprint (its certificate's fingerprint), not both"
    )
    both = f"tls://127.0.0.1:1?tls_ca={certs.ca}&tls_fingerprint={certs.fingerprint}"
    with pytest.raises(evclock.InvalidArgumentError) as in_address:
        parse_address(both)
    assert str(in_address.value) == f"{one_way}, in clock address {both!r}"
    with pytest.raises(evclock.InvalidArgumentError) as given:
        RemoteClockSource(
            f"tls://127.0.0.1:1?token={TOKEN}",
            tls_ca=str(certs.ca),
            tls_fingerprint=certs.fingerprint,
        )
    assert str(given.value) == one_way
    # Given besides the address, a way replaces the address's own.
    from evclock.remote._address import with_verification

    by_ca = parse_address(f"tls://127.0.0.1:1?tls_ca={certs.ca}")
    pinned = with_verification(by_ca, None, certs.fingerprint)
    fingerprint = bytes.fromhex(certs.fingerprint.replace(":", ""))
    assert (pinned.tls_ca, pinned.tls_fingerprint) == (None, fingerprint)
    assert with_verification(pinned, str(certs.ca), None).tls_fingerprint is None


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["run", "cartpole", "--serve", "tcp://127.0.0.1:7411", "--allow-remote"],
            "--allow-remote is for --serve tls://HOST:PORT, not tcp://: plain tcp:// stays on "
            "this machine (unencrypted, and any host could pose as the server); serve across "
            "machines on tls://HOST:PORT with --tls-cert and --tls-key",
        ),
        (
            ["run", "cartpole", "--serve", "unix:///tmp/evclock-never.sock", "--allow-remote"],
            "--allow-remote is for --serve tls://HOST:PORT, not unix://: a unix:// socket is "
            "reached from this machine only; drop --allow-remote",
        ),
        (
            ["control", "cartpole", "--clock", "tls://127.0.0.1:7411", "--tls-ca", "ca.pem",
             "--tls-fingerprint", "AB:CD"],
            "--tls-ca and --tls-fingerprint are two ways to verify the simulation: give one "
            "(--tls-ca for a certificate your CA signed, --tls-fingerprint for a self-signed "
            "one)",
        ),
        (
            ["control", "cartpole", "--clock", "tls://127.0.0.1:7411"],
            "joining the simulation at tls://127.0.0.1:7411 needs a way to verify it: --tls-ca "
            "FILE (the CA that signed its certificate) or --tls-fingerprint SHA256 (its "
            "certificate's fingerprint)",
        ),
        (
            ["control", "cartpole", "--clock", "tcp://127.0.0.1:7411", "--tls-ca", "ca.pem"],
            "--tls-ca and --tls-fingerprint verify a simulation served on tls://, not tcp://: "
            "drop the option, or join it with --clock tls://HOST:PORT",
        ),
    ],
)  # fmt: skip
def test_tls_options_that_cannot_work_are_usage_errors(args: list[str], message: str) -> None:
    from _cli import run_evclock

    proc = run_evclock(*args, "--quiet", env={**os.environ, "EVCLOCK_TOKEN": TOKEN})
    assert (proc.returncode, proc.stdout, proc.stderr) == (2, "", f"error: {message}\n")


def test_a_read_takes_what_the_ssl_object_decrypted_already(certs: Certs) -> None:
    # A TLS record is decrypted whole: what a short read leaves waits in the SSL object,
    # where a poll of the socket does not see it. The transport's reads take it all.
    import select
    import socket
    import threading

    from evclock.remote._tls import client_context, recv, server_context

    server_side, client_side = socket.socketpair()
    context = server_context(str(certs.cert), str(certs.key))
    wrapped: list[ssl.SSLSocket] = []
    handshake = threading.Thread(
        target=lambda: wrapped.append(context.wrap_socket(server_side, server_side=True))
    )
    handshake.start()
    client = client_context(str(certs.ca), None).wrap_socket(
        client_side, server_hostname="127.0.0.1"
    )
    handshake.join(30)
    (server,) = wrapped
    try:
        for reader in ("sock.recv", "recv"):
            client.sendall(b"a" * 5000 + b"b" * 5000)  # one record of 10,000 bytes
            poller = select.poll()
            poller.register(server, select.POLLIN)
            assert poller.poll(10_000)
            if reader == "sock.recv":
                first = server.recv(100)
                assert (len(first), server.pending()) == (100, 9900)
                assert poller.poll(0) == []  # the rest is there, but the socket is quiet
                server.recv(9900)
            else:
                assert recv(server, 100) == b"a" * 5000 + b"b" * 5000
                assert server.pending() == 0
    finally:
        client.close()
        server.close()


# A relay on the path (a real process): forwards a connection both ways and keeps a copy of
# every byte that crossed it, as anyone on the network between two machines could.
RELAY = """
import socket, sys, threading
target, capture = int(sys.argv[1]), sys.argv[2]
listener = socket.socket()
listener.bind(("127.0.0.1", 0))
listener.listen(1)
listener.settimeout(60)
print(listener.getsockname()[1], flush=True)
near, _ = listener.accept()
far = socket.create_connection(("127.0.0.1", target))
seen = []
def pump(source, sink):
    while data := source.recv(65536):
        seen.append(data)
        sink.sendall(data)
    sink.shutdown(socket.SHUT_WR)
threads = [threading.Thread(target=pump, args=pair) for pair in ((near, far), (far, near))]
for thread in threads:
    thread.start()
for thread in threads:
    thread.join(60)
with open(capture, "wb") as out:
    out.write(b"".join(seen))
"""

SECRETIVE = """
import evclock
async def main():
    link = evclock.remote.participant()
    await evclock.clock().sleep(0.001)
    link.publish("private.topic", b"evclock-private-payload")
evclock.run(main())
"""


@pytest.mark.parametrize("scheme", ["tcp", "tls"])
def test_someone_on_the_path_sees_nothing_of_a_tls_session(
    tmp_path: Path, certs: Certs, scheme: str
) -> None:
    capture = tmp_path / f"{scheme}.bin"
    received: list[bytes] = []

    async def main() -> None:
        tls = {"tls_cert": str(certs.cert), "tls_key": str(certs.key)} if scheme == "tls" else {}
        async with evclock.remote.serve(f"{scheme}://127.0.0.1:0", token=TOKEN, **tls) as server:
            server.subscribe("private.topic", lambda m: received.append(m.data))
            port = int(server.address.rsplit(":", 1)[1])
            relay = spawn(tmp_path, RELAY, str(port), str(capture))
            loop = asyncio.get_running_loop()
            relay_port = int(await loop.run_in_executor(None, read_line, relay))
            verify = f"&tls_ca={certs.ca}" if scheme == "tls" else ""
            url = f"{scheme}://127.0.0.1:{relay_port}?token={TOKEN}&name=secret-name{verify}"
            proc = spawn(tmp_path, SECRETIVE, EVCLOCK_CLOCK=url)
            await server.wait_for_participants("secret-name", timeout=30)
            await server.wait_until_left()
            code, _, err = await loop.run_in_executor(None, finish, proc)
            assert code == 0, err
        code, _, err = finish(relay)
        assert code == 0, err

    evclock.run(main())
    assert received == [b"evclock-private-payload"]
    wire = capture.read_bytes()
    assert len(wire) > 100
    words = [b"evclock-private-payload", b"private.topic", b"secret-name", b"EVCLK"]
    # Plain TCP shows the data, the topic, the name and the protocol; TLS none of them.
    assert [word for word in words if word in wire] == ([] if scheme == "tls" else words)
    assert TOKEN.encode() not in wire  # neither shows the token


FOLLOWER = """
import json, evclock
async def main():
    clock = evclock.clock()
    seen = []
    for _ in range(3):
        await clock.sleep(0.010)
        seen.append(clock.now().nanoseconds)
    print(json.dumps(seen))
evclock.run(main())
"""


def test_a_follower_follows_over_tls(tmp_path: Path, certs: Certs) -> None:
    async def main() -> tuple[int, str, str]:
        loop = asyncio.get_running_loop()
        async with evclock.remote.serve(
            "tls://127.0.0.1:0", token=TOKEN, tls_cert=str(certs.cert), tls_key=str(certs.key)
        ) as server:
            url = f"{server.address}?token={TOKEN}&tls_ca={certs.ca}&name=watcher&mode=follow"
            proc = spawn(tmp_path, FOLLOWER, EVCLOCK_CLOCK=url)
            await server.wait_for_participants("watcher", timeout=30)
            await server.wait_until_left()
            return await loop.run_in_executor(None, finish, proc)

    code, out, err = evclock.run(main())
    assert code == 0, err
    assert json.loads(out) == [10_000_000, 20_000_000, 30_000_000]


def test_a_split_run_over_tls_on_the_command_line_ends_bit_identical(
    tmp_path: Path, certs: Certs
) -> None:
    # evclock run --serve tls://0.0.0.0:PORT --allow-remote with its certificate (every
    # interface, reached here on 127.0.0.1), evclock control verifying it (the token from a
    # file on both ends): the same run as in one process, bit for bit (MuJoCo: every Python).
    import subprocess

    from _without_pybullet import CLI_WITHOUT_PYBULLET

    from evclock.tools._cli import run_scenario

    def cli(*args: str) -> subprocess.Popen[str]:
        return subprocess.Popen(
            [*CLI_WITHOUT_PYBULLET, *args, "--engine", "mujoco", "--quiet", "--seed", "3"],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )

    port = _free_port()
    address = f"tls://127.0.0.1:{port}"
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN)
    token_file.chmod(0o600)
    server = cli(
        "run", "cartpole", "--until", "1", "--serve", f"tls://0.0.0.0:{port}", "--allow-remote",
        "--remote-controllers", "--tls-cert", str(certs.cert), "--tls-key", str(certs.key),
        "--token-file", str(token_file), "--json", str(tmp_path / "sim.json"),
    )  # fmt: skip
    controllers = cli(
        "control", "cartpole", "--until", "1", "--clock", address, "--token-file",
        str(token_file), "--tls-fingerprint", certs.fingerprint,
        "--json", str(tmp_path / "controllers.json"),
    )  # fmt: skip
    ctrl_code, _, ctrl_err = finish(controllers)
    sim_code, _, sim_err = finish(server)
    assert (sim_code, ctrl_code) == (3, 3), sim_err + ctrl_err  # cut short by --until
    in_process = run_scenario("cartpole", until=1.0, seed=3, rtf=None, engine="mujoco").to_json()
    served = json.loads((tmp_path / "sim.json").read_text())
    joined = json.loads((tmp_path / "controllers.json").read_text())
    assert served["final_state"] == joined["final_state"] == in_process["final_state"]
    assert served["sim_time_s"] == joined["sim_time_s"] == in_process["sim_time_s"]
    assert served["summary"] == in_process["summary"]


def test_serving_tls_on_the_command_line_without_a_token_makes_one(tmp_path: Path) -> None:
    from evclock.tools._cli_remote import serve_token

    token, written = serve_token("tls://127.0.0.1:7411", None)
    assert written is not None
    try:
        assert written.read_text().strip() == token
        assert written.stat().st_mode & 0o777 == 0o600
    finally:
        written.unlink()
    assert serve_token(f"unix://{tmp_path / 'sim.sock'}", None) == (None, None)

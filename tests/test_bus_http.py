"""HTTP hardening: a real HttpServer on 127.0.0.1 against raw sockets (bad and huge Content-Length,
a burst of 200 connections, silent clients, other methods), the learner refusing symlinked
artefacts, and local services binding HTTP to the loopback."""

from __future__ import annotations

import json
import logging
import shutil
import socket
import threading
import time

import pytest

from curlnav.bus.transport import HttpServer, Request, json_response


def routes():
    def fail(request):
        raise RuntimeError("handler bug")

    return {("GET", "/ok"): lambda r: json_response({"ok": True}),
            ("POST", "/echo"): lambda r: json_response({"bytes": len(r.body)}),
            ("GET", "/fail"): fail}


@pytest.fixture
def server():
    s = HttpServer("127.0.0.1", 0, routes(), timeout_s=1.0)
    yield s
    s.close()


def exchange(port: int, data: bytes, timeout: float = 5.0) -> tuple[int, dict, bytes]:
    """Send ``data`` on a fresh connection, read until the server closes: (status, headers, body)."""
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as c:
        c.sendall(data)
        out = b""
        while chunk := c.recv(65536):
            out += chunk
    head, _, body = out.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = dict(line.split(": ", 1) for line in lines[1:] if ": " in line)
    return int(lines[0].split()[1]), headers, body


def get(port: int, path: str = "/ok", timeout: float = 5.0) -> tuple[int, dict, bytes]:
    return exchange(port, f"GET {path} HTTP/1.1\r\nHost: x\r\n\r\n".encode(), timeout)


@pytest.mark.net
def test_a_content_length_that_is_no_number_is_400_json_and_the_server_answers_the_next_request(server):
    for value in ("abc", "-1", "1.5", "3, 4", "٣"):
        status, headers, body = exchange(server.port, f"POST /echo HTTP/1.1\r\nContent-Length: {value}\r\n\r\nabc"
                                         .encode())
        assert status == 400 and headers["Content-Type"] == "application/json"
        assert "Content-Length" in json.loads(body)["error"]
    status, _, body = exchange(server.port, b"POST /echo HTTP/1.1\r\nContent-Length: 3\r\n\r\nabc")
    assert status == 200 and json.loads(body) == {"bytes": 3}
    assert get(server.port)[0] == 200


@pytest.mark.net
def test_a_huge_content_length_is_413_without_reading_the_body(server):
    start = time.monotonic()
    status, headers, body = exchange(server.port, b"POST /echo HTTP/1.1\r\nContent-Length: 10000000000\r\n\r\n")
    assert status == 413 and "error" in json.loads(body)
    assert time.monotonic() - start < 0.9  # answered at once, not after waiting for a body (timeout 1 s)
    assert get(server.port)[0] == 200


@pytest.mark.net
def test_malformed_request_lines_are_400_json_with_a_status_line(server):
    for line in (b"garbage\r\n\r\n", b"GET /ok HTTP/9.x\r\n\r\n"):
        status, headers, body = exchange(server.port, line)
        assert status == 400 and headers["Content-Type"] == "application/json" and "error" in json.loads(body)


@pytest.mark.net
def test_other_methods_are_405_json_and_unknown_paths_404(server):
    for method in ("PUT", "DELETE", "PATCH", "OPTIONS", "BREW"):
        status, headers, body = exchange(server.port, f"{method} /ok HTTP/1.1\r\nContent-Length: 0\r\n\r\n".encode())
        assert status == 405 and f"{method} not allowed" in json.loads(body)["error"]
    status, headers, body = exchange(server.port, b"HEAD /ok HTTP/1.1\r\n\r\n")
    assert status == 405 and body == b""  # HEAD: headers only
    assert get(server.port, "/nowhere")[0] == 404
    status, _, body = get(server.port, "/fail")
    assert status == 500 and "handler bug" in json.loads(body)["error"]


@pytest.mark.net
def test_client_mistakes_leave_no_traceback_in_the_log(server, caplog, capfd):
    caplog.set_level(logging.DEBUG)
    exchange(server.port, b"POST /echo HTTP/1.1\r\nContent-Length: abc\r\n\r\n")
    assert exchange(server.port, b"POST /echo HTTP/1.1\r\nContent-Length: 100\r\n\r\nshort")[0] == 408  # then silent
    with socket.create_connection(("127.0.0.1", server.port)) as c:  # gone before the answer
        c.sendall(b"POST /echo HTTP/1.1\r\nContent-Length: 5\r\n\r\n")
    exchange(server.port, b"\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03\r\n\r\n")  # TLS to plain HTTP
    assert get(server.port)[0] == 200
    assert not [r for r in caplog.records if r.exc_info or r.levelno >= logging.WARNING]
    assert "Traceback" not in capfd.readouterr().err


@pytest.mark.net
def test_200_concurrent_connections_are_all_answered_within_5_s(server):
    results: list[int | str] = []
    latencies: list[float] = []
    start = threading.Barrier(200)
    lock = threading.Lock()

    def client():
        start.wait()
        began = time.monotonic()
        try:
            status = get(server.port, timeout=5.0)[0]
        except OSError as exc:
            status = repr(exc)
        with lock:
            results.append(status)
            latencies.append(time.monotonic() - began)

    threads = [threading.Thread(target=client) for _ in range(200)]
    began = time.monotonic()
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert time.monotonic() - began < 5.0
    assert results == [200] * 200
    # a short backlog (5, even 128) sends the overflow into the kernel's 1 s SYN retry: ~70 of 200
    assert sum(latency > 0.95 for latency in latencies) < 40


@pytest.mark.net
def test_a_silent_client_blocks_nobody_and_is_dropped_after_the_timeout(server):
    with socket.create_connection(("127.0.0.1", server.port), timeout=5) as silent:
        began = time.monotonic()
        assert get(server.port, timeout=0.8)[0] == 200  # answered while the silent one waits
        assert silent.recv(1024) == b""  # the server closed it ...
        assert 0.8 < time.monotonic() - began < 3.0  # ... after its 1 s timeout


@pytest.mark.net
def test_beyond_max_threads_requests_wait_for_a_handler_and_are_then_served():
    def slow(request):
        time.sleep(1.0)
        return json_response({"slow": True})

    s = HttpServer("127.0.0.1", 0, {**routes(), ("GET", "/slow"): slow}, timeout_s=1.0, max_threads=2)
    try:
        silent = socket.create_connection(("127.0.0.1", s.port))  # holds no handler thread (issue 26)
        busy = [threading.Thread(target=get, args=(s.port, "/slow")) for _ in range(2)]  # both handlers held
        for t in busy:
            t.start()
        time.sleep(0.2)
        began = time.monotonic()
        assert get(s.port, timeout=5.0)[0] == 200  # waited for a handler, not refused
        assert 0.5 < time.monotonic() - began < 3.0
        for t in busy:
            t.join(5)
        silent.close()
    finally:
        s.close()


# -- the learner's artefacts -------------------------------------------------------------------------

def test_the_learner_serves_no_artefact_through_a_symlink(tmp_path):
    from curlnav.builder import D4PGBuilder
    from curlnav.bus.service import Deployment
    from curlnav.config import resolve_config
    from curlnav.learner.service import LearnerServiceConfig

    experiment = resolve_config(overrides=["d4pg.batch_size=8", "replay.min_size=8"])
    service = D4PGBuilder(experiment).make_learner_service(LearnerServiceConfig(Deployment(data_dir=str(tmp_path / "learner"))))
    real = service.export()
    version = int(real.name[1:])
    artefacts = real.parent

    def policy(path: str):
        return service._policy(Request("GET", path, {}, b""))

    secret = tmp_path / "outside" / "secret.bin"
    secret.parent.mkdir()
    secret.write_bytes(b"TOP-SECRET")
    (artefacts / "v999").symlink_to("/etc")  # a symlinked version folder
    shutil.copytree(real, tmp_path / "outside" / "v998")  # a whole artefact, outside, linked in
    (artefacts / "v998").symlink_to(tmp_path / "outside" / "v998")
    tampered = artefacts / "v997"  # a real folder whose files are links to the outside
    shutil.copytree(real, tampered)
    listed = next(name for name in json.loads((real / "metadata.json").read_text())["files"])
    (tampered / listed).unlink()
    (tampered / listed).symlink_to(secret)
    (real / "passwd").symlink_to(secret)
    (artefacts / "secret.bin").symlink_to(secret)

    for path in ("/policy/999/passwd", "/policy/999", "/policy/998", f"/policy/998/{listed}",
                 f"/policy/997/{listed}", f"/policy/{version}/passwd", f"/policy/{version}/../secret.bin",
                 f"/policy/{version}/..", "/policy/v999/metadata.json"):
        status, ctype, body = policy(path)
        assert status == 404 and ctype == "application/json", path
        assert b"TOP-SECRET" not in body and b"root:" not in body, path
    for bad in ("/policy/1x", "/policy/-1", "/policy/1234567890123", "/policy/\u0663", "/policy/..", "/policy/v"):
        assert policy(bad)[0] == 400, bad

    assert policy("/policy/997/metadata.json")[0] == 200  # v997's own metadata is a real file
    shutil.rmtree(tampered)

    # the real version is still served, and "latest" never picks a linked one (998, 999)
    status, _, body = policy("/policy/latest")
    assert status == 200 and json.loads(body)["version"] == version
    assert policy(f"/policy/{version}/{listed}") == (200, "application/octet-stream", (real / listed).read_bytes())


# -- loopback by default, locally ------------------------------------------------------------------

@pytest.mark.net
@pytest.mark.slow
def test_local_services_bind_http_to_the_loopback_and_containers_to_all_interfaces(tmp_path, monkeypatch):
    import argparse

    from curlnav.bus.service import Deployment
    from curlnav.run.launch import LocalCluster, add_serve_arguments

    monkeypatch.delenv("CURLNAV_HTTP_HOST", raising=False)
    parser = argparse.ArgumentParser()
    add_serve_arguments(parser)
    cluster = LocalCluster(tmp_path / "run")
    for role in ("replay", "learner", "scheduler", "actor"):
        cmd = cluster.service_command(role)
        assert cmd[cmd.index("--http-host") + 1] == "127.0.0.1"
        assert parser.parse_args(cmd[cmd.index("serve") + 1:]).http_host == "127.0.0.1"
    assert not cluster.processes
    assert parser.parse_args(["replay"]).http_host == "0.0.0.0"  # `curlnav serve` in a container
    monkeypatch.setenv("CURLNAV_HTTP_HOST", "10.1.2.3")
    parser = argparse.ArgumentParser()
    add_serve_arguments(parser)
    assert parser.parse_args(["replay"]).http_host == "10.1.2.3"
    assert Deployment().http_host == "127.0.0.1"  # services built in-process

"""Issue 26, the parts a hostile client, server or file reaches without the bus: the HTTP server
under slow clients (H4), ``curlnav pull`` against a hostile learner (H5), and the loaders (world,
curriculum and config YAML, map images, ``metadata.json``) under hostile files (H6). Each ends in
a refusal, a bounded cost or one ``curlnav: error:`` line with exit 2.

Real servers and processes: an ``HttpServer`` on loopback with 80 trickling sockets, a hostile
``http.server`` learner for ``curlnav pull``, and the CLI in a subprocess whose address space is
capped (an alias bomb must not take the machine's memory with it)."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import socket
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import HostileLearner, assert_one_line_error
from conftest import run_capped as curlnav

from curlnav.bus.transport import HttpServer, json_response

# -- H4: slow clients --------------------------------------------------------------------------------

class Trickler:
    """``n`` connections that send a request head one byte every ``every_s`` seconds, reconnecting
    when the server drops them (as an attacker would)."""

    def __init__(self, port: int, n: int, every_s: float, source: str = "127.0.0.1") -> None:
        self.port, self.every_s, self.source = port, every_s, source
        self.stop = threading.Event()
        self.dropped = 0
        self.threads = [threading.Thread(target=self._run, daemon=True) for _ in range(n)]
        for t in self.threads:
            t.start()

    def _run(self) -> None:
        head = b"GET /status HTTP/1.1\r\nX-Slow: " + b"a" * 10_000
        while not self.stop.is_set():
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=2,
                                              source_address=(self.source, 0)) as s:
                    for i in range(len(head)):
                        s.sendall(head[i:i + 1])
                        if self.stop.wait(self.every_s):
                            return
            except OSError:
                self.dropped += 1
                self.stop.wait(0.05)

    def close(self) -> None:
        self.stop.set()
        for t in self.threads:
            t.join(10)


def timed_get(port: int, path: str = "/status", timeout: float = 3.0) -> tuple[int | str, float]:
    began = time.monotonic()
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=timeout) as c:
            c.sendall(f"GET {path} HTTP/1.1\r\nHost: x\r\n\r\n".encode())
            out = b""
            while chunk := c.recv(65536):
                out += chunk
        status: int | str = int(out.split(b" ", 2)[1])
    except (OSError, IndexError, ValueError) as exc:
        status = repr(exc)
    return status, time.monotonic() - began


def status_routes():
    return {("GET", "/status"): lambda r: json_response({"stage": "S1"})}


@pytest.mark.net
def test_status_answers_within_1_s_while_80_clients_trickle_one_byte_every_5_s():
    server = HttpServer("127.0.0.1", 0, status_routes())  # the services' defaults
    attack = Trickler(server.port, 80, every_s=5.0)
    try:
        time.sleep(1.5)  # every trickler connected and waiting for its next byte
        results = [timed_get(server.port) for _ in range(5)]
        print("/status under 80 tricklers:", results)
        for status, latency in results:
            assert status == 200 and latency < 1.0, results
    finally:
        attack.close()
        server.close()


@pytest.mark.net
def test_a_request_head_or_body_trickled_past_the_deadline_is_dropped_at_the_deadline():
    server = HttpServer("127.0.0.1", 0, status_routes() | {("POST", "/echo"): lambda r: json_response({})},
                        timeout_s=1.0)
    try:
        for request in (b"GET /status HTTP/1.1\r\nX-Slow: " + b"a" * 100,  # head
                        b"POST /echo HTTP/1.1\r\nContent-Length: 100\r\n\r\n" + b"b" * 100):  # body
            with socket.create_connection(("127.0.0.1", server.port), timeout=5) as s:
                began = time.monotonic()
                split = request.index(b"X-Slow") if b"X-Slow" in request else request.index(b"\r\n\r\n") + 4
                s.sendall(request[:split])
                closed_after = None
                for byte in request[split:]:  # 0.3 s apart: every read well within the 1 s timeout
                    try:
                        s.sendall(bytes([byte]))
                        s.settimeout(0.3)
                        if s.recv(4096) is not None:  # an answer (408) or the close
                            closed_after = time.monotonic() - began
                            break
                    except TimeoutError:
                        continue
                    except OSError:
                        closed_after = time.monotonic() - began
                        break
                    if time.monotonic() - began > 4.0:
                        break
                assert closed_after is not None and closed_after < 2.0, (request[:20], closed_after)
        assert timed_get(server.port)[0] == 200
    finally:
        server.close()


@pytest.mark.net
def test_a_request_head_above_64_kb_in_all_is_refused_with_431():
    server = HttpServer("127.0.0.1", 0, status_routes())
    try:
        headers = b"".join(b"X-Pad-%d: %s\r\n" % (i, b"p" * 1000) for i in range(90))  # 90 KB, 1 KB a line
        with socket.create_connection(("127.0.0.1", server.port), timeout=5) as c:
            c.sendall(b"GET /status HTTP/1.1\r\n" + headers + b"\r\n")
            out = b""
            while chunk := c.recv(65536):
                out += chunk
        assert out.split(b" ", 2)[1] == b"431", out[:200]
        assert timed_get(server.port)[0] == 200
    finally:
        server.close()


@pytest.mark.net
def test_one_client_address_holds_at_most_max_per_client_slow_connections():
    server = HttpServer("127.0.0.1", 0, status_routes(), max_per_client=4)
    try:
        silent = [socket.create_connection(("127.0.0.1", server.port), timeout=3) for _ in range(6)]
        status, latency = timed_get(server.port)
        assert status == 200 and latency < 1.0  # an honest request is never the one pushed out
        time.sleep(1.5)  # all six are slow now (still sending after 1 s): the two oldest go

        def closed(s: socket.socket) -> bool:
            s.settimeout(0.2)
            try:
                return s.recv(4096) == b""
            except TimeoutError:
                return False

        assert [closed(s) for s in silent] == [True, True, False, False, False, False]
        for s in silent:
            s.close()
    finally:
        server.close()


# -- H5: curlnav pull against a hostile learner ----------------------------------------------------

def pull(learner: HostileLearner, out: Path) -> subprocess.CompletedProcess:
    return curlnav("pull", "--from", learner.url, "--out", str(out))[0]


def evil_files(root: Path) -> list[Path]:
    return [p for p in root.rglob("*evil*") if p.is_file()]


@pytest.mark.net
@pytest.mark.slow
def test_pull_of_an_honest_listing_still_works(learner, artefact, tmp_path):
    learner.serve_artefact(artefact)
    result = pull(learner, tmp_path / "out" / "policy")
    assert result.returncode == 0, result.stderr
    assert sorted(p.name for p in (tmp_path / "out" / "policy").iterdir()) == sorted(p.name for p in artefact.iterdir())


@pytest.mark.net
@pytest.mark.slow
@pytest.mark.parametrize("name", ["../../evil.txt", "ABSOLUTE", "sub/evil.txt", "..", "evil\\..\\x", ".evil"])
def test_pull_writes_no_file_outside_out_whatever_the_listing_names(learner, artefact, tmp_path, name):
    name = str(tmp_path / "abs-evil.txt") if name == "ABSOLUTE" else name
    learner.serve_artefact(artefact, extra={name: b"evil payload"})
    out = tmp_path / "a" / "b" / "policy"
    result = pull(learner, out)
    assert_one_line_error(result, "plain file name")
    assert evil_files(tmp_path) == [] and not out.exists()


@pytest.mark.net
@pytest.mark.slow
def test_pull_follows_no_redirect_to_another_origin(learner, artefact, tmp_path):
    other = HostileLearner()  # another origin (port) with a listing that names ../../evil.txt
    try:
        other.serve_artefact(artefact, extra={"../../evil.txt": b"evil payload"})
        learner.routes["/policy/latest"] = (302, {"Location": other.url + "/policy/latest", "Content-Length": "0"}, b"")
        out = tmp_path / "a" / "b" / "policy"
        result = pull(learner, out)
        assert_one_line_error(result, "redirect")
        assert evil_files(tmp_path) == [] and not out.exists()
    finally:
        other.close()


@pytest.mark.net
@pytest.mark.slow
def test_pull_requires_a_sha256_for_every_file(learner, artefact, tmp_path):
    def drop_sha(listing):
        del listing["files"]["policy.safetensors"]["sha256"]

    learner.serve_artefact(artefact, listing_changes=drop_sha)
    result = pull(learner, tmp_path / "policy")
    assert_one_line_error(result, "policy.safetensors", "sha256")
    assert not (tmp_path / "policy").exists()


@pytest.mark.net
@pytest.mark.slow
def test_pull_refuses_a_file_the_artefact_does_not_list(learner, artefact, tmp_path):
    learner.serve_artefact(artefact, extra={"run.sh": b"#!/bin/sh\necho pwned\n"})
    result = pull(learner, tmp_path / "policy")
    assert_one_line_error(result, "run.sh")
    assert not (tmp_path / "policy").exists()


@pytest.mark.net
@pytest.mark.slow
def test_pull_refuses_a_body_above_the_size_cap_without_holding_it_in_memory(learner, artefact, tmp_path):
    from curlnav.run.pull import MAX_FILE_BYTES

    size = MAX_FILE_BYTES + (32 << 20)
    chunk = b"\0" * (1 << 20)
    digest = hashlib.sha256()
    for _ in range(size >> 20):
        digest.update(chunk)

    def endless(wfile):  # no Content-Length: the body ends when the server closes
        for _ in range(size >> 20):
            wfile.write(chunk)

    def big_file(listing):  # metadata.json and the listing agree on the big file's checksum
        listing["metadata"]["files"]["actor.onnx"] = listing["files"]["actor.onnx"]["sha256"] = digest.hexdigest()
        meta = json.dumps(listing["metadata"]).encode()
        learner.routes[listing["files"]["metadata.json"]["url"]] = (200, {}, meta)
        listing["files"]["metadata.json"]["sha256"] = hashlib.sha256(meta).hexdigest()
        learner.routes[listing["files"]["actor.onnx"]["url"]] = (200, {"Connection": "close"}, endless)

    learner.serve_artefact(artefact, listing_changes=big_file)
    result, peak_mb, wall = curlnav("pull", "--from", learner.url, "--out", str(tmp_path / "policy"))
    print(f"pull of a {size >> 20} MiB body: peak {peak_mb:.0f} MB, {wall:.1f} s, rc {result.returncode}")
    assert_one_line_error(result, "actor.onnx", "above")
    assert peak_mb < 400 and not (tmp_path / "policy").exists()
    assert not list(tmp_path.iterdir())  # the temporary folder went too

    def declared(listing):  # a Content-Length above the cap: refused before the body
        big_file(listing)
        learner.routes[listing["files"]["actor.onnx"]["url"]] = (200, {"Content-Length": str(800 << 20)}, b"")

    learner.serve_artefact(artefact, listing_changes=declared)
    began = time.monotonic()
    assert_one_line_error(pull(learner, tmp_path / "policy"), "actor.onnx", "above")
    assert time.monotonic() - began < 20


@pytest.mark.net
@pytest.mark.slow
def test_pull_checks_the_artefact_before_replacing_out(learner, artefact, tmp_path):
    out = tmp_path / "policy"
    shutil.copytree(artefact, out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    def corrupt(listing):  # the listing's own checksum matches, metadata.json's does not
        bad = b"not an onnx model"
        learner.routes[listing["files"]["actor.onnx"]["url"]] = (200, {}, bad)
        listing["files"]["actor.onnx"]["sha256"] = hashlib.sha256(bad).hexdigest()

    learner.serve_artefact(artefact, listing_changes=corrupt)
    result = pull(learner, out)
    assert_one_line_error(result, "actor.onnx")
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before  # the old artefact, untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["policy"]


@pytest.mark.net
@pytest.mark.slow
def test_pull_never_deletes_a_folder_that_is_not_an_artefact(learner, artefact, tmp_path):
    out = tmp_path / "home"
    out.mkdir()
    (out / "thesis.tex").write_text("years of work")
    learner.serve_artefact(artefact)
    result = pull(learner, out)
    assert_one_line_error(result, str(out), "not a policy artefact")
    assert (out / "thesis.tex").read_text() == "years of work"


@pytest.mark.net
@pytest.mark.slow
@pytest.mark.parametrize("body", [b"not json", b"[]", b"{}", b'{"files": []}', b'{"files": {"actor.onnx": "x"}}',
                                  b'{"files": {"actor.onnx": {"sha256": 5, "url": 7}}}',
                                  b"[" * 100_000 + b"]" * 100_000, b'{"version": 1e400, "files": {}}',
                                  b"\xff\xfe garbage"])
def test_pull_of_a_malformed_listing_is_a_one_line_error(learner, tmp_path, body):
    learner.routes["/policy/latest"] = (200, {"Content-Type": "application/json"}, body)
    result = pull(learner, tmp_path / "policy")
    assert_one_line_error(result, learner.url)
    assert not (tmp_path / "policy").exists()


# -- H6: loaders ---------------------------------------------------------------------------------------

def alias_bomb(levels: int = 8) -> list[str]:
    """Anchored YAML flow lists, each holding the previous one 9 times: 9**levels strings."""
    names = "abcdefghij"[:levels]
    items = ['&a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    items += [f"&{cur} [" + ",".join([f"*{prev}"] * 9) + "]" for prev, cur in zip(names, names[1:])]
    return items


def plain_map(folder: Path) -> None:
    from PIL import Image

    Image.fromarray(np.full((20, 20), 254, dtype=np.uint8)).save(folder / "m.pgm")


MAP_KEYS = "image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n"


def world_show(path: Path, tmp_path: Path):
    return curlnav("worlds", "show", str(path), "--out", str(tmp_path / "shown.png"))


@pytest.mark.slow
def test_an_alias_bomb_world_file_ends_fast_in_one_short_line(tmp_path):
    plain_map(tmp_path)
    path = tmp_path / "bomb.yaml"
    path.write_text(MAP_KEYS + "mode: [" + ", ".join(alias_bomb()) + "]\n")
    result, peak_mb, wall = world_show(path, tmp_path)
    print(f"world alias bomb ({path.stat().st_size} bytes): {wall:.2f} s, peak {peak_mb:.0f} MB, "
          f"error {len(result.stderr)} characters, rc {result.returncode}")
    assert_one_line_error(result, str(path), "alias")
    assert wall < 5 and peak_mb < 1000


@pytest.mark.slow
def test_an_alias_bomb_curriculum_ends_fast_in_one_short_line(tmp_path):
    path = tmp_path / "bomb.yaml"
    path.write_text("stages:\n- name: s1\n  worlds: [open-room]\n  sampler: [" + ", ".join(alias_bomb()) + "]\n")
    result, peak_mb, wall = curlnav("train", "--serial", "--curriculum", str(path), "--minutes", "0.01",
                                    "--run-dir", str(tmp_path / "run"))
    print(f"curriculum alias bomb ({path.stat().st_size} bytes): {wall:.2f} s, peak {peak_mb:.0f} MB, "
          f"error {len(result.stderr)} characters, rc {result.returncode}")
    assert_one_line_error(result, str(path), "alias")
    assert wall < 5 and peak_mb < 1000


@pytest.mark.slow
def test_an_alias_bomb_experiment_config_ends_in_one_short_line(tmp_path):
    path = tmp_path / "bomb.yaml"
    path.write_text("d4pg:\n  hidden: [" + ", ".join(alias_bomb()) + "]\n")
    result, peak_mb, wall = curlnav("config", "show", "--config", str(path))
    assert_one_line_error(result, str(path), "alias")
    assert wall < 5 and peak_mb < 1000


@pytest.mark.slow
def test_long_user_values_are_cut_short_in_error_messages(tmp_path):
    plain_map(tmp_path)
    path = tmp_path / "long.yaml"
    path.write_text(MAP_KEYS + "mode: " + "x" * 200_000 + "\n")
    line = assert_one_line_error(world_show(path, tmp_path)[0], "mode must be one of", max_len=400)
    assert "xxxxxxxx" in line
    path.write_text("image: m.pgm\nresolution: " + "9" * 100_000 + "x\norigin: [0, 0, 0]\n")
    assert_one_line_error(world_show(path, tmp_path)[0], "resolution", max_len=400)
    curriculum = tmp_path / "long-curriculum.yaml"
    curriculum.write_text("stages:\n- name: s1\n  worlds: [open-room]\n  sampler: " + "y" * 200_000 + "\n")
    result = curlnav("train", "--serial", "--curriculum", str(curriculum), "--minutes", "0.01",
                     "--run-dir", str(tmp_path / "run"))[0]
    assert_one_line_error(result, "sampler must be one of", max_len=400)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["world", "curriculum"])
def test_deeply_nested_yaml_is_a_one_line_error(tmp_path, kind):
    path = tmp_path / f"deep-{kind}.yaml"
    deep = "[" * 20_000 + "]" * 20_000
    if kind == "world":
        plain_map(tmp_path)
        path.write_text(MAP_KEYS + f"mode: {deep}\n")
        result = world_show(path, tmp_path)[0]
    else:
        path.write_text(f"stages:\n- name: s1\n  worlds: [open-room]\n  sampler: {deep}\n")
        result = curlnav("train", "--serial", "--curriculum", str(path), "--minutes", "0.01",
                         "--run-dir", str(tmp_path / "run"))[0]
    assert_one_line_error(result, str(path), "deep")


@pytest.mark.slow
def test_a_yaml_file_above_the_size_cap_is_refused_without_parsing(tmp_path):
    plain_map(tmp_path)
    path = tmp_path / "huge.yaml"
    with open(path, "w") as f:
        f.write(MAP_KEYS)
        line = "# " + "z" * 98 + "\n"
        f.write(line * ((12 << 20) // len(line)))  # 12 MB of comments
    result, peak_mb, wall = world_show(path, tmp_path)
    print(f"12 MB world file: {wall:.2f} s, peak {peak_mb:.0f} MB, rc {result.returncode}")
    assert_one_line_error(result, str(path), "above")
    assert wall < 3


@pytest.mark.slow
def test_a_100000_x_100000_pgm_header_is_a_one_line_error(tmp_path):
    (tmp_path / "m.pgm").write_bytes(b"P5\n100000 100000\n255\n" + b"\xfe" * 1000)
    path = tmp_path / "bomb.yaml"
    path.write_text(MAP_KEYS)
    result, peak_mb, wall = world_show(path, tmp_path)
    assert_one_line_error(result, "m.pgm", "100000 x 100000")
    assert peak_mb < 1000


@pytest.mark.slow
def test_a_map_image_above_the_file_size_cap_is_refused(tmp_path):
    from PIL import Image

    Image.fromarray(np.full((20, 20), 254, dtype=np.uint8)).save(tmp_path / "m.pgm")
    with open(tmp_path / "m.pgm", "r+b") as f:  # a sparse 1 GB tail: costs no disk
        f.truncate(1 << 30)
    path = tmp_path / "m.yaml"
    path.write_text(MAP_KEYS)
    assert_one_line_error(world_show(path, tmp_path)[0], "m.pgm", "above")


# -- H6: metadata.json ---------------------------------------------------------------------------------

def policy_run(folder: Path, tmp_path: Path) -> subprocess.CompletedProcess:
    return curlnav("policy", "run", str(folder), "--out", str(tmp_path / "run-out"))[0]


def copy_with_metadata(artefact: Path, tmp_path: Path, change) -> Path:
    folder = tmp_path / "artefact"
    shutil.copytree(artefact, folder)
    meta = json.loads((folder / "metadata.json").read_text())
    text = change(meta)
    (folder / "metadata.json").write_text(text if isinstance(text, str) else json.dumps(meta))
    return folder


@pytest.mark.slow
def test_metadata_with_1e400_is_a_one_line_error(artefact, tmp_path):
    def huge(meta):
        return json.dumps(meta).replace(f'"size": {meta["observation"]["size"]}', '"size": 1e400', 1)

    folder = copy_with_metadata(artefact, tmp_path, huge)
    assert "1e400" in (folder / "metadata.json").read_text()
    assert_one_line_error(policy_run(folder, tmp_path), "metadata.json")


@pytest.mark.slow
def test_deeply_nested_metadata_is_a_one_line_error(artefact, tmp_path):
    folder = copy_with_metadata(artefact, tmp_path, lambda meta: '{"format": "curlnav-policy", "x": '
                                + "[" * 100_000 + "]" * 100_000 + "}")
    assert_one_line_error(policy_run(folder, tmp_path), "metadata.json", "deep")


@pytest.mark.slow
def test_metadata_above_the_size_cap_is_refused(artefact, tmp_path):
    def padded(meta):
        return json.dumps(meta) + " " * (20 << 20)

    folder = copy_with_metadata(artefact, tmp_path, padded)
    assert_one_line_error(policy_run(folder, tmp_path), "metadata.json", "above")


@pytest.mark.slow
@pytest.mark.parametrize("name", ["../secret.bin", "SECRET_ABSOLUTE", "sub/../../secret.bin"])
def test_metadata_names_no_file_outside_its_folder_and_no_outside_checksum_is_shown(artefact, tmp_path, name):
    secret = tmp_path / "secret.bin"
    secret.write_bytes(b"TOP-SECRET " * 100)
    secret_sha = hashlib.sha256(secret.read_bytes()).hexdigest()
    name = str(secret) if name == "SECRET_ABSOLUTE" else name

    def outside(meta):
        meta["files"][name] = "0" * 64

    folder = copy_with_metadata(artefact, tmp_path, outside)
    result = policy_run(folder, tmp_path)
    assert secret_sha not in result.stderr + result.stdout
    assert_one_line_error(result, "metadata.json", "plain file name")


def test_every_hostile_loader_keeps_existing_world_files_loading(tmp_path):
    """The shipped worlds and curricula (no aliases, small) still load with the caps in place."""
    from curlnav.scheduler.curriculum import load_curriculum
    from curlnav.sim import load_world

    root = Path(__file__).resolve().parents[1] / "scheduler" / "curricula"
    for path in sorted(root.glob("*.yaml")):
        load_curriculum(path)
    for path in sorted((root / "worlds").glob("*.yaml")):
        load_world(path)
    assert os.path.getsize(root / "worlds" / "t-maze-0.yaml") < 1 << 20

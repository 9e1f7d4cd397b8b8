"""Nothing generated is lost across a partition or a replay restart (issue 30, part 2): an actor
keeps every batch until the replay acknowledges it, bounded in memory and on disk, and resends
from the oldest, in order; the replay accepts an actor's batches only in sequence (a resend is a
duplicate, a batch above a gap waits for the gap); the scheduler marks a cut-off actor lost and
takes it back without touching the curriculum. These tests drive the cores over a channel that
loses what is put while it is cut; the real partition is in ``test_bench_hosts.py``."""

from __future__ import annotations

import time

import pytest
from conftest import a_batch, play, replay_in, scheduler_core

from curlnav.actor.resend import ResendBuffer
from curlnav.proto.messages import ServiceStatus, TransitionBatch


def test_the_buffer_spills_to_disk_then_is_full_and_acknowledgements_free_it(tmp_path):
    payloads = [a_batch("actor-0", seq=i).encode() for i in range(10)]
    size = len(payloads[0])
    buffer = ResendBuffer(tmp_path, memory_bytes=3 * size, disk_bytes=4 * size + 10, resend_after_s=1.0)
    for i, payload in enumerate(payloads[:7]):
        assert not buffer.full(size)
        buffer.add(i, payload)
    assert buffer.in_memory == 3 * size and buffer.on_disk == 4 * size and buffer.full(size)
    assert (tmp_path / "unacknowledged.spill").stat().st_size == 4 * size
    sent = buffer.due(now=0.0)
    assert [seq for seq, _ in sent] == list(range(7)) and [p for _, p in sent] == payloads[:7]  # read back in order
    assert buffer.due(now=0.5) == []  # nothing new, nothing overdue
    assert [seq for seq, _ in buffer.due(now=1.5)] == list(range(7))  # go-back-N from the oldest
    assert buffer.ack(4) == 5 and not buffer.full(size)
    assert buffer.ack(6) == 2 and buffer.on_disk == 0 and (tmp_path / "unacknowledged.spill").stat().st_size == 0
    buffer.close()
    assert not (tmp_path / "unacknowledged.spill").exists()


class Channel:
    """The bus between one actor and the replay: a put is lost while ``cut``."""

    def __init__(self) -> None:
        self.cut = False
        self.delivered: list[bytes] = []

    def put(self, payload: bytes) -> None:
        if not self.cut:
            self.delivered.append(payload)


def test_a_partition_and_a_replay_restart_lose_nothing(tmp_path):
    replay = replay_in(tmp_path / "replay")
    buffer = ResendBuffer(tmp_path / "actor", resend_after_s=2.0)
    channel, clock, seq, generated = Channel(), [0.0], time.time_ns() // 1000, 0

    def tick(batches: int = 1) -> None:
        """The actor makes ``batches`` batches and sends what is due; the replay takes what arrived."""
        nonlocal seq, generated
        for _ in range(batches):
            buffer.add(seq, a_batch("actor-0", seq=seq).encode())
            seq += 1
            generated += 6
            clock[0] += 0.25
            for _, payload in buffer.due(clock[0]):
                channel.put(payload)
            for msg in replay.accept_batches([("actor-0", p) for p in channel.delivered]):
                replay.insert_accepted(msg, force=True)
            channel.delivered.clear()
            if "actor-0" in replay.acked:  # the credit message's acknowledgement
                buffer.ack(replay.acked["actor-0"])

    tick(8)
    channel.cut = True  # the host is cut off: what is put now is lost
    tick(4)
    assert replay.accepted_total < generated
    channel.cut = False  # healed: new batches arrive above the gap and are refused until it is filled
    tick(3)
    assert replay.rejected().get("out_of_order", 0) >= 1
    tick(10)  # the oldest waited 2 s: everything unacknowledged again, in order
    replay = replay_in(tmp_path / "replay")  # kill -9 of the replay: only its log survives
    channel.cut = True  # and while it restarts nothing reaches it
    tick(5)
    channel.cut = False
    tick(12)
    for _ in range(8):  # the actor stops: no new batches, what is held goes out until acknowledged
        clock[0] += 1.0
        for _, payload in buffer.due(clock[0]):
            channel.put(payload)
        for msg in replay.accept_batches([("actor-0", p) for p in channel.delivered]):
            replay.insert_accepted(msg, force=True)
        channel.delivered.clear()
        buffer.ack(replay.acked["actor-0"])
    assert len(buffer) == 0, f"{len(buffer)} batches never acknowledged"
    assert replay.accepted_total == generated, "lost transitions"
    held = [TransitionBatch.decode(p).seq for _, p in replay.log.records()]
    assert held == sorted(held) and len(held) == len(set(held)) == generated // 6  # each batch once, in order


def test_an_actor_gone_and_back_keeps_its_acknowledgement(tmp_path):
    replay = replay_in(tmp_path)
    start = time.time_ns() // 1000
    replay.actor_alive("actor-0", True)
    assert replay.handle_batch(a_batch("actor-0", seq=start).encode()) == 6
    replay.actor_alive("actor-0", False)  # cut off: its token went
    assert b"ack/actor-0" not in replay.credit_message()
    assert replay.handle_batch(a_batch("actor-0", seq=start).encode()) == 0  # its resend is still a duplicate
    replay.actor_alive("actor-0", True)
    credit = ServiceStatus.decode(replay.credit_message())
    assert credit.values["ack/actor-0"] == start
    assert replay.handle_batch(a_batch("actor-0", seq=start + 2).encode()) == 0  # above a gap: waits
    assert replay.rejected() == {"duplicate": 1, "out_of_order": 1}
    assert replay.handle_batch(a_batch("actor-0", seq=start + 1).encode()) == 6
    assert replay.handle_batch(a_batch("actor-0", seq=start + 10_000_000).encode()) == 6  # a restarted actor


def test_the_scheduler_marks_a_cut_off_actor_lost_and_takes_it_back(tmp_path):
    core = scheduler_core(tmp_path)
    core.actor_joined("actor-0")
    core.actor_joined("actor-1")
    for _ in range(3):
        play(core, "actor-0")
    state = core.state.to_dict()
    core.actor_left("actor-0")  # its host is cut off
    status = core.status()
    assert "actor-0" not in status["live_actors"] and list(status["lost_actors"]) == ["actor-0"]
    assert status["lost_actors"]["actor-0"]["episodes"] == 3
    assert core.state.to_dict() == state  # the curriculum is not disturbed
    core.actor_joined("actor-0")  # healed: its token is back
    status = core.status()
    assert status["lost_actors"] == {} and status["rejoined_actors"] == 1
    assert status["live_actors"]["actor-0"]["episodes"] == 3
    play(core, "actor-0")
    assert core.status()["episodes"] == 4


@pytest.mark.net
def test_the_router_bounds_unacknowledged_data_on_its_links_to_other_hosts_only():
    """``LinkAckTimeout`` (issue 30): a connection to another host gets ``TCP_USER_TIMEOUT`` (so
    a TLS link whose lease expired cannot hang its router's close on a cut-off peer), a loopback
    one does not; a socket it has looked at is left alone after."""
    import socket

    import pytest

    from curlnav.bus.transport import LinkAckTimeout

    links = LinkAckTimeout(seconds=7.0)
    if not links.available:
        pytest.skip("no TCP_USER_TIMEOUT or /proc here")
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        probe.connect(("192.0.2.1", 9))  # no packet: only picks this host's outgoing address
        address = probe.getsockname()[0]
    except OSError:
        address = "127.0.0.1"
    finally:
        probe.close()
    if address.startswith("127."):
        pytest.skip("no address other than loopback here")

    def pair(host: str) -> tuple[socket.socket, socket.socket, socket.socket]:
        server = socket.create_server((host, 0))
        client = socket.create_connection((host, server.getsockname()[1]))
        accepted, _ = server.accept()
        return server, client, accepted

    def timeout_ms(sock: socket.socket) -> int:
        return sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT)

    sockets = [*pair(address), *pair("127.0.0.1")]
    try:
        assert links.sweep() >= 2
        remote_server, remote_client, remote_accepted, local_server, local_client, local_accepted = sockets
        assert timeout_ms(remote_client) == timeout_ms(remote_accepted) == 7000
        assert timeout_ms(local_client) == timeout_ms(local_accepted) == timeout_ms(remote_server) == 0
        remote_client.setsockopt(socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT, 1)
        assert links.sweep() == 0 and timeout_ms(remote_client) == 1  # set once per connection
        remote_client.getpeername()  # the sweep's duplicates are closed, the sockets still open
    finally:
        for sock in sockets:
            sock.close()

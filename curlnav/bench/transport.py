"""``curlnav bench transport``: the replay service under load, over a real router on loopback.

Four publisher processes send transition batches (64 transitions and 64 frames each, as an
actor would) through a router to a replay service process, while this process samples batches
of 256 from it; then the weights of the default network are broadcast through the router and
their one-way latency measured. Zero loss means: every transition sent was inserted and no
batch sequence number is missing.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import threading
import time
from pathlib import Path

HELP = "replay service throughput from 4 publishers, sampling, weight latency"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--publishers", type=int, default=4, help="publishing processes")
    p.add_argument("--batches", type=int, default=400, help="batches of 64 transitions per publisher")
    p.add_argument("--paths", default="plain,shm", help="sampling paths to measure: plain (sockets), shm (Zenoh "
                                                       "shared memory), comma-separated")
    p.add_argument("--in-flight", type=int, default=4, help="sample requests the learner keeps outstanding")
    p.add_argument("--per-request", type=int, default=4, help="batches of 256 in one sample request (the learner "
                                                              "service's batches_per_request)")
    p.add_argument("--learner-device", default=None, help="also step a D4PG learner on each sampled batch, on this "
                                                         "device (cpu, cuda)")
    p.add_argument("--learner-variant", default="async", help="how that learner runs (curlnav bench learner --variants)")
    p.add_argument("--insert-rates", default="0,12500", help="insert rates to measure sampling beside, transitions/s in all, "
                                                       "comma-separated; 0: the publishers as fast as they go")


def main(args: argparse.Namespace) -> int:
    run_transport_bench(publishers=args.publishers, batches=args.batches, paths=tuple(args.paths.split(",")),
                        in_flight=args.in_flight, insert_rates=tuple(float(r) for r in args.insert_rates.split(",")),
                        per_request=args.per_request, learner_device=args.learner_device,
                        learner_variant=args.learner_variant)
    return 0


def _publisher(router: str, run: str, actor_id: str, batches: int, per_batch: int, rate: float = 0.0) -> None:
    """``batches`` batches of ``per_batch`` transitions, as fast as the bus takes them (``rate``
    0) or paced at ``rate`` transitions/s."""
    import numpy as np

    from curlnav.bus.transport import open_session, reliable_publisher
    from curlnav.layout import ObservationLayout
    from curlnav.proto.messages import TransitionBatch
    from curlnav.proto.topology import Topology
    from curlnav.replay.nstep import NStepWriter

    layout = ObservationLayout()
    rng = np.random.default_rng(abs(hash(actor_id)) % (1 << 31))
    writer = NStepWriter(layout, 5, 0.99)
    writer.first(rng.uniform(0, 10, layout.size).astype(np.float32))
    obs = rng.uniform(0, 10, layout.size).astype(np.float32)
    # the messages are made before the clock starts: what is timed is the bus and the replay, not
    # this process's n-step writer (an actor runs on a core or a host of its own)
    messages = []
    for seq in range(batches):
        for _ in range(per_batch):
            writer.step(np.array([0.5, 0.0, 0.5], np.float32), 0.1, obs, False, False)
        messages.append(TransitionBatch(actor_id, seq, 1, writer.flush()).encode())
    session = open_session(router)
    pub = reliable_publisher(session, Topology(run).transitions(actor_id))
    time.sleep(1.0)  # let the subscription propagate
    start = time.monotonic()
    for i, message in enumerate(messages):
        if rate > 0 and (wait := start + i * per_batch / rate - time.monotonic()) > 0:
            time.sleep(wait)
        pub.put(message)
    time.sleep(0.5)
    session.close()


def _start_services(run_dir: Path, router: str, run: str, shm: bool) -> tuple[list[subprocess.Popen], str]:
    common = [sys.executable, "-m", "curlnav.cli", "serve"]
    procs = [subprocess.Popen(common + ["router", "--listen", router], stdout=open(run_dir / "logs/router.log", "wb"),
                              stderr=subprocess.STDOUT),
             subprocess.Popen(common + ["replay", "--router", router, "--run", run, "--data-dir", str(run_dir),
                                        "--set", "replay.min_size=256", "--set", "replay.samples_per_insert=0"]
                              + (["--shm"] if shm else []),
                              stdout=open(run_dir / "logs/replay.log", "wb"), stderr=subprocess.STDOUT)]
    port_file = run_dir / "replay" / "http_port"
    deadline = time.monotonic() + 60
    while not port_file.exists() and time.monotonic() < deadline:
        time.sleep(0.2)
    return procs, f"http://127.0.0.1:{int(port_file.read_text())}/healthz"


def _stop(procs: list[subprocess.Popen]) -> None:
    for p in procs[::-1]:
        p.terminate()
        try:
            p.wait(30)
        except subprocess.TimeoutExpired:
            p.kill()


def _insert_and_sample(run_dir: Path, path: str, publishers: int, batches: int, per_batch: int, in_flight: int,
                       weights: bool, insert_rate: float = 0.0, per_request: int = 1,
                       learner_device: str | None = None, learner_variant: str = "async") -> dict:
    """One measurement: ``publishers`` processes insert (as fast as they can, or paced at
    ``insert_rate`` transitions/s in all) while a ``SampleFeed`` (the learner's sampler) samples
    batches of 256 over the same window; ``path`` is plain or shm."""
    from curlnav.bus.transport import open_session
    from curlnav.layout import ObservationLayout
    from curlnav.learner.feed import SampleFeed
    from curlnav.proto.topology import Topology
    from curlnav.run.launch import free_port, http_json

    if run_dir.exists():
        import shutil

        shutil.rmtree(run_dir)
    (run_dir / "logs").mkdir(parents=True)
    router = f"tcp/127.0.0.1:{free_port()}"
    run = "bench"
    procs, replay_url = _start_services(run_dir, router, run, shm=path == "shm")
    try:
        session = open_session(router)
        topo = Topology(run)
        # each publisher's n-step writer (n = 5) holds its last 4 steps back: they never complete
        sent = publishers * (batches * per_batch - 4)
        tag = f"{path}, inserts {'as fast as they go' if insert_rate <= 0 else f'paced at {insert_rate:,.0f}/s'}"
        print(f"[{tag}] {publishers} publisher processes x {batches} batches x {per_batch} steps = {sent:,} "
              f"transitions; the learner's sampler: batches of 256, {per_request} per request, {in_flight} requests "
              f"in flight")
        pubs = [subprocess.Popen([sys.executable, "-m", "curlnav.bench.transport", router, run, f"pub-{i}", str(batches),
                                  str(per_batch), str(insert_rate / publishers)]) for i in range(publishers)]
        learner = _bench_learner(learner_device, learner_variant) if learner_device else None
        feed = SampleFeed(session, topo.sample, 256, ObservationLayout(), in_flight=in_flight,
                          depth=in_flight * per_request, batches_per_request=per_request,
                          assembler=learner[1] if learner else None)
        sampled = [0]
        sample_stop = threading.Event()

        def consume():  # what the learner's loop does with a batch: take it (and, with a learner, step on it)
            while not sample_stop.is_set():
                item = feed.get(timeout=0.2)
                if item is not None:
                    if learner is not None:
                        learner[2](item[1])
                    sampled[0] += 256

        consumer = threading.Thread(target=consume, daemon=True)
        start = None
        while True:  # time from the first accepted transition to the last
            info = http_json(replay_url)
            if start is None and info["inserted"] > 0:
                start = time.monotonic()
                feed.start()
                consumer.start()
            if info["inserted"] >= sent or (all(p.poll() is not None for p in pubs) and start and
                                            time.monotonic() - start > 120):
                break
            time.sleep(0.02)
        elapsed = time.monotonic() - start
        got = sampled[0]
        sample_stop.set()
        consumer.join(timeout=10)
        feed.close()
        for p in pubs:
            p.wait(timeout=60)
        info = http_json(replay_url)
        reasons = _rejection_reasons(replay_url.replace("/healthz", "/metrics"))
        rate = info["inserted"] / elapsed
        sample_rate = got / elapsed
        refused = sum(feed.rejected.values())
        print(f"[{tag}] inserting: {rate:,.0f} transitions/s; accepted {info['inserted']:,} of {sent:,} in "
              f"{elapsed:.2f} s; lost {sent - info['inserted']}, sequence gaps {info['seq_gaps']}, rejected "
              f"{info['rejected']:.0f}{' ' + str(reasons) if reasons else ''}")
        shm_note = f", {feed.payload_shm} of {feed.received} replies through shared memory"
        if learner is not None:
            learner[3]()
            print(f"[{tag}] learner on {learner_device} ({learner_variant}): {sample_rate / 256:,.1f} updates/s of "
                  f"batches sampled from the replay over the bus")
        print(f"[{tag}] sampling:  {sample_rate:,.0f} transitions/s; {sample_rate / 256:,.1f} batches of 256 per "
              f"second over the same {elapsed:.2f} s; lost {feed.unanswered + refused} (unanswered "
              f"{feed.unanswered}, refused {refused}), error replies {feed.errors}{shm_note}")
        out = {"path": path, "insert_rate": insert_rate, "per_request": per_request,
               "transitions_per_s": rate, "lost": sent - info["inserted"], "seq_gaps": info["seq_gaps"],
               "sampled_per_s": sample_rate, "sample_lost": feed.unanswered + refused,
               "shm_replies": feed.payload_shm, "replies": feed.received}
        if weights:
            out["weights_latency_ms"] = _weights_latency(session, router, topo)
        session.close()
        return out
    finally:
        _stop(procs)


def _bench_learner(device: str, variant: str):
    """(state, assembler, step(tensors), finish()) of a D4PG learner on ``device`` run as
    ``variant`` (``curlnav.bench.learner.VARIANTS``)."""
    import torch

    from curlnav.bench.learner import VARIANTS
    from curlnav.config import D4PGConfig
    from curlnav.layout import ObservationLayout
    from curlnav.learner.d4pg import compile_networks, init_state, read_metrics, set_amp, sgd_step
    from curlnav.learner.feed import BatchAssembler, resolve_device

    compile_mode, amp, sync = VARIANTS[variant]
    dev = resolve_device(device)
    state = set_amp(compile_networks(init_state(D4PGConfig(), ObservationLayout(), dev), compile_mode), amp)
    last: list = [None]

    def step(tensors) -> None:
        last[0] = sgd_step(state, tensors, sync=sync)[1]

    def finish() -> None:
        if last[0] is not None:
            read_metrics(last[0])
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    return state, BatchAssembler(dev), step, finish


def _rejection_reasons(url: str) -> dict[str, int]:
    import re
    import urllib.request

    try:
        text = urllib.request.urlopen(url, timeout=5).read().decode()
    except OSError:
        return {}
    return {m[1]: int(float(m[2])) for m in re.finditer(r'replay_messages_rejected_total\{reason="([^"]+)"\} (\S+)', text)}


def _weights_latency(session, router: str, topo) -> float:
    """The default network's weights broadcast through the router: one-way latency (ms)."""
    import numpy as np

    from curlnav.bus.transport import open_session, reliable_publisher
    from curlnav.config import D4PGConfig
    from curlnav.layout import ObservationLayout
    from curlnav.learner.d4pg import init_state
    from curlnav.learner.service import weights_message
    from curlnav.proto.messages import Weights

    state = init_state(D4PGConfig(), ObservationLayout(), "cpu")
    payload_size = len(weights_message(state, 0).encode())
    arrivals: dict[int, float] = {}
    listener = open_session(router)
    sub = listener.declare_subscriber(topo.weights, lambda s: arrivals.setdefault(
        Weights.decode(s.payload.to_bytes()).version, time.perf_counter()))
    pub = reliable_publisher(session, topo.weights)
    time.sleep(1.0)
    latencies = []
    for v in range(1, 31):
        msg = weights_message(state, v)
        sent_at = time.perf_counter()
        pub.put(msg.encode())
        deadline = time.monotonic() + 5
        while v not in arrivals and time.monotonic() < deadline:
            time.sleep(0.0002)
        if v in arrivals:
            latencies.append((arrivals[v] - sent_at) * 1000)
        time.sleep(0.05)
    sub.undeclare()
    listener.close()
    print(f"weights broadcast ({payload_size / 1e6:.2f} MB, default network, encode + router + decode): "
          f"median {np.median(latencies):.1f} ms, p90 {np.percentile(latencies, 90):.1f} ms over {len(latencies)}")
    return float(np.median(latencies))


def shm_support() -> str | None:
    """``None`` when this zenoh wheel can allocate shared memory, else why not."""
    try:
        from zenoh import shm

        provider = shm.ShmProvider.default_backend(1 << 20)
        provider.alloc(1024, shm.BlockOn(shm.GarbageCollect()))
    except Exception as exc:  # an old wheel without zenoh.shm, or no /dev/shm
        return f"{type(exc).__name__}: {exc}"
    return None


def run_transport_bench(publishers: int = 4, batches: int = 400, per_batch: int = 64,
                        run_dir: str = "runs/bench-transport", paths: tuple[str, ...] = ("plain", "shm"),
                        in_flight: int = 4, insert_rates: tuple[float, ...] = (0.0, 12500.0), per_request: int = 4,
                        learner_device: str | None = None, learner_variant: str = "async") -> dict:
    """Inserting and sampling side by side, once per sampling path (plain: the replay replies
    with an ordinary buffer; shm: from a Zenoh shared-memory buffer) and insert rate (0: the
    publishers as fast as they go; else paced, in transitions/s in all), then the weights
    broadcast latency. ``learner_device``: the sampler's batches also go through a D4PG update
    there (``learner_variant``), as the learner service does, so the figure is what a learner on
    that device takes from the bus."""
    print(f"machine: {platform.machine()} cpus={os.cpu_count()} python={platform.python_version()} "
          f"load average {', '.join(f'{x:.2f}' for x in os.getloadavg())}")
    if "shm" in paths and (why := shm_support()) is not None:
        print(f"shm: not measured, this zenoh wheel cannot allocate shared memory ({why})")
        paths = tuple(p for p in paths if p != "shm")
    results = {}
    runs = [(path, rate) for path in paths for rate in insert_rates]
    for i, (path, rate) in enumerate(runs):
        results[f"{path}@{rate:g}"] = _insert_and_sample(Path(run_dir), path, publishers, batches, per_batch, in_flight,
                                                         weights=i == len(runs) - 1, insert_rate=rate,
                                                         per_request=per_request, learner_device=learner_device,
                                                         learner_variant=learner_variant)
    return results


if __name__ == "__main__":
    _publisher(sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4]), int(sys.argv[5]), float(sys.argv[6]))

"""``curlnav bench transport``: the replay service under load, over a real router on loopback.

Four publisher processes send transition batches (64 transitions and 64 frames each, as an
actor would) through a router to a replay service process, while this process samples batches
of 256 from it; then the weights of the default network are broadcast through the router and
their one-way latency measured. Zero loss means: every transition sent was inserted and no
batch sequence number is missing.
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np


def _publisher(router: str, run: str, actor_id: str, batches: int, per_batch: int) -> None:
    from curlnav.bus.transport import open_session, reliable_publisher
    from curlnav.layout import ObservationLayout
    from curlnav.proto.messages import TransitionBatch
    from curlnav.proto.topology import Topology
    from curlnav.replay.nstep import NStepWriter

    layout = ObservationLayout()
    rng = np.random.default_rng(abs(hash(actor_id)) % (1 << 31))
    writer = NStepWriter(layout, 5, 0.99)
    writer.first(rng.uniform(0, 10, layout.size).astype(np.float32))
    session = open_session(router)
    pub = reliable_publisher(session, Topology(run).transitions(actor_id))
    obs = rng.uniform(0, 10, layout.size).astype(np.float32)
    time.sleep(1.0)  # let the subscription propagate
    for seq in range(batches):
        for _ in range(per_batch):
            writer.step(np.array([0.5, 0.0, 0.5], np.float32), 0.1, obs, False, False)
        pub.put(TransitionBatch(actor_id, seq, 1, writer.flush()).encode())
    time.sleep(0.5)
    session.close()


def run_transport_bench(publishers: int = 4, batches: int = 400, per_batch: int = 64,
                        run_dir: str = "runs/bench-transport") -> dict:
    from curlnav.bus.transport import open_session, reliable_publisher
    from curlnav.config import D4PGConfig
    from curlnav.layout import ObservationLayout
    from curlnav.learner.d4pg import init_state
    from curlnav.learner.service import weights_message
    from curlnav.proto.messages import SampledBatch, SampleRequest, Weights
    from curlnav.proto.topology import Topology
    from curlnav.run.launch import free_port, http_json

    run_dir = Path(run_dir)
    if run_dir.exists():
        import shutil

        shutil.rmtree(run_dir)
    (run_dir / "logs").mkdir(parents=True)
    port = free_port()
    router = f"tcp/127.0.0.1:{port}"
    run = "bench"
    print(f"machine: {platform.machine()} cpus={os.cpu_count()} python={platform.python_version()}")
    common = [sys.executable, "-m", "curlnav.cli", "serve"]
    procs = [subprocess.Popen(common + ["router", "--listen", router], stdout=open(run_dir / "logs/router.log", "wb"),
                              stderr=subprocess.STDOUT),
             subprocess.Popen(common + ["replay", "--router", router, "--run", run, "--data-dir", str(run_dir),
                                        "--set", "replay.min_size=256", "--set", "replay.samples_per_insert=0"],
                              stdout=open(run_dir / "logs/replay.log", "wb"), stderr=subprocess.STDOUT)]
    try:
        port_file = run_dir / "replay" / "http_port"
        deadline = time.monotonic() + 60
        while not port_file.exists() and time.monotonic() < deadline:
            time.sleep(0.2)
        replay_url = f"http://127.0.0.1:{int(port_file.read_text())}/healthz"
        session = open_session(router)
        topo = Topology(run)
        # each publisher's n-step writer (n = 5) holds its last 4 steps back: they never complete
        sent = publishers * (batches * per_batch - 4)
        print(f"{publishers} publisher processes x {batches} batches x {per_batch} steps = {sent:,} transitions")
        pubs = [subprocess.Popen([sys.executable, "-m", "curlnav.bench.transport", router, run, f"pub-{i}", str(batches),
                                  str(per_batch)]) for i in range(publishers)]
        sampled = [0]
        sample_stop = threading.Event()

        def sampler():
            request = SampleRequest(256, 0.2).encode()
            while not sample_stop.is_set():
                for reply in session.get(topo.sample, payload=request, timeout=5.0):
                    if reply.ok is not None:
                        SampledBatch.decode(reply.ok.payload.to_bytes())
                        sampled[0] += 256

        thread = threading.Thread(target=sampler, daemon=True)
        # time from the first accepted transition to the last
        start = None
        while True:
            info = http_json(replay_url)
            if start is None and info["inserted"] > 0:
                start = time.monotonic()
                sampled_at_start = sampled[0]
                thread.start()
            if info["inserted"] >= sent or (all(p.poll() is not None for p in pubs) and start and
                                            time.monotonic() - start > 120):
                break
            time.sleep(0.05)
        elapsed = time.monotonic() - start
        sample_stop.set()
        thread.join(timeout=10)
        for p in pubs:
            p.wait(timeout=60)
        info = http_json(replay_url)
        rate = info["inserted"] / elapsed
        print(f"accepted {info['inserted']:,} of {sent:,} transitions in {elapsed:.2f} s: {rate:,.0f} transitions/s; "
              f"lost {sent - info['inserted']}, sequence gaps {info['seq_gaps']}, rejected {info['rejected']}")
        print(f"sampled meanwhile: {(sampled[0] - sampled_at_start) / elapsed:,.0f} transitions/s "
              f"({(sampled[0] - sampled_at_start) / 256 / elapsed:.1f} batches of 256 per second)")
        # weight broadcast latency, default network, through the router
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
        session.close()
        print(f"weights broadcast ({payload_size / 1e6:.2f} MB, default network, encode + router + decode): "
              f"median {np.median(latencies):.1f} ms, p90 {np.percentile(latencies, 90):.1f} ms over {len(latencies)}")
        return {"transitions_per_s": rate, "lost": sent - info["inserted"], "seq_gaps": info["seq_gaps"],
                "sampled_per_s": (sampled[0] - sampled_at_start) / elapsed, "weights_latency_ms": float(np.median(latencies))}
    finally:
        for p in procs[::-1]:
            p.terminate()
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                p.kill()


if __name__ == "__main__":
    _publisher(sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4]), int(sys.argv[5]))

"""openpi clients against a one-at-a-time openpi-protocol server vs through Zetta's openpi endpoint.

Same model on both sides, each in its own process: the baseline serves it the way openpi's own
websocket server does (one observation at a time on its event loop:
services/policy_worker/openpi/serial_main.py); the Zetta side is the openpi endpoint in front of
a policy worker whose scheduler batches the concurrent clients' observations. N closed-loop
``openpi_client.WebsocketClientPolicy`` clients (one thread each) send observations for
``--seconds`` after a warm-up; printed per N: requests/s, p50 and p99 latency of both, side by side.

    python bench/bench_openpi.py [--model zetta-vla-state] [--clients 1,4,16] [--seconds 10]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "clients" / "python"))

from openpi_client.websocket_client_policy import WebsocketClientPolicy

from services.ops.openpi_local import child_env, start_endpoint, start_policy_worker
from services.ops.local_stack import HOST, free_port


def observation(metadata: dict, rng: np.random.Generator) -> dict:
    """A random observation with the inputs the server declares, plus a LIBERO instruction."""
    obs = {}
    for spec in metadata["inputs"]:
        if spec["dtype"] == "uint8":
            obs[spec["name"]] = rng.integers(0, 255, spec["shape"], dtype=np.uint8)
        else:
            obs[spec["name"]] = rng.normal(0, 0.1, spec["shape"]).astype(spec["dtype"])
    obs["prompt"] = "put the cream cheese in the bowl"
    return obs


def drive(address: str, clients: int, seconds: float, warmup: int = 3) -> tuple[float, float, float]:
    """requests/s, p50 ms and p99 ms of ``clients`` closed-loop openpi clients for ``seconds``."""
    host, port = address.split(":")
    policies = [WebsocketClientPolicy(host=host, port=int(port)) for _ in range(clients)]
    latencies: list[list[float]] = [[] for _ in range(clients)]
    start = threading.Barrier(clients + 1)
    stop_at = [0.0]

    def loop(i: int) -> None:
        rng = np.random.default_rng(i)
        obs = observation(policies[i].get_server_metadata(), rng)
        for _ in range(warmup):
            policies[i].infer(obs)
        start.wait()
        while time.monotonic() < stop_at[0]:
            t = time.monotonic()
            policies[i].infer(obs)
            latencies[i].append(time.monotonic() - t)

    threads = [threading.Thread(target=loop, args=(i,), daemon=True) for i in range(clients)]
    for t in threads:
        t.start()
    stop_at[0] = time.monotonic() + 3600
    start.wait()
    began = time.monotonic()
    stop_at[0] = began + seconds
    for t in threads:
        t.join()
    wall = time.monotonic() - began
    for p in policies:
        p._ws.close()
    lat = np.concatenate([np.asarray(x) for x in latencies]) * 1000
    return len(lat) / wall, float(np.percentile(lat, 50)), float(np.percentile(lat, 99))


def start_serial(model: str, workdir: Path) -> tuple[subprocess.Popen[bytes], str]:
    """The one-at-a-time server in its own process; returns once it prints its address."""
    port = free_port()
    log = workdir / "serial.log"
    with open(log, "wb") as err:
        proc = subprocess.Popen([sys.executable, "-m", "services.policy_worker.openpi.serial_main", "--model", model,
                                 "--port", str(port)], stdout=subprocess.PIPE, stderr=err, env=child_env())
    line = proc.stdout.readline().decode() if proc.stdout else ""
    if "serving" not in line:
        raise RuntimeError(f"serial server did not start:\n{log.read_text()[-2000:]}")
    return proc, f"{HOST}:{port}"


def main() -> None:
    """Start both servers, drive each at every N, print the table."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", default="zetta-vla-state")
    p.add_argument("--clients", default="1,4,16")
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--max-batch", type=int, default=16)
    a = p.parse_args()
    ns = [int(x) for x in a.clients.split(",")]
    workdir = Path(tempfile.mkdtemp(prefix="bench-openpi-"))
    serial, serial_addr = start_serial(a.model, workdir)
    worker = start_policy_worker(a.model, workdir, {"ZETTA_MAX_BATCH": str(a.max_batch)})
    endpoint = start_endpoint(worker.address, workdir)
    try:
        print(f"model {a.model}; {a.seconds:.0f} s per point; logs in {workdir}")
        print(f"{'clients':>7} | {'one-at-a-time req/s':>19} {'p50 ms':>7} {'p99 ms':>7} | "
              f"{'zetta endpoint req/s':>20} {'p50 ms':>7} {'p99 ms':>7} | {'speed-up':>8}")
        for n in ns:
            s = drive(serial_addr, n, a.seconds)
            z = drive(endpoint.address, n, a.seconds)
            print(f"{n:>7} | {s[0]:>19.1f} {s[1]:>7.1f} {s[2]:>7.1f} | {z[0]:>20.1f} {z[1]:>7.1f} {z[2]:>7.1f} | "
                  f"{z[0] / s[0]:>7.2f}x", flush=True)
    finally:
        endpoint.stop()
        worker.stop()
        serial.terminate()
        serial.wait(10)


if __name__ == "__main__":
    main()

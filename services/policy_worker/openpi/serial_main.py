"""`python -m services.policy_worker.openpi.serial_main --model NAME [--port 8000]`: a served model
behind a one-request-at-a-time openpi-protocol server (how openpi's own server behaves), in its
own process; bench/bench_openpi.py's baseline. Stops on SIGTERM/SIGINT.
"""

from __future__ import annotations

import argparse
import signal
import threading

from services.policy_worker.models.base import load_model
from services.policy_worker.openpi.serial_server import SerialOpenPIServer


def main() -> None:
    """Load the model, serve it, print the address, wait for a signal."""
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--model", required=True)
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8000)
    a = p.parse_args()
    model = load_model(a.model)
    model.name = a.model
    server = SerialOpenPIServer(model, a.host, a.port).start()
    print(f"serving {a.model} on ws://{server.address}", flush=True)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    stop.wait()
    server.stop()


if __name__ == "__main__":
    main()

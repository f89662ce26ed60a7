"""Container health check: exit 0 when a gRPC server answers grpc.health.v1 Check with SERVING.

    python /app/deploy/docker/healthcheck.py 127.0.0.1:50051 [service] [--timeout 3]

Used by the images' HEALTHCHECK and by deploy/docker-compose.yml (Kubernetes uses its native gRPC
probes instead). Exit codes: 0 SERVING, 1 anything else (NOT_SERVING while draining, unreachable,
timeout), with the reason on stderr.
"""

from __future__ import annotations

import argparse
import sys

import grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc


def main() -> int:
    parser = argparse.ArgumentParser(description="gRPC health check")
    parser.add_argument("address", help="host:port of the server")
    parser.add_argument("service", nargs="?", default="", help="service name; empty means the whole server")
    parser.add_argument("--timeout", type=float, default=3.0, help="seconds")
    args = parser.parse_args()
    try:
        with grpc.insecure_channel(args.address) as channel:
            reply = health_pb2_grpc.HealthStub(channel).Check(
                health_pb2.HealthCheckRequest(service=args.service), timeout=args.timeout
            )
    except grpc.RpcError as err:
        print(f"{args.address}: {err.code().name}: {err.details()}", file=sys.stderr)
        return 1
    status = health_pb2.HealthCheckResponse.ServingStatus.Name(reply.status)
    if reply.status != health_pb2.HealthCheckResponse.SERVING:
        print(f"{args.address}: {status}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

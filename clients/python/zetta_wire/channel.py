"""The gRPC channel options every Zetta client and service uses: one definition for both sides."""

from __future__ import annotations

#: Large enough for a batch of camera observations; the default 4 MiB is not.
MAX_MESSAGE_BYTES = 256 * 1024 * 1024

#: Options of every channel to a Zetta service: large messages, and keepalives that notice a dead
#: peer within half a minute without being refused as abusive by the server.
CHANNEL_OPTIONS: list[tuple[str, int]] = [
    ("grpc.max_send_message_length", MAX_MESSAGE_BYTES),
    ("grpc.max_receive_message_length", MAX_MESSAGE_BYTES),
    ("grpc.keepalive_time_ms", 20_000),
    ("grpc.keepalive_timeout_ms", 10_000),
    ("grpc.keepalive_permit_without_calls", 1),
    ("grpc.http2.max_pings_without_data", 0),
]

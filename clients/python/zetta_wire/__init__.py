"""The wire contract shared by the SDK and the services: generated stubs, tensor codec, error
metadata and channel options. It imports nothing from either side."""

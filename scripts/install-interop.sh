#!/usr/bin/env bash
# Libraries of other ecosystems that the interop tests drive (docs/policies.md, docs/evolution.md,
# docs/other-languages.md): PyPI lerobot-dataset and openpi-client, LeRobot's video decoder
# torchcodec with the FFmpeg libraries it loads, and the Node.js example's node_modules.
# lerobot-dataset and openpi-client pin old numpy/huggingface-hub/datasets releases that the rest
# of the venv cannot take; the parts the tests use run with the venv's versions, so they are
# installed without their pins. torchcodec 0.13 is the release built against torch 2.13.
set -euo pipefail
PY="${1:-.venv}/bin/python"
"$PY" -m pip install -q --no-deps "lerobot-dataset==0.4.4" "openpi-client==0.1.2"
"$PY" -m pip install -q "torchcodec==0.13.0" datasets jsonlines deepdiff termcolor dm-tree
if ! ldconfig -p | grep -q libavcodec && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
  apt-get update -qq && apt-get install -y -qq --no-install-recommends libavcodec59 libavformat59 libavutil57 \
    libswscale6 libswresample4 libavdevice59 libavfilter8 || echo "FFmpeg libraries not installed: LeRobot video tests skip"
fi
if command -v npm >/dev/null && [ -f clients/node/package-lock.json ]; then
  (cd clients/node && npm ci --no-audit --no-fund --silent) || echo "npm ci failed: the Node.js example test skips"
fi

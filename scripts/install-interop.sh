#!/usr/bin/env bash
# Libraries of other ecosystems that the interop tests drive (docs/policies.md, docs/evolution.md,
# docs/other-languages.md): PyPI lerobot-dataset, lerobot and openpi-client, LeRobot's video decoder
# torchcodec with the FFmpeg libraries it loads, and the Node.js example's node_modules.
# lerobot-dataset and openpi-client pin old numpy/huggingface-hub/datasets releases that the rest
# of the venv cannot take; the parts the tests use run with the venv's versions, so they are
# installed without their pins. torchcodec 0.13 is the release built against torch 2.13.
# PyPI lerobot (the policies LeRobotAdapter serves, docs/policies.md) pins torch < 2.11, torchvision,
# huggingface-hub < 0.36 and datasets < 5, which would replace this venv's torch, numpy and protobuf;
# it is installed without them, with the small pure-Python packages its import chain needs (none of
# them is otherwise in the venv, so no installed version changes). torchvision stays out: its PyPI
# wheels are CUDA builds that do not load beside the CPU torch, and
# services/policy_worker/vla/lerobot_import.py stands in for it (policies that need it, ACT,
# Diffusion, VQ-BeT, fail when built; TD-MPC is tested). The lerobot test skips when it does not import.
set -euo pipefail
PY="${1:-.venv}/bin/python"
"$PY" -m pip install -q --no-deps "lerobot-dataset==0.4.4" "openpi-client==0.1.2"
"$PY" -m pip install -q "torchcodec==0.13.0" datasets jsonlines deepdiff termcolor dm-tree
"$PY" -m pip install -q --no-deps "lerobot==0.4.4" "draccus==0.10.0" "mergedeep==1.3.4" "pyyaml-include==1.4.1" \
  "toml==0.10.2" "typing-inspect==0.9.0" "einops==0.8.1" "accelerate==1.16.0" "psutil==7.2.2" "imageio==2.37.0" \
  "diffusers==0.35.2" "pyserial==3.5"
# draccus's wheel ships its own test suite as a top-level package named `tests`, which would shadow
# this project's tests/ (every `from tests.conftest import ...` fails): remove exactly those files.
"$PY" - <<'PY'
import importlib.metadata as md, pathlib, shutil
dist = md.distribution("draccus")
roots = {pathlib.Path(str(f)).parts[0] for f in dist.files or [] if str(f).startswith("tests/")}
for root in roots:
    shutil.rmtree(dist.locate_file(root), ignore_errors=True)
PY
if ! ldconfig -p | grep -q libavcodec && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
  apt-get update -qq && apt-get install -y -qq --no-install-recommends libavcodec59 libavformat59 libavutil57 \
    libswscale6 libswresample4 libavdevice59 libavfilter8 || echo "FFmpeg libraries not installed: LeRobot video tests skip"
fi
if command -v npm >/dev/null && [ -f clients/node/package-lock.json ]; then
  (cd clients/node && npm ci --no-audit --no-fund --silent) || echo "npm ci failed: the Node.js example test skips"
fi

#!/usr/bin/env bash
# The GPU paths measured in one command (bench/gpu_check.py --help says what it runs and writes).
#   bench/gpu_check.sh [--results DIR] [--profile auto|gpu|cpu|tiny] [--checkpoint DIR] ...
# Python: $PYTHON if set, else python3 (on the GPU machine, the one that holds the CUDA torch).
set -euo pipefail
cd "$(dirname "$0")/.."
exec "${PYTHON:-python3}" bench/gpu_check.py "$@"

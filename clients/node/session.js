#!/usr/bin/env node
// Drive one Zetta session from Node.js with @grpc/grpc-js, knowing only proto/ (no generated code,
// no SDK): create a session, reset it, send one action, let the policy act once, close it.
//
//   node session.js GATEWAY_HOST:PORT [env_family] [env_config_json]
//   node session.js 127.0.0.1:50051 robosuite '{"env_name": "Lift"}'
//
// Each step prints one summary line `step: key=value ...`. The three traps of a grpc-js client
// (docs/other-languages.md) are handled by the helpers below: toStruct, shapeOf, toFloat32.
'use strict';

const path = require('path');
const grpc = require('@grpc/grpc-js');
const protoLoader = require('@grpc/proto-loader');

const PROTO_ROOT = process.env.ZETTA_PROTO_DIR || path.resolve(__dirname, '..', '..', 'proto');

function loadGateway() {
  const definition = protoLoader.loadSync('zetta/v1/gateway.proto', {
    includeDirs: [PROTO_ROOT],
    keepCase: true,   // Zetta's fields keep their .proto (snake_case) names: session_ids, env_family
    longs: String,    // int64 fields (Tensor.shape, ResetSpec.seed) arrive as decimal strings
    enums: String,    // enums as their names: 'DTYPE_FLOAT32'
    defaults: true,   // fields at their default value are present (0, '', [])
    oneofs: true,
  });
  return grpc.loadPackageDefinition(definition).zetta.v1.GatewayService;
}

// Trap 1: google.protobuf.Struct comes from protobufjs's bundled descriptor, whose fields are
// camelCase even under keepCase: a Value is {stringValue: ...}, never {string_value: ...}.
// A snake_case key is dropped without an error, and the gateway sees an empty config.
function toValue(v) {
  if (v === null || v === undefined) return { nullValue: 'NULL_VALUE' };
  if (typeof v === 'number') return { numberValue: v };
  if (typeof v === 'string') return { stringValue: v };
  if (typeof v === 'boolean') return { boolValue: v };
  if (Array.isArray(v)) return { listValue: { values: v.map(toValue) } };
  return { structValue: toStruct(v) };
}

function toStruct(obj) {
  const fields = {};
  for (const [k, v] of Object.entries(obj)) fields[k] = toValue(v);
  return { fields };
}

// Trap 2: int64 values (shapes) are strings with longs: String; convert before arithmetic.
function shapeOf(tensor) {
  return tensor.shape.map(Number);
}

// Trap 3: Tensor.data is a Buffer that may start at any byte offset of a shared pool, so a
// Float32Array view over it can be misaligned: copy the bytes out first (little-endian, row-major).
function toFloat32(tensor) {
  if (tensor.dtype !== 'DTYPE_FLOAT32') throw new Error(`expected DTYPE_FLOAT32, got ${tensor.dtype}`);
  const bytes = Uint8Array.from(tensor.data);
  return new Float32Array(bytes.buffer, 0, bytes.byteLength / 4);
}

function float32Tensor(values, shape) {
  const data = Buffer.from(new Float32Array(values).buffer);
  return { dtype: 'DTYPE_FLOAT32', shape: shape.map(String), data };
}

function call(client, method, request) {
  return new Promise((resolve, reject) => {
    const deadline = new Date(Date.now() + 120000);
    client[method](request, { deadline }, (err, response) => {
      if (err) {
        const failed = err.metadata ? err.metadata.get('zetta-failed-sessions') : [];
        reject(new Error(`${method}: ${grpc.status[err.code]}: ${err.details}` +
          (failed.length ? ` (sessions: ${failed.join(',')})` : '')));
      } else {
        resolve(response);
      }
    });
  });
}

async function main() {
  const [address, family = 'robosuite', configJson = '{"env_name": "Lift"}'] = process.argv.slice(2);
  if (!address) {
    console.error('usage: node session.js GATEWAY_HOST:PORT [env_family] [env_config_json]');
    process.exit(2);
  }
  const Gateway = loadGateway();
  const client = new Gateway(address, grpc.credentials.createInsecure());
  let sid = '';
  try {
    const created = await call(client, 'CreateSessions', {
      env_family: family, env_config: toStruct(JSON.parse(configJson)), count: 1,
    });
    const session = created.sessions[0];
    sid = session.session_id;
    const actionShape = shapeOf(session.action_spec);
    console.log(`create: session_id=${sid} worker=${session.worker_id} action_shape=${JSON.stringify(actionShape)}`);

    const reset = await call(client, 'Reset', { session_ids: [sid], specs: [{ seed: '7', init_state_index: 0 }] });
    const r = reset.results[0];
    const tensors = r.observation.tensors;
    const eef = tensors.robot0_eef_pos ? Array.from(toFloat32(tensors.robot0_eef_pos)).map((x) => +x.toFixed(4)) : [];
    console.log(`reset: session_id=${r.session_id} episode_id=${r.episode_id} max_steps=${r.max_steps} ` +
      `observation_tensors=${Object.keys(tensors).length} eef_pos=${JSON.stringify(eef)}`);

    const zeros = new Array(actionShape.reduce((a, b) => a * b, 1)).fill(0);
    const stepped = await call(client, 'ActionStep', { session_ids: [sid], actions: [float32Tensor(zeros, actionShape)] });
    const a = stepped.results[0];
    console.log(`action_step: session_id=${a.session_id} episode_step=${a.episode_step} ` +
      `executed_shape=${JSON.stringify(shapeOf(a.executed_actions))}`);

    const policy = await call(client, 'PolicyStep', { session_ids: [sid], policy: {} });
    const p = policy.results[0];
    const executed = toFloat32(p.executed_actions);
    const last = Array.from(executed.slice(executed.length - actionShape[actionShape.length - 1]));
    console.log(`policy_step: session_id=${p.session_id} episode_step=${p.episode_step} ` +
      `executed_shape=${JSON.stringify(shapeOf(p.executed_actions))} action=${JSON.stringify(last.map((x) => +x.toFixed(4)))}`);
  } finally {
    if (sid) {
      const closed = await call(client, 'CloseSessions', { session_ids: [sid] });
      console.log(`close: closed=${closed.closed_session_ids.join(',')} ` +
        `already_closed=${closed.already_closed_session_ids.join(',')}`);
    }
    client.close();
  }
}

main().catch((err) => {
  console.error(`error: ${err.message}`);
  process.exit(1);
});

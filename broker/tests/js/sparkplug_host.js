#!/usr/bin/env node
/*
 * A Sparkplug B 3.0 host application for tests, driven over stdin/stdout: the second
 * independent reader of what fbbus publishes, after broker/tests/python/sparkplug_host.py.
 * Payloads are decoded and commands encoded by Eclipse Tahu's JavaScript codec
 * (npm sparkplug-payload, `get('spBv1.0').decodePayload` / `encodePayload`); MQTT is
 * MQTT.js (npm mqtt). Both come from the npm cache .ci/run fills: $FBBUS_NPM_DIR, or
 * ~/.cache/fbbus/npm, as broker/testkit's npm_file() finds them.
 *
 *   node sparkplug_host.js --port N [--host 127.0.0.1] [--username U --password P]
 *                          [--client-id ID] [--host-id ID] [--group G] [--max-seconds 120]
 *
 * The protocol is the Python host's (see its docstring); what differs is said here.
 * MQTT 5, clean start. With --host-id: will spBv1.0/STATE/<id> = {"online": false,
 * "timestamp": T} (retained, QoS 1); after the SUBACK, STATE {"online": true, "timestamp": T}
 * (retained, QoS 1), answered by {"event": "puback", "op": "state", ...}; on quit STATE
 * offline with the same T before the DISCONNECT. Subscribes spBv1.0/# (with --group:
 * spBv1.0/G/# and spBv1.0/STATE/+), QoS 1, No Local.
 *
 * stdout, one JSON object per line:
 *   {"event": "ready"}
 *   {"event": "state", "topic", "host_id", "retain", "payload": <JSON or null>[, "text"]}
 *   {"event": "message", "topic", "type", "group", "node", "device": str|null, "qos",
 *    "retain", "seq", "timestamp",
 *    "metrics": [{"name", "alias", "datatype": Tahu's type string ("Int16") or null (Tahu
 *                 names no array type), "datatype_id", "value", "is_null", "timestamp",
 *                 "raw": {"field": "int_value"|..., "value": <as on the wire>},
 *                 ["raw_hex": <bytes_value as hex>]}],
 *    "raw_metrics": [{"name", "alias", "datatype_id", "field", "value", "is_null",
 *                     "timestamp"} as on the wire, before the birth filled anything in]}
 *   {"event": "undecodable", "topic", "error"}  not a Sparkplug protobuf, or Tahu threw
 *   {"event": "sent", "op", "id", "topic", "mid": null, "qos": 0}
 *   {"event": "puback", "op", "id", "topic", "mid", "reason_code"}
 *   {"event": "error", "op", "id", "error"}
 *   {"event": "disconnected", "reason_code": int|null}   then exit 3
 *
 * Values are Tahu's, made JSON: Long (64-bit) values as numbers when within +-2^53, else
 * decimal strings; bytes as hex; DateTime as epoch ms (Tahu returns the raw Long).
 * Tahu's own readings, kept as they are: Int8/Int16/Int32 are read as the int32 of the
 * 32-bit int_value (so the sign-extended 0xFFFFFFFF is -1, and the width-limited Int8 0xFF
 * is 255); UInt32 is read from long_value only (.toInt(), so above 2^31 it is negative);
 * the array datatypes (22-34) are not decoded at all: "value" is null and "raw_hex" holds
 * the bytes. A DATA metric without name or datatype gets them from the last birth
 * (alias -> name, name -> datatype) before Tahu decodes it, which Tahu itself does not do.
 *
 * stdin: the Python host's commands, "rebirth", "ncmd", "dcmd", "publish", "state",
 * "quit" (end of stdin too). METRIC datatypes are Tahu's type names (any case: "Int16",
 * "UInt64", "DateTime", "Boolean", ...); 64-bit values may be given as decimal strings;
 * Bytes/File as hex. Tahu cannot encode the array types: send those with
 * {"raw": {"field": "bytes_value", "value": "<hex>"}, "datatype_id": N}. A raw long_value
 * may be a decimal string.
 *
 * Exit codes: 0 quit; 2 could not connect/subscribe within 10 s or modules missing (stderr);
 * 3 disconnected by the broker; 4 --max-seconds elapsed.
 */
'use strict';

const path = require('path');
const os = require('os');
const { createRequire } = require('module');
const readline = require('readline');

const NAMESPACE = 'spBv1.0';
const WAIT_MS = 10000;
const START = Date.now();

function fail(message) {
  process.stderr.write(`sparkplug_host.js: ${message}\n`, () => process.exit(2));
  setTimeout(() => process.exit(2), 500);
}

function npmDir() {
  if (process.env.FBBUS_NPM_DIR) return process.env.FBBUS_NPM_DIR;
  return path.join(process.env.HOME || os.homedir(), '.cache', 'fbbus', 'npm');
}

const NODE_MODULES = path.join(npmDir(), 'node_modules');
let mqtt, tahu, Proto, Long;
try {
  mqtt = require(path.join(NODE_MODULES, 'mqtt'));
  tahu = require(path.join(NODE_MODULES, 'sparkplug-payload')).get('spBv1.0');
  // The protobuf classes and Long, resolved as sparkplug-payload itself resolves them.
  const spRequire = createRequire(path.join(NODE_MODULES, 'sparkplug-payload', 'package.json'));
  Proto = spRequire('./lib/sparkplugPayloadProto').org.eclipse.tahu.protobuf;
  Long = spRequire('long');
} catch (e) {
  process.stderr.write(`sparkplug_host.js: npm modules missing under ${NODE_MODULES} (run .ci/run): ${e.message}\n`);
  process.exit(2);
}

// ---- arguments ----
const args = { host: '127.0.0.1', port: null, username: null, password: null, clientId: null,
  hostId: null, group: null, maxSeconds: 120 };
{
  const argv = process.argv.slice(2);
  const names = { '--host': 'host', '--port': 'port', '--username': 'username',
    '--password': 'password', '--client-id': 'clientId', '--host-id': 'hostId',
    '--group': 'group', '--max-seconds': 'maxSeconds' };
  for (let i = 0; i < argv.length; i++) {
    const key = names[argv[i]];
    if (!key || i + 1 >= argv.length) {
      process.stderr.write(`sparkplug_host.js: bad argument ${argv[i]}\n`);
      process.exit(2);
    }
    args[key] = argv[++i];
  }
  if (!args.port) {
    process.stderr.write('sparkplug_host.js: --port is required\n');
    process.exit(2);
  }
  args.port = Number(args.port);
  args.maxSeconds = Number(args.maxSeconds);
}

// ---- output ----
function emit(obj) {
  process.stdout.write(JSON.stringify(obj) + '\n');
}

const TWO53 = Long.fromNumber(Number.MAX_SAFE_INTEGER);

/** A decoded value as JSON: Long -> number or decimal string, bytes -> hex. */
function jsonable(v) {
  if (v === undefined || v === null) return null;
  if (Long.isLong(v)) {
    const abs = !v.unsigned && v.isNegative() ? v.negate() : v;
    return abs.lessThanOrEqual(TWO53) ? v.toNumber() : v.toString();
  }
  if (v instanceof Uint8Array) return Buffer.from(v).toString('hex');
  if (typeof v === 'number' && !Number.isFinite(v)) {
    return Number.isNaN(v) ? 'NaN' : (v > 0 ? 'inf' : '-inf');
  }
  if (Array.isArray(v)) return v.map(jsonable);
  if (typeof v === 'object') {
    const out = {};
    for (const k of Object.keys(v)) out[k] = jsonable(v[k]);
    return out;
  }
  return v;
}

function snake(camel) {
  return camel.replace(/[A-Z]/g, (c) => '_' + c.toLowerCase());
}

function has(msg, field) {
  return Object.prototype.hasOwnProperty.call(msg, field) && msg[field] !== null;
}

/** The protobuf value oneof of a metric: [field in snake_case, JSON value] or [null, null]. */
function rawValue(m) {
  const field = m.value; // protobufjs' oneof getter: the name of the field set
  if (!field) return [null, null];
  return [snake(field), jsonable(m[field])];
}

function rawMetricJson(m) {
  const [field, value] = rawValue(m);
  return {
    name: has(m, 'name') ? m.name : null,
    alias: has(m, 'alias') ? jsonable(m.alias) : null,
    datatype_id: has(m, 'datatype') ? m.datatype : null,
    field,
    value,
    is_null: has(m, 'isNull') ? m.isNull : false,
    timestamp: has(m, 'timestamp') ? jsonable(m.timestamp) : null,
  };
}

// ---- births: alias -> name per edge node, name -> datatype per node/device ----
const aliasesByNode = new Map(); // "group/node" -> Map(alias string -> name)
const datatypesBy = new Map(); // "group/node/device|" -> Map(name -> datatype)

function recordBirth(group, node, device, payload) {
  const nodeKey = `${group}/${node}`;
  if (!aliasesByNode.has(nodeKey) || device === null) aliasesByNode.set(nodeKey, new Map());
  const aliases = aliasesByNode.get(nodeKey);
  const datatypes = new Map();
  for (const m of payload.metrics) {
    if (!has(m, 'name')) continue;
    if (has(m, 'alias')) aliases.set(String(m.alias), m.name);
    datatypes.set(m.name, m.datatype);
  }
  datatypesBy.set(`${nodeKey}/${device === null ? '' : device}`, datatypes);
}

function birthName(group, node, alias) {
  const aliases = aliasesByNode.get(`${group}/${node}`);
  return aliases ? aliases.get(String(alias)) : undefined;
}

function birthDatatype(group, node, device, name) {
  for (const d of device === null ? [''] : [device, '']) {
    const types = datatypesBy.get(`${group}/${node}/${d}`);
    if (types && types.has(name)) return types.get(name);
  }
  return undefined;
}

function handleMessage(topic, buf, packet) {
  const parts = topic.split('/');
  if (parts.length < 3 || parts[0] !== NAMESPACE) return;
  if (parts[1] === 'STATE') {
    const text = buf.toString('utf8');
    const event = { event: 'state', topic, host_id: parts[2], retain: !!packet.retain, payload: null };
    try {
      event.payload = JSON.parse(text);
    } catch (e) {
      event.text = text;
    }
    emit(event);
    return;
  }
  if (parts.length < 4) {
    emit({ event: 'undecodable', topic, error: 'topic too short' });
    return;
  }
  const [group, type, node] = [parts[1], parts[2], parts[3]];
  const device = parts.length > 4 ? parts.slice(4).join('/') : null;
  let raw;
  try {
    raw = Proto.Payload.decode(buf);
  } catch (e) {
    emit({ event: 'undecodable', topic, error: `protobuf: ${e.message}` });
    return;
  }
  const isBirth = type === 'NBIRTH' || type === 'DBIRTH';
  if (isBirth) recordBirth(group, node, type === 'DBIRTH' ? device : null, raw);
  const rawMetrics = raw.metrics.map(rawMetricJson);

  // Fill a missing name/datatype from the birth, then let Tahu decode the result.
  let filled = false;
  const work = Proto.Payload.decode(buf);
  for (const m of work.metrics) {
    if (!has(m, 'name') && has(m, 'alias')) {
      const name = birthName(group, node, m.alias);
      if (name !== undefined) { m.name = name; filled = true; }
    }
    if (!m.datatype && has(m, 'name')) {
      const dt = birthDatatype(group, node, device, m.name);
      if (dt !== undefined) { m.datatype = dt; filled = true; }
    }
  }
  let decoded;
  try {
    decoded = tahu.decodePayload(filled ? Proto.Payload.encode(work).finish() : buf);
  } catch (e) {
    emit({ event: 'undecodable', topic, error: `tahu: ${e.message}` });
    return;
  }
  const metrics = (decoded.metrics || []).map((dm, i) => {
    const wm = work.metrics[i];
    const [field, value] = rawValue(wm);
    const out = {
      name: dm.name !== undefined ? dm.name : null,
      alias: dm.alias !== undefined ? jsonable(dm.alias) : null,
      datatype: dm.type !== undefined ? dm.type : null,
      datatype_id: wm.datatype,
      value: jsonable(dm.value),
      is_null: has(wm, 'isNull') ? wm.isNull : false,
      timestamp: dm.timestamp !== undefined ? jsonable(dm.timestamp) : null,
      raw: { field, value },
    };
    if (field === 'bytes_value') out.raw_hex = value;
    return out;
  });
  emit({
    event: 'message', topic, type, group, node, device,
    qos: packet.qos, retain: !!packet.retain,
    seq: decoded.seq !== undefined ? jsonable(decoded.seq) : null,
    timestamp: decoded.timestamp !== undefined ? jsonable(decoded.timestamp) : null,
    metrics, raw_metrics: rawMetrics,
  });
}

// ---- commands ----
const INTEGER_64 = new Set([4, 7, 8, 13]); // Int64, UInt32, UInt64, DateTime: long_value in Tahu

/** Tahu's type code for a name ("Int16"), or for the array names the Sparkplug code. */
const ARRAY_TYPES = ['Int8Array', 'Int16Array', 'Int32Array', 'Int64Array', 'UInt8Array',
  'UInt16Array', 'UInt32Array', 'UInt64Array', 'FloatArray', 'DoubleArray', 'BooleanArray',
  'StringArray', 'DateTimeArray'];
function arrayTypeId(name) {
  const i = ARRAY_TYPES.findIndex((t) => t.toLowerCase() === String(name).toLowerCase());
  return i < 0 ? null : 22 + i;
}
const TYPE_NAMES = ['Int8', 'Int16', 'Int32', 'Int64', 'UInt8', 'UInt16', 'UInt32', 'UInt64',
  'Float', 'Double', 'Boolean', 'String', 'DateTime', 'Text', 'UUID', 'DataSet', 'Bytes',
  'File', 'Template', 'PropertySet', 'PropertySetList'];
function typeId(name) {
  const i = TYPE_NAMES.findIndex((t) => t.toLowerCase() === String(name).toLowerCase());
  if (i >= 0) return i + 1;
  const a = arrayTypeId(name);
  if (a !== null) return a;
  throw new Error(`unknown Sparkplug datatype ${JSON.stringify(name)}`);
}

function toLong(value, unsigned) {
  if (typeof value === 'string') return Long.fromString(value, unsigned);
  return Long.fromNumber(value, unsigned);
}

/** A METRIC for Tahu's encodePayload. */
function tahuMetric(spec, now) {
  const id = typeId(spec.datatype);
  if (id > 21) throw new Error(`Tahu JS cannot encode ${spec.datatype}; send it raw`);
  let value = spec.value === undefined ? null : spec.value;
  if (spec.is_null) value = null;
  if (value !== null) {
    if (INTEGER_64.has(id) && typeof value === 'string') value = toLong(value, id !== 4);
    if (id === 17 || id === 18) value = Buffer.from(value, 'hex');
  }
  const m = { name: spec.name, type: TYPE_NAMES[id - 1], value,
    timestamp: spec.timestamp !== undefined ? spec.timestamp : now };
  if (spec.alias !== undefined) m.alias = spec.alias;
  return m;
}

/** A protobuf metric put together by hand: the raw bypass of Tahu's encoder. */
function rawMetric(spec, now) {
  const fields = { int_value: 'intValue', long_value: 'longValue', float_value: 'floatValue',
    double_value: 'doubleValue', boolean_value: 'booleanValue', string_value: 'stringValue',
    bytes_value: 'bytesValue' };
  const field = fields[spec.raw.field];
  if (!field) throw new Error(`raw field must be one of ${Object.keys(fields).join(', ')}`);
  let value = spec.raw.value;
  if (field === 'bytesValue') value = Buffer.from(value, 'hex');
  if (field === 'longValue') value = toLong(value, true);
  const m = Proto.Payload.Metric.create({ [field]: value });
  if (spec.name !== undefined && spec.name !== null) m.name = spec.name;
  if (spec.alias !== undefined) m.alias = toLong(spec.alias, true);
  if (spec.datatype_id !== undefined) m.datatype = spec.datatype_id;
  else if (spec.datatype !== undefined) m.datatype = typeId(spec.datatype);
  const ts = spec.timestamp !== undefined ? spec.timestamp : now;
  if (ts !== null) m.timestamp = toLong(ts, true);
  if (spec.is_null) m.isNull = true;
  return m;
}

function commandPayload(specs, seq) {
  const now = Date.now();
  const normal = specs.filter((s) => !s.raw).map((s) => tahuMetric(s, now));
  const obj = { timestamp: now, metrics: normal };
  if (seq !== undefined) obj.seq = seq;
  const bytes = tahu.encodePayload(obj);
  if (!specs.some((s) => s.raw)) return Buffer.from(bytes);
  // Splice the raw metrics in at their places.
  const payload = Proto.Payload.decode(bytes);
  const encoded = payload.metrics;
  let k = 0;
  payload.metrics = specs.map((s) => (s.raw ? rawMetric(s, now) : encoded[k++]));
  return Buffer.from(Proto.Payload.encode(payload).finish());
}

let client = null;
let ready = false;
let quitting = false;
const pubackCodes = new Map(); // messageId -> reason code of the last PUBACK seen
const stateTs = Date.now();
let serverDisconnectCode = null;

function stateTopic() {
  return `${NAMESPACE}/STATE/${args.hostId}`;
}
function statePayload(online, ts) {
  return JSON.stringify({ online, timestamp: ts });
}

function publish(op, id, topic, payload, qos, retain, done) {
  client.publish(topic, payload, { qos, retain: !!retain }, (err, packet) => {
    if (qos === 0) {
      if (err) emit({ event: 'error', op, id, error: `publish failed: ${err.message}` });
      else emit({ event: 'sent', op, id, topic, mid: null, qos: 0 });
    } else if (err && typeof err.code !== 'number') {
      emit({ event: 'error', op, id, error: `publish failed: ${err.message}` });
    } else {
      const mid = packet && packet.messageId !== undefined ? packet.messageId : null;
      let code = err ? err.code : (mid !== null && pubackCodes.has(mid) ? pubackCodes.get(mid) : 0);
      if (mid !== null) pubackCodes.delete(mid);
      emit({ event: 'puback', op, id, topic, mid, reason_code: code });
    }
    if (done) done();
  });
}

function handleCommand(cmd, quit) {
  const op = cmd.op;
  const id = cmd.id === undefined ? null : cmd.id;
  const qos = Number(cmd.qos || 0);
  const group = cmd.group !== undefined ? cmd.group : args.group;
  if (op === 'quit') {
    quit();
    return;
  }
  if (op === 'rebirth' || op === 'ncmd' || op === 'dcmd') {
    if (group === null || group === undefined || cmd.node === undefined) throw new Error('group and node are required');
    const metrics = op === 'rebirth'
      ? [{ name: 'Node Control/Rebirth', datatype: 'Boolean', value: true }]
      : (cmd.metrics || []);
    let topic;
    if (op === 'dcmd') {
      if (cmd.device === undefined) throw new Error('device is required');
      topic = `${NAMESPACE}/${group}/DCMD/${cmd.node}/${cmd.device}`;
    } else {
      topic = `${NAMESPACE}/${group}/NCMD/${cmd.node}`;
    }
    publish(op, id, topic, commandPayload(metrics, cmd.seq), qos, false);
  } else if (op === 'publish') {
    publish(op, id, cmd.topic, Buffer.from(cmd.payload_hex || '', 'hex'), qos, cmd.retain);
  } else if (op === 'state') {
    if (!args.hostId) throw new Error('no --host-id: this host has no STATE');
    const ts = cmd.timestamp !== undefined ? cmd.timestamp : stateTs;
    publish(op, id, stateTopic(), statePayload(cmd.online !== false, ts), 1, true);
  } else {
    throw new Error(`unknown op ${JSON.stringify(op)}`);
  }
}

function quitCleanly() {
  if (quitting) return;
  quitting = true;
  const end = () => client.end(false, {}, () => process.exit(0));
  if (args.hostId && client.connected) {
    // A host leaving on purpose says so first, with its session's STATE timestamp.
    const timer = setTimeout(end, WAIT_MS);
    publish('state', null, stateTopic(), statePayload(false, stateTs), 1, true, () => {
      clearTimeout(timer);
      end();
    });
  } else {
    end();
  }
}

function startCommands() {
  const rl = readline.createInterface({ input: process.stdin, terminal: false });
  rl.on('line', (line) => {
    line = line.trim();
    if (!line || quitting) return;
    let cmd;
    try {
      cmd = JSON.parse(line);
      if (cmd === null || typeof cmd !== 'object' || Array.isArray(cmd)) throw new Error('a command is a JSON object');
    } catch (e) {
      emit({ event: 'error', op: null, id: null, error: `bad command: ${e.message}` });
      return;
    }
    try {
      handleCommand(cmd, quitCleanly);
    } catch (e) {
      emit({ event: 'error', op: cmd.op === undefined ? null : cmd.op, id: cmd.id === undefined ? null : cmd.id, error: e.message });
    }
  });
  rl.on('close', quitCleanly);
}

// ---- main ----
const maxTimer = setTimeout(() => {
  process.stderr.write(`sparkplug_host.js: --max-seconds ${args.maxSeconds} elapsed\n`);
  process.exit(4);
}, Math.max(0, args.maxSeconds * 1000 - (Date.now() - START)));
maxTimer.unref();

const startTimer = setTimeout(() => fail(`not connected and subscribed to ${args.host}:${args.port} within ${WAIT_MS / 1000} s`), WAIT_MS);

const options = {
  host: args.host,
  port: args.port,
  protocol: 'mqtt',
  protocolVersion: 5,
  clean: true,
  clientId: args.clientId || `spb-host-js-${process.pid}`,
  keepalive: 30,
  connectTimeout: WAIT_MS,
  reconnectPeriod: 200, // the broker may still be starting; no reconnects once connected
};
if (args.username !== null) options.username = args.username;
if (args.password !== null) options.password = args.password;
if (args.hostId) {
  options.will = { topic: stateTopic(), payload: Buffer.from(statePayload(false, stateTs)), qos: 1, retain: true };
}

client = mqtt.connect(options);
client.on('packetreceive', (packet) => {
  if (packet.cmd === 'puback') pubackCodes.set(packet.messageId, packet.reasonCode || 0);
  if (packet.cmd === 'disconnect') serverDisconnectCode = packet.reasonCode === undefined ? 0 : packet.reasonCode;
});
client.on('error', (err) => {
  if (typeof err.code === 'number') {
    // A CONNACK refusal (or another reason code) while starting.
    if (!ready) fail(`connection refused: reason code ${err.code} (${err.message})`);
    return;
  }
  if (!ready && ['ECONNREFUSED', 'ECONNRESET'].includes(err.code)) return; // retried
  if (!ready) fail(`cannot connect to ${args.host}:${args.port}: ${err.message}`);
});
client.on('close', () => {
  if (!ready || quitting) return;
  emit({ event: 'disconnected', reason_code: serverDisconnectCode });
  process.exit(3);
});
client.once('connect', () => {
  client.options.reconnectPeriod = 0;
  const sub = { qos: 1, nl: true };
  const topics = args.group
    ? { [`${NAMESPACE}/${args.group}/#`]: sub, [`${NAMESPACE}/STATE/+`]: sub }
    : { [`${NAMESPACE}/#`]: sub };
  client.subscribe(topics, (err, granted) => {
    if (err) return fail(`subscription refused: ${err.message}`);
    const bad = (granted || []).filter((g) => g.qos >= 0x80);
    if (bad.length) return fail(`subscription refused: ${JSON.stringify(bad)}`);
    const goReady = () => {
      clearTimeout(startTimer);
      ready = true;
      emit({ event: 'ready' });
      startCommands();
    };
    if (args.hostId) {
      publish('state', null, stateTopic(), statePayload(true, stateTs), 1, true, goReady);
    } else {
      goReady();
    }
  });
});
client.on('message', (topic, payload, packet) => {
  try {
    handleMessage(topic, payload, packet);
  } catch (e) {
    emit({ event: 'undecodable', topic, error: `${e.name}: ${e.message}` });
  }
});

#!/usr/bin/env node
'use strict';
// The conformance protocol of spec/40-conformance.md [CF-29] for the JavaScript port:
//   softrtc conformance run --impl-cmd "node conformance/ports/js/protocol.js"
// One JSON object per line: a hello line first, then one reply per request, in order.

const readline = require('readline');
const rtc = require('./softrtc');

// A number written with a fraction or an exponent ([CF-23]); JSON.parse would make 2.0 the integer 2.
class Real {
  constructor(value) {
    this.value = value;
  }
}

const NUMBER = /-?(?:0|[1-9]\d*)(\.\d+)?([eE][+-]?\d+)?/y;

// JSON text to values, float-written numbers as Real.
function parse(text) {
  let i = 0;
  const ws = () => {
    while (i < text.length && ' \t\n\r'.includes(text[i])) i += 1;
  };
  const fail = (what) => {
    throw new SyntaxError(`${what} at position ${i}`);
  };
  const value = () => {
    ws();
    const c = text[i];
    if (c === '{') {
      i += 1;
      const out = {};
      ws();
      if (text[i] === '}') {
        i += 1;
        return out;
      }
      for (;;) {
        ws();
        if (text[i] !== '"') fail('expected a key');
        const key = string();
        ws();
        if (text[i] !== ':') fail("expected ':'");
        i += 1;
        out[key] = value();
        ws();
        if (text[i] === ',') i += 1;
        else if (text[i] === '}') {
          i += 1;
          return out;
        } else fail("expected ',' or '}'");
      }
    }
    if (c === '[') {
      i += 1;
      const out = [];
      ws();
      if (text[i] === ']') {
        i += 1;
        return out;
      }
      for (;;) {
        out.push(value());
        ws();
        if (text[i] === ',') i += 1;
        else if (text[i] === ']') {
          i += 1;
          return out;
        } else fail("expected ',' or ']'");
      }
    }
    if (c === '"') return string();
    for (const [word, v] of [['true', true], ['false', false], ['null', null]]) {
      if (text.startsWith(word, i)) {
        i += word.length;
        return v;
      }
    }
    NUMBER.lastIndex = i;
    const m = NUMBER.exec(text);
    if (!m) fail('unexpected character');
    i += m[0].length;
    return m[1] !== undefined || m[2] !== undefined ? new Real(Number(m[0])) : Number(m[0]);
  };
  const string = () => {
    const start = i;
    i += 1;
    while (text[i] !== '"') {
      if (i >= text.length) fail('unterminated string');
      i += text[i] === '\\' ? 2 : 1;
    }
    i += 1;
    return JSON.parse(text.slice(start, i));
  };
  const v = value();
  ws();
  if (i !== text.length) fail('trailing text');
  return v;
}

// Arguments whose numbers must be integers ([N-7]): a float-written value there is rejected here, where
// the distinction still exists, as a typed port rejects it when it deserializes.
const INTEGER_KEYS = new Set(['H', 'd', 'e', 's', 'T', 'h_max', 'length', 'delays', 'end']);

function decode(v, key, integer) {
  if (v instanceof Real) {
    if (integer) throw new rtc.ValueError(`${key} must be an integer, got the real ${v.value}`);
    return v.value;
  }
  if (Array.isArray(v)) return v.map((x) => decode(x, key, integer));
  if (v !== null && typeof v === 'object') {
    const out = {};
    for (const [k, x] of Object.entries(v)) out[k] = decode(x, k, integer || INTEGER_KEYS.has(k));
    return out;
  }
  return v;
}

const FUNCTIONS = {
  endpoint: (a) => ({ e: rtc.endpoint(a.rule, a.d) }),
  prefix_weights: (a) => ({ weights: rtc.prefixWeights(a.H, a.d, a.e, a.schedule, a.parametrization) }),
  weights: (a) => ({ weights: rtc.softWeights(a.H, a.d, a.window, a.s) }),
  hard_weights: (a) => ({ weights: rtc.hardWeights(a.H, a.d) }),
  guidance_weights: (a) => ({ weights: rtc.guidanceWeights(a.H, a.s, a.d, a.variant) }),
  guidance_weight: (a) => ({ lam: rtc.guidanceWeight(a.t, a.max_guidance) }),
  method_weights: (a) => ({ weights: rtc.methodWeights(a.method, a.H, a.s, a.d, a.window) }),
  token_times: (a) => ({ times: rtc.tokenTimes(a.weights, a.t) }),
  velocity: (a) => ({ velocity: new rtc.VelocityField(a.field).velocity(a.obs, a.x, a.t) }),
  naive_sample: (a) => {
    const [chunk, trace] = rtc.naiveSample(a.field, a.obs, a.noise, a.T);
    return { chunk, trace };
  },
  rtc_sample: (a) => {
    const [chunk, trace] = rtc.rtcSample(a.field, a.obs, a.noise, a.prior, a.weights, a.T);
    return { chunk, trace };
  },
  rtc_sample_step: (a) => {
    const [chunk, trace] = rtc.rtcSample(a.field, a.obs, a.noise, a.prior, a.weights, a.T, a.step);
    return { chunk, trace };
  },
  shift_prior: (a) => ({ prior: rtc.shiftPrior(a.prev, a.s) }),
  execute_chunks: (a) => rtc.executeChunks(a.chunks, a.delays, a.s),
};

// Non-finite numbers travel as strings; JSON.stringify would write null.
function encode(obj) {
  return JSON.stringify(obj, (k, v) => {
    if (typeof v !== 'number' || Number.isFinite(v)) return v;
    if (Number.isNaN(v)) return 'NaN';
    return v > 0 ? 'Infinity' : '-Infinity';
  });
}

function reply(line) {
  let id = null;
  try {
    const req = parse(line);
    id = req.id;
    const fn = FUNCTIONS[req.function];
    if (!fn) return { id, error: { kind: 'bad_call', message: `no function ${req.function}` } };
    return { id, result: fn(decode(req.args, '', false)) };
  } catch (err) {
    if (err instanceof rtc.ValueError) return { id, error: { kind: 'invalid_input', type: 'ValueError', message: err.message } };
    const where = (err.stack || '').split('\n')[1] || '';
    return { id, error: { kind: 'exception', type: err.name || 'Error', message: String(err.message), where: where.trim() } };
  }
}

function main() {
  process.stdout.write(`${encode({ protocol: 'softrtc-conformance', version: 1, name: 'softrtc-js',
    time_convention: 'data_at_1', functions: Object.keys(FUNCTIONS) })}\n`);
  const rl = readline.createInterface({ input: process.stdin, crlfDelay: Infinity });
  rl.on('line', (line) => {
    if (line.trim()) process.stdout.write(`${encode(reply(line))}\n`);
  });
}

if (require.main === module) main();

module.exports = { parse, decode, reply, FUNCTIONS, Real };

#!/usr/bin/env node
'use strict';
// The JavaScript port in closed loop ([CR-2], [CR-4] of spec/42-rollouts.md):
//   softrtc conformance rollout --impl-cmd "node conformance/ports/js/rollout.js"
// It answers rollout_chunk requests, asking the runner for every evaluation of the policy (the served
// field) and, for the guided methods, its VJP; every other request goes to protocol.js's functions, so
// this program also serves `softrtc conformance run`. Field calls are synchronous round trips on
// stdin/stdout, so the samplers below are plain loops.

const fs = require('fs');
const rtc = require('./softrtc');
const { parse, decode, reply, FUNCTIONS, Real } = require('./protocol');

let buffered = '';
const chunkBuf = Buffer.alloc(1 << 16);

// One line of stdin (without its newline), or null at the end of input.
function readLine() {
  for (;;) {
    const nl = buffered.indexOf('\n');
    if (nl >= 0) {
      const line = buffered.slice(0, nl);
      buffered = buffered.slice(nl + 1);
      return line;
    }
    let n;
    try {
      n = fs.readSync(0, chunkBuf, 0, chunkBuf.length, null);
    } catch (err) {
      if (err.code === 'EAGAIN') continue;
      if (err.code === 'EOF') n = 0;
      else throw err;
    }
    if (n === 0) {
      if (!buffered) return null;
      const line = buffered;
      buffered = '';
      return line;
    }
    buffered += chunkBuf.toString('utf8', 0, n);
  }
}

// Non-finite numbers travel as strings ([CF-29]).
function encode(obj) {
  return JSON.stringify(obj, (k, v) => {
    if (typeof v !== 'number' || Number.isFinite(v)) return v;
    if (Number.isNaN(v)) return 'NaN';
    return v > 0 ? 'Infinity' : '-Infinity';
  });
}

function send(obj) {
  fs.writeSync(1, `${typeof obj === 'string' ? obj : encode(obj)}\n`);
}

// The policy, evaluated by the runner for the observation of the request in flight ([CR-4]).
class ServedField {
  constructor(id) {
    this.id = id;
  }

  ask(msg, key) {
    send({ id: this.id, ...msg });
    const line = readLine();
    const r = line === null ? {} : JSON.parse(line);
    if (!(key in r)) throw new Error(`field request refused: ${r.error || 'the runner closed the protocol'}`);
    return r[key];
  }

  velocity(x, t) {
    return this.ask({ field: 'velocity', x, t }, 'velocity');
  }

  vjp(x, t, cotangent) {
    return this.ask({ field: 'vjp', x, t, cotangent }, 'vjp');
  }
}

function checkInt(name, v, lo, hi) {
  if (!Number.isInteger(v) || v < lo || v > hi) throw new rtc.ValueError(`${name} must be an integer in [${lo}, ${hi}], got ${v}`);
  return v;
}

const map2 = (a, b, f) => a.map((row, j) => row.map((v, i) => f(v, b[j][i], j, i)));

// [S-1], [S-2] naive Euler: x <- x + v(obs, x, t_k) / T.
function naive(field, noise, T) {
  let x = noise;
  for (let k = 0; k < T; k += 1) {
    const v = field.velocity(x, new Array(x.length).fill(k / T));
    x = map2(x, v, (xi, vi) => xi + vi / T);
  }
  return x;
}

// [S-3]..[S-5] training-time RTC: blend toward the prior, per-token time, Euler step, no final blend.
function rtcSteps(field, noise, prior, w, T) {
  let x = noise;
  for (let k = 0; k < T; k += 1) {
    const t = k / T;
    const xb = map2(x, prior, (xi, yi, j) => w[j] * yi + (1 - w[j]) * xi);
    const v = field.velocity(xb, w.map((wj) => wj + (1 - wj) * t));
    x = map2(xb, v, (xi, vi) => xi + vi / T);
  }
  return x;
}

// [G-2]..[G-5] guided inpainting: g = err + (1 - t) (dv/dx)^T err, x <- x + (v + lam g) / T.
function guided(field, noise, prior, w, T, beta) {
  let x = noise;
  for (let k = 0; k < T; k += 1) {
    const t = k / T;
    const tv = new Array(x.length).fill(t);
    const v = field.velocity(x, tv);
    const x1 = map2(x, v, (xi, vi) => xi + (1 - t) * vi);
    const err = map2(prior, x1, (yi, x1i, j) => w[j] * (yi - x1i));
    const jt = field.vjp(x, tv, err);
    const lam = rtc.guidanceWeight(t, beta);
    x = x.map((row, j) => row.map((xi, i) => xi + (v[j][i] + lam * (err[j][i] + (1 - t) * jt[j][i])) / T));
  }
  return x;
}

// One request ([CR-2]): prior, weights [S-6], sampler, then the s executed ticks, [X-4], [R-4].
function rolloutChunk(a, field) {
  const [H, A] = [a.noise.length, a.noise[0].length];
  checkInt('s', a.s, 1, H - 1);
  checkInt('T', a.T, 1, 65536);
  const dmax = Math.min(a.s, H - a.s);
  if (a.prev === null) {
    checkInt('d', a.d, 0, 0);
    checkInt('arrival', a.arrival, 0, 0);
    const chunk = naive(field, a.noise, a.T);
    return { chunk, executed: chunk.slice(0, a.s) };
  }
  checkInt('d', a.d, 0, dmax);
  checkInt('arrival', a.arrival, 0, dmax);
  if (a.prev.length !== H || a.prev[0].length !== A) throw new rtc.ValueError(`prev must have shape [${H}, ${A}]`);
  const prior = rtc.shiftPrior(a.prev, a.s);
  const w = rtc.methodWeights(a.method, H, a.s, a.d, a.window);
  let chunk;
  if (a.method === 'naive') chunk = naive(field, a.noise, a.T);
  else if (a.method.startsWith('inference_')) chunk = guided(field, a.noise, prior, w, a.T, a.max_guidance);
  else chunk = rtcSteps(field, a.noise, prior, w, a.T);
  const e = Math.max(a.d, a.arrival);
  return { chunk, executed: a.prev.slice(a.s, a.s + e).concat(chunk.slice(e, a.s)) };
}

function answer(line) {
  let req;
  try {
    req = parse(line);
  } catch (err) {
    return reply(line);
  }
  if (req.function !== 'rollout_chunk') return reply(line);
  const { id } = req;
  try {
    if (req.args.arrival instanceof Real) throw new rtc.ValueError('arrival must be an integer');
    const a = decode(req.args, '', false);
    return { id, result: rolloutChunk(a, new ServedField(id)) };
  } catch (err) {
    if (err instanceof rtc.ValueError) return { id, error: { kind: 'invalid_input', type: 'ValueError', message: err.message } };
    return { id, error: { kind: 'exception', type: err.name || 'Error', message: String(err.message) } };
  }
}

function main() {
  send({ protocol: 'softrtc-conformance', version: 1, name: 'softrtc-js', time_convention: 'data_at_1',
    functions: [...Object.keys(FUNCTIONS), 'rollout_chunk'] });
  for (let line = readLine(); line !== null; line = readLine()) {
    if (line.trim()) send(answer(line));
  }
}

if (require.main === module) main();

module.exports = { rolloutChunk, naive, rtcSteps, guided };

'use strict';
// Soft RTC in plain JavaScript (Node.js 20+, no dependencies): the parts a robot stack needs at
// deployment, written from spec/ alone. Endpoints [E-1]..[E-6], weights and schedules [W-1]..[W-9],
// guidance weights [G-1], [G-4], method weights [S-6], per-token times [C-1], the reference velocity
// field [F-1], the naive and training-time RTC samplers [S-1]..[S-5], the prior shift and the
// executor ..[X-5]. Every function checks its inputs and throws ValueError naming the argument
// ([N-7]); arrays are plain nested arrays of numbers.

class ValueError extends Error {
  constructor(message) {
    super(message);
    this.name = 'ValueError';
  }
}

const MAX_WINDOW = 4096; // [E-1], [N-12]
const MAX_STEPS = 65536; // [N-12]
const RULES = ['delay_scaled', 'fixed', 'offset', 'hard'];
const RULE_PARAMETERS = { delay_scaled: ['lam', 'h_max'], offset: ['length', 'h_max'], fixed: ['length'], hard: [] };
const SCHEDULES = ['zeros', 'ones', 'linear', 'exp'];
const PARAMETRIZATIONS = ['rtc', 'paper'];
const OVERFLOWS = ['clip', 'zeros'];
const GUIDANCE_SCHEDULES = { hard: 'zeros', soft: 'exp' };
const METHODS = ['naive', 'inference_hard', 'inference_soft', 'train_hard', 'train_soft'];

// ------------------------------------------------------------------ checks [N-7]

function checkInt(name, v, lo, hi) {
  if (typeof v !== 'number' || !Number.isInteger(v) || v < lo || v > hi) {
    throw new ValueError(`${name} must be an integer in [${lo}, ${hi}], got ${JSON.stringify(v)}`);
  }
  return v;
}

function checkReal(name, v, lo, hi, { loOpen = false, hiOpen = false } = {}) {
  const bad = typeof v !== 'number' || !Number.isFinite(v) ||
    (lo !== undefined && (loOpen ? v <= lo : v < lo)) || (hi !== undefined && (hiOpen ? v >= hi : v > hi));
  if (bad) {
    throw new ValueError(`${name} must be a finite real number in ${loOpen ? '(' : '['}${lo}, ${hi ?? 'inf'}` +
      `${hiOpen ? ')' : ']'}, got ${JSON.stringify(v)}`);
  }
  return v;
}

function checkChoice(name, v, choices) {
  if (typeof v !== 'string' || !choices.includes(v)) {
    throw new ValueError(`${name} must be one of ${choices.join(', ')}, got ${JSON.stringify(v)}`);
  }
  return v;
}

// A finite real array of `ndim` dimensions (rectangular, every axis non-empty), values in [lo, hi].
function checkArray(name, a, ndim, { shape, lo, hi } = {}) {
  const dims = [];
  let level = a;
  for (let k = 0; k < ndim; k += 1) {
    if (!Array.isArray(level) || level.length === 0) {
      throw new ValueError(`${name} must be a non-empty ${ndim}-dimensional array`);
    }
    dims.push(level.length);
    level = level[0];
  }
  const walk = (x, k) => {
    if (k === ndim) {
      if (typeof x !== 'number' || !Number.isFinite(x)) throw new ValueError(`${name} must hold finite numbers only`);
      if ((lo !== undefined && x < lo) || (hi !== undefined && x > hi)) {
        throw new ValueError(`${name} values must lie in [${lo}, ${hi}], got ${x}`);
      }
      return;
    }
    if (!Array.isArray(x) || x.length !== dims[k]) throw new ValueError(`${name} must be a rectangular array`);
    x.forEach((y) => walk(y, k + 1));
  };
  walk(a, 0);
  if (shape && shape.some((s, k) => s !== null && s !== dims[k])) {
    throw new ValueError(`${name} must have shape [${shape.map((s) => (s === null ? '*' : s)).join(', ')}], ` +
      `got [${dims.join(', ')}]`);
  }
  return dims;
}

function checkHorizon(H) {
  return checkInt('H', H, 1, MAX_WINDOW);
}

// ------------------------------------------------------------------ endpoints [E-1]..[E-6]

function checkRule(rule) {
  if (rule === null || typeof rule !== 'object' || Array.isArray(rule)) {
    throw new ValueError('rule must be an object with a kind');
  }
  const kind = checkChoice('rule.kind', rule.kind, RULES);
  for (const key of Object.keys(rule)) {
    if (!['kind', 'lam', 'h_max', 'length'].includes(key)) throw new ValueError(`rule has unknown key ${key}`);
    if (key !== 'kind' && !RULE_PARAMETERS[kind].includes(key) && rule[key] !== null) {
      throw new ValueError(`${key} is not a parameter of the ${kind} rule`);
    }
  }
  for (const p of RULE_PARAMETERS[kind]) {
    if (p === 'lam') checkReal('lam', rule.lam, 0, MAX_WINDOW);
    else checkInt(p, rule[p], 0, MAX_WINDOW);
  }
  return rule;
}

// The largest endpoint a rule can give (h_max, or h of fixed); hard is bounded by d itself.
function ruleBound(rule) {
  if (rule.kind === 'delay_scaled' || rule.kind === 'offset') return rule.h_max;
  if (rule.kind === 'fixed') return rule.length;
  return MAX_WINDOW;
}

// The exact value of a finite double as mantissa * 2^exponent (BigInt mantissa).
function exactDouble(x) {
  const view = new DataView(new ArrayBuffer(8));
  view.setFloat64(0, x);
  const hi = view.getUint32(0);
  const lo = view.getUint32(4);
  const biased = (hi >>> 20) & 0x7ff;
  let mant = (BigInt(hi & 0xfffff) << 32n) | BigInt(lo);
  let exp;
  if (biased === 0) exp = -1074;
  else {
    mant |= 1n << 52n;
    exp = biased - 1075;
  }
  return { mant, exp };
}

function ceilDiv(p, q) { // q > 0
  return p >= 0n ? (p + q - 1n) / q : -((-p) / q);
}

// [E-2] ceil(lam * d - 1/10000) on the exact value of lam.
function delayScaledCeil(lam, d) {
  const { mant, exp } = exactDouble(lam);
  const scaled = mant * BigInt(d) * 10000n;
  if (exp >= 0) return Number(ceilDiv(scaled * (1n << BigInt(exp)) - 1n, 10000n));
  const den = 1n << BigInt(-exp);
  return Number(ceilDiv(scaled - den, 10000n * den));
}

function endpoint(rule, d) {
  checkRule(rule);
  checkInt('d', d, 0, MAX_WINDOW);
  if (d === 0) return 0; // [E-6]
  if (rule.kind === 'delay_scaled') return Math.min(delayScaledCeil(rule.lam, d), rule.h_max);
  if (rule.kind === 'offset') return Math.min(d + rule.length, rule.h_max);
  if (rule.kind === 'fixed') return rule.length;
  return d;
}

// ------------------------------------------------------------------ weights [W-1]..[W-9]

function scheduleValue(schedule, x) {
  if (schedule === 'zeros') return 0;
  if (schedule === 'ones') return 1;
  const u = 1 - x;
  if (schedule === 'linear') return u;
  return (u * Math.expm1(u)) / Math.expm1(1); // g(0) = 1 exactly [W-3]
}

function prefixWeights(H, d, e, schedule = 'linear', parametrization = 'rtc') {
  checkHorizon(H);
  checkInt('d', d, 0, H);
  checkInt('e', e, d, H);
  checkChoice('schedule', schedule, SCHEDULES);
  checkChoice('parametrization', parametrization, PARAMETRIZATIONS);
  const w = new Array(H).fill(0);
  for (let j = 0; j < d; j += 1) w[j] = 1;
  for (let j = d; j < e; j += 1) {
    const x = parametrization === 'rtc' ? (j - d + 1) / (e - d + 1) : (j - d) / (e - d);
    w[j] = scheduleValue(schedule, x);
  }
  return w;
}

const DEFAULT_WINDOW = { rule: { kind: 'delay_scaled', lam: 2.0, h_max: 5 }, schedule: 'linear',
  parametrization: 'rtc', overflow: 'clip' };

// A window object; absent keys take the defaults of [W-7], the rule is required ([CF-7]).
function checkWindow(H, window) {
  if (window === null || typeof window !== 'object' || Array.isArray(window) || !('rule' in window)) {
    throw new ValueError('window must be an object with a rule');
  }
  for (const key of Object.keys(window)) {
    if (!['rule', 'schedule', 'parametrization', 'overflow'].includes(key)) {
      throw new ValueError(`window has unknown key ${key}`);
    }
  }
  const w = { ...DEFAULT_WINDOW, ...window };
  checkRule(w.rule);
  checkChoice('schedule', w.schedule, SCHEDULES);
  checkChoice('parametrization', w.parametrization, PARAMETRIZATIONS);
  checkChoice('overflow', w.overflow, OVERFLOWS);
  if (w.rule.kind !== 'hard' && ruleBound(w.rule) > H) {
    throw new ValueError(`window endpoint bound (h_max or h) must be <= H=${H}, got ${ruleBound(w.rule)}`);
  }
  return w;
}

// [W-2], [W-6] e* = max(e, d), clipped at the overlap H - s under clip; s is checked whenever given.
function effectiveEndpoint(H, d, e, s, overflow) {
  let eStar = Math.max(e, d);
  if (s !== null && s !== undefined) checkInt('s', s, 1, H);
  if (overflow === 'clip') {
    if (s === null || s === undefined) throw new ValueError("s is required when overflow is 'clip'");
    eStar = Math.max(d, Math.min(eStar, H - s));
  }
  return eStar;
}

function softWeights(H, d, window, s) {
  checkHorizon(H);
  checkInt('d', d, 0, H);
  const w = checkWindow(H, window);
  const e = Math.min(endpoint(w.rule, d), H);
  return prefixWeights(H, d, effectiveEndpoint(H, d, e, s, w.overflow), w.schedule, w.parametrization);
}

function hardWeights(H, d) {
  checkHorizon(H);
  checkInt('d', d, 0, H);
  return Array.from({ length: H }, (_, j) => (j < d ? 1 : 0));
}

// ------------------------------------------------------------------ guidance weights [G-1], [G-4]; methods [S-6]

function guidanceWeights(H, s, d, variant) {
  checkHorizon(H);
  checkInt('s', s, 1, H);
  checkInt('d', d, 0, H - s);
  checkChoice('variant', variant, Object.keys(GUIDANCE_SCHEDULES));
  return prefixWeights(H, d, H - s, GUIDANCE_SCHEDULES[variant], 'rtc');
}

function guidanceWeight(t, maxGuidance) {
  checkReal('t', t, 0, 1, { hiOpen: true });
  checkReal('max_guidance', maxGuidance, 0, undefined, { loOpen: true });
  const c = t === 0 ? Infinity : (1 - t) / t;
  const invR2 = (t * t + (1 - t) ** 2) / (1 - t) ** 2;
  return Math.min(c * invR2, maxGuidance);
}

// an executable delay: 0 <= d <= min(s, H - s).
function checkDelay(H, s, d) {
  checkHorizon(H);
  checkInt('s', s, 1, H);
  return checkInt('d', d, 0, Math.min(s, H - s));
}

function methodWeights(method, H, s, d, window) {
  checkChoice('method', method, METHODS);
  checkDelay(H, s, d);
  if (window !== null && window !== undefined) checkWindow(H, window);
  if (method === 'naive') return new Array(H).fill(0);
  if (method.startsWith('inference_')) return guidanceWeights(H, s, d, method.slice('inference_'.length));
  if (method === 'train_hard') return hardWeights(H, d);
  return softWeights(H, d, window ?? DEFAULT_WINDOW, s);
}

// [C-1] t_j = w_j + (1 - w_j) t.
function tokenTimes(weights, t) {
  checkArray('weights', weights, 1, { lo: 0, hi: 1 });
  checkReal('t', t, 0, 1);
  return weights.map((w) => w + (1 - w) * t);
}

// ------------------------------------------------------------------ reference velocity field [F-1]

const PARAM_NAMES = ['W1', 'Wt', 'Wo', 'b1', 'W2', 'b2'];

function vecmat(v, M) { // v [n] times M [n, k], summed in index order
  const out = new Array(M[0].length).fill(0);
  for (let i = 0; i < v.length; i += 1) {
    const row = M[i];
    const vi = v[i];
    for (let k = 0; k < out.length; k += 1) out[k] += vi * row[k];
  }
  return out;
}

class VelocityField {
  constructor(params) {
    if (params === null || typeof params !== 'object') throw new ValueError('field must be an object of weights');
    const keys = Object.keys(params).sort();
    if (keys.join() !== [...PARAM_NAMES].sort().join()) {
      throw new ValueError(`field must have exactly the weights ${PARAM_NAMES.join(', ')}`);
    }
    const [HA, K] = checkArray('W1', params.W1, 2);
    const [H3] = checkArray('Wt', params.Wt, 2, { shape: [null, K] });
    if (H3 % 3 || HA % (H3 / 3)) throw new ValueError('Wt must have shape [3H, K] and W1 [H*A, K]');
    const [O] = checkArray('Wo', params.Wo, 2, { shape: [null, K] });
    checkArray('b1', params.b1, 1, { shape: [K] });
    checkArray('W2', params.W2, 2, { shape: [K, HA] });
    checkArray('b2', params.b2, 1, { shape: [HA] });
    this.p = params;
    this.H = H3 / 3;
    this.A = HA / this.H;
    this.O = O;
  }

  // v(obs, x, t) [H, A] for chunk x [H, A] and per-token times t [H] in [0, 1].
  velocity(obs, x, t) {
    checkArray('obs', obs, 1, { shape: [this.O] });
    checkArray('x', x, 2, { shape: [this.H, this.A] });
    checkArray('t', t, 1, { shape: [this.H], lo: 0, hi: 1 });
    const phi = t.flatMap((tj) => [tj, Math.sin(Math.PI * tj), Math.cos(Math.PI * tj)]);
    const a = vecmat(x.flat(), this.p.W1);
    const b = vecmat(phi, this.p.Wt);
    const c = vecmat(obs, this.p.Wo);
    const h = a.map((ak, k) => Math.tanh(ak + b[k] + c[k] + this.p.b1[k]));
    const out = vecmat(h, this.p.W2).map((vk, k) => vk + this.p.b2[k]);
    return Array.from({ length: this.H }, (_, j) => out.slice(j * this.A, (j + 1) * this.A));
  }
}

// ------------------------------------------------------------------ samplers [S-1]..[S-5], [S-10]

function checkSteps(T) {
  return checkInt('T', T, 1, MAX_STEPS);
}

function naiveSample(field, obs, noise, T) {
  const f = new VelocityField(field);
  checkArray('noise', noise, 2, { shape: [f.H, f.A] });
  checkArray('obs', obs, 1, { shape: [f.O] });
  checkSteps(T);
  let x = noise;
  const trace = [];
  for (let k = 0; k < T; k += 1) {
    const time = new Array(f.H).fill(k / T);
    const v = f.velocity(obs, x, time);
    const next = x.map((row, j) => row.map((xi, i) => xi + v[j][i] / T));
    trace.push({ state: x, time, velocity: v, next_state: next });
    x = next;
  }
  return [x, trace];
}

// The training-time sampler's solver steps [S-10]; 'algorithm1' (the paper's) is the default.
const STEPS = ['algorithm1', 'consistent'];

function rtcSample(field, obs, noise, prior, weights, T, step = 'algorithm1') {
  const f = new VelocityField(field);
  checkArray('noise', noise, 2, { shape: [f.H, f.A] });
  checkArray('obs', obs, 1, { shape: [f.O] });
  checkArray('prior', prior, 2, { shape: [f.H, f.A] });
  checkArray('weights', weights, 1, { shape: [f.H], lo: 0, hi: 1 });
  checkSteps(T);
  checkChoice('step', step, STEPS);
  const consistent = step === 'consistent';
  // [S-10] per-token step size c = 1 - w (1 at w = 1); c = 1 makes (c v) / T equal v / T exactly [S-11].
  const c = weights.map((w) => (consistent && w < 1 ? 1 - w : 1));
  // [S-10] window tokens (0 < w < 1) are blended before the first step only, then carried.
  const again = weights.map((w) => !consistent || w === 0 || w === 1);
  let x = noise;
  const trace = [];
  for (let k = 0; k < T; k += 1) {
    const t = k / T;
    const blended = x.map((row, j) => (k === 0 || again[j]
      ? row.map((xi, i) => weights[j] * prior[j][i] + (1 - weights[j]) * xi) : row));
    const time = weights.map((w) => w + (1 - w) * t);
    const v = f.velocity(obs, blended, time);
    const next = blended.map((row, j) => row.map((xi, i) => xi + (c[j] * v[j][i]) / T)); // no final blend [S-5]
    trace.push({ state: x, time, velocity: v, blended_state: blended, next_state: next });
    x = next;
  }
  return [x, trace];
}

// ------------------------------------------------------------------ executor ..[X-5]

function shiftPrior(prev, s) {
  const [H] = checkArray('prev', prev, 2);
  checkInt('s', s, 1, H);
  return prev.map((row, j) => (j + s < H ? prev[j + s].slice() : row.map(() => 0)));
}

function executeChunks(chunks, delays, s) {
  const [C, H] = checkArray('chunks', chunks, 3);
  checkInt('s', s, 1, H);
  if (!Array.isArray(delays) || delays.length !== C) {
    throw new ValueError(`delays must hold one integer per chunk (${C})`);
  }
  checkInt('delays[0]', delays[0], 0, 0);
  delays.forEach((d, c) => checkInt(`delays[${c}]`, d, 0, Math.min(s, H - s)));
  const actions = [];
  const chunkIndex = [];
  const tokenIndex = [];
  for (let j = 0; j < s; j += 1) {
    actions.push(chunks[0][j]);
    chunkIndex.push(0);
    tokenIndex.push(j);
  }
  for (let c = 1; c < C; c += 1) {
    const d = delays[c];
    for (let j = s; j < s + d; j += 1) { // committed prefix from the previous chunk
      actions.push(chunks[c - 1][j]);
      chunkIndex.push(c - 1);
      tokenIndex.push(j);
    }
    for (let j = d; j < s; j += 1) {
      actions.push(chunks[c][j]);
      chunkIndex.push(c);
      tokenIndex.push(j);
    }
  }
  return { actions, chunk_index: chunkIndex, token_index: tokenIndex };
}

module.exports = {
  ValueError, endpoint, prefixWeights, softWeights, hardWeights, guidanceWeights, guidanceWeight, methodWeights,
  tokenTimes, VelocityField, naiveSample, rtcSample, STEPS, shiftPrior, executeChunks,
};

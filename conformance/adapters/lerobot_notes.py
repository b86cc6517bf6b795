"""Hand-written text of LeRobot's compatibility report ([TP-3]): diagnoses of the failing requirement
ids, why each unsupported function is unsupported, which cases test glue, other implementations looked
for. ``softrtc conformance report --impl lerobot`` stops when a failing id has no diagnosis here, when a
diagnosis does not cover a function that fails, or when a diagnosed id no longer fails.

One module serves both releases of the compatibility matrix ([TP-7]): LeRobot 0.4.4 on Python 3.11 and
0.6.1 on Python 3.12. :data:`VERSION` is the installed release, and the few texts that differ between
them (the shared Euler loop of 0.6, the queue's clamp of a negative delay) are chosen by it.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    VERSION = version("lerobot")
except PackageNotFoundError:  # the adapter's import then fails with the install step ([TP-6])
    VERSION = "not installed"
# 0.6 has its own Euler loop (`euler_integrate`) and clamps a negative delay in `ActionQueue`.
NEW = VERSION.split(".")[:2] >= ["0", "6"] and VERSION != "not installed"

IMPLEMENTATION = "LeRobot"
INSTALL = ("pip install torch==2.13.0; pip install --no-deps lerobot==0.6.1 (Python 3.12)" if NEW
           else "pip install --no-deps lerobot==0.4.4")
SOURCE = (f"`lerobot/policies/rtc/` of LeRobot {VERSION}: `modeling_rtc.py` (`RTCProcessor.get_prefix_weights`, "
          "`RTCProcessor.denoise_step` and its debug tracker), `action_queue.py` (`ActionQueue`), "
          "`configuration_rtc.py` (`RTCConfig`)"
          + ("; `lerobot/policies/common/flow_matching.py` (`euler_integrate`)" if NEW else ""))

# Interface functions the adapter does not provide, and why ([CF-9]).
_TRAINING = (f"LeRobot {VERSION} has inference-time RTC only: no policy conditions training on a committed "
             "prefix (its flow policies pi0, pi05 and smolvla train the plain flow-matching loss)")
UNSUPPORTED_FUNCTIONS = {
    "endpoint": "LeRobot has no endpoint rules; the guided window's end is the number `execution_horizon` "
                "(our `e`, [V-4])",
    "weights": "LeRobot has no soft training windows (endpoint rule, overflow); its inference-time "
               "prefix weights are tested through `prefix_weights` and `guidance_weights`",
    "delay_probs": "LeRobot draws no training delays; it measures the inference delay at run time",
    "sample_delay": "LeRobot draws no training delays; it measures the inference delay at run time",
    "corrupt": _TRAINING,
    "token_times": _TRAINING,
    "loss": _TRAINING,
    "batch_loss": _TRAINING,
    "rtc_sample": _TRAINING + "; the training-time RTC sampler needs a policy trained so",
    "rtc_sample_step": _TRAINING + "; the training-time RTC sampler needs a policy trained so, whatever its "
                       "solver step",
    "velocity": "the velocity field is the test's stand-in for a policy, not part of LeRobot's RTC",
    "velocity_vjp": "LeRobot takes no VJP of the velocity field alone (its pull-back is taken through the "
                    "denoised estimate, checked by the guided cases)",
    "difference_norm": "LeRobot has no smoothness metrics",
    "action_delta": "LeRobot has no smoothness metrics",
    "action_jerk": "LeRobot has no smoothness metrics",
    "boundary_jump": "LeRobot has no smoothness metrics",
    "bootstrap_interval": "LeRobot has no evaluation statistics",
    "standard_error": "LeRobot has no evaluation statistics",
}

# Functions whose cases test the adapter's glue rather than LeRobot.
GLUE_ONLY = {} if NEW else {
    "naive_sample": "LeRobot's only part is `denoise_step` returning the policy's own velocity when there is no "
                    "previous chunk; the Euler loop is the adapter's copy of the loop LeRobot writes inline in "
                    "each flow policy",
}

# The one cause behind every guided-sampler failure, stated once and referred to by id.
_PULLBACK = "the guided step's pull-back lacks the velocity field's Jacobian term (see G-3)"

# Failing requirement ids: the functions whose failing cases the text explains, the kind of difference,
# a one-line summary (the README's table) and the diagnosis in the spec's terms.
DIAGNOSES = {
    "G-3": {
        "functions": ["guided_sample"],
        "kind": "defect",
        "summary": "pull-back `g` is the weighted error alone; the term `(1 - t) (dv/dx)^T err` is missing",
        "text": (
            "`RTCProcessor.denoise_step` calls the policy on the state before it marks the state as requiring "
            "gradients, so autograd sees the velocity as a constant: the pull-back it takes through the "
            "denoised estimate `x1 = x - t' u` is `err` itself, not `g = err + (1 - t) (dv/dx)^T err` of "
            "[G-3]. The first differing trace step shows it: state, time, velocity, denoised estimate, "
            "weighted error and guidance weight agree with the reference, the pull-back `vjp` (and with it "
            "the guided velocity and the next state) does not. Every guided chunk LeRobot produces equals, "
            "within 3e-7, the reference guided sampler run with the field's VJP replaced by zero "
            "(`tests/conformance/test_lerobot.py` checks this on every guided case), which is the mutant "
            "'guidance without the VJP term' that [CF-20] requires the runner to catch. LeRobot's own "
            "documentation of `denoise_step` describes the correction as an autograd pull-back through the "
            "denoised estimate, so this reads as a defect of the order of two lines, not a chosen "
            "approximation; the spec names no stop-gradient alternative. Its effect: guidance pulls the "
            "state toward the prior directly instead of through the policy's Jacobian, and a weighted token "
            "moves no other token."),
    },
    "F-2": {
        "functions": ["guided_sample"],
        "kind": "consequence of G-3",
        "summary": _PULLBACK,
        "text": (
            "The guided cases name [F-2] because the reference pull-back of [G-3] uses the field's VJP "
            "`(dv/dx)^T err`. LeRobot never takes it (G-3). No `velocity_vjp` case runs: the field is the "
            "test's stand-in for a policy, not LeRobot code."),
    },
    "G-2": {
        "functions": ["guided_sample"],
        "kind": "consequence of G-3",
        "summary": _PULLBACK,
        "text": (
            "LeRobot's denoised estimate `x1 = x - t' u` is [G-2]'s `x + (1 - t) v` under [V-1], and it "
            "agrees at the first step of every guided case; the guided cases fail as a whole because the "
            "pull-back of G-3 moves the state from the first step on."),
    },
    "G-5": {
        "functions": ["guided_sample"],
        "kind": "consequence of G-3",
        "summary": _PULLBACK,
        "text": (
            "The step, `x + dt (u - lam g)` with `dt = -1/T` in "
            + ("LeRobot's `euler_integrate`" if NEW else "the loop LeRobot's flow policies write inline")
            + ", is [G-5] under [V-1]; it is given the pull-back of G-3."),
    },
    "G-1": {
        "functions": ["guidance_weights", "guided_sample", "method_weights"],
        "kind": "consequence of G-3; the alternative of [W-2]; no check of d against s",
        "summary": "guided chunks differ through G-3; d > H - s and d > s are accepted",
        "text": (
            "The weights themselves agree: `get_prefix_weights(d, H - s, H)` under the ZEROS (hard) and EXP "
            "(soft) schedules is [G-1] for every valid `(H, s, d)`, so all valid `guidance_weights` cases "
            "pass. The guided samplers fail through G-3. Two inputs that must be rejected are accepted: with "
            "`d > H - s` LeRobot lets the window's end win (`start = min(start, end)`), giving 1 on the "
            "first `H - s` tokens only, the alternative of [W-2] that the spec did not choose because it "
            "un-clamps committed actions; with `d > s` it cannot object, since its weights never see the "
            "execute horizon `s`, only the window's end."),
    },
    "G-4": {
        "functions": ["guidance_weight", "guided_sample"],
        "kind": "no check of t < 1; consequence of G-3",
        "summary": "`lam(1)` returns 0 instead of an error; guided chunks differ through G-3",
        "text": (
            "LeRobot's guidance weight agrees with [G-4] for every `t` in `[0, 1)` (all valid "
            "`guidance_weight` cases pass, the cap at `t = 0` included, which LeRobot reaches by replacing "
            "the infinite `c` by the cap). At `t = 1`, outside [G-4]'s domain, it returns 0 instead of "
            "raising: `0 * inf` is NaN there, and `torch.nan_to_num` turns NaN into 0. The sampler never "
            "evaluates `t = 1`, so no chunk changes. The guided sampler cases fail through G-3."),
    },
    "S-6": {
        "functions": ["guided_sample", "method_weights"],
        "kind": "consequence of G-3 and S-8",
        "summary": "the inference methods' chunks differ through G-3; `d > s` is accepted (S-8)",
        "text": (
            "[S-6]'s inference methods are LeRobot's guided sampler, which fails through G-3. Their weights "
            "agree on valid requests; the request with `d > s` is accepted (S-8)."),
    },
    "S-1": {
        "functions": ["naive_sample"],
        "kind": "no bound on the step count" if NEW else "glue, no bound on the step count",
        "summary": ("a step count above 65536 is accepted by `euler_integrate`" if NEW else
                    "a step count above 65536 is accepted (the Euler loop is adapter glue)"),
        "text": (
            "LeRobot 0.6's `euler_integrate` (`lerobot/policies/common/flow_matching.py`), the loop its flow "
            "policies now share, is the naive sampler when RTC is off (the first chunk's path), and it agrees "
            "with [S-1] for every valid step count. The one failing case asks for `T = 65537` steps, beyond "
            "[N-12]'s bound; `euler_integrate` bounds the count nowhere (the policies take it from their "
            "configuration)." if NEW else
            "LeRobot has no naive sampler function: each flow policy writes its Euler loop inline, so the "
            "`naive_sample` cases run the adapter's copy of that loop ([TP-6]) and test glue, not LeRobot. "
            "The one failing case asks for `T = 65537` steps, beyond [N-12]'s bound; LeRobot's policies take "
            "their step count from their configuration and bound it nowhere, and the glue follows them. "
            "Every valid step count agrees with [S-1]."),
    },
    "CF-34": {
        "functions": ["guidance_weight"],
        "kind": "no input checks; a different error type",
        "summary": "an array flow time raises TypeError, not ValueError",
        "text": (
            "[CF-34] settles that `guidance_weight` takes a scalar flow time `t` and that an array is an "
            "input error ([N-7]: `ValueError`). LeRobot's guidance weight is computed inside "
            "`RTCProcessor.denoise_step`, which multiplies the time by tensors without checking it; given "
            "an array it fails in that arithmetic with `TypeError`. Valid scalar times agree (G-4)."),
    },
    "S-8": {
        "functions": ["method_weights"],
        "kind": "no check of d against s",
        "summary": "an inference request with `d > s` is accepted",
        "text": (
            "[S-8] checks a method request whole, `d <= s` of [X-1] included. LeRobot's weights depend on "
            "the delay and the window's end only and never see `s`, so `inference_hard` with `d = 3 > s = 2` "
            "returns 1 on the first three tokens. In LeRobot's control loop the delay is measured, and "
            "nothing compares it with the execute horizon."),
    },
    "W-1": {
        "functions": ["prefix_weights"],
        "kind": "the alternative of [W-2]; no range checks",
        "summary": "`e < d`, `e > H` and `H > 4096` are accepted",
        "text": (
            "Valid weights agree for every schedule under the `rtc` parametrization. Three inputs that "
            "`prefix_weights` must reject ([W-7]) are accepted: `e < d` gives 1 on the first `e` tokens only "
            "(`start = min(start, end)`, the alternative of [W-2] that the spec did not choose, which "
            "un-clamps committed actions); `e > H` is clipped to `H` without a word (the ramp ends at the "
            "chunk's end); `H = 4097`, beyond [N-12]'s range, gives weights of that length. LeRobot's `paper` "
            "parametrization does not exist (those cases are unsupported)."),
    },
    "W-8": {
        "functions": ["hard_weights"],
        "kind": "no range check",
        "summary": "`H > 4096` is accepted",
        "text": (
            "Hard weights, LeRobot's ZEROS schedule over the whole chunk, agree for every valid `(H, d)`; "
            "only `H = 4097`, beyond [N-12]'s range, is accepted instead of rejected."),
    },
    "N-12": {
        "functions": ["hard_weights", "naive_sample", "prefix_weights"],
        "kind": "no range check",
        "summary": "no upper bound on the chunk length or the step count",
        "text": (
            "LeRobot bounds no chunk length; `H = 4097` gives weights of that length. Nor does it bound the "
            "number of Euler steps" + (" (`euler_integrate`, S-1)" if NEW else ", and the adapter's glue loop (S-1) follows it")
            + ", so `T = 65537` runs. The spec "
            "bounds `H` at 4096 and `T` at 65536 so that every port knows where an input is an error; nothing "
            "in LeRobot depends on a bound."),
    },
    "N-7": {
        "functions": ["execute_chunks", "guidance_weight", "guidance_weights", "hard_weights", "method_weights",
                      "naive_sample", "prefix_weights"],
        "kind": "no input checks",
        "summary": "invalid inputs return results instead of raising ValueError",
        "text": (
            "LeRobot's RTC code checks two inputs (`RTCConfig` rejects a guidance cap or a debug length "
            "`<= 0`, and the `max_guidance` cases that need it pass); everything else is taken as given. A "
            "delay beyond the overlap or below 0, a window end below the delay or past the chunk, a chunk "
            "longer than 4096, flow time 1 and more than 65536 Euler steps ("
            + ("in `euler_integrate`" if NEW else "in the adapter's glue loop, which follows LeRobot's unbounded "
               "step count") + ") each return a result instead of raising `ValueError` (see "
            "W-1, G-1, G-4, S-1, S-8, X-1, X-2); an array flow time raises `TypeError` (CF-34); a float delay reaches Python's slicing, which raises `TypeError`."),
    },
    "X-1": {
        "functions": ["execute_chunks", "method_weights"],
        "kind": "no check of the delay; a late chunk idles the robot",
        "summary": "delays outside `[0, min(s, H - s)]` are executed anyway",
        "text": (
            "Executed actions, chunk and token indices agree for every valid delay sequence: `ActionQueue` in "
            "RTC mode drops the new chunk's first `real_delay` actions while the previous chunk's leftover "
            "runs, exactly [X-4]. Delays [X-1] rejects are executed: a delay past the leftover (`d > H - s`) "
            "or past `s` leaves the queue empty for some steps (it returns None; the adapter's loop idles "
            "there as a robot loop does, so fewer than `C s` actions come out), and LeRobot only logs that the "
            "consumed count differs from the delay; "
            + ("a negative delay is clamped to 0 (0.6's `_replace_actions_queue`: the whole new chunk is "
               "queued, so more than `s` of its actions run)" if NEW else
               "a negative delay keeps only the new chunk's last actions (`actions[-1:]`)")
            + "; a float delay raises `TypeError` in the slice. In LeRobot's real-time loop the "
            "delay is measured, so these are late chunks, which the spec leaves to the runtime of chapter R "
            "rather than to the executor."),
    },
    "X-2": {
        "functions": ["execute_chunks"],
        "kind": "no check of the first delay",
        "summary": "a first chunk with a delay drops its first actions",
        "text": (
            "[X-2] makes the first chunk's delay 0. LeRobot's queue takes a delay on the first chunk too: it "
            "drops the chunk's first `d` actions while the robot has nothing to execute, so the first segment "
            "runs `s - d` actions (11 actions for 3 chunks of `s = 4` with delay 1). The spec's rejected "
            "alternative holds a default action instead; LeRobot neither holds nor rejects."),
    },
}

# The implementation's own cases ([TP-8]): a left-over shorter than the guided window.
OWN_CASES = {
    "title": "A left-over shorter than the window ([W-6])",
    "text": (
        "When the queue holds fewer unexecuted actions than `execution_horizon`, the prior exists only for "
        "the left-over's rows. `RTCProcessor.denoise_step` lowers `execution_horizon` to those rows, which "
        "is [W-6]'s default `clip`. "
        + ("LeRobot 0.6's rollout loop (`lerobot/rollout/inference/rtc.py`) pads the left-over with zeros "
           "to `execution_horizon` rows first (`_normalize_prev_actions_length`, for stable compiled "
           "inference), so `denoise_step` never sees it short and window tokens past the left-over are "
           "pulled toward the zero action: [W-6]'s `zeros`, the option the spec keeps for reproducing the "
           "paper's runs and does not choose by default, because it blends toward an action no plan "
           "proposed. The two paths of 0.6.1 disagree with each other: the clip inside `denoise_step` "
           "(\"nothing to merge\" past the left-over, says its comment) is undone by the padding before "
           "it. Not a defect of [W-6], which allows both; spec strictness would be to pad for the compiler "
           "but pass the left-over's length (or clip `execution_horizon` to it) so that the padded rows get "
           "weight 0. Each row runs LeRobot's own code (a zero policy at flow time 0.5, a left-over of rows "
           "1, 2, ..., r, so a guidance target of 0 marks a padded row); the `rollout` rows call 0.6.1's "
           "padding function on the left-over before `denoise_step`."
           if NEW else
           "LeRobot 0.4.4 has no rollout loop in the package; its real-robot example passes "
           "`ActionQueue.get_left_over()` to the policy as it is, so `denoise_step`'s clip is what runs. "
           "Each row runs LeRobot's own code (a zero policy at flow time 0.5, a left-over of rows 1, 2, "
           "..., r).")),
}

# Other public RTC implementations looked for on the package registries reachable here (PyPI, npm,
# Debian), searched by name and description for rtc, real-time chunking, action chunk, inpainting,
# prefix conditioning, openpi and lerobot.
OTHERS = [
    ("openpi (Physical Intelligence; its PyTorch pi0 code runs inference-time RTC in the flipped time of "
     "[V-1])", "not on PyPI; installable from its repository only, so not testable here"),
    ("real-time-chunking-kinetix (the RTC paper's JAX code)",
     "not on PyPI; the project's own JAX twin and [V-4] follow its conventions"),
    ("lerobot 0.4.4 and 0.6.1", "both tested: one report per release (`conformance/thirdparty/lerobot/`), "
     "0.4.4 on Python 3.11 and 0.6.1 (the newest, Python >= 3.12) on Python 3.12 ([TP-7])"),
    ("GR00T N1.7 in lerobot 0.6.1 (`lerobot/policies/groot/`: `rtc_frozen_steps`, a ramp)",
     "a second RTC of LeRobot's, not guidance: its action head (flow time 0 = noise to 1 = data) starts "
     "the overlap's tokens from the previous chunk's actions instead of noise and scales their velocity by "
     "`vel_strength`: 0 on the first `rtc_frozen_steps = min(d, overlap)` tokens, then a ramp "
     "`1 - exp(-rate t)` normalised to 1 (`rtc_ramp_rate`, 6 by default) up to the overlap's end "
     "(inpainting with a frozen prefix, no pull-back). The ramp is built inline in "
     "`GR00TN17ActionHead.get_action_with_features` (`groot_n1_7.py`), between drawing the noise and "
     "running the DiT, and its options in `GrootPolicy._prepare_n1_7_rtc_inputs`, which reads the GR00T "
     "model's config: no function computes them without the GR00T model and its transformers stack, so "
     "there is no second adapter. Its frozen prefix is [X-4]'s committed prefix; its ramp is a velocity "
     "mask, which no interface function of [CF-7] takes"),
    ("flash-rt 0.2.0 (PyPI)",
     "installable (NumPy, PyYAML); its `flash_rt.runtime.rtc.AsyncChunkRunner` switches to a new chunk at the "
     "chunk's first action, with optional blending, which is not the committed prefix of [X-4], and its guided "
     "RTC step is a CUDA-graph plug-in whose denoiser VJP the user supplies: nothing of chapters W, G or X to "
     "call on a CPU, so no adapter"),
    ("lerobot-policy-act-smooth 0.1.0 (PyPI)",
     "an ACT policy conditioned on a prefix of committed actions (training-time prefix conditioning of a "
     "policy that is not a flow model): no weights, corruption, sampler or guidance to map onto the interface"),
    ("luna2 0.1.5 (PyPI)",
     "asynchronous inference for vision-language-action policies that switches chunks after an overlap; "
     "no guidance, prefix weights or committed prefix; it pins lerobot 0.4.1 and robot SDKs"),
    ("npm and Debian", "no RTC implementation found"),
]

"""Firmware channel supervision: plausibility, open circuit, ADC rails, wire break, recovery.

One state machine per sensor channel, shared by the float and fixed-point observers and
mirrored line for line by the generated C (`supervision="branches"`); `channel_rules`
states the same rules branch free, for the generated C's lane-parallel form
(`supervision="lanes"`), and a test checks it against `ChannelMonitor` for every state
and input. At each step, for channel `j`:

1. *readable*: the front end reports no open circuit (and, in float builds, the value is
   not NaN). *plausible*: readable and strictly inside the limits,
   `limits[0] < y < limits[1]`: a reading exactly at a limit (a sensor or ADC stuck at
   its end of scale) is implausible, in every build (float: the values; fixed point: the
   codes, the limits encoded once). *railed*: plausible and at or beyond an ADC rail
   (`y <= rails[j][0]` or `y >= rails[j][1]`).
2. Not plausible: the channel is dropped at once (`healthy = False`) and both counters
   are cleared.
3. Railed: the channel is left out of this step's correction (anti-windup: a clipped
   reading would drag the state toward the rail); counters and health are unchanged.
4. Otherwise the prediction residual `r = y - C x⁻ - D u` is *large* when
   `|r| > residual_threshold[j]`. A large residual increments `bad_run` and clears
   `good_run`; a small one does the opposite. When `bad_run` reaches `wire_break_after`
   (N), the wire-break flag is raised and the channel dropped. A dropped channel comes
   back (`healthy = True`, flag cleared) after `recover_after` (M) consecutive samples
   that are plausible, off the rails and with a small residual.
5. The channel is *in use* when healthy, plausible and not railed. The observer corrects
   with the precomputed gain of exactly the channels in use, without any reset.

Counters saturate at 65535.

Inputs are supervised too (`input_limits`, below): before anything else in a step, input
`j` is *good* when `input_limits[j][0] < u[j] < input_limits[j][1]` (NaN never is); a bad
sample is replaced by the last good value of that input (before the first good one: the
middle of its limits when both are finite, else 0) and its bit is set in the step's
input-fault mask. The observer only ever sees good or held inputs.
"""

from __future__ import annotations

import dataclasses

import numpy as np

COUNTER_MAX = 65535


@dataclasses.dataclass(frozen=True)
class FaultConfig:
    """Channel-supervision settings, in the measurement's physical units (°C, K).

    **Arguments:**

    - `limits`: plausible range `(low, high)`, exclusive, default −55…+125 °C; a reading
      at or outside it drops its channel, a state at or outside it is not healthy.
    - `rails`: per channel `(low, high)` ADC rails, shape `(p, 2)` or one pair for all;
      default none (±inf). A reading at or beyond a rail gets no correction.
    - `residual_threshold`: per channel `|r|` limit for the wire-break test (K), default
      inf (off).
    - `wire_break_after`: N, consecutive large residuals that raise the wire-break flag.
    - `recover_after`: M, consecutive good samples that bring a dropped channel back.
    - `input_limits`: per input `(low, high)` plausible range of `u` (exclusive), shape
      `(m, 2)` or one pair for all, in the inputs' units (°C, W); default
      `default_input_limits`: `±(limits[1] - limits[0]) / g_j`, where `g_j` is the largest
      steady-state gain from input `j` to an output (the input that, held alone, would move
      a sensor across the whole plausible span), ±inf for an input without effect.
    """

    limits: tuple[float, float] = (-55.0, 125.0)
    rails: object = None
    residual_threshold: object = None
    wire_break_after: int = 10
    recover_after: int = 20
    gate: bool = False
    input_limits: object = None

    def __post_init__(self):
        if not self.limits[0] < self.limits[1]:
            raise ValueError(f"`FaultConfig(limits={self.limits})`: need low < high.")
        for name in ("wire_break_after", "recover_after"):
            v = getattr(self, name)
            if not 1 <= int(v) <= COUNTER_MAX:
                raise ValueError(f"`FaultConfig({name}={v})`: expected 1..{COUNTER_MAX}.")

    def rails_array(self, p: int) -> np.ndarray:
        if self.rails is None:
            return np.tile([-np.inf, np.inf], (p, 1))
        r = np.asarray(self.rails, dtype=np.float64)
        r = np.tile(r, (p, 1)) if r.shape == (2,) else r
        if r.shape != (p, 2):
            raise ValueError(f"`FaultConfig(rails=...)` has shape {r.shape}; expected (2,) or "
                             f"({p}, 2).")
        return r

    def threshold_array(self, p: int) -> np.ndarray:
        if self.residual_threshold is None:
            return np.full(p, np.inf)
        t = np.broadcast_to(np.asarray(self.residual_threshold, dtype=np.float64), (p,))
        if np.any(t <= 0):
            raise ValueError("`FaultConfig(residual_threshold=...)` must be positive.")
        return t.copy()

    def input_limits_array(self, system) -> np.ndarray:
        """`(m, 2)` input limits for `system` (an `ObserverSystem`): `input_limits`, or
        `default_input_limits` when None."""
        m = system.n_inputs
        if self.input_limits is None:
            return default_input_limits(system, self.limits)
        r = np.asarray(self.input_limits, dtype=np.float64)
        r = np.tile(r, (m, 1)) if r.shape == (2,) else r.reshape(-1, 2) if r.size == 0 else r
        if r.shape != (m, 2) or np.any(np.isnan(r)) or np.any(r[:, 0] >= r[:, 1]):
            raise ValueError(f"`FaultConfig(input_limits=...)` has shape {r.shape}; expected "
                             f"(2,) or ({m}, 2) pairs with low < high.")
        return r


def default_input_limits(system, limits) -> np.ndarray:
    """`(m, 2)` default input limits: `±(limits[1] - limits[0]) / g_j` with
    `g_j = max_i |G[i, j]|`, `G = C (I - Phi)⁺ (B0 + B1) + D` the steady-state gain from
    the inputs to the outputs (K per input unit); `⁺` the pseudo-inverse with singular
    values below `1e-10` of the largest dropped (an integrating state, such as a held
    one, adds no gain); ±inf where `g_j = 0`."""
    n, m = system.n_states, system.n_inputs
    G = system.C @ np.linalg.pinv(np.eye(n) - system.Phi, rcond=1e-10) @ \
        (system.B0 + system.B1) + system.D
    g = np.abs(G).max(axis=0) if G.size else np.zeros(m)
    with np.errstate(divide="ignore"):
        half = np.where(np.isfinite(g) & (g > 0), (limits[1] - limits[0]) / g, np.inf)
    return np.stack([-half, half], axis=1)


def initial_inputs(input_limits) -> np.ndarray:
    """`(m,)` values held before the first good sample of each input: the middle of its
    limits when both are finite, else 0."""
    lo, hi = input_limits[:, 0], input_limits[:, 1]
    finite = np.isfinite(lo) & np.isfinite(hi)
    mid = np.where(finite, lo, 0.0) / 2 + np.where(finite, hi, 0.0) / 2
    return np.where(finite, mid, 0.0)


def hold_inputs(u, held, limits):
    """Input supervision of one step: `(u_used, fault_mask)`. Input `j` is used when
    `limits[j, 0] < u[j] < limits[j, 1]` (NaN never is), else `held[j]` (its last good
    value) is used and bit `j` of `fault_mask` is set. Works on floats and integer codes."""
    good = (limits[:, 0] < u) & (u < limits[:, 1])
    mask = sum(1 << j for j in range(len(u)) if not good[j])
    return np.where(good, u, held).astype(u.dtype), mask


def state_in_range(x, limits) -> bool:
    """Whether every state is strictly inside its `(low, high)` row of `limits (n, 2)`
    (False for NaN): the state part of "healthy"."""
    return bool(np.all((limits[:, 0] < x) & (x < limits[:, 1])))


class ChannelMonitor:
    """The per-channel state machine of `FaultConfig` (counters and flags, plain ints);
    with `gate`, a sample with a large residual is left out of the correction."""

    def __init__(self, p: int, wire_break_after: int, recover_after: int, gate: bool = False):
        self.p, self.N, self.M = p, int(wire_break_after), int(recover_after)
        self.gate = bool(gate)
        self.reset()

    def reset(self):
        self.healthy = [True] * self.p
        self.wire_break = [False] * self.p
        self.good_run = [0] * self.p
        self.bad_run = [0] * self.p

    def update(self, plausible, railed, large, started: bool = True) -> int:
        """Advance one step; return the bit mask of channels in use. `started`: false at
        the first step after a reset, which is never gated (its state is a guess)."""
        mask = 0
        for j in range(self.p):
            if not plausible[j]:
                self.healthy[j] = False
                self.good_run[j] = 0
                self.bad_run[j] = 0
                continue
            if railed[j]:
                continue
            if large[j]:
                self.bad_run[j] = min(self.bad_run[j] + 1, COUNTER_MAX)
                self.good_run[j] = 0
                if self.bad_run[j] >= self.N:
                    self.wire_break[j] = True
                    self.healthy[j] = False
            else:
                self.good_run[j] = min(self.good_run[j] + 1, COUNTER_MAX)
                self.bad_run[j] = 0
                if not self.healthy[j] and self.good_run[j] >= self.M:
                    self.healthy[j] = True
                    self.wire_break[j] = False
            if self.healthy[j] and not (self.gate and started and large[j]):
                mask |= 1 << j
        return mask

    def flags(self) -> tuple[int, int]:
        """`(healthy_mask, wire_break_mask)` as bit masks."""
        h = sum(1 << j for j in range(self.p) if self.healthy[j])
        w = sum(1 << j for j in range(self.p) if self.wire_break[j])
        return h, w


class _Lane:
    """One per-channel quantity of the supervision as an expression: its C text for the
    lane-parallel form (`layout="columns"`) and a Python function of the channel's
    variables, so that one description of the rules (`channel_rules`) gives the C and
    can be checked against `ChannelMonitor` (a test does it for every state and input).
    A flag is a lane mask in C (all ones or zero) and a bool in Python; a counter is an
    integer. `const` is the value when known at generation time (folded away)."""

    def __init__(self, c, f, const=None, flag=True):
        self.c, self.f, self.const, self.flag = c, f, const, flag

    @staticmethod
    def known(v, flag=True):
        return _Lane(("-1" if v else "0") if flag else str(int(v)), lambda env: v, v, flag)

    def __and__(self, o):
        if self.const is not None:
            return o if self.const else self
        if o.const is not None:
            return self if o.const else o
        return _Lane(f"({self.c} & {o.c})", lambda env: self.f(env) and o.f(env))

    def __or__(self, o):
        if self.const is not None:
            return self if self.const else o
        if o.const is not None:
            return o if o.const else self
        return _Lane(f"({self.c} | {o.c})", lambda env: self.f(env) or o.f(env))

    def __invert__(self):
        if self.const is not None:
            return _Lane.known(not self.const)
        return _Lane(f"~{self.c}", lambda env: not self.f(env))


def _var(name, c=None, flag=True):
    """The variable `name` (`env[name]` in Python), C text `c` (default: the name)."""
    return _Lane(name if c is None else c, lambda env: env[name], None, flag)


def _select(c, a, b):
    """`c ? a : b` for counters (`c & a` or `~c & b` when the other is a known 0)."""
    if c.const is not None:
        return a if c.const else b
    if a.const is not None and a.const == b.const:
        return a
    if getattr(b, "cond", None) is not None and b.cond[0].c == c.c:
        b = b.cond[2]                                   # c ? a : (c ? x : y) = c ? a : y
    if b.const == 0:
        out = _Lane(f"({c.c} & {a.c})", lambda env: a.f(env) if c.f(env) else 0, None, False)
    elif a.const == 0:
        out = _Lane(f"(~{c.c} & {b.c})", lambda env: 0 if c.f(env) else b.f(env), None, False)
    else:
        out = _Lane(f"({c.c} ? {a.c} : {b.c})", lambda env: a.f(env) if c.f(env) else b.f(env),
                    None, False)
    out.cond = (c, a, b)
    return out


def _increment(x, cap, cap_c=None):
    """`min(x + 1, cap)`; `cap_c`: the C text of `cap` (default the number)."""
    if x.const is not None:
        return _Lane.known(min(x.const + 1, cap), False)
    cap_c = str(cap) if cap_c is None else cap_c
    return _Lane(f"({x.c} - ({x.c} < {cap_c} ? -1 : 0))", lambda env: min(x.f(env) + 1, cap),
                 None, False)


def _at_least(x, k, below_c=None):
    """`x >= k` for a counter, as a flag, written `x > k - 1`; `below_c`: the C text of
    `k - 1` (default the number)."""
    if x.const is not None:
        return _Lane.known(x.const >= k)
    below_c = str(k - 1) if below_c is None else below_c
    return _Lane(f"({x.c} > {below_c} ? -1 : 0)", lambda env: x.f(env) >= k)


def channel_rules(v, N, M, bind, const_c=None, gate=False):
    """The rules of `FaultConfig` (`ChannelMonitor.update`) for one channel, branch free,
    as `_Lane` expressions: from the state `v["healthy"], v["wire_break"], v["good"],
    v["bad"]` and the step's `v["plausible"], v["railed"], v["large"]`, the new state
    and `in_use` (a dict). `bind(name, expr)` names an intermediate result (a C local)
    and returns it as a variable; `const_c` may give the C text of `COUNTER_MAX`, `N - 1`
    and `M - 1` (keys `"max"`, `"N-1"`, `"M-1"`). With `gate`, a large residual keeps
    the sample out of the correction (`in_use` false) once started (`v["started"]`, a
    flag: not at the first step after a reset)."""
    k = const_c or {}
    zero = _Lane.known(0, False)
    act = bind("act", v["plausible"] & ~v["railed"])   # neither dropped nor at a rail
    # a large residual counts bad samples, a small one good samples (saturating); an
    # implausible reading clears both, a railed one leaves them
    good = bind("gn", _select(act, _select(v["large"], zero,
                                           _increment(v["good"], COUNTER_MAX, k.get("max"))),
                              _select(v["plausible"], v["good"], zero)))
    bad = bind("bn", _select(act, _select(v["large"],
                                          _increment(v["bad"], COUNTER_MAX, k.get("max")), zero),
                             _select(v["plausible"], v["bad"], zero)))
    # N large residuals in a row: wire break, flag up and channel dropped
    broken = bind("brk", act & v["large"] & _at_least(bad, N, k.get("N-1")))
    # M good samples in a row bring a dropped channel back, flag down
    back = bind("rec", act & ~v["large"] & ~v["healthy"] & _at_least(good, M, k.get("M-1")))
    healthy = bind("hn", (v["healthy"] & v["plausible"] & ~broken) | back)
    # in use: act & healthy, which is healthy where act is plausible (no rails)
    in_use = healthy if act.c == v["plausible"].c else act & healthy
    if gate:
        in_use = in_use & ~(v["large"] & v["started"])
    wire_break = bind("wn", (v["wire_break"] & ~back) | broken)
    return {"healthy": healthy, "wire_break": wire_break, "good": good, "bad": bad,
            "in_use": in_use}

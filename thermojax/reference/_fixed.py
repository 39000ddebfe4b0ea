"""The fixed-point observer (Q16.16, Q8.24, Q15, Q31): int64 accumulation, rounding, saturation.

Representation (stated once, used by NumPy and the generated C alike):

- A state, a measurement or a temperature input is stored as its offset from a reference
  (default 35 °C, the middle of −55…+125 °C, so every state lies within ±90 K), divided by
  the format's `state_scale` (1 K for Q16.16 and Q8.24, 128 K for Q15 and Q31), as a code with
  `frac_bits` fractional bits. Q16.16 then holds ±32768 K, Q8.24, Q15 and Q31 ±128 K: −93…+163 °C.
- A non-temperature input (a power) has its own offset and scale (`FixedScaling`).
- Coefficients are the matrices in these scaled units (`B` and `D` times
  `input_scale / state_scale`), quantized once, in the data word (int32, or int16 for Q15)
  with the format's fractional bits. A matrix whose largest entry does not fit gets `h`
  fewer fractional bits (a per-matrix right shift), the smallest `h` that fits. Where a
  sum could still overflow int64 with every operand at its word limit (Q31: 32-bit codes
  with 31 fractional bits), every matrix of that sum gets one bit fewer at a time until
  it cannot (imu6 in Q31: Phi, B and C at 30 bits, L at 31).
- Products are summed exactly in int64; terms of matrices with different fractional bits
  are aligned by left shifts; each sum is rounded once to the data format (nearest, ties
  toward +inf) and saturated to the data word. Overflow of int64 is thereby excluded at
  construction.

Step (integer codes throughout):

    x⁻ = sat(rnd(Phi x << a0 + B0 u[k-1] << a1 + B1 u[k] << a2, F_pred))
    r  = sat(y - rnd(C x⁻ << c0 + D u[k] << c1, F_out))
    x  = sat(x⁻ + rnd(sum_{j in use} L[:, j] r[j], f_L))

Untrusted samples (`_faults.py`): an input code not strictly inside the encoded
`FaultConfig.input_limits` is replaced by the input's last good code before the step (a
code at the word's minimum or maximum never passes: NaN encodes to the minimum, a
saturated encoding to an end of the word); a measurement code is plausible strictly
inside the encoded `limits`. Saturation of a state (the prediction or the correction
clamped to the word) is counted per step in `saturations` (steps with any clamp, up to
65535); `state_ok` is True when no state saturated in the step and every state code is
strictly inside the limits encoded around its own reference.

Bias channels (optional, `biases=`): after the correction, `FixedBiasEvaluator` (in
`_bias.py`, where its formats and scaling rule are stated) evaluates every channel from the
corrected state codes and the input codes: polynomial by Horner, gradients, exact rate
rows, viscoelastic strain states; each channel an int32 code with its own fractional bits.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ._bias import FixedBiasEvaluator
from ._faults import (ChannelMonitor, FaultConfig, hold_inputs, initial_inputs,
                      state_in_range)
from ._formats import FixedFormat, decode, encode, fixed_format, round_shift, saturate
from ._run import ObserverRun, play
from ._system import ObserverSystem

_ACC_LIMIT = 1 << 62
# The int64 sums of a step, each rounded once: the prediction, the output, the correction.
_SUMS = (("Phi", "B0", "B1"), ("C", "D"), ("L",))


@dataclasses.dataclass(frozen=True)
class FixedScaling:
    """Offsets and scales of the fixed-point representation.

    **Arguments:**

    - `state_offset`: reference temperature of the states (°C), scalar or `(n,)`;
      default 35 °C.
    - `output_offset`: reference of the measurements (°C), scalar or `(p,)`; default 35 °C.
    - `input_offset`: `(m,)` reference of each input (35 for a temperature input, 0 for a
      power); default 0.
    - `input_scale`: `(m,)` physical size of one format unit of each input (default: the
      format's `state_scale` for every input; a power in watts usually wants 1).

    The offsets must be an equilibrium of the observer (`Phi x_ref + (B0 + B1) u_ref =
    x_ref`, `C x_ref + D u_ref = y_ref`), true for a thermal network with every
    temperature at the reference and no heating, so that the offset form needs no
    constant term.
    """

    state_offset: object = 35.0
    output_offset: object = 35.0
    input_offset: object = None
    input_scale: object = None


def _quantize(M: np.ndarray, frac: int, fmt: FixedFormat, name: str):
    """Integer coefficients of `M` with the largest fraction `<= frac` that fits the word."""
    for h in range(0, frac + 1):
        q = np.floor(M * 2.0 ** (frac - h) + 0.5)
        if q.size == 0 or (q.min() >= fmt.word_min and q.max() <= fmt.word_max):
            return q.astype(np.int64), frac - h
    raise ValueError(f"`FixedObserver`: coefficient matrix `{name}` (largest entry "
                     f"{np.abs(M).max():.3g} in scaled units) does not fit format "
                     f"{fmt.name} even with no fractional bits; scale the inputs "
                     f"(`FixedScaling(input_scale=...)`).")


class FixedObserver:
    """The observer of `ObserverSystem` in a fixed-point format, bit-exact and deterministic.

    **Arguments:**

    - `system`: an `ObserverSystem` (float64 matrices, physical units).
    - `fmt`: `"q16.16"`, `"q8.24"`, `"q15"`, `"q31"` or a `FixedFormat`.
    - `scaling`: a `FixedScaling` (offsets and input scales).
    - `faults`: a `FaultConfig` (limits, rails and thresholds are encoded once).
    - `biases`: an optional float `BiasEvaluator`: its channels are evaluated in fixed point
      (`FixedBiasEvaluator`, scaled from `faults.limits`) after each step from the
      corrected state codes and the input codes; `self.bias (q,)` holds the int32 codes,
      `run` records them (`ObserverRun.bias`, int64), `decode_bias` converts them and
      `run_physical` returns them decoded.

    After construction: `coef[name]` (int64 codes), `coef_frac[name]` (fractional bits),
    `coef_error[name]` (quantized minus exact, physical units) for
    `name in ("Phi", "B0", "B1", "C", "D", "L")`; `L` is the whole gain table
    `(2**p, n, p)`.
    """

    MATRICES = ("Phi", "B0", "B1", "C", "D", "L")

    def __init__(self, system: ObserverSystem, fmt: FixedFormat | str = "q16.16",
                 scaling: FixedScaling | None = None, faults: FaultConfig | None = None,
                 biases=None):
        self.system, self.fmt = system, fixed_format(fmt)
        self.scaling = FixedScaling() if scaling is None else scaling
        self.faults = FaultConfig() if faults is None else faults
        n, m, p, f, F = (system.n_states, system.n_inputs, system.n_outputs,
                         self.fmt.frac_bits, self.fmt)
        sc = self.scaling
        self.x_ref = np.broadcast_to(np.asarray(sc.state_offset, float), (n,)).copy()
        self.y_ref = np.broadcast_to(np.asarray(sc.output_offset, float), (p,)).copy()
        self.u_ref = np.zeros(m) if sc.input_offset is None else \
            np.broadcast_to(np.asarray(sc.input_offset, float), (m,)).copy()
        self.u_scale = np.full(m, F.state_scale) if sc.input_scale is None else \
            np.broadcast_to(np.asarray(sc.input_scale, float), (m,)).copy()
        if np.any(self.u_scale <= 0):
            raise ValueError("`FixedScaling(input_scale=...)` must be positive.")
        eq = system.Phi @ self.x_ref + (system.B0 + system.B1) @ self.u_ref - self.x_ref
        out = system.C @ self.x_ref + system.D @ self.u_ref - self.y_ref
        tol = 1e-9 * (1 + np.abs(self.x_ref).max() + np.abs(self.u_ref).max(initial=0.0))
        if np.abs(eq).max() > tol or np.abs(out).max() > tol:
            raise ValueError(f"`FixedObserver(scaling=...)`: the offsets are not an "
                             f"equilibrium (Phi x_ref + (B0+B1) u_ref - x_ref up to "
                             f"{np.abs(eq).max():.3g}, C x_ref + D u_ref - y_ref up to "
                             f"{np.abs(out).max():.3g}). Give the temperature inputs the "
                             f"reference temperature as offset and the powers 0.")
        lo, hi = F.state_range
        need = (self.faults.limits[0] - self.y_ref.max(), self.faults.limits[1] - self.y_ref.min())
        if need[0] < lo or need[1] > hi:
            raise ValueError(f"`FixedObserver(fmt={F.name!r})`: the format holds offsets "
                             f"{lo:.4g}…{hi:.4g} K, which cannot hold the limits "
                             f"{self.faults.limits} °C around {self.y_ref.tolist()} °C; raise "
                             f"`FixedFormat.state_scale` or pick Q16.16.")
        s = F.state_scale
        scaled = {"Phi": system.Phi, "B0": system.B0 * self.u_scale / s,
                  "B1": system.B1 * self.u_scale / s, "C": system.C,
                  "D": system.D * self.u_scale / s, "L": system.gain_table}
        unscale = {"Phi": 1.0, "B0": s / self.u_scale, "B1": s / self.u_scale, "C": 1.0,
                   "D": s / self.u_scale, "L": 1.0}
        self.coef, self.coef_frac, self.coef_error = {}, {}, {}
        for names in _SUMS:
            self._quantize_sum(names, scaled, unscale)
        cf = self.coef_frac
        self.f_pred = max(cf["Phi"], cf["B0"], cf["B1"])
        self.f_out = max(cf["C"], cf["D"])
        self.f_gain = cf["L"]
        self.shift = {"Phi": self.f_pred - cf["Phi"], "B0": self.f_pred - cf["B0"],
                      "B1": self.f_pred - cf["B1"], "C": self.f_out - cf["C"],
                      "D": self.f_out - cf["D"]}
        # channel supervision, encoded once
        self.limit_codes = np.stack([encode(self.faults.limits[0], f, F, self.y_ref, s),
                                     encode(self.faults.limits[1], f, F, self.y_ref, s)], 1)
        rails = self.faults.rails_array(p)
        self.rail_codes = np.stack([encode(rails[:, 0], f, F, self.y_ref, s),
                                    encode(rails[:, 1], f, F, self.y_ref, s)], 1)
        thr = self.faults.threshold_array(p)
        with np.errstate(over="ignore", invalid="ignore"):
            t = np.floor(thr / s * 2.0 ** f + 0.5)
        self.threshold_codes = np.where(np.isfinite(t) & (t < _ACC_LIMIT), t,
                                        _ACC_LIMIT).astype(np.int64)
        ulim = self.faults.input_limits_array(system)
        self.input_limit_codes = np.stack([self.encode_inputs(ulim[:, 0]),
                                           self.encode_inputs(ulim[:, 1])], 1)
        self.u_start = self.encode_inputs(initial_inputs(ulim))
        self.state_limit_codes = np.stack(
            [encode(self.faults.limits[0], f, F, self.x_ref, s),
             encode(self.faults.limits[1], f, F, self.x_ref, s)], 1)
        self.monitor = ChannelMonitor(p, self.faults.wire_break_after, self.faults.recover_after,
                                      self.faults.gate)
        self.x = np.zeros(n, np.int64)
        self.u_prev = self.u_start.copy()
        self.started = False
        self.input_fault, self.state_ok, self.saturations = 0, True, 0
        self.bias = None
        self.biases = None if biases is None else FixedBiasEvaluator(
            biases, F, self.x_ref, self.u_ref, self.u_scale, self.faults.limits)

    # -- the representation -------------------------------------------------------------
    def _quantize_sum(self, names, scaled, unscale):
        """Quantize the matrices of one int64 sum (`_SUMS`): each with the format's
        fractional bits, fewer where its largest entry does not fit the word, and all of
        them fewer by one more bit at a time while the sum could overflow int64 with every
        operand at its word limit (Q31's 32-bit coefficient and data codes: their products
        reach 2**62)."""
        exact = {"Phi": self.system.Phi, "B0": self.system.B0, "B1": self.system.B1,
                 "C": self.system.C, "D": self.system.D, "L": self.system.gain_table}
        f = self.fmt.frac_bits
        for headroom in range(f + 1):
            quantized = {name: _quantize(scaled[name], f - headroom, self.fmt, name)
                         for name in names}
            top = max(fr for _, fr in quantized.values())
            worst = sum(np.abs(q).sum(axis=-1) * 2.0 ** (top - fr)
                        for q, fr in quantized.values()) * float(-self.fmt.word_min)
            if np.max(worst, initial=0.0) < _ACC_LIMIT:
                break
        else:
            raise ValueError(f"`FixedObserver(fmt={self.fmt.name!r})`: the sum of "
                             f"{'/'.join(names)} could overflow an int64 accumulator even "
                             f"with no fractional bits; scale the inputs "
                             f"(`FixedScaling(input_scale=...)`).")
        for name, (q, fr) in quantized.items():
            self.coef[name], self.coef_frac[name] = q, fr
            self.coef_error[name] = q * 2.0 ** -fr * unscale[name] - exact[name]

    @property
    def lsb(self) -> float:
        return self.fmt.lsb

    def encode_states(self, x):
        return encode(x, self.fmt.frac_bits, self.fmt, self.x_ref, self.fmt.state_scale)

    def decode_states(self, codes):
        return decode(codes, self.fmt.frac_bits, self.x_ref, self.fmt.state_scale)

    def encode_inputs(self, u):
        return encode(u, self.fmt.frac_bits, self.fmt, self.u_ref, self.u_scale)

    def decode_inputs(self, codes):
        return decode(codes, self.fmt.frac_bits, self.u_ref, self.u_scale)

    def encode_outputs(self, y):
        return encode(y, self.fmt.frac_bits, self.fmt, self.y_ref, self.fmt.state_scale)

    def decode_outputs(self, codes):
        return decode(codes, self.fmt.frac_bits, self.y_ref, self.fmt.state_scale)

    def decode_residuals(self, codes):
        return decode(codes, self.fmt.frac_bits, 0.0, self.fmt.state_scale)

    def decode_bias(self, codes):
        """Bias codes `(..., q)` to the channels' units (`code * 2**-g_c`)."""
        return self.biases.decode(codes)

    # -- the step -------------------------------------------------------------------------
    def reset(self, x0_codes) -> None:
        """Start over from state codes `x0 (n,)`; the next step corrects `x⁻[0] = x0`."""
        self.x = saturate(np.asarray(x0_codes, np.int64).reshape(self.system.n_states), self.fmt)
        self.started = False
        self.u_prev = self.u_start.copy()       # held before the first good sample
        self.input_fault, self.saturations = 0, 0
        self.state_ok = state_in_range(self.x, self.state_limit_codes)
        self.monitor.reset()
        if self.biases is not None:
            self.biases.reset()

    def step(self, u, y, open_circuit=None):
        """One step on codes `u (m,)`, `y (p,)`; returns `(x, r, in_use_mask)` as codes."""
        c, sh, F = self.coef, self.shift, self.fmt
        u, self.input_fault = hold_inputs(saturate(u, F), self.u_prev, self.input_limit_codes)
        y = saturate(y, F)
        p = self.system.n_outputs
        clamped = False
        if self.started:
            acc = ((c["Phi"] @ self.x) << sh["Phi"]) + ((c["B0"] @ self.u_prev) << sh["B0"]) \
                + ((c["B1"] @ u) << sh["B1"])
            acc = round_shift(acc, self.f_pred)
            xm = saturate(acc, F)
            clamped = bool(np.any(xm != acc))
        else:
            xm = self.x
        pred = round_shift(((c["C"] @ xm) << sh["C"]) + ((c["D"] @ u) << sh["D"]), self.f_out)
        r = saturate(y - pred, F)
        oc = np.zeros(p, bool) if open_circuit is None else np.asarray(open_circuit, bool)
        lim, rail, thr = self.limit_codes, self.rail_codes, self.threshold_codes
        plausible = [bool(not oc[j] and lim[j, 0] < y[j] < lim[j, 1]) for j in range(p)]
        railed = [plausible[j] and bool(y[j] <= rail[j, 0] or y[j] >= rail[j, 1])
                  for j in range(p)]
        large = [plausible[j] and bool(r[j] > thr[j] or r[j] < -thr[j]) for j in range(p)]
        mask = self.monitor.update(plausible, railed, large, self.started)
        if mask:
            use = np.array([mask >> j & 1 for j in range(p)], np.int64)
            acc = xm + round_shift(c["L"][mask] @ (r * use), self.f_gain)
            xm = saturate(acc, F)
            clamped = clamped or bool(np.any(xm != acc))
        self.x, self.u_prev, self.started = xm, u, True
        self.saturations = min(self.saturations + clamped, 65535)
        self.state_ok = not clamped and state_in_range(xm, self.state_limit_codes)
        if self.biases is not None:
            self.bias = self.biases.step(xm, u)
        return xm, r, mask

    def run(self, x0_codes, u_codes, y_codes, open_circuit=None) -> ObserverRun:
        """Play back input and measurement codes `(T, m)`, `(T, p)` from state codes `x0`."""
        run = play(self, "FixedObserver", x0_codes, u_codes, y_codes, open_circuit, np.int64)
        if run.bias is not None:
            run = dataclasses.replace(run, bias=run.bias.astype(np.int64))
        return run

    def run_physical(self, x0, u, y, open_circuit=None) -> ObserverRun:
        """`run` on physical values: encodes `x0`, `u`, `y` (NaN readings count as open
        circuit), returns the run with `states` and `residuals` decoded to °C and K."""
        y = np.asarray(y, float)
        oc = np.isnan(y) if open_circuit is None else (np.asarray(open_circuit, bool) | np.isnan(y))
        run = self.run(self.encode_states(x0), self.encode_inputs(u), self.encode_outputs(y), oc)
        return dataclasses.replace(run, states=self.decode_states(run.states),
                                   residuals=self.decode_residuals(run.residuals),
                                   bias=None if run.bias is None else self.decode_bias(run.bias))

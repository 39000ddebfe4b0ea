"""Multi-rate execution: the thermal step at 10…50 Hz, bias corrections at 1…4 kHz.

The thermal task computes the bias correction after each observer step — the artifact's
bias channels (`BiasEvaluator`: polynomial, gradients, exact rates, strain states; the
same `_bias` code as the reference observer's `ObserverRun.bias`) or the older linear
form `b[k] = b0 + K x[k]` — and publishes it through a `DoubleBuffer`: it writes the slot the reader is not
using, then flips the index and bumps a sequence number (on a microcontroller, a single
word store, so the reader never sees a half-written vector). The inertial task reads the
published slot at every high-rate tick. When it sees a new sequence number it starts a
linear ramp from the value it is *currently outputting* to the new target, over
`ratio = f_inertial / f_thermal` ticks, then holds the target. Starting from the current
output (not from the previous target) keeps the output continuous even when a
publication comes early or late; with regular publications each ramp ends exactly where
the next starts, and the largest tick-to-tick change is `max_k |b[k] - b[k-1]| / ratio`.

A fixed-point observer (`FixedObserver` with bias channels) publishes int32 bias codes and
the ramp stays in integers: `out = start + ⌊(2 (target − start) i + R) / 2R⌋` (the nearest
code to `start + (target − start) i / R`, ties toward +inf; exact in int64), so the C
(`generate_multirate_c(..., word="int32_t")`) repeats it bit for bit without a float unit.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ._bias import BiasEvaluator, FixedBiasEvaluator
from ._formats import saturate


class DoubleBuffer:
    """Two slots, an index of the published one and a sequence number."""

    def __init__(self, size: int, dtype=np.float64):
        self.slots = [np.zeros(size, dtype), np.zeros(size, dtype)]
        self.published = 0
        self.sequence = 0

    def publish(self, values) -> None:
        back = 1 - self.published
        self.slots[back][:] = values      # write the slot nobody reads
        self.published = back             # then flip (one word store)
        self.sequence += 1

    def read(self) -> tuple[int, np.ndarray]:
        return self.sequence, self.slots[self.published].copy()


class BiasInterpolator:
    """The inertial task's reader: linear ramps between published bias vectors, in double
    or (`codes=True`) on integer bias codes."""

    def __init__(self, size: int, ratio: int, initial=None, codes: bool = False):
        if int(ratio) < 1:
            raise ValueError(f"`BiasInterpolator(ratio={ratio})`: need ratio >= 1.")
        self.ratio, self.codes = int(ratio), bool(codes)
        dtype = np.int64 if codes else np.float64
        self.output = np.zeros(size, dtype) if initial is None else np.array(initial, dtype)
        self.start = self.output.copy()
        self.target = self.output.copy()
        self.tick_in_ramp = self.ratio
        self.seen = 0
        self.held = 0  # non-finite bias values held at the last target so far

    def tick(self, buffer: DoubleBuffer) -> np.ndarray:
        seq, values = buffer.read()
        if seq != self.seen:
            if not self.codes:  # a non-finite bias never enters the ramp: the last target
                bad = ~np.isfinite(values)
                self.held += int(np.count_nonzero(bad))
                values = np.where(bad, self.target, values)
            self.seen, self.start, self.target, self.tick_in_ramp = seq, self.output, values, 0
        if self.tick_in_ramp < self.ratio:
            self.tick_in_ramp += 1
            if self.tick_in_ramp == self.ratio:
                self.output = self.target.copy()
            elif self.codes:   # the nearest code, ties toward +inf: floor division
                step = 2 * (self.target - self.start) * self.tick_in_ramp + self.ratio
                self.output = self.start + step // (2 * self.ratio)
            else:
                self.output = self.start + (self.target - self.start) * (self.tick_in_ramp
                                                                          / self.ratio)
        return self.output


@dataclasses.dataclass(frozen=True, eq=False)
class MultiRateRun:
    """`bias (T, q)` at the thermal rate, `inertial (T * ratio, q)` at the inertial rate,
    `published_at (T,)` the inertial tick of each publication."""

    bias: np.ndarray
    inertial: np.ndarray
    published_at: np.ndarray


def run_multirate(observer, x0, u, y, bias_matrix=None, bias_offset=None, ratio: int = 100,
                  open_circuit=None, delay_ticks=None) -> MultiRateRun:
    """Run `observer` (a `FloatObserver`, or a `FixedObserver` with bias channels) at the
    thermal rate and interpolate its bias corrections to the inertial rate.

    **Arguments:**

    - `observer`, `x0`, `u (T, m)`, `y (T, p)`, `open_circuit`: as `observer.run` (codes
      for a `FixedObserver`, whose int32 bias codes are then ramped in integers: `bias`
      and `inertial` are int64 codes, `observer.decode_bias` converts them).
    - `bias_matrix`: a `BiasEvaluator` (e.g. `load_observer(DIR).bias_evaluator()`): the
      bias channels evaluated at the thermal rate from the corrected estimates `x[k]` and
      `u[k]` (strain states from rest at `x[0]`); or `None`: the observer's own
      `biases` (an artifact's `float_observer()`); or the linear form, a matrix
      `(q, n)` with `bias_offset (q,)`: `b = bias_offset + bias_matrix @ x`.
    - `ratio`: inertial ticks per thermal step (2000 Hz / 20 Hz = 100).
    - `delay_ticks (T,)`: ticks after the start of its period at which step `k`'s result
      is published (the thermal task's run time, with jitter); default 0.

    The interpolator starts at the bias of `x0` (for bias channels: `x0` and `u[0]`, strain
    states at rest).
    """
    if isinstance(getattr(observer, "biases", None), FixedBiasEvaluator):
        if bias_matrix is not None or bias_offset is not None:
            raise ValueError("`run_multirate`: a fixed-point observer ramps its own bias "
                             "channels' codes; pass no bias_matrix or bias_offset.")
        run = observer.run(x0, u, y, open_circuit)
        ev = observer.biases
        ev.reset()
        initial = ev.step(saturate(np.asarray(x0, np.int64), observer.fmt),
                          saturate(np.asarray(u, np.int64)[0], observer.fmt))
        ev.reset()
        return _ramped(run.bias, initial, ratio, delay_ticks, codes=True)
    if bias_matrix is None:
        bias_matrix = getattr(observer, "biases", None)
        if not isinstance(bias_matrix, BiasEvaluator):
            raise ValueError("`run_multirate`: no bias given and the observer has no bias "
                             "channels; pass a `BiasEvaluator` or a bias matrix.")
    run = observer.run(x0, u, y, open_circuit)
    if isinstance(bias_matrix, BiasEvaluator):
        if bias_offset is not None:
            raise ValueError("`run_multirate(bias_offset=...)` goes with a bias matrix, not "
                             "with bias channels (their constant is their polynomial's).")
        ev = bias_matrix
        u_f = np.asarray(u, float)
        ev.reset()
        initial = ev.step(np.asarray(x0, float), u_f[0])
        bias = (np.asarray(run.bias, float) if run.bias is not None
                and getattr(observer, "biases", None) is ev else
                ev.run(np.asarray(run.states, float), u_f))
        ev.reset()
    else:
        K = np.atleast_2d(np.asarray(bias_matrix, float))
        b0 = np.zeros(K.shape[0]) if bias_offset is None else np.asarray(bias_offset, float)
        bias = b0 + np.asarray(run.states, float) @ K.T
        initial = b0 + K @ np.asarray(x0, float)
    return _ramped(bias, initial, ratio, delay_ticks, codes=False)


def _ramped(bias, initial, ratio: int, delay_ticks, codes: bool) -> MultiRateRun:
    """Publish `bias (T, q)` through a `DoubleBuffer` at its ticks and ramp to each."""
    T, q = bias.shape
    delay = np.zeros(T, int) if delay_ticks is None else np.asarray(delay_ticks, int)
    if np.any(delay < 0) or np.any(delay >= ratio):
        raise ValueError(f"`run_multirate(delay_ticks=...)` must lie in 0..{ratio - 1}.")
    at = np.arange(T) * ratio + delay
    dtype = np.int64 if codes else np.float64
    buf = DoubleBuffer(q, dtype)
    reader = BiasInterpolator(q, ratio, initial=initial, codes=codes)
    out = np.empty((T * ratio, q), dtype)
    k = 0
    for t in range(T * ratio):
        while k < T and at[k] == t:
            buf.publish(bias[k])
            k += 1
        out[t] = reader.tick(buf)
    return MultiRateRun(bias, out, at)

"""Firmware channel supervision: plausibility, open circuit, ADC rails, wire break, recovery.

One state machine per sensor channel, shared by the float and fixed-point observers and
mirrored line for line by the generated C. At each step, for channel `j`:

1. *readable*: the front end reports no open circuit (and, in float builds, the value is
   not NaN). *plausible*: readable and `limits[0] <= y <= limits[1]`.
   *railed*: plausible and at or beyond an ADC rail (`y <= rails[j][0]` or
   `y >= rails[j][1]`).
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
"""

from __future__ import annotations

import dataclasses

import numpy as np

COUNTER_MAX = 65535


@dataclasses.dataclass(frozen=True)
class FaultConfig:
    """Channel-supervision settings, in the measurement's physical units (°C, K).

    **Arguments:**

    - `limits`: plausible range `(low, high)`, default −55…+125 °C; outside it a reading
      drops its channel.
    - `rails`: per channel `(low, high)` ADC rails, shape `(p, 2)` or one pair for all;
      default none (±inf). A reading at or beyond a rail gets no correction.
    - `residual_threshold`: per channel `|r|` limit for the wire-break test (K), default
      inf (off).
    - `wire_break_after`: N, consecutive large residuals that raise the wire-break flag.
    - `recover_after`: M, consecutive good samples that bring a dropped channel back.
    """

    limits: tuple[float, float] = (-55.0, 125.0)
    rails: object = None
    residual_threshold: object = None
    wire_break_after: int = 10
    recover_after: int = 20

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


class ChannelMonitor:
    """The per-channel state machine of `FaultConfig` (counters and flags, plain ints)."""

    def __init__(self, p: int, wire_break_after: int, recover_after: int):
        self.p, self.N, self.M = p, int(wire_break_after), int(recover_after)
        self.reset()

    def reset(self):
        self.healthy = [True] * self.p
        self.wire_break = [False] * self.p
        self.good_run = [0] * self.p
        self.bad_run = [0] * self.p

    def update(self, plausible, railed, large) -> int:
        """Advance one step; return the bit mask of channels in use."""
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
            if self.healthy[j]:
                mask |= 1 << j
        return mask

    def flags(self) -> tuple[int, int]:
        """`(healthy_mask, wire_break_mask)` as bit masks."""
        h = sum(1 << j for j in range(self.p) if self.healthy[j])
        w = sum(1 << j for j in range(self.p) if self.wire_break[j])
        return h, w

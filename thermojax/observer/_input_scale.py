"""Input limits representable in the chosen fixed-point format: a Q15 or Q31 input code
spans `[-1, 1)` times its scale around its reference, so a heater whose limits are ±36 W
cannot be coded at a scale of 1 W (every power of 1 W or more saturated and then held as
a fault, with the channel reported healthy). A power input's scale is raised to the
smallest power of two that holds its limits, unless it was given; a limit no scale given
can hold refuses the format, saying why."""

from __future__ import annotations

import numpy as np

from .._errors import InputError


def _span(fmt, scale: float) -> tuple[float, float]:
    return fmt.word_min * 2.0 ** -fmt.frac_bits * scale, fmt.word_max * 2.0 ** -fmt.frac_bits * scale


def representable_input_scale(u_scale, u_ref, limits, fmt, power_inputs, names, *,
                              scale_given: bool, where: str):
    """`(u_scale (m,), problem)`: each power input's scale raised (a power of two) until
    its `limits (m, 2)` lie inside the codes' range around `u_ref`; `problem` an
    `InputError` naming `--fixed` where a given scale (or a temperature's) cannot hold
    them (for the caller to raise after the format's own checks), else None."""
    out = np.asarray(u_scale, float).copy()
    problem = None
    for j in range(len(out)):
        lo, hi = (float(v) - float(u_ref[j]) for v in limits[j])
        need_lo = lo if np.isfinite(lo) else 0.0
        need_hi = hi if np.isfinite(hi) else 0.0

        def fits(s):
            a, b = _span(fmt, s)
            return a <= need_lo and need_hi <= b

        if fits(out[j]):
            continue
        if j in power_inputs and not scale_given:
            s = out[j]
            while not fits(s) and s < 2.0 ** 60:
                s *= 2.0
            if fits(s):
                out[j] = s
                continue
        if problem is not None:
            continue
        a, b = _span(fmt, out[j])
        unit = "W" if j in power_inputs else "°C"
        problem = InputError(
            f"the input {names[j]}'s limits {limits[j][0]:g} … {limits[j][1]:g} {unit} are "
            f"not representable in {fmt.name}: at scale {out[j]:g} its codes span "
            f"{u_ref[j] + a:g} … {u_ref[j] + b:g} {unit}, so every value beyond them would "
            "saturate and be held as a fault. Choose a wider format (q16.16 or q8.24), or "
            "narrower input limits.", file=where, field="--fixed")
    return out, problem

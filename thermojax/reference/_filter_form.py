"""One step of the filter-form observer with matrices chosen at run time, in plain
float64 Python and as the C99 that repeats it operation for operation (the scheduled and
the trimmed observers share it, and its playback harness; `-ffp-contract=off`).

    x⁻ = Phi x + B0 u[k−1] + B1 u[k]     (not at the first step: x⁻ = x)
    x  = x⁻ + L (y − C x⁻ − D u[k])       a non-finite reading's residual taken as 0

Every sum in index order from 0.0, every product as written.
"""

from __future__ import annotations

import math

import numpy as np


def filter_step(M: dict, C: list, D: list, x: list, u_prev: list | None, u: list,
                y: list) -> list:
    """The next estimate from `x (n,)`: `M` holds `Phi`, `B0`, `B1`, `L` as nested lists;
    `u_prev` is `None` at the first step (no prediction)."""
    n, p = len(C[0]), len(C)
    if u_prev is not None:
        xm = []
        for r in range(n):
            acc = 0.0
            for c in range(n):
                acc = acc + M["Phi"][r][c] * x[c]
            for c in range(len(u)):
                acc = acc + M["B0"][r][c] * u_prev[c]
            for c in range(len(u)):
                acc = acc + M["B1"][r][c] * u[c]
            xm.append(acc)
    else:
        xm = list(x)
    e = []
    for i in range(p):
        acc = 0.0
        for c in range(n):
            acc = acc + C[i][c] * xm[c]
        for c in range(len(u)):
            acc = acc + D[i][c] * u[c]
        e.append(y[i] - acc if math.isfinite(y[i]) else 0.0)
    out = []
    for r in range(n):
        acc = 0.0
        for i in range(p):
            acc = acc + M["L"][r][i] * e[i]
        out.append(xm[r] + acc)
    return out


def _c_double(v: float) -> str:
    v = float(v)
    return "HUGE_VAL" if v == np.inf else "-HUGE_VAL" if v == -np.inf else repr(v)


def guard_c(prefix: str, guard) -> str:
    """C definitions of a `SampleGuard`: the limits, the held inputs, the guarded sample
    (`ug`, `yok`) and the fault masks `{prefix}_input_fault`, `{prefix}_reading_fault`."""
    P = prefix.upper()
    arr = lambda name, v: (f"static const double {name}[{len(v)}] = "
                           f"{{{', '.join(_c_double(x) for x in v)}}};")
    return "\n".join([
        arr("U_LO", guard.u_lo), arr("U_HI", guard.u_hi), arr("U_START", guard.u_start),
        f"static const double Y_LO = {_c_double(guard.y_lo)}, Y_HI = {_c_double(guard.y_hi)};",
        f"static double u_held[{P}_M], ug[{P}_M];", f"static int yok[{P}_P];",
        f"unsigned long {prefix}_input_fault, {prefix}_reading_fault;"])


def guard_reset_c(prefix: str) -> str:
    """C of `SampleGuard.reset` (inside a reset function)."""
    P = prefix.upper()
    return f"    {{ int g; for (g = 0; g < {P}_M; g++) u_held[g] = U_START[g]; }}\n"


def guard_step_c(prefix: str) -> str:
    """C of `SampleGuard.inputs` and `.readings` for `u`, `y`: fills `ug`, `yok` and the
    fault masks; first in a step function."""
    P = prefix.upper()
    return f"""    {{
    int g;
    {prefix}_input_fault = 0;
    {prefix}_reading_fault = 0;
    for (g = 0; g < {P}_M; g++) {{
        if (U_LO[g] < u[g] && u[g] < U_HI[g]) u_held[g] = u[g];
        else {prefix}_input_fault |= 1UL << g;
        ug[g] = u_held[g];
    }}
    for (g = 0; g < {P}_P; g++) {{
        yok[g] = Y_LO < y[g] && y[g] < Y_HI;
        if (!yok[g]) {prefix}_reading_fault |= 1UL << g;
    }}
    }}
"""


def filter_step_c(prefix: str) -> str:
    """The C body of `filter_step`, updating `{prefix}_x` from the guarded sample (`ug`,
    `y` where `yok`: `guard_step_c` first), `u_prev` and `started`, with the matrices in
    `Phi`, `B0`, `B1`, `L`, `CM`, `DM` and the sizes in `{PREFIX}_N`, `_M`, `_P` (declares
    its own locals `xm`, `e`, `r`, `c`, `i`)."""
    P = prefix.upper()
    return f"""    {{
    double xm[{P}_N], e[{P}_P];
    int r, c, i;
    if (started) {{
        for (r = 0; r < {P}_N; r++) {{
            double acc = 0.0;
            for (c = 0; c < {P}_N; c++) acc = acc + Phi[r][c] * {prefix}_x[c];
            for (c = 0; c < {P}_M; c++) acc = acc + B0[r][c] * u_prev[c];
            for (c = 0; c < {P}_M; c++) acc = acc + B1[r][c] * ug[c];
            xm[r] = acc;
        }}
    }} else {{
        for (r = 0; r < {P}_N; r++) xm[r] = {prefix}_x[r];
    }}
    for (i = 0; i < {P}_P; i++) {{
        double acc = 0.0;
        for (c = 0; c < {P}_N; c++) acc = acc + CM[i][c] * xm[c];
        for (c = 0; c < {P}_M; c++) acc = acc + DM[i][c] * ug[c];
        e[i] = yok[i] ? y[i] - acc : 0.0;
    }}
    for (r = 0; r < {P}_N; r++) {{
        double acc = 0.0;
        for (i = 0; i < {P}_P; i++) acc = acc + L[r][i] * e[i];
        {prefix}_x[r] = xm[r] + acc;
    }}
    for (c = 0; c < {P}_M; c++) u_prev[c] = ug[c];
    started = 1;
    }}
"""


def c_array(name, a, const: bool = True) -> str:
    """A C definition `static const double name[d0][d1]... = {...};` of `a` (17
    significant digits, exact)."""
    a = np.asarray(a, float)
    dims = "".join(f"[{d}]" for d in a.shape)

    def body(x):
        if x.ndim == 1:
            return "{" + ", ".join(repr(float(v)) for v in x) + "}"
        return "{" + ", ".join(body(r) for r in x) + "}"

    return f"static {'const ' if const else ''}double {name}{dims} = {body(a)};"


def playback_harness_c(prefix: str, comment: str, declare: str = "", before: str = "",
                       after_step: str = "") -> str:
    """A `main` that plays back `int32 T`, `double x0[N]`, then per sample `double u[M]`,
    `double y[P]` through `prefix_reset` and `prefix_step`, writing `double x[N]` per
    sample: `declare` (variables), `before` (C run after opening the files, e.g. reading
    and applying a header) and `after_step` (C writing more per sample) extend it."""
    P = prefix.upper()
    return f"""/* Playback harness for {prefix}: {comment} */
#include <stdio.h>
#include <stdint.h>
#include "{prefix}.h"
int main(int argc, char **argv) {{
    FILE *in, *out; int32_t T; long t;
    double x0[{P}_N], u[{P}_M], y[{P}_P];{declare}
    if (argc < 3) return 2;
    in = fopen(argv[1], "rb"); if (!in) return 3;
    out = fopen(argv[2], "wb"); if (!out) return 3;
{before}    if (fread(&T, sizeof T, 1, in) != 1) return 4;
    if (fread(x0, sizeof x0[0], {P}_N, in) != {P}_N) return 4;
    {prefix}_reset(x0);
    for (t = 0; t < T; t++) {{
        if (fread(u, sizeof u[0], {P}_M, in) != {P}_M) return 4;
        if (fread(y, sizeof y[0], {P}_P, in) != {P}_P) return 4;
        {prefix}_step(u, y);
        fwrite({prefix}_x, sizeof(double), {P}_N, out);
{after_step}    }}
    fclose(in); fclose(out);
    return 0;
}}
"""

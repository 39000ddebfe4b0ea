"""C99 generator: the reference observer as a `.c`/`.h` pair with `static const` arrays.

The generated code repeats the NumPy reference operation for operation:

- fixed point: the same integer coefficients, exact int64 sums, alignment by
  multiplication with `2**shift` (left shifts of negative values are undefined in C), the
  same rounding `(a + 2**(s-1)) >> s` (an arithmetic right shift is checked at compile
  time) and the same saturation: bit-exact with `FixedObserver`.
- float/double: every sum starts from 0 and adds `M[i][j] * v[j]` in order `j = 0, 1, ...`
  with the matrices stored column by column (so the compiler may vectorize over rows
  without reordering any sum). Bit-exact with `FloatObserver` when compiled without
  contraction into fused multiply-adds (`-ffp-contract=off`; `-ffast-math` is not allowed)
  on a target that evaluates `float` in single precision (FLT_EVAL_METHOD 0: x86-64 SSE,
  Cortex-M4F/M7).
- the channel supervision of `FaultConfig`, line for line.

State, inputs and flags live in statically allocated globals; nothing is allocated at run
time. `CSource.harness` is a small playback program for tests and benchmarks.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ._fixed import FixedObserver
from ._float import FloatObserver


@dataclasses.dataclass(frozen=True)
class CSource:
    """Generated files: `header` (`<prefix>.h`), `source` (`<prefix>.c`), `harness`
    (a `main` that plays back a binary file, see `generate_c`), and facts about the build:
    `word` (the C type of a value), `word_size` (bytes), `n`, `m`, `p`."""

    prefix: str
    header: str
    source: str
    harness: str
    word: str
    word_size: int
    n: int
    m: int
    p: int

    @property
    def dtype(self) -> np.dtype:
        return np.dtype({"double": np.float64, "float": np.float32, "int32_t": np.int32,
                         "int16_t": np.int16}[self.word])

    def pack_playback(self, x0, u, y, open_mask=None) -> bytes:
        """The harness's input file: `x0 (n,)`, `u (T, m)`, `y (T, p)` as words (codes for a
        fixed-point build), `open_mask (T,)` bytes or `(T, p)` booleans."""
        u = np.asarray(u).astype(self.dtype, casting="unsafe")
        y = np.asarray(y).astype(self.dtype, casting="unsafe")
        T = u.shape[0]
        if open_mask is None:
            oc = np.zeros(T, np.uint8)
        else:
            oc = np.asarray(open_mask)
            if oc.ndim == 2:
                oc = (oc.astype(np.uint8) << np.arange(oc.shape[1], dtype=np.uint8)).sum(1)
            oc = oc.astype(np.uint8)
        rec = np.zeros(T, np.dtype([("u", self.dtype, (self.m,)), ("y", self.dtype, (self.p,)),
                                    ("oc", np.uint8)], align=False))
        rec["u"], rec["y"], rec["oc"] = u, y, oc
        x0 = np.asarray(x0).astype(self.dtype, casting="unsafe").reshape(self.n)
        return np.int32(T).tobytes() + x0.tobytes() + rec.tobytes()

    def unpack_output(self, data: bytes):
        """The harness's output file as an `ObserverRun` (words, unconverted)."""
        from ._run import ObserverRun

        rec = np.frombuffer(data, np.dtype([("x", self.dtype, (self.n,)),
                                            ("r", self.dtype, (self.p,)),
                                            ("f", np.uint8, (3,))], align=False))
        return ObserverRun(rec["x"].astype(self.dtype), rec["r"].astype(self.dtype),
                           rec["f"][:, 0].copy(), rec["f"][:, 1].copy(), rec["f"][:, 2].copy())

    def write(self, folder) -> dict:
        """Write `<prefix>.h`, `<prefix>.c` and `<prefix>_main.c` into `folder`."""
        import pathlib

        folder = pathlib.Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        paths = {"header": folder / f"{self.prefix}.h", "source": folder / f"{self.prefix}.c",
                 "harness": folder / f"{self.prefix}_main.c"}
        for key, path in paths.items():
            path.write_text(getattr(self, key))
        return paths


def _lit(v, word: str) -> str:
    v = float(v)
    if np.isinf(v):
        return "INFINITY" if v > 0 else "-INFINITY"
    if word == "float":
        return float(np.float32(v)).hex() + "f"
    if word == "double":
        return v.hex()
    i = int(v)
    if word == "int64_t":
        return f"INT64_C({i})"
    return f"({i + 1} - 1)" if i < -32767 else str(i)   # no negative literal overflows int


def _braced(a, word: str, indent: str) -> str:
    if a.ndim == 1:
        return "{" + ", ".join(_lit(v, word) for v in a) + "}"
    inner = indent + "    "
    return "{\n" + ",\n".join(inner + _braced(b, word, inner) for b in a) + "\n" + indent + "}"


def _array(name: str, ctype: str, values, word: str) -> str:
    a = np.asarray(values)
    dims = "".join(f"[{d}]" for d in a.shape)
    return f"static const {ctype} {name}{dims} = {_braced(a, word, '')};\n"


def _colmajor(M):
    return np.swapaxes(np.asarray(M), -1, -2)


def generate_c(observer, prefix: str = "tj_observer") -> CSource:
    """C99 source for a `FloatObserver` (float or double) or a `FixedObserver`.

    **Arguments:**

    - `observer`: the reference observer to export (its matrices, gains, format and
      fault settings).
    - `prefix`: the name of the files and of every public symbol.

    **Returns:** a `CSource`. API of the generated code (`P_` = upper-case prefix):
    `void prefix_reset(const prefix_word_t x0[P_N])`;
    `uint8_t prefix_step(const prefix_word_t u[P_M], const prefix_word_t y[P_P], uint8_t open_mask)`
    (returns the mask of channels used); globals `prefix_x[P_N]` (the corrected state),
    `prefix_r[P_P]` (residuals), `prefix_healthy`, `prefix_wire_break` (masks).

    The harness reads `argv[1]`: int32 `T`, then `x0` (`n` words), then per step `u`
    (`m` words), `y` (`p` words) and one byte of open-circuit flags; it writes to
    `argv[2]` per step `x` (`n` words), `r` (`p` words) and three bytes (in use, healthy,
    wire break). With a third argument `repeat` it runs the playback that many times
    (for instruction counting) and writes the last.
    """
    if not prefix.isidentifier():
        raise ValueError(f"`generate_c(prefix={prefix!r})`: the prefix must be a C identifier.")
    s = observer.system
    n, m, p = s.n_states, s.n_inputs, s.n_outputs
    P = prefix.upper()
    fixed = isinstance(observer, FixedObserver)
    if fixed:
        word = "int32_t" if observer.fmt.word_bits == 32 else "int16_t"
        size = observer.fmt.word_bits // 8
    elif isinstance(observer, FloatObserver):
        word = "double" if observer.dtype == np.float64 else "float"
        size = observer.dtype.itemsize
    else:
        raise TypeError(f"`generate_c` takes a `FloatObserver` or a `FixedObserver`, got "
                        f"{type(observer).__name__}.")
    fc = observer.faults
    h = [f"/* Generated by thermojax.reference.generate_c: do not edit. */",
         f"#ifndef {P}_H", f"#define {P}_H", "#include <stdint.h>",
         f"#define {P}_N {n}", f"#define {P}_M {m}", f"#define {P}_P {p}",
         f"typedef {word} {prefix}_word_t;",
         f"void {prefix}_reset(const {prefix}_word_t x0[{P}_N]);",
         f"uint8_t {prefix}_step(const {prefix}_word_t u[{P}_M], const {prefix}_word_t "
         f"y[{P}_P], uint8_t open_mask);",
         f"extern {prefix}_word_t {prefix}_x[{P}_N];",
         f"extern {prefix}_word_t {prefix}_r[{P}_P];",
         f"extern uint8_t {prefix}_healthy, {prefix}_wire_break;", f"#endif", ""]
    c = [f"/* Generated by thermojax.reference.generate_c: do not edit.", "",
         f"   Observer in filter form with first-order-hold inputs:",
         f"     x-[k] = Phi x[k-1] + B0 u[k-1] + B1 u[k]   (skipped at the first step)",
         f"     x[k]  = x-[k] + L_S (y[k] - C x-[k] - D u[k]),  S = channels in use.",
         f"   Matrices are stored column by column: M[j][i] is row i, column j."]
    if fixed:
        F = observer.fmt
        c += [f"   Format {F.name}: values are codes of (value - offset) / {F.state_scale:g} "
              f"* 2^{F.frac_bits};",
              f"   offsets: states {observer.x_ref.tolist()}, inputs "
              f"{observer.u_ref.tolist()} (scales {observer.u_scale.tolist()}),",
              f"   outputs {observer.y_ref.tolist()}. Rounding: nearest, ties toward +inf;",
              f"   saturation to the {F.word_bits}-bit word; int64 accumulation. */"]
    else:
        c += [f"   {word} arithmetic; compile with -ffp-contract=off (no FMA) for bit-exact",
              f"   agreement with the NumPy reference. */"]
    c += [f'#include "{prefix}.h"', "#include <math.h>", ""]
    lim = (observer.limit_codes if fixed else
           np.tile(np.asarray(fc.limits, float), (p, 1)))
    rails = observer.rail_codes if fixed else fc.rails_array(p)
    thr = observer.threshold_codes if fixed else fc.threshold_array(p)
    vtype = word
    if fixed:
        cf = observer.coef
        c.append(f"typedef char {prefix}_asr_check[((-3) >> 1) == -2 ? 1 : -1]; "
                 f"/* arithmetic >> */")
        c += [f"#define {P}_WMIN ({F.word_min})", f"#define {P}_WMAX ({F.word_max})",
              f"#define {P}_F_PRED {observer.f_pred}", f"#define {P}_F_OUT {observer.f_out}",
              f"#define {P}_F_GAIN {observer.f_gain}"]
        for name in ("Phi", "B0", "B1", "C", "D"):
            c.append(f"#define {P}_SCALE_{name.upper()} INT64_C({1 << observer.shift[name]})")
        c.append("")
        mats = {"PHI": cf["Phi"], "B0": cf["B0"], "B1": cf["B1"], "CY": cf["C"], "DY": cf["D"],
                "GAIN": cf["L"]}
        for name, M in mats.items():
            c.append(_array(f"{P}_{name}", word, _colmajor(M), "int"))
        c.append(_array(f"{P}_LIM", word, lim, "int"))
        c.append(_array(f"{P}_RAIL", word, rails, "int"))
        c.append(_array(f"{P}_THR", "int64_t", thr, "int64_t"))
        c += [f"static int64_t {prefix}_rnd(int64_t a, int s) {{",
              f"    return s > 0 ? (a + ((int64_t)1 << (s - 1))) >> s : a;", "}",
              f"static {word} {prefix}_sat(int64_t a) {{",
              f"    return ({word})(a < {P}_WMIN ? {P}_WMIN : a > {P}_WMAX ? {P}_WMAX : a);",
              "}", ""]
    else:
        dt = np.float64 if word == "double" else np.float32
        mats = {"PHI": s.Phi, "B0": s.B0, "B1": s.B1, "CY": s.C, "DY": s.D,
                "GAIN": s.gain_table}
        for name, M in mats.items():
            c.append(_array(f"{P}_{name}", word, _colmajor(np.asarray(M, dt)), word))
        c.append(_array(f"{P}_LIM", word, np.asarray(lim, dt), word))
        c.append(_array(f"{P}_RAIL", word, np.asarray(rails, dt), word))
        c.append(_array(f"{P}_THR", word, np.asarray(thr, dt), word))
    acc = "int64_t" if fixed else word
    zero = "0" if fixed else ("0.0" if word == "double" else "0.0f")
    mul = (lambda a, b: f"(int64_t){a} * {b}") if fixed else (lambda a, b: f"{a} * {b}")
    c += [f"{word} {prefix}_x[{P}_N];", f"{word} {prefix}_r[{P}_P];",
          f"uint8_t {prefix}_healthy, {prefix}_wire_break;",
          f"static {word} {prefix}_u_prev[{P}_M];",
          f"static uint16_t {prefix}_good_run[{P}_P], {prefix}_bad_run[{P}_P];",
          f"static uint8_t {prefix}_started;", "",
          f"void {prefix}_reset(const {word} x0[{P}_N]) {{",
          f"    int i;",
          f"    for (i = 0; i < {P}_N; i++) {prefix}_x[i] = x0[i];",
          f"    for (i = 0; i < {P}_P; i++) {{ {prefix}_good_run[i] = 0; "
          f"{prefix}_bad_run[i] = 0; }}",
          f"    {prefix}_healthy = (uint8_t)((1u << {P}_P) - 1u);",
          f"    {prefix}_wire_break = 0;", f"    {prefix}_started = 0;", "}", "",
          f"uint8_t {prefix}_step(const {word} u[{P}_M], const {word} y[{P}_P], "
          f"uint8_t open_mask) {{",
          f"    {word} xm[{P}_N];",
          f"    int i, j;", f"    uint8_t mask = 0;"]
    # predict
    if fixed:
        c += [f"    if ({prefix}_started) {{",
              f"        int64_t a0[{P}_N] = {{0}}, a1[{P}_N] = {{0}}, a2[{P}_N] = {{0}};",
              f"        for (j = 0; j < {P}_N; j++) for (i = 0; i < {P}_N; i++) "
              f"a0[i] += {mul(f'{P}_PHI[j][i]', f'{prefix}_x[j]')};",
              f"        for (j = 0; j < {P}_M; j++) for (i = 0; i < {P}_N; i++) "
              f"a1[i] += {mul(f'{P}_B0[j][i]', f'{prefix}_u_prev[j]')};",
              f"        for (j = 0; j < {P}_M; j++) for (i = 0; i < {P}_N; i++) "
              f"a2[i] += {mul(f'{P}_B1[j][i]', 'u[j]')};",
              f"        for (i = 0; i < {P}_N; i++) xm[i] = {prefix}_sat({prefix}_rnd("
              f"a0[i] * {P}_SCALE_PHI + a1[i] * {P}_SCALE_B0 + a2[i] * {P}_SCALE_B1, "
              f"{P}_F_PRED));",
              f"    }} else {{", f"        for (i = 0; i < {P}_N; i++) xm[i] = {prefix}_x[i];",
              f"    }}",
              f"    {{", f"        int64_t a0[{P}_P] = {{0}}, a1[{P}_P] = {{0}};",
              f"        for (j = 0; j < {P}_N; j++) for (i = 0; i < {P}_P; i++) "
              f"a0[i] += {mul(f'{P}_CY[j][i]', 'xm[j]')};",
              f"        for (j = 0; j < {P}_M; j++) for (i = 0; i < {P}_P; i++) "
              f"a1[i] += {mul(f'{P}_DY[j][i]', 'u[j]')};",
              f"        for (i = 0; i < {P}_P; i++) {prefix}_r[i] = {prefix}_sat((int64_t)y[i] - "
              f"{prefix}_rnd(a0[i] * {P}_SCALE_C + a1[i] * {P}_SCALE_D, {P}_F_OUT));",
              f"    }}"]
    else:
        c += [f"    if ({prefix}_started) {{",
              f"        {word} a[{P}_N];",
              f"        for (i = 0; i < {P}_N; i++) a[i] = {zero};",
              f"        for (j = 0; j < {P}_N; j++) for (i = 0; i < {P}_N; i++) "
              f"a[i] = a[i] + {P}_PHI[j][i] * {prefix}_x[j];",
              f"        for (j = 0; j < {P}_M; j++) for (i = 0; i < {P}_N; i++) "
              f"a[i] = a[i] + {P}_B0[j][i] * {prefix}_u_prev[j];",
              f"        for (j = 0; j < {P}_M; j++) for (i = 0; i < {P}_N; i++) "
              f"a[i] = a[i] + {P}_B1[j][i] * u[j];",
              f"        for (i = 0; i < {P}_N; i++) xm[i] = a[i];",
              f"    }} else {{", f"        for (i = 0; i < {P}_N; i++) xm[i] = {prefix}_x[i];",
              f"    }}",
              f"    {{", f"        {word} a[{P}_P];",
              f"        for (i = 0; i < {P}_P; i++) a[i] = {zero};",
              f"        for (j = 0; j < {P}_N; j++) for (i = 0; i < {P}_P; i++) "
              f"a[i] = a[i] + {P}_CY[j][i] * xm[j];",
              f"        for (j = 0; j < {P}_M; j++) for (i = 0; i < {P}_P; i++) "
              f"a[i] = a[i] + {P}_DY[j][i] * u[j];",
              f"        for (i = 0; i < {P}_P; i++) {prefix}_r[i] = y[i] - a[i];",
              f"    }}"]
    # supervision
    c += [f"    for (j = 0; j < {P}_P; j++) {{",
          f"        const uint8_t bit = (uint8_t)(1u << j);",
          f"        const {vtype} v = y[j], r = {prefix}_r[j];",
          f"        if ((open_mask & bit) || !({P}_LIM[j][0] <= v && v <= {P}_LIM[j][1])) {{",
          f"            {prefix}_healthy &= (uint8_t)~bit;",
          f"            {prefix}_good_run[j] = 0; {prefix}_bad_run[j] = 0;",
          f"            continue;", f"        }}",
          f"        if (v <= {P}_RAIL[j][0] || v >= {P}_RAIL[j][1]) continue;  /* anti-windup */",
          f"        if (r > {P}_THR[j] || r < -{P}_THR[j]) {{",
          f"            if ({prefix}_bad_run[j] < 65535u) {prefix}_bad_run[j]++;",
          f"            {prefix}_good_run[j] = 0;",
          f"            if ({prefix}_bad_run[j] >= {int(fc.wire_break_after)}u) {{",
          f"                {prefix}_wire_break |= bit; {prefix}_healthy &= (uint8_t)~bit;",
          f"            }}",
          f"        }} else {{",
          f"            if ({prefix}_good_run[j] < 65535u) {prefix}_good_run[j]++;",
          f"            {prefix}_bad_run[j] = 0;",
          f"            if (!({prefix}_healthy & bit) && {prefix}_good_run[j] >= "
          f"{int(fc.recover_after)}u) {{",
          f"                {prefix}_healthy |= bit; {prefix}_wire_break &= (uint8_t)~bit;",
          f"            }}",
          f"        }}",
          f"        if ({prefix}_healthy & bit) mask |= bit;",
          f"    }}"]
    # correct
    if fixed:
        c += [f"    if (mask) {{",
              f"        int64_t a[{P}_N] = {{0}};",
              f"        for (j = 0; j < {P}_P; j++) if (mask >> j & 1u) for (i = 0; i < {P}_N; i++) "
              f"a[i] += {mul(f'{P}_GAIN[mask][j][i]', f'{prefix}_r[j]')};",
              f"        for (i = 0; i < {P}_N; i++) xm[i] = {prefix}_sat((int64_t)xm[i] + "
              f"{prefix}_rnd(a[i], {P}_F_GAIN));",
              f"    }}"]
    else:
        c += [f"    if (mask) {{",
              f"        {word} a[{P}_N];",
              f"        for (i = 0; i < {P}_N; i++) a[i] = {zero};",
              f"        for (j = 0; j < {P}_P; j++) if (mask >> j & 1u) for (i = 0; i < {P}_N; i++) "
              f"a[i] = a[i] + {P}_GAIN[mask][j][i] * {prefix}_r[j];",
              f"        for (i = 0; i < {P}_N; i++) xm[i] = xm[i] + a[i];",
              f"    }}"]
    c += [f"    for (i = 0; i < {P}_N; i++) {prefix}_x[i] = xm[i];",
          f"    for (i = 0; i < {P}_M; i++) {prefix}_u_prev[i] = u[i];",
          f"    {prefix}_started = 1;", f"    return mask;", "}", ""]
    harness = "\n".join([
        f"/* Playback harness for {prefix}: see thermojax.reference.generate_c. */",
        "#include <stdio.h>", "#include <stdlib.h>", f'#include "{prefix}.h"',
        "int main(int argc, char **argv) {",
        "    FILE *in, *out; int32_t T; long k, rep, repeat = 1;",
        f"    {word} x0[{P}_N], *u, *y; uint8_t *oc;",
        "    if (argc < 3) { fprintf(stderr, \"usage: %s in.bin out.bin [repeat]\\n\", argv[0]); return 2; }",
        "    if (argc > 3) repeat = atol(argv[3]);",
        "    in = fopen(argv[1], \"rb\"); if (!in) return 3;",
        "    if (fread(&T, sizeof T, 1, in) != 1) return 4;",
        f"    if (fread(x0, sizeof x0[0], {P}_N, in) != {P}_N) return 4;",
        f"    u = malloc(sizeof *u * {P}_M * (size_t)T); y = malloc(sizeof *y * {P}_P * (size_t)T);",
        "    oc = malloc((size_t)T); if (!u || !y || !oc) return 5;",
        "    for (k = 0; k < T; k++) {",
        f"        if (fread(u + k * {P}_M, sizeof *u, {P}_M, in) != {P}_M) return 4;",
        f"        if (fread(y + k * {P}_P, sizeof *y, {P}_P, in) != {P}_P) return 4;",
        "        if (fread(oc + k, 1, 1, in) != 1) return 4;", "    }", "    fclose(in);",
        "    out = fopen(argv[2], \"wb\"); if (!out) return 3;",
        "    for (rep = 0; rep < repeat; rep++) {",
        f"        {prefix}_reset(x0);",
        "        for (k = 0; k < T; k++) {",
        f"            uint8_t flags[3];",
        f"            flags[0] = {prefix}_step(u + k * {P}_M, y + k * {P}_P, oc[k]);",
        "            if (rep + 1 < repeat) continue;",
        f"            flags[1] = {prefix}_healthy; flags[2] = {prefix}_wire_break;",
        f"            fwrite({prefix}_x, sizeof {prefix}_x[0], {P}_N, out);",
        f"            fwrite({prefix}_r, sizeof {prefix}_r[0], {P}_P, out);",
        "            fwrite(flags, 1, 3, out);", "        }", "    }",
        "    fclose(out); free(u); free(y); free(oc);", "    return 0;", "}", ""])
    return CSource(prefix, "\n".join(h), "\n".join(c), harness, word, size, n, m, p)

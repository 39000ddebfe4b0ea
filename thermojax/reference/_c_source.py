"""C99 generator: the reference observer as a `.c`/`.h` pair with `static const` arrays.

The generated code repeats the NumPy reference operation for operation:

The step is straight-line code (no loops over matrices): each product is unrolled row by
row with the coefficients as literals and exact zeros skipped. `layout="columns"` (float
and double builds) writes the prediction and the correction as column-at-a-time loops over
rows padded to a SIMD width instead, and the channel supervision as one branch-free loop
over the channels (see `generate_c`).

- fixed point: the same integer coefficients, exact int64 sums (so skipping zeros and
  the order of terms change nothing), the alignment `2**shift` folded into the literal
  (no left shift of a negative value, undefined in C), the same rounding
  `(a + 2**(s-1)) >> s` (an arithmetic right shift is checked at compile time) and the
  same saturation: bit-exact with `FixedObserver`.
- float/double: each row is one left-to-right sum `c0 * v0 + c1 * v1 + ...` over its
  nonzero coefficients (the first product starts the sum), the order of
  `FloatObserver` (`SparseSum`); `a - c * v` stands for `a + (-c) * v` and `v` for
  `1 * v`, both identical in IEEE arithmetic. Bit-exact with `FloatObserver` when compiled without
  contraction into fused multiply-adds (`-ffp-contract=off`; `-ffast-math` is not allowed)
  on a target that evaluates `float` in single precision (FLT_EVAL_METHOD 0: x86-64 SSE,
  Cortex-M4F/M7).
- the channel supervision of `FaultConfig`, line for line (`rows`), or its branch-free
  form `channel_rules` in lanes (`columns`): the same flags, counters and masks.
- the bias channels of an observer built with `biases=` (see `_bias.py`), after the
  correction, into `prefix_bias[]`: for a float or double build in double precision in
  the operation order of `BiasEvaluator.step` (bit-exact under the same conditions), for
  a fixed-point build the integer evaluation of `FixedBiasEvaluator` (int32 codes,
  int64 products, the same roundings, clamps and strain updates: bit-exact). Strain
  states are statically allocated; the coefficients are literals in straight-line code
  and also `static const` tables (`prefix_table(P_TABLE_BIAS_*)`).

State, inputs and flags live in statically allocated globals; nothing is allocated at run
time. `CSource.harness` is a small playback program for tests and benchmarks.

The literals and tables are written by `_c_literals`, the bias channels' statements by
`_c_bias` and the lane-parallel supervision by `_c_supervision`. What stays here is one
concept, the observer's step written out as C, and most of it is `generate_c`, a single
function of some 550 lines (about 100 of them its docstring): it reads as the `.c` file
it writes, section after section, and stays one function.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ._c_bias import _bias_tables, _fixed_bias_c, _float_bias_c
from ._c_literals import _array, _lit, _readable_lit, _zero, comment_safe
from ._c_supervision import _lane_supervision_c
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
    q: int = 0
    bias_word: str = "double"
    unit: str | None = None   # a per-unit table (`<prefix>_unit.c`), where the build has one

    @property
    def dtype(self) -> np.dtype:
        return np.dtype({"double": np.float64, "float": np.float32, "int32_t": np.int32,
                         "int16_t": np.int16}[self.word])

    def pack_playback(self, x0, u, y, open_mask=None) -> bytes:
        """The harness's input file: `x0 (n,)`, `u (T, m)`, `y (T, p)` as words (codes for a
        fixed-point build), `open_mask (T,)` bytes or `(T, p)` booleans."""
        with np.errstate(over="ignore", invalid="ignore"):   # float32: ±inf, as C would
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

        fields = [("x", self.dtype, (self.n,)), ("r", self.dtype, (self.p,)),
                  ("f", np.uint8, (4,)), ("i", np.uint32), ("s", np.uint16)]
        bias_dtype = np.dtype(np.int32 if self.bias_word == "int32_t" else np.float64)
        if self.q:
            fields.append(("b", bias_dtype, (self.q,)))
        rec = np.frombuffer(data, np.dtype(fields, align=False))
        bias = None
        if self.q:
            bias = rec["b"].astype(np.int64 if self.bias_word == "int32_t" else np.float64)
        return ObserverRun(rec["x"].astype(self.dtype), rec["r"].astype(self.dtype),
                           rec["f"][:, 0].copy(), rec["f"][:, 1].copy(), rec["f"][:, 2].copy(),
                           bias, rec["i"].copy(), rec["f"][:, 3].copy(), rec["s"].copy())

    def write(self, folder) -> dict:
        """Write `<prefix>.h`, `<prefix>.c`, `<prefix>_main.c` (and `<prefix>_unit.c` where
        the build has a unit table) into `folder`."""
        import pathlib

        folder = pathlib.Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        paths = {"header": folder / f"{self.prefix}.h", "source": folder / f"{self.prefix}.c",
                 "harness": folder / f"{self.prefix}_main.c"}
        if self.unit is not None:
            paths["unit"] = folder / f"{self.prefix}_unit.c"
        for key, path in paths.items():
            path.write_text(getattr(self, key))
        return paths


def _names(source, n: int, m: int, p: int):
    """`(states, inputs, outputs)` names for comments: from a `(states, inputs, outputs)`
    tuple, from an observer's `names` attribute, or generic (`x0`, `u0`, `y0`)."""
    given = source if isinstance(source, (tuple, list)) else getattr(source, "names", None)
    generic = ([f"x{i}" for i in range(n)], [f"u{j}" for j in range(m)],
               [f"y{j}" for j in range(p)])
    if given is None:
        return generic
    out = []
    for names, default in zip(given, generic):
        names = [comment_safe(v) for v in names] if names is not None else default
        out.append(names if len(names) == len(default) else default)
    return tuple(out)


def _colmajor(M):
    return np.swapaxes(np.asarray(M), -1, -2)


def generate_c(observer, prefix: str = "tj_observer", names=None,
               layout: str = "rows", vector_bytes: int = 32,
               supervision: str | None = None) -> CSource:
    """C99 source for a `FloatObserver` (float or double) or a `FixedObserver`.

    **Arguments:**

    - `observer`: the reference observer to export (its matrices, gains, format and
      fault settings).
    - `prefix`: the name of the files and of every public symbol.
    - `names`: `(states, inputs, outputs)` names for the comments (default: the
      observer's `names` attribute if it has one, else `x0`, `u0`, `y0`, ...).
    - `layout`: `"rows"` (default) or `"columns"` (float and double builds only), how the
      products with one row per state (prediction and correction) are written; see below.
    - `vector_bytes`: the columns layout's SIMD width in bytes (32: AVX2; 16: SSE2, NEON);
      the rows are padded to a multiple of it.
    - `supervision`: `"branches"` (one block with branches per channel, the rows
      layout's) or `"lanes"` (branch free, all channels at once, for SIMD: float and
      double builds only); default `"lanes"` in the columns layout, else `"branches"`.

    The step is straight-line code: every matrix-vector product is unrolled with the
    coefficients as literals (shortest exact decimals in float builds; integer codes with
    the alignment shift folded in for fixed point), exact zeros skipped, one comment per
    matrix row; the channel supervision is unrolled per channel with its limits folded
    in, and the correction is a `switch` over the sets of channels in use. The
    coefficient tables remain as `static const` arrays, read through
    `prefix_table(P_TABLE_PHI)` etc. (for inspection and checksums only).

    `layout="columns"` writes the prediction `[Phi B0 B1] [x; u[k-1]; u[k]]` and the
    correction `L_S r` as column-at-a-time sums for SIMD: one loop over `P_W` lanes (the
    `n` rows padded to `vector_bytes`: 8 floats or 4 doubles for AVX2) whose body is
    `COLS[a][i] * v_a + COLS[b][i] * v_b + ...` over the product's nonzero columns, read
    from the `static const` table `P_COLS[K][P_W]`; the prediction reads `x`, `u[k-1]`
    and `u[k]` into locals first and writes `P_x` in place, the correction adds to it
    (no stack copy). gcc -O3 vectorizes each loop (a broadcast, a multiply and an add per
    column); without SIMD it runs as scalar code.
    Every row then also adds its zero coefficients' products, `±0`: for finite values
    this leaves each row's sum exactly the left-to-right sum over its nonzero terms (the
    first product starting it), except that a result that is exactly zero may differ in
    its sign; a zero of either sign gives the same values in every later sum, product and
    comparison (again up to the sign of zeros). So the build agrees with `FloatObserver`
    bit for bit up to the sign of an exact zero, and its flags agree exactly.
    The inputs it multiplies are finite: every input sample is checked first and a bad
    one replaced by its last good value (below). Measurements may be anything: a channel whose value is not
    plausible is not in use, and the correction reads only the columns of the channels
    in use. The output product (`p` rows) is as in `"rows"`.

    `supervision="lanes"` (the columns layout's default) writes the channel supervision
    lane-parallel: one loop over the channels padded to a power of two (lane `j` =
    channel `j`; padding lanes compute unused values), branch free, in lane masks (all
    ones or zero) and counters as wide as a word (`int32_t` for float, `int64_t` for
    double), which gcc -O3 vectorizes: the measurements compared with the limits
    (`P_SUP_LO`, `P_SUP_HI`) and rails (`P_SUP_RLO`, `P_SUP_RHI`), `|r|` with the
    thresholds (`P_SUP_THR`), the open-circuit bits as lane masks (float builds with
    `p <= 4`: a table `P_SUP_OPEN` with one row per value of the low `p` bits; else a
    bit test), the run counters `c = hit ? min(c + 1, 65535) : ...` as selects, and the
    in-use, healthy and wire-break masks OR-ed together from per-lane bits
    (`P_SUP_BITS`). Its statements are generated from `channel_rules` (`_faults.py`), a
    branch-free statement of the rules of `ChannelMonitor` that a test checks against
    `ChannelMonitor.update` for every flag state and input and counters around N, M and
    the saturation; the rows layout's per-channel blocks state the same rules with
    branches. Parts that cannot act are left out when the code is generated: the rail
    test without a rail inside the plausible range, the bad-run counter, the residual
    test and the wire-break flags without a finite residual threshold (the counter stays
    0, the flags down). The health and wire-break state lives in the lanes
    (`prefix_sup_h[]`, ...); `prefix_healthy` and `prefix_wire_break` are written from
    them every step (outputs: a value written there from outside is not read back; the
    wire-break mask is read back by the branches, whose channel health lives in
    `prefix_ch_healthy`). Cost (imu6, gcc 12, -O3 -march=x86-64-v3, instructions a step,
    see `benchmarks/observer_c.py`): lanes against branches 106 against 130 (float32) and
    133 against 158 (double) with the default `FaultConfig`, 149 against 153 and 176
    against 182 with residual thresholds and rails. At -O2 (SSE2): float32, vectorized,
    191 against 207 and 252 against 230; double, which gcc leaves scalar (SSE2 has no
    64-bit integer compare), 433 against 295 and 678 against 322. Choose
    `supervision="branches"` for double without AVX2 and on a core without SIMD, where
    the branch-free loop runs lane after lane.

    **Returns:** a `CSource`. API of the generated code (`P_` = upper-case prefix):
    `void prefix_reset(const prefix_word_t x0[P_N])`;
    `uint8_t prefix_step(const prefix_word_t u[P_M], const prefix_word_t y[P_P], uint8_t open_mask)`
    (returns the mask of channels used); globals `prefix_x[P_N]` (the corrected state;
    `prefix_x[P_W]` in the columns layout, the states then zeros),
    `prefix_r[P_P]` (residuals), `prefix_healthy`, `prefix_wire_break` (masks; healthy
    is 0 when `prefix_state_ok` is 0), `prefix_state_ok` (every state strictly inside the
    limits and, fixed point, none saturated in the step), `prefix_input_fault` (uint32
    mask of the inputs held at their last good value this step), `prefix_saturations`
    (uint16, steps with a saturated state, fixed point).

    Untrusted samples: each input `j` is used only when strictly inside its limits
    (`FaultConfig.input_limits`, codes in fixed point), else `u[k-1]` (the last good
    value) is used and its bit set in `prefix_input_fault`; reset sets `u[k-1]` to the
    initial held values. Measurement limits are exclusive too.

    With bias channels (`observer.biases`): `P_Q` channels, `prefix_bias[P_Q]` (int32
    codes in a fixed build, `prefix_bias_t` = double in a float build), evaluated at the
    end of every step from the corrected state.

    The harness reads `argv[1]`: int32 `T`, then `x0` (`n` words), then per step `u`
    (`m` words), `y` (`p` words) and one byte of open-circuit flags; it writes to
    `argv[2]` per step `x` (`n` words), `r` (`p` words), four bytes (in use, healthy,
    wire break, state ok), the uint32 input-fault mask and the uint16 saturation count,
    then the `q` bias values if any. With a third argument `repeat` it runs the playback that many times
    (for instruction counting) and writes the last.
    """
    if not prefix.isidentifier():
        raise ValueError(f"`generate_c(prefix={prefix!r})`: the prefix must be a C identifier.")
    s = observer.system
    n, m, p = s.n_states, s.n_inputs, s.n_outputs
    P = prefix.upper()
    fixed = isinstance(observer, FixedObserver)
    if layout not in ("rows", "columns") or (fixed and layout == "columns"):
        raise ValueError(f"`generate_c(layout={layout!r})`: expected 'rows', or 'columns' "
                         f"for a FloatObserver.")
    columns = layout == "columns"
    supervision = supervision or ("lanes" if columns else "branches")
    if supervision not in ("branches", "lanes") or (fixed and supervision == "lanes"):
        raise ValueError(f"`generate_c(supervision={supervision!r})`: expected 'branches', or "
                         f"'lanes' for a FloatObserver.")
    lanes_sup = supervision == "lanes"
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
    if columns and (vector_bytes < size or vector_bytes % size):
        raise ValueError(f"`generate_c(vector_bytes={vector_bytes})`: expected a multiple of "
                         f"the {size}-byte word.")
    W = -(-n * size // vector_bytes) * vector_bytes // size if columns else n   # lanes
    xdim = f"{P}_W" if columns else f"{P}_N"
    # an observer without inputs (lag compensation of the only input) takes a pointer it
    # never reads: C has no zero-size arrays
    u_param = f"u[{P}_M]" if m else "*u"
    h = [f"/* Generated by thermojax.reference.generate_c: do not edit. */",
         f"#ifndef {P}_H", f"#define {P}_H", "#include <stdint.h>",
         f"#define {P}_N {n}", f"#define {P}_M {m}", f"#define {P}_P {p}",
         f"typedef {word} {prefix}_word_t;",
         f"void {prefix}_reset(const {prefix}_word_t x0[{P}_N]);",
         f"uint8_t {prefix}_step(const {prefix}_word_t {u_param}, const {prefix}_word_t "
         f"y[{P}_P], uint8_t open_mask);",
         *([f"#define {P}_W {W}   /* lanes of the column sums: n rows padded to "
            f"{vector_bytes} bytes */"]
           if columns else []),
         f"extern {prefix}_word_t {prefix}_x[{xdim}];" +
         ("   /* the n states, then zeros */" if columns else ""),
         f"extern {prefix}_word_t {prefix}_r[{P}_P];",
         f"extern uint8_t {prefix}_healthy, {prefix}_wire_break;",
         f"extern uint8_t {prefix}_state_ok;   /* 1: every state finite and within the "
         f"limits, no saturation */",
         f"extern uint32_t {prefix}_input_fault;   /* inputs held at their last good value "
         f"this step */",
         f"extern uint16_t {prefix}_saturations;   /* steps with a saturated state (fixed "
         f"point), up to 65535 */",
         f"/* coefficient tables (column-major), for inspection: {prefix}_table({P}_TABLE_PHI) */",
         f"#define {P}_TABLE_PHI 0", f"#define {P}_TABLE_B0 1", f"#define {P}_TABLE_B1 2",
         f"#define {P}_TABLE_CY 3", f"#define {P}_TABLE_DY 4", f"#define {P}_TABLE_GAIN 5",
         f"const void *{prefix}_table(unsigned id);"]
    biases = getattr(observer, "biases", None)
    q = 0 if biases is None else biases.n_channels
    bias_word = "int32_t" if fixed else "double"
    if q:
        h += [f"/* bias channels: {', '.join(map(comment_safe, biases.names))} */", f"#define {P}_Q {q}",
              f"typedef {bias_word} {prefix}_bias_t;",
              f"extern {prefix}_bias_t {prefix}_bias[{P}_Q];"]
    h += [f"#endif", ""]
    c = [f"/* Generated by thermojax.reference.generate_c: do not edit.", "",
         f"   Observer in filter form with first-order-hold inputs:",
         f"     x-[k] = Phi x[k-1] + B0 u[k-1] + B1 u[k]   (skipped at the first step)",
         f"     x[k]  = x-[k] + L_S (y[k] - C x-[k] - D u[k]),  S = channels in use.",
         *([f"   Column layout: the prediction and the correction are sums over the nonzero",
            f"   columns ({P}_COLS), all rows at once (lanes, for SIMD); per row the same",
            f"   left-to-right sum as thermojax.reference, up to the sign of an exact zero;",
            f"   inputs must be finite (see thermojax.reference.generate_c)."] if columns else
           [f"   Straight-line code: each row's sum runs left to right over its nonzero",
            f"   coefficients only (literals), exactly as thermojax.reference does it."])]
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
    st, inp, out = _names(observer if names is None else names, n, m, p)
    lim = (observer.limit_codes if fixed else
           np.tile(np.asarray(fc.limits, float), (p, 1)))
    rails = observer.rail_codes if fixed else fc.rails_array(p)
    thr = observer.threshold_codes if fixed else fc.threshold_array(p)
    if fixed:
        cf, sh = observer.coef, observer.shift
        c.append(f"typedef char {prefix}_asr_check[((-3) >> 1) == -2 ? 1 : -1]; "
                 f"/* arithmetic >> */")
        c += [f"#define {P}_WMIN ({F.word_min})", f"#define {P}_WMAX ({F.word_max})",
              f"#define {P}_F_PRED {observer.f_pred}", f"#define {P}_F_OUT {observer.f_out}",
              f"#define {P}_F_GAIN {observer.f_gain}", ""]
        tables = {"PHI": cf["Phi"], "B0": cf["B0"], "B1": cf["B1"], "CY": cf["C"],
                  "DY": cf["D"], "GAIN": cf["L"]}
        # the step's literals: integer codes with the alignment 2**shift folded in (exact)
        pred_M = np.hstack([cf["Phi"] << sh["Phi"], cf["B0"] << sh["B0"],
                            cf["B1"] << sh["B1"]])
        out_M = np.hstack([cf["C"] << sh["C"], cf["D"] << sh["D"]])
        gain_M = cf["L"]
    else:
        dt = np.float64 if word == "double" else np.float32
        tables = {"PHI": np.asarray(s.Phi, dt), "B0": np.asarray(s.B0, dt),
                  "B1": np.asarray(s.B1, dt), "CY": np.asarray(s.C, dt),
                  "DY": np.asarray(s.D, dt), "GAIN": np.asarray(s.gain_table, dt)}
        pred_M = np.hstack([tables["PHI"], tables["B0"], tables["B1"]])
        out_M = np.hstack([tables["CY"], tables["DY"]])
        gain_M = tables["GAIN"]
    c += ["/* The coefficient tables, column by column (M[j][i] is row i, column j), for",
          f"   inspection and checksums through {prefix}_table(); the step below does not",
          f"   read them: it has the same numbers "
          f"{f'in {P}_COLS' if columns else 'as literals'}. */"]
    for name, M in tables.items():
        c.append(_array(f"{P}_{name}", word, _colmajor(M), "int" if fixed else word))
    bias_tables = _bias_tables(biases, fixed) if q else {}
    for name, (ctype, vals) in bias_tables.items():
        c.append(_array(f"{P}_{name}", ctype, vals, "int64_t" if ctype == "int64_t" else
                        ("int" if ctype != "double" else "double")))
    c += [f"const void *{prefix}_table(unsigned id) {{",
          "    switch (id) {"]
    c += [f"    case {P}_TABLE_{name}: return {P}_{name};" for name in tables]
    c += [f"    case {6 + k}: return {P}_{name};   /* {P}_TABLE_{name} */"
          for k, name in enumerate(bias_tables)]
    c += ["    default: return 0;", "    }", "}", ""]
    if fixed:
        c += [f"static int64_t {prefix}_rnd(int64_t a, int s) {{",
              f"    return (a + ((int64_t)1 << (s - 1))) >> s;   /* s > 0 */", "}",
              f"static {word} {prefix}_sat(int64_t a) {{",
              f"    return ({word})(a < {P}_WMIN ? {P}_WMIN : a > {P}_WMAX ? {P}_WMAX : a);",
              "}",
              f"static uint8_t {prefix}_clamped;",
              f"static {word} {prefix}_satx(int64_t a) {{   /* a state: saturation counted */",
              f"    if (a < {P}_WMIN || a > {P}_WMAX) {prefix}_clamped = 1;",
              f"    return {prefix}_sat(a);", "}", ""]
    if fixed and q:
        c += [f"static int64_t {prefix}_clamp(int64_t a, int64_t lo, int64_t hi) {{",
              "    return a < lo ? lo : a > hi ? hi : a;", "}",
              f"static int32_t {prefix}_sat32(int64_t a) {{",
              "    return (int32_t)(a < INT32_MIN ? INT32_MIN : a > INT32_MAX ? INT32_MAX : a);",
              "}", ""]
    if lanes_sup:   # the lane-parallel supervision (`channel_rules`)
        lanes = 1 << (p - 1).bit_length()
        sup = _lane_supervision_c(prefix, word, p, lanes, [f"r{j}" for j in range(p)], lim,
                                  rails, thr, fc)
        c += sup[0]
    if m > 32:
        raise ValueError(f"`generate_c`: {m} inputs; the input-fault mask holds 32.")
    wl = (lambda v: _lit(v, "int")) if fixed else (lambda v: _readable_lit(v, word))
    ulit = wl
    if fixed:
        u_lim, x_lim, u_start = (observer.input_limit_codes, observer.state_limit_codes,
                                 observer.u_start)
    else:
        u_lim, x_lim, u_start = (observer.input_limits, observer.state_limits,
                                 observer.u_start)
    state_check = [f"/* every state strictly inside the plausibility limits (False for NaN) */",
                   f"static uint8_t {prefix}_in_range(void) {{",
                   "    return (uint8_t)(" + "\n        && ".join(
                       f"({wl(x_lim[i][0])} < {prefix}_x[{i}] && {prefix}_x[{i}] < "
                       f"{wl(x_lim[i][1])})" for i in range(n)) + ");", "}"]
    if q:
        c += [f"{bias_word} {prefix}_bias[{P}_Q];"]
        nv = sum(len(v) for v in biases.evaluator._strain) if fixed else \
            sum(len(v) for v in biases._strain)
        if nv:
            c += [f"static {'int64_t' if fixed else 'double'} {prefix}_eps[{nv}];   "
                  "/* viscoelastic strain states */",
                  f"static {'int64_t' if fixed else 'double'} {prefix}_tprev[{P}_N];   "
                  "/* last step's temperatures of strain nodes */"]
    c += [f"{word} {prefix}_x[{xdim}];", f"{word} {prefix}_r[{P}_P];",
          f"uint8_t {prefix}_healthy, {prefix}_wire_break;",
          f"uint8_t {prefix}_state_ok;", f"uint32_t {prefix}_input_fault;",
          f"uint16_t {prefix}_saturations;",
          *([f"static {word} {prefix}_u_prev[{P}_M];   /* u[k-1]: the last good inputs */"]
            if m else []),
          *(sup[1] if lanes_sup else
            [f"static uint16_t {prefix}_good_run[{P}_P], {prefix}_bad_run[{P}_P];",
             f"static uint8_t {prefix}_ch_healthy;   /* channel health (the supervision's) */"]),
          f"static uint8_t {prefix}_started;", "",
          *state_check, "",
          f"void {prefix}_reset(const {word} x0[{P}_N]) {{",
          f"    int i;",
          f"    for (i = 0; i < {P}_N; i++) {prefix}_x[i] = x0[i];",
          *(sup[2] if lanes_sup else
            [f"    for (i = 0; i < {P}_P; i++) {{ {prefix}_good_run[i] = 0; "
             f"{prefix}_bad_run[i] = 0; }}"]),
          *([] if lanes_sup else [f"    {prefix}_ch_healthy = (uint8_t)((1u << {P}_P) - 1u);"]),
          *[f"    {prefix}_u_prev[{j}] = {ulit(u_start[j])};   /* held until a good sample */"
            for j in range(m)],
          f"    {prefix}_input_fault = 0; {prefix}_saturations = 0;",
          f"    {prefix}_state_ok = {prefix}_in_range();",
          f"    {prefix}_healthy = {prefix}_state_ok ? (uint8_t)((1u << {P}_P) - 1u) : 0u;",
          f"    {prefix}_wire_break = 0;", f"    {prefix}_started = 0;", "}", ""]
    lit = (lambda v: _lit(v, "int64_t")) if fixed else (lambda v: _readable_lit(v, word))
    xv = [f"{prefix}_x[{j}]" for j in range(n)]
    upv = [f"{prefix}_u_prev[{j}]" for j in range(m)]
    uv = [f"ug{j}" for j in range(m)]   # the inputs used: good samples or held values
    # columns: the prediction and correction update `P_x` in place (no stack copy)
    xmv = xv if columns else [f"xm{i}" for i in range(n)]
    rv = [f"r{j}" for j in range(p)]

    def total(row, vals, unit=None):
        """The left-to-right sum of a row's nonzero terms, or None when it has none.
        `unit`: the coefficient whose product is the value itself (1.0 in float)."""
        terms = [(v, vals[j]) for j, v in enumerate(row) if v != 0]
        if not terms:
            return None
        text = ""
        for k, (v, name) in enumerate(terms):
            mag, neg = abs(v), v < 0
            prod = name if (not fixed and mag == 1) else f"{lit(mag)} * {name}"
            if k == 0:
                text = ("-" if neg else "") + prod
            else:
                text += (" - " if neg else " + ") + prod
        return text

    def rounded(text, F_name, F_value):
        return f"{prefix}_rnd({text}, {P}_{F_name})" if F_value > 0 else f"({text})"

    cols = []                                           # the columns layout's table

    def column_sum(M, vals, what, indent):
        """Lane `i`'s sum over the nonzero columns of `M`, left to right, three terms a
        line (column `j` padded to `W` lanes is appended to `P_COLS`, `what(j)` names it
        there), or None."""
        terms = []
        for j in np.flatnonzero(np.any(M != 0, axis=0)):
            col = np.zeros(W, M.dtype)
            col[:M.shape[0]] = M[:, j]
            terms.append(f"{P}_COLS[{len(cols)}][i] * {vals[j]}")
            cols.append((col, what(j)))
        lines = [" + ".join(terms[k:k + 3]) for k in range(0, len(terms), 3)]
        return f"\n{indent}+ ".join(lines) or None

    at = len(c)                                         # P_COLS goes here, before the step
    c += [f"uint8_t {prefix}_step(const {word} {u_param}, const {word} y[{P}_P], "
          f"uint8_t open_mask) {{",
          *([] if m else ["    (void)u;   /* no inputs */"]),
          *([] if columns else [f"    {word} " + ", ".join(xmv) + ";   /* x-[k], then x[k] */"]),
          f"    {word} " + ", ".join(rv) + ";   /* residuals */",
          *([f"    int i;"] if columns or lanes_sup else []),
          f"    uint8_t mask = 0;",
          *([f"    {word} " + ", ".join(uv) + ";   /* the inputs used */"] if m else []),
          f"    /* untrusted inputs: outside the limits (exclusive; NaN never inside) an "
          f"input is held */",
          f"    {prefix}_input_fault = 0;",
          *[f"    if ({wl(u_lim[j][0])} < u[{j}] && u[{j}] < {wl(u_lim[j][1])}) {uv[j]} = u[{j}];"
            f"   /* {inp[j]} */"
            f"\n    else {{ {uv[j]} = {upv[j]}; {prefix}_input_fault |= UINT32_C({1 << j}); }}"
            for j in range(m)],
          *([f"    {prefix}_clamped = 0;"] if fixed else []),
          f"    if ({prefix}_started) {{"]
    if columns:
        pred_cols = ([f"Phi[:, {v}]" for v in st] + [f"B0[:, {v}]" for v in inp] +
                     [f"B1[:, {v}]" for v in inp])
        # read x, u[k-1] and u[k] into locals first: the loop then overwrites P_x
        locals_ = [f"x{j}" for j in range(n)] + [f"up{j}" for j in range(m)] + \
            [f"u{j}" for j in range(m)]
        e = column_sum(pred_M, locals_, lambda j: pred_cols[j], " " * 18)
        read = [f"{locals_[j]} = {v}" for j, v in enumerate(xv + upv + uv)
                if np.any(pred_M[:, j] != 0)]
        c += [f"        const {word} " + ", ".join(read[k:k + 6]) + ";"
              for k in range(0, len(read), 6)]
        c += [f"        /* x-[k] = Phi x + B0 u[k-1] + B1 u[k], column by column, lane i = "
              f"row i */", f"        for (i = 0; i < {P}_W; i++)",
              f"            {prefix}_x[i] = {_zero(word) if e is None else e};",
              "    }   /* first step: no prediction */"]
    else:
        for i in range(n):
            c.append(f"        /* x-[{st[i]}] = Phi[{st[i]}, :] x + B0[{st[i]}, :] u[k-1] "
                     f"+ B1[{st[i]}, :] u[k] */")
            e = total(pred_M[i], xv + upv + uv)
            if fixed:
                e = "0" if e is None else f"{prefix}_satx({rounded(e, 'F_PRED', observer.f_pred)})"
            else:
                e = _zero(word) if e is None else e
            c.append(f"        {xmv[i]} = {e};")
        c += ["    } else {   /* first step: no prediction */"]
        c += [f"        {xmv[i]} = {xv[i]};" for i in range(n)]
        c += ["    }"]
    for j in range(p):
        c.append(f"    /* r[{out[j]}] = y - C[{out[j]}, :] x- - D[{out[j]}, :] u[k] */")
        row = out_M[j]
        e = total(row, xmv + uv)
        if fixed:
            nzj = np.flatnonzero(row)
            if e is None:
                c.append(f"    {rv[j]} = y[{j}];")
            elif len(nzj) == 1 and row[nzj[0]] == 1 << observer.f_out:
                # rnd(2^F v, F) = v exactly
                c.append(f"    {rv[j]} = {prefix}_sat((int64_t)y[{j}] - {(xmv + uv)[nzj[0]]});")
            else:
                c.append(f"    {rv[j]} = {prefix}_sat((int64_t)y[{j}] - "
                         f"{rounded(e, 'F_OUT', observer.f_out)});")
        else:
            c.append(f"    {rv[j]} = y[{j}];" if e is None else f"    {rv[j]} = y[{j}] - ({e});")
    c += [f"    {prefix}_r[{j}] = {rv[j]};" for j in range(p)]
    # supervision, one block per channel, constants folded in (lanes: all at once)
    if lanes_sup:
        c += sup[3]
    for j in [] if lanes_sup else range(p):
        bit = 1 << j
        lo, hi = wl(lim[j][0]), wl(lim[j][1])
        c += [f"    /* channel {j} ({out[j]}): plausibility (limits exclusive), anti-windup, "
              f"wire break */",
              f"    if ((open_mask & {bit}u) || !({lo} < y[{j}] && y[{j}] < {hi})) {{",
              f"        {prefix}_ch_healthy &= (uint8_t)~{bit}u;",
              f"        {prefix}_good_run[{j}] = 0; {prefix}_bad_run[{j}] = 0;"]
        railed = []
        if rails[j][0] >= lim[j][0]:
            railed.append(f"y[{j}] <= {wl(rails[j][0])}")
        if rails[j][1] <= lim[j][1]:
            railed.append(f"y[{j}] >= {wl(rails[j][1])}")
        if railed:
            c += [f"    }} else if ({' || '.join(railed)}) {{",
                  f"        /* at an ADC rail: no correction, counters unchanged */"]
        c.append("    } else {" if railed else
                 "    } else {   /* (rails outside the plausible range: never railed) */")
        good = [f"if ({prefix}_good_run[{j}] < 65535u) {prefix}_good_run[{j}]++;",
                f"{prefix}_bad_run[{j}] = 0;",
                f"if (!({prefix}_ch_healthy & {bit}u) && {prefix}_good_run[{j}] >= "
                f"{int(fc.recover_after)}u) {{",
                f"    {prefix}_ch_healthy |= {bit}u; {prefix}_wire_break &= (uint8_t)~{bit}u;",
                "}"]
        never_large = (thr[j] >= -F.word_min) if fixed else not np.isfinite(thr[j])
        if never_large:
            c += [f"        /* (no residual threshold: never large) */"]
            c += [f"        {g}" for g in good]
        else:
            t = lit(thr[j]) if fixed else _readable_lit(thr[j], word)
            c += [f"        if ({rv[j]} > {t} || {rv[j]} < -{t}) {{",
                  f"            if ({prefix}_bad_run[{j}] < 65535u) {prefix}_bad_run[{j}]++;",
                  f"            {prefix}_good_run[{j}] = 0;",
                  f"            if ({prefix}_bad_run[{j}] >= {int(fc.wire_break_after)}u) {{",
                  f"                {prefix}_wire_break |= {bit}u; "
                  f"{prefix}_ch_healthy &= (uint8_t)~{bit}u;",
                  "            }",
                  *([f"            /* gated: a large residual is not used (but at the "
                     f"first step) */",
                     f"            if (!{prefix}_started && ({prefix}_ch_healthy & {bit}u)) "
                     f"mask |= {bit}u;"] if fc.gate else []),
                  "        } else {"]
            c += [f"            {g}" for g in good]
            if fc.gate:
                c += [f"            if ({prefix}_ch_healthy & {bit}u) mask |= {bit}u;"]
            c += ["        }"]
            if fc.gate:
                c += ["    }"]
                continue
        c += [f"        if ({prefix}_ch_healthy & {bit}u) mask |= {bit}u;", "    }"]
    # correction, one case per set of channels in use
    # columns: `& (2^p - 1)` with every case written tells gcc the jump table needs no
    # range check (mask < 2^p already)
    c += [f"    switch (mask{f' & {(1 << p) - 1}u' if columns else ''}) {{   "
          "/* x[k] = x-[k] + L_S r, S = the channels in use */"]
    for mask in range(1, 1 << p):
        used = [out[j] for j in range(p) if mask >> j & 1]
        c.append(f"    case {mask}:   /* {', '.join(used)} */")
        if columns:
            e = column_sum(gain_M[mask], rv, lambda j: f"L_{mask}[:, {out[j]}]", " " * 27)
            if e is not None:
                c += [f"        for (i = 0; i < {P}_W; i++)   /* L_S r, column by column */",
                      f"            {prefix}_x[i] = {prefix}_x[i] + ({e});"]
        for i in [] if columns else range(n):
            e = total(gain_M[mask][i], rv)
            if e is None:
                continue
            if fixed:
                c.append(f"        {xmv[i]} = {prefix}_satx((int64_t){xmv[i]} + "
                         f"{rounded(e, 'F_GAIN', observer.f_gain)});   /* L[{st[i]}, :] */")
            else:
                c.append(f"        {xmv[i]} = {xmv[i]} + ({e});   /* L[{st[i]}, :] */")
        c.append("        break;")
    c += [f"    {'case 0: ' if columns else ''}default:   /* no channel in use: prediction only */",
          "        break;", "    }"]
    if q:
        c += (_fixed_bias_c if fixed else _float_bias_c)(biases, prefix, xmv, uv, st)
    c += [] if columns else [f"    {xv[i]} = {xmv[i]};" for i in range(n)]
    c += [f"    {upv[j]} = {uv[j]};" for j in range(m)]
    c += [f"    {prefix}_started = 1;"]
    if fixed:
        c += [f"    if ({prefix}_clamped && {prefix}_saturations < 65535u) "
              f"{prefix}_saturations++;",
              f"    {prefix}_state_ok = (uint8_t)(!{prefix}_clamped && {prefix}_in_range());"]
    else:
        c += [f"    {prefix}_state_ok = {prefix}_in_range();"]
    c += ([f"    if (!{prefix}_state_ok) {prefix}_healthy = 0;   /* healthy: state in range */"]
          if lanes_sup else
          [f"    {prefix}_healthy = {prefix}_state_ok ? {prefix}_ch_healthy : 0u;   "
           "/* healthy: state in range */"])
    c += [f"    return mask;", "}", ""]
    if columns:
        rows = ["    {" + ", ".join(_readable_lit(v, word) for v in col) + "}" +
                ("," if k + 1 < len(cols) else "") + f"   /* {k}: {what} */"
                for k, (col, what) in enumerate(cols)]
        c[at:at] = [f"/* The nonzero columns of [Phi B0 B1] and of each L_S, rows padded to {P}_W",
                    "   lanes: the step's column-at-a-time sums read them. */",
                    f"static const {word} {P}_COLS[{len(cols)}][{P}_W] = {{", *rows, "};", ""]
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
        f"            uint8_t flags[4];",
        f"            flags[0] = {prefix}_step(u + k * {P}_M, y + k * {P}_P, oc[k]);",
        "            if (rep + 1 < repeat) continue;",
        f"            flags[1] = {prefix}_healthy; flags[2] = {prefix}_wire_break;",
        f"            flags[3] = {prefix}_state_ok;",
        f"            fwrite({prefix}_x, sizeof {prefix}_x[0], {P}_N, out);",
        f"            fwrite({prefix}_r, sizeof {prefix}_r[0], {P}_P, out);",
        "            fwrite(flags, 1, 4, out);",
        f"            fwrite(&{prefix}_input_fault, 4, 1, out);",
        f"            fwrite(&{prefix}_saturations, 2, 1, out);",
        *([f"            fwrite({prefix}_bias, sizeof {prefix}_bias[0], {P}_Q, out);"]
          if q else []), "        }", "    }",
        "    fclose(out); free(u); free(y); free(oc);", "    return 0;", "}", ""])
    return CSource(prefix, "\n".join(h), "\n".join(c), harness, word, size, n, m, p, q,
                   bias_word)


def pack_log(x0, u, y) -> bytes:
    """The input of a harness that reads `int32 T`, `double x0[n]`, then per sample
    `double u[m]` and `double y[p]` (the adaptive and the scheduled observers')."""
    rows = np.concatenate([np.asarray(u, np.float64), np.asarray(y, np.float64)], axis=1)
    return np.int32(rows.shape[0]).tobytes() + np.asarray(x0, np.float64).tobytes() + \
        rows.tobytes()

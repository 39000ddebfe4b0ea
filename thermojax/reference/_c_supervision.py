"""The channel supervision of the generated C in lanes (`generate_c(supervision="lanes")`,
the columns layout's default): every channel at once, branch free, its statements from
`channel_rules` (`_faults.py`). The rows layout's per-channel blocks with branches stay
in `generate_c`."""

from __future__ import annotations

import numpy as np

from ._c_literals import _readable_lit
from ._faults import COUNTER_MAX, _Lane, _var, channel_rules


def _lane_supervision_c(prefix, word, p, lanes, rv, lim, rails, thr, fc) -> tuple:
    """The channel supervision of `layout="columns"`: all channels at once, one loop over
    `lanes` (channel `j` in lane `j`, the rest padding), branch free, from
    `channel_rules` (the rules of `ChannelMonitor`, the rows layout's per-channel
    blocks). Returns `(tables, state, reset, step)` lines."""
    P = prefix.upper()
    # lane masks and counters as wide as a word: one vector length for the whole loop
    # (int32_t lanes for double cost 10 to 30 more instructions a step with AVX2)
    it = "int32_t" if word == "float" else "int64_t"
    fabs = "fabsf" if word == "float" else "fabs"
    lit = lambda v: _readable_lit(v, word)
    pad = lambda vals, fill: [*vals, *[fill] * (lanes - p)]
    has_rails = any(rails[j][0] >= lim[j][0] or rails[j][1] <= lim[j][1] for j in range(p))
    has_thr = bool(np.isfinite(thr).any())
    bits = [[(1 << j) << (8 * k) for j in range(p)] + [0] * (lanes - p) for k in range(3)]
    tables = [f"/* Channel supervision, lane j = channel j ({lanes} lanes, padding "
              f"lanes unused): the bits",
              "   of the in-use, healthy and wire-break masks; plausible range"
              + ("; rails" if has_rails else "") + ("; residual thresholds" if has_thr else "")
              + ". */",
              f"static const {it} {P}_SUP_BITS[3][{lanes}] = {{" +
              ", ".join("{" + ", ".join(f"0x{b:x}" for b in row) + "}" for row in bits) + "};"]
    rows = [("LO", [lim[j][0] for j in range(p)], 0.0), ("HI", [lim[j][1] for j in range(p)], 0.0)]
    if has_rails:
        rows += [("RLO", [rails[j][0] for j in range(p)], -np.inf),
                 ("RHI", [rails[j][1] for j in range(p)], np.inf)]
    if has_thr:
        rows += [("THR", list(thr), np.inf)]
    for name, vals, fill in rows:
        tables.append(f"static const {word} {P}_SUP_{name}[{lanes}] = {{" +
                      ", ".join(lit(v) for v in pad(vals, fill)) + "};")
    # the counters' limits, 0 in padding lanes (a constant that is not the same in every
    # lane stays a vector in memory: gcc -O3 builds a uniform one from an immediate)
    tables.append(f"static const {it} {P}_SUP_RUN[3][{lanes}] = {{" + ", ".join(
        "{" + ", ".join(pad([str(k)] * p, "0")) + "}"
        for k in (COUNTER_MAX, int(fc.wire_break_after) - 1, int(fc.recover_after) - 1)) +
        "};   /* run counter maximum, N - 1, M - 1 */")
    open_table = word == "float" and p <= 4   # (double: gcc vectorizes the bit test better)
    if open_table:   # open-circuit flags to lane masks: one row per value of the low p bits
        tables.append(f"static const {it} {P}_SUP_OPEN[{1 << p}][{lanes}] = {{" + ", ".join(
            "{" + ", ".join(pad(["-1" if o >> j & 1 else "0" for j in range(p)], "0")) + "}"
            for o in range(1 << p)) + "};")
    tables.append("")
    consts = {"max": f"{P}_SUP_RUN[0][i]", "N-1": f"{P}_SUP_RUN[1][i]",
              "M-1": f"{P}_SUP_RUN[2][i]"}
    sv = lambda name: f"{prefix}_sup_{name}[i]"
    v = {"healthy": _var("healthy", "h"), "good": _var("good", "g", False),
         # without a residual threshold no residual is large: `bad` stays 0 and the
         # wire-break flags stay down
         "wire_break": _var("wire_break", "w") if has_thr else _Lane.known(False),
         "bad": _var("bad", "b", False) if has_thr else _Lane.known(0, False),
         "plausible": _var("plausible", "pl"),
         "railed": _var("railed", "ra") if has_rails else _Lane.known(False),
         "large": _var("large", "lg") if has_thr else _Lane.known(False),
         "started": _var("started", "st")}
    stored = [("h", "healthy"), ("g", "good")] + \
        ([("w", "wire_break"), ("b", "bad")] if has_thr else [])
    body = [f"            {it} " + ", ".join(f"{s} = {sv(s)}" for s, _ in stored) + ";"]
    body += [f"            {it} pl = ~{P}_SUP_OPEN[open_mask & {(1 << p) - 1}u][i] & "
            f"(({P}_SUP_LO[i] < yl[i]) & (yl[i] < {P}_SUP_HI[i]) ? -1 : 0);" if open_table else
            f"            {it} pl = ((open_mask & {P}_SUP_BITS[0][i]) == 0) & "
            f"({P}_SUP_LO[i] < yl[i]) & (yl[i] < {P}_SUP_HI[i]) ? -1 : 0;"]
    if has_rails:
        body.append(f"            {it} ra = (yl[i] <= {P}_SUP_RLO[i]) | "
                    f"(yl[i] >= {P}_SUP_RHI[i]) ? -1 : 0;")
    if has_thr:
        body.append(f"            {it} lg = {fabs}(rl[i]) > {P}_SUP_THR[i] ? -1 : 0;")
    if has_thr and fc.gate:
        body.append(f"            {it} st = {prefix}_started ? -1 : 0;   /* gating from the "
                    "second step */")

    def bind(name, e):
        if e.const is not None or e.c.isidentifier():   # known, or a variable already
            return e
        body.append(f"            {it} {name} = {e.c};")
        return _var(name, flag=e.flag)

    new = channel_rules(v, int(fc.wire_break_after), int(fc.recover_after), bind, consts,
                        gate=fc.gate)
    body += [f"            {sv(s)} = {new[k].c};" for s, k in stored]
    body += [f"            bits |= ({new['in_use'].c} & {P}_SUP_BITS[0][i]) | "
             f"({new['healthy'].c} & {P}_SUP_BITS[1][i])" +
             (f"\n                  | ({new['wire_break'].c} & {P}_SUP_BITS[2][i]);" if has_thr
              else ";")]
    state = [f"static {it} " + ", ".join(f"{prefix}_sup_{s}[{lanes}]" for s, _ in stored) +
             ";   /* per channel: healthy" + (", wire break" if has_thr else "") +
             " (all ones or 0), good run" + (", bad run" if has_thr else "") + " */"]
    reset = [f"    for (i = 0; i < {lanes}; i++) {{ " +
             " ".join(f"{prefix}_sup_{s}[i] = {-1 if s == 'h' else 0};" for s, _ in stored) +
             " }"]
    step = [f"    {{   /* channel supervision (FaultConfig), all channels at once: lane j = "
            f"channel j */",
            f"        {word} yl[{lanes}]" + (f", rl[{lanes}];" if has_thr else ";"),
            f"        {it} bits = 0;   /* in-use, healthy and wire-break masks, 8 bits apart */"]
    step += [f"        yl[{j}] = y[{j}];" for j in range(p)]
    step += [f"        yl[{j}] = y[{p - 1}];" for j in range(p, lanes)]   # padding: any value
    if has_thr:
        step += [f"        rl[{j}] = {rv[j]};" for j in range(p)]
        step += [f"        rl[{j}] = {rv[p - 1]};" for j in range(p, lanes)]
    step += [f"        for (i = 0; i < {lanes}; i++) {{", *body, "        }",
             f"        mask = (uint8_t)bits;",
             f"        {prefix}_healthy = (uint8_t)(bits >> 8);",
             *([f"        {prefix}_wire_break = (uint8_t)(bits >> 16);"] if has_thr else
               [f"        /* ({prefix}_wire_break stays 0: no residual threshold) */"]),
             "    }"]
    return tables, state, reset, step

"""The bias channels in the generated C (`generate_c` of an observer built with
`biases=`, see `_bias.py`): their coefficient tables, and the statements that evaluate
them after the correction, in double in the operation order of `BiasEvaluator.step`
(`_float_bias_c`) or in integers as `FixedBiasEvaluator` (`_fixed_bias_c`)."""

from __future__ import annotations

import numpy as np

from ._c_literals import _lit, comment_safe


def _bias_tables(biases, fixed) -> dict:
    """Coefficient tables of the bias channels, for inspection (`prefix_table(6 + k)`)."""
    if fixed:
        width = max(len(ch["poly"]) for ch in biases.channels)
        poly = np.zeros((biases.n_channels, width), np.int64)
        for c, ch in enumerate(biases.channels):
            poly[c, :len(ch["poly"])] = ch["poly"]
        frac = np.array([[ch["g"], ch["h"]] for ch in biases.channels], np.int64)
        out = {"BIAS_POLY": ("int64_t", poly), "BIAS_FRAC": ("int64_t", frac)}
        if biases.strains:
            out["BIAS_STRAIN"] = ("int64_t", np.array([[s[2], s[3], s[4]] for s in
                                                      biases.strains], np.int64))
        return out
    width = max(max(len(ch.poly), 1) for ch in biases.channels)
    poly = np.zeros((biases.n_channels, width))
    for c, ch in enumerate(biases.channels):
        poly[c, :len(ch.poly)] = ch.poly
    out = {"BIAS_POLY": ("double", poly)}
    strains = [s[1:4] for coef in biases._strain for s in coef]
    if strains:
        out["BIAS_STRAIN"] = ("double", np.array(strains))
    return out


def _dlit(v) -> str:
    """A double literal, exact (hexadecimal), parenthesized when negative."""
    text = _lit(v, "double")
    return f"({text})" if text.startswith("-") else text


def _float_bias_c(ev, prefix, xmv, uv, st) -> list:
    """The bias channels in double, operation for operation as `BiasEvaluator.step`."""
    need_x, need_u = set(), set()
    for ch in ev.channels:
        need_x.add(ch.node)
        for a, b, _ in ch.gradients:
            need_x |= {a, b}
    for node in ev._rate_nodes:
        for j, _ in ev._rate_terms[node]:
            (need_x.add(j) if j >= 0 else need_u.add(-1 - j))
    for coef in ev._strain:
        need_x |= {s[0] for s in coef}
    bx = {i: f"bx{i}" for i in sorted(need_x)}
    bu = {j: f"bu{j}" for j in sorted(need_u)}
    c = [f"    {{   /* bias channels, double, in the order of BiasEvaluator.step */"]
    c += [f"        double {bx[i]} = {xmv[i]};" for i in bx]
    c += [f"        double {bu[j]} = {uv[j]};" for j in bu]
    for node in ev._rate_nodes:
        terms = [f"{_dlit(v)} * {bx[j] if j >= 0 else bu[-1 - j]}"
                 for j, v in ev._rate_terms[node]]
        c.append(f"        double rate{node} = {' + '.join(terms) if terms else '0.0'};"
                 f"   /* d{st[node]}/dt */")
    c.append("        double d, b;" if any(ch.poly for ch in ev.channels) else "        double b;")
    v_all = 0
    for k, (ch, coef) in enumerate(zip(ev.channels, ev._strain)):
        c.append(f"        /* {comment_safe(ch.name)} */")
        first = v_all
        for v, (node, a, w1, w0, _) in enumerate(coef):
            e = f"{prefix}_eps[{first + v}]"
            c += [f"        if ({prefix}_started) {e} = {_dlit(a)} * {e} + {_dlit(w1)} * "
                  f"{bx[node]} + {_dlit(w0)} * {prefix}_tprev[{node}];",
                  f"        else {e} = {bx[node]};"]
        if ch.poly:
            c.append(f"        d = {bx[ch.node]} - 25.0;")
            c.append(f"        b = {_dlit(ch.poly[-1])};")
            for cp in reversed(ch.poly[:-1]):
                c.append(f"        b = b * d + {_dlit(cp)};")
        else:
            c.append("        b = 0.0;")
        for ia, ib, dg in ch.gradients:
            c.append(f"        b = b + {_dlit(dg)} * ({bx[ia]} - {bx[ib]});")
        for n_, e_ in ch.rates:
            c.append(f"        b = b + {_dlit(e_)} * rate{n_};")
        for v, (node, _, _, _, kk) in enumerate(coef):
            c.append(f"        b = b + {_dlit(kk)} * ({bx[node]} - {prefix}_eps[{first + v}]);")
        c.append(f"        {prefix}_bias[{k}] = b;")
        v_all += len(coef)
    nodes = sorted({s[0] for coef in ev._strain for s in coef})
    c += [f"        {prefix}_tprev[{i}] = {bx[i]};" for i in nodes]
    c.append("    }")
    return c


def _fixed_bias_c(fb, prefix, xmv, uv, st) -> list:
    """The bias channels in integers, operation for operation as `FixedBiasEvaluator`."""
    P = prefix.upper()
    L = lambda v: f"INT64_C({int(v)})"
    need = {ch["node"] for ch in fb.channels}
    need |= {i for ch in fb.channels for kind, i, _ in ch["ops"] if kind == "x"}
    need |= {s[1] for s in fb.strains}
    s = fb.f_t - fb.f_k
    sh_e, f_d = fb.f_e - fb.f_t, fb.f_e - fb.f_d
    c = [f"    {{   /* bias channels, fixed point (FixedBiasEvaluator): temperatures",
         f"           th = T - 25 degC at {fb.f_t} fractional bits, clamped to the limits */"]
    for i in sorted(need):
        conv = (f"(int64_t){xmv[i]} * {L(1 << s)}" if s >= 0 else
                f"{prefix}_rnd((int64_t){xmv[i]}, {-s})")
        c.append(f"        int64_t th{i} = {prefix}_clamp({conv} + {L(fb.theta_offset[i])}, "
                 f"{L(fb.theta_lo)}, {L(fb.theta_hi)});   /* {st[i]} */")
    if fb.strains:
        c.append("        int64_t E, d1, d0;")
        c.append(f"        int64_t " + ", ".join(f"e{v}" for v in range(len(fb.strains))) + ";")
    c.append("        int64_t acc, lin;")
    for v, (ch_i, node, W1, W0, fw, k, *_r) in enumerate(fb.strains):
        e = f"{prefix}_eps[{v}]"
        inc = f"{L(W1)} * d1 + {L(W0)} * d0"
        inc = f"{prefix}_rnd({inc}, {fw - 30})" if fw > 30 else f"({inc})"
        c += [f"        /* strain {v} on {st[node]} ({comment_safe(fb.channels[ch_i]['name'])}) */",
              f"        if ({prefix}_started) {{",
              f"            E = {e};",
              f"            d1 = {prefix}_rnd(th{node} * {L(1 << sh_e)} - E, {f_d});",
              f"            d0 = {prefix}_rnd({prefix}_tprev[{node}] * {L(1 << sh_e)} - E, {f_d});",
              f"            {e} = {prefix}_clamp(E + {inc}, {L(fb.E_lo)}, {L(fb.E_hi)});",
              f"        }} else {{",
              f"            {e} = th{node} * {L(1 << sh_e)};",
              "        }",
              f"        e{v} = {prefix}_rnd({e}, {sh_e});"]
    for k, ch in enumerate(fb.channels):
        Pc = ch["poly"]
        c.append(f"        /* {comment_safe(ch['name'])}: {ch['g']} fractional bits; linear sum "
                 f"at {ch['h']} */")
        c.append(f"        acc = {L(Pc[-1])};")
        for cp in reversed(Pc[:-1]):
            c.append(f"        acc = {prefix}_rnd(acc * th{ch['node']}, 31) + {L(cp)};")
        terms = [f"{L(qq)} * " + (f"th{i}" if kind == "x" else f"(int64_t){uv[i]}"
                                  if kind == "u" else f"e{i}")
                 for kind, i, qq in ch["ops"]]
        c.append(f"        lin = {' + '.join(terms) if terms else 'INT64_C(0)'};")
        sh = ch["h"] - ch["g"]
        lin = f"{prefix}_rnd(lin, {sh})" if sh > 0 else "lin"
        c.append(f"        {prefix}_bias[{k}] = {prefix}_sat32(acc + {lin});")
    nodes = sorted({s_[1] for s_ in fb.strains})
    c += [f"        {prefix}_tprev[{i}] = th{i};" for i in nodes]
    c.append("    }")
    return c

"""The docs alone determine the exported observer (issue 65 item 4).

A small second implementation of `thermojax export`, written from docs/observer.md
(sections 2, 4, 5, 6 and 8) and docs/formats.md only, with NumPy and SciPy: it reads the
model file with `tomllib`, builds `A`, `B`, `C`, `D`, discretizes, designs the gains,
derives the offsets, limits and fixed-point codes, and compares them with the artifact
the command line writes. Nothing of thermojax is imported: the artifact is made by
running `python -m thermojax export` and read as plain files (`observer.json`,
`observer.npz`, the generated C for the fixed-point bias constants).

Floating-point arrays agree to roundoff (section 4 says so: the design is reproduced to
roundoff, not bit for bit: here within 1e-8 of the largest entry, observed 1e-15 for
the discrete model and 1e-10 for the gains); integer codes and fractional bits agree
exactly, both when quantized from the artifact's own float arrays and from this
reimplementation's.
"""

import itertools
import json
import math
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
import scipy.signal

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"

RTOL = 1e-8   # design arrays: roundoff of two implementations


def export(tmp_path, name, model, *flags):
    out = tmp_path / name
    run = subprocess.run([sys.executable, "-m", "thermojax", "export", "--model", str(model),
                          "--out", str(out), "--quiet", *flags],
                         capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert run.returncode == 0, run.stderr
    meta = json.loads((out / "observer.json").read_text(encoding="utf-8"))
    with np.load(out / "observer.npz") as z:
        arrays = {k: z[k] for k in z.files}
    return out, meta, arrays


# -- section 2: the continuous model and its discretization -------------------------------

def _value(v):
    return float(v["value"] if isinstance(v, dict) else v)


def continuous_model(path: Path) -> dict:
    """`A`, `B`, `C`, `D`, names, holds and noises of a linear model file (docs/observer.md
    §2, docs/formats.md §2)."""
    doc = tomllib.loads(path.read_text())
    nodes = [n["name"] for n in doc["nodes"]]
    idx = {nm: i for i, nm in enumerate(nodes)}
    n = len(nodes)
    c = np.array([_value(nd["capacitance"]) for nd in doc["nodes"]])
    inputs, holds = [], []
    for entry in (*doc.get("boundaries", []), *doc.get("heat_inputs", [])):
        if entry["input"] not in inputs:
            inputs.append(entry["input"])
            holds.append(entry.get("hold", "foh"))
    powers = {h["input"] for h in doc.get("heat_inputs", [])}
    m = len(inputs)
    K, G = np.zeros((n, n)), np.zeros((n, m))
    for link in doc.get("links", []):
        a, b = (idx[v] for v in link["between"])
        g = _value(link["conductance"])
        e = np.zeros(n)
        e[a], e[b] = 1.0, -1.0
        K += g * np.outer(e, e)
    for bd in doc.get("boundaries", []):
        i, g = idx[bd["node"]], _value(bd["conductance"])
        K[i, i] += g
        G[i, inputs.index(bd["input"])] += g
    for h in doc.get("heat_inputs", []):
        G[idx[h["node"]], inputs.index(h["input"])] += _value(h["gain"])
    sensors = doc["sensors"]
    C = np.zeros((len(sensors), n))
    for s, sensor in enumerate(sensors):
        C[s, idx[sensor["node"]]] = 1.0
    q = np.array([_value(nd.get("process_noise", 1e-3)) for nd in doc["nodes"]])
    r = np.array([_value(sn.get("noise", 0.01)) for sn in sensors])
    return {"doc": doc, "nodes": nodes, "inputs": inputs, "holds": holds,
            "powers": [j for j, col in enumerate(inputs) if col in powers],
            "sensors": [sn["column"] for sn in sensors],
            "A": -K / c[:, None], "B": G / c[:, None], "C": C, "D": np.zeros((len(sensors), m)),
            "q": q, "noise": r}


def discretize(A, B, holds, dt):
    n, m = B.shape
    M = np.zeros((n + 2 * m, n + 2 * m))
    M[:n, :n], M[:n, n:n + m], M[n:n + m, n + m:] = A * dt, B * dt, np.eye(m)
    E = scipy.linalg.expm(M)
    Phi, G0, G1 = E[:n, :n], E[:n, n:n + m], E[:n, n + m:]
    foh = np.array([h == "foh" for h in holds])
    B0 = np.where(foh, G0 - G1, G0)
    B1 = np.where(foh, G1, 0.0)
    return Phi, B0, B1


# -- section 4: the gains ------------------------------------------------------------------

def process_covariance(A, q, dt):
    n = A.shape[0]
    j = max(0, math.ceil(math.log2(np.linalg.norm(A, 1) * dt)))
    h = dt / 2.0 ** j
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n], M[:n, n:], M[n:, n:] = -A * h, np.diag(q ** 2) * h, A.T * h
    E = scipy.linalg.expm(M)
    Phi = E[n:, n:].T
    Qd = Phi @ E[:n, n:]
    Qd = 0.5 * (Qd + Qd.T)
    for _ in range(j):
        Qd = Qd + Phi @ Qd @ Phi.T
        Qd = 0.5 * (Qd + Qd.T)
        Phi = Phi @ Phi
    return Qd


def kalman_gain(Phi, C, Qd, noise):
    R = np.diag(noise ** 2)
    P = scipy.linalg.solve_discrete_are(Phi.T, C.T, Qd, R)
    P = 0.5 * (P + P.T)
    return np.linalg.solve(C @ P @ C.T + R, C @ P).T


def observability_rank(Phi, C):
    blocks, block = [], C
    for _ in range(Phi.shape[0]):
        norm = np.linalg.norm(block)
        blocks.append(block / norm if norm > 0 else block)
        block = block @ Phi
    s = np.linalg.svd(np.concatenate(blocks), compute_uv=False)
    return int(np.sum(s > 1e-10 * s.max()))


def pole_rule(A, dt, speedup):
    lam = np.sort(np.linalg.eigvals(A).real)[::-1]   # slowest first
    tau_min = 5 * dt
    s = []
    for v in lam:
        if -1 / v <= tau_min:
            s.append(v)
        elif speedup * abs(v) > 1 / tau_min:
            s.append(-1 / tau_min)
        else:
            s.append(speedup * v)
    s = np.array(s)
    for i in range(1, len(s)):
        while np.any(np.abs(s[:i] - s[i]) <= 1e-6 * np.abs(s[i])):
            s[i] *= 0.98
    return s, np.exp(s * dt)


def placed_gain(Phi, C, z):
    """The placed gain, or None where docs/observer.md §4 says the subset falls back."""
    n = Phi.shape[0]
    if observability_rank(Phi, C) < n or np.max(np.abs(z)) >= 1:
        return None
    if np.any(np.abs(z) > np.max(np.abs(np.linalg.eigvals(Phi))) * (1 + 1e-9)):
        return None
    try:
        L = scipy.signal.place_poles(Phi.T, (C @ Phi).T, z, method="YT").gain_matrix.T
    except ValueError:
        return None
    achieved = list(np.linalg.eigvals(Phi - L @ C @ Phi))
    for want in sorted(z, key=lambda v: -abs(v)):
        k = int(np.argmin([abs(a - want) for a in achieved]))
        if abs(achieved.pop(k) - want) / max(abs(want), 1e-12) > 1e-6:
            return None
    return L


def gain_table(Phi, C, A, q, noise, dt, method, speedup=4.0):
    n, p = Phi.shape[0], C.shape[0]
    table = np.zeros((1 << p, n, p))
    methods = {}
    Qd = process_covariance(A, q, dt)
    z = pole_rule(A, dt, speedup)[1] if method == "poles" else None
    for r in range(1, p + 1):
        for S in itertools.combinations(range(p), r):
            S = list(S)
            mask = sum(1 << j for j in S)
            L = placed_gain(Phi, C[S], z) if method == "poles" else None
            methods[mask] = "poles" if L is not None else "kalman"
            if L is None:
                L = kalman_gain(Phi, C[S], Qd, noise[S])
            table[mask][:, S] = L
    return table, methods


# -- sections 5 and 6: offsets, limits, fixed point -------------------------------------------

FORMATS = {"q16.16": (32, 16, 1.0), "q8.24": (32, 24, 1.0), "q15": (16, 15, 128.0),
           "q31": (32, 31, 128.0)}


def input_limits(Phi, B0, B1, C, D, powers, limits=(-55.0, 125.0)):
    G = C @ np.linalg.pinv(np.eye(Phi.shape[0]) - Phi, rcond=1e-10) @ (B0 + B1) + D
    out = []
    for j in range(B0.shape[1]):
        if j in powers:
            g = np.max(np.abs(G[:, j]))
            w = (limits[1] - limits[0]) / g if g > 0 else np.inf
            out.append([-w, w])
        else:
            out.append(list(limits))
    return np.array(out)


def quantize(M, frac, word_bits):
    lo, hi = -(1 << (word_bits - 1)), (1 << (word_bits - 1)) - 1
    for h in range(frac + 1):
        Mq = np.floor(M * 2.0 ** (frac - h) + 0.5)
        if Mq.size == 0 or (Mq.min() >= lo and Mq.max() <= hi):
            return Mq.astype(np.int64), frac - h
    raise AssertionError("does not fit")


def fixed_codes(arrays, fmt, u_scale):
    """`{name: (codes, frac_bits)}` of section 6 from float arrays."""
    w, F, scale = FORMATS[fmt]
    col = u_scale / scale
    scaled = {"Phi": arrays["Phi"], "B0": arrays["B0"] * col, "B1": arrays["B1"] * col,
              "C": arrays["C"], "D": arrays["D"] * col, "L": arrays["gain_table"]}
    out = {}
    for group in (("Phi", "B0", "B1"), ("C", "D"), ("L",)):
        for headroom in range(F + 1):
            got = {nm: quantize(scaled[nm], F - headroom, w) for nm in group}
            top = max(fr for _, fr in got.values())
            worst = sum(np.abs(qm).sum(axis=-1) * 2.0 ** (top - fr) for qm, fr in got.values())
            if np.max(worst * 2.0 ** (w - 1)) < 2.0 ** 62:
                break
        out.update(got)
    return out


# -- the checks -----------------------------------------------------------------------------

def close(a, b, rtol=RTOL):
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape
    scale = max(np.abs(b).max(initial=0.0), 1e-300)
    return np.abs(a - b).max(initial=0.0) <= rtol * scale


def check_design(model_path, meta, arrays, method, fmt, speedup=4.0, power_scale=1.0):
    mdl = continuous_model(model_path)
    dt = 1.0 / meta["rate_hz"]
    assert [s["name"] for s in meta["states"]] == mdl["nodes"]
    assert [i["name"] for i in meta["inputs"]] == mdl["inputs"]
    assert [i["hold"] for i in meta["inputs"]] == mdl["holds"]
    assert [i["units"] for i in meta["inputs"]] == [
        "W" if j in mdl["powers"] else "°C" for j in range(len(mdl["inputs"]))]
    assert [o["name"] for o in meta["outputs"]] == mdl["sensors"]
    Phi, B0, B1 = discretize(mdl["A"], mdl["B"], mdl["holds"], dt)
    mine = {"Phi": Phi, "B0": B0, "B1": B1, "C": mdl["C"], "D": mdl["D"]}
    for name, a in mine.items():
        assert close(a, arrays[name]), name
    table, methods = gain_table(Phi, mdl["C"], mdl["A"], mdl["q"], mdl["noise"], dt, method,
                                speedup)
    for s in meta["subsets"]:
        assert s["method"].split(" ")[0] == methods[s["mask"]], s
        assert s["observable_states"] == observability_rank(
            Phi, mdl["C"][[mdl["sensors"].index(c) for c in s["sensors"]]])
    assert close(table, arrays["gain_table"]), np.abs(table - arrays["gain_table"]).max()
    mine["gain_table"] = table
    # offsets and the starting estimate (section 2 and 6)
    m = len(mdl["inputs"])
    x_ref = np.full(len(mdl["nodes"]), 35.0)
    u_ref = np.array([0.0 if j in mdl["powers"] else 35.0 for j in range(m)])
    u_steady = np.array([0.0 if j in mdl["powers"] else 25.0 for j in range(m)])
    assert np.array_equal(arrays["x_ref"], x_ref) and np.array_equal(arrays["u_ref"], u_ref)
    assert close(mdl["C"] @ x_ref + mdl["D"] @ u_ref, arrays["y_ref"])
    assert np.array_equal(arrays["u_steady"], u_steady)
    assert close(np.linalg.solve(mdl["A"], -mdl["B"] @ u_steady), arrays["x_steady"])
    # supervision defaults (section 5)
    f = meta["faults"]
    assert f["limits_C"] == [-55.0, 125.0]
    assert (f["wire_break_after"], f["recover_after"], f["gate"]) == (10, 20, False)
    lim = input_limits(Phi, B0, B1, mdl["C"], mdl["D"], mdl["powers"])
    assert close(lim, np.array(f["input_limits"], float))
    # fixed point (section 6)
    w, F, scale = FORMATS[fmt]
    u_scale = np.array([power_scale if j in mdl["powers"] else scale for j in range(m)])
    assert np.array_equal(arrays["u_scale"], u_scale)
    fixed = meta["fixed"]
    assert (fixed["word_bits"], fixed["frac_bits"], fixed["state_scale_K"]) == (w, F, scale)
    from_artifact = fixed_codes(arrays, fmt, u_scale)
    from_mine = fixed_codes(mine, fmt, u_scale)
    for name, (codes, frac) in from_artifact.items():
        assert fixed["coefficient_frac_bits"][name] == frac, name
        assert np.array_equal(arrays[f"fixed_{name}"], codes), name
        # from the recomputed arrays too (they differ by roundoff, far from a rounding tie)
        assert from_mine[name][1] == frac, name
        assert np.array_equal(from_mine[name][0], codes), name
    return mdl, mine


def test_default_design(tmp_path):
    """Kalman gains (section 4), Q16.16 (section 6)."""
    model = CONFIGS / "imu6.toml"
    _, meta, arrays = export(tmp_path, "default", model, "--rate", "20", "--fixed", "q16.16")
    assert meta["method"] == "kalman"
    check_design(model, meta, arrays, "kalman", "q16.16")


def test_pole_placement_design(tmp_path):
    """The seed's pole rule with its Kalman fallback (section 4), a non-default speedup
    and power scale, Q8.24."""
    model = CONFIGS / "imu6.toml"
    _, meta, arrays = export(tmp_path, "poles", model, "--rate", "20", "--method", "poles",
                             "--speedup", "3", "--fixed", "q8.24", "--power-scale", "0.5",
                             "--adaptive", "links.pcb-asic.conductance",
                             "--adaptive-drift", "5e-5")
    assert meta["design"]["poles"]["speedup"] == 3.0
    mdl, _ = check_design(model, meta, arrays, "poles", "q8.24", speedup=3.0, power_scale=0.5)
    s, z = pole_rule(mdl["A"], 1 / 20, 3.0)
    assert close(s, meta["design"]["poles"]["continuous_per_s"])
    assert close(z, meta["design"]["poles"]["discrete"])
    assert {sub["method"].split(" ")[0] for sub in meta["subsets"]} == {"poles", "kalman"}
    # the adaptive firmware filter's numbers (section 11)
    import scipy.stats

    design = meta["adaptive"]["design"]
    dt, p = 1 / 20, len(mdl["sensors"])
    window = max(1, round(300.0 / dt))
    assert design["window"] == window
    assert design["threshold"] == pytest.approx(scipy.stats.chi2.isf(1e-6, p * window),
                                                rel=1e-12)
    tau_min = 1 / np.max(np.abs(np.linalg.eigvals(mdl["A"])))
    assert design["substeps"] == max(1, math.ceil(2 * dt / tau_min))
    assert design["process_noise"] == pytest.approx(np.maximum(mdl["q"], 1e-4).tolist())
    assert design["sensor_noise"] == pytest.approx(mdl["noise"].tolist())
    assert (design["excitation"], design["initial_std"], design["reacquire"]) == (3.0, 1.0, True)
    assert design["ceiling"] == [0.5] and design["drift"] == [5e-5]
    links = mdl["doc"]["links"]
    pcb_asic = next(i for i, k in enumerate(links) if k["between"] == ["pcb", "asic"])
    assert design["tracked"] == [pcb_asic]


# -- section 8: bias channels --------------------------------------------------------------

def _floor_log2(v):
    return math.frexp(v)[1] - 1


def _rnd(a, s):
    return (a + (1 << (s - 1))) >> s if s > 0 else a << -s


def fixed_bias(meta, arrays, fmt, limits=(-55.0, 125.0)):
    """The constants of section 8's fixed-point bias evaluation from `observer.json` and
    `observer.npz` alone."""
    w, F, scale = FORMATS[fmt]
    names = [s["name"] for s in meta["states"]]
    n, m = len(names), len(meta["inputs"])
    dt = meta["dt_s"]
    f_k = F - int(math.log2(scale))
    lo, hi = limits
    f_t = 30 - _floor_log2(max(abs(lo - 25), abs(hi - 25), 2.0 ** -20))
    th_lo, th_hi = math.ceil((lo - 25) * 2.0 ** f_t), math.floor((hi - 25) * 2.0 ** f_t)
    th_bound = max(-th_lo, th_hi)
    offset = [math.floor((x - 25) * 2.0 ** f_t + 0.5) for x in arrays["x_ref"]]
    f_d = 30 - _floor_log2(hi - lo)
    f_e = f_d + 30
    R = 2.0 ** (31 - f_t)
    rate_rows = {int(v): i for i, v in enumerate(arrays.get("bias_rate_nodes", []))}
    strains, channels = [], []
    for ch in meta["biases"]:
        coef = ch["coefficients"]
        order = ch["order"]
        poly = list(coef[:order + 1]) or [0.0]
        grads = coef[order + 1:order + 1 + len(ch["gradients"])]
        rates = coef[order + 1 + len(ch["gradients"]):]
        Kx, Ku, const = np.zeros(n), np.zeros(m), 0.0
        for (a, b), d in zip(ch["gradients"], grads):
            Kx[names.index(a)] += d
            Kx[names.index(b)] -= d
        for node, e in zip(ch["rates"], rates):
            i = rate_rows[names.index(node)]
            Arow, Brow = arrays["bias_rate_A"][i], arrays["bias_rate_B"][i]
            Kx += e * Arow
            Ku += e * Brow
            const += e * (25.0 * Arow.sum() + Brow @ arrays["u_ref"])
        mine = []
        for v in ch["viscoelastic"]:
            rho = dt / v["time_constant_s"]
            one_minus_a = -math.expm1(-rho)
            a = 1.0 - one_minus_a
            beta = one_minus_a / rho
            w1, w0 = 1.0 - beta, beta - a
            f_w = min(62, 30 - _floor_log2(max(abs(w1), abs(w0), 2.0 ** -60)))
            while max(abs(math.floor(w1 * 2.0 ** f_w + 0.5)),
                      abs(math.floor(w0 * 2.0 ** f_w + 0.5))) > 2 ** 31 - 1:
                f_w -= 1
            f_w = max(f_w, 30)
            strains.append((math.floor(w1 * 2.0 ** f_w + 0.5), math.floor(w0 * 2.0 ** f_w + 0.5),
                            f_w))
            mine.append(len(strains) - 1)
            Kx[names.index(v["node"])] += v["k"]
        poly[0] += const
        poly_n = [c * R ** p for p, c in enumerate(poly)]
        ops = [("x", i, Kx[i] * 2.0 ** -f_t, th_bound) for i in range(n) if Kx[i] != 0]
        ops += [("u", j, Ku[j] * arrays["u_scale"][j] * 2.0 ** -F, 2.0 ** (w - 1))
                for j in range(m) if Ku[j] != 0]
        ops += [("e", v, -ch["viscoelastic"][k]["k"] * 2.0 ** -f_t, th_bound)
                for k, v in enumerate(mine)]
        bound = sum(abs(v) for v in poly_n) + sum(abs(k) * o for *_, k, o in ops)
        g = min(30 - math.ceil(math.log2(bound)) if bound > 0 else 30, 60)
        h = g + 31
        while True:
            K = [math.floor(k * 2.0 ** h + 0.5) for *_, k, _ in ops]
            if all(abs(v) <= 2 ** 31 - 1 for v in K) and \
                    sum(abs(v) * o for v, (*_, o) in zip(K, ops)) < 2.0 ** 62:
                break
            h -= 1
        channels.append({"name": ch["column"], "g": g, "h": h,
                         "poly": [math.floor(v * 2.0 ** g + 0.5) for v in poly_n],
                         "ops": [(kind, i, q) for (kind, i, _, _), q in zip(ops, K)]})
    return {"f_t": f_t, "f_k": f_k, "theta": (offset, th_lo, th_hi), "f_e": f_e, "f_d": f_d,
            "E": (th_lo << (f_e - f_t), th_hi << (f_e - f_t)), "strains": strains,
            "channels": channels}


def _c_table(source, name):
    body = re.search(rf"{name}\[[^=]*= \{{(.*?)\}};", source, re.S).group(1)
    return [[int(v) for v in re.findall(r"INT64_C\((-?\d+)\)", row)]
            for row in re.findall(r"\{([^{}]*)\}", body)]


def test_bias_channel_design(tmp_path):
    """imu6_bias (gradients, a rate term, a viscoelastic strain), Q16.16: the float
    arrays, the rate rows of the continuous model, and every integer constant of the
    fixed-point bias evaluation in the generated C."""
    model = CONFIGS / "imu6_bias.toml"
    out, meta, arrays = export(tmp_path, "bias", model, "--rate", "20", "--fixed", "q16.16")
    mdl, _ = check_design(model, meta, arrays, "kalman", "q16.16")
    rate_nodes = sorted({mdl["nodes"].index(r) for b in mdl["doc"]["biases"]
                         for r in b.get("rates", [])})
    assert arrays["bias_rate_nodes"].tolist() == rate_nodes
    assert close(arrays["bias_rate_A"], mdl["A"][rate_nodes])
    assert close(arrays["bias_rate_B"], mdl["B"][rate_nodes])
    assert [b["column"] for b in meta["biases"]] == [b["column"] for b in mdl["doc"]["biases"]]

    mine = fixed_bias(meta, arrays, "q16.16")
    src = (out / "tj_observer_q16_16.c").read_text()
    P = "TJ_OBSERVER_Q16_16"
    width = max(len(ch["poly"]) for ch in mine["channels"])
    assert _c_table(src, f"{P}_BIAS_POLY") == [
        ch["poly"] + [0] * (width - len(ch["poly"])) for ch in mine["channels"]]
    assert _c_table(src, f"{P}_BIAS_FRAC") == [[ch["g"], ch["h"]] for ch in mine["channels"]]
    assert _c_table(src, f"{P}_BIAS_STRAIN") == [list(s) for s in mine["strains"]]
    # θ: the state code scaled to f_t bits, the offset, the clamp
    offset, th_lo, th_hi = mine["theta"]
    shift = 1 << (mine["f_t"] - mine["f_k"])
    lines = re.findall(r"int64_t th(\d+) = \w+\(\(int64_t\)xm(\d+) \* INT64_C\((\d+)\) \+ "
                       r"INT64_C\((-?\d+)\), INT64_C\((-?\d+)\), INT64_C\((-?\d+)\)\)", src)
    assert lines   # one per node the channels read
    for i, j, *consts in lines:
        assert i == j and [int(v) for v in consts] == [shift, offset[int(i)], th_lo, th_hi]
    # the linear terms: one int32 coefficient per operand, in order
    lins = re.findall(r"lin = (.*);", src)
    assert len(lins) == len(mine["channels"])
    for text, ch in zip(lins, mine["channels"]):
        got = [(int(q), ("x" if op.startswith("th") else "e" if op.startswith("e") else "u"),
                int(re.sub(r"\D", "", op))) for q, op in
               re.findall(r"INT64_C\((-?\d+)\) \* (th\d+|e\d+|\(int64_t\)\w+?\d+)", text)]
        assert got == [(q, kind, i) for kind, i, q in ch["ops"]], ch["name"]
    # the strain state's clamp and the multi-rate's fractional bits
    E_lo, E_hi = mine["E"]
    assert f"INT64_C({E_lo}), INT64_C({E_hi})" in src
    assert meta["fixed"]["coefficient_frac_bits"]["L"] == 16

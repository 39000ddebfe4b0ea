"""Bias channels evaluated from the observer's state estimate (docs/formats.md §4), float64.

A bias channel reads, at every observer step `k`, from the corrected estimate `x̂[k]`
and the inputs `u[k]`:

    b[k] = Σ_p c_p (T[k] − 25)^p                       static polynomial of node T
         + Σ_g d_g (T_a[k] − T_b[k])                    gradients
         + Σ_r e_r (A_c[n, :] x̂[k] + B_c[n, :] u[k])    rates: the model's exact
                                                        continuous dT_n/dt at the sample
         + Σ_v k_v (T_v[k] − ε_v[k])                    viscoelastic strain states

with every strain `dε_v/dt = (T_v − ε_v)/τ_v` discretized exactly for `T_v` (the node's
estimate) linear between samples (first-order hold), as `dynamics.first_order_lag`:
with `r = dt/τ`, `a = exp(−r)`, `β = (1 − a)/r`,

    ε[k] = a ε[k−1] + (1 − β) T[k] + (β − a) T[k−1],      ε[0] = T[0] (at rest).

Several strain terms may name the same node and channel (a Prony series). The
polynomial is evaluated by Horner's rule in `T − 25`; each sum runs in the order the
terms are listed (`BiasEvaluator.step` states the exact float64 operation order, which the
generated C repeats bit for bit). `FixedBiasEvaluator` evaluates the same channels in
integer arithmetic from a `FixedObserver`'s state codes; its docstring states the formats
and the scaling rule, `FixedBiasEvaluator.error_bound` the error bound. NumPy and the
standard library only.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

T_POLY = 25.0   # °C, reference of the static polynomial (docs/formats.md §4)


@dataclasses.dataclass(frozen=True)
class BiasChannel:
    """One bias channel in state indices.

    **Arguments:**

    - `name`: the channel (its data column, e.g. `"gyro_x_dph"`).
    - `node`: state index of the polynomial's temperature.
    - `poly`: `c_0 … c_P`, about 25 °C (the column's unit per K^p).
    - `gradients`: `(a, b, d)` triples: `d (x[a] − x[b])`.
    - `rates`: `(n, e)` pairs: `e dx[n]/dt` (needs `rate_A`, `rate_B` of `BiasEvaluator`).
    - `strains`: `(n, tau, k)` triples: `k (x[n] − ε)`, `dε/dt = (x[n] − ε)/tau`.
    """

    name: str
    node: int
    poly: tuple = ()
    gradients: tuple = ()
    rates: tuple = ()
    strains: tuple = ()


class BiasEvaluator:
    """All bias channels of an observer, stepped with it (see the module docstring).

    **Arguments:**

    - `channels`: a list of `BiasChannel`.
    - `dt`: the observer's sample period (s).
    - `A`, `B`: the continuous-time model's `A_c (n, n)` and `B_c (n, m)`, or only the
      rows the rate terms need (then `rate_nodes` names the state of each row).
    - `rate_nodes`: state index of each row of `A`, `B` (default: row `i` is state `i`).
    """

    def __init__(self, channels, dt: float, A=None, B=None, rate_nodes=None):
        self.channels = list(channels)
        self.dt = float(dt)
        if not self.dt > 0:
            raise ValueError(f"`BiasEvaluator(dt={dt})`: expected a positive sample period.")
        need = sorted({n for ch in self.channels for n, _ in ch.rates})
        if need and (A is None or B is None):
            raise ValueError("`BiasEvaluator`: rate terms need the continuous model's rows "
                             "`A` and `B` (dT_n/dt = A[n] x + B[n] u).")
        self.rate_A = None if A is None else np.atleast_2d(np.asarray(A, float))
        self.rate_B = None if B is None else np.atleast_2d(np.asarray(B, float))
        rows = (list(range(0 if A is None else self.rate_A.shape[0]))
                if rate_nodes is None else [int(v) for v in rate_nodes])
        self.row_of = {node: i for i, node in enumerate(rows)}
        missing = [n for n in need if n not in self.row_of]
        if missing:
            raise ValueError(f"`BiasEvaluator`: rate terms on states {missing} but no row of "
                             f"`A`, `B` for them (rows are states {rows}).")
        # the nonzero entries of each rate row, in order: (j, A[j]) for states, then
        # (-1 - j, B[j]) for inputs
        self._rate_nodes = need
        self._rate_terms = {}
        for node, i in self.row_of.items():
            terms = [(j, float(v)) for j, v in enumerate(self.rate_A[i]) if v != 0]
            if self.rate_B is not None:
                terms += [(-1 - j, float(v)) for j, v in enumerate(self.rate_B[i]) if v != 0]
            self._rate_terms[node] = terms
        # strain coefficients, once
        self._strain = []
        for ch in self.channels:
            coef = []
            for node, tau, k in ch.strains:
                if not float(tau) > 0:
                    raise ValueError(f"`BiasChannel({ch.name!r})`: strain time constant "
                                     f"{tau} must be positive.")
                r = self.dt / float(tau)
                one_minus_a = -math.expm1(-r)
                a = 1.0 - one_minus_a
                beta = one_minus_a / r
                coef.append((int(node), a, 1.0 - beta, beta - a, float(k)))
            self._strain.append(coef)
        self.eps = [np.zeros(len(c)) for c in self._strain]
        self.T_prev = None
        self.started = False

    @property
    def n_channels(self) -> int:
        return len(self.channels)

    @property
    def names(self) -> list[str]:
        return [ch.name for ch in self.channels]

    def reset(self) -> None:
        """Forget the strain states; the next step starts them at rest (ε = T)."""
        self.started = False

    def rate(self, node: int, x, u) -> float:
        """The model's continuous `dx[node]/dt = A[node] x + B[node] u`, summed left to
        right over the row's nonzero entries (`A` first, then `B`; the first product starts
        the sum, `+0.0` for an empty row), the order the generated C repeats."""
        total = None
        for j, c in self._rate_terms[node]:
            v = c * (x[j] if j >= 0 else u[-1 - j])
            total = v if total is None else total + v
        return 0.0 if total is None else float(total)

    def step(self, x, u) -> np.ndarray:
        """Advance the strain states to the estimate `x (n,)` and return `b (q,)`.

        Operation order (float64, each operation rounded, no fused multiply-add; the
        generated C repeats it): strain `ε = (a ε + w1 T) + w0 T_prev`; polynomial by
        Horner from the highest coefficient, `b = c_P`, `b = b d + c_p`, `d = T − 25`
        (`b = 0` without polynomial); then in listed order `b + d_g (T_a − T_b)`,
        `b + e_r rate_n` (`rate` above), `b + k_v (T_v − ε_v)`."""
        x = np.asarray(x, float)
        u = np.asarray(u, float)
        b = np.empty(len(self.channels))
        rates = {n: self.rate(n, x, u) for n in self._rate_nodes}
        for c, (ch, coef) in enumerate(zip(self.channels, self._strain)):
            eps = self.eps[c]
            for v, (node, a, w1, w0, _) in enumerate(coef):
                if self.started:
                    eps[v] = a * eps[v] + w1 * x[node] + w0 * self.T_prev[node]
                else:
                    eps[v] = x[node]
            d = x[ch.node] - T_POLY
            total = float(ch.poly[-1]) if ch.poly else 0.0
            for cp in reversed(ch.poly[:-1]):
                total = total * d + float(cp)
            for ia, ib, dg in ch.gradients:
                total += float(dg) * (x[ia] - x[ib])
            for n, e in ch.rates:
                total += float(e) * rates[n]
            for v, (node, _, _, _, k) in enumerate(coef):
                total += k * (x[node] - eps[v])
            b[c] = total
        self.T_prev = x.copy()
        self.started = True
        return b

    def run(self, states, inputs) -> np.ndarray:
        """`b (T, q)` along state estimates `(T, n)` and inputs `(T, m)`, from rest."""
        states = np.asarray(states, float)
        inputs = np.asarray(inputs, float)
        self.reset()
        out = np.empty((states.shape[0], len(self.channels)))
        for k in range(states.shape[0]):
            out[k] = self.step(states[k], inputs[k])
        return out


def bias_channels_from_metadata(entries, state_names) -> list[BiasChannel]:
    """`BiasChannel`s from the `"biases"` list of an artifact's `observer.json` (entries
    whose coefficients are not fitted are skipped)."""
    index = {nm: i for i, nm in enumerate(state_names)}
    out = []
    for e in entries:
        coef = e.get("coefficients")
        if coef is None:
            continue
        order, grads, rates = int(e["order"]), e.get("gradients", []), e.get("rates", [])
        if len(coef) != order + 1 + len(grads) + len(rates):
            raise ValueError(f"bias channel {e['column']!r}: {len(coef)} coefficients, expected "
                             f"{order + 1} + {len(grads)} + {len(rates)} (poly, gradients, "
                             "rates).")
        poly = tuple(float(v) for v in coef[:order + 1])
        g = tuple((index[a], index[b], float(d))
                  for (a, b), d in zip(grads, coef[order + 1:order + 1 + len(grads)]))
        r = tuple((index[n], float(v)) for n, v in zip(rates, coef[order + 1 + len(grads):]))
        s = tuple((index[v["node"]], float(v["time_constant_s"]), float(v["k"]))
                  for v in e.get("viscoelastic", []))
        out.append(BiasChannel(e["column"], index[e["temperature"]], poly, g, r, s))
    return out


# -- fixed point ----------------------------------------------------------------------------

def _rnd(a: int, s: int) -> int:
    """`round_shift` on a Python int (exact; `>>` floors like C's arithmetic shift)."""
    return (a + (1 << (s - 1))) >> s if s > 0 else a << -s


def _clamp(a: int, lo: int, hi: int) -> int:
    return lo if a < lo else hi if a > hi else a


def _floor_log2(v: float) -> int:
    return math.frexp(v)[1] - 1          # 2**e <= v < 2**(e+1)


class FixedBiasEvaluator:
    """The bias channels of a `BiasEvaluator` in integer arithmetic, from the state codes of
    a `FixedObserver` (whose `biases` it becomes: see `FixedObserver(biases=...)`).

    Every number is an integer code; every product is exact in int64, every rescaling one
    `round_shift` (nearest, ties toward +inf); the generated C repeats it operation for
    operation. The scaling rule (derived from the plausibility limits `lo…hi` °C alone, so
    that nothing can overflow for any state code):

    - **Temperatures.** Each state code `X` (kelvin LSB `2**-f_k`, offset `x_ref`) becomes
      `θ = clamp(X·2**(f_t − f_k) + O, θ_lo, θ_hi)`, the temperature minus 25 °C with
      `f_t = 30 − ⌊log2 max(|lo − 25|, |hi − 25|)⌋` fractional bits (24 for −55…+125 °C:
      |θ| ≤ 100 K < 2**7), clamped to `lo…hi` (an estimate outside the plausibility limits
      is evaluated at the nearest limit), `O = (x_ref − 25)·2**f_t` (exact for the default
      35 °C). `θ` is an int32.
    - **Output.** Channel `c` is an int32 code with `g_c` fractional bits in the column's
      unit, `g_c = 30 − ⌈log2 M_c⌉`, where `M_c` bounds `|b|` over every clamped
      temperature, every saturated input code and every strain: `M_c = Σ_p |c_p| R**p
      + Σ |coefficient|·(largest operand)` (below), so that the bias and every partial sum
      stay below `2**30` codes: a factor two of headroom in the int32 word.
    - **Polynomial** (Horner in `z = θ / R`, `R = 2**(31 − f_t)` = 128 K, so `|z| ≤ 1` and
      `z`'s code at 31 fractional bits is `θ`'s code): normalized coefficients
      `c'_p = c_p R**p` quantized to `g_c` fractional bits (int64 literals; all rate,
      gradient and strain constants folded into `c'_0`), `acc = c'_P`,
      `acc = rnd(acc·θ, 31) + c'_{p}`: every `|acc| ≤ Σ|c'_p| < 2**30` codes.
    - **Linear terms** (gradients `d (T_a − T_b)`, rates `e (A_c[n] x + B_c[n] u)`, the
      `k T_v` of strains, `−k ε_v`) are folded, once, into one coefficient per operand
      (`θ_i` of each state, each input code `U_j`, each strain `ε_v`): `K = Σ coefficients
      × the operand's LSB`, quantized with `h_c` fractional bits, the largest `≤ g_c + 31`
      with every `|K| < 2**31` and `Σ|K|·(largest operand) < 2**62`; the int64 sum
      `Σ K·operand` is rounded once to `g_c` bits and added to the polynomial, then
      saturated to int32 (never active by construction). Input codes are bounded by their
      word (a power input in Q16.16: ±32768 W), temperatures by the limits.
    - **Strain states** `ε_v` (in `θ` units) are int64 codes with `f_e = f_d + 30`
      fractional bits (53 for −55…+125 °C), `f_d = 30 − ⌊log2(hi − lo)⌋` (23): the
      exact first-order-hold lag in increment form,
      `ε += rnd(W1·rnd(θ[k]·2**(f_e−f_t) − ε, 30) + W0·rnd(θ[k−1]·2**(f_e−f_t) − ε, 30),
      f_w − 30)`, where `W1 = (1 − β)·2**f_w`, `W0 = (β − a)·2**f_w` (int32, `f_w` the
      largest with both below `2**31`, at least 30), then clamped to `θ_lo…θ_hi`. The
      increment form keeps the steady state exact (`ε = θ` is a fixed point whatever the
      coefficient rounding) and the 53-bit state leaves no deadband (an increment below
      one code needs `|θ − ε| < 2**-53/w`, 1e-11 K at τ = 1500 s, 20 Hz). The operand of
      the linear sum is `rnd(ε, f_e − f_t)` (an int32 at `f_t` bits). `ε[0] = θ[0]`.

    Error against the float64 `BiasEvaluator` on the same states: see `error_bound`.

    **Arguments:**

    - `evaluator`: the float `BiasEvaluator` (channels, rate rows, strain coefficients).
    - `fmt`: the observer's `FixedFormat` (its kelvin LSB `state_scale·2**-frac_bits` must
      be a power of two, true of Q16.16, Q8.24 and Q15).
    - `x_ref (n,)`, `u_ref (m,)`, `u_scale (m,)`: the observer's offsets and input scales.
    - `limits`: the plausibility limits `(lo, hi)` in °C.
    """

    WORD_MIN, WORD_MAX = -(1 << 31), (1 << 31) - 1   # the bias output and θ: int32
    ACC_LIMIT = 1 << 62

    def __init__(self, evaluator: BiasEvaluator, fmt, x_ref, u_ref, u_scale, limits):
        self.evaluator, self.fmt = evaluator, fmt
        n, m = len(x_ref), len(u_ref)
        self.n_states, self.n_inputs = n, m
        lsb = fmt.state_scale * 2.0 ** -fmt.frac_bits
        fk = -math.log2(lsb)
        if fk != round(fk):
            raise ValueError(f"`FixedBiasEvaluator`: the state LSB of format {fmt.name} is "
                             f"{lsb:g} K, not a power of two; bias channels in fixed point "
                             "need a power-of-two state scale.")
        self.f_k = int(round(fk))
        lo, hi = (float(v) for v in limits)
        if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
            raise ValueError(f"`FixedBiasEvaluator`: plausibility limits {limits} must be "
                             "finite with lo < hi.")
        self.limits = (lo, hi)
        theta_max = max(abs(lo - T_POLY), abs(hi - T_POLY), 2.0 ** -20)
        self.f_t = ft = 30 - _floor_log2(theta_max)
        self.theta_lo = math.ceil((lo - T_POLY) * 2.0 ** ft)
        self.theta_hi = math.floor((hi - T_POLY) * 2.0 ** ft)
        self.theta_bound = max(-self.theta_lo, self.theta_hi)
        offs = (np.asarray(x_ref, float) - T_POLY) * 2.0 ** ft
        self.theta_offset = [int(v) for v in np.floor(offs + 0.5)]
        self.theta_offset_error = (np.asarray(self.theta_offset, float) - offs) * 2.0 ** -ft
        self.f_d = 30 - _floor_log2(hi - lo)
        self.f_e = self.f_d + 30
        sh_e = self.f_e - ft
        # strains
        self.strains = []          # (channel, node, W1, W0, f_w, k)
        for c, coef in enumerate(evaluator._strain):
            for node, a, w1, w0, k in coef:
                top = max(abs(w1), abs(w0), 2.0 ** -60)
                fw = min(62, 30 - _floor_log2(top))
                while max(abs(math.floor(w1 * 2.0 ** fw + 0.5)),
                          abs(math.floor(w0 * 2.0 ** fw + 0.5))) > self.WORD_MAX:
                    fw -= 1
                fw = max(fw, 30)
                W1, W0 = (int(math.floor(w * 2.0 ** fw + 0.5)) for w in (w1, w0))
                self.strains.append((c, int(node), W1, W0, fw, float(k), a, w1, w0))
        self.E_lo, self.E_hi = self.theta_lo << sh_e, self.theta_hi << sh_e
        # per channel: normalized polynomial, folded linear coefficients, formats
        R = 2.0 ** (31 - ft)
        self.R = R
        u_ref = np.asarray(u_ref, float)
        u_scale = np.asarray(u_scale, float)
        word_u = float(1 << (fmt.word_bits - 1))
        self.channels = []
        for c, ch in enumerate(evaluator.channels):
            Kx, Ku, const = np.zeros(n), np.zeros(m), 0.0
            for ia, ib, dg in ch.gradients:
                Kx[ia] += dg
                Kx[ib] -= dg
            for node, e in ch.rates:
                i = evaluator.row_of[node]
                Arow = evaluator.rate_A[i]
                Brow = evaluator.rate_B[i] if evaluator.rate_B is not None else np.zeros(m)
                Kx += e * Arow
                Ku += e * Brow
                const += e * (T_POLY * Arow.sum() + Brow @ u_ref)
            strain_idx = [v for v, s in enumerate(self.strains) if s[0] == c]
            for v in strain_idx:
                Kx[self.strains[v][1]] += self.strains[v][5]
            poly = [float(v) for v in ch.poly] or [0.0]
            poly[0] += const
            poly_n = [cp * R ** p for p, cp in enumerate(poly)]
            # operands: (kind, index, coefficient per operand code, largest |operand|)
            ops = [("x", i, Kx[i] * 2.0 ** -ft, float(self.theta_bound))
                   for i in range(n) if Kx[i] != 0]
            ops += [("u", j, Ku[j] * u_scale[j] * 2.0 ** -fmt.frac_bits, word_u)
                    for j in range(m) if Ku[j] != 0]
            ops += [("e", v, -self.strains[v][5] * 2.0 ** -ft, float(self.theta_bound))
                    for v in strain_idx]
            bound = sum(abs(v) for v in poly_n) + sum(abs(k) * o for _, _, k, o in ops)
            g = 30 - math.ceil(math.log2(bound)) if bound > 0 else 30
            g = min(g, 60)
            P = [int(math.floor(v * 2.0 ** g + 0.5)) for v in poly_n]
            h = g + 31
            while True:
                K = [int(math.floor(k * 2.0 ** h + 0.5)) for _, _, k, _ in ops]
                big = sum(abs(q) * o for q, (_, _, _, o) in zip(K, ops))
                if all(abs(q) <= self.WORD_MAX for q in K) and big < self.ACC_LIMIT:
                    break
                h -= 1
            if h < g:
                raise ValueError(f"`FixedBiasEvaluator`: bias channel {ch.name!r} cannot be "
                                 "scaled (a coefficient too large for its operand).")
            self.channels.append({
                "name": ch.name, "node": ch.node, "g": g, "h": h, "bound": bound,
                "poly": P, "poly_exact": poly_n,
                "ops": [(kind, i, q) for (kind, i, _, _), q in zip(ops, K)],
                "ops_exact": [(kind, i, k) for kind, i, k, _ in ops],
                "Kx": Kx, "Ku": Ku, "const": const})
        self.g = np.array([ch["g"] for ch in self.channels])
        self.E = [0] * len(self.strains)
        self.theta_prev = [0] * n
        self.started = False

    # -- API shared with BiasEvaluator ---------------------------------------------------
    @property
    def n_channels(self) -> int:
        return len(self.channels)

    @property
    def names(self) -> list[str]:
        return [ch["name"] for ch in self.channels]

    @property
    def lsb(self) -> np.ndarray:
        """One output code of each channel, in the channel's unit (`2**-g_c`)."""
        return 2.0 ** -self.g

    def decode(self, codes) -> np.ndarray:
        """Bias codes `(..., q)` to the channels' units."""
        return np.asarray(codes, float) * self.lsb

    def reset(self) -> None:
        self.started = False

    def theta(self, X) -> list[int]:
        """`θ` (int32 codes at `f_t` bits, temperature − 25 °C, clamped) of state codes."""
        s = self.f_t - self.f_k
        return [_clamp(_rnd(int(v), -s) + o, self.theta_lo, self.theta_hi)
                for v, o in zip(X, self.theta_offset)]

    def step(self, X, U) -> np.ndarray:
        """Advance the strain states to the state codes `X (n,)` and return the bias codes
        `(q,)` (int64 holding int32 values); `U (m,)` the (saturated) input codes."""
        th = self.theta(X)
        U = [int(v) for v in U]
        sh_e, f_d = self.f_e - self.f_t, self.f_e - self.f_d
        eps = []
        for v, (_, node, W1, W0, fw, *_rest) in enumerate(self.strains):
            if self.started:
                E = self.E[v]
                d1 = _rnd((th[node] << sh_e) - E, f_d)
                d0 = _rnd((self.theta_prev[node] << sh_e) - E, f_d)
                E = _clamp(E + _rnd(W1 * d1 + W0 * d0, fw - 30), self.E_lo, self.E_hi)
            else:
                E = th[node] << sh_e
            self.E[v] = E
            eps.append(_rnd(E, sh_e))
        out = np.empty(len(self.channels), np.int64)
        for c, ch in enumerate(self.channels):
            P = ch["poly"]
            z = th[ch["node"]]
            acc = P[-1]
            for cp in reversed(P[:-1]):
                acc = _rnd(acc * z, 31) + cp
            lin = 0
            for kind, i, q in ch["ops"]:
                lin += q * (th[i] if kind == "x" else U[i] if kind == "u" else eps[i])
            out[c] = _clamp(acc + _rnd(lin, ch["h"] - ch["g"]), self.WORD_MIN, self.WORD_MAX)
        self.theta_prev = th
        self.started = True
        return out

    def error_bound(self, state_error, input_error=None, x_lo=None, x_hi=None) -> np.ndarray:
        """Bound `(q,)` on `|b_fixed − b_float|` (channel units) for a fixed observer whose
        decoded states differ from the float ones by at most `state_error (n,)` K (e.g.
        `quantization_error_bound(...).bound`) and inputs by `input_error (m,)` (default
        half an input code), while the states stay within `x_lo…x_hi` °C (default the
        plausibility limits) and the strain states are driven by states in that range.

        Parts: (1) the state error through the bias's slopes: `Σ_i G_i δx_i`, `G_i` the
        folded linear coefficient plus, for the polynomial's node, the largest `|poly'|`
        over `x_lo − δ…x_hi + δ`, plus `|k_v|` for each strain on node `i` (a strain is a
        convex combination of past temperatures, so its error is at most the node's);
        (2) the inputs' encoding through the rate rows; (3) the evaluator's own
        quantization: polynomial coefficients and Horner roundings (`2P + 1` half codes),
        the folded coefficients' rounding times the operands' bound, the final rounding,
        the temperature offsets, and per strain `|k|·(2**-(f_d+1) + 2**-(f_t+1) +
        |δW|·span/(w1 + w0))` (difference and output roundings, coefficient rounding
        over the lag)."""
        n, m = self.n_states, self.n_inputs
        dx = np.broadcast_to(np.asarray(state_error, float), (n,))
        du = (np.full(m, 0.0) if input_error is None
              else np.broadcast_to(np.asarray(input_error, float), (m,)))
        lo = self.limits[0] if x_lo is None else x_lo
        hi = self.limits[1] if x_hi is None else x_hi
        out = np.empty(len(self.channels))
        for c, ch in enumerate(self.channels):
            ev_ch = self.evaluator.channels[c]
            poly = np.array([float(v) for v in ev_ch.poly] or [0.0])
            dpoly = np.polynomial.polynomial.polyder(poly) if len(poly) > 1 else np.zeros(1)
            node = ch["node"]
            grid = np.linspace(lo - dx[node] - T_POLY, hi + dx[node] - T_POLY, 4001)
            slope = np.abs(np.polynomial.polynomial.polyval(grid, dpoly)).max()
            G = np.abs(ch["Kx"]).copy()
            G[node] += slope
            strains = [s for s in self.strains if s[0] == c]
            for s in strains:
                G[s[1]] += abs(s[5])
            prop = float(G @ dx + np.abs(ch["Ku"]) @ du)
            half_g = 2.0 ** -(ch["g"] + 1)
            P = len(ch["poly"]) - 1
            own = (2 * P + 1) * half_g + half_g
            own += sum(abs(q * 2.0 ** -ch["h"] - k) * (self.theta_bound if kind != "u"
                                                     else float(1 << (self.fmt.word_bits - 1)))
                       for (kind, _, q), (_, _, k) in zip(ch["ops"], ch["ops_exact"]))
            own += float(np.abs(self.theta_offset_error) @ G)
            span = self.limits[1] - self.limits[0]
            for (_, _, W1, W0, fw, k, a, w1, w0) in strains:
                dW = abs(W1 * 2.0 ** -fw - w1) + abs(W0 * 2.0 ** -fw - w0)
                own += abs(k) * (2.0 ** -(self.f_d + 1) + 2.0 ** -(self.f_t + 1)
                                 + 2.0 ** -(self.f_e + 1) / (w1 + w0)
                                 + dW * span / (w1 + w0))
            out[c] = prop + own
        return out

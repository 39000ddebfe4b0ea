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
terms are listed. NumPy and the standard library only.
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
        """The model's continuous `dx[node]/dt = A[node] x + B[node] u`."""
        i = self.row_of[node]
        return float(self.rate_A[i] @ x + self.rate_B[i] @ u)

    def step(self, x, u) -> np.ndarray:
        """Advance the strain states to the estimate `x (n,)` and return `b (q,)`."""
        x = np.asarray(x, float)
        u = np.asarray(u, float)
        b = np.empty(len(self.channels))
        for c, (ch, coef) in enumerate(zip(self.channels, self._strain)):
            eps = self.eps[c]
            for v, (node, a, w1, w0, _) in enumerate(coef):
                if self.started:
                    eps[v] = a * eps[v] + w1 * x[node] + w0 * self.T_prev[node]
                else:
                    eps[v] = x[node]
            d = x[ch.node] - T_POLY
            total = 0.0
            for cp in reversed(ch.poly):
                total = total * d + float(cp)
            for ia, ib, dg in ch.gradients:
                total += float(dg) * (x[ia] - x[ib])
            for n, e in ch.rates:
                total += float(e) * self.rate(n, x, u)
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

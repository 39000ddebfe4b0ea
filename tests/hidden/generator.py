"""Truth generator for the hidden-effect suite, independent of thermojax.

This module shares no code with the fitting path: it reads model TOML with
`tomllib`, assembles its own physics (spec §2 and §3, in SI, temperatures in °C,
radiation in kelvin) and integrates with `scipy.integrate.solve_ivp(method="Radau")`
at rtol = atol = 1e-10 with an analytic Jacobian. It must never import thermojax.

Physics, per node i (extra nodes included):

    C_i(T_i) dT_i/dt = Σ_links G_ij (T_j − T_i) + Σ_boundaries g (u_col − T_i)
                       + Σ_heat gain·u_col + Σ_radiation ± k (T_a,K⁴ − T_b,K⁴)

with every link or boundary conductance `G0 (1 + α (T̄ − 25)) (1 + c·u_input)`
(α from `conductance_temperature`, c from `conductance_input`, 0 when absent),
`C_i(T) = C0 (1 + β (T_i − 25))` (`capacitance_temperature`), plus the extra
states of `sensor_lag` (dr/dt = (T − r)/τ) and `viscoelastic` (dε/dt = (T − ε)/τ).
A sensor reads `r + gain (r − 25) + offset` with `r` the (lagged) node
temperature; a bias column reads `Σ_p c_p (T − 25)^p + Σ g (T_a − T_b) + Σ r dT_n/dt
+ Σ k (T_node − ε)`, its `coefficients` ordered as formats.md §4 (polynomial, then one per
`gradients` pair, then one per `rates` node), dT_n/dt the right-hand side's exact value
at the sample (state and input sample there; a ZOH jump gives the right-hand limit).

Inputs are piecewise linear between samples (`hold = "foh"`, default) or
piecewise constant with the left sample's value (`"zoh"`). Integration runs
stretch by stretch between the inputs' breakpoints (a kink of a FOH input, a jump
of a ZOH input), so every non-smooth instant is an integration boundary and the
inputs are exactly linear in time inside each stretch; samples inside a stretch
come from `t_eval`. The initial state is the steady state at the first input
sample (`scipy.optimize.fsolve` from the linear equilibrium); lag and strain
states start at their node's temperature.
"""

from __future__ import annotations

import copy
import math
import tomllib
from pathlib import Path

import numpy as np
import scipy.integrate
import scipy.optimize

KELVIN = 273.15
T_REF = 25.0  # °C, reference of every temperature coefficient
TOL = 1e-10  # Radau's rtol and atol

HERE = Path(__file__).resolve().parent
CASES = HERE / "cases"
MODELS = HERE / "models"
REPO = HERE.parents[1]

_MODEL_KEYS = ("name", "description", "nodes", "links", "boundaries", "heat_inputs", "sensors",
               "effects", "biases")


# ---------------------------------------------------------------------------------------------
# Model reading
# ---------------------------------------------------------------------------------------------


def _value(v) -> float:
    """A model-file parameter: a bare number or `{ value = .., fixed = .. }`."""
    if isinstance(v, dict):
        v = v["value"]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ValueError(f"expected a finite number, got {v!r}")
    return float(v)


def read_model(model) -> dict:
    """A model as a plain dict: a path to a TOML file, TOML text, or a dict (deep-copied)."""
    if isinstance(model, dict):
        return copy.deepcopy(model)
    if isinstance(model, Path) or (isinstance(model, str) and "\n" not in model
                                   and model.endswith(".toml")):
        return tomllib.loads(Path(model).read_text())
    return tomllib.loads(str(model))


class _Network:
    """The truth model compiled into arrays: nodes, conduction, heat, radiation, extra states."""

    def __init__(self, doc: dict, holds: dict[str, str] | None = None):
        doc = read_model(doc)
        for node in doc.get("nodes", []):
            if "initial" in node:
                raise ValueError(f"node '{node['name']}' sets `initial`; the generator starts every "
                                 "run at the steady state of its first input sample.")
        self.names: list[str] = [n["name"] for n in doc["nodes"]]
        self.C0: list[float] = [_value(n["capacitance"]) for n in doc["nodes"]]
        self.beta: list[float] = [0.0] * len(self.names)
        # Conduction paths. A link joins nodes a, b; a boundary joins node a to column b.
        self.links = [dict(a=lk["between"][0], b=lk["between"][1], G=_value(lk["conductance"]),
                           alpha=0.0, cin=None, coef=0.0) for lk in doc.get("links", [])]
        self.bounds = [dict(a=b["node"], col=b["input"], G=_value(b["conductance"]), alpha=0.0,
                            cin=None, coef=0.0) for b in doc.get("boundaries", [])]
        self.heats = [dict(a=h["node"], col=h["input"], gain=_value(h.get("gain", 1.0)))
                      for h in doc.get("heat_inputs", [])]
        self.rads: list[dict] = []
        self.sensors = {s["column"]: dict(node=s["node"], noise=_value(s.get("noise", 0.0)),
                                          lag=None, offset=0.0, gain=0.0)
                        for s in doc.get("sensors", [])}
        self.biases = {b["column"]: self._bias(b) for b in doc.get("biases", [])}
        self.strains: list[dict] = []
        # Holds: from the model's own entries, then the caller's, then foh.
        self.holds: dict[str, str] = {}
        for e in (*doc.get("boundaries", []), *doc.get("heat_inputs", [])):
            self.holds.setdefault(e["input"], e.get("hold", "foh"))
        for k, v in {**doc.get("input_holds", {}), **(holds or {})}.items():
            self.holds.setdefault(k, v)
        for effect in doc.get("effects", []):
            self._apply(effect)
        # Truth-only laws outside the vocabulary (`[[truth.laws]]`, see `_law_heat`).
        self.laws = [dict(law) for law in doc.get("laws", [])]
        for law in self.laws:
            if law["law"] not in ("power_law", "quadratic_exp", "arrhenius", "saturating"):
                raise ValueError(f"unknown law {law['law']!r}")
        self._compile()

    @staticmethod
    def _bias(b: dict) -> dict:
        """A `[[biases]]` entry: coefficients split as polynomial, gradients, rates (§4)."""
        coefs = [float(c) for c in b.get("coefficients", [])]
        grads = [tuple(pair) for pair in b.get("gradients", [])]
        rates = list(b.get("rates", []))
        if any(len(pair) != 2 for pair in grads):
            raise ValueError(f"bias '{b['column']}': gradients are pairs of nodes, got {grads}")
        n_poly = len(coefs) - len(grads) - len(rates)
        if coefs and n_poly < 0:
            raise ValueError(f"bias '{b['column']}': {len(coefs)} coefficients for "
                             f"{len(grads)} gradient(s) and {len(rates)} rate(s)")
        if "order" in b and n_poly > int(b["order"]) + 1:
            raise ValueError(f"bias '{b['column']}': {n_poly} polynomial coefficients for order "
                             f"{b['order']}")
        if not coefs:
            n_poly = 0
        return dict(temperature=b["temperature"], poly=coefs[:max(n_poly, 0)],
                    grads=grads, grad_coefs=coefs[n_poly:n_poly + len(grads)] if coefs else
                    [0.0] * len(grads),
                    rates=rates, rate_coefs=coefs[n_poly + len(grads):] if coefs else
                    [0.0] * len(rates),
                    noise=_value(b.get("noise", 0.0)))

    # -- effects ------------------------------------------------------------------------------

    def _is_node(self, x: str) -> bool:
        return x in self.names

    def _path(self, a: str, b: str) -> tuple[str, dict]:
        """The link a–b, or the boundary of node a to column b."""
        if self._is_node(b):
            for lk in self.links:
                if {lk["a"], lk["b"]} == {a, b}:
                    return "link", lk
            raise ValueError(f"no link between '{a}' and '{b}'")
        for bd in self.bounds:
            if bd["a"] == a and bd["col"] == b:
                return "boundary", bd
        raise ValueError(f"no boundary of node '{a}' to column '{b}'")

    def _add_node(self, name: str, capacitance: float) -> None:
        if not name or name in self.names:
            raise ValueError(f"extra_node needs a new, unique `name`, got {name!r}")
        self.names.append(name)
        self.C0.append(capacitance)
        self.beta.append(0.0)

    def _apply(self, e: dict) -> None:
        kind, where = e["kind"], list(e["where"])
        p = {k: _value(v) for k, v in e.items() if k not in ("kind", "where", "name", "hold")}
        if kind == "extra_node":
            a = where[0]
            if not self._is_node(a):
                raise ValueError(f"extra_node: '{a}' is not a node")
            new = e.get("name")
            if len(where) == 1:
                self._add_node(new, p["capacitance"])
                self.links.append(dict(a=a, b=new, G=p["conductance"], alpha=0.0, cin=None, coef=0.0))
                return
            b = where[1]
            heat = [h for h in self.heats if h["a"] == a and h["col"] == b]
            if heat:  # the power enters the new mass, which is linked to a
                self._add_node(new, p["capacitance"])
                for h in heat:
                    h["a"] = new
                self.links.append(dict(a=a, b=new, G=p["conductance"], alpha=0.0, cin=None, coef=0.0))
                return
            what, path = self._path(a, b)
            self._add_node(new, p["capacitance"])
            self.links.append(dict(a=a, b=new, G=p["conductance"], alpha=0.0, cin=None, coef=0.0))
            if what == "link":
                self.links.remove(path)
                self.links.append(dict(a=new, b=b, G=p["conductance_b"], alpha=0.0, cin=None,
                                       coef=0.0))
            else:
                self.bounds.remove(path)
                self.bounds.append(dict(a=new, col=b, G=p["conductance_b"], alpha=0.0, cin=None,
                                        coef=0.0))
        elif kind == "radiation":
            a, b = where
            if not self._is_node(a):
                raise ValueError(f"radiation: '{a}' is not a node")
            self.rads.append(dict(a=a, b=b, k=p["coefficient"]))
        elif kind == "conductance_temperature":
            self._path(*where)[1]["alpha"] = p["alpha"]
        elif kind == "capacitance_temperature":
            self.beta[self.names.index(where[0])] = p["beta"]
        elif kind == "heat_source":
            col, node = where
            self.heats.append(dict(a=node, col=col, gain=p["gain"]))
        elif kind == "boundary":
            col, node = where
            self.bounds.append(dict(a=node, col=col, G=p["conductance"], alpha=0.0, cin=None,
                                    coef=0.0))
        elif kind == "conductance_input":
            a, b, col = where
            path = self._path(a, b)[1]
            path["cin"], path["coef"] = col, p["coefficient"]
        elif kind in ("sensor_lag", "sensor_offset", "sensor_gain") and where[0] not in self.sensors:
            raise ValueError(f"{kind}: '{where[0]}' is not a sensor column")
        elif kind == "sensor_lag":
            self.sensors[where[0]]["lag"] = p["time_constant"]
        elif kind == "sensor_offset":
            self.sensors[where[0]]["offset"] = p["offset"]
        elif kind == "sensor_gain":
            self.sensors[where[0]]["gain"] = p["gain"]
        elif kind == "viscoelastic":
            node, col = where
            if col not in self.biases:
                raise ValueError(f"viscoelastic: bias column '{col}' needs a [[biases]] entry")
            self.strains.append(dict(node=node, column=col, tau=p["time_constant"], k=p["k"]))
        else:
            raise ValueError(f"unknown effect kind '{kind}'")

    # -- arrays -------------------------------------------------------------------------------

    def _compile(self) -> None:
        n = self.n = len(self.names)
        idx = {name: i for i, name in enumerate(self.names)}
        for name in [*(s["node"] for s in self.sensors.values()),
                     *(b["temperature"] for b in self.biases.values()),
                     *(n for b in self.biases.values() for pair in b["grads"] for n in pair),
                     *(n for b in self.biases.values() for n in b["rates"]),
                     *(s["node"] for s in self.strains)]:
            if name not in idx:
                raise ValueError(f"unknown node '{name}'")
        cols: list[str] = []

        def col(c):
            if c not in cols:
                cols.append(c)
            return cols.index(c)

        for law in self.laws:
            far = law.get("column", law.get("b"))
            if far is not None and far not in idx:
                col(far)
        # Conduction: links and boundaries as one list of paths a→(node b | column b).
        paths = [(idx[lk["a"]], idx[lk["b"]], -1, lk) for lk in self.links] + \
                [(idx[bd["a"]], -1, col(bd["col"]), bd) for bd in self.bounds]
        L = len(paths)
        self.pa = np.array([p[0] for p in paths], dtype=int)
        self.pb_node = np.array([p[1] for p in paths], dtype=int)
        self.pb_col = np.array([p[2] for p in paths], dtype=int)
        self.pG = np.array([p[3]["G"] for p in paths])
        self.palpha = np.array([p[3]["alpha"] for p in paths])
        self.pcin = np.array([col(p[3]["cin"]) if p[3]["cin"] else -1 for p in paths], dtype=int)
        self.pcoef = np.array([p[3]["coef"] for p in paths])
        # Heat flow q_l (into a from b) scatters +q to a and −q to b when b is a node.
        self.Pin = np.zeros((n, L))
        self.Pin[self.pa, np.arange(L)] = 1.0
        is_link = self.pb_node >= 0
        self.Pin[self.pb_node[is_link], np.arange(L)[is_link]] = -1.0
        self.Ea = np.zeros((L, n))
        self.Ea[np.arange(L), self.pa] = 1.0
        self.Eb = np.zeros((L, n))
        self.Eb[np.arange(L)[is_link], self.pb_node[is_link]] = 1.0
        self.is_link = is_link
        # Heat inputs.
        hcols, hgain = [], []
        for h in self.heats:
            hcols.append(col(h["col"]))
            hgain.append(h["gain"])
        self.hcol = np.array(hcols, dtype=int)
        self.Hm = np.zeros((n, len(self.heats)))
        self.Hm[[idx[h["a"]] for h in self.heats], np.arange(len(self.heats))] = hgain
        # Radiation: q = k (Ta⁴ − Tb⁴) leaves a, enters b when b is a node.
        R = len(self.rads)
        self.ra = np.array([idx[r["a"]] for r in self.rads], dtype=int)
        self.rb_node = np.array([idx.get(r["b"], -1) for r in self.rads], dtype=int)
        self.rb_col = np.array([-1 if r["b"] in idx else col(r["b"]) for r in self.rads], dtype=int)
        self.rk = np.array([r["k"] for r in self.rads])
        self.Rm = np.zeros((n, R))
        self.Rm[self.ra, np.arange(R)] = -1.0
        rn = self.rb_node >= 0
        self.Rm[self.rb_node[rn], np.arange(R)[rn]] = 1.0
        self.REa = np.zeros((R, n))
        self.REa[np.arange(R), self.ra] = 1.0
        self.REb = np.zeros((R, n))
        self.REb[np.arange(R)[rn], self.rb_node[rn]] = 1.0
        self.C0a = np.array(self.C0)
        self.betaa = np.array(self.beta)
        nc = len(cols)
        # Indices into ext = [T (n), u (columns), 0]: a path's far end, its input factor.
        self.pb_ext = np.where(is_link, self.pb_node, n + self.pb_col)
        self.pcin_ext = np.where(self.pcin >= 0, n + self.pcin, n + nc)
        self.rb_ext = np.where(self.rb_node >= 0, self.rb_node, n + self.rb_col)
        self.has_cin = bool(np.any(self.pcin >= 0))
        self.has_alpha = bool(np.any(self.palpha != 0))
        self.has_beta = bool(np.any(self.betaa != 0))
        # Extra states: sensor lags, then strains.
        self.lag_cols = [c for c, s in self.sensors.items() if s["lag"] is not None]
        self.extra_node = np.array([idx[self.sensors[c]["node"]] for c in self.lag_cols]
                                   + [idx[s["node"]] for s in self.strains], dtype=int)
        self.extra_tau = np.array([self.sensors[c]["lag"] for c in self.lag_cols]
                                  + [s["tau"] for s in self.strains])
        self.cols = cols
        self.idx = idx
        for c in cols:
            self.holds.setdefault(c, "foh")
            if self.holds[c] not in ("foh", "zoh"):
                raise ValueError(f"hold of '{c}' must be 'foh' or 'zoh', got {self.holds[c]!r}")

    # -- physics ------------------------------------------------------------------------------

    def _path_state(self, T, u):
        """Conductances, their temperature slopes, and the end temperatures of all paths."""
        ext = np.concatenate((T, u, (0.0,)))  # nodes, then columns, then a zero
        Ta = T[self.pa]
        Tb = ext[self.pb_ext]
        G = self.pG * (1.0 + self.pcoef * ext[self.pcin_ext]) if self.has_cin else self.pG
        if self.has_alpha:
            dG = 0.5 * G * self.palpha  # ∂G/∂Ta = ∂G/∂Tb
            G = G * (1.0 + self.palpha * (0.5 * (Ta + Tb) - T_REF))
        else:
            dG = None
        return Ta, Tb, G, dG

    def _radiation_far(self, T, u):
        return np.concatenate((T, u, (0.0,)))[self.rb_ext]

    def _end(self, name, T, u):
        return T[self.idx[name]] if name in self.idx else u[self.cols.index(name)]

    def _law_heat(self, T, u):
        """Heat (W) into each node from the truth-only laws, and its Jacobian in T:
        `power_law`: `h |Tb − Ta|^n (Tb − Ta)` into a, out of node b;
        `saturating`: `h (Tb − Ta) / (1 + s |Tb − Ta|)` likewise;
        `arrhenius`: `c exp(−E / (Ta + 273.15))` into a (E in kelvin);
        `quadratic_exp`: `c · column² · exp(k (Ta − 25 °C))` into a."""
        q, J = np.zeros(self.n), np.zeros((self.n, self.n))
        for law in self.laws:
            a = self.idx[law["a"]]
            if law["law"] == "arrhenius":
                Tk = T[a] + KELVIN
                flow = law["c"] * np.exp(-law["E"] / Tk)
                q[a] += flow
                J[a, a] += flow * law["E"] / Tk ** 2
                continue
            if law["law"] in ("power_law", "saturating"):
                d = self._end(law["b"], T, u) - T[a]
                if law["law"] == "power_law":
                    flow = law["h"] * abs(d) ** law["n"] * d
                    slope = law["h"] * (law["n"] + 1) * abs(d) ** law["n"]  # d flow / d d
                else:
                    flow = law["h"] * d / (1.0 + law["s"] * abs(d))
                    slope = law["h"] / (1.0 + law["s"] * abs(d)) ** 2
                q[a] += flow
                J[a, a] -= slope
                if law["b"] in self.idx:
                    b = self.idx[law["b"]]
                    q[b] -= flow
                    J[a, b] += slope
                    J[b, b] -= slope
                    J[b, a] += slope
            else:
                flow = law["c"] * u[self.cols.index(law["column"])] ** 2 * np.exp(
                    law["k"] * (T[a] - T_REF))
                q[a] += flow
                J[a, a] += law["k"] * flow
        return q, J

    def heat(self, T, u):
        """Net heat flow into each node (W)."""
        Ta, Tb, G, _ = self._path_state(T, u)
        q = self.Pin @ (G * (Tb - Ta))
        if self.laws:
            q = q + self._law_heat(T, u)[0]
        if self.hcol.size:
            q = q + self.Hm @ u[self.hcol]
        if self.rk.size:
            q = q + self.Rm @ (self.rk * ((T[self.ra] + KELVIN) ** 4
                                          - (self._radiation_far(T, u) + KELVIN) ** 4))
        return q

    def heat_jacobian(self, T, u):
        Ta, Tb, G, dG = self._path_state(T, u)
        if dG is None:
            J = self.Pin @ (G[:, None] * (self.Eb - self.Ea))
        else:
            d = Tb - Ta
            J = self.Pin @ ((dG * d - G)[:, None] * self.Ea + (dG * d + G)[:, None] * self.Eb)
        if self.laws:
            J = J + self._law_heat(T, u)[1]
        if self.rk.size:
            J = J + self.Rm @ ((4 * self.rk * (T[self.ra] + KELVIN) ** 3)[:, None] * self.REa
                               - (4 * self.rk * (self._radiation_far(T, u) + KELVIN) ** 3)[:, None]
                               * self.REb)
        return J

    def capacitance(self, T):
        return self.C0a * (1.0 + self.betaa * (T - T_REF)) if self.has_beta else self.C0a

    def rhs(self, x, u):
        n = self.n
        T = x[:n]
        dx = np.empty_like(x)
        dx[:n] = self.heat(T, u) / self.capacitance(T)
        dx[n:] = (T[self.extra_node] - x[n:]) / self.extra_tau
        return dx

    def jacobian(self, x, u):
        n, m = self.n, x.size - self.n
        T = x[:n]
        C = self.capacitance(T)
        J = np.zeros((n + m, n + m))
        J[:n, :n] = self.heat_jacobian(T, u) / C[:, None] \
            - np.diag(self.heat(T, u) * self.C0a * self.betaa / C**2)
        if m:
            J[n + np.arange(m), self.extra_node] = 1.0 / self.extra_tau
            J[n + np.arange(m), n + np.arange(m)] = -1.0 / self.extra_tau
        return J

    def steady_state(self, u):
        """Node temperatures with zero net heat flow at the constant input `u`."""
        # The linear equilibrium: conductances at their 25 °C values, no radiation.
        K = np.zeros((self.n, self.n))
        b = self.Hm @ u[self.hcol]
        fu = 1.0 + self.pcoef * np.where(self.pcin >= 0, u[np.maximum(self.pcin, 0)], 0.0)
        g = self.pG * fu
        for l in range(self.pa.size):
            i = self.pa[l]
            K[i, i] += g[l]
            if self.is_link[l]:
                j = self.pb_node[l]
                K[j, j] += g[l]
                K[i, j] -= g[l]
                K[j, i] -= g[l]
            else:
                b[i] += g[l] * u[self.pb_col[l]]
        T0 = np.linalg.solve(K, b)
        T, info, ier, msg = scipy.optimize.fsolve(self.heat, T0, args=(u,), fprime=self.heat_jacobian,
                                                  full_output=True, xtol=1e-14)
        if ier != 1 and np.max(np.abs(self.heat(T, u))) > 1e-12:
            raise RuntimeError(f"steady state not found: {msg}")
        return T

    def node_rates(self, X, U) -> np.ndarray:
        """Exact dT/dt (times, nodes) in K/s from the right-hand side at each sample: the
        state X[k] and the input sample U[k] (a ZOH input's value on [t_k, t_k+1), so at a
        jump this is the right-hand limit)."""
        return np.array([self.rhs(x, u)[:self.n] for x, u in zip(X, U)]).reshape(len(X), self.n)

    def observe(self, X, U, rng=None, noise=True) -> dict[str, np.ndarray]:
        """Sensor and bias columns from states X (times, states) and inputs U (times, cols)."""
        n = self.n
        T = X[:, :n]
        out = {}
        for c, s in self.sensors.items():
            r = X[:, n + self.lag_cols.index(c)] if s["lag"] is not None else T[:, self.idx[s["node"]]]
            out[c] = r + s["gain"] * (r - T_REF) + s["offset"]
        Tdot = None
        if any(b["rates"] for b in self.biases.values()):
            Tdot = self.node_rates(X, U)
        for c, b in self.biases.items():
            dT = T[:, self.idx[b["temperature"]]] - T_REF
            y = np.zeros(len(X))
            for p, cp in enumerate(b["poly"]):
                y = y + cp * dT**p
            for (na, nb), cg in zip(b["grads"], b["grad_coefs"]):
                y = y + cg * (T[:, self.idx[na]] - T[:, self.idx[nb]])
            for node, cr in zip(b["rates"], b["rate_coefs"]):
                y = y + cr * Tdot[:, self.idx[node]]
            out[c] = y
        for k, s in enumerate(self.strains):
            eps = X[:, n + len(self.lag_cols) + k]
            out[s["column"]] = out[s["column"]] + s["k"] * (T[:, self.idx[s["node"]]] - eps)
        if noise and out:
            # One row of draws per sample time: a shorter run gets a prefix of the same noise.
            rng = np.random.default_rng() if rng is None else rng
            e = rng.standard_normal((len(X), len(out)))
            for k, c in enumerate(out):
                std = self.sensors[c]["noise"] if c in self.sensors else self.biases[c]["noise"]
                out[c] = out[c] + std * e[:, k]
        return out


# ---------------------------------------------------------------------------------------------
# Integration
# ---------------------------------------------------------------------------------------------


def _stretches(ts: np.ndarray, U: np.ndarray, holds: list[str]) -> list[tuple[int, int]]:
    """Sample-index stretches [i, j] inside which every input is exactly linear in time.

    A FOH column breaks where its slope changes (beyond float roundoff), a ZOH column
    where its value changes. Each stretch is verified: every sample inside it lies on
    the line through the stretch's end samples (FOH) or equals the left value (ZOH).
    """
    n = len(ts)
    if n < 2:
        return []
    brk = np.zeros(n, dtype=bool)
    brk[0] = brk[-1] = True
    dt = np.diff(ts)
    for k, h in enumerate(holds):
        u = U[:, k]
        scale = np.max(np.abs(u)) + 1.0
        if h == "zoh":
            brk[1:] |= u[1:] != u[:-1]
        else:
            s = np.diff(u) / dt
            brk[1:-1] |= np.abs(np.diff(s)) * dt[1:] > 1e-13 * scale
    cuts = np.flatnonzero(brk)
    out = []
    for i, j in zip(cuts[:-1], cuts[1:]):
        out.extend(_verified(ts, U, holds, int(i), int(j)))
    return out


def _verified(ts, U, holds, i, j):
    """Split [i, j] until every input is linear (FOH) or constant (ZOH) on it to 1e-12."""
    if j - i <= 1:
        return [(i, j)]
    w = (ts[i:j + 1] - ts[i]) / (ts[j] - ts[i])
    ok = True
    for k, h in enumerate(holds):
        u = U[i:j + 1, k]
        line = np.full_like(u, u[0]) if h == "zoh" else u[0] + w * (u[-1] - u[0])
        tol = 1e-12 * (np.max(np.abs(u)) + 1.0)
        seg = u[:-1] if h == "zoh" else u
        if np.max(np.abs(seg - line[:len(seg)])) > tol:
            ok = False
            break
    if ok:
        return [(i, j)]
    m = (i + j) // 2
    return _verified(ts, U, holds, i, m) + _verified(ts, U, holds, m, j)


def simulate_truth(model, ts, inputs: dict[str, np.ndarray], rng=None, noise: bool = True, *,
                   holds: dict[str, str] | None = None, return_states: bool = False,
                   tol: float = TOL):
    """Simulate a model file (plus its effects) through sampled inputs.

    **Arguments:**

    - `model`: path to a model TOML, or the model as a dict (spec §2, plus the
      generator's extensions: `coefficients` on a `[[biases]]` entry (polynomial, then
      one per `gradients` pair, then one per `rates` node), a top-level
      `input_holds = {column = "zoh"}` for columns no entry of the model names).
    - `ts`: sample times (s), strictly increasing.
    - `inputs`: column → samples, for every column the model and its effects use.
    - `rng`: `numpy.random.Generator` for the sensor noise.
    - `noise`: add white Gaussian noise of each sensor's (bias's) `noise` std.
    - `holds`: column → "foh"/"zoh" for columns the model's entries do not name.
    - `tol`: Radau's rtol and atol (the truth's 1e-10 unless a check needs less).

    **Returns:** column → samples for every sensor and bias column (with
    `return_states`, also `(states, state_names)`).
    """
    net = _Network(model, holds)
    ts = np.asarray(ts, dtype=float)
    if ts.ndim != 1 or ts.size < 1 or np.any(np.diff(ts) <= 0):
        raise ValueError("ts must be a 1-d, strictly increasing array")
    missing = [c for c in net.cols if c not in inputs]
    if missing:
        raise ValueError(f"missing input column(s) {missing}")
    U = np.column_stack([np.asarray(inputs[c], dtype=float) for c in net.cols]) if net.cols \
        else np.zeros((ts.size, 0))
    if U.shape[0] != ts.size or not np.all(np.isfinite(U)):
        raise ValueError("every input needs one finite value per sample time")
    holds_l = [net.holds[c] for c in net.cols]
    T0 = net.steady_state(U[0])
    x0 = np.concatenate([T0, T0[net.extra_node]])
    X = np.empty((ts.size, x0.size))
    X[0] = x0
    for i, j in _stretches(ts, U, holds_l):
        t0, t1 = ts[i], ts[j]
        u0 = U[i].copy()
        slope = np.array([0.0 if h == "zoh" else (U[j, k] - U[i, k]) / (t1 - t0)
                          for k, h in enumerate(holds_l)])

        def fun(t, x, u0=u0, slope=slope, t0=t0):
            return net.rhs(x, u0 + slope * (t - t0))

        def jac(t, x, u0=u0, slope=slope, t0=t0):
            return net.jacobian(x, u0 + slope * (t - t0))

        sol = scipy.integrate.solve_ivp(fun, (t0, t1), X[i], method="Radau", jac=jac,
                                        t_eval=ts[i + 1:j + 1], rtol=tol, atol=tol)
        if not sol.success:
            raise RuntimeError(f"integration failed on [{t0}, {t1}] s: {sol.message}")
        X[i + 1:j + 1] = sol.y.T
    out = net.observe(X, U, rng, noise)
    if return_states:
        return out, (X, net.names + [f"lag:{c}" for c in net.lag_cols]
                     + [f"strain:{s['node']}:{s['column']}" for s in net.strains])
    return out


# ---------------------------------------------------------------------------------------------
# Chamber profiles
# ---------------------------------------------------------------------------------------------


def _rng(seed, stream: int) -> np.random.Generator:
    seed = list(np.atleast_1d(seed).astype(int)) if seed is not None else [0]
    return np.random.default_rng([*seed, stream])


def _ramp_knots(duration, rate_c_per_min, bottom, top, dwell_s, lead_s):
    ramp = abs(top - bottom) / rate_c_per_min * 60.0
    t, knots = 0.0, [(0.0, bottom)]
    t += lead_s
    knots.append((t, bottom))
    while t < duration:
        t += ramp
        knots.append((t, top))
        t += dwell_s
        knots.append((t, top))
        t += ramp
        knots.append((t, bottom))
        t += dwell_s
        knots.append((t, bottom))
    return np.array(knots)


# Every random signal draws one uniform number per slot, in order (`rng.random`), so a
# shorter run is a prefix of a longer one with the same seed.


def _prbs(ts, rng, slot_s, level):
    """Piecewise-constant 0/level, a fresh random level every `slot_s` seconds (ZOH samples)."""
    slots = np.floor((ts - ts[0]) / slot_s + 1e-9).astype(int)
    levels = np.where(rng.random(slots.max() + 1) < 0.5, 0.0, level)
    return levels[slots]


def _steps(ts, rng, every_s, low, high):
    """Random levels in [low, high], changed every `every_s`; sampled values (a change spans
    one sample period under FOH)."""
    slots = np.floor((ts - ts[0]) / every_s + 1e-9).astype(int)
    return (low + (high - low) * rng.random(slots.max() + 1))[slots]


def _first_order_lag(ts, u, tau):
    """Exact response of dy/dt = (u − y)/τ to the piecewise-linear u, from y = u[0]."""
    y = np.empty_like(u)
    y[0] = u[0]
    for k in range(len(u) - 1):
        h = ts[k + 1] - ts[k]
        s = (u[k + 1] - u[k]) / h
        a = math.exp(-h / tau)
        y[k + 1] = u[k + 1] - s * tau + (y[k] - u[k] + s * tau) * a
    return y


def chamber_inputs(ts, kind: str = "ramp5", seed=0, *, top: float = 85.0, bottom: float = 25.0,
                   dwell_s: float = 900.0, lead_s: float = 300.0, step_every_s: float = 300.0,
                   p_die: float = 0.4, p_die_slot_s: float = 90.0, p_aux: float = 0.3,
                   p_aux_slot_s: float = 300.0, mount_tau_s: float = 900.0,
                   mount_step_c: float = 4.0, mount_every_s: float = 1200.0,
                   air_low: float = 0.5, air_high: float = 3.0, air_every_s: float = 600.0,
                   pulse_w: float = 0.3, pulse_s: float = 300.0,
                   pulse_first_s: tuple[float, float] = (300.0, 600.0),
                   pulse_gap_s: tuple[float, float] = (600.0, 1500.0)) -> dict[str, np.ndarray]:
    """Every data column of one chamber run, sampled at `ts`.

    `kind` sets the chamber air temperature `T_chamber` (°C, piecewise linear):

    - `"rampR"` (`ramp1`, `ramp5`, `ramp10`, any R in °C/min): `lead_s` at `bottom`,
      then cycles of ramp to `top` at R, `dwell_s`, ramp back, `dwell_s`, to the end.
    - `"steps"`: a random level in [bottom, top] every `step_every_s`, each change
      over one sample period (plunge tests of a probe).
    - `"soak"`: constant `bottom`.

    The other columns, each from its own random stream of `seed`:

    - `P_die` (W): PRBS 0/`p_die`, a new level every `p_die_slot_s` (hold zoh).
    - `P_aux` (W): PRBS 0/`p_aux`, every `p_aux_slot_s` (hold zoh).
    - `T_mount` (°C): the mounting plate, the chamber through a first-order lag of
      `mount_tau_s` (piecewise linear between knots every 60 s) plus its own controller's random offset steps of ±`mount_step_c`
      every `mount_every_s` (so it is not a filtered copy of the chamber).
    - `air_speed` (m/s): random levels in [air_low, air_high] every `air_every_s`.
    - `Q_unrecorded` (W): pulses of `pulse_w` for `pulse_s`, the first starting at a
      random time in `pulse_first_s`, each next after a random gap in `pulse_gap_s`
      (hold zoh): a heat source no column of a case records.

    Random draws are prefix-stable: a shorter `ts` with the same seed gives the
    first samples of the longer run.
    """
    ts = np.asarray(ts, dtype=float)
    t = ts - ts[0]
    duration = float(t[-1]) if t.size else 0.0
    if kind.startswith("ramp"):
        knots = _ramp_knots(duration, float(kind[4:]), bottom, top, dwell_s, lead_s)
        T_ch = np.interp(t, knots[:, 0], knots[:, 1])
    elif kind == "steps":
        r = _rng(seed, 0)
        slots = np.floor(t / step_every_s + 1e-9).astype(int)
        levels = bottom + (top - bottom) * r.random(slots.max() + 1)
        levels[0] = bottom
        T_ch = levels[slots]
    elif kind == "soak":
        T_ch = np.full_like(t, bottom)
    else:
        raise ValueError(f"unknown chamber profile kind '{kind}'")
    out = {"T_chamber": T_ch,
           "P_die": _prbs(t, _rng(seed, 1), p_die_slot_s, p_die),
           "P_aux": _prbs(t, _rng(seed, 2), p_aux_slot_s, p_aux)}
    plate = _steps(t, _rng(seed, 3), mount_every_s, -mount_step_c, mount_step_c)
    plate[t < mount_every_s] = 0.0
    # The plate's lag, kept piecewise linear between knots every 60 s (few breakpoints).
    knots = np.unique(np.append(t[::60], t[-1]))
    lag = _first_order_lag(knots + ts[0], np.interp(knots, t, T_ch), mount_tau_s)
    out["T_mount"] = np.interp(t, knots, lag) + plate
    out["air_speed"] = _steps(t, _rng(seed, 4), air_every_s, air_low, air_high)
    q = np.zeros_like(t)
    r = _rng(seed, 5)
    start = pulse_first_s[0] + (pulse_first_s[1] - pulse_first_s[0]) * r.random()
    while start <= duration:
        q[(t >= start) & (t < start + pulse_s)] = pulse_w
        start += pulse_s + pulse_gap_s[0] + (pulse_gap_s[1] - pulse_gap_s[0]) * r.random()
    out["Q_unrecorded"] = q
    return out


# ---------------------------------------------------------------------------------------------
# Cases
# ---------------------------------------------------------------------------------------------


def law_case_names() -> list[str]:
    """Cases whose truth holds `[[truth.laws]]` of the function library's forms: physics
    outside the vocabulary."""
    return [c for c in case_names() if load_case(c)["truth"].get("laws")
            and not load_case(c).get("symbolic")]


def symbolic_case_names() -> list[str]:
    """Cases whose truth holds laws outside the function library's forms too
    (`symbolic = true`): the symbolic search's to find."""
    return [c for c in case_names() if load_case(c).get("symbolic")]


def case_names() -> list[str]:
    return sorted(p.stem for p in CASES.glob("*.toml"))


def _case_path(name) -> Path:
    p = Path(name)
    if p.suffix == ".toml" and p.exists():
        return p.resolve()
    p = CASES / f"{name}.toml"
    if not p.exists():
        raise FileNotFoundError(f"no hidden-effect case '{name}' (have {case_names()})")
    return p


def load_case(name) -> dict:
    """A case as a dict: its file's keys, plus `believed` and `truth` as model dicts,
    `data_columns` (the columns a run's CSV holds) and `header` (the leading comment)."""
    path = _case_path(name)
    text = path.read_text()
    doc = tomllib.loads(text)
    case = dict(doc)
    case["name"] = doc.get("name", path.stem)
    case["path"] = str(path)
    case["header"] = "\n".join(line[1:].strip() for line in
                               _leading_comment(text.splitlines()))
    believed = doc["believed"]
    if isinstance(believed, str):
        bpath = (path.parent / believed).resolve()
        believed = tomllib.loads(bpath.read_text())
        case["believed_path"] = str(bpath)
    believed = {k: v for k, v in believed.items() if k in _MODEL_KEYS}
    case["believed"] = believed
    truth = copy.deepcopy(believed)
    spec = doc.get("truth", {})
    for table in ("nodes", "links", "boundaries", "heat_inputs", "effects", "laws"):
        truth.setdefault(table, [])
        truth[table] = truth[table] + copy.deepcopy(spec.get(table, []))
    for col, coefs in spec.get("bias_coefficients", {}).items():
        entry = [b for b in truth.get("biases", []) if b["column"] == col]
        if not entry:
            raise ValueError(f"{path}: bias_coefficients for '{col}', which has no [[biases]]")
        entry[0]["coefficients"] = list(coefs)
    if "noise" in doc:  # the case's measurement noise on every sensor of the truth
        for s in truth.get("sensors", []):
            s["noise"] = float(doc["noise"])
    truth["input_holds"] = dict(doc.get("holds", {}))
    case["truth"] = truth
    cols: list[str] = []
    for e in (*believed.get("boundaries", []), *believed.get("heat_inputs", [])):
        if e["input"] not in cols:
            cols.append(e["input"])
    for c in doc.get("extra_columns", []):
        if c not in cols:
            cols.append(c)
    outputs = [s["column"] for s in believed.get("sensors", [])] + \
              [b["column"] for b in believed.get("biases", [])]
    case["input_columns"] = cols
    case["output_columns"] = outputs
    case["data_columns"] = cols + outputs
    case.setdefault("unrecorded", [])
    return case


def _leading_comment(lines):
    out = []
    for line in lines:
        if line.startswith("#"):
            out.append(line)
        elif line.strip() == "" and not out:
            continue
        else:
            break
    return out


def run_inputs(case: dict, index: int, seed, horizon_s: float | None = None):
    """`(ts, columns)` of every column (recorded or not) that drives run `index`."""
    run = dict(case["runs"][index])
    duration = float(run.pop("duration_s"))
    if horizon_s is not None:
        duration = min(duration, float(horizon_s))
    dt = float(run.pop("dt_s", 1.0))
    kind = run.pop("profile")
    rename = run.pop("columns", {})
    ts = np.arange(int(round(duration / dt)) + 1) * dt
    raw = chamber_inputs(ts, kind, seed=[*np.atleast_1d(seed), index], **run)
    cols = {c: raw[rename.get(c, c)] for c in {*raw, *rename} if rename.get(c, c) in raw}
    return ts, cols


def generate_case(name, seed: int = 0, *, horizon_s: float | None = None, noise: bool = True,
                  model: str = "truth", runs=None, tol: float = TOL
                  ) -> list[tuple[np.ndarray, dict[str, np.ndarray]]]:
    """One `(ts, columns)` per run: the recorded input columns and the sensor/bias columns
    of the believed model, simulated from the case's truth (or, with `model="believed"`,
    from the believed model; inputs and noise draws are the same for both).

    `horizon_s` cuts every run short (a prefix of the full run: same inputs, same
    noise); `runs` picks run indices (default all); `tol` as `simulate_truth`'s."""
    case = load_case(name)
    if model not in ("truth", "believed"):
        raise ValueError(f"model must be 'truth' or 'believed', got {model!r}")
    out = []
    for i in (range(len(case["runs"])) if runs is None else runs):
        ts, inputs = run_inputs(case, i, seed, horizon_s)
        m = case["truth"] if model == "truth" else \
            {**case["believed"], "input_holds": case["truth"]["input_holds"],
             "sensors": case["truth"]["sensors"],
             "biases": case["truth"].get("biases", [])}
        rng = np.random.default_rng([*np.atleast_1d(seed), i, 1])
        y = simulate_truth(m, ts, inputs, rng, noise=noise, tol=tol)
        cols = {c: inputs[c] for c in case["input_columns"]}
        cols.update({c: y[c] for c in case["output_columns"]})
        out.append((ts, cols))
    return out


def dump_toml(doc: dict, header: str = "") -> str:
    """A model dict as TOML text (scalars, lists, inline tables and arrays of tables)."""

    def val(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, (int, float)):
            return repr(v) if isinstance(v, int) else repr(float(v))
        if isinstance(v, str):
            return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
        if isinstance(v, list):
            return "[" + ", ".join(val(x) for x in v) + "]"
        if isinstance(v, dict):
            return "{ " + ", ".join(f"{k} = {val(x)}" for k, x in v.items()) + " }"
        raise TypeError(f"cannot write {v!r} to TOML")

    out = [f"# {line}".rstrip() for line in header.splitlines()]
    tables = []
    for k, v in doc.items():
        if isinstance(v, list) and v and all(isinstance(e, dict) for e in v):
            tables.append((k, v))
        elif not (isinstance(v, list) and not v):
            out.append(f"{k} = {val(v)}")
    for k, entries in tables:
        for e in entries:
            out += ["", f"[[{k}]]"] + [f"{kk} = {val(vv)}" for kk, vv in e.items()]
    return "\n".join(out) + "\n"


def write_case(name, folder, seed: int = 0, *, horizon_s: float | None = None) -> dict:
    """Write the believed model (`model.toml`) and one telemetry CSV per run (`run<i>.csv`)
    into `folder`; return `{"model": path, "data": [paths]}`."""
    case = load_case(name)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    model = folder / "model.toml"
    model.write_text(dump_toml(case["believed"], header=(
        f"Believed model of hidden-effect case '{case['name']}' (the truth hides an effect).")))
    paths = []
    for i, (ts, cols) in enumerate(generate_case(name, seed, horizon_s=horizon_s)):
        p = folder / f"run{i}.csv"
        names = ["time_s", *cols]
        data = np.column_stack([ts, *cols.values()])
        with p.open("w") as f:
            f.write(f"# hidden-effect case {case['name']}, run {i}, seed {seed}\n")
            f.write(",".join(names) + "\n")
            for row in data:
                f.write(",".join("%.17g" % x for x in row) + "\n")
        paths.append(p)
    return {"model": model, "data": paths}

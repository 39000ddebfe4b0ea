"""Effects (spec §3) in simulation, against the independent truth generator.

`tests/hidden/generator.py` integrates every effect kind with its own code (Radau,
rtol = atol = 1e-10, no thermojax import). Here thermojax simulates the same truth
models, with structural effects lowered to plain entries, term effects in the model,
and nonlinear ones by ETD2 at the 1 s sample period, and must agree.
"""

from __future__ import annotations

import numpy as np
import pytest

from thermojax import Dataset, Experiment, ThermalModel, parse_model
from thermojax.fitting._likelihood import simulate_dataset
from thermojax.model._model_file import dump_model
from thermojax.dynamics._sensitivity import dataset_outputs
from thermojax.model.effects import KINDS, lower_effects

from hidden import generator as g

HORIZON_S = 1800.0
# ETD2 at 1 s: a third-order local error in the rate of change of the small nonlinear
# rate; linear effects are exact (to the generator's tolerance).
TOLERANCE = {"radiation": 2e-4, "conductance_temperature": 2e-4,
             "capacitance_temperature": 2e-4, "conductance_input": 2e-4,
             # the lag's sensing element keeps 1e-6 of the smallest capacitance
             "sensor_lag": 1e-5}
THERMAL_CASES = [c for c in g.case_names()
                 if c not in ("null", "viscoelastic", *g.law_case_names(),
                              *g.symbolic_case_names())]


def _truth_spec(case):
    truth = {k: v for k, v in case["truth"].items() if k != "input_holds"}
    holds = case["truth"]["input_holds"]
    for e in truth.get("effects", []):
        for w in e["where"]:
            if w in holds:
                e["hold"] = holds[w]
    if case["name"] == "out_of_vocabulary":
        for h in truth["heat_inputs"]:
            h.setdefault("hold", holds.get(h["input"], "foh"))
    return parse_model(g.dump_toml(truth))


@pytest.mark.parametrize("name", THERMAL_CASES)
def test_effect_simulation_matches_generator(name):
    case = g.load_case(name)
    spec = _truth_spec(case)
    truth_runs = g.generate_case(name, seed=0, horizon_s=HORIZON_S, noise=False)
    model = ThermalModel.from_spec(spec)
    ts, cols = truth_runs[0]
    all_inputs = g.run_inputs(case, 0, [0], HORIZON_S)[1]
    u = np.stack([all_inputs[c] for c in lower_effects(spec).spec.input_columns], 1)
    data = Dataset.from_experiments([Experiment(ts, u, np.zeros((len(ts), 2)))])
    y = np.asarray(simulate_dataset(model, data))[0]
    fast = np.asarray(dataset_outputs(model, data))[0]
    kinds = {e.kind for e in spec.effects}
    tol = max([TOLERANCE.get(k, 2e-6) for k in kinds] or [2e-6])
    for j, c in enumerate(spec.sensor_columns):
        ref = cols[c]
        assert np.max(np.abs(y[:, j] - ref)) < tol, (c, np.max(np.abs(y[:, j] - ref)))
        assert np.max(np.abs(fast[:, j] - y[:, j])) < 1e-9


def test_every_kind_has_a_module_and_places():
    spec = parse_model(g.dump_toml(g.load_case("viscoelastic")["believed"]))
    roles = {"T_mount": "temperature", "P_aux": "power", "air_speed": "other"}
    lowered = lower_effects(spec).spec
    for kind, impl in KINDS.items():
        assert impl.kind == kind
        if kind == "expression":  # learned laws come from the discovery stage, not places
            continue
        places = impl.places(lowered, roles)
        assert places, kind
        for where in places:
            params = impl.initial_parameters(lowered, tuple(where))
            assert set(params) <= set(impl.parameters)


def test_lowered_fit_round_trip_names_effect_parameters():
    """A fitted model with structural effects writes them back as effects (loadable),
    and its report names them by effect (spec §5)."""
    from thermojax import fit, profile_interval

    case = g.load_case("sensor_lag")
    believed = g.dump_toml(case["believed"])
    spec = parse_model(believed + '\n[[effects]]\nkind = "sensor_lag"\nwhere = ["T_housing"]\n'
                       'time_constant = 2.0\n')
    runs = g.generate_case("sensor_lag", seed=1, horizon_s=1200.0)
    exps = [Experiment(ts, np.stack([c[k] for k in spec.input_columns], 1),
                       np.stack([c[k] for k in spec.sensor_columns], 1)) for ts, c in runs]
    res = fit(spec, exps)
    p = res.parameters["effects.sensor_lag.T_housing.time_constant"]
    assert abs(p["value"] - 5.0) < 3 * p["std"]
    assert not any("element" in k for k in res.parameters)
    again = parse_model(dump_model(res.spec))
    assert again.effects[0].kind == "sensor_lag"
    assert abs(again.effects[0].parameters["time_constant"].value - p["value"]) < 1e-9
    assert again.node_names == spec.node_names
    # The profile interval of tau (fitted as the element's conductance C / tau) comes back
    # in seconds, in order, and close to the Wald interval in log tau for a parameter
    # this well determined.
    lower, upper = profile_interval(res, "effects.sensor_lag.T_housing.time_constant")
    half = 1.96 * p["std"] / p["value"]
    assert lower < p["value"] < upper
    np.testing.assert_allclose(np.log([lower, upper]) - np.log(p["value"]), [-half, half],
                               rtol=0.1)


@pytest.mark.slow
def test_nonlinear_effect_under_the_kalman_likelihood():
    """The extended Kalman filter (ETD2 step and its Jacobian) recovers a radiation
    coefficient from the generator's data within two reported std."""
    from thermojax import fit

    case = g.load_case("radiation")
    spec = parse_model(g.dump_toml(case["believed"]) + '\n[[effects]]\nkind = "radiation"\n'
                       'where = ["housing", "T_chamber"]\ncoefficient = 1e-10\n')
    runs = g.generate_case("radiation", seed=0, horizon_s=900.0)
    exps = [Experiment(ts, np.stack([c[k] for k in spec.input_columns], 1),
                       np.stack([c[k] for k in spec.sensor_columns], 1)) for ts, c in runs]
    res = fit(spec, exps, likelihood="kalman")
    p = res.parameters["effects.radiation.housing-T_chamber.coefficient"]
    assert res.converged
    assert abs(p["value"] - 3e-10) < 2 * p["std"]


def test_capacitance_factors_on_one_node_multiply():
    """Two `capacitance_temperature` terms on one node (and radiation into it): the node's
    whole rate is divided by the product of the factors, `C0 (1 + β1 ΔT)(1 + β2 ΔT)`,
    written here directly in NumPy from the network's matrices."""
    import jax.numpy as jnp

    text = (g.REPO / "configs" / "imu6.toml").read_text()
    cap = '\n[[effects]]\nkind = "capacitance_temperature"\nwhere = ["housing"]\nbeta = {}\n'
    rad = ('\n[[effects]]\nkind = "radiation"\nwhere = ["housing", "T_chamber"]\n'
           'coefficient = 5e-10\n')
    spec = parse_model(text + cap.format(0.004) + cap.format(-0.0015) + rad)
    model = ThermalModel.from_spec(spec)
    system = model.linear_system()
    A, B, C0 = (np.asarray(a) for a in (system.A, system.B, system.capacitance))
    rng = np.random.default_rng(3)
    h = spec.node_names.index("housing")
    j = spec.input_columns.index("T_chamber")
    for _ in range(5):
        x = rng.uniform(10.0, 90.0, A.shape[0])
        u = np.array([rng.uniform(10.0, 90.0) if c == "T_chamber" else rng.uniform(0, 0.3)
                      for c in spec.input_columns])
        q = 5e-10 * ((u[j] + 273.15) ** 4 - (x[h] + 273.15) ** 4)  # W into the housing
        f = A @ x + B @ u
        f[h] += q / C0[h]
        f[h] /= (1 + 0.004 * (x[h] - 25.0)) * (1 - 0.0015 * (x[h] - 25.0))
        got = np.asarray(model.nonlinear_rate(system, jnp.asarray(x), jnp.asarray(u)))
        np.testing.assert_allclose(got, f - A @ x - B @ u, rtol=1e-12, atol=1e-15)


def test_an_extra_node_may_carry_its_own_process_noise():
    # formats.md §3: an added mass's diffusion under the Kalman likelihood, estimated
    # like any node's; absent, it is fixed at zero.
    from thermojax import parse_model
    from thermojax.model._model_file import dump_model
    from thermojax.model.effects import lower_effects

    from helpers import ROOM_WITH_ENVELOPE

    text = ROOM_WITH_ENVELOPE.rstrip() + "\nprocess_noise = 0.003\n"
    spec = parse_model(text)
    te = next(n for n in lower_effects(spec).spec.nodes if n.name == "Te")
    assert te.process_noise.value == 0.003 and not te.process_noise.fixed
    again = parse_model(dump_model(spec))
    assert again.effects[0].parameters["process_noise"].value == 0.003
    plain = parse_model(text.replace("process_noise = 0.003\n", ""))
    te = next(n for n in lower_effects(plain).spec.nodes if n.name == "Te")
    assert te.process_noise.value == 0.0 and te.process_noise.fixed

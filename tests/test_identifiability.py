"""Identifiability: what the data cannot determine, named in plain words.

Two kinds of truth:

- hand-built Fisher matrices whose eigen-structure is known by construction (a chosen
  orthogonal basis and chosen eigenvalues), for `identifiability(info, names, spec)`:
  covariance versus `numpy.linalg.inv` / `pinv`, condition numbers, which directions are
  flagged and what the message says;
- the physics of the networks: with temperature inputs only, multiplying every C and G
  by one factor leaves every temperature unchanged (`C dT/dt = -K T + G u` scales
  through), so `fit` must flag exactly that direction; a known heat input or one fixed
  capacitance removes it. On the six-node IMU sampled at 1 s, the proof mass (τ ≈ 0.1 s,
  no sensor) cannot be seen.
"""

import json
import re

import numpy as np
import pytest

import thermojax as tj
from thermojax.measurements._data import Experiment
from thermojax.fitting._fit import fit
from thermojax._json import json_safe
from thermojax.fitting._identifiability import identifiability

from helpers import (CONFIGS, RTD2H_NAMES, RTD2H_RUNS, RTD2H_TRUTH, cached_fit, imu6_fit,
                     np_simulate, np_steady, rtd2h_oe_fit, text_matrices)

# rtd2 (configs/rtd2.toml) with a sensor on each node and no heat input.
RTD2S_TEXT = """\
name = "rtd2s"

[[nodes]]
name = "sheath"
capacitance = 0.8

[[nodes]]
name = "core"
capacitance = 0.1

[[links]]
between = ["sheath", "core"]
conductance = 0.08333333333333333

[[boundaries]]
node = "sheath"
input = "T_fluid"
conductance = 0.2

[[sensors]]
node = "core"
column = "T_core"
noise = 0.01

[[sensors]]
node = "sheath"
column = "T_sheath"
noise = { value = 0.02, fixed = true }
"""
RTD2S_NAMES = ["nodes.sheath.capacitance", "nodes.core.capacitance",
               "links.sheath-core.conductance", "boundaries.sheath-T_fluid.conductance"]
IMU6_NAMES = ([f"nodes.{n}.capacitance" for n in
               ("housing", "bulkhead", "pcb", "asic", "mems", "proof_mass")]
              + [f"links.{k}.conductance" for k in ("housing-bulkhead", "bulkhead-pcb", "pcb-asic",
                                                    "pcb-mems", "asic-mems", "mems-proof_mass")]
              + ["boundaries.housing-T_chamber.conductance"])


def rtd2s_spec(text=RTD2S_TEXT):
    return tj.parse_model(text, source="rtd2s.toml")


def basis(k, first, seed=0):
    """An orthonormal basis of R^k whose first column is `first` (normalized)."""
    rng = np.random.default_rng(seed)
    M = np.column_stack([first, rng.standard_normal((k, k - 1))])
    Q, _ = np.linalg.qr(M)
    return Q * np.sign(Q[:, :1].T @ first)  # keep the first column's sign


def fisher(Q, eigenvalues):
    return Q @ np.diag(eigenvalues) @ Q.T


# ---------------------------------------------------------------------------------------------
# Hand-built Fisher matrices


def test_well_conditioned():
    Q = basis(4, np.ones(4), seed=1)
    F = fisher(Q, [100.0, 50.0, 20.0, 5.0])
    ident = identifiability(F, RTD2S_NAMES, rtd2s_spec())
    assert ident.ok and ident.messages == [] and ident.unidentifiable_parameters == set()
    np.testing.assert_allclose(ident.covariance, np.linalg.inv(F), rtol=1e-10, atol=1e-14)
    assert ident.condition_number == pytest.approx(100.0 / 5.0, rel=1e-10)


def test_scale_direction_is_flagged_with_its_remedy():
    """Rank 3: the null vector is the common scale of every C and G (log units)."""
    Q = basis(4, np.ones(4), seed=2)
    F = fisher(Q, [0.0, 80.0, 30.0, 9.0])
    ident = identifiability(F, RTD2S_NAMES, rtd2s_spec())
    assert not ident.ok and len(ident.directions) == 1
    d = ident.directions[0]
    (entry,) = d["directions"]
    assert set(entry["combination"]) == set(RTD2S_NAMES)
    assert all(w == pytest.approx(1.0, abs=1e-3) for w in entry["combination"].values())
    assert entry["log_std"] is None  # no information at all
    assert ident.unidentifiable_parameters == set(RTD2S_NAMES)
    msg = ident.messages[0]
    assert "scale together" in msg and "Fix one capacitance" in msg
    assert "known heat input" in msg
    # Covariance: the pseudo-inverse, nothing along the null vector.
    np.testing.assert_allclose(ident.covariance, np.linalg.pinv(F, rcond=1e-10), rtol=1e-8,
                               atol=1e-12)
    np.testing.assert_allclose(ident.covariance @ np.ones(4), 0.0, atol=1e-12)
    json.dumps(json_safe(ident.to_json()), allow_nan=False)


@pytest.mark.parametrize("mu, flagged", [(0.25, True), (4.0, False)])
def test_weak_direction_threshold(mu, flagged):
    """A direction with relative std 1/√μ: 2 (a factor e² undetermined) is flagged, 0.5 is
    not (the default threshold is a relative std of 1)."""
    v = np.array([0.0, 0.0, 1.0, -1.0])  # link against boundary conductance
    F = fisher(basis(4, v, seed=3), [mu, 60.0, 25.0, 10.0])
    ident = identifiability(F, RTD2S_NAMES, rtd2s_spec())
    assert ident.ok is not flagged
    if flagged:
        (d,) = ident.directions
        (entry,) = d["directions"]
        assert entry["combination"] == {"links.sheath-core.conductance": pytest.approx(1.0),
                                        "boundaries.sheath-T_fluid.conductance":
                                            pytest.approx(-1.0)} or \
            entry["combination"] == {"boundaries.sheath-T_fluid.conductance": pytest.approx(1.0),
                                     "links.sheath-core.conductance": pytest.approx(-1.0)}
        assert entry["log_std"] == pytest.approx(1 / np.sqrt(mu), rel=1e-8)
        assert "cannot determine the combination" in d["message"]
        assert "relative std 2" in d["message"]
        assert "Fix one of these parameters" in d["message"]  # both nodes have sensors
        assert "scale together" not in d["message"]
        assert ident.unidentifiable_parameters == {"links.sheath-core.conductance",
                                                   "boundaries.sheath-T_fluid.conductance"}
    else:
        np.testing.assert_allclose(ident.covariance, np.linalg.inv(F), rtol=1e-10, atol=1e-14)


def test_unsensed_fast_node_message():
    """imu6: the proof-mass pair (C and its link) in the null space; the message names the
    unsensed node and, given the sample period, says it is faster than the sampling."""
    spec = tj.load_model(CONFIGS / "imu6.toml")
    v = np.zeros(13)
    v[IMU6_NAMES.index("nodes.proof_mass.capacitance")] = 1.0
    v[IMU6_NAMES.index("links.mems-proof_mass.conductance")] = 1.0
    F = fisher(basis(13, v, seed=4), [0.0] + list(np.geomspace(5.0, 1e6, 12)))
    ident = identifiability(F, IMU6_NAMES, spec, sample_period=1.0)
    (d,) = ident.directions
    assert ident.unidentifiable_parameters == {"nodes.proof_mass.capacitance",
                                               "links.mems-proof_mass.conductance"}
    assert "'proof_mass']" in d["message"] and "no sensor sees" in d["message"]
    assert "sample faster" in d["message"] and "proof_mass ~0.1 s" in d["message"]
    assert ident.condition_number > 1e12
    # The advised rate puts two samples in the proof mass's time constant, C / G =
    # 0.003 J/K / 0.03 W/K = 0.1 s (configs/imu6.toml): 20 Hz, above the 1 Hz sampled.
    rate = float(re.search(r"sample faster than ([0-9.e+]+) Hz", d["message"]).group(1))
    assert rate == pytest.approx(2 / (0.003 / 0.03), rel=0.03)


def test_directions_sharing_parameters_are_merged():
    """Two null directions over three proof-mass/MEMS parameters: one report entry of
    dimension 2 (any rotation of the null space is as good as another)."""
    spec = tj.load_model(CONFIGS / "imu6.toml")
    i_c, i_g, i_m = (IMU6_NAMES.index(n) for n in (
        "nodes.proof_mass.capacitance", "links.mems-proof_mass.conductance",
        "nodes.mems.capacitance"))
    v1, v2 = np.zeros(13), np.zeros(13)
    v1[[i_c, i_g]] = 1.0
    v2[[i_m, i_g]] = [1.0, -0.5]
    Q = basis(13, v1, seed=5)
    Q2, _ = np.linalg.qr(np.column_stack([v1, v2, Q[:, 2:]]))
    F = fisher(Q2, [0.0, 0.0] + list(np.geomspace(5.0, 1e5, 11)))
    ident = identifiability(F, IMU6_NAMES, spec)
    (d,) = ident.directions
    assert d["dimension"] == 2 and len(d["directions"]) == 2
    assert set(d["parameters"]) >= {IMU6_NAMES[i] for i in (i_c, i_g, i_m)}
    assert "2 independent combinations" in d["message"]


def test_a_direction_is_reported_whole_and_named_by_its_large_loadings():
    """A null direction with a small loading (0.05 of the largest) on the core's
    capacitance: its `combination` is the direction itself to 3 decimals, small loading
    included (left out, the reported direction would sit 4 % off the null space), while
    the parameters it names, and the message, are those loaded over a tenth."""
    v = np.array([1.0, 0.05, 0.0, -0.7])  # RTD2S_NAMES order
    F = fisher(basis(4, v, seed=2), [0.0, 30.0, 300.0, 3000.0])
    (d,) = identifiability(F, RTD2S_NAMES, rtd2s_spec()).directions
    reported = np.array([d["directions"][0]["combination"].get(n, 0.0) for n in RTD2S_NAMES])
    assert np.linalg.norm(reported - v) < 2e-3, reported
    named = {RTD2S_NAMES[0], RTD2S_NAMES[3]}
    assert set(d["parameters"]) == named
    assert "nodes.core.capacitance" not in d["message"]
    assert all(n in d["message"] for n in named)


@pytest.mark.parametrize("powered", [False, True])
def test_unpowered_runs_name_the_missing_excitation(powered):
    """imu6 (which has a heat input) with the common scale of every C and G, and a
    proof-mass direction, left undetermined: when the runs' power columns are all zero
    the advice is a known heat input (a missing excitation), not faster sampling; when
    they are not, the scale is not claimed."""
    spec = tj.load_model(CONFIGS / "imu6.toml")
    v1 = np.ones(13)
    v2 = np.zeros(13)
    v2[[IMU6_NAMES.index("nodes.proof_mass.capacitance"),
        IMU6_NAMES.index("links.mems-proof_mass.conductance")]] = 1.0
    Q = basis(13, v1, seed=3)
    Q2, _ = np.linalg.qr(np.column_stack([v1, v2, Q[:, 2:]]))
    F = fisher(Q2, [0.0, 0.0] + list(np.geomspace(5.0, 1e5, 11)))
    ident = identifiability(F, IMU6_NAMES, spec, sample_period=1.0, powered=powered)
    (d,) = ident.directions
    if powered:
        assert "missing excitation" not in d["message"]
    else:
        assert "missing excitation" in d["message"] and "known heat input" in d["message"]
        assert "sample faster" not in d["message"] and d["cause"] == "practical"


def test_initial_temperatures_are_marginalized():
    """A per-run initial temperature (°C, not log) correlated with the log parameters: the
    condition number is that of the Schur complement (the log block with the initial
    temperature profiled out), and the covariance is the full inverse."""
    rng = np.random.default_rng(6)
    J = rng.standard_normal((40, 5)) * np.array([3.0, 2.0, 1.5, 4.0, 0.5])
    F = J.T @ J
    names = RTD2S_NAMES + ["runs.0.nodes.core.initial"]
    ident = identifiability(F, names, rtd2s_spec())
    assert ident.ok
    schur = F[:4, :4] - np.outer(F[:4, 4], F[4, :4]) / F[4, 4]
    mu = np.linalg.eigvalsh(schur)
    assert ident.condition_number == pytest.approx(mu.max() / mu.min(), rel=1e-9)
    np.testing.assert_allclose(ident.covariance, np.linalg.inv(F), rtol=1e-9, atol=1e-14)


def test_undetermined_initial_temperature():
    """An initial temperature the data say nothing about is flagged by name (the
    pseudo-inverse alone would give it a zero variance: "perfectly known")."""
    F = np.zeros((5, 5))
    F[:4, :4] = fisher(basis(4, np.ones(4), seed=7), [100.0, 50.0, 20.0, 5.0])
    names = RTD2S_NAMES + ["runs.1.nodes.core.initial"]
    ident = identifiability(F, names, rtd2s_spec())
    assert ident.unidentifiable_parameters == {"runs.1.nodes.core.initial"}
    assert "runs.1.nodes.core.initial is not determined by the data" in ident.messages[0]


def test_initial_temperature_sharing_a_null_direction():
    """An unsensed node's initial temperature that trades off exactly against a log
    parameter (a null direction mixing °C and log units) is flagged with it."""
    names = RTD2S_NAMES + ["runs.0.nodes.core.initial"]
    v = np.array([0.0, 1.0, 0.0, 0.0, 0.5])
    F = fisher(basis(5, v, seed=8), [0.0, 90.0, 40.0, 12.0, 6.0])
    ident = identifiability(F, names, rtd2s_spec())
    assert "runs.0.nodes.core.initial" in ident.unidentifiable_parameters
    assert "nodes.core.capacitance" in ident.unidentifiable_parameters


def test_no_free_parameters():
    ident = identifiability(np.zeros((0, 0)), [], rtd2s_spec())
    assert ident.ok and ident.covariance.shape == (0, 0)


# ---------------------------------------------------------------------------------------------
# From fits to synthetic data


def rtd2s_experiments(seed=2):
    """Two runs (600 samples at 1 s, 400 at 2 s) of the rtd2s truth driven by the fluid
    temperature alone: a slow sine plus ±3 °C steps every 40 samples (FOH)."""
    mm = text_matrices(RTD2S_TEXT)
    rng = np.random.default_rng(seed)
    runs = []
    for name, (n, dt) in zip(RTD2H_NAMES, RTD2H_RUNS):
        ts = dt * np.arange(n)
        steps = np.repeat(3.0 * rng.choice([-1.0, 1.0], n // 40 + 1), 40)[:n]
        U = (20.0 + 8.0 * np.sin(2 * np.pi * ts / 300.0) + steps)[:, None]
        _, Y = np_simulate(mm["A"], mm["B"], mm["Cy"], np_steady(mm["A"], mm["B"], U[0]), U, dt,
                           mm["holds"])
        runs.append(Experiment(ts, U, Y + rng.standard_normal(Y.shape) * mm["noise"], name=name))
    return runs


@pytest.mark.slow  # compiles a fit of another structure (~30-60 s)
def test_temperature_inputs_only_flags_the_scale():
    """rtd2 with sensors on both nodes, driven by the fluid temperature alone, every C and G
    free: the report flags their common scale (and only that), says to fix one
    capacitance or add a known heat input, and gives them no standard error."""
    result = cached_fit("rtd2s", lambda: fit(rtd2s_spec(), rtd2s_experiments()))
    ident = result.identifiability
    assert len(ident.directions) == 1, ident.messages
    (d,) = ident.directions
    assert d["dimension"] == 1 and set(d["directions"][0]["combination"]) == set(RTD2S_NAMES)
    assert "Fix one capacitance" in d["message"] and "known heat input" in d["message"]
    for name in RTD2S_NAMES:
        assert result.parameters[name]["std"] is None
    # What the data do determine is still right: the ratios, e.g. the sheath's time
    # constant against the fluid C_sheath/G_b = 4 s, and the noise std.
    tau = result.parameters[RTD2S_NAMES[0]]["value"] / result.parameters[RTD2S_NAMES[3]]["value"]
    assert tau == pytest.approx(0.8 / 0.2, rel=0.05)  # ratio known to ~1 % here
    assert result.parameters["sensors.T_core.noise"]["value"] == pytest.approx(0.01, rel=0.06)


@pytest.mark.slow  # another compilation
def test_fixing_one_capacitance_removes_the_scale():
    """The remedy the message gives: with the sheath's capacitance fixed (at its true
    value) the same data determine every other parameter, within 2 std of the truth; the
    fixed one keeps its value."""
    text = RTD2S_TEXT.replace("capacitance = 0.8", "capacitance = { value = 0.8, fixed = true }")
    result = cached_fit("rtd2s-fixed", lambda: fit(rtd2s_spec(text), rtd2s_experiments()))
    assert result.identifiability.ok, result.identifiability.messages
    assert result.parameters["nodes.sheath.capacitance"] == {"value": pytest.approx(0.8),
                                                             "std": None, "free": False}
    for name in RTD2S_NAMES[1:]:
        p = result.parameters[name]
        assert p["std"] is not None and abs(p["value"] - RTD2H_TRUTH[name]) <= 2 * p["std"], \
            (name, p)


def test_known_heat_input_identifies_everything():
    """The same network with a measured heater (helpers' rtd2h fit): no message, and every
    C and G has a standard error."""
    result = rtd2h_oe_fit()["result"]
    assert result.identifiability.ok and result.identifiability.messages == []
    for name in RTD2S_NAMES:
        assert result.parameters[name]["std"] is not None


@pytest.mark.slow  # the six-node fit (shared with test_fit)
def test_imu6_proof_mass_is_flagged():
    """imu6 sensed at housing, pcb and asic, sampled at 1 s: the proof-mass capacitance and
    its suspension conductance are flagged and have no std; the housing capacitance and
    the other determined parameters have one."""
    result = imu6_fit()["result"]
    ident = result.identifiability
    pair = {"nodes.proof_mass.capacitance", "links.mems-proof_mass.conductance"}
    assert pair <= ident.unidentifiable_parameters
    # the proof mass, unsensed and faster than a sample, cannot show its start either:
    # its per-run estimated starts are flagged with it, and nothing else is
    starts = {n for n in ident.unidentifiable_parameters
              if n.startswith("runs.") and n.endswith(".nodes.proof_mass.initial")}
    assert ident.unidentifiable_parameters <= pair | {"nodes.mems.capacitance"} | starts
    for name in pair:
        assert result.parameters[name]["std"] is None
    assert any("proof_mass" in m and "no sensor sees" in m for m in ident.messages)
    for name in ("nodes.housing.capacitance", "nodes.pcb.capacitance",
                 "boundaries.housing-T_chamber.conductance", "links.pcb-asic.conductance"):
        assert result.parameters[name]["std"] is not None, name

"""Effects with physical values only (`AbstractEffect.unphysical`, `_physical_range`).

Each verdict follows from the physics stated in the docstring of the case, with numbers
chosen here: a sensor that reads 1 % of its node's swing, a conductance factor that
crosses zero inside the data's temperatures, a passive law that pumps heat uphill."""

from __future__ import annotations

import numpy as np

from thermojax.investigation._candidates import Candidate
from thermojax.investigation._physical_range import (data_span, prefer_physics,
                                                     reject_unphysical)
from thermojax.measurements._telemetry import Telemetry
from thermojax.model.effects import KINDS, DataSpan

SPAN = DataSpan((0.0, 40.0), {"flow": (0.0, 2.0)})


def test_sensor_gain_and_offset_ranges():
    gain, offset = KINDS["sensor_gain"], KINDS["sensor_offset"]
    assert gain.unphysical(("T",), {"gain": 0.03}, SPAN) is None
    why = gain.unphysical(("T",), {"gain": -0.99}, SPAN)
    assert why and "1%" in why  # the sensor would see 1 % of the swing
    assert offset.unphysical(("T",), {"offset": -2.0}, SPAN) is None
    assert offset.unphysical(("T",), {"offset": 25.0}, SPAN)


def test_temperature_factors_must_not_vanish_within_the_data():
    # 1 + α (T − 25) at T = 0 °C: α = 0.02 → 0.5 (fine); α = 0.039 → 0.025 (fine,
    # above 2 %); α = 0.045 → −0.125 (crosses zero at 2.8 °C: not physical)
    k = KINDS["conductance_temperature"]
    assert k.unphysical(("a", "b"), {"alpha": 0.02}, SPAN) is None
    assert k.unphysical(("a", "b"), {"alpha": 0.039}, SPAN) is None
    why = k.unphysical(("a", "b"), {"alpha": 0.045}, SPAN)
    assert why and "crosses zero" in why
    # a capacitance falling with temperature: β = −0.08 → 1 − 0.08·15 = −0.2 at 40 °C
    assert KINDS["capacitance_temperature"].unphysical(("a",), {"beta": -0.08}, SPAN)
    # an input-driven conductance: 1 + c·flow over flow in [0, 2]: c = −0.6 → −0.2
    ci = KINDS["conductance_input"]
    assert ci.unphysical(("a", "b", "flow"), {"coefficient": -0.6}, SPAN)
    assert ci.unphysical(("a", "b", "flow"), {"coefficient": 0.6}, SPAN) is None


def test_a_passive_law_must_carry_heat_downhill():
    e = KINDS["expression"]
    assert e.reverses_heat("h * abs(b - a)^0.25 * (b - a)", ("a", "b"), {"h": 0.3},
                           SPAN) is None
    assert e.reverses_heat("h * (b - a) - k", ("a", "b"), {"h": 0.3, "k": 2.0}, SPAN)
    # a law reading a power is a source: not judged
    assert e.reverses_heat("h * P * (b - a)", ("a", "b"), {"h": 0.3}, SPAN) is None


def _cand(kind, where, lr, dbic, parameters=None):
    return Candidate(kind, tuple(where), lr, 1e-9, method="refit", delta_bic=dbic,
                     supported=True, parameters=parameters or {})


def test_an_unphysical_refit_is_not_supported_and_says_why():
    c = _cand("sensor_gain", ["T"], 500.0, -480.0, {"gain": -0.99})
    reject_unphysical([c], SPAN)
    assert not c.supported and not c.physical and c.note.startswith("not physical")


def test_a_sensor_artifact_steps_aside_for_physics_it_nearly_ties():
    art = _cand("sensor_offset", ["T"], 120.0, -100.0, {"offset": 0.4})
    phys = _cand("extra_node", ["a", "T_out"], 118.0, -95.0)
    prefer_physics([art, phys], lambda kinds: "a reference thermometer separates them")
    assert not art.supported and phys.supported
    assert "reference thermometer" in art.note and "preferred" in phys.note
    # clearly better: the artifact stays first (Δ BIC 30 apart)
    art = _cand("sensor_offset", ["T"], 150.0, -130.0, {"offset": 0.4})
    phys = _cand("extra_node", ["a", "T_out"], 118.0, -95.0)
    prefer_physics([art, phys], lambda kinds: "")
    assert art.supported and phys.supported


def test_data_span_covers_sensors_and_boundaries_only():
    from thermojax.model import parse_model

    spec = parse_model('name = "m"\n[[nodes]]\nname = "a"\ncapacitance = 1.0\n'
                       '[[boundaries]]\nnode = "a"\ninput = "T_out"\nconductance = 1.0\n'
                       '[[heat_inputs]]\nnode = "a"\ninput = "P"\n'
                       '[[sensors]]\nnode = "a"\ncolumn = "T_a"\n', source="m.toml")
    ts = np.arange(4.0)
    t = Telemetry(ts, {"T_out": np.array([-5.0, 0, 1, 2]), "P": np.array([0, 900.0, 0, 0]),
                       "T_a": np.array([20.0, np.nan, 22, 30])})
    span = data_span(spec, [t])
    assert span.temperatures == (-5.0, 30.0)  # the power column's 900 is not a temperature
    assert span.columns["P"] == (0.0, 900.0)


_HEATER_MASS = """
name = "room"
[[nodes]]
name = "room"
capacitance = 1e6
[[boundaries]]
node = "room"
input = "Ta"
conductance = 150.0
[[heat_inputs]]
node = "room"
input = "Ph"
gain = { value = 1.0, fixed = true }
[[sensors]]
node = "room"
column = "y"
[[effects]]
kind = "extra_node"
where = ["room", "Ph"]
name = "heater"
capacitance = %r
conductance = %r
"""


def test_an_added_node_lifted_beyond_any_body_is_a_lag_not_a_mass():
    """A heater's mass takes the logged power (up to 5000 W, gain 1) and passes it to the
    room through its conductance: at 639 W/K it runs 7.8 K over the room; the same lag
    (τ = C/G = 2,300 s) fitted as 112 J/K behind 0.0481 W/K would run 5000 / 0.0481 =
    1.04e5 K over it, which no body does."""
    from thermojax import parse_model
    from thermojax.investigation._physical_range import MAX_RISE_K, lifted_node
    from thermojax.model.effects import lower_effects

    span = DataSpan((0.0, 30.0), {"Ph": (0.0, 5000.0), "Ta": (-5.0, 10.0), "y": (18, 30)})

    def lowered(c, g):
        low = lower_effects(parse_model(_HEATER_MASS % (c, g)))
        return getattr(low, "spec", low)

    assert lifted_node(lowered(1.47e6, 639.0), span) is None
    why = lifted_node(lowered(112.0, 0.0481), span)
    assert why and "heater" in why and "1.04e+05 K" in why and "Ph" in why
    # the threshold: 1000 K at 5000 W is 5 W/K
    assert lifted_node(lowered(1e4, 5000.0 / MAX_RISE_K * 1.01), span) is None
    assert lifted_node(lowered(1e4, 5000.0 / MAX_RISE_K * 0.99), span)
    # a candidate whose refit left an earlier mass so lifted is not supported, whatever
    # its own values (here a sound mass hanging off the room)
    from types import SimpleNamespace

    c = Candidate(kind="extra_node", where=("room",), score=50.0, p_value=1e-6,
                  method="refit", supported=True,
                  parameters={"capacitance": 1e5, "conductance": 100.0})
    c.result = SimpleNamespace(result=SimpleNamespace(lowered_spec=lowered(112.0, 0.0481)))
    reject_unphysical([c], span)
    assert not c.supported and not c.physical and "a lag, not a body" in c.note

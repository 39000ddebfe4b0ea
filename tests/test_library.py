"""The library of learned laws (`thermojax.discovery`): an input term reads its column
in the column's size, so that its coefficient is the heat at that value."""

from __future__ import annotations

import numpy as np

from thermojax.discovery import LIBRARY, LearnedLaw, column_scales
from thermojax.model._expression import evaluate_numpy, parse, resolve


def test_column_scales_are_the_largest_magnitude_to_three_digits():
    scales = column_scales({"Ph": np.array([[35.3, 5287.33], [12.0, 40.0]]),
                            "Ps": np.array([-4.2, 324.1]), "neg": np.array([-0.012345, 0.01]),
                            "zero": np.zeros(4), "bad": np.array([1.0, np.nan]),
                            "empty": np.zeros(0)})
    assert scales == {"Ph": 5290.0, "Ps": 324.0, "neg": 0.0123}


def _heat(law, where, c, p, k, T, u):
    eff = law.effect(where, c, (p, k))
    tree = resolve(parse(eff.expression), ["pcb", law.column], [], list(eff.parameters))
    values = np.stack([T, u], -1)
    return evaluate_numpy(tree, values, values[..., :0], [c, p, k])


def test_a_scaled_input_term_is_the_raw_law_with_c_times_the_scale_to_the_p():
    """c·(u/U)^p·exp(k(T−25)) from the model's expression evaluator against NumPy, and
    against the unscaled term with coefficient c·U^-p."""
    rng = np.random.default_rng(0)
    T, u = rng.uniform(10, 80, 50), rng.uniform(30, 5300, 50)
    term = LIBRARY[1]
    assert term.template == "c * {u}^p * exp(k * ({a} - 25))"
    scaled = LearnedLaw(term, "P_heater", scale=5290.0)
    raw = LearnedLaw(term, "P_heater")
    assert scaled.text(("pcb",)) == "c * (P_heater / 5290)^p * exp(k * (pcb - 25))"
    assert raw.text(("pcb",)) == "c * P_heater^p * exp(k * (pcb - 25))"
    c, p, k = 2.5, 1.7, 0.02
    want = c * (u / 5290.0) ** p * np.exp(k * (T - 25.0))
    np.testing.assert_allclose(_heat(scaled, ("pcb",), c, p, k, T, u), want, rtol=1e-13)
    np.testing.assert_allclose(_heat(raw, ("pcb",), c * 5290.0 ** -p, p, k, T, u), want,
                               rtol=1e-12)
    # the kind it nests is named by the column, whatever its scale
    assert scaled.nested_kind(("pcb",)) == raw.nested_kind(("pcb",)) == \
        ("heat_source", ("P_heater", "pcb"))

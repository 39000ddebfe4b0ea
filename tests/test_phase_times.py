"""Where a step's time goes (`investigation._phase_times`): phases add their blocks' wall
time to the open tally, JAX's compiling inside them is counted apart, and nothing is
counted outside a step."""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp

from thermojax.investigation._phase_times import (COMPILATION, phase, phases_in_words,
                                                  step_phases)


def test_phases_add_their_wall_time_and_nothing_outside_a_step():
    with phase("outside"):
        time.sleep(0.01)  # no tally open: counted nowhere, no error
    with step_phases() as tally:
        for _ in range(2):
            with phase("a"):
                time.sleep(0.05)
        with phase("b"):
            pass
    assert 0.1 <= tally["a"] < 0.5 and tally["b"] < 0.05
    assert "outside" not in tally


def test_compilation_inside_a_step_is_counted():
    x = jnp.arange(7.0)
    with step_phases() as tally:
        with phase("work"):
            # a program not compiled before in this process (its constant is new)
            jax.jit(lambda v: jnp.sin(v) * 1.234567)(x).block_until_ready()
    assert 0.0 < tally[COMPILATION] <= tally["work"]
    with step_phases() as again:
        jax.jit(lambda v: jnp.cos(v) * 7.654321)(x).block_until_ready()
    assert again[COMPILATION] > 0.0  # counted in the step even outside a named phase


def test_phases_in_words_largest_first_and_small_ones_left_out():
    words = phases_in_words({"refits": 300.0, "held-out folds": 60.4, "tiny": 0.5,
                             COMPILATION: 120.0}, 400.0)
    assert words == "400 s: refits 300 s, held-out folds 60 s; compilation 120 s of it"

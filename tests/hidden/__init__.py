"""The hidden-effect suite: a truth generator independent of thermojax, and its cases.

`generator.py` simulates a model file plus effects with its own TOML reading,
physics and integrator (SciPy Radau); `cases/*.toml` each hide one effect
(or none, or one outside the vocabulary) from a believed model.
"""

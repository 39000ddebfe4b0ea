"""The loop's last question before it says `unexplained`: is the missing heat a function
of anything recorded? A small network (`discovery.learn_network_heat`) is trained into
the fitted model at the node carrying the most missing heat, through the model's own
dynamics; if it explains the misfit and a library term matches its heat, that term
becomes an `expression` candidate, refitted and judged by the same rule as every other
(docs/formats.md §3a, docs/extensions.md).

The score test evaluates a library term along the fitted model's own trajectory, which
is wrong at a node where much heat is missing; the network's trajectory carries the
heat, so its distilled form may be a term the score test did not see.
"""

from __future__ import annotations

import numpy as np

from ._candidates import Candidate

# The network must remove at least this share of the sensors' mean-square misfit (the
# mean over sensors of 1 − (RMSE after / RMSE before)²) to be believed: below it, the
# missing heat is no function of what was recorded, which `unexplained` then says.
EXPLAINED_SHARE = 0.5
# A library term must match the network's heat with at least this R² to be proposed.
MIN_R2 = 0.5
# The network is trained only where the RMS missing heat at the node is at least this
# many of its median stds (below, the reconstruction is zero within its uncertainty).
MIN_HEAT_STDS = 2.0
# Levenberg–Marquardt steps through the dynamics (each is a forward-mode Jacobian of
# every run's simulation: the cost of the whole network step).
TRAJECTORY_STEPS = 20


def network_candidate(step, runs, mh, say) -> tuple[Candidate | None, dict]:
    """Train the heat network at `mh`'s largest carrier of `step`'s fitted model and
    distil it.

    **Returns:** `(candidate or None, the step record's "network" entry)`: the node, RMSE
    (°C) per sensor before and after the network, the share of the misfit it explains,
    the best-matching library term and its R², and in words what followed."""
    from ..discovery import learn_network_heat

    per_node = mh.summary()["per_node"]
    node = max(per_node, key=lambda n: per_node[n]["rms_W"])
    rms, std = per_node[node]["rms_W"], per_node[node]["median_std_W"]
    if rms < MIN_HEAT_STDS * std:
        entry = {"node": node, "proposed": False,
                 "verdict": (f"the missing heat at {node} (RMS {rms:.3g} W) is below "
                             f"{MIN_HEAT_STDS:g} times its median std ({std:.3g} W): zero "
                             "within its uncertainty, nothing for a network to learn")}
        say(entry["verdict"])
        return None, entry
    say(f"training a heat network at {node}, where most heat is missing")
    law = learn_network_heat(step.result, [(t.ts, t.channels) for t in runs], node,
                             trajectory_steps=TRAJECTORY_STEPS, missing=mh)
    entry = account(node, law)
    say(entry["verdict"])
    if not entry["proposed"]:
        return None, entry
    best = law.distilled[0]  # proposed: there is one, and it matched
    return Candidate(best.law.kind, tuple(best.where), 0.0, 1.0, method="network",
                     estimate=best.c, learned=best.law, shape=best.shape), entry


def account(node: str, law) -> dict:
    """The step record's `network` entry for the `NetworkLaw` `law` trained at `node`,
    with `proposed`: whether its best distilled term is to be refitted."""
    share = float(np.mean([1.0 - (law.rmse_after[c] / law.rmse_before[c]) ** 2
                           for c in law.rmse_before if law.rmse_before[c] > 0]))
    best = law.distilled[0] if law.distilled else None
    rmse = ", ".join(f"{c} {law.rmse_before[c]:.3g} → {law.rmse_after[c]:.3g} °C"
                     for c in law.rmse_before)
    entry = {"node": node, "rmse_before": law.rmse_before, "rmse_after": law.rmse_after,
             "explained_share": share, "proposed": False,
             "distilled": (None if best is None else
                           {"expression": best.effect().expression, "law": best.law.term.name,
                            "where": list(best.where), "r2": best.r2})}
    if share < EXPLAINED_SHARE:
        entry["verdict"] = (f"a network of {node}'s temperature, its neighbours' and the "
                            f"recorded columns removes {share:.0%} of the mean-square misfit "
                            f"({rmse}; under {EXPLAINED_SHARE:.0%}): the heat is no function "
                            "of what was recorded")
    elif best is None or best.r2 < MIN_R2:
        entry["verdict"] = (f"a network at {node} removes {share:.0%} of the mean-square "
                            f"misfit ({rmse}), but its heat matches no library term (best R² "
                            f"{best.r2 if best else 0.0:.2f}, under {MIN_R2}): the heat "
                            "follows a law outside the library (extend `discovery.LIBRARY`) "
                            "or an unrecorded input that the network only imitates")
    else:
        entry["proposed"] = True
        entry["verdict"] = (f"a network at {node} removes {share:.0%} of the mean-square "
                            f"misfit ({rmse}); its heat matches {best.law.term.name} (R² "
                            f"{best.r2:.2f}), refitted as a candidate")
    return entry

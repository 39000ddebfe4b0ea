"""Advice for candidates the data cannot tell apart (tied, or a near-tie the report
flags): which measurement or excitation would separate them."""

from __future__ import annotations


SEPARATION = {
    frozenset(("sensor_lag", "extra_node")):
        "a lag acts on the reading alone, a mass also delays the heat reaching the rest of "
        "the network: a second sensor on (or beyond) that node, or a known power step into "
        "it, would separate them",
    frozenset(("radiation", "conductance_temperature")):
        "both strengthen the path as it warms; radiation grows with T³ in kelvin, a linear "
        "temperature coefficient with T̄ − 25 °C: runs over a wider temperature range "
        "(or in vacuum) would separate them",
}


# Every piece of advice ends by naming the command that designs the separating run.
DESIGN_RUN = ("; `thermojax design --from-investigation DIR --duration D --out RUN` (or "
              "`thermojax design --model M --rivals R.toml ...`, each model written with one of "
              "the candidates) designs the chamber run that tells them apart within the "
              "chamber's limits")


def separation_advice(kinds) -> str:
    return _advice(kinds) + DESIGN_RUN


def _advice(kinds) -> str:
    kinds = frozenset(kinds)
    for pair, text in SEPARATION.items():
        if pair <= kinds or (len(kinds) == 1 and kinds <= pair):
            return text
    if kinds & {"sensor_gain", "sensor_offset"}:
        return ("a sensor's gain or offset changes its reading alone, a thermal effect the "
                "temperatures themselves: a reference thermometer beside the sensor, read at "
                "two steady temperatures (a soak at each end of the range), separates them")
    return ("the data cannot tell these apart: excite the system differently (a power step "
            "in the node concerned, a faster ramp, a wider temperature range) or add a sensor "
            "near the candidates' places")

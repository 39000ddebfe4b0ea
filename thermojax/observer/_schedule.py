"""Gain scheduling: the observer of a nonlinear network designed at several operating
temperatures, interpolated at run time by a measured one (docs/observer.md §12)."""

from __future__ import annotations

import numpy as np

from .._errors import InputError


def refuse_sensor_offsets(model, observer: str, where: str, field: str) -> None:
    """`InputError` when `model`'s sensors have offsets, which the `observer` ("scheduled",
    "trimmed") reads without."""
    if np.any(np.asarray(model.output_offset(), float) != 0):
        raise InputError(f"the model's sensors have offsets (sensor_offset effects); the "
                         f"{observer} observer reads them without: fold the offsets into the "
                         "readings first.", file=where, field=field)


def scheduled_design(spec, rate_hz: float, points, by: str, where: str = "model"):
    """The `thermojax.reference.ScheduledDesign` of `spec` (a `ModelSpec` with nonlinear
    effects) at `rate_hz`: at each temperature of `points` (°C, increasing, two or more)
    the model linearized at that uniform temperature with no power (as `export
    --operating-point`), discretized exactly, with the steady-state Kalman gain of its
    process and sensor noise; scheduled by the sensor column `by`."""
    import equinox as eqx

    from ..dynamics._discretize import discretize
    from ..model._model import ThermalModel
    from ..reference._scheduled import ScheduledDesign
    from ._linearize import linearize
    from ._kalman import discrete_process_covariance, steady_state_kalman

    model = ThermalModel.from_spec(spec)
    if not model.is_nonlinear:
        raise InputError("the model is linear: its observer is the same at every "
                         "temperature, there is nothing to schedule (drop --schedule).",
                         file=where, field="--schedule")
    refuse_sensor_offsets(model, "scheduled", where, "--schedule")
    sensors = list(spec.sensor_columns)
    if by not in sensors:
        raise InputError(f"the scheduling variable '{by}' is not a sensor of the model; its "
                         f"sensors are {sensors}.", file=where, field="--schedule-by")
    points = np.asarray(points, float)
    if points.size < 2 or not np.all(np.isfinite(points)) or np.any(np.diff(points) <= 0):
        raise InputError(f"the operating points must be two or more increasing "
                         f"temperatures, got {points.tolist()}.", file=where,
                         field="--schedule")
    dt = 1.0 / float(rate_hz)
    system = model.linear_system()
    power_inputs = set(model.network.topology.heat_inputs)
    q = np.asarray(model.process_noise, float)
    r2 = np.asarray(model.noise, float) ** 2
    mats = {k: [] for k in ("Phi", "B0", "B1", "L")}
    for T in points:
        A, B, _, _ = linearize(model, system, power_inputs, float(T), where)
        d = discretize(eqx.tree_at(lambda s: (s.A, s.B), system, (A, B)), dt)
        L = steady_state_kalman(d, discrete_process_covariance(np.asarray(A), q, dt), r2).gain
        for k, v in (("Phi", d.Phi), ("B0", d.B0), ("B1", d.B1), ("L", L)):
            mats[k].append(np.asarray(v, float))
    return ScheduledDesign(points, *(np.stack(mats[k]) for k in ("Phi", "B0", "B1", "L")),
                           np.asarray(system.C, float), np.asarray(system.D, float),
                           sensors.index(by))

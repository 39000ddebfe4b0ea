"""`thermojax rate --model M [--anti-alias ORDER CUTOFF_HZ --rate HZ]`: which observer
rate is enough (the 8–15×-bandwidth rule of thumb checked against the observer's own error),
and what an anti-alias filter's delay costs. Edges only; the work is
`observer._rate`."""

from __future__ import annotations

from .._errors import InputError


def cmd_rate(args) -> int:
    from .. import io
    from ..model._model import ThermalModel
    from ..model.effects import lower_effects
    from ..observer._rate import DEFAULT_RATES, anti_alias_cost, rate_advice
    from ._arguments import _resolve_model

    spec = lower_effects(io.load_model(_resolve_model(args.model))).spec
    model = ThermalModel.from_spec(spec)
    if model.is_nonlinear:
        raise InputError("the model has nonlinear effects; the rate analysis is of the linear "
                         "observer: remove them, or analyse the linearization `export` makes.",
                         file=spec.source, field="effects")
    columns = list(spec.sensor_columns)
    sensors = None
    if args.sensor:
        unknown = [c for c in args.sensor if c not in columns]
        if unknown:
            raise InputError(f"no sensor {unknown[0]!r}; the model's sensors are {columns}.",
                             file=spec.source, field="--sensor")
        sensors = [columns.index(c) for c in args.sensor]
    rates = DEFAULT_RATES if args.rates is None else tuple(args.rates)
    args.progress(f"steady-state Kalman error of {spec.name} at {len(rates)} rates")
    adv = rate_advice(model, sensors, rates, args.noise_rate, args.tolerance)
    print(f"{spec.name}: sensor noise white, its std per sample given at {args.noise_rate:g} Hz "
          f"(--noise-rate); the worst-estimated state is {adv.worst_state}, continuous-time "
          f"error std {adv.limit_std:.4g} °C; the observer's closed-loop bandwidth "
          f"{adv.bandwidth_hz:.4g} Hz")
    print(f"{'rate, Hz':>10} {'error std, °C':>14} {'× limit':>8} {'rate / bandwidth':>17} "
          f"{'observable':>10}")
    for row in adv.rows:
        print(f"{row.rate_hz:>10g} {row.error_std:>14.4g} {row.error_ratio:>8.3f} "
              f"{row.rate_over_bandwidth:>17.3g} {'yes' if row.observable else 'NO':>10}")
    lo, hi = adv.rule_hz
    if adv.recommended_hz is None:
        print(f"no rate tried is within {adv.tolerance:.0%} of the limit; try higher --rates")
    else:
        ratio = adv.recommended_hz / adv.bandwidth_hz
        verdict = ("inside" if 8 <= ratio <= 15 else "below" if ratio < 8 else "above")
        print(f"enough: {adv.recommended_hz:g} Hz, the lowest rate that observes every "
              f"state and is within {adv.tolerance:.0%} of the continuous limit ({ratio:.3g}× the bandwidth, "
              f"{verdict} the rule of thumb of 8–15× the bandwidth, which asks "
              f"{lo:.3g}–{hi:.3g} Hz)")
    if args.anti_alias is not None:
        order, cutoff = args.anti_alias
        if order != int(order) or not 1 <= order <= 8 or not cutoff > 0:
            raise InputError("--anti-alias takes ORDER (1..8) and CUTOFF_HZ (> 0).",
                             field="--anti-alias")
        rate = float(args.rate) if args.rate is not None else adv.recommended_hz
        if rate is None:
            raise InputError("give --rate for the anti-alias evaluation.", field="--rate")
        cost = anti_alias_cost(model, rate, int(order), cutoff, sensors,
                               args.ramp / 60.0, args.noise_rate)
        names = model.network.topology.node_names
        worst = int(cost.ramp_error.argmax())
        print(f"anti-alias Butterworth order {int(order)} at {cutoff:g} Hz, observer at "
              f"{rate:g} Hz: group delay {cost.group_delay_s:.4g} s; during a "
              f"{args.ramp:g} °C/min ramp it adds a steady error of up to "
              f"{cost.ramp_error[worst]:.3g} °C ({names[worst]}), "
              f"{cost.ramp_error[worst] / cost.error_std[worst]:.3g}× that state's error std "
              f"({cost.error_std[worst]:.3g} °C)")
    return 0


def _rates(text: str) -> list[float]:
    """Comma-separated rates, each a number or a fraction (`1/1800,1/900,0.01`)."""
    import argparse

    from ._arguments import rate_hz

    try:
        values = [float(rate_hz(v)) for v in text.split(",")]
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected comma-separated Hz (numbers or "
                                         f"fractions such as 1/1800), got {text!r}") from None
    if not values or not all(v > 0 and v < 1e6 for v in values):
        raise argparse.ArgumentTypeError(f"rates must be positive Hz, got {text!r}")
    return values


def add_rate(sub) -> None:
    from ._arguments import _add_quiet, _positive_float, rate_hz

    p = sub.add_parser(
        "rate", help="which observer rate is enough, and an anti-alias filter's cost",
        description="The steady-state Kalman observer's worst-state error std at candidate "
        "rates against its continuous-time limit, with sensor noise of fixed density (the "
        "model's noise std per sample at --noise-rate); the lowest rate within --tolerance "
        "of the limit, and beside it the rule of thumb of sampling at 8-15x the closed-loop "
        "bandwidth. With "
        "--anti-alias ORDER CUTOFF_HZ: the filter's group delay and the steady error it "
        "adds during a ramp.")
    p.add_argument("--model", required=True, help="model TOML file or built-in model name")
    p.add_argument("--sensor", action="append", metavar="COLUMN",
                   help="use only this sensor column (repeatable; default all)")
    p.add_argument("--rates", type=_rates, default=None, metavar="HZ,HZ,...",
                   help="candidate rates, numbers or fractions such as 1/1800 (default 0.01 to "
                   "5000 Hz in 1-2-5 steps)")
    p.add_argument("--noise-rate", type=_positive_float, default=1.0, metavar="HZ",
                   help="the rate at which the model's sensor noise std holds per sample "
                   "(default 1 Hz: the rate of the data it was fitted to)")
    p.add_argument("--tolerance", type=_positive_float, default=0.1,
                   help="how close to the continuous limit is enough (default 0.1: 10 %%)")
    p.add_argument("--anti-alias", type=float, nargs=2, metavar=("ORDER", "CUTOFF_HZ"),
                   default=None, help="evaluate a Butterworth anti-alias filter")
    p.add_argument("--rate", type=rate_hz, default=None, metavar="HZ",
                   help="the observer rate for --anti-alias, a number or a fraction such as "
                   "1/1800 (default: the rate found enough)")
    p.add_argument("--ramp", type=_positive_float, default=5.0, metavar="C_PER_MIN",
                   help="the ramp of the anti-alias evaluation, °C/min (default 5)")
    _add_quiet(p)
    p.set_defaults(func=cmd_rate)

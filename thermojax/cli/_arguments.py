"""Argument types and options shared by every subcommand of the command line.

Each subcommand's file builds its own parser from these; `_main` imports the
subcommands. Keeping them here lets the arrows run one way: `_main` → subcommand →
`_arguments`.
"""

from __future__ import annotations

import argparse
from importlib import resources
from pathlib import Path

import numpy as np

from .._errors import InputError


def _builtin_model_path(name: str) -> Path:
    return Path(str(resources.files("thermojax") / "data" / f"{name}.toml"))


def builtin_model_names() -> list[str]:
    """The names `--model` takes besides a file path (`imu6`, `rtd2`, ...)."""
    folder = resources.files("thermojax") / "data"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def _resolve_model(arg: str) -> Path:
    """A model file path, or the name of a built-in model (`imu6`, `rtd2`)."""
    path = Path(arg)
    if not path.exists() and path.suffix == "":
        if _builtin_model_path(arg).exists():
            return _builtin_model_path(arg)
        raise InputError(f"model file not found, and no built-in model is called '{arg}'; "
                         f"the built-in models are {', '.join(builtin_model_names())}. Give "
                         "the path of a model TOML file or one of these names.",
                         file=arg, field="--model")
    return path


def _whole_number(minimum: int):
    """An argparse type: a whole number of at least `minimum`, named in the message."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if value < minimum:
            words = "0 or more" if minimum == 0 else f"at least {minimum}"
            raise argparse.ArgumentTypeError(f"must be {words}, got {value}")
        return value

    return parse


_positive_int, _nonnegative_int = _whole_number(1), _whole_number(0)


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not np.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def rate_hz(text: str):
    """An argparse type: a rate in Hz as a number (`20`, `0.5`) or a fraction (`1/1800`),
    returned as an exact `fractions.Fraction` so that the period recorded is the one meant.

    A decimal with more than six significant digits is read as a rounded inverse of a
    period: when a period of at most six significant digits has a rate that rounds to
    the digits given, that period is the one meant (`0.000555555555556` is 1/1800 Hz, a
    period of 1800 s, not 1799.99999999856 s); otherwise the rate is the decimal as
    given.
    """
    from decimal import Decimal, InvalidOperation, localcontext
    from fractions import Fraction

    def number(part: str) -> Decimal:
        try:
            value = Decimal(part.strip())
        except InvalidOperation:
            raise argparse.ArgumentTypeError(
                f"expected a rate in Hz, a number (20) or a fraction (1/1800), got {text!r}"
            ) from None
        if not value.is_finite() or value <= 0:
            raise argparse.ArgumentTypeError(f"must be a positive number of Hz, got {text}")
        return value

    if "/" in text:
        top, _, bottom = text.partition("/")
        return Fraction(number(top)) / Fraction(number(bottom))
    value = number(text)
    digits = value.as_tuple()
    if len(digits.digits) > 6:
        with localcontext() as ctx:
            ctx.prec = 40
            period = Decimal(1) / value
            meant = Decimal(f"{period:.6g}")
            if abs(Decimal(1) / meant - value) <= Decimal(5).scaleb(digits.exponent - 1):
                return 1 / Fraction(meant)
    return Fraction(value)


def _finite_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not np.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
    return value


def _add_quiet(p) -> None:
    """--quiet and --no-cache: every command that runs a model has both."""
    p.add_argument("--quiet", action="store_true",
                   help="print no progress (results and errors only)")
    p.add_argument("--no-cache", action="store_true",
                   help="do not read or write the persistent cache of compiled programs "
                   "(default: on, in ~/.cache/thermojax or $THERMOJAX_CACHE_DIR)")


def _add_force(p, what: str) -> None:
    p.add_argument("--force", action="store_true",
                   help=f"replace {what} even if thermojax did not write it")

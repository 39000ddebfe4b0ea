"""Fixed-point formats and the three integer primitives: rounding shift, saturation, encoding.

Every fixed-point number in the reference is an integer code `c` standing for the real
value `c * 2**-frac_bits` (times a physical scale, see `FixedScaling`). Arithmetic is done
on Python/NumPy `int64` and mirrored operation for operation by the generated C.

Rounding rule: round to nearest, ties toward +infinity, i.e. `(a + 2**(s-1)) >> s` with an
arithmetic (flooring) right shift. It is the cheapest exact rounding on every
microcontroller; its only asymmetry is at exact ties.

Saturation: results are clamped to the data word, `[-2**(w-1), 2**(w-1) - 1]`.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class FixedFormat:
    """A signed fixed-point data format: `word_bits`-bit two's-complement words with
    `frac_bits` fractional bits, and the physical size of one unit of state.

    **Arguments:**

    - `name`: the format's name (`"q16.16"`, `"q8.24"`, `"q15"`, `"q31"`).
    - `word_bits`: 32 or 16; coefficients are stored in the same word size.
    - `frac_bits`: fractional bits of states, inputs, measurements and (unless a matrix
      needs a right shift to fit) coefficients.
    - `state_scale`: kelvin per unit of the format for states and measurements (1 K for
      Q16.16 and Q8.24; 128 K for Q15 and Q31, whose values must lie in `[-1, 1)`).
    """

    name: str
    word_bits: int
    frac_bits: int
    state_scale: float

    @property
    def word_min(self) -> int:
        return -(1 << (self.word_bits - 1))

    @property
    def word_max(self) -> int:
        return (1 << (self.word_bits - 1)) - 1

    @property
    def lsb(self) -> float:
        """One code of state, in kelvin."""
        return self.state_scale * 2.0 ** -self.frac_bits

    @property
    def state_range(self) -> tuple[float, float]:
        """The representable state offsets, in kelvin (from the reference temperature)."""
        return self.word_min * self.lsb, self.word_max * self.lsb


Q16_16 = FixedFormat("q16.16", 32, 16, 1.0)
Q8_24 = FixedFormat("q8.24", 32, 24, 1.0)
Q15 = FixedFormat("q15", 16, 15, 128.0)
Q31 = FixedFormat("q31", 32, 31, 128.0)
FORMATS = {f.name: f for f in (Q16_16, Q8_24, Q15, Q31)}


def fixed_format(fmt: FixedFormat | str) -> FixedFormat:
    """`fmt` itself, or the built-in format of that name (`"q16.16"`, `"q8.24"`, `"q15"`,
    `"q31"`)."""
    if isinstance(fmt, FixedFormat):
        return fmt
    key = str(fmt).lower().replace("_", ".")
    if key not in FORMATS:
        raise ValueError(f"`fixed_format({fmt!r})`: unknown format; expected one of "
                         f"{sorted(FORMATS)} or a `FixedFormat(...)`.")
    return FORMATS[key]


def round_shift(a, s: int):
    """`a * 2**-s` rounded to nearest, ties toward +inf (`(a + 2**(s-1)) >> s`), on int64."""
    a = np.asarray(a, dtype=np.int64)
    if s <= 0:
        return a << np.int64(-s)
    return (a + np.int64(1 << (s - 1))) >> np.int64(s)


def saturate(a, fmt: FixedFormat):
    """Clamp int64 values to the data word of `fmt`."""
    return np.clip(np.asarray(a, dtype=np.int64), fmt.word_min, fmt.word_max)


def encode(values, frac_bits: int, fmt: FixedFormat, offset=0.0, scale=1.0):
    """Codes of physical `values`: `sat(floor((v - offset) / scale * 2**frac_bits + 1/2))`.

    NaN (not readable) gives the word's minimum, `-inf` and `+inf` its ends: codes that no
    exclusive limit lets through (`_faults.py`), so a bad value is flagged, never used.
    The same rule as `round_shift` (nearest, ties toward +inf), computed in float64 (an
    ADC driver's job, outside the bit-exact core; the generated C takes codes).
    """
    z = (np.asarray(values, dtype=np.float64) - offset) / scale * 2.0 ** frac_bits
    with np.errstate(invalid="ignore"):
        z = np.floor(z + 0.5)
        z = np.clip(np.where(np.isnan(z), fmt.word_min, z), fmt.word_min, fmt.word_max)
    return z.astype(np.int64)


def decode(codes, frac_bits: int, offset=0.0, scale=1.0):
    """Physical values of codes: `offset + code * 2**-frac_bits * scale`."""
    return offset + np.asarray(codes, dtype=np.float64) * 2.0 ** -frac_bits * scale

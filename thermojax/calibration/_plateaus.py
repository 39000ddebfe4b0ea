"""Static polynomial extraction: dwell plateaus found in the data, and the bias
polynomial in temperature fitted through their means."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._errors import InputError

#: Highest order of the static polynomial.
MAX_ORDER = 5


@dataclass(frozen=True)
class Plateau:
    """One settled dwell: the samples `start_s`…`end_s` (s, the settle margin already
    skipped), `n` samples, the mean and scatter of temperature (°C) and bias (its unit;
    NaN when no bias was given or none is finite)."""

    start_s: float
    end_s: float
    n: int
    temperature: float
    temperature_std: float
    bias: float
    bias_std: float


def _rate(ts, temperature, window_s):
    """dT/dt (K/s) as the centred difference over `window_s` of the linearly
    interpolated finite samples (shortened at the ends)."""
    ok = np.isfinite(temperature)
    t, v = ts[ok], temperature[ok]
    lo = np.clip(ts - window_s / 2, ts[0], ts[-1])
    hi = np.clip(ts + window_s / 2, ts[0], ts[-1])
    return (np.interp(hi, t, v) - np.interp(lo, t, v)) / np.maximum(hi - lo, 1e-300)


def find_plateaus(ts, temperature, bias=None, *, max_rate_k_per_min: float = 0.1,
                  min_duration_s: float = 1200.0, settle_s: float = 600.0,
                  rate_window_s: float = 120.0, name: str = "bias") -> list[Plateau]:
    """Dwell plateaus found automatically in a temperature record.

    A dwell is a run of samples where `|dT/dt|` (centred difference over `rate_window_s`)
    stays below `max_rate_k_per_min` for at least `min_duration_s`; the first `settle_s`
    of each dwell are skipped (the unit still settling), the rest is averaged.

    **Arguments:**

    - `ts`: `(samples,)` s, increasing.
    - `temperature`: `(samples,)` °C, the temperature that indexes the polynomial (NaN
      samples are skipped).
    - `bias`: `(samples,)` the inertial output averaged on each plateau, or None.
    - `max_rate_k_per_min`: K/min; `min_duration_s`, `settle_s`, `rate_window_s`: s.
    - `name`: the bias column's name, for messages.

    **Returns:** the plateaus in time order.
    """
    ts = np.asarray(ts, dtype=float)
    T = np.asarray(temperature, dtype=float)
    y = np.full(ts.shape, np.nan) if bias is None else np.asarray(bias, dtype=float)
    if not (ts.shape == T.shape == y.shape) or ts.ndim != 1:
        raise InputError(f"times, temperature and bias must be equally long columns, got "
                         f"shapes {ts.shape}, {T.shape}, {y.shape}.", field=name)
    if bias is not None and not np.isfinite(y).any():
        raise InputError("the bias column is all NaN: there is nothing to average on the "
                         "dwell plateaus.", field=name)
    if np.isfinite(T).sum() < 2:
        raise InputError("the temperature needs at least two finite samples.",
                         field="temperature")
    if settle_s >= min_duration_s:
        raise InputError(f"the settle margin ({settle_s:g} s) must be shorter than the minimum "
                         f"dwell ({min_duration_s:g} s).", field="settle_s")
    slow = np.abs(_rate(ts, T, rate_window_s)) * 60.0 < max_rate_k_per_min
    edges = np.diff(np.concatenate([[0], slow.astype(int), [0]]))
    plateaus = []
    for a, b in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)):
        if ts[b - 1] - ts[a] < min_duration_s:
            continue
        keep = np.arange(a, b)[ts[a:b] >= ts[a] + settle_s]
        t_k, y_k = T[keep], y[keep]
        t_k, y_k = t_k[np.isfinite(t_k)], y_k[np.isfinite(y_k)]
        plateaus.append(Plateau(
            start_s=float(ts[keep[0]]), end_s=float(ts[keep[-1]]), n=int(keep.size),
            temperature=float(t_k.mean()), temperature_std=float(t_k.std()),
            bias=float(y_k.mean()) if y_k.size else float("nan"),
            bias_std=float(y_k.std()) if y_k.size else float("nan")))
    return plateaus


@dataclass(frozen=True)
class StaticPolynomial:
    """`bias(T) = Σ_k coefficients[k] (T − reference_c)^k`, k = 0…order, with the
    coefficients' standard deviations `std` and `covariance` (bias unit / K^k)."""

    coefficients: np.ndarray
    std: np.ndarray
    covariance: np.ndarray
    reference_c: float
    residual_rms: float

    @property
    def order(self) -> int:
        return len(self.coefficients) - 1

    def __call__(self, temperature) -> np.ndarray:
        """The polynomial at `temperature` (°C, any shape)."""
        dT = np.asarray(temperature, dtype=float) - self.reference_c
        return np.polynomial.polynomial.polyval(dT, self.coefficients)


def _ordinal(n: int) -> str:
    """1st, 2nd, 3rd, 4th, 5th (orders are 0…5)."""
    suffix = {1: "st", 2: "nd", 3: "rd"}.get(n, "th")
    return f"{n}{suffix}"


def fit_static_polynomial(temperatures, biases, order: int, bias_std=None, *,
                          reference_c: float = 25.0, name: str = "bias") -> StaticPolynomial:
    """Least-squares polynomial in `(T − 25 °C)` through the plateau means.

    With `bias_std` the fit is weighted and the covariance is `(Aᵀ W A)⁻¹` (absolute
    uncertainties); without, it is `s² (Aᵀ A)⁻¹` with `s²` the residual variance
    (NaN stds where there are exactly as many plateaus as coefficients).

    **Arguments:**

    - `temperatures`, `biases`: `(plateaus,)` °C and the bias unit (e.g. from
      `find_plateaus`); pairs with a non-finite value are skipped.
    - `order`: 0…5.
    - `bias_std`: `(plateaus,)` the standard deviation of each plateau's bias, or None.
    - `name`: the bias column's name, for messages.

    **Returns:** a `StaticPolynomial`.
    """
    T = np.asarray(temperatures, dtype=float).ravel()
    y = np.asarray(biases, dtype=float).ravel()
    s = None if bias_std is None else np.asarray(bias_std, dtype=float).ravel()
    if not 0 <= int(order) <= MAX_ORDER or int(order) != order:
        raise InputError(f"the static polynomial's order must be 0…{MAX_ORDER}, got {order!r}.",
                         field="order")
    order = int(order)
    if y.size and not np.isfinite(y).any():
        raise InputError("the bias is NaN on every plateau: there is nothing to fit.",
                         field=name)
    use = np.isfinite(T) & np.isfinite(y)
    if s is not None:
        use &= np.isfinite(s) & (s > 0)
    n = int(use.sum())
    if n < order + 1:
        raise InputError(
            f"found {n} dwell plateau{'s' if n != 1 else ''}; a {_ordinal(order)}-order "
            f"polynomial needs at least {order + 1}: lower the order to {max(n - 1, 0)}, add "
            "dwells at more temperatures to the profile, or loosen `find_plateaus` "
            "(max_rate_k_per_min, min_duration_s).", field=name)
    dT = T[use] - reference_c
    w = np.ones(n) if s is None else 1.0 / s[use]
    A = dT[:, None] ** np.arange(order + 1)[None, :]
    scale = np.max(np.abs(A), axis=0)
    scale[scale == 0] = 1.0
    Aw = A * w[:, None] / scale
    if np.linalg.matrix_rank(Aw) < order + 1:
        distinct = np.unique(np.round(T[use], 3)).size
        raise InputError(f"found {n} dwell plateaus but only {distinct} distinct temperatures; a "
                         f"{_ordinal(order)}-order polynomial needs {order + 1}: lower the order "
                         "or add dwells at other temperatures.", field=name)
    beta_s, *_ = np.linalg.lstsq(Aw, y[use] * w, rcond=None)
    beta = beta_s / scale
    resid = y[use] - A @ beta
    cov_s = np.linalg.inv(Aw.T @ Aw)
    if s is None:
        cov_s = cov_s * (float(resid @ resid) / (n - order - 1) if n > order + 1 else np.nan)
    cov = cov_s / np.outer(scale, scale)
    return StaticPolynomial(coefficients=beta, std=np.sqrt(np.diag(cov)), covariance=cov,
                            reference_c=reference_c,
                            residual_rms=float(np.sqrt(np.mean(resid ** 2))))

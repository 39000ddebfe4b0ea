"""Read back the observer artifact written by `thermojax export` (NumPy and the standard
library only), checking its schema version and every array before anything runs."""

from __future__ import annotations

import dataclasses
import json
import zipfile
from pathlib import Path

import numpy as np

from .._errors import InputError
from . import _artifact_checks as checks
from ._bias import BiasEvaluator, bias_channels_from_metadata
from ._faults import FaultConfig
from ._fixed import FixedObserver, FixedScaling
from ._float import FloatObserver
from ._formats import FixedFormat
from ._system import ObserverSystem

SCHEMA = 1
META = "observer.json"
ARRAYS = "observer.npz"
REQUIRED_FIELDS = ("schema", "thermojax_version", "model", "rate_hz", "dt_s", "states",
                   "inputs", "outputs", "plausibility_limits_C", "faults", "fixed", "biases")
REQUIRED_ARRAYS = ("Phi", "B0", "B1", "C", "D", "gain_table", "x_ref", "u_ref", "y_ref",
                   "output_offset")


class ArtifactError(InputError):
    """An observer artifact that cannot be used: missing file, field or array, another
    schema version, or inconsistent shapes. The message names the file and the item."""


@dataclasses.dataclass(frozen=True, eq=False)
class ObserverArtifact:
    """An artifact read by `load_observer`.

    - `folder`: where it was read from.
    - `metadata`: `observer.json` as a dict.
    - `arrays`: `observer.npz` as a dict of arrays.
    - `system`: the `ObserverSystem` (matrices and gain table, float64).
    - `faults`: the `FaultConfig` of the artifact.
    """

    folder: Path
    metadata: dict
    arrays: dict
    system: ObserverSystem
    faults: FaultConfig

    @property
    def state_names(self) -> list[str]:
        return [s["name"] for s in self.metadata["states"]]

    @property
    def input_names(self) -> list[str]:
        return [s["name"] for s in self.metadata["inputs"]]

    @property
    def output_names(self) -> list[str]:
        return [s["name"] for s in self.metadata["outputs"]]

    @property
    def dt(self) -> float:
        return float(self.metadata["dt_s"])

    def bias_evaluator(self) -> BiasEvaluator | None:
        """The artifact's bias channels (those with fitted coefficients) as a
        `BiasEvaluator`, or None when there are none. Rate terms use the arrays
        `bias_rate_nodes`, `bias_rate_A`, `bias_rate_B` (rows of the continuous model)."""
        try:
            channels = bias_channels_from_metadata(self.metadata["biases"], self.state_names)
        except (KeyError, TypeError, ValueError) as err:
            raise ArtifactError(f"the bias channels cannot be evaluated ({err!r}).",
                                file=str(self.folder / META), field="biases") from None
        if not channels:
            return None
        a = self.arrays
        if any(ch.rates for ch in channels):
            for key in ("bias_rate_nodes", "bias_rate_A", "bias_rate_B"):
                if key not in a:
                    raise ArtifactError(f"the array '{key}' is missing (needed by the bias "
                                        "channels' rate terms).", file=str(self.folder / ARRAYS),
                                        field=key)
            A, B, rows = a["bias_rate_A"], a["bias_rate_B"], a["bias_rate_nodes"]
        else:
            A = B = rows = None
        try:
            return BiasEvaluator(channels, self.dt, A, B, rows)
        except ValueError as err:
            raise ArtifactError(str(err), file=str(self.folder / ARRAYS),
                                field="bias_rate_A") from None

    @property
    def names(self) -> tuple:
        """`(states, inputs, outputs)` names (used in the generated C's comments)."""
        return self.state_names, self.input_names, self.output_names

    def scheduled_observer(self):
        """The artifact's gain-scheduled observer (exported with `--schedule`) as a
        `ScheduledObserver`, from the `schedule_*` arrays."""
        from ._scheduled import ScheduledDesign, ScheduledObserver

        sc = self.metadata.get("schedule")
        if sc is None:
            raise ArtifactError("the artifact has no gain schedule (exported without "
                                "--schedule).", file=str(self.folder / META), field="schedule")
        names = ("points", "Phi", "B0", "B1", "L", "C", "D")
        missing = [f"schedule_{k}" for k in names if f"schedule_{k}" not in self.arrays]
        if missing:
            raise ArtifactError(f"the arrays {missing} are missing.",
                                file=str(self.folder / ARRAYS), field=missing[0])
        try:
            design = ScheduledDesign(*(self.arrays[f"schedule_{k}"] for k in names),
                                     int(sc["by_index"]))
        except (ValueError, KeyError) as err:
            raise ArtifactError(f"the gain schedule cannot be read ({err}).",
                                file=str(self.folder / META), field="schedule") from None
        return ScheduledObserver(design, reading_limits=tuple(self.faults.limits))

    def trimmed_observer(self, factors=None):
        """The artifact's end-of-line trimmed observer (exported with `--trim`) as a
        `TrimmedObserver` at `factors` (default: the unit's, exported with
        `--trim-factors`), from the `trim_*` arrays."""
        from ._trimmed import TrimDesign, TrimmedObserver

        tr = self.metadata.get("trim")
        if tr is None:
            raise ArtifactError("the artifact has no trim (exported without --trim).",
                                file=str(self.folder / META), field="trim")
        names = ("grid", "sizes", "Phi", "B0", "B1", "L", "C", "D")
        missing = [f"trim_{k}" for k in names if f"trim_{k}" not in self.arrays]
        if missing:
            raise ArtifactError(f"the arrays {missing} are missing.",
                                file=str(self.folder / ARRAYS), field=missing[0])
        if factors is None:
            if tr.get("unit") is None:
                raise ArtifactError("no unit's factors in the artifact (exported without "
                                    "--trim-factors): pass them.", file=str(self.folder / META),
                                    field="trim.unit")
            factors = tr["unit"]["factors"]
        a = {k: self.arrays[f"trim_{k}"] for k in names}
        try:
            grids = tuple(np.split(a["grid"], np.cumsum(a["sizes"])[:-1]))
            design = TrimDesign(tuple(f["name"] for f in tr["factors"]), grids, a["Phi"],
                                a["B0"], a["B1"], a["L"], a["C"], a["D"])
        except (ValueError, KeyError) as err:
            raise ArtifactError(f"the trim cannot be read ({err}).",
                                file=str(self.folder / META), field="trim") from None
        return TrimmedObserver(design, factors, reading_limits=tuple(self.faults.limits))

    def adaptive_reference(self):
        """The artifact's firmware adaptive filter (exported with `--adaptive`) as an
        `AdaptiveReference`, from the design in `observer.json`."""
        from ._adaptive import AdaptiveDesign, AdaptiveReference

        ad = self.metadata.get("adaptive")
        if ad is None:
            raise ArtifactError("the artifact has no adaptive filter (exported without "
                                "--adaptive).", file=str(self.folder / META), field="adaptive")
        d = ad["design"]
        try:
            design = AdaptiveDesign(**{k: tuple(tuple(e) if isinstance(e, list) else e
                                                for e in v) if isinstance(v, list) else v
                                       for k, v in d.items()})
        except TypeError as err:
            raise ArtifactError(f"the adaptive design cannot be read ({err}).",
                                file=str(self.folder / META), field="adaptive") from None
        return AdaptiveReference(design)

    def float_observer(self, dtype=np.float64) -> FloatObserver:
        """The float reference observer (float64 or float32) of the artifact, evaluating its
        bias channels (`ObserverRun.bias`) when it has fitted ones."""
        obs = FloatObserver(self.system, self.faults, dtype=dtype, biases=self.bias_evaluator())
        obs.names = self.names
        return obs

    def fixed_observer(self) -> FixedObserver:
        """The fixed-point reference observer of the artifact (exported with `--fixed`);
        its integer coefficients are checked against the stored ones."""
        fx = self.metadata["fixed"]
        if fx is None:
            raise ArtifactError("the artifact has no fixed-point build (exported without "
                                "--fixed).", file=str(self.folder / META), field="fixed")
        fmt = FixedFormat(fx["format"], int(fx["word_bits"]), int(fx["frac_bits"]),
                          float(fx["state_scale_K"]))
        a = self.arrays
        if "u_scale" not in a:
            raise ArtifactError("the array 'u_scale' is missing (needed by the fixed build).",
                                file=str(self.folder / ARRAYS), field="u_scale")
        try:
            obs = FixedObserver(self.system, fmt,
                                FixedScaling(a["x_ref"], a["y_ref"], a["u_ref"], a["u_scale"]),
                                self.faults, biases=self.bias_evaluator())
        except ValueError as err:
            raise ArtifactError(f"the fixed-point build cannot be made from the artifact "
                                f"({err})", file=str(self.folder / META),
                                field="fixed") from None
        for name in obs.MATRICES:
            key = f"fixed_{name}"
            if key not in a:
                raise ArtifactError(f"the array '{key}' is missing (the fixed build's "
                                    "integer coefficients).", file=str(self.folder / ARRAYS),
                                    field=key)
            if not np.array_equal(a[key], obs.coef[name]):
                raise ArtifactError(f"the stored integer coefficients '{key}' differ from "
                                    f"those the reference computes from the float matrices; "
                                    "the artifact was modified or written by an "
                                    "incompatible version.", file=str(self.folder / ARRAYS),
                                    field=key)
        obs.names = self.names
        return obs


def _rail_pairs(rails):
    if rails is None:
        return None
    return [[-np.inf if lo is None else lo, np.inf if hi is None else hi] for lo, hi in rails]


def load_observer(folder) -> ObserverArtifact:
    """Read and check an observer artifact folder (`observer.json` + `observer.npz`).

    **Arguments:**

    - `folder`: the folder `thermojax export --out` wrote.

    **Returns:** an `ObserverArtifact`.

    **Raises:** `ArtifactError` (an `InputError`, so a `ValueError`) naming the file and the
    missing or bad field or array, or the schema version found and the one expected.
    """
    folder = Path(folder)
    meta_path, npz_path = folder / META, folder / ARRAYS
    if not meta_path.is_file():
        raise ArtifactError(f"no {META} in '{folder}': not an observer artifact (write one "
                            "with `thermojax export`).", file=str(meta_path))
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ArtifactError(f"not valid JSON ({err}).", file=str(meta_path)) from None
    if not isinstance(meta, dict):
        raise ArtifactError("expected a JSON object.", file=str(meta_path))
    if "schema" not in meta:
        raise ArtifactError("the field 'schema' is missing.", file=str(meta_path),
                            field="schema")
    if meta["schema"] != SCHEMA:
        raise ArtifactError(f"schema version {meta['schema']!r}, but this thermojax reads "
                            f"schema {SCHEMA}; export the observer again with this version.",
                            file=str(meta_path), field="schema")
    for key in REQUIRED_FIELDS:
        if key not in meta:
            raise ArtifactError(f"the field '{key}' is missing.", file=str(meta_path),
                                field=key)
    checks.check_metadata(meta, meta_path, ArtifactError)
    if not npz_path.is_file():
        raise ArtifactError(f"the array file is missing from '{folder}'.", file=str(npz_path))
    try:
        with open(npz_path, "rb") as fh:  # closed here even where np.load fails midway
            z = np.load(fh, allow_pickle=False)
            if not isinstance(z, np.lib.npyio.NpzFile):
                raise ValueError("a single array, not an .npz archive")
            with z:
                arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as err:
        raise ArtifactError(f"cannot be read as .npz ({err}).", file=str(npz_path)) from None
    for key in REQUIRED_ARRAYS:
        if key not in arrays:
            raise ArtifactError(f"the array '{key}' is missing.", file=str(npz_path), field=key)
    n, m, p = len(meta["states"]), len(meta["inputs"]), len(meta["outputs"])
    shapes = {"Phi": (n, n), "B0": (n, m), "B1": (n, m), "C": (p, n), "D": (p, m),
              "gain_table": (1 << p, n, p), "x_ref": (n,), "u_ref": (m,), "y_ref": (p,),
              "output_offset": (p,)}
    for key, shape in shapes.items():
        a = arrays[key]
        if a.shape != shape:
            raise ArtifactError(f"the array '{key}' has shape {a.shape}; {META} names {n} "
                                f"states, {m} inputs and {p} outputs, so expected {shape}.",
                                file=str(npz_path), field=key)
        if not np.issubdtype(a.dtype, np.floating) or not np.all(np.isfinite(a)):
            raise ArtifactError(f"the array '{key}' must hold finite floats.",
                                file=str(npz_path), field=key)
    a = arrays
    gains = {tuple(j for j in range(p) if mask >> j & 1):
             a["gain_table"][mask][:, [j for j in range(p) if mask >> j & 1]]
             for mask in range(1, 1 << p)}
    try:
        system = ObserverSystem.build(a["Phi"], a["B0"], a["B1"], a["C"], a["D"], gains)
    except ValueError as err:
        raise ArtifactError(f"the matrices do not make an observer ({err}).",
                            file=str(npz_path), field="Phi") from None
    if not np.array_equal(system.gain_table, a["gain_table"]):
        raise ArtifactError("the array 'gain_table' has nonzero gains for sensors outside "
                            "their subset.", file=str(npz_path), field="gain_table")
    checks.check_dynamics(a, system, npz_path, ArtifactError,
                          integrating=meta.get("reconstruct") is not None)
    checks.check_hash(meta, arrays, meta_path, ArtifactError)
    f = meta["faults"]
    try:
        faults = FaultConfig(limits=tuple(f["limits_C"]), rails=_rail_pairs(f["rails_C"]),
                             residual_threshold=[np.inf if v is None else v
                                                 for v in f["residual_threshold_K"]],
                             wire_break_after=int(f["wire_break_after"]),
                             recover_after=int(f["recover_after"]),
                             # absent in artifacts written before input supervision: the
                             # default (`default_input_limits`)
                             input_limits=_rail_pairs(f.get("input_limits")),
                             gate=bool(f.get("gate", False)))   # absent before gating
        faults.input_limits_array(system)          # checks the input limits' shape
    except (KeyError, TypeError, ValueError) as err:
        raise ArtifactError(f"the fault settings are incomplete or invalid ({err!r}).",
                            file=str(meta_path), field="faults") from None
    return ObserverArtifact(folder, meta, arrays, system, faults)

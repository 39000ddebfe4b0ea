"""Model TOML files (docs/formats.md §2): read with tomllib into a validated `ModelSpec`, and write back."""

from __future__ import annotations

import math
import re
import tomllib
from pathlib import Path
from typing import Any

from .._errors import InputError
from ._spec import (Bias, Boundary, Effect, HeatInput, Link, ModelSpec, Node, Parameter, Sensor,
                    validate)

_TABLES = ("nodes", "links", "boundaries", "heat_inputs", "sensors", "effects", "biases")
_TOP_KEYS = {"name", "description", *_TABLES}


def load_model(path: str | Path) -> ModelSpec:
    """Read and validate a model file. Raises `InputError` naming the file, line and field."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise InputError("model file not found; check the path.", file=str(path)) from None
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"cannot read the model file ({err}).", file=str(path)) from None
    return parse_model(text, source=str(path))


def parse_model(text: str, source: str = "<model>") -> ModelSpec:
    """Parse model TOML text (see `load_model`)."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        m = re.search(r"line (\d+)", str(err))
        raise InputError(f"TOML syntax error: {err}. Fix the syntax at that line.", file=source,
                         line=int(m.group(1)) if m else None) from None
    lines = _entry_lines(text)
    reader = _Reader(source, lines, text.splitlines())
    unknown = set(doc) - _TOP_KEYS
    if unknown:
        key = sorted(unknown)[0]
        raise InputError(f"unknown top-level key '{key}'{_closest(key, _TOP_KEYS)}; allowed "
                         f"are {sorted(_TOP_KEYS)}.", file=source,
                         line=_key_line(text.splitlines(), key, 0, top=True), field=key)
    for t in _TABLES:
        if t in doc and not (isinstance(doc[t], list) and all(isinstance(e, dict) for e in doc[t])):
            raise InputError(f"'{t}' must be an array of tables, written [[{t}]].", file=source,
                             field=t)
    spec = ModelSpec(
        name=str(doc.get("name", Path(source).stem)),
        nodes=tuple(reader.node(e, i) for i, e in enumerate(doc.get("nodes", []))),
        links=tuple(reader.link(e, i) for i, e in enumerate(doc.get("links", []))),
        boundaries=tuple(reader.boundary(e, i) for i, e in enumerate(doc.get("boundaries", []))),
        heat_inputs=tuple(reader.heat_input(e, i) for i, e in enumerate(doc.get("heat_inputs", []))),
        sensors=tuple(reader.sensor(e, i) for i, e in enumerate(doc.get("sensors", []))),
        effects=tuple(reader.effect(e, i) for i, e in enumerate(doc.get("effects", []))),
        biases=tuple(reader.bias(e, i) for i, e in enumerate(doc.get("biases", []))),
        source=source,
    )
    return validate(spec, lines)


def _entry_lines(text: str) -> dict[tuple[str, int], int]:
    """Map (table, index) to the 1-based line of its `[[table]]` header."""
    counts: dict[str, int] = {}
    out = {}
    for lineno, line in enumerate(text.splitlines(), start=1):
        m = re.match(r"\s*\[\[\s*([A-Za-z_]+)\s*\]\]", line)
        if m:
            t = m.group(1)
            out[(t, counts.get(t, 0))] = lineno
            counts[t] = counts.get(t, 0) + 1
    return out


def _closest(key: str, allowed) -> str:
    """`; did you mean 'conductance'?` for a misspelt key, or nothing."""
    import difflib

    match = difflib.get_close_matches(key, sorted(allowed), n=1, cutoff=0.6)
    return f" (did you mean '{match[0]}'?)" if match else ""


def _key_line(text_lines: list[str], key: str, start: int, top: bool = False) -> int | None:
    """1-based line where `key = ...` is written in the entry whose header is line
    `start` (0: the top of the file), before the next table header; a top-level
    `[key]` or `[[key]]` header counts too (`top`)."""
    pattern = re.compile(rf"""\s*(["']?){re.escape(key)}\1\s*=""")
    header = re.compile(rf"\s*\[\[?\s*{re.escape(key)}\s*\]") if top else None
    for lineno in range(start + 1, len(text_lines) + 1):
        line = text_lines[lineno - 1]
        if header is not None and header.match(line):
            return lineno
        if line.lstrip().startswith("[") and not top:
            break
        if pattern.match(line) and not (top and _in_table(text_lines, lineno)):
            return lineno
    return None


def _in_table(text_lines: list[str], lineno: int) -> bool:
    """Whether line `lineno` lies below some table header (so is not a top-level key)."""
    return any(line.lstrip().startswith("[") for line in text_lines[:lineno - 1])


class _Reader:
    """Turns one TOML table entry into a spec object, with messages that point at it."""

    def __init__(self, source: str, lines: dict[tuple[str, int], int],
                 text_lines: list[str] | None = None):
        self.source = source
        self.lines = lines
        self.text_lines = text_lines or []

    def fail(self, msg: str, table: str, i: int, fld: str):
        raise InputError(msg, file=self.source, line=self.lines.get((table, i)),
                         field=f"{table}[{i}].{fld}")

    def keys(self, e: dict, table: str, i: int, required: tuple[str, ...], optional: tuple[str, ...]):
        # an unknown key first: a misspelt required key is named as written, at its own
        # line, not reported as a missing one at the table's header
        allowed = (*required, *optional)
        extra = sorted(set(e) - set(allowed))
        if extra:
            key = extra[0]
            header = self.lines.get((table, i))
            line = (_key_line(self.text_lines, key, header) if header is not None else None)
            raise InputError(f"unknown key '{key}' in this [[{table}]] entry"
                             f"{_closest(key, allowed)}; allowed are {sorted(allowed)}.",
                             file=self.source, line=line or header,
                             field=f"{table}[{i}].{key}")
        for k in required:
            if k not in e:
                self.fail(f"missing required key '{k}'.", table, i, k)

    def param(self, v: Any, table: str, i: int, fld: str) -> Parameter:
        if isinstance(v, dict):
            if "value" not in v or set(v) - {"value", "fixed"}:
                self.fail("a parameter table is written { value = 0.8, fixed = true }.", table, i, fld)
            fixed = v.get("fixed", False)
            if not isinstance(fixed, bool):
                self.fail("'fixed' must be true or false.", table, i, fld)
            return Parameter(self.number(v["value"], table, i, fld), fixed)
        return Parameter(self.number(v, table, i, fld), False)

    def known_number(self, v: Any, table: str, i: int, fld: str) -> float:
        """A number the fit never estimates: bare, or written as a fixed parameter table
        `{ value = 0.1, fixed = true }` (docs/formats.md §2's general rule)."""
        if isinstance(v, dict):
            p = self.param(v, table, i, fld)
            if not p.fixed:
                self.fail(f"{fld} is not estimated; write a number or "
                          "{ value = ..., fixed = true }.", table, i, fld)
            return p.value
        return self.number(v, table, i, fld)

    def opt_param(self, e: dict, key: str, table: str, i: int) -> Parameter | None:
        return self.param(e[key], table, i, key) if key in e else None

    def number(self, v: Any, table: str, i: int, fld: str) -> float:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            self.fail(f"expected a finite number, got {v!r}.", table, i, fld)
        return float(v)

    def string(self, v: Any, table: str, i: int, fld: str) -> str:
        if not isinstance(v, str) or not v:
            self.fail(f"expected a non-empty string, got {v!r}.", table, i, fld)
        return v

    def names(self, v: Any, table: str, i: int, fld: str) -> tuple[str, ...]:
        if not isinstance(v, list) or not all(isinstance(s, str) and s for s in v):
            self.fail(f"expected a list of names, got {v!r}.", table, i, fld)
        return tuple(v)

    def node(self, e: dict, i: int) -> Node:
        self.keys(e, "nodes", i, ("name", "capacitance"), ("process_noise", "initial", "initial_std"))
        std = e.get("initial_std")
        steady = e.get("initial") == "steady"
        if isinstance(e.get("initial"), str) and not steady:
            self.fail(f"initial must be a temperature in °C, a table {{ value = ..., fixed = "
                      f"true }} or \"steady\", got {e['initial']!r}.", "nodes", i, "initial")
        return Node(
            name=self.string(e["name"], "nodes", i, "name"),
            capacitance=self.param(e["capacitance"], "nodes", i, "capacitance"),
            process_noise=self.opt_param(e, "process_noise", "nodes", i),
            initial=None if steady else self.opt_param(e, "initial", "nodes", i),
            steady=steady,
            initial_std=None if std is None else self.known_number(std, "nodes", i,
                                                                   "initial_std"),
        )

    def link(self, e: dict, i: int) -> Link:
        self.keys(e, "links", i, ("between", "conductance"), ())
        return Link(self.names(e["between"], "links", i, "between"),
                    self.param(e["conductance"], "links", i, "conductance"))

    def boundary(self, e: dict, i: int) -> Boundary:
        self.keys(e, "boundaries", i, ("node", "input", "conductance"), ("hold",))
        return Boundary(self.string(e["node"], "boundaries", i, "node"),
                        self.string(e["input"], "boundaries", i, "input"),
                        self.param(e["conductance"], "boundaries", i, "conductance"),
                        self.string(e.get("hold", "foh"), "boundaries", i, "hold"))

    def heat_input(self, e: dict, i: int) -> HeatInput:
        self.keys(e, "heat_inputs", i, ("node", "input"), ("gain", "hold"))
        gain = self.param(e["gain"], "heat_inputs", i, "gain") if "gain" in e else Parameter(1.0, True)
        return HeatInput(self.string(e["node"], "heat_inputs", i, "node"),
                         self.string(e["input"], "heat_inputs", i, "input"), gain,
                         self.string(e.get("hold", "foh"), "heat_inputs", i, "hold"),
                         hold_written="hold" in e)

    def sensor(self, e: dict, i: int) -> Sensor:
        self.keys(e, "sensors", i, ("node", "column"), ("noise",))
        return Sensor(self.string(e["node"], "sensors", i, "node"),
                      self.string(e["column"], "sensors", i, "column"),
                      self.opt_param(e, "noise", "sensors", i))

    def effect(self, e: dict, i: int) -> Effect:
        if "kind" not in e:
            self.fail("missing required key 'kind'.", "effects", i, "kind")
        if "where" not in e:
            self.fail("missing required key 'where'.", "effects", i, "where")
        if e.get("kind") == "expression":
            return self.expression(e, i)
        params = {k: self.param(v, "effects", i, k) for k, v in e.items()
                  if k not in ("kind", "where", "name", "hold")}
        name = e.get("name")
        hold = e.get("hold")
        if hold is not None and hold not in ("foh", "zoh"):
            self.fail(f"hold must be \"foh\" or \"zoh\", got {hold!r}.", "effects", i, "hold")
        return Effect(kind=self.string(e["kind"], "effects", i, "kind"),
                      where=self.names(e["where"], "effects", i, "where"),
                      parameters=params,
                      name=None if name is None else self.string(name, "effects", i, "name"),
                      hold=hold)

    def expression(self, e: dict, i: int) -> Effect:
        """An `expression` effect (§3a): `expression` and a `parameters` table."""
        self.keys(e, "effects", i, ("kind", "where", "expression"), ("parameters", "hold"))
        table = e.get("parameters", {})
        if not isinstance(table, dict):
            self.fail("parameters is a table, parameters = { h = 0.31 }.", "effects", i,
                      "parameters")
        hold = e.get("hold")
        if hold is not None and hold not in ("foh", "zoh"):
            self.fail(f"hold must be \"foh\" or \"zoh\", got {hold!r}.", "effects", i, "hold")
        return Effect(kind="expression", where=self.names(e["where"], "effects", i, "where"),
                      parameters={k: self.param(v, "effects", i, f"parameters.{k}")
                                  for k, v in table.items()},
                      hold=hold,
                      expression=self.string(e["expression"], "effects", i, "expression"))

    def bias(self, e: dict, i: int) -> Bias:
        self.keys(e, "biases", i, ("column", "temperature"),
                  ("order", "gradients", "rates", "noise", "coefficients"))
        grads = e.get("gradients", [])
        if not isinstance(grads, list) or not all(isinstance(g, list) for g in grads):
            self.fail("gradients is a list of node pairs, [[\"a\", \"b\"]].", "biases", i, "gradients")
        order = e.get("order", 3)
        if isinstance(order, bool) or not isinstance(order, int):
            self.fail(f"order must be an integer, got {order!r}.", "biases", i, "order")
        rates = self.names(e.get("rates", []), "biases", i, "rates")
        coefs = None
        if "coefficients" in e:
            c = e["coefficients"]
            if not isinstance(c, list):
                self.fail(f"coefficients is a list of numbers, got {c!r}.", "biases", i,
                          "coefficients")
            coefs = tuple(self.number(v, "biases", i, "coefficients") for v in c)
            n = order + 1 + len(grads) + len(rates)
            if len(coefs) != n:
                self.fail(f"coefficients needs {n} numbers (order + 1 polynomial terms, then one "
                          f"per gradient, then one per rate), got {len(coefs)}.", "biases", i,
                          "coefficients")
        return Bias(column=self.string(e["column"], "biases", i, "column"),
                    temperature=self.string(e["temperature"], "biases", i, "temperature"),
                    order=order,
                    gradients=tuple(self.names(g, "biases", i, "gradients") for g in grads),
                    rates=rates,
                    noise=self.opt_param(e, "noise", "biases", i),
                    coefficients=coefs)


# ---------------------------------------------------------------------------
# Writing


def dump_model(spec: ModelSpec, header: str = "") -> str:
    """The model as TOML text that `parse_model` reads back to an equal spec."""
    out: list[str] = [f"# {line}" for line in header.splitlines()]
    out.append(f"name = {_str(spec.name)}")
    for n in spec.nodes:
        out += ["", "[[nodes]]", f"name = {_str(n.name)}", f"capacitance = {_param(n.capacitance)}"]
        if n.process_noise is not None:
            out.append(f"process_noise = {_param(n.process_noise)}")
        if n.steady:
            out.append('initial = "steady"')
        elif n.initial is not None and not n.initial_from_data:
            out.append(f"initial = {_param(n.initial)}")
        if n.initial_std is not None:
            out.append(f"initial_std = {_num(n.initial_std)}")
    for link in spec.links:
        out += ["", "[[links]]", f"between = {_list(link.between)}",
                f"conductance = {_param(link.conductance)}"]
    for b in spec.boundaries:
        out += ["", "[[boundaries]]", f"node = {_str(b.node)}", f"input = {_str(b.input)}",
                f"conductance = {_param(b.conductance)}", f"hold = {_str(b.hold)}"]
    for h in spec.heat_inputs:
        out += ["", "[[heat_inputs]]", f"node = {_str(h.node)}", f"input = {_str(h.input)}",
                f"gain = {_param(h.gain)}", f"hold = {_str(h.hold)}"]
    for s in spec.sensors:
        out += ["", "[[sensors]]", f"node = {_str(s.node)}", f"column = {_str(s.column)}"]
        if s.noise is not None:
            out.append(f"noise = {_param(s.noise)}")
    for e in spec.effects:
        out += ["", "[[effects]]", f"kind = {_str(e.kind)}", f"where = {_list(e.where)}"]
        if e.name is not None:
            out.append(f"name = {_str(e.name)}")
        if e.hold is not None:
            out.append(f"hold = {_str(e.hold)}")
        if e.kind == "expression":
            out += [f"expression = {_str(e.expression)}", "parameters = { " + ", ".join(
                f"{k} = {_param(p)}" for k, p in e.parameters.items()) + " }"]
            continue
        out += [f"{k} = {_param(p)}" for k, p in e.parameters.items()]
    for b in spec.biases:
        out += ["", "[[biases]]", f"column = {_str(b.column)}",
                f"temperature = {_str(b.temperature)}", f"order = {b.order}",
                f"gradients = [{', '.join(_list(g) for g in b.gradients)}]",
                f"rates = {_list(b.rates)}"]
        if b.noise is not None:
            out.append(f"noise = {_param(b.noise)}")
        if b.coefficients is not None:
            out.append(f"coefficients = [{', '.join(_num(c) for c in b.coefficients)}]")
    return "\n".join(out) + "\n"


def save_model(spec: ModelSpec, path: str | Path, header: str = "") -> None:
    """Write `spec` as a model file (see `dump_model`)."""
    Path(path).write_text(dump_model(spec, header))


def _num(x: float) -> str:
    return repr(float(x))


def _param(p: Parameter) -> str:
    return f"{{ value = {_num(p.value)}, fixed = true }}" if p.fixed else _num(p.value)


def _str(s: str) -> str:
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _list(xs) -> str:
    return "[" + ", ".join(_str(x) for x in xs) + "]"

"""Model TOML files (formats spec §2): loading the configs, round trips, and every bad input.

A bad model raises `thermojax.InputError` (a `ValueError`) whose message names the
file, the line of the offending `[[table]]` entry, the field, and what to do.
"""

import dataclasses
import re
import tomllib

import pytest

import thermojax as tj
from thermojax import InputError
from thermojax.model._model_file import dump_model, load_model, parse_model, save_model
from thermojax.model._spec import Bias, Effect, ModelSpec, Parameter

from helpers import CONFIGS, ROOT


def without_source(spec: ModelSpec) -> ModelSpec:
    return dataclasses.replace(spec, source=None)


KEY = "<key line>"


def header_line(text: str, table: str, index) -> int:
    """1-based line of the `index`-th `[[table]]` header in `text` (counted independently),
    or with `table` KEY, of the line that is `index` exactly."""
    if table == KEY:
        return text.splitlines().index(index) + 1
    hits = [k for k, line in enumerate(text.splitlines(), start=1)
            if line.strip() == f"[[{table}]]"]
    return hits[index]


# ---------------------------------------------------------------------------
# The shipped configs


def test_rtd2_config():
    text = (CONFIGS / "rtd2.toml").read_text()
    spec = load_model(CONFIGS / "rtd2.toml")
    raw = tomllib.loads(text)
    assert spec.name == "rtd2"
    assert spec.source == str(CONFIGS / "rtd2.toml")
    assert spec.node_names == ("sheath", "core")
    assert [n.capacitance for n in spec.nodes] == [Parameter(0.8), Parameter(0.1)]
    assert all(n.initial is None and n.process_noise is None for n in spec.nodes)
    assert len(spec.links) == len(raw["links"]) == 1
    assert spec.links[0].between == ("sheath", "core")
    assert spec.links[0].conductance == Parameter(0.08333333333333333)
    assert spec.links[0].key == "sheath-core"
    assert len(spec.boundaries) == 1
    b = spec.boundaries[0]
    assert (b.node, b.input, b.conductance, b.hold) == ("sheath", "T_fluid", Parameter(0.2), "foh")
    assert b.key == "sheath-T_fluid"
    assert spec.heat_inputs == () and spec.effects == () and spec.biases == ()
    assert len(spec.sensors) == 1
    s = spec.sensors[0]
    assert (s.node, s.column, s.noise) == ("core", "T_core", Parameter(0.01))
    assert spec.input_columns == ("T_fluid",)
    assert spec.input_holds == ("foh",)
    assert spec.sensor_columns == ("T_core",)


def test_imu6_config():
    text = (CONFIGS / "imu6.toml").read_text()
    spec = load_model(CONFIGS / "imu6.toml")
    raw = tomllib.loads(text)
    assert spec.name == "imu6"
    assert spec.node_names == ("housing", "bulkhead", "pcb", "asic", "mems", "proof_mass")
    assert [n.capacitance.value for n in spec.nodes] == [14.20, 6.85, 2.10, 0.08, 0.05, 0.003]
    assert not any(n.capacitance.fixed for n in spec.nodes)
    assert len(spec.links) == len(raw["links"]) == 6
    assert [(link.between, link.conductance.value) for link in spec.links] == [
        (("housing", "bulkhead"), 0.5), (("bulkhead", "pcb"), 0.1), (("pcb", "asic"), 0.02),
        (("pcb", "mems"), 0.01), (("asic", "mems"), 0.005), (("mems", "proof_mass"), 0.03)]
    assert len(spec.boundaries) == 1
    b = spec.boundaries[0]
    assert (b.node, b.input, b.conductance, b.hold) == ("housing", "T_chamber", Parameter(0.08),
                                                        "foh")
    assert len(spec.heat_inputs) == 1
    h = spec.heat_inputs[0]
    assert (h.node, h.input, h.gain, h.hold) == ("asic", "P_asic", Parameter(1.0, fixed=True),
                                                 "zoh")
    assert [(s.node, s.column, s.noise) for s in spec.sensors] == [
        ("housing", "T_housing", Parameter(0.01)), ("pcb", "T_pcb", Parameter(0.01)),
        ("asic", "T_asic", Parameter(0.01))]
    assert len(spec.sensors) == len(raw["sensors"])
    assert spec.input_columns == ("T_chamber", "P_asic")
    assert spec.input_holds == ("foh", "zoh")
    assert spec.boundary_columns == ("T_chamber",) and spec.heat_columns == ("P_asic",)


@pytest.mark.parametrize("name", ["rtd2", "imu6"])
def test_config_round_trip(name, tmp_path):
    spec = load_model(CONFIGS / f"{name}.toml")
    assert without_source(parse_model(dump_model(spec))) == without_source(spec)
    save_model(spec, tmp_path / "again.toml", header="written by a test\nsecond line")
    again = load_model(tmp_path / "again.toml")
    assert again.source == str(tmp_path / "again.toml")
    assert without_source(again) == without_source(spec)


@pytest.mark.parametrize("name", ["rtd2", "imu6", "chain3"])
def test_builtin_model_matches_config(name):
    """`--model imu6` (the packaged copy) is the same model as configs/imu6.toml."""
    builtin = load_model(ROOT / "thermojax" / "data" / f"{name}.toml")
    assert without_source(builtin) == without_source(load_model(CONFIGS / f"{name}.toml"))
    # configs/ holds real files, byte for byte the packaged copies (no symlinks)
    assert not (CONFIGS / f"{name}.toml").is_symlink()
    assert (CONFIGS / f"{name}.toml").read_bytes() == (ROOT / "thermojax" / "data" /
                                                       f"{name}.toml").read_bytes()


def test_public_names():
    assert tj.load_model is load_model and tj.parse_model is parse_model
    assert tj.dump_model is dump_model and tj.save_model is save_model
    assert issubclass(tj.InputError, ValueError)


# ---------------------------------------------------------------------------
# Every feature of spec §2 survives dump -> parse

FULL = """\
# every feature of the model format
name = "full"
description = "a model exercising every key"

[[nodes]]
name = "case"
capacitance = 5.0
process_noise = 0.001
initial = { value = 20.0, fixed = true }
initial_std = 0.1

[[nodes]]
name = "board"
capacitance = { value = 1.5, fixed = true }
process_noise = { value = 0.0005, fixed = true }
initial = 21.5

[[nodes]]
name = "die"
capacitance = { value = 0.05 }

[[links]]
between = ["case", "board"]
conductance = 0.3

[[links]]
between = ["die", "board"]               # the file's order is kept
conductance = { value = 0.02, fixed = true }

[[boundaries]]
node = "case"
input = "T_chamber"
conductance = 0.1

[[boundaries]]
node = "board"
input = "T_chamber"
conductance = 0.01
hold = "foh"

[[heat_inputs]]
node = "die"
input = "P_die"
gain = { value = 1.0, fixed = true }
hold = "zoh"

[[heat_inputs]]
node = "board"
input = "P_heater"
gain = 0.9
hold = "zoh"

[[heat_inputs]]
node = "case"
input = "P_die"
hold = "zoh"

[[sensors]]
node = "case"
column = "T_case"
noise = { value = 0.01, fixed = true }

[[sensors]]
node = "die"
column = "T_die"

[[effects]]
kind = "extra_node"
where = ["case", "T_chamber"]
name = "mount"
capacitance = 2.0
conductance = 0.4
conductance_b = { value = 0.2, fixed = true }

[[effects]]
kind = "radiation"
where = ["mount", "T_chamber"]
coefficient = 1e-10

[[effects]]
kind = "extra_node"
where = ["die"]
name = "lid"

[[effects]]
kind = "conductance_temperature"
where = ["board", "case"]
alpha = -0.002

[[effects]]
kind = "capacitance_temperature"
where = ["die"]
beta = { value = 0.001, fixed = true }

[[effects]]
kind = "heat_source"
where = ["P_fan", "case"]
gain = 0.3

[[effects]]
kind = "boundary"
where = ["T_wall", "die"]
conductance = 0.004

[[effects]]
kind = "conductance_input"
where = ["case", "T_chamber", "v_air"]
coefficient = 0.05

[[effects]]
kind = "sensor_lag"
where = ["T_die"]
time_constant = 3.0

[[effects]]
kind = "sensor_offset"
where = ["T_case"]
offset = -0.05

[[effects]]
kind = "sensor_gain"
where = ["T_case"]
gain = 0.001

[[effects]]
kind = "viscoelastic"
where = ["die", "gyro_x_dph"]
time_constant = 600.0
k = { value = 0.2, fixed = true }

[[biases]]
column = "gyro_x_dph"
temperature = "die"
order = 5
gradients = [["case", "die"], ["board", "die"]]
rates = ["die", "case"]
noise = 0.5

[[biases]]
column = "acc_x_ug"
temperature = "board"
noise = { value = 20.0, fixed = true }
"""


def test_full_model_reads_every_feature():
    spec = parse_model(FULL, source="full.toml")
    case, board, die = spec.nodes
    assert case.process_noise == Parameter(0.001) and case.initial == Parameter(20.0, True)
    assert case.initial_std == 0.1
    assert board.capacitance == Parameter(1.5, True)
    assert board.process_noise == Parameter(0.0005, True) and board.initial == Parameter(21.5)
    assert board.initial_std is None
    assert die.capacitance == Parameter(0.05, False)
    assert die.process_noise is None and die.initial is None
    assert spec.links[1].between == ("die", "board") and spec.links[1].key == "die-board"
    assert spec.links[1].conductance == Parameter(0.02, True)
    assert [b.hold for b in spec.boundaries] == ["foh", "foh"]
    assert [(h.input, h.gain, h.hold) for h in spec.heat_inputs] == [
        ("P_die", Parameter(1.0, True), "zoh"), ("P_heater", Parameter(0.9), "zoh"),
        ("P_die", Parameter(1.0, True), "zoh")]  # an absent gain is a known 1
    # the columns effects read are inputs too, after the boundaries' and heat inputs'
    assert spec.input_columns == ("T_chamber", "P_die", "P_heater", "P_fan", "T_wall", "v_air")
    assert spec.input_holds == ("foh", "zoh", "zoh", "foh", "foh", "foh")
    assert spec.sensors[0].noise == Parameter(0.01, True) and spec.sensors[1].noise is None
    assert [e.kind for e in spec.effects] == [
        "extra_node", "radiation", "extra_node", "conductance_temperature",
        "capacitance_temperature", "heat_source", "boundary", "conductance_input",
        "sensor_lag", "sensor_offset", "sensor_gain", "viscoelastic"]
    mount = spec.effects[0]
    assert mount == Effect("extra_node", ("case", "T_chamber"), {
        "capacitance": Parameter(2.0), "conductance": Parameter(0.4),
        "conductance_b": Parameter(0.2, True)}, name="mount")
    assert mount.key == "extra_node.case-T_chamber"
    assert spec.effects[1].where == ("mount", "T_chamber")  # a later effect names the new node
    assert spec.effects[2] == Effect("extra_node", ("die",), {}, name="lid")
    assert spec.effects[7].where == ("case", "T_chamber", "v_air")
    assert spec.effects[11] == Effect("viscoelastic", ("die", "gyro_x_dph"), {
        "time_constant": Parameter(600.0), "k": Parameter(0.2, True)})
    assert spec.biases == (
        Bias("gyro_x_dph", "die", 5, (("case", "die"), ("board", "die")), ("die", "case"),
             Parameter(0.5)),
        Bias("acc_x_ug", "board", 3, (), (), Parameter(20.0, True)))


def test_full_model_round_trip(tmp_path):
    spec = parse_model(FULL, source="full.toml")
    text = dump_model(spec, header="fitted by a test")
    assert text.startswith("# fitted by a test\n")
    again = parse_model(text)
    assert again.source == "<model>"
    assert without_source(again) == without_source(spec)
    assert dump_model(again) == dump_model(spec)  # a fixed point after one trip
    save_model(spec, tmp_path / "full.toml")
    assert without_source(load_model(tmp_path / "full.toml")) == without_source(spec)


@pytest.mark.parametrize("value", [0.1, 1 / 3, 1e-10, 6.02e23, 12345678.901234567, 5e-324])
def test_numbers_round_trip_exactly(value):
    text = FULL.replace("conductance = 0.3", f"conductance = {value!r}")
    spec = parse_model(text)
    assert spec.links[0].conductance.value == value
    assert parse_model(dump_model(spec)).links[0].conductance.value == value


def test_names_with_quotes_round_trip():
    text = FULL.replace('"mount"', '"mount \\"A\\" \\\\ left"').replace(
        'where = ["mount", "T_chamber"]', 'where = ["mount \\"A\\" \\\\ left", "T_chamber"]')
    spec = parse_model(text)
    assert spec.effects[0].name == 'mount "A" \\ left'
    assert without_source(parse_model(dump_model(spec))) == without_source(spec)


def test_line_numbers_count_only_headers():
    """Comments, blank lines and inline tables do not shift the reported line."""
    text = FULL.replace('name = "die"\ncapacitance = { value = 0.05 }',
                        'name = "die"\ncapacitance = { value = -0.05 }')
    with pytest.raises(InputError, match=re.escape(
            f"full.toml, line {header_line(text, 'nodes', 2)}, field 'nodes[2].capacitance'")):
        parse_model(text, source="full.toml")


# ---------------------------------------------------------------------------
# Bad inputs: each names the file, the entry's line, the field, and what to do

BASE = """\
# a two-node model that every bad input below starts from
name = "base"

[[nodes]]
name = "sheath"
capacitance = 0.8

[[nodes]]
name = "core"
capacitance = 0.1

[[links]]
between = ["sheath", "core"]
conductance = 0.08

[[boundaries]]
node = "sheath"
input = "T_fluid"
conductance = 0.2

[[heat_inputs]]
node = "core"
input = "P_heater"

[[sensors]]
node = "core"
column = "T_core"
noise = 0.01
"""


def test_base_is_valid():
    spec = parse_model(BASE)
    assert spec.node_names == ("sheath", "core")


def sub(old: str, new: str):
    def edit(text: str) -> str:
        assert text.count(old) == 1, old
        return text.replace(old, new)
    return edit


def add(extra: str):
    return lambda text: text + "\n" + extra


# (id, edit of BASE, (table, index) whose header line is reported, field, what-to-do regex)
BAD = [
    ("unknown-node-link", sub('["sheath", "core"]', '["sheath", "kore"]'), ("links", 0),
     "links[0].between", r"unknown node 'kore'; the model's nodes are \['sheath', 'core'\]"),
    ("unknown-node-boundary", sub('node = "sheath"\ninput', 'node = "sheeth"\ninput'),
     ("boundaries", 0), "boundaries[0].node", r"unknown node 'sheeth'.*\['sheath', 'core'\]"),
    ("unknown-node-heat-input", sub('node = "core"\ninput', 'node = "cor"\ninput'),
     ("heat_inputs", 0), "heat_inputs[0].node", r"unknown node 'cor'.*\['sheath', 'core'\]"),
    ("unknown-node-sensor", sub('node = "core"\ncolumn', 'node = "coar"\ncolumn'),
     ("sensors", 0), "sensors[0].node", r"unknown node 'coar'.*\['sheath', 'core'\]"),
    ("unknown-node-bias", add('[[biases]]\ncolumn = "gyro"\ntemperature = "mems"'),
     ("biases", 0), "biases[0].temperature", r"unknown node 'mems'"),
    ("duplicate-node", sub('name = "core"', 'name = "sheath"'), ("nodes", 1), "nodes[1].name",
     r"duplicate node name 'sheath'; every node needs a unique name"),
    ("zero-capacitance", sub("capacitance = 0.1", "capacitance = 0"), ("nodes", 1),
     "nodes[1].capacitance", r"capacitance must be a positive number of J/K, got 0\.0"),
    ("negative-capacitance", sub("capacitance = 0.1", "capacitance = -0.1"), ("nodes", 1),
     "nodes[1].capacitance", r"capacitance must be a positive number of J/K, got -0\.1"),
    ("negative-fixed-capacitance",
     sub("capacitance = 0.8", "capacitance = { value = -0.8, fixed = true }"), ("nodes", 0),
     "nodes[0].capacitance", r"must be a positive number of J/K, got -0\.8"),
    ("zero-link-conductance", sub("conductance = 0.08", "conductance = 0.0"), ("links", 0),
     "links[0].conductance", r"conductance must be a positive number of W/K, got 0\.0"),
    ("negative-link-conductance", sub("conductance = 0.08", "conductance = -0.08"),
     ("links", 0), "links[0].conductance", r"must be a positive number of W/K, got -0\.08"),
    ("zero-boundary-conductance", sub("conductance = 0.2", "conductance = 0"),
     ("boundaries", 0), "boundaries[0].conductance",
     r"must be a positive number of W/K, got 0\.0"),
    ("negative-boundary-conductance", sub("conductance = 0.2", "conductance = -0.2"),
     ("boundaries", 0), "boundaries[0].conductance",
     r"must be a positive number of W/K, got -0\.2"),
    ("lone-node", add('[[nodes]]\nname = "loose"\ncapacitance = 1.0'), ("nodes", 2),
     "nodes[2].name", r"node 'loose' has no conduction path to any boundary.*singular network"
     r".*Link it to a node that reaches a \[\[boundaries\]\] entry, or give it a boundary"),
    ("island-of-two", add('[[nodes]]\nname = "a"\ncapacitance = 1.0\n\n'
                          '[[nodes]]\nname = "b"\ncapacitance = 2.0\n\n'
                          '[[links]]\nbetween = ["a", "b"]\nconductance = 0.5'), ("nodes", 2),
     "nodes[2].name", r"node 'a' has no conduction path to any boundary.*singular.*Link it"),
    ("no-boundary", sub('[[boundaries]]\nnode = "sheath"\ninput = "T_fluid"\nconductance = 0.2\n',
                        ""), ("nodes", 0), "nodes[0].name",
     r"node 'sheath' has no conduction path.*give it a boundary"),
    ("unknown-effect-kind", add('[[effects]]\nkind = "convection"\nwhere = ["core"]'),
     ("effects", 0), "effects[0].kind",
     r"unknown effect kind 'convection'; the vocabulary is \[.*'radiation'.*\]"),
    ("arity-radiation", add('[[effects]]\nkind = "radiation"\nwhere = ["core"]'),
     ("effects", 0), "effects[0].where",
     r"'radiation' takes where = a list of 2 names, got \['core'\]"),
    ("arity-extra-node", add('[[effects]]\nkind = "extra_node"\nname = "x"\n'
                             'where = ["core", "sheath", "T_fluid"]'),
     ("effects", 0), "effects[0].where", r"'extra_node' takes where = a list of 1 or 2 names"),
    ("arity-conductance-input",
     add('[[effects]]\nkind = "conductance_input"\nwhere = ["core", "sheath"]'),
     ("effects", 0), "effects[0].where", r"'conductance_input' takes where = a list of 3 names"),
    ("viscoelastic-without-bias",
     add('[[effects]]\nkind = "viscoelastic"\nwhere = ["core", "gyro_x_dph"]'),
     ("effects", 0), "effects[0].where",
     r"bias column 'gyro_x_dph', which needs a \[\[biases\]\] entry for that column; add one"),
    ("viscoelastic-on-sensor-column",
     add('[[effects]]\nkind = "viscoelastic"\nwhere = ["core", "T_core"]'),
     ("effects", 0), "effects[0].where", r"'T_core'.*needs a \[\[biases\]\] entry"),
    ("two-holds-heat", add('[[heat_inputs]]\nnode = "sheath"\ninput = "P_heater"\nhold = "zoh"'),
     ("heat_inputs", 1), "heat_inputs[1].hold",
     r"column 'P_heater' is used with holds 'foh' and 'zoh'; a column must have one hold"),
    ("two-holds-boundary",
     add('[[boundaries]]\nnode = "core"\ninput = "T_fluid"\nconductance = 0.1\nhold = "zoh"'),
     ("boundaries", 1), "boundaries[1].hold", r"column 'T_fluid' is used with holds"),
    ("unknown-hold", sub('input = "P_heater"', 'input = "P_heater"\nhold = "cubic"'),
     ("heat_inputs", 0), "heat_inputs[0].hold", r"hold must be one of \['foh', 'zoh'\]"),
    # an unknown key is named at its own line (KEY: the line that writes it)
    ("unknown-key-node", sub("capacitance = 0.1", 'capacitance = 0.1\ncolour = "red"'),
     (KEY, 'colour = "red"'), "nodes[1].colour",
     r"unknown key 'colour' in this \[\[nodes\]\] entry; allowed are \['capacitance', "
     r"'initial', 'initial_std', 'name', 'process_noise'\]"),
    ("unknown-key-link", sub("conductance = 0.08", "conductance = 0.08\nlength = 3"),
     (KEY, "length = 3"), "links[0].length", r"unknown key 'length' in this \[\[links\]\] "
     r"entry; allowed are"),
    ("unknown-key-sensor", sub("noise = 0.01", "noise = 0.01\nnosie = 0.02"),
     (KEY, "nosie = 0.02"), "sensors[0].nosie", r"unknown key 'nosie' in this \[\[sensors\]\] "
     r"entry \(did you mean 'noise'\?\); allowed are \['column', 'node', 'noise'\]"),
    # a misspelt required key: named as written, with the key it resembles, not reported
    # as the required key missing at the entry's header
    ("misspelt-required-key", sub("conductance = 0.08", "conductanse = 0.08"),
     (KEY, "conductanse = 0.08"), "links[0].conductanse",
     r"unknown key 'conductanse' in this \[\[links\]\] entry \(did you mean "
     r"'conductance'\?\); allowed are \['between', 'conductance'\]"),
    ("unknown-effect-parameter",
     add('[[effects]]\nkind = "radiation"\nwhere = ["core", "T_fluid"]\nemissivity = 0.9'),
     ("effects", 0), "effects[0].emissivity",
     r"'radiation' has no parameter 'emissivity'; its parameters are \['coefficient'\]"),
    ("missing-key", sub("capacitance = 0.1\n", ""), ("nodes", 1), "nodes[1].capacitance",
     r"missing required key 'capacitance'"),
    ("parameter-table-without-value", sub("capacitance = 0.1", "capacitance = { fixed = true }"),
     ("nodes", 1), "nodes[1].capacitance",
     r"a parameter table is written \{ value = 0\.8, fixed = true \}"),
    ("parameter-table-misspelt", sub("conductance = 0.2", "conductance = { valeu = 0.2 }"),
     ("boundaries", 0), "boundaries[0].conductance", r"\{ value = 0\.8, fixed = true \}"),
    ("parameter-fixed-not-bool", sub("conductance = 0.08", 'conductance = { value = 0.08, '
                                     'fixed = "yes" }'),
     ("links", 0), "links[0].conductance", r"'fixed' must be true or false"),
    ("non-numeric-capacitance", sub("capacitance = 0.1", 'capacitance = "big"'), ("nodes", 1),
     "nodes[1].capacitance", r"expected a finite number, got 'big'"),
    ("boolean-capacitance", sub("capacitance = 0.1", "capacitance = true"), ("nodes", 1),
     "nodes[1].capacitance", r"expected a finite number, got True"),
    ("nan-capacitance", sub("capacitance = 0.1", "capacitance = nan"), ("nodes", 1),
     "nodes[1].capacitance", r"expected a finite number, got nan"),
    ("non-numeric-value", sub("capacitance = 0.8", 'capacitance = { value = "0.8" }'),
     ("nodes", 0), "nodes[0].capacitance", r"expected a finite number, got '0\.8'"),
    ("string-for-between", sub('["sheath", "core"]', '"sheath"'), ("links", 0),
     "links[0].between", r"expected a list of names, got 'sheath'"),
    ("string-for-where", add('[[effects]]\nkind = "sensor_lag"\nwhere = "T_core"'),
     ("effects", 0), "effects[0].where", r"expected a list of names, got 'T_core'"),
    ("string-for-rates", add('[[biases]]\ncolumn = "gyro"\ntemperature = "core"\nrates = "core"'),
     ("biases", 0), "biases[0].rates", r"expected a list of names, got 'core'"),
    ("string-for-gradients",
     add('[[biases]]\ncolumn = "gyro"\ntemperature = "core"\ngradients = ["core", "sheath"]'),
     ("biases", 0), "biases[0].gradients", r"gradients is a list of node pairs"),
    ("number-for-name", sub('name = "core"', "name = 7"), ("nodes", 1), "nodes[1].name",
     r"expected a non-empty string, got 7"),
]


@pytest.mark.parametrize("edit,entry,fld,fix", [b[1:] for b in BAD], ids=[b[0] for b in BAD])
def test_bad_model(edit, entry, fld, fix, tmp_path):
    text = edit(BASE)
    path = tmp_path / "bad_model.toml"
    path.write_text(text)
    line = header_line(text, *entry)
    where = re.escape(f"{path}, line {line}, field '{fld}': ")
    with pytest.raises(InputError, match=where + ".*" + fix) as info:
        load_model(path)
    assert isinstance(info.value, ValueError)
    assert (info.value.file, info.value.line, info.value.field) == (str(path), line, fld)
    assert "\n" not in str(info.value)  # one paragraph
    with pytest.raises(ValueError, match=re.escape("<text>, line")):  # the API, from text
        parse_model(text, source="<text>")


@pytest.mark.parametrize("bad_line,fragment,below", [
    ("capacitance = = 0.1", "Invalid value", 0),
    ("conductance 0.2", "", 0),
    ("[[nodes]", "", 0),
    ('between = ["sheath", "core"', "Unclosed array", 1),  # an array may span lines
])
def test_toml_syntax_error_reports_line(bad_line, fragment, below, tmp_path):
    lines = BASE.splitlines()
    target = {"capacitance = = 0.1": "capacitance = 0.1",
              'between = ["sheath", "core"': 'between = ["sheath", "core"]',
              "conductance 0.2": "conductance = 0.2",
              "[[nodes]": "[[sensors]]"}[bad_line]
    k = lines.index(target)
    lines[k] = bad_line
    path = tmp_path / "syntax.toml"
    path.write_text("\n".join(lines) + "\n")
    line = k + 1 + below
    with pytest.raises(InputError, match=re.escape(f"{path}, line {line}: TOML syntax error: ")
                       + f".*{fragment}.*Fix the syntax at that line") as info:
        load_model(path)
    assert info.value.line == line


@pytest.mark.parametrize("text,fld,fix", [
    (BASE.replace("[[sensors]]", "[sensors]"), "sensors",
     r"'sensors' must be an array of tables, written \[\[sensors\]\]"),
    ('name = "empty"\n', "nodes", r"the model has no \[\[nodes\]\]; add at least one node"),
])
def test_bad_model_without_line(text, fld, fix, tmp_path):
    path = tmp_path / "whole.toml"
    path.write_text(text)
    with pytest.raises(InputError, match=re.escape(f"{path}, field '{fld}': ") + fix):
        load_model(path)


def test_unknown_top_level_key_is_named_at_its_line(tmp_path):
    path = tmp_path / "top.toml"
    path.write_text("# a room\n\nnmae = 'room'\n" + BASE)
    with pytest.raises(InputError, match=re.escape(f"{path}, line 3, field 'nmae': unknown "
                                                   "top-level key 'nmae' (did you mean 'name'?)"
                                                   "; allowed are")):
        load_model(path)


def test_missing_model_file(tmp_path):
    path = tmp_path / "nowhere.toml"
    with pytest.raises(InputError, match=re.escape(str(path)) + r": model file not found; check "
                       "the path"):
        load_model(path)


def test_effect_boundary_on_unknown_node_is_an_input_error():
    """The grounding check must not trip over an effect's unknown node (was a KeyError)."""
    text = BASE + '\n[[effects]]\nkind = "boundary"\nwhere = ["T_wall", "nonode"]\n'
    with pytest.raises(InputError, match=re.escape(
            f"m.toml, line {header_line(text, 'effects', 0)}, field 'effects[0].where': ")
            + r"'nonode' should be a node for 'boundary'"):
        parse_model(text, source="m.toml")


def test_effect_boundary_grounds_a_node():
    text = BASE + ('\n[[nodes]]\nname = "wall"\ncapacitance = 1.0\n'
                   '\n[[effects]]\nkind = "boundary"\nwhere = ["T_wall", "wall"]\n')
    assert parse_model(text).node_names == ("sheath", "core", "wall")


def test_example_model_with_bias_channels():
    """configs/imu6_bias.toml: imu6's thermal part, a gyro and an accelerometer channel,
    and a viscoelastic state on the accelerometer; it survives dump -> parse."""
    spec = load_model(CONFIGS / "imu6_bias.toml")
    imu6 = load_model(CONFIGS / "imu6.toml")
    assert (spec.nodes, spec.links, spec.boundaries, spec.heat_inputs, spec.sensors) == (
        imu6.nodes, imu6.links, imu6.boundaries, imu6.heat_inputs, imu6.sensors)
    gyro, accel = spec.biases
    assert (gyro.column, gyro.temperature, gyro.order) == ("gyro_x_dph", "proof_mass", 3)
    assert len(gyro.coefficients) == 4 + 1 + 1  # cubic, one gradient, one rate
    assert (accel.column, accel.temperature, len(accel.coefficients)) == ("accel_x_ug", "mems", 4)
    (visco,) = spec.effects
    assert visco.where == ("mems", "accel_x_ug")
    assert visco.parameters["time_constant"].value == 1500.0
    assert without_source(parse_model(dump_model(spec))) == without_source(spec)


@pytest.mark.parametrize("text, value", [("0.3", 0.3), ("{ value = 0.3, fixed = true }", 0.3)])
def test_initial_std_as_number_or_fixed_table(text, value):
    spec = parse_model(f'name = "one"\n[[nodes]]\nname = "a"\ncapacitance = 1.0\n'
                       f'initial_std = {text}\n[[boundaries]]\nnode = "a"\ninput = "T"\n'
                       'conductance = 0.1\n[[sensors]]\nnode = "a"\ncolumn = "T_a"\n')
    assert spec.nodes[0].initial_std == value
    assert parse_model(dump_model(spec)).nodes[0].initial_std == value


def test_initial_std_table_must_be_fixed():
    with pytest.raises(InputError, match=r"nodes\[0\]\.initial_std.*not estimated"):
        parse_model('name = "one"\n[[nodes]]\nname = "a"\ncapacitance = 1.0\n'
                    'initial_std = { value = 0.3, fixed = false }\n[[boundaries]]\nnode = "a"\n'
                    'input = "T"\nconductance = 0.1\n[[sensors]]\nnode = "a"\ncolumn = "T_a"\n')

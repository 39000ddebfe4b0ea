"""Issue 67, item 4: an observer artifact is checked before use by `export --check` and
`playback`: content hash, schema, kinds, shapes, stability, formats, rate. A tampered or
damaged artifact exits 2 with a message naming the file and the field, never a
traceback. The generated C escapes `/*` and `*/` in names, so the documented -Werror
build passes with a node named `a/*b`; the fixed formats hold the input limits."""

from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
import pytest

import thermojax.reference as ref
from thermojax.cli import main

from helpers import CONFIGS
from helpers import run_cli as run

RTD2 = CONFIGS / "rtd2.toml"


@pytest.fixture(scope="module")
def artifact(tmp_path_factory):
    folder = tmp_path_factory.mktemp("art") / "obs"
    assert main(["export", "--model", str(RTD2), "--rate", "10", "--out", str(folder),
                 "--fixed", "q16.16", "--quiet"]) == 0
    return folder


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    path = tmp_path_factory.mktemp("log") / "shock.csv"
    assert main(["simulate", "--model", str(RTD2), "--profile", "shock", "--dt", "0.1",
                 "--out", str(path), "--noise", "--quiet"]) == 0
    return path


def _tamper(meta, arrays, what):
    if what == "phi":
        arrays["Phi"] = arrays["Phi"] * 1.04 / np.abs(np.linalg.eigvals(arrays["Phi"])).max()
    elif what == "rate":
        meta["rate_hz"] = 1000
    elif what == "format":
        meta["fixed"]["format"] = "q99"
    elif what == "states":
        meta["states"] = "sheath"
    elif what == "shifted":
        arrays["x_ref"] = arrays["x_ref"] + 7.0
    elif what == "scale":
        meta["fixed"]["state_scale_K"] = 0.0
    elif what == "gain":
        arrays["gain_table"] = arrays["gain_table"] * 1e12
    elif what == "model_name":       # only the hash can tell
        meta["model"] = "someone_else"


CASES = {"phi": ("observer.npz", "Phi"), "rate": ("observer.json", "rate_hz"),
         "format": ("observer.json", "fixed.format"), "states": ("observer.json", "states"),
         "shifted": ("observer.npz", "x_ref"), "scale": ("observer.json", "fixed.state_scale_K"),
         "gain": ("observer.npz", "gain_table"),
         "model_name": ("observer.json", "content_sha256")}


@pytest.mark.parametrize("what", sorted(CASES))
def test_a_tampered_artifact_is_refused_naming_file_and_field(capsys, tmp_path, artifact,
                                                              log, what):
    folder = tmp_path / "t"
    shutil.copytree(artifact, folder)
    meta = json.loads((folder / "observer.json").read_text())
    arrays = dict(np.load(folder / "observer.npz"))
    _tamper(meta, arrays, what)
    (folder / "observer.json").write_text(json.dumps(meta))
    np.savez(folder / "observer.npz", **arrays)
    file, field = CASES[what]
    for argv in (["export", "--check", folder],
                 ["playback", folder, "--data", log, "--out", tmp_path / "pb.csv",
                  "--build", "fixed", "--quiet"]):
        rc, out, err = run(capsys, *argv)
        assert rc == 2, (argv[0], out, err)
        assert "Traceback" not in err and "OK" not in out
        assert file in err and f"field '{field}'" in err, err
    assert not (tmp_path / "pb.csv").exists()


def test_a_garbage_npz_is_refused(capsys, tmp_path, artifact):
    folder = tmp_path / "t"
    shutil.copytree(artifact, folder)
    (folder / "observer.npz").write_bytes(b"PK\x03\x04" + b"garbage" * 50)
    rc, _, err = run(capsys, "export", "--check", folder)
    assert rc == 2 and "observer.npz" in err and "Traceback" not in err


def test_the_intact_artifact_passes_and_records_its_hash(capsys, artifact):
    rc, out, _ = run(capsys, "export", "--check", artifact)
    assert rc == 0 and out.rstrip().endswith("OK")
    assert len(json.loads((artifact / "observer.json").read_text())["content_sha256"]) == 64


def test_a_node_named_with_comment_marks_builds_with_werror(tmp_path):
    model = tmp_path / "odd.toml"
    model.write_text(RTD2.read_text().replace('"core"', '"a/*b*/c"'))
    out = tmp_path / "obs"
    assert main(["export", "--model", str(model), "--rate", "10", "--out", str(out),
                 "--fixed", "q16.16", "--quiet"]) == 0
    for prefix in ("tj_observer", "tj_observer_q16_16"):
        text = (out / f"{prefix}.c").read_text()
        body = text.replace("/*", "\0", ).split("\0")[1:]
        assert all("/*" not in b.split("*/")[0] for b in body)
        subprocess.run(["gcc", "-std=c99", "-O2", "-Wall", "-Wextra", "-pedantic", "-Werror",
                        "-ffp-contract=off", "-o", str(out / f"{prefix}_prog"),
                        str(out / f"{prefix}.c"), str(out / f"{prefix}_main.c"), "-lm"],
                       check=True, capture_output=True)


def test_comment_safe_leaves_no_comment_marks():
    from thermojax.reference._c_source import comment_safe

    for name in ("a/*b", "a*/b", "/*/", "*/*", "a//*b*//c", "x\n/*y"):
        got = comment_safe(name)
        assert "/*" not in got and "*/" not in got and "\n" not in got


@pytest.mark.parametrize("fmt", ["q15", "q31"])
def test_q_formats_hold_a_heater_within_its_limits(tmp_path, fmt):
    """chain3's die heater: limits of several watts are representable, so 1 W is used,
    not held as a fault; the fixed estimate follows the float one within the export's
    own error bound."""
    out = tmp_path / "obs"
    assert main(["export", "--model", str(CONFIGS / "chain3.toml"), "--rate", "1", "--out",
                 str(out), "--fixed", fmt, "--quiet"]) == 0
    art = ref.load_observer(out)
    lim = np.asarray(art.metadata["faults"]["input_limits"], float)
    j = art.input_names.index("P_die")
    scale = art.metadata["fixed"]["input_scale"][j]
    assert lim[j, 1] < scale  # the codes span ±scale W around 0 W
    T = 300
    u = np.stack([np.full(T, 25.0), np.where(np.arange(T) > 20, 1.0, 0.0)], 1)
    u = u[:, [art.input_names.index(c) for c in ("T_chamber", "P_die")]]
    x0 = np.full(len(art.state_names), 25.0)
    flt = art.float_observer().run(x0, u, np.full((T, 2), np.nan))
    fx = art.fixed_observer().run_physical(x0, u, np.full((T, 2), np.nan))
    assert not np.any(fx.input_fault)
    assert flt.states[-1].max() > 45  # the heater is seen: 1 W warms the die by ~24 K
    assert np.abs(fx.states - flt.states).max() <= art.metadata["fixed"]["error_bound"]["max_K"]


def test_a_given_input_scale_that_cannot_hold_the_limits_refuses_the_format(tmp_path):
    from thermojax import InputError
    from thermojax.observer import export_observer

    with pytest.raises(InputError, match=r"field '--fixed'.*P_die.*not representable in q15"):
        export_observer(CONFIGS / "chain3.toml", 1, tmp_path / "o", fixed="q15",
                        power_scale=0.5)

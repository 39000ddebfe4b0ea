"""A resumed investigation writes the report an uninterrupted one writes: the steps
finished before the interruption keep their figures, residual analysis and missing heat
(their traces and reconstruction are saved beside the checkpoint), up to timings."""

from __future__ import annotations

import re

import pytest

from hidden import generator as g


def _without_timings(md: str) -> str:
    """The report with every wall time blanked: the steps table's last column and the
    times said in words."""
    lines = []
    timed = False
    for line in md.splitlines():
        if line.startswith("| step |"):
            timed = "wall time" in line
        elif timed and line.startswith("| ") and not line.startswith("|---"):
            line = line[:line.rstrip(" |").rfind("|")] + "| (time) |"
        lines.append(re.sub(r"\d+(\.\d+)? ?(s|min)\b", "(time)", line))
    return "\n".join(lines)


@pytest.mark.slow
def test_resumed_report_is_the_uninterrupted_one(tmp_path, monkeypatch):
    from thermojax import load_model
    from thermojax.investigation import _investigate
    from thermojax.measurements import read_telemetry

    files = g.write_case("one_run", tmp_path / "data", seed=0, horizon_s=900.0)
    spec, runs = load_model(files["model"]), [read_telemetry(files["data"][0])]
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    _investigate.investigate(spec, runs, max_steps=1, refits=1, out=whole)

    real = _investigate._write_outputs

    def interrupted(*a, **k):
        raise KeyboardInterrupt  # after step 1 is checkpointed, while the report is written

    monkeypatch.setattr(_investigate, "_write_outputs", interrupted)
    with pytest.raises(KeyboardInterrupt):
        _investigate.investigate(spec, runs, max_steps=1, refits=1, out=cut)
    assert (cut / "checkpoint.json").is_file() and not (cut / "report.md").exists()
    for stale in cut.glob("step0_*.png"):  # the figures of the finished step are lost too
        stale.unlink()
    monkeypatch.setattr(_investigate, "_write_outputs", real)
    said = []
    _investigate.investigate(spec, runs, max_steps=1, refits=1, out=cut, progress=said.append)
    assert any(m.startswith("resuming after step 1") for m in said), said

    # where the first step's time went: the phases the loop names, within its wall time
    import json

    step0 = json.loads((whole / "report.json").read_text())["steps"][0]
    phases = step0["phase_times_s"]
    assert {"score tests", "refits", "held-out folds"} <= set(phases), phases
    assert sum(v for k, v in phases.items() if k != "compilation") <= step0["wall_time_s"]
    # (absent where an earlier test in this process compiled every program already)
    assert 0.0 < phases.get("compilation", 1e-9) <= step0["wall_time_s"]
    a = (whole / "report.md").read_text(encoding="utf-8")
    b = (cut / "report.md").read_text(encoding="utf-8")
    assert "step0_" in a  # the finished step's figures are in the report at all
    assert _without_timings(b) == _without_timings(a)
    for fig in re.findall(r"\]\((step\d+_[\w.]+\.png)\)", a):
        assert (cut / fig).is_file(), fig

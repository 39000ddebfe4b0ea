"""The rivals of a near-tie an investigation named, as model files ready to design for.

`investigate` writes `report.json` (each step's `candidates`, each with `tied_with`: the
candidates the data could not tell apart from it, and the next step's `added`) and the
model after each step, `step<i>_model.toml`. The near-tie taken is the last one: the
candidate added at step `i + 1` when it had ties, else the best candidate of the last
step when it has. The rivals are the step's model with each of the tied candidates added:
the one the loop added with its fitted parameters (`step<i+1>_model.toml`), the others
with their first-guess parameters, which the design's refits then move.
"""

from __future__ import annotations

import json
from pathlib import Path

from .._errors import InputError
from ..investigation._evidence import is_added
from ..model._spec import ModelSpec


def rivals_from_investigation(folder) -> list[tuple[str, ModelSpec]]:
    """`(name, spec)` of each candidate of the last near-tie in the investigation `folder`,
    the one the loop preferred first. Names are `kind(where)`."""
    from ..investigation._candidates import new_effect
    from ..model import load_model
    from ..model.effects import lower_effects

    folder = Path(folder)
    path = folder / "report.json"
    try:
        report = json.loads(path.read_text(encoding="utf-8"))
        steps = report["steps"]
    except FileNotFoundError:
        raise InputError("no report.json here: give the folder `thermojax investigate` wrote.",
                         file=str(folder), field="--from-investigation") from None
    except (ValueError, KeyError, TypeError):
        raise InputError("this report.json is not one `thermojax investigate` wrote (no "
                         "readable `steps`).", file=str(path),
                         field="--from-investigation") from None
    tie = None  # (step index, chosen {kind, where, parameters?}, tied [[kind, where]], fitted)
    for i, step in enumerate(steps):
        for c in step.get("candidates") or []:
            if not c.get("tied_with"):
                continue
            nxt = steps[i + 1] if i + 1 < len(steps) else None
            added = (nxt or {}).get("added")
            if is_added(c, added):
                tie = (i, c, c["tied_with"], True)
            elif i == len(steps) - 1 and c is (step.get("candidates") or [None])[0]:
                tie = (i, c, c["tied_with"], False)
    if tie is None:
        raise InputError("the investigation named no near-tie (no candidate has `tied_with`); "
                         "there is nothing to tell apart.", file=str(path),
                         field="--from-investigation")
    i, chosen, tied, fitted = tie
    base_path = folder / f"step{i}_model.toml"
    if not base_path.exists():
        raise InputError(f"the model of step {i} is missing; the folder is incomplete.",
                         file=str(base_path), field="--from-investigation")
    base = load_model(base_path)
    lowered = lower_effects(base).spec
    out = []
    if fitted and (folder / f"step{i + 1}_model.toml").exists():
        out.append((_label(chosen["kind"], chosen["where"]),
                    load_model(folder / f"step{i + 1}_model.toml")))
    else:
        out.append(_with(base, lowered, chosen["kind"], chosen["where"], new_effect))
    for kind, where in tied:
        out.append(_with(base, lowered, kind, where, new_effect))
    return out


def _label(kind: str, where) -> str:
    return f"{kind}({'-'.join(str(w) for w in where)})"


def _with(base: ModelSpec, lowered: ModelSpec, kind: str, where, new_effect):
    effect = new_effect(base, lowered, kind, list(where), {})
    return _label(kind, where), base.replace(effects=base.effects + (effect,))

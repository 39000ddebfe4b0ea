"""C literals and tables for the generated observer (`_c_source`): every value written so
that it parses back to exactly the value the NumPy reference uses (hexadecimal, or the
shortest decimal that round-trips, checked), and `static const` arrays of them."""

from __future__ import annotations

import numpy as np


def _lit(v, word: str) -> str:
    v = float(v)
    if np.isinf(v):
        return "INFINITY" if v > 0 else "-INFINITY"
    if word == "float":
        return float(np.float32(v)).hex() + "f"
    if word == "double":
        return v.hex()
    i = int(v)
    if word == "int64_t":
        return f"INT64_C({i})"
    return f"({i + 1} - 1)" if i < -32767 else str(i)   # no negative literal overflows int


def _braced(a, word: str, indent: str) -> str:
    if a.ndim == 1:
        return "{" + ", ".join(_lit(v, word) for v in a) + "}"
    inner = indent + "    "
    return "{\n" + ",\n".join(inner + _braced(b, word, inner) for b in a) + "\n" + indent + "}"


def _array(name: str, ctype: str, values, word: str) -> str:
    a = np.asarray(values)
    if a.size == 0:   # C has no empty arrays: a null pointer of the table's type
        return f"static const {ctype} *const {name} = 0;   /* empty: no inputs */\n"
    dims = "".join(f"[{d}]" for d in a.shape)
    return f"static const {ctype} {name}{dims} = {_braced(a, word, '')};\n"


def _readable_lit(v, word: str) -> str:
    """A decimal literal that parses back to exactly `v` in `word` (float or double):
    the shortest round-trip decimal, checked; hexadecimal if the check fails."""
    v = float(v)
    if not np.isfinite(v):
        return _lit(v, word)
    if word == "float":
        x = np.float32(v)
        text = np.format_float_positional(x, unique=True, trim="0") if \
            1e-4 <= abs(float(x)) < 1e7 or x == 0 else \
            np.format_float_scientific(x, unique=True, trim="0")
        ok = np.float32(text) == x
        text += "f"
    else:
        text = repr(v)
        ok = float(text) == v
    if "." not in text and "e" not in text and "inf" not in text:
        text = text.replace("f", "") + (".0f" if word == "float" else ".0")
    return text if ok else _lit(v, word)


def _zero(word: str) -> str:
    return "0.0f" if word == "float" else "0.0"


def comment_safe(text) -> str:
    """`text` made safe inside a C block comment: neither `/*` (which `-Wcomment` makes
    an error under `-Werror`) nor `*/` (which would end the comment) survives, and no
    line break or trigraph either."""
    t = str(text).replace("\r", " ").replace("\n", " ").replace("??", "? ?")
    while "/*" in t or "*/" in t:
        t = t.replace("/*", "/ *").replace("*/", "* /")
    return t

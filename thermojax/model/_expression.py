"""The grammar of `expression` effects (docs/formats.md §3a): parsed, never `eval`-ed.

    sum     := product (("+" | "-") product)*
    product := unary (("*" | "/") unary)*
    unary   := ("-" | "+") unary | power
    power   := atom ("^" unary)?            # right-associative: -x^2 is -(x^2)
    atom    := number | name | name "(" sum ("," sum)* ")" | "(" sum ")"

A parsed expression is a tree of tuples (hashable, so it can be a static field of a
model): `("num", v)`, `("name", s)`, `("neg", a)`, `("bin", op, a, b)`,
`("call", f, (args...))`. `resolve` turns names into `("T", i)`, `("u", j)` and
`("p", k)` (node temperature, input column, parameter), and `evaluate` computes it with
`jax.numpy` (or NumPy) on arrays of any shape.
"""

from __future__ import annotations

import functools
import re

import numpy as np

FUNCTIONS = {"exp": 1, "log": 1, "sqrt": 1, "abs": 1, "sign": 1, "step": 1, "kelvin": 1,
             "min": 2, "max": 2}
KELVIN = 273.15
_TOKEN = re.compile(r"(?:(\d+\.?\d*(?:[eE][+-]?\d+)?|\.\d+(?:[eE][+-]?\d+)?)"
                    r"|([A-Za-z_][A-Za-z0-9_]*)|(\*\*|[-+*/^(),]))")


class ExpressionError(ValueError):
    """A malformed expression; the message says where (character position) and what."""


def _tokens(text: str) -> list[tuple[str, str, int]]:
    """`(kind, text, 1-based position)` of every token."""
    out, pos = [], 0
    while True:
        while pos < len(text) and text[pos].isspace():
            pos += 1
        if pos == len(text):
            return out
        m = _TOKEN.match(text, pos)
        if m is None:
            raise ExpressionError(f"unexpected character {text[pos]!r} at position {pos + 1}; "
                                  "allowed are numbers, names, + - * / ^ ( ) and ','")
        kind = "num" if m.group(1) else "name" if m.group(2) else "op"
        value = m.group(m.lastindex)
        if value == "**":
            raise ExpressionError(f"use ^ for a power, not ** (position {pos + 1})")
        out.append((kind, value, pos + 1))
        pos = m.end()


#: Deepest nesting (parentheses, signs, powers, calls) an expression may have: a
#: physical law needs a handful; thousands would exhaust Python's recursion.
MAX_DEPTH = 64
#: Most tokens an expression may have (a long chain of terms nests as deep as it is long).
MAX_TOKENS = 400


class _Parser:
    def __init__(self, text: str):
        self.text = text
        self.toks = _tokens(text)
        if len(self.toks) > MAX_TOKENS:
            raise ExpressionError(f"the expression has {len(self.toks)} tokens, more than the "
                                  f"{MAX_TOKENS} allowed; write the law in fewer terms")
        self.i = 0
        self.depth = 0

    def nested(self, pos: int):
        self.depth += 1
        if self.depth > MAX_DEPTH:
            raise ExpressionError(f"the expression nests deeper than {MAX_DEPTH} levels "
                                  f"(parentheses, signs or powers) at position {pos}; "
                                  "simplify it")

    def peek(self):
        return self.toks[self.i] if self.i < len(self.toks) else ("end", "", len(self.text) + 1)

    def take(self, value: str | None = None):
        tok = self.peek()
        if value is not None and tok[1] != value:
            found = "the end" if tok[0] == "end" else repr(tok[1])
            raise ExpressionError(f"expected {value!r} at position {tok[2]}, found {found}")
        self.i += 1
        return tok

    def parse(self):
        if not self.toks:
            raise ExpressionError("the expression is empty")
        tree = self.sum()
        tok = self.peek()
        if tok[0] != "end":
            raise ExpressionError(f"unexpected {tok[1]!r} at position {tok[2]}")
        return tree

    def left(self, operand, ops):
        """`operand (op operand)*` for `op` in `ops`, left-associative."""
        tree = operand()
        while self.peek()[0] == "op" and self.peek()[1] in ops:
            tree = ("bin", self.take()[1], tree, operand())
        return tree

    def sum(self):
        self.nested(self.peek()[2])
        tree = self.left(self.product, ("+", "-"))
        self.depth -= 1
        return tree

    def product(self):
        return self.left(self.unary, ("*", "/"))

    def unary(self):
        if self.peek()[0] == "op" and self.peek()[1] in ("-", "+"):
            sign, pos = self.take()[1:]
            self.nested(pos)
            inner = self.unary()
            self.depth -= 1
            return ("neg", inner) if sign == "-" else inner
        return self.power()

    def power(self):
        base = self.atom()
        if self.peek()[0] == "op" and self.peek()[1] == "^":
            pos = self.take()[2]
            self.nested(pos)
            tree = ("bin", "^", base, self.unary())
            self.depth -= 1
            return tree
        return base

    def atom(self):
        kind, value, pos = self.take()
        if kind == "num":
            return ("num", float(value))
        if kind == "name":
            if self.peek()[1] == "(" and self.peek()[0] == "op":
                if value not in FUNCTIONS:
                    raise ExpressionError(f"unknown function {value!r} at position {pos}; the "
                                          f"functions are {', '.join(sorted(FUNCTIONS))}")
                self.take("(")
                args = [self.sum()]
                while self.peek()[1] == ",":
                    self.take()
                    args.append(self.sum())
                self.take(")")
                if len(args) != FUNCTIONS[value]:
                    raise ExpressionError(f"{value}() takes {FUNCTIONS[value]} argument(s), "
                                          f"got {len(args)} (position {pos})")
                return ("call", value, tuple(args))
            if value in FUNCTIONS:
                raise ExpressionError(f"{value!r} is a function: write {value}(...) "
                                      f"(position {pos})")
            return ("name", value)
        if value == "(":
            tree = self.sum()
            self.take(")")
            return tree
        found = "the end" if kind == "end" else repr(value)
        raise ExpressionError(f"expected a number, a name or '(' at position {pos}, found {found}")


@functools.lru_cache(maxsize=1024)
def parse(text: str):
    """The tree of `text`; raises `ExpressionError` saying where it is malformed."""
    if not isinstance(text, str):
        raise ExpressionError("an expression is a string")
    return _Parser(text).parse()


def names(tree) -> tuple[str, ...]:
    """Every name the tree reads, in first-use order."""
    out: dict[str, None] = {}

    def walk(t):
        if t[0] == "name":
            out[t[1]] = None
        elif t[0] == "neg":
            walk(t[1])
        elif t[0] == "bin":
            walk(t[2]), walk(t[3])
        elif t[0] == "call":
            for a in t[2]:
                walk(a)
    walk(tree)
    return tuple(out)


def resolve(tree, nodes, columns, parameters):
    """The tree with every name replaced by `("T", i)`, `("u", j)` or `("p", k)`: index
    into `nodes`, `columns` and `parameters` (sequences of names; nodes first)."""
    if tree[0] == "name":
        n = tree[1]
        for tag, seq in (("T", nodes), ("p", parameters), ("u", columns)):
            if n in seq:
                return (tag, list(seq).index(n))
        raise ExpressionError(f"unknown name {n!r}")
    if tree[0] == "neg":
        return ("neg", resolve(tree[1], nodes, columns, parameters))
    if tree[0] == "bin":
        return ("bin", tree[1], resolve(tree[2], nodes, columns, parameters),
                resolve(tree[3], nodes, columns, parameters))
    if tree[0] == "call":
        return ("call", tree[1], tuple(resolve(a, nodes, columns, parameters)
                                       for a in tree[2]))
    return tree


def _integer(tree) -> int | None:
    if tree[0] == "num" and float(tree[1]).is_integer():
        return int(tree[1])
    if tree[0] == "neg":
        k = _integer(tree[1])
        return None if k is None else -k
    return None


def evaluate(tree, T, u, p, xp=None):
    """The value of a resolved tree, elementwise: node temperatures `T[..., i]` (°C),
    inputs `u[..., j]`, parameters `p[k]`. `xp`: `jax.numpy` (default) or `numpy`.

    A non-integer power of a number ≤ 0 is 0, and `sqrt` of a number ≤ 0 is 0, with zero
    gradient there (write `abs(x)^q * sign(x)` for an odd law); `log` of a number ≤ 0 is
    not finite, which the simulation reports.
    """
    if xp is None:
        import jax.numpy as xp

    def ev(t):
        tag = t[0]
        if tag == "num":
            return t[1]
        if tag == "T":
            return T[..., t[1]]
        if tag == "u":
            return u[..., t[1]]
        if tag == "p":
            return p[t[1]]
        if tag == "neg":
            return -ev(t[1])
        if tag == "bin":
            op, a = t[1], ev(t[2])
            if op == "^":
                k = _integer(t[3])
                if k is not None and k >= 0:
                    return a ** k
                b = ev(t[3])
                if k is not None:  # a negative integer power: 1 / a^|k|
                    return 1.0 / a ** (-k)
                positive = a > 0
                safe = xp.where(positive, a, 1.0)
                return xp.where(positive, safe ** b, 0.0)
            b = ev(t[3])
            return {"+": lambda: a + b, "-": lambda: a - b, "*": lambda: a * b,
                    "/": lambda: a / b}[op]()
        if tag == "call":
            f, args = t[1], [ev(a) for a in t[2]]
            x = args[0]
            if f == "sqrt":
                positive = x > 0
                return xp.where(positive, xp.sqrt(xp.where(positive, x, 1.0)), 0.0)
            if f == "step":
                return xp.where(x > 0, 1.0, 0.0)
            if f == "kelvin":
                return x + KELVIN
            if f == "min":
                return xp.minimum(x, args[1])
            if f == "max":
                return xp.maximum(x, args[1])
            return {"exp": xp.exp, "log": xp.log, "abs": xp.abs, "sign": xp.sign}[f](x)
        raise ExpressionError(f"unresolved name {t[1]!r}")
    return ev(tree)


def evaluate_numpy(tree, T, u, p):
    """`evaluate` in NumPy (no tracing), silencing the warnings of masked branches."""
    with np.errstate(all="ignore"):
        return evaluate(tree, np.asarray(T, float), np.asarray(u, float),
                        np.asarray(p, float), xp=np)


def _subtrees(tree):
    """Every subtree of `tree`, the whole first (a walk without recursion)."""
    stack, out = [tree], []
    while stack:
        t = stack.pop()
        out.append(t)
        if t[0] == "neg":
            stack.append(t[1])
        elif t[0] == "bin":
            stack += [t[2], t[3]]
        elif t[0] == "call":
            stack += list(t[2])
    return out


def constant_fault(tree) -> str | None:
    """Why a part of `tree` that reads no name is not finite (a division by zero, `log(0)`,
    an overflow), or None: such a part is not finite at any temperature, so a model
    holding it cannot be simulated or fitted."""
    def value(t) -> float:
        with np.errstate(all="ignore"):
            return float(evaluate(t, None, None, None, xp=np))

    for t in _subtrees(tree):
        if t[0] == "bin" and t[1] == "/" and not names(t[3]) and value(t[3]) == 0.0:
            return f"{_text(t)} divides by zero"
        if t[0] in ("bin", "call") and not names(t) and not np.isfinite(value(t)):
            return f"the constant part {_text(t)} is not finite"
    return None


def _text(t) -> str:
    """A short text of a tree, for messages."""
    if t[0] == "num":
        return np.format_float_positional(t[1], trim="-")
    if t[0] == "name":
        return t[1]
    if t[0] == "neg":
        return f"-{_text(t[1])}"
    if t[0] == "bin":
        return f"({_text(t[2])} {t[1]} {_text(t[3])})"
    if t[0] == "call":
        return f"{t[1]}({', '.join(_text(a) for a in t[2])})"
    return str(t)

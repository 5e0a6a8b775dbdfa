"""``${...}`` expressions in scene files: a bounded arithmetic evaluator over ``params``.

A string value ``"${expr}"`` anywhere in a scene (outside ``params``) is replaced by the value
of ``expr``: numbers, parameter names, ``+ - * / **`` and unary signs. No calls, attributes or
subscripts. Evaluation is bounded so that a hostile file fails fast instead of spinning the
CPU or exhausting memory: the expression is at most :data:`MAX_LENGTH` characters, every
intermediate result must be a finite number of magnitude at most :data:`MAX_MAGNITUDE`, and a
power is checked for size *before* it is computed (``9**9**9`` would otherwise build an
integer of 370 million digits). Errors name the file and the field holding the expression.
"""

from __future__ import annotations

import ast
import math
import operator
from pathlib import Path
from typing import Any

from tofhil.errors import InputFileError

#: Longest expression accepted (characters between ``${`` and ``}``).
MAX_LENGTH = 200
#: Largest magnitude of any intermediate or final value.
MAX_MAGNITUDE = 1e300

_BINOPS = {ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: operator.mul,
           ast.Div: operator.truediv, ast.Pow: operator.pow}
_EXPECTED = "${name} or ${arithmetic (+ - * / **) of numbers and params}"


class _Evaluator:
    def __init__(self, expr: str, params: dict[str, Any], source: str | Path, field: str) -> None:
        self.expr, self.params, self.source, self.field = expr, params, source, field

    def fail(self, message: str, expected: str = _EXPECTED) -> InputFileError:
        return InputFileError(message, file=self.source, field=self.field, expected=expected)

    def checked(self, x: Any) -> Any:
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            raise self.fail(f"{self.expr!r} is not a number")
        try:
            big = not math.isfinite(x) or abs(x) > MAX_MAGNITUDE
        except OverflowError:  # an int beyond the float range
            big = True
        if big:
            raise self.fail(f"{self.expr!r} gives a value that is not finite or exceeds {MAX_MAGNITUDE:g}",
                            f"a result of magnitude <= {MAX_MAGNITUDE:g}")
        return x

    def power(self, base: Any, exp: Any) -> Any:
        # Bound the result's size from logarithms before computing it.
        if base == 0 and exp < 0:
            raise self.fail(f"{self.expr!r} divides by zero", "a non-zero base for a negative power")
        if base != 0 and exp * math.log10(abs(base)) > math.log10(MAX_MAGNITUDE):
            raise self.fail(f"{self.expr!r} gives a value beyond {MAX_MAGNITUDE:g}",
                            f"a result of magnitude <= {MAX_MAGNITUDE:g}")
        if base < 0 and not float(exp).is_integer():
            raise self.fail(f"{self.expr!r} takes a fractional power of a negative number",
                            "a real result")
        try:
            return base ** exp
        except (OverflowError, ZeroDivisionError):
            raise self.fail(f"{self.expr!r} cannot be computed", f"a result of magnitude <= {MAX_MAGNITUDE:g}") from None

    def ev(self, node: ast.AST) -> Any:
        if isinstance(node, ast.Expression):
            return self.ev(node.body)
        if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)) \
                and not isinstance(node.value, bool):
            return self.checked(node.value)
        if isinstance(node, ast.Name):
            if node.id not in self.params:
                raise self.fail(f"unknown parameter {node.id!r}",
                                "one of the names in params: " + ", ".join(sorted(self.params)))
            value = self.params[node.id]
            if isinstance(value, str):
                raise self.fail(f"parameter {node.id!r} is a string ({value!r})", "a numeric parameter")
            return self.checked(value)
        if isinstance(node, ast.BinOp) and type(node.op) in _BINOPS:
            a, b = self.ev(node.left), self.ev(node.right)
            if isinstance(node.op, ast.Pow):
                return self.checked(self.power(a, b))
            if isinstance(node.op, ast.Div) and b == 0:
                raise self.fail(f"{self.expr!r} divides by zero", "a non-zero divisor")
            try:
                return self.checked(_BINOPS[type(node.op)](a, b))
            except OverflowError:
                raise self.fail(f"{self.expr!r} overflows", f"a result of magnitude <= {MAX_MAGNITUDE:g}") from None
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
            val = self.ev(node.operand)
            return -val if isinstance(node.op, ast.USub) else val
        raise self.fail(f"cannot evaluate {self.expr!r}")


def evaluate(expr: str, params: dict[str, Any], source: str | Path = "<scene>", field: str = "") -> int | float:
    """The value of ``expr`` (a parameter name or bounded arithmetic of numbers and parameters)."""
    ev = _Evaluator(expr, params, source, field)
    if len(expr) > MAX_LENGTH:
        raise ev.fail(f"expression of {len(expr)} characters", f"an expression of at most {MAX_LENGTH} characters")
    try:
        tree = ast.parse(expr.strip(), mode="eval")
    except (SyntaxError, ValueError, RecursionError, MemoryError):
        raise ev.fail(f"cannot parse {expr!r}") from None
    try:
        return ev.ev(tree)
    except RecursionError:
        raise ev.fail(f"{expr!r} is nested too deeply") from None


def substitute(node: Any, params: dict[str, Any], source: str | Path, path: str = "") -> Any:
    """A copy of ``node`` with every string ``"${expr}"`` replaced by its value over ``params``
    (the top-level ``params`` mapping itself is left as it is)."""
    if isinstance(node, dict):
        return {k: (node[k] if k == "params" and not path else
                    substitute(node[k], params, source, f"{path}.{k}" if path else str(k)))
                for k in node}
    if isinstance(node, list):
        return [substitute(x, params, source, f"{path}[{i}]") for i, x in enumerate(node)]
    if isinstance(node, str):
        s = node.strip()
        if s.startswith("${") and s.endswith("}"):
            return evaluate(s[2:-1], params, source, path)
    return node

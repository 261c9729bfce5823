"""Per-parameter functions of ``u`` in specs: constants, keyframes, safe expressions.

Every spec kind that lets a value vary along a parameter (a sweep's scale,
up vector or image-path association f(u); a warp's or morph's timing) uses
this one module, so the three forms mean the same everywhere:

* a constant: ``2.5`` or ``[10, 20]`` (a vector);
* keyframes: ``{keyframes: [[u, value], ...], interp: linear|cubic}``, values
  scalars or equally long vectors, ``u`` strictly increasing; outside the
  keyframes the end values hold (no extrapolation); ``cubic`` is a natural
  cubic spline through the keys (C2), ``linear`` the polyline;
* an expression: ``{expr: "0.5 + 0.25 * sin(2 * pi * u)"}`` or a list of
  expressions for a vector (``{expr: ["cos(u)", "sin(u)", "0"]}``).

Expressions are parsed with :mod:`ast` and evaluated by walking the tree with
numpy, never with ``eval``/``compile``: only numbers, the variable ``u``, the
constant ``pi``, ``+ - * / ** %``, unary minus/plus, and calls of ``sin cos
tan exp log sqrt abs min max`` are accepted; anything else (attribute access,
subscripts, other names or calls, keywords, lambdas, comprehensions) is a
:class:`~volwarp_cli.errors.SpecError` naming the key and line.
"""

from __future__ import annotations

import ast
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from ..errors import SpecError
from ..geometry import PLACEMENT_LIMIT
from .loader import format_key

__all__ = ["Function", "parse_function", "spec_error", "is_function_spec", "ALLOWED_FUNCTIONS",
           "ALLOWED_NAMES", "MAX_EXPRESSION_LENGTH", "MAX_VALUE", "MAX_ANGLE", "check_bounded"]

#: functions an expression may call, with their numpy implementation and arity (None: 2+)
ALLOWED_FUNCTIONS: dict[str, tuple[Callable, int | None]] = {
    "sin": (np.sin, 1), "cos": (np.cos, 1), "tan": (np.tan, 1),
    "exp": (np.exp, 1), "log": (np.log, 1), "sqrt": (np.sqrt, 1), "abs": (np.abs, 1),
    "min": (np.minimum, None), "max": (np.maximum, None),
}
#: names an expression may use besides the functions
ALLOWED_NAMES = ("u", "pi")
MAX_EXPRESSION_LENGTH = 2000
_MAX_FLOAT = float(np.finfo(np.float64).max)
#: the largest magnitude of a spec's coordinates, lengths and function values: the
#: placement bound every volume keeps; beyond it squared distances overflow and a norm
#: of 1e300 is inf (a direction of 0)
MAX_VALUE = PLACEMENT_LIMIT
#: the largest rotation angle (degrees) a spec may give: 2777 turns; at 1e300 the angle
#: has no digits left below a full turn (a double's step there is 1e284 degrees)
MAX_ANGLE = 1e6


def check_bounded(doc, path: Sequence, value, *, limit: float = MAX_VALUE,
                  what: str = "world coordinates and lengths") -> None:
    """Refuse (key path and line) any number in ``value`` (nested lists) beyond ``limit``."""
    if isinstance(value, list):
        for i, v in enumerate(value):
            check_bounded(doc, tuple(path) + (i,), v, limit=limit, what=what)
    elif isinstance(value, (int, float)) and not isinstance(value, bool):
        if not abs(value) <= limit:
            raise spec_error(doc, path, f"{value:g} is too large ({what} are at most "
                                        f"{limit:g})")

_BINOPS = {ast.Add: np.add, ast.Sub: np.subtract, ast.Mult: np.multiply,
           ast.Div: np.divide, ast.Pow: np.power, ast.Mod: np.mod}
_UNARY = {ast.USub: np.negative, ast.UAdd: np.positive}
#: the operators of each operator node, and how a refusal lists them
_OPERATORS = {ast.BinOp: (_BINOPS, "+ - * / ** %"), ast.UnaryOp: (_UNARY, "unary - and +")}
#: what the checker calls each refused construct, with its verb (so that the message's
#: grammar does not depend on how the words happen to end)
_NODE_WORDS = {
    ast.Attribute: "attribute access is", ast.Subscript: "subscripts are",
    ast.Lambda: "lambdas are", ast.Compare: "comparisons are",
    ast.BoolOp: "boolean operators are", ast.IfExp: "conditional expressions are",
    ast.ListComp: "comprehensions are", ast.GeneratorExp: "comprehensions are",
    ast.DictComp: "comprehensions are", ast.SetComp: "comprehensions are",
    ast.Starred: "starred arguments are", ast.List: "lists are", ast.Tuple: "tuples are",
    ast.Dict: "dictionaries are", ast.Set: "sets are", ast.JoinedStr: "f-strings are",
    ast.NamedExpr: "assignments are", ast.Await: "await is",
}
#: refused operators as the user wrote them (not Python's class names: FloorDiv, Invert)
_OPERATOR_SYMBOLS = {
    ast.FloorDiv: "//", ast.MatMult: "@", ast.LShift: "<<", ast.RShift: ">>",
    ast.BitOr: "|", ast.BitXor: "^", ast.BitAnd: "&", ast.Not: "not", ast.Invert: "~",
}


def spec_error(doc, path: Sequence, message: str) -> SpecError:
    """A :class:`SpecError` at key ``path`` of ``doc`` (a SpecDoc, or None: key only)."""
    if doc is not None:
        return doc.error(tuple(path), message)
    return SpecError(message, key=format_key(tuple(path)) or None)


def _raise(doc, path: tuple, message: str):
    raise spec_error(doc, path, message)


class Function:
    """A function of ``u`` returning ``(N,)`` (scalar) or ``(N, dim)`` (vector) float64.

    Call it with an array of ``u``; ``dim`` is ``None`` for scalar functions.
    ``path`` is the spec key it came from (for error messages).
    """

    def __init__(self, kind: str, dim: int | None, impl: Callable[[np.ndarray], np.ndarray],
                 path: tuple = (), doc=None, constant: np.ndarray | float | None = None):
        self.kind = kind
        self.dim = dim
        self._impl = impl
        self.path = tuple(path)
        self.doc = doc
        self.constant = constant
        self.limit = None  # the largest magnitude of a value (parse_function's ``limit``)

    @property
    def is_constant(self) -> bool:
        """True when the function is a constant (the same value at every ``u``)."""
        return self.kind == "constant"

    def error(self, message: str) -> SpecError:
        """A :class:`SpecError` at the spec key the function came from (raise it)."""
        return spec_error(self.doc, self.path, message)

    def __call__(self, u) -> np.ndarray:
        """The values at ``u`` (``(N,)`` or ``(N, dim)``); a SpecError where one is not finite."""
        u = np.atleast_1d(np.asarray(u, dtype=np.float64))
        with np.errstate(all="ignore"):
            out = np.asarray(self._impl(u), dtype=np.float64)
        shape = (u.shape[0],) if self.dim is None else (u.shape[0], self.dim)
        out = np.broadcast_to(out, shape).copy() if out.shape != shape else out
        if not np.all(np.isfinite(out)):
            bad = np.flatnonzero(~np.all(np.isfinite(out.reshape(u.shape[0], -1)), axis=1))[0]
            raise self.error(f"the {self.kind} gives a non-finite value at u={u[bad]:.6g}")
        if self.limit is not None and not np.all(np.abs(out) <= self.limit):
            row = np.abs(out.reshape(u.shape[0], -1)).max(axis=1)
            bad = int(np.argmax(row > self.limit))
            raise self.error(f"the {self.kind} gives {row[bad]:.3g} at u={u[bad]:.6g} (its "
                             f"values are at most {self.limit:g})")
        return out

    def __repr__(self):
        return f"Function({self.kind}, dim={self.dim}, at {format_key(self.path)!r})"


def is_function_spec(value: Any) -> bool:
    """True for the mapping forms (``keyframes``/``expr``) of a per-u function."""
    return isinstance(value, dict) and ("keyframes" in value or "expr" in value)


def parse_function(value: Any, path: Sequence = (), doc=None, *, dim: int | None | str = "any",
                   name: str = "value", limit: float | None = None) -> Function:
    """Parse a spec value into a :class:`Function` of ``u``.

    ``dim``: ``None`` requires a scalar, an integer requires a vector of that
    length, ``"any"`` accepts either (the value decides). A scalar given where
    a vector of length ``dim`` is wanted is broadcast (``scale: 10`` means
    ``[10, 10]``) only when ``dim`` is an integer and the value is a plain number
    or a scalar function. ``limit``: the largest magnitude of a value (a constant's
    refused here, at its entry's key; any other's where it is evaluated).
    """
    path = tuple(path)
    if is_function_spec(value):
        if "keyframes" in value and "expr" in value:
            _raise(doc, path, "give either 'keyframes' or 'expr', not both")
        extra = sorted(set(value) - {"keyframes", "interp", "expr"})
        if extra:
            _raise(doc, path + (extra[0],), f"unknown key {extra[0]!r} in a function "
                   "(allowed: keyframes, interp, expr)")
        if "keyframes" in value:
            fn = _keyframes(value, path, doc)
        else:
            if "interp" in value:
                _raise(doc, path + ("interp",), "'interp' goes with 'keyframes', not 'expr'")
            fn = _expression(value["expr"], path + ("expr",), doc)
    else:
        arr = _numbers(value, path, doc, name)
        const = arr.copy()
        if arr.ndim == 0:
            fn = Function("constant", None, lambda u, c=float(arr): np.full(u.shape, c), path, doc,
                          constant=float(arr))
        else:
            fn = Function("constant", arr.shape[0],
                          lambda u, c=const: np.broadcast_to(c, (u.shape[0], c.shape[0])),
                          path, doc, constant=const)
    if limit is not None and not is_function_spec(value):
        check_bounded(doc, path, value, limit=limit, what=f"{name}'s values")
    fn = _conform(fn, dim, path, doc, name)
    fn.limit = limit
    return fn


def _conform(fn: Function, dim, path, doc, name) -> Function:
    if dim == "any" or fn.dim == dim:
        return fn
    if dim is None:
        _raise(doc, path, f"{name} must be a single number, got a vector of {fn.dim}")
    if fn.dim is None:  # broadcast a scalar to a vector
        inner = fn
        const = None if fn.constant is None else np.full(dim, float(fn.constant))
        return Function(fn.kind, dim, lambda u: np.repeat(inner(u)[:, None], dim, axis=1),
                        path, doc, constant=const)
    _raise(doc, path, f"{name} must have {dim} components, got {fn.dim}")
    raise AssertionError  # pragma: no cover


def _numbers(value, path, doc, name) -> np.ndarray:
    if isinstance(value, bool) or value is None or isinstance(value, (str, dict)):
        _raise(doc, path, f"{name} must be a number, a list of numbers, "
               "{keyframes: ...} or {expr: ...}; got " + repr(value))
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        _raise(doc, path, f"{name} must be a number or a list of numbers, got {value!r}")
    if arr.ndim > 1 or (arr.ndim == 1 and arr.size == 0):
        _raise(doc, path, f"{name} must be a number or a flat list of numbers")
    if not np.all(np.isfinite(arr)):
        _raise(doc, path, f"{name} must be finite")
    return arr


# -- keyframes -------------------------------------------------------------------
def _keyframes(value: dict, path: tuple, doc) -> Function:
    keys = value["keyframes"]
    interp = value.get("interp", "linear")
    if interp not in ("linear", "cubic"):
        _raise(doc, path + ("interp",), f"interp must be linear or cubic, got {interp!r}")
    if not isinstance(keys, list) or not keys:
        _raise(doc, path + ("keyframes",), "keyframes must be a non-empty list of [u, value]")
    us, vals, dim = [], [], "unset"
    for i, key in enumerate(keys):
        kp = path + ("keyframes", i)
        if not isinstance(key, list) or len(key) != 2:
            _raise(doc, kp, "a keyframe is [u, value]")
        u = _numbers(key[0], kp + (0,), doc, "keyframe u")
        if u.ndim != 0:
            _raise(doc, kp + (0,), "keyframe u must be a single number")
        v = _numbers(key[1], kp + (1,), doc, "keyframe value")
        this_dim = None if v.ndim == 0 else v.shape[0]
        if dim != "unset" and this_dim != dim:
            _raise(doc, kp + (1,), f"keyframe values must all have the same size "
                   f"(keyframe 0 has {dim or 'one number'}, this has {this_dim or 'one number'})")
        dim = this_dim
        if us and not float(u) > us[-1]:
            _raise(doc, kp + (0,), f"keyframe u values must increase ({float(u):g} after {us[-1]:g})")
        us.append(float(u))
        vals.append(np.atleast_1d(v))
    x = np.array(us)
    y = np.array(vals)  # (K, dim or 1)
    if interp == "cubic" and len(us) >= 3:
        from scipy.interpolate import CubicSpline

        spline = CubicSpline(x, y, axis=0, bc_type="natural")

        def impl(u):
            return spline(np.clip(u, x[0], x[-1]))
    else:
        def impl(u):
            return np.stack([np.interp(u, x, y[:, c]) for c in range(y.shape[1])], axis=1)
    if dim is None:
        return Function("keyframes", None, lambda u: impl(u)[:, 0], path, doc)
    return Function("keyframes", dim, impl, path, doc)


# -- expressions -----------------------------------------------------------------
def _expression(expr, path: tuple, doc) -> Function:
    if isinstance(expr, list):
        if not expr:
            _raise(doc, path, "an expression list needs at least one expression")
        trees = [_compile(e, path + (i,), doc) for i, e in enumerate(expr)]

        def impl(u):
            return np.stack([np.broadcast_to(_eval(t, u), u.shape) for t in trees], axis=1)
        return Function("expression", len(trees), impl, path, doc)
    tree = _compile(expr, path, doc)
    return Function("expression", None, lambda u: _eval(tree, u), path, doc)


def _compile(text, path, doc) -> ast.AST:
    """Parse ``text`` and check every node against the whitelist; return the tree."""
    if isinstance(text, bool) or not isinstance(text, (str, int, float)):
        _raise(doc, path, f"an expression must be a string, got {text!r}")
    text = str(text)
    if len(text) > MAX_EXPRESSION_LENGTH:
        _raise(doc, path, f"expression is longer than {MAX_EXPRESSION_LENGTH} characters")
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except SyntaxError as exc:
        _raise(doc, path, f"expression {text!r} is not valid: {exc.msg}")
    except (RecursionError, MemoryError, ValueError):
        _raise(doc, path, f"expression {text!r} is too deeply nested or invalid")
    try:
        _check(tree.body, path, doc, text)
    except RecursionError:
        _raise(doc, path, f"expression {text!r} is too deeply nested")
    return tree.body


def _check(node, path, doc, text) -> None:
    where = f" in expression {text!r}"
    if isinstance(node, ast.Constant):
        if isinstance(node.value, bool) or not isinstance(node.value, (int, float)):
            _raise(doc, path, f"only numbers are allowed as constants, got {node.value!r}{where}")
        if isinstance(node.value, int) and not abs(node.value) <= _MAX_FLOAT:
            digits = len(str(abs(node.value))) if abs(node.value).bit_length() < 20000 else None
            _raise(doc, path, f"number too large{where} ("
                   + (f"{digits} digits; " if digits else "")
                   + f"the limit is {_MAX_FLOAT:.4g})")
        if isinstance(node.value, float) and not np.isfinite(node.value):
            _raise(doc, path, f"number too large{where} (the limit is {_MAX_FLOAT:.4g})")
        return
    if isinstance(node, ast.Name):
        if node.id not in ALLOWED_NAMES:
            if node.id in ALLOWED_FUNCTIONS:
                _raise(doc, path, f"{node.id!r} is a function: call it as {node.id}(...){where}")
            _raise(doc, path, f"unknown name {node.id!r}{where} (allowed: u, pi and the "
                   f"functions {' '.join(ALLOWED_FUNCTIONS)})")
        return
    if type(node) in _OPERATORS:
        allowed, words = _OPERATORS[type(node)]
        if type(node.op) not in allowed:
            _raise(doc, path, f"operator {_operator(node.op)} is not allowed{where} "
                   f"(allowed: {words})")
        for operand in ast.iter_child_nodes(node):  # (left and right, or the operand)
            if isinstance(operand, ast.expr):
                _check(operand, path, doc, text)
        return
    if isinstance(node, ast.Call):
        if not isinstance(node.func, ast.Name):
            if isinstance(node.func, ast.Attribute):
                _raise(doc, path, f"attribute access is not allowed{where}")
            _raise(doc, path, f"only the functions {' '.join(ALLOWED_FUNCTIONS)} "
                   f"may be called{where}")
        name = node.func.id
        if name not in ALLOWED_FUNCTIONS:
            _raise(doc, path, f"unknown function {name!r}{where} "
                   f"(allowed: {' '.join(ALLOWED_FUNCTIONS)})")
        if node.keywords:
            _raise(doc, path, f"keyword arguments are not allowed{where}")
        arity = ALLOWED_FUNCTIONS[name][1]
        nargs = len(node.args)
        if arity is None and nargs < 2:
            _raise(doc, path, f"{name}() takes two or more arguments ({nargs} given){where}")
        if arity is not None and nargs != arity:
            _raise(doc, path, f"{name}() takes {arity} argument ({nargs} given){where}")
        for arg in node.args:
            _check(arg, path, doc, text)
        return
    what = _NODE_WORDS.get(type(node), f"{type(node).__name__} is")
    _raise(doc, path, f"{what} not allowed{where}")


def _operator(op) -> str:
    """An operator as written in the expression, for messages."""
    return repr(_OPERATOR_SYMBOLS.get(type(op), type(op).__name__))


def _eval(node, u: np.ndarray):
    if isinstance(node, ast.Constant):
        return np.float64(node.value)
    if isinstance(node, ast.Name):
        return u if node.id == "u" else np.float64(np.pi)
    if isinstance(node, ast.BinOp):
        return _BINOPS[type(node.op)](_eval(node.left, u), _eval(node.right, u))
    if isinstance(node, ast.UnaryOp):
        return _UNARY[type(node.op)](_eval(node.operand, u))
    # ast.Call, checked by _check
    fn, arity = ALLOWED_FUNCTIONS[node.func.id]
    args = [_eval(a, u) for a in node.args]
    if arity is None:
        return fn.reduce(np.broadcast_arrays(*args))
    return fn(args[0])

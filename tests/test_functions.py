"""Per-parameter functions of u: constants, keyframes, whitelisted expressions."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import CubicSpline

from volwarp_cli.errors import SpecError
from volwarp_cli.spec.functions import parse_function
from volwarp_cli.spec.loader import parse_spec_text

U = np.linspace(-0.2, 1.2, 57)


def test_constant_scalar_and_vector():
    f = parse_function(2.5, ("scale",))
    assert f.dim is None and np.all(f(U) == 2.5)
    v = parse_function([1, 2, 3], ("up",), dim=3)
    assert v(U).shape == (len(U), 3) and np.all(v(U) == [1, 2, 3])


def test_scalar_broadcast_to_vector():
    f = parse_function(4, ("scale",), dim=2)
    assert np.all(f(U) == 4) and f(U).shape == (len(U), 2)


def test_linear_keyframes_match_numpy_interp_and_hold_ends():
    keys = [[0.0, 1.0], [0.3, 5.0], [1.0, -2.0]]
    f = parse_function({"keyframes": keys}, ("scale",))
    x, y = np.array(keys).T
    assert np.allclose(f(U), np.interp(U, x, y))
    assert f(np.array([-5.0]))[0] == 1.0 and f(np.array([5.0]))[0] == -2.0


def test_vector_keyframes():
    f = parse_function({"keyframes": [[0, [10, 10]], [1, [20, 40]]]}, ("scale",), dim=2)
    assert np.allclose(f(np.array([0.5])), [[15, 25]])


def test_cubic_keyframes_are_the_natural_spline():
    keys = [[0.0, 0.0], [0.25, 1.0], [0.6, -1.0], [1.0, 2.0]]
    f = parse_function({"keyframes": keys, "interp": "cubic"}, ("s",))
    x, y = np.array(keys).T
    ref = CubicSpline(x, y, bc_type="natural")
    inside = np.linspace(0, 1, 31)
    assert np.allclose(f(inside), ref(inside))
    assert np.allclose(f(np.array(keys)[:, 0]), y)  # passes through the keys


@pytest.mark.parametrize("expr, ref", [
    ("0.5 + 0.25 * sin(2 * pi * u)", lambda u: 0.5 + 0.25 * np.sin(2 * np.pi * u)),
    ("-u ** 2 + 3 % 2", lambda u: -u ** 2 + 1),
    ("sqrt(abs(u)) * exp(-u) + log(2 + u)", lambda u: np.sqrt(np.abs(u)) * np.exp(-u) + np.log(2 + u)),
    ("min(u, 0.5, 0.7) + max(u, 0.2)", lambda u: np.minimum(u, 0.5) + np.maximum(u, 0.2)),
    ("tan(u / 4) - cos(u)", lambda u: np.tan(u / 4) - np.cos(u)),
    ("3", lambda u: np.full_like(u, 3.0)),
])
def test_expressions_match_numpy(expr, ref):
    f = parse_function({"expr": expr}, ("scale", "expr"))
    assert np.allclose(f(U), ref(U))


def test_vector_expression():
    f = parse_function({"expr": ["cos(u)", "sin(u)", "0"]}, ("up",), dim=3)
    got = f(U)
    assert np.allclose(got, np.stack([np.cos(U), np.sin(U), np.zeros_like(U)], axis=1))


@pytest.mark.parametrize("expr, words", [
    ("foo(u)", "unknown function 'foo'"),
    ("u.real", "attribute access"),
    ("__import__('os').system('echo hi')", "attribute access"),
    ("open('x')", "unknown function 'open'"),
    ("x + 1", "unknown name 'x'"),
    ("sin", "is a function"),
    ("u if u else 1", "not allowed"),
    ("[u for u in (1, 2)]", "not allowed"),
    ("(lambda: 1)()", "only the functions"),
    ("u[0]", "subscripts"),
    ("sin(u, u)", "takes 1 argument"),
    ("max(u)", "two or more"),
    ("sin(x=u)", "keyword"),
    ("'abc'", "only numbers"),
    ("u +", "not valid"),
    ("u < 1", "not allowed"),
])
def test_rejected_expressions(expr, words):
    with pytest.raises(SpecError) as exc:
        parse_function({"expr": expr}, ("scale", "expr"))
    assert words in str(exc.value)
    assert "scale.expr" in str(exc.value)


def test_errors_carry_key_path_and_line():
    doc = parse_spec_text("version: 1\nscale:\n  expr: 'evil(u)'\n", "s.yaml")
    with pytest.raises(SpecError) as exc:
        parse_function(doc.data["scale"], ("scale",), doc)
    assert exc.value.line == 3 and exc.value.key == "scale.expr"
    assert str(exc.value).startswith("s.yaml:3: scale.expr:")


def test_non_finite_value_at_evaluation_is_a_spec_error():
    f = parse_function({"expr": "log(u)"}, ("path",))
    with pytest.raises(SpecError, match="non-finite value at u=0"):
        f(np.array([0.0, 0.5]))


@pytest.mark.parametrize("value, words", [
    ({"keyframes": []}, "non-empty"),
    ({"keyframes": [[0, 1], [0, 2]]}, "must increase"),
    ({"keyframes": [[0, 1], [1, [1, 2]]]}, "same size"),
    ({"keyframes": [[0, 1]], "interp": "quintic"}, "linear or cubic"),
    ({"expr": "u", "interp": "linear"}, "goes with 'keyframes'"),
    ({"keyframes": [[0, 1]], "expr": "u"}, "not both"),
    ("u", "must be a number"),
    (True, "must be a number"),
])
def test_bad_function_specs(value, words):
    with pytest.raises(SpecError, match=words):
        parse_function(value, ("f",))


def test_dimension_checks():
    with pytest.raises(SpecError, match="3 components"):
        parse_function([1, 2], ("up",), dim=3)
    with pytest.raises(SpecError, match="single number"):
        parse_function([1, 2], ("path",), dim=None)


# The checker's messages, whole: each refused construct with the right verb (the message
# used to say "attribute access are not allowed"), operators as written (not Python's
# class names), argument counts before the expression.
@pytest.mark.parametrize("expr, message", [
    ("u.real", "attribute access is not allowed in expression 'u.real'"),
    ("await u", "await is not allowed in expression 'await u'"),
    ("u[0]", "subscripts are not allowed in expression 'u[0]'"),
    ("u < 1", "comparisons are not allowed in expression 'u < 1'"),
    ("(1, 2)", "tuples are not allowed in expression '(1, 2)'"),
    ("f'{u}'", "f-strings are not allowed in expression \"f'{u}'\""),
    ("(x := 1)", "assignments are not allowed in expression '(x := 1)'"),
    ("u // 2", "operator '//' is not allowed in expression 'u // 2' (allowed: + - * / ** %)"),
    ("u @ u", "operator '@' is not allowed in expression 'u @ u' (allowed: + - * / ** %)"),
    ("~u", "operator '~' is not allowed in expression '~u' (allowed: unary - and +)"),
    ("not u", "operator 'not' is not allowed in expression 'not u' (allowed: unary - and +)"),
    ("cos(u, 2)", "cos() takes 1 argument (2 given) in expression 'cos(u, 2)'"),
    ("min(u)", "min() takes two or more arguments (1 given) in expression 'min(u)'"),
    ("None", "only numbers are allowed as constants, got None in expression 'None'"),
    ("1e999", "number too large in expression '1e999' (the limit is 1.798e+308)"),
])
def test_rejection_messages_read_as_english(expr, message):
    with pytest.raises(SpecError) as exc:
        parse_function({"expr": expr}, ("scale",))
    assert str(exc.value) == f"scale.expr: {message}"


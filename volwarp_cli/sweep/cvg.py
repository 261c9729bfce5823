"""Constructive volume geometry (CVG) operators on scalar fields (Winter & Chen §4.3).

Chen & Tucker's CVG decomposes operations on spatial objects into real-domain
operations on their scalar fields. volwarp uses them twice:

* inside one sweep, as the paper's ``eta``: where several instances of the
  swept template map to the same point (a self-intersecting trajectory,
  segments that cross, a template that sweeps back on itself), their values
  are combined per field; points reached once keep their value, points never
  reached get the constant ``c = 0``;
* between sweeps, in a ``scene`` operator tree, pointwise on whole fields
  (0 outside each object).

Operators (``a`` first, ``b`` second; ``oa``, ``ob`` the operands' opacities):

* ``union``: ``max(a, b)``; ``intersection``: ``min(a, b)``;
* ``difference``: ``max(a - b, 0)`` (so a field minus itself is empty);
* ``sum``: ``clip(a + b, 0, 1)``;
* ``blend``: the opacity-weighted mean ``(oa a + ob b) / (oa + ob)``, with a
  weight floor of 1e-6 so that all-transparent points get the plain mean;
* ``first``: ``a`` (CVG's "select": keep the first operand's attribute).

All but ``difference`` and ``first`` are commutative; ``union``,
``intersection`` and ``blend`` are idempotent.
"""

from __future__ import annotations

import numpy as np

OPERATORS = ("union", "intersection", "difference", "blend", "sum", "first")
#: operator -> code used by the voxeliser's C kernel (:mod:`._sweepkernels`)
OP_CODES = {name: i for i, name in enumerate(OPERATORS)}
BLEND_FLOOR = 1e-6


def union(a, b):
    """``max(a, b)``."""
    return np.maximum(a, b)


def intersection(a, b):
    """``min(a, b)``."""
    return np.minimum(a, b)


def difference(a, b):
    """``max(a - b, 0)`` (a field minus itself is empty)."""
    return np.maximum(np.subtract(a, b), 0)


def sum_clamped(a, b):
    """The ``sum`` operator: ``clip(a + b, 0, 1)``."""
    return np.clip(np.add(a, b), 0, 1)


def blend(a, b, oa=None, ob=None):
    """Opacity-weighted mean; without opacities, the plain mean."""
    wa = BLEND_FLOOR if oa is None else np.maximum(oa, 0) + BLEND_FLOOR
    wb = BLEND_FLOOR if ob is None else np.maximum(ob, 0) + BLEND_FLOOR
    return (np.multiply(wa, a) + np.multiply(wb, b)) / (wa + wb)


def first(a, b):
    """A copy of ``a`` (CVG's "select": the first operand's attribute)."""
    return np.array(a, copy=True)


_BINARY = {"union": union, "intersection": intersection, "difference": difference,
           "sum": sum_clamped, "first": first}


def combine(op: str, a, b, oa=None, ob=None):
    """Apply operator ``op`` to fields ``a`` and ``b`` (opacities only matter for blend)."""
    if op == "blend":
        return blend(a, b, oa, ob)
    return _BINARY[op](a, b)


def default_attribute_op(opacity_op: str) -> str:
    """Attribute operator that goes with an opacity operator given as one word."""
    return "first" if opacity_op == "difference" else "blend"


def resolve_ops(spec, fields) -> dict[str, str]:
    """Per-field operators from a spec value (a word, or a mapping with ``default``).

    A word names the opacity operator; attributes then ``blend`` (``first``
    for ``difference``). Omitted: ``union`` for opacity, ``blend`` otherwise.
    """
    if spec is None:
        spec = {"opacity": "union", "default": "blend"}
    if isinstance(spec, str):
        spec = {"opacity": spec, "default": default_attribute_op(spec)}
    default = spec.get("default", "blend")
    out = {}
    for name in fields:
        if name in spec:
            out[name] = spec[name]
        elif name == "opacity":
            out[name] = spec.get("opacity", "union")
        else:
            out[name] = default
    return out


def combine_objects(op_by_field: dict[str, str], objects: list[dict[str, np.ndarray]],
                    shape) -> dict[str, np.ndarray]:
    """Combine spatial objects (dicts field -> array, 0 where absent) left to right."""
    names = []
    for obj in objects:
        for n in obj:
            if n not in names:
                names.append(n)
    zero = np.zeros(shape, dtype=np.float32)
    result = {n: objects[0].get(n, zero) for n in names}
    for obj in objects[1:]:
        oa = result.get("opacity")
        ob = obj.get("opacity")
        if ob is None and "opacity" in names:
            ob = zero
        new = {}
        for n in names:
            new[n] = combine(op_by_field[n], result[n], obj.get(n, zero), oa, ob).astype(
                np.float32, copy=False)
        result = new
    return result


class Accumulator:
    """Per-field ``eta`` accumulation of template instances (numpy; used by ``direct``).

    ``add`` takes one batch of instances at distinct flat voxel indices; the
    voxeliser's C kernel (:mod:`._sweepkernels`) implements the same rules.
    """

    def __init__(self, names: list[str], ops: dict[str, str], n_voxels: int,
                 opacity: str | None = "opacity"):
        self.names = list(names)
        self.ops = [ops[n] for n in names]
        self.acc = np.zeros((len(names), n_voxels), dtype=np.float32)
        self.covered = np.zeros(n_voxels, dtype=bool)
        self.opacity = self.names.index(opacity) if opacity in self.names else -1
        self.wsum = np.zeros(n_voxels, dtype=np.float32) if "blend" in self.ops else None

    def add(self, idx: np.ndarray, values: np.ndarray) -> None:
        """Add instances at flat voxel indices ``idx`` (unique) with ``values[F, len(idx)]``."""
        if idx.size == 0:
            return
        cov = self.covered[idx]
        w = (np.maximum(values[self.opacity], 0) + BLEND_FLOOR if self.opacity >= 0
             else np.ones(idx.size))
        for f, op in enumerate(self.ops):
            v = values[f]
            cur = self.acc[f, idx]
            if op == "blend":
                new = cur + w * v
            else:
                if op == "union":
                    comb = np.maximum(cur, v)
                elif op == "intersection":
                    comb = np.minimum(cur, v)
                elif op == "difference":
                    comb = np.maximum(cur - v, 0)
                elif op == "sum":
                    comb = np.clip(cur + v, 0, 1)
                else:  # first
                    comb = cur
                new = np.where(cov, comb, v)
            self.acc[f, idx] = new
        if self.wsum is not None:
            self.wsum[idx] += w
        self.covered[idx] = True

    def result(self) -> dict[str, np.ndarray]:
        """The fields, by name (see :func:`finish_fields`): once, at the end (in place)."""
        return finish_fields(self.names, self.ops, self.acc, self.wsum, self.covered)


def finish_fields(names, ops, acc, wsum, covered) -> dict[str, np.ndarray]:
    """Turn accumulators into fields: blend sums divided by their weights, 0 where uncovered.

    In place: the fields are ``acc``'s rows (a block's accumulators, used once), with
    one array of weights and one mask beside them (a copy a field and the division's
    temporaries took the blocks past their share of the memory limit).
    """
    out = {}
    weights = uncovered = None
    for f, name in enumerate(names):
        a = acc[f]
        if ops[f] == "blend":  # (in place, on the block's own accumulators: no copies)
            if weights is None:
                weights = np.where(wsum > 0, wsum, np.float32(1))
                uncovered = ~covered
            with np.errstate(invalid="ignore", divide="ignore"):
                np.divide(a, weights, out=a)
            a[uncovered] = 0
        out[name] = a
    return out

"""``--dtype``'s cast (:func:`volwarp_cli.samples.cast_samples`): rounded, clipped to the range.

float32 holds neither 2**31 - 1 nor 2**32 - 1: clipping float32 samples to
int32's range in float32 rounded the bound up to 2**31, and the cast wrapped
3e9 and +inf to -2**31 (uint32: 5e9 to 0), exit 0.
"""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from volwarp_cli.samples import cast_samples

TYPES = ["int8", "uint8", "int16", "uint16", "int32", "uint32"]


def _expected(x: float, dt: str) -> int:
    """The value rounded half to even, then clipped, in exact Python arithmetic."""
    info = np.iinfo(dt)
    if math.isinf(x):
        return info.max if x > 0 else info.min
    return max(info.min, min(info.max, round(x)))


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(allow_nan=False, width=32), min_size=1, max_size=20),
       st.sampled_from(TYPES), st.sampled_from(["float32", "float64"]))
def test_floats_are_rounded_and_clipped_to_the_type_s_range(values, dt, src):
    data = np.array(values, dtype=src)
    out = cast_samples(data, dt)
    assert out.dtype == np.dtype(dt)
    assert out.tolist() == [_expected(float(v), dt) for v in data]


def test_the_ends_of_int32_and_uint32_from_float32():
    data = np.array([3e9, 5e9, 1e10, np.inf, -3e9, -np.inf, 2147483520.0], np.float32)
    assert cast_samples(data, "int32").tolist() == [2**31 - 1] * 4 + [-2**31] * 2 + [2147483520]
    assert cast_samples(data, "uint32").tolist() == [3000000000] + [2**32 - 1] * 3 + [0, 0,
                                                                                     2147483520]

"""The Volume type's coordinate maps and the spec loader's error reporting."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from volwarp_cli.errors import SpecError, VolwarpError
from volwarp_cli.spec import format_key, parse_spec_text, validate
from volwarp_cli.volume import Header, Volume, xyz_to_zyx, zyx_to_xyz

finite = st.floats(-1e3, 1e3, allow_nan=False)
positive = st.floats(0.05, 20.0)


def rotation(angles):
    a, b, c = angles
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    return rz @ ry @ rx


@settings(max_examples=60, deadline=None)
@given(spacing=st.tuples(positive, positive, positive), origin=st.tuples(finite, finite, finite),
       angles=st.tuples(*[st.floats(-np.pi, np.pi)] * 3),
       ijk=st.tuples(*[st.floats(-50, 50)] * 3))
def test_world_and_index_are_inverse(spacing, origin, angles, ijk):
    vol = Volume(np.zeros((2, 3, 4), np.uint8), spacing=spacing, origin=origin,
                 direction=rotation(angles))
    world = vol.index_to_world(ijk)
    np.testing.assert_allclose(vol.world_to_index(world), ijk, atol=1e-6)
    # the contract's formula, written out
    expect = np.asarray(origin) + rotation(angles) @ (np.asarray(spacing) * np.asarray(ijk))
    np.testing.assert_allclose(world, expect, atol=1e-9)
    np.testing.assert_allclose(vol.index_to_world_matrix @ np.append(ijk, 1.0),
                               np.append(expect, 1.0), atol=1e-9)


def test_axis_order_helpers_and_shape():
    vol = Volume(np.zeros((2, 3, 4)))
    assert vol.shape_xyz == (4, 3, 2)
    assert xyz_to_zyx((1, 2, 3)) == (3, 2, 1)
    assert zyx_to_xyz(vol.data.shape) == (4, 3, 2)


def test_world_bounds_of_rotated_volume():
    vol = Volume(np.zeros((1, 1, 11)), spacing=(2, 1, 1), direction=rotation((0, 0, np.pi / 2)))
    lo, hi = vol.world_bounds()
    np.testing.assert_allclose(lo, (0, 0, 0), atol=1e-12)
    np.testing.assert_allclose(hi, (0, 20, 0), atol=1e-12)


@pytest.mark.parametrize("kwargs,needle", [
    ({"spacing": (1, 0, 1)}, "positive"),
    ({"spacing": (1, 1)}, "3 values"),
    ({"origin": (np.nan, 0, 0)}, "finite"),
    ({"direction": np.zeros((3, 3))}, "singular"),
])
def test_volume_rejects_bad_geometry(kwargs, needle):
    with pytest.raises(VolwarpError, match=needle):
        Volume(np.zeros((2, 2, 2)), **kwargs)


def test_volume_needs_three_axes():
    with pytest.raises(VolwarpError, match="3 axes"):
        Volume(np.zeros((2, 2)))


def test_a_header_is_its_volume_without_the_samples():
    """Volume.header: the shape, type, geometry, frame and key/values; with_data goes back."""
    data = np.arange(24, dtype=np.int16).reshape(2, 3, 4)
    vol = Volume(data, spacing=(0.5, 1.0, 2.0), origin=(1.0, 2.0, 3.0),
                 direction=rotation((0.1, 0.2, 0.3)), space="ras", meta={"k": "v"})
    head = vol.header
    assert isinstance(head, Header) and not hasattr(head, "data")
    assert head.shape == vol.shape == (2, 3, 4) and head.dtype == np.int16
    assert head.shape_xyz == vol.shape_xyz == (4, 3, 2)
    assert (head.space, head.file_space) == (vol.space, vol.file_space) == (
        "left-posterior-superior", "right-anterior-superior")
    for name in ("spacing", "origin", "direction", "index_to_world_matrix"):
        np.testing.assert_array_equal(getattr(head, name), getattr(vol, name))
    np.testing.assert_array_equal(head.world_bounds(), vol.world_bounds())
    assert head.same_grid(vol) and vol.same_grid(head) and head.meta == {"k": "v"}
    head.meta["k"] = "w"  # (its own key/values)
    assert vol.meta == {"k": "v"}
    back = vol.header.with_data(data)
    assert back.same_grid(vol) and back.meta == vol.meta and back.file_space == vol.file_space
    np.testing.assert_array_equal(back.origin, vol.origin)  # (converted once, not twice)
    moved = head.replace(shape=(5, 6, 7), dtype=np.float32, origin=np.zeros(3))
    assert moved.shape == (5, 6, 7) and moved.dtype == np.float32 and moved.meta == head.meta
    assert head.shape == (2, 3, 4)


def test_a_header_converts_its_file_frame_as_a_volume_does():
    head = Header((2, 2, 2), np.uint8, origin=(1.0, 2.0, 3.0), space="ras")
    vol = Volume(np.zeros((2, 2, 2), np.uint8), origin=(1.0, 2.0, 3.0), space="ras")
    np.testing.assert_array_equal(head.origin, (-1.0, -2.0, 3.0))
    np.testing.assert_array_equal(head.direction, vol.direction)
    assert (head.space, head.file_space) == (vol.space, vol.file_space)


@pytest.mark.parametrize("kwargs,needle", [
    ({"spacing": (1, 0, 1)}, "positive"),
    ({"origin": (np.nan, 0, 0)}, "finite"),
    ({"direction": np.zeros((3, 3))}, "singular"),
    ({"shape": (2, 2)}, "3 axes"),
    ({"shape": (2, -1, 2)}, "3 axes"),
])
def test_header_rejects_what_a_volume_rejects(kwargs, needle):
    args = {"shape": (2, 2, 2), "dtype": np.float32, **kwargs}
    with pytest.raises(VolwarpError, match=needle):
        Header(**args)


def test_a_header_pickles_small_whatever_its_grid():
    """A header travels to block tasks in other processes: no samples, whatever the grid."""
    import pickle

    small = Header((2, 3, 4), np.float32, meta={"k": "v"})
    huge = Header((4000, 5000, 6000), np.float32, meta={"k": "v"})
    sizes = [len(pickle.dumps(h)) for h in (small, huge)]
    assert max(sizes) < 2_000 and abs(sizes[1] - sizes[0]) < 16, sizes
    again = pickle.loads(pickle.dumps(huge))
    assert again.shape == huge.shape and again.same_grid(huge) and again.meta == huge.meta


SCHEMA = {
    "type": "object",
    "additionalProperties": False,
    "required": ["version", "steps"],
    "properties": {
        "version": {"const": 1},
        "steps": {"type": "array", "items": {
            "type": "object", "additionalProperties": False,
            "properties": {"move": {"type": "array", "items": {
                "type": "object", "additionalProperties": False,
                "properties": {"index": {"type": "array", "items": {"type": "integer"},
                                         "minItems": 3, "maxItems": 3}}}}}}},
    },
}

GOOD = """\
version: 1
steps:
  - move:
      - {index: [1, 2, 3]}
  - move:
      - {index: [4, 5, 6]}
"""


def test_format_key():
    assert format_key(("steps", 2, "move", 0, "index")) == "steps[2].move[0].index"
    assert format_key(()) == ""


def test_valid_spec_and_lines():
    doc = parse_spec_text(GOOD, file="w.yaml")
    validate(doc, SCHEMA)
    assert doc.line(("steps", 1, "move", 0, "index")) == 6
    assert doc.line(("steps", 1, "move", 0, "index", 2)) == 6
    assert doc.get(("steps", 1, "move", 0, "index")) == [4, 5, 6]


@pytest.mark.parametrize("text,key,line,needle", [
    (GOOD.replace("[4, 5, 6]", "[4, 5.5, 6]"), "steps[1].move[0].index[1]", 6, "integer"),
    (GOOD.replace("{index: [4, 5, 6]}", "{index: [4, 5, 6], by: 3}"), "steps[1].move[0].by", 6,
     "unknown key 'by'"),
    (GOOD + "colour: red\n", "colour", 7, "unknown key 'colour'"),
    (GOOD.replace("version: 1\n", ""), None, 1, "'version' is required"),
    (GOOD.replace("[1, 2, 3]", "[1, 2]"), "steps[0].move[0].index", 4, "too short"),
])
def test_schema_errors_name_key_and_line(text, key, line, needle):
    doc = parse_spec_text(text, file="w.yaml")
    with pytest.raises(SpecError) as info:
        validate(doc, SCHEMA)
    err = info.value
    assert err.key == key
    assert err.line == line
    assert needle in err.message
    assert str(err).startswith(f"w.yaml:{line}: ")


def test_yaml_syntax_error_has_line():
    with pytest.raises(SpecError) as info:
        parse_spec_text("version: 1\nsteps: [\n  - a\n", file="bad.yaml")
    assert info.value.line is not None and info.value.line >= 2
    assert "YAML syntax error" in str(info.value)


def test_duplicate_keys_are_refused():
    with pytest.raises(SpecError, match="duplicate key 'version'") as info:
        parse_spec_text("version: 1\nsteps: []\nversion: 2\n", file="d.yaml")
    assert info.value.line == 3


def test_spec_never_constructs_python_objects():
    with pytest.raises(SpecError):
        parse_spec_text("version: !!python/object/apply:os.system ['true']\n")


def test_empty_and_non_mapping_specs():
    with pytest.raises(SpecError, match="empty"):
        parse_spec_text("")
    with pytest.raises(SpecError, match="mapping"):
        parse_spec_text("- 1\n- 2\n")

"""Spec files: YAML loading, schema validation and per-parameter functions."""

from .loader import SpecDoc, format_key, load_schema, load_spec, parse_spec_text, validate

__all__ = ["SpecDoc", "format_key", "load_schema", "load_spec", "parse_spec_text", "validate"]

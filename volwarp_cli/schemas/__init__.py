"""The JSON schemas of the spec files: warp, morph, sweep, batch manifest, affine transform."""

"""Implicit morphs (Dinh & Carvalho 2004): alignment, landmark warps, SDF interpolation."""

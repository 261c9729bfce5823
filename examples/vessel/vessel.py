"""The synthetic angiogram's geometry, shared by make_vessel.py and make_spec.py.

A blood vessel (a tube of radius R) runs up the volume along z. Its centreline
is straight except for a V-shaped kink in the x-z plane: a triangular bump of
height AMPLITUDE and half-width HALF_WIDTH, its corners rounded by a Gaussian
of width ROUNDING (so the tube does not fold into itself at the apex). A
thinner side branch leaves the lower straight part towards -x and runs out of
the volume. Lengths are voxels (1 mm) of the full-size model; SIZE=small
scales them all by 1/2.

The "unbending" map takes the tube's own frame along its centreline to the
straight line x = X0, y = Y0: the point at arc length s and offset (a, b)
(a along the normal in the x-z plane, b along y) goes to
(X0 + a, Y0 + b, Z_START + s). Arc length is kept, so the straightened
vessel is longer than the kinked one is tall and its top end moves up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d

DZ = 0.05  # sampling step of the centreline (voxels along z)


@dataclass(frozen=True)
class Geometry:
    shape: tuple[int, int, int]  # samples along x, y, z
    radius: float                # lumen radius
    x0: float                    # the straight parts' x (and the straightened vessel's)
    y0: float
    kink_z: float                # apex of the kink
    amplitude: float             # how far the apex stands out (+x)
    half_width: float            # half the kink's extent along z, before rounding
    rounding: float              # Gaussian sigma that rounds the corners
    branch_z: float              # where the side branch leaves the vessel
    branch_angle: float          # degrees from +z towards -x
    branch_radius: float


FULL = Geometry(shape=(80, 48, 128), radius=4.5, x0=30.0, y0=23.5, kink_z=70.0,
                amplitude=16.0, half_width=22.0, rounding=6.0, branch_z=20.0,
                branch_angle=50.0, branch_radius=2.7)


def geometry(size: str) -> Geometry:
    if size == "full":
        return FULL
    if size == "small":
        g = FULL
        return Geometry(shape=tuple(n // 2 for n in g.shape), radius=g.radius / 2,
                        x0=g.x0 / 2, y0=(g.shape[1] // 2 - 1) / 2, kink_z=g.kink_z / 2,
                        amplitude=g.amplitude / 2, half_width=g.half_width / 2,
                        rounding=g.rounding / 2, branch_z=g.branch_z / 2,
                        branch_angle=g.branch_angle, branch_radius=g.branch_radius / 2)
    raise SystemExit(f"size must be full or small, not {size!r}")


class Centreline:
    """The kinked centreline sampled every DZ along z, past both ends of the volume."""

    def __init__(self, g: Geometry, margin: float = 12.0):
        nz = g.shape[2]
        self.g = g
        z = np.arange(-margin, nz - 1 + margin + DZ / 2, DZ)
        tri = np.clip(1.0 - np.abs(z - g.kink_z) / g.half_width, 0.0, None)
        x = g.x0 + g.amplitude * gaussian_filter1d(tri, g.rounding / DZ, mode="nearest")
        self.points = np.stack([x, np.full_like(z, g.y0), z], axis=1)
        seg = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        self.s = np.concatenate([[0.0], np.cumsum(seg)])
        tangent = np.gradient(self.points, self.s, axis=0)
        tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
        self.tangent = tangent
        # normal in the x-z plane: (1, 0, 0) where the vessel is straight
        self.normal = np.stack([tangent[:, 2], np.zeros_like(z), -tangent[:, 0]], axis=1)
        self.z0 = z[0]  # arc length 0 is at z = z0 (straight there: z = z0 + s)

    def at(self, s: float):
        """Point, normal of the centreline at arc length s."""
        p = np.array([np.interp(s, self.s, self.points[:, d]) for d in range(3)])
        n = np.array([np.interp(s, self.s, self.normal[:, d]) for d in range(3)])
        return p, n / np.linalg.norm(n)

    def s_at_z(self, z: float) -> float:
        return float(np.interp(z, self.points[:, 2], self.s))

    def kinked(self, s: float, a: float, b: float) -> np.ndarray:
        """The point at arc length s, offset a along the normal and b along y."""
        p, n = self.at(s)
        return p + a * n + np.array([0.0, b, 0.0])

    def straight(self, s: float, a: float, b: float) -> np.ndarray:
        """Where the unbending map sends that point."""
        return np.array([self.g.x0 + a, self.g.y0 + b, self.z0 + s])


def branch_segment(g: Geometry):
    """Start and end of the side branch's axis (long enough to leave the volume)."""
    start = np.array([g.x0, g.y0, g.branch_z])
    t = np.radians(g.branch_angle)
    direction = np.array([-np.sin(t), 0.0, np.cos(t)])
    return start, start + 2.0 * max(g.shape) * direction

"""Write the gust's warp spec: whole layers of control points moved downwind (+x).

    python make_spec.py SPEC.yaml [--gust MM] [--frames N]

The capture lattice is 5 x 5 x 11 control points over the tree's 100 x 100 x 128 mm
box (make_tree.py), uniform placement: layer k (the lattice's z index) lies at
world height z_k = 16 (k - 1) mm, for either SIZE. Every control point of layer k
moves by the same vector (u_k, 0, w_k) = (u(z_k), 0, w(z_k)), so the warp depends
on height alone (u and w at any height are the cubic B-splines of the layers'):

    u(z) = GUST * s^2,   s = (z - 16) / L,   L = 120 - 16 (mm), for z > 16, else 0

bends the tree downwind along a parabola: no move and no tilt at the root,
steepest at the top, which moves GUST mm (z = 120 mm is the crown's top; any
cantilever, whatever bends it, starts out from its root so), and

    w(z) = -(1/2) * integral_16^z u'(t)^2 dt = -(2 GUST^2 / 3 L^4) (z - 16)^3

lowers each height by what keeps the trunk's length (a bent stick's top comes
down as it swings out). Layers 0-2 (z = -16, 0, 16 mm) stay put: the lowest
region of the lattice (z = 0-16 mm, the mound and the root) then moves only by
layer 3's share, under 0.15 mm, and the base stays rooted. The step runs over
--frames equal increments: frame n of N moves every layer n/N of its way.
"""

import argparse

LATTICE = (5, 5, 11)  # control points (x, y, z); capture with the same --lattice
HEIGHT = 128.0        # the box's height (mm): layer spacing HEIGHT / (11 - 3) = 16 mm
ROOT = 16.0           # layers at or below this height do not move
TOP = 120.0           # the tree's top (mm)


def layer_z(k):
    return HEIGHT / (LATTICE[2] - 3) * (k - 1)


def layer_move(k, gust):
    """(u, w): the horizontal and vertical move (mm) of lattice layer k."""
    length = TOP - ROOT
    h = max(layer_z(k) - ROOT, 0.0)
    return gust * (h / length) ** 2, -2.0 * gust ** 2 * h ** 3 / (3.0 * length ** 4)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("spec")
    ap.add_argument("--gust", type=float, default=30.0, help="the top's sideways move (mm)")
    ap.add_argument("--frames", type=int, default=2, help="equal increments of the gust")
    args = ap.parse_args()
    nx, ny, nz = LATTICE
    lines = [
        "# A strong gust of wind from -x (True & Hughes 1992, Fig. 10), written by make_spec.py:",
        f"# every control point of lattice layer k moved by (u_k, 0, w_k) mm, the top {args.gust:g} mm",
        "# downwind. Layer k lies at z = 16 (k - 1) mm; layers 0-2 stay put.",
        "version: 1",
        "units: world",
        f"capture: {{lattice: [{nx}, {ny}, {nz}]}}",
        "pushforward: box",
        "steps:",
        "  - name: gust",
        f"    frames: {args.frames}",
        "    move:",
    ]
    for k in range(nz):
        u, w = layer_move(k, args.gust)
        if u == 0.0 and w == 0.0:
            continue
        lines.append(f"      # layer {k}, z = {layer_z(k):g} mm: u = {u:.4f}, w = {w:.4f}")
        for j in range(ny):
            for i in range(nx):
                lines.append(f"      - {{index: [{i}, {j}, {k}], by: [{u:.4f}, 0.0, {w:.4f}]}}")
    with open(args.spec, "w") as fh:
        fh.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()

"""`volwarp capture INPUT -o SCENE.vwc`: pull a volume back into a B-spline domain voxmap."""

from __future__ import annotations

import click

from ..io import check_output_path
from ..labelmap import VALUES
from ..progress import timed
from .common import load_input
from .options import (
    INPUT_PATH,
    Command,
    common_options,
    examples,
    finite,
    input_options,
    output_option,
)


class LatticeOption(click.Option):
    """``--lattice 9`` or ``--lattice 9 7 9`` (one size for every axis, or x y z)."""

    def add_to_parser(self, parser, ctx):
        """Let the option take one or three values (click's nargs is fixed)."""
        ret = super().add_to_parser(parser, ctx)
        for name in self.opts:
            opt = parser._long_opt.get(name) or parser._short_opt.get(name)
            if opt is None:
                continue
            previous = opt.process

            def process(value, state, previous=previous):
                values = [value]
                while len(values) < 3 and state.rargs and state.rargs[0].isdigit():
                    values.append(state.rargs.pop(0))
                previous(" ".join(values), state)

            opt.process = process
        return ret


def _lattice(ctx, param, value):
    if value is None:
        return None
    try:
        sizes = [int(v) for v in str(value).replace(",", " ").split()]
    except ValueError:
        raise click.BadParameter(f"{value!r} is not one or three integers") from None
    if len(sizes) == 1:
        sizes *= 3
    if len(sizes) != 3:
        raise click.BadParameter("give one size or three (x y z)")
    if min(sizes) < 4:
        raise click.BadParameter("a lattice needs at least 4 control points per axis")
    return tuple(sizes)


def lattice_option(default="9"):
    """``--lattice``, one size or three (x y z), as a tuple of three ints."""
    return click.option("--lattice", cls=LatticeOption, default=default, callback=_lattice,
                        metavar="N | NX NY NZ", show_default=True,
                        help="Control points per axis: one count for all three, or x y z; at "
                             "least 4 each (6 with --placement tripled). N points make N-3 "
                             "regions per axis and each point moves the 4 regions around it: "
                             "more points, more local moves (9: a point reaches about 2/3 of "
                             "the volume along each axis).")


@click.command(name="capture", cls=Command, epilog=examples(
    "volwarp capture head.nrrd -o head.vwc --lattice 9 --oversample 2",
    "volwarp capture block.nrrd -o block.vwc --lattice 9 7 9 --placement tripled",
))
@click.argument("input", type=INPUT_PATH)
@output_option("Capture file to write (.vwc).", volume=False)
@lattice_option()
@click.option("--placement", type=click.Choice(["uniform", "tripled"]), default="uniform",
              show_default=True,
              help="Where the capture lattice's points go. uniform: evenly spaced, an exactly "
                   "affine capture map (thesis 5.5); with an integer --oversample every domain "
                   "voxel is a whole fraction of an input voxel, so an unmoved warp returns "
                   "the input exactly. tripled: the papers' placement (paper 7), the first and "
                   "last points tripled so that the lattice ends on the volume's faces; the "
                   "grids are not aligned and even an unmoved warp resamples.")
@click.option("--oversample", type=click.FloatRange(min=0, min_open=True, max=16),
              callback=finite,
              default=2.0, show_default=True,
              help="Domain voxels per input voxel along each axis (granularity G = "
                   "ceil(oversample * I / R) for I input voxels and R regions): more gives "
                   "smoother warps of stretched parts, at oversample^3 the memory and time. "
                   "An integer one (uniform placement) makes each domain voxel an exact "
                   "1/oversample of an input voxel, so what a warp leaves unmoved stays exact. "
                   "One that leaves fewer domain voxels than input voxels on an axis is "
                   "refused (its capture skips input voxels).")
@click.option("--pad", type=click.IntRange(min=0), default=None,
              help="Output padding in voxels per side, room for material moved past the "
                   "input's box, for later warps whose spec sets none: it asks them for a "
                   "grown grid (warp --grid grow) [default: none; a warp with --grid grow "
                   "pads by its largest displacement + 1]; material moved beyond it is cut "
                   "off. `warp --grid input` leaves it unused.")
@click.option("--sampling", type=click.Choice(["linear", "nearest"]), default="linear",
              show_default=True,
              help="How each domain voxel takes its value from the input (the pullback): "
                   "linear (trilinear interpolation) or nearest (the paper's rounding). At an "
                   "integer --oversample with the uniform placement both give each domain "
                   "voxel the value of the input voxel it lies in.")
@click.option("--values", "values", type=click.Choice(VALUES), default=None,
              help="Take the samples as intensities or as label ids. A label map (as "
                   "`volwarp info` hints, or labels given) is refused on the spanning grid "
                   "(--placement tripled, or a non-integer --oversample), which blends its "
                   "ids for good; intensity captures them as intensities on any grid. The "
                   "choice is recorded in the file (key volwarp_values): a warp of the "
                   "capture takes it, unless its own --values says otherwise.")
@input_options
@common_options
def command(input, output, lattice, placement, oversample, pad, sampling, values, raw,
            volume_index, dicom):
    """Capture INPUT into a domain voxmap file (.vwc) for `volwarp warp`.

    The capture lattice's B-spline image of the domain's model voxels is exactly
    INPUT's voxel box in world space (at an integer oversample the lattice
    spans a little more, centred on it). `volwarp info SCENE.vwc --json` lists the
    lattice's world positions (lattice_points[i][j][k]).
    """
    from ..api import capture
    from ..bspline.lattice import too_coarse
    from ..warp.capture_file import write_capture

    if not output.lower().endswith(".vwc"):
        raise click.BadParameter("a capture file must end in .vwc", param_hint="'-o'")
    check_output_path(output, option="-o")
    if placement == "tripled" and min(lattice) < 6:
        raise click.BadParameter("the tripled placement needs at least 6 points per axis",
                                 param_hint="'--lattice'")
    vol = load_input(input, raw, volume_index, dicom=dicom)
    why = too_coarse(vol.shape_xyz, lattice, oversample)
    if why is not None:
        raise click.BadParameter(why, param_hint="'--oversample'")
    cap = capture(vol, lattice=lattice, placement=placement, oversample=oversample,
                  sampling=sampling, pad=pad, name=input, values=values)
    with timed(f"write {output}"):
        write_capture(cap, output)

"""`volwarp convert IN -o OUT`: any supported volume format to any other."""

from __future__ import annotations

import click

from ..io import check_output_path, write_volume
from ..progress import timed
from .common import load_input
from .options import (
    INPUT_PATH,
    common_options,
    examples,
    input_options,
    output_option,
    write_options,
)

#: --pyramid-method: write_volume's ``labels`` for each choice
PYRAMID_METHODS = {"auto": "auto", "mode": True, "mean": False}


@click.command(name="convert", epilog=examples(
    "volwarp convert ct_series/ -o ct.nrrd --compress",
    "volwarp convert scan.raw --raw-shape 256 256 128 --raw-dtype int16 -o scan.nii.gz",
))
@click.argument("input", type=INPUT_PATH)
@output_option()
@write_options
@click.option("--pyramid-method", type=click.Choice(list(PYRAMID_METHODS)), default="auto",
              show_default=True,
              help="How --pyramid makes each level from the last, 2x2x2 voxels to one: "
                   "mode (the most frequent value: label maps, never an invented label), "
                   "mean (intensities), or auto (mode for integer volumes that are "
                   "piecewise constant, whatever their number of labels; else mean).")
@input_options
@common_options
def command(input, output, dtype, compress, byte_order, pyramid_method, raw, volume_index,
            dicom, ome_zarr):
    """Convert INPUT to OUTPUT (format by extension), keeping geometry and key/values."""
    if pyramid_method != "auto" and not ome_zarr.get("pyramid"):
        raise click.UsageError(f"--pyramid-method {pyramid_method} chooses how --pyramid "
                               "levels are made: give --pyramid N (N >= 1) with it")
    check_output_path(output, option="-o")
    vol = load_input(input, raw, volume_index, dicom=dicom)
    with timed(f"write {output}"):
        write_volume(vol, output, dtype=dtype, compress=compress, byte_order=byte_order,
                     labels=PYRAMID_METHODS[pyramid_method], **ome_zarr)

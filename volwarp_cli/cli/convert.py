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


@click.command(name="convert", epilog=examples(
    "volwarp convert ct_series/ -o ct.nrrd --compress",
    "volwarp convert scan.raw --raw-shape 256 256 128 --raw-dtype int16 -o scan.nii.gz",
))
@click.argument("input", type=INPUT_PATH)
@output_option()
@write_options
@input_options
@common_options
def command(input, output, dtype, compress, byte_order, raw, volume_index, dicom, ome_zarr):
    """Convert INPUT to OUTPUT (format by extension), keeping geometry and key/values."""
    check_output_path(output)
    vol = load_input(input, raw, volume_index, dicom=dicom)
    with timed(f"write {output}"):
        write_volume(vol, output, dtype=dtype, compress=compress, byte_order=byte_order,
                     **ome_zarr)

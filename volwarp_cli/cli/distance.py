"""`volwarp distance`: not implemented yet (its issue replaces this module)."""

import click

from ..errors import VolwarpError
from .options import common_options


@click.command(name="distance", context_settings={"ignore_unknown_options": True})
@click.argument("args", nargs=-1, type=click.UNPROCESSED)
@common_options
def command(args):
    """Not implemented yet."""
    raise VolwarpError("'distance' is not implemented yet")

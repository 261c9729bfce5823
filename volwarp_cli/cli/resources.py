"""``--threads`` and ``--memory-limit``: the resources a command may use, on every subcommand.

Each option's callback enters its setting for the rest of the command
(``ctx.with_resource``: undone when the command's context closes, so runs in
one process, as the tests' do, do not leak into each other).
"""

from __future__ import annotations

import click

from ..errors import VolwarpError


def _threads(ctx, param, value):
    from .. import parallel

    try:
        n = parallel.parse_threads(value, "--threads") if value is not None else None
    except VolwarpError as exc:
        raise click.BadParameter(str(exc), ctx=ctx, param=param) from None
    # (BLAS is held to one thread by the entry point already, and numba's and VTK's
    # counts follow the count in effect where they run: nothing more to set here)
    ctx.with_resource(parallel.use_threads(n))
    return n


def _memory_limit(ctx, param, value):
    if value is None:
        return None
    from .. import memory

    try:
        limit = memory.parse_size(value)
    except (ValueError, VolwarpError) as exc:
        raise click.BadParameter(str(exc), ctx=ctx, param=param) from None
    ctx.with_resource(memory.use_memory_limit(limit))
    return limit


def resource_options(f):
    """--threads and --memory-limit (values applied by their callbacks, not passed on)."""
    f = click.option("--memory-limit", default=None, metavar="SIZE", expose_value=False,
                     callback=_memory_limit,
                     help="Memory this command may use, e.g. 8G or 512M (default: the "
                          "lower of available memory and the cgroup's limit; also "
                          "VOLWARP_MEMORY_LIMIT). Block sizes follow it; work that "
                          "cannot fit is refused before it starts.")(f)
    f = click.option("--threads", default=None, metavar="N", expose_value=False,
                     callback=_threads,
                     help="Threads to use (default: the cores this process may use, its "
                          "CPU affinity and cgroup quota honoured; also VOLWARP_THREADS). "
                          "Results are identical for any count.")(f)
    return f

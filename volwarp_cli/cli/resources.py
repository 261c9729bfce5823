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


# -- out of core, on Dask -------------------------------------------------------------------
#: ``ctx.meta`` key of the command's :class:`ScaleSettings`
SCALE_META = "volwarp.scale"


class ScaleSettings:
    """How a command runs by blocks: ``--chunked``, ``--scheduler`` and the rest.

    ``chunked``: True (``--chunked``), False (``--no-chunked``) or None (by
    blocks only when the work cannot fit in memory).
    """

    def __init__(self):
        self.chunked: bool | None = None
        self.scheduler: str | None = None
        self.workers: int | None = None
        self.threads_per_worker: int | None = None
        self.progress: str = "auto"
        self.block: tuple[int, int, int] | None = None
        #: the options above that the command's work used (an engine uses them all)
        self.used: set[str] = set()

    def unused(self) -> list[str]:
        """The options given for work by blocks that the command's work did not use."""
        given = [("--chunked", True if self.chunked else None),
                 ("--block", self.block), ("--scheduler", self.scheduler),
                 ("--workers", self.workers), ("--threads-per-worker", self.threads_per_worker),
                 ("--progress jsonl", True if self.progress == "jsonl" else None)]
        return [name for name, value in given if value is not None and name not in self.used]

    def open_engine(self):
        """The Dask engine these settings name (:func:`volwarp_cli.engine.open_engine`)."""
        from .. import memory
        from ..engine import open_engine, parse_scheduler

        kind = parse_scheduler(self.scheduler).kind
        if self.threads_per_worker is not None and kind != "local":
            raise click.UsageError("--threads-per-worker sets a --scheduler local cluster's "
                                   "workers (the others' threads are their own)")
        if self.workers is not None and kind in ("address", "file"):
            raise click.UsageError("--workers does not apply to an existing cluster (it has "
                                   "its own workers)")
        limit = memory.memory_limit() if kind == "local" else None
        self.used |= {"--chunked", "--block", "--scheduler", "--workers",
                      "--threads-per-worker", "--progress jsonl"}
        return open_engine(self.scheduler, workers=self.workers,
                           threads_per_worker=self.threads_per_worker, memory_limit=limit,
                           progress="jsonl" if self.progress == "jsonl" else None)


def scale_settings() -> ScaleSettings:
    """The current command's :class:`ScaleSettings` (defaults outside a command)."""
    ctx = click.get_current_context(silent=True)
    if ctx is None:
        return ScaleSettings()
    return ctx.find_root().meta.setdefault(SCALE_META, ScaleSettings())


def _scale_option(*decls, convert=None, **kwargs):
    """An option of :class:`ScaleSettings`, not passed to the command.

    Its value (``convert`` run on it: a ``ValueError`` or ``VolwarpError`` is a
    usage error) goes to the setting of the option's name.
    """
    def callback(ctx, param, value):
        if value is None:
            return None
        if convert is not None:
            try:
                value = convert(value)
            except (ValueError, VolwarpError) as exc:
                raise click.BadParameter(str(exc), ctx=ctx, param=param) from None
        setattr(scale_settings(), param.name, value)
        return value

    return click.option(*decls, default=None, expose_value=False, callback=callback, **kwargs)


def _scheduler(value):
    from ..engine import parse_scheduler

    parse_scheduler(value)  # a usage error now, not after the input is read
    return value


def _block(value):
    parts = value.lower().replace("x", ",").split(",")
    try:
        sizes = [int(p) for p in parts if p.strip()]
    except ValueError:
        raise ValueError(f"expected N or Z,Y,X block sizes, got {value!r}") from None
    if len(sizes) == 1:
        sizes *= 3
    if len(sizes) != 3 or min(sizes) < 1:
        raise ValueError(f"expected N or Z,Y,X positive block sizes, got {value!r}")
    return tuple(sizes)


def scale_options(f):
    """--chunked, --block, --scheduler, --workers, --threads-per-worker and --progress.

    For the commands that can run by blocks (warp, distance, mesh, sweep, morph);
    the values go to :func:`scale_settings`, not to the command's arguments.
    """
    options = [  # (applied in this order: --help lists them from the last)
        _scale_option("--progress", type=click.Choice(["auto", "jsonl"]),
                      help="auto: a bar on a terminal; jsonl: one JSON line per block on "
                           "stderr (start, done, failed, seconds, peak memory), for logs."),
        _scale_option("--threads-per-worker", type=click.IntRange(min=1), metavar="N",
                      help="With --scheduler local: threads of each worker process "
                           "[default: 1]."),
        _scale_option("--workers", type=click.IntRange(min=1), metavar="N",
                      help="With --scheduler local: worker processes [default: the cores "
                           "this process may use]; threads or processes of the local "
                           "schedulers [default: --threads]."),
        _scale_option("--scheduler", metavar="NAME", convert=_scheduler,
                      help="Who runs the blocks (with --chunked): threads [default], "
                           "processes, synchronous, local (a Dask LocalCluster), "
                           "tcp://HOST:PORT or file:PATH (an existing Dask cluster; also "
                           "DASK_SCHEDULER_ADDRESS). The output is the same on every one."),
        _scale_option("--block", metavar="N|Z,Y,X", convert=_block,
                      help="With --chunked: the output block's size in voxels [default: "
                           "the largest the memory budget holds for the tasks run at once]; "
                           "the exact distance, whose passes need whole lines, takes Z as "
                           "its x/y passes' slab depth and Y,X as its z pass's columns."),
        _scale_option("--chunked/--no-chunked",
                      help="Run by output blocks on Dask, the input read and the output "
                           "written block by block (out of core; the output is identical). "
                           "Default: only when the work does not fit the memory budget."),
    ]
    for option in options:
        f = option(f)
    return f

"""Each step's options and spec, checked by the step's own command before any scan runs.

A typo in a step's options (``--isoo 50``) would otherwise surface once per
scan, as each scan's step process failed, after the earlier steps of every
scan had run. Here each step's command line is parsed once by the click
command that will run it (``make_context``: its options, types and
callbacks, never its body), and its spec is checked against its schema:
one usage error (exit 2) naming the manifest's key and line, before any
work. Option values are the same for every scan but for ``{stem}`` and
``{relpath}``, which only change names, so one parse per step suffices.

The parse also tells which files the step reads besides its input (its
spec, ``--points-in``, ``--transform``...): the command line declares them as
it parses (:func:`..io.inputs.declare_input`). They go into what the step's
outputs are made from (:mod:`.plan`).
"""

from __future__ import annotations

import contextvars
import dataclasses
import importlib
from pathlib import Path

import click

from .manifest import Manifest, Scan, Step

#: spec files a step's command reads, by command and parameter: the schema they follow
SPEC_PARAMS = {"warp": {"spec_path": "warp"}, "distance": {"transform": "transform"}}
#: the stand-in for a step's input while its command line is parsed (it is not read)
_STAND_IN = "volwarp-batch-step-input"


def check_steps(manifest: Manifest) -> list[Step]:
    """The manifest's steps, each checked and given the files it reads (``Step.inputs``)."""
    from .plan import plan_scan

    stand_in = Scan(id="scan", path=manifest.base / f"{_STAND_IN}.nrrd", stem="scan",
                    relpath="")
    plans = plan_scan(manifest, stand_in)
    steps = []
    for plan in plans:
        argv = list(plan.argv)
        argv[1] = str(manifest.base / f"{_STAND_IN}-{plan.step.name}")  # (not read)
        declared, params = _parse(manifest, plan.step, argv)
        _check_specs(manifest, plan.step, params)
        files = tuple(_resolve(manifest, p) for p in declared if _STAND_IN not in p)
        steps.append(dataclasses.replace(plan.step, inputs=files))
    return steps


def _resolve(manifest: Manifest, path: str) -> Path:
    """A path as the step's process sees it (it runs in the manifest's folder)."""
    p = Path(path).expanduser()
    return p if p.is_absolute() else manifest.base / p


def _parse(manifest: Manifest, step: Step, argv: list[str]) -> tuple[list[str], dict]:
    """Parse ``volwarp ARGV`` with the step's command: ``(declared inputs, params)``.

    In a run scope of its own, in a copy of this context, with the log level
    put back: the parse's side effects (``-q`` sets the level, ``--threads``
    a context variable) stay there.
    """
    from ..progress import log
    from ..runscope import run_files, run_scope

    command = importlib.import_module(f"volwarp_cli.cli.{step.run}").command
    level = log.level

    def parse():
        with run_scope():
            ctx = command.make_context(f"volwarp {step.run}", argv[1:],
                                       resilient_parsing=False)
            ctx.close()
            return list(run_files().declared), dict(ctx.params)

    try:
        return contextvars.copy_context().run(parse)
    except click.ClickException as exc:
        raise manifest.doc.error(("steps", step.index, "options"),
                                 f"{step.run}: {_one_line(exc.format_message())}") from None
    finally:
        log.setLevel(level)


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _check_specs(manifest: Manifest, step: Step, params: dict) -> None:
    """Each spec the step reads, against its schema (and a warp spec read as warp reads it)."""
    from ..spec.loader import load_spec

    for param, kind in SPEC_PARAMS.get(step.run, {}).items():
        path = params.get(param)
        if not path:
            continue
        doc = load_spec(_resolve(manifest, str(path)), kind)
        if kind == "warp":
            from ..bspline.plan import read_warp_spec

            read_warp_spec(doc)

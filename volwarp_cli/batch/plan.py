"""What each scan's steps are, concretely, and whether they are up to date (Make's habit).

A step's plan is its command line (``volwarp RUN INPUT [--spec S] -o OUT
OPTIONS -q``), its input (the scan, or an earlier step's output) and its
outputs: ``-o`` and every option value holding a placeholder (a mesh's
``--render {stem}.png``), all under the output folder.

A step is up to date when every output exists, none is older than the step's
input and spec, and, for a volume written by a command that stamps its
provenance (warp, distance), the provenance read back with volwarp's own
reader records the same input name, spec sha256, command and volwarp version.
Meshes, renders, capture files and converted volumes (convert keeps its
input's key/values) carry less: for them the modification times decide.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from .. import __version__
from .manifest import SCAN, Manifest, Scan, Step, fill, placeholders

#: the subcommands whose volume outputs carry volwarp_* provenance of their own
STAMPING = ("warp", "distance")


@dataclass
class StepPlan:
    """One step for one scan, concretely: its input, its outputs and its command line."""

    step: Step
    input: Path
    output: Path
    extra_outputs: list[Path] = field(default_factory=list)
    argv: list[str] = field(default_factory=list)  # after ``volwarp``

    @property
    def outputs(self) -> list[Path]:
        """Every file the step writes: ``-o`` first, then the placeholder option values."""
        return [self.output, *self.extra_outputs]


def output_path(manifest: Manifest, scan: Scan, pattern: str) -> Path:
    """A pattern filled for ``scan``, under the output folder.

    The scan's folder is mirrored there, unless the pattern places ``{relpath}`` itself.
    """
    filled = fill(pattern, scan)
    if "relpath" in (placeholders(pattern) or ()):
        return manifest.output_dir / filled
    return manifest.output_dir / scan.relpath / filled


def plan_scan(manifest: Manifest, scan: Scan) -> list[StepPlan]:
    """The plans of the manifest's steps for ``scan``, in step order (absolute paths)."""
    plans: dict[str, StepPlan] = {}
    for step in manifest.steps:
        source = scan.path if step.input == SCAN else plans[step.input].output
        output = output_path(manifest, scan, step.output)
        options, extra = [], []
        for value in step.options:
            if placeholders(value):
                path = output_path(manifest, scan, value)
                extra.append(path)
                options.append(str(path.absolute()))
            else:
                options.append(value)
        argv = [step.run, str(Path(source).absolute())]
        if step.spec is not None:
            argv += ["--spec", str(step.spec.absolute())]
        argv += ["-o", str(output.absolute()), *options, "-q"]
        plans[step.name] = StepPlan(step, Path(source), output, extra, argv)
    return list(plans.values())


def _mtime(path: Path) -> int | None:
    try:
        return os.stat(path).st_mtime_ns
    except OSError:
        return None


#: in the output folder: each output's command (sha256 of its argv), written as steps end
STATE_NAME = ".volwarp-batch-state.json"


def command_digest(manifest: Manifest, plan: StepPlan) -> str:
    """The step as the manifest defines it (run, input, output pattern, spec, options), hashed.

    Paths are relative to the manifest, so a tree moved elsewhere is still up to date.
    """
    import hashlib
    import json

    step = plan.step
    spec = None if step.spec is None else os.path.relpath(step.spec, manifest.base)
    text = json.dumps([step.run, step.input, step.output, spec, list(step.options)])
    return hashlib.sha256(text.encode()).hexdigest()


class CommandRecord:
    """Which command made each output (``STATE_NAME``).

    Options changed since an output was made (``--crop`` added, ``--iso 20`` to 60)
    make it stale, which neither times nor the outputs' provenance (it names the
    command, not its options) would show.
    """

    def __init__(self, manifest: Manifest):
        import json
        import threading

        self.manifest = manifest
        self.path = manifest.output_dir / STATE_NAME
        self.lock = threading.Lock()
        try:
            self.made = dict(json.loads(self.path.read_text()))
        except (OSError, ValueError, TypeError):
            self.made = {}

    def _key(self, path: Path) -> str:
        return os.path.relpath(path.absolute(), self.manifest.output_dir)

    def matches(self, plan: StepPlan) -> bool:
        """True when every output of ``plan`` was made by the step as it is defined now."""
        digest = command_digest(self.manifest, plan)
        return all(self.made.get(self._key(p)) == digest for p in plan.outputs)

    def record(self, plan: StepPlan) -> None:
        """Note that the step made the outputs of ``plan`` (the state file rewritten atomically)."""
        self.record_many([plan])

    def record_many(self, plans: list[StepPlan]) -> None:
        """Note that the steps made the outputs of ``plans`` (one rewrite of the state file)."""
        import json

        from ..io.atomic import write_bytes_atomic

        if not plans:
            return
        with self.lock:
            for plan in plans:
                for p in plan.outputs:
                    self.made[self._key(p)] = command_digest(self.manifest, plan)
            self.path.parent.mkdir(parents=True, exist_ok=True)
            write_bytes_atomic(self.path, json.dumps(self.made, sort_keys=True,
                                                     indent=1).encode())

    def snapshot(self, plans: list[StepPlan]) -> dict[str, str]:
        """The record's entries for the outputs of ``plans`` (what a cluster task needs)."""
        keys = {self._key(p) for plan in plans for p in plan.outputs}
        with self.lock:
            return {k: v for k, v in self.made.items() if k in keys}


class RecordSnapshot(CommandRecord):
    """A :class:`CommandRecord` read from a snapshot (a cluster task's), noting nothing.

    The batch process records the steps a task ran when its result arrives: one
    writer of the state file, however many workers.
    """

    def __init__(self, manifest: Manifest, made: dict[str, str]):
        import threading

        self.manifest = manifest
        self.path = manifest.output_dir / STATE_NAME
        self.lock = threading.Lock()
        self.made = dict(made)

    def record_many(self, plans: list[StepPlan]) -> None:
        """Nothing: the batch process records."""


def check_outputs(manifest: Manifest, scans: list[Scan]) -> None:
    """Refuse, before any work, an output that is a scan or that two steps both write."""
    inputs = {str(s.path.resolve()): s for s in scans}
    writers: dict[str, tuple[Scan, Step]] = {}
    for scan in scans:
        for plan in plan_scan(manifest, scan):
            key = ("steps", plan.step.index, "output")
            for out in plan.outputs:
                real = str(out.resolve())
                if real in inputs:
                    raise manifest.doc.error(key, f"{out} is the scan {inputs[real].id!r} "
                                                  "itself: an output never replaces an input")
                if real in writers:
                    other = writers[real][1]
                    raise manifest.doc.error(key, f"{out} is also written by step "
                                                  f"{other.name!r} (steps[{other.index}])")
                writers[real] = (scan, plan.step)


def stale_reason(manifest: Manifest, plan: StepPlan, record: CommandRecord | None = None
                 ) -> str | None:
    """Why ``plan``'s outputs must be (re)made, or None when they are up to date."""
    if record is not None and not record.matches(plan):
        return "its command (options) changed, or this batch did not make it"
    sources = [plan.input] + ([plan.step.spec] if plan.step.spec is not None else [])
    newest = 0
    for src in sources:
        t = _mtime(src)
        if t is None:
            return f"{src} is missing"  # the step runs, and says what is wrong
        newest = max(newest, t)
    for out in plan.outputs:
        t = _mtime(out)
        if t is None:
            return f"{out.name} is missing"
        if t < newest:
            return f"{out.name} is older than its input or spec"
    if plan.step.run in STAMPING and _is_volume(plan.output):
        return _provenance_differs(manifest, plan)
    return None


def _is_volume(path: Path) -> bool:
    from ..errors import VolwarpError
    from ..io import volume_format

    try:
        volume_format(path)
    except VolwarpError:
        return False
    return True


def _provenance_differs(manifest: Manifest, plan: StepPlan) -> str | None:
    from ..io import read_volume

    try:
        meta = read_volume(plan.output).meta
    except Exception:  # unreadable: remake it  # noqa: BLE001
        return f"{plan.output.name} cannot be read"
    spec = plan.step.spec
    want = {"volwarp_version": __version__, "volwarp_command": plan.step.run,
            "volwarp_input": plan.input.name,
            "volwarp_spec_sha256": manifest.specs[str(spec)] if spec is not None else None}
    for key, value in want.items():
        if meta.get(key) != value:
            return f"{plan.output.name}: {key} differs"
    return None

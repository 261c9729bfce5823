"""Every output of a morph: the frames' patterns expanded, checked before any work, written.

A frame pattern is a Python format string with ``{i}`` (the frame's number)
and ``{t}`` (its time); each attribute's frames go beside the frames
(``frame_003_heat.nrrd``); meshes and renders have patterns of their own, the
contact sheet and the camera one file each.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import BadUsage


def expand(pattern: str, times: list[float], option: str) -> list[str]:
    """``pattern`` for each time: the frames' names (a :class:`BadUsage` naming ``option``).

    Two frames naming one file, links followed (``'d{i}/f.nrrd'`` with each
    ``d0``, ``d1`` a link to one folder, ``'a{i}/../f.nrrd'``), are refused:
    each frame replaced the last, one file left of them, exit 0.
    """
    from ..io.inputs import note_pattern, one_file_twice

    try:
        names = [pattern.format(i=i, t=t) for i, t in enumerate(times)]
    except (KeyError, IndexError, ValueError, AttributeError) as exc:
        raise BadUsage(f"{option}: bad pattern {pattern!r} ({exc}); use {{i}} and {{t}}, "
                       "e.g. frame_{i:03d}.nrrd") from None
    twice = one_file_twice(enumerate(names))
    if twice is not None:
        raise BadUsage(f"{option}: {pattern!r} gives frames {twice[0]} and {twice[1]} the same "
                       f"file {twice[2]}; put {{i}} (or {{t}}) in the file name")

    note_pattern(pattern, option)
    return names


def attribute_name(frame_path: str, name: str) -> str:
    """The path of attribute ``name`` beside the frame ``frame_path``."""
    p = Path(frame_path)
    suffix = "".join(p.suffixes[-2:]) if p.name.endswith(".nii.gz") else p.suffix
    stem = p.name[: len(p.name) - len(suffix)] if suffix else p.name
    return str(p.with_name(f"{stem}_{name}{suffix}"))


class MorphOutputs:
    """Every output path of a morph, expanded from the patterns and checked before any work."""

    def __init__(self, job, output, mesh_to=None, render_to=None, sheet_path=None):
        from ..io import check_output_path

        self.frames = expand(output, job.times, "-o")
        self.meshes = expand(mesh_to, job.times, "--mesh-to") if mesh_to else None
        self.renders = expand(render_to, job.times, "--render-to") if render_to else None
        self.sheet = sheet_path
        self.attributes = {a.name: [attribute_name(p, a.name) for p in self.frames]
                           for a in job.attributes}
        for p in self.frames:
            check_output_path(p, option="-o")
        for paths in self.attributes.values():
            for p in paths:
                check_output_path(p, option="attributes")
        if self.meshes:
            from ..surface.mesh_io import check_mesh_output

            for p in self.meshes:
                check_mesh_output(p, option="--mesh-to")
        if self.renders:
            for p in self.renders:
                check_output_path(p, option="--render-to")
            if sheet_path:
                check_output_path(sheet_path, option="--sheet")

    def write_surface(self, frame, comments, renders: list) -> None:
        """Frame's mesh and render, as asked (the render kept for the sheet)."""
        i = frame.index
        if self.meshes:
            from ..surface.mesh_io import write_mesh

            if frame.mesh.is_empty:  # (a shape may vanish between two: said, not refused)
                from ..progress import log

                log.warning("warning: frame %d (t = %g) has no surface, the shape is empty "
                            "then: %s is an empty mesh", i, frame.t, self.meshes[i])
            write_mesh(frame.mesh, self.meshes[i], comments=comments)
        if self.renders:
            from ..io.images import write_image

            write_image(self.renders[i], frame.image)
            if self.sheet:
                renders.append(frame.image)

    def finish(self, job, frame, render, camera_to, renders: list) -> None:
        """The camera file and the contact sheet, after the last frame."""
        if camera_to is not None and render is not None:
            from ..render.camera import write_camera

            write_camera(frame.camera, camera_to, source=str(job.source.path))
        if self.sheet:
            from ..io.images import write_image
            from ..render.sheet import contact_sheet

            titles = [f"t = {t:.3g}" for t in job.times]
            write_image(self.sheet, contact_sheet(renders, titles=titles))

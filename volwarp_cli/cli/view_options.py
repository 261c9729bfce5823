"""Render options shared by the commands that make pictures (mesh, morph, sweep).

``VIEW_HELP`` is the help of ``--view``; :func:`camera_options` adds
``--camera-from``, ``--camera-to`` and ``--orientation-labels``. Nothing heavy
is imported until an option is parsed (``--help`` stays instant).
"""

from __future__ import annotations

import functools

import click

#: --view of every command that renders: one convention (see volwarp_cli.render.surface)
VIEW_HELP = (
    "Render view, looking from there at the centre. What the viewer sees, in the LPS world "
    "frame: patient-left (from +x: the patient's left side, face to the left), "
    "patient-right (from -x), anterior (from -y: the face), posterior (from +y), superior "
    "(from +z, anterior up), inferior (from -z, anterior up, patient's left on the right); "
    "superior is up in the side views. Axis names: x, y, z (from +x, +y, +z), iso (from the "
    "(1,1,1) diagonal), front (= anterior), back (= posterior), right (from +x: the "
    "patient's LEFT side), left (from -x), top (= z, posterior up), bottom (= inferior). "
    "Or AZIMUTH,ELEVATION in degrees (azimuth from +x towards +y, elevation towards +z; "
    "z up).")

CAMERA_FROM_HELP = (
    "Use the camera in FILE (written by --camera-to: JSON with position, focal point, view "
    "up, parallel scale and picture size, in LPS world coordinates) instead of fitting one "
    "to this object, so that before/after pictures compare pixel for pixel. It fixes the "
    "view (no --view) and the picture size; a --render-size given keeps the camera's view and its "
    "height in world units.")

CAMERA_TO_HELP = ("Write the camera of this render to FILE (JSON, for --camera-from; pyvista "
                  "and ParaView, in parallel projection, set the same camera from its position, "
                  "focal_point, view_up and parallel_scale).")

ORIENTATION_LABELS_HELP = (
    "Write the anatomical direction at each edge of the picture (L/R, A/P, S/I of the LPS "
    "world frame; two or three letters, e.g. LP, for oblique views). Default: on when the "
    "rendered volume was read from a file with a patient frame (DICOM, NIfTI, MetaImage, "
    "a NRRD with an anatomical space), off for volumes without one (TIFF, raw, a NRRD "
    "without space) and for sweeps' generated volumes.")


def _read_camera(path):
    """--camera-from: :func:`volwarp_cli.render.camera.read_camera`, imported when first used.

    A malformed or unreadable file is a usage error (exit 2: :func:`.options.core_parser`).
    """
    from ..render.camera import read_camera

    return read_camera(path)


def option_given(ctx, name: str) -> bool:
    """Whether option ``name`` of the running command was set by the user (not its default)."""
    if ctx is None or name not in ctx.params:
        return False
    from .options import RENAMED_GIVEN  # (options imports this module)

    if name in ctx.meta.get(RENAMED_GIVEN, ()):  # (by its old spelling: --size, --background)
        return True
    source = ctx.get_parameter_source(name)
    return source in (click.core.ParameterSource.COMMANDLINE,
                      click.core.ParameterSource.ENVIRONMENT)


#: the options that shape a rendered picture (those a command has)
PICTURE_OPTIONS = ("view", "render_size", "size", "color", "background_color")


def refuse_picture_options_without(render, flag: str) -> None:
    """A usage error where options of the picture were given but no picture (``flag``).

    (mesh, morph and sweep took --view, --render-size and the colours without
    their --render and did nothing with them.)
    """
    if render is not None:
        return
    ctx = click.get_current_context(silent=True)
    given = [f"--{n.replace('_', '-')}" for n in PICTURE_OPTIONS if option_given(ctx, n)]
    if given:
        raise click.UsageError(f"{', '.join(given)} shape{'s' if len(given) == 1 else ''} "
                               f"the picture: give {flag}")


#: names of a command's picture-size parameter (--render-size; the old --size)
_SIZE_PARAMS = ("size", "render_size")


def camera_options(f):
    """``--camera-from FILE``, ``--camera-to FILE`` and ``--orientation-labels/--no-...``.

    The command receives, as keyword arguments:

    * ``camera_from``: a :class:`volwarp_cli.render.camera.Camera` read and
      validated from the file (a malformed file is a usage error, exit 2), or
      None. When the command's ``--size``/``--render-size`` was given too, the
      camera is already resized to it (same view and world height). Giving
      ``--view`` with it is a usage error.
    * ``camera_to``: the path to write the camera used to (its folder checked
      before any work), or None. Write it with
      :func:`volwarp_cli.render.camera.write_camera` (atomic).
    * ``orientation_labels``: True or False when given, None when not: resolve
      it with :func:`orientation_labels_for` once the input volume is known.
    """
    from .options import InputPath, core_parser  # (options imports this module)

    @functools.wraps(f)
    def wrapper(*args, camera_from, camera_to, orientation_labels, **kwargs):
        ctx = click.get_current_context(silent=True)
        if camera_from is not None:
            if option_given(ctx, "view"):
                raise click.UsageError("--view and --camera-from exclude each other: the "
                                       "camera file fixes the view")
            for name in _SIZE_PARAMS:
                if option_given(ctx, name) and kwargs.get(name) is not None:
                    camera_from = camera_from.resized(kwargs[name])
        if camera_to is not None:
            from ..io.atomic import check_output_path

            # a missing or read-only folder, or an input: before any work
            check_output_path(camera_to, option="--camera-to")
        return f(*args, camera_from=camera_from, camera_to=camera_to,
                 orientation_labels=orientation_labels, **kwargs)

    opts = [
        click.option("--camera-from", "camera_from", type=InputPath(dir_okay=False, once=True),
                     default=None, metavar="FILE", callback=core_parser(_read_camera),
                     help=CAMERA_FROM_HELP),
        click.option("--camera-to", "camera_to", type=click.Path(dir_okay=False), default=None,
                     metavar="FILE", help=CAMERA_TO_HELP),
        click.option("--orientation-labels/--no-orientation-labels", "orientation_labels",
                     default=None, help=ORIENTATION_LABELS_HELP),
    ]
    for opt in reversed(opts):
        wrapper = opt(wrapper)
    return wrapper


def orientation_labels_for(flag: bool | None, *volumes) -> bool:
    """The ``--orientation-labels`` choice for a render of ``volumes``.

    ``flag`` when the user gave one; else True when there are volumes and every
    one was read with a patient frame
    (:func:`volwarp_cli.render.orientation.has_anatomical_frame`). LPS is the
    world frame of every volume, so the letters are never wrong; they are left
    off by default only where they would name the axes of something that is no
    patient (a TIFF stack, a sweep's object).
    """
    if flag is not None:
        return bool(flag)
    from ..render.orientation import has_anatomical_frame

    return bool(volumes) and all(has_anatomical_frame(v) for v in volumes)

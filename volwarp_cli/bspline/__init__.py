"""True & Hughes B-spline volume warping: the papers' core (capture, lattice, warp state).

What the papers define, arrays in and arrays out; the warp as a command's job
(its inputs and outputs, labels, frames, exports, the ``.vwc`` file) is
:mod:`volwarp_cli.warp`. Modules, one idea each:

- :mod:`.lattice`: control lattice sizes, granularity, capture placements.
- :mod:`.basis`: the cubic B-spline basis, the papers' coefficient table
  evaluator (eq. 3/4) and the separable three-pass evaluator (dense, per voxel).
- :mod:`.evaluate`: the lattice's map at scattered parameters (value,
  Jacobian, a point's 64 weights): handles, moved points and fields.
- :mod:`.pullback`: capture, sampling the source through the capture map
  (whole, or any box of domain voxels).
- :mod:`.capture`: a captured volume (its domain, lattice, range, border).
- :mod:`.pushforward`: the scatter into the target (nearest and box filter)
  and the finalize.
- :mod:`.jobs`: typed calls into the compiled kernels; ``_warpkernels.c``:
  the pullback, separable evaluator, scatter and finalize loops, compiled at
  install (a warp is one short command: numba's start-up would be half of it).
- :mod:`.reach`: where the write map can send domain voxels, from the
  lattice alone (regions, planes, a stream's ring of target planes).
- :mod:`.work`: what a scatter costs, and the choices made from it.
- :mod:`.scene`: the warp state with exact local updates.
- :mod:`.handles`: the inverse problem (Newton inverse, least-norm solve).
- :mod:`.plan`: a warp spec turned into a sequence of lattice changes.

References
----------
T. J. True and J. F. Hughes, "Volume Warping", Proc. IEEE Visualization 1992.
T. J. True, "Volume Warping: A New Technique for Modeling with Volumetric Data",
Master's thesis CS-92-M11, Brown University, 1992.
"""

"""True & Hughes B-spline volume warping (capture and warp).

Modules, one idea each:

- :mod:`.lattice`: control lattice sizes, granularity, capture placements.
- :mod:`.basis`: the cubic B-spline basis, the papers' coefficient table
  evaluator (eq. 3/4) and the separable three-pass evaluator.
- :mod:`.pullback`: capture, sampling the source through the capture map.
- :mod:`.pushforward`: the scatter into the target (nearest and box filter).
- ``_warpkernels.c``: the pullback, separable evaluator, scatter and finalize
  loops, compiled at install (a warp is one short command: numba's start-up
  would be half of it).
- :mod:`.scene`: the warp state with exact local updates.
- :mod:`.handles`: the inverse problem (Newton inverse, least-norm solve).
- :mod:`.plan`: a warp spec turned into a sequence of lattice changes.
- :mod:`.capture_file`: the versioned ``.vwc`` capture file.

References
----------
T. J. True and J. F. Hughes, "Volume Warping", Proc. IEEE Visualization 1992.
T. J. True, "Volume Warping: A New Technique for Modeling with Volumetric Data",
Master's thesis CS-92-M11, Brown University, 1992.
"""

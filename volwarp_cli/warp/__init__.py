"""``volwarp warp`` as a job: the papers' warp (:mod:`volwarp_cli.bspline`) on files.

Modules, one idea each:

- :mod:`.request`: the command without click (files in, files out, the
  ``--json`` summary); how the work runs is the executor's
  (:mod:`volwarp_cli.execute`).
- :mod:`.run`: the warp of an input (intensities, a label map's labels,
  the lattice moves alone for exports) and its frames.
- :mod:`.prepare`: the spec checked against a capture, the frames planned,
  the scene built; the frames computed incrementally; a target as the
  output Volume.
- :mod:`.blocks`: the one-shot warp as an operation of the executor (any
  block of the output; the in-memory warp is its one-block case).
- :mod:`.labels`: a label map's warp (each output voxel the label of
  largest weight); :mod:`.label_blocks`: its one-shot warp, whole or by
  slabs of target planes, and its operation.
- :mod:`.defaults`: what a warp does where its user says nothing (values,
  grid, background).
- :mod:`.export`: the deformation as fields, Jacobian, ITK transform, moved
  points and meshes; ``_export_kernels``: the field inverse's compiled loop;
  :mod:`.export_outputs`: those written beside a warp's output.
- :mod:`.capture_file`: the versioned ``.vwc`` capture file.
"""

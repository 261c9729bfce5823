"""The ``volwarp`` command line (``main.py``: the group; one module per subcommand)."""

import os

# volwarp's kernels share the cores with their own threads and make no large
# dense matrix products; OpenBLAS's threads (woken by the small products of
# the spline bases) only spin beside them, about 5% of a warp's CPU. A user's
# own setting wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

"""A volwarp command's peak memory, measured from outside: a fresh process's high-water RSS.

(Measured in a wrapper process of its own: ``ru_maxrss`` of a child forked from the big
test process would count the test's pages.)
"""

from __future__ import annotations

import os
import subprocess
import sys

_WRAPPER = """\
import resource, subprocess, sys
proc = subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                      text=True)
sys.stderr.write(proc.stderr)
print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024)
raise SystemExit(proc.returncode)
"""


def volwarp_peak(*args, timeout: int = 300) -> tuple[int, str, int]:
    """Run ``volwarp *args`` as a fresh process: its exit code, its stderr, its peak bytes.

    Run without a ``VOLWARP_MEMORY_LIMIT`` of the caller's (the test's own limits only).
    """
    from volwarp_cli.memory import MEMORY_ENV

    env = {k: v for k, v in os.environ.items() if k != MEMORY_ENV}
    res = subprocess.run([sys.executable, "-c", _WRAPPER, sys.executable, "-m", "volwarp_cli",
                          *map(str, args)], capture_output=True, text=True, timeout=timeout,
                         env=env)
    return res.returncode, res.stderr, int(res.stdout.split()[-1])

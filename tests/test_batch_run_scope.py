"""A batch's scans run in the batch's own run scope, not the process's.

The scans of the local pool run in threads; what they check an output
against (the inputs this run read, :mod:`volwarp_cli.runscope`) must be the
batch run's. The process-wide record outside any run gathers what any other
code of the process read, and a file it names may since have been deleted
and its inode given to the batch's own state.json: a scan then failed with
"state.json would overwrite a file this command read as an input" (seen in
the suite, where many commands run in one process).
"""

from __future__ import annotations

import os

import numpy as np

from volwarp_cli import runscope
from volwarp_cli.io import write_volume
from volwarp_cli.volume import Volume


def test_a_stale_inode_in_the_process_record_does_not_stop_the_batch(run, tmp_path,
                                                                      monkeypatch):
    write_volume(Volume(np.arange(4 * 5 * 6, dtype=np.int16).reshape(4, 5, 6)),
                 tmp_path / "a.nrrd")
    (tmp_path / "m.yaml").write_text(
        "version: 1\ninputs: {glob: '*.nrrd'}\noutput_dir: out\nsteps:\n"
        "  - name: c\n    run: convert\n    output: '{stem}.nii'\n")
    assert run("batch", tmp_path / "m.yaml", "-q").code == 0
    state = tmp_path / "out" / ".volwarp-batch" / "state.json"
    st = os.stat(state)
    # what other code of the process read: a file whose inode state.json has now
    from volwarp_cli.batch import plan

    monkeypatch.setattr(plan, "FLUSH_SECONDS", 0.0)  # (the scans' threads write it, each time)
    monkeypatch.setattr(runscope, "_process", runscope.RunFiles())
    runscope._process.inputs.add((st.st_dev, st.st_ino))
    (tmp_path / "b.nrrd").write_bytes((tmp_path / "a.nrrd").read_bytes())  # a new scan
    res = run("batch", tmp_path / "m.yaml", "-q")
    assert res.code == 0, res.stderr
    assert (tmp_path / "out" / "b.nii").is_file()

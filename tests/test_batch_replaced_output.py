"""A step's output replaced by another writer before the batch records it is not recorded.

A review ran two batches whose output folders nest (``out`` and ``out/sub``)
over the same file: the batch hashed whatever was at the output's path once
its step ended, so one batch's record claimed the other's bytes, and its next
run skipped a wrong output. Each step now notes the identity of every output it
renames into place (:func:`volwarp_cli.io.atomic.note_committed`), and the
batch records an output only while that file is still there.
"""

from __future__ import annotations

from pathlib import Path

from test_batch import CONVERT_MANIFEST, make_tree, scan_volume

from volwarp_cli.batch.manifest import find_scans, load_manifest
from volwarp_cli.io import read_volume, write_volume


def _run(manifest, force=False):
    from volwarp_cli.batch.run import Batch

    scans = find_scans(manifest)[:1]
    (result,), stop = Batch(manifest, scans, jobs=1, force=force).run()
    assert stop is None
    return result


def test_an_output_replaced_after_its_step_is_not_recorded_and_is_made_again(
        tmp_path, monkeypatch):
    from volwarp_cli.batch.run import ScanRunner

    manifest = load_manifest(make_tree(tmp_path, CONVERT_MANIFEST))
    real = ScanRunner._call
    intruder = scan_volume(3)

    def then_another_writer(self, argv):
        result = real(self, argv)
        if argv[0] == "convert":  # (another batch's step writes the same file just after)
            write_volume(intruder, Path(argv[argv.index("-o") + 1]))
        return result

    monkeypatch.setattr(ScanRunner, "_call", then_another_writer)
    result = _run(manifest)
    conv = result.steps[0]
    assert conv.status == "failed" and conv.made is None
    assert "was replaced by another writer after this step made it" in conv.error
    out = Path(conv.outputs[0])
    assert (read_volume(out).data == intruder.data).all()  # (the intruder's: not vouched for)
    # the next run does not skip it: it is made again, and recorded
    monkeypatch.setattr(ScanRunner, "_call", real)
    again = _run(manifest)
    assert again.steps[0].status == "ok" and again.steps[0].reason is not None
    assert (read_volume(out).data == read_volume(find_scans(manifest)[0].path).data).all()
    assert _run(manifest).steps[0].status == "skipped"


def test_a_step_notes_the_identity_of_each_output_it_renames(tmp_path, monkeypatch):
    """The outputs the step renamed are noted, and unreplaced they are recorded (no false
    alarm): a plain run records every step."""
    manifest = load_manifest(make_tree(tmp_path, CONVERT_MANIFEST))
    result = _run(manifest)
    assert [s.status for s in result.steps] == ["ok", "ok"]
    assert all(s.made for s in result.steps)
    from volwarp_cli.batch.run import ScanRunner

    seen = {}
    real = ScanRunner._call

    def spy(self, argv):
        out = real(self, argv)
        seen[argv[0]] = out[3]
        return out

    monkeypatch.setattr(ScanRunner, "_call", spy)
    _run(manifest, force=True)
    for step in result.steps:
        (path,) = step.outputs
        assert str(Path(path).absolute()) in seen[step.command[1]], seen


def test_a_log_that_cannot_be_written_never_fails_the_command(tmp_path, monkeypatch):
    """The batch's log of renamed outputs is its own business: unwritable, the command's
    output is still written (and the batch records it as it did before)."""
    from volwarp_cli.io import atomic
    from volwarp_cli.runscope import run_scope
    from volwarp_cli.volume import Volume

    monkeypatch.setenv(atomic.COMMITTED_LOG, str(tmp_path / "no" / "such" / "folder.jsonl"))
    out = tmp_path / "o.nrrd"
    with run_scope():  # (each its own command: the first's read is no input of the second)
        write_volume(Volume(scan_volume(0).data), out)
        assert (read_volume(out).data == scan_volume(0).data).all()
    log = tmp_path / "log.jsonl"
    monkeypatch.setenv(atomic.COMMITTED_LOG, str(log))
    with run_scope():
        write_volume(Volume(scan_volume(1).data), out)
    import json
    import os

    (line,) = log.read_text().splitlines()
    noted = json.loads(line)
    st = os.stat(out)
    assert noted == {"path": str(out.absolute()),
                     "identity": [st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns]}


def test_a_detached_headers_data_file_replaced_after_its_step_is_not_recorded(
        tmp_path, monkeypatch):
    """The data file of a `.nhdr` output replaced (same size, other bytes) between the
    step's rename and the record: the header alone was checked, so the record vouched for
    the other writer's samples and the next run skipped them."""
    import os

    from volwarp_cli.batch.run import ScanRunner

    manifest = load_manifest(make_tree(tmp_path, CONVERT_MANIFEST.replace(
        '"{stem}.nrrd"', '"{stem}.nhdr"')))
    real = ScanRunner._call

    def then_another_writer(self, argv):
        result = real(self, argv)
        if argv[0] == "convert":
            raw = Path(argv[argv.index("-o") + 1]).with_suffix(".raw")
            foreign = raw.with_name(".foreign")
            foreign.write_bytes(b"\0" * raw.stat().st_size)
            os.replace(foreign, raw)
        return result

    monkeypatch.setattr(ScanRunner, "_call", then_another_writer)
    conv = _run(manifest).steps[0]
    assert conv.status == "failed" and conv.made is None
    assert ".raw was replaced by another writer" in conv.error
    monkeypatch.setattr(ScanRunner, "_call", real)
    again = _run(manifest).steps[0]
    assert again.status == "ok"
    out = Path(again.outputs[0])
    assert (read_volume(out).data == read_volume(find_scans(manifest)[0].path).data).all()

"""`volwarp batch` decides "up to date" by content, and refuses what is wrong before any work.

Dates decide nothing: a scan replaced by one with an older modification time
(``cp -p``, ``rsync -a``) is redone, a touched one is not. A typo in a step's
options, an output over an input, a read-only output folder: one error, before
any step runs.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from volwarp_cli.batch.lock import BOOK_DIR
from volwarp_cli.io import write_volume

sys.path.insert(0, str(Path(__file__).parent))
from test_batch import WARP_SPEC, scan_volume, summary, volwarp  # noqa: E402

#: two steps: a scan's conversion, then a conversion of that (a chain, with an option)
MANIFEST = """version: 1
inputs: {glob: "scans/**/*.n*"}
output_dir: out
steps:
  - {name: conv, run: convert, output: "{stem}.nrrd"}
  - {name: wide, run: convert, input: conv, output: "{stem}_f.nrrd", options: ["--dtype", "float32"]}
"""
SCANS = ("site-a/p01.nrrd", "site-b/p02.nhdr")  # an attached and a detached header


def make_tree(root: Path, manifest: str = MANIFEST) -> Path:
    for seed, rel in enumerate(SCANS):
        (root / "scans" / rel).parent.mkdir(parents=True, exist_ok=True)
        write_volume(scan_volume(seed), root / "scans" / rel)
    (root / "warp.yaml").write_text(WARP_SPEC)
    (root / "manifest.yaml").write_text(manifest)
    return root / "manifest.yaml"


def outputs(root: Path) -> dict[str, tuple[int, bytes]]:
    """Every output (not the batch's own files): its mtime and bytes."""
    return {str(p.relative_to(root / "out")): (p.stat().st_mtime_ns, p.read_bytes())
            for p in sorted((root / "out").rglob("*"))
            if p.is_file() and BOOK_DIR not in p.parts}


def statuses(report: Path) -> dict[str, list[str]]:
    return {s["scan"]: [t["status"] for t in s["steps"]]
            for s in json.loads(report.read_text())["scans"]}


def backdate(path: Path, seconds: float = 86400) -> None:
    """Give ``path`` a modification time a day older than it had (as cp -p of an old file)."""
    st = path.stat()
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns - int(seconds * 1e9)))


@pytest.fixture(scope="module")
def done(tmp_path_factory):
    """A tree whose batch has run once."""
    root = tmp_path_factory.mktemp("content")
    res = volwarp("batch", make_tree(root), "-j", 2)
    assert res.returncode == 0, res.stderr
    return root


@pytest.fixture
def tree(done, tmp_path):
    root = tmp_path / "tree"
    shutil.copytree(done, root)  # (keeps modification times; the record is relative)
    return root


def test_replaced_scan_with_an_older_date_is_redone(tree, tmp_path):
    """cp -p of another scan over p01 (same size, same inode, older date): redone."""
    scan = tree / "scans" / "site-a" / "p01.nrrd"
    other = tmp_path / "other.nrrd"
    write_volume(scan_volume(3), other)
    assert other.stat().st_size == scan.stat().st_size and other.read_bytes() != scan.read_bytes()
    before = outputs(tree)
    oldest = min(t for t, _ in before.values())
    shutil.copyfile(other, scan)  # in place, as cp -p does
    os.utime(scan, ns=(oldest - 10**9, oldest - 10**9))
    res = volwarp("batch", tree / "manifest.yaml", "--report-json", tree / "r.json")
    assert res.returncode == 0, res.stderr
    assert summary(res) == "volwarp batch: 2 scans, 1 ok, 1 skipped, 0 failed"
    assert statuses(tree / "r.json") == {"site-a/p01": ["ok", "ok"],
                                         "site-b/p02": ["skipped", "skipped"]}
    direct = tmp_path / "p01.nrrd"
    assert volwarp("convert", scan, "-o", direct).returncode == 0
    assert (tree / "out" / "site-a" / "p01.nrrd").read_bytes() == direct.read_bytes()
    wide = tmp_path / "p01_f.nrrd"
    assert volwarp("convert", direct, "-o", wide, "--dtype", "float32").returncode == 0
    assert (tree / "out" / "site-a" / "p01_f.nrrd").read_bytes() == wide.read_bytes()
    after = outputs(tree)
    assert {k: v for k, v in after.items() if "site-b" in k} == {
        k: v for k, v in before.items() if "site-b" in k}


def test_renamed_into_place_and_detached_data_file_are_redone(tree, tmp_path):
    """rsync -a's way (a new file renamed over the scan, older date), and a header's data file."""
    scan = tree / "scans" / "site-a" / "p01.nrrd"
    write_volume(scan_volume(4), tmp_path / "new.nrrd")
    backdate(tmp_path / "new.nrrd")
    os.replace(tmp_path / "new.nrrd", scan)
    data = tree / "scans" / "site-b" / "p02.raw"  # only the data file changes, not its header
    raw = bytearray(data.read_bytes())
    raw[:2] = bytes([raw[0] ^ 0xFF, raw[1]])
    data.write_bytes(bytes(raw))
    backdate(data)
    res = volwarp("batch", tree / "manifest.yaml", "--report-json", tree / "r.json")
    assert summary(res) == "volwarp batch: 2 scans, 2 ok, 0 skipped, 0 failed", res.stderr
    reasons = {s["scan"]: s["steps"][0]["reason"]
               for s in json.loads((tree / "r.json").read_text())["scans"]}
    assert reasons == {"site-a/p01": "p01.nrrd changed", "site-b/p02": "p02.nhdr changed"}
    direct = tmp_path / "p02.nrrd"
    assert volwarp("convert", tree / "scans" / "site-b" / "p02.nhdr", "-o",
                   direct).returncode == 0
    assert (tree / "out" / "site-b" / "p02.nrrd").read_bytes() == direct.read_bytes()


def test_touched_unchanged_scan_and_spec_are_skipped(tree):
    """A newer date with the same bytes (touch, a restore, a copy without -p): no work."""
    before = outputs(tree)
    for path in (tree / "scans" / "site-a" / "p01.nrrd", tree / "scans" / "site-b" / "p02.raw",
                 tree / "manifest.yaml"):
        os.utime(path)
    # (the manifest named relative to the working folder, through a folder)
    res = volwarp("batch", Path(tree.name) / "manifest.yaml", cwd=tree.parent)
    assert summary(res) == "volwarp batch: 2 scans, 0 ok, 2 skipped, 0 failed", res.stderr
    assert outputs(tree) == before


def test_changed_option_or_spec_redoes(tmp_path):
    """A step's options and a spec's bytes are what the outputs are made from; dates are not."""
    manifest = make_tree(tmp_path, MANIFEST + (
        '  - {name: warped, run: warp, spec: warp.yaml, output: "{stem}_w.nrrd"}\n'))
    first = volwarp("batch", manifest, "-j", 2)
    assert first.returncode == 0, first.stderr
    # an option changed: that step alone (and what reads it) runs again
    manifest.write_text(manifest.read_text().replace('"float32"', '"float64"'))
    res = volwarp("batch", manifest, "--report-json", tmp_path / "r.json")
    assert res.returncode == 0, res.stderr
    assert list(statuses(tmp_path / "r.json").values()) == [["skipped", "ok", "skipped"]] * 2
    # the spec's bytes changed, its date made older than every output: the warps run again
    spec = tmp_path / "warp.yaml"
    spec.write_text(WARP_SPEC.replace("[1.0, 0.5, 0.0]", "[1.5, 0.5, 0.0]"))
    backdate(spec)
    res = volwarp("batch", manifest, "--report-json", tmp_path / "r.json")
    assert res.returncode == 0, res.stderr
    assert list(statuses(tmp_path / "r.json").values()) == [["skipped", "skipped", "ok"]] * 2
    scans = json.loads((tmp_path / "r.json").read_text())["scans"]
    assert {s["steps"][2]["reason"] for s in scans} == {"warp.yaml changed"}


def _one_error_line(res) -> str:
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("volwarp: error: "), res.stderr
    return lines[0]


@pytest.mark.parametrize("bad, message", [
    ('["--dtyp", "float32"]', r"convert: No such option '--dtyp'"),
    ('["--dtype", "float33"]', r"convert: Invalid value for '--dtype'"),
])
def test_option_typo_is_one_usage_error_before_any_work(tmp_path, bad, message):
    """Today each scan's step failed on its own, after every scan's first step had run."""
    manifest = make_tree(tmp_path, MANIFEST.replace('["--dtype", "float32"]', bad))
    res = volwarp("batch", manifest)
    assert res.returncode == 2, res.stderr
    line = _one_error_line(res)
    assert re.search(r"manifest\.yaml:6: steps\[1\]\.options: " + message, line), line
    assert not (tmp_path / "out").exists()


def test_bad_spec_is_one_spec_error_before_any_work(tmp_path):
    manifest = make_tree(tmp_path, MANIFEST.replace(
        '{name: conv, run: convert,', '{name: conv, run: warp, spec: warp.yaml,'))
    (tmp_path / "warp.yaml").write_text(WARP_SPEC.replace("steps:", "stepz:"))
    res = volwarp("batch", manifest)
    assert res.returncode == 2, res.stderr
    assert re.search(r"warp\.yaml:\d+: stepz: unknown key 'stepz'", _one_error_line(res))
    assert not (tmp_path / "out").exists()


def test_output_over_an_input_is_refused_before_any_work(tmp_path):
    """An output that is a detached header's data file, or a link to a scan: exit 2, no work."""
    over_data = MANIFEST.replace(
        'glob: "scans/**/*.n*"', "list: [scans/site-a/p01.nrrd, scans/site-b/p02.nhdr], "
                                 "root: scans").replace("output_dir: out", "output_dir: scans"
        ).replace('"{stem}.nrrd"', '"{stem}_c.nrrd"').replace(
        '"{stem}_f.nrrd"', '"{stem}.raw"')  # scans/site-b/p02.raw: p02.nhdr's data file
    res = volwarp("batch", make_tree(tmp_path, over_data))
    assert res.returncode == 2, res.stderr
    line = _one_error_line(res)
    assert re.search(r"manifest\.yaml:6: steps\[1\]\.output: scan site-b/p02: -o \S+/p02\.raw "
                     r"would overwrite the data file \S+/p02\.raw of the input \S+/p02\.nhdr",
                     line), line
    assert sorted(p.name for p in (tmp_path / "scans").rglob("*")
                  if p.is_file()) == ["p01.nrrd", "p02.nhdr", "p02.raw"]
    # through a symbolic link in the output folder
    (tmp_path / "manifest.yaml").write_text(MANIFEST)
    (tmp_path / "out" / "site-b").mkdir(parents=True)
    (tmp_path / "out" / "site-b" / "p02_f.nrrd").symlink_to(tmp_path / "scans" / "site-b"
                                                           / "p02.raw")
    res = volwarp("batch", tmp_path / "manifest.yaml")
    assert res.returncode == 2, res.stderr
    assert "links followed" in _one_error_line(res) and "p02.raw" in res.stderr
    assert sorted(p.name for p in (tmp_path / "out").rglob("*")) == ["p02_f.nrrd", "site-b"]


@contextlib.contextmanager
def read_only(folder: Path):
    """``folder`` made unwritable, for root too (chattr +i), and made writable again."""
    folder.chmod(0o555)
    immutable = os.geteuid() == 0
    if immutable and subprocess.run(["chattr", "+i", str(folder)],
                                    capture_output=True).returncode != 0:
        folder.chmod(0o755)
        pytest.skip("running as root without chattr +i: no read-only folder")
    try:
        yield
    finally:
        if immutable:
            subprocess.run(["chattr", "-i", str(folder)], check=True)
        folder.chmod(0o755)


def test_read_only_output_folder_fails_once_up_front(tmp_path):
    manifest = make_tree(tmp_path)
    (tmp_path / "out").mkdir()
    with read_only(tmp_path / "out"):
        res = volwarp("batch", manifest)
    assert res.returncode == 1, res.stderr
    line = _one_error_line(res)
    assert re.search(r"out: cannot write in the output folder \(.*\); nothing was run$", line)
    assert not list((tmp_path / "out").iterdir())


def test_a_file_rewritten_this_run_is_hashed_once_though_its_saved_entry_is_old(tmp_path):
    """A step's output the last run recorded, rewritten by this run's step: hashed when the
    step's record is made (a racy entry: just written), and not again when the next step
    reads it (the saved entry, out of date, was looked at alone)."""
    from volwarp_cli.batch.content import FileHashes, file_sha256, stat_key

    path = tmp_path / "out.nrrd"
    path.write_bytes(b"last run's output")
    saved = [*stat_key(os.stat(path)), file_sha256(path)]
    path.write_bytes(b"this run's output, longer")
    hashes = FileHashes({str(path): saved})
    first = hashes.sha256(path)
    assert first == file_sha256(path) and hashes.hashed_bytes == path.stat().st_size
    assert hashes.sha256(path) == first
    assert hashes.hashed_bytes == path.stat().st_size  # (not hashed again)


def test_on_a_filesystem_without_change_times_the_cache_is_not_trusted(tmp_path, monkeypatch):
    """FAT and exFAT report the modification time as ctime: a scan rewritten in place
    (same inode) with ``cp -p`` keeping its size and time kept every field of its stat key,
    and the saved digest of its old bytes was taken for the new ones."""
    from volwarp_cli.batch import content

    def fat_key(st):  # (what FAT reports: ctime follows mtime, which cp -p sets back)
        return [st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_mtime_ns]

    monkeypatch.setattr(content, "stat_key", fat_key)
    path = tmp_path / "scan.nrrd"
    path.write_bytes(b"the scan, first export")
    old = os.stat(path)
    saved = [*fat_key(old), content.file_sha256(path)]
    with open(path, "r+b") as fh:  # (rewritten in place, the same size)
        fh.write(b"THE SCAN")
    os.utime(path, ns=(old.st_atime_ns, old.st_mtime_ns))
    assert fat_key(os.stat(path)) == saved[:-1]
    monkeypatch.setattr(content, "_change_time_kept", {}, raising=False)
    monkeypatch.setattr(content, "filesystem_type", lambda dev: "vfat", raising=False)
    assert content.FileHashes({str(path): saved}).sha256(path) == content.file_sha256(path)
    monkeypatch.setattr(content, "_change_time_kept", {})
    monkeypatch.setattr(content, "filesystem_type", lambda dev: "ext4")  # (a real ctime)
    assert content.FileHashes({str(path): saved}).sha256(path) == saved[-1]


def test_the_filesystem_type_is_the_mount_of_the_device(tmp_path):
    """Read from the mount table by ``major:minor``: the device of a file of this tree
    is found, with the type ``df``'s mount table gives it."""
    from volwarp_cli.batch.content import filesystem_type

    dev = os.stat(tmp_path).st_dev
    table = tmp_path / "mountinfo"
    table.write_text(f"36 25 {os.major(dev)}:{os.minor(dev)} / /media/usb rw,relatime - exfat "
                     "/dev/sdb1 rw\n"
                     "37 25 250:3 / /mnt rw - ext4 /dev/sdc1 rw\n")
    assert filesystem_type(dev, str(table)) == "exfat"
    assert filesystem_type(os.makedev(250, 4), str(table)) is None
    assert filesystem_type(dev) is not None  # (this machine's own table names it)

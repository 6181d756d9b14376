"""The output folder: refused when it holds another run, cleaned exactly with
--overwrite (a user's own files stay), and checked before any slow step."""

import json
import os

import pytest

from rvggt_jax.app.outdir import MANIFEST_NAME, Manifest, OutputDirError, prepare_output


def _fake_run(out, names):
    m = Manifest(out)
    for n in names:
        p = out / n
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(n)
    return m.write()


def test_new_folder_is_created_and_manifest_lists_written_files(tmp_path):
    out = tmp_path / "a" / "b"
    assert prepare_output(out) == 0 and out.is_dir()
    files = _fake_run(out, ["points.ply", "depth/x.png"])
    assert files == ["depth/x.png", "points.ply"]
    assert json.loads((out / MANIFEST_NAME).read_text())["files"] == files


def test_non_empty_refused_without_overwrite(tmp_path):
    out = tmp_path / "out"
    prepare_output(out)
    _fake_run(out, ["points.ply"])
    with pytest.raises(OutputDirError, match="not empty.*--overwrite"):
        prepare_output(out)
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("x")
    with pytest.raises(OutputDirError, match="not empty"):
        prepare_output(tmp_path / "mine")


def test_overwrite_removes_only_the_previous_run(tmp_path):
    out = tmp_path / "out"
    prepare_output(out)
    _fake_run(out, ["depth/f0.png", "depth/f1.png", "depth/f2.png", "depth/depth_scale.json", "points.ply"])
    (out / "my_notes.txt").write_text("keep me")
    (out / "depth" / "mine.png").write_text("keep me too")
    assert prepare_output(out, overwrite=True) == 5
    left = sorted(str(p.relative_to(out)) for p in out.rglob("*"))
    assert left == ["depth", os.path.join("depth", "mine.png"), "my_notes.txt"]
    # a second, smaller run: no stale depth PNG of the first one remains
    files = _fake_run(out, ["depth/f0.png", "depth/depth_scale.json", "points.ply"])
    assert "my_notes.txt" not in files and "depth/mine.png" not in files
    assert sorted(p.name for p in (out / "depth").iterdir()) == ["depth_scale.json", "f0.png", "mine.png"]


def test_manifest_cannot_delete_outside(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    victim = tmp_path / "victim.txt"
    victim.write_text("x")
    (out / MANIFEST_NAME).write_text(json.dumps({"files": ["../victim.txt", "/etc/hostname"]}))
    prepare_output(out, overwrite=True)
    assert victim.exists()


def test_out_under_a_file_fails_early(tmp_path):
    f = tmp_path / "file.txt"
    f.write_text("x")
    with pytest.raises(OutputDirError, match="is a file"):
        prepare_output(f / "sub" / "out")
    with pytest.raises(OutputDirError, match="not a folder"):
        prepare_output(f)


@pytest.mark.skipif(os.geteuid() == 0, reason="root can write into a read-only folder")
def test_unwritable_folder_fails_early(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        with pytest.raises(OutputDirError, match="cannot"):
            prepare_output(ro / "out")
    finally:
        ro.chmod(0o700)


def test_failed_run_that_wrote_nothing_leaves_folder_reusable(tmp_path):
    out = tmp_path / "out"
    prepare_output(out)
    assert Manifest(out).write() == [] and not (out / MANIFEST_NAME).exists()
    assert prepare_output(out) == 0  # still empty: no --overwrite needed

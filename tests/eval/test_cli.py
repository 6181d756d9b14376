"""`rvggt eval` end to end with the default weights (the bundled rvggt-small) on generated
scenes (dense and regime, one small input shape), resuming from stored results, the
--against mode, and one-line errors."""

import csv
import os
import subprocess
import sys
import pytest

from tests.helpers import REPO


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return str(tmp_path_factory.mktemp("xla_cache"))


def rvggt(cache, *args, timeout=600):
    env = dict(os.environ, RVGGT_CACHE_DIR=cache, JAX_PLATFORMS="cpu")
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.pop("RVGGT_DEBUG", None)
    return subprocess.run([sys.executable, "-m", "rvggt_jax.app.cli", "eval", *map(str, args)], capture_output=True,
                          text=True, timeout=timeout, env=env, cwd=REPO)


@pytest.fixture(scope="module")
def run(cache, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("eval")
    args = ("--dataset", "nrgbd", "--root", tmp / "data", "--synthetic", "--presets", "dense,regime", "--stride", "5",
            "--size", "56", "--out", tmp / "out")
    return tmp, args, rvggt(cache, *args)


def test_eval_end_to_end(run):
    tmp, _, r = run
    assert r.returncode == 0, r.stderr[-3000:]
    assert "rvggt-small" in r.stdout  # no --weights: the bundled trained small model, said
    out = tmp / "out"
    rows = list(csv.DictReader(open(out / "results.csv")))
    assert {(x["scene"], x["preset"]) for x in rows} == {(s, p) for s in ("synthetic_001", "synthetic_002")
                                                         for p in ("dense", "regime")}
    for x in rows:
        assert x["frames"] == "5"  # 21 frames, every 5th
        for k in ("acc", "acc_med", "comp", "comp_med", "nc", "nc_med", "time_s", "mem_gb"):
            assert float(x[k]) >= 0, k
        assert 0 <= float(x["nc"]) <= 1
    md = (out / "results.md").read_text()
    assert "| dense |" in md and "| regime |" in md and "acc per scene" in md
    plots = sorted(p.name for p in (out / "plots").iterdir())
    assert "per_scene.png" in plots and "speed_quality.png" in plots
    assert "trajectory_synthetic_001.png" in plots


def test_eval_resumes(run, cache):
    tmp, args, first = run
    assert first.returncode == 0, first.stderr[-3000:]
    stored = tmp / "out" / "runs" / "regime" / "synthetic_002.json"
    before = stored.read_text()
    (tmp / "out" / "runs" / "dense" / "synthetic_001.json").unlink()  # as if interrupted there
    r = rvggt(cache, *args, "--quiet", "--no-plots")
    assert r.returncode == 0, r.stderr[-3000:]
    assert stored.read_text() == before  # reused, not recomputed
    assert (tmp / "out" / "runs" / "dense" / "synthetic_001.json").exists()
    rows = list(csv.DictReader(open(tmp / "out" / "results.csv")))
    assert len(rows) == 4


def test_eval_against_dense(cache, tmp_path):
    r = rvggt(cache, "--dataset", "images", "--root", tmp_path / "imgs", "--synthetic", "--against", "dense",
              "--presets", "dense,regime", "--size", "56", "--frames", "5", "--out", tmp_path / "out", "--quiet")
    assert r.returncode == 0, r.stderr[-3000:]
    rows = list(csv.DictReader(open(tmp_path / "out" / "results.csv")))
    assert {x["preset"] for x in rows} == {"regime"}  # the reference is not compared with itself
    for x in rows:
        assert 0 <= float(x["auc@30"]) <= 1 and float(x["abs_rel"]) >= 0 and float(x["chamfer"]) >= 0


def one_error(capsys, argv, *needles):
    """`rvggt eval ARGV` in this process fails with one `rvggt: error:` line naming `needles`."""
    from rvggt_jax.app.cli import main

    code = main(["eval", *map(str, argv)])
    err = capsys.readouterr().err
    assert code != 0 and "Traceback" not in err, err
    errs = [ln for ln in err.splitlines() if ln.startswith("rvggt: error:")]
    assert len(errs) == 1, err
    for n in needles:
        assert n in errs[0], errs[0]


def test_eval_errors(capsys, tmp_path):
    out = ("--out", tmp_path / "o", "--quiet")
    one_error(capsys, ["--dataset", "tnt", "--root", tmp_path / "none", *out], "none")
    one_error(capsys, ["--dataset", "tnt", "--root", tmp_path, "--presets", "warp", *out], "warp")
    one_error(capsys, ["--dataset", "kittee", "--root", tmp_path, *out], "kittee")
    one_error(capsys, ["--dataset", "images", "--root", tmp_path, *out], "--against")
    one_error(capsys, ["--dataset", "tnt", "--root", tmp_path, "--size", "50", *out], "14")
    one_error(capsys, ["--dataset", "tnt", "--root", tmp_path, "--weights", tmp_path / "nockpt", *out], "nockpt")
    d = tmp_path / "s7"
    (d / "chess").mkdir(parents=True)
    (d / "chess" / "TestSplit.txt").write_text("sequence1\n")
    one_error(capsys, ["--dataset", "7scenes", "--root", d, *out], "seq-01")


def test_missing_plotting_package_is_said_before_any_scene(capsys, tmp_path, monkeypatch):
    """Without matplotlib, `rvggt eval` names the extra (and --no-plots) before it runs
    anything (it used to run every scene, then fail on the import)."""
    import importlib.util

    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda n, *a: None if n == "matplotlib" else find_spec(n, *a))
    out = tmp_path / "o"
    one_error(capsys, ["--dataset", "tnt", "--root", tmp_path / "syn", "--synthetic", "--out", out, "--quiet"],
              "matplotlib", 'pip install "rvggt-jax[eval]"', "--no-plots")
    assert not (tmp_path / "syn").exists() and not out.exists()

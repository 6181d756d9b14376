"""benchmarks/gpu_check.py's own logic (issue 54), with stand-in workers: the command line,
programs at growing sizes, the budget skipping the biggest instead of starting it, every
step guarded (a worker that crashes on import is recorded with its traceback and the next
step runs), the report written, the exit status. Its real steps run in CI's dry run
(.ci/run's second step), not here: they compile for minutes."""

from __future__ import annotations

import json
import sys
import time

import pytest

from benchmarks import gpu_check

# A stand-in worker: argv = kind, spec (JSON); plausible RESULT lines for each kind, or
# the failure that spec["fail"] names
FAKE_WORKER = f"""
import json, sys
kind, spec = sys.argv[1], json.loads(sys.argv[2])
def emit(**f):
    print({gpu_check.RESULT!r} + json.dumps(f), flush=True)
if kind in spec.get("crash", ()):
    import a_module_the_gpu_machine_lacks
if kind == "env":
    emit(python="3", jax="0.x", jaxlib="0.x", platform="cpu", device_kind="cpu", device_count=1, package="/x")
elif kind == "parity":
    emit(variant="float32", rows=[{{"output": "depth", "rel_err": spec.get("err", 0.0), "tol": 1e-4,
                                    "pass": spec.get("err", 0.0) <= 1e-4}}])
elif kind == "run":
    emit(stage="compiled", compile_s=1.0, platform="cpu", plan_bytes=10)
    if not spec.get("compile_only"):
        emit(stage="ran", run_s=0.5, times=[0.5], runs=1, peak_bytes=12)
elif kind == "plan":
    for p in spec["programs"]:
        emit(key=p["key"], target=spec["target"], compile_s=1.0, plan_bytes=10, kernel="XLA")
"""


@pytest.fixture
def fake_workers(monkeypatch):
    """Workers replaced by FAKE_WORKER; returns the dict whose "crash" / "err" every spec gets."""
    extra: dict = {}

    def cmd(kind, spec):
        return [sys.executable, "-c", FAKE_WORKER, kind, json.dumps(dict(spec, **extra))]

    monkeypatch.setattr(gpu_check, "worker_cmd", cmd)
    return extra


def test_command_line_dry_run_and_an_eight_minute_budget():
    args = gpu_check.parse_args([])
    assert args.budget <= 480 and not args.dry_run
    assert gpu_check.parse_args(["--dry-run"]).dry_run
    with pytest.raises(SystemExit):  # renamed, no alias
        gpu_check.parse_args(["--smoke"])
    with pytest.raises(SystemExit):
        gpu_check.parse_args(["--only", "regime1000"])


@pytest.mark.parametrize("argv", [[], ["--dense-1000"], ["--quick"], ["--dry-run"]])
def test_programs_at_growing_sizes_regime_first(argv):
    progs = gpu_check.programs(gpu_check.parse_args(argv))
    frames = [p["frames"] for p in progs]
    assert frames == sorted(frames) and len(set(frames)) == (1 if "--quick" in argv else 2 if "--dry-run" in argv else 3)
    assert progs[0]["preset"] == "regime"
    if not argv:
        assert [p["key"] for p in progs] == ["regime@100", "dense@100", "regime@300", "dense@300", "regime@1000"]


def test_the_biggest_program_is_skipped_not_started_when_the_budget_is_short(tmp_path, monkeypatch):
    args = gpu_check.parse_args(["--out", str(tmp_path)])
    progs = gpu_check.programs(args)
    started = []

    def run_program(args, rep, prog, row, deadline):
        started.append(prog["key"])
        row.update(run_s=1.0, platform="gpu")

    monkeypatch.setattr(gpu_check, "run_program", run_program)
    rep = {"notes": [], "failures": [], "date": "", "layout": "", "size": "", "plan_target": "h200",
           "_t0": time.monotonic()}
    # time for every program but the last
    deadline = time.monotonic() + gpu_check.expected_seconds(progs[-2], args) + 5
    gpu_check.part_speed(args, rep, progs, True, deadline)
    assert started == [p["key"] for p in progs[:-1]]
    assert "time budget" in rep["speed"][-1]["skipped"] and "run_s" not in rep["speed"][-1]
    assert not rep["failures"]
    assert "(1 skipped)" in rep["summary"] and rep["summary"].startswith("SUMMARY: OK")
    assert json.loads((tmp_path / "gpu_check.json").read_text())["speed"][-1]["skipped"]


def test_a_run_where_every_step_works_exits_0(tmp_path, fake_workers):
    assert gpu_check.main(["--dry-run", "--out", str(tmp_path)]) == 0
    rep = json.loads((tmp_path / "gpu_check.json").read_text())
    assert rep["failures"] == [] and rep["summary"].startswith("SUMMARY: OK")
    assert [r["key"] for r in rep["speed"]] == [p["key"] for p in rep["plan"]]  # ran and planned, each
    assert all("run_s" in r for r in rep["speed"]) and rep["plan"][0]["target"] == "cpu"
    assert (tmp_path / "gpu_check.md").read_text().strip().endswith(rep["summary"])


def test_a_worker_that_crashes_on_import_fails_its_step_and_the_next_steps_run(tmp_path, fake_workers):
    fake_workers["crash"] = ["env", "plan"]
    assert gpu_check.main(["--dry-run", "--out", str(tmp_path)]) == 1
    rep = json.loads((tmp_path / "gpu_check.json").read_text())
    steps = {f["step"]: f for f in rep["failures"]}
    assert set(steps) == {"env", "plan"}
    for f in steps.values():
        assert "Traceback" in f["traceback"] and "a_module_the_gpu_machine_lacks" in f["traceback"]
    assert rep["parity"] and all("run_s" in r for r in rep["speed"])  # the steps after env ran
    assert rep["summary"].startswith("SUMMARY: FAILED 2 step(s) (env, plan)")
    assert "## Failures" in (tmp_path / "gpu_check.md").read_text()


def test_a_result_over_its_tolerance_is_a_failure(tmp_path, fake_workers):
    fake_workers["err"] = 1e-2
    assert gpu_check.main(["--dry-run", "--out", str(tmp_path), "--no-plan"]) == 1
    rep = json.loads((tmp_path / "gpu_check.json").read_text())
    assert [f["step"] for f in rep["failures"]] == ["parity: float32"]

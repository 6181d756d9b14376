"""The evaluation pipeline (reader -> frame selection -> protocol -> tables) with the
model replaced by predictions made from the exact truth: perfect scores where the
prediction is the truth, the analytic value for a known perturbation, OOM rows kept."""

import csv

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rvggt_jax.eval.datasets.files import w2c_to_c2w
from rvggt_jax.eval.report import write_csv, write_markdown, write_plots
from rvggt_jax.eval.runner import EvalSettings, evaluate
from rvggt_jax.synthetic import make_scene, write_scene

W, H = 56, 42


def ideal(scene, idx, scale=0.5):
    """A perfect model's outputs for frames idx of a synthetic scene: the first camera's
    frame, another scale."""
    e = scene.extrinsics[idx]
    c2w0 = w2c_to_c2w(e[0])
    ext = np.stack([(np.vstack([x, [0, 0, 0, 1]]) @ c2w0)[:3] for x in e])
    ext[:, :, 3] *= scale
    wp = (scene.points[idx].astype(np.float64) @ e[0][:, :3].T + e[0][:, 3]) * scale
    return dict(extrinsics=ext, intrinsics=scene.intrinsics[idx], depth=scene.depth[idx] * scale,
                depth_conf=np.full(scene.depth[idx].shape, 2.0), world_points=wp,
                world_points_conf=np.ones(scene.depth[idx].shape))


class FakeModel:
    """dense: the truth; regime: camera 0 turned by 5.5 degrees; fastvggt: out of memory."""

    def __init__(self, scenes):
        self.scenes = scenes
        self.calls = 0

    def __call__(self, preset, images, scene):
        self.calls += 1
        truth = self.scenes[scene.name.split("/")[0]]
        idx = scene.meta["indices"]
        assert images.shape == (len(idx), 3, H, W)
        pred = ideal(truth, idx)
        if preset == "regime":
            q = Rotation.from_rotvec(np.deg2rad(5.5) * np.array([0.0, 1.0, 0.0])).as_matrix()
            pred["extrinsics"][0] = q @ pred["extrinsics"][0]
        if preset == "fastvggt":
            raise RuntimeError("RESOURCE_EXHAUSTED: Out of memory while trying to allocate 80.0GiB")
        return pred, dict(time_s=0.5, compile_s=0.0, mem_gb=1.0)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("pipeline")
    scenes = {}
    for i in range(2):
        s = make_scene(frames=12, height=H, width=W, seed=20 + i, focal=525 * W / 640, name=f"room{i}")
        scenes[s.name] = s
        for fmt in ("7scenes", "tnt"):
            write_scene(s, fmt, root / fmt)
    return root, scenes


def test_pose_table(data, tmp_path):
    root, scenes = data
    settings = EvalSettings("tnt", str(root / "tnt"), ("dense", "regime", "fastvggt"), str(tmp_path), "fake",
                            frames=6, sampling="even", size=W)
    model = FakeModel(scenes)
    rows = evaluate(settings, progress=False, say=lambda m: None, predictor_factory=lambda w: model)
    by = {(r["scene"], r["preset"]): r for r in rows}
    n, m = 6, 5  # frames; pairs involving camera 0
    p = n * (n - 1) // 2
    for s in scenes:
        assert by[(s, "dense")]["auc@30"] == pytest.approx(1.0)
        assert by[(s, "regime")]["auc@30"] == pytest.approx((5 * (1 - m / p) + 25) / 30)
        assert by[(s, "regime")]["auc@5"] == pytest.approx(1 - m / p)
        assert by[(s, "fastvggt")]["status"] == "OOM"
    write_csv(tmp_path / "r.csv", rows)
    write_markdown(tmp_path / "r.md", rows, ("auc@30", "auc@15", "auc@5"), "tnt", ("auc@30",))
    md = (tmp_path / "r.md").read_text()
    assert "| fastvggt | OOM | OOM |" in md
    assert f"| regime | {(5 * (1 - m / p) + 25) / 30:.4f} |" in md
    assert len(list(csv.DictReader(open(tmp_path / "r.csv")))) == 6
    plots = write_plots(tmp_path / "plots", rows, ("auc@30",), tmp_path / "runs", None)
    assert {p.name for p in plots} >= {"per_scene.png", "speed_quality.png", "trajectory_room0.png"}
    # a rerun reuses every stored result, the OOM ones included
    again = evaluate(settings, progress=False, say=lambda m: None, predictor_factory=lambda w: model)
    assert model.calls == 6 and sorted(map(str, again)) == sorted(map(str, rows))


def test_reconstruction_table(data, tmp_path):
    root, scenes = data
    settings = EvalSettings("7scenes", str(root / "7scenes"), ("dense",), str(tmp_path), "fake", stride=3, size=W)
    rows = evaluate(settings, progress=False, say=lambda m: None, predictor_factory=lambda w: FakeModel(scenes))
    assert [r["frames"] for r in rows] == [4, 4]  # 12 frames, every 3rd
    for r in rows:
        assert r["acc"] < 1e-3 and r["comp"] < 1e-3  # 1 mm depth steps on disk
        assert r["nc"] == pytest.approx(1.0, abs=1e-3)

"""The gtsam pose graph over chunk Sim(3)s: conventions, and a loop edge removing drift."""

import sys

import numpy as np
import pytest

from rvggt_jax.errors import InputError
from rvggt_jax.sequence import GraphEdge, Sim3, optimize_pose_graph
from rvggt_jax.sequence.pose_graph import from_gtsam, to_gtsam

gtsam = pytest.importorskip("gtsam")


def _rz(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])


def _rot_err_deg(a: Sim3, b: Sim3) -> float:
    cos = np.clip((np.trace(a.rotation.T @ b.rotation) - 1) / 2, -1, 1)
    return float(np.degrees(np.arccos(cos)))


def test_gtsam_conversion_matches_sim3():
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    a = Sim3(2.5, q, rng.normal(size=3))
    b = Sim3(0.7, _rz(40), rng.normal(size=3))
    ga, gb = to_gtsam(gtsam, a), to_gtsam(gtsam, b)
    p = rng.normal(size=3)
    np.testing.assert_allclose(ga.transformFrom(p), a.apply(p), atol=1e-12)
    np.testing.assert_allclose(from_gtsam(ga.compose(gb)).matrix(), (a @ b).matrix(), atol=1e-12)
    np.testing.assert_allclose(from_gtsam(ga).matrix(), a.matrix(), atol=1e-12)


def _circle(k: int = 6) -> list[Sim3]:
    """Chunks around a circle: each next chunk turned 60 degrees, moved, rescaled."""
    truth = [Sim3.identity()]
    step = Sim3(1.1, _rz(60), np.array([1.0, 0.0, 0.0]))
    for _ in range(k - 1):
        truth.append(truth[-1] @ step)
    return truth


def test_loop_edge_removes_injected_drift():
    truth = _circle()
    bias = Sim3(1.02, _rz(2.0), np.array([0.01, 0.0, 0.0]))  # per-chunk rotation/scale bias
    seq, chain = [], [Sim3.identity()]
    for k in range(len(truth) - 1):
        m = truth[k].inverse() @ truth[k + 1] @ bias
        seq.append(GraphEdge(k, k + 1, m))
        chain.append(chain[-1] @ m)
    loop = GraphEdge(0, len(truth) - 1, truth[-1], loop=True)
    before = [_rot_err_deg(c, t) for c, t in zip(chain, truth)]
    out = optimize_pose_graph(chain, seq + [loop])
    after = [_rot_err_deg(o, t) for o, t in zip(out, truth)]
    assert before[-1] > 9.0  # 5 edges of 2 degrees
    assert after[-1] < 0.25 * before[-1] and max(after) < 0.3 * max(before)
    assert abs(np.log(out[-1].scale / truth[-1].scale)) < 0.3 * abs(np.log(chain[-1].scale / truth[-1].scale))
    np.testing.assert_allclose(out[0].matrix(), np.eye(4), atol=1e-9)
    # Without the loop the chain is the optimum: the graph returns it unchanged.
    same = optimize_pose_graph(chain, seq)
    for s, c in zip(same, chain):
        np.testing.assert_allclose(s.matrix(), c.matrix(), atol=1e-6)


def test_bad_edges_raise():
    with pytest.raises(InputError, match="chunks are 0..2"):
        optimize_pose_graph([Sim3.identity()] * 3, [GraphEdge(0, 3, Sim3.identity())])
    with pytest.raises(InputError, match="spread"):
        optimize_pose_graph([Sim3.identity()] * 2, [GraphEdge(0, 1, Sim3.identity(), spread=0.0)])


def test_missing_gtsam_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "gtsam", None)  # `import gtsam` now fails
    with pytest.raises(ImportError, match=r'pip install "rvggt-jax\[sequence\]"'):
        optimize_pose_graph([Sim3.identity()] * 2, [GraphEdge(0, 1, Sim3.identity())])

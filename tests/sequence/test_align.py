"""align_chunks on small synthetic chunk predictions: cameras on a circle looking
outwards, each frame's pixels at random depths; each chunk in its own first camera's
frame at a random scale. Also the loop candidates it proposes."""

import numpy as np
import pytest

from rvggt_jax.errors import InputError
from rvggt_jax.sequence import (AlignmentError, AlignOptions, ChunkPrediction, LoopOptions, Sim3, align_chunks,
                                loop_candidates, plan_chunks)

S, H, W = 60, 12, 16
K = np.array([[20.0, 0, W / 2], [0, 20.0, H / 2], [0, 0, 1]])
LOOPS = LoopOptions(min_similarity=0.9, min_gap=30, max_loops=4, nms_radius=5, neighbourhood=2)


def _scene(seed: int = 0):
    """-> world extrinsics [S, 3, 4], world points [S, H, W, 3], confidence [S, H, W],
    descriptors [S, 32] (bumps of the camera's angle on the circle: frames 0 and S-1 look
    alike)."""
    rng = np.random.default_rng(seed)
    theta = 2 * np.pi * np.arange(S) / S
    z = np.stack([np.cos(theta), np.sin(theta), np.zeros(S)], axis=1)  # looking outwards
    y = np.tile([0.0, 0.0, -1.0], (S, 1))
    c2w = np.stack([np.cross(y, z), y, z], axis=2)
    centres = 10.0 * z
    ext = np.concatenate([c2w.transpose(0, 2, 1), -np.einsum("sji,sj->si", c2w, centres)[..., None]], axis=2)
    v, u = np.mgrid[0:H, 0:W] + 0.5
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K).T
    depth = rng.uniform(2.0, 6.0, (S, H, W, 1))
    pts = np.einsum("sij,shwj->shwi", c2w, rays * depth) + centres[:, None, None]
    centres_m = 2 * np.pi * np.arange(32) / 32
    gap = np.angle(np.exp(1j * (theta[:, None] - centres_m[None])))
    desc = np.exp(-0.5 * (gap / 0.3) ** 2)
    return ext, pts, rng.uniform(1.0, 3.0, (S, H, W)), desc


def _chunk(scene, frames, to_chunk: Sim3, bend: float = 0.0) -> ChunkPrediction:
    """The frames seen in the chunk's frame `to_chunk` (world -> chunk); `bend` turns frame
    f's geometry by bend * (f - first) radians about the chunk's vertical axis: drift that
    no single Sim(3) of the chunk undoes."""
    ext, pts, conf, desc = scene
    frames = np.asarray(frames)
    e, p = [], []
    for f in frames:
        a = bend * (f - frames[0])
        turn = Sim3(1.0, [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]], np.zeros(3))
        t = turn @ to_chunk
        e.append(t.transform_extrinsics(ext[f]))
        p.append(t.apply(pts[f]))
    return ChunkPrediction(frames, np.array(e), np.tile(K, (len(frames), 1, 1)), np.array(p), conf[frames],
                           desc[frames])


def _first_camera_frame(scene, frames, rng) -> Sim3:
    e = scene[0][frames[0]]
    return Sim3(float(np.exp(rng.uniform(-1, 1))), np.eye(3), np.zeros(3)) @ Sim3(1.0, e[:, :3], e[:, 3])


def _chunks(scene, plan, bend: float = 0.0, seed: int = 1):
    rng = np.random.default_rng(seed)
    to = [_first_camera_frame(scene, f, rng) for f in plan]
    return [_chunk(scene, f, t, bend) for f, t in zip(plan, to)], to


def _verifier(scene, calls: list):
    rng = np.random.default_rng(9)

    def verify(frames):
        calls.append(list(frames))
        return _chunk(scene, frames, _first_camera_frame(scene, frames, rng))
    return verify


def _rot_err_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-frame angle between the rotations of extrinsics a, b [S, 3, 4]."""
    tr = np.einsum("sij,sij->s", a[:, :, :3], b[:, :, :3])
    return np.degrees(np.arccos(np.clip((tr - 1) / 2, -1, 1)))


def test_exact_recovery_without_noise():
    scene = _scene()
    plan = plan_chunks(S, 12, 2)
    chunks, to = _chunks(scene, plan)
    traj = align_chunks(chunks)
    want = to[0].transform_extrinsics(scene[0])  # the truth in the first chunk's frame
    np.testing.assert_allclose(traj.extrinsics, want, atol=1e-8 * np.abs(want).max())
    np.testing.assert_allclose(traj.intrinsics, np.tile(K, (S, 1, 1)))
    for g, t in zip(traj.chunk_sim3, to):
        np.testing.assert_allclose(g.matrix(), (to[0] @ t.inverse()).matrix(), atol=1e-8)
    # Overlaps: chunks 0/1 share 10, 11; chunks 4 (40..51) / 5 (48..59) share 48..51.
    assert traj.frame_chunk[[9, 10, 11, 12, 47, 48, 49, 50, 51, 52]].tolist() == [0, 0, 1, 1, 4, 4, 4, 5, 5, 5]
    assert traj.edge_residuals.shape == (len(plan) - 1,) and traj.edge_residuals.max() < 1e-8
    assert traj.loops == ()


def test_memmapped_points_read_only_shared_frames(tmp_path):
    scene = _scene()
    chunks, _ = _chunks(scene, plan_chunks(S, 12, 2))
    reads = []

    class Recording:
        def __init__(self, a, k):
            self.a, self.k, self.shape, self.dtype = a, k, a.shape, a.dtype

        def __getitem__(self, key):
            reads.append((self.k, np.asarray(key).tolist()))
            return self.a[key]

    mapped = []
    for k, c in enumerate(chunks):
        np.save(tmp_path / f"p{k}.npy", c.points.astype(np.float32))
        np.save(tmp_path / f"c{k}.npy", c.confidence)
        points = np.load(tmp_path / f"p{k}.npy", mmap_mode="r")
        assert isinstance(points, np.memmap)
        mapped.append(ChunkPrediction(c.frames, c.extrinsics, c.intrinsics, Recording(points, k),
                                      np.load(tmp_path / f"c{k}.npy", mmap_mode="r")))
    traj, ref = align_chunks(mapped), align_chunks(chunks)
    np.testing.assert_allclose(traj.extrinsics, ref.extrinsics, atol=1e-4 * np.abs(ref.extrinsics).max())
    # Only the overlap positions were read: the last two of a chunk, the first two of the
    # next (chunk 5 shares four frames with chunk 4).
    assert reads and all(len(key) <= 4 for _, key in reads)
    assert sorted({tuple(key) for k, key in reads if k == 1}) == [(0, 1), (10, 11)]


def test_too_few_confident_points_is_refused_by_name():
    scene = _scene()
    chunks, _ = _chunks(scene, plan_chunks(S, 12, 2))
    c = chunks[2]  # frames 20..31, shares 20, 21 with chunk 1
    conf = np.array(c.confidence)
    conf[:2] = 0.5
    conf[0, 0, :10] = 2.0  # 10 confident pixels left
    chunks[2] = ChunkPrediction(c.frames, c.extrinsics, c.intrinsics, c.points, conf, c.descriptors)
    opts = AlignOptions(conf_threshold=1.0, conf_quantile=0.0)
    with pytest.raises(AlignmentError) as err:
        align_chunks(chunks, options=opts)
    msg = str(err.value)
    assert isinstance(err.value, InputError)
    assert "chunk 1 (frames 10..21)" in msg and "chunk 2 (frames 20..31)" in msg
    assert "10 usable points" in msg and "at least 64" in msg
    assert "--overlap" in msg and "--conf-threshold" in msg
    assert err.value.chunks == (1, 2) and err.value.usable == 10
    align_chunks(chunks, options=AlignOptions(conf_threshold=0.4, conf_quantile=0.0))  # a lower threshold helps


def test_input_errors():
    scene = _scene()
    chunks, _ = _chunks(scene, [np.r_[0:6, 8:12], np.arange(10, 22)])
    with pytest.raises(InputError, match=r"2 are in none: \[6, 7\]"):
        align_chunks(chunks)
    chunks, _ = _chunks(scene, [np.arange(0, 12), np.arange(12, 24)])
    with pytest.raises(InputError, match="chunks 0 .*and 1 .*share no frame"):
        align_chunks(chunks)
    chunks, _ = _chunks(scene, plan_chunks(S, 12, 2))
    with pytest.raises(InputError, match="needs verify"):
        align_chunks(chunks, loop_closure=True)
    bare = [ChunkPrediction(c.frames, c.extrinsics, c.intrinsics, c.points, c.confidence) for c in chunks]
    with pytest.raises(InputError, match="descriptors"):
        align_chunks(bare, loop_closure=True, verify=lambda frames: chunks[0])
    with pytest.raises(InputError, match="conf_quantile"):
        AlignOptions(conf_quantile=1.5)
    with pytest.raises(InputError, match="min_gap"):
        LoopOptions(min_gap=-1)


def test_loop_closure_removes_drift():
    scene = _scene()
    plan = plan_chunks(S, 12, 2)  # 6 chunks around the circle
    chunks, to = _chunks(scene, plan, bend=0.003)
    want = to[0].transform_extrinsics(scene[0])
    calls = []
    opts = AlignOptions(loops=LOOPS)
    chain = align_chunks(chunks, options=opts)
    closed = align_chunks(chunks, loop_closure=True, verify=_verifier(scene, calls), options=opts)
    before, after = _rot_err_deg(chain.extrinsics, want), _rot_err_deg(closed.extrinsics, want)
    assert before.max() > 5.0  # the drift is there
    assert after.max() < 0.4 * before.max() and after[-6:].max() < 0.3 * before[-6:].max()
    assert closed.loops and all((e.i, e.j) == (0, 5) for e in closed.loops)
    # Each verification got a neighbourhood of a (chunk 0) and one of b (chunk 5).
    for frames, e in zip(calls, closed.loops):
        assert e.frames[0] in frames and e.frames[1] in frames and len(frames) <= 10
        assert max(frames[:len(frames) // 2]) < 12 and min(frames[len(frames) // 2:]) >= 48


def test_loop_closure_without_accepted_loops_keeps_the_chain():
    scene = _scene()
    chunks, _ = _chunks(scene, plan_chunks(S, 12, 2), bend=0.003)
    rng = np.random.default_rng(3)

    def wrong(frames):  # each frame's points scrambled: nothing aligns
        p = _chunk(scene, frames, Sim3.identity())
        pts = np.array(p.points)
        return ChunkPrediction(p.frames, p.extrinsics, p.intrinsics, rng.permutation(pts.reshape(-1, 3)).reshape(
            pts.shape), p.confidence)

    chain = align_chunks(chunks, options=AlignOptions(loops=LOOPS))
    traj = align_chunks(chunks, loop_closure=True, verify=wrong, options=AlignOptions(loops=LOOPS))
    assert traj.loops == ()
    np.testing.assert_array_equal(traj.extrinsics, chain.extrinsics)


def test_loop_candidates_gap_chunks_and_suppression():
    desc = _scene()[3]
    plan = plan_chunks(S, 12, 2)
    first, last = np.full(S, 99), np.full(S, -1)
    for k, f in enumerate(plan):
        first[f], last[f] = np.minimum(first[f], k), np.maximum(last[f], k)
    opts = LoopOptions(min_similarity=0.8, min_gap=30, max_loops=10, nms_radius=5)
    got = loop_candidates(desc, opts, first_chunk=first, last_chunk=last)
    assert 1 <= len(got) <= 3  # one revisit (the circle closing): one or a few candidates
    unit = desc / np.linalg.norm(desc, axis=1, keepdims=True)
    for c in got:
        assert c.b - c.a >= 30 and first[c.b] >= last[c.a] + 2 and c.similarity >= 0.8
        assert c.similarity == pytest.approx(float(unit[c.a] @ unit[c.b]), abs=1e-5)
    # Without suppression the same revisit gives more pairs; max_loops caps them.
    many = loop_candidates(desc, LoopOptions(min_similarity=0.8, min_gap=30, max_loops=10, nms_radius=0))
    assert len(many) > len(got)
    assert len(loop_candidates(desc, LoopOptions(min_similarity=0.8, min_gap=30, max_loops=2, nms_radius=0))) == 2
    assert loop_candidates(desc, LoopOptions(min_similarity=0.8, min_gap=S)) == []


def test_loop_candidates_in_blocks_match_the_full_matrix():
    rng = np.random.default_rng(0)
    desc = rng.normal(size=(300, 16))
    desc[17] = 0  # no descriptor: never a candidate
    opts = dict(min_similarity=0.5, min_gap=20, max_loops=12, nms_radius=3)
    got = loop_candidates(desc, LoopOptions(**opts))
    small = loop_candidates(desc, LoopOptions(**opts, block=7))
    assert [(c.a, c.b) for c in got] == [(c.a, c.b) for c in small]
    np.testing.assert_allclose([c.similarity for c in got], [c.similarity for c in small], atol=1e-6)
    unit = desc / np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-30)
    sim = unit @ unit.T
    a, b = np.meshgrid(np.arange(300), np.arange(300), indexing="ij")
    sim[b - a < 20] = -np.inf
    assert len(got) == 12 and all(17 not in (c.a, c.b) for c in got)
    assert (got[0].a, got[0].b) == np.unravel_index(sim.argmax(), sim.shape)
    sims = [c.similarity for c in got]
    assert sims == sorted(sims, reverse=True) and min(sims) >= 0.5
    for n, c in enumerate(got):
        assert all(abs(c.a - o.a) > 3 or abs(c.b - o.b) > 3 for o in got[:n])

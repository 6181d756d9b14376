"""Chunks -> one trajectory: consecutive chunks chained by robust Sim(3) on the points of
the frames they share, optionally loops closed by a pose graph over the chunks.

Which chunk gives each frame's camera: in the overlap of chunks k and k+1 (their shared
frames, in frame order), the first floor(n / 2) of the n shared frames come from chunk k
and the rest from chunk k+1; every other frame from the one chunk holding it (overlaps
are taken in chunk order, a later one overriding an earlier one where three chunks share
a frame). That frame's extrinsics are G_k.transform_extrinsics(E) with chunk k's Sim(3)
G_k into the first chunk's frame, and its intrinsics are chunk k's.

A pair of chunks whose overlap holds too few confident points is refused with an
`AlignmentError` naming them; never a silently wrong trajectory.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Sequence

import numpy as np

from rvggt_jax.errors import InputError
from rvggt_jax.sequence.loops import LoopCandidate, LoopOptions, loop_candidates
from rvggt_jax.sequence.pose_graph import GraphEdge, PoseGraphOptions, optimize_pose_graph
from rvggt_jax.sequence.prediction import ChunkPrediction, LoopEdge, Trajectory
from rvggt_jax.sequence.sim3 import Sim3, Sim3Fit, sim3_align_report

__all__ = ["AlignOptions", "AlignmentError", "align_chunks"]

Verify = Callable[[list[int]], ChunkPrediction]


class AlignmentError(InputError):
    """Two chunks that cannot be aligned: their overlap has too few usable points.
    `chunks` (i, j), `frame_ranges` ((first, last) of each), `usable`, `needed`."""

    def __init__(self, message: str, *, chunks: tuple[int, int], frame_ranges: tuple[tuple[int, int], ...],
                 usable: int, needed: int) -> None:
        super().__init__(message)
        self.chunks, self.frame_ranges, self.usable, self.needed = chunks, frame_ranges, usable, needed


@dataclasses.dataclass(frozen=True)
class AlignOptions:
    """How chunks are aligned.

    conf_threshold  pixels with a confidence below this (in either chunk) are left out
    conf_quantile   and pixels below this quantile of their chunk's confidences in the
                    overlap (0.5: the less confident half of each chunk's pixels)
    min_points      fewest usable points to align two chunks (fewer: `AlignmentError`;
                    for a loop verification: the loop is rejected)
    max_points      at most this many points per alignment (a random subset, fixed seed)
    seed            of those subsets
    max_loop_residual   reject a loop verification whose alignment residual exceeds this
                    fraction of the aligned points' spread (in either chunk)
    min_loop_inliers    reject a loop verification whose alignments keep less than this
                    fraction of their points as Huber inliers
    loops           `LoopOptions`: candidates and verification neighbourhoods
    pose_graph      `PoseGraphOptions`: edge noise
    """

    conf_threshold: float = 0.0
    conf_quantile: float = 0.5
    min_points: int = 64
    max_points: int = 20_000
    seed: int = 0
    max_loop_residual: float = 0.05
    min_loop_inliers: float = 0.5
    loops: LoopOptions = LoopOptions()
    pose_graph: PoseGraphOptions = PoseGraphOptions()

    def __post_init__(self) -> None:
        if not 0.0 <= self.conf_quantile < 1.0:
            raise InputError(f"AlignOptions.conf_quantile must be in [0, 1); got {self.conf_quantile}")
        if not np.isfinite(self.conf_threshold):
            raise InputError(f"AlignOptions.conf_threshold must be finite; got {self.conf_threshold}")
        if self.min_points < 3 or self.max_points < self.min_points:
            raise InputError(f"AlignOptions needs 3 <= min_points <= max_points; got {self.min_points} and "
                             f"{self.max_points}")
        if not (self.max_loop_residual > 0 and 0.0 <= self.min_loop_inliers <= 1.0):
            raise InputError("AlignOptions.max_loop_residual must be > 0 and min_loop_inliers in [0, 1]; got "
                             f"{self.max_loop_residual} and {self.min_loop_inliers}")


def _span(chunk: ChunkPrediction) -> tuple[int, int]:
    return int(chunk.frames.min()), int(chunk.frames.max())


def _positions(chunk: ChunkPrediction, frames: np.ndarray) -> np.ndarray:
    """Positions [n] in `chunk` of the sequence frames [n] (all in it)."""
    order = np.argsort(chunk.frames)
    at = np.searchsorted(chunk.frames[order], frames)
    return order[at]


def _read(array, positions: np.ndarray) -> np.ndarray:
    """array[positions] reading only those frames (in increasing order, as memmaps and
    HDF5-like stores read best), returned in the order asked."""
    order = np.argsort(positions)
    got = np.asarray(array[positions[order]])
    out = np.empty_like(got)
    out[order] = got
    return out


def _overlap_points(dst: ChunkPrediction, src: ChunkPrediction, frames: np.ndarray, options: AlignOptions,
                    rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The usable pixels of `frames` (held by both chunks) -> src points [M, 3], dst points
    [M, 3] (float64) and weights [M]: finite in both, confidence at least the level in
    both, weight the geometric mean of the two confidences; at most max_points of them."""
    pd, ps = _positions(dst, frames), _positions(src, frames)
    xd, xs = _read(dst.points, pd), _read(src.points, ps)
    if xd.shape != xs.shape:
        raise InputError(f"chunks with frames {_span(dst)} and {_span(src)} have point maps of different sizes "
                         f"{list(xd.shape[1:3])} and {list(xs.shape[1:3])} on the frames they share")
    cd = _read(dst.confidence, pd).astype(np.float64)
    cs = _read(src.confidence, ps).astype(np.float64)
    with np.errstate(invalid="ignore"):
        ok = (np.isfinite(xd).all(-1) & np.isfinite(xs).all(-1) & np.isfinite(cd) & np.isfinite(cs)
              & (cd > 0) & (cs > 0) & (cd >= options.conf_threshold) & (cs >= options.conf_threshold))
        if ok.any() and options.conf_quantile > 0:
            q = options.conf_quantile
            ok &= (cd >= np.quantile(cd[ok], q)) & (cs >= np.quantile(cs[ok], q))
    idx = np.flatnonzero(ok)
    if len(idx) > options.max_points:
        idx = np.sort(rng.choice(idx, options.max_points, replace=False))
    return (xs.reshape(-1, 3)[idx].astype(np.float64), xd.reshape(-1, 3)[idx].astype(np.float64),
            np.sqrt(cd.reshape(-1)[idx] * cs.reshape(-1)[idx]))


def _refuse(k: int, chunks: Sequence[ChunkPrediction], shared: int, usable: int, needed: int,
            why: str = "") -> AlignmentError:
    (a0, a1), (b0, b1) = _span(chunks[k]), _span(chunks[k + 1])
    return AlignmentError(
        f"cannot align chunk {k} (frames {a0}..{a1}) with chunk {k + 1} (frames {b0}..{b1}): their {shared} "
        f"shared frames give {usable} usable points (finite in both chunks and above the confidence level), and "
        f"at least {needed} are needed{why}. A larger overlap between chunks (--overlap) or a lower confidence "
        f"threshold (--conf-threshold) gives more points.",
        chunks=(k, k + 1), frame_ranges=((a0, a1), (b0, b1)), usable=usable, needed=needed)


def _sequential(chunks: Sequence[ChunkPrediction], options: AlignOptions) -> list[Sim3Fit]:
    """Fits S_{k,k+1} (chunk k+1 -> chunk k) of every consecutive pair, on their shared frames."""
    fits = []
    for k in range(len(chunks) - 1):
        shared = np.intersect1d(chunks[k].frames, chunks[k + 1].frames)
        if not len(shared):
            (a0, a1), (b0, b1) = _span(chunks[k]), _span(chunks[k + 1])
            raise InputError(f"chunks {k} (frames {a0}..{a1}) and {k + 1} (frames {b0}..{b1}) share no frame, so "
                             f"they cannot be aligned: consecutive chunks must overlap (--overlap >= 1)")
        rng = np.random.default_rng((options.seed, k))
        src, dst, w = _overlap_points(chunks[k], chunks[k + 1], shared, options, rng)
        if len(w) < options.min_points:
            raise _refuse(k, chunks, len(shared), len(w), options.min_points)
        try:
            fits.append(sim3_align_report(src, dst, w))
        except InputError as e:
            raise _refuse(k, chunks, len(shared), len(w), options.min_points, f" ({e})") from e
    return fits


def _frame_chunk(chunks: Sequence[ChunkPrediction]) -> np.ndarray:
    """[S] the chunk giving each frame's camera (the rule in the module docstring)."""
    s = int(max(c.frames.max() for c in chunks)) + 1
    if min(int(c.frames.min()) for c in chunks) < 0:
        raise InputError("chunk frames must be sequence indices >= 0")
    owner = np.full(s, -1, dtype=np.int64)
    for k, c in enumerate(chunks):
        owner[c.frames[owner[c.frames] < 0]] = k
        if k:
            shared = np.intersect1d(chunks[k - 1].frames, c.frames)
            owner[shared[len(shared) // 2:]] = k
    missing = np.flatnonzero(owner < 0)
    if len(missing):
        raise InputError(f"frames 0..{s - 1} must each be in a chunk; {len(missing)} are in none: "
                         f"{missing[:10].tolist()}{' ...' if len(missing) > 10 else ''}")
    return owner


def _neighbourhood(chunk: ChunkPrediction, frame: int, n: int) -> np.ndarray:
    """The chunk's frames within n positions of `frame`, in frame order [<= 2n + 1]."""
    ordered = np.sort(chunk.frames)
    at = int(np.searchsorted(ordered, frame))
    return ordered[max(0, at - n):at + n + 1]


def _loop_fit(chunk: ChunkPrediction, pred: ChunkPrediction, frames: np.ndarray, options: AlignOptions,
              rng: np.random.Generator) -> Sim3Fit | None:
    """The verification's frame -> chunk's frame on `frames`, or None when unusable."""
    src, dst, w = _overlap_points(chunk, pred, frames, options, rng)
    if len(w) < options.min_points:
        return None
    try:
        fit = sim3_align_report(src, dst, w)
    except InputError:
        return None
    good = fit.relative_residual <= options.max_loop_residual and fit.inliers >= options.min_loop_inliers * fit.used
    return fit if good else None


def _verify_loop(chunks: Sequence[ChunkPrediction], verify: Verify, cand: LoopCandidate, i: int, j: int,
                 options: AlignOptions, n: int) -> tuple[LoopEdge, float] | None:
    """Verify one candidate (frame a in chunk i, b in chunk j) -> (a loop edge chunk j ->
    chunk i = (V -> i) @ (V -> j)^-1, the scene's spread in chunk j's units), or None when
    the verification is rejected. The edge's residual is the RMS of the two alignments'
    residuals in chunk i's units; its inlier count that of the weaker alignment."""
    na = _neighbourhood(chunks[i], cand.a, options.loops.neighbourhood)
    nb = _neighbourhood(chunks[j], cand.b, options.loops.neighbourhood)
    asked = [int(f) for f in np.concatenate([na, nb])]
    pred = verify(asked)
    if not isinstance(pred, ChunkPrediction):
        raise InputError(f"verify({asked}) must return a ChunkPrediction; got {type(pred).__name__}")
    if not np.isin(asked, pred.frames).all():
        raise InputError(f"verify({asked}) returned a prediction of frames {pred.frames.tolist()}, without all "
                         f"the frames asked for")
    fit_i = _loop_fit(chunks[i], pred, na, options, np.random.default_rng((options.seed, n, 0)))
    fit_j = _loop_fit(chunks[j], pred, nb, options, np.random.default_rng((options.seed, n, 1)))
    if fit_i is None or fit_j is None:
        return None
    m = fit_i.sim3 @ fit_j.sim3.inverse()
    residual = float(np.sqrt((fit_i.residual ** 2 + (m.scale * fit_j.residual) ** 2) / 2))
    return LoopEdge(i, j, (cand.a, cand.b), m, residual, min(fit_i.inliers, fit_j.inliers)), fit_j.spread


def _loops(chunks: Sequence[ChunkPrediction], verify: Verify | None, owner: np.ndarray,
           options: AlignOptions) -> tuple[list[LoopEdge], list[float]]:
    """Propose, verify and keep loop edges -> (edges, their spreads in chunk j's units)."""
    if verify is None:
        raise InputError("loop_closure=True needs verify(frames) -> ChunkPrediction, which predicts the frames "
                         "of a loop candidate together; none was given")
    missing = [k for k, c in enumerate(chunks) if c.descriptors is None]
    if missing:
        raise InputError(f"loop_closure=True needs every chunk's per-frame descriptors; chunks {missing[:10]} have "
                         f"none")
    dims = {c.descriptors.shape[1] for c in chunks}
    if len(dims) > 1:
        raise InputError(f"chunks' descriptors must all have the same length D; got {sorted(dims)}")
    s = len(owner)
    desc = np.zeros((s, dims.pop()), dtype=np.float32)
    first, last = np.full(s, len(chunks)), np.full(s, -1)
    for k, c in enumerate(chunks):
        mine = owner[c.frames] == k
        desc[c.frames[mine]] = c.descriptors[mine]
        first[c.frames] = np.minimum(first[c.frames], k)
        last[c.frames] = np.maximum(last[c.frames], k)
    edges, spreads = [], []
    for n, cand in enumerate(loop_candidates(desc, options.loops, first_chunk=first, last_chunk=last)):
        i, j = int(last[cand.a]), int(first[cand.b])
        verified = _verify_loop(chunks, verify, cand, i, j, options, n)
        if verified is not None:
            edges.append(verified[0])
            spreads.append(verified[1])
    return edges, spreads


def align_chunks(chunks: Sequence[ChunkPrediction], *, loop_closure: bool = False, verify: Verify | None = None,
                 options: AlignOptions = AlignOptions()) -> Trajectory:
    """Every frame's camera in the first chunk's frame.

    chunks        `ChunkPrediction`s in sequence order; consecutive ones share frames,
                  together they hold frames 0..S-1 (S = largest frame + 1)
    loop_closure  propose loops from the chunks' descriptors [F, D], verify each with
                  `verify(frames) -> ChunkPrediction` (the frames around both loop
                  frames predicted together), and optimise every chunk's Sim(3) in a
                  pose graph over the sequential and the accepted loop edges
    Chaining: G_0 = identity, G_{k+1} = G_k @ S_{k,k+1}, S_{k,k+1} (chunk k+1 -> chunk k)
    from `sim3_align` on the shared frames' points, weighted by confidence. Without an
    accepted loop the chain is kept as it is (it is the pose graph's optimum).
    Raises `AlignmentError` for an overlap with too few usable points, `InputError` for
    missing frames, chunks sharing no frame, or loop closure without its inputs."""
    chunks = list(chunks)
    if not chunks or not all(isinstance(c, ChunkPrediction) for c in chunks):
        raise InputError("align_chunks needs a non-empty sequence of ChunkPrediction")
    owner = _frame_chunk(chunks)
    fits = _sequential(chunks, options)
    g = [Sim3.identity()]
    for fit in fits:
        g.append(g[-1] @ fit.sim3)
    loops: list[LoopEdge] = []
    if loop_closure:
        loops, spreads = _loops(chunks, verify, owner, options)
        if loops:
            edges = [GraphEdge(k, k + 1, f.sim3, spread=f.spread / f.sim3.scale) for k, f in enumerate(fits)]
            edges += [GraphEdge(e.i, e.j, e.sim3, spread=sp, loop=True) for e, sp in zip(loops, spreads)]
            g = optimize_pose_graph(g, edges, options.pose_graph)
    s = len(owner)
    extrinsics, intrinsics = np.zeros((s, 3, 4)), np.zeros((s, 3, 3))
    for k, c in enumerate(chunks):
        mine = owner[c.frames] == k
        extrinsics[c.frames[mine]] = g[k].transform_extrinsics(c.extrinsics[mine])
        intrinsics[c.frames[mine]] = c.intrinsics[mine]
    return Trajectory(extrinsics, intrinsics, tuple(g), owner, tuple(loops),
                      np.array([f.residual for f in fits], dtype=np.float64))

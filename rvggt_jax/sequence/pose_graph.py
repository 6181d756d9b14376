"""A pose graph over chunks: every chunk's Sim(3) into the first chunk's frame, optimised
jointly over the sequential edges (consecutive chunks aligned on their shared frames)
and the loop edges (far-apart chunks aligned through a verification forward).

Solved with GTSAM's `Similarity3` factors: GTSAM is the field's factor-graph library, its
Sim(3) carries the scale that drifts between monocular chunks (each chunk of a
feed-forward model has its own unknown scale, so an SE(3) graph could not correct the
scale drift), and VGGT-SLAM builds its Sim(3) graph over submaps on the same library.

GTSAM's conventions, checked against its matrices: `Similarity3(R, t, s)` is the map
x -> s (R x + t), matrix [[R, t], [0, 1/s]], so our `Sim3` (x -> s R x + t) is
`Similarity3(R, t / s, s)`; composition is the matrix product, as for `Sim3`; the
tangent vector is [rotation (3), translation (3), log scale (1)].
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

from rvggt_jax.errors import InputError
from rvggt_jax.sequence.sim3 import Sim3

__all__ = ["GraphEdge", "PoseGraphOptions", "optimize_pose_graph"]


@dataclasses.dataclass(frozen=True)
class PoseGraphOptions:
    """Noise of the edges (standard deviations of their tangent errors).

    rotation_sigma     radians
    translation_sigma  relative to the edge's `spread` (the scene's size in chunk j's
                       units), since chunks have arbitrary units
    scale_sigma        of the log scale
    loop_sigma_factor  a loop edge's sigmas are the sequential ones times this
    loop_huber         Huber threshold of the loop edges, in sigmas: a loop that passed
                       verification but is wrong (a similar-looking other place) pulls
                       with bounded force instead of bending the whole trajectory
    max_iterations     Levenberg-Marquardt iterations
    """

    rotation_sigma: float = 0.02
    translation_sigma: float = 0.02
    scale_sigma: float = 0.02
    loop_sigma_factor: float = 1.0
    loop_huber: float = 3.0
    max_iterations: int = 100

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"PoseGraphOptions.{f.name} must be positive; got {v}")


@dataclasses.dataclass(frozen=True, eq=False)
class GraphEdge:
    """A relative measurement between chunks i and j: `sim3` maps chunk j's frame into
    chunk i's (so G_i^-1 G_j ~ sim3); `spread` is the scene's size in chunk j's units
    (it scales the translation sigma); `loop` selects the loop edges' robust noise."""

    i: int
    j: int
    sim3: Sim3
    spread: float = 1.0
    loop: bool = False


def _gtsam():
    try:
        import gtsam
    except ImportError as e:  # the [sequence] extra is optional
        raise ImportError('the pose graph over chunks (loop closure) needs GTSAM: pip install '
                          '"rvggt-jax[sequence]"') from e
    return gtsam


def to_gtsam(gtsam, t: Sim3):
    """Our `Sim3` (x -> s R x + t) -> gtsam.Similarity3 (x -> s (R x + t'), t' = t / s)."""
    return gtsam.Similarity3(gtsam.Rot3(t.rotation), t.translation / t.scale, t.scale)


def from_gtsam(g) -> Sim3:
    """gtsam.Similarity3 -> our `Sim3`."""
    s = float(g.scale())
    return Sim3(s, np.asarray(g.rotation().matrix()), s * np.asarray(g.translation()))


def _edge_noise(gtsam, edge: GraphEdge, options: PoseGraphOptions):
    factor = options.loop_sigma_factor if edge.loop else 1.0
    t = options.translation_sigma * edge.spread
    sigmas = factor * np.array([options.rotation_sigma] * 3 + [t] * 3 + [options.scale_sigma])
    noise = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
    if edge.loop:
        noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(options.loop_huber), noise)
    return noise


def optimize_pose_graph(initial: Sequence[Sim3], edges: Sequence[GraphEdge],
                        options: PoseGraphOptions = PoseGraphOptions()) -> list[Sim3]:
    """Every chunk's Sim(3) G_k (chunk k's frame -> chunk 0's frame), optimised jointly.

    initial  K initial values (the chained sequential alignments), initial[0] ignored
    edges    `GraphEdge`s between chunks 0..K-1 (sequential and loop)
    A strong prior holds G_0 at the identity (the trajectory is in the first chunk's
    frame); each edge is a `BetweenFactorSimilarity3` (loop edges with a Huber noise
    model); solved by Levenberg-Marquardt. Returns K `Sim3`s, G_0 the identity."""
    gtsam = _gtsam()
    k = len(initial)
    if k < 1:
        raise InputError("the pose graph needs at least one chunk")
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    prior = gtsam.noiseModel.Isotropic.Sigma(7, 1e-9)
    graph.add(gtsam.PriorFactorSimilarity3(0, gtsam.Similarity3(), prior))
    for n, g in enumerate(initial):
        values.insert(n, gtsam.Similarity3() if n == 0 else to_gtsam(gtsam, g))
    for e in edges:
        if not (0 <= e.i < k and 0 <= e.j < k and e.i != e.j):
            raise InputError(f"a pose-graph edge joins chunks {e.i} and {e.j}; chunks are 0..{k - 1}, two different")
        if not (np.isfinite(e.spread) and e.spread > 0):
            raise InputError(f"the pose-graph edge {e.i}-{e.j} has spread {e.spread}; it must be positive")
        graph.add(gtsam.BetweenFactorSimilarity3(e.i, e.j, to_gtsam(gtsam, e.sim3), _edge_noise(gtsam, e, options)))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(options.max_iterations)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    out = [from_gtsam(result.atSimilarity3(n)) for n in range(k)]
    out[0] = Sim3.identity()
    return out

"""Sequences longer than one forward holds: chunks predicted one at a time, chained by
Sim(3) on their shared frames, loops closed by a pose graph over chunks. Model-agnostic:
nothing here imports the model (the predictor is a callable; `rvggt_jax.app` wires in
VGGT). `rvggt_jax.sequence.oracle` holds a synthetic predictor with exact ground truth."""

from rvggt_jax.sequence.align import AlignmentError, AlignOptions, align_chunks
from rvggt_jax.sequence.chunking import check_chunking, plan_chunks
from rvggt_jax.sequence.loops import LoopCandidate, LoopOptions, loop_candidates
from rvggt_jax.sequence.pose_graph import GraphEdge, PoseGraphOptions, optimize_pose_graph
from rvggt_jax.sequence.prediction import ChunkPrediction, LoopEdge, Trajectory
from rvggt_jax.sequence.sim3 import Sim3, Sim3Fit, sim3_align, sim3_align_report, umeyama
from rvggt_jax.sequence.store import ChunkStore, DepthPoints
from rvggt_jax.sequence.voxels import VoxelCloud

__all__ = ["AlignOptions", "AlignmentError", "ChunkPrediction", "ChunkStore", "DepthPoints", "GraphEdge", "LoopCandidate", "LoopEdge",
           "LoopOptions", "PoseGraphOptions", "Sim3", "Sim3Fit", "Trajectory", "align_chunks", "check_chunking",
           "loop_candidates", "optimize_pose_graph", "plan_chunks", "sim3_align", "sim3_align_report", "umeyama",
           "VoxelCloud"]

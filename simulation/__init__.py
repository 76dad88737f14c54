"""Procedural driving scenes written in the KITTI object layout (see docs/simulation.md).

``run(RunConfig(out=..., frames=..., seed=...))`` writes a dataset;
``generate_frame(seed, index)`` makes one frame in memory.
"""

from simulation.frame import Frame, generate_frame
from simulation.run import RunConfig, RunResult, run

__all__ = ["Frame", "RunConfig", "RunResult", "generate_frame", "run"]

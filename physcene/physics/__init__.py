"""The differentiable SDF physics engine (PADA, paper eq. 3): penetration, support, pose gradients.

``engine`` scores packed scenes with the Warp kernels of :mod:`physcene.kernels`; ``batch`` holds
the packed scenes and assets; ``reference`` is the float64 torch oracle. The engine knows poses,
assets and batches, never completion text (that is :mod:`physcene.reward.text_batch`).
"""

from physcene.physics.batch import SceneBatch, Score, axis_ray_distances, bucket_points, pack_assets
from physcene.physics.engine import PenetrationEnergy, PhysicsConfig, PhysicsEngine

__all__ = ["PenetrationEnergy", "PhysicsConfig", "PhysicsEngine", "SceneBatch", "Score", "axis_ray_distances",
           "bucket_points", "pack_assets"]

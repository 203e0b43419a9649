"""Python access to a WorldPack server: `Client` (typed calls over the REST
API) and, with the `gym` extra, `WorldPackEnv` (a Gymnasium environment)."""

from .client import Client, Imagined, Rollout, Step, WorldPackError, as_pose, c2w, opencv, opengl, pose5, pose_matrix

__all__ = ["Client", "Imagined", "Rollout", "Step", "WorldPackError", "as_pose", "c2w", "opencv", "opengl", "pose5", "pose_matrix"]

"""PyBullet simulation: the Panda pick-and-place scene, cameras and depth sensor models."""

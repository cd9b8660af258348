"""don_gym: a simulation benchmark for Dense Object Nets (DONs).

Data flows one way: object mesh -> optimal descriptors (``don_gym.descriptors``) ->
rendered targets -> dataset -> model -> wrappers -> agents, with the PyBullet
simulator (``don_gym.sim``) feeding images in.

Importing ``don_gym`` registers the Gymnasium environments ``DONToolcapPick-v0``,
``DONShaftPick-v0`` and ``DONPick-v0`` (``object=`` a built-in name or a mesh path), and the
bin-picking ``DONBinPick-v0``, ``DONToolcapBinPick-v0`` and ``DONShaftBinPick-v0`` (docs/bin.md).
"""

from __future__ import annotations

__version__ = "0.1.0"

from don_gym._registration import register_envs

register_envs()

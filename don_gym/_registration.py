"""Gymnasium registration of the don_gym environments (kept import-light)."""

from __future__ import annotations

import gymnasium as gym

ENTRY_POINT = "don_gym.sim.env:PickPlaceEnv"
ENV_IDS = {"DONToolcapPick-v0": "toolcap", "DONShaftPick-v0": "shaft", "DONPick-v0": None}


def register_envs() -> None:
    for env_id, object_name in ENV_IDS.items():
        if env_id in gym.registry:
            continue
        kwargs = {} if object_name is None else {"object": object_name}
        gym.register(id=env_id, entry_point=ENTRY_POINT, kwargs=kwargs)

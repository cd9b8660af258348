"""Gymnasium registration of the don_gym environments (kept import-light)."""

from __future__ import annotations

import gymnasium as gym

ENTRY_POINT = "don_gym.sim.env:PickPlaceEnv"
ENV_IDS = {"DONToolcapPick-v0": "toolcap", "DONShaftPick-v0": "shaft", "DONPick-v0": None}
#: The lift sub-task, goal-conditioned for HER (``don_gym.wrappers.goals.make_goal_env``, ``goal="lift"``):
#: a string entry point, so registering imports nothing downstream of the env.
GOAL_ENTRY_POINT = "don_gym.wrappers.goals:make_goal_env"
GOAL_ENV_IDS = {"DONToolcapLift-v0": "toolcap", "DONShaftLift-v0": "shaft", "DONLift-v0": None}
#: Bin picking (``don_gym.sim.bin_env.BinPickEnv``): the target part of each id; the default pile in all.
BIN_ENTRY_POINT = "don_gym.sim.bin_env:BinPickEnv"
BIN_ENV_IDS = {"DONBinPick-v0": "toolcap", "DONToolcapBinPick-v0": "toolcap", "DONShaftBinPick-v0": "shaft"}


def register_envs() -> None:
    for ids, entry_point, base in ((ENV_IDS, ENTRY_POINT, {}), (GOAL_ENV_IDS, GOAL_ENTRY_POINT, {"goal": "lift"})):
        for env_id, object_name in ids.items():
            if env_id in gym.registry:
                continue
            kwargs = base if object_name is None else {**base, "object": object_name}
            gym.register(id=env_id, entry_point=entry_point, kwargs=kwargs)
    for env_id, target in BIN_ENV_IDS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=BIN_ENTRY_POINT, kwargs={"target": target})

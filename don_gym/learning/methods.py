"""The training methods don_gym compares, by canonical name (no torch import, so any stage can use it).

Three supervised methods train with the l2 loss of Kupcsik et al. 2021 towards optimal descriptor
targets, ``self-supervised`` with the contrastive loss of Florence et al. 2018 (:data:`METHOD_DESCRIPTIONS`).
"""

from __future__ import annotations

from don_gym.errors import DonGymError

__all__ = [
    "METHODS",
    "METHOD_DESCRIPTIONS",
    "SUPERVISED_METHODS",
    "SUPERVISED_TARGET_VARIANT",
    "is_supervised",
    "validate_method",
]

METHODS: tuple[str, ...] = ("supervised", "supervised-edge", "supervised-mask", "self-supervised")
SUPERVISED_METHODS: tuple[str, ...] = ("supervised", "supervised-edge", "supervised-mask")

#: What each method trains with; "supervised-edge" and "supervised-mask" use the paper's view-dependent
#: variants (a) and (b) of the targets.
METHOD_DESCRIPTIONS: dict[str, str] = {
    "supervised": "l2 loss to optimal geometric descriptor images",
    "supervised-edge": "l2 loss, object edges blended towards the background descriptor",
    "supervised-mask": "l2 loss, two geometric dimensions plus an object-mask channel",
    "self-supervised": "pixelwise contrastive loss on depth correspondences (Florence et al. 2018)",
}

#: Target variant of ``don_gym.learning.torch_data.SupervisedFrames`` that each supervised method trains on.
SUPERVISED_TARGET_VARIANT: dict[str, str] = {
    "supervised": "geometric",
    "supervised-edge": "edge",
    "supervised-mask": "mask",
}


def validate_method(method: str) -> str:
    """Return ``method`` if it is a canonical method name, else raise :class:`DonGymError`."""
    if method not in METHODS:
        raise DonGymError(f"training method {method!r} is unknown; expected one of {', '.join(METHODS)}")
    return method


def is_supervised(method: str) -> bool:
    """True for the l2-loss methods, False for ``self-supervised``."""
    return validate_method(method) in SUPERVISED_METHODS

"""Gymnasium observation wrappers that add DON descriptors to don_gym observations.

Installed as ``don_gym.wrappers``.
"""

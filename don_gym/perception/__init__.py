"""Stage "perception": what a robot makes of descriptor images.

Modules: ``descriptor_sources`` (the oracle and a DON behind one interface, reference descriptors),
``keypoints`` (matching reference descriptors into keypoints), ``pose`` (6D pose from descriptor
correspondences). Imports only the stages before it.
"""

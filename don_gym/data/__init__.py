"""Stage "data": rendered descriptor targets and datasets.

Modules: ``render`` (descriptor target images, ray cast), ``dataset`` (the on-disk format, docs/dataset_format.md),
``build`` (building one-part datasets: locks, shards, resume), ``bin_dataset`` (datasets of piles of several parts),
``fusion`` (TSDF fusion of a scene's depth), ``correspondences`` (pixel correspondences between frames),
``export`` (the original DON's pdc layout and BOP), ``bop`` (the BOP format's files), ``import_bop`` (a BOP dataset
as a don_gym dataset). Imports only the stages before it: ``objects``, ``descriptors``, ``sim``.
"""

"""The atlas (paper Section VI.B): every agent's map, merged maps, covisibility and spanning tree.

``atlas`` (the front: :class:`~services.cloud.atlas.atlas.Atlas`), ``atlas_queries`` (its
reads), ``atlas_records`` (mutable records and their frozen views), ``atlas_graph``
(covisibility graph, spanning tree), ``map_types`` (plain inputs, views, snapshots, keys),
``retired`` (keyframes MBP removed, kept relative to kept ones). Imports no other room.
Nothing is re-exported here: import from the modules.
"""

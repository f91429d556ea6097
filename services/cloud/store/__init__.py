"""What the cloud keeps and hands out: its database, recordings, result files, live view.

``persistence`` / ``persistence_schema`` (SQLite state), ``recording`` (the applied uplink,
for replays), ``mission`` (a new team inside an earlier mission's map), ``output`` (TUM
trajectories, ATE report), ``frame_trajectories`` (every frame's trajectory),
``ground_truth`` (references for the dashboard's overlay), ``map_source`` (the dashboard's
``common.map_view.MapSource``). Imports only the ``atlas`` room. Nothing is re-exported here:
import from the modules.
"""

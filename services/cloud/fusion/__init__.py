"""Map fusion (paper Section VI.B): edge messages in, places recognised, maps merged.

``uplink`` (edge messages <-> domain inputs), ``rebase`` (a payload placed through its
anchor), ``robot_sensors`` (each robot's camera), ``place_recognition`` (BoW database, loop
candidates), ``verification`` (geometric check), ``merge`` (map merging, loops) and
``map_fusion`` (the front object over them and the optimisation room). Imports the
``atlas`` and ``optimization`` rooms. Nothing is re-exported here: import from the modules.
"""

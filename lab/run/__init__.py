"""Whole runs as processes: the cloud, the edges and the robots started and supervised on one
machine (:mod:`lab.run.orchestration`), their sites (:mod:`lab.run.sites`) and the run's
report (:mod:`lab.run.report`). ``recslam demo``, ``recslam experiment`` and the end-to-end
tests use them; services never import them."""

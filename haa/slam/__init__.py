"""JC-SLAM (thesis Chapter 5): particle filters with history blocks, lazy belief propagation, an occupancy grid.

A library with no network or agent code; the SLAM agents of the control system and the offline experiments
(`haactl bench slam | ap5.1 | ap5.2`) call it. Where each part of the thesis lives:

* `filter.py`     particle filter with history blocks (Fig. 5.2-1) and the five events of §5.2.3
* `motion.py`     prediction step, the velocity model of eq. 5.1-3
* `resample.py`   n_eff (eq. 5.1-1) and systematic resampling
* `grid.py`       probabilistic occupancy grid, Bayes update of eq. 5.1-2
* `sensors.py`    sonar / landmark / co-occupancy / camera-floor models: map updates and densities g(y|x)
* `system.py`     one team's filters, grid and landmark map
* `events.py`     the SLAM event log `slam/log` of a running team (predictions, readings, requests)
* `replica.py`    the SLAM state as a replica of that log, with exact checkpoints (docs/slam.md)
* `metrics.py`    map coverage (eq. 7.1-1), accuracy (eq. 7.1-2), exploration threshold
* `strategies.py` reading schedulers (Table 7.2-2, 7.2-4) on a simulated processing clock
* `recording.py`  MCAP + protobuf recordings of predictions and readings
* `explorer.py`   exploration driver that records runs from the haa.sim world
* `replay.py`     replays a recording through a strategy (experiment AP-5.1, AP-5.2)

See docs/slam.md for the design choices.
"""

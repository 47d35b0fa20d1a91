"""Learned measurement networks: DROID-SLAM's update operator (:mod:`.droid`), DPVO's (:mod:`.dpvo`),
the official checkpoints' loader (:mod:`.checkpoint`), the networks as the frontends' measurement
sources (:mod:`.sources`) with their runtime settings (:mod:`.config`), and the differentiable dense
BA layer of training (:mod:`.dba`). Pure torch (no compiled extensions); fgslam ships no weights and
downloads nothing (docs/architecture.md section 15).

Importing this package imports nothing; the networks are built on request."""

"""Learned measurement networks: DROID-SLAM's update operator (:mod:`.droid`), DPVO's (:mod:`.dpvo`),
the official checkpoints' loader (:mod:`.checkpoint`) and the runtime settings of the learned sources
(:mod:`.config`). Pure torch (no compiled extensions); fgslam ships no weights and downloads nothing.

Importing this package imports torch only; the networks are built on request."""

"""The foundations every layer uses and that know nothing of SLAM's parts: errors (:mod:`.errors`),
typed configs with ranges (:mod:`.config`), Lie groups and their gtsam conversion (:mod:`.lie`,
:mod:`.so3`), cameras (:mod:`.camera`), alignment (:mod:`.geometry`) and the map record
(:mod:`.mapdata`)."""

"""Names of the files in a run's output folder that several layers read or write (``fgslam run``:
:mod:`fgslam.run.outputs`; ``fgslam localize``: :mod:`fgslam.localize`; ``fgslam export --bag``:
:mod:`fgslam.export.bag`). Stable: tools and tests read them."""

TUM_FILE = "trajectory_tum.txt"  # posed frames, camera-to-world, TUM format
SUMMARY_FILE = "summary.json"  # the run's (or localisation's) summary
LOCALIZATION_FILE = "localization.csv"  # fgslam localize: every frame's status

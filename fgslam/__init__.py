"""fgslam: modular factor-graph visual SLAM on GTSAM.

Subpackages: ``factors`` (residuals and analytic Jacobians), ``frontends`` (dense, patch, pointmap),
``loop`` (retrieval and loop closure), ``io`` (datasets, trajectories, synthetic sequences).
Importing the package has no side effects and imports no heavy dependency.
"""

__version__ = "0.1.0"

"""One home for a SLAM run (``fgslam run``): its configuration, its checks, its system, its loop and its outputs;
and the runs built on it (a batch, the demo) or beside it (a g2o pose-graph optimisation).

Modules, highest first (each imports only those below it; ``pyproject.toml``, contract ``run``):

- :mod:`~fgslam.run.batch`, :mod:`~fgslam.run.demo`, :mod:`~fgslam.run.pgo`: ``fgslam batch`` (many
  runs, one table), ``fgslam demo`` (render a synthetic scene and run on it), ``fgslam pgo`` (optimise
  a g2o pose graph);
- :mod:`~fgslam.run.runner`: :func:`~fgslam.run.runner.run_slam` (and
  :func:`~fgslam.run.runner.run_prepared`): builds the system, steps it over the dataset, then has
  the results collected, the outputs written and the stored map saved;
- :mod:`~fgslam.run.session`: :class:`~fgslam.run.session.Slam`, the per-frame path of every run, which
  a script drives frame by frame (``fgslam.Slam``) and the runner steps over a dataset;
- :mod:`~fgslam.run.mapstore`: ``--save-map`` / ``--map``: saving a stored map and merging a
  recording into one, a step of its own;
- :mod:`~fgslam.run.outputs`: the writers (trajectories, PLY, keyframe depths, ``map.npz``, plot,
  ``summary.json``), each on its own;
- :mod:`~fgslam.run.results`: what a run ended with (final trajectory, evaluation, end-of-run
  queries) and its summary;
- :mod:`~fgslam.run.prepare`: every check before any work, once (config, rerun target, output
  folder, the dataset against the config, the stored map's camera, the IMU stream);
- :mod:`~fgslam.run.system`: :class:`~fgslam.run.system.SlamSystem` (backend, frontend, services);
- :mod:`~fgslam.run.memory`: the peak-memory estimate (each family's parts come from its registry entry);
- :mod:`~fgslam.run.config`: :class:`~fgslam.run.config.SlamConfig`, the root configuration of a run;
- :mod:`~fgslam.run.presets`: the YAML presets shipped in ``fgslam/configs/``;
- :mod:`~fgslam.run.files`: the names of the files a run writes;
- :mod:`~fgslam.run.signals`: stopping on SIGINT / SIGTERM (:class:`~fgslam.run.signals.StopOnSignal`).

The package re-exports nothing: import a name from the module that defines it.
"""

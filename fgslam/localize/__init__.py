"""Localisation in a stored map (``fgslam run ... --save-map MAP`` writes one,
:mod:`fgslam.export.mapfile`), which never grows the map:

- :mod:`~fgslam.localize.localizer`: :class:`~fgslam.localize.localizer.MapLocalizer`, a frame at a
  time (tracking, relocalisation, the quality gate) and its config
  (:class:`~fgslam.localize.localizer.LocalizeConfig`, preset ``fgslam/configs/localize.yaml``);
- :mod:`~fgslam.localize.sequence`: ``fgslam localize MAP --data SEQ --out DIR`` over a whole sequence;
- :mod:`~fgslam.localize.merge`: a recording's keyframes localised in a map and merged into it
  (``fgslam run ... --map MAP``, :mod:`fgslam.run.mapstore`).

The package re-exports nothing: import a name from the module that defines it.
"""

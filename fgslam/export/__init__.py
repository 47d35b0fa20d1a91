"""Getting a run's results out: the saved map of a run (``map.npz``, :mod:`.map`), COLMAP models
(:mod:`.colmap`, through pycolmap), PLY point clouds (:mod:`.ply`) and rerun logs (:mod:`.rerun`)."""

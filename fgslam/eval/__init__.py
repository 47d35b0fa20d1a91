"""Trajectory evaluation (:mod:`.trajectory`): association, alignment (SE(3), Sim(3)) and ATE/RPE, tested
against the evo tool's figures; ``fgslam eval`` is its command."""

"""Studies on the host: simulated trajectories, Monte Carlo consistency studies, Allan
deviation, a recording through propagation, keyframe windows against ground truth, plots.
Imports the engine and :mod:`jaximu.io`.
"""

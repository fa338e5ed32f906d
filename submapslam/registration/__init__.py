"""The scan-matching toolbox that odometry, loop testing and localization share.

* :mod:`.point_to_line` — planar point-to-line Gauss-Newton, the recent-scan map of the 2D
  odometry refinement, line normals and first-point-per-cell thinning;
* :mod:`.wall_noise` — a 2D laser's scatter across its walls, measured from its scans (the
  line test's allowance for a noisy scanner);
* :mod:`.planar` — planar submap matching: FFT correlative search, ICP in SE(2), information;
* :mod:`.spatial` — prepared 3D clouds (normals, FPFH, structure points), their LRU, the
  structure agreement of two clouds and a deterministic feature RANSAC;
* :mod:`.correspondence` — the correspondence test between two submaps (planar or 3D): coarse
  alignment, fine registration, the fitness / RMSE / overlap gates, and its result type.

Nothing here knows about submap graphs, files or configs: inputs are point arrays and poses.
"""
